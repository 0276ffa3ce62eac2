"""The nearest surface: linear answer vs refined answer vs libigl's ARAP, measured in one run.

Sections (``--sections``, default all):

* ``scale``: every dihedral angle x 0.8 (no surface has these forms). Mean length ratio,
  mean and 95th-percentile relative length error, for the linear answer (Eq. 5), the
  orthonormalized one (Sec. 4) and the refined one (the default).
* ``noise``: dihedral noise N(0, 1e-3) rad. Max vertex distance to the original mesh after
  rigid alignment, in units of its bounding-box diagonal.
* ``interpolate``: t = 0.5 between a mesh and a near-isometric pose of it (the Botsch-Sorkine
  bar twisted and cylinder bent by the refined deformation): mean edge-length change against
  the endpoint's, form-space blend (refined and linear) against linear vertex blending.
* ``deform``: the four Botsch-Sorkine cases, positions + rotation handles: mean relative
  edge-length change, mean dihedral change (rad), their sum and the max length change, for
  libigl ARAP (spokes and rims, 200 iterations), the linear, orthonormalized and refined
  answers.
* ``parameterize``: flipped faces and mean length change against libigl's ARAP
  parameterization (harmonic start, 200 iterations).
* ``drag``: a session's refined drag at ~20K faces against the linear drag and libigl ARAP
  with 10 iterations; every session starts with empty pattern and analysis caches, as one
  on a new mesh does.
* ``weights``: the measurements behind the default angle weights and the uniform weighting.
* ``optimum``: the time section's cases (without ``--large``; with it, nefertiti's noisy
  forms too): how far the default answer stops from the exact optimum of its energy (the
  differentiable reconstruction's Newton polish with the exact Hessian), in units of the
  answer's size.
* ``time``: the default (refined) answer against the linear answer of the same call
  (``refine=False``), both warm (second call on the mesh: analyses cached), medians of
  alternating runs, on noisy and x0.8 forms from 5K faces up (100K with ``--large``) and on
  very irregular meshes (rocker-arm, genus 1, with 30 edges split to 1e-4 of their
  length, and the same with 9 near-zero-area faces; with ``--large`` also stanford-bunny,
  69K faces, the size of issue 19's held-out irregular mesh);
  iterations, factorizations and back-substitutions of the refinement; the scaling
  exponents of both answers (least-squares slope of log time against log faces).

    pip install -e ".[bench]"
    python -m bench.refinement [--sections scale noise ...] [--large]

``--large`` adds the meshes over 50K faces (armadillo, stanford-bunny, bumpy-plane, nefertiti).
Meshes come from ../shared/meshes. Times are wall-clock seconds on this machine (quote them
with the load: ``uptime``).
"""

from __future__ import annotations

import argparse
import gc
import os
import sys
import time

import numpy as np

import solver
from bench.common import SHARED_MESHES, load_bench_mesh, scaling_exponent
from solver.linalg import clear_analysis_cache
from solver.mesh.metrics import distortion
from solver.mesh.topology import build_topology
from solver.refine import clear_pattern_cache
from tests.helpers.botsch_sorkine import load_case
from tests.helpers.libigl_reference import arap_deformation, arap_parameterization, flipped_faces
from tests.helpers.meshes import (
    rigid_alignment_error,
    with_cap_faces,
    with_noisy_angles,
    with_tiny_edges,
)

SCALE_MESHES = ["decimated-knight.off", "bunny.off", "face.off", "rocker-arm.obj", "beetle.off"]
NOISE_MESHES = ["decimated-knight.off", "torus.off", "bunny.off", "face.off",
                "octopus-low-surface.off", "rocker-arm.obj", "beetle.off", "cactus.off"]
LARGE = ["armadillo.obj", "stanford-bunny.obj"]
DEFORM_CASES = ["bar", "cylinder", "cactus", "bumpy-plane"]
PARAM_MESHES = ["face.off", "beetle.off", "bumpy-plane.off"]


