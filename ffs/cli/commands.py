"""What each command does with one item: read its inputs, call the backend (the library
in-process, :class:`ffs.local.Local`, or a service, :class:`ffs.client.Client`), write its
outputs and fill its :class:`~ffs.cli.items.Row`.

Every runner has the signature ``run_<command>(backend, item, args, progress, row)``: the
parsed command line ``args``, ``progress(stage, fraction)`` for the bar, and ``row`` to fill.
numpy and the library are imported inside the runners, after the command line has set the
BLAS thread variables.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from ffs.cli.failures import RunFailedError
from ffs.cli.items import Item, Row, mesh_outputs
from ffs.operations import COMMANDS

Progress = Callable[[str, float], None]
"""``progress(stage, fraction)``: a stage's name and how far the item is, 0 to 1."""


def _refinement_columns(row: Row, report: dict[str, Any] | None) -> None:
    """The ``refined`` and residual columns of ``row`` from a report's ``refinement``."""
    refinement = (report or {}).get("refinement")
    if isinstance(refinement, list):  # a blend of several t: the worst
        refinement = max(refinement, key=lambda r: ((r or {}).get("after") or {}).get(
            "length_error", {}).get("max", 0.0), default=None)
    if not isinstance(refinement, dict):
        return
    row.refined = bool(refinement.get("refined"))
    row.outcome = str(refinement.get("outcome_text") or "")
    after = refinement.get("after") or {}
    row.length_error = (after.get("length_error") or {}).get("max")
    row.angle_error = (after.get("angle_error") or {}).get("max")


def _given(args: argparse.Namespace, name: str, read: Callable[..., Any], *mesh: Any) -> Any:
    """What the file of option ``name`` holds: as read once for every item
    (:func:`ffs.cli.items.check_given_files`), else read here by ``read(path, *mesh)``; None
    without the option."""
    path = getattr(args, name, None)
    if path is None:
        return None
    given = getattr(args, "given", None) or {}
    return given[name] if given.get(name) is not None else read(path, *mesh)


def _mesh_options(args: argparse.Namespace, *, orthonormalize_default: bool = False
                  ) -> dict[str, Any]:
    """The solver options given on the command line, by their library names (``None``s
    and an ``--orthonormalize`` equal to the operation's default left out)."""
    options = {"frame_weight": args.frame_weight, "weighting": args.weighting,
               "solver": args.solver, "max_seconds": args.max_seconds, "refine": args.refine}
    if args.orthonormalize is not None and args.orthonormalize != orthonormalize_default:
        options["orthonormalize"] = args.orthonormalize
    return {k: v for k, v in options.items() if v is not None}


def _reconstruct_options(args: argparse.Namespace) -> dict[str, Any]:
    """:func:`_mesh_options` and the integrability options of ``reconstruct`` and ``vjp``."""
    options = _mesh_options(args)
    options.update({k: v for k, v in {"tolerance": args.tolerance,
                                      "require_integrable": args.require_integrable or None,
                                      "linear_solver": args.linear_solver,
                                      }.items() if v is not None})
    return options


def _output_format(path: Path, args: argparse.Namespace,
                   allowed: Sequence[str] | None = None) -> str:
    """The format ``path`` is written in: ``--format`` or its extension.

    Raises:
        ffs.files.InputFileError: The format is not one of ``allowed`` (default: every
            format written).
    """
    from ffs import files

    fmt = (args.format or path.suffix.lstrip(".")).lower()
    writable = allowed or mesh_outputs()
    if fmt not in writable:
        raise files.InputFileError(path, f"cannot write {fmt or '(no extension)'!r} here; "
                                   f"use one of {', '.join(writable)} (or --format)")
    return fmt


def _write_mesh_result(item: Item, args: argparse.Namespace, row: Row, vertices: Any,
                       faces: Any, report: dict[str, Any]) -> None:
    """Write a mesh result to the item's output and fill the row from its report."""
    from ffs import files

    out = Path(item.outputs[0])
    files.write_mesh(out, _output_format(out, args), vertices, faces, report)
    row.faces, row.report = len(faces), report
    _refinement_columns(row, report)
    row.warnings = list(report.get("warnings") or [])


def _forms_of(backend: Any, path: str, args: argparse.Namespace, progress: Progress) -> Any:
    """The forms in a forms file, or those of a mesh file."""
    from ffs import files

    if files.is_forms_file(path):
        return files.read_forms(path)
    vertices, faces = files.read_mesh(path, args.input_format)
    return backend.fundamental_forms(vertices, faces, progress=progress)


