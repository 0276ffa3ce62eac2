import numpy as np
import pytest

from solver import check_integrability, fundamental_forms
from solver.linear.integrability import IntegrabilityReport
from tests.helpers.meshes import (
    bumpy_grid_with_holes,
    double_torus,
    flat_torus_forms,
    icosphere,
    load,
    torus_grid,
)

REAL_MESHES = ["decimated-knight.off", "torus.off", "face.off", "octopus-low-surface.off",
               "bar.off", "cylinder.off"]


def forms_of(mesh):
    V, F = mesh
    return fundamental_forms(V, F)


def check(forms, **kw):
    return check_integrability(forms.faces, forms.edges, forms.lengths, forms.angles, **kw)


@pytest.mark.parametrize("name", REAL_MESHES)
def test_real_meshes_are_integrable(name):
    report = check(forms_of(load(name)))
    assert report.integrable
    assert report.max_defect <= 1e-10
    assert report.vertex_defect.max() <= 1e-10


def interior_edge_between_interior_vertices(forms, report):
    boundary = set(np.concatenate(report.boundary_loops).tolist()) if report.boundary_loops \
        else set()
    for e in np.flatnonzero(forms.angles != 0)[::7]:
        i, j = forms.edges[e]
        if i not in boundary and j not in boundary:
            return int(e)
    raise AssertionError("no interior edge")


@pytest.mark.parametrize("name", ["decimated-knight.off", "face.off", "torus.off"])
def test_changed_angle_flags_exactly_its_end_vertices(name):
    forms = forms_of(load(name))
    e = interior_edge_between_interior_vertices(forms, check(forms))
    forms.angles[e] += 0.01
    report = check(forms)
    assert not report.integrable
    assert sorted(report.failing_vertices.tolist()) == sorted(forms.edges[e].tolist())
    # The perturbation tilts normals: it is (mostly) a Codazzi defect.
    i, j = forms.edges[e]
    assert report.codazzi_defect[[i, j]].min() > 1e-3


@pytest.mark.parametrize("name", ["decimated-knight.off", "face.off"])
def test_changed_length_flags_only_its_two_triangles(name):
    forms = forms_of(load(name))
    e = interior_edge_between_interior_vertices(forms, check(forms))
    forms.lengths[e] *= 1.01
    report = check(forms)
    i, j = forms.edges[e]
    in_both = np.isin(forms.faces, [i, j]).sum(axis=1) == 2
    expected = set(forms.faces[in_both].ravel().tolist())
    assert in_both.sum() == 2
    assert set(report.failing_vertices.tolist()) == expected
    # A metric change alone is seen by Gauss's equation (rotation about the normal).
    assert np.abs(report.gauss_defect[list(expected)]).max() > 1e-4


def test_defect_parts_bound_the_total():
    forms = forms_of(load("decimated-knight.off"))
    rng = np.random.default_rng(0)
    forms.angles += rng.normal(scale=0.01, size=len(forms.angles))
    r = check(forms)
    assert (r.vertex_defect <= np.abs(r.gauss_defect) + r.codazzi_defect + 1e-12).all()
    assert (r.vertex_defect >= r.codazzi_defect - 1e-12).all()


@pytest.mark.parametrize(("mesh", "genus", "rotation_loops"), [
    (torus_grid(16, 9), 1, 2), (double_torus(), 2, 4), (load("torus.off"), 1, 2)])
def test_closed_higher_genus_passes_global_check(mesh, genus, rotation_loops):
    report = check(forms_of(mesh))
    assert report.genus == genus
    assert len(report.rotation_holonomy) == rotation_loops == 2 * genus
    assert len(report.translation_holonomy) == 2 * genus
    assert report.global_integrable and report.integrable
    assert max(g.magnitude for g in report.rotation_holonomy + report.translation_holonomy) < 1e-10


def test_flat_torus_is_locally_but_not_globally_integrable():
    faces, edges, lengths, angles = flat_torus_forms(8, 6)
    report = check_integrability(faces, edges, lengths, angles)
    assert report.local_integrable
    assert report.vertex_defect.max() < 1e-12
    assert not report.global_integrable and not report.integrable
    assert all(g.passes for g in report.rotation_holonomy)   # flat: no rotation
    failing = [g for g in report.translation_holonomy if not g.passes]
    assert len(failing) == 2
    for g in failing:
        # The closing edge names the generator; its translation is a period of the grid.
        assert edges[g.edge_index].tolist() == g.edge
        length = np.linalg.norm(g.translation)
        periods = [np.hypot(a * 8, b * 6) for a in range(-2, 3) for b in range(-2, 3)
                   if (a, b) != (0, 0)]
        assert min(abs(length - p) for p in periods) < 1e-9


