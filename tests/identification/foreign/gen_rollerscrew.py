"""A standard (screw-driven) planetary roller-screw axis, two-mass, logged as a drive logs it.

Issue 32, part 6: a foreign log generator (numpy/scipy only, written without reading
prsa-ctrl's fitting or model code; the simulator is ``_axis.py``). What differs from the
toolkit's model structure, on purpose:

- two masses: motor side (rotor 4.0e-4 + coupling 3.0e-5 + a solid 30 mm x 600 mm steel screw
  3.7464e-4 kg m^2) and a 250 kg load, axial stiffness 120 N/um (screw, nut and bearing in
  series; softer than the catalogue values a user adds up), damper 1.04e4 N s/m (about 4 % of
  critical), first axial mode ~152 Hz at the loaded operating point, anti-resonance ~110 Hz;
- nut loss ``(1/0.88 - 1) |a F_s| sgn(w)`` on the whole force through the nut;
- standstill (Stribeck) friction, Coulomb level per direction (0.20 N m forward, 0.17 backward;
  breakaway 0.30 / 0.26 N m, Stribeck speed 0.8 rad/s), viscous 1.2e-3 N m s/rad;
- two delays: one sample of computation and one of transport (the command logged as computed at
  sample k acts from k + 2), 4 kHz PI speed loop with back-calculation anti-windup, first-order
  650 Hz current loop, torque limit 12 N m;
- a 20-bit encoder (floored) with 1e-6 rad noise, speed = backward difference then a 0.4 ms
  first-order filter (the loop runs on it);
- the log: time in ms, motor angle in degrees, filtered speed in rpm, torque command in % of the
  rated 4.5 N m, axial load in kN, described by a log description (``log.toml``).

Experiments (1.2 s each, 4800 samples, as a user records them): ``multisine.csv`` (speed
30 +- 15 rad/s, 36 lines 3.3..150 Hz, 1500 N), ``loadsteps.csv`` (30 rad/s, 0 -> 3000 -> 800
-> 3000 N at 0.3/0.6/0.9 s), ``staircase.csv`` (0 N, from rest: +20, +45, +30, -20, -45, -30
rad/s, 0.2 s each), ``frf_experiment.csv`` (30 rad/s, 2500 N, a 0.3 N m torque multisine
5..1500 Hz added to the command, column ``dither_pct``) and ``bode.csv`` (the measured FRF,
torque command as logged -> motor speed as the backward difference of the encoder angle,
5..1800 Hz, at 30 rad/s and 2500 N, from the exact linear part, 2 % complex noise).
``base.toml`` is the plant a user writes from datasheets (nominal values, not the truth).

Run ``python gen_rollerscrew.py OUT_DIR [SEED]`` or call :func:`generate`.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

try:
    from . import _axis
except ImportError:  # run as a script
    import _axis  # type: ignore[no-redef]

RATED_TORQUE_N_M = 4.5
TS = 2.5e-4
N_SAMPLES = 4800
FRF_SPEED_RAD_S = 30.0
FRF_LOAD_N = 2500.0
FRF_NOISE = 0.02

SCREW_INERTIA = math.pi * 7850.0 * 0.030 ** 4 * 0.600 / 32.0  # solid steel, 30 mm x 600 mm
M_EFF = 1.0 / ((0.010 / (2 * math.pi)) ** 2 / (4.3e-4 + SCREW_INERTIA) + 1.0 / 250.0)

AXIS = _axis.Axis(
    lead_m=0.010,
    motor_side_inertia_kg_m2=4.0e-4 + 3.0e-5 + SCREW_INERTIA,
    load_mass_kg=250.0,
    stiffness_n_per_m=1.2e8,
    damping_n_s_per_m=2.0 * 0.04 * math.sqrt(1.2e8 * M_EFF),
    efficiency=0.88,
    coulomb_pos_n_m=0.20,
    coulomb_neg_n_m=0.17,
    breakaway_pos_n_m=0.30,
    breakaway_neg_n_m=0.26,
    stribeck_speed_rad_s=0.8,
    viscous_n_m_s_per_rad=1.2e-3,
)
DRIVE = _axis.Drive(sample_time_s=TS, kp=0.27, ki=11.0, torque_limit_n_m=12.0, current_loop_hz=650.0,
                    transport_delay_samples=1, torque_noise_n_m=0.01, n_sub=4)
SENSORS = _axis.Sensors(counts_per_rev=2 ** 20, angle_noise_rad=1e-6, speed_filter_s=4e-4, load_noise_n=8.0)

LOG_DESCRIPTION = f"""\
# Log description of the roller-screw drive's recorder (prsa-fit --log-format).
description = "Roller screw 30 x 10, 4 kHz drive recorder: time ms, angle deg, speed rpm, torque % of rated, load kN"
format = "csv"
axis = "rotary"

[time]
name = "t_ms"
unit = "ms"

[position]               # motor encoder angle, 20 bit
name = "pos_deg"
unit = "deg"

[speed]                  # the drive's filtered speed (0.4 ms)
name = "speed_rpm"
unit = "rpm"

