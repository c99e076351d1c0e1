"""Benchmark the differentiable step: backward against forward time, and memory over a rollout.

The scene is the swinging cantilever of `bench_step.py` (E = 1e5 Pa, ν = 0.3, ρ = 1000 kg/m³,
h = 1/60 s, float64), with its Young's modulus requiring grad. It is measured for each gradient mode:
- "implicit": the implicit-function-theorem backward, one adjoint solve per step;
- "unrolled": backward through recorded Newton iterations;
- "implicit+checkpoint": implicit, keeping tensors only every 10 steps.

Per step it reports the forward and backward wall time and their ratio. The loss is a random
weighting of the new state, and the gradient reaches the state and E. Peak memory is the
process's peak RSS over a rollout of `--rollout-steps` steps plus its backward, minus the peak
before the rollout; each rollout runs in a fresh subprocess. Where a rollout would take too
long, fewer steps are measured, and the per-step memory is scaled to the full rollout
(marked "projected").

Run:  python scripts/bench_grad.py                  # 1k and 10k tets
      python scripts/bench_grad.py --sizes tiny     # quick
Writes <out>/bench_grad.csv and <out>/bench_grad.md.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
import weakref
from pathlib import Path

import torch

import energysim as es

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _bench import make_parser, table, write_outputs  # noqa: E402
from bench_step import SIZES  # noqa: E402

MODES = ("implicit", "unrolled", "implicit+checkpoint")


def build_scene(size: str) -> tuple[es.Scene, torch.Tensor]:
    """The cantilever, with Young's modulus as a leaf that requires grad."""
    mesh = es.TetMesh.box(size=(1.0, 0.2, 0.2), cells=SIZES[size])
    scene = es.Scene(mesh, density=1000.0, dt=1 / 60, gravity=(0.0, -9.81, 0.0), solver=es.NewtonCG(tol=1e-6))
    youngs = torch.tensor(1e5, dtype=torch.float64, requires_grad=True)
    scene.add(es.NeoHookean(youngs_modulus=youngs, poissons_ratio=0.3))
    scene.fix(torch.nonzero(mesh.vertices[:, 0] < 1e-9).reshape(-1))
    return scene, youngs


def time_steps(size: str, mode: str, steps: int, warmup: int) -> dict[str, float]:
    """Median forward and backward ms of single steps taken from a swinging state."""
    scene, youngs = build_scene(size)
    with torch.no_grad():
        state = scene.initial_state()
        for _ in range(warmup):
            state = es.timestep(scene, state)
    forwards, backwards = [], []
    for _ in range(steps):
        leaf = state.detach().clone().requires_grad_(True)
        start = time.perf_counter()
        out = es.timestep(scene, leaf, grad_mode=mode)
        middle = time.perf_counter()
        torch.autograd.grad((torch.randn_like(out) * out).sum(), (leaf, youngs))
        end = time.perf_counter()
        forwards.append(middle - start)
        backwards.append(end - middle)
        state = out.detach()
    forward, backward = statistics.median(forwards), statistics.median(backwards)
    return {"forward_ms": 1e3 * forward, "backward_ms": 1e3 * backward, "ratio": backward / forward}


def peak_memory_child(size: str, mode: str, steps: int) -> None:
    """(In a subprocess) memory of a rollout and its backward, printed as JSON.

    `saved_mb`: bytes of the distinct storages that autograd saved for backward during the rollout
    and that are still alive when it ends, excluding the scene's own tensors: what the gradient
    costs in memory (tensors saved and freed inside the solver's own gradient evaluations do not
    count). `peak_mb`: the growth of the process's peak RSS, which also counts solver temporaries
    (and is coarse: the allocator keeps freed memory).
    """
    scene, youngs = build_scene(size)
    with torch.no_grad():
        state = es.timestep(scene, scene.initial_state())  # pattern caches, allocator warm
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    grad_mode = "unrolled" if mode == "unrolled" else "implicit"
    every = 10 if mode == "implicit+checkpoint" else 0
    kept: list[weakref.ref] = []
    scene_storages = {t.untyped_storage().data_ptr() for t in [*scene.buffers(), *scene.parameters(), state]}

    def pack(tensor: torch.Tensor) -> torch.Tensor:
        kept.append(weakref.ref(tensor))
        return tensor

    start = time.perf_counter()
    with torch.autograd.graph.saved_tensors_hooks(pack, lambda tensor: tensor):
        states = es.rollout(scene, state, steps=steps, checkpoint_every=every, grad_mode=grad_mode)
    alive = {}
    for reference in kept:
        tensor = reference()
        if tensor is not None:
            storage = tensor.untyped_storage()
            if storage.data_ptr() not in scene_storages:
                alive[storage.data_ptr()] = storage.nbytes()
    saved = sum(alive.values())
    states[-1].square().sum().backward()
    seconds = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({"saved_mb": saved / 2**20, "peak_mb": (after - before) / 1024, "seconds": seconds}))


