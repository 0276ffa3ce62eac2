"""The nearest surface (solver.refine): real numbers against independent truth.

Noise tests compare with the mesh the forms came from; scale tests with the prescribed
lengths; interpolation with its endpoints; deformation with libigl's ARAP run here, in the
same test; parameterization with libigl's ARAP parameterization.
"""

import numpy as np
import pytest

import solver.refine.refiner as refine_module
from solver import (
    Constraints,
    Deformer,
    deform,
    fundamental_forms,
    interpolate,
    linalg,
    parameterize,
    reconstruct,
)
from solver.differentiable import reconstruct_vjp
from solver.mesh.metrics import distortion
from solver.mesh.topology import build_topology
from solver.refine import (
    FormTargets,
    Handles,
    Refiner,
    factor_precision,
    hinge_angles,
    hinges,
    refine,
    signed_areas,
)
from solver.refine.steps import DEFAULT_STEP_RULES, StepRules
from tests.helpers.libigl_reference import arap_deformation, arap_parameterization, flipped_faces
from tests.helpers.meshes import (
    SHARED,
    double_torus,
    icosphere,
    load,
    rigid_alignment_error,
    with_cap_faces,
    with_noisy_angles,
    with_tiny_edges,
)

NOISY_MESHES = {
    "knight (genus 0)": lambda: load("decimated-knight.off"),
    "torus (genus 1)": lambda: load("torus.off"),
    "double torus (genus 2)": double_torus,
    "face (open)": lambda: load("face.off"),
    "octopus (skinny triangles)": lambda: load("octopus-low-surface.off"),
}


def solve(forms, **kw):
    return reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles, **kw)


def length_ratios(X, forms, lengths=None):
    L = forms.lengths if lengths is None else lengths
    return np.linalg.norm(X[forms.edges[:, 1]] - X[forms.edges[:, 0]], axis=1) / L


# --------------------------------------------------------------------- the derivatives


def test_hinge_angles_and_gradients_match_forms_and_finite_differences():
    V, F = load("octopus-low-surface.off")
    topology = build_topology(F, len(V))
    inner, hinge = hinges(topology)
    theta, G = hinge_angles(V, hinge)
    assert np.abs(theta - fundamental_forms(V, F).angles[inner]).max() < 1e-12
    rng = np.random.default_rng(0)
    D = rng.normal(size=V.shape)
    h = 1e-6 * np.ptp(V)
    plus, _ = hinge_angles(V + h * D, hinge, gradients=False)
    minus, _ = hinge_angles(V - h * D, hinge, gradients=False)
    directional = np.einsum("kcd,kcd->k", G, D[hinge])
    assert np.allclose((plus - minus) / (2 * h), directional, rtol=1e-5, atol=1e-5)
    assert np.abs(G.sum(axis=1)).max() < 1e-8 * np.abs(G).max()  # translation invariant


def test_signed_area_gradients_match_finite_differences():
    V, F = load("face.off")
    X = V[:, :2]
    _, G = signed_areas(X, F)
    D = np.random.default_rng(1).normal(size=X.shape)
    h = 1e-6
    plus, _ = signed_areas(X + h * D, F, gradients=False)
    minus, _ = signed_areas(X - h * D, F, gradients=False)
    assert np.allclose((plus - minus) / (2 * h), np.einsum("kcd,kcd->k", G, D[F]), atol=1e-6)


