"""The judge's foreign generator: screw axes simulated with numpy only, for issue 32's acceptance.

Written without reading the toolkit's fitting code, its plant model or the other generators of
this folder; it imports nothing from ``prsa_ctrl``. It deliberately differs from the toolkit's
model structure where real axes do:

- **Mechanics.** Rigid axis (motor + screw inertia ``J_ms`` and the carriage mass ``m`` through the
  lead ``a = lead / 2 pi``) or **two-mass** axis (``J_ms`` and ``m`` joined by an axial spring
  ``k`` and damper ``c`` at the nut). Ball screw or roller screw (different numbers, same laws).
- **Nut loss on the whole force through the nut**: the motor sees ``a F_s + (1/eta - 1) a |F_s|
  sgn(w)``, ``F_s`` the force the nut transmits (spring + damper force of the two-mass axis; the
  external load plus the carriage's inertial force of the rigid one, solved exactly at every
  evaluation: the law is piecewise linear and monotone in the acceleration).
- **Friction on the motor side**: Coulomb + viscous + Stribeck standstill friction,
  ``(T_c + (T_s - T_c) exp(-(w/w_s)^2)) tanh(w/eps) + b w``, eps = 0.02 rad/s.
- **Drive**: first-order current loop ``T' = 2 pi f_c (u_act + n - T)`` (``n`` a process torque
  noise held over each sample); a discrete PI speed loop (conditional-integration anti-windup,
  torque limit) whose command computed at sample k acts over ``[t_{k+D}, t_{k+D+1})``, D = 1 or
  2 (computation delay, plus one sample of transport for D = 2).
- **Speed** from an encoder quantised to whole counts (floor) by backward difference, then a
  first-order filter (exact discretisation, time constant ``tau_f``).
- **Logs**: the command logged as **computed** (``u_k`` at row k: it acts D samples later) or as
  **applied** (the controller's output held over the sample, ``u_{k-1}`` at row k: it acts D - 1
  samples later); SI with the toolkit's default columns, or **non-SI** (time in ms, angle in
  degrees, torque in % of the rated torque, load in kN) with a log description.
- Integration: fixed-step RK4, ``N_SUB`` sub-steps per sample, a 0.3 s unlogged pre-roll.

Each case writes ``multisine.csv``, ``loadsteps.csv``, ``staircase.csv``, ``bode.csv`` (torque
command -> motor speed at the operating point of the multisine, the speed as the docs' "nut speed"
is measured: the backward difference of the angle; the linear part with the zero-order hold, ``D_log`` samples of delay, the current loop, 2 % magnitude and 0.02 rad phase
noise), a base plant file written as a user writes it from datasheets (nominal values: motor
inertia -10 %, efficiency off by 0.02, friction and current loop from the catalogue, no command
delay) and, for the non-SI case, ``log.toml``. :func:`generate` returns the truth (SI).

Truth definitions: ``reflected_inertia_kg_m2 = J_ms + m a^2`` (the total at the motor, without
the loss); ``delay_logged_to_action_samples = D_log`` (D computed, D - 1 applied) and
``drive.command_delay_samples = D - 1`` (the plant-file key: delay beyond the one-sample
computation delay); ``first_mode_hz``: the two-mass axis linearised at the FRF operating point
(forward speed, nut force > 0: the loss makes the load side ``1/eta`` heavier seen from the
motor), ``sqrt(k (a^2/(eta J_ms) + 1/m)) / 2 pi``; ``first_mode_lossless_hz`` without the loss.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

N_SUB = 8          # RK4 sub-steps per sample
EPS_W = 0.02       # rad/s, tanh smoothing of the friction's sign at standstill
PREROLL_S = 0.3    # unlogged settling before each log, s
DURATION_S = 1.2   # logged length of each experiment, s


@dataclass(frozen=True)
class Mech:
    """One screw axis (truth, SI)."""

    mechanism: str            # plant-file mechanism: "ball-screw" or "roller-screw"
    lead_m: float             # m of travel per revolution
    ts: float                 # speed-loop sample time, s
    j_motor: float            # rotor + coupling, kg m^2
    j_screw: float            # screw shaft about its axis, kg m^2
    mass: float               # carriage / rod / table, kg
    eta: float                # nut efficiency (forward)
    t_coulomb: float          # N m, motor-side drag
    t_static: float           # N m, breakaway level at standstill (Stribeck)
    w_stribeck: float         # rad/s
    viscous: float            # N m s/rad
    k_axial: float            # N/m (two-mass only)
    zeta: float               # modal damping ratio of the axial spring (two-mass only)
    f_current: float          # current-loop bandwidth, Hz
    torque_limit: float       # N m
    rated_torque: float       # N m (the % unit of the non-SI log)
    counts: int               # encoder counts per revolution
    tau_filter: float         # speed filter time constant, s
    kp: float                 # PI speed loop, N m s/rad
    ki: float                 # N m/rad
    torque_noise: float       # process torque noise, N m rms per sample
    load_noise: float         # load cell noise, N rms
    f_load_ms: float          # constant load of the multisine (and the FRF's operating point), N
    steps: tuple              # load-step levels, N

    @property
    def a(self):
        return self.lead_m / (2 * math.pi)

    @property
    def j_ms(self):
        return self.j_motor + self.j_screw


def _shaft_inertia(d_m, length_m, rho=7850.0):
    """Solid steel shaft about its axis, kg m^2."""
    return math.pi * rho * length_m * d_m ** 4 / 32.0


BALL = Mech(mechanism="ball-screw", lead_m=0.010, ts=1.25e-4, j_motor=1.6e-3,
            j_screw=_shaft_inertia(0.0292, 1.0), mass=300.0, eta=0.92, t_coulomb=0.40, t_static=0.60,
            w_stribeck=0.5, viscous=6e-4, k_axial=1.5e8, zeta=0.03, f_current=1100.0, torque_limit=20.0,
            rated_torque=6.5, counts=2 ** 20, tau_filter=2.0e-4, kp=0.65, ki=32.0, torque_noise=0.01,
            load_noise=5.0, f_load_ms=1000.0, steps=(0.0, 2000.0, 500.0, 2000.0))

ROLLER = Mech(mechanism="roller-screw", lead_m=0.005, ts=2.5e-4, j_motor=5.0e-4,
              j_screw=_shaft_inertia(0.029, 0.6), mass=400.0, eta=0.83, t_coulomb=0.20, t_static=0.32,
              w_stribeck=0.4, viscous=3e-4, k_axial=3.0e8, zeta=0.03, f_current=700.0, torque_limit=12.0,
              rated_torque=4.0, counts=2 ** 18, tau_filter=4.0e-4, kp=0.22, ki=11.0, torque_noise=0.006,
              load_noise=8.0, f_load_ms=2000.0, steps=(0.0, 4000.0, 1000.0, 4000.0))


@dataclass(frozen=True)
class Case:
    mech: Mech
    two_mass: bool
    delay: int         # D: samples from the controller's computation to the action (1 or 2)
    logged: str        # "computed" or "applied"
    units: str         # "si" or "nonsi"

    @property
    def delay_logged(self):
        return self.delay if self.logged == "computed" else self.delay - 1


CASES = {
    "ball-2mass-d1-computed-si": Case(BALL, True, 1, "computed", "si"),
    "ball-rigid-d2-applied-si": Case(BALL, False, 2, "applied", "si"),
    "ball-rigid-d1-computed-nonsi": Case(BALL, False, 1, "computed", "nonsi"),
    "roller-rigid-d1-applied-si": Case(ROLLER, False, 1, "applied", "si"),
    "roller-2mass-d2-computed-nonsi": Case(ROLLER, True, 2, "computed", "nonsi"),
    "roller-2mass-d1-applied-si": Case(ROLLER, True, 1, "applied", "si"),
}


# ------------------------------------------------------------------------------------------
# the axis


def _damper(m: Mech):
    """Axial damper, N s/m, for the modal damping ratio of the lossless two-mass mode."""
    jl = m.mass * m.a ** 2
    j_red = m.j_ms * jl / (m.j_ms + jl)           # reduced inertia of the torsional pair
    kt = m.k_axial * m.a ** 2
    ct = 2.0 * m.zeta * math.sqrt(kt * j_red)     # N m s/rad
    return ct / m.a ** 2


def _friction(m: Mech, w):
    s = math.tanh(w / EPS_W)
    g = math.exp(-(w / m.w_stribeck) ** 2)
    return (m.t_coulomb + (m.t_static - m.t_coulomb) * g) * s + m.viscous * w, s


def _rigid_accel(m: Mech, torque, w, f_ext):
    """dw/dt of the rigid axis: J_ms w' + a F_s + (1/eta - 1) a |F_s| s = T - T_f,
    F_s = f_ext + m a w' (exact: one of the two sign branches is consistent)."""
    tf, s = _friction(m, w)
    rhs = torque - tf
    loss = 1.0 / m.eta - 1.0
    for sigma in (1.0, -1.0):
        c = 1.0 + loss * sigma * s
        wd = (rhs - m.a * f_ext * c) / (m.j_ms + m.mass * m.a ** 2 * c)
        fs = f_ext + m.mass * m.a * wd
        if fs * sigma >= 0.0:
            return wd
    return -f_ext / (m.mass * m.a)    # the nut force is exactly zero


