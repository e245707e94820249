"""prsa_ctrl.plots.fit: the fit's figures and views draw the result's own arrays (the replay of
the plant as written, its residual, the frequency responses beside the fitted models, the
coherence) on a Hz axis (rad/s on request), with the verdict; log_response checked against the
true plant's response; the linear axis's replay and response overlays."""

import json
import math
import warnings

import matplotlib.pyplot as plt
import numpy as np
import pytest
from scipy.signal import lfilter

from prsa_ctrl.identification.axis import AxisReplay
from prsa_ctrl.identification.common import FitResult
from prsa_ctrl.identification.frf import frf_response
from prsa_ctrl.identification.synthetic import fit_record
from prsa_ctrl.plots.fit import (axis_replay_figure, axis_response_figure, figure_names, fit_figures, fit_views,
                                 log_response)


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


def test_bode_figure_shows_data_models_and_residual():
    f = np.geomspace(5, 1500, 80)
    g = 1 / (1j * 2 * np.pi * f * 4e-3)
    g_data = g * np.exp(0.01 * np.sin(np.arange(80)))
    tr = {"frequency_hz": f, "measured": g_data, "model": g, "chosen": "two-mass",
          "models": {"rigid (75.0 %)": g * 1.3, "two-mass (98.0 %)": g * 1.01, "plant model as written (98 %)": g}}
    res = FitResult(plant=None, parameters={}, reflected_inertia_kg_m2={}, correlation=np.zeros((0, 0)), keys=(),
                    fit_percent={"b.csv": 98.0}, warnings=[], solver={}, traces={"b.csv": tr})
    figs = fit_figures(res)
    assert list(figs) == ["b-bode"]
    fig = figs["b-bode"]
    try:
        ax_mag, ax_ph, ax_res = fig.axes[:3]
        labels = [ln.get_label() for ln in ax_mag.get_lines()]
        assert labels == ["measured", "rigid (75.0 %)", "two-mass (98.0 %)", "fitted plant as written"]
        assert ax_res.get_xlabel() == "frequency (Hz)"
        assert ax_mag.get_xscale() == "log"
        res_db = ax_res.get_lines()[0].get_ydata()
        assert np.allclose(res_db, 20 / np.log(10) * 0.01 * np.sin(np.arange(80)), atol=1e-9)
        assert "structure: two-mass" in ax_mag.get_title()
    finally:
        plt.close(fig)


CLOSED = "plant as written, closed-loop replay from the reference"


def _fit_result(traces, solver=None, fit_percent=None):
    return FitResult(plant=None, parameters={}, reflected_inertia_kg_m2={}, correlation=np.zeros((0, 0)), keys=(),
                     fit_percent=fit_percent or {}, warnings=[], solver=solver or {}, traces=traces)


def _validation(passes: bool):
    e = {"fit_percent": 31.5, "error_rms_rad_s": 2.0, "noise_floor_rad_s": 0.1, "skip_samples": 20, "finite": True,
         "explained": passes,
         "whiteness": {"lags": [1], "acf": {1: 0.734}, "band": 0.03, "ljung_box_q": 900.0, "ljung_box_limit": 67.5,
                       "ljung_box_lags": 50, "white": False}}
    return {"replay": "closed loop", "passes": passes, "reasons": [] if passes else ["a.csv: the written plant replays "
                                                                                    "it at 31.5 %"],
            "diagnosis": None if passes else "second mass: 80 % of the replay residual of a.csv lies within 15 % of "
                                             "105.5 Hz",
            "written_plant": {"a.csv": e}, "free_fit": {}, "cross_validation": None, "rule": "r"}


