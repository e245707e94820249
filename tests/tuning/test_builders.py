"""The one sampled-loop builder (``drive_loop``) with its pluggable measurement blocks, checked
against the drive's per-sample law written out by hand here (plain NumPy, no builder code)."""

import math

import numpy as np
import pytest
from scipy.linalg import expm, solve_discrete_are

from prsa_ctrl.drive.estimator import KFDesign
from prsa_ctrl.drive.filters import DiscreteBiquad
from prsa_ctrl.tuning.builders import drive_loop
from prsa_ctrl.tuning.loopmeasure import EncoderDifference, KalmanEstimate

TS = 2.5e-4  # s
J = 1e-3  # kg m^2
TC = 5e-4  # s, current-loop lag
LEAD = 1e-3  # m/rad (load N -> torque N m)
TF = 4 * TS  # s, derivative filter
# Plant states [speed rad/s, angle rad, motor torque N m]; inputs (torque command N m, load N).
A = np.array([[0.0, 0.0, 1.0 / J], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0 / TC]])
B = np.array([[0.0, -LEAD / J], [0.0, 0.0], [1.0 / TC, 0.0]])
C_SPEED = np.array([1.0, 0.0, 0.0])
ANGLE = 1
STEP = 200.0  # N
# A first-order low-pass on the measured speed and a (made-up) biquad on the torque command.
SPEED_BQ = DiscreteBiquad(0.2, 0.2, 0.0, -0.6, 0.0, TS)
TORQUE_BQ = DiscreteBiquad(0.7, -0.5, 0.3, -0.4, 0.1, TS)
GAINS = (0.3, 15.0, 2e-4, 0.4)  # kp N m s/rad, ki N m/rad, kd N m s^2/rad, kff


def _zoh(a, b):
    n, m = a.shape[0], b.shape[1]
    blk = np.zeros((n + m, n + m))
    blk[:n, :n], blk[:n, n:] = a * TS, b * TS
    e = expm(blk)
    return e[:n, :n], e[:n, n:]


def _kf() -> KFDesign:
    """A steady-state Kalman filter of [angle, speed, motor torque, load torque] (the plant's
    own dynamics plus a load random walk), its gain from scipy's Riccati solver."""
    a = np.array([[0, 1, 0, 0], [0, 0, 1 / J, -1 / J], [0, 0, -1 / TC, 0], [0, 0, 0, 0]], float)
    f, g = _zoh(a, np.array([[0.0], [0.0], [1.0 / TC], [0.0]]))
    h = np.array([[1.0, 0.0, 0.0, 0.0]])
    q = 1e-4 * (g @ g.T) + np.diag([0.0, 0.0, 0.0, 1e-3])
    r = (2 * math.pi / 2**16) ** 2 / 12
    p = solve_discrete_are(f.T, h.T, q, np.array([[r]]))
    k = (p @ h.T) / (float((h @ p @ h.T).item()) + r)
    return KFDesign(f, g, h, q, r, k, p, TS, J)


class _HandLoop:
    """The drive's per-sample law as the simulator runs it, written out state by state: the
    filter updates with the angle, the speed biquad filters its speed, the PID (plus kff times
    the load estimate) computes the command, the torque biquad filters it, the command stored
    at the previous sample goes down the delay line (the oldest drives the plant over the
    sample, plus an input disturbance ``d``) and the filter predicts with the stored command."""

    def __init__(self, kf: KFDesign, gains, n_delay: int, weight: float = 1.0):
        self.kf, self.gains, self.n_delay, self.weight = kf, gains, n_delay, weight
        self.ad, bd = _zoh(A, B)
        self.bu, self.bl = bd[:, 0], bd[:, 1]
        # Layout: x(3), kf prior(4), I, d, w_prev, u_pend, speed biquad(4), torque biquad(4), delay line.
        self.size = 3 + 4 + 4 + 8 + n_delay

    def split(self, s):
        return s[:3], s[3:7], s[7], s[8], s[9], s[10], s[11:15], s[15:19], s[19:]

    def applied(self, s):
        line, u_pend = self.split(s)[8], self.split(s)[5]
        return line[0] if self.n_delay else u_pend

    def step(self, s, load: float, d: float, ref: float = 0.0):
        kp, ki, kd, kff = self.gains
        x, m, integral, deriv_old, w_prev, u_pend, mb_s, mb_t, line = self.split(np.asarray(s, float))
        K = self.kf.K.ravel()
        post = m + K * (x[ANGLE] - m[0])
        w_raw, tl_hat = post[1], post[3]
        bq = SPEED_BQ
        w_meas = bq.b0 * w_raw + bq.b1 * mb_s[0] + bq.b2 * mb_s[1] - bq.a1 * mb_s[2] - bq.a2 * mb_s[3]
        mb_s = np.array([w_raw, mb_s[0], w_meas, mb_s[2]])
        beta = math.exp(-TS / TF)
        deriv = beta * deriv_old + (1 - beta) * (w_meas - w_prev) / TS
        e = ref - w_meas
        u = kp * (self.weight * ref - w_meas) + integral - kd * deriv + kff * tl_hat
        bq = TORQUE_BQ
        u_f = bq.b0 * u + bq.b1 * mb_t[0] + bq.b2 * mb_t[1] - bq.a1 * mb_t[2] - bq.a2 * mb_t[3]
        mb_t = np.array([u, mb_t[0], u_f, mb_t[2]])
        applied = (line[0] if self.n_delay else u_pend) + d
        line = np.concatenate([line[1:], [u_pend]]) if self.n_delay else line
        x = self.ad @ x + self.bu * applied + self.bl * load
        m = self.kf.F @ post + self.kf.G.ravel() * u_pend
        return np.concatenate([x, m, [integral + TS * ki * e, deriv, w_meas, u_f], mb_s, mb_t, line])

    def matrices(self):
        """The (linear) law as ``s+ = A s + B_load load + B_d d``, column by column."""
        z = np.zeros(self.size)
        a = np.column_stack([self.step(e, 0.0, 0.0) for e in np.eye(self.size)])
        return a, self.step(z, 1.0, 0.0), self.step(z, 0.0, 1.0)


