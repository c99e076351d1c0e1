"""The work-precision benchmark in its quick form: implicit Euler converges at first order and TR-BDF2 at
second, tighter solver tolerances give smaller solver errors, and every run (failed ones too) reaches the
CSV."""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))

import bench_work_precision  # noqa: E402


def test_quick_work_precision_converges_at_each_integrators_order_and_solver_error_follows_tolerance(
    tmp_path,
):
    threads = torch.get_num_threads()
    try:
        rows = bench_work_precision.main(
            [
                "--quick",
                "--scenes",
                "cantilever",
                "--optimizers",
                "newton-cg",
                "projected-newton",
                "lbfgs",
                "--out",
                str(tmp_path),
            ]
        )
    finally:
        torch.set_num_threads(threads)

    # halving h halves implicit Euler's error against the fine-h reference, and quarters TR-BDF2's
    orders = {}
    for integrator in ("implicit_euler", "tr_bdf2"):
        tight = bench_work_precision.time_series(rows, "cantilever", integrator)
        assert [r.status for r in tight] == ["ok", "ok"], integrator
        assert all(r.solves_per_step == (2.0 if integrator == "tr_bdf2" else 1.0) for r in tight)
        orders[integrator] = bench_work_precision.observed_order(tight)
    assert 0.7 <= orders["implicit_euler"] <= 1.3, orders
    assert orders["tr_bdf2"] > orders["implicit_euler"] + 0.5 and orders["tr_bdf2"] >= 1.6, orders
    # the reference is TR-BDF2: halving its h moves it by 3/4 of its own error c h_ref², against errors
    # of at least c (h_min² − h_ref²): ((1/120)² − (1/960)²) / (3/4 (1/960)²) = 84 for second order
    assert next(r for r in rows if r.role == "reference").integrator == "tr_bdf2"
    check = bench_work_precision.reference_check(rows, "cantilever")
    assert check["ratio"] >= 10, check

    # a tighter velocity tolerance gives a smaller solver error (against Newton–CG at 1e-9 m/s, same h
    # and integrator)
    sweep = [r for r in rows if r.role == "sweep"]
    for optimizer in ("newton-cg", "projected-newton", "lbfgs"):
        for integrator in ("implicit_euler", "tr_bdf2"):
            for dt in {r.dt for r in sweep}:
                loose, tight_run = sorted(
                    (
                        r
                        for r in sweep
                        if r.optimizer == optimizer and r.integrator == integrator and r.dt == dt
                    ),
                    key=lambda r: -r.tol,
                )
                if loose.status == tight_run.status == "ok":
                    assert tight_run.solver_error < loose.solver_error, (optimizer, integrator, dt)

    # every run is one CSV row: 2 reference runs, 2 integrators × 2 h tight runs, and 3 optimizers ×
    # 2 integrators × 2 h × 2 tolerances in the sweep; the table and both figures are written
    with open(tmp_path / "work_precision.csv") as handle:
        written = list(csv.DictReader(handle))
    assert len(written) == len(rows) == 2 + 2 * 2 + 3 * 2 * 2 * 2
    assert [(w["role"], w["optimizer"], w["integrator"], w["dt"], w["status"]) for w in written] == [
        (r.role, r.optimizer, r.integrator, r.dt, r.status) for r in rows
    ]
    table = (tmp_path / "work_precision.md").read_text()
    assert "Fastest setting" in table and "observed order" in table and "second order" in table
    for name in ("work_precision.png", "work_precision_errors.png"):
        assert (tmp_path / name).stat().st_size > 1000


def test_adam_runs_with_implicit_euler_only():
    assert bench_work_precision.integrators_for("adam", ["implicit_euler", "tr_bdf2"]) == ["implicit_euler"]
    assert bench_work_precision.integrators_for("lbfgs", ["implicit_euler", "tr_bdf2"]) == [
        "implicit_euler",
        "tr_bdf2",
    ]
