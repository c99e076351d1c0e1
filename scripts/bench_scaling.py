"""How one implicit-Euler step scales with the mesh: wall time, peak memory and error against tet count.

The scene is `bench_step`'s cantilever (1 × 0.2 × 0.2 m, clamped at x = 0, E = 1e5 Pa, ν = 0.3,
ρ = 1000 kg/m³, h = 1/60 s, float64) on meshes of about 1k, 3k, 10k, 30k and 100k tets. For each
size a reference trajectory is computed once with Newton–CG at tol 1e-10 m/s (`--warmup` steps to
bend the beam, then `--steps` more); every optimizer then takes the same steps from the reference
states, so each step's error is measured against a tight solution of that very step.

Each (size, optimizer, thread count) runs in a fresh Python process, so its peak resident set
(`resource.getrusage(...).ru_maxrss`) is its own. Memory is reported as growth over an idle
process that imported the same modules (torch, energysim) and started torch's thread pool:
"scene" after building the scene and loading the states, "peak" at the end of the timed steps.
Time is the median wall time per step and the process's CPU time per step (all its threads; on a
machine shared with other jobs it is the steadier measure, and with 1 thread it estimates the wall
time on an idle core). The table gives the log–log slopes of both times and of peak memory against
tet count, fitted by least squares over the sizes with at least `--fit-min-tets` tets (the small
sizes are dominated by per-call overhead). L-BFGS is capped by `--lbfgs-max-iter` and by `--budget`
seconds per run (after its first step); steps that stop short of the tolerance are counted as not
converged, never dropped. A run that fails (crash, out of memory) is a row with its error message.

`--profile` adds where a Newton–CG step spends its time at the largest size (cProfile, by time
spent inside each function), in a fresh process with the first thread count.

Run:  python scripts/bench_scaling.py --out docs/benchmarks                  # 1k … 100k, 2 threads
      python scripts/bench_scaling.py --threads 2 1 --omp-wait-policy PASSIVE --profile --out docs/benchmarks
      python scripts/bench_scaling.py --sizes 1k 3k --steps 2 --warmup 2       # quick
Writes: <out>/bench_scaling.csv, bench_scaling.md (the tables), bench_scaling.png, and with
--profile bench_scaling_profile.csv.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import torch

import energysim as es

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _bench import loglog_slope, make_parser, pyplot, save_figure, table, write_csv, write_outputs  # noqa: E402
from bench_step import REFERENCE_TOL, build_scene, effort, timed_steps  # noqa: E402
from bench_step import SIZES as STEP_SIZES  # noqa: E402

# cells along (x, y, z), 6 tets per cell: bench_step's meshes and the ones between them
SIZES = {
    **STEP_SIZES,
    "3k": (25, 5, 5),  # 3,750 tets
    "30k": (50, 10, 10),  # 30,000 tets
    "100k": (75, 15, 15),  # 101,250 tets
}
DEFAULT_SIZES = ["1k", "3k", "10k", "30k", "100k"]
SOLVERS = ("newton-cg", "lbfgs")
TOL = 1e-5  # m/s, velocity residual, as in bench_step
GOAL_SLOPE = 1.15  # the project's aim for the time-vs-tets slope of Newton–CG
GOAL_SECONDS_AT_100K = 2.0  # and for one Newton–CG step at 100k tets on 2 cores
SCRIPT = Path(__file__).resolve()


@dataclass(frozen=True)
class Row:
    """One (mesh, optimizer, thread count) line of the table; NaN where the run failed."""

    tets: int
    solver: str
    threads: int
    steps: int
    ms_per_step: float  # median wall time
    cpu_ms_per_step: float  # mean CPU time of the process (all its threads), robust to other jobs' load
    iterations: float  # mean per step
    grad_evals: float
    hvps: float
    residual: float  # largest velocity residual, m/s
    converged: str  # "k/n"
    error_m: float  # largest max |x_(n+1) − x_ref| over the steps, m
    scene_mb: float  # resident-set growth after building the scene, over the idle baseline
    peak_mb: float  # peak resident-set growth over the idle baseline
    status: str  # "ok", "budget" (fewer steps than asked), or the failure


def make_solver(name: str, lbfgs_max_iter: int) -> es.Solver:
    """The optimizer `name`, stopping at velocity residual `TOL`."""
    if name == "newton-cg":
        return es.NewtonCG(tol=TOL)
    if name == "lbfgs":
        return es.LBFGS(tol=TOL, max_iter=lbfgs_max_iter)
    raise ValueError(f"solver must be one of {SOLVERS}, got {name!r}")


def resident_mb() -> float:
    """Peak resident set of this process so far, in MB (Linux reports ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def start_threads(threads: int) -> None:
    """Set torch's intra-op threads and start the pool, so the baseline holds the same stacks."""
    torch.set_num_threads(threads)
    torch.ones(256, 256, dtype=torch.float64).sum(dim=0)


# --- what runs in the child processes ---------------------------------------------------------


def worker_reference(size: str, warmup: int, steps: int, path: Path) -> dict[str, object]:
    """The reference states of `size` (`warmup` steps to bend the beam, then `steps`), saved to `path`."""
    scene = build_scene(SIZES[size])
    reference = es.NewtonCG(tol=REFERENCE_TOL, max_iter=100, strict=True)
    state = scene.initial_state()
    start = time.perf_counter()
    for _ in range(warmup):
        state = es.step(scene, state, solver=reference).state
    states = [state]
    for _ in range(steps):
        states.append(es.step(scene, states[-1], solver=reference).state)
    torch.save(torch.stack(states), path)
    return {"tets": scene.mesh.num_elements, "seconds": time.perf_counter() - start}


def worker_measure(
    size: str, solver_name: str, states_path: Path, lbfgs_max_iter: int, budget_s: float
) -> dict[str, object]:
    """Time `solver_name` on the saved reference steps; the numbers of a `Row` and the raw RSS (MB)."""
    scene = build_scene(SIZES[size])
    states = list(torch.load(states_path))
    scene_rss = resident_mb()
    cpu_start = time.process_time()
    times, stats, errors, _ = timed_steps(
        scene, states, len(states) - 1, make_solver(solver_name, lbfgs_max_iter), budget_s
    )
    cpu_seconds = time.process_time() - cpu_start
    return {
        "tets": scene.mesh.num_elements,
        "steps": len(times),
        "ms_per_step": 1e3 * statistics.median(times),
        "cpu_ms_per_step": 1e3 * cpu_seconds / len(times),
        **effort(stats),
        "error_m": max(errors),
        "scene_rss_mb": scene_rss,
        "peak_rss_mb": resident_mb(),
        "asked_steps": len(states) - 1,
    }


def worker_profile(size: str, states_path: Path, top: int) -> dict[str, object]:
    """cProfile of one Newton–CG step from the last-but-one reference state: the `top` functions by
    time spent inside them (ms), with call counts and cumulative time."""
    import cProfile
    import pstats

    scene = build_scene(SIZES[size])
    states = torch.load(states_path)
    solver = make_solver("newton-cg", 1)
    es.step(scene, states[-2], solver=solver)  # first call: allocations and lazy set-up
    profiler = cProfile.Profile()
    start = time.perf_counter()
    profiler.enable()
    result = es.step(scene, states[-2], solver=solver)
    profiler.disable()
    wall = time.perf_counter() - start
    table = pstats.Stats(
        profiler
    ).stats  # (file, line, name) -> (calls, primitive, tottime, cumtime, callers)
    items = sorted(table.items(), key=lambda item: item[1][2], reverse=True)[:top]
    return {
        "tets": scene.mesh.num_elements,
        "wall_ms": 1e3 * wall,
        "summary": result.stats.summary(),
        "items": [
            {
                "function": f"{Path(file).name}:{line}({name})" if line else name,
                "calls": calls,
                "self_ms": 1e3 * self_time,
                "cumulative_ms": 1e3 * cumulative,
                "self_pct": 100.0 * self_time / wall,
            }
            for (file, line, name), (_, calls, self_time, cumulative, _) in items
        ],
    }


def worker_main(args: argparse.Namespace) -> None:
    """Run one child job and print its result as the last line of stdout (JSON)."""
    start_threads(args.threads[0])
    if args.worker == "baseline":
        result: dict[str, object] = {"peak_rss_mb": resident_mb()}
    elif args.worker == "reference":
        result = worker_reference(args.sizes[0], args.warmup, args.steps, args.states)
    elif args.worker == "measure":
        result = worker_measure(args.sizes[0], args.solvers[0], args.states, args.lbfgs_max_iter, args.budget)
    else:
        result = worker_profile(args.sizes[0], args.states, args.profile_top)
    print(json.dumps(result))


def child_environment(args: argparse.Namespace) -> dict[str, str]:
    """The environment of the timed processes: OMP_WAIT_POLICY as asked, and with `--huge-pages`
    torch's THP_MEM_ALLOC_ENABLE=1, which torch reads once, at its first allocation, so it must be
    set before the child starts. Fresh buffers of over 32 MB (element blocks at 100k tets are 115 MB)
    then fault in 2 MB pages instead of 4 kB ones: filling a fresh 115 MB buffer took 60 ms against
    8 ms for a reused one, and 17 ms with huge pages."""
    environment = dict(os.environ)
    if args.omp_wait_policy is not None:
        environment["OMP_WAIT_POLICY"] = args.omp_wait_policy
    if args.huge_pages:
        environment["THP_MEM_ALLOC_ENABLE"] = "1"
    return environment


def child(job: list[str], timeout_s: float, environment: dict[str, str]) -> dict[str, object]:
    """Run this script with `job` in a fresh interpreter with `environment`; its JSON result, or
    {"error": ...}."""
    command = [sys.executable, str(SCRIPT), *job]
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=timeout_s, env=environment)
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {timeout_s:.0f} s"}
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or [f"exit status {done.returncode}"])[-1]
        return {"error": f"exit status {done.returncode}: {last}"}
    return json.loads(done.stdout.strip().splitlines()[-1])


