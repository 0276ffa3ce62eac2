"""What runs in a worker process (a local pool worker, a session process, a Dask worker).

* :mod:`~service.worker.runtime`: process set-up, :func:`~service.worker.runtime.run` (decode
  a raw body, run the operation's task, time its stages), failures as dicts;
* :mod:`~service.worker.tasks`: the operations' task functions, calling :mod:`solver`;
* :mod:`~service.worker.session`: a deformation session's warm state;
* :mod:`~service.worker.output`: response bodies (JSON, glTF via :mod:`~service.worker.gltf`).
"""
