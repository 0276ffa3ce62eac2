"""Pydantic v2 models of the API's request bodies (the responses: :mod:`service.api.documents`).

Request models reject NaN and infinities at the schema (``allow_inf_nan=False``) and unknown
fields (``extra="forbid"``). Large arrays are typed as lists of fixed-size tuples, which
pydantic-core validates in Rust; routes turn them into numpy arrays once. Every model carries
an example (``json_schema_extra``) that the OpenAPI document and the docs page show; the
request examples are valid requests (a test posts each one).

Request models for the multipart upload form are split into a *mesh* part (taken from the
uploaded file) and a *params* part (the other form fields); the operation registry
(:data:`service.operations.OPERATIONS`) names both of each operation.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, create_model, model_validator

from solver import options as solver_options
from solver.options import MAX_WEIGHT
from solver.refine.stopping import StopReason, describe_stop_reasons
from solver.shape_space import MAX_SHAPES

# ---------------------------------------------------------------------------- examples

_V = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.5, 0.5, 0.5]]
_F = [[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]]
_E = [[0, 1], [0, 3], [0, 4], [1, 2], [1, 4], [2, 3], [2, 4], [3, 4]]
_S = 0.8660254037844386  # slanted edge length of the example pyramid
_A = 1.0471975511965979  # its dihedral angle (pi / 3)
_L = [1.0, 1.0, _S, 1.0, _S, 1.0, _S, _S]
_ANG = [0.0, 0.0, _A, 0.0, _A, 0.0, _A, _A]
_V_UP = [*_V[:4], [0.5, 0.5, 0.8]]
EXAMPLE_MESH: dict[str, Any] = {"vertices": _V, "faces": _F}
EXAMPLE_FORMS: dict[str, Any] = {"faces": _F, "edges": _E, "lengths": _L, "angles": _ANG}
_IDENTITY = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]

Operation = Literal["reconstruct", "deform", "parameterize", "integrability", "forms",
                    "interpolate", "mesh", "reconstruct/vjp", "blend", "transfer"]
ColorField = Literal["defect", "distortion"]
JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
StopReasonName = Literal[*(reason.value for reason in StopReason)]  # type: ignore[valid-type]
"""A refinement report's ``stop_reason`` (:class:`solver.refine.stopping.StopReason`)."""
STOP_REASONS_TEXT = describe_stop_reasons()
"""Every stop reason and its meaning, in words."""

MAX_MAGNITUDE = 1e60
"""Largest accepted |coordinate| or length (Heron's formula takes 4th powers of lengths)."""
MAX_INDEX = 2**31 - 1

Real = Annotated[float, Field(ge=-MAX_MAGNITUDE, le=MAX_MAGNITUDE)]
Weight = Annotated[float, Field(gt=0, le=MAX_WEIGHT)]
Index = Annotated[int, Field(ge=0, le=MAX_INDEX)]
# Fixed-length rows are lists with a length (not tuples): the same rule, and a JSON schema
# (`items` + `minItems`/`maxItems`) that every OpenAPI tool reads (`prefixItems` is 3.1-only).
Vec3 = Annotated[list[Real], Field(min_length=3, max_length=3)]
Tri = Annotated[list[Index], Field(min_length=3, max_length=3)]
Pair = Annotated[list[Index], Field(min_length=2, max_length=2)]
Mat3 = Annotated[list[Vec3], Field(min_length=3, max_length=3)]


BUDGET_NOTE = (
    " A budget that runs out is a 200, not a 504. The service also stops the refinement in "
    "time for FFS_REQUEST_TIMEOUT (synchronous requests) or FFS_JOB_TIMEOUT (jobs), less a "
    "margin for encoding; the smaller budget applies.")
SESSION_REFINE_NOTE = (
    " In a session (`POST /v1/sessions`) `true` makes drags progressive (the linear shape at "
    "once, the refined one when ready: docs/service.md); `null` and `false` answer linear "
    "shapes only.")


class ApiModel(BaseModel):
    """Base of the request models: finite floats only, unknown fields rejected, and strict
    types as the schema says (``"no"`` or ``0`` is not a boolean, ``"1.5"`` not a number)."""

    model_config = ConfigDict(allow_inf_nan=False, extra="forbid", strict=True)


def _example(example: dict[str, Any], model: type[BaseModel] = ApiModel) -> ConfigDict:
    config = ConfigDict(**model.model_config)
    config["json_schema_extra"] = {"examples": [example]}
    return config


