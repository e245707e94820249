"""The toolkit's main job: tune the actuator's speed loop for a load-step or duty-cycle scene,
verify the best candidates and the baselines on the nonlinear simulator, and report predicted
against verified metrics.

A duty-cycle scene (:class:`~prsa_ctrl.studies.scenekinds.DutyCycle`) is tuned on its actual profile: the sampled loop
model takes the load as its mean over every controller sample and the setpoint as the
controller reads it at every sample (:func:`prsa_ctrl.tuning.builders.drive_loop`), and the
verification runs the nonlinear simulator on the same profile. A 2-DOF setpoint weight
``b != 1`` is verified as the equivalent 1-DOF loop behind the reference prefilter
``F(z) = (b kp (1 - z^-1) + Ts ki z^-1) / (kp (1 - z^-1) + Ts ki z^-1)`` (identical while the
torque is not saturated; the simulator's back-calculation anti-windup then acts on the
prefiltered error).

The public functions (:func:`predict`, :func:`verify`, :func:`checked`, ...) take a
:class:`~prsa_ctrl.studies.scene.Scene`; :func:`tune_actuator` has the scene's kind resolve it
once against the plant (:class:`~prsa_ctrl.studies.kindruns.ResolvedProblem`) and runs its
stages on that. What differs between the kinds is asked of the problem
(:mod:`prsa_ctrl.studies.kindruns`)."""

from __future__ import annotations

import math
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np

from ..drive.pid import PID
from ..options import PEAK_BOUND_RANGE, RAD_S_PER_RPM
from ..plant.plantfile import Plant
from ..results import is_ok
from ..sim.metrics import LoadStepMetrics, Margins, ProfileMetrics, relative_difference
from ..sim.integrators import SimSettings
from ..sim.engine import fast_settings
from ..tuning.loops import LoopModel
from ..tuning.tuner import Tuner
from .paper import default_pid
from .scene import PRE_EVENT_SAMPLES, Scene, choose_fidelity
from .scenefilters import filter_rows
from .kindruns import ResolvedProblem, setpoint_prefilter, speed_kind
from .sceneloops import actuator_loops, duty_record, linear_fidelity, loop_spec


__all__ = ["Design", "ActuatorTuning", "tune_actuator", "resolve_scene", "actuator_loops", "baseline_designs", "duty_record",
           "setpoint_prefilter", "predict", "predict_all", "verify", "verify_all", "checked", "health_flags", "prediction_warnings",
           "integral_warning", "checked_all", "verify_settings", "fast_verify_settings", "default_workers", "linear_fidelity",
           "FAST_VERIFY", "PREDICTION_TOLERANCE"]

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


@dataclass(frozen=True)
class Design:
    """One controller with its predicted (linear) and verified (nonlinear) load-step metrics.

    Frozen: :func:`predict`, :func:`verify` and :func:`checked` return new designs.
    ``predicted`` / ``verified`` hold one :class:`LoadStepMetrics` (duty cycle:
    :class:`ProfileMetrics`) per final load (record) of the scene; ``objective_*`` aggregate
    them as the scene says (sum or worst). ``status`` (:mod:`prsa_ctrl.results`) is
    ``"unverified"`` before :func:`verify`, then ``"ok"`` or ``"flagged: <checks failed>"``
    (from ``flags``, the health checks of :func:`health_flags`).
    """

    name: str
    pid: PID
    margins: Margins
    predicted: tuple = ()
    verified: tuple = ()
    objective_predicted: float = math.nan
    objective_verified: float = math.nan
    verified_runs: tuple = field(default=(), repr=False)  # per level: (time s, {output: array})
    predicted_error: tuple = field(default=(), repr=False)  # per level: speed error, rad/s, per sample
    predicted_h: float = math.nan
    predicted_start_speed: float = math.nan  # rad/s before the step (below the setpoint for P-only)
    estimator: str = "none"
    estimation: tuple = ()  # per step: speed RMS errors (rad/s)
    flags: tuple[str, ...] = ()  # health checks the verified runs failed
    tuner_status: str = "optimal"  # the tuner's status for tuned designs (see TuningResult.status)
    warnings: tuple[str, ...] = ()  # caveats that are not health flags (prediction gap below the flag limit)

    @property
    def healthy(self) -> bool:
        """Whether the verified runs passed every health check (see :func:`health_flags`)."""
        return not self.flags

    @property
    def status(self) -> str:
        """``"unverified"``, ``"ok"`` or ``"flagged: ..."`` (see :data:`prsa_ctrl.results.STATUSES`)."""
        if self.flags:
            return "flagged: " + "; ".join(self.flags)
        return "ok" if self.verified else "unverified"

    @property
    def ok(self) -> bool:
        """Verified and healthy."""
        return is_ok(self.status)

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
            "estimation": [dict(e) for e in self.estimation],
            "flags": list(self.flags),
        }


