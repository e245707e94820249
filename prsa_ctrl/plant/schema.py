"""The plant file's schema: every section and key, the kind of value, its plausible range, which
keys each mechanism needs and the documented default of every other key.

The lowest layer of :mod:`prsa_ctrl.plant`: both the plant-file reader and the uncertainty
checks read it, so it imports nothing of the package.

Mechanisms (:data:`MECHANISMS`, the plant file's top-level ``mechanism``):

``inverted-roller-screw`` (default)
    The motor turns the nut, the screw translates (the source paper's IPRSM). Keys: :data:`SCHEMA`.
``roller-screw``, ``ball-screw``
    Screw-driven: the motor turns the screw, the nut and the carriage translate. Keys:
    :data:`SCHEMA` plus :data:`SCREW_AXIS_SCHEMA` (motor and screw inertia, moving mass, the
    screw's axial stiffness along the stroke, nut and bearing stiffness, mounting).
``linear-axis``
    Only load-side equivalents (mass, friction, drive gain), in load coordinates (m, N): the
    keys of :data:`LINEAR_AXIS_SCHEMA` (the file format of
    :mod:`prsa_ctrl.identification.axis`).

:data:`REQUIRED` lists the keys a file must give per mechanism; every other key takes its
entry in :data:`DEFAULTS` (value, or a rule on other values, with the source string the plant
then carries, "default: ...").
"""

from __future__ import annotations

import math
from typing import Any, Callable, Mapping, Union

__all__ = ["SCHEMA", "PLAUSIBLE", "ALLOWED_KEYS", "POSITIVE", "NON_NEGATIVE", "POSITIVE_INTEGER", "NON_NEGATIVE_INTEGER",
           "FINITE", "FRACTION", "COMMAND_DELAY_KEY", "BREAKAWAY_KEY", "VISCOUS_OFFSET_KEY",
           "MECHANISMS", "DEFAULT_MECHANISM", "SCREW_DRIVEN", "AXIAL_MODE_KEYS", "axial_mode_keys", "MOUNTINGS", "DEFAULT_MOUNTING", "SCREW_AXIS_SCHEMA",
           "LINEAR_AXIS_SCHEMA", "LOOP_KEYS", "KIND", "REQUIRED", "DEFAULTS", "UNITS", "keys_of", "kind_of"]

# Kinds of value: positive finite, non-negative finite, positive integer, non-negative integer, fraction in (0, 1].
POSITIVE, NON_NEGATIVE, POSITIVE_INTEGER, FRACTION = "positive", "non-negative", "positive integer", "fraction in (0, 1]"
NON_NEGATIVE_INTEGER = "non-negative integer"
#: Kind of a signed value (any finite number).
FINITE = "finite"

#: The drive's command delay beyond the controller's own one-sample computation delay, in
#: controller samples: transport (fieldbus, PWM update) and current-loop dead time between the
#: command leaving the controller and the current loop acting on it. Already modelled without
#: it: the controller's one-sample computation delay (the command computed at sample ``k`` is
#: held from ``k + 1``, zero-order hold) and the current loop as a first-order lag of
#: ``drive.current_loop_bandwidth_hz``. With it, the command computed at ``k`` is held from
#: ``k + 1 + n``: exact for whole samples; a fraction of a sample is lumped into the
#: current-loop lag (the fit writes it so, see :mod:`prsa_ctrl.identification.common`).
COMMAND_DELAY_KEY = "drive.command_delay_samples"

#: The breakaway level ``T_s0`` (N m) of the load-independent drag ``T_0``
#: (``friction.no_load_torque_n_m``): at rest the drag holds up to ``T_s0``; sliding, it is
#: ``T_0 + (T_s0 - T_0) exp(-(v/v_s)^2)``, the Stribeck shape of the thread friction
#: (:mod:`prsa_ctrl.plant.model`). Default: equal to ``T_0`` (no breakaway excess), so every
#: plant without the key behaves as before, to the bit. At least ``T_0`` (checked, as
#: ``friction.static >= friction.dynamic``).
BREAKAWAY_KEY = "friction.no_load_breakaway_torque_n_m"
#: Direction-dependent viscous friction ``b_o`` (N m s/rad): the viscous coefficient is
#: ``friction.viscous_n_m_s_per_rad + b_o`` forward and ``- b_o`` backward. Default 0.
VISCOUS_OFFSET_KEY = "friction.viscous_offset_n_m_s_per_rad"

