"""The shipped creatures: sound meshes and muscles, a stress-free rest shape, muscles that bend the body
the way their layout says, reproducible files, and clear errors for missing ones."""

from __future__ import annotations

import importlib
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import energysim as es
from energysim.creatures import CREATURES, Creature, default_meshes_dir, load_creature, shipped_meshes_dir
from energysim.energies.fibre_muscles import FibreMuscles
from energysim.mesh import TetMesh, TriMesh, signed_volumes
from energysim.objective.derivatives import energy_and_gradient

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"
if str(SCRIPTS) not in sys.path:
    sys.path.insert(0, str(SCRIPTS))
make_creatures = importlib.import_module("make_creatures")

# element counts each creature must stay within: the worm is kept small enough to step in real time
ELEMENT_RANGE = {
    "worm": (300, 800),
    "quadruped": (300, 5000),
    "starfish": (300, 5000),
    "jumper": (300, 5000),
    "crawler2d": (100, 3000),
    "walker2d": (100, 3000),
}


@pytest.fixture(scope="module", params=CREATURES)
def creature(request) -> Creature:
    return load_creature(request.param)


def test_every_creature_is_listed_and_designed():
    assert set(CREATURES) == set(make_creatures.DESIGNS) == set(ELEMENT_RANGE)
    assert sum(load_creature(name).dim == 3 for name in CREATURES) >= 4
    assert sum(load_creature(name).dim == 2 for name in CREATURES) >= 2


def test_mesh_is_sound_and_in_range(creature):
    mesh = creature.mesh
    assert isinstance(mesh, TetMesh if creature.dim == 3 else TriMesh)
    low, high = ELEMENT_RANGE[creature.name]
    assert low <= mesh.num_elements <= high
    # voxel simplices: every one positive and of the same volume h^d / d!
    volume = signed_volumes(mesh.vertices, mesh.elements)
    assert float(volume.min()) > 0
    assert torch.allclose(volume, volume.mean().expand_as(volume), rtol=1e-9)
    assert float(volume.sum()) == pytest.approx(float(mesh.element_rest_volume().sum()), rel=1e-12)
    # a closed surface: in 3D every surface edge is shared by exactly two surface triangles
    if creature.dim == 3:
        faces = mesh.surface()
        edges = faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2).sort(dim=1).values
        _, counts = torch.unique(edges, dim=0, return_counts=True)
        assert bool((counts == 2).all())


def test_frame_and_size(creature):
    low, high = creature.mesh.bounding_box()
    assert float(low[1]) == 0.0  # lowest vertex exactly on y = 0
    assert 0.1 <= creature.body_length <= 0.5
    assert creature.body_length == pytest.approx(float(high[0] - low[0]), rel=1e-12)
    # centred horizontally
    assert float(low[0] + high[0]) == pytest.approx(0.0, abs=1e-12)
    if creature.dim == 3:
        assert float(low[2] + high[2]) == pytest.approx(0.0, abs=1e-12)


def test_actuators_and_fibres(creature):
    actuators, fibres = creature.actuators, creature.fibres
    count = creature.mesh.num_elements
    assert actuators.dtype == torch.int64 and tuple(actuators.shape) == (count,)
    assert fibres.dtype == torch.float64 and tuple(fibres.shape) == (count, creature.dim)
    assert int(actuators.min()) >= -1
    groups = torch.bincount(actuators[actuators >= 0], minlength=creature.num_actuators)
    assert len(groups) == creature.num_actuators
    assert int(groups.min()) > 0, f"actuators {torch.nonzero(groups == 0).tolist()} drive no element"
    assert torch.allclose(fibres.norm(dim=-1), torch.ones(count, dtype=torch.float64), rtol=0, atol=1e-12)
    assert len(creature.actuator_names) == len(creature.gait_phases) == creature.num_actuators
    assert 0 < creature.max_contraction < 1 and creature.muscle_stiffness > 0


def test_zero_activation_is_the_rest_shape(creature):
    mesh = creature.mesh
    body = es.NeoHookean(creature.youngs_modulus, creature.poissons_ratio)
    muscles = creature.muscles()
    mass = creature.density * mesh.vertex_rest_volume()
    for term in (body, muscles):
        term.bind(mesh, mass)
    assert muscles.num_actuators == creature.num_actuators
    zero = torch.zeros(1, creature.num_actuators, dtype=torch.float64)
    for action in (None, zero):
        _, gradient = energy_and_gradient(lambda x, a=action: body(x) + muscles(x, a), mesh.vertices[None])
        assert float(gradient.abs().max()) < 1e-9  # N
    # and a full activation does load it: the force is of order k c V^(2/3)
    _, gradient = energy_and_gradient(lambda x: muscles(x, zero + 1.0), mesh.vertices[None])
    voxel = float(mesh.element_rest_volume().mean()) ** (1 / creature.dim)
    assert float(
        gradient.abs().max()
    ) > 0.01 * creature.muscle_stiffness * creature.max_contraction * voxel ** (creature.dim - 1)


