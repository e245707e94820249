import json
import math

import numpy as np
import pytest

from prsa_ctrl import load_plant, linearize
from prsa_ctrl.studies.autotune import Design, actuator_loops, predict, verify
from prsa_ctrl.cli.plot import plot_main
from prsa_ctrl.drive.pid import PID
from prsa_ctrl.studies.paper import gain_study
from prsa_ctrl.plots.loop import (baseline_pairs_plot, binding_level, bode_loop, bode_plant, contact_force_plot,
                             gain_study_plot, load_step_comparison, load_step_plot, sensitivity_plot,
                             step_response_plot, tuning_landscape)
from prsa_ctrl.studies.scene import load_scene
from prsa_ctrl.identification.common import FitResult
import matplotlib.pyplot as plt


@pytest.fixture(scope="module")
def setup():
    plant = load_plant()
    scene = load_scene().replace(duration=0.3)
    loops = actuator_loops(plant, scene)
    designs = []
    for name, pid in (("tuned (Ms <= 1.4)", PID(0.085, 14.7)), ("b", PID(0.127, 15.9))):
        d = predict(Design(name, pid, loops[0].margins(pid.gains)), loops, plant, scene)
        designs.append(verify(d, plant, scene))
    return plant, scene, loops, designs


@pytest.fixture(scope="module")
def multi():
    """One design verified on two load levels, ITAE objective."""
    plant = load_plant()
    scene = load_scene().replace(duration=0.28, final_loads=(1000.0, 2500.0), objective="itae")
    loops = actuator_loops(plant, scene)
    pid = PID(0.085, 14.7)
    d = predict(Design("tuned (Ms <= 1.4)", pid, loops[0].margins(pid.gains)), loops, plant, scene)
    return plant, scene, loops, verify(d, plant, scene)


def _labels(ax):
    return [line.get_label() for line in ax.get_lines()]


def _overlaps_line(text, line) -> bool:
    """Whether any vertex of ``line`` lies inside the drawn box of ``text`` (display pixels)."""
    fig = text.figure
    fig.canvas.draw()
    box = text.get_window_extent()
    xy = line.get_transform().transform(np.column_stack(line.get_data()))
    inside = (xy[:, 0] >= box.x0) & (xy[:, 0] <= box.x1) & (xy[:, 1] >= box.y0) & (xy[:, 1] <= box.y1)
    return bool(inside.any())


def test_bode_plant_has_two_paths_operating_point_and_nyquist(setup):
    plant, scene, *_ = setup
    fig, axs = bode_plant(linearize(plant, scene.setpoint_rad_s, 500.0), sample_time_s=plant.sample_time_s)
    assert len(axs) == 2 and len([l for l in _labels(axs[0]) if l.startswith("nut speed")]) == 2
    assert "dB" in axs[0].get_ylabel() and "Hz" in axs[1].get_xlabel()  # issue 33: Hz by default (tests/plots/test_loop.py)
    assert "300 rpm, 500 N" in axs[0].get_title()  # operating point in the title
    nyq = [l for l in axs[0].get_lines() if l.get_label().startswith("Nyquist")]
    assert len(nyq) == 1 and nyq[0].get_xdata()[0] == pytest.approx(0.5 / plant.sample_time_s)  # 1/(2 Ts) Hz


def test_loop_plots_mark_margins_without_overlap(setup):
    plant, scene, loops, designs = setup
    lp, d = loops[0], designs[0]
    L = lp.loop_response(d.pid.gains)
    fig, axs = bode_loop(lp.omega, L, d.margins, operating_point="300 rpm, 1000 N", sample_time_s=plant.sample_time_s)
    texts = {t.get_text().split()[0]: t for a in axs for t in a.texts}
    assert {"PM", "GM"} <= set(texts) and "300 rpm, 1000 N" in axs[0].get_title()
    curve_mag, curve_phase = axs[0].get_lines()[0], axs[1].get_lines()[0]
    assert not _overlaps_line(texts["PM"], curve_phase)  # the label sits off the curve
    assert not _overlaps_line(texts["GM"], curve_mag)


