"""prsa_ctrl.studies.scenereport (was prsa_ctrl.cli.report): reports an engineer acts on (issue 24, item 5): setpoint-step metrics (overshoot %, 10-90 %
rise time, 2 % settling time) against an independent computation on a known second-order
response; setpoint steps found in a duty-cycle profile (ramps are not steps); no percentage
between a value at numerical zero and a real one; crossover in Hz; one name per design."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from scipy.optimize import brentq

from prsa_ctrl.studies.scenereport import setpoint_table, diff_text
from prsa_ctrl.sim.metrics import profile_metrics, setpoint_step_metrics

ZETA, WN = 0.4, 100.0  # a known underdamped second-order loop


def _second_order(t):
    """Unit step response of wn^2/(s^2 + 2 zeta wn s + wn^2), t >= 0."""
    wd = WN * math.sqrt(1 - ZETA**2)
    phi = math.acos(ZETA)
    return 1 - np.exp(-ZETA * WN * t) / math.sqrt(1 - ZETA**2) * np.sin(wd * t + phi)


def _reference_metrics():
    """Overshoot in closed form; rise and settling times as roots of the analytic response."""
    f = lambda t: float(_second_order(np.array(t)))  # noqa: E731
    overshoot = 100 * math.exp(-math.pi * ZETA / math.sqrt(1 - ZETA**2))
    t_peak = math.pi / (WN * math.sqrt(1 - ZETA**2))
    rise = brentq(lambda t: f(t) - 0.9, 0.0, t_peak) - brentq(lambda t: f(t) - 0.1, 0.0, t_peak)
    # settling: the last time |y - 1| = 0.02 (bracketed on a dense grid, then a root)
    tg = np.linspace(0.0, 0.5, 500001)
    out = np.nonzero(np.abs(_second_order(tg) - 1) > 0.02)[0][-1]
    a, b = tg[out], tg[out + 1]
    g = (lambda t: f(t) - 1 - 0.02) if f(a) > 1 else (lambda t: f(t) - 1 + 0.02)
    return overshoot, rise, brentq(g, a, b, xtol=1e-14)


@pytest.mark.parametrize("w0, dw", [(0.0, 1.0), (31.4, 10.5), (50.0, -7.0)])
def test_second_order_step_against_independent_values(w0, dw):
    t_step, dt = 0.01, 1e-5
    t = np.arange(0.0, 0.3, dt)
    y = w0 + dw * np.where(t >= t_step, _second_order(np.maximum(t - t_step, 0.0)), 0.0)
    m = setpoint_step_metrics(t, y, t_step, w0, w0 + dw)
    overshoot, rise, settle = _reference_metrics()
    assert overshoot == pytest.approx(25.38, abs=0.01)  # the textbook value at zeta = 0.4
    assert m.overshoot_percent == pytest.approx(overshoot, abs=1e-4)
    assert m.rise_time_s == pytest.approx(rise, abs=1e-8)
    assert m.settling_time_s == pytest.approx(settle, abs=1e-8)
    assert m.step_rad_s == pytest.approx(dw, rel=1e-12)


def test_never_settled_and_no_overshoot():
    t = np.linspace(0.0, 0.1, 1001)
    m = setpoint_step_metrics(t, 1 - np.exp(-t / 1.0), 0.0, 0.0, 1.0)  # far too slow for the window
    assert m.rise_time_s == math.inf
    assert m.settling_time_s == math.inf
    assert m.overshoot_percent == 0.0
    assert m.as_dict()["settling_time_s"] is None
    with pytest.raises(ValueError, match="expected a setpoint step"):
        setpoint_step_metrics(t, t, 0.0, 1.0, 1.0)


def test_profile_finds_setpoint_steps_not_ramps():
    """Setpoint 300 rpm, ramp to 350 rpm (0.02-0.04 s), step to 400 rpm at 0.1 s; the speed a
    first-order follower (time constant 5 ms) of the setpoint."""
    ts = 2.5e-4
    t = np.arange(0.0, 0.2, ts)
    rpm = np.interp(t, [0.0, 0.02, 0.04], [300.0, 300.0, 350.0]) + np.where(t >= 0.1 - 1e-12, 50.0, 0.0)
    r = rpm * math.pi / 30
    y = np.empty_like(r)
    y[0] = r[0]
    a = math.exp(-ts / 5e-3)
    for k in range(1, len(t)):
        y[k] = a * y[k - 1] + (1 - a) * r[k - 1]
    m = profile_metrics(t, y, r, breaks=[0.02, 0.04, 0.1])
    assert m.setpoint_step_times_s == pytest.approx((0.1,), abs=1e-12)
    sp = m.setpoint_steps[0]
    # a first-order lag with one sample of delay: 10-90 % = tau ln 9, to the sample grid
    assert sp.rise_time_s == pytest.approx(5e-3 * math.log(9), abs=ts)
    assert sp.overshoot_percent == 0.0
    assert m.as_dict()["setpoint_steps"][0]["time_s"] == pytest.approx(0.1)
    # the report's table carries the verified numbers and a difference where both exist
    text = "\n".join(setpoint_table(m, m, lambda name: ts))
    assert "+50 rpm" in text
    assert f"{sp.rise_time_s:.4g}" in text
    assert "0.0 %" in text


@pytest.mark.parametrize("p, v, res", [(1.4e-14, 1.4e-4, 0.0), (-1.4e-14, 1.4e-4, 0.0), (1.4e-4, 1e-15, 0.0),
                                       (1.776e-15, 3.829e-06, 0.0365)])
def test_no_percentage_against_numerical_zero(p, v, res):
    text = diff_text(p, v, res)
    assert "%" not in text
    assert text.endswith("abs.")
    assert float(text.split()[0]) == pytest.approx(p - v, rel=1e-2)


def test_real_percentages_stay():
    assert diff_text(1e-6, 1e-4) == "-99.0 %"
    assert diff_text(3.67, 3.651, res=0.0365) == "+0.5 %"


@pytest.mark.slow
def test_cli_report_of_a_setpoint_duty_cycle(tmp_path, capsys):
    """A duty scene with a setpoint step: the report has the setpoint table with both columns,
    the crossover in rad/s and Hz (Hz = rad/s / 2 pi), and the baselines table names the
    design each baseline is compared with."""
    from prsa_ctrl.cli.tune import main

    f = tmp_path / "duty.toml"
    f.write_text('name = "duty"\n[operating]\ninitial_load_n = 500.0\n'
                 'setpoint_profile_rpm = [[0.0, 300.0], [0.05, 400.0, "step"]]\nduration_s = 0.15\n'
                 '[verify]\nfidelity = "rigid"\ndiscrete = true\n')
    assert main(["--scene", str(f)]) == 0
    out = capsys.readouterr().out
    assert "Setpoint steps in the profile" in out
    assert "settling 2 % (s)" in out
    assert "+100 rpm" in out
    m = re.search(r"crossover ([0-9.e+-]+) rad/s \(([0-9.e+-]+) Hz\)", out)
    assert m
    assert float(m.group(2)) == pytest.approx(float(m.group(1)) / (2 * math.pi), rel=1e-3)
    assert "compared with" in out
    assert "tuned (Ms <=" in out
