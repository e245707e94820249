"""prsa-app: calibration from an uploaded drive log (the ``prsa-fit`` path), in a real browser
and through the session.

The log is simulated here with a known truth (:func:`prsa_ctrl.identification.synthetic.fit_record`,
seeded, 1 s at 4 kHz); the page's fitted values are checked against a fit run in the test
(:func:`prsa_ctrl.identification.timedomain.fit_plant` on the same file) and against the truth,
the re-tuned gains against a fresh tuning of the fitted plant, and a bad log's message against
the ``prsa-fit`` command's own line. The calibration tab's views (replay, frequency response in
Hz, residuals) are checked against :func:`prsa_ctrl.plots.fit.fit_views` of the test's own fit;
a log with a 105 Hz oscillation the rigid model lacks (a second mass seen by the encoder) is
refused with prsa-fit's diagnosis, and shown as refused.
"""

from __future__ import annotations

import pytest

pytest.importorskip("bokeh", reason="prsa-app tests need the app extra (pip install '.[app]')")

from prsa_ctrl import load_plant, load_scene  # noqa: E402
from test_app_browser import _shot, _text, _tuned  # noqa: E402

BAD_LOG = "time_s,torque_command_n_m\n0,0.1\n0.00025,0.1\n0.0005,0.1\n"
CAL_TAB = "Calibration (fit a drive log)"
ACT_TAB = "Actuator (plant and scene files)"


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


@pytest.fixture(scope="module")
def resonant_log(tmp_path_factory):
    """The first half second of the simulated log (``fit_record(0.5, seed=1)``) with a 105 Hz,
    15 rad/s oscillation in the measured angle: the rigid fit converges and its plant does not
    explain the log (prsa-fit exits 3, no plant file; the same half second without the oscillation
    is validated, exit 0). Half a second: the delay search's five rigid fits of a log they cannot
    explain cost 7 s of CPU here against 19 s on the 1 s log, once in prsa-fit, once in the
    session and once in the served app."""
    import math
    import warnings

    import numpy as np

    from prsa_ctrl.identification.data import record_from_arrays
    from prsa_ctrl.identification.synthetic import fit_record

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec, _ = fit_record(0.5, seed=1)
    w = 2 * math.pi * 105.0
    bad = record_from_arrays("resonant", rec.time_s, rec.torque_command_n_m,
                             nut_angle_rad=rec.nut_angle_rad + 15.0 / w * np.sin(w * rec.time_s),
                             axial_load_n=rec.axial_load_n)
    path = tmp_path_factory.mktemp("log") / "resonant-log.csv"
    bad.to_csv(path)
    return path


#: The fits made by ``shared_fits`` in this module, by their arguments (pickled).
_FITS: dict = {}


@pytest.fixture
def shared_fits(monkeypatch):
    """``prsa_ctrl.identification.timedomain.fit_plant`` made once per module for each value of its
    arguments (bound to its signature with the defaults, sequences as tuples, a rigid fit's
    ``segment_s=None`` as the :data:`~prsa_ctrl.identification.timedomain.SEGMENT_S` it means,
    compared by their pickled bytes; ``check_interrupt`` aside: the tests that use this fixture
    never cancel), for the tests where prsa-fit and the session fit the resonant log (its refusal
    costs about 7 s of CPU per fit; the served app's fit, in its own process, is not shared; the
    test of the session's output against the command's, byte for byte, fits twice): a call after
    the first gets a deep copy of the first call's result, the rest of the command or the session runs as it is. A call with
    other arguments fits afresh, so a test comparing two paths still sees a difference in what they
    ask of the fit. The fit's warnings (recorded in this thread,
    :func:`prsa_ctrl.app.session.thread_warnings`) are said again at every call, where the caller's
    filters or recorder take them. Returns the list of calls, ``True`` for each shared one."""
    import copy
    import inspect
    import pickle
    import warnings

    import prsa_ctrl.identification.timedomain as timedomain
    from prsa_ctrl.app.session import thread_warnings

    real = timedomain.fit_plant
    signature = inspect.signature(real)
    calls: list = []

    def shared(*args, **kwargs):
        bound = signature.bind(*args, **kwargs)
        bound.apply_defaults()
        given = {k: tuple(v) if isinstance(v, (list, tuple)) else v for k, v in bound.arguments.items()
                 if k != "check_interrupt"}
        if given["segment_s"] is None and given["fidelity"] == "rigid":  # prsa-fit's default: the library's
            given["segment_s"] = timedomain.SEGMENT_S
        key = pickle.dumps(sorted(given.items()))
        calls.append(key in _FITS)
        if key not in _FITS:
            with thread_warnings() as caught:  # every warning of this fit (its trial plants' geometry notes)
                _FITS[key] = real(*args, **kwargs), [w.message for w in caught]
        result, said = _FITS[key]
        for message in said:  # said again, here, at every call: the caller's filters or recorder take them
            warnings.warn(message, stacklevel=2)
        return copy.deepcopy(result)

    monkeypatch.setattr(timedomain, "fit_plant", shared)
    return calls


