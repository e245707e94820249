"""Scene kinds as a registry of types, in the manner of scipy's ``METHODS``:
``KINDS = {"load-step": LoadStep, "duty-cycle": DutyCycle, "move": Move}``.

Each kind is a frozen problem type built from a loaded scene (:func:`problem`):

* :meth:`resolve` fixes what the run reads once (the fidelity, the duty cycle's sampled
  records, the operating points): the frozen
  :class:`~prsa_ctrl.studies.kindruns.ResolvedProblem` of a speed-loop kind (the problem on its
  scene as run and what the plant fixes, no copy of the scene's numbers), the scene itself for a
  move, whose fidelity is written in the file;
* :meth:`tune` tunes and verifies it, with the studies a caller asks for
  (:class:`TuneOptions`), and returns the kind's report;
* the report (:class:`SpeedReport`, :class:`MoveReport`) owns its JSON (:meth:`as_dict`), its
  text (:meth:`format`) and what its drive export holds (:meth:`export_target`).

A Kalman-filter scene (``[estimator] kind = "kf"``) is a :class:`LoadStep` or a
:class:`DutyCycle`: the problem (the records, the speed PI/PID, the same verification and
report) is the same; only the speed measurement of the loop models and of the verified runs
differs, a measurement block of the one loop builder, not a kind of problem.

``prsa-tune`` parses its flags, loads the scene, builds its problem here, tunes, and prints
or writes the report: it does not branch on the kind.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Callable, ClassVar, Mapping, Sequence

from ..errors import SceneError, UsageError
from ..textsafe import quote
from ..results import json_safe
from .kindruns import ProfileRuns, StepRuns
from .movescene import MoveScene
from .scene import Scene

__all__ = ["KINDS", "kind_of", "problem", "file_kind", "MOVE_FLAGS", "LoadStep", "DutyCycle", "Move", "TuneOptions", "SpeedReport",
           "MoveReport", "ExportTarget", "add_design", "add_setpoint_weight", "setpoint_weight", "export_choice"]


#: ``prsa-tune`` options (argparse destinations) a move scene honours; every other option given is
#: refused (:meth:`Move.refuse_flags`, exit 2).
MOVE_FLAGS = ("plant", "scene", "json", "export", "plots", "quiet", "verbose", "export_real", "export_template", "motor",
              "rated_torque", "friction_ff")


def _quiet(_text: str) -> None:
    return None


def _nothing(*_args: Any) -> None:
    return None


@dataclass(frozen=True)
class TuneOptions:
    """What a caller asks besides the scene (``prsa-tune``'s study flags).

    Attributes
    ----------
    workers : int, optional
        Verification and Monte-Carlo processes (None: the machine's default).
    tune_filter : {"notch", "lowpass", "lowpass2"}, optional
        A filter tuned with the gains (speed-loop kinds).
    robust : bool
        The robust study even without a ``[robust]`` section.
    design_to_spec : bool
    monte_carlo : int, optional
        Samples (None: the scene's ``[robust] monte_carlo``; 0: off).
    seed : int, optional
    scheduler : str or dask Client, optional
    quiet : bool
    friction_ff : bool
        Move kind: verify and export the joint design with the friction feed-forward.
    progress : callable
        Called with a progress line (str).
    checkpoint : callable
        Called without arguments between the stages; raises to stop the run (e.g.
        ``KeyboardInterrupt`` after a solver the user stopped returned).
    """

    workers: int | None = None
    tune_filter: str | None = None
    robust: bool = False
    design_to_spec: bool = False
    monte_carlo: int | None = None
    seed: int | None = None
    scheduler: Any = None
    quiet: bool = False
    friction_ff: bool = False
    progress: Callable[[str], None] = field(default=_quiet, compare=False)
    checkpoint: Callable[[], None] = field(default=_nothing, compare=False)


@dataclass(frozen=True)
class ExportTarget:
    """What a report's ``--export`` holds, for the writers of :mod:`prsa_ctrl.io`.

    Attributes
    ----------
    design : PID or CascadeDesign or None
        None: nothing to export (``choice["why"]`` says why).
    plant : Plant
    choice : dict
        How the design was chosen (``name``, ``chosen_by``, ...); empty for a cascade.
    setpoint_weight : float or None
        The 2-DOF b of a speed loop; None for a cascade.
    filters : tuple
        The loop filters exported with the gains.
    friction_table_speed_rad_s : float or None
        A cascade's friction table's top speed, rad/s.
    """

    design: Any
    plant: Any
    choice: Mapping[str, Any]
    setpoint_weight: float | None = None
    filters: tuple = ()
    friction_table_speed_rad_s: float | None = None

    @property
    def is_cascade(self) -> bool:
        """Whether the design is a position/speed cascade (else a speed PI/PID)."""
        return self.setpoint_weight is None


# --- the speed-loop kinds -------------------------------------------------------------------------

def setpoint_weight(scene: Scene) -> float:
    """The 2-DOF setpoint weight b the design runs with (1 unless a duty cycle's setpoint
    profile sets ``[tuning] setpoint_weight``)."""
    return scene.design_setpoint_weight


def add_setpoint_weight(data: dict, scene: Scene) -> None:
    """Put the scene's b (:func:`setpoint_weight`) into every ``gains`` block of a JSON report
    (the controller law is ``u = kp (b r - y) + I``; b = 1 for load-step scenes)."""
    b = setpoint_weight(scene)

    def walk(obj, depth: int = 0) -> None:
        if depth > 6:
            return
        if isinstance(obj, dict):
            for k, v in obj.items():
                if k == "gains" and isinstance(v, dict) and "kp" in v:
                    v.setdefault("b", b)
                else:
                    walk(v, depth + 1)
        elif isinstance(obj, list):
            for v in obj:
                walk(v, depth + 1)

    walk(data)
    units = data.get("units")
    if isinstance(units, dict):
        units.setdefault("b", "dimensionless (2-DOF setpoint weight: u = kp (b r - y) + I)")


def add_design(designs: dict, name: str, pid) -> None:
    """Add a design to verify unless one with the same gains is there already (one name per
    design: the robust study's nominal design is the tuned design when their gains agree)."""
    key = (pid.kp, pid.ki, pid.kd, pid.tf, pid.kff)
    if name in designs or any((p.kp, p.ki, p.kd, p.tf, p.kff) == key for p in designs.values()):
        return
    designs[name] = pid


def export_choice(rep, robust_rep) -> tuple[Any, dict]:
    """The design ``--export`` writes and how it was chosen: the robust study's recommended
    design (:meth:`prsa_ctrl.tuning.robust.RobustTuning.recommend`) when there is one, else the
    tuned design; ``(None, {"why": ...})`` when there is none to export."""
    if robust_rep is not None:
        r = robust_rep.recommended or robust_rep.recommend()
        if r.get("design") is None:
            return None, {"why": f"no design recommended ({r['why']})"}
        d = {"name": r.get("name") or f"{r['design']} design", "chosen_by": "recommended by the robust study",
             "why": r["why"],
             "basis": r["basis"]}
        if r.get("yield") is not None:
            d["yield"] = r["yield"]
        return robust_rep.design(r["design"]), d
    if rep.best.pid.kff != 0:
        return None, {"why": "the best design feeds the Kalman filter's load estimate forward (kff > 0), which the "
                             "drive export does not describe"}
    return rep.best.pid, {"name": rep.best.name, "chosen_by": "the tuned design (no robust study)"}


@dataclass(frozen=True)
class SpeedReport:
    """The report of a speed-loop problem (:class:`LoadStep`, :class:`DutyCycle`).

    Attributes
    ----------
    kind : str
        The registry name of the problem's kind.
    rep : ActuatorTuning
    robust : RobustTuning or None
    mc : MonteCarloReport or None
    filter_tuning : SceneFilterTuning or None
    design_to_spec : DesignToSpec or None
    coordinates : str
        The coordinates the numbers are in (the JSON's ``coordinates``).
    """

    kind: str
    rep: Any
    robust: Any = None
    mc: Any = None
    filter_tuning: Any = None
    design_to_spec: Any = None
    coordinates: str = ""

    @property
    def status(self) -> str:
        """The best design's status (``"ok"`` or why not)."""
        return self.rep.status

    @property
    def timing_s(self) -> dict:
        """The run's timings, s (mutable: a command adds its process time)."""
        return self.rep.timing_s

    @property
    def scene(self) -> Scene:
        """The scene as tuned (with a tuned filter added, its fidelity resolved)."""
        return self.rep.scene

    def as_dict(self) -> dict:
        """The JSON report (``prsa-tune --json``)."""
        rep = self.rep
        data = rep.as_dict()
        data["coordinates"] = self.coordinates
        data["timing_s"] = dict(rep.timing_s)
        add_setpoint_weight(data, rep.scene)
        if self.robust is not None:
            data["robust"] = self.robust.as_dict()
            data["recommended"] = data["robust"]["recommended"]
        if self.mc is not None:
            data["monte_carlo"] = self.mc.as_dict()
        if self.design_to_spec is not None:
            data["design_to_spec"] = self.design_to_spec.as_dict()
        if self.filter_tuning is not None:
            data["filter_tuning"] = json_safe(self.filter_tuning.as_dict())
        return data

    def format(self, overrides: Sequence[str] = ()) -> str:
        """The text report (the flags that overrode the scene named as typed)."""
        from .scenereport import format_report, format_robust

        parts = [format_report(self.rep, overrides)]
        if self.filter_tuning is not None:
            parts.append("\n".join(self.filter_tuning.lines()))
        if self.robust is not None:
            parts.append(format_robust(self.robust))
        if self.mc is not None:
            from .montecarlo import format_report as format_mc

            parts.append(format_mc(self.mc))
        return "\n".join(parts)

    def export_target(self) -> ExportTarget:
        """The design the drive export holds (the robust study's recommendation where it ran)."""
        design, choice = export_choice(self.rep, self.robust)
        return ExportTarget(design, self.rep.plant, choice, setpoint_weight(self.rep.scene),
                            tuple(self.rep.scene.filters))

    def file_lines(self, json: str | None = None, export: str | None = None, target: ExportTarget | None = None,
                   plots: Sequence[Any] | None = None) -> list[str]:
        """The lines naming the files written: the JSON report, the plots (None: not asked),
        the drive export and the design it holds (``target``: :meth:`export_target`)."""
        lines = [] if json is None else [f"JSON report: {json}"]
        if plots is not None:
            lines.append(f"plots: {', '.join(str(p) for p in plots)}")
        if export is not None:
            choice = (target or self.export_target()).choice
            lines.append(f"drive export: {export} holds the design {choice['name']!r}, {choice['chosen_by']}")
        return lines


@dataclass(frozen=True)
class LoadStep(StepRuns):
    """A speed-loop problem on load steps (``[operating] final_loads_n``), with the drive's
    speed measurement or a Kalman filter (``[estimator]``). What its runs do (loop models,
    linear and nonlinear runs, metrics, the studies it takes) is :class:`~prsa_ctrl.studies.kindruns.StepRuns`'.

    Attributes
    ----------
    scene : Scene
    """

    name: ClassVar[str] = "load-step"
    #: Whether a command announces "linearise, tune, verify" before the run.
    announces: ClassVar[bool] = True
    #: The command's options the kind honours (argparse destinations); None: every one (the
    #: overrides it does not take are refused once the scene is loaded, :meth:`check_overrides`).
    flags: ClassVar[tuple[str, ...] | None] = None
    scene: Scene

    @classmethod
    def load(cls, scene_ref, plant_ref, given: Sequence[tuple[str, str]], override: Callable[[], Any]):
        """Plant and scene for a command: a speed-loop scene takes the command's overrides, so
        the command's own loader does it (``override()``: ``prsa_ctrl.cli.inputs.load_and_override``,
        plant first, then the scene, the overrides and the check against the plant).

        Returns
        -------
        (Plant, Scene, list of str)
            With the overriding flags as typed.
        """
        return override()

    def __post_init__(self) -> None:
        if not type(self).accepts(self.scene):
            raise SceneError(f"{getattr(self.scene, 'origin', '<scene>')}: not a {self.name} scene; expected "
                             f"{kind_of(self.scene)}")

    def what(self, plant) -> str:
        """What the run does, for progress and failure lines."""
        sc = self.scene
        return (f"tuning {plant.name} at {sc.setpoint_rpm:g} rpm, {sc.initial_load:g} N -> "
                f"{', '.join(f'{f:g}' for f in sc.final_loads)} N")

    def check_options(self, options: TuneOptions) -> None:
        """Refuse the study options the problem does not take, before any work.

        Raises
        ------
        UsageError
            One line naming the option as typed and what was expected.
        """
        sc = self.scene
        if options.friction_ff:
            raise UsageError(f"--friction-ff does not apply to the speed-loop scene {sc.name}; expected a move "
                             "scene (the feed-forward acts from a motion profile's speed), e.g. --scene "
                             "paper-slow-reversal")
        if options.design_to_spec:
            self._check_design_to_spec(options)

    def _check_design_to_spec(self, options: TuneOptions) -> None:
        sc = self.scene
        if not sc.sections.spec_bounds:
            raise UsageError(f"--design-to-spec: the scene {sc.name} has no [spec] section; expected the bounds "
                             "to design to (e.g. [spec] peak_drop_rad_s = 12.0)")
        if options.monte_carlo == 0:
            raise UsageError("--design-to-spec with --monte-carlo 0; expected a sample count of the final check >= 1")
        from .designspec import SAMPLES_MAX
        from .montecarlo import scene_options

        # the final check's sample count, refused here rather than by the study after the robust tuning (was exit 3)
        if options.monte_carlo is not None and options.monte_carlo > SAMPLES_MAX:
            raise UsageError(f"--design-to-spec with --monte-carlo {options.monte_carlo}; expected a sample count of "
                             f"the final check in 1..{SAMPLES_MAX}")
        n_scene = scene_options(sc)["samples"]
        if options.monte_carlo is None and n_scene > SAMPLES_MAX:
            raise UsageError(f"--design-to-spec: the scene {sc.name} has [robust] monte_carlo = {n_scene}; expected "
                             f"a sample count of the final check in 1..{SAMPLES_MAX} (or --monte-carlo N)")

    def check_overrides(self, given: Mapping[str, Any], typed: Mapping[str, str]) -> None:
        """Refuse the command-line overrides of the scene the problem does not take (a load-step
        problem takes them all).

        Parameters
        ----------
        given : Mapping
            Flag (``"--load-step"``) -> the parsed value, None or False when not given.
        typed : Mapping
            Flag -> the text as typed (``--flag=text`` forms), for the messages.
        """

    def check_export(self, path: str) -> None:
        """Refuse a drive export of what it cannot describe (the Kalman filter's load feed-forward).

        Raises
        ------
        UsageError
        """
        if self.scene.feedforward:
            raise UsageError(f"--export {path!r} with --feedforward: the drive export does not describe the "
                             "Kalman filter's load-torque feed-forward (kff > 0); expected --export without "
                             "--feedforward (or no --export)")

    def check(self, options: TuneOptions) -> None:
        """Refuse a filter to tune where the filter tuner does not apply (one line), once the
        outputs are checked."""
        if options.tune_filter is not None:
            from .scenetunefilter import check_tune_filter

            check_tune_filter(self.scene, options.tune_filter)

    def tune(self, plant, options: TuneOptions = TuneOptions(), coordinates: str = "") -> SpeedReport:
        """Tune and verify (:func:`prsa_ctrl.studies.autotune.tune_actuator`), then the studies
        asked: a filter tuned with the gains first, the robust design, Monte Carlo, design to spec."""
        from .autotune import tune_actuator

        prob, ft = self, None
        if options.tune_filter is not None:  # issue 24: a filter tuned with the gains joins the scene's
            from .scenetunefilter import tune_scene_filter

            options.progress(f"tuning a {options.tune_filter} with the gains ...")
            ft = tune_scene_filter(plant, self.scene, options.tune_filter)
            prob = replace(self, scene=ft.scene)
            options.checkpoint()
        rep = tune_actuator(plant, prob.scene, workers=options.workers, resolved=prob.resolve(plant))
        options.checkpoint()
        if options.design_to_spec:
            robust_rep, mc, dts = _design_to_spec(plant, rep, options)
            return SpeedReport(self.name, rep, robust_rep, mc, ft, dts, coordinates)
        robust_rep, mc = _robust_and_monte_carlo(plant, rep, options)
        return SpeedReport(self.name, rep, robust_rep, mc, ft, None, coordinates)


@dataclass(frozen=True)
class DutyCycle(ProfileRuns, LoadStep):
    """A speed-loop problem on a duty cycle: a load and/or setpoint profile (``load_profile_n``,
    ``setpoint_profile_rpm``, a CSV trace); tuned on the whole record, no robust study. What its
    runs do is :class:`~prsa_ctrl.studies.kindruns.ProfileRuns`'.

    Attributes
    ----------
    scene : Scene
    """

    name: ClassVar[str] = "duty-cycle"

    def what(self, plant) -> str:
        return f"tuning {plant.name} on the {self.scene.name} duty cycle"

    def _check_design_to_spec(self, options: TuneOptions) -> None:
        raise UsageError(f"--design-to-spec does not apply to the scene {self.scene.name}; expected a load-step scene "
                         "with a [spec] section")

    def check_overrides(self, given: Mapping[str, Any], typed: Mapping[str, str]) -> None:
        """Refuse the robust and Monte-Carlo studies and the flags that set load steps or (with a
        setpoint profile) the setpoint: the profile sets them (the Kalman filter is taken).

        Raises
        ------
        UsageError
            One line naming the flag as typed.
        """
        sc = self.scene
        for flag in ("--robust", "--monte-carlo", "--scheduler"):
            if given.get(flag):
                raise UsageError(f"{flag}: scene {sc.name} is a duty cycle ({sc.profile_source}); expected a "
                                 "load-step scene (the robust and Monte-Carlo studies run load steps)")
        for flag, v in (("--load-step", given.get("--load-step")), ("--step-time", given.get("--step-time")),
                        ("--setpoint-rpm", given.get("--setpoint-rpm") if sc.setpoint_profile is not None else None)):
            if v is not None:
                raise UsageError(f"{flag} {quote(typed.get(flag, v))}: scene {sc.name} is a duty cycle "
                                 f"({sc.profile_source}); expected its profile to set the "
                                 f"{'load' if flag != '--setpoint-rpm' else 'setpoint'} "
                                 "and events (edit the scene file to change them)")


def _robust_and_monte_carlo(plant, rep, options: TuneOptions):
    """The robust design (``options.robust`` or a scene ``[robust]`` section) and the Monte-Carlo
    verification (``options.monte_carlo`` or the scene's setting) of the report's designs."""
    from .autotune import default_workers
    from .montecarlo import run_monte_carlo, scene_options

    scene = rep.scene
    opts = scene_options(scene)
    has_robust = scene.sections.robust is not None and bool(scene.sections.robust.given)
    robust_rep = None
    if options.robust or has_robust:
        from .scenerobust import tune_robust_actuator

        options.progress("robust tuning over the scenario models ...")
        robust_rep = tune_robust_actuator(plant, scene)
        options.checkpoint()
    n = options.monte_carlo if options.monte_carlo is not None else opts["samples"]
    if not n:
        return robust_rep, None
    designs = {rep.best.name: rep.best.pid}
    if robust_rep is not None:
        designs = {"nominal design": robust_rep.nominal, "robust design": robust_rep.robust}
        add_design(designs, rep.best.name, rep.best.pid)
        # every design the run tuned: the recommendation ranks them all on the same samples
        for c in getattr(rep, "candidates", ()) or ():
            if c.pid.kff == 0:
                add_design(designs, c.name, c.pid)
    for b in rep.baselines:
        add_design(designs, b.name, b.pid)
    seed = options.seed if options.seed is not None else opts["seed"]
    options.progress(f"Monte Carlo: {n} samples of {len(designs)} designs ...")
    # Like the verification: in parallel on the machine's cores unless told otherwise.
    mc = run_monte_carlo(plant, scene, designs, n, seed=seed, scheduler=options.scheduler,
                         workers=options.workers or default_workers(), quiet=options.quiet)
    if robust_rep is not None:
        others = {k: v for k, v in designs.items() if k not in ("nominal design", "robust design")}
        robust_rep = robust_rep.with_recommendation(mc, others=others, target=scene.sections.yield_target)
    return robust_rep, mc


def _design_to_spec(plant, rep, options: TuneOptions):
    """Design to spec: the robust study, then :func:`prsa_ctrl.studies.designspec.design_to_spec`
    over the nominal and robust designs at a sequence of Ms bounds and the run's designs; the
    Monte-Carlo report is the chosen design's on fresh samples."""
    from .autotune import default_workers
    from .designspec import design_to_spec
    from .montecarlo import scene_options
    from .scenerobust import tune_robust_actuator

    scene = rep.scene
    if not scene.sections.spec_bounds:
        raise SceneError(f"{scene.origin}: --design-to-spec needs a [spec] section; expected the bounds to design to")
    opts = scene_options(scene)
    n = options.monte_carlo or opts["samples"] or 200
    seed = options.seed if options.seed is not None else opts["seed"]
    options.progress("robust tuning over the scenario models ...")
    rr = tune_robust_actuator(plant, scene)
    options.checkpoint()
    extra = {"nominal design": rr.nominal, "robust design": rr.robust}
    for d in (rep.best, *(getattr(rep, "candidates", ()) or ()), *rep.baselines):
        add_design(extra, d.name, d.pid)
    n_search = min(64, n)
    options.progress(f"design to the spec: proposals on {n_search} common samples, the chosen one on "
                     f"{n} fresh samples ...")
    dts = design_to_spec(plant, scene, n_search=n_search, n_final=n, seed=seed, extra=extra,
                         workers=options.workers or default_workers(), quiet=options.quiet, robust=rr)
    s = dts.search
    d = dts.decide or s  # the decision among the (near-)maximal designs on more samples, where it ran
    nd = d["rows"][0]["samples"] if dts.decide and d.get("rows") else n_search
    basis = (f"design to the spec: {len(dts.designs)} designs screened on {n_search} common Monte-Carlo samples "
             f"(seed {dts.search_seed})" + (f", the {len(d['rows'])} of (near-)maximal yield decided on {nd} samples "
                                            "of the same seed" if dts.decide else "")
             + f"; yield on {n} fresh samples (seed {dts.final_seed})")
    rec = {"basis": basis, "table": s.get("rows", []), "rule": s.get("rule", ""),
           **{k: d[k] for k in ("target", "reached", "limit") if k in d}}
    if dts.decide:
        rec["decide_table"] = d.get("rows", [])
    fy = dts.final_yield
    if fy is None:
        rec.update(design=None, name=None, why=s.get("why", "no design chosen"))
    else:
        lo, hi = fy.ci95
        rec.update(design=dts.chosen, name=dts.chosen, gains=dts.pid.as_dict(), **{"yield": fy.yield_},
                   passed=fy.passed, samples=fy.n, yield_ci95=list(fy.ci95),
                   why=(f"on the {'decision' if dts.decide else 'search'} samples: {d['why']}; on {fy.n} fresh samples: "
                        f"yield {100 * fy.yield_:.1f} % "
                        f"({fy.passed}/{fy.n}), 95 % CI [{100 * lo:.1f}, {100 * hi:.1f}] %"))
    rr = replace(rr, others=dict(dts.designs), recommended=rec)
    return rr, dts.final, dts


# --- the move kind --------------------------------------------------------------------------------

@dataclass(frozen=True)
class MoveReport:
    """The report of a :class:`Move`: the sequential and the joint cascade designs, and the
    friction feed-forward's effect where asked.

    Attributes
    ----------
    kind : str
    plant : Plant
    scene : MoveScene
    designs : tuple
        ``(sequential, joint)`` :class:`~prsa_ctrl.tuning.cascade.CascadeDesign`.
    friction_ff : dict or None
        :func:`prsa_ctrl.studies.move.friction_feedforward_effect`.
    """

    kind: str
    plant: Any
    scene: MoveScene
    designs: tuple
    friction_ff: Mapping[str, Any] | None = None

    #: A move's report carries no verification status of its own (its designs say theirs).
    status: ClassVar[str] = "ok"
    #: No run timings either.
    timing_s: ClassVar[None] = None

    def as_dict(self) -> dict:
        """The JSON report."""
        seq, joint = self.designs
        out = {"plant": self.plant.name, "scene": self.scene.name, "sequential": seq.as_dict(),
               "joint": joint.as_dict()}
        if self.friction_ff is not None:
            out["friction_feedforward"] = {k: v for k, v in self.friction_ff.items() if k != "design"}
        return json_safe(out)

    def format(self, overrides: Sequence[str] = ()) -> str:
        """The text report (a move takes no overriding flags)."""
        from .scenereport import format_friction_ff, format_move_report

        text = format_move_report(self.plant, self.scene, list(self.designs), "prsa-tune")
        if self.friction_ff is not None:
            text += "\n" + format_friction_ff(self.friction_ff, self.scene.fidelity)
        return text

    def export_target(self) -> ExportTarget:
        """The joint design (with the friction feed-forward in its position loop where asked)."""
        design = self.friction_ff["design"] if self.friction_ff is not None else self.designs[1]
        return ExportTarget(design, self.plant, {}, None, tuple(design.filters),  # issue 34: the scene's fixed filters
                            self.scene.max_speed_m_s / self.plant.lead_per_rad)

    def file_lines(self, json: str | None = None, export: str | None = None, target: ExportTarget | None = None,
                   plots: Sequence[Any] | None = None) -> list[str]:
        """The lines naming the files written (the plots only when some were)."""
        lines = [] if json is None else [f"JSON report: {json}"]
        if export is not None:
            lines.append(f"drive export: {export}")
        if plots:
            lines.append(f"plots: {', '.join(str(p) for p in plots)}")
        return lines


@dataclass(frozen=True)
class Move:
    """A positioning problem (``[move]``, ``[cascade]``): the position loop over the speed
    loop, tuned sequentially and jointly (:func:`prsa_ctrl.studies.move.tune_move`).

    Attributes
    ----------
    scene : MoveScene
    """

    name: ClassVar[str] = "move"
    announces: ClassVar[bool] = False
    #: The speed-loop studies a move takes (:data:`~prsa_ctrl.studies.kindruns.STEP_STUDIES`): none.
    studies: ClassVar[frozenset] = frozenset()
    #: What the scene is, for messages.
    described: ClassVar[str] = "a move (cascade) scene"
    #: The command's options the kind honours (argparse destinations, :data:`MOVE_FLAGS`).
    flags: ClassVar[tuple[str, ...] | None] = MOVE_FLAGS
    scene: MoveScene

    @classmethod
    def refuse_flags(cls, given: Sequence[tuple[str, str]], name: str) -> None:
        """Refuse the first option given that a move does not honour (not in :attr:`flags`).

        Parameters
        ----------
        given : sequence of (str, str)
            Every option given, in the command's order: (argparse destination, the flag and
            its value as typed, e.g. ``"--seed 3"``).
        name : str
            The scene's name, for the message.

        Raises
        ------
        UsageError
            One line naming the flag as typed and the flags a move takes.
        """
        for dest, text in given:
            if dest not in cls.flags:
                raise UsageError(f"{text} does not apply to a move scene ({name}); expected only --plant, --json, "
                                 "--export, --plots, --quiet and --verbose")

    @classmethod
    def load(cls, scene_ref, plant_ref, given: Sequence[tuple[str, str]], override: Callable[[], Any] = _nothing):
        """Plant and move scene for a command: the scene (its own errors first), the options it
        does not honour refused (:meth:`refuse_flags`), the plant (without notes: a move's run
        shows none), the move checked against it
        (:func:`~prsa_ctrl.studies.move.check_move_against_plant`). A move takes no override
        (``override`` is not called).

        Returns
        -------
        (Plant, MoveScene, list)
            No overriding flags.
        """
        import warnings

        from ..plant.plantfile import load_plant
        from .move import check_move_against_plant
        from .scene import load_scene

        scene = load_scene(scene_ref)
        cls.refuse_flags(given, scene.name)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a move scene's run shows no plant notes
            plant = load_plant(plant_ref)
        check_move_against_plant(scene, plant)
        return plant, scene, []

    def takes(self, study: str) -> bool:
        """Whether the problem takes a study (a move takes none of the speed loop's)."""
        return study in self.studies

    #: The scene type of the kind.
    scene_type: ClassVar[type] = MoveScene

    @classmethod
    def accepts(cls, scene: Any) -> bool:
        """Whether a loaded scene is a move (an instance of :attr:`scene_type`)."""
        return isinstance(scene, cls.scene_type)

    @classmethod
    def claims(cls, doc: Any) -> bool:
        """Whether a parsed scene file is a move (its :attr:`scene_type`'s ``claims``)."""
        return cls.scene_type.claims(doc)

    def __post_init__(self) -> None:
        if not type(self).accepts(self.scene):
            raise SceneError(f"{getattr(self.scene, 'origin', '<scene>')}: not a move scene; expected "
                             f"{kind_of(self.scene)}")

    def what(self, plant) -> str:
        return f"tuning the cascade of {self.scene.name}"

    def resolve(self, plant) -> MoveScene:
        """A move's fidelity and operating points are the file's ([move] fidelity, loads): the
        scene as loaded (checked against the plant by
        :func:`prsa_ctrl.studies.move.check_move_against_plant`)."""
        return self.scene

    def check_options(self, options: TuneOptions) -> None:
        """Nothing to refuse here: the flags a move does not honour (the robust studies, a filter
        to tune, ...) are refused as typed when it is loaded (:meth:`refuse_flags`)."""

    def check_overrides(self, given: Mapping[str, Any], typed: Mapping[str, str]) -> None:
        """Nothing: a move scene takes no override (every flag outside :data:`MOVE_FLAGS` is
        refused when it is loaded, :meth:`refuse_flags`)."""

    def check_export(self, path: str) -> None:
        """Every cascade can be exported."""

    def check(self, options: TuneOptions) -> None:
        """Nothing to refuse (see :meth:`check_options`)."""

    def tune(self, plant, options: TuneOptions = TuneOptions(), coordinates: str = "") -> MoveReport:
        """Tune the cascade; with ``options.friction_ff``, verify the joint design with the
        friction feed-forward."""
        import warnings

        from .move import tune_move

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # as the cascade always ran: no notes
            designs = tune_move(plant, self.resolve(plant), options.progress)
            if not options.friction_ff:
                return MoveReport(self.name, plant, self.scene, tuple(designs))
            from .move import friction_feedforward_effect  # issue 24: friction feed-forward

            options.progress("verifying the joint design with the friction feed-forward ...")
            return MoveReport(self.name, plant, self.scene, tuple(designs),
                              friction_feedforward_effect(designs[1], plant, self.scene))


#: The registry: kind name -> problem type (each with its ``scene_type``, ``accepts(scene)``, ``resolve(plant)``,
#: ``tune``).
KINDS: Mapping[str, type] = {"load-step": LoadStep, "duty-cycle": DutyCycle, "move": Move}


def kind_of(scene: Any) -> str:
    """The registry name of a loaded scene's kind.

    Raises
    ------
    TypeError
        Not a scene (:class:`~prsa_ctrl.studies.scene.Scene` or
        :class:`~prsa_ctrl.studies.movescene.MoveScene`).
    """
    for name, kind in KINDS.items():
        if kind.accepts(scene):
            return name
    raise TypeError(f"scene = {type(scene).__name__}; expected a Scene or a MoveScene (prsa_ctrl.load_scene)")


def file_kind(name_or_path) -> type:
    """The kind a scene file declares, before it is loaded (what a command's loader needs): the
    one kind of :data:`KINDS` that claims the parsed file (``claims``), where that is
    :class:`Move`; else :class:`LoadStep`, whose loader serves both speed-loop kinds (a duty cycle
    is told apart once loaded, :func:`problem`) and reports a missing, unreadable, unclaimed or
    ambiguous file.

    Parameters
    ----------
    name_or_path : str, Path or None
        A built-in scene name or a file (None: the default scene).
    """
    from .scenefile import locate_scene, read_scene_doc

    if name_or_path is None:
        return LoadStep
    try:
        doc = read_scene_doc(*locate_scene(name_or_path)[:2])
    except SceneError:
        return LoadStep
    claimed = [kind for kind in KINDS.values() if kind.claims(doc)]
    return claimed[0] if claimed == [Move] else LoadStep


def problem(scene: Any):
    """The problem of a loaded scene: ``KINDS[kind_of(scene)](scene)``."""
    return KINDS[kind_of(scene)](scene)
