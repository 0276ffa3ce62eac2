"""Bodies and uploads streamed (issue 45), on a real uvicorn: the body limit answers 413
while the body is still arriving, a multipart upload is parsed as it arrives (the HTTP
process's peak memory stays well under twice the file), and what is streamed is read as
before (binary bodies and uploads give the answer of the same mesh as JSON).
"""

from __future__ import annotations

import socket
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
import trimesh

from solver.mesh.io import save_mesh
from tests.helpers.servers import uvicorn_fixture, uvicorn_process

LIMIT = 2 * 1024 * 1024
small_limit_server = uvicorn_fixture({"FFS_MAX_BODY_BYTES": str(LIMIT), "FFS_WORKERS": "1"},
                                     scope="module")


def _status_while_sending(base: str, path: str, headers: dict[str, str], send: int,
                          prefix: bytes = b"") -> bytes:
    """Send ``prefix`` and ``send`` more bytes as a chunked body, stop without finishing it,
    and return the status line the server answers with (within 10 s)."""
    host, port = base.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=10) as sock:
        head = (f"POST {path} HTTP/1.1\r\nHost: {host}\r\nTransfer-Encoding: chunked\r\n"
                + "".join(f"{k}: {v}\r\n" for k, v in headers.items()) + "\r\n")
        sock.sendall(head.encode())
        if prefix:
            sock.sendall(f"{len(prefix):x}\r\n".encode() + prefix + b"\r\n")
        chunk = b"0" * 65536
        sent = 0
        try:
            while sent < send:
                sock.sendall(f"{len(chunk):x}\r\n".encode() + chunk + b"\r\n")
                sent += len(chunk)
        except (BrokenPipeError, ConnectionResetError):
            pass  # the server answered and closed while we were still sending
        answer = b""
        deadline = time.monotonic() + 10
        while b"\r\n" not in answer and time.monotonic() < deadline:
            data = sock.recv(4096)
            if not data:
                break
            answer += data
        return answer.split(b"\r\n", 1)[0]


@pytest.mark.parametrize(("path", "content_type"), [
    ("/v1/forms", "application/json"),
    ("/v1/forms", "application/vnd.ffs.arrays"),
    ("/v1/forms", "multipart/form-data; boundary=xyz"),
    ("/v1/jobs", "multipart/form-data; boundary=xyz"),
])
def test_413_before_the_body_ends(small_limit_server: str, path: str, content_type: str) -> None:
    """A chunked body (no Content-Length) past FFS_MAX_BODY_BYTES is answered 413 while it
    is still being sent: the body never ends here (no last chunk), so an answer at all
    means it was not read whole."""
    prefix = FILE_PART if content_type.startswith("multipart") else b""
    status = _status_while_sending(small_limit_server, path, {"Content-Type": content_type},
                                   send=LIMIT + 4 * 65536, prefix=prefix)
    assert status.startswith(b"HTTP/1.1 413"), status


def test_multipart_within_the_limit_still_reads(small_limit_server: str) -> None:
    mesh = trimesh.creation.icosphere(subdivisions=3)
    data = save_mesh(mesh.vertices, mesh.faces, "ply")
    with httpx.Client(base_url=small_limit_server, timeout=60) as http:
        answer = http.post("/v1/forms", files={"file": ("m.ply", data)})
        assert answer.status_code == 200, answer.text
        assert len(answer.json()["faces"]) == len(mesh.faces)
        cut = http.post("/v1/forms", content=FILE_PART + data[:1000],
                        headers={"Content-Type": "multipart/form-data; boundary=xyz"})
        assert cut.status_code == 400
        assert "closing boundary" in cut.json()["detail"]


FILE_PART = (b'--xyz\r\nContent-Disposition: form-data; name="file"; filename="m.ply"\r\n'
             b"Content-Type: application/octet-stream\r\n\r\n")
"""The head of a multipart body's file part (boundary ``xyz``)."""


def _peak_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmHWM")


def test_an_upload_is_not_held_twice(tmp_path: Path) -> None:
    """A 40 MB PLY upload (a job: answered 202 before the worker reads it) raises the HTTP
    process's peak memory by less than twice the file: the body is never held whole (it
    was three times the file when the body was read whole, joined and parsed again). The
    file's bytes for the worker and their pickled copy on the way are the two that remain."""
    rng = np.random.default_rng(0)
    vertices = rng.normal(size=(800_000, 3))
    faces = rng.integers(0, len(vertices), size=(1_600_000, 3))
    path = tmp_path / "big.ply"
    path.write_bytes(save_mesh(vertices, faces, "ply"))
    size_mb = path.stat().st_size / 1024**2
    with uvicorn_process({"FFS_WORKERS": "1"}) as (base, proc), \
            httpx.Client(base_url=base, timeout=120) as http, path.open("rb") as file:
        ready = _peak_mb(proc.pid)
        answer = http.post("/v1/jobs", data={"operation": "forms"},
                           files={"file": ("big.ply", file, "application/octet-stream")})
        assert answer.status_code == 202, answer.text
        peak = _peak_mb(proc.pid)
        http.delete(answer.headers["location"])
    assert peak - ready < 2.2 * size_mb, (ready, peak, size_mb)
