"""The drive's speed PID around the linearised plant, as python-control systems.

:func:`pid_controller` is the continuous PID, :func:`closed_loop` closes it around a plant from
:func:`prsa_ctrl.plant.linear.linearize`, and :func:`predict_load_step` is the closed loop's
response to a load step.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .pid import PID

if TYPE_CHECKING:  # annotations only: python-control is imported where it is used
    import control

__all__ = ["pid_controller", "closed_loop", "predict_load_step"]


def pid_controller(pid: PID, name: str = "pid") -> "control.StateSpace":
    """Continuous PID with inputs ``speed_setpoint`` and ``nut_speed_measured`` (rad/s) and
    output ``torque_command`` (N m); derivative on the measurement with filter ``tf``.

    Parameters
    ----------
    pid : PID
    name : str
        System name.
    """
    import control

    kp, ki, kd, tf = pid.kp, pid.ki, pid.kd, pid.tf
    # States: integral of the error, derivative-filter state.
    a = np.array([[0.0, 0.0], [0.0, -1.0 / tf]])
    b = np.array([[1.0, -1.0], [0.0, 1.0 / tf]])
    c = np.array([[ki, kd / tf]])
    d = np.array([[kp, -kp - kd / tf]])
    return control.ss(
        a, b, c, d,
        inputs=["speed_setpoint", "nut_speed_measured"], outputs=["torque_command"],
        states=["pid_integral", "pid_derivative"], name=name,
    )


def closed_loop(sys: control.StateSpace, pid: PID) -> "control.StateSpace":
    """Speed loop of a linearised plant: inputs ``speed_setpoint`` and ``axial_load``; outputs
    the plant's plus ``torque_command`` (N m).

    Parameters
    ----------
    sys : control.StateSpace
        From :func:`linearize`.
    pid : PID
    """
    import control

    outs = [o for o in sys.output_labels] + ["torque_command"]
    plant_part = control.ss(sys.A, sys.B, sys.C, sys.D, inputs=sys.input_labels,
                            outputs=sys.output_labels, states=sys.state_labels, name="P")
    return control.interconnect(
        [plant_part, pid_controller(pid)],
        inplist=["speed_setpoint", "axial_load"],
        outlist=outs,
        inputs=["speed_setpoint", "axial_load"],
        outputs=outs,
        name="speed_loop",
    )


def predict_load_step(
    sys: "control.StateSpace",
    pid: PID,
    load_step: float,
    t_step: float,
    duration: float,
    dt: float = 1e-4,
) -> "control.TimeResponseData":
    """Linear prediction of a load step of ``load_step`` N at ``t_step`` s.

    Parameters
    ----------
    sys : control.StateSpace
        From :func:`linearize`.
    pid : PID
    load_step : float, N
        Change of the axial load.
    t_step, duration, dt : float, s

    Returns absolute signals (operating point added back) on a uniform grid of spacing ``dt``;
    the step is exact (the step response of the closed loop, not an interpolated ramp).
    """
    import control

    cl = closed_loop(sys, pid)
    op = sys.operating_point
    if not cl.isctime() or np.any(np.real(cl.poles()) >= 0):
        raise ValueError(f"closed loop with {pid} is unstable; expected stabilising gains")
    t = np.arange(0.0, duration + 0.5 * dt, dt)
    after = t >= t_step
    resp = control.step_response(cl, T=t[after] - t_step, input=1)
    y = np.zeros((cl.noutputs, t.size))
    y[:, after] = load_step * np.asarray(resp.outputs).reshape(cl.noutputs, -1)
    base = dict(sys.operating_outputs, torque_command=op.torque)
    for i, name in enumerate(cl.output_labels):
        y[i] += base[name]
    return control.TimeResponseData(
        t, y, output_labels=list(cl.output_labels), sysname="linear_prediction", issiso=False
    )
