"""The browser page (Bokeh server document) of ``prsa-app``.

Every computation runs off the server's event loop: tuning, manual designs and the landscape
on one worker thread (the session's Tuner is reused there, requests coalesce: only the newest
settings are computed), verification on a second one with progress and a cancel. Results
reach the page through ``Document.add_next_tick_callback``, so the page never freezes.

Elements the browser tests read carry ``data-k`` attributes (``opt-ms``, ``man-kp``, ...), and
the widgets carry CSS classes named ``prsa-*``.
"""

from __future__ import annotations

import html
import math
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from functools import partial

import numpy as np
from bokeh.events import Pan, PanEnd, PanStart, Tap
from bokeh.layouts import column, row
from bokeh.models import (Button, CheckboxGroup, ColumnDataSource, CustomJS, Div, FileInput, HoverTool,
                          LinearColorMapper, RadioButtonGroup, Select, Slider, Span, TabPanel, Tabs, TextInput)
from bokeh.plotting import figure
from bokeh.plotting.contour import contour_data

from ..options import OBJECTIVES
from .fitpanel import SIZE_CHECK_JS, FitPanel, too_large_line, upload_input, uploaded_file
from .genericpanel import FrequencyAxes, GenericPanel, frequency_unit_widget
from .session import (FIDELITIES, AppInputError, AppSession, Cancelled, Settings, View, builtin_names, one_line,
                      robust_study, typed)

__all__ = ["AppPage", "make_document"]

_COLORS = {"opt": "#1f77b4", "man": "#ff7f0e"}
_BASE_COLORS = ("#7f7f7f", "#2ca02c", "#9467bd", "#8c564b", "#e377c2")
_PLOT = dict(height=300, sizing_mode="stretch_width", toolbar_location="above")


def _fmt(v, spec: str) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-" if v is None or math.isnan(v) else ("inf" if v > 0 else "-inf")
    return format(v, spec)


