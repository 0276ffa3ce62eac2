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


def exceeded(value: float, limit: float, code: str, template: str,
             ) -> AnswerWarning | None:
    """An :class:`AnswerWarning` when ``value`` is past ``limit`` (None otherwise).

    Args:
        value: the measured quantity.
        limit: its threshold; ``value > limit`` warns (NaN warns too).
        code: the rule's name.
        template: the message, formatted with ``value`` and ``limit``.
    """
    value = float(value)
    if value <= limit:
        return None
    return AnswerWarning(code, template.format(value=value, limit=limit), value, float(limit))


def as_report(warnings: list[AnswerWarning | None]) -> list[dict[str, Any]]:
    """The report's ``warnings`` list: the warnings found, as JSON-ready dicts."""
    return [dataclasses.asdict(found) for found in warnings if found is not None]