# --- the parent: jobs, table, plot ------------------------------------------------------------


def failed_row(tets: int, solver: str, threads: int, status: str) -> Row:
    nan = math.nan
    return Row(tets, solver, threads, 0, nan, nan, nan, nan, nan, nan, "0/0", nan, nan, nan, status)


def run(args: argparse.Namespace, folder: Path) -> tuple[list[Row], dict[str, object] | None, float]:
    """Every (size, thread count, optimizer) in its own process; rows, the profile, the baseline (MB)."""
    baselines = {}
    environment = child_environment(args)
    for threads in args.threads:
        baseline = child(["--worker", "baseline", "--threads", str(threads)], args.child_timeout, environment)
        if "error" in baseline:
            raise RuntimeError(f"the idle baseline process failed: {baseline['error']}")
        baselines[threads] = float(baseline["peak_rss_mb"])
    rows, profile = [], None
    for size in args.sizes:
        states = folder / f"reference_{size}.pt"
        common = ["--sizes", size, "--states", str(states)]
        reference = child(
            ["--worker", "reference", *common, "--warmup", str(args.warmup), "--steps", str(args.steps)]
            + ["--threads", str(max(args.threads))],
            args.child_timeout,
            environment,
        )
        tets = math.prod(SIZES[size]) * 6
        if "error" in reference:
            for threads in args.threads:
                rows += [
                    failed_row(tets, name, threads, f"no reference: {reference['error']}")
                    for name in args.solvers
                ]
            continue
        print(
            f"{size}: reference of {args.warmup} + {args.steps} steps in {reference['seconds']:.1f} s",
            flush=True,
        )
        for threads in args.threads:
            for name in args.solvers:
                job = ["--worker", "measure", *common, "--solvers", name, "--threads", str(threads)]
                job += ["--lbfgs-max-iter", str(args.lbfgs_max_iter), "--budget", str(args.budget)]
                measured = child(job, args.child_timeout, environment)
                if "error" in measured:
                    row = failed_row(tets, name, threads, str(measured["error"]))
                else:
                    asked = int(measured.pop("asked_steps"))
                    scene_rss, peak_rss = measured.pop("scene_rss_mb"), measured.pop("peak_rss_mb")
                    row = Row(
                        solver=name,
                        threads=threads,
                        scene_mb=float(scene_rss) - baselines[threads],
                        peak_mb=float(peak_rss) - baselines[threads],
                        status="ok" if measured["steps"] == asked else "budget",
                        **measured,
                    )
                rows.append(row)
                print(row, flush=True)
        if args.profile and size == args.sizes[-1]:
            profile = child(
                ["--worker", "profile", *common, "--threads", str(args.threads[0])]
                + ["--profile-top", str(args.profile_top)],
                args.child_timeout,
                environment,
            )
    return rows, profile, baselines[args.threads[0]]


