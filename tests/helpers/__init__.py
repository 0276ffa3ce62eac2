"""Helpers shared by the tests and the benchmarks, imported as ``tests.helpers.<module>``:

* :mod:`tests.helpers.meshes`: the meshes of tests/data (``load``), procedural meshes with
  known topology (``icosphere``, ``grid``, tori, voxel surfaces) and rigid alignment errors;
* :mod:`tests.helpers.botsch_sorkine`: the Botsch-Sorkine 2008 deformation cases;
* :mod:`tests.helpers.libigl_reference`: libigl's ARAP as the independent reference;
* :mod:`tests.helpers.gltf_validator`: the Khronos glTF validator run on bytes;
* :mod:`tests.helpers.servers`: a free loopback port, an in-process app and a real uvicorn;
* :mod:`tests.helpers.service`: request bodies, problem assertions, metrics, debug tasks;
* :mod:`tests.helpers.sessions`: reference drags computed like a session worker computes them;
* :mod:`tests.helpers.web`: paths, Chromium and screenshot checks of the browser tests.
"""

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
"""The repository's root folder."""
DATA = REPO / "tests" / "data"
"""The meshes and deformation cases the tests read (tests/data)."""