def test_the_curvature_kept_across_needle_edges_matches_finite_differences():
    """The Gauss-Newton matrix keeps ``r ∇²r`` across stretched edges far shorter than the
    mean (solver.refine.form_energy.STRETCH_CURVATURE): on each such edge, the second derivative
    of r^2 / 2 along random directions equals (∇r . d)^2 + d^T (r ∇²r) d; on the other
    edges nothing is kept."""
    # Edges 3% of their length (not needles: solver.refine.ties ties the endpoints of those).
    knight = load("decimated-knight.off")
    V, F = with_tiny_edges(*knight, count=5, ratio=0.03)
    topology = build_topology(F, len(V))
    forms = fundamental_forms(V, F)
    # The shortest edge at each split vertex (the later ones) is its tiny edge.
    tiny = np.array([min(np.flatnonzero((topology.edges == p).any(axis=1)),
                         key=lambda e: forms.lengths[e]) for p in range(len(knight[0]), len(V))])
    assert len(tiny) == 5 and Refiner(FormTargets(topology, forms.lengths, forms.angles),
                                      Handles()).form_energy.ties.vertices.size == 0
    X = V.copy()
    i, p = topology.edges[tiny].T  # the split vertex is the later one
    X[p] += 0.5 * (V[p] - V[i])     # stretch each needle edge by 50%
    energy = FormTargets(topology, forms.lengths, forms.angles)
    group = Refiner(energy, Handles()).form_energy.groups[0]
    r, G = group.evaluate(X)
    rows, M = group.curvature(X, r)
    assert set(rows) == set(tiny)
    D = np.zeros_like(X)
    D[np.concatenate([i, p])] = np.random.default_rng(2).normal(size=(2 * len(tiny), 3))
    D[np.concatenate([i, p])] *= np.tile(forms.lengths[tiny], 2)[:, None]
    h = 1e-3
    half_square = [0.5 * group.evaluate(X + t * h * D, False)[0][rows] ** 2 for t in (-1, 0, 1)]
    second = (half_square[0] - 2 * half_square[1] + half_square[2]) / h**2
    edges = topology.edges[rows]
    d = D[edges[:, 1]] - D[edges[:, 0]]
    gauss_newton = np.einsum("kcd,kcd->k", G[rows], D[edges]) ** 2
    assert np.allclose(second, gauss_newton + np.einsum("ki,kij,kj->k", d, M, d), rtol=1e-4)
    assert np.all(np.einsum("ki,kij,kj->k", d, M, d) > 0.1 * gauss_newton)  # not negligible


def distance_to_exact_optimum(result, forms) -> float:
    """Largest vertex distance, over the answer's size, from a reconstruction ``result`` of
    ``forms`` to the exact optimum of its energy (the adjoint's Newton polish with the exact
    Hessian, which must converge)."""
    optimum, vjp = reconstruct_vjp(forms.faces, forms.edges, forms.lengths, forms.angles)
    assert vjp.report["polish_converged"]
    size = np.ptp(result.vertices, axis=0).max()
    return float(np.abs(optimum.vertices - result.vertices).max() / size)


def test_noisy_forms_on_needle_edges_converge_near_the_exact_optimum():
    """Noisy angles on a torus with 20 edges split to 1e-4 of their length: the default
    refinement converges within 1e-5 of the size of the exact optimum (the adjoint's Newton
    polish) and within 3e-5 of the diagonal of the original, in at most 3 factorizations.
    Before the damping stopped scaling with the needles' diagonal (NEEDLE_STIFFNESS): 4
    factorizations, 3.7e-4 from the optimum and 6.5e-5 from the original (8
    factorizations before the needle edges' curvature was kept)."""
    V, F = with_tiny_edges(*load("torus.off"), count=20)
    forms = with_noisy_angles(fundamental_forms(V, F), seed=4)
    result = solve(forms)
    report = result.report["refinement"]
    assert report["converged"] and report["factorizations"] <= 3
    assert rigid_alignment_error(result.vertices, V) < 3e-5
    assert distance_to_exact_optimum(result, forms) <= 1e-5


@pytest.mark.skipif(not (SHARED / "cactus.off").exists(),
                    reason="../shared/meshes is not present")
