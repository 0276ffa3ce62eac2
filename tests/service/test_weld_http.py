"""Vertices joined by zero-length edges over HTTP (issue 40, solver.mesh.weld), on a real
uvicorn: an upload's forms carry ``weld_map`` and ``dropped_faces`` (the counts of the
construction), the forms document goes back to /v1/reconstruct as it is and answers the
file's vertices (one rigid alignment, 1e-8 of the diagonal; welded copies at one position),
deform and flatten uploads report the weld; handles on two copies with different targets
are a 422 naming both."""

from __future__ import annotations

import json

import httpx
import numpy as np
import pytest

from solver.mesh.io import save_mesh
from solver.mesh.weld import weld_vertices
from tests.helpers.meshes import rigid_alignment_error
from tests.helpers.real_meshes import diagonal
from tests.helpers.welded_meshes import CASES

NAMES = ["latlong-capsule", "duplicated-corner", "repeated-index-face", "bunny-welded-pairs"]


@pytest.fixture(scope="module")
def http(live_server):
    with httpx.Client(base_url=live_server, timeout=120.0) as session:
        yield session


@pytest.mark.parametrize("fmt", ["off", "ply"])
@pytest.mark.parametrize("name", NAMES)
def test_upload_forms_reconstruct_is_the_files_mesh(http, name, fmt):
    V, F, welded, dropped = CASES[name]()
    upload = {"file": (f"{name}.{fmt}", save_mesh(V, F, fmt))}
    response = http.post("/v1/forms", files=upload)
    assert response.status_code == 200, response.text
    doc = response.json()
    assert len(doc["dropped_faces"]) == dropped and len(doc["faces"]) == len(F) - dropped
    weld_map = np.asarray(doc.get("weld_map", np.arange(len(V))))
    assert int((weld_map != np.arange(len(V))).sum()) == welded
    rebuilt = http.post("/v1/reconstruct", json=doc)  # the forms response is the body
    assert rebuilt.status_code == 200, rebuilt.text
    answer = rebuilt.json()
    vertices = np.asarray(answer["vertices"])
    assert vertices.shape == V.shape
    assert rigid_alignment_error(vertices, V) < 1e-8
    np.testing.assert_array_equal(vertices, vertices[weld_map])
    if welded:
        assert answer["report"]["input"]["weld"]["welded_vertices"] == welded
    checked = http.post("/v1/integrability", json=doc)
    assert checked.status_code == 200 and checked.json()["integrable"], checked.text
    assert len(checked.json()["vertex_defect"]) == len(V)


@pytest.mark.parametrize("name", NAMES)
def test_deform_and_flatten_uploads_report_the_weld(http, name):
    V, F, welded, dropped = CASES[name]()
    upload = {"file": (f"{name}.off", save_mesh(V, F, "off"))}
    rng = np.random.default_rng(2)
    handles = rng.choice(np.unique(F), 3, replace=False)
    targets = V[handles] + rng.normal(0, 0.05 * diagonal(V), (3, 3))
    spec = [{"vertex": int(v), "position": p} for v, p in zip(handles, targets.tolist(),
                                                             strict=True)]
    response = http.post("/v1/deform", files=upload, data={"handles": json.dumps(spec)})
    assert response.status_code == 200, response.text
    moved = np.asarray(response.json()["vertices"])
    np.testing.assert_allclose(moved[handles], targets, atol=1e-8 * diagonal(V))
    report = response.json()["report"]["input"]["weld"]
    assert report["dropped_faces"] == dropped and report["welded_vertices"] == welded
    if name == "latlong-capsule":  # the flattening keeps its seam open: one chart
        flat = http.post("/v1/parameterize", files=upload)
        assert flat.status_code == 200, flat.text
        poles_only = len(weld_vertices(F, V).welded_vertices)  # zero-length edges only
        assert flat.json()["report"]["input"]["weld"]["welded_vertices"] == poles_only < welded


def test_conflicting_targets_on_welded_copies_are_a_422(http):
    V, F, _, _ = CASES["latlong-capsule"]()
    pole = [0, 1]  # the first two copies of the south pole: welded into one vertex
    spec = [{"vertex": 0, "position": V[0].tolist()},
            {"vertex": 1, "position": (V[1] + [0.0, 0.0, 0.1]).tolist()}]
    response = http.post("/v1/deform", files={"file": ("c.off", save_mesh(V, F, "off"))},
                         data={"handles": json.dumps(spec)})
    assert response.status_code == 422, response.text
    doc = response.json()
    assert doc["type"].endswith("invalid-constraint")
    assert all(str(v) in doc["detail"] for v in pole)
    same = [{"vertex": 0, "position": (V[0] + [0, 0, 0.1]).tolist()},
            {"vertex": 1, "position": (V[1] + [0, 0, 0.1]).tolist()},
            {"vertex": len(V) - 1, "position": V[-1].tolist()}]
    response = http.post("/v1/deform", files={"file": ("c.off", save_mesh(V, F, "off"))},
                         data={"handles": json.dumps(same)})
    assert response.status_code == 200, response.text
    moved = np.asarray(response.json()["vertices"])
    np.testing.assert_allclose(moved[:2], [same[0]["position"]] * 2, atol=1e-9)


def test_session_drags_a_welded_mesh_per_file_vertex(http):
    """A deform session on the capsule: a drag of handles on two pole copies (one target)
    answers every file vertex, the copies at one position, equal to /v1/deform's answer."""
    V, F, _, _ = CASES["latlong-capsule"]()
    handles = [0, 1, len(V) - 1]
    targets = [(V[0] + [0.0, 0.0, -0.2]).tolist()] * 2 + [V[-1].tolist()]
    created = http.post("/v1/sessions", json={
        "vertices": V.tolist(), "faces": F.tolist(),
        "handles": [{"vertex": h} for h in handles]})
    assert created.status_code == 201, created.text
    location = created.headers["location"]
    try:
        solved = http.post(f"{location}/solve", json={"handle_positions": targets})
        assert solved.status_code == 200, solved.text
        dragged = np.asarray(solved.json()["vertices"])
        assert dragged.shape == V.shape
        np.testing.assert_allclose(dragged[handles], targets, atol=1e-9)
        columns = 20  # every copy of the south pole moved with its handle
        np.testing.assert_allclose(dragged[:columns + 1], [targets[0]] * (columns + 1),
                                   atol=1e-9)
        spec = [{"vertex": h, "position": p} for h, p in zip(handles, targets, strict=True)]
        once = http.post("/v1/deform", json={"vertices": V.tolist(), "faces": F.tolist(),
                                              "handles": spec, "options": {"refine": False}})
        assert once.status_code == 200, once.text
        np.testing.assert_allclose(dragged, once.json()["vertices"], atol=1e-6)
        clash = http.post(f"{location}/solve", json={"handle_positions": [
            targets[0], V[1].tolist(), targets[2]]})
        assert clash.status_code == 422, clash.text
    finally:
        http.delete(location)
