"""The page never waits forever for its worker (issue 25), in a real browser against a real
uvicorn: a worker that starts late loses no call (the page waits for its "ready"), and a
call whose answer does not come (a lost message, a worker that never starts, one that hangs)
is rejected after a bound with a message in words; ``window.app.ready`` settles either way,
and the next call runs on a new worker.

The workers here are the page's own js/worker.js behind a wrapper module
(tests.helpers.web.worker_wrapper) that delays it, drops a message or blocks it on purpose.
"""

from __future__ import annotations

from typing import Any

from tests.helpers import REPO
from tests.helpers.web import worker_wrapper

SAMPLE = (REPO / "service" / "static" / "samples" / "torus.off").read_bytes()

# The worker module is imported only once a BroadcastChannel "gate" message arrives (the page
# sends one right after its first postMessage to the worker) or after 2 s: whatever the page
# posts before the worker listens arrives at a worker with no message handler.
LATE_START = worker_wrapper(
    """
    const opened = await new Promise((open) => {
      new BroadcastChannel("gate").onmessage = () => open("by the page's first message");
      setTimeout(() => open("by the timer"), 2000);
    });
    await new Promise((r) => setTimeout(r, 200));
    new BroadcastChannel("gate-report").postMessage(opened);
    """,
    late=True,
    page_setup="""
      const gate = new BroadcastChannel("gate");
      const post = worker.postMessage.bind(worker);
      worker.postMessage = (...args) => { post(...args); gate.postMessage("open"); };
      new BroadcastChannel("gate-report").onmessage = (e) => { window.__gate = e.data; };
    """)

# Messages about files named lost*.off never reach the worker's handler (a lost message);
# while window.__stillborn is set, new workers never start listening; reading stuck.off
# blocks the worker's thread (a hung worker: it stops pulsing).
FAULTS = worker_wrapper(
    """
    self.addEventListener("message", (event) => {
      if (/^lost/.test(event.data?.args?.name ?? "")) event.stopImmediatePropagation();
    });
    if (new URL(import.meta.url).hash === "#stillborn") await new Promise(() => {});
    const plainFetch = self.fetch;
    self.fetch = (input, init) => {
      if (init?.body instanceof FormData && init.body.get("file")?.name === "stuck.off") {
        for (;;) {}  // eslint-disable-line no-empty
      }
      return plainFetch(input, init);
    };
    """,
    late=True, url_suffix="window.__stillborn ? '#stillborn' : ''")
# Every mesh file's message is lost, the default sample's included.
NO_READING = worker_wrapper(
    """
    self.addEventListener("message", (event) => {
      if (event.data?.kind === "readMesh") event.stopImmediatePropagation();
    });
    """,
    late=True)


def _upload(page, name: str, content: bytes) -> None:
    page.set_input_files("#mesh-file", files=[{"name": name, "mimeType": "text/plain",
                                               "buffer": content}])


def test_a_late_worker_loses_no_call(web):
    """The race of issue 25, made certain: the worker's handler is installed only after the
    page would have posted its first call. The page waits for the worker's "ready", so the
    default sample loads (before the fix the first call was dropped and the page hung)."""
    web.page.add_init_script(LATE_START)
    page = web.open(timeout=60)
    assert web.app("app.state.name") == "face.off"
    assert web.app("app.state.integrability.integrable") is True
    assert page.evaluate("window.__gate") == "by the timer"  # nothing posted before "ready"
    assert web.app("app.diagnostics()")["startup"] == "ready"
    assert web.shown_errors() == []
    # Calls after the start run as usual.
    page.select_option("#sample-select", "torus.off")
    web.wait_for("window.app.state.name === 'torus.off'")
    web.idle()
    assert web.app("app.state.integrability") is not None


