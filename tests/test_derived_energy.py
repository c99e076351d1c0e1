"""A term written only as a density (`es.DensityEnergy`): derived kernels against closed forms and
finite differences, steps against the built-in term, batches, parameter gradients, compile."""

from __future__ import annotations

import warnings

import pytest
import torch

import energysim as es
from energysim.energies import derived
from energysim.energies.derived import density_stiffness, density_stress
from energysim.fem.materials import cofactor_matrix, lame_parameters, stable_neo_hookean_density
from energysim.integrators.adjoint import step_terms
from energysim.linalg.linear_solve import level_layout_of
from energysim.objective.derivatives import autograd_element_hessian, hessian_operator
from energysim.objective.objective import Objective

pytestmark = pytest.mark.usefixtures("one_thread")

# every derived quantity is the same arithmetic as its reference, reordered: rounding only
DERIVED_RTOL = 1e-10
BATCH = 8  # a batch of bodies, compiled batch-last on the CPU


def determinant(F: torch.Tensor) -> torch.Tensor:
    """det F of `[..., 3, 3]` written out: `torch.linalg.det`'s derivative goes through an SVD that
    raises on a non-finite F, which a line search's far trial point may reach."""
    return (
        F[..., 0, 0] * (F[..., 1, 1] * F[..., 2, 2] - F[..., 1, 2] * F[..., 2, 1])
        - F[..., 0, 1] * (F[..., 1, 0] * F[..., 2, 2] - F[..., 1, 2] * F[..., 2, 0])
        + F[..., 0, 2] * (F[..., 1, 0] * F[..., 2, 1] - F[..., 1, 1] * F[..., 2, 0])
    )


class VolumePreservation(es.DensityEnergy):
    """ψ = k/2 (det F − 1)², k in Pa."""

    def __init__(self, stiffness: float | torch.Tensor = 1e5) -> None:
        super().__init__()
        self.register_buffer("stiffness", torch.as_tensor(stiffness, dtype=torch.float64))

    def density(self, F: torch.Tensor) -> torch.Tensor:
        return 0.5 * self.stiffness * (determinant(F) - 1.0) ** 2


class UserNeoHookean(es.DensityEnergy):
    """The stable neo-Hookean density, written as a user's term."""

    def __init__(self, youngs_modulus: float, poissons_ratio: float) -> None:
        super().__init__()
        mu, lam = lame_parameters(*torch.tensor([youngs_modulus, poissons_ratio], dtype=torch.float64))
        self.register_buffer("mu", mu)
        self.register_buffer("lam", lam)

    def density(self, F: torch.Tensor) -> torch.Tensor:
        return stable_neo_hookean_density(F, self.mu, self.lam)


def _bound(term: es.ElementEnergy, dim: int = 3) -> es.Scene:
    mesh = es.TetMesh.box(cells=(2, 2, 2)) if dim == 3 else es.TriMesh.box(cells=(3, 3))
    scene = es.Scene(mesh, dt=1 / 60, gravity=None)
    scene.add(term)
    return scene


def _deformed(scene: es.Scene, batch: int = 2, scale: float = 0.15) -> torch.Tensor:
    generator = torch.Generator().manual_seed(3)
    noise = torch.randn(batch, *scene.rest_positions.shape, dtype=torch.float64, generator=generator)
    return scene.rest_positions + scale * noise


def _relative(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().max() / b.abs().max())


@pytest.mark.parametrize("dim", [2, 3])
def test_the_derived_neo_hookean_kernels_equal_the_closed_forms(dim):
    built_in = es.NeoHookean(1e5, 0.3)
    user = UserNeoHookean(1e5, 0.3)
    scene, _ = _bound(user, dim), _bound(built_in, dim)
    x = _deformed(scene)
    corners = x[:, user.element_vertices]
    energy, gradient = user.element_energy_and_gradient(corners, None)
    _, expected_gradient = built_in.element_energy_and_gradient(corners, None)
    assert _relative(energy, built_in.element_energy(corners, None)) < DERIVED_RTOL
    assert _relative(gradient, expected_gradient) < DERIVED_RTOL
    blocks = user.element_hessian(corners, None)
    assert _relative(blocks, built_in.element_hessian(corners, None)) < DERIVED_RTOL


