"""The hard-case stability matrix: every hard case under every optimizer, each cell judged automatically.

    python scripts/stability_matrix.py [--quick] [--optimizers adam lbfgs newton-cg newton-cg-projected]
        [--cases random flat inverted ...] [--out docs/benchmarks] [--threads 1] [--budget 60]

Cases (stable neo-Hookean, ρ = 1000 kg/m³, boxes of 0.2 m, ν = 0.3 and E = 100 kPa unless named):
- `random`, `flat`, `inverted`: a free body (no gravity, 3×3×3 cells) released at rest from scrambled
  positions: every vertex uniformly in its bounding box; squashed to zero volume; the mirror image plus
  1 mm of noise. h = 1/24 s, 1 s. It must recover its rest shape.
- `nu=0.45`, `nu=0.49`, `nu=0.495`, `E=1e2` … `E=1e8`, `h=1/24`, `h=1/60`, `h=1/240`: a tilted box
  (2×2×2 cells) dropped 2 cm onto frictional ground (μ = 0.5), 0.4 s; h = 1/60 s unless named.
- `ratio=1e4`: one mesh with two materials, a 100 MPa block on a 10 kPa block, dropped like the others.
- `impact`: the tilted box thrown at the ground at 20 m/s (E = 1 MPa), 1.5 s. It must end at rest.

Every optimizer stops at the same velocity residual, `TOL`; Adam and L-BFGS get at most `MAX_ITER`
iterations per step, so that they either converge or warn. Each cell passes, fails with a clear error,
or is WRONG:
- pass: every step converged, no NaN, no vertex reached the ground, the independently recomputed
  implicit-Euler residual agreed with the solver's report, the mechanical energy (kinetic + gravity +
  elastic + barrier) never rose beyond the work of the step's own residual and rounding
  (`energy_allowance`), and the expected end held (rest shape recovered with every element positive; at
  rest above the ground).
- clear error: a `ConvergenceError` or `ValueError` whose message gives figures, or `ConvergenceWarning`s
  with their figures for the steps that stopped short (those steps are excused from the energy and
  residual rules; the reason counts the ones whose energy rose).
- WRONG: NaN, penetration, speeds beyond what the initial energy allows, a residual above the tolerance
  or an energy rise in a step the solver reported converged, an expected end that failed with no warning,
  or any other exception.

The energy rule assumes the potential is convex along each step. Implicit Euler dissipates only then: an
exact step changes the energy by −½‖v' − v‖²_M − B with B the Bregman distance of the potential between
the two positions, and B < 0 is possible on non-convex elasticity (a compressed body spinning fast). The
rule calls such a gain WRONG too (tests/test_stability.py shows one); no cell of the matrix has one.

A cell that has warned, and so cannot pass, stops after `--budget` seconds of wall time.

Writes `stability_matrix.md` and `stability_matrix.csv` to `--out`, prints the table, and exits non-zero
if any cell is WRONG.
"""

from __future__ import annotations

import argparse
import math
import re
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import _bench
import torch
from torch import Tensor

import energysim as es
from energysim.mesh import signed_volumes

SIZE = 0.2  # m, edge of every box
DENSITY = 1000.0  # kg/m³
FRICTION = 0.5
TOL = 1e-5  # m/s, the velocity-residual tolerance of every optimizer
# The most outer iterations per step: Newton–CG keeps its default; the first-order methods get a cap
# that lets them converge on easy steps and makes them stop (and warn) on hard ones.
MAX_ITER = {"adam": 500, "lbfgs": 500, "newton-cg": 100, "newton-cg-projected": 100}
# A solve reported converged must have an independently recomputed residual below this many times the
# tolerance: the two computations differ only in rounding (about 1e-12 m/s here).
RESIDUAL_SLACK = 1.01
# Relative rounding tolerated in the mechanical energy: it is a sum of terms of up to this scale, each
# accurate to a few ulps.
ENERGY_ROUNDING = 1e-11
# A recovered body is within this RMS distance of its rest shape, after the best rigid motion, as a
# fraction of its size; and every element has at least this fraction of its rest volume.
ALIGNMENT_LIMIT = 1e-3
VOLUME_FLOOR = 0.5
# At the end of the impact case no vertex moves faster than this, m/s.
REST_SPEED = 1e-2
# Speeds beyond this multiple of what the initial mechanical energy could give a vertex are an explosion.
SPEED_SLACK = 2.0
# Wall time, s, after which a cell that has already warned (and so cannot pass) stops: a first-order
# method that stops at its iteration cap every step would otherwise take most of the run's time.
CELL_BUDGET = 60.0

