"""Loop models of an actuator scene: the sampled (or continuous) speed loop linearised at each
load step's mid load, or over each record of a duty cycle.

The builders the tuners, the robust study and the verification share (:func:`actuator_loops`,
:func:`duty_record`); a scene is read through its attributes (``final_loads``, ``estimator``,
``is_profile``, ...), so this module needs nothing from :mod:`prsa_ctrl.studies`.
"""

from __future__ import annotations

import numpy as np

from .._lazy import module
from ..drive.estimator import design_kf, kf_drive_loop
from ..options import DERIVATIVE_FILTER_SAMPLES
from ..plant.linear import linear_core
from ..plant.model import plant_model
from ..plant.plantfile import Plant
from ..sim.signals import PiecewiseLinear, normalise_profile
from .tuner import LoopModel, continuous_loop, drive_loop

__all__ = ["actuator_loops", "duty_record", "linear_fidelity", "derivative_filter_s"]

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
                setpoint_weight=scene.setpoint_weight))
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
