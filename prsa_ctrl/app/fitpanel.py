"""The page's calibration tab: upload a drive log, fit the plant in the background
(``prsa-fit``'s path, :meth:`prsa_ctrl.app.session.AppSession.calibrate`), show the verdict, the
fitted values with their 95 % intervals and the fit's warnings, the three views of the fit
(``prsa-fit --json``'s ``views``, :func:`prsa_ctrl.plots.fit.fit_views`: the replay of the plant
as written against the log, the log's frequency response beside the written plant's on a Hz axis
with the coherence, and the residuals), and on the user's confirmation make the fitted plant the
app's plant and re-tune. A fit whose plant does not explain the log is shown as refused, with
prsa-fit's diagnosis: no plant to use or download. A measured frequency response uploaded beside
the log is fitted as ``prsa-fit --frf`` does (:func:`prsa_ctrl.identification.calibrate.calibrate_frf`):
the structure the data chose, why, and the mode with its intervals (``fit-structure``), the Bode view;
a response the command refuses (exit 3) is shown as refused with its line.

Elements the browser tests read carry ``data-k`` attributes (``fit-state``, ``fit-verdict``,
``fit-views``, ``fit-<key>-value``, ``fit-<key>-ci``, ``fit-warning``), the widgets CSS classes
``prsa-log-upload``, ``prsa-format-upload`` (a log description the next log is read through: a ``.mat``
log, a linear axis), ``prsa-frf-upload``, ``prsa-fit-use``, ``prsa-fit-discard``, ``prsa-fit-download``, the figures
``prsa-fit-replay``, ``prsa-fit-residual``, ``prsa-fit-frf-mag``, ``prsa-fit-frf-phase``,
``prsa-fit-coherence``, and their data sources the names ``prsa-fit-replay``,
``prsa-fit-frf``, ``prsa-fit-frf-models``.
"""

from __future__ import annotations

import base64
import binascii
import html
from concurrent.futures import ThreadPoolExecutor
from functools import partial

from bokeh.layouts import column, row
from bokeh.models import Button, ColumnDataSource, CustomJS, Div, FileInput
from bokeh.plotting import figure

from .session import AppInputError, Calibration, Cancelled, one_line, upload_name

__all__ = ["FitPanel", "uploaded_file", "upload_input", "too_large_line", "MAX_UPLOAD_BYTES", "SIZE_CHECK_JS",
           "report_html"]


#: Largest file the page takes (bytes). Bokeh's websocket takes messages up to 20 MB, and a
#: file travels as base64 (4/3 of its size); the browser checks the size before sending
#: (:data:`SIZE_CHECK_JS`), the server again.
MAX_UPLOAD_BYTES = 10_000_000


def upload_input(accept: str, title: str, css: str) -> tuple[FileInput, ColumnDataSource]:
    """A ``FileInput`` whose browser side refuses a file above :data:`MAX_UPLOAD_BYTES` before
    reading it, and the source it then reports ``name`` and ``bytes`` to (watch its ``data``)."""
    too_large = ColumnDataSource(data={"name": [], "bytes": []})
    widget = FileInput(accept=accept, title=title, css_classes=[css], tags=[MAX_UPLOAD_BYTES, too_large])
    return widget, too_large


def too_large_line(src: ColumnDataSource, default: str) -> str | None:
    """The one line for a file the browser refused as too large (None if ``src`` holds none)."""
    names, sizes = src.data.get("name", []), src.data.get("bytes", [])
    if not names or not sizes:
        return None
    try:
        size = float(sizes[0])
    except (TypeError, ValueError):
        size = float("nan")
    return (f"{upload_name(names[0], default)}: {size / 1e6:.1f} MB; expected a file of at most "
            f"{MAX_UPLOAD_BYTES / 1e6:g} MB (the app's upload limit)")


