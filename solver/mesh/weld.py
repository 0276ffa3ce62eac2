"""Vertices joined by zero-length edges welded into one, and the faces that collapse dropped.

The rule (deterministic, vectorized), applied before the manifold cut
(:func:`solver.mesh.manifold.manifold_topology`):

1. **Zero-length edges.** An edge of a face whose length is at most :data:`WELD_TOLERANCE`
   times the bounding-box diagonal of the faces' vertices (0 included: two corners at one
   position, e.g. a capsule's pole repeated once per longitude, a scan's duplicated
   vertices) joins its two vertices.
   **Split seams.** Exporters split a vertex where its normal or texture coordinate
   changes (a flat-shaded glTF box is 24 vertices in 6 parts, a triangle soup one part per
   face); a surface split so would come apart when deformed. Unless the caller keeps seams
   open (``coincident=False`` of :func:`solver.mesh.manifold.manifold_topology`), two
   boundary edges that lie on each other (their ends at one position each, bit
   for bit, ``-0.0`` is ``0.0``), run opposite ways (consistently oriented across the
   seam) and whose faces are not folded onto each other (normals not opposite:
   :data:`FOLDED`) are zipped: their ends are joined. Only a seam edge with exactly one such
   partner is zipped; vertices that merely touch (at a point, or layers folded onto each
   other) stay apart. The flattening keeps seams as the user's cuts
   (:func:`solver.parameterize` passes ``coincident=False``).
2. **Groups.** The vertices joined through such edges (transitively) form a group; the
   group's lowest file index is its representative and every other vertex of it is
   welded into it: the solve has one unknown for the group, and the answer gives each
   welded vertex its representative's position.
3. **Faces.** A face that repeats a vertex once the weld is applied (``(a, a, b)`` as
   given, or two corners of one group) has no line or no normal: it is dropped from the
   solve and reported; the other faces keep the file's order.

The weld keeps the file's vertex numbering: a welded vertex is an index no solved face uses
(an isolated vertex of the solve), and :class:`solver.mesh.manifold.ManifoldCut` (the one
owner of "file numbering <-> solve numbering") maps every answer back.

Example:
    A square whose corner 2 is repeated as vertex 4, with a sliver face ``(2, 4, 3)`` and
    a face written ``(0, 0, 1)``:

    >>> import numpy as np
    >>> V = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [1, 1, 0]])
    >>> weld = weld_vertices([[0, 1, 2], [0, 4, 3], [2, 4, 3], [0, 0, 1]], V)
    >>> weld.target.tolist(), weld.faces.tolist(), weld.dropped_faces.tolist()
    ([0, 1, 2, 3, 2], [[0, 1, 2], [0, 2, 3]], [2, 3])
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Final

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike
from scipy.sparse.csgraph import connected_components

from ..core.errors import ConstraintError, ShapeMismatchError
from ..core.validation import as_indices

WELD_TOLERANCE = 1e-12
"""An edge at most this fraction of the bounding-box diagonal of the faces' vertices long
has zero length: its two vertices are welded (rule 1 of the module docstring). Far below
any edge a mesh means (1e-12 of a 1 m part is a picometre), far above the round-off of
coordinates written with 15 or more significant digits."""


@dataclass(frozen=True)
class Weld:
    """What :func:`weld_vertices` did (module docstring: the rule).

    Attributes:
        target: (n,) int64 the representative of each file vertex (itself unless welded).
        faces: (m', 3) int64 the kept faces on the representatives, in the file's order.
        kept_faces: (m',) int64 the file index of each kept face.
        n_faces: m, the file's face count.
    """

    target: np.ndarray
    faces: np.ndarray
    kept_faces: np.ndarray
    n_faces: int

    @property
    def welded_vertices(self) -> np.ndarray:
        """(k,) int64 the file vertices welded into another one."""
        return np.flatnonzero(self.target != np.arange(len(self.target)))

    @property
    def dropped_faces(self) -> np.ndarray:
        """(d,) int64 the file faces dropped (a repeated vertex once welded)."""
        keep = np.zeros(self.n_faces, dtype=bool)
        keep[self.kept_faces] = True
        return np.flatnonzero(~keep)

    @property
    def is_identity(self) -> bool:
        """True when nothing was welded or dropped."""
        return len(self.kept_faces) == self.n_faces and not len(self.welded_vertices)


def weld_vertices(faces: ArrayLike, vertices: ArrayLike | None = None,
                  n_vertices: int | None = None,
                  joined: tuple[np.ndarray, np.ndarray] | None = None) -> Weld:
    """Weld the vertices joined by zero-length edges (and the pairs ``joined``: a split
    seam's, :func:`seam_pairs`) and drop the faces that collapse.

    Args:
        faces: (m, 3) int (a face may repeat an index: it is dropped).
        vertices: optional (n, 3) float64 positions (without them only faces that repeat an
            index are dropped: nothing is welded).
        n_vertices: vertex count (default ``len(vertices)`` or ``faces.max() + 1``).
        joined: optional ``(a, b)`` (p,) int64 file vertices to weld pairwise too (rule 1).

    Returns:
        :class:`Weld`.

    Raises:
        ShapeMismatchError: no faces, or none left once the collapsed ones are dropped.
        IndexOutOfRangeError: a face index outside [0, n).
    """
    if n_vertices is None and vertices is not None:
        n_vertices = len(vertices)
    F = as_indices(faces, "faces", upper=n_vertices, width=3)
    if len(F) == 0:
        raise ShapeMismatchError("the mesh has no faces", field="faces")
    n = int(F.max()) + 1 if n_vertices is None else int(n_vertices)
    target = np.arange(n, dtype=np.int64)
    if vertices is not None:
        target = _representatives(F, np.asarray(vertices, dtype=np.float64), n, joined)
    welded = target[F]
    collapsed = ((welded[:, 0] == welded[:, 1]) | (welded[:, 1] == welded[:, 2])
                 | (welded[:, 2] == welded[:, 0]))
    kept = np.flatnonzero(~collapsed)
    if not len(kept):
        raise ShapeMismatchError(
            f"every one of the {len(F)} faces has two corners at one position (or repeats a "
            "vertex index): no face is left to solve", field="faces")
    return Weld(target=target, faces=welded[kept], kept_faces=kept.astype(np.int64),
                n_faces=len(F))


def _representatives(F: np.ndarray, V: np.ndarray, n: int,
                     joined: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
    """(n,) int64 the lowest vertex of each group joined by zero-length edges or ``joined``
    pairs (rules 1, 2)."""
    a = F.ravel()
    b = F[:, [1, 2, 0]].ravel()
    referenced = np.zeros(n, dtype=bool)
    referenced[a] = True
    used = V[:n][referenced]
    low, high = used.min(axis=0), used.max(axis=0)
    scale = float(max(np.abs(low).max(), np.abs(high).max())) or 1.0  # no overflow to inf
    diagonal = float(np.linalg.norm((high - low) / scale))
    d = (V[b] - V[a]) / scale
    short = (np.einsum("ij,ij->i", d, d) <= (WELD_TOLERANCE * diagonal) ** 2) & (a != b)
    first, second = a[short], b[short]
    if joined is not None:
        first, second = np.concatenate([first, joined[0]]), np.concatenate([second, joined[1]])
    target = np.arange(n, dtype=np.int64)
    if not len(first):
        return target
    graph = sp.coo_matrix((np.ones(len(first)), (first, second)), shape=(n, n))
    _, group = connected_components(graph, directed=False)
    lowest = np.full(int(group.max()) + 1, n, dtype=np.int64)
    np.minimum.at(lowest, group, target)
    return lowest[group]


FOLDED: Final = 1.0 - 1e-9
"""Two faces whose unit normals' dot product is at most ``-FOLDED`` lie folded onto each
other: a boundary edge between them is not a split seam (rule 1)."""


def seam_pairs(faces: np.ndarray, V: np.ndarray, boundary: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """The vertex pairs a split seam joins (rule 1): the ends of boundary edges that lie on
    each other, run opposite ways and are not folded, each with exactly one partner.

    Args:
        faces: (m, 3) int64 faces (half-edge ``h`` runs from ``faces[h // 3, h % 3]`` to the
            next corner).
        V: (n, 3) float64 positions of their vertices.
        boundary: (k,) int64 the boundary half-edges (of one face).

    Returns:
        ``(a, b)``: (p,) int64 vertices to join pairwise (empty when there is no seam).
    """
    empty = np.zeros(0, dtype=np.int64)
    if len(boundary) < 2:
        return empty, empty
    origin = faces[boundary // 3, boundary % 3]
    dest = faces[boundary // 3, (boundary % 3 + 1) % 3]
    ends, slot = np.unique(np.concatenate([origin, dest]), return_inverse=True)
    order, same = sorted_positions(np.ascontiguousarray(V[ends], dtype=np.float64) + 0.0)
    place = np.empty(len(ends), dtype=np.int64)  # the position class of every end
    place[order] = np.cumsum(np.r_[True, ~same]) - 1
    count = int(place.max()) + 1
    u, v = place[slot[:len(boundary)]], place[slot[len(boundary):]]
    key, wanted = u * count + v, v * count + u
    keys, first, own, many = np.unique(key, return_index=True, return_inverse=True,
                                       return_counts=True)
    at = np.minimum(np.searchsorted(keys, wanted), len(keys) - 1)
    single = (keys[at] == wanted) & (many[at] == 1) & (many[own.ravel()] == 1)
    mine, partner = np.flatnonzero(single), first[at[single]]
    normals = _unit_normals(V, faces[boundary[mine] // 3]), _unit_normals(
        V, faces[boundary[partner] // 3])
    keep = np.einsum("ij,ij->i", *normals) > -FOLDED
    mine, partner = mine[keep], partner[keep]
    return (np.concatenate([origin[mine], dest[mine]]),
            np.concatenate([dest[partner], origin[partner]]))


def _unit_normals(V: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(k, 3) unit normals of ``faces`` (zero for a face without area)."""
    normals = np.cross(V[faces[:, 1]] - V[faces[:, 0]], V[faces[:, 2]] - V[faces[:, 0]])
    return normals / np.maximum(np.linalg.norm(normals, axis=1), 1e-300)[:, None]


def weld_report(weld: Weld) -> dict[str, Any]:
    """The ``input.weld`` report section: how many vertices were welded and faces dropped
    (the first 20 of each listed)."""
    welded, dropped = weld.welded_vertices, weld.dropped_faces
    return {"rule": "vertices joined by edges of length <= "
                    f"{WELD_TOLERANCE:g} x the bounding-box diagonal welded into the "
                    "lowest index; faces that repeat a vertex once welded dropped",
            "welded_vertices": len(welded), "dropped_faces": len(dropped),
            "welded_vertex_list": welded[:20].tolist(),
            "welded_into": weld.target[welded[:20]].tolist(),
            "dropped_face_list": dropped[:20].tolist()}


def check_weld_map(weld_map: np.ndarray, n_vertices: int) -> None:
    """Refuse a forms' ``weld_map`` (n,) int64 that is not one of :func:`weld_vertices`.

    Raises:
        ShapeMismatchError: not of length ``n_vertices``.
        ConstraintError: a vertex welded into one that is itself welded (each group has
            one representative, welded into nothing).
    """
    if len(weld_map) != n_vertices:
        raise ShapeMismatchError(f"weld_map has {len(weld_map)} entries, the mesh "
                                 f"{n_vertices} vertices", field="weld_map")
    chained = np.flatnonzero(weld_map[weld_map] != weld_map)
    if len(chained):
        v = int(chained[0])
        raise ConstraintError(f"vertex {v} is welded into {int(weld_map[v])}, which is "
                              f"welded into {int(weld_map[weld_map[v]])}: name the "
                              "representative", field="weld_map", index=v)


def one_handle_per_vertex(handles: np.ndarray, source: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One handle per solve vertex: the copies of a welded vertex share it.

    Args:
        handles: (h,) int64 solve vertices of the handles
            (:meth:`solver.mesh.manifold.ManifoldCut.copies_of`).
        source: (h,) int64 the position of each in the file's handle list.

    Returns:
        ``(handles, source, welded)``: the first handle of each solve vertex, in order,
        and (w, 2) int64 pairs of positions in the file's handle list that name one
        vertex (their targets must agree: :func:`check_welded_targets`).
    """
    _, first, inverse = np.unique(handles, return_index=True, return_inverse=True)
    leader = source[first[inverse.ravel()]]
    welded = np.unique(np.stack([leader, source], axis=1)[leader != source], axis=0)
    keep = np.sort(first)
    return handles[keep], source[keep], welded.reshape(-1, 2).astype(np.int64)


def welded_mask(weld_map: np.ndarray | None, mask: np.ndarray) -> np.ndarray:
    """(n,) bool ``mask`` (n,) with every vertex of a welded group set when any is."""
    if weld_map is None:
        return mask
    grouped = np.zeros(len(mask), dtype=bool)
    np.logical_or.at(grouped, weld_map, mask)
    return grouped[weld_map]


def check_welded_targets(targets: np.ndarray, file_handles: np.ndarray, welded: np.ndarray,
                         rest: np.ndarray) -> None:
    """Refuse different targets (h, 3) for two handles welded into one vertex (farther
    apart than :data:`WELD_TOLERANCE` of the rest's (n, 3) bounding-box diagonal).

    Raises:
        ConstraintError: naming both handle vertices and their targets.
    """
    if not len(welded):
        return
    diagonal = float(np.linalg.norm(rest.max(axis=0) - rest.min(axis=0)))
    apart = np.linalg.norm(targets[welded[:, 0]] - targets[welded[:, 1]], axis=1)
    bad = np.flatnonzero(apart > WELD_TOLERANCE * max(diagonal, np.finfo(float).tiny))
    if len(bad):
        a, b = welded[bad[0]]
        raise ConstraintError(
            f"handle vertices {int(file_handles[a])} and {int(file_handles[b])} are welded "
            f"into one vertex (a zero-length edge joins them) but have different targets "
            f"{targets[a].tolist()} and {targets[b].tolist()}: give them one target, or "
            "one handle", field="handle_positions", index=int(b),
            details={"vertices": [int(file_handles[a]), int(file_handles[b])]})


_MIX: Final = (np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB), np.uint64(31))
"""SplitMix64's finalizer constants: two odd multipliers and a shift."""


def sorted_positions(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A stable order of (k, 3) float64 positions that puts identical ones next to each other.

    Returns:
        ``(order, same)``: (k,) int64 the order, and (k - 1,) bool whether each sorted
        position equals the one before it.
    """
    bits = v.view(np.uint64)
    first, second, shift = _MIX
    key = bits[:, 0].copy()
    for column in (1, 2):
        key *= first
        key ^= key >> shift
        key ^= bits[:, column]
    key *= second
    key ^= key >> shift
    order = np.argsort(key, kind="stable")
    ordered = v[order]
    same = (ordered[1:] == ordered[:-1]).all(axis=1)
    sorted_key = key[order]
    if (same != (sorted_key[1:] == sorted_key[:-1])).any():  # a hash two positions share
        order = np.lexsort(v.T[::-1])
        ordered = v[order]
        same = (ordered[1:] == ordered[:-1]).all(axis=1)
    return order, same
