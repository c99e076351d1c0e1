"""The scaling and peer benchmarks: their fits and references are right, and their tiny runs make sense."""

from __future__ import annotations

import csv
import math
import sys
from pathlib import Path

import pytest
import torch

import energysim as es
from energysim.fem.materials import lame_parameters, smith_parameters

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))

import bench_peers  # noqa: E402
import bench_scaling  # noqa: E402

H = 1 / 60  # the scaling benchmark's step, s


def test_loglog_slope_recovers_the_exponent_of_a_power_law():
    tets = [3750.0, 10290.0, 30000.0, 101250.0]
    assert bench_scaling.loglog_slope(tets, [3.0 * t**1.1 for t in tets]) == pytest.approx(1.1, abs=1e-12)
    assert bench_scaling.loglog_slope(tets, [7.0 for _ in tets]) == pytest.approx(0.0, abs=1e-12)
    # noise of ±10 % alternating in sign about a slope-1 law: the least-squares slope stays near 1
    noisy = [t * (1.1 if k % 2 else 0.9) for k, t in enumerate(tets)]
    assert bench_scaling.loglog_slope(tets, noisy) == pytest.approx(1.0, abs=0.1)


def test_loglog_slope_skips_failed_points_and_needs_two():
    tets = [1000.0, 3000.0, 10000.0]
    assert bench_scaling.loglog_slope(tets, [2.0, math.nan, 20.0]) == pytest.approx(1.0)
    assert math.isnan(bench_scaling.loglog_slope(tets, [2.0, math.nan, -1.0]))
    assert math.isnan(bench_scaling.loglog_slope([5.0, 5.0], [1.0, 2.0]))


def test_slopes_fit_only_the_sizes_from_the_threshold():
    def row(tets: int, ms: float, cpu_ms: float, mb: float) -> bench_scaling.Row:
        return bench_scaling.Row(
            tets, "newton-cg", 1, 3, ms, cpu_ms, 3, 4, 50, 1e-6, "3/3", 1e-9, mb, mb, "ok"
        )

    # the smallest mesh is all overhead; from 3k on, wall time ∝ tets^1.2, CPU time ∝ tets^1.1 and
    # memory ∝ tets
    rows = [row(810, 500.0, 400.0, 50.0)]
    rows += [row(t, 1e-3 * t**1.2, 2e-3 * t**1.1, 1e-2 * t) for t in (3750, 10290, 30000)]
    (fit,) = bench_scaling.slopes(rows, fit_min_tets=2500)
    assert fit["sizes"] == 3
    assert fit["time_slope"] == pytest.approx(1.2)
    assert fit["cpu_time_slope"] == pytest.approx(1.1)
    assert fit["memory_slope"] == pytest.approx(1.0)


def test_richardson_cancels_the_leading_error_term_of_either_order():
    exact = torch.tensor([[0.3, -1.2, 2.0]], dtype=torch.float64)
    for order in (1, 2):
        h = 0.01
        coarse, fine = exact + 5.0 * (2 * h) ** order, exact + 5.0 * h**order
        assert torch.allclose(bench_peers.richardson(coarse, fine, order), exact, atol=1e-14, rtol=0)


def free_fall(mesh: es.TetMesh, checkpoints: int) -> torch.Tensor:
    """The rest positions in free fall from rest (g = 9.81 m/s²) at t = 0, 1/12, … s: `[C + 1, n, 3]`."""
    times = torch.arange(checkpoints + 1, dtype=torch.float64) * bench_peers.CHECKPOINT_S
    fall = torch.tensor([0.0, 9.81, 0.0], dtype=torch.float64) * times[:, None, None] ** 2 / 2
    return mesh.vertices[None] - fall


def test_richardson_reference_is_exact_for_free_fall():
    # implicit Euler's free fall is x_n = x_0 − g h² n(n+1)/2: its error −g h t/2 is exactly linear in h,
    # so the extrapolation must give the exact x_0 − g t²/2
    mesh = es.TetMesh.box(size=(0.2, 0.2, 0.2), cells=(1, 1, 1))
    scene = es.Scene(mesh, density=1000.0, gravity=(0.0, -9.81, 0.0))
    reference, estimate, runs = bench_peers.reference_trajectory(
        scene, checkpoints=2, finest_steps=8, integrator="implicit_euler"
    )
    assert [run.integrator for run in runs] == ["implicit_euler"] * 3
    exact = free_fall(mesh, checkpoints=2)
    assert float((reference - exact).abs().max()) < 1e-9
    assert estimate < 1e-9
    # and each run's error is g h t / 2, largest at the last time t = 2/12 s
    for run in runs:
        h = bench_peers.CHECKPOINT_S / run.steps_per_checkpoint
        error, final = bench_peers.errors(run.positions, reference)
        assert error == final == pytest.approx(9.81 * h * 2 * bench_peers.CHECKPOINT_S / 2, rel=1e-6)


