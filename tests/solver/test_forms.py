import numpy as np
import pytest

from solver import fundamental_forms
from solver.core.errors import (
    EdgeMismatchError,
    NonFiniteValueError,
    NonPositiveLengthError,
    ShapeMismatchError,
)
from solver.mesh.forms import validate_forms
from tests.helpers.meshes import icosphere, load, random_rotation


def test_sphere_angles_positive_and_match_geometry():
    V, F = icosphere(3)
    forms = fundamental_forms(V, F)
    assert (forms.angles > 0).all()
    # Independent truth: the angle between the two face normals (unsigned).
    tri = V[F]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    edge_faces = {}
    for t, face in enumerate(F):
        for k in range(3):
            edge_faces.setdefault(tuple(sorted((face[k], face[(k + 1) % 3]))), []).append(t)
    for e, (i, j) in enumerate(forms.edges[:50]):
        a, b = edge_faces[(i, j)]
        expected = np.arccos(np.clip(normals[a] @ normals[b], -1, 1))
        assert forms.angles[e] == pytest.approx(expected, abs=1e-12)
        assert forms.lengths[e] == pytest.approx(np.linalg.norm(V[i] - V[j]))


def test_saddle_has_negative_angles():
    # A concave fold: a flat square bent downwards along its diagonal (valley) is concave.
    V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.0]])
    V[[1, 3], 2] = 0.3  # raise the off-diagonal corners: valley along 0-2
    forms = fundamental_forms(V, [[0, 1, 2], [0, 2, 3]])
    diagonal = np.flatnonzero((forms.edges == [0, 2]).all(1))[0]
    assert forms.angles[diagonal] < 0
    assert np.count_nonzero(forms.angles) == 1  # boundary edges are 0


def test_rigid_motion_invariance():
    V, F = load("decimated-knight.off")
    rng = np.random.default_rng(1)
    moved = V @ random_rotation(rng).T + rng.normal(size=3) * 10
    a, b = fundamental_forms(V, F), fundamental_forms(moved, F)
    assert np.allclose(a.lengths, b.lengths, rtol=1e-12, atol=0)
    assert np.allclose(a.angles, b.angles, atol=1e-10)


def test_mirror_flips_every_angle():
    V, F = load("decimated-knight.off")
    a = fundamental_forms(V, F)
    # The mirror image with the same faces: its face normals now point inwards.
    b = fundamental_forms(V * [1, 1, -1], F)
    assert np.array_equal(a.edges, b.edges)
    assert np.allclose(a.lengths, b.lengths, rtol=1e-14)
    assert np.allclose(b.angles, -a.angles, atol=1e-12)
    # Re-oriented (outward again), the mirror image has the same angles as the original.
    c = fundamental_forms(V * [1, 1, -1], F[:, ::-1])
    assert np.allclose(c.angles, a.angles, atol=1e-12)


def test_round_trip_dict():
    V, F = icosphere(1)
    forms = fundamental_forms(V, F)
    again = type(forms).from_dict(forms.to_dict())
    assert np.array_equal(again.edges, forms.edges) and np.array_equal(again.angles, forms.angles)


def test_zero_area_face_is_measured_by_the_rule():
    """Collinear corners (issue 40): the face's normal is its neighbour's, projected off
    its line (solver.mesh.forms.degenerate_normals): the edge they share is flat (angle 0)."""
    V = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0.3]])
    forms = fundamental_forms(V, [[0, 1, 2], [0, 3, 1]])
    assert forms.zero_area_faces.tolist() == [0]
    np.testing.assert_allclose(forms.angles, 0.0, atol=1e-15)


def test_face_with_two_corners_at_one_position_is_welded_and_dropped():
    """Vertices 1 and 2 are at one position and face 0 joins them: 2 is welded into 1
    and face 0 dropped (solver.mesh.weld); the other face is measured."""
    V = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 0], [0, 1, 0.0]])
    forms = fundamental_forms(V, [[0, 1, 2], [0, 3, 1]])
    assert forms.weld_map.tolist() == [0, 1, 1, 3] and forms.dropped_faces.tolist() == [0]
    assert forms.faces.tolist() == [[0, 3, 1]]
    np.testing.assert_allclose(forms.lengths, [1.0, 1.0, np.sqrt(2.0)])


def test_nan_vertex_is_named():
    V, F = icosphere(0)
    V[5, 1] = np.nan
    with pytest.raises(NonFiniteValueError) as err:
        fundamental_forms(V, F)
    assert err.value.field == "vertices" and err.value.index == 5


class TestValidateForms:
    def setup_method(self):
        V, F = icosphere(1)
        self.forms = fundamental_forms(V, F)

    def args(self, **change):
        data = {"faces": self.forms.faces, "edges": self.forms.edges,
                "lengths": self.forms.lengths.copy(), "angles": self.forms.angles.copy()}
        data.update(change)
        return data

    def test_valid(self):
        topo, L, A = validate_forms(**self.args())
        assert len(L) == len(A) == topo.n_edges

    def test_non_positive_length(self):
        L = self.forms.lengths.copy()
        L[7] = 0.0
        with pytest.raises(NonPositiveLengthError) as err:
            validate_forms(**self.args(lengths=L))
        assert err.value.index == 7 and err.value.field == "lengths"

    def test_infinite_length(self):
        L = self.forms.lengths.copy()
        L[3] = np.inf
        with pytest.raises(NonFiniteValueError) as err:
            validate_forms(**self.args(lengths=L))
        assert err.value.index == 3

    def test_angle_out_of_range_is_wrapped(self):
        # An angle is periodic: 3.5 rad is the angle 3.5 - 2 pi (issue 40).
        A = self.forms.angles.copy()
        A[11] = 3.5
        _, _, wrapped = validate_forms(**self.args(angles=A))
        assert wrapped[11] == pytest.approx(3.5 - 2 * np.pi, abs=1e-15)
        np.testing.assert_array_equal(np.delete(wrapped, 11), np.delete(A, 11))

    def test_minus_pi_excluded(self):
        A = self.forms.angles.copy()
        A[2] = -np.pi - 1e-6
        A[3] = -np.pi
        _, _, wrapped = validate_forms(**self.args(angles=A))
        assert wrapped[2] == pytest.approx(np.pi - 1e-6, abs=1e-14)
        assert wrapped[3] == np.pi

    def test_lengths_wrong_count(self):
        with pytest.raises(ShapeMismatchError) as err:
            validate_forms(**self.args(lengths=self.forms.lengths[:-1]))
        assert err.value.field == "lengths"

    def test_edges_wrong_count(self):
        with pytest.raises(EdgeMismatchError):
            validate_forms(**self.args(edges=self.forms.edges[:-1]))

    def test_edges_unsorted_pair(self):
        E = self.forms.edges.copy()
        E[4] = E[4, ::-1]
        with pytest.raises(EdgeMismatchError) as err:
            validate_forms(**self.args(edges=E))
        assert err.value.index == 4 and "i < j" in str(err.value)

    def test_edges_not_of_faces(self):
        E = self.forms.edges.copy()
        E[0] = [0, 40]
        with pytest.raises(EdgeMismatchError) as err:
            validate_forms(**self.args(edges=E))
        assert err.value.index == 0