def run_forms(backend: Any, item: Item, args: argparse.Namespace, progress: Progress,
              row: Row) -> None:
    """``ffs forms``: a mesh's edge lengths and dihedral angles as .json or .npz."""
    import numpy as np

    from ffs import files

    vertices, faces = files.read_mesh(item.inputs[0], args.input_format)
    forms = backend.fundamental_forms(vertices, faces, progress=progress)
    out = Path(item.outputs[0])
    fmt = _output_format(out, args, ("json", "npz"))
    extra = forms.params()
    if forms.dropped_faces is not None:
        extra["dropped_faces"] = np.asarray(forms.dropped_faces).tolist()
    files.write_arrays(out, fmt, forms.stored_arrays() if fmt == "npz" else forms.arrays(),
                       extra)
    row.faces = len(forms.faces)
    row.note = f"{len(forms.edges)} edges"
    if forms.weld_map is not None or forms.dropped_faces is not None:  # solver.mesh.weld
        welded = (0 if forms.weld_map is None else
                  int((np.asarray(forms.weld_map) != np.arange(len(forms.weld_map))).sum()))
        dropped = 0 if forms.dropped_faces is None else len(forms.dropped_faces)
        row.note += f"; {welded} vertices welded, {dropped} faces dropped"


def run_check(backend: Any, item: Item, args: argparse.Namespace, progress: Progress,
              row: Row) -> None:
    """``ffs check``: integrability of forms (or of a mesh's forms).

    Raises:
        RunFailedError: ``--require-integrable`` and the forms are not integrable.
    """
    from ffs import files

    forms = _forms_of(backend, item.inputs[0], args, progress)
    report = backend.check_integrability(forms, tol=args.tolerance, progress=progress)
    row.faces, row.report = len(forms.faces), report.report
    row.extra = {"integrable": report.integrable, "max_defect": report.max_defect}
    row.note = ("integrable" if report.integrable else "NOT integrable") + \
        f", max defect {report.max_defect:.3g} rad"
    if item.outputs:
        out = Path(item.outputs[0])
        files.write_arrays(out, _output_format(out, args, ("json",)), {}, report.report)
    if args.require_integrable and not report.integrable:
        worst = (report.report.get("worst_vertices") or [None])[0]
        raise RunFailedError(f"the forms are not integrable: max defect "
                             f"{report.max_defect:.3g} rad (tolerance "
                             f"{args.tolerance or 1e-8:g} rad); worst vertex {worst}")


def run_reconstruct(backend: Any, item: Item, args: argparse.Namespace, progress: Progress,
                    row: Row) -> None:
    """``ffs reconstruct``: a mesh from forms (``--constraints`` pins positions/frames)."""
    from ffs import files

    forms = _forms_of(backend, item.inputs[0], args, progress)
    options = _reconstruct_options(args)
    constraints = _given(args, "constraints", files.read_json)
    reference = _given(args, "align_to", lambda path: files.read_mesh(path)[0])
    if reference is not None:
        options["align_to"] = reference
    result = backend.reconstruct(forms, constraints=constraints, progress=progress, **options)
    _write_mesh_result(item, args, row, result.vertices, result.faces, result.report)
    alignment = result.report.get("alignment")
    if alignment:
        row.note = (f"aligned to {Path(args.align_to).name}: residual rms "
                    f"{alignment['residual_rms']:.3g}, max {alignment['residual_max']:.3g} "
                    "(mesh units)")


def counted(n: int, noun: str) -> str:
    """``n`` and the noun, in the plural unless ``n`` is 1.

    Example:
        >>> counted(1, "chart"), counted(0, "flipped face")
        ('1 chart', '0 flipped faces')
    """
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def run_vjp(backend: Any, item: Item, args: argparse.Namespace, progress: Progress,
            row: Row) -> None:
    """``ffs vjp``: the cotangents of a reconstruction's inputs (lengths, angles, constraint
    targets) for ``--cotangent``, the gradient of a loss with respect to its vertices, as
    .json or .npz (with the reconstructed ``vertices`` and ``faces``)."""
    from ffs import files

    forms = _forms_of(backend, item.inputs[0], args, progress)
    options = _reconstruct_options(args)
    constraints = _given(args, "constraints", files.read_json)
    cotangent = _given(args, "cotangent", files.read_cotangent)
    result = backend.reconstruct_vjp(forms, cotangent=cotangent,
                                     constraints=constraints, progress=progress, **options)
    out = Path(item.outputs[0])
    files.write_arrays(out, _output_format(out, args, ("json", "npz")),
                       {**result.arrays(), "vertices": result.vertices, "faces": result.faces},
                       {"report": result.report})
    row.faces, row.report = len(result.faces), result.report
    _refinement_columns(row, result.report)
    mode = (result.report.get("vjp") or {}).get("mode", "")
    row.note = f"{mode} answer differentiated".strip()
    row.warnings = list(result.report.get("warnings") or [])


