"""Third foreign generator: screw axes with three bodies, a stroke-dependent axial spring and cogging.

Written for issue 32 (part 6) without reading the toolkit's fitting or plant-model code, and
importing nothing from ``prsa_ctrl`` (numpy only). It differs from the toolkit's two-mass model
on purpose:

(a) the axial stiffness depends on where the nut is on a screw held axially at the motor end,
    ``k(x) = 1 / (1/k_nut + 1/k_bearing + x / (E A_root))`` (x: nut to fixed bearing, m;
    THK/HIWIN "axial rigidity of the screw shaft" for a fixed-free mounting, the nut and the
    support bearing in series), so the first axial mode moves as the carriage travels;
(b) a torsional coupling (bellows or jaw) between the motor and the screw: three bodies (rotor,
    screw, carriage) and a second, higher mode;
(c) motor torque ripple periodic in the motor angle (cogging: a fraction of the rated torque at
    6 and 12 per revolution);
(d) the nut's thread loss on the whole transmitted force (the spring force through the nut, the
    carriage's inertial force included) with the power-screw law of a textbook (Shigley, Mechanical
    Engineering Design, ch. 8: driving ``T = a F / eta_f``, ``eta_f = tan(lam) / tan(lam + rho)``;
    back-driven ``T = a F eta_b``, ``eta_b = tan(lam - rho) / tan(lam)``, rho = atan(mu)), and
    Coulomb + viscous + Stribeck friction on the motor side (bearings, seals, preload drag);
(e) a discrete PI speed loop with a torque limit (conditional integration), the computation delay
    plus ``delay_samples`` of transport, a first-order current loop, an encoder quantised to whole
    counts and the speed a filtered backward difference of the counts.

Integration: fixed-step RK4 with ``substeps`` sub-steps per controller sample, the command held
over the sample (the current loop is a state of the ODE).

Time convention. The controller computes ``u[k]`` at ``t_k`` from the angle sampled at ``t_k``;
``u[k]`` reaches the current loop over ``[t_(k+1+n), t_(k+2+n))``, n = ``delay_samples``. A log
"computed" holds ``u[k]`` in row k (it acts ``n + 1`` samples after it is logged), a log "applied"
holds ``u[k-1]`` in row k, the controller's output held over that sample (it acts ``n`` samples
after it is logged). Either way the toolkit's ``drive.command_delay_samples`` of the truth is n.

Sign convention: the axial load (``axial_load_n``) is positive when it resists positive motion;
the load-step torque balance is then ``T = T_f(w) + a F / eta_f`` for F > 0, w > 0.

Public: ``CASES``, ``EXPERIMENTS``, ``generate(out_dir, name, seed)``, ``truth(name)``,
``simulate(...)``, ``steady_command(...)``, ``mode_formula_hz(...)``, ``linearised_modes_hz(...)``,
``stiffness(...)``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

TWO_PI = 2.0 * math.pi
RHO_STEEL_KG_M3 = 7850.0  # textbook density of steel
E_STEEL_PA = 206e9  # THK/HIWIN rigidity formulas: E = 2.06e5 N/mm^2
W_EPS_MOTOR = 0.02  # rad/s, tanh smoothing of the motor-side Coulomb/Stribeck sign
W_EPS_NUT = 0.05  # rad/s, tanh smoothing of the nut's driving/back-driven switch in speed
F_EPS_NUT = 20.0  # N, the same in the nut force
EXPERIMENTS = ("multisine", "loadsteps", "staircase")


@dataclass(frozen=True)
class Case:
    """One axis. SI throughout; every number's source in ``SOURCES``."""

    name: str
    mechanism: str  # "ball-screw" | "roller-screw"
    lead_m: float
    d_nominal_m: float
    d_root_m: float
    span_m: float
    j_rotor: float  # kg m^2, motor rotor
    j_hub_motor: float  # kg m^2, coupling hub on the motor shaft
    j_hub_screw: float  # kg m^2, coupling hub on the screw
    k_coupling: float  # N m/rad
    zeta_coupling: float
    mass_kg: float
    k_nut: float  # N/m
    k_bearing: float  # N/m
    zeta_axial: float
    mu_thread: float
    t_coulomb: float  # N m, motor-side Coulomb level
    t_static: float  # N m, motor-side breakaway
    w_stribeck: float  # rad/s
    b_viscous: float  # N m s/rad
    torque_limit: float  # N m
    rated_torque: float  # N m
    cog6: float  # fraction of rated torque at 6 per rev
    cog12: float  # at 12 per rev
    ts: float  # s
    current_bw_hz: float
    delay_samples: int
    command_logged: str  # "computed" | "applied"
    counts_per_rev: int
    speed_filter_s: float
    kp: float  # N m s/rad
    ki: float  # N m/rad
    torque_noise: float  # N m RMS per sample (process)
    load_noise_n: float  # N RMS (load cell)
    frf_speed: float  # rad/s
    frf_load: float  # N
    frf_position_m: float  # nut position at the FRF's midpoint (m from the fixed bearing)
    non_si: bool
    substeps: int

    # -- derived -----------------------------------------------------------------------------
    @property
    def a(self):
        """Lead per radian, m/rad."""
        return self.lead_m / TWO_PI

    @property
    def j_screw(self):
        """Screw shaft inertia (solid cylinder of the nominal diameter over the span) + its hub."""
        return math.pi * RHO_STEEL_KG_M3 * self.d_nominal_m ** 4 * self.span_m / 32.0 + self.j_hub_screw

    @property
    def j_motor(self):
        return self.j_rotor + self.j_hub_motor

    @property
    def ea(self):
        return E_STEEL_PA * math.pi * self.d_root_m ** 2 / 4.0

    @property
    def lead_angle(self):
        return math.atan(self.lead_m / (math.pi * self.d_nominal_m))

    @property
    def eta_f(self):
        rho = math.atan(self.mu_thread)
        return math.tan(self.lead_angle) / math.tan(self.lead_angle + rho)

    @property
    def eta_b(self):
        rho = math.atan(self.mu_thread)
        return math.tan(self.lead_angle - rho) / math.tan(self.lead_angle)

    @property
    def j_total(self):
        """Total inertia at the motor, kg m^2: rotor + hubs + screw + m a^2."""
        return self.j_motor + self.j_screw + self.mass_kg * self.a ** 2

    @property
    def c_coupling(self):
        """Coupling damper, N m s/rad: zeta of the rotor against the screw alone."""
        jr = self.j_motor * self.j_screw / (self.j_motor + self.j_screw)
        return 2.0 * self.zeta_coupling * math.sqrt(self.k_coupling * jr)

    @property
    def c_axial(self):
        """Axial damper, N s/m: zeta of the carriage on the spring at the FRF's position."""
        return 2.0 * self.zeta_axial * math.sqrt(stiffness(self, self.frf_position_m) * self.mass_kg)