# ------------------------------------------------------------------------ mesh sources


class MeshPart(ApiModel):
    """A triangle mesh: vertex positions and counter-clockwise faces (0-based)."""

    model_config = _example(EXAMPLE_MESH)

    vertices: list[Vec3] = Field(min_length=1, fail_fast=True,
                                description="(n, 3) vertex positions.")
    faces: list[Tri] = Field(min_length=1, fail_fast=True,
                             description="(m, 3) vertex indices, 0-based, "
                             "counter-clockwise seen from outside.")


class FormsPart(ApiModel):
    """Discrete fundamental forms: the output of ``POST /v1/forms``."""

    model_config = _example(EXAMPLE_FORMS)

    faces: list[Tri] = Field(min_length=1, fail_fast=True,
                             description="(m, 3) vertex indices.")
    edges: list[Pair] = Field(
        fail_fast=True,
        description="(E, 2) the faces' edges [i, j], i < j, sorted lexicographically.")
    lengths: list[Real] = Field(fail_fast=True,
                                description="(E,) edge lengths (first fundamental form).")
    angles: list[Real] = Field(
        fail_fast=True,
        description="(E,) signed dihedral angles in (-pi, pi], positive where convex, 0 on "
                    "boundary edges (second fundamental form).")


# ------------------------------------------------------------------------- parameters


class FormsParams(ApiModel):
    """``POST /v1/forms`` takes no parameters besides the mesh."""

    model_config = _example({})


class MeshParams(ApiModel):
    """``POST /v1/mesh`` takes no parameters besides the mesh."""

    model_config = _example({})


class PlacementModel(ApiModel):
    """The rigid placement of each connected component (``solver.mesh.placement``): the pose
    of its anchor face (its largest face, the lowest-numbered among equals) when the forms
    were computed."""

    model_config = _example({"faces": [0], "origins": [[0.0, 0.0, 0.0]],
                             "frames": [_IDENTITY]})

    faces: list[Index] = Field(fail_fast=True, description="(c,) anchor face of each "
                               "component.")
    origins: list[Vec3] = Field(fail_fast=True, description="(c, 3) position of each anchor "
                                "face's first vertex.")
    frames: list[Mat3] = Field(fail_fast=True, description="(c, 3, 3) rotation whose columns "
                               "are the anchor face's edge direction, in-plane normal and "
                               "face normal (rows given).")


class CutFormsParams(ApiModel):
    """What forms of ``POST /v1/forms`` carry besides the arrays (issue 40)."""

    vertex_map: list[Index] | None = Field(
        None, fail_fast=True,
        description="Forms of a non-manifold mesh are those of its manifold cut (`faces` are "
                    "the cut faces): `vertex_map[c]` is the file vertex of cut vertex c. "
                    "Answers are then per file vertex (the mean of its copies; their spread "
                    "in `report.input.cut`). Omitted: the faces' own vertices.")
    weld_map: list[Index] | None = Field(
        None, fail_fast=True,
        description="Forms of a mesh with zero-length edges (two corners of a face at one "
                    "position) are those of the welded mesh: `weld_map[i]` is the file vertex "
                    "vertex i was welded into (i itself unless welded; with `vertex_map`, "
                    "whose length-n prefix then names representatives only). Answers give a "
                    "welded vertex its representative's position (`report.input.weld`). "
                    "Omitted: nothing welded.")
    dropped_faces: list[Index] | None = Field(
        None, fail_fast=True,
        description="Informational, as `POST /v1/forms` answers it: the file faces left out "
                    "of `faces` (they repeat a vertex once welded). Ignored.")
    zero_area_faces: list[Index] | None = Field(
        None, fail_fast=True,
        description="Informational, as `POST /v1/forms` answers it: the faces of zero area "
                    "(collinear corners) whose normal the documented rule chose. Ignored: "
                    "the solvers find such faces from the lengths "
                    "(`report.input.zero_area_faces`).")
    placement: PlacementModel | None = Field(
        None, description="Each component's rigid placement (from `POST /v1/forms`): "
                          "`reconstruct` moves every unconstrained component so that its "
                          "anchor face has that pose, so a multi-part model comes back whole. "
                          "Omitted: each component is anchored at the origin.")


class IntegrabilityParams(CutFormsParams):
    """Parameters of ``POST /v1/integrability``."""

    model_config = _example({"tolerance": 1e-8})

    tolerance: float = Field(1e-8, gt=0, description="Tolerance on vertex defects and global "
                             "holonomy (radians; translation relative to the mean edge).")


