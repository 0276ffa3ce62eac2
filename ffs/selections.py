"""Handle sets in the Botsch-Sorkine format (*On linear variational surface deformation
methods*, 2008; the ``.sel`` / ``.def`` files beside its benchmark meshes), read for
``ffs deform --handles NAME.sel`` (or ``NAME.def``; the other file is the one with the same
stem beside it).

* ``NAME.sel``: one integer per mesh vertex, in vertex order (``#`` comments): ``0`` fixed
  (stays at rest), ``1`` free (the deformable region), ``2`` handle.
* ``NAME.def``: the 4x4 affine transform (16 numbers, row-major; ``#`` comments) that moves
  the handle vertices.

They become the API's deformation: the handle vertices with their transformed positions as
``handles``, the free and handle vertices as ``roi`` (the fixed ones stay at rest), and,
where the transform's 3x3 part is a rotation, the faces whose three corners are handle
vertices as one orientation handle with that rotation.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

FIXED, FREE, HANDLE = 0, 1, 2
"""The ``.sel`` values."""
SELECTION_SUFFIXES = (".sel", ".def")
ROTATION_TOLERANCE = 1e-4
"""Largest |R^T R - I| entry of a ``.def``'s 3x3 part read as a rotation (the files print
six decimals); it is then replaced by its nearest rotation."""


def is_selection_file(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` names a ``.sel`` or ``.def`` file."""
    return Path(path).suffix.lower() in SELECTION_SUFFIXES


def selection_pair(path: str | os.PathLike[str]) -> tuple[Path, Path]:
    """The ``.sel`` and ``.def`` files of the pair ``path`` (either of them) belongs to."""
    base = Path(path)
    return base.with_suffix(".sel"), base.with_suffix(".def")


def _numbers(path: Path) -> np.ndarray:
    from ffs.files import InputFileError

    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except FileNotFoundError:
        raise InputFileError(path, "no such file (a .sel needs its .def beside it, with the "
                             "same name, and the other way round)") from None
    except OSError as exc:
        raise InputFileError(path, exc.strerror or str(exc)) from None
    tokens = [t for line in lines for t in line.split("#", 1)[0].split()]
    try:
        return np.asarray([float(t) for t in tokens], dtype=np.float64)
    except ValueError:
        bad = next(t for t in tokens if not _is_number(t))
        raise InputFileError(path, f"{bad!r} is not a number") from None


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def read_selection(path: str | os.PathLike[str], vertices: np.ndarray, faces: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], np.ndarray | None,
                              np.ndarray]:
    """The deformation a ``.sel`` / ``.def`` pair describes on a mesh.

    Args:
        path: The ``.sel`` or the ``.def`` file.
        vertices: (n, 3) float64 rest positions of the mesh.
        faces: (m, 3) int64.

    Returns:
        ``(handle vertices (h,), their targets (h, 3), rotation face groups, rotations
        (g, 3, 3) or None, roi (r,))``.

    Raises:
        ffs.files.InputFileError: A count that is not the mesh's, a value that is not 0, 1
            or 2, no handle vertex, a transform that is not 4x4 affine.
    """
    from ffs.files import InputFileError
    from solver.mesh.rotations import is_rotation, nearest_rotation

    sel_path, def_path = selection_pair(path)
    selection = _numbers(sel_path)
    if len(selection) != len(vertices):
        raise InputFileError(sel_path, f"{len(selection)} values for a mesh of "
                             f"{len(vertices)} vertices (one per vertex: 0 fixed, 1 free, "
                             "2 handle)")
    bad = np.flatnonzero(~np.isin(selection, (FIXED, FREE, HANDLE)))
    if len(bad):
        raise InputFileError(sel_path, f"{selection[bad[0]]:g} is not 0 (fixed), 1 (free) or "
                             "2 (handle)", field="vertex", index=int(bad[0]))
    status = selection.astype(np.int64)
    handles = np.flatnonzero(status == HANDLE)
    if not len(handles):
        raise InputFileError(sel_path, "no handle vertex (value 2)")
    matrix = _numbers(def_path)
    if matrix.shape != (16,):
        raise InputFileError(def_path, f"{len(matrix)} numbers; a 4x4 transform has 16")
    transform = matrix.reshape(4, 4)
    if not np.allclose(transform[3], [0, 0, 0, 1], atol=1e-9):
        raise InputFileError(def_path, "the last row of the transform must be 0 0 0 1 "
                             "(affine)")
    linear, shift = transform[:3, :3], transform[:3, 3]
    targets = vertices[handles] @ linear.T + shift
    roi = np.flatnonzero(status != FIXED)
    groups: list[np.ndarray] = []
    rotations = None
    if is_rotation(linear, ROTATION_TOLERANCE):
        handle_faces = np.flatnonzero((status[faces] == HANDLE).all(axis=1))
        if len(handle_faces):
            groups, rotations = [handle_faces], nearest_rotation(linear[None])
    return handles, targets, groups, rotations, roi
