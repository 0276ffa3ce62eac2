"""openapi/openapi.json is generated from the app (scripts/generate_openapi.py) and complete."""

from __future__ import annotations

import json

from scripts import generate_openapi
from tests.helpers import REPO


def test_committed_openapi_is_up_to_date():
    current = (REPO / "openapi" / "openapi.json").read_text(encoding="utf-8")
    assert current == generate_openapi.render(), (
        "openapi/openapi.json is stale: run `python scripts/generate_openapi.py`")


def test_every_schema_has_an_example():
    doc = json.loads((REPO / "openapi" / "openapi.json").read_text(encoding="utf-8"))
    schemas = doc["components"]["schemas"]
    missing = [name for name, schema in schemas.items() if not schema.get("examples")]
    assert not missing, f"schemas without examples: {missing}"
    for path, item in doc["paths"].items():
        for method, operation in item.items():
            body = operation.get("requestBody")
            if body is None:
                continue
            for media, content in body["content"].items():
                has = ("example" in content or "examples" in content
                       or "examples" in content.get("schema", {}))
                assert has, f"{method.upper()} {path} {media} has no example"


def test_error_responses_are_problem_documents():
    doc = json.loads((REPO / "openapi" / "openapi.json").read_text(encoding="utf-8"))
    assert "HTTPValidationError" not in doc["components"]["schemas"]
    for path, item in doc["paths"].items():
        for operation in item.values():
            for code, response in operation["responses"].items():
                if int(code) >= 400 and path != "/readyz":
                    assert list(response["content"]) == ["application/problem+json"], (
                        path, code)


def test_docs_page_and_served_document(client):
    assert "swagger" in client.get("/docs").text.lower()
    served = client.get("/openapi.json").json()
    committed = json.loads((REPO / "openapi" / "openapi.json").read_text(encoding="utf-8"))
    assert served == committed
    for operation in ("forms", "integrability", "reconstruct", "deform", "parameterize",
                      "interpolate"):
        content = served["paths"][f"/v1/{operation}"]["post"]["requestBody"]["content"]
        assert set(content) == {"application/json", "multipart/form-data",
                                "application/vnd.ffs.arrays"}


def _document() -> dict:
    return json.loads((REPO / "openapi" / "openapi.json").read_text(encoding="utf-8"))


def _refs(node):
    if isinstance(node, dict):
        for key, value in node.items():
            if key == "$ref":
                yield value
            else:
                yield from _refs(value)
    elif isinstance(node, list):
        for value in node:
            yield from _refs(value)


def test_every_reference_resolves():
    doc = _document()
    refs = set(_refs(doc))
    assert "#/components/schemas/SessionRequest" in refs
    assert "#/components/schemas/SessionDrag" in refs
    prefix = "#/components/schemas/"
    dangling = sorted(r for r in refs
                      if not r.startswith(prefix) or r[len(prefix):] not in
                      doc["components"]["schemas"])
    assert not dangling, dangling


def test_color_is_documented_only_where_it_works():
    from service.operations import OPERATIONS

    doc = _document()
    for operation in ("forms", "integrability", "reconstruct", "deform", "parameterize",
                      "interpolate", "mesh"):
        params = {p["name"]: p for p in
                  doc["paths"][f"/v1/{operation}"]["post"].get("parameters", [])}
        if not OPERATIONS[operation].colors:
            assert "color" not in params, operation
            continue
        options = {s.get("const") for s in params["color"]["schema"]["anyOf"]} - {None}
        assert options == set(OPERATIONS[operation].colors), (operation, options)


def test_multipart_parameter_fields_are_documented_as_sent():
    """Every parameter field is a property of the upload form; arrays are arrays (one part
    per item) except nested ones (one JSON part), objects are JSON parts, and nothing is
    nullable (a field is left out instead)."""
    from service.http.bodies import array_fields
    from service.operations import OPERATIONS

    doc = _document()
    for operation, spec in OPERATIONS.items():
        form = doc["paths"][f"/v1/{operation}"]["post"]["requestBody"]["content"][
            "multipart/form-data"]
        properties = form["schema"]["properties"]
        assert set(properties) == {*spec.files, *spec.params.model_fields}, operation
        assert form["schema"]["additionalProperties"] is False
        for name in spec.params.model_fields:
            schema = properties[name]
            assert "null" not in json.dumps(schema), (operation, name)
            if name in array_fields(spec.params):
                nested = schema.get("contentMediaType") == "application/json"
                assert schema.get("type") == ("string" if nested else "array"), (operation,
                                                                                name)
            if "$ref" in schema or schema.get("type") in ("array", "string"):
                assert form["encoding"][name] == {"contentType": "application/json"}, (
                    operation, name)


def test_job_upload_fields_are_typed():
    from service.operations import OPERATIONS

    form = _document()["paths"]["/v1/jobs"]["post"]["requestBody"]["content"][
        "multipart/form-data"]
    properties = form["schema"]["properties"]
    every = {name for spec in OPERATIONS.values() for name in (*spec.files,
                                                               *spec.params.model_fields)}
    assert set(properties) == every | {"operation", "color", "callback_url"}  # (issue 46)
    assert form["schema"]["additionalProperties"] is False
    options = {ref["$ref"].rsplit("/", 1)[1] for ref in properties["options"]["anyOf"]}
    assert options == {spec.params.model_fields["options"].annotation.__name__
                       for spec in OPERATIONS.values() if "options" in spec.params.model_fields}
    assert all("default" not in schema for schema in properties.values())


def test_bodies_are_declared_for_every_success():
    """Every 2xx but 204 declares its media types and schema (jobs and sessions included)."""
    doc = _document()
    for path, item in doc["paths"].items():
        for method, operation in item.items():
            for code, response in operation["responses"].items():
                if code.startswith("2") and code != "204":
                    content = response.get("content")
                    assert content, (method, path, code)
                    assert all(media.get("schema") for media in content.values()), (path, code)
    jobs = doc["paths"]["/v1/jobs"]["post"]["responses"]["202"]["content"]
    assert jobs == {"application/json": {"schema": {"$ref": "#/components/schemas/JobStatus"}}}
    session = doc["paths"]["/v1/sessions/{session_id}"]["get"]["responses"]["200"]["content"]
    assert session["application/json"]["schema"]["$ref"].endswith("/SessionInfo")
    assert list(doc["paths"]["/metrics"]["get"]["responses"]["200"]["content"]) == [
        "text/plain"]


def test_format_is_declared_beside_accept_for_mesh_results():
    from service.operations import OPERATIONS

    doc = _document()
    for operation, spec in OPERATIONS.items():
        post = doc["paths"][f"/v1/{operation}"]["post"]
        params = {p["name"]: p for p in post.get("parameters", [])}
        if not spec.mesh_result:
            assert "format" not in params
            continue
        (values,) = [s["enum"] for s in params["format"]["schema"]["anyOf"] if "enum" in s]
        assert values == ["json", "glb", "gltf"]
        assert {"model/gltf-binary", "model/gltf+json"} <= set(post["responses"]["200"][
            "content"])
