"""Bad input gets a clear error, and a solve that does not converge says so with its figures."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import small_box

import energysim as es


def scene_3d(**kwargs) -> es.Scene:
    scene = es.Scene(small_box(3), **kwargs)
    scene.add(es.NeoHookean(1e5, 0.3))
    return scene


@pytest.mark.parametrize("poissons_ratio", [0.5, 0.6, -1.0, math.nan])
def test_poissons_ratio_outside_the_open_interval_is_refused(poissons_ratio):
    with pytest.raises(ValueError, match="poissons_ratio"):
        es.NeoHookean(1e5, poissons_ratio)


def test_per_element_poissons_ratio_names_the_offending_element():
    ratios = torch.full((10,), 0.3, dtype=torch.float64)
    ratios[7] = 0.5
    with pytest.raises(ValueError, match=r"\[7\]"):
        es.NeoHookean(1e5, ratios)


@pytest.mark.parametrize("youngs_modulus", [0.0, -1e5, math.inf])
def test_nonpositive_youngs_modulus_is_refused(youngs_modulus):
    with pytest.raises(ValueError, match="youngs_modulus"):
        es.NeoHookean(youngs_modulus, 0.3)


def test_per_element_parameters_must_match_the_mesh():
    scene = es.Scene(small_box(3))
    with pytest.raises(ValueError, match="one per element"):
        scene.add(es.NeoHookean(torch.ones(3, dtype=torch.float64) * 1e5, 0.3))


@pytest.mark.parametrize("dt", [0.0, -0.01, math.nan, math.inf])
def test_nonpositive_time_step_is_refused(dt):
    with pytest.raises(ValueError, match="dt"):
        es.Scene(small_box(3), dt=dt)


@pytest.mark.parametrize("density", [0.0, -1.0, math.nan])
def test_nonpositive_density_is_refused(density):
    with pytest.raises(ValueError, match="density"):
        es.Scene(small_box(3), density=density)


def test_gravity_of_the_wrong_dimension_is_refused():
    with pytest.raises(ValueError, match="gravity"):
        es.Scene(small_box(2), gravity=(0.0, -9.81, 0.0))


def test_wrong_state_shapes_are_refused_with_the_expected_shape():
    scene = scene_3d()
    good = scene.initial_state()
    for bad in (good[:-1], good.reshape(2, -1), good[None, None], torch.zeros(0, dtype=torch.float64)):
        with pytest.raises(ValueError, match=str(2 * scene.num_dofs)):
            es.timestep(scene, bad)
    with pytest.raises(TypeError, match="floating"):
        es.timestep(scene, torch.zeros(2 * scene.num_dofs, dtype=torch.int64))
    with pytest.raises(TypeError, match="Tensor"):
        es.timestep(scene, good.tolist())


def test_non_finite_state_is_refused():
    scene = scene_3d()
    state = scene.initial_state()
    state[5] = math.nan
    with pytest.raises(ValueError, match="non-finite"):
        es.timestep(scene, state)


def test_wrong_action_shape_is_refused():
    scene = scene_3d()
    states = scene.initial_state(batch_size=2)
    with pytest.raises(ValueError, match="action"):
        es.timestep(scene, states, action=torch.zeros(3, 1))


def test_pinning_vertices_outside_the_mesh_is_refused():
    scene = scene_3d()
    with pytest.raises(ValueError, match=r"\[99\]"):
        scene.fix([0, 99])


def test_springs_naming_missing_vertices_are_refused():
    scene = scene_3d()
    with pytest.raises(ValueError, match=r"springs \[1\]"):
        scene.add(es.Springs(edges=[[0, 1], [2, 500]], stiffness=1.0))


def test_solver_settings_are_checked():
    with pytest.raises(ValueError, match="tol"):
        es.NewtonCG(tol=0.0)
    with pytest.raises(ValueError, match="max_iter"):
        es.LBFGS(max_iter=0)
    with pytest.raises(ValueError, match="hessian"):
        es.NewtonCG(hessian="exact")


def test_a_solve_that_does_not_converge_warns_with_its_figures():
    scene = scene_3d(solver=es.NewtonCG(tol=1e-12, max_iter=1))
    state = scene.initial_state(velocities=torch.randn(scene.num_vertices, 3, dtype=torch.float64))
    with pytest.warns(
        es.ConvergenceWarning, match=r"NOT converged in 1 iterations, velocity residual .* m/s"
    ):
        result = es.step(scene, state)
    assert not result.stats.converged
    assert result.stats.residual > 1e-12
    assert torch.isfinite(result.state).all()


def test_strict_solvers_raise_instead():
    for solver in (
        es.NewtonCG(tol=1e-12, max_iter=1, strict=True),
        es.LBFGS(tol=1e-12, max_iter=1, strict=True),
        es.Adam(tol=1e-12, max_iter=1, strict=True),
    ):
        scene = scene_3d(solver=solver)
        state = scene.initial_state(velocities=torch.randn(scene.num_vertices, 3, dtype=torch.float64))
        with pytest.raises(es.ConvergenceError, match="velocity residual"):
            es.step(scene, state)


def test_missing_mesh_file_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="nowhere.msh"):
        es.TetMesh.load(tmp_path / "nowhere.msh")
