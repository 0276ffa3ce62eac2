"""A client generated from the committed openapi/openapi.json with openapi-python-client (the
version pinned in the test extra, the configuration docs/service.md recommends), used against
a real uvicorn: every operation with JSON, uploads with array fields, a job to GLB, a session,
a problem document. The generator must not warn."""

from __future__ import annotations

import importlib
import io
import json
import re
import subprocess
import sys
import time
from typing import Any

import numpy as np
import pytest

from tests.helpers import REPO

DOC = REPO / "docs" / "service.md"
PACKAGE = "fundamental_forms_service_client"
DOCUMENT = json.loads((REPO / "openapi" / "openapi.json").read_text(encoding="utf-8"))
SCHEMAS = DOCUMENT["components"]["schemas"]


def _example(model: str) -> dict[str, Any]:
    return SCHEMAS[model]["examples"][0]


def documented_config() -> str:
    """The generator configuration of docs/service.md (its one ``yaml`` block)."""
    (block,) = re.findall(r"```yaml\n(.*?)```", DOC.read_text(encoding="utf-8"), re.DOTALL)
    return block


def documented_command() -> str:
    """The documented generator command."""
    (command,) = [line for line in DOC.read_text(encoding="utf-8").splitlines()
                  if line.startswith("openapi-python-client generate")]
    return command


@pytest.fixture(scope="module")
def gen(tmp_path_factory) -> Any:
    """``gen(module)``: a module of the generated package (``"models"``,
    ``"api.jobs.get_job"``, ...); the package leaves ``sys.modules`` afterwards."""
    work = tmp_path_factory.mktemp("client")
    (work / "openapi").mkdir()
    (work / "openapi" / "openapi.json").write_bytes(
        (REPO / "openapi" / "openapi.json").read_bytes())
    (work / "openapi-python-client.yaml").write_text(documented_config(), encoding="utf-8")
    proc = subprocess.run(documented_command(), shell=True, cwd=work, capture_output=True,
                          text=True, timeout=300, check=False)
    output = proc.stdout + proc.stderr
    assert proc.returncode == 0, output
    assert "warning" not in output.lower() and "error" not in output.lower(), output
    sys.path.insert(0, str(work))
    try:
        yield lambda name: importlib.import_module(f"{PACKAGE}.{name}")
    finally:
        sys.path.remove(str(work))
        for name in [m for m in sys.modules if m.split(".")[0] == PACKAGE]:
            del sys.modules[name]


@pytest.fixture(scope="module")
def client(gen, live_server) -> Any:
    with gen("client").Client(base_url=live_server, timeout=120) as client:
        yield client


def _lengths(vertices: Any, edges: Any) -> np.ndarray:
    vertices, edges = np.asarray(vertices), np.asarray(edges)
    return np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)


