"""The actuator's equations of motion, written once in CasADi (SI units inside).

Fidelities of one physical model
--------------------------------
``rigid``
    One rotational degree of freedom. Cage, rollers and screw are slaved to the nut through the
    rigid kinematics, so their inertia is reflected to the nut; the axial load acts through the
    lead; thread friction (below) on the quasi-static thread normal forces (it grows with the
    load) sets the forward efficiency.
``compliant``
    Nut, cage (with the rollers' orbit and spin through the screw-roller gearing), roller
    assembly (axially) and screw are separate bodies. The nut-roller and screw-roller thread
    contacts follow the paper's IMPACT law on both flanks (with axial backlash); the nut drives
    the cage through a friction-limited traction (a creep law); thread friction as below.
``multi-roller``
    The compliant model with every roller's own nut-side and screw-side contact, offset by
    seeded position errors and a once-per-spin runout drawn from the plant's tolerances, so
    load sharing is uneven and the contact forces fluctuate as the rollers turn.

All include the drive: torque-command saturation and a first-order current loop.

Mechanisms (``Plant.mechanism``) on the same model
--------------------------------------------------
The rotating degree of freedom is always the motor's (``theta_nut``, ``omega_nut``: the nut of
the inverted roller screw, the screw of a screw-driven axis) and ``v_screw`` the translating
member's speed (the screw of the inverted design, the nut with the carriage of a screw-driven
axis); the inputs are always the torque command (N m) and the axial load (N).

``inverted-roller-screw``
    All three fidelities as described above.
``roller-screw``, ``ball-screw`` (screw-driven: the motor turns the screw, the nut translates)
    ``rigid``: the motor, screw and carriage as one inertia ``J_motor + J_screw + m (L/2 pi)^2``
    (the rollers' or balls' own inertia neglected), thread friction as below (efficiency
    ``friction.efficiency`` forward, ``2 - 1/eta`` back-driving, :attr:`Plant.backdrive_efficiency`).
    ``compliant``: the axial spring of the screw-shaft/nut/bearing path, whose stiffness depends
    on the nut's position along the stroke (:func:`_screw_driven`): three bodies, rotor with
    screw, screw shaft axially on its bearings, carriage. The states keep the inverted model's
    names (``x_roller``/``v_roller``: the shaft's axial displacement/speed, ``delta_screw``: the
    helix spring's compression) and outputs (``contact_force_nut``: the nut force,
    ``contact_force_screw``: the bearing force). ``multi-roller``: not available (it models the
    inverted design's per-roller contacts). The roller-screw's carrier and roller speeds are
    outputs of its rigid kinematics; a ball screw's are 0 (the ball train is not modelled).
``linear-axis`` (load coordinates: 1 m of travel per radian, force in N as torque in N m)
    ``rigid``: one mass with direction-dependent Coulomb and viscous friction
    (:func:`_linear_axis_friction`); ``compliant``: the same, or the two-mass axis of
    :mod:`prsa_ctrl.plant.linearaxis` when ``axis.load_mass_kg`` > 0. ``multi-roller``: not available.

Axial kinematics of the inverted design (derivation)
----------------------------------------------------
Bodies: the nut rotates (angle ``th_N``) and is axially fixed in the housing by its bearings;
the screw translates (``x_S``) and does not rotate; the cage/carrier turns (``th_P``) and, with
the rollers, is free axially (the paper's ADAMS model: cylindrical joint cage-ground); each
roller turns (absolute ``th_R``) and translates (``x_R``) with the cage. The screw-roller gearing
forces pure rolling at the screw, ``th_R - th_P = th_P d_S / d_R``; rolling at the nut pitch
circle gives the cage ratio ``th_P = th_N d_N / (d_N + d_S)``.

A thread of signed lead ``L`` (right hand > 0) has its flank at axial position
``x_body + L/(2 pi) * (psi - th_body)`` at the polar angle ``psi`` around its own axis. At a
contact both flanks are at the same axial position. The screw-roller contact sits at
``psi = th_P`` on the screw and ``th_P + pi`` on the roller; the nut-roller contact at
``psi = th_P`` on both (the roller's outer side). With ``th_S = 0``::

    screw-roller:  x_R - x_S = th_P/(2 pi) * (L_S + L_R d_S/d_R)
    nut-roller:    x_R - x_N = 1/(2 pi) * (L_N (th_P - th_N) + L_R th_P d_S/d_R)

The inverted design's matching rule is ``d_S = n d_R`` with the roller (single start, lead
``P``) of the opposite hand to the screw, ``L_R = -P``, ``L_S = L_N = n P``: the screw-roller
helices are matched, so ``x_R - x_S = 0`` -- **the rollers (and their cage) travel axially with
the screw** -- and the nut-roller relation collapses to ``x_R - x_N = -n P th_N / (2 pi)``
(sign = hand convention), independent of the cage angle: the rollers move relative to the
nut by the lead per nut turn, which is where the helix motion happens (the paper: rollers
"moving axially relative to the nut"). Summing both relations gives ``x_S - x_N = -L th_N/(2 pi)``
for any diameters, so the screw lead is exact; if ``d_S != n d_R`` (Table 1: 14.0 vs 14.4 mm)
the matched side would make the rollers walk along the screw and out of the nut, which no
steady state allows -- the geometry report flags it and the model uses the matched helices.

Consequences used below (``a = L / 2 pi``, m/rad):

* nut-roller axial compression ``delta_N = a th_N - x_R`` (state ``x_roller = x_R - a th_N``,
  the roller assembly's axial position relative to where the nut's helix carries it);
  its generalised forces: torque ``-a F_N`` on the nut, ``+F_N`` on the roller assembly,
  nothing on the cage (the spin and orbit torques of the helical flank force cancel through
  the gearing, ``d delta_N / d th_P = 0``);
* screw-roller compression ``delta_S = x_R - x_S`` (state ``delta_screw``): a pure axial
  spring, ``+F_S`` on the screw, ``-F_S`` on the roller assembly, no torque on the cage;
* the load path is screw -> screw-roller contact -> rollers -> nut-roller helix -> nut torque;
  the cage is driven only by the nut-roller traction and carries none of the load torque.

Before this derivation the model held the rollers axially with the nut (``delta_N = -x_R``)
and put the helix in the screw-roller contact (``delta_S = x_R + (a/c) th_P - x_S``, ``c`` the
cage ratio), so the whole load torque flowed nut -> traction -> cage -> screw thread.
``_build(..., roller_axial="nut")`` keeps that assumption for comparison only
(``tests/plant/test_model.py`` measures the difference).

Thread friction: Stribeck curve with Karnopp stiction
-----------------------------------------------------
The Coulomb part of the nut's loss torque is ``T_c(v) = k mu(v) N + T_0`` where ``N`` is the
thread normal force, ``k`` the effective sliding arm that gives the plant's forward efficiency
at speed (:attr:`Plant.slip_arm_m`), ``T_0`` the load-independent no-load torque and
``mu(v) = mu_d + (mu_s - mu_d) exp(-(v/v_s)^2)`` the Stribeck curve (Armstrong-Helouvry,
Dupont, Canudas de Wit, Automatica 30(7) 1994), with ``v = a w_N`` the screw speed and ``v_s``
``friction.stribeck_velocity_m_s``. Stiction follows Karnopp's stick band (D. Karnopp,
J. Dyn. Sys. Meas. Control 107(1):100-103, 1985): for ``|w_N| <= w_b`` (``w_b = v_t / a``,
``v_t = friction.transition_velocity_m_s``) friction balances every other torque on the nut
``T_net`` up to the breakaway torque ``T_s = k mu_s N + T_0`` and adds a restoring damping
``J w / tau_stick`` (``STICK_TIME_CONSTANT_S``), so a stuck nut decays to exactly zero speed and
stays there while ``|T_net| < T_s`` (no creep); beyond ``2 w_b`` it slides on ``T_c(v) sign(w)``;
a C1 cubic blends the two in between. The law is odd in ``w`` (reversal symmetric), has no
state, and has finite derivatives everywhere (no division by ``w``). At 300 rpm it equals the
previous smooth-sign law to 1e-12 (efficiency = ``friction.efficiency``); at 0.05 and 0.01
rad/s the load-dependent losses sit on the static branch (implied efficiency 0.826 / 0.825 on
the paper plant, instead of 0.93 / 0.98 with the old ``tanh(v/v_t)`` sign).
Why not LuGre (Canudas de Wit et al., IEEE TAC 40(3) 1995): it adds a bristle state whose
stiffness (presliding displacement) has no source for this plant, relaxes at ~1e4 1/s at 300
rpm (a stiff extra pole in every linearised tuning model) and drifts under oscillating forces
below breakaway (Dupont et al., IEEE TAC 47(5) 2002); Karnopp gives exact stiction, the same
sliding curve and no new state. Presliding/hysteresis are out of its scope.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass, field

import casadi as ca

from .plantfile import Plant
from .nutloss import NUT_LOSS_KEY, nut_loss_band_n, nut_loss_on_whole_force, smooth_abs
from .schema import BREAKAWAY_KEY, VISCOUS_OFFSET_KEY
from .linearaxis import TWO_MASS_AXIS_STATES, is_two_mass_axis, two_mass_axis

__all__ = ["FIDELITIES", "PlantModel", "state_derivative", "RollerErrors", "plant_model", "INPUTS", "stribeck_coefficient",
           "ParametricModel", "parametric_family", "register_member",
           "stick_band_rad_s", "STICK_TIME_CONSTANT_S", "screw_axis_springs", "drag_breakaway_excess",
           "NUT_LOSS_KEY", "nut_loss_on_whole_force"]

from ..options import FIDELITIES  # noqa: E402  (re-exported)

#: Plant inputs: torque command to the current loop (N m) and external axial load (N,
#: positive opposing forward screw motion).
INPUTS = ("torque_command", "axial_load")

_STATES = {
    "rigid": ("theta_nut", "omega_nut", "tau_motor"),
    "compliant": (
        "theta_nut",
        "omega_nut",
        "omega_cage",
        "x_roller",
        "v_roller",
        "delta_screw",
        "v_screw",
        "tau_motor",
    ),
    "multi-roller": (
        "theta_nut",
        "omega_nut",
        "theta_cage",
        "omega_cage",
        "x_roller",
        "v_roller",
        "delta_screw",
        "v_screw",
        "tau_motor",
    ),
}
_STATE_UNITS = {
    "theta_nut": "rad",
    "theta_cage": "rad",
    "omega_nut": "rad/s",
    "omega_cage": "rad/s",
    "x_roller": "m",  # x_R - a th_N: minus the nut-side axial compression
    "v_roller": "m/s",  # absolute axial speed of the roller assembly (= v_screw at steady state)
    "delta_screw": "m",  # x_R - x_S: screw-side axial compression
    "v_screw": "m/s",
    "tau_motor": "N m",
}

_OUTPUTS_COMMON = (
    "nut_speed",
    "cage_speed",
    "roller_speed",
    "roller_speed_abs",
    "screw_velocity",
    "motor_torque",
)
_OUTPUTS = {
    "rigid": _OUTPUTS_COMMON,
    "compliant": _OUTPUTS_COMMON + ("contact_force_nut", "contact_force_screw"),
}


_SCREW_DRIVEN_STATES = ("theta_nut", "omega_nut", "x_roller", "v_roller", "delta_screw", "v_screw", "tau_motor")


def _state_names(plant: Plant, fidelity: str) -> tuple[str, ...]:
    """States of ``fidelity`` for the plant's mechanism (module docstring: what the names mean)."""
    if fidelity == "multi-roller" and plant.mechanism != "inverted-roller-screw":
        raise ValueError(f"fidelity = 'multi-roller' models the per-roller contacts of the inverted roller screw; "
                         f"expected 'rigid' or 'compliant' for mechanism = {plant.mechanism!r}")
    if fidelity == "compliant" and plant.screw_driven:
        return _SCREW_DRIVEN_STATES
    if fidelity == "compliant" and plant.mechanism == "linear-axis":
        return TWO_MASS_AXIS_STATES if is_two_mass_axis(plant) else _STATES["rigid"]
    return _STATES[fidelity]