def test_sensitivity_plot_absolute_with_bounds_on_the_same_scale(setup):
    _, scene, loops, designs = setup
    lp = loops[0]
    L = lp.loop_response(designs[0].pid.gains)
    fig, (ax,) = sensitivity_plot(lp.omega, L, scene.ms_max, mt_max=1.3)
    labels = _labels(ax)
    ms = np.max(np.abs(1 / (1 + L)))
    assert any(l.startswith(f"|S|: Ms = {ms:.3f}") for l in labels) and any(l.startswith("|T|: Mt = ") for l in labels)
    bounds = {l.get_label(): l.get_ydata()[0] for l in ax.get_lines() if "bound" in l.get_label()}
    assert bounds == {"Ms bound 1.4": 1.4, "Mt bound 1.3": 1.3}  # absolute, same scale as |S|
    assert ax.get_yscale() == "log" and ax.get_ylim()[1] > max(ms, 1.4) and not ax.texts


def test_load_step_plot_has_torque_panel_and_fitted_range(setup):
    plant, scene, _, designs = setup
    fig, (ax, at) = load_step_plot(designs[0], scene, torque_limit=plant.torque_limit)
    assert {"verified (nonlinear)", "predicted (linear)"} <= set(_labels(ax))
    assert any(l.startswith("motor torque") for l in _labels(at)) and "N m" in at.get_ylabel()
    assert "IAE" in ax.texts[-1].get_text()
    t, _ = designs[0].verified_runs[0]
    lo, hi = ax.get_xlim()
    assert t[0] <= lo and hi <= t[-1]  # never wider than the data
    assert not _overlaps_line(ax.texts[-1], ax.get_lines()[0])  # metrics box off the response


def test_load_step_plot_shows_every_level_and_highlights_the_binding_one(multi):
    plant, scene, _, d = multi
    kb = binding_level(d, scene)
    assert kb == int(np.argmax([m.itae for m in d.verified])) == 1  # the larger step binds
    fig, (ax, at) = load_step_plot(d, scene, k=None)
    verified = [l for l in ax.get_lines() if l.get_label().startswith("verified")]
    assert len(verified) == 2
    bind = [l for l in verified if "(binding)" in l.get_label()]
    assert len(bind) == 1 and "2500 N" in bind[0].get_label()
    assert bind[0].get_linewidth() > max(l.get_linewidth() for l in verified if l is not bind[0])
    assert "ITAE" in ax.texts[-1].get_text() and "2500 N" in ax.get_title()


def test_comparison_labels_name_the_objective_without_doubled_brackets(setup, multi):
    _, scene, _, designs = setup
    fig, (ax,) = load_step_comparison(designs, scene)
    labels = [l for l in _labels(ax) if "IAE" in l]
    assert len(labels) == 2 and labels[0].startswith("tuned (Ms <= 1.4): Ms ")
    assert not any(") (" in l or "((" in l for l in labels)
    _, sc2, _, d2 = multi
    fig, (ax,) = load_step_comparison([d2], sc2, k=1)
    assert "ITAE" in _labels(ax)[0] and "IAE " not in _labels(ax)[0].replace("ITAE", "")


def test_baseline_pairs_plot_draws_each_baseline_with_its_equal_ms_design(setup):
    _, scene, _, designs = setup
    a, b = designs
    fig, axs = baseline_pairs_plot([(b, a), (a, b)], scene)
    assert len(axs) == 2
    for ax, (base, ours) in zip(axs, [(b, a), (a, b)]):
        names = [l.split(":")[0] for l in _labels(ax) if ":" in l]
        assert names == [base.name, ours.name] and f": Ms {base.margins.ms:.2f}, load" in ax.get_title()
        assert ") (" not in ax.get_title()


def test_landscape_marks_optimum_baselines_and_bounds(setup):
    _, scene, loops, designs = setup
    fig, (ax,) = tuning_landscape(loops[0], "iae", 1.4, designs[0].pid, [("b", designs[1].pid)], n=8)
    labels = _labels(ax)
    assert "optimum" in labels and "b" in labels and any("Ms = 1.4" in l for l in labels)
    assert not any("Mt" in l for l in labels)
    assert ax.get_xscale() == "log" and "kp" in ax.get_xlabel()
    assert any(p.get_hatch() == "//" for p in ax.patches)  # unstable background, no white strip
    fig, (ax,) = tuning_landscape(loops, "iae", 1.4, designs[0].pid, n=8, mt_max=1.3, aggregate="worst")
    assert any("Mt = 1.3" in l for l in _labels(ax))


