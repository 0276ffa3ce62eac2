"""Charts: seams that cut a mesh into pieces that flatten well.

A chart is a set of faces, edge-connected, flattened on its own. The seams are the edges
between charts. :func:`xatlas_charts` gives xatlas's charting (normal deviation, roundness,
straightness, seam costs), the start of :func:`solver.atlas.chart_layouts`;
:func:`labelled_face_sets` turns its labels into edge-connected charts. :func:`bisect`
splits a chart that fails the checks in two: the two faces farthest apart on the dual graph
(two Dijkstra sweeps from any face) grow Voronoi regions over the dual graph whose edge
costs are the distances between face centroids, raised where the surface bends
(``1 + crease_weight * (1 - cos dihedral)``), so the cut between them tends to run along
creases and never crosses a flat region it could go around. Graph Voronoi regions are
connected (a face's predecessor on its shortest path has the same seed), so both halves
are charts; a chart that is closed or has a handle is always split, so the cuts through the
homology generators and between holes come from the same recursion (docs/flattening.md
compares the chartings in numbers).

:func:`chart_mesh` extracts a chart as its own mesh, giving a vertex where a chart touches
itself only at a vertex (two face fans) one copy per fan, so every chart is manifold.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components, dijkstra

from .placement import face_components
from .topology import MeshTopology


@dataclass(frozen=True)
class ChartMesh:
    """One chart as a mesh of its own.

    Attributes:
        face_ids: (m_c,) int64 indices of its faces in the whole mesh.
        vertex_ids: (n_c,) int64 mesh vertex of each chart vertex (a mesh vertex where the
            chart touches itself at a vertex appears once per face fan).
        faces: (m_c, 3) int64 faces over the chart's vertices, same order as ``face_ids``.
    """

    face_ids: np.ndarray
    vertex_ids: np.ndarray
    faces: np.ndarray


@dataclass(frozen=True)
class DualGraph:
    """The whole mesh's face adjacency with seam costs.

    Attributes:
        edge_faces: (I, 2) int64 the two faces of each interior edge.
        cost: (I,) float64 centroid distance times the crease factor.
        mesh_edge: (I,) int64 the edge of each entry in ``topology.edges``.
        face_entries: (m, 3) int64 the entries of each face (-1 where an edge of the face is
            on the boundary), so that a chart's graph is read from its own faces' entries.
    """

    edge_faces: np.ndarray
    cost: np.ndarray
    mesh_edge: np.ndarray
    face_entries: np.ndarray


def dual_graph(vertices: np.ndarray, topology: MeshTopology, angles: np.ndarray,
               crease_weight: float) -> DualGraph:
    """The dual graph of ``topology`` with costs (module docstring).

    Args:
        vertices: (n, 3) float64.
        topology: the mesh.
        angles: (E,) float64 signed dihedral angles (0 on the boundary).
        crease_weight: how much more a bent edge costs (0: plain centroid distances).
    """
    interior = np.flatnonzero((topology.edge_faces >= 0).all(axis=1))
    pairs = topology.edge_faces[interior]
    centroids = vertices[topology.faces].mean(axis=1)
    distance = np.linalg.norm(centroids[pairs[:, 0]] - centroids[pairs[:, 1]], axis=1)
    cost = np.maximum(distance, 1e-12) * (1.0 + crease_weight * (1.0 - np.cos(angles[interior])))
    return DualGraph(pairs, cost, interior, _face_entries(pairs, len(topology.faces)))


def _face_entries(pairs: np.ndarray, n_faces: int) -> np.ndarray:
    """(n_faces, 3) int64: the rows of ``pairs`` (I, 2) naming each face, -1 padded."""
    owner = pairs.T.ravel()                                  # face of each (entry, side)
    entry = np.tile(np.arange(len(pairs)), 2)
    order = np.argsort(owner, kind="stable")
    count = np.bincount(owner, minlength=n_faces)
    slot = np.arange(len(owner)) - np.repeat(np.cumsum(count) - count, count)
    table = np.full((n_faces, max(3, int(count.max(initial=0)))), -1, dtype=np.int64)
    table[owner[order], slot] = entry[order]
    return table


def _local_graph(graph: DualGraph, face_ids: np.ndarray, n_faces: int) -> sp.csr_array:
    """The dual graph restricted to ``face_ids`` (local indices), read from those faces'
    entries (its cost grows with the chart, not the mesh: a chart bisected again and again
    on a 100K-face mesh read every entry each time, 6 s of its atlas)."""
    local = np.full(n_faces, -1, dtype=np.int64)
    local[face_ids] = np.arange(len(face_ids))
    entries = graph.face_entries[face_ids].ravel()
    entries = np.unique(entries[entries >= 0])               # in the mesh's entry order
    ends = local[graph.edge_faces[entries]]
    keep = (ends >= 0).all(axis=1)
    a, b = ends[keep, 0], ends[keep, 1]
    cost = graph.cost[entries[keep]]
    k = len(face_ids)
    matrix = sp.coo_array((np.concatenate([cost, cost]),
                           (np.concatenate([a, b]), np.concatenate([b, a]))), shape=(k, k))
    return matrix.tocsr()


def connected_face_sets(graph: DualGraph, face_ids: np.ndarray, n_faces: int,
                        ) -> list[np.ndarray]:
    """The edge-connected components of ``face_ids`` (each (k,) int64, mesh face indices)."""
    matrix = _local_graph(graph, face_ids, n_faces)
    count, label = connected_components(matrix, directed=False)
    order = np.argsort(label, kind="stable")
    bounds = np.searchsorted(label[order], np.arange(count + 1))
    return [face_ids[order[bounds[c]:bounds[c + 1]]] for c in range(count)]


def bisect(graph: DualGraph, face_ids: np.ndarray, n_faces: int) -> list[np.ndarray]:
    """Split an edge-connected chart of two or more faces into connected charts.

    The two faces farthest apart (two Dijkstra sweeps) seed graph Voronoi regions; each
    region is edge-connected. Returns the parts (two, or more if a region is not connected,
    which only exact ties can cause), each a (k,) int64 array of mesh face indices.
    """
    matrix = _local_graph(graph, face_ids, n_faces)
    first = dijkstra(matrix, directed=False, indices=0)
    a = int(np.argmax(np.where(np.isfinite(first), first, -1.0)))
    from_a = dijkstra(matrix, directed=False, indices=a)
    b = int(np.argmax(np.where(np.isfinite(from_a), from_a, -1.0)))
    if a == b:
        b = (a + 1) % len(face_ids)
    from_b = dijkstra(matrix, directed=False, indices=b)
    nearer_a = from_a <= from_b
    parts = []
    for side in (nearer_a, ~nearer_a):
        if side.any():
            parts.extend(connected_face_sets(graph, face_ids[side], n_faces))
    return parts


def chart_mesh(faces: np.ndarray, face_ids: np.ndarray) -> ChartMesh:
    """The chart ``face_ids`` of the mesh ``faces`` (m, 3) as a manifold mesh of its own.

    Corners of one mesh vertex are joined when their faces share an edge through that
    vertex (within the chart); each group of corners (a face fan) becomes one chart vertex.

    Example:
        >>> import numpy as np
        >>> bowtie = np.array([[0, 1, 2], [0, 3, 4]])       # two fans meet at vertex 0
        >>> chart = chart_mesh(bowtie, np.array([0, 1]))
        >>> chart.vertex_ids.tolist(), chart.faces.tolist()
        ([0, 0, 1, 2, 3, 4], [[0, 2, 3], [1, 4, 5]])
    """
    F = faces[face_ids]
    m = len(F)
    corner_vertex = F.ravel()                                   # corner 3 t + k
    tail, head = F.ravel(), np.roll(F, -1, axis=1).ravel()      # half-edge 3 t + k
    key = np.minimum(tail, head) * (faces.max() + 1) + np.maximum(tail, head)
    order = np.argsort(key, kind="stable")
    same = key[order[1:]] == key[order[:-1]]
    h1, h2 = order[:-1][same], order[1:][same]                  # twin half-edges
    # h1: a -> b in face t1 (corner h1 at a, corner next(h1) at b); h2: b -> a.
    nxt = 3 * (np.arange(3 * m) // 3) + (np.arange(3 * m) + 1) % 3
    join = sp.coo_array((np.ones(2 * len(h1)), (np.concatenate([h1, nxt[h1]]),
                                                np.concatenate([nxt[h2], h2]))),
                        shape=(3 * m, 3 * m))
    _, fan = connected_components(join, directed=False)
    fan_vertex = np.zeros(fan.max() + 1, dtype=np.int64)
    fan_vertex[fan] = corner_vertex
    # Number chart vertices by (mesh vertex, fan) so a chart without pinches keeps the
    # mesh's vertex order.
    rank = np.lexsort((np.arange(len(fan_vertex)), fan_vertex))
    new_index = np.empty_like(rank)
    new_index[rank] = np.arange(len(rank))
    return ChartMesh(np.asarray(face_ids, dtype=np.int64), fan_vertex[rank],
                     new_index[fan].reshape(m, 3))


def is_disk_like(topology: MeshTopology) -> bool:
    """One component with a boundary and genus 0 (a disk, possibly with holes)."""
    return topology.n_components == 1 and bool(disk_like_components(topology)[0])


def disk_like_components(topology: MeshTopology) -> np.ndarray:
    """(components,) bool: each component has a boundary and genus 0 (Euler characteristic
    2 - b over its used vertices, edges and faces; b its boundary loops). A component without
    faces (an unused vertex) is not disk-like."""
    count = topology.n_components
    used = np.bincount(topology.vertex_component[topology.is_referenced], minlength=count)
    edges = np.bincount(topology.vertex_component[topology.edges[:, 0]], minlength=count)
    faces = np.bincount(topology.face_component, minlength=count)
    loops = np.bincount(np.asarray(topology.boundary_loop_component, dtype=np.int64),
                        minlength=count)
    return (loops > 0) & (used - edges + faces == 2 - loops)


def seam_edges(topology: MeshTopology, face_chart: np.ndarray) -> np.ndarray:
    """(s,) int64 the interior edges of ``topology`` whose two faces lie in different charts."""
    ends = topology.edge_faces
    interior = (ends >= 0).all(axis=1)
    cut = np.zeros(len(ends), dtype=bool)
    cut[interior] = face_chart[ends[interior, 0]] != face_chart[ends[interior, 1]]
    return np.flatnonzero(cut)


def xatlas_charts(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """xatlas's charting of the mesh (its default ``ChartOptions``: charts grown from seed
    faces by normal deviation, roundness, straightness and seam costs; ``xatlas`` on PyPI).

    Args:
        vertices: (n, 3) float64; faces: (m, 3) int64.

    Returns:
        (m,) int64 the xatlas chart of each face; faces xatlas leaves out (degenerate
        ones) get one label past the last chart, so callers split labels into
        edge-connected sets (:func:`connected_face_sets`).
    """
    import xatlas

    atlas = xatlas.Atlas()
    atlas.add_mesh(np.asarray(touching_parts_apart(vertices, faces), dtype=np.float32),
                   np.asarray(faces, dtype=np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution = 256                  # the placement is not used: keep it cheap
    atlas.generate(pack_options=pack)
    count = atlas.get_mesh_chart_count(0)
    label = np.full(len(faces), count, dtype=np.int64)
    for chart in range(count):             # a loop over charts
        label[np.asarray(atlas.get_mesh_chart(0, chart).faces, dtype=np.int64)] = chart
    return label


def touching_parts_apart(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``vertices`` (n, 3) float64 with the parts (vertex-connected components of ``faces``
    (m, 3)) that share a position with another part moved apart: each to a cell of its own
    past the mesh's bounding box, cells twice the largest moved part's extent. The copies
    a non-manifold cut makes of a vertex lie at one position in different parts, and xatlas
    welds vertices at one position again (on libigl's cube_40k.obj, 55,981 such parts: no
    atlas after 20 minutes; 6 s apart). The parts that touch no other stay where they are
    (a mesh of one part is returned as it is). Charting is the same wherever a part lies.

    Example:
        >>> import numpy as np
        >>> V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0], [1, 0, 0], [0, 0, 1.]])
        >>> apart = touching_parts_apart(V, np.array([[0, 1, 2], [3, 4, 5]]))
        >>> apart[:3].tolist() == V[:3].tolist(), bool((apart[3:] != V[3:]).any())
        (True, True)
    """
    part, _ = face_components(faces, len(vertices))
    count = int(part.max(initial=-1)) + 1
    if count < 2:
        return vertices
    _, position = np.unique(vertices, axis=0, return_inverse=True)
    position = position.ravel()
    first = np.full(position.max() + 1, count)
    np.minimum.at(first, position, part)
    moved = np.zeros(count, dtype=bool)
    moved[part[part != first[position]]] = True
    if not moved.any():
        return vertices
    low = np.full((count, 3), np.inf)
    high = np.full((count, 3), -np.inf)
    np.minimum.at(low, part, vertices)
    np.maximum.at(high, part, vertices)
    movers = np.flatnonzero(moved)
    step = 2.0 * max(float((high[movers] - low[movers]).max()), np.finfo(float).tiny)
    side = int(np.ceil(len(movers) ** (1 / 3)))
    cell = np.zeros((count, 3))
    cell[movers] = np.stack(np.unravel_index(np.arange(len(movers)), (side,) * 3), axis=1)
    origin = vertices.max(axis=0) + step
    out = vertices.copy()
    at = moved[part]
    out[at] = vertices[at] - low[part[at]] + origin + cell[part[at]] * step
    return out


def labelled_face_sets(graph: DualGraph, label: np.ndarray) -> list[np.ndarray]:
    """The edge-connected face sets of equal ``label`` (m,): each (k,) int64 mesh faces."""
    m = len(label)
    keep = label[graph.edge_faces[:, 0]] == label[graph.edge_faces[:, 1]]
    a, b = graph.edge_faces[keep, 0], graph.edge_faces[keep, 1]
    matrix = sp.coo_array((np.ones(len(a)), (a, b)), shape=(m, m))
    count, component = connected_components(matrix, directed=False)
    order = np.argsort(component, kind="stable")
    bounds = np.searchsorted(component[order], np.arange(count + 1))
    return [order[bounds[c]:bounds[c + 1]] for c in range(count)]


__all__ = ["ChartMesh", "DualGraph", "bisect", "chart_mesh", "connected_face_sets",
           "disk_like_components", "dual_graph", "is_disk_like", "labelled_face_sets", "seam_edges",
           "touching_parts_apart", "xatlas_charts"]