def _output_names(plant: Plant, fidelity: str) -> tuple[str, ...]:
    if fidelity == "compliant" and plant.mechanism == "linear-axis":
        return _OUTPUTS["rigid"]
    if fidelity != "multi-roller":
        return _OUTPUTS[fidelity]
    n = plant.n_rollers
    return (
        _OUTPUTS["compliant"]
        + tuple(f"contact_force_nut_{i + 1}" for i in range(n))
        + tuple(f"contact_force_screw_{i + 1}" for i in range(n))
    )


@dataclass(frozen=True, eq=False)
class PlantModel:
    """Symbolic plant of one fidelity with its compiled CasADi functions.

    Attributes
    ----------
    f : casadi.Function
        ``(x, u) -> dx/dt`` with ``u = [torque_command (N m), axial_load (N)]``; the output
        ``motor_torque`` is the actual torque after saturation and the current loop.
    h : casadi.Function
        ``(x, u) -> y`` with outputs named in ``output_names``.
    power : casadi.Function
        ``(x, u) -> [stored energy (J), motor power (W), load power (W), dissipated power (W)]``.
    family : ParametricModel or None
        For a member of a parametric family (:func:`register_member`): the family whose
        equations this model is, with ``theta`` (the family's parameter values) filled in.
    theta : tuple of float
        The member's values of ``family.keys`` (file units); empty otherwise.
    """

    plant: Plant
    fidelity: str
    state_names: tuple[str, ...]
    output_names: tuple[str, ...]
    x: ca.SX
    u: ca.SX
    xdot: ca.SX
    y: ca.SX
    energy_terms: ca.SX
    f: ca.Function
    h: ca.Function
    power: ca.Function
    family: "ParametricModel | None" = None
    theta: tuple = ()
    #: Typical magnitudes of states whose scale differs from the inverted screw's (read by the
    #: simulator's tolerances): the axial deflections of a screw-driven axis.
    state_scales: "dict | None" = None

    @property
    def nx(self) -> int:
        return len(self.state_names)

    def index(self, state: str) -> int:
        return self.state_names.index(state)

    def state_unit(self, state: str) -> str:
        return _STATE_UNITS[state]


