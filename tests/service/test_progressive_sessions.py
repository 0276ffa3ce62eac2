"""Progressive session drags (``options.refine: true``): each drag answers its linear shape
at once and its refined shape when ready, over the WebSocket (two replies in order, each with
a JSON trailer) and over HTTP (``Link: rel="refined"`` to poll); a newer drag supersedes a
refinement in progress; both backends (a dedicated process on a real uvicorn, a Dask actor on
a real cluster). The shapes equal ``solver.Deformer``'s ``solve(refine=False)`` and
``refine_last()`` computed in a fresh process of the test."""

from __future__ import annotations

import json
import struct

import httpx
import numpy as np
import pytest

from tests.helpers.meshes import icosphere
from tests.helpers.servers import running_app, uvicorn_server
from tests.helpers.service import problem
from tests.helpers.sessions import reference_progressive

HANDLES = [0, 40, 80, 120]
OCTET = "application/octet-stream"
ONE_SLICE = 60.0
"""A slice longer than any refinement here: the session refines each drag in one slice, as
the reference does (``refine_last(ONE_SLICE)``)."""


@pytest.fixture(scope="module")
def sphere():
    return icosphere(3)


def _targets(V: np.ndarray, lifts: list[float]) -> np.ndarray:
    """Handle targets, exactly representable in float32 (binary drags equal JSON ones): the
    first handle lifted by each of ``lifts``, the others at rest (rounded)."""
    rest = np.round(V[HANDLES] * 1024) / 1024
    out = np.repeat(rest[None], len(lifts), axis=0)
    out[:, 0, 2] += np.asarray(lifts)
    return out


def _create(http, V, F, **options):
    response = http.post("/v1/sessions", json={
        "vertices": V.tolist(), "faces": F.tolist(),
        "handles": [{"vertex": h} for h in HANDLES], "options": options})
    assert response.status_code == 201, response.text
    return response.headers["location"], response.json()


def _refined_link(response: httpx.Response) -> str:
    link = response.headers["link"]
    assert link.endswith('>; rel="refined"'), link
    return link[1:link.index(">")]


def _ws_message(message: bytes) -> tuple[int, np.ndarray, dict | None]:
    """(seq, float32 vertices (n, 3), JSON trailer or None) of a WebSocket reply."""
    seq, n = struct.unpack("<II", message[:8])
    vertices = np.frombuffer(message[8:8 + 12 * n], "<f4").reshape(n, 3)
    rest = message[8 + 12 * n:]
    return seq, vertices, json.loads(rest) if rest else None


def _check_refined_report(report: dict, converged: bool = True) -> None:
    """A finished refinement's report; ``converged``: it must have converged (else it may
    also have stopped at the iteration limit: the solver's business, not the protocol's)."""
    stops = ("converged", "stationary") + (() if converged else ("max_iterations",))
    assert report["stop_reason"] in stops, report
    assert report["converged"] is (report["stop_reason"] != "max_iterations"), report
    assert report["iterations"] >= 1 and report["factorizations"] >= 0, report
    assert report["slices"] >= 1 and report["seconds"] > 0


def _http_drag_then_refined(http, location, target, linear, refined, drag):
    """A JSON drag answers the linear shape with a Link; the link answers the refined shape
    (both to 1e-9 of the reference)."""
    answer = http.post(f"{location}/solve", json={"handle_positions": target.tolist()})
    assert answer.status_code == 200, answer.text
    doc = answer.json()
    assert doc["shape"] == "linear" and doc["drag"] == drag
    np.testing.assert_allclose(doc["vertices"], linear, rtol=0, atol=1e-9)
    link = _refined_link(answer)
    assert link == f"{location}/drags/{drag}/refined"
    got = http.get(link, params={"wait": 60})
    assert got.status_code == 200, got.text
    doc = got.json()
    assert doc["shape"] == "refined" and doc["drag"] == drag
    _check_refined_report(doc["refinement"])
    np.testing.assert_allclose(doc["vertices"], refined, rtol=0, atol=1e-9)
    return doc


def _ws_drag_linear_then_refined(ws, target, linear, refined, drag, seq, recv):
    ws_send = ws.send_bytes if hasattr(ws, "send_bytes") else ws.send
    ws_send(target.astype("<f4").tobytes())
    first, second = _ws_message(recv()), _ws_message(recv())
    assert first[0] == second[0] == seq
    assert first[2] == {"shape": "linear", "drag": drag}
    assert second[2]["shape"] == "refined" and second[2]["drag"] == drag, second[2]
    _check_refined_report(second[2])
    np.testing.assert_allclose(first[1], linear, rtol=0, atol=2e-6)
    np.testing.assert_allclose(second[1], refined, rtol=0, atol=2e-6)


