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
import binascii
import html
from concurrent.futures import ThreadPoolExecutor
from functools import partial

from bokeh.models import Button, ColumnDataSource, CustomJS, Div, FileInput

from .session import AppInputError, Calibration, Cancelled, one_line, upload_name

__all__ = ["FitPanel", "uploaded_file", "upload_input", "too_large_line", "MAX_UPLOAD_BYTES", "SIZE_CHECK_JS"]


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
        self.upload, self.too_large = upload_input(".csv", "Calibrate from a drive log (prsa-fit LOG --plant <this "
                                                   "plant>)", "prsa-log-upload")
        self.too_large.on_change("data", lambda attr, old, new: self._too_large())
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

    def _too_large(self) -> None:
        line = too_large_line(self.too_large, "uploaded-log.csv")
        if line is not None:
            self.page.show_error(line)

    def _start(self) -> None:
        try:
            got = uploaded_file(self.upload, "uploaded-log.csv")
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
        base = self.page.session.plant_label
        self.out.text = (f"<div data-k='fit-state' data-state='running'><b>Calibration</b>: fitting "
                         f"<b>{html.escape(base)}</b> to {html.escape(name)} ({len(content)} bytes) in the background "
                         f"(prsa-fit's fit in a worker thread: Gauss-Newton on the whole log, no intermediate progress; "
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
        """Stop taking work (a running fit stops at its next iteration)."""
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