#: Time constant (s) with which Karnopp's stick band pulls a stuck nut to exactly zero speed
#: (a numerical device of the stick phase: fast against the loop, slow against nothing stiff).
STICK_TIME_CONSTANT_S = 1e-4


def stribeck_coefficient(plant: Plant, v_screw):
    """Stribeck friction coefficient at screw speed ``v_screw`` (m/s), magnitude:
    ``mu_d + (mu_s - mu_d) exp(-(v/v_s)^2)``.

    Examples
    --------
    >>> from prsa_ctrl import load_plant
    >>> p = load_plant()
    >>> round(float(stribeck_coefficient(p, 0.0)), 6), round(float(stribeck_coefficient(p, 0.01)), 6)
    (0.3, 0.25)
    """
    p = plant.values
    mu_s, mu_d = p["friction.static"], p["friction.dynamic"]
    return mu_d + (mu_s - mu_d) * _stribeck_shape(plant, v_screw)


def _stribeck_shape(plant: Plant, v_screw):
    """``exp(-(v/v_s)^2)``: 1 at rest, 0 well beyond the Stribeck velocity ``v_s`` (m/s)."""
    return ca.exp(-((v_screw / plant.values["friction.stribeck_velocity_m_s"]) ** 2))


def drag_breakaway_excess(plant: Plant):
    """``T_s0 - T_0`` (N m), the no-load drag's breakaway excess, or None when the plant has none
    (the key absent, defaulted, or equal to ``friction.no_load_torque_n_m``; then the friction
    law is the same expression as without the key, to the bit). A defaulted key follows the
    no-load torque, also where that one is a CasADi symbol (a fit, a parametric family)."""
    v = plant.values
    t0 = v["friction.no_load_torque_n_m"]
    ts0 = v.get(BREAKAWAY_KEY, t0)
    if ts0 is t0 or BREAKAWAY_KEY in (getattr(plant, "defaulted", None) or ()):
        return None
    if isinstance(ts0, (int, float)) and isinstance(t0, (int, float)) and ts0 == t0:
        return None
    return ts0 - t0


def stick_band_rad_s(plant: Plant) -> float:
    """Half-width ``w_b`` (rad/s of the nut) of Karnopp's stick band: ``v_t / (L / 2 pi)``.

    Below ``w_b`` the nut sticks, beyond ``2 w_b`` it slides (module docstring).
    """
    return plant.values["friction.transition_velocity_m_s"] / plant.lead_per_rad


def _slide_parts(plant: Plant, omega: ca.SX):
    """The sliding loss torque's parts (:func:`_nut_friction`): ``(k mu(v), T_0 + excess shape(v))``,
    the torque per newton of thread normal force (m) and the load-independent part (N m)."""
    t0 = plant.values["friction.no_load_torque_n_m"]
    excess = drag_breakaway_excess(plant)
    if excess is not None:  # the no-load drag's own Stribeck drop
        t0 = t0 + excess * _stribeck_shape(plant, plant.lead_per_rad * omega)
    return plant.slip_arm_m * stribeck_coefficient(plant, plant.lead_per_rad * omega), t0


def _nut_friction(plant: Plant, omega: ca.SX, normal: ca.SX, t_net: ca.SX, inertia: float,
                  normal_slide: ca.SX | None = None) -> ca.SX:
    """Coulomb-type loss torque on the nut (N m): Stribeck sliding torque with Karnopp stiction.

    ``normal``: thread normal force carried (N, >= 0); ``t_net``: every other torque on the
    nut's degree of freedom (N m; motor, load/contact, traction, viscous); ``inertia``: the
    inertia of that degree of freedom (kg m^2), which sets the stick-phase restoring damping.
    ``normal_slide``: the sliding branch's normal force where it differs from the stuck one
    (the whole force through the nut, :func:`_nut_force_rigid`); default ``normal``.
    """
    v = plant.values
    k_slip = plant.slip_arm_m
    t0 = v["friction.no_load_torque_n_m"]
    slide = k_slip * stribeck_coefficient(plant, plant.lead_per_rad * omega) * (
        normal if normal_slide is None else normal_slide) + t0
    breakaway = k_slip * v["friction.static"] * normal + t0
    excess = drag_breakaway_excess(plant)
    if excess is not None:  # the no-load drag's own Stribeck drop (none by default: the same expression as before)
        slide = slide + excess * _stribeck_shape(plant, plant.lead_per_rad * omega)
        breakaway = breakaway + excess
    stick = ca.fmin(ca.fmax(t_net + inertia / STICK_TIME_CONSTANT_S * omega, -breakaway), breakaway)
    # 1 inside the band |w| <= w_b, 0 beyond 2 w_b, C1 cubic in between.
    blend = 1.0 - _smooth_step(ca.fabs(omega) / stick_band_rad_s(plant) - 1.0, 1.0)
    return blend * stick + (1.0 - blend) * slide * ca.sign(omega)


def _viscous(plant: Plant, omega: ca.SX) -> ca.SX:
    """Viscous drag torque (grease churning, iron losses) plus the drag offset, N m.

    The offset ``friction.torque_offset_n_m`` (``T_o``) makes the Coulomb levels direction
    dependent, ``T_0 + T_o`` forward and ``T_0 - T_o`` backward (``T_0`` =
    ``friction.no_load_torque_n_m``), as the linear axis's ``(Fc+ - Fc-)/2``; like that one it
    acts as a constant torque, also at rest (a gravity or sensor offset is the same term). The
    viscous offset ``friction.viscous_offset_n_m_s_per_rad`` (``b_o``) makes the viscous
    coefficient direction dependent: ``b + b_o`` forward, ``b - b_o`` backward (``b_o |w|`` added).
    """
    v = plant.values
    visc = v["friction.viscous_n_m_s_per_rad"] * omega + v.get("friction.torque_offset_n_m", 0.0)
    b_o = v.get(VISCOUS_OFFSET_KEY, 0.0)
    if isinstance(b_o, (int, float)) and b_o == 0.0:
        return visc  # the default: the same expression as without the key, to the bit
    return visc + b_o * ca.fabs(omega)


def _smooth_step(p: ca.SX, depth: float) -> ca.SX:
    """ADAMS STEP(p, 0, 0, depth, 1): cubic ramp, C1, 0 at no penetration and 1 at ``depth``."""
    s = ca.fmin(ca.fmax(p / depth, 0.0), 1.0)
    return s * s * (3.0 - 2.0 * s)


