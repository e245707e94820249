"""A rigid high-lead ball-screw axis with a two-sample drive delay, logged as applied and as computed.

Issue 32, part 6: a foreign log generator (numpy/scipy only, written without reading
prsa-ctrl's fitting or model code; the simulator is ``_axis.py``). What differs from the
toolkit's model structure, on purpose:

- a 32 x 20 ball screw moving an 80 kg carriage, taken as rigid (the axial spring idealised
  away), where the load reflects 39 % of the total inertia: motor side rotor 6.0e-4 + coupling
  4.0e-5 + a solid 32 mm x 800 mm steel screw 6.465e-4 kg m^2; load 80 (0.02 / (2 pi))^2 =
  8.106e-4 kg m^2;
- nut loss ``(1/0.93 - 1) |a F_s| sgn(w)`` on the whole force through the nut, whose inertial
  part ``m a dw/dt`` is solved exactly with the load (piecewise-linear balance);
- standstill (Stribeck) friction with a Coulomb level per direction (0.32 / 0.28 N m, breakaway
  0.42 / 0.36 N m, Stribeck speed 1 rad/s), viscous 6e-4 N m s/rad;
- an 8 kHz PI speed loop (back-calculation anti-windup, torque limit 18 N m), one sample of
  computation delay plus **two of transport**: the command the controller outputs over sample k
  (logged as applied) acts from k + 2; logged as computed at k it acts from k + 3; first-order
  current loop 1100 Hz;
- a 22-bit encoder (floored) with 5e-7 rad noise, the loop on the backward-difference speed
  through a 0.2 ms filter; load cell with 5 N noise.

Logs (1.0 s each, 8000 samples, SI, the toolkit's default column names ``time_s,
nut_angle_rad, torque_command_n_m, axial_load_n``) in ``applied/`` (the command as applied)
and ``computed/`` (the same runs, the command as computed): ``multisine.csv`` (30 +- 12 rad/s,
2..150 Hz, 800 N), ``loadsteps.csv`` (30 rad/s, 0 -> 1500 -> 300 -> 1500 N at 0.25/0.5/0.75 s),
``staircase.csv`` (0 N from rest: +20, +45, +30, -20, -45, -30 rad/s), ``frf_experiment.csv``
(30 rad/s, 1500 N, a 0.4 N m torque multisine 5..3000 Hz added, column
``torque_dither_n_m``); ``bode_applied.csv`` / ``bode_computed.csv`` (measured FRF, torque
command as logged -> backward-difference motor speed, 5..3500 Hz, 30 rad/s, 1500 N, exact
linear part with 2 % complex noise). ``base.toml``: the plant from datasheets.

Run ``python gen_ballscrew.py OUT_DIR [SEED]`` or call :func:`generate`.
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

TS = 1.25e-4
N_SAMPLES = 8000
FRF_SPEED_RAD_S = 30.0
FRF_LOAD_N = 1500.0
FRF_NOISE = 0.02
SCREW_INERTIA = math.pi * 7850.0 * 0.032 ** 4 * 0.800 / 32.0  # solid steel, 32 mm x 800 mm

AXIS = _axis.Axis(
    lead_m=0.020,
    motor_side_inertia_kg_m2=6.0e-4 + 4.0e-5 + SCREW_INERTIA,
    load_mass_kg=80.0,
    stiffness_n_per_m=None,
    damping_n_s_per_m=0.0,
    efficiency=0.93,
    coulomb_pos_n_m=0.32,
    coulomb_neg_n_m=0.28,
    breakaway_pos_n_m=0.42,
    breakaway_neg_n_m=0.36,
    stribeck_speed_rad_s=1.0,
    viscous_n_m_s_per_rad=6.0e-4,
)
DRIVE = _axis.Drive(sample_time_s=TS, kp=0.66, ki=33.0, torque_limit_n_m=18.0, current_loop_hz=1100.0,
                    transport_delay_samples=2, torque_noise_n_m=0.015, n_sub=2)
SENSORS = _axis.Sensors(counts_per_rev=2 ** 22, angle_noise_rad=5e-7, speed_filter_s=2e-4, load_noise_n=5.0)

BASE_PLANT = """\
# A feed axis with a high-lead ball screw, as its user writes it from datasheets (nominal values).
name = "feed-axis-32x20"
description = "Ball screw 32 x 20, screw-driven, fixed-fixed over 800 mm, ~75 kg carriage, 8 kHz drive"
mechanism = "ball-screw"
mounting = { value = "fixed-fixed", source = "drawing: bearing pairs at both ends" }

