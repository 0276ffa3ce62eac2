"""Discrete fundamental forms: edge lengths (first form) and signed dihedral angles (second).

The dihedral angle of an interior edge is the signed angle between its two face normals, in
(-pi, pi], positive where the surface is convex (every edge of a sphere with outward normals is
positive); it is 0 on boundary edges. For edge ``[i, j]`` with face ``L`` left of ``i -> j`` and
face ``R`` on the other side, ``phi = atan2(((n_L x n_R) . e), n_L . n_R)`` with ``e`` the unit
vector from ``i`` to ``j``; this is the angle of ``R_x(phi)`` in the transition rotation of
Section 2.3 of the paper.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike

from ..core.errors import (
    DegenerateFaceError,
    EdgeMismatchError,
    NonFiniteValueError,
    NonPositiveLengthError,
    SolverInputError,
)
from ..core.serialization import JsonDataclass
from ..core.validation import as_indices, as_points, as_vector
from .manifold import manifold_topology
from .placement import Placement, placement_of
from .topology import MeshTopology, build_topology

ANGLE_SLACK = 1e-12
"""Angles this far beyond +-pi (radians) are accepted and clamped (rounding of pi)."""


def wrap_angles(angles: np.ndarray) -> tuple[np.ndarray, int]:
    """Dihedral angles mapped into (-pi, pi]: an angle is periodic (pi + x means -pi + x).

    Angles within :data:`ANGLE_SLACK` of -pi or pi are clamped to pi (rounding of pi) and
    not counted; every other finite angle outside (-pi, pi] is wrapped by a multiple of
    2 pi and counted.

    Args:
        angles: (E,) float64, finite.

    Returns:
        ``(wrapped, count)``: (E,) float64 in (-pi, pi] and how many were wrapped.

    Example:
        >>> import numpy as np
        >>> wrapped, count = wrap_angles(np.array([np.pi + 1e-3, -np.pi, 0.5, 7.0]))
        >>> wrapped.round(6).tolist(), count
        ([-3.140593, 3.141593, 0.5, 0.716815], 2)
    """
    near = (np.abs(angles) <= np.pi + ANGLE_SLACK) & (np.abs(angles) >= np.pi - ANGLE_SLACK)
    outside = ~near & ((angles <= -np.pi) | (angles > np.pi))
    turns = np.ceil((angles - np.pi) / (2 * np.pi))
    wrapped = np.where(outside, angles - 2 * np.pi * turns, angles)
    wrapped = np.where(near & (np.abs(angles) >= np.pi), np.pi, wrapped)
    wrapped = np.where(wrapped <= -np.pi, np.pi, wrapped)
    return wrapped, int(np.count_nonzero(outside))


@dataclass
class Forms(JsonDataclass):
    """Discrete fundamental forms of a mesh.

    Attributes:
        faces: (m, 3) int64.
        edges: (E, 2) int64, i < j, sorted lexicographically.
        lengths: (E,) float64 edge lengths (first fundamental form).
        angles: (E,) float64 signed dihedral angles in (-pi, pi], 0 on boundary edges.
        vertex_map: None for a manifold mesh; for a non-manifold one, whose forms are those
            of its manifold cut (:mod:`solver.mesh.manifold`; ``faces`` are the cut faces), the
            (n_cut,) int64 file vertex of each cut vertex.
        placement: the rigid placement of each connected component
            (:class:`solver.mesh.placement.Placement`), so that :func:`solver.reconstruct` puts
            every part where it was; None when not known.
        zero_area_faces: None, or the (k,) int64 faces of zero area (collinear corners)
            whose normal :func:`degenerate_normals` chose (informational: the solvers
            find such faces from the lengths, :func:`flat_faces`).
        weld_map: None, or for a mesh with vertices joined by zero-length edges
            (:mod:`solver.mesh.weld`) the (n,) int64 file vertex each file vertex was
            welded into (itself unless welded); ``vertex_map`` is then given too (names
            representatives only) and ``faces`` leave out the faces the weld collapsed.
        dropped_faces: None, or the (d,) int64 file faces left out of ``faces`` (they
            repeat a vertex once welded; informational).
    """

    faces: np.ndarray
    edges: np.ndarray
    lengths: np.ndarray
    angles: np.ndarray
    vertex_map: np.ndarray | None = None
    placement: Placement | None = None
    zero_area_faces: np.ndarray | None = None
    weld_map: np.ndarray | None = None
    dropped_faces: np.ndarray | None = None

    _array_fields: ClassVar[dict[str, Any]] = {
        "faces": np.int64, "edges": np.int64, "lengths": np.float64,
        "angles": np.float64, "vertex_map": np.int64, "zero_area_faces": np.int64,
        "weld_map": np.int64, "dropped_faces": np.int64,
    }
    _nested_fields: ClassVar[dict[str, Any]] = {"placement": Placement}


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals and areas of the faces.

    Args:
        vertices: (n, 3) float64.
        faces: (m, 3) int64, counter-clockwise seen from outside.

    Returns:
        ``(normals, areas)``: (m, 3) float64 unit normals (zero for a zero-area face) and
        (m,) float64 areas.
    """
    cross = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]],
                     vertices[faces[:, 2]] - vertices[faces[:, 0]])
    norm = np.linalg.norm(cross, axis=1)
    safe = np.where(norm > 0, norm, 1.0)
    return cross / safe[:, None], 0.5 * norm