def _thread_contact(plant: Plant, delta: ca.SX, ddelta: ca.SX, cos_helix: float, n_contacts: int | None = None):
    """Axial force of one roller-thread interface from its axial compression ``delta`` (m).

    Each of the ``N_R z`` engaged flanks follows the IMPACT law on its normal penetration
    ``p = delta cos(beta) cos(lambda)``: ``F_n = K p^e + C_max dp/dt STEP(p; 0, d)``. The
    opposite flank engages after the axial backlash. Returns the axial force on the driven
    side (N), the total normal force (N, both flanks), the stored elastic energy (J) and the
    damping power (W). ``n_contacts`` defaults to all ``N_R z`` flanks of the interface.
    """
    v = plant.values
    k, e = plant.contact_stiffness_si, v["contact.exponent"]
    c_max, depth = plant.contact_damping_si, plant.penetration_m
    n_c = plant.n_contacts if n_contacts is None else n_contacts
    c = math.cos(plant.flank_angle_rad) * cos_helix
    gap = v["thread.backlash_mm"] * 1e-3 * c
    axial = 0
    normal = 0
    energy = 0
    damping = 0
    for sign, pen, rate in ((1.0, delta * c, ddelta * c), (-1.0, -delta * c - gap, -ddelta * c)):
        engaged = ca.fmax(pen, 0.0)  # max(x, 0)**e keeps the Jacobian finite at first touch
        ramp = _smooth_step(pen, depth)
        fn = n_c * (k * engaged**e + c_max * rate * ramp)
        axial = axial + sign * c * fn
        normal = normal + fn
        energy = energy + n_c * k * engaged ** (e + 1.0) / (e + 1.0)
        damping = damping + n_c * c_max * rate * rate * ramp
    return axial, normal, energy, damping


def _drive(plant: Plant, tau_cmd: ca.SX, tau: ca.SX) -> ca.SX:
    """Current loop: saturated torque command through a first-order lag; returns d tau/dt."""
    t_max = plant.torque_limit
    return (ca.fmin(ca.fmax(tau_cmd, -t_max), t_max) - tau) / plant.current_loop_time_constant_s


def _kinematic_outputs(plant: Plant, omega_nut, omega_cage, v_screw, tau) -> list:
    if plant.mechanism != "inverted-roller-screw":
        rel, ab = plant.roller_spin_ratios
        return [omega_nut, omega_cage, omega_cage * rel, omega_cage * ab, v_screw, tau]
    d_s, d_r = plant.d_screw_m, plant.d_roller_m
    return [omega_nut, omega_cage, omega_cage * d_s / d_r, omega_cage * (d_s + d_r) / d_r, v_screw, tau]


def _linear_axis_friction(plant: Plant, omega: ca.SX):
    """Viscous force and constant offset of a linear axis (load coordinates, N): ``Fv+ v`` for
    ``v > 0``, ``Fv- v`` for ``v < 0``; the offset ``(Fc+ - Fc-)/2`` makes the Coulomb levels
    ``Fc+`` and ``-Fc-`` around the symmetric part ``(Fc+ + Fc-)/2`` (``friction.no_load_torque_n_m``)."""
    v = plant.values
    visc = ca.if_else(omega >= 0, v["friction.viscous_positive_n_s_per_m"] * omega,
                      v["friction.viscous_negative_n_s_per_m"] * omega)
    return visc, 0.5 * (v["friction.coulomb_positive_n"] - v["friction.coulomb_negative_n"])


def _nut_force_rigid(plant: Plant, omega, load, t_net, j_eq):
    """The force through the nut ``F_s = F_load + m a w'`` (N) of the rigid screw-driven axis
    whose sliding loss acts on it (:func:`nut_loss_on_whole_force`), in closed form.

    Sliding, ``J w' = T_net - s (T_0' + c |F_s|)`` with ``s = sign(w)``, ``c`` the sliding loss
    per newton of the nut force and ``T_0'`` the load-independent drag; with ``A = m a`` and
    ``F_s = F_load + A w'`` this is ``(J/A) F_s + s c |F_s| = R``, ``R = T_net - s T_0' +
    (J/A) F_load``, whose left side increases with ``F_s`` while ``J/A > c`` (``J >= m a^2``, so
    for every efficiency above ~0.55): ``F_s = R / (J/A + s c sign(R))``; below that (a nut that
    nearly self-locks, no unique solution) the denominator is held at 5 % of ``J/A``.
    """
    f_n, f_s = plant.normal_force_factor()
    per_newton, t0 = _slide_parts(plant, omega)
    c = per_newton * (f_n + f_s)
    s = ca.sign(omega)
    j_over_a = j_eq / (plant.values["axis.moving_mass_kg"] * plant.lead_per_rad)
    r = t_net - s * t0 + j_over_a * load
    return r / ca.fmax(j_over_a + s * c * ca.sign(r), 0.05 * j_over_a)


def _rigid(plant: Plant, x: ca.SX, u: ca.SX):
    _, omega, tau = ca.vertsplit(x)
    load = u[1]
    a = plant.lead_per_rad
    j_eq = plant.reflected_inertia_kg_m2
    f_n, f_s = plant.normal_force_factor()
    if plant.mechanism == "linear-axis":
        t_visc, offset = _linear_axis_friction(plant, omega)
        load = load + offset  # the Coulomb offset acts like a constant load (both in N, a = 1 m/rad)
    else:
        t_visc = _viscous(plant, omega)
    t_net = tau - load * a - t_visc
    slide = (ca.fabs(_nut_force_rigid(plant, omega, load, t_net, j_eq)) * (f_n + f_s)
             if nut_loss_on_whole_force(plant) else None)  # (the default: the same expression as before)
    t_fric = _nut_friction(plant, omega, ca.fabs(load) * (f_n + f_s), t_net, j_eq, normal_slide=slide)
    xdot = ca.vertcat(omega, (t_net - t_fric) / j_eq, _drive(plant, u[0], tau))
    y = _kinematic_outputs(plant, omega, omega * plant.cage_ratio, omega * a, tau)
    stored = 0.5 * j_eq * omega**2
    dissipated = (t_fric + t_visc) * omega
    if plant.mechanism == "linear-axis":  # the offset is friction: dissipated, not load power
        return xdot, y, [stored, tau * omega, u[1] * a * omega, dissipated + (load - u[1]) * a * omega]
    return xdot, y, [stored, tau * omega, load * a * omega, dissipated]


def _two_mass_linear(plant: Plant, x: ca.SX, u: ca.SX):
    """The two-mass linear axis (:func:`prsa_ctrl.plant.linearaxis.two_mass_axis`) with this model's laws."""
    f_n, f_s = plant.normal_force_factor()

    def friction(p, w):
        visc, offset = _linear_axis_friction(p, w)
        return visc, offset, lambda t_net, m: _nut_friction(p, w, ca.fabs(u[1]) * (f_n + f_s), t_net, m)
    return two_mass_axis(plant, x, u, friction, _drive, _kinematic_outputs)