def test_gain_contact_and_step_plots(setup):
    plant, *_ = setup
    runs = gain_study(plant, "kp", (0.5, 1.0), duration=0.22)
    assert runs[1].metrics.peak_drop_rad_s < runs[0].metrics.peak_drop_rad_s  # paper trend: higher Kp, smaller drop
    fig, (ax,) = gain_study_plot([(r.label, r.time, r.speed) for r in runs], 31.4, "Effect of kp")
    assert len(ax.get_lines()) == 3  # two runs and the setpoint
    t = np.linspace(0, 1, 11)
    fig, (ax, ad) = contact_force_plot(t, {"contact_force_nut": 3 * t, "contact_force_screw": 2 * t}, static=(3.0, 2.0))
    labels = _labels(ax)
    assert labels[:2] == ["nut-roller", "screw-roller"] and "N" in ax.get_ylabel()
    assert {l.get_linestyle() for l in ax.get_lines()[:2]} == {"-", "--"}  # distinguishable
    assert [l.get_ydata()[0] for l in ax.get_lines()[2:]] == [3.0, 2.0]  # static means
    assert np.allclose(ad.get_lines()[0].get_ydata(), t)  # nut minus screw
    fig, (ax,) = step_response_plot(t, t, t, t, setpoint=1.0)
    assert _labels(ax) == ["nonlinear", "linear", "setpoint"]


def test_functions_draw_into_given_axes(setup):
    import matplotlib.pyplot as plt

    _, scene, _, designs = setup
    fig, ax = plt.subplots()
    f2, (a2,) = load_step_plot(designs[0], scene, ax=ax)
    assert f2 is fig and a2 is ax
    t = np.linspace(0, 1, 11)
    f3, (a3,) = contact_force_plot(t, {"contact_force_nut": t, "contact_force_screw": t}, ax=ax)
    assert a3 is ax


@pytest.fixture(autouse=True)
def _close_figures():
    import matplotlib.pyplot as plt

    yield
    plt.close("all")


def test_prsa_plot_command(tmp_path, capsys):
    rc = plot_main(["--kp", "0.085", "--ki", "14.7", "--out", str(tmp_path)])
    assert rc == 0
    names = {p.stem for p in tmp_path.glob("*.png")}
    assert names == {"plant_bode", "loop_bode", "sensitivity", "load_step", "setpoint_step"}
    out = capsys.readouterr().out
    assert "Margins: Ms 1.4" in out and "crossover" in out
    # Unstable gains are plotted with a warning (frequency plots only), not refused.
    assert plot_main(["--kp", "50", "--ki", "1", "--out", str(tmp_path / "x")]) == 0
    assert "UNSTABLE" in capsys.readouterr().out
    assert {p.stem for p in (tmp_path / "x").glob("*.png")} == {"plant_bode", "loop_bode", "sensitivity"}


def test_bode_figure_shows_data_models_and_residual():
    import matplotlib.pyplot as plt

    from prsa_ctrl.identification.common import FitResult
    from prsa_ctrl.plots.fit import fit_figures

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
        assert ax_res.get_xlabel() == "frequency (Hz)" and ax_mag.get_xscale() == "log"
        res_db = ax_res.get_lines()[0].get_ydata()
        assert np.allclose(res_db, 20 / np.log(10) * 0.01 * np.sin(np.arange(80)), atol=1e-9)
        assert "structure: two-mass" in ax_mag.get_title()
    finally:
        plt.close(fig)


# ---- prsa_ctrl.plots.fit: the fit's figures and views draw the result's own arrays (the replay
# of the plant as written, its residual, the frequency responses beside the fitted models, the
# coherence) on a Hz axis (rad/s on request), with the verdict; log_response checked against the
# true plant's response.

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
    from prsa_ctrl.plots.fit import fit_figures

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
        assert ax2.get_ylabel() == "residual (rad/s)" and ax2.get_xlabel() == "time (s)"
        assert "replay fit 31.5 %" in ax1.get_title() and "NOT explained" in ax1.get_title()
        assert "20 x noise floor" in ax1.get_title()  # 2.0 / 0.1
        assert "lag 1 +0.73" in ax2.get_title() and "not white" in ax2.get_title()
        caption = " ".join(t.get_text() for t in fig.texts)
        assert "NOT validated" in caption and "second mass" in caption  # a refusal, never "good"
    finally:
        plt.close(fig)
    fig = fit_figures(_fit_result({"a.csv": tr}, {"validation": _validation(True)}, {"a.csv": 99.0}))["a-fit"]
    try:
        assert "explained" in fig.axes[0].get_title() and "NOT" not in fig.axes[0].get_title()
        assert "the plant explains the data" in " ".join(t.get_text() for t in fig.texts)
    finally:
        plt.close(fig)


