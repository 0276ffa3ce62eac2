"""The one glTF 2.0 writer: triangle meshes as binary ``.glb`` or JSON ``.gltf`` (the
buffer embedded as a ``data:`` URI), optionally with vertex colours, the atlas as
``TEXCOORD_0``, or a sequence of shapes as morph targets with an animation.

Used by the library's file writing (:func:`solver.mesh.io.save_mesh`, :mod:`solver.mesh.uv_files`),
the service's response encoders (``service/worker/output.py``) and ``ffs``. Pure numpy +
stdlib (validator-clean: the tests run the Khronos glTF-Validator). Every array operation is
vectorized (no Python loops over vertices or faces).

Layout of the produced asset (both encodings carry the same JSON and the same buffer):

* one scene -> one node -> one mesh -> one primitive, ``mode`` 4 (TRIANGLES);
* attributes ``POSITION`` (float32 VEC3, with accessor ``min``/``max``), ``NORMAL``
  (float32 VEC3, unit length, area-weighted) and optionally ``COLOR_0`` (float32 VEC4,
  *linear* RGBA in [0, 1] as the glTF spec requires for vertex colours);
* ``indices``: UNSIGNED_SHORT when ``n <= 65535`` (so the primitive-restart value 65535 never
  occurs), otherwise UNSIGNED_INT;
* one non-interleaved bufferView per accessor, each starting on a 4-byte boundary, with
  ``target`` 34962 (ARRAY_BUFFER) or 34963 (ELEMENT_ARRAY_BUFFER);
* one default material: ``pbrMetallicRoughness`` (white, non-metallic) and ``doubleSided``.

Vertex order and count are exactly the caller's: vertex ``i`` of the input is element ``i`` of
every vertex accessor, including vertices that no face references (a valid glTF; they simply
are not drawn). A mesh with no faces is written as a ``mode`` 0 (POINTS) primitive without
indices.
"""

from __future__ import annotations

import base64
import json
import struct
from collections.abc import Mapping
from typing import Any, Final, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..core.errors import IndexOutOfRangeError, NonFiniteValueError, ShapeMismatchError

__all__ = [
    "GENERATOR",
    "color_ramp",
    "encode_gltf",
    "encode_gltf_animation",
    "encode_gltf_binary",
    "encode_gltf_json",
    "vertex_normals",
]

GENERATOR: Final = "fundamental-forms-service"
"""``asset.generator`` written into every glTF."""

# glTF enums (glTF 2.0 spec, section 5): component types, bufferView targets, primitive modes.
_FLOAT, _UNSIGNED_SHORT, _UNSIGNED_INT = 5126, 5123, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_MODE_POINTS, _MODE_TRIANGLES = 0, 4

# GLB container (glTF 2.0 spec, section 4.4).
_GLB_MAGIC: Final = 0x46546C67  # "glTF"
_GLB_VERSION: Final = 2
_CHUNK_JSON: Final = 0x4E4F534A  # "JSON"
_CHUNK_BIN: Final = 0x004E4942  # "BIN\0"

_FALLBACK_NORMAL: Final = (0.0, 0.0, 1.0)
_NAN_COLOR: Final = (0.5, 0.5, 0.5, 1.0)

# Viridis (matplotlib's `viridis` colormap, CC0 licensed) sampled at 33 evenly spaced points,
# sRGB. Linear interpolation between them stays within 0.01 of the full 256-entry table.
_VIRIDIS_SRGB: Final = np.array([
    [0.267004, 0.004874, 0.329415],
    [0.277018, 0.050344, 0.375715],
    [0.282327, 0.094955, 0.417331],
    [0.282884, 0.135920, 0.453427],
    [0.278826, 0.175490, 0.483397],
    [0.270595, 0.214069, 0.507052],
    [0.258965, 0.251537, 0.524736],
    [0.244972, 0.287675, 0.537260],
    [0.229739, 0.322361, 0.545706],
    [0.214298, 0.355619, 0.551184],
    [0.199430, 0.387607, 0.554642],
    [0.185556, 0.418570, 0.556753],
    [0.172719, 0.448791, 0.557885],
    [0.160665, 0.478540, 0.558115],
    [0.149039, 0.508051, 0.557250],
    [0.137770, 0.537492, 0.554906],
    [0.127568, 0.566949, 0.550556],
    [0.120565, 0.596422, 0.543611],
    [0.120638, 0.625828, 0.533488],
    [0.132268, 0.655014, 0.519661],
    [0.157851, 0.683765, 0.501686],
    [0.196571, 0.711827, 0.479221],
    [0.246070, 0.738910, 0.452024],
    [0.304148, 0.764704, 0.419943],
    [0.369214, 0.788888, 0.382914],
    [0.440137, 0.811138, 0.340967],
    [0.515992, 0.831158, 0.294279],
    [0.595839, 0.848717, 0.243329],
    [0.678489, 0.863742, 0.189503],
    [0.762373, 0.876424, 0.137064],
    [0.845561, 0.887322, 0.099702],
    [0.926106, 0.897330, 0.104071],
    [0.993248, 0.906157, 0.143936],
], dtype=np.float64)
_VIRIDIS_SRGB.setflags(write=False)


def _srgb_to_linear(c: NDArray[np.float64]) -> NDArray[np.float64]:
    """sRGB transfer function inverse (IEC 61966-2-1), elementwise on values in [0, 1]."""
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def color_ramp(values: ArrayLike, vmin: float | None = None, vmax: float | None = None,
               *, linear: bool = True) -> NDArray[np.float32]:
    """Map scalars to RGBA colours with a perceptually uniform (viridis) ramp.

    Args:
        values: (n,) float, a scalar per vertex. NaN maps to opaque grey
            ``(0.5, 0.5, 0.5, 1)``; +-inf clamp to the ends of the ramp.
        vmin: Low end of the range mapped onto the ramp (values outside are clamped).
            Default: the min of the finite values.
        vmax: High end of that range. Default: the max of the finite values. A zero-width
            range maps every finite value to the ramp's midpoint.
        linear: Return linear-light RGB (default), which is what glTF ``COLOR_0`` expects;
            the ramp table is defined in sRGB, so viewers then display the intended viridis
            colours. ``False`` for sRGB values (e.g. for a PNG or CSS).

    Returns:
        (n, 4) float32 RGBA in [0, 1], alpha 1.

    Raises:
        solver.core.errors.ShapeMismatchError: ``values`` is not one-dimensional.

    Example:
        >>> rgba = color_ramp([0.0, 1.0, float("nan")], linear=False)
        >>> rgba[:, :3].astype(float).round(3).tolist()
        [[0.267, 0.005, 0.329], [0.993, 0.906, 0.144], [0.5, 0.5, 0.5]]
    """
    v = np.asarray(values, dtype=np.float64)
    if v.ndim != 1:
        raise ShapeMismatchError(f"expected shape (n,), got {v.shape}", field="values")
    finite = np.isfinite(v)
    lo = float(np.min(v[finite])) if vmin is None and finite.any() else vmin
    hi = float(np.max(v[finite])) if vmax is None and finite.any() else vmax
    lo = 0.0 if lo is None else float(lo)
    hi = 1.0 if hi is None else float(hi)
    span = hi - lo
    with np.errstate(invalid="ignore", over="ignore"):
        t = np.full_like(v, 0.5) if span == 0.0 else (v - lo) / span
    t = np.clip(np.where(np.isnan(v), 0.0, t), 0.0, 1.0)

    knots = np.linspace(0.0, 1.0, len(_VIRIDIS_SRGB))
    rgb = np.stack([np.interp(t, knots, _VIRIDIS_SRGB[:, k]) for k in range(3)], axis=1)
    if linear:
        rgb = _srgb_to_linear(rgb)
    out = np.ones((v.shape[0], 4), dtype=np.float32)
    out[:, :3] = rgb
    out[np.isnan(v)] = _NAN_COLOR
    return out


def vertex_normals(vertices: ArrayLike, faces: ArrayLike) -> NDArray[np.float32]:
    """Area-weighted unit vertex normals.

    Each face contributes its unnormalised normal ``(b - a) x (c - a)`` (twice its area times
    its unit normal) to its three vertices. Vertices whose sum is zero or not finite (no faces,
    only degenerate faces, or cancelling contributions) get ``(0, 0, 1)`` so every normal is a
    valid unit vector, as glTF requires.

    Args:
        vertices: (n, 3) float.
        faces: (m, 3) int, indices in ``[0, n)``.

    Returns:
        (n, 3) float32, unit length.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    n = v.shape[0]
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # (m, 3)
    idx = f.ravel()  # (3m,)
    contrib = np.repeat(fn, 3, axis=0)  # row 3j+k is face j's normal, for corner k
    acc = np.stack([np.bincount(idx, weights=contrib[:, k], minlength=n) for k in range(3)],
                   axis=1)
    norm = np.linalg.norm(acc, axis=1)
    ok = np.isfinite(norm) & (norm > 0.0)
    out = np.empty((n, 3), dtype=np.float64)
    out[ok] = acc[ok] / norm[ok, None]
    out[~ok] = _FALLBACK_NORMAL
    out32 = out.astype(np.float32)
    # Renormalise in float32 so |n| is 1 to float32 precision (the validator checks it).
    out32 /= np.linalg.norm(out32, axis=1, keepdims=True)
    return out32


def _check_inputs(vertices: ArrayLike, faces: ArrayLike, colors: ArrayLike | None
                  ) -> tuple[NDArray[np.float32], NDArray[np.int64], NDArray[np.float32] | None,
                             NDArray[np.float64]]:
    """Validate and convert: returns (positions f32, faces i64, colors f32 | None, vertices f64)."""
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
        raise ShapeMismatchError(f"expected shape (n, 3) with n >= 1, got {v.shape}",
                                 field="vertices")
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        raise NonFiniteValueError("non-finite coordinate", field="vertices",
                                  index=int(np.flatnonzero(bad)[0]))
    with np.errstate(over="ignore"):
        pos = v.astype(np.float32)
    bad = ~np.isfinite(pos).all(axis=1)
    if bad.any():
        raise NonFiniteValueError("coordinate overflows float32", field="vertices",
                                  index=int(np.flatnonzero(bad)[0]))

    f_raw = np.asarray(faces)
    if f_raw.size == 0:
        f_raw = f_raw.reshape(0, 3)
    if f_raw.ndim != 2 or f_raw.shape[1] != 3:
        raise ShapeMismatchError(f"expected shape (m, 3), got {f_raw.shape}", field="faces")
    if f_raw.size and not np.issubdtype(f_raw.dtype, np.integer):
        raise ShapeMismatchError(f"expected integer indices, got dtype {f_raw.dtype}",
                                 field="faces")
    f = f_raw.astype(np.int64, copy=False)
    bad = ((f < 0) | (f >= v.shape[0])).any(axis=1)
    if bad.any():
        raise IndexOutOfRangeError(f"vertex index outside [0, {v.shape[0]})", field="faces",
                                   index=int(np.flatnonzero(bad)[0]))

    c32: NDArray[np.float32] | None = None
    if colors is not None:
        c = np.asarray(colors, dtype=np.float64)
        if c.ndim != 2 or c.shape[0] != v.shape[0] or c.shape[1] not in (3, 4):
            raise ShapeMismatchError(
                f"expected shape ({v.shape[0]}, 4) or ({v.shape[0]}, 3), got {c.shape}",
                field="colors")
        bad = ~np.isfinite(c).all(axis=1)
        if bad.any():
            raise NonFiniteValueError("non-finite colour", field="colors",
                                      index=int(np.flatnonzero(bad)[0]))
        c32 = np.ones((v.shape[0], 4), dtype=np.float32)
        c32[:, : c.shape[1]] = np.clip(c, 0.0, 1.0)
    return pos, f, c32, v


class _BufferBuilder:
    """Accumulates one binary buffer plus its bufferViews/accessors (all 4-byte aligned)."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []
        self.length = 0
        self.buffer_views: list[dict[str, Any]] = []
        self.accessors: list[dict[str, Any]] = []

    def add(self, array: np.ndarray, *, component_type: int, type_: str, target: int,
            minmax: bool = False) -> int:
        """Append ``array`` (C-contiguous little-endian) as a new bufferView + accessor."""
        pad = (-self.length) % 4
        if pad:
            self.parts.append(b"\x00" * pad)
            self.length += pad
        data = np.ascontiguousarray(array).astype(array.dtype.newbyteorder("<"), copy=False)
        raw = data.tobytes()
        self.buffer_views.append({"buffer": 0, "byteOffset": self.length,
                                  "byteLength": len(raw), "target": target})
        accessor: dict[str, Any] = {
            "bufferView": len(self.buffer_views) - 1,
            "componentType": component_type,
            "count": int(data.shape[0]) if data.ndim > 1 else int(data.size),
            "type": type_,
        }
        if minmax:
            accessor["min"] = [float(x) for x in data.min(axis=0)]
            accessor["max"] = [float(x) for x in data.max(axis=0)]
        self.accessors.append(accessor)
        self.parts.append(raw)
        self.length += len(raw)
        return len(self.accessors) - 1

    def tobytes(self) -> bytes:
        """The buffer: every bufferView so far, in order."""
        return b"".join(self.parts)


def _build(vertices: ArrayLike, faces: ArrayLike, colors: ArrayLike | None, normals: bool,
           texcoords: ArrayLike | None = None) -> tuple[dict[str, Any], bytes]:
    """The glTF JSON document (without ``buffers[0].uri``) and the binary buffer."""
    pos, f, c32, v64 = _check_inputs(vertices, faces, colors)
    n, m = pos.shape[0], f.shape[0]
    buf = _BufferBuilder()
    attributes: dict[str, int] = {
        "POSITION": buf.add(pos, component_type=_FLOAT, type_="VEC3", target=_ARRAY_BUFFER,
                            minmax=True),
    }
    if normals:
        attributes["NORMAL"] = buf.add(vertex_normals(v64, f), component_type=_FLOAT,
                                       type_="VEC3", target=_ARRAY_BUFFER)
    if c32 is not None:
        attributes["COLOR_0"] = buf.add(c32, component_type=_FLOAT, type_="VEC4",
                                        target=_ARRAY_BUFFER)
    if texcoords is not None:
        attributes["TEXCOORD_0"] = buf.add(gltf_texcoords(texcoords, n),
                                           component_type=_FLOAT, type_="VEC2",
                                           target=_ARRAY_BUFFER)
    primitive: dict[str, Any] = {"attributes": attributes, "material": 0}
    if m > 0:
        if n <= 0xFFFF:  # max index n - 1 <= 65534: never the restart value 65535
            idx, ctype = f.astype(np.uint16).ravel(), _UNSIGNED_SHORT
        else:
            idx, ctype = f.astype(np.uint32).ravel(), _UNSIGNED_INT
        primitive["indices"] = buf.add(idx, component_type=ctype, type_="SCALAR",
                                       target=_ELEMENT_ARRAY_BUFFER)
        primitive["mode"] = _MODE_TRIANGLES
    else:
        primitive["mode"] = _MODE_POINTS
    binary = buf.tobytes()
    doc: dict[str, Any] = {
        "asset": {"version": "2.0", "generator": GENERATOR},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "mesh"}],
        "meshes": [{"name": "mesh", "primitives": [primitive]}],
        "materials": [{
            "name": "default",
            "pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0],
                                     "metallicFactor": 0.0, "roughnessFactor": 0.7},
            "doubleSided": True,
        }],
        "accessors": buf.accessors,
        "bufferViews": buf.buffer_views,
        "buffers": [{"byteLength": len(binary)}],
    }
    return doc, binary


def gltf_texcoords(texcoords: ArrayLike, n: int) -> NDArray[np.float32]:
    """(n, 2) float32 ``TEXCOORD_0`` from uv with v up (OBJ's, the library's): glTF's
    texture origin is the image's top-left corner, so v becomes 1 - v.

    Raises:
        solver.core.errors.ShapeMismatchError: not (n, 2); NonFiniteValueError: not finite.
    """
    t = np.asarray(texcoords, dtype=np.float64)
    if t.shape != (n, 2):
        raise ShapeMismatchError(f"expected shape ({n}, 2), got {t.shape}", field="texcoords")
    bad = ~np.isfinite(t).all(axis=1)
    if bad.any():
        raise NonFiniteValueError("non-finite texture coordinate", field="texcoords",
                                  index=int(np.flatnonzero(bad)[0]))
    return np.column_stack([t[:, 0], 1.0 - t[:, 1]]).astype(np.float32)


def _json_bytes(doc: dict[str, Any]) -> bytes:
    """Compact UTF-8 JSON of a glTF document (no NaN: the inputs were checked finite)."""
    return json.dumps(doc, separators=(",", ":"), allow_nan=False).encode("utf-8")


def _container(doc: dict[str, Any], binary: bytes, kind: str,
               extras: Mapping[str, Any] | None = None) -> bytes:
    """The file of a glTF document and its one buffer: ``glb`` (12-byte header, a JSON
    chunk padded with spaces, a BIN chunk padded with zeros, every chunk length a multiple
    of 4) or ``gltf`` (JSON, the buffer embedded as a base64 data URI). ``extras`` (JSON
    values), when given and not empty, become ``asset.extras``.

    Raises:
        ValueError: Another ``kind``.
    """
    if extras:
        doc["asset"]["extras"] = dict(extras)
    if kind == "gltf":
        doc["buffers"][0]["uri"] = ("data:application/octet-stream;base64,"
                                    + base64.b64encode(binary).decode("ascii"))
        return _json_bytes(doc)
    if kind != "glb":
        raise ValueError(f"unknown glTF kind {kind!r} (expected 'glb' or 'gltf')")
    js = _json_bytes(doc)
    js += b" " * ((-len(js)) % 4)
    bin_chunk = binary + b"\x00" * ((-len(binary)) % 4)
    total = 12 + 8 + len(js) + 8 + len(bin_chunk)
    return b"".join([
        struct.pack("<III", _GLB_MAGIC, _GLB_VERSION, total),
        struct.pack("<II", len(js), _CHUNK_JSON), js,
        struct.pack("<II", len(bin_chunk), _CHUNK_BIN), bin_chunk,
    ])


def encode_gltf_binary(vertices: ArrayLike, faces: ArrayLike, colors: ArrayLike | None = None,
                       normals: bool = True, texcoords: ArrayLike | None = None,
                       extras: Mapping[str, Any] | None = None) -> bytes:
    """Encode a triangle mesh as a GLB 2.0 file (media type ``model/gltf-binary``).

    Args:
        vertices: (n, 3) float, n >= 1, finite; written as float32 ``POSITION``, in this
            order.
        faces: (m, 3) int, indices in ``[0, n)``; m may be 0 (then a POINTS primitive).
        colors: (n, 4) or (n, 3) float, or None: linear RGBA (RGB gets alpha 1) in [0, 1],
            clipped; written as float32 ``COLOR_0``. :func:`color_ramp` produces suitable
            values.
        normals: Write area-weighted unit vertex normals as ``NORMAL``.
        texcoords: (n, 2) float uv (v up), or None: written as float32 ``TEXCOORD_0``
            (:func:`gltf_texcoords`).
        extras: JSON values written as ``asset.extras`` when not empty (the service puts
            the answer's ``warnings`` there), or None.

    Returns:
        12-byte header, a JSON chunk padded with spaces and a BIN chunk padded with zeros,
        every chunk length a multiple of 4.

    Raises:
        solver.core.errors.ShapeMismatchError: An array of the wrong shape or dtype.
        solver.core.errors.IndexOutOfRangeError: A face index outside ``[0, n)``.
        solver.core.errors.NonFiniteValueError: A non-finite coordinate or colour, or a
            coordinate that overflows float32.
    """
    doc, binary = _build(vertices, faces, colors, normals, texcoords)
    return _container(doc, binary, "glb", extras)


def encode_gltf_json(vertices: ArrayLike, faces: ArrayLike, colors: ArrayLike | None = None,
                     normals: bool = True, texcoords: ArrayLike | None = None,
                     extras: Mapping[str, Any] | None = None) -> bytes:
    """Encode a triangle mesh as a self-contained ``.gltf`` (media type ``model/gltf+json``).

    Same document as :func:`encode_gltf_binary`; the buffer is embedded as a
    ``data:application/octet-stream;base64,...`` URI.

    Args:
        vertices: As :func:`encode_gltf_binary`'s.
        faces: As there.
        colors: As there.
        normals: As there.
        texcoords: As there.
        extras: As there.

    Returns:
        UTF-8 JSON.

    Raises:
        solver.core.errors.SolverInputError: As :func:`encode_gltf_binary`.
    """
    doc, binary = _build(vertices, faces, colors, normals, texcoords)
    return _container(doc, binary, "gltf", extras)


def encode_gltf(vertices: ArrayLike, faces: ArrayLike, colors: ArrayLike | None = None,
                normals: bool = True, *, kind: Literal["glb", "gltf"] = "glb",
                texcoords: ArrayLike | None = None,
                extras: Mapping[str, Any] | None = None) -> bytes:
    """Encode with :func:`encode_gltf_binary` (``kind="glb"``) or :func:`encode_gltf_json`
    (``kind="gltf"``); the other arguments are theirs (``extras``: ``asset.extras``, e.g.
    the answer's warnings).

    Raises:
        ValueError: Another ``kind``.
    """
    if kind == "glb":
        return encode_gltf_binary(vertices, faces, colors, normals, texcoords, extras)
    if kind == "gltf":
        return encode_gltf_json(vertices, faces, colors, normals, texcoords, extras)
    raise ValueError(f"unknown glTF kind {kind!r} (expected 'glb' or 'gltf')")


# ----------------------------------------------------------------- morph targets, animation

ROWS_PER_SECOND: Final = 24.0
"""Default playback rate of an animated blend: rows (keyframes) per second."""


def _check_rows(rows: ArrayLike, n: int) -> NDArray[np.float64]:
    """Validate (T, n, 3) finite rows of vertices for :func:`encode_gltf_animation`."""
    r = np.asarray(rows, dtype=np.float64)
    if r.ndim != 3 or r.shape[1:] != (n, 3) or r.shape[0] == 0:
        raise ShapeMismatchError(f"expected rows of shape (T, {n}, 3) with T >= 1, got "
                                 f"{r.shape}", field="rows")
    bad = ~np.isfinite(r).all(axis=(1, 2))
    if bad.any():
        raise NonFiniteValueError("non-finite coordinate", field="rows",
                                  index=int(np.flatnonzero(bad)[0]))
    return r


def _add_morph_animation(doc: dict[str, Any], buf: _BufferBuilder, base: NDArray[np.float64],
                         faces: NDArray[np.int64], rows: NDArray[np.float64],
                         times: NDArray[np.float64], normals: bool) -> None:
    """Add each row as a morph target of the document's one primitive (POSITION, and NORMAL
    where ``normals``, as displacements from ``base``) and an animation whose weights step
    from target to target at ``times`` (LINEAR: consecutive rows cross-fade)."""
    primitive = doc["meshes"][0]["primitives"][0]
    base_normals = vertex_normals(base, faces) if normals else None
    targets = []
    for row in rows:  # a loop over rows (morph targets), not over mesh elements
        target = {"POSITION": buf.add((row - base).astype(np.float32), component_type=_FLOAT,
                                      type_="VEC3", target=_ARRAY_BUFFER, minmax=True)}
        if base_normals is not None:
            target["NORMAL"] = buf.add(vertex_normals(row, faces) - base_normals,
                                       component_type=_FLOAT, type_="VEC3",
                                       target=_ARRAY_BUFFER)
        targets.append(target)
    primitive["targets"] = targets
    count = len(rows)
    doc["meshes"][0]["weights"] = [0.0] * count
    doc["meshes"][0]["extras"] = {"targetNames": [f"row {k}" for k in range(count)]}
    # Animation input and output are not vertex data: bufferViews without a target.
    key_times = buf.add(times.astype(np.float32).reshape(-1, 1), component_type=_FLOAT,
                        type_="SCALAR", target=_ARRAY_BUFFER, minmax=True)
    weights = buf.add(np.eye(count, dtype=np.float32).ravel(), component_type=_FLOAT,
                      type_="SCALAR", target=_ARRAY_BUFFER)
    for accessor in (key_times, weights):
        del buf.buffer_views[buf.accessors[accessor]["bufferView"]]["target"]
    doc["animations"] = [{
        "name": "blend",
        "samplers": [{"input": key_times, "output": weights, "interpolation": "LINEAR"}],
        "channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}],
    }]