def run_deform(backend: Any, item: Item, args: argparse.Namespace, progress: Progress,
               row: Row) -> None:
    """``ffs deform``: the mesh with its ``--handles`` moved."""
    from ffs import files

    vertices, faces = files.read_mesh(item.inputs[0], args.input_format)
    handles = _given(args, "handles", files.read_handles, vertices, faces)
    result = backend.deform(vertices, faces, handles.vertices, handles.positions,
                            rotation_handles=handles.rotation_faces or None,
                            handle_rotations=handles.rotations, roi=handles.roi,
                            progress=progress, **_mesh_options(args))
    _write_mesh_result(item, args, row, result.vertices, result.faces, result.report)


def run_flatten(backend: Any, item: Item, args: argparse.Namespace, progress: Progress,
                row: Row) -> None:
    """``ffs flatten``: the atlas of a mesh. OBJ and GLB: the mesh with its uv (``vt`` /
    ``TEXCOORD_0``; ``--flat``: the flat layout instead); PLY, OFF, STL: the flat layout
    (u, v, 0) over the uv faces; .json/.npz: the arrays."""
    import numpy as np

    from ffs import files

    vertices, faces = files.read_mesh(item.inputs[0], args.input_format)
    seams = {"seams": args.seams} if getattr(args, "seams", None) else {}
    result = backend.parameterize(vertices, faces, progress=progress, **seams,
                                  **_mesh_options(args, orthonormalize_default=True))
    out = Path(item.outputs[0])
    fmt = _output_format(out, args)
    uv_faces = result.uv_faces if result.uv_faces is not None else np.asarray(faces)
    if fmt in files.DATA_FORMATS:
        arrays = {"uv": result.uv, "flipped_faces": result.flipped_faces,
                  "faces": np.asarray(faces)}
        arrays.update({name: getattr(result, name) for name in
                       ("texcoords", "uv_faces", "uv_vertex", "face_chart")
                       if getattr(result, name) is not None})
        files.write_arrays(out, fmt, arrays, {"report": result.report})
    elif fmt in ("obj", "glb") and not args.flat and result.texcoords is not None:
        files.write_textured_mesh(out, fmt, vertices, np.asarray(faces), result.texcoords,
                                  uv_faces, result.uv_vertex)
    else:
        flat = np.column_stack([result.uv, np.zeros(len(result.uv))])
        files.write_mesh(out, fmt, flat, uv_faces)
    row.faces, row.report = len(faces), result.report
    charts = (result.report.get("atlas") or {}).get("charts", 1)
    row.note = f"{counted(len(result.flipped_faces), 'flipped face')}, {counted(charts, 'chart')}"
    _refinement_columns(row, result.report)
    # A layout's errors are its distortion against the 3D mesh (mean edge-length and
    # corner-angle change: the statistics of its distortion warnings, summary.ERROR_STATISTIC),
    # one chart or an atlas alike: a planar refinement's dihedral angles are all 0, so its
    # "angle error" said 0 rad beside 1 rad corner distortion.
    row.length_error = (result.report.get("length_change_summary") or {}).get("mean")
    row.angle_error = (result.report.get("angle_distortion_summary") or {}).get("mean")
    row.warnings = list(result.report.get("warnings") or [])


def run_blend(backend: Any, item: Item, args: argparse.Namespace, progress: Progress,
              row: Row) -> None:
    """``ffs blend``: meshes between A and B (same faces) at each ``-t``, in form space
    (K meshes, ``--weights`` or one file for several rows: :func:`run_shape_blend`)."""
    from ffs import files

    if args.weights_rows is not None or len(item.outputs) != len(args.t):
        run_shape_blend(backend, item, args, progress, row)
        return

    vertices_a, faces = files.read_mesh(item.inputs[0], args.input_format)
    vertices_b, _ = files.read_mesh(item.inputs[1], args.input_format)
    options = _mesh_options(args)
    options.pop("orthonormalize", None)
    t = args.t[0] if len(args.t) == 1 else list(args.t)
    result = backend.interpolate(vertices_a, vertices_b, faces, t, progress=progress,
                                 **options)
    shapes = [result.vertices] if len(args.t) == 1 else list(result.vertices)
    for out, vertices in zip(item.outputs, shapes, strict=True):
        files.write_mesh(Path(out), _output_format(Path(out), args), vertices, result.faces,
                         {"t": result.t, "refinement": result.refinement})
    row.faces, row.report = len(result.faces), {"refinement": result.refinement}
    row.note = "t = " + ", ".join(f"{x:g}" for x in args.t)
    _refinement_columns(row, row.report)


