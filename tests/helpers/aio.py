"""Running a coroutine from a test, whatever the main thread's event loop is doing.

The browser tests' session-wide Playwright (sync API) keeps an event loop running in the
main thread for as long as the browser is open, and ``asyncio.run`` refuses to start inside
a running loop; so a test that runs after them in the same process would fail for its
order, not for what it checks. :func:`run` gives the coroutine a fresh loop in a thread of
its own.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
from collections.abc import Coroutine
from typing import Any, TypeVar

T = TypeVar("T")


def run(coroutine: Coroutine[Any, Any, T]) -> T:
    """``asyncio.run(coroutine)`` in a new thread; its result, or its exception raised here.

    Example:
        >>> async def answer() -> int:
        ...     return 42
        >>> run(answer())
        42
    """
    with concurrent.futures.ThreadPoolExecutor(max_workers=1) as pool:
        return pool.submit(asyncio.run, coroutine).result()