def dihedral_angles(vertices: np.ndarray, topology: MeshTopology,
                    normals: np.ndarray) -> np.ndarray:
    """Signed dihedral angle of every edge (the module docstring defines its sign).

    Args:
        vertices: (n, 3) float64.
        topology: the mesh's connectivity.
        normals: (m, 3) float64 unit face normals (:func:`face_normals`).

    Returns:
        (E,) float64 angles in (-pi, pi], 0 on boundary edges.
    """
    angles = np.zeros(topology.n_edges)
    inner = topology.interior_edges
    left, right = topology.edge_faces[inner, 0], topology.edge_faces[inner, 1]
    i, j = topology.edges[inner, 0], topology.edges[inner, 1]
    direction = vertices[j] - vertices[i]
    direction /= np.linalg.norm(direction, axis=1)[:, None]
    n_l, n_r = normals[left], normals[right]
    sin = np.einsum("ij,ij->i", np.cross(n_l, n_r), direction)
    cos = np.einsum("ij,ij->i", n_l, n_r)
    phi = np.arctan2(sin, cos)
    angles[inner] = np.where(phi <= -np.pi, np.pi, phi)
    return angles


def fundamental_forms(vertices: ArrayLike, faces: ArrayLike, *, coincident: bool = True,
                      ) -> Forms:
    """Edge lengths and signed dihedral angles of a mesh.

    Args:
        vertices: (n, 3) float coordinates.
        faces: (m, 3) int, 0-based, counter-clockwise seen from outside.
        coincident: weld the vertices at one position (a seam an exporter split by normals
            or texture coordinates) too; False keeps such seams open.

    Vertices joined by zero-length edges (and, with ``coincident``, vertices at one
    position) are welded first and the faces that collapse dropped (:mod:`solver.mesh.weld`:
    ``weld_map``, ``dropped_faces``); faces written the wrong way round are turned
    (:mod:`solver.mesh.orientation`); a non-manifold mesh
    is cut into a manifold one (:mod:`solver.mesh.manifold`): the forms are those of the
    cut, ``faces`` are the cut faces and ``vertex_map`` names the file vertex of each cut
    vertex. ``placement`` holds each component's pose (:mod:`solver.mesh.placement`).

    Returns:
        :class:`Forms` with edges (E, 2), lengths (E,), angles (E,), vertex_map, placement.

    Raises:
        SolverInputError: a subclass naming the first bad element of a malformed mesh.
            Faces of zero area with distinct corners (collinear) are measured with the
            normal of :func:`degenerate_normals`; a face with two corners at one position
            is dropped once its vertices are welded.

    Example:
        A unit right-angled tetrahedron: six edges, every one convex.

        >>> import numpy as np
        >>> from solver import fundamental_forms
        >>> corners = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
        >>> forms = fundamental_forms(corners, [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
        >>> forms.edges.tolist()
        [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]
        >>> forms.lengths.round(4).tolist()
        [1.0, 1.0, 1.0, 1.4142, 1.4142, 1.4142]
        >>> bool((forms.angles > 0).all())
        True
    """
    V = as_points(vertices, "vertices")
    cut, topology = manifold_topology(faces, V, coincident=coincident)
    cut_vertices = V if cut.is_identity else cut.to_cut(V)
    forms = forms_of(cut_vertices, topology)
    forms.placement = placement_of(cut_vertices, forms.faces, topology.face_component)
    if cut.is_cut or cut.weld_map is not None:
        forms.vertex_map = cut.vertex_map
    forms.weld_map = cut.weld_map
    if cut.face_map is not None:
        forms.dropped_faces = np.setdiff1d(np.arange(cut.n_file_faces or 0), cut.face_map)
    return forms


