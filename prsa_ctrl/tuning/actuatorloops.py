"""Loop models of the actuator's speed loop from numbers: the sampled (or continuous) loop
linearised at each load step's mid load (:func:`step_loops`), or over each record of a duty
cycle (:func:`profile_loops`), and the sampled loop with the Kalman filter (:func:`kf_drive_loop`).

The builders take numbers and arrays only; a scene is read in :mod:`prsa_ctrl.studies.sceneloops`
(:func:`~prsa_ctrl.studies.sceneloops.loop_spec`, :func:`~prsa_ctrl.studies.sceneloops.actuator_loops`).
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from .._lazy import module
from ..drive.estimator import KFDesign, design_kf
from ..drive.sampled import freq_grid, pid_frequency_parts, pid_rows, ss_response, zoh
from ..options import DERIVATIVE_FILTER_SAMPLES
from ..plant.linear import linear_core
from ..plant.model import plant_model
from ..plant.plantfile import Plant
from .loops import LoopModel
from .builders import continuous_loop, drive_loop

__all__ = ["step_loops", "profile_loops", "derivative_filter_s", "kf_drive_loop"]

control = module("control")


def derivative_filter_s(plant: Plant) -> float:
    """Derivative-filter time constant of the tuned PID, s (``DERIVATIVE_FILTER_SAMPLES``
    controller samples)."""
    return DERIVATIVE_FILTER_SAMPLES * plant.sample_time_s


def step_loops(plant: Plant, *, setpoint_rad_s: float, initial_load_n: float, final_loads_n: Sequence[float],
               fidelity: str, horizon_s: float, discrete: bool = True, kf_load_change_time_s: float | None = None,
               feedforward: bool = False, filters: Sequence = ()) -> list[LoopModel]:
    """One loop model per final load, linearised at the mid load of the step (the response
    to a step is the same from any linearisation point; the mid load keeps the Jacobians
    closest to both ends).

    Parameters
    ----------
    plant : Plant
    setpoint_rad_s : float, rad/s
        Nut-speed setpoint (the linearisation speed).
    initial_load_n : float, N
        Axial load before the step.
    final_loads_n : sequence of float, N
        Axial load after each step; one loop per value.
    fidelity : str
        Fidelity of the linearised plant model.
    horizon_s : float, s
        Horizon of the objective after the step.
    discrete : bool
        The sampled drive loop (default) or the continuous controller.
    kf_load_change_time_s : float, s, optional
        With a value: the speed is measured by the Kalman filter designed for this load-change
        time scale (:func:`prsa_ctrl.drive.estimator.design_kf`; sampled loops only).
    feedforward : bool
        With the Kalman filter: tune the load feed-forward gain as a fourth gain.
    filters : sequence of LoopFilter
        The drive's speed-measurement and torque-command filters (sampled loops without the
        Kalman filter only; :func:`prsa_ctrl.tuning.builders.drive_loop`).

    Returns
    -------
    list of LoopModel
    """
    kf = None
    if filters and (kf_load_change_time_s is not None or not discrete):
        raise ValueError("filters: expected a sampled loop without the Kalman filter (the Kalman-filter and the "
                         "continuous loops have no loop filters)")
    if kf_load_change_time_s is not None:
        if plant.command_delay_samples:  # kf_drive_loop models the one-sample computation delay only
            raise ValueError(f"estimator 'kf' with drive.command_delay_samples = {plant.command_delay_samples}; "
                             "expected no command delay (the Kalman-filter loop model does not model it)")
        kf = design_kf(plant, kf_load_change_time_s)
    model = plant_model(plant, fidelity)
    i_speed = model.output_names.index("nut_speed")
    i_torque = model.output_names.index("motor_torque")
    horizon = horizon_s
    # The plant linearised at every step's mid load, then the loop models.
    cores = [linear_core(plant, setpoint_rad_s, 0.5 * (initial_load_n + f1), fidelity)[:3] for f1 in final_loads_n]
    loops = []
    for f1, (a, b, c) in zip(final_loads_n, cores):
        step = f1 - initial_load_n
        if kf is not None:
            loops.append(
                kf_drive_loop(
                    a, b, c[i_speed], model.index("theta_nut"), kf, tf=derivative_filter_s(plant), horizon=horizon,
                    step=step, feedforward=feedforward, name=f"step to {f1:g} N (KF)",
                    outputs={"nut_speed": c[i_speed], "motor_torque": c[i_torque]},
                )
            )
        elif discrete:
            loops.append(
                drive_loop(
                    a, b, c[i_speed], model.index("theta_nut"),
                    ts=plant.sample_time_s, speed_filter=plant.speed_filter_s, tf=derivative_filter_s(plant),
                    horizon=horizon, step=step, name=f"step to {f1:g} N",
                    outputs={"nut_speed": c[i_speed], "motor_torque": c[i_torque]}, filters=filters,
                    command_delay_samples=plant.command_delay_samples,
                )
            )
        else:
            t_f = plant.speed_filter_s
            # The continuous controller measures speed, never the angle: the nut-angle state is
            # a pure integrator nothing depends on (its column is zero) and would leave a pole
            # at exactly 0 for every gain, so it is removed.
            i_th = model.index("theta_nut")
            if np.any(a[:, i_th] != 0) or np.any(c[:, i_th] != 0):
                raise ArithmeticError("the linearised plant depends on the absolute nut angle")
            keep = [i for i in range(a.shape[0]) if i != i_th]
            a, b, c = a[np.ix_(keep, keep)], b[keep], c[:, keep]
            n = a.shape[0]
            # Plant plus speed filter; the filtered speed is fed back.
            aa = np.block([[a, np.zeros((n, 1))], [c[i_speed][None, :] / t_f, -np.ones((1, 1)) / t_f]])
            bb = np.vstack([b, np.zeros((1, 2))])
            cc = np.concatenate([np.zeros(n), [1.0]])[None, :]
            sys = control.ss(aa, bb, cc, np.zeros((1, 2)))
            loops.append(continuous_loop(sys, tf=derivative_filter_s(plant), horizon=horizon, n_steps=int(round(horizon / 1e-4)), step=step))
    return loops


def profile_loops(plant: Plant, records: Sequence[tuple], *, fidelity: str, horizon_s: float,
                  setpoint_weight: float = 1.0, filters: Sequence = ()) -> list[LoopModel]:
    """One sampled loop model per duty-cycle record, linearised at the middle of its range.

    Parameters
    ----------
    plant : Plant
    records : sequence of (name, w_lin, f_lin, load_sequence, setpoint_sequence)
        Per record: its name, the linearisation point (rad/s, N), the mean load deviation over
        each controller sample (N, or None) and the setpoint deviation the controller reads at
        each sample (rad/s, or None).
    fidelity : str
        Fidelity of the linearised plant model.
    horizon_s : float, s
        Length of each record.
    setpoint_weight : float
        2-DOF setpoint weight b.
    filters : sequence of LoopFilter
        The drive's speed-measurement and torque-command filters.

    Returns
    -------
    list of LoopModel
    """
    model = plant_model(plant, fidelity)
    i_speed = model.output_names.index("nut_speed")
    i_torque = model.output_names.index("motor_torque")
    cores = [linear_core(plant, w_lin, f_lin, fidelity)[:3] for _, w_lin, f_lin, _, _ in records]
    loops = []
    for (name, _, _, load_sequence, setpoint_sequence), (a, b, c) in zip(records, cores):
        loops.append(drive_loop(
            a, b, c[i_speed], model.index("theta_nut"), ts=plant.sample_time_s, speed_filter=plant.speed_filter_s,
            tf=derivative_filter_s(plant), horizon=horizon_s, name=name,
            outputs={"nut_speed": c[i_speed], "motor_torque": c[i_torque]},
            load_sequence=load_sequence, setpoint_sequence=setpoint_sequence,
            setpoint_weight=setpoint_weight, filters=filters, command_delay_samples=plant.command_delay_samples))
    return loops


def kf_drive_loop(a, b, c_speed, angle_index: int, kf: KFDesign, *, tf: float, horizon: float, step: float,
                  feedforward: bool, omega: NDArray | None = None, name: str = "drive+KF",
                  outputs: dict | None = None):
    """Loop model of the sampled drive with the Kalman filter in the loop (see
    :func:`prsa_ctrl.tuning.builders.drive_loop` for the plain one).

    Parameters
    ----------
    a, b : ndarray
        Continuous plant Jacobians with the nut angle kept (inputs torque command, load).
    c_speed : ndarray
        Output row of the nut speed.
    angle_index : int
        Index of the nut angle state.
    kf : KFDesign
    tf : float, s
        Derivative-filter time constant.
    horizon : float, s
    step : float, N
        Load step of the objective's disturbance.
    feedforward : bool
        Tune the load feed-forward gain ``kff`` as a fourth gain.
    omega : array, rad/s, optional
        Frequency grid (default up to the Nyquist frequency).
    name : str
    outputs : dict, optional
        Extra output rows to record along the trajectory.

    Per sample: the filter updates with the angle, the PID acts on the estimated speed (plus the
    estimated load torque if ``feedforward``), the command is applied one sample later, and the
    filter predicts with the applied command. The absolute angle and its estimate drift
    together; the loop keeps only the estimation error of the angle. With ``feedforward`` the
    load feed-forward gain ``kff`` is a fourth tuned gain (``u += kff * load estimate``).
    """

    ts = kf.ts
    n_steps = max(10, int(round(horizon / ts)))
    ad, bd_all = zoh(np.asarray(a, float), np.asarray(b, float), ts)
    bu, bdist = bd_all[:, 0], bd_all[:, 1]
    n = ad.shape[0]
    c_w = np.asarray(c_speed, float).ravel()
    c_th = np.eye(n)[angle_index]
    beta = math.exp(-ts / tf)
    K = kf.K.ravel()
    # Full coordinates X = [x (plant, with angle), xh (prior estimate, 4), d, I, w_prev, u_pending]
    ix = slice(0, n)
    i_d, i_i, i_wp, i_u = n + 4, n + 5, n + 6, n + 7
    N = n + 8
    E = np.eye(N)
    innov = np.zeros(N)
    innov[ix] = c_th
    innov[n] = -1.0  # theta - theta_hat
    post = [E[n + r] + K[r] * innov for r in range(4)]  # posterior estimate rows
    w_hat, tl_hat = post[1], post[3]
    d_new = beta * E[i_d] + (1 - beta) * (w_hat - E[i_wp]) / ts
    e_meas = -w_hat
    A0 = np.zeros((N, N))
    A0[ix, ix] = ad
    A0[ix, i_u] = bu
    for r in range(4):
        A0[n + r] = sum(kf.F[r, c] * post[c] for c in range(4)) + kf.G[r, 0] * E[i_u]
    A0[i_d] = d_new
    A0[i_i, i_i] = 1.0
    A0[i_wp] = w_hat
    A0[i_u] = E[i_i]  # u = kp e + I - kd d (+ kff * load estimate)
    a_kp, a_ki, a_kd = pid_rows(N, i_u, i_i, e_meas, d_new, ts)
    a_ff = np.zeros((N, N))
    a_ff[i_u] = tl_hat
    gain_mats = (A0, a_kp, a_ki, a_kd) + ((a_ff,) if feedforward else ())
    bdv = np.zeros(N)
    bdv[ix] = bdist * step
    ce = np.zeros(N)
    ce[ix] = -c_w
    # Drop the common drift: replace theta_hat by eps = theta_hat - theta, then delete theta.
    M = np.eye(N)
    M[n, angle_index] = -1.0
    Mi = np.linalg.inv(M)
    keep = [i for i in range(N) if i != angle_index]
    mats = []
    for A_ in gain_mats:
        At = M @ A_ @ Mi
        col = np.delete(At[:, angle_index], angle_index)
        if np.max(np.abs(col)) > 1e-9 * max(1.0, np.max(np.abs(At))):
            raise ArithmeticError("the loop depends on the absolute angle; expected only angle differences")
        mats.append(At[np.ix_(keep, keep)])
    bdv = (M @ bdv)[keep]
    ce = (ce @ Mi)[keep]
    extra = {}
    for k, r in (outputs or {}).items():
        row = np.zeros(N)
        row[ix] = np.asarray(r, float).ravel()
        extra[k] = (row @ Mi)[keep]
    # Frequency response: L = N/D with N, D affine in the gains (see LoopModel), at any
    # frequencies (the tuner refines its Ms search off the grid).
    if omega is None:
        omega = freq_grid(1e-1, math.pi / ts * 0.999, 500)
    a_kf = kf.F @ (np.eye(4) - np.outer(K, kf.H.ravel()))
    b_th, b_u = kf.F @ K, kf.G.ravel()
    ikh = np.eye(4) - np.outer(K, kf.H.ravel())

    def response(w):
        w = np.atleast_1d(np.asarray(w, dtype=float))
        zi = np.exp(-1j * w * ts)

        def z_of(x):
            return np.exp(1j * x * ts)

        p_th = ss_response(ad, bu[:, None], c_th[None, :], w, z_of)  # applied torque -> angle

        def kf_tf(row, b_in, d_in):
            return ss_response(a_kf, b_in[:, None], (row @ ikh)[None, :], w, z_of) + d_in

        h_wt, h_wu = kf_tf(np.eye(4)[1], b_th, K[1]), kf_tf(np.eye(4)[1], b_u, 0.0)
        h_lt, h_lu = kf_tf(np.eye(4)[3], b_th, K[3]), kf_tf(np.eye(4)[3], b_u, 0.0)
        c = pid_frequency_parts(zi, ts, beta)
        Lg = [ci * h_wt * p_th * zi for ci in c]
        Dg = [ci * h_wu * zi for ci in c]
        if feedforward:  # u += kff * load estimate
            Lg.append(-h_lt * p_th * zi)
            Dg.append(-h_lu * zi)
        return None, np.vstack(Lg), None, np.vstack(Dg)

    _, L, _, D = response(omega)
    return LoopModel(mats[0], tuple(mats[1:]), bdv, ce, ts, n_steps, omega, L, tf, name=name,
                     outputs=extra, N0=None, D0=None, D=D, response=response, nyquist=math.pi / ts)
