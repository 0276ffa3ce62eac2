"""Helpers shared by the service tests: request bodies, alignment, metrics, problem
assertions, task requests."""

from __future__ import annotations

from typing import Any

import httpx
import numpy as np


def mesh_json(V: np.ndarray, F: np.ndarray) -> dict[str, Any]:
    return {"vertices": V.tolist(), "faces": F.tolist()}


def forms_json(V: np.ndarray, F: np.ndarray) -> dict[str, Any]:
    """The four arrays of a (manifold) mesh's forms, without the placement (issue 40)."""
    import solver

    forms = solver.fundamental_forms(V, F).to_dict()
    return {name: forms[name] for name in ("faces", "edges", "lengths", "angles")}


def rigid_error(A: np.ndarray, B: np.ndarray) -> float:
    """max |R A + t - B| after the best rigid alignment of A onto B (Kabsch)."""
    from solver import rigid_alignment

    return rigid_alignment(A, B).residual_max


def metric_value(text: str, name: str, **labels: str) -> float:
    """Sum of the Prometheus samples of ``name`` whose labels include ``labels``."""
    import re

    total = 0.0
    for line in text.splitlines():
        match = re.match(r"^(\w+)(\{.*\})? ([0-9.e+-]+)$", line)
        if not match or match.group(1) != name:
            continue
        found = dict(re.findall(r'(\w+)="([^"]*)"', match.group(2) or ""))
        if all(found.get(k) == v for k, v in labels.items()):
            total += float(match.group(3))
    return total


def problem(response: httpx.Response, status: int, kind: str) -> dict[str, Any]:
    """Assert an RFC 9457 problem response of ``status``/``kind``; return the document."""
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("application/problem+json")
    doc = response.json()
    assert doc["type"] == f"/problems/{kind}", doc
    assert doc["status"] == status and doc["kind"] == kind
    assert isinstance(doc["title"], str) and isinstance(doc["detail"], str) and doc["detail"]
    assert isinstance(doc["errors"], list)
    return doc


def debug_task(task: str, operation: str = "forms", **params: Any) -> Any:
    """A test-only task request (``debug.sleep``, ``debug.crash``, ``debug.raise``) that
    reports ``operation``'s stages; ``params`` are its arguments (``seconds``, ...)."""
    from service.api.task import TaskRequest

    return TaskRequest(operation, None, params, task=task)


def forms_task(V: np.ndarray, F: np.ndarray) -> Any:
    """A decoded ``forms`` task request of a mesh (what a worker runs)."""
    from service.api.task import Limits, MeshArrays, TaskRequest

    return TaskRequest("forms", MeshArrays(V, F), {}, Limits(10**6, 10**6))
