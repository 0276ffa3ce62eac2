"""Tests of solver.linalg: the sparse SPD factorization layer and its backends."""

from __future__ import annotations

import functools
import importlib.util
import pickle
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
import trimesh
from scipy.sparse.linalg import spsolve

from solver import linalg
from solver.linalg import (
    BACKENDS,
    BackendUnavailableError,
    Factorization,
    SingularSystemError,
    available_backends,
    default_backend,
    factorize,
)

AVAILABLE = available_backends()
BENCH = Path(__file__).resolve().parents[2] / "bench" / "linalg_backends.py"


@functools.cache
def _bench_module():
    """bench/linalg_backends.py (not a package), for its test-matrix builder."""
    spec = importlib.util.spec_from_file_location("linalg_backends", BENCH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while executing
    spec.loader.exec_module(module)
    return module


def grid_laplacian(n: int) -> sp.csr_array:
    """Graph Laplacian of the n x n grid: (n^2, n^2), symmetric, singular (constants)."""
    path = sp.diags_array([-np.ones(n - 1), np.r_[1.0, 2.0 * np.ones(n - 2), 1.0],
                           -np.ones(n - 1)], offsets=[-1, 0, 1])
    eye = sp.eye_array(n)
    return sp.csr_array(sp.kron(path, eye) + sp.kron(eye, path))


def laplacian_plus_identity(n: int = 20) -> sp.csr_array:
    """SPD: grid Laplacian + identity, (n^2, n^2)."""
    return sp.csr_array(grid_laplacian(n) + sp.eye_array(n * n))


def frame_matrix(subdivisions: int = 2, pin: bool = True) -> sp.csr_array:
    """The reconstruction-structured matrix of the benchmark on a small icosphere."""
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions)
    return _bench_module().frame_system_matrix(mesh.vertices, mesh.faces, pin=pin)


MATRICES = {"laplacian+I": laplacian_plus_identity, "icosphere(2)": frame_matrix}


def relative_error(x: np.ndarray, reference: np.ndarray) -> float:
    return float(np.linalg.norm(x - reference) / np.linalg.norm(reference))


@pytest.fixture(scope="module", params=sorted(MATRICES))
def spd_matrix(request: pytest.FixtureRequest) -> sp.csr_array:
    return MATRICES[request.param]()


# ------------------------------------------------------------------- backend selection


def test_default_backend_is_available() -> None:
    assert default_backend() in AVAILABLE
    assert default_backend() == AVAILABLE[0]
    assert "superlu" in AVAILABLE
    assert [b for b in BACKENDS if b in AVAILABLE] == AVAILABLE  # keeps the speed order


def test_unknown_backend_raises_value_error_listing_names() -> None:
    with pytest.raises(ValueError, match="valid names") as info:
        factorize(laplacian_plus_identity(4), "umfpack")
    assert not isinstance(info.value, BackendUnavailableError)
    for name in BACKENDS:
        assert name in str(info.value)


def test_uninstalled_backend_names_pip_package(monkeypatch: pytest.MonkeyPatch) -> None:
    reasons = {"pardiso": None, "cholespy": "ImportError: No module named 'cholespy'",
               "superlu": None}
    monkeypatch.setattr(linalg.backends, "_unavailable_reason", reasons.get)
    assert "cholespy" not in available_backends()
    with pytest.raises(BackendUnavailableError, match="pip install cholespy") as info:
        factorize(laplacian_plus_identity(4), "cholespy")
    assert isinstance(info.value, ValueError)
    assert isinstance(info.value, ImportError)


def test_an_uninstalled_backend_is_named_in_words() -> None:
    """The real reason of a backend that does not import, without the exception's class
    name (issue 43: no internal names in errors)."""
    import importlib.util

    missing = [name for name in ("cholespy", "pardiso")
               if importlib.util.find_spec(linalg.backends._PIP_PACKAGE[name]) is None]
    if not missing:
        pytest.skip("every optional backend is installed here")
    linalg.backends._unavailable_reason.cache_clear()
    with pytest.raises(BackendUnavailableError) as info:
        factorize(laplacian_plus_identity(4), missing[0])
    message, package = str(info.value), linalg.backends._PIP_PACKAGE[missing[0]]
    assert "No module named" in message and f"pip install {package}" in message
    assert "Error" not in message, message


