"""What runs in a worker process (a local pool worker, a session process, a Dask worker).

* :mod:`~service.worker.runtime`: process set-up, stage timing, failures as dicts (the
  dispatch itself is :func:`service.operations.run`);
* :mod:`~service.worker.tasks`: the operations' task functions, calling :mod:`solver`;
* :mod:`~service.worker.session`: a deformation session's warm state;
* :mod:`~service.worker.output`: response bodies (JSON, glTF via :mod:`solver.mesh.gltf`).
"""
