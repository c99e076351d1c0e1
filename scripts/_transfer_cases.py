"""Which envs `policy_transfer.py` evaluates a policy on: the policy and its run's settings as its
checkpoint records them, and the discretisation of each evaluation env (the defaults the policy was
trained with, and the finer "converged" settings of each integrator)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from _training import check_integer

INTEGRATORS = ("implicit_euler", "leapfrog")


@dataclass(frozen=True)
class EnvSettings:
    """The discretisation of one evaluation env; the env step is `frame_skip`·`dt` either way.

    Attributes:
        integrator: "implicit_euler" or "leapfrog".
        label: "default" or "converged".
        dt: physics step h in s.
        frame_skip: physics steps per env step.
        solver_tol: Newton–CG velocity-residual tolerance in m/s (implicit only).
        substeps: leapfrog substeps per physics step; None: the env's stable count at rest.
        solver_budget: at most this many Newton iterations per physics step, the last iterate kept
            (`CreatureEnvConfig.solver_budget`); None: every step solved to `solver_tol`. Implicit only.
    """

    integrator: str
    label: str
    dt: float = 1 / 60
    frame_skip: int = 1
    solver_tol: float = 1e-4
    substeps: int | None = None
    solver_budget: int | None = None


# the converged settings of each env (module docstring)
CONVERGED = {
    "implicit_euler": EnvSettings("implicit_euler", "converged", dt=1 / 240, frame_skip=4, solver_tol=1e-6),
    "leapfrog": EnvSettings("leapfrog", "converged", substeps=128),
}


@dataclass(frozen=True)
class Policy:
    """A PPO policy trained by `train_ppo.py` and the settings of its run.

    Attributes:
        model: the SB3 PPO model.
        settings: the run's settings as its checkpoint records them (`checkpoint_settings`).
        path: the model file.
    """

    model: Any
    settings: dict[str, Any]
    path: Path

    @property
    def integrator(self) -> str:
        return str(self.settings["integrator"])


def load_policy(path: Path) -> Policy:
    """The policy and run settings of a ``model.zip`` written by `train_ppo.py`.

    Raises:
        FileNotFoundError: there is no file at `path`.
        ValueError: it is not a `train_ppo.py` checkpoint (a PPO model without the run's settings).
    """
    from stable_baselines3 import PPO
    from train_ppo import RUN_ATTRIBUTE

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"--model: no model file at {path} (train_ppo.py writes OUT/model.zip)")
    try:
        model = PPO.load(path, device="cpu")
    except Exception as error:  # SB3 raises whatever its zip and pickle readers raise
        raise ValueError(f"--model: {path} is not a stable-baselines3 PPO model file ({error})") from error
    run = getattr(model, RUN_ATTRIBUTE, None)
    if not isinstance(run, dict) or not isinstance(run.get("settings"), dict):
        raise ValueError(
            f"--model: {path} is a PPO model but not a checkpoint of train_ppo.py (no run settings)"
        )
    settings = run["settings"]
    if settings.get("integrator") not in INTEGRATORS:
        raise ValueError(
            f"--model: {path} was trained on integrator {settings.get('integrator')!r}; expected one "
            f"of {INTEGRATORS}"
        )
    return Policy(model, settings, path)


def default_settings(policy: Policy, integrator: str) -> EnvSettings:
    """The env of `integrator` at the defaults `policy` was trained with (module docstring): the run's
    solver tolerance and, for the implicit env, its Newton budget (None where the run had none)."""
    budget = policy.settings.get("solver_budget") if integrator == "implicit_euler" else None
    if budget is not None:
        budget = check_integer(budget, f"{policy.path}: solver_budget", 1)
    return EnvSettings(
        integrator, "default", solver_tol=float(policy.settings["solver_tol"]), solver_budget=budget
    )


def cases(policy: Policy, converged: bool, implicit_frame_skip: int | None = None) -> list[EnvSettings]:
    """The evaluation envs: own and other at the defaults, then (with `converged`) own and other at
    the converged settings; `implicit_frame_skip` k: the implicit env's converged step is 1/(60·k) s
    instead of 1/240 s (the env step stays 1/60 s)."""
    own = policy.integrator
    other = next(name for name in INTEGRATORS if name != own)
    envs = [default_settings(policy, own), default_settings(policy, other)]
    if converged:
        finer = dict(CONVERGED)
        if implicit_frame_skip is not None:
            finer["implicit_euler"] = replace(
                finer["implicit_euler"], dt=1 / (60 * implicit_frame_skip), frame_skip=implicit_frame_skip
            )
        envs += [finer[own], finer[other]]
    return envs
