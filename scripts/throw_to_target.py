"""Throw a soft ball so that it lands on a target: Nimble's trajectory-optimisation tutorial, soft.

    python scripts/throw_to_target.py [--steps 100] [--dt 0.01] [--iterations 40] [--resolution 4]
                                      [--serve [PORT]] [--host HOST]

A ball of neo-Hookean rubber (voxelised sphere, E = 50 kPa) is thrown from the origin. The initial
velocity (one vector for the whole ball) is optimised by plain gradient descent on the squared
distance so that after `steps` implicit-Euler steps the ball's centre of mass is at the target,
2 m away and 0.5 m up. Gradients flow through every step by the implicit function theorem:
`loss.backward()` reaches `initial_velocity`. The centre of mass moves by T·v₀ in the flight time
T = steps·h, so the loss has curvature T² in v₀; the step size 0.5/T² halves the distance each
iteration (the elastic wobble of the ball does not move its centre of mass).

With `--serve` (port 8080 unless given) the optimisation is shown live in the browser at
http://127.0.0.1:PORT: every iteration's flight replaces the one the page loops over (colouring by
speed on request), with the target as a red sphere; the server keeps running after the optimisation
until Ctrl+C.

`check`: the final distance is below 1 mm, and the optimised velocity agrees with the exact
discrete ballistic answer (internal forces do not move the centre of mass, so implicit Euler gives
c_N = c_0 + N h v_0 + h² g N(N+1)/2 exactly).
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from dataclasses import dataclass

import torch
from torch import Tensor

import energysim as es
from energysim.viewer import Viewer

TARGET = (2.0, 0.5, 0.0)
BALL_RADIUS = 0.1  # m


def build_scene(resolution: int = 4, dt: float = 0.01) -> es.Scene:
    """A ball of radius 0.1 m made of `resolution`³ voxels (those inside the sphere)."""
    centres = (torch.arange(resolution, dtype=torch.float64) + 0.5) / resolution * 2 - 1
    grid = torch.stack(torch.meshgrid(centres, centres, centres, indexing="ij"), dim=-1)
    occupancy = grid.norm(dim=-1) <= 1.0 + 1e-9
    mesh = es.TetMesh.from_voxels(occupancy.numpy(), voxel_size=0.2 / resolution, origin=(-0.1, -0.1, -0.1))
    scene = es.Scene(mesh, density=1100.0, dt=dt, gravity=(0.0, -9.81, 0.0), solver=es.NewtonCG(tol=1e-8))
    scene.add(es.NeoHookean(youngs_modulus=5e4, poissons_ratio=0.4))
    return scene


def centre_of_mass(scene: es.Scene, state: Tensor) -> Tensor:
    """Mass-weighted mean position, shape `[3]`, in m."""
    x, _ = scene.split_state(state)
    return (scene.vertex_mass[:, None] * x[0]).sum(0) / scene.vertex_mass.sum()


def simulate(
    scene: es.Scene, initial_velocity: Tensor, steps: int, frames: list[Tensor] | None = None
) -> Tensor:
    """The final state after throwing the ball at `initial_velocity` (shape `[3]`, m/s).

    `frames`, if given, receives every state of the flight (detached), the initial one first.
    """
    velocities = initial_velocity.expand(scene.num_vertices, 3)
    state = torch.cat([scene.rest_positions.reshape(-1), velocities.reshape(-1)])
    if frames is not None:
        frames.append(state.detach())
    for _ in range(steps):
        state = es.timestep(scene, state)
        if frames is not None:
            frames.append(state.detach())
    return state


@dataclass(frozen=True)
class Result:
    initial_velocity: Tensor
    distances: list[float]
    steps: int
    dt: float
    seconds: float


def run(
    scene: es.Scene, steps: int = 100, iterations: int = 40, goal: float = 1e-4, viewer: Viewer | None = None
) -> Result:
    """Gradient descent on the initial velocity until the centre of mass is within `goal` m of the target.

    With a `viewer`, each iteration's flight replaces the trajectory it shows (with the ball's speed
    as a colouring to pick).
    """
    target = torch.tensor(TARGET, dtype=torch.float64)
    velocity = torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64, requires_grad=True)
    flight_time = steps * scene.dt
    optimizer = torch.optim.SGD([velocity], lr=0.5 / flight_time**2)
    distances = []
    start = time.perf_counter()
    for _ in range(iterations):
        optimizer.zero_grad()
        frames = None if viewer is None else []
        offset = centre_of_mass(scene, simulate(scene, velocity, steps, frames)) - target
        if viewer is not None:
            # the flight is rigid (uniform start velocity, uniform gravity, no contact), so colour by speed
            _, flight_velocities = scene.split_state(torch.stack(frames))
            viewer.loop_states(frames, vertex_scalars={"speed (m/s)": flight_velocities.norm(dim=-1)})
        distances.append(float(offset.detach().norm()))
        if distances[-1] < goal:
            break
        (0.5 * offset.square().sum()).backward()
        optimizer.step()
    return Result(velocity.detach(), distances, steps, scene.dt, time.perf_counter() - start)


def check(result: Result) -> None:
    """The ball lands within 1 mm of the target, with the discrete ballistic velocity."""
    assert result.distances[-1] < 1e-3, f"final distance {result.distances[-1]:.2e} m"
    n, h = result.steps, result.dt
    gravity = torch.tensor([0.0, -9.81, 0.0], dtype=torch.float64)
    exact = (torch.tensor(TARGET, dtype=torch.float64) - h**2 * gravity * n * (n + 1) / 2) / (n * h)
    error = float((result.initial_velocity - exact).norm())
    assert error < 2e-3, f"velocity {result.initial_velocity.tolist()} vs ballistic {exact.tolist()}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--dt", type=float, default=0.01)
    parser.add_argument("--iterations", type=int, default=40)
    parser.add_argument("--resolution", type=int, default=4, help="voxels across the ball")
    parser.add_argument(
        "--serve",
        type=int,
        nargs="?",
        const=8080,
        default=None,
        metavar="PORT",
        help="show the optimisation live at http://127.0.0.1:PORT (default 8080; 0 picks a free port)",
    )
    parser.add_argument("--host", default="127.0.0.1", help="address the viewer binds (with --serve)")
    args = parser.parse_args(argv)
    scene = build_scene(args.resolution, args.dt)
    viewer = None
    if args.serve is not None:
        viewer = Viewer(scene, ground_height=-BALL_RADIUS)  # thrown from the ground
        viewer.add_sphere("target", TARGET, 0.03, "red")
        print(f"viewer: open {viewer.serve(args.serve, args.host)}", flush=True)
    try:
        result = run(scene, args.steps, args.iterations, viewer=viewer)
        report(scene, args, result)
        if viewer is not None:
            print("viewer: showing the last trajectory; Ctrl+C to stop", flush=True)
            wait_for_interrupt()
    finally:
        if viewer is not None:
            viewer.stop()
    return 0


def wait_for_interrupt() -> None:
    """Block until Ctrl+C (the viewer's server thread keeps serving meanwhile)."""
    try:
        threading.Event().wait()
    except KeyboardInterrupt:
        pass


def report(scene: es.Scene, args: argparse.Namespace, result: Result) -> None:
    """Print the run's figures and raise AssertionError if it fails `check`."""
    print(
        f"{scene.mesh.num_elements} tets, {args.steps} steps: distance {result.distances[0]:.3f} m -> "
        f"{result.distances[-1]:.2e} m in {len(result.distances)} evaluations ({result.seconds:.1f} s); "
        f"initial velocity {[round(v, 4) for v in result.initial_velocity.tolist()]} m/s"
    )
    check(result)


if __name__ == "__main__":
    sys.exit(main())
