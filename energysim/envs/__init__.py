"""Gymnasium environments for the shipped soft creatures (needs the optional `rl` extra: gymnasium).

Importing this package registers one id per creature in `energysim.creatures.CREATURES`, e.g.
``energysim/Worm-v0``, with an `entry_point` for the single `CreatureEnv` and a `vector_entry_point`
for the batched `CreatureVectorEnv`:

    import gymnasium, energysim.envs
    env = gymnasium.make("energysim/Worm-v0")
    envs = gymnasium.make_vec("energysim/Worm-v0", num_envs=16, vectorization_mode="vector_entry_point")

`SB3VecEnv` shows the batched env to stable-baselines3 (``PPO("MlpPolicy", SB3VecEnv(envs))``); it is
imported on first use, so stable-baselines3 is needed only then.

``import energysim`` alone never imports gymnasium. See docs/envs.md.

Modules: `config` (`CreatureEnvConfig`), `actions` (what an action may be), `core`
(`CreatureSimulation`, the batched reset and step without Gymnasium), `transition` (what a step
yields and its reward), `observation` (what a controller sees), `rendering` (a numpy side view),
`creature_env` and `vector_env` (the Gymnasium wrappers).
"""

from __future__ import annotations

try:
    import gymnasium
except ImportError as error:  # pragma: no cover - depends on the installation
    raise ImportError(
        "energysim.envs needs gymnasium; install the rl extra: pip install 'torch-energysim[rl]'"
    ) from error

from energysim.creatures import CREATURES
from energysim.envs.config import CreatureEnvConfig
from energysim.envs.core import CreatureSimulation
from energysim.envs.creature_env import CreatureEnv
from energysim.envs.observation import ObservationLayout
from energysim.envs.transition import Transition
from energysim.envs.vector_env import CreatureVectorEnv

# 300 env steps of the default h = 1/60 s: 5 s, several gait periods of every creature
MAX_EPISODE_STEPS = 300


def env_id(creature: str) -> str:
    """The registered id of `creature`'s environment, e.g. "energysim/Worm-v0" for "worm"."""
    return f"energysim/{creature[:1].upper()}{creature[1:]}-v0"


ENV_IDS = {creature: env_id(creature) for creature in CREATURES}


def register_envs() -> None:
    """Register every creature's id with Gymnasium (ids already registered are left as they are)."""
    for creature, name in ENV_IDS.items():
        if name in gymnasium.registry:
            continue
        gymnasium.register(
            id=name,
            entry_point="energysim.envs.creature_env:CreatureEnv",
            vector_entry_point="energysim.envs.vector_env:CreatureVectorEnv",
            max_episode_steps=MAX_EPISODE_STEPS,
            kwargs={"creature": creature},
        )


register_envs()


def __getattr__(name: str) -> object:
    # stable-baselines3 is imported only when its adapter is asked for
    if name == "SB3VecEnv":
        from energysim.envs.sb3 import SB3VecEnv

        return SB3VecEnv
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "ENV_IDS",
    "MAX_EPISODE_STEPS",
    "CreatureEnv",
    "CreatureEnvConfig",
    "CreatureSimulation",
    "CreatureVectorEnv",
    "ObservationLayout",
    "SB3VecEnv",
    "Transition",
    "env_id",
    "register_envs",
]