def uploaded_file(widget: FileInput, default: str) -> tuple[str, bytes] | None:
    """The file a Bokeh ``FileInput`` holds: ``(name, content)``, or None when it holds none.
    The name is :func:`~prsa_ctrl.app.session.upload_name`'s (``default`` when the browser sent
    none or one that is no plain file name).

    Raises
    ------
    AppInputError
        One line: the value is not base64 text (a client can send anything), or it is larger
        than :data:`MAX_UPLOAD_BYTES`.
    """
    value = widget.value
    if not value:
        return None
    try:
        name = widget.filename
    except Exception:  # noqa: BLE001 - bokeh's UnsetValueError: no name came with the file
        name = None
    value = value[0] if isinstance(value, list) else value
    name = upload_name(name[0] if isinstance(name, list) and name else name, default)
    if not isinstance(value, str):
        raise AppInputError(f"{name}: the upload holds a {type(value).__name__}; expected the file's bytes as base64 "
                            "text (as a browser sends a file)")
    if len(value) > 4 * ((MAX_UPLOAD_BYTES + 2) // 3):
        raise AppInputError(f"{name}: {len(value) * 3 / 4 / 1e6:.1f} MB; expected a file of at most "
                            f"{MAX_UPLOAD_BYTES / 1e6:g} MB (the app's upload limit)")
    try:
        return name, base64.b64decode(value, validate=True)
    except (binascii.Error, ValueError):
        raise AppInputError(f"{name}: the upload is not base64 text; expected the file's bytes as base64 "
                            "(as a browser sends a file)") from None


#: Installed once per browser page (a Bokeh ``document_ready`` callback): a ``FileInput``
#: tagged ``[max_bytes, source]`` (:func:`upload_input`) refuses a larger file before reading
#: it, clears itself and reports the file's name and size to ``source``; nothing is sent.
SIZE_CHECK_JS = """
const FileInput = Bokeh.Models.get("FileInput");
const View = FileInput == null ? null : FileInput.prototype.default_view;
if (View != null && !View.prototype.__prsa_size_check) {
  const load = View.prototype.load_files;
  View.prototype.load_files = async function(files) {
    const tags = this.model.tags;
    const limit = tags.length == 2 && typeof tags[0] == "number" ? tags[0] : null;
    if (limit != null) {
      for (const file of files) {
        if (file.size > limit) {
          this.input_el.value = "";
          tags[1].data = {name: [file.name], bytes: [file.size]};
          return;
        }
      }
    }
    return load.call(this, files);
  };
  View.prototype.__prsa_size_check = true;
}
"""


_BAR = ("<style>@keyframes prsa-ind {from {margin-left: -30%} to {margin-left: 100%}}</style>"
        "<div style='background:#eee;width:100%;height:8px;overflow:hidden'><div style='background:#9467bd;"
        "width:30%;height:8px;animation:prsa-ind 1.2s linear infinite'></div></div>")

_DOWNLOAD_FIRST_JS = """
if (files.data.name.length == 0) { return; }
const blob = new Blob([files.data.text[0]], {type: 'application/toml'});
const a = document.createElement('a');
a.href = URL.createObjectURL(blob);
a.download = files.data.name[0];
document.body.appendChild(a);
a.click();
setTimeout(() => { URL.revokeObjectURL(a.href); a.remove(); }, 1000);
"""


class FitPanel:
    """Calibration from an uploaded log, for one :class:`prsa_ctrl.app.page.AppPage`.

    Parameters
    ----------
    page : AppPage
        The page: its document, session, error line and ``after_switch`` (re-tune after a plant
        change).
    """

    def __init__(self, page) -> None:
        self.page = page
        self.calibration: Calibration | None = None
        self._seq = 0
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="prsa-app-fit")
        self.upload, self.too_large = upload_input(".csv,.mat", "Calibrate from a drive log (prsa-fit LOG --plant <this "
                                                   "plant>; a .mat log or a linear axis with its description below)",
                                                   "prsa-log-upload")
        self.too_large.on_change("data", lambda attr, old, new: self._too_large())
        #: the log description (name, bytes) the next log is read through (prsa-fit --log-format), or None
        self.log_format: tuple[str, bytes] | None = None
        self.fmt_upload, self.fmt_too_large = upload_input(
            ".toml", "log description for the next log (prsa-fit --log-format FORMAT.toml: a .mat log, a linear "
            "axis in load coordinates)", "prsa-format-upload")
        self.fmt_too_large.on_change("data", lambda attr, old, new: self._too_large(self.fmt_too_large, "format"))
        self.fmt_upload.on_change("value", lambda attr, old, new: page.doc.add_next_tick_callback(self._take_log_format))
        self.frf_upload, self.frf_too_large = upload_input(
            ".csv", "or from a measured frequency response (prsa-fit --frf FRF.csv --plant <this plant>: frequency_hz, "
            "magnitude_db, phase_deg or real, imag, optional coherence)", "prsa-frf-upload")
        self.frf_too_large.on_change("data", lambda attr, old, new: self._too_large(self.frf_too_large, "frf"))
        self.use = Button(label="Use the fitted plant", disabled=True, button_type="success",
                          css_classes=["prsa-fit-use"])
        self.discard = Button(label="Cancel / discard", disabled=True, css_classes=["prsa-fit-discard"])
        self.download = Button(label="Download the fitted plant (TOML)", disabled=True,
                               css_classes=["prsa-fit-download"])
        self.files = ColumnDataSource(data={"name": [], "text": []})
        self.download.js_on_click(CustomJS(args={"files": self.files}, code=_DOWNLOAD_FIRST_JS))
        self.out = Div(text="", css_classes=["prsa-fit-out"], sizing_mode="stretch_width")
        #: the figures, built at the first calibration (the first page stays as light as before)
        self.views: FitViews | None = None
        self._views_box = column(sizing_mode="stretch_width")
        #: the calibration tab's content (:class:`prsa_ctrl.app.page.AppPage` puts it in its tab)
        self.layout = row(column(self.fmt_upload, self.upload, self.frf_upload, row(self.use, self.discard), self.download,
                                 width=330),
                          column(self.out, self._views_box, sizing_mode="stretch_width"), sizing_mode="stretch_width")
        # value and filename arrive in one patch, value first: read both once the patch is applied
        self.upload.on_change("value", lambda attr, old, new: page.doc.add_next_tick_callback(self._start))
        self.frf_upload.on_change("value", lambda attr, old, new: page.doc.add_next_tick_callback(
            partial(self._start, "frf")))
        self.use.on_click(self._use)
        self.discard.on_click(self._discard)

    def _too_large(self, src: ColumnDataSource | None = None, kind: str = "log") -> None:
        line = too_large_line(self.too_large if src is None else src, f"uploaded-{kind}.csv")
        if line is not None:
            self.page.show_error(line)

    def _take_log_format(self) -> None:
        """Keep the uploaded log description for the next log (nothing is fitted yet)."""
        try:
            got = uploaded_file(self.fmt_upload, "log-format.toml")
        except AppInputError as exc:
            self.page.show_error(str(exc))
            return
        if got is not None:
            self.log_format = got
            self.out.text = (f"<div data-k='fit-format' data-name='{html.escape(got[0])}'>Log description "
                             f"{html.escape(got[0])} ({len(got[1])} bytes): the next log is read through it</div>")

    def _start(self, kind: str = "log") -> None:
        try:
            got = uploaded_file(self.frf_upload if kind == "frf" else self.upload, f"uploaded-{kind}.csv")
        except AppInputError as exc:
            self.page.show_error(str(exc))
            return
        if got is None:
            return
        name, content = got
        self._seq += 1
        self.calibration = None
        self.use.disabled = self.download.disabled = True
        self.discard.disabled = False  # cancels the running fit
        self._show_views(None)
        base = self.page.session.plant_label
        self.out.text = (f"<div data-k='fit-state' data-state='running'><b>Calibration</b>: fitting "
                         f"<b>{html.escape(base)}</b> to {html.escape(name)} ({len(content)} bytes) in the background "
                         f"<span data-k='fit-kind' data-kind='{kind}'></span>"
                         + ("(prsa-fit --frf in a worker thread: the rigid and the two-mass model fitted to the "
                            "response, the structure the data choose; seconds)" if kind == "frf" else
                            "(prsa-fit's fit in a worker thread: Gauss-Newton on the whole log, no intermediate progress; "
                            "seconds)") + f"</div>{_BAR}")
        self._pool.submit(self._work, self._seq, name, content, kind, self.log_format if kind == "log" else None)

    def _work(self, seq: int, name: str, content: bytes, kind: str = "log", log_format=None) -> None:
        try:
            cal = self.page.session.calibrate(name, content, cancelled=lambda: seq != self._seq, kind=kind,
                                              log_format=log_format)
        except Cancelled:
            return
        except AppInputError as exc:
            self.page.doc.add_next_tick_callback(partial(self._failed, seq, name, str(exc)))
            return
        except Exception as exc:  # noqa: BLE001 - one line in the page, never a traceback
            self.page.doc.add_next_tick_callback(partial(self._failed, seq, name,
                                                         f"{name}: the fit failed ({one_line(exc)})"))
            return
        self.page.doc.add_next_tick_callback(partial(self._done, seq, cal))

    def _failed(self, seq: int, name: str, line: str) -> None:
        if seq != self._seq:
            return
        self.discard.disabled = True
        self.page.show_error(line)
        self.out.text = (f"<div data-k='fit-state' data-state='failed'><b>Calibration</b> from "
                         f"{html.escape(name)} failed; the plant is unchanged</div>"
                         f"<div data-k='fit-error' style='color:#b00'>error: {html.escape(line)}</div>")

    def _done(self, seq: int, cal: Calibration) -> None:
        if seq != self._seq:
            return
        self.calibration = cal
        self.discard.disabled = False
        if cal.refused is not None:  # no plant file: nothing to use or download
            self.use.disabled = self.download.disabled = True
            self.files.data = {"name": [], "text": []}
            self.out.text = report_html(cal, "refused")
        else:
            self.use.disabled, self.download.disabled = not cal.usable, False
            self.files.data = {"name": [cal.file_name], "text": [cal.plant_text]}
            self.out.text = report_html(cal, "done")
        self._show_views(cal.report.get("views"))

    def _show_views(self, views: dict | None) -> None:
        """Draw a fit's views (built on first use), or hide them (None)."""
        if self.views is None:
            if not views:
                return
            self.views = FitViews()
            self._views_box.children = [self.views.root]
        self.views.show(views)

    def _use(self) -> None:
        cal = self.calibration
        if cal is None or cal.refused is not None:
            return
        try:
            notes = self.page.session.use_calibration(cal)
        except AppInputError as exc:
            self.page.show_error(str(exc))
            return
        self.use.disabled = True
        self.out.text = report_html(cal, "used")
        self.page.after_switch("plant", notes)

    def _discard(self) -> None:
        self._seq += 1
        self.calibration = None
        self.use.disabled = self.discard.disabled = self.download.disabled = True
        self.files.data = {"name": [], "text": []}
        self.out.text = ""
        self._show_views(None)

    def close(self) -> None:
        """Stop taking work (a running fit stops at its next iteration)."""
        self._seq += 1
        self._pool.shutdown(wait=False, cancel_futures=True)


