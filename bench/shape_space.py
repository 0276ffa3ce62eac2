"""Shape-space sequences: rows per second of a blend sequence against independent rows.

For each mesh, a near-isometric pose is made with the library's deformation (one end of
the longest axis held, the other turned by 0.6 rad: tests/helpers/poses.py), and a T-row
blend from the rest shape to the pose (t = 0 .. 1) is solved twice in the same run:

* as a sequence (:func:`solver.blend`, the default: one symbolic analysis, each row from
  its neighbour's answer, the Gauss-Newton factor kept across rows);
* as independent reconstructions (``sequence=False``: each row Eq. 5, then the nearest
  surface from the better of the layout fit and the vertex blend), on every row, or on
  ``--independent`` rows spread over the sequence (the rate is then per row measured).

Since the machine is shared, each mesh's row also records the 1-minute load average before
and after its runs and the seconds of a fixed *reference* computation timed in the same run
just before it (the median of three Eq. 5 reconstructions of bunny.off from its own forms,
no refinement): rows/s x reference seconds is a rate that varies less with the load.

Quality per row: the mean relative length error and the mean dihedral-angle error of each
answer against its row's blended forms (what the row asks for), for the sequence, the
independent answer and the vertex blend ``(1 - t) A + t B``; the table gives the worst
ratio sequence / independent over the rows compared, and the mean errors.

With ``--baseline REV`` the sequence is also solved by the solver of git revision ``REV``
(:func:`bench.baseline.solver_at`), ``--pairs`` times each, alternating which goes first:
the table then gives both rates (medians) and the median of the pairs' ratios, a comparison
under the same load.

    python -m bench.shape_space [--meshes bunny.off rocker-arm.obj bumpy-plane.off]
        [--rows 100] [--independent 100] [--baseline REV [--pairs 3]] [--write]

``--write`` replaces the section "Shape space: blend sequences" of bench/README.md.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from bench.common import REPO, load_averages, load_bench_mesh, write_section
from solver import blend
from solver.mesh.topology import build_topology
from solver.refine.form_energy import form_residuals
from tests.helpers.poses import bent_pose

MESHES = ("bunny.off", "rocker-arm.obj", "bumpy-plane.off")
SECTION = "## Shape space: blend sequences"


def errors(X: np.ndarray, topology, lengths: np.ndarray, angles: np.ndarray) -> tuple[float,
                                                                                       float]:
    """Mean relative length error and mean angle error (rad) of ``X`` against forms."""
    r = form_residuals(X, topology, lengths, angles)
    return r["length_error"]["mean"], r["angle_error"]["mean"]


def reference_seconds() -> float:
    """Median seconds of three Eq. 5 reconstructions of bunny.off from its own forms."""
    from solver import fundamental_forms, reconstruct

    V, F = load_bench_mesh("bunny.off")
    forms = fundamental_forms(V, F)
    times = []
    for _ in range(3):
        clock = time.perf_counter()
        reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles, refine=False)
        times.append(time.perf_counter() - clock)
    return float(np.median(times))


def timed(function, *args, cpu: list | None = None) -> tuple[float, object]:
    """(seconds, result) of ``function(*args)``; the process's CPU seconds (every thread's)
    are appended to ``cpu`` where given."""
    clock, used = time.perf_counter(), time.process_time()
    result = function(*args)
    if cpu is not None:
        cpu.append(time.process_time() - used)
    return time.perf_counter() - clock, result


def paired(shapes: list[np.ndarray], weights: np.ndarray, faces: np.ndarray, baseline,
           pairs: int) -> tuple[dict[str, list[float]], object]:
    """Wall and CPU seconds of ``pairs`` sequences by this solver (``ours``, ``ours_cpu``)
    and by ``baseline``'s ``blend`` (``theirs``, ``theirs_cpu``), alternating which goes
    first, and this solver's first result."""
    times: dict[str, list[float]] = {k: [] for k in ("ours", "theirs", "ours_cpu",
                                                      "theirs_cpu")}
    result = None
    for k in range(pairs):
        order = [("ours", blend), ("theirs", baseline.blend)]
        for key, function in order if k % 2 == 0 else order[::-1]:
            seconds, out = timed(function, shapes, weights, faces, cpu=times[f"{key}_cpu"])
            times[key].append(seconds)
            if function is blend and result is None:
                result = out
    return times, result


