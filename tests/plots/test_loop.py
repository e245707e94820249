"""prsa_ctrl.plots.loop: the frequency axes of the Bode and sensitivity figures are in Hz by
default and in rad/s on request (issue 33); the data checked against crossovers computed
independently of the figures. The figures of a tuned and verified design: margins marked off the
curves, absolute sensitivity bounds, the binding load level highlighted, labels naming the
objective, the tuning landscape, the gain-study, contact-force and step figures."""

import math
import re

import matplotlib.pyplot as plt
import numpy as np
import pytest

from prsa_ctrl import linearize, load_plant
from prsa_ctrl.drive.pid import PID
from prsa_ctrl.options import FREQUENCY_UNITS
from prsa_ctrl.plots import loop as loop_plots
from prsa_ctrl.plots.loop import (baseline_pairs_plot, binding_level, bode_loop, bode_plant, contact_force_plot,
                                  gain_study_plot, load_step_comparison, load_step_plot, sensitivity_plot,
                                  step_response_plot, tuning_landscape)
from prsa_ctrl.studies.autotune import Design, actuator_loops, predict, verify
from prsa_ctrl.studies.paper import gain_study
from prsa_ctrl.studies.scene import load_scene

K, A = 2.0e4, 150.0  # L(s) = K / (s (s + A)): |L(j w)| = 1 at w^2 = (sqrt(A^4 + 4 K^2) - A^2) / 2
WC_RAD_S = math.sqrt((math.sqrt(A**4 + 4 * K**2) - A**2) / 2)


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


def _loop(omega):
    s = 1j * omega
    return K / (s * (s + A))


def _zero_db_crossing(line) -> float:
    """Where the plotted magnitude (dB) crosses 0, interpolated in log frequency (axis units)."""
    x, y = (np.asarray(v, float) for v in line.get_data())
    i = int(np.flatnonzero((y[:-1] > 0) & (y[1:] <= 0))[0])
    lx = np.log10(x[i]) + (np.log10(x[i + 1]) - np.log10(x[i])) * y[i] / (y[i] - y[i + 1])
    return float(10**lx)


@pytest.mark.parametrize("unit, per_rad_s", [("Hz", 1 / (2 * math.pi)), ("rad/s", 1.0)])
def test_bode_loop_axis_in_the_unit_asked(unit, per_rad_s):
    omega = np.logspace(0, 4, 4001)
    kwargs = {} if unit == "Hz" else {"frequency_unit": unit}
    fig, axs = bode_loop(omega, _loop(omega), **kwargs)
    assert axs[1].get_xlabel() == f"frequency ({unit})"
    wc_plot = _zero_db_crossing(axs[0].get_lines()[0])
    assert wc_plot == pytest.approx(WC_RAD_S * per_rad_s, rel=1e-4)  # the analytic crossover, in the axis's unit
    pm_line = next(ln for ln in axs[1].get_lines() if ln.get_color() == "C3")
    assert pm_line.get_xdata()[0] == pytest.approx(WC_RAD_S * per_rad_s, rel=1e-3)
    shown = float(re.search(r"crossover (\S+) " + re.escape(unit), axs[0].get_title()).group(1))
    assert shown == pytest.approx(WC_RAD_S * per_rad_s, abs=0.5)


def test_hz_is_the_default_everywhere():
    omega = np.logspace(0, 4, 500)
    _, (ax,) = sensitivity_plot(omega, _loop(omega), sample_time_s=1e-3)
    assert ax.get_xlabel() == "frequency (Hz)"
    nyq = next(ln for ln in ax.get_lines() if ln.get_label().startswith("Nyquist"))
    assert nyq.get_xdata()[0] == pytest.approx(500.0)  # 1/(2 Ts)
    assert np.asarray(ax.get_lines()[0].get_xdata()) == pytest.approx(omega / (2 * math.pi))
    import control

    plant = control.ss([[-1e3]], [[1e3, 1.0]], [[1.0]], [[0.0, 0.0]], inputs=["torque_command", "axial_load"],
                       outputs=["nut_speed"])
    fig, axs = bode_plant(plant)
    assert axs[1].get_xlabel() == "frequency (Hz)"
    x = np.asarray(axs[0].get_lines()[0].get_xdata())
    assert x[0] == pytest.approx(0.1 / (2 * math.pi))
    assert x[-1] == pytest.approx(1e5 / (2 * math.pi))


