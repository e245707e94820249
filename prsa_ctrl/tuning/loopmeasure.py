"""Speed-measurement blocks of the sampled loop model :func:`prsa_ctrl.tuning.builders.drive_loop`.

The one sampled-loop builder assembles the drive's per-sample law (plant, measurement, speed
filters, PID, torque-command filters, computation and command delay); the block plugged in
says how the speed the PID acts on is measured from the encoder angle, as the simulator's
blocks (:mod:`prsa_ctrl.drive.measurement`) do in the nonlinear runs:

:class:`EncoderDifference`
    the drive's backward difference of the angle over one sample through a first-order
    low-pass (the default);
:class:`KalmanEstimate`
    the steady-state Kalman filter of :func:`prsa_ctrl.drive.estimator.design_kf`, updated
    with the angle and predicted with the command the controller stored at the previous
    sample (the command before the drive's command delay, as the simulator's filter), with an
    optional load-torque feed-forward gain ``kff`` tuned as a fourth gain.

A block gives the builder

- how the loop carries the drifting nut angle (``keeps_angle``): the encoder block needs only
  the angle's increment over the last sample; the Kalman filter needs the angle itself, and the
  builder then keeps only the estimate's error (the angle and its estimate drift together);
- its states' next-value rows, the measured speed row, the previous measured speed row (or
  ``None``: the builder stores it) and the load-estimate row (:meth:`rows`);
- its part of the loop's frequency response (:meth:`response`) and of the controller's noise
  response (:meth:`noise`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from ..drive.sampled import freq_grid, ss_response
from .loops import resonance_points
from .settings import checked_number

if TYPE_CHECKING:
    from ..drive.estimator import KFDesign

__all__ = ["LoopMeasurement", "EncoderDifference", "KalmanEstimate"]


class LoopMeasurement:
    """Interface of a measurement block of the sampled loop model (module docstring)."""

    #: Whether the loop state keeps the nut angle (else its increment over the last sample).
    keeps_angle: bool = False
    #: Number of the block's own loop states.
    n_states: int = 0
    #: Whether the load estimate is fed forward with a fourth tuned gain ``kff``.
    feedforward: bool = False
    #: Whether one of the block's states is the speed it measured at the previous sample (else
    #: the builder stores it, or the last speed-measurement filter's output memory serves).
    keeps_previous_speed: bool = False

    def rows(self, E: NDArray, i_angle: int, i0: int, i_cmd: int, ts: float):
        """``(next_rows, speed, previous_speed, load)`` over the loop state of identity ``E``.

        ``i_angle`` is the state holding the angle (or its increment), ``i0`` the block's
        first state, ``i_cmd`` the command stored at the previous sample (N m). ``next_rows``
        maps each of the block's states to its next-value row; ``speed`` is the measured speed
        row (rad/s), ``previous_speed`` the row of the speed measured at the previous sample
        (``None`` unless ``keeps_previous_speed``), ``load`` the load-torque estimate row (N m)
        or ``None``.
        """
        raise NotImplementedError

    def grid(self, ad: NDArray, ts: float) -> NDArray[np.float64]:
        """Default constraint grid, rad/s."""
        raise NotImplementedError

    def response(self, w, plant, n_dl: int, pid_parts, filt):
        """``(L parts, D parts or None)`` at ``w`` (rad/s): the loop broken at the plant input,
        ``L = sum g_i L_i / (1 + sum g_i D_i)``, one part per tuned gain.

        ``plant`` is ``(ad, bu, c_angle, inc_u, ts)``: the sampled plant the loop carries, the row
        of the angle (or of its increment) and the command's direct part of the increment;
        ``n_dl`` the command delay (samples); ``pid_parts(zi)`` the PID's parts
        (:func:`prsa_ctrl.drive.sampled.pid_frequency_parts`); ``filt(w)`` the loop filters'
        responses ``(all, speed-measurement ones or None, torque-command ones or None)``."""
        raise NotImplementedError

    def noise(self, w, ts: float, pid_parts, filt):
        """The controller per unit gain from a speed-measurement noise to the command (the
        :attr:`~prsa_ctrl.tuning.loops.LoopModel.noise` of the loop), or ``None`` when the
        block has no such path."""
        return None


@dataclass(frozen=True)
class EncoderDifference(LoopMeasurement):
    """Backward difference of the encoder angle over one sample, through a first-order low-pass
    of time constant ``speed_filter_s`` (s): ``w_f <- a w_f + (1 - a) dtheta/Ts``,
    ``a = exp(-Ts / speed_filter_s)``."""

    speed_filter_s: float
    keeps_angle = False
    n_states = 1
    keeps_previous_speed = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "speed_filter_s", checked_number(
            "speed_filter_s", self.speed_filter_s, lo=0.0, expected="a positive finite time constant in s"))

    def alpha(self, ts: float) -> float:
        """The low-pass's pole ``exp(-Ts / speed_filter_s)``."""
        return math.exp(-ts / self.speed_filter_s)

    def rows(self, E, i_angle, i0, i_cmd, ts):
        alpha = self.alpha(ts)
        w_m = E[i_angle] / ts  # backward-difference speed
        w_f_new = alpha * E[i0] + (1 - alpha) * w_m
        return {i0: w_f_new}, w_f_new, E[i0], None

    def grid(self, ad, ts):
        nyq = math.pi / ts
        lam = np.linalg.eigvals(ad) if ad.shape[0] else np.array([], complex)
        lam = lam[np.abs(lam) > 1e-300]
        cont = np.log(lam.astype(complex)) / ts  # continuous-equivalent poles
        return np.unique(np.concatenate([freq_grid(1e-1, nyq * 0.999, 500), resonance_points(cont, 1e-1, nyq * 0.999)]))

    def response(self, w, plant, n_dl, pid_parts, filt):
        ad, bu, inc_x, inc_u, ts = plant
        w = np.asarray(w, float)
        zi = np.exp(-1j * w * ts)
        alpha = self.alpha(ts)
        # Torque command -> angle increment: z^-1 (inc_x (zI - Ad)^-1 bu + inc_u).
        p_inc = zi * (ss_response(ad, bu[:, None], inc_x[None, :], w, lambda x: np.exp(1j * x * ts)) + inc_u)
        meas = (1 - alpha) / (1 - alpha * zi) / ts
        base = zi ** (1 + n_dl) * meas * p_inc * filt(w)[0]  # computation and command delay, filters, speed, plant
        return np.vstack([base * c for c in pid_parts(zi)]), None

    def noise(self, w, ts, pid_parts, filt):
        w = np.asarray(w, float)
        zi = np.exp(-1j * w * ts)
        alpha = self.alpha(ts)
        f_all = (1 - alpha) / (1 - alpha * zi) * filt(w)[0]
        return np.vstack([f_all * c for c in pid_parts(zi)])