@pytest.mark.parametrize("unit, factor", [("Hz", 1.0), ("rad/s", 2 * math.pi)])
def test_bode_figure_data_models_residual_and_coherence_in_the_unit(unit, factor):
    from prsa_ctrl.plots.fit import fit_figures

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
        assert ax_coh.get_ylabel() == "coherence" and ax_coh.get_xlabel() == f"frequency ({unit})"
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
    from prsa_ctrl.plots.fit import fit_figures

    with pytest.raises(ValueError, match=r"frequency unit 'kHz'; expected one of Hz, rad/s"):
        fit_figures(_fit_result({"b.csv": _frf_trace()}), frequency_unit="kHz")


def test_fit_views_are_the_results_arrays():
    from prsa_ctrl.plots.fit import fit_views

    tr, fr = _record_trace(n=4501), _frf_trace()
    tr["simulated"]["model"][6] = np.nan  # no NaN reaches a reader: None
    res = _fit_result({"a.csv": tr, "b.csv": fr}, {"validation": _validation(False)}, {"a.csv": 31.5, "b.csv": 97.0})
    v = fit_views(res, max_points=2000)
    json.dumps(v, allow_nan=False)  # JSON-ready, every number finite or None
    assert v["verdict"] == {"validated": False, "diagnosis": _validation(False)["diagnosis"],
                            "reasons": _validation(False)["reasons"], "replay": "closed loop"}
    r = v["replay"]["a.csv"]
    assert r["every"] == 3 and r["mode"] == "closed-loop" and r["label"] == CLOSED  # ceil(4501 / 2000)
    idx = np.arange(0, 4501, 3)
    sim = tr["simulated"]
    for key, a in (("time_s", sim["time_s"]), ("measured_rad_s", sim["measured"]), ("model_rad_s", sim["model"]),
                   ("residual_rad_s", sim["measured"] - sim["model"])):
        got = np.array([np.nan if x is None else x for x in r[key]])
        np.testing.assert_array_equal(got, a[idx])
    assert r["model_rad_s"][2] is None and r["residual_rad_s"][2] is None and r["model_rad_s"][1] is not None
    assert r["explained"] is False and r["fit_percent"] == 31.5 and r["whiteness"]["acf"][1] == 0.734
    f = v["frf"]["b.csv"]
    np.testing.assert_array_equal(f["frequency_hz"], fr["frequency_hz"])
    np.testing.assert_allclose(f["measured"]["magnitude_db"], 20 * np.log10(np.abs(fr["measured"])), rtol=1e-12)
    assert [(k, m["written"]) for k, m in f["models"].items()] == [
        ("rigid (75.0 %)", False), ("two-mass (98.0 %)", False), ("fitted plant as written", True)]
    np.testing.assert_allclose(f["models"]["rigid (75.0 %)"]["magnitude_db"],
                               20 * np.log10(np.abs(fr["models"]["rigid (75.0 %)"])), rtol=1e-12)
    np.testing.assert_allclose(f["residual"]["magnitude_db"], 20 / np.log(10) * 0.01 * np.sin(np.arange(80)), atol=1e-9)
    np.testing.assert_array_equal(f["coherence"], fr["coherence"])
    assert f["chosen"] == "two-mass" and f["fit_percent"] == 97.0
    # phases on the written model's branch: the data's own angle, within half a turn of the model
    ph, ref = np.radians(f["measured"]["phase_deg"]), np.radians(f["models"]["fitted plant as written"]["phase_deg"])
    np.testing.assert_allclose(np.exp(1j * ph), fr["measured"] / np.abs(fr["measured"]), atol=1e-12)
    np.testing.assert_allclose(np.exp(1j * ref), fr["model"] / np.abs(fr["model"]), atol=1e-12)
    assert np.all(np.abs(ph - ref) <= np.pi + 1e-12) and np.all(np.abs(np.diff(ref)) < np.pi)
    short = fit_views(_fit_result({"a.csv": _record_trace(n=300)}))
    assert short["replay"]["a.csv"]["every"] == 1 and len(short["replay"]["a.csv"]["time_s"]) == 300
    assert short["verdict"]["validated"] is None  # no validation ran: not "validated"
    with pytest.raises(ValueError, match="max_points = 1; expected an integer >= 2"):
        fit_views(res, max_points=1)


