"""Files of the command line: meshes, forms, handles and results, by extension.

* Meshes: the library's formats (:data:`solver.mesh.formats.FORMATS`: OBJ, PLY, OFF, STL,
  GLB/glTF; file vertex order kept; OBJ/OFF/PLY are written with full float64 precision,
  STL and glTF in float32) through :mod:`solver.mesh.io`, or ``.json`` / ``.npz`` holding
  ``vertices`` and ``faces`` (the API's mesh document).
* Forms: ``.json`` with the fields of the API's forms response (``faces``, ``edges``,
  ``lengths``, ``angles``, and the optional ``vertex_map`` of a non-manifold mesh and
  ``placement`` of its components) or ``.npz`` with the same names (the placement as
  ``placement_faces``, ``placement_origins``, ``placement_frames``).
* Handles (``ffs deform --handles``): JSON, either the API's ``handles`` list
  ``[{"vertex": i, "position": [x, y, z]}, ...]`` or an object with ``handles`` and the
  optional ``rotations`` (``[{"faces": [...], "rotation": 3x3 rows}]``) and ``roi``; or a
  Botsch-Sorkine ``.sel`` / ``.def`` pair (:mod:`ffs.selections`).

Every problem with a file raises :class:`InputFileError` naming the file, the field and the
index, so the command line can print one line.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ffs.results import Forms
from ffs_wire.arrays import json_default
from solver.mesh.formats import LOAD_FORMATS as MESH_FORMATS

DATA_FORMATS = ("json", "npz")
"""Formats of arrays by name: forms, meshes as documents, reports."""


class InputFileError(Exception):
    """A file the command cannot use; its message is ``path: field[index]: reason``.

    Args:
        path: The file.
        reason: What is wrong with it.
        field: The field of the document, where the problem is in one.
        index: The element of ``field``, where the problem is in one.
    """

    def __init__(self, path: str | os.PathLike[str], reason: str, *, field: str | None = None,
                 index: int | None = None) -> None:
        self.path, self.reason, self.field, self.index = str(path), reason, field, index
        where = "" if field is None else (f"{field}[{index}]: " if index is not None
                                          else f"{field}: ")
        super().__init__(f"{self.path}: {where}{reason}")


def file_format(path: str | os.PathLike[str], override: str | None = None) -> str:
    """The lower-case format of ``path``: ``override`` or its extension.

    Raises:
        InputFileError: Neither a mesh format nor a data format (.json, .npz).
    """
    fmt = (override or Path(path).suffix.lstrip(".")).lower()
    if fmt not in MESH_FORMATS + DATA_FORMATS:
        raise InputFileError(path, f"unknown file format {fmt or '(no extension)'!r}; use "
                             f"one of {', '.join(MESH_FORMATS + DATA_FORMATS)}")
    return fmt


def _read_fields(path: Path, fmt: str) -> dict[str, Any]:
    """The named fields of a .json or .npz file."""
    try:
        if fmt == "npz":
            with np.load(path, allow_pickle=False) as data:
                return {name: data[name] for name in data.files}
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputFileError(path, "no such file") from None
    except (OSError, ValueError) as exc:
        raise InputFileError(path, f"cannot read it as {fmt.upper()}: {exc}") from None
    if not isinstance(doc, dict):
        raise InputFileError(path, f"expected a JSON object, got {type(doc).__name__}")
    return doc


def _array(path: Path, doc: dict[str, Any], name: str, dtype: type, cols: int | None
           ) -> np.ndarray:
    if name not in doc:
        raise InputFileError(path, "missing", field=name)
    try:
        array = np.asarray(doc[name], dtype=dtype)
    except (TypeError, ValueError, OverflowError) as exc:
        raise InputFileError(path, f"not an array of numbers ({exc})", field=name) from None
    if dtype is np.int64 and np.issubdtype(np.asarray(doc[name]).dtype, np.floating):
        fractional = np.flatnonzero(np.asarray(doc[name]) % 1 != 0)
        if len(fractional):
            raise InputFileError(path, "indices must be integers", field=name,
                                 index=int(fractional[0]) // (cols or 1))
    if (cols and (array.ndim != 2 or array.shape[1] != cols)) or (not cols and array.ndim != 1):
        shape = f"(n, {cols})" if cols else "(n,)"
        raise InputFileError(path, f"expected shape {shape}, got {list(array.shape)}",
                             field=name)
    return array


def read_mesh(path: str | os.PathLike[str], fmt: str | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
    """Read a mesh file or mesh document.

    Args:
        path: An OBJ, OFF, PLY, STL, GLB/glTF file, or a .json/.npz with ``vertices`` and
            ``faces``.
        fmt: The format instead of the extension (``--input-format``).

    Returns:
        ``(vertices (n, 3) float64, faces (m, 3) int64)``, in the file's vertex order.

    Raises:
        InputFileError: Missing, unreadable, or not a mesh (naming the field and index).
    """
    path = Path(path)
    fmt = file_format(path, fmt)
    if fmt in DATA_FORMATS:
        doc = _read_fields(path, fmt)
        if "vertices" not in doc and "edges" in doc:
            raise InputFileError(path, "a forms file (edges, lengths, angles) has no vertices; "
                                 "this command takes a mesh: make one of the forms with "
                                 "'ffs reconstruct' first", field="vertices")
        return (_array(path, doc, "vertices", np.float64, 3),
                _array(path, doc, "faces", np.int64, 3))
    from solver.mesh.io import MeshFileError, file_bytes, load_mesh

    name = path.name if fmt == path.suffix.lstrip(".").lower() else fmt
    try:
        data = file_bytes(path, name)  # a .gltf with the buffer files beside it
    except FileNotFoundError:
        raise InputFileError(path, "no such file") from None
    except OSError as exc:
        raise InputFileError(path, exc.strerror or str(exc)) from None
    except MeshFileError as exc:
        raise InputFileError(path, exc.reason) from None
    try:
        return load_mesh(data, name)
    except MeshFileError as exc:
        raise InputFileError(path, exc.reason) from None


def is_forms_file(path: str | os.PathLike[str], fmt: str | None = None) -> bool:
    """Whether ``path`` holds forms (a .json/.npz with ``edges``) rather than a mesh."""
    fmt = file_format(path, fmt)
    return fmt in DATA_FORMATS and "edges" in _read_fields(Path(path), fmt)


def read_forms(path: str | os.PathLike[str], fmt: str | None = None) -> Forms:
    """Read forms.

    Args:
        path: A .json or .npz with ``faces`` (m, 3), ``edges`` (k, 2), ``lengths`` (k,) and
            ``angles`` (k,).
        fmt: The format instead of the extension.

    Returns:
        The forms (faces and edges int64, lengths and angles float64).

    Raises:
        InputFileError: Not a .json/.npz, a field missing, or of the wrong shape or dtype.
    """
    path = Path(path)
    fmt = file_format(path, fmt)
    if fmt not in DATA_FORMATS:
        raise InputFileError(path, "forms are read from .json or .npz files")
    doc = _read_fields(path, fmt)
    forms = Forms(_array(path, doc, "faces", np.int64, 3),
                  _array(path, doc, "edges", np.int64, 2),
                  _array(path, doc, "lengths", np.float64, None),
                  _array(path, doc, "angles", np.float64, None))
    for name in ("vertex_map", "weld_map", "dropped_faces"):  # a cut or welded mesh's
        if doc.get(name) is not None:
            setattr(forms, name, _array(path, doc, name, np.int64, None))
    extras = Forms.from_dict({**doc, "faces": [], "edges": [], "lengths": [], "angles": []})
    forms.placement = extras.placement
    return forms


@dataclass(frozen=True)
class Handles:
    """Deformation handles: vertices (h,), targets (h, 3), rotation groups with (g, 3, 3)
    rotations, region of interest."""

    vertices: np.ndarray
    positions: np.ndarray
    rotation_faces: list[np.ndarray]
    rotations: np.ndarray | None
    roi: np.ndarray | None


HANDLE_FILE_MEMBERS = ("handles", "rotations", "roi", "groups")
"""The members of a handles file: the API's three and the web page's ``groups`` (ignored)."""


def _no_unknown_members(path: str | os.PathLike[str], doc: dict[str, Any],
                        members: Sequence[str], where: tuple[str, int] | None) -> None:
    """Refuse a member ``doc`` does not take (a typo such as ``weigth`` or ``rotation``
    would otherwise be dropped silently), naming it and where it is."""
    for name in doc:
        if name not in members:
            field, index = (where[0], where[1]) if where else (name, None)
            raise InputFileError(path, f"unknown member {name!r}; expected "
                                 f"{', '.join(members)}", field=field, index=index)


def read_handles(path: str | os.PathLike[str], vertices: np.ndarray | None = None,
                 faces: np.ndarray | None = None) -> Handles:
    """Read deformation handles (``ffs deform --handles``).

    Args:
        path: JSON: the API's ``handles`` list, or an object with ``handles`` and the
            optional ``rotations`` and ``roi``; or a ``.sel`` / ``.def`` pair
            (:mod:`ffs.selections`), which needs the mesh's ``vertices`` and ``faces``.

    Returns:
        The handles.

    Raises:
        InputFileError: Not such a document (naming the field and index).
    """
    from ffs.selections import is_selection_file, read_selection

    if is_selection_file(path):
        if vertices is None or faces is None:
            raise InputFileError(path, "a .sel/.def handle set needs the mesh it selects on")
        handles, targets, groups, rotations, roi = read_selection(path, vertices, faces)
        return Handles(handles, targets, groups, rotations, roi)
    doc = read_json(path)
    if isinstance(doc, list):
        doc = {"handles": doc}
    if not isinstance(doc, dict) or not isinstance(doc.get("handles"), list) or not doc[
            "handles"]:
        raise InputFileError(path, 'expected a non-empty list [{"vertex": i, "position": '
                             '[x, y, z]}, ...] or an object with "handles"', field="handles")
    _no_unknown_members(path, doc, HANDLE_FILE_MEMBERS, None)
    for name, members in (("handles", ("vertex", "position")), ("rotations",
                                                                ("faces", "rotation"))):
        for i, item in enumerate(doc.get(name) or []):
            if isinstance(item, dict):
                _no_unknown_members(path, item, members, (name, i))
    vertices, positions = [], []
    for i, handle in enumerate(doc["handles"]):
        try:
            vertex, position = handle["vertex"], [float(x) for x in handle["position"]]
            if type(vertex) is not int or len(position) != 3:
                raise ValueError
        except (KeyError, TypeError, ValueError):
            raise InputFileError(path, 'expected {"vertex": integer, "position": [x, y, z]}',
                                 field="handles", index=i) from None
        vertices.append(vertex)
        positions.append(position)
    groups, rotations = [], []
    for i, group in enumerate(doc.get("rotations") or []):
        try:
            groups.append(np.asarray(group["faces"], dtype=np.int64).ravel())
            rotations.append(np.asarray(group["rotation"], dtype=np.float64).reshape(3, 3))
        except (KeyError, TypeError, ValueError):
            raise InputFileError(path, 'expected {"faces": [...], "rotation": 3x3 rows}',
                                 field="rotations", index=i) from None
    roi = doc.get("roi")
    return Handles(np.asarray(vertices, dtype=np.int64), np.asarray(positions), groups,
                   np.asarray(rotations) if rotations else None,
                   None if roi is None else np.asarray(roi, dtype=np.int64))


def read_json(path: str | os.PathLike[str]) -> Any:
    """A JSON document (e.g. reconstruct constraints).

    Raises:
        InputFileError: Missing, or not JSON.
    """
    path = Path(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputFileError(path, "no such file") from None
    except (OSError, ValueError) as exc:
        raise InputFileError(path, f"cannot read it as JSON: {exc}") from None


def read_cotangent(path: str | os.PathLike[str]) -> np.ndarray:
    """The cotangent of ``ffs vjp --cotangent``: (n, 3) or (k, n, 3) float64 from a .npy,
    an .npz (array ``cotangent``, or its only array) or a .json (the array, or an object
    with ``cotangent``).

    Raises:
        InputFileError: Missing, unreadable, not numbers, or not (n, 3) / (k, n, 3).
    """
    path = Path(path)
    fmt = path.suffix.lstrip(".").lower()
    try:
        if fmt == "npy":
            value: Any = np.load(path, allow_pickle=False)
        elif fmt == "npz":
            fields = _read_fields(path, fmt)
            value = fields.get("cotangent", next(iter(fields.values())) if len(fields) == 1
                               else None)
        else:
            value = read_json(path)
            value = value.get("cotangent") if isinstance(value, dict) else value
        array = np.asarray(value, dtype=np.float64)
    except FileNotFoundError:
        raise InputFileError(path, "no such file") from None
    except (OSError, TypeError, ValueError) as exc:
        raise InputFileError(path, f"not an array of numbers ({exc})",
                             field="cotangent") from None
    if array.ndim not in (2, 3) or array.shape[-1] != 3:
        raise InputFileError(path, f"expected shape (n, 3) or (k, n, 3), got "
                             f"{list(array.shape)}", field="cotangent")
    return array


# ----------------------------------------------------------------------------- writing


def json_text(document: Any) -> str:
    """JSON of results and reports (numpy values as lists and numbers; float64 exact)."""
    return json.dumps(document, default=json_default)


def write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    """Write a file's bytes (an animated GLB from the service or the library), atomically."""
    _atomic_write(Path(path), data)