def timed(fn, *args, **kw):
    t0 = time.perf_counter()
    out = fn(*args, **kw)
    return out, time.perf_counter() - t0


def ratios(X: np.ndarray, forms) -> np.ndarray:
    return np.linalg.norm(X[forms.edges[:, 1]] - X[forms.edges[:, 0]], axis=1) / forms.lengths


def table_head(title: str, header: str) -> None:
    """Print a section's ``### title`` and the head of its markdown table."""
    print(f"\n### {title}\n")
    print(header)
    print("|" + "---|" * (header.count("|") - 1))


def shared_forms(name: str):
    """(vertices, faces, forms) of the shared mesh ``name``."""
    V, F = load_bench_mesh(name)
    return V, F, solver.fundamental_forms(V, F)


def reconstruct(forms, **kw):
    return solver.reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles,
                              check_integrability=False, **kw)


def scale_section(meshes: list[str]) -> None:
    """Every dihedral angle x 0.8: length ratios of the linear, orthonormalized and refined
    answers."""
    table_head("Angles x 0.8",
               "| mesh | faces | answer | mean l/L | mean abs(l/L - 1) | p95 | iterations | s |")
    for name in meshes:
        _, F, forms = shared_forms(name)
        forms.angles *= 0.8
        for label, kw in (("linear", {"refine": False}),
                          ("orthonormalized", {"refine": False, "orthonormalize": True}),
                          ("refined (default)", {})):
            rec, seconds = timed(reconstruct, forms, **kw)
            r = ratios(rec.vertices, forms)
            it = rec.report["refinement"].get("iterations", "")
            print(f"| {name} | {len(F)} | {label} | {r.mean():.4f} | {np.abs(r - 1).mean():.4f}"
                  f" | {np.percentile(np.abs(r - 1), 95):.4f} | {it} | {seconds:.2f} |")


def noise_section(meshes: list[str]) -> None:
    """Dihedral noise N(0, 1e-3) rad: distance of each answer to the original mesh."""
    table_head("Dihedral noise N(0, 1e-3) rad: distance to the original / bbox diagonal",
               "| mesh | faces | genus | linear | orthonormalized | refined (default) "
               "| iterations | refine s | total s |")
    for name in meshes:
        V, F, forms = shared_forms(name)
        forms = with_noisy_angles(forms)
        linear = reconstruct(forms, refine=False)
        ortho = reconstruct(forms, refine=False, orthonormalize=True)
        refined, seconds = timed(reconstruct, forms)
        rep = refined.report
        genus = rep.get("integrability", {}).get("genus", "")
        genus = solver.check_integrability(forms.faces, forms.edges, forms.lengths,
                                           forms.angles).genus if genus == "" else genus
        print(f"| {name} | {len(F)} | {genus} | {rigid_alignment_error(linear.vertices, V):.2e}"
              f" | {rigid_alignment_error(ortho.vertices, V):.2e}"
              f" | {rigid_alignment_error(refined.vertices, V):.2e}"
              f" | {rep['refinement'].get('iterations')} | {rep['timings'].get('refine', 0):.2f}"
              f" | {seconds:.2f} |")


def case_kwargs(case) -> dict:
    return {"rotation_handles": [case.handle_faces()],
            "handle_rotations": case.transform[None, :3, :3], "roi": case.roi}


