"""Benchmark a user's energy term written only as a density (`es.DensityEnergy`) against built-in terms.

The scene: the cantilever beam 1 × 0.2 × 0.2 m (20 × 4 × 4 cells, 1,920 tets), clamped at x = 0,
swinging under gravity (E = 1e5 Pa, ν = 0.3, ρ = 1000 kg/m³, h = 1/60 s, float64, one thread),
stepped by Newton–CG at tol 1e-5 m/s. Configurations:

    neo-hookean                 the built-in `es.NeoHookean` alone (the baseline)
    neo-hookean + plain volume  plus ψ = k/2 (J − 1)² as a plain `es.ElementEnergy` (only `element_energy`)
    neo-hookean + volume        plus the same ψ as an `es.DensityEnergy` (only `density`)
    user neo-hookean            the stable neo-Hookean density as an `es.DensityEnergy`, alone

each eager and with `NewtonCG(compile=True)`. Every configuration takes the same number of steps from
rest, one configuration after the other at every step (interleaved, so a busy machine slows all
alike); the table gives the median ms per step after the warm-up steps, the ratio to the eager
baseline, and the error: the largest vertex distance of the final state from a tol-1e-10 reference
run of the same physics.

Run:  python scripts/bench_user_term.py --out out/bench_user_term           # 20 timed steps
      python scripts/bench_user_term.py --steps 3 --warmup 1 --no-compile   # quick
Writes: <out>/bench_user_term.csv.
"""

from __future__ import annotations

import argparse
import statistics
import time
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from _bench import write_csv

import energysim as es
from energysim.fem.kinematics import deformation_gradient
from energysim.fem.materials import lame_parameters, stable_neo_hookean_density

YOUNGS_MODULUS = 1e5
POISSONS_RATIO = 0.3
VOLUME_STIFFNESS = 1e5  # Pa, k of ψ = k/2 (J − 1)²
REFERENCE_TOL = 1e-10


def _determinant(F: torch.Tensor) -> torch.Tensor:
    # written out: torch.linalg.det of tiny matrices goes through an LU factorisation
    return (
        F[..., 0, 0] * (F[..., 1, 1] * F[..., 2, 2] - F[..., 1, 2] * F[..., 2, 1])
        - F[..., 0, 1] * (F[..., 1, 0] * F[..., 2, 2] - F[..., 1, 2] * F[..., 2, 0])
        + F[..., 0, 2] * (F[..., 1, 0] * F[..., 2, 1] - F[..., 1, 1] * F[..., 2, 0])
    )


class VolumeDensity(es.DensityEnergy):
    """ψ = k/2 (det F − 1)², written as a density."""

    def __init__(self, stiffness: float = VOLUME_STIFFNESS) -> None:
        super().__init__()
        self.register_buffer("stiffness", torch.tensor(stiffness, dtype=torch.float64))

    def density(self, F: torch.Tensor) -> torch.Tensor:
        return 0.5 * self.stiffness * (_determinant(F) - 1.0) ** 2


class PlainVolume(es.ElementEnergy):
    """The same energy as a plain `ElementEnergy`: only `element_energy`, derivatives by autograd."""

    def __init__(self, stiffness: float = VOLUME_STIFFNESS) -> None:
        super().__init__()
        self.register_buffer("stiffness", torch.tensor(stiffness, dtype=torch.float64))

    def bind(self, mesh: es.SimplexMesh, vertex_mass: torch.Tensor) -> None:
        self.register_buffer("element_vertices", mesh.elements)
        rest = mesh.vertices[mesh.elements]
        edges = (rest[:, 1:] - rest[:, :1]).transpose(-1, -2)
        self.register_buffer("rest_edge_inverse", torch.linalg.inv(edges))
        self.register_buffer("rest_volume", torch.linalg.det(edges) / 6.0)

    def element_energy(self, element_positions: torch.Tensor, action: torch.Tensor | None) -> torch.Tensor:
        F = deformation_gradient(element_positions, self.rest_edge_inverse)
        return self.rest_volume * 0.5 * self.stiffness * (_determinant(F) - 1.0) ** 2


class UserNeoHookean(es.DensityEnergy):
    """The built-in stable neo-Hookean density, written as a user's term."""

    def __init__(
        self, youngs_modulus: float = YOUNGS_MODULUS, poissons_ratio: float = POISSONS_RATIO
    ) -> None:
        super().__init__()
        mu, lam = lame_parameters(*torch.tensor([youngs_modulus, poissons_ratio], dtype=torch.float64))
        self.register_buffer("mu", mu)
        self.register_buffer("lam", lam)

    def density(self, F: torch.Tensor) -> torch.Tensor:
        return stable_neo_hookean_density(F, self.mu, self.lam)


CONFIGURATIONS: dict[str, Callable[[], list[es.EnergyTerm]]] = {
    "neo-hookean": lambda: [es.NeoHookean(YOUNGS_MODULUS, POISSONS_RATIO)],
    "neo-hookean + plain volume": lambda: [es.NeoHookean(YOUNGS_MODULUS, POISSONS_RATIO), PlainVolume()],
    "neo-hookean + volume": lambda: [es.NeoHookean(YOUNGS_MODULUS, POISSONS_RATIO), VolumeDensity()],
    "user neo-hookean": lambda: [UserNeoHookean()],
}
# configurations with the same physics share one reference run
PHYSICS = {
    "neo-hookean": "neo-hookean",
    "user neo-hookean": "neo-hookean",
    "neo-hookean + plain volume": "neo-hookean + volume",
    "neo-hookean + volume": "neo-hookean + volume",
}


