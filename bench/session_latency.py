"""Drag latency of a deformation session against the direct ``Deformer.solve`` call.

A ~20K-face mesh (shared/meshes/rocker-arm.obj, 20 088 faces; icosphere(5) with 20 480
faces if the shared meshes are absent) with 10 position handles. Each round drags all
handles to new targets and waits for the vertices:

* direct: ``solver.Deformer(...).solve(targets)`` in this process (MKL's default threads,
  one per core, like a local session process with the default FFS_SESSION_THREADS);
* HTTP: ``POST /v1/sessions/{id}/solve`` with a JSON drag, answered as raw float32
  (``Accept: application/octet-stream``, what a frontend uploads into a vertex buffer) and
  as JSON;
* WebSocket: one binary drag per message, waiting for each reply (no drops).

The drags run in ``--rounds`` rounds; within a round each path runs its block of drags
before the next path starts, so slow drift of the machine's load spreads over all paths.
(Interleaving the paths drag by drag distorts the result: after each solve, MKL's OpenMP
threads spin for up to 200 ms (KMP_BLOCKTIME) and slow down whatever process runs next on
the same cores.)

The service is a real ``uvicorn service.app:app`` on loopback (``FFS_EXECUTOR=local``: the
session is a dedicated process; with ``--dask`` also ``FFS_EXECUTOR=dask`` on a one-worker
cluster: the session is a Dask actor). Targets: HTTP p50 <= 40 ms, WebSocket p50 <= 30 ms.

``python -m bench.session_latency [--drags 200] [--dask] [--out bench/SESSIONS.md]``
prints a markdown table (and writes it with ``--out``, replacing that file's latency
section).

``--progressive N`` measures progressive drags instead (a session opened with
``options.refine: true`` on the local executor, its WebSocket): for each of N drags of the
same smooth drag, the time from sending it to its linear reply and to its refined reply
(the client waits for both before the next drag: the user pauses after each one), side by
side with libigl's ARAP, 10 iterations per drag warm-started from the previous drag, in
this process, on the same drags; and the quality of the last shape of each (RMS relative
edge-length change and RMS dihedral change against the rest shape).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import os
import platform
import time
from pathlib import Path

import httpx
import numpy as np
import orjson

from bench.common import load_averages, session_mesh, write_section
from bench.servers import dask_cluster, uvicorn


def targets(V: np.ndarray, handles: np.ndarray, count: int) -> np.ndarray:
    """A smooth drag of the first handle (the others stay), float32-exact values."""
    t = np.linspace(0.0, 1.0, count)[:, None]
    scale = float(np.ptp(V, axis=0).max())
    out = np.repeat(V[handles][None], count, axis=0)
    out[:, 0] += t * np.array([0.1, 0.05, 0.0]) * scale
    return out.astype(np.float32).astype(np.float64)


def stats(seconds: list[float]) -> dict[str, float]:
    ms = np.asarray(seconds) * 1000
    return {"p50": float(np.median(ms)), "p90": float(np.percentile(ms, 90)),
            "mean": float(ms.mean())}


class Session:
    """One session on one server: an HTTP client and a WebSocket, each drag timed."""

    def __init__(self, base: str, V: np.ndarray, F: np.ndarray, handles: np.ndarray) -> None:
        from websockets.sync.client import connect

        self.http = httpx.Client(base_url=base, timeout=300)
        body = orjson.dumps({"vertices": V, "faces": F,
                             "handles": [{"vertex": int(h)} for h in handles]},
                            option=orjson.OPT_SERIALIZE_NUMPY)
        t0 = time.perf_counter()
        created = self.http.post("/v1/sessions", content=body,
                                 headers={"content-type": "application/json"})
        created.raise_for_status()
        self.create = time.perf_counter() - t0
        self.doc = created.json()
        self.location = created.headers["location"]
        self._stack = contextlib.ExitStack()
        self.ws = self._stack.enter_context(connect(
            base.replace("http://", "ws://") + self.location + "/ws", max_size=None))
        self.worker_solve: list[float] = []
        self.bytes: dict[str, int] = {}

    def http_drag(self, target: np.ndarray, accept: str, key: str) -> None:
        payload = orjson.dumps({"handle_positions": target}, option=orjson.OPT_SERIALIZE_NUMPY)
        r = self.http.post(f"{self.location}/solve", content=payload, headers={
            "content-type": "application/json", "accept": accept,
            "accept-encoding": "identity"})
        r.raise_for_status()
        self.bytes[key] = len(r.content)
        timing = dict(part.split(";dur=") for part in r.headers["server-timing"].split(", "))
        self.worker_solve.append(float(timing["solve"]) / 1000)

    def ws_drag(self, target: np.ndarray) -> None:
        self.ws.send(target.astype("<f4").tobytes())
        self.bytes["ws"] = len(self.ws.recv(timeout=60))

    def close(self) -> None:
        self._stack.close()
        self.http.delete(self.location).raise_for_status()
        self.http.close()


def measure(V: np.ndarray, F: np.ndarray, handles: np.ndarray, drags: np.ndarray,
            servers: dict[str, str], rounds: int) -> tuple[dict, dict[str, Session]]:
    """Time each path in blocks of drags: ``rounds`` rounds, the paths one after the other
    within a round."""
    import solver

    sessions = {name: Session(base, V, F, handles) for name, base in servers.items()}
    # MKL's default threads (one per core), as in a local session process.
    t0 = time.perf_counter()
    deformer = solver.Deformer(V, F, handles)
    setup = time.perf_counter() - t0
    deformer.solve()  # a session's first solve (it verifies the factorization)
    paths = {"direct": deformer.solve}
    for name, session in sessions.items():
        paths[f"{name}:http_f32"] = functools.partial(
            session.http_drag, accept="application/octet-stream", key="http_f32")
        paths[f"{name}:http_json"] = functools.partial(
            session.http_drag, accept="application/json", key="http_json")
        paths[f"{name}:ws"] = session.ws_drag
    times: dict[str, list[float]] = {key: [] for key in paths}
    for chunk in np.array_split(drags, rounds):  # rounds spread slow drift over all paths
        for key, drag in paths.items():  # within a round, one path after the other
            for i, target in enumerate(chunk):
                t0 = time.perf_counter()
                drag(target)
                if i:  # the first drag of a block warms the connection up
                    times[key].append(time.perf_counter() - t0)
    out = {key: stats(values) for key, values in times.items()}
    out["direct"]["setup"] = setup
    return out, sessions


def report(name: str, V: np.ndarray, F: np.ndarray, n_drags: int, rounds: int, out: dict,
           sessions: dict[str, Session], loads: list[str]) -> str:
    ref = out["direct"]
    lines = [
        "## Session drag latency",
        "",
        f"`python -m bench.session_latency --drags {n_drags} --rounds {rounds}"
        f"{' --dask' if 'dask' in sessions else ''}` on {platform.machine()} with "
        f"{os.cpu_count()} cores, Python {platform.python_version()}; {name}: {len(F)} faces, "
        f"{len(V)} vertices, 10 position handles; {n_drags} drags per path in {rounds} "
        "rounds, within a round one path after the other. Milliseconds from sending a drag "
        "to having all vertices, one request or message at a time over one keep-alive "
        "connection; uvicorn without WebSocket deflate, as in the image; MKL threads: one "
        "per core in this process and in the local session process, one in the Dask "
        "worker. Load average (1, 5, 15 min) before and after: "
        f"{loads[0]} / {loads[-1]}.",
        "",
        "| Path | p50 (ms) | p90 (ms) | mean (ms) | p50 x direct | reply bytes |",
        "|---|---|---|---|---|---|",
        f"| direct `Deformer.solve` (this process) | {ref['p50']:.1f} | "
        f"{ref['p90']:.1f} | {ref['mean']:.1f} | 1.00 | |",
    ]
    labels = {"http_f32": "HTTP, JSON drag -> float32 vertices",
              "http_json": "HTTP, JSON drag -> JSON vertices",
              "ws": "WebSocket, binary drag -> float32 vertices"}
    for backend, session in sessions.items():
        for key, label in labels.items():
            row = out[f"{backend}:{key}"]
            lines.append(f"| {backend}: {label} | {row['p50']:.1f} | {row['p90']:.1f} | "
                         f"{row['mean']:.1f} | {row['p50'] / ref['p50']:.2f} | "
                         f"{session.bytes[key]:,} |")
    local = sessions["local"]
    http_p50, ws_p50 = out["local:http_f32"]["p50"], out["local:ws"]["p50"]
    lines += [
        "",
        f"Session set-up (assemble + factorize + the first, verified solve): "
        f"{local.doc['setup_seconds']:.2f} s in the session process ({ref['setup']:.2f} s "
        f"for the bare `Deformer` here); `POST /v1/sessions` took {local.create:.2f} s "
        "including the 1.9 MB JSON body and the process start. Measured session memory: "
        f"{local.doc['memory_bytes'] / 2**20:.0f} MiB (private memory of its process). The "
        "session process's own solve time (`Server-Timing`) had a p50 of "
        f"{stats(local.worker_solve)['p50']:.1f} ms.",
        "",
        f"Targets (p50, local executor): HTTP <= 40 ms: {'met' if http_p50 <= 40 else 'NOT met'}"
        f" ({http_p50:.1f} ms with float32 vertices, {out['local:http_json']['p50']:.1f} ms "
        f"with JSON); WebSocket <= 30 ms: {'met' if ws_p50 <= 30 else 'NOT met'} "
        f"({ws_p50:.1f} ms).",
        "",
    ]
    return "\n".join(lines)


def progressive_session(base: str, V: np.ndarray, F: np.ndarray, handles: np.ndarray,
                        drags: np.ndarray) -> tuple[dict, list[dict], np.ndarray]:
    """Per drag: seconds to the linear and to the refined WebSocket reply of a progressive
    session; the refined replies' trailers; the last refined shape (float32)."""
    from websockets.sync.client import connect

    with httpx.Client(base_url=base, timeout=300) as http:
        body = orjson.dumps({"vertices": V, "faces": F, "options": {"refine": True},
                             "handles": [{"vertex": int(h)} for h in handles]},
                            option=orjson.OPT_SERIALIZE_NUMPY)
        created = http.post("/v1/sessions", content=body,
                            headers={"content-type": "application/json"})
        created.raise_for_status()
        location = created.headers["location"]
        times: dict[str, list[float]] = {"linear": [], "refined": [], "continuous": []}
        reports: list[dict] = []
        last = V
        with connect(base.replace("http://", "ws://") + location + "/ws",
                     max_size=None) as ws:
            # A continuous drag first (back and forth along the same path): each drag sent
            # as soon as the previous linear frame is back, the refined frames only for the
            # last one; then the paused drags, each waited for until refined.
            for target in list(drags[::-1]) + list(drags[:1]):
                t0 = time.perf_counter()
                ws.send(target.astype("<f4").tobytes())
                while True:
                    message = ws.recv(timeout=300)
                    n = int(np.frombuffer(message, "<u4", count=2)[1])
                    if orjson.loads(message[8 + 12 * n:])["shape"] == "linear":
                        break
                times["continuous"].append(time.perf_counter() - t0)
            while orjson.loads(message[8 + 12 * n:])["shape"] != "refined":
                message = ws.recv(timeout=300)
                n = int(np.frombuffer(message, "<u4", count=2)[1])
            reports.append(orjson.loads(message[8 + 12 * n:]))
            for target in drags[1:]:
                t0 = time.perf_counter()
                ws.send(target.astype("<f4").tobytes())
                while True:
                    message = ws.recv(timeout=300)
                    n = int(np.frombuffer(message, "<u4", count=2)[1])
                    trailer = orjson.loads(message[8 + 12 * n:])
                    times[trailer["shape"]].append(time.perf_counter() - t0)
                    if trailer["shape"] == "refined":
                        reports.append(trailer)
                        last = np.frombuffer(message, "<f4", count=3 * n, offset=8).reshape(n, 3)
                        break
        http.delete(location).raise_for_status()
    return times, reports, last.astype(np.float64)


