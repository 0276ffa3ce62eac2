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
                    components: np.ndarray | None = None) -> SpanningForest:
    """Breadth-first spanning forest of an undirected graph.

    Parallel links are allowed (only one of them can be a tree link).

    Args:
        n_nodes: k, the number of nodes.
        links: (L, 2) int node pairs.
        roots: optional preferred roots: a component containing one is grown from it;
            other components are grown from their smallest node.
        components: optional (k,) int64 connected component of each node when the caller
            knows them (e.g. a mesh's faces across its interior edges: the face
            components); computed otherwise.

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
    if components is None:
        graph = sp.coo_matrix((np.ones(len(links)), (links[:, 0], links[:, 1])),
                              shape=(n_nodes, n_nodes))
        components = connected_components(graph, directed=False)[1]
        del graph
    n_comp = int(components.max()) + 1 if n_nodes else 0
    first = np.full(n_comp, n_nodes, dtype=np.int64)
    if roots is not None and len(roots):
        np.minimum.at(first, components[roots], roots)
    smallest = np.full(n_comp, n_nodes, dtype=np.int64)
    np.minimum.at(smallest, components, np.arange(n_nodes))
    first = np.where(first == n_nodes, smallest, first)
    first = first[first < n_nodes]
    # Each entry holds its link (+1), so that each node's parent link is read off the rows
    # of its pair (the search is scipy's undirected one, as before).
    L = len(links)
    full = sp.csr_matrix(
        (np.concatenate([np.arange(1, L + 1, dtype=np.float64), np.ones(len(first))]),
         (np.concatenate([links[:, 0], np.full(len(first), super_root)]),
          np.concatenate([links[:, 1], first]))),
        shape=(n_nodes + 1, n_nodes + 1))
    visit, pred = breadth_first_order(full, super_root, directed=False,
                                      return_predecessors=True)
    parent = pred[:n_nodes].astype(np.int64)
    is_root = parent == super_root
    parent[is_root] = np.flatnonzero(is_root)
    levels = _breadth_first_levels(visit[1:].astype(np.int64), parent, len(first))

    nodes = np.flatnonzero(~is_root)
    if full.nnz == L + len(first):
        parent_link = _row_lookup(full, nodes, parent[nodes], n_nodes)
    else:  # parallel links were summed into one entry: look the pair up among the links
        parent_link = _pair_lookup(links, nodes, parent[nodes], n_nodes)
    in_tree = np.zeros(L, dtype=bool)
    in_tree[parent_link[nodes]] = True
    return SpanningForest(parent=parent, parent_link=parent_link, in_tree=in_tree,
                          levels=levels)


ROW_PROBE_LIMIT = 16
"""Rows of at most this many entries are probed entry by entry by :func:`_row_lookup`;
longer ones (a virtual vertex joined to every boundary vertex: as many entries as the
boundary has vertices) are searched by sorting their entries, since probing takes as many
steps as the longest row and, on such a row, time quadratic in its length."""


def _row_lookup(full: sp.csr_matrix, nodes: np.ndarray, parents: np.ndarray,
                n_nodes: int) -> np.ndarray:
    """(k,) int64 link of each of ``nodes`` to its parent (-1 elsewhere): the entry of the
    pair in ``full`` (links + 1 as values, no duplicates, one direction each), looked up
    in row ``node`` for column ``parent``, then in row ``parent`` for the rest; rows of at
    most :data:`ROW_PROBE_LIMIT` entries probed (as many steps as the longest of them),
    longer rows searched (:func:`_search_rows`)."""
    parent_link = np.full(n_nodes, -1, dtype=np.int64)
    row_length = np.diff(full.indptr)
    rest = np.arange(len(nodes))
    for rows, columns in ((nodes, parents), (parents, nodes)):
        long = row_length[rows[rest]] > ROW_PROBE_LIMIT
        for lookup, pick in ((_probe_rows, rest[~long]), (_search_rows, rest[long])):
            if len(pick):
                found, link = lookup(full, rows[pick], columns[pick])
                parent_link[nodes[pick[found]]] = link
        rest = rest[parent_link[nodes[rest]] < 0]
    return parent_link


def _probe_rows(full: sp.csr_matrix, rows: np.ndarray, columns: np.ndarray,
                ) -> tuple[np.ndarray, np.ndarray]:
    """``(found, link)``: the pairs (``rows``, ``columns``) (k,) int64 found in ``full`` (a
    (k',) int64 index into them) and their links (``full``'s value - 1), probing each row
    entry by entry."""
    position = full.indptr[rows].astype(np.int64)
    end = full.indptr[rows + 1]
    probing = np.arange(len(rows))
    found, link = [], []
    while len(probing):
        at = position[probing]
        inside = at < end[probing]
        hit = inside.copy()
        hit[inside] = full.indices[at[inside]] == columns[probing[inside]]
        found.append(probing[hit])
        link.append(full.data[at[hit]].astype(np.int64) - 1)
        probing = probing[inside & ~hit]
        position[probing] += 1
    return np.concatenate(found), np.concatenate(link)


def _search_rows(full: sp.csr_matrix, rows: np.ndarray, columns: np.ndarray,
                 ) -> tuple[np.ndarray, np.ndarray]:
    """As :func:`_probe_rows`, by sorting the entries of the rows asked for (time
    O(R log R) for their R entries, whatever their lengths)."""
    width = full.shape[1]
    asked = np.unique(rows)
    starts = full.indptr[asked].astype(np.int64)
    counts = full.indptr[asked + 1] - starts
    positions = np.repeat(starts - np.cumsum(counts) + counts, counts) + np.arange(counts.sum())
    keys = np.repeat(asked.astype(np.int64), counts) * width + full.indices[positions]
    wanted = rows.astype(np.int64) * width + columns
    found, position = _find_keys(keys, wanted)
    return found, full.data[positions[position]].astype(np.int64) - 1


def _pair_lookup(links: np.ndarray, nodes: np.ndarray, parents: np.ndarray,
                 n_nodes: int) -> np.ndarray:
    """As :func:`_row_lookup`, by sorting the links' unordered pairs (the first of parallel
    links)."""
    key = np.minimum(links[:, 0], links[:, 1]) * (n_nodes + 1) + np.maximum(links[:, 0],
                                                                            links[:, 1])
    want = np.minimum(nodes, parents) * (n_nodes + 1) + np.maximum(nodes, parents)
    found, link = _find_keys(key, want)
    parent_link = np.full(n_nodes, -1, dtype=np.int64)
    parent_link[nodes[found]] = link
    return parent_link


def _find_keys(keys: np.ndarray, wanted: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(found, position)``: which of ``wanted`` (k,) int64 occur in ``keys`` (K,) int64
    (a (k',) int64 index into ``wanted``) and where (the first of equal keys), by one stable
    sort of ``keys`` and a binary search each (time O((K + k) log K))."""
    if not len(keys):
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    order = np.argsort(keys, kind="stable")
    ordered = keys[order]
    at = np.minimum(np.searchsorted(ordered, wanted), len(keys) - 1)
    found = np.flatnonzero(ordered[at] == wanted)
    return found, order[at[found]]


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