#: Section -> key -> kind: the keys of the inverted roller screw (and the rotary core every
#: mechanism maps onto, see :mod:`prsa_ctrl.plant.model`).
SCHEMA: Mapping[str, Mapping[str, str]] = {
    "screw": {
        "pitch_diameter_mm": POSITIVE,
        "lead_mm": POSITIVE,
        "starts": POSITIVE_INTEGER,
        "mass_kg": POSITIVE,
        "rated_load_n": POSITIVE,
    },
    "nut": {
        "pitch_diameter_mm": POSITIVE,
        "lead_mm": POSITIVE,
        "starts": POSITIVE_INTEGER,
        "inertia_kg_m2": POSITIVE,
    },
    "roller": {
        "pitch_diameter_mm": POSITIVE,
        "lead_mm": POSITIVE,
        "starts": POSITIVE_INTEGER,
        "count": POSITIVE_INTEGER,
        "mass_kg": POSITIVE,
    },
    "cage": {"mass_kg": POSITIVE, "inertia_kg_m2": POSITIVE},
    "thread": {"flank_angle_deg": POSITIVE, "engaged_threads": POSITIVE_INTEGER, "backlash_mm": NON_NEGATIVE},
    "contact": {
        "stiffness_n_per_mm_e": POSITIVE,
        "exponent": POSITIVE,
        "damping_n_s_per_mm": NON_NEGATIVE,
        "penetration_mm": POSITIVE,
    },
    "friction": {
        "static": NON_NEGATIVE,
        "dynamic": NON_NEGATIVE,
        "stribeck_velocity_m_s": POSITIVE,
        "transition_velocity_m_s": POSITIVE,
        "efficiency": FRACTION,
        "no_load_torque_n_m": NON_NEGATIVE,
        "viscous_n_m_s_per_rad": NON_NEGATIVE,
        "creep_velocity_m_s": POSITIVE,
        "traction_preload_n": NON_NEGATIVE,
        "torque_offset_n_m": FINITE,
        "no_load_breakaway_torque_n_m": NON_NEGATIVE,
        "viscous_offset_n_m_s_per_rad": FINITE,
    },
    "drive": {"torque_limit_n_m": POSITIVE, "current_loop_bandwidth_hz": POSITIVE,
              "command_delay_samples": NON_NEGATIVE_INTEGER},
    "sensor": {
        "sample_time_s": POSITIVE,
        "encoder_counts_per_rev": POSITIVE_INTEGER,
        "speed_filter_time_constant_s": POSITIVE,
        "torque_noise_n_m": NON_NEGATIVE,
    },
    "tolerance": {"roller_position_std_um": NON_NEGATIVE, "roller_runout_um": NON_NEGATIVE},
}

ALLOWED_KEYS = tuple(f"{s}.{k}" for s, keys in SCHEMA.items() for k in keys)

