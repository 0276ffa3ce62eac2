"""Peak memory of the service's HTTP process while it receives a large mesh (issue 45).

A real uvicorn on loopback (``tests.helpers.servers.uvicorn_process``, one worker) receives
a mesh file as a multipart job upload (``POST /v1/jobs``, ``operation=forms``); the HTTP
process's peak RSS (``VmHWM`` of ``/proc/<pid>/status``) is read once it is ready and
after the 202, and the job is cancelled at once (its worker's memory is not the HTTP
process's). The mesh is the bench's 1.6M-face scan (``bench.scale``'s level 2,
written as binary PLY under ``/tmp/ffs-scale`` on first use)::

    python -m bench.upload_memory                 # level 2 (1.6M faces)
    python -m bench.upload_memory --level 1       # 400K faces
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import httpx
import numpy as np

from bench.scale import CACHE, forms_file


def ply_file(level: int) -> Path:
    """The scan subdivided ``level`` times as binary PLY (made on first use)."""
    path = CACHE / f"nefertiti-s{level}.ply"
    if not path.exists():
        from solver.mesh.io import save_mesh

        data = np.load(forms_file(level))
        path.write_bytes(save_mesh(data["vertices"], data["faces"], "ply"))
    return path


def peak_mb(pid: int) -> dict[str, float]:
    """The process's resident memory now and at its peak (MB)."""
    fields = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text()
                  .splitlines() if line.startswith(("VmRSS", "VmHWM")))
    return {k: int(v.split()[0]) / 1024 for k, v in fields.items()}


def measure(level: int) -> dict[str, object]:
    """Upload the level's PLY file and report the HTTP process's memory (MB)."""
    from tests.helpers.servers import uvicorn_process

    path = ply_file(level)
    rows: dict[str, object] = {"faces": len(np.load(forms_file(level))["faces"]),
                               "ply_mb": round(path.stat().st_size / 1e6, 1)}
    with uvicorn_process({"FFS_WORKERS": "1"}) as (base, proc):
        rows["ready"] = peak_mb(proc.pid)
        with httpx.Client(base_url=base, timeout=600) as http, path.open("rb") as file:
            start = time.perf_counter()
            answer = http.post("/v1/jobs", data={"operation": "forms"},
                               files={"file": (path.name, file, "application/octet-stream")})
            rows["upload_seconds"] = round(time.perf_counter() - start, 2)
            rows["upload_status"] = answer.status_code
            rows["after_upload"] = peak_mb(proc.pid)
            if answer.status_code == 202:
                http.delete(answer.headers["location"])
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--level", type=int, default=2)
    args = parser.parse_args()
    print(json.dumps(measure(args.level)))


if __name__ == "__main__":
    main()