def slopes(rows: list[Row], fit_min_tets: int) -> list[dict[str, object]]:
    """Log–log slopes of median time and of peak memory against tets, per optimizer and thread count."""
    fits = []
    for name, threads in dict.fromkeys((r.solver, r.threads) for r in rows):
        mine = [r for r in rows if r.solver == name and r.threads == threads and r.tets >= fit_min_tets]
        tets = [float(r.tets) for r in mine]
        fits.append(
            {
                "solver": name,
                "threads": threads,
                "sizes": len([r for r in mine if math.isfinite(r.ms_per_step)]),
                "time_slope": loglog_slope(tets, [r.ms_per_step for r in mine]),
                "cpu_time_slope": loglog_slope(tets, [r.cpu_ms_per_step for r in mine]),
                "memory_slope": loglog_slope(tets, [r.peak_mb for r in mine]),
            }
        )
    return fits


def markdown(
    rows: list[Row],
    fits: list[dict[str, object]],
    profile: dict[str, object] | None,
    baseline_mb: float,
    args: argparse.Namespace,
    load: tuple[tuple[float, float, float], tuple[float, float, float]],
) -> str:
    """The results as markdown tables."""
    lines = [
        "Cantilever step against mesh size: h = 1/60 s, float64, tol = "
        f"{TOL:g} m/s (velocity residual); `--warmup {args.warmup}` reference steps, then "
        f"{args.steps} timed steps from the reference states; error = max |x_(n+1) − x_ref| against "
        f"Newton–CG at {REFERENCE_TOL:g} m/s from the same state. Each row is a fresh process; memory "
        f"= resident-set growth over an idle process with torch and energysim imported ({baseline_mb:.0f} "
        f"MB): after building the scene, and its peak. L-BFGS: max_iter {args.lbfgs_max_iter}, at most "
        f"{args.budget:g} s of steps after the first. OMP_WAIT_POLICY "
        f"{args.omp_wait_policy or os.environ.get('OMP_WAIT_POLICY', 'unset (spin, then sleep)')}; "
        f"THP_MEM_ALLOC_ENABLE {'1 (large buffers in huge pages)' if args.huge_pages else 'unset'}. "
        "Wall times are medians on a shared 2-core machine: "
        f"load average {load[0][0]:.1f} at the start and {load[1][0]:.1f} at the end (another job's "
        "work competes for the same cores; treat times as noisy, up to a few times slower than alone). "
        "CPU ms/step = the process's CPU time (all threads) per step, mean over the steps: other jobs "
        "hardly change it, so with 1 thread it is the best estimate of the wall time on an idle core, "
        "and its slope the most trustworthy.",
        "",
    ]
    header = ["tets", "optimizer", "threads", "median ms/step", "CPU ms/step", "iterations", "grad evals",
              "HVPs", "max residual (m/s)", "converged", "max error (m)", "scene MB", "peak MB", "status"]
    lines += table(header, [
        [r.tets, r.solver, r.threads, f"{r.ms_per_step:.1f}", f"{r.cpu_ms_per_step:.1f}",
            f"{r.iterations:.1f}",
         f"{r.grad_evals:.1f}", f"{r.hvps:.1f}", f"{r.residual:.1e}", r.converged, f"{r.error_m:.1e}",
         f"{r.scene_mb:.0f}", f"{r.peak_mb:.0f}", r.status]
        for r in rows
    ], align="rl" + "r" * 11 + "l")
    lines += [
        "",
        f"Log–log slopes (least squares over the sizes with ≥ {args.fit_min_tets} tets): time ∝ tets^p. "
        f"The project aims at p ≤ {GOAL_SLOPE} and under {GOAL_SECONDS_AT_100K:g} s per Newton–CG step at "
        "100k tets on 2 cores.",
        "",
    ]
    header = ["optimizer", "threads", "sizes fitted", "wall-time slope", "CPU-time slope",
        "peak-memory slope"]
    lines += table(header, [
        [f["solver"], f["threads"], f["sizes"], f"{f['time_slope']:.2f}", f"{f['cpu_time_slope']:.2f}",
         f"{f['memory_slope']:.2f}"]
        for f in fits
    ])
    newton = [r for r in rows if r.solver == "newton-cg" and r.tets >= 100_000 and r.threads == 2]
    for r in newton:
        verdict = "meets" if r.ms_per_step < 1e3 * GOAL_SECONDS_AT_100K else "misses"
        lines += [
            "",
            f"Newton–CG at {r.tets} tets, 2 threads: {r.ms_per_step / 1e3:.2f} s per step ({verdict} "
            f"the {GOAL_SECONDS_AT_100K:g} s goal).",
        ]
    if profile is not None and "error" not in profile:
        lines += [
            "",
            f"Where one Newton–CG step spends its time at {profile['tets']} tets ({args.threads[0]} "
            f"thread{'s' * (args.threads[0] != 1)}, cProfile, {profile['wall_ms']:.0f} ms under the "
            f"profiler; {profile['summary']}). Self = time inside the function itself.",
            "",
        ]
        lines += table(["function", "calls", "self ms", "self %", "cumulative ms"], [
            [f"`{i['function']}`", i["calls"], f"{i['self_ms']:.0f}", f"{i['self_pct']:.1f}",
             f"{i['cumulative_ms']:.0f}"]
            for i in profile["items"]
        ])
    elif profile is not None:
        lines += ["", f"The profile run failed: {profile['error']}"]
    return "\n".join(lines) + "\n"


