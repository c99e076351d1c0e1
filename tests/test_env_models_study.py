"""The contact study of `scripts/bench_env_models.py`: its explicit sequence refines the activation's
sampling with the substeps, and its options replace the implicit ground's ε_v and d̂ (at an unchanged
κ·d̂, the body placed again at d̂/2) in the refined implicit runs only."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

pytest.importorskip("gymnasium")

from energysim.creatures import scene_ground  # noqa: E402
from energysim.envs import CreatureEnv  # noqa: E402
from energysim.envs.config import FRICTION_SMOOTHING  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def study_script():  # noqa: ANN201
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import bench_env_models
    finally:
        sys.path.remove(str(ROOT / "scripts"))
    return bench_env_models


def test_set_contact_keeps_the_barrier_force_scale_and_rests_the_body_at_half_the_new_distance(
    study_script,  # noqa: ANN001
) -> None:
    env = CreatureEnv("worm", reset_noise_scale=0.0)
    ground = scene_ground(env.simulation.scene)
    old_distance, old_stiffness = ground.barrier_distance, float(ground.barrier_stiffness)
    study_script.set_contact(env, friction_smoothing=1e-2, barrier_distance=1e-4)
    assert ground.friction_smoothing == 1e-2
    assert ground.barrier_distance == 1e-4
    assert float(ground.barrier_stiffness) * 1e-4 == pytest.approx(old_stiffness * old_distance, rel=1e-12)
    # the ground is y = 0 and the reset starts from the rest state: its lowest vertex at d̂/2
    env.reset(seed=0)
    n = env.simulation.scene.num_vertices
    lowest = float(env.simulation.rest_state.reshape(-1)[: 3 * n].reshape(n, 3)[:, 1].min())
    assert lowest == pytest.approx(0.5e-4, rel=1e-6)


@pytest.mark.parametrize("name", ["friction_smoothing", "barrier_distance"])
@pytest.mark.parametrize("value", [0.0, -1e-3, float("nan"), float("inf")])
def test_set_contact_refuses_a_setting_that_is_not_positive_and_finite(
    study_script, name: str, value: float  # noqa: ANN001
) -> None:
    env = CreatureEnv("worm", reset_noise_scale=0.0)
    with pytest.raises(ValueError, match=name):
        study_script.set_contact(env, **{"friction_smoothing": None, "barrier_distance": None, name: value})


def test_set_contact_refuses_the_leapfrog_ground(study_script) -> None:  # noqa: ANN001
    env = CreatureEnv("worm", reset_noise_scale=0.0, integrator="leapfrog")
    with pytest.raises(ValueError, match="leapfrog"):
        study_script.set_contact(env, friction_smoothing=1e-2, barrier_distance=None)


def test_quick_study_refines_the_explicit_activation_and_sets_only_the_refined_implicit_ground(
    study_script, tmp_path: Path  # noqa: ANN001
) -> None:
    argv = ["--quick", "--friction-smoothing", "1e-2", "--barrier-distance", "2e-4", "--out", str(tmp_path)]
    study = study_script.main(argv)
    # the explicit physics step halves with the substeps per env step: 32 of them per step
    assert [r.frame_skip for r in study.explicit] == [1, 2]
    assert [r.dt for r in study.explicit] == pytest.approx([1 / 60, 1 / 120], rel=1e-12)
    assert [r.substeps for r in study.explicit] == [32, 64]
    for r in study.implicit:
        assert (r.friction_smoothing, r.barrier_distance) == (1e-2, 2e-4)
    # the default run keeps the env's ground: its ε_v, d̂ = 1e-3 of the body's size (not 2e-4)
    assert study.implicit_default.friction_smoothing == FRICTION_SMOOTHING
    assert study.implicit_default.barrier_distance != pytest.approx(2e-4, rel=0.1)
    # 0.1 s of gait: both envs move the worm the same way to within their discretisation error
    assert study.gap_default < 0.1
    text = (tmp_path / "bench_env_models.md").read_text()
    assert "ε_v (m/s)" in text and "2.00e-04" in text
