"""Issue 25: 2-DOF setpoint weights after the load-disturbance design. Goal (stated in the result):
the least IAE of r - y after a unit setpoint step with the load-optimal gains fixed. Checked
against an independent search on closed-loop transfer functions (tests/independent_tuner.py)."""

import control
import numpy as np
import pytest
from scipy.optimize import minimize, minimize_scalar

import independent_tuner as ref
from prsa_ctrl.tuning import tune_pid

P3 = ([1.0], [1.0, 3.0, 3.0, 1.0])


def test_pi_weight_b_matches_independent_search():
    num, den = [1.0], [4.0, 1.0]
    r = tune_pid(control.tf(num, den), objective="iae", ms_max=1.2, mt_max=1.2, mks_max=10.0, setpoint_weights=True)
    sp = r.setpoint
    assert sp["c"] == 0.0 and "setpoint step" in sp["goal"]
    p = r.pid
    f = lambda b: ref.setpoint_iae(num, den, p.kp, p.ki, 0.0, p.tf, b, 0.0, t_end=20.0, n=8001)[0]
    best = minimize_scalar(f, bounds=(0.0, 1.0), method="bounded", options={"xatol": 1e-6})
    # The reference checks itself: converged, and no worse than any point of a grid over [0, 1].
    assert best.success, best.message
    assert best.fun <= min(f(b) for b in np.linspace(0.0, 1.0, 21))
    assert sp["b"] == pytest.approx(best.x, abs=2e-3)
    assert sp["iae"] == pytest.approx(f(sp["b"]), rel=1e-4)
    assert sp["iae"] <= sp["iae_unweighted"]
    assert sp["iae_unweighted"] == pytest.approx(f(1.0), rel=1e-4)
    # The weights leave the feedback loop alone: same gains and peaks as without them.
    r0 = tune_pid(control.tf(num, den), objective="iae", ms_max=1.2, mt_max=1.2, mks_max=10.0)
    assert (r0.pid.kp, r0.pid.ki, r0.pid.kd) == (p.kp, p.ki, p.kd) and r0.ms == r.ms and r0.mks == r.mks
    assert r0.setpoint is None


def test_pid_weights_b_c_match_independent_search():
    r = tune_pid(control.tf(*P3), objective="iae", controller="pid", setpoint_weights=True)
    sp, p = r.setpoint, r.pid
    f = lambda x: ref.setpoint_iae(*P3, p.kp, p.ki, p.kd, p.tf, x[0], min(max(x[1], 0.0), 1.0), t_end=40.0, n=4001)[0] \
        + 1e3 * (max(x[0] - 1, 0) + max(-x[0], 0) + max(x[1] - 1, 0) + max(-x[1], 0))
    # IAE is convex in (b, c) (the error is affine in them): one local search finds the minimum.
    # (with maxfev 120 it stopped unconverged; 152 evaluations measured)
    best = minimize(f, [0.5, 0.5], method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-8, "maxfev": 600})
    assert best.success, best.message  # the reference checks itself: converged, within the box
    assert 0.0 <= best.x[0] <= 1.0 and 0.0 <= best.x[1] <= 1.0
    assert sp["iae"] <= best.fun * (1 + 1e-4)  # no worse than the independent search
    assert sp["iae"] == pytest.approx(f([sp["b"], sp["c"]]), rel=1e-4)
    assert sp["iae"] < sp["iae_unweighted"]


def test_setpoint_weights_flag_is_checked():
    with pytest.raises(ValueError, match="setpoint_weights"):
        tune_pid(control.tf(*P3), setpoint_weights="yes")
