"""prsa-app in a real browser: Playwright drives Debian's Chromium against a served app.

The app runs as ``python -m prsa_ctrl.app.cli --no-browser`` (free port, printed) in a
subprocess; each test drives the page as a person would and checks what it shows against an
independent computation. Without Chromium or Playwright the tests skip with one line, except
under ``CI=true`` where they fail. ``PRSA_APP_SCREENSHOTS=1`` saves the main views to
``docs/app/*.png``. Waits are Playwright timeouts; nothing reads the clock.
"""

from __future__ import annotations

import json
import math
import os
import queue
import subprocess
import sys
import threading
import tomllib
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("bokeh", reason="prsa-app tests need the app extra (pip install '.[app]')")

from prsa_ctrl import PID, load_plant, load_scene  # noqa: E402

SHOTS = Path(__file__).resolve().parents[2] / "docs" / "app"


def _text(pg, key: str) -> str:
    return pg.locator(f'[data-k="{key}"]').inner_text().strip()


def _shot(pg, name: str) -> None:
    if os.environ.get("PRSA_APP_SCREENSHOTS"):
        SHOTS.mkdir(parents=True, exist_ok=True)
        pg.screenshot(path=str(SHOTS / name), full_page=True)


def _tuned(ms_max: float):
    """The toolkit's own answer, computed afresh (a new Tuner, not the app's)."""
    from prsa_ctrl.studies.autotune import actuator_loops
    from prsa_ctrl.tuning.generic import tune_loops

    plant, scene = load_plant(), load_scene()
    return tune_loops(actuator_loops(plant, scene), objective=scene.objective, controller=scene.controller,
                      ms_max=ms_max)


def _independent_margins(kp: float, ki: float) -> dict:
    """Ms, Mt, GM and PM of the sampled speed loop built in python-control from the plant's
    continuous linearisation: ZOH plant to the nut angle, encoder backward difference through
    the first-order speed filter, the PI's per-sample law, one sample of computation delay.
    Margins from the loop's own frequency response on a dense grid up to Nyquist."""
    import control

    plant, scene = load_plant(), load_scene()
    ts = plant.sample_time_s
    mid = 0.5 * (scene.initial_load + scene.final_loads[0])
    from prsa_ctrl import linearize

    lin = linearize(plant, omega_nut=scene.setpoint_rad_s, load=mid, fidelity="compliant", sampled=False)
    pw = lin[lin.output_labels.index("nut_speed"), 0]
    pz = control.c2d(control.ss(pw) * control.tf([1.0], [1.0, 0.0]), ts, "zoh")
    a = math.exp(-ts / plant.speed_filter_s)
    speed = control.tf([(1 - a) / ts, -(1 - a) / ts], [1.0, -a], ts)
    delay = control.tf([1.0], [1.0, 0.0], ts)
    loop = PID(kp, ki).to_tf(dt=ts) * delay * speed * pz
    w = np.logspace(-2, math.log10(math.pi / ts), 400_001)
    L = np.squeeze(loop(np.exp(1j * w * ts)))
    mag, ph = np.abs(L), np.unwrap(np.angle(L))
    cross = np.flatnonzero(np.diff(np.sign(mag - 1.0)))
    pm = min(180.0 + math.degrees(ph[i] + (ph[i + 1] - ph[i]) * (1 - mag[i]) / (mag[i + 1] - mag[i]))
             for i in cross)
    turn = np.flatnonzero(np.diff(np.sign(np.degrees(ph) + 180.0)))
    gm = min(-20 * math.log10(mag[i]) for i in turn) if turn.size else math.inf
    return {"ms": float(np.max(1 / np.abs(1 + L))), "mt": float(np.max(np.abs(L / (1 + L)))), "gm": gm, "pm": pm}


def test_ms_slider_retunes_to_the_tuners_result(app_page):
    page = app_page
    r0 = _tuned(1.4)
    assert _text(page, "opt-kp") == f"{r0.pid.kp:.6g}"
    assert _text(page, "opt-ms") == f"{r0.ms:.4f}"
    _shot(page, "app-main.png")
    handle = page.locator(".prsa-ms .noUi-handle")
    handle.focus()
    page.keyboard.press("ArrowRight")  # one step of 0.05
    page.locator('[data-k="bound-ms"]', has_text="1.45").wait_for()
    r1 = _tuned(1.45)
    assert (_text(page, "opt-kp"), _text(page, "opt-ki")) == (f"{r1.pid.kp:.6g}", f"{r1.pid.ki:.6g}")
    assert _text(page, "opt-ms") == f"{r1.ms:.4f}"
    assert r1.pid.kp > r0.pid.kp  # the looser bound really changed the design
    assert _text(page, "opt-status") == r1.status


