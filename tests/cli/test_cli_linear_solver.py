"""``--linear-solver`` (issue 45): the same option in-process and over HTTP (a real uvicorn),
its answer the library's direct one, and the report saying which solve ran."""

from __future__ import annotations

import json

import httpx
import numpy as np

import solver
from solver.mesh.io import load_mesh_file
from tests.helpers import DATA
from tests.helpers.service import rigid_error


def test_iterative_linear_answer_in_process_and_over_http(ffs, server, workdir):
    V, F = load_mesh_file(workdir / "torus.off")
    forms = solver.fundamental_forms(V, F)
    angles = forms.angles + np.random.default_rng(3).normal(scale=1e-2, size=len(forms.angles))
    np.savez(workdir / "noisy.npz", faces=forms.faces, edges=forms.edges,
             lengths=forms.lengths, angles=angles)
    direct = solver.reconstruct(forms.faces, forms.edges, forms.lengths, angles,
                                refine=False, linear_solver="direct")
    for where in (["--threads", "1"], ["--server", server]):
        out = f"out-{len(where[1])}.obj"
        result = ffs("reconstruct", "noisy.npz", "-o", out, "--no-refine",
                     "--linear-solver", "iterative", *where)
        assert result.returncode == 0, result.stderr
        W = load_mesh_file(workdir / out)[0]
        assert rigid_error(W, direct.vertices) < 1e-6 * np.ptp(V, axis=0).max()
    bad = ffs("reconstruct", "noisy.npz", "-o", "x.obj", "--linear-solver", "cg")
    assert bad.returncode == 2 and "invalid choice" in bad.stderr


def test_http_report_names_the_linear_solver(server):
    V, F = load_mesh_file(DATA / "torus.off")
    forms = solver.fundamental_forms(V, F)
    angles = (forms.angles + 1e-2 * np.sin(np.arange(len(forms.angles)))).tolist()
    body = {"faces": forms.faces.tolist(), "edges": forms.edges.tolist(),
            "lengths": forms.lengths.tolist(), "angles": angles}
    for method in ("direct", "iterative"):
        answer = httpx.post(f"{server}/v1/reconstruct", timeout=120, json={
            **body, "options": {"refine": False, "linear_solver": method}})
        assert answer.status_code == 200, answer.text
        report = answer.json()["report"]
        assert report["linear_solver"]["method"] == method
        if method == "iterative":
            assert report["linear_solver"]["converged"] is True
            assert report["linear_solver"]["iterations"] >= 1
    wrong = httpx.post(f"{server}/v1/reconstruct", timeout=60, json={
        **body, "options": {"linear_solver": "cg"}})
    assert wrong.status_code == 422
    assert "linear_solver" in json.dumps(wrong.json())
