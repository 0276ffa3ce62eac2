"""Vector-Jacobian products of reconstruct (solver.differentiable) against central finite
differences of reconstruct itself: several random directions and two step sizes (the
differences of the two steps show the finite differences' own accuracy), on shared meshes,
for the linear answer and for the refined answer at converged optima (noisy and x0.8 forms).
"""

import numpy as np
import pytest
import scipy.linalg

from solver import Constraints, fundamental_forms, reconstruct
from solver.core.errors import ConstraintError
from solver.differentiable import aligned_distance, reconstruct_vjp
from solver.mesh.frames import face_edge_lengths, layout_frames, triangle_layouts
from solver.mesh.rotations import nearest_rotation
from solver.mesh.topology import build_topology
from solver.refine import FormTargets, Handles, Refiner
from solver.refine.refined_energy import RefinedEnergy
from tests.helpers.finite_differences import STEPS, directional_errors
from tests.helpers.meshes import grid, load, with_cap_faces

TOLERANCE = 1e-4


def forms_of(name: str, kind: str, seed: int = 0):
    V, F = load(name)
    forms = fundamental_forms(V, F)
    rng = np.random.default_rng(seed)
    L, A = forms.lengths.copy(), forms.angles.copy()
    if kind == "noisy":   # face.off has near-degenerate triangles: less length noise
        L *= 1.0 + (0.001 if name == "face.off" else 0.01) * rng.standard_normal(len(L))
        A = np.clip(A + 0.01 * rng.standard_normal(len(A)), -np.pi + 1e-6, np.pi)
    elif kind == "x0.8":
        A *= 0.8
    return V, forms, L, A


def finite_difference_errors(forms, L, A, cotangent, grads, rng, directions=3, **keywords):
    """max over directions of |FD - VJP| / |VJP| of ``cotangent . vertices``, one value per
    step size."""
    def loss(L, A):
        answer, _ = reconstruct_vjp(forms.faces, forms.edges, L, A, **keywords)
        return float(np.sum(cotangent * answer.vertices))
    return directional_errors(L, A, grads, rng, loss, directions)


@pytest.mark.parametrize("name", ["decimated-knight.off", "torus.off", "face.off"])
@pytest.mark.parametrize("kind", ["exact", "noisy", "x0.8"])
def test_linear_answer_matches_finite_differences(name, kind):
    _, forms, L, A = forms_of(name, kind)
    result, vjp = reconstruct_vjp(forms.faces, forms.edges, L, A, refine=False)
    assert vjp.mode == "linear"
    reference = reconstruct(forms.faces, forms.edges, L, A, refine=False)
    np.testing.assert_allclose(result.vertices, reference.vertices, atol=1e-9)
    rng = np.random.default_rng(1)
    g = rng.standard_normal(result.vertices.shape)
    errors = finite_difference_errors(forms, L, A, g, vjp(g), rng, refine=False)
    assert errors.min() <= TOLERANCE, errors


@pytest.mark.parametrize("name", ["decimated-knight.off", "torus.off", "face.off"])
@pytest.mark.parametrize("kind", ["exact", "noisy", "x0.8"])
def test_refined_answer_matches_finite_differences(name, kind):
    _, forms, L, A = forms_of(name, kind)
    result, vjp = reconstruct_vjp(forms.faces, forms.edges, L, A)
    assert vjp.mode == "refined"
    assert vjp.report["polish_converged"]
    # Polishing only finishes the refinement: it stays where reconstruct stopped.
    reference = reconstruct(forms.faces, forms.edges, L, A)
    size = np.ptp(reference.vertices, axis=0).max()
    assert np.abs(result.vertices - reference.vertices).max() <= 1e-3 * size
    rng = np.random.default_rng(2)
    g = rng.standard_normal(result.vertices.shape)
    errors = finite_difference_errors(forms, L, A, g, vjp(g), rng)
    assert errors.min() <= TOLERANCE, errors


