"""Content negotiation: pick a response format from the ``Accept`` header.

Formats in server preference order: ``json`` (application/json, the default), ``glb``
(model/gltf-binary) and ``gltf`` (model/gltf+json, buffer embedded as a data URI). Quality
values and wildcards (``*/*``, ``model/*``) are honoured; exact types beat wildcards.
"""

from __future__ import annotations

from collections.abc import Sequence

from service.api.problems import ProblemError
from service.worker.output import MEDIA_TYPES

MESH_FORMATS: tuple[str, ...] = ("json", "glb", "gltf")
JSON_ONLY: tuple[str, ...] = ("json",)


def _parse(accept: str) -> list[tuple[str, str, float]]:
    ranges = []
    for part in accept.split(","):
        pieces = [p.strip() for p in part.split(";")]
        media = pieces[0].lower()
        if not media:
            continue
        if media == "*":
            media = "*/*"
        if "/" not in media:
            continue
        q = 1.0
        for param in pieces[1:]:
            key, _, value = param.partition("=")
            if key.strip().lower() == "q":
                try:
                    q = float(value)
                except ValueError:
                    q = 0.0
        main, _, sub = media.partition("/")
        ranges.append((main, sub, max(0.0, min(1.0, q))))
    return ranges


def _quality(media_type: str, ranges: list[tuple[str, str, float]]) -> float:
    main, _, sub = media_type.partition("/")
    best, specificity = 0.0, -1
    for r_main, r_sub, q in ranges:
        if r_main == main and r_sub == sub:
            level = 2
        elif r_main == main and r_sub == "*":
            level = 1
        elif r_main == "*" and r_sub == "*":
            level = 0
        else:
            continue
        if level > specificity:
            best, specificity = q, level
    return best


def negotiate(accept: str | None, formats: Sequence[str] = MESH_FORMATS) -> str:
    """The format to answer with.

    Args:
        accept: The request's Accept header.
        formats: What the endpoint produces, its default first.

    Returns:
        The best format ``accept`` allows (the default when it is absent or empty).

    Raises:
        ProblemError: 406 ``not-acceptable`` listing what the endpoint can produce.
    """
    if accept is None or not accept.strip():
        return formats[0]
    ranges = _parse(accept)
    if not ranges:
        return formats[0]
    scored = [(_quality(MEDIA_TYPES[f], ranges), -i, f) for i, f in enumerate(formats)]
    q, _, best = max(scored)
    if q <= 0.0:
        offered = ", ".join(MEDIA_TYPES[f] for f in formats)
        raise ProblemError("not-acceptable",
                           f"cannot produce any of Accept: {accept!r}; available: {offered}",
                           available=[MEDIA_TYPES[f] for f in formats])
    return best