def test_well_predicted_steps_of_a_kept_factor_finish_without_refactorizing():
    """Angles x 0.8 on the cactus (10K faces): after two Gauss-Newton factorizations, the
    steps of the second one lower E as it predicts but move a vertex by just over
    QUASI_NEWTON_REACH (1.1e-2 of the mean edge): they continue on that factor until one
    moves less, instead of refactorizing to confirm (3 factorizations before). The answer is
    within 1e-4 of its size of the exact optimum (the adjoint's Newton polish)."""
    V, F = load(SHARED / "cactus.off")
    forms = fundamental_forms(V, F)
    forms.angles *= 0.8
    result = solve(forms)
    report = result.report["refinement"]
    assert report["converged"] and report["factorizations"] == 2, report["factorizations"]
    assert distance_to_exact_optimum(result, forms) <= 1e-4


@pytest.mark.skipif(not (SHARED / "nefertiti.obj").exists(),
                    reason="../shared/meshes is not present")
def test_a_refused_step_of_a_factor_that_expects_little_ends_the_run():
    """Noisy angles on nefertiti (100K faces, min angle 0.06°): after one Gauss-Newton
    factorization the kept factor predicts 1.02e-3 of E (just over StopRules.energy_tolerance) and
    its step gains nothing at any length: the run ends there, converged, instead of
    factorizing again to confirm (StopRules.refused_prediction), as near the mesh the
    forms came from as the confirmed answer (3.4e-5 of the diagonal)."""
    V, F = load(SHARED / "nefertiti.obj")
    forms = with_noisy_angles(fundamental_forms(V, F))
    result = solve(forms)
    report = result.report["refinement"]
    assert report["converged"] and report["factorizations"] == 1, report["factorizations"]
    assert rigid_alignment_error(result.vertices, V) < 5e-5


def test_the_knight_that_crawled_converges():
    """A knight with 5 faces flattened to 2e-3 of their width (above CAP_HEIGHT: their
    angles are kept) and 10 needle edges, noisy angles. Before the needles were tied
    (solver.refine.ties) the damping grew until steps barely lowered E and the refinement stopped
    ``stalled`` after 12-21 iterations; now it converges in a few factorizations, to a lower
    energy than its start, near the original."""
    V, F = load("decimated-knight.off")
    V, F = with_tiny_edges(with_cap_faces(V, F, 5, height=2e-3), F, count=10)
    forms = with_noisy_angles(fundamental_forms(V, F), seed=4)
    report = (result := solve(forms)).report["refinement"]
    assert report["converged"] and report["stop_reason"] == "converged", report
    assert report["factorizations"] <= 4
    assert report["energy_after"] <= report["energy_before"]
    assert rigid_alignment_error(result.vertices, V) < 2e-3


@pytest.mark.parametrize("height", [1e-6, 1e-4])
def test_cap_faces_converge_in_few_factorizations(height):
    """The same knight with its 5 faces flattened to ``height`` of their width (under
    CAP_HEIGHT: apex residuals replace their edges' angles) converges in a few
    factorizations (it stalled after 17 iterations and 15-22 factorizations with their
    angles), near the original, and E nearly vanishes where the forms are met."""
    V, F = load("decimated-knight.off")
    V, F = with_tiny_edges(with_cap_faces(V, F, 5, height=height), F, count=10)
    forms = fundamental_forms(V, F)
    energy = Refiner(FormTargets(build_topology(F, len(V)), forms.lengths, forms.angles))
    assert len(energy.form_energy.caps.faces) >= 5
    # At the original only the caps' and the needle faces' own heights remain (at most
    # 1e-4 of their bases): E ~1e-7, against 3.3e-6 at the noisy forms' optimum.
    assert energy.energy(V) <= 2e-7
    forms = with_noisy_angles(forms, seed=4)
    report = (result := solve(forms)).report["refinement"]
    assert report["converged"] and report["factorizations"] <= 3, report["factorizations"]
    assert rigid_alignment_error(result.vertices, V) < 1e-4


def test_refine_recovers_a_shrunk_mesh_exactly():
    V, F = load("decimated-knight.off")
    forms = fundamental_forms(V, F)
    rng = np.random.default_rng(3)
    start = 0.8 * V + rng.normal(scale=1e-3, size=V.shape)
    fit = refine(start, FormTargets(build_topology(F, len(V)), forms.lengths, forms.angles))
    assert fit.report["converged"]
    assert rigid_alignment_error(fit.vertices, V) < 1e-7
    assert fit.report["energy_after"] < 1e-12 * fit.report["energy_before"]


