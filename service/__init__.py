"""HTTP microservice around :mod:`solver` (FastAPI app at ``service.app:app``).

The service is thin: pydantic schemas (:mod:`service.schemas`), routes
(:mod:`service.routes`), content negotiation, a worker-process pool behind a small executor
interface (:mod:`service.executor`), asynchronous jobs (:mod:`service.jobs`), interactive
deformation sessions (:mod:`service.sessions`), the Dask distributed backend of all three
(:mod:`service.cluster`), RFC 9457 problem documents (:mod:`service.problems`) and
Prometheus metrics. Numerics stay in :mod:`solver`. See docs/service.md and
docs/distributed.md.
"""
