"""Shape space (solver.shape_space): blends of K shapes, means, extrapolation, transfer and
sequences, checked against independent truths (vertex blends, independent reconstructions,
exact scalings) on pose families built with the library's own deformation."""

from __future__ import annotations

import numpy as np
import pytest

from solver import blend, fundamental_forms, interpolate, mean, rigid_alignment, transfer
from solver.core.errors import ShapeMismatchError, TriangleInequalityError
from solver.mesh.metrics import wrap_angle
from solver.shape_space import _stacked, path_extrapolation, shape_set
from tests.helpers import DATA
from tests.helpers.botsch_sorkine import load_case
from tests.helpers.meshes import icosphere, load, random_rotation, rigid_alignment_error
from tests.helpers.poses import bent_pose, case_pose, smoothed


def length_change(X: np.ndarray, Y: np.ndarray, F: np.ndarray) -> float:
    """Mean relative edge-length change of ``X`` against ``Y`` (same faces)."""
    return float(np.abs(fundamental_forms(X, F).lengths / fundamental_forms(Y, F).lengths
                        - 1.0).mean())


@pytest.fixture(scope="module")
def knight():
    return load("decimated-knight.off")


@pytest.fixture(scope="module")
def pose_pairs(knight):
    """Near-isometric (rest, pose) pairs: the knight bent by 0.5 rad, the bar twisted by
    half and all of its 135 degrees, the cylinder bent by half of its 120 degrees."""
    V, F = knight
    pairs = [("knight", V, bent_pose(V, F, 0.5), F)]
    bar = load_case(DATA, "bar")
    pairs += [("bar 1/2", bar.vertices, case_pose(bar, 0.5), bar.faces),
              ("bar", bar.vertices, case_pose(bar, 1.0), bar.faces)]
    cylinder = load_case(DATA, "cylinder")
    pairs.append(("cylinder 1/2", cylinder.vertices, case_pose(cylinder, 0.5),
                  cylinder.faces))
    return pairs


# ------------------------------------------------------------------------ forms and weights


def test_lengths_blend_in_log_space_and_extrapolate_to_the_exact_scaling():
    """A and 2A: the row (-1, 2) asks for lengths exp(-log L + 2 log 2L) = 4L, an
    integrable scaling, so the answer is 4A up to a rigid motion (a vertex extrapolation
    gives 3A)."""
    A, F = icosphere(2)
    out = blend([A, 2.0 * A], [[-1.0, 2.0], [0.5, 0.5]], F)
    assert rigid_alignment_error(out.vertices[0], 4.0 * A) < 1e-8
    assert rigid_alignment_error(out.vertices[1], np.sqrt(2.0) * A) < 1e-8


def test_angles_are_unwrapped_against_the_first_shape():
    """An edge folded to +(pi - 0.1) in one shape and -(pi - 0.1) in the other (0.2 rad
    apart across pi): their mean is pi, not the 0 that averaging the numbers gives."""
    A, F = icosphere(1)
    base = shape_set([A, A], F)
    angles = base.angles.copy()
    angles[0, 0], angles[1, 0] = np.pi - 0.1, -(np.pi - 0.1)
    shapes = _stacked(base.topology, list(np.exp(base.log_lengths)), list(angles), None)
    _, blended = shapes.forms(np.array([[0.5, 0.5], [0.75, 0.25]]))
    assert abs(blended[0, 0]) == pytest.approx(np.pi, abs=1e-12)
    assert blended[1, 0] == pytest.approx(np.pi - 0.05, abs=1e-12)
    assert abs(angles[:, 0].mean()) < 1e-12  # what averaging without unwrapping asks for


@pytest.mark.parametrize("weights, field", [
    ([[0.5, 0.6]], "weights"), ([[np.nan, 1.0]], "weights"), ([[1.0, 0.0, 0.0]], "weights"),
])
def test_bad_weights_are_refused_naming_the_row(weights, field):
    A, F = icosphere(1)
    with pytest.raises(ShapeMismatchError) as error:
        blend([A, 1.1 * A], weights, F)
    assert error.value.field == field


def test_mismatched_shapes_and_too_far_extrapolation_are_refused(knight):
    V, F = knight
    with pytest.raises(ShapeMismatchError) as error:
        blend([V, V, V[:-1]], [1 / 3, 1 / 3, 1 / 3], F)
    assert error.value.field == "shapes[2]"
    squashed = V * [1.0, 1.0, 0.05]
    with pytest.raises(TriangleInequalityError) as error:
        blend([V, squashed], [[0.0, 1.0], [-6.0, 7.0]], F)
    assert error.value.field == "weights" and error.value.index == 1


