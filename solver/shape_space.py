"""Shape space: blends of K shapes of one connectivity in form space, means and transfer.

Beyond the paper (which cites [WDAH10] for blending forms and names deformation transfer as
future work). K shapes with the same faces give K sets of fundamental forms; a row of
affine weights ``w`` (K,), ``sum w = 1`` (negative weights extrapolate) blends them::

    log L(w) = sum_k w_k log L_k          lengths in log space: positive under extrapolation
    Theta(w) = wrap(sum_k w_k Theta~_k)    Theta~_k = Theta_0 + wrap(Theta_k - Theta_0)

(each shape's angles unwrapped against the first shape's, so that a fin near pi does not
average to 0). Each row's answer is the surface nearest to the blended forms
(:mod:`solver.refine`; blended forms of different poses do not integrate), rigidly aligned
(rotation + translation, Kabsch) to the vertex blend ``sum_k w_k V_k`` of the shapes as
given, so that it sits where a user expects it. :func:`mean` is the equal-weight row;
:func:`transfer` is the row ``(1, -1, 1)`` over ``(target, source, source_deformed)``: the
target's forms plus the source's change, ``log L_B' = log L_B + log L_A' - log L_A``.

A sequence of rows (``options.sequence``, the default) is solved as a session's drags are
(:class:`solver.deform.Deformer`): the rows run in order, a row whose weights are one-hot
(a given shape) and the first row are reconstructed on their own (Eq. 5, then refined),
every other row starts from the better of its neighbour's answer and its vertex blend, and
keeps the Gauss-Newton factor of the rows before (:meth:`solver.refine.Refiner.run` with
``keep_factor``; its symbolic analysis is computed once and cached per pattern).
``sequence=False`` reconstructs every row on its own.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from .core.budget import Budget
from .core.errors import ShapeMismatchError, TriangleInequalityError
from .core.validation import as_points
from .core.warnings import AnswerWarning, as_report, residual_warnings, time_limit_warning
from .mesh.forms import Forms, fundamental_forms
from .mesh.frames import face_edge_lengths, triangle_inequality_violations
from .mesh.manifold import ManifoldCut, manifold_topology
from .mesh.metrics import wrap_angle
from .mesh.placement import align_components
from .mesh.topology import MeshTopology, build_topology
from .options import BlendOptions, ReconstructOptions
from .reconstruct import reconstruct
from .refine.form_energy import FormTargets, form_residuals
from .refine.refiner import Refiner
from .reports import Progress, Stages

WEIGHT_SUM_TOLERANCE = 1e-9
"""Largest ``|sum_k w_k - 1|`` of a row of weights (affine combinations only)."""
MAX_SHAPES = 64
"""Most shapes one blend takes."""
EXTRAPOLATED_ROWS = 3
"""Previous answers a sequence row's start extrapolates (quadratically) from."""
SMOOTH_TURN = 0.9
"""Smallest cosine between consecutive steps of rows in weight space for the rows to count
as a smooth path (:func:`path_extrapolation`)."""
SMOOTH_SPACING = 2.0
"""Largest ratio of consecutive steps' lengths in weight space on a smooth path."""