def _rhs(m: Mech, two_mass, c_ax, x, u, f_ext):
    """State derivative. Rigid x = [theta, w, T]; two-mass x = [theta, w, y, v, T] (y, v carriage)."""
    if not two_mass:
        theta, w, tq = x
        return np.array([w, _rigid_accel(m, tq, w, f_ext), 2 * math.pi * m.f_current * (u - tq)])
    theta, w, y, v, tq = x
    fs = m.k_axial * (m.a * theta - y) + c_ax * (m.a * w - v)
    tf, s = _friction(m, w)
    wd = (tq - tf - m.a * fs - (1.0 / m.eta - 1.0) * m.a * abs(fs) * s) / m.j_ms
    vd = (fs - f_ext) / m.mass
    return np.array([w, wd, v, vd, 2 * math.pi * m.f_current * (u - tq)])


def _steady_torque(m: Mech, w, f):
    tf, s = _friction(m, w)
    return tf + m.a * f * (1.0 + (1.0 / m.eta - 1.0) * (1.0 if f * s >= 0 else -1.0) * s)


def simulate(case: Case, ref, force, rng):
    """Closed-loop run. ``ref`` speed reference (rad/s) and ``force`` external axial load (N,
    opposing positive motion) per sample, pre-roll included. Returns per sample: true angle,
    measured (quantised) angle, computed command, applied command, filtered speed."""
    m, n = case.mech, ref.size
    ts, h = m.ts, m.ts / N_SUB
    c_ax = _damper(m)
    q = 2 * math.pi / m.counts
    alpha = 1.0 - math.exp(-ts / m.tau_filter)
    t0 = _steady_torque(m, ref[0], force[0]) if abs(ref[0]) > 0 else 0.0
    if case.two_mass:
        x = np.array([0.0, ref[0], -force[0] / m.k_axial, m.a * ref[0], t0])
    else:
        x = np.array([0.0, ref[0], t0])
    integ = t0
    theta_q_prev = math.floor(x[0] / q) * q
    wf = ref[0]
    pending = [t0] * case.delay     # commands computed, not yet acting
    noise = rng.normal(0.0, m.torque_noise, n)
    out_theta = np.empty(n)
    out_q = np.empty(n)
    out_uc = np.empty(n)
    out_wf = np.empty(n)
    for k in range(n):
        theta_q = math.floor(x[0] / q) * q
        raw = (theta_q - theta_q_prev) / ts
        theta_q_prev = theta_q
        wf += alpha * (raw - wf)
        e = ref[k] - wf
        u_free = m.kp * e + integ
        u = min(max(u_free, -m.torque_limit), m.torque_limit)
        if u == u_free or (u_free > u and e < 0) or (u_free < u and e > 0):
            integ += ts * m.ki * e
        out_theta[k], out_q[k], out_uc[k], out_wf[k] = x[0], theta_q, u, wf
        pending.append(u)
        u_act = pending.pop(0) + noise[k]
        f = force[k]
        for _ in range(N_SUB):
            k1 = _rhs(m, case.two_mass, c_ax, x, u_act, f)
            k2 = _rhs(m, case.two_mass, c_ax, x + 0.5 * h * k1, u_act, f)
            k3 = _rhs(m, case.two_mass, c_ax, x + 0.5 * h * k2, u_act, f)
            k4 = _rhs(m, case.two_mass, c_ax, x + h * k3, u_act, f)
            x = x + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
    out_ua = np.concatenate([[out_uc[0]], out_uc[:-1]])   # held over the sample: u_{k-1} at row k
    return out_theta, out_q, out_uc, out_ua, out_wf


