"""JSON round-trips for the package's result dataclasses (plain dataclasses of numpy arrays)."""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar, Self

import numpy as np


def to_jsonable(value: Any) -> Any:
    """Recursively convert numpy arrays and scalars and dataclasses to JSON-ready values.

    Args:
        value: any nesting of dataclasses, dicts, lists, tuples, arrays and scalars.

    Returns:
        The same nesting of dicts (string keys), lists, floats, ints, bools and strings.

    Example:
        >>> import numpy as np
        >>> from solver.core.serialization import to_jsonable
        >>> to_jsonable({"edges": np.array([[0, 1]]), 2: (np.float64(0.5), True)})
        {'edges': [[0, 1]], '2': [0.5, True]}
    """
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [to_jsonable(v) for v in value]
    return value


class JsonDataclass:
    """Mixin: ``to_dict()`` gives JSON-ready data; ``from_dict()`` restores numpy arrays.

    Fields listed in ``_array_fields`` (name -> dtype) are turned back into arrays; nested
    dataclass fields are listed in ``_nested_fields`` (name -> class).
    """

    _array_fields: ClassVar[dict[str, Any]] = {}
    _nested_fields: ClassVar[dict[str, Any]] = {}

    def to_dict(self) -> dict[str, Any]:
        """The instance as JSON-ready data (:func:`to_jsonable`)."""
        return to_jsonable(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Self:
        """Rebuild an instance from :meth:`to_dict`'s data.

        Args:
            data: field name -> value; unknown keys are ignored.

        Returns:
            The instance, with ``_array_fields`` as numpy arrays of their dtype and
            ``_nested_fields`` rebuilt as their classes.
        """
        names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
        kwargs: dict[str, Any] = {}
        for key, value in data.items():
            if key not in names:
                continue
            if key in cls._array_fields and value is not None:
                value = np.asarray(value, dtype=cls._array_fields[key])
            elif key in cls._nested_fields and value is not None:
                nested = cls._nested_fields[key]
                value = ([nested.from_dict(v) for v in value] if isinstance(value, list)
                         else nested.from_dict(value))
            kwargs[key] = value
        return cls(**kwargs)
