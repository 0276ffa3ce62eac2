"""Event-loop plumbing shared by the backends: reader threads posting to the loop, one
periodic sweep, futures whose exception nobody may read."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from typing import Any

logger = logging.getLogger("service.backends")


def post_threadsafe(loop: asyncio.AbstractEventLoop | None, fn: Callable[..., None],
                    *args: Any) -> bool:
    """Schedule ``fn(*args)`` on ``loop`` from a reader thread; False once the loop is gone."""
    if loop is None or loop.is_closed():
        return False
    try:
        loop.call_soon_threadsafe(fn, *args)
    except RuntimeError:
        return False
    return True


async def sweep_forever(ttl: float, sweep: Callable[[], Awaitable[Any]], what: str, *,
                        ceiling: float = 5.0, active: Callable[[], bool] = lambda: True
                        ) -> None:
    """Await ``sweep()`` every ttl / 4 (between 0.05 s and ``ceiling``) while ``active()``;
    log a failure, never stop (cancel the task to stop it)."""
    interval = max(0.05, min(ceiling, ttl / 4))
    while True:
        await asyncio.sleep(interval)
        if not active():
            continue
        try:
            await sweep()
        except Exception:
            logger.exception("%s failed", what)


def new_future() -> asyncio.Future[Any]:
    """A future on the running loop whose exception counts as retrieved (a caller may stop
    waiting for it, e.g. a cancelled job or a timed-out drag)."""
    future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
    future.add_done_callback(_consume)
    return future


def settle(future: asyncio.Future[Any], *, result: Any = None,
           exc: BaseException | None = None) -> None:
    """Resolve ``future`` with ``exc`` or ``result`` unless it is done already."""
    if future.done():
        return
    if exc is not None:
        future.set_exception(exc)
    else:
        future.set_result(result)


def _consume(future: asyncio.Future[Any]) -> None:
    if not future.cancelled():
        future.exception()
