"""An uploaded file that cannot be the mesh format its name gives is refused when it is
submitted (400 ``unreadable-file`` naming the file, its field and what its first bytes
hold), a job included, instead of a 202 and a job that fails in its worker; every genuine
mesh is still accepted. Against a real uvicorn on loopback."""

from __future__ import annotations

import io
import json
import time

import httpx
import numpy as np
import pytest
from starlette.datastructures import UploadFile

from service.api.problems import ProblemError
from service.http.bodies import upload
from solver.mesh.formats import FORMATS
from solver.mesh.io import load_mesh, save_mesh
from solver.mesh.sniffing import SNIFF_BYTES
from tests.helpers import DATA
from tests.helpers.aio import run as run_async
from tests.helpers.meshes import bumpy_grid

PNG = b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\x00\x00\x00\x10" + bytes(range(256)) * 8
RANDOM = np.random.default_rng(7).bytes(5000)

NOT_MESHES = [  # (file name, bytes, words of the reason)
    ("photo.off", PNG, "binary data"),
    ("noise.stl", RANDOM, "neither an ASCII STL"),
    ("noise.ply", RANDOM, "'ply' line"),
    ("noise.glb", RANDOM, "starts with 'glTF'"),
    ("noise.obj", RANDOM, "binary data"),
    ("notes.obj", b"hello, this is not a mesh\n", "no vertices ('v' lines) found"),
    ("notes.off", b"# a mesh?\nhello world\n", "does not start with the OFF keyword"),
    ("notes-utf16.obj", "\ufeffhello, not a mesh\n".encode("utf-16-le"),
     "no vertices ('v' lines) found"),
    ("photo-named-binary.off", b"OFF\n" + PNG, "binary data"),
    ("scene.gltf", b"<html>not json</html>", "JSON object"),
    ("short.stl", b"\x00" * 80 + (10).to_bytes(4, "little") + bytes(100),
     "10 triangles needs 584 bytes, the file has 184"),
    ("cut.glb", b"glTF" + (2).to_bytes(4, "little") + (10_000).to_bytes(4, "little")
     + bytes(100), "the file ends after 112 of the 10000 bytes"),
    ("model.obj", save_mesh(*bumpy_grid(3, 3), "glb"), "it starts like a GLB file"),
]


def _genuine() -> dict[str, bytes]:
    """Meshes as files come: every format written, ASCII STL and PLY, headers and comments
    longer than the bytes the check reads."""
    V, F = bumpy_grid(4, 3)
    files = {f"grid.{fmt}": save_mesh(V, F, fmt) for fmt in ("obj", "off", "ply", "stl",
                                                              "glb", "gltf")}
    comments = b"".join(b"# %d: a long exporter's preamble\n" % k for k in range(300))
    files["late-vertices.obj"] = comments + files["grid.obj"]
    files["late-keyword.off"] = comments + files["grid.off"]
    rows = "".join("facet normal 0 0 0\nouter loop\n"
                   + "".join(f"vertex {x!r} {y!r} {z!r}\n" for x, y, z in V[f].tolist())
                   + "endloop\nendfacet\n" for f in F)
    files["ascii.stl"] = b"solid grid\n" + rows.encode() + b"endsolid grid\n"
    files["ascii.ply"] = (f"ply\nformat ascii 1.0\nelement vertex {len(V)}\n"
                          "property double x\nproperty double y\nproperty double z\n"
                          f"element face {len(F)}\nproperty list uchar int vertex_indices\n"
                          "end_header\n").encode() + "".join(
        f"{x!r} {y!r} {z!r}\n" for x, y, z in V.tolist()).encode() + "".join(
        f"3 {a} {b} {c}\n" for a, b, c in F.tolist()).encode()
    files["knight.off"] = (DATA / "decimated-knight.off").read_bytes()
    files["binary.off"] = (DATA / "pmp_fairing-cross_binary.off").read_bytes()
    files["utf16-box.obj"] = (DATA / "assimp_box_UTF16BE.obj").read_bytes()
    files["marked.off"] = b"\xef\xbb\xbf" + files["grid.off"]
    return files


def _wait(http: httpx.Client, location: str) -> dict:
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        doc = http.get(location).json()
        if doc["status"] in ("succeeded", "failed", "cancelled"):
            return doc
        time.sleep(0.05)
    raise AssertionError(f"job {location} did not finish")


