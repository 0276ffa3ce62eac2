"""The map from the solver's answer to the answer :func:`solver.reconstruct` returns, and its
vector-Jacobian product (for :func:`solver.differentiable.reconstruct_vjp`).

:func:`solver.reconstruct` solves on the forms' own (cut) mesh in its gauge (each anchored
component's anchor vertex at the origin, its anchor frame the identity), then

1. moves each unconstrained component rigidly so that its anchor face has the placement's
   pose (:func:`solver.mesh.placement.apply_placement`), or, without a placement, lays the
   anchored components out side by side along +x (:func:`solver.mesh.placement.side_by_side`);
2. with a ``vertex_map``, gives each file vertex the mean of its copies and each welded
   vertex its representative's position (:meth:`solver.mesh.manifold.ManifoldCut.to_file`).

:class:`AnswerMap` is the one home of both steps: :func:`solver.reconstruct` builds one from
the solved mesh's topology (:meth:`AnswerMap.of`) and maps its answer with ``forward``;
:func:`solver.differentiable.reconstruct_vjp` maps its polished answer with the same map and
pulls a cotangent of the returned vertices back to the solver's answer (``vjp``): step 2 is
linear, ``cut_bar[k] = m_bar[vertex_map[k]] / count[vertex_map[k]]`` with ``m_bar`` the
scatter-add of the file cotangent over ``weld_map``; step 1 is differentiated exactly (the
placement's rotation depends on the anchor face's positions; the side-by-side shifts on the
components' bounding boxes, almost everywhere). Components are numbered as the solved
mesh's :class:`~solver.mesh.topology.MeshTopology` numbers them (the numbering of
``laid_out`` and of the anchors of :meth:`solver.immersion.ImmersionProblem.anchors`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from .mesh.manifold import ManifoldCut
from .mesh.placement import (
    SIDE_BY_SIDE_GAP,
    Placement,
    apply_placement,
    face_frames,
    side_by_side,
)
from .mesh.topology import MeshTopology


class FileAnswer(NamedTuple):
    """What :meth:`AnswerMap.forward` returns.

    Attributes:
        vertices: (n, 3) float64 the returned vertices (per file vertex with a cut).
        frames: (m, 3, 3) float64 the face frames, rotated with their placed components.
        spread: (n,) float64 the largest distance of a file vertex's copies from their
            mean (:meth:`ManifoldCut.to_file`), or None without a cut.
    """

    vertices: np.ndarray
    frames: np.ndarray
    spread: np.ndarray | None


@dataclass(frozen=True)
class AnswerMap:
    """Solver answer (n_cut, 3) -> returned answer (n, 3) (module docstring).

    Attributes:
        faces: (m, 3) int64 the solved (cut) faces.
        vertex_component: (n_cut,) int64 component of each solved vertex
            (:attr:`MeshTopology.vertex_component`).
        face_component: (m,) int64 component of each solved face.
        cut: the forms' :class:`ManifoldCut`, or None (no ``vertex_map``).
        placement: the placement of the moved components, or None.
        laid_out: (k,) int64 components laid out side by side, in order (empty with a
            placement or fewer than two).
    """

    faces: np.ndarray
    vertex_component: np.ndarray
    face_component: np.ndarray
    cut: ManifoldCut | None
    placement: Placement | None
    laid_out: np.ndarray

    @classmethod
    def of(cls, topology: MeshTopology, cut: ManifoldCut | None,
           placement: Placement | None, laid_out: np.ndarray) -> AnswerMap:
        """The map of an answer solved on ``topology`` (its faces and components)."""
        laid_out = np.asarray(laid_out, dtype=np.int64)
        return cls(faces=topology.faces, vertex_component=topology.vertex_component,
                   face_component=topology.face_component, cut=cut, placement=placement,
                   laid_out=laid_out if len(laid_out) > 1 else laid_out[:0])

    @property
    def n_solved(self) -> int:
        """n_cut, the solved vertex count."""
        return len(self.vertex_component)

    @property
    def is_identity(self) -> bool:
        """True when the answer is returned as solved."""
        return self.cut is None and self.placement is None and len(self.laid_out) < 2

    @property
    def n_vertices(self) -> int:
        """n, the returned vertex count."""
        return self.n_solved if self.cut is None else self.cut.n_file_vertices

    def forward(self, vertices: np.ndarray, frames: np.ndarray) -> FileAnswer:
        """The answer :func:`solver.reconstruct` returns for a solver answer: vertices
        (n_cut, 3) float64 and their face frames (m, 3, 3) float64 in the solver's gauge
        (the inputs are not modified)."""
        if len(self.laid_out) > 1:
            vertices = side_by_side(vertices, self.vertex_component, self.laid_out)
        if self.placement is not None:
            vertices, frames = apply_placement(vertices, self.faces, self.placement,
                                               frames=frames)
        spread = None
        if self.cut is not None:
            vertices, spread = self.cut.to_file(vertices)
        return FileAnswer(vertices, frames, spread)

    def vjp(self, x: np.ndarray, g: np.ndarray) -> np.ndarray:
        """Cotangent (B, n_cut, 3) of the solver answer ``x`` (n_cut, 3) from ``g`` (B, n, 3),
        the cotangent of :meth:`forward`'s vertices."""
        if self.cut is not None:
            g = self._to_file_vjp(g)
        if self.placement is not None:
            g = self._placement_vjp(x, g)
        if len(self.laid_out) > 1:
            g = self._side_by_side_vjp(x, g)
        return g

    @functools.cached_property
    def _copies(self) -> np.ndarray:
        """(n_cut,) float64 the copy count of each cut vertex's file vertex (the divisor of
        the mean of :meth:`ManifoldCut.to_file`), counted once per map."""
        cut = self.cut
        assert cut is not None
        counts = np.bincount(cut.vertex_map, minlength=cut.n_file_vertices)
        return np.maximum(counts, 1).astype(np.float64)[cut.vertex_map]

    def _to_file_vjp(self, g: np.ndarray) -> np.ndarray:
        cut = self.cut
        assert cut is not None
        if cut.weld_map is not None:     # file = mean[weld_map]: scatter-add back
            summed = np.zeros((len(g), cut.n_file_vertices, 3))
            np.add.at(summed, (slice(None), cut.weld_map), g)
            g = summed
        return g[:, cut.vertex_map] / self._copies[None, :, None]

    def _placement_vjp(self, x: np.ndarray, g: np.ndarray) -> np.ndarray:
        """``y = P F(x)^T (x - x_a) + o`` on each moved component, F the anchor face's frame
        (:func:`face_frames`), P and o the placement's pose."""
        placement = self.placement
        assert placement is not None
        vertex_component, face_component = self.vertex_component, self.face_component
        k = int(max(vertex_component.max(initial=-1), face_component.max(initial=-1))) + 1
        comp = face_component[placement.faces]
        anchor_faces = self.faces[placement.faces]                      # (c, 3)
        F = face_frames(x, anchor_faces)                                # (c, 3, 3)
        rotation = placement.frames @ np.swapaxes(F, 1, 2)              # (c, 3, 3)
        slot = np.full(k, -1, dtype=np.int64)
        slot[comp] = np.arange(len(comp))
        which = slot[vertex_component]
        moved = np.flatnonzero(which >= 0)
        w = which[moved]
        out = g.copy()
        R = rotation[w]                                                 # (v, 3, 3)
        gy = g[:, moved]                                                # (B, v, 3)
        gx = np.einsum("vij,bvi->bvj", R, gy)                           # R^T g_y
        out[:, moved] = gx
        B, c = len(g), len(comp)
        per_comp = np.zeros((B, c, 3))
        np.add.at(per_comp, (slice(None), w), gx)
        np.add.at(out, (slice(None), anchor_faces[:, 0]), -per_comp)
        d = x[moved] - x[anchor_faces[w, 0]]                            # (v, 3)
        rotation_bar = np.zeros((B, c, 3, 3))
        np.add.at(rotation_bar, (slice(None), w), np.einsum("bvi,vj->bvij", gy, d))
        frame_bar = np.einsum("bcij,cik->bcjk", rotation_bar, placement.frames)  # R_bar^T P
        corner_bar = _face_frames_vjp(x, anchor_faces, F, frame_bar)    # (B, c, 3, 3)
        np.add.at(out, (slice(None), anchor_faces), corner_bar)
        return out

    def _side_by_side_vjp(self, x: np.ndarray, g: np.ndarray) -> np.ndarray:
        """Each laid-out component i >= 1 moves along x by ``low_0 + sum_{j<i} (width_j +
        gap) - low_i`` (bounding boxes of the solver answer; ``gap`` from the largest
        diagonal): the cotangents of the shifts go to the extreme vertices."""
        vertex_component = self.vertex_component
        comps = self.laid_out
        k = int(vertex_component.max()) + 1
        B, c = len(g), len(comps)
        shift_bar = np.zeros((B, k))
        np.add.at(shift_bar, (slice(None), vertex_component), g[:, :, 0])
        s = shift_bar[:, comps]
        s[:, 0] = 0.0                                        # the first one stays
        low_bar = np.zeros((B, k, 3))
        high_bar = np.zeros((B, k, 3))
        low_bar[:, comps[0], 0] += s.sum(axis=1)
        low_bar[:, comps, 0] -= s
        after = np.cumsum(s[:, ::-1], axis=1)[:, ::-1]       # sum_{i >= j} s_i
        width_bar = np.zeros((B, c))
        width_bar[:, :-1] = after[:, 1:]
        high_bar[:, comps, 0] += width_bar
        low_bar[:, comps, 0] -= width_bar
        gap_bar = SIDE_BY_SIDE_GAP * np.einsum("bi,i->b", s, np.arange(c, dtype=np.float64))
        low, high, low_at, high_at = _boxes(x, vertex_component, k)
        box = high[comps] - low[comps]
        diag = np.linalg.norm(box, axis=1)
        j = comps[int(np.argmax(diag))]
        unit = (high[j] - low[j]) / max(float(np.linalg.norm(high[j] - low[j])), 1e-300)
        high_bar[:, j] += gap_bar[:, None] * unit
        low_bar[:, j] -= gap_bar[:, None] * unit
        out = g.copy()
        for axis in range(3):                                # the three coordinates
            np.add.at(out, (slice(None), low_at[:, axis], axis), low_bar[:, :, axis])
            np.add.at(out, (slice(None), high_at[:, axis], axis), high_bar[:, :, axis])
        return out


