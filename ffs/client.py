"""A Python client of the fundamental-forms service: numpy arrays in, numpy arrays out.

Needs only ``httpx`` and ``numpy`` (``websockets`` for WebSocket sessions; without it they
fall back to HTTP): ``pip install ".[client]"``. Nothing here imports FastAPI or the
service::

    from ffs import Client

    with Client("http://localhost:8000") as client:
        forms = client.fundamental_forms(vertices, faces)
        mesh = client.reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles)

* One method per operation of the service, named like the library's function
  (:mod:`solver`), taking the same arrays and returning :mod:`ffs.results` (vertices (n, 3)
  float64, faces (m, 3) int64, ...): the table :data:`ffs.operations.OPERATIONS` names
  them; each ``<method>_call`` builds the request (written here), ``<method>`` runs it
  (made from the table). Options are the HTTP options (``refine``, ``frame_weight``,
  ``orthonormalize``, ``weighting``, ``solver``, ...; docs/service.md) and are sent only
  when given, so the service's defaults apply.
* Bodies are ``application/vnd.ffs.arrays`` (:mod:`ffs_wire.arrays`) unless ``binary=False``
  (JSON); answers are JSON, whose float64 values round-trip exactly.
* ``progress=callback`` (or :meth:`Client.submit`) runs the operation as a job: the
  callback gets ``(stage, fraction)`` as the service reports them; jobs have no
  synchronous request timeout.
* :meth:`Client.session` keeps one mesh's factorization warm on the service and drags it
  over a WebSocket (float32 vertices) or, without one, over HTTP (float64).
* Mesh files (:meth:`Client.load_mesh`, :meth:`Client.blend_files`) are uploaded as they
  are, but a ``.gltf`` with its buffer files beside it embedded (:func:`upload`).
* A problem document raises the :mod:`ffs.errors` class of its status; 503 (and 429 with
  ``Retry-After``) are retried ``retries`` times, waiting ``Retry-After`` seconds (at most
  ``max_wait``) or an exponential backoff from ``backoff`` seconds.
"""

from __future__ import annotations

import inspect
import json
import os
import random
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from ffs import __version__
from ffs.errors import (
    FFSError,
    LocalFileError,
    ProblemError,
    RequestTimeoutError,
    ServiceUnreachableError,
    problem_error,
)
from ffs.jobs import Job
from ffs.operations import OPERATIONS, Operation
from ffs.results import Forms, Mesh, ShapeBlend
from ffs.sessions import Session
from ffs_wire import gltf
from ffs_wire.arrays import BINARY_MEDIA_TYPE, binary_body, json_default

Progress = Callable[[str, float], None]
"""``progress(stage, fraction)``: the service's stage names (validate, assemble, factorize,
solve, refine, encode; ``queued`` while a job waits), fraction of that stage in [0, 1]."""

DEFAULT_URL = "http://127.0.0.1:8000"
SERVER_ENV = "FFS_SERVER"
"""Environment variable naming the service when ``Client()`` is given no URL."""
TOKEN_ENV = "FFS_TOKEN"
"""The API key a :class:`Client` sends when it is given none (services with keys)."""
USE_A_JOB = "use-a-job"
"""The problem kind of a request too large to answer synchronously: :meth:`Client.run`
submits it as a job instead."""
LARGE_INPUT_FACES = 10_000
"""Faces beyond which :meth:`Client.run` compares a call with the service's synchronous
limit (``GET /v1/me``) before sending it."""


@dataclass(frozen=True)
class Call:
    """One operation request: its name (:data:`ffs.operations.OPERATIONS`), large arrays
    and other fields."""

    operation: str
    arrays: dict[str, np.ndarray]
    params: dict[str, Any]

    @property
    def decode(self) -> Callable[[dict[str, Any]], Any]:
        """The decoder of the operation's JSON answer (its result type's ``from_dict``)."""
        return OPERATIONS[self.operation].decode

    def json_body(self) -> dict[str, Any]:
        """The JSON body of the synchronous endpoint (the ``input`` of a job)."""
        return {**self.params, **{name: np.asarray(a).tolist() for name, a in self.arrays.items()}}


