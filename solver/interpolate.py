"""Shape interpolation in form space: blend lengths and dihedral angles, then reconstruct.

Beyond the paper (which cites [WDAH10] for the idea): for each t the blended forms are
reconstructed with one solve and, by default, refined to the surface whose forms are
nearest to the blended ones (:mod:`solver.refine`; blended forms of two poses do not
integrate, and the linear answer alone shrinks), started from whichever of the linear answer
and the vertex blend ``(1 - t) A + t B`` is nearer to them. Each connected part of the result
is rigidly aligned (rotation + translation, no scale) to its vertex blend so it sits where a
user expects it. A non-manifold mesh is blended on its manifold cut (:mod:`solver.manifold`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from .errors import ShapeMismatchError
from .forms import fundamental_forms
from .manifold import manifold_topology
from .metrics import wrap_angle
from .options import InterpolateOptions, ReconstructOptions
from .placement import align_components, face_components
from .reconstruct import reconstruct
from .reports import Stages
from .validation import as_points


def rigid_alignment(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R (3, 3) and translation t (3,) minimizing ||source R^T + t - target|| (Kabsch)."""
    cs, ct = source.mean(axis=0), target.mean(axis=0)
    U, _, Vt = np.linalg.svd((source - cs).T @ (target - ct))
    d = np.sign(np.linalg.det(U @ Vt)) or 1.0
    R = (U @ np.diag([1.0, 1.0, d]) @ Vt).T
    return R, ct - cs @ R.T


def interpolate(vertices_a: ArrayLike, vertices_b: ArrayLike, faces: ArrayLike,
                t: float | Sequence[float], *, options: InterpolateOptions | None = None,
                return_reports: bool = False, **overrides: Any,
                ) -> np.ndarray | tuple[np.ndarray, list[dict[str, Any]]]:
    """Blend two meshes with the same faces in form space.

    Lengths blend linearly; dihedral angles along the shorter way round. For each t the
    blended forms are reconstructed (one solve of Eq. 5), refined unless ``refine=False``
    (see the module docstring) and aligned rigidly to (1 - t) A + t B.

    Args:
        vertices_a, vertices_b: (n, 3) the two embeddings (t = 0 and t = 1).
        faces: (m, 3) int, their faces.
        t: a blend value or a sequence of k of them.
        options: :class:`solver.options.InterpolateOptions`; ``max_seconds`` budgets the
            whole call, shared out evenly among the blend values still to compute (a
            refinement that runs out of its share returns its best shape,
            ``stop_reason: "time_limit"``).
        return_reports: also return the refinement reports.
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
    opts = InterpolateOptions.given(options, overrides)
    A = as_points(vertices_a, "vertices_a")
    B = as_points(vertices_b, "vertices_b")
    if A.shape != B.shape:
        raise ShapeMismatchError(f"vertices_b has shape {B.shape}, vertices_a {A.shape}",
                                 field="vertices_b")
    cut = manifold_topology(faces, A)[0]
    if not cut.is_identity:  # a non-manifold mesh: blended on its cut (solver.manifold)
        blended = interpolate(cut.to_cut(A), cut.to_cut(B), cut.faces, t, options=opts,
                              return_reports=True)
        out = np.asarray(blended[0])
        out = (cut.to_file(out)[0] if np.ndim(t) == 0
               else np.stack([cut.to_file(x)[0] for x in out]))
        return (out, blended[1]) if return_reports else out
    forms_a = fundamental_forms(A, faces)
    forms_b = fundamental_forms(B, forms_a.faces)
    components = face_components(np.asarray(forms_a.faces), len(A))[0]
    scalar = np.ndim(t) == 0
    ts = np.atleast_1d(np.asarray(t, dtype=np.float64))
    if not np.all(np.isfinite(ts)):
        raise ShapeMismatchError("t must be finite", field="t")
    results, reports = [], []
    stages = Stages()
    per_blend = ReconstructOptions.given(opts, {"check_integrability": False})
    for k, s in enumerate(ts):  # one solve (and refinement) per requested blend value
        lengths = (1 - s) * forms_a.lengths + s * forms_b.lengths
        angles = wrap_angle(forms_a.angles + s * wrap_angle(forms_b.angles - forms_a.angles))
        linear = (1 - s) * A + s * B
        left = stages.left(opts.max_seconds)
        share = None if left is None else left / (len(ts) - k)
        # The refinement starts from the better of the layout fit and the vertex blend.
        rec = reconstruct(forms_a.faces, forms_a.edges, lengths, angles, n_vertices=len(A),
                          options=per_blend.replace(max_seconds=share), initial_guess=linear)
        vertices, report = rec.vertices, rec.report["refinement"]
        if report.get("start") == "initial guess":
            report["start"] = "vertex blend"
        # Every part moved rigidly onto its vertex blend (one part: one rigid alignment).
        results.append(align_components(vertices, linear, components))
        reports.append(report)
    out = results[0] if scalar else np.stack(results)
    return (out, reports) if return_reports else out
