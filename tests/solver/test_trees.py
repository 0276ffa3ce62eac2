"""Spanning forests and the products and sums along them, against a plain walk from the roots."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from solver.mesh.trees import accumulate_products, accumulate_sums, forest_levels, spanning_forest


def _graph(kind: str, k: int, rng: np.random.Generator) -> tuple[int, np.ndarray]:
    if kind == "path":                       # one long chain: the pointer-doubling branch
        return k, np.stack([np.arange(k - 1), np.arange(1, k)], 1)
    if kind == "grid":                       # shallow: the level-by-level branch
        s = int(np.sqrt(k))
        idx = np.arange(s * s).reshape(s, s)
        return s * s, np.concatenate([np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], 1),
                                      np.stack([idx[:-1].ravel(), idx[1:].ravel()], 1)])
    return k, rng.integers(0, k, size=(k, 2))  # random: several components, parallel links


def _depths(parent: np.ndarray) -> np.ndarray:
    """Depth of each node by walking up to its root (plain Python, the reference)."""
    out = np.zeros(len(parent), dtype=np.int64)
    for v in range(len(parent)):
        u = v
        while parent[u] != u:
            u = parent[u]
            out[v] += 1
    return out


@pytest.mark.parametrize(("kind", "k"), [("path", 3000), ("grid", 4900), ("random", 2000),
                                         ("random", 1)])
def test_products_and_sums_follow_the_forest(kind: str, k: int) -> None:
    rng = np.random.default_rng(k)
    n, links = _graph(kind, k, rng)
    forest = spanning_forest(n, links)
    parent = forest.parent
    roots = parent == np.arange(n)
    local = Rotation.random(n, random_state=3).as_matrix()
    local[roots] = np.eye(3)
    steps = rng.normal(size=(n, 3))
    steps[roots] = 0.0
    depth = _depths(parent)
    # Reference: nodes in order of depth, each from its (already done) parent.
    want_g, want_s = local.copy(), steps.copy()
    for v in np.argsort(depth, kind="stable"):
        if not roots[v]:
            want_g[v] = want_g[parent[v]] @ local[v]
            want_s[v] = want_s[parent[v]] + steps[v]
    for levels in (None, forest.levels):
        np.testing.assert_allclose(accumulate_products(parent, local, levels), want_g,
                                   atol=1e-12)
        np.testing.assert_allclose(accumulate_sums(parent, steps, levels), want_s, atol=1e-12)
    for order, bounds in (forest_levels(parent), forest.levels):
        assert sorted(order.tolist()) == list(range(n))
        got = np.empty(n, dtype=np.int64)
        got[order] = np.repeat(np.arange(len(bounds) - 1), np.diff(bounds))
        np.testing.assert_array_equal(got, depth)


@pytest.mark.parametrize(("kind", "k"), [("grid", 4900), ("random", 2000), ("path", 500)])
def test_known_components_give_the_same_forest(kind: str, k: int) -> None:
    """The components a caller knows (a mesh's) replace the search for them: same forest."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rng = np.random.default_rng(k)
    n, links = _graph(kind, k, rng)
    graph = coo_matrix((np.ones(len(links)), (links[:, 0], links[:, 1])), shape=(n, n))
    components = connected_components(graph, directed=False)[1].astype(np.int64)
    roots = rng.integers(0, n, size=3)
    # None: searched; the same labels; other labels of the same partition (reversed).
    for given in (None, components, components.max() - components):
        forest = spanning_forest(n, links, roots=roots, components=given)
        reference = spanning_forest(n, links, roots=roots)
        np.testing.assert_array_equal(forest.parent, reference.parent)
        np.testing.assert_array_equal(forest.in_tree, reference.in_tree)
        # each node's parent link joins it to its parent
        nodes = np.flatnonzero(forest.parent_link >= 0)
        pair = np.sort(links[forest.parent_link[nodes]], axis=1)
        np.testing.assert_array_equal(pair, np.sort(np.stack([nodes, forest.parent[nodes]], 1),
                                                    axis=1))


@pytest.mark.parametrize("hub_first", [True, False])
def test_hub_rows_give_each_node_a_link_to_its_parent(hub_first: bool) -> None:
    """A virtual vertex joined to every boundary vertex (a mesh whose non-manifold cuts
    leave most vertices on a boundary: libigl's cube_40k.obj, 56K such links) makes one row
    of the link matrix as long as the boundary; its links are searched, not probed (a
    probe of that row took time quadratic in its length: over 20 minutes there). Truth:
    each non-root's parent link joins it to its parent, and the tree has one link per
    non-root."""
    rng = np.random.default_rng(7)
    n, grid = _graph("grid", 4900, rng)
    hub = n
    boundary = rng.choice(n, size=3000, replace=False)
    virtual = (np.stack([np.full(len(boundary), hub), boundary], 1) if hub_first
               else np.stack([boundary, np.full(len(boundary), hub)], 1))
    links = np.concatenate([grid, virtual, grid[:50, ::-1]])  # some parallel links too
    cases = [(links, np.array([hub])), (links[len(grid) // 2:], None)]  # one, several parts
    for pairs, roots in cases:
        forest = spanning_forest(n + 1, pairs, roots=roots)
        parent, link = forest.parent, forest.parent_link
        is_root = parent == np.arange(n + 1)
        nodes = np.flatnonzero(~is_root)
        assert (link[nodes] >= 0).all() and (link[is_root] == -1).all()
        joined = np.sort(pairs[link[nodes]], axis=1)
        np.testing.assert_array_equal(joined, np.sort(np.stack([nodes, parent[nodes]], 1), 1))
        assert forest.in_tree.sum() == len(nodes)