def test_landscape_click_shows_the_manual_designs_true_margins(app_page):
    page = app_page
    box = page.locator(".prsa-landscape").bounding_box()
    page.mouse.click(box["x"] + 0.55 * box["width"], box["y"] + 0.45 * box["height"])
    page.locator('[data-k="man-ms"]').wait_for()
    kp, ki = float(_text(page, "man-kp")), float(_text(page, "man-ki"))
    ref = _independent_margins(kp, ki)
    assert float(_text(page, "man-ms")) == pytest.approx(ref["ms"], abs=2e-4)
    assert float(_text(page, "man-mt")) == pytest.approx(ref["mt"], abs=2e-4)
    assert float(_text(page, "man-gm")) == pytest.approx(ref["gm"], abs=0.02)
    assert float(_text(page, "man-pm")) == pytest.approx(ref["pm"], abs=0.05)
    # the optimum stays beside it
    assert _text(page, "opt-kp") == f"{_tuned(1.4).pid.kp:.6g}"
    _shot(page, "app-manual.png")


def test_verification_overlays_the_prediction_with_health(app_page):
    page = app_page
    from prsa_ctrl.studies.autotune import Design, verify

    page.locator(".prsa-verify button").click()
    page.locator('[data-k="progress"][data-state="done"]').wait_for()
    r = _tuned(1.4)
    d = verify(Design("check", r.pid, r.margins[0]), load_plant(), load_scene())
    assert _text(page, "opt-ver") == f"{d.objective_verified:.5g}"
    assert _text(page, "opt-vdrop") == f"{d.verified[0].peak_drop_rad_s:.4g}"
    assert _text(page, "opt-flags") == "healthy"
    _shot(page, "app-verified.png")


def test_bad_plant_upload_shows_the_clis_one_line(shared_app_page, tmp_path, monkeypatch, capsys):
    page = shared_app_page
    from prsa_ctrl.cli.tune import main as tune_main

    from prsa_ctrl.plant.plantfile import plant_file_path

    text = plant_file_path("paper-iprsm").read_text()
    bad = text.replace("inertia_kg_m2 = { value = 2.0e-4", "inertia_kg_m2 = { value = 2.0e+4", 1)
    assert bad != text
    (tmp_path / "my-actuator.toml").write_text(bad)
    monkeypatch.chdir(tmp_path)
    assert tune_main(["--plant", "my-actuator.toml"]) == 2
    cli_line = capsys.readouterr().err.strip()
    assert cli_line.startswith("prsa-tune: error: my-actuator.toml")
    page.locator(".prsa-plant-upload input[type=file]").set_input_files(
        files=[{"name": "my-actuator.toml", "mimeType": "application/toml", "buffer": bad.encode()}])
    line = cli_line.removeprefix("prsa-tune: ")
    page.locator('[data-k="error"]', has_text=line).wait_for()  # (the shared page: this upload's line)
    assert _text(page, "error") == line
    _shot(page, "app-bad-upload.png")


def test_export_downloads_load_with_the_toolkits_readers(shared_app_page):
    page = shared_app_page
    from prsa_ctrl.io.export import dumps, export_controller

    r = _tuned(1.4)
    with page.expect_download() as info:
        page.locator(".prsa-dl-drive button").click()
    drive = tomllib.loads(Path(info.value.path()).read_text())
    assert info.value.suggested_filename == "speed-controller.toml"
    assert drive == tomllib.loads(dumps(export_controller(r.pid, load_plant(), fmt="toml"), "toml"))
    with page.expect_download() as info:
        page.locator(".prsa-dl-report button").click()
    report = json.loads(Path(info.value.path()).read_text())
    assert report["design"]["gains"]["kp"] == r.pid.kp
    assert report["design"]["gains"]["ki"] == r.pid.ki
    assert report["design"]["margins"]["ms"] == pytest.approx(r.ms, rel=1e-12)


def test_copy_as_code_runs_to_the_shown_gains(shared_app_page):
    page = shared_app_page
    code = _text(page, "code-py")
    cli = _text(page, "code-cli")
    assert cli.startswith("prsa-tune --plant paper-iprsm --scene paper-load-step --load-step 500:1500")
    assert "--ms-max 1.4" in cli
    ns: dict = {}
    exec(compile(code.replace("print(", "(lambda *a: None)("), "<copied>", "exec"), ns)
    assert f"{ns['result'].pid.kp:.6g}" == _text(page, "opt-kp")


