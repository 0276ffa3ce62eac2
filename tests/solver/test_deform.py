import numpy as np
import pytest

from solver import Deformer, deform, fundamental_forms
from solver.core.errors import ConstraintError, IndexOutOfRangeError, NonFiniteValueError
from solver.mesh.metrics import distortion
from tests.helpers import DATA
from tests.helpers.botsch_sorkine import load_case
from tests.helpers.meshes import grid, load, random_rotation, rigid_alignment_error


def test_hard_handles_are_met_exactly_and_solve_reuses_factorization():
    V, F = load("face.off")
    handles = np.array([10, 200, 600, 900])
    deformer = Deformer(V, F, handles)
    rng = np.random.default_rng(0)
    for _ in range(3):
        targets = V[handles] + rng.normal(scale=5.0, size=(4, 3))
        out = deformer.solve(targets)
        assert np.abs(out[handles] - targets).max() <= 1e-10 * np.ptp(V)
    one_shot = deform(V, F, handles, targets, refine=False)
    assert np.allclose(one_shot.vertices, out, atol=1e-12 * np.ptp(V))
    refined = deform(V, F, handles, targets)  # the default refines; handles stay exact
    assert refined.report["refinement"]["refined"]
    assert np.abs(refined.vertices[handles] - targets).max() <= 1e-10 * np.ptp(V)


def test_rest_handles_give_rest_mesh():
    V, F = load("decimated-knight.off")
    handles = np.arange(0, len(V), 50)
    out = Deformer(V, F, handles).solve(V[handles])
    assert np.abs(out - V).max() <= 1e-10 * np.ptp(V)


@pytest.mark.parametrize("orthonormalize", [False, True])
def test_rigid_motion_of_all_handles_moves_mesh_rigidly(orthonormalize):
    V, F = load("decimated-knight.off")
    rng = np.random.default_rng(3)
    R, t = random_rotation(rng), rng.normal(size=3)
    handles = np.arange(0, len(V), 40)
    groups = [np.arange(0, 30), np.arange(500, 520)]
    deformer = Deformer(V, F, handles, rotation_handles=groups, orthonormalize=orthonormalize)
    out = deformer.solve(V[handles] @ R.T + t, np.stack([R, R]))
    assert np.abs(out - (V @ R.T + t)).max() <= 1e-8 * np.ptp(V)


def test_translation_only_handles_on_coplanar_sets_are_well_posed():
    # A bumpy plane whose fixed border and handle both lie in z = 0: position handles alone
    # leave the normal scale of the frames free; the solver pins that gauge to the rest.
    V, F = grid(24, 12, width=2.0, height=1.0)
    V[:, 2] = 0.05 * np.exp(-((V[:, 0] - 1.0) ** 2 + (V[:, 1] - 0.5) ** 2) / 0.02)
    fixed = np.flatnonzero(V[:, 0] < 0.2)
    handle = np.flatnonzero(V[:, 0] > 1.8)
    out = deform(V, F, np.concatenate([fixed, handle]),
                 np.concatenate([V[fixed], V[handle] + [0, 0, 0.3]])).vertices
    assert np.isfinite(out).all()
    bump = np.argmax(V[:, 2])
    # The bump still points up relative to its neighbourhood after the lift.
    ring = np.flatnonzero(np.linalg.norm(V[:, :2] - V[bump, :2], axis=1) < 0.25)
    assert out[bump, 2] - out[ring, 2].min() > 0.03


def test_rotation_only_handles_rotate_the_mesh():
    V, F = load("decimated-knight.off")
    R = random_rotation(np.random.default_rng(9))
    out = Deformer(V, F, [], rotation_handles=[np.arange(len(F))]).solve([], [R])
    assert rigid_alignment_error(out, V @ R.T) < 1e-8
    centroid_shift = np.linalg.norm(out.mean(0) - (V @ R.T).mean(0))
    assert np.isfinite(centroid_shift)


def test_roi_outside_never_moves_and_system_follows_roi():
    V, F = load("face.off")
    centre = V[np.argmin(np.linalg.norm(V - V.mean(0), axis=1))]
    dist = np.linalg.norm(V - centre, axis=1)
    roi = np.flatnonzero(dist < np.percentile(dist, 30))
    handle = roi[np.argsort(dist[roi])[:5]]
    deformer = Deformer(V, F, handle, roi=roi)
    out = deformer.solve(V[handle] + [0, 0, 20.0])
    outside = np.setdiff1d(np.arange(len(V)), roi)
    assert np.array_equal(out[outside], V[outside])
    assert np.abs(out[handle] - (V[handle] + [0, 0, 20.0])).max() < 1e-9 * np.ptp(V)
    assert deformer.problem.topology.n_faces < 0.5 * len(F)


