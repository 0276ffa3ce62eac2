"""``python -m service``: serve the app with uvicorn on FFS_HOST:FFS_PORT."""

from __future__ import annotations

import signal
from types import FrameType
from typing import NoReturn


def stop_on_sigterm(signum: int, frame: FrameType | None) -> NoReturn:
    """After uvicorn's graceful shutdown it raises the SIGTERM it caught again; this handler
    turns that into the interpreter's own exit (status 0), so exit handlers run: among them
    multiprocessing's, which removes the forkserver's socket folder (``$TMPDIR/pymp-*``).
    A death by the signal itself would leave one such folder per start of the service."""
    raise SystemExit(0)


def main() -> None:
    import uvicorn

    from service.http.server import PROTOCOL
    from service.logs import LOG_CONFIG
    from service.settings import Settings

    settings = Settings()
    signal.signal(signal.SIGTERM, stop_on_sigterm)
    # Session WebSockets carry float32 vertex buffers: deflate costs more than it saves.
    # The protocol adds a deadline for request headers (FFS_HEADER_TIMEOUT). After SIGTERM,
    # open requests get FFS_SHUTDOWN_TIMEOUT s, then the lifespan ends every child process,
    # and the process exits with status 0 (stop_on_sigterm).
    uvicorn.run("service.app:app", host=settings.host, port=settings.port,
                log_level=settings.log_level, ws_per_message_deflate=False, http=PROTOCOL,
                timeout_graceful_shutdown=settings.shutdown_timeout, log_config=LOG_CONFIG)


if __name__ == "__main__":
    main()
