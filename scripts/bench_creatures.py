"""Benchmark the walking creatures: time per step, real-time factor, distance, and the error beside them.

Each creature walks its default gait (`walk.SPECS[name]`) at its default h from rest for `--seconds`; the
same run is repeated at a 10× tighter solver tolerance as the reference, and the error is the distance
between the two final centres of mass (what the looser tolerance costs in where the creature ends up).
Timing is the wall time of each `es.step` call. The real-time factor is simulated time over the summed
step times (h / mean step time), > 1: faster than real time; the median step is shown beside it, since
steps where contact changes take several times the typical one. The default 5 s is the walking scripts'
own duration: the first second is the gait's ramp-in, cheaper than steady walking. Runs use `--threads`
intra-op threads (default 1, best for meshes this small).

Run:  python scripts/bench_creatures.py                               # every creature, 5 s each
      python scripts/bench_creatures.py --creatures worm --seconds 0.5  # quick
Writes: <out>/bench_creatures.csv, <out>/bench_creatures.md (the table) and <out>/bench_creatures.png.
"""

from __future__ import annotations

import statistics
from dataclasses import dataclass
from pathlib import Path

import torch
from _bench import configure_threads, make_parser, pyplot, save_figure, table, timed, walk_spec, write_outputs
from _locomotion import body_length, build_scene, default_gait, run

from energysim.creatures import CREATURES, load_creature

REFERENCE_FACTOR = 10.0  # the reference run's tolerance is this many times tighter
COMPILE_WARMUP = 0.5  # s of walking that compile, untimed, before a --compile run


@dataclass(frozen=True)
class Row:
    """One creature's line of the table."""

    creature: str
    elements: int
    kind: str
    dt: float
    steps: int
    ms_per_step: float
    median_ms_per_step: float
    realtime_factor: float
    iterations: float
    converged: str
    distance_m: float
    body_lengths: float
    tol: float
    error_m: float


def bench(name: str, seconds: float, tol: float | None, compile: bool = False) -> Row:
    """Walk `name` for `seconds` at `tol` (default: the script's) and at `tol` / 10; one table row.
    With `compile`, a first walk of `COMPILE_WARMUP` s compiles the objective's functions untimed."""
    spec = walk_spec(name)
    creature = load_creature(name)
    gait = default_gait(spec, creature)
    tol = spec.tol if tol is None else tol
    if compile:
        warmup = build_scene(creature, spec.dt, spec.friction, "newton-cg", tol, True)
        _, wall = timed(lambda: run(warmup, gait, COMPILE_WARMUP, progress=False))
        print(f"{name}: compiled in a {COMPILE_WARMUP:g} s warm-up walk of {wall:.1f} s wall")
    scene = build_scene(creature, spec.dt, spec.friction, "newton-cg", tol, compile)
    rollout, wall = timed(lambda: run(scene, gait, seconds, progress=False))
    reference = run(
        build_scene(creature, spec.dt, spec.friction, "newton-cg", tol / REFERENCE_FACTOR),
        gait,
        seconds,
        progress=False,
    )
    com, com_reference = rollout.history["com"], reference.history["com"]
    step_seconds = rollout.step_seconds.tolist()
    mean, median = statistics.fmean(step_seconds), statistics.median(step_seconds)
    distance = float(com[-1, 0] - com[0, 0])
    steps = len(rollout.stats)
    print(f"{name}: {steps} steps in {wall:.1f} s wall")
    return Row(
        creature=name,
        elements=scene.mesh.num_elements,
        kind="tets" if scene.dim == 3 else "triangles",
        dt=scene.dt,
        steps=steps,
        ms_per_step=1e3 * mean,
        median_ms_per_step=1e3 * median,
        realtime_factor=scene.dt / mean,
        iterations=statistics.fmean(s.iterations for s in rollout.stats),
        converged=f"{sum(s.converged for s in rollout.stats)}/{steps}",
        distance_m=distance,
        body_lengths=distance / body_length(scene),
        tol=tol,
        error_m=float((com[-1] - com_reference[-1]).norm()),
    )


def markdown(rows: list[Row], seconds: float, compile: bool = False) -> str:
    """The results as a markdown table."""
    compiled = f", compiled evaluations (untimed {COMPILE_WARMUP:g} s warm-up walk)" if compile else ""
    lines = [
        f"Walking creatures, {seconds:g} s of simulated time each from rest, float64, "
        f"{torch.get_num_threads()} thread(s), Newton–CG{compiled}; error = |final centre of mass − "
        "that of a run at "
        f"{REFERENCE_FACTOR:g}× tighter tolerance|.",
        "",
    ]
    header = ["creature", "elements", "h (s)", "mean ms/step", "median ms/step", "real-time factor",
              "iterations/step", "converged", "distance (m)", "body lengths", "tol (m/s)", "error (m)"]
    lines += table(header, [
        [r.creature, f"{r.elements} {r.kind}", f"{r.dt:.4g}", f"{r.ms_per_step:.1f}",
            f"{r.median_ms_per_step:.1f}",
         f"{r.realtime_factor:.2f}", f"{r.iterations:.1f}", r.converged, f"{r.distance_m:+.4f}",
         f"{r.body_lengths:+.3f}", f"{r.tol:.0e}", f"{r.error_m:.1e}"]
        for r in rows
    ])
    return "\n".join(lines) + "\n"


def plot(rows: list[Row], path: Path) -> None:
    """Real-time factor per creature, and error against distance travelled."""
    plt = pyplot()
    figure, axes = plt.subplots(1, 2, figsize=(10, 4))
    names = [r.creature for r in rows]
    axes[0].bar(names, [r.realtime_factor for r in rows], color="#8fb3d9")
    axes[0].axhline(1.0, color="black", linestyle="--", linewidth=1, label="real time")
    axes[0].set(ylabel="simulated s per wall s", title="Real-time factor (simulated / wall time)")
    axes[0].legend()
    axes[0].tick_params(axis="x", rotation=30)
    for r in rows:
        axes[1].loglog(abs(r.distance_m) or 1e-6, max(r.error_m, 1e-16), "o")
        axes[1].annotate(r.creature, (abs(r.distance_m) or 1e-6, max(r.error_m, 1e-16)), fontsize=8)
    axes[1].set(xlabel="|distance travelled| (m)", ylabel="final centre-of-mass error (m)", title="Error")
    axes[1].grid(True, which="both", alpha=0.3)
    figure.tight_layout()
    save_figure(figure, path)


def main(argv: list[str] | None = None) -> list[Row]:
    parser = make_parser(__doc__, "bench_creatures")
    parser.add_argument("--creatures", nargs="+", default=list(CREATURES), choices=CREATURES)
    parser.add_argument("--seconds", type=float, default=5.0, help="simulated time per creature, s")
    parser.add_argument(
        "--tol", type=float, default=None, help="velocity residual, m/s; default the script's"
    )
    parser.add_argument("--compile", action="store_true", help="compiled evaluations, compiled untimed")
    args = parser.parse_args(argv)
    configure_threads(args.threads)
    rows = [bench(name, args.seconds, args.tol, args.compile) for name in args.creatures]
    text = markdown(rows, args.seconds, args.compile)
    print(text)
    write_outputs(args.out, "bench_creatures", rows, text,
        None if args.no_plot else lambda path: plot(rows, path))
    return rows


if __name__ == "__main__":
    main()
