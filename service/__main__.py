"""``python -m service``: serve the app with uvicorn on FFS_HOST:FFS_PORT."""

from __future__ import annotations


def main() -> None:
    import uvicorn

    from service.http.server import PROTOCOL
    from service.logs import LOG_CONFIG
    from service.settings import Settings

    settings = Settings()
    # Session WebSockets carry float32 vertex buffers: deflate costs more than it saves.
    # The protocol adds a deadline for request headers (FFS_HEADER_TIMEOUT). After SIGTERM,
    # open requests get FFS_SHUTDOWN_TIMEOUT s, then the lifespan ends every child process.
    uvicorn.run("service.app:app", host=settings.host, port=settings.port,
                log_level=settings.log_level, ws_per_message_deflate=False, http=PROTOCOL,
                timeout_graceful_shutdown=settings.shutdown_timeout, log_config=LOG_CONFIG)


if __name__ == "__main__":
    main()
