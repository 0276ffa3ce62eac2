"""What crosses the process boundary: a :class:`TaskRequest` in, a :class:`TaskResult` out.

The HTTP edge builds one immutable request per operation call (arrays already numpy, or the
raw body when the worker is to parse it); a backend carries it to a worker process (a local
pool worker, or a Dask worker) unchanged; :func:`service.operations.run` answers with a
result or a failure dict. Everything here is a frozen dataclass of numpy arrays, bytes and
JSON-able values, importable at top level, so it pickles under ``spawn``/``forkserver`` and
through Dask.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Literal, TypeVar

import numpy as np

from service.api.budgets import TIME_POLICY
from solver.options import DeformOptions, SolveOptions

Format = Literal["json", "glb", "gltf"]
Options = TypeVar("Options", bound=SolveOptions)
SERVICE_OPTIONS: tuple[str, ...] = ("require_integrable",)
"""Request options the service acts on itself (not the solver's)."""


@dataclass(frozen=True)
class MeshArrays:
    """A mesh sent as arrays: ``vertices`` (n, 3) float64, ``faces`` (m, 3) int64."""

    vertices: np.ndarray
    faces: np.ndarray


@dataclass(frozen=True)
class FormsArrays:
    """Fundamental forms sent as arrays: ``faces`` (m, 3), ``edges`` (E, 2) int64,
    ``lengths`` and ``angles`` (E,) float64 aligned with ``edges``."""

    faces: np.ndarray
    edges: np.ndarray
    lengths: np.ndarray
    angles: np.ndarray
    vertex_map: np.ndarray | None = None
    """The cut's file vertex of each vertex (forms of a non-manifold mesh), or None."""
    placement: Any = None
    """The components' placement (:class:`solver.mesh.placement.Placement` or its dict), or None."""
    weld_map: np.ndarray | None = None
    """The file vertex each file vertex was welded into (solver.mesh.weld), or None."""


@dataclass(frozen=True)
class MeshPair:
    """Two embeddings of one connectivity (``interpolate``)."""

    vertices_a: np.ndarray
    vertices_b: np.ndarray
    faces: np.ndarray


@dataclass(frozen=True)
class MeshStack:
    """K embeddings of one connectivity (``blend``): ``shapes`` (K, n, 3) float64,
    ``faces`` (m, 3) int64."""

    shapes: np.ndarray
    faces: np.ndarray


@dataclass(frozen=True)
class MeshTriple:
    """A deformation and the mesh it is transferred to (``transfer``): ``source``,
    ``source_deformed`` and ``target`` (n, 3) float64 of one connectivity ``faces``."""

    source: np.ndarray
    source_deformed: np.ndarray
    target: np.ndarray
    faces: np.ndarray


@dataclass(frozen=True)
class MeshFile:
    """An uploaded mesh file: its bytes and the name (or media type) that says its format."""

    data: bytes
    filename: str
    field: str = "file"


@dataclass(frozen=True)
class RawBody:
    """A JSON or binary (``application/vnd.ffs.arrays``) body the worker parses and
    validates itself, so that the main process never holds the parsed arrays."""

    kind: Literal["json", "binary"]
    body: bytes | bytearray


MeshFiles = tuple[MeshFile, ...]
"""Several uploaded mesh files (``interpolate``, ``blend``: ``file_a``, ``file_b``;
``transfer``: ``file_source``, ``file_source_deformed``, ``file_target``)."""
Source = (MeshArrays | FormsArrays | MeshPair | MeshStack | MeshTriple | MeshFile | MeshFiles
          | RawBody | None)
ARRAY_SOURCES: dict[str, type] = {"mesh": MeshArrays, "forms": FormsArrays, "pair": MeshPair,
                                  "shapes": MeshStack, "transfer": MeshTriple}
"""The array source of each operation's ``source`` kind (:mod:`service.operations`)."""


@dataclass(frozen=True)
class Limits:
    """Size limits of one request (``FFS_MAX_VERTICES``, ``FFS_MAX_FACES``,
    ``FFS_MAX_BLEND_STEPS``, ``FFS_MAX_BLEND_VERTICES``: rows x vertices of a blend)."""

    max_vertices: int
    max_faces: int
    max_blend_steps: int = 1024
    max_blend_vertices: int = 4_000_000
    max_memory: int | None = None
    """FFS_MAX_REQUEST_MEMORY when it, not FFS_MAX_FACES, sets ``max_faces`` (the most
    faces the operation's predicted peak fits in; named by the 413)."""
    max_sync_faces: int | None = None
    """A synchronous request's most faces: those whose first answer is predicted within
    ``sync_seconds`` (:func:`service.backends.admission.sync_faces_within`); None for a job
    or a session."""
    sync_seconds: float | None = None
    """The seconds a synchronous request's solver has (FFS_REQUEST_TIMEOUT less the margin
    for encoding the answer)."""
    request_memory: int | None = None
    """FFS_MAX_REQUEST_MEMORY: the solver's ``memory_budget`` (its ``linear_solver="auto"``
    chooses the path within it, as admission priced the request)."""
    max_direct_faces: int | None = None
    """Of an operation with an iterative path: the most faces its factorization fits
    (at most FFS_MAX_FACES; beyond them, up to ``max_faces``, it solves iteratively); None
    for the others."""
    linear: Limits | None = None
    """The limits of the operation's linear answer (``options.refine: false``) where they
    differ (``reconstruct``: its iterative linear answer takes less memory per face)."""

    def answering(self, params: dict[str, Any]) -> Limits:
        """The limits of a request with these (dumped) ``params``: :attr:`linear` for a
        linear answer (``options.refine`` false), these otherwise."""
        refine = (params.get("options") or {}).get("refine")
        return self.linear if refine is False and self.linear is not None else self


@dataclass(frozen=True)
class Output:
    """How the result is wanted: ``format``; ``color`` (a vertex colour field added to the
    body); ``compute`` (colour fields to keep for later, jobs); ``keep`` (keep the mesh
    arrays next to the body, so that a job's result can be re-encoded)."""

    format: Format = "json"
    color: str | None = None
    compute: tuple[str, ...] = ()
    keep: bool = False

    def wants(self, field_name: str) -> bool:
        """Whether the colour field ``field_name`` must be computed."""
        return self.color == field_name or field_name in self.compute


@dataclass(frozen=True)
class TaskRequest:
    """One call of an operation.

    Attributes:
        operation: the API operation (a key of :data:`service.operations.OPERATIONS`).
        source: the input mesh, forms or files; a :class:`RawBody` until the worker parses
            it; ``None`` for the test-only debug tasks.
        params: the operation's params model, dumped (``{}`` until a raw body is parsed).
        limits: the vertex and face limits.
        backend: the default factorization backend (``FFS_SOLVER_BACKEND``), used when
            ``options.solver`` (the solver's ``backend``) is not given.
        output: the wanted result.
        task: the worker function to run when it is not the operation's own (test-only
            ``debug.*`` tasks, which report the operation's stages).
        deadline: ``time.time()`` by which the solver must have returned (the request's or
            job's timeout less the encoding margin of
            :data:`~service.api.budgets.TIME_POLICY`; see :meth:`with_deadline`), or None.
    """

    operation: str
    source: Source
    params: dict[str, Any] = field(default_factory=dict)
    limits: Limits = Limits(10**9, 10**9)
    backend: str = "auto"
    output: Output = Output()
    task: str | None = None
    deadline: float | None = None

    @property
    def task_name(self) -> str:
        return self.task or self.operation

    def solve_options(self, kind: type[Options]) -> Options:
        """The solver's options of this request (``kind``, e.g.
        :class:`solver.options.ReconstructOptions`), in one call: the params' ``options``
        (HTTP names: ``solver`` is the backend), :attr:`backend` where none was chosen, and
        :meth:`solver_budget` as ``max_seconds``; FFS_MAX_REQUEST_MEMORY as
        ``memory_budget`` where the options have it (:attr:`Limits.request_memory`)."""
        options = kind.from_api(self.params.get("options") or {}, ignore=SERVICE_OPTIONS)
        options = options.replace(backend=options.backend or self.backend,
                                  max_seconds=self.solver_budget())
        if self.limits.request_memory is not None and "memory_budget" in kind.names():
            options = options.replace(memory_budget=float(self.limits.request_memory))
        return options

    def with_output(self, output: Output) -> TaskRequest:
        return replace(self, output=output)

    def with_deadline(self, timeout: float) -> TaskRequest:
        """This request with a deadline ``timeout`` seconds from now, less the margin its
        answer needs to be encoded and sent (:meth:`TimePolicy.deadline
        <service.api.budgets.TimePolicy.deadline>`)."""
        return replace(self, deadline=TIME_POLICY.deadline(timeout))

    def solver_budget(self) -> float | None:
        """The ``max_seconds`` of the solver call, measured from now
        (:meth:`TimePolicy.solver_budget <service.api.budgets.TimePolicy.solver_budget>` of
        ``options.max_seconds`` and :attr:`deadline`); None: no limit."""
        explicit = (self.params.get("options") or {}).get("max_seconds")
        return TIME_POLICY.solver_budget(explicit, self.deadline).seconds  # from now


@dataclass
class TaskResult:
    """A finished task: the response ``body`` in ``media_type``; with ``output.keep`` also
    the ``mesh`` (vertices, faces) and the per-vertex ``colors`` for re-encoding; the
    wall time of each stage in ``timings`` (seconds)."""

    media_type: str
    body: bytes
    mesh: tuple[np.ndarray, np.ndarray] | None = None
    colors: dict[str, np.ndarray] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    encoded: dict[str, bytes] = field(default_factory=dict)
    """Bodies of other formats computed with the result (``output.keep``), for results that
    are not one mesh: ``blend``'s animated GLB / glTF (format -> bytes)."""
    texcoords: np.ndarray | None = None
    """(n, 2) uv of ``mesh``'s vertices (a flattening's atlas), written as TEXCOORD_0."""


@dataclass(frozen=True)
class SessionSpec:
    """What a deformation session is built from (``POST /v1/sessions``).

    Attributes:
        vertices: (n, 3) float64 rest positions; ``faces`` (m, 3) int64.
        handles: (h,) int64 handle vertices, in the order of every drag's targets.
        rotations: one (k,) int64 face-index array per rotation group.
        roi: (r,) int64 vertices that may move, or ``None`` (all).
        options: the request's ``options`` (``DeformOptions``, dumped; HTTP names).
        backend: the default factorization backend, used when ``options.solver`` is unset.
        memory_budget: FFS_MAX_REQUEST_MEMORY, the memory the session was admitted in
            (:attr:`Limits.request_memory`), or None (the machine's available memory).
    """

    vertices: np.ndarray
    faces: np.ndarray
    handles: np.ndarray
    rotations: tuple[np.ndarray, ...] = ()
    roi: np.ndarray | None = None
    options: dict[str, Any] = field(default_factory=dict)
    backend: str = "auto"
    memory_budget: float | None = None

    def deform_options(self) -> DeformOptions:
        """The solver's options of the session, in one call (:meth:`TaskRequest.solve_options`
        without a budget: each drag's refinement has its own): ``memory_budget`` is the
        memory the session was admitted in, so that ``linear_solver="auto"`` chooses by it
        as a request's solve does, not by the machine's free memory of the moment."""
        options = DeformOptions.from_api(self.options)
        return options.replace(backend=options.backend or self.backend,
                               memory_budget=self.memory_budget)
