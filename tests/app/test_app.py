"""prsa-app without a browser: the command line, the session model behind the page, the
Bokeh document and the notebook entry point."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace

import pytest

pytest.importorskip("bokeh", reason="prsa-app tests need the app extra (pip install '.[app]')")

from prsa_ctrl import PID, load_plant, load_scene  # noqa: E402
from prsa_ctrl.app.cli import main  # noqa: E402
from prsa_ctrl.app.session import AppInputError, AppSession, Settings  # noqa: E402


@pytest.fixture(scope="module")
def session():
    s = AppSession()
    yield s
    s.close()


def _fresh(**bounds):
    from prsa_ctrl.studies.autotune import actuator_loops
    from prsa_ctrl.tuning.generic import tune_loops

    plant, scene = load_plant(), load_scene()
    return tune_loops(actuator_loops(plant, scene), objective=scene.objective, controller=scene.controller, **bounds)


@pytest.mark.parametrize("argv, expected", [
    (["--plant", "nope"], "prsa-app: error: unknown plant 'nope'; expected a built-in name"),
    (["--plant", "missing.toml"], "prsa-app: error: plant file 'missing.toml' not found"),
    (["--scene", "duty-ramp"], "prsa-app: error: scene 'duty-ramp' is a duty cycle"),
    (["--scene", "paper-move"], "prsa-app: error: scene 'paper-move' is a move (cascade) scene"),
    (["--port", "70000"], "prsa-app: error: argument --port: --port 70000: expected an integer port in [0, 65535]"),
    (["--port", "x"], "prsa-app: error: argument --port: --port 'x': expected an integer port"),
    (["--bogus"], "prsa-app: error: unrecognized arguments: --bogus"),
    # a value that starts with '-' reaches its flag's check, named as typed (was "--port: expected one argument")
    (["--port", "-x"], "prsa-app: error: argument --port: --port '-x': expected an integer port"),
    (["--po", "-x"], "prsa-app: error: argument --port: --port '-x': expected an integer port"),
    (["--plant", "-x"], "prsa-app: error: unknown plant '-x'; expected a built-in name"),
    (["--port", "--"], "prsa-app: error: --port '--': expected a value"),
])
def test_bad_flags_and_files_one_line_exit_2(argv, expected, capsys):
    assert main(argv) == 2
    out = capsys.readouterr()
    assert out.out == ""
    assert out.err.startswith(expected), out.err
    assert out.err.count("\n") == 1, out.err


def test_port_in_use_is_one_line_exit_2(capsys):
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        assert main(["--port", str(port), "--no-browser"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"prsa-app: error: --port {port}: cannot listen on 127.0.0.1")
    assert err.count("\n") == 1


def test_core_commands_do_not_import_the_app_stack():
    code = ("import sys, prsa_ctrl.cli.tune, prsa_ctrl.studies.autotune, prsa_ctrl.tuning.tuner; "
            "print(any(m.split('.')[0] in ('bokeh', 'tornado', 'panel') for m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_bounds_retune_on_one_tuner_to_the_fresh_tuners_result(session):
    s0 = session.default_settings()
    first = session.tuned(s0)
    tuner = session.tuner(session.scene_for(s0))
    for bounds in ({"ms_max": 1.55}, {"ms_max": 1.5, "mt_max": 1.3}, {"ms_max": 1.6, "max_noise_gain": 0.09}):
        v = session.tuned(replace(s0, **bounds))
        ref = _fresh(**bounds)
        assert session.tuner(session.scene_for(replace(s0, **bounds))) is tuner  # reused, not rebuilt
        assert v.pid.gains == ref.pid.gains
        assert v.status == ref.status
        assert v.design.margins.ms == pytest.approx(ref.ms, rel=1e-12)
    assert v.noise_gain <= 0.09 * (1 + 1e-6)
    assert v.pid.kp < _fresh(ms_max=1.6).pid.kp  # the bound is active
    assert first.pid.gains == _fresh(ms_max=s0.ms_max).pid.gains


def test_bad_settings_are_one_line_errors(session):
    s0 = session.default_settings()
    with pytest.raises(AppInputError, match=r"^load step '500:1e9': load 1e\+09 N out of range for paper-iprsm"):
        session.tuned(replace(s0, load_step="500:1e9"))
    with pytest.raises(AppInputError, match=r"^load step '500-1500': expected INITIAL:FINAL"):
        session.tuned(replace(s0, load_step="500-1500"))
    with pytest.raises(AppInputError, match=r"^Ms bound 0.9: expected a number in \(1, 10\)"):
        session.tuned(replace(s0, ms_max=0.9))
    with pytest.raises(AppInputError, match=r"^manual kp 0.0: expected a positive gain"):
        session.manual(s0, 0.0, 1.0)


def test_uploaded_plant_is_named_as_uploaded_and_leaves_the_session_intact(tmp_path):
    s = AppSession()
    try:
        with pytest.raises(AppInputError) as info:
            s.upload("plant", "my-plant.toml", b"[nut\n")
        assert str(info.value).startswith("my-plant.toml: invalid TOML")
        assert s.plant.name == "paper-iprsm"  # the old plant stays
        from prsa_ctrl.plant.plantfile import plant_file_path

        s.upload("plant", "copy.toml", plant_file_path("iprsm-60").read_text().encode())
        assert s.plant.name == load_plant("iprsm-60").name
        assert s.plant_label == "copy.toml"
    finally:
        s.close()


def test_copy_as_code_is_the_same_tuning(session):
    s = replace(session.default_settings(), ms_max=1.5, mt_max=1.35)
    cli, py = session.code(s)
    assert cli == ("prsa-tune --plant paper-iprsm --scene paper-load-step --load-step 500:1500 --objective iae "
                   "--controller pi --ms-max 1.5 --mt-max 1.35")
    ns: dict = {}
    exec(compile(py.replace("print(", "(lambda *a: None)("), "<copied>", "exec"), ns)
    assert ns["result"].pid.gains == session.tuned(s).pid.gains


def test_document_builds_and_the_notebook_entry_returns_the_application():
    from bokeh.application import Application
    from bokeh.document import Document

    from prsa_ctrl.app import application
    from prsa_ctrl.app.page import make_document

    doc = Document()
    page = make_document(doc)
    try:
        assert len(doc.roots) == 1
        assert doc.title.startswith("prsa-app")
        assert page.settings == Settings(objective="iae", controller="pi", ms_max=1.4, mt_max=None,
                                         load_step="500:1500", fidelity="auto")
    finally:
        page._destroyed(None)
    assert isinstance(application(), Application)
    with pytest.raises(AppInputError, match="unknown plant 'nope'"):
        application(plant="nope")


@pytest.mark.parametrize("replay", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_robust_study_cancel_keeps_the_finished_samples(session, replay):
    """Cancel after the first chunk: the report says incomplete and its yields cover exactly
    the samples done, which are the first samples of the seeded stream (same as a run of that
    size)."""
    
    from prsa_ctrl.app.session import robust_study
    from prsa_ctrl.studies.montecarlo import run_monte_carlo

    s0 = session.default_settings()
    opt = session.tuned(s0)
    calls = []
    out = robust_study(session, s0, {"optimum": opt.pid}, 40, progress=lambda *a: calls.append(a),
                       cancelled=lambda: len(calls) >= 2)
    mc = out["monte_carlo"]
    assert calls[0] == ("robust tuning", 0, 40)
    assert calls[1][0] == "Monte Carlo"
    assert mc["complete"] is False
    assert mc["samples"] == 40
    assert 0 < mc["samples_done"] < 40
    assert [d["name"] for d in mc["designs"]] == ["optimum", "robust"]
    assert all(d["samples"] == mc["samples_done"] for d in mc["designs"])
    assert out["comparison"]["robust"]["max_ms"] <= s0.ms_max * (1 + 1e-3)  # robust holds Ms on every scenario
    assert out["comparison"]["optimum"]["max_ms"] > out["comparison"]["robust"]["max_ms"]
    if replay:  # the same samples as a fresh run of that size
        ref = run_monte_carlo(session.plant, session.scene_for(s0), {"optimum": opt.pid, "robust": PID(**out["robust"])},
                              n=mc["samples_done"], backend="serial", quiet=True)
        assert [d["passed"] for d in ref.as_dict()["designs"]] == [d["passed"] for d in mc["designs"]]


def test_show_in_a_notebook_serves_the_app_from_the_kernel():
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    nb = nbformat.v4.new_notebook()
    nb.cells = [nbformat.v4.new_code_cell("from prsa_ctrl.app import show\napp = show()\ntype(app).__name__")]
    nbclient.NotebookClient(nb, timeout=120, kernel_name="python3").execute()
    outs = nb.cells[0].outputs
    html_out = [o["data"]["text/html"] for o in outs if "text/html" in o.get("data", {})]
    assert len(html_out) == 1
    assert "/autoload.js?bokeh-autoload-element=" in html_out[0]
    assert outs[-1]["data"]["text/plain"] == "'Application'"


# ---- issue 31: no client text reaches the disk as a path -----------------------------------


def test_session_takes_only_builtin_names_or_its_own_uploads(tmp_path):
    """A valid plant or scene file elsewhere on the disk is refused before it is read (the
    page's selects send client text to set_plant/set_scene), with the same line as a path that
    does not exist; the session's plant and scene stay."""
    from prsa_ctrl.app.session import builtin_names, typed
    from prsa_ctrl.plant.plantfile import plant_file_path
    from prsa_ctrl.studies.scenefile import locate_scene

    (tmp_path / "other.toml").write_text(plant_file_path("iprsm-60").read_text())
    (tmp_path / "scene.toml").write_text(locate_scene("paper-table3")[0].read_text())
    s = AppSession()
    try:
        for what, call, arg in (("plant", s.set_plant, tmp_path / "other.toml"),
                                ("plant", s.set_plant, str(tmp_path / "other.toml")),
                                ("plant", s.set_plant, "/etc/passwd"),
                                ("plant", s.set_plant, str(tmp_path / "missing.toml")),
                                ("scene", s.set_scene, str(tmp_path / "scene.toml")),
                                ("scene", s.set_scene, "../tuning/paper-table3.toml"),
                                ("scene", s.set_scene, "/etc/passwd")):
            with pytest.raises(AppInputError) as info:
                call(arg)
            names = builtin_names()[what == "scene"]
            assert str(info.value) == (f"{what} {typed(str(arg))}: expected a built-in {what} ({', '.join(names)}) "
                                       f"or an uploaded {what} file")
        assert (s.plant_label, s.scene_label) == ("paper-iprsm", "paper-load-step")
        # built-in names still switch
        s.set_plant("iprsm-60")
        assert s.plant.name == load_plant("iprsm-60").name
    finally:
        s.close()


@pytest.mark.parametrize("trace", ["/etc/passwd", "../../../../etc/passwd", "trace.csv"])
@pytest.mark.parametrize("key", ["load_trace_csv", "setpoint_trace_csv"])
def test_uploaded_scene_naming_a_trace_is_refused_before_any_read(tmp_path, monkeypatch, trace, key):
    import prsa_ctrl.studies.dutyscene as scene_mod  # the CSV reader of the duty-cycle type
    from prsa_ctrl.app.session import builtin_names

    builtin_names()  # the page's built-in names (cached) read the built-in duty-trace.csv: before the reader is patched
    # a valid trace where a relative name would resolve: still refused, and never opened
    (tmp_path / "trace.csv").write_text("time_s,axial_load_n\n0,500\n1,500\n")
    monkeypatch.chdir(tmp_path)
    reads = []
    monkeypatch.setattr(scene_mod, "read_trace_csv", lambda *a, **k: reads.append(a) or (_ for _ in ()).throw(
        AssertionError("read")))
    s = AppSession()
    try:
        with pytest.raises(AppInputError) as info:
            s.upload("scene", "hostile.toml", f'[operating]\n{key} = "{trace}"\n'.encode())
        assert str(info.value) == (f"hostile.toml: operating.{key} = {trace!r}: an uploaded scene cannot read files "
                                   "on the server; expected a load-step scene without a CSV trace")
        assert reads == []
        assert s.scene_label == "paper-load-step"
    finally:
        s.close()


def test_uploaded_scene_without_a_trace_still_loads():
    from prsa_ctrl.studies.scenefile import locate_scene

    s = AppSession()
    try:
        s.upload("scene", "../../etc/table3.toml", locate_scene("paper-table3")[0].read_bytes())
        assert s.scene_label == "table3.toml"  # stored and named under its last part only
        assert s.base_scene.final_loads == load_scene("paper-table3").final_loads
    finally:
        s.close()


@pytest.mark.parametrize("sent, stored", [
    ("../../etc/x.toml", "x.toml"), ("..", "default.toml"), (".", "default.toml"), ("a\\b\\c.toml", "c.toml"),
    ("", "default.toml"), (None, "default.toml"), (".stdout", "default.toml"), ("\x1b]0;pwned\x07.toml", "default.toml"),
    ("x" * 201, "default.toml"), ("Messung-ü.csv", "Messung-ü.csv"), ("/abs/path/p.toml", "p.toml"),
])
def test_upload_name_is_never_a_path(sent, stored):
    from prsa_ctrl.app.session import upload_name

    assert upload_name(sent, "default.toml") == stored


@pytest.mark.parametrize("value, line", [
    ("not base64 ~~", "x.toml: the upload is not base64 text; expected the file's bytes as base64 (as a browser "
                      "sends a file)"),
    (["QUJD", "x"], None),  # the first of a list is taken
    (12, "x.toml: the upload holds a int; expected the file's bytes as base64 text (as a browser sends a file)"),
    ("A" * (4 * 3_333_334 + 4), "x.toml: 10.0 MB; expected a file of at most 10 MB (the app's upload limit)"),
])
def test_uploaded_file_checks_what_the_client_sent(value, line):
    from types import SimpleNamespace

    from prsa_ctrl.app.fitpanel import uploaded_file

    w = SimpleNamespace(value=value, filename="../x.toml")
    if line is None:
        assert uploaded_file(w, "d.toml") == ("x.toml", b"ABC")
    else:
        with pytest.raises(AppInputError) as info:
            uploaded_file(w, "d.toml")
        assert str(info.value) == line


def test_bode_axes_in_hz_by_default_rad_s_on_request():
    """Issue 33: the page's Bode and |S|, |T| axes in Hz (the sources keep rad/s as "w", the
    lines draw "f"), rad/s one click away; the generic tab alike."""
    import numpy as np
    from bokeh.document import Document

    from prsa_ctrl.app.genericpanel import GenericPanel
    from prsa_ctrl.app.page import AppPage

    page = AppPage(Document(), attach=False)
    try:
        figs = (page.mag, page.phase, page.st)
        assert page.axes.unit == "Hz"
        assert [f.xaxis[0].axis_label for f in figs] == ["frequency (Hz)"] * 3
        assert {r.glyph.x for f in figs for r in f.renderers if hasattr(r.glyph, "x")} == {"f"}
        w = np.geomspace(1, 1e4, 7)
        page.freq["opt"].data = page.axes.data({"w": w, "db": w, "deg": w, "s": w, "t": w})
        np.testing.assert_allclose(page.freq["opt"].data["f"], w / (2 * np.pi), rtol=1e-15)
        page.freq_unit.active = 1  # rad/s
        assert page.axes.unit == "rad/s"
        assert page.mag.xaxis[0].axis_label == "frequency (rad/s)"
        np.testing.assert_array_equal(page.freq["opt"].data["f"], w)
        np.testing.assert_array_equal(page.freq["opt"].data["w"], w)  # SI kept
    finally:
        page.close(wait=True)
    g = GenericPanel(Document())
    try:
        assert g.axes.unit == "Hz"
        assert g.noise_fig.xaxis[0].axis_label == "frequency (Hz)"
        assert {r.glyph.x for r in g.mag.renderers} == {"f"}
        g.freq_unit.active = 1
        assert g.noise_fig.xaxis[0].axis_label == "frequency (rad/s)"
    finally:
        g.close()


def test_an_uploaded_scene_sets_every_widget_and_the_select_names_it():
    """Issue 33 (newcomer): after an upload the scene select shows the uploaded file (was: the
    last built-in name) and the fidelity and Mt widgets show the uploaded scene's values (was:
    the fidelity widget kept its value and overrode the scene's); choosing a built-in again
    drops the upload from the list."""
    from bokeh.document import Document

    from prsa_ctrl.app.page import AppPage
    from prsa_ctrl.studies.scenefile import locate_scene

    text = locate_scene("paper-load-step")[0].read_text(encoding="utf-8")
    text = text.replace('fidelity = "auto"', 'fidelity = "rigid"').replace("ms_max = 1.4", "ms_max = 1.4\nmt_max = 1.25")
    assert 'fidelity = "rigid"' in text
    assert "mt_max = 1.25" in text
    page = AppPage(Document(), attach=False)
    try:
        assert page.fidelity.value == "auto"
        assert page.mt_on.active == []
        page.after_switch("scene", page.session.upload("scene", "my-step.toml", text.encode("utf-8")))
        assert page.scene_select.value == "file: my-step.toml"
        assert page.scene_select.options[-1] == "file: my-step.toml"
        assert page.session.scene_label == "my-step.toml"  # the display did not switch the scene back
        assert page.fidelity.value == "rigid"
        assert page._read().fidelity == "rigid"  # what the next tune runs with
        assert page.mt_on.active == [0]
        assert page.mt.value == 1.25
        assert page._read().mt_max == 1.25
        page.scene_select.value = "paper-load-step"  # the user picks a built-in again
        assert page.session.scene_label == "paper-load-step"
        assert page.fidelity.value == "auto"
        assert "file: my-step.toml" not in page.scene_select.options
        page.scene_select.value = "file: nothing.toml"  # a client's text outside the list
        assert page.scene_select.value == "paper-load-step"
        assert "expected one of the built-in scenes" in page.error.text
    finally:
        page._destroyed(None)
