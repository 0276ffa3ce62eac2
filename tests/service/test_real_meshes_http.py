"""Meshes as people have them over HTTP (issue 40), on a real uvicorn: non-manifold uploads,
many parts, a fin at pi, closed surfaces and slivers through forms -> reconstruct (whole mesh
back after one rigid alignment, in the file's numbering), noisy forms, deform, flatten;
polygons triangulated the same way in OFF, PLY and OBJ and reported; angles wrapped."""

from __future__ import annotations

import json

import httpx
import numpy as np
import pytest

import solver
from solver.mesh.io import read_mesh, save_mesh
from tests.helpers.meshes import rigid_alignment_error
from tests.helpers.real_meshes import CASES, HAS_CLOSED_PART, ZERO_AREA, diagonal

TIMEOUT = 120.0


@pytest.fixture(scope="module")
def http(live_server):
    with httpx.Client(base_url=live_server, timeout=TIMEOUT) as session:
        yield session


@pytest.mark.parametrize("name", list(CASES))
def test_upload_forms_reconstruct_is_the_whole_mesh(http, name):
    V, F = CASES[name]()
    data = save_mesh(V, F, "off")
    forms = http.post("/v1/forms", files={"file": (f"{name}.off", data)})
    assert forms.status_code == 200, forms.text
    doc = forms.json()
    assert ("vertex_map" in doc) == (name in {"edge-with-3-faces", "edge-with-4-faces",
                                              "cones-at-apex"})
    rebuilt = http.post("/v1/reconstruct", json=doc)  # the forms response is the body
    assert rebuilt.status_code == 200, rebuilt.text
    answer = rebuilt.json()
    vertices = np.asarray(answer["vertices"])
    assert vertices.shape == V.shape
    np.testing.assert_array_equal(answer["faces"], F)  # the file's faces and numbering
    assert rigid_alignment_error(vertices, V) < 1e-8
    assert answer["report"]["refinement"]["refined"] is False


@pytest.mark.parametrize("name", ["edge-with-3-faces", "cones-at-apex", "multi-component",
                                  "fin-at-pi", "slivers-1e-4", "slivers-1e-6",
                                  "zero-area-inserted"])
def test_noisy_forms_converge(http, name):
    V, F = CASES[name]()
    forms = solver.fundamental_forms(V, F)
    rng = np.random.default_rng(5)
    interior = solver.check_integrability(forms.faces, forms.edges, forms.lengths,
                                          forms.angles).vertex_defect is not None
    angles = forms.angles + np.where(forms.angles != 0, rng.normal(0, 1e-3, len(forms.angles)),
                                     0.0)
    body = {"faces": forms.faces.tolist(), "edges": forms.edges.tolist(),
            "lengths": forms.lengths.tolist(), "angles": angles.tolist(),
            "placement": forms.placement.to_dict()}
    if forms.vertex_map is not None:
        body["vertex_map"] = forms.vertex_map.tolist()
    response = http.post("/v1/reconstruct", json=body)
    assert response.status_code == 200, response.text
    refinement = response.json()["report"]["refinement"]
    assert interior and refinement["refined"] and refinement["converged"], refinement
    assert refinement["factorizations"] <= 4
    if name.startswith("slivers") or name in ZERO_AREA:  # needles, zero-area faces
        well = refinement["well_shaped_error"]
        assert well["refined"] <= well["start"] * (1 + 1e-9)
    assert rigid_alignment_error(np.asarray(response.json()["vertices"]), V) < 0.05