PASS, CLEAR, WRONG = "pass", "clear error", "WRONG"


# --- the cases ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Case:
    """One hard case: a scene, its initial state and what must hold at the end.

    Attributes:
        name: short name used on the command line and in the table.
        description: one line for the table's legend.
        build: returns the scene (its solver is replaced per cell) and the initial state `[2·num_dofs]`.
        seconds: simulated time, s.
        quick_seconds: simulated time with `--quick`, s.
        recovers_rest_shape: the body is unforced and must return to its rest shape.
        comes_to_rest: the body must end at rest (no vertex faster than `REST_SPEED`).
    """

    name: str
    description: str
    build: Callable[[], tuple[es.Scene, Tensor]]
    seconds: float
    quick_seconds: float
    recovers_rest_shape: bool = False
    comes_to_rest: bool = False


def scrambled(mesh: es.TetMesh, how: str, seed: int = 0) -> Tensor:
    """Rest positions scrambled `how`, shape `[n, 3]`, in m.

    "random": every vertex uniformly in the mesh's bounding box; "flat": every vertex moved to the
    bottom plane, so every element has zero volume; "inverted": the mirror image through that plane
    (every element inverted) plus 1 mm of Gaussian noise. The noise breaks the mirror symmetry: the
    energy is invariant under the reflection that maps the mirror image back to the mesh, so exact
    dynamics would stay in the symmetric subspace and could stop at a symmetric saddle.
    """
    generator = torch.Generator().manual_seed(seed)
    x = mesh.vertices.clone()
    low, high = mesh.bounding_box()
    if how == "random":
        return low + (high - low) * torch.rand(x.shape, generator=generator, dtype=x.dtype)
    if how == "flat":
        x[:, 1] = low[1]
        return x
    if how == "inverted":
        x[:, 1] = 2 * low[1] - x[:, 1]
        return x + 1e-3 * torch.randn(x.shape, generator=generator, dtype=x.dtype)
    raise ValueError(f"how must be 'random', 'flat' or 'inverted', got {how!r}")


def rotation(angles: Sequence[float]) -> Tensor:
    """Rotation about x, then y, then z by `angles` (rad), shape `[3, 3]`."""
    rotation = torch.eye(3, dtype=torch.float64)
    for axis, angle in enumerate(angles):
        c, s = math.cos(angle), math.sin(angle)
        i, j = [a for a in range(3) if a != axis]
        turn = torch.eye(3, dtype=torch.float64)
        turn[i, i], turn[i, j], turn[j, i], turn[j, j] = c, -s, s, c
        rotation = turn @ rotation
    return rotation


TILT = (0.35, 0.2, 0.25)  # rad: the box lands on a corner, not flat on a face


def tilted_above_ground(mesh: es.TetMesh, gap: float) -> Tensor:
    """The rest mesh rotated by `TILT` about its centre, its lowest vertex `gap` m above y = 0, `[n, 3]`."""
    centre = mesh.vertices.mean(dim=0)
    x = (mesh.vertices - centre) @ rotation(TILT).T
    return x - torch.tensor([0.0, float(x[:, 1].min()) - gap, 0.0], dtype=x.dtype)


def recovery_case(how: str) -> Case:
    """A free body at rest, no gravity, released from positions scrambled `how` (see `scrambled`)."""

    def build() -> tuple[es.Scene, Tensor]:
        mesh = es.TetMesh.box(size=(SIZE,) * 3, cells=(3, 3, 3))
        scene = es.Scene(mesh, density=DENSITY, dt=1 / 24, gravity=None)
        scene.add(es.NeoHookean(1e5, 0.3))
        return scene, scene.initial_state(positions=scrambled(mesh, how))

    words = {
        "random": "every vertex at random",
        "flat": "squashed flat",
        "inverted": "every element inverted",
    }
    return Case(
        how,
        f"{words[how]}, no gravity, 3×3×3 cells, E = 100 kPa, h = 1/24 s",
        build,
        seconds=1.0,
        quick_seconds=0.5,
        recovers_rest_shape=True,
    )


