"""What a newcomer hits (issue 43), through ``ffs`` as a user runs it: the summary says how
a refinement ended (its stop reason), carries units (% and rad), says WARN for answers past
the documented thresholds (one line per warning on stderr) and ``--strict`` exits 1."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

OLD_README_HANDLES = [{"vertex": 0, "position": [0, 0, 0]},
                      {"vertex": 500, "position": [0, 0, 1]}]
"""The README's old deform example: two vertices 79 units apart pinned 1 unit apart."""


def _lines(text: str, start: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith(start)]


def test_warn_in_the_summary_and_strict_exits_1(ffs, workdir: Path) -> None:
    (workdir / "handles.json").write_text(json.dumps(OLD_README_HANDLES))
    run = ffs("deform", "face.off", "--handles", "handles.json", "-o", "out.ply",
              "--report", "report.json")
    assert run.returncode == 0, run.stderr
    row = _lines(run.stdout, "face.off")[0]
    assert "WARN length-error" in row and "converged after" in row, run.stdout
    report = json.loads((workdir / "report.json").read_text())["files"][0]
    warning = {w["code"]: w for w in report["warnings"]}["length-error"]
    rest = trimesh.load(workdir / "face.off", process=False)
    out = trimesh.load(workdir / "out.ply", process=False)
    edges = rest.edges_unique
    ratio = (np.linalg.norm(np.diff(out.vertices[edges], axis=1)[:, 0], axis=1)
             / np.linalg.norm(np.diff(rest.vertices[edges], axis=1)[:, 0], axis=1))
    assert abs(warning["value"] - np.abs(ratio - 1).max()) < 1e-5  # PLY stores float32
    assert f"{100 * warning['value']:.3g}%" in row  # the length error, as a percentage
    assert "rad (" in row and "°)" in row  # the angle error in radians and degrees
    assert f"face.off: warning: {warning['message']}" in run.stderr
    strict = ffs("deform", "face.off", "--handles", "handles.json", "-o", "out.ply",
                 "--strict")
    assert strict.returncode == 1, strict.stdout + strict.stderr


def test_scaled_example_is_clean_even_with_strict(ffs, workdir: Path) -> None:
    rest = trimesh.load(workdir / "face.off", process=False).vertices
    handles = [{"vertex": 0, "position": rest[0].tolist()},
               {"vertex": 500, "position": (rest[500] + [0, 0, 3]).tolist()}]
    (workdir / "handles.json").write_text(json.dumps(handles))
    run = ffs("deform", "face.off", "--handles", "handles.json", "-o", "out.ply", "--strict")
    assert run.returncode == 0, run.stdout + run.stderr
    assert "WARN" not in run.stdout and "warning" not in run.stderr


def test_summary_shows_the_stop_reason(ffs, workdir: Path) -> None:
    ffs("forms", "face.off", "-o", "forms.json")
    forms = json.loads((workdir / "forms.json").read_text())
    forms["angles"] = [0.8 * a for a in forms["angles"]]
    (workdir / "bent.json").write_text(json.dumps(forms))
    hurried = ffs("reconstruct", "bent.json", "-o", "bent.ply", "--max-seconds", "0.0001")
    assert hurried.returncode == 0, hurried.stderr
    row = _lines(hurried.stdout, "bent.json")[0]
    assert "not refined: time limit before the first iteration" in row, hurried.stdout
    assert "WARN" in row and "time-limit-no-progress" in row
    calm = ffs("reconstruct", "bent.json", "-o", "bent.ply")
    assert "converged after" in _lines(calm.stdout, "bent.json")[0], calm.stdout


# ------------------------------------------------------- the README's install keeps promises


def test_progress_bars_come_with_the_base_install() -> None:
    """``pip install -e .`` (the README's install) brings every package ``ffs``'s bars and
    table need: rich is a base dependency, not only the client extra's."""
    import tomllib

    from tests.helpers import REPO

    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    base = {dep.split(">")[0].split("=")[0].split("[")[0].split(";")[0].strip().lower()
            for dep in project["dependencies"]}
    assert "rich" in base, sorted(base)