@pytest.mark.parametrize("refine", [False, None])
def test_options_object_and_keywords_differentiate_the_same_answer(refine):
    """``options=`` and keyword overrides are one thing: the adjoint differentiates the
    answer of the options the reconstruction used (a frame weight of 10, not the default)."""
    from solver.options import ReconstructOptions

    _, forms, L, A = forms_of("decimated-knight.off", "noisy")
    by_keyword, vjp_k = reconstruct_vjp(forms.faces, forms.edges, L, A, refine=refine,
                                        frame_weight=10.0)
    by_options, vjp_o = reconstruct_vjp(
        forms.faces, forms.edges, L, A,
        options=ReconstructOptions(refine=refine, frame_weight=10.0))
    _, vjp_d = reconstruct_vjp(forms.faces, forms.edges, L, A, refine=refine)
    np.testing.assert_allclose(by_options.vertices, by_keyword.vertices, atol=1e-12)
    g = np.random.default_rng(2).standard_normal(by_keyword.vertices.shape)
    k, o, d = vjp_k.cotangents(g), vjp_o.cotangents(g), vjp_d.cotangents(g)
    np.testing.assert_allclose(o.lengths, k.lengths, atol=1e-10)
    np.testing.assert_allclose(o.angles, k.angles, atol=1e-10)
    if refine is False:  # the linear answer depends on the frame weight
        assert np.abs(d.lengths - k.lengths).max() > 1e-6


def test_batch_of_cotangents_equals_single_ones():
    _, forms, L, A = forms_of("decimated-knight.off", "noisy")
    rng = np.random.default_rng(3)
    for refine in (False, None):
        result, vjp = reconstruct_vjp(forms.faces, forms.edges, L, A, refine=refine)
        G = rng.standard_normal((3, *result.vertices.shape))
        grad_L, grad_A = vjp(G)
        assert grad_L.shape == grad_A.shape == (3, len(L))
        for k in range(3):
            single_L, single_A = vjp(G[k])
            scale = np.abs(single_L).max() + np.abs(single_A).max()
            np.testing.assert_allclose(grad_L[k], single_L, rtol=0, atol=1e-10 * scale)
            np.testing.assert_allclose(grad_A[k], single_A, rtol=0, atol=1e-10 * scale)


def test_gauge_does_not_change_the_gradient_of_a_rigid_invariant_loss():
    """Reordering the faces moves the anchor (another face, another vertex): the refined
    answer comes out in another rigid placement, and an invariant loss must get the same
    gradient."""
    V, forms, L, A = forms_of("decimated-knight.off", "x0.8")
    result, vjp = reconstruct_vjp(forms.faces, forms.edges, L, A)
    order = np.roll(np.arange(len(forms.faces)), 357)
    moved, vjp_moved = reconstruct_vjp(forms.faces[order], forms.edges, L, A)
    assert np.abs(moved.vertices - result.vertices).max() > 0.1 * np.ptp(V)
    loss, g = aligned_distance(result.vertices, V)
    loss_moved, g_moved = aligned_distance(moved.vertices, V)
    assert loss_moved == pytest.approx(loss, rel=1e-6)
    grad_L, grad_A = vjp(g)
    moved_L, moved_A = vjp_moved(g_moved)
    scale = np.abs(np.concatenate([grad_L, grad_A])).max()
    assert np.abs(moved_L - grad_L).max() <= 1e-6 * scale
    assert np.abs(moved_A - grad_A).max() <= 1e-6 * scale


def test_aligned_distance_gradient():
    V, _ = load("decimated-knight.off")
    rng = np.random.default_rng(5)
    X = V @ scipy.linalg.expm(np.cross(np.eye(3), [0.3, -0.2, 0.5])) + 0.05 * rng.standard_normal(
        V.shape)
    _loss, g = aligned_distance(X, V)
    d = rng.standard_normal(V.shape)
    h = 1e-6
    fd = (aligned_distance(X + h * d, V)[0] - aligned_distance(X - h * d, V)[0]) / (2 * h)
    assert fd == pytest.approx(np.sum(g * d), rel=1e-6)
    assert aligned_distance(V @ scipy.linalg.expm(np.cross(np.eye(3), [1.0, 2, 3])) + 7, V)[
        0] == pytest.approx(0.0, abs=1e-20)


def _constraints(V, forms, rng):
    hard = np.array([3, 60, 200, 410])
    soft = np.array([120, 333])
    face = 17
    layouts = triangle_layouts(face_edge_lengths(build_topology(forms.faces), forms.lengths))
    frame = nearest_rotation(layout_frames(V, forms.faces[[face]], layouts[[face]]))[0]
    return Constraints(
        position_vertices=np.concatenate([hard, soft]),
        positions=np.concatenate([V[hard], V[soft] + 0.01 * rng.standard_normal((2, 3))]),
        position_weights=np.array([np.inf] * 4 + [5.0, 20.0]),
        frame_faces=np.array([face]), frames=frame[None], frame_weights=np.array([3.0]))


