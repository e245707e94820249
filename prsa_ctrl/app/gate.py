"""How ``prsa-app`` admits pages: sessions built off the server's event loop, with caps.

Building a page's session (plant, loop models, Tuner, first design, baselines, landscape) takes
seconds of CPU, and building its Bokeh models a fraction of one. Done inside Bokeh's
``make_document`` it blocks Tornado's only event-loop thread: every other page waits, and a flood
of page loads freezes them all. :class:`PageGate` instead

- answers a page load at once with a placeholder (``data-k="loading"``) and builds nothing
  for it: a plain ``GET /`` (no browser behind it) costs a one-``Div`` document, dropped by
  Bokeh :data:`UNUSED_SESSION_S` s later;
- starts the build when the browser has rendered the placeholder and says so (Bokeh's
  ``DocumentReady`` event): on one builder thread, one page at a time, never on the event
  loop; the finished page replaces the placeholder in a next-tick callback;
- admits at most :data:`MAX_PENDING_PAGES` pages waiting for or in their build and at most
  :data:`MAX_LIVE_PAGES` pages built or being built; a page beyond either limit shows one line
  (``data-k="refused"``) saying which limit and what to do, and costs nothing more;
- when a page's session ends (its tab closed, then Bokeh's unused-session lifetime), drops the
  page, its tuners and caches, and runs the garbage collector and ``malloc_trim`` on the
  builder thread, so the memory goes back to the system.
"""

from __future__ import annotations

import gc
import html
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from functools import partial

__all__ = ["PageGate", "MAX_PENDING_PAGES", "MAX_LIVE_PAGES", "UNUSED_SESSION_S", "CHECK_UNUSED_S"]

#: Pages waiting for or in their build at one time (the builder builds one at a time).
MAX_PENDING_PAGES = 4
#: Pages built or being built at one time (each holds its session: about 15 MB).
MAX_LIVE_PAGES = 16
#: A session without a connected browser (a closed tab, a page load without a browser) is
#: dropped this many seconds after its last connection (Bokeh's unused-session lifetime).
UNUSED_SESSION_S = 10
#: How often the server looks for such sessions, s.
CHECK_UNUSED_S = 5

#: Delay from a session's end to the garbage collection that frees its page, s.
RELEASE_DELAY_S = 2.0

_TITLE = "prsa-app: speed-loop tuning"


class _Slot:
    """One document's way through the gate: ``waiting`` (placeholder shown) -> ``building``
    -> ``ready`` (built, not yet in the document) -> ``live``; or ``refused``; ``dead`` once
    Bokeh destroyed the session."""

    __slots__ = ("doc", "state", "placeholder", "future", "page")

    def __init__(self, doc, placeholder) -> None:
        self.doc, self.placeholder = doc, placeholder
        self.state = "waiting"
        self.future: Future | None = None
        self.page = None


