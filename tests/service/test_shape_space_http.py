"""POST /v1/blend and POST /v1/transfer: JSON, uploads, animated GLB, jobs with per-row
progress, and the problems of bad input, against the library's own answers."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

import solver
from solver.mesh.io import save_mesh
from tests.helpers.gltf_validator import issue_codes, validate_gltf
from tests.helpers.meshes import load
from tests.helpers.poses import bent_pose
from tests.helpers.service import problem


@pytest.fixture(scope="module")
def poses():
    V, F = load("decimated-knight.off")
    return V, bent_pose(V, F, 0.5), bent_pose(V, F, -0.4, bend_axis=0), F


def body(shapes, F, **fields):
    return {"shapes": [s.tolist() for s in shapes], "faces": F.tolist(), **fields}


def test_blend_json_is_the_library_answer(client, poses):
    V, P, Q, F = poses
    weights = [[1.0, 0.0, 0.0], [0.2, 0.5, 0.3], [-0.2, 0.6, 0.6], [0.0, 0.0, 1.0]]
    response = client.post("/v1/blend", json=body([V, P, Q], F, weights=weights))
    assert response.status_code == 200, response.text
    doc = response.json()
    expected = solver.blend([V, P, Q], weights, F)
    np.testing.assert_allclose(doc["vertices"], expected.vertices, atol=1e-9)
    np.testing.assert_allclose(doc["vertices"][0], V, atol=1e-8)
    np.testing.assert_allclose(doc["vertices"][3], Q, atol=1e-8)
    assert [r["path"] for r in doc["reports"]] == ["reconstruct", "sequence", "sequence",
                                                   "reconstruct"]
    assert all(r["form_error"]["length_error"]["mean"] < 0.02 for r in doc["reports"])
    assert doc["warnings"] == expected.warnings == []
    tall = client.post("/v1/blend", json=body([V, V * [1, 1, 3.0]], F, t=[0.5])).json()
    truth = solver.blend([V, V * [1, 1, 3.0]], [[0.5, 0.5]], F).warnings
    assert [(w["code"], w["message"], w["row"]) for w in tall["warnings"]] == [
        (w["code"], w["message"], w["row"]) for w in truth]
    assert [w["value"] for w in tall["warnings"]] == pytest.approx([w["value"] for w in truth])
    assert {w["code"] for w in tall["warnings"]} >= {"angle-error"}
    assert tall["reports"][0]["warnings"] == [{k: v for k, v in w.items() if k != "row"}
                                              for w in tall["warnings"]]


def test_glb_answers_carry_their_warnings(client, poses):
    """A GLB answer has no report beside it: its warnings (the same as the JSON answer's)
    are the asset's ``extras.warnings``, for the animated blend and a single mesh alike; an
    answer without warnings has no extras. The files stay valid glTF."""
    from tests.service.test_gltf_animation import read_glb

    V, P, _, F = poses
    tall = body([V, V * [1, 1, 3.0]], F, t=[0.0, 0.5, 1.0])
    want = client.post("/v1/blend", json=tall).json()["warnings"]
    assert want
    glb = client.post("/v1/blend", json=tall, headers={"Accept": "model/gltf-binary"})
    assert glb.status_code == 200, glb.text
    doc, _ = read_glb(glb.content)
    assert doc["asset"]["extras"]["warnings"] == json.loads(json.dumps(want))
    report = validate_gltf(glb.content, "glb")
    assert report["issues"]["numErrors"] == 0, issue_codes(report)
    quiet = client.post("/v1/blend", json=body([V, P], F, t=[0.0, 1.0]),
                        headers={"Accept": "model/gltf-binary"})
    assert "extras" not in read_glb(quiet.content)[0]["asset"]

    forms = solver.fundamental_forms(V, F)
    scaled = {"faces": F.tolist(), "edges": forms.edges.tolist(),
              "lengths": forms.lengths.tolist(), "angles": (0.5 * forms.angles).tolist()}
    answer = client.post("/v1/reconstruct", json=scaled).json()
    assert answer["report"]["warnings"]
    glb = client.post("/v1/reconstruct", json=scaled, headers={"Accept": "model/gltf-binary"})
    assert glb.status_code == 200, glb.text
    assert read_glb(glb.content)[0]["asset"]["extras"]["warnings"] == \
        answer["report"]["warnings"]


def test_blend_t_is_interpolate(client, poses):
    V, P, _, F = poses
    doc = client.post("/v1/blend", json=body([V, P], F, t=[0.25, 1.5])).json()
    np.testing.assert_allclose(doc["vertices"], solver.interpolate(V, P, F, [0.25, 1.5]),
                               atol=1e-9)
    assert doc["weights"] == [[0.75, 0.25], [-0.5, 1.5]]


def test_blend_as_glb_is_an_animation_the_validator_accepts(client, poses):
    V, P, _, F = poses
    t = np.linspace(0.0, 1.0, 6).tolist()
    response = client.post("/v1/blend", json=body([V, P], F, t=t, times=[0, 1, 2, 3, 4, 5]),
                           headers={"Accept": "model/gltf-binary"})
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "model/gltf-binary"
    report = validate_gltf(response.content, "glb")
    assert report["issues"]["numErrors"] == 0 and report["issues"]["numWarnings"] == 0, \
        issue_codes(report)
    assert report["info"]["animationCount"] == 1
    bad = client.post("/v1/blend", json=body([V, P], F, t=t, times=[0, 1]),
                      headers={"Accept": "model/gltf-binary"})
    assert problem(bad, 422, "validation-error")["errors"][0]["field"] == "times"


@pytest.mark.parametrize("change, kind, field", [
    ({"weights": [[0.5, 0.6]]}, "shape-mismatch", "weights"),
    ({}, "validation-error", None),
    ({"weights": [[1.0, 0.0]], "t": 0.5}, "validation-error", None),
    ({"weights": [[np.nan, 1.0]]}, "validation-error", "weights"),
    ({"t": np.linspace(0, 1, 1025).tolist()}, "validation-error", "t"),  # FFS_MAX_BLEND_STEPS
    ({"weights": [[0.5, 0.5]] * 1025}, "validation-error", "weights"),
])
def test_blend_refuses_bad_weights(client, poses, change, kind, field):
    V, P, _, F = poses
    sent = json.dumps(body([V, P], F, **change))  # NaN as Python's json writes it
    response = client.post("/v1/blend", content=sent,
                           headers={"Content-Type": "application/json"})
    doc = problem(response, 422, kind)
    if field is not None:
        assert doc["errors"][0]["field"] == field, doc


def test_blend_refuses_mismatched_shapes_and_t_for_three(client, poses):
    V, P, Q, F = poses
    doc = problem(client.post("/v1/blend", json=body([V, P[:-1]], F, t=0.5)), 422,
                  "validation-error")
    assert doc["errors"][0]["pointer"] == "/shapes/1"
    doc = problem(client.post("/v1/blend", json=body([V, P, Q], F, t=0.5)), 422,
                  "validation-error")
    assert doc["errors"][0]["field"] == "t"


def test_blend_job_reports_progress_per_row_and_its_glb(client, poses):
    V, P, _, F = poses
    t = np.linspace(0.0, 1.0, 40).tolist()
    submitted = client.post("/v1/jobs", json={"operation": "blend",
                                              "input": body([V, P], F, t=t)})
    assert submitted.status_code == 202, submitted.text
    url = submitted.json()["links"]["self"]
    fractions = []
    for _ in range(600):
        status = client.get(url).json()
        if status["progress"]["stage"] == "rows":
            fractions.append(status["progress"]["fraction"])
        if status["status"] in ("succeeded", "failed"):
            break
        time.sleep(0.02)
    assert status["status"] == "succeeded", status
    assert any(0.0 < f < 1.0 for f in fractions), fractions  # seen mid-way, per row
    assert fractions == sorted(fractions)
    doc = client.get(url + "/result").json()
    assert len(doc["vertices"]) == 40
    glb = client.get(url + "/result?format=glb")
    assert glb.status_code == 200 and glb.headers["content-type"] == "model/gltf-binary"
    assert validate_gltf(glb.content, "glb")["issues"]["numErrors"] == 0


def test_blend_uploads_k_files_as_shapes_parts(client, poses):
    """Three meshes uploaded as three `shapes` parts (formats mixed) blend as the same
    shapes sent as arrays; two with `t` are interpolate."""
    V, P, Q, F = poses
    weights = [[0.2, 0.5, 0.3], [-0.2, 0.6, 0.6]]
    files = [("shapes", ("a.off", save_mesh(V, F, "off"))),
             ("shapes", ("b.obj", save_mesh(P, F, "obj"))),
             ("shapes", ("c.ply", save_mesh(Q, F, "ply")))]
    response = client.post("/v1/blend", files=files, data={"weights": json.dumps(weights)})
    assert response.status_code == 200, response.text
    np.testing.assert_allclose(response.json()["vertices"],
                               solver.blend([V, P, Q], weights, F).vertices, atol=1e-6)
    response = client.post("/v1/blend", files=files[:2], data={"t": "[0.5]"})
    assert response.status_code == 200, response.text
    np.testing.assert_allclose(response.json()["vertices"][0],
                               solver.interpolate(V, P, F, 0.5), atol=1e-6)


def test_blend_uploads_name_the_part_at_fault(client, poses):
    V, P, _, F = poses
    other = save_mesh(P, F[:, ::-1], "off")  # the faces of the second part differ
    files = [("shapes", ("a.off", save_mesh(V, F, "off"))), ("shapes", ("b.off", other))]
    doc = problem(client.post("/v1/blend", files=files, data={"t": "[0.5]"}), 422,
                  "shape-mismatch")
    assert doc["errors"][0]["field"] == "shapes[1]"
    doc = problem(client.post("/v1/blend", files=[("file_a", ("a.off", other))],
                              data={"t": "0.5"}), 422, "validation-error")
    assert {e["field"] for e in doc["errors"]} == {"shapes", "file_a"}
    files = [("file", ("a.off", other)), ("file", ("b.off", other))]
    problem(client.post("/v1/forms", files=files), 400, "malformed-request")


def test_rows_are_bounded_by_rows_times_vertices():
    """FFS_MAX_BLEND_VERTICES bounds rows x vertices (413 blend-too-large naming the most
    rows that pass), for arrays, uploads and jobs; the rows that fit are answered."""
    from tests.helpers.servers import running_app

    V, F = load("decimated-knight.off")
    P = bent_pose(V, F, 0.3)
    most = 3
    with running_app(workers=1, max_blend_vertices=most * len(V)) as c:
        t = np.linspace(0.0, 1.0, most + 1).tolist()
        files = [("shapes", ("a.off", save_mesh(V, F, "off"))),
                 ("shapes", ("b.off", save_mesh(P, F, "off")))]
        answers = [c.post("/v1/blend", json=body([V, P], F, t=t)),
                   c.post("/v1/blend", files=files, data={"t": json.dumps(t)}),
                   c.post("/v1/interpolate", json={"vertices_a": V.tolist(),
                                                   "vertices_b": P.tolist(),
                                                   "faces": F.tolist(), "t": t})]
        for response in answers:
            doc = problem(response, 413, "blend-too-large")
            assert f"at most {most} rows" in doc["detail"], doc
            assert "FFS_MAX_BLEND_VERTICES" in doc["detail"]
        job = c.post("/v1/jobs", json={"operation": "blend", "input": body([V, P], F, t=t)})
        assert problem(job, 413, "blend-too-large")["errors"][0]["field"] == "input.t"
        fits = c.post("/v1/blend", json=body([V, P], F, t=t[:most]))
        assert fits.status_code == 200 and len(fits.json()["vertices"]) == most


def test_transfer_to_the_source_itself_and_by_upload(client, poses):
    V, P, Q, F = poses
    response = client.post("/v1/transfer", json={"source": V.tolist(),
                                                 "source_deformed": P.tolist(),
                                                 "target": V.tolist(), "faces": F.tolist()})
    assert response.status_code == 200, response.text
    assert np.abs(np.array(response.json()["vertices"]) - P).max() < 1e-8
    files = {"file_source": ("a.off", save_mesh(V, F, "off")),
             "file_source_deformed": ("b.off", save_mesh(P, F, "off")),
             "file_target": ("c.off", save_mesh(Q, F, "off"))}
    response = client.post("/v1/transfer", files=files)
    assert response.status_code == 200, response.text
    np.testing.assert_allclose(response.json()["vertices"], solver.transfer(V, P, Q, F),
                               atol=1e-5 * np.ptp(V))
    other = load("face.off")
    files["file_target"] = ("c.off", save_mesh(*other, "off"))
    doc = problem(client.post("/v1/transfer", files=files), 422, "shape-mismatch")
    assert doc["errors"][0]["field"] == "file_target"


def test_blend_of_a_non_manifold_mesh_is_the_librarys(client):
    """Cones touching at their apex: blended on the manifold cut, answered per file vertex."""
    from tests.helpers.real_meshes import cones_at_apex, diagonal

    V, F = cones_at_apex()
    tall = V * [1.0, 1.0, 1.3]
    weights = [[1.0, 0.0], [0.5, 0.5], [0.0, 1.0]]
    response = client.post("/v1/blend", json={"shapes": [V.tolist(), tall.tolist()],
                                              "faces": F.tolist(), "weights": weights})
    assert response.status_code == 200, response.text
    doc = response.json()
    expected = solver.blend([V, tall], weights, F)
    np.testing.assert_allclose(doc["vertices"], expected.vertices, atol=1e-8 * diagonal(V))
    assert all("cut" in report["input"] for report in doc["reports"])
