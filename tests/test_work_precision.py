"""The work-precision benchmark in its quick form: implicit Euler converges at first order, tighter solver
tolerances give smaller solver errors, and every run (failed ones too) reaches the CSV."""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))

import bench_work_precision  # noqa: E402


def test_quick_work_precision_converges_at_first_order_and_solver_error_follows_tolerance(tmp_path):
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

    # implicit Euler is first order: halving h halves the error against a fine-h reference
    tight = sorted((r for r in rows if r.role == "tight"), key=lambda r: -r.dt_s)
    assert [r.status for r in tight] == ["ok", "ok"]
    order = bench_work_precision.observed_order(tight)
    assert 0.7 <= order <= 1.3, f"observed order {order:.3f}"
    # halving the reference's h moves it by half its own error, c h_ref / 2, against errors of at least
    # c (h_min − h_ref): (1/120 − 1/960) / (1/1920) = 14 for first order
    check = bench_work_precision.reference_check(rows, "cantilever")
    assert check["ratio"] >= 10, check

    # a tighter velocity tolerance gives a smaller solver error (against Newton–CG at 1e-9 m/s, same h)
    sweep = [r for r in rows if r.role == "sweep"]
    for optimizer in ("newton-cg", "projected-newton", "lbfgs"):
        for dt in {r.dt for r in sweep}:
            loose, tight_run = sorted(
                (r for r in sweep if r.optimizer == optimizer and r.dt == dt), key=lambda r: -r.tol
            )
            if loose.status == tight_run.status == "ok":
                assert tight_run.solver_error < loose.solver_error, (optimizer, dt, loose, tight_run)

    # every run is one CSV row; the table and both figures are written
    with open(tmp_path / "work_precision.csv") as handle:
        written = list(csv.DictReader(handle))
    assert len(written) == len(rows) == 2 + 2 + 3 * 2 * 2
    assert [(w["role"], w["optimizer"], w["dt"], w["status"]) for w in written] == [
        (r.role, r.optimizer, r.dt, r.status) for r in rows
    ]
    table = (tmp_path / "work_precision.md").read_text()
    assert "Fastest setting" in table and "observed order" in table
    for name in ("work_precision.png", "work_precision_errors.png"):
        assert (tmp_path / name).stat().st_size > 1000
