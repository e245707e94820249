"""What differs between the two speed-loop kinds of :mod:`prsa_ctrl.studies.scenekinds` when a
problem is tuned, predicted, verified and reported: load steps (:class:`StepRuns`, the base of
``LoadStep``) or a duty cycle's records (:class:`ProfileRuns`, the base of ``DutyCycle``).

The pipeline (:mod:`prsa_ctrl.studies.sceneloops`, :mod:`prsa_ctrl.studies.autotune`, the
report, the plots, the app) asks the problem (``spec.problem`` or
:func:`~prsa_ctrl.studies.scenekinds.problem`) instead of branching on the kind: the loop
models, the records, how the per-record objectives aggregate, the linear and the nonlinear runs
and their metrics, the warnings only one kind gives, and which studies the kind takes.

A problem is resolved against a plant once (:meth:`StepRuns.resolve`): the frozen
:class:`ResolvedProblem` holds the problem (its scene with the fidelity fixed) and only what is
derived from the plant (the fidelity the loop models are linearised at, the duty cycle's sampled
records, the steady torque); the scene's own numbers are read from the scene, not copied. The
methods that run take it as ``spec``; SI units throughout (rad/s, N, N m, s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from ..options import check_number, rad_s_to_rpm
from ..plant.plantfile import Plant
from ..sim.signals import PiecewiseLinear, normalise_profile
from .dutyscene import DutyCycleScene
from .scene import LoadStepScene, Scene, choose_fidelity

if TYPE_CHECKING:
    from ..drive.pid import PID  # CasADi: an annotation only (a bad flag is refused before CasADi loads)

__all__ = ["StepRuns", "ProfileRuns", "ResolvedProblem", "STEP_STUDIES", "speed_kind", "duty_record", "DutyRecord", "DUTY_CASES",
           "setpoint_prefilter", "linear_fidelity"]

#: What a load-step problem takes beyond tuning and a duty cycle does not: the robust study and
#: Monte Carlo (they run load steps), a filter tuned with the gains (its objective is the load
#: step), the fixed-step fast verification and the batched Monte-Carlo path (they measure on one
#: load step), the compliant model's contact-force run of the figures, a ``--step-time`` (the
#: duty cycle's events are its profile's) and the browser app's session (it tunes load steps).
STEP_STUDIES = frozenset({"robust", "monte-carlo", "tune-filter", "fast-verify", "batched", "contact-run", "step-time",
                          "app"})


def linear_fidelity(scene: Scene) -> str:
    """The fidelity the loop models are linearised at: the scene's, except that the
    multi-roller model (periodic in the cage angle) is replaced by the compliant model, its
    mean behaviour (and ``"auto"``, not yet resolved, reads as compliant).

    Parameters
    ----------
    scene : Scene

    Returns
    -------
    str
    """
    return "compliant" if scene.fidelity in ("multi-roller", "auto") else scene.fidelity


@dataclass(frozen=True)
class ResolvedProblem:
    """A speed-loop problem resolved against a plant, once (frozen; :meth:`StepRuns.resolve`):
    the problem of the scene's kind, its scene as run, and what the plant fixes. The scene's own
    numbers (setpoint, loads, times, bounds, estimator, filters, ...) are read from
    :attr:`scene`; nothing here repeats them.

    Attributes
    ----------
    problem : StepRuns
        The kind's problem (:class:`StepRuns` or :class:`ProfileRuns`); its ``scene`` is the
        scene as run (fidelity resolved where :meth:`StepRuns.resolve` chose it).
    fidelity_reason : str
        Why the verification runs at this fidelity (empty where it was not chosen).
    linear_fidelity : str
        The fidelity the loop models are linearised at (:func:`linear_fidelity`).
    records : tuple of DutyRecord
        The problem's sampled records (a duty cycle: :func:`duty_record` per case; load steps:
        none), at the plant's sample time.
    steady_torque_n_m : float, N m
        Motor torque holding the setpoint at the initial load (at :attr:`linear_fidelity`).
    """

    problem: Any = field(repr=False)
    fidelity_reason: str
    linear_fidelity: str
    records: tuple = field(repr=False)
    steady_torque_n_m: float

    @property
    def scene(self) -> Scene:
        """The scene as run (the problem's)."""
        return self.problem.scene

    def loop_models(self, plant: Plant, estimator: str | None = None) -> list:
        """The problem's loop models (one per final load or record), the speed measured as the
        scene says or as ``estimator`` (``"none"``, ``"kf"``) says."""
        return self.problem.loop_models(plant, self, self.scene.estimator if estimator is None else estimator)


@dataclass(frozen=True)
class StepRuns:
    """Load steps: one loop model, linear run and verified run per final load (``[operating]
    final_loads_n``), each starting in equilibrium before the step.

    Attributes
    ----------
    scene : Scene
    """

    #: The registry name of the kind (:data:`prsa_ctrl.studies.scenekinds.KINDS`).
    name: ClassVar[str] = "load-step"
    scene: Any

    #: The scene type of the kind (built by :func:`~prsa_ctrl.studies.scene.load_scene` or
    #: ``scene_type(**fields)``).
    scene_type: ClassVar[type] = LoadStepScene

    @classmethod
    def accepts(cls, scene: Any) -> bool:
        """Whether a loaded scene is a problem of this kind (an instance of its :attr:`scene_type`)."""
        return isinstance(scene, cls.scene_type)

    @classmethod
    def claims(cls, doc: Any) -> bool:
        """Whether a parsed scene file (its TOML document) is of this kind (its :attr:`scene_type`'s
        ``claims``, which :func:`~prsa_ctrl.studies.scene.parse_scene` asks)."""
        return cls.scene_type.claims(doc)
    #: The studies this kind takes beyond tuning (see :data:`STEP_STUDIES`).
    studies: ClassVar[frozenset] = STEP_STUDIES
    #: The figures of a report (:mod:`prsa_ctrl.plots.loop`): a kind's time responses.
    plot_panels: ClassVar[str] = "load-step"

    def takes(self, study: str) -> bool:
        """Whether the problem takes a study (a name of :data:`STEP_STUDIES`)."""
        return study in self.studies

    @property
    def described(self) -> str:
        """What the scene is, for messages (``"a load-step scene"``)."""
        return "a load-step scene"

    def records(self, plant) -> tuple:
        """The sampled records the runs read besides the scene's numbers (load steps: none)."""
        return ()

    def resolve(self, plant: Plant, choose: bool = True) -> ResolvedProblem:
        """The problem resolved against ``plant``, once: the fidelity (``choose``:
        :func:`~prsa_ctrl.studies.scene.choose_fidelity` fixes ``"auto"`` and says why; False:
        the scene's as it is, which the loop models read as compliant), the linearisation
        fidelity, the sampled records and the steady torque.

        Parameters
        ----------
        plant : Plant
            Its sample time sets the duty cycle's records.
        choose : bool

        Returns
        -------
        ResolvedProblem
        """
        from ..plant.equilibrium import operating_point  # CasADi: a bad flag is refused before it loads

        prob, reason = self, ""
        if choose:
            scene, reason = choose_fidelity(self.scene)
            prob = self if scene is self.scene else type(self)(scene)
        sc = prob.scene
        lin = linear_fidelity(sc)
        return ResolvedProblem(problem=prob, fidelity_reason=reason, linear_fidelity=lin, records=prob.records(plant),
                               steady_torque_n_m=operating_point(plant, sc.setpoint_rad_s, sc.initial_load, lin).torque)

    def loop_models(self, plant, spec, estimator: str) -> list:
        """One loop model per final load, linearised at the mid load of the step
        (:func:`prsa_ctrl.tuning.actuatorloops.step_loops`)."""
        from ..tuning.actuatorloops import step_loops

        sc = spec.scene
        return step_loops(plant, setpoint_rad_s=sc.setpoint_rad_s, initial_load_n=sc.initial_load,
                          final_loads_n=tuple(sc.final_loads), fidelity=spec.linear_fidelity,
                          horizon_s=sc.duration - sc.step_time, discrete=sc.discrete,
                          kf_load_change_time_s=sc.load_change_time_s if estimator == "kf" else None,
                          feedforward=sc.feedforward, filters=tuple(sc.filters))

    def aggregate(self, values: list[float], spec) -> float:
        """The objective over the records: the worst or the sum (``[tuning] aggregate``)."""
        if spec.scene.aggregate == "worst":
            return float(max(values))
        return float(np.sum(values))

    def tuner_weights(self, spec) -> list[float] | None:
        """Weights of the records in the tuner's objective (None: the aggregate's own)."""
        return None

    def start(self, plant, spec, design) -> tuple[float, float]:
        """``(speed rad/s, torque N m)`` before the event: the setpoint and the steady torque, or,
        for a P-only design, where the loop settles below the setpoint."""
        sc = spec.scene
        if design.pid.ki != 0:
            return sc.setpoint_rad_s, spec.steady_torque_n_m
        from ..sim.engine import initial_state

        op, _ = initial_state(plant, spec.linear_fidelity, sc.setpoint_rad_s, sc.initial_load, design.pid, 0.0, 0,
                              observer_ff=design.estimator == "kf")
        return op.omega_nut, op.torque

    def predicted_metrics(self, plant, spec, loops, trajectories, start) -> list:
        """The metrics of one design's linear runs (one per loop model)."""
        from ..sim.metrics import load_step_metrics

        w_pre, tau0 = start
        sc = spec.scene
        return [load_step_metrics(sc.step_time + lp.h * np.arange(-1, lp.n_steps),
                                  w_pre + np.concatenate([[0.0], -tr["error"]]), sc.setpoint_rad_s, sc.step_time,
                                  tau0 + np.concatenate([[0.0], tr.get("motor_torque", np.zeros(lp.n_steps))]),
                                  plant.torque_limit, direction=1 if f1 >= sc.initial_load else -1)
                for f1, lp, tr in zip(sc.final_loads, loops, trajectories)]

    def simulate(self, design, plant, spec, settings, seed: int, pre_samples: int) -> tuple[list, list]:
        """The nonlinear runs of one design: one per final load, starting ``pre_samples``
        controller samples before the step in equilibrium; ``(runs, estimation)`` with one
        ``(time s, {output: array})`` per step and the Kalman filter's speed RMS errors (rad/s)."""
        from ..drive.estimator import design_kf
        from ..sim.engine import run

        ts = plant.sample_time_s
        sc = spec.scene
        runs, estimation = [], []
        pre = min(sc.step_time, pre_samples * ts) if sc.discrete else min(sc.step_time, 1e-3)
        offset = sc.step_time - pre
        for f1 in sc.final_loads:
            kw = dict(setpoint=sc.setpoint_rad_s, load=[(0.0, sc.initial_load), (pre, f1)],
                      duration=pre + sc.duration - sc.step_time, controller=design.pid,
                      fidelity=sc.fidelity, settings=settings, seed=seed, filters=tuple(sc.filters) or None)
            measurement = "encoder"
            kf = None
            if design.estimator == "kf":
                measurement, kf = "kf", design_kf(plant, sc.load_change_time_s)
            r = run(plant, discrete=sc.discrete, measurement=measurement, kf=kf, **kw)
            if design.estimator == "kf":
                w = r.output("nut_speed")
                estimation.append({
                    "kf_speed_rms_rad_s": float(np.sqrt(np.mean((r.output("speed_measured") - w) ** 2))),
                    "fd_speed_rms_rad_s": float(np.sqrt(np.mean((r.output("speed_fd") - w) ** 2))),
                })
            t = np.asarray(r.time) + offset
            runs.append((t, dict(zip(r.output_labels, np.asarray(r.outputs)))))
        return runs, estimation

    def verified_metrics(self, plant, spec, runs) -> list:
        """The metrics of one design's nonlinear runs (:meth:`simulate`)."""
        from ..sim.metrics import load_step_metrics

        sc = spec.scene
        return [load_step_metrics(t, y["nut_speed"], sc.setpoint_rad_s, sc.step_time, y["motor_torque"],
                                  plant.torque_limit, direction=1 if f1 >= sc.initial_load else -1)
                for (t, y), f1 in zip(runs, sc.final_loads)]

    def integral_warning(self, design) -> str | None:
        """A warning when the records cannot inform the integral gain (load steps always can)."""
        return None

    def header(self, name: str, bounds: str) -> str:
        """The report's one line saying what the scene asks (``name``: the scene as named, with the
        overriding flags; ``bounds``: the sensitivity bounds)."""
        sc = self.scene
        loads = ", ".join(f"{f:g}" for f in sc.final_loads)
        return (f"{name}: {sc.setpoint_rpm:g} rpm, {sc.initial_load:g} N -> {loads} N at {sc.step_time:g} s, "
                f"record to {sc.duration:g} s; {sc.objective.upper()}, {sc.controller.upper()}, {bounds}")

    def operating_text(self, k: int) -> str:
        """Where the figures' loop response is linearised, for their titles (``k``: the level)."""
        sc = self.scene
        f0, f1 = sc.initial_load, sc.final_loads[k]
        return f"{rad_s_to_rpm(sc.setpoint_rad_s):.0f} rpm, {0.5 * (f0 + f1):g} N (mid load of {f0:g} -> {f1:g} N)"



@dataclass(frozen=True)
class ProfileRuns(StepRuns):
    """A duty cycle: one loop model, linear run and verified run per record (``scene.cases``:
    the load and/or setpoint profile), over the whole record from a steady start."""

    name: ClassVar[str] = "duty-cycle"
    studies: ClassVar[frozenset] = frozenset()
    plot_panels: ClassVar[str] = "duty-cycle"

    scene_type: ClassVar[type] = DutyCycleScene

    @property
    def described(self) -> str:
        return f"a duty cycle ({self.scene.profile_source})"

    def records(self, plant) -> tuple:
        """:func:`duty_record` of every case."""
        return tuple(duty_record(plant, self.scene, case) for case in self.scene.cases)

    def loop_models(self, plant, spec, estimator: str) -> list:
        """One sampled loop model per record, linearised at the middle of its range
        (:func:`prsa_ctrl.tuning.actuatorloops.profile_loops`), the speed measured by the encoder's
        difference or (``estimator = "kf"``) the Kalman filter."""
        from ..tuning.actuatorloops import profile_loops

        sc = spec.scene
        return profile_loops(plant, [(rec.case, rec.w_lin_rad_s, rec.f_lin_n, rec.load_sequence_n,
                                      rec.setpoint_sequence_rad_s)
                                     for rec in spec.records],
                             fidelity=spec.linear_fidelity, horizon_s=sc.duration,
                             setpoint_weight=sc.setpoint_weight, filters=tuple(sc.filters),
                             kf_load_change_time_s=sc.load_change_time_s if estimator == "kf" else None,
                             feedforward=sc.feedforward)

    def aggregate(self, values: list[float], spec) -> float:
        """The worst, the goal "mix"'s weighted sum of the load and setpoint records, or the sum."""
        sc = spec.scene
        if sc.aggregate == "worst":
            return float(max(values))
        if sc.goal == "mix":
            return float((1.0 - sc.setpoint_share) * values[0] + sc.setpoint_share * values[1])
        return float(np.sum(values))

    def tuner_weights(self, spec) -> list[float] | None:
        sc = spec.scene
        return [1.0 - sc.setpoint_share, sc.setpoint_share] if sc.goal == "mix" else None

    def start(self, plant, spec, design) -> tuple[float, float]:
        """The record starts at the setpoint with the steady torque (any design)."""
        return spec.scene.setpoint_rad_s, spec.steady_torque_n_m

    def predicted_metrics(self, plant, spec, loops, trajectories, start) -> list:
        from ..sim.metrics import profile_metrics

        _, tau0 = start
        return [profile_metrics(rec.time_s[: lp.n_steps], rec.setpoint_at_rad_s[: lp.n_steps] - tr["error"],
                                rec.setpoint_at_rad_s[: lp.n_steps], tau0 + tr["motor_torque"],
                                plant.torque_limit, rec.load_steps, rec.breaks_s)
                for rec, lp, tr in zip(spec.records, loops, trajectories)]

    def simulate(self, design, plant, spec, settings, seed: int, pre_samples: int) -> tuple[list, list]:
        """One sampled run per record, over the whole record, with the scene's profiles (a setpoint
        weight ``b != 1`` through :func:`setpoint_prefilter`); ``(runs, estimation)`` as
        :meth:`StepRuns.simulate` (the Kalman filter's speed RMS errors, rad/s, per record)."""
        from ..drive.estimator import design_kf
        from ..sim.engine import run

        ts = plant.sample_time_s
        sc = spec.scene
        runs, estimation = [], []
        kf = design_kf(plant, sc.load_change_time_s) if design.estimator == "kf" else None
        for rec in spec.records:
            setpoint = rec.setpoint_rad_s
            if rec.case == "setpoint profile" and sc.setpoint_weight != 1.0:
                rf = setpoint_prefilter(rec.setpoint_at_rad_s, design.pid, ts, sc.setpoint_weight)
                n_pts = int(np.searchsorted(rec.time_s, sc.duration - 1e-9 * ts))  # points before the end
                setpoint = PiecewiseLinear(tuple(zip(rec.time_s[:n_pts].tolist(), rf[:n_pts].tolist())))
            r = run(plant, discrete=True, setpoint=setpoint, load=rec.load_n, duration=sc.duration,
                    controller=design.pid, fidelity=sc.fidelity, settings=settings, seed=seed,
                    filters=tuple(sc.filters) or None, measurement="encoder" if kf is None else "kf", kf=kf)
            t = np.asarray(r.time)
            y = dict(zip(r.output_labels, np.asarray(r.outputs)))
            if kf is not None:
                w = y["nut_speed"]
                estimation.append({"kf_speed_rms_rad_s": float(np.sqrt(np.mean((y["speed_measured"] - w) ** 2))),
                                   "fd_speed_rms_rad_s": float(np.sqrt(np.mean((y["speed_fd"] - w) ** 2)))})
            y["setpoint"] = rec.setpoint_at_rad_s[: t.size]
            runs.append((t, y))
        return runs, estimation

    def verified_metrics(self, plant, spec, runs) -> list:
        from ..sim.metrics import profile_metrics

        return [profile_metrics(t, y["nut_speed"], y["setpoint"], y["motor_torque"], plant.torque_limit,
                                rec.load_steps, rec.breaks_s)
                for (t, y), rec in zip(runs, spec.records)]

    def integral_warning(self, design) -> str | None:
        """A warning (not a flag) when the record cannot inform the integral gain: the integral
        time ``Ti = kp / ki`` is longer than the record (or ``ki = 0``), so the objective barely
        depends on ``ki`` and the tuner's value is arbitrary (see
        :func:`prsa_ctrl.studies.autotune.integral_warning`)."""
        sc = self.scene
        if sc.controller not in ("pi", "pid"):
            return None
        kp, ki = design.pid.kp, design.pid.ki
        record = sc.duration
        ti = kp / ki if ki > 0 else math.inf
        if ti <= record:
            return None
        ti_text = f"Ti = {ti:.3g} s" if math.isfinite(ti) else "ki = 0"
        if sc.goal == "setpoint":
            return (f"the setpoint-only goal does not inform the integral gain ({ti_text} > record {record:g} s): the "
                    "objective hardly changes with ki, so this design holds a load change only slowly; use goal = "
                    "\"mix\" with a load profile (or a load-step scene) to tune ki for load rejection")
        return (f"the integral time is longer than the record ({ti_text} > {record:g} s): the record does not show the "
                "integral's effect and does not inform ki; lengthen the record or add load changes")

    def header(self, name: str, bounds: str) -> str:
        sc = self.scene
        goal = {"load": "load rejection", "setpoint": "setpoint tracking",
                "mix": f"mix, setpoint share {sc.setpoint_share:g}"}[sc.goal]
        b = f", setpoint weight b = {sc.setpoint_weight:g}" if sc.setpoint_profile is not None else ""
        return (f"{name}: duty cycle ({sc.profile_source}) from {sc.setpoint_rpm:g} rpm, {sc.initial_load:g} N, "
                f"record to {sc.duration:g} s; {sc.objective.upper()} over the record ({goal}{b}), "
                f"{sc.controller.upper()}, {bounds}")

    def operating_text(self, k: int) -> str:
        sc = self.scene
        return f"{rad_s_to_rpm(sc.setpoint_rad_s):.0f} rpm, {sc.initial_load:g} N (start of the {sc.name} duty cycle)"


def speed_kind(scene: Scene) -> StepRuns:
    """The runs of a speed-loop scene's kind: :class:`ProfileRuns` of a duty cycle, else
    :class:`StepRuns` (the base of :class:`~prsa_ctrl.studies.scenekinds.DutyCycle` and
    :class:`~prsa_ctrl.studies.scenekinds.LoadStep`, whose :func:`~prsa_ctrl.studies.scenekinds.problem`
    adds the studies and the report).

    Raises
    ------
    TypeError
        Not a speed-loop :class:`~prsa_ctrl.studies.scene.Scene`.
    """
    for kind in (ProfileRuns, StepRuns):
        if kind.accepts(scene):
            return kind(scene)
    raise TypeError(f"scene = {type(scene).__name__}; expected a prsa_ctrl Scene (prsa_ctrl.load_scene)")


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
    >>> from prsa_ctrl.drive.pid import PID
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


def _n_samples(plant: Plant, scene) -> int:
    return max(10, int(round(scene.duration / plant.sample_time_s)))


#: The cases of a duty cycle (``scene.cases``): which profile a record follows.
DUTY_CASES = ("load profile", "setpoint profile")


def _frozen_array(name: str, value, size: int | None = None) -> np.ndarray:
    """A read-only float copy of a 1-D finite array (``size``: its required length)."""
    try:
        a = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"DutyRecord {name} = {value!r}; expected a 1-D array of numbers") from None
    if a.ndim != 1 or (size is not None and a.size != size):
        want = f"{size} samples" if size is not None else "a 1-D array"
        raise ValueError(f"DutyRecord {name} has shape {a.shape}; expected {want}")
    if not np.all(np.isfinite(a)):
        i = int(np.flatnonzero(~np.isfinite(a))[0])
        raise ValueError(f"DutyRecord {name}[{i}] = {float(a[i])!r}; expected finite numbers")
    a.flags.writeable = False
    return a


