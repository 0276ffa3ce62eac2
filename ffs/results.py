"""Results of the operations, as the client and the command line return them: numpy arrays
with the names of the library's results (:mod:`solver`), and the service's report.

Shapes and dtypes follow the project's conventions: ``vertices`` (n, 3) float64, ``faces``
(m, 3) int64, ``edges`` (E, 2) int64 (i < j, sorted), ``lengths``/``angles`` (E,) float64.
The service does not send what only the library computes (a reconstruction's frames, a
flattening's per-face area ratios), so these are not the library's classes themselves.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
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
    (E,) and signed dihedral angles (E,) aligned with the edges; for a non-manifold mesh
    ``vertex_map`` (n_cut,) int64, the file vertex of each vertex of the (cut) faces; and
    ``placement``, each component's pose (``{"faces", "origins", "frames"}``), which
    ``reconstruct`` uses to put every part back where it was; for a mesh with zero-length
    edges ``weld_map`` (n,) int64, the file vertex each file vertex was welded into, and
    ``dropped_faces`` (d,) int64, the file faces the weld collapsed (informational)."""

    faces: np.ndarray
    edges: np.ndarray
    lengths: np.ndarray
    angles: np.ndarray
    vertex_map: np.ndarray | None = None
    placement: dict[str, Any] | None = None
    weld_map: np.ndarray | None = None
    dropped_faces: np.ndarray | None = None

    PLACEMENT_ARRAYS = ("faces", "origins", "frames")
    """The placement's arrays, stored as ``placement_<name>`` in an .npz."""

    @classmethod
    def given(cls, faces: Any, edges: Any = None, lengths: Any = None, angles: Any = None, *,
              vertex_map: Any = None, weld_map: Any = None, placement: Any = None) -> Forms:
        """The forms a call was given: one :class:`Forms`, or its four arrays; and the
        ``vertex_map``, ``weld_map`` and ``placement`` given as keywords, as the library's
        ``reconstruct`` takes them (each overrides the Forms' own). ``placement`` is a
        mapping of ``faces``, ``origins`` and ``frames`` or an object with those attributes
        (the library's).

        Raises:
            TypeError: Neither one Forms nor the four arrays.
        """
        if isinstance(faces, Forms) and edges is None:
            forms = faces
        elif edges is None or lengths is None or angles is None:
            raise TypeError("pass faces, edges, lengths and angles, or one Forms")
        else:
            forms = cls(np.asarray(faces), np.asarray(edges), np.asarray(lengths),
                        np.asarray(angles))
        if placement is not None and not isinstance(placement, Mapping):
            placement = {name: getattr(placement, name) for name in cls.PLACEMENT_ARRAYS}
        maps = {"vertex_map": vertex_map, "weld_map": weld_map, "placement": placement}
        return replace(forms, **{name: value for name, value in maps.items()
                                 if value is not None})

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> Forms:
        """From the API's forms document (``{"faces", "edges", "lengths", "angles"}``, and
        the optional ``vertex_map`` and ``placement``; an .npz's ``placement_faces``,
        ``placement_origins`` and ``placement_frames``)."""
        placement = doc.get("placement")
        if placement is None and "placement_faces" in doc:
            placement = {name: np.asarray(doc[f"placement_{name}"]).tolist()
                         for name in cls.PLACEMENT_ARRAYS}
        vertex_map, weld_map = doc.get("vertex_map"), doc.get("weld_map")
        dropped = doc.get("dropped_faces")
        return cls(_ints(doc["faces"]), _ints(doc["edges"], 2), _floats(doc["lengths"], None),
                   _floats(doc["angles"], None),
                   None if vertex_map is None else _ints(vertex_map, None),
                   None if placement is None else dict(placement),
                   None if weld_map is None else _ints(weld_map, None),
                   None if dropped is None else _ints(dropped, None))

    def to_dict(self) -> dict[str, Any]:
        """The API's forms document (lists; a valid body for integrability/reconstruct)."""
        doc = {name: getattr(self, name).tolist()
               for name in ("faces", "edges", "lengths", "angles")}
        if self.dropped_faces is not None:
            doc["dropped_faces"] = np.asarray(self.dropped_faces).tolist()
        return {**doc, **self.params()}

    def params(self) -> dict[str, Any]:
        """The optional ``vertex_map``, ``weld_map`` and ``placement`` as request params
        (JSON-ready)."""
        out: dict[str, Any] = {}
        for name in ("vertex_map", "weld_map"):
            if getattr(self, name) is not None:
                out[name] = np.asarray(getattr(self, name)).tolist()
        if self.placement is not None:
            out["placement"] = {name: np.asarray(self.placement[name]).tolist()
                                for name in self.PLACEMENT_ARRAYS}
        return out

    def stored_arrays(self) -> dict[str, np.ndarray]:
        """Every array by name, for an .npz: :meth:`arrays`, ``vertex_map``, ``weld_map``,
        ``dropped_faces`` and the ``placement_*`` arrays where present."""
        out = dict(self.arrays())
        for name in ("vertex_map", "weld_map", "dropped_faces"):
            if getattr(self, name) is not None:
                out[name] = np.asarray(getattr(self, name))
        if self.placement is not None:
            out.update({f"placement_{name}": np.asarray(self.placement[name])
                        for name in self.PLACEMENT_ARRAYS})
        return out

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

    @property
    def warnings(self) -> list[dict[str, Any]]:
        """The report's ``warnings``: ``{code, message, value, limit}`` of each threshold
        the answer is past ([] for a good answer; see docs/service.md#warnings)."""
        return list(self.report.get("warnings") or [])


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

    @property
    def warnings(self) -> list[dict[str, Any]]:
        """The report's ``warnings`` (as :attr:`Mesh.warnings`)."""
        return list(self.report.get("warnings") or [])


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


