"""Where each connected component of a mesh sits: its rigid placement.

Forms (lengths and dihedral angles) fix each connected component only up to a rigid motion,
so a multi-part model rebuilt from its forms alone has its parts anywhere. The placement of a
component is the pose of one face of it, its *anchor* (the component's largest face, the
lowest-numbered among equals): the position of the anchor's first vertex ``faces[t][0]``
and its frame (columns ``b1``, along ``faces[t][0] -> faces[t][1]``; ``b2``, in-plane;
``b3``, the unit normal; the frame convention of the README). :func:`placement_of`
measures it on a mesh; :func:`apply_placement` moves each component of a reconstruction
rigidly so that its anchor face has that pose, which makes a round trip of exact forms
exact as a whole mesh.

Example:
    Two triangles far apart, rebuilt at the origin, put back where they were:

    >>> import numpy as np
    >>> from solver.mesh.placement import apply_placement, placement_of
    >>> F = np.array([[0, 1, 2], [3, 4, 5]])
    >>> V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5], [5, 6, 5], [5, 5, 6.0]])
    >>> placement = placement_of(V, F)
    >>> placement.faces.tolist()
    [0, 1]
    >>> moved = V - V[[0, 0, 0, 3, 3, 3]]  # both parts at the origin
    >>> bool(np.allclose(apply_placement(moved, F, placement), V))
    True
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Final

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike
from scipy.sparse.csgraph import connected_components

from ..core.errors import ConstraintError
from ..core.serialization import JsonDataclass
from ..core.validation import as_indices, as_points
from .alignment import kabsch
from .rotations import nearest_rotation


@dataclass
class Placement(JsonDataclass):
    """The rigid placement of each connected component (c components).

    Attributes:
        faces: (c,) int64 anchor face of each component (its largest face: :func:`placement_of`).
        origins: (c, 3) float64 position of each anchor face's first vertex.
        frames: (c, 3, 3) float64 rotation whose columns are the anchor face's b1, b2, b3.
    """

    faces: np.ndarray
    origins: np.ndarray
    frames: np.ndarray

    _array_fields: ClassVar[dict[str, Any]] = {
        "faces": np.int64, "origins": np.float64, "frames": np.float64}

    def subset(self, keep: np.ndarray) -> Placement:
        """The entries where ``keep`` (c,) bool is True."""
        return Placement(self.faces[keep], self.origins[keep], self.frames[keep])

    @classmethod
    def coerce(cls, value: Placement | dict[str, Any] | None, n_faces: int
               ) -> Placement | None:
        """A placement given by a caller (dict or instance), validated; None stays None.

        Raises:
            ShapeMismatchError, IndexOutOfRangeError, NonFiniteValueError: malformed.
            ConstraintError: a frame that is not a rotation (det <= 0 or far from
                orthonormal).
        """
        if value is None:
            return None
        data = value.to_dict() if isinstance(value, Placement) else dict(value)
        faces = as_indices(data.get("faces", []), "placement.faces", upper=n_faces)
        origins = as_points(data.get("origins", []), "placement.origins")
        frames = np.asarray(data.get("frames", []), dtype=np.float64).reshape(-1, 3, 3)
        if not (len(faces) == len(origins) == len(frames)):
            raise ConstraintError(
                f"placement.faces, origins and frames must have one entry per component: got "
                f"{len(faces)}, {len(origins)} and {len(frames)}", field="placement")
        if not np.isfinite(frames).all():
            raise ConstraintError("a frame is not finite", field="placement.frames")
        off = np.abs(np.swapaxes(frames, 1, 2) @ frames - np.eye(3)).reshape(len(frames), -1)
        bad = np.flatnonzero((off.max(axis=1, initial=0) > 1e-6)
                             | (np.linalg.det(frames) <= 0))
        if len(bad):
            raise ConstraintError("not a rotation matrix (orthonormal with det +1)",
                                  field="placement.frames", index=int(bad[0]))
        return cls(faces=faces, origins=origins, frames=nearest_rotation(frames))


def face_frames(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Frames (k, 3, 3) of faces (k, 3) from positions: columns b1, b2, b3 (README).

    A face of zero area (collinear or coincident corners: a component made only of such
    faces has its anchor among them) still gets a rotation: b1 along the edge from corner 0
    to corner 1 (to corner 2 when corners 0 and 1 coincide; ``e_x`` when all three do) and
    b3 a unit vector perpendicular to b1 (across the axis b1 leans on least); the same positions
    give the same frame, so a file's frame and the rebuilt one agree up to a turn about b1,
    which moves nothing of a collinear component.

    Args:
        vertices: (n, 3) float64.
        faces: (k, 3) int64.

    Returns:
        (k, 3, 3) float64 rotations.

    Example:
        >>> V = np.array([[0, 0, 0], [2, 2, 0], [1, 1, 0.]])
        >>> frame = face_frames(V, np.array([[0, 1, 2]]))[0]
        >>> bool(np.allclose(frame.T @ frame, np.eye(3))), round(float(np.linalg.det(frame)), 12)
        (True, 1.0)
    """
    p0, p1, p2 = (vertices[faces[:, c]] for c in range(3))
    e1, e2 = p1 - p0, p2 - p0
    b3 = np.cross(e1, e2)
    scale = np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1)
    flat = np.linalg.norm(b3, axis=1) <= DEGENERATE_AREA * scale
    b1 = np.where((np.linalg.norm(e1, axis=1) == 0)[:, None] & flat[:, None], e2, e1)
    length = np.linalg.norm(b1, axis=1)
    b1 = np.where(length[:, None] > 0, b1 / np.maximum(length, 1e-300)[:, None], [1.0, 0, 0])
    if flat.any():  # any unit vector perpendicular to b1, chosen by b1 alone
        axis = np.eye(3)[np.argmin(np.abs(b1[flat]), axis=1)]
        b3[flat] = np.cross(b1[flat], axis)
    b3 /= np.maximum(np.linalg.norm(b3, axis=1), 1e-300)[:, None]
    return np.stack([b1, np.cross(b3, b1), b3], axis=2)


