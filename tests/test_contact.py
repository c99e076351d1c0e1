"""Contact and friction checked against analytic numbers: drops that never penetrate and rest with
the contact force equal to the weight, stick/slip on a slope at μ = tan θ, the stopping distance
v₀²/(2μg), a ball rolling off a sphere, energy that never grows, and gradients through contact."""

from __future__ import annotations

import math
import warnings

import pytest
import torch

import energysim as es
from energysim.contact import barrier, barrier_derivatives, mollified_slip
from energysim.contact.friction import LaggedFriction
from energysim.contact.obstacles import CCD_SAFETY
from energysim.objective.derivatives import autograd_element_hessian, energy_and_gradient

G = 9.81


def cube(size: float = 0.2, cells: int = 2, lift: float = 0.0) -> tuple[es.TetMesh, torch.Tensor]:
    mesh = es.TetMesh.box(size=(size, size, size), cells=(cells, cells, cells))
    return mesh, mesh.vertices + torch.tensor([0.0, lift, 0.0])


def contact_scene(mesh, dt=1 / 60, friction=0.5, youngs_modulus=1e6, gravity=(0.0, -G, 0.0), solver=None):
    scene = es.Scene(mesh, density=1000.0, dt=dt, gravity=gravity, solver=solver or es.NewtonCG(tol=1e-6))
    scene.add(es.NeoHookean(youngs_modulus, 0.3))
    ground = scene.add(es.Ground(0.0, friction=friction))
    return scene, ground


def total_mass(scene) -> float:
    return float(scene.vertex_mass.sum())


def centroid(scene, state) -> torch.Tensor:
    x, _ = scene.split_state(state)
    m = scene.vertex_mass[:, None]
    return (x[0] * m).sum(0) / m.sum()


def centroid_velocity(scene, state) -> torch.Tensor:
    _, v = scene.split_state(state)
    m = scene.vertex_mass[:, None]
    return (v[0] * m).sum(0) / m.sum()


# --- the pieces against autograd and closed forms ------------------------------------------


def test_barrier_derivatives_match_autograd_and_vanish_beyond_the_barrier_distance():
    dhat = 1e-3
    d = torch.tensor([1e-7, 1e-5, 3e-4, 9.99e-4, 1e-3, 2e-3], dtype=torch.float64, requires_grad=True)
    (first_auto,) = torch.autograd.grad(barrier(d, dhat).sum(), d, create_graph=True)
    (second_auto,) = torch.autograd.grad(first_auto.sum(), d)
    first, second = barrier_derivatives(d.detach(), dhat)
    torch.testing.assert_close(first, first_auto.detach(), rtol=1e-10, atol=1e-18)
    torch.testing.assert_close(second, second_auto, rtol=1e-10, atol=1e-12)
    assert float(barrier(d.detach(), dhat)[-2:].abs().max()) == 0.0
    assert bool((first[:-2] < 0).all()) and bool((second[:-2] > 0).all())
    assert math.isinf(float(barrier(torch.tensor([0.0, -1e-3]), dhat)[0]))


