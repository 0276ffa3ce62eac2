"""Cost models of a solve as a power of the mesh's face count: the memory (and the time) a
path takes, measured by ``bench.scale`` and fitted through its points.

:class:`solver.linalg.iterative.LinearSolverRules` chooses the direct or the iterative path
by these models; the service's request admission (``service.backends.admission``) reads the
same models to price a request by the path its solver will take.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class PowerLaw:
    """A cost that grows as a power of the face count: ``base + per_face * m * (m /
    reference)^(exponent - 1)`` for m faces, fitted through measured points (bench.scale,
    nefertiti subdivided): bytes of peak memory or seconds.

    Attributes:
        per_face: the cost per face at ``reference`` faces (bytes or seconds).
        exponent: how the cost beyond ``base`` grows with the face count.
        reference: the face count ``per_face`` is measured at.
        base: the cost of no faces (the process itself, for memory).

    Example:
        >>> PowerLaw(per_face=2.0, exponent=1.0).at(1000)
        2000.0
        >>> PowerLaw(per_face=2.0, exponent=1.0).within(2001.0)
        1000
    """

    per_face: float
    exponent: float = 1.0
    reference: int = 400_000
    base: float = 0.0

    def at(self, n_faces: int) -> float:
        """The predicted cost of ``n_faces`` faces."""
        m = max(n_faces, 1)
        return self.base + self.per_face * m * (m / self.reference) ** (self.exponent - 1)

    def within(self, budget: float) -> int:
        """The most faces whose predicted cost stays within ``budget`` (0 when even the base
        does not fit)."""
        room = budget - self.base
        if room <= 0:
            return 0
        # per_face * m^exponent / reference^(exponent - 1) = room
        scale = self.per_face / self.reference ** (self.exponent - 1)
        m = int((room / scale) ** (1 / self.exponent))
        while m > 0 and self.at(m) > budget:  # rounding of the power
            m -= 1
        return m
