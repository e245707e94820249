"""The toolkit's main job: tune the actuator's speed loop for a load-step or duty-cycle scene,
verify the best candidates and the baselines on the nonlinear simulator, and report predicted
against verified metrics.

A duty-cycle scene (:attr:`Scene.is_profile`) is tuned on its actual profile: the sampled loop
model takes the load as its mean over every controller sample and the setpoint as the
controller reads it at every sample (:func:`prsa_ctrl.tuning.tuner.drive_loop`), and the
verification runs the nonlinear simulator on the same profile. A 2-DOF setpoint weight
``b != 1`` is verified as the equivalent 1-DOF loop behind the reference prefilter
``F(z) = (b kp (1 - z^-1) + Ts ki z^-1) / (kp (1 - z^-1) + Ts ki z^-1)`` (identical while the
torque is not saturated; the simulator's back-calculation anti-windup then acts on the
prefiltered error)."""

from __future__ import annotations

import math
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from ..drive.pid import PID
from ..plant.linear import linear_core
from ..sim.metrics import LoadStepMetrics, Margins, ProfileMetrics, load_step_metrics, profile_metrics, relative_difference
from ..plant.model import plant_model
from ..options import DERIVATIVE_FILTER_SAMPLES, RAD_S_PER_RPM
from .paper import default_pid
from ..plant.plantfile import Plant
from .scene import PRE_EVENT_SAMPLES, Scene, choose_fidelity
from ..sim.simulate import SimSettings, run
from ..tuning.tuner import LoopModel, Tuner, continuous_loop, drive_loop

__all__ = ["Design", "ActuatorTuning", "tune_actuator", "actuator_loops", "baseline_designs", "duty_record",
           "setpoint_prefilter"]

#: Samples of steady state simulated before the step (the run starts in equilibrium).
_PRE_SAMPLES = PRE_EVENT_SAMPLES
#: Relative disagreement between predicted and verified objective that triggers a warning.
PREDICTION_TOLERANCE = 0.10
#: A verified run that holds the torque at its limit for more than this fraction of the time
#: after the step is flagged.
SATURATION_FRACTION = 0.10
#: A duty-cycle record whose mean error over its last 10 % exceeds this fraction of its peak
#: error has not settled after the last change of the profile (flagged).
DUTY_SETTLE_BAND = 0.05


@dataclass
class Design:
    """One controller with its predicted (linear) and verified (nonlinear) load-step metrics.

    ``predicted`` / ``verified`` hold one :class:`LoadStepMetrics` per final load of the scene;
    ``objective_*`` aggregate them as the scene says (sum or worst).
    """

    name: str
    pid: PID
    margins: Margins
    predicted: list[LoadStepMetrics] = field(default_factory=list)
    verified: list[LoadStepMetrics] = field(default_factory=list)
    objective_predicted: float = math.nan
    objective_verified: float = math.nan
    verified_runs: list = field(default_factory=list, repr=False)
    predicted_error: list = field(default_factory=list, repr=False)
    predicted_h: float = math.nan
    predicted_start_speed: float = math.nan  # rad/s before the step (below the setpoint for P-only)
    estimator: str = "none"
    estimation: list = field(default_factory=list)  # per step: speed RMS errors (rad/s)
    flags: list[str] = field(default_factory=list)  # health checks the verified runs failed
    tuner_status: str = "optimal"  # the tuner's status for tuned designs (see TuningResult.status)

    @property
    def healthy(self) -> bool:
        """Whether the verified runs passed every health check (see :func:`health_flags`)."""
        return not self.flags

    def as_dict(self) -> dict:
        return {
            "name": self.name,
            "gains": self.pid.as_dict(),
            "margins": self.margins.as_dict(),
            "predicted": self.predicted[0].as_dict() if self.predicted else None,
            "verified": self.verified[0].as_dict() if self.verified else None,
            "per_step": {
                "predicted": [m.as_dict() for m in self.predicted],
                "verified": [m.as_dict() for m in self.verified],
            },
            "objective_predicted": self.objective_predicted,
            "objective_verified": self.objective_verified,
            "estimator": self.estimator,
            "estimation": self.estimation,
            "flags": list(self.flags),
        }