def test_every_format_has_a_rule():
    assert all(fmt.sniff is not None for fmt in FORMATS.values())


@pytest.mark.parametrize(("name", "data", "words"), NOT_MESHES)
def test_a_file_that_is_not_its_format_is_refused_at_submission(live_server, name, data,
                                                                words):
    with httpx.Client(base_url=live_server, timeout=60) as http:
        before = len(http.get("/v1/jobs").json())
        response = http.post("/v1/jobs", data={"operation": "forms"},
                             files={"file": (name, data)})
        assert response.status_code == 400, response.text
        assert response.headers["content-type"] == "application/problem+json"
        doc = response.json()
        assert doc["kind"] == "unreadable-file" and doc["instance"] == "/v1/jobs"
        assert doc["detail"].startswith(f"file: '{name}' does not read as "), doc["detail"]
        assert words in doc["detail"] and "Error" not in doc["detail"], doc["detail"]
        item = doc["errors"][0]
        assert (item["field"], item["value"]) == ("file", name) and words in item["reason"]
        assert item["format"] == name.rsplit(".", 1)[1] and item["starts"]
        assert len(http.get("/v1/jobs").json()) == before  # no job was made
        # the synchronous endpoint answers the same, before any worker reads the file
        sync = http.post("/v1/mesh", files={"file": (name, data)})
        assert sync.status_code == 400 and sync.json()["detail"] == doc["detail"]


def test_genuine_meshes_are_still_accepted_and_read(live_server):
    with httpx.Client(base_url=live_server, timeout=60) as http:
        for name, data in _genuine().items():
            response = http.post("/v1/jobs", data={"operation": "mesh"},
                                 files={"file": (name, data)})
            assert response.status_code == 202, (name, response.text)
            job = _wait(http, response.headers["location"])
            assert job["status"] == "succeeded", (name, job)
            got = http.get(response.headers["location"] + "/result").json()
            want = load_mesh(data, name)
            np.testing.assert_allclose(got["vertices"], want[0], atol=1e-6)
            np.testing.assert_array_equal(got["faces"], want[1])


def test_a_blend_names_the_shape_that_is_not_a_mesh(live_server):
    V, F = bumpy_grid(3, 3)
    good = save_mesh(V, F, "off")
    with httpx.Client(base_url=live_server, timeout=60) as http:
        response = http.post("/v1/jobs", data={"operation": "blend",
                                               "weights": json.dumps([[0.5, 0.5]])},
                             files=[("shapes", ("a.off", good)), ("shapes", ("b.off", PNG))])
        assert response.status_code == 400, response.text
        doc = response.json()
        assert doc["errors"][0]["field"] == "shapes[1]" and "'b.off'" in doc["detail"]


class _CountingFile(io.BytesIO):
    """A spooled upload that counts the bytes read from it."""

    read_bytes = 0

    def read(self, size: int | None = -1) -> bytes:
        data = super().read(size)
        self.read_bytes += len(data)
        return data


def _upload(name: str, data: bytes) -> tuple[UploadFile, _CountingFile]:
    spool = _CountingFile(data)
    return UploadFile(spool, size=len(data), filename=name), spool


def test_a_large_wrong_file_is_refused_after_its_first_bytes_and_a_mesh_is_read_once():
    async def scenario() -> None:
        wrong, spool = _upload("big.ply", b"PK\x03\x04" + bytes(5_000_000))  # a zip
        try:
            await upload(wrong, "file")
        except ProblemError as exc:
            assert exc.kind == "unreadable-file"
        else:
            raise AssertionError("accepted")
        assert spool.read_bytes == SNIFF_BYTES  # 4 KiB of the 5 MB, never all of it
        data = _genuine()["late-vertices.obj"]
        mesh, spool = _upload("late.obj", data)
        assert (await upload(mesh, "file")).data == data
        assert spool.read_bytes == len(data) + SNIFF_BYTES  # the whole file once
        small = save_mesh(*bumpy_grid(2, 2), "off")
        mesh, spool = _upload("small.off", small)
        assert (await upload(mesh, "file")).data == small and spool.read_bytes == len(small)

    run_async(scenario())
