"""PARDISO on the refinement's Gauss-Newton matrix: its own ordering against the ``groups`` hint.

The refinement factorizes ``J^T J + lambda D`` (:mod:`solver.refine.normal_equations`, one 3x3 block
per pair of vertices that share a residual) once per fresh Gauss-Newton step and solves
with it once per step. For one mesh, in one process and interleaved over ``--rounds``
rounds (so that machine load hits both alike), it times on the same matrix:

* ``PARDISO's ordering``: what :func:`solver.refine.Refiner` does, PARDISO ordering the
  matrix itself (MKL's two-level factor);
* ``groups hint``: the ordering of the compressed graph (one node per vertex,
  :func:`solver.linalg.pardiso.group_ordering`) passed as a user permutation, which makes
  MKL build the classic factor;
* ``single precision``: PARDISO's ordering, factorized and solved in float32
  (:mod:`solver.refine.mixed_precision`; a refinement's solve then costs two of these solves and
  a product with the matrix);

the analysis (ordering and symbolic factorization, once per pattern: cached afterwards), the
numerical factorization and a one-column solve, with nnz(L); and the assembly of the matrix
and gradient (:meth:`solver.refine.normal_equations.GaussNewtonSystem.normal_equations`), once per
fresh step, and of the gradient alone, once per step.

Over several meshes it also fits the scaling exponents (time ~ faces^k) of the
factorization, the solve, nnz(L) and the assembly: the refinement's factorizations set a
floor under its own exponent.

    python -m bench.gauss_newton_factor [mesh ...] [--rounds 5]
"""

from __future__ import annotations

import os
import time

import numpy as np

import solver
from bench.common import load_bench_mesh, meshes_and_rounds, scaling_exponent
from solver.linalg import pardiso
from solver.mesh.topology import build_topology
from solver.refine import DEFORM_ANGLE_WEIGHT, FormTargets, Handles, Refiner


def gauss_newton_matrix(name: str):
    """The damped upper-triangle Gauss-Newton matrix (values, ia, ja) and a gradient of a
    deformation of mesh ``name`` (50 fixed vertices, every other vertex moved by 1e-3 of
    the mean edge), as the refinement factorizes it; and the median seconds of assembling
    the matrix with the gradient, and the gradient alone."""
    V, F = load_bench_mesh(name)
    forms = solver.fundamental_forms(V, F)
    refiner = Refiner(FormTargets(build_topology(F, len(V)), forms.lengths, forms.angles,
                                  angle_weight=DEFORM_ANGLE_WEIGHT),
                      Handles(fixed=np.arange(50)))
    X = V + 1e-3 * forms.lengths.mean() * np.random.default_rng(0).normal(size=V.shape)
    _, H, g = refiner.system.normal_equations(X)
    values = H.data.copy()
    values[refiner.system.diagonal_positions] *= 1.0 + 1e-9
    assembly = [median_seconds(refiner.system.normal_equations, X, matrix=matrix)
                for matrix in (True, False)]
    return values, H.indptr.astype(np.int32), H.indices.astype(np.int32), g, len(F), assembly


def median_seconds(fn, *args, repeats: int = 15, **kw) -> float:
    """Median wall-clock seconds of ``fn(*args, **kw)`` over ``repeats`` calls."""
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn(*args, **kw)
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def one_round(values, ia, ja, g, groups, solves: int = 9) -> dict[str, list[float]]:
    """Seconds of analysis, factorization and the median one-column solve, and nnz(L), of
    each variant."""
    mkl = pardiso.load_mkl()
    out = {}
    variants = (("PARDISO's ordering", False, False), ("groups hint", True, False),
                ("single precision", False, True))
    for label, hinted, single in variants:
        t0 = time.perf_counter()
        perm = pardiso.group_ordering(mkl, ia, ja, groups) if hinted else None
        handle = pardiso.PardisoHandle(mkl, len(ia) - 1, perm, single=single)
        a = values.astype(np.float32 if single else np.float64)
        assert handle.call(11, a, ia, ja) == 0
        t1 = time.perf_counter()
        assert handle.call(22, a, ia, ja) == 0
        t2 = time.perf_counter()
        b = np.asfortranarray(g[:, None], dtype=a.dtype)
        x = np.zeros_like(b)
        times = []
        for _ in range(solves):
            t = time.perf_counter()
            handle.call(33, a, ia, ja, b, x, 1)
            times.append(time.perf_counter() - t)
        out[label] = [t1 - t0, t2 - t1, float(np.median(times)), float(handle.iparm[17])]
        handle.release()
    return out


def main() -> None:
    args = meshes_and_rounds(__doc__, ["rocker-arm.obj", "beetle.off"], rounds=5)
    print(f"load average {os.getloadavg()[0]:.1f}; MKL threads "
          f"{os.environ.get('MKL_NUM_THREADS', 'default')}\n")
    print("| mesh | faces | unknowns | variant | analysis ms | factorization ms "
          "| solve ms | nnz(L) |")
    print("|---|---|---|---|---|---|---|---|")
    assemblies, own, single = [], [], []
    for name in args.meshes:
        values, ia, ja, g, faces, assembly = gauss_newton_matrix(name)
        assemblies.append((name, faces, assembly))
        groups = np.repeat(np.arange((len(ia) - 1) // 3), 3)
        rounds = [one_round(values, ia, ja, g, groups) for _ in range(args.rounds)]
        for label in rounds[0]:
            medians = np.median([r[label] for r in rounds], axis=0)
            print(f"| {name} | {faces} | {len(ia) - 1} | {label} | {1000 * medians[0]:.0f} | "
                  f"{1000 * medians[1]:.0f} | {1000 * medians[2]:.1f} | {medians[3]:.0f} |")
            if label == "PARDISO's ordering":
                own.append((faces, medians[1], medians[2], medians[3]))
            elif label == "single precision":
                single.append(medians[1])
    print("\n| mesh | faces | assembly of matrix + gradient ms | gradient alone ms |")
    print("|---|---|---|---|")
    for name, faces, (full, gradient) in assemblies:
        print(f"| {name} | {faces} | {1000 * full:.1f} | {1000 * gradient:.1f} |")
    if len(own) > 1:
        faces = [row[0] for row in own]
        print("\nScaling exponents over faces (PARDISO's ordering): factorization "
              f"{scaling_exponent(faces, [row[1] for row in own]):.2f}, solve "
              f"{scaling_exponent(faces, [row[2] for row in own]):.2f}, nnz(L) "
              f"{scaling_exponent(faces, [row[3] for row in own]):.2f}, assembly "
              f"{scaling_exponent(faces, [a[2][0] for a in assemblies]):.2f}; "
              f"single-precision factorization {scaling_exponent(faces, single):.2f}")


if __name__ == "__main__":
    main()
