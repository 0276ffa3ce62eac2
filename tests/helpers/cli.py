"""What the command-line tests of meshes as they come share: where ``ffs`` runs, and a
deformation of a file by three random handles through ``ffs deform``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from solver.mesh.io import load_mesh_file
from tests.helpers.real_meshes import diagonal


def where(server: str, remote: bool) -> list[str]:
    """``ffs`` options that run on ``server`` when ``remote``, in-process otherwise."""
    return ["--server", server] if remote else []


def deform_by_three_handles(ffs: Any, workdir: Path, name: str, V: np.ndarray, F: np.ndarray,
                            options: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """``ffs deform name.off`` (written already) with three of its vertices moved by 5% of the
    diagonal (seed 4); checks that it succeeded and hit its handles to 1e-6 of the diagonal.
    Returns the deformed file's vertices and faces."""
    rng = np.random.default_rng(4)
    handles = rng.choice(np.unique(F), 3, replace=False)
    targets = V[handles] + rng.normal(0, 0.05 * diagonal(V), (3, 3))
    (workdir / "handles.json").write_text(json.dumps(
        [{"vertex": int(v), "position": p} for v, p in zip(handles, targets.tolist(),
                                                          strict=True)]))
    done = ffs("deform", f"{name}.off", "--handles", "handles.json", "-o", f"{name}-d.ply",
               "-q", *options)
    assert done.returncode == 0, done.stderr
    moved, faces = load_mesh_file(workdir / f"{name}-d.ply")
    np.testing.assert_allclose(moved[handles], targets, atol=1e-6 * diagonal(V))
    return moved, faces