@pytest.mark.slow  # robust tuning + Monte Carlo, ~20 s
def test_robust_and_monte_carlo_with_progress_and_cancel(app_page):
    page = app_page
    page.locator(".prsa-samples input").fill("40")
    page.locator(".prsa-samples input").press("Enter")
    page.locator(".prsa-robust button").click()
    page.locator("[data-k='rprogress'][data-stage='Monte Carlo']").wait_for()
    page.locator(".prsa-robust-cancel button").click()
    page.locator("[data-k='rprogress'][data-state='cancelled']").wait_for()
    done = int(page.locator("[data-k='rprogress']").get_attribute("data-done"))
    assert 0 < done < 40
    passed, samples = _text(page, "mc-optimum-yield").split("/")
    assert int(samples) == done
    assert 0 <= int(passed) <= done
    assert float(_text(page, "mc-robust-maxms")) <= 1.4 * (1 + 1e-3)
    _shot(page, "app-robust.png")


# ---- issue 31: the page's own BokehJS model cannot make the server read a file -------------

_SET_SELECT_JS = """([title, value]) => {
    const doc = Bokeh.documents[0];
    const models = doc._all_models ? [...doc._all_models.values()] : [...doc.all_models];
    const sel = models.find(m => m.type == "Select" && m.title == title);
    sel.value = value;
    return sel.options.length;
}"""


def typed(value) -> str:
    """A value as the page's messages quote it: its repr, cut to 200 characters."""
    text = repr(value)
    return text if len(text) <= 200 else text[:197] + "..."


@pytest.mark.parametrize("title, kind", [("Plant (built-in)", "plant"), ("Scene (built-in)", "scene")])
def test_select_set_to_a_server_path_is_refused_and_reverts(shared_app_page, tmp_path, title, kind):
    """A client that sets a select's value to a path (here a valid plant or scene file, so a
    server that read it would switch to it) gets one line and the select back; the page keeps
    its plant and design."""
    from prsa_ctrl.app.session import builtin_names
    from prsa_ctrl.plant.plantfile import plant_file_path
    from prsa_ctrl.studies.scenefile import locate_scene

    page = shared_app_page
    kp = _text(page, "opt-kp")
    src = plant_file_path("iprsm-60") if kind == "plant" else locate_scene("paper-table3")[0]
    path = tmp_path / f"elsewhere-{kind}.toml"
    path.write_text(src.read_text())
    for value in (str(path), "/etc/passwd"):
        page.evaluate(_SET_SELECT_JS, [title, value])
        names = builtin_names()[kind == "scene"]
        line = f"error: {kind} select value {typed(value)}: expected one of the built-in {kind}s ({', '.join(names)})"
        page.locator('[data-k="error"]', has_text=line).wait_for()  # (the shared page: this value's line)
        assert _text(page, "error") == line
        page.wait_for_function("([t, v]) => { const d = Bokeh.documents[0]; const ms = d._all_models ? "
                               "[...d._all_models.values()] : [...d.all_models]; return ms.find(m => m.type == "
                               "'Select' && m.title == t).value == v; }",
                               arg=[title, "paper-iprsm" if kind == "plant" else "paper-load-step"])
    assert "root:" not in page.content()
    assert _text(page, "opt-kp") == kp
    assert f"Plant <b>paper-iprsm</b>, scene <b>paper-load-step</b>" in page.locator('[data-k="bounds"]').inner_html()


@pytest.mark.parametrize("trace", ["/etc/passwd", "../../../../../../etc/passwd"])
def test_uploaded_scene_with_a_server_trace_is_refused_on_the_page(shared_app_page, trace):
    page = shared_app_page
    text = f'[operating]\nload_trace_csv = "{trace}"\n'
    page.locator(".prsa-scene-upload input[type=file]").set_input_files(
        files=[{"name": "hostile.toml", "mimeType": "application/toml", "buffer": text.encode()}])
    line = (f"error: hostile.toml: operating.load_trace_csv = {trace!r}: an uploaded scene "
            "cannot read files on the server; expected a load-step scene without a CSV trace")
    page.locator('[data-k="error"]', has_text=line).wait_for()  # (the shared page: this upload's line)
    assert _text(page, "error") == line
    assert "root:" not in page.content()


# ---- issue 31: uploads the page cannot take get one line; SIGTERM stops like Ctrl-C --------

_SET_UPLOAD_JS = """([cls, value, name]) => {
    const doc = Bokeh.documents[0];
    const models = doc._all_models ? [...doc._all_models.values()] : [...doc.all_models];
    const fi = models.find(m => m.type == "FileInput" && m.css_classes.includes(cls));
    fi.setv({value: value, filename: name, mime_type: "text/plain"});
}"""


@pytest.mark.parametrize("cls, name", [("prsa-plant-upload", "p.toml"), ("prsa-scene-upload", "s.toml"),
                                       ("prsa-log-upload", "log.csv")])
def test_upload_that_is_not_base64_is_one_line_on_the_page(shared_app_page, cls, name):
    page = shared_app_page
    page.evaluate(_SET_UPLOAD_JS, [cls, "this is not base64 ~~~", name])
    line = f"error: {name}: the upload is not base64 text; expected the file's bytes as base64 (as a browser sends a file)"
    page.locator('[data-k="error"]', has_text=line).wait_for()  # (the shared page: this upload's line)
    assert _text(page, "error") == line
    assert page.locator('[data-k="opt-ms"]').count() == 1