def test_the_derived_volume_kernels_equal_the_hand_derived_stress_and_autograd_blocks():
    # ψ = k/2 (J − 1)²: P = k (J − 1) cof F, an independent closed form
    term = VolumePreservation(2e5)
    x = _deformed(_bound(term))
    corners = x[:, term.element_vertices]
    F = corners[..., 1:, :].sub(corners[..., :1, :]).transpose(-1, -2) @ term.rest_edge_inverse
    J = torch.linalg.det(F)
    stress, density = density_stress(term.density, F)
    assert _relative(stress, 2e5 * (J - 1.0)[..., None, None] * cofactor_matrix(F)) < DERIVED_RTOL
    assert _relative(density, 1e5 * (J - 1.0) ** 2) < DERIVED_RTOL
    blocks = term.element_hessian(corners, None)
    assert _relative(blocks, autograd_element_hessian(term, x, None)) < DERIVED_RTOL
    assert torch.allclose(blocks, blocks.transpose(-1, -2), rtol=0, atol=1e-12 * float(blocks.abs().max()))


@pytest.mark.parametrize("make", [lambda: VolumePreservation(2e5), lambda: UserNeoHookean(1e5, 0.3)])
def test_derived_gradients_and_hessians_match_central_differences(make):
    term = make()
    scene = _bound(term)
    x = _deformed(scene, batch=1)
    energy, gradient = term.value_and_gradient(x)
    assert energy.item() == pytest.approx(term(x).item(), rel=DERIVED_RTOL)
    # central differences, O(ε²) truncation: with ε = 1e-5 m and curvatures of order k, the
    # truncation and the rounding both sit near 1e-9 relative; 1e-7 leaves a factor 100
    eps = 1e-5
    direction = torch.randn_like(x)
    slope = (term(x + eps * direction) - term(x - eps * direction)) / (2 * eps)
    assert float(slope) == pytest.approx(float((gradient * direction).sum()), rel=1e-7)
    blocks = term.element_hessian(x[:, term.element_vertices], None)
    dofs = (term.element_vertices[..., None] * 3 + torch.arange(3)).reshape(len(term.element_vertices), -1)
    product = torch.zeros(x.numel(), dtype=x.dtype).index_add_(
        0, dofs.reshape(-1), (blocks[0] @ direction.reshape(-1)[dofs][..., None]).reshape(-1)
    )
    _, ahead = term.value_and_gradient(x + eps * direction)
    _, behind = term.value_and_gradient(x - eps * direction)
    expected = ((ahead - behind) / (2 * eps)).reshape(-1)
    assert _relative(product, expected) < 1e-7


SOLVERS = {
    "newton-cg": lambda: es.NewtonCG(tol=1e-11),
    "lbfgs": lambda: es.LBFGS(tol=1e-11, max_iter=4000),
    "adam": lambda: es.Adam(tol=1e-9, max_iter=40000, lr=1e-3),
}


def _beam(term: es.EnergyTerm, integrator: str = "implicit_euler") -> es.Scene:
    mesh = es.TetMesh.box(size=(1.0, 0.2, 0.2), cells=(4, 1, 1))
    scene = es.Scene(mesh, dt=1 / 60, integrator=integrator)
    scene.add(term)
    scene.fix(torch.nonzero(mesh.vertices[:, 0] < 1e-9).reshape(-1))
    return scene


@pytest.mark.parametrize("integrator", ["implicit_euler", "tr_bdf2"])
@pytest.mark.parametrize("solver", list(SOLVERS))
def test_a_step_with_the_user_density_equals_the_step_with_the_built_in_term(solver, integrator):
    user, built_in = _beam(UserNeoHookean(1e5, 0.3), integrator), _beam(es.NeoHookean(1e5, 0.3), integrator)
    velocities = 0.5 * torch.randn(user.num_vertices, 3, dtype=torch.float64)
    result = es.step(user, user.initial_state(velocities=velocities), solver=SOLVERS[solver]())
    assert result.stats.converged
    expected = es.step(built_in, built_in.initial_state(velocities=velocities), solver=es.NewtonCG(tol=1e-11))
    x, _ = user.split_state(result.state)
    x_expected, _ = built_in.split_state(expected.state)
    assert float((x - x_expected).norm(dim=-1).max()) < 1e-9
    # and the step moved: gravity and the initial velocities carry the beam ~1 cm
    assert float((x - user.rest_positions).norm(dim=-1).max()) > 1e-3


