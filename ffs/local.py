"""The operations in this process through :mod:`solver`, with the client's signatures.

:class:`Local` has the methods of :class:`ffs.client.Client` (same arguments, the HTTP
option names, the same :mod:`ffs.results`) and calls the library the way the service's
workers do (``service/worker/tasks.py``: the same options and defaults), so that
``ffs <command>`` gives the same vertices in-process and with ``--server`` (bit for bit with
the same BLAS thread count; other thread counts change the round-off of refined answers).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

import solver
from ffs.results import Blend, Forms, Integrability, Mesh, Parameterization
from solver.errors import SolverInputError
from solver.serialization import to_jsonable

Progress = Callable[[str, float], None]

_SOLVE_OPTIONS = {"frame_weight": "frame_weight", "orthonormalize": "orthonormalize",
                  "orthonormal_weight": "orthonormal_weight", "weighting": "weighting",
                  "solver": "backend", "max_seconds": "max_seconds"}
"""HTTP option name -> the library's keyword (the rest are the operation's own)."""


class NotIntegrableError(SolverInputError):
    """``require_integrable`` and the forms fail the check (the service's 422
    ``not-integrable``), naming the worst vertex."""

    kind = "not-integrable"


def _keywords(options: Mapping[str, Any], allowed: Sequence[str]) -> dict[str, Any]:
    """The library keywords of the given HTTP options (None means the default)."""
    unknown = [name for name in options if name not in allowed]
    if unknown:
        raise SolverInputError(f"unknown option {unknown[0]!r}; options: {', '.join(allowed)}",
                               field=f"options.{unknown[0]}")
    return {_SOLVE_OPTIONS.get(name, name): value for name, value in options.items()
            if value is not None}


def _constraints(data: Mapping[str, Any] | None) -> solver.Constraints | None:
    """The library's constraints of the API's ``constraints`` document."""
    if not data:
        return None
    positions, frames = data.get("positions") or [], data.get("frames") or []
    if not positions and not frames:
        return None

    def weights(items: list[dict[str, Any]]) -> np.ndarray:
        return np.array([np.inf if c.get("weight") is None else c["weight"] for c in items],
                        dtype=np.float64)

    return solver.Constraints(
        position_vertices=np.array([c["vertex"] for c in positions], dtype=np.int64),
        positions=np.array([c["position"] for c in positions], dtype=np.float64).reshape(-1, 3),
        position_weights=weights(positions),
        frame_faces=np.array([c["face"] for c in frames], dtype=np.int64),
        frames=np.array([c["frame"] for c in frames], dtype=np.float64).reshape(-1, 3, 3),
        frame_weights=weights(frames))


def _forms(faces: Any, edges: Any, lengths: Any, angles: Any) -> Forms:
    if isinstance(faces, Forms) and edges is None:
        return faces
    return Forms(np.asarray(faces), np.asarray(edges), np.asarray(lengths), np.asarray(angles))


def integrability_report(report: solver.IntegrabilityReport) -> Integrability:
    return Integrability(report.integrable, report.max_defect, report.vertex_defect,
                         to_jsonable(report.to_dict()))


class Local:
    """The operations in-process (see the module docstring)."""

    url = None

    def fundamental_forms(self, vertices: Any, faces: Any, *,
                          progress: Progress | None = None) -> Forms:
        forms = solver.fundamental_forms(vertices, faces)
        return Forms(forms.faces, forms.edges, forms.lengths, forms.angles)

    def check_integrability(self, faces: Any, edges: Any = None, lengths: Any = None,
                            angles: Any = None, *, tol: float | None = None,
                            n_vertices: int | None = None,
                            progress: Progress | None = None) -> Integrability:
        forms = _forms(faces, edges, lengths, angles)
        report = solver.check_integrability(forms.faces, forms.edges, forms.lengths,
                                            forms.angles, tol=1e-8 if tol is None else tol,
                                            n_vertices=n_vertices)
        return integrability_report(report)

    def reconstruct(self, faces: Any, edges: Any = None, lengths: Any = None,
                    angles: Any = None, *, constraints: Mapping[str, Any] | None = None,
                    refine: bool | None = None, progress: Progress | None = None,
                    **options: Any) -> Mesh:
        forms = _forms(faces, edges, lengths, angles)
        keywords = _keywords(options, (*_SOLVE_OPTIONS, "tolerance", "require_integrable",
                                       "exact_shortcut"))
        tolerance = keywords.pop("tolerance", 1e-8)
        report_first = None
        if keywords.pop("require_integrable", False):
            report_first = solver.check_integrability(forms.faces, forms.edges, forms.lengths,
                                                      forms.angles, tol=tolerance)
            if not report_first.integrable:
                worst = [int(v) for v in report_first.worst_vertices]
                raise NotIntegrableError(
                    f"the forms are not integrable: max defect {report_first.max_defect:.3g} "
                    f"(tolerance {tolerance:g}); worst vertices {worst}",
                    field="vertices", index=worst[0] if worst else None)
        result = solver.reconstruct(
            forms.faces, forms.edges, forms.lengths, forms.angles,
            constraints=_constraints(constraints), refine=refine,
            check_integrability=report_first is None, integrability_tol=tolerance,
            progress=progress, **keywords)
        report = to_jsonable(result.report)
        if report_first is not None:
            report = {"integrability": to_jsonable(report_first.summary()), **report}
        return Mesh(result.vertices, np.asarray(forms.faces, dtype=np.int64), report)

    def deform(self, vertices: Any, faces: Any, handles: Sequence[int] | np.ndarray,
               handle_positions: Any, *, rotation_handles: Sequence[Any] | None = None,
               handle_rotations: Any = None, roi: Any = None, refine: bool | None = None,
               progress: Progress | None = None, **options: Any) -> Mesh:
        keywords = _keywords(options, tuple(_SOLVE_OPTIONS))
        result = solver.deform(
            vertices, faces, np.asarray(handles, dtype=np.int64),
            np.asarray(handle_positions, dtype=np.float64).reshape(-1, 3),
            rotation_handles=[np.asarray(g, dtype=np.int64) for g in rotation_handles or []]
            or None,
            handle_rotations=(None if not rotation_handles else
                              np.asarray(handle_rotations, dtype=np.float64).reshape(-1, 3, 3)),
            roi=None if roi is None else np.asarray(roi, dtype=np.int64), refine=refine,
            progress=progress, **keywords)
        return Mesh(result.vertices, np.asarray(faces, dtype=np.int64),
                    to_jsonable(result.report))

    def parameterize(self, vertices: Any, faces: Any, *, refine: bool | None = None,
                     progress: Progress | None = None, **options: Any) -> Parameterization:
        keywords = _keywords(options, tuple(_SOLVE_OPTIONS))
        result = solver.parameterize(vertices, faces, refine=refine, progress=progress,
                                     **keywords)
        return Parameterization(result.uv, result.flipped_faces, to_jsonable(result.report))

    def interpolate(self, vertices_a: Any, vertices_b: Any, faces: Any,
                    t: float | Sequence[float], *, refine: bool | None = None,
                    progress: Progress | None = None, **options: Any) -> Blend:
        keywords = _keywords(options, ("frame_weight", "weighting", "solver", "max_seconds"))
        t_value = float(t) if np.ndim(t) == 0 else [float(x) for x in np.ravel(t)]
        vertices, reports = solver.interpolate(vertices_a, vertices_b, faces, t_value,
                                               refine=refine, return_reports=True, **keywords)
        return Blend(t_value, vertices, np.asarray(faces, dtype=np.int64),
                     to_jsonable(reports[0] if np.ndim(t_value) == 0 else reports))

    def mesh(self, vertices: Any, faces: Any, *, progress: Progress | None = None) -> Mesh:
        """The mesh checked like the service checks it (``POST /v1/mesh``), its report."""
        from solver.topology import build_topology
        from solver.validation import as_points

        points = as_points(vertices, "vertices")
        topology = build_topology(faces, n_vertices=len(points))
        edges = topology.edges
        lengths = np.linalg.norm(points[edges[:, 1]] - points[edges[:, 0]], axis=1)
        report = {"n_vertices": len(points), "n_faces": len(topology.faces),
                  "n_edges": len(edges),
                  "bounds": [points.min(axis=0).tolist(), points.max(axis=0).tolist()],
                  "mean_edge_length": float(lengths.mean()) if len(lengths) else 0.0}
        return Mesh(points, np.asarray(topology.faces, dtype=np.int64), report)