@dataclass
class ActuatorTuning:
    """Report of :func:`tune_actuator`."""

    plant: Plant
    scene: Scene
    best: Design
    candidates: list[Design]
    baselines: list[Design]
    comparisons: list[dict]
    timing_s: dict[str, float]
    solver: dict
    warnings: list[str]
    loops: list = field(default_factory=list, repr=False)
    fidelity_reason: str = ""

    @property
    def beats_all_baselines(self) -> bool:
        return all(c["beaten"] for c in self.comparisons)

    @property
    def status(self) -> str:
        """``"ok"``, or ``"flagged: ..."`` when every candidate failed a health check and the
        reported best is only the least bad of them."""
        return "ok" if self.best.healthy else "flagged: " + "; ".join(self.best.flags)

    def as_dict(self) -> dict:
        b = self.best
        return {
            "status": self.status,
            "plant": self.plant.name,
            "scene": self.scene.as_dict(),
            "gains": b.pid.as_dict(),
            "units": {"kp": "N m s/rad", "ki": "N m/rad", "kd": "N m s^2/rad", "tf": "s", "kff": "1"},
            "sample_time_s": self.plant.sample_time_s if self.scene.discrete else None,
            "integral_time_s": b.pid.kp / b.pid.ki if b.pid.ki > 0 else None,
            "gains_per_rpm": {"kp_n_m_per_rpm": b.pid.kp * RAD_S_PER_RPM,
                              "ki_n_m_per_rev": b.pid.ki * 2.0 * math.pi,
                              "kd_n_m_s_per_rpm": b.pid.kd * RAD_S_PER_RPM},
            "estimator": {"kind": self.scene.estimator, "feedforward": self.scene.feedforward,
                          "estimation": b.estimation},
            "objective": self.scene.objective,
            "predicted": b.predicted[0].as_dict(),
            "verified": b.verified[0].as_dict(),
            "margins": b.margins.as_dict(),
            "best": b.as_dict(),
            "candidates": [c.as_dict() for c in self.candidates],
            "baselines": [d.as_dict() for d in self.baselines],
            "comparisons": self.comparisons,
            "beats_all_baselines": self.beats_all_baselines,
            "solver": self.solver,
            "timing_s": self.timing_s,
            "verification": {"fidelity": self.fidelity_reason, "discrete": self.scene.discrete,
                             "tolerance": verify_settings(self.scene).rtol},
            "warnings": self.warnings,
        }


def _tf_default(plant: Plant) -> float:
    """Derivative-filter time constant, s (``DERIVATIVE_FILTER_SAMPLES`` controller samples)."""
    return DERIVATIVE_FILTER_SAMPLES * plant.sample_time_s


def _linear_fidelity(scene: Scene) -> str:
    """The multi-roller model is periodic in the cage angle; its mean behaviour is the
    compliant model's, which is linearised instead."""
    return "compliant" if scene.fidelity in ("multi-roller", "auto") else scene.fidelity


def actuator_loops(plant: Plant, scene: Scene, estimator: str | None = None) -> list[LoopModel]:
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
        from ..drive.estimator import design_kf

        kf = design_kf(plant, scene.load_change_time_s)
    fidelity = _linear_fidelity(scene)
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
                tf=_tf_default(plant), horizon=scene.duration, name=case,
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
            from ..drive.estimator import kf_drive_loop

            loops.append(
                kf_drive_loop(
                    a, b, c[i_speed], model.index("theta_nut"), kf, tf=_tf_default(plant), horizon=horizon,
                    step=step, feedforward=scene.feedforward, name=f"step to {f1:g} N (KF)",
                    outputs={"nut_speed": c[i_speed], "motor_torque": c[i_torque]},
                )
            )
        elif scene.discrete:
            loops.append(
                drive_loop(
                    a, b, c[i_speed], model.index("theta_nut"),
                    ts=plant.sample_time_s, speed_filter=plant.speed_filter_s, tf=_tf_default(plant),
                    horizon=horizon, step=step, name=f"step to {f1:g} N",
                    outputs={"nut_speed": c[i_speed], "motor_torque": c[i_torque]},
                )
            )
        else:
            import control

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
            loops.append(continuous_loop(sys, tf=_tf_default(plant), horizon=horizon, n_steps=int(round(horizon / 1e-4)), step=step))
    return loops


def _aggregate(values: list[float], scene: Scene) -> float:
    if scene.aggregate == "worst":
        return float(max(values))
    if scene.is_profile and scene.goal == "mix":
        return float((1.0 - scene.setpoint_share) * values[0] + scene.setpoint_share * values[1])
    return float(np.sum(values))


def _n_samples(plant: Plant, scene: Scene) -> int:
    return max(10, int(round(scene.duration / plant.sample_time_s)))


def duty_record(plant: Plant, scene: Scene, case: str) -> dict:
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
    from ..sim.simulate import PiecewiseLinear, _normalise_profile

    ts = plant.sample_time_s
    n = _n_samples(plant, scene)
    t = ts * np.arange(n + 1)
    w0, f0 = scene.setpoint_rad_s, scene.initial_load
    out: dict = {"t": t, "load_sequence": None, "setpoint_sequence": None, "load_steps": [], "breaks": [],
                 "load": f0, "setpoint": w0, "w_lin": w0, "f_lin": f0}
    if case == "load profile":
        pts = scene.load_profile
        prof = _normalise_profile(PiecewiseLinear(pts), scene.duration + 1.0, "load", "N")
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
        prof = _normalise_profile(PiecewiseLinear(pts), scene.duration + 1.0, "setpoint", "rad/s")
        r = prof.at(t)
        out["setpoint_sequence"] = r - w0
        out["setpoint_sequence"][0] = 0.0
        out["setpoint"] = PiecewiseLinear(pts)
        out["breaks"] = [float(x) for x in prof.t[1:]]
        vals = [v for _, v in pts]
        out["w_lin"] = 0.5 * (min(vals) + max(vals))
        out["setpoint_at"] = r
    return out