def plot(rows: list[Row], path: Path) -> None:
    """Time, peak memory and error against tets, log–log, one line per optimizer and thread count."""
    plt = pyplot()
    figure, axes = plt.subplots(1, 3, figsize=(15, 4))
    for name, threads in dict.fromkeys((r.solver, r.threads) for r in rows):
        mine = [r for r in rows if r.solver == name and r.threads == threads and math.isfinite(r.ms_per_step)]
        label = f"{name}, {threads} thread{'s' * (threads != 1)}"
        tets = [r.tets for r in mine]
        line = axes[0].loglog(tets, [r.ms_per_step for r in mine], "o-", label=f"{label}, wall")
        axes[0].loglog(
            tets, [r.cpu_ms_per_step for r in mine], "x:", color=line[0].get_color(), label=f"{label}, CPU"
        )
        axes[1].loglog(tets, [max(r.peak_mb, 1e-1) for r in mine], "o-", label=label)
        axes[2].loglog(tets, [max(r.error_m, 1e-16) for r in mine], "o-", label=label)
    if rows:
        low, high = min(r.tets for r in rows), max(r.tets for r in rows)
        newton = [r for r in rows if r.solver == "newton-cg" and math.isfinite(r.ms_per_step)]
        if newton:
            anchor = min(newton, key=lambda r: r.tets)
            axes[0].loglog(
                [low, high],
                [anchor.ms_per_step * (t / anchor.tets) ** GOAL_SLOPE for t in (low, high)],
                "k:",
                label=f"slope {GOAL_SLOPE}",
            )
    axes[0].set(xlabel="tets", ylabel="ms per step", title="Time per step (wall: median; CPU: mean)")
    axes[1].set(xlabel="tets", ylabel="peak RSS growth (MB)", title="Peak memory")
    axes[2].set(xlabel="tets", ylabel="max position error (m)", title="Error against a 1e-10 Newton step")
    for ax in axes:
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    figure.tight_layout()
    save_figure(figure, path)


