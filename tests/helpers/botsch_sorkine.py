"""The Botsch-Sorkine 2008 deformation cases: mesh, selection (.sel) and handle transform (.def)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh


@dataclass
class DeformationCase:
    name: str
    vertices: np.ndarray
    faces: np.ndarray
    selection: np.ndarray   # (n,) 0 fixed, 1 free, 2 handle
    transform: np.ndarray   # (4, 4) applied to the handle

    @property
    def handles(self) -> np.ndarray:
        return np.flatnonzero(self.selection == 2)

    @property
    def fixed(self) -> np.ndarray:
        return np.flatnonzero(self.selection == 0)

    @property
    def roi(self) -> np.ndarray:
        return np.flatnonzero(self.selection != 0)

    def handle_targets(self) -> np.ndarray:
        """(h, 3) handle positions after the transform."""
        P = self.vertices[self.handles]
        return P @ self.transform[:3, :3].T + self.transform[:3, 3]

    def handle_faces(self) -> np.ndarray:
        """Faces whose three vertices are all handle vertices (orientation handle)."""
        return np.flatnonzero((self.selection[self.faces] == 2).all(axis=1))

    def fixed_faces(self) -> np.ndarray:
        return np.flatnonzero((self.selection[self.faces] == 0).all(axis=1))


def load_case(folder: Path, name: str) -> DeformationCase:
    mesh = trimesh.load(folder / f"{name}.off", process=False)
    selection = np.loadtxt(folder / f"{name}.sel", comments="#").astype(np.int64)
    transform = np.loadtxt(folder / f"{name}.def", comments="#").reshape(4, 4)
    return DeformationCase(name, np.asarray(mesh.vertices, dtype=np.float64),
                           np.asarray(mesh.faces, dtype=np.int64), selection, transform)