def test_a_convex_row_whose_log_lengths_make_no_triangle_blends_lengths_arithmetically():
    """A face that is a sliver in both shapes, its long edge sliding: the geometric mean of
    its lengths (1, 1, 1.99) and (0.5, 1.5, 1.99) is (0.71, 1.22, 1.99), no triangle; the
    arithmetic mean (0.75, 1.25, 1.99) is one. Rows whose log blend is a triangle keep it."""
    F = np.array([[0, 1, 2]])
    A = np.array([[0.0, 0, 0], [1.99, 0, 0], [0.995, np.sqrt(1 - 0.995**2), 0]])
    x = (1.99**2 + 1.5**2 - 0.5**2) / (2 * 1.99)
    B = np.array([[0.0, 0, 0], [1.99, 0, 0], [x, np.sqrt(1.5**2 - x**2), 0]])
    out = blend([A, B], [[0.5, 0.5]], F)
    assert out.reports[0]["length_blend"] == "arithmetic"
    lengths = np.sort(fundamental_forms(out.vertices[0], F).lengths)
    np.testing.assert_allclose(lengths, [0.75, 1.25, 1.99], atol=1e-9)
    assert blend([A, B], [[0.99, 0.01]], F).reports[0]["length_blend"] == "log"


def test_shapes_given_as_forms_blend_like_shapes_given_as_vertices(knight):
    V, F = knight
    P = bent_pose(V, F, 0.4)
    from_vertices = blend([V, P], [0.3, 0.7], F).vertices[0]
    forms = [fundamental_forms(V, F), fundamental_forms(P, F)]
    from_forms = blend(forms, [0.3, 0.7]).vertices[0]
    assert rigid_alignment_error(from_forms, from_vertices) < 1e-6 * np.ptp(V)


# ------------------------------------------------------------------------ targets


def test_extrapolation_stays_near_isometric(pose_pairs):
    """t = 1.5 of near-isometric pairs: the mean relative length change against the rest
    is at most 1.6x the endpoint pair's (measured 1.49-1.54x), through interpolate and the
    N-way blend alike, while the vertex extrapolation's is several times larger."""
    for name, A, B, F in pose_pairs:
        endpoint = length_change(B, A, F)
        by_t = interpolate(A, B, F, 1.5)
        by_weights = blend([A, B, A], [[-0.25, 1.5, -0.25]], F).vertices[0]
        vertex = length_change(-0.5 * A + 1.5 * B, A, F)
        for X in (by_t, by_weights):
            assert length_change(X, A, F) <= 1.6 * endpoint, name
        assert vertex >= 2.0 * length_change(by_t, A, F), name


def test_mean_of_poses_is_nearer_isometric_than_the_procrustes_vertex_mean(knight):
    """Five poses of the knight (bends about three axes) and five of the cylinder (0 to
    all of its bend): the form-space mean's mean length change against each pose, averaged,
    is below the Procrustes vertex mean's (measured 0.0048 vs 0.0070 and 0.027 vs 0.058)."""
    V, F = knight
    families = [([bent_pose(V, F, a, bend_axis=axis) for a, axis in
                  ((0.5, None), (-0.4, None), (0.3, 0), (0.6, 2), (-0.2, 0))], F)]
    cylinder = load_case(DATA, "cylinder")
    families.append(([case_pose(cylinder, f) for f in (0.0, 0.25, 0.5, 0.75, 1.0)],
                     cylinder.faces))
    for poses, faces in families:
        form_mean = mean(poses, faces)
        vertex_mean = np.mean([rigid_alignment(p, poses[0]).vertices for p in poses], axis=0)
        form = np.mean([length_change(form_mean, p, faces) for p in poses])
        vertex = np.mean([length_change(vertex_mean, p, faces) for p in poses])
        assert form < 0.8 * vertex


def test_mean_of_one_shape_placed_five_times_is_that_shape(knight):
    V, F = knight
    rng = np.random.default_rng(4)
    copies = [V] + [V @ random_rotation(rng).T + rng.normal(size=3) for _ in range(4)]
    assert np.abs(mean(copies, F) - V).max() < 1e-8


def test_transfer_to_the_source_itself_reproduces_the_deformed_source(pose_pairs):
    for name, A, A2, F in pose_pairs[:2]:
        assert np.abs(transfer(A, A2, A, F) - A2).max() < 1e-8, name


def dihedral_change(before: np.ndarray, after: np.ndarray, F: np.ndarray) -> np.ndarray:
    return wrap_angle(fundamental_forms(after, F).angles - fundamental_forms(before, F).angles)