# ---------------------------------------------------------------- forms that don't integrate


@pytest.mark.parametrize("name", list(NOISY_MESHES))
def test_noisy_angles_give_the_original_mesh_back(name):
    """Dihedral noise N(0, 1e-3) rad: the refined answer lies within 1e-4 of the bbox
    diagonal of the mesh the forms came from (after rigid alignment), and much closer than
    the linear answer."""
    V, F = NOISY_MESHES[name]()
    forms = with_noisy_angles(fundamental_forms(V, F), seed=5)
    linear = solve(forms, refine=False)
    refined = solve(forms)
    report = refined.report["refinement"]
    assert report["refined"] and report["iterations"] >= 1
    error = rigid_alignment_error(refined.vertices, V)
    assert error < 1e-4
    assert error < 0.5 * rigid_alignment_error(linear.vertices, V)
    assert report["energy_after"] <= report["energy_before"]


@pytest.mark.parametrize("name", ["decimated-knight.off", "face.off"])
def test_scaled_angles_keep_the_prescribed_lengths(name):
    """Every dihedral angle x 0.8 (no surface has these forms): the linear answer collapses
    (mean length ratio 0.06 on the knight); the refined one keeps the prescribed lengths:
    mean ratio within 1% of 1, mean relative error <= 1%, 95th percentile <= 3%."""
    V, F = load(name)
    forms = fundamental_forms(V, F)
    forms.angles *= 0.8
    linear = solve(forms, refine=False)
    refined = solve(forms)
    ratio = length_ratios(refined.vertices, forms)
    assert abs(ratio.mean() - 1.0) < 0.01
    assert np.abs(ratio - 1).mean() <= 0.01
    assert np.percentile(np.abs(ratio - 1), 95) <= 0.03
    linear_error = np.abs(length_ratios(linear.vertices, forms) - 1).mean()
    assert np.abs(ratio - 1).mean() < 0.5 * linear_error
    after = refined.report["refinement"]["after"]
    assert after["length_error"]["mean"] == pytest.approx(np.abs(ratio - 1).mean())


def test_integrable_forms_stay_exact_and_on_the_tree_path():
    V, F = load("decimated-knight.off")
    result = solve(fundamental_forms(V, F))
    assert result.report["solve_path"] == "tree-integration"
    assert result.report["refinement"]["refined"] is False
    assert rigid_alignment_error(result.vertices, V) < 1e-8


def test_refined_answer_is_never_worse_than_the_linear_one():
    V, F = icosphere(2)
    forms = fundamental_forms(V, F)
    rng = np.random.default_rng(9)
    forms.angles += rng.normal(scale=0.2, size=len(forms.angles))
    forms.lengths *= rng.uniform(0.9, 1.1, size=len(forms.lengths))
    linear = solve(forms, refine=False, orthonormalize=True)
    refined = solve(forms, refine=True)
    report = refined.report["refinement"]
    assert report["energy_after"] <= report["energy_before"]
    assert report["after"]["length_error"]["rms"] <= report["before"]["length_error"]["rms"] \
        or report["after"]["angle_error"]["rms"] <= report["before"]["angle_error"]["rms"]
    lin = np.abs(length_ratios(linear.vertices, forms) - 1).mean()
    ref = np.abs(length_ratios(refined.vertices, forms) - 1).mean()
    assert ref < lin