@dataclass(frozen=True)
class ActuatorTuning:
    """Report of :func:`tune_actuator` (frozen).

    ``comparison_designs`` are the verified designs tuned at a baseline's Ms that the report
    compares with it but does not keep as candidates (tuned above the scene's Ms bound).
    """

    plant: Plant
    scene: Scene
    best: Design
    candidates: tuple[Design, ...]
    baselines: tuple[Design, ...]
    comparisons: tuple[dict, ...]
    timing_s: dict[str, float]
    solver: dict
    warnings: tuple[str, ...]
    loops: tuple = field(default=(), repr=False)
    fidelity_reason: str = ""
    comparison_designs: tuple[Design, ...] = field(default=(), repr=False)

    @property
    def beats_all_baselines(self) -> bool:
        return all(c["beaten"] for c in self.comparisons)

    @property
    def status(self) -> str:
        """``"ok"``, or ``"flagged: ..."`` when every candidate failed a health check and the
        reported best is only the least bad of them."""
        return "ok" if self.best.healthy else "flagged: " + "; ".join(self.best.flags)

    @property
    def ok(self) -> bool:
        """The reported best passed every health check."""
        return is_ok(self.status)

    def comparison_pairs(self) -> list[tuple[Design, Design]]:
        """``(baseline, verified tuned design at equal or lower Ms)`` for every comparison whose
        baseline was verified, in the order of :attr:`comparisons`."""
        pool = [self.best, *self.candidates, *self.comparison_designs]
        pairs = []
        for c in self.comparisons:
            b = next((d for d in self.baselines if d.name == c["baseline"]), None)
            d = next((x for x in pool if x.pid.as_dict() == c["tuned_gains"] and x.verified_runs), None)
            if b is not None and b.verified_runs and d is not None:
                pairs.append((b, d))
        return pairs

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
                          "estimation": [dict(e) for e in b.estimation]},
            "objective": self.scene.objective,
            "predicted": b.predicted[0].as_dict(),
            "verified": b.verified[0].as_dict(),
            "margins": b.margins.as_dict(),
            "best": b.as_dict(),
            "candidates": [c.as_dict() for c in self.candidates],
            "baselines": [d.as_dict() for d in self.baselines],
            "comparisons": list(self.comparisons),
            "beats_all_baselines": self.beats_all_baselines,
            "solver": self.solver,
            "timing_s": self.timing_s,
            "verification": {"fidelity": self.fidelity_reason, "discrete": self.scene.discrete,
                             "tolerance": verify_settings(self.scene).rtol},
            "warnings": list(self.warnings),
            **({"filters": filter_rows(self.scene.filters, self.plant.sample_time_s)} if self.scene.filters else {}),
        }


