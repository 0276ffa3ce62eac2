"""Vector-Jacobian products of reconstructions of real files (non-manifold, welded, several
parts): the forms of :func:`solver.fundamental_forms` carry ``vertex_map``, ``weld_map`` and
``placement``, and ``reconstruct_vjp`` differentiates the answer per FILE vertex that
``reconstruct`` returns for them (mean of the cut copies, welded vertices at their
representative, parts placed or laid side by side).

Truth is independent of the adjoint: central finite differences, at two step sizes, of a loss
invariant to rigid motions (:func:`solver.differentiable.aligned_distance`) of
``reconstruct``'s own file-vertex answer (linear answers) or of the polished optimum
(refined answers: ``reconstruct`` stops within its refinement tolerance, checked to be near
it), along random directions of lengths and angles, exact and noisy forms.
"""

import numpy as np
import pytest

import solver
from solver import Constraints
from solver.core.errors import ConstraintError
from solver.differentiable import aligned_distance, reconstruct_vjp
from solver.mesh.placement import face_components
from tests.helpers.finite_differences import STEPS, directional_errors
from tests.helpers.meshes import load
from tests.helpers.real_meshes import CASES as REAL
from tests.helpers.welded_meshes import CASES as WELDED

TOLERANCE = 1e-4


def parts_listed_out_of_order() -> tuple[np.ndarray, np.ndarray]:
    """Two icospheres whose faces are listed in the other order than their vertices: the
    part of vertex 0 comes second in the faces (components numbered by faces and by
    vertices differ)."""
    V, F = REAL["closed-genus-0"]()
    return np.vstack([V, V + np.array([5.0, 1.0, 0.0])]), np.vstack([F + len(V), F])


def mesh(name: str) -> tuple[np.ndarray, np.ndarray]:
    if name == "parts-listed-out-of-order":
        return parts_listed_out_of_order()
    return REAL[name]() if name in REAL else WELDED[name]()[:2]


def forms_of(name: str, kind: str, seed: int = 0):
    """A real mesh, its forms (the cut's, with maps and placement) and lengths and angles
    (exact, or with 0.3% noise)."""
    V, F = mesh(name)
    forms = solver.fundamental_forms(V, F)
    L, A = forms.lengths.copy(), forms.angles.copy()
    if kind == "noisy":
        rng = np.random.default_rng(seed)
        L *= 1.0 + 0.003 * rng.standard_normal(len(L))
        A = np.clip(A + 0.003 * rng.standard_normal(len(A)), -np.pi + 1e-6, np.pi)
    return V, forms, L, A


def keywords_of(V, forms, placed=True, **options):
    out = dict(vertex_map=forms.vertex_map, weld_map=forms.weld_map, n_vertices=len(V),
               **options)
    if placed:
        out["placement"] = forms.placement
    return out


def finite_difference_errors(forms, L, A, target, grads, rng, answer, directions=2):
    """max over directions of |FD - VJP| / |VJP| of ``aligned_distance(answer(L, A),
    target)``, one value per step size."""
    return directional_errors(L, A, grads, rng,
                              lambda L, A: aligned_distance(answer(L, A), target)[0],
                              directions)


def check_gradient(name, kind, refine, placed=True, constraints=None):
    V, forms, L, A = forms_of(name, kind)
    keywords = keywords_of(V, forms, placed, constraints=constraints)
    if not refine:
        keywords["refine"] = False
    result, vjp = reconstruct_vjp(forms.faces, forms.edges, L, A, **keywords)
    assert result.vertices.shape == V.shape
    assert result.frames.shape == (len(forms.faces), 3, 3)
    plain = solver.reconstruct(forms.faces, forms.edges, L, A, **keywords)
    if refine:   # the polished optimum; reconstruct stops within its tolerance of it
        assert np.abs(result.vertices - plain.vertices).max() <= 1e-4 * np.ptp(V)

        def answer(lengths, angles):
            return reconstruct_vjp(forms.faces, forms.edges, lengths, angles,
                                   **keywords)[0].vertices
    else:        # the linear answer is reconstruct's, to the bit
        np.testing.assert_array_equal(result.vertices, plain.vertices)

        def answer(lengths, angles):
            return solver.reconstruct(forms.faces, forms.edges, lengths, angles,
                                      **keywords).vertices
    rng = np.random.default_rng(7)
    target = V + 0.02 * np.ptp(V) * rng.standard_normal(V.shape)
    _, g = aligned_distance(result.vertices, target)
    errors = finite_difference_errors(forms, L, A, target, vjp(g), rng, answer)
    assert min(errors) < TOLERANCE, (name, kind, errors)
    return forms, result