def drop_case(
    name: str,
    description: str,
    youngs_modulus: float | Callable[[es.TetMesh], Tensor] = 1e5,
    poissons_ratio: float = 0.3,
    dt: float = 1 / 60,
    size: tuple[float, float, float] = (SIZE, SIZE, SIZE),
    cells: tuple[int, int, int] = (2, 2, 2),
    seconds: float = 0.4,
    quick_seconds: float = 0.2,
) -> Case:
    """A box of `size` (m) and `cells`, tilted by `TILT`, released at rest 2 cm above frictional ground.

    `youngs_modulus` is in Pa, or a function of the mesh giving one value per element.
    """

    def build() -> tuple[es.Scene, Tensor]:
        mesh = es.TetMesh.box(size=size, cells=cells)
        scene = es.Scene(mesh, density=DENSITY, dt=dt)
        modulus = youngs_modulus(mesh) if callable(youngs_modulus) else youngs_modulus
        scene.add(es.NeoHookean(modulus, poissons_ratio))
        scene.add(es.Ground(0.0, friction=FRICTION))
        return scene, scene.initial_state(positions=tilted_above_ground(mesh, 0.02))

    return Case(name, description, build, seconds=seconds, quick_seconds=quick_seconds)


def stiff_on_soft(mesh: es.TetMesh) -> Tensor:
    """Young's modulus per element: 100 MPa in the upper half, 10 kPa in the lower half, Pa, `[m]`."""
    centres = mesh.vertices[mesh.elements].mean(dim=1)
    middle = 0.5 * float(mesh.vertices[:, 1].max() + mesh.vertices[:, 1].min())
    return torch.where(centres[:, 1] > middle, 1e8, 1e4).to(torch.float64)


def impact_case() -> Case:
    """The tilted box thrown down at 20 m/s from 0.3 m above frictional ground."""

    def build() -> tuple[es.Scene, Tensor]:
        mesh = es.TetMesh.box(size=(SIZE,) * 3, cells=(2, 2, 2))
        scene = es.Scene(mesh, density=DENSITY, dt=1 / 60)
        scene.add(es.NeoHookean(1e6, 0.3))
        scene.add(es.Ground(0.0, friction=FRICTION))
        x0 = tilted_above_ground(mesh, 0.3)
        return scene, scene.initial_state(x0, torch.tensor([0.0, -20.0, 0.0]).expand_as(x0))

    return Case(
        "impact",
        "thrown at the ground at 20 m/s from 0.3 m, E = 1 MPa, μ = 0.5, h = 1/60 s; must end at rest",
        build,
        seconds=1.5,
        quick_seconds=0.5,
        comes_to_rest=True,
    )


def build_cases() -> dict[str, Case]:
    """Every case of the matrix, by name, in table order."""
    drop = "tilted box dropped 2 cm on the ground, μ = 0.5"
    cases = [recovery_case(how) for how in ("random", "flat", "inverted")]
    cases += [drop_case(f"nu={nu:g}", f"{drop}, ν = {nu:g}", poissons_ratio=nu) for nu in (0.45, 0.49, 0.495)]
    cases += [
        drop_case(f"E=1e{exponent}", f"{drop}, E = 1e{exponent} Pa", youngs_modulus=10.0**exponent)
        for exponent in (2, 4, 6, 8)
    ]
    cases.append(
        drop_case(
            "ratio=1e4",
            "one mesh, two materials: a 100 MPa block on a 10 kPa block (2×4×2 cells), dropped 2 cm",
            youngs_modulus=stiff_on_soft,
            size=(SIZE, 2 * SIZE, SIZE),
            cells=(2, 4, 2),
        )
    )
    for label, dt in (("1/24", 1 / 24), ("1/60", 1 / 60), ("1/240", 1 / 240)):
        cases.append(drop_case(f"h={label}", f"{drop}, h = {label} s", dt=dt))
    cases.append(impact_case())
    return {case.name: case for case in cases}


def build_optimizers(tol: float = TOL) -> dict[str, es.Solver]:
    """Every optimizer of the matrix, by command-line name, stopping at velocity residual `tol` (m/s)."""
    return {
        "adam": es.Adam(tol=tol, max_iter=MAX_ITER["adam"]),
        "lbfgs": es.LBFGS(tol=tol, max_iter=MAX_ITER["lbfgs"]),
        "newton-cg": es.NewtonCG(tol=tol, max_iter=MAX_ITER["newton-cg"]),
        "newton-cg-projected": es.NewtonCG(
            tol=tol, max_iter=MAX_ITER["newton-cg-projected"], project_hessian=True
        ),
    }


