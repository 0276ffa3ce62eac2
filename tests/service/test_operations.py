"""Every synchronous endpoint through HTTP, checked against the direct library call."""

from __future__ import annotations

import numpy as np
import pytest

import solver
from service.operations import OPERATIONS
from tests.helpers.meshes import bumpy_grid, icosphere, load
from tests.helpers.service import forms_json, mesh_json, problem, rigid_error


@pytest.mark.parametrize("operation", list(OPERATIONS))
def test_schema_example_is_a_valid_request(client, operation):
    example = OPERATIONS[operation].request.model_config["json_schema_extra"]["examples"][0]
    response = client.post(f"/v1/{operation}", json=example)
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "application/json"
    assert "Server-Timing" in response.headers


def test_forms_match_library(client):
    V, F = load("decimated-knight.off")
    response = client.post("/v1/forms", json=mesh_json(V, F))
    assert response.status_code == 200, response.text
    got = response.json()
    want = solver.fundamental_forms(V, F)
    assert set(got) == {"faces", "edges", "lengths", "angles", "placement"}
    np.testing.assert_array_equal(got["faces"], want.faces)
    np.testing.assert_array_equal(got["edges"], want.edges)
    np.testing.assert_array_equal(got["lengths"], want.lengths)  # orjson floats round-trip
    np.testing.assert_array_equal(got["angles"], want.angles)


def test_forms_output_feeds_integrability_and_reconstruct(client):
    V, F = load("decimated-knight.off")
    forms = client.post("/v1/forms", json=mesh_json(V, F)).json()
    report = client.post("/v1/integrability", json=forms)
    assert report.status_code == 200, report.text
    assert report.json()["integrable"] is True
    rebuilt = client.post("/v1/reconstruct", json=forms)
    assert rebuilt.status_code == 200, rebuilt.text
    body = rebuilt.json()
    assert len(body["vertices"]) == len(V)
    np.testing.assert_array_equal(body["faces"], F)
    assert rigid_error(body["vertices"], V) < 1e-6 * np.ptp(V, axis=0).max()
    assert body["report"]["integrability"]["integrable"] is True


def test_integrability_report_fields_and_torus_holonomy(client):
    V, F = load("torus.off")
    response = client.post("/v1/integrability", json={**forms_json(V, F), "tolerance": 1e-7})
    assert response.status_code == 200, response.text
    doc = response.json()
    want = solver.check_integrability(**{k: v for k, v in forms_json(V, F).items()}, tol=1e-7)
    for key in ("integrable", "local_integrable", "global_integrable"):
        assert doc[key] is getattr(want, key)
    assert doc["max_defect"] == pytest.approx(want.max_defect, abs=1e-15)
    assert doc["tolerance"] == 1e-7
    for key in ("vertex_defect", "gauss_defect", "codazzi_defect"):
        np.testing.assert_allclose(doc[key], getattr(want, key), atol=1e-15)
        assert len(doc[key]) == len(V)
    assert doc["topology"]["genus"] == 1 and doc["topology"]["n_components"] == 1
    assert doc["topology"]["boundary_loops"] == []
    assert doc["topology"]["components"][0]["closed"] is True
    holonomy = doc["global_holonomy"]
    assert len(holonomy["rotation"]) == 2 and len(holonomy["translation"]) == 2
    assert all(loop["passes"] for loop in holonomy["rotation"] + holonomy["translation"])


def test_integrability_of_perturbed_forms_names_worst_vertices(client):
    V, F = icosphere(2)
    forms = forms_json(V, F)
    forms["angles"][5] += 0.05
    doc = client.post("/v1/integrability", json=forms).json()
    assert doc["integrable"] is False and doc["local_integrable"] is False
    edge = forms["edges"][5]
    assert set(doc["worst_vertices"][:2]) == set(edge)
    assert doc["max_defect"] > 0.01
    assert set(doc["failing_vertices"]) >= set(edge)


