"""An actuator simulator written independently of prsa_ctrl's model and simulator (plain scipy).

Same physics as the rigid fidelity, written from the plant's physical meaning rather than from
prsa_ctrl.plant.model: one rotating inertia (nut + rotor + reflected cage/rollers + screw mass), a
first-order current loop on the saturated command, the axial load through the lead, thread
friction that gives the forward efficiency at speed, a no-load drag torque and a viscous torque.
Different on purpose: the friction sign is smoothed with ``w / sqrt(w^2 + eps^2)`` (not tanh),
there is no Stribeck stiction peak, the speed loop is a plain sampled PI written here, and the
recorded load carries load-cell noise. Integration: ``scipy.integrate.solve_ivp`` (LSODA, stiff-switching) per
sample with the command held.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.integrate import solve_ivp


def simulate_independent(
    *,
    inertia_kg_m2: float,
    lead_m: float,
    efficiency: float,
    no_load_torque_n_m: float,
    viscous_n_m_s_per_rad: float,
    current_loop_bandwidth_hz: float,
    torque_limit_n_m: float,
    setpoint_rad_s: np.ndarray,
    load_n: np.ndarray,
    sample_time_s: float,
    kp: float = 0.05,
    ki: float = 2.0,
    encoder_counts: int = 2**20,
    load_cell_noise_n: float = 5.0,
    friction_eps_rad_s: float = 0.05,
    seed: int = 0,
) -> dict:
    """Closed-loop record: arrays ``time_s, torque_command_n_m, nut_angle_rad, axial_load_n``.

    ``setpoint_rad_s`` and ``load_n`` give one value per sample; the load acts on the plant as
    given and is recorded with Gaussian load-cell noise (N RMS).
    """
    rng = np.random.default_rng(seed)
    a = lead_m / (2 * math.pi)
    wc = 2 * math.pi * current_loop_bandwidth_hz
    n = len(setpoint_rad_s)
    q = 2 * math.pi / encoder_counts

    def sgn(w):
        return w / math.sqrt(w * w + friction_eps_rad_s**2)

    def rhs(_t, x, u, f):
        th, w, tau = x
        load_torque = f * a
        friction = abs(f) * a * (1.0 / efficiency - 1.0) * sgn(w)
        drag = no_load_torque_n_m * sgn(w) + viscous_n_m_s_per_rad * w
        return [w, (tau - load_torque - friction - drag) / inertia_kg_m2,
                wc * (min(max(u, -torque_limit_n_m), torque_limit_n_m) - tau)]

    # Steady start at the first setpoint: torque balances load, friction and drag.
    w0 = float(setpoint_rad_s[0])
    f0 = float(load_n[0])
    tau0 = f0 * a + abs(f0) * a * (1 / efficiency - 1) * sgn(w0) + no_load_torque_n_m * sgn(w0) + viscous_n_m_s_per_rad * w0
    x = np.array([0.0, w0, tau0])
    integral = tau0
    theta_prev = math.floor(-w0 * sample_time_s / q) * q
    u_pending = tau0
    t = np.arange(n) * sample_time_s
    cmd = np.empty(n)
    ang = np.empty(n)
    for k in range(n):
        theta_q = math.floor(x[0] / q) * q
        ang[k] = theta_q
        w_meas = (theta_q - theta_prev) / sample_time_s
        theta_prev = theta_q
        err = float(setpoint_rad_s[k]) - w_meas
        u_new = kp * err + integral
        integral += ki * err * sample_time_s
        u = u_pending  # one-sample computation delay: apply the previous command
        cmd[k] = u
        sol = solve_ivp(rhs, (0.0, sample_time_s), x, method="LSODA", rtol=1e-9, atol=[1e-11, 1e-8, 1e-9],
                        args=(u, float(load_n[k])))
        if not sol.success:  # the reference checks itself: a failed step is never a record
            raise AssertionError(f"independent_actuator: solve_ivp failed in sample {k}: {sol.message}")
        x = sol.y[:, -1]
        u_pending = u_new
    return {
        "time_s": t,
        "torque_command_n_m": cmd,
        "nut_angle_rad": ang,
        "axial_load_n": np.asarray(load_n, float) + load_cell_noise_n * rng.standard_normal(n),
    }


def multisine_load_step_record(truth, sample_time_s: float = 2.5e-4, *, inertia_factor: float = 1.0,
                               name: str = "independent", seed: int = 1):
    """The identification tests' independent log of ``truth`` (a prsa_ctrl ``Plant``): 0.4 s of a
    5..150 Hz speed multisine (20 rad/s around 30 rad/s) under axial-load steps 200 -> 1500 -> 300
    -> 2500 N, simulated by :func:`simulate_independent` (``inertia_factor`` times the truth's
    reflected inertia, efficiency 0.88, drag 0.03 N m, viscous 1.5e-4 N m s/rad, current loop
    1200 Hz, noise ``seed``), named ``name``. Only the excitation's design and the record
    container are prsa_ctrl's; the dynamics are this module's."""
    from prsa_ctrl.identification.data import design_excitation, record_from_arrays

    ts = sample_time_s
    n = int(round(0.4 / ts))
    t = np.arange(n) * ts
    _, sp = design_excitation("multisine", duration_s=n * ts, sample_time_s=ts, f_min_hz=5, f_max_hz=150,
                              amplitude=20, offset=30)
    load = np.select([t < 0.1, t < 0.2, t < 0.3], [200.0, 1500.0, 300.0], 2500.0)
    d = simulate_independent(
        inertia_kg_m2=inertia_factor * truth.reflected_inertia_kg_m2, lead_m=truth.lead_m, efficiency=0.88,
        no_load_torque_n_m=0.03, viscous_n_m_s_per_rad=1.5e-4, current_loop_bandwidth_hz=1200.0,
        torque_limit_n_m=truth.torque_limit, setpoint_rad_s=sp, load_n=load, sample_time_s=ts, seed=seed)
    return record_from_arrays(name, d["time_s"], d["torque_command_n_m"], nut_angle_rad=d["nut_angle_rad"],
                              axial_load_n=d["axial_load_n"])


def two_mass_eom_response(f_hz, jm, jl, k, c, b=0.0, fc_hz=math.inf, delay_s=0.0):
    """Motor speed / torque command ((rad/s)/(N m)) of two inertias ``jm``, ``jl`` (kg m^2) on a
    spring ``k`` (N m/rad) and damper ``c`` (N m s/rad), viscous ``b`` on the motor side, a
    first-order current loop ``fc_hz`` and a delay: ``[Jm s + b + Z, -Z; -Z, Jl s + Z] [wm, wl] =
    [tau, 0]`` with ``Z = c + k / s``, solved at each frequency (not prsa_ctrl's closed form)."""
    out = []
    for fi in np.asarray(f_hz, float):
        s = 1j * 2 * math.pi * fi
        z = c + k / s
        w = np.linalg.solve(np.array([[jm * s + b + z, -z], [-z, jl * s + z]]), np.array([1.0, 0.0]))
        out.append(w[0] / (1 + s / (2 * math.pi * fc_hz)) * np.exp(-s * delay_s))
    return np.array(out)


def modal_damper(k, jm, jl, zeta):
    """The damper (N m s/rad) that gives the two-mass mode the damping ratio ``zeta``."""
    return 2 * zeta * math.sqrt(k * jm * jl / (jm + jl))