class PositionConstraint(ApiModel):
    """Pin one vertex to a position; ``weight`` omitted = hard constraint."""

    model_config = _example({"vertex": 0, "position": [0.0, 0.0, 0.0]})

    vertex: Index = Field(description="Vertex index.")
    position: Vec3 = Field(description="Target position.")
    weight: Weight | None = Field(None, description="Soft weight; omit for hard.")


class FrameConstraint(ApiModel):
    """Fix the frame of one face (a rotation: columns edge direction, in-plane normal,
    face normal); ``weight`` omitted = hard."""

    model_config = _example({"face": 0, "frame": _IDENTITY})

    face: Index = Field(description="Face index.")
    frame: Mat3 = Field(description="3x3 rotation matrix (rows).")
    weight: Weight | None = Field(None, description="Soft weight; omit for hard.")


class Constraints(ApiModel):
    """Position and frame constraints of a reconstruction."""

    model_config = _example({"positions": [{"vertex": 0, "position": [0.0, 0.0, 0.0]}],
                             "frames": [{"face": 0, "frame": _IDENTITY}]})

    positions: list[PositionConstraint] = Field(default_factory=list, fail_fast=True)
    frames: list[FrameConstraint] = Field(default_factory=list, fail_fast=True)


def served_options(source: type[solver_options.SolveOptions],
                   notes: dict[str, str] | None = None) -> type[ApiModel]:
    """The request model of an operation's ``options``, made from the solver's options
    class ``source``: each field it serves, under its HTTP name, with its type, default,
    bounds and description (and ``notes``, HTTP name -> text added to a description).
    Subclass it for the docstring, the example and the service's own options."""
    hints = typing.get_type_hints(source)
    notes = {"max_seconds": BUDGET_NOTE, **(notes or {})}
    fields: dict[str, Any] = {}
    for item in dataclasses.fields(source):
        if not item.metadata["served"]:
            continue
        name = solver_options.api_name(item)
        fields[name] = (hints[item.name], Field(
            item.default, description=item.metadata["description"] + notes.get(name, ""),
            **item.metadata["bounds"]))
    return create_model(f"_{source.__name__}Fields", __base__=ApiModel, **fields)


class ReconstructOptions(served_options(solver_options.ReconstructOptions)):  # type: ignore[misc]
    """Options of ``POST /v1/reconstruct`` (:class:`solver.options.ReconstructOptions`)."""

    model_config = _example({"frame_weight": 1000.0, "orthonormalize": False,
                             "solver": "auto", "require_integrable": False})

    require_integrable: bool = Field(
        False, description="Fail with 422 naming the worst vertices instead of returning a "
                           "least-squares answer when the forms are not integrable.")


class ReconstructParams(CutFormsParams):
    """Parameters of ``POST /v1/reconstruct`` besides the forms (or mesh file)."""

    model_config = _example({"constraints": {"positions": [{"vertex": 0,
                                                             "position": [0.0, 0.0, 0.0]}]},
                             "options": {"orthonormalize": True}})

    constraints: Constraints | None = None
    options: ReconstructOptions = Field(default_factory=ReconstructOptions)
    align_to: list[Vec3] | None = Field(
        None, description="(n, 3) vertices of a reference mesh with the same vertices (the "
        "mesh the forms came from): the answer is moved rigidly onto it (rotation and "
        "translation, least squares) and `report.alignment` gives the residual left "
        "(`residual_rms`, `residual_max`, in the mesh's units), the rotation and the "
        "translation. Without it the answer's placement is the solver's (arbitrary).")


class HandleTarget(ApiModel):
    """Move vertex ``vertex`` to ``position``."""

    model_config = _example({"vertex": 4, "position": [0.5, 0.5, 0.8]})

    vertex: Index
    position: Vec3


class RotationHandle(ApiModel):
    """Rotate the frames of a group of faces by ``rotation``."""

    model_config = _example({"faces": [0, 1], "rotation": _IDENTITY})

    faces: list[Index] = Field(min_length=1, fail_fast=True)
    rotation: Mat3


class DeformOptions(served_options(solver_options.DeformOptions,  # type: ignore[misc]
                                   {"refine": SESSION_REFINE_NOTE})):
    """Options of ``POST /v1/deform`` (:class:`solver.options.DeformOptions`)."""

    model_config = _example({"frame_weight": 1000.0, "orthonormalize": False,
                             "solver": "auto"})


