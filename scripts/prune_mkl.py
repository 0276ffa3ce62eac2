"""Keep only the MKL libraries PARDISO loads; delete the rest of the MKL/oneAPI runtime.

Run by the Dockerfile's dependency stage with the Python that has ``pypardiso`` (and so the
``mkl``, ``intel-openmp``, ``tbb``, ... wheels) installed. Those wheels put ~1 GB of shared
libraries into ``<sys.prefix>/lib``; a PARDISO factorization maps a small part of them.

1. Measure: factorize and solve a 2D Laplacian (40 000 unknowns) with PARDISO, with MKL's
   default threading layer, and read ``/proc/self/maps``: the libraries from
   ``<sys.prefix>/lib`` mapped at that point are what PARDISO loads on this CPU.
2. Keep those plus :data:`ALSO_KEEP`, delete every other regular file directly in
   ``<sys.prefix>/lib`` (only the oneAPI wheels put files there).
3. Verify: a fresh process factorizes again from the pruned folder, maps exactly the same
   libraries (no fallback to another kernel) and gets the same solution (residual < 1e-8).

Why :data:`ALSO_KEEP`: MKL picks its compute kernel library by CPU. On AMD and other CPUs
without Intel's dispatch it loads ``libmkl_def`` and ``libmkl_vml_def``; on Intel CPUs with
AVX2 (and with ``MKL_ENABLE_INSTRUCTIONS=AVX2``, which the image sets, also on AVX-512 ones)
it loads ``libmkl_avx2`` and ``libmkl_vml_avx2``. Both pairs are kept whichever CPU builds
the image, so the image is the same and runs PARDISO on any x86-64 CPU.

Usage (exit status 1 when a check fails)::

    python scripts/prune_mkl.py            # measure, prune, verify
    python scripts/prune_mkl.py --measure  # print the libraries PARDISO maps, change nothing
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

LIB = Path(sys.prefix) / "lib"
ALSO_KEEP = frozenset({"libmkl_def.so.2", "libmkl_def.so.3", "libmkl_vml_def.so.2",
                       "libmkl_vml_def.so.3", "libmkl_avx2.so.2", "libmkl_avx2.so.3",
                       "libmkl_vml_avx2.so.2", "libmkl_vml_avx2.so.3"})

_PROBE = r"""
import json, sys
import numpy as np, scipy.sparse as sp, pypardiso
n = 200
lap = sp.diags([-1.0, 2.001, -1.0], [-1, 0, 1], shape=(n, n))
A = sp.csr_matrix(sp.kronsum(lap, lap))
b = np.ones(A.shape[0])
x = pypardiso.spsolve(A, b)
residual = float(np.linalg.norm(A @ x - b) / np.linalg.norm(b))
lib = sys.argv[1]
maps = {line.split()[-1] for line in open("/proc/self/maps") if len(line.split()) >= 6}
print(json.dumps({"residual": residual, "x": float(x.sum()),
                  "mapped": sorted(p.rsplit("/", 1)[1] for p in maps
                                   if p.rsplit("/", 1)[0] == lib and ".so" in p)}))
"""


def measure() -> dict:
    """Run one PARDISO factorization in a fresh process.

    Returns ``{"residual": float, "x": float (sum of the solution), "mapped": [file names
    in <sys.prefix>/lib mapped by that process]}``.
    """
    out = subprocess.run([sys.executable, "-c", _PROBE, str(LIB)], check=True,
                         capture_output=True, text=True).stdout
    return json.loads(out)


def prune(keep: set[str]) -> tuple[int, int]:
    """Delete the regular files of ``<sys.prefix>/lib`` not in ``keep``.

    Returns (files deleted, bytes freed).
    """
    count = freed = 0
    for path in sorted(LIB.iterdir()):
        if path.name in keep or path.is_dir() or not (path.is_file() or path.is_symlink()):
            continue
        freed += path.lstat().st_size
        path.unlink()
        count += 1
    return count, freed


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--measure", action="store_true",
                        help="only print what a PARDISO factorization maps")
    args = parser.parse_args()
    before = measure()
    print(f"prune_mkl: PARDISO maps {', '.join(before['mapped'])}")
    if args.measure:
        return 0
    keep = set(before["mapped"]) | {name for name in ALSO_KEEP if (LIB / name).is_file()}
    count, freed = prune(keep)
    print(f"prune_mkl: kept {', '.join(sorted(keep))}")
    print(f"prune_mkl: deleted {count} files, {freed / 2**20:.0f} MiB")
    after = measure()
    if (after["mapped"] != before["mapped"] or after["residual"] > 1e-8
            or before["residual"] > 1e-8
            or abs(after["x"] - before["x"]) > 1e-9 * abs(before["x"])):
        print(f"prune_mkl: FAILED after pruning: {after}", file=sys.stderr)
        return 1
    print(f"prune_mkl: PARDISO works after pruning (residual {after['residual']:.1e})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
