"""Batched 3x3 rotation utilities: axis rotations, angles, swing-twist split, polar projection."""

from __future__ import annotations

import numpy as np


def rotation_z(angle: np.ndarray) -> np.ndarray:
    """(k, 3, 3) rotations about the z axis by ``angle`` (k,) radians."""
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros((*np.shape(angle), 3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1] = c, -s, s, c
    R[..., 2, 2] = 1.0
    return R


def rotation_x(angle: np.ndarray) -> np.ndarray:
    """(k, 3, 3) rotations about the x axis by ``angle`` (k,) radians."""
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros((*np.shape(angle), 3, 3))
    R[..., 0, 0] = 1.0
    R[..., 1, 1], R[..., 1, 2], R[..., 2, 1], R[..., 2, 2] = c, -s, s, c
    return R


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Rotation angle in [0, pi] of each (..., 3, 3) rotation, accurate near 0.

    Uses atan2(|axis * sin|, cos) from the skew and trace parts instead of arccos of the
    trace, which loses half the digits for small angles.
    """
    skew = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                     R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    sin = 0.5 * np.linalg.norm(skew, axis=-1)
    cos = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    return np.arctan2(sin, cos)


def swing_twist_angles(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split rotations into a twist about the local z axis and a swing that tilts z.

    Returns (twist, swing): twist in (-pi, pi] is the signed rotation about z, swing in
    [0, pi] the angle by which z itself is tilted (angle between ``R e_z`` and ``e_z``).
    """
    swing = np.arctan2(np.linalg.norm(np.cross(R[..., :, 2], [0.0, 0.0, 1.0]), axis=-1),
                       R[..., 2, 2])
    # Twist: rotate R e_z back onto e_z by the minimal swing, then read the in-plane angle
    # of the image of e_x. Equivalent to 2 atan2(q_z, q_w) of R's quaternion.
    q_w2 = 1.0 + np.trace(R, axis1=-2, axis2=-1)  # 4 q_w^2
    q_z = R[..., 1, 0] - R[..., 0, 1]            # 4 q_w q_z
    twist = 2.0 * np.arctan2(q_z, q_w2)          # atan2(q_z, q_w) scaled by 4 q_w (> 0 branch)
    twist = np.where(twist > np.pi, twist - 2 * np.pi, twist)
    twist = np.where(twist <= -np.pi, twist + 2 * np.pi, twist)
    return twist, swing


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """Closest rotation (Frobenius) to each (..., 3, 3) matrix: polar factor with det +1."""
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    U[..., :, 2] *= d[..., None]
    return U @ Vt


def is_rotation(M: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """Boolean (...,): M^T M = I within ``tol`` and det(M) > 0."""
    eye = np.eye(3)
    err = np.abs(np.swapaxes(M, -1, -2) @ M - eye).max(axis=(-2, -1))
    return (err <= tol) & (np.linalg.det(M) > 0)