@pytest.fixture(scope="module")
def fitted_page(module_open_page, app_url, log):
    """One page of the served app with the module's log uploaded in the calibration tab and its
    fit done (running, then done), nothing used yet: shared by the test of the fit's values and
    its use and the test of its views, which made the same upload and the same fit on a page
    each. The views are read in either order (the use changes neither them nor their data)."""
    _, page = module_open_page(app_url, accept_downloads=True)
    page.locator('[data-k="opt-ms"]').wait_for()
    page.locator('[data-k="status"]').wait_for()
    page.get_by_text(CAL_TAB).click()
    page.locator(".prsa-log-upload input[type=file]").set_input_files(str(log[0]))
    page.locator("[data-k='fit-state'][data-state='running']").wait_for()
    page.locator("[data-k='fit-state'][data-state='done']").wait_for()
    return page


def _views_of(res, path):
    """What the tab must show: :func:`prsa_ctrl.plots.fit.fit_views` of the test's own fit."""
    from prsa_ctrl.identification.data import load_record
    from prsa_ctrl.plots.fit import fit_views

    rec = load_record(path)
    return fit_views(res, [rec])


def _none_nan(a):
    import numpy as np

    return np.array([np.nan if v is None else v for v in a], float)


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


def test_uploaded_log_fits_and_the_fitted_plant_is_tuned_on_confirmation(fitted_page, log):
    page = fitted_page  # the log uploaded in the calibration tab, its fit done
    path, truth, res = log
    r0 = _tuned(1.4)
    page.get_by_text(CAL_TAB).click()
    assert page.locator("[data-k='fit-state']").get_attribute("data-state") == "done"
    assert page.locator("[data-k='fit-verdict']").get_attribute("data-verdict") == "validated"
    for key, v in res.parameters.items():
        assert _text(page, f"fit-{key}-value") == f"{v['value']:.6g}"
        lo, hi = v["ci95"]
        assert _text(page, f"fit-{key}-ci") == f"{lo:.6g} .. {hi:.6g}"
        assert abs(v["value"] / truth.values[key] - 1) < 1e-3  # the truth is found
    assert [w.replace("warning: ", "", 1) for w in page.locator("[data-k='fit-warning']").all_inner_texts()] \
        == list(res.warnings)
    _shot(page, "app-calibration.png")
    page.get_by_text(ACT_TAB).click()
    assert _text(page, "opt-kp") == f"{r0.pid.kp:.6g}"  # not used before the confirmation
    page.get_by_text(CAL_TAB).click()
    page.locator(".prsa-fit-use button").click()
    page.locator("[data-k='fit-state'][data-state='used']").wait_for()
    page.get_by_text(ACT_TAB).click()
    page.locator('[data-k="status"][data-landscape]').wait_for()
    r1 = _tuned_on(res.plant)
    assert (_text(page, "opt-kp"), _text(page, "opt-ki")) == (f"{r1.pid.kp:.6g}", f"{r1.pid.ki:.6g}")
    assert _text(page, "opt-ms") == f"{r1.ms:.4f}"
    assert f"{r1.pid.kp:.6g}" != f"{r0.pid.kp:.6g}"  # the fitted plant really changed the design
    assert "axis-log-fitted.toml" in page.locator("[data-k='bounds']").inner_text()


