"""Speed and load estimation with a Kalman filter (filterpy), and load feed-forward.

Real drives differentiate a quantised encoder angle and see the load only through its effect.
The filter here estimates ``x = [angle (rad), speed (rad/s), motor torque (N m), load torque
(N m)]`` from the quantised angle and the applied torque command, on the rigid reflected
inertia with the current-loop lag; the load torque (everything that opposes the motor: axial
load through the lead, friction, drag) is a random walk.

Noise model, from the plant's sensor section:

- measurement: uniform quantisation of the encoder, ``R = q^2 / 12`` with
  ``q = 2 pi / counts``;
- torque: the motor-current measurement noise ``sensor.torque_noise_n_m`` (std per sample)
  enters as torque ripple, so ``Q`` gets ``sigma_tau^2`` on the motor-torque state;
- load: a random walk that can cover the plant's rated load torque within
  ``load_change_time_s`` (default 1 s, a design choice measured on the paper step: 0.3 / 1 / 3 s give
  a feed-forward peak drop of 2.04 / 2.14 / 2.26 rad/s and, with a 14-bit encoder, a speed RMS error
  4.96 / 5.7 / 5.9 times below backward differences): ``sigma_L^2 = tau_rated^2 Ts / T``.

This module only designs the filter (and its linear loop model for the tuner); the filter
runs inside the one sampled-loop simulator as the measurement block
:class:`prsa_ctrl.drive.measurement.KalmanSpeed` (``run(..., discrete=True, measurement="kf")``).
filterpy is imported only by :meth:`KFDesign.make_filter`, the reference the tests hold the
in-loop filter against.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import expm

from ..plant.plantfile import Plant

__all__ = ["KFDesign", "design_kf", "kf_drive_loop", "DEFAULT_LOAD_CHANGE_TIME_S"]

#: Time over which the load torque may change by its rated value (assumption), s.
DEFAULT_LOAD_CHANGE_TIME_S = 1.0


@dataclass(frozen=True, eq=False)
class KFDesign:
    """A steady-state-ready Kalman filter design (discrete, at the controller sample time).

    ``F, G`` propagate the state over one sample with the applied torque command held; ``H``
    picks the angle; ``Q, R`` are the noise covariances; ``K`` and ``P`` the steady-state gain
    and prior covariance (from filterpy's own recursion).
    """

    F: NDArray[np.float64]
    G: NDArray[np.float64]
    H: NDArray[np.float64]
    Q: NDArray[np.float64]
    R: float
    K: NDArray[np.float64]
    P: NDArray[np.float64]
    ts: float
    inertia: float

    def make_filter(self, x0: NDArray[np.float64]):
        """A filterpy ``KalmanFilter`` with this design, started in steady state at ``x0``."""
        from filterpy.kalman import KalmanFilter

        kf = KalmanFilter(dim_x=4, dim_z=1, dim_u=1)
        kf.F, kf.B, kf.H = self.F.copy(), self.G.copy(), self.H.copy()
        kf.Q, kf.R = self.Q.copy(), np.array([[self.R]])
        kf.x = np.asarray(x0, dtype=float).reshape(4, 1)
        kf.P = self.P.copy()
        return kf


def design_kf(plant: Plant, load_change_time_s: float = DEFAULT_LOAD_CHANGE_TIME_S) -> KFDesign:
    """Design the speed/load Kalman filter of ``plant`` (see module docstring).

    Parameters
    ----------
    plant : Plant
    load_change_time_s : float, s
        Time in which the load torque may change by its rated value (sets the load random walk).

    The steady-state prior covariance solves the discrete Riccati equation (scipy); running
    filterpy's own predict/update recursion converges to the same matrix (tested).
    """
    if not (load_change_time_s > 0 and math.isfinite(load_change_time_s)):
        raise ValueError(f"load_change_time_s = {load_change_time_s!r}; expected a positive time in s")
    from scipy.linalg import solve_discrete_are

    ts = plant.sample_time_s
    j = plant.reflected_inertia_kg_m2
    t_c = plant.current_loop_time_constant_s
    a = np.array([[0, 1, 0, 0], [0, 0, 1 / j, -1 / j], [0, 0, -1 / t_c, 0], [0, 0, 0, 0]], float)
    b = np.array([[0], [0], [1 / t_c], [0]], float)
    blk = np.zeros((5, 5))
    blk[:4, :4], blk[:4, 4:] = a * ts, b * ts
    e = expm(blk)
    F, G = e[:4, :4], e[:4, 4:]
    q = 2 * math.pi / plant.encoder_counts
    R = q * q / 12.0
    tau_rated = plant.rated_load_n * plant.lead_per_rad / plant.values["friction.efficiency"]
    sigma_l2 = tau_rated**2 * ts / load_change_time_s
    sigma_t = plant.values["sensor.torque_noise_n_m"]
    Q = sigma_t**2 * (G @ G.T)  # ripple on the applied torque command, through the current loop
    Q[3, 3] += sigma_l2
    Q += np.eye(4) * 1e-30  # keeps the Riccati equation well posed if every noise is zero
    H = np.array([[1.0, 0, 0, 0]])
    P = solve_discrete_are(F.T, H.T, Q, np.array([[R]]))  # steady-state prior covariance
    K = (P @ H.T) / (float((H @ P @ H.T).item()) + R)
    return KFDesign(F, G, H, Q, R, K, P, ts, j)


def kf_drive_loop(a, b, c_speed, angle_index: int, kf: KFDesign, *, tf: float, horizon: float, step: float,
                  feedforward: bool, omega: NDArray | None = None, name: str = "drive+KF",
                  outputs: dict | None = None):
    """Loop model of the sampled drive with the Kalman filter in the loop (see
    :func:`prsa_ctrl.tuning.tuner.drive_loop` for the plain one).

    Parameters
    ----------
    a, b : ndarray
        Continuous plant Jacobians with the nut angle kept (inputs torque command, load).
    c_speed : ndarray
        Output row of the nut speed.
    angle_index : int
        Index of the nut angle state.
    kf : KFDesign
    tf : float, s
        Derivative-filter time constant.
    horizon : float, s
    step : float, N
        Load step of the objective's disturbance.
    feedforward : bool
        Tune the load feed-forward gain ``kff`` as a fourth gain.
    omega : array, rad/s, optional
        Frequency grid (default up to the Nyquist frequency).
    name : str
    outputs : dict, optional
        Extra output rows to record along the trajectory.

    Per sample: the filter updates with the angle, the PID acts on the estimated speed (plus the
    estimated load torque if ``feedforward``), the command is applied one sample later, and the
    filter predicts with the applied command. The absolute angle and its estimate drift
    together; the loop keeps only the estimation error of the angle. With ``feedforward`` the
    load feed-forward gain ``kff`` is a fourth tuned gain (``u += kff * load estimate``).
    """
    from ..tuning.tuner import LoopModel, _freq_grid, _pid_frequency_parts, _pid_rows, _ss_response, _zoh

    ts = kf.ts
    n_steps = max(10, int(round(horizon / ts)))
    ad, bd_all = _zoh(np.asarray(a, float), np.asarray(b, float), ts)
    bu, bdist = bd_all[:, 0], bd_all[:, 1]
    n = ad.shape[0]
    c_w = np.asarray(c_speed, float).ravel()
    c_th = np.eye(n)[angle_index]
    beta = math.exp(-ts / tf)
    K = kf.K.ravel()
    # Full coordinates X = [x (plant, with angle), xh (prior estimate, 4), d, I, w_prev, u_pending]
    ix = slice(0, n)
    i_d, i_i, i_wp, i_u = n + 4, n + 5, n + 6, n + 7
    N = n + 8
    E = np.eye(N)
    innov = np.zeros(N)
    innov[ix] = c_th
    innov[n] = -1.0  # theta - theta_hat
    post = [E[n + r] + K[r] * innov for r in range(4)]  # posterior estimate rows
    w_hat, tl_hat = post[1], post[3]
    d_new = beta * E[i_d] + (1 - beta) * (w_hat - E[i_wp]) / ts
    e_meas = -w_hat
    A0 = np.zeros((N, N))
    A0[ix, ix] = ad
    A0[ix, i_u] = bu
    for r in range(4):
        A0[n + r] = sum(kf.F[r, c] * post[c] for c in range(4)) + kf.G[r, 0] * E[i_u]
    A0[i_d] = d_new
    A0[i_i, i_i] = 1.0
    A0[i_wp] = w_hat
    A0[i_u] = E[i_i]  # u = kp e + I - kd d (+ kff * load estimate)
    a_kp, a_ki, a_kd = _pid_rows(N, i_u, i_i, e_meas, d_new, ts)
    a_ff = np.zeros((N, N))
    a_ff[i_u] = tl_hat
    gain_mats = (A0, a_kp, a_ki, a_kd) + ((a_ff,) if feedforward else ())
    bdv = np.zeros(N)
    bdv[ix] = bdist * step
    ce = np.zeros(N)
    ce[ix] = -c_w
    # Drop the common drift: replace theta_hat by eps = theta_hat - theta, then delete theta.
    M = np.eye(N)
    M[n, angle_index] = -1.0
    Mi = np.linalg.inv(M)
    keep = [i for i in range(N) if i != angle_index]
    mats = []
    for A_ in gain_mats:
        At = M @ A_ @ Mi
        col = np.delete(At[:, angle_index], angle_index)
        if np.max(np.abs(col)) > 1e-9 * max(1.0, np.max(np.abs(At))):
            raise ArithmeticError("the loop depends on the absolute angle; expected only angle differences")
        mats.append(At[np.ix_(keep, keep)])
    bdv = (M @ bdv)[keep]
    ce = (ce @ Mi)[keep]
    extra = {}
    for k, r in (outputs or {}).items():
        row = np.zeros(N)
        row[ix] = np.asarray(r, float).ravel()
        extra[k] = (row @ Mi)[keep]
    # Frequency response: L = N/D with N, D affine in the gains (see LoopModel), at any
    # frequencies (the tuner refines its Ms search off the grid).
    if omega is None:
        omega = _freq_grid(1e-1, math.pi / ts * 0.999, 500)
    a_kf = kf.F @ (np.eye(4) - np.outer(K, kf.H.ravel()))
    b_th, b_u = kf.F @ K, kf.G.ravel()
    ikh = np.eye(4) - np.outer(K, kf.H.ravel())

    def response(w):
        w = np.atleast_1d(np.asarray(w, dtype=float))
        zi = np.exp(-1j * w * ts)

        def z_of(x):
            return np.exp(1j * x * ts)

        p_th = _ss_response(ad, bu[:, None], c_th[None, :], w, z_of)  # applied torque -> angle

        def kf_tf(row, b_in, d_in):
            return _ss_response(a_kf, b_in[:, None], (row @ ikh)[None, :], w, z_of) + d_in

        h_wt, h_wu = kf_tf(np.eye(4)[1], b_th, K[1]), kf_tf(np.eye(4)[1], b_u, 0.0)
        h_lt, h_lu = kf_tf(np.eye(4)[3], b_th, K[3]), kf_tf(np.eye(4)[3], b_u, 0.0)
        c = _pid_frequency_parts(zi, ts, beta)
        Lg = [ci * h_wt * p_th * zi for ci in c]
        Dg = [ci * h_wu * zi for ci in c]
        if feedforward:  # u += kff * load estimate
            Lg.append(-h_lt * p_th * zi)
            Dg.append(-h_lu * zi)
        return None, np.vstack(Lg), None, np.vstack(Dg)

    _, L, _, D = response(omega)
    return LoopModel(mats[0], tuple(mats[1:]), bdv, ce, ts, n_steps, omega, L, tf, name=name,
                     outputs=extra, N0=None, D0=None, D=D, response=response, nyquist=math.pi / ts)
