"""The default weights of the refinement's energy (:mod:`solver.refine.form_energy`).

Here, below both the energy and :mod:`solver.options` (whose defaults they are), so that the
options do not import the refinement. Why these values: ``docs/refinement.md``.
"""

ANGLE_WEIGHT = 0.005
"""Default ``beta`` where forms are prescribed (reconstruct, interpolate): the weight of a
radian of dihedral angle against a relative length change of 1. Small: lengths are kept and
the angles give way, which is what noisy, scaled and blended forms need (docs/refinement.md)."""
DEFORM_ANGLE_WEIGHT = 0.3
"""Default ``beta`` for deformations, whose targets are the rest forms: stiffer bending,
smoother shapes under conflicting handles (measured against libigl's ARAP in
docs/refinement.md)."""
AREA_WEIGHT = 100.0
"""Default ``gamma`` (planar fits only): weight of the one-sided signed-area residual."""
AREA_FLOOR = 0.2
"""Planar fits: a face whose signed area falls below this fraction of its target area (or
flips) pays ``gamma/2 (A/A0 - AREA_FLOOR)^2``; larger faces pay nothing."""
HARD_FRAME_WEIGHT = 1e3
"""Weight standing in for a hard orientation handle (not eliminable in positions)."""
