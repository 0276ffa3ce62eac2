"""Results of the operations, as the client and the command line return them: numpy arrays
with the names of the library's results (:mod:`solver`), and the service's report.

Shapes and dtypes follow the project's conventions: ``vertices`` (n, 3) float64, ``faces``
(m, 3) int64, ``edges`` (E, 2) int64 (i < j, sorted), ``lengths``/``angles`` (E,) float64.
The service does not send what only the library computes (a reconstruction's frames, a
flattening's per-face area ratios), so these are not the library's classes themselves.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


def _floats(value: Any, cols: int | None = 3) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    return array.reshape(-1, cols) if cols else array.reshape(-1)


def _ints(value: Any, cols: int | None = 3) -> np.ndarray:
    array = np.asarray(value, dtype=np.int64)
    return array.reshape(-1, cols) if cols else array.reshape(-1)


@dataclass
class Forms:
    """Discrete fundamental forms (``solver.Forms``): faces (m, 3), edges (E, 2), lengths
    (E,) and signed dihedral angles (E,) aligned with the edges."""

    faces: np.ndarray
    edges: np.ndarray
    lengths: np.ndarray
    angles: np.ndarray

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> Forms:
        """From the API's forms document (``{"faces", "edges", "lengths", "angles"}``)."""
        return cls(_ints(doc["faces"]), _ints(doc["edges"], 2), _floats(doc["lengths"], None),
                   _floats(doc["angles"], None))

    def to_dict(self) -> dict[str, Any]:
        """The API's forms document (lists; a valid body for integrability/reconstruct)."""
        return {name: getattr(self, name).tolist()
                for name in ("faces", "edges", "lengths", "angles")}

    def arrays(self) -> dict[str, np.ndarray]:
        return {"faces": self.faces, "edges": self.edges, "lengths": self.lengths,
                "angles": self.angles}


@dataclass
class Integrability:
    """An integrability report: ``integrable``, ``max_defect`` and the per-vertex
    ``vertex_defect`` (n,) float64; ``report`` is the whole document (Gauss and Codazzi
    parts, topology, global holonomy, ...)."""

    integrable: bool
    max_defect: float
    vertex_defect: np.ndarray
    report: dict[str, Any]

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> Integrability:
        return cls(bool(doc["integrable"]), float(doc["max_defect"]),
                   _floats(doc.get("vertex_defect", []), None), doc)


@dataclass
class Mesh:
    """A mesh with its report: vertices (n, 3) float64, faces (m, 3) int64.

    What ``reconstruct``, ``deform`` and ``mesh`` (read and check) return; the report is the
    operation's (timings, backend, integrability, refinement, distortion, ...)."""

    vertices: np.ndarray
    faces: np.ndarray
    report: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> Mesh:
        return cls(_floats(doc["vertices"]), _ints(doc["faces"]), doc.get("report") or {})


Reconstruction = Mesh
"""The result of ``reconstruct`` (the library's ``Reconstruction`` without frames)."""
Deformation = Mesh
"""The result of ``deform`` (the library's ``Deformation``, with the faces)."""


@dataclass
class Parameterization:
    """A flattening: the layout uv (k, 2) float64 over uv_faces (m, 3) int64, flipped_faces
    (f,) int64, the report; the atlas in the unit square ``texcoords`` (k, 2), the file
    vertex of each uv ``uv_vertex`` (k,) and the chart of each face ``face_chart`` (m,)
    (None from a service without them)."""

    uv: np.ndarray
    flipped_faces: np.ndarray
    report: dict[str, Any] = field(default_factory=dict)
    texcoords: np.ndarray | None = None
    uv_faces: np.ndarray | None = None
    uv_vertex: np.ndarray | None = None
    face_chart: np.ndarray | None = None

    @property
    def charts(self) -> int:
        """Number of charts (1 without an atlas report)."""
        return int((self.report.get("atlas") or {}).get("charts", 1))

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> Parameterization:
        def optional(key: str, convert: Any, cols: int | None) -> np.ndarray | None:
            return None if doc.get(key) is None else convert(doc[key], cols)

        return cls(_floats(doc["uv"], 2), _ints(doc.get("flipped_faces", []), None),
                   doc.get("report") or {}, optional("texcoords", _floats, 2),
                   optional("uv_faces", _ints, 3), optional("uv_vertex", _ints, None),
                   optional("face_chart", _ints, None))


@dataclass
class Blend:
    """A form-space blend: ``vertices`` (n, 3) for one t, (k, n, 3) for a list of k values,
    the faces and the refinement report(s)."""

    t: float | list[float]
    vertices: np.ndarray
    faces: np.ndarray
    refinement: Any = None

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> Blend:
        t = doc["t"]
        vertices = np.asarray(doc["vertices"], dtype=np.float64)
        return cls(t, vertices.reshape(-1, 3) if np.ndim(t) == 0 else vertices,
                   _ints(doc["faces"]), doc.get("refinement"))
