"""The page's generic-tuner tab: a plant typed as a transfer function, ``tune_pid``'s options,
and the tuned design (gains, true Ms/Mt/Mks, margins, status, Bode, |S| and |T|, |C F S|).

Each change of an input re-tunes in a child process (:class:`prsa_ctrl.app.generic.TuneProcess`)
fed by one worker thread: a change made while a tuning runs ends that tuning at once and starts
the newest, so a long tuning (an optimised filter with a delay) never holds the panel.

Elements the browser tests read carry ``data-k`` attributes (``g-kp``, ``g-ki``, ``g-ms``,
``g-mks``, ``g-state`` ...), the inputs CSS classes ``prsa-g-*``.
"""

from __future__ import annotations

import html
import math
from concurrent.futures import ThreadPoolExecutor
from functools import partial

import numpy as np
from bokeh.layouts import column, row
from bokeh.models import Button, CheckboxGroup, ColumnDataSource, Div, RadioButtonGroup, Select, Span, TextInput
from bokeh.plotting import figure

from ..options import DEFAULT_FREQUENCY_UNIT, FREQUENCY_UNITS, OBJECTIVES, PEAK_BOUND_RANGE
from .generic import GenericSettings, GenericView, TuneProcess, generic_code
from .session import AppInputError, Cancelled, one_line

__all__ = ["GenericPanel", "signature", "frequency_unit_widget", "FrequencyAxes"]


def frequency_unit_widget(css: str) -> RadioButtonGroup:
    """The choice of the frequency axes' unit (:data:`prsa_ctrl.options.FREQUENCY_UNITS`,
    default :data:`~prsa_ctrl.options.DEFAULT_FREQUENCY_UNIT`: Hz)."""
    units = list(FREQUENCY_UNITS)
    return RadioButtonGroup(labels=units, active=units.index(DEFAULT_FREQUENCY_UNIT), css_classes=[css])


class FrequencyAxes:
    """Frequency axes in the unit a :func:`frequency_unit_widget` holds: each source keeps the
    response's ``"w"`` (rad/s, SI) and gets ``"f"`` (in the unit) that the lines draw; the
    figures' x labels name the unit."""

    def __init__(self, widget: RadioButtonGroup, sources, figures) -> None:
        self.widget, self.sources, self.figures = widget, list(sources), list(figures)
        widget.on_change("active", lambda attr, old, new: self.refresh())
        self.refresh()

    @property
    def unit(self) -> str:
        units = list(FREQUENCY_UNITS)
        a = self.widget.active
        return units[a] if isinstance(a, int) and 0 <= a < len(units) else DEFAULT_FREQUENCY_UNIT

    def data(self, data: dict) -> dict:
        """``data`` with its ``"f"`` column: ``"w"`` (rad/s) in the unit."""
        return {**data, "f": np.asarray(data.get("w", []), float) * FREQUENCY_UNITS[self.unit]}

    def refresh(self) -> None:
        for src in self.sources:
            src.data = self.data(dict(src.data))
        for fig in self.figures:
            fig.xaxis.axis_label = f"frequency ({self.unit})"

_PLOT = dict(height=280, sizing_mode="stretch_width", toolbar_location="above")


def _num(v, spec: str) -> str:
    if v is None:
        return "-"
    if isinstance(v, float) and not math.isfinite(v):
        return "inf" if v > 0 else ("-inf" if v < 0 else "-")
    return format(v, spec)


def signature(gs: GenericSettings) -> str:
    """The settings in one line, ``|``-separated (plant, delay, objective, controller, Ms, Mt,
    Mks, filter order, ideal, setpoint weights; ``-`` for no bound): the page marks the shown
    design with it."""
    return "|".join([gs.plant, f"{gs.delay_s:g}", gs.objective, gs.controller, f"{gs.ms_max:g}",
                     "-" if gs.mt_max is None else f"{gs.mt_max:g}", "-" if gs.mks_max is None else f"{gs.mks_max:g}",
                     str(gs.filter_order), str(int(gs.ideal)), str(int(gs.setpoint_weights))])


