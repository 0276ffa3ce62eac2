"""Service settings, read from environment variables (prefix ``FFS_``) by pydantic-settings.

Every field below is documented in ``docs/service.md`` (a test checks that the table there
lists each one). Lists such as ``FFS_CORS_ORIGINS`` are given as JSON (``'["https://a.b"]'``)
or comma-separated (``https://a.b,https://c.d``).

Two settings also answer to the unprefixed names of the scale-out spec: ``SOLVER_EXECUTOR``
(= ``FFS_EXECUTOR``) and ``DASK_SCHEDULER_ADDRESS`` (= ``FFS_DASK_SCHEDULER_ADDRESS``); the
prefixed name wins when both are set.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import AliasChoices, Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from solver.options import Backend

ENV_PREFIX = "FFS_"


def seconds(default: float, description: str, **bounds: float) -> Any:
    """A setting in seconds: a positive number with a default and a description."""
    return Field(default, gt=0, description=description, **bounds)


def _default_workers() -> int:
    return max(1, os.cpu_count() or 1)


def _default_request_memory(data: dict[str, Any]) -> int:
    """FFS_MAX_REQUEST_MEMORY's default: one worker's share of this machine, or with Dask
    the memory of a cluster worker."""
    from service.backends.admission import DASK_REQUEST_MEMORY, request_memory_budget
    from service.memory import machine_memory

    if data.get("executor") == "dask":
        return DASK_REQUEST_MEMORY
    return request_memory_budget(machine_memory(), data.get("max_session_memory", 0),
                                 data.get("workers") or _default_workers())


def _default_max_faces(data: dict[str, Any]) -> int:
    """FFS_MAX_FACES's default: what the lightest operations fit in a request's memory."""
    from service.backends.admission import LIGHT

    return max(1, LIGHT.faces_within(data.get("max_request_memory", 64 * 1024**2)))


def _default_body_bytes(data: dict[str, Any]) -> int:
    """FFS_MAX_BODY_BYTES's default: a JSON body of FFS_MAX_FACES faces, at least 64 MiB."""
    from service.backends.admission import BODY_BYTES_PER_FACE

    return max(64 * 1024**2, BODY_BYTES_PER_FACE * data.get("max_faces", 0))


