"""Array coercion and checks shared by every public entry point.

Each helper turns caller input into a contiguous numpy array of the documented dtype and
raises a typed :mod:`solver.core.errors` exception that names the first offending row.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from .errors import (
    DegenerateFaceError,
    IndexOutOfRangeError,
    NonFiniteValueError,
    ShapeMismatchError,
)


def _as_array(values: ArrayLike, field: str, dtype: type) -> np.ndarray:
    """``values`` as a contiguous array of ``dtype``; ShapeMismatchError if it cannot be."""
    try:
        return np.ascontiguousarray(np.asarray(values, dtype=dtype))
    except (TypeError, ValueError) as exc:
        raise ShapeMismatchError(f"cannot be read as a {np.dtype(dtype).name} array: {exc}",
                                 field=field) from exc


def as_points(values: ArrayLike, field: str = "vertices", dim: int = 3) -> np.ndarray:
    """Read points.

    Args:
        values: (k, dim) numbers (an empty sequence gives (0, dim)).
        field: the name errors give for ``values``.
        dim: coordinates per point.

    Returns:
        (k, dim) float64, contiguous.

    Raises:
        ShapeMismatchError: not numbers, or not of shape (k, dim).
        NonFiniteValueError: naming the first row with a NaN or infinity.

    Example:
        >>> from solver.core.validation import as_points
        >>> as_points([[0, 0, 1]]).dtype, as_points([]).shape
        (dtype('float64'), (0, 3))
        >>> as_points([[0, 0]], field="positions")
        Traceback (most recent call last):
        ...
        solver.core.errors.ShapeMismatchError: ...expected shape (k, 3), got (1, 2)
    """
    points = _as_array(values, field, np.float64)
    if points.ndim == 1 and points.size == 0:
        points = points.reshape(0, dim)
    if points.ndim != 2 or points.shape[1] != dim:
        raise ShapeMismatchError(f"expected shape (k, {dim}), got {points.shape}", field=field)
    require_finite(points, field)
    return points


def as_vector(values: ArrayLike, field: str, size: int | None = None) -> np.ndarray:
    """Read a vector.

    Args:
        values: (size,) numbers.
        field: the name errors give for ``values``.
        size: the required length (one per edge), or None for any.

    Returns:
        (size,) float64, contiguous.

    Raises:
        ShapeMismatchError: not numbers, not 1-D or not ``size`` long.
        NonFiniteValueError: naming the first NaN or infinity.
    """
    vector = _as_array(values, field, np.float64)
    if vector.ndim != 1:
        raise ShapeMismatchError(f"expected a 1-D array, got shape {vector.shape}", field=field)
    if size is not None and vector.shape[0] != size:
        raise ShapeMismatchError(f"expected {size} values (one per edge), got {vector.shape[0]}",
                                 field=field)
    require_finite(vector, field)
    return vector


def as_indices(values: ArrayLike, field: str, upper: int | None = None,
               width: int | None = None) -> np.ndarray:
    """Read indices.

    Args:
        values: (k,) or (k, width) integers (floats with integral values are accepted).
        field: the name errors give for ``values``.
        upper: exclusive upper bound of the entries, or None for any non-negative one.
        width: columns per row, or None for a 1-D array.

    Returns:
        (k,) or (k, width) int64.

    Raises:
        ShapeMismatchError: not integers or of the wrong shape.
        NonFiniteValueError: a NaN or infinite index.
        IndexOutOfRangeError: naming the first row with an entry outside [0, upper).
    """
    raw = np.asarray(values)
    if raw.size and raw.dtype.kind == "f":
        if not np.all(np.isfinite(raw)):
            bad = int(np.flatnonzero(~np.isfinite(raw).reshape(len(raw), -1).all(axis=1))[0])
            raise NonFiniteValueError("index is not a finite number", field=field, index=bad)
        if np.any(raw != np.round(raw)):
            flat = (raw != np.round(raw)).reshape(len(raw), -1).any(axis=1)
            raise ShapeMismatchError("index is not an integer", field=field,
                                     index=int(np.flatnonzero(flat)[0]))
    if raw.size and raw.dtype.kind not in "iuf":
        raise ShapeMismatchError(f"indices must be integers, got dtype {raw.dtype}", field=field)
    idx = _as_array(raw, field, np.int64)
    if width is not None:
        if idx.ndim == 1 and idx.size == 0:
            idx = idx.reshape(0, width)
        if idx.ndim != 2 or idx.shape[1] != width:
            raise ShapeMismatchError(f"expected shape (k, {width}), got {idx.shape}", field=field)
    elif idx.ndim != 1:
        raise ShapeMismatchError(f"expected a 1-D array, got shape {idx.shape}", field=field)
    if idx.size:
        rows = idx.reshape(len(idx), -1)
        bad = (rows < 0).any(axis=1)
        if upper is not None:
            bad |= (rows >= upper).any(axis=1)
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            out = (rows[row] < 0) | ((rows[row] >= upper) if upper is not None else False)
            value = int(rows[row][out][0])
            limit = f"[0, {upper})" if upper is not None else ">= 0"
            raise IndexOutOfRangeError(f"index {value} out of range {limit}", field=field,
                                       index=row, details={"value": value})
    return idx


def as_faces(faces: ArrayLike, n_vertices: int | None = None) -> np.ndarray:
    """Read faces.

    Args:
        faces: (m, 3) vertex indices, m >= 1.
        n_vertices: vertex count (exclusive bound of the indices), or None.

    Returns:
        (m, 3) int64.

    Raises:
        ShapeMismatchError: not (m, 3) integers, or no faces.
        IndexOutOfRangeError: an index outside [0, n_vertices).
        DegenerateFaceError: a face that repeats a vertex.
    """
    F = as_indices(faces, "faces", upper=n_vertices, width=3)
    if len(F) == 0:
        raise ShapeMismatchError("the mesh has no faces", field="faces")
    repeated = (F[:, 0] == F[:, 1]) | (F[:, 1] == F[:, 2]) | (F[:, 2] == F[:, 0])
    if repeated.any():
        t = int(np.flatnonzero(repeated)[0])
        raise DegenerateFaceError(f"face {F[t].tolist()} repeats a vertex index",
                                  field="faces", index=t)
    return F


def require_finite(values: np.ndarray, field: str) -> None:
    """Refuse NaN and infinite values.

    Args:
        values: array whose first axis is rows.
        field: the name the error gives for ``values``.

    Raises:
        NonFiniteValueError: naming the first row with a NaN or infinity.
    """
    finite = np.isfinite(values)
    if not finite.all():
        rows = finite.reshape(len(values), -1).all(axis=1) if values.ndim else finite
        row = int(np.flatnonzero(~rows)[0])
        raise NonFiniteValueError("value is NaN or infinite", field=field, index=row)


def require_unique(indices: np.ndarray, field: str, what: str) -> None:
    """Refuse repeated indices.

    Args:
        indices: (k,) int64.
        field: the name the error gives for ``indices``.
        what: what an index stands for in the message (``"vertex"``, ``"face"``).

    Raises:
        ConstraintError: naming the second occurrence of a repeated index.
    """
    from .errors import ConstraintError

    values, counts = np.unique(indices, return_counts=True)
    if (counts > 1).any():
        dup = int(values[counts > 1][0])
        raise ConstraintError(f"{what} {dup} is given more than once", field=field,
                              index=int(np.flatnonzero(indices == dup)[1]))