def setpoint_prefilter(r: np.ndarray, pid: PID, ts: float, b: float) -> np.ndarray:
    """Reference prefilter that makes the 1-DOF sampled PI(D) act like the 2-DOF law
    ``u = kp (b r - y) + I``, ``I += Ts ki (r - y)`` (derivative on the measurement):
    ``F(z) = (b kp (1 - z^-1) + Ts ki z^-1) / (kp (1 - z^-1) + Ts ki z^-1)``, unity at DC.

    Parameters
    ----------
    r : array, rad/s
        Setpoint read at each sample (from a steady start, ``r[0]`` held before).
    pid : PID
    ts : float, s
    b : float
        Setpoint weight in [0, 1].

    Returns
    -------
    array, rad/s
        The prefiltered setpoint, sample by sample.

    Examples
    --------
    >>> import numpy as np
    >>> rf = setpoint_prefilter(np.r_[0.0, np.ones(400)], PID(0.1, 10.0), 2.5e-4, 0.5)
    >>> float(rf[1]), round(float(rf[-1]), 3)
    (0.5, 1.0)
    """
    r = np.asarray(r, float)
    if b == 1.0 or pid.kp <= 0:
        return r.copy()
    kp, kit = pid.kp, ts * pid.ki
    rf = np.empty_like(r)
    rf[0] = r[0]
    for k in range(1, r.size):
        rf[k] = b * r[k] + ((kit - kp * b) * r[k - 1] - (kit - kp) * rf[k - 1]) / kp
    return rf


def _predict(design: Design, loops: list[LoopModel], plant: Plant, scene: Scene) -> None:
    """Linear load-step metrics of a design, on the same footing as the verification."""
    w0 = scene.setpoint_rad_s
    design.predicted, design.predicted_error = [], []
    design.predicted_h = loops[0].h
    if scene.is_profile:
        tau0 = _steady_torque(plant, scene, scene.initial_load)
        design.predicted_start_speed = w0
        for case, lp in zip(scene.cases, loops):
            rec = duty_record(plant, scene, case)
            tr = lp.trajectory(design.pid.gains)
            design.predicted_error.append(tr["error"])
            t = rec["t"][: lp.n_steps]
            r = rec["setpoint_at"][: lp.n_steps]
            design.predicted.append(profile_metrics(t, r - tr["error"], r, tau0 + tr["motor_torque"],
                                                    plant.torque_limit, rec["load_steps"], rec["breaks"]))
        design.objective_predicted = _aggregate([getattr(m, scene.objective) for m in design.predicted], scene)
        return
    w_pre, tau0 = w0, _steady_torque(plant, scene, scene.initial_load)
    if design.pid.ki == 0:  # P-only: the loop settles below the setpoint before the step too
        from ..sim.simulate import _initial_state

        op, _ = _initial_state(plant, _linear_fidelity(scene), w0, scene.initial_load, design.pid, 0.0, 0,
                               observer_ff=design.estimator == "kf")
        w_pre, tau0 = op.omega_nut, op.torque
    design.predicted_start_speed = w_pre
    for f1, lp in zip(scene.final_loads, loops):
        tr = lp.trajectory(design.pid.gains)
        design.predicted_error.append(tr["error"])
        t = scene.step_time + lp.h * np.arange(-1, lp.n_steps)
        speed = w_pre + np.concatenate([[0.0], -tr["error"]])
        torque = tau0 + np.concatenate([[0.0], tr.get("motor_torque", np.zeros(lp.n_steps))])
        design.predicted.append(
            load_step_metrics(t, speed, w0, scene.step_time, torque, plant.torque_limit,
                              direction=1 if f1 >= scene.initial_load else -1)
        )
    design.objective_predicted = _aggregate([getattr(m, scene.objective) for m in design.predicted], scene)


def _steady_torque(plant: Plant, scene: Scene, load: float) -> float:
    from ..plant.equilibrium import operating_point

    return operating_point(plant, scene.setpoint_rad_s, load, _linear_fidelity(scene)).torque