# ------------------------------------------------------------------------------------------
# experiments


def _ramp_to(levels, hold_n, ts, accel):
    """Piecewise-constant speed levels joined by ramps of ``accel`` rad/s^2 (each level held
    ``hold_n`` samples from the start of its ramp)."""
    r = np.empty(len(levels) * hold_n)
    cur = 0.0
    for i, lev in enumerate(levels):
        for j in range(hold_n):
            step = accel * ts
            cur = min(cur + step, lev) if lev > cur else max(cur - step, lev)
            r[i * hold_n + j] = cur
    return r


def experiments(case: Case, rng):
    """{name: (ref, force)} for the logged part; the pre-roll is prepended by :func:`run`."""
    m = case.mech
    n = int(round(DURATION_S / m.ts))
    t = np.arange(n) * m.ts
    # multisine: 20 lines 1..150 Hz on the 1.2 s grid, Schroeder phases, +-20 rad/s peak around 30
    lines = np.unique(np.round(np.geomspace(1.0, 150.0, 20) * DURATION_S)) / DURATION_S
    ph = -np.pi * np.arange(1, lines.size + 1) ** 2 / lines.size
    ms = np.sum(np.sin(2 * np.pi * lines[:, None] * t[None, :] + ph[:, None]), axis=0)
    ms = 30.0 + 20.0 * ms / np.max(np.abs(ms))
    out = {"multisine": (ms, np.full(n, m.f_load_ms))}
    q = n // 4
    f_steps = np.concatenate([np.full(q, m.steps[0]), np.full(q, m.steps[1]), np.full(q, m.steps[2]),
                              np.full(n - 3 * q, m.steps[3])])
    out["loadsteps"] = (np.full(n, 30.0), f_steps)
    hold = n // 6
    stair = _ramp_to([20.0, 45.0, 30.0, -20.0, -45.0, -30.0], hold, m.ts, 2000.0)
    stair = np.concatenate([stair, np.full(n - stair.size, stair[-1])])
    out["staircase"] = (stair, np.zeros(n))
    return out


