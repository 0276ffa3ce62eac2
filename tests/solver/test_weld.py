"""Vertices joined by zero-length edges (issue 40, solver.mesh.weld), through the library:
capsule-like latitude-longitude grids (a pole repeated per longitude), a duplicated corner, a
face ``(a, a, b)``, and shared meshes with random edges split exactly at an endpoint (or
within 1e-15 of it). The counts of welded vertices and dropped faces are those of the
construction; forms -> reconstruct gives the file's vertices back (one rigid alignment, 1e-8
of the diagonal), welded copies at one position; noisy forms converge; deform, flatten and
blend answer per file vertex; handles on two copies of one vertex must agree."""

from __future__ import annotations

import numpy as np
import pytest

import solver
from solver.core.errors import (
    ConstraintError,
    DegenerateFaceError,
    ShapeMismatchError,
)
from solver.mesh.topology import build_topology
from solver.mesh.weld import WELD_TOLERANCE, weld_vertices
from tests.helpers.meshes import icosphere, rigid_alignment_error
from tests.helpers.real_meshes import diagonal
from tests.helpers.welded_meshes import CASES


@pytest.fixture(scope="module", params=list(CASES))
def case(request):
    return (request.param, *CASES[request.param]())


def _counts(forms: solver.Forms, n: int) -> tuple[int, int]:
    welded = 0 if forms.weld_map is None else int((forms.weld_map != np.arange(n)).sum())
    dropped = 0 if forms.dropped_faces is None else len(forms.dropped_faces)
    return welded, dropped


def _rebuilt(forms: solver.Forms, n: int, **options) -> solver.Reconstruction:
    return solver.reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles,
                              vertex_map=forms.vertex_map, weld_map=forms.weld_map,
                              placement=forms.placement, n_vertices=n, **options)


def test_forms_weld_and_drop_what_the_construction_made(case):
    _name, V, F, welded, dropped = case
    forms = solver.fundamental_forms(V, F)
    assert _counts(forms, len(V)) == (welded, dropped)
    # Independently: a dropped face repeats an index or has an edge of length ~0.
    edge = np.linalg.norm(V[F[:, [1, 2, 0]]] - V[F], axis=2).min(axis=1)
    collapsed = np.flatnonzero(edge <= WELD_TOLERANCE * diagonal(V))
    np.testing.assert_array_equal(forms.dropped_faces, collapsed)
    assert len(forms.faces) == len(F) - dropped
    if forms.weld_map is not None:  # welded into a vertex at its position, never a chain
        moved = np.flatnonzero(forms.weld_map != np.arange(len(V)))
        assert (forms.weld_map[moved] < moved).all()
        assert (forms.weld_map[forms.weld_map] == forms.weld_map).all()
        assert np.linalg.norm(V[moved] - V[forms.weld_map[moved]], axis=1).max() <= (
            WELD_TOLERANCE * diagonal(V))


def test_exact_round_trip_is_the_files_mesh(case):
    _name, V, F, welded, _dropped = case
    forms = solver.fundamental_forms(V, F)
    result = _rebuilt(forms, len(V))
    assert result.vertices.shape == V.shape
    assert rigid_alignment_error(result.vertices, V) < 1e-8
    if forms.weld_map is not None:  # copies of a welded vertex: one position
        np.testing.assert_array_equal(result.vertices, result.vertices[forms.weld_map])
        weld = result.report["input"]["weld"]
        assert weld["welded_vertices"] == welded
        assert result.report["isolated_vertices"] == []
    check = solver.check_integrability(forms.faces, forms.edges, forms.lengths,
                                       forms.angles, n_vertices=len(V),
                                       vertex_map=forms.vertex_map, weld_map=forms.weld_map)
    assert check.integrable and len(check.vertex_defect) == len(V)
    assert len(check.isolated_vertices) == 0


@pytest.mark.parametrize("name", ["latlong-capsule", "duplicated-corner",
                                  "bunny-welded-pairs"])
def test_noisy_forms_converge(name):
    V, F, _, _ = CASES[name]()
    forms = solver.fundamental_forms(V, F)
    rng = np.random.default_rng(8)
    inner = build_topology(forms.faces, n_vertices=len(forms.vertex_map)
                           if forms.vertex_map is not None else len(V)).interior_edges
    angles = forms.angles.copy()
    angles[inner] += rng.normal(0, 1e-3, len(inner))
    noisy = solver.Forms(forms.faces, forms.edges, forms.lengths, angles, forms.vertex_map,
                         forms.placement, weld_map=forms.weld_map)
    result = _rebuilt(noisy, len(V))
    refinement = result.report["refinement"]
    assert refinement["refined"] and refinement["converged"], refinement
    assert refinement["factorizations"] <= 4
    assert rigid_alignment_error(result.vertices, V) < 0.05