@pytest.mark.parametrize("megabytes", [12, 25])  # above the app's limit; above Bokeh's 20 MB message limit
def test_upload_above_the_limit_is_one_line_and_sends_nothing(shared_app_page, megabytes):
    """On the module's shared page (the refused uploads change neither the plant nor the design);
    the later small upload's name and bytes are this case's own, so that the page reads an
    upload it has not read before (a refused 25 MB file never reaches the server: the same small
    file as the 12 MB case's would leave the server's upload value unchanged)."""
    page = shared_app_page
    kp = _text(page, "opt-kp")
    page.locator(".prsa-plant-upload input[type=file]").set_input_files(
        files=[{"name": "big.toml", "mimeType": "application/toml", "buffer": b"#" * (megabytes * 1_000_000)}])
    line = f"error: big.toml: {megabytes:.1f} MB; expected a file of at most 10 MB (the app's upload limit)"
    page.locator('[data-k="error"]', has_text=line).wait_for()  # (the shared page: this upload's line)
    assert _text(page, "error") == line
    assert page.evaluate("() => Bokeh.documents.length") == 1  # the connection held: no second document
    # the page still answers: a later small upload is read
    small = f"small-{megabytes}.toml"
    page.locator(".prsa-plant-upload input[type=file]").set_input_files(
        files=[{"name": small, "mimeType": "application/toml", "buffer": f"[nut{megabytes}\n".encode()}])
    page.locator('[data-k="error"]', has_text=f"{small}: invalid TOML").wait_for()
    assert _text(page, "opt-kp") == kp


def test_sigterm_stops_like_ctrl_c_and_removes_the_uploads(open_page, tmp_path):
    """SIGTERM: exit 0, one line, the uploaded files' temporary folder gone (today's main dies
    by the signal and leaves it)."""
    import signal

    from prsa_ctrl.plant.plantfile import plant_file_path

    tmp = tmp_path / "tmp"
    tmp.mkdir()
    proc = subprocess.Popen([sys.executable, "-m", "prsa_ctrl.app.cli", "--no-browser"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=str(tmp_path), env={**os.environ, "TMPDIR": str(tmp)})
    try:
        lines: queue.Queue = queue.Queue()
        threading.Thread(target=lambda: lines.put(proc.stdout.readline()), daemon=True).start()
        url = lines.get(timeout=120).split()[2]
        ctx, pg = open_page(url)
        pg.locator('[data-k="opt-ms"]').wait_for()
        pg.locator(".prsa-plant-upload input[type=file]").set_input_files(
            files=[{"name": "copy.toml", "mimeType": "application/toml",
                    "buffer": plant_file_path("iprsm-60").read_bytes()}])
        pg.locator('[data-k="bounds"]', has_text="copy.toml").wait_for()
        assert [p.name for p in tmp.iterdir() if p.name.startswith("prsa-app-")], "no upload folder to remove"
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
        ctx.close()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert err.strip().splitlines()[-1] == "prsa-app: stopped (SIGTERM)", err
    assert [p.name for p in tmp.iterdir() if p.name.startswith("prsa-app-")] == []


def _browser_source(pg, name):
    """A Bokeh data source's columns as the browser holds them (typed arrays to lists)."""
    return pg.evaluate("(name) => { const d = Bokeh.documents[0].get_model_by_name(name).data; const o = {};"
                       " for (const [k, v] of (d instanceof Map ? d.entries() : Object.entries(d)))"
                       " o[k] = Array.from(v, (x) => (Array.isArray(x) || ArrayBuffer.isView(x)) ? Array.from(x) : x);"
                       " return o; }", name)


def test_bode_axes_in_hz_with_rad_s_on_request(shared_app_page):
    """Issue 33: the optimum's Bode data in the browser are drawn against Hz (w / 2 pi of the
    rad/s the page computed), and against rad/s after one click."""
    page = shared_app_page
    d = _browser_source(page, "prsa-freq-opt")
    w, f = np.asarray(d["w"], float), np.asarray(d["f"], float)
    assert w.size > 10
    np.testing.assert_allclose(f, w / (2 * math.pi), rtol=1e-12)
    page.locator(".prsa-freq-unit button", has_text="rad/s").click()
    page.wait_for_function("() => { const d = Bokeh.documents[0].get_model_by_name('prsa-freq-opt').data;"
                           " const g = (k) => d instanceof Map ? d.get(k) : d[k]; return g('f')[1] == g('w')[1]; }")
    d = _browser_source(page, "prsa-freq-opt")
    np.testing.assert_array_equal(np.asarray(d["f"], float), np.asarray(d["w"], float))
