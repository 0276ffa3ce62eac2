"""Levenberg-Marquardt's damping of the Gauss-Newton matrix: :func:`damped`.

Example:
    >>> import numpy as np, scipy.sparse as sp
    >>> H = sp.csr_array(np.diag([1.0, 4.0]))
    >>> damped(H, 0.5, np.array([0, 1]), np.array([], dtype=np.int64)).toarray().diagonal()
    array([1.5, 6. ])
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def damped(H: sp.csr_array, damping: float, diagonal_positions: np.ndarray,
           needle_coordinates: np.ndarray) -> sp.csr_array:
    """``H + damping D + floor I``: Levenberg-Marquardt with Marquardt's scaling.

    ``D`` is the diagonal of H floored at ``floor``, 1e-9 of its median, which is also
    added, so that the sum is definite. At the coordinates of needle edges' vertices
    (:attr:`solver.refine.form_energy.FormEnergy.needle_vertices`) ``D`` is capped at the median
    diagonal: their diagonal is that of the needle's relative length, ~1e8 times the
    others' on an edge 1e-4 of the mean long, and stiff along the needle only, so scaling by
    it would hold the vertices' other directions back (docs/refinement.md). Flattened faces
    keep the full scaling: their vertices' large diagonal is their angles', and a step that
    turns them over is what the damping must hold back.

    Args:
        H: (N, N) upper triangle of the Gauss-Newton matrix, canonical CSR.
        damping: the relative damping lambda.
        diagonal_positions: (N,) int, where the diagonal sits in ``H.data``.
        needle_coordinates: int, the coordinates (vertex * dim + axis) of needle vertices.

    Returns:
        (N, N) CSR in ``H``'s pattern.
    """
    diag = H.data[diagonal_positions]
    median = float(np.median(diag))
    floor = 1e-9 * median
    scale = np.maximum(diag, floor)
    scale[needle_coordinates] = np.minimum(scale[needle_coordinates], median)
    values = H.data.copy()
    values[diagonal_positions] += damping * scale + floor
    out = sp.csr_array((values, H.indices, H.indptr), shape=H.shape)
    out.has_canonical_format = True
    return out
