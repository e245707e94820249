import math

import control
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from prsa_ctrl.sim.metrics import load_step_metrics, margins_from_response

T = np.linspace(0.0, 20.0, 200001)


def test_ie_equals_one_over_ki_for_an_input_load_step():
    kp, ki = 0.8, 0.5
    P = control.tf([1.0], [1.0, 1.0])
    C = control.tf([kp, ki], [1.0, 0.0])
    # Load step at the plant input slows the output: y = -P/(1+PC) d.
    resp = control.step_response(-P / (1 + P * C), T=np.linspace(0.0, 60.0, 60001))
    m = load_step_metrics(resp.time + 1.0, np.asarray(resp.outputs), 0.0, 1.0)
    assert m.ie == pytest.approx(1.0 / ki, rel=1e-4)
    assert m.iae >= m.ie - 1e-12


def test_known_shapes():
    t = T + 1.0
    e = np.exp(-T)  # error after the step: 1, decaying
    m = load_step_metrics(t, 5.0 - e, 5.0, 1.0)
    assert m.peak_drop_rad_s == pytest.approx(1.0)
    assert m.peak_time_s == pytest.approx(0.0)
    assert m.ie == pytest.approx(1.0, rel=1e-6)
    assert m.iae == pytest.approx(1.0, rel=1e-6)
    assert m.ise == pytest.approx(0.5, rel=1e-6)
    assert m.itae == pytest.approx(1.0, rel=1e-6)
    assert m.recovery_time_s == pytest.approx(math.log(20.0), abs=1e-3)
    assert m.steady_state_error_rad_s == pytest.approx(0.0, abs=1e-6)
    assert m.overshoot_rad_s == 0.0
    assert math.isnan(m.peak_torque_n_m)
    assert not m.saturated


def test_drop_time_overshoot_torque_and_saturation():
    ts = T
    y = 1.0 - ts * np.exp(-ts) + 0.05 * np.exp(-(((ts - 8.0) / 0.5) ** 2))  # drop, then a bump above
    torque = 2.0 + np.minimum(ts, 1.0)
    pre_t = np.concatenate([[-1.0], ts]) + 2.0
    m = load_step_metrics(pre_t, np.concatenate([[1.0], y]), 1.0, 2.0, np.concatenate([[2.0], torque]), torque_limit=3.0)
    assert m.peak_drop_rad_s == pytest.approx(math.exp(-1.0), rel=1e-6)
    assert m.peak_time_s == pytest.approx(1.0, abs=1e-3)
    assert m.overshoot_rad_s == pytest.approx(0.05 - 8 * math.exp(-8.0), abs=2e-4)
    assert m.peak_torque_n_m == pytest.approx(3.0)
    assert m.saturated


def test_steady_offset_never_recovers():
    y = 1.0 - 0.5 * (1 - np.exp(-T))  # settles 0.5 below the setpoint
    m = load_step_metrics(T, y, 1.0, 0.0)
    assert m.steady_state_error_rad_s == pytest.approx(0.5, rel=1e-3)
    assert math.isinf(m.recovery_time_s)
    assert m.as_dict()["recovery_time_s"] is None


@pytest.mark.parametrize(
    "args, match",
    [
        (([0, 1], [1, 1], 1.0, 0.0), r"equal length >= 3"),
        (([0, 1, 1], [1, 1, 1], 1.0, 0.0), r"increase strictly"),
        (([0, 1, 2], [1, np.nan, 1], 1.0, 0.0), r"must be finite"),
        (([0, 1, 2], [1, 1, 1], 1.0, 5.0), r"step_time = 5\.0 s; expected a time inside the record"),
    ],
)
def test_bad_metric_inputs(args, match):
    with pytest.raises(ValueError, match=match):
        load_step_metrics(*args)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(st.floats(0.01, 100.0), st.floats(0.1, 10.0), st.floats(0.5, 5.0))
