"""Warnings: answers that were computed but are past a documented quality threshold.

An operation that returns an answer whose quality is worse than a threshold of
:class:`WarningRules` (too many flipped faces, a large length or angle error left, a time
limit reached before any progress) says so in its report's ``warnings``: a list of
:class:`AnswerWarning` dicts, each naming the rule (``code``), what was measured
(``value``), the threshold (``limit``) and a sentence with units (``message``). The
service returns them in its reports, ``ffs`` prints WARN (``--strict``: exit 1) and the
client exposes them as ``result.warnings``: one mechanism for every operation.

Example:
    >>> rules = WarningRules()
    >>> found = exceeded(0.2, rules.max_flipped_fraction, "flipped-faces",
    ...                  "{value:.1%} of the faces are flipped (limit {limit:.1%})")
    >>> found.code, found.message
    ('flipped-faces', '20.0% of the faces are flipped (limit 0.1%)')
    >>> exceeded(0.0, rules.max_flipped_fraction, "flipped-faces", "") is None
    True
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

from .serialization import JsonDataclass


@dataclasses.dataclass(frozen=True)
class AnswerWarning(JsonDataclass):
    """One threshold an answer is past.

    Attributes:
        code: the rule, kebab-case (``flipped-faces``, ``length-error``, ...).
        message: one sentence for people, with units.
        value: what was measured, in the unit of ``limit``.
        limit: the threshold it is past (:class:`WarningRules`).
    """

    code: str
    message: str
    value: float
    limit: float


@dataclasses.dataclass(frozen=True)
class WarningRules:
    """The documented thresholds past which an answer carries a warning.

    Attributes:
        max_flipped_fraction: flipped faces of a flattening, as a fraction of its faces.
        max_length_error: the largest relative edge-length error left (a fraction:
            0.05 is 5%) of a reconstruction, deformation or flattening.
        max_angle_error: the largest dihedral-angle error left, radians.
        max_flatten_length_change: a flattening's mean relative edge-length change.
        max_flatten_angle_change: a flattening's mean (over faces) largest corner-angle
            change, radians.
        min_packing_efficiency: the fraction of the unit square an atlas of several
            charts should cover.
        max_boundary_crossings: pairs of boundary edges of a one-chart flattening that
            cross (a layout that overlaps itself).
    """

    max_flipped_fraction: float = 1e-3
    max_length_error: float = 0.05
    max_angle_error: float = 0.1
    max_flatten_length_change: float = 0.1
    max_flatten_angle_change: float = 0.2
    min_packing_efficiency: float = 0.4
    max_boundary_crossings: int = 0


DEFAULT_RULES = WarningRules()
"""The thresholds every operation uses unless given others."""


def exceeded(value: float, limit: float, code: str, template: str, **fields: Any,
             ) -> AnswerWarning | None:
    """An :class:`AnswerWarning` when ``value`` is past ``limit`` (None otherwise).

    Args:
        value: the measured quantity.
        limit: its threshold; ``value > limit`` warns (NaN warns too).
        code: the rule's name.
        template: the message, formatted with ``value``, ``limit`` and ``fields``.
        fields: more values the message names (e.g. ``degrees``).
    """
    value = float(value)
    if value <= limit:
        return None
    return AnswerWarning(code, template.format(value=value, limit=limit, **fields), value,
                         float(limit))


def as_report(warnings: list[AnswerWarning | None]) -> list[dict[str, Any]]:
    """The report's ``warnings`` list: the warnings found, as JSON-ready dicts."""
    return [dataclasses.asdict(found) for found in warnings if found is not None]


LENGTH_ERROR_MESSAGE = ("the largest edge-length error left is {value:.1%} of the edge's "
                        "target length (limit {limit:.0%})")
ANGLE_ERROR_MESSAGE = ("the largest dihedral-angle error left is {value:.3g} rad "
                       "({degrees:.3g}°; limit {limit:g} rad)")
FLIPPED_MESSAGE = "{value:.2%} of the faces are flipped (limit {limit:.2%})"


