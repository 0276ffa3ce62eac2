"""Flatten anything (issue 41): closed genus 0 and 2, multi-part and holed surfaces through
the library, checked by an independent rasterization (PIL), orientation and lengths."""

import numpy as np
import pytest

from solver import parameterize
from solver.mesh.charts import bisect, chart_mesh, connected_face_sets, dual_graph, is_disk_like
from solver.mesh.forms import fundamental_forms
from solver.mesh.packing import rasterized_overlap, signed_areas
from solver.mesh.topology import build_topology
from tests.helpers.atlas import euler_genus, genus_two, overlapping_pixels
from tests.helpers.meshes import holed, icosphere, load, side_by_side, sphere_cap

CASES = {
    "sphere (genus 0)": lambda: icosphere(3),
    "knight (genus 0)": lambda: load("decimated-knight.off"),
    "torus (genus 1)": lambda: load("torus.off"),
    "slab (genus 2)": genus_two,
    "multi-part": lambda: side_by_side(load("torus.off"), icosphere(2),
                                       load("decimated-knight.off"), load("face.off")),
    "octopus with holes": lambda: holed(*load("octopus-low-surface.off"), [5, 100, 300]),
}


def check_atlas(V, F, result, min_efficiency=0.3):
    """Every face once, uv ids map to the file's vertices, texcoords in the unit square,
    no flips, no overlap (PIL and the solver's rasterizer), shapes kept up to one scale."""
    m = len(F)
    assert result.uv_faces.shape == (m, 3) and result.face_chart.shape == (m,)
    assert np.array_equal(result.uv_vertex[result.uv_faces], F)
    assert result.texcoords.min() >= 0.0 and result.texcoords.max() <= 1.0
    assert (signed_areas(result.texcoords, result.uv_faces) > 0).all()
    assert len(result.flipped_faces) == 0 and result.report["flipped_count"] == 0
    assert overlapping_pixels(result.texcoords, result.uv_faces, result.face_chart) == 0
    assert rasterized_overlap(result.texcoords, result.uv_faces, 2048) == 0
    # texcoords are uv times one scale (and a shift): every edge has the same ratio.
    tail, head = result.uv_faces, np.roll(result.uv_faces, -1, axis=1)
    ratio = (np.linalg.norm(result.uv[head] - result.uv[tail], axis=2)
             / np.linalg.norm(result.texcoords[head] - result.texcoords[tail], axis=2))
    assert np.ptp(ratio) < 1e-6 * ratio.mean()
    atlas = result.report["atlas"]
    assert atlas["charts"] == result.face_chart.max() + 1
    assert min_efficiency < atlas["packing_efficiency"] <= 1.0
    # Efficiency is the covered fraction: the charts' uv area over the unit square.
    assert atlas["packing_efficiency"] == pytest.approx(
        np.abs(signed_areas(result.texcoords, result.uv_faces)).sum())


@pytest.mark.parametrize("name", list(CASES))
def test_atlas_of_a_surface_without_a_single_good_chart(name):
    V, F = CASES[name]()
    result = parameterize(V, F)
    check_atlas(V, F, result)
    atlas = result.report["atlas"]
    assert atlas["charts"] >= 2
    # Seams: the interior edges between charts, measured on the 3D mesh.
    forms = fundamental_forms(V, F)
    topology = build_topology(F, n_vertices=len(V))
    ends = topology.edge_faces
    interior = (ends >= 0).all(axis=1)
    cut = interior.copy()
    cut[interior] = result.face_chart[ends[interior, 0]] != result.face_chart[ends[interior, 1]]
    assert atlas["seam_edges"] == cut.sum()
    assert atlas["seam_length"] == pytest.approx(forms.lengths[cut].sum())
    # Each chart is flattened with at most the chart threshold's mean length change.
    assert result.report["length_change_summary"]["mean"] < 0.05
    assert result.report["warnings"] == []