def measure(name: str, rows: int, independent: int, baseline=None, pairs: int = 1) -> dict:
    V, F = load_bench_mesh(name)
    load_before = os.getloadavg()[0]
    reference = reference_seconds()
    pose_seconds, P = timed(bent_pose, V, F, 0.6)
    t = np.linspace(0.0, 1.0, rows)
    weights = np.stack([1 - t, t], axis=1)
    compared = {}
    if baseline is None:
        sequence_seconds, sequence = timed(blend, [V, P], weights, F)
    else:
        times, sequence = paired([V, P], weights, F, baseline, pairs)
        ours, theirs = times["ours"], times["theirs"]
        sequence_seconds = float(np.median(ours))
        compared = {"baseline_rows_per_second": rows / float(np.median(theirs)),
                    "pair_ratios": [b / a for a, b in zip(ours, theirs, strict=True)],
                    "cpu_ratios": [b / a for a, b in zip(times["ours_cpu"],
                                                         times["theirs_cpu"], strict=True)],
                    **times}
    picked = np.unique(np.linspace(0, rows - 1, min(independent, rows)).round().astype(int))
    clock = time.perf_counter()
    alone = blend([V, P], weights[picked], F, sequence=False)
    alone_seconds = time.perf_counter() - clock
    topology = build_topology(F, len(V))
    ratios, seq_err, ind_err, vtx_err = [], [], [], []
    from solver.shape_space import shape_set

    shapes = shape_set([V, P], F)
    for k, row in zip(picked, alone.vertices, strict=True):
        L, A = shapes.forms(weights[k][None])
        ours = errors(sequence.vertices[k], topology, L[0], A[0])
        theirs = errors(row, topology, L[0], A[0])
        vertex = errors((1 - t[k]) * V + t[k] * P, topology, L[0], A[0])
        seq_err.append(ours)
        ind_err.append(theirs)
        vtx_err.append(vertex)
        if theirs[0] > 1e-12 and theirs[1] > 1e-12:
            ratios.append(max(ours[0] / theirs[0], ours[1] / theirs[1]))
    paths = [r["path"] for r in sequence.reports]
    return {
        "mesh": name, "faces": len(F), "rows": rows, "independent_rows": len(picked),
        "load": [load_before, os.getloadavg()[0]], "reference_seconds": reference,
        "pose_seconds": pose_seconds,
        "sequence_rows_per_second": rows / sequence_seconds,
        "independent_rows_per_second": len(picked) / alone_seconds,
        "factorizations": sum(r["refinement"].get("factorizations", 0)
                              for r in sequence.reports),
        "iterations": float(np.mean([r["refinement"].get("iterations", 0)
                                     for r in sequence.reports])),
        "sequence_rows": paths.count("sequence"),
        "worst_ratio": max(ratios) if ratios else float("nan"),
        "length_error": [float(np.mean([e[0] for e in x])) for x in (seq_err, ind_err,
                                                                     vtx_err)],
        "angle_error": [float(np.mean([e[1] for e in x])) for x in (seq_err, ind_err,
                                                                    vtx_err)],
        **compared,
    }


