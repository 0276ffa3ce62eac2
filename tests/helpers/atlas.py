"""Procedural closed surfaces of known genus and an independent check of an atlas."""

from __future__ import annotations

import numpy as np
from PIL import Image, ImageChops, ImageDraw


def voxel_surface(solid: np.ndarray, smoothing: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """The boundary of a union of unit voxels (``solid`` (X, Y, Z) bool), triangulated,
    outward, then Laplacian-smoothed ``smoothing`` times (vertices only: topology kept).

    A slab with k through-holes (voxels meeting face to face) is a closed surface of
    genus k.
    """
    padded = np.pad(solid, 1)
    quads = []
    corners = {  # axis, side -> the quad's corner offsets, counter-clockwise from outside
        (0, 1): [(1, 0, 0), (1, 1, 0), (1, 1, 1), (1, 0, 1)],
        (0, -1): [(0, 0, 0), (0, 0, 1), (0, 1, 1), (0, 1, 0)],
        (1, 1): [(0, 1, 0), (0, 1, 1), (1, 1, 1), (1, 1, 0)],
        (1, -1): [(0, 0, 0), (1, 0, 0), (1, 0, 1), (0, 0, 1)],
        (2, 1): [(0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)],
        (2, -1): [(0, 0, 0), (0, 1, 0), (1, 1, 0), (1, 0, 0)],
    }
    for (axis, side), offsets in corners.items():
        neighbour = np.roll(padded, -side, axis=axis)
        cells = np.argwhere(padded & ~neighbour)
        quads.append(np.stack([cells + np.array(offset) for offset in offsets], axis=1))
    points = np.concatenate(quads).reshape(-1, 3)                      # (4 q, 3)
    unique, index = np.unique(points, axis=0, return_inverse=True)
    q = index.reshape(-1, 4)
    faces = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    vertices = unique.astype(np.float64)
    for _ in range(smoothing):
        total = np.zeros_like(vertices)
        count = np.zeros(len(vertices))
        for a, b in ((0, 1), (1, 2), (2, 0)):
            np.add.at(total, faces[:, a], vertices[faces[:, b]])
            np.add.at(count, faces[:, a], 1)
        vertices = 0.5 * vertices + 0.5 * total / count[:, None]
    return vertices, faces


def genus_two() -> tuple[np.ndarray, np.ndarray]:
    """A closed genus-2 surface: a 7 x 3 x 1 slab with two square through-holes."""
    solid = np.ones((7, 3, 1), dtype=bool)
    solid[1:3, 1, :] = False
    solid[4:6, 1, :] = False
    return voxel_surface(np.repeat(np.repeat(solid, 2, axis=0), 2, axis=1))


def euler_genus(vertices: np.ndarray, faces: np.ndarray) -> int:
    """Genus of a closed connected surface from V - E + F."""
    edges = np.unique(np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]],
                                              faces[:, [2, 0]]]), axis=1), axis=0)
    chi = len(np.unique(faces)) - len(edges) + len(faces)
    return (2 - chi) // 2


def overlapping_pixels(texcoords: np.ndarray, uv_faces: np.ndarray, face_chart: np.ndarray,
                       size: int = 1024) -> int:
    """Pixels of a ``size``² image covered by two charts, each chart drawn by PIL (not the
    solver's rasterizer) with its triangles shrunk by 1% towards their centroids, plus
    pixels covered twice inside one chart (a chart's pixel count against its drawn area is
    checked by the caller through flips; here charts are drawn separately and added)."""
    total = Image.new("L", (size, size), 0)
    for chart in np.unique(face_chart):
        image = Image.new("L", (size, size), 0)
        draw = ImageDraw.Draw(image)
        triangles = texcoords[uv_faces[face_chart == chart]] * size
        centre = triangles.mean(axis=1, keepdims=True)
        triangles = centre + 0.99 * (triangles - centre)
        for triangle in triangles:
            draw.polygon([tuple(p) for p in triangle], fill=1)
        total = ImageChops.add(total, image)
    return int((np.asarray(total) > 1).sum())