def _options(refine: bool | None, options: Mapping[str, Any]) -> dict[str, Any]:
    chosen = {name: value for name, value in options.items() if value is not None}
    if refine is not None:
        chosen["refine"] = refine
    return chosen


def _linear_answer(call: Call) -> bool:
    """Whether ``call`` asks for the linear answer (``options.refine`` false), which the
    service prices by its own limits."""
    options = call.params.get("options")
    return isinstance(options, Mapping) and options.get("refine") is False


def _dumps(document: Any) -> bytes:
    return json.dumps(document, separators=(",", ":"), default=json_default).encode()


def _retry_after(response: httpx.Response) -> float | None:
    value = response.headers.get("retry-after")
    try:
        return max(0.0, float(value)) if value is not None else None
    except ValueError:
        return None




class Client:
    """The service at ``url`` (default: ``$FFS_SERVER``, else http://127.0.0.1:8000).

    Args:
        url: base URL of the service.
        timeout: seconds for connecting and for each answer (a synchronous solve must
            finish within it; jobs are polled, so they are not bound by it).
        binary: send operation bodies as ``application/vnd.ffs.arrays`` (default) or JSON.
        retries: how often a 503 (or a 429 with ``Retry-After``) is retried.
        backoff: first wait without ``Retry-After`` (doubled on each retry, with jitter).
        max_wait: longest single wait, whatever ``Retry-After`` says.
        headers: extra headers for every request.
        transport: an ``httpx`` transport (tests, proxies).
        token: the API key of a service with keys (default ``$FFS_TOKEN``), sent as
            ``Authorization: Bearer`` on every request and the sessions' WebSocket
            handshake (never in a URL).

    The client is thread-safe: one instance can run many requests and jobs at once.
    """

    def __init__(self, url: str | None = None, *, timeout: float = 60.0, binary: bool = True,
                 retries: int = 4, backoff: float = 0.5, max_wait: float = 30.0,
                 headers: Mapping[str, str] | None = None,
                 transport: httpx.BaseTransport | None = None,
                 token: str | None = None) -> None:
        self.url = (url or os.environ.get(SERVER_ENV) or DEFAULT_URL).rstrip("/")
        self.token = token or os.environ.get(TOKEN_ENV) or None
        """The API key sent as ``Authorization: Bearer`` (HTTP and the sessions'
        WebSocket handshake); None for a service without keys."""
        self.timeout = timeout
        self.binary = binary
        self.retries = retries
        self.backoff = backoff
        self.max_wait = max_wait
        self._sync_faces: dict[str, int] | None = None
        """The service's ``max_sync_faces_by_operation``, read on the first large call."""
        self._linear_sync_faces: dict[str, int] = {}
        """Its ``max_linear_sync_faces_by_operation`` (a linear answer's, read with it)."""
        self._http = httpx.Client(base_url=self.url, timeout=timeout, transport=transport,
                                  headers={"User-Agent": f"ffs-client/{__version__}",
                                           **self.auth_headers(), **(headers or {})})

    # ------------------------------------------------------------------ plumbing

    def auth_headers(self) -> dict[str, str]:
        """``Authorization: Bearer <token>``, or nothing without a token."""
        return {"Authorization": f"Bearer {self.token}"} if self.token else {}

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        """One HTTP request with the retries; a problem document raises its typed error."""
        for attempt in range(self.retries + 1):
            try:
                response = self._http.request(method, path, **kwargs)
            except httpx.TimeoutException:
                raise RequestTimeoutError(f"{method} {self.url}{path}: no answer within "
                                     f"{self.timeout:g} s") from None
            except httpx.TransportError as exc:
                raise ServiceUnreachableError(f"cannot reach {self.url}: {exc}") from None
            wait = self._retry_wait(response, attempt)
            if wait is None:
                break
            response.close()
            time.sleep(wait)
        if response.status_code >= 400:
            raise self._problem(response)
        return response

    def _retry_wait(self, response: httpx.Response, attempt: int) -> float | None:
        """Seconds to wait before retrying ``response``, or None to take it as it is."""
        status, after = response.status_code, _retry_after(response)
        if attempt >= self.retries or status not in (429, 503) or (status == 429
                                                                   and after is None):
            return None
        if after is None:
            after = self.backoff * 2 ** attempt * (0.5 + random.random())
        return min(after, self.max_wait)

    def _problem(self, response: httpx.Response) -> ProblemError:
        try:
            document = response.json()
        except ValueError:
            document = None
        if not isinstance(document, dict):
            text = response.text.strip()[:200]
            document = {"title": response.reason_phrase or "Error", "status":
                        response.status_code, "detail": text or response.reason_phrase}
        return problem_error(document, response.status_code, _retry_after(response))

    def _post_json(self, path: str, document: Any, **kwargs: Any) -> httpx.Response:
        return self.request("POST", path, content=_dumps(document),
                            headers={"Content-Type": "application/json",
                                     **kwargs.pop("headers", {})}, **kwargs)

    def run(self, call: Call, progress: Progress | None = None) -> Any:
        """Run one :class:`Call`: synchronously, or as a job when ``progress`` is given or
        when the service answers that the request is too large to answer synchronously
        (413 ``use-a-job``: its answer is predicted to take longer than the service's
        ``FFS_REQUEST_TIMEOUT``)."""
        if progress is not None or self._too_slow_for_sync(call):
            return self._run_as_job(call, progress)
        try:
            return self._run_synchronously(call)
        except ProblemError as exc:
            if exc.kind != USE_A_JOB:
                raise
        return self._run_as_job(call, None)

    def _too_slow_for_sync(self, call: Call) -> bool:
        """Whether a call of more than :data:`LARGE_INPUT_FACES` faces exceeds the faces the
        service answers synchronously for its operation (``GET /v1/me``'s
        ``max_sync_faces_by_operation``, or for a linear answer, ``options.refine`` false,
        its ``max_linear_sync_faces_by_operation`` where the service names one; read once),
        so that it goes to the job API without being sent twice."""
        faces = call.arrays.get("faces")
        if faces is None or len(faces) <= LARGE_INPUT_FACES:
            return False
        if self._sync_faces is None:
            try:
                limits = self.size_limits()
            except (ProblemError, KeyError, TypeError, ValueError):  # keys, older services
                limits = {}
            self._sync_faces = dict(limits.get("max_sync_faces_by_operation") or {})
            self._linear_sync_faces = dict(limits.get("max_linear_sync_faces_by_operation")
                                           or {})
        limit = self._sync_faces.get(call.operation)
        if _linear_answer(call):
            limit = self._linear_sync_faces.get(call.operation, limit)
        return limit is not None and len(faces) > limit

    def _run_as_job(self, call: Call, progress: Progress | None) -> Any:
        job = self.submit_call(call)
        try:
            return job.result(on_progress=progress)
        finally:
            job.discard()

    def _run_synchronously(self, call: Call) -> Any:
        if self.binary:
            response = self.request("POST", f"/v1/{call.operation}",
                                    content=binary_body(call.params, call.arrays),
                                    headers={"Content-Type": BINARY_MEDIA_TYPE,
                                             "Accept": "application/json"})
        else:
            response = self._post_json(f"/v1/{call.operation}", call.json_body(),
                                       headers={"Accept": "application/json"})
        return call.decode(response.json())

    # ---------------------------------------------------------------- operations

    def health(self) -> dict[str, Any]:
        """``GET /readyz``: the pool's readiness (status, workers, busy, queue depth)."""
        try:
            return dict(self.request("GET", "/readyz").json())
        except ProblemError as exc:  # 503 while starting: the document says why
            return exc.document

    # ------------------------------------------------------ operations (requests)
    # One ``<method>_call`` per operation of :data:`ffs.operations.OPERATIONS`: its
    # arguments -> the request; ``Client.<method>(..., progress=None)`` runs it (made from
    # the table below the class, with this docstring and signature). Written here for the
    # operations that need more than their arrays and options; :func:`table_call` makes
    # the others' from their row.

    def check_integrability_call(self, faces: Any, edges: Any = None, lengths: Any = None,
                                 angles: Any = None, *, tol: float | None = None,
                                 vertex_map: Any = None, weld_map: Any = None) -> Call:
        """The integrability report of forms (``POST /v1/integrability``); ``faces`` may be
        a :class:`~ffs.results.Forms` alone (its ``vertex_map`` and ``weld_map`` are sent),
        or those maps given as keywords."""
        forms = Forms.given(faces, edges, lengths, angles, vertex_map=vertex_map,
                            weld_map=weld_map)
        params = {} if tol is None else {"tolerance": tol}
        params.update(forms.params())
        return Call("integrability", forms.arrays(), params)

    def reconstruct_call(self, faces: Any, edges: Any = None, lengths: Any = None,
                         angles: Any = None, *, constraints: Mapping[str, Any] | None = None,
                         refine: bool | None = None, align_to: Any = None,
                         vertex_map: Any = None, weld_map: Any = None, placement: Any = None,
                         **options: Any) -> Call:
        """Vertex positions from forms (``POST /v1/reconstruct``). ``constraints`` is the
        API's ``{"positions": [{"vertex", "position", "weight"?}], "frames": [...]}``;
        ``align_to``: (n, 3) vertices of a reference to move the answer onto rigidly
        (``report["alignment"]`` has the residual); ``vertex_map``, ``weld_map`` and
        ``placement``: those of the forms, as the library's ``reconstruct`` takes them (a
        :class:`~ffs.results.Forms` alone brings its own): the answer per file vertex, each
        part where it was; ``options``: frame_weight, orthonormalize, orthonormal_weight,
        weighting, solver, tolerance, require_integrable, exact_shortcut, linear_solver."""
        forms = Forms.given(faces, edges, lengths, angles, vertex_map=vertex_map,
                            weld_map=weld_map, placement=placement)
        params: dict[str, Any] = {"options": _options(refine, options)}
        if constraints:
            params["constraints"] = (dict(constraints) if isinstance(constraints, Mapping)
                                     else constraints)  # the service names what is wrong
        if align_to is not None:
            params["align_to"] = np.asarray(align_to, dtype=np.float64).reshape(-1, 3).tolist()
        params.update(forms.params())
        return Call("reconstruct", forms.arrays(), params)

    def reconstruct_vjp_call(self, faces: Any, edges: Any = None, lengths: Any = None,
                             angles: Any = None, *, cotangent: Any,
                             constraints: Mapping[str, Any] | None = None,
                             refine: bool | None = None, **options: Any) -> Call:
        """A reconstruction and the cotangents of its inputs (``POST
        /v1/reconstruct/vjp``; :func:`solver.reconstruct_vjp`): ``cotangent`` (n, 3) or
        (k, n, 3), the gradient of a loss with respect to the vertices, pulled back to the
        lengths, angles and constraint targets (:class:`~ffs.results.VjpResult`). The
        arguments and options of :meth:`reconstruct` (``refine=False``: the linear answer
        is differentiated)."""
        call = self.reconstruct_call(faces, edges, lengths, angles, constraints=constraints,
                                     refine=refine, **options)
        cotangent = np.asarray(cotangent, dtype=np.float64).tolist()
        return Call("reconstruct/vjp", call.arrays, {**call.params, "cotangent": cotangent})

    def deform_call(self, vertices: Any, faces: Any, handles: Sequence[int] | np.ndarray,
                    handle_positions: Any, *, rotation_handles: Sequence[Any] | None = None,
                    handle_rotations: Any = None, roi: Any = None, refine: bool | None = None,
                    **options: Any) -> Call:
        """Move ``handles`` (h,) to ``handle_positions`` (h, 3) (``POST /v1/deform``), with
        optional rotation groups (face lists) and their (g, 3, 3) rotations, and a region
        of interest; ``options``: frame_weight, orthonormalize, weighting, solver."""
        targets = np.asarray(handle_positions, dtype=np.float64).reshape(-1, 3)
        params: dict[str, Any] = {
            "handles": [{"vertex": int(v), "position": p}
                        for v, p in zip(np.asarray(handles).ravel().tolist(), targets.tolist(),
                                        strict=True)],
            "options": _options(refine, options)}
        if rotation_handles:
            rotations = np.asarray(handle_rotations, dtype=np.float64).reshape(-1, 3, 3)
            params["rotations"] = [{"faces": np.asarray(group).ravel().tolist(), "rotation": r}
                                   for group, r in zip(rotation_handles, rotations.tolist(),
                                                       strict=True)]
        if roi is not None:
            params["roi"] = np.asarray(roi).ravel().tolist()
        return Call("deform", {"vertices": np.asarray(vertices), "faces": np.asarray(faces)},
                    params)

    def interpolate_call(self, vertices_a: Any, vertices_b: Any, faces: Any,
                         t: float | Sequence[float], *, refine: bool | None = None,
                         **options: Any) -> Call:
        """Blend two embeddings of ``faces`` in form space (``POST /v1/interpolate``)."""
        t_value = _t_values(t)
        return Call("interpolate", {"vertices_a": np.asarray(vertices_a),
                                    "vertices_b": np.asarray(vertices_b),
                                    "faces": np.asarray(faces)},
                    {"t": t_value, "options": _options(refine, options)})

    def blend_call(self, shapes: Any, faces: Any, weights: Any = None, *,
                   t: float | Sequence[float] | None = None,
                   refine: bool | None = None, **options: Any) -> Call:
        """Blend K embeddings (K, n, 3) of ``faces`` in form space (``POST /v1/blend``): one
        shape per row of affine ``weights`` (T, K), or per ``t`` for two shapes; ``options``:
        sequence, align, solver, max_seconds. With ``progress`` it runs as a job and
        reports the rows as they are solved (stage ``rows``)."""
        params = _blend_params(len(shapes), weights, t, _options(refine, options))
        return Call("blend", {"shapes": np.asarray(shapes, dtype=np.float64),
                              "faces": np.asarray(faces)}, params)

    def blend_files(self, paths: Sequence[str | os.PathLike[str]], weights: Any = None, *,
                    t: float | Sequence[float] | None = None, refine: bool | None = None,
                    **options: Any) -> ShapeBlend:
        """Blend K mesh files of one connectivity (OBJ, PLY, OFF, STL, GLB, glTF), uploaded
        as they are (a ``.gltf``'s buffer files beside it embedded: :func:`upload`;
        ``POST /v1/blend``, one ``shapes`` part per file, in order): rows of ``weights``
        (T, K), or ``t`` for two files. Its :attr:`ShapeBlend.warnings` name the rows past
        the documented thresholds."""
        params = _blend_params(len(paths), weights, t, _options(refine, options))
        files = [("shapes", upload(p)) for p in paths]
        response = self.request("POST", "/v1/blend", headers={"Accept": "application/json"},
                                files=files, data={k: json.dumps(v) for k, v in params.items()})
        return ShapeBlend.from_dict(response.json())

    def blend_gltf(self, shapes: Any, faces: Any, weights: Any = None, *,
                   t: float | Sequence[float] | None = None,
                   times: Sequence[float] | None = None, kind: str = "glb",
                   refine: bool | None = None, **options: Any) -> bytes:
        """The blend as one animated glTF file (``kind`` ``glb`` or ``gltf``): the first
        shape as the mesh, each row a morph target, an animation playing them at ``times``
        (default 24 rows per second)."""
        call = self.blend_call(shapes, faces, weights, t=t, refine=refine, **options)
        body = call.json_body()
        if times is not None:
            body["times"] = [float(x) for x in times]
        media = {"glb": "model/gltf-binary", "gltf": "model/gltf+json"}[kind]
        return self._post_json("/v1/blend", body,
                               headers={"Accept": media}).content

    def mean(self, shapes: Any, faces: Any, *, refine: bool | None = None,
             progress: Progress | None = None, **options: Any) -> Mesh:
        """The form-space mean (n, 3) of K shapes (``POST /v1/blend`` with equal weights and
        ``align``: where each shape sits does not matter)."""
        count = len(shapes)  # none: the service names the count (422, ``shapes``)
        result = self.blend(shapes, faces, np.full((1, count), 1.0 / max(count, 1)),
                            refine=refine, progress=progress, **{"align": True, **options})
        return Mesh(result.vertices[0], result.faces, result.reports[0])

    def size_limits(self) -> dict[str, Any]:
        """How large a request the service admits for this client (``GET /v1/me``):
        ``max_faces``, ``max_vertices``, ``max_body_bytes``, ``max_request_memory`` and
        ``max_faces_by_operation`` (each operation's largest mesh, the key's quota
        included; a larger one is answered 413, :class:`ffs.errors.PayloadTooLargeError`),
        ``max_sync_faces_by_operation`` (the most a synchronous request may bring; beyond,
        :meth:`run` sends a job) and, for ``reconstruct``, ``max_direct_faces_by_operation``,
        ``max_linear_faces_by_operation`` and ``max_linear_sync_faces_by_operation`` (its
        linear answer's, ``refine=False``)."""
        limits: dict[str, Any] = self.request("GET", "/v1/me").json()["size_limits"]
        return limits

    def load_mesh(self, path: str | os.PathLike[str]) -> Mesh:
        """A mesh file (OBJ, PLY, OFF, STL, GLB, glTF) uploaded and read by the service (a
        ``.gltf``'s buffer files beside it embedded: :func:`upload`)."""
        response = self.request("POST", "/v1/mesh", headers={"Accept": "application/json"},
                                files={"file": upload(path)})
        return Mesh.from_dict(response.json())

    # ---------------------------------------------------------------------- jobs

    CALLS = tuple(OPERATIONS)
    """Operations :meth:`submit` takes (the job API's names)."""

    def submit(self, operation: str, *args: Any, **kwargs: Any) -> Job:
        """Queue ``operation`` (a name of :data:`CALLS`, with the arguments of its method:
        ``submit("reconstruct", forms, refine=True)``) as a job."""
        if operation not in OPERATIONS:
            raise ValueError(f"unknown operation {operation!r}; one of {', '.join(OPERATIONS)}")
        build = getattr(self, f"{OPERATIONS[operation].method}_call")
        return self.submit_call(build(*args, **kwargs))

    def submit_call(self, call: Call) -> Job:
        """Queue a :class:`Call` as a job (``POST /v1/jobs``, JSON)."""
        response = self._post_json("/v1/jobs", {"operation": call.operation,
                                                "input": call.json_body()})
        document = response.json()
        return Job(self, document["id"], call.operation, call.decode, document)

    def job(self, job_id: str, decode: Callable[[dict[str, Any]], Any] | None = None) -> Job:
        """A handle on an existing job (its result decoded as a dict unless ``decode``)."""
        return Job(self, job_id, "", decode or dict, None)

    # ------------------------------------------------------------------ sessions

    def session(self, vertices: Any, faces: Any, handles: Sequence[int] | np.ndarray, *,
                rotation_handles: Sequence[Any] | None = None, roi: Any = None,
                transport: str = "auto", **options: Any) -> Session:
        """Open a deformation session (``POST /v1/sessions``): the mesh and handle set are
        factorized once; every :meth:`Session.drag` then only back-substitutes.

        ``transport``: ``"auto"`` (a WebSocket when ``websockets`` is installed and the
        socket opens, else HTTP), ``"ws"`` or ``"http"``. ``options``: frame_weight,
        orthonormalize, weighting, solver, refine (a session refines only with True)."""
        if transport not in ("auto", "ws", "http"):
            raise ValueError("transport must be 'auto', 'ws' or 'http'")
        body: dict[str, Any] = {
            "vertices": np.asarray(vertices, dtype=np.float64).tolist(),
            "faces": np.asarray(faces).tolist(),
            "handles": [{"vertex": int(v)} for v in np.asarray(handles).ravel().tolist()],
            "options": _options(None, options)}
        if rotation_handles:
            body["rotations"] = [{"faces": np.asarray(g).ravel().tolist()}
                                 for g in rotation_handles]
        if roi is not None:
            body["roi"] = np.asarray(roi).ravel().tolist()
        info = self._post_json("/v1/sessions", body).json()
        session = Session(self, info)
        if transport != "http":
            try:
                session.connect()
            except (ImportError, OSError, FFSError):
                if transport == "ws":
                    session.close()
                    raise
        return session