@dataclass(frozen=True)
class ShapeSet:
    """K shapes of one connectivity, as what a blend combines.

    Attributes:
        topology: the shared connectivity (n vertices, m faces, E edges).
        log_lengths: (K, E) float64 logarithms of the edge lengths.
        angles: (K, E) float64 dihedral angles, shape 0's in (-pi, pi], the others
            unwrapped against it (``Theta_0 + wrap(Theta_k - Theta_0)``).
        vertices: (K, n, 3) float64 embeddings, or None where the shapes were given as forms.
    """

    topology: MeshTopology
    log_lengths: np.ndarray
    angles: np.ndarray
    vertices: np.ndarray | None

    @property
    def count(self) -> int:
        """K, the number of shapes."""
        return len(self.log_lengths)

    def forms(self, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Blended lengths and angles, each (T, E) float64, of weights (T, K)."""
        return np.exp(weights @ self.log_lengths), wrap_angle(weights @ self.angles)

    def arithmetic_lengths(self, row: np.ndarray) -> np.ndarray:
        """``sum_k w_k L_k`` (E,) of one row (K,): for a convex row (weights >= 0) these
        lengths satisfy every triangle inequality the shapes do, which the log-space blend
        of nearly degenerate faces may not (Hoelder's inequality runs the other way)."""
        return row @ np.exp(self.log_lengths)

    def vertex_blend(self, row: np.ndarray) -> np.ndarray | None:
        """``sum_k w_k V_k`` (n, 3) of one row of weights (K,); None without vertices."""
        if self.vertices is None:
            return None
        return np.einsum("k,kvc->vc", row, self.vertices)


def shape_set(shapes: Sequence[Any] | np.ndarray, faces: ArrayLike | None = None) -> ShapeSet:
    """The :class:`ShapeSet` of ``shapes``: K embeddings (n, 3) of ``faces`` (or a (K, n, 3)
    array), or K :class:`solver.mesh.forms.Forms` of one connectivity (``faces`` then unused).

    Raises:
        ShapeMismatchError: fewer than one or more than :data:`MAX_SHAPES` shapes, shapes of
            different sizes or connectivities (``shapes[k]``), or embeddings without faces.

    Example:
        >>> import numpy as np
        >>> V = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.2]])
        >>> shapes = shape_set([V, 2 * V], [[0, 1, 2], [2, 1, 3]])
        >>> shapes.count, shapes.log_lengths.shape, bool(np.allclose(
        ...     shapes.log_lengths[1] - shapes.log_lengths[0], np.log(2)))
        (2, (2, 5), True)
    """
    items = list(shapes)
    if not 1 <= len(items) <= MAX_SHAPES:
        raise ShapeMismatchError(f"a blend takes 1 to {MAX_SHAPES} shapes, got {len(items)}",
                                 field="shapes")
    if all(isinstance(item, Forms) for item in items):
        return _from_forms(items)
    if faces is None:
        raise ShapeMismatchError("shapes given as vertices need their faces", field="faces")
    first = as_points(items[0], "shapes[0]")
    topology = build_topology(np.asarray(faces), n_vertices=len(first))
    vertices = np.empty((len(items), len(first), 3))
    vertices[0] = first
    for k, item in enumerate(items[1:], start=1):  # a loop over shapes, not mesh elements
        points = as_points(item, f"shapes[{k}]")
        if points.shape != first.shape:
            raise ShapeMismatchError(f"shapes[{k}] has shape {points.shape}, shapes[0] "
                                     f"{first.shape}", field=f"shapes[{k}]")
        vertices[k] = points
    # The connectivity is the first shape's (welded by _cut): no shape welds on its own.
    forms = [fundamental_forms(v, topology.faces, coincident=False) for v in vertices]
    return _stacked(topology, [f.lengths for f in forms], [f.angles for f in forms], vertices)


def _from_forms(items: list[Forms]) -> ShapeSet:
    """The :class:`ShapeSet` of K forms with one connectivity (no vertices)."""
    from .mesh.forms import validate_forms

    first = items[0]
    topology, _, _ = validate_forms(first.faces, first.edges, first.lengths, first.angles)
    lengths, angles = [], []
    for k, item in enumerate(items):
        if (np.shape(item.faces) != topology.faces.shape
                or not np.array_equal(item.faces, topology.faces)):
            raise ShapeMismatchError(f"shapes[{k}] has other faces than shapes[0]",
                                     field=f"shapes[{k}].faces")
        _, L, A = validate_forms(item.faces, item.edges, item.lengths, item.angles,
                                 topology.n_vertices)
        lengths.append(L)
        angles.append(A)
    return _stacked(topology, lengths, angles, None)


def _stacked(topology: MeshTopology, lengths: list[np.ndarray], angles: list[np.ndarray],
             vertices: np.ndarray | None) -> ShapeSet:
    A = np.stack(angles)
    A[1:] = A[0] + wrap_angle(A[1:] - A[0])
    return ShapeSet(topology, np.log(np.stack(lengths)), A, vertices)


def affine_weights(weights: ArrayLike, count: int) -> np.ndarray:
    """Rows of affine weights (T, K) float64 from ``weights`` (K,) or (T, K).

    Raises:
        ShapeMismatchError: a wrong shape, a value that is not finite, or a row whose sum is
            not 1 (``weights[t]``).
    """
    W = np.asarray(weights, dtype=np.float64)
    if W.ndim == 1:
        W = W[None]
    if W.ndim != 2 or W.shape[1] != count or not len(W):
        raise ShapeMismatchError(f"weights must have shape (T, {count}), got "
                                 f"{np.shape(weights)}", field="weights")
    finite = np.isfinite(W).all(axis=1)
    if not finite.all():
        row = int(np.flatnonzero(~finite)[0])
        raise ShapeMismatchError(f"weights[{row}] is not finite", field="weights", index=row)
    off = np.abs(W.sum(axis=1) - 1.0) > WEIGHT_SUM_TOLERANCE
    if off.any():
        row = int(np.flatnonzero(off)[0])
        raise ShapeMismatchError(f"the row sums to {W[row].sum()!r}, not 1 (blends are "
                                 "affine: negative weights extrapolate)", field="weights",
                                 index=row)
    return W


def aligned(source: np.ndarray, target: np.ndarray, topology: MeshTopology) -> np.ndarray:
    """``source`` (n, 3) with each connected part moved rigidly onto the same vertices of
    ``target`` (n, 3) (:func:`solver.mesh.placement.align_components`): a multi-part blend keeps
    every part where its vertex blend puts it."""
    return align_components(source, target, topology.vertex_component)


@dataclass
class Blend:
    """Result of :func:`blend`.

    Attributes:
        vertices: (T, n, 3) float64, one shape per row of weights.
        faces: (m, 3) int64.
        weights: (T, K) float64 the rows.
        reports: one dict per row: ``row``, ``path`` (``"reconstruct"``: Eq. 5 then the
            refinement; ``"sequence"``: refined from the neighbour's answer with the kept
            factor), ``length_blend`` (``"log"``, or ``"arithmetic"`` for a convex row
            whose log-space lengths violate a triangle inequality of a nearly degenerate
            face: :meth:`ShapeSet.arithmetic_lengths`), ``refinement``
            (:class:`solver.refine.Refinement`'s report, its ``start``), ``form_error``
            (:func:`solver.refine.form_energy.form_residuals` of the answer against the row's
            blended forms), ``warnings`` (:func:`row_warnings`) and ``seconds``.
        timings: stage -> seconds (``validate``, ``rows``).
    """

    vertices: np.ndarray
    faces: np.ndarray
    weights: np.ndarray
    reports: list[dict[str, Any]] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def warnings(self) -> list[dict[str, Any]]:
        """Every row's ``warnings``, each with its ``row`` (index into the rows)."""
        return [{**found, "row": report["row"]} for report in self.reports
                for found in report.get("warnings", [])]


def row_warnings(report: dict[str, Any]) -> list[AnswerWarning | None]:
    """The warnings of one row's report (:mod:`solver.core.warnings`, the thresholds every
    operation uses): the largest length and dihedral-angle errors its answer leaves against
    the row's blended forms (``form_error``; blended forms of different poses do not
    integrate, so a row past them is a blend the shapes cannot make nearly isometrically,
    e.g. an extrapolation too far), and a time limit that ran out before any progress."""
    residual = report["form_error"]
    return [*residual_warnings(residual["length_error"]["max"],
                               residual["angle_error"]["max"]),
            time_limit_warning(report["refinement"])]


class _Rows:
    """Solves the rows of one blend in order (see the module docstring)."""

    def __init__(self, shapes: ShapeSet, opts: BlendOptions) -> None:
        self.shapes = shapes
        self.opts = opts
        self.answers: list[np.ndarray] = []      # the last three rows' aligned answers
        self.blends: list[np.ndarray | None] = []  # the last two rows' vertex blends
        self.rows: list[np.ndarray] = []          # ... and their weights
        self.refiner: Refiner | None = None       # the last sequence row's refiner

    def solve(self, index: int, row: np.ndarray, lengths: np.ndarray, angles: np.ndarray,
              budget: Budget) -> tuple[np.ndarray, dict[str, Any]]:
        """Vertices (n, 3), aligned to the row's vertex blend, and the row's report, within
        ``budget``."""
        shapes, topology = self.shapes, self.shapes.topology
        length_blend = "log"
        bad = _violations(topology, lengths)
        if len(bad) and row.min() >= 0:
            lengths, length_blend = shapes.arithmetic_lengths(row), "arithmetic"
            bad = _violations(topology, lengths)
        if len(bad):
            raise TriangleInequalityError(
                f"the blended lengths of weights[{index}] violate the triangle inequality at "
                f"face {int(bad[0])} ({len(bad)} faces): extrapolate less", field="weights",
                index=index)
        guess = shapes.vertex_blend(row)
        one_hot = np.count_nonzero(row) == 1
        if not self.answers or one_hot or not self.opts.sequence or not self._refines():
            path = "reconstruct"
            rec = reconstruct(topology.faces, topology.edges, lengths, angles,
                              n_vertices=topology.n_vertices, initial_guess=guess,
                              options=ReconstructOptions.given(self.opts, {
                                  "check_integrability": False, "max_seconds": budget.left()}))
            vertices, refinement = rec.vertices, dict(rec.report["refinement"])
            if refinement.get("start") == "initial guess":
                refinement["start"] = "vertex blend"
        else:
            path = "sequence"
            vertices, refinement = self._continue(row, lengths, angles, guess, budget)
        after = refinement.get("after") if refinement.get("refined") else None
        residual = after or form_residuals(vertices, topology, lengths, angles)
        if guess is not None:
            vertices = aligned(vertices, guess, topology)
        self.answers = [*self.answers[-EXTRAPOLATED_ROWS + 1:], vertices]
        self.blends = [*self.blends[-1:], guess]
        self.rows = [*self.rows[-EXTRAPOLATED_ROWS + 1:], row]
        return vertices, {"row": index, "path": path, "length_blend": length_blend,
                          "refinement": refinement, "form_error": residual}

    def _starts(self, row: np.ndarray, guess: np.ndarray | None,
                ) -> list[tuple[str, np.ndarray]]:
        """Candidate starts of a sequence row, scored by energy in :meth:`_continue`.

        On a smooth path of rows (:func:`path_extrapolation`: the last steps in weight space
        turn by less than :data:`SMOOTH_TURN` and change length by at most
        :data:`SMOOTH_SPACING` times) with three previous answers, only their quadratic
        extrapolation along the path (not scored: one energy less). Measured: its energy
        exceeds the row's optimum by 1e-5 to 1e-3 of the secant's excess on the bunny and
        bumpy-plane sequences of 100 rows (on bumpy-plane the secant start was even worse
        than the previous answer: consecutive answers of a nearly flat sheet differ along
        its soft bending modes, which a linear extrapolation doubles), and most rows then
        converge on one quasi-Newton step of the kept factor (rocker-arm: 1.5 solves per
        row instead of 2.6). Otherwise the previous answer moved by what the vertex blend
        moved (as a session's next drag starts) and the secant of the two previous answers
        where the last two steps are smooth, or the previous answer and the vertex blend."""
        previous = self.answers[-1]
        starts = []
        if guess is not None and self.blends[-1] is not None:
            starts.append(("previous row + vertex-blend motion",
                           previous + (guess - self.blends[-1])))
        coefficients = path_extrapolation([*self.rows, row])
        if coefficients is not None and len(self.answers) >= len(coefficients):
            answers = np.stack(self.answers[-len(coefficients):])
            extrapolated = np.einsum("k,kvc->vc", coefficients, answers)
            if len(coefficients) == EXTRAPOLATED_ROWS:
                return [("quadratic extrapolation of the previous rows", extrapolated)]
            starts.append(("secant of the previous rows", extrapolated))
        if len(starts) < 2:
            starts.append(("previous row", previous))
            if guess is not None:
                starts.append(("vertex blend", guess))
        return starts

    def _refines(self) -> bool:
        return self.opts.refine is not False

    def _continue(self, row: np.ndarray, lengths: np.ndarray, angles: np.ndarray,
                  guess: np.ndarray | None, budget: Budget,
                  ) -> tuple[np.ndarray, dict[str, Any]]:
        """The refinement of a row from the best of :meth:`_starts` (lowest energy), with
        the factor the rows before kept."""
        refiner = self._refiner(FormTargets(self.shapes.topology, lengths, angles,
                                            angle_weight=self.opts.angle_weight))
        starts = self._starts(row, guess)
        energy = None  # one start: the run measures it (with its report) in one pass
        if len(starts) > 1:
            energy, _, label, start = min((refiner.energy(start), k, label, start)
                                          for k, (label, start) in enumerate(starts))
        else:
            (label, start), = starts
        if refiner.reproduces(start):
            return start, {"refined": False, "reason": "exact: the start has the forms",
                           "start": label}
        fit = refiner.run(start, keep_factor=True, interactive=False, time_limit=budget,
                          start_energy=energy)
        return fit.vertices, dict(fit.report, start=label)

    def _refiner(self, targets: FormTargets) -> Refiner:
        """The sequence's refiner with the row's ``targets``: the previous rows' with its
        targets replaced in place (:meth:`Refiner.retarget`: its residual groups, pattern,
        rigid motions and kept factor stay), or, the first time or where the targets'
        structure changed (other cap faces or needle ties), a new one that adopts the
        previous one's factor where the patterns agree."""
        refiner = self.refiner
        if refiner is None or not refiner.retarget(targets):
            refiner = Refiner(targets, backend=self.opts.backend or "auto")
            if self.refiner is not None:
                refiner.adopt_factor(self.refiner)
            self.refiner = refiner
        return refiner


def path_extrapolation(rows: Sequence[np.ndarray]) -> np.ndarray | None:
    """Coefficients (j,) float64, j = 3 or 2, that extrapolate the answers of the last j rows
    before ``rows[-1]`` to it, or None where the rows are no smooth path.

    ``rows``: the weights (K,) of up to :data:`EXTRAPOLATED_ROWS` previous rows and the new
    one, in order. The rows are parameterized by arc length ``s`` in weight space; the
    coefficients are the Lagrange basis of the previous rows' ``s`` evaluated at the new
    row's (quadratic with three previous rows, the secant with two). Quadratic needs the
    last three steps to turn by less than :data:`SMOOTH_TURN` and to change length by at
    most :data:`SMOOTH_SPACING` times; otherwise (or with two previous rows) the secant,
    provided the last two steps are such; a repeated row (a step of length 0) is no path.

    Example:
        >>> import numpy as np
        >>> rows = [np.array([1 - t, t]) for t in (0.0, 0.1, 0.2, 0.3)]
        >>> [round(float(c), 12) for c in path_extrapolation(rows)]
        [1.0, -3.0, 3.0]
    """
    W = np.asarray(rows[-EXTRAPOLATED_ROWS - 1:], dtype=np.float64)
    steps = np.diff(W, axis=0)
    lengths = np.linalg.norm(steps, axis=1)
    if len(lengths) < 2 or lengths.min(initial=np.inf) <= 0:
        return None
    cosines = np.einsum("ij,ij->i", steps[1:], steps[:-1]) / (lengths[1:] * lengths[:-1])
    spacing = np.maximum(lengths[1:] / lengths[:-1], lengths[:-1] / lengths[1:])
    smooth = (cosines >= SMOOTH_TURN) & (spacing <= SMOOTH_SPACING)
    # the smooth turns at the end: 2 (quadratic from three rows), 1 (secant) or none
    count = len(smooth) - (int(np.flatnonzero(~smooth)[-1]) + 1 if (~smooth).any() else 0)
    if count == 0:
        return None
    nodes = np.concatenate([[0.0], np.cumsum(lengths)])[-count - 2:]
    known, new = nodes[:-1], nodes[-1]
    return np.array([np.prod([(new - known[m]) / (known[i] - known[m])
                              for m in range(len(known)) if m != i])
                     for i in range(len(known))])


def _violations(topology: MeshTopology, lengths: np.ndarray) -> np.ndarray:
    """The faces (k,) int64 where lengths (E,) violate the triangle inequality."""
    return triangle_inequality_violations(face_edge_lengths(topology, lengths))


def blend(shapes: Sequence[Any] | np.ndarray, weights: ArrayLike,
          faces: ArrayLike | None = None, *, options: BlendOptions | None = None,
          progress: Progress | None = None, **overrides: Any) -> Blend:
    """Blend K shapes of one connectivity in form space, one shape per row of weights.

    Args:
        shapes: K embeddings (n, 3) of ``faces`` (or a (K, n, 3) array), or K
            :class:`solver.mesh.forms.Forms` of one connectivity (then the answers are not
            aligned: they sit where the reconstruction's anchors put them).
        weights: (K,) or (T, K) affine weights (each row sums to 1; negative weights
            extrapolate).
        faces: (m, 3) int, for shapes given as vertices.
        options: :class:`solver.options.BlendOptions`; ``max_seconds`` budgets the whole
            call, shared out evenly among the rows still to compute.
        progress: optional ``progress("rows", fraction)`` after each row (and the stages of
            the rows that are reconstructed on their own).
        **overrides: fields of ``options`` given as keywords.

    Returns:
        :class:`Blend` with vertices (T, n, 3) and one report per row.

    Example:
        >>> import numpy as np
        >>> from solver import blend
        >>> V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 0.5]])
        >>> F = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
        >>> out = blend([V, V * [1, 1, 2], V * [1, 1, 3]], [[1, 0, 0], [0, 0, 1]], F)
        >>> out.vertices.shape, bool(np.allclose(out.vertices[1], V * [1, 1, 3]))
        ((2, 5, 3), True)
    """
    opts = BlendOptions.given(options, overrides)
    cut = _file_cut(shapes, faces)
    if cut is not None:  # non-manifold or welded: blended on the cut (solver.mesh.manifold)
        return _blend_on_cut(cut, list(shapes), weights, np.asarray(faces), opts, progress)
    return _blend_rows(shapes, weights, faces, opts, progress)


def _blend_rows(shapes: Sequence[Any] | np.ndarray, weights: ArrayLike,
                faces: ArrayLike | None, opts: BlendOptions, progress: Progress | None,
                ) -> Blend:
    """:func:`blend` of shapes whose mesh is taken as it is (a file's mesh that needs no cut,
    or a cut's: its split copies sit at one position and must not be welded again)."""
    stages = Stages(progress)
    stages("validate")
    shape_space = shape_set(shapes, faces)
    if opts.align and shape_space.vertices is not None:
        first = shape_space.vertices[0]
        moved = np.stack([first, *(aligned(v, first, shape_space.topology)
                                  for v in shape_space.vertices[1:])])
        shape_space = ShapeSet(shape_space.topology, shape_space.log_lengths,
                               shape_space.angles, moved)
    W = affine_weights(weights, shape_space.count)
    stages.lap("validate")
    rows = _Rows(shape_space, opts)
    out = np.empty((len(W), shape_space.topology.n_vertices, 3))
    reports = []
    budget = stages.budget(opts.max_seconds)
    for k, row in enumerate(W):  # rows in order: each starts from its neighbour's answer
        lengths, angles = shape_space.forms(row[None])
        share = budget.share(len(W) - k)
        clock = time.perf_counter()
        out[k], report = rows.solve(k, row, lengths[0], angles[0], share)
        report["warnings"] = as_report(row_warnings(report))
        report["seconds"] = time.perf_counter() - clock
        reports.append(report)
        stages("rows", (k + 1) / len(W))
    stages.lap("rows")
    return Blend(vertices=out, faces=shape_space.topology.faces, weights=W, reports=reports,
                 timings=stages.timings)


def _file_cut(shapes: Sequence[Any] | np.ndarray, faces: ArrayLike | None
              ) -> ManifoldCut | None:
    """The manifold cut of shapes given as vertices when the mesh needs one (a non-manifold
    edge or vertex, or vertices joined by zero-length edges in the first shape: welded), else
    None (forms, or a mesh :func:`shape_set` takes as it is)."""
    items = list(shapes)
    if faces is None or not items or any(isinstance(item, Forms) for item in items):
        return None
    cut = manifold_topology(faces, as_points(items[0], "shapes[0]"))[0]
    return None if cut.is_identity else cut


def _blend_on_cut(cut: ManifoldCut, shapes: list[Any], weights: ArrayLike, faces: np.ndarray,
                  opts: BlendOptions, progress: Progress | None) -> Blend:
    """:func:`blend` of the shapes moved onto ``cut``'s vertices, answered in the file's
    numbering: each file vertex at the mean of its copies, the file's ``faces``, and each
    row's report's ``input`` saying what was cut or welded (with the copies' spread)."""
    n = cut.n_file_vertices
    points = [as_points(item, f"shapes[{k}]") for k, item in enumerate(shapes)]
    for k, item in enumerate(points):  # a loop over shapes, not mesh elements
        if item.shape != (n, 3):
            raise ShapeMismatchError(f"shapes[{k}] has shape {item.shape}, shapes[0] "
                                     f"{(n, 3)}", field=f"shapes[{k}]")
    result = _blend_rows([cut.to_cut(item) for item in points], weights, cut.faces, opts,
                         progress)
    vertices = np.empty((len(result.vertices), n, 3))
    for k, row in enumerate(result.vertices):  # a loop over rows
        vertices[k], spread = cut.to_file(row)
        result.reports[k]["input"] = cut.sections(spread)
    return Blend(vertices=vertices, faces=faces.astype(np.int64), weights=result.weights,
                 reports=result.reports, timings=result.timings)


def mean(shapes: Sequence[Any] | np.ndarray, faces: ArrayLike | None = None, *,
         options: BlendOptions | None = None, progress: Progress | None = None,
         return_report: bool = False, **overrides: Any,
         ) -> np.ndarray | tuple[np.ndarray, dict[str, Any]]:
    """The form-space mean (n, 3) of K shapes of one connectivity: the equal-weight blend
    (geometric mean of the lengths, arithmetic mean of the unwrapped angles), nearest
    surface, aligned to the Procrustes vertex mean (``align``: each shape first moved
    rigidly onto the first, so that where the shapes sit does not matter).

    Args:
        shapes, faces, options, progress, overrides: as for :func:`blend`.
        return_report: also return the row's report.

    Example:
        >>> import numpy as np
        >>> from solver import mean
        >>> V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 0.5]])
        >>> F = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
        >>> bool(np.allclose(mean([V, V + 5.0, V], F), V))
        True
    """
    items = list(shapes)
    return _one_row(items, np.full(len(items), 1.0 / max(len(items), 1)), faces, options,
                    progress, return_report, {"align": True, **overrides})


def transfer(source: Any, source_deformed: Any, target: Any, faces: ArrayLike | None = None,
             *, options: BlendOptions | None = None, progress: Progress | None = None,
             return_report: bool = False, **overrides: Any,
             ) -> np.ndarray | tuple[np.ndarray, dict[str, Any]]:
    """Deformation transfer in form space: the target (n, 3) deformed as the source was.

    ``forms(B') = forms(B) + (forms(A') - forms(A))`` (lengths in log space: each edge is
    stretched by the source's ratio; angles bent by the source's change), then the nearest
    surface, aligned to the vertex transfer ``B + A' - A``. It is the blend of ``(target,
    source, source_deformed)`` with weights ``(1, -1, 1)``.

    Args:
        source, source_deformed, target: embeddings (n, 3) of ``faces`` (or forms).
        faces, options, progress, overrides, return_report: as for :func:`mean`.

    Example:
        >>> import numpy as np
        >>> from solver import transfer
        >>> V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 0.5]])
        >>> F = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
        >>> tall = V * [1, 1, 2]
        >>> bool(np.allclose(transfer(V, tall, V, F), tall))
        True
    """
    return _one_row([target, source, source_deformed], [1.0, -1.0, 1.0], faces, options,
                    progress, return_report, overrides)


def _one_row(shapes: list[Any], weights: ArrayLike, faces: ArrayLike | None,
             options: BlendOptions | None, progress: Progress | None, return_report: bool,
             overrides: dict[str, Any]) -> np.ndarray | tuple[np.ndarray, dict[str, Any]]:
    """The one-row :func:`blend` of ``shapes`` by ``weights`` (K,): its vertices (n, 3)
    float64, with its report when ``return_report`` (what :func:`mean` and
    :func:`transfer` answer)."""
    result = blend(shapes, weights, faces, options=options, progress=progress, **overrides)
    return (result.vertices[0], result.reports[0]) if return_report else result.vertices[0]