CUT = ["edge-with-3-faces", "edge-with-4-faces", "cones-at-apex"]
WELD = ["duplicated-corner", "latlong-capsule"]


@pytest.mark.parametrize("name", CUT + WELD)
@pytest.mark.parametrize("kind", ["exact", "noisy"])
def test_linear_answer_of_a_real_file_matches_finite_differences(name, kind):
    forms, _ = check_gradient(name, kind, refine=False)
    assert forms.vertex_map is not None        # a real file: its forms are the cut's
    assert (len(forms.vertex_map) > len(mesh(name)[0])) == (name in CUT)
    assert (forms.weld_map is not None) == (name in WELD)


@pytest.mark.parametrize("name", CUT + WELD)
@pytest.mark.parametrize("kind", ["exact", "noisy"])
def test_refined_answer_of_a_real_file_matches_finite_differences(name, kind):
    check_gradient(name, kind, refine=True)


@pytest.mark.parametrize("refine", [False, True])
def test_parts_laid_side_by_side_without_placement(refine):
    """Without the forms' placement the cut's parts are laid out along +x (shifts from the
    parts' bounding boxes) before the copies are averaged: that map is differentiated too."""
    check_gradient("edge-with-4-faces", "noisy", refine, placed=False)


@pytest.mark.parametrize("refine", [False, True])
def test_parts_laid_side_by_side_in_reconstructs_order(refine):
    """The parts are laid out in the order reconstruct lays them out (its components'
    numbering), also when the faces list them in another order than the vertices: the
    refined answer is reconstruct's (not the parts swapped) and the linear gradient
    matches finite differences."""
    _, result = check_gradient("parts-listed-out-of-order", "noisy", refine, placed=False)
    assert "2 components laid out side by side" in result.report["input"]["placement"]


@pytest.mark.parametrize("refine", [False, True])
def test_several_manifold_parts_placed(refine):
    """A manifold file of four parts: no vertex_map, but its placement moves every part."""
    check_gradient("multi-component", "noisy", refine)


def test_shared_file_with_welded_pairs():
    """torus.off (../shared/meshes) with 25 edges split within 1e-15 of an endpoint."""
    forms, result = check_gradient("torus-near-pairs", "noisy", refine=False)
    assert forms.weld_map is not None and (forms.weld_map != np.arange(len(forms.weld_map))).any()
    assert "weld" in result.report["input"]


@pytest.mark.parametrize("refine", [False, True])
def test_constraints_on_file_vertices_mean_what_they_mean_in_reconstruct(refine):
    """Hard positions on file vertices, the split apex among them, hold the same copies as
    in reconstruct, and their cotangents match finite differences."""
    name = "cones-at-apex"
    V, forms, L, A = forms_of(name, "noisy")
    component = face_components(forms.faces, len(forms.vertex_map))[0][:len(V)]
    # Four file vertices spanning 3D in each part (the split apex 0 among them: it holds
    # its copy 0), so that the positions fix every part.
    held = np.concatenate([spanning(V, np.flatnonzero(component == c))
                           for c in np.unique(component)])
    assert 0 in held and len(held) == 8
    positions = V[held] + 0.01
    constraints = Constraints(position_vertices=held, positions=positions)
    keywords = keywords_of(V, forms, constraints=constraints)
    if not refine:
        keywords["refine"] = False
    result, vjp = reconstruct_vjp(forms.faces, forms.edges, L, A, **keywords)
    plain = solver.reconstruct(forms.faces, forms.edges, L, A, **keywords)
    assert np.abs(result.vertices - plain.vertices).max() <= 1e-4 * np.ptp(V)
    rng = np.random.default_rng(3)
    target = V + 0.02 * rng.standard_normal(V.shape)
    _, g = aligned_distance(result.vertices, target)
    cotangents = vjp.cotangents(g)
    d = rng.standard_normal(positions.shape)
    predicted = float(np.sum(cotangents.positions * d))
    errors = []
    for h in STEPS:
        moved = []
        for sign in (1, -1):
            c = Constraints(position_vertices=held, positions=positions + sign * h * d)
            moved.append(aligned_distance(reconstruct_vjp(
                forms.faces, forms.edges, L, A, **{**keywords, "constraints": c})[0].vertices,
                target)[0])
        errors.append(abs((moved[0] - moved[1]) / (2 * h) - predicted) / abs(predicted))
    assert min(errors) < TOLERANCE, errors
    check_gradient(name, "noisy", refine, constraints=constraints)


