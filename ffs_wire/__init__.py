"""``ffs_wire``: what travels between the client (:mod:`ffs`) and the service
(:mod:`service`), in a package of its own so that neither imports the other.

* :mod:`ffs_wire.arrays`: the ``application/vnd.ffs.arrays`` binary body (media type,
  framing, the reference encoder) and :func:`~ffs_wire.arrays.json_default` (numpy values
  in every JSON the project writes).
* :mod:`ffs_wire.gltf`: a ``.gltf`` file as it is sent, its buffer files beside it embedded
  (the library's rule for files on disk, for the client, which may not import it).
* :mod:`ffs_wire.progress`: the one rule of progress reports (:class:`~ffs_wire.progress.
  ProgressThrottle`: at most 5 a second), the service's workers' and ``ffs -j N``'s.

numpy and the standard library only: importing it never imports FastAPI, httpx or the solver.
"""
