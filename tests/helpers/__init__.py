"""Helpers shared by the tests (import as ``helpers.<module>``; ``tests/`` is on sys.path):

* :mod:`helpers.servers`: an in-process app and a real uvicorn on loopback;
* :mod:`helpers.service`: small meshes, request bodies, problem assertions, debug tasks;
* :mod:`helpers.sessions`: reference drags computed like a session worker computes them.
"""