def health_flags(design: Design, plant: Plant, scene: Scene) -> list[str]:
    """Health checks of a verified design: what its nonlinear runs did that the report must
    not hide. A flagged design is never the best and never beats a baseline.

    - the nut reverses (the speed crosses zero against a non-zero setpoint);
    - the speed never recovers into the recovery band;
    - the torque sits at its limit for more than ``SATURATION_FRACTION`` of the time after the step;
    - the tuner did not converge to an optimum whose bounds hold (``TuningResult.status``);
    - the verified objective departs from the linear prediction by more than
      ``max(scene.accuracy, PREDICTION_TOLERANCE)`` (relative): the linear model the design
      was optimised on does not describe what happened. (Below ``PREDICTION_TOLERANCE`` a
      gap is a warning, not a flag: on the paper plant the 20-bit encoder's quantisation,
      which the linear model leaves out, already moves the IAE of a Kalman-filter
      feed-forward design by 5 % while its peak drop agrees to 0.4 %.)

    Parameters
    ----------
    design : Design
        Verified (and predicted) by :func:`verify` / :func:`tune_actuator`.
    plant : Plant
    scene : Scene

    Returns
    -------
    list of str
        One sentence per failed check (empty when healthy).
    """
    flags = []
    if not design.tuner_status.startswith("optimal"):
        flags.append(f"the tuner did not converge ({design.tuner_status})")
    w0 = scene.setpoint_rad_s
    for case, m, (t, y) in zip(scene.cases, design.verified, design.verified_runs):
        w = y["nut_speed"]
        if w0 != 0 and np.any(np.sign(w) == -np.sign(w0)):
            ext = float(w.min() if w0 > 0 else w.max())
            flags.append(f"{case}: the nut reverses (speed reaches {ext:.3g} rad/s at setpoint {w0:.4g})")
        if isinstance(m, ProfileMetrics):
            if abs(m.final_error_rad_s) > DUTY_SETTLE_BAND * max(abs(m.peak_deviation_rad_s), 1e-300):
                flags.append(f"{case}: the speed does not settle: the error at the end of the record is "
                             f"{m.final_error_rad_s:.3g} rad/s, more than {100 * DUTY_SETTLE_BAND:g} % of the peak "
                             f"{abs(m.peak_deviation_rad_s):.3g} rad/s")
        elif not math.isfinite(m.recovery_time_s):
            flags.append(f"{case}: the speed never recovers into the band")
        after = t >= scene.step_time
        sat = float(np.mean(np.abs(y["motor_torque"][after]) >= 0.999 * plant.torque_limit))
        if sat > SATURATION_FRACTION:
            flags.append(f"{case}: the torque is at its limit for {100 * sat:.0f} % of the run")
    p, v = design.objective_predicted, design.objective_verified
    limit = max(scene.accuracy, PREDICTION_TOLERANCE)
    diff = relative_difference(p, v)  # the report's one definition: (predicted - verified) / |verified|
    if diff is not None and p != 0 and abs(diff) > limit:
        flags.append(f"verified {scene.objective.upper()} {v:.4g} departs from the linear prediction {p:.4g}: "
                     f"difference {100 * diff:+.1f} % (more than {100 * limit:g} %)")
    return flags


def integral_warning(design: Design, scene: Scene) -> str | None:
    """A warning (not a flag) when a duty-cycle record cannot inform the integral gain: the
    integral time ``Ti = kp / ki`` is longer than the record (or ``ki = 0``), so the
    objective barely depends on ``ki`` and the tuner's value is arbitrary. Typical for
    ``goal = "setpoint"`` at a constant load: the viscous plant follows setpoint changes on the
    proportional action, and the design then holds a load change only slowly (the integral
    removes a load's speed offset over several ``Ti``).

    It is a warning rather than a health flag: the design does what its objective asks and the
    nonlinear verification agrees with the prediction (flags mark designs whose verified runs
    contradict the design); what is missing is information in the scene, which the message
    says how to add.

    Returns
    -------
    str or None
    """
    if not scene.is_profile or scene.controller not in ("pi", "pid"):
        return None
    kp, ki = design.pid.kp, design.pid.ki
    record = scene.duration
    ti = kp / ki if ki > 0 else math.inf
    if ti <= record:
        return None
    ti_text = f"Ti = {ti:.3g} s" if math.isfinite(ti) else "ki = 0"
    if scene.goal == "setpoint":
        return (f"the setpoint-only goal does not inform the integral gain ({ti_text} > record {record:g} s): the "
                "objective hardly changes with ki, so this design holds a load change only slowly; use goal = "
                "\"mix\" with a load profile (or a load-step scene) to tune ki for load rejection")
    return (f"the integral time is longer than the record ({ti_text} > {record:g} s): the record does not show the "
            "integral's effect and does not inform ki; lengthen the record or add load changes")


#: The fixed-step settings :func:`verify_settings` offers where their measured error is inside
#: the scene's accuracy: Radau IIA, 2 stages (order 3), 8 steps per controller sample, the
#: per-sample law compiled (``SimSettings.jit``).
FAST_VERIFY = SimSettings(integrator="radau", stages=2, substeps=8, jit=True)


