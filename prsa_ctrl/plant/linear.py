"""Exact (automatic-differentiation) linearisation of the plant (the speed loop around it:
:mod:`prsa_ctrl.drive.linear_loop`).

The rigid plant alone makes speed-loop tuning ill-posed (any gain is robust on a pure inertia),
so the linear model carries what limits real bandwidth: the current-loop lag (inside the
plant model), the speed-measurement filter, and, for a sampled controller, the computation
delay plus zero-order hold (1.5 Ts on the command, a Pade approximation). The backward-difference
speed estimate lags by Ts/2 but the discrete filter's direct feed-through leads by Ts/2, so the
measurement path carries no net delay (checked against the sampled nonlinear simulation: peak
drops agree within 1.5 % where a Ts/2 measurement delay over-predicts them by up to 9 %).
"""

from __future__ import annotations

import math
import weakref

from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from .equilibrium import operating_point
from .model import INPUTS, plant_model
from ..options import SETPOINT_RAD_S
from .plantfile import Plant

if TYPE_CHECKING:  # annotations only: python-control is imported where it is used
    import control

__all__ = ["linear_core", "linearize"]


def _pade(delay: float, order: int, inp: str, out: str, name: str) -> "control.StateSpace":

    import control
    if delay <= 0 or order == 0:
        return control.ss([], [], [], [[1.0]], inputs=[inp], outputs=[out], name=name)
    num, den = control.pade(delay, order)
    sys = control.ss(control.tf(num, den))
    return control.ss(
        sys.A, sys.B, sys.C, sys.D,
        inputs=[inp], outputs=[out], states=[f"{name}_{k}" for k in range(sys.nstates)], name=name,
    )


def linear_core(plant: Plant, omega_nut: float, load: float, fidelity: str = "compliant"):
    """Jacobians ``(A, B, C, D, op)`` of the plant about an operating point, all states kept
    (including the nut angle), inputs ``(torque_command, axial_load)``, outputs the model's.

    Parameters
    ----------
    plant : Plant
    omega_nut : float, rad/s
    load : float, N
    fidelity : {"rigid", "compliant"}

    Returns
    -------
    A, B, C, D : ndarray
        SI units of the model's states (``model.state_names``), inputs and outputs.
    op : OperatingPoint
    """
    if fidelity not in ("rigid", "compliant"):
        raise ValueError(
            f"fidelity = {fidelity!r}; expected 'rigid' or 'compliant' (the multi-roller model is "
            "periodic in the cage angle and has no constant operating point)"
        )
    model = plant_model(plant, fidelity)
    op = operating_point(plant, omega_nut, load, fidelity)
    u0 = np.array([op.torque, load])
    jac = _jacobians(model)
    mats = tuple(np.asarray(m) for m in jac(op.x, u0))
    for m in mats:
        if not np.all(np.isfinite(m)):
            raise ArithmeticError(
                f"non-finite Jacobian at {omega_nut} rad/s, {load} N; the contact law must stay "
                "differentiable (contact.exponent >= 1)"
            )
    return (*mats, op)


_JACOBIANS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _jacobians(model) -> ca.Function:
    if model not in _JACOBIANS:
        _JACOBIANS[model] = ca.Function("linearization", [model.x, model.u], [
            ca.jacobian(model.xdot, model.x), ca.jacobian(model.xdot, model.u),
            ca.jacobian(model.y, model.x), ca.jacobian(model.y, model.u),
        ])
    return _JACOBIANS[model]


def linearize(
    plant: Plant,
    omega_nut: float = SETPOINT_RAD_S,
    load: float = 500.0,
    fidelity: str = "compliant",
    sampled: bool = True,
    pade_order: int = 2,
) -> "control.StateSpace":
    """Linearise the actuator about constant nut speed and axial load.

    Parameters
    ----------
    plant : Plant
    omega_nut : float, rad/s
        Operating nut speed.
    load : float, N
        Operating axial load.
    fidelity : {"rigid", "compliant"}
    sampled : bool
        Include the sampled controller's computation delay and zero-order hold (1.5 Ts on the
        command, plus the plant's ``drive.command_delay_samples`` n: (1.5 + n) Ts) as a Pade
        approximation of order ``pade_order``.

    Returns
    -------
    control.StateSpace
        Inputs ``torque_command`` (N m) and ``axial_load`` (N); outputs the plant's
        (``nut_speed`` rad/s, ``screw_velocity`` m/s, ``motor_torque`` the actual torque after
        the current loop, N m, ...) plus ``nut_speed_measured`` (rad/s), the speed the
        controller sees. Signals are deviations
        from the operating point, which is stored in ``sys.operating_point``.

    Examples
    --------
    >>> from prsa_ctrl import load_plant, linearize
    >>> P = linearize(load_plant(), omega_nut=31.4159, load=1000.0)
    >>> P.input_labels
    ['torque_command', 'axial_load']
    """
    import control

    if not (math.isfinite(omega_nut) and math.isfinite(load)):
        raise ValueError(f"operating point ({omega_nut!r} rad/s, {load!r} N); expected finite values")
    if pade_order not in range(0, 6):
        raise ValueError(f"pade_order = {pade_order!r}; expected an integer 0..5")
    model = plant_model(plant, fidelity)
    a_full, b, c_full, d, op = linear_core(plant, omega_nut, load, fidelity)
    keep = [i for i, n in enumerate(model.state_names) if n != "theta_nut"]
    a, c = a_full[np.ix_(keep, keep)], c_full[:, keep]
    out_names = list(model.output_names)
    core = control.ss(
        a, b[keep], c, d,
        states=[model.state_names[i] for i in keep],
        inputs=["torque_command_delayed", INPUTS[1]],
        outputs=out_names,
        name="plant",
    )
    ts = plant.sample_time_s if sampled else 0.0
    t_f = plant.speed_filter_s
    filt = control.ss(
        [[-1 / t_f]], [[1 / t_f]], [[1.0]], [[0.0]],
        inputs=["nut_speed"], outputs=["nut_speed_measured"], states=["speed_filter"], name="filter",
    )
    parts = [_pade((1.5 + plant.command_delay_samples) * ts, pade_order, INPUTS[0], "torque_command_delayed", "command_delay"), core, filt]
    sys = control.interconnect(
        parts,
        inplist=list(INPUTS),
        outlist=out_names + ["nut_speed_measured"],
        inputs=list(INPUTS),
        outputs=out_names + ["nut_speed_measured"],
        name=f"{plant.name}_{fidelity}_linear".replace(".", "_"),
    )
    y0 = np.asarray(model.h(op.x, [op.torque, load])).ravel()
    sys.operating_point = op
    sys.operating_outputs = dict(zip(out_names, y0.tolist()))
    sys.operating_outputs["nut_speed_measured"] = op.omega_nut
    return sys
