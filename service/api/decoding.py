"""Request bodies decoded as arrays: orjson parses, numpy checks the large arrays (shapes,
dtypes, ranges), pydantic validates the small rest (the operation's params model). JSON
bodies and binary ``application/vnd.ffs.arrays`` bodies decode to the same arrays.

The request models in :mod:`service.api.schemas` document the bodies; this module enforces the
same rules on the large arrays without one Python object per element error:

* shapes and element types are checked with C-level passes (``map``/``set``/``np.fromiter``)
  before any element-wise work, so a flat list of a million numbers where ``[x, y, z]`` rows
  belong is one error found in milliseconds;
* at most :data:`MAX_ERRORS` errors are collected per array, and the params models' lists
  fail fast (``Field(fail_fast=True)``);
* the result is the numpy arrays the workers use, so nothing is converted twice.

Synchronous operations run this in the worker process (the event loop and the main process's
memory never see the parsed body); jobs and sessions run it in a thread of the main process.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from itertools import chain
from typing import Any, Protocol

import numpy as np
import orjson
from pydantic import BaseModel, ValidationError

from ffs_wire.arrays import (  # binary_body: the reference encoder, re-exported
    BINARY_DTYPES,
    BINARY_MAGIC,
    BINARY_MEDIA_TYPE,
    binary_body,  # noqa: F401
    padded,
)
from service.api.problems import ProblemError, element_error, from_validation_errors, use_a_job
from service.api.schemas import MAX_INDEX, MAX_MAGNITUDE, MAX_SHAPES
from service.api.task import (
    ARRAY_SOURCES,
    FormsArrays,
    Limits,
    MeshArrays,
    MeshPair,
    RawBody,
    TaskRequest,
)
from service.memory import free_later, gc_paused

MAX_ERRORS = 5
"""Errors reported per array (the first ones in element order)."""


@dataclass(frozen=True)
class ArraySpec:
    """One large array of a request body: rows of ``cols`` values (``cols == 0``: a flat
    vector), integer indices in [0, MAX_INDEX] or reals in [-MAX_MAGNITUDE, MAX_MAGNITUDE]."""

    cols: int
    integer: bool
    min_rows: int = 0
    stacked: bool = False
    """A list of such arrays, all of one shape (``blend``'s ``shapes``: (K, n, cols))."""

    @property
    def dtype(self) -> type:
        return np.int64 if self.integer else np.float64

    @property
    def what(self) -> str:
        return "integer" if self.integer else "number"


_POINTS = ArraySpec(3, False, 1)
_TRIANGLES = ArraySpec(3, True, 1)
MESH_ARRAYS: dict[str, ArraySpec] = {"vertices": _POINTS, "faces": _TRIANGLES}
FORMS_ARRAYS: dict[str, ArraySpec] = {"faces": _TRIANGLES, "edges": ArraySpec(2, True),
                                      "lengths": ArraySpec(0, False),
                                      "angles": ArraySpec(0, False)}
PAIR_ARRAYS: dict[str, ArraySpec] = {"vertices_a": _POINTS, "vertices_b": _POINTS,
                                     "faces": _TRIANGLES}
STACK_ARRAYS: dict[str, ArraySpec] = {"shapes": ArraySpec(3, False, 1, stacked=True),
                                      "faces": _TRIANGLES}
TRANSFER_ARRAYS: dict[str, ArraySpec] = {"source": _POINTS, "source_deformed": _POINTS,
                                         "target": _POINTS, "faces": _TRIANGLES}
ArraySpecs = Mapping[str, ArraySpec]
"""The large arrays of a body (its request model's fields minus its params model's)."""

_NUMBER_TYPES = frozenset({int, float})
_JSON_TYPES = {dict: "an object", list: "a list", str: "a string", bool: "a boolean",
               type(None): "null", int: "an integer", float: "a number"}


def parse_json(body: bytes | bytearray) -> Any:
    """The parsed JSON body.

    ``NaN``, ``Infinity`` and overflowing numbers such as ``1e400`` (which Python's ``json``
    writes and reads) parse, as non-finite floats, so that the schema check names the element
    (422) instead of calling the whole body malformed.

    Args:
        body: The body, UTF-8.

    Returns:
        The parsed document.

    Raises:
        ProblemError: 400 ``malformed-json`` when it is empty or not JSON.
    """
    if not body or body.isspace():  # strip() would copy a bytearray
        raise ProblemError("malformed-json", "the body is empty; send a JSON object")
    try:
        return orjson.loads(body)
    except orjson.JSONDecodeError as exc:
        try:  # only on the error path: the stdlib parser reads the non-finite literals
            return json.loads(body)
        except (ValueError, RecursionError):
            pass
        raise ProblemError("malformed-json", f"the body is not valid JSON: {exc}") from None


def _error(loc: Sequence[Any], msg: str, kind: str, *value: Any) -> dict[str, Any]:
    """An error in pydantic's shape; ``value``, when given, is the element sent (quoted)."""
    return {"loc": tuple(loc), "msg": msg, "type": kind, **({"input": value[0]} if value else {})}


def _json_type(value: Any) -> str:
    return _JSON_TYPES.get(type(value), type(value).__name__)


def _first(mask: np.ndarray) -> list[int]:
    return np.flatnonzero(mask)[:MAX_ERRORS].tolist()


def _flat(name: str, value: list[Any], spec: ArraySpec) -> tuple[list[Any], list[dict[str, Any]]]:
    """The values of a list of rows in row-major order, or the structure errors."""
    n, cols = len(value), spec.cols
    if n and set(map(type, value)) != {list}:
        if set(map(type, value)) <= _NUMBER_TYPES:
            rows = f"{n // cols}" if n % cols == 0 else "n"
            return [], [_error((name,), f"expected a list of {rows} rows of {cols} "
                               f"{spec.what}s, got a flat list of {n} {spec.what}s; nest "
                               "each row: [[...], [...], ...]", "list_of_rows")]
        is_row = np.fromiter(map(list.__instancecheck__, value), bool, n)
        return [], [_error((name, i), f"expected a list of {cols} {spec.what}s, got "
                           f"{_json_type(value[i])}", "row_type") for i in _first(~is_row)]
    lengths = np.fromiter(map(len, value), np.intp, n)
    wrong = lengths != cols
    if wrong.any():
        return [], [_error((name, i), f"expected {cols} values, got {int(lengths[i])}",
                           "row_length") for i in _first(wrong)]
    return list(chain.from_iterable(value)), []


def _numbers(name: str, flat: list[Any] | np.ndarray, spec: ArraySpec
             ) -> tuple[np.ndarray | None, list[dict[str, Any]]]:
    """A 1-D array of ``flat`` (int64 or float64 per ``spec``), or the element errors."""
    cols = max(spec.cols, 1)

    def loc(k: int) -> tuple[Any, ...]:
        return (name, k // cols, k % cols) if spec.cols else (name, k)

    if isinstance(flat, np.ndarray):  # a binary body: already numbers
        return _checked(flat.astype(spec.dtype if flat.dtype.kind in "iu" else np.float64),
                        spec, loc)
    kinds = set(map(type, flat))
    if not kinds <= _NUMBER_TYPES:
        ok = np.fromiter(map(_NUMBER_TYPES.__contains__, map(type, flat)), bool, len(flat))
        return None, [_error(loc(k), f"Input should be a valid {spec.what}, got "
                             f"{_json_type(flat[k])}", f"{spec.what}_type")
                      for k in _first(~ok)]
    if spec.integer and float not in kinds:
        try:
            array = np.array(flat, dtype=np.int64)
        except OverflowError:  # beyond int64: certainly beyond MAX_INDEX
            array = np.array(flat, dtype=np.float64)
    else:
        array = np.array(flat, dtype=np.float64)
    return _checked(array, spec, loc)


def _checked(array: np.ndarray, spec: ArraySpec, loc: Any
             ) -> tuple[np.ndarray | None, list[dict[str, Any]]]:
    """``array`` cast to the spec's dtype, or its first integrality and range errors."""
    errors = []
    if spec.integer and array.dtype == np.float64:
        fractional = array != np.trunc(array)
        errors += [_error(loc(k), "Input should be a valid integer, got a number with a "
                          "fractional part", "int_from_float", array.flat[k].item())
                   for k in _first(fractional)]
    low, high = (0, MAX_INDEX) if spec.integer else (-MAX_MAGNITUDE, MAX_MAGNITUDE)
    errors += [_error(loc(k), f"Input should be greater than or equal to {low}",
                      "greater_than_equal", array.flat[k].item()) for k in _first(array < low)]
    errors += [_error(loc(k), f"Input should be less than or equal to {high}",
                      "less_than_equal", array.flat[k].item()) for k in _first(array > high)]
    if not spec.integer:
        errors += [_error(loc(k), "Input should be a finite number", "finite_number",
                          array.flat[k].item()) for k in _first(~np.isfinite(array))]
    if errors:
        return None, errors[:MAX_ERRORS]
    return array.astype(spec.dtype, copy=False), []


def as_array(name: str, value: Any, spec: ArraySpec
             ) -> tuple[np.ndarray | None, list[dict[str, Any]]]:
    """One large array of a parsed JSON body, checked.

    Args:
        name: Its field name.
        value: The parsed JSON value.
        spec: Its shape, element type and range.

    Returns:
        ``(array, [])``: an (n, cols) or (n,) array of ``spec``'s dtype, or ``(None,
        errors)``: at most MAX_ERRORS errors in pydantic's shape (``loc``, ``msg``, ``type``).
    """
    if not isinstance(value, list):
        return None, [_error((name,), f"Input should be a valid list, got {_json_type(value)}",
                             "list_type")]
    if spec.stacked:
        return _stacked_array(name, value, spec)
    if len(value) < spec.min_rows:
        return None, [_error((name,), f"List should have at least {spec.min_rows} item, "
                             f"not {len(value)}", "too_short")]
    flat, errors = _flat(name, value, spec) if spec.cols else (value, [])
    if errors:
        return None, errors
    array, errors = _numbers(name, flat, spec)
    if array is None:
        return None, errors
    return (array.reshape(-1, spec.cols) if spec.cols else array), []


def decode_json(specs: ArraySpecs, params_model: type[BaseModel], doc: Any,
                prefix: tuple[Any, ...] = ()) -> tuple[dict[str, np.ndarray], BaseModel]:
    """The arrays and params of a parsed JSON body.

    Args:
        specs: The large arrays, checked by numpy.
        params_model: The model that validates the rest.
        doc: The parsed body.
        prefix: Where ``doc`` sits in the body (``("input",)`` for a job).

    Returns:
        ``(arrays, params)``: the arrays by name and the validated params.

    Raises:
        ProblemError: One 422 ``validation-error`` listing the first errors of every array
            and of the params (pointers below ``prefix``).
    """
    if not isinstance(doc, Mapping):
        raise from_validation_errors([_error((), f"Input should be a JSON object, got "
                                              f"{_json_type(doc)}", "model_type")], prefix)
    rest = dict(doc)
    sent = {name: rest.pop(name) for name in specs if name in rest}
    return _decode(specs, params_model, sent, rest, as_array, prefix)


def _decode(specs: ArraySpecs, params_model: type[BaseModel], sent: dict[str, Any],
            rest: Mapping[str, Any], convert: Any, prefix: tuple[Any, ...] = ()
            ) -> tuple[dict[str, np.ndarray], BaseModel]:
    """Arrays ``sent`` checked by ``convert(name, value, spec)`` against ``specs`` (missing
    and unknown ones are errors), ``rest`` by ``params_model``; one 422 for all errors."""
    arrays: dict[str, np.ndarray] = {}
    errors: list[dict[str, Any]] = []
    for name, spec in specs.items():
        if name not in sent:
            errors.append(_error((name,), "Field required", "missing"))
            continue
        array, found = convert(name, sent.pop(name), spec)
        errors += found
        if array is not None:
            arrays[name] = array
    errors += [_error((name,), "Extra inputs are not permitted", "extra_forbidden")
               for name in sent]
    params = None
    try:
        params = params_model.model_validate(rest)
    except ValidationError as exc:
        errors += exc.errors(include_url=False)[:MAX_ERRORS * 4]
    if errors or params is None:
        raise from_validation_errors(errors, prefix)
    return arrays, params


# ------------------------------------------------------------------------- binary bodies

# The media type, framing constants and the encoder are shared with the client (ffs_wire.arrays,
# numpy and the standard library only); the reader and its checks are the service's.


def _binary_error(detail: str) -> ProblemError:
    return ProblemError("malformed-request", f"cannot read the {BINARY_MEDIA_TYPE} body: "
                        f"{detail}", errors=[element_error("body", detail)])


MAX_RANK = 3
"""Most dimensions an array of a binary body may declare (the arrays are 1-D or 2-D)."""


def _array_layout(name: str, meta: Any, offset: int, body_size: int
                  ) -> tuple[np.dtype, list[int], int]:
    """(dtype, shape, byte count) of one array's header entry, checked before any arithmetic
    on it: the dtype one of :data:`BINARY_DTYPES` (a string), the shape a list of at most
    :data:`MAX_RANK` non-negative integers, and the byte count (Python integers: no
    wrap-around) within what is left of the body."""
    allowed = ", ".join(BINARY_DTYPES)
    if not isinstance(meta, dict):
        raise _binary_error(f"{name}: expected an object with a dtype and a shape")
    dtype = meta.get("dtype")
    if not isinstance(dtype, str) or dtype not in BINARY_DTYPES:
        raise _binary_error(f"{name}: the dtype must be one of {allowed}")
    shape = meta.get("shape")
    if not isinstance(shape, list) or not all(type(d) is int and d >= 0 for d in shape):
        raise _binary_error(f"{name}: the shape must be a list of non-negative integers")
    if len(shape) > MAX_RANK:
        raise _binary_error(f"{name}: the shape has {len(shape)} dimensions; at most "
                            f"{MAX_RANK} are allowed")
    item = np.dtype(BINARY_DTYPES[dtype])
    size = math.prod(shape) * item.itemsize
    if offset + size > body_size:
        raise _binary_error(f"{name}: a {'x'.join(map(str, shape)) or 'scalar'} {dtype} "
                            f"array needs {size} bytes; the body has {max(0, body_size - offset)}"
                            " left")
    return item, shape, size


def parse_binary(body: bytes) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The header and arrays of an ``application/vnd.ffs.arrays`` body.

    Args:
        body: The body.

    Returns:
        ``(header, arrays)``: the header without ``arrays``, and each array as a view into
        ``body``.

    Raises:
        ProblemError: 400 ``malformed-request`` when the framing is wrong.
    """
    if len(body) < 8 or body[:4] != BINARY_MAGIC:
        raise _binary_error(f"it must start with {BINARY_MAGIC!r} and a uint32 header length")
    size = int.from_bytes(body[4:8], "little")
    if 8 + size > len(body):
        raise _binary_error(f"the header length {size} runs past the end of the body")
    try:
        header = orjson.loads(body[8:8 + size])
    except orjson.JSONDecodeError:
        raise _binary_error("the header is not valid JSON") from None
    if not isinstance(header, dict) or not isinstance(header.get("arrays"), dict):
        raise _binary_error('the header must be a JSON object with "arrays"')
    offset, arrays = padded(8 + size), {}
    for name, meta in header.pop("arrays").items():
        dtype, shape, nbytes = _array_layout(name, meta, offset, len(body))
        arrays[name] = np.frombuffer(body, dtype=dtype, count=nbytes // dtype.itemsize,
                                     offset=offset).reshape(shape)
        offset = padded(offset + nbytes)
    return header, arrays


def _shape_count_error(name: str, count: int) -> dict[str, Any] | None:
    """The error of ``count`` arrays in a stacked field (``blend``'s ``shapes``) outside 1 to
    :data:`MAX_SHAPES` (the library's :data:`solver.shape_space.MAX_SHAPES`), JSON and binary
    bodies alike; None within."""
    if 1 <= count <= MAX_SHAPES:
        return None
    return _error((name,), f"expected 1 to {MAX_SHAPES} arrays, got {count}",
                  "too_long" if count else "too_short")


def _stacked_array(name: str, value: list[Any], spec: ArraySpec
                   ) -> tuple[np.ndarray | None, list[dict[str, Any]]]:
    """A JSON list of arrays of one shape (``spec.stacked``), each checked by
    :func:`as_array` (errors located as ``name[k]...``), stacked (K, n, cols)."""
    if problem := _shape_count_error(name, len(value)):
        return None, [problem]
    single = replace(spec, stacked=False)
    arrays, errors = [], []
    for k, item in enumerate(value):  # a loop over shapes (at most MAX_SHAPES)
        array, found = as_array(f"{name}.{k}", item, single)
        errors += [{**e, "loc": (name, k, *e["loc"][1:])} for e in found]
        if array is not None:
            if arrays and array.shape != arrays[0].shape:
                errors.append(_error((name, k), f"expected shape {list(arrays[0].shape)} like "
                                     f"{name}[0], got {list(array.shape)}", "shape"))
            arrays.append(array)
        if len(errors) >= MAX_ERRORS:
            break
    if errors:
        return None, errors[:MAX_ERRORS]
    return np.stack(arrays), []


def _binary_array(name: str, array: np.ndarray, spec: ArraySpec
                  ) -> tuple[np.ndarray | None, list[dict[str, Any]]]:
    """A binary array checked like a JSON one (shape, integer dtype for indices, range)."""
    if spec.stacked:
        if array.ndim != 3 or array.shape[2] != spec.cols:
            return None, [_error((name,), f"expected shape (K, n, {spec.cols}), got "
                                 f"{list(array.shape)}", "shape")]
        if problem := _shape_count_error(name, len(array)):
            return None, [problem]
        values, errors = _numbers(name, array.ravel(), replace(spec, stacked=False))
        return (None if values is None else values.reshape(array.shape)), errors
    shape = f"(n, {spec.cols})" if spec.cols else "(n,)"
    if array.ndim != (2 if spec.cols else 1) or (spec.cols and array.shape[1] != spec.cols):
        return None, [_error((name,), f"expected shape {shape}, got {list(array.shape)}",
                             "shape")]
    if len(array) < spec.min_rows:
        return None, [_error((name,), f"List should have at least {spec.min_rows} item, "
                             "not 0", "too_short")]
    if spec.integer and array.dtype.kind not in "iu":
        return None, [_error((name,), f"expected an integer dtype, got {array.dtype.str}",
                             "dtype")]
    values, errors = _numbers(name, array.ravel(), spec)
    return (None if values is None else values.reshape(array.shape)), errors


def decode_binary(specs: ArraySpecs, params_model: type[BaseModel], body: bytes
                  ) -> tuple[dict[str, np.ndarray], BaseModel]:
    """The arrays and params of a binary body.

    Args:
        specs: The large arrays.
        params_model: The model that validates the header's other members.
        body: The body.

    Returns:
        ``(arrays, params)`` as :func:`decode_json` returns them.

    Raises:
        ProblemError: 400 for a wrong framing; the 422 errors of :func:`decode_json`.
    """
    header, raw = parse_binary(body)
    return _decode(specs, params_model, raw, header, _binary_array)


# ------------------------------------------------------------------------------ requests


class BodySpec(Protocol):
    """What decoding needs of an operation (:class:`service.operations.OperationSpec`)."""

    @property
    def arrays(self) -> ArraySpecs: ...

    @property
    def params(self) -> type[BaseModel]: ...

    @property
    def source(self) -> str: ...


def check_limits(n_vertices: int, n_faces: int, limits: Limits, field: str,
                 faces_field: str | None = None) -> None:
    """Check a mesh's size against the vertex and face limits.

    Args:
        n_vertices: Its vertex count.
        n_faces: Its face count.
        limits: FFS_MAX_VERTICES and FFS_MAX_FACES.
        field: The input the mesh came in (named by the problem).
        faces_field: The input its faces came in where that is another one (``faces`` of
            a JSON or binary body; an upload's file holds both).

    Raises:
        ProblemError: 413 ``mesh-too-large`` beyond a limit (each error quoting the count
            as its ``value``), ``use-a-job`` beyond max_sync_faces.
    """
    errors = []
    faces_field = faces_field or field
    if n_vertices > limits.max_vertices:
        errors.append(element_error(field, f"{n_vertices} vertices exceed the limit of "
                                           f"{limits.max_vertices}", value=n_vertices))
    if n_faces > limits.max_faces and limits.max_memory is not None:
        errors.append(element_error(faces_field, _memory_reason(n_faces, limits),
                                    value=n_faces))
    elif n_faces > limits.max_faces:
        errors.append(element_error(faces_field, f"{n_faces} faces exceed the limit of "
                                                 f"{limits.max_faces}", value=n_faces))
    if errors:
        raise ProblemError("mesh-too-large", errors[0]["reason"], errors=errors)
    if limits.max_sync_faces is not None and n_faces > limits.max_sync_faces:
        raise use_a_job(n_faces, limits.max_sync_faces, limits.sync_seconds or 0.0,
                        faces_field)


def _memory_reason(n_faces: int, limits: Limits) -> str:
    """Why a mesh over the memory's face limit is refused, in words with the numbers: the
    limit, the memory, and for an operation with an iterative path what each path takes
    (and, for a refined answer, what its linear answer would)."""
    reason = (f"{n_faces} faces exceed the {limits.max_faces} faces this operation can take "
              f"in the {limits.max_memory / 2**30:.1f} GiB one request may use "
              "(FFS_MAX_REQUEST_MEMORY)")
    if limits.max_direct_faces is None:
        return reason
    reason += (f" by either path: a factorization fits {limits.max_direct_faces} faces, the "
               f"iterative solver (options.linear_solver) {limits.max_faces}")
    if limits.linear is not None and limits.linear.max_faces > n_faces:
        reason += (f"; its linear answer (options.refine: false) fits up to "
                   f"{limits.linear.max_faces} faces")
    return reason


def blend_rows(params: Mapping[str, Any]) -> tuple[int, str]:
    """The rows a blend or interpolate request asks for and the field that sets them:
    ``weights`` (its rows), else ``t`` (its values; one for a number), else 1."""
    if isinstance(params.get("weights"), list):
        weights = params["weights"]
        nested = bool(weights) and isinstance(weights[0], list)
        return (len(weights) if nested else 1), "weights"
    t = params.get("t")
    return (len(t) if isinstance(t, list) else 1), "t"


def check_work(params: Mapping[str, Any], limits: Limits, prefix: tuple[Any, ...] = (),
               n_vertices: int | None = None) -> None:
    """Bound the work a small body can ask for.

    Args:
        params: The dumped params.
        limits: FFS_MAX_BLEND_STEPS and FFS_MAX_BLEND_VERTICES.
        prefix: Where the params sit in the body.
        n_vertices: The mesh's vertex count where it is known (arrays decoded, files read).

    Raises:
        ProblemError: 422 ``validation-error`` for more than ``FFS_MAX_BLEND_STEPS`` rows
            (blend values in ``t``, rows of ``weights``), checked before any mesh is read;
            413 ``blend-too-large`` for rows x ``n_vertices`` beyond
            ``FFS_MAX_BLEND_VERTICES`` (each row is a solve of the whole mesh, and the
            answer holds rows x vertices x 3 numbers).
    """
    rows, name = blend_rows(params)
    field = ".".join(map(str, (*prefix, name)))
    pointer = "/" + "/".join(map(str, (*prefix, name)))
    if rows > limits.max_blend_steps:
        raise ProblemError(
            "validation-error", f"{field}: {rows} blend values; at most "
            f"{limits.max_blend_steps} are allowed (FFS_MAX_BLEND_STEPS): send the others in "
            "further requests",
            errors=[element_error(field, f"at most {limits.max_blend_steps} values",
                                  type="too_long", pointer=pointer)])
    blends = "t" in params or "weights" in params  # interpolate, blend
    if blends and n_vertices is not None and rows * n_vertices > limits.max_blend_vertices:
        most = max(limits.max_blend_vertices // max(n_vertices, 1), 0)
        raise ProblemError(
            "blend-too-large", f"{field}: {rows} rows of a {n_vertices}-vertex mesh are "
            f"{rows * n_vertices} row vertices, beyond {limits.max_blend_vertices} "
            f"(FFS_MAX_BLEND_VERTICES): send at most {most} rows per request",
            errors=[element_error(field, f"at most {most} rows of this mesh",
                                  pointer=pointer)])


def _vertex_count(kind: str, arrays: Mapping[str, np.ndarray]) -> tuple[int, str]:
    """The vertex count of decoded arrays of a source kind and the field it is checked on."""
    faces = arrays["faces"]
    if kind == "forms":
        return (int(faces.max()) + 1 if faces.size else 0), "faces"
    if kind == "pair":
        return max(len(arrays["vertices_a"]), len(arrays["vertices_b"])), "vertices_a"
    if kind == "shapes":
        return arrays["shapes"].shape[1], "shapes"
    if kind == "transfer":
        return max(len(arrays[name]) for name in ("source", "source_deformed", "target")), \
            "source"
    return len(arrays["vertices"]), "vertices"


def array_source(kind: str, arrays: Mapping[str, np.ndarray], limits: Limits
                 ) -> MeshArrays | FormsArrays | MeshPair:
    """The task source of decoded arrays, after the vertex and face limits.

    Args:
        kind: ``mesh``, ``forms`` or ``pair``.
        arrays: The decoded arrays by name.
        limits: The size limits (:func:`check_limits`, 413).

    Returns:
        The source of that kind.
    """
    n_vertices, field = _vertex_count(kind, arrays)
    check_limits(n_vertices, len(arrays["faces"]), limits, field, "faces")
    return ARRAY_SOURCES[kind](**arrays)


def decode_document(spec: BodySpec, doc: Any, limits: Limits, prefix: tuple[Any, ...] = ()
                    ) -> tuple[MeshArrays | FormsArrays | MeshPair, dict[str, Any]]:
    """The source and params of a parsed JSON body.

    Args:
        spec: The operation.
        doc: A synchronous body, or a job's ``input``.
        limits: The size and work limits.
        prefix: Where ``doc`` sits (``("input",)`` for a job's).

    Returns:
        ``(source, params)``: the task's source and its dumped params.
    """
    arrays, params = decode_json(spec.arrays, spec.params, doc, prefix)
    dumped = params.model_dump()
    limits = limits.answering(dumped)
    check_work(dumped, limits, prefix)
    source = array_source(spec.source, arrays, limits)
    check_work(dumped, limits, prefix, _vertex_count(spec.source, arrays)[0])
    return source, dumped


def decode_raw(spec: BodySpec, request: TaskRequest) -> TaskRequest:
    """A task with its raw body parsed and validated (in the worker).

    Args:
        spec: The operation.
        request: The task, its source a :class:`RawBody`.

    Returns:
        ``request`` with its decoded source and params.
    """
    raw = request.source
    assert isinstance(raw, RawBody)
    if raw.kind == "binary":
        arrays, model = decode_binary(spec.arrays, spec.params, raw.body)
    else:
        with gc_paused():
            doc = parse_json(raw.body)
            arrays, model = decode_json(spec.arrays, spec.params, doc)
        free_later(doc)  # freed once the answer is sent
    params = model.model_dump()
    size = request.limits.answering(params)
    check_work(params, size)
    source = array_source(spec.source, arrays, size)
    check_work(params, size, n_vertices=_vertex_count(spec.source, arrays)[0])
    return replace(request, source=source, params=params, limits=size)