def test_deform_handles_on_welded_copies(case):
    _name, V, F, welded, _ = case
    forms = solver.fundamental_forms(V, F)
    rng = np.random.default_rng(6)
    handles = list(rng.choice(np.unique(forms.faces), 3, replace=False))
    if forms.weld_map is not None:  # a welded vertex and its representative, both
        copy = int(np.flatnonzero(forms.weld_map != np.arange(len(V)))[0])
        handles += [copy, int(forms.weld_map[copy])]
    handles = np.unique(handles)
    targets = V[handles] + rng.normal(0, 0.05 * diagonal(V), (len(handles), 3))
    if forms.weld_map is not None:
        same = forms.weld_map[handles]
        targets = targets[np.searchsorted(handles, same)]  # one target per welded vertex
    moved = solver.deform(V, F, handles, targets)
    np.testing.assert_allclose(moved.vertices[handles], targets, atol=1e-9 * diagonal(V))
    if forms.weld_map is not None:
        np.testing.assert_array_equal(moved.vertices, moved.vertices[forms.weld_map])
        assert moved.report["input"]["weld"]["welded_vertices"] == welded
        clash = targets.copy()
        k = int(np.flatnonzero(forms.weld_map[handles] != handles)[0])
        clash[k] += 0.01 * diagonal(V)
        with pytest.raises(ConstraintError) as err:
            solver.deform(V, F, handles, clash)
        assert err.value.field == "handle_positions"
        assert str(int(handles[k])) in str(err.value)


