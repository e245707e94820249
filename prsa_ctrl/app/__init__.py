"""prsa-app: interactive, robustness-constrained speed-loop tuning in the browser.

Needs the optional extra (``pip install "prsa-ctrl[app]"``: Bokeh); nothing else in the toolkit
imports this package, so the core install stays as light as it is.

- ``prsa-app [--plant NAME|PATH] [--scene NAME|PATH] [--port N] [--no-browser]`` serves the app
  on 127.0.0.1 (:func:`prsa_ctrl.app.cli.main`);
- :func:`application` returns the Bokeh application (for ``bokeh.server``, or embedding);
- :func:`show` displays the app inside a Jupyter notebook.

The numbers come from :class:`prsa_ctrl.app.session.AppSession` (no GUI code), which calls the
toolkit's public functions; calibration from a drive log calls ``prsa-fit``'s library entry
(:meth:`~prsa_ctrl.app.session.AppSession.calibrate`, :func:`prsa_ctrl.identification.calibrate.calibrate_logs`), and the generic tuner's model is
:mod:`prsa_ctrl.app.generic` (``tune_pid`` on a typed transfer function).
"""

from __future__ import annotations

__all__ = ["application", "show"]


def application(plant: str | None = None, scene: str | None = None, warm: bool = False):
    """The app as a Bokeh :class:`~bokeh.application.Application`.

    Parameters
    ----------
    plant, scene : str, optional
        Built-in name or path of the plant and of the load-step scene (defaults:
        ``paper-iprsm``, ``paper-load-step``). Checked at once: a bad one raises
        :class:`~prsa_ctrl.app.session.AppInputError` (one line).
    warm : bool
        Prepare each next page's session (loop models, Tuner, first design, landscape) in a
        background thread, so that pages open with their numbers ready (``prsa-app`` does).

    Returns
    -------
    bokeh.application.Application
        Its pages are built off the server's event loop and capped
        (:class:`prsa_ctrl.app.gate.PageGate`: at most
        :data:`~prsa_ctrl.app.gate.MAX_PENDING_PAGES` pages in preparation and
        :data:`~prsa_ctrl.app.gate.MAX_LIVE_PAGES` open; the gate is ``app.prsa_gate``).
    """
    from bokeh.application import Application
    from bokeh.application.handlers.function import FunctionHandler

    from .gate import PageGate
    from .session import AppSession

    AppSession(plant, scene).close()  # bad files fail here, not in the browser
    gate = PageGate(plant, scene, warm=warm)
    app = Application(FunctionHandler(gate))
    app.prsa_gate = gate
    return app


def show(plant: str | None = None, scene: str | None = None, notebook_url: str = "localhost:8888"):
    """Show the app in a Jupyter notebook cell (Bokeh serves it from the kernel).

    Parameters
    ----------
    plant, scene : str, optional
        See :func:`application`.
    notebook_url : str
        Where the notebook server runs (as Bokeh's ``show`` takes it).

    Returns
    -------
    bokeh.application.Application
        The application shown (pass it to ``bokeh.io.show`` to show it again).
    """
    from bokeh.io import output_notebook
    from bokeh.io import show as bokeh_show

    app = application(plant, scene)
    output_notebook(hide_banner=True)
    bokeh_show(app, notebook_url=notebook_url)
    return app