def encode_gltf_animation(rows: ArrayLike, faces: ArrayLike, *, base: ArrayLike | None = None,
                          times: ArrayLike | None = None, normals: bool = True,
                          kind: Literal["glb", "gltf"] = "glb",
                          extras: Mapping[str, Any] | None = None) -> bytes:
    """Encode a sequence of shapes of one mesh as an animated glTF: the base mesh, each row
    a morph target, and one animation (``blend``) that plays them.

    Args:
        rows: (T, n, 3) float, the shapes (e.g. :func:`solver.blend`'s rows), finite.
        faces: (m, 3) int, their faces.
        base: (n, 3) the mesh itself (default: ``rows[0]``); targets are displacements
            from it (float32).
        times: (T,) strictly increasing keyframe times in seconds (default: row ``k`` at
            ``k / ROWS_PER_SECOND``). At time ``times[k]`` the weights are one-hot on
            target ``k``; between keyframes they cross-fade linearly.
        normals: write ``NORMAL`` for the base and each target.
        kind: ``"glb"`` or ``"gltf"`` (buffer as a ``data:`` URI).
        extras: JSON values written as ``asset.extras`` when not empty (e.g. the blend's
            ``warnings``).

    Returns:
        The file's bytes.

    Raises:
        solver.core.errors.SolverInputError: As :func:`encode_gltf_binary`, or rows / times of
            the wrong shape, not finite, or times not increasing.

    Example:
        >>> import json, numpy as np
        >>> V = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0]])
        >>> data = encode_gltf_animation(np.stack([V, 2 * V]), [[0, 1, 2]], kind="gltf")
        >>> doc = json.loads(data)
        >>> len(doc["meshes"][0]["primitives"][0]["targets"]), doc["animations"][0]["name"]
        (2, 'blend')
    """
    f = np.asarray(faces)
    first = np.asarray(rows, dtype=np.float64)
    n = first.shape[1] if first.ndim == 3 else 0
    r = _check_rows(rows, n)
    b = r[0] if base is None else np.asarray(base, dtype=np.float64)
    if b.shape != r.shape[1:]:
        raise ShapeMismatchError(f"base has shape {b.shape}, rows {r.shape[1:]}",
                                 field="base")
    doc, binary = _build(b, f, None, normals)
    _, f64, _, v64 = _check_inputs(b, f, None)
    t = (np.arange(len(r)) / ROWS_PER_SECOND if times is None
         else np.asarray(times, dtype=np.float64).ravel())
    if t.shape != (len(r),) or not np.isfinite(t).all() or (np.diff(t) <= 0).any():
        raise ShapeMismatchError(f"times must be {len(r)} finite, strictly increasing "
                                 "seconds", field="times")
    buf = _BufferBuilder()
    buf.parts, buf.length = [binary], len(binary)
    buf.buffer_views, buf.accessors = doc["bufferViews"], doc["accessors"]
    _add_morph_animation(doc, buf, v64, f64, r, t, normals)
    binary = buf.tobytes()
    doc["buffers"] = [{"byteLength": len(binary)}]
    return _container(doc, binary, kind, extras)
