"""What several benchmark scripts share: where the meshes are, how a benchmark mesh, its
handles and its drags are made, the machine's load, a markdown table and a markdown section
rewritten in place, and the command line of the scripts that time a few meshes over rounds.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
"""The repository's root folder."""
SHARED_MESHES = REPO.parent / "shared" / "meshes"
"""The larger meshes beside the repository (../shared/meshes; absent in a bare clone)."""
SESSION_MESH = SHARED_MESHES / "rocker-arm.obj"
"""The ~20K-face mesh of the service and session benchmarks (20 088 faces)."""


def load_bench_mesh(name: str) -> tuple[np.ndarray, np.ndarray]:
    """Read a benchmark mesh with trimesh, in file order.

    Args:
        name: a file name in ../shared/meshes, or ``icosphere:N`` (trimesh's icosphere with
            ``N`` subdivisions, 20 * 4**N faces; ``icosphere`` alone is ``icosphere:5``).

    Returns:
        (vertices (n, 3) float64, faces (m, 3) int64).
    """
    import trimesh

    if name == "icosphere" or name.startswith("icosphere:"):
        subdivisions = int(name.partition(":")[2] or 5)
        mesh = trimesh.creation.icosphere(subdivisions=subdivisions)
    else:
        mesh = trimesh.load(SHARED_MESHES / name, process=False)
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


def session_mesh() -> tuple[str, np.ndarray, np.ndarray]:
    """The ~20K-face mesh of the service and session benchmarks: rocker-arm.obj read by the
    solver's reader, or ``icosphere(5)`` (20 480 faces) where the shared meshes are absent.

    Returns:
        (its name, vertices (n, 3) float64, faces (m, 3) int64).
    """
    if SESSION_MESH.exists():
        from solver.mesh.io import load_mesh_file

        V, F = load_mesh_file(SESSION_MESH)
        return SESSION_MESH.name, V, F
    return ("icosphere(5)", *load_bench_mesh("icosphere:5"))


def two_handle_regions(V: np.ndarray) -> np.ndarray:
    """Handle vertices: the 2 % of ``V`` (n, 3) lowest and the 2 % highest along its longest
    axis (at least 4 each), lowest first. Returns (h,) int64."""
    order = np.argsort(V[:, int(np.argmax(np.ptp(V, axis=0)))])
    k = max(len(V) // 50, 4)
    return np.concatenate([order[:k], order[-k:]])


def random_drags(V: np.ndarray, handles: np.ndarray, count: int,
                 seed: int = 0) -> list[np.ndarray]:
    """``count`` handle targets (h, 3) float64: the upper half of ``handles`` (see
    :func:`two_handle_regions`) translated by a random vector of 10 % of the bounding-box
    diagonal, the lower half where it is."""
    rng = np.random.default_rng(seed)
    scale = 0.1 * np.linalg.norm(np.ptp(V, axis=0))
    top = len(handles) // 2
    out = []
    for _ in range(count):
        P = V[handles].copy()
        P[top:] += rng.normal(scale=scale, size=3)
        out.append(P)
    return out


def scaling_exponent(sizes, seconds) -> float:
    """k of ``seconds ~ sizes^k``: the least-squares slope of log time against log size."""
    return float(np.polyfit(np.log(sizes), np.log(seconds), 1)[0])


def markdown_table(columns: Sequence[tuple[str, str]], rows: Iterable[Sequence[Any]]
                   ) -> list[str]:
    """The lines of a markdown table: ``columns`` are (heading, ``"l"`` or ``"r"``
    alignment); each row's cells are written with ``str``, a row shorter than the columns
    (an error row) padded with empty cells.

    Example:
        >>> print("\\n".join(markdown_table([("mesh", "l"), ("faces", "r")],
        ...                                 [["bunny", 1000], ["big: out of memory"]])))
        | mesh | faces |
        |---|---:|
        | bunny | 1000 |
        | big: out of memory | |
    """
    def line(cells: Sequence[str]) -> str:
        return "|" + "|".join(f" {c} " if c else " " for c in cells) + "|"

    out = [line([heading for heading, _ in columns]),
           "|" + "|".join("---:" if align == "r" else "---" for _, align in columns) + "|"]
    for row in rows:
        cells = [str(c) for c in row]
        out.append(line(cells + [""] * (len(columns) - len(cells))))
    return out


def load_averages() -> str:
    """The machine's 1, 5 and 15 minute load averages, e.g. ``"1.02, 0.87, 0.80"`` (the box
    is shared with other runs: a table records the load it was measured under)."""
    return ", ".join(f"{x:.2f}" for x in os.getloadavg())


def write_section(path: Path, heading: str, text: str,
                  title: str = "# Sessions and scale-out benchmarks") -> None:
    """Replace the section of the markdown file ``path`` that starts with ``heading`` (up to
    the next ``## ``) by ``text``; append ``text`` when there is no such section, and start
    the file with ``title`` when it does not exist."""
    old = path.read_text() if path.exists() else title + "\n\n"
    start = old.find(heading)
    if start < 0:
        new = old.rstrip("\n") + "\n\n" + text
    else:
        end = old.find("\n## ", start + len(heading))
        new = old[:start] + text + (old[end + 1:] if end >= 0 else "")
    path.write_text(new.rstrip("\n") + "\n")


def meshes_and_rounds(doc: str, meshes: list[str], rounds: int,
                      name: str = "meshes") -> argparse.Namespace:
    """Parse the command line ``[MESH ...] [--rounds N]`` of a script timing a few meshes
    (default ``meshes``) over ``rounds`` rounds; ``doc`` is the script's docstring (its first
    line describes it) and ``name`` the attribute the mesh names land in."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument(name, nargs="*", default=meshes)
    parser.add_argument("--rounds", type=int, default=rounds)
    return parser.parse_args()