def test_progress_bar_on_a_terminal(ffs, workdir: Path) -> None:
    """On a terminal (a pseudo-terminal here) a running file has a bar with its stage."""
    import os
    import pty
    import subprocess
    import sys

    from tests.helpers import REPO

    leader, follower = pty.openpty()
    env = {k: v for k, v in os.environ.items() if k != "FFS_SERVER"}
    env["PYTHONPATH"] = str(REPO)
    env["COLUMNS"] = "120"
    proc = subprocess.Popen([sys.executable, "-m", "ffs", "flatten", "face.off", "-o",
                             "flat.obj"], cwd=workdir, stdout=subprocess.DEVNULL,
                            stderr=follower, env=env)
    os.close(follower)
    chunks = []
    while True:
        try:
            chunk = os.read(leader, 65536)
        except OSError:  # the follower side closed: the process ended
            break
        if not chunk:
            break
        chunks.append(chunk)
    assert proc.wait(timeout=120) == 0
    os.close(leader)
    shown = b"".join(chunks).decode("utf-8", "replace")
    assert "face.off" in shown and "━" in shown, shown[:2000]


def test_every_number_says_its_unit(ffs, workdir: Path) -> None:
    """The integrability defect and its tolerance are angles: rad, in the table and in the
    failure line (the length and angle errors' % and rad: test_warn_in_the_summary...)."""
    import re

    ffs("forms", "face.off", "-o", "forms.json")
    forms = json.loads((workdir / "forms.json").read_text())
    forms["angles"] = [0.8 * a for a in forms["angles"]]
    (workdir / "bent.json").write_text(json.dumps(forms))
    check = ffs("check", "bent.json")
    assert re.search(r"NOT integrable, max defect [0-9.e+-]+ rad", check.stdout), check.stdout
    strict = ffs("reconstruct", "bent.json", "-o", "x.ply", "--require-integrable")
    assert strict.returncode == 1
    assert re.search(r"max defect [0-9.e+-]+ rad \(tolerance 1e-08 rad\)", strict.stderr), \
        strict.stderr


# --------------------------------------------------- file errors in words, usage errors early


def test_unwritable_output_format_is_a_usage_error_before_any_work(ffs, workdir: Path) -> None:
    for args in (("reconstruct", "face.off", "-o", "x.xyz"),
                 ("forms", "face.off", "-o", "forms.ply"),
                 ("flatten", "face.off", "torus.off", "-o", "flat/{stem}.xyz"),
                 ("convert", "face.off", "-o", "x.ply", "--format", "xyz")):
        run = ffs(*args, "--report", "report.json")
        assert run.returncode == 2, (args, run.stdout, run.stderr)
        assert "cannot write" in run.stderr and "Traceback" not in run.stderr
        assert run.stdout == ""  # no summary table: nothing ran
        assert not (workdir / "report.json").exists()


def test_truncated_off_in_words(ffs, workdir: Path) -> None:
    lines = (workdir / "torus.off").read_text().splitlines(keepends=True)
    (workdir / "cut.off").write_text("".join(lines[:60]) + "0.5 0.25\n")
    run = ffs("convert", "cut.off", "-o", "x.ply")
    assert run.returncode == 1
    assert "cut.off: cannot parse OFF data: line 61: vertex 58 has 2 coordinates, " \
        "expected 3" in run.stderr, run.stderr
    assert "inhomogeneous" not in run.stderr and "sequence" not in run.stderr


def test_bad_obj_entry_in_words(ffs, workdir: Path) -> None:
    """An OBJ face entry or coordinate that is not a number: its line and the entry, not
    Python's "invalid literal for int() with base 10"."""
    (workdir / "tri.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n# a face\nf 1 2 x3\n")
    run = ffs("convert", "tri.obj", "-o", "x.ply")
    assert run.returncode == 1
    assert "tri.obj: line 5: face index 'x3' is not a whole number" in run.stderr, run.stderr
    (workdir / "tri.obj").write_text("v 0 0 0\nv 1 0,5 0\nv 0 1 0\nf 1 2 3\n")
    run = ffs("convert", "tri.obj", "-o", "x.ply")
    assert "tri.obj: line 2: vertex coordinate '0,5' is not a number" in run.stderr, run.stderr
    assert "literal" not in run.stderr and "could not convert" not in run.stderr


# ------------------------------------------------------------- Botsch-Sorkine handle sets