def test_metrics_scale_with_amplitude(a, tau, w):
    t = np.linspace(0, 10 * tau, 4001)
    e = np.exp(-t / tau) * np.cos(w * t / tau)
    m1 = load_step_metrics(t, 3.0 - e, 3.0, 0.0)
    m2 = load_step_metrics(t, 3.0 - a * e, 3.0, 0.0)
    assert m2.iae == pytest.approx(a * m1.iae, rel=1e-9)
    assert m2.ie == pytest.approx(a * m1.ie, rel=1e-9, abs=1e-12)
    assert m2.ise == pytest.approx(a * a * m1.ise, rel=1e-9)
    assert m2.recovery_time_s == pytest.approx(m1.recovery_time_s)
    assert m1.iae >= abs(m1.ie) - 1e-12
    assert m1.ise >= 0


def test_margins_match_known_loop():
    # L = 4/(s+1)^3: phase crossover at sqrt(3) rad/s where |L| = 4/8 -> GM = 6.02 dB.
    w = np.logspace(-3, 3, 20000)
    L = 4.0 / (1j * w + 1) ** 3
    m = margins_from_response(w, L)
    assert m.gm_db == pytest.approx(20 * math.log10(2.0), abs=1e-3)
    gm, pm, _, _, wc, _ = control.stability_margins(control.tf([4.0], [1, 3, 3, 1]))
    assert m.pm_deg == pytest.approx(pm, abs=1e-2)
    assert m.wc_rad_s == pytest.approx(wc, rel=1e-3)
    assert m.ms == pytest.approx(np.max(np.abs(1 / (1 + L))))
    assert m.mt == pytest.approx(np.max(np.abs(L / (1 + L))))


def test_margins_without_crossings_are_infinite():
    w = np.logspace(-2, 2, 100)
    m = margins_from_response(w, 0.1 / (1j * w + 1))
    assert math.isinf(m.gm_db)
    assert math.isinf(m.pm_deg)
    assert math.isnan(m.wc_rad_s)
    assert m.as_dict()["gm_db"] is None


def _sixty_bisections(f, lo, hi, f_lo):
    """The reference: 60 bisections of every bracket, none skipped."""
    lo, hi = lo.copy(), hi.copy()
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        same = np.sign(f(mid)) == np.sign(f_lo)
        lo, hi = np.where(same, mid, lo), np.where(same, hi, mid)
    return 0.5 * (lo + hi)


@pytest.mark.parametrize("w_lo, w_hi, n", [(1e-3, 1e3, 200), (1e-1, 1e4, 57), (0.5, 3.0, 9)])
def test_exact_crossings_equal_sixty_full_bisections_bit_for_bit(w_lo, w_hi, n):
    # The bisection stops once a step leaves every bracket unchanged: the result must be the
    # number 60 full bisections give (crossings near w = 1 rad/s, where log w ~ 0 has the finest
    # floating-point spacing, and far from it).
    def loop(wv):
        s = 1j * np.asarray(wv, float)
        return 4.0 / (s + 1) ** 3 * np.exp(-0.05 * s)

    w = np.logspace(math.log10(w_lo), math.log10(w_hi), n)
    L = loop(w)
    m = margins_from_response(w, L, response=loop)
    x, lm, phase = np.log(w), np.log(np.abs(L)), np.unwrap(np.angle(L))
    i = np.flatnonzero(np.sign(lm[:-1]) * np.sign(lm[1:]) < 0)
    r = _sixty_bisections(lambda xs: np.log(np.abs(loop(np.exp(xs)))), x[i], x[i + 1], lm[i])
    assert m.wc_rad_s == float(math.exp(r[0]))
    k = np.floor((phase + math.pi) / (2 * math.pi))
    j = np.flatnonzero(np.diff(k) != 0)
    target = np.maximum(k[j], k[j + 1]) * 2 * math.pi - math.pi
    rp = _sixty_bisections(lambda xs: phase[j] + np.angle(loop(np.exp(xs)) / L[j]) - target, x[j], x[j + 1],
                           phase[j] - target)
    assert m.gm_db == float(np.min(-20 * np.log10(np.abs(loop(np.exp(rp))))))
