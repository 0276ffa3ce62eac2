"""Fill-reducing orderings and analysis reuse for PARDISO on the reconstruction matrix.

For one mesh (noisy forms, anchored, the matrix the linear path factorizes), in one
process and interleaved over ``--rounds`` rounds so that machine load hits every variant
alike, it times PARDISO's phases on the same matrix:

* ``iparm[1]=0`` (minimum degree), ``=2`` (METIS nested dissection), ``=3`` (parallel
  METIS, MKL's default for SPD): analysis (phase 11, ordering + symbolic) and numerical
  factorization (phase 22);
* ``cached ordering``: phase 11 with the ordering given (``iparm[4]=1``): symbolic only;
* ``cached handle``: phase 22 on a handle whose numerical factor was freed (phase 0);
* ``compressed PARDISO``: what ``factorize(..., groups=...)`` does on a cold analysis --
  PARDISO's own ordering of the compressed graph (one node per vertex and one per face),
  expanded to the face's 3 unknowns, then phase 11 with that ordering;
* ``compressed METIS``: ``pymetis.nested_dissection`` of the compressed graph (one node
  per vertex and one per face, |V| + |F| nodes), expanded to the face's 3 unknowns, then
  phase 11 with that ordering (needs ``pip install pymetis``; skipped without).

Reports nnz(L) (fill) and the 3-RHS solve's relative residual of each variant.

    python -m bench.orderings [mesh ...] [--rounds 3]
"""

from __future__ import annotations

import os
import time
from typing import Any

import numpy as np
import scipy.sparse as sp

from bench.common import load_bench_mesh, meshes_and_rounds
from solver import fundamental_forms
from solver.immersion import ImmersionProblem
from solver.linalg import pardiso
from solver.mesh.topology import build_topology


def system_matrix(case: str) -> tuple[sp.csr_array, int, int]:
    """The anchored reconstruction matrix of noisy forms, |V| and |F|."""
    V, F = load_bench_mesh(case)
    forms = fundamental_forms(V, F)
    inner = forms.angles != 0
    forms.angles[inner] += np.random.default_rng(0).normal(scale=1e-3, size=int(inner.sum()))
    problem = ImmersionProblem(build_topology(forms.faces, n_vertices=len(V)), forms.lengths,
                               forms.angles)
    anchor, _ = problem.anchors(np.ones(problem.topology.n_components, dtype=bool))
    matrix = sp.csr_array(problem.system(anchor, "superlu").factor._matrix)
    return matrix, len(V), len(F)


def compressed_ordering(matrix: sp.csr_array, n: int, m: int) -> np.ndarray | None:
    """METIS nested dissection of the |V| + |F| node graph, expanded to unknowns."""
    try:
        import pymetis
    except ImportError:
        return None
    N = matrix.shape[0]
    node = np.concatenate([np.arange(n), n + np.repeat(np.arange(m), 3)]).astype(np.int64)
    rows = np.repeat(np.arange(N), np.diff(matrix.indptr))
    r, c = node[rows], node[matrix.indices]
    pairs = np.unique(r[r != c] * (n + m) + c[r != c])
    r, c = pairs // (n + m), pairs % (n + m)
    xadj = np.zeros(n + m + 1, dtype=np.int64)
    np.cumsum(np.bincount(r, minlength=n + m), out=xadj[1:])
    order, _ = pymetis.nested_dissection(pymetis.CSRAdjacency(xadj.astype(np.int32),
                                                              c.astype(np.int32)))
    order = np.asarray(order)
    sizes = np.where(order < n, 1, 3)
    starts = np.where(order < n, order, n + 3 * (order - n))
    first = np.repeat(np.cumsum(sizes) - sizes, sizes)
    return (np.repeat(starts, sizes) + np.arange(N) - first).astype(np.int32)