def test_a_batch_with_the_user_density_equals_its_entries_stepped_alone():
    scene = _beam(VolumePreservation(1e5))
    scene.add(es.NeoHookean(1e5, 0.3))
    velocities = torch.randn(3, scene.num_vertices, 3, dtype=torch.float64)
    states = torch.stack([scene.initial_state(velocities=v) for v in velocities])
    solver = es.NewtonCG(tol=1e-11)
    batched = es.step(scene, states, solver=solver).state
    for b in range(3):
        single = es.step(scene, states[b], solver=solver).state
        assert torch.allclose(batched[b], single, rtol=0, atol=1e-10)


def test_gradients_through_a_step_reach_the_user_terms_parameter():
    def loss(stiffness: torch.Tensor) -> torch.Tensor:
        scene = _beam(VolumePreservation(stiffness))
        scene.add(es.NeoHookean(2e4, 0.3))
        velocities = torch.zeros(scene.num_vertices, 3, dtype=torch.float64)
        velocities[:, 1] = -2.0
        state = scene.initial_state(velocities=velocities)
        for _ in range(2):
            state = es.step(scene, state, solver=es.NewtonCG(tol=1e-13)).state
        x, _ = scene.split_state(state)
        weights = torch.linspace(-1.0, 1.0, x.numel(), dtype=torch.float64).reshape(x.shape)
        return (weights * x).sum()

    stiffness = torch.tensor(5e4, dtype=torch.float64, requires_grad=True)
    (gradient,) = torch.autograd.grad(loss(stiffness), stiffness)
    # step 5e2 Pa: large against the solver's noise (tol 1e-13 m/s), small against k
    step = 5e2
    with torch.no_grad():
        expected = (loss(torch.tensor(5e4 + step)) - loss(torch.tensor(5e4 - step))) / (2 * step)
    assert float(expected) != 0.0
    assert float(gradient) == pytest.approx(float(expected), rel=1e-5)


def test_a_density_of_the_wrong_shape_is_refused_when_the_term_is_added():
    class Summed(es.DensityEnergy):
        def density(self, F: torch.Tensor) -> torch.Tensor:
            return (F**2).sum()

    with pytest.raises(ValueError, match=r"Summed\.density\(F\) must return .* shape F\.shape\[:-2\]"):
        _bound(Summed())

    class Missing(es.DensityEnergy):
        pass

    with pytest.raises(NotImplementedError, match="Missing must implement density"):
        _bound(Missing())


def test_density_stiffness_is_the_hessian_of_the_density():
    # ψ = (tr F)³: ∂²ψ/∂F_ii∂F_jj = 6 tr F, every other entry zero
    F = torch.eye(3, dtype=torch.float64) + 0.1 * torch.randn(4, 3, 3, dtype=torch.float64)
    stiffness = density_stiffness(lambda F: F.diagonal(dim1=-2, dim2=-1).sum(-1) ** 3, F)
    trace = F.diagonal(dim1=-2, dim2=-1).sum(-1)
    diagonal = torch.tensor([0, 4, 8])
    expected = torch.zeros(4, 9, 9, dtype=torch.float64)
    expected[:, diagonal[:, None], diagonal[None, :]] = 6.0 * trace[:, None, None]
    assert _relative(stiffness, expected) < DERIVED_RTOL


def _compiler_works() -> bool:
    try:
        return bool(torch.compile(lambda t: t + 1.0)(torch.zeros(1)) == 1.0)
    except Exception:  # noqa: BLE001 - no C++ toolchain, an unsupported platform
        return False


def test_a_compiled_step_with_the_user_density_equals_the_eager_one():
    if not _compiler_works():
        pytest.skip("torch.compile is not available here")
    scene = _beam(VolumePreservation(1e5))
    scene.add(es.NeoHookean(1e5, 0.3))
    state = scene.initial_state(velocities=0.5 * torch.randn(scene.num_vertices, 3, dtype=torch.float64))
    eager = es.step(scene, state, solver=es.NewtonCG(tol=1e-11))
    with warnings.catch_warnings():
        # a fallback to eager evaluation would pass unseen: the derived kernels must compile
        warnings.filterwarnings("error", message="torch.compile could not compile")
        compiled = es.step(scene, state, solver=es.NewtonCG(tol=1e-11, compile=True))
    assert compiled.stats.converged
    assert torch.allclose(compiled.state, eager.state, rtol=0, atol=1e-10)