@dataclass
class ShapeBlend:
    """Rows of a form-space blend of K shapes (``POST /v1/blend``): ``weights`` (T, K),
    ``vertices`` (T, n, 3), the faces and one report per row."""

    weights: np.ndarray
    vertices: np.ndarray
    faces: np.ndarray
    reports: list[dict[str, Any]] = field(default_factory=list)

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> ShapeBlend:
        weights = np.asarray(doc["weights"], dtype=np.float64)
        vertices = np.asarray(doc["vertices"], dtype=np.float64).reshape(len(weights), -1, 3)
        return cls(weights, vertices, _ints(doc["faces"]), list(doc.get("reports") or []))

    @property
    def warnings(self) -> list[dict[str, Any]]:
        """Every row's ``warnings`` (as :attr:`Mesh.warnings`), each with its ``row``."""
        return [{**found, "row": report.get("row", k)}
                for k, report in enumerate(self.reports)
                for found in report.get("warnings") or []]

@dataclass
class VjpResult:
    """A reconstruction and the cotangents of its inputs (``POST /v1/reconstruct/vjp``;
    the library's :class:`solver.adjoints.FormCotangents`): ``vertices`` (n, 3),
    ``faces`` (m, 3), ``grad_lengths`` and ``grad_angles`` (E,) float64 (or (k, E) for k
    cotangents at once), ``grad_positions`` (p, 3) and ``grad_frames`` (q, 3, 3) of the
    constraint targets in the order they were given (leading k likewise), the report
    (``report["vjp"]``: which answer was differentiated)."""

    vertices: np.ndarray
    faces: np.ndarray
    grad_lengths: np.ndarray
    grad_angles: np.ndarray
    grad_positions: np.ndarray
    grad_frames: np.ndarray
    report: dict[str, Any] = field(default_factory=dict)

    GRADIENTS = ("grad_lengths", "grad_angles", "grad_positions", "grad_frames")
    """The cotangent arrays, by name."""

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> VjpResult:
        lengths = np.asarray(doc["grad_lengths"], dtype=np.float64)
        batch = lengths.shape[:-1]  # (k,) for k cotangents at once, else ()
        positions = np.asarray(doc["grad_positions"], dtype=np.float64).reshape(*batch, -1, 3)
        frames = np.asarray(doc["grad_frames"], dtype=np.float64).reshape(*batch, -1, 3, 3)
        return cls(_floats(doc["vertices"]), _ints(doc["faces"]), lengths,
                   np.asarray(doc["grad_angles"], dtype=np.float64), positions, frames,
                   doc.get("report") or {})

    def arrays(self) -> dict[str, np.ndarray]:
        """The cotangents by name (for a .json or .npz file)."""
        return {name: getattr(self, name) for name in self.GRADIENTS}