def residual_warnings(length_error: float | None, angle_error: float | None,
                      rules: WarningRules = DEFAULT_RULES, *,
                      length_limit: float | None = None) -> list[AnswerWarning | None]:
    """Warnings for the largest relative edge-length error (a fraction) and dihedral-angle
    error (radians) an answer leaves; None for a measure that is absent. ``length_limit``:
    instead of ``rules.max_length_error``."""
    found: list[AnswerWarning | None] = []
    if length_error is not None:
        limit = rules.max_length_error if length_limit is None else length_limit
        found.append(exceeded(length_error, limit, "length-error", LENGTH_ERROR_MESSAGE))
    if angle_error is not None:
        found.append(exceeded(angle_error, rules.max_angle_error, "angle-error",
                              ANGLE_ERROR_MESSAGE, degrees=math.degrees(angle_error)))
    return found


def time_limit_warning(refinement: Mapping[str, Any]) -> AnswerWarning | None:
    """A warning when a refinement's time limit ran out before any step lowered the energy:
    the answer is the refinement's start (``value`` and ``limit``: the energy left as a
    fraction of the start's, and 1)."""
    if refinement.get("stop_reason") != "time_limit" or refinement.get("outcome") != (
            "not-refined"):
        return None
    before, after = refinement.get("energy_before"), refinement.get("energy_after")
    left = 1.0 if not before or after is None else float(after) / float(before)
    return AnswerWarning(
        "time-limit-no-progress",
        f"the time limit ran out after {int(refinement.get('iterations') or 0)} refinement "
        "iterations, before any progress: the answer is the refinement's start (energy "
        f"{after if after is not None else float('nan'):.4g}, unchanged); raise max_seconds",
        left, 1.0)


def refinement_warnings(refinement: Mapping[str, Any] | None,
                        rules: WarningRules = DEFAULT_RULES) -> list[AnswerWarning | None]:
    """The warnings of a refinement report (:mod:`solver.refine`): the length and angle
    errors it left (``after``) and a time limit with no progress."""
    if not refinement:
        return []
    after = refinement.get("after") or {}
    length = (after.get("length_error") or {}).get("max")
    angle = (after.get("angle_error") or {}).get("max")
    return [*residual_warnings(length, angle, rules), time_limit_warning(refinement)]


def flattening_warnings(flipped_count: int, face_count: int, mean_length_change: float,
                        mean_angle_change: float, refinement: Mapping[str, Any] | None, *,
                        packing: float = 1.0, charts: int = 1, crossings: int = 0,
                        rules: WarningRules = DEFAULT_RULES) -> list[AnswerWarning | None]:
    """The warnings of a flattening (one chart or an atlas): flipped faces (a fraction of
    ``face_count``), the mean relative edge-length change and the mean (over faces) largest
    corner-angle change of the layout, the packing efficiency of several charts, a one-chart
    layout whose boundary crosses itself, and a time limit with no progress.

    Example:
        >>> found = flattening_warnings(0, 10, 0.2, 0.01, None)
        >>> [w.code for w in found if w is not None]
        ['length-distortion']
    """
    fraction = flipped_count / face_count if face_count else 0.0
    return [
        exceeded(fraction, rules.max_flipped_fraction, "flipped-faces", FLIPPED_MESSAGE),
        exceeded(mean_length_change, rules.max_flatten_length_change, "length-distortion",
                 "the uv edge lengths differ from the 3D ones by {value:.1%} on average "
                 "(limit {limit:.1%})"),
        exceeded(mean_angle_change, rules.max_flatten_angle_change, "angle-distortion",
                 "the uv corner angles differ from the 3D ones by {value:.3f} rad on "
                 "average (largest per face; limit {limit:.3f} rad)"),
        exceeded(1.0 - packing if charts > 1 else 0.0, 1.0 - rules.min_packing_efficiency,
                 "packing-efficiency",
                 "the charts leave {value:.0%} of the unit square empty (limit {limit:.0%})"),
        exceeded(crossings, rules.max_boundary_crossings, "overlapping-layout",
                 "{value:.0f} pairs of boundary edges cross in uv: the layout overlaps "
                 "itself (limit {limit:.0f}; seams='auto' cuts such a mesh into charts)"),
        time_limit_warning(refinement or {})]
