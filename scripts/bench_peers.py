"""energysim against NVIDIA Warp's soft-body FEM (the `newton` package): wall time per simulated second
at equal or smaller error.

The scene is `bench_step`'s cantilever (1 × 0.2 × 0.2 m clamped at x = 0, E = 1e5 Pa, ν = 0.3 or
`--poissons-ratio`, ρ = 1000 kg/m³, gravity 9.81 m/s² along −y), released from rest and simulated for
`--checkpoints` × 1/12 s (1 s by default). Both simulators get the same tet mesh (energysim's
`TetMesh.box`, handed to `newton.ModelBuilder.add_soft_mesh`), the same lumped masses (ρ V/4 per
vertex), the clamped vertices as zero-mass (kinematic) particles, and no contact of any kind
(Newton's particle–particle and triangle contact are switched off: the energysim scene has none).

Materials. energysim uses the stable neo-Hookean energy of Smith et al. (2018) in the paper's form
ψ = μ'/2 (I_C − 3) + λ'/2 (J − α)² − μ'/2 log(I_C + 1), μ' = 4μ/3, λ' = λ + 5μ/6, α = 1 + 3μ'/(4λ').
Newton's semi-implicit solver evaluates that same form with (k_mu, k_lambda) taken as (μ', λ'), so it
gets k_mu = 4μ/3 and k_lambda = λ + 5μ/6: the same energy. Newton's VBD solver uses the production
form without the log term, ψ = μ/2 (I_C − 3) + (λ+μ)/2 (J − 1 − μ/(λ+μ))², with the Lamé parameters
(k_mu = μ, k_lambda = λ): the same small-strain limit, a slightly different energy at finite strain.
Newton's XPBD tet constraint (C = I_C − 3 and C = J − 1) is a different material altogether (no
small-strain shear stiffness), so it is not compared.

Error. Every run is compared at the times all of them share (multiples of 1/12 s; nothing is
interpolated) with one reference trajectory: energysim's Newton–CG at tol 1e-9 m/s on the same mesh
with the second-order TR-BDF2 step (`--reference-integrator`), at h_f = 1/(12 `--reference-steps`) s
(1/1920 s by default) and 2 h_f, combined by Richardson extrapolation for order 2:
x_ref = (4 x(h_f) − x(2 h_f))/3. Its error is estimated conservatively as max |x(h_f) − x(2 h_f)|/3
over vertices and times: that is the error of the finer run itself, which the extrapolation only
reduces. `--reference-integrator implicit_euler` gives the earlier reference instead: implicit Euler
at h_f·4, h_f·2 and h_f (`--reference-steps` 320 by default), extrapolated for order 1 twice over,
its error a third of the two extrapolations' largest difference. The check that the reference is
right: the energysim runs converge to it at their own order, first for implicit Euler and second for
TR-BDF2 (`check`, and the observed orders printed under the table). error = the largest distance
|x − x_ref| of any vertex at any of those times; final error = at the last time.
A trajectory is the right yardstick for time integrators: the settled sag would reward any heavily
damped scheme (and the semi-implicit integrator never settles without added damping, which changes
the physics), and this beam's sag (about 0.7 m for a 1 m beam) is far outside linear elasticity, so a
linear scikit-fem static solution is no reference for it.

Runs. energysim: Newton–CG with each implicit integrator of `--integrators` (implicit Euler: one
solve per step, first order; TR-BDF2: two solves per step, second order; see `es.step`) at
h = 1/24 … 1/240 s and the tolerances `--tols`, the explicit leapfrog (position Verlet, second
order, one gradient per substep, no solve) at `--leapfrog-substeps` substeps per 1/12 s, and the
reference's own runs (tol 1e-9 m/s, tighter
than their error needs: a conservative cost). Newton–CG solves its linear systems directly up to
`--direct-max-dofs` DOFs (5000 by default, so the 1k-tet beam's 768 DOFs take the block-tridiagonal
level solve of `direct="auto"`; the solver's own default, 600, would send them to CG), by CG above
that. Peer: the semi-implicit integrator at its largest stable step, found by doubling h from
1/(12·`--search-start`) s until the run blows up (non-finite, or farther than 1 m from the reference)
or its error exceeds `--accuracy-limit`, then bisecting the steps per 1/12 s between the last good
and the first bad count (with the same ν as energysim); it is then also timed at 1/2 and 1/4 of that
step, and at finer steps (halving, to 1/`--finest-peer-fraction`) until its error is no larger than
energysim's smallest, so that every energysim run has a peer run at equal or smaller error.
VBD (implicit Euler by vertex block descent, a fixed number of iterations per step) at `--vbd`
settings. With `--compile` energysim's runs evaluate the step objective by `torch.compile`d functions
(`NewtonCG(compile=True)`, which also takes the band Cholesky solve), compiled in an untimed run of
1/12 s before each timed run. Wall time per simulated second is the median of `--repeats` runs for
the peer (Warp's kernels are compiled, and cached, before timing) and of `--energysim-repeats` runs
(default one) for energysim (torch threads:
`--threads`; Warp's CPU kernels run on one thread). The ratio of an energysim run = its wall time /
the fastest peer run whose error is at most its own; "ratio VBD" the same against VBD runs alone
(implicit against implicit).

Without warp/newton installed the energysim side still runs, and the table says the peer is missing
(`pip install warp-lang newton`); the script then exits normally.

Run:  python scripts/bench_peers.py --out docs/benchmarks            # 1k tets, about 5 min on 2 cores
      python scripts/bench_peers.py --sizes tiny --checkpoints 3 --reference-steps 40 --dts 2 4 --vbd
      python scripts/bench_peers.py --poissons-ratio 0.49 --out out/bench_peers_nu049  # near-incompressible
      python scripts/bench_peers.py --compile --out docs/benchmarks/bench_peers_compiled
      python scripts/bench_peers.py --compile --reuse-factorization 0.5 \\
          --out docs/benchmarks/bench_peers_reuse
      python scripts/bench_peers.py --compile --integrators leapfrog \\
          --out docs/benchmarks/bench_peers_leapfrog
Writes: <out>/bench_peers.csv (every run), bench_peers.md (tables), bench_peers.png (error against
wall time per simulated second) and bench_peers_search.csv (the stable-step search).
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
import warnings
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import torch
from torch import Tensor

import energysim as es
from energysim.fem.materials import lame_parameters, smith_parameters

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _bench import (  # noqa: E402  # noqa: E402
    INTEGRATOR_ORDER,
    configure_threads,
    make_parser,
    pyplot,
    save_figure,
    table,
    write_csv,
    write_outputs,
)
from bench_step import SIZES, build_scene  # noqa: E402

CHECKPOINT_S = 1.0 / 12.0  # every step size below divides it
YOUNGS_MODULUS, POISSONS_RATIO, DENSITY, GRAVITY = 1e5, 0.3, 1000.0, 9.81  # bench_step's cantilever
DEFAULT_DTS = (2, 4, 5, 10, 20)  # energysim steps per 1/12 s: h = 1/24, 1/48, 1/60, 1/120, 1/240 s
DEFAULT_TOLS = (1e-2, 1e-3, 1e-5)  # m/s
# explicit leapfrog substeps per 1/12 s: 27 (h = 3.09 ms) is past its Courant limit on the 1k-tet beam
DEFAULT_LEAPFROG_SUBSTEPS = (27, 28, 32, 48, 96)
REFERENCE_TOL = 1e-9  # m/s
# finest reference steps per 1/12 s. On the 1k-tet beam over 1 s, TR-BDF2's two runs at 1/960 and
# 1/1920 s give an estimated error of 7e-6 m in 61 s (one thread); implicit Euler's three down to
# 1/3840 s took 112 s for an estimated 2.7e-4 m, and lie 4.4e-4 m from the TR-BDF2 extrapolation
DEFAULT_REFERENCE_STEPS = {"tr_bdf2": 160, "implicit_euler": 320}
# Newton–CG solves systems of up to this many DOFs directly: the 1k-tet beam (768) takes the
# block-tridiagonal level solve, 0.87 against 1.07 s per simulated second by CG at h = 1/48 s, tol 1e-3
DEFAULT_DIRECT_MAX_DOFS = 5000
BLOWN_UP_M = 1.0  # a run farther than the beam's length from the reference has blown up
ENERGYSIM = "energysim"
PEER = "warp/newton"


@dataclass(frozen=True)
class Run:
    """One simulated trajectory: its cost and its error against the reference; NaN where it failed."""

    tets: int
    simulator: str  # "energysim" or "warp/newton"
    integrator: str  # energysim: one of `es.INTEGRATORS`; the peer: "semi_implicit_euler" or "implicit_euler"
    method: str  # e.g. "newton-cg tol 1e-05", "semi-implicit", "vbd 10 iterations"
    tol: float  # energysim: the velocity-residual tolerance (m/s); NaN for the peer
    dt: float  # time step, s
    steps_per_checkpoint: int  # steps per 1/12 s
    wall_s_per_sim_s: float  # median wall time per simulated second
    repeats: int
    error_m: float  # largest |x − x_ref| of any vertex at any shared time, m
    final_error_m: float  # the same at the last time, m
    converged: str  # energysim: "k/n" steps that reached the tolerance; the peer: "–"
    ratio: float  # energysim: wall time / the fastest peer run with at most this error; NaN otherwise
    ratio_vbd: float  # the same against the peer's implicit integrator (VBD) only
    status: str  # "ok", "unstable", "inaccurate", or why it did not run
    note: str


# --- energysim ---------------------------------------------------------------------------------


def cantilever_scene(cells: tuple[int, int, int], poissons_ratio: float = POISSONS_RATIO) -> es.Scene:
    """`bench_step`'s cantilever on a box mesh with `cells` cells, its material's ν = `poissons_ratio`."""
    scene = build_scene(cells)
    for term in scene.terms:
        if isinstance(term, es.NeoHookean):
            term.poissons_ratio = torch.full_like(term.poissons_ratio, poissons_ratio)
    return scene


@dataclass(frozen=True)
class Trajectory:
    """An energysim run from rest: positions at t = 0, 1/12 s, …, shape `[C + 1, n, 3]` in m, and its cost."""

    positions: Tensor
    steps_per_checkpoint: int
    integrator: str
    wall_s: float
    steps: int
    converged: int  # steps that reached the tolerance
    iterations: int  # Newton iterations, all steps (both stages of a TR-BDF2 step)
    hvps: int  # Hessian-vector products, all steps


def energysim_trajectory(
    scene: es.Scene,
    steps_per_checkpoint: int,
    checkpoints: int,
    solver: es.Solver,
    integrator: str = "implicit_euler",
) -> Trajectory:
    """Step the scene from rest with `integrator` at h = 1/(12 `steps_per_checkpoint`) s for
    `checkpoints` × 1/12 s."""
    scene.dt = CHECKPOINT_S / steps_per_checkpoint
    scene.integrator = integrator
    state = scene.initial_state()
    positions = [scene.split_state(state)[0][0]]
    converged = steps = iterations = hvps = 0
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", es.ConvergenceWarning)  # counted below instead
        for _ in range(checkpoints):
            for _ in range(steps_per_checkpoint):
                result = es.step(scene, state, solver=solver)
                state = result.state
                converged += bool(result.stats.converged)
                iterations += result.stats.iterations
                hvps += result.stats.hvp_evals
                steps += 1
            positions.append(scene.split_state(state)[0][0])
    return Trajectory(
        torch.stack(positions),
        steps_per_checkpoint,
        integrator,
        time.perf_counter() - start,
        steps,
        converged,
        iterations,
        hvps,
    )


def richardson(coarse: Tensor, fine: Tensor, order: int) -> Tensor:
    """Richardson extrapolation of two runs at h and h/2 of a method of `order`:
    fine + (fine − coarse)/(2^order − 1), which cancels the error's leading term c h^order."""
    return fine + (fine - coarse) / (2**order - 1)