def _kf_loop(n_delay: int, feedforward: bool = True, **kw):
    return drive_loop(A, B, C_SPEED, ANGLE, ts=TS, tf=TF, horizon=0.02, step=STEP,
                      filters=(("speed_measurement", SPEED_BQ), ("torque_command", TORQUE_BQ)),
                      command_delay_samples=n_delay, measurement=KalmanEstimate(_kf(), feedforward), **kw)


@pytest.mark.parametrize("n_delay", [0, 2])
def test_kf_loop_with_filters_and_delay_follows_the_hand_written_law_in_time(n_delay):
    lp = _kf_loop(n_delay)
    assert lp.stability(GAINS) == "stable"
    hand = _HandLoop(_kf(), GAINS, n_delay)
    s = np.zeros(hand.size)
    speed = []
    for _ in range(lp.n_steps):
        speed.append(s[0])
        s = hand.step(s, STEP, 0.0)
    err = lp.error(GAINS)
    scale = np.max(np.abs(speed))
    assert scale > 1e-3  # the step moves the speed
    np.testing.assert_allclose(err, -np.asarray(speed), rtol=0, atol=1e-9 * scale)


@pytest.mark.parametrize("n_delay", [0, 2])
def test_kf_loop_poles_are_the_hand_written_loops_poles(n_delay):
    lp = _kf_loop(n_delay)
    a_hand = _HandLoop(_kf(), GAINS, n_delay).matrices()[0]
    lam_h = np.linalg.eigvals(a_hand)
    drift = np.argmin(np.abs(lam_h - 1.0))  # the angle and its estimate drifting together
    assert abs(lam_h[drift] - 1.0) < 1e-9
    lam_h = np.delete(lam_h, drift)
    lam_m = lp.poles(GAINS)
    # (the hand loop also stores the previous measured speed, which the model reads from the
    # speed biquad's memory: one more pole at 0)
    assert np.sum(np.abs(lam_m) > 0.1) == np.sum(np.abs(lam_h) > 0.1) >= 8
    for x, y in ((lam_h, lam_m), (lam_m, lam_h)):  # the well-separated poles match both ways
        for lam in x[np.abs(x) > 0.1]:
            assert np.min(np.abs(y - lam)) < 1e-7, lam


@pytest.mark.parametrize("n_delay", [0, 2])
def test_kf_loop_sensitivity_is_the_hand_written_loops_at_the_plant_input(n_delay):
    """``S = 1/(1 + L)`` of the model against the hand loop's transfer from a disturbance added
    to the plant's input to that input, ``1 + c (zI - A)^-1 b_d``."""
    lp = _kf_loop(n_delay)
    hand = _HandLoop(_kf(), GAINS, n_delay)
    a, _, b_d = hand.matrices()
    c_app = np.array([hand.applied(e) for e in np.eye(hand.size)])
    w = np.array([5.0, 60.0, 700.0, 3000.0, 9000.0])  # rad/s, below Nyquist (12566)
    s_hand = np.array([1.0 + c_app @ np.linalg.solve(np.exp(1j * wi * TS) * np.eye(hand.size) - a, b_d) for wi in w])
    s_model = 1.0 / (1.0 + lp.loop_response(GAINS, w))
    np.testing.assert_allclose(s_model, s_hand, rtol=1e-8)