def test_integrability_open_mesh_with_holes_and_file_upload(client):
    from tests.helpers.meshes import bumpy_grid_with_holes

    V, F = bumpy_grid_with_holes()
    doc = client.post("/v1/integrability", json=forms_json(V, F)).json()
    assert doc["integrable"] is True
    assert len(doc["topology"]["boundary_loops"]) == 3
    assert len(doc["global_holonomy"]["rotation"]) == 2  # 2g + b - 1


def test_reconstruct_equals_library_call(client):
    V, F = load("face.off")
    forms = forms_json(V, F)
    body = {**forms, "options": {"frame_weight": 500.0, "orthonormalize": True}}
    response = client.post("/v1/reconstruct", json=body)
    assert response.status_code == 200, response.text
    got = response.json()
    want = solver.reconstruct(forms["faces"], forms["edges"], forms["lengths"], forms["angles"],
                              frame_weight=500.0, orthonormalize=True)
    np.testing.assert_allclose(got["vertices"], want.vertices, atol=1e-9)
    report = got["report"]
    assert report["orthonormalized"] is True and report["frame_weight"] == 500.0
    summary = report["integrability"]
    assert set(summary) >= {"integrable", "max_defect", "worst_vertices", "rotation_holonomy",
                            "translation_holonomy"}
    # Exact forms take the tree-integration path: no factorization stage.
    assert report["solve_path"] == "tree-integration"
    assert set(report["timings"]) >= {"validate", "assemble", "solve"}


def test_reconstruct_with_position_and_frame_constraints(client):
    V, F = icosphere(2)
    forms = forms_json(V, F)
    # Positions alone fix the frames only if they span 3D: four extreme, non-coplanar vertices.
    pinned = [int(np.argmax(V[:, 0])), int(np.argmin(V[:, 0])), int(np.argmax(V[:, 1])),
              int(np.argmax(V[:, 2]))]
    spread = V[pinned[1:]] - V[pinned[0]]
    assert abs(np.linalg.det(spread)) > 0.1
    constraints = {"positions": [{"vertex": v, "position": V[v].tolist()} for v in pinned]}
    got = client.post("/v1/reconstruct", json={**forms, "constraints": constraints}).json()
    X = np.asarray(got["vertices"])
    np.testing.assert_allclose(X[pinned], V[pinned], atol=1e-12)  # hard constraints are exact
    np.testing.assert_allclose(X, V, atol=1e-6)  # and they fix the rigid motion

    # A frame constraint (rotation about z by 90 degrees of face 0's frame) + one soft position.
    anchored = client.post("/v1/reconstruct", json=forms).json()
    frame = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    body = {**forms, "constraints": {
        "frames": [{"face": 0, "frame": frame}],
        "positions": [{"vertex": 0, "position": [1.0, 2.0, 3.0], "weight": 10.0}]}}
    got = client.post("/v1/reconstruct", json=body)
    assert got.status_code == 200, got.text
    Y = np.asarray(got.json()["vertices"])
    assert rigid_error(Y, np.asarray(anchored["vertices"])) < 1e-6
    np.testing.assert_allclose(Y[0], [1.0, 2.0, 3.0], atol=1e-6)


def test_reconstruct_require_integrable(client):
    V, F = icosphere(2)
    forms = forms_json(V, F)
    forms["angles"][7] += 0.1
    lenient = client.post("/v1/reconstruct", json=forms)
    assert lenient.status_code == 200, lenient.text
    summary = lenient.json()["report"]["integrability"]
    assert summary["integrable"] is False
    strict = client.post("/v1/reconstruct",
                         json={**forms, "options": {"require_integrable": True}})
    doc = problem(strict, 422, "not-integrable")
    edge = set(forms["edges"][7])
    assert set(doc["worst_vertices"][:2]) == edge
    named = {e["index"] for e in doc["errors"] if e["field"] == "vertices"}
    assert named >= edge
    assert "worst vertices" in doc["detail"]
    assert doc["integrability"]["integrable"] is False
    # Units (issue 43): the defect and its tolerance are angles.
    defect = doc["integrability"]["max_defect"]
    assert f"max defect {defect:.3g} rad (tolerance 1e-08 rad)" in doc["detail"], doc["detail"]