def deform_section(cases: list[str]) -> None:
    """The Botsch-Sorkine cases, positions + rotation handles, against libigl ARAP."""
    table_head("Botsch-Sorkine cases, positions + rotation handles",
               "| case | faces | method | mean length change | mean dihedral change (rad) "
               "| sum | max length change | iterations | s |")
    for name in cases:
        case = load_case(SHARED_MESHES, name)
        runs = []
        try:
            for iterations in (10, 200):
                out, seconds = timed(arap_deformation, case, iterations)
                runs.append((f"libigl ARAP ({iterations} it.)", out, str(iterations), seconds))
        except ImportError:
            print(f"| {name} | | libigl ARAP | not installed (pip install libigl) | | | | | |")
        for label, kw in (("linear", {"refine": False}),
                          ("orthonormalized", {"refine": False, "orthonormalize": True}),
                          ("refined (default)", {})):
            res, seconds = timed(solver.deform, case.vertices, case.faces, case.handles,
                                 case.handle_targets(), **case_kwargs(case), **kw)
            rep = res.report["refinement"]
            counts = (f"{rep['iterations']} ({rep['factorizations']} f., {rep['solves']} s.)"
                      if "iterations" in rep else "")
            runs.append((label, res.vertices, counts, seconds))
        for label, X, it, seconds in runs:
            d = distortion(case.vertices, X, case.faces)
            length, angle = d["length_summary"]["mean"], d["angle_summary"]["mean"]
            print(f"| {name} | {len(case.faces)} | {label} | {length:.4f} | {angle:.4f} | "
                  f"{length + angle:.4f} | {d['length_summary']['max']:.3f} | {it} | "
                  f"{seconds:.2f} |")


def interpolate_section(cases: list[str]) -> None:
    """t = 0.5 between a mesh and a near-isometric pose of it: form space against vertex
    blending."""
    table_head("Interpolation at t = 0.5 between a mesh and a near-isometric pose of it",
               "| case | endpoint mean length change | form space, refined (default) "
               "| form space, linear | vertex blend | s (refined) |")
    for name in cases:
        case = load_case(SHARED_MESHES, name)
        pose = solver.deform(case.vertices, case.faces, case.handles, case.handle_targets(),
                             **case_kwargs(case)).vertices
        rest = solver.fundamental_forms(case.vertices, case.faces)

        def change(X, rest=rest):
            return np.abs(ratios(X, rest) - 1).mean()

        refined, seconds = timed(solver.interpolate, case.vertices, pose, case.faces, 0.5)
        linear = solver.interpolate(case.vertices, pose, case.faces, 0.5, refine=False)
        print(f"| {name} | {change(pose):.4f} | {change(refined):.4f} | {change(linear):.4f} |"
              f" {change(0.5 * (case.vertices + pose)):.4f} | {seconds:.2f} |")


def parameterize_section(meshes: list[str]) -> None:
    """Flattening against libigl's ARAP parameterization."""
    table_head("Parameterization (flattening)",
               "| mesh | faces | method | flipped faces | mean length change | iterations | s |")
    for name in meshes:
        V, F, forms = shared_forms(name)
        try:
            uv, seconds = timed(arap_parameterization, V, F)
            flips = flipped_faces(uv, F)
            print(f"| {name} | {len(F)} | libigl ARAP (200 it.) | {flips} | "
                  f"{np.abs(ratios(uv, forms) - 1).mean():.4f} | | {seconds:.2f} |")
        except ImportError:
            print(f"| {name} | {len(F)} | libigl ARAP | not installed | | | |")
        for label, kw in (("linear (orthonormalized)", {"refine": False}),
                          ("refined (default)", {})):
            p, seconds = timed(solver.parameterize, V, F, **kw)
            r = p.report
            print(f"| {name} | {len(F)} | {label} | {r['flipped_count']} | "
                  f"{r['length_change_summary']['mean']:.4f} | "
                  f"{r['refinement'].get('iterations', '')} | {seconds:.2f} |")


