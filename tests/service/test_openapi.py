"""openapi/openapi.json is generated from the app (scripts/generate_openapi.py) and complete."""

from __future__ import annotations

import importlib.util
import json

from helpers.service import REPO


def _script():
    spec = importlib.util.spec_from_file_location("generate_openapi",
                                                  REPO / "scripts" / "generate_openapi.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_committed_openapi_is_up_to_date():
    current = (REPO / "openapi" / "openapi.json").read_text(encoding="utf-8")
    assert current == _script().render(), (
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


def test_multipart_parameter_fields_are_documented_as_json():
    from service.operations import OPERATIONS

    doc = _document()
    for operation, spec in OPERATIONS.items():
        model = spec.params
        form = doc["paths"][f"/v1/{operation}"]["post"]["requestBody"]["content"][
            "multipart/form-data"]
        assert set(form["encoding"]) == set(model.model_fields), operation
        for name in model.model_fields:
            assert form["encoding"][name]["contentType"] == "application/json"
            assert form["schema"]["properties"][name].get("type") != "string", (operation, name)
