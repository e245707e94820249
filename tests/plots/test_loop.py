"""prsa_ctrl.plots.loop: the frequency axes of the Bode and sensitivity figures are in Hz by
default and in rad/s on request (issue 33); the data checked against crossovers computed
independently of the figures."""

import math
import re

import numpy as np
import pytest

from prsa_ctrl.options import FREQUENCY_UNITS
from prsa_ctrl.plots import loop as loop_plots
from prsa_ctrl.plots.loop import bode_loop, bode_plant, sensitivity_plot

K, A = 2.0e4, 150.0  # L(s) = K / (s (s + A)): |L(j w)| = 1 at w^2 = (sqrt(A^4 + 4 K^2) - A^2) / 2
WC_RAD_S = math.sqrt((math.sqrt(A**4 + 4 * K**2) - A**2) / 2)


@pytest.fixture(autouse=True)
def _close_figures():
    import matplotlib.pyplot as plt

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
    assert x[0] == pytest.approx(0.1 / (2 * math.pi)) and x[-1] == pytest.approx(1e5 / (2 * math.pi))


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
