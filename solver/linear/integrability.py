"""The discrete integrability condition (Sec. 2.3): local (Eq. 4) and global holonomy.

Local: around every interior vertex, the transition rotations of the counter-clockwise loop of
faces multiply to the identity. The rotation angle of that product is the vertex defect; it
splits into a twist about the normal (Gauss's equation: intrinsic vs. extrinsic curvature) and
a tilt of the normal (the Codazzi equations).

Global: on a surface with handles or holes, loops that do not bound a disk need checking too
(the paper's global theorem). Tree-cotree decompositions give a homology basis:

* rotation holonomy along dual generator loops: a primal spanning tree (with all boundary
  vertices joined to one virtual root) and a dual spanning tree of the remaining interior
  edges; each interior edge in neither tree closes one dual loop (2 g + b - 1 of them);
* translation holonomy along primal generator loops: a dual spanning tree first, then a
  primal spanning tree of the remaining edges; each edge in neither closes one primal loop.
  Frames follow the transition rotations along the dual tree ("following the rotated
  frames"); the translation accumulated around the loop must vanish.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike

from ..core.errors import ConstraintError
from ..core.serialization import JsonDataclass
from ..mesh.forms import validate_forms, wrapped_angle_count
from ..mesh.frames import (
    face_edge_lengths,
    transition_rotations,
    triangle_inequality_violations,
)
from ..mesh.manifold import ManifoldCut
from ..mesh.rotations import (
    quaternion_angles,
    quaternion_multiply,
    rotation_angle,
)
from ..mesh.topology import MeshTopology, corner_successor, previous_halfedge
from ..mesh.trees import spanning_forest
from .system import EnergyTerms, energy_terms
from .tree_integration import (
    edge_vectors,
    integrate_along_forests,
    integration_forests,
    links_to_inner,
    tree_frames,
)

WORST_COUNT = 10
"""How many of the largest vertex defects a report lists (``worst_vertices``), and of
each kind's largest holonomy loops its summary lists (:meth:`IntegrabilityReport.summary`;
a mesh of thousands of open parts has a loop per part)."""


@dataclass
class HolonomyLoop(JsonDataclass):
    """One homology generator and the holonomy measured along it.

    Attributes:
        kind: "rotation" (a dual loop of faces) or "translation" (a primal loop of edges).
        component: connected component of the loop.
        edge: [i, j], the edge that closes the loop (in neither spanning tree).
        edge_index: row of that edge in the sorted edge list.
        faces: the faces on either side of that edge (-1 for none).
        angle: rotation angle (radians) of the accumulated rotation (rotation loops).
        translation: [x, y, z] accumulated translation in the root face's frame
            (translation loops; its length is ``magnitude``).
        magnitude: ``angle`` for rotation loops, the length of ``translation`` divided by the
            mean edge length for translation loops.
        passes: magnitude <= tolerance.
    """

    kind: str
    component: int
    edge: list[int]
    faces: list[int]
    edge_index: int = -1
    angle: float = 0.0
    translation: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    magnitude: float = 0.0
    passes: bool = True


@dataclass
class IntegrabilityReport(JsonDataclass):
    """Result of :func:`check_integrability` (n vertices).

    Attributes:
        integrable: every check passes (local, triangle inequality, global).
        max_defect: largest vertex defect or global rotation holonomy (radians), or relative
            translation holonomy.
        tolerance: the tolerance used.
        vertex_defect: (n,) rotation angle of the holonomy around each interior vertex (Eq. 4);
            0 on boundary and isolated vertices.
        gauss_defect: (n,) signed rotation of that holonomy about the normal (Gauss part).
        codazzi_defect: (n,) tilt of the normal by that holonomy (Codazzi part).
        failing_vertices: vertices whose defect exceeds the tolerance.
        worst_vertices: up to 10 vertices with the largest defects, largest first.
        triangle_violations: faces whose lengths violate the triangle inequality.
        components: per component: vertices, edges, faces, boundary_loops,
            euler_characteristic, genus, closed.
        n_components, euler_characteristic, genus: totals over components with faces.
        boundary_loops: vertex loops of the boundary, in boundary order.
        isolated_vertices: vertices that no face uses.
        rotation_holonomy, translation_holonomy: the global generator loops.
        local_integrable, global_integrable: the two halves of ``integrable``.
        wrapped_angles: angles given outside (-pi, pi] and wrapped into it (an angle is
            periodic; :func:`solver.mesh.forms.wrap_angles`).
    """

    integrable: bool
    max_defect: float
    tolerance: float
    vertex_defect: np.ndarray
    gauss_defect: np.ndarray
    codazzi_defect: np.ndarray
    failing_vertices: np.ndarray
    worst_vertices: np.ndarray
    triangle_violations: np.ndarray
    components: list[dict[str, Any]]
    n_components: int
    euler_characteristic: int
    genus: int
    boundary_loops: list[np.ndarray]
    isolated_vertices: np.ndarray
    rotation_holonomy: list[HolonomyLoop]
    translation_holonomy: list[HolonomyLoop]
    local_integrable: bool
    global_integrable: bool
    wrapped_angles: int = 0

    _array_fields: ClassVar[dict[str, Any]] = {
        "vertex_defect": np.float64, "gauss_defect": np.float64, "codazzi_defect": np.float64,
        "failing_vertices": np.int64, "worst_vertices": np.int64,
        "triangle_violations": np.int64, "isolated_vertices": np.int64,
    }
    _nested_fields: ClassVar[dict[str, Any]] = {
        "rotation_holonomy": HolonomyLoop, "translation_holonomy": HolonomyLoop,
    }

    def summary(self) -> dict[str, Any]:
        """The short form used in reconstruction reports.

        Returns:
            JSON-ready dict without per-vertex arrays: the verdicts, ``max_defect``,
            ``tolerance``, the worst vertices with their defects, the count of failing
            vertices, triangle violations, genus, component count, and of the global loops
            the :data:`WORST_COUNT` largest of each kind (``rotation_holonomy``,
            ``translation_holonomy``, largest magnitude first) with the counts of all
            (``rotation_loop_count``, ``translation_loop_count``, ``failing_loop_count``;
            the full report lists every loop).
        """
        loops = self.rotation_holonomy + self.translation_holonomy
        return {
            "integrable": self.integrable, "local_integrable": self.local_integrable,
            "global_integrable": self.global_integrable, "max_defect": self.max_defect,
            "tolerance": self.tolerance,
            "worst_vertices": [{"vertex": int(v), "defect": float(self.vertex_defect[v])}
                               for v in self.worst_vertices],
            "failing_vertex_count": len(self.failing_vertices),
            "triangle_violations": self.triangle_violations.tolist(),
            "genus": self.genus, "n_components": self.n_components,
            "rotation_holonomy": _largest_loops(self.rotation_holonomy),
            "translation_holonomy": _largest_loops(self.translation_holonomy),
            "rotation_loop_count": len(self.rotation_holonomy),
            "translation_loop_count": len(self.translation_holonomy),
            "failing_loop_count": sum(not g.passes for g in loops),
        }


def _largest_loops(loops: list[HolonomyLoop]) -> list[dict[str, Any]]:
    """The :data:`WORST_COUNT` loops of largest magnitude, largest first (ties in order), as
    dicts."""
    largest = heapq.nlargest(WORST_COUNT, enumerate(loops),
                             key=lambda item: (item[1].magnitude, -item[0]))
    return [loop.to_dict() for _, loop in largest]


def check_integrability(faces: ArrayLike, edges: ArrayLike, lengths: ArrayLike,
                        angles: ArrayLike, tol: float = 1e-8,
                        n_vertices: int | None = None,
                        vertex_map: ArrayLike | None = None,
                        weld_map: ArrayLike | None = None) -> IntegrabilityReport:
    """Check whether edge lengths and dihedral angles come from an immersion.

    Args:
        faces: (m, 3) int, counter-clockwise.
        edges: (E, 2) int, the faces' edges (i < j, sorted).
        lengths: (E,) positive edge lengths.
        angles: (E,) signed dihedral angles in (-pi, pi].
        tol: tolerance on defects (radians) and on translation holonomy (relative to the mean
            edge length).
        n_vertices: vertex count (default ``faces.max() + 1``; the file's with
            ``vertex_map``).
        vertex_map: the forms' (n_cut,) file vertex of each vertex of ``faces`` (forms of a
            non-manifold mesh, :mod:`solver.mesh.manifold`): the per-vertex defects are then given
            per file vertex (the copy of largest defect).
        weld_map: the forms' (n,) file vertex each file vertex was welded into
            (:mod:`solver.mesh.weld`; with ``vertex_map``): a welded vertex reports its
            representative's defects.

    Returns:
        :class:`IntegrabilityReport`. Faces violating the triangle inequality are listed in
        ``triangle_violations`` and their vertices are excluded from the rotation check.

    Raises:
        SolverInputError: a subclass naming the first malformed element
            (:func:`solver.mesh.forms.validate_forms`).

    Example:
        The forms of an embedded mesh integrate; bending one edge breaks Eq. (4) at its
        two end vertices:

        >>> import numpy as np
        >>> from solver import fundamental_forms
        >>> from solver.linear.integrability import check_integrability
        >>> corners = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
        >>> forms = fundamental_forms(corners, [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
        >>> report = check_integrability(forms.faces, forms.edges, forms.lengths, forms.angles)
        >>> report.integrable, report.genus, report.max_defect < 1e-12
        (True, 0, True)
        >>> bent = forms.angles + np.array([0.1, 0, 0, 0, 0, 0])
        >>> check_integrability(forms.faces, forms.edges, forms.lengths, bent
        ...                     ).failing_vertices.tolist()
        [0, 1]
    """
    cut = None
    if vertex_map is not None:
        cut = ManifoldCut.from_vertex_map(vertex_map, faces, n_vertices, weld_map)
        n_vertices = cut.n_vertices
    elif weld_map is not None:
        raise ConstraintError("weld_map needs the forms' vertex_map", field="weld_map")
    topology, L, A = validate_forms(faces, edges, lengths, angles, n_vertices)
    violations = triangle_inequality_violations(face_edge_lengths(topology, L))
    terms = energy_terms(topology, L, A, check=False)
    report = integrability_from_terms(terms, tol, mean_length=float(L.mean()),
                                      violations=violations)
    report.wrapped_angles = wrapped_angle_count(angles)
    if cut is not None and not cut.is_identity:
        report.vertex_defect, report.gauss_defect, report.codazzi_defect = (
            cut.largest_to_file(values) for values in
            (report.vertex_defect, report.gauss_defect, report.codazzi_defect))
        report.failing_vertices = np.flatnonzero(report.vertex_defect > tol)
        worst = np.argsort(-report.vertex_defect, kind="stable")[:WORST_COUNT]
        report.worst_vertices = worst[report.vertex_defect[worst] > 0]
        used = np.zeros(cut.n_file_vertices, dtype=bool)
        used[cut.vertex_map[topology.faces.ravel()]] = True
        report.isolated_vertices = np.flatnonzero(
            ~(used if cut.weld_map is None else used[cut.weld_map]))
    return report


def integrability_from_terms(terms: EnergyTerms, tol: float, mean_length: float,
                             violations: np.ndarray | None = None,
                             length_unit: float = 1.0) -> IntegrabilityReport:
    """:func:`check_integrability` on precomputed layouts and transition rotations.

    Args:
        terms: the forms' layouts and transition rotations
            (:func:`solver.linear.system.energy_terms`).
        tol: tolerance on defects (radians) and relative translation holonomy.
        mean_length: the mean edge length in the units of ``terms``.
        violations: (k,) int64 faces that violate the triangle inequality: their vertices
            are excluded from the vertex check (their defect is reported as 0), and the
            report is then not integrable.
        length_unit: converts the units of ``terms`` back to the caller's (translations are
            reported in the caller's units).

    Returns:
        :class:`IntegrabilityReport`.
    """
    violations = np.zeros(0, np.int64) if violations is None else violations
    topo = terms.topology
    holonomy = vertex_holonomy(terms)
    interior = _interior_vertices(topo)
    defect = np.zeros(topo.n_vertices)
    gauss = np.zeros(topo.n_vertices)
    codazzi = np.zeros(topo.n_vertices)
    defect[interior], gauss[interior], codazzi[interior] = quaternion_angles(holonomy)
    for values in (defect, gauss, codazzi):
        values[topo.faces[violations].ravel()] = 0.0

    rotation_loops, translation_loops = global_holonomy(terms, tol, mean_length, length_unit)
    global_ok = all(g.passes for g in rotation_loops + translation_loops)
    global_max = max([g.magnitude for g in rotation_loops + translation_loops], default=0.0)
    local_max = float(defect.max()) if len(defect) else 0.0
    local_ok = local_max <= tol
    return _assemble_report(topo, defect, gauss, codazzi, violations, tol,
                            rotation_loops, translation_loops, local_ok, global_ok,
                            max(local_max, global_max))


def _interior_vertices(topology: MeshTopology) -> np.ndarray:
    """(k,) int64 vertices used by faces and not on the boundary."""
    return np.flatnonzero(topology.is_referenced & ~topology.is_boundary_vertex)


def vertex_holonomy(terms: EnergyTerms) -> np.ndarray:
    """The transition rotations multiplied around each interior vertex (Eq. 4).

    The loop starts at the vertex's first corner (smallest half-edge leaving it) and goes
    counter-clockwise; the product is expressed in that face's frame (its z axis is the
    normal). All vertices walk their rings at once, one vectorized quaternion product per
    ring position, the vertices sorted by valence so that those still walking are a prefix
    (slices, no index lists): O(H) products in all, in as many steps as the largest valence.

    Args:
        terms: layouts and transition rotations (:func:`solver.linear.system.energy_terms`).

    Returns:
        (k, 4) float64 unit quaternions, one per interior vertex in increasing vertex
        order; +-(1, 0, 0, 0) where the forms integrate.

    Example:
        >>> import numpy as np
        >>> from solver import fundamental_forms
        >>> from solver.linear.integrability import vertex_holonomy
        >>> from solver.linear.system import energy_terms
        >>> from solver.mesh.topology import build_topology
        >>> corners = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
        >>> topology = build_topology([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
        >>> forms = fundamental_forms(corners, topology.faces)
        >>> holonomy = vertex_holonomy(energy_terms(topology, forms.lengths, forms.angles))
        >>> holonomy.shape, bool(np.allclose(np.abs(holonomy[:, 0]), 1.0))
        ((4, 4), True)
    """
    topo = terms.topology
    interior = _interior_vertices(topo)
    if not len(interior):
        return np.zeros((0, 4))
    H = 3 * topo.n_faces
    origin = topo.halfedge_origin
    index = np.int32 if np.iinfo(np.int32).max > H else np.int64
    first = np.full(topo.n_vertices, H, dtype=index)
    np.minimum.at(first, origin, np.arange(H, dtype=index))
    count = np.bincount(origin, minlength=topo.n_vertices)[interior]
    by_valence = np.argsort(-count, kind="stable")
    count = count[by_valence]
    corner = first[interior[by_valence]]
    successor = corner_successor(topo.halfedge_twin).astype(index)
    # Transition of the step out of corner c: across the half-edge before it, from c's face
    # to the next one; +-(1 + interior edge position): + where that half-edge runs i -> j
    # (R_LR), - where it runs j -> i (R_RL = R_LR^T, the conjugate quaternion).
    slot = np.zeros(topo.n_edges, dtype=index)
    slot[terms.interior_edges] = np.arange(1, len(terms.interior_edges) + 1, dtype=index)
    signed = slot[topo.halfedge_edge]
    np.negative(signed, out=signed, where=origin > topo.halfedge_dest)
    quaternions = terms.quaternions
    result = _ring_step(quaternions, signed, corner)
    walking = np.searchsorted(-count, -np.arange(int(count[0]) + 1), side="left")
    for r in range(1, int(count[0])):  # the vertices of valence > r are the first walking[r]
        active = slice(0, int(walking[r]))
        corner[active] = successor[corner[active]]
        result[active] = quaternion_multiply(result[active],
                                             _ring_step(quaternions, signed, corner[active]))
    holonomy = np.empty_like(result)
    holonomy[by_valence] = result
    return holonomy


def _ring_step(quaternions: np.ndarray, signed: np.ndarray, corners: np.ndarray,
               ) -> np.ndarray:
    """(c, 4) transition quaternions of the ring steps out of ``corners`` (c,) (see
    :func:`vertex_holonomy`: ``signed`` is +-(1 + interior edge position) per half-edge)."""
    edge = signed[previous_halfedge(corners)]
    q = np.take(quaternions, np.abs(edge) - 1, axis=0)
    q[:, 1:] *= np.where(edge < 0, -1.0, 1.0)[:, None]
    return q


def homology_rank(topology: MeshTopology) -> np.ndarray:
    """The number of independent loops (generators of the first homology) of each component
    with faces: ``2 g + b - 1`` with ``b > 0`` boundary loops, ``2 g`` when closed; i.e.
    ``1 - chi`` or ``2 - chi`` from the Euler characteristic chi.

    Args:
        topology: a validated (manifold) mesh.

    Returns:
        (C,) int64, 0 for components without faces.

    Example:
        A closed tetrahedron has none:

        >>> from solver.mesh.topology import build_topology
        >>> homology_rank(build_topology([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])).tolist()
        [0]
    """
    C = topology.n_components
    v = np.bincount(topology.vertex_component[topology.is_referenced], minlength=C)
    e = np.bincount(topology.vertex_component[topology.edges[:, 0]], minlength=C)
    f = np.bincount(topology.face_component, minlength=C)
    b = np.bincount(topology.boundary_loop_component, minlength=C)
    chi = v - e + f
    rank = np.where(b > 0, 1 - chi, 2 - chi)
    return np.where(f > 0, rank, 0).astype(np.int64)


def global_holonomy(terms: EnergyTerms, tol: float, mean_length: float,
                    length_unit: float = 1.0) -> tuple[list[HolonomyLoop], list[HolonomyLoop]]:
    """Rotation holonomy of the dual generators and translation holonomy of the primal ones.

    Args:
        terms: layouts and transition rotations (:func:`solver.linear.system.energy_terms`).
        tol: tolerance of each loop's magnitude.
        mean_length: mean edge length in the units of ``terms`` (translations are divided
            by it).
        length_unit: converts the units of ``terms`` back to the caller's.

    Returns:
        ``(rotation_loops, translation_loops)``: one :class:`HolonomyLoop` per generator
        (2 g + b - 1 dual loops; the primal loops of the edges in neither forest).
    """
    topo = terms.topology
    if not len(topo.boundary_loops) and not homology_rank(topo).any():
        return [], []  # closed, genus 0: no loop of either kind (no forest to build)
    n, m = topo.n_vertices, topo.n_faces
    inner = terms.interior_edges
    dual_links = topo.edge_faces[inner]
    edge_is_inner = np.zeros(topo.n_edges, dtype=bool)
    edge_is_inner[inner] = True

    # Rotation generators: primal tree (boundary joined to a virtual vertex n) then cotree.
    boundary_vertices = np.flatnonzero(topo.is_boundary_vertex)
    virtual = np.stack([np.full(len(boundary_vertices), n), boundary_vertices], axis=1)
    primal = spanning_forest(n + 1, np.concatenate([topo.edges, virtual]),
                             roots=np.array([n]) if len(boundary_vertices) else None)
    primal_tree_edges = primal.in_tree[: topo.n_edges]
    cotree_mask = ~primal_tree_edges[inner]
    cotree = spanning_forest(m, dual_links[cotree_mask])
    in_cotree = np.zeros(len(inner), dtype=bool)
    in_cotree[np.flatnonzero(cotree_mask)[cotree.in_tree]] = True
    generators = np.flatnonzero(~in_cotree & ~primal_tree_edges[inner])
    left, right = dual_links[generators].T
    angles = np.zeros(0)
    if len(generators):  # genus 0 without holes has none: skip the frame integration
        frames = tree_frames(terms, cotree.parent, links_to_inner(cotree, cotree_mask),
                              cotree.levels)
        hol = (frames[left] @ transition_rotations(terms.transition[generators])
               @ np.swapaxes(frames[right], 1, 2))
        angles = rotation_angle(hol)
    # Columns converted to Python lists once (a mesh of many open parts has a loop per part).
    rotation_loops = [
        HolonomyLoop(kind="rotation", component=c, edge=edge, faces=[lf, rf], edge_index=e,
                     angle=a, magnitude=a, passes=a <= tol)
        for c, edge, lf, rf, e, a in zip(
            topo.face_component[left].tolist(), topo.edges[inner[generators]].tolist(),
            left.tolist(), right.tolist(), inner[generators].tolist(), angles.tolist(),
            strict=True)]

    # Translation generators: dual tree first, then a primal tree of the remaining edges.
    forests = integration_forests(terms)
    rest, tree = forests.rest, forests.primal
    if tree.in_tree.all():
        return rotation_loops, []
    frames, positions = integrate_along_forests(terms, forests)
    closing = rest[~tree.in_tree]
    i, j = topo.edges[closing].T
    gaps = positions[i] + edge_vectors(terms, frames, closing) - positions[j]
    sizes = np.linalg.norm(gaps, axis=1) / mean_length
    translation_loops = [
        HolonomyLoop(kind="translation", component=c, edge=edge, faces=faces, edge_index=e,
                     translation=gap, magnitude=s, passes=s <= tol)
        for c, edge, faces, e, gap, s in zip(
            topo.vertex_component[i].tolist(), topo.edges[closing].tolist(),
            topo.edge_faces[closing].tolist(), closing.tolist(),
            (gaps * length_unit).tolist(), sizes.tolist(), strict=True)]
    return rotation_loops, translation_loops


def _largest(values: np.ndarray, count: int) -> np.ndarray:
    """(<= count,) int64 indices of the largest positive ``values`` (n,), largest first, ties
    in index order: ``np.argsort(-values, kind="stable")[:count]`` without sorting all n
    (a partition finds the count-th largest value; only those at least as large are
    sorted)."""
    if len(values) > count:
        threshold = np.partition(values, len(values) - count)[len(values) - count]
        candidates = np.flatnonzero(values >= threshold)
    else:
        candidates = np.arange(len(values))
    chosen = candidates[np.argsort(-values[candidates], kind="stable")[:count]]
    return chosen[values[chosen] > 0]


def _assemble_report(topo: MeshTopology, defect: np.ndarray, gauss: np.ndarray,
                     codazzi: np.ndarray, violations: np.ndarray, tol: float,
                     rotation_loops: list[HolonomyLoop], translation_loops: list[HolonomyLoop],
                     local_ok: bool, global_ok: bool, max_defect: float,
                     ) -> IntegrabilityReport:
    """The :class:`IntegrabilityReport` of measured defects and loops."""
    components = topo.component_summary()
    worst = _largest(defect, WORST_COUNT)
    return IntegrabilityReport(
        integrable=bool(local_ok and global_ok and len(violations) == 0),
        max_defect=float(max_defect), tolerance=float(tol), vertex_defect=defect,
        gauss_defect=gauss, codazzi_defect=codazzi,
        failing_vertices=np.flatnonzero(defect > tol), worst_vertices=worst,
        triangle_violations=violations, components=components,
        n_components=len(components),
        euler_characteristic=int(sum(c["euler_characteristic"] for c in components)),
        genus=int(sum(c["genus"] for c in components)), boundary_loops=topo.boundary_loops,
        isolated_vertices=topo.isolated_vertices, rotation_holonomy=rotation_loops,
        translation_holonomy=translation_loops, local_integrable=bool(local_ok),
        global_integrable=bool(global_ok))
