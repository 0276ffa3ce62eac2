"""Helpers of the session tests: reference solves computed like a worker computes them."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from tests.helpers import REPO

_REFERENCE = """
import sys
import numpy as np
import solver
data = np.load(sys.argv[1], allow_pickle=True)
groups = list(data["groups"]) if len(data["groups"]) else None
deformer = solver.Deformer(data["V"], data["F"], data["handles"], rotation_handles=groups,
                           backend=str(data["backend"]))
rotations = data["rotations"]
out = [deformer.solve(p, rotations[i] if len(rotations) else None)
       for i, p in enumerate(data["targets"])]
np.save(sys.argv[2], np.stack(out))
"""


def reference_solves(V: np.ndarray, F: np.ndarray, handles: Any, targets: np.ndarray, *,
                     groups: list[Any] | None = None, rotations: np.ndarray | None = None,
                     backend: str = "auto", threads: int = 1) -> np.ndarray:
    """``Deformer(V, F, handles).solve(t)`` for each target set, in a fresh process with
    ``threads`` BLAS/MKL threads set at start-up -- exactly how the session processes and
    the Dask workers run (MKL's results depend on how its thread count was set)."""
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads),
           "OPENBLAS_NUM_THREADS": str(threads), "PYTHONPATH": str(REPO)}
    with tempfile.TemporaryDirectory() as tmp:
        inp, out = Path(tmp) / "in.npz", Path(tmp) / "out.npy"
        group_array = np.empty(len(groups or []), dtype=object)
        for i, g in enumerate(groups or []):
            group_array[i] = np.asarray(g, dtype=np.int64)
        np.savez(inp, V=V, F=F, handles=np.asarray(handles, dtype=np.int64),
                 targets=np.asarray(targets, dtype=np.float64), groups=group_array,
                 rotations=np.zeros((0, 0, 3, 3)) if rotations is None else rotations,
                 backend=np.array(backend))
        subprocess.run([sys.executable, "-c", _REFERENCE, str(inp), str(out)], env=env,
                       check=True, timeout=300, cwd=REPO)
        return np.load(out)


def rotation_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


_PROGRESSIVE = """
import sys
import numpy as np
import solver
data = np.load(sys.argv[1])
deformer = solver.Deformer(data["V"], data["F"], data["handles"], refine=True)
deformer.solve(refine=False)
linear, refined = [], []
for p in data["targets"]:
    linear.append(deformer.solve(p, refine=False))
    refined.append(deformer.refine_last(float(data["slice"])))
    assert deformer.last_report.get("converged"), deformer.last_report
np.save(sys.argv[2], np.stack([np.stack(linear), np.stack(refined)]))
"""


def reference_progressive(V: np.ndarray, F: np.ndarray, handles: Any, targets: np.ndarray, *,
                          slice_seconds: float, threads: int = 1
                          ) -> tuple[np.ndarray, np.ndarray]:
    """(linear, refined) shapes (k, n, 3) of a progressive session's drags, each refined to
    convergence before the next: ``Deformer(V, F, handles, refine=True)``, then per target
    ``solve(p, refine=False)`` and ``refine_last(slice_seconds)`` (one slice, as a session
    whose FFS_SESSION_REFINE_SLICE exceeds the refinement), in a fresh process with
    ``threads`` BLAS/MKL threads, like :func:`reference_solves`."""
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads),
           "OPENBLAS_NUM_THREADS": str(threads), "PYTHONPATH": str(REPO)}
    with tempfile.TemporaryDirectory() as tmp:
        inp, out = Path(tmp) / "in.npz", Path(tmp) / "out.npy"
        np.savez(inp, V=V, F=F, handles=np.asarray(handles, dtype=np.int64),
                 targets=np.asarray(targets, dtype=np.float64), slice=slice_seconds)
        subprocess.run([sys.executable, "-c", _PROGRESSIVE, str(inp), str(out)], env=env,
                       check=True, timeout=300, cwd=REPO)
        linear, refined = np.load(out)
        return linear, refined