@pytest.mark.parametrize(
    "obstacle",
    [
        es.Ground(0.0, normal=(0.3, 1.0, -0.2)),
        es.SphereObstacle((0.1, -0.5, 0.05), 0.5),
        es.BoxObstacle((-1.0, -1.0, -1.0), (1.0, 0.0, 1.0)),
        es.BoxObstacle((0.0, -0.3, 0.0), (0.05, 0.0, 0.05)),  # edges and corners too
    ],
    ids=["plane", "sphere", "box-face", "box-edges"],
)
def test_obstacle_hessian_blocks_and_forces_match_autograd(obstacle):
    mesh, x = cube(0.2, 2)
    scene = es.Scene(mesh, gravity=None)
    scene.add(obstacle)
    obstacle.barrier_distance = 0.3  # every vertex inside the barrier's range
    x = (x + torch.tensor([0.0, 0.1, 0.0]) + 0.02 * torch.rand_like(x))[None]
    assert float(obstacle.signed_distance(x).min()) > 0
    exact = obstacle.element_hessian(x[:, obstacle.element_vertices], None)
    reference = autograd_element_hessian(obstacle, x, None)
    torch.testing.assert_close(exact, reference, rtol=1e-9, atol=1e-9 * float(reference.abs().max()))
    _, gradient = energy_and_gradient(lambda y: obstacle(y), x)
    torch.testing.assert_close(obstacle.contact_force(x), -gradient, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("slip", [0.0, 3e-6, 9e-6, 4e-5])
def test_friction_hessian_matches_autograd_at_rest_in_the_ramp_and_sliding(slip):
    smoothing = 1e-5
    previous = torch.zeros(1, 1, 3, dtype=torch.float64)
    normals = torch.tensor([[[0.0, 1.0, 0.0]]], dtype=torch.float64)
    term = LaggedFriction(
        torch.tensor([[0]]),
        previous,
        normals,
        torch.tensor([[2.0]], dtype=torch.float64),
        torch.tensor(0.4, dtype=torch.float64),
        smoothing,
    )
    x = torch.tensor([[[slip * 0.6, 1e-4, slip * 0.8]]], dtype=torch.float64)
    exact = term.element_hessian(x[:, term.element_vertices], None)
    reference = autograd_element_hessian(term, x, None)
    torch.testing.assert_close(exact, reference, rtol=1e-9, atol=1e-6)
    assert bool((torch.linalg.eigvalsh(exact) > -1e-9).all())  # convex
    # the friction force never exceeds μλ and is μλ once sliding beyond ε
    _, gradient = energy_and_gradient(lambda y: term(y), x)
    force = float(gradient.norm())
    assert force <= 0.4 * 2.0 * (1 + 1e-12)
    if slip > smoothing:
        assert force == pytest.approx(0.8, rel=1e-12)


def test_mollifier_is_continuous_at_the_smoothing_length():
    eps = 1e-3
    u = torch.tensor([[eps * (1 - 1e-9), 0.0], [eps * (1 + 1e-9), 0.0]], dtype=torch.float64)
    values = mollified_slip(u, eps)
    assert float(values[1] - values[0]) == pytest.approx(0.0, abs=1e-11)


@pytest.mark.parametrize(
    "obstacle",
    [
        es.Ground(0.0, normal=(0.2, 1.0, 0.1)),
        es.SphereObstacle((0.0, -0.6, 0.0), 0.5),
        es.BoxObstacle((-0.3, -0.4, -0.3), (0.3, -0.1, 0.3)),
    ],
    ids=["plane", "sphere", "box"],
)
def test_time_of_impact_is_the_first_contact_along_the_segment(obstacle):
    generator = torch.Generator().manual_seed(1)
    corner = torch.tensor([0.2, -0.1, 0.2], dtype=torch.float64)
    points = torch.rand(400, 3, generator=generator, dtype=torch.float64) * 0.4 - corner
    motion = torch.randn(400, 3, generator=generator, dtype=torch.float64) * 0.5
    assert float(obstacle.signed_distance(points).min()) > 0
    impact = obstacle.time_of_impact(points, motion)
    samples = torch.linspace(0, 1, 2001, dtype=torch.float64)
    along = obstacle.signed_distance(points[:, None] + samples[None, :, None] * motion[:, None])
    first_inside = torch.where(
        (along <= 0).any(dim=1), samples[(along <= 0).to(torch.int8).argmax(dim=1)], torch.tensor(math.inf)
    )
    hits = torch.isfinite(first_inside)
    assert int(hits.sum()) > 20  # the sample exercises hits and misses
    # no contact before the computed time; contact within one sample after it
    assert bool(((impact > 1) | torch.isfinite(impact))[hits].all())
    assert bool((impact[hits] <= first_inside[hits] + 1e-12).all())
    assert bool((impact[hits] >= first_inside[hits] - 1 / 2000 - 1e-12).all())
    touching = obstacle.signed_distance(points[hits] + impact[hits, None] * motion[hits])
    assert float(touching.abs().max()) < 1e-9
    misses = ~hits & torch.isfinite(impact)
    assert bool((impact[misses] > 1).all())


# --- drops ----------------------------------------------------------------------------------


@pytest.mark.parametrize("dt", [1 / 60, 1 / 24], ids=["h=1/60", "h=1/24"])
@pytest.mark.parametrize("speed", [0.0, 20.0], ids=["from-1m", "20m/s"])
def test_a_dropped_box_never_penetrates_and_rests_on_its_weight(dt, speed):
    mesh, x0 = cube(0.2, 2, lift=1.0)
    scene, ground = contact_scene(mesh, dt=dt)
    state = scene.initial_state(x0, torch.tensor([0.0, -speed, 0.0]).expand_as(x0))
    lowest = math.inf
    for _ in range(round(2.0 / dt)):
        result = es.step(scene, state)
        assert result.stats.converged, result.stats.summary()
        state = result.state
        assert torch.isfinite(state).all()
        lowest = min(lowest, float(scene.split_state(state)[0][..., 1].min()))
    assert lowest > 0.0
    x, v = scene.split_state(state)
    assert float(v.abs().max()) < 1e-3  # at rest
    force = ground.contact_force(x)[0].sum(0)
    assert float(force[1]) == pytest.approx(total_mass(scene) * G, rel=1e-2)
    assert float(force[[0, 2]].abs().max()) < 1e-3 * total_mass(scene) * G


@pytest.mark.parametrize(
    "solver", [es.LBFGS(tol=1e-4, max_iter=3000), es.Adam(tol=1e-3, lr=1e-3)], ids=["lbfgs", "adam"]
)
def test_first_order_solvers_respect_the_obstacle_at_20_m_per_s(solver):
    mesh, x0 = cube(0.2, 1, lift=0.3)
    scene, _ = contact_scene(mesh, dt=1 / 60, solver=solver)
    state = scene.initial_state(x0, torch.tensor([0.0, -20.0, 0.0]).expand_as(x0))
    # against the stiff barrier these may stop short of the tolerance (and warn so); what they must
    # never do is cross the obstacle
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", es.ConvergenceWarning)
        for _ in range(6):
            state = es.step(scene, state).state
            assert float(scene.split_state(state)[0][..., 1].min()) > 0.0
    assert float(centroid_velocity(scene, state)[1]) > -20.0  # the ground stopped it


def test_energy_never_increases_in_a_drop_with_friction():
    mesh, x0 = cube(0.2, 2, lift=0.3)
    scene, ground = contact_scene(mesh, dt=1 / 60, youngs_modulus=1e5, friction=0.5)
    elastic = scene.terms[1]
    # a sideways push makes friction work too
    state = scene.initial_state(x0, torch.tensor([1.0, 0.0, 0.5]).expand_as(x0))
    mass = scene.vertex_mass[:, None]

    def energy(state):
        x, v = scene.split_state(state)
        kinetic = 0.5 * float((mass * v[0] ** 2).sum())
        potential = float((mass[:, 0] * G * x[0, :, 1]).sum())
        return kinetic + potential + float(elastic(x)) + float(ground(x))

    values = [energy(state)]
    for _ in range(90):
        state = es.step(scene, state, solver=es.NewtonCG(tol=1e-9)).state
        values.append(energy(state))
    increases = torch.tensor(values).diff()
    assert float(increases.max()) <= 1e-9 * abs(values[0]) + 1e-9
    assert values[-1] < values[0] - 0.5  # and it did dissipate: the fall and the slide


# --- friction against Coulomb's law ---------------------------------------------------------


def settled_on_ground(dt, friction, cells=2, steps=40):
    """A cube resting on the ground (its equilibrium gap), with velocity zero."""
    mesh, x0 = cube(0.2, cells)
    scene, ground = contact_scene(mesh, dt=dt, friction=friction)
    x0 = x0 + torch.tensor([0.0, 0.5 * ground.barrier_distance, 0.0])
    state = scene.initial_state(x0)
    for _ in range(steps):
        state = es.step(scene, state).state
    x, _ = scene.split_state(state)
    return mesh, scene.initial_state(x[0])


def on_slope(mesh, angle, friction, dt):
    # a slope of angle θ: the ground stays y = 0 and gravity tilts by θ (down the slope is +x)
    gravity = (G * math.sin(angle), -G * math.cos(angle), 0.0)
    return contact_scene(mesh, dt=dt, friction=friction, gravity=gravity)


def test_static_friction_holds_a_block_on_a_slope_with_mu_above_tan_theta():
    angle = math.radians(20.0)  # tan θ = 0.364
    mesh, state = settled_on_ground(1 / 60, friction=0.6)
    scene, _ = on_slope(mesh, angle, friction=0.6, dt=1 / 60)
    start = centroid(scene, state)
    for _ in range(60):
        state = es.step(scene, state).state
    assert abs(float(centroid(scene, state)[0] - start[0])) < 1e-3


def test_kinetic_friction_slides_a_block_down_a_slope_at_g_sin_minus_mu_cos():
    angle = math.radians(30.0)  # tan θ = 0.577
    friction = 0.3
    dt = 1 / 60
    mesh, state = settled_on_ground(dt, friction=friction)
    scene, _ = on_slope(mesh, angle, friction=friction, dt=dt)
    speeds = []
    for _ in range(60):
        state = es.step(scene, state).state
        speeds.append(float(centroid_velocity(scene, state)[0]))
    # fit over the second half second, after the block has broken away
    times = torch.arange(30, 60, dtype=torch.float64) * dt
    late = torch.tensor(speeds[30:], dtype=torch.float64)[:, None]
    slope = torch.linalg.lstsq(torch.stack([times, torch.ones_like(times)], 1), late).solution[0, 0]
    expected = G * (math.sin(angle) - friction * math.cos(angle))
    assert float(slope) == pytest.approx(expected, rel=0.03)


def test_a_sliding_block_stops_after_v0_squared_over_2_mu_g():
    friction, speed, dt = 0.3, 3.0, 1 / 120
    mesh, state = settled_on_ground(dt, friction=friction, steps=60)
    scene, _ = contact_scene(mesh, dt=dt, friction=friction)
    x, _ = scene.split_state(state)
    state = scene.initial_state(x[0], torch.tensor([speed, 0.0, 0.0]).expand_as(x[0]))
    start = centroid(scene, state)
    for _ in range(round(1.5 / dt)):
        state = es.step(scene, state).state
    travelled = float(centroid(scene, state)[0] - start[0])
    assert float(centroid_velocity(scene, state).norm()) < 1e-2
    assert travelled == pytest.approx(speed**2 / (2 * friction * G), rel=0.03)


def test_a_step_starts_with_the_vertices_in_contact_held_where_they_were():
    # friction's warm start: a prediction that moved them would start them sliding, in the regime
    # where Newton overshoots; the vertices off the ground keep the prediction. The slides above
    # (v0²/2μg, g sin θ − μ g cos θ) are solved from this start.
    mesh, state = settled_on_ground(1 / 60, friction=0.5)
    scene, ground = contact_scene(mesh, friction=0.5)
    x, _ = scene.split_state(state)
    (friction,) = ground.lagged_terms(x, scene.dt)
    candidate = x + torch.tensor([0.01, 0.002, 0.0], dtype=x.dtype)
    held = friction.warm_start(x, candidate)
    touching = friction.weight[0] > 0
    assert int(touching.sum()) == 9  # the bottom face's 3 × 3 vertices
    assert torch.equal(held[0, touching], x[0, touching])
    assert torch.equal(held[0, ~touching], candidate[0, ~touching])


def test_a_body_resting_on_the_ground_takes_one_newton_iteration_a_step():
    # the unmoved inertial prediction competes with the held one: from x_n + h v_n a resting body's
    # step converges in one iteration; when only held candidates and x_n competed it took two
    mesh, state = settled_on_ground(1 / 60, friction=0.5)
    scene, _ = contact_scene(mesh, friction=0.5)
    start = centroid(scene, state)
    iterations = []
    for _ in range(20):
        result = es.step(scene, state)
        state, iterations = result.state, [*iterations, result.stats.iterations]
    assert iterations[1:] == [1] * 19
    assert float((centroid(scene, state) - start).norm()) < 1e-6  # and it stays at rest
    assert float(centroid_velocity(scene, state).norm()) < 1e-5


def test_a_ball_dropped_on_a_sphere_rolls_off_without_touching_it():
    occupancy = torch.zeros(4, 4, 4, dtype=torch.bool)
    centre = torch.arange(4) - 1.5
    occupancy = (centre[:, None, None] ** 2 + centre[None, :, None] ** 2 + centre[None, None, :] ** 2) <= 4.0
    mesh = es.TetMesh.from_voxels(occupancy.numpy(), voxel_size=0.025)
    radius = 0.5
    sphere = es.SphereObstacle((0.0, 0.0, 0.0), radius, friction=0.2)
    scene = es.Scene(mesh, density=500.0, dt=1 / 60, solver=es.NewtonCG(tol=1e-6))
    scene.add(es.NeoHookean(1e5, 0.3))
    scene.add(sphere)
    x0 = mesh.vertices - mesh.vertices.mean(0) + torch.tensor([0.2, radius + 0.1, 0.0])
    state = scene.initial_state(x0)
    closest = math.inf
    for _ in range(60):
        state = es.step(scene, state).state
        x, _ = scene.split_state(state)
        closest = min(closest, float(sphere.signed_distance(x).min()))
    assert closest > 0.0
    c = centroid(scene, state)
    # it went over the side: beside the sphere and below its top
    assert float(c[0]) > radius and float(c[1]) < radius


# --- errors ----------------------------------------------------------------------------------


def test_a_state_inside_an_obstacle_is_refused_with_the_vertices_named():
    mesh, x0 = cube(0.2, 1, lift=-0.05)
    scene, _ = contact_scene(mesh)
    with pytest.raises(ValueError, match="not admissible: vertices"):
        es.step(scene, scene.initial_state(x0))


def test_the_unchecked_step_limit_is_nan_exactly_where_the_start_is_inside():
    # what compiled code calls: no branch on data, so an inadmissible entry shows as NaN
    mesh, x0 = cube(0.2, 1, lift=0.01)
    ground = es.Ground()
    scene = es.Scene(mesh, dt=1 / 60)
    scene.add(ground)
    x = torch.stack([x0, x0 - torch.tensor([0.0, 0.02, 0.0], dtype=x0.dtype)])
    dx = torch.zeros_like(x)
    dx[..., 1] = -0.04
    limit = ground.step_limit(x, dx)
    assert limit[0] == pytest.approx(CCD_SAFETY * float(x[0, :, 1].min()) / 0.04, rel=1e-12)  # 0.2
    assert torch.isnan(limit[1])
    with pytest.raises(ValueError, match="not admissible"):
        ground.max_step(x, dx)


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: es.Ground(friction=-0.1), "friction"),
        (lambda: es.Ground(normal=(0.0, 0.0, 0.0)), "normal"),
        (lambda: es.SphereObstacle((0, 0, 0), 0.0), "radius"),
        (lambda: es.BoxObstacle((0, 0, 0), (1, -1, 1)), "upper > lower"),
        (lambda: es.Ground(barrier_distance=0.0), "barrier_distance"),
        (lambda: es.Ground(friction_smoothing=-1.0), "friction_smoothing"),
    ],
)
def test_bad_obstacle_parameters_are_refused(make, message):
    with pytest.raises(ValueError, match=message):
        make()