def test_bad_log_shows_prsa_fits_one_line(app_page, tmp_path, monkeypatch, capsys):
    page = app_page
    cli = _cli_line(tmp_path, monkeypatch, capsys, "bad-log.csv", BAD_LOG)
    page.get_by_text(CAL_TAB).click()
    page.locator(".prsa-log-upload input[type=file]").set_input_files(
        files=[{"name": "bad-log.csv", "mimeType": "text/csv", "buffer": BAD_LOG.encode()}])
    page.locator("[data-k='fit-state'][data-state='failed']").wait_for()
    assert _text(page, "fit-error") == cli.removeprefix("prsa-fit: ")
    assert not page.locator(".prsa-fit-replay").is_visible()  # no views of a fit that did not run
    _shot(page, "app-calibration-bad-log.png")
    page.get_by_text(ACT_TAB).click()
    assert _text(page, "error") == cli.removeprefix("prsa-fit: ")
    assert "Traceback" not in page.content()
    r0 = _tuned(1.4)
    assert _text(page, "opt-kp") == f"{r0.pid.kp:.6g}"  # the plant is unchanged


def _source(page, name):
    """A Bokeh data source's columns as the browser holds them (typed arrays to lists)."""
    data = page.evaluate("(name) => { const d = Bokeh.documents[0].get_model_by_name(name).data; const o = {};"
                         " for (const [k, v] of (d instanceof Map ? d.entries() : Object.entries(d)))"
                         " o[k] = Array.from(v, (x) => (Array.isArray(x) || ArrayBuffer.isView(x)) ? Array.from(x) : x);"
                         " return o; }", name)
    return data


