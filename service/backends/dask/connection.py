"""A replica's connection to the Dask scheduler: :class:`DaskConnection`."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from typing import Any

from service.backends.dask.registry import registry_call, registry_call_async
from service.backends.errors import ExecutorClosedError

logger = logging.getLogger("service.backends.dask")


class DaskConnection:
    """One async ``distributed.Client`` per app, connected in the background with retries;
    worker counts refreshed every second for readiness and capacity."""

    def __init__(self, address: str, connect_timeout: float = 30.0) -> None:
        self.address = address
        self.connect_timeout = connect_timeout
        self.client: Any = None
        self.workers = 0
        self.threads = 0
        self.connected: asyncio.Event | None = None  # made in start (needs the loop)
        self._task: asyncio.Task[None] | None = None
        self._closing = False
        self.last_error: str | None = None

    async def start(self) -> None:
        self.connected = asyncio.Event()
        self._task = asyncio.create_task(self._run())

    async def _connect(self) -> None:
        from distributed import Client

        while not self._closing:
            try:
                self.client = await Client(self.address, asynchronous=True,
                                           timeout=self.connect_timeout,
                                           name="ffs-service", set_as_default=False)
                await self.client.run_on_scheduler(registry_call, "job_counts", ())
                self.last_error = None
                logger.info("connected to the Dask scheduler at %s", self.address)
                return
            except Exception as exc:
                self.last_error = f"{type(exc).__name__}: {exc}"
                logger.warning("cannot reach the Dask scheduler at %s (%s); retrying",
                               self.address, self.last_error)
                if self.client is not None:
                    with contextlib.suppress(Exception):
                        await self.client.close()
                    self.client = None
                await asyncio.sleep(1.0)

    async def _run(self) -> None:
        await self._connect()
        assert self.connected is not None
        self.connected.set()
        while not self._closing:
            try:
                nthreads = await asyncio.wait_for(self.client.nthreads(), 10)
                self.workers, self.threads = len(nthreads), int(sum(nthreads.values()))
            except Exception as exc:
                self.workers = self.threads = 0
                self.last_error = f"{type(exc).__name__}: {exc}"
            await asyncio.sleep(1.0)

    async def wait_connected(self, timeout: float) -> Any:
        if self.client is None or self.connected is None:
            if self.connected is None:
                raise ExecutorClosedError("the Dask backend is not running")
            try:
                await asyncio.wait_for(self.connected.wait(), timeout)
            except TimeoutError:
                raise ExecutorClosedError(
                    f"not connected to the Dask scheduler at {self.address} "
                    f"({self.last_error or 'connecting'})") from None
        return self.client

    def connected_now(self) -> bool:
        """A client is connected (the sweepers skip their turn while it is not)."""
        return self.client is not None

    def require(self) -> Any:
        if self.client is None:
            raise ExecutorClosedError(f"not connected to the Dask scheduler at {self.address} "
                                      f"({self.last_error or 'connecting'})")
        return self.client

    async def call(self, op: str, *args: Any) -> Any:
        """Call a :class:`Registry` method in the scheduler."""
        client = self.require()
        try:
            return await asyncio.wait_for(client.run_on_scheduler(registry_call, op, args), 30)
        except (OSError, TimeoutError) as exc:
            raise ExecutorClosedError(f"the Dask scheduler did not answer: {exc}") from None

    async def call_async(self, op: str, *args: Any) -> Any:
        """Call a coroutine method of :class:`Registry` in the scheduler."""
        client = self.require()
        try:
            return await asyncio.wait_for(
                client.run_on_scheduler(registry_call_async, op, args), 60)
        except (OSError, TimeoutError) as exc:
            raise ExecutorClosedError(f"the Dask scheduler did not answer: {exc}") from None

    async def close(self) -> None:
        self._closing = True
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._task
        if self.client is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self.client.close(), 10)
            self.client = None