def test_open_surface_with_holes_checks_loops_around_holes():
    V, F = bumpy_grid_with_holes()
    forms = fundamental_forms(V, F)
    report = check(forms)
    assert report.integrable and len(report.rotation_holonomy) == 2  # 2g + b - 1
    # Twist the strip between the two holes: local checks still pass where untouched,
    # and an inconsistent rotation around a hole is caught either locally or globally.
    forms.angles[np.flatnonzero(forms.angles)[40]] += 0.2
    assert not check(forms).integrable


def test_triangle_inequality_violation_is_reported_not_raised():
    forms = forms_of(icosphere(1))
    forms.lengths[5] = 10.0
    report = check(forms)
    assert not report.integrable
    assert len(report.triangle_violations) == 2
    face_edges = set(forms.edges[5].tolist())
    for t in report.triangle_violations:
        assert face_edges <= set(forms.faces[t].tolist())


def test_report_round_trips_through_json():
    report = check(forms_of(torus_grid(10, 6)))
    data = report.to_dict()
    again = IntegrabilityReport.from_dict(data)
    assert again.genus == 1 and np.array_equal(again.vertex_defect, report.vertex_defect)
    assert again.rotation_holonomy[0].kind == "rotation"


@pytest.mark.parametrize(("name", "expected"), [
    ("sphere", [0]), ("disk", [0]), ("torus", [2]), ("double torus", [4]),
    ("disk with two holes", [2]), ("torus, sphere and disk", [2, 0, 0])])
def test_homology_rank_counts_the_independent_loops(name, expected):
    """2g + b - 1 loops (2g when closed), by the meshes' known genus and holes; and the
    global holonomy reports that many rotation loops."""
    from solver.linear.integrability import global_holonomy, homology_rank
    from solver.linear.system import energy_terms
    from solver.mesh.topology import build_topology
    from tests.helpers.meshes import (
        bumpy_grid_with_holes,
        double_torus,
        grid,
        icosphere,
        side_by_side,
        torus_grid,
    )

    V, F = {"sphere": lambda: icosphere(2), "disk": lambda: grid(5, 4),
            "torus": lambda: torus_grid(8, 6), "double torus": double_torus,
            "disk with two holes": bumpy_grid_with_holes,
            "torus, sphere and disk": lambda: side_by_side(torus_grid(8, 6), icosphere(2),
                                                            grid(4, 4))}[name]()
    topology = build_topology(F, len(V))
    assert homology_rank(topology).tolist() == expected
    forms = fundamental_forms(V, F)
    rotations, _ = global_holonomy(energy_terms(topology, forms.lengths, forms.angles),
                                   1e-6, 1.0)
    assert len(rotations) == sum(expected)


def test_summary_lists_the_largest_loops_of_each_kind_and_counts_them_all():
    """Six tori side by side: 12 loops of each kind, more than a summary lists; the angles
    of one torus are bent so that some of its loops fail. The summary's loops are the full
    report's largest (largest first), its counts the full report's."""
    from solver.linear.integrability import WORST_COUNT
    from tests.helpers.meshes import side_by_side

    forms = forms_of(side_by_side(*[torus_grid(10, 6)] * 6))
    bent = np.flatnonzero(forms.faces.max(axis=1) < 60)   # faces of the first torus
    edges = np.unique(np.sort(forms.faces[bent][:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), 1), axis=0)
    first = np.flatnonzero((forms.edges[:, None] == edges[None]).all(-1).any(1))
    forms.angles[first] *= 0.9
    report = check(forms)
    summary = report.summary()
    for kind in ("rotation", "translation"):
        loops = getattr(report, f"{kind}_holonomy")
        assert len(loops) == 12 > WORST_COUNT and summary[f"{kind}_loop_count"] == 12
        listed = [g["magnitude"] for g in summary[f"{kind}_holonomy"]]
        assert listed == sorted((g.magnitude for g in loops), reverse=True)[:WORST_COUNT]
    failing = sum(not g.passes for g in report.rotation_holonomy + report.translation_holonomy)
    assert summary["failing_loop_count"] == failing > 0
