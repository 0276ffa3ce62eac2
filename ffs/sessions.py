"""A deformation session of the service (:meth:`ffs.client.Client.session`): one mesh's
factorization kept warm, dragged over a WebSocket (float32 vertices) or, without one, over
HTTP (float64)."""

from __future__ import annotations

import contextlib
import json
from typing import TYPE_CHECKING, Any

import numpy as np

from ffs.errors import (
    GoneError,
    NotFoundError,
    RequestTimeoutError,
    ServiceUnreachableError,
    problem_error,
)

if TYPE_CHECKING:
    from ffs.client import Client


class Session:
    """A deformation session (:meth:`Client.session`); a context manager that closes it.

    Attributes: ``id``, ``info`` (the session document), ``handles`` (the handle vertices
    in the order :meth:`drag` takes their targets), ``transport`` (``"ws"`` or ``"http"``).
    """

    def __init__(self, client: Client, info: dict[str, Any]) -> None:
        self.client = client
        self.info = info
        self.id = str(info["id"])
        self.handles = list(info.get("handles", []))
        self.n_vertices = int(info.get("n_vertices", 0))
        self.links = dict(info.get("links") or {})
        self.transport = "http"
        self._socket: Any = None
        self._closing = contextlib.ExitStack()  # the socket's context (websockets >= 17.1)
        self._seq = 0

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def connect(self) -> None:
        """Open the session's WebSocket (``links.ws``)."""
        from websockets.sync.client import connect

        base = self.client.url.replace("https://", "wss://", 1).replace("http://", "ws://", 1)
        path = self.links.get("ws") or f"/v1/sessions/{self.id}/ws"
        try:
            self._socket = self._closing.enter_context(connect(
                base + path, open_timeout=self.client.timeout, max_size=None,
                compression=None, additional_headers=self.client.auth_headers() or None))
        except Exception as exc:  # handshake refused, proxy without WebSockets...
            raise ServiceUnreachableError(f"cannot open the session's WebSocket: {exc}") from None
        self.transport = "ws"

    def drag(self, handle_positions: Any, handle_rotations: Any = None) -> np.ndarray:
        """The deformed vertices (n, 3) float64 for handle targets (h, 3) and optional
        rotations (g, 3, 3). Over the WebSocket the values are float32 rounded; over HTTP
        they are the solver's float64."""
        positions = np.asarray(handle_positions, dtype=np.float64).reshape(-1, 3)
        rotations = (None if handle_rotations is None else
                     np.asarray(handle_rotations, dtype=np.float64).reshape(-1, 3, 3))
        if self._socket is not None:
            return self._drag_ws(positions, rotations)
        body: dict[str, Any] = {"handle_positions": positions.tolist()}
        if rotations is not None:
            body["handle_rotations"] = rotations.tolist()
        path = self.links.get("solve") or f"/v1/sessions/{self.id}/solve"
        response = self.client._post_json(path, body, headers={"Accept": "application/json"})
        return np.asarray(response.json()["vertices"], dtype=np.float64).reshape(-1, 3)

    def _drag_ws(self, positions: np.ndarray, rotations: np.ndarray | None) -> np.ndarray:
        from websockets.exceptions import ConnectionClosed

        values = [positions.ravel()] + ([] if rotations is None else [rotations.ravel()])
        self._seq += 1
        try:
            self._socket.send(np.concatenate(values).astype("<f4").tobytes())
            while True:
                message = self._socket.recv(timeout=self.client.timeout)
                if isinstance(message, str):
                    doc = json.loads(message)
                    if doc.get("seq") in (None, self._seq):
                        raise problem_error(doc, int(doc.get("status") or 500))
                    continue
                seq, n = np.frombuffer(message, "<u4", count=2).tolist()
                if seq == self._seq:
                    return np.frombuffer(message, "<f4", offset=8, count=3 * n).reshape(
                        n, 3).astype(np.float64)
        except TimeoutError:
            raise RequestTimeoutError(f"no answer to drag {self._seq} within "
                                 f"{self.client.timeout:g} s") from None
        except ConnectionClosed as exc:
            self._socket = None
            self._closing.close()
            status = 404 if exc.rcvd and exc.rcvd.code == 4404 else 410
            raise problem_error({"title": "Session gone", "status": status, "detail":
                                 f"the session's WebSocket closed ({exc})",
                                 "kind": "not-found" if status == 404 else "session-gone"},
                                status) from None

    def state(self) -> dict[str, Any]:
        """The session document now (``expires_in``, ``solves``, ``memory_bytes``...)."""
        self.info = dict(self.client.request("GET", f"/v1/sessions/{self.id}").json())
        return self.info

    def close(self) -> None:
        """Close the WebSocket and delete the session (an expired one is fine)."""
        self._socket = None
        self._closing.close()
        with contextlib.suppress(NotFoundError, GoneError, ServiceUnreachableError):
            self.client.request("DELETE", f"/v1/sessions/{self.id}")