def _atomic_write(path: Path, data: bytes) -> None:
    """Write through a temporary file in the same folder, so that a failed or interrupted
    run never leaves a truncated output behind."""
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.name}.{os.getpid()}.partial")
    partial.write_bytes(data)
    partial.replace(path)


def write_arrays(path: Path, fmt: str, arrays: dict[str, Any], extra: dict[str, Any]
                 ) -> None:
    """Write arrays by name, atomically.

    Args:
        path: The output file.
        fmt: ``json`` or ``npz``.
        arrays: Name -> array.
        extra: More fields of a .json document (not written to an .npz).
    """
    if fmt == "npz":
        import io

        buffer = io.BytesIO()
        np.savez(buffer, **{k: np.asarray(v) for k, v in arrays.items()})
        _atomic_write(path, buffer.getvalue())
    else:
        _atomic_write(path, json_text({**arrays, **extra}).encode())


def write_textured_mesh(path: Path, fmt: str, vertices: np.ndarray, faces: np.ndarray,
                        texcoords: np.ndarray, uv_faces: np.ndarray, uv_vertex: np.ndarray,
                        ) -> None:
    """Write a mesh with its atlas, atomically: ``obj`` (``v``, ``vt``, ``f v/vt``) or
    ``glb`` (seam vertices duplicated, ``TEXCOORD_0``); :mod:`solver.mesh.uv_files`."""
    from solver.mesh.uv_files import textured_glb, textured_obj

    data = (textured_obj(vertices, faces, texcoords, uv_faces) if fmt == "obj"
            else textured_glb(vertices, texcoords, uv_faces, uv_vertex))
    _atomic_write(path, data)


def write_mesh(path: Path, fmt: str, vertices: np.ndarray, faces: np.ndarray,
               report: dict[str, Any] | None = None) -> None:
    """Write a mesh, atomically.

    Args:
        path: The output file.
        fmt: a mesh format the library writes (:data:`solver.mesh.formats.SAVE_FORMATS`), or
            ``json``/``npz`` (a document with ``vertices``, ``faces`` and ``report``).
        vertices: (n, 3) float64 (written in float32 to STL and GLB).
        faces: (m, 3) int.
        report: The ``report`` field of a document.
    """
    if fmt in DATA_FORMATS:
        write_arrays(path, fmt, {"vertices": vertices, "faces": faces},
                     {"report": report or {}})
        return
    from solver.mesh.io import save_mesh

    _atomic_write(path, save_mesh(vertices, faces, fmt))