def test_every_operation_with_json(gen, client):
    m = gen("models")
    forms = gen("api.operations.forms").sync(
        client=client, body=m.FormsRequest.from_dict(_example("FormsRequest")))
    assert isinstance(forms, m.FormsResponse)
    mesh = _example("FormsRequest")
    np.testing.assert_allclose(forms.lengths, _lengths(mesh["vertices"], forms.edges))

    report = gen("api.operations.integrability").sync(
        client=client, body=m.IntegrabilityRequest.from_dict(forms.to_dict()))
    assert isinstance(report, m.IntegrabilityResponse) and report.integrable

    rebuilt = gen("api.operations.reconstruct").sync(
        client=client, body=m.ReconstructRequest.from_dict(forms.to_dict()))
    assert isinstance(rebuilt, m.MeshResponse)
    np.testing.assert_allclose(_lengths(rebuilt.vertices, forms.edges), forms.lengths,
                               atol=1e-8)

    vjp = gen("api.operations.reconstruct_vjp").sync(
        client=client, body=m.ReconstructVjpRequest.from_dict(_example("ReconstructVjpRequest")))
    assert isinstance(vjp, m.ReconstructVjpResponse), vjp
    assert len(vjp.grad_lengths) == len(forms.lengths)

    example = _example("DeformRequest")
    deformed = gen("api.operations.deform").sync(
        client=client, body=m.DeformRequest.from_dict(example))
    for handle in example["handles"]:
        np.testing.assert_allclose(deformed.vertices[handle["vertex"]], handle["position"],
                                   atol=1e-6)

    flat = gen("api.operations.parameterize").sync(
        client=client, body=m.ParameterizeRequest.from_dict(_example("ParameterizeRequest")))
    assert isinstance(flat, m.ParameterizeResponse) and len(flat.uv) == len(flat.uv_vertex)
    assert sorted(set(flat.uv_vertex)) == [0, 1, 2, 3, 4]  # the pyramid's 5 vertices

    example = _example("InterpolateRequest")
    blend = gen("api.operations.interpolate").sync(
        client=client, body=m.InterpolateRequest.from_dict(example))
    assert isinstance(blend, m.InterpolateResponse) and blend.t == [0.0, 0.5, 1.0]
    np.testing.assert_allclose(_lengths(blend.vertices[2], forms.edges),
                               _lengths(example["vertices_b"], forms.edges), atol=1e-6)
    assert blend.refinement is not None

    read = gen("api.operations.mesh").sync(
        client=client, body=m.MeshRequest.from_dict(_example("MeshRequest")))
    assert read.vertices == mesh["vertices"] and read.faces == mesh["faces"]


def test_blend_and_transfer(gen, client):
    """The shape-space endpoints through the generated client: the example blend's rows
    (1, 0) and (0, 1) are its two shapes, the example transfer of a pyramid's lift to a
    stretched pyramid lifts it by the same ratio."""
    m = gen("models")
    example = _example("BlendRequest")
    blended = gen("api.operations.blend").sync(
        client=client, body=m.BlendRequest.from_dict(example))
    assert isinstance(blended, m.BlendResponse), blended
    np.testing.assert_allclose(blended.vertices[0], example["shapes"][0], atol=1e-8)
    paths = [row.to_dict()["path"] for row in blended.reports]
    assert paths[0] == "reconstruct" and set(paths) <= {"reconstruct", "sequence"}
    example = _example("TransferRequest")
    moved = gen("api.operations.transfer").sync(
        client=client, body=m.TransferRequest.from_dict(example))
    assert isinstance(moved, m.TransferResponse), moved
    edges = np.array([[0, 4], [1, 4], [2, 4], [3, 4]])
    ratio = _lengths(example["source_deformed"], edges) / _lengths(example["source"], edges)
    np.testing.assert_allclose(_lengths(moved.vertices, edges),
                               ratio * _lengths(example["target"], edges), rtol=2e-3)


def test_health_and_problem_types(gen, client):
    assert gen("api.health.healthz").sync(client=client).status == "ok"
    assert gen("api.health.readyz").sync(client=client).workers_ready >= 1
    kinds = gen("api.health.list_problems").sync(client=client)
    assert "index-out-of-range" in {k.kind for k in kinds}
    one = gen("api.health.get_problem").sync("index-out-of-range", client=client)
    assert one.status == 422
    text = gen("api.health.metrics").sync(client=client)
    assert isinstance(text, str) and "# TYPE" in text


def test_uploads_with_array_fields(gen, client):
    m, File = gen("models"), gen("types").File
    face = (REPO / "tests" / "data" / "face.off").read_bytes()
    handles = [m.HandleTarget(vertex=0, position=[0.0, 0.0, 0.0]),
               m.HandleTarget(vertex=500, position=[0.0, 0.0, 1.0])]
    deformed = gen("api.operations.deform").sync(client=client, body=m.DeformFilesBody(
        file=File(payload=io.BytesIO(face), file_name="face.off"), handles=handles,
        options=m.DeformOptions(refine=False)))
    assert isinstance(deformed, m.MeshResponse), deformed
    for handle in handles:
        np.testing.assert_allclose(deformed.vertices[handle.vertex], handle.position,
                                   atol=1e-6)

    blend = gen("api.operations.interpolate").sync(
        client=client, body=m.InterpolateFilesBody(
            file_a=File(payload=io.BytesIO(face), file_name="a.off"),
            file_b=File(payload=io.BytesIO(face), file_name="b.off"), t=[0.0, 0.25, 1.0]))
    assert isinstance(blend, m.InterpolateResponse), blend
    assert blend.t == [0.0, 0.25, 1.0] and len(blend.vertices) == 3