def _boxes(x: np.ndarray, component: np.ndarray, k: int
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Bounding boxes (k, 3) low and high of each component's vertices, and the vertex
    (k, 3) int64 at each extreme (the first in index order among ties)."""
    low, high = np.zeros((k, 3)), np.zeros((k, 3))
    low_at = np.zeros((k, 3), dtype=np.int64)
    high_at = np.zeros((k, 3), dtype=np.int64)
    for axis in range(3):                                    # the three coordinates
        for sign, value, at in ((1.0, low, low_at), (-1.0, high, high_at)):
            order = np.lexsort((np.arange(len(x)), sign * x[:, axis], component))
            first = np.r_[True, component[order][1:] != component[order][:-1]]
            at[component[order[first]], axis] = order[first]
            value[component[order[first]], axis] = x[order[first], axis]
    return low, high, low_at, high_at


def _face_frames_vjp(x: np.ndarray, faces: np.ndarray, F: np.ndarray,
                     F_bar: np.ndarray) -> np.ndarray:
    """Cotangent (B, c, 3, 3) of the corners (``[b, t, corner, coordinate]``) of faces (c, 3)
    from that of their frames :func:`face_frames` ``F`` (c, 3, 3), ``F_bar`` (B, c, 3, 3):
    ``b1 = e1 / |e1|``, ``b3 = n / |n|`` with ``n = e1 x e2``, ``b2 = b3 x b1``."""
    p0, p1, p2 = (x[faces[:, i]] for i in range(3))
    e1, e2 = p1 - p0, p2 - p0
    b1, b3 = F[:, :, 0], F[:, :, 2]
    g1, g2, g3 = F_bar[..., 0], F_bar[..., 1], F_bar[..., 2]
    g3 = g3 + np.cross(b1[None], g2)                       # b2 = b3 x b1
    g1 = g1 + np.cross(g2, b3[None])
    normal = np.cross(e1, e2)

    def unit_vjp(u: np.ndarray, v: np.ndarray, gu: np.ndarray) -> np.ndarray:
        size = np.maximum(np.linalg.norm(v, axis=1), 1e-300)[None, :, None]
        return (gu - u[None] * np.einsum("bck,ck->bc", gu, u)[..., None]) / size

    g_e1 = unit_vjp(b1, e1, g1)
    g_n = unit_vjp(b3, normal, g3)
    g_e1 = g_e1 + np.cross(e2[None], g_n)                  # n = e1 x e2
    g_e2 = np.cross(g_n, e1[None])
    return np.stack([-(g_e1 + g_e2), g_e1, g_e2], axis=2)
