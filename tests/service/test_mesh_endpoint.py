"""POST /v1/mesh: a mesh file (or JSON mesh) read, checked and returned as JSON, GLB or glTF.
The web page opens uploads and downloads the current mesh through it."""

from __future__ import annotations

import io

import numpy as np
import trimesh

from tests.helpers import DATA
from tests.helpers.gltf_validator import validate_gltf
from tests.helpers.meshes import load
from tests.helpers.service import problem


def test_upload_returns_file_order_and_report(client):
    data = (DATA / "face.off").read_bytes()
    response = client.post("/v1/mesh", files={"file": ("face.off", data)})
    assert response.status_code == 200, response.text
    body = response.json()
    V, F = load("face.off")
    np.testing.assert_array_equal(body["vertices"], V)
    np.testing.assert_array_equal(body["faces"], F)
    report = body["report"]
    assert (report["n_vertices"], report["n_faces"]) == (len(V), len(F))
    np.testing.assert_allclose(report["bounds"], [V.min(axis=0), V.max(axis=0)])
    edges = np.unique(np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]),
                              axis=1), axis=0)
    assert report["n_edges"] == len(edges)
    mean = np.linalg.norm(V[edges[:, 1]] - V[edges[:, 0]], axis=1).mean()
    assert np.isclose(report["mean_edge_length"], mean, rtol=1e-12)


def test_json_mesh_to_glb(client):
    V, F = load("decimated-knight.off")
    response = client.post("/v1/mesh", json={"vertices": V.tolist(), "faces": F.tolist()},
                           headers={"accept": "model/gltf-binary"})
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "model/gltf-binary"
    report = validate_gltf(response.content, "glb")
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"][:5]
    scene = trimesh.load(io.BytesIO(response.content), file_type="glb", process=False)
    mesh = next(iter(scene.geometry.values()))
    np.testing.assert_allclose(mesh.vertices, V, atol=1e-6)
    np.testing.assert_array_equal(mesh.faces, F)


def test_errors(client):
    problem(client.post("/v1/mesh", files={"file": ("notes.txt", b"hello")}), 415,
            "unsupported-file-type")
    doc = problem(client.post("/v1/mesh", json={"vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]],
                                                "faces": [[0, 1, 5]]}), 422,
                  "index-out-of-range")
    assert doc["errors"][0]["field"] == "faces"
    # Connectivity is checked like every other operation does: an edge of three faces is cut
    # (issue 40), a face flipped against its neighbour turned back, and both reported.
    V = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]]
    F = [[0, 1, 2], [1, 0, 3], [0, 1, 4]]
    cut = client.post("/v1/mesh", json={"vertices": V, "faces": F}).json()["report"]["input"]
    assert cut["cut"]["split_edges"] == 1 and cut["cut"]["split_vertices"] == 2
    flipped = client.post("/v1/mesh", json={"vertices": V, "faces": [[0, 1, 2], [0, 1, 3]]})
    turned = flipped.json()["report"]["input"]
    assert "cut" not in turned and turned["reoriented"]["flipped_face_list"] == [1]
    twice = client.post("/v1/mesh", json={"vertices": V, "faces": [[0, 1, 2], [0, 1, 2]]})
    # a duplicated face on its own: turned, the two bound a closed sliver (dihedral pi)
    assert twice.json()["report"]["input"]["reoriented"]["flipped_faces"] == 1
    fin = client.post("/v1/mesh", json={"vertices": V, "faces": [[0, 1, 2], [0, 1, 2],
                                                                  [1, 0, 3]]})
    assert fin.json()["report"]["input"]["cut"]["split_edges"] == 1  # duplicated in a mesh
