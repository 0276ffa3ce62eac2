"""Per-face 2D layouts, edge coefficients ``a`` and transition rotations ``R_ij`` (Sec. 2.3).

Each face ``t = (v0, v1, v2)`` gets a 2D layout from its three edge lengths: ``v0`` at the
origin, ``v1`` on the positive x axis, ``v2`` above it (counter-clockwise). Its local frame is
``(t, t_perp) = (e_x, e_y)`` of that layout, optionally rotated by a per-face angle (the
reconstruction does not depend on it, Sec. 3). A 3D frame ``f_t`` (3x3, columns b1, b2, b3)
is "consistent with the layout" when ``x_n - x_m = f_t (a^1, a^2, 0)`` for every edge (Eq. 3)
and ``b3`` is the outward normal.
"""

from __future__ import annotations

import numpy as np

from ..core.errors import TriangleInequalityError
from .topology import MeshTopology

TRIANGLE_SLACK = 1e-12
"""Relative slack of the triangle inequality (of the longest edge), for rounding."""


COLLINEAR_SLACK = 8 * np.finfo(np.float64).eps
"""Lengths whose triangle inequality holds with equality up to this relative slack (of the
longest edge: a few roundings) are a zero-area face (collinear corners): its area is 0 and
its layout a segment. Heron's area would give it a height of ~sqrt(slack) of its longest
edge instead (1e-8 for a face measured flat), which no embedding of the face has."""


def face_edge_lengths(topology: MeshTopology, lengths: np.ndarray) -> np.ndarray:
    """Edge lengths arranged per face.

    Args:
        topology: the mesh's connectivity.
        lengths: (E,) float64 edge lengths.

    Returns:
        (m, 3) float64: length of half-edge k of each face (from corner k to corner k + 1).
    """
    return lengths[topology.halfedge_edge].reshape(-1, 3)


def triangle_inequality_violations(face_lengths: np.ndarray) -> np.ndarray:
    """Faces whose lengths cannot form a triangle.

    Args:
        face_lengths: (m, 3) float64 (:func:`face_edge_lengths`).

    Returns:
        (k,) int64 faces whose longest edge exceeds the sum of the other two (beyond
        :data:`TRIANGLE_SLACK`).

    Example:
        >>> import numpy as np
        >>> from solver.mesh.frames import triangle_inequality_violations
        >>> triangle_inequality_violations(np.array([[3.0, 4.0, 5.0], [1.0, 1.0, 3.0]])).tolist()
        [1]
    """
    shortest, middle, longest = _sorted_columns(face_lengths)
    slack = shortest + middle - longest
    return np.flatnonzero(slack < -TRIANGLE_SLACK * longest)