def stiffness(case: Case, x_m: float) -> float:
    """Axial stiffness, N/m, with the nut ``x_m`` from the fixed bearing: nut, bearing and the
    screw length x in series (fixed-free, the THK/HIWIN shaft rigidity ``E A / x``)."""
    x = max(float(x_m), 1e-3)
    return 1.0 / (1.0 / case.k_nut + 1.0 / case.k_bearing + x / case.ea)


CASES = {
    "ball-40x16": Case(
        name="ball-40x16", mechanism="ball-screw", lead_m=0.016, d_nominal_m=0.040, d_root_m=0.0340,
        span_m=1.4, j_rotor=3.3e-3, j_hub_motor=1.0e-4, j_hub_screw=1.0e-4, k_coupling=5.5e4,
        zeta_coupling=0.04, mass_kg=420.0, k_nut=900e6, k_bearing=1100e6, zeta_axial=0.025,
        mu_thread=0.008, t_coulomb=0.35, t_static=0.55, w_stribeck=0.8, b_viscous=1.2e-3,
        torque_limit=35.0, rated_torque=12.0, cog6=0.02, cog12=0.01, ts=2.5e-4, current_bw_hz=800.0,
        delay_samples=1, command_logged="computed", counts_per_rev=2 ** 20, speed_filter_s=2.5e-4,
        kp=1.4, ki=50.0, torque_noise=0.02, load_noise_n=5.0, frf_speed=12.0, frf_load=1500.0,
        frf_position_m=0.80, non_si=False, substeps=8),
    "roller-39x10": Case(
        name="roller-39x10", mechanism="roller-screw", lead_m=0.010, d_nominal_m=0.039, d_root_m=0.0365,
        span_m=0.8, j_rotor=1.5e-3, j_hub_motor=6.0e-5, j_hub_screw=6.0e-5, k_coupling=1.5e4,
        zeta_coupling=0.08, mass_kg=500.0, k_nut=2000e6, k_bearing=1300e6, zeta_axial=0.03,
        mu_thread=0.012, t_coulomb=0.25, t_static=0.40, w_stribeck=0.6, b_viscous=8.0e-4,
        torque_limit=22.0, rated_torque=9.0, cog6=0.02, cog12=0.01, ts=2.0e-4, current_bw_hz=1000.0,
        delay_samples=2, command_logged="applied", counts_per_rev=2 ** 17, speed_filter_s=3.0e-4,
        kp=0.6, ki=25.0, torque_noise=0.015, load_noise_n=8.0, frf_speed=10.0, frf_load=4000.0,
        frf_position_m=0.60, non_si=True, substeps=6),
}

