"""The two-mass linear axis: the ``compliant`` model of a ``linear-axis`` plant whose
``axis.load_mass_kg`` is above 0 (load coordinates: 1 m of travel per radian, force in N as
torque in N m).

Bodies: the motor side (the drive's moving part with the encoder: ``m_m = axis.mass_kg -
axis.load_mass_kg``, position ``theta_nut`` m, speed ``omega_nut`` m/s) and the load mass ``m_l =
axis.load_mass_kg`` (speed ``v_screw`` m/s) joined by a spring-damper of stiffness ``k =
axis.load_stiffness_n_per_um x 1e6`` N/m and damping ``c = 2 zeta sqrt(k m_m m_l / M)`` (``zeta``
= ``axis.axial_damping_ratio``, the modal damping of the axial mode, ``M = m_m + m_l``: the
two-mass model of :mod:`prsa_ctrl.identification.twomass`). State ``delta_screw = x_m - x_l``
(m) is the spring's compression::

    m_m x_m'' = tau - F_s - F_f(x_m')        F_s = k delta + c (x_m' - x_l')
    m_l x_l'' = F_s - F_load

``tau`` the drive force after saturation and the current loop (state ``tau_motor``), ``F_load``
the external load (input ``axial_load``, N, opposing forward motion) acting on the load mass, and
``F_f`` the axis's friction (direction-dependent Coulomb and viscous,
:func:`prsa_ctrl.plant.model._linear_axis_friction`'s law) on the motor side, where the logs
measure it: the frequency response torque command -> motor speed of this model is the two-mass
response with the anti-resonance ``sqrt(k / m_l) / 2 pi`` and the mode ``sqrt(k M / (m_m m_l)) /
2 pi`` (Hz). A rigid axis (``axis.load_mass_kg = 0``, the default) keeps its one-body model in
both fidelities.
"""

from __future__ import annotations

import math

import casadi as ca

from .plantfile import Plant

__all__ = ["is_two_mass_axis", "two_mass_axis_parameters", "TWO_MASS_AXIS_STATES"]

#: States of the two-mass linear axis (names shared with the screw models: ``delta_screw`` the
#: spring's compression, ``v_screw`` the load mass's speed).
TWO_MASS_AXIS_STATES = ("theta_nut", "omega_nut", "delta_screw", "v_screw", "tau_motor")


def is_two_mass_axis(plant: Plant) -> bool:
    """Whether ``plant`` is a linear axis with a second mass (``axis.load_mass_kg`` > 0; a CasADi
    symbol, a fitted load mass, counts as one)."""
    if plant.mechanism != "linear-axis":
        return False
    m = plant.values.get("axis.load_mass_kg", 0.0)
    try:
        return float(m) > 0.0
    except (TypeError, RuntimeError):  # a symbol: the fit of a load mass
        return True


def two_mass_axis_parameters(plant: Plant):
    """``(m_m kg, m_l kg, k N/m, c N s/m)`` of a two-mass linear axis (numbers or CasADi symbols)."""
    v = plant.values
    total, m_l = v["axis.mass_kg"], v["axis.load_mass_kg"]
    m_m = total - m_l
    k = v["axis.load_stiffness_n_per_um"] * 1e6
    zeta = v["axis.axial_damping_ratio"]
    sqrt = ca.sqrt if any(isinstance(z, (ca.SX, ca.MX)) for z in (total, m_l, k, zeta)) else math.sqrt
    c = 2.0 * zeta * sqrt(k * m_m * m_l / total)
    return m_m, m_l, k, c


def two_mass_axis(plant: Plant, x, u, friction, drive, outputs):
    """``(xdot, outputs, energy terms)`` of the two-mass linear axis (module docstring).

    ``friction(plant, omega, t_net, inertia) -> (viscous, offset, coulomb)`` forces on the motor
    side (N), ``drive(plant, command, tau) -> d tau/dt`` and ``outputs(plant, omega_nut,
    omega_cage, v_screw, tau)`` are the model's own (:mod:`prsa_ctrl.plant.model`), passed in so
    that this module does not import it.
    """
    _, w_m, delta, v_l, tau = ca.vertsplit(x)
    m_m, m_l, k, c = two_mass_axis_parameters(plant)
    f_s = k * delta + c * (w_m - v_l)
    t_visc, offset, t_fric_of = friction(plant, w_m)
    t_net = tau - f_s - offset - t_visc
    t_fric = t_fric_of(t_net, m_m)
    xdot = ca.vertcat(w_m, (t_net - t_fric) / m_m, w_m - v_l, (f_s - u[1]) / m_l, drive(plant, u[0], tau))
    y = outputs(plant, w_m, w_m * plant.cage_ratio, v_l, tau)
    stored = 0.5 * m_m * w_m**2 + 0.5 * m_l * v_l**2 + 0.5 * k * delta**2
    dissipated = (t_fric + t_visc + offset) * w_m + c * (w_m - v_l) ** 2
    return xdot, y, [stored, tau * w_m, u[1] * v_l, dissipated]
