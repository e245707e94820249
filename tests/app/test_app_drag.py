"""prsa-app in a real browser: a drag on the Kp-Ki landscape moves the manual design.

The mouse is pressed on the landscape, moved in steps and released, as a person drags; the
manual design's margins shown after the drag are checked against an independent python-control
computation of the sampled loop (``_independent_margins`` of ``test_app_browser``), and the
manual row is on the page while the button is still down (the page updates during the drag).
"""

from __future__ import annotations

import pytest

pytest.importorskip("bokeh", reason="prsa-app tests need the app extra (pip install '.[app]')")

from test_app_browser import _independent_margins, _shot, _text, _tuned  # noqa: E402
from prsa_ctrl.app.session import MANUAL_STATUS, UNSTABLE_STATUS  # noqa: E402


def _press(page, start):
    """Press the mouse at ``start`` (fractions of the landscape's box); returns the map from
    fractions to page pixels."""
    box = page.locator(".prsa-landscape").bounding_box()

    def at(f):
        return box["x"] + f[0] * box["width"], box["y"] + f[1] * box["height"]

    page.mouse.move(*at(start))
    page.mouse.down()
    return at


def test_drag_on_the_landscape_sets_the_manual_design_with_true_margins(app_page):
    page = app_page
    page.locator('[data-k="status"][data-landscape]').wait_for()
    assert page.locator('[data-k="man-kp"]').count() == 0
    start, end = (0.35, 0.65), (0.6, 0.4)
    at = _press(page, start)
    n = 12
    for i in range(1, n + 1):
        f = i / n
        page.mouse.move(*at((start[0] + f * (end[0] - start[0]), start[1] + f * (end[1] - start[1]))))
        if i == n // 2:  # still pressed: the manual design already follows the pointer
            page.locator('[data-k="man-kp"]').wait_for()
            mid = (_text(page, "man-kp"), _text(page, "man-ki"))
    page.mouse.up()
    page.locator('[data-k="status"][data-drag="end"]').wait_for()
    kp, ki = float(_text(page, "man-kp")), float(_text(page, "man-ki"))
    assert (f"{kp:.6g}", f"{ki:.6g}") != mid  # moved on after the midpoint
    ref = _independent_margins(kp, ki)
    assert float(_text(page, "man-ms")) == pytest.approx(ref["ms"], abs=1e-3)
    assert float(_text(page, "man-mt")) == pytest.approx(ref["mt"], abs=1e-3)
    assert float(_text(page, "man-gm")) == pytest.approx(ref["gm"], abs=0.02)
    assert float(_text(page, "man-pm")) == pytest.approx(ref["pm"], abs=0.05)
    assert kp > 0
    assert ki > 0
    # the optimum is kept beside it (not re-tuned by the drag) with its own prediction
    r = _tuned(1.4)
    assert _text(page, "opt-kp") == f"{r.pid.kp:.6g}"
    assert _text(page, "opt-ms") == f"{r.ms:.4f}"
    assert _text(page, "man-status") in (MANUAL_STATUS, UNSTABLE_STATUS)
    if _text(page, "man-status") == MANUAL_STATUS:
        assert _text(page, "man-pred") != "-"
        assert _text(page, "man-pred") != _text(page, "opt-pred")
    _shot(page, "app-drag.png")


def test_drag_then_click_the_click_wins(app_page):
    """A click after a drag sets the gains where it lands (same handler order as a person's)."""
    page = app_page
    page.locator('[data-k="status"][data-landscape]').wait_for()
    at = _press(page, (0.3, 0.7))
    for i in range(1, 6):
        page.mouse.move(*at((0.3 + 0.04 * i, 0.7 - 0.04 * i)))
    page.mouse.up()
    page.locator('[data-k="status"][data-drag="end"]').wait_for()
    dragged = (_text(page, "man-kp"), _text(page, "man-ki"))
    page.mouse.click(*at((0.7, 0.3)))
    page.locator('[data-k="status"][data-landscape]:not([data-mseq])').wait_for()
    clicked = (_text(page, "man-kp"), _text(page, "man-ki"))
    assert clicked != dragged
    kp, ki = map(float, clicked)
    assert float(_text(page, "man-ms")) == pytest.approx(_independent_margins(kp, ki)["ms"], abs=1e-3)


def test_session_manual_design_has_the_loops_true_margins():
    """The session path a drag calls (no browser): AppSession.manual's Ms, Mt, GM, PM against the
    independent python-control loop, at a few points of the plane, stable and not."""
    from prsa_ctrl.app.session import AppSession

    s = AppSession()
    try:
        st = s.default_settings()
        for kp, ki in ((0.05, 5.0), (0.12, 20.0), (0.189, 26.9)):
            v = s.manual(st, kp, ki)
            ref = _independent_margins(kp, ki)
            m = v.design.margins
            assert m.ms == pytest.approx(ref["ms"], abs=2e-4)
            assert m.mt == pytest.approx(ref["mt"], abs=2e-4)
            assert m.gm_db == pytest.approx(ref["gm"], abs=0.02)
            assert m.pm_deg == pytest.approx(ref["pm"], abs=0.05)
            assert v.status == MANUAL_STATUS
            assert v.t
            assert v.design.objective_predicted > 0
    finally:
        s.close()


def test_page_drag_events_coalesce_to_the_last_position():
    """The page's handlers without a browser: a burst of Pan events, then PanEnd, computes the
    manual design of the newest position only (older ones are skipped in the worker) and marks
    the drag's end; the optimum is not re-tuned by a drag."""
    import threading

    from bokeh.document import Document
    from bokeh.events import Pan, PanEnd

    from prsa_ctrl.app.page import make_document

    class Doc(Document):  # next-tick callbacks run at once (no server)
        def add_next_tick_callback(self, callback):
            callback()

    doc = Doc()
    page = make_document(doc)
    try:
        page._tune_pool.submit(lambda: None).result()  # the first tuning applied
        opt = page.opt
        gate = threading.Event()
        page._tune_pool.submit(gate.wait)  # hold the worker while the burst arrives
        calls = []
        manual = page.session.manual
        page.session.manual = lambda *a: calls.append(a[1:3]) or manual(*a)
        tuned = page.session.tuned
        page.session.tuned = lambda *a: calls.append("tuned") or tuned(*a)
        for i in range(1, 9):
            page._drag(Pan(page.land, x=0.01 * i, y=2.0 * i))
        page._drag(PanEnd(page.land, x=0.1, y=20.0))
        gate.set()
        page._tune_pool.submit(lambda: None).result()
        assert calls == [(0.1, 20.0)]
        assert page.man.pid.kp == 0.1
        assert page.man.pid.ki == 20.0
        assert page.opt is opt
        assert 'data-drag="end"' in page.status.text
        assert "data-k='man-kp' style='padding:2px 6px'>0.1<" in page.readout.text
    finally:
        page._destroyed(None)
