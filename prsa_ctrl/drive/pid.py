"""The speed controller: a PID on nut speed with anti-windup and a derivative filter.

The same law runs in continuous time (inside the ODE) or at the drive's sample time with a
zero-order hold, a one-sample computation delay and a quantised encoder (see
:mod:`prsa_ctrl.simulate`). Gains are SI: ``kp`` in N m s/rad, ``ki`` in N m/rad, ``kd`` in
N m s^2/rad.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import casadi as ca

from ..options import check_number

if TYPE_CHECKING:
    import control

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
        provides the load torque, see :mod:`prsa_ctrl.drive.estimator`).
    """

    kp: float
    ki: float = 0.0
    kd: float = 0.0
    tf: float = 1e-3
    kff: float = 0.0

    def __post_init__(self) -> None:
        for name in ("kp", "ki", "kd", "kff"):
            check_number(f"PID {name}", getattr(self, name), 0.0)
        check_number("PID tf", self.tf, 0.0, lo_open=True, expected="a finite time constant > 0 s")

    @property
    def params(self) -> list[float]:
        return [float(self.kp), float(self.ki), float(self.kd), float(self.tf)]

    @property
    def gains(self) -> list[float]:
        """``[kp, ki, kd, kff]`` as the loop models take them."""
        return [float(self.kp), float(self.ki), float(self.kd), float(self.kff)]

    def as_dict(self) -> dict[str, float]:
        return {"kp": self.kp, "ki": self.ki, "kd": self.kd, "tf": self.tf, "kff": self.kff}

    def _check_dt(self, dt: float | None) -> float | None:
        return check_number("PID sample time dt", dt, 0.0, lo_open=True, optional=True,
                            expected="None (continuous) or a sample time > 0 s")

    def to_ss(self, dt: float | None = None) -> "control.StateSpace":
        """The PID as a python-control state-space system from speed error to torque command.

        Continuous (``dt=None``): ``C(s) = kp + ki/s + kd s/(1 + tf s)``. Sampled (``dt`` in s,
        usually ``plant.sample_time_s``): the law the toolkit's drive runs every sample,
        ``u[k] = kp e[k] + I[k] + kd d[k]`` with ``I[k+1] = I[k] + dt ki e[k]`` and the derivative
        filter matched at ``beta = exp(-dt/tf)``, ``d[k] = beta d[k-1] + (1 - beta)(e[k] - e[k-1])/dt``,
        i.e. ``C(z) = kp + ki dt/(z - 1) + kd (1 - beta)(z - 1)/(dt (z - beta))``. Its output is held
        between samples (zero-order hold): close the loop with the plant sampled by
        ``control.sample_system(P, dt, "zoh")``. The drive's one-sample computation delay, speed
        filter and encoder difference belong to the measurement, not to this law.

        In the toolkit the derivative acts on the measured speed only (no setpoint kick); for a
        load disturbance at a constant setpoint that is the same as acting on the error.
        States are kept only for the parts in use (``ki > 0``: ``pid_integral``; ``kd > 0``:
        ``pid_derivative``); ``kff`` (estimator feed-forward) is not part of this system.

        Parameters
        ----------
        dt : float or None, s
            Sample time of the discrete law; ``None`` for the continuous PID.

        Returns
        -------
        control.StateSpace
            Input ``speed_error`` (rad/s), output ``torque_command`` (N m), time base ``dt``
            (0 when continuous).

        Examples
        --------
        >>> C = PID(0.085, 14.7).to_ss()
        >>> C.input_labels, C.output_labels, C.nstates
        (['speed_error'], ['torque_command'], 1)
        >>> round(abs(complex(C(100j))), 4)  # |kp + ki/(j 100)| in N m per rad/s
        0.1698
        >>> Cz = PID(0.085, 14.7, kd=1e-4, tf=1e-3).to_ss(dt=2.5e-4)
        >>> Cz.dt, Cz.nstates
        (0.00025, 2)
        """
        import control
        import numpy as np

        dt = self._check_dt(dt)
        kp, ki, kd, tf = float(self.kp), float(self.ki), float(self.kd), float(self.tf)
        a, b, c, states = [], [], [], []
        d = kp
        if dt is None:
            if ki > 0:  # x' = e, u += ki x
                a.append(0.0), b.append(1.0), c.append(ki), states.append("pid_integral")
            if kd > 0:  # kd s/(1 + tf s) = kd/tf (1 - 1/(1 + tf s)): x' = (e - x)/tf
                a.append(-1.0 / tf), b.append(1.0 / tf), c.append(-kd / tf), states.append("pid_derivative")
                d += kd / tf
        else:
            if ki > 0:  # x[k+1] = x[k] + e[k], u += ki dt x
                a.append(1.0), b.append(1.0), c.append(ki * dt), states.append("pid_integral")
            if kd > 0:  # (1 - beta)/dt (z - 1)/(z - beta) = g (1 + (beta - 1)/(z - beta))
                beta = math.exp(-dt / tf)
                g = (1.0 - beta) / dt
                a.append(beta), b.append(1.0), c.append(kd * g * (beta - 1.0)), states.append("pid_derivative")
                d += kd * g
        n = len(states)
        return control.ss(
            np.diag(a).reshape(n, n), np.array(b).reshape(n, 1), np.array(c).reshape(1, n), [[d]],
            dt if dt is not None else 0, inputs=["speed_error"], outputs=["torque_command"],
            states=states, name="pid",
        )

    def to_tf(self, dt: float | None = None) -> "control.TransferFunction":
        """The PID as a python-control transfer function from speed error (rad/s) to torque
        command (N m); see :meth:`to_ss` for the continuous and sampled (``dt`` s) laws.

        Parameters
        ----------
        dt : float or None, s
            Sample time of the discrete law; ``None`` for the continuous PID.

        Returns
        -------
        control.TransferFunction
            ``C(s)`` or, sampled, ``C(z)`` with time base ``dt``.

        Examples
        --------
        >>> C = PID(0.085, 14.7).to_tf()
        >>> [round(float(v), 4) for v in C.num[0][0]], [round(float(v), 4) for v in C.den[0][0]]
        ([0.085, 14.7], [1.0, 0.0])
        >>> Cz = PID(0.085, 14.7).to_tf(dt=2.5e-4)
        >>> [round(float(v), 6) for v in Cz.num[0][0]], [round(float(v), 6) for v in Cz.den[0][0]]
        ([0.085, -0.081325], [1.0, -1.0])
        """
        import control

        ss = self.to_ss(dt)
        kp, ki, kd, tf = float(self.kp), float(self.ki), float(self.kd), float(self.tf)
        dt = self._check_dt(dt)
        if dt is None:  # exact polynomial form, no state-space round trip
            s = control.tf("s")
            c = kp + (ki / s if ki > 0 else 0) + (kd * s / (1 + tf * s) if kd > 0 else 0)
        else:
            z = control.tf([1.0, 0.0], [1.0], dt)
            beta = math.exp(-dt / tf)
            c = kp + (ki * dt / (z - 1) if ki > 0 else 0) + (kd * (1 - beta) * (z - 1) / (dt * (z - beta)) if kd > 0 else 0)
        c = c if isinstance(c, control.TransferFunction) else control.tf([c], [1.0], ss.dt)
        return control.tf(c.num, c.den, ss.dt, inputs=["speed_error"], outputs=["torque_command"], name="pid")


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