def predict(design: Design, loops: list[LoopModel], plant: Plant, scene: Scene) -> Design:
    """The design with its linear load-step (or duty-cycle) metrics, on the same footing as
    the verification (a new :class:`Design`; the argument is left as it is).

    Parameters
    ----------
    design : Design
    loops : list of LoopModel
        The scene's loop models (:func:`actuator_loops`), one per load level or record.
    plant : Plant
    scene : Scene

    Returns
    -------
    Design
        With ``predicted`` (metrics per level), ``predicted_error`` (speed error per sample,
        rad/s), ``predicted_h`` (s), ``predicted_start_speed`` (rad/s) and
        ``objective_predicted``.
    """
    return predict_all([design], loops, plant, scene)[0]


def predict_all(designs: list[Design], loops: list[LoopModel], plant: Plant, scene: Scene) -> list[Design]:
    """:func:`predict` of several designs on the same loop models: the linear runs and metrics
    of every design, then their objectives (new designs, in the same order).

    Parameters
    ----------
    designs : list of Design
    loops : list of LoopModel
        The scene's loop models (:func:`actuator_loops`), one per load level or record.
    plant : Plant
    scene : Scene

    Returns
    -------
    list of Design
    """
    return _predict_all(designs, loops, plant, loop_spec(plant, scene))


def _predict_all(designs: list[Design], loops: list[LoopModel], plant: Plant, spec: ResolvedProblem) -> list[Design]:
    """:func:`predict_all` on the resolved problem: the linear runs of every design (the loop
    models), then their metrics (the problem's), then the objectives."""
    prob = spec.problem
    traj = [[lp.trajectory(d.pid.gains) for lp in loops] for d in designs]
    starts = [prob.start(plant, spec, d) for d in designs]  # (speed rad/s, torque N m) before the event
    metrics = [prob.predicted_metrics(plant, spec, loops, trs, st) for trs, st in zip(traj, starts)]
    return [replace(d, predicted=tuple(m), predicted_error=tuple(tr["error"] for tr in trs), predicted_h=loops[0].h,
                    predicted_start_speed=w_pre,
                    objective_predicted=prob.aggregate([getattr(x, spec.scene.objective) for x in m], spec))
            for d, m, trs, (w_pre, _) in zip(designs, metrics, traj, starts)]


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
    # The report's one definition of the gap: (predicted - verified) / |verified|.
    return _flags(design, plant, loop_spec(plant, scene),
                  relative_difference(design.objective_predicted, design.objective_verified))


def _flags(design: Design, plant: Plant, spec: ResolvedProblem, diff: float | None) -> list[str]:
    """:func:`health_flags` on the resolved problem with the relative prediction gap ``diff`` given."""
    scene = spec.scene
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
    says how to add. Asked of the scene's problem (load steps always inform ``ki``).

    Returns
    -------
    str or None
    """
    return speed_kind(scene).integral_warning(design)


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
        the scene's accuracy (:func:`prsa_ctrl.sim.engine.fast_settings`); otherwise, and
        without a plant, the adaptive integrator below.
    pid : PID, optional

    The adaptive integrator's tolerance follows the scene's accuracy: ``1e-4 x accuracy``
    (clipped to [1e-10, 1e-5]). At 1e-6 (accuracy 1 %) the sampled compliant loop's nut speed
    differs from a 1e-10 reference by ~1e-3 rad/s on the paper step (0.03 % of the peak drop),
    at half the cost of 1e-8.
    """
    adaptive = _adaptive_settings(scene.accuracy)
    if plant is None:
        return adaptive
    fast, _ = fast_verify_settings(scene, plant, pid)
    return fast or adaptive


def _adaptive_settings(accuracy: float) -> SimSettings:
    """The adaptive integrator at ``1e-4 x accuracy`` (clipped to [1e-10, 1e-5])."""
    tol = min(max(1e-4 * accuracy, 1e-10), 1e-5)
    return SimSettings(rtol=tol, atol=tol)