def drag_section() -> None:
    """A session's drags at ~20K faces: linear, refined, refined with a frame budget (among
    them ARAP-10's per-drag time in this run) and libigl ARAP-10."""
    print("\n### Interactive drags at ~20K faces (rocker-arm, 3 handle patches)\n")
    V, F = load_bench_mesh("rocker-arm.obj")
    rng = np.random.default_rng(0)
    centres = V[rng.choice(len(V), 3, replace=False)]
    near = [np.flatnonzero(np.linalg.norm(V - c, axis=1) < 0.05 * np.ptp(V)) for c in centres]
    handles = np.unique(np.concatenate(near))
    moves = [V[handles] + 0.02 * np.ptp(V) * k * np.array([0.0, 0.0, 1.0]) *
             (np.isin(handles, near[0]))[:, None] for k in range(1, 6)]
    print("| method | set-up s | median drag ms | mean length change (last drag) "
          "| factorizations / iterations per drag |")
    print("|---|---|---|---|---|")
    rest = solver.fundamental_forms(V, F)
    arap = None
    try:
        import igl

        data = igl.ARAPData()
        data.max_iter = 10
        _, setup = timed(igl.arap_precomputation, V, F, 3, handles.astype(np.int64), data)
        U, times = V.copy(), []
        for P in moves:
            U, seconds = timed(igl.arap_solve, P, data, U)
            times.append(seconds)
        arap = float(np.median(times))
        print(f"| libigl ARAP, 10 iterations | {setup:.2f} | {1000 * arap:.0f} | "
              f"{np.abs(ratios(U, rest) - 1).mean():.4f} | |")
    except ImportError:
        print("| libigl ARAP | not installed | | | |")
    for label, refine in (("linear drag", False), ("refined drag", True)):
        cold_caches()
        deformer, setup = timed(solver.Deformer, V, F, handles, refine=refine)
        times, out, factorizations = [], V, []
        for P in moves:
            out, seconds = timed(deformer.solve, P)
            times.append(seconds)
            report = deformer.last_report
            factorizations.append(f"{report.get('factorizations', '')}/"
                                  f"{report.get('iterations', '')}")
        counts = ", ".join(map(str, factorizations)) if refine else ""
        print(f"| {label} | {setup:.2f} | {1000 * float(np.median(times)):.0f} | "
              f"{np.abs(ratios(out, rest) - 1).mean():.4f} | {counts} |")
    print("\nRefined drags with a frame budget (`Deformer.solve(P, max_seconds=b)`; the first "
          "row's b is ARAP-10's median drag above), then one `refine_last()` for the pause "
          "after the last drag:\n")
    print("| budget b s | drags ms | median drag ms | mean length change, last drag "
          "| after the pause |")
    print("|---|---|---|---|---|")
    for budget in ([round(arap, 3)] if arap else []) + [0.06, 0.1]:
        cold_caches()
        deformer, times = solver.Deformer(V, F, handles, refine=True), []
        for P in moves:
            out, seconds = timed(deformer.solve, P, max_seconds=budget)
            times.append(seconds)
        stop = deformer.last_report.get("stop_reason")
        settled, pause = timed(deformer.refine_last)
        r = deformer.last_report
        print(f"| {budget} | {', '.join(f'{1000 * t:.0f}' for t in times)} | "
              f"{1000 * float(np.median(times)):.0f} | "
              f"{np.abs(ratios(out, rest) - 1).mean():.4f} ({stop}) | "
              f"{np.abs(ratios(settled, rest) - 1).mean():.4f} in {1000 * pause:.0f} ms "
              f"({r.get('stop_reason')}, {r.get('iterations')} iterations) |")


def cold_caches() -> None:
    """Forget the Gauss-Newton patterns and PARDISO analyses, as a new session on a mesh
    the process has not seen finds them (the drag section's sessions start this way)."""
    gc.collect()
    clear_pattern_cache()
    clear_analysis_cache()


TIME_MESHES = ["bunny.off", "cactus.off", "rocker-arm.obj", "beetle.off"]
TIME_LARGE = ["stanford-bunny.obj", "armadillo.obj", "nefertiti.obj"]


