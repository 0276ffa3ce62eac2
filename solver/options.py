"""The solve options: one frozen dataclass per operation, every option declared once.

:class:`SolveOptions` holds what every solve takes; :class:`ReconstructOptions`,
:class:`DeformOptions`, :class:`ParameterizeOptions` and :class:`InterpolateOptions` add an
operation's own options (and declare, where they are declared, the two defaults that
differ: ``parameterize`` orthonormalizes, ``deform`` bends stiffer). Each field carries its
description, whether the HTTP service offers it (``served``), the service's name for it
where that differs (``api_name``: the backend is ``options.solver`` over HTTP, the
integrability tolerance ``options.tolerance``) and the bounds the service checks, so the
service derives its request models from these classes (:mod:`service.api.schemas`) and a
new option is added here only.

Every entry point takes ``options=`` and, for convenience, the same names as keywords:
``reconstruct(..., refine=False)`` is ``reconstruct(..., options=ReconstructOptions(
refine=False))``; :meth:`SolveOptions.replace` changes some fields of an options object.

Example:
    >>> from solver.options import ReconstructOptions
    >>> options = ReconstructOptions(frame_weight=10.0)
    >>> options.replace(refine=False).refine, options.frame_weight
    (False, 10.0)
    >>> ReconstructOptions.from_api({"solver": "superlu", "tolerance": 1e-6}).backend
    'superlu'
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, Literal, Self

import numpy as np

from .core.errors import SolverInputError
from .linalg import BACKENDS
from .linalg.iterative import LinearSolver
from .linear.system import Weighting
from .refine.energy_weights import ANGLE_WEIGHT, AREA_WEIGHT, DEFORM_ANGLE_WEIGHT

FRAME_WEIGHT = 1000.0
"""Default relative weight w of the frame term E_f of Eq. 5 (the paper's value)."""
ORTHONORMAL_WEIGHT = 1000.0
"""Default weight of the second solve's rotation targets (Sec. 4)."""
COTAN_FLOOR = 1e-11
"""Lower threshold of cotangent weights (the paper's value)."""
INTEGRABILITY_TOL = 1e-8
"""Default tolerance of the integrability check (radians; translations relative to the
mean edge length)."""
MAX_WEIGHT = 1e12
"""Largest energy weight the service accepts (frame, orthonormalization, soft constraint)."""
MAX_SECONDS = 1e9
"""Largest ``max_seconds`` the service accepts."""

Backend = Literal["auto", *sorted(BACKENDS)]  # type: ignore[valid-type]


def option(default: Any, description: str, *, served: bool = True, api_name: str | None = None,
           **bounds: float) -> Any:
    """A field of an options class: its default, its description (the docs of the library
    and of the HTTP schema), whether the service offers it, its HTTP name when it differs
    and the bounds (``gt``, ``ge``, ``le``) the service's schema checks."""
    return dataclasses.field(default=default, metadata={
        "description": description, "served": served, "api_name": api_name, "bounds": bounds})


def redefault(cls: type, name: str, default: Any) -> Any:
    """The field ``name`` of ``cls`` with another default (same description and metadata)."""
    return dataclasses.field(default=default, metadata=cls.__dataclass_fields__[name].metadata)


def shared(cls: type, name: str, **metadata: Any) -> Any:
    """The field ``name`` of ``cls`` declared for another options class with the same default
    and description (``metadata`` changed, e.g. ``served=False``: not offered over HTTP)."""
    field = cls.__dataclass_fields__[name]
    return dataclasses.field(default=field.default,
                             metadata={**field.metadata, **metadata})


def api_name(field: dataclasses.Field[Any]) -> str:
    """The HTTP service's name of an options field."""
    return field.metadata.get("api_name") or field.name


@dataclasses.dataclass(frozen=True)
class SolveOptions:
    """The options every solve takes (each field's ``description`` documents it).

    Attributes:
        frame_weight: see :data:`FRAME_WEIGHT`.
        weighting: edge weighting of the energy.
        backend: sparse factorization backend (HTTP: ``solver``).
        refine: the nearest-surface refinement (None: auto).
        angle_weight: the refinement's dihedral weight.
        max_seconds: wall-clock budget.
    """

    frame_weight: float = option(
        FRAME_WEIGHT, "Weight w of the frame term E_f of Eq. 5 (the paper's 1000). Lengths "
        "are divided by their mean first, so it means the same at every mesh scale.",
        gt=0, le=MAX_WEIGHT)
    weighting: Weighting = option(  # noqa: RUF009 - a field specifier (dataclasses.field)
        "uniform", "Edge weighting of the energy: `uniform`, `cotan` (the paper literally) "
        "or `cotan_clamped` (docs/weights.md).")
    backend: Backend | None = option(  # noqa: RUF009 - likewise
        None, "Sparse factorization backend: `auto` or one of "
        f"{', '.join(f'`{name}`' for name in sorted(BACKENDS))}; null: the default (`auto`; "
        "the service's FFS_SOLVER_BACKEND). Named `backend` in the library, `solver` over HTTP.",
        api_name="solver")
    refine: bool | None = option(
        None, "Nearest-surface refinement (Levenberg-Marquardt on edge lengths and dihedral "
        "angles, started from the linear answer): `null` (default) refines when the linear "
        "answer does not reproduce the forms; `false` returns the linear answer of Eq. 5 "
        "(fast; it shrinks non-integrable forms); `true` refines whenever the answer is not "
        "exact. `report.refinement` says whether and how it refined.")
    angle_weight: float = option(
        ANGLE_WEIGHT, "The refinement's weight of a radian of dihedral angle against a "
        "relative length change of 1 (docs/refinement.md).", served=False)
    max_seconds: float | None = option(
        None, "Wall-clock budget of the solve in seconds. When the refinement runs out of it "
        "the answer is its best shape so far, reported as `converged: false, stop_reason: "
        "\"time_limit\"` (the linear solve itself is never cut short).", gt=0, le=MAX_SECONDS)

    def replace(self, **changes: Any) -> Self:
        """A copy with ``changes`` (field names of this class) applied.

        Raises:
            TypeError: a name that is not an option of this class.
        """
        unknown = sorted(set(changes) - set(self.names()))
        if unknown:
            raise TypeError(f"{type(self).__name__} has no option {unknown[0]!r}; options: "
                            f"{', '.join(self.names())}")
        return dataclasses.replace(self, **changes)

    @classmethod
    def names(cls) -> tuple[str, ...]:
        """The field names, in declaration order."""
        return tuple(f.name for f in dataclasses.fields(cls))

    @classmethod
    def given(cls, options: SolveOptions | None, overrides: Mapping[str, Any]) -> Self:
        """What an entry point solves with: ``options`` (default ``cls()``; the fields this
        class shares with another options class are taken from it) with the keyword
        ``overrides`` applied."""
        if options is None:
            base = cls()
        elif isinstance(options, cls):
            base = options
        else:
            shared = set(cls.names()) & set(options.names())
            base = cls(**{name: getattr(options, name) for name in shared})
        return base.replace(**overrides) if overrides else base

    @classmethod
    def from_api(cls, values: Mapping[str, Any], *, ignore: tuple[str, ...] = ()) -> Self:
        """Options from the HTTP service's names and values (``null`` is the default).

        Args:
            values: HTTP option name -> value (a request's ``options``).
            ignore: names that are not solver options (the service's own).
        Raises:
            SolverInputError: an option this operation does not offer (``options.<name>``).
        """
        by_api = {api_name(f): f.name for f in dataclasses.fields(cls)
                  if f.metadata.get("served", True)}
        unknown = [name for name in values if name not in by_api and name not in ignore]
        if unknown:
            raise SolverInputError(f"unknown option {unknown[0]!r}; options: "
                                   f"{', '.join((*by_api, *ignore))}",
                                   field=f"options.{unknown[0]}")
        return cls(**{by_api[name]: value for name, value in values.items()
                      if name in by_api and value is not None})


@dataclasses.dataclass(frozen=True)
class OrthonormalizeOptions(SolveOptions):
    """The options of the solves that can orthonormalize their frames (Sec. 4)."""

    orthonormalize: bool = option(
        False, "Second solve with the frames projected to rotations as soft targets (Sec. "
        "4). Defaults to true for `parameterize` (planar rotations keep the flattening "
        "closer to an isometry), false for the other operations.")
    orthonormal_weight: float = option(
        ORTHONORMAL_WEIGHT, "Weight of that second solve's rotation targets.",
        gt=0, le=MAX_WEIGHT)


@dataclasses.dataclass(frozen=True)
class ReconstructOptions(OrthonormalizeOptions):
    """Options of :func:`solver.reconstruct` (and, per blend value, of interpolate)."""

    integrability_tol: float = option(
        INTEGRABILITY_TOL, "Integrability tolerance (vertex defects and global holonomy, "
        "radians; translations relative to the mean edge length).", api_name="tolerance",
        gt=0)
    exact_shortcut: bool = option(
        True, "Without constraints, integrate the forms along spanning trees first and skip "
        "the factorization when that immersion already has zero energy (integrable forms; "
        "report.solve_path = tree-integration).")
    check_integrability: bool = option(
        True, "Include the integrability summary in the report (and skip the tree "
        "integration for forms that fail it).", served=False)
    cotan_floor: float = option(
        COTAN_FLOOR, "Lower threshold of cotangent weights (weighting `cotan`).",
        served=False)
    length_scale: float | None = option(
        None, "Lengths are divided by it before assembly; null: the mean edge length (1.0 "
        "reproduces the paper's raw-unit weighting).", served=False)
    linear_solver: LinearSolver = option(  # noqa: RUF009 - a field specifier
        "auto", "How Eq. 5's linear system is solved: `direct` factorizes it (sparse "
        "Cholesky); `iterative` runs conjugate gradients preconditioned by smoothed-"
        "aggregation multigrid (no factor: bounded memory on meshes of millions of faces; "
        "the answer agrees with the direct one to ~1e-8 relative); `auto` (default) is "
        "iterative where the factor would not fit in the memory available, and from 2 "
        "million faces (solver.linalg.iterative.LinearSolverRules). "
        "`report.linear_solver` says which ran, its iterations and final residual. The "
        "refinement's Gauss-Newton steps follow the choice (`iterative`: inexact steps by "
        "preconditioned CG, no factor; under `auto` also where only its own factor would not "
        "fit); `report.refinement.linear_solver` gives their CG iterations per step.")
    memory_budget: float | None = option(
        None, "Bytes the solve may use, by which `linear_solver=\"auto\"` chooses its path "
        "(solver.linalg.iterative.available_memory); null: the machine's available memory. "
        "The service sets it to FFS_MAX_REQUEST_MEMORY, the memory its admission priced the "
        "request in.", served=False, gt=0)


@dataclasses.dataclass(frozen=True)
class DeformOptions(OrthonormalizeOptions):
    """Options of :func:`solver.deform` and :class:`solver.Deformer`.

    Two defaults differ from the other operations, declared here: ``angle_weight`` is
    :data:`solver.refine.energy_weights.DEFORM_ANGLE_WEIGHT` (the targets are the rest forms:
    stiffer
    bending, smoother shapes), and a :class:`solver.Deformer` reads ``refine=None`` as off
    (an interactive client answers each drag's linear shape first and refines it after,
    :meth:`solver.Deformer.refine_last`); :func:`solver.deform` reads it as auto.
    ``linear_solver`` and ``memory_budget`` are :class:`ReconstructOptions`' (declared there):
    Eq. 5's system of the handle set (factorized once, or multigrid-preconditioned CG per
    drag) and the refinement's Gauss-Newton steps; not offered over HTTP.
    """

    angle_weight: float = redefault(SolveOptions, "angle_weight", DEFORM_ANGLE_WEIGHT)
    handle_weight: float = option(
        np.inf, "Weight of the handle positions; inf eliminates them exactly.", served=False)
    rotation_weight: float = option(
        np.inf, "Weight of the orientation handles; inf makes them hard.", served=False)
    # As reconstruct's, for the drags' Eq. 5 solves and the refinement's steps (library only:
    # the service prices deformations by the factorization, service.operations.ITERATIVE).
    linear_solver: LinearSolver = shared(  # noqa: RUF009 - a field specifier
        ReconstructOptions, "linear_solver", served=False)
    memory_budget: float | None = shared(ReconstructOptions, "memory_budget")


@dataclasses.dataclass(frozen=True)
class ParameterizeOptions(OrthonormalizeOptions):
    """Options of :func:`solver.parameterize`; ``orthonormalize`` defaults to True here."""

    orthonormalize: bool = redefault(OrthonormalizeOptions, "orthonormalize", True)
    area_weight: float = option(
        AREA_WEIGHT, "The planar refinement's weight of the relative signed-area residual "
        "(pushes flipped faces back).", served=False)
    seams: Literal["auto", "none"] = option(
        "auto", "auto: cut closed surfaces, handles, several parts and charts that flatten "
        "too distorted into charts along seams and pack them into the unit square (a mesh "
        "that flattens well as one chart keeps it); none: one chart per component, closed "
        "components refused.")
    max_chart_distortion: float = option(
        0.05, "The largest mean relative edge-length change a chart may keep (0.05 is 5%); "
        "a chart above it, or with a flipped face or overlapping itself, is split in two.",
        gt=0.0, le=10.0)
    crease_weight: float = option(
        4.0, "How much more a bent edge costs a seam's growth than a flat one (the dual "
        "graph's 1 + w (1 - cos dihedral), solver.mesh.charts).", served=False)


@dataclasses.dataclass(frozen=True)
class InterpolateOptions(SolveOptions):
    """Options of :func:`solver.interpolate` (each blend value is one reconstruction)."""


@dataclasses.dataclass(frozen=True)
class BlendOptions(SolveOptions):
    """Options of :func:`solver.blend`, :func:`solver.mean` and :func:`solver.transfer`
    (each row of weights is one nearest surface)."""

    sequence: bool = option(
        True, "Solve the rows as a sequence: each row after the first starts from the better "
        "of its neighbour's answer and its vertex blend and keeps the Gauss-Newton factor of "
        "the rows before (playback rate; rows whose weights pick one shape are reconstructed "
        "on their own). `false`: every row is an independent reconstruction.")
    align: bool = option(
        False, "Move each shape rigidly onto the first (Kabsch) before the vertex blends the "
        "rows are aligned to are formed: where the shapes sit then does not matter (a mean "
        "of poses scanned in different frames). The forms do not depend on it.")


__all__ = ["BlendOptions", "DeformOptions", "InterpolateOptions", "OrthonormalizeOptions",
           "ParameterizeOptions", "ReconstructOptions", "SolveOptions"]
