"""Compute backends: where tasks run, jobs wait and sessions stay warm.

The contract is :mod:`service.backends.contracts` (``Executor``, ``JobService``,
``SessionBackend``, bundled as a ``Backend``); failures are the domain errors of
:mod:`service.backends.errors`. Two implementations sit side by side:
:mod:`service.backends.local` (processes of this service) and :mod:`service.backends.dask`
(a Dask cluster shared by every replica). :func:`make_backend` picks one by
``FFS_EXECUTOR``; shared pieces: job records (:mod:`~service.backends.jobs`), admission
(:mod:`~service.backends.admission`), worker processes (:mod:`~service.backends.processes`)
and event-loop plumbing (:mod:`~service.backends.loops`).
"""

from __future__ import annotations

from collections.abc import Callable

from service.backends.contracts import Backend, JobPolicy, ResultCallback, SessionPolicy
from service.settings import Settings


def job_policy(settings: Settings) -> JobPolicy:
    """The job limits and lifetimes of ``settings`` (``FFS_JOB_*``, ``FFS_MAX_*JOBS``)."""
    return JobPolicy(settings.job_ttl, settings.job_timeout, settings.max_jobs,
                     settings.max_client_jobs)


def session_policy(settings: Settings, threads: int) -> SessionPolicy:
    """The session limits of ``settings``, each session process using ``threads`` threads."""
    return SessionPolicy(settings.session_ttl, settings.max_sessions,
                         settings.max_session_memory, threads, settings.session_solve_timeout,
                         settings.request_timeout, settings.session_refine_slice,
                         settings.max_client_sessions, settings.session_give_way)


def _local(settings: Settings, on_result: ResultCallback | None) -> Backend:
    """The local backend: a process pool, in-memory jobs and session processes."""
    from service.backends.local.executor import ProcessExecutor
    from service.backends.local.jobs import JobManager, MemoryJobStore
    from service.backends.local.sessions import LocalSessions

    executor = ProcessExecutor(settings.workers, settings.queue_size,
                               start_method=settings.start_method,
                               threads_per_worker=settings.effective_threads)
    jobs = JobManager(MemoryJobStore(), executor, job_policy(settings), on_result)
    sessions = LocalSessions(session_policy(settings, settings.effective_session_threads),
                             settings.start_method)
    return Backend(executor, jobs, sessions)


def _dask(settings: Settings, on_result: ResultCallback | None) -> Backend:
    """The Dask backend: tasks, jobs and sessions on the cluster of ``settings``."""
    from service.backends.dask.connection import DaskConnection
    from service.backends.dask.executor import DaskExecutor
    from service.backends.dask.jobs import DaskJobManager
    from service.backends.dask.sessions import DaskSessions

    connection = DaskConnection(settings.dask_scheduler_address,
                                connect_timeout=settings.dask_connect_timeout)
    executor = DaskExecutor(connection, settings.queue_size, settings.threads_per_worker or 1)
    jobs = DaskJobManager(executor, job_policy(settings), on_result)
    sessions = DaskSessions(connection, session_policy(settings, settings.session_threads or 1))
    return Backend(executor, jobs, sessions)


BACKENDS: dict[str, Callable[[Settings, ResultCallback | None], Backend]] = {
    "local": _local, "process": _local, "dask": _dask}
"""``FFS_EXECUTOR`` value -> backend factory."""


def make_backend(settings: Settings, on_result: ResultCallback | None = None) -> Backend:
    """The backend ``settings.executor`` names.

    Args:
        settings: the service's settings.
        on_result: called as ``on_result(operation, result)`` for every job that succeeds
            (the app's metrics).

    Returns:
        The :class:`~service.backends.contracts.Backend`, not started yet.

    Raises:
        ValueError: an unknown ``FFS_EXECUTOR``.
    """
    try:
        factory = BACKENDS[settings.executor]
    except KeyError:
        raise ValueError(f"unknown executor {settings.executor!r}; use one of "
                         f"{', '.join(BACKENDS)}") from None
    return factory(settings, on_result)