DEGENERATE_AREA: Final = 1e-14
"""A face whose doubled area is at most this times the product of its two edges from
corner 0 has no normal to build a frame on (:func:`face_frames`; per face, where
:data:`solver.mesh.forms.ZERO_AREA`, relative to the mesh's longest edge, decides which
faces take a neighbour's normal in the forms)."""


def face_components(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Connected components through shared vertices.

    Returns:
        ``(vertex_component, face_component)``: (n,) and (m,) int64.
    """
    m = len(faces)
    rows = np.repeat(np.arange(m), 3)
    graph = sp.coo_matrix((np.ones(3 * m), (rows, faces.ravel())), shape=(m, n_vertices))
    graph = sp.bmat([[None, graph], [graph.T, None]])
    _, labels = connected_components(graph, directed=False)
    return labels[m:].astype(np.int64), labels[:m].astype(np.int64)


def placement_of(vertices: ArrayLike, faces: ArrayLike,
                 face_component: np.ndarray | None = None) -> Placement:
    """The placement of every component of a mesh (anchor: its face of largest area, the
    lowest-numbered among equals: a zero-area face, issue 40, has no frame of its own).

    Args:
        vertices: (n, 3) float.
        faces: (m, 3) int.
        face_component: optional (m,) int64 component of each face, when the caller has
            it (:attr:`solver.mesh.topology.MeshTopology.face_component`).

    Returns:
        :class:`Placement`, components in the order of their anchor faces.
    """
    V = as_points(vertices, "vertices")
    F = np.asarray(faces, dtype=np.int64)
    if face_component is None:
        _, face_component = face_components(F, len(V))
    area = np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    order = np.lexsort((np.arange(len(F)), -area, face_component))
    _, first = np.unique(face_component[order], return_index=True)
    anchors = np.sort(order[first])
    return Placement(faces=anchors.astype(np.int64), origins=V[F[anchors, 0]].copy(),
                     frames=face_frames(V, F[anchors]))


def apply_placement(vertices: np.ndarray, faces: np.ndarray, placement: Placement,
                    keep: np.ndarray | None = None, frames: np.ndarray | None = None,
                    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Move each component rigidly so that its anchor face has the placement's pose.

    Args:
        vertices: (n, 3) float64 a reconstruction.
        faces: (m, 3) int64 its faces.
        placement: :class:`Placement` (at most one anchor per component).
        keep: optional (c',) int64 face components not to move (e.g. constrained ones).
        frames: optional (m, 3, 3) face frames to rotate with their components.

    Returns:
        (n, 3) float64; components without an anchor (and kept ones) are unchanged; with
        ``frames``, also the (m, 3, 3) rotated frames.

    Raises:
        ConstraintError: two anchors in one component.
    """
    vertex_component, face_component = face_components(faces, len(vertices))
    n_comp = int(max(vertex_component.max(initial=-1), face_component.max(initial=-1))) + 1
    anchor_component = face_component[placement.faces]
    unique, first = np.unique(anchor_component, return_index=True)
    if len(unique) < len(anchor_component):
        twice = np.setdiff1d(np.arange(len(anchor_component)), first)[0]
        raise ConstraintError(
            f"placement.faces[{int(twice)}] (face {int(placement.faces[twice])}) is in a "
            "component that already has an anchor", field="placement.faces", index=int(twice))
    rotation = np.tile(np.eye(3), (n_comp, 1, 1))
    shift_from = np.zeros((n_comp, 3))
    shift_to = np.zeros((n_comp, 3))
    move = np.ones(len(anchor_component), dtype=bool)
    if keep is not None:
        move &= ~np.isin(anchor_component, keep)
    comp = anchor_component[move]
    anchor_faces = faces[placement.faces[move]]
    rebuilt = face_frames(vertices, anchor_faces)
    rotation[comp] = placement.frames[move] @ np.swapaxes(rebuilt, 1, 2)
    shift_from[comp] = vertices[anchor_faces[:, 0]]
    shift_to[comp] = placement.origins[move]
    c = vertex_component
    local = vertices - shift_from[c]
    placed = np.einsum("kij,kj->ki", rotation[c], local) + shift_to[c]
    if frames is None:
        return placed
    return placed, rotation[face_component] @ frames


def align_components(source: np.ndarray, target: np.ndarray,
                     vertex_component: np.ndarray) -> np.ndarray:
    """Each component of ``source`` moved rigidly (rotation + translation, Kabsch) onto the
    same vertices of ``target``: parts keep their places (a blend, a reconstruction).

    Args:
        source, target: (n, 3) float64.
        vertex_component: (n,) int64 component of each vertex.

    Returns:
        (n, 3) float64.

    Example:
        >>> import numpy as np
        >>> X = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0], [0, 0, 1.0]])
        >>> Y = X + np.array([[0, 0, 5]] * 3 + [[7, 0, 0]] * 2)  # each part its own way
        >>> bool(np.allclose(align_components(X, Y, np.array([0, 0, 0, 1, 1])), Y))
        True
    """
    c = np.asarray(vertex_component, dtype=np.int64)
    rotations, source_centers, target_centers = kabsch(source, target, c)
    if len(rotations) == 1:  # one part: no per-vertex gather of its rotation
        return (np.einsum("ij,vj->vi", rotations[0], source - source_centers[0])
                + target_centers[0])
    return (np.einsum("vij,vj->vi", rotations[c], source - source_centers[c])
            + target_centers[c])


SIDE_BY_SIDE_GAP = 0.1
"""The gap between components laid out side by side, relative to the largest bounding-box
diagonal (:func:`side_by_side`'s default; :mod:`solver.answer_map` differentiates it)."""


def side_by_side(vertices: np.ndarray, vertex_component: np.ndarray,
                 components: np.ndarray, gap_ratio: float = SIDE_BY_SIDE_GAP) -> np.ndarray:
    """Components laid out along +x without overlap: the first of ``components`` stays, each
    next one starts ``gap`` beyond the previous one's largest x (``gap``: ``gap_ratio``
    times the largest bounding-box diagonal); y and z are untouched. For a reconstruction
    without placement, whose components would otherwise all sit at the origin.

    Args:
        vertices: (n, 3) float64.
        vertex_component: (n,) int64.
        components: (k,) int64 the components to lay out, in order.
        gap_ratio: the gap relative to the largest diagonal.

    Returns:
        (n, 3) float64.

    Example:
        >>> import numpy as np
        >>> V = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 0], [2, 0, 0.0]])
        >>> side_by_side(V, np.array([0, 0, 1, 1]), np.array([0, 1]))[:, 0].tolist()
        [0.0, 1.0, 1.2, 3.2]
    """
    components = np.asarray(components, dtype=np.int64)
    if len(components) < 2:
        return vertices
    k = int(vertex_component.max()) + 1
    low = np.full((k, 3), np.inf)
    high = np.full((k, 3), -np.inf)
    np.minimum.at(low, vertex_component, vertices)
    np.maximum.at(high, vertex_component, vertices)
    width = (high - low)[components, 0]
    gap = gap_ratio * float(np.linalg.norm(high - low, axis=1)[components].max())
    start = np.concatenate([[low[components[0], 0]],
                            low[components[0], 0] + np.cumsum(width + gap)[:-1]])
    shift = np.zeros(k)
    shift[components] = start - low[components, 0]
    out = vertices.copy()
    out[:, 0] += shift[vertex_component]
    return out
