import numpy as np
import pytest

from solver import parameterize
from solver.core.errors import TopologyError
from solver.mesh.metrics import corner_angles
from tests.helpers.meshes import bumpy_grid_with_holes, grid, icosphere, load, sphere_cap


def rolled_sheet(nu: int = 30, nv: int = 10):
    """A developable surface: a rectangle rolled onto a cylinder (isometric to the plane)."""
    V, F = grid(nu, nv, width=3.0, height=1.0)
    u, v = V[:, 0], V[:, 1]
    rolled = np.stack([np.cos(u), np.sin(u), v], axis=1)
    # Its exact unrolling: mesh edges are chords, so u-steps shrink to 2 sin(du / 2).
    du = 3.0 / nu
    unrolled = np.stack([u * 2 * np.sin(du / 2) / du, v, np.zeros_like(u)], axis=1)
    return rolled, F, unrolled


@pytest.mark.parametrize("orthonormalize", [False, True])
def test_developable_surface_is_flattened_isometrically(orthonormalize):
    V, F, flat = rolled_sheet()
    result = parameterize(V, F, orthonormalize=orthonormalize)
    uv = result.uv
    edges = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    length_3d = np.linalg.norm(V[edges[:, 0]] - V[edges[:, 1]], axis=1)
    length_uv = np.linalg.norm(uv[edges[:, 0]] - uv[edges[:, 1]], axis=1)
    assert np.abs(length_uv / length_3d - 1).max() < 1e-8
    assert len(result.flipped_faces) == 0
    assert np.abs(result.area_ratio - 1).max() < 1e-8
    # Congruent to the exact unrolling (all pairwise distances, not only edges).
    far = np.linalg.norm(uv[:, None] - uv[None, :], axis=2)
    ref = np.linalg.norm(flat[:, None, :2] - flat[None, :, :2], axis=2)
    assert np.abs(far - ref).max() < 1e-8 * ref.max()


def test_face_scan_flattens_without_flips_and_with_bounded_distortion():
    V, F = load("face.off")
    result = parameterize(V, F)
    assert result.uv.shape == (len(V), 2)
    assert result.report["planarity_error"] == 0.0
    assert result.report["flipped_count"] == len(result.flipped_faces) == 0
    # Measured 0.046 mean relative edge-length change (bench: orthonormalized solve).
    assert result.report["length_change_summary"]["mean"] < 0.06


def test_second_solve_reduces_shrinkage():
    V, F = load("face.off")
    plain = parameterize(V, F, orthonormalize=False, refine=False, seams="none")
    ortho = parameterize(V, F, orthonormalize=True, refine=False, seams="none")
    assert (ortho.report["length_change_summary"]["mean"]
            < plain.report["length_change_summary"]["mean"])


def test_mesh_with_holes():
    V, F = bumpy_grid_with_holes()
    result = parameterize(V, F)
    assert np.isfinite(result.uv).all() and len(result.flipped_faces) == 0
    flat = np.concatenate([result.uv, np.zeros((len(V), 1))], axis=1)
    assert np.abs(corner_angles(flat, F) - corner_angles(V, F)).mean() < 0.05


def test_flips_are_reported_not_hidden():
    # A strongly curved cap flattened without the second solve folds over near the pole.
    cap_V, cap_F = sphere_cap()
    result = parameterize(cap_V, cap_F, orthonormalize=False, seams="none")
    e1 = result.uv[cap_F[:, 1]] - result.uv[cap_F[:, 0]]
    e2 = result.uv[cap_F[:, 2]] - result.uv[cap_F[:, 0]]
    signed = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    assert np.array_equal(np.flatnonzero(signed < 0), result.flipped_faces)
    assert result.report["flipped_count"] == len(result.flipped_faces)


def test_closed_mesh_needs_a_cut_without_seams():
    V, F = icosphere(2)
    with pytest.raises(TopologyError) as err:
        parameterize(V, F, seams="none")
    assert "cut" in str(err.value)