def peak_memory(size: str, mode: str, steps: int) -> dict[str, float]:
    command = [sys.executable, __file__, "--memory-child", size, mode, str(steps)]
    output = subprocess.run(command, capture_output=True, text=True, check=True).stdout
    return json.loads(output.strip().splitlines()[-1])


def measure(size: str, mode: str, args: argparse.Namespace) -> dict[str, object]:
    """One table row: `mode`'s step times at `size` and its memory over the rollout (projected from
    at most `--unrolled-steps-max` steps when unrolled)."""
    timing = time_steps(size, "unrolled" if mode == "unrolled" else "implicit", args.steps, 10)
    steps = min(args.rollout_steps, args.unrolled_steps_max) if mode == "unrolled" else args.rollout_steps
    memory = peak_memory(size, mode, steps)
    scale = args.rollout_steps / steps
    return {
        "tets": build_scene(size)[0].mesh.num_elements,
        "mode": mode,
        **timing,
        "rollout_steps": args.rollout_steps,
        "measured_steps": steps,
        "saved_mb": memory["saved_mb"] * scale,
        "peak_rss_mb": memory["peak_mb"] * scale,
        "projected": steps < args.rollout_steps,
        "rollout_s": memory["seconds"],
    }


def markdown(rows: list[dict], rollout_steps: int) -> str:
    """The results as a markdown table."""
    lines = [
        f"Cantilever (bench_step scene), h = 1/60 s, float64, {torch.get_num_threads()} threads; the loss "
        f"reaches the state and Young's modulus. Memory over a {rollout_steps}-step rollout and its "
        "backward: tensors saved for backward (exact) and peak RSS growth (coarse).",
        "",
    ]
    header = ["tets", "mode", "forward ms/step", "backward ms/step", "backward / forward",
              "saved for backward (MB)", "peak RSS growth (MB)", "measured steps"]
    note = {True: " (projected)", False: ""}
    lines += table(header, [
        [r["tets"], r["mode"], f"{r['forward_ms']:.1f}", f"{r['backward_ms']:.1f}", f"{r['ratio']:.2f}",
         f"{r['saved_mb']:.1f}{note[r['projected']]}", f"{r['peak_rss_mb']:.0f}{note[r['projected']]}",
         r["measured_steps"]]
        for r in rows
    ], align="rlrrrrrr")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> list[dict]:
    parser = make_parser(__doc__, "bench_grad", threads=None, plot=False)
    parser.add_argument("--sizes", nargs="+", default=["1k", "10k"], choices=list(SIZES))
    parser.add_argument("--steps", type=int, default=5, help="timed steps per mode")
    parser.add_argument("--rollout-steps", type=int, default=100)
    parser.add_argument(
        "--unrolled-steps-max",
        type=int,
        default=100,
        help="unrolled rollouts measure at most this many steps (then projected)",
    )
    parser.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    parser.add_argument("--memory-child", nargs=3, metavar=("SIZE", "MODE", "STEPS"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.memory_child:
        size, mode, steps = args.memory_child
        peak_memory_child(size, mode, int(steps))
        return []
    rows = []
    for size in args.sizes:
        for mode in args.modes:
            rows.append(measure(size, mode, args))
            print(rows[-1])
    text = markdown(rows, args.rollout_steps)
    print(text)
    write_outputs(args.out, "bench_grad", rows, text)
    return rows


if __name__ == "__main__":
    main()