def run(case: Case, name, seed):
    """Simulate one experiment: dict of SI arrays (logged part only)."""
    rng = np.random.default_rng([seed, list(CASES.values()).index(case), list(EXPERIMENTS).index(name)])
    ref, force = experiments(case, rng)[name]
    npre = int(round(PREROLL_S / case.mech.ts))
    if name == "staircase":
        pre_r, pre_f = np.zeros(npre), np.zeros(npre)
    else:
        pre_r, pre_f = np.full(npre, ref[0]), np.full(npre, force[0])
    theta, theta_q, uc, ua, wf = simulate(case, np.concatenate([pre_r, ref]), np.concatenate([pre_f, force]), rng)
    sl = slice(npre, None)
    load = force + rng.normal(0.0, case.mech.load_noise, force.size)
    t = np.arange(ref.size) * case.mech.ts
    return {"time_s": t, "angle_rad": theta_q[sl] - theta_q[npre], "true_angle_rad": theta[sl],
            "computed_n_m": uc[sl], "applied_n_m": ua[sl], "speed_filtered_rad_s": wf[sl], "load_n": load,
            "ref_rad_s": ref, "force_n": force}


# ------------------------------------------------------------------------------------------
# frequency response (the linear part at the operating point)


def frf(case: Case, f_hz, delay_logged=None):
    """Torque command (as logged) -> motor speed as the backward difference of the angle, rad/s per
    N m, at forward speed with the multisine's load (nut force > 0: the loss multiplies the nut
    force by 1/eta)."""
    m = case.mech
    d = case.delay_logged if delay_logged is None else delay_logged
    s = 2j * np.pi * np.asarray(f_hz, float)
    if case.two_mass:
        z = (m.k_axial + _damper(m) * s) / s           # N/m per (m/s): spring + damper impedance
        load = (m.a ** 2 / m.eta) * m.mass * s * z / (m.mass * s + z)
        mech = 1.0 / (m.j_ms * s + m.viscous + load)
    else:
        mech = 1.0 / ((m.j_ms + m.mass * m.a ** 2 / m.eta) * s + m.viscous)
    wc = 2 * np.pi * m.f_current
    # the zero-order hold of the command, and the speed as the docs' "nut speed" is measured:
    # the one-sample (backward) difference of the encoder angle, the mean speed over the last
    # sample -- the same factor (1 - exp(-s Ts)) / (s Ts) (no filter, no quantisation)
    zoh = (1.0 - np.exp(-s * m.ts)) / (s * m.ts)
    return mech * wc / (s + wc) * np.exp(-s * d * m.ts) * zoh * zoh


