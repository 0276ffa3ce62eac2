"""The flattening's atlas rules as data: when to chart again, when to push flips back, and
which charts are small enough for SuperLU.

One frozen dataclass, :class:`AtlasRules`, read by :mod:`solver.parameterize`,
:mod:`solver.chart_flattening` and :mod:`solver.atlas` (``ATLAS_RULES`` is the default;
tests and benchmarks pass their own).

Example:
    >>> from solver.atlas_rules import ATLAS_RULES
    >>> ATLAS_RULES.rechart_below, ATLAS_RULES.flip_retry_area_factor
    (0.5, 10.0)
    >>> ATLAS_RULES.replace(rechart_below=0.6).rechart_below
    0.6
"""

from __future__ import annotations

from dataclasses import dataclass, replace


@dataclass(frozen=True)
class AtlasRules:
    """Rules of :func:`solver.parameterize.parameterize`'s atlases."""

    rechart_below: float = 0.5
    """An atlas of xatlas-seeded charts covering less of the unit square than this is charted
    again by the bisection alone and the atlas that packs better is kept (bench/flatten.py:
    the torus 0.338 -> 0.478, the cylinder 0.407 -> 0.557, the beetle 0.356 -> 0.473, the
    koala 0.457 -> 0.619 (odedstein/meshes); every other measured atlas covers 0.5 or more).
    Above :attr:`solver.core.warnings.WarningRules.min_packing_efficiency` (0.4): an atlas is
    charted again before it would warn."""

    flip_retry_area_factor: float = 10.0
    """A chart's refinement that ends with flipped faces is continued from its answer with
    the signed-area weight times this (the bumpy plane: 6 flipped faces of 80,000 at the
    default weight, 0 after the retry)."""

    small_chart_faces: int = 20_000
    """Charts with fewer faces are solved with SuperLU when the backend is ``auto``:
    PARDISO's fixed cost per call (measured 0.95 s against 0.10 s per 456-face flattening)
    dominates there."""

    def replace(self, **changes: float) -> AtlasRules:
        """A copy with ``changes`` applied."""
        return replace(self, **changes)


ATLAS_RULES = AtlasRules()
"""The rules the service and ``ffs`` use."""

__all__ = ["ATLAS_RULES", "AtlasRules"]
