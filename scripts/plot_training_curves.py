"""Training curves of several runs in one figure: mean evaluation return against the env steps
simulated for training (left) and against the training wall time (right), one line per run, from
the ``curve.csv`` files the training scripts write (`_training.write_curve`).

The returns of the explicit and the implicit creature env differ by an order of magnitude, so the
return axis is linear within ±0.01 and logarithmic beyond (`_training.plot_curves`' symlog).

Run:  python scripts/plot_training_curves.py      # the three PPO runs of docs/benchmarks/policy_transfer
      python scripts/plot_training_curves.py --curve "explicit=out/a/curve.csv" \\
          --curve "implicit=out/b/curve.csv" --out out/curves.png
Writes the PNG at --out.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

from _training import CurvePoint, plot_curves, read_curve

FOLDER = Path(__file__).resolve().parents[1] / "docs" / "benchmarks" / "policy_transfer"
# the PPO runs compared in docs/training.md (label, curve file)
DEFAULT_CURVES = (
    ("explicit (leapfrog)", FOLDER / "curve_ppo_leapfrog.csv"),
    ("implicit, solved to 1e-4 m/s, ε_v = 1e-3 m/s", FOLDER / "curve_ppo_implicit.csv"),
    ("implicit, 4 Newton it./step, ε_v = 5e-3 m/s", FOLDER / "curve_ppo_implicit_budget4.csv"),
)
TITLE = "worm, PPO: explicit env vs implicit env"


def parse_curve(spec: str) -> tuple[str, Path]:
    """`LABEL=PATH` as (label, path), or ValueError naming `spec` and the form expected."""
    label, separator, path = spec.partition("=")
    if not separator or not label.strip() or not path.strip():
        raise ValueError(f"--curve must be LABEL=PATH (a non-empty label and a curve.csv), got {spec!r}")
    return label.strip(), Path(path.strip())


def load_curves(curves: Sequence[tuple[str, Path]]) -> list[CurvePoint]:
    """Every evaluation of every (label, curve.csv) of `curves`, with its `method` set to the label
    (the line `plot_curves` draws it on).

    Raises:
        ValueError: no curves, a label given twice, or a curve file without an evaluation.
        FileNotFoundError: a curve file is missing (named).
    """
    if not curves:
        raise ValueError("curves: give at least one (label, curve.csv)")
    labels = [label for label, _ in curves]
    repeated = sorted({label for label in labels if labels.count(label) > 1})
    if repeated:
        raise ValueError(f"curves: every label must be distinct, {repeated} given more than once")
    points: list[CurvePoint] = []
    for label, path in curves:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"curve {label!r}: no file at {path}")
        rows = read_curve(path)
        if not rows:
            raise ValueError(f"curve {label!r}: {path} holds no evaluation")
        points += [replace(row, method=label) for row in rows]
    return points


def run(curves: Sequence[tuple[str, Path]], out: Path, title: str = TITLE) -> list[CurvePoint]:
    """Plot `curves` (label, curve.csv) into the PNG `out` (written whole); returns the points drawn."""
    points = load_curves(curves)
    plot_curves(points, Path(out), title, symlog=True)
    return points


def check(points: Sequence[CurvePoint]) -> None:
    """What every training curve satisfies: per run, the env steps and the wall time never decrease
    from one evaluation to the next, and the first evaluation is before any training."""
    for label in dict.fromkeys(point.method for point in points):
        rows = [point for point in points if point.method == label]
        if rows[0].env_steps != 0:
            raise AssertionError(f"curve {label!r} starts at {rows[0].env_steps} env steps, not 0")
        for before, after in zip(rows, rows[1:], strict=False):
            if after.env_steps < before.env_steps or after.wall_seconds < before.wall_seconds:
                raise AssertionError(
                    f"curve {label!r} goes back in env steps or wall time: {before} → {after}"
                )


def main(argv: list[str] | None = None) -> int:
    """Command line entry point (module docstring); returns 0."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--curve", action="append", default=None, help="LABEL=PATH of a curve.csv (repeat; default: PPO runs)"
    )
    parser.add_argument("--out", type=Path, default=FOLDER / "curves.png", help="the PNG to write")
    parser.add_argument("--title", default=TITLE)
    args = parser.parse_args(argv)
    curves = [parse_curve(spec) for spec in args.curve] if args.curve else list(DEFAULT_CURVES)
    points = run(curves, args.out, args.title)
    check(points)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