[command]                # torque command in % of the rated torque {RATED_TORQUE_N_M} N m
name = "torque_pct"
unit = "%"
gain = {RATED_TORQUE_N_M / 100.0!r}            # N m per %
logged = "as-computed"

[load]
name = "load_kN"
unit = "kN"
"""

BASE_PLANT = """\
# A roller-screw axis as its user writes it from datasheets (nominal values, not the truth).
name = "press-axis-30x10"
description = "Roller screw 30 x 10, screw-driven, fixed-free over 600 mm, ~230 kg load, 4 kHz drive"
mechanism = "roller-screw"
mounting = { value = "fixed-free", source = "drawing: screw held by the bearing pair at the motor end" }

[screw]
pitch_diameter_mm = { value = 30.0, source = "catalogue size 30 x 10" }
lead_mm = { value = 10.0, source = "catalogue size 30 x 10" }
starts = { value = 5, source = "catalogue: 5 starts of 2 mm pitch" }
root_diameter_mm = { value = 28.0, source = "assumption: pitch diameter minus one thread depth" }
rated_load_n = { value = 10000.0, source = "assumption: rated thrust of the axis" }

[roller]
pitch_diameter_mm = { value = 10.0, source = "catalogue" }
count = { value = 10, source = "catalogue" }

[axis]
motor_inertia_kg_m2 = { value = 3.8e-4, source = "motor catalogue: rotor 3.8e-4 kg m^2" }
moving_mass_kg = { value = 230.0, source = "drawing: carriage and tool, about 230 kg" }
bearing_span_mm = { value = 600.0, source = "drawing" }
stroke_position_mm = { value = 300.0, source = "assumption: nut at mid-stroke" }
nut_stiffness_n_per_um = { value = 1200.0, source = "catalogue: preloaded roller nut" }
bearing_stiffness_n_per_um = { value = 900.0, source = "catalogue: angular-contact pair" }

[friction]
efficiency = { value = 0.85, source = "catalogue: roller screw efficiency 0.75 to 0.9" }
no_load_torque_n_m = { value = 0.15, source = "assumption: nut preload and seal drag" }
viscous_n_m_s_per_rad = { value = 1.0e-3, source = "assumption" }

[drive]
torque_limit_n_m = { value = 12.0, source = "drive parameter: torque limit" }
current_loop_bandwidth_hz = { value = 1000.0, source = "assumption: typical current loop" }