def _record_trace(n=4501, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(1, n + 1) * 2.5e-4
    meas = 30 + 5 * np.sin(2 * np.pi * 7 * t) + 0.1 * rng.standard_normal(n)
    model = 30 + 4.6 * np.sin(2 * np.pi * 7 * t + 0.05)
    seg = model + 0.01  # the shooting segments' (not what the figure shows when a replay exists)
    return {"time_s": t, "measured": meas, "model": seg,
            "simulated": {"time_s": t, "measured": meas, "model": model, "label": CLOSED}}


def _frf_trace(coherence=True):
    f = np.geomspace(5, 1500, 80)
    g = 1 / (1j * 2 * np.pi * f * 4e-3)
    tr = {"frequency_hz": f, "measured": g * np.exp(0.01 * np.sin(np.arange(80))), "model": g, "chosen": "two-mass",
          "models": {"rigid (75.0 %)": g * 1.3, "two-mass (98.0 %)": g * 1.01, "plant model as written (98 %)": g}}
    tr["coherence"] = 0.5 + 0.5 * np.cos(np.arange(80) / 9.0) ** 2 if coherence else None
    return tr


def test_record_figure_is_the_replay_its_residual_and_the_verdict():
    tr = _record_trace()
    res = _fit_result({"a.csv": tr}, {"validation": _validation(False)}, {"a.csv": 31.5})
    fig = fit_figures(res)["a-fit"]
    try:
        ax1, ax2 = fig.axes
        meas, model = ax1.get_lines()[:2]
        assert model.get_label() == CLOSED  # which replay: the validation's, named
        np.testing.assert_array_equal(meas.get_ydata(), tr["simulated"]["measured"])
        np.testing.assert_array_equal(model.get_ydata(), tr["simulated"]["model"])  # not the segments
        np.testing.assert_array_equal(model.get_xdata(), tr["time_s"])
        np.testing.assert_array_equal(ax2.get_lines()[0].get_ydata(), tr["simulated"]["measured"] - tr["simulated"]["model"])
        assert ax2.get_ylabel() == "residual (rad/s)"
        assert ax2.get_xlabel() == "time (s)"
        assert "replay fit 31.5 %" in ax1.get_title()
        assert "NOT explained" in ax1.get_title()
        assert "20 x noise floor" in ax1.get_title()  # 2.0 / 0.1
        assert "lag 1 +0.73" in ax2.get_title()
        assert "not white" in ax2.get_title()
        caption = " ".join(t.get_text() for t in fig.texts)
        assert "NOT validated" in caption
        assert "second mass" in caption  # a refusal, never "good"
    finally:
        plt.close(fig)
    fig = fit_figures(_fit_result({"a.csv": tr}, {"validation": _validation(True)}, {"a.csv": 99.0}))["a-fit"]
    try:
        assert "explained" in fig.axes[0].get_title()
        assert "NOT" not in fig.axes[0].get_title()
        assert "the plant explains the data" in " ".join(t.get_text() for t in fig.texts)
    finally:
        plt.close(fig)


@pytest.mark.parametrize("unit, factor", [("Hz", 1.0), ("rad/s", 2 * math.pi)])
def test_bode_figure_data_models_residual_and_coherence_in_the_unit(unit, factor):
    tr = _frf_trace()
    fig = fit_figures(_fit_result({"b.csv": tr}, fit_percent={"b.csv": 98.0}), frequency_unit=unit)["b-bode"]
    try:
        ax_mag, ax_ph, ax_res, ax_coh = fig.axes[:4]
        lines = ax_mag.get_lines()
        assert [ln.get_label() for ln in lines] == ["measured", "rigid (75.0 %)", "two-mass (98.0 %)",
                                                   "fitted plant as written"]
        for ln, g in zip(lines, (tr["measured"], tr["models"]["rigid (75.0 %)"], tr["models"]["two-mass (98.0 %)"],
                                 tr["model"])):
            np.testing.assert_allclose(ln.get_xdata(), tr["frequency_hz"] * factor, rtol=1e-15)
            np.testing.assert_allclose(ln.get_ydata(), 20 * np.log10(np.abs(g)), rtol=1e-12)
        np.testing.assert_allclose(ax_ph.get_lines()[0].get_ydata(), np.degrees(np.unwrap(np.angle(tr["measured"]))))
        np.testing.assert_array_equal(ax_coh.get_lines()[0].get_ydata(), tr["coherence"])
        assert ax_coh.get_ylabel() == "coherence"
        assert ax_coh.get_xlabel() == f"frequency ({unit})"
        assert ax_mag.get_xscale() == "log"
        np.testing.assert_allclose(ax_res.get_lines()[0].get_ydata(), 20 / np.log(10) * 0.01 * np.sin(np.arange(80)),
                                   atol=1e-9)
    finally:
        plt.close(fig)
    fig = fit_figures(_fit_result({"b.csv": _frf_trace(coherence=False)}))["b-bode"]
    try:
        assert len([a for a in fig.axes if a.get_ylabel() == "coherence"]) == 0  # none drawn when the data have none
    finally:
        plt.close(fig)


def test_fit_figures_refuse_an_unknown_frequency_unit():
    with pytest.raises(ValueError, match=r"frequency unit 'kHz'; expected one of Hz, rad/s"):
        fit_figures(_fit_result({"b.csv": _frf_trace()}), frequency_unit="kHz")


def test_fit_views_are_the_results_arrays():
    tr, fr = _record_trace(n=4501), _frf_trace()
    tr["simulated"]["model"][6] = np.nan  # no NaN reaches a reader: None
    res = _fit_result({"a.csv": tr, "b.csv": fr}, {"validation": _validation(False)}, {"a.csv": 31.5, "b.csv": 97.0})
    v = fit_views(res, max_points=2000)
    json.dumps(v, allow_nan=False)  # JSON-ready, every number finite or None
    assert v["verdict"] == {"validated": False, "diagnosis": _validation(False)["diagnosis"],
                            "reasons": _validation(False)["reasons"], "replay": "closed loop"}
    r = v["replay"]["a.csv"]
    assert r["every"] == 3
    assert r["mode"] == "closed-loop"
    assert r["label"] == CLOSED  # ceil(4501 / 2000)
    idx = np.arange(0, 4501, 3)
    sim = tr["simulated"]
    for key, a in (("time_s", sim["time_s"]), ("measured_rad_s", sim["measured"]), ("model_rad_s", sim["model"]),
                   ("residual_rad_s", sim["measured"] - sim["model"])):
        got = np.array([np.nan if x is None else x for x in r[key]])
        np.testing.assert_array_equal(got, a[idx])
    assert r["model_rad_s"][2] is None
    assert r["residual_rad_s"][2] is None
    assert r["model_rad_s"][1] is not None
    assert r["explained"] is False
    assert r["fit_percent"] == 31.5
    assert r["whiteness"]["acf"][1] == 0.734
    f = v["frf"]["b.csv"]
    np.testing.assert_array_equal(f["frequency_hz"], fr["frequency_hz"])
    np.testing.assert_allclose(f["measured"]["magnitude_db"], 20 * np.log10(np.abs(fr["measured"])), rtol=1e-12)
    assert [(k, m["written"]) for k, m in f["models"].items()] == [
        ("rigid (75.0 %)", False), ("two-mass (98.0 %)", False), ("fitted plant as written", True)]
    np.testing.assert_allclose(f["models"]["rigid (75.0 %)"]["magnitude_db"],
                               20 * np.log10(np.abs(fr["models"]["rigid (75.0 %)"])), rtol=1e-12)
    np.testing.assert_allclose(f["residual"]["magnitude_db"], 20 / np.log(10) * 0.01 * np.sin(np.arange(80)), atol=1e-9)
    np.testing.assert_array_equal(f["coherence"], fr["coherence"])
    assert f["chosen"] == "two-mass"
    assert f["fit_percent"] == 97.0
    # phases on the written model's branch: the data's own angle, within half a turn of the model
    ph, ref = np.radians(f["measured"]["phase_deg"]), np.radians(f["models"]["fitted plant as written"]["phase_deg"])
    np.testing.assert_allclose(np.exp(1j * ph), fr["measured"] / np.abs(fr["measured"]), atol=1e-12)
    np.testing.assert_allclose(np.exp(1j * ref), fr["model"] / np.abs(fr["model"]), atol=1e-12)
    assert np.all(np.abs(ph - ref) <= np.pi + 1e-12)
    assert np.all(np.abs(np.diff(ref)) < np.pi)
    short = fit_views(_fit_result({"a.csv": _record_trace(n=300)}))
    assert short["replay"]["a.csv"]["every"] == 1
    assert len(short["replay"]["a.csv"]["time_s"]) == 300
    assert short["verdict"]["validated"] is None  # no validation ran: not "validated"
    with pytest.raises(ValueError, match="max_points = 1; expected an integer >= 2"):
        fit_views(res, max_points=1)


def test_log_response_is_the_true_plants_response():
    """The H1 estimate of a simulated closed-loop log (the toolkit's sampled simulator, truth
    known) against the true plant's sampled response: where the coherence is high they agree;
    the comparison sees a one-sample delay (so a pairing off by a sample would fail)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec, truth = fit_record(1.0, seed=1)
    f, g, coh = log_response(rec)
    assert np.all((coh >= 0) & (coh <= 1))
    assert f[0] > 0
    assert f[-1] <= 0.45 / rec.sample_time_s
    good = coh > 0.9
    assert np.count_nonzero(good) >= 20
    kw = dict(speed_rad_s=float(np.mean(rec.speed_rad_s)), load_n=float(np.mean(rec.axial_load_n)),
              sample_time_s=rec.sample_time_s)
    err = np.log(g[good] / frf_response(truth, f[good], delay_samples=0, **kw))
    assert np.median(np.abs(err.real)) * 20 / np.log(10) < 0.6  # dB
    assert np.degrees(np.median(np.abs(err.imag))) < 3.0
    late = np.angle(g[good] / frf_response(truth, f[good], delay_samples=1, **kw))
    assert np.degrees(np.median(np.abs(late))) > 15.0
    short = type(rec)(**{**rec.__dict__, "time_s": rec.time_s[:200], "torque_command_n_m": rec.torque_command_n_m[:200],
                         "nut_angle_rad": rec.nut_angle_rad[:200], "axial_load_n": rec.axial_load_n[:200]})
    assert log_response(short) is None  # under 256 samples: no spectral estimate


def test_record_response_figure_is_the_logs_h1_beside_the_written_plant():
    """fit_figures(..., records=...): each record's -frf figure draws log_response's estimate and
    the written plant's response (computed here independently), coherence below, axis in Hz."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec, truth = fit_record(0.5, seed=2)
    res = FitResult(plant=truth, parameters={}, reflected_inertia_kg_m2={}, correlation=np.zeros((0, 0)), keys=(),
                    fit_percent={rec.name: 99.0}, warnings=[], solver={"command_delay": {"shift_samples": 1}},
                    traces={rec.name: _record_trace(n=rec.n - 1)})
    figs = fit_figures(res, records=[rec])
    assert sorted(figs) == ["sim-0-fit", "sim-0-frf"]  # stems of "sim-0.5s", as figure_names says
    assert figure_names([rec.name], log_responses=True) == ["sim-0-fit", "sim-0-frf"]
    f, g, coh = log_response(rec)
    model = frf_response(truth, f, speed_rad_s=float(np.mean(rec.speed_rad_s)),
                         load_n=float(np.mean(rec.axial_load_n)), sample_time_s=rec.sample_time_s, delay_samples=1)
    ax_mag, ax_ph, ax_res, ax_coh = figs["sim-0-frf"].axes[:4]
    data, line = ax_mag.get_lines()[:2]
    np.testing.assert_array_equal(data.get_xdata(), f)
    np.testing.assert_allclose(data.get_ydata(), 20 * np.log10(np.abs(g)), rtol=1e-12)
    np.testing.assert_allclose(line.get_ydata(), 20 * np.log10(np.abs(model)), rtol=1e-9)
    assert line.get_label().startswith("plant as written (linearised at")
    np.testing.assert_array_equal(ax_coh.get_lines()[0].get_ydata(), coh)
    assert ax_coh.get_xlabel() == "frequency (Hz)"
    assert "the log's response" in ax_mag.get_title()
    assert fit_figures(res).keys() == {"sim-0-fit"}  # no records given: no response figure


def test_fit_figures_show_a_file_name_as_typed(tmp_path):
    """Text from the user's file names is data: a '$...$' in a log's name and in the diagnosis is
    drawn as it is, not parsed as mathtext (an invalid expression would fail the save)."""
    name = r"a$\frac$b.csv"
    v = {**_validation(False), "diagnosis": f"second mass: 80 % of the replay residual of {name}"}
    v["written_plant"] = {name: v["written_plant"]["a.csv"]}
    fr = _frf_trace()
    fr["models"] = {r"rigid $\frac$ (75.0 %)": fr["models"]["rigid (75.0 %)"]}
    res = _fit_result({name: _record_trace(n=400), r"b$\x$.csv": fr}, {"validation": v}, {name: 31.5})
    figs = fit_figures(res)
    try:
        for fig in figs.values():
            fig.savefig(tmp_path / "x.png")
        assert name in figs["a_frac_b-fit"].axes[0].get_title().replace("\\$", "$")
    finally:
        for fig in figs.values():
            plt.close(fig)


@pytest.mark.parametrize("closed", [True, False])
def test_axis_replay_figure_names_its_replay_and_draws_the_residual(closed):
    """The linear-axis overlay (prsa-fit --log-format ... --plots): measured against replayed
    position error, velocity and force, the replay named (closed loop from the reference or
    open loop from the command), and the velocity residual below."""
    t = np.linspace(0, 1, 501)
    ref = 0.01 * np.sin(2 * np.pi * t)
    pm, ps = ref - 1e-5 * np.cos(9 * t), ref - 1.2e-5 * np.cos(9 * t)
    vm, vs = np.gradient(pm, t), np.gradient(ps, t) + 1e-4
    fm, fs = 20 * np.sin(3 * t), 21 * np.sin(3 * t)
    r = AxisReplay("logs/a$b.mat", closed, t, pm, ps, vm, vs, fm, fs, {"position": 1.0, "velocity": 2.0, "force": 3.0},
                   {"position": 99.0, "velocity": 98.0, "force": 97.0}, ref if closed else None)
    fig = axis_replay_figure(r)
    try:
        ax = fig.axes
        how = "closed-loop replay from the reference" if closed else "open-loop replay from the logged command"
        assert [ln.get_label() for ln in ax[1].get_lines()] == ["measured", how]
        base = ref if closed else np.mean(pm)
        np.testing.assert_allclose(ax[0].get_lines()[1].get_ydata(), 1e6 * (base - ps))
        np.testing.assert_array_equal(ax[1].get_lines()[1].get_ydata(), vs)
        np.testing.assert_array_equal(ax[2].get_lines()[0].get_ydata(), fm)
        np.testing.assert_allclose(ax[3].get_lines()[0].get_ydata(), vm - vs)
        assert ax[3].get_ylabel() == "velocity residual, m/s"
        title = fig._suptitle.get_text()
        assert how in title
        assert "a\\$b.mat" in title
        assert "velocity 2 %" in title
    finally:
        plt.close(fig)


def test_axis_response_figure_puts_the_logs_response_beside_the_replays_on_a_hz_axis():
    """The linear-axis frequency-response overlay: force -> velocity of the log (H1) against the
    known response of the filter that made it (written here), beside the replay's through the same
    estimator, their residual in dB, the coherence; None for a log too short to estimate."""
    rng = np.random.default_rng(4)
    n, h = 8192, 1e-3
    t = np.arange(n) * h
    fm = rng.standard_normal(n) * 50.0
    fs = fm.copy()
    pm, ps = 0.9, 0.8  # first-order responses, m/s per N: 0.01 (1 - p) / (1 - p z^-1)
    vm = lfilter([0.01 * (1 - pm)], [1.0, -pm], fm)
    vs = lfilter([0.01 * (1 - ps)], [1.0, -ps], fs)
    zero = np.zeros(n)
    r = AxisReplay("a.mat", True, t, zero, zero, vm, vs, fm, fs, {"position": 1.0, "velocity": 1.0, "force": 1.0},
                   {"position": 99.0, "velocity": 99.0, "force": 99.0}, zero)
    fig = axis_response_figure(r)
    try:
        ax = fig.axes
        assert ax[-1].get_xlabel() == "frequency (Hz)"
        assert ax[0].get_xscale() == "log"
        f, mag_data = ax[0].get_lines()[0].get_xdata(), ax[0].get_lines()[0].get_ydata()
        mag_replay = ax[0].get_lines()[1].get_ydata()
        zi = np.exp(-2j * np.pi * f * h)
        truth_m = 20 * np.log10(np.abs(0.01 * (1 - pm) / (1 - pm * zi)))
        truth_s = 20 * np.log10(np.abs(0.01 * (1 - ps) / (1 - ps * zi)))
        # H1 with a Hann window on a noise-free filter: leakage bias up to ~0.25 dB at the lowest bins,
        # far below the 0.9 vs 0.8 filters' difference (up to 5.6 dB, which swapped lines would show)
        for mag, truth in ((mag_data, truth_m), (mag_replay, truth_s)):
            assert np.max(np.abs(mag - truth)) < 0.5
            assert np.median(np.abs(mag - truth)) < 0.02  # dB
        assert np.max(np.abs(truth_m - truth_s)) > 5.0
        assert f.max() <= 0.45 / h
        assert f.min() > 0
        np.testing.assert_allclose(ax[2].get_lines()[0].get_ydata(), mag_data - mag_replay, atol=1e-9)
        assert np.all(ax[3].get_lines()[0].get_ydata() > 0.99)  # noise-free: coherent
        assert "data beside the closed-loop replay" in fig._suptitle.get_text()
    finally:
        plt.close(fig)
    short = AxisReplay("s.mat", True, t[:200], zero[:200], zero[:200], vm[:200], vs[:200], fm[:200], fs[:200],
                       r.errors_percent, r.fit_percent, zero[:200])
    assert axis_response_figure(short) is None
