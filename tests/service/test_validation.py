"""service.api.decoding: JSON arrays checked as arrays, with the request models' rules."""

from __future__ import annotations

import numpy as np
import pytest

from service.api.decoding import (
    BINARY_MEDIA_TYPE,
    MAX_ERRORS,
    MESH_ARRAYS,
    as_array,
    binary_body,
    decode_json,
)
from service.api.problems import ProblemError
from service.api.schemas import SessionParams, SessionRequest
from service.operations import OPERATIONS
from tests.helpers.meshes import bumpy_grid
from tests.helpers.service import forms_json, problem


def request_arrays(operation, doc):
    spec = OPERATIONS[operation]
    return decode_json(spec.arrays, spec.params, doc)

MESH = {"vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0.5]], "faces": [[0, 1, 2]]}


@pytest.mark.parametrize("operation", sorted(OPERATIONS))
def test_the_arrays_are_the_request_model_minus_its_params(operation):
    spec = OPERATIONS[operation]
    documented = set(spec.request.model_fields)
    assert set(spec.arrays) == documented - set(spec.params.model_fields)


def test_session_arrays_match_the_session_model():
    assert set(MESH_ARRAYS) == (set(SessionRequest.model_fields)
                                      - set(SessionParams.model_fields))


def test_valid_body_gives_typed_arrays_and_params():
    arrays, params = request_arrays("deform", {**MESH, "handles": [
        {"vertex": 0, "position": [0, 0, 0]}]})
    assert arrays["vertices"].dtype == np.float64 and arrays["vertices"].shape == (3, 3)
    assert arrays["faces"].dtype == np.int64 and arrays["faces"].tolist() == [[0, 1, 2]]
    assert params.handles[0].vertex == 0
    np.testing.assert_array_equal(arrays["vertices"], np.asarray(MESH["vertices"], float))


def _errors(operation, doc):
    with pytest.raises(ProblemError) as info:
        request_arrays(operation, doc)
    assert info.value.status == 422 and info.value.kind == "validation-error"
    return info.value.errors


@pytest.mark.parametrize(("faces", "pointer", "words"), [
    ([[0, 1]], "/faces/0", "expected 3 values, got 2"),
    ([[0, 1, "2"]], "/faces/0/2", "valid integer, got a string"),
    ([[0, 1, 1.5]], "/faces/0/2", "fractional part"),
    ([[0, 1, True]], "/faces/0/2", "valid integer, got a boolean"),
    ([[0, 1, -1]], "/faces/0/2", "greater than or equal to 0"),
    ([[0, 1, 2**70]], "/faces/0/2", "less than or equal to 2147483647"),
    ([[0, 1, 2], 7], "/faces/1", "got an integer"),
    ([0, 1, 2], "/faces", "flat list of 3 integers"),
    ("0 1 2", "/faces", "valid list, got a string"),
    ([], "/faces", "at least 1 item"),
])
def test_each_kind_of_bad_array_names_its_element(faces, pointer, words):
    errors = _errors("forms", {**MESH, "faces": faces})
    assert errors[0]["pointer"] == pointer and words in errors[0]["reason"], errors


def test_integral_floats_are_indices_and_non_finite_values_are_named():
    arrays, _ = request_arrays("forms", {**MESH, "faces": [[0, 1.0, 2]]})
    assert arrays["faces"].dtype == np.int64 and arrays["faces"].tolist() == [[0, 1, 2]]
    errors = _errors("forms", {**MESH, "vertices": [[0, 0, 0], [1, 0, float("nan")],
                                                   [0, 1, 0]]})
    assert errors[0]["pointer"] == "/vertices/1/2" and "finite" in errors[0]["reason"]


def test_errors_are_capped_and_arrays_and_params_reported_together():
    bad = [[0, 0, "x"]] * 100_000
    errors = _errors("deform", {"vertices": bad, "faces": [[0, 1, 2]],
                                "handles": ["h"] * 100_000})
    vertex_errors = [e for e in errors if e["field"] == "vertices"]
    assert len(vertex_errors) == MAX_ERRORS
    assert [e["index"] for e in vertex_errors] == list(range(MAX_ERRORS))
    assert any(e["field"] == "handles" for e in errors)
    assert len(errors) <= 2 * MAX_ERRORS


def test_flat_list_of_a_million_numbers_is_one_error():
    values, errors = as_array("vertices", [0.5] * 1_000_000, MESH_ARRAYS["vertices"])
    assert values is None and len(errors) == 1
    assert "flat list of 1000000 numbers" in errors[0]["msg"]
    assert "333333 rows" not in errors[0]["msg"]  # 10**6 is not a multiple of 3


def test_missing_array_and_non_object_body():
    errors = _errors("reconstruct", {"faces": [[0, 1, 2]], "edges": [], "lengths": []})
    assert {"field": "angles", "type": "missing"}.items() <= errors[0].items()
    assert _errors("forms", [1, 2, 3])[0]["reason"].startswith("Input should be a JSON object")


def test_binary_body_gives_the_json_answer(client):
    V, F = bumpy_grid(6, 5)
    forms = forms_json(V, F)
    params = {"options": {"orthonormalize": True}}
    arrays = {k: np.asarray(forms[k]) for k in ("faces", "edges", "lengths", "angles")}
    via_json = client.post("/v1/reconstruct", json={**forms, **params})
    via_binary = client.post("/v1/reconstruct", content=binary_body(params, arrays),
                             headers={"content-type": BINARY_MEDIA_TYPE})
    assert via_json.status_code == via_binary.status_code == 200, via_binary.text
    np.testing.assert_array_equal(via_binary.json()["vertices"], via_json.json()["vertices"])
    mesh = client.post("/v1/mesh", content=binary_body({}, {"vertices": V, "faces": F}),
                       headers={"content-type": BINARY_MEDIA_TYPE})
    assert mesh.status_code == 200 and mesh.json()["vertices"] == V.tolist()


def test_binary_body_errors(client):
    def post(body):
        return client.post("/v1/forms", content=body,
                           headers={"content-type": BINARY_MEDIA_TYPE})

    V = np.asarray(MESH["vertices"], dtype=float)
    problem(post(b"nope"), 400, "malformed-request")
    good = binary_body({}, {"vertices": V, "faces": np.array([[0, 1, 2]])})
    problem(post(good[:-8]), 400, "malformed-request")  # truncated
    doc = problem(post(binary_body({}, {"vertices": V, "faces": np.array([[0.0, 1.0, 2.0]])})),
                  422, "validation-error")
    assert doc["errors"][0]["field"] == "faces" and "integer dtype" in doc["errors"][0]["reason"]
    doc = problem(post(binary_body({}, {"vertices": V.ravel(), "faces": np.array([[0, 1, 9]])})),
                  422, "validation-error")
    assert doc["errors"][0]["field"] == "vertices" and "shape (n, 3)" in doc["errors"][0]["reason"]
    V[1, 2] = np.nan
    doc = problem(post(binary_body({"tolerance": 1}, {"vertices": V, "faces": [[0, 1, 2]]})),
                  422, "validation-error")
    assert {e["pointer"] for e in doc["errors"]} == {"/vertices/1/2", "/tolerance"}
