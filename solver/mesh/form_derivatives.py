"""Reverse-mode derivatives of the per-face quantities that the forms determine (Sec. 2.3).

The linear system of Eq. (5) depends on the forms only through the edge coefficients
``a`` (each face's 2D layout, from its three lengths) and the transition rotations
``R_LR = Rz(theta_L) Rx(phi_e) Rz(-theta_R)`` (the dihedral angle ``phi_e`` and the layout
angles ``theta`` of the shared edge in both faces). This module pulls cotangents of those
quantities back to the lengths and angles, batched over a leading axis of ``B`` cotangents.
Every function takes the forward values it needs and returns the cotangent of its inputs;
shapes are stated with the batch axis ``B`` first.
"""

from __future__ import annotations

import numpy as np

from .rotations import rotation_x, rotation_z
from .topology import MeshTopology

_GZ = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])  # d Rz / d theta = Gz Rz
_GX = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # d Rx / d phi = Gx Rx


def layouts_vjp(face_lengths: np.ndarray, layouts: np.ndarray,
                layouts_bar: np.ndarray) -> np.ndarray:
    """Pull the cotangent of the layouts back to the face lengths.

    The layout of :func:`solver.mesh.frames.triangle_layouts` (no layout angles): corner 0 at the
    origin, corner 1 at ``(l01, 0)``, corner 2 at ``(x2, y2)`` with
    ``x2 = (l01^2 + l20^2 - l12^2) / (2 l01)`` and ``y2 = sqrt(l20^2 - x2^2)``.
    Faces of zero area (y2 = 0) get an infinite derivative there; they are refused earlier.

    Args:
        face_lengths: (m, 3) float64 forward lengths.
        layouts: (m, 3, 2) float64 forward layouts.
        layouts_bar: (B, m, 3, 2) float64 cotangent of the layouts.

    Returns:
        (B, m, 3) float64 cotangent of the face lengths.

    Example:
        Moving corner 1 of the 3-4-5 layout along x is changing the first length:

        >>> import numpy as np
        >>> from solver.mesh.form_derivatives import layouts_vjp
        >>> from solver.mesh.frames import triangle_layouts
        >>> lengths = np.array([[3.0, 4.0, 5.0]])
        >>> bar = np.zeros((1, 1, 3, 2))
        >>> bar[0, 0, 1, 0] = 1.0
        >>> (layouts_vjp(lengths, triangle_layouts(lengths), bar) + 0.0).tolist()
        [[[1.0, 0.0, 0.0]]]
    """
    l01, l12, l20 = face_lengths.T
    x2, y2 = layouts[:, 2, 0], layouts[:, 2, 1]
    y2 = np.where(y2 > 0, y2, np.finfo(float).tiny)
    x2_bar = layouts_bar[..., 2, 0] - (x2 / y2) * layouts_bar[..., 2, 1]   # y2 depends on x2
    l20_bar = (l20 / y2) * layouts_bar[..., 2, 1] + (l20 / l01) * x2_bar
    l01_bar = layouts_bar[..., 1, 0] + (1.0 - x2 / l01) * x2_bar
    l12_bar = -(l12 / l01) * x2_bar
    return np.stack([l01_bar, l12_bar, l20_bar], axis=-1)


def coefficients_vjp(coefficients_bar: np.ndarray) -> np.ndarray:
    """Pull the cotangent of the edge coefficients back to the layouts.

    Args:
        coefficients_bar: (B, m, 3, 2) float64 cotangent of
            ``a = layouts[:, [1, 2, 0]] - layouts`` (:func:`solver.mesh.frames.edge_coefficients`).

    Returns:
        (B, m, 3, 2) float64 cotangent of the layouts.
    """
    layouts_bar = -coefficients_bar.copy()
    layouts_bar[..., [1, 2, 0], :] += coefficients_bar
    return layouts_bar


def direction_angle_vjp(vectors: np.ndarray, angle_bar: np.ndarray) -> np.ndarray:
    """Pull the cotangent of the direction angles ``atan2(v_y, v_x)`` back to the vectors.

    Args:
        vectors: (k, 2) float64 nonzero 2D vectors.
        angle_bar: (B, k) float64 cotangent of their angles.

    Returns:
        (B, k, 2) float64 cotangent of the vectors.
    """
    norm2 = np.einsum("ij,ij->i", vectors, vectors)
    perp = np.stack([-vectors[:, 1], vectors[:, 0]], axis=1) / norm2[:, None]
    return angle_bar[..., None] * perp