@dataclass(frozen=True, eq=False)
class DutyRecord:
    """One record of a duty-cycle scene, as the loop model and the verification see it
    (:func:`duty_record`), sampled at the plant's sample time; frozen, its arrays read-only, SI
    units. Checked when built: a known case, finite values, the sample arrays' lengths, and the
    one profile the case follows (a load profile has a load sequence and no setpoint sequence, a
    setpoint profile the other way round); a bad field raises ``ValueError`` naming it.

    Attributes
    ----------
    case : {"load profile", "setpoint profile"}
        Which of the scene's profiles the record follows (one of ``scene.cases``).
    time_s : array, s
        The controller's sample times ``0, Ts, ..., n Ts`` (``n + 1`` values, increasing).
    setpoint_at_rad_s : array, rad/s
        The setpoint at :attr:`time_s` (the initial setpoint throughout for a load profile).
    load_n : float or PiecewiseLinear, N
        The simulator's axial load: the scene's load profile, or the constant initial load.
    setpoint_rad_s : float or PiecewiseLinear, rad/s
        The simulator's setpoint: the scene's setpoint profile, or the constant setpoint.
    load_sequence_n : array, N, or None
        A load profile: the mean load deviation from the initial load over each controller
        sample (``n`` values, the exact mean of the piecewise-linear profile); else None.
    setpoint_sequence_rad_s : array, rad/s, or None
        A setpoint profile: the setpoint deviation the controller reads at each sample (``n + 1``
        values, the first 0); else None.
    load_steps : tuple of (time s, signed size N)
        Each step of the load profile.
    breaks_s : tuple of float, s
        Every change of the profile after its first point.
    w_lin_rad_s : float, rad/s
        Where the loop model is linearised: the middle of the setpoint profile's range (the
        setpoint for a load profile).
    f_lin_n : float, N
        Likewise for the load: the middle of the load profile's range (the initial load for a
        setpoint profile).
    """

    case: str
    time_s: np.ndarray = field(repr=False)
    setpoint_at_rad_s: np.ndarray = field(repr=False)
    load_n: Any = field(repr=False)
    setpoint_rad_s: Any = field(repr=False)
    load_sequence_n: np.ndarray | None = field(repr=False)
    setpoint_sequence_rad_s: np.ndarray | None = field(repr=False)
    load_steps: tuple = ()
    breaks_s: tuple = ()
    w_lin_rad_s: float = 0.0
    f_lin_n: float = 0.0

    def __post_init__(self) -> None:
        if self.case not in DUTY_CASES:
            raise ValueError(f"DutyRecord case = {self.case!r}; expected one of {', '.join(map(repr, DUTY_CASES))}")
        t = _frozen_array("time_s", self.time_s)
        if t.size < 2 or t[0] != 0.0 or np.any(np.diff(t) <= 0.0):
            raise ValueError(f"DutyRecord time_s runs {t[:3].tolist()}...; expected increasing sample times from 0 s")
        set_ = object.__setattr__
        set_(self, "time_s", t)
        set_(self, "setpoint_at_rad_s", _frozen_array("setpoint_at_rad_s", self.setpoint_at_rad_s, t.size))
        load_case = self.case == "load profile"
        for name, size, needed in (("load_sequence_n", t.size - 1, load_case),
                                   ("setpoint_sequence_rad_s", t.size, not load_case)):
            value = getattr(self, name)
            if needed and value is None:
                raise ValueError(f"DutyRecord {name} = None; expected {size} samples for a {self.case}")
            if not needed and value is not None:
                raise ValueError(f"DutyRecord {name} given for a {self.case}; expected None")
            if value is not None:
                set_(self, name, _frozen_array(name, value, size))
        for name in ("load_n", "setpoint_rad_s"):
            value = getattr(self, name)
            if not isinstance(value, PiecewiseLinear):
                set_(self, name, check_number(f"DutyRecord {name}", value))
        set_(self, "load_steps", tuple((check_number("DutyRecord load_steps time", tk), check_number("DutyRecord load_steps size", df))
                                       for tk, df in self.load_steps))
        set_(self, "breaks_s", tuple(check_number("DutyRecord breaks_s", x) for x in self.breaks_s))
        set_(self, "w_lin_rad_s", check_number("DutyRecord w_lin_rad_s", self.w_lin_rad_s))
        set_(self, "f_lin_n", check_number("DutyRecord f_lin_n", self.f_lin_n))


