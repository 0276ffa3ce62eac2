"""``GET /v1/me``: who the service takes the caller for (its key's name, role and quotas),
so that a client can check its key before it sends work (the page asks for a key here)."""

from __future__ import annotations

from dataclasses import asdict

from fastapi import APIRouter
from starlette.responses import Response

from service.api.documents import Caller as CallerDocument
from service.http.auth import CallerDep
from service.http.dependencies import ServicesDep, SettingsDep
from service.http.payloads import size_limits
from service.http.routes import API_PREFIX, model_response

router = APIRouter(prefix=API_PREFIX, tags=["health"])


@router.get("/me", operation_id="get_caller", response_model=CallerDocument,
            summary="The caller",
            description="Whether the service has API keys and, with keys, the name, role and "
                        "quotas of the caller's key (401 without a known key); and how "
                        "large a request may be (`size_limits`: faces, vertices, body bytes, "
                        "memory, and the faces each operation takes).")
async def me(caller: CallerDep, services: ServicesDep, settings: SettingsDep) -> Response:
    keys = services.access is not None and services.access.enabled
    sizes = size_limits(settings)
    if caller.key is None:
        return model_response(CallerDocument(keys=keys, size_limits=sizes))
    return model_response(CallerDocument(keys=keys, name=caller.key.name, role=caller.key.role,
                                         limits=asdict(caller.key.limits), size_limits=sizes))
