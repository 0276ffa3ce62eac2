"""Shape interpolation in form space: the two-shape case of :func:`solver.blend`.

Beyond the paper (which cites [WDAH10] for the idea): for each t the blended forms (lengths
in log space, dihedral angles along the shorter way round) are reconstructed and, by
default, refined to the surface whose forms are nearest to them (:mod:`solver.refine`;
blended forms of two poses do not integrate, and the linear answer alone shrinks), started
from whichever of the linear answer and the vertex blend ``(1 - t) A + t B`` is nearer to
them; a list of t is solved as a sequence (:mod:`solver.shape_space`). The result is rigidly
aligned (rotation + translation, no scale) to the vertex blend so it sits where a user
expects it. A non-manifold mesh is blended on its manifold cut (:mod:`solver.mesh.manifold`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from .core.errors import ShapeMismatchError
from .core.validation import as_points
from .options import BlendOptions, InterpolateOptions
from .reports import Progress
from .shape_space import blend

__all__ = ["interpolate", "two_shape_weights"]


def two_shape_weights(t: float | Sequence[float]) -> np.ndarray:
    """Rows ``(1 - t, t)`` (k, 2) float64 of blend values ``t`` (a number or k of them).

    Raises:
        ShapeMismatchError: a t that is not finite (``field="t"``).
    """
    ts = np.atleast_1d(np.asarray(t, dtype=np.float64)).ravel()
    if not np.all(np.isfinite(ts)):
        raise ShapeMismatchError("t must be finite", field="t")
    return np.stack([1.0 - ts, ts], axis=1)


def interpolate(vertices_a: ArrayLike, vertices_b: ArrayLike, faces: ArrayLike,
                t: float | Sequence[float], *, options: InterpolateOptions | None = None,
                return_reports: bool = False, progress: Progress | None = None,
                **overrides: Any,
                ) -> np.ndarray | tuple[np.ndarray, list[dict[str, Any]]]:
    """Blend two meshes with the same faces in form space (:func:`solver.blend` of ``(A, B)``
    with rows ``(1 - t, t)``).

    Args:
        vertices_a, vertices_b: (n, 3) the two embeddings (t = 0 and t = 1).
        faces: (m, 3) int, their faces.
        t: a blend value or a sequence of k of them (outside [0, 1]: extrapolation).
        options: :class:`solver.options.InterpolateOptions`; ``max_seconds`` budgets the
            whole call, shared out evenly among the blend values still to compute (a
            refinement that runs out of its share returns its best shape,
            ``stop_reason: "time_limit"``).
        return_reports: also return the refinement reports.
        progress: optional ``progress("rows", fraction)`` after each blend value.
        **overrides: fields of ``options`` given as keywords.

    Returns:
        (n, 3) for a scalar t, (k, n, 3) for a sequence of k values; with
        ``return_reports`` also a list (one per t) of the refinement reports
        (``{"refined": False, ...}`` where nothing was refined).

    Example:
        >>> import numpy as np
        >>> from solver import interpolate
        >>> V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 0.5]])
        >>> F = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
        >>> W = V * [1.0, 1.0, 2.0]  # a taller pyramid
        >>> ends = interpolate(V, W, F, [0.0, 1.0])
        >>> bool(np.allclose(ends[0], V, atol=1e-6)), bool(np.allclose(ends[1], W, atol=1e-6))
        (True, True)
    """
    opts = BlendOptions.given(InterpolateOptions.given(options, overrides), {})
    A = as_points(vertices_a, "vertices_a")
    B = as_points(vertices_b, "vertices_b")
    if A.shape != B.shape:
        raise ShapeMismatchError(f"vertices_b has shape {B.shape}, vertices_a {A.shape}",
                                 field="vertices_b")
    result = blend([A, B], two_shape_weights(t), faces, options=opts, progress=progress)
    reports = [row["refinement"] for row in result.reports]
    out = result.vertices[0] if np.ndim(t) == 0 else result.vertices
    return (out, reports) if return_reports else out
