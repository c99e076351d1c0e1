"""Solves whose verdict does not depend on the CPU's rounding, and solver settings checked where given.

The static solve of a scrambled 3×3×3 box (E = 1e5 Pa) ends where its energy, a sum of terms of
size μV that cancel to 0 at rest, is ~4e-13 J with a rounding noise of ~4e-12 J, while the last
Newton step predicts a decrease of ~1e-14 J: the energy cannot judge that step, its derivatives
can. Another CPU rounds E differently; the tests emulate that by adding to E a deterministic
function of x that varies at random between positions a few ulps apart, with an amplitude up to
25 times the measured noise, and ask for the same verdict.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import pytest
import torch
from conftest import rigid_alignment_error

import energysim as es
from energysim.objective.objective import Objective
from energysim.solvers.line_search import line_step

pytestmark = pytest.mark.usefixtures("one_thread")

# The velocity residual this solve reaches when asked for less than it can: 1.3e-14 to 5e-14 m/s,
# the size of the change of the residual itself between positions a few ulps apart (up to 1.4e-13
# m/s). Below it the steps are the rounding's.
RESIDUAL_FLOOR = 1.4e-13  # m/s
TOL = 1e-8  # m/s, 7e4 times that floor


PRIME = 1_000_003


def rounding_like(x: torch.Tensor, amplitude: float, seed: int) -> torch.Tensor:
    """A stand-in for another CPU's rounding of E, `[B]`, within ±amplitude/2 J: deterministic in
    `x` `[B, n, 3]`, and a new value, uncorrelated with the last, where any coordinate changes by an
    ulp (a hash of the significands' bits)."""
    significand, _ = torch.frexp(x)
    bits = (significand * 2.0**53).to(torch.int64) % PRIME
    keys = torch.randint(1, PRIME, x.shape[1:], generator=torch.Generator().manual_seed(seed))
    hashed = ((bits * keys) % PRIME).sum(dim=(-1, -2)) % PRIME
    return amplitude * (hashed.to(x.dtype) / PRIME - 0.5)


@dataclass
class OtherRounding(Objective):
    """The objective with E rounded as another CPU might (`rounding_like`); ∇E unchanged."""

    amplitude: float = 0.0
    seed: int = 0

    def energy(self, x: torch.Tensor) -> torch.Tensor:
        return super().energy(x) + rounding_like(x, self.amplitude, self.seed)

    def energy_and_gradient(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        energy, gradient = super().energy_and_gradient(x)
        return energy + rounding_like(x, self.amplitude, self.seed), gradient


def scrambled_box() -> tuple[es.Scene, torch.Tensor]:
    mesh = es.TetMesh.box(size=(1, 1, 1), cells=(3, 3, 3))
    scene = es.Scene(mesh, gravity=None)
    scene.add(es.NeoHookean(1e5, 0.3))
    return scene, torch.rand_like(mesh.vertices)[None]


def objective_of(scene: es.Scene, x0: torch.Tensor, amplitude: float = 0.0, seed: int = 0) -> Objective:
    return OtherRounding(
        terms=list(scene.terms),
        free=scene.free,
        residual_scale=scene.dt / scene.vertex_mass,
        anchor=x0,
        amplitude=amplitude,
        seed=seed,
    )


@pytest.mark.parametrize(("amplitude", "seed"), [(0.0, 0), (1e-11, 8), (1e-10, 6), (1e-9, 0)])
def test_the_scrambled_box_returns_to_rest_whatever_the_rounding_of_its_energy(amplitude, seed):
    # Each of these roundings made the line search refuse the Newton steps near the minimum (the
    # energy rose by its noise) and accept what tiny steps the noise favoured, 300 iterations long:
    # (1e-11, 8) at 2.776e-8 m/s, as on the CPU where the static solve of test_hard_cases failed
    scene, x0 = scrambled_box()
    result = es.NewtonCG(tol=TOL, max_iter=300, strict=True).minimize(
        objective_of(scene, x0, amplitude, seed), x0
    )
    assert result.residual < TOL and result.iterations < 60, result.summary()
    assert rigid_alignment_error(result.x[0], scene.rest_positions) < 1e-9


def test_the_newton_step_the_energy_cannot_judge_is_taken_whole():
    # one Newton step from 1e-11 m off the rest shape (3 vertices fixed, so H is definite): its
    # predicted decrease is ~3e-16 J, E's noise ~1e-11 J, yet the step is exact to second order,
    # and the residual after it falls by orders of magnitude
    mesh = es.TetMesh.box(size=(1, 1, 1), cells=(2, 2, 2))
    scene = es.Scene(mesh, gravity=None)
    scene.add(es.NeoHookean(1e5, 0.3))
    scene.fix([0, 1, 2])
    rest = scene.rest_positions[None]
    x = rest + 1e-11 * torch.randn_like(rest) * scene.free[:, None]
    objective = objective_of(scene, rest, amplitude=1e-11)
    energy, gradient = objective.energy_and_gradient(x)
    free = scene.free.repeat_interleave(3)
    hessian = torch.autograd.functional.hessian(
        lambda flat: sum(term(flat.reshape(1, -1, 3), None) for term in scene.terms).sum(), x.reshape(-1)
    )[free][:, free]
    direction = torch.zeros_like(x).reshape(-1)
    direction[free] = torch.linalg.solve(hessian, -gradient.reshape(-1)[free])
    direction = direction.reshape(x.shape)
    predicted = -0.5 * float((gradient * direction).sum())
    assert 0 < predicted < 1e-14
    search = line_step(objective, x, energy, gradient, direction)
    assert float(search.step) == 1.0
    assert float(search.residual) < 1e-3 * float(objective.residual(gradient))


@pytest.mark.parametrize("solver", [es.NewtonCG(tol=1e-16, max_iter=300), es.LBFGS(tol=1e-16, max_iter=3000)])
def test_a_tolerance_below_the_rounding_floor_stops_early_at_the_best_iterate_and_says_why(solver):
    scene, x0 = scrambled_box()
    with pytest.warns(es.ConvergenceWarning, match="rounding"):
        result = solver.minimize(objective_of(scene, x0), x0)
    assert not result.converged and result.stalled
    # far short of max_iter (both spun to it), at the floor: Newton–CG's, or L-BFGS's, whose
    # curvature pairs from gradient differences lose their digits first (it stopped at 1.3e-14 m/s
    # after 246 iterations on the machine this was written on)
    assert result.iterations < solver.max_iter // 5, result.summary()
    floor = RESIDUAL_FLOOR if isinstance(solver, es.NewtonCG) else 1e-9
    assert result.residual < floor, result.summary()
    assert rigid_alignment_error(result.x[0], scene.rest_positions) < 1e-9


def test_strict_mode_raises_at_the_floor_with_the_reason():
    scene, x0 = scrambled_box()
    with pytest.raises(es.ConvergenceError, match="floor"):
        es.NewtonCG(tol=1e-16, max_iter=300, strict=True).minimize(objective_of(scene, x0), x0)


@pytest.mark.parametrize(
    ("make", "argument", "value", "error"),
    [
        (es.NewtonCG, "max_iter", 2.5, TypeError),
        (es.NewtonCG, "tol", "1e-5", TypeError),
        (es.NewtonCG, "tol", True, TypeError),
        (es.NewtonCG, "max_iter", True, TypeError),
        (es.NewtonCG, "tol", float("nan"), ValueError),
        (es.NewtonCG, "tol", float("inf"), ValueError),
        (es.NewtonCG, "tol", -1e-6, ValueError),
        (es.NewtonCG, "max_iter", 0, ValueError),
        (es.NewtonCG, "strict", 1, TypeError),
        (es.NewtonCG, "compile", "yes", TypeError),
        (es.NewtonCG, "max_cg_iter", 10.0, TypeError),
        (es.NewtonCG, "max_cg_iter", 0, ValueError),
        (es.NewtonCG, "forcing", "0.1", TypeError),
        (es.NewtonCG, "forcing", float("nan"), ValueError),
        (es.NewtonCG, "hessian", None, TypeError),
        (es.NewtonCG, "preconditioner", "jacobi", ValueError),
        (es.NewtonCG, "direct_max_dofs", 100.5, TypeError),
        (es.NewtonCG, "project_hessian", 0, TypeError),
        (es.NewtonCG, "compact_below", float("nan"), ValueError),
        (es.NewtonCG, "reuse_factorization", "0.5", TypeError),
        (es.LBFGS, "tol", "1e-5", TypeError),
        (es.LBFGS, "max_iter", 1e3, TypeError),
        (es.LBFGS, "history_size", 2.0, TypeError),
        (es.LBFGS, "history_size", 0, ValueError),
        (es.Adam, "tol", 0.0, ValueError),
        (es.Adam, "max_iter", 100.0, TypeError),
        (es.Adam, "lr", "1e-3", TypeError),
        (es.Adam, "lr", 0.0, ValueError),
        (es.Adam, "lr", float("inf"), ValueError),
        (es.Adam, "patience", 1.5, TypeError),
        (es.Adam, "patience", -1, ValueError),
    ],
)
def test_a_wrong_solver_setting_is_refused_where_it_is_given_naming_it_and_the_value(
    make, argument, value, error
):
    with pytest.raises(error, match=rf"{make.__name__}: {argument}\b.*got {repr(value)[:4]}") as raised:
        make(**{argument: value})
    assert repr(value) in str(raised.value) or str(value) in str(raised.value)


def test_valid_settings_of_every_kind_are_accepted():
    import numpy as np

    solver = es.NewtonCG(tol=np.float64(1e-6), max_iter=np.int64(10), direct_max_dofs=None, forcing=0.1)
    assert solver.tol == 1e-6 and solver.max_iter == 10
    assert es.LBFGS(tol=1, history_size=5).tol == 1
    assert es.Adam(lr=1e-2, patience=0).patience == 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        es.NewtonCG(reuse_factorization=0.5, compact_below=0.0)