@dataclass
class _Contacts:
    """Thread-contact totals of the compliant models: axial forces on the roller assembly
    from the nut (``f_nr``) and on the screw (``f_sr``), N; normal forces, N; the normal force
    friction acts on, N; stored energy, J; damping power, W; generalised torques of the
    contacts on the cage (``t_cage``) and on the nut (``t_nut``), N m."""

    f_nr: ca.SX
    f_sr: ca.SX
    n_nut: ca.SX
    n_screw: ca.SX
    n_fric: ca.SX
    energy: ca.SX
    damping: ca.SX
    t_cage: ca.SX
    t_nut: ca.SX


def _compliant_bodies(plant: Plant, w_n, w_p, v_r, v_s, tau, u, c: _Contacts):
    """Rates of nut speed, cage speed, roller axial speed, screw speed and motor torque, with
    the energy terms, given the contact totals (shared by the compliant models)."""
    v = plant.values
    load = u[1]
    d_s, d_n = plant.d_screw_m, plant.d_nut_m
    j_cage, m_axial = plant.cage_inertia_kg_m2, plant.roller_assembly_mass_kg
    j_nut, m_s = v["nut.inertia_kg_m2"], v["screw.mass_kg"]
    # Nut-roller traction drives the cage (rolling with creep, limited by mu_d * normal force).
    v_slip = 0.5 * d_n * w_n - 0.5 * (d_n + d_s) * w_p
    n_trac = ca.fmax(c.n_nut, 0.0) + v["friction.traction_preload_n"]
    f_t = v["friction.dynamic"] * ca.tanh(v_slip / v["friction.creep_velocity_m_s"]) * n_trac
    # Thread sliding friction on the nut (Stribeck + Karnopp stiction, module docstring).
    t_visc = _viscous(plant, w_n)
    t_net = tau - 0.5 * d_n * f_t + c.t_nut - t_visc
    t_fric = _nut_friction(plant, w_n, c.n_fric, t_net, j_nut)
    rates = {
        "omega_nut": (t_net - t_fric) / j_nut,
        "omega_cage": (0.5 * (d_n + d_s) * f_t + c.t_cage) / j_cage,
        "v_roller": (c.f_nr - c.f_sr) / m_axial,
        "v_screw": (c.f_sr - load) / m_s,
        "tau_motor": _drive(plant, u[0], tau),
    }
    stored = 0.5 * j_nut * w_n**2 + 0.5 * j_cage * w_p**2 + 0.5 * m_axial * v_r**2 + 0.5 * m_s * v_s**2 + c.energy
    dissipated = (t_fric + t_visc) * w_n + f_t * v_slip + c.damping
    y = _kinematic_outputs(plant, w_n, w_p, v_s, tau) + [c.n_nut, c.n_screw]
    return rates, y, [stored, tau * w_n, load * v_s, dissipated]


def _axial_kinematics(plant: Plant, roller_axial: str, w_n, w_p, v_r, v_s):
    """Rates of the nut-side and screw-side axial compressions (m/s) and the helix leads
    (m/rad) that enter the nut and cage torques, for the chosen roller axial assumption.

    ``"screw"`` (the mechanism, module docstring): ``delta_N = a th_N - x_R``,
    ``delta_S = x_R - x_S``. ``"nut"`` (the former assumption, kept for comparison):
    ``delta_N = -x_R``, ``delta_S = x_R + (a/c) th_P - x_S``.
    Returns ``(d delta_N/dt, d delta_S/dt, lead on the nut, lead on the cage)``.
    """
    a = plant.lead_per_rad
    if roller_axial == "screw":
        return a * w_n - v_r, v_r - v_s, a, 0.0
    if roller_axial == "nut":
        a_cage = a / plant.cage_ratio
        return -v_r, v_r + a_cage * w_p - v_s, 0.0, a_cage
    raise ValueError(f"roller_axial = {roller_axial!r}; expected 'screw' or 'nut'")


def _compliant(plant: Plant, x: ca.SX, u: ca.SX, roller_axial: str = "screw"):
    _, w_n, w_p, x_r, v_r, d_sr, v_s, tau = ca.vertsplit(x)
    dd_nr, dd_sr, a_nut, a_cage = _axial_kinematics(plant, roller_axial, w_n, w_p, v_r, v_s)
    cos_n, cos_s = math.cos(plant.helix_nut_rad), math.cos(plant.helix_screw_rad)
    # x_roller is minus the nut-side compression under both assumptions.
    f_nr, n_nut, e_nr, pd_nr = _thread_contact(plant, -x_r, dd_nr, cos_n)
    f_sr, n_screw, e_sr, pd_sr = _thread_contact(plant, d_sr, dd_sr, cos_s)
    contacts = _Contacts(f_nr, f_sr, n_nut, n_screw, ca.fmax(n_nut, 0.0) + ca.fmax(n_screw, 0.0),
                         e_nr + e_sr, pd_nr + pd_sr, -a_cage * f_sr, -a_nut * f_nr)
    r, y, terms = _compliant_bodies(plant, w_n, w_p, v_r, v_s, tau, u, contacts)
    xdot = ca.vertcat(w_n, r["omega_nut"], r["omega_cage"], -dd_nr, r["v_roller"], dd_sr, r["v_screw"], r["tau_motor"])
    return xdot, y, terms


def screw_axis_springs(plant: Plant):
    """Springs and masses of a screw-driven axis's compliant model (numbers or CasADi symbols):
    ``(k_helix, c_helix, k_bearing, c_bearing, m_shaft)`` in N/m, N s/m, kg.

    ``k_helix``: the screw shaft between the fixed bearing(s) and the nut (stroke-dependent,
    :meth:`Plant.shaft_stiffness_n_per_m`) in series with the nut; ``k_bearing``: the axial
    support bearing(s). Damping ``c = 2 zeta sqrt(k m)`` with ``zeta`` =
    ``axis.axial_damping_ratio`` and ``m`` the mass the spring moves against (the carriage
    with the rotor reflected through the lead for the helix spring, the shaft for the bearing).
    """
    v = plant.values
    k_shaft = plant.shaft_stiffness_n_per_m()
    k_nut = v["axis.nut_stiffness_n_per_um"] * 1e6
    k_helix = k_shaft * k_nut / (k_shaft + k_nut)
    k_brg = v["axis.bearing_stiffness_n_per_um"] * 1e6
    zeta = v["axis.axial_damping_ratio"]
    j_rot = v["axis.motor_inertia_kg_m2"] + v["axis.screw_inertia_kg_m2"]
    m_c = v["axis.moving_mass_kg"]
    a = plant.lead_per_rad
    m_red = 1.0 / (1.0 / m_c + a * a / j_rot)
    m_sh = plant.screw_axial_mass_kg
    return k_helix, 2.0 * zeta * ca.sqrt(k_helix * m_red), k_brg, 2.0 * zeta * ca.sqrt(k_brg * m_sh), m_sh


