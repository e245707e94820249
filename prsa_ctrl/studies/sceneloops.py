"""What the tuning pipeline reads from a scene, read in one place: the scene's loop spec (plain
numbers and the duty cycle's sampled records) and the scene's loop models.

A :class:`~prsa_ctrl.studies.scene.Scene` is a studies-level object; the loop builders of
:mod:`prsa_ctrl.tuning.actuatorloops` take numbers and arrays only. :func:`loop_spec` reads the
scene once, :func:`actuator_loops` hands its numbers to the builders. The verification,
prediction and health checks of :mod:`prsa_ctrl.studies.autotune` read the same spec.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..plant.equilibrium import operating_point
from ..plant.plantfile import Plant
from ..sim.signals import PiecewiseLinear, normalise_profile
from ..tuning.loops import LoopModel
from ..tuning.actuatorloops import profile_loops, step_loops

__all__ = ["LoopSpec", "loop_spec", "linear_fidelity", "duty_record", "actuator_loops"]


@dataclass(frozen=True)
class LoopSpec:
    """Every number the tuning pipeline reads from a scene (frozen), under the scene's names
    so that the studies' helpers read a spec and a scene alike.

    Built by :func:`loop_spec`; the loop models, the prediction, the verification and the
    health checks of :mod:`prsa_ctrl.studies.autotune` read this object instead of the scene.
    """

    setpoint_rad_s: float  #: nut-speed setpoint, rad/s
    initial_load: float  #: axial load before the step (duty cycle: at t = 0), N
    final_loads: tuple[float, ...]  #: axial load after each step, N (one loop per value)
    step_time: float  #: time of the load step, s
    duration: float  #: end of the record, s
    fidelity: str  #: the simulator's fidelity (as resolved by ``choose_fidelity``)
    linear_fidelity: str  #: the fidelity the loop models are linearised at (:func:`linear_fidelity`)
    discrete: bool  #: sampled drive (True) or continuous controller
    estimator: str  #: speed measurement: ``"none"`` or ``"kf"``
    feedforward: bool  #: load feed-forward from the Kalman filter's load estimate
    load_change_time_s: float  #: the Kalman filter's load-change time scale, s
    setpoint_weight: float  #: 2-DOF setpoint weight b
    is_profile: bool  #: a duty cycle rather than load steps
    cases: tuple[str, ...]  #: one label per loop / verified record
    records: tuple[dict, ...]  #: duty cycle: :func:`duty_record` per case (load steps: empty)
    objective: str  #: "ie", "iae", "itae" or "ise"
    aggregate: str  #: "sum" or "worst" over the loops
    goal: str  #: duty cycle: "load", "setpoint" or "mix"
    setpoint_share: float  #: duty cycle, goal "mix": weight of the setpoint record
    controller: str  #: "pi" or "pid"
    ms_max: float  #: peak-sensitivity bound
    mt_max: float | None  #: peak complementary-sensitivity bound
    mks_max: float | None  #: peak noise-sensitivity bound, N m s/rad
    candidates: int  #: designs verified per run
    accuracy: float  #: relative accuracy the verification is held to
    steady_torque_n_m: float  #: motor torque holding the setpoint at the initial load, N m (linear fidelity)
    filters: tuple = ()  #: the drive's loop filters (:class:`~prsa_ctrl.drive.filters.LoopFilter`), in every loop and run


def linear_fidelity(scene) -> str:
    """The fidelity the loop models are linearised at: the scene's, except that the
    multi-roller model (periodic in the cage angle) is replaced by the compliant model, its
    mean behaviour.

    Parameters
    ----------
    scene : Scene or LoopSpec

    Returns
    -------
    str
    """
    if isinstance(scene, LoopSpec):
        return scene.linear_fidelity
    return "compliant" if scene.fidelity in ("multi-roller", "auto") else scene.fidelity


def loop_spec(plant: Plant, scene) -> LoopSpec:
    """Read a scene once: the numbers the loop models, the tuner, the prediction and the
    verification need (a spec is returned as it is).

    Parameters
    ----------
    plant : Plant
        Its sample time sets the duty cycle's records.
    scene : Scene or LoopSpec
        Resolve ``fidelity = "auto"`` first (:func:`~prsa_ctrl.studies.scene.choose_fidelity`)
        when the spec is used for verification.

    Returns
    -------
    LoopSpec
    """
    if isinstance(scene, LoopSpec):
        return scene
    cases = tuple(scene.cases)
    records = tuple(duty_record(plant, scene, case) for case in cases) if scene.is_profile else ()
    lin = linear_fidelity(scene)
    return LoopSpec(
        setpoint_rad_s=scene.setpoint_rad_s, initial_load=scene.initial_load, final_loads=tuple(scene.final_loads),
        step_time=scene.step_time, duration=scene.duration, fidelity=scene.fidelity,
        linear_fidelity=lin, discrete=scene.discrete, estimator=scene.estimator,
        feedforward=scene.feedforward, load_change_time_s=scene.load_change_time_s,
        setpoint_weight=scene.setpoint_weight, is_profile=scene.is_profile, cases=cases, records=records,
        objective=scene.objective, aggregate=scene.aggregate, goal=scene.goal, setpoint_share=scene.setpoint_share,
        controller=scene.controller, ms_max=scene.ms_max, mt_max=scene.mt_max, mks_max=scene.mks_max,
        candidates=scene.candidates, accuracy=scene.accuracy,
        steady_torque_n_m=operating_point(plant, scene.setpoint_rad_s, scene.initial_load, lin).torque,
        filters=tuple(getattr(scene, "filters", ())))


def actuator_loops(plant: Plant, scene, estimator: str | None = None) -> list[LoopModel]:
    """One loop model per final load, linearised at the mid load of the step (the response
    to a step is the same from any linearisation point; the mid load keeps the Jacobians
    closest to both ends); a duty cycle: one per record, linearised at the middle of its
    range. ``estimator`` (default: the scene's) selects the speed measurement: ``"none"`` for
    the drive's filtered difference, ``"kf"`` for the Kalman filter (with the load
    feed-forward gain as a fourth tuned gain when the scene asks for feed-forward).

    Parameters
    ----------
    plant : Plant
    scene : Scene or LoopSpec
    estimator : {"none", "kf"}, optional

    Returns
    -------
    list of LoopModel
        Sampled drive loops (``scene.discrete``) or continuous loops, one per final load or record.
    """
    spec = loop_spec(plant, scene)
    estimator = spec.estimator if estimator is None else estimator
    if spec.is_profile:
        return profile_loops(plant, [(case, rec["w_lin"], rec["f_lin"], rec["load_sequence"], rec["setpoint_sequence"])
                                     for case, rec in zip(spec.cases, spec.records)],
                             fidelity=spec.linear_fidelity, horizon_s=spec.duration,
                             setpoint_weight=spec.setpoint_weight, filters=spec.filters)
    return step_loops(plant, setpoint_rad_s=spec.setpoint_rad_s, initial_load_n=spec.initial_load,
                      final_loads_n=spec.final_loads, fidelity=spec.linear_fidelity,
                      horizon_s=spec.duration - spec.step_time, discrete=spec.discrete,
                      kf_load_change_time_s=spec.load_change_time_s if estimator == "kf" else None,
                      feedforward=spec.feedforward, filters=spec.filters)


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
