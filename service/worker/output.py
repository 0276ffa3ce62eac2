"""Response bodies: JSON via orjson and meshes via :mod:`service.worker.gltf`.

Used in the worker processes (synchronous requests are encoded where they are solved) and in
the main process (job results fetched later with another ``Accept`` or ``?color=``).
"""

from __future__ import annotations

from typing import Any, Final

import numpy as np
import orjson

from service.worker.gltf import color_ramp, encode_gltf_binary, encode_gltf_json

MEDIA_TYPES: Final[dict[str, str]] = {
    "json": "application/json",
    "glb": "model/gltf-binary",
    "gltf": "model/gltf+json",
    "f32": "application/octet-stream",
}
"""Response format -> media type (``f32``: little-endian float32 vertices, sessions only)."""

_OPTIONS = orjson.OPT_SERIALIZE_NUMPY | orjson.OPT_NON_STR_KEYS


def _default(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if hasattr(value, "to_dict"):
        return value.to_dict()
    if isinstance(value, set | frozenset | tuple):
        return list(value)
    raise TypeError(f"{type(value).__name__} is not JSON serializable")


def json_bytes(document: Any) -> bytes:
    """orjson with numpy support; non-contiguous or exotic arrays fall back to lists."""
    return orjson.dumps(document, option=_OPTIONS, default=_default)


def colors_for(values: np.ndarray | None) -> np.ndarray | None:
    """(n, 4) float32 linear RGBA colour ramp of per-vertex scalars (None passes through)."""
    return None if values is None else color_ramp(np.asarray(values, dtype=np.float64))


def with_colors(body: bytes, colors: np.ndarray) -> bytes:
    """Add ``"colors": [[r, g, b, a], ...]`` to an encoded JSON object without re-encoding it."""
    if not body.endswith(b"}"):
        raise ValueError("not a JSON object")
    separator = b"," if body != b"{}" else b""
    return body[:-1] + separator + b'"colors":' + json_bytes(colors) + b"}"


def mesh_bytes(fmt: str, vertices: np.ndarray, faces: np.ndarray,
               values: np.ndarray | None = None) -> bytes:
    """Encode a mesh as ``glb`` or ``gltf`` with an optional colour ramp of ``values``."""
    colors = colors_for(values)
    if fmt == "glb":
        return encode_gltf_binary(vertices, faces, colors)
    if fmt == "gltf":
        return encode_gltf_json(vertices, faces, colors)
    raise ValueError(f"unknown mesh format {fmt!r}")
