"""The page says where a mesh stands against reconstruct's limits by path (``GET /v1/me``:
``max_faces_by_operation``, ``max_linear_faces_by_operation``,
``max_direct_faces_by_operation``) and against the limit of the other operations its tabs
run that factorize (Deform, Flatten, Blend: ``max_faces_by_operation``), in Debian's Chromium
against a real uvicorn whose FFS_MAX_REQUEST_MEMORY (236 MiB) puts the sample under every
limit, a second mesh between the factorization's limit (the one Deform, Flatten and Blend
have too) and the refined answer's, and a third between the refined answer's and the linear
answer's; what the page says is checked against what the service does with the same meshes
(real reconstruct jobs: refused 413, answered by a linear answer, refined iteratively; a
deformation and a flattening refused 413)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import httpx
import numpy as np
import pytest

from solver.mesh.io import load_mesh_file, save_mesh
from tests.helpers import DATA
from tests.helpers.meshes import bumpy_grid
from tests.helpers.servers import uvicorn_server
from tests.helpers.service import forms_json, mesh_json, problem
from tests.web.conftest import VENDOR_MANIFEST

MEMORY = 236 * 1024**2


@pytest.fixture(scope="module")
def web_server() -> Iterator[str]:
    """This module's server (the ``web`` fixture's page opens it): 236 MiB a request (the
    light operations, which the page calls on a file, fit the largest mesh)."""
    if not VENDOR_MANIFEST.is_file():
        pytest.fail("the page's three.js modules are not built: run `npm ci --prefix web`")
    with uvicorn_server({"FFS_WORKERS": "1", "FFS_MAX_REQUEST_MEMORY": str(MEMORY),
                         "FFS_MAX_FACES": "100000"}) as base:
        yield base


def _reconstruct(base: str, V: np.ndarray, F: np.ndarray, refine: bool | None) -> dict[str, Any]:
    """A reconstruct job of the mesh's forms (angles with noise: the answer is refined) run
    to its end: the submission's problem (4xx) or the finished job's document."""
    forms = forms_json(V, F)
    forms["angles"] = (np.asarray(forms["angles"])
                       + np.random.default_rng(2).normal(scale=1e-3, size=len(forms["angles"]))
                       ).tolist()
    options = {} if refine is None else {"refine": refine}
    with httpx.Client(base_url=base, timeout=120) as http:
        submitted = http.post("/v1/jobs", json={"operation": "reconstruct",
                                                "input": {**forms, "options": options}})
        if submitted.status_code >= 400:
            return submitted.json()
        deadline = time.monotonic() + 300
        while (job := http.get(submitted.headers["location"]).json())["status"] in (
                "queued", "running"):
            assert time.monotonic() < deadline, job
            time.sleep(0.2)
        if job["status"] == "succeeded":
            job["result"] = http.get(job["result_url"] if "result_url" in job
                                     else f"{submitted.headers['location']}/result").json()
        return job


def _line(web: Any) -> tuple[str, list[str]]:
    line = web.page.locator("#service-limits")
    return line.inner_text(), line.get_attribute("class").split()


def test_the_page_says_where_a_mesh_stands_against_reconstructs_limits(web, tmp_path):
    limits = httpx.get(f"{web.base}/v1/me", timeout=30).json()["size_limits"]
    solve = limits["max_faces_by_operation"]["reconstruct"]
    linear = limits["max_linear_faces_by_operation"]["reconstruct"]
    direct = limits["max_direct_faces_by_operation"]["reconstruct"]
    tabs = {limits["max_faces_by_operation"][name] for name in ("deform", "parameterize",
                                                                "blend")}
    assert tabs == {direct}  # the operations that only factorize: the factorization's limit
    knight = load_mesh_file(DATA / "decimated-knight.off")     # 1000 faces
    iterative = bumpy_grid(60, 70)                               # 8400 faces
    over = bumpy_grid(70, 98)                                    # 13 720 faces
    assert len(knight[1]) < direct < len(iterative[1]) <= solve < len(over[1]) <= linear
    assert len(over[1]) <= limits["max_faces_by_operation"]["forms"]  # the page reads it
    assert linear < limits["max_faces"]

    web.open("sample=decimated-knight.off")
    text, classes = _line(web)
    assert (f"({solve:,} to rebuild, {linear:,} for a linear answer, {direct:,} to deform, "
            "flatten or blend)" in text), text
    assert "mesh" not in text and "over-limit" not in classes and "iterative" not in classes

    web.load_file(_saved(tmp_path, "iterative.off", iterative))
    text, classes = _line(web)
    assert text.endswith(f"This mesh is over the {direct:,} faces a factorization fits: it is "
                         "rebuilt iteratively (slower). It is too large to deform, flatten or "
                         "blend."), text
    assert "iterative" in classes and "over-limit" in classes
    # The service: Deform and Flatten refuse it with the limit the page names.
    with httpx.Client(base_url=web.base, timeout=120) as http:
        body = {**mesh_json(*iterative), "handles": [
            {"vertex": 0, "position": iterative[0][0].tolist()}]}
        for path, doc in (("/v1/deform", body), ("/v1/parameterize", mesh_json(*iterative))):
            refused = problem(http.post(path, json=doc), 413, "mesh-too-large")
            assert f"the {direct} faces this operation can take" in refused["detail"], refused
    # The service: the refined answer within the memory, by the iterative path.
    job = _reconstruct(web.base, *iterative, refine=None)
    assert job["status"] == "succeeded", job
    solver = job["result"]["report"]["refinement"]["linear_solver"]
    assert solver["method"] == "iterative", solver

    web.load_file(_saved(tmp_path, "over.off", over))
    text, classes = _line(web)
    assert text.endswith("This mesh is over the limit to rebuild refined; its linear answer "
                         f"(up to {linear:,} faces) fits. It is too large to deform, flatten "
                         "or blend."), text
    assert "over-limit" in classes and "iterative" not in classes
    # The service: the refined answer refused with the limit, the linear answer given.
    refused = _reconstruct(web.base, *over, refine=None)
    assert refused["status"] == 413 and refused["kind"] == "mesh-too-large", refused
    assert f"{solve} faces" in refused["detail"], refused
    job = _reconstruct(web.base, *over, refine=False)
    assert job["status"] == "succeeded", job
    assert len(job["result"]["faces"]) == len(over[1])

    # A linear limit under the mesh's faces: over every limit to solve.
    web.app("app.setSizeLimits(arg)", dict(limits, max_linear_faces_by_operation={
        "reconstruct": len(over[1]) - 1}))
    text, classes = _line(web)
    assert text.endswith("This mesh is over the limit to rebuild. It is too large to deform, "
                         "flatten or blend."), text
    assert "over-limit" in classes
    # A service whose factorization fits the mesh: nothing said.
    web.app("app.setSizeLimits(arg)", dict(
        limits, max_faces_by_operation=dict(limits["max_faces_by_operation"], reconstruct=14000,
                                            deform=14000, parameterize=14000, blend=14000),
        max_direct_faces_by_operation={"reconstruct": 14000}))
    text, classes = _line(web)
    assert "mesh" not in text and "over-limit" not in classes and "iterative" not in classes
    assert "to deform" not in text, text
    # Limits of their own, Blend's alone under the mesh's 13 720 faces: each named, Blend's
    # said to be under the mesh.
    web.app("app.setSizeLimits(arg)", dict(
        limits, max_faces_by_operation=dict(limits["max_faces_by_operation"], reconstruct=16000,
                                            deform=15000, parameterize=15000, blend=12000),
        max_direct_faces_by_operation={"reconstruct": 16000}))
    text, classes = _line(web)
    assert (f"(16,000 to rebuild, {linear:,} for a linear answer, 15,000 to deform or flatten, "
            "12,000 to blend)" in text), text
    assert text.endswith(" It is too large to blend.") and "This mesh" not in text, text
    assert "over-limit" in classes


def _saved(folder: Any, name: str, mesh: tuple[np.ndarray, np.ndarray]) -> Any:
    path = folder / name
    path.write_bytes(save_mesh(*mesh, "off"))
    return path