def test_deform_reads_a_sel_def_pair(ffs, workdir: Path) -> None:
    """``--handles bar.sel`` (bar.def beside it): the handle vertices reach the .def's
    transform of their rest positions, the fixed ones stay at rest bit for bit, and the
    answer is the library's deformation with the same handles, ROI and rotation."""
    import shutil

    import solver
    from tests.helpers import DATA
    from tests.helpers.botsch_sorkine import load_case

    for suffix in (".off", ".sel", ".def"):
        shutil.copy(DATA / f"bar{suffix}", workdir / f"bar{suffix}")
    run = ffs("deform", "bar.off", "--handles", "bar.sel", "-o", "twisted.ply", "--no-refine")
    assert run.returncode == 0, run.stderr
    case = load_case(DATA, "bar")
    out = np.asarray(trimesh.load(workdir / "twisted.ply", process=False).vertices)
    size = np.ptp(case.vertices)
    assert np.abs(out[case.handles] - case.handle_targets()).max() < 1e-5 * size
    assert np.array_equal(out[case.fixed], case.vertices[case.fixed])
    assert np.abs(out[case.handles] - case.vertices[case.handles]).max() > 0.1 * size
    library = solver.deform(case.vertices, case.faces, case.handles, case.handle_targets(),
                            rotation_handles=[case.handle_faces()],
                            handle_rotations=case.transform[None, :3, :3], roi=case.roi,
                            refine=False).vertices
    assert np.abs(out - library).max() < 1e-4 * size
    same = ffs("deform", "bar.off", "--handles", "bar.def", "-o", "twisted2.ply",
               "--no-refine")  # the .def names the pair as well
    assert same.returncode == 0, same.stderr
    again = np.asarray(trimesh.load(workdir / "twisted2.ply", process=False).vertices)
    assert np.array_equal(again, out)


def test_sel_def_errors_in_words(ffs, workdir: Path) -> None:
    (workdir / "face.sel").write_text("# three values for 1180 vertices\n0\n1\n2\n")
    (workdir / "face.def").write_text("1 0 0 0\n0 1 0 0\n0 0 1 5\n0 0 0 1\n")
    run = ffs("deform", "face.off", "--handles", "face.sel", "-o", "x.ply")
    assert run.returncode == 1
    assert "face.sel: 3 values for a mesh of 1180 vertices" in run.stderr, run.stderr
    (workdir / "face.sel").write_text("\n".join(["0"] * 1179 + ["7"]) + "\n")
    run = ffs("deform", "face.off", "--handles", "face.sel", "-o", "x.ply")
    assert "face.sel: vertex[1179]: 7 is not 0 (fixed), 1 (free) or 2 (handle)" in run.stderr
    (workdir / "torus.sel").write_text("2\n" * 1200)
    run = ffs("deform", "torus.off", "--handles", "torus.sel", "-o", "x.ply")
    assert run.returncode == 2, (run.stdout, run.stderr)   # usage: before any work
    assert "no such file torus.def (the other half of torus.sel)" in run.stderr, run.stderr


def test_a_missing_option_file_is_a_usage_error_before_any_work(ffs, workdir: Path) -> None:
    """--align-to, --handles, --cotangent and --constraints name one file every input reads:
    a missing one is exit 2 with its name before anything runs, not a failure of each
    input."""
    for args, flag in ((("reconstruct", "face.off", "torus.off", "--align-to", "ref.off",
                         "-o", "out/{stem}.ply"), "--align-to"),
                       (("deform", "face.off", "--handles", "moves.json", "-o", "out/x.ply"),
                        "--handles"),
                       (("deform", "face.off", "--handles", "face.def", "-o", "out/x.ply"),
                        "--handles"),
                       (("vjp", "face.off", "--cotangent", "g.npy", "-o", "out/g.npz"),
                        "--cotangent"),
                       # newcomer sweep: --constraints failed each input instead (exit 1)
                       (("reconstruct", "face.off", "torus.off", "--constraints", "pins.json",
                         "-o", "out/{stem}.ply"), "--constraints")):
        run = ffs(*args, "--report", "report.json")
        assert run.returncode == 2, (args, run.stdout, run.stderr)
        assert f"{flag} " in run.stderr and "no such file" in run.stderr, run.stderr
        assert "Traceback" not in run.stderr and run.stdout == ""   # nothing ran
        assert not (workdir / "report.json").exists() and not (workdir / "out").exists()