def test_reconstruct_colored_by_defect(client):
    V, F = icosphere(1)
    forms = forms_json(V, F)
    forms["angles"][3] += 0.05
    doc = client.post("/v1/reconstruct", params={"color": "defect"}, json=forms).json()
    colors = np.asarray(doc["colors"])
    assert colors.shape == (len(V), 4)
    assert np.all((colors >= 0) & (colors <= 1)) and np.all(colors[:, 3] == 1)
    defect = solver.check_integrability(**forms_json(V, F) | {"angles": forms["angles"]})
    hot = int(np.argmax(defect.vertex_defect))
    cold = int(np.argmin(defect.vertex_defect))
    assert not np.allclose(colors[hot], colors[cold])


def test_deform_equals_library_call(client):
    V, F = bumpy_grid()
    handles = [0, 5, len(V) - 1]
    targets = V[handles] + [[0, 0, 0], [0, 0, 0.1], [0, 0, 0.3]]
    body = {**mesh_json(V, F),
            "handles": [{"vertex": h, "position": p.tolist()}
                        for h, p in zip(handles, targets, strict=True)],
            "options": {"orthonormalize": True}}
    response = client.post("/v1/deform", json=body)
    assert response.status_code == 200, response.text
    got = response.json()
    want = solver.deform(V, F, handles, targets, orthonormalize=True)
    np.testing.assert_allclose(got["vertices"], want.vertices, atol=1e-9)
    np.testing.assert_allclose(np.asarray(got["vertices"])[handles], targets, atol=1e-12)
    distortion = got["report"]["distortion"]
    assert len(distortion["vertex"]) == len(V)
    assert distortion["length_summary"]["max"] > 0


