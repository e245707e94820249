"""A two-mass ball-screw feed axis logged in load coordinates (mm, N), command as applied, delay 1.

Issue 32, part 6: a foreign log generator (numpy/scipy only, written without reading
prsa-ctrl's fitting or model code; the simulator is ``_axis.py``). What differs from the
toolkit's model structure, on purpose:

- two masses: motor side (rotor 1.5e-3 + coupling 5e-5 + a solid 40 mm x 1.4 m steel screw
  2.762e-3 kg m^2) and a 500 kg table (40 x 10 ball screw), axial stiffness 180 N/um, about 3 %
  of critical damping: first axial mode ~110 Hz at the loaded operating point, anti-resonance
  ~95 Hz (a shallow pair: the table reflects 23 % of the total inertia);
- nut loss ``(1/0.92 - 1) |a F_s| sgn(w)`` on the whole force through the nut;
- standstill (Stribeck) friction, Coulomb 0.55 / 0.62 N m forward / backward (breakaway
  0.75 / 0.80 N m, Stribeck speed 0.5 rad/s), viscous 2.0e-3 N m s/rad;
- a 4 kHz PI speed loop (back-calculation anti-windup, torque limit 30 N m), one sample of
  computation delay plus one of transport: the command logged **as applied** at sample k acts
  from k + 1 (``drive.command_delay_samples`` = 1); first-order current loop 800 Hz;
- a 21-bit encoder (floored) with 1e-6 rad noise, speed filter 0.25 ms;
- the log in **load coordinates** as a drive with linear scaling writes it: time in s, table
  position in mm (the motor encoder times the lead), the command as a force in N (the torque
  command over ``a`` = lead / 2 pi, the force an ideal screw would make of it), the load cell
  in N; described by ``log.toml`` (``axis = "linear"``).

Experiments (1.2 s each, 4800 samples): ``multisine.csv`` (screw speed 25 +- 10 rad/s, 2..120
Hz, 2000 N), ``loadsteps.csv`` (25 rad/s, 0 -> 4000 -> 1000 -> 4000 N), ``staircase.csv``
(0 N, from rest: +15, +35, +25, -15, -35, -25 rad/s), ``frf_experiment.csv`` (25 rad/s, 3000 N,
a 0.8 N m torque multisine 5..1500 Hz, column ``dither_n``); ``bode.csv`` (measured FRF in motor
coordinates, torque command as logged -> backward-difference motor speed, 5..1800 Hz, at
25 rad/s and 3000 N, exact linear part with 2 % complex noise). ``base.toml``: the plant from
datasheets.

Run ``python gen_feedaxis_load.py OUT_DIR [SEED]`` or call :func:`generate`.
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

TS = 2.5e-4
N_SAMPLES = 4800
FRF_SPEED_RAD_S = 25.0
FRF_LOAD_N = 3000.0
FRF_NOISE = 0.02
SCREW_INERTIA = math.pi * 7850.0 * 0.040 ** 4 * 1.4 / 32.0  # solid steel, 40 mm x 1.4 m
_A = 0.010 / (2 * math.pi)
_JM = 1.5e-3 + 5e-5 + SCREW_INERTIA
_M_EFF = 1.0 / (_A ** 2 / _JM + 1.0 / 500.0)

AXIS = _axis.Axis(
    lead_m=0.010,
    motor_side_inertia_kg_m2=_JM,
    load_mass_kg=500.0,
    stiffness_n_per_m=1.8e8,
    damping_n_s_per_m=2.0 * 0.03 * math.sqrt(1.8e8 * _M_EFF),
    efficiency=0.92,
    coulomb_pos_n_m=0.55,
    coulomb_neg_n_m=0.62,
    breakaway_pos_n_m=0.75,
    breakaway_neg_n_m=0.80,
    stribeck_speed_rad_s=0.5,
    viscous_n_m_s_per_rad=2.0e-3,
)
DRIVE = _axis.Drive(sample_time_s=TS, kp=0.8, ki=24.0, torque_limit_n_m=30.0, current_loop_hz=800.0,
                    transport_delay_samples=1, torque_noise_n_m=0.03, n_sub=4)
SENSORS = _axis.Sensors(counts_per_rev=2 ** 21, angle_noise_rad=1e-6, speed_filter_s=2.5e-4, load_noise_n=10.0)

LOG_DESCRIPTION = """\
# Log description of the feed axis's drive recorder, linear scaling (prsa-fit --log-format).
description = "Feed axis 40 x 10, 4 kHz drive, linear scaling: position mm, force command N, load N"
format = "csv"
axis = "linear"

[time]
name = "time_s"
unit = "s"

[position]               # table position from the motor encoder x lead
name = "position_mm"
unit = "mm"

[command]                # the torque command scaled to a force through the lead
name = "force_command_n"
unit = "N"
logged = "as-applied"

[load]
name = "load_n"
unit = "N"
"""

BASE_PLANT = """\
# A heavy feed axis as its user writes it from datasheets (nominal values, not the truth).
name = "feed-axis-40x10"
description = "Ball screw 40 x 10, fixed-fixed over 1.4 m, ~450 kg table, 4 kHz drive"
mechanism = "ball-screw"
mounting = { value = "fixed-fixed", source = "drawing: bearing pairs at both ends" }

[screw]
pitch_diameter_mm = { value = 40.0, source = "catalogue size 40 x 10" }
lead_mm = { value = 10.0, source = "catalogue size 40 x 10" }
root_diameter_mm = { value = 34.0, source = "catalogue: 40 mm screw, 6.35 mm balls" }
rated_load_n = { value = 8000.0, source = "assumption: continuous thrust of the axis" }