class PageGate:
    """The server's page factory (the function of Bokeh's ``FunctionHandler``): see the module
    docstring.

    Parameters
    ----------
    plant, scene : str, optional
        Built-in name or path of the plant and the scene every page starts with.
    warm : bool
        Prepare the next page's session ahead in a second thread
        (:class:`prsa_ctrl.app.page.WarmSessions`), so that a page opens with its numbers ready.
    max_pending, max_live : int
        The limits (:data:`MAX_PENDING_PAGES`, :data:`MAX_LIVE_PAGES`).
    """

    def __init__(self, plant: str | None = None, scene: str | None = None, warm: bool = False,
                 max_pending: int = MAX_PENDING_PAGES, max_live: int = MAX_LIVE_PAGES) -> None:
        from .page import WarmSessions

        if not (isinstance(max_pending, int) and isinstance(max_live, int) and 1 <= max_pending <= max_live):
            raise ValueError(f"max_pending = {max_pending!r}, max_live = {max_live!r}; expected integers "
                             "1 <= max_pending <= max_live")
        self.plant, self.scene = plant, scene
        self.max_pending, self.max_live = max_pending, max_live
        self._lock = threading.Lock()
        self._builder = ThreadPoolExecutor(1, thread_name_prefix="prsa-app-build")
        self._warm = WarmSessions(plant, scene) if warm else None
        self.pending = 0  # slots building (admitted, page not built yet)
        self.live = 0  # slots ready or live (a built page holding its session)
        self._slots: set = set()  # slots ready or live

    # ---- on the event loop ---------------------------------------------------------------

    def __call__(self, doc) -> None:
        """Fill a new document with the placeholder (fast; on the event loop)."""
        from bokeh.events import DocumentReady
        from bokeh.models import CustomJS, Div

        from .fitpanel import SIZE_CHECK_JS

        placeholder = Div(text="<span data-k='loading'>prsa-app: preparing the page ...</span>",
                          css_classes=["prsa-loading"], sizing_mode="stretch_width")
        slot = _Slot(doc, placeholder)
        doc.add_root(placeholder)
        doc.title = _TITLE
        doc.on_event(DocumentReady, partial(self._ready, slot))
        doc.js_on_event("document_ready", CustomJS(code=SIZE_CHECK_JS))  # the browser's upload size check
        doc.on_session_destroyed(partial(self._destroyed, slot))

    def counts(self) -> tuple[int, int]:
        """``(pending, live)`` pages now."""
        with self._lock:
            return self.pending, self.live

    def _ready(self, slot: _Slot, event) -> None:
        """The browser rendered the placeholder: admit the page and start its build, or refuse it."""
        with self._lock:
            if slot.state != "waiting":
                return  # a second DocumentReady (the page reconnected)
            if self.pending >= self.max_pending:
                line = (f"prsa-app: busy: {self.pending} pages are being prepared (at most {self.max_pending} at a "
                        "time); reload this page in a few seconds")
            elif self.pending + self.live >= self.max_live:
                line = (f"prsa-app: {self.pending + self.live} pages are open (at most {self.max_live}); close one "
                        f"(its session ends {UNUSED_SESSION_S} s later) and reload this page")
            else:
                line = None
                slot.state = "building"
                self.pending += 1
            if line is not None:
                slot.state = "refused"
        if line is not None:
            slot.placeholder.text = f"<span data-k='refused'>{html.escape(line)}</span>"
            return
        slot.future = self._builder.submit(self._build, slot)
        slot.future.add_done_callback(partial(self._built, slot))

    def _attach(self, slot: _Slot) -> None:
        with self._lock:
            if slot.state != "ready":
                return
            slot.state = "live"
        slot.doc.remove_root(slot.placeholder)
        slot.page.attach()

    def _failed(self, slot: _Slot, line: str) -> None:
        slot.placeholder.text = f"<span data-k='refused'>{html.escape(line)}</span>"

    def _destroyed(self, slot: _Slot, session_context) -> None:
        """Bokeh dropped the session: free the slot, drop a page never attached, give the
        memory back (a live page closes itself: :meth:`AppPage._destroyed`)."""
        with self._lock:
            prev, slot.state = slot.state, "dead"
            page, slot.page = slot.page, None
            if prev in ("ready", "live"):
                self.live -= 1
                self._slots.discard(slot)
        if prev == "building" and slot.future is not None:
            slot.future.cancel()  # not started yet: _built frees its place
        if prev == "ready" and page is not None:
            page.close()
        # Bokeh drops its references to the document after this callback: collect a little later
        timer = threading.Timer(RELEASE_DELAY_S, self._release)
        timer.daemon = True
        timer.start()

    def _release(self) -> None:
        try:
            self._builder.submit(_release_memory)
        except RuntimeError:  # shut down
            pass

    # ---- on the builder thread -----------------------------------------------------------

    def _build(self, slot: _Slot):
        from .page import AppPage
        from .session import AppSession

        if slot.state == "dead":
            return None
        session = self._warm.take() if self._warm is not None else AppSession(self.plant, self.scene)
        try:
            return AppPage(slot.doc, session=session, attach=False)
        except BaseException:
            session.close()
            raise

    def _built(self, slot: _Slot, fut: Future) -> None:
        page = error = None
        if not fut.cancelled():
            error = fut.exception()
            page = None if error is not None else fut.result()
        with self._lock:
            self.pending -= 1
            alive = slot.state == "building"
            if alive and page is not None:
                slot.state, slot.page = "ready", page
                self.live += 1
                self._slots.add(slot)
        if not alive:
            if page is not None:
                page.close()
            return
        if page is not None:
            slot.doc.add_next_tick_callback(partial(self._attach, slot))
        else:
            from .session import one_line

            with self._lock:
                slot.state = "refused"
            what = one_line(error) if error is not None else "cancelled"
            slot.doc.add_next_tick_callback(partial(self._failed, slot, f"prsa-app: the page could not be prepared "
                                                                         f"({what}); reload it"))

    def shutdown(self) -> None:
        """Stop building (pages waiting for their build are dropped) and close every page (their
        workers stopped, a running calibration's fit stopped, uploaded files removed)."""
        self._builder.shutdown(wait=False, cancel_futures=True)
        with self._lock:
            slots, self._slots = list(self._slots), set()
            pages = [s.page for s in slots]
            for s in slots:
                s.state, s.page = "dead", None
        for page in pages:
            if page is not None:
                page.close(wait=True)


def _release_memory() -> None:
    """Collect the cycles a dropped page leaves and hand freed heap back to the system
    (glibc's ``malloc_trim``; nothing where it does not exist)."""
    gc.collect()
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass
