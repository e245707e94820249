"""prsa-app session: calibration from an uploaded measured frequency response
(:meth:`prsa_ctrl.app.session.AppSession.calibrate` with ``kind="frf"``), checked against the
``prsa-fit --frf`` command run on the same file (its plant file, its lines, its JSON report, its
exit-3 line) and, for a two-mass response written here, against the truth of its mode."""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest

from independent_actuator import modal_damper, two_mass_eom_response

pytest.importorskip("bokeh", reason="prsa-app tests need the app extra (pip install '.[app]')")

TWO_PI = 2 * math.pi


def _rigid_frf(path, scale=1.0, seed=3):
    """The default plant's own rigid response (2 % noise, coherence 0.97), times ``scale``
    (1000: a response in the wrong unit, which prsa-fit refuses with exit 3)."""
    from prsa_ctrl import load_plant
    from prsa_ctrl.identification.data import frf_from_arrays
    from prsa_ctrl.identification.frf import frf_response

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p = load_plant()
    f = np.geomspace(5, 1000, 60)
    rng = np.random.default_rng(seed)
    g = frf_response(p, f, speed_rad_s=30.0) * np.exp(0.02 * (rng.standard_normal(60) + 1j * rng.standard_normal(60)))
    coh = np.clip(0.97 + 0.01 * rng.standard_normal(60), 0, 1)
    frf_from_arrays("syn", f, scale * g, coherence=coh).to_csv(path)


def _cli(argv, capsys):
    from prsa_ctrl.cli.fit import main

    capsys.readouterr()
    code = main(argv)
    out = capsys.readouterr()
    return code, out.out, out.err


def test_frf_upload_is_prsa_fit_frf_and_its_plant_is_used(tmp_path, capsys):
    """The session's FRF calibration writes the command's plant file byte for byte, prints its
    lines, reports its values and the structure the data chose, and draws the response (data
    beside the rigid and two-mass models, Hz, coherence); the fitted plant is then the session's."""
    from prsa_ctrl.app.fitpanel import FitViews, report_html
    from prsa_ctrl.app.session import AppSession

    csv = tmp_path / "bode.csv"
    _rigid_frf(csv)
    code, out, _ = _cli(["--frf", str(csv), "--out", str(tmp_path / "bode-fitted.toml"), "--json",
                         str(tmp_path / "rep.json")], capsys)
    assert code == 0
    want = json.loads((tmp_path / "rep.json").read_text())
    s = AppSession()
    try:
        cal = s.calibrate("bode.csv", csv.read_bytes(), kind="frf")
        assert cal.refused is None
        assert cal.file_name == "bode-fitted.toml"
        # the command's file and lines, the response named as uploaded (not by the server's path)
        assert cal.plant_text == (tmp_path / "bode-fitted.toml").read_text().replace(str(csv), "bode.csv")
        assert str(tmp_path) not in cal.plant_text
        assert list(cal.lines) == [" ".join(x.replace(str(csv), "bode.csv").split()) for x in out.splitlines()
                                   if not x.startswith("wrote ")]  # (the app's lines: runs of blanks as one)
        for key, v in want["parameters"].items():
            assert cal.report["parameters"][key]["value"] == pytest.approx(v["value"], rel=1e-12)
            assert cal.report["parameters"][key]["ci95"] == pytest.approx(v["ci95"], rel=1e-12)
        st = cal.report["frf_structure"]
        assert st["structure"] == "rigid"
        assert any(x.startswith(f"structure: rigid ({st['reason']}") for x in out.splitlines())
        (fr,) = cal.report["views"]["frf"].values()
        (fw,) = want["views"]["frf"].values()
        assert list(fr["models"]) == list(fw["models"])
        assert len(fr["models"]) == 3  # rigid, two-mass, written
        np.testing.assert_allclose(fr["frequency_hz"], fw["frequency_hz"], rtol=1e-12)
        np.testing.assert_allclose(fr["coherence"], fw["coherence"], rtol=1e-12)
        html_ = report_html(cal, "done")
        assert "data-k='fit-structure' data-structure='rigid'" in html_
        assert "data-verdict='not-validated'" in html_
        # the fit's status in the one vocabulary, as prsa-fit's JSON has it (an FRF fit is not replayed)
        assert want["status"].startswith("unverified: ")
        assert f"<span data-k='fit-status'>{want['status']}</span>" in html_
        views = FitViews()
        views.show(cal.report["views"])
        assert views.mag.visible
        assert views.coherence.visible
        assert not views.replay.visible
        assert views.frf_src.data["f"] == pytest.approx(fw["frequency_hz"], rel=1e-12)
        s.use_calibration(cal)
        assert s.plant_label == "bode-fitted.toml"
        assert s.plant.values["nut.inertia_kg_m2"] == pytest.approx(cal.report["parameters"]["nut.inertia_kg_m2"]["value"],
                                                                    rel=1e-6)
    finally:
        s.close()


