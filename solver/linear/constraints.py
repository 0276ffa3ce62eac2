"""Position and frame constraints of a reconstruction (:class:`Constraints`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, Self

import numpy as np
from numpy.typing import ArrayLike

from ..core.errors import ConstraintError
from ..core.serialization import JsonDataclass
from ..core.validation import as_indices, as_points, require_finite, require_unique
from ..mesh.rotations import is_rotation


@dataclass
class Constraints(JsonDataclass):
    """Position and frame constraints. A weight of ``inf`` (the default) makes it hard.

    Attributes:
        position_vertices: (p,) int64 constrained vertices (no repeats).
        positions: (p, 3) float64 their target positions.
        position_weights: (p,) float64 > 0, ``inf`` = hard (eliminated).
        frame_faces: (q,) int64 constrained faces (no repeats).
        frames: (q, 3, 3) float64 target frames, rotations whose columns are (unit vector
            along the face's edge faces[t][0] -> faces[t][1], in-plane perpendicular, normal).
        frame_weights: (q,) float64 > 0, ``inf`` = hard.
    """

    position_vertices: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    positions: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    position_weights: np.ndarray | None = None
    frame_faces: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    frames: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    frame_weights: np.ndarray | None = None

    _array_fields: ClassVar[dict[str, Any]] = {
        "position_vertices": np.int64, "positions": np.float64, "position_weights": np.float64,
        "frame_faces": np.int64, "frames": np.float64, "frame_weights": np.float64,
    }

    @classmethod
    def from_records(cls, positions: Sequence[Mapping[str, Any]] = (),
                     frames: Sequence[Mapping[str, Any]] = ()) -> Self | None:
        """Constraints from one record per constraint (the service's ``constraints``
        document): ``{"vertex", "position", "weight"}`` and ``{"face", "frame", "weight"}``,
        a missing or None weight hard; None when there are none.

        Example:
            >>> c = Constraints.from_records([{"vertex": 2, "position": [0.0, 1.0, 0.0]}])
            >>> c.position_vertices.tolist(), c.position_weights.tolist()
            ([2], [inf])
        """
        if not positions and not frames:
            return None

        def weights(items: Sequence[Mapping[str, Any]]) -> np.ndarray:
            return np.array([np.inf if c.get("weight") is None else c["weight"]
                             for c in items], dtype=np.float64)

        return cls(
            position_vertices=np.array([c["vertex"] for c in positions], dtype=np.int64),
            positions=np.array([c["position"] for c in positions],
                               dtype=np.float64).reshape(-1, 3),
            position_weights=weights(positions),
            frame_faces=np.array([c["face"] for c in frames], dtype=np.int64),
            frames=np.array([c["frame"] for c in frames], dtype=np.float64).reshape(-1, 3, 3),
            frame_weights=weights(frames))

    def validated(self, n_vertices: int, n_faces: int, rotation_tol: float = 1e-6,
                  ) -> Constraints:
        """Checked copy with arrays of the documented shapes; raises ConstraintError etc."""
        pv = as_indices(self.position_vertices, "constraints.positions.vertex", n_vertices)
        pos = as_points(self.positions, "constraints.positions.position")
        pw = _weights(self.position_weights, len(pv), "constraints.positions.weight")
        ff = as_indices(self.frame_faces, "constraints.frames.face", n_faces)
        fr = np.asarray(self.frames, dtype=np.float64).reshape(-1, 3, 3) if np.size(
            self.frames) else np.zeros((0, 3, 3))
        require_finite(fr, "constraints.frames.frame")
        fw = _weights(self.frame_weights, len(ff), "constraints.frames.weight")
        if len(pos) != len(pv):
            raise ConstraintError(f"{len(pv)} constrained vertices but {len(pos)} positions",
                                  field="constraints.positions")
        if len(fr) != len(ff):
            raise ConstraintError(f"{len(ff)} constrained faces but {len(fr)} frames",
                                  field="constraints.frames")
        require_unique(pv, "constraints.positions.vertex", "vertex")
        require_unique(ff, "constraints.frames.face", "face")
        bad = np.flatnonzero(~is_rotation(fr, rotation_tol))
        if len(bad):
            raise ConstraintError(
                f"frame of face {int(ff[bad[0]])} is not a rotation matrix (orthonormal, det +1)",
                field="constraints.frames.frame", index=int(bad[0]))
        return Constraints(pv, pos, pw, ff, fr, fw)


def _weights(values: ArrayLike | None, size: int, name: str) -> np.ndarray:
    if values is None:
        return np.full(size, np.inf)
    w = np.asarray(values, dtype=np.float64).reshape(-1)
    if len(w) != size:
        raise ConstraintError(f"expected {size} weights, got {len(w)}", field=name)
    bad = np.flatnonzero(~(w > 0))
    if len(bad):
        raise ConstraintError(f"weight {w[bad[0]]!r} must be positive (inf = hard)",
                              field=name, index=int(bad[0]))
    return w