_PLOT = dict(height=260, sizing_mode="stretch_width", toolbar_location="above")
_MODEL_COLORS = ("#2ca02c", "#ff7f0e", "#1f77b4")  # other fitted models (rigid, two-mass), then the written plant


class FitViews:
    """The three views of a fit, drawn from ``prsa-fit --json``'s ``views``
    (:func:`prsa_ctrl.plots.fit.fit_views`): the replay of the plant as written against the
    measured speed, the residual below it, and the frequency response of the data (points)
    beside the fitted models (lines) on a Hz axis, with the coherence when the data carry one.
    The first record and the first response are shown (the app fits one log)."""

    def __init__(self) -> None:
        self.replay_src = ColumnDataSource(data={"t": [], "measured": [], "model": [], "residual": []},
                                           name="prsa-fit-replay")
        self.frf_src = ColumnDataSource(data={"f": [], "mag": [], "phase": [], "coherence": [], "res_db": [],
                                              "res_deg": []}, name="prsa-fit-frf")
        self.models_src = ColumnDataSource(data={"xs": [], "mag": [], "phase": [], "label": [], "color": [],
                                                 "width": []}, name="prsa-fit-frf-models")
        self.replay = figure(title="Replay of the plant as written", x_axis_label="time (s)",
                             y_axis_label="nut speed (rad/s)", css_classes=["prsa-fit-replay"], **_PLOT)
        self.replay.line("t", "measured", source=self.replay_src, color="#7f7f7f", line_width=1,
                         legend_label="measured (angle difference)")
        self.replay_line = self.replay.line("t", "model", source=self.replay_src, color="#1f77b4", line_width=1.5,
                                            legend_label="plant as written")
        self.replay.legend.location = "bottom_right"
        self.residual = figure(title="Residual (measured - replay)", x_axis_label="time (s)",
                               y_axis_label="residual (rad/s)", x_range=self.replay.x_range,
                               css_classes=["prsa-fit-residual"], **{**_PLOT, "height": 180})
        self.residual.line("t", "residual", source=self.replay_src, color="#d62728", line_width=0.8)
        self.mag = figure(title="Frequency response torque command -> nut speed", x_axis_type="log",
                          x_axis_label="frequency (Hz)", y_axis_label="|G| (dB re 1 rad/s per N m)",
                          css_classes=["prsa-fit-frf-mag"], **_PLOT)
        self.mag.scatter("f", "mag", source=self.frf_src, size=4, color="#555555", legend_label="data")
        self.mag.multi_line("xs", "mag", source=self.models_src, color="color", line_width="width",
                            legend_field="label")
        self.mag.legend.location = "bottom_left"
        self.phase = figure(x_axis_type="log", x_axis_label="frequency (Hz)", y_axis_label="phase (deg)",
                            x_range=self.mag.x_range, css_classes=["prsa-fit-frf-phase"], **{**_PLOT, "height": 200})
        self.phase.scatter("f", "phase", source=self.frf_src, size=4, color="#555555")
        self.phase.multi_line("xs", "phase", source=self.models_src, color="color", line_width="width")
        self.frf_res = figure(title="Residual of the written plant's response", x_axis_type="log",
                              x_axis_label="frequency (Hz)", y_axis_label="residual (dB)", x_range=self.mag.x_range,
                              css_classes=["prsa-fit-frf-residual"], **{**_PLOT, "height": 170})
        self.frf_res.line("f", "res_db", source=self.frf_src, color="#d62728", legend_label="magnitude (dB)")
        self.frf_res.line("f", "res_deg", source=self.frf_src, color="#9467bd", legend_label="phase (deg)")
        self.coherence = figure(x_axis_type="log", x_axis_label="frequency (Hz)", y_axis_label="coherence",
                                x_range=self.mag.x_range, y_range=(0.0, 1.05), css_classes=["prsa-fit-coherence"],
                                **{**_PLOT, "height": 150})
        self.coherence.line("f", "coherence", source=self.frf_src, color="#2ca02c")
        self.summary = Div(text="", sizing_mode="stretch_width")
        self.root = column(self.summary, self.replay, self.residual, self.mag, self.phase, self.frf_res,
                           self.coherence, sizing_mode="stretch_width", visible=False)

    def show(self, views: dict | None) -> None:
        """Draw ``views`` (None or without data: hide the views)."""
        views = views if isinstance(views, dict) else {}
        linear = views.get("unit") == "m/s"  # a linear axis (load coordinates): speed m/s, force N
        self.replay.yaxis.axis_label = "speed (m/s)" if linear else "nut speed (rad/s)"
        self.residual.yaxis.axis_label = "residual (m/s)" if linear else "residual (rad/s)"
        self.mag.yaxis.axis_label = "|G| (dB re 1 m/s per N)" if linear else "|G| (dB re 1 rad/s per N m)"
        replay = next(iter((views.get("replay") or {}).items()), None)
        frf = next(iter((views.get("frf") or {}).items()), None)
        self.root.visible = replay is not None or frf is not None
        parts = []
        self.replay.visible = self.residual.visible = replay is not None
        if replay is not None:
            name, r = replay
            self.replay_src.data = {"t": _nums(r["time_s"]), "measured": _nums(r["measured_rad_s"]),
                                    "model": _nums(r["model_rad_s"]), "residual": _nums(r["residual_rad_s"])}
            self.replay.title.text = f"{name}: {r['label']}"
            w = r.get("whiteness")
            self.residual.title.text = ("Residual (measured - replay)" + (
                f": autocorrelation lag 1 {w['acf'].get('1', w['acf'].get(1, float('nan'))):+.2f} (white band "
                f"+/- {w['band']:.2g})" if w else ""))
            parts.append(f"<span data-k='fit-views-replay' data-mode='{html.escape(r['mode'])}' "
                         f"data-n='{len(r['time_s'])}' data-every='{int(r['every'])}'>replay of {html.escape(name)}: "
                         f"{html.escape(r['label'])}" + (f" (one sample in {int(r['every'])} shown)" if r["every"] > 1 else "")
                         + "</span>")
        else:
            self.replay_src.data = {"t": [], "measured": [], "model": [], "residual": []}
        self.mag.visible = self.phase.visible = self.frf_res.visible = frf is not None
        coh = None
        if frf is not None:
            name, fr = frf
            coh = fr.get("coherence")
            n = len(fr["frequency_hz"])
            self.frf_src.data = {"f": _nums(fr["frequency_hz"]), "mag": _nums(fr["measured"]["magnitude_db"]),
                                 "phase": _nums(fr["measured"]["phase_deg"]),
                                 "coherence": _nums(coh) if coh is not None else [float("nan")] * n,
                                 "res_db": _nums(fr["residual"]["magnitude_db"]),
                                 "res_deg": _nums(fr["residual"]["phase_deg"])}
            labels = list(fr["models"])
            others = [k for k in labels if not fr["models"][k]["written"]]
            colors = {k: _MODEL_COLORS[i % 2] for i, k in enumerate(others)}
            self.models_src.data = {
                "xs": [_nums(fr["frequency_hz"]) for _ in labels],
                "mag": [_nums(fr["models"][k]["magnitude_db"]) for k in labels],
                "phase": [_nums(fr["models"][k]["phase_deg"]) for k in labels],
                "label": labels, "color": [colors.get(k, _MODEL_COLORS[2]) for k in labels],
                "width": [2.0 if fr["models"][k]["written"] else 1.2 for k in labels]}
            self.mag.title.text = (f"{name}: frequency response{' force -> speed' if linear else ''}, data beside "
                                   "the fitted model" + ("s" if len(labels) > 1 else ""))
            parts.append(f"<span data-k='fit-views-frf' data-n='{n}' data-unit='Hz' "
                         f"data-models='{len(labels)}'>frequency response of {html.escape(name)} ({n} points, Hz): "
                         f"{html.escape(fr['source'])}</span>")
        else:
            self.frf_src.data = {"f": [], "mag": [], "phase": [], "coherence": [], "res_db": [], "res_deg": []}
            self.models_src.data = {"xs": [], "mag": [], "phase": [], "label": [], "color": [], "width": []}
        self.coherence.visible = coh is not None
        self.summary.text = (f"<div data-k='fit-views' style='font-size:12px'>{'<br>'.join(parts)}</div>"
                             if parts else "")


