"""HTTP microservice around :mod:`solver` (FastAPI app at ``service.app:app``).

The service is thin: numerics stay in :mod:`solver`. One request, in the order the files
are met (see docs/service.md, docs/distributed.md):

1. :mod:`service.http` — the HTTP edge. A route (:mod:`service.http.routes`) gets its
   collaborators as typed dependencies, negotiates the result format, reads the body
   (:mod:`~service.http.bodies`) and builds one immutable
   :class:`~service.api.task.TaskRequest` (:mod:`~service.http.payloads`); errors leave as
   RFC 9457 problem documents (:mod:`~service.http.problems`).
2. :mod:`service.operations` — the registry: what each operation takes, answers, reports
   and which task computes it.
3. :mod:`service.backends` — where it runs: the contract (executor, jobs, sessions) and two
   implementations, local processes and a Dask cluster.
4. :mod:`service.worker` — in the worker process: the raw body decoded
   (:mod:`service.api.decoding`), the task run (:mod:`~service.worker.tasks`, calling
   :mod:`solver`), the result encoded (:mod:`~service.worker.output`, glTF by the
   library's writer :mod:`solver.mesh.gltf`).
5. Back up: a :class:`~service.api.task.TaskResult` or a failure dict, turned into the
   response by the route.

:mod:`service.api` is what the HTTP edge and the workers share: request models, response
documents, body decoding, problems and the task types. :mod:`service.settings` holds the
``FFS_*`` settings, :mod:`service.memory` process-memory helpers.
"""
