"""The benchmark scripts run, in a short form, and their numbers make sense (never timings)."""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))

import bench_grad  # noqa: E402
import bench_step  # noqa: E402


@pytest.mark.heavy
def test_bench_step_reports_small_errors_for_converged_solvers(tmp_path):
    rows = bench_step.main(
        [
            "--sizes",
            "tiny",
            "--steps",
            "2",
            "--warmup",
            "3",
            "--solvers",
            "newton-cg",
            "lbfgs",
            "--no-plot",
            "--out",
            str(tmp_path),
        ]
    )
    by_solver = {row.solver: row for row in rows}
    newton = by_solver["newton-cg"]
    assert newton.converged == "2/2"
    # a residual r (m/s) leaves a position error of about h·r at most
    assert newton.error_m < 10 * (1 / 60) * 1e-5
    assert (tmp_path / "bench_step.csv").exists() and (tmp_path / "bench_step.md").exists()
    with open(tmp_path / "bench_step.csv") as handle:
        assert len(list(csv.DictReader(handle))) == 2


@pytest.mark.heavy
def test_bench_grad_implicit_mode_keeps_far_less_than_the_unrolled_one(tmp_path):
    rows = bench_grad.main(
        [
            "--sizes",
            "tiny",
            "--steps",
            "1",
            "--rollout-steps",
            "3",
            "--unrolled-steps-max",
            "3",
            "--out",
            str(tmp_path),
        ]
    )
    saved = {row["mode"]: row["saved_mb"] for row in rows}
    assert saved["unrolled"] > 10 * saved["implicit"]
    assert (tmp_path / "bench_grad.md").exists()
