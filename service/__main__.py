"""``python -m service``: serve the app with uvicorn on FFS_HOST:FFS_PORT."""

from __future__ import annotations


def main() -> None:
    import uvicorn

    from service.settings import Settings

    settings = Settings()
    uvicorn.run("service.app:app", host=settings.host, port=settings.port,
                log_level=settings.log_level)


if __name__ == "__main__":
    main()
