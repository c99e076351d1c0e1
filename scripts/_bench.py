"""What the benchmarks share: the command line's common flags, CPU settings, timing, stepping and output.

Every benchmark reports a time with the error of what was timed beside it, writes its rows as
``<name>.csv`` and a ``<name>.md`` table (and, with matplotlib, a ``<name>.png``), each file whole
(written to a temporary file, then renamed) or not at all.
"""

from __future__ import annotations

import argparse
import csv
import importlib
import math
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, is_dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

import energysim as es
from energysim.cpu import configure as configure_cpu

# each of `es.INTEGRATORS`' order of accuracy in h away from contact (on a step that touches an
# obstacle TR-BDF2 takes an implicit-Euler step): what the convergence checks expect
INTEGRATOR_ORDER = {"implicit_euler": 1, "tr_bdf2": 2, "leapfrog": 2}


def make_parser(
    doc: str | None, name: str, *, threads: int | None = 1, out: Path | None = None, plot: bool = True
) -> argparse.ArgumentParser:
    """The flags every benchmark takes: ``--out`` (default ``out/<name>``), with `plot` ``--no-plot``,
    and unless `threads` is None ``--threads`` (torch intra-op threads)."""
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=out or Path("out") / name, help="output folder")
    if plot:
        parser.add_argument("--no-plot", action="store_true", help="skip the PNG")
    if threads is not None:
        parser.add_argument("--threads", type=int, default=threads, help="torch intra-op threads")
    return parser


def configure_threads(threads: int | None, *, retain_memory: bool = True) -> None:
    """Torch intra-op threads (None: torch's choice) and, with `retain_memory`, glibc keeping freed
    buffers for reuse (`energysim.cpu.configure`)."""
    configure_cpu(threads, retain_memory=retain_memory)


@dataclass(frozen=True)
class Timing:
    """Wall times of repeated runs of one thing, in s: the median and the quartiles (IQR = high − low)."""

    median: float
    low: float
    high: float
    samples: int

    @property
    def iqr(self) -> float:
        """Interquartile range, s."""
        return self.high - self.low


def quartiles(values: Sequence[float]) -> Timing:
    """Median and quartiles of `values` (inclusive method: a single sample is its own quartiles)."""
    if len(values) == 0:
        raise ValueError("quartiles of no samples")
    if len(values) == 1:
        return Timing(values[0], values[0], values[0], 1)
    low, median, high = statistics.quantiles(values, n=4, method="inclusive")
    return Timing(median, low, high, len(values))


def time_call(function: Callable[[], object], *, warmup: int = 1, repeats: int = 7) -> Timing:
    """Wall time of `function()` over `repeats` calls after `warmup` untimed ones."""
    if repeats < 1 or warmup < 0:
        raise ValueError(f"need repeats >= 1 and warmup >= 0, got repeats={repeats}, warmup={warmup}")
    for _ in range(warmup):
        function()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return quartiles(times)


def median_ms(function: Callable[[], object], repeats: int = 7) -> float:
    """Median wall time of `function()` in ms, after one untimed call."""
    return 1e3 * time_call(function, repeats=repeats).median


def timed(function: Callable[[], Any]) -> tuple[Any, float]:
    """`function()` and its wall time in s."""
    start = time.perf_counter()
    result = function()
    return result, time.perf_counter() - start


@dataclass(frozen=True)
class Stepped:
    """States saved while stepping: `positions` `[F, n, d]` (m) at steps `frame_steps` `[F]` (0: the
    start), the solver's report of every step, and each `es.step` call's wall time `[S]` in s."""

    positions: Tensor
    frame_steps: Tensor
    stats: tuple[es.SolverResult, ...]
    step_seconds: Tensor


def step_through(
    scene: es.Scene,
    state: Tensor,
    steps: int,
    *,
    every: int = 1,
    action: Callable[[float], Tensor] | None = None,
    after_step: Callable[[], None] | None = None,
) -> Stepped:
    """Take `steps` steps from `state`, saving the positions every `every` steps and after the last.

    With `action`, the step to time t (s) is taken with `action(t)`; `after_step()` is called once
    before the first step and after every step (a solver wrapper counts steps with it).
    """
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    frames, saved, stats, walls = [], [], [], []

    def save(k: int, state: Tensor) -> None:
        if after_step is not None:
            after_step()
        if k % every == 0 or k == steps:
            frames.append(scene.split_state(state)[0][0])
            saved.append(k)

    save(0, state)
    for k in range(1, steps + 1):
        start = time.perf_counter()
        result = es.step(scene, state, None if action is None else action(k * scene.dt))
        walls.append(time.perf_counter() - start)
        state = result.state
        stats.append(result.stats)
        save(k, state)
    return Stepped(torch.stack(frames), torch.tensor(saved), tuple(stats), torch.tensor(walls,
        dtype=torch.float64))