CASES = build_cases()
OPTIMIZERS = build_optimizers()
LABELS = {
    "adam": "Adam",
    "lbfgs": "L-BFGS",
    "newton-cg": "Newton–CG",
    "newton-cg-projected": "Newton–CG, projected Hessian",
}


# --- the measurements ---------------------------------------------------------------------------


def obstacles_of(scene: es.Scene) -> list[es.Obstacle]:
    """The scene's obstacle terms (the ground)."""
    return [term for term in scene.terms if isinstance(term, es.Obstacle)]


def mechanical_energy(scene: es.Scene, state: Tensor) -> tuple[float, float]:
    """Kinetic plus every potential term of the scene (gravity, elasticity, barriers), in J, and the
    sum of their magnitudes (the scale of its rounding error), in J."""
    x, v = scene.split_state(state)
    with torch.no_grad():
        parts = [0.5 * float((scene.vertex_mass[:, None] * v[0] ** 2).sum())]
        parts += [float(term(x)[0]) for term in scene.terms]
    return sum(parts), sum(abs(part) for part in parts)


def step_residual(scene: es.Scene, state: Tensor, new_state: Tensor) -> Tensor:
    """The implicit-Euler momentum residual (v' − v) + h M⁻¹ ∇(Φ + D)(x'), per vertex, `[n, d]`, m/s.

    Recomputed from the two states alone: Φ is the sum of the scene's terms and D the friction the
    obstacles lag from the step's start, both differentiated by autograd through their plain
    `forward` (not the solvers' closed-form kernels). Zero on fixed vertices.
    """
    x_prev, v_prev = scene.split_state(state)
    x_next, v_next = scene.split_state(new_state)
    lagged = [extra for term in scene.terms for extra in term.lagged_terms(x_prev, scene.dt)]
    with torch.enable_grad():
        x = x_next.detach().clone().requires_grad_(True)
        potential = sum(term(x) for term in [*scene.terms, *lagged]).sum()
        (gradient,) = torch.autograd.grad(potential, x)
    residual = (v_next - v_prev)[0] + scene.dt / scene.vertex_mass[:, None] * gradient[0]
    return residual * scene.free[:, None].to(residual.dtype)


def energy_allowance(scene: es.Scene, new_state: Tensor, residual: Tensor, scale: float) -> float:
    """How much the mechanical energy may rise in a step whose residual is `residual`, in J.

    From M(v' − v)/h = −∇Φ(x') − ∇D(x') + Mρ/h (ρ the residual) and convexity along the step,
    E' − E ≤ −½‖v' − v‖²_M − (friction work) + v'ᵀMρ: an exact solve never gains energy, and an
    inexact one at most the work of its residual, |v'ᵀMρ|. Rounding adds `ENERGY_ROUNDING` × `scale`.
    """
    _, v = scene.split_state(new_state)
    work = float((scene.vertex_mass[:, None] * v[0] * residual).sum())
    return abs(work) + ENERGY_ROUNDING * scale


def potential_floor(scene: es.Scene, x: Tensor) -> float:
    """A lower bound of the scene's potential energy, J: elasticity and barriers are ≥ 0, and gravity
    is least with every vertex on the ground (−∞ with gravity and no ground)."""
    floor = 0.0
    ground = [term for term in obstacles_of(scene) if isinstance(term, es.HalfSpace)]
    for term in scene.terms:
        if isinstance(term, es.Gravity):
            if not ground:
                return -math.inf
            plane = ground[0]
            # every vertex projected onto the plane: the lowest it can be
            on_plane = x - (plane.signed_distance(x))[..., None] * plane.normal
            with torch.no_grad():
                floor += float(term(on_plane)[0])
    return floor


def rigid_alignment_error(x: Tensor, rest: Tensor) -> float:
    """RMS distance between `x` and `rest` (`[n, d]`, m) after the best proper rigid motion (Kabsch), m."""
    xc, rc = x - x.mean(0), rest - rest.mean(0)
    u, _, vt = torch.linalg.svd(rc.T @ xc)
    signs = torch.ones(x.shape[1], dtype=x.dtype)
    signs[-1] = torch.sign(torch.linalg.det(u @ vt))
    return float(((rc @ u @ torch.diag(signs) @ vt - xc) ** 2).sum(-1).mean().sqrt())


FIGURE = re.compile(r"\d\.?\d*(e[-+]?\d+)?")