#: Plausible range (file units, inclusive) of each key, with the reason. Values outside are
#: refused with a message naming key, value, range and file: they are typing errors (inertia
#: in g cm^2 typed as kg m^2, a missing exponent) or make the stiff equations meaningless
#: (solver chatter, overflow). The ranges span what real roller-screw actuators have, from
#: ~5 mm / 1 kN screws to ~200 mm / 1 MN presses, with an order of magnitude to spare.
PLAUSIBLE: Mapping[str, tuple[float, float, str]] = {
    "screw.pitch_diameter_mm": (2.0, 500.0, "roller-screw catalogues: 5 to 250 mm"),
    "screw.lead_mm": (0.1, 100.0, "catalogue leads 0.5 to 50 mm"),
    "screw.starts": (1, 20, "catalogue screws have 1 to 10 starts"),
    "screw.mass_kg": (1e-3, 5e3, "a screw with its moving load, grams to tonnes"),
    "screw.rated_load_n": (10.0, 1e7, "catalogue dynamic load ratings 1 kN to 4 MN"),
    "nut.pitch_diameter_mm": (2.0, 600.0, "larger than the screw, catalogue nuts up to ~300 mm"),
    "nut.lead_mm": (0.1, 100.0, "equal to the screw lead"),
    "nut.starts": (1, 20, "equal to the screw starts"),
    "nut.inertia_kg_m2": (1e-7, 10.0, "nut plus motor rotor: 1e-6 (small servo) to ~1 kg m^2 (large torque motor)"),
    "roller.pitch_diameter_mm": (0.5, 150.0, "a fraction of the screw diameter"),
    "roller.lead_mm": (0.05, 50.0, "one thread pitch for single-start rollers"),
    "roller.starts": (1, 10, "rollers are single-start in practice"),
    "roller.count": (2, 60, "catalogue nuts carry 5 to 20 rollers"),
    "roller.mass_kg": (1e-6, 50.0, "grams for small rollers, kilograms for the largest"),
    "cage.mass_kg": (1e-5, 500.0, "retainer rings of the roller cage"),
    "cage.inertia_kg_m2": (1e-11, 10.0, "retainer rings, far below the nut inertia"),
    "thread.flank_angle_deg": (5.0, 80.0, "standard flank half-angle 45 deg"),
    "thread.engaged_threads": (1, 1000, "a nut is at most a few hundred pitches long"),
    "thread.backlash_mm": (0.0, 1.0, "axial play of a worn or standard-grade nut is below 0.1 mm"),
    "contact.stiffness_n_per_mm_e": (1e1, 1e9, "steel thread contacts: IMPACT K ~1e5 N/mm^e"),
    "contact.exponent": (0.5, 3.0, "Hertzian point contact 1.5; below 1 refused by the contact check"),
    "contact.damping_n_s_per_mm": (0.0, 1e5, "IMPACT C_max of steel contacts ~10 to 100 N s/mm"),
    "contact.penetration_mm": (1e-5, 10.0, "full-damping depth, micrometres to a millimetre"),
    "friction.static": (0.0, 1.0, "lubricated steel 0.05 to 0.3"),
    "friction.dynamic": (0.0, 1.0, "lubricated steel 0.05 to 0.3"),
    "friction.stribeck_velocity_m_s": (1e-7, 1.0, "decay speed of the Stribeck curve (static to dynamic coefficient), ~0.1 mm/s"),
    "friction.transition_velocity_m_s": (1e-8, 1.0, "Karnopp stick band (screw speed below which the nut sticks; prsa_ctrl.plant.model.stick_band_rad_s), below the Stribeck velocity"),
    "friction.efficiency": (0.2, 1.0, "roller screws 0.75 to 0.9; below ~0.3 a screw self-locks"),
    "friction.no_load_torque_n_m": (0.0, 1e3, "seal and bearing drag, well below the motor torque"),
    "friction.viscous_n_m_s_per_rad": (0.0, 100.0, "grease and iron losses"),
    "friction.creep_velocity_m_s": (1e-6, 1.0, "rolling creep ~0.1 % of the rolling speed; below 1e-6 m/s the "
                                    "traction law becomes a discontinuity the integrator cannot resolve"),
    "friction.traction_preload_n": (0.0, 1e7, "at most the rated load"),
    "friction.torque_offset_n_m": (-1e3, 1e3, "direction-dependent drag: half the difference of the Coulomb levels, "
                                   "well below the motor torque"),
    "friction.no_load_breakaway_torque_n_m": (0.0, 1e3, "breakaway level of the seal and bearing drag, at least "
                                              "friction.no_load_torque_n_m (checked), well below the motor torque"),
    "friction.viscous_offset_n_m_s_per_rad": (-100.0, 100.0, "direction-dependent viscous friction: half the "
                                              "difference of the viscous coefficients forward and backward, at most "
                                              "friction.viscous_n_m_s_per_rad in magnitude (checked)"),
    "drive.torque_limit_n_m": (1e-3, 1e5, "servo and torque motors: 0.01 to ~10 kN m"),
    "drive.current_loop_bandwidth_hz": (10.0, 1e5, "servo drives 0.5 to 5 kHz"),
    "drive.command_delay_samples": (0, 20, "transport and current-loop dead time of servo drives: 0 to ~3 samples"),
    "sensor.sample_time_s": (1e-6, 0.02, "speed loops run at 50 Hz to 100 kHz (servo drives 1 to 16 kHz); the "
                             "tuner's prediction and the verification record hold one point per sample"),
    "sensor.encoder_counts_per_rev": (64, 2**32, "counts per revolution: the coarsest incremental encoders "
                                      "(16 lines, x4 quadrature) to 32-bit absolute encoders"),
    "sensor.speed_filter_time_constant_s": (1e-7, 1.0, "speed-measurement filter of a servo drive, ~0.1 ms"),
    "sensor.torque_noise_n_m": (0.0, 1e3, "current-measurement noise, a fraction of the torque limit"),
    "tolerance.roller_position_std_um": (0.0, 50.0, "lead deviation of precision to transport grades stays "
                                         "below ~50 um; beyond it rollers lose contact"),
    "tolerance.roller_runout_um": (0.0, 50.0, "ground rollers run out by a few micrometres"),
    # screw-driven axes
    "axis.motor_inertia_kg_m2": (1e-7, 10.0, "motor rotor plus coupling: 1e-6 (small servo) to ~1 kg m^2 (large torque motor)"),
    "axis.screw_inertia_kg_m2": (1e-8, 10.0, "a steel screw of 6 to 160 mm diameter and up to ~10 m"),
    "axis.moving_mass_kg": (1e-3, 1e5, "nut, carriage and payload: grams to a machine table of tonnes"),
    "axis.bearing_span_mm": (10.0, 2e4, "screw lengths of catalogues: ~50 mm to ~12 m"),
    "axis.stroke_position_mm": (0.1, 2e4, "distance of the nut from the axially fixed bearing, within the bearing span"),
    "axis.bearing_stiffness_n_per_um": (1.0, 1e5, "support bearings: ~50 N/um (small) to ~5000 N/um (large pairs)"),
    "axis.nut_stiffness_n_per_um": (1.0, 1e5, "catalogue nut rigidity: ~50 N/um to ~5000 N/um"),
    "axis.fixed_ends": (1, 2, "1: fixed-free (or fixed-supported), 2: fixed-fixed"),
    "axis.nut_loss_on_whole_force": (0, 1, "1: the nut's load-dependent loss on the whole force through the nut "
                                     "(external load and the carriage's inertial force), 0: on the external load only"),
    "axis.axial_damping_ratio": (1e-4, 1.0, "modal damping of a feed drive's axial mode, ~0.01 to 0.1"),
    "screw.root_diameter_mm": (1.0, 500.0, "below the pitch diameter, catalogue screws 4 to 250 mm"),
    "screw.youngs_modulus_gpa": (50.0, 400.0, "steels ~200 to 210 GPa"),
    # linear axes
    "axis.mass_kg": (1e-3, 1e5, "a moving slide of grams to a machine table of tonnes"),
    "axis.load_mass_kg": (0.0, 1e5, "the part of axis.mass_kg beyond the axis's first spring (0: rigid)"),
    "axis.load_stiffness_n_per_um": (1e-3, 1e5, "a payload's mount, a belt or a coupling: ~0.01 N/um to a rigid "
                                     "bolted table of ~1000 N/um"),
    "drive.gain_n_per_unit": (1e-6, 1e6, "force per command unit: N/V of a drive, 1 for a command in N"),
    "drive.force_limit_n": (1e-3, 1e7, "peak force of the drive at the load"),
    "sensor.encoder_resolution_m": (1e-10, 1e-2, "linear scales and encoders at the load: 1 nm to 10 mm"),
    "friction.coulomb_positive_n": (0.0, 1e6, "a fraction of the force limit"),
    "friction.coulomb_negative_n": (0.0, 1e6, "a fraction of the force limit"),
    "friction.viscous_positive_n_s_per_m": (0.0, 1e7, "guides and seals, N per m/s"),
    "friction.viscous_negative_n_s_per_m": (0.0, 1e7, "guides and seals, N per m/s"),
}

