"""Families of meshes that are hard by their structure, not their size, at growing sizes:
many fins on one edge, many cones on one apex, one vertex of huge valence, many separate
quads, and a triangle soup. Each case runs in a fresh child; the seconds of forms, the
exact and noisy round trips, a deformation and an atlas (issue 40's operations), so that
a cost growing faster than the faces shows as a ratio between sizes.

    python -m bench.many_parts --markdown
    python -m bench.many_parts --families cone --sizes 500 2000 8000

A case that takes longer than ``--timeout`` seconds reports ``timeout``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from collections.abc import Callable

import numpy as np


def fins(k: int) -> tuple[np.ndarray, np.ndarray]:
    """``k`` triangles on one edge (a non-manifold edge of ``k`` faces)."""
    turn = np.linspace(0, 2 * np.pi, k, endpoint=False)
    V = np.vstack([[0, 0, 0], [0, 0, 1],
                   np.stack([np.cos(turn), np.sin(turn), np.full(k, 0.5)], axis=1)])
    return V, np.stack([np.zeros(k, int), np.ones(k, int), 2 + np.arange(k)], axis=1)


def urchin(k: int) -> tuple[np.ndarray, np.ndarray]:
    """``k`` open four-sided cones on one apex (a non-manifold vertex of ``k`` fans)."""
    rng = np.random.default_rng(0)
    axis = rng.normal(size=(k, 3))
    axis /= np.linalg.norm(axis, axis=1)[:, None]
    u = np.cross(axis, [0.3, 0.5, 0.8])
    u /= np.linalg.norm(u, axis=1)[:, None]
    w = np.cross(axis, u)
    turn = np.arange(4) * np.pi / 2
    rim = (2 * axis[:, None] + 0.3 * (np.cos(turn)[None, :, None] * u[:, None]
                                      + np.sin(turn)[None, :, None] * w[:, None]))
    V = np.vstack([[0, 0, 0], rim.reshape(-1, 3)])
    base = 1 + 4 * np.arange(k)[:, None]
    t = np.arange(4)[None, :]
    F = np.stack([np.zeros((k, 4), int), base + t, base + (t + 1) % 4], axis=-1)
    return V, F.reshape(-1, 3)


def cone(k: int) -> tuple[np.ndarray, np.ndarray]:
    """A closed cone of ``k`` sides: two vertices of valence ``k`` (manifold)."""
    turn = np.linspace(0, 2 * np.pi, k, endpoint=False)
    V = np.vstack([[0, 0, 1], [0, 0, 0], np.stack([np.cos(turn), np.sin(turn), 0 * turn], 1)])
    i, j = 2 + np.arange(k), 2 + (np.arange(k) + 1) % k
    return V, np.vstack([np.stack([np.zeros(k, int), i, j], 1),
                         np.stack([np.ones(k, int), j, i], 1)])


def quads(k: int) -> tuple[np.ndarray, np.ndarray]:
    """``k`` separate non-planar quads (two faces each)."""
    corner = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0.1], [0, 1, 0]], dtype=float)
    V = (corner[None] + np.stack([2.0 * np.arange(k), np.zeros(k), np.zeros(k)], 1)[:, None])
    o = 4 * np.arange(k)
    return V.reshape(-1, 3), np.concatenate([np.stack([o, o + 1, o + 2], 1),
                                             np.stack([o, o + 2, o + 3], 1)])


def soup(k: int) -> tuple[np.ndarray, np.ndarray]:
    """``k`` faces of an icosphere, each on its own three vertices."""
    from tests.helpers.meshes import icosphere

    level = 1
    while 20 * 4 ** level < k:
        level += 1
    V, F = icosphere(level)
    F = F[:k]
    return V[F].reshape(-1, 3), np.arange(3 * len(F)).reshape(-1, 3)


FAMILIES: dict[str, Callable[[int], tuple[np.ndarray, np.ndarray]]] = {
    "fins": fins, "urchin": urchin, "cone": cone, "quads": quads, "soup": soup}


def run_case(family: str, k: int) -> dict[str, object]:
    """Every operation on one case (in this process)."""
    import solver

    V, F = FAMILIES[family](k)
    rng = np.random.default_rng(1)
    seconds: dict[str, float | str] = {}

    def timed(name: str, call: Callable[[], object]) -> object:
        start = time.perf_counter()
        try:
            out = call()
        except Exception as err:  # a row says what failed, the others still run
            seconds[name] = f"{type(err).__name__}"
            return None
        seconds[name] = round(time.perf_counter() - start, 2)
        return out

    forms = timed("forms", lambda: solver.fundamental_forms(V, F))
    if forms is not None:
        def rebuild(angles: np.ndarray) -> object:
            return solver.reconstruct(forms.faces, forms.edges, forms.lengths, angles,
                                      vertex_map=forms.vertex_map, placement=forms.placement,
                                      weld_map=forms.weld_map, n_vertices=len(V))

        timed("exact", lambda: rebuild(forms.angles))
        noise = rng.normal(0, 1e-3, len(forms.angles)) * (forms.angles != 0)
        timed("noisy", lambda: rebuild(forms.angles + noise))
    ends = np.array([0, len(V) - 1])
    timed("deform", lambda: solver.deform(V, F, ends, V[ends] + [[0, 0, 0], [0.1, 0, 0]]))
    timed("flatten", lambda: solver.parameterize(V, F))
    return {"family": family, "k": k, "faces": len(F), "seconds": seconds}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--families", nargs="+", default=list(FAMILIES), choices=FAMILIES)
    parser.add_argument("--sizes", nargs="+", type=int, default=[500, 2000, 8000])
    parser.add_argument("--timeout", type=float, default=600.0)
    parser.add_argument("--markdown", action="store_true")
    parser.add_argument("--case", nargs=2, help=argparse.SUPPRESS)    # the child's entry
    args = parser.parse_args(argv)
    if args.case:
        print(json.dumps(run_case(args.case[0], int(args.case[1]))))
        return
    operations = ["forms", "exact", "noisy", "deform", "flatten"]
    if args.markdown:
        print("| family | k | faces | " + " | ".join(f"{op} s" for op in operations) + " |")
        print("|---|---:|---:|" + "---:|" * len(operations))
    for family in args.families:
        for k in args.sizes:
            try:
                child = subprocess.run([sys.executable, "-m", "bench.many_parts", "--case",
                                        family, str(k)], capture_output=True, text=True,
                                       timeout=args.timeout, check=True)
                row = json.loads(child.stdout.strip().splitlines()[-1])
                cells = [str(row["seconds"].get(op, "-")) for op in operations]
                faces = row["faces"]
            except subprocess.TimeoutExpired:
                cells, faces = ["timeout"] * len(operations), "-"
            if args.markdown:
                print(f"| {family} | {k} | {faces} | " + " | ".join(cells) + " |", flush=True)
            else:
                print(family, k, faces, dict(zip(operations, cells, strict=True)), flush=True)


if __name__ == "__main__":
    main()