def gives_figures(message: str) -> bool:
    """Whether an error message names at least one number (a residual, a distance, an index)."""
    return FIGURE.search(message) is not None


# --- one cell -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Cell:
    """The verdict on one case under one optimizer, with the figures it rests on.

    Attributes:
        case, optimizer: names.
        outcome: "pass", "clear error" or "WRONG".
        reason: a short explanation (empty for a pass).
        steps: steps completed; planned_steps: steps asked for.
        warned_steps: steps whose solve warned that it did not converge.
        seconds: wall time of the cell, s.
        iterations: outer iterations over all steps.
        worst_residual: largest recomputed residual over the steps reported converged, m/s.
        worst_energy_excess: largest rise of the mechanical energy beyond the allowance in one step, J
            (negative: it never came within that of rising).
        energy_start, energy_end: mechanical energy, J.
        min_gap: smallest distance of any vertex to an obstacle over the run, m (nan: no obstacle).
        max_speed: largest vertex speed over the run, m/s; speed_limit: what the energy allows, m/s.
        final_speed: largest vertex speed at the end, m/s.
        final_momentum: ‖Σ m v‖ at the end, kg·m/s.
        alignment_error: RMS distance to the rest shape after the best rigid motion, over the size.
        min_volume_ratio: smallest element volume over its rest volume, at the end.
        volume_ratio: total volume over the rest volume, at the end.
    """

    case: str
    optimizer: str
    outcome: str
    reason: str
    steps: int
    planned_steps: int
    warned_steps: int
    seconds: float
    iterations: int
    worst_residual: float
    worst_energy_excess: float
    energy_start: float
    energy_end: float
    min_gap: float
    max_speed: float
    speed_limit: float
    final_speed: float
    final_momentum: float
    alignment_error: float
    min_volume_ratio: float
    volume_ratio: float


@dataclass
class Judge:
    """What one cell has shown so far, step by step: the reasons for WRONG and for a clear error, and the
    figures behind them. `look` judges one step; `verdict` the whole cell."""

    scene: es.Scene
    speed_limit: float
    energy: float
    wrong: list[str] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    warned: list[tuple[int, str]] = field(default_factory=list)  # (step, the solver's report)
    rises_when_warned: int = 0
    worst_residual: float = 0.0
    worst_excess: float = -math.inf
    iterations: int = 0
    min_gap: float = math.nan
    max_speed: float = 0.0
    steps: int = 0

    @property
    def hopeless(self) -> bool:
        """Whether a NaN, an explosion or a penetration has been seen: nothing after it is meaningful."""
        return any(reason.startswith(("NaN", "explosion", "penetration")) for reason in self.wrong)

    def refuse(self, step: int, error: Exception) -> None:
        """A step raised: a clear error if it is a documented type with figures, else WRONG."""
        if isinstance(error, (es.ConvergenceError, ValueError)):
            message = f"{type(error).__name__} at step {step}: {error}"
            (self.errors if gives_figures(str(error)) else self.wrong).append(message)
        else:
            self.wrong.append(f"unexpected {type(error).__name__} at step {step}: {error}")

    def look(self, state: Tensor, result: es.StepResult, reports: list[str]) -> None:
        """Judge one step from `state` to `result.state`; `reports` are its convergence warnings."""
        scene, new_state = self.scene, result.state
        self.steps += 1
        self.iterations += result.stats.iterations
        if reports:
            self.warned.append((self.steps, reports[0]))
            if not all(gives_figures(report) for report in reports):
                self.wrong.append(f"step {self.steps}: a convergence warning without figures: {reports[0]}")
        if not torch.isfinite(new_state).all():
            self.wrong.append(f"NaN or infinite state after step {self.steps}")
            return
        x, v = scene.split_state(new_state)
        speed = float(v[0].norm(dim=-1).max())
        self.max_speed = max(self.max_speed, speed)
        if speed > self.speed_limit:
            self.wrong.append(
                f"explosion: a vertex at {speed:.3g} m/s after step {self.steps}, more than the initial "
                f"energy allows ({self.speed_limit / SPEED_SLACK:.3g} m/s)"
            )
        for obstacle in obstacles_of(scene):
            gap = float(obstacle.signed_distance(x[0, obstacle.element_vertices[:, 0]]).min())
            self.min_gap = gap if math.isnan(self.min_gap) else min(self.min_gap, gap)
            if gap <= 0:
                self.wrong.append(
                    f"penetration: a vertex {-gap:.3g} m inside {obstacle!r} after step {self.steps}"
                )
        residual = step_residual(scene, state, new_state)
        energy, scale = mechanical_energy(scene, new_state)
        rise = energy - self.energy
        excess = rise - energy_allowance(scene, new_state, residual, scale)
        self.energy = energy
        if reports:
            self.rises_when_warned += excess > 0
            return
        # the solver reported convergence: hold it to that
        worst = float(residual.abs().max())
        self.worst_residual = max(self.worst_residual, worst)
        self.worst_excess = max(self.worst_excess, excess)
        if not result.stats.converged:
            self.wrong.append(f"step {self.steps}: not converged and no warning ({result.stats.summary()})")
        if worst > RESIDUAL_SLACK * scene.solver.tol:
            self.wrong.append(
                f"silent non-convergence at step {self.steps}: reported converged, but the recomputed "
                f"residual is {worst:.3g} m/s (tol {scene.solver.tol:.1e})"
            )
        if excess > 0:
            self.wrong.append(
                f"energy rose by {rise:.3g} J in step {self.steps} ({excess:.3g} J beyond the residual's "
                "work and rounding)"
            )

    def expect(self, holds: bool, shortfall: str) -> None:
        """An expected end did not hold: a clear error if a solve warned, WRONG if none did."""
        if not holds:
            if self.warned:
                self.errors.append(shortfall)
            else:
                self.wrong.append(shortfall + ", and no solve warned")

    def verdict(self) -> tuple[str, str]:
        """The outcome and its reason."""
        if self.wrong:
            return WRONG, self.wrong[0]
        if self.errors:
            return CLEAR, self.errors[0]
        if self.warned:
            first_step, first_report = self.warned[0]
            reason = (
                f"warned at {len(self.warned)} of {self.steps} steps "
                f"(first at step {first_step}: {first_report})"
            )
            if self.rises_when_warned:
                reason += f"; the energy rose at {self.rises_when_warned} of them"
            return CLEAR, reason
        return PASS, ""


