"""The actuator's equations of motion, written once in CasADi (SI units inside).

Two fidelities of one physical model:

``rigid``
    One rotational degree of freedom. Cage, rollers and screw are slaved to the nut through the
    rigid kinematics, so their inertia is reflected to the nut; the axial load acts through the
    lead; Coulomb friction on the quasi-static thread normal forces (it grows with the load) sets
    the forward efficiency.
``compliant``
    Nut, cage (with the rollers' orbit and spin through the screw-roller gearing) and screw are
    separate bodies; the roller/cage assembly also moves axially. The nut-roller and screw-roller
    thread contacts follow the paper's IMPACT law on both flanks (with axial backlash), the nut
    drives the cage through a friction-limited traction (a creep law), and thread friction uses
    the static/dynamic coefficients with a smooth stiction (Stribeck) curve.
``multi-roller``
    The compliant model with every roller's own nut-side and screw-side contact, offset by
    seeded position errors and a once-per-spin runout drawn from the plant's tolerances, so
    load sharing is uneven and the contact forces fluctuate as the rollers turn.

Both include the drive: torque-command saturation and a first-order current loop.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import casadi as ca

from .plant import Plant

__all__ = ["FIDELITIES", "PlantModel", "RollerErrors", "plant_model", "INPUTS"]

from .options import FIDELITIES  # noqa: E402  (re-exported)

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
    "x_roller": "m",
    "v_roller": "m/s",
    "delta_screw": "m",
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


def _output_names(plant: Plant, fidelity: str) -> tuple[str, ...]:
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

    @property
    def nx(self) -> int:
        return len(self.state_names)

    def index(self, state: str) -> int:
        return self.state_names.index(state)

    def state_unit(self, state: str) -> str:
        return _STATE_UNITS[state]


def _smooth_sign(v: ca.SX, width: float) -> ca.SX:
    return ca.tanh(v / width)


def _friction_coefficient(plant: Plant, v_slide: ca.SX) -> ca.SX:
    """Coulomb coefficient with stiction: mu_d + (mu_s - mu_d) exp(-(v/v_s)^2), smooth sign."""
    p = plant.values
    mu_s, mu_d = p["friction.static"], p["friction.dynamic"]
    v_s, v_t = p["friction.stribeck_velocity_m_s"], p["friction.transition_velocity_m_s"]
    return (mu_d + (mu_s - mu_d) * ca.exp(-((v_slide / v_s) ** 2))) * _smooth_sign(v_slide, v_t)


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


def _bearing_losses(plant: Plant, omega: ca.SX) -> ca.SX:
    """Load-independent drag: no-load torque (smooth sign) plus viscous torque, N m."""
    v = plant.values
    omega_t = v["friction.transition_velocity_m_s"] / (0.5 * plant.d_nut_m)
    return v["friction.no_load_torque_n_m"] * _smooth_sign(omega, omega_t) + v[
        "friction.viscous_n_m_s_per_rad"
    ] * omega


def _kinematic_outputs(plant: Plant, omega_nut, omega_cage, v_screw, tau) -> list:
    d_s, d_r = plant.d_screw_m, plant.d_roller_m
    return [omega_nut, omega_cage, omega_cage * d_s / d_r, omega_cage * (d_s + d_r) / d_r, v_screw, tau]


def _rigid(plant: Plant, x: ca.SX, u: ca.SX):
    v = plant.values
    _, omega, tau = ca.vertsplit(x)
    load = u[1]
    a = plant.lead_per_rad
    j_eq = plant.reflected_inertia_kg_m2
    f_n, f_s = plant.normal_force_factor()
    k_slip = plant.slip_arm_m
    t_fric = k_slip * _friction_coefficient(plant, k_slip * omega) * ca.fabs(load) * (f_n + f_s)
    t_drag = _bearing_losses(plant, omega)
    xdot = ca.vertcat(omega, (tau - load * a - t_fric - t_drag) / j_eq, _drive(plant, u[0], tau))
    y = _kinematic_outputs(plant, omega, omega * plant.cage_ratio, omega * a, tau)
    stored = 0.5 * j_eq * omega**2
    dissipated = (t_fric + t_drag) * omega
    return xdot, y, [stored, tau * omega, load * a * omega, dissipated]


@dataclass
class _Contacts:
    """Thread-contact totals of the compliant models: axial forces on the roller assembly
    from the nut (``f_nr``) and on the screw (``f_sr``), N; normal forces, N; the normal force
    friction acts on, N; stored energy, J; damping power, W; torque on the cage, N m."""

    f_nr: ca.SX
    f_sr: ca.SX
    n_nut: ca.SX
    n_screw: ca.SX
    n_fric: ca.SX
    energy: ca.SX
    damping: ca.SX
    t_cage: ca.SX


def _compliant_bodies(plant: Plant, w_n, w_p, v_r, v_s, tau, u, c: _Contacts):
    """Rates of nut speed, cage speed, roller axial speed, screw speed and motor torque, with
    the energy terms, given the contact totals (shared by the compliant models)."""
    v = plant.values
    load = u[1]
    d_s, d_n = plant.d_screw_m, plant.d_nut_m
    j_cage, m_axial = plant.cage_inertia_kg_m2, plant.roller_assembly_mass_kg
    # Thread sliding friction, acting on the nut through the effective sliding arm.
    k_slip = plant.slip_arm_m
    t_fric = k_slip * _friction_coefficient(plant, k_slip * w_n) * c.n_fric
    t_drag = _bearing_losses(plant, w_n)
    # Nut-roller traction drives the cage (rolling with creep, limited by mu_d * normal force).
    v_slip = 0.5 * d_n * w_n - 0.5 * (d_n + d_s) * w_p
    n_trac = ca.fmax(c.n_nut, 0.0) + v["friction.traction_preload_n"]
    f_t = v["friction.dynamic"] * _smooth_sign(v_slip, v["friction.creep_velocity_m_s"]) * n_trac
    j_nut, m_s = v["nut.inertia_kg_m2"], v["screw.mass_kg"]
    rates = {
        "omega_nut": (tau - 0.5 * d_n * f_t - t_fric - t_drag) / j_nut,
        "omega_cage": (0.5 * (d_n + d_s) * f_t + c.t_cage) / j_cage,
        "v_roller": (c.f_nr - c.f_sr) / m_axial,
        "v_screw": (c.f_sr - load) / m_s,
        "tau_motor": _drive(plant, u[0], tau),
    }
    stored = 0.5 * j_nut * w_n**2 + 0.5 * j_cage * w_p**2 + 0.5 * m_axial * v_r**2 + 0.5 * m_s * v_s**2 + c.energy
    dissipated = (t_fric + t_drag) * w_n + f_t * v_slip + c.damping
    y = _kinematic_outputs(plant, w_n, w_p, v_s, tau) + [c.n_nut, c.n_screw]
    return rates, y, [stored, tau * w_n, load * v_s, dissipated]


def _compliant(plant: Plant, x: ca.SX, u: ca.SX):
    _, w_n, w_p, x_r, v_r, d_sr, v_s, tau = ca.vertsplit(x)
    # Screw advance per radian of cage rotation (screw-roller helix): v_S = a w_P rigidly.
    a = plant.lead_per_rad / plant.cage_ratio
    ddelta_sr = v_r + a * w_p - v_s
    cos_n, cos_s = math.cos(plant.helix_nut_rad), math.cos(plant.helix_screw_rad)
    f_nr, n_nut, e_nr, pd_nr = _thread_contact(plant, -x_r, -v_r, cos_n)
    f_sr, n_screw, e_sr, pd_sr = _thread_contact(plant, d_sr, ddelta_sr, cos_s)
    contacts = _Contacts(f_nr, f_sr, n_nut, n_screw, ca.fmax(n_nut, 0.0) + ca.fmax(n_screw, 0.0),
                         e_nr + e_sr, pd_nr + pd_sr, -a * f_sr)
    r, y, terms = _compliant_bodies(plant, w_n, w_p, v_r, v_s, tau, u, contacts)
    xdot = ca.vertcat(w_n, r["omega_nut"], r["omega_cage"], v_r, r["v_roller"], ddelta_sr, r["v_screw"], r["tau_motor"])
    return xdot, y, terms


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


def _multi_roller(plant: Plant, x: ca.SX, u: ca.SX, errors: RollerErrors):
    """Compliant model with each roller's own nut-side and screw-side contact (engaged threads
    per roller), offset by its position error and runout; the rollers share the cage's axial
    and rotational motion. The offsets depend on the cage angle, so their forces also act on
    the cage (generalised forces from the same contact Jacobian keep the energy balance)."""
    _, w_n, th_p, w_p, x_r, v_r, d_sr, v_s, tau = ca.vertsplit(x)
    d_s, d_r = plant.d_screw_m, plant.d_roller_m
    a = plant.lead_per_rad / plant.cage_ratio
    spin = d_s / d_r  # roller spin (relative to the cage) per radian of cage rotation
    ddelta_sr = v_r + a * w_p - v_s
    cos_n, cos_s = math.cos(plant.helix_nut_rad), math.cos(plant.helix_screw_rad)
    z = int(plant.values["thread.engaged_threads"])
    f_nr = f_sr = n_nut = n_screw = energy = damp = t_cage = n_fric = 0
    per_nut, per_screw = [], []
    for i in range(plant.n_rollers):
        ang = spin * th_p + errors.phase[i]
        wob = errors.runout[i] * ca.sin(ang)
        dwob = errors.runout[i] * spin * ca.cos(ang)  # d(wobble)/d(theta_cage)
        e_n, e_s = errors.position_nut[i] + wob, errors.position_screw[i] + wob
        fn_i, nn_i, en_i, pn_i = _thread_contact(plant, -x_r - e_n, -v_r - dwob * w_p, cos_n, z)
        fs_i, ns_i, es_i, ps_i = _thread_contact(plant, d_sr + e_s, ddelta_sr + dwob * w_p, cos_s, z)
        f_nr, f_sr = f_nr + fn_i, f_sr + fs_i
        n_nut, n_screw = n_nut + nn_i, n_screw + ns_i
        n_fric = n_fric + ca.fmax(nn_i, 0.0) + ca.fmax(ns_i, 0.0)
        energy, damp = energy + en_i + es_i, damp + pn_i + ps_i
        t_cage = t_cage + fn_i * dwob - fs_i * (a + dwob)
        per_nut.append(nn_i)
        per_screw.append(ns_i)
    contacts = _Contacts(f_nr, f_sr, n_nut, n_screw, n_fric, energy, damp, t_cage)
    r, y, terms = _compliant_bodies(plant, w_n, w_p, v_r, v_s, tau, u, contacts)
    xdot = ca.vertcat(w_n, r["omega_nut"], w_p, r["omega_cage"], v_r, r["v_roller"], ddelta_sr, r["v_screw"], r["tau_motor"])
    return xdot, y + per_nut + per_screw, terms


_CACHE: "weakref.WeakKeyDictionary[Plant, dict[tuple, PlantModel]]" = weakref.WeakKeyDictionary()


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
    """
    if fidelity not in FIDELITIES:
        raise ValueError(f"fidelity = {fidelity!r}; expected one of {', '.join(FIDELITIES)}")
    key = (fidelity, int(seed) if fidelity == "multi-roller" else 0)
    per_plant = _CACHE.setdefault(plant, {})
    if key in per_plant:
        return per_plant[key]
    names = _STATES[fidelity]
    x = ca.SX.sym("x", len(names))
    u = ca.SX.sym("u", 2)
    if fidelity == "multi-roller":
        xdot, y, terms = _multi_roller(plant, x, u, RollerErrors.draw(plant, key[1]))
    else:
        xdot, y, terms = (_rigid if fidelity == "rigid" else _compliant)(plant, x, u)
    y = ca.vertcat(*y)
    terms = ca.vertcat(*terms)
    model = PlantModel(
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
    )
    per_plant[key] = model
    return model