def frf_band(case: Case):
    fmax = {"ball-screw": 1500.0, "roller-screw": 1000.0}[case.mech.mechanism]
    return np.geomspace(5.0, fmax, 220)


# ------------------------------------------------------------------------------------------
# truth and files


def truth(case: Case):
    m = case.mech
    t = {
        "mechanism": m.mechanism,
        "two_mass": case.two_mass,
        "reflected_inertia_kg_m2": m.j_ms + m.mass * m.a ** 2,
        "frf_low_frequency_inertia_kg_m2": m.j_ms + m.mass * m.a ** 2 / m.eta,
        "axis.motor_inertia_kg_m2": m.j_motor,
        "screw_inertia_kg_m2": m.j_screw,
        "axis.moving_mass_kg": m.mass,
        "screw.lead_mm": m.lead_m * 1e3,
        "friction.efficiency": m.eta,
        "drive.current_loop_bandwidth_hz": m.f_current,
        "delay_samples_total": case.delay,
        "delay_logged_to_action_samples": case.delay_logged,
        "drive.command_delay_samples": case.delay - 1,
        "command_logged": case.logged,
        "units": case.units,
        "sensor.sample_time_s": m.ts,
        "rated_torque_n_m": m.rated_torque,
        "frf_speed_rad_s": 30.0,
        "frf_load_n": m.f_load_ms,
        "speed_loop": {"kp": m.kp, "ki": m.ki, "tau_filter_s": m.tau_filter},
        # for a judge of diagnoses: every resonance and anti-resonance of the axis (none when rigid),
        # no position-periodic torque, and the units and coordinates given to prsa-fit are the logs' own
        "modes_hz": (),
        "anti_resonances_hz": (),
        "periodic_orders_per_rev": (),
        "units_right": True,
        "coordinates_right": True,
    }
    if case.two_mass:
        t["axial_stiffness_n_per_m"] = m.k_axial
        t["first_mode_hz"] = math.sqrt(m.k_axial * (m.a ** 2 / (m.eta * m.j_ms) + 1.0 / m.mass)) / (2 * math.pi)
        t["first_mode_lossless_hz"] = math.sqrt(m.k_axial * (m.a ** 2 / m.j_ms + 1.0 / m.mass)) / (2 * math.pi)
        t["anti_resonance_hz"] = math.sqrt(m.k_axial / m.mass) / (2 * math.pi)
        t["modes_hz"] = (t["first_mode_hz"], t["first_mode_lossless_hz"])
        t["anti_resonances_hz"] = (t["anti_resonance_hz"],)
    return t