def verify_settings(scene: Scene, plant: Plant | None = None, pid: PID | None = None) -> SimSettings:
    """Integrator settings of the verification runs.

    Parameters
    ----------
    scene : Scene
    plant : Plant, optional
        With a plant (and a sampled load-step scene): the fixed-step :data:`FAST_VERIFY` where
        its nut-speed error against a tight CVODES reference (1e-9), measured on the scene's first
        load step with ``pid`` (default :func:`~prsa_ctrl.studies.paper.default_pid`), is inside half
        the scene's accuracy (:func:`prsa_ctrl.sim.simulate.fast_settings`); otherwise, and
        without a plant, the adaptive integrator below.
    pid : PID, optional

    The adaptive integrator's tolerance follows the scene's accuracy: ``1e-4 x accuracy``
    (clipped to [1e-10, 1e-5]). At 1e-6 (accuracy 1 %) the sampled compliant loop's nut speed
    differs from a 1e-10 reference by ~1e-3 rad/s on the paper step (0.03 % of the peak drop),
    at half the cost of 1e-8.
    """
    tol = min(max(1e-4 * scene.accuracy, 1e-10), 1e-5)
    adaptive = SimSettings(rtol=tol, atol=tol)
    if plant is None:
        return adaptive
    fast, _ = fast_verify_settings(scene, plant, pid)
    return fast or adaptive


def fast_verify_settings(scene: Scene, plant: Plant, pid: PID | None = None) -> tuple[SimSettings | None, dict]:
    """:data:`FAST_VERIFY` if its measured error on ``scene``'s first load step is inside half
    the scene's accuracy, else ``None``; with the measurement (``relative`` error, or a
    ``reason`` where the fast path does not apply: continuous or duty-cycle scenes)."""
    from ..sim.simulate import fast_settings

    scene, _ = choose_fidelity(scene)
    if not scene.discrete or scene.is_profile:
        return None, {"reason": "fixed-step fast path: sampled load-step scenes only"}
    pre = min(scene.step_time, _PRE_SAMPLES * plant.sample_time_s)
    kw = dict(setpoint=scene.setpoint_rad_s, load=[(0.0, scene.initial_load), (pre, scene.final_loads[0])],
              duration=pre + scene.duration - scene.step_time, controller=pid or default_pid(plant),
              fidelity=scene.fidelity, discrete=True)
    return fast_settings(plant, scene.accuracy, FAST_VERIFY, reference=SimSettings(rtol=1e-9, atol=1e-9), **kw)


def verify(design: Design, plant: Plant, scene: Scene, seed: int = 0, settings: SimSettings | None = None) -> Design:
    """Nonlinear load-step runs of a design (one per final load); fills ``design.verified``
    and ``design.verified_runs`` (time s, dict of output arrays) and returns the design.

    Parameters
    ----------
    design : Design
    plant : Plant
    scene : Scene
    seed : int
        Seed of the per-roller errors (multi-roller fidelity).
    settings : SimSettings, optional
        Integrator settings (default :func:`verify_settings` of the scene).
    """
    scene, _ = choose_fidelity(scene)
    ts = plant.sample_time_s
    settings = verify_settings(scene) if settings is None else settings
    if scene.is_profile:
        return _verify_profile(design, plant, scene, seed, settings)
    pre = min(scene.step_time, _PRE_SAMPLES * ts) if scene.discrete else min(scene.step_time, 1e-3)
    offset = scene.step_time - pre
    design.verified, design.verified_runs, design.estimation = [], [], []
    for f1 in scene.final_loads:
        kw = dict(setpoint=scene.setpoint_rad_s, load=[(0.0, scene.initial_load), (pre, f1)],
                  duration=pre + scene.duration - scene.step_time, controller=design.pid,
                  fidelity=scene.fidelity, settings=settings, seed=seed)
        measurement = "encoder"
        kf = None
        if design.estimator == "kf":
            from ..drive.estimator import design_kf

            measurement, kf = "kf", design_kf(plant, scene.load_change_time_s)
        r = run(plant, discrete=scene.discrete, measurement=measurement, kf=kf, **kw)
        if design.estimator == "kf":
            w = r.output("nut_speed")
            design.estimation.append({
                "kf_speed_rms_rad_s": float(np.sqrt(np.mean((r.output("speed_measured") - w) ** 2))),
                "fd_speed_rms_rad_s": float(np.sqrt(np.mean((r.output("speed_fd") - w) ** 2))),
            })
        t = np.asarray(r.time) + offset
        y = dict(zip(r.output_labels, np.asarray(r.outputs)))
        design.verified.append(
            load_step_metrics(t, y["nut_speed"], scene.setpoint_rad_s, scene.step_time, y["motor_torque"],
                              plant.torque_limit, direction=1 if f1 >= scene.initial_load else -1)
        )
        design.verified_runs.append((t, y))
    design.objective_verified = _aggregate([getattr(m, scene.objective) for m in design.verified], scene)
    return design


