"""A soft beam clamped at one end, released from rest, swings under gravity for 2 s; the run checks itself.

    python scripts/cantilever.py [--seconds 2] [--dt 0.01667] [--solver newton-cg|lbfgs|adam] [--tol 1e-5]
                                 [--resolution 4] [--out out/cantilever] [--frames-every 1] [--no-render]

A 1 × 0.2 × 0.2 m beam (E = 100 kPa, ν = 0.3, ρ = 1000 kg/m³) along x, its end face x = 0 clamped. So
soft a beam cannot hold itself up (linear theory would sag it 3.7 m): it swings down like a pendulum,
past the vertical under the clamp (t ≈ 0.6 s), and back.

What must hold (`check`):
- nothing becomes NaN, and the clamped vertices never move (exactly: they are out of every solve);
- total energy (kinetic + elastic + gravitational) never rises from one step to the next beyond what the
  step's solver residual and rounding allow: implicit Euler only dissipates;
- the tip sags below its rest height and is still below it at the end;
- the tip reaches a lowest point and comes back up (its y velocity turns positive at least once),
  which takes about 0.6 s at the default resolution: shorter runs fail this part of the check.

Writes ``frame_*.vtu`` + ``frame.pvd`` (velocity, energy density), ``cantilever.png`` and
``cantilever.gif``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from _common import (
    Rollout,
    deformation,
    gravity,
    make_solver,
    script_main,
    simulate,
)
from torch import Tensor

import energysim as es

NAME = "cantilever"
LENGTH, WIDTH = 1.0, 0.2  # m; the cross-section is WIDTH × WIDTH
# An energy of a few hundred J is summed from thousands of float64 terms: rounding ~1e-13 of it per step.
ROUNDING = 1e-12


def build_scene(
    resolution: int = 4, dt: float = 1 / 60, solver: str = "newton-cg", tol: float = 1e-5
) -> es.Scene:
    """The beam, `resolution` cells across its width (5× as many along it), its x = 0 face fixed."""
    mesh = es.TetMesh.box(size=(LENGTH, WIDTH, WIDTH), cells=(5 * resolution, resolution, resolution))
    scene = es.Scene(mesh, density=1000.0, dt=dt, gravity=(0.0, -9.81, 0.0))
    scene.add(es.NeoHookean(youngs_modulus=1e5, poissons_ratio=0.3))
    scene.fix(torch.nonzero(_on_plane(mesh.vertices[:, 0], 0.0)).flatten())
    scene.solver = make_solver(solver, tol)
    return scene


def _on_plane(coordinate: Tensor, value: float) -> Tensor:
    # lattice coordinates come from products of cell counts and spacings: equal only to rounding
    return (coordinate - value).abs() < 1e-9 * LENGTH


def run(
    scene: es.Scene,
    seconds: float = 2.0,
    out: Path | None = None,
    *,
    frames_every: int = 1,
    progress: bool = True,
) -> Rollout:
    """Release the beam from its rest shape at rest and let it swing.

    `history` holds per step (J, m, m/s): ``kinetic``, ``elastic`` and ``gravitational`` energy,
    ``momentum_l1`` (Σ m‖v‖₁, which turns a velocity residual into an energy allowance),
    ``magnitude`` (the sum of the magnitudes of the energy parts, for the rounding allowance),
    ``tip_y`` and ``tip_vy`` (mean over the free end face), ``clamp_motion`` (largest |x − x_rest|
    or |v| of a clamped vertex), ``min_det`` (smallest J) and ``finite``.
    """
    mass = scene.vertex_mass
    rest = scene.rest_positions
    volume = scene.mesh.element_rest_volume()
    g = gravity(scene)
    tip = _on_plane(rest[:, 0], LENGTH)
    clamped = scene.fixed

    def observe(x: Tensor, v: Tensor) -> dict[str, Tensor]:
        F, psi = deformation(scene, x)
        height_energy = mass * (x @ g)  # m g·x per vertex; the potential is minus their sum
        kinetic = 0.5 * (mass * (v * v).sum(dim=1)).sum()
        elastic = (volume * psi).sum()
        return {
            "kinetic": kinetic,
            "elastic": elastic,
            "gravitational": -height_energy.sum(),
            "momentum_l1": (mass * v.abs().sum(dim=1)).sum(),
            "magnitude": kinetic + elastic + height_energy.abs().sum(),
            "tip_y": x[tip, 1].mean(),
            "tip_vy": v[tip, 1].mean(),
            "clamp_motion": torch.maximum((x - rest)[clamped].abs().max(), v[clamped].abs().max()),
            "min_det": torch.linalg.det(F).min(),
            "finite": torch.isfinite(x).all() & torch.isfinite(v).all(),
        }

    state = scene.initial_state()
    return simulate(scene, state, seconds, observe, out=out, frames_every=frames_every, progress=progress)


def measure(rollout: Rollout) -> dict[str, float]:
    """The figures `check` judges, by name (units in the names)."""
    history = rollout.history
    energy = history["kinetic"] + history["elastic"] + history["gravitational"]
    rise = energy[1:] - energy[:-1]
    # A step stopped at velocity residual r (‖h M⁻¹∇E‖∞) can gain at most r Σ m‖v‖₁ over the exact
    # implicit-Euler step, whose energy cannot rise (for a convex potential).
    residual = torch.tensor([s.residual for s in rollout.stats], dtype=energy.dtype)
    allowance = residual * history["momentum_l1"][1:] + ROUNDING * history["magnitude"][1:]
    tip_y, tip_vy = history["tip_y"], history["tip_vy"]
    lowest = int(tip_y.argmin())
    turns_up = ((tip_vy[:-1] < 0) & (tip_vy[1:] > 0)).sum()
    return {
        "energy initial (J)": float(energy[0]),
        "energy final (J)": float(energy[-1]),
        "largest energy rise (J)": float(rise.max()),
        "largest energy rise / allowance": float((rise / allowance).max()),
        "tip rest y (m)": float(tip_y[0]),
        "tip lowest displacement (m)": float(tip_y[lowest] - tip_y[0]),
        "tip lowest at (s)": lowest * rollout.dt,
        "tip final displacement (m)": float(tip_y[-1] - tip_y[0]),
        "tip rebound from lowest (m)": float(tip_y[lowest:].max() - tip_y[lowest]),
        "tip upward turns": float(turns_up),
        "clamped vertex motion (m, m/s)": float(history["clamp_motion"].max()),
        "min J": float(history["min_det"].min()),
        "non-finite steps": float((~history["finite"]).sum()),
    }


def check(rollout: Rollout) -> None:
    """Raise AssertionError, with the figures, unless the swing is physically right."""
    f = measure(rollout)
    assert f["non-finite steps"] == 0, f"{f['non-finite steps']:.0f} steps have NaN or inf"
    assert torch.isfinite(rollout.positions).all(), "saved positions hold NaN or inf"
    assert f["clamped vertex motion (m, m/s)"] == 0.0, (
        f"clamped vertices moved: {f['clamped vertex motion (m, m/s)']:.3e} m or m/s"
    )
    assert f["largest energy rise / allowance"] <= 1.0, (
        f"total energy rose by {f['largest energy rise (J)']:.3e} J in one step, "
        f"{f['largest energy rise / allowance']:.3g} times the solver and rounding allowance"
    )
    assert f["tip lowest displacement (m)"] < 0, (
        f"the tip never sagged: lowest displacement {f['tip lowest displacement (m)']:.4g} m"
    )
    assert f["tip final displacement (m)"] < 0, (
        f"the tip ended above its rest height: displacement {f['tip final displacement (m)']:.4g} m"
    )
    assert f["tip upward turns"] >= 1, (
        f"the tip never came back up in {len(rollout.stats) * rollout.dt:.3g} s (lowest at "
        f"{f['tip lowest at (s)']:.3g} s, {f['tip lowest displacement (m)']:.4g} m): too short a run?"
    )


def main(argv: list[str] | None = None) -> int:
    """Command line entry point; returns 0 when the run passes its check."""
    return script_main(argv, sys.modules[__name__], seconds=2.0, resolution=4)


if __name__ == "__main__":
    sys.exit(main())
