"""Sparse symmetric-positive-definite factorization with selectable backends.

Factorize a sparse SPD matrix ``K`` once, then solve ``K x = b`` for as many right-hand
sides as needed; each solve only back-substitutes::

    fact = factorize(K)               # backend="auto": the fastest one installed
    x = fact.solve(b)                 # b: (N,) or (N, k) float64 -> same shape

Backends, fastest first on the reference machine (2-core x86_64; factorization plus one
solve of 3 right-hand sides, numbers in ``bench/LINALG.md``):

``"pardiso"``
    Intel oneMKL PARDISO, real SPD mode (``mtype=2``), upper triangle in zero-based CSR,
    called directly through ``ctypes`` so that the factor stays inside MKL between
    solves and nothing is copied per solve. Needs the MKL runtime ``libmkl_rt``, which
    ``pip install pypardiso`` brings (it depends on the ``mkl`` wheel); x86_64 only.
    2-10x faster than the others from 70K unknowns on, and the smallest factor. It
    releases the GIL and uses MKL's OpenMP threads, by default one per core. Limit them
    with ``MKL_NUM_THREADS`` (and ``OMP_NUM_THREADS``) set before the process loads MKL
    when several processes factorize at once: ``threadpoolctl`` does not see the MKL
    library loaded here through ``ctypes``, so its limits do not reach PARDISO (the
    service's worker processes set the environment variables at start-up).
``"superlu"``
    SciPy's SuperLU (``scipy.sparse.linalg.splu``) with the minimum-degree ordering on
    ``K + K^T`` and diagonal pivoting (``SymmetricMode``, ``diag_pivot_thresh=0``).
    Always available; single-threaded; releases the GIL. It is an LU factorization, so
    it needs about twice the memory of a Cholesky factor, and it does *not* reject a
    matrix that is symmetric indefinite but nonsingular: it solves it correctly instead
    of raising.
``"cholespy"``
    CHOLMOD (SuiteSparse) Cholesky ``L L^T`` through ``pip install cholespy``, from the
    lower triangle. Its factorization is as fast as SuperLU's or up to 1.4x slower (the
    wheel bundles the unoptimized reference BLAS), so ``"auto"`` never picks it while
    SuperLU works; choose it explicitly for less memory than SuperLU (up to half) and
    1.5-3x faster solves (many solves per factorization). Single-threaded; holds the GIL
    while it factorizes. CHOLMOD prints a one-line "not positive definite" warning to
    stdout when it rejects a matrix.

Not backends: ``python-mumps`` 0.0.2 does not import with NumPy 2; ``sksparse-minimal``
0.3 provides no ``sksparse`` module (only ``sksparse_minimal``).

Errors: an unknown backend name raises :class:`ValueError`; a known but uninstalled one
raises :class:`BackendUnavailableError` (a ``ValueError`` and an ``ImportError``) naming
the pip package. A matrix that is singular or not positive definite raises
:class:`SingularSystemError`, either from the factorization or from :meth:`solve`,
which checks the relative residual ``||K x - b|| / ||b||`` of every column it returns
(one sparse matrix product) and refuses results above :data:`RESIDUAL_TOLERANCE`.

Pickling: every :class:`Factorization` pickles, whatever the backend, but no native
factor is ever serialized (none of the three libraries can export one). The pickle
holds the backend name and the matrix (CSR arrays, about ``12 * nnz(K)`` bytes), and
unpickling **factorizes again** in the receiving process, which costs one factorization
there and raises :class:`BackendUnavailableError` if that process lacks the backend.
For worker pools it is therefore as cheap to send the matrix and call :func:`factorize`
in the worker.

Analysis cache (PARDISO): the ordering and symbolic factorization depend only on the
sparsity pattern, so each process keeps them per pattern (:mod:`solver.linalg.analysis_cache`,
within :data:`ANALYSIS_CACHE_BYTES`). ``Factorization.analysis`` says ``"cached"`` or
``"computed"``; :func:`analysis_cache_info` and :func:`clear_analysis_cache` inspect and empty
the cache. Repeated factorizations of one pattern with new values (refinement iterations,
successive reconstructs of one mesh, new handle sets) therefore skip the analysis without any
change to the calls. SuperLU and cholespy always compute their analysis.

Thread safety: :meth:`Factorization.solve` may be called from several threads; solves on
one factorization are serialized by a lock (the native solvers reuse workspaces), and
different factorizations run in parallel where the backend releases the GIL.

Modules: :mod:`~solver.linalg.factorization` (:func:`factorize`, :class:`Factorization`),
:mod:`~solver.linalg.backends` (the native solvers and the choice among them),
:mod:`~solver.linalg.pardiso` (the ``ctypes`` binding of MKL PARDISO),
:mod:`~solver.linalg.analysis_cache` and :mod:`~solver.linalg.errors`. This package
re-exports their public names.
"""

from __future__ import annotations

import sys
import types

from . import analysis_cache
from .analysis_cache import analysis_cache_info, clear_analysis_cache, release_cached_factors
from .backends import BACKENDS, available_backends, default_backend, resolve_backend
from .errors import BackendUnavailableError, SingularSystemError
from .factorization import (
    RESIDUAL_TOLERANCE,
    Factorization,
    analyze,
    factorize,
    upper_symmetric_product,
)

__all__ = [
    "ANALYSIS_CACHE_BYTES",
    "BACKENDS",
    "RESIDUAL_TOLERANCE",
    "BackendUnavailableError",
    "Factorization",
    "SingularSystemError",
    "analysis_cache_info",
    "analyze",
    "available_backends",
    "clear_analysis_cache",
    "default_backend",
    "factorize",
    "release_cached_factors",
    "resolve_backend",
    "upper_symmetric_product",
]


class _LinalgModule(types.ModuleType):
    """This package's module type: ``ANALYSIS_CACHE_BYTES`` reads and assigns the limit
    that :mod:`solver.linalg.analysis_cache` applies, so ``solver.linalg.ANALYSIS_CACHE_BYTES
    = 0`` keeps working as it did when this package was one module."""

    @property
    def ANALYSIS_CACHE_BYTES(self) -> int:  # noqa: N802
        """Memory limit (bytes) of the analysis cache: see
        :data:`solver.linalg.analysis_cache.ANALYSIS_CACHE_BYTES`."""
        return analysis_cache.ANALYSIS_CACHE_BYTES

    @ANALYSIS_CACHE_BYTES.setter
    def ANALYSIS_CACHE_BYTES(self, value: int) -> None:  # noqa: N802
        analysis_cache.ANALYSIS_CACHE_BYTES = value


sys.modules[__name__].__class__ = _LinalgModule