def upload(path: str | os.PathLike[str]) -> tuple[str, bytes]:
    """A mesh file as a multipart upload ``(name, bytes)``: the file as it is, but a ``.gltf``
    whose buffers are files beside it gets them embedded as ``data:`` URIs (separate images
    dropped: :func:`ffs_wire.gltf.file_bytes`, the rule ``ffs`` and the library apply to files
    on disk), since the service gets the bytes alone.

    Raises:
        OSError: the file cannot be read.
        LocalFileError: a buffer file the ``.gltf`` names cannot (``buffers[index]``).
    """
    path = Path(path)
    try:
        return path.name, gltf.file_bytes(path)
    except gltf.BufferFileError as exc:
        raise LocalFileError(str(path), exc.reason, field="buffers", index=exc.index) from None


def table_call(operation: Operation) -> Callable[..., Call]:
    """``Client.<method>_call`` of an operation that takes only its arrays (positional, in
    the row's order) and, where it has options, ``refine`` and the solver options."""
    P = inspect.Parameter
    parameters = [P("self", P.POSITIONAL_OR_KEYWORD),
                  *(P(name, P.POSITIONAL_OR_KEYWORD, annotation="Any")
                    for name in operation.arrays)]
    if operation.options:
        parameters += [P("refine", P.KEYWORD_ONLY, default=None, annotation="bool | None"),
                       P("options", P.VAR_KEYWORD, annotation="Any")]
    signature = inspect.Signature(parameters, return_annotation="Call")

    def build(*args: Any, **kwargs: Any) -> Call:
        given = signature.bind(*args, **kwargs).arguments
        arrays = {name: np.asarray(given[name]) for name in operation.arrays}
        params = ({"options": _options(given.get("refine"), given.get("options", {}))}
                  if operation.options else {})
        return Call(operation.name, arrays, params)

    build.__name__ = f"{operation.method}_call"
    build.__qualname__ = f"Client.{build.__name__}"
    build.__doc__ = operation.summary
    build.__signature__ = signature  # type: ignore[attr-defined]
    return build


