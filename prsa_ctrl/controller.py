"""The speed controller: a PID on nut speed with anti-windup and a derivative filter.

The same law runs in continuous time (inside the ODE) or at the drive's sample time with a
zero-order hold, a one-sample computation delay and a quantised encoder (see
:mod:`prsa_ctrl.simulate`). Gains are SI: ``kp`` in N m s/rad, ``ki`` in N m/rad, ``kd`` in
N m s^2/rad.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import casadi as ca

__all__ = ["PID", "pid_law"]


@dataclass(frozen=True)
class PID:
    """PID gains of the speed loop (output: torque command, N m).

    Parameters
    ----------
    kp : float, N m s/rad
        Proportional gain on the speed error.
    ki : float, N m/rad
        Integral gain.
    kd : float, N m s^2/rad
        Derivative gain, acting on the measured speed (no setpoint kick).
    tf : float, s
        Time constant of the derivative filter ``kd s / (1 + tf s)``.
    kff : float
        Gain of the load-torque feed-forward (dimensionless; used only with an estimator that
        provides the load torque, see :mod:`prsa_ctrl.estimator`).
    """

    kp: float
    ki: float = 0.0
    kd: float = 0.0
    tf: float = 1e-3
    kff: float = 0.0

    def __post_init__(self) -> None:
        for name in ("kp", "ki", "kd", "kff"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"PID {name} = {v!r}; expected a finite number >= 0")
        if not isinstance(self.tf, (int, float)) or not math.isfinite(self.tf) or self.tf <= 0:
            raise ValueError(f"PID tf = {self.tf!r}; expected a finite time constant > 0 s")

    @property
    def params(self) -> list[float]:
        return [float(self.kp), float(self.ki), float(self.kd), float(self.tf)]

    @property
    def gains(self) -> list[float]:
        """``[kp, ki, kd, kff]`` as the loop models take them."""
        return [float(self.kp), float(self.ki), float(self.kd), float(self.kff)]

    def as_dict(self) -> dict[str, float]:
        return {"kp": self.kp, "ki": self.ki, "kd": self.kd, "tf": self.tf, "kff": self.kff}


def pid_law(error, integral, derivative, gains, tau_ff, torque_limit: float):
    """Torque command and integrator rate of the PID with back-calculation anti-windup.

    Parameters
    ----------
    error : rad/s
        Setpoint minus measured speed.
    integral : N m
        Integral state (already in torque units).
    derivative : rad/s^2
        Filtered derivative of the measured speed.
    gains : sequence
        ``[kp, ki, kd, tf]`` (symbolic or numeric).
    tau_ff : N m
        Feed-forward torque added to the command.
    torque_limit : float, N m
        Saturation of the command; the integrator is driven back with tracking time ``kp/ki``.

    Returns
    -------
    command, saturated command, d(integral)/dt
    """
    kp, ki, kd = gains[0], gains[1], gains[2]
    u = kp * error + integral - kd * derivative + tau_ff
    u_sat = ca.fmin(ca.fmax(u, -torque_limit), torque_limit)
    k_aw = ki / ca.fmax(kp, 1e-9)
    return u, u_sat, ki * error + k_aw * (u_sat - u)