def _screw_driven(plant: Plant, x: ca.SX, u: ca.SX):
    """Compliant model of a screw-driven axis (``roller-screw``, ``ball-screw``): three bodies.

    * the rotor with the screw turning (``theta_nut``, ``omega_nut``; inertia
      ``J_motor + J_screw``),
    * the screw shaft moving axially on its support bearing(s) (``x_roller`` = its axial
      displacement ``u``, ``v_roller`` = its speed; mass: the shaft's),
    * the nut with the carriage (``v_screw``; mass ``axis.moving_mass_kg``).

    The bearing spring ``k_B`` holds the shaft (force ``-k_B u``); the helix spring ``k_H``
    (shaft between bearing and nut, in series with the nut) carries ``F = k_H delta`` with the
    compression ``delta = a th + u - x_C`` (state ``delta_screw``): ``+F`` on the carriage,
    ``-F`` on the shaft, torque ``-a F`` on the rotor. The carriage position is
    ``a th + x_roller - delta_screw`` (as for the inverted screw's translating member). Thread
    friction: the same Stribeck/Karnopp law as the inverted screw on the normal force of ``|F|``
    (smoothed within 5 % of the rated load: :func:`prsa_ctrl.plant.nutloss.smooth_abs`).
    At steady state ``F`` = the load, and the static stiffness from the motor to the carriage
    is ``1 / (1/k_shaft + 1/k_nut + 1/k_bearing)`` (:meth:`Plant.axial_stiffness_n_per_m`).
    """
    _, w, u_sh, v_sh, delta, v_c, tau = ca.vertsplit(x)
    load = u[1]
    v = plant.values
    a = plant.lead_per_rad
    j_rot = v["axis.motor_inertia_kg_m2"] + v["axis.screw_inertia_kg_m2"]
    m_c = v["axis.moving_mass_kg"]
    k_h, c_h, k_b, c_b, m_sh = screw_axis_springs(plant)
    d_delta = a * w + v_sh - v_c
    f_h = k_h * delta + c_h * d_delta
    f_n, f_s = plant.normal_force_factor()
    t_visc = _viscous(plant, w)
    t_net = tau - a * f_h - t_visc
    # |F| smoothed over 5 % of the rated load (plant.nutloss: the kink at F = 0 stalls a fit)
    t_fric = _nut_friction(plant, w, smooth_abs(f_h, nut_loss_band_n(plant)) * (f_n + f_s), t_net, j_rot)
    xdot = ca.vertcat(w, (t_net - t_fric) / j_rot, v_sh, (-f_h - k_b * u_sh - c_b * v_sh) / m_sh, d_delta,
                      (f_h - load) / m_c, _drive(plant, u[0], tau))
    y = _kinematic_outputs(plant, w, w * plant.cage_ratio, v_c, tau) + [f_h, k_b * u_sh + c_b * v_sh]
    stored = (0.5 * j_rot * w**2 + 0.5 * m_sh * v_sh**2 + 0.5 * m_c * v_c**2 + 0.5 * k_h * delta**2
              + 0.5 * k_b * u_sh**2)
    dissipated = (t_fric + t_visc) * w + c_h * d_delta**2 + c_b * v_sh**2
    return xdot, y, [stored, tau * w, load * v_c, dissipated]


@dataclass(frozen=True)
class RollerErrors:
    """Per-roller manufacturing errors of the multi-roller fidelity (m, rad).

    ``position_nut`` / ``position_screw``: axial offsets of each roller's flanks at the two
    interfaces (zero mean over the rollers); ``runout``: amplitude of a once-per-spin axial
    wobble of the roller thread; ``phase``: its phase.
    """

    position_nut: tuple[float, ...]
    position_screw: tuple[float, ...]
    runout: tuple[float, ...]
    phase: tuple[float, ...]

    @classmethod
    def draw(cls, plant: Plant, seed: int) -> "RollerErrors":
        """Seeded draw from the plant's tolerances (``[tolerance]`` section)."""
        import numpy as np

        rng = np.random.default_rng(seed)
        n = plant.n_rollers
        std = plant.values["tolerance.roller_position_std_um"] * 1e-6
        run = plant.values["tolerance.roller_runout_um"] * 1e-6
        p_n = rng.normal(0.0, std, n)
        p_s = rng.normal(0.0, std, n)
        if n > 1:
            p_n -= p_n.mean()
            p_s -= p_s.mean()
        return cls(
            tuple(p_n.tolist()),
            tuple(p_s.tolist()),
            tuple((run * rng.uniform(0.5, 1.0, n)).tolist()),
            tuple(rng.uniform(0.0, 2.0 * math.pi, n).tolist()),
        )


def _multi_roller(plant: Plant, x: ca.SX, u: ca.SX, errors: RollerErrors, roller_axial: str = "screw"):
    """Compliant model with each roller's own nut-side and screw-side contact (engaged threads
    per roller), offset by its position error and runout; the rollers share the cage's axial
    and rotational motion. The offsets depend on the cage angle, so their forces also act on
    the cage (generalised forces from the same contact Jacobian keep the energy balance)."""
    _, w_n, th_p, w_p, x_r, v_r, d_sr, v_s, tau = ca.vertsplit(x)
    d_s, d_r = plant.d_screw_m, plant.d_roller_m
    dd_nr, dd_sr, a_nut, a_cage = _axial_kinematics(plant, roller_axial, w_n, w_p, v_r, v_s)
    spin = d_s / d_r  # roller spin (relative to the cage) per radian of cage rotation
    cos_n, cos_s = math.cos(plant.helix_nut_rad), math.cos(plant.helix_screw_rad)
    z = int(plant.values["thread.engaged_threads"])
    f_nr = f_sr = n_nut = n_screw = energy = damp = t_cage = n_fric = 0
    per_nut, per_screw = [], []
    for i in range(plant.n_rollers):
        ang = spin * th_p + errors.phase[i]
        wob = errors.runout[i] * ca.sin(ang)
        dwob = errors.runout[i] * spin * ca.cos(ang)  # d(wobble)/d(theta_cage)
        e_n, e_s = errors.position_nut[i] + wob, errors.position_screw[i] + wob
        fn_i, nn_i, en_i, pn_i = _thread_contact(plant, -x_r - e_n, dd_nr - dwob * w_p, cos_n, z)
        fs_i, ns_i, es_i, ps_i = _thread_contact(plant, d_sr + e_s, dd_sr + dwob * w_p, cos_s, z)
        f_nr, f_sr = f_nr + fn_i, f_sr + fs_i
        n_nut, n_screw = n_nut + nn_i, n_screw + ns_i
        n_fric = n_fric + ca.fmax(nn_i, 0.0) + ca.fmax(ns_i, 0.0)
        energy, damp = energy + en_i + es_i, damp + pn_i + ps_i
        t_cage = t_cage + fn_i * dwob - fs_i * (a_cage + dwob)
        per_nut.append(nn_i)
        per_screw.append(ns_i)
    contacts = _Contacts(f_nr, f_sr, n_nut, n_screw, n_fric, energy, damp, t_cage, -a_nut * f_nr)
    r, y, terms = _compliant_bodies(plant, w_n, w_p, v_r, v_s, tau, u, contacts)
    xdot = ca.vertcat(w_n, r["omega_nut"], w_p, r["omega_cage"], -dd_nr, r["v_roller"], dd_sr, r["v_screw"],
                      r["tau_motor"])
    return xdot, y + per_nut + per_screw, terms


