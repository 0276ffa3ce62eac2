"""The operation registry: every fact about each of the eight operations, in one place.

An :class:`OperationSpec` says what an operation takes (its JSON request model, the params
model of its non-array fields, its large arrays and what they form, its upload fields),
what it answers (response model, whether the result is a mesh, which vertex colours it can
add), how it reports progress (stages) and which worker function computes it. The routes,
the request parsing, the OpenAPI document, the jobs and the workers all read
:data:`OPERATIONS`; adding an operation means a spec here and its task function (its
models ``schemas.<Stem>Request`` / ``<Stem>Params`` and ``tasks.<name>_task`` are found by
the operation's name).
:func:`run` is how every worker runs one.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

from pydantic import BaseModel

from service.api import documents, schemas
from service.api.decoding import (
    FORMS_ARRAYS,
    MAX_SHAPES,
    MESH_ARRAYS,
    PAIR_ARRAYS,
    STACK_ARRAYS,
    TRANSFER_ARRAYS,
    ArraySpecs,
    decode_raw,
)
from service.api.task import RawBody, TaskRequest, TaskResult
from service.worker import tasks
from service.worker.runtime import Progress, ProgressThrottle, StageClock

STAGES_SOLVE: tuple[str, ...] = ("validate", "assemble", "factorize", "solve", "refine",
                                  "encode")
"""Progress stages of the operations that factorize and refine."""
STAGES_LIGHT: tuple[str, ...] = ("validate", "solve", "encode")
"""Progress stages of the operations that only compute."""
COMPUTE_ONLY: frozenset[str] = frozenset({"forms", "integrability", "mesh"})
"""The operations that factorize nothing (their memory grows like the mesh's arrays);
``interpolate`` has light stages but reconstructs each blend."""
ITERATIVE: frozenset[str] = frozenset({"reconstruct"})
"""The operations whose solver chooses between a factorization and the iterative path by the
request's memory (the others factorize)."""
STAGES_ROWS: tuple[str, ...] = ("validate", "rows", "encode")
"""Progress stages of the shape-space operations: ``rows`` goes from 0 to 1 as the rows of
weights are solved, in order (:func:`solver.blend`)."""
STAGES_FLATTEN: tuple[str, ...] = ("validate", "assemble", "factorize", "solve", "refine",
                                   "charts", "pack", "encode")
"""Progress stages of ``parameterize``: a first single chart, then charts (fraction of the
faces placed, chart by chart) and their packing where one chart does not do."""


@dataclass(frozen=True)
class OperationSpec:
    """One operation (``POST /v1/{name}``; ``{"operation": name}`` in a job).

    Attributes:
        name: the operation's name.
        request: model of the JSON body (documents it; the arrays are checked with numpy).
        params: model of the fields besides the large arrays (the other multipart fields).
        response: model of the JSON result.
        source: what the large arrays of the body form (``mesh``: vertices + faces,
            ``forms``: faces, edges, lengths, angles, ``pair``: two embeddings of one
            connectivity); :attr:`arrays` are those arrays.
        files: upload field names of the multipart form.
        file_list: the one name in ``files`` is given once per mesh (1 to
            :data:`service.api.decoding.MAX_SHAPES` parts, in order: ``blend``'s ``shapes``).
        stages: progress stages, in order.
        mesh_result: the result is one mesh (glTF can be negotiated).
        colors: vertex colour fields it can add (``?color=``).
        task: the worker function ``task(request, progress) -> TaskResult``.
        summary, description: the OpenAPI text.
    """

    name: str
    request: type[BaseModel]
    params: type[BaseModel]
    response: type[BaseModel]
    source: Literal["mesh", "forms", "pair", "shapes", "transfer"]
    stages: tuple[str, ...]
    mesh_result: bool
    task: Callable[..., Any]
    summary: str
    description: str
    colors: tuple[str, ...] = ()
    files: tuple[str, ...] = ("file",)
    file_list: bool = False

    @property
    def solves(self) -> bool:
        """Whether it factorizes (its requests' memory: :func:`service.backends.admission.
        pricing`): every operation but :data:`COMPUTE_ONLY`."""
        return self.name not in COMPUTE_ONLY

    @property
    def iterative(self) -> bool:
        """Whether its solver may take the iterative path (``options.linear_solver``,
        chosen within FFS_MAX_REQUEST_MEMORY; its requests are priced by that path:
        :class:`service.backends.admission.Pricing`): :data:`ITERATIVE`."""
        return self.name in ITERATIVE

    @property
    def arrays(self) -> ArraySpecs:
        """The large arrays of the body (the ``source``'s)."""
        return ARRAYS_OF[self.source]


ARRAYS_OF: dict[str, ArraySpecs] = {"mesh": MESH_ARRAYS, "forms": FORMS_ARRAYS,
                                    "pair": PAIR_ARRAYS, "shapes": STACK_ARRAYS,
                                    "transfer": TRANSFER_ARRAYS}

def _operation(name: str, response: type[BaseModel],
               source: Literal["mesh", "forms", "pair", "shapes", "transfer"],
               stages: tuple[str, ...], mesh_result: bool, summary: str, description: str,
               **more: Any) -> OperationSpec:
    """The spec of operation ``name``, whose request and params models and worker task are
    named after it: ``reconstruct/vjp`` -> ``schemas.ReconstructVjpRequest``,
    ``schemas.ReconstructVjpParams``, ``tasks.reconstruct_vjp_task`` (a missing one fails
    the import). ``more``: the optional :class:`OperationSpec` fields."""
    stem = "".join(part.capitalize() for part in name.replace("_", "/").split("/"))
    return OperationSpec(name, getattr(schemas, f"{stem}Request"),
                         getattr(schemas, f"{stem}Params"), response, source, stages,
                         mesh_result, getattr(tasks, f"{name.replace('/', '_')}_task"),
                         summary, description, **more)


OPERATIONS: dict[str, OperationSpec] = {spec.name: spec for spec in (
    _operation(
        "forms", documents.FormsResponse, "mesh", STAGES_LIGHT, False,
        "Fundamental forms of a mesh",
        "Edge lengths and signed dihedral angles of a mesh. The result is a valid body for "
        "/v1/integrability and /v1/reconstruct. Meshes as they come: polygons are "
        "fan-triangulated; a non-manifold mesh (an edge of 3 or more faces, a vertex joining "
        "two fans, faces flipped against a neighbour) is cut into a manifold one and its "
        "forms carry `vertex_map` (the file vertex of each cut vertex); vertices joined by a "
        "zero-length edge are welded (`weld_map`) and the faces that collapse dropped "
        "(`dropped_faces`); `placement` holds "
        "each connected part's pose, so /v1/reconstruct puts every part back in place "
        "(docs/service.md, Meshes as they come)."),
    _operation(
        "integrability", documents.IntegrabilityResponse, "forms", STAGES_LIGHT, False,
        "Integrability report",
        "Checks whether lengths and angles come from a surface: per-vertex holonomy defects "
        "(Gauss and Codazzi parts), triangle inequality, topology and the global holonomy "
        "along homology generators. A mesh file upload is checked through its own forms."),
    _operation(
        "reconstruct", documents.MeshResponse, "forms", STAGES_SOLVE, True,
        "Reconstruct a mesh from its forms",
        "One sparse linear solve (Eq. 5) with optional position and frame constraints. The "
        "integrability condition is always checked first and summarized in "
        "`report.integrability`; with `options.require_integrable` a failed check is a 422 "
        "naming the worst vertices. A mesh file upload is reconstructed from its own forms. "
        "With `vertex_map` the answer is per file vertex (the mean of its copies, their "
        "spread in `report.input.cut`; with `weld_map` a welded vertex at its "
        "representative's position) on the file's triangles; with `placement` every "
        "unconstrained part is put where it was, without it the parts are laid side by side. "
        "Angles outside (-pi, pi] are wrapped (`report.input.wrapped_angles`).",
        colors=("defect",)),
    _operation(
        "reconstruct/vjp", schemas.ReconstructVjpResponse, "forms", STAGES_SOLVE, False,
        "Gradients of a reconstruction (vector-Jacobian product)",
        "Reconstructs like /v1/reconstruct and pulls the `cotangent` of the vertices (the "
        "gradient of a loss with respect to them) back to the lengths, angles and "
        "constraint targets: the service as a remote differentiable layer. With "
        "`options.refine: false` the linear answer is differentiated (adjoint method), "
        "otherwise the refined one (implicit differentiation at its optimum, exact "
        "Hessian); the gauge is the anchor of the answer (docs/differentiable.md). The forms "
        "of a real file (`vertex_map`, `weld_map`, `placement` from /v1/forms) are taken as "
        "/v1/reconstruct takes them: the answer and the `cotangent` are per file vertex, "
        "on the file's triangles."),
    _operation(
        "deform", documents.MeshResponse, "mesh", STAGES_SOLVE, True,
        "Deform a mesh with handles",
        "Moves handle vertices (and optionally rotates groups of face frames) while "
        "preserving the fundamental forms as well as possible; `report.distortion` measures "
        "the change. A non-manifold mesh is deformed on its manifold cut (every copy of a "
        "handle vertex follows it) and answered per file vertex (`report.input.cut`); parts "
        "without handles stay where they are.", colors=("distortion",)),
    _operation(
        "parameterize", documents.ParameterizeResponse, "mesh", STAGES_FLATTEN, True,
        "Flatten a mesh (seams, charts and an atlas where needed)",
        "Planar coordinates by reconstructing with all dihedral angles 0, per chart: a mesh "
        "that does not flatten well as one chart (closed, handles, several parts, too "
        "distorted) is cut along seams into charts packed into the unit square "
        "(`texcoords`, `uv_faces`, `uv_vertex`, `face_chart`; `report.atlas`, "
        "`report.warnings`). With `options.seams` = `none` closed meshes are a 422 "
        "(unsupported-topology). glTF output is the 3D mesh, seam vertices duplicated, with "
        "the atlas as TEXCOORD_0. A non-manifold mesh is flattened on its manifold cut "
        "(`uv_vertex` names the file vertex of each uv index, `report.input.cut`)."),
    _operation(
        "interpolate", documents.InterpolateResponse, "pair", STAGES_LIGHT, True,
        "Interpolate two meshes in form space",
        "Blends lengths and dihedral angles of two embeddings of the same faces and "
        "reconstructs for each t. glTF output needs a single t. Uploads use `file_a` and "
        "`file_b`.", files=("file_a", "file_b")),
    _operation(
        "blend", documents.BlendResponse, "shapes", STAGES_ROWS, True,
        "Blend, average or extrapolate K meshes in form space",
        "K embeddings of the same faces (`shapes`) and rows of affine `weights` (or `t` for "
        "two shapes): lengths blend in log space, dihedral angles linearly (unwrapped "
        "against the first shape), and each row is the nearest surface to its blended "
        "forms, aligned rigidly to the row's vertex blend. Rows are solved in order, each "
        "from its neighbour's answer with a kept factorization (`options.sequence`); a job "
        "reports progress per row. GLB / glTF output is one animated file: the first shape "
        "as the mesh, each row a morph target, and an animation playing them at `times`. "
        "Uploads give one `shapes` part per mesh file, in order (1 to "
        f"{MAX_SHAPES} files of the same faces). Rows x vertices are bounded by "
        "FFS_MAX_BLEND_VERTICES (413 `blend-too-large`).", files=("shapes",), file_list=True),
    _operation(
        "transfer", documents.TransferResponse, "transfer", STAGES_ROWS, True,
        "Transfer a deformation to another mesh of the same connectivity",
        "The target's forms plus the source's change (lengths stretched by the source's "
        "ratios, dihedral angles bent by its change), then the nearest surface, aligned to "
        "the vertex transfer `target + source_deformed - source`. Uploads use "
        "`file_source`, `file_source_deformed` and `file_target`.",
        files=("file_source", "file_source_deformed", "file_target")),
    _operation(
        "mesh", documents.MeshResponse, "mesh", STAGES_LIGHT, True,
        "Read or convert a mesh",
        "Reads a mesh file (OBJ, PLY, OFF, STL, GLB) or a JSON mesh, checks its connectivity "
        "like the other operations do (a non-manifold mesh's cut in `report.input.cut`, "
        "triangulated polygons in `report.input`), and returns it in the negotiated format: JSON "
        "`vertices` (file order) and `faces` with a `report` (counts, bounds, mean edge "
        "length), or GLB / glTF. The web page uses it to open uploads and to download the "
        "current mesh."),
)}
"""Every operation, by name, in the order the API documents them."""


def run(request: TaskRequest, progress: Progress) -> TaskResult:
    """Run ``request`` with stage timing: the entry point of every worker.

    A raw body (:class:`~service.api.task.RawBody`) is parsed and validated first, as part
    of the ``validate`` stage; ``request.task`` names a test-only task instead of the
    operation's own. ``progress`` gets the task's reports through a
    :class:`~service.worker.runtime.ProgressThrottle`, whichever backend's it is: at most 5
    a second, the first and the last always."""
    throttle = ProgressThrottle(progress)
    clock = StageClock(throttle)
    try:
        if isinstance(request.source, RawBody):
            clock("validate", 0.0)
            request = decode_raw(OPERATIONS[request.operation], request)
        task = tasks.DEBUG_TASKS.get(request.task_name) or OPERATIONS[request.task_name].task
        result: TaskResult = task(request, clock)
    finally:
        throttle.flush()  # the last report, before the result or the failure goes out
    result.timings = clock.finish()
    return result