def test_refinement_keeps_hard_constraints_and_anchors():
    V, F = load("decimated-knight.off")
    forms = fundamental_forms(V, F)
    forms.angles *= 0.9
    pinned = np.array([3, 77, 250])
    targets = V[pinned] * 1.02
    result = solve(forms, constraints=Constraints(position_vertices=pinned, positions=targets))
    assert result.report["refinement"]["refined"]
    assert np.array_equal(result.vertices[pinned], targets)
    free = solve(forms)
    anchor = free.report["anchored_components"][0]
    assert np.abs(free.vertices[anchor["vertex"]]).max() < 1e-12
    assert np.abs(free.frames[anchor["face"]] - np.eye(3)).max() < 1e-9


def test_frame_constraint_orients_the_refined_mesh():
    V, F = load("decimated-knight.off")
    forms = fundamental_forms(V, F)
    forms.angles *= 0.9
    angle = 0.7
    R = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0],
                  [0, 0, 1.0]])
    result = solve(forms, constraints=Constraints(
        position_vertices=[F[0, 0]], positions=[[0.0, 0.0, 0.0]], frame_faces=[0],
        frames=[R]))
    assert result.report["refinement"]["refined"]
    assert np.abs(result.frames[0] - R).max() < 1e-3


# ---------------------------------------------------------------------- interpolation


def test_form_space_blend_halves_the_length_change_and_beats_vertex_blending():
    """Two near-isometric poses of the bar (rest and a refined 135-degree twist): at
    t = 0.5 the blended lengths ask for half the endpoint's length change; the refined blend
    stays within 0.6x of it, while blending vertices linearly folds the twist."""
    from tests.helpers import DATA
    from tests.helpers.botsch_sorkine import load_case

    case = load_case(DATA, "bar")
    twisted = deform(case.vertices, case.faces, case.handles, case.handle_targets(),
                     rotation_handles=[case.handle_faces()],
                     handle_rotations=case.transform[None, :3, :3], roi=case.roi).vertices
    rest = fundamental_forms(case.vertices, case.faces)
    endpoint = np.abs(length_ratios(twisted, rest) - 1).mean()
    mid, reports = interpolate(case.vertices, twisted, case.faces, 0.5, return_reports=True)
    assert reports[0]["refined"]
    change = np.abs(length_ratios(mid, rest) - 1).mean()
    vertex_blend = np.abs(length_ratios(0.5 * (case.vertices + twisted), rest) - 1).mean()
    linear = interpolate(case.vertices, twisted, case.faces, 0.5, refine=False)
    assert change <= 0.6 * endpoint
    assert change < vertex_blend
    assert change < np.abs(length_ratios(linear, rest) - 1).mean()


# ------------------------------------------------------------------------ deformation


@pytest.mark.parametrize("name", ["bar", "cylinder"])
def test_refined_deformation_matches_or_beats_arap(name):
    """Botsch-Sorkine bar (135 degree twist) and cylinder (120 degree bend), positions and
    rotation handles, defaults: mean relative edge-length change + mean dihedral change <=
    libigl ARAP's (spokes and rims, 200 iterations) in the same run, max length change <=
    2x ARAP's; the linear answer does not manage either."""
    from tests.helpers import DATA
    from tests.helpers.botsch_sorkine import load_case

    case = load_case(DATA, name)
    kw = {"rotation_handles": [case.handle_faces()],
          "handle_rotations": case.transform[None, :3, :3], "roi": case.roi}
    ours = deform(case.vertices, case.faces, case.handles, case.handle_targets(), **kw)
    linear = deform(case.vertices, case.faces, case.handles, case.handle_targets(),
                    refine=False, **kw)
    pytest.importorskip("igl")
    arap = distortion(case.vertices, arap_deformation(case), case.faces)

    def measure(d):
        return (d["length_summary"]["mean"] + d["angle_summary"]["mean"],
                d["length_summary"]["max"])

    ours_sum, ours_max = measure(ours.report["distortion"])
    arap_sum, arap_max = measure(arap)
    linear_sum, _ = measure(linear.report["distortion"])
    assert ours.report["refinement"]["refined"]
    assert np.abs(ours.vertices[case.handles] - case.handle_targets()).max() < 1e-9
    assert np.array_equal(ours.vertices[case.fixed], case.vertices[case.fixed])
    assert ours_sum <= arap_sum
    assert ours_max <= 2 * arap_max
    assert linear_sum > arap_sum