@pytest.mark.parametrize(("name", "text", "words"), [
    ("moves.json", "not json {", "cannot read it as JSON"),
    ("moves.json", '{"handle": [{"vertex": 0, "position": [0, 0, 0]}]}', "non-empty list"),
    ("moves.json", '[{"vertex": 0, "positon": [0, 0, 0]}]', "unknown member 'positon'"),
])
@pytest.mark.parametrize("jobs", ["1", "2"])
def test_a_handles_file_that_is_not_handles_is_one_usage_error(ffs, workdir: Path, name, text,
                                                               words, jobs) -> None:
    """A --handles file every input reads that is not JSON handles: exit 2 and one line
    before any input is read (it failed once per input, exit 1), in threads and in worker
    processes alike; the same for --constraints."""
    (workdir / name).write_text(text)
    run = ffs("deform", "face.off", "torus.off", "--handles", name, "-o", "out/",
              "-j", jobs, "--report", "report.json")
    assert run.returncode == 2, (run.stdout, run.stderr)
    lines = [line for line in run.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"ffs deform: error: --handles {name}"), lines
    assert words in lines[0] and "face.off" not in lines[0] and "torus.off" not in lines[0]
    assert "Traceback" not in run.stderr and run.stdout == ""
    assert not (workdir / "report.json").exists() and not (workdir / "out").exists()
    if jobs == "1":
        run = ffs("reconstruct", "face.off", "torus.off", "--constraints", name,
                  "-o", "out/{stem}.ply")
        if text.startswith("not json"):
            assert run.returncode == 2 and "--constraints" in run.stderr, run.stderr
            assert not (workdir / "out").exists()


def test_json_handles_read_once_move_every_input(ffs, workdir: Path) -> None:
    """Handles read up front serve each input: both meshes keep vertex 0 where the file says,
    as a run per file does."""
    (workdir / "moves.json").write_text(json.dumps([{"vertex": 0, "position": [0, 0, 0]}]))
    run = ffs("deform", "face.off", "torus.off", "--handles", "moves.json", "-o",
              "out/{stem}.ply", "--no-refine", "-q")
    assert run.returncode == 0, run.stderr
    for stem in ("face", "torus"):
        one = ffs("deform", f"{stem}.off", "--handles", "moves.json", "-o", f"{stem}-1.ply",
                  "--no-refine", "-q")
        assert one.returncode == 0, one.stderr
        both = trimesh.load(workdir / "out" / f"{stem}.ply", process=False).vertices
        alone = trimesh.load(workdir / f"{stem}-1.ply", process=False).vertices
        np.testing.assert_allclose(both, alone, atol=1e-12)
        np.testing.assert_allclose(both[0], [0, 0, 0], atol=1e-9)


# ------------------------------------------------------------------------- --align-to REF


def _rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


def test_align_to_puts_the_answer_on_the_reference(ffs, workdir: Path) -> None:
    """Without --align-to the reconstruction lies anywhere; with it, the face rebuilt from
    its own forms lies on face.off (residual ~0), and from bent forms the reported residual
    is the RMS distance between the written answer and the reference."""
    face = np.asarray(trimesh.load(workdir / "face.off", process=False).vertices)
    ffs("forms", "face.off", "-o", "forms.json")
    forms = json.loads((workdir / "forms.json").read_text())
    forms.pop("placement")  # forms without the mesh's placement: the solver places it
    (workdir / "forms.json").write_text(json.dumps(forms))
    loose = ffs("reconstruct", "forms.json", "-o", "loose.ply")
    assert loose.returncode == 0, loose.stderr
    placed = np.asarray(trimesh.load(workdir / "loose.ply", process=False).vertices)
    assert _rms(placed, face) > 1.0  # the solver's placement is not the face's
    run = ffs("reconstruct", "forms.json", "-o", "aligned.ply", "--align-to", "face.off",
              "--report", "report.json")
    assert run.returncode == 0, run.stderr
    aligned = np.asarray(trimesh.load(workdir / "aligned.ply", process=False).vertices)
    assert _rms(aligned, face) < 1e-6 * np.ptp(face)
    assert "aligned to face.off: residual rms" in run.stdout

    forms = json.loads((workdir / "forms.json").read_text())
    forms["angles"] = [0.8 * a for a in forms["angles"]]
    (workdir / "bent.json").write_text(json.dumps(forms))
    bent = ffs("reconstruct", "bent.json", "-o", "bent.ply", "--align-to", "face.off",
               "--report", "bent.json.report")
    assert bent.returncode == 0, bent.stderr
    shape = np.asarray(trimesh.load(workdir / "bent.ply", process=False).vertices)
    alignment = json.loads((workdir / "bent.json.report").read_text())["files"][0][
        "report"]["alignment"]
    row = _lines(bent.stdout, "bent.json")[0]  # the bent answer warns: the residual stays
    assert "WARN angle-error; aligned to face.off: residual rms " \
        f"{alignment['residual_rms']:.3g}, max {alignment['residual_max']:.3g}" in row, row
    assert abs(alignment["residual_rms"] - _rms(shape, face)) < 1e-9 * np.ptp(face)
    distances = np.linalg.norm(shape - face, axis=1)
    assert abs(alignment["residual_max"] - distances.max()) < 1e-9 * np.ptp(face)
    rotation = np.asarray(alignment["rotation"])
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) > 0


