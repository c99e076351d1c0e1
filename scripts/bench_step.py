"""Benchmark one implicit-Euler step: wall time *and* error, per optimizer and mesh size.

The scene: a cantilever 1 × 0.2 × 0.2 m clamped at x = 0, swinging under gravity (E = 1e5 Pa,
ν = 0.3, ρ = 1000 kg/m³, h = 1/60 s, float64). A reference trajectory is computed with
Newton–CG at tol 1e-10 m/s; every optimizer then takes the same steps from the reference
states, and each step's x_{n+1} is compared with the reference's.

Run:  python scripts/bench_step.py                       # ~1k, 10k and 50k tets
      python scripts/bench_step.py --sizes 1k --steps 3  # quick
Writes: <out>/bench_step.csv, <out>/bench_step.md (the table) and <out>/bench_step.png.
"""

from __future__ import annotations

import argparse
import csv
import statistics
import time
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

import energysim as es
from energysim.objective import Objective

# cells along (x, y, z) for about 1k, 10k and 50k tets (6 tets per cell)
SIZES = {"tiny": (6, 1, 1), "1k": (15, 3, 3), "10k": (35, 7, 7), "50k": (60, 12, 12)}
REFERENCE_TOL = 1e-10


def solvers(tol: float, first_order_iterations: int) -> dict[str, es.Solver]:
    """The optimizers compared, all stopping at the same velocity residual `tol` (m/s)."""
    return {
        "newton-cg": es.NewtonCG(tol=tol),
        "newton-cg-autograd": es.NewtonCG(tol=tol, hessian="autograd", preconditioner="none"),
        "lbfgs": es.LBFGS(tol=tol, max_iter=first_order_iterations),
        "adam": es.Adam(tol=tol, max_iter=first_order_iterations, lr=1e-4),
    }


def build_scene(cells: tuple[int, int, int]) -> es.Scene:
    """The swinging cantilever on a box mesh with `cells` cells."""
    mesh = es.TetMesh.box(size=(1.0, 0.2, 0.2), cells=cells)
    scene = es.Scene(mesh, density=1000.0, dt=1 / 60, gravity=(0.0, -9.81, 0.0))
    scene.add(es.NeoHookean(youngs_modulus=1e5, poissons_ratio=0.3))
    scene.fix(torch.nonzero(mesh.vertices[:, 0] < 1e-9).reshape(-1))
    return scene


@dataclass(frozen=True)
class Row:
    """One (mesh, optimizer) line of the table."""

    tets: int
    solver: str
    steps: int
    ms_per_step: float
    iterations: float
    grad_evals: float
    hvps: float
    residual: float
    converged: str
    error_m: float


def median_ms(function: Callable[[], object], repeats: int = 7) -> float:
    """Median wall time of `function` in ms, after one warm-up call."""
    function()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def kernel_timings(scene: es.Scene, state: torch.Tensor) -> dict[str, float]:
    """ms per energy, energy + gradient, Hessian assembly and Hessian-vector product at `state`."""
    x, _ = scene.split_state(state)
    objective = Objective(list(scene.terms), scene.free, scene.dt / scene.vertex_mass)
    operator = objective.hessian(x)
    operator.matrix(x)
    vector = torch.randn_like(x)
    autograd_operator = objective.hessian(x, use_element_blocks=False)
    return {
        "energy": median_ms(lambda: objective.energy(x)),
        "energy+gradient": median_ms(lambda: objective.energy_and_gradient(x)),
        "element Hessians + CSR assembly": median_ms(lambda: objective.hessian(x).matrix(x)),
        "HVP (assembled CSR)": median_ms(lambda: operator.matvec(vector)),
        "HVP (autograd double backward)": median_ms(lambda: autograd_operator.matvec(vector)),
    }


def run(
    size: str,
    steps: int,
    warmup: int,
    tol: float,
    names: list[str],
    first_order_iterations: int,
    budget_s: float,
) -> tuple[list[Row], dict[str, float]]:
    """Reference trajectory, then every optimizer on the same steps; rows and kernel timings."""
    scene = build_scene(SIZES[size])
    reference = es.NewtonCG(tol=REFERENCE_TOL, max_iter=100, strict=True)
    state = scene.initial_state()
    for _ in range(warmup):  # start from a swinging, bent beam, not from rest
        state = es.step(scene, state, solver=reference).state
    states = [state]
    for _ in range(steps):
        states.append(es.step(scene, states[-1], solver=reference).state)
    rows = []
    for name, solver in solvers(tol, first_order_iterations).items():
        if name not in names:
            continue
        times, stats, errors = [], [], []
        for k in range(steps):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", es.ConvergenceWarning)  # reported in the table instead
                start = time.perf_counter()
                result = es.step(scene, states[k], solver=solver)
                times.append(time.perf_counter() - start)
            stats.append(result.stats)
            x, _ = scene.split_state(result.state)
            x_ref, _ = scene.split_state(states[k + 1])
            errors.append(float((x - x_ref).abs().max()))
            if sum(times) > budget_s:  # a slow optimizer on a big mesh: fewer samples
                break
        count = len(times)
        converged = sum(s.converged for s in stats)
        rows.append(
            Row(
                tets=scene.mesh.num_elements,
                solver=name,
                steps=count,
                ms_per_step=1e3 * statistics.median(times),
                iterations=statistics.mean(s.iterations for s in stats),
                grad_evals=statistics.mean(s.grad_evals for s in stats),
                hvps=statistics.mean(s.hvp_evals for s in stats),
                residual=max(s.residual for s in stats),
                converged=f"{converged}/{count}",
                error_m=max(errors),
            )
        )
    return rows, kernel_timings(scene, states[-1])


