"""Energy weightings compared: exactness of reconstruction from exact forms.

For each shared mesh and each weighting ("uniform", "cotan_clamped", "cotan" = the paper
literally), reconstruct from the mesh's own forms and report the error after rigid
alignment (relative to the bounding-box diagonal) together with the spread of the row
weights (max / min), which bounds how much the weighting worsens conditioning.
Deformation quality per weighting: ``python -m bench.deformation_cases --weightings ...``

    python -m bench.weights [backend]

A solve whose relative residual exceeds 1e-6 is refused by solver.linalg ("refused: r").
"""

from __future__ import annotations

import sys

from bench.common import load_bench_mesh
from solver import fundamental_forms, reconstruct
from solver.immersion import ImmersionProblem
from solver.linalg import SingularSystemError
from solver.mesh.forms import validate_forms
from tests.helpers.meshes import rigid_alignment_error

MESHES = ["decimated-knight.off", "octopus-low-surface.off", "torus.off", "face.off",
          "bar.off", "cylinder.off", "cactus.off", "bunny.off"]
WEIGHTINGS = ["uniform", "cotan_clamped", "cotan"]


def main() -> None:
    backend = sys.argv[1] if len(sys.argv) > 1 else "auto"
    print(f"backend: {backend}")
    print("| mesh | faces | obtuse faces | " + " | ".join(
        f"{w} error (weight spread)" for w in WEIGHTINGS) + " |")
    print("|---|---|---|" + "---|" * len(WEIGHTINGS))
    for name in MESHES:
        V, F = load_bench_mesh(name)
        forms = fundamental_forms(V, F)
        topo, L, A = validate_forms(forms.faces, forms.edges, forms.lengths, forms.angles)
        cells = []
        obtuse = None
        for weighting in WEIGHTINGS:
            problem = ImmersionProblem(topo, L, A, weighting=weighting)
            w = problem.row_weights
            try:
                result = reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles,
                                     weighting=weighting, check_integrability=False,
                                     backend=backend, exact_shortcut=False)
                error = f"{rigid_alignment_error(result.vertices, V):.1e}"
            except SingularSystemError as exc:
                error = "refused: " + str(exc).split("=")[1].split(" exceeds")[0].strip()
            cells.append(f"{error} ({w.max() / w.min():.0e})")
            if obtuse is None:
                from solver.linear.system import half_cotangents
                from solver.mesh.frames import face_edge_lengths
                obtuse = int((half_cotangents(face_edge_lengths(topo, L)) < 0).any(1).sum())
        print(f"| {name} | {len(F)} | {obtuse} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
