"""The PARDISO analysis cache and MKL's thread count: an analysis (ordering and symbolic
factorization) is reused only at the thread count it was made with.

Measured before the cache was keyed by it (the mkl 2026.2 wheel, 2 cores, the anchored
reconstruction system of a 120 x 120 grid: 99,366 unknowns): an analysis made with one
thread and reused by a factorization with two failed with PARDISO error -4 ("zero or negative
pivot") on that SPD matrix, every time; made with two and factorized with one it worked.
Solves at another thread count than the factorization's are fine (checked below)."""

from __future__ import annotations

import ctypes
import gc
from collections.abc import Iterator

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

from solver import linalg
from solver.linalg import analysis_cache_info, factorize
from tests.solver.test_analysis_cache import grid_mesh, noisy_system, relative

pytestmark = pytest.mark.skipif("pardiso" not in linalg.available_backends(),
                                reason="PARDISO (pypardiso / mkl) not installed")


@pytest.fixture
def threads() -> Iterator[object]:
    """``threads(n)`` sets MKL's thread count for this thread (``mkl_set_num_threads_local``,
    which PARDISO's calls from this thread follow), restored after the test; the cache
    starts and ends empty.

    The thread-local setter, not ``mkl_set_num_threads``: a thread-local count overrides the
    global one, and threadpoolctl leaves one behind (its MKL limits are thread-local and are
    restored to the count they found, not cleared), so after any ``threadpool_limits`` in
    this process (the refinement, bench.gauss_newton_cg's tests) the global setter changes
    nothing (the whole suite failed this way once)."""
    from solver.linalg.pardiso import load_mkl

    mkl = load_mkl()
    local = mkl.lib.MKL_Set_Num_Threads_Local
    local.argtypes = [ctypes.c_int]
    local.restype = ctypes.c_int
    found: list[int] = []
    gc.collect()
    linalg.clear_analysis_cache()

    def set_threads(n: int) -> None:
        previous = local(n)
        if not found:
            found.append(previous)
        assert mkl.max_threads() == n

    yield set_threads
    if found:
        local(found[0])
    gc.collect()
    linalg.clear_analysis_cache()


@pytest.mark.parametrize("k", [60, 120])
@pytest.mark.parametrize(("first", "second"), [(1, 2), (2, 1)])
def test_an_analysis_is_reused_only_at_its_thread_count(threads, k, first, second):
    K, b = noisy_system(*grid_mesh(k, False))
    reference = spsolve(sp.csc_array(K), b)
    threads(first)
    factor = factorize(K, "pardiso")
    assert factor.analysis == "computed"
    assert relative(factor.solve(b), reference) < 1e-9
    del factor
    gc.collect()  # its handle, analysed with `first` threads, goes to the cache
    assert analysis_cache_info()["idle_handles"] == 1

    threads(second)
    other = factorize(K, "pardiso")  # not the idle handle: a fresh analysis
    assert other.analysis == "computed"
    assert relative(other.solve(b), reference) < 1e-9
    info = analysis_cache_info()
    assert (info["patterns"], info["computed"], info["cached_handle"]) == (2, 2, 0)
    del other
    gc.collect()

    threads(first)  # back at the first count: its analysis is reused
    again = factorize(K, "pardiso")
    assert again.analysis == "cached" and analysis_cache_info()["cached_handle"] == 1
    assert relative(again.solve(b), reference) < 1e-9
    threads(second)  # a solve at another count than the factorization's
    assert relative(again.solve(b), reference) < 1e-9


def test_an_analysis_ahead_is_made_for_the_current_thread_count(threads):
    """``analyze_upper`` (a session's analysis ahead of its first refined drag) files the
    analysis under the thread count of the moment: a factorization at another count does
    not take it."""
    from solver.linalg.pardiso import analyze_upper, upper_triangle

    K, b = noisy_system(*grid_mesh(40, True))
    threads(1)
    assert analyze_upper(upper_triangle(K))
    threads(2)
    factor = factorize(K, "pardiso")
    assert factor.analysis == "computed"
    assert relative(factor.solve(b), spsolve(sp.csc_array(K), b)) < 1e-9
    threads(1)
    assert not analyze_upper(upper_triangle(K))  # already there for one thread
    assert np.isfinite(factor.solve(b)).all()