class AppPage:
    """One browser session of the app: widgets, figures and the workers that feed them.

    Parameters
    ----------
    doc : bokeh.document.Document
    plant, scene : str, optional
        Initial plant and scene (built-in name or path), as ``prsa-app --plant/--scene`` give.
    """

    def __init__(self, doc, plant: str | None = None, scene: str | None = None,
                 session: AppSession | None = None, attach: bool = True) -> None:
        self.doc = doc
        self.session = session if session is not None else AppSession(plant, scene)
        self.settings = self.session.default_settings()
        self.manual_gains: tuple[float, float, float] | None = None
        self.opt: View | None = None
        self.man: View | None = None
        self.base: list[View] = []
        self.verified: dict[str, View] = {}
        self._seq = 0
        self._vseq = 0
        self._mseq = 0  # manual-only updates (a drag on the landscape)
        self._pending = self.settings
        self._drag_end = -1  # the manual-only update of the last drag's end
        self._land_seq = -1
        self._cancel = threading.Event()
        self._reverting = {"plant": False, "scene": False}  # a select set back after a refused value
        self._tune_pool = ThreadPoolExecutor(1, thread_name_prefix="prsa-app-tune")
        self._verify_pool = ThreadPoolExecutor(1, thread_name_prefix="prsa-app-verify")
        self._build()
        if attach:
            self.attach()

    def attach(self) -> None:
        """Put the page into its document and start the first tuning (on the server's event
        loop). Building the page (``attach=False``) touches no document, so it can run on
        another thread (:class:`prsa_ctrl.app.gate.PageGate` does)."""
        self.doc.add_root(self.root)
        self.doc.title = "prsa-app: speed-loop tuning"
        self.doc.js_on_event("document_ready", CustomJS(code=SIZE_CHECK_JS))  # a page built at once
        self.doc.on_session_destroyed(self._destroyed)
        self.request()

    # ---- layout -------------------------------------------------------------------------

    def _build(self) -> None:
        s = self.settings
        plants, scenes = builtin_names()
        self._builtins = {"plant": list(plants), "scene": list(scenes)}
        self.title = Div(text="", css_classes=["prsa-title"], sizing_mode="stretch_width")
        self.error = Div(text="", css_classes=["prsa-error"], styles={"color": "#b00020"}, sizing_mode="stretch_width")
        self.status = Div(text="starting", css_classes=["prsa-status"])
        self.plant_select = Select(title="Plant (built-in)", options=plants,
                                   value=self.session.plant_label if self.session.plant_label in plants else plants[0])
        self.plant_upload, plant_big = upload_input(".toml", "or upload a plant file", "prsa-plant-upload")
        self.scene_select = Select(title="Scene (built-in)", options=scenes,
                                   value=self.session.scene_label if self.session.scene_label in scenes else scenes[0])
        self.scene_upload, scene_big = upload_input(".toml", "or upload a scene file", "prsa-scene-upload")
        for kind, src in (("plant", plant_big), ("scene", scene_big)):
            src.on_change("data", partial(self._too_large, kind))
        self.objective = Select(title="Objective", options=list(OBJECTIVES), value=s.objective)
        self.controller = RadioButtonGroup(labels=["PI", "PID"], active=0 if s.controller == "pi" else 1,
                                           css_classes=["prsa-controller"])
        self.ms = Slider(title="Ms bound", start=1.05, end=3.0, step=0.05, value=s.ms_max, format="0.00",
                         css_classes=["prsa-ms"])
        self.mt_on = CheckboxGroup(labels=["bound Mt"], active=[0] if s.mt_max is not None else [])
        self.mt = Slider(title="Mt bound", start=1.05, end=3.0, step=0.05, value=s.mt_max or 1.3, format="0.00",
                         css_classes=["prsa-mt"])
        self.noise = TextInput(title="Noise-gain bound kp + kd/tf (N m s/rad, empty: none)", value="",
                               css_classes=["prsa-noise"])
        self.mks = TextInput(title="Mks bound, true peak of |C F S| (N m s/rad, empty: none)",
                             value="" if s.mks_max is None else f"{s.mks_max:g}", css_classes=["prsa-mks"])
        self.loads = TextInput(title="Load step INITIAL:FINAL[,FINAL...] (N)", value=s.load_step,
                               css_classes=["prsa-loads"])
        self.fidelity = Select(title="Verification fidelity", options=list(FIDELITIES), value=s.fidelity)
        self.verify_button = Button(label="Verify on the nonlinear model", button_type="primary",
                                    css_classes=["prsa-verify"])
        self.cancel_button = Button(label="Cancel", disabled=True, css_classes=["prsa-cancel"])
        self.progress = Div(text="", css_classes=["prsa-progress"], sizing_mode="stretch_width")
        self.samples = TextInput(title="Monte-Carlo samples", value="40", css_classes=["prsa-samples"])
        self.robust_button = Button(label="Robust tuning + Monte-Carlo yield", css_classes=["prsa-robust"])
        self.robust_cancel = Button(label="Cancel", disabled=True, css_classes=["prsa-robust-cancel"])
        self.robust_out = Div(text="", css_classes=["prsa-robust-out"], sizing_mode="stretch_width")
        self._rcancel = threading.Event()
        self._robust_pool = ThreadPoolExecutor(1, thread_name_prefix="prsa-app-robust")
        self.clear_manual = Button(label="Clear manual design", css_classes=["prsa-clear-manual"])
        self.export_which = RadioButtonGroup(labels=["export optimum", "export manual"], active=0)
        self.files = ColumnDataSource(data={"name": [], "text": [], "mime": []})
        self.dl_drive = Button(label="Download drive file (TOML)", css_classes=["prsa-dl-drive"])
        self.dl_report = Button(label="Download JSON report", css_classes=["prsa-dl-report"])
        for btn, name in ((self.dl_drive, "speed-controller.toml"), (self.dl_report, "prsa-app-report.json")):
            btn.js_on_click(CustomJS(args={"files": self.files, "fname": name}, code=_DOWNLOAD_JS))
        self.code = Div(text="", css_classes=["prsa-code"], sizing_mode="stretch_width")
        self.code_src = ColumnDataSource(data={"cli": [""], "py": [""]})
        self.copy_cli = Button(label="Copy prsa-tune command", css_classes=["prsa-copy-cli"])
        self.copy_py = Button(label="Copy Python call", css_classes=["prsa-copy-py"])
        for btn, key in ((self.copy_cli, "cli"), (self.copy_py, "py")):
            btn.js_on_click(CustomJS(args={"src": self.code_src, "key": key}, code=_COPY_JS))
        self.readout = Div(text="", css_classes=["prsa-readout"], sizing_mode="stretch_width")
        self.fit = FitPanel(self)
        self._figures()

        for w in (self.objective, self.fidelity):
            w.on_change("value", lambda attr, old, new: self.request())
        self.loads.on_change("value", lambda attr, old, new: self.request())
        self.noise.on_change("value", lambda attr, old, new: self.request())
        self.mks.on_change("value", lambda attr, old, new: self.request())
        self.controller.on_change("active", lambda attr, old, new: self.request())
        self.mt_on.on_change("active", lambda attr, old, new: self.request())
        self.ms.on_change("value_throttled", lambda attr, old, new: self.request())
        self.mt.on_change("value_throttled", lambda attr, old, new: self.request())
        self.plant_select.on_change("value", lambda attr, old, new: self._switch("plant", old, new))
        self.scene_select.on_change("value", lambda attr, old, new: self._switch("scene", old, new))
        # value and filename arrive in one patch, value first: read both once the patch is applied
        self.plant_upload.on_change("value", lambda attr, old, new: self.doc.add_next_tick_callback(
            partial(self._upload, "plant", self.plant_upload)))
        self.scene_upload.on_change("value", lambda attr, old, new: self.doc.add_next_tick_callback(
            partial(self._upload, "scene", self.scene_upload)))
        self.verify_button.on_click(self._verify)
        self.cancel_button.on_click(lambda: self._cancel.set())
        self.clear_manual.on_click(self._clear_manual)
        self.robust_button.on_click(self._robust)
        self.robust_cancel.on_click(lambda: self._rcancel.set())
        self.export_which.on_change("active", lambda attr, old, new: self._refresh_outputs())
        self.land.on_event(Tap, self._tap)
        self.land.on_event(Pan, self._drag)
        self.land.on_event(PanEnd, self._drag)
        drag_js = CustomJS(args={"src": self.drag_src}, code=_DRAG_JS)
        for ev in (PanStart, Pan, PanEnd):
            self.land.js_on_event(ev, drag_js)

        controls = column(self.plant_select, self.plant_upload, self.scene_select, self.scene_upload,
                          self.objective, self.controller, self.ms, self.mt_on, self.mt, self.noise, self.mks, self.loads,
                          Div(text="Frequency axes"), self.freq_unit,
                          self.fidelity, row(self.verify_button, self.cancel_button), self.progress,
                          self.samples, row(self.robust_button, self.robust_cancel),
                          self.clear_manual, self.export_which, self.dl_drive, self.dl_report,
                          self.copy_cli, self.copy_py, width=330)
        views = column(self.error, self.status, self.readout, row(self.resp, self.land, sizing_mode="stretch_width"),
                       row(self.mag, self.st, sizing_mode="stretch_width"),
                       row(self.phase, self.code, sizing_mode="stretch_width"), self.robust_out,
                       sizing_mode="stretch_width")
        # the generic tuner is built (and its child process started) when its tab is first
        # opened: the first page stays as light as before
        self.generic: GenericPanel | None = None
        self.tabs = Tabs(tabs=[TabPanel(child=row(controls, views, sizing_mode="stretch_width"),
                                        title="Actuator (plant and scene files)"),
                               TabPanel(child=Div(text="loading the generic tuner ..."),
                                        title="Generic plant (transfer function)"),
                               TabPanel(child=self.fit.layout, title="Calibration (fit a drive log)")],
                         sizing_mode="stretch_width", css_classes=["prsa-tabs"])
        self.tabs.on_change("active", lambda attr, old, new: self._open_generic() if new == 1 else None)
        self.root = column(self.title, self.tabs, sizing_mode="stretch_width")

    def _figures(self) -> None:
        self.resp = figure(title="Predicted load-step response (first load level)", x_axis_label="time (s)",
                           y_axis_label="nut speed (rad/s)", css_classes=["prsa-response"], **_PLOT)
        self.src = {k: ColumnDataSource(data={"t": [], "w": []}) for k in ("opt", "man", "opt_ver", "man_ver")}
        self.base_src = ColumnDataSource(data={"t": [], "w": [], "name": [], "color": []})
        self.resp.multi_line("t", "w", source=self.base_src, color="color", line_width=1, alpha=0.8,
                             legend_field="name")
        self.resp.line("t", "w", source=self.src["opt"], color=_COLORS["opt"], line_width=2.5, legend_label="optimum")
        self.resp.line("t", "w", source=self.src["man"], color=_COLORS["man"], line_width=2, line_dash="dashed",
                       legend_label="manual")
        self.resp.line("t", "w", source=self.src["opt_ver"], color="black", line_width=1.5, line_dash="dotted",
                       legend_label="optimum verified")
        self.resp.line("t", "w", source=self.src["man_ver"], color="#d62728", line_width=1.5, line_dash="dotted",
                       legend_label="manual verified")
        self.resp.legend.location = "bottom_right"
        self.resp.legend.label_text_font_size = "8pt"
        self.resp.legend.click_policy = "hide"
        self.resp.legend.background_fill_alpha = 0.6

        # a drag (no pan tool: a drag on the plane moves the manual design) or a click sets the
        # manual gains; the wheel zooms
        self.land = figure(title="Kp-Ki landscape: objective (colour), Ms bound (line); click or drag sets manual gains",
                           x_axis_label="kp (N m s/rad)", y_axis_label="ki (N m/rad)", tools="tap,wheel_zoom,reset",
                           css_classes=["prsa-landscape"], **_PLOT)
        self.land.toolbar.active_drag = None
        self.land_img = ColumnDataSource(data={"image": [], "x": [], "y": [], "dw": [], "dh": []})
        self.cmap = LinearColorMapper(palette="Viridis256", nan_color="#dddddd")
        self.land.image(image="image", x="x", y="y", dw="dw", dh="dh", source=self.land_img, color_mapper=self.cmap)
        self.contour = None
        self.land_pts = ColumnDataSource(data={"kp": [], "ki": [], "name": [], "color": [], "marker": []})
        self.land.scatter("kp", "ki", source=self.land_pts, color="color", marker="marker", size=12, line_color="white")
        self.land.add_tools(HoverTool(tooltips=[("design", "@name"), ("kp", "@kp"), ("ki", "@ki")]))
        # the cursor of a drag, moved in the browser at once (the server's manual design follows)
        self.drag_src = ColumnDataSource(data={"kp": [], "ki": []})
        self.land.scatter("kp", "ki", source=self.drag_src, marker="circle", size=16, fill_alpha=0.0,
                          line_color=_COLORS["man"], line_width=2)

        self.mag = figure(title="Bode magnitude |L|", x_axis_type="log", x_axis_label="rad/s", y_axis_label="dB",
                          **_PLOT)
        self.phase = figure(title="Bode phase of L", x_axis_type="log", x_axis_label="rad/s", y_axis_label="deg",
                            x_range=self.mag.x_range, **_PLOT)
        self.st = figure(title="|S| and |T| with the bounds", x_axis_type="log", x_axis_label="rad/s",
                         y_axis_label="magnitude", x_range=self.mag.x_range, **_PLOT)
        self.freq = {k: ColumnDataSource(data={"w": [], "f": [], "db": [], "deg": [], "s": [], "t": []},
                                         name=f"prsa-freq-{k}") for k in ("opt", "man")}
        for k, dash in (("opt", "solid"), ("man", "dashed")):
            c = _COLORS[k]
            name = "optimum" if k == "opt" else "manual"
            self.mag.line("f", "db", source=self.freq[k], color=c, line_dash=dash, line_width=2, legend_label=name)
            self.phase.line("f", "deg", source=self.freq[k], color=c, line_dash=dash, line_width=2, legend_label=name)
            self.st.line("f", "s", source=self.freq[k], color=c, line_dash=dash, line_width=2, legend_label=f"|S| {name}")
            self.st.line("f", "t", source=self.freq[k], color=c, line_dash="dotted", line_width=2,
                         legend_label=f"|T| {name}")
        self.mag.add_layout(Span(location=0, dimension="width", line_color="black", line_width=1))
        self.phase.add_layout(Span(location=-180, dimension="width", line_color="black", line_width=1))
        self.ms_span = Span(location=self.settings.ms_max, dimension="width", line_color="#b00020", line_dash="dashed")
        self.mt_span = Span(location=1.0, dimension="width", line_color="#b00020", line_dash="dotted", visible=False)
        self.st.add_layout(self.ms_span)
        self.st.add_layout(self.mt_span)
        for f in (self.mag, self.phase, self.st):
            f.legend.label_text_font_size = "8pt"
            f.legend.location = "bottom_left"
        self.freq_unit = frequency_unit_widget("prsa-freq-unit")
        self.axes = FrequencyAxes(self.freq_unit, self.freq.values(), [self.mag, self.phase, self.st])

    # ---- reading the controls ------------------------------------------------------------

    def _read(self) -> Settings:
        text = self.noise.value.strip()
        if text:
            try:
                noise = float(text)
            except ValueError:
                raise AppInputError(f"noise-gain bound {text!r}: expected a positive number in N m s/rad "
                                    "or nothing") from None
        else:
            noise = None
        text = self.mks.value.strip()
        mks = None
        if text:
            try:
                mks = float(text)
            except ValueError:
                raise AppInputError(f"Mks bound {text!r}: expected a positive number in N m s/rad or nothing") from None
        return Settings(objective=self.objective.value, controller="pi" if self.controller.active == 0 else "pid",
                        ms_max=round(float(self.ms.value), 6),
                        mt_max=round(float(self.mt.value), 6) if 0 in self.mt_on.active else None,
                        max_noise_gain=noise, load_step=self.loads.value, fidelity=self.fidelity.value, mks_max=mks)

    # ---- tuning round trip ---------------------------------------------------------------

    def request(self) -> None:
        """Re-tune with the controls' values (in the worker; only the newest request runs)."""
        try:
            settings = self._read()
        except AppInputError as exc:
            self._show_error(str(exc))
            return
        self._seq += 1
        self._pending = settings  # what a drag computes with until this request is applied
        self._vseq += 1  # a running verification belongs to the old design
        self._cancel.set()
        self.status.text = "tuning..."
        self._tune_pool.submit(self._work, self._seq, settings, self.manual_gains)

    def _work(self, seq: int, settings: Settings, manual) -> None:
        if seq != self._seq:
            return  # superseded before it started
        def compute():
            opt = self.session.tuned(settings)
            base = self.session.baselines(settings)
            man = None
            if manual is not None:
                kd = opt.pid.kd if settings.controller == "pid" else 0.0
                man = self.session.manual(settings, manual[0], manual[1], kd)
            cli, py = self.session.code(settings)
            return opt, base, man, cli, py, self.session.export_files(settings, opt)

        out = self._guarded(compute, seq)
        if out is None:
            return
        opt, base, man, cli, py, files = out
        self.doc.add_next_tick_callback(partial(self._apply, seq, settings, opt, base, man, cli, py, files))
        if seq != self._seq:
            return
        try:
            land = self.session.landscape(settings, [opt.pid] + [b.pid for b in base], kd=opt.pid.kd)
        except Exception as exc:  # noqa: BLE001
            self.doc.add_next_tick_callback(partial(self._show_error, f"landscape: {one_line(exc)}", seq))
            return
        self.doc.add_next_tick_callback(partial(self._apply_landscape, seq, settings, land))

    def _show_error(self, line: str, seq: int | None = None) -> None:
        if seq is not None and seq != self._seq:
            return
        self.error.text = f'<span data-k="error">error: {html.escape(line)}</span>'
        self.status.text = "ready (last input rejected)"

    def _apply(self, seq, settings, opt, base, man, cli, py, files) -> None:
        if seq != self._seq:
            return
        self.settings, self.opt, self.base, self.man = settings, opt, base, man
        self.verified = {}
        self.error.text = ""
        self.progress.text = ""
        self.code_src.data = {"cli": [cli], "py": [py]}
        self.code.text = ("<b>Copy as code</b><pre data-k='code-cli' style='white-space:pre-wrap'>"
                          f"{html.escape(cli)}</pre><pre data-k='code-py' style='white-space:pre-wrap'>"
                          f"{html.escape(py)}</pre>")
        self._files_opt = files
        self._redraw()
        self.status.text = f'<span data-k="status" data-seq="{seq}">ready</span>'

    def _apply_landscape(self, seq, settings, land) -> None:
        if seq != self._seq:
            return
        self._land = land
        self._land_seq = seq
        obj = land["objective"]
        kp, ki = land["kp"], land["ki"]
        dkp = kp[1] - kp[0]
        dki = ki[1] - ki[0]
        img = np.log10(obj)
        self.land_img.data = {"image": [img], "x": [kp[0] - dkp / 2], "y": [ki[0] - dki / 2],
                              "dw": [kp[-1] - kp[0] + dkp], "dh": [ki[-1] - ki[0] + dki]}
        finite = img[np.isfinite(img)]
        if finite.size:
            self.cmap.low, self.cmap.high = float(finite.min()), float(np.percentile(finite, 90))
        ms = np.where(np.isfinite(land["ms"]), land["ms"], 1e3)
        data = contour_data(kp, ki, ms, levels=[settings.ms_max], want_fill=False, want_line=True)
        if self.contour is None:
            self.contour = self.land.contour(kp, ki, ms, levels=[settings.ms_max], line_color="#b00020", line_width=2)
        self.contour.set_data(data)
        self.status.text = f'<span data-k="status" data-seq="{seq}" data-landscape="{seq}">ready</span>'
        self.land.title.text = (f"Kp-Ki landscape: log10 {settings.objective.upper()} (colour, grey: unstable), "
                                f"Ms = {settings.ms_max:g} (red line); click or drag sets manual gains"
                                + (f"; kd = {land['kd']:.3g} fixed" if land["kd"] else ""))

    # ---- drawing --------------------------------------------------------------------------

    def _redraw(self) -> None:
        s, opt, man = self.settings, self.opt, self.man
        if opt is None:
            return
        self._trace(self.src["opt"], opt)
        self._trace(self.src["man"], man)
        self._trace(self.src["opt_ver"], self.verified.get("opt"), verified=True)
        self._trace(self.src["man_ver"], self.verified.get("man"), verified=True)
        bt, bw, bn, bc = [], [], [], []
        for i, b in enumerate(self.base):
            if b.t:
                bt.append(b.t[0])
                bw.append(b.speed[0])
                bn.append(b.design.name)
                bc.append(_BASE_COLORS[i % len(_BASE_COLORS)])
        self.base_src.data = {"t": bt, "w": bw, "name": bn, "color": bc}
        for k, v in (("opt", opt), ("man", man)):
            if v is None:
                self.freq[k].data = {"w": [], "f": [], "db": [], "deg": [], "s": [], "t": []}
                continue
            L = v.loop
            self.freq[k].data = self.axes.data({"w": v.omega, "db": 20 * np.log10(np.abs(L)),
                                                "deg": np.degrees(np.unwrap(np.angle(L))),
                                                "s": 1 / np.abs(1 + L), "t": np.abs(L / (1 + L))})
        self.ms_span.location = s.ms_max
        self.mt_span.visible = s.mt_max is not None
        self.mt_span.location = s.mt_max or 1.0
        m = opt.design.margins
        self.mag.title.text = f"Bode |L|: optimum GM {_fmt(m.gm_db, '.2f')} dB, PM {_fmt(m.pm_deg, '.1f')} deg" + (
            f"; manual GM {_fmt(man.design.margins.gm_db, '.2f')} dB, PM {_fmt(man.design.margins.pm_deg, '.1f')} deg"
            if man else "")
        pts = {"kp": [opt.pid.kp], "ki": [opt.pid.ki], "name": ["optimum"], "color": [_COLORS["opt"]],
               "marker": ["star"]}
        for i, b in enumerate(self.base):
            for key, val in (("kp", b.pid.kp), ("ki", b.pid.ki), ("name", b.design.name),
                             ("color", _BASE_COLORS[i % len(_BASE_COLORS)]), ("marker", "circle")):
                pts[key].append(val)
        if man is not None:
            for key, val in (("kp", man.pid.kp), ("ki", man.pid.ki), ("name", "manual"), ("color", _COLORS["man"]),
                             ("marker", "x")):
                pts[key].append(val)
        self.land_pts.data = pts
        self._readout()
        self._refresh_outputs()

    @staticmethod
    def _trace(src: ColumnDataSource, v: View | None, verified: bool = False) -> None:
        if v is None:
            src.data = {"t": [], "w": []}
        elif verified:
            t, y = v.design.verified_runs[0] if v.design.verified_runs else ([], [])
            src.data = {"t": np.asarray(t), "w": np.asarray(y["nut_speed"]) if len(t) else []}
        else:
            src.data = {"t": v.t[0] if v.t else [], "w": v.speed[0] if v.speed else []}

    def _readout(self) -> None:
        s = self.settings
        ts = self.session.plant.sample_time_s
        obj = s.objective.upper()
        head = ("design", "status", "kp (N m s/rad)", "ki (N m/rad)", "kd (N m s^2/rad)", "Ti (ms)",
                "kp (N m/rpm)", "Ms", "Mt", "GM (dB)", "PM (deg)", "wc (rad/s)", "kp+kd/tf", "Mks", f"pred. {obj}",
                "pred. drop (rad/s)", f"verified {obj}", "verified drop", "health")
        rows = [("opt", self.opt)] + ([("man", self.man)] if self.man else []) + \
               [(f"base{i}", b) for i, b in enumerate(self.base)]
        out = [f'<div data-k="bounds" data-ms="{s.ms_max}">Plant <b>{html.escape(self.session.plant_label)}</b>, '
               f"scene <b>{html.escape(self.session.scene_label)}</b>, sample time {ts * 1e3:g} ms; bounds "
               f'Ms &le; <span data-k="bound-ms">{s.ms_max:g}</span>'
               + (f", Mt &le; {s.mt_max:g}" if s.mt_max is not None else "")
               + (f", kp + kd/tf &le; {s.max_noise_gain:g} N m s/rad" if s.max_noise_gain is not None else "")
               + (f", Mks &le; {s.mks_max:g} N m s/rad" if s.mks_max is not None else "")
               + f"; load step {html.escape(s.load_step)} N</div>",
               "<table style='border-collapse:collapse;font-size:12px'><tr>"
               + "".join(f"<th style='padding:2px 6px;border-bottom:1px solid #999'>{html.escape(h)}</th>" for h in head)
               + "</tr>"]
        for key, v in rows:
            d, m = v.design, v.design.margins
            ver = self.verified.get(key)
            pred = d.predicted[0].peak_drop_rad_s if d.predicted else math.nan
            cells = [("name", html.escape(d.name)), ("status", html.escape(v.status)),
                     ("kp", _fmt(d.pid.kp, ".6g")), ("ki", _fmt(d.pid.ki, ".6g")), ("kd", _fmt(d.pid.kd, ".6g")),
                     ("ti", _fmt(1e3 * d.pid.kp / d.pid.ki if d.pid.ki > 0 else math.inf, ".4g")),
                     ("kprpm", _fmt(v.drive_terms(ts)["kp_n_m_per_rpm"], ".4g")),
                     ("ms", _fmt(m.ms, ".4f")), ("mt", _fmt(m.mt, ".4f")), ("gm", _fmt(m.gm_db, ".2f")),
                     ("pm", _fmt(m.pm_deg, ".2f")), ("wc", _fmt(m.wc_rad_s, ".4g")), ("noise", _fmt(v.noise_gain, ".4g")),
                     ("mks", _fmt(v.mks, ".4g") if v.mks is not None else "-"),
                     ("pred", _fmt(d.objective_predicted, ".5g")), ("drop", _fmt(pred, ".4g")),
                     ("ver", _fmt(ver.design.objective_verified, ".5g") if ver else "-"),
                     ("vdrop", _fmt(ver.design.verified[0].peak_drop_rad_s, ".4g") if ver and ver.design.verified else "-"),
                     ("flags", (html.escape("; ".join(ver.design.flags)) or "healthy") if ver else "-")]
            out.append("<tr>" + "".join(f"<td data-k='{key}-{c}' style='padding:2px 6px'>{t}</td>" for c, t in cells)
                       + "</tr>")
        out.append("</table>")
        self.readout.text = "".join(out)
        self.title.text = (f"<h2 style='margin:4px 0'>prsa-app: speed-loop tuning of "
                           f"{html.escape(self.session.plant.name)}</h2>"
                           + "".join(f"<div style='font-size:11px;color:#666'>note: {html.escape(n)}</div>"
                                     for n in self.session.notes))

    def _refresh_outputs(self) -> None:
        if self.opt is None:
            return
        v = self.man if self.export_which.active == 1 and self.man is not None else self.opt
        files = self._files_opt if v is self.opt else self.session.export_files(self.settings, v)
        names = list(files)
        self.files.data = {"name": names, "text": [files[n] for n in names],
                           "mime": ["application/toml" if n.endswith(".toml") else "application/json" for n in names]}

    # ---- events ---------------------------------------------------------------------------

    def _tap(self, event) -> None:
        if event.x is None or event.y is None:
            return
        kp, ki = float(event.x), max(float(event.y), 0.0)
        if kp <= 0:
            self._show_error(f"manual kp {kp:.4g}: expected a positive gain in N m s/rad")
            return
        self.set_manual(kp, ki)

    def set_manual(self, kp: float, ki: float) -> None:
        """Set the manual design's gains (as a click on the landscape does) and redraw."""
        self.manual_gains = (kp, ki, 0.0)
        self.request()

    def _drag(self, event) -> None:
        """A drag on the landscape: the manual design follows the pointer (manual-only
        updates, coalesced in the worker: the optimum is not re-tuned)."""
        if event.x is None or event.y is None or self.opt is None:
            return
        kp, ki = float(event.x), max(float(event.y), 0.0)
        if not (math.isfinite(kp) and math.isfinite(ki)) or kp <= 0:
            return  # outside the plane: the last valid point stays
        self.manual_gains = (kp, ki, 0.0)
        self._mseq += 1
        if isinstance(event, PanEnd):
            self._drag_end = self._mseq
        kd = self.opt.pid.kd if self._pending.controller == "pid" else 0.0  # the optimum's, as a click takes it
        self._tune_pool.submit(self._manual_work, self._seq, self._mseq, self._pending, (kp, ki, kd))

    def _manual_work(self, seq: int, mseq: int, settings: Settings, manual) -> None:
        if seq != self._seq or mseq != self._mseq:
            return  # superseded before it started
        man = self._guarded(lambda: self.session.manual(settings, *manual), seq)
        if man is not None:
            self.doc.add_next_tick_callback(partial(self._apply_manual, seq, mseq, man))

    def _guarded(self, compute, seq: int):
        """``compute()`` on the worker; a failure becomes one line in the page (never a traceback)
        and ``None``."""
        try:
            return compute()
        except AppInputError as exc:
            self.doc.add_next_tick_callback(partial(self._show_error, str(exc), seq))
        except Exception as exc:  # noqa: BLE001 - one line in the page, never a traceback
            self.doc.add_next_tick_callback(partial(self._show_error, f"numerical failure: {one_line(exc)}", seq))
        return None

    def _apply_manual(self, seq: int, mseq: int, man: View) -> None:
        if seq != self._seq or mseq != self._mseq:
            return
        self.man = man
        self.verified.pop("man", None)
        self.error.text = ""
        self._redraw()
        end = ' data-drag="end"' if mseq == self._drag_end else ""
        self.status.text = (f'<span data-k="status" data-seq="{seq}" data-mseq="{mseq}"{end}'
                            + (f' data-landscape="{seq}"' if self._land_seq == seq else "") + ">ready</span>")

    def _clear_manual(self) -> None:
        self.manual_gains = None
        self.export_which.active = 0
        self.request()

    def _switch(self, kind: str, old: str, name: str) -> None:
        """A built-in plant or scene chosen in its select. Bokeh does not check that a select's
        value is one of its options (a client can set any text): anything else is refused with
        one line and the select goes back to its previous value; the session refuses it too
        (:meth:`AppSession.set_plant`)."""
        select = self.plant_select if kind == "plant" else self.scene_select
        if self._reverting.get(kind):
            self._reverting[kind] = False
            return
        if not isinstance(name, str) or name not in select.options:
            self._show_error(f"{kind} select value {typed(name)}: expected one of the built-in {kind}s "
                             f"({', '.join(select.options)})")
            self._reverting[kind] = True
            select.value = old if old in select.options else select.options[0]
            return
        try:
            notes = (self.session.set_plant if kind == "plant" else self.session.set_scene)(name)
        except AppInputError as exc:
            self._show_error(str(exc))
            return
        self._after_switch(kind, notes)

    def _show_source(self, kind: str) -> None:
        """The plant or scene select shows what the session uses: a built-in name, or
        ``file: NAME`` (an upload or a calibrated plant, listed while it is in use; was:
        the select kept showing the last built-in name after an upload)."""
        select = self.plant_select if kind == "plant" else self.scene_select
        label = self.session.plant_label if kind == "plant" else self.session.scene_label
        builtins = self._builtins[kind]
        value = label if label in builtins else f"file: {label}"
        options = builtins if label in builtins else [*builtins, value]
        if list(select.options) != options:
            select.options = options
        if select.value != value:
            self._reverting[kind] = True  # a display change, not a choice: _switch skips it
            select.value = value

    def _too_large(self, kind: str, attr, old, new) -> None:
        src = (self.plant_upload if kind == "plant" else self.scene_upload).tags[1]
        line = too_large_line(src, f"uploaded-{kind}.toml")
        if line is not None:
            self._show_error(line)

    def _upload(self, kind: str, widget: FileInput) -> None:
        try:
            got = uploaded_file(widget, f"uploaded-{kind}.toml")
        except AppInputError as exc:
            self._show_error(str(exc))
            return
        if got is None:
            return
        name, content = got
        try:
            notes = self.session.upload(kind, name, content)
        except AppInputError as exc:
            self._show_error(str(exc))
            return
        except Exception as exc:  # noqa: BLE001 - one line in the page, never a traceback
            self._show_error(f"{name}: cannot be read ({one_line(exc)})")
            return
        self._after_switch(kind, notes)

    def _open_generic(self) -> None:
        if self.generic is None:
            self.generic = GenericPanel(self.doc)
            # a new panel (BokehJS re-renders Tabs on a change of ``tabs``, not of a panel's child)
            self.tabs.tabs = [self.tabs.tabs[0], TabPanel(child=self.generic.layout,
                                                          title="Generic plant (transfer function)"),
                              *self.tabs.tabs[2:]]
            self.tabs.active = 1
            self.generic.request()

    def show_error(self, line: str) -> None:
        """Show one line as the page's error (``error: LINE``)."""
        self._show_error(line)

    def after_switch(self, kind: str, notes: list[str]) -> None:
        """After the plant (``kind`` ``"plant"``) or scene changed in the session: show its
        notes, reset what depends on it and re-tune."""
        self._after_switch(kind, notes)

    def _after_switch(self, kind: str, notes: list[str]) -> None:
        self.session.notes = notes
        self._show_source(kind)
        if kind == "scene":  # every widget the scene sets shows the scene's value (its fidelity and Mt too)
            d = self.session.default_settings()
            self.objective.value, self.loads.value = d.objective, d.load_step
            self.controller.active = 0 if d.controller == "pi" else 1
            self.ms.value = d.ms_max
            self.mt_on.active = [0] if d.mt_max is not None else []
            if d.mt_max is not None:
                self.mt.value = d.mt_max
            if d.fidelity in self.fidelity.options:
                self.fidelity.value = d.fidelity
        self.manual_gains = None
        self.error.text = ""
        self.request()

    def _verify(self) -> None:
        if self.opt is None:
            return
        self._vseq += 1
        vseq = self._vseq
        self._cancel = threading.Event()
        views = [("opt", self.opt)] + ([("man", self.man)] if self.man else [])
        self.verify_button.disabled = True
        self.cancel_button.disabled = False
        self._set_progress(vseq, 0, len(views), views[0][1].design.name)
        self._verify_pool.submit(self._verify_work, vseq, self.settings, views, self._cancel)

    def _verify_work(self, vseq, settings, views, cancel) -> None:
        def progress(done, total, name):
            self.doc.add_next_tick_callback(partial(self._set_progress, vseq, done, total, name))

        try:
            out = self.session.verify(settings, [v for _, v in views], progress, cancel.is_set)
        except Exception as exc:  # noqa: BLE001
            self.doc.add_next_tick_callback(partial(self._verify_done, vseq, None, f"verification failed: {one_line(exc)}"))
            return
        keys = [k for k, _ in views][: len(out)]
        note = "cancelled" if len(out) < len(views) else ""
        self.doc.add_next_tick_callback(partial(self._verify_done, vseq, dict(zip(keys, out)), note))

    def _set_progress(self, vseq, done, total, name) -> None:
        if vseq != self._vseq:
            return
        pct = 100.0 * done / max(total, 1)
        what = f"verifying {html.escape(name)} ({done + 1}/{total})" if done < total else "verified"
        self.progress.text = (f"<div data-k='progress' data-done='{done}' data-total='{total}'>{what}"
                              f"<div style='background:#eee;width:100%;height:8px'><div style='background:#1f77b4;"
                              f"width:{pct:.0f}%;height:8px'></div></div></div>")

    def _verify_done(self, vseq, result, note) -> None:
        self.verify_button.disabled = False
        self.cancel_button.disabled = True
        if vseq != self._vseq:
            if note:
                self.progress.text = ""
            return
        if result is None:
            self._show_error(note)
            self.progress.text = ""
            return
        self.verified = result
        self.progress.text = f"<div data-k='progress' data-state='{note or 'done'}'>verification {note or 'done'}</div>"
        self._redraw()

    # ---- robust tuning and Monte Carlo ---------------------------------------------------

    def _robust(self) -> None:
        if self.opt is None:
            return
        try:
            n = int(self.samples.value.strip())
            if not 1 <= n <= 10_000:
                raise ValueError
        except ValueError:
            self._show_error(f"Monte-Carlo samples {self.samples.value!r}: expected an integer in 1..10000")
            return
        designs = {"optimum": self.opt.pid, **({"manual": self.man.pid} if self.man else {})}
        self._rcancel = threading.Event()
        self.robust_button.disabled = True
        self.robust_cancel.disabled = False
        self._robust_progress("robust tuning", 0, n)
        self._robust_pool.submit(self._robust_work, self.settings, designs, n, self._rcancel)

    def _robust_work(self, settings, designs, n, cancel) -> None:
        def progress(stage, done, total):
            self.doc.add_next_tick_callback(partial(self._robust_progress, stage, done, total))

        try:
            out = robust_study(self.session, settings, designs, n, progress, cancel.is_set)
            note = ""
        except Cancelled as exc:
            out, note = None, str(exc)
        except Exception as exc:  # noqa: BLE001 - one line in the page
            out, note = None, f"robust study failed: {one_line(exc)}"
        self.doc.add_next_tick_callback(partial(self._robust_done, settings, out, note))

    def _robust_progress(self, stage, done, total) -> None:
        pct = 100.0 * done / max(total, 1)
        self.robust_out.text = (f"<div data-k='rprogress' data-stage='{stage}' data-done='{done}' data-total='{total}'>"
                                f"{html.escape(stage)}: {done}/{total} samples"
                                f"<div style='background:#eee;width:300px;height:8px'><div style='background:#2ca02c;"
                                f"width:{pct:.0f}%;height:8px'></div></div></div>")

    def _robust_done(self, settings, out, note) -> None:
        self.robust_button.disabled = False
        self.robust_cancel.disabled = True
        if out is None:
            self.robust_out.text = f"<div data-k='rprogress' data-state='stopped'>{html.escape(note)}</div>"
            return
        mc = out["monte_carlo"]
        state = "done" if mc["complete"] else "cancelled"
        r = out["robust"]
        rows = []
        for d in mc["designs"]:
            name = d["name"]
            lo, hi = d["yield_ci95"]
            comp = out["comparison"].get(name, {})
            rows.append(f"<tr><td>{html.escape(name)}</td><td data-k='mc-{name}-kp'>{d['gains']['kp']:.6g}</td>"
                        f"<td data-k='mc-{name}-ki'>{d['gains']['ki']:.6g}</td>"
                        f"<td data-k='mc-{name}-maxms'>{_fmt(comp.get('max_ms', math.nan), '.4f')}</td>"
                        f"<td data-k='mc-{name}-worst'>{_fmt(comp.get('worst_objective', math.nan), '.5g')}</td>"
                        f"<td data-k='mc-{name}-yield'>{d['passed']}/{d['samples']}</td>"
                        f"<td data-k='mc-{name}-ci'>[{lo:.3f}, {hi:.3f}]</td></tr>")
        spec_text = (f"spec {html.escape(str(mc['spec']))}" if mc["spec"] else
                     "the scene has no [spec]: a sample passes when its run is finite")
        head = ("design", "kp", "ki", "max Ms over scenarios", f"worst {settings.objective.upper()}",
                "passed/samples", "yield 95 % CI")
        self.robust_out.text = (
            f"<div data-k='rprogress' data-state='{state}' data-done='{mc['samples_done']}'>"
            f"<b>Robust tuning and Monte-Carlo yield</b> ({state}: {mc['samples_done']} of {mc['samples']} samples, seed "
            f"{mc['seed']}; {spec_text}; robust design kp {r['kp']:.6g}, ki {r['ki']:.6g};"
            " the noise-gain bound is not part of the robust problem)</div>"
            "<table style='font-size:12px'><tr>" + "".join(f"<th style='padding:2px 6px'>{h}</th>" for h in head)
            + "</tr>" + "".join(rows) + "</table>")

    def close(self, wait: bool = False) -> None:
        """Stop the page's workers and release its session (uploaded files, tuners and caches);
        ``wait``: return once the session is released (it waits for a running tuning)."""
        self._destroyed(None)
        if wait:
            self.session.close()

    def _destroyed(self, session_context) -> None:
        self._seq += 1
        self._cancel.set()
        self._rcancel.set()
        self._robust_pool.shutdown(wait=False, cancel_futures=True)
        self._tune_pool.shutdown(wait=False, cancel_futures=True)
        self._verify_pool.shutdown(wait=False, cancel_futures=True)
        self.fit.close()
        if self.generic is not None:
            self.generic.close()
        # the session's lock may be held by a running tuning (seconds): release it off the loop
        threading.Thread(target=self.session.close, name="prsa-app-close", daemon=True).start()