def check(rows: list[Row]) -> None:
    """Physical sense of the results: converged Newton–CG steps are accurate and memory grows."""
    for r in rows:
        if r.solver == "newton-cg" and r.status == "ok":
            assert r.converged == f"{r.steps}/{r.steps}", f"Newton–CG did not converge at {r.tets} tets"
            # a residual r (m/s) leaves a position error of about h·r at most
            assert r.error_m < 10 * (1 / 60) * TOL, f"Newton–CG error {r.error_m:.1e} m at {r.tets} tets"
            assert r.peak_mb >= r.scene_mb - 1.0, "the peak cannot be below the memory after building"


def main(argv: list[str] | None = None) -> list[Row]:
    parser = make_parser(__doc__, "bench_scaling", threads=None)
    parser.add_argument("--sizes", nargs="+", default=DEFAULT_SIZES, choices=list(SIZES))
    parser.add_argument("--solvers", nargs="+", default=list(SOLVERS), choices=list(SOLVERS))
    parser.add_argument("--threads", nargs="+", type=int, default=[2], help="torch intra-op threads, each")
    parser.add_argument("--steps", type=int, default=3, help="timed steps per optimizer")
    parser.add_argument("--warmup", type=int, default=5, help="reference steps before the timed ones")
    parser.add_argument("--lbfgs-max-iter", type=int, default=1000, help="max_iter of L-BFGS")
    parser.add_argument(
        "--budget", type=float, default=120.0, help="seconds of steps per run, after the first"
    )
    parser.add_argument("--fit-min-tets", type=int, default=2500, help="smallest mesh in the slope fits")
    parser.add_argument("--child-timeout", type=float, default=1800.0, help="seconds per child process")
    parser.add_argument(
        "--omp-wait-policy",
        choices=["PASSIVE", "ACTIVE"],
        default=None,
        help="OMP_WAIT_POLICY of the timed processes (default: inherited). PASSIVE: idle threads sleep "
        "instead of spinning, which matters on a machine other jobs load",
    )
    parser.add_argument(
        "--huge-pages",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="run the timed processes with THP_MEM_ALLOC_ENABLE=1 (torch's huge-page allocation)",
    )
    parser.add_argument("--profile", action="store_true", help="profile a Newton–CG step at the largest size")
    parser.add_argument("--profile-top", type=int, default=12, help="functions listed in the profile")
    # the child processes' side (internal)
    parser.add_argument(
        "--worker", choices=["baseline", "reference", "measure", "profile"], help=argparse.SUPPRESS
    )
    parser.add_argument("--states", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker is not None:
        worker_main(args)
        return []
    load_start = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="bench_scaling_") as folder:
        rows, profile, baseline_mb = run(args, Path(folder))
    fits = slopes(rows, args.fit_min_tets)
    text = markdown(rows, fits, profile, baseline_mb, args, (load_start, os.getloadavg()))
    print(text)
    write_outputs(args.out, "bench_scaling", rows, text,
        None if args.no_plot else lambda path: plot(rows, path))
    if profile is not None and "error" not in profile:
        profiled = [{"tets": profile["tets"], **i} for i in profile["items"]]
        write_csv(args.out / "bench_scaling_profile.csv", profiled)
    check(rows)
    return rows


if __name__ == "__main__":
    main()
