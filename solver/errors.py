"""Typed input errors.

Every problem with caller-supplied data raises a subclass of :class:`SolverInputError`.
Each error names the offending element: ``field`` (the input array, e.g. ``"faces"``),
``index`` (the row in that array, or ``None`` when the whole array is at fault) and a
human-readable ``reason``. The HTTP service maps each class to a 422 problem document.
"""

from __future__ import annotations

from typing import Any


class SolverInputError(ValueError):
    """Base class of all errors caused by invalid input data."""

    kind: str = "invalid-input"

    def __init__(self, reason: str, *, field: str | None = None, index: int | None = None,
                 details: dict[str, Any] | None = None) -> None:
        self.reason = reason
        self.field = field
        self.index = None if index is None else int(index)
        self.details = dict(details or {})
        where = ""
        if field is not None:
            where = f"{field}[{self.index}]: " if self.index is not None else f"{field}: "
        super().__init__(where + reason)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description: ``{"kind", "field", "index", "reason", **details}``."""
        return {"kind": self.kind, "field": self.field, "index": self.index,
                "reason": self.reason, **self.details}


class ShapeMismatchError(SolverInputError):
    """An array has the wrong shape, or two arrays that must align do not."""

    kind = "shape-mismatch"


class IndexOutOfRangeError(SolverInputError):
    """An index (vertex, face, edge) is negative or not below the element count."""

    kind = "index-out-of-range"


class NonFiniteValueError(SolverInputError):
    """A NaN or an infinity where a finite number is required."""

    kind = "non-finite-value"


class NonPositiveLengthError(SolverInputError):
    """An edge length that is zero or negative."""

    kind = "non-positive-length"


class TriangleInequalityError(SolverInputError):
    """A face whose three edge lengths violate the triangle inequality."""

    kind = "triangle-inequality"


class AngleRangeError(SolverInputError):
    """A dihedral angle outside (-pi, pi]."""

    kind = "angle-out-of-range"


class EdgeMismatchError(SolverInputError):
    """The edge list is not exactly the set of undirected edges of the faces (sorted, i < j)."""

    kind = "edge-mismatch"


class DegenerateFaceError(SolverInputError):
    """A face that repeats a vertex index, or has zero area where a normal is needed."""

    kind = "degenerate-face"


class NonManifoldEdgeError(SolverInputError):
    """An edge shared by more than two faces."""

    kind = "non-manifold-edge"


class NonManifoldVertexError(SolverInputError):
    """A vertex whose faces form more than one fan (two surface sheets touch at a point)."""

    kind = "non-manifold-vertex"


class InconsistentOrientationError(SolverInputError):
    """Two faces sharing an edge traverse it in the same direction (or a duplicated face)."""

    kind = "inconsistent-orientation"


class ConstraintError(SolverInputError):
    """A constraint or handle refers to an unknown element, repeats one, or is not valid."""

    kind = "invalid-constraint"


class TopologyError(SolverInputError):
    """The mesh topology does not allow the requested operation (e.g. a closed mesh to flatten)."""

    kind = "unsupported-topology"


ERROR_KINDS: tuple[type[SolverInputError], ...] = (
    ShapeMismatchError, IndexOutOfRangeError, NonFiniteValueError, NonPositiveLengthError,
    TriangleInequalityError, AngleRangeError, EdgeMismatchError, DegenerateFaceError,
    NonManifoldEdgeError, NonManifoldVertexError, InconsistentOrientationError,
    ConstraintError, TopologyError,
)
