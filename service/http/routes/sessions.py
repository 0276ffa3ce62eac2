"""Interactive deformation sessions: create (factorize once), solve per drag over HTTP or a
WebSocket, inspect, delete. The wire formats are described in :mod:`service.http.drags` and
docs/service.md.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from typing import Annotated, Any

import numpy as np
import orjson
from fastapi import APIRouter, Path, Query, Request, WebSocket
from starlette.responses import JSONResponse, Response
from starlette.websockets import WebSocketDisconnect, WebSocketState

from service.access.quotas import CONCURRENT_SESSIONS
from service.api.decoding import parse_json
from service.api.documents import RefiningStatus, SessionInfo, SessionVertices
from service.api.problems import ProblemError, element_error
from service.api.schemas import SessionDrag, SessionRequest
from service.backends.contracts import DragAnswer, SessionBackend, SessionRecord
from service.backends.errors import (
    BackendError,
    ClientSessionsError,
    DragSupersededError,
    SessionNotFoundError,
)
from service.http.auth import Caller, CallerDep, accepted_subprotocol, quota_problem
from service.http.bodies import is_json, media_type, read_body
from service.http.dependencies import MetricsDep, ParserDep, SessionsDep, SettingsDep
from service.http.drags import parse_drag_binary, parse_drag_json, ws_reply
from service.http.openapi import created, error_responses
from service.http.payloads import session_spec
from service.http.problems import problem_for
from service.http.routes import API_PREFIX, model_response, path_to
from service.http.routes.operations import format_query, result_format
from service.http.running import server_timing
from service.worker.output import MEDIA_TYPES
from service.worker.session import SESSION_FORMATS

logger = logging.getLogger("service.sessions")
router = APIRouter(prefix=API_PREFIX, tags=["sessions"])

SessionId = Annotated[str, Path(description="Session id (from the Location header).")]
OCTET = "application/octet-stream"
MAX_REFINED_WAIT = 60.0
"""Longest ``?wait=`` of ``GET .../drags/{drag}/refined`` (seconds)."""


def refined_path(session_id: str, drag: int) -> str:
    """Where a progressive session's drag has its refined shape.

    Args:
        session_id: The session.
        drag: The drag's number in it.

    Returns:
        The path of ``GET /v1/sessions/{id}/drags/{drag}/refined``.
    """
    return path_to(router, "get_refined_drag", session_id=session_id, drag=drag)


def drag_headers(session_id: str, answer: DragAnswer) -> dict[str, str]:
    """The headers of a drag's answer.

    Args:
        session_id: The session.
        answer: The drag's linear answer.

    Returns:
        Server-Timing, and for a drag whose refined shape follows
        ``Link: <...>; rel="refined"``.
    """
    headers = server_timing(answer.timings)
    if answer.refining:
        headers["Link"] = f'<{refined_path(session_id, answer.drag)}>; rel="refined"'
    return headers


async def check_owner(sessions: SessionBackend, caller: Caller, session_id: str) -> None:
    """404 for a session of another key (keys off, or an admin key: every session)."""
    if caller.key is None or caller.is_admin:
        return
    if await sessions.owner(session_id) != caller.owner:
        raise SessionNotFoundError(session_id)


def session_document(record: SessionRecord) -> SessionInfo:
    """The 201 body of ``POST /v1/sessions`` and the body of ``GET /v1/sessions/{id}``.

    Args:
        record: What the backend knows of the session.

    Returns:
        Its sizes, expiry, set-up time, backend, memory, solves and links.
    """
    info = record.info
    return SessionInfo(
        id=record.id, n_vertices=info["n_vertices"], n_faces=info["n_faces"],
        handles=info["handles"], n_rotation_groups=info["n_rotation_groups"],
        expires_in=round(max(0.0, record.expires_in), 3),
        setup_seconds=round(info["setup_seconds"], 6), backend=info["backend"],
        executor=record.executor, memory_bytes=int(record.memory), solves=int(record.solves),
        refine=bool(info.get("refine", False)),
        links={"self": path_to(router, "get_session", session_id=record.id),
               "solve": path_to(router, "solve_session", session_id=record.id),
               "ws": path_to(router, "session_ws", session_id=record.id)})


@router.post("/sessions", status_code=201, response_model=SessionInfo,
             summary="Open a deformation session",
             description="Factorizes the rest mesh's deformation system once and keeps it "
                         "warm with one worker (a dedicated process, or a Dask actor). Each "
                         "drag then only back-substitutes: `POST /v1/sessions/{id}/solve` or "
                         "the WebSocket `/v1/sessions/{id}/ws`. Answers 201 with Location. "
                         "Idle sessions expire after FFS_SESSION_TTL seconds.",
             response_class=JSONResponse,
             openapi_extra={"requestBody": {"required": True, "content": {
                 "application/json": {"schema": {"$ref": "#/components/schemas/"
                                                         "SessionRequest"},
                                      "example": SessionRequest.model_config[
                                          "json_schema_extra"]["examples"][0]}}}},
             operation_id="create_session",
             responses={201: created("Created.", f"{API_PREFIX}/sessions/{{id}}", "session_id", {
                                 "SolveSession": "solve_session", "GetSession": "get_session",
                                 "DeleteSession": "delete_session"}),
                        **error_responses(400, 408, 413, 415, 422, 429, 500, 503, 504)})
async def create_session(request: Request, settings: SettingsDep, sessions: SessionsDep,
                         metrics: MetricsDep, parser: ParserDep, caller: CallerDep) -> Response:
    spec = await session_spec(request, settings, parser)
    try:  # FFS_MAX_CLIENT_SESSIONS per address, or the key's quota
        record = await sessions.create(spec, caller.owner, caller.concurrent_sessions)
    except ClientSessionsError as exc:
        if caller.key is None:
            raise
        raise quota_problem(caller, CONCURRENT_SESSIONS, exc.limit, "sessions open") from None
    doc = session_document(record)
    metrics.session_created()
    return model_response(doc, 201, {"Location": doc.links["self"]})


@router.get("/sessions", response_model=list[SessionInfo], summary="List sessions",
            operation_id="list_sessions",
            description="The caller's open sessions: those of its API key (an admin key: "
                        "every key's), or without keys those opened from its address.",
            response_class=JSONResponse)
async def list_sessions(sessions: SessionsDep, caller: CallerDep) -> Response:
    owner = None if caller.is_admin else caller.owner
    documents = [session_document(r).model_dump(exclude_unset=True)
                 for r in await sessions.list(owner)]
    return Response(orjson.dumps(documents), media_type="application/json")


@router.get("/sessions/{session_id}", response_model=SessionInfo, summary="Session state",
            operation_id="get_session",
            response_class=JSONResponse, responses=error_responses(404, 410))
async def get_session(sessions: SessionsDep, session_id: SessionId,
                      caller: CallerDep) -> Response:
    await check_owner(sessions, caller, session_id)
    return model_response(session_document(await sessions.describe(session_id)))


@router.delete("/sessions/{session_id}", status_code=204, summary="Close a session",
               operation_id="delete_session",
               description="Frees the session's factorization (204). A session that expired "
                           "or whose worker died is forgotten as well.",
               response_class=Response, responses=error_responses(404))
async def delete_session(sessions: SessionsDep, session_id: SessionId,
                         caller: CallerDep) -> Response:
    await check_owner(sessions, caller, session_id)
    await sessions.delete(session_id)
    return Response(status_code=204)


SolveFormat = format_query(SESSION_FORMATS)
_SOLVE_CONTENT = {
    "application/json": {"schema": {"$ref": "#/components/schemas/SessionVertices"}},
    "application/octet-stream": {"schema": {"type": "string", "format": "binary",
                                            "description": "Little-endian float32, n x 3."}},
    "model/gltf-binary": {"schema": {"type": "string", "format": "binary"}},
    "model/gltf+json": {"schema": {"type": "object"}},
}


@router.post("/sessions/{session_id}/solve", response_model=SessionVertices,
             operation_id="solve_session",
             summary="Solve one drag",
             description="New targets for the handles (and rotations for the rotation "
                         "groups) -> the deformed vertices, by back-substitution only. Body: "
                         "JSON `{\"handle_positions\", \"handle_rotations\"?}` or "
                         "`application/octet-stream` (little-endian float32: 3 h positions, "
                         "optionally followed by 9 g rotation entries). Result by `Accept` "
                         "or `?format=`: JSON (default), `application/octet-stream` "
                         "(little-endian float32 "
                         "n x 3, ready for a vertex buffer), GLB or glTF. In a session opened "
                         "with `options.refine: true` the answer is the linear shape at once "
                         "(JSON: `shape: \"linear\"`, `drag`) and `Link: <...>; "
                         "rel=\"refined\"` names where its refined shape will be "
                         "(`GET /v1/sessions/{id}/drags/{drag}/refined`).",
             response_class=Response,
             openapi_extra={"requestBody": {"required": True, "content": {
                 "application/json": {"schema": {"$ref": "#/components/schemas/SessionDrag"},
                                      "example": SessionDrag.model_config[
                                          "json_schema_extra"]["examples"][0]},
                 OCTET: {"schema": {"type": "string", "format": "binary",
                                    "examples": ["<3 h float32 values>"]}}}}},
             responses={200: {"description": "The deformed vertices.",
                              "content": _SOLVE_CONTENT},
                        **error_responses(400, 404, 406, 408, 410, 413, 415, 422, 503, 504)})
async def solve_session(request: Request, session_id: SessionId, settings: SettingsDep,
                        sessions: SessionsDep, metrics: MetricsDep, caller: CallerDep,
                        fmt: SolveFormat = None) -> Response:
    fmt = result_format(request, SESSION_FORMATS, fmt)
    await check_owner(sessions, caller, session_id)
    n_handles, n_groups = await sessions.shape(session_id)
    mtype = media_type(request)
    body = await read_body(request, settings)
    if mtype == OCTET:
        positions, rotations = parse_drag_binary(body, n_handles, n_groups)
    elif is_json(mtype):
        # NaN and Infinity parse, so that the drag's check names them (422), as everywhere
        positions, rotations, _ = parse_drag_json(parse_json(body), n_handles, n_groups)
    else:
        raise ProblemError("unsupported-media-type",
                           f"Content-Type {mtype!r} is not supported; send application/json "
                           "or application/octet-stream",
                           errors=[element_error("Content-Type", mtype)])
    start = time.perf_counter()
    answer = await sessions.solve(session_id, positions, rotations, fmt)
    metrics.session_solve("http", time.perf_counter() - start)
    return Response(answer.body, media_type=MEDIA_TYPES[fmt],
                    headers=drag_headers(session_id, answer))


@router.get("/sessions/{session_id}/drags/{drag}/refined", response_model=SessionVertices,
            operation_id="get_refined_drag", summary="The refined shape of a drag",
            description="A progressive session's (`options.refine: true`) refined shape of "
                        "drag `drag` (the `Link` of its solve's answer), in the format of "
                        "that answer; JSON adds `refinement` (converged, stop_reason, "
                        "iterations, factorizations, slices, seconds, energy), other formats "
                        "carry it in the `X-Refinement` header (JSON). While it refines: 202 "
                        "with `Retry-After`; `?wait=s` (at most 60) waits up to s seconds "
                        "for it first. Only the newest drag is refined: an older one is 409 "
                        "`drag-superseded` naming the newest (`latest`).",
            response_class=Response,
            responses={200: {"description": "The refined vertices.",
                             "content": _SOLVE_CONTENT},
                       202: {"description": "Still refining; poll again.",
                             "model": RefiningStatus},
                       **error_responses(404, 409, 410, 422)})
async def get_refined_drag(
        sessions: SessionsDep, session_id: SessionId, caller: CallerDep,
        drag: Annotated[int, Path(ge=1, le=2**32 - 1, description="The drag's number (in "
                                                                  "its Link).")],
        wait: Annotated[float, Query(ge=0, le=MAX_REFINED_WAIT,
                                     description="Seconds to wait for the refined shape "
                                                 "before answering 202.")] = 0.0) -> Response:
    await check_owner(sessions, caller, session_id)
    refined = await sessions.refined(session_id, drag, wait)
    if refined is None:
        doc = RefiningStatus(drag=drag, status="refining",
                             links={"self": refined_path(session_id, drag)})
        return model_response(doc, 202, {"Retry-After": "1"})
    return Response(refined.body, media_type=MEDIA_TYPES[refined.fmt], headers={
        "X-Refinement": orjson.dumps(refined.report).decode()})


def _problem_text(problem: ProblemError, instance: str, seq: int | None) -> str:
    """A problem as a WebSocket text message (with the drag's ``seq`` when known)."""
    doc = problem.to_dict(instance)
    if seq is not None:
        doc["seq"] = seq
    return orjson.dumps(doc, option=orjson.OPT_SERIALIZE_NUMPY).decode()


@router.websocket("/sessions/{session_id}/ws")
async def session_ws(websocket: WebSocket, session_id: str, sessions: SessionsDep,
                     metrics: MetricsDep, caller: CallerDep) -> None:
    """Drags in, vertices out; the newest drag wins (see docs/service.md). In a progressive
    session each drag answers twice, the linear shape at once and the refined one when it
    is ready (unless a newer drag came first), each reply with a JSON trailer saying which."""
    instance = path_to(router, "session_ws", session_id=session_id)
    await websocket.accept(subprotocol=accepted_subprotocol(websocket.scope))
    send_lock = asyncio.Lock()

    async def send_problem(problem: ProblemError, seq: int | None) -> None:
        async with send_lock:
            await websocket.send_text(_problem_text(problem, instance, seq))

    try:
        await check_owner(sessions, caller, session_id)
        n_handles, n_groups = await sessions.shape(session_id)
    except BackendError as exc:
        problem = problem_for(exc)
        await send_problem(problem, None)
        await websocket.close(code=4000 + problem.status, reason=problem.kind)
        return

    latest: list[tuple[int, np.ndarray, np.ndarray | None] | None] = [None]
    wake = asyncio.Event()
    closed = False

    async def receive() -> None:
        nonlocal closed
        count = 0
        try:
            while True:
                message = await websocket.receive()
                if message["type"] == "websocket.disconnect":
                    break
                count += 1
                seq: int | None = count
                try:
                    if message.get("bytes") is not None:
                        positions, rotations = parse_drag_binary(message["bytes"], n_handles,
                                                                 n_groups)
                    else:
                        doc = parse_json((message.get("text") or "").encode())  # NaN: 422
                        positions, rotations, given = parse_drag_json(doc, n_handles,
                                                                      n_groups)
                        seq = count if given is None else given
                except ProblemError as exc:
                    await send_problem(exc, seq)
                    continue
                if latest[0] is not None:
                    metrics.session_dropped()
                latest[0] = (seq, positions, rotations)
                wake.set()
        except (WebSocketDisconnect, RuntimeError):
            pass
        finally:
            closed = True
            wake.set()

    async def follow(drag: int) -> Any:
        """The refined shape of ``drag`` (None: superseded by a newer drag)."""
        while True:
            try:
                refined = await sessions.refined(session_id, drag, MAX_REFINED_WAIT)
            except DragSupersededError:
                return None
            if refined is not None:
                return refined

    # The newest drag's refined shape to come: (seq, task).
    following: tuple[int, asyncio.Task[Any]] | None = None
    receiver = asyncio.create_task(receive())
    try:
        while True:
            woken = asyncio.ensure_future(wake.wait())
            waiting: set[asyncio.Future[Any]] = {woken}
            if following is not None:
                waiting.add(following[1])
            done, _ = await asyncio.wait(waiting, return_when=asyncio.FIRST_COMPLETED)
            if following is not None and following[1] in done:
                (seq, task), following = following, None
                try:
                    refined = task.result()
                except BackendError as exc:
                    await send_problem(problem_for(exc), seq)
                else:
                    if refined is not None:
                        async with send_lock:
                            await websocket.send_bytes(ws_reply(seq, refined.body, {
                                "shape": "refined", "drag": refined.drag, **refined.report}))
            if woken not in done:
                woken.cancel()
                continue
            wake.clear()
            if closed:
                break
            item, latest[0] = latest[0], None
            if item is None:
                continue
            if following is not None:  # this drag supersedes it
                following[1].cancel()
                following = None
            seq, positions, rotations = item
            start = time.perf_counter()
            try:
                answer = await sessions.solve(session_id, positions, rotations, "f32")
            except BackendError as exc:
                problem = problem_for(exc)
                await send_problem(problem, seq)
                if problem.status in (404, 410):
                    await websocket.close(code=4000 + problem.status, reason=problem.kind)
                    break
                continue
            metrics.session_solve("ws", time.perf_counter() - start)
            trailer = ({"shape": "linear", "drag": answer.drag} if answer.refining else None)
            async with send_lock:
                await websocket.send_bytes(ws_reply(seq, answer.body, trailer))
            if answer.refining:
                following = (seq, asyncio.create_task(follow(answer.drag)))
    except (WebSocketDisconnect, RuntimeError, OSError):
        pass
    finally:
        if following is not None:
            following[1].cancel()
        receiver.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await receiver
        if websocket.application_state != WebSocketState.DISCONNECTED:
            with contextlib.suppress(Exception):
                await websocket.close()
