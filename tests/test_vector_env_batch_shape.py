"""Every physics step of a `CreatureVectorEnv` has the batch's full shape, so a compiled step is
compiled once: entries that are being reset, and the search for a failing entry, keep the shape."""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("gymnasium")

import energysim as es  # noqa: E402
import energysim.envs.core as env_core  # noqa: E402
from energysim.envs import CreatureVectorEnv  # noqa: E402
from energysim.solvers import ConvergenceError  # noqa: E402

BATCH = 4


def _recording_step(monkeypatch: pytest.MonkeyPatch, failing_row: torch.Tensor | None = None) -> list[int]:
    """Patch the env's physics step to record each call's batch size; a batch holding `failing_row`
    raises, as a blown-up solve does."""
    real_step = env_core.step
    sizes: list[int] = []

    def step(scene: es.Scene, state: torch.Tensor, action: torch.Tensor) -> es.StepResult:
        sizes.append(state.shape[0])
        if failing_row is not None and (state == failing_row).all(dim=1).any():
            raise ConvergenceError("driven to fail")
        return real_step(scene, state, action)

    monkeypatch.setattr(env_core, "step", step)
    return sizes


def test_entries_out_of_phase_are_stepped_as_the_full_batch(monkeypatch: pytest.MonkeyPatch) -> None:
    # entry 0 restarts one step after the others, so later steps reset some entries while they step
    # the rest: each must still be one physics step of all BATCH entries
    env = CreatureVectorEnv(BATCH, "worm", integrator="leapfrog", max_episode_steps=2)
    env.reset(seed=0)
    actions = np.random.default_rng(1).uniform(-1, 1, (6, *env.action_space.shape))
    env.step(actions[0])
    env.reset(options={"reset_mask": np.array([True, False, False, False])})
    sizes = _recording_step(monkeypatch)
    partial_steps = 0
    for k in range(1, 6):
        resetting = env._autoreset.copy()
        partial_steps += bool(resetting.any() and not resetting.all())
        states, activations = env.states.clone(), env.activations.clone()
        _, rewards, _, _, _ = env.step(actions[k])
        assert sizes == [BATCH]
        # the stepped entries advanced exactly as a step of those entries alone (entries never mix)
        stepped = np.flatnonzero(~resetting)
        alone = env.simulation.step(
            states[stepped], torch.from_numpy(actions[k][stepped]), activations[stepped]
        )
        sizes.clear()
        assert torch.allclose(env.states[stepped], alone.state, rtol=0, atol=1e-12)
        np.testing.assert_allclose(rewards[stepped], alone.reward.numpy(), rtol=0, atol=1e-12)
        assert (rewards[resetting] == 0).all()
    assert partial_steps >= 2


def test_a_failing_entry_is_found_by_solves_of_the_full_batch(monkeypatch: pytest.MonkeyPatch) -> None:
    env = CreatureVectorEnv(BATCH, "worm", integrator="leapfrog")
    env.reset(seed=0)
    action = np.random.default_rng(2).uniform(-1, 1, env.action_space.shape)
    start = env.states.clone()
    clean = env.simulation.step(start, torch.from_numpy(action), env.activations)
    sizes = _recording_step(monkeypatch, failing_row=start[2])
    _, rewards, terminated, _, info = env.step(action)
    assert terminated.tolist() == [False, False, True, False]
    assert info["numerical_failure"].tolist() == [False, False, True, False]
    assert torch.equal(env.states[2], start[2])
    ok = [0, 1, 3]
    assert torch.allclose(env.states[ok], clean.state[ok], rtol=0, atol=1e-12)
    np.testing.assert_allclose(rewards[ok], clean.reward.numpy()[ok], rtol=0, atol=1e-12)
    # the first solve, then bisection over 4 entries: 2 halves, then 2 singles of the failing half
    assert sizes == [BATCH] * 5