@pytest.mark.parametrize("refine", [False, None])
def test_constraint_targets_match_finite_differences(refine):
    V, forms, L, A = forms_of("decimated-knight.off", "noisy")
    rng = np.random.default_rng(6)
    constraints = _constraints(V, forms, rng)
    result, vjp = reconstruct_vjp(forms.faces, forms.edges, L, A, constraints=constraints,
                                  refine=refine)
    g = rng.standard_normal(result.vertices.shape)
    cot = vjp.cotangents(g)

    def run(positions=None, frames=None, lengths=L):
        c = Constraints(constraints.position_vertices,
                        constraints.positions if positions is None else positions,
                        constraints.position_weights, constraints.frame_faces,
                        constraints.frames if frames is None else frames,
                        constraints.frame_weights)
        out, _ = reconstruct_vjp(forms.faces, forms.edges, lengths, A, constraints=c,
                                 refine=refine)
        return np.sum(g * out.vertices)

    dP = rng.standard_normal(constraints.positions.shape) * np.ptp(V) * 0.1
    omega = np.cross(np.eye(3), rng.standard_normal(3))          # skew: a tangent of SO(3)
    dL = rng.standard_normal(len(L)) * L
    checks = []
    for h in STEPS:
        fd_p = (run(positions=constraints.positions + h * dP)
                - run(positions=constraints.positions - h * dP)) / (2 * h)
        rot = lambda s: constraints.frames @ scipy.linalg.expm(s * omega)  # noqa: E731
        fd_f = (run(frames=rot(h)) - run(frames=rot(-h))) / (2 * h)
        fd_l = (run(lengths=L + h * dL) - run(lengths=L - h * dL)) / (2 * h)
        checks.append([
            abs(fd_p - np.sum(cot.positions * dP)) / abs(np.sum(cot.positions * dP)),
            abs(fd_f - np.sum(cot.frames * (constraints.frames @ omega)))
            / abs(np.sum(cot.frames * (constraints.frames @ omega))),
            abs(fd_l - cot.lengths @ dL) / abs(cot.lengths @ dL)])
    assert np.min(checks, axis=0).max() <= TOLERANCE, checks


@pytest.mark.parametrize("caps", [0, 5])
def test_energy_is_the_refinements(caps):
    """RefinedEnergy evaluates the energy Refiner minimizes (handles included; with
    ``caps`` faces flattened to 1e-6 of their width, whose apex residuals replace their
    edges' angles), its gradient is that energy's, and its Hessian that gradient's
    derivative."""
    V, forms, L, A = forms_of("decimated-knight.off", "x0.8")
    if caps:
        V = with_cap_faces(V, forms.faces, caps)
        forms = fundamental_forms(V, forms.faces)
        L, A = forms.lengths, 0.8 * forms.angles
    topo = build_topology(forms.faces)
    rng = np.random.default_rng(7)
    handles = Handles(fixed=np.array([0, 5]), soft_vertices=np.array([7, 9]),
                      soft_positions=V[[7, 9]] + 0.1, soft_weights=np.array([2.0, 3.0]),
                      frame_faces=np.array([4]),
                      frame_edges=(V[forms.faces[4, 1:]] - V[forms.faces[4, 0]])[None] * 1.1,
                      frame_weights=np.array([5.0]))
    targets = FormTargets(topo, L, A, angle_weight=0.05)
    energy = RefinedEnergy(targets, handles)
    X = V + 0.01 * rng.standard_normal(V.shape)
    assert energy.energy(X) == pytest.approx(Refiner(targets, handles).energy(X), rel=1e-12)
    d = rng.standard_normal(V.shape) * L.mean()
    h = 1e-6
    fd = (energy.energy(X + h * d) - energy.energy(X - h * d)) / (2 * h)
    assert fd == pytest.approx(np.sum(energy.gradient(X) * d), rel=1e-6)
    fd_grad = (energy.gradient(X + h * d) - energy.gradient(X - h * d)) / (2 * h)
    Hd = (energy.hessian(X) @ d.ravel()).reshape(-1, 3)
    assert np.abs(Hd - fd_grad).max() <= 1e-6 * np.abs(Hd).max()
    np.testing.assert_allclose(energy.hessian_vector(X, d), Hd, rtol=1e-9, atol=1e-9 * np.abs(
        Hd).max())
    H = energy.hessian(X)
    assert abs(H - H.T).max() <= 1e-10 * abs(H).max()
    assert len(energy.cap_corners) == caps


