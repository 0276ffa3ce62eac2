"""The atlas's charts are flattened in rounds (solver.atlas.chart_layouts): the linear
flattening and the refinement's start solved once for the disjoint union of the charts
waiting, each chart then refined and checked alone. Checked against each chart flattened
alone by the per-chart path (solver.atlas._flatten_or_none, which solves one chart's own
system): the same layout up to a rigid motion, on several meshes; and the union's Tutte
embedding and local/global fit against each component's own."""

import itertools

import numpy as np
import pytest

from solver.atlas import _flatten_or_none, chart_layouts, chart_options
from solver.chart_flattening import local_global_flattening, tutte_embedding
from solver.mesh.forms import fundamental_forms
from solver.mesh.topology import build_topology
from solver.options import ParameterizeOptions
from solver.reports import Stages
from tests.helpers.atlas import genus_two
from tests.helpers.meshes import holed, icosphere, load

MESHES = {
    "knight": lambda: load("decimated-knight.off"),
    "torus": lambda: load("torus.off"),
    "slab (genus 2)": genus_two,
    "octopus with holes": lambda: holed(*load("octopus-low-surface.off"), [5, 100, 300]),
    "sphere": lambda: icosphere(2),
}


def _rigid_gap(a: np.ndarray, b: np.ndarray) -> float:
    """Largest distance between ``a`` and ``b`` (n, 2) after the best rotation and shift of
    ``a`` (no reflection), relative to ``b``'s extent."""
    A, B = a - a.mean(axis=0), b - b.mean(axis=0)
    U, _, Vt = np.linalg.svd(A.T @ B)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        return float("inf")
    return float(np.abs(A @ R - B).max() / np.ptp(B, axis=0).max())


def _lengths(V: np.ndarray, topology) -> np.ndarray:
    return np.linalg.norm(V[topology.edges[:, 1]] - V[topology.edges[:, 0]], axis=1)


@pytest.mark.parametrize("name", list(MESHES))
def test_each_chart_is_flattened_as_it_would_be_alone(name):
    V, F = MESHES[name]()
    topology = build_topology(F, n_vertices=len(V))
    forms = fundamental_forms(V, F)
    opts = ParameterizeOptions()
    charts = chart_layouts(V, topology, forms.angles, opts, Stages(None))
    assert sorted(np.concatenate([c.mesh.face_ids for c in charts]).tolist()) == list(
        range(len(F)))
    several = [c for c in charts if len(c.mesh.face_ids) > 1]
    assert len(several) >= 2
    for chart in several:
        alone = _flatten_or_none(V[chart.mesh.vertex_ids], chart.mesh.faces,
                                 chart_options(opts, len(chart.mesh.face_ids)), Stages(None),
                                 out_of_time=False)
        assert alone is not None, "a chart kept in a round fails alone"
        assert _rigid_gap(chart.flattening.uv, alone.uv) < 1e-6
        assert (chart.flattening.refinement.get("iterations")
                == alone.refinement.get("iterations"))


def test_the_union_start_is_each_components_own():
    """Tutte's embedding and the local/global fit of three disjoint charts (different sizes
    and scales, one with a sliver) against each chart's alone: equal to rounding."""
    pieces = [load("face.off"), holed(*icosphere(3), [0]), holed(*load("torus.off"), [7])]
    pieces[1] = (pieces[1][0] * 1e3, pieces[1][1])                     # another scale
    V0, F0 = pieces[0]
    V0 = V0.copy()
    V0[F0[10, 2]] = 0.5 * (V0[F0[10, 0]] + V0[F0[10, 1]]) + 1e-9       # a near-zero-area face
    pieces[0] = (V0, F0)
    # only the disk-like part of the holed torus has a Tutte embedding; keep disks
    disks = []
    for V, F in pieces:
        topology = build_topology(F, n_vertices=len(V))
        if tutte_embedding(V, topology, _lengths(V, topology)) is not None:
            disks.append((V, F, topology))
    assert len(disks) >= 2
    offsets = np.cumsum([0] + [len(V) for V, _, _ in disks])
    UV = np.concatenate([V for V, _, _ in disks])
    UF = np.concatenate([F + offsets[k] for k, (_, F, _) in enumerate(disks)])
    union = build_topology(UF, n_vertices=len(UV))
    lengths = _lengths(UV, union)
    together = tutte_embedding(UV, union, lengths)
    fitted = local_global_flattening(union, lengths, together)
    for k, (V, _, topology) in enumerate(disks):
        rows = slice(offsets[k], offsets[k + 1])
        own = tutte_embedding(V, topology, _lengths(V, topology))
        scale = np.ptp(own, axis=0).max()
        np.testing.assert_allclose(together[rows], own, rtol=0, atol=1e-9 * scale)
        own_fit = local_global_flattening(topology, _lengths(V, topology), own)
        assert _rigid_gap(fitted[rows], own_fit) < 1e-8


def test_a_closed_component_has_no_tutte_embedding():
    V1, F1 = load("face.off")
    V2, F2 = icosphere(1)
    V = np.concatenate([V1, V2])
    F = np.concatenate([F1, F2 + len(V1)])
    topology = build_topology(F, n_vertices=len(V))
    assert tutte_embedding(V, topology, _lengths(V, topology)) is None


