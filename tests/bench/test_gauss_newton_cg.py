"""bench/gauss_newton_cg.py's pieces on small shared meshes (forced iterative refinement).

Independent truth: the refinement's own report (its CG iterations, forcing terms and
setups per solve) and the refinement run without an observer. The capture must not change
the answer; the bench's production row, built by the refinement's own code on a captured
matrix, must take exactly the iterations the refinement reported for that solve; the reuse
policies must set the hierarchy up as often as they say.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from bench import gauss_newton_cg as bench
from bench.common import SHARED_MESHES
from solver import reconstruct
from solver.refine.iterative_steps import HIERARCHY_RULES, observe_solves

SOURCES = ["rocker-arm.obj", "bunny.off"]
pytestmark = pytest.mark.skipif(not SHARED_MESHES.exists(), reason="no ../shared/meshes")


def _answer(source: str, observer=None):
    data = np.load(bench.source_forms(source)[1])
    args = (data["faces"], data["edges"], data["lengths"], data["noisy"])
    kwargs = {"n_vertices": len(data["vertices"]), "linear_solver": "iterative"}
    if observer is None:
        return reconstruct(*args, **kwargs)
    with observe_solves(observer):
        return reconstruct(*args, **kwargs)


@pytest.fixture(scope="module", params=SOURCES)
def captured(request, tmp_path_factory):
    root = tmp_path_factory.mktemp("captures")
    return request.param, root, bench.capture(request.param, root)


def test_capture_changes_no_answer_and_sees_every_solve(captured):
    source, _, summary = captured
    plain = _answer(source)
    seen = []
    observed = _answer(source, seen.append)
    np.testing.assert_array_equal(observed.vertices, plain.vertices)
    report = plain.report["refinement"]["linear_solver"]
    assert observed.report["refinement"]["linear_solver"]["cg_iterations"] == \
        report["cg_iterations"]
    # Every solve of the refinement, as its report counts them, seen once.
    assert [s.iterations for s in seen] == report["cg_iterations"]
    assert [float(f"{s.tolerance:.3g}") for s in seen] == report["tolerances"]
    assert sum(s.fresh for s in seen) == report["setups"] >= 1
    assert seen[0].fresh
    n = seen[0].matrix.shape[0]
    assert seen[0].positions.size == n and seen[0].rhs.shape == (n,)
    # The capture (in its own run) saw the same.
    assert [s["iterations"] for s in summary["solves"]] == report["cg_iterations"]
    assert summary["energy_after"] == plain.report["refinement"]["energy_after"]
    # No observer is left behind: a later run is not observed.
    _answer(source)
    assert len(seen) == len(report["cg_iterations"])


def test_production_variant_repeats_the_refinements_solves(captured):
    source, root, summary = captured
    fresh = [k for k, s in enumerate(summary["solves"]) if s["fresh"]]
    assert fresh
    for k in fresh:
        solve = bench.load_solve(source, k, root)
        row = bench.solve_with(solve, bench.variants()["production"], solve["tolerance"],
                               bench.DEFAULT_STEP_RULES.cg_max_iterations)
        # The hierarchy set up for that matrix, the same CG: the same iterations and
        # residual to the bit as the refinement reported for that solve.
        assert row["iterations"] == summary["report"]["cg_iterations"][k]
        assert row["relative_residual"] == summary["solves"][k]["relative_residual"]
        assert row["levels"] == summary["report"]["levels"] or k != fresh[-1]
    # A variant to 1e-3 on the last solve reaches it (CG converges with every hierarchy).
    rows = [bench.measure_variant(source, name, -1, 1e-3, 1500, root)
            for name in ("production", "energy 2", "W-cycle", "per vertex float64")]
    assert all(r["relative_residual"] <= 1e-3 and not r["capped"] for r in rows)
    assert all(r["order"] == rows[0]["order"] for r in rows)


def test_variants_change_one_field_of_the_production_hierarchy():
    variants = bench.variants()
    assert variants["production"] is HIERARCHY_RULES
    fields = [f.name for f in dataclasses.fields(HIERARCHY_RULES)]
    for name, rules in variants.items():
        changed = [f for f in fields if getattr(rules, f) != getattr(HIERARCHY_RULES, f)]
        two = "sweeps" in name or name == "per vertex float64"  # both smoothers; both fields
        assert len(changed) == (0 if name == "production" else 2 if two else 1), (name,
                                                                                   changed)


@pytest.mark.parametrize("source", SOURCES[:1])
def test_policies_set_up_as_they_say(source):
    plain = _answer(source).report["refinement"]
    rows = {p: bench.child({"kind": "policy", "source": source, "policy": p}, None)
            for p in bench.POLICIES}
    rows["energy 2"] = bench.child({"kind": "policy", "source": source, "policy": "rule",
                                    "hierarchy": "energy 2"}, None)
    assert all("error" not in r for r in rows.values()), rows
    # The refinement's own rule: the answer without any policy.
    assert rows["rule"]["cg_iterations"] == plain["linear_solver"]["cg_iterations"]
    assert rows["rule"]["setups"] == plain["linear_solver"]["setups"]
    assert rows["rule"]["energy_after"] == plain["energy_after"]
    # Set up before every solve; never after the first.
    assert rows["always"]["setups"] == len(rows["always"]["cg_iterations"])
    assert rows["never"]["setups"] == 1
    # Another hierarchy takes effect (prolongators smoothed by 2 iterations instead of the
    # production's: more CG iterations), the policy's rows say which ran.
    assert rows["energy 2"]["hierarchy"] == "energy 2" and rows["rule"]["hierarchy"] == \
        "production"
    assert sum(rows["energy 2"]["cg_iterations"]) > sum(rows["rule"]["cg_iterations"])
    for r in rows.values():  # the same optimum within the refinement's tolerance
        assert abs(r["energy_after"] - plain["energy_after"]) <= 1e-3 * plain["energy_after"]


def test_setup_price_is_the_setup_over_one_iteration(tmp_path):
    source = SOURCES[1]
    bench.capture(source, tmp_path)
    row = bench.setup_price(source, -1, 2, tmp_path)
    assert row["setup_cpu_seconds"] > 0 and row["iteration_cpu_seconds"] > 0
    assert row["setup_in_iterations"] == pytest.approx(
        row["setup_cpu_seconds"] / row["iteration_cpu_seconds"])
    solve = bench.load_solve(source, -1, tmp_path)
    assert row["iterations"] == bench.solve_with(solve, HIERARCHY_RULES, 1e-3, 3000)[
        "iterations"]


def test_a_per_vertex_hierarchy_reused_on_the_next_matrix_solves_it(captured):
    """The per-vertex hierarchy (block Gauss-Seidel keeps its finest blocks' inverses) set
    up on one captured matrix and reused on the next (the refinement's reuse): each solve
    reaches 1e-3 and the reused one by the next matrix's inverses, not the stale ones (a
    hierarchy whose smoothers still held the first matrix's would differ from a fresh
    hierarchy's finest smoother on the second)."""
    source, root, summary = captured
    assert len(summary["solves"]) >= 2  # two matrices (of one pattern) to reuse it on
    first, second = (bench.load_solve(source, k, root) for k in (0, -1))
    rules = bench.variants()["per vertex float64"]
    multigrid = bench.Multigrid(1500, 2.0, 85.0, rules)
    for k, solve in enumerate((first, second)):
        operator = multigrid.operator(solve["matrix"], solve["positions"], solve["project"])
        assert operator.fresh == (k == 0)
        operator.tolerance = 1e-3
        operator.solve(solve["rhs"])
    assert all(r <= 1e-3 for r in multigrid.stats.residuals), multigrid.stats.residuals
    # The reused hierarchy's finest smoother is bound to the second matrix: its cycle
    # equals the one of a hierarchy whose finest level took that matrix at its setup's
    # coarse levels (the same object, smoothers bound again by hand).
    from pyamg.relaxation.smoothing import change_smoothers

    r = np.random.default_rng(0).standard_normal(second["matrix"].shape[0])
    reused = multigrid.cycle(r)
    ml = multigrid._ml
    change_smoothers(ml, *rules.smoothers())
    np.testing.assert_array_equal(reused, ml.aspreconditioner(cycle=rules.cycle) @ r)