def _verify_profile(design: Design, plant: Plant, scene: Scene, seed: int, settings: SimSettings) -> Design:
    """:func:`verify` on a duty cycle: one sampled nonlinear run per record, over the whole
    record, with the scene's profiles (a setpoint weight ``b != 1`` through
    :func:`setpoint_prefilter`)."""
    from ..sim.simulate import PiecewiseLinear

    ts = plant.sample_time_s
    design.verified, design.verified_runs, design.estimation = [], [], []
    for case in scene.cases:
        rec = duty_record(plant, scene, case)
        setpoint = rec["setpoint"]
        if case == "setpoint profile" and scene.setpoint_weight != 1.0:
            rf = setpoint_prefilter(rec["setpoint_at"], design.pid, ts, scene.setpoint_weight)
            n_pts = int(np.searchsorted(rec["t"], scene.duration - 1e-9 * ts))  # points before the end
            setpoint = PiecewiseLinear(tuple(zip(rec["t"][:n_pts].tolist(), rf[:n_pts].tolist())))
        r = run(plant, discrete=True, setpoint=setpoint, load=rec["load"], duration=scene.duration,
                controller=design.pid, fidelity=scene.fidelity, settings=settings, seed=seed)
        t = np.asarray(r.time)
        y = dict(zip(r.output_labels, np.asarray(r.outputs)))
        ref = rec["setpoint_at"][: t.size]
        y["setpoint"] = ref
        design.verified.append(profile_metrics(t, y["nut_speed"], ref, y["motor_torque"], plant.torque_limit,
                                               rec["load_steps"], rec["breaks"]))
        design.verified_runs.append((t, y))
    design.objective_verified = _aggregate([getattr(m, scene.objective) for m in design.verified], scene)
    return design


_POOL_JOB: tuple | None = None


def _verify_job(i: int):
    designs, plant, scene = _POOL_JOB  # type: ignore[misc]
    d = verify(designs[i], plant, scene)
    return d.verified, d.verified_runs, d.objective_verified, d.estimation


def default_workers() -> int:
    """Processes of a parallel verification when none are asked for: ``$PRSA_WORKERS``, else
    the machine's cores, at most 4."""
    return int(os.environ.get("PRSA_WORKERS", "0")) or min(os.cpu_count() or 1, 4)


def verify_all(designs: list[Design], plant: Plant, scene: Scene, workers: int | None = None) -> None:
    """Verify several designs, in parallel worker processes where the machine has cores.

    The workers are forked after the simulator's integrators are built, so each inherits them
    instead of rebuilding; ``PRSA_WORKERS=1`` forces serial runs.
    """
    global _POOL_JOB
    if not designs:
        return
    verify(designs[0], plant, scene)  # builds (and caches) the integrators before any fork
    rest = designs[1:]
    if workers is None:
        workers = default_workers()
    if workers <= 1 or len(rest) < 2 or "fork" not in multiprocessing.get_all_start_methods():
        for d in rest:
            verify(d, plant, scene)
        return
    _POOL_JOB = (rest, plant, scene)
    try:
        ctx = multiprocessing.get_context("fork")
        with ProcessPoolExecutor(max_workers=min(workers, len(rest)), mp_context=ctx) as pool:
            for d, (ver, runs, obj, est) in zip(rest, pool.map(_verify_job, range(len(rest)))):
                d.verified, d.verified_runs, d.objective_verified, d.estimation = ver, runs, obj, est
    finally:
        _POOL_JOB = None