def test_cap_faces_mixed_derivatives_match_finite_differences(monkeypatch):
    """``lambda^T d(grad E)/d(lengths)`` of the cap faces' apex residuals (their foot and
    weight depend on all three target lengths) against central differences of the
    gradient, on a knight with 5 faces flattened to 1e-3 of their width and caps up to
    1e-2 (a flat face's height moves with the square root of its lengths' excess: at the
    default threshold, a difference step of 1e-7 would turn caps into faces)."""
    monkeypatch.setattr("solver.refine.form_energy.CAP_HEIGHT", 1e-2)
    V, F = load("decimated-knight.off")
    V = with_cap_faces(V, F, 5, height=1e-3)
    forms = fundamental_forms(V, F)
    topo = build_topology(F)
    rng = np.random.default_rng(3)
    X = V + 1e-3 * rng.standard_normal(V.shape)
    lam = rng.standard_normal((2, *V.shape))
    dL = rng.standard_normal(len(forms.lengths)) * forms.lengths

    def gradient(L):
        return RefinedEnergy(FormTargets(topo, L, forms.angles), Handles()).gradient(X)

    energy = RefinedEnergy(FormTargets(topo, forms.lengths, forms.angles), Handles())
    assert len(energy.cap_corners) == 5
    predicted = energy.mixed_vjp(X, lam).lengths @ dL
    h = 1e-7
    fd = np.einsum("bnk,nk->b", lam, gradient(forms.lengths + h * dL)
                   - gradient(forms.lengths - h * dL)) / (2 * h)
    np.testing.assert_allclose(predicted, fd, rtol=1e-5)


def test_inverse_design_folds_a_sheet():
    """Gradient descent on the dihedral angles (lengths kept) of a flat sheet until its
    reconstruction matches the sheet bent around a cylinder: the loss falls >= 100x."""
    V, F = grid(8, 8)
    radius = 0.5
    target = np.stack([radius * np.sin(V[:, 0] / radius), V[:, 1],
                       radius * (1 - np.cos(V[:, 0] / radius))], axis=1)
    forms = fundamental_forms(target, F)
    angles = np.zeros_like(forms.angles)
    step, history = 1.0, []
    for _ in range(40):
        result, vjp = reconstruct_vjp(forms.faces, forms.edges, forms.lengths, angles)
        loss, g = aligned_distance(result.vertices, target)
        history.append(loss)
        if loss <= history[0] / 100:
            break
        _, grad = vjp(g)
        while step > 1e-8:   # backtracking: a step that lowers the loss
            trial = np.clip(angles - step * grad, -np.pi + 1e-9, np.pi)
            moved = reconstruct(forms.faces, forms.edges, forms.lengths, trial)
            if aligned_distance(moved.vertices, target)[0] < loss:
                break
            step *= 0.5
        angles, step = trial, step * 1.5
    assert history[-1] <= history[0] / 100, history


def test_unsupported_options_are_refused():
    _, forms, L, A = forms_of("decimated-knight.off", "noisy")
    with pytest.raises(ConstraintError, match="weighting"):
        reconstruct_vjp(forms.faces, forms.edges, L, A, weighting="cotan")
    with pytest.raises(ConstraintError, match="orthonormalized"):
        reconstruct_vjp(forms.faces, forms.edges, L, A, refine=False, orthonormalize=True)
    _result, vjp = reconstruct_vjp(forms.faces, forms.edges, L, A, refine=False)
    with pytest.raises(ConstraintError, match="shape"):
        vjp(np.zeros((3, 3)))


@pytest.mark.parametrize("weight", [5e-324, 1e-300, 1e-15, 1e-9, 1.0])
@pytest.mark.parametrize("mesh", ["pyramid", "grid"])
def test_a_tiny_soft_weight_still_differentiates_reconstructs_answer(mesh, weight):
    """A hard frame and a soft position whose weight is (nearly) nothing: the system is
    singular but for that weight along the translation, and the adjoint's system must be
    reconstruct's to the bit (found by the HTTP fuzzer: a weight of 5e-324 answered 500 when
    the two were built by different paths)."""
    if mesh == "pyramid":
        V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 0.5]], float)
        F = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    else:
        V, F = grid(6, 5)
    forms = fundamental_forms(V, F)
    constraints = Constraints(position_vertices=np.array([0]), positions=np.zeros((1, 3)),
                              position_weights=np.array([weight]), frame_faces=np.array([0]),
                              frames=np.eye(3)[None], frame_weights=np.array([np.inf]))
    result, vjp = reconstruct_vjp(forms.faces, forms.edges, forms.lengths, forms.angles,
                                  constraints=constraints, refine=False)
    plain = reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles,
                        constraints=constraints, refine=False)
    np.testing.assert_array_equal(result.vertices, plain.vertices)
    cotangents = vjp(np.ones_like(result.vertices))
    assert all(np.isfinite(np.asarray(c)).all() for c in cotangents)
