"""Distortion between two embeddings of one connectivity, or an embedding and target forms.

All functions are vectorized; per-element arrays are aligned with the sorted edge list
(edges) or with the faces. Summaries give mean, rms, max and the 95th percentile;
histograms give counts over fixed bin edges so reports are comparable across meshes.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ..core.validation import as_points
from .forms import Forms, forms_of, fundamental_forms
from .topology import build_topology

HISTOGRAM_BINS = 20
"""Bins of every histogram in a distortion report."""


def wrap_angle(angle: np.ndarray) -> np.ndarray:
    """Map angles to (-pi, pi].

    Args:
        angle: array of angles (radians).

    Returns:
        float64 array of the same shape.

    Example:
        >>> import numpy as np
        >>> from solver.mesh.metrics import wrap_angle
        >>> wrap_angle(np.array([1.5 * np.pi, -np.pi, 0.25])).round(4).tolist()
        [-1.5708, 3.1416, 0.25]
    """
    wrapped = np.mod(angle + np.pi, 2 * np.pi) - np.pi
    return np.where(wrapped <= -np.pi, np.pi, wrapped)


def corner_angles(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Interior angle at each corner of each face.

    Args:
        vertices: (n, 3) float64.
        faces: (m, 3) int64.

    Returns:
        (m, 3) float64 angles (radians); corner k of face t is at ``faces[t, k]``.
    """
    P = vertices[faces]                                # (m, 3, 3)
    u = np.roll(P, -1, axis=1) - P                     # to next corner
    v = np.roll(P, 1, axis=1) - P                      # to previous corner
    cross = np.linalg.norm(np.cross(u, v), axis=2)
    return np.arctan2(cross, np.einsum("tkc,tkc->tk", u, v))


def summary(values: np.ndarray) -> dict[str, float]:
    """Mean, rms, max and 95th percentile of ``|values|``.

    Args:
        values: array of any shape.

    Returns:
        ``{"mean", "rms", "max", "p95"}`` floats, zeros for an empty array.

    Example:
        >>> from solver.mesh.metrics import summary
        >>> summary([3.0, -4.0])
        {'mean': 3.5, 'rms': 3.5355339059327378, 'max': 4.0, 'p95': 3.95}
    """
    a = np.abs(np.asarray(values, dtype=np.float64))
    if a.size == 0:
        return {"mean": 0.0, "rms": 0.0, "max": 0.0, "p95": 0.0}
    return {"mean": float(a.mean()), "rms": float(np.sqrt((a**2).mean())),
            "max": float(a.max()), "p95": float(np.percentile(a, 95))}


def histogram(values: np.ndarray, upper: float | None = None,
              bins: int = HISTOGRAM_BINS) -> dict[str, list[float]]:
    """Counts of ``|values|`` over equal bins.

    Args:
        values: array of any shape.
        upper: top of the range [0, upper] (default the largest ``|value|``); larger values
            count in the last bin.
        bins: number of bins.

    Returns:
        ``{"counts": [bins ints], "bin_edges": [bins + 1 floats]}``.
    """
    a = np.abs(np.asarray(values, dtype=np.float64))
    top = float(upper if upper is not None else (a.max() if a.size else 1.0)) or 1.0
    counts, edges = np.histogram(np.minimum(a, top), bins=bins, range=(0.0, top))
    return {"counts": counts.tolist(), "bin_edges": edges.tolist()}


def edge_values_to_vertices(edges: np.ndarray, values: np.ndarray, n_vertices: int,
                            ) -> np.ndarray:
    """The largest ``|value|`` over the edges at each vertex (for colour maps).

    Args:
        edges: (E, 2) int64.
        values: (E,) float64.
        n_vertices: n.

    Returns:
        (n,) float64, 0 at vertices without edges.
    """
    out = np.zeros(n_vertices)
    a = np.abs(values)
    np.maximum.at(out, edges[:, 0], a)
    np.maximum.at(out, edges[:, 1], a)
    return out


