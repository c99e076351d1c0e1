"""`NewtonCG(reuse_factorization=ρ)`: band factorisations kept across iterations and steps (a chord
method) reach the same minimisers as fresh ones, are renewed where they serve poorly, and are
counted: fewer Hessians than iterations where H changes slowly."""

from __future__ import annotations

import pytest
import torch

import energysim as es
from energysim.objective.objective import Objective

TOL = 1e-8  # m/s: tight, so that both solvers land on the same minimiser to ~h·tol


def _beam(youngs_modulus: float = 1e5) -> es.Scene:
    # a clamped beam long enough for the band path (its Hessian is banded in the level order)
    mesh = es.TetMesh.box(size=(1.0, 0.2, 0.2), cells=(10, 2, 2))
    scene = es.Scene(mesh, density=1000.0, dt=1 / 48, gravity=(0.0, -9.81, 0.0))
    scene.add(es.NeoHookean(youngs_modulus=youngs_modulus, poissons_ratio=0.3))
    scene.fix(torch.nonzero(mesh.vertices[:, 0] < 1e-9).reshape(-1))
    scene.integrator = "tr_bdf2"
    return scene


def _count_hessians(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    calls = [0]
    band_hessian = Objective.band_hessian

    def counted(self: Objective, *args: object, **options: object) -> object:
        calls[0] += 1
        return band_hessian(self, *args, **options)

    monkeypatch.setattr(Objective, "band_hessian", counted)
    return calls


def _assert_same_state(scene: es.Scene, state: torch.Tensor, expected: torch.Tensor) -> None:
    x, v = scene.split_state(state)
    x_expected, v_expected = scene.split_state(expected)
    # measured: 2e-11 m and 3e-9 m/s (a velocity is a position difference over h/3)
    assert torch.allclose(x, x_expected, rtol=0, atol=1e-10)  # m
    assert torch.allclose(v, v_expected, rtol=0, atol=2e-8)  # m/s


def _swing(scene: es.Scene, solver: es.NewtonCG, steps: int, state: torch.Tensor) -> tuple[torch.Tensor, int]:
    iterations = 0
    for _ in range(steps):
        result = es.step(scene, state, solver=solver)
        assert result.stats.converged
        state, iterations = result.state, iterations + result.stats.iterations
    return state, iterations


def test_kept_factorisations_reach_the_fresh_minimisers_with_fewer_hessians(monkeypatch):
    scene = _beam()
    start = scene.initial_state(batch_size=2)
    start[1, scene.num_dofs :] = 0.3  # the second entry moves: the batch's rows differ
    fresh, fresh_iterations = _swing(scene, es.NewtonCG(tol=TOL, compile=True), 6, start)
    calls = _count_hessians(monkeypatch)
    kept, kept_iterations = _swing(
        scene, es.NewtonCG(tol=TOL, compile=True, reuse_factorization=0.5), 6, start
    )
    # both minimise each stage to 1e-8 m/s: the states agree to far below h·tol·steps
    _assert_same_state(scene, kept, fresh)
    # a chord iteration converges linearly, so there are more of them, but far fewer Hessians
    assert kept_iterations >= fresh_iterations
    assert calls[0] < fresh_iterations / 2


def test_a_factorisation_of_another_material_is_renewed_and_the_solve_still_converges(monkeypatch):
    solver = es.NewtonCG(tol=TOL, compile=True, reuse_factorization=0.5)
    soft, stiff = _beam(1e5), _beam(1e7)  # the same mesh, hence the same band layout
    state, _ = _swing(soft, solver, 2, soft.initial_state())
    calls = _count_hessians(monkeypatch)
    # the soft beam's factors are 100× too compliant for the stiff one: they must be replaced
    kept, _ = _swing(stiff, solver, 2, state)
    assert calls[0] >= 1
    fresh, _ = _swing(stiff, es.NewtonCG(tol=TOL, compile=True), 2, state)
    _assert_same_state(stiff, kept, fresh)


@pytest.mark.parametrize("fraction", [0.0, 1.0, -0.5, 2.0])
def test_reuse_factorization_must_be_a_fraction(fraction):
    with pytest.raises(ValueError, match="reuse_factorization"):
        es.NewtonCG(reuse_factorization=fraction)