def test_log_response_is_the_true_plants_response():
    """The H1 estimate of a simulated closed-loop log (the toolkit's sampled simulator, truth
    known) against the true plant's sampled response: where the coherence is high they agree;
    the comparison sees a one-sample delay (so a pairing off by a sample would fail)."""
    import warnings

    from prsa_ctrl.identification.frf import frf_response
    from prsa_ctrl.identification.synthetic import fit_record
    from prsa_ctrl.plots.fit import log_response

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec, truth = fit_record(1.0, seed=1)
    f, g, coh = log_response(rec)
    assert np.all((coh >= 0) & (coh <= 1)) and f[0] > 0 and f[-1] <= 0.45 / rec.sample_time_s
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
    import warnings

    from prsa_ctrl.identification.frf import frf_response
    from prsa_ctrl.identification.synthetic import fit_record
    from prsa_ctrl.plots.fit import fit_figures, log_response

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec, truth = fit_record(0.5, seed=2)
    res = FitResult(plant=truth, parameters={}, reflected_inertia_kg_m2={}, correlation=np.zeros((0, 0)), keys=(),
                    fit_percent={rec.name: 99.0}, warnings=[], solver={"command_delay": {"shift_samples": 1}},
                    traces={rec.name: _record_trace(n=rec.n - 1)})
    figs = fit_figures(res, records=[rec])
    assert sorted(figs) == ["sim-0-fit", "sim-0-frf"]  # stems of "sim-0.5s", as figure_names says
    from prsa_ctrl.plots.fit import figure_names

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
    assert ax_coh.get_xlabel() == "frequency (Hz)" and "the log's response" in ax_mag.get_title()
    assert fit_figures(res).keys() == {"sim-0-fit"}  # no records given: no response figure


def test_fit_figures_show_a_file_name_as_typed(tmp_path):
    """Text from the user's file names is data: a '$...$' in a log's name and in the diagnosis is
    drawn as it is, not parsed as mathtext (an invalid expression would fail the save)."""
    from prsa_ctrl.plots.fit import fit_figures

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
    from prsa_ctrl.identification.axis import AxisReplay
    from prsa_ctrl.plots.fit import axis_replay_figure

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
        assert how in title and "a\\$b.mat" in title and "velocity 2 %" in title
    finally:
        plt.close(fig)


def test_axis_response_figure_puts_the_logs_response_beside_the_replays_on_a_hz_axis():
    """The linear-axis frequency-response overlay: force -> velocity of the log (H1) against the
    known response of the filter that made it (written here), beside the replay's through the same
    estimator, their residual in dB, the coherence; None for a log too short to estimate."""
    from scipy.signal import lfilter

    from prsa_ctrl.identification.axis import AxisReplay
    from prsa_ctrl.plots.fit import axis_response_figure

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
        assert ax[-1].get_xlabel() == "frequency (Hz)" and ax[0].get_xscale() == "log"
        f, mag_data = ax[0].get_lines()[0].get_xdata(), ax[0].get_lines()[0].get_ydata()
        mag_replay = ax[0].get_lines()[1].get_ydata()
        zi = np.exp(-2j * np.pi * f * h)
        truth_m = 20 * np.log10(np.abs(0.01 * (1 - pm) / (1 - pm * zi)))
        truth_s = 20 * np.log10(np.abs(0.01 * (1 - ps) / (1 - ps * zi)))
        # H1 with a Hann window on a noise-free filter: leakage bias up to ~0.25 dB at the lowest bins,
        # far below the 0.9 vs 0.8 filters' difference (up to 5.6 dB, which swapped lines would show)
        for mag, truth in ((mag_data, truth_m), (mag_replay, truth_s)):
            assert np.max(np.abs(mag - truth)) < 0.5 and np.median(np.abs(mag - truth)) < 0.02  # dB
        assert np.max(np.abs(truth_m - truth_s)) > 5.0
        assert f.max() <= 0.45 / h and f.min() > 0
        np.testing.assert_allclose(ax[2].get_lines()[0].get_ydata(), mag_data - mag_replay, atol=1e-9)
        assert np.all(ax[3].get_lines()[0].get_ydata() > 0.99)  # noise-free: coherent
        assert "data beside the closed-loop replay" in fig._suptitle.get_text()
    finally:
        plt.close(fig)
    short = AxisReplay("s.mat", True, t[:200], zero[:200], zero[:200], vm[:200], vs[:200], fm[:200], fs[:200],
                       r.errors_percent, r.fit_percent, zero[:200])
    assert axis_response_figure(short) is None