class DeformParams(ApiModel):
    """Parameters of ``POST /v1/deform`` besides the mesh."""

    model_config = _example({"handles": [{"vertex": 0, "position": [0.0, 0.0, 0.0]},
                                         {"vertex": 4, "position": [0.5, 0.5, 0.8]}]})

    handles: list[HandleTarget] = Field(min_length=1, fail_fast=True)
    rotations: list[RotationHandle] | None = Field(None, fail_fast=True)
    roi: list[Index] | None = Field(None, description="Vertices that may move (default all).",
                                    fail_fast=True)
    options: DeformOptions = Field(default_factory=DeformOptions)


class ParameterizeOptions(served_options(solver_options.ParameterizeOptions)):  # type: ignore[misc]
    """Options of ``POST /v1/parameterize`` (:class:`solver.options.ParameterizeOptions`)."""

    model_config = _example({"orthonormalize": True, "solver": "auto"})


class ParameterizeParams(ApiModel):
    """Parameters of ``POST /v1/parameterize`` besides the mesh."""

    model_config = _example({"options": {"orthonormalize": True}})

    options: ParameterizeOptions = Field(default_factory=ParameterizeOptions)


class InterpolateOptions(served_options(solver_options.InterpolateOptions)):  # type: ignore[misc]
    """Options of ``POST /v1/interpolate`` (:class:`solver.options.InterpolateOptions`)."""

    model_config = _example({"frame_weight": 1000.0, "solver": "auto"})


class InterpolateParams(ApiModel):
    """Parameters of ``POST /v1/interpolate`` besides the two meshes."""

    model_config = _example({"t": [0.0, 0.5, 1.0]})

    t: Real | Annotated[list[Real], Field(min_length=1, fail_fast=True)] = Field(
        description="Blend value(s); 0 gives A, 1 gives B. A list holds at least one and at "
                    "most FFS_MAX_BLEND_STEPS (default 1024) values, and values x vertices "
                    "at most FFS_MAX_BLEND_VERTICES (default 4,000,000; 413 beyond).")
    options: InterpolateOptions = Field(default_factory=InterpolateOptions)


class BlendOptions(served_options(solver_options.BlendOptions)):  # type: ignore[misc]
    """Options of ``POST /v1/blend`` and ``POST /v1/transfer``
    (:class:`solver.options.BlendOptions`)."""

    model_config = _example({"sequence": True, "solver": "auto"})


class BlendParams(ApiModel):
    """Parameters of ``POST /v1/blend`` besides the shapes: ``weights`` or ``t``."""

    model_config = _example({"weights": [[1.0, 0.0], [0.5, 0.5], [-0.5, 1.5]]})

    weights: Annotated[list[Annotated[list[Real], Field(min_length=1)]],
                       Field(min_length=1, fail_fast=True)] | None = Field(
        None, description="(T, K) rows of affine weights, one per shape (each row sums to "
        "1; negative weights extrapolate); at most FFS_MAX_BLEND_STEPS (default 1024) rows, "
        "and rows x vertices at most FFS_MAX_BLEND_VERTICES (default 4,000,000: 100 rows of "
        "a 40,000-vertex mesh; 413 `blend-too-large` beyond). Give `weights` or `t`.")
    t: Real | Annotated[list[Real], Field(min_length=1, fail_fast=True)] | None = Field(
        None, description="Two shapes only: blend value(s), the rows (1 - t, t); 0 gives the "
        "first shape, 1 the second, 1.5 extrapolates.")
    times: Annotated[list[Real], Field(min_length=1, fail_fast=True)] | None = Field(
        None, description="glTF output: the keyframe time of each row in seconds, strictly "
        "increasing (default: 24 rows per second).")
    options: BlendOptions = Field(default_factory=BlendOptions)

    @model_validator(mode="after")
    def _weights_or_t(self) -> BlendParams:
        if (self.weights is None) == (self.t is None):
            raise ValueError("give exactly one of `weights` (rows of K weights) and `t` "
                             "(two shapes)")
        return self


class TransferParams(ApiModel):
    """Parameters of ``POST /v1/transfer`` besides the three meshes."""

    model_config = _example({"options": {"refine": True}})

    options: BlendOptions = Field(default_factory=BlendOptions)


# ---------------------------------------------------------------------- request bodies