def test_progressive_drags_on_a_real_server_equal_the_deformer(sphere):
    """Linear first, refined last, over HTTP and the WebSocket of a live uvicorn; the refined
    shape equals Deformer.refine_last's and is far from the linear one."""
    from websockets.sync.client import connect

    V, F = sphere
    targets = _targets(V, [0.25, 0.4])
    linear, refined = reference_progressive(V, F, HANDLES, targets, slice_seconds=ONE_SLICE)
    assert np.abs(refined - linear).max() > 1e-3  # refining changes the shape
    env = {"FFS_WORKERS": "1", "FFS_SESSION_THREADS": "1",
           "FFS_SESSION_REFINE_SLICE": str(ONE_SLICE)}
    with uvicorn_server(env) as base, httpx.Client(base_url=base, timeout=90) as http:
        location, doc = _create(http, V, F, refine=True)
        assert doc["refine"] is True
        _http_drag_then_refined(http, location, targets[0], linear[0], refined[0], 1)
        url = base.replace("http://", "ws://") + location + "/ws"
        with connect(url, max_size=None) as ws:
            _ws_drag_linear_then_refined(ws, targets[1], linear[1], refined[1], drag=2, seq=1,
                                         recv=lambda: ws.recv(timeout=90))
        # The WebSocket drag's refined shape over HTTP: in its format (float32), the report
        # in X-Refinement.
        raw = http.get(f"{location}/drags/2/refined")
        assert raw.status_code == 200 and raw.headers["content-type"] == OCTET
        _check_refined_report(json.loads(raw.headers["x-refinement"]))
        np.testing.assert_allclose(np.frombuffer(raw.content, "<f4").reshape(-1, 3),
                                   refined[1], rtol=0, atol=2e-6)


def test_a_new_drag_supersedes_the_refinement_in_progress(sphere):
    """Small slices: a drag sent while the previous one refines is answered (linear) before
    any refined shape of the older drag, which never comes (WebSocket) or answers 409
    (HTTP); the newest drag's refined shape comes last, converged."""
    V, F = sphere
    targets = _targets(V, [0.35, -0.2, 0.3, 0.1])
    with running_app(workers=1, session_refine_slice=0.01) as client:
        location, _ = _create(client, V, F, refine=True)
        # HTTP: drag 1 refines (several iterations, one per slice); drag 2 supersedes it.
        first = client.post(f"{location}/solve",
                            json={"handle_positions": targets[0].tolist()})
        pending = client.get(_refined_link(first))
        assert pending.status_code == 202, pending.text  # still refining
        assert pending.json() == {"drag": 1, "status": "refining",
                                  "links": {"self": f"{location}/drags/1/refined"}}
        assert pending.headers["retry-after"] == "1"
        second = client.post(f"{location}/solve",
                             json={"handle_positions": targets[1].tolist()})
        assert second.json()["drag"] == 2
        doc = problem(client.get(_refined_link(first)), 409, "drag-superseded")
        assert doc["drag"] == 1 and doc["latest"] == 2
        refined = client.get(_refined_link(second), params={"wait": 60})
        assert refined.status_code == 200
        _check_refined_report(refined.json()["refinement"], converged=False)
        problem(client.get(f"{location}/drags/3/refined"), 404, "not-found")

        # WebSocket: drag 3, and as soon as its linear shape is back, drag 4.
        with client.websocket_connect(f"{location}/ws") as ws:
            ws.send_bytes(targets[2].astype("<f4").tobytes())
            seq, _, trailer = _ws_message(ws.receive_bytes())
            assert (seq, trailer) == (1, {"shape": "linear", "drag": 3})
            ws.send_bytes(targets[3].astype("<f4").tobytes())
            replies = []
            while not replies or replies[-1][2]["shape"] != "refined":
                replies.append(_ws_message(ws.receive_bytes()))
        kinds = [(seq, trailer["shape"], trailer["drag"]) for seq, _, trailer in replies]
        assert kinds == [(2, "linear", 4), (2, "refined", 4)], kinds
        _check_refined_report(replies[-1][2], converged=False)
        # The newest drag's refined shape over HTTP is the one the socket sent.
        got = client.get(f"{location}/drags/4/refined")
        assert got.status_code == 200 and got.headers["content-type"] == OCTET
        assert np.array_equal(np.frombuffer(got.content, "<f4").reshape(-1, 3), replies[-1][1])
        assert json.loads(got.headers["x-refinement"]) == {
            k: v for k, v in replies[-1][2].items() if k not in ("shape", "drag")}


