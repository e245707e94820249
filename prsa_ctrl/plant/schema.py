"""The plant file's schema: every section and key, the kind of value, and its plausible range.

The lowest layer of :mod:`prsa_ctrl.plant`: both the plant-file reader and the uncertainty
checks read it, so it imports nothing of the package.
"""

from __future__ import annotations

from typing import Mapping

__all__ = ["SCHEMA", "PLAUSIBLE", "ALLOWED_KEYS", "POSITIVE", "NON_NEGATIVE", "POSITIVE_INTEGER", "FRACTION"]

# Kinds of value: positive finite, non-negative finite, positive integer, fraction in (0, 1].
POSITIVE, NON_NEGATIVE, POSITIVE_INTEGER, FRACTION = "positive", "non-negative", "positive integer", "fraction in (0, 1]"

#: Section -> key -> kind. Every key is required; no other key is accepted.
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
    },
    "drive": {"torque_limit_n_m": POSITIVE, "current_loop_bandwidth_hz": POSITIVE},
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
    "drive.torque_limit_n_m": (1e-3, 1e5, "servo and torque motors: 0.01 to ~10 kN m"),
    "drive.current_loop_bandwidth_hz": (10.0, 1e5, "servo drives 0.5 to 5 kHz"),
    "sensor.sample_time_s": (1e-6, 0.02, "speed loops run at 50 Hz to 100 kHz (servo drives 1 to 16 kHz); the "
                             "tuner's prediction and the verification record hold one point per sample"),
    "sensor.encoder_counts_per_rev": (64, 2**32, "counts per revolution: the coarsest incremental encoders "
                                      "(16 lines, x4 quadrature) to 32-bit absolute encoders"),
    "sensor.speed_filter_time_constant_s": (1e-7, 1.0, "speed-measurement filter of a servo drive, ~0.1 ms"),
    "sensor.torque_noise_n_m": (0.0, 1e3, "current-measurement noise, a fraction of the torque limit"),
    "tolerance.roller_position_std_um": (0.0, 50.0, "lead deviation of precision to transport grades stays "
                                         "below ~50 um; beyond it rollers lose contact"),
    "tolerance.roller_runout_um": (0.0, 50.0, "ground rollers run out by a few micrometres"),
}
