"""Rigid alignment of an answer to a reference mesh of the same connectivity (Kabsch).

A reconstruction from forms is determined up to a rigid motion; :func:`rigid_alignment`
moves it onto a reference (the mesh the forms came from, a scan, ...): the rotation and
translation minimizing the sum of squared vertex distances (no scaling, no reflection),
and the residual left, which says how far the shapes differ once placed.

Example:
    >>> import numpy as np
    >>> ref = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    >>> turned = ref @ np.array([[0., -1, 0], [1, 0, 0], [0, 0, 1]]).T + 5.0
    >>> fit = rigid_alignment(turned, ref)
    >>> bool(np.allclose(fit.vertices, ref)), fit.residual_rms < 1e-12
    (True, True)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ..core.errors import ShapeMismatchError
from ..core.validation import as_points


@dataclass(frozen=True)
class Alignment:
    """A rigid alignment.

    Attributes:
        vertices: (n, 3) float64 aligned vertices: ``vertices @ rotation.T + translation``.
        rotation: (3, 3) float64, a proper rotation (det +1).
        translation: (3,) float64.
        residual_rms: sqrt(mean_i |aligned_i - reference_i|^2), in the mesh's units.
        residual_max: max_i |aligned_i - reference_i|.
    """

    vertices: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    residual_rms: float
    residual_max: float

    def report(self) -> dict[str, Any]:
        """The report's ``alignment`` section (JSON-ready)."""
        return {"residual_rms": self.residual_rms, "residual_max": self.residual_max,
                "rotation": self.rotation.tolist(), "translation": self.translation.tolist(),
                "vertices": len(self.vertices)}


def rigid_alignment(vertices: ArrayLike, reference: ArrayLike, *,
                    field: str = "align_to") -> Alignment:
    """The rigid motion that puts ``vertices`` (n, 3) nearest to ``reference`` (n, 3).

    Args:
        vertices: (n, 3) the answer.
        reference: (n, 3) the reference, vertex for vertex.
        field: the name errors give for ``reference``.

    Returns:
        The :class:`Alignment`.

    Raises:
        ShapeMismatchError: ``reference`` has another number of vertices.
        NonFiniteValueError: a coordinate is NaN or infinite.
    """
    moving = as_points(vertices, "vertices")
    target = as_points(reference, field)
    if target.shape != moving.shape:
        raise ShapeMismatchError(
            f"the reference has {len(target)} vertices, the answer {len(moving)}: align to a "
            "mesh with the same vertices (the mesh the forms came from)", field=field)
    rotations, moving_center, target_center = kabsch(moving, target)
    rotation = rotations[0]
    translation = target_center[0] - rotation @ moving_center[0]
    aligned = moving @ rotation.T + translation
    distance = np.linalg.norm(aligned - target, axis=1)
    return Alignment(aligned, rotation, translation,
                     float(np.sqrt(np.mean(distance ** 2))) if len(distance) else 0.0,
                     float(distance.max(initial=0.0)))


def kabsch(source: np.ndarray, target: np.ndarray, group: np.ndarray | None = None
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The proper rotations that best map each group of ``source`` onto ``target`` (Kabsch).

    For every group ``g``, ``R_g`` minimizes ``sum_{v in g} |R_g (x_v - c_g) - (y_v - d_g)|^2``
    over rotations (det +1, no reflection), ``c_g`` and ``d_g`` the groups' centroids.

    Args:
        source, target: (n, 3) float64, vertex for vertex.
        group: (n,) int64 group of each point (e.g. its connected component); ``None``: one
            group.

    Returns:
        ``(rotations, source_centers, target_centers)``: (k, 3, 3), (k, 3), (k, 3) float64,
        ``k`` the number of groups; ``x -> R_g (x - c_g) + d_g`` is the fit of group ``g``.

    Example:
        >>> import numpy as np
        >>> X = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
        >>> R = np.array([[0., -1, 0], [1, 0, 0], [0, 0, 1]])
        >>> rotations, _, _ = kabsch(X, X @ R.T + 2.0)
        >>> bool(np.allclose(rotations[0], R))
        True
    """
    c = (np.zeros(len(source), dtype=np.int64) if group is None
         else np.asarray(group, dtype=np.int64))
    k = int(c.max(initial=0)) + 1
    if k == 1 and len(source):  # one group: no per-point gathers
        source_centers, target_centers = source.mean(axis=0)[None], target.mean(axis=0)[None]
        covariance = np.einsum("vi,vj->ij", target - target_centers,
                               source - source_centers)[None]
    else:
        counts = np.maximum(np.bincount(c, minlength=k), 1).astype(np.float64)[:, None]
        source_centers = np.stack([np.bincount(c, source[:, d], k) for d in range(3)],
                                  1) / counts
        target_centers = np.stack([np.bincount(c, target[:, d], k) for d in range(3)],
                                  1) / counts
        products = ((target - target_centers[c])[:, :, None]
                    * (source - source_centers[c])[:, None, :]).reshape(-1, 9)
        covariance = np.bincount((c[:, None] * 9 + np.arange(9)).ravel(), products.ravel(),
                                 9 * k).reshape(k, 3, 3)
    u, _, vt = np.linalg.svd(covariance)
    sign = np.sign(np.linalg.det(u @ vt))
    sign[sign == 0] = 1.0
    u[:, :, 2] *= sign[:, None]
    return u @ vt, source_centers, target_centers