def spanning(V, members):
    """Four of ``members`` spanning 3D: the first, then each time the farthest from the
    affine hull of those chosen."""
    chosen = [int(members[0])]
    for _ in range(3):
        P = V[chosen] - V[chosen[0]]
        basis = np.linalg.svd(P, full_matrices=False)[2] if len(chosen) > 1 else np.zeros((0, 3))
        d = V[members] - V[chosen[0]]
        d = d - d @ basis.T @ basis
        chosen.append(int(members[np.argmax(np.linalg.norm(d, axis=1))]))
    return np.array(chosen)


@pytest.mark.parametrize("refine", [False, True])
def test_welded_constraint_holds_the_representative(refine):
    """A hard position on a welded file vertex holds its representative (as in reconstruct):
    both sit on the target, and the gradient still matches finite differences."""
    V, forms, L, A = forms_of("duplicated-corner", "noisy")
    welded = int(np.flatnonzero(forms.weld_map != np.arange(len(forms.weld_map)))[0])
    members = np.flatnonzero(forms.weld_map == np.arange(len(V)))
    held = np.r_[welded, spanning(V, members)[1:]]
    c = Constraints(position_vertices=held, positions=V[held] + 0.5)
    result, _ = reconstruct_vjp(forms.faces, forms.edges, L, A, refine=None if refine else False,
                                **keywords_of(V, forms, constraints=c))
    np.testing.assert_allclose(result.vertices[held], V[held] + 0.5, atol=1e-12)
    np.testing.assert_array_equal(result.vertices[welded],
                                  result.vertices[forms.weld_map[welded]])
    check_gradient("duplicated-corner", "noisy", refine, constraints=c)


def test_cotangent_is_per_file_vertex_and_batches():
    V, forms, L, A = forms_of("edge-with-4-faces", "noisy")
    _, vjp = reconstruct_vjp(forms.faces, forms.edges, L, A, **keywords_of(V, forms))
    n_cut = len(forms.vertex_map)
    assert vjp.n_vertices == len(V) < n_cut
    with pytest.raises(ConstraintError, match="cotangent"):
        vjp(np.zeros((n_cut, 3)))
    rng = np.random.default_rng(0)
    g = rng.standard_normal((3, len(V), 3))
    batch = vjp(g)
    for k in range(3):
        single = vjp(g[k])
        np.testing.assert_allclose(batch[0][k], single[0], rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(batch[1][k], single[1], rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("refine", [False, None])
def test_a_manifold_single_part_is_differentiated_as_before(refine):
    """No map at all: the answer is reconstruct's (linear: to the bit), and the gradient of
    the solver's answer is unchanged (it was compared bit for bit against main: see the
    commit message)."""
    V, F = load("decimated-knight.off")
    forms = solver.fundamental_forms(V, F)
    assert forms.vertex_map is None
    rng = np.random.default_rng(1)
    L = forms.lengths * (1 + 0.01 * rng.standard_normal(len(forms.lengths)))
    A = forms.angles + 0.01 * rng.standard_normal(len(forms.angles))
    result, vjp = reconstruct_vjp(forms.faces, forms.edges, L, A, refine=refine)
    if refine is False:
        plain = solver.reconstruct(forms.faces, forms.edges, L, A, refine=False)
        np.testing.assert_array_equal(result.vertices, plain.vertices)
    assert vjp._answer.is_identity
