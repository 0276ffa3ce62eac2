"""Faces written the wrong way round are turned back (solver.mesh.orientation) instead of being
cut apart: a mesh with flipped faces gives the answers of the same mesh consistently written
(spheres, a torus, an open sheet with 1, a few and 40% of their faces flipped; CGAL's
cube4-shuffled.off and tet-shuffled.off), a Möbius strip (no orientation exists) is still
cut, and parts are turned each on their own.
"""

from __future__ import annotations

import numpy as np
import pytest

import solver
from solver.mesh.manifold import manifold_topology
from solver.mesh.orientation import orientation_flips
from tests.helpers.meshes import grid, icosphere, torus_grid

CUBE_SHUFFLED = (  # CGAL Data/data/meshes/cube4-shuffled.off: quads, two written inwards
    np.array([[-1, -1, -1], [-1, 1, -1], [1, 1, -1], [1, -1, -1], [-1, -1, 1], [-1, 1, 1],
              [1, 1, 1], [1, -1, 1]], dtype=np.float64),
    np.array([[1, 2, 3], [1, 3, 0], [0, 1, 5], [0, 5, 4], [2, 6, 7], [2, 7, 3], [3, 7, 4],
              [3, 4, 0], [6, 5, 4], [6, 4, 7], [6, 2, 1], [6, 1, 5]]))


def _base_meshes() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    V, F = grid(7, 5)
    V = np.asarray(V, dtype=np.float64).copy()
    V[:, 2] = 0.3 * np.sin(V[:, 0] * 3) * np.cos(V[:, 1] * 2)
    return {"sphere": icosphere(2), "torus": torus_grid(12, 8), "sheet": (V, np.asarray(F))}


BASES = _base_meshes()


def _flipped(F: np.ndarray, share: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    count = max(1, int(share * len(F)))
    which = np.sort(rng.choice(len(F), count, replace=False))
    G = np.asarray(F, dtype=np.int64).copy()
    G[which] = G[which][:, [0, 2, 1]]
    return G, which


@pytest.mark.parametrize("share", [0.0, 0.05, 0.4])
@pytest.mark.parametrize("name", BASES)
def test_flipped_faces_are_turned_back_to_the_majoritys_orientation(name, share):
    V, F = BASES[name]
    G, which = _flipped(F, share, seed=len(name))
    flips = orientation_flips(G, len(V))
    np.testing.assert_array_equal(np.flatnonzero(flips), which)
    cut, _ = manifold_topology(G, V)
    np.testing.assert_array_equal(cut.faces, F)
    assert not cut.is_cut and cut.flipped_faces.tolist() == which.tolist()
    assert cut.sections()["reoriented"]["flipped_faces"] == len(which)


@pytest.mark.parametrize("name", BASES)
def test_a_mesh_with_flipped_faces_deforms_as_the_consistent_one(name):
    V, F = BASES[name]
    G, _ = _flipped(F, 0.05, seed=3)
    handles = [0, len(V) // 2, len(V) - 1]
    targets = V[handles] + [[0, 0, 0], [0.1, 0.2, 0.3], [0, 0, -0.2]]
    consistent = solver.deform(V, F, handles, targets)
    turned = solver.deform(V, G, handles, targets)
    np.testing.assert_allclose(turned.vertices, consistent.vertices, atol=1e-9)
    assert "cut" not in (turned.report.input or {})


def test_cgal_cube4_shuffled_is_one_closed_surface():
    V, F = CUBE_SHUFFLED
    cut, topology = manifold_topology(F, V)
    assert topology.n_vertices == 8 and not cut.is_cut
    assert [c["closed"] for c in topology.component_summary()] == [True]
    handles = [0, 6]
    moved = solver.deform(V, F, handles, V[handles] + [[0, 0, 0], [0.5, 0.5, 0.5]])
    assert "cut" not in moved.report.input  # before: two parts, copies 0.31 apart
    forms = solver.fundamental_forms(V, F)
    rebuilt = solver.reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles,
                                 vertex_map=forms.vertex_map, placement=forms.placement,
                                 n_vertices=len(V))
    np.testing.assert_allclose(rebuilt.vertices, V, atol=1e-12)


def _mobius(n: int = 12, w: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """A Möbius strip of ``n`` quads (two triangles each): no consistent orientation exists.
    Vertex k sits at (t_k, -w), vertex n + k at (t_k, +w); past t = 2 pi, -w is +w."""
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    V = np.concatenate([np.stack([(1 + s * np.cos(t / 2)) * np.cos(t),
                                  (1 + s * np.cos(t / 2)) * np.sin(t), s * np.sin(t / 2)],
                                 axis=1) for s in (-w, w)])
    quads = [(k, k + 1, n + k + 1, n + k) for k in range(n - 1)] + [(n - 1, n, 0, 2 * n - 1)]
    return V, np.array([tri for a, b, c, d in quads for tri in ([a, b, c], [a, c, d])])


def test_a_mobius_strip_is_left_to_the_cut_and_other_parts_are_still_turned():
    V, F = _mobius()
    assert not orientation_flips(F, len(V)).any()
    cut, _ = manifold_topology(F, V)
    assert cut.is_cut and cut.flipped_faces is None
    sphere_v, sphere_f = BASES["sphere"]
    G, which = _flipped(sphere_f, 0.05, seed=9)
    both_v = np.concatenate([V, sphere_v + 5.0])
    both_f = np.concatenate([F, G + len(V)])
    cut, _ = manifold_topology(both_f, both_v)
    assert cut.flipped_faces.tolist() == (which + len(F)).tolist() and cut.is_cut


def test_a_tie_keeps_the_lowest_faces_orientation():
    assert orientation_flips(np.array([[0, 1, 2], [0, 3, 2]]), 4).tolist() == [False, True]
    assert orientation_flips(np.array([[0, 3, 2], [0, 1, 2]]), 4).tolist() == [False, True]
