"""The one sampled-loop algebra (prsa_ctrl.drive.sampled): zero-order hold, per-sample PID rows
and their frequency responses, checked against closed forms."""

import math

import numpy as np
import pytest

from scipy.linalg import expm

from prsa_ctrl.drive.sampled import expm_stack, first_order_hold, freq_grid, pid_frequency_parts, pid_rows, ss_response, zoh

TS = 1e-3


def test_zoh_double_integrator_is_exact():
    ad, bd = zoh([[0.0, 1.0], [0.0, 0.0]], [[0.0], [2.0]], 0.1)
    np.testing.assert_allclose(ad, [[1.0, 0.1], [0.0, 1.0]], rtol=0, atol=1e-15)
    np.testing.assert_allclose(bd, [[2.0 * 0.1**2 / 2], [2.0 * 0.1]], rtol=1e-14)


@pytest.mark.parametrize("tau", [1e-9, 1e-4, 1e-3, 1.0])
def test_zoh_first_order_lag_any_stiffness(tau):
    """``e^{-Ts/tau}`` exactly, also far below the sample time (no step-size limit, no NaN)."""
    ad, bd = zoh([[-1.0 / tau]], [[1.0 / tau]], TS)
    assert np.all(np.isfinite(ad))
    assert np.all(np.isfinite(bd))
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


def _two_mass_a(jm, jl, k, c, b, wc):
    """State matrix [theta_m, omega_m, theta_l, omega_l, tau] of a two-mass axis behind a
    first-order current loop ``wc`` (rad/s), written here from the equations of motion."""
    return np.array([[0.0, 1.0, 0.0, 0.0, 0.0],
                     [-k / jm, -(b + c) / jm, k / jm, c / jm, 1.0 / jm],
                     [0.0, 0.0, 0.0, 1.0, 0.0],
                     [k / jl, c / jl, -k / jl, -c / jl, 0.0],
                     [0.0, 0.0, 0.0, 0.0, -wc]])


def _two_mass_zoh_closed_form(a, b, ts):
    """The zero-order hold of :func:`_two_mass_a` with input ``b`` on the current-loop state, in
    closed form around the stiff lag: the mechanics ``M`` (4 x 4, ``|M Ts|`` small) by its own
    exponential, the lag ``e^(-wc Ts)`` exactly, their coupling
    ``P = int_0^Ts e^(M (Ts - s)) e^(-wc s) ds = (M + wc I)^-1 (e^(M Ts) - e^(-wc Ts) I)``."""
    m, g, wc, gain = a[:4, :4], a[:4, 4], -a[4, 4], b[4, 0] / -a[4, 4]
    big = np.zeros((8, 8))
    big[:4, :4], big[:4, 4:] = m * ts, np.eye(4) * ts
    e = expm(big)  # |M Ts| < 1: no squaring
    em, q = e[:4, :4], e[:4, 4:]
    p = np.linalg.solve(m + wc * np.eye(4), em - math.exp(-wc * ts) * np.eye(4))
    ad = np.zeros((5, 5))
    ad[:4, :4], ad[:4, 4], ad[4, 4] = em, p @ g, math.exp(-wc * ts)
    bd = np.zeros((5, 1))
    bd[:4, 0], bd[4, 0] = (q @ g - p @ g) * gain, -math.expm1(-wc * ts) * gain
    return ad, bd


#: (jm, jl, k, c, b, wc, Ts): the sampled FRF model's blocks: a linear axis with a 900 Hz current loop
#: and with none (a 1e9 rad/s lag stands in), a screw axis at 4 kHz.
_TWO_MASS = [(2e-3, 8e-4, 80.0, 0.02, 0.0, 2 * math.pi * 900, 1e-3), (2e-3, 8e-4, 80.0, 0.02, 0.0, 1e9, 1e-3),
             (3e-4, 1e-4, 4e3, 0.05, 1e-4, 2 * math.pi * 1500, 2.5e-4)]


