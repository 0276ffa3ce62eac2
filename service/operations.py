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
from service.api.decoding import (
    FORMS_ARRAYS,
    MESH_ARRAYS,
    PAIR_ARRAYS,
    STACK_ARRAYS,
    TRANSFER_ARRAYS,
    ArraySpecs,
    decode_raw,
)
from service.api.task import RawBody, TaskRequest, TaskResult
from service.worker import tasks
from service.worker.runtime import Progress, StageClock

STAGES_SOLVE: tuple[str, ...] = ("validate", "assemble", "factorize", "solve", "refine",
                                  "encode")
"""Progress stages of the operations that factorize and refine."""
STAGES_LIGHT: tuple[str, ...] = ("validate", "solve", "encode")
"""Progress stages of the operations that only compute."""
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

    @property
    def solves(self) -> bool:
        """Whether it factorizes (its requests' memory: :func:`service.backends.admission.
        request_cost`)."""
        return self.stages != STAGES_LIGHT

    @property
    def arrays(self) -> ArraySpecs:
        """The large arrays of the body (the ``source``'s)."""
        return ARRAYS_OF[self.source]


ARRAYS_OF: dict[str, ArraySpecs] = {"mesh": MESH_ARRAYS, "forms": FORMS_ARRAYS,
                                    "pair": PAIR_ARRAYS, "shapes": STACK_ARRAYS,
                                    "transfer": TRANSFER_ARRAYS}

OPERATIONS: dict[str, OperationSpec] = {spec.name: spec for spec in (
    OperationSpec(
        "forms", schemas.FormsRequest, schemas.FormsParams, documents.FormsResponse,
        "mesh", STAGES_LIGHT, False, tasks.forms_task,
        "Fundamental forms of a mesh",
        "Edge lengths and signed dihedral angles of a mesh. The result is a valid body for "
        "/v1/integrability and /v1/reconstruct. Meshes as they come: polygons are "
        "fan-triangulated; a non-manifold mesh (an edge of 3 or more faces, a vertex joining "
        "two fans, faces flipped against a neighbour) is cut into a manifold one and its "
        "forms carry `vertex_map` (the file vertex of each cut vertex); `placement` holds "
        "each connected part's pose, so /v1/reconstruct puts every part back in place "
        "(docs/service.md, Meshes as they come)."),
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
        "naming the worst vertices. A mesh file upload is reconstructed from its own forms. "
        "With `vertex_map` the answer is per file vertex (the mean of its copies, their "
        "spread in `report.input.cut`) on the file's triangles; with `placement` every "
        "unconstrained part is put where it was, without it the parts are laid side by side. "
        "Angles outside (-pi, pi] are wrapped (`report.input.wrapped_angles`).",
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
        "the change. A non-manifold mesh is deformed on its manifold cut (every copy of a "
        "handle vertex follows it) and answered per file vertex (`report.input.cut`); parts "
        "without handles stay where they are.", colors=("distortion",)),
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
        "the atlas as TEXCOORD_0. A non-manifold mesh is flattened on its manifold cut "
        "(`uv_vertex` names the file vertex of each uv index, `report.input.cut`)."),
    OperationSpec(
        "interpolate", schemas.InterpolateRequest, schemas.InterpolateParams,
        documents.InterpolateResponse, "pair", STAGES_LIGHT, True,
        tasks.interpolate_task, "Interpolate two meshes in form space",
        "Blends lengths and dihedral angles of two embeddings of the same faces and "
        "reconstructs for each t. glTF output needs a single t. Uploads use `file_a` and "
        "`file_b`.", files=("file_a", "file_b")),
    OperationSpec(
        "blend", schemas.BlendRequest, schemas.BlendParams, documents.BlendResponse,
        "shapes", STAGES_ROWS, True, tasks.blend_task,
        "Blend, average or extrapolate K meshes in form space",
        "K embeddings of the same faces (`shapes`) and rows of affine `weights` (or `t` for "
        "two shapes): lengths blend in log space, dihedral angles linearly (unwrapped "
        "against the first shape), and each row is the nearest surface to its blended "
        "forms, aligned rigidly to the row's vertex blend. Rows are solved in order, each "
        "from its neighbour's answer with a kept factorization (`options.sequence`); a job "
        "reports progress per row. GLB / glTF output is one animated file: the first shape "
        "as the mesh, each row a morph target, and an animation playing them at `times`. "
        "Uploads use `file_a` and `file_b` (two shapes).", files=("file_a", "file_b")),
    OperationSpec(
        "transfer", schemas.TransferRequest, schemas.TransferParams,
        documents.TransferResponse, "transfer", STAGES_ROWS, True, tasks.transfer_task,
        "Transfer a deformation to another mesh of the same connectivity",
        "The target's forms plus the source's change (lengths stretched by the source's "
        "ratios, dihedral angles bent by its change), then the nearest surface, aligned to "
        "the vertex transfer `target + source_deformed - source`. Uploads use "
        "`file_source`, `file_source_deformed` and `file_target`.",
        files=("file_source", "file_source_deformed", "file_target")),
    OperationSpec(
        "mesh", schemas.MeshRequest, schemas.MeshParams, documents.MeshResponse,
        "mesh", STAGES_LIGHT, True, tasks.mesh_task, "Read or convert a mesh",
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
    operation's own."""
    clock = StageClock(progress)
    if isinstance(request.source, RawBody):
        clock("validate", 0.0)
        request = decode_raw(OPERATIONS[request.operation], request)
    task = tasks.DEBUG_TASKS.get(request.task_name) or OPERATIONS[request.task_name].task
    result: TaskResult = task(request, clock)
    result.timings = clock.finish()
    return result
