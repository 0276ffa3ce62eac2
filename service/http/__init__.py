"""The HTTP edge (FastAPI): everything that knows about requests and responses.

* :mod:`~service.http.routes`: one module per area (operations, jobs, sessions, health,
  web page);
* :mod:`~service.http.dependencies`: the routes' collaborators as typed dependencies;
* :mod:`~service.http.bodies`: body limit and timeout, multipart forms, uploads;
* :mod:`~service.http.payloads`: a body -> a task request or a session spec;
* :mod:`~service.http.running`: one synchronous task, with timeout and disconnect;
* :mod:`~service.http.drags`: the session drag wire formats;
* :mod:`~service.http.negotiation`: ``Accept`` -> result format;
* :mod:`~service.http.problems`: problem responses, error handlers, backend failures ->
  problems;
* :mod:`~service.http.openapi`: the hand-written parts of the OpenAPI document;
* :mod:`~service.http.metrics`: Prometheus metrics and their middleware;
* :mod:`~service.http.server`: the uvicorn protocol with a header deadline
  (``python -m service``).
"""