def base_plant_text(case: Case):
    """The plant file a user writes from datasheets: nominal values, each with its source."""
    m = case.mech
    if m.mechanism == "ball-screw":
        geometry = f"""[screw]
pitch_diameter_mm = {{ value = 32.0, source = "catalogue: 32 x 10 ball screw" }}
lead_mm = {{ value = 10.0, source = "catalogue: 32 x 10 ball screw" }}
root_diameter_mm = {{ value = 27.0, source = "catalogue: root diameter of the 32 x 10 screw" }}
rated_load_n = {{ value = 6000.0, source = "assumption: continuous thrust of the axis" }}
"""
        mounting = "fixed-fixed"
        span, stroke, nut_k, brg_k = 1000.0, 500.0, 650.0, 900.0
        fc_base = 1500.0
        mass_src = "datasheet: table + fixture"
    else:
        geometry = f"""[screw]
pitch_diameter_mm = {{ value = 30.0, source = "catalogue: 30 x 5 planetary roller screw" }}
lead_mm = {{ value = 5.0, source = "catalogue: 30 x 5 planetary roller screw" }}
starts = {{ value = 5, source = "catalogue: 5 starts of 1 mm pitch" }}
root_diameter_mm = {{ value = 28.0, source = "catalogue: root diameter" }}
rated_load_n = {{ value = 9000.0, source = "assumption: continuous thrust of the actuator" }}

[roller]
pitch_diameter_mm = {{ value = 10.0, source = "catalogue: roller pitch diameter" }}
count = {{ value = 10, source = "catalogue: 10 rollers" }}
"""
        mounting = "fixed-free"
        span, stroke, nut_k, brg_k = 600.0, 300.0, 1100.0, 900.0
        fc_base = 1000.0
        mass_src = "datasheet: rod + tooling + press head"
    eta_base = round(m.eta - 0.02, 4) if m.mechanism == "ball-screw" else round(m.eta + 0.02, 4)
    return f"""# Base plant written from datasheets for the judge's foreign generator (nominal values, not the truth)
name = "judge-{m.mechanism}"
description = "judge's foreign {m.mechanism} axis (datasheet values)"
mechanism = "{m.mechanism}"
mounting = {{ value = "{mounting}", source = "datasheet: bearing arrangement" }}

{geometry}
[axis]
motor_inertia_kg_m2 = {{ value = {0.9 * m.j_motor:.6g}, source = "catalogue: rotor + coupling (nominal)" }}
moving_mass_kg = {{ value = {round(1.05 * m.mass, 1)}, source = "{mass_src}" }}
bearing_span_mm = {{ value = {span}, source = "drawing" }}
stroke_position_mm = {{ value = {stroke}, source = "assumption: mid-stroke" }}
nut_stiffness_n_per_um = {{ value = {nut_k}, source = "catalogue: preloaded nut" }}
bearing_stiffness_n_per_um = {{ value = {brg_k}, source = "catalogue: support bearings" }}

[friction]
efficiency = {{ value = {eta_base}, source = "catalogue: nut efficiency" }}
no_load_torque_n_m = {{ value = {round(0.75 * m.t_coulomb, 3)}, source = "catalogue: preload drag" }}
viscous_n_m_s_per_rad = {{ value = {1.5 * m.viscous:.3g}, source = "assumption" }}

[drive]
torque_limit_n_m = {{ value = {m.torque_limit}, source = "datasheet: peak torque" }}
current_loop_bandwidth_hz = {{ value = {fc_base}, source = "datasheet: current loop" }}

[sensor]
sample_time_s = {{ value = {m.ts}, source = "drive setting: speed-loop period" }}
encoder_counts_per_rev = {{ value = {m.counts}, source = "datasheet: encoder" }}
"""