class CompiledVolume(VolumePreservation):
    """The volume term with its derived kernels compiled on every eager call."""

    compile_derivatives = True


def test_the_compiled_derived_kernels_equal_the_eager_ones():
    if not _compiler_works():
        pytest.skip("torch.compile is not available here")
    compiled, eager = CompiledVolume(2e5), VolumePreservation(2e5)
    x = _deformed(_bound(compiled))
    _bound(eager)
    corners = x[:, compiled.element_vertices]
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message="torch.compile could not compile")
        energy, gradient = compiled.element_energy_and_gradient(corners, None)
        blocks = compiled.element_hessian(corners, None)
    kernels = {("energy_and_gradient", "cpu", CompiledVolume), ("hessian", "cpu", CompiledVolume)}
    assert kernels <= set(derived._COMPILED)
    expected_energy, expected_gradient = eager.element_energy_and_gradient(corners, None)
    assert _relative(energy, expected_energy) < DERIVED_RTOL
    assert _relative(gradient, expected_gradient) < DERIVED_RTOL
    assert _relative(blocks, autograd_element_hessian(eager, x, None)) < DERIVED_RTOL


def test_a_kernel_that_does_not_compile_falls_back_to_the_eager_derivation_with_one_warning(monkeypatch):
    def failing(*args: object, **kwargs: object) -> object:
        def call(*args: object) -> object:
            raise RuntimeError("no C++ compiler")

        return call

    monkeypatch.setattr(derived, "_COMPILED", {})
    monkeypatch.setattr(derived, "_FAILED", set())
    monkeypatch.setattr(torch, "compile", failing)
    term, reference = CompiledVolume(2e5), VolumePreservation(2e5)
    x = _deformed(_bound(term))
    _bound(reference)
    corners = x[:, term.element_vertices]
    with pytest.warns(RuntimeWarning, match=r"derived hessian kernel of CompiledVolume .*no C\+\+ compiler"):
        blocks = term.element_hessian(corners, None)
    assert torch.equal(blocks, reference.element_hessian(corners, None))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # warned once: the eager derivation serves from now on
        assert torch.equal(term.element_hessian(corners, None), blocks)


def test_small_meshes_keep_the_eager_derivation(monkeypatch):
    # 40 tets: a compilation could never pay for itself, however often the term is called
    monkeypatch.setattr(derived, "_COMPILED", {})
    term = VolumePreservation(2e5)
    x = _deformed(_bound(term))
    for _ in range(derived.COMPILE_AFTER_CALLS + 2):
        term.element_hessian(x[:, term.element_vertices], None)
    assert derived._COMPILED == {}


def test_blocks_of_terms_on_the_same_elements_are_summed_into_one_group():
    volume, elastic = VolumePreservation(2e5), es.NeoHookean(1e5, 0.3)
    scene = _bound(volume)
    scene.add(elastic)
    x = _deformed(scene)
    free = torch.ones(scene.num_vertices, dtype=torch.bool)
    together = hessian_operator([volume, elastic], x, None, free)
    assert len(together.blocks) == 1
    apart = [hessian_operator([term], x, None, free) for term in (volume, elastic)]
    expected = apart[0].dense(x) + apart[1].dense(x)
    assert _relative(together.dense(x), expected) < DERIVED_RTOL
    v = torch.randn_like(x)
    assert _relative(together.matvec(v), apart[0].matvec(v) + apart[1].matvec(v)) < DERIVED_RTOL