def test_plain_sessions_answer_linear_shapes_only(client, sphere):
    """Without refine: true a drag has no Link, its refined link is 404, and WebSocket
    replies have no trailer (the wire format of linear sessions is unchanged)."""
    V, F = sphere
    location, doc = _create(client, V, F)
    assert doc["refine"] is False
    answer = client.post(f"{location}/solve",
                         json={"handle_positions": _targets(V, [0.2])[0].tolist()})
    assert answer.status_code == 200 and "link" not in answer.headers
    assert set(answer.json()) == {"vertices"}
    problem(client.get(f"{location}/drags/1/refined"), 404, "not-found")
    problem(client.get(f"{location}/drags/0/refined"), 422, "validation-error")
    with client.websocket_connect(f"{location}/ws") as ws:
        ws.send_bytes(_targets(V, [0.1])[0].astype("<f4").tobytes())
        message = ws.receive_bytes()
        assert len(message) == 8 + 12 * len(V)
    assert client.delete(location).status_code == 204


@pytest.fixture(scope="module")
def dask_app():
    """An app on a real Dask cluster (one single-threaded worker process)."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=":0", worker_dashboard_address=None) as cluster, \
            running_app(executor="dask", dask_scheduler_address=cluster.scheduler_address,
                        workers=1, session_refine_slice=ONE_SLICE) as client:
        yield client


def test_progressive_drags_on_a_dask_actor(dask_app, sphere):
    """The same protocol on a Dask actor: HTTP and WebSocket answers linear then refined,
    equal to the Deformer's; a newer drag supersedes an older one's refined shape."""
    V, F = sphere
    targets = _targets(V, [0.25, 0.4, 0.1, -0.1])
    linear, refined = reference_progressive(V, F, HANDLES, targets[:2],
                                            slice_seconds=ONE_SLICE)
    location, doc = _create(dask_app, V, F, refine=True)
    assert doc["executor"] == "dask" and doc["refine"] is True
    _http_drag_then_refined(dask_app, location, targets[0], linear[0], refined[0], 1)
    with dask_app.websocket_connect(f"{location}/ws") as ws:
        _ws_drag_linear_then_refined(ws, targets[1], linear[1], refined[1], drag=2, seq=1,
                                     recv=ws.receive_bytes)
    third = dask_app.post(f"{location}/solve", json={"handle_positions": targets[2].tolist()})
    fourth = dask_app.post(f"{location}/solve", json={"handle_positions": targets[3].tolist()})
    assert (third.json()["drag"], fourth.json()["drag"]) == (3, 4)
    doc = problem(dask_app.get(_refined_link(third)), 409, "drag-superseded")
    assert doc["latest"] == 4
    got = dask_app.get(_refined_link(fourth), params={"wait": 60})
    assert got.status_code == 200, got.text
    _check_refined_report(got.json()["refinement"], converged=False)
    assert dask_app.delete(location).status_code == 204


def test_slices_too_short_for_one_iteration_still_converge(sphere):
    """A slice of 1e-7 s ends before the refinement's first iteration; the session doubles
    the next slice after each such one, so the drag converges instead of spending its whole
    budget in empty slices, and the slices continue one refinement: the shape is the one a
    single long slice gives."""
    from service.api.task import SessionSpec
    from service.worker.session import SessionState

    V, F = sphere
    spec = SessionSpec(vertices=V, faces=F, handles=np.asarray(HANDLES),
                       options={"refine": True})
    sliced, whole = (SessionState(spec, solve_timeout=20.0) for _ in range(2))
    for lift in (0.3, 0.5):  # the second drag starts from the first's kept factor
        target = _targets(V, [lift])[0]
        sliced.solve(target, None, "f64")
        refined, slices = None, 0
        while refined is None:
            refined = sliced.refine_slice(1e-7)
            slices += 1
        whole.solve(target, None, "f64")
        one = whole.refine_slice(ONE_SLICE)
        assert refined.report["converged"] and one.report["converged"], refined.report
        assert refined.report["iterations"] == one.report["iterations"] >= 1
        assert slices == refined.report["slices"] <= 100 and one.report["slices"] == 1
        shapes = [np.frombuffer(r.body, "<f8").reshape(-1, 3) for r in (refined, one)]
        assert np.abs(shapes[0] - shapes[1]).max() <= 1e-9 * np.ptp(V), lift
