"""What the HTTP edge and the workers share, free of FastAPI and of processes.

* :mod:`~service.api.schemas`: the request models (pydantic);
* :mod:`~service.api.documents`: the response models (they produce the OpenAPI schemas);
* :mod:`~service.api.decoding`: JSON and binary bodies decoded as numpy arrays;
* :mod:`~service.api.task`: the typed request and result that cross the process boundary;
* :mod:`~service.api.problems`: problem kinds, :class:`~service.api.problems.ProblemError`
  and failure dicts.
"""