SOURCES = {
    "ball-40x16": {
        "lead_m, d_nominal_m": "catalogue size class 40 x 16 (THK BIF / HIWIN FSI 40-16 designations)",
        "d_root_m": "textbook: root ~ nominal diameter minus the ball (6.35 mm) plus groove clearance",
        "span_m": "assumption: 1.2 m stroke plus nut and bearing housing",
        "j_rotor": "catalogue class: AC servo motor of ~35 N m peak, rotor 2.5e-3..4.5e-3 kg m^2",
        "j_hub_motor, j_hub_screw": "catalogue class: bellows coupling of 60 N m, 2e-4 kg m^2 both hubs",
        "k_coupling": "catalogue class: metal bellows coupling of 60 N m, 4e4..8e4 N m/rad",
        "zeta_coupling": "assumption: metal bellows, 4 % modal damping",
        "mass_kg": "assumption: table with fixture and workpiece",
        "k_nut": "catalogue class: preloaded 40 mm double nut, 700..1100 N/um at 10 % preload",
        "k_bearing": "catalogue class: 60 deg angular-contact support-bearing pair, 25..35 mm bore",
        "zeta_axial": "assumption: 2.5 % modal damping of the axial mode (feed-drive literature 1..5 %)",
        "mu_thread": "textbook: rolling friction coefficient of a ball nut 0.003..0.01 (eta_f ~0.94)",
        "motor friction": "assumption: preload drag 0.35 N m (catalogue 0.2..0.5 at 40 mm) + seals, breakaway +60 %",
        "torque_limit, rated_torque": "catalogue class: servo motor 12 N m rated, 35 N m peak",
        "cogging": "assumption: 2 % and 1 % of rated torque at 6 and 12 per rev (PM motor cogging class)",
        "ts, current_bw_hz, delay": "assumption: 4 kHz speed loop, 800 Hz current loop, one fieldbus sample",
        "counts_per_rev": "assumption: 20-bit motor encoder",
    },
    "roller-39x10": {
        "lead_m, d_nominal_m": "catalogue size class 39 x 10 planetary roller screw (SKF SR/Rollvis RV 39x10)",
        "d_root_m": "textbook: shallow roller thread, root ~ nominal minus 1.2 x the 2 mm pitch",
        "span_m": "assumption: 0.6 m stroke plus nut and housing",
        "j_rotor": "catalogue class: AC servo motor of ~22 N m peak, rotor 1.0e-3..2.0e-3 kg m^2",
        "j_hub_motor, j_hub_screw": "catalogue class: jaw coupling (elastomer spider), 1.2e-4 kg m^2 both hubs",
        "k_coupling": "catalogue class: jaw coupling with a 98 Sh A spider, 1e4..2e4 N m/rad",
        "zeta_coupling": "assumption: elastomer spider, 8 % modal damping",
        "mass_kg": "assumption: press ram with tooling",
        "k_nut": "catalogue class: preloaded roller nut of 39 mm, ~2x a ball nut's rigidity",
        "k_bearing": "catalogue class: angular-contact thrust bearing pair at the motor end",
        "zeta_axial": "assumption: 3 % modal damping of the axial mode",
        "mu_thread": "textbook: planetary roller screw friction coefficient ~0.01..0.02 (eta_f ~0.87)",
        "motor friction": "assumption: roller nut preload and seal drag 0.25 N m, breakaway +60 %",
        "torque_limit, rated_torque": "catalogue class: servo motor 9 N m rated, 22 N m peak",
        "cogging": "assumption: 2 % and 1 % of rated torque at 6 and 12 per rev",
        "ts, current_bw_hz, delay": "assumption: 5 kHz speed loop, 1 kHz current loop, two fieldbus samples",
        "counts_per_rev": "assumption: 17-bit resolver-class encoder",
    },
}


# -- the continuous dynamics -----------------------------------------------------------------------

def _rhs(c: Case, cst, y, cmd, f_ext, tnoise):
    """State derivative. y = (th_m, w_m, th_s, w_s, q, v, tau); ``cst`` the case constants."""
    th_m, w_m, th_s, w_s, q, v, tau = y
    (a, jm, js, m, kc, cc, cax, kn_inv, ea, eta_f, eta_b, tc, tst, wst, bv, tr6, tr12, wc, off) = cst
    k = 1.0 / (kn_inv + max(q, 1e-3) / ea)
    delta = a * th_s + off - q
    fs = k * delta + cax * (a * w_s - v)
    wgt = 0.5 * (1.0 + math.tanh(w_s / W_EPS_NUT) * math.tanh(fs / F_EPS_NUT))
    t_nut = a * fs * (wgt / eta_f + (1.0 - wgt) * eta_b)
    t_cpl = kc * (th_m - th_s) + cc * (w_m - w_s)
    t_fric = (tc + (tst - tc) * math.exp(-(w_m / wst) ** 2)) * math.tanh(w_m / W_EPS_MOTOR) + bv * w_m
    t_cog = tr6 * math.sin(6.0 * th_m + 0.7) + tr12 * math.sin(12.0 * th_m + 2.1)
    return (w_m, (tau + t_cog + tnoise - t_fric - t_cpl) / jm, w_s, (t_cpl - t_nut) / js, v,
            (fs - f_ext) / m, wc * (cmd - tau))


def _constants(c: Case, off: float):
    return (c.a, c.j_motor, c.j_screw, c.mass_kg, c.k_coupling, c.c_coupling, c.c_axial,
            1.0 / c.k_nut + 1.0 / c.k_bearing, c.ea, c.eta_f, c.eta_b, c.t_coulomb, c.t_static,
            c.w_stribeck, c.b_viscous, c.cog6 * c.rated_torque, c.cog12 * c.rated_torque,
            TWO_PI * c.current_bw_hz, off)


