"""The options classes: keywords and ``options=`` are the same call, the per-operation
defaults, the HTTP names, and the timings every operation reports in one shape."""

import dataclasses

import numpy as np
import pytest

import solver
from solver.core.errors import SolverInputError
from solver.options import (
    DeformOptions,
    InterpolateOptions,
    ParameterizeOptions,
    ReconstructOptions,
    SolveOptions,
)
from tests.helpers.meshes import load

STAGES = {"validate", "assemble", "factorize", "solve", "refine"}


@pytest.fixture(scope="module")
def face():
    return load("face.off")


def test_keywords_and_options_object_give_the_same_reconstruction(face):
    V, F = face
    forms = solver.fundamental_forms(V, F)
    args = (forms.faces, forms.edges, forms.lengths, forms.angles * 0.9)
    by_keywords = solver.reconstruct(*args, frame_weight=10.0, refine=False)
    by_object = solver.reconstruct(*args, options=ReconstructOptions(frame_weight=10.0,
                                                                     refine=False))
    default = solver.reconstruct(*args, refine=False)
    np.testing.assert_array_equal(by_keywords.vertices, by_object.vertices)
    assert by_object.report["frame_weight"] == 10.0
    assert np.abs(default.vertices - by_object.vertices).max() > 1e-6  # the option acts


def test_keywords_override_the_options_object_and_unknown_names_fail(face):
    V, F = face
    base = DeformOptions(refine=False, orthonormalize=True)
    assert base.replace(frame_weight=5.0) == DeformOptions(refine=False, orthonormalize=True,
                                                           frame_weight=5.0)
    with pytest.raises(TypeError, match="no option 'frame_wieght'"):
        solver.deform(V, F, [0], V[[0]], options=base, frame_wieght=5.0)
    with pytest.raises(TypeError, match="no option 'handle_weight'"):
        solver.parameterize(V, F, handle_weight=1.0)  # a deformation's option


def test_per_operation_defaults_are_declared_by_the_classes():
    assert ParameterizeOptions().orthonormalize is True
    assert ReconstructOptions().orthonormalize is DeformOptions().orthonormalize is False
    assert DeformOptions().angle_weight == solver.refine.DEFORM_ANGLE_WEIGHT
    assert ReconstructOptions().angle_weight == InterpolateOptions().angle_weight \
        == solver.refine.ANGLE_WEIGHT
    # Shared fields carry over from another operation's options; the rest keep defaults.
    moved = ParameterizeOptions.given(DeformOptions(frame_weight=3.0, refine=False), {})
    assert (moved.frame_weight, moved.refine, moved.orthonormalize) == (3.0, False, False)
    assert ParameterizeOptions.given(SolveOptions(frame_weight=3.0), {}).orthonormalize


def test_parameterize_orthonormalizes_by_default(face):
    V, F = face
    default = solver.parameterize(V, F, refine=False, seams="none")
    explicit = solver.parameterize(V, F, options=ParameterizeOptions(
        orthonormalize=True, refine=False, seams="none"))
    plain = solver.parameterize(V, F, orthonormalize=False, refine=False, seams="none")
    np.testing.assert_array_equal(default.uv, explicit.uv)
    assert default.report["orthonormalized"] and not plain.report["orthonormalized"]
    assert np.abs(default.uv - plain.uv).max() > 1e-6


def test_api_names_map_to_the_library_fields():
    options = ReconstructOptions.from_api({"solver": "superlu", "tolerance": 1e-6,
                                           "refine": None, "frame_weight": 7.0})
    assert (options.backend, options.integrability_tol, options.frame_weight) == (
        "superlu", 1e-6, 7.0)
    assert options.refine is None  # null is the default
    with pytest.raises(SolverInputError) as caught:
        InterpolateOptions.from_api({"orthonormalize": True})  # not an interpolate option
    assert caught.value.field == "options.orthonormalize"
    with pytest.raises(SolverInputError):
        ReconstructOptions.from_api({"cotan_floor": 1e-3})  # the library's only


def test_every_field_is_described():
    for cls in (ReconstructOptions, DeformOptions, ParameterizeOptions, InterpolateOptions):
        for field in dataclasses.fields(cls):
            assert len(field.metadata["description"]) > 20, (cls.__name__, field.name)


def test_timings_have_one_shape_on_every_operation(face):
    V, F = face
    forms = solver.fundamental_forms(V, F)
    reports = [
        solver.reconstruct(forms.faces, forms.edges, forms.lengths, 0.9 * forms.angles,
                           refine=False).report,
        solver.deform(V, F, [5, 700], V[[5, 700]] + [[0, 0, 0], [0, 0, 20.0]],
                      refine=False).report,
        solver.parameterize(V, F, refine=False).report,
    ]
    for report in reports:
        timings = report["timings"]
        assert {"validate", "assemble", "factorize", "solve"} <= set(timings) <= STAGES
        assert all(isinstance(s, float) and s >= 0 for s in timings.values())