def test_rotation_faces_are_the_files(case):
    _name, V, F, _, _dropped = case
    forms = solver.fundamental_forms(V, F)
    if forms.dropped_faces is None:
        pytest.skip("no face dropped")
    kept = np.setdiff1d(np.arange(len(F)), forms.dropped_faces)
    face = int(kept[len(kept) // 2])
    deformer = solver.Deformer(V, F, [int(F[face, 0])], rotation_handles=[[face]])
    (solve_face,) = deformer._group_faces[0]
    np.testing.assert_array_equal(forms.vertex_map[forms.faces[solve_face]]
                                  if forms.vertex_map is not None else forms.faces[solve_face],
                                  (forms.weld_map if forms.weld_map is not None
                                   else np.arange(len(V)))[F[face]])
    with pytest.raises(ConstraintError, match="dropped"):
        solver.Deformer(V, F, [int(F[face, 0])], rotation_handles=[[forms.dropped_faces[0]]])


def test_flatten_and_blend_answer_per_file_vertex(case):
    name, V, F, _welded, dropped = case
    forms = solver.fundamental_forms(V, F)
    if name.startswith("latlong"):  # open along the seam: one chart
        flat = solver.parameterize(V, F)
        assert flat.report.input["weld"]["dropped_faces"] == dropped
        assert len(flat.uv_faces) == len(F) - dropped
        assert len(flat.flipped_faces) == 0
    tall = V * [1.0, 1.0, 1.5]
    middle = solver.interpolate(V, tall, F, 0.5)
    assert middle.shape == V.shape
    if forms.weld_map is not None:
        np.testing.assert_array_equal(middle, middle[forms.weld_map])
    assert rigid_alignment_error(middle, V * [1.0, 1.0, 1.25]) < 0.05


def test_a_split_seam_is_zipped_and_kept_open_on_request():
    """The latitude-longitude seam: coincident columns no face's edge joins, their boundary
    edges on each other and running opposite ways, are welded (a split seam); with
    ``coincident=False`` (the flattening's user cuts) they stay apart."""
    V, F, _, _ = CASES["latlong-sphere"]()
    columns = 16
    seam = np.arange(1, 10) * (columns + 1)
    np.testing.assert_array_equal(V[seam], V[seam + columns])
    forms = solver.fundamental_forms(V, F)
    assert (forms.weld_map[seam + columns] == seam).all()
    assert len(forms.placement.faces) == 1
    kept = solver.fundamental_forms(V, F, coincident=False)
    assert (kept.weld_map[seam + columns] == seam + columns).all()


def _split_by_face(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every face with corners of its own (a triangle soup, as flat shading writes it)."""
    return V[F.ravel()], np.arange(3 * len(F)).reshape(-1, 3)


@pytest.mark.parametrize("name", ["icosphere", "torus", "open grid"])
def test_a_triangle_soup_is_zipped_into_its_surface(name):
    from tests.helpers.meshes import grid, torus_grid

    V, F = {"icosphere": lambda: icosphere(2), "torus": lambda: torus_grid(10, 6),
            "open grid": lambda: grid(5, 4)}[name]()
    V, F = np.asarray(V, dtype=np.float64), np.asarray(F)
    soup_v, soup_f = _split_by_face(V, F)
    forms = solver.fundamental_forms(soup_v, soup_f)
    whole = solver.fundamental_forms(V, F)
    assert len(forms.placement.faces) == 1
    np.testing.assert_allclose(np.sort(forms.lengths), np.sort(whole.lengths))
    np.testing.assert_allclose(np.sort(forms.angles), np.sort(whole.angles), atol=1e-12)
    moved = solver.deform(soup_v, soup_f, [0, len(soup_v) - 1],
                          soup_v[[0, -1]] + [[0, 0, 0], [0, 0, 0.3]])
    same_place = (soup_v[:, None] == soup_v[None]).all(axis=2)
    gap = np.abs(moved.vertices[:, None] - moved.vertices[None]).max(axis=2)[same_place]
    assert gap.max() < 1e-12  # copies of one corner move together


def test_layers_folded_onto_each_other_and_touching_parts_stay_apart():
    from solver.mesh.manifold import manifold_topology
    from tests.helpers.real_meshes import boxes_sharing_an_edge, folded_sheet

    for V, F in (folded_sheet(), boxes_sharing_an_edge()):
        V, F = np.asarray(V), np.asarray(F)
        kept = manifold_topology(F, V, coincident=False)[0]
        zipped = manifold_topology(F, V)[0]
        assert kept.weld_map is None and zipped.weld_map is None


def test_weld_rule_is_deterministic_and_transitive():
    V = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 1, 0], [1, 1, 1e-14], [0, 1, 0]])
    weld = weld_vertices([[4, 0, 1], [0, 3, 5], [2, 3, 4], [1, 2, 0]], V)
    assert weld.target.tolist() == [0, 1, 2, 2, 2, 5]  # 4 -> 3 -> 2: the lowest index
    assert weld.dropped_faces.tolist() == [2]
    assert weld.faces.tolist() == [[2, 0, 1], [0, 2, 5], [1, 2, 0]]


def test_nothing_left_and_forms_with_a_repeated_index_are_refused():
    V = np.array([[0.0, 0, 0], [1, 0, 0], [1, 0, 0]])
    with pytest.raises(ShapeMismatchError, match="no face is left"):
        solver.fundamental_forms(V, [[0, 1, 2]])
    with pytest.raises(DegenerateFaceError):  # forms carry no positions: nothing to weld
        solver.check_integrability([[0, 0, 1]], [[0, 1]], [1.0], [0.0])
    forms = solver.fundamental_forms(*CASES["duplicated-corner"]()[:2])
    with pytest.raises(ConstraintError, match="welded"):
        chained = forms.weld_map.copy()
        moved = int(np.flatnonzero(chained != np.arange(len(chained)))[0])
        chained[chained[moved]] = moved  # the representative welded into its copy
        _rebuilt(solver.Forms(forms.faces, forms.edges, forms.lengths, forms.angles,
                              forms.vertex_map, forms.placement, weld_map=chained),
                 len(chained))


def test_huge_coordinates_do_not_weld_everything():
    V, F, _, _ = CASES["duplicated-corner"]()
    weld = weld_vertices(F, V * 1e300)
    assert len(weld.welded_vertices) == 1 and len(weld.dropped_faces) == 2


def test_a_constraint_on_a_welded_vertex_holds_the_welded_vertex():
    V, F, _, _ = CASES["duplicated-corner"]()
    forms = solver.fundamental_forms(V, F)
    copy = int(np.flatnonzero(forms.weld_map != np.arange(len(V)))[0])
    far = int(np.argmax(np.linalg.norm(V - V[copy], axis=1)))
    lifted = V[[copy, far]] + [0.0, 0.0, 0.3]
    held = solver.Constraints(position_vertices=np.array([copy, far]), positions=lifted)
    result = _rebuilt(forms, len(V), constraints=held, refine=False)
    np.testing.assert_allclose(result.vertices[[copy, forms.weld_map[copy], far]],
                               lifted[[0, 0, 1]], atol=1e-12)
    twice = solver.Constraints(position_vertices=np.array([copy, forms.weld_map[copy]]),
                               positions=V[[copy, copy]])
    with pytest.raises(ConstraintError):
        _rebuilt(forms, len(V), constraints=twice)
