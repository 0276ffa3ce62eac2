"""Bad input: RFC 9457 problems with pointers; every solver error kind is a 422; never a 500."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from service.api.problems import PROBLEM_KINDS, ProblemError, failure_of
from service.api.schemas import EXAMPLE_FORMS, EXAMPLE_MESH
from solver.core.errors import ERROR_KINDS
from tests.helpers.meshes import icosphere
from tests.helpers.servers import running_app
from tests.helpers.service import forms_json, mesh_json, problem

S2 = 1.4142135623730951
QUAD = {"faces": [[0, 1, 2], [0, 2, 3]], "edges": [[0, 1], [0, 2], [0, 3], [1, 2], [2, 3]],
        "lengths": [1.0, S2, 1.0, 1.0, 1.0], "angles": [0.0] * 5}
QUAD_MESH = {"vertices": [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]],
             "faces": [[0, 1, 2], [0, 2, 3]]}
ROT = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]


def _forms(**changes):
    body = copy.deepcopy(EXAMPLE_FORMS)
    body.update(changes)
    return body


def _with(values, index, value):
    values = list(values)
    values[index] = value
    return values


# (kind, endpoint, body, expected pointer (field, index))
SOLVER_CASES = [
    ("shape-mismatch", "integrability", _forms(lengths=EXAMPLE_FORMS["lengths"][:-1]),
     ("lengths", None)),
    ("index-out-of-range", "forms", {"vertices": EXAMPLE_MESH["vertices"],
                                     "faces": [[0, 1, 4], [1, 2, 9001]]}, ("faces", 1)),
    ("non-positive-length", "integrability", _forms(lengths=_with(EXAMPLE_FORMS["lengths"], 3,
                                                                   0.0)), ("lengths", 3)),
    ("triangle-inequality", "reconstruct", _forms(lengths=_with(EXAMPLE_FORMS["lengths"], 0,
                                                                 5.0)), ("faces", 0)),
    ("edge-mismatch", "integrability", _forms(edges=_with(EXAMPLE_FORMS["edges"], 1, [3, 0])),
     ("edges", 1)),
    # Collinear corners are measured and two corners at one position welded (issue 40);
    # forms, which carry no positions, with a face that repeats a vertex are not.
    ("degenerate-face", "integrability",
     {"faces": [[0, 1, 2], [0, 0, 1]], "edges": [[0, 1], [0, 2], [1, 2]],
      "lengths": [1.0] * 3, "angles": [0.0] * 3}, ("faces", 1)),
    # A mesh whose every face collapses once welded has nothing left to solve.
    ("shape-mismatch", "forms", {"vertices": [[0, 0, 0], [1, 0, 0], [1, 0, 0]],
                                 "faces": [[0, 1, 2]]}, ("faces", None)),
    # Meshes are cut into manifold ones (issue 40); forms sent with non-manifold faces and
    # no vertex_map are still refused.
    ("non-manifold-edge", "integrability",
     {"faces": [[0, 1, 2], [1, 0, 3], [0, 1, 4]],
      "edges": [[0, 1], [0, 2], [0, 3], [0, 4], [1, 2], [1, 3], [1, 4]],
      "lengths": [1.0] * 7, "angles": [0.0] * 7}, ("faces", None)),
    ("non-manifold-vertex", "integrability",
     {"faces": [[0, 1, 2], [0, 3, 4]], "edges": [[0, 1], [0, 2], [0, 3], [0, 4], [1, 2],
                                                  [3, 4]],
      "lengths": [1.0] * 6, "angles": [0.0] * 6}, (None, None)),
    ("inconsistent-orientation", "integrability",
     {"faces": [[0, 1, 2], [0, 1, 3]], "edges": [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3]],
      "lengths": [1.0] * 5, "angles": [0.0] * 5}, ("faces", None)),
    ("invalid-constraint", "reconstruct",
     {**EXAMPLE_FORMS, "constraints": {"frames": [{"face": 0, "frame": [[2.0, 0, 0], [0, 1, 0],
                                                                          [0, 0, 1]]}]}},
     ("constraints.frames.frame", 0)),
    ("unsupported-topology", "parameterize",
     {**mesh_json(*icosphere(0)), "options": {"seams": "none"}}, ("faces", None)),
]


@pytest.mark.parametrize(("kind", "operation", "body", "pointer"), SOLVER_CASES,
                         ids=[c[0] for c in SOLVER_CASES])
def test_solver_error_kinds_are_422_over_http(client, kind, operation, body, pointer):
    doc = problem(client.post(f"/v1/{operation}", json=body), 422, kind)
    assert doc["instance"] == f"/v1/{operation}"
    error = doc["errors"][0]
    field, index = pointer
    if field is not None:
        assert error["field"] == field, error
    if index is not None:
        assert error["index"] == index, error
    assert error["reason"]


def test_every_solver_error_kind_maps_to_422():
    reached = {case[0] for case in SOLVER_CASES}
    # non-finite-value cannot come from a client: NaN/inf are rejected at the schema.
    assert {cls.kind for cls in ERROR_KINDS} - reached == {"non-finite-value"}
    for cls in ERROR_KINDS:
        assert PROBLEM_KINDS[cls.kind][0] == 422
        exc = cls("something is wrong", field="faces", index=17, details={"value": 9001})
        doc = ProblemError.from_dict(failure_of(exc)).to_dict("/v1/forms")
        assert doc["status"] == 422 and doc["type"] == f"/problems/{cls.kind}"
        assert doc["errors"] == [{"field": "faces", "index": 17,
                                  "reason": "something is wrong", "value": 9001}]


def test_example_pointer_from_the_spec(client):
    V, F = icosphere(1)
    faces = F.tolist()
    faces[17] = [0, 1, 9001]
    doc = problem(client.post("/v1/forms", json={"vertices": V.tolist(), "faces": faces}),
                  422, "index-out-of-range")
    assert doc["errors"][0] == {"field": "faces", "index": 17, "value": 9001,
                                "reason": f"index 9001 out of range [0, {len(V)})"}


@pytest.mark.parametrize("raw", [
    b'{"vertices": [[0, 0, 0], [1, 0, NaN], [0, 1, 0]], "faces": [[0, 1, 2]]}',
    b'{"vertices": [[0, 0, 0], [1, 0, Infinity], [0, 1, 0]], "faces": [[0, 1, 2]]}',
    b'{"vertices": [[0, 0, 0], [1, 0, -Infinity], [0, 1, 0]], "faces": [[0, 1, 2]]}',
    b'{"vertices": [[0, 0, 0], [1, 0, 1e400], [0, 1, 0]], "faces": [[0, 1, 2]]}',
])
def test_nan_and_infinity_rejected_at_the_schema(client, raw):
    response = client.post("/v1/forms", content=raw,
                           headers={"content-type": "application/json"})
    doc = problem(response, 422, "validation-error")
    assert doc["errors"][0]["field"] == "vertices" and doc["errors"][0]["index"] == 1
    assert doc["errors"][0]["pointer"] == "/vertices/1/2"


def test_nested_schema_pointers(client):
    body = {**EXAMPLE_FORMS, "constraints": {"positions": [
        {"vertex": 0, "position": [0, 0, 0]}, {"vertex": 1, "position": [0, 0]}]},
        "options": {"frame_weight": -1}}
    doc = problem(client.post("/v1/reconstruct", json=body), 422, "validation-error")
    fields = {(e["field"], e["index"]) for e in doc["errors"]}
    assert ("constraints.positions.position", 1) in fields
    assert ("options.frame_weight", None) in fields


def test_unknown_fields_and_wrong_types(client):
    doc = problem(client.post("/v1/forms", json={**EXAMPLE_MESH, "vertexes": []}), 422,
                  "validation-error")
    assert doc["errors"][0]["field"] == "vertexes"
    problem(client.post("/v1/forms", json=[1, 2, 3]), 422, "validation-error")
    problem(client.post("/v1/forms", json={"vertices": "abc", "faces": []}), 422,
            "validation-error")
    doc = problem(client.post("/v1/reconstruct", json={**EXAMPLE_FORMS,
                                                       "options": {"solver": "magic"}}),
                  422, "validation-error")
    assert doc["errors"][0]["field"] == "options.solver"


def test_huge_coordinates_and_indices_rejected_at_the_schema(client):
    body = {"vertices": [[0, 0, 0], [1e200, 0, 0], [0, 1, 0]], "faces": [[0, 1, 2]]}
    problem(client.post("/v1/forms", json=body), 422, "validation-error")
    body = {"vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "faces": [[0, 1, 2**70]]}
    doc = problem(client.post("/v1/forms", json=body), 422, "validation-error")
    assert doc["errors"][0]["pointer"] == "/faces/0/2"


@pytest.mark.parametrize(("raw", "reason"), [
    (b'{"vertices": ', "end of data"), (b"", "empty"), (b"   ", "empty"), (b"\xff\xfe", "JSON")])
def test_malformed_json_is_400(client, raw, reason):
    doc = problem(client.post("/v1/forms", content=raw,
                              headers={"content-type": "application/json"}),
                  400, "malformed-json")
    assert reason in doc["detail"]


def test_unsupported_media_type_is_415(client):
    response = client.post("/v1/forms", content=b"vertices", headers={
        "content-type": "text/plain"})
    doc = problem(response, 415, "unsupported-media-type")
    assert "text/plain" in doc["detail"]
    problem(client.post("/v1/jobs", content=b"x", headers={"content-type": "text/csv"}),
            415, "unsupported-media-type")


def test_not_acceptable_is_406(client):
    doc = problem(client.post("/v1/forms", json=EXAMPLE_MESH,
                              headers={"accept": "model/gltf-binary"}), 406, "not-acceptable")
    assert doc["available"] == ["application/json"]
    problem(client.post("/v1/reconstruct", json=EXAMPLE_FORMS, headers={"accept": "text/html"}),
            406, "not-acceptable")
    body = {"vertices_a": EXAMPLE_MESH["vertices"], "vertices_b": EXAMPLE_MESH["vertices"],
            "faces": EXAMPLE_MESH["faces"], "t": [0.0, 1.0]}
    problem(client.post("/v1/interpolate", json=body, headers={"accept": "model/gltf+json"}),
            406, "not-acceptable")


def test_colors(client):
    doc = problem(client.post("/v1/reconstruct", params={"color": "distortion"},
                              json=EXAMPLE_FORMS), 422, "validation-error")
    assert doc["errors"][0]["field"] == "query.color" and "defect" in doc["errors"][0]["reason"]
    problem(client.post("/v1/forms", params={"color": "defect"}, json=EXAMPLE_MESH),
            422, "unsupported-color")
    doc = problem(client.post("/v1/reconstruct", params={"color": "rainbow"},
                              json=EXAMPLE_FORMS), 422, "validation-error")
    assert doc["errors"][0]["field"] == "query.color"


def test_not_found_and_method_not_allowed(client):
    problem(client.get("/v1/nothing"), 404, "not-found")
    problem(client.get("/v1/forms"), 405, "method-not-allowed")
    problem(client.get("/v1/jobs/0123456789abcdef0123456789abcdef"), 404, "not-found")
    problem(client.get("/problems/no-such-kind"), 404, "not-found")


def test_unavailable_backend_is_422(client):
    from solver.linalg import BACKENDS, available_backends

    missing = [b for b in BACKENDS if b not in available_backends()]
    if not missing:
        pytest.skip("every linear-algebra backend is available here")
    doc = problem(client.post("/v1/reconstruct", json={**EXAMPLE_FORMS,
                                                       "options": {"solver": missing[0]}}),
                  422, "invalid-option")
    assert doc["errors"][0]["field"] == "options.solver"


def test_limits_are_413():
    V, F = icosphere(2)  # 162 vertices, 320 faces
    with running_app(workers=1, max_body_bytes=64 * 1024, max_vertices=100,
                     max_faces=1000) as small:
        doc = problem(small.post("/v1/forms", json=mesh_json(V, F)), 413, "mesh-too-large")
        assert doc["errors"][0]["field"] == "vertices" and "162" in doc["detail"]
        doc = problem(small.post("/v1/reconstruct", json=forms_json(V, F)), 413,
                      "mesh-too-large")
        big = {"vertices": [[0.123456789, 0.123456789, 0.123456789]] * 5000, "faces": [[0, 1, 2]]}
        problem(small.post("/v1/forms", json=big), 413, "payload-too-large")
        # Declared too large: rejected before the body is read.
        problem(small.post("/v1/forms", content=b"{}", headers={
            "content-type": "application/json", "content-length": str(10**9)}),
            413, "payload-too-large")
        # A mesh file over the vertex limit is rejected by the worker that reads it.
        import trimesh

        off = trimesh.Trimesh(V, F, process=False).export(file_type="off").encode()
        doc = problem(small.post("/v1/forms", files={"file": ("sphere.off", off)}), 413,
                      "mesh-too-large")
        assert doc["errors"][0]["field"] == "file"
        assert small.get("/readyz").status_code == 200


FUZZ_BODIES = [
    b"null", b"[]", b"{}", b'"text"', b"1e999", b"true",
    b'{"vertices": 1, "faces": 2}',
    b'{"vertices": [[1, 2]], "faces": [[0, 1, 2]]}',
    b'{"vertices": [[0, 0, 0]], "faces": [[0, 0, 0]]}',
    b'{"vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "faces": [[-1, 0, 1]]}',
    b'{"vertices": [[0, 0, 0], [0, 0, 0], [0, 0, 0]], "faces": [[0, 1, 2]]}',
    b'{"vertices": [[0, 0, 0], [1e59, 0, 0], [0, 1e59, 0]], "faces": [[0, 1, 2]]}',
    b'{"vertices": [[0, 0, 0], [1e-59, 0, 0], [0, 1e-59, 0]], "faces": [[0, 1, 2]]}',
    b'{"faces": [[0, 1, 2]], "edges": [], "lengths": [], "angles": []}',
    b'{"faces": [[0, 1, 2], [0, 2, 3]], "edges": [[0, 1], [0, 2], [0, 3], [1, 2], [2, 3]], '
    b'"lengths": [1e59, 1e59, 1e59, 1e59, 1e59], "angles": [0, 0, 0, 0, 0]}',
    b'{"faces": [[0, 1, 2], [0, 2, 3]], "edges": [[0, 1], [0, 2], [0, 3], [1, 2], [2, 3]], '
    b'"lengths": [1, 2, 1, 1, 1], "angles": [0, 0, 0, 0, 0], '
    b'"options": {"weighting": "cotan", "frame_weight": 1e300}}',
    b'{"faces": [[0, 1, 2], [0, 2, 3]], "edges": [[0, 1], [0, 2], [0, 3], [1, 2], [2, 3]], '
    b'"lengths": [1, 1.5, 1, 1, 1], "angles": [3.14159, -3.14159, 0, 1, 2], '
    b'"constraints": {"positions": [{"vertex": 0, "position": [1e59, 0, 0], "weight": 1e59}],'
    b' "frames": [{"face": 1, "frame": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "weight": 1e-300}]}}',
    b'{"vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], "faces": [[0, 1, 2], '
    b'[1, 3, 2]], "handles": [{"vertex": 0, "position": [1e59, 1e59, 1e59]}]}',
    b'{"vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], "faces": [[0, 1, 2], '
    b'[1, 3, 2]], "handles": [{"vertex": 0, "position": [0, 0, 0]}], "roi": [], '
    b'"rotations": [{"faces": [1, 1], "rotation": [[0, 1, 0], [1, 0, 0], [0, 0, 1]]}]}',
    b'{"vertices_a": [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], "vertices_b": [[0, 0, 0], '
    b'[1, 0, 0], [0, 1, 0], [1, 1, 1e59]], "faces": [[0, 1, 2], [1, 3, 2]], "t": [-1e59]}',
]


@pytest.mark.parametrize("operation", ["forms", "integrability", "reconstruct", "deform",
                                       "parameterize", "interpolate"])
def test_never_a_500_for_client_input(client, operation):
    for raw in FUZZ_BODIES:
        response = client.post(f"/v1/{operation}", content=raw,
                               headers={"content-type": "application/json"})
        assert response.status_code < 500, (raw, response.text)
        if response.status_code >= 400:
            assert response.headers["content-type"] == "application/problem+json"
        else:
            assert "null" not in response.text, (raw, response.text[:300])


@pytest.mark.parametrize("faces", [[[0, 1, 2]], [[0, 1, 2], [3, 4, 5]]])
def test_components_without_interior_edges(client, faces):
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 0, 0], [6, 0, 0], [5, 1, 0]], float)
    forms = forms_json(V[: np.max(faces) + 1], np.array(faces))
    for operation in ("integrability", "reconstruct"):
        response = client.post(f"/v1/{operation}", json=forms)
        assert response.status_code == 200, response.text


def test_triangle_inequality_quotes_the_lengths_as_sent(client):
    V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
    F = np.array([[0, 1, 2], [0, 2, 3]])
    body = forms_json(V, F)
    edges = [tuple(e) for e in body["edges"]]
    body["lengths"] = [1.41] * len(edges)
    body["lengths"][edges.index((0, 1))] = 100  # face 0: 100 > 1.41 + 1.41
    doc = problem(client.post("/v1/reconstruct", json=body), 422, "triangle-inequality")
    assert doc["errors"][0]["field"] == "faces" and doc["errors"][0]["index"] == 0
    assert "100 > 1.41 + 1.41" in doc["detail"], doc["detail"]
    assert sorted(doc["errors"][0]["lengths"]) == [1.41, 1.41, 100]
    normalized = 100 / np.mean(body["lengths"])
    assert f"{normalized:.3f}" not in doc["detail"]


# A newcomer's mistakes (newcomer sweep): every problem quotes the value that was sent.
@pytest.mark.parametrize(("raw", "pointer", "value"), [
    (b'{"vertices": [[0, 0, 0], [1, 0, NaN], [0, 1, 0]], "faces": [[0, 1, 2]]}',
     "/vertices/1/2", "NaN"),
    (b'{"vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "faces": [[0, 1, -1]]}',
     "/faces/0/2", -1),
    (b'{"vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "faces": [[0, 1, 2.5]]}',
     "/faces/0/2", 2.5),
])
def test_array_validation_errors_quote_the_value_sent(client, raw, pointer, value):
    doc = problem(client.post("/v1/forms", content=raw,
                              headers={"content-type": "application/json"}),
                  422, "validation-error")
    assert doc["errors"][0]["pointer"] == pointer and doc["errors"][0]["value"] == value
    assert f"(sent: {value})" in doc["detail"]


def test_option_validation_errors_quote_the_value_sent(client):
    body = {**EXAMPLE_FORMS, "options": {"weighting": "cotangent", "frame_weight": -5}}
    doc = problem(client.post("/v1/reconstruct", json=body), 422, "validation-error")
    values = {e["field"]: e.get("value") for e in doc["errors"]}
    assert values == {"options.weighting": "cotangent", "options.frame_weight": -5}
    assert '(sent: "cotangent")' in doc["detail"] or "(sent: -5)" in doc["detail"]
    # a missing field or an unknown one has no value of its own to quote
    doc = problem(client.post("/v1/forms", json={"vertices": EXAMPLE_MESH["vertices"],
                                                 "triangles": EXAMPLE_MESH["faces"]}),
                  422, "validation-error")
    assert all("value" not in e for e in doc["errors"]) and "sent" not in doc["detail"]


def test_415_names_what_each_endpoint_takes(client):
    doc = problem(client.post("/v1/forms", content=b"x", headers={"content-type": "text/plain"}),
                  415, "unsupported-media-type")
    assert "multipart/form-data" in doc["detail"] and "application/vnd.ffs.arrays" in doc["detail"]
    doc = problem(client.post("/v1/jobs", content=b"x", headers={
        "content-type": "application/vnd.ffs.arrays"}), 415, "unsupported-media-type")
    assert "application/vnd.ffs.arrays' is not supported" in doc["detail"]
    assert "send application/json" in doc["detail"] and "`operation`" in doc["detail"]
    # a session takes JSON only: an upload is not offered as an alternative
    off = b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"
    doc = problem(client.post("/v1/sessions", files={"file": ("tri.off", off)},
                              data={"handles": '[{"vertex": 0}]'}), 415, "unsupported-media-type")
    assert "multipart/form-data" in doc["errors"][0]["reason"]
    assert "send application/json" in doc["detail"] and "multipart" not in doc["detail"].split(
        "send")[1].split("POST /v1/mesh")[0]
    assert "POST /v1/mesh" in doc["detail"]


def test_face_limit_names_faces_and_quotes_the_count():
    V, F = icosphere(2)  # 162 vertices, 320 faces
    with running_app(workers=1, max_vertices=1000, max_faces=300) as small:
        doc = problem(small.post("/v1/forms", json=mesh_json(V, F)), 413, "mesh-too-large")
        assert doc["errors"][0]["field"] == "faces" and doc["errors"][0]["value"] == 320
        doc = problem(small.post("/v1/sessions", json={**mesh_json(V, F),
                                                       "handles": [{"vertex": 0}]}),
                      413, "mesh-too-large")
        assert doc["errors"][0]["field"] == "faces" and doc["errors"][0]["value"] == 320


def test_a_job_upload_without_operation_says_it_is_required(client):
    off = b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"
    doc = problem(client.post("/v1/jobs", files={"file": ("tri.off", off)}), 422,
                  "validation-error")
    assert doc["errors"][0]["field"] == "operation" and doc["errors"][0]["type"] == "missing"
    assert doc["detail"].startswith("operation: Field required") and "sent" not in doc["detail"]


def test_an_unknown_query_parameter_is_refused_not_ignored(client):
    """``?colour=defect`` was answered without colours, as if nothing had been asked."""
    response = client.post("/v1/reconstruct?colour=defect", json=EXAMPLE_FORMS)
    doc = problem(response, 422, "validation-error")
    assert doc["errors"][0]["field"] == "query.colour"
    assert doc["errors"][0]["value"] == "defect" and '(sent: "defect")' in doc["detail"]
    assert "`format` and `color`" in doc["detail"]
    ok = client.post("/v1/reconstruct?color=defect&format=json", json=EXAMPLE_FORMS)
    assert ok.status_code == 200 and "colors" in ok.json()


def test_a_field_that_is_not_an_object_names_no_python_class(client):
    """A form field that is not JSON (``-F 'handles=not json'``) is read as a string: the
    problem says a JSON object was expected, not pydantic's "instance of HandleTarget"."""
    off = b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"
    doc = problem(client.post("/v1/deform", files={"file": ("tri.off", off)},
                              data={"handles": "not json"}), 422, "validation-error")
    assert doc["errors"][0]["reason"] == "Input should be a JSON object", doc
    assert doc["errors"][0]["value"] == "not json" and "instance" not in doc["detail"]


@pytest.mark.parametrize(("sent", "value", "text"), [
    (float("nan"), "NaN", "NaN"), (float("-inf"), "-Infinity", "-Infinity"),
    ("NaN", "NaN", '"NaN"'), (-5, -5, "-5"), (None, None, "null"),
    ("x" * 100, "x" * 80 + "…", '"' + "x" * 80 + '…"'),
])
def test_the_detail_quotes_the_value_its_item_quotes(monkeypatch, sent, value, text):
    from service.api import problems

    calls = []
    quote = problems.quoted_value
    monkeypatch.setattr(problems, "quoted_value", lambda e: calls.append(e) or quote(e))
    errors = [{"loc": ("a",), "msg": "bad", "type": "value_error", "input": sent},
              {"loc": ("b",), "msg": "bad", "type": "value_error", "input": 1}]
    doc = problems.from_validation_errors(errors).to_dict()
    assert doc["errors"][0]["value"] == value and f"(sent: {text})" in doc["detail"]
    assert len(calls) == len(errors)  # quoted once per error: the item and the detail share it
