"""The Dask distributed backend (``FFS_EXECUTOR=dask``): executor, jobs and sessions.

Work and state live on an existing Dask cluster, so any number of service replicas can
share it (design and measurements: docs/distributed.md). Its parts, in the order a request
meets them:

* :mod:`~service.backends.dask.connection`: the replica's client, connected in the
  background with retries;
* :mod:`~service.backends.dask.executor`: tasks as Dask futures (retried once when their
  worker dies);
* :mod:`~service.backends.dask.jobs`: job records in the scheduler, results held by
  published datasets;
* :mod:`~service.backends.dask.sessions`: one actor per session;
* :mod:`~service.backends.dask.worker`: what runs on the workers;
* :mod:`~service.backends.dask.registry`: the scheduler plugin holding jobs and sessions.

``dask scheduler --preload service.backends.dask`` installs the registry at start
(:func:`dask_setup`); otherwise the first replica that calls it does.
"""

from __future__ import annotations

from typing import Any

from service.backends.dask.registry import install_registry


def dask_setup(scheduler: Any) -> None:
    """``dask scheduler --preload service.backends.dask`` installs the registry at start."""
    install_registry(scheduler)