# --- mechanisms, required keys and defaults (issue 21) ------------------------------------------

#: The mechanisms a plant file may name (top-level ``mechanism = "..."``).
MECHANISMS = ("inverted-roller-screw", "roller-screw", "ball-screw", "linear-axis")
#: What a plant file that names none is (every plant file written before mechanisms existed).
DEFAULT_MECHANISM = "inverted-roller-screw"
#: Mechanisms where the motor turns the screw and the nut (with the carriage) translates.
SCREW_DRIVEN = ("roller-screw", "ball-screw")
#: The keys that set each mechanism's first axial mode in its compliant model, by role:
#: ``inertias`` the rotating inertia on the motor's side of the spring, then the mass (or inertia)
#: on its far side; ``springs`` the spring a measured mode is matched by first (the least known of
#: the series), then the one scaled together with it when it alone cannot place the mode;
#: ``damping`` the mode's. The one table of them: a two-mass fit of a response writes these keys
#: (:mod:`prsa_ctrl.identification.frfplant`) and the compliant time-domain fit starts from them
#: (:func:`prsa_ctrl.identification.compliant.seed_keys`). A linear axis has no entry (no axial
#: mode in its model).
AXIAL_MODE_KEYS: Mapping[str, Mapping[str, tuple[str, ...]]] = {
    "inverted-roller-screw": {"inertias": ("nut.inertia_kg_m2", "screw.mass_kg"),
                              "springs": ("contact.stiffness_n_per_mm_e",), "damping": ()},
    **{m: {"inertias": ("axis.motor_inertia_kg_m2", "axis.moving_mass_kg"),
           "springs": ("axis.nut_stiffness_n_per_um", "axis.bearing_stiffness_n_per_um"),
           "damping": ("axis.axial_damping_ratio",)} for m in SCREW_DRIVEN},
}


def axial_mode_keys(mechanism: str, role: str | None = None) -> tuple[str, ...]:
    """The :data:`AXIAL_MODE_KEYS` of ``mechanism``: those of one ``role`` (``"inertias"``,
    ``"springs"``, ``"damping"``), or all of them in that order; ``()`` for a mechanism without an
    axial mode."""
    roles = AXIAL_MODE_KEYS.get(mechanism, {})
    if role is not None:
        return tuple(roles.get(role, ()))
    return tuple(k for r in ("inertias", "springs", "damping") for k in roles.get(r, ()))


#: Axial mountings of a driven screw (top-level ``mounting = "..."``) -> number of axially fixed
#: ends (the plant value ``axis.fixed_ends``): ``fixed-free`` (one end held axially, the other
#: free or only radially supported: fixed-supported behaves the same axially) and
#: ``fixed-fixed`` (both ends held axially).
MOUNTINGS: Mapping[str, int] = {"fixed-free": 1, "fixed-fixed": 2}
DEFAULT_MOUNTING = "fixed-free"

#: Keys a screw-driven axis adds to :data:`SCHEMA` (same kinds).
SCREW_AXIS_SCHEMA: Mapping[str, Mapping[str, str]] = {
    "axis": {
        "motor_inertia_kg_m2": POSITIVE,
        "screw_inertia_kg_m2": POSITIVE,
        "moving_mass_kg": POSITIVE,
        "bearing_span_mm": POSITIVE,
        "stroke_position_mm": POSITIVE,
        "bearing_stiffness_n_per_um": POSITIVE,
        "nut_stiffness_n_per_um": POSITIVE,
        "axial_damping_ratio": FRACTION,
        "fixed_ends": POSITIVE_INTEGER,
        "nut_loss_on_whole_force": NON_NEGATIVE_INTEGER,
    },
    "screw": {"root_diameter_mm": POSITIVE, "youngs_modulus_gpa": POSITIVE},
}

