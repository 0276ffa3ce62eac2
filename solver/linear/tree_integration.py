"""Integration of the forms along spanning trees (Sec. 2.3's proof of the global theorem).

Frames follow the transition rotations from a root face along a spanning forest of the
faces (Eq. 2); positions add the edge vectors ``f_T (a1, a2, 0)`` (Eq. 3) along a spanning
forest of the vertices through the edges the first forest does not cross. For integrable
forms this is the immersion itself (up to rounding): :mod:`solver.immersion` answers with
it when the residual rows of Eq. 5 vanish, and :mod:`solver.linear.integrability` measures
the translation holonomy of the loops it leaves open.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..mesh.frames import transition_rotations
from ..mesh.trees import fold_from_roots, spanning_forest
from .system import EnergyTerms


@dataclass(frozen=True)
class IntegrationForests:
    """The paths along which frames and then positions are integrated (Sec. 2.3's proof).

    Attributes:
        dual: :class:`solver.mesh.trees.SpanningForest` of the faces, across interior edges.
        rest: (r,) int64 edges the dual forest does not cross.
        primal: :class:`solver.mesh.trees.SpanningForest` of the vertices along ``rest``.
    """

    dual: Any
    rest: np.ndarray
    primal: Any


def integration_forests(terms: EnergyTerms, root_faces: np.ndarray | None = None,
                        root_vertices: np.ndarray | None = None) -> IntegrationForests:
    """Spanning forests for :func:`integrate_along_forests`, grown from the given roots.

    Args:
        terms: layouts and transition rotations (:func:`solver.linear.system.energy_terms`).
        root_faces: optional (r,) int64 preferred roots of the dual forest.
        root_vertices: optional (s,) int64 preferred roots of the primal forest.

    Returns:
        :class:`IntegrationForests`.
    """
    topo = terms.topology
    inner = terms.interior_edges
    # A manifold mesh's faces are connected across interior edges exactly when they share
    # a component (one fan per vertex), and the edges a dual spanning forest does not cross
    # still connect each component's vertices (a cut of crossed edges would close a loop of
    # the dual forest): both forests' components are the mesh's.
    dual = spanning_forest(topo.n_faces, topo.edge_faces[inner], roots=root_faces,
                           components=topo.face_component)
    crossed = np.zeros(topo.n_edges, dtype=bool)
    crossed[inner[dual.in_tree]] = True
    rest = np.flatnonzero(~crossed)
    primal = spanning_forest(topo.n_vertices, topo.edges[rest], roots=root_vertices,
                             components=topo.vertex_component)
    return IntegrationForests(dual=dual, rest=rest, primal=primal)


def integrate_along_forests(terms: EnergyTerms, forests: IntegrationForests,
                            ) -> tuple[np.ndarray, np.ndarray]:
    """Frames (m, 3, 3) and positions (n, 3) integrated from the roots.

    Frames follow ``f_child = f_parent R`` (Eq. 2) from the identity at each dual root;
    positions add edge vectors ``f_T (a1, a2, 0)`` (Eq. 3, from one face containing the
    edge) along the primal forest from the origin at each primal root. For integrable
    forms this is the immersion itself (up to rounding).

    Args:
        terms: layouts and transition rotations (:func:`solver.linear.system.energy_terms`).
        forests: the paths (:func:`integration_forests`).

    Returns:
        ``(frames, positions)``: (m, 3, 3) and (n, 3) float64 (views of
        :func:`integrated_unknowns`).
    """
    u = integrated_unknowns(terms, forests)
    n, m = terms.topology.n_vertices, terms.topology.n_faces
    return np.swapaxes(u[n:].reshape(m, 3, 3), 1, 2), u[:n]


def integrated_unknowns(terms: EnergyTerms, forests: IntegrationForests) -> np.ndarray:
    """The unknowns of Eq. 5 (N, 3) integrated along ``forests``: positions (n, 3), then
    each face's frame transposed (``u[n + 3 t + c, k] = f_t[k, c]``), written in place.

    Args:
        terms: layouts and transition rotations (:func:`solver.linear.system.energy_terms`).
        forests: the paths (:func:`integration_forests`).

    Returns:
        (n + 3 m, 3) float64.
    """
    topo = terms.topology
    n, m = topo.n_vertices, topo.n_faces
    u = np.empty((n + 3 * m, 3))
    frames_t = u[n:].reshape(m, 3, 3)              # f_t transposed
    dual = forests.dual
    inner_link = links_to_inner(dual, np.ones(len(terms.interior_edges), bool))
    # Transposed: f_child^T = R^T f_parent^T, folded with the factors swapped.
    fold_from_roots(dual.parent, _local_rotations(terms, dual.parent, inner_link, True),
                    dual.levels, lambda above, own: np.matmul(own, above), frames_t)
    tree, rest = forests.primal, forests.rest

    def steps_of(nodes: np.ndarray) -> np.ndarray:
        """Step from each node's parent to it along its tree edge: +-d (0 at roots)."""
        link = tree.parent_link[nodes]
        has = link >= 0
        edge = rest[np.where(has, link, 0)]
        step = edge_vectors(terms, frames_t, edge, transposed=True)
        # +d if the edge runs parent -> node, -d if node -> parent, 0 at roots.
        sign = np.where(topo.edges[edge, 1] == nodes, 1.0, -1.0) * has
        step *= sign[:, None]
        return step

    fold_from_roots(tree.parent, steps_of, tree.levels, np.add, u[:n])
    return u


def links_to_inner(forest: Any, mask: np.ndarray) -> np.ndarray:
    """Map each face's parent link (an index into the masked link list) to interior-edge
    positions (index into ``terms.interior_edges``); -1 at roots."""
    positions = np.flatnonzero(mask)
    out = np.full(len(forest.parent_link), -1, dtype=np.int64)
    has = forest.parent_link >= 0
    out[has] = positions[forest.parent_link[has]]
    return out


def _local_rotations(terms: EnergyTerms, parent: np.ndarray, parent_inner: np.ndarray,
                     transposed: bool = False) -> Any:
    """``local_of(nodes)`` for :func:`solver.mesh.trees.fold_from_roots`: the rotation from
    each face's parent to it, ``R_{parent -> child}`` (``R_LR`` where the parent is left of
    the edge, ``R_RL = R_LR^T`` otherwise; the transposes with ``transposed``), built from
    the transition angles of the tree's edges only (``R_RL`` from ``(theta_R, -phi,
    theta_L)``); the identity at roots."""
    topo = terms.topology

    def local_of(nodes: np.ndarray) -> np.ndarray:
        if not len(terms.interior_edges):  # every face a root (no face has a neighbour)
            return np.broadcast_to(np.eye(3), (len(nodes), 3, 3)).copy()
        link = parent_inner[nodes]
        has = link >= 0
        link = np.where(has, link, 0)
        angles = np.take(terms.transition, link, axis=0)
        parent_is_left = topo.edge_faces[np.take(terms.interior_edges, link), 0] == \
            np.take(parent, nodes)
        flip = parent_is_left if transposed else ~parent_is_left
        first = np.where(flip, angles[:, 2], angles[:, 0])
        angles[:, 2] = np.where(flip, angles[:, 0], angles[:, 2])
        angles[:, 0] = first
        np.negative(angles[:, 1], out=angles[:, 1], where=flip)
        R = transition_rotations(angles)
        R[~has] = np.eye(3)
        return R

    return local_of


def tree_frames(terms: EnergyTerms, parent: np.ndarray, parent_inner: np.ndarray,
                 levels: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Frames (m, 3, 3) integrated from each root face (identity) along a dual tree."""
    frames = np.empty((terms.topology.n_faces, 3, 3))
    return fold_from_roots(parent, _local_rotations(terms, parent, parent_inner), levels,
                           np.matmul, frames)


def edge_vectors(terms: EnergyTerms, frames: np.ndarray, edges: np.ndarray,
                  transposed: bool = False) -> np.ndarray:
    """(k, 3) vector of each of ``edges`` (k,) i -> j, ``f_T (a1, a2, 0)`` from a face
    containing it (``frames`` (m, 3, 3) given transposed with ``transposed``)."""
    topo = terms.topology
    fwd, bwd = np.take(topo.edge_halfedges, edges, axis=0).T
    use_fwd = fwd >= 0
    h = np.where(use_fwd, fwd, bwd)
    f = np.take(frames, h // 3, axis=0)
    a = np.take(terms.coefficients.reshape(-1, 2), h, axis=0)
    if transposed:                                   # rows of f^T are the columns of f
        vec = f[:, 0] * a[:, 0, None]
        vec += f[:, 1] * a[:, 1, None]
    else:
        vec = f[:, :, 0] * a[:, 0, None]
        vec += f[:, :, 1] * a[:, 1, None]
    np.negative(vec, out=vec, where=~use_fwd[:, None])
    return vec
