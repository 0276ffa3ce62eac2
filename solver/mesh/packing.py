"""Packing: place flattened charts in the unit square, apart, at a documented padding.

The placement is xatlas's packer (``xatlas`` on PyPI, the packer of the xatlas library used
by Blender add-ons and game pipelines): each chart is handed over as a uv island of its own
(``Atlas.add_uv_mesh``), rasterized at ``texels_per_unit`` and placed on the atlas's texel
grid with ``padding`` free texels around it, never rotated by xatlas (its axis-aligning
rotation mirrors some charts) but turned by :func:`principal_rotation` first so its long
axis lies along u. Every chart keeps its shape: the packed chart is the flattened chart
times one rotation, one global scale and a translation (:func:`similarity_fit` checks it).

:func:`packing_efficiency` is the fraction of the unit square the charts cover, the number
bench/flatten.py compares with xatlas's own atlases.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PackingRules:
    """The packer's settings (one home for their values).

    Attributes:
        resolution: texels along the longer side the atlas is aimed at (2048 packs tighter
            than 1024: 0.635 against 0.618 of the unit square on the shared bunny's 28
            charts, 0.4 s against 0.15 s; xatlas's brute-force search reached 0.672 in 49 s).
        padding: free texels around every chart (at ``resolution``: 2 / 2048 of the side).
        target_efficiency: the coverage assumed when choosing ``texels_per_unit``.
    """

    resolution: int = 2048
    padding: int = 2
    target_efficiency: float = 0.7


@dataclass(frozen=True)
class Packed:
    """The packed atlas.

    Attributes:
        texcoords: (k, 2) float64 uv in the unit square, one per input uv vertex.
        scale: 3D length units per unit of ``texcoords`` (texcoords * scale is the
            flat layout in the mesh's units).
        side_texels: texels along the atlas's longer side.
        padding: the padding, as a fraction of the unit square's side.
        efficiency: fraction of the unit square covered by charts.
    """

    texcoords: np.ndarray
    scale: float
    side_texels: int
    padding: float
    efficiency: float


def signed_areas(uv: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(m,) float64 signed areas of the triangles ``faces`` (m, 3) over ``uv`` (k, 2)."""
    e1, e2 = uv[faces[:, 1]] - uv[faces[:, 0]], uv[faces[:, 2]] - uv[faces[:, 0]]
    return 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


def folded(uv: np.ndarray, faces: np.ndarray, ignore: np.ndarray | None = None,
           strict: bool = False) -> np.ndarray:
    """(m,) bool, the ``faces`` (m, 3) flipped over ``uv`` (k, 2): signed area <= 0 (< 0
    with ``strict``), except the faces ``ignore`` (k,) int64: faces of zero area in 3D
    (collinear corners, issue 40), whose uv area is 0 up to rounding, of either sign, and
    says nothing about a fold."""
    area = signed_areas(uv, faces)
    out = area < 0 if strict else area <= 0
    if ignore is not None and len(ignore):
        out[ignore] = False
    return out


def principal_rotation(points: np.ndarray) -> np.ndarray:
    """(2, 2) rotation (det +1) turning the principal axis of ``points`` (k, 2) onto u
    (:func:`_principal_rotations` of one chart)."""
    return _principal_rotations(points, np.zeros(len(points), dtype=np.int64), 1)[0]


def packing_efficiency(texcoords: np.ndarray, faces: np.ndarray) -> float:
    """Covered fraction of the unit square: the charts' total |area| (no overlap assumed)."""
    return float(np.abs(signed_areas(texcoords, faces)).sum())


def pack_charts(uv: np.ndarray, faces: np.ndarray, face_chart: np.ndarray,
                rules: PackingRules | None = None) -> Packed:
    """Pack the charts of a layout into the unit square.

    Args:
        uv: (k, 2) float64 flattened charts in 3D units (each chart's uv vertices its own).
        faces: (m, 3) int64 triangles over ``uv``.
        face_chart: (m,) int64 chart of each face (charts share no uv vertex).
        rules: :class:`PackingRules`.

    Returns:
        :class:`Packed`.
    """
    import xatlas

    rules = rules or PackingRules()
    uv = np.asarray(uv, dtype=np.float64)
    members = _chart_vertices(faces, face_chart, len(uv))
    turned = _turn_charts(uv, members)
    area = float(np.abs(signed_areas(turned, faces)).sum())
    options = xatlas.PackOptions()
    options.padding = rules.padding
    options.rotate_charts = False
    options.rotate_charts_to_axis = False
    texels_per_unit = rules.resolution * np.sqrt(rules.target_efficiency / area)
    # Handed over in texels (texels_per_unit 1): in the mesh's units a chart of a few texels
    # can fall under xatlas's float32 area threshold, and xatlas then leaves it unplaced
    # (the 69K-face scan: charts of one or two faces piled at the corner).
    options.texels_per_unit = 1.0
    atlas = xatlas.Atlas()
    atlas.add_uv_mesh((turned * texels_per_unit).astype(np.float32), faces.astype(np.uint32),
                      face_chart.astype(np.uint32)[:, None])
    atlas.generate(pack_options=options)
    mapping, _, out_uv = atlas.get_mesh(0)
    side = max(atlas.width, atlas.height)
    texels = out_uv.astype(np.float64) * [atlas.width, atlas.height]
    texcoords = np.zeros_like(uv)
    texcoords[mapping.astype(np.int64)] = texels / side
    # Exact shapes: map each chart back by the similarity xatlas applied (translation and
    # the one scale), so float32 rounding never reaches the layout.
    scale = 1.0 / (texels_per_unit / side)
    texcoords = _exact_translation(turned, texcoords, members, scale)
    return Packed(texcoords, scale, int(side), rules.padding / side,
                  packing_efficiency(texcoords, faces))


def _chart_vertices(faces: np.ndarray, face_chart: np.ndarray, k: int,
                    ) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices, chart)``: the (j,) int64 uv vertices that faces use, ascending, and the
    (j,) int64 rank of each one's chart among the charts (ascending chart labels)."""
    vertex_chart = np.full(k, -1, dtype=np.int64)
    vertex_chart[faces.ravel()] = np.repeat(face_chart, 3)
    vertices = np.flatnonzero(vertex_chart >= 0)
    labels = vertex_chart[vertices]
    return vertices, np.searchsorted(np.unique(labels), labels)


def _chart_sums(chart: np.ndarray, values: np.ndarray, count: int) -> np.ndarray:
    """(count, c) the sums of ``values`` (j, c) per ``chart`` (j,)."""
    return np.stack([np.bincount(chart, values[:, i], count) for i in range(values.shape[1])],
                    axis=1)


def _principal_rotations(points: np.ndarray, chart: np.ndarray, count: int) -> np.ndarray:
    """(count, 2, 2) :func:`principal_rotation` of each chart's ``points`` (j, 2)."""
    size = np.bincount(chart, minlength=count)[:, None]
    centred = points - (_chart_sums(chart, points, count) / size)[chart]
    x, y = centred.T
    xx, xy, yy = _chart_sums(chart, np.stack([x * x, x * y, y * y], axis=1), count).T
    _, vectors = np.linalg.eigh(np.stack([np.stack([xx, xy], -1), np.stack([xy, yy], -1)], 1))
    rotation = np.swapaxes(vectors[:, :, ::-1], 1, 2).copy()
    rotation[np.linalg.det(rotation) < 0, 1] *= -1
    return rotation


def _turn_charts(uv: np.ndarray, members: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Each chart turned by :func:`principal_rotation` and set apart along u, in order of
    its label (xatlas welds uv vertices at equal positions, which would join charts); all
    charts at once. ``members``: :func:`_chart_vertices`."""
    turned = uv.copy()
    vertices, chart = members
    count = int(chart.max()) + 1 if len(chart) else 0
    rotation = _principal_rotations(uv[vertices], chart, count)
    points = np.einsum("jab,jb->ja", rotation[chart], uv[vertices])
    low = np.full((count, 2), np.inf)
    high = np.full((count, 2), -np.inf)
    np.minimum.at(low, chart, points)
    np.maximum.at(high, chart, points)
    widths = (high[:, 0] - low[:, 0]) * 1.5 + 1e-9
    cursor = np.concatenate([[0.0], np.cumsum(widths)[:-1]])
    turned[vertices] = points - low[chart] + np.stack([cursor, np.zeros(count)], 1)[chart]
    return turned


def _exact_translation(turned: np.ndarray, texcoords: np.ndarray,
                       members: tuple[np.ndarray, np.ndarray], scale: float) -> np.ndarray:
    """Per chart: ``turned / scale`` moved onto xatlas's placement by the rigid motion
    that fits it best (Procrustes, never a mirror); all charts at once. ``members``:
    :func:`_chart_vertices`."""
    exact = turned / scale
    vertices, chart = members
    count = int(chart.max()) + 1 if len(chart) else 0
    size = np.bincount(chart, minlength=count)[:, None]
    source, target = exact[vertices], texcoords[vertices]
    s_mean = _chart_sums(chart, source, count) / size
    t_mean = _chart_sums(chart, target, count) / size
    a, b = source - s_mean[chart], target - t_mean[chart]
    cross = _chart_sums(chart, (a[:, :, None] * b[:, None, :]).reshape(-1, 4), count)
    u, _, vt = np.linalg.svd(cross.reshape(-1, 2, 2))
    mirrored = np.linalg.det(u @ vt) < 0    # never a mirror: keep the chart's orientation
    u[mirrored, :, 1] *= -1
    rotation = u @ vt
    exact[vertices] = np.einsum("ja,jab->jb", a, rotation[chart]) + t_mean[chart]
    return exact


def rasterized_overlap(texcoords: np.ndarray, faces: np.ndarray, resolution: int = 1024,
                       ) -> int:
    """Texel centres of a ``resolution``² grid over the unit square covered by two or more
    triangles (strictly inside each): 0 for a layout without overlap.

    Vectorized: every triangle's bounding box of texel centres is enumerated at once.

    Example:
        >>> import numpy as np
        >>> uv = np.array([[0.1, 0.1], [0.9, 0.1], [0.1, 0.9], [0.9, 0.9]])
        >>> rasterized_overlap(uv, np.array([[0, 1, 2], [1, 3, 2]]), 64)
        0
        >>> rasterized_overlap(uv, np.array([[0, 1, 2], [0, 3, 2]]), 64) > 0
        True
    """
    counts = texel_coverage(texcoords, faces, resolution)
    return int((counts > 1).sum())


BOUNDARY_CELL_LIMIT = 64
"""A boundary edge whose bounding box covers more grid cells than this (cells one mean edge
wide) is tested against every other edge by :func:`boundary_crossings`; the others only
against the edges that share a cell with them."""


def boundary_crossings(uv: np.ndarray, faces: np.ndarray, chunk: int = 2_000_000) -> int:
    """Pairs of boundary edges of the layout ``uv`` (k, 2) over ``faces`` (m, 3) that cross
    (proper intersections; pairs sharing a vertex are skipped): 0 for a flip-free chart
    means its layout does not overlap itself (a locally injective map of a disk whose
    boundary stays simple is injective). Only edges whose bounding boxes share a cell of a
    grid one mean edge wide are tested (two edges cross at a point inside both boxes), so
    the time grows with the boundary's length, not its square; vectorized, ``chunk`` pairs
    at a time.

    Example:
        >>> import numpy as np
        >>> square = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=float)
        >>> boundary_crossings(square, np.array([[0, 1, 2], [0, 2, 3]]))
        0
        >>> bow = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], dtype=float)
        >>> boundary_crossings(bow, np.array([[0, 1, 2], [0, 2, 3]]))
        1
    """
    half = np.stack([faces, np.roll(faces, -1, axis=1)], axis=-1).reshape(-1, 2)
    key = np.sort(half, axis=1)
    _, first, count = np.unique(key, axis=0, return_index=True, return_counts=True)
    segments = half[first[count == 1]]                                 # (B, 2)
    ii, jj = _nearby_pairs(uv, segments)
    keep = ((segments[ii, 0] != segments[jj, 0]) & (segments[ii, 0] != segments[jj, 1])
            & (segments[ii, 1] != segments[jj, 0]) & (segments[ii, 1] != segments[jj, 1]))
    ii, jj = ii[keep], jj[keep]
    p, r = uv[segments[:, 0]], uv[segments[:, 1]] - uv[segments[:, 0]]
    total = 0
    for start in range(0, len(ii), chunk):          # bounded memory: a loop over chunks
        i, j = ii[start:start + chunk], jj[start:start + chunk]
        denominator = r[i, 0] * r[j, 1] - r[i, 1] * r[j, 0]
        d = p[j] - p[i]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (d[:, 0] * r[j, 1] - d[:, 1] * r[j, 0]) / denominator
            u = (d[:, 0] * r[i, 1] - d[:, 1] * r[i, 0]) / denominator
        total += int(((t > 0) & (t < 1) & (u > 0) & (u < 1)).sum())
    return total


def _nearby_pairs(uv: np.ndarray, segments: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(i, j)`` (q,) int64 each pair i < j of ``segments`` (B, 2) whose bounding boxes in
    ``uv`` share a cell of a grid one mean segment long (every pair with a segment that
    covers more than :data:`BOUNDARY_CELL_LIMIT` cells), once each."""
    b = len(segments)
    if b < 2:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    ends = uv[segments]                                                 # (B, 2, 2)
    low, high = ends.min(axis=1), ends.max(axis=1)
    extent = float((high.max(axis=0) - low.min(axis=0)).max())
    size = max(float(np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1).mean()), extent * 1e-6,
               np.finfo(float).tiny)
    origin = low.min(axis=0)
    first_cell = np.floor((low - origin) / size).astype(np.int64)
    last_cell = np.floor((high - origin) / size).astype(np.int64)
    span = last_cell - first_cell + 1
    cells = span[:, 0] * span[:, 1]
    long = np.flatnonzero(cells > BOUNDARY_CELL_LIMIT)
    short = np.flatnonzero(cells <= BOUNDARY_CELL_LIMIT)
    # Every (segment, cell) of the short segments' boxes, then pairs within each cell.
    owner = np.repeat(short, cells[short])
    rank = np.arange(len(owner)) - np.repeat(np.cumsum(cells[short]) - cells[short],
                                             cells[short])
    cx = first_cell[owner, 0] + rank // span[owner, 1]
    cy = first_cell[owner, 1] + rank % span[owner, 1]
    cell_key = cx * (int(last_cell[:, 1].max()) + 1) + cy
    order = np.argsort(cell_key, kind="stable")
    cell_key, owner = cell_key[order], owner[order]
    end = np.searchsorted(cell_key, cell_key, side="right")
    partners = end - np.arange(len(owner)) - 1
    left = np.repeat(np.arange(len(owner)), partners)
    right = left + 1 + (np.arange(len(left)) - np.repeat(np.cumsum(partners) - partners,
                                                         partners))
    a = np.concatenate([owner[left], np.repeat(long, b)])
    c = np.concatenate([owner[right], np.tile(np.arange(b), len(long))])
    i, j = np.minimum(a, c), np.maximum(a, c)
    pair = np.unique(i[i != j] * b + j[i != j])
    return pair // b, pair % b


