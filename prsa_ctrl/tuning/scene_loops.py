"""Loop models of an actuator scene: the sampled (or continuous) speed loop linearised at each
load step's mid load, or over each record of a duty cycle.

The builders the tuners, the robust study and the verification share (:func:`actuator_loops`,
:func:`duty_record`); a scene is read through its attributes (``final_loads``, ``estimator``,
``is_profile``, ...), so this module needs nothing from :mod:`prsa_ctrl.studies`.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from .._lazy import module
from ..drive.estimator import KFDesign, design_kf
from ..drive.sampled import freq_grid, pid_frequency_parts, pid_rows, ss_response, zoh
from ..options import DERIVATIVE_FILTER_SAMPLES
from ..plant.linear import linear_core
from ..plant.model import plant_model
from ..plant.plantfile import Plant
from ..sim.signals import PiecewiseLinear, normalise_profile
from .loops import LoopModel
from .builders import continuous_loop, drive_loop

__all__ = ["actuator_loops", "duty_record", "linear_fidelity", "derivative_filter_s", "kf_drive_loop"]

control = module("control")


def derivative_filter_s(plant: Plant) -> float:
    """Derivative-filter time constant of the tuned PID, s (``DERIVATIVE_FILTER_SAMPLES``
    controller samples)."""
    return DERIVATIVE_FILTER_SAMPLES * plant.sample_time_s


def linear_fidelity(scene) -> str:
    """The fidelity the loop models are linearised at: the scene's, except that the
    multi-roller model (periodic in the cage angle) is replaced by the compliant model, its
    mean behaviour."""
    return "compliant" if scene.fidelity in ("multi-roller", "auto") else scene.fidelity


def actuator_loops(plant: Plant, scene, estimator: str | None = None) -> list[LoopModel]:
    """One loop model per final load, linearised at the mid load of the step (the response
    to a step is the same from any linearisation point; the mid load keeps the Jacobians
    closest to both ends). ``estimator`` (default: the scene's) selects the speed measurement:
    ``"none"`` for the drive's filtered difference, ``"kf"`` for the Kalman filter (with the
    load feed-forward gain as a fourth tuned gain when the scene asks for feed-forward).

    Parameters
    ----------
    plant : Plant
    scene : Scene
    estimator : {"none", "kf"}, optional

    Returns
    -------
    list of LoopModel
        Sampled drive loops (``scene.discrete``) or continuous loops, one per final load.
    """
    estimator = scene.estimator if estimator is None else estimator
    kf = None
    if estimator == "kf":
        if plant.command_delay_samples:  # kf_drive_loop models the one-sample computation delay only
            raise ValueError(f"estimator 'kf' with drive.command_delay_samples = {plant.command_delay_samples}; "
                             "expected no command delay (the Kalman-filter loop model does not model it)")
        kf = design_kf(plant, scene.load_change_time_s)
    fidelity = linear_fidelity(scene)
    model = plant_model(plant, fidelity)
    i_speed = model.output_names.index("nut_speed")
    i_torque = model.output_names.index("motor_torque")
    if scene.is_profile:
        loops = []
        for case in scene.cases:
            rec = duty_record(plant, scene, case)
            a, b, c, _, _ = linear_core(plant, rec["w_lin"], rec["f_lin"], fidelity)
            loops.append(drive_loop(
                a, b, c[i_speed], model.index("theta_nut"), ts=plant.sample_time_s, speed_filter=plant.speed_filter_s,
                tf=derivative_filter_s(plant), horizon=scene.duration, name=case,
                outputs={"nut_speed": c[i_speed], "motor_torque": c[i_torque]},
                load_sequence=rec["load_sequence"], setpoint_sequence=rec["setpoint_sequence"],
                setpoint_weight=scene.setpoint_weight, command_delay_samples=plant.command_delay_samples))
        return loops
    horizon = scene.duration - scene.step_time
    loops = []
    for f1 in scene.final_loads:
        a, b, c, _, _ = linear_core(plant, scene.setpoint_rad_s, 0.5 * (scene.initial_load + f1), fidelity)
        step = f1 - scene.initial_load
        if kf is not None:
            loops.append(
                kf_drive_loop(
                    a, b, c[i_speed], model.index("theta_nut"), kf, tf=derivative_filter_s(plant), horizon=horizon,
                    step=step, feedforward=scene.feedforward, name=f"step to {f1:g} N (KF)",
                    outputs={"nut_speed": c[i_speed], "motor_torque": c[i_torque]},
                )
            )
        elif scene.discrete:
            loops.append(
                drive_loop(
                    a, b, c[i_speed], model.index("theta_nut"),
                    ts=plant.sample_time_s, speed_filter=plant.speed_filter_s, tf=derivative_filter_s(plant),
                    horizon=horizon, step=step, name=f"step to {f1:g} N",
                    outputs={"nut_speed": c[i_speed], "motor_torque": c[i_torque]},
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


def _n_samples(plant: Plant, scene) -> int:
    return max(10, int(round(scene.duration / plant.sample_time_s)))


def duty_record(plant: Plant, scene, case: str) -> dict:
    """One record of a duty-cycle scene, as the loop model and the verification see it.

    Parameters
    ----------
    plant : Plant
    scene : Scene
        A duty-cycle scene (``scene.is_profile``).
    case : {"load profile", "setpoint profile"}
        One of ``scene.cases``.

    Returns
    -------
    dict
        ``load`` and ``setpoint`` (simulator profiles, N and rad/s), ``load_sequence`` (mean
        load deviation over each controller sample, N, or None), ``setpoint_sequence``
        (setpoint deviation the controller reads at each sample, rad/s, or None), ``t``
        (sample times, s), ``setpoint_at`` (setpoint at them, rad/s), ``load_steps`` ((time s,
        signed size N) of each load step), ``breaks`` (every change, s) and the linearisation
        point ``w_lin`` (rad/s), ``f_lin`` (N): the middle of the profile's range.
    """
    ts = plant.sample_time_s
    n = _n_samples(plant, scene)
    t = ts * np.arange(n + 1)
    w0, f0 = scene.setpoint_rad_s, scene.initial_load
    out: dict = {"t": t, "load_sequence": None, "setpoint_sequence": None, "load_steps": [], "breaks": [],
                 "load": f0, "setpoint": w0, "w_lin": w0, "f_lin": f0}
    if case == "load profile":
        pts = scene.load_profile
        prof = normalise_profile(PiecewiseLinear(pts), scene.duration + 1.0, "load", "N")
        # Exact mean over each sample interval: integral of the piecewise-linear load.
        edges = ts * np.arange(n + 1)
        seg_len = np.append(np.diff(prof.t), np.inf)
        lens = np.clip(edges[:, None] - prof.t[None, :], 0.0, seg_len[None, :])
        integral = lens @ prof.v + (lens * lens) @ prof.s / 2.0
        out["load_sequence"] = np.diff(integral) / ts - f0
        out["load"] = PiecewiseLinear(pts)
        out["load_steps"] = [(float(tk), float(prof.v[i] - prof.at(tk - 1e-9)))
                             for i, tk in enumerate(prof.t) if prof.jump[i]]
        out["breaks"] = [float(x) for x in prof.t[1:]]
        vals = [v for _, v in pts]
        out["f_lin"] = 0.5 * (min(vals) + max(vals))
        out["setpoint_at"] = np.full(n + 1, w0)
    else:
        pts = scene.setpoint_profile
        prof = normalise_profile(PiecewiseLinear(pts), scene.duration + 1.0, "setpoint", "rad/s")
        r = prof.at(t)
        out["setpoint_sequence"] = r - w0
        out["setpoint_sequence"][0] = 0.0
        out["setpoint"] = PiecewiseLinear(pts)
        out["breaks"] = [float(x) for x in prof.t[1:]]
        vals = [v for _, v in pts]
        out["w_lin"] = 0.5 * (min(vals) + max(vals))
        out["setpoint_at"] = r
    return out


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