class FormsRequest(MeshPart, FormsParams):
    """Body of ``POST /v1/forms``."""

    model_config = _example(EXAMPLE_MESH)


class IntegrabilityRequest(FormsPart, IntegrabilityParams):
    """Body of ``POST /v1/integrability``."""

    model_config = _example({**EXAMPLE_FORMS, "tolerance": 1e-8})


class ReconstructRequest(FormsPart, ReconstructParams):
    """Body of ``POST /v1/reconstruct``: the forms, optional constraints and options."""

    model_config = _example({**EXAMPLE_FORMS, "constraints": {
        "positions": [{"vertex": 0, "position": [0.0, 0.0, 0.0]}],
        "frames": [{"face": 0, "frame": [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0],
                                         [0.0, 1.0, 0.0]]}]},
        "options": {"frame_weight": 1000.0, "orthonormalize": False, "solver": "auto",
                    "require_integrable": True}})


class ReconstructVjpParams(ReconstructParams):
    """Parameters of ``POST /v1/reconstruct/vjp``: those of ``/v1/reconstruct`` and the
    cotangent of the reconstructed vertices."""

    model_config = _example({"cotangent": [[0.0, 0.0, 1.0]] * 5,
                             "options": {"refine": False}})

    cotangent: list[Vec3] | list[list[Vec3]] = Field(
        description="(n, 3) cotangent of the reconstructed vertices (the gradient of a loss "
                    "with respect to them), or (k, n, 3): k cotangents on one factorization.")


class ReconstructVjpRequest(FormsPart, ReconstructVjpParams):
    """Body of ``POST /v1/reconstruct/vjp``: the forms, constraints, options and cotangent."""

    model_config = _example({**EXAMPLE_FORMS, "cotangent": [[0.0, 0.0, 1.0]] * 5,
                             "options": {"refine": False}})


class ReconstructVjpResponse(BaseModel):
    """The reconstruction and the cotangents of its inputs (batch axis k first when the
    cotangent had one): lengths and angles (E,), constraint positions (p, 3) and frames
    (q, 3, 3) in the order they were sent. ``report.vjp`` says which answer was
    differentiated (``linear`` or ``refined``) and what it cost."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {**EXAMPLE_MESH, "grad_lengths": [0.0] * 8, "grad_angles": [0.0] * 8,
         "grad_positions": [], "grad_frames": [], "report": {"vjp": {"mode": "linear"}}}]})

    vertices: list[Vec3]
    faces: list[Tri]
    grad_lengths: list[float] | list[list[float]]
    grad_angles: list[float] | list[list[float]]
    grad_positions: list[Any]
    grad_frames: list[Any]
    report: dict[str, Any]


class DeformRequest(MeshPart, DeformParams):
    """Body of ``POST /v1/deform``."""

    model_config = _example({**EXAMPLE_MESH, "handles": [
        {"vertex": 0, "position": [0.0, 0.0, 0.0]}, {"vertex": 1, "position": [1.0, 0.0, 0.0]},
        {"vertex": 2, "position": [1.0, 1.0, 0.0]}, {"vertex": 3, "position": [0.0, 1.0, 0.0]},
        {"vertex": 4, "position": [0.5, 0.5, 0.8]}], "options": {"orthonormalize": False}})


class ParameterizeRequest(MeshPart, ParameterizeParams):
    """Body of ``POST /v1/parameterize`` (a mesh with boundary)."""

    model_config = _example({**EXAMPLE_MESH, "options": {"orthonormalize": True}})


class MeshRequest(MeshPart, MeshParams):
    """Body of ``POST /v1/mesh`` (the JSON form is useful for GLB/glTF output)."""

    model_config = _example(EXAMPLE_MESH)


class InterpolateRequest(InterpolateParams):
    """Body of ``POST /v1/interpolate``: two embeddings of the same faces and t."""

    model_config = _example({"vertices_a": _V, "vertices_b": _V_UP, "faces": _F,
                             "t": [0.0, 0.5, 1.0]})

    vertices_a: list[Vec3] = Field(min_length=1, fail_fast=True)
    vertices_b: list[Vec3] = Field(min_length=1, fail_fast=True)
    faces: list[Tri] = Field(min_length=1, fail_fast=True)


class BlendRequest(BlendParams):
    """Body of ``POST /v1/blend``: K embeddings of the same faces and the rows of weights."""

    model_config = _example({"shapes": [_V, _V_UP], "faces": _F,
                             "weights": [[1.0, 0.0], [0.5, 0.5], [-0.5, 1.5]]})

    shapes: Annotated[list[Annotated[list[Vec3], Field(min_length=1)]],
                      Field(min_length=1, max_length=MAX_SHAPES, fail_fast=True)] = Field(
        description=f"K (n, 3) embeddings of `faces` (1 to {MAX_SHAPES} shapes).")
    faces: list[Tri] = Field(min_length=1, fail_fast=True)


class TransferRequest(TransferParams):
    """Body of ``POST /v1/transfer``: the deformation ``source -> source_deformed`` applied to
    ``target`` (three embeddings of the same faces)."""

    model_config = _example({"source": _V, "source_deformed": _V_UP,
                             "target": [[2.0 * x, y, z] for x, y, z in _V], "faces": _F})

    source: list[Vec3] = Field(min_length=1, fail_fast=True)
    source_deformed: list[Vec3] = Field(min_length=1, fail_fast=True)
    target: list[Vec3] = Field(min_length=1, fail_fast=True)
    faces: list[Tri] = Field(min_length=1, fail_fast=True)


class JobRequest(BaseModel):
    """Body of ``POST /v1/jobs``: an operation and its input (the operation's JSON body)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"operation": "reconstruct", "input": ReconstructRequest.model_config[
            "json_schema_extra"]["examples"][0], "color": "defect"}]})

    operation: Operation
    input: dict[str, Any] = Field(description="The body the synchronous endpoint takes.")
    color: ColorField | None = Field(
        None, description="Precompute this vertex colour field so that "
                          "GET /v1/jobs/{id}/result?color=... can add it.")
    callback_url: str | None = Field(
        None, max_length=2048,
        description="Where to POST the job's status document, signed, when it succeeds, "
                    "fails or is cancelled (a host of FFS_WEBHOOK_HOSTS; services with API "
                    "keys only). See docs/deployment.md#webhooks.")


