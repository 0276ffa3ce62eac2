"""The operation registry: every fact about each of the eight operations, in one place.

An :class:`OperationSpec` says what an operation takes (its JSON request model, the params
model of its non-array fields, its large arrays and what they form, its upload fields),
what it answers (response model, whether the result is a mesh, which vertex colours it can
add), how it reports progress (stages) and which worker function computes it. The routes,
the request parsing, the OpenAPI document, the jobs and the workers all read
:data:`OPERATIONS`; adding an operation means a spec here and its task function.
:func:`run` is how every worker runs one.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

from pydantic import BaseModel

from service.api import documents, schemas
from service.api.decoding import FORMS_ARRAYS, MESH_ARRAYS, PAIR_ARRAYS, ArraySpecs, decode_raw
from service.api.task import RawBody, TaskRequest, TaskResult
from service.worker import tasks
from service.worker.runtime import Progress, StageClock

STAGES_SOLVE: tuple[str, ...] = ("validate", "assemble", "factorize", "solve", "refine",
                                  "encode")
"""Progress stages of the operations that factorize and refine."""
STAGES_LIGHT: tuple[str, ...] = ("validate", "solve", "encode")
"""Progress stages of the operations that only compute."""
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
    source: Literal["mesh", "forms", "pair"]
    stages: tuple[str, ...]
    mesh_result: bool
    task: Callable[..., Any]
    summary: str
    description: str
    colors: tuple[str, ...] = ()
    files: tuple[str, ...] = ("file",)

    @property
    def arrays(self) -> ArraySpecs:
        """The large arrays of the body (the ``source``'s)."""
        return ARRAYS_OF[self.source]


ARRAYS_OF: dict[str, ArraySpecs] = {"mesh": MESH_ARRAYS, "forms": FORMS_ARRAYS,
                                    "pair": PAIR_ARRAYS}

OPERATIONS: dict[str, OperationSpec] = {spec.name: spec for spec in (
    OperationSpec(
        "forms", schemas.FormsRequest, schemas.FormsParams, documents.FormsResponse,
        "mesh", STAGES_LIGHT, False, tasks.forms_task,
        "Fundamental forms of a mesh",
        "Edge lengths and signed dihedral angles of a mesh. The result is a valid body for "
        "/v1/integrability and /v1/reconstruct."),
    OperationSpec(
        "integrability", schemas.IntegrabilityRequest, schemas.IntegrabilityParams,
        documents.IntegrabilityResponse, "forms", STAGES_LIGHT, False,
        tasks.integrability_task, "Integrability report",
        "Checks whether lengths and angles come from a surface: per-vertex holonomy defects "
        "(Gauss and Codazzi parts), triangle inequality, topology and the global holonomy "
        "along homology generators. A mesh file upload is checked through its own forms."),
    OperationSpec(
        "reconstruct", schemas.ReconstructRequest, schemas.ReconstructParams,
        documents.MeshResponse, "forms", STAGES_SOLVE, True,
        tasks.reconstruct_task, "Reconstruct a mesh from its forms",
        "One sparse linear solve (Eq. 5) with optional position and frame constraints. The "
        "integrability condition is always checked first and summarized in "
        "`report.integrability`; with `options.require_integrable` a failed check is a 422 "
        "naming the worst vertices. A mesh file upload is reconstructed from its own forms.",
        colors=("defect",)),
    OperationSpec(
        "reconstruct/vjp", schemas.ReconstructVjpRequest, schemas.ReconstructVjpParams,
        schemas.ReconstructVjpResponse, "forms", STAGES_SOLVE, False,
        tasks.reconstruct_vjp_task, "Gradients of a reconstruction (vector-Jacobian product)",
        "Reconstructs like /v1/reconstruct and pulls the `cotangent` of the vertices (the "
        "gradient of a loss with respect to them) back to the lengths, angles and "
        "constraint targets: the service as a remote differentiable layer. With "
        "`options.refine: false` the linear answer is differentiated (adjoint method), "
        "otherwise the refined one (implicit differentiation at its optimum, exact "
        "Hessian); the gauge is the anchor of the answer (docs/differentiable.md)."),
    OperationSpec(
        "deform", schemas.DeformRequest, schemas.DeformParams, documents.MeshResponse,
        "mesh", STAGES_SOLVE, True, tasks.deform_task,
        "Deform a mesh with handles",
        "Moves handle vertices (and optionally rotates groups of face frames) while "
        "preserving the fundamental forms as well as possible; `report.distortion` measures "
        "the change.", colors=("distortion",)),
    OperationSpec(
        "parameterize", schemas.ParameterizeRequest, schemas.ParameterizeParams,
        documents.ParameterizeResponse, "mesh", STAGES_FLATTEN, True,
        tasks.parameterize_task, "Flatten a mesh (seams, charts and an atlas where needed)",
        "Planar coordinates by reconstructing with all dihedral angles 0, per chart: a mesh "
        "that does not flatten well as one chart (closed, handles, several parts, too "
        "distorted) is cut along seams into charts packed into the unit square "
        "(`texcoords`, `uv_faces`, `uv_vertex`, `face_chart`; `report.atlas`, "
        "`report.warnings`). With `options.seams` = `none` closed meshes are a 422 "
        "(unsupported-topology). glTF output is the 3D mesh, seam vertices duplicated, with "
        "the atlas as TEXCOORD_0."),
    OperationSpec(
        "interpolate", schemas.InterpolateRequest, schemas.InterpolateParams,
        documents.InterpolateResponse, "pair", STAGES_LIGHT, True,
        tasks.interpolate_task, "Interpolate two meshes in form space",
        "Blends lengths and dihedral angles of two embeddings of the same faces and "
        "reconstructs for each t. glTF output needs a single t. Uploads use `file_a` and "
        "`file_b`.", files=("file_a", "file_b")),
    OperationSpec(
        "mesh", schemas.MeshRequest, schemas.MeshParams, documents.MeshResponse,
        "mesh", STAGES_LIGHT, True, tasks.mesh_task, "Read or convert a mesh",
        "Reads a mesh file (OBJ, PLY, OFF, STL, GLB) or a JSON mesh, checks its connectivity "
        "like the other operations do, and returns it in the negotiated format: JSON "
        "`vertices` (file order) and `faces` with a `report` (counts, bounds, mean edge "
        "length), or GLB / glTF. The web page uses it to open uploads and to download the "
        "current mesh."),
)}
"""Every operation, by name, in the order the API documents them."""


def run(request: TaskRequest, progress: Progress) -> TaskResult:
    """Run ``request`` with stage timing: the entry point of every worker.

    A raw body (:class:`~service.api.task.RawBody`) is parsed and validated first, as part
    of the ``validate`` stage; ``request.task`` names a test-only task instead of the
    operation's own."""
    clock = StageClock(progress)
    if isinstance(request.source, RawBody):
        clock("validate", 0.0)
        request = decode_raw(OPERATIONS[request.operation], request)
    task = tasks.DEBUG_TASKS.get(request.task_name) or OPERATIONS[request.task_name].task
    result: TaskResult = task(request, clock)
    result.timings = clock.finish()
    return result
