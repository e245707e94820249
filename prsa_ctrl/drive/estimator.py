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
from scipy.linalg import solve_discrete_are

from .._lazy import module
from ..plant.plantfile import Plant
from .sampled import zoh

kalman = module("filterpy.kalman")  # only the reference filter (KFDesign.make_filter) needs filterpy

__all__ = ["KFDesign", "design_kf", "DEFAULT_LOAD_CHANGE_TIME_S"]

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
        kf = kalman.KalmanFilter(dim_x=4, dim_z=1, dim_u=1)
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
    ts = plant.sample_time_s
    j = plant.reflected_inertia_kg_m2
    t_c = plant.current_loop_time_constant_s
    a = np.array([[0, 1, 0, 0], [0, 0, 1 / j, -1 / j], [0, 0, -1 / t_c, 0], [0, 0, 0, 0]], float)
    b = np.array([[0], [0], [1 / t_c], [0]], float)
    F, G = zoh(a, b, ts)
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