def test_ready_settles_when_the_first_reply_never_comes(web):
    """The default sample's message is lost: after the acknowledgement bound (15 s) the call
    is rejected, `window.app.ready` settles and the page says in words what did not answer.

    The page's clock is Playwright's (``page.clock``, flowing as usual): once the call is
    posted and not taken up, it is fast-forwarded to 1 s short of the page's default bound
    (the call still waits) and then 2 s more (rejected), instead of the test waiting 15 s."""
    web.page.add_init_script(NO_READING)
    web.page.clock.install()
    web.page.goto(f"{web.base}/?test", timeout=60_000)
    web.wait_for("window.app !== undefined && window.app.diagnostics().workerCalls.some("
                 "(c) => c.posted && !c.accepted)", timeout=60,
                 what="the default sample's call to be posted to the worker")
    (call,) = web.evaluate("window.app.diagnostics().workerCalls")
    web.page.clock.fast_forward(max(0, 14_000 - call["waitingMs"]))
    web.frame()
    assert web.evaluate("window.app.diagnostics().workerCalls") != [], "rejected before 15 s"
    assert web.shown_errors() == []
    web.page.clock.fast_forward(2_000)
    web.evaluate("window.app.ready", timeout=60, what="window.app.ready")
    web.idle()
    diagnostics = web.app("app.diagnostics()")
    assert diagnostics["startup"] == "failed", diagnostics
    assert diagnostics["workerCalls"] == []
    (error,) = web.shown_errors()
    assert error["detail"] == ("The page's background worker did not begin reading face.off "
                               "within 15 s. It was restarted: try again."), error
    assert "did not begin reading face.off" in web.page.locator(".toast").first.inner_text()


def _first_failed_upload(web, limits: str, name: str) -> tuple[Any, dict[str, Any]]:
    """Open the page with :data:`FAULTS` and ``limits`` (a JavaScript object) assigned to
    its worker limits, upload ``name`` (a file those faults make fail) and wait until the
    page is idle again; return the page and the one error it shows."""
    web.page.add_init_script(FAULTS)
    page = web.open()
    web.app(f"Object.assign(app.workerLimits, {limits})")
    _upload(page, name, SAMPLE)
    web.wait_for("window.app.state.errors.length >= 1", timeout=20)
    web.idle()
    (error,) = web.shown_errors()
    return page, error


def test_a_lost_message_is_reported_and_the_worker_replaced(web):
    """An upload whose message never reaches the worker's handler fails after the bound
    with a message naming what the page was doing; a worker that then never starts fails
    after its own bound; afterwards the page reads files again on a new worker, and the
    mesh on screen stayed the previous one throughout."""
    page, lost = _first_failed_upload(web, "{ ackMs: 1500, startMs: 1500 }", "lost.off")
    assert lost["title"] == "The page stopped waiting", lost
    assert lost["detail"] == ("The page's background worker did not begin reading lost.off "
                              "within 1.5 s. It was restarted: try again."), lost
    toast = page.locator(".toast").first.inner_text()
    assert "did not begin reading lost.off" in toast, toast
    assert web.app("app.state.name") == "face.off"
    assert web.app("app.diagnostics().workerCalls") == []

    page.evaluate("window.__stillborn = true")
    _upload(page, "torus-copy.off", SAMPLE)
    web.wait_for("window.app.state.errors.length >= 2", timeout=20)
    web.idle()
    assert web.shown_errors()[1]["detail"] == (
        "The page's background worker did not start within 1.5 s. It was restarted: "
        "try again.")
    assert web.app("app.state.name") == "face.off"

    page.evaluate("window.__stillborn = false")
    _upload(page, "torus-copy.off", SAMPLE)
    web.wait_for("window.app.state.name === 'torus-copy.off'", timeout=30)
    web.idle()
    assert web.app("app.state.integrability") is not None
    assert len(web.shown_errors()) == 2


def test_a_hung_worker_is_reported_and_replaced(web):
    """A worker that took the call up and then stops answering (its thread blocked: no
    pulses) fails after the silence bound, in words; the page reads the next file."""
    page, stuck = _first_failed_upload(web, "{ silenceMs: 2000 }", "stuck.off")
    assert stuck["detail"] == ("The page's background worker stopped responding (nothing "
                               "for 2 s) while reading stuck.off. It was restarted: try "
                               "again."), stuck
    _upload(page, "torus-copy.off", SAMPLE)
    web.wait_for("window.app.state.name === 'torus-copy.off'", timeout=30)
    web.idle()
    assert web.shown_errors() == [stuck]
