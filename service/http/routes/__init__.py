"""HTTP routes, one module per area: operations, jobs, sessions, health, web, docs.

The operations, jobs and sessions routers share the API's version prefix
(:data:`API_PREFIX`); links and Location headers are the paths of their routes
(:func:`path_to`), and documents with a response model are answered as that model
(:func:`model_response`).
"""

from __future__ import annotations

from collections.abc import Mapping

from fastapi import APIRouter
from pydantic import BaseModel
from starlette.responses import Response

from service.worker.output import json_bytes

API_PREFIX = "/v1"
"""The version prefix of the operations', jobs' and sessions' paths."""


def path_to(router: APIRouter, name: str, **params: str | int) -> str:
    """The path of one of a router's routes.

    Args:
        router: The router that declares the route (its prefix is part of the path).
        name: The route's name (its endpoint function's name, ``"get_job"``).
        **params: The path parameters (``job_id="..."``).

    Returns:
        The path, e.g. ``/v1/jobs/6f1c...``.
    """
    return str(router.url_path_for(name, **params))


def model_response(document: BaseModel, status_code: int = 200,
                   headers: Mapping[str, str] | None = None) -> Response:
    """A JSON response of a response model.

    Args:
        document: The document, holding the members it was given (none is added).
        status_code: The HTTP status.
        headers: Further response headers.

    Returns:
        An ``application/json`` response of the members set in ``document``.
    """
    return Response(json_bytes(document.model_dump(exclude_unset=True)),
                    status_code=status_code, media_type="application/json",
                    headers=dict(headers or {}))
