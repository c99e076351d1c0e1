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
def test_bench_step_landing_never_penetrates_and_pays_nothing_without_obstacles(tmp_path):
    rows = bench_step.main(
        [
            "--scenes",
            "landing",
            "--sizes",
            "tiny",
            "--landing-steps",
            "3",
            "--landing-repeats",
            "1",
            "--solvers",
            "newton-cg",
            "--no-plot",
            "--out",
            str(tmp_path),
        ]
    )
    (newton,) = rows
    assert newton.converged == "3/3"
    assert newton.min_height_m > 0.0  # it landed (below the barrier distance) without penetrating
    assert newton.min_height_m < 1e-3
    assert newton.max_iterations > 0  # the impact takes Newton iterations; the free fall before it none
    assert newton.error_m < 10 * (1 / 60) * 1e-5
    with open(tmp_path / "bench_step_landing_obstacles.csv") as handle:
        free, far, landing = list(csv.DictReader(handle))
    # no obstacle: no contact term in the step objective, no CCD
    assert "Ground" not in free["terms"] and "Friction" not in free["terms"]
    assert int(free["ccd_terms"]) == 0 and float(free["ccd_calls_per_step"]) == 0.0
    # a ground out of reach: about the same solve, CCD runs; in contact: friction joins the objective
    assert float(far["iterations"]) == pytest.approx(float(free["iterations"]), abs=1.0)
    assert float(far["ccd_calls_per_step"]) > 0
    assert "LaggedFriction" in landing["terms"] and "LaggedFriction" not in far["terms"]
    with open(tmp_path / "bench_step_landing_terms.csv") as handle:
        terms = {row["term"].split(" (")[0] for row in csv.DictReader(handle)}
    assert {"elastic", "ground barrier", "lagged friction"} <= terms
    for name in ("bench_step_landing.md", "bench_step_landing_trace.csv"):
        assert (tmp_path / name).exists()


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