def baseline_designs(plant: Plant, scene: Scene, loops: list[LoopModel]) -> list[Design]:
    """Reference designs every report carries.

    Parameters
    ----------
    plant : Plant
    scene : Scene
    loops : list of LoopModel
        From :func:`actuator_loops` (the margins and predictions are computed on them).

    - ``paper Kp sweep``: the paper's manual approach, a Kp sweep with a small fixed Ki
      (one tenth of the rule-of-thumb Ki) and Kd = 0, keeping the Kp with the best predicted
      objective among the sweep points a manual tuner would accept (stable, Ms <= 2).
    - ``SIMC``: Skogestad's rule for an integrating process ``1/(J s)`` with effective delay
      theta = current-loop lag + speed filter + 1.5 Ts: ``Kc = J/(2 theta)``, ``tau_I = 8 theta``.
    - ``PM 60 deg``: crossover where the PI loop's phase margin is 60 deg with the integral
      corner at a quarter of the crossover.
    - ``rule of thumb``: crossover a decade below the current loop (see ``paper.default_pid``).
    """
    lp = loops[0]
    ref = default_pid(plant)
    designs = []
    ki_small = ref.ki / 10.0
    best = None
    for kp in ref.kp * np.logspace(-1, 0.6, 17):
        g = (kp, ki_small, 0.0)
        if not all(l.is_stable(g) for l in loops) or lp.margins(g).ms > 2.0:
            continue
        val = _aggregate([l.objective(g, scene.objective) for l in loops], scene)
        if best is None or val < best[1]:
            best = (kp, val)
    if best is not None:
        designs.append(Design("paper Kp sweep (small Ki)", PID(best[0], ki_small), lp.margins((best[0], ki_small, 0))))
    theta = plant.current_loop_time_constant_s + plant.speed_filter_s + (1.5 * plant.sample_time_s if scene.discrete else 0.0)
    kc = plant.reflected_inertia_kg_m2 / (2.0 * theta)
    designs.append(Design("SIMC (tau_c = theta)", PID(kc, kc / (8.0 * theta)), lp.margins((kc, kc / (8 * theta), 0))))
    # PM 60: L = kp (L1 + (wc/4) L2); find wc where the phase is -120 deg.
    w = lp.omega
    shape = lp.L[0] + (w / 4.0) * lp.L[1]
    phase = np.unwrap(np.angle(shape))
    idx = np.flatnonzero(phase <= math.radians(-120.0))
    if idx.size:
        i = idx[0]
        kp = 1.0 / abs(shape[i])
        designs.append(Design("PM 60 deg", PID(kp, kp * w[i] / 4.0), lp.margins((kp, kp * w[i] / 4.0, 0))))
    designs.append(Design("rule of thumb (wc = f_c/10)", ref, lp.margins(ref.gains)))
    return designs


def _best(designs: list[Design]) -> Design:
    """The verified best among the healthy designs; only when none is healthy, the least bad
    (the report's ``status`` then says so)."""
    healthy = [d for d in designs if d.healthy]
    return min(healthy or designs, key=lambda d: d.objective_verified)