def run_cell(
    case: Case,
    optimizer: str,
    quick: bool = False,
    solver: es.Solver | None = None,
    budget: float | None = CELL_BUDGET,
) -> Cell:
    """Run `case` with the optimizer named `optimizer` (or with `solver`) and classify the outcome.

    A cell that has warned stops once it has run `budget` seconds (None: never); its reason says so.
    """
    scene, state = case.build()
    scene.solver = solver if solver is not None else OPTIMIZERS[optimizer]
    steps = round((case.quick_seconds if quick else case.seconds) / scene.dt)
    energy_start, _ = mechanical_energy(scene, state)
    x0, _ = scene.split_state(state)
    available = max(energy_start - potential_floor(scene, x0), 0.0)
    speed_limit = SPEED_SLACK * math.sqrt(2 * available / float(scene.vertex_mass.min()))
    judge = Judge(scene, speed_limit, energy_start)
    started = time.perf_counter()
    for index in range(steps):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                result = es.step(scene, state)
            except Exception as error:  # noqa: BLE001 - the judge tells documented errors from the rest
                judge.refuse(index + 1, error)
                break
        reports = [str(w.message) for w in caught if issubclass(w.category, es.ConvergenceWarning)]
        judge.look(state, result, reports)
        state = result.state
        if judge.hopeless:
            break
        if judge.warned and budget is not None and time.perf_counter() - started > budget:
            break
    seconds = time.perf_counter() - started

    x, v = scene.split_state(state)
    final_speed = float(v[0].norm(dim=-1).max())
    rest_volumes = signed_volumes(scene.mesh.vertices, scene.mesh.elements)
    volumes = signed_volumes(x[0], scene.mesh.elements)
    min_volume_ratio = float((volumes / rest_volumes).min())
    alignment = rigid_alignment_error(x[0], scene.mesh.vertices) / SIZE
    if judge.steps == steps and not judge.errors and not judge.wrong:
        if case.recovers_rest_shape:
            judge.expect(
                alignment <= ALIGNMENT_LIMIT and min_volume_ratio >= VOLUME_FLOOR,
                f"rest shape not recovered: alignment error {alignment:.3g} of the size (limit "
                f"{ALIGNMENT_LIMIT:g}), smallest element at {min_volume_ratio:.3g} of its rest volume",
            )
        if case.comes_to_rest:
            judge.expect(
                final_speed <= REST_SPEED,
                f"not at rest: a vertex at {final_speed:.3g} m/s at the end (limit {REST_SPEED:g} m/s)",
            )
    outcome, reason = judge.verdict()
    if judge.steps < steps and outcome == CLEAR and not judge.errors:
        reason += f"; stopped after {judge.steps} of {steps} steps (time budget {budget:g} s)"
    return Cell(
        case=case.name,
        optimizer=optimizer,
        outcome=outcome,
        reason=reason,
        steps=judge.steps,
        planned_steps=steps,
        warned_steps=len(judge.warned),
        seconds=seconds,
        iterations=judge.iterations,
        worst_residual=judge.worst_residual,
        worst_energy_excess=judge.worst_excess,
        energy_start=energy_start,
        energy_end=judge.energy,
        min_gap=judge.min_gap,
        max_speed=judge.max_speed,
        speed_limit=speed_limit,
        final_speed=final_speed,
        final_momentum=float((scene.vertex_mass[:, None] * v[0]).sum(dim=0).norm()),
        alignment_error=alignment,
        min_volume_ratio=min_volume_ratio,
        volume_ratio=float(volumes.sum() / rest_volumes.sum()),
    )


