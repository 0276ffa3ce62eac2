"""Spanning forests and prefix products along them (vectorized, by pointer doubling)."""

from __future__ import annotations

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
    """

    parent: np.ndarray
    parent_link: np.ndarray
    in_tree: np.ndarray


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
        >>> from solver.trees import spanning_forest
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
    _, pred = breadth_first_order(full, super_root, directed=False, return_predecessors=True)
    parent = pred[:n_nodes].astype(np.int64)
    is_root = parent == super_root
    parent[is_root] = np.flatnonzero(is_root)

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
    return SpanningForest(parent=parent, parent_link=parent_link, in_tree=in_tree)


def accumulate_products(parent: np.ndarray, local: np.ndarray) -> np.ndarray:
    """Root-to-node matrix products ``G[v] = G[parent[v]] @ local[v]``, G[root] = local[root].

    Args:
        parent: (k,) int64 forest parents (roots point to themselves).
        local: (k, d, d) float64 per-node transforms; roots should hold the identity.

    Returns:
        (k, d, d) float64 products, by pointer doubling (O(k log depth)).
    """
    anc = parent.copy()
    acc = local.copy()
    while not np.array_equal(anc[anc], anc):
        acc = acc[anc] @ acc
        anc = anc[anc]
    return acc


def accumulate_sums(parent: np.ndarray, local: np.ndarray) -> np.ndarray:
    """Root-to-node sums ``S[v] = S[parent[v]] + local[v]``.

    Args:
        parent: (k,) int64 forest parents (roots point to themselves).
        local: (k, ...) float64 per-node steps; roots should hold zeros.

    Returns:
        (k, ...) float64 sums, by pointer doubling.

    Example:
        >>> import numpy as np
        >>> from solver.trees import accumulate_sums
        >>> accumulate_sums(np.array([0, 0, 1, 2]), np.array([0.0, 1.0, 2.0, 4.0])).tolist()
        [0.0, 1.0, 3.0, 7.0]
    """
    anc = parent.copy()
    acc = local.copy()
    while not np.array_equal(anc[anc], anc):
        acc = acc[anc] + acc
        anc = anc[anc]
    return acc