def test_an_obstacle_of_the_wrong_dimension_is_refused():
    scene = es.Scene(es.TriMesh.box(size=(1.0, 1.0), cells=(2, 2)), gravity=(0.0, -G))
    with pytest.raises(ValueError, match="3D but the mesh is 2D"):
        scene.add(es.Ground())


def test_a_scene_without_obstacles_has_no_contact_terms_in_its_step():
    mesh, _ = cube(0.2, 1)
    scene = es.Scene(mesh)
    scene.add(es.NeoHookean(1e5, 0.3))
    x = scene.rest_positions[None]
    extra = [t for term in scene.terms for t in term.lagged_terms(x, scene.dt)]
    assert extra == []
    assert all(term.max_step(x, x) is None for term in scene.terms)


# --- gradients through contact ----------------------------------------------------------------


def test_sliding_distance_gradients_match_finite_differences():
    dt = 1 / 60
    mesh, rest = settled_on_ground(dt, friction=0.4, cells=1, steps=30)
    x_rest = es.Scene(mesh).split_state(rest)[0][0]

    def distance(friction, speed):
        scene, _ = contact_scene(mesh, dt=dt, friction=friction, solver=es.NewtonCG(tol=1e-10))
        velocity = torch.zeros_like(x_rest)
        velocity = velocity + torch.stack([speed, speed * 0, speed * 0])
        state = torch.cat([x_rest.reshape(-1), velocity.reshape(-1)])
        for _ in range(12):
            state = es.timestep(scene, state)
        return centroid(scene, state)[0]

    friction = torch.tensor(0.4, dtype=torch.float64, requires_grad=True)
    speed = torch.tensor(1.0, dtype=torch.float64, requires_grad=True)
    value = distance(friction, speed)
    value.backward()
    step = 1e-5
    with torch.no_grad():
        fd_friction = (distance(friction + step, speed) - distance(friction - step, speed)) / (2 * step)
        fd_speed = (distance(friction, speed + step) - distance(friction, speed - step)) / (2 * step)
    # the block is still sliding after 12 steps: friction shortens the slide, speed lengthens it
    assert float(fd_friction) < 0 < float(fd_speed)
    assert float(friction.grad) == pytest.approx(float(fd_friction), rel=1e-4)
    assert float(speed.grad) == pytest.approx(float(fd_speed), rel=1e-4)


def test_resting_height_gradient_after_a_push_into_the_ground_matches_finite_differences():
    dt = 1 / 60
    mesh, rest = settled_on_ground(dt, friction=0.4, cells=1, steps=30)
    x_rest = es.Scene(mesh).split_state(rest)[0][0]

    def height(speed):
        scene, _ = contact_scene(mesh, dt=dt, friction=0.4, solver=es.NewtonCG(tol=1e-10))
        velocity = torch.zeros_like(x_rest) + torch.stack([speed * 0, -speed, speed * 0])
        state = torch.cat([x_rest.reshape(-1), velocity.reshape(-1)])
        for _ in range(5):
            state = es.timestep(scene, state)
        return scene.split_state(state)[0][0, :, 1].min()

    speed = torch.tensor(0.05, dtype=torch.float64, requires_grad=True)
    height(speed).backward()
    step = 1e-6
    with torch.no_grad():
        fd = (height(speed + step) - height(speed - step)) / (2 * step)
    assert float(speed.grad) == pytest.approx(float(fd), rel=1e-4)
