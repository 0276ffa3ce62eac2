"""Mesh-file errors in words (issue 43): a truncated or malformed OFF file names the record
and line at fault, never numpy's "inhomogeneous shape" message; the service's problem says
the same."""

from __future__ import annotations

import pytest

from solver.core.errors import MeshFileError
from solver.mesh.io import load_mesh
from tests.helpers import DATA

GOOD = (DATA / "torus.off").read_bytes()
INTERNALS = ("inhomogeneous", "sequence", "array", "shape", "dtype")


def _lines(data: bytes) -> list[bytes]:
    return data.splitlines(keepends=True)


CASES = {
    # the last vertex line cut after two numbers (the "setting an array element")
    "vertex cut": (b"OFF\n4 1 0\n0 0 0\n1 0 0\n0 1 0\n0 1\n3 0 1 2\n",
                   "line 6: vertex 3 has 2 coordinates, expected 3"),
    "file cut in the vertices": (b"".join(_lines(GOOD)[:100]),
                                 "the file ends after 98 of the 1200 vertices"),
    "file cut in the faces": (b"".join(_lines(GOOD)[:1300]),
                              "the file ends after 98 of the 2400 faces"),
    "face cut": (b"OFF\n3 2 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 0 1\n",
                 "line 7: face 1 lists 2 vertex indices, its count says 3"),
    "not a number": (b"OFF\n3 1 0\n0 0 0\n1 x 0\n0 1 0\n3 0 1 2\n",
                     "line 4: vertex 1 has a coordinate that is not a number: '1 x 0'"),
    "no counts": (b"OFF\nthree one zero\n0 0 0\n", "the header needs the vertex and face counts"),
}


@pytest.mark.parametrize("name", list(CASES))
def test_truncated_off_in_words(name: str) -> None:
    data, words = CASES[name]
    with pytest.raises(MeshFileError) as caught:
        load_mesh(data, "x.off")
    message = str(caught.value)
    assert words in message, message
    assert not any(word in message.lower() for word in INTERNALS), message


def test_good_off_still_reads() -> None:
    vertices, faces = load_mesh(GOOD, "torus.off")
    assert vertices.shape == (1200, 3) and faces.shape == (2400, 3)



# ---------------------------------------------------------------- binary files cut short

def _binary_files() -> dict[str, bytes]:
    """A family of complete files: three meshes (an icosphere, the torus, a bumpy grid with
    a boundary) in binary and ASCII PLY, binary and ASCII STL, and GLB."""
    import trimesh

    from solver.mesh.io import save_mesh
    from tests.helpers.meshes import bumpy_grid, icosphere

    files = {}
    for name, (V, F) in {"sphere": icosphere(2), "torus": load_mesh(GOOD, "torus.off"),
                         "grid": bumpy_grid(12)}.items():
        mesh = trimesh.Trimesh(V, F, process=False)
        files[f"{name}.ply"] = save_mesh(V, F, "ply")
        files[f"{name}-ascii.ply"] = mesh.export(file_type="ply", encoding="ascii")
        files[f"{name}.stl"] = save_mesh(V, F, "stl")
        files[f"{name}-ascii.stl"] = mesh.export(file_type="stl_ascii").encode()
        files[f"{name}.glb"] = save_mesh(V, F, "glb")
    return files


FILES = _binary_files()


@pytest.mark.parametrize("name", sorted(FILES))
@pytest.mark.parametrize("kept", [0.97, 0.6, 0.2])
def test_a_cut_binary_file_says_it_ends_early(name: str, kept: float) -> None:
    """Cut anywhere past its header, each file is refused in words that say it ends early
    (with what its header announced), never a parser's internals; the diagnosis has nothing
    to say of the complete file, which reads."""
    from solver.mesh.formats import FORMATS

    data = FILES[name]
    fmt = name.rsplit(".", 1)[1]
    assert FORMATS[fmt].diagnose(data) is None
    load_mesh(data, name)
    cut = data[:max(int(len(data) * kept), 300)]
    with pytest.raises(MeshFileError) as caught:
        load_mesh(cut, name)
    message = str(caught.value)
    assert "truncated?" in message and "the file ends" in message, message
    assert not any(word in message.lower() for word in INTERNALS), message
    assert "unexpected length" not in message and "no triangle mesh" not in message