class GenericPanel:
    """The generic tuner of one page.

    Parameters
    ----------
    doc : bokeh.document.Document
        The page's document (results arrive through its next-tick callbacks).
    """

    def __init__(self, doc) -> None:
        self.doc = doc
        self.view: GenericView | None = None
        self._seq = 0
        self._proc = TuneProcess()
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="prsa-app-generic")
        d = GenericSettings()
        self.plant = TextInput(title="Plant P(s), e.g. 1/(4s+1) or 2(s+1)/((s+2)^2 (0.1s+1))", value=d.plant,
                               css_classes=["prsa-g-plant"])
        self.delay = TextInput(title="Exact delay (s; 0: none)", value="0", css_classes=["prsa-g-delay"])
        self.objective = Select(title="Objective (load step at the plant input)", options=list(OBJECTIVES),
                                value=d.objective, css_classes=["prsa-g-objective"])
        self.controller = RadioButtonGroup(labels=["PI", "PID"], active=0, css_classes=["prsa-g-controller"])
        self.ms = TextInput(title="Ms bound (true peak of |S|)", value=f"{d.ms_max:g}", css_classes=["prsa-g-ms"])
        self.mt = TextInput(title="Mt bound (true peak of |T|; empty: none)", value="", css_classes=["prsa-g-mt"])
        self.mks = TextInput(title="Mks bound (true peak of |C F S|; empty: none)", value="",
                             css_classes=["prsa-g-mks"])
        self.filter = RadioButtonGroup(labels=["no filter", "1st-order filter", "2nd-order filter"], active=0,
                                       css_classes=["prsa-g-filter"])
        self.options = CheckboxGroup(labels=["ideal PID (no derivative filter)", "2-DOF setpoint weights b, c"],
                                     active=[], css_classes=["prsa-g-options"])
        self.tune_button = Button(label="Tune", button_type="primary", css_classes=["prsa-g-tune"])
        self.freq_unit = frequency_unit_widget("prsa-g-freq-unit")
        self.state = Div(text="", css_classes=["prsa-g-state"], sizing_mode="stretch_width")
        self.readout = Div(text="", css_classes=["prsa-g-readout"], sizing_mode="stretch_width")
        self.code = Div(text="", css_classes=["prsa-g-code"], sizing_mode="stretch_width")
        self._figures()
        self.axes = FrequencyAxes(self.freq_unit, [self.src], [self.mag, self.phase, self.st, self.noise_fig])
        for w in (self.plant, self.delay, self.objective, self.ms, self.mt, self.mks):
            w.on_change("value", lambda attr, old, new: self.request())
        for w in (self.controller, self.filter, self.options):
            w.on_change("active", lambda attr, old, new: self.request())
        self.tune_button.on_click(self.request)
        controls = column(self.plant, self.delay, self.objective, self.controller, self.ms, self.mt, self.mks,
                          self.filter, self.options, self.tune_button,
                          Div(text="Frequency axes"), self.freq_unit, width=330)
        views = column(self.state, self.readout, row(self.mag, self.st, sizing_mode="stretch_width"),
                       row(self.phase, self.noise_fig, sizing_mode="stretch_width"), self.code,
                       sizing_mode="stretch_width")
        self.layout = row(controls, views, sizing_mode="stretch_width")

    def _figures(self) -> None:
        self.src = ColumnDataSource(data={"w": [], "f": [], "db": [], "deg": [], "s": [], "t": [], "cs": []})
        self.mag = figure(title="Bode |L|", x_axis_type="log", x_axis_label="rad/s", y_axis_label="dB",
                          css_classes=["prsa-g-bode"], **_PLOT)
        self.phase = figure(title="Bode phase of L", x_axis_type="log", x_axis_label="rad/s", y_axis_label="deg",
                            x_range=self.mag.x_range, **_PLOT)
        self.st = figure(title="|S| and |T| with the bounds", x_axis_type="log", x_axis_label="rad/s",
                         y_axis_label="magnitude", x_range=self.mag.x_range, **_PLOT)
        self.noise_fig = figure(title="|C F S| (noise sensitivity) with the Mks bound", x_axis_type="log",
                                y_axis_type="log", x_axis_label="rad/s", y_axis_label="magnitude",
                                x_range=self.mag.x_range, **_PLOT)
        self.mag.line("f", "db", source=self.src, line_width=2)
        self.phase.line("f", "deg", source=self.src, line_width=2)
        self.st.line("f", "s", source=self.src, line_width=2, legend_label="|S|")
        self.st.line("f", "t", source=self.src, line_width=2, line_dash="dotted", legend_label="|T|")
        self.noise_fig.line("f", "cs", source=self.src, line_width=2)
        self.mag.add_layout(Span(location=0, dimension="width", line_color="black", line_width=1))
        self.phase.add_layout(Span(location=-180, dimension="width", line_color="black", line_width=1))
        self.ms_span = Span(location=1.4, dimension="width", line_color="#b00020", line_dash="dashed")
        self.mt_span = Span(location=1.0, dimension="width", line_color="#b00020", line_dash="dotted", visible=False)
        self.mks_span = Span(location=1.0, dimension="width", line_color="#b00020", line_dash="dashed", visible=False)
        self.st.add_layout(self.ms_span)
        self.st.add_layout(self.mt_span)
        self.noise_fig.add_layout(self.mks_span)
        self.st.legend.location = "bottom_left"

    # ---- reading the controls -------------------------------------------------------------

    def read(self) -> GenericSettings:
        """The controls' settings (one-line :class:`AppInputError` naming a bad field as typed)."""
        def number(widget, what, expected, ok, optional):
            text = widget.value.strip()
            if not text and optional:
                return None
            try:
                v = float(text)
            except ValueError:
                v = math.nan
            if not (math.isfinite(v) and ok(v)):
                raise AppInputError(f"{what} {widget.value!r}: expected {expected}")
            return v

        lo, hi = PEAK_BOUND_RANGE
        gs = GenericSettings(
            plant=self.plant.value,
            delay_s=number(self.delay, "delay", "a finite number >= 0 in s", lambda v: v >= 0, False),
            objective=self.objective.value, controller="pi" if self.controller.active == 0 else "pid",
            ms_max=number(self.ms, "Ms bound", f"a number in ({lo:g}, {hi:g})", lambda v: lo < v < hi, False),
            mt_max=number(self.mt, "Mt bound", f"a number in ({lo:g}, {hi:g}) or nothing", lambda v: lo < v < hi, True),
            mks_max=number(self.mks, "Mks bound", "a positive number or nothing", lambda v: v > 0, True),
            filter_order=int(self.filter.active), ideal=0 in self.options.active,
            setpoint_weights=1 in self.options.active)
        gs.kwargs()  # every field checked before any work
        from .generic import parse_transfer_function

        parse_transfer_function(gs.plant)
        return gs

    # ---- tuning round trip ---------------------------------------------------------------

    def request(self) -> None:
        """Re-tune with the controls' values (the newest request ends an older running one)."""
        try:
            gs = self.read()
        except AppInputError as exc:
            self._seq += 1  # a running tuning is of older inputs
            self._error(self._seq, str(exc))
            return
        self._seq += 1
        seq = self._seq
        self.state.text = (f"<div data-k='g-state' data-state='running' data-seq='{seq}'>tuning "
                           f"{html.escape(gs.plant)} ... (in a child process; a change of an input restarts it)</div>")
        self._pool.submit(self._work, seq, gs)

    def _work(self, seq: int, gs: GenericSettings) -> None:
        if seq != self._seq:
            return
        try:
            view = self._proc.run(gs, lambda: seq != self._seq)
            code = generic_code(gs)
        except Cancelled:
            return
        except AppInputError as exc:
            self.doc.add_next_tick_callback(partial(self._error, seq, str(exc)))
            return
        except Exception as exc:  # noqa: BLE001 - one line in the page, never a traceback
            self.doc.add_next_tick_callback(partial(self._error, seq, one_line(exc)))
            return
        self.doc.add_next_tick_callback(partial(self._apply, seq, view, code))

    def _error(self, seq: int, line: str) -> None:
        if seq != self._seq:
            return
        self.state.text = (f"<div data-k='g-state' data-state='error' data-seq='{seq}' style='color:#b00020'>"
                           f"<span data-k='g-error'>error: {html.escape(line)}</span></div>")

    def _apply(self, seq: int, view: GenericView, code: str) -> None:
        if seq != self._seq:
            return
        self.view = view
        r, gs = view.result, view.settings
        L = view.loop
        self.src.data = self.axes.data({"w": view.omega, "db": 20 * np.log10(np.abs(L)),
                                        "deg": np.degrees(np.unwrap(np.angle(L))), "s": 1 / np.abs(1 + L),
                                        "t": np.abs(L / (1 + L)),
                                        "cs": np.abs(view.noise) if view.noise.size else np.full(L.shape, np.nan)})
        self.ms_span.location = gs.ms_max
        self.mt_span.visible, self.mt_span.location = gs.mt_max is not None, gs.mt_max or 1.0
        self.mks_span.visible, self.mks_span.location = gs.mks_max is not None, gs.mks_max or 1.0
        m = r.margins[0]
        self.mag.title.text = f"Bode |L|: GM {_num(m.gm_db, '.2f')} dB, PM {_num(m.pm_deg, '.1f')} deg"
        filt, sp = r.filter or {}, r.setpoint or {}
        ideal = filt.get("derivative") == "ideal"
        cells = [("status", html.escape(r.status)), ("kp", _num(r.pid.kp, ".6g")), ("ki", _num(r.pid.ki, ".6g")),
                 ("kd", _num(r.pid.kd, ".6g")),
                 ("tf", "ideal" if ideal else (_num(r.pid.tf, ".4g") if gs.controller == "pid" else "-")),
                 ("filter", f"order {filt['order']}, Tf {_num(filt.get('tf_s'), '.4g')} s"
                  if filt.get("order") else "none"),
                 ("b", _num(sp.get("b"), ".4g")), ("c", _num(sp.get("c"), ".4g")),
                 ("ms", _num(r.ms, ".5f")), ("mt", _num(r.mt, ".5f")), ("mks", _num(r.mks, ".6g")),
                 ("gm", _num(m.gm_db, ".2f")), ("pm", _num(m.pm_deg, ".2f")), ("wc", _num(m.wc_rad_s, ".4g")),
                 ("obj", _num(r.objective, ".6g"))]
        head = ("status", "kp", "ki", "kd", "derivative tf (s)", "measurement filter", "b", "c", "Ms", "Mt", "Mks",
                "GM (dB)", "PM (deg)", "wc (rad/s)", gs.objective.upper())
        warns = "".join(f"<li data-k='g-warning'>{html.escape(w)}</li>" for w in r.warnings)
        self.readout.text = (
            f"<div>P(s) = <b>{html.escape(gs.plant)}</b>" + (f" e^(-{gs.delay_s:g} s)" if gs.delay_s else "")
            + f"; bounds Ms &le; {gs.ms_max:g}" + (f", Mt &le; {gs.mt_max:g}" if gs.mt_max is not None else "")
            + (f", Mks &le; {gs.mks_max:g}" if gs.mks_max is not None else "")
            + (f"; setpoint IAE {_num(sp.get('iae'), '.5g')} with b, c (unweighted "
               f"{_num(sp.get('iae_unweighted'), '.5g')}), overshoot {_num(sp.get('overshoot'), '.3g')}" if sp else "")
            + "</div><table style='border-collapse:collapse;font-size:12px'><tr>"
            + "".join(f"<th style='padding:2px 6px;border-bottom:1px solid #999'>{html.escape(h)}</th>" for h in head)
            + "</tr><tr>" + "".join(f"<td data-k='g-{k}' style='padding:2px 6px'>{t}</td>" for k, t in cells)
            + "</tr></table>" + (f"<ul style='font-size:12px'>{warns}</ul>" if warns else ""))
        self.code.text = ("<b>Copy as code</b><pre data-k='g-code' style='white-space:pre-wrap'>"
                          f"{html.escape(code)}</pre>")
        self.state.text = (f"<div data-k='g-state' data-state='done' data-seq='{seq}' "
                           f"data-sig='{html.escape(signature(gs), quote=True)}'>tuned</div>")

    def close(self) -> None:
        """End the child process and the worker."""
        self._seq += 1  # a running tuning sees it and ends its child
        self._pool.submit(self._proc.stop)  # after it, in the worker (no race on the child's pipe)
        self._pool.shutdown(wait=False)