def test_every_chart_is_a_disk_like_piece_and_charts_are_edge_connected():
    V, F = genus_two()
    assert euler_genus(V, F) == 2
    result = parameterize(V, F)
    for chart in np.unique(result.face_chart):
        ids = np.flatnonzero(result.face_chart == chart)
        piece = chart_mesh(F, ids)
        assert is_disk_like(build_topology(piece.faces)) or len(ids) == 1


def test_disk_like_meshes_keep_one_chart_and_todays_layout():
    V, F = load("face.off")
    result = parameterize(V, F)
    today = parameterize(V, F, seams="none")
    assert result.report["atlas"]["charts"] == 1
    assert np.array_equal(result.uv, today.uv)
    assert np.array_equal(result.uv_faces, F)
    assert np.array_equal(result.uv_vertex, np.arange(len(V)))
    check_atlas(V, F, result)


def test_bisection_gives_connected_halves_covering_the_chart():
    V, F = icosphere(3)
    topology = build_topology(F, n_vertices=len(V))
    graph = dual_graph(V, topology, fundamental_forms(V, F).angles, 4.0)
    parts = bisect(graph, np.arange(len(F)), len(F))
    assert len(parts) == 2
    assert np.array_equal(np.sort(np.concatenate(parts)), np.arange(len(F)))
    for part in parts:
        assert len(connected_face_sets(graph, part, len(F))) == 1
        assert 0.25 * len(F) < len(part) < 0.75 * len(F)       # farthest seeds: balanced


def test_warnings_name_a_flattening_past_its_thresholds():
    V, F = sphere_cap()
    result = parameterize(V, F, orthonormalize=False, refine=False,
                          seams="none")
    codes = {w["code"] for w in result.report["warnings"]}
    assert "length-distortion" in codes
    flipped = result.report["flipped_count"] / len(F)
    assert ("flipped-faces" in codes) == (flipped > 1e-3)


def test_face_scan_with_small_holes_flattens_without_flips_or_overlap():
    """A real scan (the face) with three small holes punched inside, as scans come."""
    V, F = holed(*load("face.off"), [300, 600, 900])
    topology = build_topology(F, n_vertices=len(V))
    assert len(topology.boundary_loops) == 4
    result = parameterize(V, F)
    check_atlas(V, F, result)
    assert result.report["warnings"] == []


def test_a_spent_time_budget_still_cuts_closed_pieces_and_says_what_is_left():
    V, F = load("decimated-knight.off")
    result = parameterize(V, F, max_seconds=0.01)
    assert result.report["atlas"]["charts"] >= 2      # a closed surface is always cut
    assert np.array_equal(result.uv_vertex[result.uv_faces], F)
    flipped = result.report["flipped_count"] / len(F)
    codes = {w["code"] for w in result.report["warnings"]}
    assert ("flipped-faces" in codes) == (flipped > 1e-3)
    mean_change = result.report["length_change_summary"]["mean"]
    assert ("length-distortion" in codes) == (mean_change > 0.1)


def test_a_one_chart_layout_that_crosses_itself_is_named():
    from solver.core.warnings import flattening_warnings
    from solver.mesh.packing import boundary_crossings

    # A strip wound round past a full turn: no flipped face, its ends overlap.
    angle = np.linspace(0, 2.24 * np.pi, 30)
    inner = np.stack([np.cos(angle), np.sin(angle)], 1)
    uv = np.concatenate([inner, 1.5 * inner])
    i = np.arange(29)
    faces = np.concatenate([np.stack([i, i + 30, i + 1], 1), np.stack([i + 1, i + 30, i + 31], 1)])
    faces = faces[:, ::-1] if signed_areas(uv, faces)[0] < 0 else faces
    assert (signed_areas(uv, faces) > 0).all()
    crossings = boundary_crossings(uv, faces)
    assert crossings > 0 and rasterized_overlap((uv + 3) / 6, faces, 512) > 0
    found = flattening_warnings(0, 1, 0.0, 0.0, None, crossings=crossings)
    codes = [w.code for w in found if w is not None]
    assert codes == ["overlapping-layout"]