# --- the matrix ---------------------------------------------------------------------------------


def run(
    cases: Sequence[str] | None = None,
    optimizers: Sequence[str] | None = None,
    quick: bool = False,
    budget: float | None = CELL_BUDGET,
    log: Callable[[str], None] | None = None,
) -> list[Cell]:
    """Every requested cell, case by case; `log` receives one line per finished cell."""
    cells = []
    for case_name in cases or list(CASES):
        for optimizer in optimizers or list(OPTIMIZERS):
            cell = run_cell(CASES[case_name], optimizer, quick=quick, budget=budget)
            cells.append(cell)
            if log is not None:
                timing = f"{cell.seconds:6.1f} s"
                log(f"{case_name:>10} × {optimizer:<19} {cell.outcome:<11} {timing}  {cell.reason}")
    return cells


def short(cell: Cell) -> str:
    """The table cell: the outcome and, for anything but a pass, a short reason."""
    if cell.outcome == PASS:
        return PASS
    reason = cell.reason
    if cell.warned_steps and reason.startswith("warned"):
        reason = f"{cell.warned_steps}/{cell.steps} steps warned"
    elif len(reason) > 60:
        reason = reason[:57] + "…"
    return f"{cell.outcome}: {reason}"


def table(cells: Sequence[Cell]) -> str:
    """A markdown table, rows = cases, columns = optimizers."""
    case_names = list(dict.fromkeys(cell.case for cell in cells))
    optimizer_names = list(dict.fromkeys(cell.optimizer for cell in cells))
    by_key = {(cell.case, cell.optimizer): cell for cell in cells}
    header = ["case", *(LABELS.get(name, name) for name in optimizer_names)]
    rows = [
        [case, *(short(by_key[case, name]) if (case, name) in by_key else "" for name in optimizer_names)]
        for case in case_names
    ]
    return "\n".join(_bench.table(header, rows, align="l" * len(header)))


def counts(cells: Sequence[Cell]) -> dict[str, int]:
    """How many cells have each outcome."""
    return {outcome: sum(cell.outcome == outcome for cell in cells) for outcome in (PASS, CLEAR, WRONG)}


def optimizer_summary(cells: Sequence[Cell]) -> str:
    """A markdown table per optimizer: outcomes, outer iterations and wall time over its cells."""
    rows = []
    for name in dict.fromkeys(cell.optimizer for cell in cells):
        own = [cell for cell in cells if cell.optimizer == name]
        tally = counts(own)
        rows.append([LABELS.get(name, name), tally[PASS], tally[CLEAR], tally[WRONG],
                     sum(cell.iterations for cell in own), f"{sum(cell.seconds for cell in own):.0f}"])
    header = ["optimizer", "pass", "clear error", "WRONG", "iterations", "seconds"]
    return "\n".join(_bench.table(header, rows))


