"""``GET /v1/me``'s size limits (:func:`service.http.payloads.size_limits`) and the limits
a request carries to its worker (:func:`~service.http.payloads.sync_limits`,
:func:`~service.http.payloads.limits`) come from one computation: for every operation of the
registry, under several settings (memory binding or FFS_MAX_FACES binding, short and long
deadlines), what the caller is shown is what a request is held to (a mesh of the shown
faces passes :func:`service.api.decoding.check_limits`, one face more is refused), and the
numbers are the admission models' (:mod:`service.backends.admission`)."""

from __future__ import annotations

import pytest

from service.api.budgets import TIME_POLICY
from service.api.decoding import check_limits
from service.api.problems import ProblemError
from service.backends.admission import pricing
from service.http.payloads import limits, size_limits, sync_limits
from service.operations import OPERATIONS
from service.settings import Settings

GIB = 1024**3
SETTINGS = [{}, {"max_request_memory": 1 * GIB}, {"max_request_memory": 2 * GIB},
            {"max_request_memory": 8 * GIB, "request_timeout": 10},
            {"max_request_memory": 30 * GIB, "max_faces": 2_000_000},
            {"max_request_memory": 64 * GIB, "max_faces": 10_000_000, "request_timeout": 600},
            {"max_faces": 1000}]


@pytest.mark.parametrize("overrides", SETTINGS, ids=lambda o: ",".join(map(str, o.values()))
                         or "defaults")
def test_what_me_shows_is_what_a_request_is_held_to(overrides):
    settings = Settings(**overrides)
    shown = size_limits(settings)
    memory = settings.max_request_memory
    seconds = settings.request_timeout - TIME_POLICY.encode_margin(settings.request_timeout)
    assert set(shown["max_faces_by_operation"]) == {*OPERATIONS, "sessions"}
    assert shown["max_faces_by_operation"]["sessions"] == limits(settings).max_faces
    for name, spec in OPERATIONS.items():
        carried = sync_limits(settings, name)
        how = pricing(spec.solves, spec.iterative)
        faces = min(how.faces_within(memory), settings.max_faces)
        sync = min(how.sync_faces_within(seconds, memory), faces)  # never above the size limit
        assert shown["max_faces_by_operation"][name] == carried.max_faces == faces, name
        assert shown["max_sync_faces_by_operation"][name] == carried.max_sync_faces == sync
        assert shown["max_sync_faces_by_operation"][name] <= shown["max_faces_by_operation"][name]
        assert limits(settings, name).max_faces == faces  # a job: the same faces, no deadline
        assert limits(settings, name).max_sync_faces is None
        most = min(faces, sync)
        check_limits(0, most, carried, "input")
        with pytest.raises(ProblemError):
            check_limits(0, most + 1, carried, "input")
        if not spec.iterative:
            assert name not in shown["max_direct_faces_by_operation"]
            assert name not in shown["max_linear_faces_by_operation"]
            assert name not in shown["max_linear_sync_faces_by_operation"]
            continue
        direct = min(how.direct_faces(memory), settings.max_faces)
        assert shown["max_direct_faces_by_operation"][name] == carried.max_direct_faces == direct
        linear = pricing(spec.solves, spec.iterative, linear=True)
        answering = carried.answering({"options": {"refine": False}})
        assert answering is carried.linear
        linear_faces = min(linear.faces_within(memory), settings.max_faces)
        assert shown["max_linear_faces_by_operation"][name] == answering.max_faces == linear_faces
        assert (shown["max_linear_sync_faces_by_operation"][name] == answering.max_sync_faces
                == min(linear.sync_faces_within(seconds, memory), linear_faces))
        most = min(linear_faces, answering.max_sync_faces)
        check_limits(0, most, answering, "input")
        with pytest.raises(ProblemError):
            check_limits(0, most + 1, answering, "input")


def test_the_settings_cover_both_bindings():
    """The family above has settings where memory sets reconstruct's faces and where
    FFS_MAX_FACES does, and a deadline that binds before either."""
    bound = {sync_limits(Settings(**o), "reconstruct").max_memory is not None for o in SETTINGS}
    assert bound == {True, False}
    assert any(sync_limits(Settings(**o), "reconstruct").max_sync_faces
               < sync_limits(Settings(**o), "reconstruct").max_faces for o in SETTINGS)
    # and one where the deadline alone would admit more faces than the size limit
    assert any(pricing(spec.solves, spec.iterative).sync_faces_within(
        Settings(**o).request_timeout, Settings(**o).max_request_memory)
        > sync_limits(Settings(**o), name).max_faces
        for o in SETTINGS for name, spec in OPERATIONS.items())


def test_a_linear_answer_is_held_to_its_own_synchronous_limit(monkeypatch):
    """Today both answers' synchronous limits are priced by the time to the first (linear)
    answer, so they coincide; with a linear answer priced faster (its first answer in half
    the time) the two differ, and ``GET /v1/me``'s ``max_linear_sync_faces_by_operation`` is
    the one a ``refine: false`` request is held to, while a refined request keeps
    ``max_sync_faces_by_operation``."""
    from dataclasses import replace

    from service.backends import admission
    from service.http import payloads

    def faster(how: admission.Pricing) -> admission.Pricing:
        return replace(how, direct=replace(how.direct, first_answer=replace(
            how.direct.first_answer, per_face=how.direct.first_answer.per_face / 2)))

    settings = Settings(max_request_memory=8 * GIB, request_timeout=10)
    before = size_limits(settings)
    assert (before["max_linear_sync_faces_by_operation"]["reconstruct"]
            == before["max_sync_faces_by_operation"]["reconstruct"])
    monkeypatch.setattr(payloads, "pricing", lambda solves, iterative=False, linear=False: (
        faster(pricing(solves, iterative, linear)) if linear else pricing(solves, iterative)))
    shown = size_limits(settings)
    refined = shown["max_sync_faces_by_operation"]["reconstruct"]
    linear = shown["max_linear_sync_faces_by_operation"]["reconstruct"]
    assert refined == before["max_sync_faces_by_operation"]["reconstruct"] < linear
    assert linear < shown["max_linear_faces_by_operation"]["reconstruct"]  # time binds
    carried = sync_limits(settings, "reconstruct")
    check_limits(0, linear, carried.answering({"options": {"refine": False}}), "input")
    with pytest.raises(ProblemError) as refused:
        check_limits(0, linear + 1, carried.answering({"options": {"refine": False}}), "input")
    assert refused.value.kind == "use-a-job" and f"{linear} faces" in str(refused.value)
    with pytest.raises(ProblemError) as refused:
        check_limits(0, refined + 1, carried.answering({"options": {}}), "input")
    assert refused.value.kind == "use-a-job"