def test_a_compiled_batch_evaluates_the_user_density_batch_last_as_eagerly():
    # a compiled CPU batch takes every element term batch-last: the user's
    # term through the defaults that transpose its derived element kernels. Static shapes: after
    # other scenes a compiled objective turns its sizes symbolic, which the derived kernels'
    # forward-mode derivatives cannot trace (they then fall back to eager derivation, with a warning)
    if not _compiler_works():
        pytest.skip("torch.compile is not available here")
    scene = _beam(VolumePreservation(1e5))
    scene.add(es.NeoHookean(1e5, 0.3))
    generator = torch.Generator().manual_seed(3)
    noise = torch.randn(BATCH, scene.num_vertices, 3, generator=generator, dtype=torch.float64)
    x = scene.rest_positions[None] + 0.01 * noise
    terms = step_terms(list(scene.terms), scene.vertex_mass, scene.dt, x, 0 * x, scene.free)
    objective = Objective(terms, scene.free, scene.dt / scene.vertex_mass)
    energy, gradient = objective.energy_and_gradient(x)
    dense = objective.hessian(x).dense(x)
    layout = level_layout_of(objective.element_groups(), x)
    objective.compiled = True
    with warnings.catch_warnings(), torch._dynamo.config.patch(automatic_dynamic_shapes=False):
        warnings.filterwarnings("error", message="torch.compile could not compile")
        fast_energy, fast_gradient = objective.energy_and_gradient(x)
        bands = objective.band_hessian(x, layout)
    assert torch.allclose(fast_energy, energy, rtol=1e-12, atol=0)
    assert torch.allclose(fast_gradient, gradient, rtol=0, atol=1e-9 * float(gradient.abs().max()))
    size, width = bands.shape[1], bands.shape[2]
    read = torch.arange(size)[:, None] + torch.arange(width) < size  # the slots LAPACK reads
    expected = dense.reshape(BATCH, -1)[:, layout.band_entries]
    assert torch.allclose(bands[:, read], expected[:, read], rtol=0, atol=1e-9 * float(dense.abs().max()))


class QuadraticStrain(es.DensityEnergy):
    """ψ = k ‖F − I‖², quadratic in F: its Hessian never changes, which it declares."""

    has_constant_hessian = True

    def __init__(self, stiffness: float = 1e5) -> None:
        super().__init__()
        self.register_buffer("stiffness", torch.as_tensor(stiffness, dtype=torch.float64))

    def density(self, F: torch.Tensor) -> torch.Tensor:
        identity = torch.eye(F.shape[-1], dtype=F.dtype, device=F.device)
        return self.stiffness * (F - identity).square().sum(dim=(-1, -2))


def test_a_user_density_declared_constant_is_assembled_once_and_still_exact():
    # a compiled batch keeps the declared term's part from the first Hessian; the later Hessians,
    # at other positions, equal the eager ones there (static shapes, as in the test above)
    if not _compiler_works():
        pytest.skip("torch.compile is not available here")
    scene = _beam(QuadraticStrain())
    scene.add(es.NeoHookean(1e5, 0.3))
    generator = torch.Generator().manual_seed(4)
    shape = (BATCH, scene.num_vertices, 3)
    start = scene.rest_positions[None] + 0.01 * torch.randn(shape, generator=generator, dtype=torch.float64)
    positions = [start, start + 0.01 * torch.randn(shape, generator=generator, dtype=torch.float64)]
    terms = step_terms(list(scene.terms), scene.vertex_mass, scene.dt, start, 0 * start, scene.free)
    objective = Objective(terms, scene.free, scene.dt / scene.vertex_mass)
    expected = [objective.hessian(x).dense(x) for x in positions]
    layout = level_layout_of(objective.element_groups(), positions[0])
    objective.compiled = True
    with warnings.catch_warnings(), torch._dynamo.config.patch(automatic_dynamic_shapes=False):
        warnings.filterwarnings("error", message="torch.compile could not compile")
        computed = [objective.band_hessian(x, layout) for x in positions]
    # one constant part kept, for the one storage (beside it: the calls' arguments and fixed DOFs)
    assert [key[0] for key in objective._constant_hessians if key[0] == "band"] == ["band"]
    size, width = computed[0].shape[1], computed[0].shape[2]
    read = torch.arange(size)[:, None] + torch.arange(width) < size  # the slots LAPACK reads
    for bands, dense in zip(computed, expected, strict=True):
        reference = dense.reshape(BATCH, -1)[:, layout.band_entries]
        tolerance = 1e-9 * float(dense.abs().max())
        assert torch.allclose(bands[:, read], reference[:, read], rtol=0, atol=tolerance)
