"""The differentiable reconstruction as a JAX and a PyTorch operation (optional extras).

``reconstruct = jax_reconstruction(faces, edges, **keywords)`` returns a function
``vertices = reconstruct(lengths, angles)`` with a ``jax.custom_vjp`` (the numerical work
runs on the host through ``jax.pure_callback``; it needs ``jax_enable_x64``), and
:func:`torch_reconstruction` the same as a ``torch.autograd.Function``, so that
``loss(reconstruct(L, A))`` backpropagates into ``L`` and ``A`` through
:func:`solver.differentiable.reconstruct_vjp`. The keywords are those of
:func:`solver.reconstruct` (constraints fixed). Install with ``pip install -e ".[jax]"``;
torch is not a dependency of the project (import it yourself).

Both keep the :class:`solver.differentiable.ReconstructionVJP` of the last few forward
evaluations (:data:`KEPT`), so the backward pass reuses their factorization instead of
reconstructing again. Neither is vectorized by ``jax.vmap`` over batches of forms (each
call reconstructs one mesh); a batch of cotangents is one ``vjp`` call in the library.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from .differentiable import ReconstructionVJP, reconstruct_vjp

KEPT = 4
"""Forward evaluations whose VJPs are kept for their backward passes."""


class _KeptVJPs:
    """``reconstruct_vjp`` memoized on the bytes of (lengths, angles), last KEPT kept.

    Args:
        faces, edges: the connectivity every call reconstructs.
        keywords: the keywords of :func:`solver.reconstruct`.
    """

    def __init__(self, faces: ArrayLike, edges: ArrayLike, keywords: dict[str, Any]) -> None:
        self.faces, self.edges, self.keywords = faces, edges, keywords
        self.kept: OrderedDict[bytes, tuple[np.ndarray, ReconstructionVJP]] = OrderedDict()

    def __call__(self, lengths: np.ndarray, angles: np.ndarray,
                 ) -> tuple[np.ndarray, ReconstructionVJP]:
        """The vertices (n, 3) and VJP of ``(lengths, angles)``, each (E,) float64."""
        L = np.ascontiguousarray(lengths, dtype=np.float64)
        A = np.ascontiguousarray(angles, dtype=np.float64)
        key = L.tobytes() + A.tobytes()
        if key not in self.kept:
            result, vjp = reconstruct_vjp(self.faces, self.edges, L, A, **self.keywords)
            self.kept[key] = (result.vertices, vjp)
            while len(self.kept) > KEPT:
                self.kept.popitem(last=False)
        self.kept.move_to_end(key)
        return self.kept[key]


def _n_vertices(faces: ArrayLike, keywords: dict[str, Any]) -> int:
    """n, the answer's vertex count: ``keywords["n_vertices"]``; else, for a real file's
    forms, the file's (``len(weld_map)``, or ``vertex_map.max() + 1``: as
    :func:`solver.reconstruct` counts them); else ``faces.max() + 1``."""
    n = keywords.get("n_vertices")
    if n is not None:
        return int(n)
    if keywords.get("weld_map") is not None:
        return len(np.asarray(keywords["weld_map"]).reshape(-1))
    if keywords.get("vertex_map") is not None:
        return int(np.max(keywords["vertex_map"])) + 1
    return int(np.max(faces)) + 1


def jax_reconstruction(faces: ArrayLike, edges: ArrayLike,
                       **keywords: Any) -> Callable[[Any, Any], Any]:
    """The reconstruction as a JAX function with a custom VJP.

    Args:
        faces: (m, 3) int, counter-clockwise.
        edges: (E, 2) int, the faces' edges.
        **keywords: the keywords of :func:`solver.reconstruct` (constraints fixed).

    Returns:
        ``f(lengths (E,), angles (E,)) -> vertices (n, 3)``, float64 JAX arrays.

    Raises:
        ImportError: jax is not installed.
        RuntimeError: ``jax_enable_x64`` is off.
    """
    import jax
    import jax.numpy as jnp

    if not jax.config.jax_enable_x64:
        raise RuntimeError('jax_reconstruction needs float64: jax.config.update('
                           '"jax_enable_x64", True) before creating arrays')
    kept = _KeptVJPs(faces, edges, keywords)
    n, E = _n_vertices(faces, keywords), len(np.asarray(edges))
    vertices_shape = jax.ShapeDtypeStruct((n, 3), jnp.float64)
    form_shape = jax.ShapeDtypeStruct((E,), jnp.float64)

    def host_forward(L: np.ndarray, A: np.ndarray) -> np.ndarray:
        return kept(L, A)[0]

    def host_backward(L: np.ndarray, A: np.ndarray, g: np.ndarray,
                      ) -> tuple[np.ndarray, np.ndarray]:
        return kept(L, A)[1](np.asarray(g))

    @jax.custom_vjp
    def reconstruct(lengths: Any, angles: Any) -> Any:
        return jax.pure_callback(host_forward, vertices_shape, lengths, angles)

    def forward(lengths: Any, angles: Any) -> tuple[Any, tuple[Any, Any]]:
        return reconstruct(lengths, angles), (lengths, angles)

    def backward(saved: tuple[Any, Any], g: Any) -> tuple[Any, Any]:
        lengths, angles = saved
        return jax.pure_callback(host_backward, (form_shape, form_shape), lengths, angles, g)

    reconstruct.defvjp(forward, backward)
    return reconstruct


def torch_reconstruction(faces: ArrayLike, edges: ArrayLike,
                         **keywords: Any) -> Callable[[Any, Any], Any]:
    """The reconstruction as a ``torch.autograd.Function``.

    Args:
        faces: (m, 3) int, counter-clockwise.
        edges: (E, 2) int, the faces' edges.
        **keywords: the keywords of :func:`solver.reconstruct` (constraints fixed).

    Returns:
        ``f(lengths (E,), angles (E,)) -> vertices (n, 3)`` on tensors (computed on CPU in
        float64; the result has the dtype and device of ``lengths``).

    Raises:
        ImportError: torch is not installed.
    """
    import torch

    kept = _KeptVJPs(faces, edges, keywords)

    class Reconstruct(torch.autograd.Function):
        @staticmethod
        def forward(ctx: Any, lengths: Any, angles: Any) -> Any:
            vertices, vjp = kept(lengths.detach().cpu().double().numpy(),
                                 angles.detach().cpu().double().numpy())
            ctx.vjp = vjp
            return torch.as_tensor(vertices.copy(), dtype=lengths.dtype,
                                   device=lengths.device)

        @staticmethod
        def backward(ctx: Any, g: Any) -> tuple[Any, Any]:
            grad_L, grad_A = ctx.vjp(g.detach().cpu().double().numpy())
            return (torch.as_tensor(grad_L, dtype=g.dtype, device=g.device),
                    torch.as_tensor(grad_A, dtype=g.dtype, device=g.device))

    return Reconstruct.apply