def fold_from_roots(parent: np.ndarray, local_of: Callable[[np.ndarray], np.ndarray],
                    levels: tuple[np.ndarray, np.ndarray] | None,
                    combine: Callable[[np.ndarray, np.ndarray], np.ndarray],
                    out: np.ndarray) -> np.ndarray:
    """Root-to-node folds ``A[v] = combine(A[parent[v]], local[v])`` of an associative
    ``combine`` (``np.matmul``, ``np.add``), written into ``out`` (k, ...).

    On shallow forests the nodes are taken in breadth-first order, where every depth is a
    contiguous slice whose parents lie in the slice before (no scattered writes per
    level; one scatter into ``out`` at the end); deep forests use pointer doubling.

    Args:
        parent: (k,) int64 forest parents (roots point to themselves).
        local_of: ``local_of(nodes)`` gives the (len(nodes), ...) float64 per-node
            transforms of ``nodes`` (k,), in that order (roots: the identity of
            ``combine``); called once.
        levels: ``(order, bounds)`` of :func:`forest_levels`, or None.
        combine: the associative operation.
        out: (k, ...) float64 array the folds are written into.

    Returns:
        ``out``.
    """
    order, bounds = forest_levels(parent) if levels is None else levels
    if _by_levels(parent, len(bounds) - 2):
        acc = local_of(order)
        position = np.empty(len(order), dtype=np.int64)
        position[order] = np.arange(len(order))
        parent_position = position[np.asarray(parent)[order]]
        del position
        for d in range(1, len(bounds) - 1):
            level = slice(int(bounds[d]), int(bounds[d + 1]))
            acc[level] = combine(np.take(acc, parent_position[level], axis=0), acc[level])
        out[order] = acc
        return out
    acc = local_of(np.arange(len(parent)))
    anc = np.asarray(parent, dtype=np.int64).copy()
    while not np.array_equal(anc[anc], anc):
        acc = combine(acc[anc], acc)
        anc = anc[anc]
    out[...] = acc
    return out


def _accumulate(parent: np.ndarray, local: np.ndarray,
                levels: tuple[np.ndarray, np.ndarray] | None,
                combine: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> np.ndarray:
    """:func:`fold_from_roots` of the per-node transforms ``local`` (k, ...) float64."""
    return fold_from_roots(parent, lambda nodes: np.take(local, nodes, axis=0), levels,
                           combine, np.empty_like(local))


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