def warm_pair(forms, repeats: int = 3) -> tuple[float, float, object]:
    """Median seconds of the linear and of the default answer (``solver.reconstruct`` with
    its defaults), alternating after one untimed call of each; and the default result."""
    def call(**kw):
        return solver.reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles, **kw)

    call(refine=False)
    call()
    linear, default = [], []
    for _ in range(repeats):
        linear.append(timed(call, refine=False)[1])
        result, seconds = timed(call)
        default.append(seconds)
    return float(np.median(linear)), float(np.median(default)), result


def time_case_forms(name: str, kind: str):
    """(vertices, forms) of a case of the time section: ``"noise"`` (N(0, 1e-3) rad on the
    angles), ``"x0.8"`` (every angle x 0.8), ``"irregular"`` (30 edges split to 1e-4 of
    their length, then noise) or ``"irregular + caps"`` (the same after 9 faces were
    flattened to 1e-6 of their width, like the held-out mesh of issue 19 with its zero-area
    faces)."""
    V, F = load_bench_mesh(name)
    if kind == "irregular + caps":
        V = with_cap_faces(V, F, 10)
    if kind.startswith("irregular"):
        V, F = with_tiny_edges(V, F, 30)
    forms = solver.fundamental_forms(V, F)
    if kind == "x0.8":
        forms.angles *= 0.8
        return V, forms
    return V, with_noisy_angles(forms)


def time_section(meshes: list[str], irregular: list[str] | None = None) -> None:
    """The default (refined) answer against the linear one, both warm: noisy and x 0.8
    forms on ``meshes``, irregular ones on ``irregular`` (default: rocker-arm, and
    stanford-bunny too where ``meshes`` has it: the held-out irregular mesh of issue 19 has
    69K faces)."""
    table_head("Time: the default (refined) answer against the linear one, warm",
               "| case | faces | linear s | default s | ratio | iterations | factorizations "
               "| solves | converged | quality |")
    sizes, linear_times, default_times = [], [], []
    cases = [(name, kind) for name in meshes for kind in ("noise", "x0.8")]
    if irregular is None:
        irregular = ["rocker-arm.obj"] + [m for m in meshes if m == "stanford-bunny.obj"]
    cases += [(name, kind) for name in irregular for kind in ("irregular", "irregular + caps")]
    for name, kind in cases:
        V, forms = time_case_forms(name, kind)
        F = forms.faces
        linear, default, result = warm_pair(forms)
        rep = result.report["refinement"]
        if kind == "x0.8":
            quality = f"mean abs(l/L - 1) {np.abs(ratios(result.vertices, forms) - 1).mean():.4f}"
        else:
            quality = f"distance {rigid_alignment_error(result.vertices, V):.1e}"
        if kind == "noise":
            sizes.append(len(F))
            linear_times.append(linear)
            default_times.append(default)
        print(f"| {name} {kind} | {len(F)} | {linear:.3f} | {default:.3f} | "
              f"{default / linear:.2f} | {rep.get('iterations', '')} | "
              f"{rep.get('factorizations', '')} | {rep.get('solves', '')} | "
              f"{rep.get('converged', '')} | {quality} |")
        sys.stdout.flush()
    if len(sizes) > 1:
        print(f"\nScaling exponents (noise rows): linear "
              f"{scaling_exponent(sizes, linear_times):.2f}, default (refined) "
              f"{scaling_exponent(sizes, default_times):.2f}")


def optimum_section(meshes: list[str], large: bool = False) -> None:
    """How far the default answer stops from the exact optimum of its energy; ``large``
    adds nefertiti's noisy forms (100K faces; the case of ``REFUSED_PREDICTION``)."""
    from solver.differentiable import reconstruct_vjp

    table_head("Distance of the default answer to the exact optimum / size",
               "| case | faces | iterations | factorizations | distance to the optimum |")
    cases = [(name, kind) for name in meshes for kind in ("noise", "x0.8")]
    cases.append(("rocker-arm.obj", "irregular"))
    if large:
        cases.append(("nefertiti.obj", "noise"))
    for name, kind in cases:
        forms = time_case_forms(name, kind)[1]
        args = (forms.faces, forms.edges, forms.lengths, forms.angles)
        result = solver.reconstruct(*args)
        optimum, vjp = reconstruct_vjp(*args)  # Newton with the exact Hessian from there
        rep = result.report["refinement"]
        size = np.ptp(result.vertices, axis=0).max()
        distance = np.abs(optimum.vertices - result.vertices).max() / size
        polished = "" if vjp.report["polish_converged"] else " (polish not converged)"
        print(f"| {name} {kind} | {len(forms.faces)} | {rep.get('iterations', '')} | "
              f"{rep.get('factorizations', '')} | {distance:.1e}{polished} |")
        sys.stdout.flush()