def _nums(values) -> list:
    """A JSON list of numbers or None as floats for a Bokeh source (None: NaN, a gap in a line)."""
    return [float("nan") if v is None else float(v) for v in values]


def _verdict_html(cal: Calibration) -> str:
    """The verdict: refused (prsa-fit's line with the diagnosis), validated or not validated."""
    v = (cal.report.get("solver") or {}).get("validation") or cal.report.get("validation")  # (a linear axis's: top level)
    if cal.refused is not None:
        return (f"<div data-k='fit-verdict' data-verdict='refused' style='color:#b00;font-weight:bold'>Refused: "
                f"{html.escape(cal.refused)}. No plant file was written; the app's plant is unchanged.</div>")
    if v is None and cal.report.get("frf_structure"):  # prsa-fit --frf alone: exit 0, no log to replay
        return ("<div data-k='fit-verdict' data-verdict='not-validated'>Fitted to the measured frequency response "
                "(no replay validation: that needs a drive log); the structure the data chose:</div>"
                + _structure_html(cal.report["frf_structure"]))
    if v is None and cal.report.get("mechanism") == "linear-axis":  # prsa-fit --log-format: each log replayed
        return ("<div data-k='fit-verdict' data-verdict='replayed'>" + "<br>".join(
            html.escape(f"{r['log']}: {r['replay']}, fit position {r['fit_percent']['position']:.3f} %, velocity "
                        f"{r['fit_percent']['velocity']:.3f} %, force {r['fit_percent']['force']:.3f} %")
            for r in cal.report.get("replay", [])) + "</div>")
    if v is None:
        return ("<div data-k='fit-verdict' data-verdict='not-validated'>Not validated: prsa-fit replayed no log "
                "through the written plant.</div>")
    unit = "m/s" if cal.report.get("mechanism") == "linear-axis" else "rad/s"  # (a linear axis's entries: m/s)
    u = unit.replace("/", "_")
    pct = "; ".join(f"{html.escape(n)} replayed at {e['fit_percent']:.1f} % ({e[f'error_rms_{u}']:.3g} {unit}, "
                    f"{e[f'error_rms_{u}'] / max(e[f'noise_floor_{u}'], 1e-300):.3g} x its noise floor)"
                    for n, e in (v.get("written_plant") or {}).items() if e.get("finite", "residual_peak_hz" in e))
    if not v.get("passes"):  # exit 0 with a failed validation does not happen; never shown as good
        return (f"<div data-k='fit-verdict' data-verdict='refused' style='color:#b00;font-weight:bold'>Not validated: "
                f"{html.escape('; '.join(v.get('reasons') or []))}</div>")
    how = f" ({html.escape(v['replay'])})" if v.get("replay") else ""  # (a linear axis's validation says its replay)
    return (f"<div data-k='fit-verdict' data-verdict='validated' style='color:#060'>Validated: the plant as written "
            f"explains the log ({pct}){how}.</div>")