#: Keys of a ``linear-axis`` plant (load coordinates; the file format of
#: :mod:`prsa_ctrl.identification.axis`), besides the rotary core it maps onto.
LINEAR_AXIS_SCHEMA: Mapping[str, Mapping[str, str]] = {
    # axis.mass_kg is the whole moving mass; a two-mass axis (a payload on a spring, the FRF
    # fit's two-mass structure) puts axis.load_mass_kg of it beyond axis.load_stiffness_n_per_um
    # with the modal damping axis.axial_damping_ratio (0 kg: rigid, the other two unused)
    "axis": {"mass_kg": POSITIVE, "load_mass_kg": NON_NEGATIVE, "load_stiffness_n_per_um": POSITIVE,
             "axial_damping_ratio": FRACTION},
    "friction": {
        "coulomb_positive_n": NON_NEGATIVE,
        "coulomb_negative_n": NON_NEGATIVE,
        "viscous_positive_n_s_per_m": NON_NEGATIVE,
        "viscous_negative_n_s_per_m": NON_NEGATIVE,
    },
    "drive": {"gain_n_per_unit": POSITIVE, "force_limit_n": POSITIVE},
    "sensor": {"encoder_resolution_m": POSITIVE},
}

#: Keys read outside the model's equations, by the sampled loop and the tools around it, for
#: every mechanism that has them -> who reads them. With the keys the equations read (a run-time
#: trace, :func:`prsa_ctrl.plant.describe.keys_read`) and the keys those derive from, they are the
#: keys a plant uses (:func:`prsa_ctrl.plant.describe.used_keys`, what ``prsa-tune --show-plant``
#: lists).
LOOP_KEYS: Mapping[str, str] = {
    "drive.torque_limit_n_m": "the controller's command saturation and the tuner's torque limit",
    "drive.command_delay_samples": "the sampled loop's command delay (tuner and simulator)",
    "sensor.sample_time_s": "the controller's sample time (tuner and simulator)",
    "sensor.encoder_counts_per_rev": "the encoder quantisation of the simulated measurement",
    "sensor.speed_filter_time_constant_s": "the controller's speed-measurement filter (tuner and simulator)",
    "sensor.torque_noise_n_m": "the simulator's torque ripple and the Kalman estimator's measurement noise",
    "screw.rated_load_n": "the simulator's tolerances, the Kalman estimator's rated torque and the FRF load bound",
    "drive.gain_n_per_unit": "the linear-axis fit's command gain (force per command unit of the logs)",
}

#: Every key of every mechanism -> its kind.
KIND: Mapping[str, str] = {
    f"{s}.{k}": kind
    for table in (SCHEMA, SCREW_AXIS_SCHEMA, LINEAR_AXIS_SCHEMA) for s, keys in table.items() for k, kind in keys.items()
}


def kind_of(key: str) -> str | None:
    """The kind (:data:`POSITIVE` ...) of a plant key ``section.key`` of any mechanism, or ``None``."""
    return KIND.get(key)


_CORE = tuple(f"{s}.{k}" for s, keys in SCHEMA.items() for k in keys)
_SCREW_AXIS = tuple(f"{s}.{k}" for s, keys in SCREW_AXIS_SCHEMA.items() for k in keys)
_LINEAR = tuple(f"{s}.{k}" for s, keys in LINEAR_AXIS_SCHEMA.items() for k in keys)


def keys_of(mechanism: str) -> tuple[str, ...]:
    """The keys a plant of ``mechanism`` holds, in file order (the rotary core first).

    A ``linear-axis`` plant holds its own keys and the rotary core derived from them
    (load coordinates: 1 m of travel per radian, force in N as torque in N m).
    """
    if mechanism in SCREW_DRIVEN:
        return _CORE + _SCREW_AXIS
    if mechanism == "linear-axis":
        return _LINEAR_KEYS
    return _CORE


def _grouped(keys: tuple[str, ...]) -> tuple[str, ...]:
    """``keys`` with each section's keys together, sections in order of first appearance."""
    sections = dict.fromkeys(k.split(".")[0] for k in keys)
    return tuple(k for s in sections for k in keys if k.split(".")[0] == s)


_LINEAR_KEYS = _grouped(_LINEAR + _CORE)


#: Keys a plant file must give, per mechanism (the minimal plant file). ``mechanism`` itself
#: defaults to :data:`DEFAULT_MECHANISM` so that older files keep loading.
REQUIRED: Mapping[str, tuple[str, ...]] = {
    "inverted-roller-screw": ("screw.lead_mm", "nut.inertia_kg_m2", "drive.torque_limit_n_m", "sensor.sample_time_s",
                              "sensor.encoder_counts_per_rev"),
    "roller-screw": ("screw.lead_mm", "axis.motor_inertia_kg_m2", "axis.moving_mass_kg", "drive.torque_limit_n_m",
                     "sensor.sample_time_s", "sensor.encoder_counts_per_rev"),
    "ball-screw": ("screw.lead_mm", "axis.motor_inertia_kg_m2", "axis.moving_mass_kg", "drive.torque_limit_n_m",
                   "sensor.sample_time_s", "sensor.encoder_counts_per_rev"),
    "linear-axis": ("axis.mass_kg", "drive.gain_n_per_unit", "drive.force_limit_n", "sensor.sample_time_s",
                    "sensor.encoder_resolution_m"),
}

Rule = Callable[[Mapping[str, float], str], float]

_STEEL_KG_M3 = 7850.0  # density of steel, kg/m^3
_LOAD_COORDINATES_LEAD_MM = 2000.0 * math.pi  # 1 m of travel per radian: a linear axis in load coordinates