def rotations_vjp(transition: np.ndarray, rotations: np.ndarray,
                  rotations_bar: np.ndarray) -> np.ndarray:
    """Pull the cotangent of the transition rotations back to their angles.

    ``R = Rz(theta_L) Rx(phi) Rz(-theta_R)``: ``dR/dtheta_L = Gz R``,
    ``dR/dphi = Rz(theta_L) Gx Rx(phi) Rz(-theta_R)``, ``dR/dtheta_R = -R Gz`` with the
    generators ``Gz``, ``Gx`` of the axis rotations.

    Args:
        transition: (k, 3) float64 forward angles ``(theta_L, phi, theta_R)``.
        rotations: (k, 3, 3) float64 forward rotations.
        rotations_bar: (B, k, 3, 3) float64 cotangent of the rotations.

    Returns:
        (B, k, 3) float64 cotangent of the angles.
    """
    theta_left, phi, theta_right = transition.T
    d_left = _GZ @ rotations
    d_phi = rotation_z(theta_left) @ _GX @ rotation_x(phi) @ rotation_z(-theta_right)
    d_right = -(rotations @ _GZ)
    inner = lambda d: np.einsum("...kij,kij->...k", rotations_bar, d)  # noqa: E731
    return np.stack([inner(d_left), inner(d_phi), inner(d_right)], axis=-1)


def transition_vjp(topology: MeshTopology, coefficients: np.ndarray,
                   transition_bar: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pull back the cotangent of :func:`solver.mesh.frames.transition_angles`.

    The layout angles ``theta_L``, ``theta_R`` are directions of half-edge coefficients,
    ``phi`` is the dihedral angle of the interior edge.

    Args:
        topology: the mesh's connectivity.
        coefficients: (m, 3, 2) float64 forward edge coefficients.
        transition_bar: (B, k, 3) float64 cotangent of the transition angles.

    Returns:
        ``(coefficients_bar, angles_bar)``: (B, m, 3, 2) and (B, E) float64.
    """
    inner = topology.interior_edges
    h_left, h_right = topology.edge_halfedges[inner, 0], topology.edge_halfedges[inner, 1]
    a = coefficients.reshape(-1, 2)
    batch = transition_bar.shape[:-2]
    a_bar = np.zeros((*batch, len(a), 2))
    a_bar[..., h_left, :] += direction_angle_vjp(a[h_left], transition_bar[..., 0])
    a_bar[..., h_right, :] += direction_angle_vjp(a[h_right], transition_bar[..., 2])
    angles_bar = np.zeros((*batch, topology.n_edges))
    angles_bar[..., inner] = transition_bar[..., 1]
    return a_bar.reshape(*batch, *coefficients.shape), angles_bar


def face_lengths_vjp(topology: MeshTopology, face_lengths_bar: np.ndarray) -> np.ndarray:
    """Pull the cotangent of :func:`solver.mesh.frames.face_edge_lengths` back to the lengths.

    Args:
        topology: the mesh's connectivity.
        face_lengths_bar: (B, m, 3) float64.

    Returns:
        (B, E) float64: a sum over each edge's half-edges.
    """
    flat = face_lengths_bar.reshape(-1, face_lengths_bar.shape[-2] * 3)
    out = np.stack([np.bincount(topology.halfedge_edge, weights=row,
                                minlength=topology.n_edges) for row in flat])
    return out.reshape(*face_lengths_bar.shape[:-2], topology.n_edges)


def layout_terms_vjp(topology: MeshTopology, face_lengths: np.ndarray, layouts: np.ndarray,
                     coefficients: np.ndarray, transition: np.ndarray, rotations: np.ndarray,
                     coefficients_bar: np.ndarray, rotations_bar: np.ndarray,
                     layouts_bar: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pull the cotangents of every per-face quantity back to the lengths and angles.

    Args:
        topology: the mesh's connectivity.
        face_lengths, layouts, coefficients, transition, rotations: forward values, as in
            :class:`solver.linear.system.EnergyTerms`.
        coefficients_bar: (B, m, 3, 2) float64 cotangent of the edge coefficients.
        rotations_bar: (B, k, 3, 3) float64 cotangent of the transition rotations.
        layouts_bar: optional (B, m, 3, 2) float64 cotangent of the layouts.

    Returns:
        ``(lengths_bar, angles_bar)``: (B, E) float64 each.
    """
    a_bar, angles_bar = transition_vjp(
        topology, coefficients, rotations_vjp(transition, rotations, rotations_bar))
    lay_bar = coefficients_vjp(coefficients_bar + a_bar)
    if layouts_bar is not None:
        lay_bar = lay_bar + layouts_bar
    lengths_bar = face_lengths_vjp(topology, layouts_vjp(face_lengths, layouts, lay_bar))
    return lengths_bar, angles_bar
