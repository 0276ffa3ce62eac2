"""Throughput of a batch of mid-size reconstructs: the local process pool against Dask.

A batch of ``--requests`` synchronous ``POST /v1/reconstruct`` of an icosphere with 5 120
faces (about 60 ms of solver work each), ``--concurrency`` requests in flight, through a
real ``uvicorn service.app:app`` on loopback, with 1 and 2 workers:

* local: ``FFS_EXECUTOR=local``, ``FFS_WORKERS`` = 1 or 2;
* Dask: ``FFS_EXECUTOR=dask`` on a cluster started like docker-compose.yml (``dask
  scheduler --preload service.backends.dask`` and ``dask worker --nworkers N --nthreads 1``).

Every worker uses one BLAS thread (``FFS_THREADS_PER_WORKER=1``), so both backends do the
same arithmetic; the script checks that their vertices are equal to the last bit.

``python -m bench.dask_throughput [--requests 48] [--concurrency 8] [--out bench/SESSIONS.md]``
prints a markdown table (and writes it with ``--out``, replacing that file's section).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import platform
import time
from pathlib import Path

import httpx
import numpy as np
import orjson
import trimesh

import solver
from bench.common import load_averages, write_section
from bench.servers import dask_cluster, uvicorn


def body() -> tuple[bytes, int]:
    m = trimesh.creation.icosphere(subdivisions=4)
    forms = solver.fundamental_forms(np.asarray(m.vertices), np.asarray(m.faces))
    return orjson.dumps(forms.to_dict()), len(m.faces)


def batch(base: str, payload: bytes, n_requests: int, concurrency: int) -> dict:
    async def run() -> dict:
        limits = httpx.Limits(max_connections=concurrency)
        async with httpx.AsyncClient(base_url=base, timeout=600, limits=limits) as http:
            sem = asyncio.Semaphore(concurrency)
            latencies: list[float] = []
            last: list[bytes] = []

            async def one(record: bool) -> None:
                async with sem:
                    t0 = time.perf_counter()
                    r = await http.post("/v1/reconstruct", content=payload, headers={
                        "content-type": "application/json", "accept-encoding": "identity"})
                    r.raise_for_status()
                    if record:
                        latencies.append(time.perf_counter() - t0)
                        last[:] = [r.content]

            await asyncio.gather(*(one(False) for _ in range(concurrency)))  # warm-up
            t0 = time.perf_counter()
            await asyncio.gather(*(one(True) for _ in range(n_requests)))
            wall = time.perf_counter() - t0
            return {"rate": n_requests / wall, "wall": wall,
                    "p50": float(np.median(latencies)), "vertices": np.asarray(
                        orjson.loads(last[0])["vertices"])}

    return asyncio.run(run())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--requests", type=int, default=48)
    parser.add_argument("--concurrency", type=int, default=8)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    payload, n_faces = body()
    env = {"FFS_THREADS_PER_WORKER": "1", "FFS_QUEUE_SIZE": "256", "FFS_LOG_LEVEL": "warning"}
    loads = [load_averages()]
    results: dict[tuple[str, int], dict] = {}
    for workers in (1, 2):
        with uvicorn({**env, "FFS_WORKERS": str(workers)}, workers) as base:
            results["local", workers] = batch(base, payload, args.requests, args.concurrency)
        with dask_cluster(workers) as address, uvicorn(
                {**env, "FFS_EXECUTOR": "dask", "FFS_DASK_SCHEDULER_ADDRESS": address},
                workers) as base:
            results["dask", workers] = batch(base, payload, args.requests, args.concurrency)
    loads.append(load_averages())
    equal = all(np.array_equal(results["local", 1]["vertices"], r["vertices"])
                for r in results.values())
    lines = [
        "## Throughput: local pool against Dask",
        "",
        f"`python -m bench.dask_throughput --requests {args.requests} --concurrency "
        f"{args.concurrency}` on {platform.machine()} with {os.cpu_count()} cores, Python "
        f"{platform.python_version()}: {args.requests} synchronous reconstructs of an "
        f"icosphere with {n_faces} faces ({len(payload) / 1e6:.2f} MB of JSON forms each), "
        f"{args.concurrency} in flight, after {args.concurrency} warm-up requests; one BLAS "
        f"thread per worker. Load average (1, 5, 15 min) before and after: {loads[0]} / "
        f"{loads[-1]}.",
        "",
        "| Backend | Workers | Requests/s | Batch (s) | p50 latency (s) |",
        "|---|---|---|---|---|",
    ]
    for (backend, workers), r in results.items():
        lines.append(f"| {backend} | {workers} | {r['rate']:.2f} | {r['wall']:.1f} | "
                     f"{r['p50']:.2f} |")
    speed = {b: results[b, 2]["rate"] / results[b, 1]["rate"] for b in ("local", "dask")}
    lines += [
        "",
        f"2 workers against 1: local x {speed['local']:.2f}, Dask x {speed['dask']:.2f}. "
        f"Dask against local with 2 workers: x "
        f"{results['dask', 2]['rate'] / results['local', 2]['rate']:.2f}. Vertices of every "
        f"run equal to the last bit: {'yes' if equal else 'NO'}.",
        "",
        "This box has 2 cores for everything: the client, uvicorn's event loop, the workers "
        "and, for Dask, the scheduler and the nannies. Two workers cannot double the "
        "throughput when the API process itself needs a good part of a core (parsing "
        f"{len(payload) / 1e6:.2f} MB bodies, encoding results), and Dask adds a hop "
        "(API -> scheduler -> worker, the result back through the API) and its own "
        "processes. The point of the Dask backend is more machines, which this box cannot "
        "show; the numbers here bound its overhead.",
        "",
    ]
    text = "\n".join(lines)
    print(text)
    if args.out:
        write_section(args.out, "## Throughput: local pool against Dask", text)


if __name__ == "__main__":
    main()