def test_refused_frf_fit_is_the_commands_exit_3_line_and_no_plant(tmp_path, capsys):
    """A response in the wrong unit (x 1000): prsa-fit exits 3 and writes nothing; the session
    returns a refused calibration with the same line, no plant to use; the tab shows it refused."""
    from prsa_ctrl.app.fitpanel import report_html
    from prsa_ctrl.app.session import AppInputError, AppSession

    csv = tmp_path / "bad.csv"
    _rigid_frf(csv, scale=1000.0)
    code, _, err = _cli(["--frf", str(csv), "--out", str(tmp_path / "bad-fitted.toml")], capsys)
    assert code == 3
    assert not (tmp_path / "bad-fitted.toml").exists()
    s = AppSession()
    try:
        cal = s.calibrate("bad.csv", csv.read_bytes(), kind="frf")
        assert cal.refused == " ".join(err.strip().removeprefix("prsa-fit: ").split())
        assert cal.refused.startswith("no plant written: the response's inertia")
        assert cal.file_name == ""
        with pytest.raises(AppInputError, match="no plant to use"):
            s.use_calibration(cal)
        with pytest.raises(ValueError):
            cal.plant_text
        html_ = report_html(cal, "refused")
        assert "data-verdict='refused'" in html_
        assert "data-state='refused' data-file=''" in html_
        assert s.plant.name == "paper-iprsm"
        # a bad file is prsa-fit's exit-2 line, named as uploaded
        with pytest.raises(AppInputError, match=r"^x<b>\.csv: header frequency_hz, magnitude_db; expected frequency_hz "
                                                r"with magnitude_db,phase_deg or with real,imag"):
            s.calibrate("x<b>.csv", b"frequency_hz,magnitude_db\n1,2\n", kind="frf")
        with pytest.raises(ValueError, match="kind = 'bode'"):
            s.calibrate("a.csv", b"", kind="bode")
    finally:
        s.close()


def _two_mass(f, jm, jl, k, zeta, fc):
    """Motor speed / torque command of two inertias on a spring (modal damping ``zeta``) and a
    first-order current loop, from the equations of motion (tests/independent_actuator.py)."""
    return two_mass_eom_response(f, jm, jl, k, modal_damper(k, jm, jl, zeta), fc_hz=fc)


def test_two_mass_response_shows_the_chosen_structure_and_the_mode_with_intervals(tmp_path, capsys):
    """A two-mass ball-screw axis written here (mode 107 Hz at the motor): the data choose the
    two-mass structure, the report's mode and anti-resonance intervals hold the truth, and the
    tab shows the structure line with the mode."""
    from prsa_ctrl.app.fitpanel import report_html
    from prsa_ctrl.app.session import AppSession

    s = AppSession()
    try:
        s.set_plant("ballscrew-32x10")
        j0 = s.plant.reflected_inertia_kg_m2
        jm, jl, fa = 0.7 * j0, 0.4 * j0, 80.0
        k = jl * (TWO_PI * fa) ** 2
        f_r = fa * math.sqrt((jm + jl) / jm)
        f = np.geomspace(3.0, 1500.0, 220)
        rng = np.random.default_rng(9)
        g = _two_mass(f, jm, jl, k, 0.04, 1100.0) * np.exp(0.01 * (rng.standard_normal(220)
                                                                   + 1j * rng.standard_normal(220)))
        from prsa_ctrl.identification.data import frf_from_arrays

        frf_from_arrays("two-mass", f, g, sample_time_s=0.0).to_csv(tmp_path / "axis.csv")
        cal = s.calibrate("axis.csv", (tmp_path / "axis.csv").read_bytes(), kind="frf")
        assert cal.report["frf_structure"]["structure"] == "two-mass", cal.report["frf_structure"]["reason"]
        # the command's numbers (prsa-fit --frf on the same file and base)
        code, _, _ = _cli(["--frf", str(tmp_path / "axis.csv"), "--plant", "ballscrew-32x10", "--out",
                           str(tmp_path / "axis-fitted.toml"), "--json", str(tmp_path / "rep.json")], capsys)
        want = json.loads((tmp_path / "rep.json").read_text())
        assert code == (0 if cal.refused is None else 3)
        for key, truth in (("frf_axial_mode_hz", f_r), ("frf_antiresonance_hz", fa)):
            got = cal.report[key]
            assert got["value"] == pytest.approx(want[key]["value"], rel=1e-12)
            assert got["ci95"] == pytest.approx(want[key]["ci95"], rel=1e-12)
            lo, hi = got["ci95"]
            assert lo < got["value"] < hi
            # the truth of the continuous formula, read from the file as sampled at the plant's
            # 125 us (as a drive's measurement is): within 1 % (the truth sits 0.1-0.2 % outside the
            # interval: mode 100.29 Hz against 99.59..100.09, anti-resonance 80.00 against 80.09..80.46)
            assert got["value"] == pytest.approx(truth, rel=0.01)
        html_ = report_html(cal, "done") if cal.refused is None else report_html(cal, "refused")
        assert "data-structure='two-mass'" in html_
        assert "axial mode" in html_
        assert "anti-resonance" in html_
        # the mode is quoted with the point it holds at (the command's default 30 rad/s, 0 N)
        assert "operating point 30 rad/s, 0 N" in html_
        assert cal.report["frf_axial_mode_hz"]["load_n"] == want["frf_axial_mode_hz"]["load_n"] == 0.0
    finally:
        s.close()


def test_every_view_status_is_in_the_one_vocabulary():
    """The optimum carries the tuner's status, a hand design and a baseline say they are not
    tuned (``unverified: ...``), an unstable loop is ``flagged: ...`` and verification leaves it
    unsimulated; each status belongs to :data:`prsa_ctrl.results.STATUSES`."""
    from prsa_ctrl.app.session import BASELINE_STATUS, MANUAL_STATUS, UNSTABLE_STATUS, AppSession, View
    from prsa_ctrl.results import status_head

    s = AppSession()
    try:
        st = s.default_settings()
        opt = s.tuned(st)
        assert status_head(opt.status) == "optimal"
        man = s.manual(st, 0.05, 5.0)
        assert man.status == MANUAL_STATUS
        assert status_head(man.status) == "unverified"
        base = s.baselines(st)
        assert base
        assert {b.status for b in base} <= {BASELINE_STATUS, UNSTABLE_STATUS}
        assert status_head(BASELINE_STATUS) == "unverified"
        bad = s.manual(st, 5.0, 5000.0)  # far beyond the stable region
        assert bad.status == UNSTABLE_STATUS
        assert status_head(bad.status) == "flagged"
        assert not bad.t
        [checked] = s.verify(st, [bad])
        assert checked.design.flags == ("the loop is unstable: not simulated",)
        with pytest.raises(ValueError, match="status = 'manual'; expected a str starting with one of"):
            View(man.design, man.omega, man.loop, man.t, man.speed, "manual", man.noise_gain)
    finally:
        s.close()


# ---- a described log (.mat, linear axis): prsa-fit LOG --log-format FORMAT.toml ----------------

def _emps():
    """The EMPS record and its description (examples/emps), or a skip."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    data = next((p for p in (root.parent / "shared" / "data" / "emps" / "DATA_EMPS.mat",
                             root / "examples" / "emps" / "DATA_EMPS.mat") if p.is_file()), None)
    fmt = root / "examples" / "emps" / "log.toml"
    if data is None or not fmt.is_file():
        pytest.skip("EMPS data or its description absent (../shared/data/emps/, examples/emps/)")
    return data, fmt


def test_a_mat_log_of_a_linear_axis_is_fitted_through_its_description(emps_fit):
    """The EMPS .mat record uploaded with its description: the session's calibration writes what
    ``prsa-fit DATA_EMPS.mat --log-format log.toml`` writes (the plant file byte for byte but its
    name, which is its file's), its lines (files named as uploaded), a linear-axis plant to
    download, not to tune here; without the description the .mat log is refused with the
    command's line. The command's run is the session's ``emps_fit`` (tests/conftest.py: one fit
    per session, shared with the identification and Monte Carlo tests; this test ran its own)."""
    from pathlib import Path

    from prsa_ctrl.app.fitpanel import report_html
    from prsa_ctrl.app.session import AppInputError, AppSession
    from prsa_ctrl.identification.calibrate import mat_log_refusal

    example = Path(__file__).resolve().parents[2] / "examples" / "emps"  # the files emps_fit fitted
    data, fmt = example / "DATA_EMPS.mat", example / "log.toml"
    assert emps_fit.code == 0
    want = json.loads(emps_fit.json.read_text())
    command_text = emps_fit.toml.read_text()
    assert command_text.count(f'name = "{emps_fit.toml.stem}"\n') == 1  # the command names the plant after --out
    s = AppSession()
    try:
        cal = s.calibrate("DATA_EMPS.mat", data.read_bytes(), log_format=("log.toml", fmt.read_bytes()))
        assert cal.refused is None
        assert not cal.usable
        assert cal.file_name == "DATA_EMPS-fitted.toml"
        assert cal.plant_text == command_text.replace(f'name = "{emps_fit.toml.stem}"\n', 'name = "DATA_EMPS-fitted"\n')
        assert list(cal.lines) == [" ".join(x.replace(str(data), "DATA_EMPS.mat").split())
                                   for x in emps_fit.out.splitlines() if not x.startswith("wrote ")]
        for key, v in want["parameters"].items():
            assert cal.report["parameters"][key]["value"] == pytest.approx(v["value"], rel=1e-12)
        html_ = report_html(cal, "done")
        assert "data-verdict='validated'" in html_  # the linear axis's validation (was: 'replayed', no verdict)
        assert "download it, prsa-axis tunes it" in html_
        with pytest.raises(AppInputError, match="a linear-axis plant; expected a screw-driven plant"):
            s.use_calibration(cal)
        assert s.plant.name == "paper-iprsm"
        with pytest.raises(AppInputError) as e:
            s.calibrate("DATA_EMPS.mat", data.read_bytes())
        assert str(e.value) == mat_log_refusal("DATA_EMPS.mat")
        with pytest.raises(AppInputError, match=r"^log\.toml: .*expected"):  # a bad description: its one line
            s.calibrate("DATA_EMPS.mat", data.read_bytes(), log_format=("log.toml", b"format = 3\n"))
    finally:
        s.close()


_AXIS_FORMAT = b"""format = "csv"
[time]
name = "t_s"
unit = "s"
[position]
name = "x_mm"
unit = "mm"
[reference]
name = "r_mm"
unit = "mm"
[command]
name = "u_V"
unit = "V"
gain = 30.0
[test_signal]
name = "d_V"
unit = "V"
[controller]
structure = "position-p/velocity-p"
kp = 150.0
kv = 250.0
saturation = 10.0
sample_time_s = 0.001
check_tolerance = 1e-6
"""


def _axis_csv(n=2500, seed=5) -> bytes:
    """A closed-loop log of one 80 kg mass with viscous (180 N s/m) and Coulomb (20 N) friction,
    written here (explicit Euler on 20 substeps, its own controller with the two-sample average),
    with a random binary test signal at the drive input."""
    rng = np.random.default_rng(seed)
    h, sub = 1e-3, 20
    r = 0.05 * (1 - np.cos(2 * math.pi * np.arange(n) * h / 1.25))  # 0 .. 0.1 m and back, twice
    d = 0.5 * np.repeat(rng.choice([-1.0, 1.0], n // 5 + 1), 5)[:n]
    x = v = qprev = qfprev = 0.0
    rows = ["t_s,x_mm,r_mm,u_V,d_V"]
    for k in range(n):
        q = 5e-8 * math.floor(x / 5e-8 + 0.5)
        qf = 0.5 * (q + qprev)
        dq = (qf - qfprev) / h
        qprev, qfprev = q, qf
        u = min(10.0, max(-10.0, 250.0 * (150.0 * (r[k] - q) - dq)))
        rows.append(f"{k * h:.6f},{q * 1e3:.9f},{r[k] * 1e3:.9f},{float(u + d[k])!r},{float(d[k])!r}")
        f = 30.0 * (u + d[k])
        for _ in range(sub):
            a = (f - 180.0 * v - 20.0 * math.copysign(1.0, v) * (v != 0)) / 80.0
            if v == 0 and abs(f) <= 20.0:
                a = 0.0
            vn = v + a * h / sub
            x += 0.5 * (v + vn) * h / sub
            v = 0.0 if v != 0 and vn * v < 0 else vn
    return ("\n".join(rows) + "\n").encode()


def _two_mass_csv(n=3000, seed=4) -> bytes:
    """A closed-loop log of a 30 kg motor side carrying 50 kg through a spring (3.16 N/um, damping
    ratio 0.05 of the mode) with viscous (150 N s/m) and Coulomb (15 N) friction on the motor side,
    written here (semi-implicit Euler on 40 substeps), in _AXIS_FORMAT's columns; the profile of
    _axis_csv's controller and test signal."""
    rng = np.random.default_rng(seed)
    h, sub = 1e-3, 40
    hs = h / sub
    mm, ml, k = 30.0, 50.0, 3.16e6
    c = 2 * 0.05 * math.sqrt(k * mm * ml / (mm + ml))
    r = 0.05 * (1 - np.cos(2 * math.pi * np.arange(n) * h / 1.5))
    d = 0.5 * np.repeat(rng.choice([-1.0, 1.0], n // 5 + 1), 5)[:n]
    x = v = xl = vl = qprev = qfprev = 0.0
    rows = ["t_s,x_mm,r_mm,u_V,d_V"]
    for i in range(n):
        q = 5e-8 * math.floor(x / 5e-8 + 0.5)
        qf = 0.5 * (q + qprev)
        dq = (qf - qfprev) / h
        qprev, qfprev = q, qf
        u = min(10.0, max(-10.0, 250.0 * (150.0 * (r[i] - q) - dq)))
        rows.append(f"{i * h:.6f},{q * 1e3:.9f},{r[i] * 1e3:.9f},{float(u + d[i])!r},{float(d[i])!r}")
        f = 30.0 * (u + d[i])
        for _ in range(sub):
            spring = k * (x - xl) + c * (v - vl)
            net = f - spring
            if v == 0 and abs(net) <= 15.0:
                a = 0.0
            else:
                a = (net - 150.0 * v - 15.0 * math.copysign(1.0, v if v != 0 else net)) / mm
            vn = v + a * hs
            v = 0.0 if v != 0 and vn * v < 0 else vn
            x += v * hs
            vl += spring / ml * hs
            xl += vl * hs
    return ("\n".join(rows) + "\n").encode()


def test_the_apps_linear_axis_calibration_chooses_the_two_mass_axis_when_the_data_do(tmp_path):
    """A two-mass log uploaded with its description: the rigid fit's validation refuses it (a
    second mass); the app then fits the two-mass axis as ``prsa-fit --fidelity compliant`` does and
    takes it because it explains the log, saying so in the first line; the plant file is a two-mass
    axis near the truth (80 kg in all, 50 kg beyond the spring). A rigid log keeps the rigid fit, no
    structure line."""
    import tomllib

    from prsa_ctrl.app.fitpanel import report_html
    from prsa_ctrl.app.session import AppSession
    from prsa_ctrl.identification.calibrate_axis import calibrate_described

    (tmp_path / "two.csv").write_bytes(_two_mass_csv())
    (tmp_path / "log.toml").write_bytes(_AXIS_FORMAT)
    rigid = calibrate_described([str(tmp_path / "two.csv")], str(tmp_path / "log.toml"), name="x", fidelity="rigid")
    assert rigid.failure is not None
    assert "second mass" in rigid.failure
    assert rigid.plant_text is None
    s = AppSession()
    try:
        cal = s.calibrate("two.csv", _two_mass_csv(), log_format=("log.toml", _AXIS_FORMAT))
        plain = s.calibrate("axis.csv", _axis_csv(), log_format=("log.toml", _AXIS_FORMAT))
        texts = cal.plant_text, plain.plant_text  # (the session's folder goes with it)
    finally:
        s.close()
    assert cal.refused is None
    assert cal.lines[0].startswith("structure: the rigid fit does not explain the logs (second mass)")
    assert "the two-mass fit (prsa-fit --fidelity compliant) does: chosen" in cal.lines[0]
    assert cal.report["structure"] == "two-mass"
    assert cal.report["validation"]["passes"] is True
    doc = tomllib.loads(texts[0])
    assert doc["axis"]["mass_kg"]["value"] == pytest.approx(80.0, rel=0.02)
    assert doc["axis"]["load_mass_kg"]["value"] == pytest.approx(50.0, rel=0.05)
    assert "data-verdict='validated'" in report_html(cal, "done")
    assert plain.refused is None
    assert "structure_choice" not in plain.report
    assert "load_mass_kg" not in texts[1]


def test_a_linear_axis_calibration_shows_the_clis_overlay_figures(tmp_path):
    """The app's linear-axis calibration carries the views of ``prsa-fit LOG --log-format F --plots
    DIR`` as data (:func:`prsa_ctrl.plots.fit.axis_views`): the closed-loop replay of the plant as
    written beside the measured speed and its residual, the log's force -> speed response (Hz)
    beside the replay's through the same estimator, with its residual and coherence -- the very
    numbers the CLI's figures plot (read back from them) -- and the panel draws them in m/s."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from prsa_ctrl.app.fitpanel import FitViews
    from prsa_ctrl.app.session import AppSession
    from prsa_ctrl.identification.axis import replay_axis
    from prsa_ctrl.identification.calibrate_axis import calibrate_described
    from prsa_ctrl.plots.fit import axis_replay_figure, axis_response_figure

    (tmp_path / "axis.csv").write_bytes(_axis_csv())
    (tmp_path / "log.toml").write_bytes(_AXIS_FORMAT)
    s = AppSession()
    try:
        cal = s.calibrate("axis.csv", _axis_csv(), log_format=("log.toml", _AXIS_FORMAT))
    finally:
        s.close()
    assert cal.refused is None
    assert not cal.usable
    views = cal.report["views"]
    assert set(views["replay"]) == {"axis.csv"}
    assert set(views["frf"]) == {"axis.csv"}
    assert views["unit"] == "m/s"
    rp, fr = views["replay"]["axis.csv"], views["frf"]["axis.csv"]
    assert rp["mode"] == "closed-loop"
    assert "closed-loop replay from the reference" in rp["label"]
    # the CLI's figures of the same fit (prsa-fit --plots draws these from its replays)
    got = calibrate_described([str(tmp_path / "axis.csv")], str(tmp_path / "log.toml"), name="axis-fitted",
                              labels=["axis.csv"])
    replay = got.result.replays[0]
    assert replay_axis(got.result.plant, got.records[0]).velocity_simulated == pytest.approx(replay.velocity_simulated)
    fig = axis_replay_figure(replay)
    vel = fig.axes[1]
    t = vel.lines[0].get_xdata()
    every = rp["every"]
    assert rp["time_s"] == pytest.approx(list(t[::every]))
    assert rp["measured_rad_s"] == pytest.approx(list(vel.lines[0].get_ydata()[::every]))
    assert rp["model_rad_s"] == pytest.approx(list(vel.lines[1].get_ydata()[::every]))
    assert rp["residual_rad_s"] == pytest.approx(list(fig.axes[3].lines[0].get_ydata()[::every]))
    plt.close(fig)
    fig = axis_response_figure(replay)
    mag = fig.axes[0]
    assert fr["frequency_hz"] == pytest.approx(list(mag.lines[0].get_xdata()))
    assert fr["measured"]["magnitude_db"] == pytest.approx(list(mag.lines[0].get_ydata()))
    (model,) = fr["models"].values()
    assert model["written"]
    assert model["magnitude_db"] == pytest.approx(list(mag.lines[1].get_ydata()))
    assert fr["residual"]["magnitude_db"] == pytest.approx(list(fig.axes[2].lines[0].get_ydata()))
    assert fr["coherence"] == pytest.approx(list(fig.axes[3].lines[0].get_ydata()))
    plt.close(fig)
    assert max(fr["frequency_hz"]) < 0.5 / 1e-3  # a Hz axis below the Nyquist frequency of the 1 kHz log
    panel = FitViews()
    panel.show(views)
    assert panel.root.visible
    assert panel.replay.visible
    assert panel.mag.visible
    assert panel.coherence.visible
    assert panel.replay.yaxis.axis_label == "speed (m/s)"
    assert "m/s per N" in panel.mag.yaxis.axis_label
    assert len(panel.replay_src.data["t"]) == len(rp["time_s"])
    assert len(panel.frf_src.data["f"]) == len(fr["frequency_hz"])


_MOTOR_FORMAT = b"""axis = "rotary"
[time]
name = "t_ms"
unit = "ms"
[position]
name = "angle_deg"
unit = "deg"
[command]
name = "torque"
unit = "N m"
logged = "as-applied"
[load]
name = "fz"
unit = "N"
"""


def test_a_log_in_motor_coordinates_uploaded_with_its_description_fits_the_sessions_plant(tmp_path, capsys,
                                                                                          monkeypatch):
    """The rotary path of ``calibrate_described``: a log in motor coordinates (ms, deg, N m; the
    independent simulator's multisine under load steps of the default plant) uploaded with its
    description (``axis = "rotary"``) fits the session's screw-driven plant as ``prsa-fit LOG
    --log-format F --plant paper-iprsm`` does: the same plant file byte for byte but its name,
    the same values, lines (files named as uploaded) and verdict; the plant is usable and, once
    used, is the session's; the views are the screw fit's (the replay in rad/s, not m/s)."""
    from prsa_ctrl import load_plant
    from prsa_ctrl.app.session import AppSession
    from independent_actuator import multisine_load_step_record

    rec = multisine_load_step_record(load_plant(), name="motor")
    csv = tmp_path / "motor.csv"
    np.savetxt(csv, np.column_stack([rec.time_s * 1e3, np.degrees(rec.nut_angle_rad), rec.torque_command_n_m,
                                     rec.axial_load_n]), delimiter=",", header="t_ms,angle_deg,torque,fz",
               comments="", fmt="%.17g")
    fmt = tmp_path / "motor.toml"
    fmt.write_bytes(_MOTOR_FORMAT)
    monkeypatch.chdir(tmp_path)  # the command names the files as given: as uploaded here
    code, out, _ = _cli(["motor.csv", "--log-format", "motor.toml", "--plant", "paper-iprsm", "--out",
                         "motor-fitted.toml", "--json", "r.json"], capsys)
    assert code == 0
    want = json.loads((tmp_path / "r.json").read_text())
    s = AppSession()
    try:
        assert s.plant.name == "paper-iprsm"
        cal = s.calibrate("motor.csv", csv.read_bytes(), log_format=("motor.toml", _MOTOR_FORMAT))
        assert cal.refused is None
        assert cal.usable
        assert cal.file_name == "motor-fitted.toml"
        assert cal.plant_text == (tmp_path / "motor-fitted.toml").read_text()
        assert list(cal.lines) == [" ".join(x.split()) for x in out.splitlines() if not x.startswith("wrote ")]
        for key, v in want["parameters"].items():
            assert cal.report["parameters"][key]["value"] == pytest.approx(v["value"], rel=1e-12)
        assert cal.report["solver"]["validation"]["passes"] is True
        views = cal.report["views"]
        assert "unit" not in views
        assert set(views["replay"]) == {"motor.csv"}
        s.use_calibration(cal)
        assert s.plant.name == "motor-fitted"
    finally:
        s.close()