def weights_section() -> None:
    """The measurements behind the default weights (docs/refinement.md, "Weights")."""
    from solver.refine import FormTargets, Refiner

    table_head("Angle weight beta, prescribed forms: noise N(0, 1e-3), distance / diagonal",
               "| mesh | beta = 0.05 | 0.005 (default) | 0.0005 |")
    for name in ("octopus-low-surface.off", "face.off", "torus.off"):
        V, _, forms = shared_forms(name)
        forms = with_noisy_angles(forms, seed=5)
        cells = [f"{rigid_alignment_error(reconstruct(forms, angle_weight=b).vertices, V):.2e}"
                 for b in (0.05, 0.005, 0.0005)]
        print(f"| {name} | " + " | ".join(cells) + " |")
    table_head("Angle weight beta and weighting, deformation: bar, positions + rotations",
               "| beta | weighting | mean length + mean dihedral change | max length change |")
    case = load_case(SHARED_MESHES, "bar")
    start = solver.deform(case.vertices, case.faces, case.handles, case.handle_targets(),
                          orthonormalize=True, refine=False, **case_kwargs(case)).vertices
    topology = build_topology(case.faces, len(case.vertices))
    rest = solver.fundamental_forms(case.vertices, case.faces)
    fixed = np.concatenate([case.fixed, case.handles])
    from solver.refine import Handles

    for beta, weighting in ((0.03, "uniform"), (0.1, "uniform"), (0.3, "uniform"),
                            (0.3, "area")):
        refiner = Refiner(FormTargets(topology, rest.lengths, rest.angles, angle_weight=beta,
                                      weighting=weighting), Handles(fixed=fixed))
        d = distortion(case.vertices, refiner.run(start).vertices, case.faces)
        print(f"| {beta} | {weighting} | "
              f"{d['length_summary']['mean'] + d['angle_summary']['mean']:.4f} | "
              f"{d['length_summary']['max']:.3f} |")


SECTIONS = ("scale", "noise", "interpolate", "deform", "parameterize", "drag", "weights",
            "time", "optimum")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sections", nargs="+", choices=SECTIONS, default=list(SECTIONS))
    parser.add_argument("--large", action="store_true", help="add meshes over 50K faces")
    args = parser.parse_args()
    print(f"load average {os.getloadavg()[0]:.1f}; backend {solver.linalg.default_backend()}")
    noise = NOISE_MESHES + (LARGE if args.large else [])
    scale = SCALE_MESHES + (LARGE if args.large else [])
    deform_cases = DEFORM_CASES if args.large else DEFORM_CASES[:3]
    param = PARAM_MESHES if args.large else PARAM_MESHES[:2]
    run = {"scale": lambda: scale_section(scale), "noise": lambda: noise_section(noise),
           "interpolate": lambda: interpolate_section(["bar", "cylinder"]),
           "deform": lambda: deform_section(deform_cases),
           "parameterize": lambda: parameterize_section(param), "drag": drag_section,
           "weights": weights_section,
           "time": lambda: time_section(TIME_MESHES + (TIME_LARGE if args.large else [])),
           "optimum": lambda: optimum_section(TIME_MESHES, args.large)}
    for section in args.sections:
        run[section]()
        sys.stdout.flush()


if __name__ == "__main__":
    main()
