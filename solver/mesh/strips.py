"""Triangle strips (PLY's ``tristrips`` element, glTF's mode-5 primitives:
:func:`solver.mesh.gltf_documents.triangle_lists`) unrolled into triangles.

A strip ``s0 s1 s2 s3 ...`` holds the triangles ``(s0, s1, s2)``, ``(s2, s1, s3)``,
``(s2, s3, s4)``, ... : every second triangle is flipped so that all keep the strip's
orientation. ``-1`` ends a strip and starts the next. Triangles that repeat an index are the
strips' joins (a strip turning a corner, or two strips stitched into one), not faces, and are
dropped.

Example:
    >>> import numpy as np
    >>> triangles, strip = strip_triangles(np.array([0, 1, 2, 3, -1, 4, 5, 6, 6, 7]))
    >>> triangles.tolist(), strip.tolist()
    ([[0, 1, 2], [2, 1, 3], [4, 5, 6]], [0, 0, 1])
"""

from __future__ import annotations

import numpy as np


def strip_triangles(indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The triangles of a strip list, in order.

    Args:
        indices: (L,) int the strips' vertex indices, each strip ended by ``-1`` (the last
            one may end without it).

    Returns:
        triangles: (t, 3) int64, every second triangle of a strip flipped; triangles with a
            repeated index dropped.
        strip: (t,) int64 the strip (0-based) each triangle comes from.
    """
    idx = np.asarray(indices, dtype=np.int64).ravel()
    if len(idx) < 3:
        return np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.int64)
    restart = idx < 0
    positions = np.arange(len(idx))
    # start of the strip each position belongs to: one past the last restart before it
    last_restart = np.maximum.accumulate(np.where(restart, positions, -1))
    start = last_restart + 1
    strip_of = np.cumsum(restart) - restart
    first = positions[:-2]
    a, b, c = idx[first], idx[first + 1], idx[first + 2]
    inside = (a >= 0) & (b >= 0) & (c >= 0)
    odd = ((first - start[first]) % 2).astype(bool)
    triangles = np.stack([np.where(odd, b, a), np.where(odd, a, b), c], axis=1)
    keep = inside & (a != b) & (b != c) & (a != c)
    return triangles[keep], strip_of[first][keep].astype(np.int64)


__all__ = ["strip_triangles"]
