"""The browser tests' server and browser: ``python -m prsa_ctrl.app.cli --no-browser`` started
once per session (``app_url``), Debian's Chromium driven by Playwright once per module
(``browser``), and a fresh page per test (``app_page``: of the served app; ``open_page``: of any
URL). Without Chromium or Playwright the browser tests skip with one line, except under
``CI=true`` where they fail.
Shared by test_app_browser, test_app_calibration, test_app_drag, test_app_generic and test_gate
(the last had a twin of the browser fixture, one browser per test; the others imported the
fixtures from test_app_browser)."""

from __future__ import annotations

import contextlib
import os
import queue
import shutil
import subprocess
import sys
import threading

import pytest

CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--no-first-run", "--disable-sync"]
#: Playwright's bound on every wait, ms (it bounds a failure; nothing reads the clock).
TIMEOUT_MS = 60_000


def need_browser():
    """Playwright's sync API and Chromium's path, or a one-line skip (a failure under CI=true)."""
    missing = []
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        sync_playwright = None
        missing.append("playwright (pip install '.[app,test]')")
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        missing.append("chromium (apt-get install chromium)")
    if missing:
        line = "browser tests skipped: missing " + " and ".join(missing)
        if os.environ.get("CI") == "true":
            pytest.fail(line.replace("skipped", "cannot run under CI=true"), pytrace=False)
        pytest.skip(line)
    return sync_playwright, exe


@pytest.fixture(scope="session")
def app_url(tmp_path_factory):
    """The URL of ``prsa-app`` served by its command (a subprocess, free port, printed), started
    once for the page tests of every module (of a pytest-xdist worker): each page is a session of
    its own (a browser context of its own, closed after its test), so the modules share nothing
    but the server process, its start and its imports (it was started once per module, four
    times); its log is read on failure only."""
    log = open(tmp_path_factory.mktemp("app") / "server.log", "w+")
    proc = subprocess.Popen([sys.executable, "-m", "prsa_ctrl.app.cli", "--no-browser"], stdout=subprocess.PIPE,
                            stderr=log, text=True, cwd=str(tmp_path_factory.getbasetemp()))
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: lines.put(proc.stdout.readline()), daemon=True).start()
    try:
        first = lines.get(timeout=120)
        log.seek(0)
        assert first.startswith("prsa-app: serving http://127.0.0.1:"), (first, log.read())
        yield first.split()[2]
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        proc.stdout.close()
        log.close()


@contextlib.contextmanager
def _chromium():
    sync_playwright, exe = need_browser()
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=exe, args=CHROMIUM_ARGS)
        yield b
        b.close()


def _page_opener(browser):
    """``(open_, made)``: ``open_(url) -> (context, page)`` opens a page at ``url`` in a browser
    context of its own (a new app session), every wait bounded by ``TIMEOUT_MS``; ``made`` holds
    the contexts, closed after the test."""
    made = []

    def open_(url: str, **context_options):
        ctx = browser.new_context(viewport={"width": 1500, "height": 1300}, **context_options)
        made.append(ctx)
        pg = ctx.new_page()
        pg.set_default_timeout(TIMEOUT_MS)
        pg.goto(url, timeout=TIMEOUT_MS)
        return ctx, pg

    return open_, made


@pytest.fixture(scope="module")
def browser():
    """Headless Chromium (one per module: Playwright's sync API keeps an event loop of its own,
    closed with the module)."""
    with _chromium() as b:
        yield b


@pytest.fixture
def open_page(browser):
    """``open_page(url) -> (context, page)`` in the module's browser (:func:`_page_opener`)."""
    open_, made = _page_opener(browser)
    yield open_
    for ctx in made:
        ctx.close()


@pytest.fixture(scope="module")
def module_open_page(browser):
    """``open_page`` whose pages stay open for the module (a page shared by several of its tests,
    made by a module-scoped fixture of the test file: e.g. test_app_calibration's ``fitted_page``)."""
    open_, made = _page_opener(browser)
    yield open_
    for ctx in made:
        ctx.close()


@pytest.fixture
def fresh_open_page():
    """``open_page`` in a browser of the test's own (test_gate: its pages' sessions are counted
    and collected; in the module's browser the second test ran slower, 14.0 -> 23.0 s)."""
    with _chromium() as b:
        open_, made = _page_opener(b)
        yield open_
        for ctx in made:
            ctx.close()


@pytest.fixture(scope="module")
def shared_app_page(browser, app_url):
    """One page of the served app for the module's hostile-input tests (a refused select value or
    upload: each waits for its own one-line error by its text, and none changes the plant or
    the design; a refused plant upload among them) and for the tests that read the page's first
    design as it is (its copied code, its downloads, its Bode data: the Bode unit, which that test
    switches to rad/s after reading it in Hz, is read by no other test). A page costs about 4.3 s
    of CPU (Chromium 2.9 s, the server 1.4 s; 4 pages measured at load 26), most of
    test_app_browser's; eleven such tests had a page each. (The
    uploads above the limit use it too: each then uploads a small file of its own name and bytes,
    which the page must read; a refused 25 MB file never reaches the server, so an earlier
    test's identical upload would look unchanged to it.)"""
    open_, made = _page_opener(browser)
    _, pg = open_(app_url, accept_downloads=True)
    pg.locator('[data-k="opt-ms"]').wait_for()
    pg.locator('[data-k="status"]').wait_for()
    yield pg
    for ctx in made:
        ctx.close()


@pytest.fixture
def app_page(open_page, app_url):
    """A new page of the served app (its own browser context: a new session), ready."""
    _, pg = open_page(app_url, accept_downloads=True)
    pg.locator('[data-k="opt-ms"]').wait_for()
    pg.locator('[data-k="status"]').wait_for()
    return pg
