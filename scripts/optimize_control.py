"""Open-loop control by gradient: an activation sequence that bends a soft arm onto a target.

    python scripts/optimize_control.py [--steps 30] [--dt 0.0333] [--iterations 80] [--resolution 1]

A soft arm (0.6 × 0.1 × 0.1 m, E = 20 kPa, no gravity) is clamped at x = 0. Springs along its top
and its bottom edges are two actuators: an action of 1 shortens a group's rest lengths by 30 %,
curling the arm towards that side. The actions of every step (a `[steps, 2]` sequence, squashed
into [−1, 1] by tanh) are optimised by Adam so that the arm's tip ends at a target point above
the rest position, with gradients through every implicit step.

`check`: the tip ends within 1 cm of the target, from a start 8 cm away.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass

import torch
from torch import Tensor

import energysim as es

TARGET = (0.55, 0.13, 0.0)


def build_scene(resolution: int = 1, dt: float = 1 / 30) -> es.Scene:
    """The arm with its two actuated spring groups (0: top, 1: bottom)."""
    mesh = es.TetMesh.box(size=(0.6, 0.1, 0.1), cells=(6 * resolution, resolution, resolution))
    scene = es.Scene(mesh, density=1000.0, dt=dt, gravity=None, solver=es.NewtonCG(tol=1e-8))
    scene.add(es.NeoHookean(youngs_modulus=2e4, poissons_ratio=0.3))
    edges = mesh.edges()
    ends = mesh.vertices[edges]  # [s, 2, 3]
    along = (ends[:, 1, 0] - ends[:, 0, 0]).abs() > 1e-9
    top = along & (ends[:, :, 1] > 0.1 - 1e-9).all(dim=1)
    bottom = along & (ends[:, :, 1] < 1e-9).all(dim=1)
    muscles = top | bottom
    scene.add(es.ActuatedSprings(edges[muscles], actuators=bottom[muscles].long(), stiffness=2000.0))
    scene.fix(torch.nonzero(mesh.vertices[:, 0] < 1e-9).reshape(-1))
    return scene


def tip(scene: es.Scene, state: Tensor) -> Tensor:
    """Mean position of the free end's vertices, shape `[3]`, in m."""
    x, _ = scene.split_state(state)
    end = scene.rest_positions[:, 0] > scene.rest_positions[:, 0].max() - 1e-9
    return x[0, end].mean(dim=0)


@dataclass(frozen=True)
class Result:
    actions: Tensor
    distances: list[float]
    seconds: float


def run(scene: es.Scene, steps: int = 30, iterations: int = 80, lr: float = 0.1) -> Result:
    """Adam on the unconstrained action sequence (the actions are its tanh)."""
    target = torch.tensor(TARGET, dtype=torch.float64)
    raw = torch.zeros(steps, 2, dtype=torch.float64, requires_grad=True)
    optimizer = torch.optim.Adam([raw], lr=lr)
    distances = []
    start = time.perf_counter()
    for _ in range(iterations):
        optimizer.zero_grad()
        states = es.rollout(scene, scene.initial_state(), torch.tanh(raw))
        distance = (tip(scene, states[-1]) - target).norm()
        distances.append(float(distance.detach()))
        if distances[-1] < 2e-3:
            break
        (distance + 1e-3 * raw.square().mean()).backward()
        optimizer.step()
    return Result(torch.tanh(raw).detach(), distances, time.perf_counter() - start)


def check(result: Result) -> None:
    """The tip reaches the target within 1 cm and the distance shrank at least fivefold."""
    assert result.distances[-1] < 1e-2, f"tip ends {result.distances[-1] * 100:.1f} cm from the target"
    assert result.distances[-1] < result.distances[0] / 5, (
        f"distances {result.distances[0]:.3f} -> {result.distances[-1]:.3f} m"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--iterations", type=int, default=80)
    parser.add_argument("--resolution", type=int, default=1)
    parser.add_argument("--dt", type=float, default=1 / 30)
    args = parser.parse_args(argv)
    scene = build_scene(args.resolution, args.dt)
    result = run(scene, args.steps, args.iterations)
    print(
        f"tip distance {result.distances[0] * 100:.2f} cm -> {result.distances[-1] * 100:.2f} cm in "
        f"{len(result.distances)} rollouts of {args.steps} steps ({result.seconds:.1f} s)"
    )
    check(result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
