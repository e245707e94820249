"""prsa-app's page admission (:mod:`prsa_ctrl.app.gate`) against an in-process Bokeh server, in a
real browser (Playwright + Debian's Chromium: ``fresh_open_page`` of tests/app/conftest.py, a browser per test).

A session build is held on purpose (``AppSession.__init__`` waits on an event the test sets),
so "the event loop answers while a session is being built" is a fact of the test's order, not
of the clock: Playwright's timeouts only bound a failure.
"""

from __future__ import annotations

import asyncio
import gc
import queue
import threading
import urllib.request
import weakref

import pytest

pytest.importorskip("bokeh", reason="prsa-app tests need the app extra (pip install '.[app]')")

from test_app_browser import _text  # noqa: E402


class _Served:
    """A Bokeh server for ``app`` on a free loopback port, run on its own thread."""

    def __init__(self, app, unused_ms: int = 15_000, check_ms: int = 17_000) -> None:
        from prsa_ctrl.app.cli import free_port

        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}/"
        got: queue.Queue = queue.Queue()

        def run():
            from bokeh.server.server import Server
            from tornado.ioloop import IOLoop

            asyncio.set_event_loop(asyncio.new_event_loop())
            loop = IOLoop.current()
            try:
                server = Server({"/": app}, io_loop=loop, address="127.0.0.1", port=self.port, num_procs=1,
                                allow_websocket_origin=[f"127.0.0.1:{self.port}"],
                                unused_session_lifetime_milliseconds=unused_ms,
                                check_unused_sessions_milliseconds=check_ms)
                server.start()
            except BaseException as exc:  # noqa: BLE001 - reported by the test thread
                got.put(exc)
                return
            got.put((server, loop))
            loop.start()

        self.thread = threading.Thread(target=run, daemon=True)
        self.thread.start()
        out = got.get(timeout=60)
        if isinstance(out, BaseException):
            raise out
        self.server, self.loop = out

    def stop(self) -> None:
        self.loop.add_callback(self.server.stop)
        self.loop.add_callback(self.loop.stop)
        self.thread.join(timeout=30)


@pytest.fixture
def held(monkeypatch):
    """``AppSession.__init__`` held until ``release`` is set (``entered`` tells one is held)."""
    from prsa_ctrl.app.session import AppSession

    entered, release = threading.Event(), threading.Event()
    original = AppSession.__init__
    made: list = []  # weak references to the sessions built since hold()

    def init(self, *a, **k):
        if not release.is_set():
            entered.set()
            release.wait(timeout=300)
        original(self, *a, **k)
        made.append(weakref.ref(self))

    yield made, (lambda: monkeypatch.setattr(AppSession, "__init__", init)), entered, release
    release.set()


def test_a_page_in_preparation_blocks_neither_the_loop_nor_the_open_pages(fresh_open_page, held):
    """While a new page's session is being built (held): a static file and another page load
    are answered, and the page already open re-tunes after a slider step. Today's main builds
    the session inside Bokeh's make_document, on the event loop: all three wait."""
    from prsa_ctrl.app import application

    _, hold, entered, release = held
    served = _Served(application())
    try:
        ctx_a, a = fresh_open_page(served.url)
        a.locator('[data-k="opt-ms"]').wait_for()
        a.locator('[data-k="status"]').wait_for()
        hold()
        ctx_b, b = fresh_open_page(served.url)  # its session build is now held
        assert entered.wait(timeout=120), "the second page never started its session build"
        with urllib.request.urlopen(served.url + "static/js/bokeh.min.js", timeout=60) as r:
            assert r.status == 200
            assert len(r.read()) > 100_000
        with urllib.request.urlopen(served.url, timeout=60) as r:
            assert r.status == 200
        handle = a.locator(".prsa-ms .noUi-handle")
        handle.focus()
        a.keyboard.press("ArrowRight")
        a.locator('[data-k="bound-ms"]', has_text="1.45").wait_for()
        a.locator('[data-k="status"]').wait_for()
        assert b.locator('[data-k="loading"]').count() == 1
        assert b.locator('[data-k="opt-ms"]').count() == 0
        release.set()
        b.locator('[data-k="opt-ms"]').wait_for()
        ctx_a.close()
        ctx_b.close()
    finally:
        release.set()
        served.stop()


def test_caps_refuse_with_one_line_and_a_closed_page_frees_its_place_and_memory(fresh_open_page, held):
    from bokeh.application import Application
    from bokeh.application.handlers.function import FunctionHandler

    from prsa_ctrl.app.gate import PageGate, UNUSED_SESSION_S

    made, hold, entered, release = held
    gate = PageGate(max_pending=1, max_live=2)
    served = _Served(Application(FunctionHandler(gate)), unused_ms=500, check_ms=300)
    try:
        hold()
        ctx_b, b = fresh_open_page(served.url)
        assert entered.wait(timeout=120)
        ctx_c, c = fresh_open_page(served.url)  # one page is in preparation: the limit
        c.locator('[data-k="refused"]').wait_for()
        assert _text(c, "refused") == ("prsa-app: busy: 1 pages are being prepared (at most 1 at a time); reload this "
                                       "page in a few seconds")
        release.set()
        b.locator('[data-k="opt-ms"]').wait_for()
        ctx_d, d = fresh_open_page(served.url)
        d.locator('[data-k="opt-ms"]').wait_for()
        ctx_e, e = fresh_open_page(served.url)  # two pages live: the limit
        e.locator('[data-k="refused"]').wait_for()
        assert _text(e, "refused") == (f"prsa-app: 2 pages are open (at most 2); close one (its session ends "
                                       f"{UNUSED_SESSION_S} s later) and reload this page")
        assert gate.counts() == (0, 2)
        assert len(made) == 2
        assert all(r() is not None for r in made)  # the sessions of b and d
        gone = list(made)
        ctx_b.close()
        ctx_d.close()
        e.wait_for_function("() => true")  # a round trip; the server drops b and d on its own
        for _ in range(600):  # bounded: Bokeh's check runs every 0.3 s
            if gate.counts() == (0, 0):
                break
            e.wait_for_timeout(100)
        assert gate.counts() == (0, 0)
        e.reload()
        e.locator('[data-k="opt-ms"]').wait_for()
        for _ in range(100):  # the pages' workers end on their own after the session ends
            gc.collect()
            if all(r() is None for r in gone):
                break
            e.wait_for_timeout(100)
        assert all(r() is None for r in gone), "a closed page's session is still held"
        ctx_c.close()
        ctx_e.close()
    finally:
        release.set()
        gate.shutdown()
        served.stop()
