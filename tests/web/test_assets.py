"""The page's files without a browser: every module the page imports is served, the vendor
build matches the lockfile, and without a build `/` says which command makes it."""

from __future__ import annotations

import json
import re
import warnings

import pytest

from tests.helpers import REPO

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from starlette.testclient import TestClient

STATIC = REPO / "service" / "static"


@pytest.fixture(scope="module")
def plain_client():
    """The app without its lifespan (no worker pool): enough for the static routes."""
    from service.app import create_app
    from service.settings import Settings

    return TestClient(create_app(Settings(workers=1)))


def test_vendor_build_matches_lockfile():
    manifest = json.loads((STATIC / "vendor" / "three" / "manifest.json").read_text())
    lock = json.loads((REPO / "web" / "package-lock.json").read_text())
    assert manifest["version"] == lock["packages"]["node_modules/three"]["version"]
    package = json.loads((REPO / "web" / "package.json").read_text())
    assert package["dependencies"]["three"] == manifest["version"]  # pinned exactly
    for name in manifest["files"]:
        assert (STATIC / "vendor" / "three" / name).is_file(), name


def test_every_import_resolves(plain_client):
    """Relative imports and the import map's bare specifiers of the page's modules exist."""
    html = plain_client.get("/").text
    imports = json.loads(re.search(r'<script type="importmap">(.*?)</script>', html,
                                   re.S).group(1))["imports"]
    for path in [*re.findall(r'(?:src|href)="(/static/[^"]+)"', html)]:
        assert plain_client.get(path).status_code == 200, path
    for module in sorted((STATIC / "js").glob("*.js")):
        for spec in re.findall(r'^import .*? from "([^"]+)";', module.read_text(), re.M | re.S):
            if spec.startswith("./"):
                url = f"/static/js/{spec[2:]}"
            elif spec in imports:
                url = imports[spec]
            else:
                prefix = next(p for p in imports if p.endswith("/") and spec.startswith(p))
                url = imports[prefix] + spec[len(prefix):]
            response = plain_client.get(url)
            assert response.status_code == 200, (module.name, spec, url)
            assert "javascript" in response.headers["content-type"]


def test_missing_build_names_the_command(plain_client, monkeypatch, tmp_path):
    from service.http.routes import web

    monkeypatch.setattr(web, "VENDOR_MANIFEST", tmp_path / "missing.json")
    response = plain_client.get("/")
    assert response.status_code == 503
    assert "npm ci --prefix web" in response.text and "/docs" in response.text
