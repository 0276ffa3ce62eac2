"""The Deformer's per-process cache of rest states (forms + assembled system of a mesh).

Truth: a Deformer built with the cache disabled (``REST_CACHE_SIZE = 0``), and the
handles' prescribed positions, which every answer must meet exactly.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterator

import numpy as np
import pytest
import trimesh

deform = importlib.import_module("solver.deform")  # the module, not solver.deform()


@pytest.fixture(autouse=True)
def _fresh_cache() -> Iterator[None]:
    size = deform.REST_CACHE_SIZE
    deform.clear_rest_cache()
    yield
    deform.REST_CACHE_SIZE = size
    deform.clear_rest_cache()


def _mesh() -> tuple[np.ndarray, np.ndarray]:
    mesh = trimesh.creation.icosphere(subdivisions=2)
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


def _drag(V: np.ndarray, F: np.ndarray, handles: np.ndarray) -> np.ndarray:
    deformer = deform.Deformer(V, F, handles, backend="superlu")
    target = V[handles] + np.array([0.2, -0.1, 0.3]) * (handles % 2)[:, None]
    out = deformer.solve(target)
    assert np.array_equal(out[handles], target)  # hard handles are met bit for bit
    return out


def test_new_handle_set_reuses_the_rest_state_and_equals_an_uncached_build():
    V, F = _mesh()
    first, second = np.array([0, 5, 17, 40]), np.array([3, 8, 60, 100, 120])
    _drag(V, F, first)
    assert deform.rest_cache_info() == {"entries": 1, "computed": 1, "cached": 0}
    cached = _drag(V, F, second)
    assert deform.rest_cache_info() == {"entries": 1, "computed": 1, "cached": 1}
    deform.REST_CACHE_SIZE = 0
    deform.clear_rest_cache()
    uncached = _drag(V, F, second)
    assert deform.rest_cache_info()["entries"] == 0
    assert np.abs(cached - uncached).max() <= 1e-12 * np.abs(uncached).max()


def test_a_changed_mesh_never_reuses_a_stale_rest_state():
    """Same connectivity and size, other rest positions (and another ROI): computed anew,
    and the answer is the one of an uncached build of that mesh."""
    V, F = _mesh()
    handles = np.array([0, 5, 17, 40])
    _drag(V, F, handles)
    moved = V * np.array([1.0, 1.3, 0.8])
    cached_run = _drag(moved, F, handles)
    assert deform.rest_cache_info()["computed"] == 2
    original_run = _drag(V, F, handles)
    assert deform.rest_cache_info()["cached"] == 1
    assert np.abs(cached_run - original_run).max() > 1e-3  # the two rest shapes differ
    deform.REST_CACHE_SIZE = 0
    deform.clear_rest_cache()
    assert np.abs(_drag(moved, F, handles) - cached_run).max() <= 1e-12
    roi = np.flatnonzero(V[:, 2] > -0.2)
    deform.REST_CACHE_SIZE = 2
    whole = deform.Deformer(V, F, handles[:3], backend="superlu")
    part = deform.Deformer(V, F, handles[:3], roi=roi, backend="superlu")
    assert whole.rest_state == "computed" and part.rest_state == "computed"
    assert part.problem.topology.n_faces < whole.problem.topology.n_faces


def test_the_cache_is_bounded_least_recently_used_first():
    V, F = _mesh()
    handles = np.array([0, 5, 17, 40])
    meshes = [V * (1.0 + 0.1 * k) for k in range(3)]
    for mesh in meshes:
        deform.Deformer(mesh, F, handles, backend="superlu")
    assert deform.rest_cache_info()["entries"] == deform.REST_CACHE_SIZE == 2
    assert deform.Deformer(meshes[2], F, handles, backend="superlu").rest_state == "cached"
    assert deform.Deformer(meshes[0], F, handles, backend="superlu").rest_state == "computed"


def test_faces_as_given_key_the_cache_and_invalid_faces_are_never_kept():
    from solver.core.errors import SolverInputError

    V, F = _mesh()
    handles = np.array([0, 5, 17])
    first = deform.Deformer(V, F, handles, backend="superlu")
    again = deform.Deformer(V, F.tolist(), handles[::-1], backend="superlu")  # a list
    assert (first.rest_state, again.rest_state) == ("computed", "cached")
    np.testing.assert_array_equal(again.faces, first.faces)
    bad = F.copy()
    bad[0] = [0, 1, len(V) + 5]  # an index out of range: refused, every time
    for _ in range(2):
        with pytest.raises(SolverInputError):
            deform.Deformer(V, bad, handles, backend="superlu")
    assert deform.rest_cache_info()["entries"] == 1