def test_deformer_refines_each_drag_on_request():
    V, F = load("face.off")
    handles = np.array([10, 200, 600, 900])
    deformer = Deformer(V, F, handles, refine=True)
    rng = np.random.default_rng(4)
    targets = V[handles] + rng.normal(scale=3.0, size=(4, 3))
    refined = deformer.solve(targets)
    assert deformer.last_report["refined"]
    assert np.abs(refined[handles] - targets).max() <= 1e-10 * np.ptp(V)
    linear = deformer.solve(targets, refine=False)
    assert deformer.last_report["refined"] is False
    rest = fundamental_forms(V, F)
    assert np.abs(length_ratios(refined, rest) - 1).mean() < np.abs(
        length_ratios(linear, rest) - 1).mean()
    # A rigid motion of every handle: the linear answer is exact, nothing to refine.
    exact = deformer.solve(V[handles] + [1.0, 2.0, 3.0])
    assert deformer.last_report["refined"] is False
    assert np.abs(exact - V - np.array([1.0, 2.0, 3.0])).max() < 1e-8 * np.ptp(V)


def test_session_drags_on_a_kept_factor_beat_arap_and_match_a_fresh_refinement():
    """A session's drags after the first start from the previous drag's factor and take
    quasi-Newton steps on it (solver.refine.steps.StepRules.kept_steps): the last shape of a drag
    sequence
    is better than libigl's ARAP with 10 iterations per drag run on the same drags here,
    and its energy is within a few percent of a refinement that starts afresh."""
    igl = pytest.importorskip("igl")
    V, F = load("face.off")
    handles = np.array([10, 200, 600, 900])
    direction = np.random.default_rng(4).normal(size=(4, 3))
    drags = [V[handles] + 0.75 * k * direction for k in range(1, 5)]
    session = Deformer(V, F, handles, refine=True)
    for P in drags:
        X = session.solve(P)
        assert session.last_report["converged"]
        assert np.abs(X[handles] - P).max() <= 1e-10 * np.ptp(V)
    fresh = Deformer(V, F, handles, refine=True)
    Y = fresh.solve(drags[-1])
    assert session.last_report["energy_after"] <= 1.05 * fresh.last_report["energy_after"]
    data = igl.ARAPData()
    data.max_iter = 10
    igl.arap_precomputation(V, F, 3, handles.astype(np.int64), data)
    U = V.copy()
    for P in drags:
        U = igl.arap_solve(P, data, U)

    def quality(Z):
        d = distortion(V, Z, F)
        return d["length_summary"]["mean"] + d["angle_summary"]["mean"]

    assert quality(X) < quality(U)
    assert quality(X) <= 1.1 * quality(Y)


def test_soft_handles_and_rotation_only_handles_refine():
    """One patch turned by 90 degrees, another held, one soft position: no rigid motion has
    these handles, so the answer is refined, and the turned patch's normals follow."""
    V, F = load("face.off")
    rotation = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    turned, held = np.arange(0, 40), np.arange(1900, 1940)
    out = deform(V, F, [500], V[[500]], rotation_handles=[turned, held],
                 handle_rotations=np.stack([rotation, np.eye(3)]), handle_weight=10.0)
    assert out.report["refinement"]["refined"]

    def unit_normals(X, faces):
        n = np.cross(X[F[faces, 1]] - X[F[faces, 0]], X[F[faces, 2]] - X[F[faces, 0]])
        return n / np.linalg.norm(n, axis=1)[:, None]

    X = out.vertices
    for group, R in ((turned, rotation), (held, np.eye(3))):
        cos = np.einsum("ij,ij->i", unit_normals(X, group), unit_normals(V, group) @ R.T)
        assert cos.min() > 0.98


# --------------------------------------------------------------------- parameterization