def motor_friction(c: Case, w: float) -> float:
    return (c.t_coulomb + (c.t_static - c.t_coulomb) * math.exp(-(w / c.w_stribeck) ** 2)) * math.tanh(
        w / W_EPS_MOTOR) + c.b_viscous * w


def steady_command(c: Case, w: float, f_load: float) -> float:
    """Mean motor torque, N m, at constant speed w (rad/s) against the load f_load (N), cogging
    averaged out: the motor friction plus the nut torque of the power-screw law."""
    wgt = 0.5 * (1.0 + math.tanh(w / W_EPS_NUT) * math.tanh(f_load / F_EPS_NUT))
    return motor_friction(c, w) + c.a * f_load * (wgt / c.eta_f + (1.0 - wgt) * c.eta_b)


def _steady_state(c: Case, w: float, f_load: float, q: float):
    """A quasi-static initial state at speed w, load f_load, nut position q: (y, off)."""
    t_nut = steady_command(c, w, f_load) - motor_friction(c, w)
    k = stiffness(c, q)
    delta = f_load / k
    th_s = 0.0
    th_m = th_s + t_nut / c.k_coupling
    off = q + delta - c.a * th_s
    tau = steady_command(c, w, f_load)
    return [th_m, w, th_s, w, q, c.a * w, tau], off


# -- the closed loop -------------------------------------------------------------------------------

def simulate(c: Case, w_ref, f_load, dither, *, q0: float, rng, n_pre: int = 0):
    """Closed-loop run of ``len(w_ref)`` samples (after ``n_pre`` unlogged samples at the first
    reference and load). Returns a dict of per-sample arrays: ``angle`` (quantised, rad),
    ``u`` (computed command, N m), ``logged`` (the command as the case logs it), ``load``
    (load cell, N), ``q`` (nut position, m), ``w_true`` (rad/s), ``tau`` (motor torque, N m)."""
    w_ref = np.concatenate([np.full(n_pre, w_ref[0]), np.asarray(w_ref, float)])
    f_load = np.concatenate([np.full(n_pre, f_load[0]), np.asarray(f_load, float)])
    dither = np.concatenate([np.zeros(n_pre), np.asarray(dither, float)])
    n = len(w_ref)
    y, off = _steady_state(c, float(w_ref[0]), float(f_load[0]), q0)
    cst = _constants(c, off)
    ts, h = c.ts, c.ts / c.substeps
    cpr = c.counts_per_rev
    noise = rng.normal(0.0, c.torque_noise, n)
    lnoise = rng.normal(0.0, c.load_noise_n, n)
    nd = c.delay_samples + 1
    u0 = y[6]
    pipe = [u0] * nd  # u[k-1-n] .. u[k-1]
    integ = u0 - 0.0  # at the steady state the error is zero: the integrator holds the torque
    counts_prev = math.floor(y[0] * cpr / TWO_PI)
    w_f = float(w_ref[0])
    angle = np.empty(n)
    u_out = np.empty(n)
    q_out = np.empty(n)
    w_out = np.empty(n)
    tau_out = np.empty(n)
    for k in range(n):
        counts = math.floor(y[0] * cpr / TWO_PI)
        th_q = counts * TWO_PI / cpr
        raw = (counts - counts_prev) * TWO_PI / cpr / ts
        counts_prev = counts
        w_f += ts / (c.speed_filter_s + ts) * (raw - w_f)
        e = w_ref[k] - w_f
        u_pi = c.kp * e + integ
        u = u_pi + dither[k]
        if abs(u) < c.torque_limit:
            integ += ts * c.ki * e  # conditional integration (anti-windup)
        u = min(max(u, -c.torque_limit), c.torque_limit)
        angle[k], u_out[k], q_out[k], w_out[k], tau_out[k] = th_q, u, y[4], y[1], y[6]
        cmd = pipe.pop(0)  # u[k-1-n], held over [t_k, t_k+1)
        pipe.append(u)
        fe, tn = float(f_load[k]), float(noise[k])
        for _ in range(c.substeps):
            k1 = _rhs(c, cst, y, cmd, fe, tn)
            y2 = [yi + 0.5 * h * di for yi, di in zip(y, k1)]
            k2 = _rhs(c, cst, y2, cmd, fe, tn)
            y3 = [yi + 0.5 * h * di for yi, di in zip(y, k2)]
            k3 = _rhs(c, cst, y3, cmd, fe, tn)
            y4 = [yi + h * di for yi, di in zip(y, k3)]
            k4 = _rhs(c, cst, y4, cmd, fe, tn)
            y = [yi + h / 6.0 * (d1 + 2.0 * d2 + 2.0 * d3 + d4) for yi, d1, d2, d3, d4 in zip(y, k1, k2, k3, k4)]
        if not all(map(math.isfinite, y)):
            raise FloatingPointError(f"{c.name}: the simulation diverged at sample {k}")
    s = slice(n_pre, n)
    u_k = u_out[s]
    logged = u_k if c.command_logged == "computed" else np.concatenate([u_out[n_pre - 1:n_pre] if n_pre else u_k[:1], u_k[:-1]])
    return {"angle": angle[s] - angle[n_pre], "u": u_k, "logged": logged,
            "load": f_load[s] + lnoise[s], "load_true": f_load[s], "q": q_out[s], "w_true": w_out[s],
            "tau": tau_out[s], "w_ref": w_ref[s], "dither": dither[s]}


