"""``ffs flatten``'s summary: the error columns are the statistics its distortion warnings
are on (the means), labelled so, and a refinement that stalled with no warning says done."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import trimesh

from tests.helpers.meshes import sphere_cap


def _row(stdout: str, name: str) -> list[str]:
    """The table's cells of ``name`` (columns are two or more spaces apart)."""
    import re

    [line] = [line for line in stdout.splitlines() if line.startswith(name)]
    return re.split(r"\s{2,}", line.strip())


def test_the_columns_are_the_warnings_statistics(ffs, workdir: Path) -> None:
    V, F = sphere_cap()
    trimesh.Trimesh(V, F, process=False).export(workdir / "cap.obj")
    run = ffs("flatten", "face.off", "octopus-low-surface.off", "-o", "flat/{stem}.obj",
              "--report", "report.json")
    capped = ffs("flatten", "cap.obj", "--seams", "none", "-o", "flat/cap.obj",
                 "--report", "cap.json")
    assert run.returncode == 0 and capped.returncode == 0, run.stderr + capped.stderr
    header = next(line for line in run.stdout.splitlines() if line.startswith("file"))
    assert "length err (mean)" in header and "angle err (mean)" in header, header
    files = {f["file"]: f for f in json.loads((workdir / "report.json").read_text())["files"]}
    files.update({f["file"]: f for f in json.loads((workdir / "cap.json").read_text())[
        "files"]})
    for name, stdout in (("face.off", run.stdout), ("octopus-low-surface.off", run.stdout),
                         ("cap.obj", capped.stdout)):
        entry, cells = files[name], _row(stdout, name)
        report = entry["report"]
        # The columns: the means of the written layout's distortion.
        length = report["length_change_summary"]["mean"]
        angle = report["angle_distortion_summary"]["mean"]
        assert entry["length_error"] == length and entry["angle_error"] == angle
        assert f"{100 * length:.3g}%" in cells, cells
        assert f"{angle:.3g} rad ({np.degrees(angle):.3g}°)" in cells, cells
        warnings = {w["code"]: w for w in entry["warnings"]}
        if "length-distortion" in warnings:  # the warning's value is the column's
            assert warnings["length-distortion"]["value"] == length > 0.1
        else:
            assert length <= 0.1
        if "angle-distortion" in warnings:
            assert warnings["angle-distortion"]["value"] == angle > 0.2
        else:
            assert angle <= 0.2
        refinement = report["refinement"]
        if refinement["stop_reason"] == "stalled" and not warnings:
            assert entry["outcome"].startswith("done: quality targets met, stalled"), entry
        elif refinement["stop_reason"] == "stalled":
            assert entry["outcome"].startswith("partly: stalled"), entry
    # The family: two stalls at the targets (one chart, an atlas), one past them.
    assert files["face.off"]["outcome"].startswith("done:")
    assert files["octopus-low-surface.off"]["outcome"].startswith("done:")
    assert files["cap.obj"]["outcome"].startswith("partly: stalled")
    assert "WARN" in _row(capped.stdout, "cap.obj")[-1]