def test_deform_with_rotation_handles_and_roi(client):
    V, F = bumpy_grid()
    roi = list(range(len(V) // 2))
    rot = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    body = {**mesh_json(V, F), "handles": [{"vertex": 0, "position": V[0].tolist()}],
            "rotations": [{"faces": [0, 1], "rotation": rot}], "roi": roi}
    response = client.post("/v1/deform", json=body)
    assert response.status_code == 200, response.text
    want = solver.deform(V, F, [0], V[[0]], rotation_handles=[np.array([0, 1])],
                         handle_rotations=np.array([rot]), roi=np.array(roi))
    got = np.asarray(response.json()["vertices"])
    np.testing.assert_allclose(got, want.vertices, atol=1e-9)
    outside = np.setdiff1d(np.arange(len(V)), roi)
    np.testing.assert_array_equal(got[outside], V[outside])


def test_deform_colored_by_distortion(client):
    V, F = bumpy_grid()
    body = {**mesh_json(V, F), "handles": [{"vertex": 0, "position": [0.0, 0.0, 0.5]},
                                           {"vertex": len(V) - 1,
                                            "position": V[-1].tolist()}]}
    doc = client.post("/v1/deform", params={"color": "distortion"}, json=body).json()
    assert np.asarray(doc["colors"]).shape == (len(V), 4)


def test_parameterize_equals_library_call(client):
    V, F = load("face.off")
    response = client.post("/v1/parameterize", json=mesh_json(V, F))
    assert response.status_code == 200, response.text
    got = response.json()
    assert set(got) == {"uv", "flipped_faces", "report", "texcoords", "uv_faces", "uv_vertex",
                        "face_chart"}
    want = solver.parameterize(V, F)
    np.testing.assert_allclose(got["uv"], want.uv, atol=1e-9)
    np.testing.assert_allclose(got["texcoords"], want.texcoords, atol=1e-9)
    assert got["uv_faces"] == F.tolist() and got["uv_vertex"] == list(range(len(V)))
    assert got["flipped_faces"] == want.flipped_faces.tolist()
    assert got["report"]["flipped_count"] == len(want.flipped_faces)


def test_parameterize_closed_mesh_is_422_without_seams(client):
    V, F = icosphere(1)
    doc = problem(client.post("/v1/parameterize", json={**mesh_json(V, F),
                                                        "options": {"seams": "none"}}), 422,
                  "unsupported-topology")
    assert doc["errors"][0]["field"] == "faces"
    assert doc["errors"][0]["closed_components"] == [0]


def test_interpolate_scalar_and_list(client):
    V, F = bumpy_grid()
    W = V.copy()
    W[:, 2] *= -1.5
    base = {"vertices_a": V.tolist(), "vertices_b": W.tolist(), "faces": F.tolist()}
    single = client.post("/v1/interpolate", json={**base, "t": 0.5})
    assert single.status_code == 200, single.text
    doc = single.json()
    assert doc["t"] == 0.5 and np.asarray(doc["vertices"]).shape == V.shape
    np.testing.assert_allclose(doc["vertices"], solver.interpolate(V, W, F, 0.5), atol=1e-9)
    several = client.post("/v1/interpolate", json={**base, "t": [0.0, 0.25, 1.0]}).json()
    X = np.asarray(several["vertices"])
    assert several["t"] == [0.0, 0.25, 1.0] and X.shape == (3, *V.shape)
    np.testing.assert_allclose(X, solver.interpolate(V, W, F, [0.0, 0.25, 1.0]), atol=1e-9)
    assert np.abs(X[0] - V).max() < 1e-6 and np.abs(X[2] - W).max() < 1e-6


def test_refine_option_reaches_deform_parameterize_interpolate_and_sessions(client):
    V, F = bumpy_grid(8, 6)
    lifted = (V[-1] + [0, 0, 0.6]).tolist()
    handles = [{"vertex": 0, "position": V[0].tolist()}, {"vertex": len(V) - 1,
                                                          "position": lifted}]

    def post(path, body, refine):
        options = {} if refine is None else {"refine": refine}
        response = client.post(path, json={**body, "options": {**body.get("options", {}),
                                                               **options}})
        assert response.status_code == 200, response.text
        return response.json()

    deform = {r: post("/v1/deform", {**mesh_json(V, F), "handles": handles}, r)
              for r in (None, False)}
    assert deform[None]["report"]["refinement"]["refined"] is True
    assert deform[False]["report"]["refinement"]["refined"] is False
    assert not np.allclose(deform[None]["vertices"], deform[False]["vertices"], atol=1e-3)
    flat = {r: post("/v1/parameterize", {**mesh_json(V, F), "options": {"seams": "none"}}, r)
            for r in (None, False)}
    assert flat[None]["report"]["refinement"]["refined"] is True
    assert not np.allclose(flat[None]["uv"], flat[False]["uv"], atol=1e-3)
    B = V.copy()
    B[:, 2] *= -1.5
    pair = {"vertices_a": V.tolist(), "vertices_b": B.tolist(), "faces": F.tolist(), "t": 0.5}
    blend = {r: post("/v1/interpolate", pair, r) for r in (None, False)}
    assert not np.allclose(blend[None]["vertices"], blend[False]["vertices"], atol=1e-3)
    assert blend[None]["refinement"]["refined"] is True
    assert blend[None]["refinement"]["after"]["length_error"]["mean"] < \
        blend[None]["refinement"]["before"]["length_error"]["mean"]
    assert blend[False]["refinement"]["refined"] is False
    # A session drags linearly by default (latency); with refine=true a drag answers the
    # linear shape at once and links the refined one, which is /v1/deform's answer.
    for refine in (None, True):
        options = {} if refine is None else {"refine": refine}
        created = client.post("/v1/sessions", json={
            **mesh_json(V, F), "handles": [{"vertex": h["vertex"]} for h in handles],
            "options": options})
        assert created.status_code == 201, created.text
        location = created.headers["location"]
        solved = client.post(f"{location}/solve", json={
            "handle_positions": [h["position"] for h in handles]})
        assert solved.status_code == 200, solved.text
        np.testing.assert_allclose(solved.json()["vertices"], deform[False]["vertices"],
                                   atol=1e-6)
        if refine:
            link = solved.headers["link"]
            refined = client.get(link[1:link.index(">")], params={"wait": 60})
            assert refined.status_code == 200, refined.text
            np.testing.assert_allclose(refined.json()["vertices"], deform[None]["vertices"],
                                       atol=1e-6)
        else:
            assert "link" not in solved.headers
        assert client.delete(location).status_code == 204