@dataclass(frozen=True, eq=False)
class KalmanEstimate(LoopMeasurement):
    """The steady-state Kalman filter ``kf`` (state: angle rad, speed rad/s, motor torque N m,
    load torque N m) as the speed measurement; with ``feedforward`` its load-torque estimate is
    fed forward, ``u += kff * load estimate``, ``kff`` a fourth tuned gain.

    Per sample: the filter updates with the angle, the PID acts on the estimated speed (through
    the speed-measurement filters), and the filter predicts with the command the controller
    stored at the previous sample (after the torque-command filters, before the drive's
    command delay), as :class:`prsa_ctrl.drive.measurement.KalmanSpeed` in the simulator.
    """

    kf: "KFDesign"
    feedforward: bool = False
    keeps_angle = True
    n_states = 4

    def __post_init__(self) -> None:
        from ..drive.estimator import KFDesign

        if not isinstance(self.kf, KFDesign):
            raise ValueError(f"kf = {self.kf!r}; expected a KFDesign (prsa_ctrl.drive.estimator.design_kf)")
        if not isinstance(self.feedforward, bool):
            raise ValueError(f"feedforward = {self.feedforward!r}; expected True or False")

    def rows(self, E, i_angle, i0, i_cmd, ts):
        kf = self.kf
        if abs(kf.ts - ts) > 1e-12 * ts:
            raise ValueError(f"Kalman filter designed at ts = {kf.ts!r} s; expected the loop's sample time {ts!r} s")
        K = kf.K.ravel()
        innov = E[i_angle] - E[i0]  # theta - theta_hat
        post = [E[i0 + r] + K[r] * innov for r in range(4)]  # posterior estimate rows
        nxt = {i0 + r: sum(kf.F[r, c] * post[c] for c in range(4)) + kf.G[r, 0] * E[i_cmd] for r in range(4)}
        return nxt, post[1], None, post[3]

    def grid(self, ad, ts):
        return freq_grid(1e-1, math.pi / ts * 0.999, 500)

    def estimates(self, w, ts: float) -> tuple:
        """``(h_wt, h_wu, h_lt, h_lu)`` at ``w`` (rad/s): the filter's posterior speed (rad/s) and
        load-torque (N m) estimates per unit angle it updates with (rad) and per unit command it
        predicts with (N m, the command stored one sample earlier: ``z^-1`` included)."""
        kf = self.kf
        K = kf.K.ravel()
        w = np.atleast_1d(np.asarray(w, dtype=float))
        ikh = np.eye(4) - np.outer(K, kf.H.ravel())
        a_kf = kf.F @ ikh
        b_th, b_u = kf.F @ K, kf.G.ravel()

        def kf_tf(row, b_in, d_in):
            return ss_response(a_kf, b_in[:, None], (row @ ikh)[None, :], w, lambda x: np.exp(1j * x * ts)) + d_in

        return (kf_tf(np.eye(4)[1], b_th, K[1]), kf_tf(np.eye(4)[1], b_u, 0.0),
                kf_tf(np.eye(4)[3], b_th, K[3]), kf_tf(np.eye(4)[3], b_u, 0.0))

    def _parts(self, w, ts, pid_parts, filt, to_angle, to_cmd):
        """Per gain: the command through the speed and load estimates of the angle (``to_angle``
        multiplies each estimate's response by the path to the angle) and of the command the
        filter predicts with (``to_cmd``): the ``L`` and ``D`` parts."""
        h_wt, h_wu, h_lt, h_lu = self.estimates(w, ts)
        zi = np.exp(-1j * w * ts)
        f_speed, f_torque = filt(w)[1:]
        Lg = [to_angle(ci * h_wt) for ci in pid_parts(zi)]
        Dg = [to_cmd(ci * h_wu) for ci in pid_parts(zi)]
        if f_speed is not None:  # the speed filters act on the estimate, the torque filters on the command
            Lg, Dg = [x * f_speed for x in Lg], [x * f_speed for x in Dg]
        if self.feedforward:  # u += kff * load estimate (not through the speed filters)
            Lg.append(to_angle(-h_lt))
            Dg.append(to_cmd(-h_lu))
        if f_torque is not None:
            Lg, Dg = [x * f_torque for x in Lg], [x * f_torque for x in Dg]
        return np.vstack(Lg), np.vstack(Dg)

    def response(self, w, plant, n_dl, pid_parts, filt):
        ad, bu, c_th, _, ts = plant
        w = np.atleast_1d(np.asarray(w, dtype=float))
        zi = np.exp(-1j * w * ts)
        zd = zi if not n_dl else zi ** (1 + n_dl)  # computation and command delay to the plant
        p_th = ss_response(ad, bu[:, None], c_th[None, :], w, lambda x: np.exp(1j * x * ts))  # torque -> angle
        return self._parts(w, ts, pid_parts, filt, lambda x: x * p_th * zd, lambda x: x * zi)

    def noise(self, w, ts, pid_parts, filt):
        """Per gain, the command (N m) per unit speed noise (rad/s) as the encoder's backward
        difference reads it: an angle noise ``n`` (rad) the filter updates with, expressed as the
        difference speed ``(1 - z^-1) n / Ts`` it would give, the noise input of
        :class:`EncoderDifference` (so Mks bounds the same encoder noise with either block).
        With the loop's denominator part: ``C F S = g.K / (1 + g.D + g.N)``
        (:meth:`~prsa_ctrl.tuning.loops.LoopModel.noise_response`)."""
        w = np.atleast_1d(np.asarray(w, dtype=float))
        per_speed = ts / (1.0 - np.exp(-1j * w * ts))  # rad per rad/s of difference speed
        return self._parts(w, ts, pid_parts, filt, lambda x: x * per_speed, lambda x: x * per_speed)[0]
