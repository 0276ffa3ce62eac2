"""The warm side of a deformation session: one prefactorized :class:`solver.Deformer`.

A backend keeps one :class:`SessionState` alive with exactly one worker (a dedicated
process locally, a Dask actor on a cluster); every drag only back-substitutes and encodes.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from service.api.task import SessionSpec
from service.worker import output

SESSION_FORMATS: tuple[str, ...] = ("json", "glb", "gltf", "f32")
"""Response formats of a session solve, in server preference order."""


def encode_vertices(vertices: np.ndarray, faces: np.ndarray, fmt: str) -> bytes:
    """The body of a solve in format ``fmt`` (see :data:`SESSION_FORMATS`): ``f32`` is
    little-endian float32 (n, 3), ready for a vertex buffer."""
    if fmt == "f32":
        return np.ascontiguousarray(vertices, dtype="<f4").tobytes()
    if fmt == "json":
        return output.json_bytes({"vertices": vertices})
    if fmt == "f64":  # not offered over HTTP; exact float64 for tests
        return np.ascontiguousarray(vertices, dtype="<f8").tobytes()
    return output.mesh_bytes(fmt, vertices, faces)


class SessionState:
    """A :class:`solver.Deformer` factorized at init, and a first solve at rest that checks
    the factorization (and warms the backend up)."""

    def __init__(self, spec: SessionSpec) -> None:
        import solver

        options = spec.options
        start = time.perf_counter()
        self.deformer = solver.Deformer(
            spec.vertices, spec.faces, spec.handles, rotation_handles=list(spec.rotations) or None,
            roi=spec.roi, frame_weight=options.get("frame_weight", 1000.0),
            orthonormalize=options.get("orthonormalize", False),
            orthonormal_weight=options.get("orthonormal_weight", 1000.0),
            weighting=options.get("weighting", "uniform"),
            backend=options.get("solver") or spec.backend,
            refine=bool(options.get("refine")))  # null: off (a refined drag costs more)
        self.deformer.solve()
        self.setup_seconds = time.perf_counter() - start
        self.faces = self.deformer.faces
        self.solves = 0

    def info(self) -> dict[str, Any]:
        """Sizes, handles, set-up time and linear-solver backend."""
        d = self.deformer
        return {"n_vertices": len(d.rest), "n_faces": len(d.faces),
                "handles": [int(h) for h in d.handles], "n_rotation_groups": d.n_groups,
                "setup_seconds": self.setup_seconds, "backend": d.backend}

    def solve(self, positions: np.ndarray, rotations: np.ndarray | None,
              fmt: str) -> tuple[bytes, dict[str, float]]:
        """Deformed vertices for new handle targets, encoded; and stage timings."""
        t0 = time.perf_counter()
        vertices = self.deformer.solve(positions, rotations)
        t1 = time.perf_counter()
        body = encode_vertices(vertices, self.faces, fmt)
        self.solves += 1
        return body, {"solve": t1 - t0, "encode": time.perf_counter() - t1}
