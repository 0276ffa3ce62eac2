"""Packing charts (solver.mesh.packing) and xatlas's charting input (solver.mesh.charts):
the per-chart rotations and rigid fits done for all charts at once, checked against each
chart done alone by a plain loop (numpy's eigh and SVD of that chart's own points); parts
that touch another moved apart for xatlas, the others left where they are."""

import numpy as np
import pytest

from solver.mesh.charts import touching_parts_apart
from solver.mesh.packing import (
    _chart_vertices,
    _exact_translation,
    _turn_charts,
    principal_rotation,
)
from tests.helpers.meshes import load


def _charts(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Charts of 1 to 40 faces with random layouts, labels out of order and with gaps, one
    unused uv vertex."""
    rng = np.random.default_rng(seed)
    sizes = rng.integers(1, 41, size=60)
    faces, chart, start = [], [], 1                         # uv vertex 0 unused
    for label, size in zip(rng.permutation(500)[:60] * 3, sizes, strict=True):
        faces.append(start + rng.integers(0, size + 2, size=(size, 3)))
        chart.append(np.full(size, label))
        start += size + 2
    uv = rng.normal(size=(start, 2)) * rng.uniform(0.1, 10.0)
    return uv, np.concatenate(faces), np.concatenate(chart)


def _vertices(faces: np.ndarray, chart: np.ndarray, label: int) -> np.ndarray:
    return np.unique(faces[chart == label])


def test_charts_are_turned_and_set_apart_as_each_alone():
    uv, faces, chart = _charts()
    turned = _turn_charts(uv, _chart_vertices(faces, chart, len(uv)))
    cursor = 0.0
    for label in np.unique(chart):                           # the reference: one at a time
        ids = _vertices(faces, chart, label)
        centred = uv[ids] - uv[ids].mean(axis=0)
        _, vectors = np.linalg.eigh(centred.T @ centred)
        rotation = vectors[:, ::-1].T
        if np.linalg.det(rotation) < 0:
            rotation[1] *= -1
        points = uv[ids] @ rotation.T
        low = points.min(axis=0)
        np.testing.assert_allclose(turned[ids], points - low + [cursor, 0.0], atol=1e-9)
        cursor += float(np.ptp(points[:, 0])) * 1.5 + 1e-9
        np.testing.assert_allclose(principal_rotation(uv[ids]), rotation, atol=1e-9)
    assert turned[0].tolist() == uv[0].tolist()              # an unused vertex stays


def test_each_chart_is_fitted_onto_its_placement_by_its_own_rigid_motion():
    uv, faces, chart = _charts(1)
    rng = np.random.default_rng(2)
    scale = 3.0
    placed = uv.copy() / scale
    for label in np.unique(chart):                           # a rotation and a shift each
        ids = _vertices(faces, chart, label)
        a = rng.uniform(0, 2 * np.pi)
        R = np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]])
        placed[ids] = placed[ids] @ R + rng.normal(size=2)
    noisy = placed + rng.normal(scale=1e-6, size=placed.shape)   # float32 rounding's stand-in
    exact = _exact_translation(uv, noisy, _chart_vertices(faces, chart, len(uv)), scale)
    used = np.unique(faces)
    np.testing.assert_allclose(exact[used], placed[used], atol=1e-5)
    for label in np.unique(chart):                           # shapes kept to round-off
        ids = _vertices(faces, chart, label)
        gaps = np.linalg.norm(exact[ids][:, None] - exact[ids][None], axis=2)
        want = np.linalg.norm(uv[ids][:, None] - uv[ids][None], axis=2) / scale
        np.testing.assert_allclose(gaps, want, atol=1e-12 * want.max())


def test_parts_touching_another_are_moved_apart_for_xatlas():
    V, F = load("decimated-knight.off")
    assert touching_parts_apart(V, F) is V                   # one part: as it is
    # Three copies: the second at the first's place (touching), the third far away.
    far = V + np.array([100.0, 0.0, 0.0])
    vertices = np.concatenate([V, V, far])
    faces = np.concatenate([F, F + len(V), F + 2 * len(V)])
    apart = touching_parts_apart(vertices, faces)
    n = len(V)
    np.testing.assert_array_equal(apart[:n], V)              # the first stays
    np.testing.assert_array_equal(apart[2 * n:], far)        # touches nothing: stays
    moved = apart[n:2 * n]
    np.testing.assert_allclose(moved - moved[0], V - V[0], atol=1e-12)   # only shifted
    shared = set(map(tuple, apart[:n])) & set(map(tuple, moved))
    assert not shared


def _crossings_brute_force(uv: np.ndarray, faces: np.ndarray) -> int:
    """Every pair of boundary edges tested (the reference)."""
    half = np.stack([faces, np.roll(faces, -1, axis=1)], axis=-1).reshape(-1, 2)
    keys = [tuple(sorted(e)) for e in half.tolist()]
    boundary = [e for e, k in zip(half.tolist(), keys, strict=True) if keys.count(k) == 1]
    count = 0
    for n, (a, b) in enumerate(boundary):
        for c, d in boundary[n + 1:]:
            if {a, b} & {c, d}:
                continue
            p, r, q, s = uv[a], uv[b] - uv[a], uv[c], uv[d] - uv[c]
            den = r[0] * s[1] - r[1] * s[0]
            if den == 0:
                continue
            t = ((q - p)[0] * s[1] - (q - p)[1] * s[0]) / den
            u = ((q - p)[0] * r[1] - (q - p)[1] * r[0]) / den
            count += 0 < t < 1 and 0 < u < 1
    return count


@pytest.mark.parametrize("seed", range(4))
def test_boundary_crossings_are_those_of_every_pair(seed):
    """Separate triangles of very different sizes scattered over one another (long edges
    over many grid cells, tiny ones inside one), and a strip of quads folded over itself:
    the grid's candidate pairs find every crossing a test of all pairs finds."""
    from solver.mesh.packing import boundary_crossings

    rng = np.random.default_rng(seed)
    k = 120
    centres = rng.uniform(0, 10, size=(k, 1, 2))
    sizes = np.exp(rng.uniform(np.log(0.01), np.log(8.0), size=(k, 1, 1)))
    sizes[:3] = 40.0                                        # edges over hundreds of cells
    uv = (centres + sizes * rng.normal(size=(k, 3, 2))).reshape(-1, 2)
    faces = np.arange(3 * k).reshape(k, 3)
    assert boundary_crossings(uv, faces) == _crossings_brute_force(uv, faces) > 0
    t = np.linspace(0, 6 * np.pi, 80)                      # a strip wound round three times
    strip = np.concatenate([np.stack([np.cos(t), np.sin(t)], 1) * (1 + 0.01 * t[:, None]),
                            np.stack([np.cos(t), np.sin(t)], 1) * (1.3 + 0.01 * t[:, None])])
    i = np.arange(79)
    quads = np.concatenate([np.stack([i, i + 1, i + 81], 1), np.stack([i, i + 81, i + 80], 1)])
    assert boundary_crossings(strip, quads) == _crossings_brute_force(strip, quads) > 0