# -- experiments -----------------------------------------------------------------------------------

def _ramp_steps(t, times, levels, ramp_s):
    """Piecewise-constant levels switching at ``times`` with linear ramps of ``ramp_s``."""
    out = np.full_like(t, levels[0], dtype=float)
    for t0, (l0, l1) in zip(times, zip(levels[:-1], levels[1:])):
        out += (l1 - l0) * np.clip((t - t0) / ramp_s, 0.0, 1.0)
    return out


def _multisine(t, f_lo, f_hi, n_lines, rms, rng_phase):
    """Random-phase multisine on log-spaced lines (0.1 Hz grid), scaled to ``rms``."""
    f = np.unique(np.round(np.geomspace(f_lo, f_hi, n_lines), 1))
    ph = rng_phase.uniform(0.0, TWO_PI, len(f))
    x = np.sin(TWO_PI * f[:, None] * t[None, :] + ph[:, None]).sum(axis=0)
    return x * rms / np.sqrt(np.mean(x ** 2))


def experiment_inputs(c: Case, kind: str):
    """(w_ref rad/s, load N, dither N m, q0 m, n_pre) of one experiment. Deterministic: the
    excitation's phases come from a fixed generator, the seed only draws the noise."""
    ph = np.random.default_rng(12345)
    if kind == "multisine":
        n = int(round(1.0 / c.ts))
        t = np.arange(n) * c.ts
        w = 20.0 + _multisine(t, 1.0, 20.0, 12, 3.0, ph)
        d = _multisine(t, 20.0, 0.35 / c.ts, 60, 0.06 * c.torque_limit, ph)
        return w, np.full(n, 0.4 * c.frf_load), d, c.frf_position_m - 0.03, int(0.1 / c.ts)
    if kind == "loadsteps":
        n = int(round(1.0 / c.ts))
        t = np.arange(n) * c.ts
        load = _ramp_steps(t, (0.2, 0.45, 0.7), (0.0, 0.8 * c.frf_load, 1.6 * c.frf_load, 0.3 * c.frf_load), 0.005)
        return np.full(n, 25.0), load, np.zeros(n), c.frf_position_m - 0.05, int(0.1 / c.ts)
    if kind == "staircase":
        n = int(round(1.2 / c.ts))
        t = np.arange(n) * c.ts
        w = _ramp_steps(t, (0.1, 0.35, 0.6, 0.85), (0.0, 8.0, 30.0, -12.0, -35.0), 0.02)
        return w, np.full(n, 0.25 * c.frf_load), np.zeros(n), c.frf_position_m, int(0.05 / c.ts)
    raise ValueError(f"unknown experiment {kind!r}")


def frf_experiment(c: Case, rng, *, n_period: int = 2048, n_periods: int = 5):
    """The drive's FRF measurement at (frf_speed, frf_load) around frf_position_m: a periodic
    random-phase multisine added to the speed loop's output, the first period dropped (transient).
    Returns (f_hz, G, coherence, q_mid): G = mean over periods of Y / mean of U at the excited
    bins, Y the DFT of the backward difference of the logged (quantised) angle / Ts, U of the
    command as the case logs it; the coherence the product of the excitation's coherence with
    the speed and with the command (|mean X|^2 / mean |X|^2 over the periods)."""
    ph = np.random.default_rng(777)
    fs = 1.0 / c.ts
    df = fs / n_period
    bins = np.unique(np.round(np.geomspace(4.0 / df, 0.42 * n_period, 160)).astype(int))
    t = np.arange(n_period) * c.ts
    x = np.zeros(n_period)
    for b, p in zip(bins, ph.uniform(0, TWO_PI, len(bins))):
        x += np.cos(TWO_PI * b * df * t + p)
    x *= 0.05 * c.torque_limit / np.sqrt(np.mean(x ** 2))
    n = n_period * n_periods
    n_pre = int(0.1 / c.ts)
    # the measured periods' midpoint at frf_position_m
    q0 = c.frf_position_m - c.a * c.frf_speed * (n_pre + n_period + 0.5 * (n - n_period)) * c.ts
    r = simulate(c, np.full(n, c.frf_speed), np.full(n, c.frf_load), np.tile(x, n_periods), q0=q0, rng=rng,
                 n_pre=n_pre)
    ang = r["angle"]
    spd = np.diff(ang, prepend=ang[0] - c.frf_speed * c.ts) / c.ts
    Y = np.fft.rfft(spd.reshape(n_periods, n_period)[1:], axis=1)[:, bins]
    U = np.fft.rfft(r["logged"].reshape(n_periods, n_period)[1:], axis=1)[:, bins]
    G = Y.mean(0) / U.mean(0)
    coh = (np.abs(Y.mean(0)) ** 2 / np.mean(np.abs(Y) ** 2, 0)) * (np.abs(U.mean(0)) ** 2 / np.mean(np.abs(U) ** 2, 0))
    return bins * df, G, coh, float(np.mean(r["q"][n_period:]))