def table(results: list[dict], command: str, started: str, baseline: str | None = None,
          ) -> str:
    paired_text = "" if baseline is None else (
        f" *Baseline*: the sequence solved by the solver of commit {baseline} in the same "
        "process, alternating with this one (bench/baseline.py); rates are medians, *x* "
        "the median of the pairs' ratios of rates, *CPU seconds x* that of the process's "
        "CPU seconds (every thread's: less sensitive to the other processes' load).")
    lines = [
        SECTION, "",
        f"`{command}` (load averages before the run: {started}; 2 cores shared with "
        "other developers' runs, so the rates are lower bounds of an idle machine's). A "
        "row blend from a mesh to its pose bent by 0.6 rad (tests/helpers/poses.py), t = 0 "
        "... 1. *Sequence*: `solver.blend` (one analysis, each row from its neighbour, "
        "the factor kept); *independent*: `sequence=False` on the rows compared. Errors: "
        "mean |l / L - 1| and mean |angle error| (rad) of each answer against its row's "
        "blended forms, averaged over the rows compared (sequence / independent / vertex "
        "blend); *worst ratio*: the largest of sequence / independent over those rows "
        "(length or angle)." + paired_text, "",
        "| mesh | faces | rows | load before / after | reference s | sequence rows/s | "
        "rows/s x reference s | independent rows/s (rows timed) | speed-up | "
        "factorizations in the sequence | iterations per row | worst ratio | "
        "length error seq / ind / vertex | angle error seq / ind / vertex |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        le, ae = r["length_error"], r["angle_error"]
        lines.append(
            f"| {r['mesh']} | {r['faces']} | {r['rows']} | "
            f"{r['load'][0]:.1f} / {r['load'][1]:.1f} | {r['reference_seconds']:.3f} | "
            f"{r['sequence_rows_per_second']:.1f}{_versus(r)} | "
            f"{r['sequence_rows_per_second'] * r['reference_seconds']:.2f} | "
            f"{r['independent_rows_per_second']:.2f} ({r['independent_rows']}) | "
            f"{r['sequence_rows_per_second'] / r['independent_rows_per_second']:.1f}x | "
            f"{r['factorizations']} | {r['iterations']:.1f} | {r['worst_ratio']:.3f} | "
            f"{le[0]:.2e} / {le[1]:.2e} / {le[2]:.2e} | "
            f"{ae[0]:.2e} / {ae[1]:.2e} / {ae[2]:.2e} |")
    return "\n".join(lines) + "\n"


def _versus(result: dict) -> str:
    """`` (baseline B, x R)`` where the result has a paired baseline, else empty."""
    if "baseline_rows_per_second" not in result:
        return ""
    return (f" (baseline {result['baseline_rows_per_second']:.1f}, "
            f"x {float(np.median(result['pair_ratios'])):.2f}; CPU seconds x "
            f"{float(np.median(result['cpu_ratios'])):.2f})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--meshes", nargs="+", default=list(MESHES))
    parser.add_argument("--rows", type=int, default=100)
    parser.add_argument("--independent", type=int, default=100,
                        help="independent rows timed and compared (spread over the rows)")
    parser.add_argument("--baseline", help="a git revision whose solver is timed on the "
                        "same sequences, alternately, in this process")
    parser.add_argument("--pairs", type=int, default=3,
                        help="sequences timed per solver with --baseline")
    parser.add_argument("--write", action="store_true",
                        help="replace the section of bench/README.md")
    args = parser.parse_args()
    command = "python -m bench.shape_space " + " ".join(
        ["--meshes", *args.meshes, "--rows", str(args.rows),
         "--independent", str(args.independent)]
        + ([] if args.baseline is None else ["--baseline", args.baseline,
                                             "--pairs", str(args.pairs)]))
    baseline = None
    if args.baseline is not None:
        from bench.baseline import solver_at

        baseline = solver_at(args.baseline)
    started, results = load_averages(), []
    for name in args.meshes:
        result = measure(name, args.rows, args.independent, baseline, args.pairs)
        print(result, flush=True)
        results.append(result)
    text = table(results, command, started,
                 None if baseline is None else baseline.__name__.removeprefix("solver_"))
    print(text)
    if args.write:
        write_section(REPO / "bench" / "README.md", SECTION, text)


if __name__ == "__main__":
    main()