def _by(mechanism_values: Mapping[str, Any]) -> Rule:
    return lambda v, m: mechanism_values[m] if m in mechanism_values else mechanism_values["*"]


def _linear_or(rule: Rule, linear: Rule) -> Rule:
    return lambda v, m: linear(v, m) if m == "linear-axis" else rule(v, m)


#: ``key -> (value or rule, source)``: the default of every key a file may leave out. A rule
#: ``f(values, mechanism)`` derives the value from other values (given or defaulted; the
#: reader evaluates each rule once its inputs exist); a source given as a mapping is per
#: mechanism (``"*"``: the others). The source becomes the plant's source of the key
#: (``Plant.sources``), so a defaulted value says where it came from: ``"default: ..."`` (a
#: typical value and why), ``"derived: ..."`` (follows from other keys; cannot be overridden)
#: or ``"assumption: ..."`` (an engineering estimate).
DEFAULTS: Mapping[str, tuple[Union[float, Rule], Union[str, Mapping[str, str]]]] = {
    # the linear axis's own keys
    "friction.coulomb_positive_n": (0.0, "default: no Coulomb friction (frictionless guide)"),
    "friction.coulomb_negative_n": (0.0, "default: no Coulomb friction (frictionless guide)"),
    "friction.viscous_positive_n_s_per_m": (0.0, "default: no viscous friction"),
    "friction.viscous_negative_n_s_per_m": (0.0, "default: no viscous friction"),
    # rotary core: what the motor turns and how far the load moves per radian
    "screw.lead_mm": (_LOAD_COORDINATES_LEAD_MM, "derived: load coordinates, 1 m of travel per radian (linear axis)"),
    "nut.inertia_kg_m2": (
        lambda v, m: v["axis.mass_kg"] if m == "linear-axis" else v["axis.motor_inertia_kg_m2"] + v["axis.screw_inertia_kg_m2"],
        {"linear-axis": "derived: axis.mass_kg in load coordinates (kg m^2 per rad^2 = kg)",
         "*": "derived: axis.motor_inertia_kg_m2 + axis.screw_inertia_kg_m2 (the rotating member of a screw-driven axis)"}),
    "drive.torque_limit_n_m": (lambda v, m: v["drive.force_limit_n"],
                               "derived: drive.force_limit_n in load coordinates (N as N m per rad)"),
    "sensor.encoder_counts_per_rev": (lambda v, m: max(64, round(2.0 * math.pi / v["sensor.encoder_resolution_m"])),
                                      "derived: sensor.encoder_resolution_m in load coordinates (2 pi m per 'revolution')"),
    "screw.pitch_diameter_mm": (
        _linear_or(lambda v, m: v["screw.lead_mm"] * (7.0 if m == "inverted-roller-screw" else 3.2), lambda v, m: 10.0),
        {"inverted-roller-screw": "default: the paper's proportions, pitch diameter 7 x lead (14 mm for 2 mm)",
         "linear-axis": "default: not used by a linear axis (rotary core placeholder)",
         "*": "default: catalogue proportions of screw-driven axes, pitch diameter ~3.2 x lead (16x5, 32x10, 40x12 mm)"}),
    "screw.starts": (_by({"inverted-roller-screw": 4, "roller-screw": 5, "*": 1}),
                     {"inverted-roller-screw": "default: the paper's 4-start screw",
                      "roller-screw": "assumption: standard planetary roller screws have 5-start screws and nuts",
                      "*": "default: single start (not used by the model of this mechanism)"}),
    "screw.mass_kg": (lambda v, m: v["axis.mass_kg"] if m == "linear-axis" else
                      (v["axis.moving_mass_kg"] if m in SCREW_DRIVEN else 1.0),
                      {"inverted-roller-screw": "default: the paper plant's translating screw with rod end and fixture, 1 kg",
                       "linear-axis": "derived: axis.mass_kg (the translating member)",
                       "*": "derived: axis.moving_mass_kg (the translating member: nut, carriage and payload)"}),
    "nut.lead_mm": (lambda v, m: v["screw.lead_mm"], "default: equal to screw.lead_mm (the threads mesh)"),
    "nut.starts": (lambda v, m: v["screw.starts"], "default: equal to screw.starts (the threads mesh)"),
    "roller.starts": (1, "default: single-start rollers (all catalogue roller screws)"),
    "roller.pitch_diameter_mm": (lambda v, m: v["screw.pitch_diameter_mm"] / (v["screw.starts"] - 2.0)
                                 if m == "roller-screw" and v["screw.starts"] > 2 else
                                 v["screw.pitch_diameter_mm"] / v["screw.starts"],
                                 {"roller-screw": "default: the standard design's matching rule d_S = (n_S - 2) d_R",
                                  "*": "default: the inverted design's matching rule d_S = n_S d_R"}),
    "roller.lead_mm": (lambda v, m: v["screw.lead_mm"] / v["screw.starts"],
                       "default: one thread pitch (screw.lead_mm / screw.starts), single-start rollers"),
    "nut.pitch_diameter_mm": (lambda v, m: v["screw.pitch_diameter_mm"] + 2.0 * v["roller.pitch_diameter_mm"],
                              "default: closed geometry d_N = d_S + 2 d_R"),
    "roller.count": (lambda v, m: min(10, math.floor(0.9 * math.pi * (v["screw.pitch_diameter_mm"]
                                                                       / v["roller.pitch_diameter_mm"] + 1))),
                     "default: 10 rollers (the paper), fewer where they would not fit on the orbit"),
    "roller.mass_kg": (lambda v, m: _STEEL_KG_M3 * math.pi / 4 * (v["roller.pitch_diameter_mm"] * 1e-3) ** 3 * 30.0 / 3.6,
                       "default: solid steel cylinder of the roller pitch diameter, 8.3 diameters long (the paper's 3.6 x 30 mm)"),
    "cage.mass_kg": (0.02, "default: the paper plant's two steel retainer rings, 20 g"),
    "cage.inertia_kg_m2": (2.0e-6, "default: the paper plant's retainer rings of ~18 mm mean diameter"),
    "thread.flank_angle_deg": (45.0, "default: standard roller-screw flank half-angle 45 deg"),
    "thread.engaged_threads": (15, "default: the paper plant's loaded threads per roller and side"),
    "thread.backlash_mm": (0.01, "default: axial play of a standard-grade (non-preloaded) nut"),
    "contact.stiffness_n_per_mm_e": (1.0e5, "default: the paper's IMPACT K for GCr15"),
    "contact.exponent": (1.5, "default: the paper's IMPACT exponent (Hertzian point contact)"),
    "contact.damping_n_s_per_mm": (50.0, "default: the paper's IMPACT C_max"),
    "contact.penetration_mm": (0.2, "default: the paper's IMPACT full-damping depth"),
    "friction.static": (0.3, "default: the paper's Coulomb static coefficient (sets the breakaway, 1.2 x sliding)"),
    "friction.dynamic": (0.25, "default: the paper's Coulomb dynamic coefficient"),
    "friction.stribeck_velocity_m_s": (1.0e-4, "default: ADAMS stiction transition velocity 0.1 mm/s"),
    "friction.transition_velocity_m_s": (1.0e-6, "default: Karnopp stick band 1 um/s (the paper plant's)"),
    "friction.efficiency": (_by({"inverted-roller-screw": 0.85, "roller-screw": 0.85, "ball-screw": 0.9, "linear-axis": 1.0}),
                            {"linear-axis": "derived: a linear axis has no screw (its friction is in friction.coulomb_*/viscous_*)",
                             "ball-screw": "default: typical forward efficiency of ball screws, catalogues 0.9 to 0.95",
                             "*": "default: typical forward efficiency of planetary roller screws, catalogues 0.75 to 0.9"}),
    "screw.rated_load_n": (lambda v, m: v["drive.torque_limit_n_m"] * 2 * math.pi * v["friction.efficiency"]
                           / (v["screw.lead_mm"] * 1e-3),
                           "default: the axial force the torque limit drives through the screw at its efficiency"),
    "friction.no_load_torque_n_m": (lambda v, m: (v["friction.coulomb_positive_n"] + v["friction.coulomb_negative_n"]) / 2
                                    if m == "linear-axis" else 0.01 * v["drive.torque_limit_n_m"],
                                    {"linear-axis": "derived: mean of friction.coulomb_positive_n and _negative_n",
                                     "*": "default: seal and bearing drag ~1 % of the torque limit (the paper plant's 0.7 %)"}),
    "friction.viscous_n_m_s_per_rad": (lambda v, m: (v["friction.viscous_positive_n_s_per_m"]
                                                     + v["friction.viscous_negative_n_s_per_m"]) / 2
                                       if m == "linear-axis" else 1.0e-4,
                                       {"linear-axis": "derived: mean of friction.viscous_positive/negative_n_s_per_m",
                                        "*": "default: grease churning and motor iron losses (the paper plant's 1e-4 N m s/rad)"}),
    "friction.torque_offset_n_m": (0.0, {"linear-axis": "derived: 0 (a linear axis carries its offset in "
                                                        "friction.coulomb_positive_n and _negative_n)",
                                         "*": "default: symmetric drag (Coulomb level friction.no_load_torque_n_m in "
                                              "both directions)"}),
    "friction.no_load_breakaway_torque_n_m": (lambda v, m: v["friction.no_load_torque_n_m"],
                                              "default: no breakaway excess on the drag (equal to "
                                              "friction.no_load_torque_n_m)"),
    "friction.viscous_offset_n_m_s_per_rad": (0.0, {"linear-axis": "derived: 0 (a linear axis carries its viscous "
                                                                   "friction per direction in "
                                                                   "friction.viscous_positive/negative_n_s_per_m)",
                                                    "*": "default: symmetric viscous friction (the same coefficient "
                                                         "in both directions)"}),
    "friction.creep_velocity_m_s": (1.0e-3, "default: lubricated rolling creep (the paper plant's 1 mm/s)"),
    "friction.traction_preload_n": (lambda v, m: 0.04 * v["screw.rated_load_n"],
                                    "default: 4 % of the rated load (the paper plant's 200 N at 5 kN)"),
    "drive.current_loop_bandwidth_hz": (1000.0, "default: typical servo-drive current-loop bandwidth 1 kHz"),
    "drive.command_delay_samples": (0, "default: no delay beyond the controller's one-sample computation delay "
                                       "(the drive acts on the command at the next sample; a fieldbus drive "
                                       "typically adds 1 to 2 samples)"),
    "sensor.speed_filter_time_constant_s": (2.0e-4, "default: typical speed-measurement filter of a servo drive, 0.2 ms"),
    "sensor.torque_noise_n_m": (lambda v, m: v["drive.torque_limit_n_m"] / 600.0,
                                "default: ~0.17 % of the torque limit RMS per sample (12-bit current sensing; the paper plant's 5 mN m at 3 N m)"),
    "tolerance.roller_position_std_um": (2.0, "default: precision-grade roller screw (lead deviation class ~G5)"),
    "tolerance.roller_runout_um": (1.0, "default: runout of a ground roller"),
    # screw-driven axes
    "axis.bearing_span_mm": (lambda v, m: 30.0 * v["screw.pitch_diameter_mm"],
                             "assumption: bearing span ~30 screw diameters (a 32 mm screw over ~1 m, the slenderness of "
                             "catalogue critical-speed tables)"),
    "axis.stroke_position_mm": (lambda v, m: 0.5 * v["axis.bearing_span_mm"],
                                "default: nut at mid-span (where a fixed-fixed screw is softest)"),
    "axis.screw_inertia_kg_m2": (lambda v, m: math.pi * _STEEL_KG_M3 * (v["screw.pitch_diameter_mm"] * 1e-3) ** 4
                                 * v["axis.bearing_span_mm"] * 1e-3 / 32.0,
                                 "default: solid steel cylinder of the pitch diameter over the bearing span, pi rho d^4 L / 32"),
    "screw.root_diameter_mm": (lambda v, m: 0.83 * v["screw.pitch_diameter_mm"],
                               "assumption: root ~0.83 x pitch diameter (ball screws: pitch diameter minus ball diameter, "
                               "e.g. ~26.5 mm for 32 x 10 with 1/4 in balls)"),
    "screw.youngs_modulus_gpa": (206.0, "default: steel, E = 2.06e5 N/mm^2 (the THK and HIWIN rigidity formulas)"),
    "axis.nut_stiffness_n_per_um": (lambda v, m: (40.0 if m == "roller-screw" else 20.0) * v["screw.pitch_diameter_mm"],
                                    {"roller-screw": "assumption: preloaded roller nut ~40 N/um per mm of screw diameter "
                                                     "(roller screws are ~2x stiffer than ball screws of the same size)",
                                     "*": "assumption: preloaded ball nut ~20 N/um per mm of screw diameter "
                                          "(~650 N/um for 32 mm)"}),
    "axis.bearing_stiffness_n_per_um": (lambda v, m: 25.0 * v["screw.pitch_diameter_mm"],
                                        "assumption: preloaded angular-contact support-bearing pair ~25 N/um per mm of screw "
                                        "diameter (~800 N/um for 32 mm)"),
    "axis.fixed_ends": (1, "default: fixed-free mounting (one axially fixed end; fixed-supported is the same axially)"),
    "axis.nut_loss_on_whole_force": (1, "default: a real nut's thread loss grows with the whole force it transmits, "
                                        "the carriage's inertial force included (Varanasi & Nayfeh, J. Dyn. Sys. Meas. "
                                        "Control 126(2) 2004; the stiff limit of the compliant screw-driven model); 0 "
                                        "puts it on the external load only (prsa_ctrl.plant.model.nut_loss_on_whole_force)"),
    "axis.axial_damping_ratio": (0.03, {"linear-axis": "default: typical modal damping of a feed axis's first mode (1 to "
                                                       "5 %); not used while axis.load_mass_kg = 0 (rigid)",
                                        "*": "default: typical modal damping of the axial mode of a screw feed drive (1 to 5 %)"}),
    "axis.load_mass_kg": (0.0, "default: rigid, the whole axis.mass_kg moves as one body"),
    "axis.load_stiffness_n_per_um": (100.0, "default: not used while axis.load_mass_kg = 0 (rigid)"),
}

#: Unit of each key (for :func:`prsa_ctrl.plant.describe.describe_plant`), from its name.
UNITS: Mapping[str, str] = {
    k: next((u for suffix, u in (("_mm_e", "N/mm^e"), ("_n_s_per_mm", "N s/mm"), ("_kg_m2", "kg m^2"), ("_kg_m3", "kg/m^3"),
                                  ("_n_m_s_per_rad", "N m s/rad"), ("_n_s_per_m", "N s/m"), ("_n_per_um", "N/um"),
                                  ("_n_per_unit", "N per command unit"), ("_kg", "kg"), ("_mm", "mm"), ("_um", "um"),
                                  ("_deg", "deg"), ("_m_s", "m/s"), ("_n_m", "N m"), ("_n", "N"), ("_hz", "Hz"),
                                  ("_s", "s"), ("_gpa", "GPa"), ("_m", "m"), ("_per_rev", "counts/rev"), ("_samples", "samples"))
             if k.endswith(suffix)), "-")
    for k in KIND
}
