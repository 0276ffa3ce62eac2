"""openapi/openapi.json is generated from the app (scripts/generate_openapi.py) and complete."""

from __future__ import annotations

import importlib.util
import json

from service_helpers import REPO


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
        assert set(content) == {"application/json", "multipart/form-data"}