_CACHE: "weakref.WeakKeyDictionary[Plant, dict[tuple, PlantModel]]" = weakref.WeakKeyDictionary()


def _build(plant: Plant, fidelity: str, seed: int = 0, roller_axial: str = "screw") -> PlantModel:
    """Build a model (uncached). ``roller_axial="nut"`` selects the former, superseded
    assumption that the rollers stay axially with the nut (comparison only, module docstring)."""
    names, x, u, xdot, y, terms = _equations(plant, fidelity, seed, roller_axial)
    return PlantModel(
        plant=plant,
        fidelity=fidelity,
        state_names=names,
        output_names=_output_names(plant, fidelity),
        x=x,
        u=u,
        xdot=xdot,
        y=y,
        energy_terms=terms,
        f=ca.Function("f", [x, u], [xdot], ["x", "u"], ["xdot"]),
        h=ca.Function("h", [x, u], [y], ["x", "u"], ["y"]),
        power=ca.Function("power", [x, u], [terms], ["x", "u"], ["terms"]),
        state_scales=_state_scales(plant, names),
    )


def _state_scales(plant: Plant, names: tuple[str, ...]) -> "dict | None":
    """Typical deflections of a screw-driven axis's compliant model: the rated load over each
    spring's stiffness (m); ``None`` for the other models (the simulator's defaults hold)."""
    if names == TWO_MASS_AXIS_STATES:  # the spring under the drive's force limit
        return {"delta_screw": float(plant.torque_limit) / (float(plant.values["axis.load_stiffness_n_per_um"]) * 1e6)}
    if not (plant.screw_driven and "delta_screw" in names):
        return None
    k_h, _, k_b, _, _ = (float(z) for z in screw_axis_springs(plant))
    return {"x_roller": plant.rated_load_n / k_b, "delta_screw": plant.rated_load_n / k_h}


def state_derivative(plant: Plant, fidelity: str, x: ca.SX, u: ca.SX, roller_axial: str = "screw"):
    """Symbolic ``(xdot, outputs, energy terms)`` of the ``rigid`` or ``compliant`` model.

    ``plant``'s values may be CasADi symbols (the fits differentiate through them); ``x`` and
    ``u`` are the state and input symbols in the order of :func:`plant_model`'s names. The
    multi-roller model draws its roller errors and is built by :func:`plant_model` only.
    """
    if fidelity == "compliant" and plant.screw_driven:
        return _screw_driven(plant, x, u)
    if fidelity == "compliant" and plant.mechanism != "linear-axis":
        return _compliant(plant, x, u, roller_axial)
    if fidelity == "compliant" and is_two_mass_axis(plant):
        return _two_mass_linear(plant, x, u)
    if fidelity in ("rigid", "compliant"):
        return _rigid(plant, x, u)
    raise ValueError(f"fidelity = {fidelity!r}; expected 'rigid' or 'compliant'")


def _equations(plant: Plant, fidelity: str, seed: int = 0, roller_axial: str = "screw"):
    """State names, symbols ``x``, ``u`` and the expressions ``xdot``, ``y``, energy terms."""
    names = _state_names(plant, fidelity)
    x = ca.SX.sym("x", len(names))
    u = ca.SX.sym("u", 2)
    if fidelity == "multi-roller":
        xdot, y, terms = _multi_roller(plant, x, u, RollerErrors.draw(plant, seed), roller_axial)
    else:
        xdot, y, terms = state_derivative(plant, fidelity, x, u, roller_axial)
    return names, x, u, xdot, ca.vertcat(*y), ca.vertcat(*terms)


def plant_model(plant: Plant, fidelity: str = "compliant", seed: int = 0) -> PlantModel:
    """Build (once per plant, fidelity and seed) the CasADi model of ``plant``.

    Parameters
    ----------
    plant : Plant
        A validated plant.
    fidelity : {"rigid", "compliant", "multi-roller"}
        Model fidelity (see module docstring).
    seed : int
        Seed of the per-roller errors drawn from the plant's tolerances (multi-roller only).

    Returns
    -------
    PlantModel
        States ``state_names`` (units from :meth:`PlantModel.state_unit`), inputs
        ``[torque_command (N m), axial_load (N)]``.

    Examples
    --------
    >>> from prsa_ctrl import load_plant
    >>> m = plant_model(load_plant(), "rigid")
    >>> m.state_names, m.nx
    (('theta_nut', 'omega_nut', 'tau_motor'), 3)
    """
    if fidelity not in FIDELITIES:
        raise ValueError(f"fidelity = {fidelity!r}; expected one of {', '.join(FIDELITIES)}")
    key = (fidelity, int(seed) if fidelity == "multi-roller" else 0)
    per_plant = _CACHE.setdefault(plant, {})
    if key not in per_plant:
        member = _member_model(plant, fidelity, key[1])
        per_plant[key] = member if member is not None else _build(plant, fidelity, key[1])
    return per_plant[key]


# --- parametric families (one model for the plants of a Monte-Carlo run) ----------------------

@dataclass(frozen=True, eq=False)
class ParametricModel:
    """The equations of one fidelity with some plant values as CasADi parameters ``theta``.

    Built once for a base plant; every plant that differs from it only in ``keys`` (a
    *member*, see :func:`register_member`) is this model with its own ``theta``, so the
    simulator's functions (and their compiled code) serve all members. Same equations as
    :func:`plant_model` builds for each member (checked against a direct build, see
    :func:`parametric_family`); only the order of constant folding differs (rounding level).

    Attributes
    ----------
    plant : Plant
        The base plant (the numbers of every key not in ``keys``).
    keys : tuple of str
        The parameters, ``section.key`` in file units.
    f, h, power : casadi.Function
        As :class:`PlantModel`'s, with a third input ``theta``.
    """

    plant: Plant
    fidelity: str
    seed: int
    keys: tuple[str, ...]
    state_names: tuple[str, ...]
    output_names: tuple[str, ...]
    f: ca.Function
    h: ca.Function
    power: ca.Function
    cache: dict = field(default_factory=dict, repr=False)  # the simulator's functions of this family

    @property
    def nx(self) -> int:
        return len(self.state_names)

    def index(self, state: str) -> int:
        return self.state_names.index(state)

    @property
    def n_theta(self) -> int:
        return len(self.keys)

    def theta_of(self, plant: Plant) -> tuple[float, ...]:
        return tuple(float(plant.values[k]) for k in self.keys)

    def bind(self, plant: Plant) -> PlantModel:
        """``plant``'s model: these equations with ``theta`` = its values (no rebuild of the
        equations: one symbolic call with the numbers folded in)."""
        theta = self.theta_of(plant)
        x = ca.SX.sym("x", self.nx)
        u = ca.SX.sym("u", 2)
        th = ca.DM(theta) if theta else ca.DM.zeros(0, 1)
        xdot, y, terms = self.f(x, u, th), self.h(x, u, th), self.power(x, u, th)
        return PlantModel(
            plant=plant, fidelity=self.fidelity, state_names=self.state_names, output_names=self.output_names,
            x=x, u=u, xdot=xdot, y=y, energy_terms=terms,
            f=ca.Function("f", [x, u], [xdot], ["x", "u"], ["xdot"]),
            h=ca.Function("h", [x, u], [y], ["x", "u"], ["y"]),
            power=ca.Function("power", [x, u], [terms], ["x", "u"], ["terms"]),
            family=self, theta=theta, state_scales=_state_scales(plant, self.state_names),
        )


