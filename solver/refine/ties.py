"""Tied vertices: the endpoints of needle edges move as one in the refinement's steps.

An edge far shorter than the faces it bounds (a split near an endpoint, a needle left by a
scanner or a decimation: :data:`TIE_RATIO`) makes the refinement of :mod:`solver.refine`
ill-posed in two ways (issue 40, measured on rocker-arm with 100 edges split at 1e-5 of
their length, noisy angles; ``docs/refinement.md``, "Needles"):

* **Conditioning.** The relative length residual of an edge of length ``l`` has stiffness
  ``1 / l^2``: 1e10 times a mean edge's. With the floor that regularizes the rigid motions
  (1e-9 of the median diagonal) the damped Gauss-Newton matrix has a condition number of
  ~1e19, beyond double precision: its solves failed their residual check for every damping
  up to 1e-3 (7 factorizations spent before a first step).
* **Nonlinearity.** Gauss-Newton's model of that residual sees only the motion along the
  edge. Moving one endpoint by ``d`` across it stretches it by ``d^2 / (2 l)``: a step that
  moves vertices by 1e-3 of the mean edge (what noise of 1e-3 rad asks for) stretches an
  edge of 1e-5 by a factor 5000. Every full step was refused, the damping grew to 2e3 and
  the steps shrank to 1e-7 of an edge: stalled after 15 factorizations.

The tie removes both: the endpoints of every needle edge are one unknown (the *master*'s),
the other endpoints (*tied* vertices) follow it at a fixed offset, set at the start of each
run to the edge's target length (:meth:`Ties.offsets`). A needle's length residual is then
constant (0) in every step, its stiffness leaves the matrix, and its direction stays that of
the start (a rotation of an edge 1e-4 of its faces' size moves its faces' other elements by
1e-4 of their size times the angle: below the refinement's tolerance). Ties join needle
edges into clusters (connected components); a cluster with two or more vertices a handle
holds is not tied, one with one such vertex has it as master.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from ..mesh.topology import MeshTopology

TIE_RATIO = 1e-2
"""An edge shorter than this fraction of the longest edge of one of its faces is a needle:
its endpoints are tied. The same 1/100 as :data:`solver.refine.form_energy.NEEDLE_STIFFNESS`'s
(a stiffness 1e4 times a mean edge's), but local: a region sampled 100 times finer than the
mean, whose faces are well shaped, is not tied."""


@dataclass(frozen=True)
class Ties:
    """Which vertices follow which (:func:`needle_ties`).

    Attributes:
        vertices: (k,) int64 the tied vertices.
        masters: (k,) int64 the vertex each follows (never itself tied).
        edges: (k,) int64 the needle edge from each tied vertex to its master, -1 where it
            reaches its master through other tied vertices.
        lengths: (k,) float64 the target lengths of those edges (nan where -1).
    """

    vertices: np.ndarray
    masters: np.ndarray
    edges: np.ndarray
    lengths: np.ndarray

    def __len__(self) -> int:
        return len(self.vertices)

    def rigid_edges(self, edges: np.ndarray, n: int) -> np.ndarray:
        """(E,) bool, the ``edges`` (E, 2) whose endpoints move as one (same master)."""
        root = np.arange(n)
        root[self.vertices] = self.masters
        return root[edges[:, 0]] == root[edges[:, 1]]

    def offsets(self, X: np.ndarray) -> np.ndarray:
        """(k, dim) float64 offsets of the tied vertices from their masters at positions
        ``X`` (n, dim), those joined to their master by one needle edge scaled to its
        target length (a start whose needles are off their lengths is put on them)."""
        offset = X[self.vertices] - X[self.masters]
        direct = self.edges >= 0
        size = np.linalg.norm(offset[direct], axis=1)
        scale = np.where(size > 0, self.lengths[direct] / np.where(size > 0, size, 1.0), 1.0)
        offset[direct] *= scale[:, None]
        return offset

    def place(self, X: np.ndarray, offsets: np.ndarray) -> None:
        """Put the tied vertices of ``X`` (n, dim) at their masters plus ``offsets``
        (k, dim), in place."""
        X[self.vertices] = X[self.masters] + offsets


def no_ties() -> Ties:
    """Ties of a mesh without needles."""
    empty = np.zeros(0, dtype=np.int64)
    return Ties(empty, empty, empty, np.zeros(0))


def needle_ties(topology: MeshTopology, lengths: np.ndarray, held: np.ndarray) -> Ties:
    """The ties of a mesh's needle edges (:data:`TIE_RATIO`).

    Args:
        topology: the mesh's connectivity (E edges).
        lengths: (E,) float64 target edge lengths.
        held: (n,) bool, the vertices a handle holds.

    Returns:
        :class:`Ties` (empty for a mesh without needles).

    Example:
        >>> import numpy as np
        >>> from solver.mesh.topology import build_topology
        >>> topo = build_topology(np.array([[0, 1, 2], [1, 3, 2]]))
        >>> L = np.ones(topo.n_edges); L[topo.edges.tolist().index([1, 2])] = 1e-5
        >>> ties = needle_ties(topo, L, np.zeros(4, bool))
        >>> ties.vertices.tolist(), ties.masters.tolist()
        ([2], [1])
    """
    # Candidates: edges that short beside the longest edge of all; then the longest edge of
    # their own faces decides (O(candidates), not O(faces): each row of a blend asks).
    candidates = np.flatnonzero(lengths < TIE_RATIO * lengths.max(initial=0.0))
    faces = topology.edge_faces[candidates]                                     # (k, 2)
    face_edges = topology.halfedge_edge.reshape(-1, 3)[np.maximum(faces, 0)]    # (k, 2, 3)
    around = np.where(faces >= 0, lengths[face_edges].max(axis=2), 0.0).max(axis=1,
                                                                          initial=0.0)
    needle = candidates[lengths[candidates] < TIE_RATIO * around]
    if not len(needle):
        return no_ties()
    n = topology.n_vertices
    i, j = topology.edges[needle, 0], topology.edges[needle, 1]
    graph = sp.coo_array((np.ones(len(needle)), (i, j)), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    size = np.bincount(label)
    held_count = np.bincount(label, weights=held.astype(np.float64), minlength=len(size))
    tied_cluster = (size > 1) & (held_count <= 1)
    # Master: the held vertex of a cluster that has one, else its smallest vertex.
    vertex = np.arange(n)
    priority = np.where(held, vertex - n, vertex)
    best = np.full(len(size), n, dtype=np.int64)
    np.minimum.at(best, label, priority)
    master = np.where(best < 0, best + n, best)[label]                         # (n,)
    tied = np.flatnonzero(tied_cluster[label] & (master != vertex))
    if not len(tied):
        return no_ties()
    # The needle edge from a tied vertex straight to its master, where there is one.
    edge_of = np.full(n, -1, dtype=np.int64)
    to_master = master[j] == i
    edge_of[j[to_master]] = needle[to_master]
    from_master = master[i] == j
    edge_of[i[from_master]] = needle[from_master]
    edges = edge_of[tied]
    target = np.where(edges >= 0, lengths[np.maximum(edges, 0)], np.nan)
    return Ties(tied, master[tied], edges, target)