@pytest.mark.parametrize("name", ["decimated-knight.off", "cylinder"])
def test_transferred_bend_matches_the_source_bend_on_the_bent_region(name):
    """A bend of A transferred to B (A smoothed, or A scaled anisotropically): the
    dihedral change of B -> B' correlates with A -> A''s on the 10% of edges the source
    bent most (measured 0.63 / 0.96 on the knight, 1.00 / 0.98 on the cylinder)."""
    if name == "cylinder":
        case = load_case(DATA, "cylinder")
        A, F = case.vertices, case.faces
    else:
        A, F = load(name)
    A2 = bent_pose(A, F, 0.5)
    source = dihedral_change(A, A2, F)
    region = np.abs(source) > np.quantile(np.abs(source), 0.9)
    for B in (smoothed(A, F, 10), A * [1.3, 0.8, 1.1]):
        B2 = transfer(A, A2, B, F)
        moved = dihedral_change(B, B2, F)
        assert np.corrcoef(source[region], moved[region])[0, 1] > 0.6
        assert length_change(B2, B, F) < 3.0 * length_change(A2, A, F)


# ------------------------------------------------------------------------ sequences


def test_a_sequence_keeps_its_factor_and_matches_independent_rows(knight):
    """40 rows between two poses: rows after the first are refined from their neighbour
    with a kept factor (few factorizations in all), and each checked row's form errors
    are within 5% of an independent reconstruction's."""
    V, F = knight
    P = bent_pose(V, F, 0.8)
    t = np.linspace(0.0, 1.0, 40)
    weights = np.stack([1 - t, t], axis=1)
    seen = []
    seq = blend([V, P], weights, F, progress=lambda stage, f: seen.append((stage, f)))
    assert [r["path"] for r in seq.reports[:2]] == ["reconstruct", "sequence"]
    assert seq.reports[-1]["path"] == "reconstruct"  # t = 1: one given shape
    assert sum(r["refinement"].get("factorizations", 0) for r in seq.reports) < 20
    assert [f for stage, f in seen if stage == "rows"] == pytest.approx((np.arange(40) + 1) / 40)
    checked = [5, 20, 33]
    independent = blend([V, P], weights[checked], F, sequence=False)
    for k, report in zip(checked, independent.reports, strict=True):
        for kind in ("length_error", "angle_error"):
            ours = seq.reports[k]["form_error"][kind]["mean"]
            assert ours <= 1.05 * report["form_error"][kind]["mean"] + 1e-9
    assert np.abs(seq.vertices[-1] - P).max() < 1e-8
    assert np.abs(seq.vertices[0] - V).max() < 1e-8


@pytest.mark.parametrize("ts", [(0.0, 0.1, 0.2, 0.3), (0.2, 0.35, 0.45, 0.6),
                                (1.0, 0.9, 0.75, 0.6)])
def test_path_extrapolation_is_exact_on_a_quadratic_path_of_rows(ts):
    """The coefficients extrapolate any quadratic of the rows' arc length exactly
    (unevenly spaced rows included), along a straight and a bent path of 3 shapes."""
    rng = np.random.default_rng(7)
    a, b, c = rng.normal(size=(3, 5))
    for path in (lambda t: np.array([1 - t, t, 0.0]),
                 lambda t: np.array([1 - t - 0.3 * t * t, t, 0.3 * t * t])):
        rows = [path(t) for t in ts]
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(rows, axis=0), axis=1))])
        values = a + b * s[:, None] + c * s[:, None] ** 2
        coefficients = path_extrapolation(rows)
        assert len(coefficients) == 3
        assert np.abs(coefficients @ values[:3] - values[3]).max() < 1e-9


def test_path_extrapolation_needs_a_smooth_path_of_rows():
    rows = [np.array([1 - t, t]) for t in (0.0, 0.1, 0.2, 0.3)]
    assert len(path_extrapolation(rows[:3])) == 2  # two previous rows: the secant
    assert path_extrapolation(rows[:2]) is None
    back = [np.array([1 - t, t]) for t in (0.0, 0.1, 0.2, 0.1)]
    assert path_extrapolation(back) is None  # a turn back
    jump = [np.array([1 - t, t]) for t in (0.0, 0.1, 0.2, 0.8)]
    assert path_extrapolation(jump) is None  # a step 6x the last
    repeat = [np.array([1 - t, t]) for t in (0.0, 0.1, 0.2, 0.2)]
    assert path_extrapolation(repeat) is None
    uneven = [np.array([1 - t, t]) for t in (0.0, 0.5, 0.6, 0.7)]
    assert len(path_extrapolation(uneven)) == 2  # the last two steps alone are alike