def test_auto_falls_back_to_superlu(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(linalg.backends, "_unavailable_reason",
                        lambda name: None if name == "superlu" else "not installed")
    assert available_backends() == ["superlu"]
    assert factorize(laplacian_plus_identity(4)).backend == "superlu"


# ----------------------------------------------------------------------------- solving


@pytest.mark.parametrize("backend", AVAILABLE)
def test_solves_match_spsolve(backend: str, spd_matrix: sp.csr_array) -> None:
    rng = np.random.default_rng(0)
    n = spd_matrix.shape[0]
    fact = factorize(spd_matrix, backend)
    assert isinstance(fact, Factorization)
    assert (fact.backend, fact.size) == (backend, n)
    for shape in [(n,), (n, 3), (n, 1)]:
        b = rng.standard_normal(shape)
        x = fact.solve(b)
        assert x.shape == shape and x.dtype == np.float64
        reference = spsolve(sp.csc_array(spd_matrix), b).reshape(shape)
        assert relative_error(x, reference) < 1e-10


@pytest.mark.parametrize("backend", AVAILABLE)
def test_factorization_is_reused(backend: str) -> None:
    K = frame_matrix()
    rng = np.random.default_rng(1)
    fact = factorize(K, backend)
    b1, b2 = rng.standard_normal(K.shape[0]), rng.standard_normal((K.shape[0], 3))
    x1, x2 = fact.solve(b1), fact.solve(b2)
    x1_again = fact.solve(b1)
    assert relative_error(x1, spsolve(sp.csc_array(K), b1)) < 1e-10
    assert relative_error(x2, spsolve(sp.csc_array(K), b2)) < 1e-10
    np.testing.assert_array_equal(x1, x1_again)


@pytest.mark.parametrize("backend", AVAILABLE)
def test_any_sparse_format_and_dtype(backend: str) -> None:
    K = laplacian_plus_identity(6)
    b = np.arange(K.shape[0], dtype=np.int64)  # integer rhs is converted to float64
    reference = spsolve(sp.csc_array(K), b.astype(float))
    for variant in (K.tocoo(), K.tocsc(), sp.csr_matrix(K), K.todok(), K.astype(np.float32),
                    sp.coo_array(K.astype(np.int32))):
        x = factorize(variant, backend).solve(b)
        assert x.dtype == np.float64
        assert relative_error(x, reference) < 1e-6  # float32 input is rounded


@pytest.mark.parametrize("backend", AVAILABLE)
def test_matrix_is_copied(backend: str) -> None:
    K = laplacian_plus_identity(5)
    b = np.ones(K.shape[0])
    fact = factorize(K, backend)
    expected = fact.solve(b)
    K.data *= 3.0  # later changes to the caller's matrix do not matter
    np.testing.assert_allclose(fact.solve(b), expected, rtol=1e-12)


@pytest.mark.parametrize("backend", AVAILABLE)
def test_zero_and_empty_rhs(backend: str) -> None:
    K = laplacian_plus_identity(5)
    fact = factorize(K, backend)
    np.testing.assert_array_equal(fact.solve(np.zeros(K.shape[0])), 0.0)
    assert fact.solve(np.zeros((K.shape[0], 0))).shape == (K.shape[0], 0)


def test_empty_matrix() -> None:
    fact = factorize(sp.csr_array((0, 0)))
    assert fact.size == 0
    assert fact.solve(np.zeros(0)).shape == (0,)
    assert fact.solve(np.zeros((0, 2))).shape == (0, 2)


@pytest.mark.parametrize("backend", AVAILABLE)
def test_concurrent_solves(backend: str) -> None:
    K = frame_matrix(1)
    fact = factorize(K, backend)
    rhs = [np.random.default_rng(i).standard_normal((K.shape[0], 2)) for i in range(8)]
    with ThreadPoolExecutor(4) as pool:
        solutions = list(pool.map(fact.solve, rhs))
    for b, x in zip(rhs, solutions, strict=True):
        assert relative_error(K @ x, b) < 1e-10


@pytest.mark.parametrize("backend", AVAILABLE)
def test_pickle_refactorizes(backend: str) -> None:
    K = frame_matrix(1)
    b = np.random.default_rng(2).standard_normal((K.shape[0], 3))
    fact = factorize(K, backend)
    clone = pickle.loads(pickle.dumps(fact))
    assert (clone.backend, clone.size) == (backend, fact.size)
    np.testing.assert_allclose(clone.solve(b), fact.solve(b), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("backend", AVAILABLE)
def test_upper_triangle_input_matches_the_full_matrix(backend: str) -> None:
    """factorize(triangle="upper") (the refinement's Gauss-Newton matrices): the same
    solutions as the full matrix, pickling included; lower entries or a missing diagonal
    entry are refused."""
    K = frame_matrix(1)
    upper = sp.csr_array(sp.triu(K, format="csr"))
    upper.sum_duplicates()
    b = np.random.default_rng(3).standard_normal((K.shape[0], 3))
    full = factorize(K, backend).solve(b)
    fact = factorize(upper, backend, triangle="upper")
    np.testing.assert_allclose(fact.solve(b), full, rtol=1e-9, atol=1e-12)
    clone = pickle.loads(pickle.dumps(fact))
    np.testing.assert_allclose(clone.solve(b), full, rtol=1e-9, atol=1e-12)
    with pytest.raises(ValueError, match="below the diagonal"):
        factorize(K, backend, triangle="upper")
    no_diagonal = sp.csr_array(sp.triu(K, k=1, format="csr") + sp.eye_array(K.shape[0]) * 0)
    no_diagonal.eliminate_zeros()
    with pytest.raises(ValueError, match="diagonal entry"):
        factorize(no_diagonal, backend, triangle="upper")
    with pytest.raises(ValueError, match="triangle"):
        factorize(K, backend, triangle="lower")


# ------------------------------------------------------------------ errors and checks


@pytest.mark.parametrize("backend", AVAILABLE)
@pytest.mark.parametrize("matrix", ["grid laplacian", "unpinned icosphere(1)"])
def test_singular_matrix_raises(backend: str, matrix: str) -> None:
    K = grid_laplacian(12) if matrix == "grid laplacian" else frame_matrix(1, pin=False)
    b = np.random.default_rng(3).standard_normal(K.shape[0])
    with pytest.raises(SingularSystemError):
        factorize(K, backend).solve(b)


@pytest.mark.parametrize("backend", [b for b in AVAILABLE if b != "superlu"])
def test_cholesky_backends_reject_indefinite(backend: str) -> None:
    K = sp.diags_array(np.r_[np.ones(9), -1.0]).tocsr()
    with pytest.raises(SingularSystemError):
        factorize(K, backend).solve(np.ones(10))


@pytest.mark.parametrize("backend", AVAILABLE)
def test_inaccurate_solution_is_refused(backend: str) -> None:
    fact = factorize(laplacian_plus_identity(5), backend)

    class Garbage:
        def solve(self, rhs: np.ndarray) -> np.ndarray:
            return rhs * 0.5

    fact._solver = Garbage()
    with pytest.raises(SingularSystemError, match="residual"):
        fact.solve(np.ones(fact.size))
    fact._solver.solve = lambda rhs: np.full_like(rhs, np.nan)
    with pytest.raises(SingularSystemError, match="not finite"):
        fact.solve(np.ones(fact.size))


def test_invalid_inputs() -> None:
    K = laplacian_plus_identity(4)
    with pytest.raises(TypeError):
        factorize(K.toarray())
    with pytest.raises(TypeError):
        factorize(K.astype(np.complex128))
    with pytest.raises(ValueError, match="square"):
        factorize(sp.csr_array(np.ones((3, 4))))
    with pytest.raises(ValueError, match="symmetric"):
        factorize(sp.csr_array(K + sp.csr_array(([1.0], ([0], [1])), shape=K.shape)))
    nan = K.copy()
    nan.data[0] = np.nan
    with pytest.raises(SingularSystemError, match="non-finite"):
        factorize(nan)
    fact = factorize(K)
    with pytest.raises(ValueError, match="shape"):
        fact.solve(np.ones(K.shape[0] + 1))
    with pytest.raises(ValueError, match="shape"):
        fact.solve(np.ones((K.shape[0], 2, 2)))
    with pytest.raises(ValueError, match="non-finite"):
        fact.solve(np.full(K.shape[0], np.inf))