def test_calibration_tab_shows_the_replay_the_frf_in_hz_and_the_residuals(fitted_page, log):
    """After a fit the tab draws the replay of the written plant against the log, its residual,
    and the log's frequency response beside the written plant's (Hz), the data the browser holds
    being the fit's (fit_views of the test's own fit of the same file)."""
    import numpy as np

    page = fitted_page  # the log uploaded in the calibration tab, its fit done
    path, truth, res = log
    want = _views_of(res, path)
    (name, rep), = want["replay"].items()
    (_, frf), = want["frf"].items()
    page.get_by_text(CAL_TAB).click()
    for css in (".prsa-fit-replay", ".prsa-fit-residual", ".prsa-fit-frf-mag", ".prsa-fit-frf-phase",
                ".prsa-fit-coherence"):
        page.locator(css).wait_for()  # visible
    rv = page.locator("[data-k='fit-views-replay']")
    assert rv.get_attribute("data-mode") == "prediction-error"
    assert int(rv.get_attribute("data-n")) == len(rep["time_s"])
    assert page.locator("[data-k='fit-views-frf']").get_attribute("data-unit") == "Hz"
    got = _source(page, "prsa-fit-replay")
    np.testing.assert_allclose(got["t"], rep["time_s"], rtol=1e-12)
    np.testing.assert_allclose(got["measured"], rep["measured_rad_s"], rtol=1e-12)
    np.testing.assert_allclose(got["model"], rep["model_rad_s"], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(got["residual"], rep["residual_rad_s"], rtol=1e-6, atol=1e-6)
    got = _source(page, "prsa-fit-frf")
    np.testing.assert_allclose(got["f"], frf["frequency_hz"], rtol=1e-12)
    np.testing.assert_allclose(got["mag"], frf["measured"]["magnitude_db"], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(got["coherence"], frf["coherence"], rtol=1e-9, atol=1e-12)
    models = _source(page, "prsa-fit-frf-models")
    assert models["label"] == list(frf["models"])
    np.testing.assert_allclose(models["mag"][-1], list(frf["models"].values())[-1]["magnitude_db"], rtol=1e-6, atol=1e-6)
    _shot(page, "app-calibration-views.png")


def test_refused_fit_is_shown_as_refused_with_its_views(app_page, resonant_log, tmp_path, monkeypatch, capsys,
                                                         shared_fits):
    """A log the rigid plant cannot explain: prsa-fit exits 3 with its diagnosis and no plant
    file; the tab says refused (never a good fit), offers no plant, and shows why."""
    from prsa_ctrl.cli.fit import main as fit_main

    page = app_page
    monkeypatch.chdir(tmp_path)
    (tmp_path / resonant_log.name).write_bytes(resonant_log.read_bytes())
    assert fit_main([resonant_log.name, "--out", "r.toml"]) == 3  # named as the app names it (as uploaded)
    err = capsys.readouterr().err
    assert not (tmp_path / "r.toml").exists()
    page.get_by_text(CAL_TAB).click()
    page.locator(".prsa-log-upload input[type=file]").set_input_files(str(resonant_log))
    page.locator("[data-k='fit-state'][data-state='refused']").wait_for()
    verdict = page.locator("[data-k='fit-verdict']")
    assert verdict.get_attribute("data-verdict") == "refused"
    text = verdict.inner_text()
    assert text.startswith("Refused: the fitted plant does not explain the data")
    assert "second mass" in text
    diag = err.split("most likely missing physics: ", 1)[1].split(" (no plant file written", 1)[0]
    assert diag in text  # prsa-fit's own diagnosis
    assert "Validated" not in page.locator(".prsa-fit-out").inner_text()
    assert page.locator(".prsa-fit-use button").is_disabled()
    assert page.locator(".prsa-fit-download button").is_disabled()
    page.locator(".prsa-fit-replay").wait_for()
    page.locator(".prsa-fit-frf-mag").wait_for()
    _shot(page, "app-calibration-refused.png")


def test_uploaded_frf_is_fitted_as_prsa_fit_frf_and_a_refused_one_offers_no_plant(app_page, tmp_path, capsys):
    """A measured frequency response uploaded in the tab: the command's values and the structure
    the data chose, the Bode view in Hz with the coherence, a plant to use; the same response in
    the wrong unit (x 1000) is refused as the command refuses it, with no plant to use."""
    import json

    from prsa_ctrl.cli.fit import main as fit_main
    from test_session import _rigid_frf

    page = app_page
    good, bad = tmp_path / "bode.csv", tmp_path / "bode-x1000.csv"
    _rigid_frf(good)
    _rigid_frf(bad, scale=1000.0)
    assert fit_main(["--frf", str(good), "--out", str(tmp_path / "o.toml"), "--json", str(tmp_path / "r.json")]) == 0
    want = json.loads((tmp_path / "r.json").read_text())
    page.get_by_text(CAL_TAB).click()
    page.locator(".prsa-frf-upload input[type=file]").set_input_files(str(good))
    page.locator("[data-k='fit-state'][data-state='done']").wait_for()
    assert page.locator("[data-k='fit-structure']").get_attribute("data-structure") == "rigid"
    assert page.locator("[data-k='fit-verdict']").get_attribute("data-verdict") == "not-validated"
    for key, v in want["parameters"].items():
        assert _text(page, f"fit-{key}-value") == f"{v['value']:.6g}"
        assert _text(page, f"fit-{key}-ci") == f"{v['ci95'][0]:.6g} .. {v['ci95'][1]:.6g}"
    page.locator(".prsa-fit-frf-mag").wait_for()
    page.locator(".prsa-fit-coherence").wait_for()
    assert page.locator("[data-k='fit-views-frf']").get_attribute("data-unit") == "Hz"
    assert page.locator("[data-k='fit-views-frf']").get_attribute("data-models") == "3"
    assert not page.locator(".prsa-fit-use button").is_disabled()
    _shot(page, "app-calibration-frf.png")
    capsys.readouterr()
    assert fit_main(["--frf", str(bad), "--out", str(tmp_path / "b.toml")]) == 3
    err = capsys.readouterr().err
    page.locator(".prsa-frf-upload input[type=file]").set_input_files(str(bad))
    page.locator("[data-k='fit-state'][data-state='refused']").wait_for()
    text = page.locator("[data-k='fit-verdict']").inner_text()
    assert text.startswith("Refused: no plant written: the response's inertia")
    assert " ".join(err.split("prsa-fit: ", 1)[1].split()).replace(str(bad), bad.name) in " ".join(text.split())
    assert page.locator(".prsa-fit-use button").is_disabled()
    assert page.locator(".prsa-fit-download button").is_disabled()


# ---- the session, without a browser ---------------------------------------------------------


def test_session_calibrate_is_prsa_fit_and_use_retunes(log):
    import tomllib

    from prsa_ctrl.app.session import AppSession

    path, truth, res = log
    s = AppSession()
    try:
        cal = s.calibrate("axis-log.csv", path.read_bytes())
        assert s.plant.name == "paper-iprsm"  # nothing changes before use_calibration
        assert cal.file_name == "axis-log-fitted.toml"
        assert cal.base_label == "paper-iprsm"
        for key, v in res.parameters.items():
            assert cal.report["parameters"][key]["value"] == pytest.approx(v["value"], rel=1e-9)
            assert cal.report["parameters"][key]["ci95"] == pytest.approx(v["ci95"], rel=1e-9)
        assert cal.report["warnings"] == list(res.warnings)
        assert list(cal.report["fit_percent"]) == ["axis-log.csv"]  # named as uploaded
        assert cal.refused is None
        assert cal.report["views"]["verdict"]["validated"] is True
        (want,) = _views_of(res, path)["replay"].values()
        got = cal.report["views"]["replay"]["axis-log.csv"]
        assert got["label"] == want["label"]
        assert got["every"] == want["every"]
        assert got["explained"] is True
        import numpy as np

        np.testing.assert_allclose(got["model_rad_s"], want["model_rad_s"], rtol=1e-6, atol=1e-6)
        assert any(line.startswith("fit ") and line.endswith(" % on axis-log.csv") for line in cal.lines)
        # the written file: prsa-fit's (its name from --out, the log named as uploaded), the fitted values
        doc = tomllib.loads(cal.plant_text)
        assert doc["name"] == "axis-log-fitted"
        assert "prsa-app-" not in cal.plant_text
        assert "calibrated by prsa-fit from axis-log.csv" in doc["description"]
        for key in res.plant_keys:
            section, sub = key.split(".")
            assert doc[section][sub]["value"] == pytest.approx(res.plant.values[key], rel=1e-9)
        notes = s.use_calibration(cal)
        assert all("prsa-app-" not in n for n in notes)  # notes name the file, not the temp folder
        assert s.plant_label == "axis-log-fitted.toml"
        st = s.default_settings()
        v = s.tuned(st)
        # the tuning of the plant as written (its values equal the fit's to 1e-9 above; the tuner's
        # optimum moves with them by more than that, so the reference is the written file's own)
        from prsa_ctrl.plant.plantfile import load_plant

        ref = _tuned_on(load_plant(cal.plant_path))
        assert v.pid.kp == pytest.approx(ref.pid.kp, rel=1e-9)
        assert v.pid.ki == pytest.approx(ref.pid.ki, rel=1e-9)
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


def test_session_refused_calibration_has_the_verdict_the_views_and_no_plant(resonant_log, shared_fits):
    """prsa-fit's exit 3 after a fit whose plant does not explain the log: a Calibration marked
    refused (prsa-fit's line, its report with the views), no plant file to use; the tab's
    views draw the report's arrays and the verdict is a refusal."""
    import numpy as np

    from prsa_ctrl.app.fitpanel import FitViews, report_html
    from prsa_ctrl.app.session import AppInputError, AppSession

    s = AppSession()
    try:
        cal = s.calibrate("resonant-log.csv", resonant_log.read_bytes())
        assert (cal.refused.startswith("the fitted plant does not explain the data; most likely missing physics: "
                                      "second mass"))
        assert "--force" not in cal.refused
        assert cal.file_name == ""
        assert cal.plant_path == ""
        with pytest.raises(ValueError, match="no fitted plant file"):
            cal.plant_text
        with pytest.raises(AppInputError, match="the fit is refused, no plant to use"):
            s.use_calibration(cal)
        assert s.plant.name == "paper-iprsm"
        v = cal.report["solver"]["validation"]
        assert v["passes"] is False
        assert cal.report["views"]["verdict"]["validated"] is False
        r = cal.report["views"]["replay"]["resonant-log.csv"]
        assert r["explained"] is False
        assert r["mode"] == "prediction-error"
        page_html = report_html(cal, "refused")
        assert "data-verdict='refused'" in page_html
        assert "Validated" not in page_html
        assert "data-state='refused'" in page_html
        assert v["diagnosis"].split(":")[0] in page_html
        views = FitViews()
        views.show(cal.report["views"])
        assert views.root.visible
        assert views.replay.visible
        assert views.mag.visible
        assert views.coherence.visible
        np.testing.assert_array_equal(views.replay_src.data["model"], _none_nan(r["model_rad_s"]))
        np.testing.assert_array_equal(views.replay_src.data["residual"], _none_nan(r["residual_rad_s"]))
        fr = cal.report["views"]["frf"]["resonant-log.csv"]
        np.testing.assert_array_equal(views.frf_src.data["f"], fr["frequency_hz"])
        np.testing.assert_array_equal(views.frf_src.data["coherence"], _none_nan(fr["coherence"]))
        assert views.mag.xaxis[0].axis_label == "frequency (Hz)"
        assert views.mag.x_scale.__class__.__name__ == "LogScale"
        views.show(None)
        assert not views.root.visible
        assert views.replay_src.data["t"] == []
        # the page: the calibration tab builds its figures at the first fit, not with the page
        from bokeh.document import Document

        from prsa_ctrl.app.page import AppPage

        page = AppPage(Document(), session=s, attach=False)
        try:
            assert [t.title for t in page.tabs.tabs][-1] == "Calibration (fit a drive log)"
            assert page.fit.views is None
            assert page.fit._views_box.children == []
            page.fit._done(page.fit._seq, cal)
            assert page.fit.views is not None
            assert page.fit._views_box.children == [page.fit.views.root]
            assert page.fit.use.disabled
            assert page.fit.download.disabled
            assert not page.fit.discard.disabled
            assert "data-state='refused'" in page.fit.out.text
            assert page.fit.files.data["name"] == []
            page.fit._use()  # nothing to use: the plant stays
            assert s.plant.name == "paper-iprsm"
            assert "data-state='refused'" in page.fit.out.text
            page.fit._discard()
            assert not page.fit.views.root.visible
            assert page.fit.out.text == ""
        finally:
            page.close(wait=True)
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
        assert len(polls) == 2
        assert s.plant.name == "paper-iprsm"
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


def test_two_sessions_calibrating_at_once_keep_their_own_notes(log):
    """Two sessions calibrate in two threads at once (the app's worker threads): each gets its
    own notes, none of the other's. Was: ``warnings.catch_warnings`` (process-wide state) around
    each call: a warning of another thread during a calibration became one of its notes, and
    the calibration that finished first reset the other's recording (its plant's geometry note
    was lost). Interleaved deterministically through the ``cancelled`` polls: A starts, B starts
    and waits in its first poll until A has finished, then loads its plant."""
    import threading
    import warnings

    from prsa_ctrl.app.session import AppSession
    from prsa_ctrl.errors import GeometryWarning
    from prsa_ctrl.plant.plantfile import plant_file_path

    base = plant_file_path("paper-iprsm").read_bytes()  # geometry does not close: a note naming the file
    data = log[0].read_bytes()
    sa, sb = AppSession(), AppSession()
    got, errors = {}, []
    b_started, a_done = threading.Event(), threading.Event()

    def other_thread_warns():  # (a category the test run ignores: nothing to show where it goes)
        warnings.warn(GeometryWarning("a warning of another thread"))

    def poll_a():
        if "a-polled" not in got:
            got["a-polled"] = True
            tb.start()
            assert b_started.wait(60)
            t = threading.Thread(target=other_thread_warns)
            t.start()
            t.join()
        return False

    def poll_b():
        if not b_started.is_set():
            b_started.set()
            assert a_done.wait(120)
        return False

    def run(key, session, poll, done=None):
        try:
            got[key] = session.calibrate("axis-log.csv", data, cancelled=poll, poll_s=0.0)
        except BaseException as exc:  # noqa: BLE001 - reported by the test thread
            errors.append(exc)
        finally:
            if done is not None:
                done.set()

    try:
        assert sa.upload("plant", "plant-a.toml", base)
        assert sb.upload("plant", "plant-b.toml", base)
        tb = threading.Thread(target=run, args=("b", sb, poll_b))
        ta = threading.Thread(target=run, args=("a", sa, poll_a, a_done))
        ta.start()
        ta.join(180)
        tb.join(180)
        assert not errors, errors
        notes_a, notes_b = " | ".join(got["a"].notes), " | ".join(got["b"].notes)
        assert "another thread" not in notes_a + notes_b, notes_a  # was one of A's notes
        assert "plant-a.toml: geometry does not close" in notes_a, notes_a
        assert "plant-b.toml: geometry does not close" in notes_b, notes_b  # was lost (A's exit reset B's recording)
        assert "plant-b" not in notes_a
        assert "plant-a" not in notes_b
    finally:
        sa.close()
        sb.close()


def test_thread_warnings_records_this_threads_warnings_as_its_code_filters_them():
    """The per-thread recorder of the calibration: every warning of this thread (as ``always``,
    whatever the process's filters), none of another thread's, and the code it runs can still
    silence one (``catch_warnings(); simplefilter("ignore", ...)``: the fit's own geometry notes
    of its trial plants) or make it an error; nested blocks get their own list."""
    import threading
    import warnings

    from prsa_ctrl.app.session import thread_warnings
    from prsa_ctrl.errors import GeometryWarning

    with thread_warnings() as caught:
        warnings.warn("mine", UserWarning)
        warnings.warn(GeometryWarning("geometry, ignored by the test run's filters"))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", GeometryWarning)
            warnings.warn(GeometryWarning("silenced by the code"))
            warnings.warn("not a geometry warning", RuntimeWarning)
        with warnings.catch_warnings():
            warnings.simplefilter("error", DeprecationWarning)
            with pytest.raises(DeprecationWarning, match="an error"):
                warnings.warn("an error", DeprecationWarning)
        with thread_warnings() as inner:
            warnings.warn("inner", UserWarning)
        with warnings.catch_warnings(record=True) as theirs:  # another thread's warning goes where it went
            warnings.simplefilter("always")
            t = threading.Thread(target=lambda: warnings.warn("other thread", UserWarning))
            t.start()
            t.join()
        warnings.warn("mine again", UserWarning)
    assert [str(w.message) for w in caught] == ["mine", "geometry, ignored by the test run's filters",
                                                "not a geometry warning", "mine again"]
    assert [str(w.message) for w in inner] == ["inner"]
    assert [str(w.message) for w in theirs] == ["other thread"]
    with pytest.raises(UserWarning, match="outside"):  # outside a block: the process's filters (the test run's "error")
        warnings.warn("outside", UserWarning)


def test_thread_warnings_wrapped_by_another_wrapper_does_not_loop(monkeypatch):
    """Someone wraps the routed ``warnings.warn`` after it was installed, and a recording
    block installs it again over theirs: a warning outside any block goes to the process's
    filters once (no RecursionError between the two wrappers)."""
    import warnings

    from prsa_ctrl.app.session import thread_warnings

    from prsa_ctrl.app import session

    with thread_warnings():
        pass
    ours = warnings.warn
    monkeypatch.setattr(session._warn_routed, "previous", session._warn_routed.previous)  # put back at the end

    def theirs(message, category=None, stacklevel=1, source=None):
        return ours(message, category, stacklevel + 1, source)

    monkeypatch.setattr(warnings, "warn", theirs)
    with thread_warnings() as caught:
        warnings.warn("in the block", UserWarning)
    assert [str(w.message) for w in caught] == ["in the block"]
    with pytest.raises(UserWarning, match="outside"):
        warnings.warn("outside", UserWarning)


def test_a_mat_log_of_a_linear_axis_uploaded_with_its_description(app_page, emps_fit):
    """The EMPS .mat record uploaded after its description (the format upload): the tab shows the
    command's values (prsa-fit DATA_EMPS.mat --log-format log.toml: the session's ``emps_fit`` of
    tests/conftest.py, one fit shared with the other tests of that command; this test ran its
    own), the closed-loop replay as the verdict and as a figure beside the log's response (Hz), a
    plant to download and none to use (a linear axis: prsa-axis tunes it)."""
    import json
    from pathlib import Path

    example = Path(__file__).resolve().parents[2] / "examples" / "emps"  # the files emps_fit fitted
    data, fmt = example / "DATA_EMPS.mat", example / "log.toml"
    assert emps_fit.code == 0
    want = json.loads(emps_fit.json.read_text())
    page = app_page
    page.get_by_text(CAL_TAB).click()
    page.locator(".prsa-format-upload input[type=file]").set_input_files(str(fmt))
    page.locator("[data-k='fit-format'][data-name='log.toml']").wait_for()
    page.locator(".prsa-log-upload input[type=file]").set_input_files(str(data))
    page.locator("[data-k='fit-state'][data-state='done']").wait_for()
    # the linear axis's validation (identification.axisvalidation; was 'replayed', no verdict)
    assert page.locator("[data-k='fit-verdict']").get_attribute("data-verdict") == "validated"
    assert "closed-loop replay from the reference" in page.locator("[data-k='fit-verdict']").inner_text()
    for key, v in want["parameters"].items():
        assert _text(page, f"fit-{key}-value") == f"{v['value']:.6g}"
    assert page.locator(".prsa-fit-use button").is_disabled()
    assert not page.locator(".prsa-fit-download button").is_disabled()
    # the CLI's overlay figures (prsa-fit --plots) drawn: the closed-loop replay and the response in Hz
    assert page.locator("[data-k='fit-views-replay']").get_attribute("data-mode") == "closed-loop"
    assert page.locator("[data-k='fit-views-frf']").get_attribute("data-unit") == "Hz"
    assert page.locator(".prsa-fit-replay").is_visible()
    assert page.locator(".prsa-fit-frf-mag").is_visible()
    _shot(page, "app-calibration-mat.png")