# -- the truth and its checks ----------------------------------------------------------------------

def mode_formula_hz(c: Case, x_m: float, *, driving: bool = True):
    """Undamped natural frequencies, Hz, of the three bodies at nut position x_m: the
    characteristic cubic of ``det(K - w^2 M) = 0`` expanded by hand, with the nut's torque on the
    screw ``a F / eta_f`` (driving) or ``a F eta_b`` (back-driven). Ascending; no friction,
    current loop or damping."""
    k = stiffness(c, x_m)
    g = c.a / c.eta_f if driving else c.a * c.eta_b
    j1, j2, m, kc = c.j_motor, c.j_screw, c.mass_kg, c.k_coupling
    # M^-1 K = [[kc/j1, -kc/j1, 0], [-kc/j2, (kc + g a k)/j2, -g k/j2], [0, -a k/m, k/m]]
    # det(lam I - A) = lam^3 - tr lam^2 + s2 lam - det
    a11, a12 = kc / j1, -kc / j1
    a21, a22, a23 = -kc / j2, (kc + g * c.a * k) / j2, -g * k / j2
    a32, a33 = -c.a * k / m, k / m
    tr = a11 + a22 + a33
    s2 = (a11 * a22 - a12 * a21) + (a22 * a33 - a23 * a32) + a11 * a33
    det = a11 * (a22 * a33 - a23 * a32) - a12 * (a21 * a33)
    lam = np.roots([1.0, -tr, s2, -det])
    lam = np.sort(lam.real[lam.real > 1e-9])
    return np.sqrt(lam) / TWO_PI


def linearised_modes_hz(c: Case, w: float, f_load: float, x_m: float, eps: float = 1e-7):
    """The simulator's own linearisation at the steady state (speed w, load f_load, nut at x_m):
    the central-difference Jacobian of ``_rhs`` (torque input held, cogging and noise off);
    returns the oscillatory eigenvalues' magnitudes |lambda| / 2 pi, Hz, ascending, and their
    damping ratios."""
    y0, off = _steady_state(c, w, f_load, x_m)
    cst = list(_constants(c, off))
    cst[15] = cst[16] = 0.0  # cogging off
    cst = tuple(cst)
    cmd = y0[6]
    n = len(y0)
    jac = np.zeros((n, n))
    for i in range(n):
        sc = eps * max(1.0, abs(y0[i]))
        yp = list(y0)
        ym = list(y0)
        yp[i] += sc
        ym[i] -= sc
        jac[:, i] = (np.array(_rhs(c, cst, yp, cmd, f_load, 0.0)) - np.array(_rhs(c, cst, ym, cmd, f_load, 0.0))) / (2 * sc)
    # the rigid-body angle gives a zero eigenvalue and the current loop a real one: the
    # oscillatory pairs (positive imaginary part) are the two modes
    ev = np.linalg.eigvals(jac)
    osc = ev[ev.imag > 1.0]
    order = np.argsort(np.abs(osc))
    osc = osc[order]
    return np.abs(osc) / TWO_PI, -osc.real / np.abs(osc)


def anti_resonance_formula_hz(c: Case, x_m: float, *, driving: bool = True):
    """Undamped anti-resonances, Hz, of the torque -> motor speed response at nut position x_m:
    the natural frequencies with the rotor held (the screw and the carriage on the coupling and
    the axial spring), from the 2 x 2 block of ``mode_formula_hz``'s matrix. Ascending."""
    k = stiffness(c, x_m)
    g = c.a / c.eta_f if driving else c.a * c.eta_b
    a22, a23 = (c.k_coupling + g * c.a * k) / c.j_screw, -g * k / c.j_screw
    a32, a33 = -c.a * k / c.mass_kg, k / c.mass_kg
    lam = np.roots([1.0, -(a22 + a33), a22 * a33 - a23 * a32])
    return np.sqrt(np.sort(lam.real[lam.real > 1e-9])) / TWO_PI


