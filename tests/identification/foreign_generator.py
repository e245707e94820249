"""An independent drive simulator that writes logs as a real servo drive would (numpy/scipy only:
nothing of prsa_ctrl). The foreign-log tests (the foreign-log section of test_delay.py) fit its logs.

The axis, in motor coordinates (rad, N m), an axial load ``F`` (N) acting through the lead
``a`` (m/rad)::

    theta' = omega
    J omega' = tau - a F - b omega - T_off - T_c(omega, F) sign(omega)        (sliding)
    tau'   = (u(t) - tau) / t_c,   t_c = 1 / (2 pi f_c)                     (current loop)

with the Coulomb level ``T_c = (T_0 + c_F |F|) (1 + (s - 1) exp(-(omega / w_s)^2))``
(Stribeck: ``s`` times the sliding level at rest), ``c_F = a (1 / eta - 1)`` the screw's load
losses at forward efficiency ``eta`` and the offset ``T_off`` (levels ``T_0 + T_off`` forward,
``T_0 - T_off`` backward at no load). A stuck axis (``omega = 0``) stays stuck while
``|tau - a F - T_off|`` is below the breakaway level ``s (T_0 + c_F |F|)``.

Integration: substeps of ``Ts / substeps``; over each the linear part is integrated exactly
(matrix exponential, inputs held) with the Coulomb torque of the substep's start. At speed that
is exact (the Stribeck term has died out, ``exp(-(omega/w_s)^2)`` below 1e-30 beyond 8
``w_s``); near reversals a substep that would change the sign of ``omega`` ends at rest.

The drive: at each sample ``k`` the encoder angle (Gaussian interpolation noise, then
quantised to ``counts`` per revolution) gives the speed by backward difference and a
first-order filter; a PI speed controller (saturated at the torque limit, integrator clamped)
computes ``u_k``; the controller outputs it over ``[k+1, k+2)`` (one-sample computation delay)
and the drive's transport adds ``transport`` samples before the current loop receives it.
The log holds, per sample, the time, the quantised angle, the axial load and the command:
``convention="applied"`` the controller's output over the sample (``u_{k-1}``),
``"computed"`` the command computed at the sample (``u_k``, which acts later).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.linalg import expm


@dataclass(frozen=True)
class Axis:
    """The true axis and drive (SI units)."""

    inertia_kg_m2: float = 2.0e-4
    lead_m_per_rad: float = 2.0e-3 / (2 * math.pi)
    efficiency: float = 0.86
    no_load_torque_n_m: float = 0.025
    offset_torque_n_m: float = 0.006
    viscous_n_m_s_per_rad: float = 1.5e-4
    stribeck_ratio: float = 1.4
    stribeck_speed_rad_s: float = 0.25
    bandwidth_hz: float = 650.0
    transport_samples: int = 1
    sample_time_s: float = 2.5e-4
    counts_per_rev: int = 2**20
    angle_noise_rad: float = 2e-6
    torque_limit_n_m: float = 3.0
    kp: float = 0.05
    ki: float = 2.0
    speed_filter_s: float = 2e-4
    substeps: int = 4

    @property
    def load_coefficient(self) -> float:
        """``c_F``: Coulomb torque per newton of axial load, N m/N."""
        return self.lead_m_per_rad * (1.0 / self.efficiency - 1.0)


@dataclass
class Log:
    """One log: per sample time (s), quantised angle (rad), command (N m), axial load (N); and
    the true motor torque and speed (for checks)."""

    name: str
    time_s: np.ndarray
    angle_rad: np.ndarray
    command_n_m: np.ndarray
    load_n: np.ndarray
    speed_rad_s: np.ndarray = field(repr=False, default=None)
    convention: str = "applied"


def _discrete(ax: Axis, h: float):
    """Exact ZOH matrices over ``h`` of the linear part: state (theta, omega, tau), inputs
    (u, T_ext) with ``T_ext`` every torque but the motor's and the viscous one."""
    tc = 1.0 / (2 * math.pi * ax.bandwidth_hz)
    a = np.array([[0.0, 1.0, 0.0], [0.0, -ax.viscous_n_m_s_per_rad / ax.inertia_kg_m2, 1.0 / ax.inertia_kg_m2],
                  [0.0, 0.0, -1.0 / tc]])
    b = np.array([[0.0, 0.0], [0.0, -1.0 / ax.inertia_kg_m2], [1.0 / tc, 0.0]])
    m = np.zeros((5, 5))
    m[:3, :3], m[:3, 3:] = a * h, b * h
    e = expm(m)
    return e[:3, :3], e[:3, 3:]


