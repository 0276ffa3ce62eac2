"""The one family of errors a caller's input causes.

Every problem with caller-supplied data (arrays, a mesh file, a constraint set that leaves
the system singular, a backend that is not installed) raises a subclass of
:class:`SolverInputError`. Each error names the offending element: ``field`` (the input,
e.g. ``"faces"``), ``index`` (the row in that input, or ``None`` when the whole input is at
fault), a human-readable ``reason`` and, where the value the caller sent is worth quoting,
``details["value"]``. Its ``kind`` names the class of fault; the HTTP service answers each
kind with the problem document of that name (422 for most, 400 for an unreadable file, 415
for an unknown file type).

The family::

    SolverInputError                       invalid-input
    ├── ShapeMismatchError, IndexOutOfRangeError, ... (ERROR_KINDS: the array checks)
    ├── MeshFileError                      unreadable-file         (solver.mesh.io)
    │   └── UnsupportedFormatError         unsupported-file-type
    ├── SingularSystemError                singular-system         (solver.linalg)
    └── BackendUnavailableError            invalid-option          (solver.linalg)
"""

from __future__ import annotations

from typing import Any


class SolverInputError(ValueError):
    """Base class of every error caused by invalid input.

    Args:
        reason: Why the element is at fault, in words.
        field: The input at fault (``"faces"``, ``"constraints.frames.frame"``), or None.
        index: The row of ``field`` at fault, or None when the whole input is.
        value: The offending value as the caller sent it (kept in ``details["value"]``).
        details: Further JSON-ready facts about the fault (``{"edge": [3, 7]}``).
        message: What ``str()`` says; by default ``"<field>[<index>]: <reason>"``.

    Attributes:
        kind: The name of this class of fault (a problem kind of the HTTP service).

    Example:
        >>> error = IndexOutOfRangeError("index 9 out of range [0, 4)", field="faces",
        ...                              index=2, value=9)
        >>> str(error)
        'faces[2]: index 9 out of range [0, 4)'
        >>> error.element()
        {'field': 'faces', 'index': 2, 'reason': 'index 9 out of range [0, 4)', 'value': 9}
    """

    kind: str = "invalid-input"

    def __init__(self, reason: str, *, field: str | None = None, index: int | None = None,
                 value: Any = None, details: dict[str, Any] | None = None,
                 message: str | None = None) -> None:
        self.reason = reason
        self.field = field
        self.index = None if index is None else int(index)
        self.details = dict(details or {})
        if value is not None:
            self.details["value"] = value
        super().__init__(message if message is not None else self._where() + reason)

    def __reduce__(self) -> tuple[Any, ...]:
        # Pickled as its state: ``cls(*args)`` would read the message as the reason.
        return _restore, (type(self), self.args, self.__dict__)

    def _where(self) -> str:
        if self.field is None:
            return ""
        return f"{self.field}[{self.index}]: " if self.index is not None else f"{self.field}: "

    def element(self) -> dict[str, Any]:
        """The element at fault, as a problem document's ``errors`` item.

        Returns:
            ``{"field", "index", "reason", **details}``, JSON-ready.
        """
        return {"field": self.field, "index": self.index, "reason": self.reason,
                **self.details}

    def to_dict(self) -> dict[str, Any]:
        """The error as JSON-ready data.

        Returns:
            ``{"kind", "field", "index", "reason", **details}``.
        """
        return {"kind": self.kind, **self.element()}


def _restore(cls: type[SolverInputError], args: tuple[Any, ...], state: dict[str, Any]
             ) -> SolverInputError:
    error = cls.__new__(cls, *args)
    error.args = args
    error.__dict__.update(state)
    return error


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
    TriangleInequalityError, EdgeMismatchError, DegenerateFaceError,
    NonManifoldEdgeError, NonManifoldVertexError, InconsistentOrientationError,
    ConstraintError, TopologyError,
)
"""The checks of the input arrays: each kind is a 422 problem named after the class."""


class MeshFileError(SolverInputError):
    """Mesh file data that cannot be read as a triangle mesh.

    Args:
        reason: The cause, in words.
        file_type: The resolved format (``"obj"``, ...), when known.
        index: The vertex or face record at fault, when one is.
        details: Further JSON-ready facts (``{"line": 6}``).

    Attributes:
        file_type: As given, or filled in by :func:`solver.mesh.io.load_mesh`.
        file_name: The file's name where the caller gave one (:meth:`located`).

    ``str()`` reads ``"[<file name>: ][<file type>: ]<reason>"``; ``field`` is the input
    the file came in, None until :meth:`located` names it.
    """

    kind = "unreadable-file"

    def __init__(self, reason: str, *, file_type: str | None = None, index: int | None = None,
                 details: dict[str, Any] | None = None) -> None:
        self.file_type = file_type
        self.file_name: str | None = None
        super().__init__(reason, index=index, details=details, message=reason)
        self._name_it()

    def _name_it(self) -> None:
        self.args = (": ".join(part for part in (self.file_name, self.file_type, self.reason)
                               if part),)

    def located(self, *, file_type: str | None = None, field: str | None = None,
                file_name: str | None = None) -> MeshFileError:
        """This error, with what the caller knows of the file filled in.

        Args:
            file_type: The format, where the error does not name one yet.
            field: The input the file came in (a form field, ``"file"``).
            file_name: The file's name.

        Returns:
            The same error (its message now names the file).
        """
        self.file_type = self.file_type or file_type
        self.field = field or self.field
        self.file_name = file_name or self.file_name
        self._name_it()
        return self

    def to_dict(self) -> dict[str, Any]:
        """The error as JSON-ready data.

        Returns:
            ``{"kind", "file_type", "field", "index", "reason", **details}``.
        """
        return {"kind": self.kind, "file_type": self.file_type, **self.element()}


class UnsupportedFormatError(MeshFileError):
    """The file name or type names no format :mod:`solver.mesh.io` reads (or writes)."""

    kind = "unsupported-file-type"