[screw]
pitch_diameter_mm = { value = 32.0, source = "catalogue size 32 x 20" }
lead_mm = { value = 20.0, source = "catalogue size 32 x 20" }
root_diameter_mm = { value = 26.4, source = "catalogue: 32 mm screw, 6.35 mm balls" }
rated_load_n = { value = 1700.0, source = "assumption: thrust at the rated 6 N m (6 * 2 pi * 0.9 / 0.02)" }

[axis]
motor_inertia_kg_m2 = { value = 6.2e-4, source = "motor catalogue: rotor 6.0e-4 plus coupling ~2e-5 kg m^2" }
moving_mass_kg = { value = 75.0, source = "drawing: carriage and fixture, about 75 kg" }
bearing_span_mm = { value = 800.0, source = "drawing" }
stroke_position_mm = { value = 400.0, source = "assumption: carriage at mid-stroke" }
nut_stiffness_n_per_um = { value = 800.0, source = "catalogue: preloaded double nut" }
bearing_stiffness_n_per_um = { value = 1000.0, source = "catalogue: support bearing pairs" }

[friction]
efficiency = { value = 0.9, source = "catalogue: ball screw efficiency 0.9 to 0.95" }
no_load_torque_n_m = { value = 0.25, source = "catalogue: preload drag torque" }
viscous_n_m_s_per_rad = { value = 5.0e-4, source = "assumption" }

[drive]
torque_limit_n_m = { value = 18.0, source = "drive parameter: torque limit" }
current_loop_bandwidth_hz = { value = 2000.0, source = "assumption: current loop of a 16 kHz PWM drive" }