def build_scene(terms: list[es.EnergyTerm], cells: tuple[int, int, int] = (20, 4, 4)) -> es.Scene:
    """The clamped beam with `terms`, float64."""
    mesh = es.TetMesh.box(size=(1.0, 0.2, 0.2), cells=cells)
    scene = es.Scene(mesh, density=1000.0, dt=1 / 60, gravity=(0.0, -9.81, 0.0))
    for term in terms:
        scene.add(term)
    scene.fix(torch.nonzero(mesh.vertices[:, 0] < 1e-9).reshape(-1))
    return scene


@dataclass(frozen=True)
class Row:
    configuration: str
    compiled: bool
    median_ms: float
    ratio: float  # to the eager built-in neo-Hookean alone
    error_m: float  # max vertex distance of the final state from the tol-1e-10 reference
    iterations: float  # mean Newton iterations per timed step


def run(
    steps: int, warmup: int, compile_too: bool, cells: tuple[int, int, int], rounds: int = 3
) -> list[Row]:
    """Time every configuration, interleaved step by step, in `rounds` rounds from rest (fresh states
    and solvers each); a row's time is the median over rounds of the round's median step. Rows in the
    order of `CONFIGURATIONS`, the error and iterations from the last round."""
    modes = [False, True] if compile_too else [False]
    keys = [(name, compiled) for name in CONFIGURATIONS for compiled in modes]
    round_medians: dict[tuple[str, bool], list[float]] = {key: [] for key in keys}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", es.ConvergenceWarning)
        # the same scenes every round: a new scene would compile anew
        runs = {key: build_scene(CONFIGURATIONS[key[0]](), cells) for key in keys}
        for _ in range(rounds):
            states = {key: scene.initial_state() for key, scene in runs.items()}
            solvers = {key: es.NewtonCG(tol=1e-5, compile=key[1]) for key in runs}
            times: dict[tuple[str, bool], list[float]] = {key: [] for key in runs}
            iterations: dict[tuple[str, bool], list[int]] = {key: [] for key in runs}
            for k in range(warmup + steps):
                for key, scene in runs.items():
                    start = time.perf_counter()
                    result = es.step(scene, states[key], solver=solvers[key])
                    elapsed = time.perf_counter() - start
                    states[key] = result.state
                    if k >= warmup:
                        times[key].append(elapsed)
                        iterations[key].append(result.stats.iterations)
            for key in keys:
                round_medians[key].append(statistics.median(times[key]))
        references = {}
        for name, make in CONFIGURATIONS.items():
            if PHYSICS[name] == name:
                scene = build_scene(make(), cells)
                state = scene.initial_state()
                for _ in range(warmup + steps):
                    state = es.step(scene, state, solver=es.NewtonCG(tol=REFERENCE_TOL)).state
                references[name] = scene.split_state(state)[0]
    baseline = statistics.median(round_medians[("neo-hookean", False)])
    rows = []
    for name, compiled in keys:
        x = runs[(name, compiled)].split_state(states[(name, compiled)])[0]
        median = statistics.median(round_medians[(name, compiled)])
        rows.append(
            Row(
                configuration=name,
                compiled=compiled,
                median_ms=1e3 * median,
                ratio=median / baseline,
                error_m=float((x - references[PHYSICS[name]]).norm(dim=-1).max()),
                iterations=statistics.mean(iterations[(name, compiled)]),
            )
        )
    return rows


def table(rows: list[Row]) -> str:
    """The rows as an aligned text table."""
    columns = (("configuration", "<28"), ("compiled", ">8"), ("ms/step", ">9"), ("ratio", ">6"))
    columns += (("error (m)", ">10"), ("iters", ">6"))
    header = " ".join(f"{name:{spec}}" for name, spec in columns)
    lines = [header]
    for row in rows:
        lines.append(
            f"{row.configuration:<28} {str(row.compiled):>8} {row.median_ms:9.1f} {row.ratio:6.2f} "
            f"{row.error_m:10.1e} {row.iterations:6.1f}"
        )
    return "\n".join(lines)


def check(rows: list[Row]) -> None:
    """Every configuration reaches its reference to the solver's tolerance over the run."""
    for row in rows:
        assert row.error_m < 1e-4, f"{row.configuration} (compiled={row.compiled}) is {row.error_m:.1e} m off"


def main(argv: list[str] | None = None) -> list[Row]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=20, help="timed steps per configuration")
    parser.add_argument("--warmup", type=int, default=5, help="untimed steps per round (compilation)")
    parser.add_argument("--rounds", type=int, default=3, help="rounds from rest; medians over rounds")
    parser.add_argument("--cells", type=int, nargs=3, default=(20, 4, 4), help="cells along x, y, z")
    parser.add_argument("--no-compile", action="store_true", help="eager configurations only")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--out", type=Path, default=None, help="folder for bench_user_term.csv")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    rows = run(args.steps, args.warmup, not args.no_compile, tuple(args.cells), args.rounds)
    print(table(rows))
    check(rows)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        write_csv(args.out / "bench_user_term.csv", [asdict(row) for row in rows])
    return rows


if __name__ == "__main__":
    main()
