"""``ffs`` batches: the files ``--align-to`` and ``--cotangent`` name are read once per
command, not once per input (counted by an audit hook in every process, the local worker
processes of ``-j 2`` included), a bad one is a usage error before any work; and a local
item's progress reaches the queue through the service's throttle
(:class:`ffs_wire.progress.ProgressThrottle`), not once per chart."""

from __future__ import annotations

import itertools
import os
import queue
import time
from pathlib import Path

import numpy as np

from ffs.cli.arguments import build_parser
from ffs.cli.batch import run_item
from ffs.cli.commands import RUNNERS
from ffs.cli.items import Row, plan_items
from ffs.local import Local
from ffs_wire.progress import PROGRESS_INTERVAL
from tests.helpers import DATA, REPO

_COUNT_OPENS = '''
import os, sys
_names = set(os.environ.get("FFS_TEST_COUNT_OPENS", "").split(","))
_log = os.environ.get("FFS_TEST_OPENS_LOG")

def _hook(event, args):
    if event == "open" and args and isinstance(args[0], (str, bytes, os.PathLike)):
        name = os.path.basename(os.fsdecode(args[0]))
        if name in _names:
            with open(_log, "a") as out:
                out.write(f"{name} {os.getpid()}\\n")

if _log:
    sys.addaudithook(_hook)
'''


def _opens(ffs, workdir: Path, names: list[str], *args: str) -> tuple[object, list[str]]:
    """Run ``ffs *args`` with every Python process it starts counting its opens of the
    files ``names`` (a ``sitecustomize`` audit hook); the run and the names opened."""
    hook = workdir / "hook"
    hook.mkdir(exist_ok=True)
    (hook / "sitecustomize.py").write_text(_COUNT_OPENS)
    log = workdir / "opens.log"
    log.unlink(missing_ok=True)
    env = {"PYTHONPATH": os.pathsep.join([str(hook), str(REPO),
                                          os.environ.get("PYTHONPATH", "")]),
           "FFS_TEST_COUNT_OPENS": ",".join(names), "FFS_TEST_OPENS_LOG": str(log)}
    run = ffs(*args, env=env)
    opened = log.read_text().split() if log.exists() else []
    return run, opened[::2]


def test_align_to_and_cotangent_files_are_read_once_for_all_inputs(ffs, workdir: Path):
    done = ffs("forms", "torus.off", "-o", "a.json", "-q")
    assert done.returncode == 0, done.stderr
    for name in ("b.json", "c.json"):
        (workdir / name).write_bytes((workdir / "a.json").read_bytes())
    run, opened = _opens(ffs, workdir, ["torus.off"], "reconstruct", "a.json", "b.json",
                         "c.json", "--align-to", "torus.off", "-o", "out/{stem}.ply",
                         "-j", "2", "-q")
    assert run.returncode == 0, run.stderr
    assert opened == ["torus.off"], opened  # once, by the command: not by each input
    for stem in ("a", "b", "c"):  # and every input was aligned with it
        assert (workdir / "out" / f"{stem}.ply").exists()
    n = len(np.loadtxt(workdir / "torus.off", skiprows=2, max_rows=1200))
    np.save(workdir / "g.npy", np.random.default_rng(0).normal(size=(n, 3)))
    run, opened = _opens(ffs, workdir, ["g.npy"], "vjp", "a.json", "b.json", "c.json",
                         "--cotangent", "g.npy", "--no-refine", "-o", "grads/{stem}.npz",
                         "-j", "2", "-q")
    assert run.returncode == 0, run.stderr
    assert opened == ["g.npy"], opened
    grads = [np.load(workdir / "grads" / f"{s}.npz")["grad_lengths"] for s in "abc"]
    np.testing.assert_array_equal(grads[0], grads[1])  # the same forms, the same gradient
    np.testing.assert_array_equal(grads[0], grads[2])


def test_an_align_to_or_cotangent_that_does_not_read_is_one_usage_error(ffs, workdir: Path):
    """A reference that is not a mesh, a cotangent that is not (n, 3): exit 2 naming the
    option before any input is read (each input failed on its own, exit 1)."""
    ffs("forms", "torus.off", "-o", "a.json", "-q")
    (workdir / "b.json").write_bytes((workdir / "a.json").read_bytes())
    np.save(workdir / "g.npy", np.zeros((4, 2)))
    for args, flag, words in (
            (("reconstruct", "a.json", "b.json", "--align-to", "a.json"), "--align-to",
             "a forms file (edges, lengths, angles) has no vertices"),
            (("vjp", "a.json", "b.json", "--cotangent", "g.npy"), "--cotangent",
             "expected shape (n, 3) or (k, n, 3), got [4, 2]")):
        run = ffs(*args, "-o", "out/{stem}.npz" if flag == "--cotangent" else "out/{stem}.ply",
                  "-j", "2", "--report", "report.json")
        assert run.returncode == 2, (run.stdout, run.stderr)
        lines = [line for line in run.stderr.splitlines() if line.strip()]
        assert len(lines) == 1 and lines[0].startswith(f"ffs {args[0]}: error: {flag} ")
        assert words in lines[0], lines
        assert not (workdir / "out").exists() and not (workdir / "report.json").exists()


def test_a_local_items_progress_is_throttled_and_its_last_report_arrives(tmp_path):
    """A flattening of the octopus reports each of its 82 charts (85 reports in a second);
    through run_item (what each worker process of ``-j N`` runs) at most one per
    PROGRESS_INTERVAL reaches the queue, plus one per stage, and the last always."""
    args = build_parser().parse_args(["flatten", str(DATA / "octopus-low-surface.off"),
                                      "-o", str(tmp_path / "flat.obj"), "-q"])
    item = plan_items("flatten", args.inputs, args.output, None, None)[0]
    raw: list[tuple[str, float]] = []
    RUNNERS["flatten"](Local(), item, args, lambda s, f: raw.append((s, float(f))),
                       Row(file=item.name, outputs=item.outputs))
    assert len(raw) > 40, len(raw)  # unthrottled: a report per chart
    events: queue.Queue = queue.Queue()
    started = time.perf_counter()
    row = run_item("flatten", args, item, Local(), events)
    elapsed = time.perf_counter() - started
    assert row.status == "ok", row.error
    sent = []
    while not events.empty():
        sent.append(events.get_nowait())
    stages = [stage for _, stage, _ in sent]
    runs = 1 + sum(a != b for a, b in itertools.pairwise(stages))
    assert sent[0] == (item.index, "start", 0.0)
    assert len(sent) <= runs + elapsed / PROGRESS_INTERVAL + 2, (len(sent), runs, elapsed)
    assert sent[-1][1:] == raw[-1]  # the last report is never held back