@pytest.mark.parametrize("name", sorted(ZERO_AREA))
def test_zero_area_faces_are_answered_and_reported(http, name):
    """Faces with collinear corners: the forms name them (as an independent cross product
    finds them), the forms document goes back to reconstruct as it is, and reconstruct,
    deform and (open meshes) flatten count them in their report."""
    V, F = CASES[name]()
    cross = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    flat = np.flatnonzero(np.linalg.norm(cross, axis=1) <= 1e-12 * diagonal(V) ** 2)
    upload = {"file": (f"{name}.ply", save_mesh(V, F, "ply"))}
    doc = http.post("/v1/forms", files=upload).json()
    assert doc["zero_area_faces"] == flat.tolist()
    rebuilt = http.post("/v1/reconstruct", json=doc)
    assert rebuilt.status_code == 200, rebuilt.text
    assert rebuilt.json()["report"]["input"]["zero_area_faces"] == len(flat)
    handles = [{"vertex": int(v), "position": (V[v] + 0.01).tolist()} for v in F[0]]
    deformed = http.post("/v1/deform", files=upload, data={"handles": json.dumps(handles)})
    assert deformed.status_code == 200, deformed.text
    assert deformed.json()["report"]["input"]["zero_area_faces"] == len(flat)
    if name not in HAS_CLOSED_PART:
        flattened = http.post("/v1/parameterize", files=upload)
        assert flattened.status_code == 200, flattened.text
        assert flattened.json()["report"]["input"]["zero_area_faces"] == len(flat)


@pytest.mark.parametrize("name", list(CASES))
def test_deform_upload_hits_its_handles(http, name):
    V, F = CASES[name]()
    rng = np.random.default_rng(8)
    handles = rng.choice(np.unique(F), 3, replace=False)
    targets = V[handles] + rng.normal(0, 0.05 * diagonal(V), (3, 3))
    spec = [{"vertex": int(v), "position": p} for v, p in zip(handles, targets.tolist(),
                                                              strict=True)]
    response = http.post("/v1/deform", files={"file": (f"{name}.ply", save_mesh(V, F, "ply"))},
                         data={"handles": json.dumps(spec)})
    assert response.status_code == 200, response.text
    moved = np.asarray(response.json()["vertices"])
    np.testing.assert_allclose(moved[handles], targets, atol=1e-8 * diagonal(V))
    np.testing.assert_array_equal(response.json()["faces"], F)


@pytest.mark.parametrize("name", [n for n in CASES if n not in HAS_CLOSED_PART])
def test_flatten_upload_accepts_them(http, name):
    V, F = CASES[name]()
    response = http.post("/v1/parameterize",
                         files={"file": (f"{name}.obj", save_mesh(V, F, "obj"))})
    assert response.status_code == 200, response.text
    assert np.asarray(response.json()["uv"]).shape == (len(V), 2)


def test_non_manifold_mesh_is_read_and_reported(http):
    V, F = CASES["edge-with-4-faces"]()
    response = http.post("/v1/mesh", files={"file": ("boxes.off", save_mesh(V, F, "off"))})
    assert response.status_code == 200, response.text
    cut = response.json()["report"]["input"]["cut"]
    assert cut["split_edges"] == 1 and cut["split_vertices"] == 2


POLYGONS = {
    "off": b"OFF\n6 3 0\n0 0 0\n1 0 0\n1 1 0.2\n0 1 0\n2 0 0.1\n2 1 0.3\n"
           b"4 0 1 2 3\n3 1 4 2\n3 4 5 2\n",
    "obj": b"v 0 0 0\nv 1 0 0\nv 1 1 0.2\nv 0 1 0\nv 2 0 0.1\nv 2 1 0.3\n"
           b"f 1 2 3 4\nf 2 5 3\nf 5 6 3\n",
    "ply": b"ply\nformat ascii 1.0\nelement vertex 6\nproperty double x\nproperty double y\n"
           b"property double z\nelement face 3\nproperty list uchar int vertex_indices\n"
           b"end_header\n0 0 0\n1 0 0\n1 1 0.2\n0 1 0\n2 0 0.1\n2 1 0.3\n"
           b"4 0 1 2 3\n3 1 4 2\n3 4 5 2\n",
}