def test_a_job_polled_and_fetched_as_glb(gen, client):
    m, File = gen("models"), gen("types").File
    torus = (REPO / "tests" / "data" / "torus.off").read_bytes()
    submitted = gen("api.jobs.submit_job").sync_detailed(
        client=client, body=m.SubmitJobFilesBody(
            operation=m.SubmitJobFilesBodyOperation.RECONSTRUCT,
            file=File(payload=io.BytesIO(torus), file_name="torus.off"),
            options=m.ReconstructOptions(orthonormalize=True)))
    assert submitted.status_code == 202, submitted.content
    job = submitted.parsed
    assert isinstance(job, m.JobStatus) and submitted.headers["location"] == job.links["self"]
    deadline = time.monotonic() + 120
    while job.status in (m.JobStatusStatus.QUEUED, m.JobStatusStatus.RUNNING):
        assert time.monotonic() < deadline, job.to_dict()
        time.sleep(0.1)
        job = gen("api.jobs.get_job").sync(job.id, client=client)
        assert isinstance(job, m.JobStatus)
    assert job.status == m.JobStatusStatus.SUCCEEDED, job.to_dict()
    assert set(job.progress.stages.to_dict()) >= {"validate", "solve", "encode"}

    glb = gen("api.jobs.get_job_mesh").sync(job.id, client=client)
    assert isinstance(glb, File)
    data = glb.payload.read()
    assert data[:4] == b"glTF" and int.from_bytes(data[8:12], "little") == len(data)
    result = gen("api.jobs.get_job_result").sync(job.id, client=client)
    assert len(result.to_dict()["vertices"]) == int(torus.split()[1])
    deleted = gen("api.jobs.delete_job").sync_detailed(job.id, client=client)
    assert deleted.status_code == 204


def test_a_session_created_read_dragged_deleted(gen, client):
    m = gen("models")
    example = _example("SessionRequest")
    created = gen("api.sessions.create_session").sync_detailed(
        client=client, body=m.SessionRequest.from_dict(example))
    assert created.status_code == 201, created.content
    session = created.parsed
    assert isinstance(session, m.SessionInfo) and session.n_vertices == 5
    read = gen("api.sessions.get_session").sync(session.id, client=client)
    assert isinstance(read, m.SessionInfo) and read.handles == session.handles
    targets = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0],
               [0.5, 0.5, 0.9]]
    dragged = gen("api.sessions.solve_session").sync(
        session.id, client=client, body=m.SessionDrag(handle_positions=targets))
    assert isinstance(dragged, m.SessionVertices), dragged
    np.testing.assert_allclose(dragged.vertices, targets, atol=1e-6)  # every vertex a handle
    again = gen("api.sessions.get_session").sync(session.id, client=client)
    assert again.solves == 1
    deleted = gen("api.sessions.delete_session").sync_detailed(session.id,
                                                                       client=client)
    assert deleted.status_code == 204
    gone = gen("api.sessions.get_session").sync(session.id, client=client)
    assert isinstance(gone, m.Problem) and gone.status in (404, 410)


def test_a_problem_document_is_parsed(gen, client):
    m = gen("models")
    body = _example("FormsRequest")
    body = {**body, "faces": [*body["faces"][:-1], [3, 0, 9001]]}
    problem = gen("api.operations.forms").sync(client=client,
                                                        body=m.FormsRequest.from_dict(body))
    assert isinstance(problem, m.Problem), problem
    assert problem.status == 422 and problem.kind == "index-out-of-range"
    assert problem.errors[0].field == "faces" and problem.errors[0].index == 3