@pytest.mark.parametrize("name", ["worm", "crawler2d"])
def test_contracting_the_bottom_layer_arches_the_crawler(name):
    # the bottom layer shortens, the top does not: the body bends with the bottom inside, so its ends
    # drop below its middle, and the driven fibres shorten towards 1 − c (the passive top resists)
    creature = load_creature(name)
    mesh = creature.mesh
    scene = es.Scene(mesh, density=creature.density, gravity=None, solver=es.NewtonCG(tol=1e-6))
    scene.add(es.NeoHookean(creature.youngs_modulus, creature.poissons_ratio))
    muscles = scene.add(creature.muscles())
    x = mesh.vertices[:, 0]
    middle = (x - x[x.abs().argmin()]).abs() < 1e-9  # the cross-section nearest the middle
    scene.fix(torch.nonzero(middle).reshape(-1))
    action = torch.zeros(1, creature.num_actuators, dtype=torch.float64)
    action[0, 0::2] = 1.0  # every bottom actuator
    result = es.solve_static(scene, action=action)
    assert result.stats.converged
    rise = result.state[:, 1] - mesh.vertices[:, 1]
    ends = x.abs() > 0.45 * creature.body_length
    assert float(rise[ends].mean()) < -0.02 * creature.body_length
    stretch = muscles.fibre_stretch(result.state[None])[0]
    bottom = muscles.element_actuator % 2 == 0
    assert 1 - creature.max_contraction < float(stretch[bottom].mean()) < 0.95
    assert float(stretch[~bottom].mean()) > float(stretch[bottom].mean()) + 0.05


def test_gait_action(creature):
    times = torch.linspace(0.0, 1.0, 7, dtype=torch.float64)
    actions = creature.gait_action(times)
    assert actions.shape == (7, creature.num_actuators)
    assert float(actions.abs().max()) <= creature.gait_amplitude + 1e-12
    phases = torch.tensor(creature.gait_phases, dtype=torch.float64)
    expected = creature.gait_amplitude * torch.sin(2 * math.pi * creature.gait_frequency * 0.25 + phases)
    assert torch.allclose(creature.gait_action(0.25), expected, rtol=0, atol=1e-15)


@pytest.mark.parametrize("name", CREATURES)
def test_builds_are_reproducible_and_match_the_shipped_files(name, tmp_path):
    first = make_creatures.build_creature(make_creatures.DESIGNS[name]())
    second = make_creatures.build_creature(make_creatures.DESIGNS[name]())
    for field in ("vertices", "elements", "actuators", "fibres"):
        assert np.array_equal(getattr(first, field), getattr(second, field)), field
    assert first.metadata == second.metadata
    # written and read back, and the shipped file is what the script makes today
    make_creatures.write_creature(first, tmp_path)
    make_creatures.check(first, load_creature(name, tmp_path))
    make_creatures.check(first, load_creature(name))


def test_script_main_writes_every_creature(tmp_path, capsys):
    make_creatures.main(["--out", str(tmp_path), "--only", "crawler2d", "walker2d"])
    assert sorted(path.name for path in tmp_path.iterdir()) == [
        "crawler2d.json",
        "crawler2d.vtu",
        "walker2d.json",
        "walker2d.vtu",
    ]
    assert "walker2d" in capsys.readouterr().out


def test_meshes_folder_override_and_missing_files(tmp_path, monkeypatch):
    shipped = Path(__file__).resolve().parents[1] / "energysim" / "assets" / "creatures"
    monkeypatch.delenv("ENERGYSIM_MESHES", raising=False)
    assert Path(default_meshes_dir()).resolve() == shipped
    monkeypatch.setenv("ENERGYSIM_MESHES", str(tmp_path))
    assert default_meshes_dir() == tmp_path
    with pytest.raises(
        FileNotFoundError,
        match=r"worm\.vtu: creature file not found; make it with .*scripts/make_creatures\.py",
    ):
        load_creature("worm")
    make_creatures.write_creature(make_creatures.build_creature(make_creatures.worm()), tmp_path)
    assert torch.equal(load_creature("worm").actuators, load_creature("worm", shipped).actuators)
    (tmp_path / "worm.json").unlink()
    with pytest.raises(FileNotFoundError, match=r"worm\.json: creature file not found"):
        load_creature("worm")
    with pytest.raises(ValueError, match="unknown creature 'dragon'"):
        load_creature("dragon")


def test_make_creatures_writes_the_package_data_that_loads_by_default(monkeypatch):
    # the script's default output folder is the one the package ships and load_creature reads
    monkeypatch.delenv("ENERGYSIM_MESHES", raising=False)
    shipped = Path(shipped_meshes_dir()).resolve()
    assert shipped == (Path(es.__file__).resolve().parent / "assets" / "creatures")
    assert make_creatures.MESHES.resolve() == shipped == Path(default_meshes_dir()).resolve()
    assert sorted(path.name for path in shipped.iterdir()) == sorted(
        f"{name}.{ext}" for name in CREATURES for ext in ("json", "vtu")
    )


def test_muscles_take_overrides():
    creature = load_creature("jumper")
    muscles = creature.muscles(stiffness=torch.tensor(2e5, dtype=torch.float64), max_contraction=0.1)
    assert isinstance(muscles, FibreMuscles)
    assert float(muscles.stiffness) == 2e5 and muscles.max_contraction == 0.1
    assert creature.muscles().max_contraction == creature.max_contraction
