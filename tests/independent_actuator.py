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