@pytest.mark.parametrize("case", _TWO_MASS)
def test_zoh_of_the_two_mass_model_is_its_closed_form(case):
    """Each entry of ``Ad`` and ``Bd`` to 1e-10 of itself against the closed form (on the stiff
    1e9 rad/s lag scipy.linalg.expm's entries are off by up to 1.1e-11, these by 5.3e-11)."""
    *phys, ts = case
    a = _two_mass_a(*phys)
    b = np.eye(5)[:, 4:] * phys[-1]
    ad, bd = zoh(a, b, ts)
    ad_ref, bd_ref = _two_mass_zoh_closed_form(a, b, ts)
    np.testing.assert_allclose(ad, ad_ref, rtol=1e-10, atol=1e-300)
    np.testing.assert_allclose(bd, bd_ref, rtol=1e-10, atol=1e-300)


#: (A, B, Ts): a stiff scalar lag, a lower-triangular and a dense system.
_ZOH_CASES = [
    (np.array([[-1e9]]), np.array([[1e9]]), 1e-3),
    (np.array([[-3.0, 0.0], [2.0, -5e4]]), np.zeros((2, 1)), 1e-3),
    (np.random.default_rng(3).normal(size=(6, 6)) * 200.0, np.random.default_rng(4).normal(size=(6, 2)), 1e-2),
    (np.array([[0.0, 1.0], [-4e4, -3.0]]), np.array([[0.0], [1.0]]), 1e-3),
]


@pytest.mark.parametrize("case", range(len(_ZOH_CASES)))
def test_expm_stack_equals_scipys_matrix_exponential_on_hold_blocks(case):
    """:func:`expm_stack` (the Monte Carlo's batched exponential) gives what ``scipy.linalg.expm``
    gives on these zero-order-hold blocks, to 1e-12 of the block's largest entry. (``zoh`` itself
    keeps scipy's: on a block scaled from 1e-20 to 1e33 the stack was off by 2.6e-6; see
    expm_stack's docstring.)"""
    a, b, ts = _ZOH_CASES[case]
    n, m = a.shape[0], b.shape[1]
    blk = np.zeros((n + m, n + m))
    blk[:n, :n], blk[:n, n:] = a * ts, b * ts
    ref = expm(blk)
    e = expm_stack(blk[None])[0]
    ad, bd = e[:n, :n], e[:n, n:]
    scale = max(1.0, float(np.max(np.abs(ref))))
    assert np.max(np.abs(ad - ref[:n, :n])) <= 1e-12 * scale
    assert np.max(np.abs(bd - ref[:n, n:])) <= 1e-12 * scale


def test_expm_stack_keeps_a_stiff_triangular_matrix_exact():
    """An upper and a lower triangular matrix with a stiff diagonal entry: the exponential's
    diagonal and first off-diagonal are the closed forms (no rounding left by the squarings)."""
    lam, mu, c = -1e6, -2.0, 3.0
    up = np.array([[lam, c], [0.0, mu]])
    e = expm_stack(np.stack([up, up.T]))
    off = c * (math.exp(mu) - math.exp(lam)) / (mu - lam)
    for got in (e[0], e[1].T):
        assert got[0, 0] == math.exp(lam)
        assert got[1, 0] == 0.0
        assert got[1, 1] == pytest.approx(math.exp(mu), rel=1e-14)
        assert got[0, 1] == pytest.approx(off, rel=1e-13)


def test_first_order_hold_equals_scipys_matrix_exponential():
    a = _two_mass_a(*_TWO_MASS[0][:6])
    h = 1e-3
    n = a.shape[0]
    big = np.zeros((3 * n, 3 * n))
    big[:n, :n], big[:n, n:2 * n], big[n:2 * n, 2 * n:] = a * h, np.eye(n) * h, np.eye(n) * h
    e = expm(big)
    phi, p0, p1 = first_order_hold(a, h)
    np.testing.assert_allclose(phi, e[:n, :n], rtol=0, atol=1e-12 * np.max(np.abs(e)))
    np.testing.assert_allclose(p1, e[:n, 2 * n:] / h, rtol=0, atol=1e-12 * np.max(np.abs(e)) / h)
    np.testing.assert_allclose(p0 + p1, e[:n, n:2 * n], rtol=0, atol=1e-12 * np.max(np.abs(e)))


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
    assert g[0] == pytest.approx(0.1)
    assert g[-1] == pytest.approx(1e3)