def test_an_unknown_unit_is_refused_naming_it():
    omega = np.logspace(0, 2, 10)
    with pytest.raises(ValueError, match=r"frequency unit 'kHz'; expected one of Hz, rad/s"):
        bode_loop(omega, _loop(omega), frequency_unit="kHz")
    assert set(FREQUENCY_UNITS) == {"Hz", "rad/s"}


@pytest.mark.parametrize("unit", [None, "rad/s"])
def test_prsa_plot_loop_bode_in_hz_matches_the_printed_crossover(unit, tmp_path, capsys, monkeypatch):
    from prsa_ctrl.cli.plot import plot_main

    drawn = {}
    real = loop_plots._save_all

    def keep(figs, directory):
        drawn.update({name: (fig.axes[0].get_lines()[0], fig.axes[-1].get_xlabel()) for name, fig in figs.items()})
        return real(figs, directory)

    monkeypatch.setattr(loop_plots, "_save_all", keep)
    argv = ["--kp", "0.085", "--ki", "14.7", "--out", str(tmp_path)] + (["--frequency-unit", unit] if unit else [])
    assert plot_main(argv) == 0
    out = capsys.readouterr().out
    wc_rad_s = float(re.search(r"crossover (\S+) rad/s", out).group(1))  # the tuner's margins, printed in rad/s
    line, xlabel = drawn["loop_bode"]
    unit = unit or "Hz"
    assert xlabel == f"frequency ({unit})"
    assert _zero_db_crossing(line) == pytest.approx(wc_rad_s * FREQUENCY_UNITS[unit], rel=2e-3)
    assert drawn["plant_bode"][1] == drawn["sensitivity"][1] == f"frequency ({unit})"


# --- the figures of a tuned and verified design -------------------------------------------

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
    assert len(axs) == 2
    assert len([l for l in _labels(axs[0]) if l.startswith("nut speed")]) == 2
    assert "dB" in axs[0].get_ylabel()
    assert "Hz" in axs[1].get_xlabel()  # issue 33: Hz by default (tests/plots/test_loop.py)
    assert "300 rpm, 500 N" in axs[0].get_title()  # operating point in the title
    nyq = [l for l in axs[0].get_lines() if l.get_label().startswith("Nyquist")]
    assert len(nyq) == 1
    assert nyq[0].get_xdata()[0] == pytest.approx(0.5 / plant.sample_time_s)  # 1/(2 Ts) Hz


def test_loop_plots_mark_margins_without_overlap(setup):
    plant, scene, loops, designs = setup
    lp, d = loops[0], designs[0]
    L = lp.loop_response(d.pid.gains)
    fig, axs = bode_loop(lp.omega, L, d.margins, operating_point="300 rpm, 1000 N", sample_time_s=plant.sample_time_s)
    texts = {t.get_text().split()[0]: t for a in axs for t in a.texts}
    assert {"PM", "GM"} <= set(texts)
    assert "300 rpm, 1000 N" in axs[0].get_title()
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
    assert any(l.startswith(f"|S|: Ms = {ms:.3f}") for l in labels)
    assert any(l.startswith("|T|: Mt = ") for l in labels)
    bounds = {l.get_label(): l.get_ydata()[0] for l in ax.get_lines() if "bound" in l.get_label()}
    assert bounds == {"Ms bound 1.4": 1.4, "Mt bound 1.3": 1.3}  # absolute, same scale as |S|
    assert ax.get_yscale() == "log"
    assert ax.get_ylim()[1] > max(ms, 1.4)
    assert not ax.texts