@pytest.mark.parametrize(("kwargs", "error", "field"), [
    ({"handles": [10**6]}, IndexOutOfRangeError, "handles"),
    ({"handles": [3, 4, 3]}, ConstraintError, "handles"),
    ({"handles": []}, ConstraintError, "handles"),
    ({"handles": [1], "roi": [2, 3]}, ConstraintError, "handles"),
    ({"handles": [1], "rotation_handles": [[0, 1], [1]]}, ConstraintError, "rotations.faces"),
])
def test_bad_handles_are_typed_errors(kwargs, error, field):
    V, F = load("decimated-knight.off")
    with pytest.raises(error) as err:
        Deformer(V, F, **kwargs)
    assert err.value.field == field


def test_bad_handle_values_are_typed_errors():
    V, F = load("decimated-knight.off")
    deformer = Deformer(V, F, [1, 2], rotation_handles=[[0]])
    with pytest.raises(NonFiniteValueError) as err:
        deformer.solve([[0, 0, 0], [np.nan, 0, 0]], [np.eye(3)])
    assert err.value.index == 1
    with pytest.raises(ConstraintError) as err:
        deformer.solve(V[[1, 2]], [np.diag([1.0, 1.0, -1.0])])
    assert err.value.field == "handle_rotations"
    with pytest.raises(ConstraintError):
        deformer.solve(V[[1]])


CASES = {name: load_case(DATA, name) for name in ("bar", "cylinder")}


@pytest.mark.parametrize("name", list(CASES))
@pytest.mark.parametrize("rotations", [False, True])
def test_botsch_sorkine_cases(name, rotations):
    """The handle reaches its transform exactly; distortion stays within measured bounds.

    Bounds are the values measured by ``python bench/deformation_cases.py --cases bar
    cylinder`` (bench/README.md; uniform weights, orthonormalized) plus 30% headroom, so a
    regression in the energy, the constraints or the second solve fails here. The
    cylinder's large length change is inherent: its 120 degree bend compresses the inner
    and stretches the outer side of a thick tube.
    """
    case = CASES[name]
    R = case.transform[:3, :3]
    groups = [case.handle_faces()] if rotations else None
    handle_rot = R[None] if rotations else None
    # The fixed region lies outside the ROI (free + handle): it stays at rest.
    result = deform(case.vertices, case.faces, case.handles, case.handle_targets(),
                    rotation_handles=groups, handle_rotations=handle_rot, roi=case.roi,
                    orthonormalize=True, refine=False)  # the refined answer: test_refine.py
    out = result.vertices
    assert np.abs(out[case.handles] - case.handle_targets()).max() <= 1e-10 * np.ptp(
        case.vertices)
    assert np.array_equal(out[case.fixed], case.vertices[case.fixed])
    d = distortion(case.vertices, out, case.faces)
    bounds = BOUNDS[(name, rotations)]
    assert d["length_summary"]["mean"] < bounds[0]
    assert d["angle_summary"]["mean"] < bounds[1]


# (mean relative length change, mean dihedral change in radians): measured x 1.3.
BOUNDS = {("bar", False): (0.065, 0.042), ("bar", True): (0.067, 0.047),
          ("cylinder", False): (0.20, 0.015), ("cylinder", True): (0.172, 0.0115)}


def symmetric_torus(dense: int, coarse: int, nv: int = 16):
    """Torus sampled with ``dense`` rings on y > 0 and ``coarse`` rings on y < 0."""
    u = np.concatenate([np.linspace(0, np.pi, dense, endpoint=False),
                        np.linspace(np.pi, 2 * np.pi, coarse, endpoint=False)])
    v = np.arange(nv) / nv * 2 * np.pi
    uu, vv = np.meshgrid(u, v, indexing="ij")
    R, r = 2.0, 0.6
    V = np.stack([(R + r * np.cos(vv)) * np.cos(uu), (R + r * np.cos(vv)) * np.sin(uu),
                  r * np.sin(vv)], -1).reshape(-1, 3)
    nu = len(u)
    idx = np.arange(nu * nv).reshape(nu, nv)
    a, b = idx, np.roll(idx, -1, 0)
    c, d = np.roll(b, -1, 1), np.roll(idx, -1, 1)
    F = np.concatenate([np.stack([a.ravel(), b.ravel(), c.ravel()], 1),
                        np.stack([a.ravel(), c.ravel(), d.ravel()], 1)])
    return V, F, uu.ravel()


