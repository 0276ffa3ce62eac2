"""Process memory of the service: a worker gives its heap back once idle; the garbage
collector is paused while a body is parsed and restored afterwards."""

from __future__ import annotations

import gc
import threading
import time

import orjson
import psutil

from service.memory import IDLE_RELEASE, free_deferred, free_later, gc_paused
from tests.helpers.meshes import icosphere
from tests.helpers.servers import running_app
from tests.helpers.service import mesh_json


def test_gc_paused_nests_across_threads_and_restores_the_collector():
    assert gc.isenabled()
    inside: list[bool] = []
    release = threading.Event()

    def other() -> None:
        with gc_paused():
            inside.append(gc.isenabled())
            release.wait(5)
        inside.append(gc.isenabled())

    with gc_paused():
        thread = threading.Thread(target=other)
        thread.start()
        while not inside:
            time.sleep(0.001)
        with gc_paused():
            assert not gc.isenabled()
    assert not gc.isenabled()  # the other thread is still parsing
    release.set()
    thread.join(5)
    assert inside == [False, True] and gc.isenabled()
    gc.disable()
    try:
        with gc_paused():
            pass
        assert not gc.isenabled()  # a collector that was off stays off
    finally:
        gc.enable()


def test_idle_worker_gives_the_heap_of_a_large_body_back():
    V, F = icosphere(6)  # 81 920 faces: a 4 MB JSON body, ~40 MB of parsed objects
    body = orjson.dumps({"vertices": V, "faces": F}, option=orjson.OPT_SERIALIZE_NUMPY)
    with running_app(workers=1) as c:
        worker = psutil.Process(c.app.state.services.backend.executor.worker_pids()[0])
        assert c.post("/v1/forms", json=mesh_json(*icosphere(0))).status_code == 200
        time.sleep(IDLE_RELEASE + 0.5)
        before = worker.memory_info().rss
        response = c.post("/v1/forms", content=body, headers={"content-type":
                                                               "application/json"})
        assert response.status_code == 200, response.text[:300]
        after = worker.memory_info().rss
        time.sleep(IDLE_RELEASE + 0.5)
        idle = worker.memory_info().rss
    grown = [(x - before) / 2**20 for x in (after, idle)]
    print(f"worker RSS after a {len(body) / 1e6:.1f} MB body: +{grown[0]:.0f} MB, "
          f"idle {IDLE_RELEASE:g} s later: +{grown[1]:.0f} MB")
    assert grown[1] < 25, grown  # kept, it would stay at 'after' (~+40 MB here)


def test_free_later_keeps_one_object_until_free_deferred():
    import weakref

    class Parsed:
        pass

    first, second = Parsed(), Parsed()
    refs = [weakref.ref(first), weakref.ref(second)]
    free_later(first)
    del first
    assert refs[0]() is not None  # kept past its last reference
    free_later(second)
    del second
    assert refs[0]() is None and refs[1]() is not None  # at most one is kept
    free_deferred()
    assert refs[1]() is None
