import numpy as np
import pytest
import trimesh

from solver import Constraints, fundamental_forms, reconstruct
from solver.core.errors import ConstraintError, TriangleInequalityError
from solver.linalg import available_backends
from solver.mesh.frames import face_edge_lengths, layout_frames, triangle_layouts
from solver.mesh.topology import build_topology
from tests.helpers.meshes import (
    SHARED,
    bumpy_grid_with_holes,
    double_torus,
    grid,
    icosphere,
    load,
    random_rotation,
    rigid_alignment_error,
    skinny_grid,
    torus_grid,
)

MESHES = {
    "icosphere (closed, genus 0)": icosphere(3),
    "knight (closed, genus 0)": load("decimated-knight.off"),
    "torus grid (genus 1)": torus_grid(24, 10),
    "torus.off (genus 1)": load("torus.off"),
    "double torus (genus 2)": double_torus(),
    "face (open, 1 loop)": load("face.off"),
    "grid with holes (3 loops)": bumpy_grid_with_holes(),
    "skinny strip": skinny_grid(),
    "octopus (skinny triangles)": load("octopus-low-surface.off"),
    "bar (Botsch-Sorkine)": load("bar.off"),
    "cylinder (Botsch-Sorkine)": load("cylinder.off"),
}


def solve(forms, **kw):
    return reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles, **kw)


@pytest.mark.parametrize("name", list(MESHES))
def test_exact_forms_reconstruct_exactly(name):
    V, F = MESHES[name]
    result = solve(fundamental_forms(V, F))
    assert rigid_alignment_error(result.vertices, V) <= 1e-8
    assert result.report["integrability"]["integrable"]
    frames = result.frames
    assert np.abs(np.swapaxes(frames, 1, 2) @ frames - np.eye(3)).max() < 1e-8


@pytest.mark.parametrize("weighting", ["uniform", "cotan_clamped"])
def test_weightings_are_exact(weighting):
    V, F = load("torus.off")
    result = solve(fundamental_forms(V, F), weighting=weighting)
    assert rigid_alignment_error(result.vertices, V) <= 1e-8


def test_paper_cotan_weights_are_ill_conditioned_on_obtuse_meshes():
    # Documented behaviour (docs/weights.md): the literal weights lose accuracy here.
    V, F = load("torus.off")
    exact = solve(fundamental_forms(V, F), weighting="uniform", exact_shortcut=False)
    literal = solve(fundamental_forms(V, F), weighting="cotan", exact_shortcut=False,
                    refine=False)
    assert rigid_alignment_error(exact.vertices, V) < 1e-10
    assert rigid_alignment_error(literal.vertices, V) > 1e-6
    # The refinement notices that the linear answer misses the forms and repairs it.
    refined = solve(fundamental_forms(V, F), weighting="cotan", exact_shortcut=False)
    assert refined.report["refinement"]["refined"]
    assert rigid_alignment_error(refined.vertices, V) < 1e-8


@pytest.mark.parametrize("backend", available_backends())
def test_every_backend_is_exact(backend):
    V, F = load("decimated-knight.off")
    result = solve(fundamental_forms(V, F), backend=backend, exact_shortcut=False)
    assert result.report["backend"] == backend
    assert rigid_alignment_error(result.vertices, V) <= 1e-8


def test_frame_choice_invariance():
    V, F = load("decimated-knight.off")
    forms = fundamental_forms(V, F)
    rng = np.random.default_rng(7)
    # Non-integrable forms make the test meaningful: the solution is a compromise.
    forms.angles += rng.normal(scale=0.05, size=len(forms.angles)) * (forms.angles != 0)
    forms.lengths *= rng.uniform(0.995, 1.005, size=len(forms.lengths))
    alpha = rng.uniform(-np.pi, np.pi, size=len(F))
    a = solve(forms, refine=False)  # a property of the linear solve of Eq. 5
    b = solve(forms, layout_angles=alpha, refine=False)
    # Same shape: the default anchor (frame of face 0 = I) differs by a rotation.
    assert rigid_alignment_error(a.vertices, b.vertices) <= 1e-10
    # Same vertices with the same anchor: a rotated 2D frame f' = f Rz(-alpha) (Sec. 3).
    c, s = np.cos(-alpha[0]), np.sin(-alpha[0])
    same_anchor = Constraints(position_vertices=[F[0, 0]], positions=[[0.0, 0.0, 0.0]],
                              frame_faces=[0], frames=[[[c, -s, 0], [s, c, 0], [0, 0, 1]]])
    b = solve(forms, layout_angles=alpha, constraints=same_anchor, refine=False)
    scale = np.linalg.norm(a.vertices.max(0) - a.vertices.min(0))
    assert np.abs(a.vertices - b.vertices).max() <= 1e-10 * scale
    # ... and frames related by f' = f Rz(-alpha_t) for every face.
    rz = np.zeros((len(F), 3, 3))
    rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1], rz[:, 2, 2] = (
        np.cos(alpha), np.sin(alpha), -np.sin(alpha), np.cos(alpha), 1.0)
    assert np.abs(a.frames @ rz - b.frames).max() <= 1e-9


def test_noisy_forms_still_reconstruct_with_residual_reported():
    V, F = load("decimated-knight.off")
    forms = fundamental_forms(V, F)
    rng = np.random.default_rng(2)
    forms.lengths *= rng.uniform(0.99, 1.01, size=len(forms.lengths))
    forms.angles += rng.normal(scale=0.02, size=len(forms.angles))
    plain = solve(forms, refine=False)
    report = plain.report
    assert not report["integrability"]["integrable"]
    assert report["integrability"]["max_defect"] > 0.01
    assert report["energy"]["edge"] + report["energy"]["frame"] > 1e-3
    assert np.isfinite(plain.vertices).all()
    # Averaging inconsistent rotations shrinks the linear frames (measured: 12% shape error);
    # the second, orthonormalized solve of Sec. 4 recovers the shape (measured: 0.7%).
    ortho = solve(forms, orthonormalize=True, refine=False)
    assert rigid_alignment_error(ortho.vertices, V) < 0.02
    assert rigid_alignment_error(ortho.vertices, V) < rigid_alignment_error(plain.vertices, V)


def test_orthonormalize_gives_rotations_and_keeps_exact_data_exact():
    V, F = load("face.off")
    result = solve(fundamental_forms(V, F), orthonormalize=True)
    assert result.report["orthonormalized"]
    assert rigid_alignment_error(result.vertices, V) <= 1e-8


def test_orthonormalize_reduces_frame_error_on_noisy_forms():
    V, F = load("decimated-knight.off")
    forms = fundamental_forms(V, F)
    forms.angles *= 0.5
    plain = solve(forms, refine=False)
    ortho = solve(forms, orthonormalize=True, refine=False)
    def gram_error(frames):
        return np.abs(np.swapaxes(frames, 1, 2) @ frames - np.eye(3)).max(axis=(1, 2)).mean()
    assert gram_error(ortho.frames) < gram_error(plain.frames)


def test_hard_position_and_frame_constraints_place_the_mesh():
    V, F = load("face.off")
    forms = fundamental_forms(V, F)
    rng = np.random.default_rng(4)
    target = V @ random_rotation(rng).T + rng.normal(size=3)
    # The frame of face 0 in the target placement, in the layout convention.
    topo = build_topology(F)
    frames = layout_frames(target, F, triangle_layouts(face_edge_lengths(topo, forms.lengths)))
    v0 = F[0, 0]
    result = solve(forms, constraints=Constraints(
        position_vertices=[v0], positions=[target[v0]], frame_faces=[0], frames=[frames[0]]))
    assert np.abs(result.vertices - target).max() < 1e-9 * np.ptp(target)
    assert np.array_equal(result.vertices[v0], target[v0])
    assert result.report["anchored_components"] == []


def test_positions_only_constraints_reproduce_a_rigid_motion():
    V, F = load("decimated-knight.off")
    forms = fundamental_forms(V, F)
    rng = np.random.default_rng(5)
    R, t = random_rotation(rng), rng.normal(size=3)
    target = V @ R.T + t
    pick = rng.choice(len(V), size=6, replace=False)
    result = solve(forms, constraints=Constraints(position_vertices=pick, positions=target[pick]))
    assert np.abs(result.vertices - target).max() < 1e-6 * np.ptp(target)


def test_soft_positions_pull_towards_targets():
    V, F = grid(6, 6)
    forms = fundamental_forms(V, F)
    corners = [0, 6]
    soft = solve(forms, constraints=Constraints(
        position_vertices=corners, positions=[[0, 0, 0], [1.2, 0, 0]], position_weights=[1, 1]))
    gap = np.linalg.norm(soft.vertices[6] - soft.vertices[0])
    assert 1.0 < gap < 1.2  # a compromise between the forms (1.0) and the targets (1.2)


def test_each_component_is_anchored():
    V1, F1 = icosphere(2)
    V2, F2 = load("face.off")
    V = np.concatenate([V1, V2])
    F = np.concatenate([F1, F2 + len(V1)])
    result = solve(fundamental_forms(V, F))
    assert len(result.report["anchored_components"]) == 2
    assert rigid_alignment_error(result.vertices[: len(V1)], V1) < 1e-8
    assert rigid_alignment_error(result.vertices[len(V1):], V2) < 1e-8


def test_isolated_vertex_is_pinned_and_reported():
    V, F = icosphere(1)
    V = np.concatenate([V, [[5.0, 5, 5]]])
    forms = fundamental_forms(V, F)
    result = solve(forms, n_vertices=len(V))
    assert result.report["isolated_vertices"] == [len(V) - 1]
    assert rigid_alignment_error(result.vertices[:-1], V[:-1]) < 1e-8


def test_progress_reports_every_stage():
    V, F = icosphere(2)
    seen = []
    solve(fundamental_forms(V, F), progress=lambda stage, fraction: seen.append(stage),
          exact_shortcut=False)
    assert [s for i, s in enumerate(seen) if s not in seen[:i]] == [
        "validate", "assemble", "factorize", "solve"]


def test_report_has_timings_backend_and_energy():
    V, F = icosphere(2)
    report = solve(fundamental_forms(V, F), exact_shortcut=False).report
    assert set(report["timings"]) >= {"validate", "assemble", "factorize", "solve"}
    assert report["backend"] in available_backends()
    assert report["energy"]["edge"] < 1e-18 and report["energy"]["frame"] < 1e-18


def test_violated_triangle_inequality_raises():
    forms = fundamental_forms(*icosphere(1))
    forms.lengths[3] = 5.0
    with pytest.raises(TriangleInequalityError) as err:
        solve(forms)
    assert err.value.field == "faces"


@pytest.mark.parametrize(("constraints", "field"), [
    (Constraints(position_vertices=[10**6], positions=[[0, 0, 0]]),
     "constraints.positions.vertex"),
    (Constraints(position_vertices=[1, 1], positions=[[0, 0, 0], [1, 0, 0]]),
     "constraints.positions.vertex"),
    (Constraints(position_vertices=[1], positions=[[0, np.nan, 0]]),
     "constraints.positions.position"),
    (Constraints(frame_faces=[0], frames=[np.diag([1, 1, 2.0])]), "constraints.frames.frame"),
    (Constraints(position_vertices=[1], positions=[[0, 0, 0]], position_weights=[-1]),
     "constraints.positions.weight"),
])
def test_bad_constraints_are_typed_errors(constraints, field):
    forms = fundamental_forms(*icosphere(1))
    with pytest.raises(Exception) as err:
        solve(forms, constraints=constraints)
    assert err.value.field == field
    assert isinstance(err.value, ConstraintError) or err.value.kind in {
        "index-out-of-range", "non-finite-value"}


SHARED_MESHES = sorted(p.name for p in SHARED.glob("*")
                       if p.suffix in {".off", ".obj"}) if SHARED.exists() else []


@pytest.mark.skipif(not SHARED_MESHES, reason="../shared/meshes is not present")
@pytest.mark.parametrize("name", SHARED_MESHES)
def test_every_shared_mesh_reconstructs_exactly(name):
    """forms -> reconstruct -> the original positions, for every mesh in ../shared/meshes
    (up to 100K faces; closed, open, several boundary loops, genus 1, skinny triangles)."""
    mesh = trimesh.load(SHARED / name, process=False)
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    forms = fundamental_forms(V, F)
    result = reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles,
                         n_vertices=len(V))
    assert result.report["integrability"]["max_defect"] <= 1e-10
    assert rigid_alignment_error(result.vertices, V) <= 1e-8


@pytest.mark.parametrize("name", ["knight (closed, genus 0)", "torus grid (genus 1)",
                                  "double torus (genus 2)", "grid with holes (3 loops)",
                                  "skinny strip"])
def test_tree_integration_shortcut_equals_the_factorized_solve(name):
    """Integrable forms are solved by integration along spanning trees (no factorization);
    the result is the same minimizer of Eq. 5 as the factorized solve, anchors included."""
    V, F = MESHES[name]
    forms = fundamental_forms(V, F)
    fast = solve(forms)
    direct = solve(forms, exact_shortcut=False)
    assert fast.report["solve_path"] == "tree-integration"
    assert direct.report["solve_path"] == "factorization"
    scale = np.linalg.norm(np.ptp(V, axis=0))
    assert np.abs(fast.vertices - direct.vertices).max() <= 1e-9 * scale
    assert np.abs(fast.frames - direct.frames).max() <= 1e-9
    assert fast.report["energy"]["edge"] + fast.report["energy"]["frame"] < 1e-18


def test_shortcut_declines_non_integrable_forms_and_constraints():
    V, F = load("decimated-knight.off")
    forms = fundamental_forms(V, F)
    pinned = solve(forms, constraints=Constraints(position_vertices=[0, 5, 9, 200],
                                                   positions=V[[0, 5, 9, 200]]))
    assert pinned.report["solve_path"] == "factorization"
    forms.angles[np.flatnonzero(forms.angles)[3]] += 1e-6
    assert solve(forms).report["solve_path"] == "factorization"


@pytest.mark.parametrize("constrained", [False, True])
def test_unavailable_or_unknown_backend_is_refused_on_every_path(monkeypatch, constrained):
    """Exact forms take the tree-integration path, which never factorizes: an invalid
    backend must still be refused there (it used to be accepted silently)."""
    from solver import linalg

    forms = fundamental_forms(*icosphere(1))
    kw = {}
    if constrained:
        kw["constraints"] = Constraints(position_vertices=[0], positions=[[0.0, 0.0, 0.0]])
    monkeypatch.setattr(linalg.backends, "_unavailable_reason",
                        lambda name: "ImportError: not here" if name == "cholespy" else None)
    with pytest.raises(linalg.BackendUnavailableError, match="pip install cholespy"):
        solve(forms, backend="cholespy", **kw)
    with pytest.raises(ValueError, match="unknown linear-algebra backend"):
        solve(forms, backend="umfpack", **kw)
    assert solve(forms, backend="superlu", **kw).report["solve_path"] == (
        "factorization" if constrained else "tree-integration")
