"""One creature model in both envs: the same body (τ, η, μ) whatever the integrator, and the
convergence study of the two discretisations runs, extrapolates exact sequences exactly and checks
itself."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

pytest.importorskip("gymnasium")

from energysim import envs  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def models_script():
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import bench_env_models
    finally:
        sys.path.remove(str(ROOT / "scripts"))
    return bench_env_models


def test_both_integrators_get_the_same_body_model() -> None:
    implicit = envs.CreatureSimulation(envs.CreatureEnvConfig())
    explicit = envs.CreatureSimulation(envs.CreatureEnvConfig(integrator="leapfrog"))
    for simulation in (implicit, explicit):
        assert simulation.config.time_constant == 0.05
        viscosity = [t for t in simulation.scene.terms if type(t).__name__ == "Viscosity"]
        assert len(viscosity) == 1 and float(viscosity[0].viscosity) == 30.0
    # the bare body is still reachable: no viscosity term, instant activations
    bare = envs.CreatureSimulation(envs.CreatureEnvConfig(activation_time_constant=0.0, viscosity=0.0))
    assert bare.config.time_constant == 0.0
    assert not [t for t in bare.scene.terms if type(t).__name__ == "Viscosity"]


def test_extrapolation_recovers_the_limit_of_exact_power_laws() -> None:
    study = models_script()
    for order in (1.0, 2.0):
        # d(h) = L + C h^p at h = 1, 1/2, 1/4, 1/8
        sequence = [0.12 + 0.03 * (0.5**k) ** order for k in range(4)]
        limit = study.extrapolate(sequence)
        assert limit.order == pytest.approx(order, rel=1e-9)
        assert limit.distance == pytest.approx(0.12, abs=1e-12)
        assert limit.finest_error == pytest.approx(0.03 * 0.125**order, rel=1e-9)


def test_quick_study_walks_both_envs_to_their_tolerances(tmp_path: Path) -> None:
    study = models_script().main(["--quick", "--out", str(tmp_path)])
    assert [r.integrator for r in study.implicit] == ["implicit_euler"] * 2
    assert [r.substeps for r in study.explicit] == [32, 64]
    for r in study.implicit:
        assert 0 < r.max_residual <= 1e-6
    # 0.1 s of gait: the worm has barely moved, but both envs move it the same way to within the
    # discretisation error of a 0.1 s run (the two envs' default runs differ by 0.5 %)
    assert study.gap_default < 0.1
    assert "gap at the default settings" in (tmp_path / "bench_env_models.md").read_text()
