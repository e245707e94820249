"""The simulator shared by the foreign generators: a screw-driven axis under a sampled speed loop.

Written for issue 32 (part 6) without reading prsa-ctrl's fitting or model code, with numpy and
scipy only. It deliberately differs from the toolkit's model structure where real axes do:

- **Mechanics** (motor coordinates, lead ``a`` = lead / (2 pi) in m/rad). Two masses: the motor
  side (rotor, coupling and screw, inertia ``J_m``, angle ``theta``, speed ``w``) and the load
  (mass ``m``, position ``x``, velocity ``v``), joined by the axial spring of screw, nut and
  bearings ``k`` (N/m) with a damper ``c`` (N s/m). The force through the nut is
  ``F_s = k (a theta - x) + c (a w - v)``. A rigid axis (``k = None``) has ``x = a theta``; its
  nut force ``F_s = m a dw/dt + F_ext`` is solved exactly from the piecewise-linear balance.
- **Nut loss on the whole force through the nut** (inertial force included):
  ``T_loss = (1/eta - 1) |a F_s| sgn(w)``, ``sgn`` smoothed as ``tanh(w / w_eps)``.
- **Motor-side friction** with standstill (Stribeck) excess and a Coulomb level per direction:
  ``T_f = sgn(w) [T_c,dir + (T_s,dir - T_c,dir) exp(-(w / w_s)^2)] + b w``.
- **Drive**: PI speed loop at ``Ts`` with back-calculation anti-windup (tracking time
  ``kp / ki``) and a symmetric torque limit; the command computed at sample ``k`` acts from
  sample ``k + 1 + n_t`` (one sample of computation delay plus ``n_t`` of transport), held over
  each sample (zero-order hold), through a first-order current loop ``dT_e/dt = 2 pi f_c
  (u - T_e)``; a white process torque noise, constant over each sample.
- **Sensors**: encoder angle ``floor(theta / q) q`` (``q = 2 pi / counts``) plus white angle noise;
  speed = backward difference of that angle, then a first-order filter (``exp(-Ts/tau)``, exact
  for a held input); load cell = external force plus white noise.
- **Integration**: fixed-step classical Runge-Kutta (RK4), ``n_sub`` sub-steps per sample, inputs
  held over the sample.

Units: SI throughout (s, rad, rad/s, m, N, N m, kg, kg m^2); a generator converts to the units of
its log when it writes it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import cont2discrete

__all__ = ["Axis", "Drive", "Sensors", "simulate", "frf", "linear_matrices", "schroeder_multisine",
           "steady_torque", "mode_frequencies_hz", "write_csv"]


@dataclass(frozen=True)
class Axis:
    """Mechanics of a screw-driven axis, SI.

    Attributes
    ----------
    lead_m : float
        Travel per screw revolution, m.
    motor_side_inertia_kg_m2 : float
        Rotor, coupling and screw (everything on the motor side of the axial spring), kg m^2.
    load_mass_kg : float
        Translating mass (nut, carriage, payload), kg.
    stiffness_n_per_m : float or None
        Axial stiffness between the screw's angle and the load (screw, nut, bearings in series),
        N/m; ``None``: rigid axis.
    damping_n_s_per_m : float
        Axial damper parallel to the spring, N s/m (ignored when rigid).
    efficiency : float
        Nut efficiency ``eta`` in (0.5, 1]; the loss ``(1/eta - 1) |a F_s|`` acts on the whole
        force through the nut.
    coulomb_pos_n_m, coulomb_neg_n_m : float
        Coulomb drag torque moving forward / backward (magnitudes), N m.
    breakaway_pos_n_m, breakaway_neg_n_m : float
        Standstill (Stribeck) level per direction (magnitudes, >= the Coulomb level), N m.
    stribeck_speed_rad_s : float
        Stribeck speed ``w_s`` of the Gaussian decay, rad/s (motor speed).
    viscous_n_m_s_per_rad : float
        Viscous drag ``b``, N m s/rad.
    sign_speed_rad_s : float
        ``w_eps`` of the smoothed sign ``tanh(w / w_eps)``, rad/s.
    """

    lead_m: float
    motor_side_inertia_kg_m2: float
    load_mass_kg: float
    stiffness_n_per_m: float | None
    damping_n_s_per_m: float
    efficiency: float
    coulomb_pos_n_m: float
    coulomb_neg_n_m: float
    breakaway_pos_n_m: float
    breakaway_neg_n_m: float
    stribeck_speed_rad_s: float
    viscous_n_m_s_per_rad: float
    sign_speed_rad_s: float = 0.05

    @property
    def a(self) -> float:
        """Lead per radian, m/rad."""
        return self.lead_m / (2.0 * math.pi)

    @property
    def load_inertia_kg_m2(self) -> float:
        """The load mass reflected to the motor, ``m a^2``, kg m^2."""
        return self.load_mass_kg * self.a ** 2

    @property
    def total_inertia_kg_m2(self) -> float:
        """Total reflected inertia ``J_m + m a^2`` (the loss excluded), kg m^2."""
        return self.motor_side_inertia_kg_m2 + self.load_inertia_kg_m2

    @property
    def loss(self) -> float:
        """``1/eta - 1``."""
        return 1.0 / self.efficiency - 1.0


@dataclass(frozen=True)
class Drive:
    """Sampled PI speed loop, delays and current loop.

    Attributes
    ----------
    sample_time_s : float
        Speed-loop sample time, s.
    kp : float
        Proportional gain, N m s/rad.
    ki : float
        Integral gain, N m/rad.
    torque_limit_n_m : float
        Symmetric limit of the command, N m.
    current_loop_hz : float
        Bandwidth ``f_c`` of the first-order current loop, Hz.
    transport_delay_samples : int
        Whole samples of transport delay beyond the one-sample computation delay.
    torque_noise_n_m : float
        RMS of the process torque noise per sample, N m.
    n_sub : int
        RK4 sub-steps per sample.
    """

    sample_time_s: float
    kp: float
    ki: float
    torque_limit_n_m: float
    current_loop_hz: float
    transport_delay_samples: int
    torque_noise_n_m: float
    n_sub: int = 4


@dataclass(frozen=True)
class Sensors:
    """Encoder, speed filter and load cell.

    Attributes
    ----------
    counts_per_rev : int
        Encoder counts per revolution (the angle is floored to a count).
    angle_noise_rad : float
        White angle noise before quantisation, rad RMS.
    speed_filter_s : float
        Time constant of the first-order speed filter, s (0: none).
    load_noise_n : float
        Load-cell noise, N RMS.
    """

    counts_per_rev: int
    angle_noise_rad: float
    speed_filter_s: float
    load_noise_n: float


def _friction(ax: Axis, w: float) -> float:
    """Motor-side friction torque at speed ``w`` (rad/s), N m."""
    s = math.tanh(w / ax.sign_speed_rad_s)
    g = math.exp(-(w / ax.stribeck_speed_rad_s) ** 2)
    if w >= 0.0:
        level = ax.coulomb_pos_n_m + (ax.breakaway_pos_n_m - ax.coulomb_pos_n_m) * g
    else:
        level = ax.coulomb_neg_n_m + (ax.breakaway_neg_n_m - ax.coulomb_neg_n_m) * g
    return s * level + ax.viscous_n_m_s_per_rad * w


def steady_torque(ax: Axis, w: float, force_n: float) -> float:
    """Motor torque that holds speed ``w`` (rad/s, nonzero) against the external force ``force_n``.

    Independent of the integrator: ``T = T_f(w) + a F + (1/eta - 1) |a F| sgn(w)``, N m.
    """
    s = math.tanh(w / ax.sign_speed_rad_s)
    p = ax.a * force_n
    return _friction(ax, w) + p + ax.loss * abs(p) * s


def _deriv_two_mass(ax: Axis, wc: float, y, te_in: float, dist: float, f_ext: float):
    th, w, x, v, te = y
    a = ax.a
    fs = ax.stiffness_n_per_m * (a * th - x) + ax.damping_n_s_per_m * (a * w - v)
    p = a * fs
    t_loss = ax.loss * abs(p) * math.tanh(w / ax.sign_speed_rad_s)
    dw = (te + dist - _friction(ax, w) - p - t_loss) / ax.motor_side_inertia_kg_m2
    dv = (fs - f_ext) / ax.load_mass_kg
    return (w, dw, v, dv, wc * (te_in - te))


def _deriv_rigid(ax: Axis, wc: float, y, te_in: float, dist: float, f_ext: float):
    th, w, te = y
    s = math.tanh(w / ax.sign_speed_rad_s)
    r_ratio = ax.motor_side_inertia_kg_m2 / ax.load_inertia_kg_m2
    rhs = te + dist - _friction(ax, w)
    num = rhs + r_ratio * ax.a * f_ext
    # (r+1) P + loss s |P| = rhs + r a F: monotone in P, sign(P) = sign(num)
    p = num / (r_ratio + 1.0 + ax.loss * s) if num >= 0.0 else num / (r_ratio + 1.0 - ax.loss * s)
    dw = (rhs - p - ax.loss * s * abs(p)) / ax.motor_side_inertia_kg_m2
    return (w, dw, wc * (te_in - te))


def _rk4(f, y, h, *args):
    k1 = f(y, *args)
    y2 = tuple(yi + 0.5 * h * ki for yi, ki in zip(y, k1))
    k2 = f(y2, *args)
    y3 = tuple(yi + 0.5 * h * ki for yi, ki in zip(y, k2))
    k3 = f(y3, *args)
    y4 = tuple(yi + h * ki for yi, ki in zip(y, k3))
    k4 = f(y4, *args)
    return tuple(yi + h / 6.0 * (a + 2.0 * b + 2.0 * c + d) for yi, a, b, c, d in zip(y, k1, k2, k3, k4))


@dataclass
class Run:
    """One simulated experiment, SI, one entry per sample ``k`` (time ``k Ts``).

    ``command_computed`` is the command computed at sample k (acts from ``k + 1 + n_t``);
    ``command_applied`` the one the controller outputs over sample k (computed at ``k - 1``);
    ``angle_measured`` the encoder angle, ``speed_measured`` the filtered speed the loop uses,
    ``load_measured`` the load cell; ``speed_true``, ``force_true``, ``torque_motor`` the truth.
    """

    time: np.ndarray
    command_computed: np.ndarray
    command_applied: np.ndarray
    dither: np.ndarray
    angle_measured: np.ndarray
    speed_measured: np.ndarray
    load_measured: np.ndarray
    speed_true: np.ndarray
    force_true: np.ndarray
    setpoint: np.ndarray
    extra: dict = field(default_factory=dict)


def simulate(ax: Axis, drv: Drive, sen: Sensors, setpoint, force, rng: np.random.Generator,
             dither=None, start_speed: float = 0.0) -> Run:
    """Simulate the closed speed loop over ``len(setpoint)`` samples.

    Parameters
    ----------
    ax, drv, sen : Axis, Drive, Sensors
        The axis, its drive and sensors.
    setpoint : array_like
        Speed setpoint per sample, rad/s.
    force : array_like
        External axial force per sample (held over the sample), N; positive opposes positive motion.
    rng : numpy.random.Generator
        Source of every noise (the run is a function of its state).
    dither : array_like, optional
        Torque added to the PI output before the limit, N m per sample.
    start_speed : float
        Speed of the steady state the run starts in, rad/s (0: at rest; else nonzero, with the
        first sample's force).

    Returns
    -------
    Run
    """
    r = np.asarray(setpoint, dtype=float)
    f_ext = np.asarray(force, dtype=float)
    n = r.size
    dth = np.zeros(n) if dither is None else np.asarray(dither, dtype=float)
    ts = drv.sample_time_s
    h = ts / drv.n_sub
    wc = 2.0 * math.pi * drv.current_loop_hz
    q = 2.0 * math.pi / sen.counts_per_rev
    alpha = math.exp(-ts / sen.speed_filter_s) if sen.speed_filter_s > 0 else 0.0
    two_mass = ax.stiffness_n_per_m is not None
    deriv = _deriv_two_mass if two_mass else _deriv_rigid
    tt = 1.0 / (drv.kp / drv.ki)  # back-calculation gain 1/T_t, T_t = kp/ki
    lim = drv.torque_limit_n_m

    w0 = float(start_speed)
    t0 = steady_torque(ax, w0, f_ext[0]) if w0 != 0.0 else 0.0
    if two_mass:
        fs0 = f_ext[0] if w0 != 0.0 else 0.0
        y = (0.0, w0, -fs0 / ax.stiffness_n_per_m, ax.a * w0, t0)
    else:
        y = (0.0, w0, t0)
    integ = t0
    d_total = 1 + drv.transport_delay_samples
    queue = [t0] * d_total  # commands computed at k-d_total .. k-1
    noise_t = rng.standard_normal(n) * drv.torque_noise_n_m
    noise_a = rng.standard_normal(n) * sen.angle_noise_rad
    noise_f = rng.standard_normal(n) * sen.load_noise_n
    th_prev_meas = math.floor((-w0 * ts + noise_a[0]) / q) * q
    wf = w0

    u_comp = np.empty(n)
    ang = np.empty(n)
    spd = np.empty(n)
    w_true = np.empty(n)
    f_true = np.empty(n)
    def f(yy, *args):
        return deriv(ax, wc, yy, *args)

    for k in range(n):
        th_meas = math.floor((y[0] + noise_a[k]) / q) * q
        raw = (th_meas - th_prev_meas) / ts
        th_prev_meas = th_meas
        wf = alpha * wf + (1.0 - alpha) * raw
        e = r[k] - wf
        v_uns = drv.kp * e + integ + dth[k]
        u = min(max(v_uns, -lim), lim)
        integ += ts * (drv.ki * e + tt * (u - v_uns))
        u_comp[k] = u
        ang[k] = th_meas
        spd[k] = wf
        w_true[k] = y[1]
        if two_mass:
            f_true[k] = ax.stiffness_n_per_m * (ax.a * y[0] - y[2]) + ax.damping_n_s_per_m * (ax.a * y[1] - y[3])
        else:
            f_true[k] = f_ext[k]
        te_in = queue.pop(0)  # computed at k - d_total, acts over [k, k+1)
        queue.append(u)
        for _ in range(drv.n_sub):
            y = _rk4(f, y, h, te_in, noise_t[k], f_ext[k])
    applied = np.concatenate(([t0], u_comp[:-1]))
    return Run(time=np.arange(n) * ts, command_computed=u_comp, command_applied=applied, dither=dth,
               angle_measured=ang, speed_measured=spd, load_measured=f_ext + noise_f,
               speed_true=w_true, force_true=f_true, setpoint=r)


def linear_matrices(ax: Axis, current_loop_hz: float, force_n: float):
    """Continuous linear part at a speed > 0 under the force ``force_n`` > 0 (nut force positive).

    There the loss is linear, ``(1/eta - 1) a F_s``, so the motor side sees the nut force times
    ``1/eta``; the Stribeck term has decayed (speed >> ``w_s``) and the sign is +1.

    Returns
    -------
    (A, B, C) : numpy.ndarray
        Input: the torque command reaching the current loop, N m; output: the motor angle, rad.
        States ``[theta, w, x, v, T_e]`` (two-mass) or ``[theta, w, T_e]`` (rigid).
    """
    if force_n <= 0:
        raise ValueError(f"force_n = {force_n!r}: the linear part needs a positive nut force")
    wc = 2.0 * math.pi * current_loop_hz
    a, jm, m, b, g = ax.a, ax.motor_side_inertia_kg_m2, ax.load_mass_kg, ax.viscous_n_m_s_per_rad, 1.0 / ax.efficiency
    if ax.stiffness_n_per_m is None:
        jeff = jm + g * ax.load_inertia_kg_m2
        A = np.array([[0, 1, 0], [0, -b / jeff, 1 / jeff], [0, 0, -wc]], dtype=float)
        B = np.array([[0], [0], [wc]], dtype=float)
        C = np.array([[1, 0, 0]], dtype=float)
        return A, B, C
    k, c = ax.stiffness_n_per_m, ax.damping_n_s_per_m
    A = np.array([
        [0, 1, 0, 0, 0],
        [-g * a * k * a / jm, -(b + g * a * c * a) / jm, g * a * k / jm, g * a * c / jm, 1 / jm],
        [0, 0, 0, 1, 0],
        [k * a / m, c * a / m, -k / m, -c / m, 0],
        [0, 0, 0, 0, -wc],
    ], dtype=float)
    B = np.array([[0], [0], [0], [0], [wc]], dtype=float)
    C = np.array([[1, 0, 0, 0, 0]], dtype=float)
    return A, B, C


def frf(ax: Axis, drv: Drive, sen: Sensors, freq_hz, force_n: float, delay_samples: int,
        speed_filter: bool = False) -> np.ndarray:
    """Frequency response from the logged torque command to the measured motor speed, rad/s per N m.

    As the drive measures it: the logged command acts ``delay_samples`` later, held over each
    sample (ZOH), through the current loop and the linear mechanics at ``force_n``; the angle is
    sampled and differenced backwards (``(1 - z^-1) / Ts``); with ``speed_filter`` the drive's
    first-order speed filter follows. Exact for the linear part (matrix exponential).
    """
    A, B, C = linear_matrices(ax, drv.current_loop_hz, force_n)
    ts = drv.sample_time_s
    Ad, Bd, Cd, _, _ = cont2discrete((A, B, C, np.zeros((1, 1))), ts, method="zoh")
    f = np.asarray(freq_hz, dtype=float)
    z = np.exp(1j * 2.0 * math.pi * f * ts)
    eye = np.eye(Ad.shape[0])
    out = np.empty(f.size, dtype=complex)
    for i, zi in enumerate(z):
        h_ang = (Cd @ np.linalg.solve(zi * eye - Ad, Bd))[0, 0]
        h = h_ang * (1.0 - 1.0 / zi) / ts * zi ** (-delay_samples)
        if speed_filter and sen.speed_filter_s > 0:
            al = math.exp(-ts / sen.speed_filter_s)
            h *= (1.0 - al) / (1.0 - al / zi)
        out[i] = h
    return out


def mode_frequencies_hz(ax: Axis, force_n: float | None = None) -> tuple[float, float]:
    """Analytic first axial mode and anti-resonance of the undamped two-mass axis, Hz.

    ``force_n`` > 0: at a loaded operating point (the motor side sees ``1/eta`` of the nut force:
    ``w_r^2 = k (a^2 / (eta J_m) + 1/m)``); ``None``: without the loss (``w_r^2 = k (a^2/J_m + 1/m)``).
    The anti-resonance is ``sqrt(k/m)`` either way.
    """
    g = 1.0 / ax.efficiency if force_n is not None and force_n > 0 else 1.0
    k, a, jm, m = ax.stiffness_n_per_m, ax.a, ax.motor_side_inertia_kg_m2, ax.load_mass_kg
    wr = math.sqrt(k * (g * a * a / jm + 1.0 / m))
    war = math.sqrt(k / m)
    return wr / (2.0 * math.pi), war / (2.0 * math.pi)


def schroeder_multisine(n: int, ts: float, period_s: float, f_lo: float, f_hi: float, amplitude: float,
                        n_lines: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A periodic multisine of peak-ish ``amplitude`` on harmonics of ``1/period_s`` in [f_lo, f_hi].

    Schroeder phases (low crest factor). Returns the signal (n samples) and the excited
    frequencies, Hz.
    """
    f0 = 1.0 / period_s
    harm = np.arange(max(1, math.ceil(f_lo / f0)), math.floor(f_hi / f0) + 1)
    if n_lines is not None and harm.size > n_lines:
        idx = np.unique(np.round(np.geomspace(1, harm.size, n_lines)).astype(int) - 1)
        harm = harm[idx]
    t = np.arange(n) * ts
    nl = harm.size
    phases = -math.pi * np.arange(1, nl + 1) * np.arange(nl) / nl
    sig = np.zeros(n)
    for hk, ph in zip(harm, phases):
        sig += np.cos(2.0 * math.pi * hk * f0 * t + ph)
    sig *= amplitude / np.max(np.abs(sig))
    return sig, harm * f0


def write_csv(path, columns: dict, fmt: str = "%.10g") -> None:
    """Write ``columns`` (header -> 1-D array, equal lengths) as a comma-separated file."""
    names = list(columns)
    data = np.column_stack([np.asarray(columns[c], dtype=float) for c in names])
    np.savetxt(path, data, delimiter=",", header=",".join(names), comments="", fmt=fmt)