class Settings(BaseSettings):
    """Runtime configuration of the HTTP service (see the module docstring)."""

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, extra="ignore",
                                      validate_default=True, populate_by_name=True)

    host: str = Field("127.0.0.1", description="Bind address of `python -m service`.")
    port: int = Field(8000, ge=0, le=65535, description="Port of `python -m service`.")
    log_level: Literal["critical", "error", "warning", "info", "debug"] = Field(
        "info", description="Log level of `python -m service`.")
    access_log_static: bool = Field(
        False, description="Also log successful requests for the page's static files "
        "(`/static/...`, `/favicon.ico`); by default uvicorn's access log keeps only API "
        "calls, pages and failed requests.")

    executor: Literal["local", "process", "dask"] = Field(
        "local", validation_alias=AliasChoices("FFS_EXECUTOR", "SOLVER_EXECUTOR"),
        description="Worker backend: `local` (a local process pool; `process` is a synonym) "
                    "or `dask` (a Dask distributed cluster at FFS_DASK_SCHEDULER_ADDRESS).")
    dask_scheduler_address: str | None = Field(
        None, validation_alias=AliasChoices("FFS_DASK_SCHEDULER_ADDRESS",
                                            "DASK_SCHEDULER_ADDRESS"),
        description="Scheduler of the Dask cluster, e.g. `tcp://scheduler:8786` "
                    "(required with FFS_EXECUTOR=dask).")
    dask_connect_timeout: float = seconds(
        30.0, "Seconds to wait for the Dask scheduler at each connection "
                                "attempt; the service retries until it answers.")
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
    request_timeout: float = seconds(
        120.0, "Seconds a synchronous request waits for its result (504).")
    job_timeout: float = seconds(
        1800.0, "Seconds a job may run before it is failed.")
    job_ttl: float = seconds(
        3600.0, "Seconds a finished job and its result are kept.")
    max_jobs: int = Field(
        256, ge=1, description="Jobs kept at once; when full, the oldest finished ones give "
                               "way, and only a store full of unfinished jobs answers 503.")
    max_client_jobs: int = Field(
        16, ge=1, description="Unfinished (queued or running) jobs one client address may "
                              "have at once; beyond it: 429.")

    session_ttl: float = seconds(
        600.0, "Seconds a deformation session may stay idle before it is "
                                 "closed (its memory freed).")
    max_sessions: int = Field(
        8, ge=0, le=10_000, description="Live deformation sessions at once; when full, "
                                        "sessions idle for FFS_SESSION_GIVE_WAY seconds give "
                                        "way (the longest idle first), else 429.")
    max_client_sessions: int = Field(
        4, ge=1, le=10_000, description="Sessions one client address may have open at once; "
                                        "beyond it: 429.")
    session_give_way: float = Field(
        60.0, ge=0, description="Seconds without a drag after which a session is closed to "
                                "make room for a new one when FFS_MAX_SESSIONS (or "
                                "FFS_MAX_SESSION_MEMORY) is reached (410 afterwards).")
    max_session_memory: int = Field(
        4 * 1024**3, ge=0,
        description="Bytes all live sessions may hold together (measured per session after "
                    "its factorization, estimated before); beyond it: 503.")
    session_threads: int | None = Field(
        None, ge=1, le=256,
        description="BLAS/MKL threads of each local session process (default: the number "
                    "of cores: a drag is latency-bound, and sessions rarely drag at once).")
    session_solve_timeout: float = seconds(
        30.0, "Seconds one session solve may take; then 504 and the "
                                "session is closed (410 afterwards). Also the most a "
                                "progressive session refines one drag (`options.max_seconds` "
                                "overrides it).")
    session_refine_slice: float = seconds(
        0.05, "Seconds of one slice of a progressive session's refinement (a slice that "
              "ends before its first iteration doubles the next): a new drag waits at most "
              "one slice.", le=60)

    header_timeout: float = seconds(
        10.0, "Seconds a client may take to send a request's headers; then "
                                "408 and the connection is closed (`python -m service`, or "
                                "uvicorn with `--http service.http.server:HeaderTimeoutProtocol`).")
    body_timeout: float = seconds(
        60.0, "Seconds a client may take to send a request body; then 408 "
                                "and the connection is closed (slow or stalled uploads).")
    max_blend_steps: int = Field(
        1024, ge=1, le=100_000,
        description="Most rows of one blend or interpolate request (`weights` rows or `t` "
                    "values; 422 beyond), checked before any mesh is read. What a request "
                    "may ask for is bounded by size: FFS_MAX_BLEND_VERTICES.")
    max_blend_vertices: int = Field(
        4_000_000, ge=1,
        description="Most rows x vertices of one blend or interpolate request (413 "
                    "blend-too-large beyond): the answer holds rows x vertices x 3 float64 "
                    "(96 MB at the default) and each row is a solve of the whole mesh, so "
                    "100 rows of a 40,000-vertex mesh pass and 1,000 of it do not.")
    send_timeout: float = seconds(
        30.0, "Seconds a client may leave a response unread (the send "
                                "buffer full) before the connection is aborted and the "
                                "buffered bytes freed.")
    shutdown_timeout: float = Field(
        5.0, ge=0, description="Seconds `python -m service` waits, after SIGTERM, for open "
                               "requests to finish before it cancels them and stops.")
    max_request_memory: int = Field(
        default_factory=lambda data: _default_request_memory(data), ge=64 * 1024**2,
        description="Bytes one request may use in its worker (default: 80 % of the "
                    "machine's memory less FFS_MAX_SESSION_MEMORY (at most half of it), "
                    "divided by FFS_WORKERS, at least 1 GiB; 4 GiB with FFS_EXECUTOR=dask); "
                    "each operation's largest mesh follows from its predicted peak memory "
                    "(413 beyond).")
    max_faces: int = Field(
        default_factory=lambda data: _default_max_faces(data), ge=1,
        description="Largest face count of a mesh (413 beyond; default: the most faces an "
                    "operation that factorizes nothing fits in FFS_MAX_REQUEST_MEMORY).")
    max_vertices: int = Field(
        default_factory=lambda data: max(3, 3 * data.get("max_faces", 500_000) // 5), ge=3,
        description="Largest vertex count of a mesh (413 beyond; default: 0.6 x "
                    "FFS_MAX_FACES).")
    max_body_bytes: int = Field(
        default_factory=lambda data: _default_body_bytes(data), ge=1024,
        description="Largest request body (413 beyond; default: room for a JSON body of "
                    "FFS_MAX_FACES faces, at least 64 MiB).")

    solver_backend: Backend = Field(
        "auto", description="Default sparse factorization backend (`auto`, `pardiso`, "
        "`cholespy`, `superlu`): the solver's `backend` (solver.options.SolveOptions) of a "
        "request whose `options.solver` is null.")
    cors_origins: Annotated[list[str], NoDecode] = Field(
        default_factory=list,
        description="Origins allowed by CORS (`*` for any); empty disables CORS.")
    gzip_minimum_size: int = Field(
        65536, ge=0, description="Responses at least this large are gzip-compressed.")
    gzip_level: int = Field(1, ge=1, le=9, description="gzip compression level (1 fastest).")

    # Who may use the service (docs/deployment.md#api-keys): off unless keys are given.
    api_keys: SecretStr | None = Field(
        None,
        description="API keys as a JSON object name -> key (`{\"alice\": \"...\"}`); "
                    "with keys (here or in FFS_API_KEYS_FILE) every request but the health "
                    "checks, the page and the docs needs `Authorization: Bearer <key>`.")
    admin_keys: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="Names of FFS_API_KEYS (or of the keys file) with "
                                          "the `admin` role (/metrics, every job and "
                                          "session); comma-separated or JSON.")
    api_keys_file: Path | None = Field(
        None, description="JSON file of hashed keys with a name, role and limits each "
                          "(`python -m service.access add NAME` creates a key in it).")
    key_requests_per_minute: int = Field(
        600, ge=1, description="Default requests per minute of one key (429 beyond).")
    key_concurrent_jobs: int = Field(
        16, ge=1, description="Default jobs one key may have queued or running (429 "
                              "beyond); replaces FFS_MAX_CLIENT_JOBS when keys are on.")
    key_concurrent_sessions: int = Field(
        4, ge=1, description="Default sessions one key may have open (429 beyond); "
                             "replaces FFS_MAX_CLIENT_SESSIONS when keys are on.")
    key_max_faces: int | None = Field(
        None, ge=1, description="Default largest face count of one key's meshes (413 "
                                "beyond; default FFS_MAX_FACES).")
    webhook_hosts: Annotated[list[str], NoDecode] = Field(
        default_factory=list,
        description="Hosts a job's `callback_url` may name (`host` or `host:port`; "
                    "`*.example.com` for its subdomains); empty: no webhooks. Loopback "
                    "and private addresses only when listed.")
    webhook_attempts: int = Field(
        5, ge=1, le=20, description="Deliveries of one webhook before it is given up.")
    webhook_backoff: float = seconds(
        1.0, "Seconds before the second delivery of a webhook; doubled each time.", le=600)
    webhook_timeout: float = seconds(
        10.0, "Seconds one webhook delivery may take.", le=120)

    @field_validator("cors_origins", "admin_keys", "webhook_hosts", mode="before")
    @classmethod
    def _split_origins(cls, value: object) -> object:
        if isinstance(value, str):
            text = value.strip()
            if text.startswith("["):
                import json

                return json.loads(text)
            return [part.strip() for part in text.split(",") if part.strip()]
        return value

    @field_validator("api_keys", mode="before")
    @classmethod
    def _keys_as_json(cls, value: object) -> object:
        """A mapping given in Python is kept as its JSON text: the keys stay a secret
        (parsed by :meth:`api_key_mapping`, whose errors never echo them)."""
        if isinstance(value, dict):
            import json

            return json.dumps(value)
        return value

    def api_key_mapping(self) -> dict[str, str]:
        """FFS_API_KEYS as name -> key (empty when unset).

        Raises:
            ValueError: not a JSON object of strings (the message quotes no key).
        """
        text = self.api_keys.get_secret_value().strip() if self.api_keys else ""
        if not text:
            return {}
        import json

        try:
            found = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"FFS_API_KEYS is not a JSON object of name -> key (line "
                             f"{exc.lineno}, column {exc.colno})") from None
        if not isinstance(found, dict) or not all(
                isinstance(k, str) and isinstance(v, str) for k, v in found.items()):
            raise ValueError('FFS_API_KEYS must be a JSON object of name -> key strings, '
                             'e.g. {"alice": "..."}')
        return found

    @field_validator("executor", mode="after")
    @classmethod
    def _local_synonym(cls, value: str) -> str:
        return "local" if value == "process" else value

    @field_validator("dask_scheduler_address", mode="before")
    @classmethod
    def _blank_is_none(cls, value: object) -> object:
        return None if isinstance(value, str) and not value.strip() else value

    @model_validator(mode="after")
    def _dask_needs_an_address(self) -> Settings:
        if self.executor == "dask" and not self.dask_scheduler_address:
            raise ValueError("FFS_EXECUTOR=dask needs FFS_DASK_SCHEDULER_ADDRESS "
                             "(or DASK_SCHEDULER_ADDRESS), e.g. tcp://scheduler:8786")
        return self

    @property
    def effective_session_threads(self) -> int:
        """BLAS threads of a local session process: the setting, or the number of cores."""
        return self.session_threads or max(1, os.cpu_count() or 1)

    @property
    def effective_threads(self) -> int:
        """BLAS threads per worker: the setting, or cores / workers."""
        if self.threads_per_worker is not None:
            return self.threads_per_worker
        return max(1, (os.cpu_count() or 1) // self.workers)
