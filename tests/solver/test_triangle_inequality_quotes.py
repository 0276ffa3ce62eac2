"""The solver's triangle-inequality error quotes the lengths the caller passed.

The solver divides lengths by their mean before laying faces out; its error must still name
the caller's numbers (issue 13, finding 9), checked here against the input arrays.
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from solver import fundamental_forms, reconstruct
from solver.core.errors import TriangleInequalityError
from tests.helpers.meshes import icosphere

NUMBER = r"-?\d+(?:\.\d+)?(?:e[-+]?\d+)?"


def _face_edges(faces: np.ndarray, edges: np.ndarray, t: int) -> list[int]:
    """Indices into ``edges`` (E, 2) of the edges v0v1, v1v2, v2v0 of face ``t``."""
    rows = [tuple(e) for e in edges.tolist()]
    a, b, c = faces[t].tolist()
    return [rows.index(tuple(sorted(pair))) for pair in ((a, b), (b, c), (c, a))]


def _quoted(message: str) -> list[float]:
    """The numbers between 'edge lengths' and 'of face' in the message."""
    found = re.search(rf"edge lengths ((?:{NUMBER}, )*{NUMBER}) of face", message)
    assert found, message
    return [float(x) for x in found.group(1).split(", ")]


def test_square_quotes_100_and_1_41() -> None:
    """Two faces; the client's lengths 100 and 1.41 appear as written, not divided by the
    mean edge length (which was about 21.3)."""
    vertices = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    forms = fundamental_forms(vertices, faces)
    lengths = np.full(len(forms.edges), 1.41)
    long_edge = _face_edges(faces, forms.edges, 0)[0]  # [0, 1]
    lengths[long_edge] = 100.0
    with pytest.raises(TriangleInequalityError) as err:
        reconstruct(faces, forms.edges, lengths, forms.angles)
    message = str(err.value)
    assert err.value.field == "faces" and err.value.index == 0
    assert "edge lengths 100, 1.41, 1.41 of face 0" in message, message
    assert "100 > 1.41 + 1.41" in message, message
    mean = lengths.mean()
    assert f"{100 / mean:.3f}" not in message and f"{1.41 / mean:.4f}" not in message
    assert err.value.details["edges"] == _face_edges(faces, forms.edges, 0)
    assert err.value.details["lengths"] == [100.0, 1.41, 1.41]


def test_quoted_numbers_are_the_input_lengths_bit_for_bit() -> None:
    """An icosphere with lengths far from 1 (random, scaled by 1e3) and a few faces broken:
    the message's numbers and ``details`` are exactly the first bad face's input lengths,
    and the face count is the number of faces that really violate the inequality."""
    vertices, faces = icosphere(2)
    forms = fundamental_forms(vertices, faces)
    rng = np.random.default_rng(13)
    lengths = forms.lengths * 1e3 * rng.uniform(0.999, 1.001, len(forms.lengths))
    broken = [17, 40, 41]
    lengths[broken] *= 7.3  # each breaks both faces beside that edge
    rows = np.array([_face_edges(faces, forms.edges, t) for t in range(len(faces))])
    sides = np.sort(lengths[rows], axis=1)
    violating = np.flatnonzero(sides[:, 2] > sides[:, 0] + sides[:, 1])
    assert len(violating) >= 4  # independent count from the input lengths
    with pytest.raises(TriangleInequalityError) as err:
        reconstruct(faces, forms.edges, lengths, forms.angles)
    t = int(violating[0])
    assert err.value.index == t
    expected = lengths[rows[t]].tolist()
    assert _quoted(str(err.value)) == expected  # repr round-trips: equal bit for bit
    assert err.value.details["lengths"] == expected
    assert err.value.details["edges"] == rows[t].tolist()
    assert err.value.details["faces"] == violating.tolist()
    assert f"({len(violating)} faces in all)" in str(err.value)
    edges = forms.edges[rows[t]].tolist()
    assert f"(edges {edges})" in str(err.value)