def simulate(ax: Axis, setpoint_rad_s: np.ndarray, load_n: np.ndarray, *, seed: int = 0, name: str = "log",
             convention: str = "applied", speed0: float | None = None) -> Log:
    """Run the drive over ``len(setpoint_rad_s)`` samples (setpoint and load per sample)."""
    if convention not in ("applied", "computed"):
        raise ValueError(convention)
    n = len(setpoint_rad_s)
    ts, h = ax.sample_time_s, ax.sample_time_s / ax.substeps
    phi, gam = _discrete(ax, h)
    rng = np.random.default_rng(seed)
    q = 2 * math.pi / ax.counts_per_rev
    cf = ax.load_coefficient
    w0 = float(setpoint_rad_s[0]) if speed0 is None else speed0
    f0 = float(load_n[0])
    # start in steady state at w0 (sliding) or at rest
    tau0 = ax.lead_m_per_rad * f0 + ax.viscous_n_m_s_per_rad * w0 + ax.offset_torque_n_m \
        + (math.copysign(ax.no_load_torque_n_m + cf * abs(f0), w0) if w0 else 0.0)
    x = np.array([0.0, w0, tau0])
    alpha = math.exp(-ts / ax.speed_filter_s)
    th_prev = math.floor((x[0] - w0 * ts) / q) * q
    w_f = w0
    integ = tau0
    line = [tau0] * (ax.transport_samples + 1)  # controller output + transport, oldest first
    angles, cmds_applied, cmds_computed, speeds = (np.empty(n) for _ in range(4))
    for k in range(n):
        th_q = math.floor((x[0] + ax.angle_noise_rad * rng.standard_normal()) / q) * q
        w_f = alpha * w_f + (1 - alpha) * (th_q - th_prev) / ts
        th_prev = th_q
        e = setpoint_rad_s[k] - w_f
        u = ax.kp * e + integ
        u_sat = min(max(u, -ax.torque_limit_n_m), ax.torque_limit_n_m)
        if u == u_sat:  # conditional integration (anti-windup)
            integ += ts * ax.ki * e
        angles[k], speeds[k] = th_q, x[1]
        cmds_applied[k] = line[-1]  # the controller's output over this sample (computed at k-1)
        cmds_computed[k] = u_sat
        acting = line[0]  # what the current loop receives over this sample
        line = line[1:] + [u_sat]
        f = float(load_n[k])
        for _ in range(ax.substeps):
            x = _substep(ax, x, acting, f, phi, gam, h, cf)
    log_cmd = cmds_applied if convention == "applied" else cmds_computed
    return Log(name, ts * np.arange(n), angles, log_cmd, np.asarray(load_n, float), speeds, convention)


def _substep(ax: Axis, x, u, f, phi, gam, h, cf):
    w = x[1]
    level0 = ax.no_load_torque_n_m + cf * abs(f)
    strib = 1.0 + (ax.stribeck_ratio - 1.0) * math.exp(-((w / ax.stribeck_speed_rad_s) ** 2))
    load_t = ax.lead_m_per_rad * f + ax.offset_torque_n_m
    if w == 0.0:
        # stuck: net torque against the breakaway level (the current loop moves on)
        tau_mid = x[2] + (1 - math.exp(-h * 2 * math.pi * ax.bandwidth_hz)) * (u - x[2])
        net = tau_mid - load_t
        if abs(net) <= ax.stribeck_ratio * level0:
            nxt = phi @ np.array([x[0], 0.0, x[2]]) + gam @ np.array([u, 0.0])
            return np.array([x[0], 0.0, nxt[2]])
        direction = math.copysign(1.0, net)
    else:
        direction = math.copysign(1.0, w)
    t_ext = load_t + direction * level0 * strib
    nxt = phi @ x + gam @ np.array([u, t_ext])
    if nxt[1] * direction < 0:  # the substep would reverse the motion: it ends at rest
        nxt[1] = 0.0
    return nxt


# --- the experiments of the issue -------------------------------------------------------------

