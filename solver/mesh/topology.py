"""Combinatorial structure of an oriented triangle mesh (vectorized half-edges).

Conventions (shared by the whole package):

* ``faces`` (m, 3) int64, counter-clockwise seen from outside.
* Half-edge ``h = 3 t + k`` runs from ``faces[t, k]`` to ``faces[t, (k + 1) % 3]``; face ``t``
  lies to its left.
* ``edges`` (E, 2) int64: unique undirected pairs ``[i, j]``, ``i < j``, sorted
  lexicographically. ``edge_halfedges[e] = (h_fwd, h_bwd)`` are the half-edges running
  ``i -> j`` and ``j -> i`` (-1 where absent, i.e. on the boundary), and ``edge_faces[e]``
  their faces: the face left of ``i -> j`` first.

:func:`build_topology` also validates: edges shared by more than two faces, faces that
traverse a shared edge in the same direction, and vertices with more than one face fan all
raise a typed :mod:`solver.core.errors` exception naming the element.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from ..core.errors import (
    InconsistentOrientationError,
    NonManifoldEdgeError,
    NonManifoldVertexError,
)
from ..core.validation import as_faces


@dataclass(frozen=True)
class MeshTopology:
    """Half-edge connectivity, components and topological invariants of a mesh.

    Attributes (n vertices, m faces, E edges, H = 3 m half-edges):
        n_vertices: int.
        faces: (m, 3) int64.
        edges: (E, 2) int64, i < j, lexicographic.
        halfedge_origin, halfedge_dest: (H,) int64 vertex indices.
        halfedge_edge: (H,) int64 edge index of each half-edge.
        halfedge_twin: (H,) int64 opposite half-edge, -1 on the boundary.
        edge_halfedges: (E, 2) int64 half-edges i->j and j->i (-1 if absent).
        edge_faces: (E, 2) int64 faces left of i->j and left of j->i (-1 if absent).
        vertex_component: (n,) int64 connected component of each vertex.
        face_component: (m,) int64.
        is_boundary_vertex: (n,) bool.
        is_referenced: (n,) bool, False for vertices no face uses.
        boundary_loops: list of (k,) int64 vertex loops, each in boundary half-edge order.
        boundary_loop_component: (b,) int64 component of each loop.
    """

    n_vertices: int
    faces: np.ndarray
    edges: np.ndarray
    halfedge_origin: np.ndarray
    halfedge_dest: np.ndarray
    halfedge_edge: np.ndarray
    halfedge_twin: np.ndarray
    edge_halfedges: np.ndarray
    edge_faces: np.ndarray
    vertex_component: np.ndarray
    face_component: np.ndarray
    is_boundary_vertex: np.ndarray
    is_referenced: np.ndarray
    boundary_loops: list[np.ndarray]
    boundary_loop_component: np.ndarray

    @property
    def n_faces(self) -> int:
        """m, the number of faces."""
        return len(self.faces)

    @property
    def n_edges(self) -> int:
        """E, the number of edges."""
        return len(self.edges)

    @property
    def n_components(self) -> int:
        """Number of connected components (isolated vertices count as components)."""
        return int(self.vertex_component.max()) + 1 if self.n_vertices else 0

    @property
    def interior_edges(self) -> np.ndarray:
        """(k,) int64 indices of edges with two faces."""
        return np.flatnonzero((self.edge_halfedges >= 0).all(axis=1))

    @property
    def isolated_vertices(self) -> np.ndarray:
        """(k,) int64 vertices that no face uses."""
        return np.flatnonzero(~self.is_referenced)

    def component_summary(self) -> list[dict[str, int | bool]]:
        """Counts and invariants of each connected component with faces.

        Returns:
            One dict per component: ``component``, ``vertices``, ``edges``, ``faces``,
            ``boundary_loops``, ``euler_characteristic``, ``genus`` and ``closed``.
        """
        comps = self.face_component
        n_comp = self.n_components
        v_count = np.bincount(self.vertex_component[self.is_referenced], minlength=n_comp)
        f_count = np.bincount(comps, minlength=n_comp)
        e_count = np.bincount(self.vertex_component[self.edges[:, 0]], minlength=n_comp)
        b_count = np.bincount(self.boundary_loop_component, minlength=n_comp)
        c = np.flatnonzero(f_count)
        chi = v_count[c] - e_count[c] + f_count[c]
        columns = {"component": c, "vertices": v_count[c], "edges": e_count[c],
                   "faces": f_count[c], "boundary_loops": b_count[c],
                   "euler_characteristic": chi, "genus": (2 - chi - b_count[c]) // 2,
                   "closed": b_count[c] == 0}
        names = list(columns)
        # One conversion per column (Python ints and bools), then one dict per component.
        return [dict(zip(names, row, strict=True))
                for row in zip(*(np.asarray(v).tolist() for v in columns.values()), strict=True)]


def build_topology(faces: np.ndarray, n_vertices: int | None = None,
                   edges: np.ndarray | None = None) -> MeshTopology:
    """Build and validate the half-edge structure of ``faces``.

    Args:
        faces: (m, 3) integer array, counter-clockwise.
        n_vertices: vertex count; defaults to ``faces.max() + 1``.
        edges: optional (E, 2) int64 edge list the caller expects (the forms' edges): when
            it is exactly the faces' sorted edge list, the half-edges are looked up in it
            (a binary search instead of sorting the half-edges); otherwise it is ignored
            (the caller compares it with ``topology.edges`` for its own error).

    Returns:
        The :class:`MeshTopology`.

    Raises:
        IndexOutOfRangeError: a face index outside [0, n_vertices).
        DegenerateFaceError: a face that repeats a vertex.
        NonManifoldEdgeError: an edge shared by more than two faces.
        InconsistentOrientationError: two faces that traverse a shared edge the same way.
        NonManifoldVertexError: a vertex joining more than one fan of faces.

    Example:
        Two triangles sharing an edge make a disk with one boundary loop:

        >>> from solver.mesh.topology import build_topology
        >>> square = build_topology([[0, 1, 2], [0, 2, 3]])
        >>> square.n_edges, square.interior_edges.tolist(), square.boundary_loops[0].tolist()
        (5, [1], [0, 1, 2, 3])
        >>> summary = square.component_summary()[0]
        >>> summary["euler_characteristic"], summary["genus"], summary["closed"]
        (1, 0, False)
    """
    F = as_faces(faces, n_vertices)
    n = int(F.max()) + 1 if n_vertices is None else int(n_vertices)
    m = len(F)
    H = 3 * m
    origin = F.ravel()
    dest = F[:, [1, 2, 0]].ravel()
    keys = np.minimum(origin, dest) * n + np.maximum(origin, dest)
    found = None if edges is None else _given_edges(keys, edges, n)
    if found is None:
        edge_keys, halfedge_edge, counts = np.unique(keys, return_inverse=True,
                                                     return_counts=True)
        edges = np.stack([edge_keys // n, edge_keys % n], axis=1)
    else:
        edges, halfedge_edge, counts = found
    del keys
    _check_edge_multiplicity(edges, halfedge_edge, counts)

    forward = origin < dest
    # Each edge of two faces must be traversed once each way: one forward half-edge.
    forward_count = np.bincount(halfedge_edge[forward], minlength=len(edges))
    if ((counts == 2) & (forward_count != 1)).any():
        e = int(np.flatnonzero((counts == 2) & (forward_count != 1))[0])
        h1, h2 = np.flatnonzero(halfedge_edge == e)[:2]
        raise InconsistentOrientationError(
            f"faces {h1 // 3} and {h2 // 3} both traverse edge {edges[e].tolist()} from vertex "
            f"{origin[h1]} to {dest[h1]}: flip one of them (or remove a duplicated face)",
            field="faces", index=int(h2 // 3), details={"edge": edges[e].tolist(),
                                                        "faces": [int(h1 // 3), int(h2 // 3)]})

    halfedges = np.arange(H)
    edge_halfedges = np.full((len(edges), 2), -1, dtype=np.int64)
    edge_halfedges[halfedge_edge[forward], 0] = halfedges[forward]
    edge_halfedges[halfedge_edge[~forward], 1] = halfedges[~forward]
    twin = np.full(H, -1, dtype=np.int64)
    both = (edge_halfedges >= 0).all(axis=1)
    twin[edge_halfedges[both, 0]] = edge_halfedges[both, 1]
    twin[edge_halfedges[both, 1]] = edge_halfedges[both, 0]
    edge_faces = np.where(edge_halfedges >= 0, edge_halfedges // 3, -1)

    _check_vertex_fans(origin, twin, n)

    graph = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, vertex_component = connected_components(graph, directed=False)
    vertex_component = vertex_component.astype(np.int64)
    is_referenced = np.zeros(n, dtype=bool)
    is_referenced[origin] = True

    boundary = twin < 0
    is_boundary_vertex = np.zeros(n, dtype=bool)
    is_boundary_vertex[origin[boundary]] = True
    loops, loop_component = _boundary_loops(origin, dest, boundary, n, vertex_component)

    return MeshTopology(
        n_vertices=n, faces=F, edges=edges, halfedge_origin=origin, halfedge_dest=dest,
        halfedge_edge=halfedge_edge.astype(np.int64), halfedge_twin=twin,
        edge_halfedges=edge_halfedges, edge_faces=edge_faces,
        vertex_component=vertex_component, face_component=vertex_component[F[:, 0]],
        is_boundary_vertex=is_boundary_vertex, is_referenced=is_referenced,
        boundary_loops=loops, boundary_loop_component=loop_component,
    )


def _given_edges(keys: np.ndarray, edges: np.ndarray, n: int,
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``(edges, halfedge_edge, counts)`` when ``edges`` (E, 2) is exactly the sorted edge
    list of the half-edges' ``keys`` (H,) = ``min * n + max``, else None."""
    edges = np.asarray(edges)
    if edges.ndim != 2 or edges.shape[1] != 2 or not len(edges) or not len(keys):
        return None
    edges = edges.astype(np.int64, copy=False)
    if (edges < 0).any() or (edges >= n).any() or (edges[:, 0] >= edges[:, 1]).any():
        return None
    edge_keys = edges[:, 0] * n + edges[:, 1]
    if (edge_keys[1:] <= edge_keys[:-1]).any():      # strictly increasing: sorted, distinct
        return None
    position = np.searchsorted(edge_keys, keys)
    np.minimum(position, len(edge_keys) - 1, out=position)
    if (edge_keys[position] != keys).any():           # a face edge missing from the list
        return None
    counts = np.bincount(position, minlength=len(edge_keys))
    if (counts == 0).any():                            # a listed edge of no face
        return None
    return edges, position, counts


def _check_edge_multiplicity(edges: np.ndarray, halfedge_edge: np.ndarray,
                             counts: np.ndarray) -> None:
    """Raise :class:`NonManifoldEdgeError` for the first edge of more than two faces."""
    if counts.max() <= 2:
        return
    e = int(np.flatnonzero(counts > 2)[0])
    faces_of_e = (np.flatnonzero(halfedge_edge == e) // 3).tolist()
    raise NonManifoldEdgeError(
        f"edge {edges[e].tolist()} is shared by {int(counts[e])} faces {faces_of_e}; "
        "at most two faces may share an edge", field="faces", index=int(faces_of_e[2]),
        details={"edge": edges[e].tolist(), "faces": faces_of_e})


def previous_halfedge(h: np.ndarray) -> np.ndarray:
    """Half-edge before ``h`` in its face (the one ending at ``h``'s origin).

    Args:
        h: (k,) int64 half-edges.

    Returns:
        (k,) int64 half-edges.

    Example:
        >>> import numpy as np
        >>> from solver.mesh.topology import previous_halfedge
        >>> previous_halfedge(np.arange(6)).tolist()
        [2, 0, 1, 5, 3, 4]
    """
    return h - h % 3 + (h + 2) % 3


def corner_successor(twin: np.ndarray) -> np.ndarray:
    """Next corner counter-clockwise around each corner's vertex (seen from outside).

    Corners are identified with the half-edge leaving the vertex (corner ``h`` of face
    ``h // 3`` sits at ``halfedge_origin[h]``). The next face counter-clockwise around that
    vertex lies across the previous half-edge of the face.

    Args:
        twin: (H,) int64 opposite half-edge of each half-edge, -1 on the boundary.

    Returns:
        (H,) int64 next corner of each corner, -1 at the boundary.
    """
    return twin[previous_halfedge(np.arange(len(twin)))]


FAN_WALK_VALENCE = 1024
"""Largest valence for which :func:`_check_vertex_fans` walks the fans (one vectorized step
per ring position); meshes with a vertex of more faces take the connected components of
the corner graph instead."""


def _check_vertex_fans(origin: np.ndarray, twin: np.ndarray, n: int) -> None:
    """Raise :class:`NonManifoldVertexError` for the first vertex with two fans of faces.

    Every vertex walks its corners from the start of an open fan (a corner no other corner
    leads to) or, when it has none, from its first corner: the corner successor is
    one-to-one, so the vertex has one fan exactly when that walk meets all its corners
    (all vertices at once, sorted by valence so that those still walking are a prefix).
    A vertex that fails, and every mesh with a vertex of more than
    :data:`FAN_WALK_VALENCE` faces, takes :func:`_count_vertex_fans` (which names it).
    """
    H = len(origin)
    succ = corner_successor(twin)
    count = np.bincount(origin, minlength=n)
    if not H or count.max() > FAN_WALK_VALENCE:
        _count_vertex_fans(origin, succ, n)
        return
    corners = np.arange(H)
    has_pred = np.zeros(H, dtype=bool)
    has_pred[succ[succ >= 0]] = True
    start = np.full(n, H, dtype=np.int64)
    np.minimum.at(start, origin, np.where(has_pred, H, corners))   # an open fan's start
    first = np.full(n, H, dtype=np.int64)
    np.minimum.at(first, origin, corners)
    used = np.flatnonzero(count)
    used = used[np.argsort(-count[used], kind="stable")]
    count = count[used]
    start = np.where(start[used] < H, start[used], first[used])
    walking = np.searchsorted(-count, -np.arange(int(count[0]) + 1), side="left")
    corner = start.copy()
    for r in range(1, int(count[0])):  # the vertices of valence > r are the first walking[r]
        active = slice(0, int(walking[r]))
        corner[active] = succ[corner[active]]
        if ((corner[active] < 0) | (corner[active] == start[active])).any():
            _count_vertex_fans(origin, succ, n)  # a fan shorter than the vertex's valence
            return


def _count_vertex_fans(origin: np.ndarray, succ: np.ndarray, n: int) -> None:
    """Raise :class:`NonManifoldVertexError` for the first vertex with two fans of faces
    (connected components of the corner graph linked by ``succ`` (H,))."""
    H = len(origin)
    linked = succ >= 0
    graph = sp.coo_matrix((np.ones(int(linked.sum())), (np.arange(H)[linked], succ[linked])),
                          shape=(H, H))
    n_fans, fan = connected_components(graph, directed=False)
    # Corners linked around a vertex share it: each fan has one vertex (no sort needed).
    fan_vertex = np.empty(n_fans, dtype=np.int64)
    fan_vertex[fan] = origin
    fans_per_vertex = np.bincount(fan_vertex, minlength=n)
    if fans_per_vertex.max() > 1:
        v = int(np.flatnonzero(fans_per_vertex > 1)[0])
        raise NonManifoldVertexError(
            f"vertex {v} joins {int(fans_per_vertex[v])} separate fans of faces "
            f"{(np.flatnonzero(origin == v) // 3).tolist()[:12]}; split the vertex",
            field="faces", index=int(np.flatnonzero(origin == v)[0] // 3),
            details={"vertex": v})


def cycle_ranks(successor: np.ndarray, max_length: int | None = None,
                ) -> tuple[np.ndarray, np.ndarray]:
    """Cycle id and position of each element of a permutation made of cycles.

    Args:
        successor: (k,) int64 permutation.
        max_length: an upper bound on the cycle lengths (default k); the cost is
            O(k log max_length) by pointer doubling.

    Returns:
        ``(leader, rank)``, (k,) int64 each: the smallest index in each element's cycle,
        and the number of steps from that leader to the element.

    Example:
        The cycles 0 -> 1 -> 2 -> 0 and 3 -> 4 -> 3:

        >>> import numpy as np
        >>> from solver.mesh.topology import cycle_ranks
        >>> leader, rank = cycle_ranks(np.array([1, 2, 0, 4, 3]))
        >>> leader.tolist(), rank.tolist()
        ([0, 0, 0, 3, 3], [0, 1, 2, 0, 1])
    """
    k = len(successor)
    bound = k if max_length is None else max(int(max_length), 1)
    leader = np.arange(k)
    jump = successor.copy()
    span = 1
    while span < bound:
        leader = np.minimum(leader, leader[jump])
        jump = jump[jump]
        span *= 2
    succ = np.where(successor == leader, np.arange(k), successor)  # cut each cycle at its leader
    dist = (succ != np.arange(k)).astype(np.int64)
    span = 1
    while span < bound:
        dist = dist + dist[succ]
        succ = succ[succ]
        span *= 2
    length = dist[leader] + 1
    return leader, length - 1 - dist


def _boundary_loops(origin: np.ndarray, dest: np.ndarray, boundary: np.ndarray, n: int,
                    vertex_component: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
    """Boundary vertex loops in half-edge order and the component of each loop.

    Args:
        origin, dest: (H,) int64 half-edge endpoints.
        boundary: (H,) bool, half-edges without a twin.
        n: vertex count.
        vertex_component: (n,) int64.

    Returns:
        ``(loops, loop_component)``: a list of (k,) int64 loops and (b,) int64.
    """
    b_half = np.flatnonzero(boundary)
    if len(b_half) == 0:
        return [], np.zeros(0, dtype=np.int64)
    outgoing = np.full(n, -1, dtype=np.int64)
    outgoing[origin[b_half]] = np.arange(len(b_half))
    successor = outgoing[dest[b_half]]
    leader, rank = cycle_ranks(successor)
    order = np.lexsort((rank, leader))
    loop_vertices = origin[b_half][order]
    _, starts = np.unique(leader[order], return_index=True)
    loops = np.split(loop_vertices, starts[1:])
    return loops, vertex_component[loop_vertices[starts]].astype(np.int64)
