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
    """Schedule ``fn(*args)`` on ``loop`` from a reader thread.

    Args:
        loop: the event loop, or None.
        fn: the callback.
        *args: its arguments.

    Returns:
        Whether it was scheduled (False once the loop is gone or closed).
    """
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
    """Await ``sweep()`` periodically; cancel the task to stop it.

    A failing sweep is logged and the loop goes on.

    Args:
        ttl: the lifetime the sweep enforces; it runs every ``ttl / 4`` seconds, between
            0.05 s and ``ceiling``.
        sweep: the coroutine function to await.
        what: its name in the log.
        ceiling: the longest interval (seconds).
        active: the sweep is skipped while this returns False.
    """
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
    """Resolve ``future`` unless it is done already.

    Args:
        future: the future.
        result: its result, when ``exc`` is None.
        exc: its exception.
    """
    if future.done():
        return
    if exc is not None:
        future.set_exception(exc)
    else:
        future.set_result(result)


def _consume(future: asyncio.Future[Any]) -> None:
    """Mark a future's exception as retrieved (done callback of :func:`new_future`)."""
    if not future.cancelled():
        future.exception()
