"""The one sampled-loop algebra (prsa_ctrl.drive.sampled): zero-order hold, per-sample PID rows
and their frequency responses, checked against closed forms."""

import math

import numpy as np
import pytest

from prsa_ctrl.drive.sampled import freq_grid, pid_frequency_parts, pid_rows, ss_response, zoh

TS = 1e-3


def test_zoh_double_integrator_is_exact():
    ad, bd = zoh([[0.0, 1.0], [0.0, 0.0]], [[0.0], [2.0]], 0.1)
    np.testing.assert_allclose(ad, [[1.0, 0.1], [0.0, 1.0]], rtol=0, atol=1e-15)
    np.testing.assert_allclose(bd, [[2.0 * 0.1**2 / 2], [2.0 * 0.1]], rtol=1e-14)


@pytest.mark.parametrize("tau", [1e-9, 1e-4, 1e-3, 1.0])
def test_zoh_first_order_lag_any_stiffness(tau):
    """``e^{-Ts/tau}`` exactly, also far below the sample time (no step-size limit, no NaN)."""
    ad, bd = zoh([[-1.0 / tau]], [[1.0 / tau]], TS)
    assert np.all(np.isfinite(ad)) and np.all(np.isfinite(bd))
    assert ad[0, 0] == pytest.approx(math.exp(-TS / tau), rel=1e-12, abs=1e-300)
    assert bd[0, 0] == pytest.approx(1.0 - math.exp(-TS / tau), rel=1e-12)


def test_zoh_two_inputs_match_one_by_one():
    a = np.array([[-3.0, 1.0], [0.5, -20.0]])
    b = np.array([[1.0, 0.0], [0.3, 2.0]])
    ad, bd = zoh(a, b, TS)
    for j in range(2):
        ad_j, bd_j = zoh(a, b[:, j:j + 1], TS)
        np.testing.assert_array_equal(ad_j, ad)
        np.testing.assert_allclose(bd_j[:, 0], bd[:, j], rtol=1e-14)


def test_pid_rows_run_the_drive_law():
    """Loop state [w, I, u]: one sample of A0 + kp A_kp + ki A_ki + kd A_kd gives
    u = kp e + I - kd d and I += Ts ki e for the error e = r - w and a derivative row d."""
    n, i_i, i_u = 3, 1, 2
    e_row = np.array([-1.0, 0.0, 0.0])  # e = -w (reference 0)
    d_row = np.array([0.5, 0.0, 0.0])  # some derivative row
    a0 = np.zeros((n, n))
    a0[0, 0] = 1.0  # w held
    a0[i_i, i_i] = 1.0
    a0[i_u, i_i] = 1.0  # u = I + ...
    a_kp, a_ki, a_kd = pid_rows(n, i_u, i_i, e_row, d_row, TS)
    kp, ki, kd = 0.2, 30.0, 1e-3
    x = np.array([4.0, 0.7, 0.0])
    nxt = (a0 + kp * a_kp + ki * a_ki + kd * a_kd) @ x
    e, d = -x[0], 0.5 * x[0]
    assert nxt[i_u] == pytest.approx(kp * e + x[i_i] - kd * d)
    assert nxt[i_i] == pytest.approx(x[i_i] + TS * ki * e)


def test_pid_rows_setpoint_weight():
    n, i_i, i_u = 3, 1, 2
    y, r = np.array([1.0, 0, 0]), np.array([0, 0, 1.0])
    a_kp, a_ki, _ = pid_rows(n, i_u, i_i, -y, np.zeros(n), TS, ref=r, weight=0.4)
    x = np.array([2.0, 0.0, 5.0])
    assert a_kp[i_u] @ x == pytest.approx(0.4 * 5.0 - 2.0)  # b r - y
    assert a_ki[i_i] @ x == pytest.approx(TS * (5.0 - 2.0))  # Ts (r - y)


def test_pid_frequency_parts_match_their_state_space():
    """The integral part is the accumulator ``I += Ts e`` and the derivative part the filter
    ``d = beta d + (1 - beta)(w - w_prev) / Ts``, evaluated as discrete state space."""
    beta = math.exp(-TS / 2e-3)
    w = freq_grid(1.0, math.pi / TS * 0.99, 50)
    zi = np.exp(-1j * w * TS)
    kp, ki, kd = pid_frequency_parts(zi, TS, beta)

    def z_of(x):
        return np.exp(1j * x * TS)

    np.testing.assert_array_equal(kp, np.ones_like(zi))
    # accumulator seen one sample later (the command uses the integral before this sample's update)
    np.testing.assert_allclose(ki, ss_response([[1.0]], [[TS]], [[1.0]], w, z_of), rtol=1e-10)
    # derivative filter: states [d, w_prev]; output the new d
    a = np.array([[beta, -(1 - beta) / TS], [0.0, 0.0]])
    b = np.array([[(1 - beta) / TS], [1.0]])
    c = np.array([[beta, -(1 - beta) / TS]])
    direct = (1 - beta) / TS
    np.testing.assert_allclose(kd, ss_response(a, b, c, w, z_of) + direct, rtol=1e-9)


def test_ss_response_continuous_and_empty():
    w = np.array([0.0, 1.0, 10.0])
    np.testing.assert_allclose(ss_response([[-1.0]], [[1.0]], [[1.0]], w), 1.0 / (1j * w + 1.0), rtol=1e-14)
    assert ss_response(np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)), w).tolist() == [0j, 0j, 0j]


def test_freq_grid_is_log_spaced():
    g = freq_grid(0.1, 1e3, 5)
    np.testing.assert_allclose(np.diff(np.log10(g)), 1.0, rtol=1e-12)
    assert g[0] == pytest.approx(0.1) and g[-1] == pytest.approx(1e3)