def markdown(rows: list[Row], kernels: dict[int, dict[str, float]], tol: float) -> str:
    """The results as markdown tables."""
    lines = [
        f"Cantilever step, h = 1/60 s, float64, {torch.get_num_threads()} threads; tol = {tol:g} m/s "
        f"(velocity residual); error = max |x_(n+1) − x_ref| against Newton–CG at {REFERENCE_TOL:g} m/s.",
        "",
        "| tets | optimizer | median ms/step | iterations | grad evals | HVPs | max residual (m/s) "
        "| converged | max error (m) |",
        "|---:|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r.tets} | {r.solver} | {r.ms_per_step:.1f} | {r.iterations:.1f} | {r.grad_evals:.1f} | "
            f"{r.hvps:.1f} | {r.residual:.1e} | {r.converged} | {r.error_m:.1e} |"
        )
    lines += ["", "| tets | " + " | ".join(f"{k} (ms)" for k in next(iter(kernels.values()))) + " |"]
    lines.append("|---:|" + "---:|" * len(next(iter(kernels.values()))))
    for tets, timing in kernels.items():
        lines.append(f"| {tets} | " + " | ".join(f"{v:.2f}" for v in timing.values()) + " |")
    return "\n".join(lines) + "\n"


def plot(rows: list[Row], path: Path) -> None:
    """ms per step against tet count, one line per optimizer, log–log."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 2, figsize=(10, 4))
    for name in dict.fromkeys(r.solver for r in rows):
        mine = [r for r in rows if r.solver == name]
        axes[0].loglog([r.tets for r in mine], [r.ms_per_step for r in mine], "o-", label=name)
        axes[1].loglog([r.ms_per_step for r in mine], [max(r.error_m, 1e-16) for r in mine], "o-", label=name)
    axes[0].set(xlabel="tets", ylabel="median ms per step", title="Wall time per step")
    axes[1].set(xlabel="median ms per step", ylabel="max position error (m)", title="Error against time")
    for ax in axes:
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    figure.tight_layout()
    temporary = path.with_suffix(".tmp.png")
    figure.savefig(temporary, dpi=120)
    temporary.replace(path)
    plt.close(figure)


def main(argv: list[str] | None = None) -> list[Row]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["1k", "10k", "50k"], choices=list(SIZES))
    parser.add_argument("--solvers", nargs="+", default=list(solvers(1.0, 1)), choices=list(solvers(1.0, 1)))
    parser.add_argument("--steps", type=int, default=5, help="timed steps per optimizer")
    parser.add_argument("--warmup", type=int, default=10, help="reference steps before the timed ones")
    parser.add_argument("--tol", type=float, default=1e-5, help="velocity residual, m/s")
    parser.add_argument(
        "--first-order-iterations", type=int, default=1000, help="max_iter of Adam and L-BFGS"
    )
    parser.add_argument("--budget", type=float, default=60.0, help="seconds per optimizer and size, at most")
    parser.add_argument("--out", type=Path, default=Path("out/bench_step"))
    parser.add_argument("--no-plot", action="store_true")
    args = parser.parse_args(argv)
    rows, kernels = [], {}
    for size in args.sizes:
        size_rows, timing = run(
            size, args.steps, args.warmup, args.tol, args.solvers, args.first_order_iterations, args.budget
        )
        rows += size_rows
        kernels[size_rows[0].tets] = timing
        for row in size_rows:
            print(row)
    table = markdown(rows, kernels, args.tol)
    print(table)
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / "bench_step.csv.tmp", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(asdict(rows[0])))
        writer.writeheader()
        writer.writerows(asdict(r) for r in rows)
    (args.out / "bench_step.csv.tmp").replace(args.out / "bench_step.csv")
    (args.out / "bench_step.md.tmp").write_text(table)
    (args.out / "bench_step.md.tmp").replace(args.out / "bench_step.md")
    if not args.no_plot:
        plot(rows, args.out / "bench_step.png")
    return rows


if __name__ == "__main__":
    main()