class Run:
    """PARDISO phases on one upper-triangle matrix with one handle."""

    def __init__(self, matrix: sp.csr_array, perm: np.ndarray | None,
                 iparm: dict[int, int]) -> None:
        upper = pardiso.upper_triangle(matrix)
        self.arrays = (np.ascontiguousarray(upper.data), upper.indptr, upper.indices)
        self.handle = pardiso.PardisoHandle(pardiso.load_mkl(), matrix.shape[0], perm)
        for key, value in iparm.items():
            self.handle.iparm[key] = value
        self.matrix = matrix

    def phase(self, phase: int) -> float:
        start = time.perf_counter()
        error = self.handle.call(phase, *self.arrays)
        if error:
            raise RuntimeError(f"phase {phase}: PARDISO error {error}")
        return time.perf_counter() - start

    def residual(self) -> float:
        b = np.asfortranarray(np.random.default_rng(1).normal(size=(self.matrix.shape[0], 3)))
        x = np.zeros_like(b, order="F")
        self.handle.call(33, *self.arrays, b, x, 3)
        return float(np.linalg.norm(self.matrix @ x - b) / np.linalg.norm(b))


def one_round(matrix: sp.csr_array, n: int, m: int) -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    kept: Run | None = None
    for ordering in (3, 2, 0):
        run = Run(matrix, None, {1: ordering})
        analysis, numeric = run.phase(11), run.phase(22)
        out[f"iparm[1]={ordering}"] = {"analysis": analysis, "numeric": numeric,
                                       "nnz_L": int(run.handle.iparm[17]),
                                       "residual": run.residual()}
        if ordering == 3:
            kept = run
        else:
            run.handle.release()
    assert kept is not None
    again = Run(matrix, kept.handle.perm, {})
    out["cached ordering"] = {"analysis": again.phase(11), "numeric": again.phase(22),
                              "nnz_L": int(again.handle.iparm[17]),
                              "residual": again.residual()}
    again.handle.release()
    kept.handle.drop_factor()
    out["cached handle"] = {"analysis": 0.0, "numeric": kept.phase(22),
                            "nnz_L": int(kept.handle.iparm[17]), "residual": kept.residual()}
    kept.handle.release()
    start = time.perf_counter()
    groups = np.concatenate([np.arange(n), n + np.repeat(np.arange(m), 3)])
    upper = pardiso.upper_triangle(matrix)
    perm = pardiso.group_ordering(pardiso.load_mkl(), upper.indptr, upper.indices, groups)
    ordering = time.perf_counter() - start
    run = Run(matrix, perm, {})
    symbolic = run.phase(11)
    out["compressed PARDISO"] = {"analysis": ordering + symbolic, "nd": ordering,
                                 "numeric": run.phase(22), "nnz_L": int(run.handle.iparm[17]),
                                 "residual": run.residual()}
    run.handle.release()
    start = time.perf_counter()
    perm = compressed_ordering(matrix, n, m)
    if perm is not None:
        nd = time.perf_counter() - start
        run = Run(matrix, perm, {})
        symbolic = run.phase(11)
        out["compressed METIS"] = {"analysis": nd + symbolic, "nd": nd, "numeric": run.phase(22),
                                   "nnz_L": int(run.handle.iparm[17]), "residual": run.residual()}
        run.handle.release()
    return out


def main() -> None:
    args = meshes_and_rounds(__doc__, ["rocker-arm.obj", "armadillo.obj"], rounds=3,
                             name="cases")
    for case in args.cases:
        matrix, n, m = system_matrix(case)
        print(f"\n{case}: N = {matrix.shape[0]}, nnz = {matrix.nnz}; "
              f"MKL threads: {os.environ.get('MKL_NUM_THREADS', 'default')}\n")
        print("| round | load | variant | analysis s | numeric s | analysis + numeric s | "
              "nnz(L) | residual |")
        print("|---:|---:|---|---:|---:|---:|---:|---:|")
        for k in range(args.rounds):
            load_now = os.getloadavg()[0]
            for name, r in one_round(matrix, n, m).items():
                nd = f" (ND {r['nd']:.2f})" if "nd" in r else ""
                print(f"| {k} | {load_now:.1f} | {name} | {r['analysis']:.2f}{nd} | "
                      f"{r['numeric']:.2f} | {r['analysis'] + r['numeric']:.2f} | "
                      f"{r['nnz_L'] / 1e6:.2f}M | {r['residual']:.1e} |", flush=True)


if __name__ == "__main__":
    main()
