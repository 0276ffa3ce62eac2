"""Shape interpolation in form space: blend lengths and dihedral angles, then reconstruct.

Beyond the paper (which cites [WDAH10] for the idea): for each t the blended forms are
reconstructed with one solve and, by default, refined to the surface whose forms are
nearest to the blended ones (:mod:`solver.refine`; blended forms of two poses do not
integrate, and the linear answer alone shrinks), started from whichever of the linear answer
and the vertex blend ``(1 - t) A + t B`` is nearer to them. The result is rigidly aligned
(rotation + translation, no scale) to the vertex blend so it sits where a user expects it.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from .errors import ShapeMismatchError
from .forms import fundamental_forms
from .metrics import wrap_angle
from .reconstruct import reconstruct
from .refine import ANGLE_WEIGHT
from .system import Weighting
from .validation import as_points


def rigid_alignment(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R (3, 3) and translation t (3,) minimizing ||source R^T + t - target|| (Kabsch)."""
    cs, ct = source.mean(axis=0), target.mean(axis=0)
    U, _, Vt = np.linalg.svd((source - cs).T @ (target - ct))
    d = np.sign(np.linalg.det(U @ Vt)) or 1.0
    R = (U @ np.diag([1.0, 1.0, d]) @ Vt).T
    return R, ct - cs @ R.T


def interpolate(vertices_a: ArrayLike, vertices_b: ArrayLike, faces: ArrayLike,
                t: float | Sequence[float], *, frame_weight: float = 1000.0,
                weighting: Weighting = "uniform", backend: str = "auto",
                refine: bool | None = None, angle_weight: float = ANGLE_WEIGHT,
                max_seconds: float | None = None, return_reports: bool = False,
                ) -> np.ndarray | tuple[np.ndarray, list[dict[str, Any]]]:
    """Blend two meshes with the same faces in form space.

    Lengths blend linearly; dihedral angles along the shorter way round. For each t the
    blended forms are reconstructed (one solve of Eq. 5), refined unless ``refine=False``
    (see the module docstring) and aligned rigidly to (1 - t) A + t B.

    ``max_seconds``: optional wall-clock budget of the whole call, shared out evenly among
    the blend values still to compute; a refinement that runs out of its share returns its
    best shape (``stop_reason: "time_limit"``).

    Returns:
        (n, 3) for a scalar t, (k, n, 3) for a sequence of k values; with
        ``return_reports`` also a list (one per t) of the refinement reports
        (``{"refined": False, ...}`` where nothing was refined).
    """
    A = as_points(vertices_a, "vertices_a")
    B = as_points(vertices_b, "vertices_b")
    if A.shape != B.shape:
        raise ShapeMismatchError(f"vertices_b has shape {B.shape}, vertices_a {A.shape}",
                                 field="vertices_b")
    forms_a = fundamental_forms(A, faces)
    forms_b = fundamental_forms(B, forms_a.faces)
    scalar = np.ndim(t) == 0
    ts = np.atleast_1d(np.asarray(t, dtype=np.float64))
    if not np.all(np.isfinite(ts)):
        raise ShapeMismatchError("t must be finite", field="t")
    results, reports = [], []
    started = time.perf_counter()
    for k, s in enumerate(ts):  # one solve (and refinement) per requested blend value
        lengths = (1 - s) * forms_a.lengths + s * forms_b.lengths
        angles = wrap_angle(forms_a.angles + s * wrap_angle(forms_b.angles - forms_a.angles))
        linear = (1 - s) * A + s * B
        share = None if max_seconds is None else (
            (max_seconds - (time.perf_counter() - started)) / (len(ts) - k))
        # The refinement starts from the better of the layout fit and the vertex blend.
        rec = reconstruct(forms_a.faces, forms_a.edges, lengths, angles, n_vertices=len(A),
                          frame_weight=frame_weight, weighting=weighting, backend=backend,
                          check_integrability=False, refine=refine, angle_weight=angle_weight,
                          initial_guess=linear, max_seconds=share)
        vertices, report = rec.vertices, rec.report["refinement"]
        if report.get("start") == "initial guess":
            report["start"] = "vertex blend"
        R, shift = rigid_alignment(vertices, linear)
        results.append(vertices @ R.T + shift)
        reports.append(report)
    out = results[0] if scalar else np.stack(results)
    return (out, reports) if return_reports else out
