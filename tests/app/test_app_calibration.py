"""prsa-app: calibration from an uploaded drive log (the ``prsa-fit`` path), in a real browser
and through the session.

The log is simulated here with a known truth (:func:`prsa_ctrl.identification.synthetic.fit_record`,
seeded, 1 s at 4 kHz); the page's fitted values are checked against a fit run in the test
(:func:`prsa_ctrl.identification.timedomain.fit_plant` on the same file) and against the truth,
the re-tuned gains against a fresh tuning of the fitted plant, and a bad log's message against
the ``prsa-fit`` command's own line.
"""

from __future__ import annotations

import pytest

pytest.importorskip("bokeh", reason="prsa-app tests need the app extra (pip install '.[app]')")

from prsa_ctrl import load_plant, load_scene  # noqa: E402
from test_app_browser import _shot, _text, _tuned, app_browser, app_page, app_url  # noqa: E402,F401

BAD_LOG = "time_s,torque_command_n_m\n0,0.1\n0.00025,0.1\n0.0005,0.1\n"


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    """A 1 s drive log of the perturbed plant (seeded) and the fit of the toolkit on it."""
    import warnings

    from prsa_ctrl.identification.data import load_record
    from prsa_ctrl.identification.synthetic import fit_record
    from prsa_ctrl.identification.timedomain import fit_plant

    rec, truth = fit_record(1.0, seed=1)
    path = tmp_path_factory.mktemp("log") / "axis-log.csv"
    rec.to_csv(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = fit_plant([load_record(path)], load_plant())
    return path, truth, res


def _tuned_on(plant, ms_max=1.4):
    from prsa_ctrl.studies.autotune import actuator_loops
    from prsa_ctrl.tuning.generic import tune_loops

    scene = load_scene()
    return tune_loops(actuator_loops(plant, scene), objective=scene.objective, controller=scene.controller,
                      ms_max=ms_max)


def _cli_line(tmp_path, monkeypatch, capsys, name: str, text: str) -> str:
    from prsa_ctrl.cli.fit import main as fit_main

    (tmp_path / name).write_text(text)
    monkeypatch.chdir(tmp_path)
    assert fit_main([name, "--out", "fitted.toml"]) == 2
    line = capsys.readouterr().err.strip().splitlines()[0]
    assert line.startswith(f"prsa-fit: error: {name}")
    return line


def test_uploaded_log_fits_and_the_fitted_plant_is_tuned_on_confirmation(app_page, log):
    page = app_page
    path, truth, res = log
    r0 = _tuned(1.4)
    assert _text(page, "opt-kp") == f"{r0.pid.kp:.6g}"
    page.locator(".prsa-log-upload input[type=file]").set_input_files(str(path))
    page.locator("[data-k='fit-state'][data-state='running']").wait_for()
    page.locator("[data-k='fit-state'][data-state='done']").wait_for()
    for key, v in res.parameters.items():
        assert _text(page, f"fit-{key}-value") == f"{v['value']:.6g}"
        lo, hi = v["ci95"]
        assert _text(page, f"fit-{key}-ci") == f"{lo:.6g} .. {hi:.6g}"
        assert abs(v["value"] / truth.values[key] - 1) < 1e-3  # the truth is found
    assert [w.replace("warning: ", "", 1) for w in page.locator("[data-k='fit-warning']").all_inner_texts()] \
        == list(res.warnings)
    assert _text(page, "opt-kp") == f"{r0.pid.kp:.6g}"  # not used before the confirmation
    _shot(page, "app-calibration.png")
    page.locator(".prsa-fit-use button").click()
    page.locator("[data-k='fit-state'][data-state='used']").wait_for()
    page.locator('[data-k="status"][data-landscape]').wait_for()
    r1 = _tuned_on(res.plant)
    assert (_text(page, "opt-kp"), _text(page, "opt-ki")) == (f"{r1.pid.kp:.6g}", f"{r1.pid.ki:.6g}")
    assert _text(page, "opt-ms") == f"{r1.ms:.4f}"
    assert f"{r1.pid.kp:.6g}" != f"{r0.pid.kp:.6g}"  # the fitted plant really changed the design
    assert "axis-log-fitted.toml" in page.locator("[data-k='bounds']").inner_text()


def test_bad_log_shows_prsa_fits_one_line(app_page, tmp_path, monkeypatch, capsys):
    page = app_page
    cli = _cli_line(tmp_path, monkeypatch, capsys, "bad-log.csv", BAD_LOG)
    page.locator(".prsa-log-upload input[type=file]").set_input_files(
        files=[{"name": "bad-log.csv", "mimeType": "text/csv", "buffer": BAD_LOG.encode()}])
    page.locator("[data-k='fit-state'][data-state='failed']").wait_for()
    assert _text(page, "error") == cli.removeprefix("prsa-fit: ")
    assert "Traceback" not in page.content()
    r0 = _tuned(1.4)
    assert _text(page, "opt-kp") == f"{r0.pid.kp:.6g}"  # the plant is unchanged
    _shot(page, "app-calibration-bad-log.png")


# ---- the session, without a browser ---------------------------------------------------------


def test_session_calibrate_is_prsa_fit_and_use_retunes(log):
    import tomllib

    from prsa_ctrl.app.session import AppSession

    path, truth, res = log
    s = AppSession()
    try:
        cal = s.calibrate("axis-log.csv", path.read_bytes())
        assert s.plant.name == "paper-iprsm"  # nothing changes before use_calibration
        assert cal.file_name == "axis-log-fitted.toml" and cal.base_label == "paper-iprsm"
        for key, v in res.parameters.items():
            assert cal.report["parameters"][key]["value"] == pytest.approx(v["value"], rel=1e-9)
            assert cal.report["parameters"][key]["ci95"] == pytest.approx(v["ci95"], rel=1e-9)
        assert cal.report["warnings"] == list(res.warnings)
        assert list(cal.report["fit_percent"]) == ["axis-log.csv"]  # named as uploaded
        assert any(line.startswith("fit ") and line.endswith(" % on axis-log.csv") for line in cal.lines)
        # the written file: prsa-fit's (its name from --out, the log named as uploaded), the fitted values
        doc = tomllib.loads(cal.plant_text)
        assert doc["name"] == "axis-log-fitted" and "prsa-app-" not in cal.plant_text
        assert "calibrated by prsa-fit from axis-log.csv" in doc["description"]
        for key in res.plant_keys:
            section, sub = key.split(".")
            assert doc[section][sub]["value"] == pytest.approx(res.plant.values[key], rel=1e-9)
        notes = s.use_calibration(cal)
        assert all("prsa-app-" not in n for n in notes)  # notes name the file, not the temp folder
        assert s.plant_label == "axis-log-fitted.toml"
        st = s.default_settings()
        v = s.tuned(st)
        ref = _tuned_on(res.plant)
        assert v.pid.kp == pytest.approx(ref.pid.kp, rel=1e-9) and v.pid.ki == pytest.approx(ref.pid.ki, rel=1e-9)
        cli, _ = s.code(st)
        assert "--plant axis-log-fitted.toml" in cli
    finally:
        s.close()


def test_session_bad_log_is_the_clis_line(tmp_path, monkeypatch, capsys):
    from prsa_ctrl.app.session import AppInputError, AppSession

    cli = _cli_line(tmp_path, monkeypatch, capsys, "bad-log.csv", BAD_LOG)
    s = AppSession()
    try:
        with pytest.raises(AppInputError) as info:
            s.calibrate("bad-log.csv", BAD_LOG.encode())
        assert "error: " + str(info.value) == cli.removeprefix("prsa-fit: ")
        with pytest.raises(AppInputError, match=r"^'my-log.mat': a MATLAB .mat log"):
            s.calibrate("my-log.mat", b"\x00\x01")
        with pytest.raises(AppInputError, match=r"^-bad.csv: missing column"):  # a name like a flag
            s.calibrate("-bad.csv", BAD_LOG.encode())
        assert s.plant.name == "paper-iprsm"
    finally:
        s.close()


def test_session_calibration_cancel_ends_the_command(log):
    from prsa_ctrl.app.session import AppSession, Cancelled

    path = log[0]
    s = AppSession()
    try:
        polls = []
        with pytest.raises(Cancelled):
            s.calibrate("axis-log.csv", path.read_bytes(), cancelled=lambda: polls.append(1) or len(polls) >= 2)
        assert len(polls) == 2 and s.plant.name == "paper-iprsm"
    finally:
        s.close()


def test_session_calibrate_is_the_commands_output(log, tmp_path, monkeypatch, capsys):
    """The library call the app makes gives prsa-fit's lines, JSON report and plant file, byte for byte."""
    import json
    import shutil

    from prsa_ctrl.app.session import AppSession
    from prsa_ctrl.cli.fit import main as fit_main

    path = log[0]
    shutil.copy(path, tmp_path / "axis-log.csv")
    monkeypatch.chdir(tmp_path)
    assert fit_main(["axis-log.csv", "--out", "axis-log-fitted.toml", "--json", "axis-log-fit.json"]) == 0
    out = capsys.readouterr().out
    s = AppSession()
    try:
        cal = s.calibrate("axis-log.csv", path.read_bytes())
        text = cal.plant_text  # (in the session's folder, removed by close)
    finally:
        s.close()
    shown = [" ".join(line.split()) for line in out.splitlines() if line.strip() and not line.startswith("wrote ")]
    assert list(cal.lines) == shown
    assert cal.report == json.loads((tmp_path / "axis-log-fit.json").read_text())
    assert text == (tmp_path / "axis-log-fitted.toml").read_text()


def test_session_calibrate_starts_no_process_and_imports_no_cli(log):
    """A run-time trace in a fresh interpreter: the calibration imports no prsa_ctrl.cli module and
    starts no process (subprocess, multiprocessing, os.fork are made to fail)."""
    import os
    import subprocess
    import sys

    code = f"""
import os, subprocess, sys, multiprocessing
def refuse(*a, **k):
    raise AssertionError("a process was started")
subprocess.Popen.__init__ = refuse
os.fork = os.posix_spawn = os.system = refuse
multiprocessing.Process.start = refuse
from pathlib import Path
from prsa_ctrl.app.session import AppSession
s = AppSession()
try:
    cal = s.calibrate("axis-log.csv", Path({str(log[0])!r}).read_bytes())
    assert cal.file_name == "axis-log-fitted.toml" and cal.plant_text
finally:
    s.close()
cli = sorted(m for m in sys.modules if m == "prsa_ctrl.cli" or m.startswith("prsa_ctrl.cli."))
print("cli modules:", cli)
assert not cli, cli
"""
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "cli modules: []" in proc.stdout