_DOWNLOAD_JS = """
const i = files.data.name.indexOf(fname);
if (i < 0) { return; }
const blob = new Blob([files.data.text[i]], {type: files.data.mime[i]});
const a = document.createElement('a');
a.href = URL.createObjectURL(blob);
a.download = fname;
document.body.appendChild(a);
a.click();
setTimeout(() => { URL.revokeObjectURL(a.href); a.remove(); }, 1000);
"""

_DRAG_JS = """
if (cb_obj.x == null || cb_obj.y == null) { return; }
if (cb_obj.event_name == 'panend') { src.data = {kp: [], ki: []}; return; }
src.data = {kp: [cb_obj.x], ki: [Math.max(cb_obj.y, 0)]};
"""

_COPY_JS = """
const text = src.data[key][0];
if (navigator.clipboard) { navigator.clipboard.writeText(text); }
"""


class WarmSessions:
    """Sessions prepared ahead in a background thread (loop models, Tuner, first design,
    baselines and landscape built), so a new page starts with its numbers ready: each
    :meth:`take` hands one over and starts preparing the next."""

    def __init__(self, plant: str | None = None, scene: str | None = None) -> None:
        self.plant, self.scene = plant, scene
        self._lock = threading.Lock()
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="prsa-app-warm")
        self._next = self._pool.submit(self._build)

    def _build(self) -> AppSession:
        s = AppSession(self.plant, self.scene)
        st = s.default_settings()
        opt = s.tuned(st)
        base = s.baselines(st)
        s.landscape(st, [opt.pid] + [b.pid for b in base], kd=opt.pid.kd)
        return s

    def take(self) -> AppSession:
        """A prepared session (waits for the one in preparation), or a plain new one if that
        preparation failed. Slow (seconds): call it off the server's event loop."""
        with self._lock:
            fut, self._next = self._next, self._pool.submit(self._build)
        try:
            return fut.result()
        except Exception:  # noqa: BLE001 - the page reports the same error itself
            return AppSession(self.plant, self.scene)


def make_document(doc, plant: str | None = None, scene: str | None = None,
                  warm: WarmSessions | None = None) -> AppPage:
    """Build the app into a Bokeh document at once, on the calling thread (seconds). The
    server builds its pages off the event loop instead (:class:`prsa_ctrl.app.gate.PageGate`)."""
    return AppPage(doc, plant, scene, session=warm.take() if warm is not None else None)