def test_align_to_a_mesh_with_other_vertices_fails_in_words(ffs) -> None:
    ffs("forms", "face.off", "-o", "forms.json")
    run = ffs("reconstruct", "forms.json", "-o", "x.ply", "--align-to", "torus.off")
    assert run.returncode == 1
    assert "align_to: the reference has 1200 vertices, the answer 1180" in run.stderr, \
        run.stderr


# ------------------------------------------------------------ "ok" on a broken flattening


def _obj_uv(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """An OBJ's positions, texture coordinates and the v and vt indices of its faces."""
    lines = path.read_text().splitlines()
    v = np.array([ln.split()[1:4] for ln in lines if ln.startswith("v ")], dtype=float)
    vt = np.array([ln.split()[1:3] for ln in lines if ln.startswith("vt ")], dtype=float)
    corners = [[c.split("/") for c in ln.split()[1:]] for ln in lines if ln.startswith("f ")]
    index = np.array(corners, dtype=np.int64) - 1  # (m, 3, 2): v and vt of each corner
    return v, vt, index[:, :, 0], index[:, :, 1]


def test_a_broken_flattening_says_warn_and_strict_exits_1(ffs, workdir: Path) -> None:
    """A sphere with a hole at its south pole flattened as one chart without refinement
    (--seams none --no-refine): a third of its faces flip in the written uv. The summary says
    WARN with the measured fraction, --strict exits 1; the default (an atlas) is clean."""
    from tests.helpers.meshes import sphere_cap

    V, F = sphere_cap()
    trimesh.Trimesh(V, F, process=False).export(workdir / "cap.obj")
    run = ffs("flatten", "cap.obj", "--seams", "none", "--no-refine", "-o", "flat.obj",
              "--report", "report.json")
    assert run.returncode == 0, run.stderr
    row = _lines(run.stdout, "cap.obj")[0]
    assert "WARN" in row and "flipped-faces" in row and "length-distortion" in row, row
    _, vt, faces, uv_faces = _obj_uv(workdir / "flat.obj")
    assert np.array_equal(faces, F)
    a, b, c = (vt[uv_faces[:, k]] for k in range(3))
    signed = (b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0]
    flipped = float((signed < 0).sum() / len(F))
    report = json.loads((workdir / "report.json").read_text())["files"][0]
    warning = {w["code"]: w for w in report["warnings"]}["flipped-faces"]
    assert 0.1 < flipped < 0.9 and abs(warning["value"] - flipped) < 1e-12
    # The angle column is the layout's mean (over faces) largest corner-angle change
    # (scale-free, so the written vt give it; the statistic of its angle-distortion warning),
    # not the planar refinement's dihedral error (always 0).
    def corners(p: np.ndarray, t: np.ndarray) -> np.ndarray:
        e = [p[t[:, (k + 1) % 3]] - p[t[:, k]] for k in range(3)]
        cos = [np.sum(-e[k - 1] * e[k], 1) / np.linalg.norm(e[k - 1], axis=1)
               / np.linalg.norm(e[k], axis=1) for k in range(3)]
        return np.arccos(np.clip(np.stack(cos, 1), -1, 1))

    change = np.abs(corners(vt, uv_faces) - corners(V, F)).max(axis=1).mean()
    assert abs(report["angle_error"] - change) < 1e-6 and change > 0.2
    assert f"{change:.3g} rad ({np.degrees(change):.3g}°)" in row, row
    assert f"{100 * report['report']['length_change_summary']['mean']:.3g}%" in row, row
    assert f"{100 * flipped:.2f}% of the faces are flipped" in run.stderr, run.stderr
    strict = ffs("flatten", "cap.obj", "--seams", "none", "--no-refine", "-o", "flat.obj",
                 "--strict")
    assert strict.returncode == 1, strict.stdout + strict.stderr
    atlas = ffs("flatten", "cap.obj", "-o", "atlas.obj", "--strict")
    assert atlas.returncode == 0 and "WARN" not in atlas.stdout, atlas.stdout + atlas.stderr


def test_flatten_counts_read_in_words(ffs, workdir: Path) -> None:
    """One chart is "1 chart", not "1 charts" (newcomer sweep: libigl's planexy.off)."""
    box = trimesh.creation.box()  # two triangles of one square side: one chart
    trimesh.Trimesh(box.vertices, box.faces[:2], process=True).export(workdir / "square.obj")
    run = ffs("flatten", "square.obj", "-o", "flat.obj")
    assert run.returncode == 0, run.stderr
    row = _lines(run.stdout, "square.obj")[0]
    assert "0 flipped faces, 1 chart" in row and "1 charts" not in row, run.stdout


def test_a_folder_output_takes_the_extension_of_format(ffs, workdir: Path) -> None:
    """``-o out/ --format gltf`` wrote glTF into ``out/face.off`` (the input's extension),
    and ``ffs forms -o out/ --format npz`` an .npz into ``out/face.json``."""
    run = ffs("convert", "face.off", "torus.off", "-o", "out/", "--format", "gltf")
    assert run.returncode == 0, run.stderr
    assert sorted(p.name for p in (workdir / "out").iterdir()) == ["face.gltf", "torus.gltf"]
    assert trimesh.load(workdir / "out" / "face.gltf", force="mesh").faces.shape[1] == 3
    run = ffs("forms", "face.off", "-o", "forms/", "--format", "npz")
    assert run.returncode == 0, run.stderr
    assert [p.name for p in (workdir / "forms").iterdir()] == ["face.npz"]
    assert "lengths" in np.load(workdir / "forms" / "face.npz")


def test_a_constraints_file_the_api_refuses_fails_locally_too(ffs, server, workdir: Path) -> None:
    """``{"position": [...]}`` (a typo) was ignored in-process, answered as if unconstrained,
    while the service refused it; a list crashed the client with a TypeError."""
    for document, words in (({"position": [{"vertex": 0, "position": [0, 0, 0]}]},
                             "constraints.position"),
                            ([1, 2], "constraints")):
        (workdir / "pins.json").write_text(json.dumps(document))
        for where in ((), ("--server", server)):
            run = ffs("reconstruct", "decimated-knight.off", "--constraints", "pins.json",
                      "-o", "out.ply", *where)
            assert run.returncode == 1, (where, run.stdout, run.stderr)
            assert words in run.stderr and "unexpected error" not in run.stderr, run.stderr


def test_a_handles_file_with_a_mistyped_member_is_refused(ffs, workdir: Path) -> None:
    """``weigth`` in a handle or ``rotation`` for ``rotations`` was dropped silently (the
    drag done without it); the page's own ``groups`` is still read (and ignored). The file is
    every input's: a usage error (exit 2) before any input is read."""
    handle = {"vertex": 0, "position": [0.0, 0.0, 0.0]}
    for document, words in (([{**handle, "weigth": 2}], "handles[0]: unknown member 'weigth'"),
                            ({"handles": [handle], "rotation": []},
                             "rotation: unknown member 'rotation'")):
        (workdir / "moves.json").write_text(json.dumps(document))
        run = ffs("deform", "face.off", "--handles", "moves.json", "-o", "out.ply")
        assert run.returncode == 2 and words in run.stderr, run.stderr
    (workdir / "moves.json").write_text(json.dumps({"handles": [handle], "groups": []}))
    assert ffs("deform", "face.off", "--handles", "moves.json", "-o", "out.ply").returncode == 0


def test_a_forms_file_where_a_mesh_belongs_says_so(ffs, workdir: Path) -> None:
    """``ffs flatten forms.npz`` said only "vertices: missing"."""
    assert ffs("forms", "face.off", "-o", "face-forms.npz").returncode == 0
    for command in (("flatten",), ("convert",)):
        run = ffs(*command, "face-forms.npz", "-o", "out.obj")
        assert run.returncode == 1 and "a forms file" in run.stderr, run.stderr
        assert "ffs reconstruct" in run.stderr, run.stderr


def test_a_server_without_scheme_is_a_usage_error(ffs, workdir: Path) -> None:
    """``--server 127.0.0.1:8000`` failed every input with httpx's "missing an 'http://'
    protocol" (exit 1, one line per file); now exit 2 before any work, with the fix."""
    run = ffs("forms", "face.off", "torus.off", "-o", "out/{stem}.json", "--server",
              "127.0.0.1:8000")
    assert run.returncode == 2 and run.stdout == "", (run.stdout, run.stderr)
    assert "e.g. http://127.0.0.1:8000" in run.stderr and not (workdir / "out").exists()
    run = ffs("forms", "face.off", "-o", "out.json", env={"FFS_SERVER": "localhost:8000"})
    assert run.returncode == 2 and "FFS_SERVER" in run.stderr, run.stderr