def test_refined_parameterization_against_arap():
    """face.off flattened: no more flipped faces than libigl's ARAP parameterization and a
    mean length change no larger than ARAP's (measured in the same run)."""
    pytest.importorskip("igl")
    V, F = load("face.off")
    uv_arap = arap_parameterization(V, F)
    forms = fundamental_forms(V, F)
    arap_change = np.abs(np.linalg.norm(uv_arap[forms.edges[:, 1]] - uv_arap[forms.edges[:, 0]],
                                        axis=1) / forms.lengths - 1).mean()
    arap_flips = flipped_faces(uv_arap, F)
    ours = parameterize(V, F)
    linear = parameterize(V, F, refine=False, seams="none")
    assert ours.report["refinement"]["refined"]
    assert len(ours.flipped_faces) <= arap_flips
    assert ours.report["length_change_summary"]["mean"] <= arap_change
    assert ours.report["length_change_summary"]["mean"] < \
        linear.report["length_change_summary"]["mean"]



def test_every_vertex_a_handle_leaves_nothing_to_refine():
    """A deformation whose handles are every vertex (a schemathesis case that once raised
    IndexError while building the Gauss-Newton pattern): the answer is the handles."""
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    result = deform(V, [[0, 1, 2]], [0, 1, 2], V * 1.1)
    np.testing.assert_array_equal(result.vertices, V * 1.1)
    assert result.report["refinement"]["stop_reason"] == "no_free_vertices"


def test_gauss_newton_patterns_are_kept_per_mesh_and_handle_set():
    """A second refinement on the same mesh and free vertices reuses the pattern (counted),
    with the same answer to the bit; another handle set builds its own."""
    from solver.refine import Handles, Refiner, clear_pattern_cache, pattern_cache_info

    V, F = load("decimated-knight.off")
    forms = fundamental_forms(V, F)
    targets = FormTargets(build_topology(F), forms.lengths, forms.angles * 0.9)
    clear_pattern_cache()
    first = Refiner(targets).run(V)
    second = Refiner(targets).run(V)
    assert pattern_cache_info()["computed"] == 1 and pattern_cache_info()["cached"] == 1
    np.testing.assert_array_equal(first.vertices, second.vertices)
    Refiner(targets, Handles(fixed=np.array([0, 1, 2])))
    assert pattern_cache_info()["computed"] == 2


needs_pardiso = pytest.mark.skipif("pardiso" not in linalg.available_backends(),
                                   reason="single precision needs PARDISO")


def gauss_newton_diagonal(V, F):
    """The diagonal of the Gauss-Newton matrix of noisy forms of (V, F) at V."""
    forms = with_noisy_angles(fundamental_forms(V, F))
    refiner = Refiner(FormTargets(build_topology(F, len(V)), forms.lengths, forms.angles))
    _, H, _ = refiner.system.normal_equations(V)
    return H.data[refiner.system.diagonal_positions]


def test_tied_needle_edges_leave_the_gauss_newton_factor_in_single_precision():
    """A regular mesh's Gauss-Newton matrix is factorized in single precision. Needle edges
    (1e-4 of their length) spread its diagonal over 1e8 (double precision) unless their
    endpoints are tied (solver.refine.ties): then their stiffness leaves the matrix, whose
    diagonal spreads as little as the regular mesh's."""
    V, F = load("torus.off")
    regular = gauss_newton_diagonal(V, F)
    assert factor_precision(regular) == "single"
    needles = gauss_newton_diagonal(*with_tiny_edges(V, F, 10))
    assert factor_precision(needles) == "single"
    assert needles.max() / np.median(needles) < 2 * regular.max() / np.median(regular)
    assert factor_precision(np.r_[np.ones(99), 1e8]) == "double"


def torus_x08():
    forms = fundamental_forms(*load("torus.off"))
    forms.angles *= 0.8
    return forms


DOUBLE_ONLY = StepRules(single_precision_spread=0.0)
"""Every factor in double precision: no diagonal spreads by at most 0."""