def truth(name: str) -> dict:
    """The truth under the toolkit's keys, SI.

    For a judge of diagnoses: ``modes_hz`` every resonance of the three bodies at the FRF's nut
    position, driving and back-driven (the logs' nut stays within 5 cm of it); ``anti_resonances_hz``
    the same for the anti-resonances; ``periodic_orders_per_rev`` the cogging's orders;
    ``units_right`` / ``coordinates_right``: the log description and the plant file given to
    prsa-fit state the logs' true units and coordinates.
    """
    c = CASES[name]
    modes = mode_formula_hz(c, c.frf_position_m, driving=c.frf_load * c.frf_speed > 0)
    both = [mode_formula_hz(c, c.frf_position_m, driving=d) for d in (True, False)]
    antis = [anti_resonance_formula_hz(c, c.frf_position_m, driving=d) for d in (True, False)]
    return {
        "case": name,
        "mechanism": c.mechanism,
        "reflected_inertia_kg_m2": c.j_total,
        "motor_side_inertia_kg_m2": c.j_motor + c.j_screw,
        "moving_mass_kg": c.mass_kg,
        "drive.current_loop_bandwidth_hz": c.current_bw_hz,
        "drive.command_delay_samples": c.delay_samples,
        "delay_logged_to_action_samples": c.delay_samples + (1 if c.command_logged == "computed" else 0),
        "command_logged": c.command_logged,
        "first_mode_hz": float(modes[0]),
        "second_mode_hz": float(modes[1]),  # the coupling's
        "modes_hz": tuple(sorted(float(f) for fs in both for f in fs)),
        "anti_resonances_hz": tuple(sorted(float(f) for fs in antis for f in fs)),
        "periodic_orders_per_rev": (6, 12) if c.cog6 or c.cog12 else (),
        "units_right": True,
        "coordinates_right": True,
        "axial_stiffness_at_frf_n_per_um": stiffness(c, c.frf_position_m) * 1e-6,
        "frf_speed_rad_s": c.frf_speed,
        "frf_load_n": c.frf_load,
        "frf_position_m": c.frf_position_m,
        "efficiency_forward": c.eta_f,
        "efficiency_backward": c.eta_b,
        "two_mass": True,
        "sample_time_s": c.ts,
        "sources": SOURCES[name],
    }


# -- files -----------------------------------------------------------------------------------------

def _base_plant(c: Case) -> str:
    """The plant file a user writes from datasheets: nominal values, not the truth."""
    if c.mechanism == "ball-screw":
        return f"""# {c.name}: written from datasheets before any measurement (nominal values)
name = "{c.name}"
description = "Ball screw 40 x 16, screw held axially at the motor end, 420 kg class table, 4 kHz drive"
mechanism = "ball-screw"
mounting = {{ value = "fixed-free", source = "drawing: angular-contact pair at the motor end, radial support at the tail" }}

[screw]
pitch_diameter_mm = {{ value = 40.0, source = "catalogue: size 40 x 16" }}
lead_mm = {{ value = 16.0, source = "catalogue: size 40 x 16" }}
root_diameter_mm = {{ value = 35.0, source = "catalogue: root diameter of the 40 x 16 shaft" }}
rated_load_n = {{ value = 6000.0, source = "assumption: rated thrust of the axis" }}

[axis]
motor_inertia_kg_m2 = {{ value = 3.35e-3, source = "motor datasheet: rotor 3.2e-3 plus coupling 1.5e-4" }}
screw_inertia_kg_m2 = {{ value = 2.70e-3, source = "catalogue: 1.93e-3 kg m^2 per m of 40 mm shaft x 1.4 m" }}
moving_mass_kg = {{ value = 400.0, source = "estimate: table 250 kg, fixture and workpiece 150 kg" }}
bearing_span_mm = {{ value = 1400.0, source = "drawing" }}
stroke_position_mm = {{ value = {c.frf_position_m * 1000:.1f}, source = "the table's position during the FRF measurement" }}
nut_stiffness_n_per_um = {{ value = 1200.0, source = "catalogue: nut rigidity at 10 % preload (theoretical)" }}
bearing_stiffness_n_per_um = {{ value = 1500.0, source = "catalogue: support-bearing pair" }}

[friction]
efficiency = {{ value = 0.92, source = "catalogue: ball screw efficiency 0.9 to 0.95" }}
no_load_torque_n_m = {{ value = 0.30, source = "catalogue: preload drag torque" }}
viscous_n_m_s_per_rad = {{ value = 1.0e-3, source = "estimate" }}

[drive]
torque_limit_n_m = {{ value = 35.0, source = "motor datasheet: peak torque" }}
current_loop_bandwidth_hz = {{ value = 1000.0, source = "drive manual: current loop ~1 kHz" }}

[sensor]
sample_time_s = {{ value = {c.ts!r}, source = "drive setting: 4 kHz speed loop" }}
encoder_counts_per_rev = {{ value = {c.counts_per_rev}, source = "motor datasheet: 20-bit encoder" }}
speed_filter_time_constant_s = {{ value = {c.speed_filter_s!r}, source = "drive setting" }}
"""
    return f"""# {c.name}: written from datasheets before any measurement (nominal values)
name = "{c.name}"
description = "Planetary roller screw 39 x 10, screw held axially at the motor end, 500 kg class ram, 5 kHz drive"
mechanism = "roller-screw"
mounting = {{ value = "fixed-free", source = "drawing: thrust bearing pair at the motor end" }}

[screw]
pitch_diameter_mm = {{ value = 39.0, source = "catalogue: size 39 x 10" }}
lead_mm = {{ value = 10.0, source = "catalogue: size 39 x 10" }}
starts = {{ value = 5, source = "catalogue: 5 starts of 2 mm pitch" }}
root_diameter_mm = {{ value = 37.0, source = "catalogue" }}
rated_load_n = {{ value = 12000.0, source = "assumption: rated thrust of the press" }}

[roller]
pitch_diameter_mm = {{ value = 13.0, source = "catalogue: standard design d_S = (n_S - 2) d_R with n_S = 5" }}
count = {{ value = 10, source = "catalogue" }}

[axis]
motor_inertia_kg_m2 = {{ value = 1.6e-3, source = "motor datasheet: rotor 1.45e-3 plus coupling 1.5e-4" }}
screw_inertia_kg_m2 = {{ value = 1.40e-3, source = "catalogue: 1.75e-3 kg m^2 per m x 0.8 m" }}
moving_mass_kg = {{ value = 480.0, source = "estimate: ram and tooling" }}
bearing_span_mm = {{ value = 800.0, source = "drawing" }}
stroke_position_mm = {{ value = {c.frf_position_m * 1000:.1f}, source = "the ram's position during the FRF measurement" }}
nut_stiffness_n_per_um = {{ value = 2400.0, source = "catalogue: roller nut rigidity (theoretical)" }}
bearing_stiffness_n_per_um = {{ value = 1800.0, source = "catalogue: thrust bearing pair" }}

[friction]
efficiency = {{ value = 0.85, source = "catalogue: roller screw efficiency 0.8 to 0.9" }}
no_load_torque_n_m = {{ value = 0.2, source = "catalogue: preload drag torque" }}
viscous_n_m_s_per_rad = {{ value = 6.0e-4, source = "estimate" }}

[drive]
torque_limit_n_m = {{ value = 22.0, source = "motor datasheet: peak torque" }}
current_loop_bandwidth_hz = {{ value = 1200.0, source = "drive manual" }}

[sensor]
sample_time_s = {{ value = {c.ts!r}, source = "drive setting: 5 kHz speed loop" }}
encoder_counts_per_rev = {{ value = {c.counts_per_rev}, source = "motor datasheet: 17-bit encoder" }}
speed_filter_time_constant_s = {{ value = {c.speed_filter_s!r}, source = "drive setting" }}
"""