def test_a_tetrahedron_is_cut_down_to_single_faces_without_flips():
    """The smallest closed surface: its charts end as single faces and hinged pairs, each laid
    out with its own corners (a single face keeps its orientation whatever its vertex order)."""
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    result = parameterize(V, F)
    check_atlas(V, F, result, min_efficiency=0.0)     # 4 faces: padding dominates
    # Every chart is congruent to its faces: uv edge lengths are the 3D ones times one scale.
    tail, head = result.uv_faces, np.roll(result.uv_faces, -1, axis=1)
    flat = np.linalg.norm(result.uv[head] - result.uv[tail], axis=2)
    rest = np.linalg.norm(V[np.roll(F, -1, axis=1)] - V[F], axis=2)
    np.testing.assert_allclose(flat, rest, rtol=1e-9)


def test_a_hole_laid_out_inside_out_counts_as_overlap():
    """A square ring laid out as it is (one counter-clockwise loop: its outline) does not
    overlap itself; the same ring with its hole's rim run the other way round (the hole
    inside out, as a boundary vertex whose angles pass a full turn leaves it) does."""
    from solver.atlas import overlaps_itself
    from solver.mesh.packing import boundary_crossings, positive_loops

    V = np.array([[0, 0], [3, 0], [3, 3], [0, 3], [1, 1], [2, 1], [2, 2], [1, 2]], float)
    F = np.array([[0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5], [2, 3, 7],
                  [2, 7, 6], [3, 0, 4], [3, 4, 7]])
    loops = build_topology(F, n_vertices=8).boundary_loops
    assert sorted(len(loop) for loop in loops) == [4, 4]
    assert positive_loops(V, loops) == 1 and boundary_crossings(V, F) == 0
    assert not overlaps_itself(V, F, loops)
    turned = [loop if positive_loops(V, [loop]) else loop[::-1] for loop in loops]
    assert positive_loops(V, turned) == 2 and overlaps_itself(V, F, turned)


def test_xatlas_seeds_cover_every_face_once_in_edge_connected_sets():
    from solver.mesh.charts import labelled_face_sets, xatlas_charts

    for V, F in (load("decimated-knight.off"), load("torus.off"), genus_two()):
        topology = build_topology(F, n_vertices=len(V))
        graph = dual_graph(V, topology, fundamental_forms(V, F).angles, 4.0)
        sets = labelled_face_sets(graph, xatlas_charts(V, F))
        assert np.array_equal(np.sort(np.concatenate(sets)), np.arange(len(F)))
        for piece in sets:
            assert len(connected_face_sets(graph, piece, len(F))) == 1


@pytest.mark.parametrize("unit", [1e-6, 1.0, 1e4])
def test_packing_places_every_chart_whatever_the_mesh_units(unit):
    """The same charts in micrometres, metres or tens of kilometres pack the same way: no
    chart is left unplaced by xatlas's float32 area threshold (the 69K-face scan's one-face
    charts once piled up at the atlas's corner), none overlaps, shapes are kept."""
    from solver.mesh.packing import pack_charts

    V, F = load("decimated-knight.off")
    result = parameterize(V, F)
    packed = pack_charts(result.uv * unit, result.uv_faces, result.face_chart)
    assert rasterized_overlap(packed.texcoords, result.uv_faces, 2048) == 0
    assert packed.texcoords.min() >= 0.0 and packed.texcoords.max() <= 1.0
    tail, head = result.uv_faces, np.roll(result.uv_faces, -1, axis=1)
    placed = packed.texcoords * packed.scale / unit
    np.testing.assert_allclose(np.linalg.norm(placed[head] - placed[tail], axis=2),
                               np.linalg.norm(result.uv[head] - result.uv[tail], axis=2),
                               rtol=1e-6)