def markdown(cells: Sequence[Cell], command: str, threads: int) -> str:
    """The report: counts, the table, the legend of cases, and every non-pass cell in full."""
    tally = counts(cells)
    total = sum(cell.seconds for cell in cells)
    lines = [
        "# Hard-case stability matrix",
        "",
        f"`{command}`: {len(cells)} cells, {tally[PASS]} pass, {tally[CLEAR]} clear error, {tally[WRONG]} "
        f"WRONG; {total:.0f} s of stepping on {threads} thread(s), torch {torch.__version__}, float64.",
        "",
        f"Every optimizer stops at a velocity residual of {TOL:g} m/s; the most iterations per step are "
        + ", ".join(f"{MAX_ITER[name]} ({LABELS[name]})" for name in MAX_ITER)
        + "; other settings are the defaults. A cell passes when every step converged with no NaN, no "
        "vertex reached the ground, the recomputed implicit-Euler residual agreed with the solver's "
        "report, the mechanical energy never rose beyond the work of the step's own residual plus "
        "rounding, and the expected end held. It is a clear error when a solve raised or warned, with "
        "figures; anything else is WRONG. The script's docstring gives the precise rules.",
        "",
        "Steps that warned are excused from the residual and energy rules (the reason counts those whose "
        "energy rose), and a cell that has warned stops after `--budget` seconds of wall time (default "
        f"{CELL_BUDGET:g}). The energy rule assumes the potential is convex along each step: an exact "
        "implicit-Euler step can gain energy on non-convex elasticity (a compressed body spinning fast), "
        "and the rule would call that WRONG too.",
        "",
        table(cells),
        "",
        optimizer_summary(cells),
        "",
        "## Cases",
        "",
    ]
    for name in dict.fromkeys(cell.case for cell in cells):
        lines.append(f"- `{name}`: {CASES[name].description}" if name in CASES else f"- `{name}`")
    details = [cell for cell in cells if cell.outcome != PASS]
    if details:
        lines += ["", "## Cells that did not pass", ""]
        for cell in details:
            lines.append(
                f"- **{cell.case} × {LABELS.get(cell.optimizer, cell.optimizer)}** ({cell.outcome}, "
                f"{cell.steps}/{cell.planned_steps} steps): {cell.reason}"
            )
    lines += [
        "",
        "Per-cell figures (iterations, residuals, energies, gaps, speeds, volumes): `stability_matrix.csv`.",
        "",
    ]
    return "\n".join(lines)


def write(cells: Sequence[Cell], out: Path, command: str, threads: int) -> tuple[Path, Path]:
    """Write `stability_matrix.md` and `stability_matrix.csv` to `out`, each whole or not at all;
    returns their paths (floats in the CSV to 6 significant digits)."""
    rows = [
        {key: f"{value:.6g}" if isinstance(value, float) else value for key, value in asdict(cell).items()}
        for cell in cells
    ]
    csv_path, md_path = _bench.write_outputs(out, "stability_matrix", rows, markdown(cells, command, threads))
    return md_path, csv_path


def check(cells: Sequence[Cell]) -> None:
    """No cell may be WRONG."""
    wrong = [f"{cell.case} × {cell.optimizer}: {cell.reason}" for cell in cells if cell.outcome == WRONG]
    assert not wrong, "WRONG cells:\n" + "\n".join(wrong)


def main(argv: list[str] | None = None) -> list[Cell]:
    """Run the matrix as the command line asks, print the table, write the files and `check`."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="simulate a shorter time per case")
    parser.add_argument("--optimizers", nargs="+", choices=list(OPTIMIZERS), default=list(OPTIMIZERS))
    parser.add_argument("--cases", nargs="+", choices=list(CASES), default=list(CASES))
    parser.add_argument("--out", type=Path, default=Path("docs") / "benchmarks", help="output folder")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    parser.add_argument(
        "--budget",
        type=float,
        default=CELL_BUDGET,
        help="s after which a cell that has warned stops; 0: never",
    )
    args = parser.parse_args(argv)
    _bench.configure_threads(args.threads, retain_memory=False)
    budget = args.budget if args.budget > 0 else None
    cells = run(args.cases, args.optimizers, quick=args.quick, budget=budget, log=print)
    print()
    print(table(cells))
    tally = counts(cells)
    print(f"\n{tally[PASS]} pass, {tally[CLEAR]} clear error, {tally[WRONG]} WRONG")
    command = " ".join(["python scripts/stability_matrix.py", *(sys.argv[1:] if argv is None else argv)])
    for path in write(cells, args.out, command, args.threads):
        print(f"wrote {path}")
    check(cells)
    return cells


if __name__ == "__main__":
    try:
        main()
    except AssertionError as failure:
        print(failure, file=sys.stderr)
        sys.exit(1)