def test_sequence_rows_start_from_the_extrapolated_answers(knight):
    """On a smooth path, rows from the fourth on start from the quadratic extrapolation of
    the previous answers, and most then converge on one step (no factorization)."""
    V, F = knight
    P = bent_pose(V, F, 0.8)
    t = np.linspace(0.0, 0.9, 20)
    seq = blend([V, P], np.stack([1 - t, t], axis=1), F)
    starts = [r["refinement"].get("start") for r in seq.reports]
    assert starts[2] == "secant of the previous rows"
    assert set(starts[3:]) == {"quadratic extrapolation of the previous rows"}
    iterations = [r["refinement"]["iterations"] for r in seq.reports[3:]]
    assert np.mean(iterations) < 2.0, iterations


def test_rows_carry_warnings_past_the_documented_thresholds(knight):
    """A blend of two poses leaves small errors (no warning); one of a mesh and its copy
    stretched 3x along z leaves a dihedral error past WarningRules.max_angle_error, which
    the row's warning reports as measured independently from the answer and the blended
    forms (geometric mean of the lengths, mean of the angles)."""
    from solver.core.warnings import DEFAULT_RULES
    from solver.mesh.topology import build_topology
    from solver.refine.form_energy import form_residuals

    V, F = knight
    calm = blend([V, bent_pose(V, F, 0.8)], [[0.5, 0.5], [-0.2, 1.2]], F)
    assert calm.warnings == [] and all(r["warnings"] == [] for r in calm.reports)
    S = V * [1.0, 1.0, 3.0]
    out = blend([V, S], [[0.5, 0.5], [1.0, 0.0]], F)
    a, b = fundamental_forms(V, F), fundamental_forms(S, F)
    lengths = np.sqrt(a.lengths * b.lengths)
    angles = wrap_angle(a.angles + 0.5 * wrap_angle(b.angles - a.angles))
    truth = form_residuals(out.vertices[0], build_topology(F, len(V)), lengths, angles)
    found = {w["code"]: w for w in out.reports[0]["warnings"]}
    assert truth["angle_error"]["max"] > DEFAULT_RULES.max_angle_error
    assert found["angle-error"]["value"] == pytest.approx(truth["angle_error"]["max"],
                                                          rel=1e-9)
    assert found["angle-error"]["limit"] == DEFAULT_RULES.max_angle_error
    assert ("length-error" in found) == (truth["length_error"]["max"]
                                         > DEFAULT_RULES.max_length_error)
    assert out.reports[1]["warnings"] == []  # the given shape itself
    assert [w["row"] for w in out.warnings] == [0] * len(found)


def test_a_row_whose_time_ran_out_before_any_progress_warns(knight):
    V, F = knight
    P = bent_pose(V, F, 0.8)
    t = np.linspace(0.05, 0.95, 30)
    out = blend([V, P], np.stack([1 - t, t], axis=1), F, max_seconds=0.02)
    stuck = [r["row"] for r in out.reports
             if r["refinement"].get("stop_reason") == "time_limit"
             and r["refinement"].get("outcome") == "not-refined"]
    assert stuck, [r["refinement"].get("stop_reason") for r in out.reports]
    warned = [w["row"] for w in out.warnings if w["code"] == "time-limit-no-progress"]
    assert warned == stuck


def test_interpolate_is_the_two_shape_blend(knight):
    V, F = knight
    P = bent_pose(V, F, 0.3)
    ts = [0.0, 0.4, 1.2]
    via_blend = blend([V, P], np.stack([1 - np.array(ts), ts], axis=1), F).vertices
    assert np.abs(interpolate(V, P, F, ts) - via_blend).max() < 1e-12


def test_a_budget_is_shared_among_the_rows(knight):
    """max_seconds covers the whole sequence: with 0.05 s for 30 rows every row is still
    answered (the rows past the budget keep their start, reported as time_limit)."""
    import time

    V, F = knight
    P = bent_pose(V, F, 0.8)
    t = np.linspace(0.05, 0.95, 30)
    began = time.perf_counter()
    out = blend([V, P], np.stack([1 - t, t], axis=1), F, max_seconds=0.05)
    assert out.vertices.shape == (30, len(V), 3) and np.isfinite(out.vertices).all()
    stops = [r["refinement"].get("stop_reason") for r in out.reports]
    assert stops.count("time_limit") >= 20, stops
    assert time.perf_counter() - began < 0.05 + 30 * 0.2  # no row refines past its share
