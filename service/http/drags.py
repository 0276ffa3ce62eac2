"""The wire formats of a deformation session's drags (HTTP bodies and WebSocket messages).

* a drag in JSON: ``{"handle_positions": [[x, y, z], ...], "handle_rotations"?: [3x3, ...],
  "seq"?: n}``;
* a drag in binary: little-endian float32, ``3 h`` values (h handle positions) optionally
  followed by ``9 g`` values (g row-major rotations, re-orthonormalized on arrival);
* the vertices in binary (``application/octet-stream``): little-endian float32, ``3 n``
  values; WebSocket replies put an 8-byte header in front: uint32 ``seq``, uint32 ``n``
  (both little-endian); a progressive session's replies end with a UTF-8 JSON trailer
  after the ``12 n`` bytes of vertices: ``{"shape": "linear", "drag"}`` at once, then
  ``{"shape": "refined", "drag", "converged", "stop_reason", "iterations", ...}``.

docs/service.md describes them for clients.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np
import orjson

from service.api.problems import ProblemError, element_error
from service.api.schemas import MAX_MAGNITUDE, SessionDrag
from service.http.bodies import validate_object

WS_HEADER = struct.Struct("<II")
"""WebSocket reply header: uint32 seq, uint32 vertex count (little-endian)."""


def _bad(field: str, reason: str, index: int | None = None) -> ProblemError:
    return ProblemError("validation-error", f"{field}: {reason}",
                        errors=[element_error(field, reason, index)])


def _check_finite(values: np.ndarray, field: str) -> None:
    bad = ~np.isfinite(values) | (np.abs(values) > MAX_MAGNITUDE)
    if bad.any():
        row = int(np.argwhere(bad)[0][0])
        raise _bad(field, "not a finite number within +-1e60", row)


def parse_drag_binary(data: bytes, n_handles: int,
                      n_groups: int) -> tuple[np.ndarray, np.ndarray | None]:
    """The targets of a binary drag.

    Args:
        data: Little-endian float32: h x 3 handle positions, then optionally g x 9 rotations.
        n_handles: The session's handle count h.
        n_groups: The session's rotation group count g.

    Returns:
        ``(positions, rotations)``: (h, 3) float64, and (g, 3, 3) float64 or None.

    Raises:
        ProblemError: 422 ``validation-error`` for a wrong size or a non-finite value.
    """
    if len(data) % 4:
        raise _bad("body", f"{len(data)} bytes is not a whole number of float32 values")
    values = np.frombuffer(data, dtype="<f4").astype(np.float64)
    n_pos = 3 * n_handles
    if len(values) == n_pos:
        rotations = None
    elif n_groups and len(values) == n_pos + 9 * n_groups:
        from solver.mesh.rotations import is_rotation, nearest_rotation

        rotations = values[n_pos:].reshape(n_groups, 3, 3)
        _check_finite(rotations.reshape(n_groups, 9), "handle_rotations")
        near = np.abs(np.swapaxes(rotations, 1, 2) @ rotations - np.eye(3)).max(axis=(1, 2))
        close = (near <= 1e-4) & (np.linalg.det(rotations) > 0)
        rotations = np.where(close[:, None, None], nearest_rotation(rotations), rotations)
        bad = np.flatnonzero(~is_rotation(rotations))
        if len(bad):
            raise _bad("handle_rotations", "not a rotation matrix (orthonormal with det +1)",
                       int(bad[0]))
    else:
        expected = f"{n_pos}" + (f" or {n_pos + 9 * n_groups}" if n_groups else "")
        raise _bad("body", f"expected {expected} little-endian float32 values "
                           f"({n_handles} handle positions"
                           + (f", then {n_groups} row-major 3x3 rotations" if n_groups else "")
                           + f"), got {len(values)}")
    positions = values[:n_pos].reshape(n_handles, 3)
    _check_finite(positions, "handle_positions")
    return positions, rotations


def parse_drag_json(doc: Any, n_handles: int,
                    n_groups: int) -> tuple[np.ndarray, np.ndarray | None, int | None]:
    """The targets of a JSON drag.

    Args:
        doc: The parsed drag (``{"handle_positions", "rotations"?, "seq"?}``).
        n_handles: The session's handle count.
        n_groups: The session's rotation group count.

    Returns:
        ``(positions, rotations, seq)`` as :func:`parse_drag_binary` returns them, and the
        drag's ``seq`` or None.

    Raises:
        ProblemError: 422 ``validation-error`` naming the element at fault.
    """
    model = validate_object(SessionDrag, doc)
    positions = np.asarray(model.handle_positions, dtype=np.float64).reshape(-1, 3)
    if len(positions) != n_handles:
        raise _bad("handle_positions", f"expected {n_handles} positions (one per handle), "
                                       f"got {len(positions)}")
    rotations = None
    if model.handle_rotations is not None:
        rotations = np.asarray(model.handle_rotations, dtype=np.float64).reshape(-1, 3, 3)
        if len(rotations) != n_groups:
            raise _bad("handle_rotations", f"expected {n_groups} rotations (one per rotation "
                                           f"group), got {len(rotations)}")
    return positions, rotations, model.seq


def ws_reply(seq: int, body: bytes, trailer: dict[str, Any] | None = None) -> bytes:
    """A WebSocket reply.

    Args:
        seq: The drag's sequence number.
        body: The float32 vertices.
        trailer: The JSON trailer of a progressive session's reply, if any.

    Returns:
        Header (uint32 seq, uint32 n) + float32 vertices (+ the UTF-8 JSON trailer).
    """
    reply = WS_HEADER.pack(seq & 0xFFFFFFFF, len(body) // 12) + body
    if trailer is None:
        return reply
    return reply + orjson.dumps(trailer, option=orjson.OPT_SERIALIZE_NUMPY)