def test_polygons_are_triangulated_the_same_way_and_reported(http):
    expected = [[0, 1, 2], [0, 2, 3], [1, 4, 2], [4, 5, 2]]
    for fmt, data in POLYGONS.items():
        loaded = read_mesh(data, fmt)
        assert loaded.faces.tolist() == expected, fmt
        assert loaded.polygons == 1 and loaded.face_polygon.tolist() == [0, 0, 1, 2]
        response = http.post("/v1/mesh", files={"file": (f"quads.{fmt}", data)})
        assert response.status_code == 200, response.text
        assert response.json()["faces"] == expected
        assert response.json()["report"]["input"]["triangulated_polygons"] == 1
        handles = [{"vertex": 0, "position": [0, 0, 0]}, {"vertex": 5, "position": [2, 1, 0.5]}]
        deformed = http.post("/v1/deform", files={"file": (f"quads.{fmt}", data)},
                             data={"handles": json.dumps(handles)})
        assert deformed.status_code == 200, deformed.text
        assert deformed.json()["report"]["input"]["triangulated_polygons"] == 1


def test_angles_beyond_pi_are_wrapped_not_refused(http):
    V, F = CASES["fin-at-pi"]()
    forms = solver.fundamental_forms(V, F)
    at_pi = np.isclose(np.abs(forms.angles), np.pi)
    angles = np.where(at_pi, np.pi + 1e-3, forms.angles)
    body = {"faces": forms.faces.tolist(), "edges": forms.edges.tolist(),
            "lengths": forms.lengths.tolist(), "angles": angles.tolist()}
    checked = http.post("/v1/integrability", json=body)
    assert checked.status_code == 200, checked.text
    assert checked.json()["wrapped_angles"] == int(at_pi.sum())
    rebuilt = http.post("/v1/reconstruct", json=body)
    assert rebuilt.status_code == 200, rebuilt.text
    assert rebuilt.json()["report"]["input"]["wrapped_angles"] == int(at_pi.sum())


def test_bad_vertex_map_is_a_clear_422(http):
    V, F = CASES["cones-at-apex"]()
    doc = http.post("/v1/forms", files={"file": ("cones.off", save_mesh(V, F, "off"))}).json()
    doc["vertex_map"] = doc["vertex_map"][:-1]  # one cut vertex without a file vertex
    response = http.post("/v1/reconstruct", json=doc)
    assert response.status_code == 422, response.text
    assert "faces" in response.text or "vertex_map" in response.text


def test_hostile_vertex_map_and_placement_are_422(http):
    V, F = CASES["cones-at-apex"]()
    doc = http.post("/v1/forms", files={"file": ("cones.off", save_mesh(V, F, "off"))}).json()
    huge = {**doc, "vertex_map": [*doc["vertex_map"][:-1], 10**9]}
    assert http.post("/v1/reconstruct", json=huge).status_code == 422
    bad_frame = {**doc, "placement": {**doc["placement"],
                                      "frames": [[[2.0, 0, 0], [0, 1, 0], [0, 0, 1]]] * 2}}
    assert http.post("/v1/reconstruct", json=bad_frame).status_code == 422
    short = {**doc, "placement": {**doc["placement"], "faces": doc["placement"]["faces"][:1]}}
    assert http.post("/v1/reconstruct", json=short).status_code == 422
    twice = {**doc, "placement": {**doc["placement"], "faces": [0, 1]}}
    response = http.post("/v1/reconstruct", json=twice)  # two anchors in one part
    assert response.status_code == 422, response.text
    assert "placement" in response.text


def test_integrable_sliver_forms_are_not_refined_with_require_integrable(http):
    V, F = CASES["slivers-1e-6"]()
    forms = solver.fundamental_forms(V, F)
    body = {"faces": forms.faces.tolist(), "edges": forms.edges.tolist(),
            "lengths": forms.lengths.tolist(), "angles": forms.angles.tolist(),
            "options": {"require_integrable": True}}
    response = http.post("/v1/reconstruct", json=body, params={"color": "defect"})
    assert response.status_code == 200, response.text
    assert response.json()["report"]["refinement"]["refined"] is False
    assert rigid_alignment_error(np.asarray(response.json()["vertices"]), V) < 1e-8


def test_empty_vertex_map_is_a_422(http):
    V, F = CASES["cones-at-apex"]()
    doc = http.post("/v1/forms", files={"file": ("cones.off", save_mesh(V, F, "off"))}).json()
    for operation in ("integrability", "reconstruct"):
        response = http.post(f"/v1/{operation}", json={**doc, "vertex_map": []})
        assert response.status_code == 422, response.text
