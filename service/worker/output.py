"""Response bodies: JSON via orjson and meshes via the library's glTF writer
(:mod:`solver.mesh.gltf`).

Used in the worker processes (synchronous requests are encoded where they are solved) and in
the main process (job results fetched later with another ``Accept`` or ``?color=``).
"""

from __future__ import annotations

from typing import Any, Final

import numpy as np
import orjson

from ffs_wire.arrays import json_default
from solver.mesh import gltf

MEDIA_TYPES: Final[dict[str, str]] = {"json": "application/json", "glb": "model/gltf-binary",
                                      "gltf": "model/gltf+json",
                                      "f32": "application/octet-stream"}
"""Response format -> media type (``f32``: little-endian float32 vertices, sessions only)."""

_OPTIONS = orjson.OPT_SERIALIZE_NUMPY | orjson.OPT_NON_STR_KEYS


def json_bytes(document: Any) -> bytes:
    """A JSON response body.

    Args:
        document: JSON-able values, numpy arrays and scalars, objects with ``to_dict()``.

    Returns:
        UTF-8 JSON by orjson (numpy arrays natively; non-contiguous or exotic ones, and
        what orjson cannot encode, through :func:`ffs_wire.arrays.json_default`).
    """
    return orjson.dumps(document, option=_OPTIONS, default=json_default)


def colors_for(values: np.ndarray | None) -> np.ndarray | None:
    """The colour ramp of per-vertex scalars.

    Args:
        values: (n,) float per-vertex scalars, or None.

    Returns:
        (n, 4) float32 linear RGBA (:func:`solver.mesh.gltf.color_ramp`); None for None.
    """
    return None if values is None else gltf.color_ramp(np.asarray(values, dtype=np.float64))


def with_colors(body: bytes, colors: np.ndarray) -> bytes:
    """Add ``"colors": [[r, g, b, a], ...]`` to an encoded JSON object without re-encoding it.

    Args:
        body: An encoded JSON object (``{...}``).
        colors: (n, 4) float32 RGBA.

    Returns:
        ``body`` with a last ``"colors"`` member.

    Raises:
        ValueError: ``body`` is not a JSON object.
    """
    if not body.endswith(b"}"):
        raise ValueError("not a JSON object")
    separator = b"," if body != b"{}" else b""
    return body[:-1] + separator + b'"colors":' + json_bytes(colors) + b"}"


def mesh_bytes(fmt: str, vertices: np.ndarray, faces: np.ndarray,
               values: np.ndarray | None = None, texcoords: np.ndarray | None = None,
               warnings: list[dict[str, Any]] | None = None) -> bytes:
    """A mesh response body.

    Args:
        fmt: ``glb`` or ``gltf``.
        vertices: (n, 3) float64.
        faces: (m, 3) int.
        values: (n,) float per-vertex scalars drawn as a colour ramp, or None.
        texcoords: (n, 2) float uv written as ``TEXCOORD_0``, or None.
        warnings: the answer's warnings (``report.warnings``), written as the asset's
            ``extras.warnings`` when there are any.

    Returns:
        The glTF 2.0 asset (:func:`solver.mesh.gltf.encode_gltf`).

    Raises:
        ValueError: ``fmt`` is neither ``glb`` nor ``gltf``.
    """
    return gltf.encode_gltf(vertices, faces, colors_for(values), kind=fmt,  # type: ignore[arg-type]
                            texcoords=texcoords,
                            extras={"warnings": warnings} if warnings else None)