def load_steps(n: int, ts: float, loads=(500.0, 1500.0, 0.0), speed: float = 40.0, ripple: float = 8.0, seed: int = 0):
    """Setpoint and load of the load-step log: constant speed with a small random-phase
    multisine on the setpoint (a drive test always has some), loads in equal thirds."""
    t = ts * np.arange(n)
    rng = np.random.default_rng(seed + 1000)
    sp = speed + ripple * sum(np.sin(2 * np.pi * fr * t + rng.uniform(0, 2 * np.pi)) for fr in (3.0, 11.0, 37.0)) / 3
    load = np.asarray(loads, float)[np.minimum((3 * np.arange(n)) // n, len(loads) - 1)]
    return sp, load


def staircase(n: int, ts: float, levels=(20.0, 45.0, -20.0, -45.0, 30.0, -30.0), load: float = 500.0):
    """A speed staircase through both directions at a constant load."""
    idx = np.minimum((len(levels) * np.arange(n)) // n, len(levels) - 1)
    return np.asarray(levels, float)[idx], np.full(n, load)


def multisine(n: int, ts: float, seed: int = 0, mean: float = 30.0, amp: float = 20.0, f_lo=2.0, f_hi=400.0,
              loads=(200.0, 1500.0, 300.0, 1000.0)):
    """Random-phase multisine setpoint (``f_lo..f_hi`` Hz, 40 lines) with load steps every quarter."""
    t = ts * np.arange(n)
    rng = np.random.default_rng(seed + 2000)
    freqs = np.geomspace(f_lo, f_hi, 40)
    s = sum(np.sin(2 * np.pi * fr * t + rng.uniform(0, 2 * np.pi)) for fr in freqs)
    sp = mean + amp * s / np.max(np.abs(s))
    load = np.asarray(loads, float)[np.minimum((len(loads) * np.arange(n)) // n, len(loads) - 1)]
    return sp, load


#: Speed levels (rad/s) of the low-speed staircase: 0.4 to 8 Stribeck speeds of the default axis.
LOW_LEVELS = (0.1, 0.2, 0.35, 0.6, 1.0, 2.0)
#: Speed-loop gains (kp N m s/rad, ki 1/s) of the low-speed test: stiffer than the default drive's.
#: At kp = 0.05 the Stribeck curve's negative slope below ~0.3 rad/s under load outweighs the
#: loop's damping and the axis sticks and slips; at these it holds every level at 0 N and from
#: 0.2 rad/s at 1000 N (the first level after a start or reversal under load still sticks and
#: slips: no plateau there, which the friction map has to recognise).
LOW_GAINS = (0.15, 6.0)


def low_speed_staircase(ts: float, levels=LOW_LEVELS, loads=(0.0, 1000.0), plateau_s: float = 0.4):
    """Setpoint and load of the low-speed staircase: at each load the levels upwards in the positive
    direction, then the same in the negative direction, ``plateau_s`` each (a friction-map test)."""
    m = int(round(plateau_s / ts))
    sp, ld = [], []
    for f in loads:
        for sign in (1.0, -1.0):
            for lv in levels:
                sp.append(np.full(m, sign * lv))
                ld.append(np.full(m, float(f)))
    return np.concatenate(sp), np.concatenate(ld)


def low_speed_log(ax: Axis, seed: int, convention: str = "applied", **kw) -> Log:
    """The low-speed staircase of one seed (:func:`low_speed_staircase`), starting at rest, with
    the speed-loop gains :data:`LOW_GAINS`."""
    ax = replace(ax, kp=LOW_GAINS[0], ki=LOW_GAINS[1])
    sp, ld = low_speed_staircase(ax.sample_time_s, **kw)
    return simulate(ax, sp, ld, seed=seed * 7 + 5, name=f"low-speed-{seed}", convention=convention, speed0=0.0)


def logs(ax: Axis, seed: int, duration_s: float = 1.5, convention: str = "applied") -> list[Log]:
    """The three logs of one seed: load steps, staircase, multisine."""
    n = int(round(duration_s / ax.sample_time_s))
    ts = ax.sample_time_s
    out = []
    for name, (sp, ld) in (("load-steps", load_steps(n, ts, seed=seed)), ("staircase", staircase(n, ts)),
                           ("multisine", multisine(n, ts, seed=seed))):
        out.append(simulate(ax, sp, ld, seed=seed * 7 + len(out), name=f"{name}-{seed}", convention=convention))
    return out


def with_(ax: Axis, **kw) -> Axis:
    """A copy of ``ax`` with some fields changed."""
    return replace(ax, **kw)