def positive_loops(uv: np.ndarray, loops: list[np.ndarray]) -> int:
    """How many of the vertex ``loops`` (each (k,) int64, in boundary half-edge order) run
    counter-clockwise in the layout ``uv`` (k, 2) (positive shoelace area).

    A flip-free chart whose boundary edges do not cross (:func:`boundary_crossings`) covers
    a point as many times as the positive loops around it, less the negative ones; with
    exactly one positive loop (its outline; every hole negative) it covers no point twice.
    Two positive loops mean a hole laid out inside out: the faces around it wrap over it
    (a boundary vertex whose uv angles add up past a full turn), which no boundary edge
    crossing shows. A loop over loops (a chart has few).

    Example:
        >>> import numpy as np
        >>> square = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=float)
        >>> positive_loops(square, [np.array([0, 1, 2, 3]), np.array([3, 2, 1, 0])])
        1
    """
    count = 0
    for loop in loops:
        p = uv[loop]
        q = np.roll(p, -1, axis=0)
        count += int((p[:, 0] * q[:, 1] - p[:, 1] * q[:, 0]).sum() > 0)
    return count


def texel_coverage(texcoords: np.ndarray, faces: np.ndarray, resolution: int,
                   ) -> np.ndarray:
    """(resolution, resolution) int64 how many triangles cover each texel centre."""
    corners = texcoords[faces] * resolution - 0.5                  # texel-centre units
    low = np.clip(np.ceil(corners.min(axis=1)), 0, resolution - 1).astype(np.int64)
    high = np.clip(np.floor(corners.max(axis=1)), 0, resolution - 1).astype(np.int64)
    width = np.maximum(high - low + 1, 0)
    sizes = width[:, 0] * width[:, 1]
    tri = np.repeat(np.arange(len(faces)), sizes)
    offset = np.arange(sizes.sum()) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    x = low[tri, 0] + offset % width[tri, 0]
    y = low[tri, 1] + offset // width[tri, 0]
    p = np.stack([x, y], axis=1).astype(np.float64)
    a, b, c = corners[tri, 0], corners[tri, 1], corners[tri, 2]

    def edge(p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
        return (p1[:, 0] - p0[:, 0]) * (p[:, 1] - p0[:, 1]) \
            - (p1[:, 1] - p0[:, 1]) * (p[:, 0] - p0[:, 0])

    w = np.stack([edge(a, b), edge(b, c), edge(c, a)], axis=1)
    inside = (w > 1e-9).all(axis=1) | (w < -1e-9).all(axis=1)
    cover = np.bincount(y[inside] * resolution + x[inside], minlength=resolution ** 2)
    return cover.reshape(resolution, resolution)


__all__ = ["Packed", "PackingRules", "boundary_crossings", "pack_charts", "packing_efficiency",
           "positive_loops", "principal_rotation", "rasterized_overlap", "signed_areas",
           "texel_coverage"]
