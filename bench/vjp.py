"""Differentiable reconstruction: the cost of a VJP against the reconstruct that produced
it, and the worked inverse-design example (docs/differentiable.md).

    python -m bench.vjp                       # timings on the shared meshes, then the example
    python -m bench.vjp --meshes bunny.off --no-example
    python -m bench.vjp --example-only --plot loss.png

Per mesh and answer (linear: ``refine=False``; refined: the default), in one run, with
noisy angles (0.01 rad; the linear answer then needs its factorization and the refined one
its Gauss-Newton iterations): the median of ``--repeats`` runs of ``reconstruct``, of
``reconstruct_vjp``'s own preparation (the factorization it keeps, and for the refined
answer the Newton polishing), of one VJP call and of one call with 3 cotangents; and what a
finite-difference gradient would cost (2 E reconstructs for central differences).
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

import solver
from bench.common import load_bench_mesh
from solver.differentiable import aligned_distance, reconstruct_vjp
from tests.helpers.meshes import grid

MESHES = ("bunny.off", "cactus.off", "rocker-arm.obj", "bumpy-plane.off", "armadillo.obj")


def noisy_forms(name: str, seed: int = 0) -> solver.Forms:
    forms = solver.fundamental_forms(*load_bench_mesh(name))
    rng = np.random.default_rng(seed)
    angles = np.clip(forms.angles + 0.01 * rng.standard_normal(len(forms.angles)),
                     -np.pi + 1e-9, np.pi)
    return solver.Forms(forms.faces, forms.edges, forms.lengths, angles)


def seconds(function) -> tuple[float, object]:
    start = time.perf_counter()
    out = function()
    return time.perf_counter() - start, out


def time_mesh(name: str, repeats: int) -> list[dict]:
    forms = noisy_forms(name)
    rows = []
    for refine, label in ((False, "linear"), (None, "refined")):
        times: dict[str, list[float]] = {"reconstruct": [], "prepare": [], "vjp1": [],
                                         "vjp3": []}
        rng = np.random.default_rng(1)
        for _ in range(repeats):   # alternated in one run: the machine is shared
            t, _ = seconds(lambda r=refine: solver.reconstruct(
                forms.faces, forms.edges, forms.lengths, forms.angles, refine=r))
            times["reconstruct"].append(t)
            _, (result, vjp) = seconds(lambda r=refine: reconstruct_vjp(
                forms.faces, forms.edges, forms.lengths, forms.angles, refine=r))
            times["prepare"].append(vjp.report["seconds"])
            G = rng.standard_normal((3, *result.vertices.shape))
            times["vjp1"].append(seconds(lambda v=vjp, g=G: v(g[0]))[0])
            times["vjp3"].append(seconds(lambda v=vjp, g=G: v(g))[0])
        median = {k: statistics.median(v) for k, v in times.items()}
        row = {"mesh": name, "faces": len(forms.faces), "answer": label, **median,
               "fd_gradient": 2 * len(forms.lengths) * median["reconstruct"],
               "report": {k: v for k, v in vjp.report.items() if k != "seconds"}}
        rows.append(row)
        r = median["reconstruct"]
        print(f"| {name} | {row['faces']} | {label} | {r:.2f} | {median['prepare']:.2f} "
              f"({median['prepare'] / r:.2f}x) | {median['vjp1']:.3f} "
              f"({median['vjp1'] / r:.2f}x) | {median['vjp3']:.3f} ({median['vjp3'] / r:.2f}x) "
              f"| {row['fd_gradient']:.3g} | {row['report']} |", flush=True)
    return rows


def inverse_design(n: int = 16, radius: float = 0.5, iterations: int = 300,
                   plot: str | None = None) -> dict:
    """Find the dihedral angles (lengths kept) whose reconstruction is a flat sheet bent
    around a cylinder: gradient descent with backtracking from all angles 0."""
    V, F = grid(n, n)
    target = np.stack([radius * np.sin(V[:, 0] / radius), V[:, 1],
                       radius * (1 - np.cos(V[:, 0] / radius))], axis=1)
    forms = solver.fundamental_forms(target, F)
    angles = np.zeros_like(forms.angles)
    step, history, gradient_seconds, reconstruct_seconds = 1.0, [], [], []
    for _ in range(iterations):
        t, (result, vjp) = seconds(lambda a=angles: reconstruct_vjp(
            forms.faces, forms.edges, forms.lengths, a))
        loss, g = aligned_distance(result.vertices, target)
        history.append(loss)
        if loss <= history[0] * 1e-4:
            break
        t_vjp, (_, grad) = seconds(lambda v=vjp, c=g: v(c))
        gradient_seconds.append(t + t_vjp)
        while step > 1e-10:
            trial = np.clip(angles - step * grad, -np.pi + 1e-9, np.pi)
            t_r, moved = seconds(lambda a=trial: solver.reconstruct(
                forms.faces, forms.edges, forms.lengths, a))
            reconstruct_seconds.append(t_r)
            if aligned_distance(moved.vertices, target)[0] < loss:
                break
            step *= 0.5
        angles, step = trial, step * 1.5
    summary = {"faces": len(F), "edges": len(forms.edges), "iterations": len(history),
               "loss_first": history[0], "loss_last": history[-1],
               "reduction": history[0] / history[-1],
               "gradient_seconds": statistics.median(gradient_seconds),
               "reconstruct_seconds": statistics.median(reconstruct_seconds),
               "fd_gradient_seconds": 2 * len(forms.edges)
               * statistics.median(reconstruct_seconds)}
    print(summary)
    if plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(5, 3.2), dpi=100)
        ax.semilogy(history)
        ax.set_xlabel("iteration")
        ax.set_ylabel("aligned distance to the target")
        ax.set_title(f"inverse design: a {len(F)}-face sheet bent by its angles")
        fig.tight_layout()
        fig.savefig(plot)
        print(f"wrote {plot}")
    return summary


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", nargs="*", default=list(MESHES))
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-example", action="store_true")
    parser.add_argument("--example-only", action="store_true")
    parser.add_argument("--plot", default=None, help="PNG of the example's loss curve")
    args = parser.parse_args()
    if not args.example_only:
        print("| mesh | faces | answer | reconstruct s | prepare s | 1 VJP s | 3 VJPs s | "
              "FD gradient s (2E reconstructs) | vjp report |")
        print("|---|---|---|---|---|---|---|---|---|")
        for name in args.meshes:
            time_mesh(name, args.repeats)
    if not args.no_example:
        inverse_design(plot=args.plot)


if __name__ == "__main__":
    main()
