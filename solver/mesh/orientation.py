"""Faces flipped against their neighbours turned back: a consistent orientation of every
orientable part of a mesh (files written with some faces the wrong way round: CGAL's
``cube4-shuffled.off`` and ``tet-shuffled.off``, STL exports, hand-stitched patches).

The rule (vectorized, deterministic):

1. Two faces that share an edge of exactly two faces are **consistent** when they run it
   opposite ways and **inconsistent** when they run it the same way; edges of one face or of
   three and more (non-manifold: :mod:`solver.mesh.manifold` pairs those) join nothing here.
2. The faces joined across such edges form parts. In each part a breadth-first spanning
   forest (:func:`solver.mesh.trees.spanning_forest`, from the part's lowest face) gives
   every face a parity, the number of inconsistent links on its path to the root, mod 2.
3. A part is **orientable** when every one of its links, tree or not, agrees with the
   parities (an inconsistent link between faces of different parity, a consistent one
   between faces of the same parity). A non-orientable part (a Möbius strip) is left as it
   is: :func:`solver.mesh.manifold.cut_to_manifold` cuts it where its faces disagree.
4. In an orientable part the faces of the parity held by fewer faces are flipped (the
   majority's orientation is kept; a tie keeps the lowest face's). A flipped face
   ``(a, b, c)`` becomes ``(a, c, b)``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from .trees import accumulate_sums, spanning_forest


def orientation_flips(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Which faces to flip for a consistent orientation of every orientable part (module
    docstring: the rule).

    Args:
        faces: (m, 3) int64 triangles, indices below ``n_vertices``, no repeated index.
        n_vertices: n.

    Returns:
        (m,) bool, True for the faces to flip (all False when the mesh is consistent).

    Example:
        A square of two triangles, the second written the wrong way round:

        >>> import numpy as np
        >>> orientation_flips(np.array([[0, 1, 2], [0, 3, 2]]), 4).tolist()
        [False, True]
    """
    F = np.asarray(faces, dtype=np.int64)
    m = len(F)
    if m == 0:
        return np.zeros(0, dtype=bool)
    links, inconsistent = _face_links(F, n_vertices)
    if not inconsistent.any():
        return np.zeros(m, dtype=bool)
    graph = sp.coo_matrix((np.ones(len(links)), (links[:, 0], links[:, 1])), shape=(m, m))
    part = connected_components(graph, directed=False)[1].astype(np.int64)
    forest = spanning_forest(m, links, components=part)
    step = np.zeros(m, dtype=np.float64)
    child = np.flatnonzero(forest.parent_link >= 0)
    step[child] = inconsistent[forest.parent_link[child]]
    parity = (accumulate_sums(forest.parent, step, forest.levels).round().astype(np.int64)
              & 1).astype(bool)
    disagree = (parity[links[:, 0]] != parity[links[:, 1]]) != inconsistent
    broken = np.zeros(m, dtype=bool)
    broken[part[links[disagree, 0]]] = True  # a part with a disagreeing link: not orientable
    flipped = np.bincount(part, weights=parity, minlength=m)
    size = np.bincount(part, minlength=m)
    minority = np.where(2 * flipped[part] > size[part], ~parity, parity)  # the smaller flips
    return minority & ~broken[part]


def _face_links(F: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The pairs of faces across edges of exactly two faces, and whether each pair runs its
    edge the same way.

    Returns:
        ``(links, inconsistent)``: (L, 2) int64 face pairs and (L,) bool.
    """
    origin, dest = F.ravel(), F[:, [1, 2, 0]].ravel()
    key = np.minimum(origin, dest) * n + np.maximum(origin, dest)
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    starts = np.flatnonzero(np.r_[True, sorted_key[1:] != sorted_key[:-1]])
    counts = np.diff(np.r_[starts, len(key)])
    pairs = starts[counts == 2]
    first, second = order[pairs], order[pairs + 1]
    links = np.stack([first // 3, second // 3], axis=1)
    return links, origin[first] == origin[second]