# ---------------------------------------------------------------------------- sessions


class SessionHandle(ApiModel):
    """A handle vertex of a session; ``position`` is optional and unused at creation (each
    solve brings the targets), so a ``/v1/deform`` body can be reused as is."""

    model_config = _example({"vertex": 4, "position": [0.5, 0.5, 0.5]})

    vertex: Index
    position: Vec3 | None = None


class SessionRotationHandle(ApiModel):
    """A group of faces whose frames each solve rotates by one matrix (``rotation`` is
    optional and unused at creation)."""

    model_config = _example({"faces": [0, 1]})

    faces: list[Index] = Field(min_length=1, fail_fast=True)
    rotation: Mat3 | None = None


class SessionParams(ApiModel):
    """The fields of ``POST /v1/sessions`` besides the mesh."""

    model_config = _example({"handles": [{"vertex": 0}, {"vertex": 4}]})

    handles: list[SessionHandle] = Field(min_length=1, fail_fast=True)
    rotations: list[SessionRotationHandle] | None = Field(None, fail_fast=True)
    roi: list[Index] | None = Field(None, description="Vertices that may move (default all).",
                                    fail_fast=True)
    options: DeformOptions = Field(default_factory=DeformOptions)


class SessionRequest(MeshPart, SessionParams):
    """Body of ``POST /v1/sessions``: the rest mesh, the handles (vertex indices and,
    optionally, face groups with a rotation handle), an optional region of interest and
    the deformation options. The system is factorized once here."""

    model_config = _example({**EXAMPLE_MESH, "handles": [
        {"vertex": 0}, {"vertex": 1}, {"vertex": 2}, {"vertex": 3},
        {"vertex": 4, "position": [0.5, 0.5, 0.5]}]})


class SessionDrag(ApiModel):
    """Body of ``POST /v1/sessions/{id}/solve`` (and a JSON WebSocket message): one target
    per handle, in the order of the session's ``handles``, and one rotation per rotation
    group (default: identity). ``seq`` (WebSocket only) is echoed in the reply header."""

    model_config = _example({"handle_positions": [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0],
                                                  [1.0, 1.0, 0.0], [0.0, 1.0, 0.0],
                                                  [0.5, 0.5, 0.8]]})

    handle_positions: list[Vec3] = Field(min_length=1, fail_fast=True)
    handle_rotations: list[Mat3] | None = Field(None, fail_fast=True)
    seq: int | None = Field(None, ge=0, le=2**32 - 1)
