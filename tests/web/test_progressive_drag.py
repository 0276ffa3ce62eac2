"""Progressive drags on the page: Refine is on by default; a drag shows the linear shape at
once and settles to the refined shape when the session sends it (over the WebSocket, and
over HTTP with ?transport=http). The settled shape is checked against solver.Deformer run in
this process: at its refined answer's optimum, far from its linear one."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

import solver


def _vertices(web: Any) -> np.ndarray:
    return np.asarray(web.app("app.vertices()")).reshape(-1, 3)


def _reference(body: dict) -> tuple[np.ndarray, np.ndarray]:
    """(linear, refined) shapes of the page's deformation, computed here from the request
    body the page would send (rest mesh, handles, targets, rotation groups)."""
    V = np.asarray(body["vertices"], dtype=np.float64)
    F = np.asarray(body["faces"], dtype=np.int64)
    handles = [h["vertex"] for h in body["handles"]]
    P = np.asarray([h["position"] for h in body["handles"]], dtype=np.float64)
    rotations = body.get("rotations") or []
    groups = [r["faces"] for r in rotations] or None
    R = np.asarray([r["rotation"] for r in rotations]) if rotations else None
    deformer = solver.Deformer(V, F, handles, rotation_handles=groups,
                               orthonormalize=body["options"]["orthonormalize"])
    linear = deformer.solve(P, R, refine=False)
    refined = deformer.solve(P, R, refine=True)
    assert deformer.last_report["converged"], deformer.last_report
    return linear, refined


def _form_error(rest: np.ndarray, X: np.ndarray, faces: np.ndarray) -> tuple[float, float]:
    """(RMS relative edge-length change, RMS dihedral-angle change) of X against rest."""
    before = solver.fundamental_forms(rest, faces)
    after = solver.fundamental_forms(X, before.faces)
    lengths = after.lengths / before.lengths - 1.0
    angles = after.angles - before.angles
    return float(np.sqrt(np.mean(lengths**2))), float(np.sqrt(np.mean(angles**2)))


@pytest.mark.parametrize("query", ["", "?transport=http"])
def test_drag_settles_to_the_refined_shape(web, query):
    page = web.open(query)
    if not web.app("app.capabilities.deformRefine"):
        pytest.skip("this server's deform has no options.refine")
    page.click("#tab-deform")
    assert page.locator("#deform-refine").is_visible()
    assert page.locator("#deform-refine").is_checked()  # on by default
    web.app("app.makeHandle([0, 1, 2])")
    web.app("app.makeHandle(app.visibleVertices().slice(600, 620))")
    transport = web.app("app.state.transport.label")
    assert ("WebSocket" in transport) == (query == ""), transport
    web.app("app.dragHandle(0, 0, 12)")
    web.wait_for("app.state.transport.refinedShapes >= 1", timeout=60,
                 what="the refined shape of the drag")
    web.idle()
    body = web.app("app.deformRequest()")
    assert body["options"]["refine"] is True
    report = web.app("app.state.transport.lastRefinement")
    assert report["converged"] is True and report["iterations"] >= 1, report
    linear, refined = _reference(body)
    got = _vertices(web)
    scale = float(np.ptp(refined, axis=0).max())
    assert np.abs(refined - linear).max() > 1e-2 * scale  # the two shapes differ visibly
    # The page settled to the refined shape. The session's refinement starts from the
    # previous drag's shape (as far as that drag's refinement got before this drag came,
    # which depends on the machine's load), the reference's from the layout fit: the two
    # stop at points of the convergence test up to ~6e-3 of the size apart (measured in a
    # fresh-clone run under the suite's load, when slices also restarted the refinement;
    # face.off, two drags: 4.6e-3 of the diagonal; slices now resume one refinement exactly,
    # tests/service/test_progressive_sessions.py, and this bound was not re-measured), where
    # linear and refined are more than 1e-2 apart. The form errors below are the quality check:
    # within 15% of the reference's (8% measured under that load, 0.2% on a quiet machine)
    # and far below the linear shape's.
    np.testing.assert_allclose(got, refined, rtol=0, atol=8e-3 * scale)
    assert np.abs(got - linear).max() > 5e-3 * scale
    rest, faces = np.asarray(body["vertices"]), np.asarray(body["faces"])
    errors = _form_error(rest, got, faces)
    want, worse = _form_error(rest, refined, faces), _form_error(rest, linear, faces)
    for e, w, lin in zip(errors, want, worse, strict=True):
        assert e <= 1.15 * w and e < 0.7 * lin, (errors, want, worse)
    handles = [h["vertex"] for h in body["handles"]]
    targets = np.asarray([h["position"] for h in body["handles"]])
    np.testing.assert_allclose(got[handles], targets, atol=2e-4 * scale)
    web.screenshot(f"progressive-drag{'-http' if query else ''}")
    assert web.shown_errors() == []