[axis]
motor_inertia_kg_m2 = { value = 1.4e-3, source = "motor catalogue: rotor 1.4e-3 kg m^2" }
moving_mass_kg = { value = 450.0, source = "drawing: table and fixture, about 450 kg" }
bearing_span_mm = { value = 1400.0, source = "drawing" }
stroke_position_mm = { value = 700.0, source = "assumption: table at mid-stroke" }
nut_stiffness_n_per_um = { value = 900.0, source = "catalogue: preloaded double nut" }
bearing_stiffness_n_per_um = { value = 1000.0, source = "catalogue: support bearing pairs" }

[friction]
efficiency = { value = 0.9, source = "catalogue: ball screw efficiency 0.9 to 0.95" }
no_load_torque_n_m = { value = 0.5, source = "catalogue: preload drag torque plus seals" }
viscous_n_m_s_per_rad = { value = 1.5e-3, source = "assumption" }

[drive]
torque_limit_n_m = { value = 30.0, source = "drive parameter: torque limit" }
current_loop_bandwidth_hz = { value = 1000.0, source = "assumption: typical current loop" }

[sensor]
sample_time_s = { value = 2.5e-4, source = "drive parameter: 4 kHz speed loop" }
encoder_counts_per_rev = { value = 2097152, source = "motor nameplate: 21-bit encoder" }
speed_filter_time_constant_s = { value = 2.5e-4, source = "drive parameter: speed filter 0.25 ms" }
"""


def truth() -> dict:
    """The truth, SI, under the toolkit's plant keys where one exists (see the module docstring).

    ``drive.command_delay_samples`` = 1 = ``delay_logged_to_action_samples`` (logged as applied).
    """
    ax, drv, sen = AXIS, DRIVE, SENSORS
    fr, far = _axis.mode_frequencies_hz(ax, FRF_LOAD_N)
    fr0, _ = _axis.mode_frequencies_hz(ax, None)
    return {
        "mechanism": "ball-screw",
        "screw.lead_mm": ax.lead_m * 1e3,
        "axis.motor_inertia_kg_m2": 1.55e-3,
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
        "friction.stribeck_velocity_m_s": ax.stribeck_speed_rad_s * ax.a,
        "friction.viscous_n_m_s_per_rad": ax.viscous_n_m_s_per_rad,
        "drive.current_loop_bandwidth_hz": drv.current_loop_hz,
        "drive.command_delay_samples": drv.transport_delay_samples,
        "delay_logged_to_action_samples": drv.transport_delay_samples,
        "command_logged": "applied",
        "drive.torque_limit_n_m": drv.torque_limit_n_m,
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


def _profiles() -> dict:
    n, t = N_SAMPLES, np.arange(N_SAMPLES) * TS
    ms, _ = _axis.schroeder_multisine(n, TS, 0.4, 2.0, 120.0, 10.0)
    steps = np.select([t < 0.3, t < 0.6, t < 0.9], [0.0, 4000.0, 1000.0], 4000.0)
    levels = np.array([15.0, 35.0, 25.0, -15.0, -35.0, -25.0])
    stair = levels[np.minimum((t / 0.2).astype(int), levels.size - 1)]
    dith, _ = _axis.schroeder_multisine(n, TS, 0.2, 5.0, 1500.0, 0.8, n_lines=60)
    return {
        "multisine": (25.0 + ms, np.full(n, 2000.0), None, 25.0),
        "loadsteps": (np.full(n, 25.0), steps, None, 25.0),
        "staircase": (stair, np.zeros(n), None, 0.0),
        "frf_experiment": (np.full(n, FRF_SPEED_RAD_S), np.full(n, FRF_LOAD_N), dith, FRF_SPEED_RAD_S),
    }


def simulate_all(seed: int = 0) -> dict:
    """Simulate every experiment (SI :class:`_axis.Run` per name), deterministic in ``seed``."""
    rng = np.random.default_rng([seed, 32, 6, 5])
    return {name: _axis.simulate(AXIS, DRIVE, SENSORS, r, f, rng, dither=d, start_speed=w0)
            for name, (r, f, d, w0) in _profiles().items()}


def bode(seed: int = 0):
    """The measured FRF: frequencies (Hz), the exact linear response and the noisy one written."""
    f = np.geomspace(5.0, 1800.0, 160)
    h = _axis.frf(AXIS, DRIVE, SENSORS, f, FRF_LOAD_N, DRIVE.transport_delay_samples)
    rng = np.random.default_rng([seed, 32, 6, 6])
    noise = FRF_NOISE * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)) / math.sqrt(2.0)
    return f, h, h * (1.0 + noise)


def generate(out_dir, seed: int = 0) -> dict:
    """Write the logs (load coordinates), ``log.toml``, ``bode.csv`` and ``base.toml``.

    Returns
    -------
    dict
        ``{"logs": {name: Path}, "frf": Path, "log_format": Path, "base": Path, "truth": dict}``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    a = AXIS.a
    logs = {}
    for name, run in simulate_all(seed).items():
        cols = {"time_s": run.time, "position_mm": run.angle_measured * a * 1e3,
                "force_command_n": run.command_applied / a, "load_n": run.load_measured}
        if name == "frf_experiment":
            cols["dither_n"] = np.concatenate(([0.0], run.dither[:-1])) / a
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