ZERO_AREA = 1e-15
"""A face whose area is at most this fraction of the squared longest edge of the mesh has
zero area (collinear corners): its normal comes from :func:`degenerate_normals`."""
NORMAL_PASSES = 3
"""Passes of :func:`degenerate_normals` over chains of zero-area faces (each pass gives a
normal to the zero-area faces next to one that has one)."""


def degenerate_normals(V: np.ndarray, topology: MeshTopology, normals: np.ndarray,
                       zero: np.ndarray) -> np.ndarray:
    """Unit normals of the zero-area faces, by one documented rule (issue 40).

    A face whose corners are collinear has no normal of its own; any unit vector
    perpendicular to its line makes its frame a rotation that carries its (flat) layout
    onto it, so the forms measured with it are integrable whatever the choice. The rule
    chooses a least bent one: the sum of the unit normals of its edge neighbours that have
    one, with the component along the face's longest edge removed, normalized. The face
    then lies flat between its neighbours: the dihedral angles of its edges split those of
    the surface around it (0 across an edge to its only neighbour with a normal; an
    inserted face on an edge splits that edge's angle in two parts that add up to it).
    Zero-area faces next to zero-area faces get theirs in up to :data:`NORMAL_PASSES`
    passes; a face with none around (or whose neighbours cancel)
    gets the unit vector perpendicular to its line nearest to a coordinate axis.

    Args:
        V: (n, 3) float64 vertices.
        topology: the mesh's connectivity.
        normals: (m, 3) float64 unit face normals (:func:`face_normals`; zero rows for
            zero-area faces).
        zero: (m,) bool, the zero-area faces.

    Returns:
        (m, 3) float64 normals, the zero-area faces' rows filled in.
    """
    normals = normals.copy()
    faces = topology.faces
    d = np.stack([V[faces[:, 1]] - V[faces[:, 0]], V[faces[:, 2]] - V[faces[:, 1]],
                  V[faces[:, 0]] - V[faces[:, 2]]], axis=1)                # (m, 3, 3)
    rows = np.flatnonzero(zero)
    longest = np.linalg.norm(d[rows], axis=2).argmax(axis=1)
    line = d[rows, longest]
    line /= np.maximum(np.linalg.norm(line, axis=1), np.finfo(float).tiny)[:, None]
    halfedge_edge = topology.halfedge_edge.reshape(-1, 3)[rows]           # (k, 3)
    sides = topology.edge_faces[halfedge_edge]                            # (k, 3, 2)
    neighbours = np.where(sides == rows[:, None, None], sides[..., ::-1], sides)[..., 0]
    missing = np.ones(len(rows), dtype=bool)
    for _ in range(NORMAL_PASSES):  # a few vectorized passes along chains of such faces
        around = np.where((neighbours >= 0)[..., None], normals[np.maximum(neighbours, 0)],
                          0.0).sum(axis=1)
        around -= np.einsum("kj,kj->k", around, line)[:, None] * line
        size = np.linalg.norm(around, axis=1)
        found = missing & (size > 1e-8)
        normals[rows[found]] = around[found] / size[found, None]
        missing &= ~found
        if not missing.any():
            break
    if missing.any():
        axis = np.eye(3)[np.abs(line[missing]).argmin(axis=1)]
        axis -= np.einsum("kj,kj->k", axis, line[missing])[:, None] * line[missing]
        normals[rows[missing]] = axis / np.linalg.norm(axis, axis=1)[:, None]
    return normals