def fast_verify_settings(scene: Scene, plant: Plant, pid: PID | None = None) -> tuple[SimSettings | None, dict]:
    """:data:`FAST_VERIFY` if its measured error on ``scene``'s first load step is inside half
    the scene's accuracy, else ``None``; with the measurement (``relative`` error, or a
    ``reason`` where the fast path does not apply: continuous or duty-cycle scenes)."""
    scene, _ = choose_fidelity(scene)
    if not scene.discrete or not speed_kind(scene).takes("fast-verify"):
        return None, {"reason": "fixed-step fast path: sampled load-step scenes only"}
    pre = min(scene.step_time, _PRE_SAMPLES * plant.sample_time_s)
    kw = dict(setpoint=scene.setpoint_rad_s, load=[(0.0, scene.initial_load), (pre, scene.final_loads[0])],
              duration=pre + scene.duration - scene.step_time, controller=pid or default_pid(plant),
              fidelity=scene.fidelity, discrete=True, filters=tuple(getattr(scene, "filters", ())) or None)
    return fast_settings(plant, scene.accuracy, FAST_VERIFY, reference=SimSettings(rtol=1e-9, atol=1e-9), **kw)


def verify(design: Design, plant: Plant, scene: Scene, seed: int = 0,
           settings: SimSettings | None = None) -> Design:
    """Nonlinear load-step runs of a design (one per final load; a duty cycle: one per record).

    The package's one argument order for verification: the design first, then what it is
    verified on (``plant``, ``scene``). The argument is not changed.

    Parameters
    ----------
    design : Design
    plant : Plant
    scene : Scene
        Its fidelity is resolved here (:func:`~prsa_ctrl.studies.scene.choose_fidelity`).
    seed : int
        Seed of the per-roller errors (multi-roller fidelity).
    settings : SimSettings, optional
        Integrator settings (default :func:`verify_settings` of the scene).

    Returns
    -------
    Design
        A new design with ``verified`` (metrics per level), ``verified_runs`` (time s, dict of
        output arrays), ``estimation`` (Kalman-filter designs: speed RMS errors, rad/s) and
        ``objective_verified``; its ``flags`` are those of ``design`` (see :func:`checked`).
    """
    spec = _verification_spec(plant, scene)
    return _with_runs([design], _simulate([design], plant, spec, seed, settings), plant, spec)[0]


def _verification_spec(plant: Plant, scene: Scene) -> ResolvedProblem:
    """The problem the verification reads: the scene's, its fidelity resolved."""
    if not isinstance(scene, Scene):
        raise TypeError(f"scene = {type(scene).__name__}; expected a prsa_ctrl Scene (prsa_ctrl.load_scene)")
    return speed_kind(scene).resolve(plant)


def _simulate(designs: list[Design], plant: Plant, spec: ResolvedProblem, seed: int = 0,
              settings: SimSettings | None = None) -> list[tuple]:
    """The nonlinear runs of :func:`verify`, for every design: ``(runs, estimation)`` with one
    ``(time s, {output: array})`` per level and the Kalman filter's speed RMS errors (rad/s)
    (the problem's runs: load steps from ``_PRE_SAMPLES`` samples before the step, or the duty
    cycle's records)."""
    if spec.scene.fidelity == "auto":
        raise ValueError("scene: a problem with fidelity 'auto'; expected a problem whose fidelity is resolved "
                         "(its kind's resolve(plant))")
    settings = _adaptive_settings(spec.scene.accuracy) if settings is None else settings
    return [spec.problem.simulate(design, plant, spec, settings, seed, _PRE_SAMPLES) for design in designs]


def _with_runs(designs: list[Design], simulated: list[tuple], plant: Plant, spec: ResolvedProblem) -> list[Design]:
    """The designs with their verified runs (:func:`_simulate`), the metrics of every run, then
    the objectives (new designs)."""
    prob = spec.problem
    metrics = [prob.verified_metrics(plant, spec, runs) for runs, _ in simulated]
    return [replace(d, verified=tuple(m), verified_runs=tuple(runs), estimation=tuple(estimation),
                    objective_verified=prob.aggregate([getattr(x, spec.scene.objective) for x in m], spec))
            for d, m, (runs, estimation) in zip(designs, metrics, simulated)]


