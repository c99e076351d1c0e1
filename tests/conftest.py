"""Shared fixtures: small scenes, rigid motions, a fixed random seed, and the scripts as modules."""

from __future__ import annotations

import importlib
import math
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest
import torch

import energysim as es
from energysim.objective import batch_last


@pytest.fixture(autouse=True)
def _seed() -> None:
    torch.manual_seed(0)


def random_rotation(dim: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """A proper rotation (det +1), shape `[d, d]`."""
    if dim == 2:
        angle = float(torch.rand((), generator=generator)) * 2 * math.pi
        c, s = math.cos(angle), math.sin(angle)
        return torch.tensor([[c, -s], [s, c]], dtype=torch.float64)
    q, r = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64, generator=generator))
    q = q * torch.sign(torch.diagonal(r))
    if torch.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def lay_out_per_element(monkeypatch: pytest.MonkeyPatch) -> None:
    """Compiled CPU batches of every size laid out per element for the rest of the test, as a GPU lays
    out small batches (`energysim.objective.batch_last.takes_batch_last`)."""
    monkeypatch.setitem(batch_last.BATCH_LAST_MIN_BATCH, "cpu", 2**62)


def small_box(dim: int, cells: int = 2) -> es.SimplexMesh:
    """A unit box (square in 2D) with `cells` cells per side."""
    if dim == 2:
        return es.TriMesh.box(size=(1.0, 1.0), cells=(cells, cells))
    return es.TetMesh.box(size=(1.0, 1.0, 1.0), cells=(cells, cells, cells))


def rigid_alignment_error(x: torch.Tensor, rest: torch.Tensor) -> float:
    """RMS distance between `x` and `rest` after the best proper rigid motion (Kabsch), in m."""
    xc, rc = x - x.mean(0), rest - rest.mean(0)
    u, _, vt = torch.linalg.svd(rc.T @ xc)
    d = torch.ones(x.shape[1], dtype=x.dtype)
    d[-1] = torch.sign(torch.linalg.det(u @ vt))
    rotation = u @ torch.diag(d) @ vt
    return float(((rc @ rotation - xc) ** 2).sum(-1).mean().sqrt())


@pytest.fixture(scope="module")
def one_thread() -> Iterator[None]:
    """One torch thread for a module (`pytestmark = pytest.mark.usefixtures("one_thread")`): meshes this
    small gain nothing from intra-op threads, and on a busy machine torch's thread pool can make a
    15 ms step take 700 ms."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def script_module(name: str) -> ModuleType:
    """`scripts/<name>.py` as a module. scripts/ is not a package: its modules import each other
    (`_training`, `_bench`) as top-level modules, so the folder goes on `sys.path`."""
    if str(SCRIPTS) not in sys.path:
        sys.path.insert(0, str(SCRIPTS))
    return importlib.import_module(name)