[sensor]
sample_time_s = { value = 1.25e-4, source = "drive parameter: 8 kHz speed loop" }
encoder_counts_per_rev = { value = 4194304, source = "motor nameplate: 22-bit encoder" }
speed_filter_time_constant_s = { value = 2.0e-4, source = "drive parameter: speed filter 0.2 ms" }
"""


def truth(command_logged: str = "applied") -> dict:
    """The truth, SI, under the toolkit's plant keys where one exists.

    ``reflected_inertia_kg_m2`` is ``J_m + m a^2``; ``drive.command_delay_samples`` = 2, the
    transport delay beyond the computation delay; ``delay_logged_to_action_samples`` = 2 for the
    command logged as applied, 3 as computed. The axis is rigid: no axial mode.
    """
    if command_logged not in ("applied", "computed"):
        raise ValueError(f"command_logged = {command_logged!r}: expected 'applied' or 'computed'")
    ax, drv, sen = AXIS, DRIVE, SENSORS
    n_t = drv.transport_delay_samples
    return {
        "mechanism": "ball-screw",
        "screw.lead_mm": ax.lead_m * 1e3,
        "axis.motor_inertia_kg_m2": 6.4e-4,
        "axis.screw_inertia_kg_m2": SCREW_INERTIA,
        "nut.inertia_kg_m2": ax.motor_side_inertia_kg_m2,
        "axis.moving_mass_kg": ax.load_mass_kg,
        "load_inertia_kg_m2": ax.load_inertia_kg_m2,
        "reflected_inertia_kg_m2": ax.total_inertia_kg_m2,
        "frf_low_frequency_inertia_kg_m2": ax.motor_side_inertia_kg_m2 + ax.load_inertia_kg_m2 / ax.efficiency,
        "first_mode_hz": None,
        "friction.efficiency": ax.efficiency,
        "friction.no_load_torque_n_m": 0.5 * (ax.coulomb_pos_n_m + ax.coulomb_neg_n_m),
        "friction.torque_offset_n_m": 0.5 * (ax.coulomb_pos_n_m - ax.coulomb_neg_n_m),
        "friction.no_load_breakaway_torque_n_m": 0.5 * (ax.breakaway_pos_n_m + ax.breakaway_neg_n_m),
        "friction.stribeck_velocity_m_s": ax.stribeck_speed_rad_s * ax.a,
        "friction.viscous_n_m_s_per_rad": ax.viscous_n_m_s_per_rad,
        "drive.current_loop_bandwidth_hz": drv.current_loop_hz,
        "drive.command_delay_samples": n_t,
        "delay_logged_to_action_samples": n_t + (1 if command_logged == "computed" else 0),
        "command_logged": command_logged,
        "drive.torque_limit_n_m": drv.torque_limit_n_m,
        "speed_loop_kp_n_m_s_per_rad": drv.kp,
        "speed_loop_ki_n_m_per_rad": drv.ki,
        "sensor.sample_time_s": drv.sample_time_s,
        "sensor.encoder_counts_per_rev": sen.counts_per_rev,
        "sensor.speed_filter_time_constant_s": sen.speed_filter_s,
        "sensor.torque_noise_n_m": drv.torque_noise_n_m,
        "frf_speed_rad_s": FRF_SPEED_RAD_S,
        "frf_load_n": FRF_LOAD_N,
        # for a judge of diagnoses: a rigid axis (no resonance, no anti-resonance), no position-periodic
        # torque, the units and coordinates given to prsa-fit the logs' own
        "modes_hz": (),
        "anti_resonances_hz": (),
        "periodic_orders_per_rev": (),
        "units_right": True,
        "coordinates_right": True,
    }


def _profiles() -> dict:
    n, t = N_SAMPLES, np.arange(N_SAMPLES) * TS
    ms, _ = _axis.schroeder_multisine(n, TS, 0.25, 2.0, 150.0, 12.0)
    steps = np.select([t < 0.25, t < 0.5, t < 0.75], [0.0, 1500.0, 300.0], 1500.0)
    levels = np.array([20.0, 45.0, 30.0, -20.0, -45.0, -30.0])
    stair = levels[np.minimum((t / (1.0 / 6.0)).astype(int), levels.size - 1)]
    dith, _ = _axis.schroeder_multisine(n, TS, 0.2, 5.0, 3000.0, 0.4, n_lines=60)
    return {
        "multisine": (30.0 + ms, np.full(n, 800.0), None, 30.0),
        "loadsteps": (np.full(n, 30.0), steps, None, 30.0),
        "staircase": (stair, np.zeros(n), None, 0.0),
        "frf_experiment": (np.full(n, FRF_SPEED_RAD_S), np.full(n, FRF_LOAD_N), dith, FRF_SPEED_RAD_S),
    }


def simulate_all(seed: int = 0) -> dict:
    """Simulate every experiment (SI :class:`_axis.Run` per name), deterministic in ``seed``."""
    rng = np.random.default_rng([seed, 32, 6, 3])
    return {name: _axis.simulate(AXIS, DRIVE, SENSORS, r, f, rng, dither=d, start_speed=w0)
            for name, (r, f, d, w0) in _profiles().items()}


def bode(command_logged: str = "applied", seed: int = 0):
    """The measured FRF: frequencies (Hz), the exact linear response and the noisy one written."""
    delay = truth(command_logged)["delay_logged_to_action_samples"]
    f = np.geomspace(5.0, 3500.0, 180)
    h = _axis.frf(AXIS, DRIVE, SENSORS, f, FRF_LOAD_N, delay)
    rng = np.random.default_rng([seed, 32, 6, 4])
    noise = FRF_NOISE * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)) / math.sqrt(2.0)
    return f, h, h * (1.0 + noise)


def generate(out_dir, seed: int = 0) -> dict:
    """Write ``applied/`` and ``computed/`` logs, both measured FRFs and ``base.toml``.

    Returns
    -------
    dict
        ``{"logs": {"applied": {name: Path}, "computed": {...}}, "frf": {"applied": Path,
        "computed": Path}, "base": Path, "truth": {"applied": dict, "computed": dict}}``.
    """
    out = Path(out_dir)
    logs: dict = {"applied": {}, "computed": {}}
    for how in logs:
        (out / how).mkdir(parents=True, exist_ok=True)
    for name, run in simulate_all(seed).items():
        for how, cmd in (("applied", run.command_applied), ("computed", run.command_computed)):
            cols = {"time_s": run.time, "nut_angle_rad": run.angle_measured, "torque_command_n_m": cmd,
                    "axial_load_n": run.load_measured}
            if name == "frf_experiment":
                cols["torque_dither_n_m"] = run.dither if how == "computed" else np.concatenate(([0.0], run.dither[:-1]))
            path = out / how / f"{name}.csv"
            _axis.write_csv(path, cols, fmt="%.12g")
            logs[how][name] = path
    frfs = {}
    for how in ("applied", "computed"):
        f, _, hn = bode(how, seed)
        frfs[how] = out / f"bode_{how}.csv"
        _axis.write_csv(frfs[how], {"frequency_hz": f, "magnitude_db": 20.0 * np.log10(np.abs(hn)),
                                    "phase_deg": np.degrees(np.unwrap(np.angle(hn)))})
    base = out / "base.toml"
    base.write_text(BASE_PLANT)
    return {"logs": logs, "frf": frfs, "base": base,
            "truth": {"applied": truth("applied"), "computed": truth("computed")}}


if __name__ == "__main__":
    res = generate(sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 0)
    for k, v in res["truth"]["applied"].items():
        print(f"{k} = {v}")
