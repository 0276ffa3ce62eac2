"""The JAX and PyTorch wrappers of the differentiable reconstruction: their gradients are
checked by the frameworks' own finite-difference checkers (jax.test_util.check_grads,
torch.autograd.gradcheck). Each test is skipped where its framework is not installed
(jax is in the test extra; torch is never installed by CI)."""

import numpy as np
import pytest

from solver import fundamental_forms
from solver.differentiable_frameworks import jax_reconstruction, torch_reconstruction
from tests.helpers.meshes import grid
from tests.helpers.real_meshes import CASES as REAL
from tests.helpers.welded_meshes import CASES as WELDED


def bent_sheet_forms(angle_scale: float):
    V, F = grid(4, 4)
    T = np.stack([0.6 * np.sin(V[:, 0] / 0.6), V[:, 1], 0.6 * (1 - np.cos(V[:, 0] / 0.6))], 1)
    forms = fundamental_forms(T, F)
    return forms, forms.lengths, forms.angles * angle_scale


@pytest.mark.parametrize("refine", [False, None])
def test_jax_custom_vjp_passes_check_grads(refine):
    jax = pytest.importorskip("jax")
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    from jax.test_util import check_grads

    forms, L, A = bent_sheet_forms(0.8)
    reconstruct = jax_reconstruction(forms.faces, forms.edges, refine=refine)
    rng = np.random.default_rng(0)
    weights = jnp.asarray(rng.standard_normal((forms.faces.max() + 1, 3)))

    def loss(lengths, angles):
        return jnp.sum(weights * reconstruct(lengths, angles))

    check_grads(loss, (jnp.asarray(L), jnp.asarray(A)), order=1, modes=["rev"], eps=1e-6,
                atol=1e-5, rtol=1e-5)
    _, grad_A = jax.grad(loss, argnums=(0, 1))(jnp.asarray(L), jnp.asarray(A))
    assert np.abs(np.asarray(grad_A)).max() > 0


@pytest.mark.parametrize("name", ["edge-with-4-faces", "duplicated-corner"])
def test_jax_on_a_real_files_forms(name):
    """The forms of a non-manifold or welded file (vertex_map, weld_map, placement, no
    n_vertices): the JAX function answers per file vertex and passes check_grads."""
    jax = pytest.importorskip("jax")
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    from jax.test_util import check_grads

    V, F = REAL[name]() if name in REAL else WELDED[name]()[:2]
    forms = fundamental_forms(V, F)
    reconstruct = jax_reconstruction(forms.faces, forms.edges, refine=False,
                                     vertex_map=forms.vertex_map, weld_map=forms.weld_map,
                                     placement=forms.placement)
    rng = np.random.default_rng(1)
    A = forms.angles + 0.003 * rng.standard_normal(len(forms.angles))
    assert reconstruct(jnp.asarray(forms.lengths), jnp.asarray(A)).shape == V.shape
    weights = jnp.asarray(rng.standard_normal(V.shape))

    def loss(lengths, angles):
        return jnp.sum(weights * reconstruct(lengths, angles))

    check_grads(loss, (jnp.asarray(forms.lengths), jnp.asarray(A)), order=1, modes=["rev"],
                eps=1e-6, atol=1e-5, rtol=1e-5)


def test_torch_autograd_function_passes_gradcheck():
    torch = pytest.importorskip("torch")
    forms, L, A = bent_sheet_forms(0.8)
    reconstruct = torch_reconstruction(forms.faces, forms.edges)
    lengths = torch.tensor(L, dtype=torch.float64, requires_grad=True)
    angles = torch.tensor(A, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(reconstruct, (lengths, angles), eps=1e-6, atol=1e-5,
                                    rtol=1e-4)