def forms_distortion(forms: Forms, target_lengths: ArrayLike, target_angles: ArrayLike,
                     n_vertices: int | None = None) -> dict[str, Any]:
    """Change of edge lengths (relative) and dihedral angles (radians) from target forms.

    Args:
        forms: the forms of an embedding.
        target_lengths: (E,) float target edge lengths.
        target_angles: (E,) float target dihedral angles.
        n_vertices: vertex count (default ``faces.max() + 1``).

    Returns:
        A dict with per-edge (E,) arrays ``length_change`` (relative, signed) and
        ``angle_change`` (signed, wrapped), per-vertex (n,) ``vertex`` (max |change| of
        either kind over incident edges, relative length and radians summed), their
        summaries (``length_summary``, ``angle_summary``) and histograms.
    """
    L0 = np.asarray(target_lengths, dtype=np.float64)
    A0 = np.asarray(target_angles, dtype=np.float64)
    length_change = forms.lengths / L0 - 1.0
    angle_change = wrap_angle(forms.angles - A0)
    n = int(forms.faces.max()) + 1 if n_vertices is None else n_vertices
    vertex = (edge_values_to_vertices(forms.edges, length_change, n)
              + edge_values_to_vertices(forms.edges, angle_change, n))
    return {
        "length_change": length_change, "angle_change": angle_change, "vertex": vertex,
        "length_summary": summary(length_change), "angle_summary": summary(angle_change),
        "length_histogram": histogram(length_change),
        "angle_histogram": histogram(angle_change),
    }


def distortion(vertices_ref: ArrayLike, vertices: ArrayLike, faces: ArrayLike, *,
               coincident: bool = True) -> dict[str, Any]:
    """Distortion of ``vertices`` relative to ``vertices_ref`` (same faces).

    Args:
        vertices_ref: (n, 3) float reference embedding.
        vertices: (n, 3) float embedding to measure.
        faces: (m, 3) int, counter-clockwise.
        coincident: weld the reference's vertices at one position
            (:func:`solver.mesh.forms.fundamental_forms`); False for a mesh already cut (its
            split copies sit at one position).

    Returns:
        :func:`forms_distortion`'s entries plus per-face (m,) ``face_angle_change`` (max
        |change| of the three corner angles, radians) and ``area_ratio`` (area / reference
        area; a reference face of zero area counts 1 while it keeps zero area, else its
        area over the smallest positive reference area), with their summaries
        (``area_ratio_summary`` of ``area_ratio - 1``).

    Raises:
        SolverInputError: a subclass naming the first malformed element of either mesh.

    Example:
        Scaling a tetrahedron by 2 doubles every length and quadruples every area, and
        changes no angle:

        >>> import numpy as np
        >>> from solver.mesh.metrics import distortion
        >>> corners = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
        >>> faces = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]
        >>> report = distortion(corners, 2.0 * corners, faces)
        >>> report["length_summary"]["max"], report["area_ratio"].round(12).tolist()
        (1.0, [4.0, 4.0, 4.0, 4.0])
        >>> bool(report["face_angle_summary"]["max"] < 1e-12)
        True
    """
    V0 = as_points(vertices_ref, "vertices_ref")
    V1 = as_points(vertices, "vertices")
    rest = fundamental_forms(V0, faces, coincident=coincident)
    if rest.vertex_map is not None:  # a non-manifold mesh: measured on its cut
        V0, V1 = V0[rest.vertex_map], V1[rest.vertex_map]
    # The measured shape may have collapsed a face: it is measured, not refused.
    now = forms_of(V1, build_topology(rest.faces, n_vertices=len(V0)), allow_degenerate=True)
    report = forms_distortion(now, rest.lengths, rest.angles, len(V0))
    F = rest.faces
    with np.errstate(invalid="ignore", divide="ignore"):  # a collapsed face: changed by pi
        corner_change = np.nan_to_num(
            np.abs(corner_angles(V1, F) - corner_angles(V0, F)).max(axis=1), nan=np.pi)
    area0 = 0.5 * np.linalg.norm(np.cross(V0[F[:, 1]] - V0[F[:, 0]], V0[F[:, 2]] - V0[F[:, 0]]),
                                 axis=1)
    area1 = 0.5 * np.linalg.norm(np.cross(V1[F[:, 1]] - V1[F[:, 0]], V1[F[:, 2]] - V1[F[:, 0]]),
                                 axis=1)
    # A rest face of zero area (issue 40) has no area ratio: 1 where it stays of zero area,
    # the ratio to the smallest positive rest area where it opens.
    positive = area0[area0 > 0]
    floor = positive.min() if len(positive) else 1.0
    opened = np.where(area1 > 0, area1 / floor, 1.0)
    ratio = np.divide(area1, area0, out=opened, where=area0 > 0)
    report.update({
        "face_angle_change": corner_change, "area_ratio": ratio,
        "face_angle_summary": summary(corner_change),
        "area_ratio_summary": summary(ratio - 1.0),
    })
    return report


def compact(report: dict[str, Any]) -> dict[str, Any]:
    """A distortion report without per-element arrays.

    Args:
        report: from :func:`distortion` or :func:`forms_distortion`.

    Returns:
        The same dict without its arrays, except the per-vertex ``vertex`` (for colours).
    """
    return {k: v for k, v in report.items() if not isinstance(v, np.ndarray) or k == "vertex"}