LOG_FORMAT_NONSI = """# roller-39x10 logs: time in ms, motor angle in revolutions, torque command in % of the
# rated torque (9 N m), load cell in kN; the command as the drive applied it over the sample
description = "roller-39x10 press axis, drive trace export"
axis = "rotary"

[time]
name = "t_ms"
unit = "ms"

[position]
name = "motor_rev"
unit = "rev"

[command]
name = "torque_pct"
unit = "%"
gain = {gain}
logged = "as-applied"

[load]
name = "force_kn"
unit = "kN"
"""


def _write_log(path: Path, c: Case, r) -> None:
    n = len(r["u"])
    t = np.arange(n) * c.ts
    if c.non_si:
        cols = np.column_stack([t * 1e3, r["angle"] / TWO_PI, r["logged"] / c.rated_torque * 100.0, r["load"] * 1e-3])
        header = "t_ms,motor_rev,torque_pct,force_kn"
        fmt = ["%.4f", "%.10f", "%.6f", "%.6f"]
    else:
        cols = np.column_stack([t, r["logged"], r["angle"], r["load"]])
        header = "time_s,torque_command_n_m,nut_angle_rad,axial_load_n"
        fmt = ["%.7f", "%.8e", "%.10e", "%.4f"]
    np.savetxt(path, cols, delimiter=",", header=header, comments="", fmt=fmt)


def generate(out_dir, name: str, seed: int = 0, experiments=EXPERIMENTS, frf: bool = True) -> dict:
    """Write the case's logs, bode.csv, base plant (and log description for the non-SI case) and
    truth.json into ``out_dir``; return the paths, the truth and the simulated runs."""
    c = CASES[name]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ss = np.random.SeedSequence([seed, sum(map(ord, name))])
    rngs = {k: np.random.default_rng(s) for k, s in zip(("frf", *EXPERIMENTS), ss.spawn(4))}
    res = {"logs": {}, "runs": {}, "truth": truth(name), "case": c}
    for kind in experiments:
        w, load, d, q0, npre = experiment_inputs(c, kind)
        r = simulate(c, w, load, d, q0=q0, rng=rngs[kind], n_pre=npre)
        p = out / f"{kind}.csv"
        _write_log(p, c, r)
        res["logs"][kind] = p
        res["runs"][kind] = r
    if frf:
        f, g, coh, q_mid = frf_experiment(c, rngs["frf"])
        p = out / "bode.csv"
        np.savetxt(p, np.column_stack([f, 20 * np.log10(np.abs(g)), np.degrees(np.angle(g)), coh]), delimiter=",",
                   header="frequency_hz,magnitude_db,phase_deg,coherence", comments="", fmt="%.8g")
        res["frf"] = p
        res["frf_data"] = (f, g, coh, q_mid)
    base = out / "base.toml"
    base.write_text(_base_plant(c))
    res["base"] = base
    res["log_format"] = None
    if c.non_si:
        lf = out / "log.toml"
        lf.write_text(LOG_FORMAT_NONSI.format(gain=c.rated_torque / 100.0))
        res["log_format"] = lf
    (out / "truth.json").write_text(json.dumps(res["truth"], indent=1))
    return res