LOG_FORMAT_NONSI = """# Log description of the judge's non-SI logs: ms, deg, % of the rated torque, kN
description = "judge's foreign axis, drive trace in drive units"
format = "csv"
axis = "rotary"

[time]
name = "t_ms"
unit = "ms"

[position]
name = "motor_pos_deg"
unit = "deg"

# The torque is in % of the rated torque. A rotary description takes N m, A or V (unit = "%" is
# refused in one line: expected one of N m, A, V), so the percent is declared as a drive unit
# with its gain: {gain} N m per % (the rated torque / 100).
[command]
name = "torque_pct_rated"
unit = "V"
gain = {gain}
logged = "{logged}"

[load]
name = "load_kN"
unit = "kN"
"""


def _write_csv(path, header, cols):
    data = np.column_stack(cols)
    np.savetxt(path, data, delimiter=",", header=",".join(header), comments="", fmt="%.10g")


def write_log(case: Case, log, path):
    u = log["computed_n_m"] if case.logged == "computed" else log["applied_n_m"]
    if case.units == "si":
        _write_csv(path, ["time_s", "nut_angle_rad", "torque_command_n_m", "axial_load_n"],
                   [log["time_s"], log["angle_rad"], u, log["load_n"]])
    else:
        _write_csv(path, ["t_ms", "motor_pos_deg", "torque_pct_rated", "load_kN"],
                   [log["time_s"] * 1e3, np.degrees(log["angle_rad"]), 100.0 * u / case.mech.rated_torque,
                    log["load_n"] / 1e3])


def write_bode(case: Case, path, rng):
    f = frf_band(case)
    h = frf(case, f)
    mag = np.abs(h) * (1.0 + 0.02 * rng.standard_normal(f.size))
    ph = np.unwrap(np.angle(h)) + 0.02 * rng.standard_normal(f.size)
    _write_csv(path, ["frequency_hz", "magnitude_db", "phase_deg"], [f, 20 * np.log10(mag), np.degrees(ph)])


EXPERIMENTS = ("multisine", "loadsteps", "staircase")


def generate(folder, name, seed=0, experiments=EXPERIMENTS):
    """Write one case's logs (``experiments``, default all three), FRF, base plant (and log
    description) into ``folder``.

    Returns {"truth", "logs": {experiment: path}, "frf": path, "base": path, "log_format": path or None}.
    """
    case = CASES[name]
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    logs = {}
    for exp in experiments:
        log = run(case, exp, seed)
        logs[exp] = folder / f"{exp}.csv"
        write_log(case, log, logs[exp])
    bode = folder / "bode.csv"
    write_bode(case, bode, np.random.default_rng([seed, 99, list(CASES).index(name)]))
    base = folder / "base.toml"
    base.write_text(base_plant_text(case))
    fmt = None
    if case.units == "nonsi":
        fmt = folder / "log.toml"
        fmt.write_text(LOG_FORMAT_NONSI.format(gain=case.mech.rated_torque / 100.0,
                                               logged="as-computed" if case.logged == "computed" else "as-applied"))
    return {"truth": truth(case), "logs": logs, "frf": bode, "base": base, "log_format": fmt}


if __name__ == "__main__":   # python gen_judge.py OUTDIR [seed]: every case into OUTDIR/<case>/
    import json
    import sys

    out = Path(sys.argv[1])
    sd = int(sys.argv[2]) if len(sys.argv) > 2 else 0
    for nm in CASES:
        res = generate(out / nm, nm, sd)
        (out / nm / "truth.json").write_text(json.dumps(res["truth"], indent=1))
        print(nm, "written")