def _structure_html(st: dict) -> str:
    """The structure a frequency response chose, why, and the two-mass model's axial mode and
    anti-resonance with their 95 % intervals (``prsa-fit``'s ``structure:`` lines)."""
    lines = st.get("lines") or []
    return (f"<div data-k='fit-structure' data-structure='{html.escape(str(st.get('structure')))}' "
            "style='font-size:12px;white-space:pre-wrap'>" + "<br>".join(html.escape(x) for x in lines) + "</div>")


def report_html(cal: Calibration, state: str) -> str:
    """The calibration tab's report: the verdict, the fitted values with their 95 % intervals,
    fit %, warnings and notes, as HTML (every text from the data escaped).

    Parameters
    ----------
    cal : Calibration
        The session's calibration (:meth:`prsa_ctrl.app.session.AppSession.calibrate`).
    state : {"done", "used", "refused"}
        Fitted and not yet used, the session's plant now, or refused.

    Returns
    -------
    str
        The HTML; its ``data-k`` attributes name the parts (``fit-state``, ``fit-verdict``, ...).
    """
    rep = cal.report
    if not rep.get("parameters"):  # a refused frequency-response fit: prsa-fit's exit 3 line, nothing fitted
        return (f"<div data-k='fit-state' data-state='refused' data-file=''><b>Calibration</b> of "
                f"<b>{html.escape(cal.base_label)}</b> from {html.escape(cal.log_name)} (prsa-fit --frf): refused</div>"
                + _verdict_html(cal))
    rows = []
    for key, v in rep["parameters"].items():
        kept = v.get("kept_base")
        shown = f"{v['written']:.6g} (base value kept: not identifiable)" if kept else f"{v['value']:.6g}"
        ci = (html.escape(v.get("note", "held, not fitted")) if v.get("ci95") is None else
              f"{v['ci95'][0]:.6g} .. {v['ci95'][1]:.6g}")
        rows.append(f"<tr><td>{html.escape(key)}</td><td data-k='fit-{key}-value'>{shown}</td>"
                    f"<td data-k='fit-{key}-ci'>{ci}</td><td>{html.escape(v['unit'])}</td></tr>")
    j = rep.get("reflected_inertia_kg_m2")  # (a linear axis: its mass is among the parameters)
    if j is not None:
        rows.append(f"<tr><td>reflected inertia</td><td data-k='fit-reflected-value'>{j['value']:.6g}</td>"
                    f"<td>{j['ci95'][0]:.6g} .. {j['ci95'][1]:.6g}</td><td>kg m^2</td></tr>")
    fits = "; ".join(f"{pct:.2f} % on {html.escape(f)}" if pct is not None else f"n/a on {html.escape(f)}"
                     for f, pct in rep["fit_percent"].items())
    warns = "".join(f"<li data-k='fit-warning'>warning: {html.escape(w)}</li>" for w in rep["warnings"])
    notes = "".join(f"<li>note: {html.escape(n)}</li>" for n in cal.notes)
    if state == "refused":
        return (f"<div data-k='fit-state' data-state='refused' data-file=''><b>Calibration</b> of "
                f"<b>{html.escape(cal.base_label)}</b> from {html.escape(cal.log_name)} (prsa-fit, status "
                f"<span data-k='fit-status'>{html.escape(str(rep.get('status', '')))}</span>; solver "
                f"{html.escape(str(rep.get('solver', {}).get('status', '')))}): refused, fit {fits}</div>" + _verdict_html(cal)
                + "<div style='font-size:12px'>The values the refused fit found (not written, not for tuning):</div>"
                "<table style='font-size:12px;color:#777'><tr><th style='text-align:left'>key</th><th>value</th>"
                "<th>95 % CI</th><th>unit</th></tr>" + "".join(rows) + "</table>"
                + (f"<ul style='font-size:12px;margin:2px 0'>{warns}{notes}</ul>" if warns or notes else ""))
    head = ("in use: the app now tunes this plant (Actuator tab)" if state == "used" else
            "press <i>Use the fitted plant</i> to tune it, or discard it" if cal.usable else
            "a linear-axis plant (load coordinates, replayed closed loop from the log's reference): download it, "
            "prsa-axis tunes it; the app tunes screw-driven actuators")
    return (f"<div data-k='fit-state' data-state='{state}' data-file='{html.escape(cal.file_name)}'><b>Calibration</b> "
            f"of <b>{html.escape(cal.base_label)}</b> from {html.escape(cal.log_name)} (prsa-fit, status "
            f"<span data-k='fit-status'>{html.escape(str(rep.get('status', '')))}</span>; solver "
            f"{html.escape(str(rep.get('solver', {}).get('status', '')))}): fit {fits}; {head}. Fitted plant file: "
            f"{html.escape(cal.file_name)}</div>" + _verdict_html(cal)
            + "<table style='font-size:12px'><tr><th style='text-align:left'>key</th><th>value</th><th>95 % CI</th>"
            "<th>unit</th></tr>" + "".join(rows) + "</table>"
            + (f"<ul style='font-size:12px;margin:2px 0'>{warns}{notes}</ul>" if warns or notes else ""))