def test_tr_bdf2_reference_is_exact_for_free_fall_and_its_runs_too():
    # TR-BDF2 is second order: both its stages integrate a constant acceleration exactly, so each run,
    # the extrapolation and the error estimate (their difference) are exact up to rounding
    mesh = es.TetMesh.box(size=(0.2, 0.2, 0.2), cells=(1, 1, 1))
    scene = es.Scene(mesh, density=1000.0, gravity=(0.0, -9.81, 0.0))
    reference, estimate, runs = bench_peers.reference_trajectory(scene, checkpoints=2, finest_steps=8)
    assert [(run.integrator, run.steps_per_checkpoint) for run in runs] == [("tr_bdf2", 4), ("tr_bdf2", 8)]
    exact = free_fall(mesh, checkpoints=2)
    assert float((reference - exact).abs().max()) < 1e-9
    assert estimate < 1e-9
    for run in runs:
        assert float((run.positions - exact).abs().max()) < 1e-9
    with pytest.raises(ValueError, match="multiple of 2"):
        bench_peers.reference_trajectory(scene, checkpoints=1, finest_steps=5)


def test_poissons_ratio_reaches_the_energysim_material():
    scene = bench_peers.cantilever_scene(bench_peers.SIZES["tiny"], 0.49)
    (material,) = [term for term in scene.terms if isinstance(term, es.NeoHookean)]
    assert float(material.poissons_ratio) == pytest.approx(0.49)
    assert float(material.youngs_modulus) == bench_peers.YOUNGS_MODULUS


@pytest.mark.heavy
def test_bench_scaling_tiny_run_is_accurate_and_measures_memory(tmp_path):
    rows = bench_scaling.main(
        [
            "--sizes",
            "tiny",
            "--steps",
            "2",
            "--warmup",
            "2",
            "--threads",
            "1",
            "--no-plot",
            "--out",
            str(tmp_path),
        ]
    )
    by_solver = {row.solver: row for row in rows}
    assert set(by_solver) == {"newton-cg", "lbfgs"}
    newton = by_solver["newton-cg"]
    assert newton.status == "ok" and newton.converged == "2/2"
    # a residual r (m/s) leaves a position error of about h·r at most
    assert newton.error_m < 10 * H * bench_scaling.TOL
    lbfgs = by_solver["lbfgs"]
    assert (
        lbfgs.error_m < 10 * H * bench_scaling.TOL
        if lbfgs.converged == "2/2"
        else math.isfinite(lbfgs.error_m)
    )
    for row in rows:
        assert row.ms_per_step > 0 and row.cpu_ms_per_step > 0
        # growth over an idle process that imported the same modules: small for 36 tets, never negative
        assert -5.0 < row.scene_mb <= row.peak_mb + 1.0 < 500.0
    with open(tmp_path / "bench_scaling.csv") as handle:
        assert len(list(csv.DictReader(handle))) == 2
    assert "time slope" in (tmp_path / "bench_scaling.md").read_text()


@pytest.mark.heavy
def test_bench_peers_runs_energysim_alone_and_says_the_peer_is_missing(tmp_path, monkeypatch):
    monkeypatch.setattr(bench_peers, "peer_missing", lambda: "ModuleNotFoundError: No module named 'newton'")
    runs = bench_peers.main(
        ["--sizes", "tiny", "--checkpoints", "3", "--reference-steps", "40", "--dts", "2", "4"]
        + ["--tols", "1e-6", "--threads", "1", "--no-plot", "--out", str(tmp_path)]
        + ["--leapfrog-substeps", "6", "16", "32"]
    )

    def ours(integrator: str) -> list[bench_peers.Run]:
        return sorted(
            (
                r
                for r in runs
                if r.simulator == bench_peers.ENERGYSIM and r.integrator == integrator and r.tol == 1e-6
            ),
            key=lambda r: -r.dt,
        )

    euler, tr_bdf2 = ours("implicit_euler"), ours("tr_bdf2")
    assert len(euler) == len(tr_bdf2) == 2
    (note,) = [r for r in runs if r.simulator == bench_peers.PEER]
    assert note.status == "not installed" and "newton" in note.note
    for r in euler + tr_bdf2:
        assert r.converged == f"{r.steps_per_checkpoint * 3}/{r.steps_per_checkpoint * 3}"
    # against the extrapolated TR-BDF2 reference, halving h halves implicit Euler's error (first order)
    # and quarters TR-BDF2's (second order): the reference converges where both say it should
    assert euler[0].error_m / euler[1].error_m == pytest.approx(2.0, rel=0.25)
    assert tr_bdf2[0].error_m / tr_bdf2[1].error_m == pytest.approx(4.0, rel=0.3)
    # implicit Euler's free-fall part alone is g h t / 2 at t = 1/4 s; bending adds to it, not orders of
    # magnitude
    assert 0.2 < euler[0].error_m / (9.81 * euler[0].dt * 0.25 / 2) < 5.0
    # the reference's own runs are TR-BDF2 at 20 and 40 steps per 1/12 s, tol 1e-9
    reference = [r for r in runs if "a run of the reference" in r.note]
    assert [(r.integrator, r.steps_per_checkpoint, r.tol) for r in reference] == [
        ("tr_bdf2", 20, bench_peers.REFERENCE_TOL),
        ("tr_bdf2", 40, bench_peers.REFERENCE_TOL),
    ]
    # the explicit leapfrog: h = 13.9 ms is past the tiny beam's Courant limit (10.0 ms at rest) and
    # is reported as a failed row, not dropped; below it the error falls at second order
    blown, *leapfrog = sorted(
        (r for r in runs if r.integrator == "leapfrog"), key=lambda r: r.steps_per_checkpoint
    )
    assert blown.status == "unstable" and "blew up" in blown.note and blown.dt == pytest.approx(1 / 72)
    assert [r.status for r in leapfrog] == ["ok", "ok"]
    assert leapfrog[0].error_m / leapfrog[1].error_m == pytest.approx(4.0, rel=0.3)
    table = (tmp_path / "bench_peers.md").read_text()
    assert "not installed" in table and "Richardson-extrapolated for order 2" in table
    assert "Observed order" in table and "implicit_euler" in table and "tr_bdf2" in table
    assert "leapfrog 2." in table or "leapfrog 1.9" in table  # its observed order
    with open(tmp_path / "bench_peers.csv") as handle:
        integrators = {row["integrator"] for row in csv.DictReader(handle)}
    assert integrators == {"implicit_euler", "tr_bdf2", "leapfrog", "–"}


@pytest.mark.heavy
def test_bench_peers_finds_a_stable_accurate_step_for_the_peer(tmp_path):
    pytest.importorskip("newton")
    runs = bench_peers.main(
        ["--sizes", "tiny", "--checkpoints", "3", "--reference-steps", "40", "--dts", "2", "--tols", "1e-5"]
        + ["--leapfrog-substeps", "16"]
        + [
            "--search-start",
            "64",
            "--vbd",
            "--repeats",
            "1",
            "--threads",
            "1",
            "--no-plot",
            "--out",
            str(tmp_path),
        ]
    )
    peer = {r.note.split(";")[0]: r for r in runs if r.simulator == bench_peers.PEER}
    integrators = {r.integrator for r in runs if r.simulator == bench_peers.ENERGYSIM}
    assert integrators == {"implicit_euler", "tr_bdf2", "leapfrog"}
    largest = peer["largest stable step"]
    assert largest.status == "ok" and largest.error_m <= 0.01
    # the semi-implicit (symplectic) Euler integrator is first order too
    assert largest.error_m / peer["1/4 of the largest stable step"].error_m == pytest.approx(4.0, rel=0.3)
    with open(tmp_path / "bench_peers_search.csv") as handle:
        search = list(csv.DictReader(handle))
    assert search[0]["status"] == "ok" and any(row["status"] != "ok" for row in search)
    # the headlines come per integrator, each against the peer's largest stable step
    table = (tmp_path / "bench_peers.md").read_text()
    assert (
        table.count("At the peer's error at its largest stable step")
        + table.count("No energysim run reached the peer's error")
        == 3
    )


def test_poissons_ratio_reaches_the_peer_material():
    pytest.importorskip("newton")
    scene = bench_peers.cantilever_scene(bench_peers.SIZES["tiny"], 0.49)
    mu, lam = lame_parameters(torch.tensor(bench_peers.YOUNGS_MODULUS), torch.tensor(0.49))
    k_mu, k_lambda, _ = (float(p) for p in smith_parameters(mu, lam))
    peer = bench_peers.PeerCantilever(scene, "semi-implicit", poissons_ratio=0.49)
    materials = peer.model.tet_materials.numpy()
    assert materials[:, 0] == pytest.approx(k_mu, rel=1e-6)
    assert materials[:, 1] == pytest.approx(k_lambda, rel=1e-6)


@pytest.mark.parametrize(
    "flags", [["--reuse-factorization", "0.5"], ["--compile", "--reuse-factorization", "1.5"]]
)
def test_bench_peers_refuses_reuse_without_compile_or_outside_zero_one(flags):
    # kept factorisations exist only on the compiled band path, and ρ is a contraction fraction
    with pytest.raises(SystemExit) as refused:
        bench_peers.main(flags)
    assert refused.value.code == 2
