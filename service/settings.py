"""Service settings, read from environment variables (prefix ``FFS_``) by pydantic-settings.

Every field below is documented in ``docs/service.md`` (a test checks that the table there
lists each one). Lists such as ``FFS_CORS_ORIGINS`` are given as JSON (``'["https://a.b"]'``)
or comma-separated (``https://a.b,https://c.d``).
"""

from __future__ import annotations

import os
from typing import Annotated, Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from solver.linalg import BACKENDS

ENV_PREFIX = "FFS_"


def _default_workers() -> int:
    return max(1, os.cpu_count() or 1)


class Settings(BaseSettings):
    """Runtime configuration of the HTTP service (see the module docstring)."""

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, extra="ignore",
                                      validate_default=True)

    host: str = Field("127.0.0.1", description="Bind address of `python -m service`.")
    port: int = Field(8000, ge=0, le=65535, description="Port of `python -m service`.")
    log_level: Literal["critical", "error", "warning", "info", "debug"] = Field(
        "info", description="Log level of `python -m service`.")

    executor: Literal["process"] = Field(
        "process", description="Worker backend: `process` (a local process pool).")
    workers: int = Field(default_factory=_default_workers, ge=1, le=256,
                         description="Worker processes (default: the number of cores).")
    threads_per_worker: int | None = Field(
        None, ge=1, le=256,
        description="BLAS/MKL threads per worker (default: cores / workers, at least 1).")
    start_method: Literal["forkserver", "spawn"] = Field(
        "forkserver", description="How worker processes are started.")
    queue_size: int = Field(
        32, ge=0, le=100_000,
        description="Requests and jobs that may wait for a free worker; beyond it: 503.")
    request_timeout: float = Field(
        120.0, gt=0, description="Seconds a synchronous request waits for its result (504).")
    job_timeout: float = Field(
        1800.0, gt=0, description="Seconds a job may run before it is failed.")
    job_ttl: float = Field(
        3600.0, gt=0, description="Seconds a finished job and its result are kept.")
    max_jobs: int = Field(
        256, ge=1, description="Jobs kept at once (all states); beyond it: 503.")

    max_body_bytes: int = Field(
        64 * 1024 * 1024, ge=1024, description="Largest request body (413 beyond).")
    max_vertices: int = Field(
        250_000, ge=3, description="Largest vertex count of a mesh (413 beyond).")
    max_faces: int = Field(
        500_000, ge=1, description="Largest face count of a mesh (413 beyond).")

    solver_backend: Literal["auto", *sorted(BACKENDS)] = Field(  # type: ignore[valid-type]
        "auto", description="Default sparse backend (`auto`, `pardiso`, `cholespy`, `superlu`).")
    cors_origins: Annotated[list[str], NoDecode] = Field(
        default_factory=list,
        description="Origins allowed by CORS (`*` for any); empty disables CORS.")
    gzip_minimum_size: int = Field(
        65536, ge=0, description="Responses at least this large are gzip-compressed.")
    gzip_level: int = Field(1, ge=1, le=9, description="gzip compression level (1 fastest).")

    @field_validator("cors_origins", mode="before")
    @classmethod
    def _split_origins(cls, value: object) -> object:
        if isinstance(value, str):
            text = value.strip()
            if text.startswith("["):
                import json

                return json.loads(text)
            return [part.strip() for part in text.split(",") if part.strip()]
        return value

    @property
    def effective_threads(self) -> int:
        """BLAS threads per worker: the setting, or cores / workers."""
        if self.threads_per_worker is not None:
            return self.threads_per_worker
        return max(1, (os.cpu_count() or 1) // self.workers)
