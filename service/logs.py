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
