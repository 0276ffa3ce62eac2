"""Log lines with time and level: ``2026-01-02T12:00:00.123Z INFO service: message``.

:func:`configure_logging` gives the ``service`` loggers (the app, the executor, the jobs,
the workers) a handler on stderr at FFS_LOG_LEVEL, unless the host application configured
them already; :data:`LOG_CONFIG` is the same format for uvicorn's own loggers
(``python -m service`` passes it to uvicorn).
"""

from __future__ import annotations

import logging
import time
from typing import Any

FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


class UTCFormatter(logging.Formatter):
    """ISO 8601 UTC times with milliseconds."""

    converter = time.gmtime

    def formatTime(self, record: logging.LogRecord, datefmt: str | None = None) -> str:  # noqa: N802
        """``2026-01-02T12:00:00.123Z`` (``datefmt`` is ignored)."""
        stamp = time.strftime("%Y-%m-%dT%H:%M:%S", self.converter(record.created))
        return f"{stamp}.{int(record.msecs):03d}Z"


LOG_CONFIG: dict[str, Any] = {
    "version": 1,
    "disable_existing_loggers": False,
    "formatters": {"plain": {"()": UTCFormatter, "format": FORMAT}},
    "handlers": {"stderr": {"class": "logging.StreamHandler", "formatter": "plain",
                            "stream": "ext://sys.stderr"}},
    "loggers": {"uvicorn": {"handlers": ["stderr"], "level": "INFO", "propagate": False},
                "uvicorn.access": {"handlers": ["stderr"], "level": "INFO",
                                   "propagate": False}},
}


STATIC_PREFIXES = ("/static/", "/favicon.ico")
"""Paths of the page's files, left out of the access log unless FFS_ACCESS_LOG_STATIC."""


class StaticFilesFilter(logging.Filter):
    """Drops uvicorn's access-log lines of successful static-file requests (a page load asks
    for dozens of modules); API calls, pages and any answer of 400 or more stay.

    uvicorn logs ``'%s - "%s %s HTTP/%s" %d'`` with ``(client, method, path, version,
    status)`` as the record's arguments.
    """

    def filter(self, record: logging.LogRecord) -> bool:
        """False for a static file answered below 400."""
        args = record.args
        if not isinstance(args, tuple) or len(args) < 5:
            return True
        path, status = str(args[2]), args[4]
        return not (path.startswith(STATIC_PREFIXES) and isinstance(status, int)
                    and status < 400)


def configure_access_log(static: bool) -> None:
    """Leave static files out of uvicorn's access log (:class:`StaticFilesFilter`), or put
    them back (``static``: FFS_ACCESS_LOG_STATIC)."""
    access = logging.getLogger("uvicorn.access")
    for old in [f for f in access.filters if isinstance(f, StaticFilesFilter)]:
        access.removeFilter(old)
    if not static:
        access.addFilter(StaticFilesFilter())


def configure_logging(level: str) -> None:
    """Give the ``service`` logger a timed, levelled handler on stderr (once).

    Args:
        level: a logging level name (``FFS_LOG_LEVEL``), any case.
    """
    logger = logging.getLogger("service")
    logger.setLevel(level.upper())
    if not logger.handlers:
        handler = logging.StreamHandler()
        handler.setFormatter(UTCFormatter(FORMAT))
        logger.addHandler(handler)
        logger.propagate = False