def walk_spec(creature: str) -> Any:
    """The walking script's settings (`WalkSpec`) of `creature`: its gait, h and friction."""
    return importlib.import_module("walk").SPECS[creature]


def loglog_slope(x: Sequence[float], y: Sequence[float]) -> float:
    """Least-squares slope of log y against log x (the exponent p of y ∝ x^p); NaN with fewer than
    two usable points (non-finite or non-positive values are skipped)."""
    points = [
        (math.log(a), math.log(b))
        for a, b in zip(x, y, strict=True)
        if a > 0 and b > 0 and math.isfinite(a) and math.isfinite(b)
    ]
    if len(points) < 2:
        return math.nan
    mean_x = statistics.fmean(p[0] for p in points)
    mean_y = statistics.fmean(p[1] for p in points)
    spread = sum((p[0] - mean_x) ** 2 for p in points)
    if spread == 0.0:
        return math.nan
    return sum((p[0] - mean_x) * (p[1] - mean_y) for p in points) / spread


def finite(value: float) -> bool:
    """Whether `value` is neither NaN nor infinite."""
    return math.isfinite(value)


def sci(value: float, digits: int = 1) -> str:
    """`value` in scientific notation, "–" where it is not finite."""
    return f"{value:.{digits}e}" if finite(value) else "–"


def fixed(value: float, digits: int = 1) -> str:
    """`value` with `digits` decimals, "–" where it is not finite."""
    return f"{value:.{digits}f}" if finite(value) else "–"


def table(header: Sequence[str], rows: Sequence[Sequence[object]], align: str | None = None) -> list[str]:
    """A markdown table's lines; `align` has one letter per column, "l" or "r" (default: the first
    column left, the others right)."""
    align = align or "l" + "r" * (len(header) - 1)
    if len(align) != len(header):
        raise ValueError(f"align {align!r} has {len(align)} letters for {len(header)} columns")
    rule = "|" + "|".join("---" if a == "l" else "---:" for a in align) + "|"
    return ["| " + " | ".join(header) + " |",
        rule] + ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]


def pyplot() -> Any:
    """matplotlib's pyplot on the file-only Agg backend (imported here: matplotlib is optional)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(figure: Any, path: Path) -> None:
    """Save a matplotlib figure as PNG at `path` (to a temporary file, then renamed) and close it."""
    temporary = path.with_suffix(".tmp.png")
    figure.savefig(temporary, dpi=120)
    temporary.replace(path)
    pyplot().close(figure)


def write_text(path: Path, text: str) -> None:
    """`text` at `path`, written to a temporary file first."""
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text(text)
    temporary.replace(path)


def _as_dict(row: object) -> dict[str, object]:
    return asdict(row) if is_dataclass(row) else dict(row)  # type: ignore[arg-type]


def write_csv(path: Path, rows: Sequence[object]) -> None:
    """`rows` (dataclasses or dicts with the same keys) as CSV at `path`, via a temporary file."""
    if not rows:
        raise ValueError(f"no rows to write to {path}")
    records = [_as_dict(row) for row in rows]
    temporary = path.with_name(path.name + ".tmp")
    with open(temporary, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(records[0]))
        writer.writeheader()
        writer.writerows(records)
    temporary.replace(path)


def write_outputs(
    out: Path,
    name: str,
    rows: Sequence[object],
    markdown: str,
    plot: Callable[[Path], None] | None = None,
) -> list[Path]:
    """`out/<name>.csv` (one line per row), `out/<name>.md` (`markdown`) and, with `plot`,
    `plot(out/<name>.png)`; returns the paths written."""
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / f"{name}.csv", out / f"{name}.md"]
    write_csv(paths[0], rows)
    write_text(paths[1], markdown)
    if plot is not None:
        paths.append(out / f"{name}.png")
        plot(paths[2])
    return paths