def _sorted_columns(face_lengths: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The three columns of (m, 3) ``face_lengths`` sorted per row: ``(shortest, middle,
    longest)``, (m,) each (the values of ``np.sort(axis=1)`` by minima and maxima: no
    sort of rows of three)."""
    l0, l1, l2 = face_lengths.T
    low, high = np.minimum(l0, l1), np.maximum(l0, l1)
    return np.minimum(low, l2), np.maximum(low, np.minimum(high, l2)), np.maximum(high, l2)


def _as_written(value: float) -> str:
    """A float as the caller most likely wrote it (``100``, ``1.41``): shortest repr."""
    value = float(value)
    return str(int(value)) if value.is_integer() and abs(value) < 1e15 else repr(value)


def triangle_inequality_error(topology: MeshTopology, lengths: np.ndarray,
                              bad: np.ndarray) -> TriangleInequalityError:
    """The error for faces that violate the triangle inequality, in the caller's units.

    Args:
        topology: the mesh's topology.
        lengths: (E,) float64 edge lengths exactly as the caller passed them (not normalized).
        bad: (k,) int64 violating faces, k >= 1, from :func:`triangle_inequality_violations`.

    Returns:
        :class:`TriangleInequalityError` naming the first face, its three edges ``[i, j]``
        and their lengths as given; ``details`` lists up to 100 faces, and the first face's
        edge indices and lengths.
    """
    t = int(bad[0])
    rows = topology.halfedge_edge.reshape(-1, 3)[t]  # edge of each half-edge of face t
    sent = lengths[rows]
    quoted = [_as_written(x) for x in sent]
    order = np.argsort(sent, kind="stable")
    return TriangleInequalityError(
        f"edge lengths {', '.join(quoted)} of face {t} (edges "
        f"{topology.edges[rows].tolist()}) violate the triangle inequality: "
        f"{quoted[order[2]]} > {quoted[order[0]]} + {quoted[order[1]]}"
        + (f" ({len(bad)} faces in all)" if len(bad) > 1 else ""),
        field="faces", index=t,
        details={"faces": bad[:100].tolist(), "edges": rows.tolist(),
                 "lengths": sent.tolist()})


def triangle_areas(face_lengths: np.ndarray) -> np.ndarray:
    """Triangle areas from edge lengths by Kahan's stable Heron formula.

    Args:
        face_lengths: (m, 3) float64.

    Returns:
        (m,) float64 areas, 0 for degenerate (or impossible) triangles, and for those whose
        triangle inequality holds with equality within :data:`COLLINEAR_SLACK`.

    Example:
        >>> import numpy as np
        >>> from solver.mesh.frames import triangle_areas
        >>> triangle_areas(np.array([[3.0, 4.0, 5.0], [1.0, 1.0, 2.0]])).tolist()
        [6.0, 0.0]
    """
    shortest, middle, longest = _sorted_columns(face_lengths)
    scale = np.where(longest > 0, longest, 1.0)  # avoids overflow of the product
    c, b, a = shortest / scale, middle / scale, longest / scale  # a >= b >= c
    slack = c - (a - b)
    product = (a + (b + c)) * slack * (c + (a - b)) * (a + (b - c))
    product = np.where(slack <= COLLINEAR_SLACK, 0.0, product)
    return 0.25 * np.sqrt(np.maximum(product, 0.0)) * scale**2


def triangle_layouts(face_lengths: np.ndarray, layout_angles: np.ndarray | None = None,
                     check: bool = True) -> np.ndarray:
    """2D corner positions (m, 3, 2) of each face in its local orthonormal frame.

    Args:
        face_lengths: (m, 3) from :func:`face_edge_lengths`.
        layout_angles: optional (m,) rotation of each face's 2D frame (radians).
        check: raise on triangle-inequality violations; with False, such faces are laid out
            flat (zero area) and only approximate their lengths.

    Returns:
        (m, 3, 2) float64: corner 0 at the origin, corner 1 on the positive x axis, corner 2
        above it (before ``layout_angles``).

    Raises:
        TriangleInequalityError: naming the first face whose lengths cannot form a triangle.

    Example:
        >>> import numpy as np
        >>> from solver.mesh.frames import triangle_layouts
        >>> triangle_layouts(np.array([[3.0, 4.0, 5.0]])).round(12).tolist()
        [[[0.0, 0.0], [3.0, 0.0], [3.0, 4.0]]]
    """
    bad = triangle_inequality_violations(face_lengths) if check else np.zeros(0, np.int64)
    if len(bad):
        t = int(bad[0])
        raise TriangleInequalityError(
            f"edge lengths {face_lengths[t].tolist()} of face {t} violate the triangle "
            f"inequality ({len(bad)} faces in all)", field="faces", index=t,
            details={"faces": bad[:100].tolist()})
    l01, l12, l20 = face_lengths.T
    x2 = (l01**2 + l20**2 - l12**2) / (2.0 * l01)
    y2 = 2.0 * triangle_areas(face_lengths) / l01
    points = np.zeros((len(face_lengths), 3, 2))
    points[:, 1, 0] = l01
    points[:, 2, 0] = x2
    points[:, 2, 1] = y2
    if layout_angles is not None:
        c, s = np.cos(layout_angles), np.sin(layout_angles)
        rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)  # (m, 2, 2)
        points = np.einsum("tij,tkj->tki", rot, points)
    return points


def edge_coefficients(layouts: np.ndarray) -> np.ndarray:
    """Edge coefficients ``a_{mn,T}`` of Eq. (3): the layout vector of each half-edge.

    Args:
        layouts: (m, 3, 2) float64 (:func:`triangle_layouts`).

    Returns:
        (m, 3, 2) float64: the vector from corner k to corner k + 1 of each face.
    """
    return np.roll(layouts, -1, axis=1) - layouts  # corner k + 1 - corner k (a slice copy)


def transition_angles(topology: MeshTopology, coefficients: np.ndarray,
                      angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Angles of the transition rotations of the interior edges.

    For interior edge ``e = [i, j]`` with face ``L`` left of ``i -> j`` and face ``R`` on the
    other side, ``R_LR = Rz(theta_L) Rx(phi_e) Rz(-theta_R)`` where ``theta_T`` is the angle
    that turns face T's first frame axis onto the direction ``i -> j`` (Sec. 2.3). With an
    immersion, ``f_R = f_L R_LR``.

    Args:
        topology: the mesh's connectivity.
        coefficients: (m, 3, 2) float64 edge coefficients (:func:`edge_coefficients`).
        angles: (E,) float64 dihedral angles.

    Returns:
        ``(interior_edges, transition)``: (k,) int64 and (k, 3) float64 with columns
        theta_L, phi_e, theta_R.
    """
    inner = topology.interior_edges
    h_left, h_right = topology.edge_halfedges[inner, 0], topology.edge_halfedges[inner, 1]
    a = coefficients.reshape(-1, 2)
    theta_left = np.arctan2(a[h_left, 1], a[h_left, 0])
    # In face R the edge runs j -> i; the direction i -> j is that vector turned by pi.
    theta_right = np.arctan2(a[h_right, 1], a[h_right, 0]) + np.pi
    return inner, np.stack([theta_left, angles[inner], theta_right], axis=1)


def transition_rotations(transition: np.ndarray) -> np.ndarray:
    """Transition rotations ``Rz(theta_L) Rx(phi) Rz(-theta_R)``.

    Args:
        transition: (k, 3) float64 angles from :func:`transition_angles`.

    Returns:
        (k, 3, 3) float64 rotation matrices.
    """
    R = np.empty((len(transition), 3, 3))
    for lo in range(0, len(transition), BLOCK):  # temporaries of a block stay in cache
        _rotations_into(transition[lo:lo + BLOCK], R[lo:lo + BLOCK])
    return R


BLOCK = 1 << 15
"""Rows per block of :func:`transition_rotations` and :func:`transition_quaternions`: their
temporaries (a few per entry of the result) stay in cache instead of streaming
whole-array passes through memory."""


def _rotations_into(transition: np.ndarray, R: np.ndarray) -> None:
    """:func:`transition_rotations` of (b, 3) ``transition`` written into (b, 3, 3) ``R``."""
    theta_left, phi, theta_right = transition.T
    ca, sa = np.cos(theta_left), np.sin(theta_left)
    cp, sp = np.cos(phi), np.sin(phi)
    cb, sb = np.cos(theta_right), np.sin(theta_right)
    # Written out entry by entry into the result (no (k, 3) or (k, 3, 3) temporaries):
    # M = Rz(a) Rx(phi) has columns m0 = (ca, sa, 0), m1 = (-sa cp, ca cp, sp),
    # m2 = (sa sp, -ca sp, cp); R = M Rz(-b) turns its first two columns by b.
    sacp, cacp = sa * cp, ca * cp
    np.multiply(ca, cb, out=R[:, 0, 0])
    R[:, 0, 0] += sacp * sb
    np.multiply(sa, cb, out=R[:, 1, 0])
    R[:, 1, 0] -= cacp * sb
    np.multiply(sp, sb, out=R[:, 2, 0])
    np.negative(R[:, 2, 0], out=R[:, 2, 0])
    np.multiply(ca, sb, out=R[:, 0, 1])
    R[:, 0, 1] -= sacp * cb
    np.multiply(sa, sb, out=R[:, 1, 1])
    R[:, 1, 1] += cacp * cb
    np.multiply(sp, cb, out=R[:, 2, 1])
    np.multiply(sa, sp, out=R[:, 0, 2])
    np.multiply(ca, sp, out=R[:, 1, 2])
    np.negative(R[:, 1, 2], out=R[:, 1, 2])
    R[:, 2, 2] = cp


def transition_quaternions(transition: np.ndarray) -> np.ndarray:
    """The transition rotations as unit quaternions (cheaper to compose).

    Args:
        transition: (k, 3) float64 angles from :func:`transition_angles`.

    Returns:
        (k, 4) float64 unit quaternions (w, x, y, z).
    """
    q = np.empty((len(transition), 4))
    for lo in range(0, len(transition), BLOCK):  # temporaries of a block stay in cache
        _quaternions_into(transition[lo:lo + BLOCK], q[lo:lo + BLOCK])
    return q


def _quaternions_into(transition: np.ndarray, q: np.ndarray) -> None:
    """:func:`transition_quaternions` of (b, 3) ``transition`` written into (b, 4) ``q``."""
    half = 0.5 * transition
    c, s = np.cos(half), np.sin(half)
    ca, cp, cb = c.T
    sa, sp, sb = s.T
    # qz(a) qx(phi) = (ca cp, ca sp, sa sp, sa cp), then times qz(-b) = (cb, 0, 0, -sb);
    # written into the result column by column (no (k, 4) temporaries).
    w, x, y, z = ca * cp, ca * sp, sa * sp, sa * cp
    np.multiply(w, cb, out=q[:, 0])
    q[:, 0] += z * sb
    np.multiply(x, cb, out=q[:, 1])
    q[:, 1] -= y * sb
    np.multiply(y, cb, out=q[:, 2])
    q[:, 2] += x * sb
    np.multiply(z, cb, out=q[:, 3])
    q[:, 3] -= w * sb


def layout_frames(vertices: np.ndarray, faces: np.ndarray, layouts: np.ndarray) -> np.ndarray:
    """3D frames (m, 3, 3) that map each face's layout onto its embedding (Eq. 3).

    Columns b1, b2 solve ``[x1 - x0, x2 - x0] = [b1, b2] [p1 - p0, p2 - p0]``; b3 = b1 x b2.
    For a mesh whose lengths produced ``layouts`` these are rotations (the lift's f). A
    zero-area layout (collinear corners) determines b1 only: its b1, b2 are the
    least-squares (pseudo-inverse) solution, b2 = b3 = 0 for a segment, and the nearest
    rotation of that frame is any one that carries the segment onto the face (every such
    rotation does, which is all a layout of zero area asks for).

    Args:
        vertices: (n, 3) float64.
        faces: (m, 3) int64.
        layouts: (m, 3, 2) float64 (:func:`triangle_layouts`).

    Returns:
        (m, 3, 3) float64 frames, columns b1, b2, b3.
    """
    X = np.stack([vertices[faces[:, 1]] - vertices[faces[:, 0]],
                  vertices[faces[:, 2]] - vertices[faces[:, 0]]], axis=2)   # (m, 3, 2)
    P = np.stack([layouts[:, 1] - layouts[:, 0], layouts[:, 2] - layouts[:, 0]], axis=2)
    det = P[:, 0, 0] * P[:, 1, 1] - P[:, 0, 1] * P[:, 1, 0]
    size = np.einsum("tij,tij->t", P, P)
    flat = np.abs(det) <= 1e-14 * size
    inverse = np.empty_like(P)
    inverse[~flat] = np.linalg.inv(P[~flat])
    if flat.any():  # zero-area layouts: the least-squares frame (a few faces)
        inverse[flat] = np.linalg.pinv(P[flat])
    B = X @ inverse                                                         # (m, 3, 2)
    return np.concatenate([B, np.cross(B[:, :, 0], B[:, :, 1])[:, :, None]], axis=2)