def _operation_method(operation: Operation) -> Callable[..., Any]:
    """``Client.<method>``: the request of ``<method>_call`` run synchronously, or as a job
    with ``progress`` (:meth:`Client.run`); its docstring and signature (plus ``progress``)."""
    build = getattr(Client, f"{operation.method}_call")

    def method(self: Client, *args: Any, progress: Progress | None = None,
               **kwargs: Any) -> Any:
        return self.run(build(self, *args, **kwargs), progress)

    signature = inspect.signature(build)
    parameters = list(signature.parameters.values())
    at = len(parameters) - (parameters[-1].kind is inspect.Parameter.VAR_KEYWORD)
    parameters.insert(at, inspect.Parameter("progress", inspect.Parameter.KEYWORD_ONLY,
                                            default=None, annotation="Progress | None"))
    method.__name__, method.__qualname__ = operation.method, f"Client.{operation.method}"
    method.__doc__ = build.__doc__
    method.__signature__ = signature.replace(  # type: ignore[attr-defined]
        parameters=parameters, return_annotation=operation.result)
    return method


for _operation in OPERATIONS.values():
    if _operation.arrays:
        setattr(Client, f"{_operation.method}_call", table_call(_operation))
    setattr(Client, _operation.method, _operation_method(_operation))


def _t_values(t: float | Sequence[float]) -> float | list[float]:
    """A blend's ``t``: one number or a list of them (JSON-ready)."""
    return float(t) if np.ndim(t) == 0 else [float(x) for x in np.ravel(t)]


def _blend_params(count: int, weights: Any, t: float | Sequence[float] | None,
                  options: dict[str, Any]) -> dict[str, Any]:
    """The parameters of ``POST /v1/blend`` for ``count`` shapes: rows of ``weights``
    (T, count) or ``t`` values, and the options."""
    params: dict[str, Any] = {"options": options}
    if weights is not None:
        rows = np.asarray(weights, dtype=np.float64)
        params["weights"] = (rows.reshape(-1, count) if count else np.atleast_2d(rows)).tolist()
    if t is not None:
        params["t"] = _t_values(t)
    return params
