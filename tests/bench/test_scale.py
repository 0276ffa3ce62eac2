"""bench/scale.py's progress on stderr: a long case shows its stages and the refinement's
iterations as they come, and they agree with the row the case reports.

Independent truth: the case's own row (its refinement iterations and energy, from the
solver's report) against the progress lines forwarded by the parent; a child that fails
is reported by its error line, never by a progress line.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import pytest

from bench import scale
from bench.common import REPO, SHARED_MESHES

pytestmark = pytest.mark.skipif(not SHARED_MESHES.exists(), reason="no ../shared/meshes")

ITERATION = re.compile(r"refine iteration (\d+): E ([0-9.e+-]+), (\d+) factorizations")


@pytest.mark.parametrize(("base", "case"), [("bunny.off", "default-iterative"),
                                            ("torus.off", "default")])
def test_the_parent_forwards_each_stage_and_iteration_of_the_refinement(tmp_path, base, case):
    env = dict(os.environ, FFS_SCALE_CACHE=str(tmp_path))
    proc = subprocess.run(
        [sys.executable, "-m", "bench.scale", "--bases", base, "--levels", "0", "--cases",
         case, "--max-gb", "0"], capture_output=True, text=True, env=env, cwd=REPO,
        timeout=300, check=True)
    row = json.loads([line for line in proc.stdout.splitlines() if line.startswith("{")][-1])
    prefix = f"[{base.split('.')[0]} level 0 {case}]"
    progress = [line for line in proc.stderr.splitlines() if line.startswith(prefix)]
    stages = [line.split()[-4] for line in progress if "iteration" not in line]
    assert stages == ["validate", "assemble", "factorize", "solve", "refine"]
    iterations = [ITERATION.search(line).groups() for line in progress if "iteration" in line]
    assert [int(i) for i, _, _ in iterations] == list(range(1, row["iterations"] + 1))
    assert float(iterations[-1][1]) == pytest.approx(row["energy_after"], rel=1e-6)
    assert int(iterations[-1][2]) == row["factorizations"]
    elapsed = [float(line[len(prefix):].split()[0]) for line in progress]
    assert elapsed == sorted(elapsed) and elapsed[-1] <= row["seconds"] + 5.0


def test_a_failed_child_is_reported_by_its_error_not_its_progress():
    program = ("import sys; print('progress: 1.0 s  solve', file=sys.stderr); "
               "print('ValueError: the forms are not finite', file=sys.stderr); "
               "print('progress: 2.0 s  refine', file=sys.stderr); sys.exit(3)")
    returncode, stdout, stderr = scale.run_forwarding_progress(
        [sys.executable, "-c", program], dict(os.environ), REPO, "[x] ")
    assert returncode == 3 and stdout == ""
    assert scale.failure(returncode, stderr) == "ValueError: the forms are not finite"
    assert scale.failure(-9, "progress: 1.0 s  solve\n") == "exit -9"
    assert scale.failure(1, "progress: x\nMemoryError: cannot\n") == "out of memory"


def test_the_forwarded_lines_carry_the_prefix_and_keep_their_order(capfd):
    program = ("import sys\nfor i in range(50): print(f'progress: {i}.0 s  step {i}', "
               "file=sys.stderr, flush=True)\nprint('{\"done\": 1}')")
    returncode, stdout, stderr = scale.run_forwarding_progress(
        [sys.executable, "-c", program], dict(os.environ), REPO, "[case] ")
    forwarded = capfd.readouterr().err.splitlines()
    assert returncode == 0 and json.loads(stdout) == {"done": 1}
    assert forwarded == [f"[case] {i}.0 s  step {i}" for i in range(50)]
    assert len(stderr.splitlines()) == 50
