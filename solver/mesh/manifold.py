"""Non-manifold meshes cut into manifold ones, and answers mapped back to the file's vertices.

The rule (deterministic, vectorized; the one MeshLab's "split non-manifold vertices" and
libigl's ``cut_to_disk``-style corner unions follow in spirit):

1. **Edges.** An edge of two faces keeps them together when they run it opposite ways (two
   faces flipped against each other are cut apart there). Around an edge of more than two
   faces the faces are sorted by the angle of their third vertex about the edge (from a
   reference direction perpendicular to the edge; ties by face index). A face that runs the
   edge ``i -> j`` (``i < j``) is paired with the face just before it in that order when that
   face runs ``j -> i``: the two bound the same solid wedge (their normals point away from
   it). Every other face of the edge gets its own copy of the edge (a boundary edge).
   Without positions the faces are taken in file order.
2. **Vertices.** The corners of one file vertex joined across paired edges form a fan; each
   fan becomes one vertex. The first fan (the one holding the lowest corner ``3 t + k``)
   keeps the file's index, every other fan is a new vertex numbered ``n, n + 1, ...`` in the
   order (file vertex, lowest corner).
3. **Self-touching surfaces.** Where fans joined around an endpoint leave an edge with more
   than two faces, the faces of that edge other than its lowest half-edge's and that one's
   pair are detached from all their neighbours (each becomes a part of its own), and rule 2
   runs again.

Before the cut, :func:`manifold_topology` welds the vertices joined by zero-length edges and
drops the faces that collapse (:mod:`solver.mesh.weld`); :class:`ManifoldCut` then also
carries ``weld_map`` and ``face_map``, and maps answers back through both: it is the one owner
of "file numbering <-> solve numbering".

So a manifold mesh is its own cut (``vertex_map`` = ``arange(n)``, faces unchanged), the cut
faces keep the file's face order, and ``vertex_map[c]`` names the file vertex of cut vertex
``c``. Answers computed on the cut mesh come back with :meth:`ManifoldCut.to_file`: the mean
of the copies of each file vertex, with the spread (largest distance of a copy from that
mean; 0 when the copies agree, e.g. for exact forms placed by :mod:`solver.mesh.placement`).

Example:
    Two tetrahedra sharing vertex 0 only (two fans at vertex 0):

    >>> import numpy as np
    >>> from solver.mesh.manifold import cut_to_manifold
    >>> F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3],
    ...               [0, 5, 4], [0, 4, 6], [0, 6, 5], [4, 5, 6]])
    >>> cut = cut_to_manifold(F)
    >>> cut.vertex_map.tolist(), cut.faces[4:].tolist()
    ([0, 1, 2, 3, 4, 5, 6, 0], [[7, 5, 4], [7, 4, 6], [7, 6, 5], [4, 5, 6]])
    >>> cut.split_vertices.tolist(), cut.is_identity
    ([0], False)
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike
from scipy.sparse.csgraph import connected_components

from ..core.errors import (
    ConstraintError,
    InconsistentOrientationError,
    NonManifoldEdgeError,
    NonManifoldVertexError,
)
from ..core.validation import as_faces, as_indices, as_points
from .orientation import orientation_flips
from .topology import MeshTopology, build_topology
from .weld import Weld, check_weld_map, seam_pairs, weld_report, weld_vertices


@dataclass(frozen=True)
class ManifoldCut:
    """A mesh's manifold cut (module docstring: the rule).

    Attributes:
        faces: (m, 3) int64 the file's faces on the cut vertices, in the file's order.
        vertex_map: (n_cut,) int64 file vertex of each cut vertex; ``vertex_map[:n]`` is
            ``arange(n)`` (the first copy keeps the file index).
        n_file_vertices: n, the file's vertex count.
        split_edges: (k, 2) int64 file edges ``[i, j]`` (i < j) of more than two faces, or
            of two faces that run them the same way.
        split_vertices: (j,) int64 file vertices with more than one copy.
        weld_map: None, or (n,) int64 the file vertex each file vertex was welded into
            (itself unless welded: :mod:`solver.mesh.weld`); ``vertex_map`` then names
            representatives only, and a welded vertex is a cut vertex no face uses.
        face_map: None, or (m',) int64 the file face of each cut face when faces were
            dropped (collapsed by the weld).
        n_file_faces: m, the file's face count, where known (from a mesh, not from forms).
        flipped_faces: None, or (f,) int64 the cut faces written the other way round than
            in the file (:mod:`solver.mesh.orientation`: faces flipped against their
            neighbours turned back); ``faces`` holds them turned.
    """

    faces: np.ndarray
    vertex_map: np.ndarray
    n_file_vertices: int
    split_edges: np.ndarray
    split_vertices: np.ndarray
    weld_map: np.ndarray | None = None
    face_map: np.ndarray | None = None
    n_file_faces: int | None = None
    flipped_faces: np.ndarray | None = None

    @classmethod
    def from_vertex_map(cls, vertex_map: ArrayLike, faces: ArrayLike,
                        n_file_vertices: int | None = None,
                        weld_map: ArrayLike | None = None) -> ManifoldCut:
        """The cut a forms' ``vertex_map`` (and ``weld_map``) describe (``faces``: the cut
        faces).

        Args:
            vertex_map: (n_cut,) int file vertex of each cut vertex.
            faces: (m, 3) int cut faces (indices below n_cut).
            n_file_vertices: n (default ``len(weld_map)``, else ``vertex_map.max() + 1``).
            weld_map: optional (n,) int the file vertex each file vertex was welded into.

        Raises:
            IndexOutOfRangeError: a face beyond the map, or a map entry beyond n (without n:
                beyond the map's length).
            ShapeMismatchError: a ``weld_map`` of another length than n.
            ConstraintError: a ``weld_map`` entry that is itself welded into another vertex.
        """
        welds = None
        if weld_map is not None:
            welds = as_indices(weld_map, "weld_map",
                               upper=n_file_vertices if n_file_vertices is not None
                               else len(np.asarray(weld_map).reshape(-1)))
            n_file_vertices = len(welds) if n_file_vertices is None else n_file_vertices
            check_weld_map(welds, int(n_file_vertices))
        # A cut's map numbers its file vertices 0 .. n - 1 first (n <= n_cut): without n the
        # entries are bounded by the map's length (never a huge vertex count from one entry).
        vmap = as_indices(vertex_map, "vertex_map",
                          upper=n_file_vertices if n_file_vertices is not None
                          else len(np.asarray(vertex_map).reshape(-1)))
        n = (int(vmap.max(initial=-1)) + 1 if n_file_vertices is None
             else int(n_file_vertices))
        F = as_faces(faces, len(vmap))  # an empty map: every face index is out of range
        counts = np.bincount(vmap, minlength=n)
        return cls(faces=F, vertex_map=vmap, n_file_vertices=n,
                   split_edges=np.zeros((0, 2), dtype=np.int64),
                   split_vertices=np.flatnonzero(counts > 1).astype(np.int64),
                   weld_map=welds)

    @property
    def n_vertices(self) -> int:
        """n_cut, the cut mesh's vertex count."""
        return len(self.vertex_map)

    @property
    def is_identity(self) -> bool:
        """True for a manifold mesh: nothing was cut, welded, dropped or turned."""
        return self.weld_map is None and self.face_map is None and (
            self.flipped_faces is None) and (
            self.n_vertices == self.n_file_vertices) and bool(
            (self.vertex_map == np.arange(self.n_vertices)).all())

    @property
    def is_cut(self) -> bool:
        """True when the cut split a vertex or an edge (more than the weld)."""
        return self.n_vertices > self.n_file_vertices or len(self.split_edges) > 0

    def to_solve_faces(self, file_faces: np.ndarray, field: str = "faces") -> np.ndarray:
        """File face indices (k,) int64 as cut face indices (the same without a drop).

        Raises:
            ConstraintError: a face dropped by the weld (it is not solved).
        """
        file_faces = np.asarray(file_faces, dtype=np.int64)
        if self.face_map is None:
            return file_faces
        solve = np.full(int(self.face_map.max(initial=-1)) + 1, -1, dtype=np.int64)
        solve[self.face_map] = np.arange(len(self.face_map))
        inside = file_faces < len(solve)
        out = np.full(len(file_faces), -1, dtype=np.int64)
        out[inside] = solve[file_faces[inside]]
        if (out < 0).any():
            k = int(np.flatnonzero(out < 0)[0])
            raise ConstraintError(
                f"face {int(file_faces[k])} was dropped (it repeats a vertex once the "
                "vertices joined by zero-length edges are welded): it is not solved",
                field=field, index=k)
        return out

    def to_cut(self, values: np.ndarray) -> np.ndarray:
        """Per-file-vertex values (n, ...) as per-cut-vertex values (n_cut, ...)."""
        return np.asarray(values)[self.vertex_map]

    def to_file(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-cut-vertex values (n_cut, d) float as per-file-vertex ones.

        Returns:
            ``(mean, spread)``: (n, d) float64 the mean of each file vertex's copies and
            (n,) float64 the largest distance of a copy from that mean.

        Example:
            >>> import numpy as np
            >>> cut = ManifoldCut(np.zeros((0, 3), np.int64), np.array([0, 1, 0]), 2,
            ...                   np.zeros((0, 2), np.int64), np.array([0]))
            >>> mean, spread = cut.to_file(np.array([[0.0, 0], [5, 5], [2, 0]]))
            >>> mean.tolist(), spread.tolist()
            ([[1.0, 0.0], [5.0, 5.0]], [1.0, 0.0])
        """
        values = np.asarray(values, dtype=np.float64)
        flat = values.reshape(len(values), -1)
        if self.is_identity:
            return values.copy(), np.zeros(self.n_file_vertices)
        n = self.n_file_vertices
        counts = np.bincount(self.vertex_map, minlength=n).astype(np.float64)
        total = np.zeros((n, flat.shape[1]))
        np.add.at(total, self.vertex_map, flat)
        mean = total / np.maximum(counts, 1.0)[:, None]
        distance = np.linalg.norm(flat - mean[self.vertex_map], axis=1)
        spread = np.zeros(n)
        np.maximum.at(spread, self.vertex_map, distance)
        if self.weld_map is not None:  # a welded vertex is where its representative is
            mean, spread = mean[self.weld_map], spread[self.weld_map]
        return mean.reshape((n, *values.shape[1:])), spread

    def largest_to_file(self, values: np.ndarray) -> np.ndarray:
        """Per-cut-vertex values (n_cut,) float as per-file-vertex ones (n,): the value of
        largest magnitude among the copies (e.g. the worst holonomy defect)."""
        values = np.asarray(values, dtype=np.float64)
        if self.is_identity:
            return values.copy()
        order = np.lexsort((-np.abs(values), self.vertex_map))
        first = np.ones(len(order), dtype=bool)
        first[1:] = self.vertex_map[order][1:] != self.vertex_map[order][:-1]
        out = np.zeros(self.n_file_vertices)
        out[self.vertex_map[order[first]]] = values[order[first]]
        return out if self.weld_map is None else out[self.weld_map]

    def copies_of(self, file_vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every cut vertex of the given file vertices.

        Args:
            file_vertices: (h,) int64 file vertex indices.

        Returns:
            ``(cut_vertices, source)``: (h',) int64 cut vertices and (h',) int64 the
            position in ``file_vertices`` each comes from (in the order of
            ``file_vertices``, copies by cut index). A welded vertex names its
            representative's copies: two file vertices of one group give the same cut
            vertices (:func:`solver.mesh.weld.one_handle_per_vertex` keeps one).
        """
        file_vertices = np.asarray(file_vertices, dtype=np.int64)
        if self.weld_map is not None:
            file_vertices = self.weld_map[file_vertices]
        if self.n_vertices == self.n_file_vertices and bool(
                (self.vertex_map == np.arange(self.n_vertices)).all()):
            return file_vertices.copy(), np.arange(len(file_vertices))
        order = np.argsort(self.vertex_map, kind="stable")
        starts = np.searchsorted(self.vertex_map[order], file_vertices, side="left")
        ends = np.searchsorted(self.vertex_map[order], file_vertices, side="right")
        counts = ends - starts
        source = np.repeat(np.arange(len(file_vertices)), counts)
        offset = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)
        return order[np.repeat(starts, counts) + offset], source

    def sections(self, spread: np.ndarray | None = None) -> dict[str, Any]:
        """The ``input`` report sections of what was done to the file's mesh: ``cut``
        (:meth:`report`) when a vertex or edge was split, ``weld``
        (:func:`solver.mesh.weld.weld_report`) when vertices were welded or faces dropped;
        {} for a manifold mesh.

        Args:
            spread: optional (n,) per-file-vertex spread of the answer (:meth:`to_file`).
        """
        out: dict[str, Any] = {}
        if self.flipped_faces is not None:
            file_faces = (self.flipped_faces if self.face_map is None
                          else self.face_map[self.flipped_faces])
            out["reoriented"] = {
                "rule": "faces running a shared edge the same way as their neighbour turned "
                        "to the orientation of the most faces of their part",
                "flipped_faces": len(file_faces), "flipped_face_list": file_faces[:20].tolist()}
        if self.is_cut:
            out["cut"] = self.report(spread)
        if self.weld_map is not None or self.face_map is not None:
            n = self.n_file_vertices
            kept = self.face_map if self.face_map is not None else np.arange(len(self.faces))
            out["weld"] = weld_report(Weld(
                target=self.weld_map if self.weld_map is not None else np.arange(n),
                faces=self.faces, kept_faces=kept,
                n_faces=self.n_file_faces or len(kept)))
            if self.n_file_faces is None:  # forms carry no file faces: drops not known
                del out["weld"]["dropped_faces"], out["weld"]["dropped_face_list"]
        return out

    def report(self, spread: np.ndarray | None = None) -> dict[str, Any]:
        """The ``input.cut`` report section: what was cut, and how far copies disagree.

        Args:
            spread: optional (n,) per-file-vertex spread of the answer (:meth:`to_file`).
        """
        section: dict[str, Any] = {
            "rule": "non-manifold vertices split per fan; faces of an edge paired by "
                    "orientation and angle, flipped neighbours of a non-orientable part cut "
                    "apart",
            "split_vertices": len(self.split_vertices), "split_edges": len(self.split_edges),
            "added_vertices": self.n_vertices - self.n_file_vertices,
            "split_vertex_list": self.split_vertices[:20].tolist(),
            "split_edge_list": self.split_edges[:20].tolist()}
        if spread is not None:
            section["max_spread"] = float(spread.max()) if len(spread) else 0.0
        return section


def manifold_topology(faces: ArrayLike, vertices: ArrayLike | None = None,
                      n_vertices: int | None = None, coincident: bool = True,
                      ) -> tuple[ManifoldCut, MeshTopology]:
    """The one layer every mesh entry point passes through: the vertices joined by
    zero-length edges welded and the faces that collapse dropped (:mod:`solver.mesh.weld`;
    with positions only), then the mesh's topology when it is manifold and consistently
    oriented (the cut is then the identity, at no extra cost), else its
    :func:`cut_to_manifold` and the cut's topology.

    Args:
        faces, vertices, n_vertices: as for :func:`cut_to_manifold`.
        coincident: weld the vertices of faces at one position too
            (:func:`solver.mesh.weld.weld_vertices`); False keeps such seams open (the
            flattening's user cuts).

    Returns:
        ``(cut, topology)``: the :class:`ManifoldCut` and the cut mesh's
        :class:`~solver.mesh.topology.MeshTopology`.

    Example:
        >>> cut, topology = manifold_topology([[0, 1, 2], [0, 1, 3]])  # flipped neighbours
        >>> cut.is_identity, topology.n_vertices, cut.flipped_faces.tolist(), cut.faces[1].tolist()
        (False, 4, [1], [0, 3, 1])
    """
    if n_vertices is None and vertices is not None:
        n_vertices = len(vertices)
    weld = weld_vertices(faces, vertices, n_vertices)
    cut, topology = _cut_of_weld(weld, vertices)
    if coincident and vertices is not None and topology.boundary_loops:
        # Split seams are boundary edges on each other (solver.mesh.weld, rule 1): looked
        # for on the first answer's boundary only, so a closed mesh pays nothing.
        boundary = np.flatnonzero(topology.halfedge_twin < 0)
        a, b = seam_pairs(topology.faces, cut.to_cut(as_points(vertices, "vertices")),
                          boundary)
        if len(a):
            joined = (cut.vertex_map[a], cut.vertex_map[b])  # cut copies -> file vertices
            return _cut_of_weld(weld_vertices(faces, vertices, n_vertices, joined), vertices)
    return cut, topology


def _cut_of_weld(weld: Weld, vertices: ArrayLike | None) -> tuple[ManifoldCut, MeshTopology]:
    """The cut and topology of the welded faces: the topology as they are when they are
    manifold and consistently oriented, else after turning faces written the wrong way round,
    else their :func:`cut_to_manifold`."""
    welded = not weld.is_identity
    faces, n_vertices = weld.faces, len(weld.target)
    flipped = None
    for attempt in ("as given", "reoriented"):
        try:
            topology = build_topology(faces, n_vertices)
            break
        except (NonManifoldEdgeError, NonManifoldVertexError, InconsistentOrientationError):
            flips = orientation_flips(faces, n_vertices) if attempt == "as given" else None
            if flips is None or not flips.any():
                cut = replace(cut_to_manifold(faces, vertices, n_vertices),
                              flipped_faces=flipped)
                cut = _with_weld(cut, weld, welded)
                return cut, build_topology(cut.faces, n_vertices=cut.n_vertices)
            flipped = np.flatnonzero(flips)
            faces = faces.copy()
            faces[flipped] = faces[flipped][:, [0, 2, 1]]
    n = topology.n_vertices
    identity = ManifoldCut(faces=topology.faces, vertex_map=np.arange(n, dtype=np.int64),
                           n_file_vertices=n, split_edges=np.zeros((0, 2), dtype=np.int64),
                           split_vertices=np.zeros(0, dtype=np.int64), flipped_faces=flipped)
    return _with_weld(identity, weld, welded), topology


def _with_weld(cut: ManifoldCut, weld: Weld, welded: bool) -> ManifoldCut:
    """``cut`` (of the welded faces) with what :func:`solver.mesh.weld.weld_vertices` did."""
    if not welded:
        return cut
    dropped = len(weld.kept_faces) < weld.n_faces
    return replace(cut, weld_map=weld.target if len(weld.welded_vertices) else None,
                   face_map=weld.kept_faces if dropped else None,
                   n_file_faces=weld.n_faces)


def cut_to_manifold(faces: ArrayLike, vertices: ArrayLike | None = None,
                    n_vertices: int | None = None) -> ManifoldCut:
    """The manifold cut of a mesh (module docstring: the rule).

    Args:
        faces: (m, 3) int, counter-clockwise.
        vertices: optional (n, 3) float64 positions (they order the faces around an edge of
            more than two faces; without them, file order).
        n_vertices: vertex count (default ``len(vertices)`` or ``faces.max() + 1``).

    Returns:
        :class:`ManifoldCut`; an edge whose two faces run it the same way is cut (each side
        is then consistently oriented).

    Raises:
        IndexOutOfRangeError, DegenerateFaceError, ShapeMismatchError: malformed faces.
    """
    if n_vertices is None and vertices is not None:
        n_vertices = len(vertices)
    F = as_faces(faces, n_vertices)
    n = int(F.max()) + 1 if n_vertices is None else int(n_vertices)
    m = len(F)
    origin = F.ravel()
    dest = F[:, [1, 2, 0]].ravel()
    lo, hi = np.minimum(origin, dest), np.maximum(origin, dest)
    keys, halfedge_edge, counts = np.unique(lo * n + hi, return_inverse=True,
                                            return_counts=True)
    halfedge_edge = halfedge_edge.ravel()
    h_first, h_second = _paired_halfedges(F, origin, dest, halfedge_edge, counts, vertices)
    H = 3 * m
    partner = np.full(H, -1, dtype=np.int64)
    partner[h_first], partner[h_second] = h_second, h_first
    detached = np.zeros(m, dtype=bool)
    for _ in range(MAX_PASSES):
        kept = ~(detached[h_first // 3] | detached[h_second // 3])
        first, second = h_first[kept], h_second[kept]
        # Corners (named by the half-edge leaving them) joined across each paired edge.
        same_way = origin[first] == origin[second]
        a = np.concatenate([first, _next(first)])
        b = np.concatenate([np.where(same_way, second, _next(second)),
                            np.where(same_way, _next(second), second)])
        corner_vertex, vertex_map = _fans(a, b, origin, n)
        crowded = _crowded_halfedges(corner_vertex, partner, len(vertex_map))
        if not len(crowded):
            break
        # Fans joined around an endpoint kept an edge crowded (a surface touching itself):
        # its extra faces are detached from their neighbours and the fans formed again.
        detached[crowded // 3] = True
    split_vertices = np.unique(vertex_map[n:])
    forward = np.bincount(halfedge_edge, weights=origin < dest, minlength=len(counts))
    many = (counts > 2) | ((counts == 2) & (forward != 1))  # crowded, or flipped neighbours
    split_edges = np.stack([keys[many] // n, keys[many] % n], axis=1).astype(np.int64)
    return ManifoldCut(faces=corner_vertex.reshape(m, 3), vertex_map=vertex_map,
                       n_file_vertices=n, split_edges=split_edges,
                       split_vertices=split_vertices.astype(np.int64))


MAX_PASSES = 8
"""Passes of :func:`cut_to_manifold`: an edge still crowded after the fans are formed (the
faces' fans join around an endpoint: a surface touching itself) has its extra faces, all
but its lowest half-edge's and that one's partner's, detached from every neighbour (rule 3
of the module docstring), and the fans are formed again."""


def _next(h: np.ndarray) -> np.ndarray:
    """The next half-edge in the face of each of ``h`` (k,) int64."""
    return h - h % 3 + (h + 1) % 3


def _fans(a: np.ndarray, b: np.ndarray, origin: np.ndarray, n: int
          ) -> tuple[np.ndarray, np.ndarray]:
    """Cut vertices of the corners joined by the links ``a[i] ~ b[i]`` (module docstring,
    rule 2).

    Returns:
        ``(corner_vertex, vertex_map)``: (H,) int64 cut vertex of each corner and (n_cut,)
        int64 file vertex of each cut vertex.
    """
    H = len(origin)
    graph = sp.coo_matrix((np.ones(len(a)), (a, b)), shape=(H, H))
    _, fan = connected_components(graph, directed=False)
    lowest = np.full(fan.max() + 1, H, dtype=np.int64)
    np.minimum.at(lowest, fan, np.arange(H))
    fan_vertex = origin[lowest]
    order = np.lexsort((lowest, fan_vertex))
    first = np.ones(len(order), dtype=bool)
    first[1:] = fan_vertex[order][1:] != fan_vertex[order][:-1]
    new_index = np.empty(len(order), dtype=np.int64)
    extra = order[~first]
    new_index[order[first]] = fan_vertex[order[first]]
    new_index[extra] = n + np.arange(len(extra))
    vertex_map = np.concatenate([np.arange(n), fan_vertex[extra]]).astype(np.int64)
    return new_index[fan], vertex_map


def _crowded_halfedges(corner_vertex: np.ndarray, partner: np.ndarray, n_cut: int
                       ) -> np.ndarray:
    """Half-edges of cut edges with more than two faces, except the lowest one of each such
    edge and its partner: (k,) int64."""
    origin = corner_vertex
    dest = corner_vertex[_next(np.arange(len(corner_vertex)))]
    key = np.minimum(origin, dest) * n_cut + np.maximum(origin, dest)
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    halfedges = np.flatnonzero(counts[inverse] > 2)
    if not len(halfedges):
        return halfedges
    order = np.lexsort((halfedges, inverse[halfedges]))
    halfedges = halfedges[order]
    group = inverse[halfedges]
    starts = np.r_[True, group[1:] != group[:-1]]
    first = halfedges[starts][np.cumsum(starts) - 1]
    return halfedges[(halfedges != first) & (halfedges != partner[first])]


def _paired_halfedges(F: np.ndarray, origin: np.ndarray, dest: np.ndarray,
                      halfedge_edge: np.ndarray, counts: np.ndarray,
                      vertices: ArrayLike | None) -> tuple[np.ndarray, np.ndarray]:
    """The pairs of half-edges that stay joined (rule 1 of the module docstring).

    Returns:
        ``(h_first, h_second)``: (p,) int64 each.
    """
    H = len(origin)
    by_edge = np.argsort(halfedge_edge, kind="stable")
    edge_of = halfedge_edge[by_edge]
    count_of = counts[edge_of]
    two = count_of == 2
    pairs_two = by_edge[two].reshape(-1, 2)
    # Two faces that run their edge the same way (flipped against each other) are not
    # joined there: the edge is cut, each side consistently oriented (rule 1).
    pairs_two = pairs_two[origin[pairs_two[:, 0]] != origin[pairs_two[:, 1]]]
    many = np.flatnonzero(count_of > 2)
    if len(many) == 0:
        return pairs_two[:, 0], pairs_two[:, 1]
    h = by_edge[many]
    angle = _angle_about_edge(F, origin, dest, h, vertices)
    # Sort the half-edges of each crowded edge by angle (ties: half-edge index).
    order = np.lexsort((h, angle, halfedge_edge[h]))
    h = h[order]
    edges_h = halfedge_edge[h]
    group_start = np.flatnonzero(np.r_[True, edges_h[1:] != edges_h[:-1]])
    group_len = np.diff(np.r_[group_start, len(h)])
    start_of = np.repeat(group_start, group_len)
    len_of = np.repeat(group_len, group_len)
    position = np.arange(len(h)) - start_of
    previous = h[start_of + (position - 1) % len_of]
    forward = origin[h] < dest[h]
    joined = forward & (origin[previous] > dest[previous])
    del H
    return (np.concatenate([pairs_two[:, 0], h[joined]]),
            np.concatenate([pairs_two[:, 1], previous[joined]]))


def _angle_about_edge(F: np.ndarray, origin: np.ndarray, dest: np.ndarray, h: np.ndarray,
                      vertices: ArrayLike | None) -> np.ndarray:
    """Angle (k,) float64 of each half-edge's face about its edge ``i -> j`` (i < j): of the
    face's third vertex, from a reference direction perpendicular to the edge, right-handed
    about ``j - i``; the half-edge index (file order) without positions."""
    if vertices is None:
        return h.astype(np.float64)
    V = np.asarray(vertices, dtype=np.float64)
    i, j = np.minimum(origin[h], dest[h]), np.maximum(origin[h], dest[h])
    apex = F.ravel()[h - h % 3 + (h + 2) % 3]
    axis = V[j] - V[i]
    axis /= np.maximum(np.linalg.norm(axis, axis=1), 1e-300)[:, None]
    helper = np.where((np.abs(axis[:, 0]) < 0.9)[:, None], [1.0, 0, 0], [0, 1.0, 0])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u, axis=1)[:, None]
    w = np.cross(axis, u)
    d = V[apex] - V[i]
    return np.arctan2(np.einsum("ij,ij->i", d, w), np.einsum("ij,ij->i", d, u))
