import control
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from prsa_ctrl.tuning.builders import continuous_loop

from prsa_ctrl.tuning.generic import tune_pid

P3 = control.tf([1.0], [1.0, 3.0, 3.0, 1.0])
MATLAB_PI = (1.14, 0.454, 0.0)  # pidtune(1/(s+1)^3, 'pi') as published


def _ms_dense(plant, pid):
    w = np.logspace(-4, 4, 40000)
    C = control.tf([pid.kp, pid.ki], [1.0, 0.0])
    L = np.asarray(control.frequency_response(plant * C, w).complex).ravel()
    return float(np.max(np.abs(1 / (1 + L))))


def test_beats_matlab_pidtune_at_the_same_ms():
    loop = continuous_loop(control.ss(P3), tf=0.1, horizon=40.0, n_steps=2000)
    ms_matlab = loop.margins(MATLAB_PI).ms
    ie_matlab = loop.objective(MATLAB_PI, "ie")
    assert ms_matlab == pytest.approx(1.63, abs=0.01)
    assert ie_matlab == pytest.approx(1 / 0.454, rel=1e-3)  # IE = 1/ki for a unit input step
    res = tune_pid(P3, objective="ie", ms_max=ms_matlab, n_steps=2000)
    assert res.ms <= ms_matlab
    assert _ms_dense(P3, res.pid) <= ms_matlab * (1 + 1e-3)
    assert res.objective < ie_matlab
    assert res.objective == pytest.approx(1 / res.pid.ki, rel=1e-9)  # IE to infinity, exact
    assert res.stats["status"] == "Solve_Succeeded"
    assert res.status == "optimal" and res.converged and not res.warnings
    assert res.ms == pytest.approx(_ms_dense(P3, res.pid), rel=1e-4)  # the reported Ms is the true one


def test_pid_improves_on_pi_at_equal_ms():
    pi = tune_pid(P3, objective="iae", ms_max=1.4, n_steps=800)
    pid = tune_pid(P3, objective="iae", ms_max=1.4, controller="pid", n_steps=800)
    assert pid.pid.kd > 0 and pid.ms <= 1.4
    assert pid.objective < pi.objective


def test_noise_gain_bound_limits_gains():
    res = tune_pid(P3, objective="iae", ms_max=1.8, max_noise_gain=0.3, n_steps=800)
    assert res.pid.kp <= 0.3 * (1 + 1e-6)


def test_mt_bound_is_respected():
    res = tune_pid(P3, objective="iae", ms_max=2.0, mt_max=1.1, n_steps=800)
    assert max(m.mt for m in res.margins) <= 1.1


def _closed_loop_stable(plant, pid):
    C = control.tf([pid.kd + pid.kp * pid.tf, pid.kp + pid.ki * pid.tf, pid.ki], [pid.tf, 1.0, 0.0])
    cl = control.feedback(plant * C, 1)
    return bool(np.all(np.real(cl.poles()) < 0))


@settings(max_examples=6, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.floats(0.2, 5.0),  # gain
    st.floats(0.05, 3.0),  # second time constant
    st.floats(0.01, 1.0),  # third time constant
    st.one_of(st.just(0.0), st.floats(0.05, 0.8)),  # right-half-plane zero time constant
    st.sampled_from(["iae", "ie", "ise"]),
    st.floats(1.2, 2.0),
)
def test_tuner_never_returns_an_unstable_loop(k, t2, t3, tz, objective, ms_max):
    num = [-k * tz, k] if tz > 0 else [k]
    plant = control.tf(num, np.polymul([1.0, 1.0], np.polymul([t2, 1.0], [t3, 1.0])))
    res = tune_pid(plant, objective=objective, ms_max=ms_max, n_steps=600)
    assert _closed_loop_stable(plant, res.pid)
    assert res.ms <= ms_max


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"objective": "iaee"}, r"objective = 'iaee'; expected one of ie, iae, itae, ise"),
        ({"controller": "pd"}, r"controller = 'pd'; expected 'pi' or 'pid'"),
        ({"ms_max": 0.9}, r"ms_max = 0\.9; expected a number in \(1, 10\)"),
        ({"mt_max": 0.1}, r"mt_max = 0\.1"),
        ({"max_noise_gain": -1.0}, r"max_noise_gain = -1\.0"),
        ({"step": float("nan")}, r"^step = nan; expected a finite non-zero step size"),
        ({"kp_max": -1.0}, r"^kp_max = -1\.0; expected a positive number"),
        ({"tf": 0.0}, r"^tf = 0\.0; expected a positive finite time constant in s"),
    ],
)
def test_bad_tuner_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        tune_pid(P3, n_steps=200, **kwargs)


def test_pure_integrator_gets_the_stated_default_bound():
    """1/s: robustness alone never limits the gains, so the default design bounds the
    controller's high-frequency gain (10/|P(j w0)| = 10 at w0 = 1 rad/s) and says so."""
    r = tune_pid(control.tf([1.0], [1.0, 0.0]))
    assert r.status == "optimal" and r.pid.kp == pytest.approx(10.0, rel=1e-5) and r.ms <= 1.4 * (1 + 1e-9)
    assert "default noise-gain bound max_noise_gain = 10/|P(j w0)| = 10 at w0 = 1 rad/s" in r.warnings[0]
    explicit = tune_pid(control.tf([1.0], [1.0, 0.0]), max_noise_gain=3.0, horizon=10.0, tf=0.01)
    assert explicit.pid.kp == pytest.approx(3.0, rel=1e-5) and not explicit.warnings[:1] == r.warnings[:1]


def test_discrete_and_mimo_plants_are_rejected():
    with pytest.raises(ValueError, match=r"discrete-time"):
        tune_pid(control.c2d(P3, 0.1), horizon=10.0, tf=0.1)
    with pytest.raises(ValueError, match=r"2 outputs; expected one"):
        tune_pid(control.ss(np.eye(2) * -1, np.eye(2), np.eye(2), np.zeros((2, 2))), horizon=10.0, tf=0.1)
