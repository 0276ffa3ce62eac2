"""The local backend (``FFS_EXECUTOR=local``, the default): processes of this service.

* :mod:`~service.backends.local.executor`: a pool of worker processes;
* :mod:`~service.backends.local.jobs`: job records in this process's memory;
* :mod:`~service.backends.local.sessions`: one dedicated process per session.
"""
