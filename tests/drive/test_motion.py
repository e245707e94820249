"""Motion profiles (prsa_ctrl.drive.motion): exact rest-to-rest moves, limits, continuity, reversal."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from prsa_ctrl.drive.motion import MotionProfile, out_and_back, plan, s_curve, trapezoidal

distances = st.floats(1e-6, 0.5).flatmap(lambda d: st.sampled_from([d, -d]))
speeds = st.floats(1e-3, 1.0)
accels = st.floats(1e-2, 50.0)
jerks = st.floats(1.0, 1e4)


def _check_move(m: MotionProfile, d: float, v: float, a: float, j: float | None) -> None:
    # Ends exactly where asked, at rest; never exceeds a limit; starts at rest.
    p, vv, aa = m.at([0.0, m.end_time, m.end_time + 1.0])
    assert p[1] == pytest.approx(d, rel=1e-12, abs=1e-18)
    assert p[2] == p[1]
    assert vv[1] == vv[2] == 0.0
    assert aa[1] == 0.0
    assert vv[0] == 0.0
    assert p[0] == 0.0
    lim = m.limits()
    assert lim["speed_m_s"] <= v * (1 + 1e-9)
    assert lim["acceleration_m_s2"] <= a * (1 + 1e-9)
    if j is not None:
        assert lim["jerk_m_s3"] <= j * (1 + 1e-9)
    # The state is continuous at every segment boundary (position and speed always; the
    # S-curve's acceleration too).
    ends = np.array(m.t0[1:] + (m.end_time,))
    eps = 1e-12 * max(m.end_time, 1.0)
    left, right = m.at(ends - eps), m.at(ends + eps)
    scale_p, scale_v = abs(d), max(lim["speed_m_s"], 1e-300)
    assert np.all(np.abs(left[0] - right[0]) <= 1e-9 * scale_p + 10 * eps * scale_v)
    assert np.all(np.abs(left[1] - right[1]) <= 1e-9 * scale_v + 10 * eps * lim["acceleration_m_s2"])
    if j is not None:
        assert np.all(np.abs(left[2] - right[2]) <= 1e-9 * lim["acceleration_m_s2"] + 10 * eps * j)


@settings(max_examples=60, deadline=None)
@given(distances, speeds, accels)
def test_trapezoid_exact_and_within_limits(d, v, a):
    m = trapezoidal(d, v, a)
    _check_move(m, d, v, a, None)
    # Minimum time: the speed limit is reached exactly when the distance allows it.
    if v * v / a <= abs(d):
        assert m.duration == pytest.approx(abs(d) / v + v / a, rel=1e-12)
        assert m.limits()["speed_m_s"] == pytest.approx(v, rel=1e-12)
    else:
        assert m.duration == pytest.approx(2 * math.sqrt(abs(d) / a), rel=1e-12)


@settings(max_examples=60, deadline=None)
@given(distances, speeds, accels, jerks)
def test_s_curve_exact_and_within_limits(d, v, a, j):
    m = s_curve(d, v, a, j)
    _check_move(m, d, v, a, j)
    # One of the limits is active: the move is as fast as its limits allow.
    lim = m.limits()
    assert max(lim["speed_m_s"] / v, lim["acceleration_m_s2"] / a) == pytest.approx(1.0, rel=1e-9) or \
        lim["jerk_m_s3"] == pytest.approx(j, rel=1e-12)


def test_derivatives_are_consistent():
    """v = dp/dt and a = dv/dt (central differences on a fine grid; error O(h^2 jerk))."""
    m = s_curve(0.01, 0.03, 0.5, 50.0)
    t = np.linspace(0.0, m.duration, 400001)
    h = t[1] - t[0]
    p, v, a = m.at(t)
    assert np.max(np.abs((p[2:] - p[:-2]) / (2 * h) - v[1:-1])) < 50.0 * h**2
    assert np.max(np.abs((v[2:] - v[:-2]) / (2 * h) - a[1:-1])) < 50.0 * h  # O(h jerk) at the jerk steps
    # Cruise at exactly 30 mm/s in the middle; the pure jerk phase lasts a/j = 10 ms.
    assert m.at(m.duration / 2)[1] == pytest.approx(0.03, rel=1e-12)
    assert m.at(0.005)[2] == pytest.approx(50.0 * 0.005, rel=1e-12)


def test_out_and_back_reverses_and_returns():
    m = out_and_back("s-curve", 0.002, 0.03, 0.5, 50.0, dwell_s=0.05, start_s=0.01)
    t = np.linspace(0.0, m.duration + 0.01, 20001)
    p, v, _ = m.at(t)
    assert abs(m.final_position) < 1e-18
    assert np.max(p) == pytest.approx(0.002, rel=1e-9)
    assert np.min(v) < -0.02
    assert np.max(v) > 0.02  # both directions
    dwell = (t > 0.01 + m.duration / 2 - 0.02) & (t < 0.01 + m.duration / 2 + 0.02)
    assert np.all(v[dwell] == 0.0)
    assert np.all(p[dwell] == pytest.approx(0.002, rel=1e-12))
    assert np.all(p[t < 0.01] == 0.0)


@pytest.mark.parametrize("call, name", [
    (lambda: trapezoidal(0.0, 0.03, 0.5), "distance_m"),
    (lambda: trapezoidal(0.01, -1.0, 0.5), "max_speed_m_s"),
    (lambda: s_curve(0.01, 0.03, float("nan"), 1.0), "acceleration_m_s2"),
    (lambda: s_curve(0.01, 0.03, 0.5, 0.0), "jerk_m_s3"),
    (lambda: plan("s-curve", 0.01, 0.03, 0.5), "jerk_m_s3"),
    (lambda: plan("sine", 0.01, 0.03, 0.5), "kind"),
])
def test_bad_arguments_name_themselves(call, name):
    with pytest.raises(ValueError, match=name):
        call()
