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

from .errors import ShapeMismatchError
from .validation import as_points


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
    moving_center, target_center = moving.mean(axis=0), target.mean(axis=0)
    covariance = (target - target_center).T @ (moving - moving_center)
    u, _, vt = np.linalg.svd(covariance)
    flip = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
    rotation = u @ flip @ vt
    translation = target_center - rotation @ moving_center
    aligned = moving @ rotation.T + translation
    distance = np.linalg.norm(aligned - target, axis=1)
    return Alignment(aligned, rotation, translation,
                     float(np.sqrt(np.mean(distance ** 2))) if len(distance) else 0.0,
                     float(distance.max(initial=0.0)))