def duty_record(plant: Plant, scene, case: str) -> DutyRecord:
    """One record of a duty-cycle scene, as the loop model and the verification see it.

    Parameters
    ----------
    plant : Plant
        Its sample time (s) sets the record's samples.
    scene : Scene
        A duty-cycle scene (:class:`~prsa_ctrl.studies.scenekinds.DutyCycle`).
    case : {"load profile", "setpoint profile"}
        One of ``scene.cases``.

    Returns
    -------
    DutyRecord
        The simulator's profiles, the sequences the sampled loop model reads, the sample times and
        the setpoint at them, the load steps and breaks, and the linearisation point (the middle
        of the profile's range), in SI units.
    """
    ts = plant.sample_time_s
    n = _n_samples(plant, scene)
    t = ts * np.arange(n + 1)
    w0, f0 = scene.setpoint_rad_s, scene.initial_load
    if case == "load profile":
        pts = scene.load_profile
        prof = normalise_profile(PiecewiseLinear(pts), scene.duration + 1.0, "load", "N")
        # Exact mean over each sample interval: integral of the piecewise-linear load.
        edges = ts * np.arange(n + 1)
        seg_len = np.append(np.diff(prof.t), np.inf)
        lens = np.clip(edges[:, None] - prof.t[None, :], 0.0, seg_len[None, :])
        integral = lens @ prof.v + (lens * lens) @ prof.s / 2.0
        vals = [v for _, v in pts]
        return DutyRecord(case=case, time_s=t, setpoint_at_rad_s=np.full(n + 1, w0), load_n=PiecewiseLinear(pts),
                          setpoint_rad_s=w0, load_sequence_n=np.diff(integral) / ts - f0,
                          setpoint_sequence_rad_s=None,
                          load_steps=[(float(tk), float(prof.v[i] - prof.at(tk - 1e-9)))
                                      for i, tk in enumerate(prof.t) if prof.jump[i]],
                          breaks_s=[float(x) for x in prof.t[1:]], w_lin_rad_s=w0,
                          f_lin_n=0.5 * (min(vals) + max(vals)))
    if case != "setpoint profile":
        raise ValueError(f"case = {case!r}; expected one of {', '.join(map(repr, DUTY_CASES))}")
    pts = scene.setpoint_profile
    prof = normalise_profile(PiecewiseLinear(pts), scene.duration + 1.0, "setpoint", "rad/s")
    r = prof.at(t)
    deviation = r - w0
    deviation[0] = 0.0
    vals = [v for _, v in pts]
    return DutyRecord(case=case, time_s=t, setpoint_at_rad_s=r, load_n=f0, setpoint_rad_s=PiecewiseLinear(pts),
                      load_sequence_n=None, setpoint_sequence_rad_s=deviation,
                      breaks_s=[float(x) for x in prof.t[1:]], w_lin_rad_s=0.5 * (min(vals) + max(vals)),
                      f_lin_n=f0)
