"""The request option models are made from the solver's options classes, and the worker
builds the solver's options of a request in one call."""

import dataclasses
import time

import pytest

import solver
from service.api import schemas
from service.api.task import SessionSpec, TaskRequest
from solver import options as solver_options

MODELS = {schemas.ReconstructOptions: solver.ReconstructOptions,
          schemas.DeformOptions: solver.DeformOptions,
          schemas.ParameterizeOptions: solver.ParameterizeOptions,
          schemas.InterpolateOptions: solver.InterpolateOptions}


@pytest.mark.parametrize("model", MODELS, ids=lambda m: m.__name__)
def test_each_served_option_is_a_field_with_the_libraries_default(model):
    source = MODELS[model]
    served = {solver_options.api_name(f): f for f in dataclasses.fields(source)
              if f.metadata["served"]}
    service_only = {"require_integrable"} if model is schemas.ReconstructOptions else set()
    assert set(model.model_fields) == set(served) | service_only
    schema = model.model_json_schema()["properties"]
    for name, field in served.items():
        assert model.model_fields[name].default == field.default, name
        assert schema[name]["description"].startswith(field.metadata["description"]), name


def test_the_schema_checks_the_declared_bounds():
    with pytest.raises(ValueError, match="frame_weight"):
        schemas.DeformOptions(frame_weight=0.0)
    with pytest.raises(ValueError, match="frame_weight"):
        schemas.ReconstructOptions(frame_weight=2 * solver_options.MAX_WEIGHT)
    with pytest.raises(ValueError, match="solver"):
        schemas.InterpolateOptions(solver="mumps")
    assert schemas.ParameterizeOptions().orthonormalize is True


def test_solve_options_of_a_request_in_one_call():
    dumped = schemas.ReconstructParams.model_validate(
        {"options": {"frame_weight": 5.0, "tolerance": 1e-6, "require_integrable": True,
                     "max_seconds": 1000.0}}).model_dump()
    request = TaskRequest("reconstruct", None, dumped, backend="superlu")
    options = request.solve_options(solver.ReconstructOptions)
    assert (options.frame_weight, options.integrability_tol, options.backend) == (
        5.0, 1e-6, "superlu")
    assert options.max_seconds == 1000.0
    # A deadline nearer than max_seconds is the budget; a chosen backend wins.
    soon = TaskRequest("reconstruct", None, {"options": {"solver": "superlu"}},
                       backend="pardiso", deadline=time.time() + 10.0)
    options = soon.solve_options(solver.ReconstructOptions)
    assert options.backend == "superlu" and 0 < options.max_seconds <= 10.0


def test_a_session_spec_gives_deform_options():
    dumped = schemas.DeformOptions(refine=True, orthonormalize=True).model_dump()
    spec = SessionSpec(None, None, None, options=dumped, backend="superlu")
    options = spec.deform_options()
    assert options == solver.DeformOptions(refine=True, orthonormalize=True, backend="superlu")


def test_a_session_deforms_within_the_memory_it_was_admitted_in():
    """POST /v1/sessions' spec carries FFS_MAX_REQUEST_MEMORY as the Deformer's
    ``memory_budget``: ``linear_solver="auto"`` chooses by what admission priced, not by
    the machine's free memory of the moment (a budget too small for a factor goes
    iterative, the default one stays direct, as the library's own choice says)."""
    import json

    import numpy as np

    from service.http.payloads import _session_spec
    from service.settings import Settings
    from service.worker.session import SessionState
    from tests.helpers.meshes import icosphere

    V, F = icosphere(2)
    body = json.dumps({"vertices": V.tolist(), "faces": F.tolist(),
                       "handles": [{"vertex": 0}, {"vertex": 30}]}).encode()
    settings = Settings(workers=1)
    spec = _session_spec(body, settings)
    assert spec.memory_budget == float(settings.max_request_memory)
    assert spec.deform_options().memory_budget == spec.memory_budget
    methods = {}
    for budget in (spec.memory_budget, 1e5):
        state = SessionState(dataclasses.replace(spec, memory_budget=budget), 30.0)
        methods[budget] = state.deformer.last_linear_solver["method"]
        moved = state.deformer.solve(V[[0, 30]] + [0.0, 0.0, 0.1], refine=False)
        assert np.isfinite(moved).all()
    assert methods == {spec.memory_budget: "direct", 1e5: "iterative"}, methods