#: Member plant -> (base plant, keys that may differ), see :func:`register_member`.
_MEMBERS: "weakref.WeakKeyDictionary[Plant, tuple[Plant, tuple[str, ...]]]" = weakref.WeakKeyDictionary()
#: (base plant's values, fidelity, seed, keys) -> ParametricModel, or None where no key can be a
#: parameter. Keyed by content, not identity, so that worker processes forked after a family was
#: built (or that rebuild the same plant) reuse it and its functions; at most 8 kept.
_FAMILIES: dict[tuple, "ParametricModel | None"] = {}


def _parameter_candidate(key: str) -> bool:
    """Keys that may be parameters: not read as numbers by the sampled loop (``sensor.*``,
    the torque limit) and not structural (integers: starts, counts, engaged threads)."""
    from .schema import KIND

    return not key.startswith("sensor.") and key != "drive.torque_limit_n_m" and KIND[key] != "positive integer"


def _symbolic_build(base: Plant, fidelity: str, seed: int, keys: tuple[str, ...]) -> ParametricModel:
    theta = ca.SX.sym("theta", len(keys))
    view = object.__new__(Plant)  # the base plant with SX symbols for ``keys`` (no validation)
    for name in ("name", "sources", "origin", "description", "uncertainty", "mechanism", "defaulted", "mechanism_source"):
        object.__setattr__(view, name, getattr(base, name))
    values = dict(base.values)
    values.update({k: theta[i] for i, k in enumerate(keys)})
    object.__setattr__(view, "values", values)
    states, x, u, xdot, y, terms = _equations(view, fidelity, seed)
    args, names = [x, u, theta], ["x", "u", "theta"]
    return ParametricModel(
        plant=base, fidelity=fidelity, seed=seed, keys=keys, state_names=states,
        output_names=_output_names(base, fidelity),
        f=ca.Function("f", args, [xdot], names, ["xdot"]),
        h=ca.Function("h", args, [y], names, ["y"]),
        power=ca.Function("power", args, [terms], names, ["terms"]),
    )


def _test_points(names: tuple[str, ...], n: int = 6):
    """Seeded states and inputs around typical magnitudes (both thread flanks, both directions)."""
    import numpy as np

    mag = {"omega_nut": 40.0, "omega_cage": 20.0, "x_roller": 3e-5, "delta_screw": 3e-5, "v_roller": 2e-3,
           "v_screw": 2e-3, "tau_motor": 1.0}
    rng = np.random.default_rng(12345)
    for _ in range(n):
        x = [mag.get(k, 1.0) * rng.uniform(-1.0, 1.0) for k in names]
        yield x, [rng.uniform(-2.0, 2.0), rng.uniform(-3000.0, 3000.0)]


def _agrees(a: PlantModel, b: PlantModel) -> bool:
    """The two models' f, h and power agree to 1e-9 (relative) at the test points, all finite."""
    import numpy as np

    for x, u in _test_points(a.state_names):
        for fa, fb in ((a.f, b.f), (a.h, b.h), (a.power, b.power)):
            va, vb = np.asarray(fa(x, u), float), np.asarray(fb(x, u), float)
            if not (np.all(np.isfinite(va)) and np.all(np.isfinite(vb))):
                return False
            if np.any(np.abs(va - vb) > 1e-9 * np.maximum(np.abs(vb), 1e-12 * max(1.0, float(np.max(np.abs(vb)))))):
                return False
    return True


def _has_nan_constant(fam: ParametricModel) -> bool:
    """A value that went through ``float``/``math`` as a symbol leaves a NaN constant behind."""
    for fun in (fam.f, fam.h, fam.power):
        for k in range(fun.n_instructions()):
            if fun.instruction_id(k) == ca.OP_CONST and math.isnan(fun.instruction_constant(k)):
                return True
    return False


def parametric_family(base: Plant, fidelity: str, keys, seed: int = 0) -> ParametricModel | None:
    """The model of ``base`` with the values of ``keys`` as parameters (built once per base
    plant, fidelity, seed and key set), or ``None`` when none of them can be one.

    A key becomes a parameter when the equations use it symbolically: the family is checked
    for NaN constants (a value that went through ``float``/``math``) and against a direct
    build of ``base`` at seeded test states (f, h, power to 1e-9); a key that fails is left
    out (members differing in it get their own model).
    """
    key = (tuple(sorted(base.values.items())), fidelity, int(seed), tuple(sorted(keys)))
    if key in _FAMILIES:
        return _FAMILIES[key]
    cands = tuple(k for k in key[3] if _parameter_candidate(k))
    ref = plant_model(base, fidelity, seed)

    def ok(ks: tuple[str, ...]) -> ParametricModel | None:
        try:
            fam = _symbolic_build(base, fidelity, int(seed), ks)
        except (RuntimeError, TypeError, ValueError, ZeroDivisionError):
            return None
        return fam if not _has_nan_constant(fam) and _agrees(fam.bind(base), ref) else None

    fam = ok(cands) if cands else None
    if fam is None and len(cands) > 1:
        good = tuple(k for k in cands if ok((k,)) is not None)
        fam = ok(good) if good else None
    while len(_FAMILIES) >= 8:
        del _FAMILIES[next(iter(_FAMILIES))]
    _FAMILIES[key] = fam
    return fam


def register_member(plant: Plant, base: Plant, keys) -> None:
    """Declare that ``plant`` differs from ``base`` only in ``keys`` (e.g. one Monte-Carlo
    sample): :func:`plant_model` then gives it the parametric family's model (same equations,
    shared simulator functions) where every differing key is a parameter of the family."""
    _MEMBERS[plant] = (base, tuple(sorted(keys)))


def _member_model(plant: Plant, fidelity: str, seed: int) -> PlantModel | None:
    entry = _MEMBERS.get(plant)
    if entry is None:
        return None
    base, keys = entry
    differ = {k for k in plant.values if plant.values[k] != base.values[k]}
    if BREAKAWAY_KEY in plant.defaulted and BREAKAWAY_KEY in base.defaulted:
        differ.discard(BREAKAWAY_KEY)  # follows the no-load torque; the equations do not read it
    fam = parametric_family(base, fidelity, keys, seed)
    if fam is None or not differ <= set(fam.keys):
        return None
    member = fam.bind(plant)
    if differ and not fam.cache.get("checked"):
        # once per family: a member with other values against its direct build
        if not _agrees(member, _build(plant, fidelity, seed)):
            _FAMILIES[(tuple(sorted(base.values.items())), fidelity, int(seed), keys)] = None
            return None
        fam.cache["checked"] = True
    return member
