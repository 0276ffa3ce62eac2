"""A truncated OFF upload is a 400 whose problem says, in words, which record is cut
(issue 43: it quoted numpy's "setting an array element with a sequence")."""

from __future__ import annotations

from tests.solver.test_file_diagnosis import CASES, INTERNALS


def test_the_service_answers_the_same_words(client) -> None:
    data, words = CASES["vertex cut"]
    response = client.post("/v1/forms", files={"file": ("cut.off", data)})
    assert response.status_code == 400, response.text
    text = response.text
    assert words in text and not any(word in text.lower() for word in INTERNALS[:2]), text


def test_a_cut_binary_upload_says_it_ends_early(client) -> None:
    """A binary PLY cut short (an interrupted download): 400 saying the file ends before
    what its header announces, not trimesh's "PLY is unexpected length!"."""
    from tests.solver.test_file_diagnosis import FILES

    data = FILES["torus.ply"]
    response = client.post("/v1/forms", files={"file": ("scan.ply", data[:len(data) // 2])})
    assert response.status_code == 400, response.text
    detail = response.json()["detail"]
    assert "the file ends after" in detail and "truncated?" in detail, detail
    assert "unexpected length" not in response.text