def _shapes(item: Item, args: argparse.Namespace) -> tuple[list[Any], Any]:
    """The meshes of an item with several inputs (same faces), and their faces."""
    import numpy as np

    from ffs import files

    shapes, faces = [], None
    for path in item.inputs:
        vertices, these = files.read_mesh(path, args.input_format)
        if faces is None:
            faces = these
        elif np.shape(these) != np.shape(faces) or not np.array_equal(these, faces):
            raise files.InputFileError(path, f"its faces differ from {item.inputs[0]}'s (a "
                                       "blend needs one connectivity)", field="faces")
        shapes.append(vertices)
    return shapes, faces


def _shape_options(args: argparse.Namespace) -> dict[str, Any]:
    options = _mesh_options(args)
    options.pop("orthonormalize", None)
    if getattr(args, "independent", False):
        options["sequence"] = False
    return options


def run_shape_blend(backend: Any, item: Item, args: argparse.Namespace, progress: Progress,
                    row: Row) -> None:
    """``ffs blend`` of K meshes (``--weights``) or of several ``-t`` into one file: an
    animated GLB (the first mesh, each row a morph target, an animation at
    ``--rows-per-second`` or the weights file's ``times``), the rows as .json/.npz arrays,
    or one mesh file per row (``{index}``, ``{t}``)."""
    import numpy as np

    from ffs import files

    shapes, faces = _shapes(item, args)
    weights = args.weights_rows
    t = None if weights is not None else list(args.t)
    options = _shape_options(args)
    first = Path(item.outputs[0])
    if len(item.outputs) == 1 and _output_format(first, args) == "glb":
        count = len(weights) if weights is not None else len(t or [])
        times = args.times or (np.arange(count) / args.rows_per_second).tolist()
        data = backend.blend_gltf(np.stack(shapes), faces, weights, t=t, times=times,
                                  **options)
        files.write_bytes(first, data)
        row.faces, row.note = len(faces), f"{count} rows, animated"
        return
    result = backend.blend(np.stack(shapes), faces, weights, t=t, progress=progress,
                           **options)
    if len(item.outputs) == 1 and len(result.vertices) > 1:
        files.write_arrays(first, _output_format(first, args, files.DATA_FORMATS),
                           {"weights": result.weights, "vertices": result.vertices,
                            "faces": result.faces}, {"reports": result.reports})
    else:
        for out, vertices, report in zip(item.outputs, result.vertices, result.reports,
                                         strict=True):
            files.write_mesh(Path(out), _output_format(Path(out), args), vertices,
                             result.faces, report)
    worst = max(result.reports, key=lambda r: r["form_error"]["length_error"]["mean"])
    row.faces, row.report = len(result.faces), {"rows": result.reports}
    row.refined = any((r.get("refinement") or {}).get("refined") for r in result.reports)
    row.length_error = worst["form_error"]["length_error"]["max"]
    row.angle_error = worst["form_error"]["angle_error"]["max"]
    row.note = f"{len(result.vertices)} rows"
    row.warnings = [{**found, "message": f"row {found['row']}: {found['message']}"}
                    for found in result.warnings]


def run_mean(backend: Any, item: Item, args: argparse.Namespace, progress: Progress,
             row: Row) -> None:
    """``ffs mean``: the form-space mean of the meshes (same faces)."""
    import numpy as np

    shapes, faces = _shapes(item, args)
    result = backend.mean(np.stack(shapes), faces, progress=progress, **_shape_options(args))
    _write_mesh_result(item, args, row, result.vertices, result.faces, result.report)
    row.note = f"mean of {len(shapes)}"


def run_transfer(backend: Any, item: Item, args: argparse.Namespace, progress: Progress,
                 row: Row) -> None:
    """``ffs transfer SOURCE DEFORMED TARGET``: TARGET deformed as SOURCE was."""
    (source, deformed, target), faces = _shapes(item, args)
    result = backend.transfer(source, deformed, target, faces, progress=progress,
                              **_shape_options(args))
    _write_mesh_result(item, args, row, result.vertices, result.faces, result.report)


def run_convert(backend: Any, item: Item, args: argparse.Namespace, progress: Progress,
                row: Row) -> None:
    """``ffs convert``: read, check and write a mesh (formats from the extensions)."""
    from ffs import files

    vertices, faces = files.read_mesh(item.inputs[0], args.input_format)
    mesh = backend.mesh(vertices, faces, progress=progress)
    out = Path(item.outputs[0])
    files.write_mesh(out, _output_format(out, args), mesh.vertices, mesh.faces, mesh.report)
    row.faces, row.report = len(mesh.faces), mesh.report
    row.note = f"{len(mesh.vertices)} vertices"


RUNNERS: dict[str, Callable[[Any, Item, argparse.Namespace, Progress, Row], None]] = {
    name: globals()[f"run_{name}"] for name in COMMANDS}
"""Command name -> its runner (``run_<command>``, one per row of
:data:`ffs.operations.COMMANDS`)."""