def tune_actuator(plant: Plant, scene: Scene, workers: int | None = None) -> ActuatorTuning:
    """Tune, verify and compare (see module docstring).

    Parameters
    ----------
    plant : Plant
    scene : Scene
    workers : int, optional
        Verification processes (default: up to 4 where the machine has the cores;
        ``PRSA_WORKERS=1`` forces serial runs).

    1. Linearise at each load step's mid load and build the sampled loop models.
    2. Tune at the scene's Ms bound, plus ``candidates - 1`` more robust alternatives.
    3. Verify candidates and baselines on the nonlinear simulator; pick the verified best.
    4. Compare with each baseline at equal or better Ms: the verified best where its Ms is not
       above the baseline's and it wins, otherwise a design tuned at the baseline's Ms.

    Returns
    -------
    ActuatorTuning
        The verified-best design, the other candidates, the baselines, the comparisons,
        timings (s) and warnings.
    """
    if not isinstance(plant, Plant):
        raise TypeError(f"plant = {plant!r}; expected a prsa_ctrl Plant (e.g. prsa_ctrl.load_plant('paper-iprsm'))")
    if not isinstance(scene, Scene):
        raise TypeError(f"scene = {scene!r}; expected a prsa_ctrl Scene (e.g. prsa_ctrl.load_scene(...))")
    timing: dict[str, float] = {}
    t0 = time.perf_counter()
    scene, fidelity_reason = choose_fidelity(scene)
    loops = actuator_loops(plant, scene)
    timing["linearize"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    common = dict(objective=scene.objective, controller=scene.controller, worst_case=scene.aggregate == "worst")
    if scene.is_profile and scene.goal == "mix":
        common["weights"] = [1.0 - scene.setpoint_share, scene.setpoint_share]
    tuner = Tuner(loops, **common)  # one scan grid and NLP for every Ms level
    runs: list[dict] = []

    def tuned(ms: float) -> Design:
        res = tuner.tune(ms_max=ms, mt_max=scene.mt_max, mks_max=scene.mks_max)
        runs.append({"ms_max": ms, "result": res.status,
                     **{k: res.stats[k] for k in ("status", "iterations", "wall_time_s")}})
        label = f"tuned (Ms <= {ms:.3g})" + (" + KF" if scene.estimator == "kf" else "") + (" + load FF" if scene.feedforward else "")
        d = Design(label, res.pid, res.margins[0], estimator=scene.estimator, tuner_status=res.status)
        _predict(d, loops, plant, scene)
        return d

    # Baselines use the drive's standard speed measurement; with an estimator in the scene the
    # PI tuned without it is a baseline too (the reference for what the estimator buys).
    plain = loops if scene.estimator == "none" else actuator_loops(plant, scene, estimator="none")
    baselines = baseline_designs(plant, scene, plain)
    if scene.estimator != "none":
        res = Tuner(plain, **common).tune(ms_max=scene.ms_max, mt_max=scene.mt_max, mks_max=scene.mks_max)
        baselines.insert(0, Design(f"tuned PI alone (Ms <= {scene.ms_max:.3g})", res.pid, res.margins[0]))
    for d in baselines:
        _predict(d, plain, plant, scene)
    # Candidates: the design at the scene's Ms bound, designs at the Ms of every baseline that
    # is more robust (they double as its equal-Ms comparison), then more robust alternatives
    # until there are ``scene.candidates``.
    ms_levels = [scene.ms_max] + sorted({b.margins.ms for b in baselines if b.margins.ms < scene.ms_max}, reverse=True)
    hedges = [1 + (scene.ms_max - 1) * f for f in (0.85, 0.7, 0.55, 0.4)]
    ms_levels += hedges[: max(0, scene.candidates - len(ms_levels))]
    candidates = [tuned(ms) for ms in ms_levels]
    timing["tune"] = time.perf_counter() - t1

    t2 = time.perf_counter()
    verify_all(candidates + baselines, plant, scene, workers)
    timing["verify"] = time.perf_counter() - t2
    for d in candidates + baselines:
        d.flags = health_flags(d, plant, scene)
    best = _best(candidates)
    # Equal-Ms comparison designs where the verified best and the candidates do not settle it.
    t3 = time.perf_counter()

    def settles(d: Design, b: Design) -> bool:
        return d.healthy and d.margins.ms <= b.margins.ms * (1 + 1e-9) and d.objective_verified < b.objective_verified

    ours_for = {id(b): next((d for d in [best, *candidates] if settles(d, b)), None) for b in baselines}
    extra = {id(b): tuned(b.margins.ms) for b in baselines if ours_for[id(b)] is None}
    t4 = time.perf_counter()
    timing["tune"] += t4 - t3
    verify_all(list(extra.values()), plant, scene, workers)
    for d in extra.values():
        d.flags = health_flags(d, plant, scene)
    timing["verify"] += time.perf_counter() - t4
    comparisons = []
    for b in baselines:
        ours = extra.get(id(b)) or ours_for[id(b)]
        comparisons.append(
            {
                "baseline": b.name,
                "baseline_ms": b.margins.ms,
                "baseline_objective_verified": b.objective_verified,
                "tuned": ours.name,
                "tuned_ms": ours.margins.ms,
                "tuned_gains": ours.pid.as_dict(),
                "tuned_objective_verified": ours.objective_verified,
                "tuned_flags": list(ours.flags),
                "baseline_flags": list(b.flags),
                "beaten": bool(ours.healthy and ours.objective_verified < b.objective_verified
                               and ours.margins.ms <= b.margins.ms * (1 + 1e-9)),
            }
        )
    # Equal-Ms designs within the scene's bound are candidates too.
    best = _best([best, *[d for d in extra.values() if d.margins.ms <= scene.ms_max]])
    timing["total"] = time.perf_counter() - t0

    warnings_out = []
    for d in candidates + baselines + list(extra.values()):
        departed = any("departs from the linear prediction" in f for f in d.flags)  # said once, as a flag
        diff = relative_difference(d.objective_predicted, d.objective_verified)
        if not departed and d.objective_verified > 0 and diff is not None and abs(diff) > PREDICTION_TOLERANCE:
            warnings_out.append(
                f"{d.name}: predicted {scene.objective.upper()} {d.objective_predicted:.4g} differs from verified "
                f"{d.objective_verified:.4g}: difference {100 * diff:+.1f} %"
            )
    for d in candidates + baselines + list(extra.values()):
        for f in d.flags:
            warnings_out.append(f"{d.name}: {f}")
    w_int = integral_warning(best, scene)
    if w_int:
        warnings_out.append(f"{best.name}: {w_int}")
    for c in comparisons:
        if not c["beaten"]:
            mt_note = ""
            b_mt = next((b.margins.mt for b in baselines if b.name == c["baseline"]), math.nan)
            if scene.mt_max is not None and b_mt > scene.mt_max:
                mt_note = (f" (the comparison design also keeps Mt <= {scene.mt_max:g}; the baseline reaches "
                           f"Mt {b_mt:.3g})")
            warnings_out.append(f"baseline {c['baseline']!r} is not beaten at equal or better Ms{mt_note}")
    return ActuatorTuning(
        plant=plant,
        scene=scene,
        best=best,
        candidates=candidates + [d for d in extra.values() if d.margins.ms <= scene.ms_max],
        baselines=baselines,
        comparisons=comparisons,
        timing_s=timing,
        solver={"name": "ipopt (CasADi)", "runs": runs},
        warnings=warnings_out,
        loops=loops,
        fidelity_reason=fidelity_reason,
    )