def checked(design: Design, plant: Plant, scene: Scene) -> Design:
    """The verified design with its health ``flags`` (:func:`health_flags`) and its
    ``warnings`` (:func:`prediction_warnings`), as a new design."""
    return checked_all([design], plant, scene)[0]


def checked_all(designs: list[Design], plant: Plant, scene: Scene) -> list[Design]:
    """:func:`checked` of several verified designs (new designs, in the same order): the gap
    between predicted and verified objective of each, then its flags and warnings."""
    return _checked_all(designs, plant, loop_spec(plant, scene))


def _checked_all(designs: list[Design], plant: Plant, spec: ResolvedProblem) -> list[Design]:
    """:func:`checked_all` on the resolved problem."""
    diffs = [relative_difference(d.objective_predicted, d.objective_verified) for d in designs]
    out = []
    for d, diff in zip(designs, diffs):
        d = replace(d, flags=tuple(_flags(d, plant, spec, diff)))
        out.append(replace(d, warnings=tuple(_warnings(d, spec.scene.objective, diff))))
    return out


def prediction_warnings(design: Design, scene: Scene) -> list[str]:
    """A warning when the verified objective differs from the predicted one by more than
    ``PREDICTION_TOLERANCE`` (relative) but the gap is not already a health flag.

    Returns
    -------
    list of str
        Empty, or one sentence (without the design's name).
    """
    return _warnings(design, scene.objective, relative_difference(design.objective_predicted, design.objective_verified))


def _warnings(design: Design, objective: str, diff: float | None) -> list[str]:
    """:func:`prediction_warnings` with the scene's objective and the relative prediction gap ``diff`` given."""
    departed = any("departs from the linear prediction" in f for f in design.flags)  # said once, as a flag
    if departed or not design.objective_verified > 0 or diff is None or not abs(diff) > PREDICTION_TOLERANCE:
        return []
    return [f"predicted {objective.upper()} {design.objective_predicted:.4g} differs from verified "
            f"{design.objective_verified:.4g}: difference {100 * diff:+.1f} %"]


_POOL_JOB: tuple | None = None


def _verify_job(i: int) -> tuple:
    designs, plant, spec = _POOL_JOB  # type: ignore[misc]
    return _simulate([designs[i]], plant, spec)[0]


def default_workers() -> int:
    """Processes of a parallel verification when none are asked for: ``$PRSA_WORKERS``, else
    the machine's cores, at most 4."""
    return int(os.environ.get("PRSA_WORKERS", "0")) or min(os.cpu_count() or 1, 4)


def verify_all(designs: list[Design], plant: Plant, scene: Scene, workers: int | None = None) -> list[Design]:
    """:func:`verify` of several designs, in parallel worker processes where the machine has
    cores; the verified designs in the same order (the arguments are not changed).

    The workers are forked after the simulator's integrators are built, so each inherits them
    instead of rebuilding; ``PRSA_WORKERS=1`` forces serial runs.
    """
    if not designs:
        return []
    return _verify_all(designs, plant, _verification_spec(plant, scene), workers)


def _verify_all(designs: list[Design], plant: Plant, spec: ResolvedProblem, workers: int | None = None) -> list[Design]:
    """:func:`verify_all` on a problem whose fidelity is resolved."""
    if not designs:
        return []
    simulated = _simulate_all(designs, plant, spec, default_workers() if workers is None else workers)
    return _with_runs(designs, simulated, plant, spec)


