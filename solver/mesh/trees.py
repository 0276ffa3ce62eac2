"""Spanning forests and prefix products along them (vectorized, by pointer doubling)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order, connected_components


@dataclass(frozen=True)
class SpanningForest:
    """A breadth-first spanning forest of a graph with one root per connected component.

    Attributes:
        parent: (k,) int64 parent node; roots are their own parent.
        parent_link: (k,) int64 index (into the graph's link list) of the link to the parent,
            -1 at roots.
        in_tree: (L,) bool, True for links used by the forest.
        levels: ``(order, bounds)`` of :func:`forest_levels` (nodes by depth), read off the
            breadth-first order; None: computed from ``parent`` when needed.
    """

    parent: np.ndarray
    parent_link: np.ndarray
    in_tree: np.ndarray
    levels: tuple[np.ndarray, np.ndarray] | None = None


def spanning_forest(n_nodes: int, links: np.ndarray, roots: np.ndarray | None = None,
                    ) -> SpanningForest:
    """Breadth-first spanning forest of an undirected graph.

    Parallel links are allowed (only one of them can be a tree link).

    Args:
        n_nodes: k, the number of nodes.
        links: (L, 2) int node pairs.
        roots: optional preferred roots: a component containing one is grown from it;
            other components are grown from their smallest node.

    Returns:
        The :class:`SpanningForest`.

    Example:
        A triangle 0-1-2 with a tail 2-3: the link 1-2 closes the cycle.

        >>> import numpy as np
        >>> from solver.mesh.trees import spanning_forest
        >>> forest = spanning_forest(4, np.array([[0, 1], [1, 2], [2, 0], [2, 3]]))
        >>> forest.parent.tolist(), forest.in_tree.tolist()
        ([0, 0, 0, 2], [True, False, True, True])
    """
    links = np.asarray(links, dtype=np.int64).reshape(-1, 2)
    super_root = n_nodes
    graph = sp.coo_matrix((np.ones(len(links)), (links[:, 0], links[:, 1])),
                          shape=(n_nodes, n_nodes))
    _, component = connected_components(graph, directed=False)
    first = np.full(component.max() + 1 if n_nodes else 0, n_nodes, dtype=np.int64)
    if roots is not None and len(roots):
        np.minimum.at(first, component[roots], roots)
    unset = first == n_nodes
    first[unset] = np.unique(component, return_index=True)[1][unset]
    starts = np.concatenate([links[:, 0], np.full(len(first), super_root)])
    ends = np.concatenate([links[:, 1], first])
    full = sp.coo_matrix((np.ones(len(starts)), (starts, ends)),
                         shape=(n_nodes + 1, n_nodes + 1)).tocsr()
    visit, pred = breadth_first_order(full, super_root, directed=False,
                                      return_predecessors=True)
    parent = pred[:n_nodes].astype(np.int64)
    is_root = parent == super_root
    parent[is_root] = np.flatnonzero(is_root)
    levels = _breadth_first_levels(visit[1:].astype(np.int64), parent, len(first))

    # Which link joins each node to its parent: look the unordered pair up among the links.
    key = np.minimum(links[:, 0], links[:, 1]) * (n_nodes + 1) + np.maximum(links[:, 0],
                                                                            links[:, 1])
    order = np.argsort(key, kind="stable")
    nodes = np.flatnonzero(~is_root)
    want = (np.minimum(nodes, parent[nodes]) * (n_nodes + 1)
            + np.maximum(nodes, parent[nodes]))
    pos = np.searchsorted(key[order], want)
    parent_link = np.full(n_nodes, -1, dtype=np.int64)
    parent_link[nodes] = order[pos]
    in_tree = np.zeros(len(links), dtype=bool)
    in_tree[parent_link[nodes]] = True
    return SpanningForest(parent=parent, parent_link=parent_link, in_tree=in_tree,
                          levels=levels)


def _breadth_first_levels(order: np.ndarray, parent: np.ndarray, n_roots: int,
                          ) -> tuple[np.ndarray, np.ndarray]:
    """``(order, bounds)`` of :func:`forest_levels` from a breadth-first visit ``order``
    (k,) whose first ``n_roots`` nodes are the roots: there the parents' positions never
    decrease, so each level ends where the parents leave the level before (one binary
    search per level)."""
    position = np.empty(len(order), dtype=np.int64)
    position[order] = np.arange(len(order))
    parent_position = position[parent[order]]
    bounds = [0, n_roots]
    while bounds[-1] < len(order):
        bounds.append(int(np.searchsorted(parent_position, bounds[-1])))
    return order, np.asarray(bounds, dtype=np.int64)


def forest_levels(parent: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The nodes of a forest ordered by depth, and where each depth starts in that order.

    Args:
        parent: (k,) int forest parents (roots point to themselves).

    Returns:
        ``(order, bounds)``: (k,) int64 nodes sorted by depth (stable), and (D + 2,) int64
        offsets such that ``order[bounds[d]:bounds[d + 1]]`` are the nodes of depth d
        (roots: depth 0; D the largest depth).

    Example:
        >>> import numpy as np
        >>> from solver.mesh.trees import forest_levels
        >>> order, bounds = forest_levels(np.array([0, 0, 1, 0, 4]))
        >>> order.tolist(), bounds.tolist()
        ([0, 4, 1, 3, 2], [0, 2, 4, 5])
    """
    parent = np.asarray(parent, dtype=np.int64)
    anc = parent.copy()
    depth = (parent != np.arange(len(parent))).astype(np.int64)
    while not np.array_equal(anc[anc], anc):      # pointer doubling on integers: cheap
        depth = depth[anc] + depth
        anc = anc[anc]
    order = np.argsort(depth, kind="stable")
    top = int(depth.max(initial=0))
    bounds = np.searchsorted(depth[order], np.arange(top + 2))
    return order, bounds


LEVELS_PER_NODE = 1 / 128
"""Propagate level by level (one small batch per depth, O(k) work) when a forest has at
most ``LEVELS_PER_NODE * k`` levels (and at least 64); deeper forests (long paths) use
pointer doubling (O(k log depth) work, O(log depth) numpy calls)."""


def _by_levels(parent: np.ndarray, n_levels: int) -> bool:
    return n_levels <= max(64, LEVELS_PER_NODE * len(parent))


def _accumulate(parent: np.ndarray, local: np.ndarray,
                levels: tuple[np.ndarray, np.ndarray] | None,
                combine: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> np.ndarray:
    """Root-to-node folds ``A[v] = combine(A[parent[v]], local[v])`` of an associative
    ``combine`` (``np.matmul``, ``np.add``) on (k, ...) float64 ``local``: level by level
    from the roots on shallow forests, by pointer doubling on deep ones."""
    order, bounds = forest_levels(parent) if levels is None else levels
    acc = local.copy()
    if _by_levels(parent, len(bounds) - 2):
        for d in range(1, len(bounds) - 1):
            nodes = order[bounds[d]:bounds[d + 1]]
            acc[nodes] = combine(acc[parent[nodes]], acc[nodes])
        return acc
    anc = np.asarray(parent, dtype=np.int64).copy()
    while not np.array_equal(anc[anc], anc):
        acc = combine(acc[anc], acc)
        anc = anc[anc]
    return acc


def accumulate_products(parent: np.ndarray, local: np.ndarray,
                        levels: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Root-to-node matrix products ``G[v] = G[parent[v]] @ local[v]``, G[root] = local[root].

    Args:
        parent: (k,) int64 forest parents (roots point to themselves).
        local: (k, d, d) float64 per-node transforms; roots should hold the identity.
        levels: optional ``(order, bounds)`` of :func:`forest_levels` (a
            :class:`SpanningForest`'s ``levels``); computed when None.

    Returns:
        (k, d, d) float64 products: level by level from the roots (one batched product
        per depth) on shallow forests, by pointer doubling (O(k log depth)) on deep ones.

    Example:
        >>> import numpy as np
        >>> from solver.mesh.trees import accumulate_products
        >>> local = np.array([[[1.0]], [[2.0]], [[3.0]], [[5.0]]])
        >>> accumulate_products(np.array([0, 0, 1, 0]), local).ravel().tolist()
        [1.0, 2.0, 6.0, 5.0]
    """
    return _accumulate(parent, local, levels, np.matmul)


def accumulate_sums(parent: np.ndarray, local: np.ndarray,
                    levels: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Root-to-node sums ``S[v] = S[parent[v]] + local[v]``.

    Args:
        parent: (k,) int64 forest parents (roots point to themselves).
        local: (k, ...) float64 per-node steps; roots should hold zeros.
        levels: as in :func:`accumulate_products`.

    Returns:
        (k, ...) float64 sums (level by level on shallow forests, by pointer doubling on
        deep ones, as :func:`accumulate_products`).

    Example:
        >>> import numpy as np
        >>> from solver.mesh.trees import accumulate_sums
        >>> accumulate_sums(np.array([0, 0, 1, 2]), np.array([0.0, 1.0, 2.0, 4.0])).tolist()
        [0.0, 1.0, 3.0, 7.0]
    """
    return _accumulate(parent, local, levels, np.add)