def arap_drags(V: np.ndarray, F: np.ndarray, handles: np.ndarray, drags: np.ndarray,
               iterations: int = 10) -> tuple[list[float], np.ndarray]:
    """libigl ARAP: seconds per drag (``iterations`` local/global steps from the previous
    drag's shape) and the last shape."""
    import igl

    data = igl.ARAPData()
    data.max_iter = iterations
    igl.arap_precomputation(V, F, 3, handles.astype(np.int64), data)
    U, times = V.copy(), []
    for target in drags:
        t0 = time.perf_counter()
        U = igl.arap_solve(target, data, U)
        times.append(time.perf_counter() - t0)
    return times, U


def direct_progressive(V: np.ndarray, F: np.ndarray, handles: np.ndarray, drags: np.ndarray,
                       slice_seconds: float = 0.05) -> dict[str, list[float]]:
    """The same drags in this process, as a progressive session computes them:
    ``Deformer.solve(refine=False)`` (the linear frame), then ``refine_last`` in slices of
    ``slice_seconds`` (the default FFS_SESSION_REFINE_SLICE) until it stops."""
    import solver

    deformer = solver.Deformer(V, F, handles, refine=True)
    deformer.solve(refine=False)
    times: dict[str, list[float]] = {"linear": [], "refined": []}
    for target in drags:
        t0 = time.perf_counter()
        deformer.solve(target, refine=False)
        times["linear"].append(time.perf_counter() - t0)
        while True:
            deformer.refine_last(slice_seconds)
            if deformer.last_report.get("stop_reason") != "time_limit":
                break
        times["refined"].append(time.perf_counter() - t0)
    return times


