import numpy as np
import pytest

from prsa_ctrl import load_plant, linearize
from prsa_ctrl.autotune import Design, _predict, actuator_loops, verify
from prsa_ctrl.cli import plot_main
from prsa_ctrl.controller import PID
from prsa_ctrl.paper import gain_study
from prsa_ctrl.plots import (bode_loop, bode_plant, contact_force_plot, gain_study_plot, load_step_comparison,
                             load_step_plot, sensitivity_plot, step_response_plot, tuning_landscape)
from prsa_ctrl.scene import load_scene


@pytest.fixture(scope="module")
def setup():
    plant = load_plant()
    scene = load_scene().replace(duration=0.3)
    loops = actuator_loops(plant, scene)
    designs = []
    for name, pid in (("a", PID(0.085, 14.7)), ("b", PID(0.127, 15.9))):
        d = Design(name, pid, loops[0].margins(pid.gains))
        _predict(d, loops, plant, scene)
        designs.append(verify(d, plant, scene))
    return plant, scene, loops, designs


def _labels(ax):
    return [line.get_label() for line in ax.get_lines()]


def test_bode_plant_has_two_paths(setup):
    plant, scene, *_ = setup
    fig, axs = bode_plant(linearize(plant, scene.setpoint_rad_s, 500.0))
    assert len(axs) == 2 and len(axs[0].get_lines()) == 2
    assert "dB" in axs[0].get_ylabel() and "rad/s" in axs[1].get_xlabel()


def test_loop_plots_mark_margins(setup):
    _, scene, loops, designs = setup
    lp, d = loops[0], designs[0]
    L = lp.loop_response(d.pid.gains)
    fig, axs = bode_loop(lp.omega, L, d.margins)
    texts = [t.get_text() for a in axs for t in a.texts]
    assert any(t.startswith("PM") for t in texts) and any(t.startswith("GM") for t in texts)
    fig, (ax,) = sensitivity_plot(lp.omega, L, scene.ms_max)
    assert {"|S|", "|T|"} <= set(_labels(ax))
    assert any(t.get_text().startswith("Ms = ") for t in ax.texts)


def test_load_step_plots(setup):
    _, scene, _, designs = setup
    fig, (ax,) = load_step_plot(designs[0], scene)
    assert {"verified (nonlinear)", "predicted (linear)"} <= set(_labels(ax))
    assert "IAE" in ax.texts[-1].get_text()
    fig, (ax,) = load_step_comparison(designs, scene)
    assert len([l for l in _labels(ax) if "IAE" in l]) == 2


def test_landscape_marks_optimum_and_baselines(setup):
    _, scene, loops, designs = setup
    fig, (ax,) = tuning_landscape(loops[0], "iae", 1.4, designs[0].pid, [("b", designs[1].pid)], n=8)
    labels = _labels(ax)
    assert "optimum" in labels and "b" in labels and any("Ms = 1.4" in l for l in labels)
    assert ax.get_xscale() == "log" and "kp" in ax.get_xlabel()


def test_gain_contact_and_step_plots(setup):
    plant, *_ = setup
    runs = gain_study(plant, "kp", (0.5, 1.0), duration=0.22)
    assert runs[1].metrics.peak_drop_rad_s < runs[0].metrics.peak_drop_rad_s  # paper trend: higher Kp, smaller drop
    fig, (ax,) = gain_study_plot([(r.label, r.time, r.speed) for r in runs], 31.4, "Effect of kp")
    assert len(ax.get_lines()) == 3  # two runs and the setpoint
    t = np.linspace(0, 1, 11)
    fig, (ax,) = contact_force_plot(t, {"contact_force_nut": t, "contact_force_screw": 2 * t})
    assert _labels(ax) == ["nut-roller", "screw-roller"] and "N" in ax.get_ylabel()
    fig, (ax,) = step_response_plot(t, t, t, t, setpoint=1.0)
    assert _labels(ax) == ["nonlinear", "linear", "setpoint"]


def test_functions_draw_into_given_axes(setup):
    import matplotlib.pyplot as plt

    _, scene, _, designs = setup
    fig, ax = plt.subplots()
    f2, (a2,) = load_step_plot(designs[0], scene, ax=ax)
    assert f2 is fig and a2 is ax


def test_prsa_plot_command(tmp_path, capsys):
    rc = plot_main(["--kp", "0.085", "--ki", "14.7", "--out", str(tmp_path)])
    assert rc == 0
    names = {p.stem for p in tmp_path.glob("*.png")}
    assert names == {"plant_bode", "loop_bode", "sensitivity", "load_step", "setpoint_step"}
    assert plot_main(["--kp", "50", "--ki", "1", "--out", str(tmp_path / "x")]) == 2
    assert "unstable" in capsys.readouterr().err
