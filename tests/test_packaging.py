"""A wheel built from the source tree is a working library: it imports without the source tree, ships the
creatures, says its version, and declares every third-party module the package imports.

The wheel is built once per module from a copy of the files a build reads (pyproject.toml, README.md,
LICENSE, energysim/), offline and without build isolation, so the source tree gets no build/ or egg-info.
It is then imported in subprocesses whose only path entry for energysim is the unpacked wheel or the wheel
file itself (a zip archive), from a folder outside the source tree.
"""

from __future__ import annotations

import ast
import email.parser
import importlib
import json
import os
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

import energysim

setuptools = pytest.importorskip("setuptools", reason="building the wheel needs setuptools (the dev extra)")
if int(setuptools.__version__.split(".")[0]) < 77:
    pytest.skip("building the wheel needs setuptools >= 77 (the dev extra)", allow_module_level=True)

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = ROOT / "scripts"
if str(SCRIPTS) not in sys.path:
    sys.path.insert(0, str(SCRIPTS))
make_creatures = importlib.import_module("make_creatures")

DISTRIBUTION = "torch-energysim"
# the files and folders a wheel is built from
BUILD_INPUTS = ("pyproject.toml", "README.md", "LICENSE", "energysim")
# parts of the package whose third-party imports are optional, and the extra that installs them
# (the first matching prefix wins: the more specific parts come first)
OPTIONAL_PARTS = {
    "energysim/envs/rllib.py": "ray",
    "energysim/envs/": "rl",
    "energysim/export/render.py": "render",
    "energysim/export/xdmf.py": "xdmf",
    "energysim/viewer/server.py": "notebook",
    "energysim/viewer/notebook.py": "notebook",
}
# import names whose distribution is named differently
DISTRIBUTION_OF_MODULE = {"PIL": "pillow", "stable_baselines3": "stable-baselines3"}
# the largest wait for a subprocess that imports torch, in s: far above its few seconds, below a hang
SUBPROCESS_TIMEOUT = 300


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    source = tmp_path_factory.mktemp("source")
    for name in BUILD_INPUTS:
        if (ROOT / name).is_dir():
            shutil.copytree(ROOT / name, source / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        else:
            shutil.copy2(ROOT / name, source / name)
    out = tmp_path_factory.mktemp("wheel")
    command = [sys.executable, "-m", "pip", "wheel", str(source), "--no-deps", "--no-build-isolation"]
    command += ["--no-index", "--disable-pip-version-check", "-w", str(out)]
    result = subprocess.run(
        command, cwd=out, capture_output=True, text=True, timeout=SUBPROCESS_TIMEOUT, check=False
    )
    assert result.returncode == 0, f"building the wheel failed:\n{result.stdout}\n{result.stderr}"
    (wheel_file,) = out.glob("*.whl")
    return wheel_file


@pytest.fixture(scope="module")
def metadata(wheel: Path) -> email.message.Message:
    with zipfile.ZipFile(wheel) as archive:
        (name,) = [n for n in archive.namelist() if n.endswith(".dist-info/METADATA")]
        return email.parser.Parser().parsestr(archive.read(name).decode("utf-8"))


def run_isolated(path_entry: Path, code: str, cwd: Path) -> dict:
    """Run `code` with `path_entry` first on sys.path and neither the source tree nor the creature folder
    override in reach; return the JSON object it prints last."""
    env = {key: value for key, value in os.environ.items() if key not in ("PYTHONPATH", "ENERGYSIM_MESHES")}
    env["PYTHONPATH"] = str(path_entry)
    env.setdefault("OMP_NUM_THREADS", "1")
    result = subprocess.run(
        [sys.executable, "-c", code],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=SUBPROCESS_TIMEOUT,
        check=False,
    )
    assert result.returncode == 0, f"the installed package failed:\n{result.stdout}\n{result.stderr}"
    return json.loads(result.stdout.strip().splitlines()[-1])


LOAD_WORM = """
import json, energysim
worm = energysim.load_creature("worm")
report = dict(
    file=energysim.__file__,
    version=energysim.__version__,
    num_actuators=worm.num_actuators,
    actuators=worm.actuators.tolist(),
    vertices=worm.mesh.num_vertices,
)
try:
    import gymnasium
except ImportError:
    gymnasium = None
if gymnasium is not None:
    import energysim.envs
    env = gymnasium.make("energysim/Worm-v0")
    observation, _ = env.reset(seed=0)
    report.update(
        observation_shape=list(observation.shape),
        observation_space_shape=list(env.observation_space.shape),
        action_shape=list(env.action_space.shape),
    )
print(json.dumps(report))
"""


def test_metadata_names_the_distribution_its_licence_and_version(wheel, metadata):
    assert metadata["Name"] == DISTRIBUTION
    assert metadata["License-Expression"] == "MIT"
    assert metadata.get_all("License-File") == ["LICENSE"]
    assert metadata["Version"] == energysim.__version__
    assert wheel.name.startswith(f"torch_energysim-{energysim.__version__}-")
    with zipfile.ZipFile(wheel) as archive:
        (licence,) = [n for n in archive.namelist() if n.endswith(".dist-info/licenses/LICENSE")]
        assert archive.read(licence) == (ROOT / "LICENSE").read_bytes()


def test_wheel_ships_every_creature_file(wheel):
    shipped = {path.name for path in (ROOT / "energysim" / "assets" / "creatures").iterdir()}
    expected = {f"{name}.{ext}" for name in energysim.CREATURES for ext in ("vtu", "json")}
    assert shipped == expected
    with zipfile.ZipFile(wheel) as archive:
        folder = "energysim/assets/creatures/"
        in_wheel = {n.removeprefix(folder) for n in archive.namelist() if n.startswith(folder)}
    assert in_wheel == expected


def _third_party_imports() -> dict[str, set[str]]:
    """Top-level third-party modules the package imports (anywhere in a file), by file relative to ROOT."""
    found: dict[str, set[str]] = {}
    for path in sorted((ROOT / "energysim").rglob("*.py")):
        names = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names.update(alias.name.split(".")[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
        names -= set(sys.stdlib_module_names) | {"energysim"}
        if names:
            found[path.relative_to(ROOT).as_posix()] = names
    return found


def _requirements(metadata: email.message.Message) -> dict[str, set[str]]:
    """Distribution names required by each extra ("" for the core), lower-case."""
    required: dict[str, set[str]] = {}
    for line in metadata.get_all("Requires-Dist"):
        name = re.match(r"[A-Za-z0-9._-]+", line).group(0).lower()
        extra = re.search(r"""extra\s*==\s*["']([^"']+)["']""", line)
        required.setdefault(extra.group(1) if extra else "", set()).add(name)
    return required


def test_metadata_requires_every_module_the_package_imports(metadata):
    imports = _third_party_imports()
    required = _requirements(metadata)
    # the imports of the core step, read from the source, cover at least these
    core_modules = set().union(
        *(names for file, names in imports.items() if not any(file.startswith(p) for p in OPTIONAL_PARTS))
    )
    assert {"torch", "numpy", "meshio", "scipy"} <= core_modules
    for file, names in imports.items():
        extra = next((e for part, e in OPTIONAL_PARTS.items() if file.startswith(part)), "")
        for module in names:
            distribution = DISTRIBUTION_OF_MODULE.get(module, module).lower()
            where = "the core dependencies" if not extra else f"the {extra!r} extra"
            assert distribution in required.get(extra, set()) | required[""], (
                f"{file} imports {module}, but {where} do not require {distribution}"
            )
    # optional modules stay optional: nothing the core does not import is a core requirement
    assert required[""] == {DISTRIBUTION_OF_MODULE.get(m, m).lower() for m in core_modules}


def test_installed_wheel_loads_creatures_and_makes_environments(wheel, tmp_path):
    unpacked = tmp_path / "site"
    with zipfile.ZipFile(wheel) as archive:
        archive.extractall(unpacked)
    report = run_isolated(unpacked, LOAD_WORM, cwd=tmp_path)
    assert Path(report["file"]).resolve() == (unpacked / "energysim" / "__init__.py").resolve()
    assert report["version"] == energysim.__version__
    # the worm's voxel design, built here, fixes its actuators element by element
    design = make_creatures.build_creature(make_creatures.DESIGNS["worm"]())
    assert report["num_actuators"] == int(design.actuators.max()) + 1 == 10
    assert report["actuators"] == design.actuators.tolist()
    assert report["vertices"] == design.vertices.shape[0]
    if "observation_shape" in report:
        assert report["observation_shape"] == report["observation_space_shape"]
        assert report["action_shape"] == [report["num_actuators"]]


def test_creatures_load_from_the_zipped_wheel(wheel, tmp_path):
    code = """
import json, energysim
walker = energysim.load_creature("walker2d")
print(json.dumps(dict(file=energysim.__file__, dim=walker.dim, actuators=walker.actuators.tolist())))
"""
    report = run_isolated(wheel, code, cwd=tmp_path)
    assert report["file"].startswith(str(wheel))
    design = make_creatures.build_creature(make_creatures.DESIGNS["walker2d"]())
    assert report["dim"] == 2
    assert report["actuators"] == design.actuators.tolist()


def test_missing_optional_modules_name_the_extra_to_install(monkeypatch):
    from energysim.export import render

    monkeypatch.setitem(sys.modules, "pyvista", None)
    with pytest.raises(ImportError, match=re.escape("pip install 'torch-energysim[render]'")):
        render._pyvista()
    for name in [n for n in sys.modules if n == "energysim.envs" or n.startswith("energysim.envs.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "gymnasium", None)
    with pytest.raises(ImportError, match=re.escape("pip install 'torch-energysim[rl]'")):
        importlib.import_module("energysim.envs")