@pytest.mark.parametrize("name", ["knight", "octopus with holes"])
def test_a_charts_graph_is_the_dual_graph_restricted_to_it(name):
    """The chart's dual graph, read from its faces' entries, against the whole mesh's dual
    graph (every interior edge's two faces and cost) restricted to the chart's faces."""
    import scipy.sparse as sp

    from solver.mesh.charts import _local_graph, dual_graph

    V, F = MESHES[name]()
    topology = build_topology(F, n_vertices=len(V))
    graph = dual_graph(V, topology, fundamental_forms(V, F).angles, 4.0)
    m = len(F)
    a, b = graph.edge_faces.T
    whole = sp.coo_array((np.concatenate([graph.cost, graph.cost]),
                          (np.concatenate([a, b]), np.concatenate([b, a]))), shape=(m, m)).tocsr()
    rng = np.random.default_rng(7)
    for size in (1, 2, 40, m // 3, m):
        ids = np.sort(rng.choice(m, size=size, replace=False))
        local = _local_graph(graph, ids, m)
        expected = whole[ids][:, ids]
        assert local.shape == expected.shape and (local != expected).nnz == 0
        assert local.nnz == expected.nnz


def test_progress_counts_the_faces_placed_chart_by_chart():
    """``progress("charts", fraction)`` rises as each chart is accepted (not once a round):
    one report per chart of the atlas kept, never falling, the last 1 (every face placed)."""
    from solver import parameterize

    V, F = MESHES["octopus with holes"]()
    reports: list[tuple[str, float]] = []
    result = parameterize(V, F, progress=lambda stage, fraction: reports.append(
        (stage, fraction)))
    charts = [fraction for stage, fraction in reports if stage == "charts"]
    assert charts and charts[-1] == pytest.approx(1.0)
    rounds = [0] + [k for k in range(1, len(charts)) if charts[k] < charts[k - 1]]
    # the xatlas-seeded atlas, then (packing below AtlasRules.rechart_below) the bisection's
    assert len(rounds) <= 2
    segments = [charts[a:b] for a, b in itertools.pairwise([*rounds, len(charts)])]
    for segment in segments:
        assert all(b > a for a, b in itertools.pairwise(segment))
        assert segment[-1] == pytest.approx(1.0)
    # the atlas kept (the one that packs better) had one report per chart
    assert result.report["atlas"]["charts"] in [len(segment) for segment in segments]


def test_single_face_charts_are_laid_out_all_at_once_with_their_edge_lengths():
    """A triangle soup (every face its own part: the knight's faces apart) is an atlas of
    one-face charts, laid out together (solver.atlas._single_faces): each chart is the one
    chart_mesh makes of its face, counter-clockwise, with the face's 3D edge lengths."""
    from solver.mesh.charts import chart_mesh

    V, F = load("decimated-knight.off")
    F = F[::3]
    soup_V, soup_F = V[F].reshape(-1, 3), np.arange(3 * len(F)).reshape(-1, 3)
    forms = fundamental_forms(soup_V, soup_F, coincident=False)  # kept a soup (no zip)
    topology = build_topology(forms.faces, n_vertices=len(soup_V))
    charts = chart_layouts(soup_V, topology, forms.angles, ParameterizeOptions(), Stages(None))
    assert sorted(int(c.mesh.face_ids[0]) for c in charts) == list(range(len(F)))
    for chart in charts:
        want = chart_mesh(soup_F, chart.mesh.face_ids)
        np.testing.assert_array_equal(chart.mesh.vertex_ids, want.vertex_ids)
        np.testing.assert_array_equal(chart.mesh.faces, want.faces)
        a, b, c = chart.flattening.uv[chart.mesh.faces[0]]
        assert (b - a)[0] * (c - a)[1] - (b - a)[1] * (c - a)[0] > 0
        corners = soup_V[chart.mesh.vertex_ids][chart.mesh.faces[0]]
        sides_3d = np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1)
        sides_uv = np.linalg.norm(np.roll([a, b, c], -1, axis=0) - [a, b, c], axis=1)
        np.testing.assert_allclose(sides_uv, sides_3d, rtol=1e-12)


def test_two_face_charts_are_kept_as_the_per_chart_path_keeps_them():
    """Separate two-face pieces (hinges bent by 0 to 170 degrees, one with a zero-area
    face, one of sides 1e-3) are kept without a refinement or check of their own
    (solver.atlas._Union.exact_hinges) where the per-chart path finds them exact; the same
    layouts, up to a rigid motion, and the same refinement reports."""
    rng = np.random.default_rng(3)
    pieces = []
    for k, bend in enumerate(np.radians(np.linspace(0, 170, 12))):
        a, b = np.array([0.0, 0, 0]), np.array([1.0, 0, 0])
        c = np.array([0.4, 0.8, 0.0])
        d = np.array([0.6, -0.7 * np.cos(bend), 0.7 * np.sin(bend)])
        quad = np.stack([a, b, c, d]) * (1e-3 if k == 5 else 1.0)
        if k == 7:
            quad[2] = [0.5, 0.0, 0.0]                               # zero area: checked alone
        pieces.append(quad @ np.linalg.qr(rng.normal(size=(3, 3)))[0] + rng.normal(size=3))
    V = np.concatenate(pieces)
    o = 4 * np.arange(len(pieces))[:, None]
    F = np.concatenate([np.array([[0, 1, 2], [1, 0, 3]]) + o[k] for k in range(len(pieces))])
    topology = build_topology(F, n_vertices=len(V))
    opts = ParameterizeOptions()
    charts = chart_layouts(V, topology, fundamental_forms(V, F).angles, opts, Stages(None))
    assert sorted(np.concatenate([c.mesh.face_ids for c in charts]).tolist()) == list(
        range(len(F)))
    for chart in charts:
        alone = _flatten_or_none(V[chart.mesh.vertex_ids], chart.mesh.faces,
                                 chart_options(opts, len(chart.mesh.face_ids)), Stages(None),
                                 out_of_time=False)
        assert alone is not None
        assert _rigid_gap(chart.flattening.uv, alone.uv) < 1e-9
        assert chart.flattening.refinement == alone.refinement
