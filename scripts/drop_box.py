"""A soft cube, released 1 m up with a small spin, falls freely for 1 s; the run checks itself.

    python scripts/drop_box.py [--seconds 1] [--dt 0.01667] [--solver newton-cg|lbfgs|adam] [--tol 1e-5]
                               [--resolution 6] [--out out/drop_box] [--frames-every 1] [--no-render]

A 0.3 m cube (E = 100 kPa, ν = 0.3, ρ = 1000 kg/m³), its bottom face at y = 1 m, spinning at 2 rad/s
about the horizontal z axis through its centre, falls under gravity. There is no ground yet.

What must hold (`check`):
- internal forces sum to zero, so the centre of mass follows implicit Euler's free-fall recurrence
  y_n = y_0 + n h v_y0 − g h² n(n+1)/2 exactly, up to the solver's velocity residual;
- nothing becomes NaN and no element inverts (J > 0);
- the cube stays nearly rigid: only the small centrifugal strain of the spin;
- internal forces exert no torque about the centre of mass, so the angular momentum can only lose what
  implicit Euler's numerical damping takes: it must not grow.

Writes ``frame_*.vtu`` + ``frame.pvd`` (velocity, energy density), ``drop_box.png`` and ``drop_box.gif``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from _common import Rollout, deformation, make_solver, script_main, simulate
from torch import Tensor

import energysim as es

NAME = "drop_box"
SIZE = 0.3  # m, edge of the cube
HEIGHT = 1.0  # m, height of the bottom face at release
STRAIN_LIMIT = 0.1  # largest ‖FᵀF − I‖_F allowed: the spin's centrifugal strain is about 1e-3
MOMENTUM_SLACK = 1e-6  # relative growth of |L| tolerated
# float64 rounding of positions of a few metres is ~1e-15 m per step, so ~1e-12 m after even 1000 steps
ROUNDING = 1e-10


def build_scene(
    resolution: int = 6, dt: float = 1 / 60, solver: str = "newton-cg", tol: float = 1e-5
) -> es.Scene:
    """The cube, `resolution` cells along each edge, under gravity (−9.81 m/s² along y), nothing fixed."""
    mesh = es.TetMesh.box(size=(SIZE,) * 3, cells=(resolution,) * 3, origin=(0.0, HEIGHT, 0.0))
    scene = es.Scene(mesh, density=1000.0, dt=dt, gravity=(0.0, -9.81, 0.0))
    scene.add(es.NeoHookean(youngs_modulus=1e5, poissons_ratio=0.3))
    scene.solver = make_solver(solver, tol)
    return scene


def _centre_of_mass(mass: Tensor, values: Tensor) -> Tensor:
    return (mass[:, None] * values).sum(dim=0) / mass.sum()


def run(
    scene: es.Scene,
    seconds: float = 1.0,
    out: Path | None = None,
    *,
    spin: float = 2.0,
    frames_every: int = 1,
    progress: bool = True,
) -> Rollout:
    """Release the cube at rest shape with angular velocity `spin` (rad/s) about z and let it fall.

    `history` holds per step: ``com`` and ``com_velocity`` `[3]`, ``angular_momentum`` about the
    centre of mass `[3]` (kg m²/s), ``min_det`` (smallest J), ``max_strain`` (largest ‖FᵀF − I‖_F)
    and ``finite`` (whether every position and velocity is finite).
    """
    mass = scene.vertex_mass
    x0 = scene.rest_positions
    # about the centre of mass, so the spin adds no linear momentum
    omega = x0.new_tensor([0.0, 0.0, spin])
    v0 = torch.linalg.cross(omega.expand_as(x0), x0 - _centre_of_mass(mass, x0))

    def observe(x: Tensor, v: Tensor) -> dict[str, Tensor]:
        com, com_velocity = _centre_of_mass(mass, x), _centre_of_mass(mass, v)
        arm, relative = x - com, v - com_velocity
        F, _ = deformation(scene, x)
        eye = torch.eye(3, dtype=F.dtype)
        return {
            "com": com,
            "com_velocity": com_velocity,
            "angular_momentum": (mass[:, None] * torch.linalg.cross(arm, relative)).sum(dim=0),
            "min_det": torch.linalg.det(F).min(),
            "max_strain": torch.linalg.matrix_norm(F.transpose(-1, -2) @ F - eye).max(),
            "finite": torch.isfinite(x).all() & torch.isfinite(v).all(),
        }

    state = scene.initial_state(velocities=v0)
    return simulate(scene, state, seconds, observe, out=out, frames_every=frames_every, progress=progress)


def measure(rollout: Rollout) -> dict[str, float]:
    """The figures `check` judges, by name (units in the names)."""
    h, g = rollout.dt, rollout.gravity
    history = rollout.history
    com, com_velocity = history["com"], history["com_velocity"]
    n = torch.arange(com.shape[0], dtype=com.dtype)[:, None]
    # v_n = v_0 + n h g and x_n = x_0 + h Σ_{k=1..n} v_k: implicit Euler's exact free fall
    expected_velocity = com_velocity[0] + n * h * g
    expected = com[0] + n * h * com_velocity[0] + h * h * g * n * (n + 1) / 2
    # A step that stops at velocity residual r_k (‖h M⁻¹∇E‖∞) leaves the centre of mass off by at most
    # h r_k and its velocity by r_k; both errors carry forward, the position's growing with n.
    residual = torch.tensor([0.0] + [s.residual for s in rollout.stats], dtype=com.dtype)
    velocity_bound = residual.cumsum(0) + ROUNDING / h
    position_bound = h * residual.cumsum(0).cumsum(0) + ROUNDING
    position_error = (com - expected).abs().amax(dim=1)
    velocity_error = (com_velocity - expected_velocity).abs().amax(dim=1)
    momentum = history["angular_momentum"].norm(dim=1)
    return {
        "com fall (m)": float(com[0, 1] - com[-1, 1]),
        "com position error (m)": float(position_error.max()),
        "com position bound at the end (m)": float(position_bound[-1]),
        "com position error / bound": float((position_error / position_bound).max()),
        "com velocity error (m/s)": float(velocity_error.max()),
        "com velocity error / bound": float((velocity_error / velocity_bound).max()),
        "min J": float(history["min_det"].min()),
        "max strain |F^T F - I|": float(history["max_strain"].max()),
        "|L| initial (kg m^2/s)": float(momentum[0]),
        "|L| final / initial": float(momentum[-1] / momentum[0]),
        "|L| largest step-to-step growth": float((momentum[1:] / momentum[:-1]).max() - 1.0),
        "non-finite steps": float((~history["finite"]).sum()),
    }


def check(rollout: Rollout) -> None:
    """Raise AssertionError, with the figures, unless the fall is physically right."""
    f = measure(rollout)
    assert f["non-finite steps"] == 0, f"{f['non-finite steps']:.0f} steps have NaN or inf"
    assert torch.isfinite(rollout.positions).all(), "saved positions hold NaN or inf"
    assert f["com position error / bound"] <= 1.0, (
        f"centre of mass is {f['com position error (m)']:.3e} m off implicit Euler's free fall, "
        f"{f['com position error / bound']:.3g} times what the solver residuals allow"
    )
    assert f["com velocity error / bound"] <= 1.0, (
        f"centre-of-mass velocity is {f['com velocity error (m/s)']:.3e} m/s off free fall, "
        f"{f['com velocity error / bound']:.3g} times what the solver residuals allow"
    )
    assert f["min J"] > 0, f"an element inverted: min J = {f['min J']:.4g}"
    assert f["max strain |F^T F - I|"] < STRAIN_LIMIT, (
        f"the cube deformed: max ‖FᵀF − I‖ = {f['max strain |F^T F - I|']:.4g} >= {STRAIN_LIMIT}"
    )
    assert f["|L| final / initial"] <= 1.0 + MOMENTUM_SLACK, (
        f"angular momentum grew: |L| final / initial = {f['|L| final / initial']:.9f}"
    )


def main(argv: list[str] | None = None) -> int:
    """Command line entry point; returns 0 when the run passes its check."""
    return script_main(argv, sys.modules[__name__], seconds=1.0, resolution=6)


if __name__ == "__main__":
    sys.exit(main())
