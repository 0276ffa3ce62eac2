"""The ``application/vnd.ffs.arrays`` request body: the JSON body with its large arrays as
raw little-endian bytes (docs/service.md, "Binary bodies"). Pure numpy + the standard
library, so that the client (which must not need FastAPI) and the service share one
encoder::

    b"FFSA" | uint32 LE header length H | H bytes of UTF-8 JSON header | zero padding to a
    multiple of 8 | each array's bytes (C order), each padded to a multiple of 8

The header is the JSON body without its large arrays, plus ``"arrays": {name: {"dtype",
"shape"}}`` in the order the arrays follow. dtypes: ``<f8`` ``<f4`` (reals), ``<i4`` ``<i8``
``<u4`` (indices). The service's reader with its checks is
:func:`service.api.decoding.parse_binary`.

:func:`json_default` (numpy values in JSON) serves the JSON header here and every other JSON
the client, the command line and the service write.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any, Final

import numpy as np

BINARY_MEDIA_TYPE: Final = "application/vnd.ffs.arrays"
"""Media type of a binary body."""
BINARY_MAGIC: Final = b"FFSA"
"""The first four bytes of a binary body."""
BINARY_DTYPES: Final[dict[str, type]] = {"<f8": np.float64, "<f4": np.float32,
                                         "<i4": np.int32, "<i8": np.int64, "<u4": np.uint32}
"""dtype strings a binary body may declare -> numpy types."""


def padded(n: int) -> int:
    """``n`` rounded up to a multiple of 8 (every part of a binary body is 8-aligned)."""
    return -(-n // 8) * 8


def json_default(value: Any) -> Any:
    """The ``default`` of ``json.dumps`` and ``orjson.dumps`` for every JSON this project
    writes (request bodies, the command line's files and reports, the service's responses).

    Args:
        value: What the encoder cannot encode itself.

    Returns:
        numpy arrays as lists, numpy scalars as Python numbers, an object with
        ``to_dict()`` as that dict, sets and tuples as lists.

    Raises:
        TypeError: Anything else (what ``default`` must raise).

    Example:
        >>> json.dumps({"lengths": np.array([1.5, 2.0]), "n": np.int64(3)}, default=json_default)
        '{"lengths": [1.5, 2.0], "n": 3}'
    """
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if hasattr(value, "to_dict"):
        return value.to_dict()
    if isinstance(value, set | frozenset | tuple):
        return list(value)
    raise TypeError(f"{type(value).__name__} is not JSON serializable")


def _finite_or_none(value: Any) -> Any:
    """``value`` with every non-finite float replaced by ``None`` (what orjson writes for
    them, so that the service's schema check names the element instead of refusing the
    whole header as invalid JSON)."""
    if isinstance(value, float | np.floating):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, np.ndarray):
        return _finite_or_none(value.tolist())
    if isinstance(value, Mapping):
        return {key: _finite_or_none(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [_finite_or_none(item) for item in value]
    return value


def _header_json(header: Mapping[str, Any]) -> bytes:
    """Compact UTF-8 JSON of a header (numpy values allowed; non-finite floats as null)."""
    try:
        text = json.dumps(header, separators=(",", ":"), ensure_ascii=False,
                          allow_nan=False, default=json_default)
    except ValueError:
        text = json.dumps(_finite_or_none(header), separators=(",", ":"), ensure_ascii=False,
                          default=json_default)
    return text.encode()


def binary_body(params: Mapping[str, Any], arrays: Mapping[str, Any]) -> bytes:
    """A :data:`BINARY_MEDIA_TYPE` body: ``params`` are the JSON body's other fields (numpy
    values allowed), ``arrays`` its large arrays, cast to ``<i4`` when integer or boolean
    and to ``<f8`` otherwise (values are not checked here: the service names bad ones)."""
    parts, meta = [], {}
    for name, value in arrays.items():
        array = np.asarray(value)
        array = array.astype("<i4" if array.dtype.kind in "iub" else "<f8", copy=False)
        meta[name] = {"dtype": array.dtype.str, "shape": list(array.shape)}
        raw = np.ascontiguousarray(array).tobytes()
        parts.append(raw + b"\0" * (padded(len(raw)) - len(raw)))
    header = _header_json({**params, "arrays": meta})
    head = BINARY_MAGIC + len(header).to_bytes(4, "little") + header
    return head + b"\0" * (padded(len(head)) - len(head)) + b"".join(parts)
