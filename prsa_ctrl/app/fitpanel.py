"""The page's calibration panel: upload a drive log, fit the plant in the background
(``prsa-fit``'s path, :meth:`prsa_ctrl.app.session.AppSession.calibrate`), show the fitted values
with their 95 % intervals and the fit's warnings, and on the user's confirmation make the fitted
plant the app's plant and re-tune.

Elements the browser tests read carry ``data-k`` attributes (``fit-state``, ``fit-<key>-value``,
``fit-<key>-ci``, ``fit-warning``), the widgets CSS classes ``prsa-log-upload``, ``prsa-fit-use``,
``prsa-fit-discard``, ``prsa-fit-download``.
"""

from __future__ import annotations

import base64
import html
from concurrent.futures import ThreadPoolExecutor
from functools import partial

from bokeh.models import Button, ColumnDataSource, CustomJS, Div, FileInput

from .session import AppInputError, Calibration, Cancelled, one_line

__all__ = ["FitPanel", "uploaded_file"]


def uploaded_file(widget: FileInput, default: str) -> tuple[str, bytes] | None:
    """The file a Bokeh ``FileInput`` holds: ``(name, content)`` (``default`` when the browser
    sent no name), or None when it holds none."""
    value = widget.value
    if not value:
        return None
    try:
        name = widget.filename
    except Exception:  # noqa: BLE001 - bokeh's UnsetValueError: no name came with the file
        name = None
    value = value[0] if isinstance(value, list) else value
    name = (name[0] if isinstance(name, list) else name) or default
    return name, base64.b64decode(value)


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
        self.upload = FileInput(accept=".csv", title="Calibrate from a drive log (prsa-fit LOG --plant <this plant>)",
                                css_classes=["prsa-log-upload"])
        self.use = Button(label="Use the fitted plant", disabled=True, button_type="success",
                          css_classes=["prsa-fit-use"])
        self.discard = Button(label="Cancel / discard", disabled=True, css_classes=["prsa-fit-discard"])
        self.download = Button(label="Download the fitted plant (TOML)", disabled=True,
                               css_classes=["prsa-fit-download"])
        self.files = ColumnDataSource(data={"name": [], "text": []})
        self.download.js_on_click(CustomJS(args={"files": self.files}, code=_DOWNLOAD_FIRST_JS))
        self.out = Div(text="", css_classes=["prsa-fit-out"], sizing_mode="stretch_width")
        # value and filename arrive in one patch, value first: read both once the patch is applied
        self.upload.on_change("value", lambda attr, old, new: page.doc.add_next_tick_callback(self._start))
        self.use.on_click(self._use)
        self.discard.on_click(self._discard)

    def _start(self) -> None:
        got = uploaded_file(self.upload, "uploaded-log.csv")
        if got is None:
            return
        name, content = got
        self._seq += 1
        self.calibration = None
        self.use.disabled = self.download.disabled = True
        self.discard.disabled = False  # cancels the running fit
        base = self.page.session.plant_label
        self.out.text = (f"<div data-k='fit-state' data-state='running'><b>Calibration</b>: fitting "
                         f"<b>{html.escape(base)}</b> to {html.escape(name)} ({len(content)} bytes) in the background "
                         f"(prsa-fit in a child process: Gauss-Newton on the whole log, no intermediate progress; "
                         f"seconds)</div>{_BAR}")
        self._pool.submit(self._work, self._seq, name, content)

    def _work(self, seq: int, name: str, content: bytes) -> None:
        try:
            cal = self.page.session.calibrate(name, content, cancelled=lambda: seq != self._seq)
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
                         f"{html.escape(name)} failed; the plant is unchanged</div>")

    def _done(self, seq: int, cal: Calibration) -> None:
        if seq != self._seq:
            return
        self.calibration = cal
        self.use.disabled = self.discard.disabled = self.download.disabled = False
        self.files.data = {"name": [cal.file_name], "text": [cal.plant_text]}
        self.out.text = _report_html(cal, "done")

    def _use(self) -> None:
        cal = self.calibration
        if cal is None:
            return
        try:
            notes = self.page.session.use_calibration(cal)
        except AppInputError as exc:
            self.page.show_error(str(exc))
            return
        self.use.disabled = True
        self.out.text = _report_html(cal, "used")
        self.page.after_switch("plant", notes)

    def _discard(self) -> None:
        self._seq += 1
        self.calibration = None
        self.use.disabled = self.discard.disabled = self.download.disabled = True
        self.files.data = {"name": [], "text": []}
        self.out.text = ""

    def close(self) -> None:
        """Stop taking work (a running fit's command is ended)."""
        self._seq += 1
        self._pool.shutdown(wait=False, cancel_futures=True)


def _report_html(cal: Calibration, state: str) -> str:
    """The fitted values with their 95 % intervals, fit %, warnings and notes."""
    rep = cal.report
    rows = []
    for key, v in rep["parameters"].items():
        lo, hi = v["ci95"]
        kept = v.get("kept_base")
        shown = f"{v['written']:.6g} (base value kept: not identifiable)" if kept else f"{v['value']:.6g}"
        rows.append(f"<tr><td>{html.escape(key)}</td><td data-k='fit-{key}-value'>{shown}</td>"
                    f"<td data-k='fit-{key}-ci'>{lo:.6g} .. {hi:.6g}</td><td>{html.escape(v['unit'])}</td></tr>")
    j = rep["reflected_inertia_kg_m2"]
    rows.append(f"<tr><td>reflected inertia</td><td data-k='fit-reflected-value'>{j['value']:.6g}</td>"
                f"<td>{j['ci95'][0]:.6g} .. {j['ci95'][1]:.6g}</td><td>kg m^2</td></tr>")
    fits = "; ".join(f"{pct:.2f} % on {html.escape(f)}" if pct is not None else f"n/a on {html.escape(f)}"
                     for f, pct in rep["fit_percent"].items())
    warns = "".join(f"<li data-k='fit-warning'>warning: {html.escape(w)}</li>" for w in rep["warnings"])
    notes = "".join(f"<li>note: {html.escape(n)}</li>" for n in cal.notes)
    head = ("in use: the app now tunes this plant" if state == "used" else
            "press <i>Use the fitted plant</i> to tune it, or discard it")
    return (f"<div data-k='fit-state' data-state='{state}' data-file='{html.escape(cal.file_name)}'><b>Calibration</b> "
            f"of <b>{html.escape(cal.base_label)}</b> from {html.escape(cal.log_name)} (prsa-fit, solver "
            f"{html.escape(str(rep['solver'].get('status', '')))}): fit {fits}; {head}. Fitted plant file: "
            f"{html.escape(cal.file_name)}</div>"
            "<table style='font-size:12px'><tr><th style='text-align:left'>key</th><th>value</th><th>95 % CI</th>"
            "<th>unit</th></tr>" + "".join(rows) + "</table>"
            + (f"<ul style='font-size:12px;margin:2px 0'>{warns}{notes}</ul>" if warns or notes else ""))
