"""Parts without area and vertices in no face (CGAL's Data/data/meshes/degeneracies, issue 40's
follow-up): a component whose every face has collinear corners is reconstructed from its
forms (its anchor face's frame is a rotation), a mesh without any area is refused by the
flattening with a problem naming it, and a handle on a vertex no face uses is refused by name
instead of being applied to another vertex.
"""

from __future__ import annotations

import numpy as np
import pytest

import solver
from solver.core.errors import ConstraintError, DegenerateFaceError
from solver.mesh.placement import face_frames
from tests.helpers.meshes import grid, icosphere, random_rotation, rigid_alignment_error

ALL_DEGENERATE = (  # CGAL's degeneracies/all_degen.off: coincident and collinear corners
    np.array([[0, 0, 0], [1, 1, 0], [1, 1, 0], [2, 2, 0], [1, 1, 0], [2, 2, 0],
              [0.5, 1, 0]], dtype=np.float64),
    np.array([[0, 2, 1], [0, 3, 2], [4, 3, 5], [1, 4, 5], [1, 2, 6], [6, 2, 4], [6, 4, 1]]))


def _needle(count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``count`` faces of collinear corners on one line (a fan of segments), turned."""
    t = np.sort(rng.uniform(0, 3, count + 2))
    V = np.outer(t, [1.0, 2.0, -0.5]) @ random_rotation(rng).T + rng.normal(0, 1, 3)
    F = np.array([[0, k + 1, k + 2] for k in range(count)])
    return V, F


def _flat_part_cases() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(11)
    sphere_v, sphere_f = icosphere(1)
    cases = {"all_degen.off": ALL_DEGENERATE}
    for count in (1, 3):
        needle_v, needle_f = _needle(count, rng)
        cases[f"needle of {count}"] = (needle_v, needle_f)
        cases[f"sphere and a needle of {count}"] = (
            np.concatenate([sphere_v, needle_v + 4.0]),
            np.concatenate([sphere_f, needle_f + len(sphere_v)]))
    return cases


CASES = _flat_part_cases()


@pytest.mark.parametrize("name", CASES)
def test_a_part_without_area_is_rebuilt_from_its_forms(name):
    V, F = CASES[name]
    forms = solver.fundamental_forms(V, F)
    assert np.allclose(np.swapaxes(forms.placement.frames, 1, 2) @ forms.placement.frames,
                       np.eye(3))
    result = solver.reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles,
                                vertex_map=forms.vertex_map, weld_map=forms.weld_map,
                                placement=forms.placement, n_vertices=len(V))
    in_faces = np.setdiff1d(np.arange(len(V)), result.report["isolated_vertices"])
    # each part placed where it was: the file's own positions, no alignment
    np.testing.assert_allclose(result.vertices[in_faces], V[in_faces], atol=1e-9)


def test_a_collinear_face_gets_a_rotation_and_a_plane_face_its_own_frame():
    V = np.array([[0, 0, 0], [2, 2, 0], [1, 1, 0], [0, 0, 0], [0, 0, 0], [1, 0, 0.]])
    frames = face_frames(V, np.array([[0, 1, 2], [3, 4, 0], [0, 5, 1]]))
    assert np.allclose(np.swapaxes(frames, 1, 2) @ frames, np.eye(3))
    assert np.allclose(np.linalg.det(frames), 1.0)
    np.testing.assert_allclose(frames[0][:, 0], [2 ** -0.5, 2 ** -0.5, 0])  # b1 on the line
    np.testing.assert_allclose(frames[2][:, 2], [0, 0, 1])  # b3 the normal, as ever
    np.testing.assert_allclose(frames[1], np.eye(3))  # three corners at one point: e_x, e_z


@pytest.mark.parametrize("name", ["all_degen.off", "needle of 3"])
def test_flattening_a_mesh_without_area_is_refused_by_name(name):
    V, F = CASES[name]
    with pytest.raises(DegenerateFaceError, match="every face has zero area") as caught:
        solver.parameterize(V, F)
    assert caught.value.field == "faces"


def test_flattening_a_mesh_with_a_part_without_area_lays_out_the_rest():
    V, F = CASES["sphere and a needle of 3"]
    flat = solver.parameterize(V, F)
    assert len(flat.flipped_faces) == 0 and np.isfinite(flat.uv).all()


def _plain_with_spare_vertex() -> tuple[np.ndarray, np.ndarray, int]:
    V, F = grid(4, 3)
    V = np.asarray(V, dtype=np.float64)
    return np.vstack([V, [[5.0, 5.0, 5.0]]]), np.asarray(F), len(V)


@pytest.mark.parametrize("case", ["unreferenced vertex", "faces dropped as degenerate"])
def test_a_handle_on_a_vertex_in_no_face_is_refused_by_name(case):
    if case == "unreferenced vertex":
        V, F, lonely = _plain_with_spare_vertex()
        handles = [0, lonely, len(V) - 2]
    else:
        (V, F), lonely = ALL_DEGENERATE, 6
        handles = [3, lonely, 0]
    targets = V[handles] + 0.1
    with pytest.raises(ConstraintError, match=f"handle vertex {lonely} is in no face") as caught:
        solver.deform(V, F, handles, targets)
    assert caught.value.field == "handles" and caught.value.index == 1


def test_the_other_handles_hold_once_the_lonely_one_is_left_out():
    """Before the refusal, the lonely handle's target was applied to the system's last
    vertex (a local index of -1): here vertex 11 went to (6, 6, 6)."""
    V, F, lonely = _plain_with_spare_vertex()
    handles = [0, len(V) - 2]
    targets = V[handles] + [[0, 0, 0], [0, 0, 0.3]]
    moved = solver.deform(V, F, handles, targets)
    np.testing.assert_allclose(moved.vertices[handles], targets, atol=1e-9)
    np.testing.assert_array_equal(moved.vertices[lonely], V[lonely])
    assert rigid_alignment_error(moved.vertices[:lonely], V[:lonely]) > 1e-3
