"""Render the pictures of docs/shape-space.md: a blend, an extrapolation and a transfer.

Each panel is a mesh drawn with matplotlib (Agg), its faces coloured by the mean relative
length change of their edges against the rest mesh (white: isometric, dark red: 5 % or
more), so the pictures show what the numbers in the page say: form-space answers stay
near-isometric where vertex blends shrink or stretch.

    python scripts/render_shape_space.py   # docs/shape-space-{blend,extrapolation,transfer}.png
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from solver import blend, fundamental_forms, transfer  # noqa: E402
from tests.helpers import DATA  # noqa: E402
from tests.helpers.botsch_sorkine import load_case  # noqa: E402
from tests.helpers.meshes import load  # noqa: E402
from tests.helpers.poses import bent_pose, case_pose  # noqa: E402

OUT = REPO / "docs"
TOP = 0.05  # colour scale: relative length change


def face_change(X: np.ndarray, rest: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(m,) mean |l / l_rest - 1| of each face's edges."""
    forms = fundamental_forms(X, F)
    change = np.abs(forms.lengths / fundamental_forms(rest, F).lengths - 1.0)
    lookup = {tuple(e): i for i, e in enumerate(forms.edges.tolist())}
    index = np.array([[lookup[tuple(sorted((f[a], f[(a + 1) % 3])))] for a in range(3)]
                      for f in F.tolist()])
    return change[index].mean(axis=1)


def draw(ax, X: np.ndarray, F: np.ndarray, rest: np.ndarray, title: str, view: tuple,
         axes: list[int]) -> None:
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    values = face_change(X, rest, F)
    normals = np.cross(X[F[:, 1]] - X[F[:, 0]], X[F[:, 2]] - X[F[:, 0]])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    light = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    shade = 0.55 + 0.45 * np.abs(normals @ light)
    colors = plt.cm.Reds(np.clip(values / TOP, 0, 1) * 0.9)
    colors[:, :3] *= shade[:, None]
    Y = X[:, axes]  # the mesh's up axis as matplotlib's z
    ax.add_collection3d(Poly3DCollection(Y[F], facecolors=colors, linewidths=0))
    lo, hi = Y.min(0), Y.max(0)
    centre, half = (lo + hi) / 2, (hi - lo).max() / 2
    for set_lim, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre, strict=True):
        set_lim(c - half, c + half)
    ax.view_init(*view)
    ax.set_axis_off()
    mean = float(np.abs(fundamental_forms(X, F).lengths / fundamental_forms(rest, F).lengths
                        - 1).mean())
    ax.set_title(f"{title}\nlength change {100 * mean:.2f} %", fontsize=8)


def figure(panels: list[tuple[np.ndarray, str, np.ndarray]], F: np.ndarray, name: str,
           view: tuple, axes: tuple[int, int, int] = (0, 1, 2)) -> Path:
    """One row of panels ``(vertices, title, reference)``: each coloured by its length
    change against its reference mesh."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(2.3 * len(panels), 2.7), dpi=100)
    for k, (X, title, rest) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), k + 1, projection="3d")
        draw(ax, X, F, rest, title, view, list(axes))
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.86, wspace=0)
    path = OUT / f"shape-space-{name}.png"
    fig.savefig(path)
    plt.close(fig)
    return path


def main() -> None:
    cylinder = load_case(DATA, "cylinder")
    A, F = cylinder.vertices, cylinder.faces
    B = case_pose(cylinder, 1.0)                      # the 120-degree bend
    mid = blend([A, B], [[0.5, 0.5]], F).vertices[0]
    print(figure([(A, "A (rest)", A), (mid, "form-space blend t = 0.5", A),
                  (0.5 * (A + B), "vertex blend t = 0.5", A), (B, "B (bent 120°)", A)],
                 F, "blend", (10, -60)))
    bent = bent_pose(A, F, 0.5)                       # bent 0.5 rad about its middle
    out = blend([A, bent], [[-0.5, 1.5]], F).vertices[0]
    print(figure([(A, "A (rest)", A), (bent, "B (bent 0.5 rad)", A),
                  (out, "form-space t = 1.5", A),
                  (-0.5 * A + 1.5 * bent, "vertex extrapolation t = 1.5", A)],
                 F, "extrapolation", (10, -60)))
    knight, G = load("decimated-knight.off")
    pose = bent_pose(knight, G, 0.6)
    target = knight * [1.3, 0.8, 1.1]
    moved = transfer(knight, pose, target, G)
    print(figure([(knight, "A", knight), (pose, "A' (A bent; vs A)", knight),
                  (target, "B = A scaled 1.3/0.8/1.1", target),
                  (moved, "B' form-space transfer (vs B)", target),
                  (target + pose - knight, "B + A' - A (vs B)", target)],
                 G, "transfer", (12, -70), (0, 2, 1)))


if __name__ == "__main__":
    main()