def refine_with(forms, step_rules=DEFAULT_STEP_RULES):
    """:func:`reconstruct`'s refinement of ``forms``, from its start (the answer of a time
    limit that stops it before its first iteration), with ``step_rules``."""
    start = solve(forms, max_seconds=1e-9).vertices
    targets = FormTargets(build_topology(forms.faces), forms.lengths, forms.angles)
    return Refiner(targets, step_rules=step_rules).run(start)


@needs_pardiso
def test_single_precision_factors_reach_the_double_precision_answer():
    """Angles x 0.8 on the torus, factorized in single precision (one step of iterative
    refinement per solve): the same steps and the same answer, to 1e-6 of the diagonal, as
    the refinement factorized in double precision."""
    forms = torus_x08()
    single, double = refine_with(forms), refine_with(forms, DOUBLE_ONLY)
    s, d = single.report, double.report
    assert (s["precision"], d["precision"]) == ("single", "double")
    assert s["converged"] and d["converged"]
    assert (s["iterations"], s["factorizations"]) == (d["iterations"], d["factorizations"])
    assert s["solves"] == 2 * d["solves"]  # the refinement step's back-substitution
    assert rigid_alignment_error(single.vertices, double.vertices) < 1e-6


@needs_pardiso
def test_an_imprecise_single_precision_factor_is_redone_in_double():
    """A single-precision solve whose refinement step corrects it by more than
    ``StepRules.single_precision_error`` (0 here) makes the refinement factorize in double
    precision there, and every later time: the answer is the double-precision one, at one
    extra factorization, and the report says the precision was mixed."""
    forms = torus_x08()
    redone = refine_with(forms, StepRules(single_precision_error=0.0))
    double = refine_with(forms, DOUBLE_ONLY)
    r, d = redone.report, double.report
    assert r["precision"] == "mixed" and r["converged"]
    assert r["factorizations"] == d["factorizations"] + 1
    assert rigid_alignment_error(redone.vertices, double.vertices) < 1e-12


@needs_pardiso
def test_a_single_precision_factor_that_is_not_definite_is_redone_in_double(monkeypatch):
    """On the knight the float32 pivots of the free rigid motions (damped by 1e-9 of the
    diagonal, below float32's resolution) come out negative: PARDISO refuses the factor,
    and the refinement factorizes in double precision, to the double-precision answer."""
    forms = fundamental_forms(*load("decimated-knight.off"))
    forms.angles *= 0.8
    attempts = []
    original = refine_module.SinglePrecisionFactor

    class Counted(original):
        def __init__(self, *args, **kw):
            attempts.append(1)
            super().__init__(*args, **kw)

    monkeypatch.setattr(refine_module, "SinglePrecisionFactor", Counted)
    redone, double = refine_with(forms), refine_with(forms, DOUBLE_ONLY)
    assert len(attempts) == 1  # the first refusal sets the refiner to double
    r, d = redone.report, double.report
    assert r["precision"] == "double"  # the refused float32 factor is not counted
    assert r["factorizations"] == d["factorizations"]
    assert rigid_alignment_error(redone.vertices, double.vertices) < 1e-12


@needs_pardiso
@pytest.mark.skipif(not (SHARED / "beetle.off").exists(),
                    reason="../shared/meshes is not present")
def test_the_beetle_s_soft_rims_are_refined_in_double_precision():
    """The beetle's eleven holes have softly bending rims: a single-precision factor's
    refinement step corrects its solve by 18% (rocker-arm's by 0.3%), so the noisy forms'
    refinement redoes its factor in double precision and ends as near the mesh the forms
    came from as a double-precision one (8.4e-5 of the diagonal)."""
    V, F = load(SHARED / "beetle.off")
    forms = with_noisy_angles(fundamental_forms(V, F))
    result = solve(forms)
    report = result.report["refinement"]
    assert report["converged"] and report["precision"] == "mixed"
    assert report["factorizations"] == 2
    assert rigid_alignment_error(result.vertices, V) < 1e-4