def test_kf_loop_without_feedforward_has_three_gains_and_ignores_kff():
    lp = _kf_loop(1, feedforward=False)
    assert lp.n_gains == 3
    hand = _HandLoop(_kf(), GAINS[:3] + (0.0,), 1)
    s, speed = np.zeros(hand.size), []
    for _ in range(lp.n_steps):
        speed.append(s[0])
        s = hand.step(s, STEP, 0.0)
    np.testing.assert_allclose(lp.error(GAINS[:3]), -np.asarray(speed), rtol=0, atol=1e-9 * np.max(np.abs(speed)))


def test_kf_duty_cycle_loop_follows_the_hand_written_law():
    """A load profile (mean load per sample) and a setpoint profile with a 2-DOF weight: the
    loop's error ``r - speed`` against the hand-written law fed the same sequences."""
    n = int(round(0.02 / TS))
    k = np.arange(n)
    load = 150.0 * np.sin(2 * np.pi * k / 37.0) + 80.0 * (k > 20)  # N
    ref = np.concatenate([[0.0], 3.0 * (np.arange(1, n + 1) > 10) - 1.5 * (np.arange(1, n + 1) > 50)])  # rad/s
    lp = drive_loop(A, B, C_SPEED, ANGLE, ts=TS, tf=TF, horizon=0.02, load_sequence=load, setpoint_sequence=ref,
                    setpoint_weight=0.6, filters=(("speed_measurement", SPEED_BQ), ("torque_command", TORQUE_BQ)),
                    command_delay_samples=1, measurement=KalmanEstimate(_kf(), True))
    hand = _HandLoop(_kf(), GAINS, 1, weight=0.6)
    s, err = np.zeros(hand.size), []
    for j in range(n):
        err.append(ref[j] - s[0])
        s = hand.step(s, load[j], 0.0, ref[j])
    np.testing.assert_allclose(lp.error(GAINS), err, rtol=0, atol=1e-9 * np.max(np.abs(err)))


def test_the_command_delay_changes_the_kf_loop():
    e0, e2 = _kf_loop(0).error(GAINS), _kf_loop(2).error(GAINS)
    assert np.max(np.abs(e0 - e2)) > 1e-3 * np.max(np.abs(e0))


def test_drive_loop_takes_one_measurement():
    with pytest.raises(ValueError, match="speed_filter = 0.001 with measurement KalmanEstimate"):
        _kf_loop(0, speed_filter=1e-3)
    with pytest.raises(ValueError, match="speed_filter = None; expected"):
        drive_loop(A, B, C_SPEED, ANGLE, ts=TS, tf=TF, horizon=0.02, step=STEP)
    with pytest.raises(ValueError, match="measurement = 'kf'; expected a LoopMeasurement"):
        drive_loop(A, B, C_SPEED, ANGLE, ts=TS, tf=TF, horizon=0.02, step=STEP, measurement="kf")


def test_kalman_block_refuses_a_filter_designed_at_another_sample_time():
    kf = _kf()
    with pytest.raises(ValueError, match="Kalman filter designed at ts = 0.00025 s; expected the loop's sample time"):
        drive_loop(A, B, C_SPEED, ANGLE, ts=2 * TS, tf=TF, horizon=0.02, step=STEP, measurement=KalmanEstimate(kf))


def test_blocks_refuse_what_they_cannot_use():
    with pytest.raises(ValueError, match="kf = 'kf'; expected a KFDesign"):
        KalmanEstimate("kf")
    with pytest.raises(ValueError, match="feedforward = 1; expected True or False"):
        KalmanEstimate(_kf(), 1)
    with pytest.raises(ValueError, match="speed_filter_s = -0.001; expected a positive finite time constant"):
        EncoderDifference(-1e-3)


def test_encoder_block_is_the_default_measurement():
    plain = drive_loop(A, B, C_SPEED, ANGLE, ts=TS, speed_filter=1e-3, tf=TF, horizon=0.02, step=STEP)
    block = drive_loop(A, B, C_SPEED, ANGLE, ts=TS, tf=TF, horizon=0.02, step=STEP,
                       measurement=EncoderDifference(1e-3))
    np.testing.assert_array_equal(plain.A0, block.A0)
    np.testing.assert_array_equal(plain.L, block.L)
