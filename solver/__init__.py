"""Linear surface reconstruction from discrete fundamental forms on triangle meshes.

Reference implementation of the method of Sections 2.3-4 of *Linear Surface Reconstruction
from Discrete Fundamental Forms on Triangle Meshes*: edge lengths (first form) and signed
dihedral angles (second form) -> integrability check -> one sparse linear least-squares
solve over vertex positions and per-face frames (the lift to 6D, Eq. 5).

Conventions: ``vertices`` (n, 3) float64, ``faces`` (m, 3) int64 counter-clockwise seen from
outside; ``edges`` (E, 2) unique pairs i < j sorted lexicographically; ``lengths``/``angles``
(E,) aligned with ``edges``; dihedral angles in (-pi, pi], positive where convex.
"""

from .core.allocator import retain_freed_memory
from .core.errors import SolverInputError
from .deform import Deformation, Deformer, deform
from .differentiable import ReconstructionVJP, reconstruct_vjp
from .interpolate import interpolate
from .linear.constraints import Constraints
from .linear.integrability import IntegrabilityReport, check_integrability
from .mesh import metrics
from .mesh.alignment import Alignment, rigid_alignment
from .mesh.forms import Forms, fundamental_forms
from .options import (
    BlendOptions,
    DeformOptions,
    InterpolateOptions,
    ParameterizeOptions,
    ReconstructOptions,
    SolveOptions,
)
from .parameterize import Parameterization, parameterize
from .reconstruct import Reconstruction, reconstruct
from .shape_space import Blend, blend, mean, transfer

retain_freed_memory()  # numpy temporaries reuse freed pages (solver/core/allocator.py)

__all__ = [
    "Alignment",
    "Blend",
    "BlendOptions",
    "Constraints",
    "DeformOptions",
    "Deformation",
    "Deformer",
    "Forms",
    "IntegrabilityReport",
    "InterpolateOptions",
    "Parameterization",
    "ParameterizeOptions",
    "ReconstructOptions",
    "Reconstruction",
    "ReconstructionVJP",
    "SolveOptions",
    "SolverInputError",
    "blend",
    "check_integrability",
    "deform",
    "fundamental_forms",
    "interpolate",
    "mean",
    "metrics",
    "parameterize",
    "reconstruct",
    "reconstruct_vjp",
    "rigid_alignment",
    "transfer",
]