def form_change(rest: np.ndarray, X: np.ndarray, F: np.ndarray) -> tuple[float, float]:
    """(RMS relative edge-length change, RMS dihedral change in radians) of X against rest."""
    import solver

    before = solver.fundamental_forms(rest, F)
    after = solver.fundamental_forms(X, before.faces)
    return (float(np.sqrt(np.mean((after.lengths / before.lengths - 1.0) ** 2))),
            float(np.sqrt(np.mean((after.angles - before.angles) ** 2))))


def progressive_report(name: str, V: np.ndarray, F: np.ndarray, handles: np.ndarray,
                       count: int) -> str:
    """Progressive drags against libigl ARAP-10 per drag, measured in one run."""
    drags = targets(V, handles, count + 1)[1:]
    loads = [load_averages()]
    with uvicorn({"FFS_WORKERS": "1", "FFS_LOG_LEVEL": "warning"}) as base:
        times, reports, ours = progressive_session(base, V, F, handles, drags)
    arap, theirs = arap_drags(V, F, handles, drags)
    direct = direct_progressive(V, F, handles, drags)
    loads.append(load_averages())
    # The first drag starts from the layout fit; the others from the previous refined shape.
    lin, ref, igl10 = stats(times["linear"]), stats(times["refined"]), stats(arap[1:])
    cont = stats(times["continuous"][1:])
    d_lin, d_ref = stats(direct["linear"][1:]), stats(direct["refined"][1:])
    converged = sum(bool(r["converged"]) for r in reports)
    iterations = np.median([r["iterations"] for r in reports])
    factorizations = np.median([r["factorizations"] for r in reports])
    q_ours, q_arap = form_change(V, ours, F), form_change(V, theirs, F)
    first = reports[0]["elapsed"] * 1000
    return "\n".join([
        "## Progressive drags",
        "",
        f"`python -m bench.session_latency --progressive {count}` on {platform.machine()} with "
        f"{os.cpu_count()} cores; {name}: {len(F)} faces, 10 position handles, one smooth "
        f"drag of the first handle in {count} steps, the client waiting for both replies "
        "before the next drag. Local session process (MKL threads: one per core), its "
        "WebSocket; libigl ARAP in this process on the same drags, 10 iterations per drag "
        "from the previous drag's shape. First a continuous drag along the path and back "
        "(each drag sent when the previous linear frame is back; its first refined shape, "
        f"from the layout fit, took {first:.0f} ms), then the paused drags (drags 2 "
        "onwards, each waited for until refined). Milliseconds per drag. Load average "
        f"before and after: {loads[0]} / {loads[-1]}.",
        "",
        "| | p50 (ms) | p90 (ms) | mean (ms) | p50 x ARAP-10 |",
        "|---|---|---|---|---|",
        f"| linear frame of a continuous drag (no pause) | {cont['p50']:.1f} | "
        f"{cont['p90']:.1f} | {cont['mean']:.1f} | {cont['p50'] / igl10['p50']:.2f} |",
        f"| linear frame (first reply) | {lin['p50']:.1f} | {lin['p90']:.1f} | "
        f"{lin['mean']:.1f} | {lin['p50'] / igl10['p50']:.2f} |",
        f"| refined frame (second reply) | {ref['p50']:.1f} | {ref['p90']:.1f} | "
        f"{ref['mean']:.1f} | {ref['p50'] / igl10['p50']:.2f} |",
        f"| libigl ARAP-10 per drag | {igl10['p50']:.1f} | {igl10['p90']:.1f} | "
        f"{igl10['mean']:.1f} | 1.00 |",
        f"| in this process: `Deformer.solve(refine=False)` | {d_lin['p50']:.1f} | "
        f"{d_lin['p90']:.1f} | {d_lin['mean']:.1f} | {d_lin['p50'] / igl10['p50']:.2f} |",
        f"| in this process: then `refine_last(0.05)` until it stops | {d_ref['p50']:.1f} | "
        f"{d_ref['p90']:.1f} | {d_ref['mean']:.1f} | {d_ref['p50'] / igl10['p50']:.2f} |",
        "",
        f"Refined drags: {converged} of {len(reports)} converged; median {iterations:.0f} "
        f"iterations and {factorizations:.0f} factorizations per drag. Last shape against the "
        f"rest shape, RMS relative length change / RMS dihedral change: refined "
        f"{q_ours[0]:.2e} / {q_ours[1]:.2e} rad, ARAP-10 {q_arap[0]:.2e} / {q_arap[1]:.2e} "
        "rad.",
        "",
    ])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--drags", type=int, default=200)
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--dask", action="store_true", help="also measure a Dask actor")
    parser.add_argument("--out", type=Path, help="write the section into this markdown file")
    parser.add_argument("--progressive", type=int, metavar="N",
                        help="measure N progressive drags against libigl ARAP-10 instead")
    args = parser.parse_args()
    name, V, F = session_mesh()
    handles = np.linspace(0, len(V) - 1, 10).astype(np.int64)
    if args.progressive:
        text = progressive_report(name, V, F, handles, args.progressive)
        print(text)
        if args.out:
            write_section(args.out, "## Progressive drags", text)
        return
    drags = targets(V, handles, args.drags + args.rounds)
    env = {"FFS_WORKERS": "1", "FFS_LOG_LEVEL": "warning"}
    loads = [load_averages()]
    with contextlib.ExitStack() as stack:
        servers = {"local": stack.enter_context(uvicorn(env))}
        if args.dask:
            address = stack.enter_context(dask_cluster(1))
            servers["dask"] = stack.enter_context(uvicorn(
                {**env, "FFS_EXECUTOR": "dask", "FFS_DASK_SCHEDULER_ADDRESS": address}))
        out, sessions = measure(V, F, handles, drags, servers, args.rounds)
        loads.append(load_averages())
        text = report(name, V, F, args.drags, args.rounds, out, sessions, loads)
        for session in sessions.values():
            session.close()
    print(text)
    if args.out:
        write_section(args.out, "## Session drag latency", text)


if __name__ == "__main__":
    main()