@pytest.mark.parametrize("weighting", ["uniform", "cotan_clamped"])
def test_sampling_density_does_not_break_symmetry(weighting):
    """Fig. 2: a torus with a dense half (y > 0) and a coarse half (y < 0), bent by a
    handle ring on the mirror plane, must stay mirror-symmetric (y -> -y)."""
    V, F, u = symmetric_torus(dense=48, coarse=12)
    fixed = np.flatnonzero(np.isclose(u, np.pi))
    handle = np.flatnonzero(np.isclose(u, 0.0))
    lift = V[handle] + [0.0, 0.0, 1.5]
    # A property of the linear solve (the refinement's thin-shell energy resolves the
    # coarse half differently: measured 12% asymmetry, docs/refinement.md).
    out = deform(V, F, np.concatenate([fixed, handle]), np.concatenate([V[fixed], lift]),
                 weighting=weighting, orthonormalize=True, refine=False).vertices
    ring_dense = np.flatnonzero(np.isclose(u, np.pi / 2))
    ring_coarse = np.flatnonzero(np.isclose(u, 3 * np.pi / 2))
    mirrored = out[ring_coarse] * [1, -1, 1]
    asymmetry = np.abs(out[ring_dense] - mirrored).max()
    displacement = np.abs(out[ring_dense] - V[ring_dense]).max()
    assert displacement > 0.3
    assert asymmetry < 0.05 * displacement


def test_distortion_report_in_one_shot_deform():
    V, F = load("face.off")
    result = deform(V, F, [5, 700], V[[5, 700]] + [[0, 0, 0], [0, 0, 30.0]])
    report = result.report
    assert report["distortion"]["length_summary"]["max"] > 0
    assert len(report["distortion"]["vertex"]) == len(V)
    # Timings in the shape of every operation's: stage -> seconds.
    assert set(report["timings"]) == {"validate", "assemble", "factorize", "solve", "refine"}
    assert all(seconds >= 0 for seconds in report["timings"].values())


def bumpy_plane(nx: int = 60, ny: int = 30):
    """A plane with a 4 x 2 array of Gaussian bumps; fixed strip at x < 0.15, handle strip
    at x > 1.85 (like the Botsch-Sorkine bumpy plane, smaller)."""
    V, F = grid(nx, ny, width=2.0, height=1.0)
    centres = [(0.4 + 0.4 * i, 0.25 + 0.5 * j) for i in range(4) for j in range(2)]
    bump = sum(np.exp(-((V[:, 0] - cx) ** 2 + (V[:, 1] - cy) ** 2) / 0.004)
               for cx, cy in centres)
    V[:, 2] = 0.06 * bump
    return V, F, bump > 0.05


@pytest.mark.parametrize(("orthonormalize", "refine"), [(False, False), (True, False),
                                                        (False, None)])
def test_bumps_keep_their_shape_when_the_plane_is_raised(orthonormalize, refine):
    """Issue 3 / Fig. 3: lifting one end of a bumpy plane bends it; the bumps ride along
    with little change of their dihedral angles. Measured mean |change| on bump edges:
    0.038 rad (linear) / 0.027 rad (orthonormalized) against 0.236 rad mean |dihedral|
    there, i.e. 16% / 11%; flattened bumps would change by 100%. Bound: 25%."""
    V, F, on_bump = bumpy_plane()
    fixed = np.flatnonzero(V[:, 0] < 0.15)
    handle = np.flatnonzero(V[:, 0] > 1.85)
    roi = np.flatnonzero(V[:, 0] >= 0.15)
    result = deform(V, F, handle, V[handle] + [-0.3, 0.0, 0.6], roi=roi,
                    orthonormalize=orthonormalize, refine=refine)
    out = result.vertices
    assert np.array_equal(out[fixed], V[fixed])
    forms0 = fundamental_forms(V, F)
    forms1 = fundamental_forms(out, F)
    bump_edges = on_bump[forms0.edges].all(axis=1)
    change = np.abs(forms1.angles - forms0.angles)[bump_edges]
    magnitude = np.abs(forms0.angles[bump_edges]).mean()
    assert magnitude > 0.05
    assert change.mean() < 0.25 * magnitude
    # The bumps still bulge out of the bent sheet: clearly convex or concave edges keep
    # their sign (edges near the inflection rings, |angle| < 0.1, may cross zero).
    clear = bump_edges & (np.abs(forms0.angles) > 0.1)
    assert (np.sign(forms1.angles[clear]) == np.sign(forms0.angles[clear])).all()
