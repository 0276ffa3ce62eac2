"""Textured mesh files: a mesh with its atlas (a flattening's ``texcoords``) as OBJ or GLB.

OBJ keeps the file's vertices (``v``, in order) and writes one ``vt`` per uv index, faces as
``f v/vt``: a seam vertex is one ``v`` with one ``vt`` per chart it borders, the map back to
the file's vertices being the ``v`` index itself. GLB (the one glTF writer,
:mod:`solver.mesh.gltf`, as the service's flattening answers) has one vertex per uv index (seam
vertices duplicated, positions ``vertices[uv_vertex]``) and the atlas as ``TEXCOORD_0``
(glTF's v runs down the image: written as 1 - v).
"""

from __future__ import annotations

import numpy as np

from ..core.errors import ShapeMismatchError
from .formats import text_rows
from .gltf import encode_gltf


def _check(faces: np.ndarray, texcoords: np.ndarray, uv_faces: np.ndarray) -> None:
    if uv_faces.shape != faces.shape:
        raise ShapeMismatchError(f"expected shape {faces.shape}, got {uv_faces.shape}",
                                 field="uv_faces")
    if texcoords.ndim != 2 or texcoords.shape[1] != 2:
        raise ShapeMismatchError(f"expected shape (k, 2), got {texcoords.shape}",
                                 field="texcoords")


def textured_obj(vertices: np.ndarray, faces: np.ndarray, texcoords: np.ndarray,
                 uv_faces: np.ndarray) -> bytes:
    """OBJ text: ``v`` (n), ``vt`` (k), ``f v/vt`` (m), 1-based.

    Args:
        vertices: (n, 3) float64; faces: (m, 3) int; texcoords: (k, 2) float64 (v up);
        uv_faces: (m, 3) int into ``texcoords``.

    Example:
        >>> text = textured_obj(np.eye(3), np.array([[0, 1, 2]]), np.eye(3)[:, :2],
        ...                     np.array([[2, 1, 0]])).decode()
        >>> text.splitlines()[-1]
        'f 1/3 2/2 3/1'
    """
    V, F = np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)
    T, U = np.asarray(texcoords, dtype=np.float64), np.asarray(uv_faces, dtype=np.int64)
    _check(F, T, U)
    corners = np.stack([F + 1, U + 1], axis=2).reshape(len(F), 6)
    return ("# written by fundamental-forms-service (uv atlas)\n" + text_rows(V, "%.17g", "v ")
            + text_rows(T, "%.17g", "vt ") + text_rows(corners, "%d/%d %d/%d %d/%d", "f ")
            ).encode("ascii")


def textured_glb(vertices: np.ndarray, texcoords: np.ndarray, uv_faces: np.ndarray,
                 uv_vertex: np.ndarray) -> bytes:
    """GLB: one vertex per uv index at ``vertices[uv_vertex]``, ``TEXCOORD_0`` the atlas."""
    V = np.asarray(vertices, dtype=np.float64)[np.asarray(uv_vertex, dtype=np.int64)]
    return encode_gltf(V, np.asarray(uv_faces, dtype=np.int64), kind="glb",
                       texcoords=np.asarray(texcoords, dtype=np.float64))


__all__ = ["textured_glb", "textured_obj"]
