"""Speed measurements of the sampled drive, as pluggable blocks of the one sampled-loop law.

The drive samples the quantised encoder angle once per controller sample. A measurement block
turns that angle into the speed the PID acts on (and, for an observer, an estimate of the load
torque). Each block is written in CasADi so the whole per-sample law of
:mod:`prsa_ctrl.simulation` (quantise, measure, PID, one-sample delay, integrate the plant) is
one compiled function, whichever measurement is plugged in.

A block has a memory vector (carried from sample to sample) and two steps:

``update(mem, theta_q, theta_prev_q) -> (speed rad/s, load torque estimate N m, mem)``
    at the sampling instant, with the new and previous quantised angles (rad);
``predict(mem, u_applied) -> mem``
    over the sample, knowing the torque command applied during it (N m).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import casadi as ca

if TYPE_CHECKING:
    from .estimator import KFDesign
    from .plant import Plant

__all__ = ["SpeedMeasurement", "EncoderDifference", "KalmanSpeed", "measurement_for"]


class SpeedMeasurement:
    """Interface of a speed-measurement block (see the module docstring)."""

    #: Short name stored in the run's ``info``.
    name: str = ""
    #: Names of the memory entries (they become state rows of a sampled run).
    memory_names: tuple[str, ...] = ()
    #: Whether the block estimates the load torque (needed by load feed-forward, ``kff > 0``).
    estimates_load: bool = False

    def initial(self, theta: float, omega: float, torque: float) -> list[float]:
        """Memory at a steady state with nut angle ``theta`` (rad), speed ``omega`` (rad/s) and
        torque ``torque`` (N m, motor torque equal to the load torque)."""
        raise NotImplementedError

    def update(self, mem: ca.SX, theta_q: ca.SX, theta_prev_q: ca.SX) -> tuple[Any, Any, ca.SX]:
        raise NotImplementedError

    def predict(self, mem: ca.SX, u_applied: ca.SX) -> ca.SX:
        raise NotImplementedError

    def key(self) -> tuple:
        """Identity of the compiled law (blocks with equal keys share one CasADi function)."""
        raise NotImplementedError


@dataclass(frozen=True)
class EncoderDifference(SpeedMeasurement):
    """The drive's standard measurement: backward difference of the quantised angle over one
    sample, through a first-order low-pass of time constant ``filter_s`` (exact discretisation
    ``w_f <- a w_f + (1 - a) w_diff`` with ``a = exp(-Ts / filter_s)``).

    Parameters
    ----------
    ts : float, s
        Controller sample time.
    filter_s : float, s
        Speed-filter time constant.
    """

    ts: float
    filter_s: float
    name = "encoder"
    memory_names = ("speed_filtered",)

    def initial(self, theta: float, omega: float, torque: float) -> list[float]:
        return [omega]

    def update(self, mem, theta_q, theta_prev_q):
        alpha = math.exp(-self.ts / self.filter_s)
        w_f = alpha * mem[0] + (1 - alpha) * (theta_q - theta_prev_q) / self.ts
        return w_f, 0.0, ca.vertcat(w_f)

    def predict(self, mem, u_applied):
        return mem

    def key(self) -> tuple:
        return ("encoder", self.ts, self.filter_s)


@dataclass(frozen=True, eq=False)
class KalmanSpeed(SpeedMeasurement):
    """Steady-state Kalman filter of :func:`prsa_ctrl.estimator.design_kf`: state
    ``[angle rad, speed rad/s, motor torque N m, load torque N m]``, updated with the quantised
    angle and propagated with the applied command.

    Started in steady state with the design's steady-state covariance, filterpy's
    predict/update recursion keeps that covariance and gain, so this fixed-gain form is the
    same filter (tested against filterpy).
    """

    design: "KFDesign"
    name = "kf"
    memory_names = ("kf_angle", "kf_speed", "kf_motor_torque", "kf_load_torque")
    estimates_load = True

    def initial(self, theta: float, omega: float, torque: float) -> list[float]:
        return [theta, omega, torque, torque]

    def update(self, mem, theta_q, theta_prev_q):
        k = self.design.K.ravel()
        innov = theta_q - mem[0]
        post = ca.vertcat(*[mem[i] + float(k[i]) * innov for i in range(4)])
        return post[1], post[3], post

    def predict(self, mem, u_applied):
        f, g = self.design.F, self.design.G.ravel()
        return ca.vertcat(*[sum(float(f[r, c]) * mem[c] for c in range(4)) + float(g[r]) * u_applied
                            for r in range(4)])

    def key(self) -> tuple:
        d = self.design
        return ("kf", d.ts, tuple(d.K.ravel()), tuple(d.F.ravel()), tuple(d.G.ravel()))


def measurement_for(plant: "Plant", kind: "str | SpeedMeasurement", kf: "KFDesign | None" = None) -> SpeedMeasurement:
    """The measurement block named ``kind`` for ``plant``.

    Parameters
    ----------
    plant : Plant
    kind : {"encoder", "kf"} or SpeedMeasurement
        ``"encoder"``: filtered backward difference (the drive's default); ``"kf"``: the Kalman
        filter ``kf`` (default :func:`prsa_ctrl.estimator.design_kf` of the plant).
    kf : KFDesign, optional
    """
    if isinstance(kind, SpeedMeasurement):
        return kind
    if kind == "encoder":
        return EncoderDifference(plant.sample_time_s, plant.speed_filter_s)
    if kind == "kf":
        if kf is None:
            from .estimator import design_kf

            kf = design_kf(plant)
        if abs(kf.ts - plant.sample_time_s) > 1e-12 * plant.sample_time_s:
            raise ValueError(f"Kalman filter sample time {kf.ts} s differs from the plant's {plant.sample_time_s} s")
        return KalmanSpeed(kf)
    raise ValueError(f"measurement = {kind!r}; expected 'encoder', 'kf' or a SpeedMeasurement")