def test_load_step_plot_has_torque_panel_and_fitted_range(setup):
    plant, scene, _, designs = setup
    fig, (ax, at) = load_step_plot(designs[0], scene, torque_limit=plant.torque_limit)
    assert {"verified (nonlinear)", "predicted (linear)"} <= set(_labels(ax))
    assert any(l.startswith("motor torque") for l in _labels(at))
    assert "N m" in at.get_ylabel()
    assert "IAE" in ax.texts[-1].get_text()
    t, _ = designs[0].verified_runs[0]
    lo, hi = ax.get_xlim()
    assert t[0] <= lo
    assert hi <= t[-1]  # never wider than the data
    assert not _overlaps_line(ax.texts[-1], ax.get_lines()[0])  # metrics box off the response


def test_load_step_plot_shows_every_level_and_highlights_the_binding_one(multi):
    plant, scene, _, d = multi
    kb = binding_level(d, scene)
    assert kb == int(np.argmax([m.itae for m in d.verified])) == 1  # the larger step binds
    fig, (ax, at) = load_step_plot(d, scene, k=None)
    verified = [l for l in ax.get_lines() if l.get_label().startswith("verified")]
    assert len(verified) == 2
    bind = [l for l in verified if "(binding)" in l.get_label()]
    assert len(bind) == 1
    assert "2500 N" in bind[0].get_label()
    assert bind[0].get_linewidth() > max(l.get_linewidth() for l in verified if l is not bind[0])
    assert "ITAE" in ax.texts[-1].get_text()
    assert "2500 N" in ax.get_title()


def test_comparison_labels_name_the_objective_without_doubled_brackets(setup, multi):
    _, scene, _, designs = setup
    fig, (ax,) = load_step_comparison(designs, scene)
    labels = [l for l in _labels(ax) if "IAE" in l]
    assert len(labels) == 2
    assert labels[0].startswith("tuned (Ms <= 1.4): Ms ")
    assert not any(") (" in l or "((" in l for l in labels)
    _, sc2, _, d2 = multi
    fig, (ax,) = load_step_comparison([d2], sc2, k=1)
    assert "ITAE" in _labels(ax)[0]
    assert "IAE " not in _labels(ax)[0].replace("ITAE", "")


def test_baseline_pairs_plot_draws_each_baseline_with_its_equal_ms_design(setup):
    _, scene, _, designs = setup
    a, b = designs
    fig, axs = baseline_pairs_plot([(b, a), (a, b)], scene)
    assert len(axs) == 2
    for ax, (base, ours) in zip(axs, [(b, a), (a, b)]):
        names = [l.split(":")[0] for l in _labels(ax) if ":" in l]
        assert names == [base.name, ours.name]
        assert f": Ms {base.margins.ms:.2f}, load" in ax.get_title()
        assert ") (" not in ax.get_title()


def test_landscape_marks_optimum_baselines_and_bounds(setup):
    _, scene, loops, designs = setup
    fig, (ax,) = tuning_landscape(loops[0], "iae", 1.4, designs[0].pid, [("b", designs[1].pid)], n=8)
    labels = _labels(ax)
    assert "optimum" in labels
    assert "b" in labels
    assert any("Ms = 1.4" in l for l in labels)
    assert not any("Mt" in l for l in labels)
    assert ax.get_xscale() == "log"
    assert "kp" in ax.get_xlabel()
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
    assert labels[:2] == ["nut-roller", "screw-roller"]
    assert "N" in ax.get_ylabel()
    assert {l.get_linestyle() for l in ax.get_lines()[:2]} == {"-", "--"}  # distinguishable
    assert [l.get_ydata()[0] for l in ax.get_lines()[2:]] == [3.0, 2.0]  # static means
    assert np.allclose(ad.get_lines()[0].get_ydata(), t)  # nut minus screw
    fig, (ax,) = step_response_plot(t, t, t, t, setpoint=1.0)
    assert _labels(ax) == ["nonlinear", "linear", "setpoint"]


def test_functions_draw_into_given_axes(setup):
    _, scene, _, designs = setup
    fig, ax = plt.subplots()
    f2, (a2,) = load_step_plot(designs[0], scene, ax=ax)
    assert f2 is fig
    assert a2 is ax
    t = np.linspace(0, 1, 11)
    f3, (a3,) = contact_force_plot(t, {"contact_force_nut": t, "contact_force_screw": t}, ax=ax)
    assert a3 is ax
