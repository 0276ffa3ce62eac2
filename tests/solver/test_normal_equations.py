"""solver.refine.normal_equations: the Gauss-Newton matrix and gradient assembled in their fixed
pattern equal J^T J (plus the kept curvature) and J^T r built densely from the residuals'
gradients, with fixed vertices, soft and orientation handles, needle edges and degenerate
hinges (two slots on one vertex); each with the positions kept and computed at each assembly
(``KEPT_POSITIONS_BYTES``), in one block and pair by pair (``PRODUCT_BLOCK``)."""

import numpy as np
import pytest

from solver import fundamental_forms
from solver.mesh.topology import build_topology
from solver.refine import FormTargets, Handles, Refiner
from solver.refine import normal_equations as normal_equations_module
from tests.helpers.meshes import load, with_tiny_edges


@pytest.fixture(autouse=True, params=["kept positions", "computed positions",
                                      "computed, pair by pair"])
def product_block(request, monkeypatch):
    """Every test assembles with the positions kept (small systems), computed at each
    assembly (large ones), and its products one slot pair at a time."""
    if request.param != "kept positions":
        monkeypatch.setattr(normal_equations_module, "KEPT_POSITIONS_BYTES", 0)
    if request.param == "computed, pair by pair":
        monkeypatch.setattr(normal_equations_module, "PRODUCT_BLOCK", 1)


def dense_reference(refiner: Refiner, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(J^T J + curvature, J^T r) over the free coordinates, dense, from each group's
    residuals and gradients."""
    energy, system = refiner.form_energy, refiner.system
    dim, n = energy.dim, system.n_free * energy.dim
    H, g = np.zeros((n, n)), np.zeros(n)
    for group in energy.groups:
        r, G = group.evaluate(X)
        J = np.zeros((len(r), n))
        for slot in range(group.vertices.shape[1]):
            index = system.index[group.vertices[:, slot]]
            free = np.flatnonzero(index >= 0)
            for c in range(dim):
                np.add.at(J, (free, dim * index[free] + c), G[free, slot, c])
        H += J.T @ J
        g += J.T @ r
        if group.curvature is not None:
            rows, M = group.curvature(X, r)
            for row, block in zip(rows, M, strict=True):
                a, b = system.index[group.vertices[row]]
                for u, v, sign in ((a, a, 1), (b, b, 1), (a, b, -1), (b, a, -1)):
                    if u >= 0 and v >= 0:
                        H[dim * u:dim * u + dim, dim * v:dim * v + dim] += sign * block
    return H, g


def check(refiner: Refiner, X: np.ndarray) -> None:
    _, upper, gradient = refiner.system.normal_equations(X)
    H, g = dense_reference(refiner, X)
    scale = np.abs(H).max()
    assert np.abs(upper.toarray() - np.triu(H)).max() <= 1e-12 * scale
    assert np.abs(gradient - g).max() <= 1e-12 * np.abs(g).max()


@pytest.mark.parametrize("ratio", [0.03, 1e-4])
def test_handles_and_needle_edges(ratio):
    """Short edges at 3% of their length keep their curvature (stretched here); needles at
    1e-4 are tied (solver.refine.ties): a tied vertex's gradients land on its master's unknowns."""
    knight = load("decimated-knight.off")
    V, F = with_tiny_edges(*knight, count=5, ratio=ratio)
    forms = fundamental_forms(V, F)
    topology = build_topology(F, len(V))
    rng = np.random.default_rng(0)
    X = V + 1e-2 * forms.lengths.mean() * rng.normal(size=V.shape)
    split = np.arange(len(knight[0]), len(V))
    tiny = np.array([min(np.flatnonzero((topology.edges == p).any(axis=1)),
                         key=lambda e: forms.lengths[e]) for p in split])
    i, p = topology.edges[tiny].T
    X[p] = V[p] + 0.5 * (V[p] - V[i])  # stretched short edges: their curvature is kept
    handles = Handles(fixed=np.arange(0, 40, 3), soft_vertices=np.array([50, 60]),
                      soft_positions=V[[50, 60]] + 0.01, soft_weights=np.array([2.0, 3.0]),
                      frame_faces=np.array([7, 8]), frame_edges=rng.normal(size=(2, 2, 3)),
                      frame_weights=np.array([1.0, 5.0]))
    refiner = Refiner(FormTargets(topology, forms.lengths, forms.angles, angle_weight=0.3),
                      handles)
    ties = refiner.form_energy.ties
    if ratio < 0.01:
        assert sorted(ties.vertices.tolist()) == split.tolist()  # the later endpoint
        assert (refiner.system.index[ties.vertices] == refiner.system.index[i]).all()
        refiner.form_energy.tie(X)  # as a run's start: tied vertices on their needles
        assert np.allclose(np.linalg.norm(X[p] - X[i], axis=1), forms.lengths[tiny])
        check(refiner, X)
        return
    assert len(ties) == 0
    rows, _ = refiner.form_energy.groups[0].curvature(X, refiner.form_energy.groups[0]
                                                      .evaluate(X, False)[0])
    assert sorted(rows.tolist()) == sorted(tiny.tolist())
    check(refiner, X)


def test_degenerate_hinges_with_both_tips_on_one_vertex():
    """Two triangles glued back to back (a pillow): every hinge's two tips are one vertex."""
    V = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.3, 0.8, 0.0]])
    F = np.array([[0, 1, 2], [0, 2, 1]])
    topology = build_topology(F, 3)
    lengths = np.array([1.0, 0.9, 1.1])
    X = V + np.array([[0.0, 0.0, 0.1], [0.0, 0.05, 0.0], [0.02, 0.0, -0.1]])
    refiner = Refiner(FormTargets(topology, lengths, np.full(3, 3.0), angle_weight=0.5),
                      Handles())
    assert any(len(set(row[2:])) == 1 for row in refiner.form_energy.hinges[1])
    check(refiner, X)


@pytest.mark.parametrize("name", ["face.off"])
def test_planar(name):
    V, F = load(name)
    forms = fundamental_forms(V, F)
    topology = build_topology(F, len(V))
    X = V[:, :2] * [1.0, 0.2]  # squashed: some faces below the area floor
    refiner = Refiner(FormTargets(topology, forms.lengths, np.zeros_like(forms.angles)),
                      Handles(fixed=np.array([0, 1]), soft_positions=np.zeros((0, 2)),
                              frame_edges=np.zeros((0, 2, 2))), dim=2)
    check(refiner, X)