[sensor]
sample_time_s = { value = 2.5e-4, source = "drive parameter: 4 kHz speed loop" }
encoder_counts_per_rev = { value = 1048576, source = "motor nameplate: 20-bit encoder" }
speed_filter_time_constant_s = { value = 4.0e-4, source = "drive parameter: speed filter 0.4 ms" }
"""


def truth() -> dict:
    """The truth, SI, under the toolkit's plant keys where one exists (else a descriptive name).

    ``reflected_inertia_kg_m2`` is ``J_m + m a^2`` (what the acceptance compares);
    ``drive.command_delay_samples`` the transport delay beyond the computation delay;
    ``delay_logged_to_action_samples`` the whole delay of the logged (as-computed) command;
    ``first_mode_hz`` the axial mode at the FRF's operating point (loaded, the motor side sees
    ``1/eta`` of the nut force), ``first_mode_lossless_hz`` without the loss.
    """
    ax, drv, sen = AXIS, DRIVE, SENSORS
    a = ax.a
    fr, far = _axis.mode_frequencies_hz(ax, FRF_LOAD_N)
    fr0, _ = _axis.mode_frequencies_hz(ax, None)
    return {
        "mechanism": "roller-screw",
        "screw.lead_mm": ax.lead_m * 1e3,
        "axis.motor_inertia_kg_m2": 4.3e-4,  # rotor + coupling
        "axis.screw_inertia_kg_m2": SCREW_INERTIA,
        "nut.inertia_kg_m2": ax.motor_side_inertia_kg_m2,
        "axis.moving_mass_kg": ax.load_mass_kg,
        "load_inertia_kg_m2": ax.load_inertia_kg_m2,
        "reflected_inertia_kg_m2": ax.total_inertia_kg_m2,
        "frf_low_frequency_inertia_kg_m2": ax.motor_side_inertia_kg_m2 + ax.load_inertia_kg_m2 / ax.efficiency,
        "axial_stiffness_n_per_m": ax.stiffness_n_per_m,
        "axial_damping_n_s_per_m": ax.damping_n_s_per_m,
        "first_mode_hz": fr,
        "anti_resonance_hz": far,
        "first_mode_lossless_hz": fr0,
        "friction.efficiency": ax.efficiency,
        "friction.no_load_torque_n_m": 0.5 * (ax.coulomb_pos_n_m + ax.coulomb_neg_n_m),
        "friction.torque_offset_n_m": 0.5 * (ax.coulomb_pos_n_m - ax.coulomb_neg_n_m),
        "friction.no_load_breakaway_torque_n_m": 0.5 * (ax.breakaway_pos_n_m + ax.breakaway_neg_n_m),
        "friction.stribeck_velocity_m_s": ax.stribeck_speed_rad_s * a,
        "friction.viscous_n_m_s_per_rad": ax.viscous_n_m_s_per_rad,
        "drive.current_loop_bandwidth_hz": drv.current_loop_hz,
        "drive.command_delay_samples": drv.transport_delay_samples,
        "delay_logged_to_action_samples": 1 + drv.transport_delay_samples,
        "command_logged": "computed",
        "drive.torque_limit_n_m": drv.torque_limit_n_m,
        "rated_torque_n_m": RATED_TORQUE_N_M,
        "speed_loop_kp_n_m_s_per_rad": drv.kp,
        "speed_loop_ki_n_m_per_rad": drv.ki,
        "sensor.sample_time_s": drv.sample_time_s,
        "sensor.encoder_counts_per_rev": sen.counts_per_rev,
        "sensor.speed_filter_time_constant_s": sen.speed_filter_s,
        "sensor.torque_noise_n_m": drv.torque_noise_n_m,
        "frf_speed_rad_s": FRF_SPEED_RAD_S,
        "frf_load_n": FRF_LOAD_N,
        # for a judge of diagnoses: every resonance (loaded and without the loss) and anti-resonance,
        # no position-periodic torque, the units and coordinates given to prsa-fit the logs' own
        "modes_hz": (fr, fr0),
        "anti_resonances_hz": (far,),
        "periodic_orders_per_rev": (),
        "units_right": True,
        "coordinates_right": True,
    }


def _profiles(seed: int) -> dict:
    """Setpoint (rad/s), force (N), dither (N m) and start speed per experiment."""
    n, t = N_SAMPLES, np.arange(N_SAMPLES) * TS
    ms, _ = _axis.schroeder_multisine(n, TS, 0.3, 3.0, 150.0, 15.0)
    steps = np.select([t < 0.3, t < 0.6, t < 0.9], [0.0, 3000.0, 800.0], 3000.0)
    levels = np.array([20.0, 45.0, 30.0, -20.0, -45.0, -30.0])
    stair = levels[np.minimum((t / 0.2).astype(int), levels.size - 1)]
    dith, _ = _axis.schroeder_multisine(n, TS, 0.2, 5.0, 1500.0, 0.3, n_lines=60)
    return {
        "multisine": (30.0 + ms, np.full(n, 1500.0), None, 30.0),
        "loadsteps": (np.full(n, 30.0), steps, None, 30.0),
        "staircase": (stair, np.zeros(n), None, 0.0),
        "frf_experiment": (np.full(n, FRF_SPEED_RAD_S), np.full(n, FRF_LOAD_N), dith, FRF_SPEED_RAD_S),
    }


def simulate_all(seed: int = 0) -> dict:
    """Simulate every experiment (SI :class:`_axis.Run` per name), deterministic in ``seed``."""
    rng = np.random.default_rng([seed, 32, 6, 1])
    runs = {}
    for name, (r, f, d, w0) in _profiles(seed).items():
        runs[name] = _axis.simulate(AXIS, DRIVE, SENSORS, r, f, rng, dither=d, start_speed=w0)
    return runs


def bode(seed: int = 0):
    """The measured FRF: frequencies (Hz), the exact linear response and the noisy one written."""
    f = np.geomspace(5.0, 1800.0, 160)
    h = _axis.frf(AXIS, DRIVE, SENSORS, f, FRF_LOAD_N, 1 + DRIVE.transport_delay_samples)
    rng = np.random.default_rng([seed, 32, 6, 2])
    noise = FRF_NOISE * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)) / math.sqrt(2.0)
    return f, h, h * (1.0 + noise)


def generate(out_dir, seed: int = 0) -> dict:
    """Write the logs, ``log.toml``, ``bode.csv`` and ``base.toml`` into ``out_dir``.

    Returns
    -------
    dict
        ``{"logs": {name: Path}, "frf": Path, "log_format": Path, "base": Path, "truth": dict}``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    logs = {}
    for name, run in simulate_all(seed).items():
        cols = {
            "t_ms": run.time * 1e3,
            "pos_deg": np.degrees(run.angle_measured),
            "speed_rpm": run.speed_measured * 30.0 / math.pi,
            "torque_pct": run.command_computed / RATED_TORQUE_N_M * 100.0,
            "load_kN": run.load_measured / 1e3,
        }
        if name == "frf_experiment":
            cols["dither_pct"] = run.dither / RATED_TORQUE_N_M * 100.0
        path = out / f"{name}.csv"
        _axis.write_csv(path, cols, fmt="%.12g")
        logs[name] = path
    f, _, hn = bode(seed)
    frf_path = out / "bode.csv"
    _axis.write_csv(frf_path, {"frequency_hz": f, "magnitude_db": 20.0 * np.log10(np.abs(hn)),
                               "phase_deg": np.degrees(np.unwrap(np.angle(hn)))})
    fmt = out / "log.toml"
    fmt.write_text(LOG_DESCRIPTION)
    base = out / "base.toml"
    base.write_text(BASE_PLANT)
    return {"logs": logs, "frf": frf_path, "log_format": fmt, "base": base, "truth": truth()}


if __name__ == "__main__":
    res = generate(sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 0)
    for k, v in res["truth"].items():
        print(f"{k} = {v}")
