"""How many shapes a blend takes: one rule, ``solver.shape_space.MAX_SHAPES`` (1 to 64), read
by the library, the service (JSON, binary and multipart bodies, jobs, OpenAPI), the Python
client and the in-process backend alike; outside it a 422 (``InvalidInputError``) naming
``shapes``. Against a real uvicorn on loopback."""

from __future__ import annotations

import json

import httpx
import numpy as np
import pytest

import ffs
import solver
from ffs.local import Local
from ffs_wire.arrays import BINARY_MEDIA_TYPE, binary_body
from solver.core.errors import SolverInputError
from solver.mesh.io import save_mesh
from solver.shape_space import MAX_SHAPES
from tests.helpers.meshes import icosphere

V, F = icosphere(0)


def _rows(count: int) -> list[list[float]]:
    return [[1.0] + [0.0] * (count - 1)] if count else [[1.0]]


def _bodies(count: int) -> dict[str, dict]:
    """The three kinds of POST /v1/blend body, with ``count`` shapes."""
    shapes = np.repeat(V[None], count, axis=0)
    return {
        "json": {"json": {"shapes": shapes.tolist(), "faces": F.tolist(),
                          "weights": _rows(count)}},
        "binary": {"content": binary_body({"weights": _rows(count)},
                                          {"shapes": shapes, "faces": F}),
                   "headers": {"content-type": BINARY_MEDIA_TYPE}},
        "multipart": {"files": [("shapes", (f"s{k}.off", save_mesh(V, F, "off")))
                                for k in range(count)],
                      "data": {"weights": json.dumps(_rows(count))}},
    }


def _shapes_problem(response: httpx.Response) -> dict:
    assert response.status_code == 422, response.text
    doc = response.json()
    assert doc["kind"] == "validation-error", doc
    assert doc["errors"][0]["field"] in ("shapes", "input.shapes"), doc  # a JSON job: its input
    assert f"{MAX_SHAPES}" in doc["detail"] and "Error" not in doc["detail"], doc
    return doc


def test_the_service_takes_1_to_max_shapes_in_every_body(server):
    with httpx.Client(base_url=server, timeout=120) as http:
        for kind, body in _bodies(1).items():  # one shape: its own nearest surface
            response = http.post("/v1/blend", **body)
            assert response.status_code == 200, (kind, response.text)
            np.testing.assert_allclose(response.json()["vertices"][0], V, atol=1e-9)
        for count in (0, MAX_SHAPES + 1):
            for kind, body in _bodies(count).items():
                if kind == "multipart" and count == 0:
                    continue  # no shapes part at all: "a mesh file is required", below
                doc = _shapes_problem(http.post("/v1/blend", **body))
                assert f"got {count}" in doc["detail"] or kind == "multipart", (kind, doc)
        doc = _shapes_problem(http.post("/v1/blend", files=[("shapes", (
            f"s{k}.off", b"OFF\n")) for k in range(MAX_SHAPES + 10)]))  # past the form's files
        assert "at most" in doc["errors"][0]["reason"]
        response = http.post("/v1/blend", data={"weights": "[[1]]"}, files={"x": ("a", b"")})
        assert response.status_code == 422 and response.json()["errors"][0]["field"] == "shapes"
        # a job is refused at submission, not when it runs
        _shapes_problem(http.post("/v1/jobs", json={
            "operation": "blend", "input": _bodies(MAX_SHAPES + 1)["json"]["json"]}))
        _shapes_problem(http.post("/v1/jobs", data={
            "operation": "blend", **_bodies(MAX_SHAPES + 1)["multipart"]["data"]},
            files=_bodies(MAX_SHAPES + 1)["multipart"]["files"]))
        schema = http.get("/openapi.json").json()["components"]["schemas"]["BlendRequest"]
        assert schema["properties"]["shapes"]["maxItems"] == MAX_SHAPES
        assert schema["properties"]["shapes"]["minItems"] == 1


@pytest.mark.parametrize("binary", [True, False])
def test_client_and_local_backend_agree_with_the_library(server, binary):
    with ffs.Client(server, binary=binary) as client:
        for backend in (client, Local()):
            np.testing.assert_allclose(backend.blend([V], F, [[1.0]]).vertices[0],
                                       solver.blend([V], [[1.0]], F).vertices[0], atol=1e-9)
            np.testing.assert_allclose(backend.mean([V], F).vertices, V, atol=1e-9)
            for count in (0, MAX_SHAPES + 1):
                shapes = np.repeat(V[None], count, axis=0)
                error = ffs.InvalidInputError if backend is client else SolverInputError
                with pytest.raises(error) as info:
                    backend.blend(shapes, F, _rows(count))
                field = (info.value.errors[0]["field"] if backend is client
                         else info.value.field)
                assert field == "shapes", (backend, count, str(info.value))
                with pytest.raises(error):
                    backend.mean(shapes, F)
