"""The drive's per-sample law with the Kalman filter as its speed measurement, written out by
hand (plain NumPy, no builder code): the independent reference of the sampled-loop builder
(``tests/tuning/test_builders.py``) and of the filter tuner's Ms/Mt claims
(``tests/tuning/test_filtered.py``). tests/tuning is on sys.path."""

import math

import numpy as np
from scipy.linalg import expm, solve_discrete_are

from prsa_ctrl.drive.estimator import KFDesign
from prsa_ctrl.drive.filters import DiscreteBiquad

__all__ = ["TS", "J", "TC", "LEAD", "TF", "A", "B", "C_SPEED", "ANGLE", "STEP", "SPEED_BQ", "TORQUE_BQ", "GAINS",
           "IDENTITY_BQ", "zoh", "toy_kf", "HandLoop"]

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
IDENTITY_BQ = DiscreteBiquad(1.0, 0.0, 0.0, 0.0, 0.0, TS)  # no filter on that path
GAINS = (0.3, 15.0, 2e-4, 0.4)  # kp N m s/rad, ki N m/rad, kd N m s^2/rad, kff


def zoh(a, b):
    n, m = a.shape[0], b.shape[1]
    blk = np.zeros((n + m, n + m))
    blk[:n, :n], blk[:n, n:] = a * TS, b * TS
    e = expm(blk)
    return e[:n, :n], e[:n, n:]


def toy_kf() -> KFDesign:
    """A steady-state Kalman filter of [angle, speed, motor torque, load torque] (the plant's
    own dynamics plus a load random walk), its gain from scipy's Riccati solver."""
    a = np.array([[0, 1, 0, 0], [0, 0, 1 / J, -1 / J], [0, 0, -1 / TC, 0], [0, 0, 0, 0]], float)
    f, g = zoh(a, np.array([[0.0], [0.0], [1.0 / TC], [0.0]]))
    h = np.array([[1.0, 0.0, 0.0, 0.0]])
    q = 1e-4 * (g @ g.T) + np.diag([0.0, 0.0, 0.0, 1e-3])
    r = (2 * math.pi / 2**16) ** 2 / 12
    p = solve_discrete_are(f.T, h.T, q, np.array([[r]]))
    k = (p @ h.T) / (float((h @ p @ h.T).item()) + r)
    return KFDesign(f, g, h, q, r, k, p, TS, J)


class HandLoop:
    """The drive's per-sample law as the simulator runs it, written out state by state: the
    filter updates with the angle, the speed biquad filters its speed, the PID (plus kff times
    the load estimate) computes the command, the torque biquad filters it, the command stored
    at the previous sample goes down the delay line (the oldest drives the plant over the
    sample, plus an input disturbance ``d``) and the filter predicts with the stored command; an
    angle noise ``n`` (rad) adds to the angle the filter updates with."""

    def __init__(self, kf: KFDesign, gains, n_delay: int, weight: float = 1.0, speed_bq: DiscreteBiquad = SPEED_BQ,
                 torque_bq: DiscreteBiquad = TORQUE_BQ):
        self.kf, self.gains, self.n_delay, self.weight = kf, gains, n_delay, weight
        self.speed_bq, self.torque_bq = speed_bq, torque_bq
        self.ad, bd = zoh(A, B)
        self.bu, self.bl = bd[:, 0], bd[:, 1]
        # Layout: x(3), kf prior(4), I, d, w_prev, u_pend, speed biquad(4), torque biquad(4), delay line.
        self.size = 3 + 4 + 4 + 8 + n_delay

    def split(self, s):
        return s[:3], s[3:7], s[7], s[8], s[9], s[10], s[11:15], s[15:19], s[19:]

    def applied(self, s):
        line, u_pend = self.split(s)[8], self.split(s)[5]
        return line[0] if self.n_delay else u_pend

    def step(self, s, load: float, d: float, ref: float = 0.0, n: float = 0.0):
        kp, ki, kd, kff = self.gains
        x, m, integral, deriv_old, w_prev, u_pend, mb_s, mb_t, line = self.split(np.asarray(s, float))
        K = self.kf.K.ravel()
        post = m + K * (x[ANGLE] + n - m[0])
        w_raw, tl_hat = post[1], post[3]
        bq = self.speed_bq
        w_meas = bq.b0 * w_raw + bq.b1 * mb_s[0] + bq.b2 * mb_s[1] - bq.a1 * mb_s[2] - bq.a2 * mb_s[3]
        mb_s = np.array([w_raw, mb_s[0], w_meas, mb_s[2]])
        beta = math.exp(-TS / TF)
        deriv = beta * deriv_old + (1 - beta) * (w_meas - w_prev) / TS
        e = ref - w_meas
        u = kp * (self.weight * ref - w_meas) + integral - kd * deriv + kff * tl_hat
        bq = self.torque_bq
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

    def sensitivity(self, w):
        """``S`` at the plant input at ``w`` (rad/s): the transfer from a disturbance added to
        the applied command to the applied command, ``1 + c (zI - A)^-1 b_d``."""
        a, _, b_d = self.matrices()
        c_app = np.array([self.applied(e) for e in np.eye(self.size)])
        eye = np.eye(self.size)
        return np.array([1.0 + c_app @ np.linalg.solve(np.exp(1j * wi * TS) * eye - a, b_d) for wi in np.atleast_1d(w)])

    def noise_gain(self, w):
        """``|C F S|`` at ``w`` (rad/s): the filtered command's response (N m) to an angle noise
        the filter updates with, per rad/s of the speed the encoder's backward difference reads
        from that noise, ``(1 - z^-1) n / Ts``."""
        a, _, _ = self.matrices()
        b_n = self.step(np.zeros(self.size), 0.0, 0.0, n=1.0)
        c_cmd = np.eye(self.size)[10]  # the filtered command, stored for the next sample
        eye = np.eye(self.size)
        out = []
        for wi in np.atleast_1d(w):
            z = np.exp(1j * wi * TS)
            out.append(abs(c_cmd @ np.linalg.solve(z * eye - a, b_n)) * TS / abs(1.0 - 1.0 / z))
        return np.array(out)
