"""A job's ``callback_url`` at the HTTP edge: checked at submission (422 naming
``callback_url``), then followed until the job finishes and delivered, signed with the
caller's key's webhook secret (:mod:`service.access.webhooks`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from starlette.requests import HTTPConnection

from service.access.webhooks import CallbackRefusedError, CallbackTarget, check_callback_url
from service.api.problems import ProblemError, element_error
from service.backends.contracts import JobService
from service.http.auth import Caller
from service.http.dependencies import services
from service.worker.output import json_bytes


def _refuse(reason: str) -> ProblemError:
    return ProblemError("validation-error", f"callback_url: {reason}",
                        errors=[element_error("callback_url", reason)])


def callback_target(connection: HTTPConnection, url: str | None, caller: Caller
                    ) -> CallbackTarget | None:
    """The checked target of a job's ``callback_url`` (None without one).

    Raises:
        ProblemError: 422 ``validation-error`` naming ``callback_url``: a host outside
            FFS_WEBHOOK_HOSTS, a private address not listed, not http(s), or a service
            without API keys (there is no secret to sign with).
    """
    if url is None:
        return None
    access = services(connection).access
    if access is None or caller.key is None:
        raise _refuse("webhooks need API keys (each key's webhook secret signs them); "
                      "this service has none")
    if not caller.key.webhook_secret:
        raise _refuse(f"the key {caller.name!r} has no webhook secret in the keys file")
    try:
        return check_callback_url(url, access.webhooks.policy)
    except CallbackRefusedError as exc:
        raise _refuse(str(exc)) from None


def follow_job(connection: HTTPConnection, jobs: JobService, job_id: str,
               target: CallbackTarget, caller: Caller,
               document: Callable[[Any], Any]) -> None:
    """Deliver job ``job_id``'s status document (``document(job)``, a response model) to
    ``target`` once it finishes."""
    access = services(connection).access
    assert access is not None and caller.key is not None

    async def lookup() -> tuple[str, bytes] | None:
        job = await jobs.get(job_id)
        if job is None:
            raise LookupError(job_id)
        if not job.done:
            return None
        return job.status, json_bytes(document(job).model_dump(exclude_unset=True))

    access.webhooks.schedule(job_id, target, caller.key.webhook_secret, lookup)
