"""Array coercion and checks shared by every public entry point.

Each helper turns caller input into a contiguous numpy array of the documented dtype and
raises a typed :mod:`solver.errors` exception that names the first offending row.
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
    try:
        return np.ascontiguousarray(np.asarray(values, dtype=dtype))
    except (TypeError, ValueError) as exc:
        raise ShapeMismatchError(f"cannot be read as a {np.dtype(dtype).name} array: {exc}",
                                 field=field) from exc


def as_points(values: ArrayLike, field: str = "vertices", dim: int = 3) -> np.ndarray:
    """Return ``values`` as a finite float64 array of shape (k, dim)."""
    points = _as_array(values, field, np.float64)
    if points.ndim == 1 and points.size == 0:
        points = points.reshape(0, dim)
    if points.ndim != 2 or points.shape[1] != dim:
        raise ShapeMismatchError(f"expected shape (k, {dim}), got {points.shape}", field=field)
    require_finite(points, field)
    return points


def as_vector(values: ArrayLike, field: str, size: int | None = None) -> np.ndarray:
    """Return ``values`` as a finite float64 array of shape (size,)."""
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
    """Return ``values`` as int64 of shape (k,) or (k, width), entries in [0, upper)."""
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
    """Return faces as int64 (m, 3), checking index range and repeated corners."""
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
    """Raise :class:`NonFiniteValueError` naming the first row with a NaN or infinity."""
    finite = np.isfinite(values)
    if not finite.all():
        rows = finite.reshape(len(values), -1).all(axis=1) if values.ndim else finite
        row = int(np.flatnonzero(~rows)[0])
        raise NonFiniteValueError("value is NaN or infinite", field=field, index=row)


def require_unique(indices: np.ndarray, field: str, what: str) -> None:
    """Raise ConstraintError naming the second occurrence of a repeated index."""
    from .errors import ConstraintError

    values, counts = np.unique(indices, return_counts=True)
    if (counts > 1).any():
        dup = int(values[counts > 1][0])
        raise ConstraintError(f"{what} {dup} is given more than once", field=field,
                              index=int(np.flatnonzero(indices == dup)[1]))
