import numpy as np
import pytest

from solver import fundamental_forms, interpolate
from solver.core.errors import ShapeMismatchError
from solver.mesh.metrics import distortion, histogram, summary, wrap_angle
from tests.helpers.meshes import icosphere, load


def test_endpoints_are_reproduced():
    A, F = icosphere(2)
    B = A * [2.0, 1.0, 0.5]
    out = interpolate(A, B, F, [0.0, 1.0])
    assert np.abs(out[0] - A).max() < 1e-9
    assert np.abs(out[1] - B).max() < 1e-9


def test_form_blend_keeps_edge_lengths_closer_than_linear_blend():
    # A strip bent into a half circle: the linear blend with the straight strip shrinks
    # the edges mid-way; the form-space blend keeps them (lengths are equal at both ends).
    u, v = np.meshgrid(np.linspace(0, np.pi, 40), np.linspace(0, 0.3, 5))
    idx = np.arange(u.size).reshape(u.shape)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    straight = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], 1)
    bent = np.stack([np.cos(u.ravel()), v.ravel(), np.sin(u.ravel())], 1)
    lengths_a = fundamental_forms(straight, F).lengths
    lengths_b = fundamental_forms(bent, F).lengths
    mid = interpolate(straight, bent, F, 0.5)
    linear = 0.5 * (straight + bent)
    def length_error(X):
        L = fundamental_forms(X, F).lengths
        return max(np.abs(L / lengths_a - 1).max(), np.abs(L / lengths_b - 1).max())
    assert length_error(mid) < 0.02
    assert length_error(linear) > 0.2
    assert length_error(mid) < 0.1 * length_error(linear)


def test_angles_blend_the_short_way():
    assert wrap_angle(np.array([3.0 + 0.5, -np.pi]))[1] == np.pi
    assert wrap_angle(np.array([2 * np.pi + 0.1]))[0] == pytest.approx(0.1)


def test_interpolate_rejects_mismatched_meshes():
    A, F = icosphere(1)
    with pytest.raises(ShapeMismatchError):
        interpolate(A, A[:-1], F, 0.5)


def test_distortion_of_a_known_scaling():
    V, F = icosphere(2)
    report = distortion(V, V * 1.1, F)
    assert report["length_summary"]["mean"] == pytest.approx(0.1)
    assert report["angle_summary"]["max"] < 1e-12
    assert report["face_angle_summary"]["max"] < 1e-12
    assert np.allclose(report["area_ratio"], 1.21)
    assert len(report["vertex"]) == len(V)


def test_distortion_of_a_rigid_motion_is_zero():
    V, F = load("decimated-knight.off")
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    report = distortion(V, V @ R.T + 3.0, F)
    assert report["length_summary"]["max"] < 1e-12
    assert report["angle_summary"]["max"] < 1e-9


def test_summary_and_histogram():
    values = np.array([0.0, -1.0, 2.0, 3.0])
    s = summary(values)
    assert s["max"] == 3.0 and s["mean"] == 1.5
    h = histogram(values, bins=3)
    assert sum(h["counts"]) == 4 and h["bin_edges"][-1] == 3.0