def zero_area_faces(V: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(k,) int64 the faces of zero area (:data:`ZERO_AREA`) of ``V`` (n, 3), ``faces`` (m, 3)."""
    _, areas = face_normals(V, faces)
    lengths = np.linalg.norm(V[faces[:, [1, 2, 0]]] - V[faces], axis=2)
    return np.flatnonzero(areas <= ZERO_AREA * float(lengths.max(initial=0.0)) ** 2)


def forms_of(V: np.ndarray, topology: MeshTopology, allow_degenerate: bool = False) -> Forms:
    """:func:`fundamental_forms` on a topology built already (callers that have one do not
    build it again).

    Faces of zero area (collinear corners) get the normal of :func:`degenerate_normals`, so
    their edges have dihedral angles and the forms stay integrable.

    Args:
        V: (n, 3) float64 validated vertices.
        topology: their mesh's connectivity.
        allow_degenerate: measure a mesh with faces that collapse to a point or an edge of
            length 0 anyway (their dihedral angles are 0): for metrics of an answer, never
            for forms to solve with.

    Returns:
        :class:`Forms`.

    Raises:
        NonFiniteValueError: a face's area overflows double precision.
        DegenerateFaceError: a face with an edge of length 0 (two corners at one position:
            no line, hence no normal by any rule), unless ``allow_degenerate``.
    """
    with np.errstate(over="ignore", invalid="ignore"):
        normals, areas = face_normals(V, topology.faces)
        lengths = np.linalg.norm(V[topology.edges[:, 1]] - V[topology.edges[:, 0]], axis=1)
    overflow = ~np.isfinite(areas)
    if overflow.any():
        t = int(np.flatnonzero(overflow)[0])
        raise NonFiniteValueError(
            "coordinates are too large: the face's area overflows double precision",
            field="faces", index=t)
    scale = float(lengths.max()) ** 2
    zero = areas <= ZERO_AREA * scale
    collapsed = zero & (lengths[topology.halfedge_edge].reshape(-1, 3).min(axis=1) <= 0)
    if collapsed.any() and not allow_degenerate:
        t = int(np.flatnonzero(collapsed)[0])
        raise DegenerateFaceError(
            f"face {topology.faces[t].tolist()} has two corners at one position: it has no "
            "line, hence no normal (weld its vertices)", field="faces", index=t)
    flagged = None
    if zero.any() and not collapsed.any():
        normals = degenerate_normals(V, topology, normals, zero)
        flagged = np.flatnonzero(zero)
    if allow_degenerate:  # a collapsed face or edge has no angle: 0 (measured, not solved)
        with np.errstate(invalid="ignore", divide="ignore"):
            angles = np.nan_to_num(dihedral_angles(V, topology, normals), nan=0.0)
        return Forms(faces=topology.faces, edges=topology.edges, lengths=lengths,
                     angles=angles)
    return Forms(faces=topology.faces, edges=topology.edges, lengths=lengths,
                 angles=dihedral_angles(V, topology, normals), zero_area_faces=flagged)


def flat_faces(topology: MeshTopology, lengths: np.ndarray) -> np.ndarray:
    """(k,) int64 the faces whose edge ``lengths`` (E,) give zero area (the triangle
    inequality holds with equality: :data:`solver.mesh.frames.COLLINEAR_SLACK`): laid out as
    segments, their frames are any rotation that carries the segment onto the face."""
    from .frames import face_edge_lengths, triangle_areas

    return np.flatnonzero(triangle_areas(face_edge_lengths(topology, lengths)) == 0)


def wrapped_angle_count(angles: ArrayLike) -> int:
    """How many of validated ``angles`` (E,) :func:`validate_forms` wraps into (-pi, pi]."""
    return wrap_angles(np.asarray(angles, dtype=np.float64).ravel())[1]


def validate_forms(faces: ArrayLike, edges: ArrayLike, lengths: ArrayLike, angles: ArrayLike,
                   n_vertices: int | None = None,
                   ) -> tuple[MeshTopology, np.ndarray, np.ndarray]:
    """Check forms against their connectivity.

    The triangle inequality is checked by the callers that need it
    (:func:`solver.mesh.frames.triangle_layouts`).

    Args:
        faces: (m, 3) int, counter-clockwise.
        edges: (E, 2) int, the faces' edges ``[i, j]``, i < j, sorted.
        lengths: (E,) float edge lengths.
        angles: (E,) finite float dihedral angles; those outside (-pi, pi] are wrapped
            into it (:func:`wrap_angles`: an angle is periodic).
        n_vertices: vertex count (default ``faces.max() + 1``).

    Returns:
        ``(topology, lengths, angles)``: the :class:`~solver.mesh.topology.MeshTopology` and
        (E,) float64 lengths and angles, angles wrapped into (-pi, pi].

    Raises:
        EdgeMismatchError: edges that are not the faces' edges (sorted, i < j).
        ShapeMismatchError: arrays of the wrong shape or length.
        NonFiniteValueError: a length or angle that is not finite.
        NonPositiveLengthError: a length that is not positive.

    Example:
        >>> from solver.mesh.forms import validate_forms
        >>> validate_forms([[0, 1, 2]], [[0, 1], [0, 2], [1, 2]], [1.0, 1.0, -1.0], [0, 0, 0])
        Traceback (most recent call last):
        ...
        solver.core.errors.NonPositiveLengthError: ...length -1.0 of edge [1, 2] is not positive
    """
    try:  # the edges serve the topology's half-edge lookup when they are well formed
        E = as_indices(edges, "edges", width=2)
    except SolverInputError:
        E = None
    topology = build_topology(faces, n_vertices, edges=E)  # the faces' errors first
    E = as_indices(edges, "edges", width=2) if E is None else E
    expected = topology.edges
    if len(E) != len(expected):
        raise EdgeMismatchError(
            f"the faces have {len(expected)} distinct edges but {len(E)} were given",
            field="edges", details={"expected_count": len(expected)})
    differs = (expected != E).any(axis=1)
    if differs.any():
        e = int(np.flatnonzero(differs)[0])
        hint = " (write each edge as [i, j] with i < j)" if E[e, 0] > E[e, 1] else ""
        raise EdgeMismatchError(
            f"edge {E[e].tolist()} does not match the faces: row {e} of the sorted edge list of "
            f"the faces is {expected[e].tolist()}{hint}", field="edges", index=e,
            details={"expected": expected[e].tolist()})
    L = as_vector(lengths, "lengths", size=len(expected))
    A = as_vector(angles, "angles", size=len(expected))
    if (L <= 0).any():
        e = int(np.flatnonzero(L <= 0)[0])
        raise NonPositiveLengthError(
            f"length {float(L[e])!r} of edge {E[e].tolist()} is not positive",
            field="lengths", index=e)
    return topology, L, wrap_angles(A)[0]
