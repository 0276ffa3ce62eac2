import numpy as np
import pytest

from solver.core.errors import (
    DegenerateFaceError,
    InconsistentOrientationError,
    IndexOutOfRangeError,
    NonManifoldEdgeError,
    NonManifoldVertexError,
    ShapeMismatchError,
)
from solver.mesh.topology import build_topology, cycle_ranks
from tests.helpers.meshes import (
    bumpy_grid_with_holes,
    double_torus,
    grid,
    icosphere,
    load,
    torus_grid,
)


@pytest.mark.parametrize(("mesh", "components", "loops", "genus", "euler"), [
    (icosphere(2), 1, 0, 0, 2),
    (torus_grid(12, 8), 1, 0, 1, 0),
    (double_torus(), 1, 0, 2, -2),
    (bumpy_grid_with_holes(), 1, 3, 0, -1),
    (load("face.off"), 1, 1, 0, 1),
    (load("torus.off"), 1, 0, 1, 0),
])
def test_invariants(mesh, components, loops, genus, euler):
    topo = build_topology(mesh[1], len(mesh[0]))
    summary = topo.component_summary()
    assert len(summary) == components
    assert sum(c["boundary_loops"] for c in summary) == loops == len(topo.boundary_loops)
    assert sum(c["genus"] for c in summary) == genus
    assert sum(c["euler_characteristic"] for c in summary) == euler


def test_edges_sorted_and_halfedges_consistent():
    _, F = icosphere(1)
    topo = build_topology(F)
    e = topo.edges
    assert (e[:, 0] < e[:, 1]).all()
    assert (np.lexsort((e[:, 1], e[:, 0])) == np.arange(len(e))).all()
    fwd, bwd = topo.edge_halfedges.T
    assert (topo.halfedge_origin[fwd] == e[:, 0]).all()
    assert (topo.halfedge_origin[bwd] == e[:, 1]).all()
    assert (topo.halfedge_twin[topo.halfedge_twin] == np.arange(3 * len(F))).all()


def test_boundary_loops_are_ordered_cycles():
    _, F = bumpy_grid_with_holes()
    topo = build_topology(F)
    edge_set = {tuple(sorted(p)) for p in topo.edges[(topo.edge_halfedges < 0).any(1)].tolist()}
    for loop in topo.boundary_loops:
        pairs = {tuple(sorted(p)) for p in zip(loop, np.roll(loop, -1), strict=True)}
        assert pairs <= edge_set
    assert sorted(len(loop) for loop in topo.boundary_loops) == [8, 8, 50]


def test_two_components_and_isolated_vertex():
    V1, F1 = icosphere(1)
    _, F2 = grid(3, 2)
    F = np.concatenate([F1, F2 + len(V1) + 1])  # vertex len(V1) is unused
    topo = build_topology(F)
    assert topo.isolated_vertices.tolist() == [len(V1)]
    assert [c["closed"] for c in topo.component_summary()] == [True, False]


def test_cycle_ranks():
    successor = np.array([2, 0, 3, 1, 5, 4, 6])  # cycles (0 2 3 1), (4 5), (6)
    leader, rank = cycle_ranks(successor)
    assert leader.tolist() == [0, 0, 0, 0, 4, 4, 6]
    assert rank.tolist() == [0, 3, 1, 2, 0, 1, 0]


def test_index_out_of_range_names_face():
    with pytest.raises(IndexOutOfRangeError) as err:
        build_topology([[0, 1, 2], [0, 2, 9001]], n_vertices=4)
    assert err.value.field == "faces" and err.value.index == 1 and "9001" in str(err.value)


def test_negative_index():
    with pytest.raises(IndexOutOfRangeError):
        build_topology([[0, 1, -1]])


def test_repeated_corner_is_degenerate():
    with pytest.raises(DegenerateFaceError) as err:
        build_topology([[0, 1, 2], [2, 3, 3]])
    assert err.value.index == 1


def test_bad_shape():
    with pytest.raises(ShapeMismatchError):
        build_topology([[0, 1, 2, 3]])
    with pytest.raises(ShapeMismatchError):
        build_topology([])


def test_non_manifold_edge():
    with pytest.raises(NonManifoldEdgeError) as err:
        build_topology([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    assert err.value.details["edge"] == [0, 1]


def test_inconsistent_orientation_names_edge_and_faces():
    with pytest.raises(InconsistentOrientationError) as err:
        build_topology([[0, 1, 2], [0, 1, 3]])
    assert err.value.details["edge"] == [0, 1] and err.value.details["faces"] == [0, 1]


def test_duplicated_face_is_reported():
    with pytest.raises(InconsistentOrientationError):
        build_topology([[0, 1, 2], [0, 1, 2]])


def test_non_manifold_vertex_bowtie():
    with pytest.raises(NonManifoldVertexError) as err:
        build_topology([[0, 1, 2], [0, 3, 4]])
    assert err.value.details["vertex"] == 0


def _fan(centre: int, rim: list[int], closed: bool) -> list[list[int]]:
    """Triangles (centre, rim[i], rim[i + 1]) around ``centre`` (a closed ring if asked)."""
    stop = len(rim) if closed else len(rim) - 1
    return [[centre, rim[i], rim[(i + 1) % len(rim)]] for i in range(stop)]


@pytest.mark.parametrize("mesh", [icosphere(2), torus_grid(12, 8), double_torus(),
                                  bumpy_grid_with_holes(), load("face.off")])
def test_edges_given_by_the_forms_give_the_same_topology(mesh):
    """validate_forms passes the forms' edges: looked up when they are exactly the faces'
    sorted edges, ignored otherwise (a missing, extra, unsorted or reversed edge)."""
    _, F = mesh
    reference = build_topology(F)
    E = reference.edges
    wrong = [E[1:], np.concatenate([E, [[E[-1, 1] + 1, E[-1, 1] + 2]]]), E[::-1],
             np.where(np.arange(len(E))[:, None] == 3, E[:, ::-1], E), E[:, ::-1][::-1]]
    for edges in [E, *wrong]:
        topology = build_topology(F, edges=edges)
        for name in ("edges", "halfedge_edge", "halfedge_twin", "edge_halfedges", "edge_faces",
                     "vertex_component", "is_boundary_vertex"):
            np.testing.assert_array_equal(getattr(topology, name), getattr(reference, name))


@pytest.mark.parametrize("valence", [40, 1500])  # the fan walk, and the components beyond it
def test_non_manifold_vertices_of_any_valence(valence):
    rim = list(range(1, valence + 1))
    other = list(range(valence + 1, 2 * valence + 1))
    build_topology(_fan(0, rim, closed=False))                  # one open fan: manifold
    for faces in (_fan(0, rim, closed=False) + _fan(0, other, closed=False),   # two open
                  _fan(0, rim, closed=True) + _fan(0, other, closed=False)):   # closed + open
        with pytest.raises(NonManifoldVertexError) as err:
            build_topology(faces)
        assert err.value.details["vertex"] == 0
        assert "joins 2 separate fans" in str(err.value)