def _simulate_all(designs: list[Design], plant: Plant, spec: ResolvedProblem, workers: int) -> list[tuple]:
    """:func:`_simulate` of every design: in this process, or the first here (it builds and
    caches the integrators) and the others in forked workers where there are cores."""
    global _POOL_JOB
    if workers <= 1 or len(designs) < 3 or "fork" not in multiprocessing.get_all_start_methods():
        return _simulate(designs, plant, spec)
    first, rest = _simulate(designs[:1], plant, spec), list(designs[1:])
    _POOL_JOB = (rest, plant, spec)
    try:
        ctx = multiprocessing.get_context("fork")
        with ProcessPoolExecutor(max_workers=min(workers, len(rest)), mp_context=ctx) as pool:
            return [*first, *pool.map(_verify_job, range(len(rest)))]
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
    return _baselines(plant, loop_spec(plant, scene), loops)


def _baselines(plant: Plant, spec: ResolvedProblem, loops: list[LoopModel]) -> list[Design]:
    """:func:`baseline_designs` on the resolved problem."""
    scene, lp = spec.scene, loops[0]
    ref = default_pid(plant)
    designs = []
    ki_small = ref.ki / 10.0
    best = None
    for kp in ref.kp * np.logspace(-1, 0.6, 17):
        g = (kp, ki_small, 0.0)
        if not all(l.is_stable(g) for l in loops) or lp.peak_sensitivity(g) > 2.0:
            continue
        val = spec.problem.aggregate([l.objective(g, scene.objective) for l in loops], spec)
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


def resolve_scene(plant: Plant, scene: Scene) -> tuple[Scene, str, ResolvedProblem]:
    """What a tuning run reads, fixed once: the scene with its fidelity resolved
    (:func:`~prsa_ctrl.studies.scene.choose_fidelity`), the reason for that fidelity, and the
    resolved problem (the scene's kind's :meth:`~prsa_ctrl.studies.kindruns.StepRuns.resolve`).

    Returns
    -------
    tuple
        ``(scene, fidelity_reason, problem)``: ``problem.scene`` and ``problem.fidelity_reason``
        are the first two.
    """
    res = speed_kind(scene).resolve(plant)
    return res.scene, res.fidelity_reason, res