def reference_trajectory(
    scene: es.Scene,
    checkpoints: int,
    finest_steps: int,
    integrator: str = "tr_bdf2",
    direct_max_dofs: int = DEFAULT_DIRECT_MAX_DOFS,
) -> tuple[Tensor, float, list[Trajectory]]:
    """Richardson-extrapolated Newton–CG trajectory `[checkpoints + 1, n, 3]` (m), its estimated error
    (m) and the runs it came from.

    "tr_bdf2" (second order): runs at `finest_steps` / 2 and / 1 steps per 1/12 s, x_ref = (4 x_fine −
    x_coarse)/3; the error estimate max |x_fine − x_coarse|/3 is the fine run's own error, which the
    extrapolation only reduces (conservative). "implicit_euler" (first order): runs at `finest_steps`
    / 4, / 2 and / 1, extrapolated pairwise (2 x(h/2) − x(h)); the finer extrapolation is x_ref and a
    third of the two extrapolations' largest difference its error, as theirs fall by 4× per halving."""
    order = INTEGRATOR_ORDER[integrator]
    # a second-order method needs one extrapolation, and one pair of runs; implicit Euler two of each
    divisors = (2, 1) if order == 2 else (4, 2, 1)
    if finest_steps % divisors[0]:
        raise ValueError(
            f"--reference-steps must be a multiple of {divisors[0]} for {integrator}, got {finest_steps}"
        )
    solver = es.NewtonCG(tol=REFERENCE_TOL, max_iter=100, direct_max_dofs=direct_max_dofs)
    runs = []
    for divisor in divisors:
        run = energysim_trajectory(scene, finest_steps // divisor, checkpoints, solver, integrator)
        if run.converged != run.steps:
            raise RuntimeError(
                f"the reference left {run.steps - run.converged} of {run.steps} steps unconverged"
            )
        runs.append(run)
    if order == 2:
        coarse, fine = runs[0].positions, runs[1].positions
        return richardson(coarse, fine, 2), float((fine - coarse).norm(dim=-1).max()) / 3.0, runs
    coarse = richardson(runs[0].positions, runs[1].positions, 1)
    fine = richardson(runs[1].positions, runs[2].positions, 1)
    return fine, float((fine - coarse).norm(dim=-1).max()) / 3.0, runs


def energysim_row(
    tets: int,
    tol: float,
    run: Trajectory,
    reference: Tensor,
    note: str = "",
    compiled: bool = False,
    repeats: int = 1,
    reuse_factorization: float | None = None,
) -> Run:
    """`run`'s line of the table (its wall time the median of `repeats` runs)."""
    error, final = errors(run.positions, reference)
    return Run(
        tets=tets,
        simulator=ENERGYSIM,
        integrator=run.integrator,
        method=f"newton-cg{' compiled' if compiled else ''}"
        + (f" reuse {reuse_factorization:g}" if reuse_factorization is not None else "")
        + f" tol {tol:g}",
        tol=tol,
        dt=CHECKPOINT_S / run.steps_per_checkpoint,
        steps_per_checkpoint=run.steps_per_checkpoint,
        wall_s_per_sim_s=run.wall_s / (run.steps / run.steps_per_checkpoint * CHECKPOINT_S),
        repeats=repeats,
        error_m=error,
        final_error_m=final,
        converged=f"{run.converged}/{run.steps}",
        ratio=math.nan,
        ratio_vbd=math.nan,
        status=status_of(error, math.inf),
        note=f"{run.iterations / run.steps:.1f} Newton iterations, {run.hvps / run.steps:.0f} HVPs per step"
        + (f"; {note}" if note else ""),
    )


def leapfrog_rows(scene: es.Scene, tets: int, reference: Tensor, args: argparse.Namespace) -> list[Run]:
    """energysim's explicit leapfrog at each of `--leapfrog-substeps` substeps per 1/12 s (one step of
    1/12 s each, compiled with `--compile`); a run that blows up is a row with status "unstable"."""
    rows = []
    for substeps in args.leapfrog_substeps:
        solver = es.NewtonCG(compile=args.compile)  # only its `compile` matters to an explicit step
        scene.substeps = substeps
        try:
            if args.compile:  # compiled before timing, as the peer's kernels are: one untimed 1/12 s
                energysim_trajectory(scene, 1, 1, solver, "leapfrog")
            timed = [
                energysim_trajectory(scene, 1, args.checkpoints, solver, "leapfrog")
                for _ in range(args.energysim_repeats)
            ]
        except es.InstabilityError as error:
            timed, failure = [], str(error).split(";")[0]
        finally:
            scene.substeps = 1
        h = CHECKPOINT_S / substeps
        method = f"leapfrog{' compiled' if args.compile else ''}"
        if not timed:
            row = replace(
                run_without_result(tets, ENERGYSIM, "unstable", failure),
                integrator="leapfrog",
                method=method,
                tol=0.0,
                dt=h,
                steps_per_checkpoint=substeps,
                error_m=math.inf,
                final_error_m=math.inf,
            )
        else:
            run = replace(timed[0], wall_s=statistics.median(r.wall_s for r in timed))
            row = replace(
                energysim_row(tets, 0.0, run, reference, repeats=len(timed)),
                method=method,
                dt=h,
                steps_per_checkpoint=substeps,
                converged="–",
                note="explicit: one gradient per substep, no solve",
            )
        rows.append(row)
        print(row, flush=True)
    return rows


def run_without_result(tets: int, simulator: str, status: str, note: str) -> Run:
    """A row for a run that produced nothing to time or measure (it blew up, or could not run)."""
    return Run(
        tets=tets,
        simulator=simulator,
        integrator="–",
        method="–",
        tol=math.nan,
        dt=math.nan,
        steps_per_checkpoint=0,
        wall_s_per_sim_s=math.nan,
        repeats=0,
        error_m=math.nan,
        final_error_m=math.nan,
        converged="–",
        ratio=math.nan,
        ratio_vbd=math.nan,
        status=status,
        note=note,
    )


def errors(positions: Tensor, reference: Tensor) -> tuple[float, float]:
    """Largest vertex distance over the shared times after t = 0, and at the last one (m); inf when
    not finite."""
    distance = (positions.to(reference.dtype) - reference)[1:].norm(dim=-1)
    if not bool(torch.isfinite(distance).all()):
        return math.inf, math.inf
    return float(distance.max()), float(distance[-1].max())


def status_of(error: float, accuracy_limit: float) -> str:
    """ "unstable" when the run blew up (not finite, or farther than `BLOWN_UP_M` from the reference),
    "inaccurate" past `accuracy_limit` (m), else "ok"."""
    if not error <= BLOWN_UP_M:
        return "unstable"
    return "inaccurate" if error > accuracy_limit else "ok"


# --- the peer: NVIDIA Warp through `newton` ----------------------------------------------------


def peer_missing() -> str | None:
    """Why the peer cannot run here (the import error), or None when warp and newton import."""
    try:
        import newton  # noqa: F401
        import warp  # noqa: F401
    except Exception as error:  # an ImportError, or a broken install that fails while importing
        return f"{type(error).__name__}: {error}"
    return None


def peer_versions() -> str:
    import newton
    import warp

    return f"warp {warp.__version__}, newton {newton.__version__}"


class PeerCantilever:
    """The cantilever as a Newton model with one solver; `trajectory` steps it from rest.

    Args:
        scene: the energysim scene whose mesh, masses and clamped vertices are copied.
        method: "semi-implicit" or "vbd".
        iterations: VBD iterations per step (ignored by the semi-implicit solver).
        poissons_ratio: ν of the material (E is `YOUNGS_MODULUS`), as in the energysim scene.
    """

    def __init__(
        self, scene: es.Scene, method: str, iterations: int = 10, poissons_ratio: float = POISSONS_RATIO
    ) -> None:
        import newton
        import warp as wp

        wp.config.quiet = True
        mu, lam = lame_parameters(torch.tensor(YOUNGS_MODULUS), torch.tensor(poissons_ratio))
        if method == "semi-implicit":
            # Newton's semi-implicit tet force is Smith et al.'s paper form with (k_mu, k_lambda) = (μ', λ')
            k_mu, k_lambda, _ = (float(p) for p in smith_parameters(mu, lam))
        elif method == "vbd":
            k_mu, k_lambda = float(mu), float(lam)  # VBD converts the Lamé parameters itself
        else:
            raise ValueError(f"method must be 'semi-implicit' or 'vbd', got {method!r}")
        builder = newton.ModelBuilder(up_axis=newton.Axis.Y, gravity=(0.0, -GRAVITY, 0.0))
        builder.add_soft_mesh(
            pos=wp.vec3(0.0, 0.0, 0.0),
            rot=wp.quat_identity(),
            scale=1.0,
            vel=wp.vec3(0.0, 0.0, 0.0),
            vertices=[wp.vec3(*v) for v in scene.mesh.vertices.tolist()],
            indices=scene.mesh.tets.reshape(-1).tolist(),
            density=DENSITY,
            k_mu=k_mu,
            k_lambda=k_lambda,
            k_damp=0.0,
            add_surface_mesh_edges=False,
        )
        for index in torch.nonzero(scene.fixed).reshape(-1).tolist():
            builder.particle_mass[index] = 0.0  # zero mass: a kinematic (clamped) particle
        if method == "vbd":
            builder.color()  # VBD sweeps the vertices colour by colour
        model = builder.finalize(device="cpu")
        # no contact in this scene: no particle–particle contact (it needs a grid and a radius)
        model.particle_grid = None
        model.particle_max_radius = 0.0
        if method == "semi-implicit":
            solver = newton.solvers.SolverSemiImplicit(model, enable_tri_contact=False)
        else:
            solver = newton.solvers.SolverVBD(
                model, iterations=iterations, particle_enable_self_contact=False
            )
        self.model, self.solver, self.method, self.iterations = model, solver, method, iterations
        self.trajectory(1, 1)  # compile (or load) the kernels before anything is timed

    def trajectory(self, steps_per_checkpoint: int, checkpoints: int) -> tuple[Tensor, float]:
        """Positions at t = 0, 1/12 s, … from rest, shape `[checkpoints + 1, n, 3]` in m (float32), and
        the wall time (s)."""
        dt = CHECKPOINT_S / steps_per_checkpoint
        current, following = self.model.state(), self.model.state()
        control = self.model.control()
        positions = [torch.from_numpy(current.particle_q.numpy().copy())]
        start = time.perf_counter()
        for _ in range(checkpoints):
            for _ in range(steps_per_checkpoint):
                current.clear_forces()
                self.solver.step(current, following, control, None, dt)
                current, following = following, current
            positions.append(torch.from_numpy(current.particle_q.numpy().copy()))  # also synchronises
        return torch.stack(positions), time.perf_counter() - start


def peer_run(
    peer: PeerCantilever,
    steps: int,
    checkpoints: int,
    reference: Tensor,
    repeats: int,
    tets: int,
    accuracy_limit: float,
) -> Run:
    """`repeats` trajectories of the peer at `steps` per 1/12 s; the median wall time per simulated second."""
    walls = []
    for _ in range(repeats):
        positions, wall = peer.trajectory(steps, checkpoints)
        walls.append(wall / (checkpoints * CHECKPOINT_S))
        error, final = errors(positions, reference)
        if status_of(error, math.inf) == "unstable":
            break  # no point in timing it again
    status = status_of(error, accuracy_limit)
    method = peer.method if peer.method == "semi-implicit" else f"vbd {peer.iterations} iterations"
    return Run(
        tets=tets,
        simulator=PEER,
        integrator="semi_implicit_euler" if peer.method == "semi-implicit" else "implicit_euler",
        method=method,
        tol=math.nan,
        dt=CHECKPOINT_S / steps,
        steps_per_checkpoint=steps,
        wall_s_per_sim_s=statistics.median(walls),
        repeats=len(walls),
        error_m=error,
        final_error_m=final,
        converged="–",
        ratio=math.nan,
        ratio_vbd=math.nan,
        status=status,
        note="",
    )


def largest_stable_step(
    peer: PeerCantilever,
    checkpoints: int,
    reference: Tensor,
    tets: int,
    start: int,
    accuracy_limit: float,
) -> tuple[int | None, list[Run]]:
    """The fewest steps per 1/12 s with a stable, accurate run: halve the count from `start` (double h)
    until a run fails, then bisect. Returns that count (None when even `start` fails) and every run."""
    trace, good, bad = [], None, None
    steps = start
    while steps >= 1:
        run = peer_run(peer, steps, checkpoints, reference, 1, tets, accuracy_limit)
        trace.append(run)
        if run.status != "ok":
            bad = steps
            break
        good = steps
        steps //= 2
    if good is None or bad is None:
        return good, trace
    while good - bad > 1:
        middle = (good + bad) // 2
        run = peer_run(peer, middle, checkpoints, reference, 1, tets, accuracy_limit)
        trace.append(run)
        if run.status == "ok":
            good = middle
        else:
            bad = middle
    return good, trace


# --- the benchmark -----------------------------------------------------------------------------


def with_ratios(runs: list[Run]) -> list[Run]:
    """Each energysim run with its ratios: its wall time / the fastest stable peer run with no larger
    error, of any integrator and of VBD alone (NaN where there is none)."""
    peers = [r for r in runs if r.simulator == PEER and r.status == "ok" and math.isfinite(r.error_m)]

    def ratio(run: Run, rivals: list[Run]) -> float:
        times = [p.wall_s_per_sim_s for p in rivals if p.tets == run.tets and p.error_m <= run.error_m]
        return run.wall_s_per_sim_s / min(times) if times else math.nan

    return [
        Run(
            **{
                **asdict(r),
                "ratio": ratio(r, peers),
                "ratio_vbd": ratio(r, [p for p in peers if "vbd" in p.method]),
            }
        )
        if r.simulator == ENERGYSIM
        else r
        for r in runs
    ]


def run_size(size: str, args: argparse.Namespace) -> tuple[list[Run], list[Run], dict[str, float]]:
    """All runs at one mesh size; the table's runs, the stable-step search, and the reference's numbers."""
    scene = cantilever_scene(SIZES[size], args.poissons_ratio)
    tets = scene.mesh.num_elements
    reference, estimate, reference_runs = reference_trajectory(
        scene, args.checkpoints, args.reference_steps, args.reference_integrator, args.direct_max_dofs
    )
    reference_wall = sum(run.wall_s for run in reference_runs)
    info = {"tets": tets, "dofs": scene.num_dofs, "reference_error_m": estimate, "wall_s": reference_wall}
    print(f"{size}: reference in {reference_wall:.0f} s, its error ≈ {estimate:.1e} m", flush=True)
    runs: list[Run] = []
    if "leapfrog" in args.integrators:
        runs += leapfrog_rows(scene, tets, reference, args)
    for integrator in [name for name in args.integrators if name != "leapfrog"]:
        for tol in args.tols:
            for steps in args.dts:
                solver = es.NewtonCG(
                    tol=tol,
                    direct_max_dofs=args.direct_max_dofs,
                    compile=args.compile,
                    reuse_factorization=args.reuse_factorization,
                )
                if args.compile:
                    # compiled before timing, as the peer's kernels are: one untimed 1/12 s
                    energysim_trajectory(scene, steps, 1, solver, integrator)
                timed = [
                    energysim_trajectory(scene, steps, args.checkpoints, solver, integrator)
                    for _ in range(args.energysim_repeats)
                ]
                run = replace(timed[0], wall_s=statistics.median(r.wall_s for r in timed))
                row = energysim_row(
                    tets,
                    tol,
                    run,
                    reference,
                    compiled=args.compile,
                    repeats=len(timed),
                    reuse_factorization=args.reuse_factorization,
                )
                runs.append(row)
                print(runs[-1], flush=True)
    # the reference's own runs are energysim runs too, at small h (their error: their differences)
    for run in reference_runs:
        runs.append(energysim_row(tets, REFERENCE_TOL, run, reference, "a run of the reference"))
    search: list[Run] = []
    missing = peer_missing()
    if missing is not None:
        note = f"{missing}; install with `pip install warp-lang newton`"
        runs.append(run_without_result(tets, PEER, "not installed", note))
        print(f"the peer is not installed ({missing}); only energysim ran", flush=True)
        return with_ratios(runs), search, info
    semi = PeerCantilever(scene, "semi-implicit", poissons_ratio=args.poissons_ratio)
    largest, search = largest_stable_step(
        semi, args.checkpoints, reference, tets, args.search_start, args.accuracy_limit
    )
    for run in search:
        print(run, flush=True)
    if largest is None:
        runs.append(
            Run(**{**asdict(search[-1]), "note": f"fails even at {args.search_start} steps per 1/12 s"})
        )
    else:
        # 1, 1/2 and 1/4 of the largest stable step, then finer while some energysim run is more
        # accurate than the finest so far (up to 1/`--finest-peer-fraction`): equal error, timed
        ours = [r.error_m for r in runs if r.simulator == ENERGYSIM and "reference" not in r.note]
        smallest = min((e for e in ours if math.isfinite(e)), default=math.inf)
        factor = 1
        while factor <= args.finest_peer_fraction:
            run = peer_run(semi, largest * factor, args.checkpoints, reference, args.repeats, tets, math.inf)
            note = "largest stable step" if factor == 1 else f"1/{factor} of the largest stable step"
            runs.append(Run(**{**asdict(run), "note": note}))
            print(runs[-1], flush=True)
            if factor >= 4 and not run.error_m > smallest:
                break
            factor *= 2
    for setting in args.vbd:
        steps, iterations = (int(part) for part in setting.split(":"))
        vbd = PeerCantilever(scene, "vbd", iterations, args.poissons_ratio)
        run = peer_run(vbd, steps, args.checkpoints, reference, args.repeats, tets, math.inf)
        runs.append(Run(**{**asdict(run), "note": "HOBAK neo-Hookean form"}))
        print(runs[-1], flush=True)
    return with_ratios(runs), search, info


def observed_order(runs: list[Run], tets: int, integrator: str) -> float:
    """Slope of log(error) against log(h) between the largest and the smallest h of energysim's runs with
    `integrator` at `tets` and the tightest tolerance (the reference's own runs and runs that blew up
    left out); NaN with fewer than two such runs or a non-positive error."""
    ours = [
        r
        for r in runs
        if r.tets == tets
        and r.simulator == ENERGYSIM
        and r.integrator == integrator
        and "reference" not in r.note
        and math.isfinite(r.error_m)
    ]
    if not ours:
        return math.nan
    tightest = min(r.tol for r in ours)
    tight = sorted((r for r in ours if r.tol == tightest), key=lambda r: r.dt)
    if len(tight) < 2 or not all(0 < r.error_m < math.inf for r in (tight[0], tight[-1])):
        return math.nan
    return math.log(tight[-1].error_m / tight[0].error_m) / math.log(tight[-1].dt / tight[0].dt)


def reference_text(args: argparse.Namespace) -> str:
    """How the reference was computed and checked, for the markdown."""
    steps = args.reference_steps
    if args.reference_integrator == "tr_bdf2":
        return (
            f"Reference: energysim Newton–CG at tol {REFERENCE_TOL:g} m/s with TR-BDF2 (second order) at "
            f"h = 1/{12 * steps // 2} and 1/{12 * steps} s, Richardson-extrapolated for order 2, "
            "x_ref = (4 x(h) − x(2h))/3; its error is estimated conservatively as the largest "
            "|x(h) − x(2h)|/3 over vertices and times, the error of the finer run itself, which the "
            "extrapolation only reduces. It is checked by the convergence of the runs to it: implicit "
            "Euler's errors fall at first order in h, TR-BDF2's at second (observed orders under the "
            "table)."
        )
    return (
        f"Reference: energysim Newton–CG at tol {REFERENCE_TOL:g} m/s with implicit Euler, Richardson-"
        f"extrapolated for order 1 from h = 1/{12 * steps // 4}, 1/{12 * steps // 2} and 1/{12 * steps} s "
        "(2 x(h/2) − x(h) twice over); its error is a third of the two extrapolations' largest difference."
    )


def caption(args: argparse.Namespace, load: tuple[tuple[float, float, float], tuple[float, float,
    float]]) -> str:
    """What the tables measure, and on which machine and settings."""
    missing = peer_missing()
    peer = f"not installed ({missing})" if missing else peer_versions()
    seconds = args.checkpoints * CHECKPOINT_S
    integrators = " and ".join(args.integrators)
    return (
        f"Cantilever from rest for {seconds:g} s (`bench_step.build_scene`: E = 1e5 Pa, "
        f"ν = {args.poissons_ratio:g}, ρ = 1000 kg/m³), energysim (float64, Newton–CG; integrators "
        f"{integrators}) against Warp through `newton` ({peer}; float32, CPU). error = largest vertex "
        f"distance from the reference at t = 1/12, 2/12, … s. {reference_text(args)} Newton–CG solves "
        f"its linear systems directly up to {args.direct_max_dofs} DOFs (`direct_max_dofs`; "
        '`direct="auto"` picks dense Cholesky, the band Cholesky or the block-tridiagonal level solve), '
        "by CG above. "
        + (
            "energysim's runs (not the reference's) evaluate the objective by compiled functions "
            "(`compile=True`, which takes the band solve), compiled in an untimed 1/12 s before each "
            "timed run. "
            if args.compile
            else ""
        )
        + (
            f"Newton–CG keeps its band factorisations across iterations and steps while each iteration "
            f"shrinks the residual to at most {args.reuse_factorization:g} of its previous value "
            "(`reuse_factorization`, a chord method; it stops on the same tolerance). "
            if args.reuse_factorization is not None
            else ""
        )
        + "implicit_euler takes one solve per step, tr_bdf2 two (each of a shorter effective step); "
        + "leapfrog is explicit (position Verlet, `Scene.substeps` substeps per 1/12 s step, one gradient "
        + "each, no solve; its tol column is 0) and stable only below the Courant limit, so its h is "
        + "that of a substep; a run that blew up is listed as unstable. The peer runs at 1, 1/2 and 1/4 "
        + "of its largest stable step, then finer until its error is no larger than energysim's "
        + "smallest. "
        f"Wall time per simulated second: median of {args.repeats} runs for the peer, "
        + (f"of {args.energysim_repeats} runs" if args.energysim_repeats > 1 else "one run")
        + " for energysim. ratio = energysim's wall time / the fastest stable peer run whose error is "
        "at most energysim's (> 1: energysim is slower); ratio VBD: the same against the peer's implicit "
        f"integrator alone. torch threads {args.threads}, OMP_WAIT_POLICY "
        f"{os.environ.get('OMP_WAIT_POLICY', 'unset')}; Warp runs its CPU kernels on one thread. A shared "
        f"2-core machine: load average {load[0][0]:.1f} at the start, {load[1][0]:.1f} at the end; treat "
        "times as noisy."
    )


def verdicts(runs: list[Run], tets: int, integrator: str) -> list[str]:
    """energysim's best settings with `integrator` at `tets`: against any peer run, against VBD alone,
    and at the error of the peer's largest stable step."""
    peer = [r for r in runs if r.tets == tets and r.note == "largest stable step" and r.status == "ok"]
    ours = [r for r in runs if r.tets == tets and r.simulator == ENERGYSIM and r.integrator == integrator]
    lines = ["", f"**{integrator}** ({tets} tets):"]
    best = [r for r in ours if math.isfinite(r.ratio)]
    if best:
        winner = min(best, key=lambda r: r.ratio)
        lines.append(
            f"energysim's best setting by this measure: {winner.method} at h = {winner.dt:.3g} s, "
            f"{winner.wall_s_per_sim_s:.3g} s per simulated second with error "
            f"{winner.error_m:.2e} m, {winner.ratio:.3g}× the peer's time at equal or smaller error."
        )
    against_vbd = [r for r in ours if math.isfinite(r.ratio_vbd)]
    if against_vbd:
        winner = min(against_vbd, key=lambda r: r.ratio_vbd)
        lines.append(
            f"Against the peer's implicit integrator (VBD) alone, energysim's best is "
            f"{winner.method} at h = {winner.dt:.3g} s: {winner.ratio_vbd:.3g}× the fastest VBD "
            "run with no smaller error (< 1: energysim is faster)."
        )
    if peer:
        matched = [r for r in ours if r.error_m <= peer[0].error_m]
        if matched:
            cheapest = min(matched, key=lambda r: r.wall_s_per_sim_s)
            lines.append(
                f"At the peer's error at its largest stable step ({peer[0].error_m:.2e} m, "
                f"{peer[0].wall_s_per_sim_s:.3g} s per simulated second), energysim's cheapest "
                f"run with no larger error is {cheapest.method} at h = {cheapest.dt:.3g} s: "
                f"{cheapest.wall_s_per_sim_s:.3g} s per simulated second, "
                f"{cheapest.wall_s_per_sim_s / peer[0].wall_s_per_sim_s:.3g}× the peer's."
            )
        else:
            lines.append(
                "No energysim run reached the peer's error at its largest stable step "
                f"({peer[0].error_m:.2e} m)."
            )
    return lines


def markdown(
    runs: list[Run],
    search: list[Run],
    references: list[dict[str, float]],
    args: argparse.Namespace,
    load: tuple[tuple[float, float, float], tuple[float, float, float]],
) -> str:
    """The results as markdown tables."""
    lines = [caption(args, load), ""]
    for ref in references:
        lines.append(
            f"- {ref['tets']} tets ({ref['dofs']} DOFs): the reference's error ≤ "
            f"{ref['reference_error_m']:.1e} m (estimated as above); {ref['wall_s']:.0f} s to compute. "
            f"Its runs are in the table too (tol {REFERENCE_TOL:g}): their errors are their distances "
            "from the extrapolation."
        )
    header = ["tets", "simulator", "integrator", "method", "h (s)", "wall s / simulated s", "error (m)",
              "final error (m)", "converged", "ratio", "ratio VBD", "status", "note"]
    lines += ["", *table(header, [
        [r.tets, r.simulator, r.integrator, r.method, f"{r.dt:.3g}", f"{r.wall_s_per_sim_s:.3g}",
         f"{r.error_m:.2e}", f"{r.final_error_m:.2e}", r.converged, f"{r.ratio:.3g}", f"{r.ratio_vbd:.3g}",
         r.status, r.note]
        for r in runs
    ], align="rlll" + "r" * 7 + "ll")]
    for tets in dict.fromkeys(r.tets for r in runs):
        orders = []
        for integrator in args.integrators:
            lines += verdicts(runs, tets, integrator)
            order = observed_order(runs, tets, integrator)
            if math.isfinite(order):
                orders.append(f"{integrator} {order:.2f} (expected {INTEGRATOR_ORDER[integrator]})")
        if orders:
            lines += [
                "",
                f"Observed order of convergence to the reference ({tets} tets; tightest tolerance, "
                "largest against smallest h): " + ", ".join(orders) + ".",
            ]
    if search:
        lines += [
            "",
            f"The peer's largest stable step (semi-implicit): halve the steps per 1/12 s from "
            f"{args.search_start} until a run blows up or its error exceeds {args.accuracy_limit:g} m, "
            "then bisect, in this order:",
            "",
            *table(["tets", "steps per 1/12 s", "h (s)", "error (m)", "status"], [
                [r.tets, r.steps_per_checkpoint, f"{r.dt:.3g}", f"{r.error_m:.2e}", r.status] for r in search
            ], align="rrrrl"),
        ]
    return "\n".join(lines) + "\n"


def plot(runs: list[Run], path: Path) -> None:
    """Error against wall time per simulated second, one line per simulator, integrator and method."""
    plt = pyplot()
    figure, ax = plt.subplots(figsize=(7, 5))
    for key in dict.fromkeys((r.tets, r.simulator, r.integrator, r.method) for r in runs):
        mine = [
            r
            for r in runs
            if (r.tets, r.simulator, r.integrator, r.method) == key
            and math.isfinite(r.error_m)
            and math.isfinite(r.wall_s_per_sim_s)
        ]
        if mine:
            mine.sort(key=lambda r: r.dt)
            tets, simulator, integrator, method = key
            # energysim: solid for implicit Euler, dash-dotted for TR-BDF2; the peer dashed
            style = {"implicit_euler": "o-", "tr_bdf2": "^-."}.get(integrator, "o-")
            ax.loglog(
                [r.wall_s_per_sim_s for r in mine],
                [max(r.error_m, 1e-9) for r in mine],
                style if simulator == ENERGYSIM else "s--",
                label=f"{simulator} {integrator} {method} ({tets} tets)"
                if simulator == ENERGYSIM
                else f"{simulator} {method} ({tets} tets)",
            )
    ax.set(
        xlabel="wall time per simulated second (s)",
        ylabel="largest vertex error (m)",
        title="Cantilever: work against precision",
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    figure.tight_layout()
    save_figure(figure, path)


def check(runs: list[Run]) -> None:
    """Physical sense: each integrator's error shrinks at its order in h (implicit Euler ≈ 1, TR-BDF2
    ≈ 2), which also checks the reference; the peer's runs at its largest stable step are stable."""
    # TR-BDF2's coarse steps are pre-asymptotic on short runs (over 1/6 s its order is 1.4 from h = 1/24
    # to 1/48 s and 1.8 from 1/120 to 1/240 s), so its lower bound only asks for clearly above first order
    bounds = {1: (0.7, 1.3), 2: (1.3, 2.6)}
    for tets in dict.fromkeys(r.tets for r in runs):
        for integrator in dict.fromkeys(r.integrator for r in runs if r.simulator == ENERGYSIM):
            order = observed_order(runs, tets, integrator)
            expected = INTEGRATOR_ORDER[integrator]
            low, high = bounds[expected]
            assert not math.isfinite(order) or low < order < high, (
                f"{integrator}'s observed order is {order:.2f} at {tets} tets, not ≈ {expected}"
            )
        largest = [r for r in runs if r.tets == tets and r.note.startswith("largest stable step")]
        for r in largest:
            assert r.status == "ok", f"the peer's largest stable step is {r.status} on its timed run"


def poissons_ratio(text: str) -> float:
    """ν from the command line: it must lie in (−1, 0.5) for λ to be finite and positive-definite."""
    value = float(text)
    if not -1.0 < value < 0.5:
        raise argparse.ArgumentTypeError(f"Poisson's ratio must lie in (-1, 0.5), got {text}")
    return value


def main(argv: list[str] | None = None) -> list[Run]:
    """Run the benchmark; write CSV, markdown and plot to `--out`; return every run."""
    parser = make_parser(__doc__, "bench_peers", threads=2)
    parser.add_argument("--sizes", nargs="+", default=["1k"], choices=list(SIZES))
    parser.add_argument("--checkpoints", type=int, default=12, help="simulated time in units of 1/12 s")
    parser.add_argument(
        "--dts",
        nargs="+",
        type=int,
        default=list(DEFAULT_DTS),
        help="energysim steps per 1/12 s (2: h = 1/24 s)",
    )
    parser.add_argument("--tols", nargs="+", type=float, default=list(DEFAULT_TOLS), help="m/s")
    parser.add_argument(
        "--integrators",
        nargs="+",
        choices=list(es.INTEGRATORS),
        default=list(es.INTEGRATORS),
        help="energysim's time integrators; every h and tolerance runs with each implicit one, and "
        "leapfrog at each of --leapfrog-substeps",
    )
    parser.add_argument(
        "--leapfrog-substeps",
        nargs="+",
        type=int,
        default=list(DEFAULT_LEAPFROG_SUBSTEPS),
        help="explicit leapfrog substeps per 1/12 s (28: h = 2.98 ms, its Courant limit is 3.0 ms)",
    )
    parser.add_argument(
        "--finest-peer-fraction",
        type=int,
        default=64,
        help="after 1, 1/2 and 1/4 of its largest stable step, the peer runs at finer steps (halving) "
        "until its error is no larger than energysim's smallest, down to 1/this of that step",
    )
    parser.add_argument(
        "--reference-integrator",
        choices=list(INTEGRATOR_ORDER),
        default="tr_bdf2",
        help="tr_bdf2: two runs, extrapolated for order 2; implicit_euler: three runs, for order 1",
    )
    parser.add_argument(
        "--reference-steps",
        type=int,
        default=None,
        help="steps per 1/12 s of the finest reference run (default 160 for tr_bdf2, even; 320 for "
        "implicit_euler, a multiple of 4)",
    )
    parser.add_argument(
        "--direct-max-dofs",
        type=int,
        default=DEFAULT_DIRECT_MAX_DOFS,
        help="Newton–CG solves systems of at most this many DOFs directly, larger ones by CG (0: CG only)",
    )
    parser.add_argument(
        "--poissons-ratio",
        type=poissons_ratio,
        default=POISSONS_RATIO,
        help="ν of both simulators' material (0.49: nearly incompressible)",
    )
    parser.add_argument(
        "--search-start", type=int, default=256, help="steps per 1/12 s to start the search at"
    )
    parser.add_argument(
        "--accuracy-limit",
        type=float,
        default=0.01,
        help="error (m) above which a peer run counts as failed in the search",
    )
    parser.add_argument(
        "--vbd",
        nargs="*",
        default=["5:10", "5:40", "20:10", "80:10"],
        help="VBD settings, steps per 1/12 s : iterations per step",
    )
    parser.add_argument(
        "--compile",
        action="store_true",
        help="energysim's runs (not the reference's) evaluate the objective by compiled functions, "
        "compiled in an untimed run of 1/12 s before each timed one",
    )
    parser.add_argument(
        "--reuse-factorization",
        type=float,
        default=None,
        metavar="RHO",
        help="energysim's Newton–CG keeps its band factorisations while each iteration shrinks the "
        "residual to at most RHO of its previous value (`NewtonCG(reuse_factorization=RHO)`; with --compile)",
    )
    parser.add_argument("--repeats", type=int, default=3, help="timed runs of each peer setting")
    parser.add_argument(
        "--energysim-repeats",
        type=int,
        default=1,
        help="timed runs of each energysim setting (the reference's runs: one)",
    )
    args = parser.parse_args(argv)
    for name in ("repeats", "energysim_repeats"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be at least 1, got {getattr(args, name)}")
    if args.reuse_factorization is not None and not (0 < args.reuse_factorization < 1 and args.compile):
        parser.error("--reuse-factorization needs --compile and a value in (0, 1)")
    if args.reference_steps is None:
        args.reference_steps = DEFAULT_REFERENCE_STEPS[args.reference_integrator]
    configure_threads(args.threads, retain_memory=False)
    load_start = os.getloadavg()
    runs, search, references = [], [], []
    for size in args.sizes:
        size_runs, size_search, info = run_size(size, args)
        runs += size_runs
        search += size_search
        references.append(info)
    text = markdown(runs, search, references, args, (load_start, os.getloadavg()))
    print(text)
    write_outputs(args.out, "bench_peers", runs, text, None if args.no_plot else lambda path: plot(runs,
        path))
    if search:
        write_csv(args.out / "bench_peers_search.csv", search)
    check(runs)
    return runs


if __name__ == "__main__":
    main()