def tune_actuator(plant: Plant, scene: Scene, workers: int | None = None,
                  resolved: ResolvedProblem | tuple | None = None) -> ActuatorTuning:
    """Tune, verify and compare (see module docstring).

    Parameters
    ----------
    plant : Plant
    scene : Scene
    workers : int, optional
        Verification processes (default: up to 4 where the machine has the cores;
        ``PRSA_WORKERS=1`` forces serial runs).
    resolved : ResolvedProblem, optional
        The scene's problem resolved against this plant (its kind's ``resolve(plant)``, or the
        tuple of :func:`resolve_scene`), when the caller has resolved it already; default:
        resolved here.

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
    # Resolve the scene once: everything below reads the resolved problem (its scene as run and
    # what the plant fixed), the tuning layer gets its numbers.
    spec = speed_kind(scene).resolve(plant) if resolved is None else resolved
    spec = spec[2] if isinstance(spec, tuple) else spec  # resolve_scene's (scene, reason, problem)
    scene, fidelity_reason = spec.scene, spec.fidelity_reason
    loops = spec.loop_models(plant)
    # Baselines use the drive's standard speed measurement; with an estimator in the scene the
    # PI tuned without it is a baseline too (the reference for what the estimator buys).
    plain = loops if scene.estimator == "none" else spec.loop_models(plant, estimator="none")
    timing["linearize"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    common = dict(objective=scene.objective, controller=scene.controller, worst_case=scene.aggregate == "worst")
    weights = spec.problem.tuner_weights(spec)
    if weights is not None:
        common["weights"] = weights
    tuner = Tuner(loops, **common)  # one scan grid and NLP for every Ms level
    runs: list[dict] = []
    suffix = (" + KF" if scene.estimator == "kf" else "") + (" + load FF" if scene.feedforward else "")

    def tuned(ms_levels: list[float]) -> list[Design]:
        """Tuned designs at these Ms bounds, predicted."""
        out = []
        for ms in ms_levels:
            res = tuner.tune(ms_max=ms, mt_max=scene.mt_max, mks_max=scene.mks_max)
            runs.append({"ms_max": ms, "result": res.status,
                         **{k: res.stats[k] for k in ("status", "iterations", "wall_time_s")}})
            out.append(Design(f"tuned (Ms <= {ms:.3g})" + suffix, res.pid, res.margins[0], estimator=scene.estimator,
                              tuner_status=res.status))
        return out

    baselines = _baselines(plant, spec, plain)
    if scene.estimator != "none":
        res = Tuner(plain, **common).tune(ms_max=scene.ms_max, mt_max=scene.mt_max, mks_max=scene.mks_max)
        baselines.insert(0, Design(f"tuned PI alone (Ms <= {scene.ms_max:.3g})", res.pid, res.margins[0]))
    # Candidates: the design at the scene's Ms bound, designs at the Ms of every baseline that
    # is more robust (they double as its equal-Ms comparison), then more robust alternatives
    # until there are ``scene.candidates``.
    ms_levels = [scene.ms_max] + sorted({b.margins.ms for b in baselines if b.margins.ms < scene.ms_max}, reverse=True)
    hedges = [1 + (scene.ms_max - 1) * f for f in (0.85, 0.7, 0.55, 0.4)]
    ms_levels += hedges[: max(0, scene.candidates - len(ms_levels))]
    candidates = tuned(ms_levels)
    candidates, baselines = _predict_all(candidates, loops, plant, spec), _predict_all(baselines, plain, plant, spec)
    timing["tune"] = time.perf_counter() - t1

    t2 = time.perf_counter()
    done = _checked_all(_verify_all(candidates + baselines, plant, spec, workers), plant, spec)
    candidates, baselines = done[: len(candidates)], done[len(candidates):]
    timing["verify"] = time.perf_counter() - t2
    best = _best(candidates)
    # Equal-Ms comparison designs where the verified best and the candidates do not settle it.
    t3 = time.perf_counter()

    def settles(d: Design, b: Design) -> bool:
        return d.healthy and d.margins.ms <= b.margins.ms * (1 + 1e-9) and d.objective_verified < b.objective_verified

    ours_for = {id(b): next((d for d in [best, *candidates] if settles(d, b)), None) for b in baselines}
    # (a baseline beyond the tuner's Ms range, e.g. a rule of thumb on a heavy linear axis, is
    # compared with the design at the range's top: still "equal or better Ms")
    unsettled = [b for b in baselines if ours_for[id(b)] is None]
    extra = dict(zip((id(b) for b in unsettled),
                     _predict_all(tuned([min(b.margins.ms, PEAK_BOUND_RANGE[1] * (1 - 1e-9)) for b in unsettled]),
                                 loops, plant, spec)))
    t4 = time.perf_counter()
    timing["tune"] += t4 - t3
    extra = dict(zip(extra, _checked_all(_verify_all(list(extra.values()), plant, spec, workers), plant, spec)))
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

    warnings_out = [f"{d.name}: {w}" for d in candidates + baselines + list(extra.values()) for w in d.warnings]
    for d in candidates + baselines + list(extra.values()):
        for f in d.flags:
            warnings_out.append(f"{d.name}: {f}")
    w_int = spec.problem.integral_warning(best)
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
        candidates=tuple(candidates + [d for d in extra.values() if d.margins.ms <= scene.ms_max]),
        baselines=tuple(baselines),
        comparisons=tuple(comparisons),
        timing_s=timing,
        solver={"name": "ipopt (CasADi)", "runs": runs},
        warnings=tuple(warnings_out),
        loops=tuple(loops),
        fidelity_reason=fidelity_reason,
        comparison_designs=tuple(d for d in extra.values() if d.margins.ms > scene.ms_max),
    )
