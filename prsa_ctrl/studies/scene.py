"""Tuning scenes (``tuning/*.toml``): the operating point, the load step(s) or a duty cycle,
the objective, the robustness limits and what the verification must deliver.

A scene file is read by :func:`load_scene` into one of three frozen types, each validating its
own fields:

* :class:`LoadStepScene`: load steps (``[operating] initial_load_n``, ``final_loads_n``,
  ``step_time_s``), optionally with ``[spec]``/``[robust]``/``[uncertainty]`` sections and a
  Kalman-filter speed measurement;
* :class:`~prsa_ctrl.studies.dutyscene.DutyCycleScene`: a load and/or setpoint profile over
  the record (``load_profile_n``, ``load_trace_csv``, ``setpoint_profile_rpm``,
  ``setpoint_trace_csv``; see :mod:`prsa_ctrl.studies.dutyscene`);
* :class:`~prsa_ctrl.studies.movescene.MoveScene`: a positioning move (``[move]``).

:class:`Scene` (:mod:`prsa_ctrl.studies.scenebase`) is the base of the two speed-loop types and
the name both answer to; ``Scene(**fields)`` builds the one the fields describe. The problem
each kind poses, and how it is tuned, is :mod:`prsa_ctrl.studies.scenekinds`' registry.
"""

from __future__ import annotations

import math
from dataclasses import InitVar, dataclass, replace
from pathlib import Path
from typing import Any, Callable, ClassVar, Mapping, Sequence

from ..textsafe import quote
from ..errors import SceneError
from ..options import RIGID_RELATIVE_ERROR, rad_s_to_rpm, rpm_to_rad_s
from .movescene import MoveScene
from .scenebase import OUTPUTS, Scene, holding_capacity_n, scene_type
from .scenesections import Robust
from .scenefilters import check_filters_against_plant
from .scenefile import (DEFAULT_SCENE, MAX_LOAD_LEVELS, MAX_RECORD_SAMPLES, MIN_LOAD_STEP_N, POST_EVENT_SAMPLES,
                        PRE_EVENT_SAMPLES, SETPOINT_MAX_RPM, STICTION_MARGIN, builtin_scenes, locate_scene,
                        read_scene_doc)
from .dutyscene import (GOALS, MAX_PROFILE_ROWS, MAX_TRACE_BYTES, PROFILE_KEYS, PROFILE_SOURCES, DutyCycleScene,
                        profile_rows, read_trace_csv, refuse_other_kind_keys)

__all__ = ["Scene", "LoadStepScene", "DutyCycleScene", "load_scene", "builtin_scenes", "choose_fidelity",
           "DEFAULT_SCENE", "OUTPUTS", "RIGID_RELATIVE_ERROR", "check_against_plant", "holding_capacity_n",
           "SETPOINT_MAX_RPM", "PRE_EVENT_SAMPLES", "POST_EVENT_SAMPLES", "MAX_RECORD_SAMPLES", "MAX_LOAD_LEVELS",
           "MIN_LOAD_STEP_N", "GOALS", "MAX_PROFILE_ROWS", "MAX_TRACE_BYTES", "read_trace_csv", "profile_rows",
           "require_speed_scene", "parse_scene", "SCENE_TYPES"]


@dataclass(frozen=True)
class LoadStepScene(Scene):
    """Load steps: the load steps from ``initial_load`` to each of ``final_loads`` at
    ``step_time``, the record ends at ``duration`` (the shared fields are
    :class:`~prsa_ctrl.studies.scenebase.Scene`'s). Several final loads are tuned jointly
    (``aggregate``); the design's 2-DOF setpoint weight is 1.

    ``goal``, ``setpoint_weight`` and ``setpoint_share`` are the duty cycle's ``[tuning]`` keys: a
    load-step scene file that sets one is refused (one line naming the key,
    :func:`~prsa_ctrl.studies.dutyscene.refuse_other_kind_keys`). ``Scene(**fields)`` takes them
    as init-only values and checks them: ``goal`` "auto" or "load", ``setpoint_weight`` 1,
    ``setpoint_share`` its default 0.5 (a load step has no setpoint record to weigh). They are not
    fields of a load step (its class keeps their defaults, which ``dataclasses.replace`` reads);
    the design's weight is :attr:`design_setpoint_weight`.
    """

    goal: InitVar[str] = "auto"
    setpoint_weight: InitVar[float] = 1.0
    setpoint_share: InitVar[float] = 0.5

    #: The registry name of the kind (:data:`prsa_ctrl.studies.scenekinds.KINDS`) and what marks its files.
    kind_name: ClassVar[str] = "load-step"
    marks: ClassVar[str] = "no [move] table and no load or setpoint profile in [operating]"

    @classmethod
    def describes(cls, given: Mapping[str, Any]) -> bool:
        """No profile given."""
        return given.get("load_profile") is None and given.get("setpoint_profile") is None

    @classmethod
    def claims(cls, doc: Mapping[str, Any]) -> bool:
        """A file with neither a ``[move]`` table nor a profile key in ``[operating]`` (an empty
        file is the default load step)."""
        op = doc.get("operating")
        return "move" not in doc and not (isinstance(op, Mapping) and any(k in op for k in PROFILE_SOURCES))

    @classmethod
    def refuse_foreign(cls, doc: Mapping[str, Any], origin: str) -> None:
        """A duty cycle's ``[tuning]`` key is refused by name
        (:func:`~prsa_ctrl.studies.dutyscene.refuse_other_kind_keys`)."""
        refuse_other_kind_keys(doc, origin)

    @classmethod
    def own_fields(cls, kw: dict, origin: str, base: Any) -> None:
        """``operating.final_loads_n`` (N) and ``step_time_s`` (s) as ``final_loads`` and ``step_time``."""
        if "final_loads_n" in kw:
            kw["final_loads"] = tuple(kw.pop("final_loads_n"))
        if "step_time_s" in kw:
            kw["step_time"] = float(kw.pop("step_time_s"))

    def __post_init__(self, goal: str, setpoint_weight: float, setpoint_share: float) -> None:
        if goal not in ("auto", "load"):
            raise SceneError(f"{self.origin}: goal = {quote(goal)}; expected 'load' for a load-step scene (setpoint "
                             "and mix goals need a setpoint_profile_rpm / load_profile_n duty cycle)")
        if setpoint_weight != 1.0:
            raise SceneError(f"{self.origin}: setpoint_weight = {quote(setpoint_weight)}; expected 1 without a "
                             "setpoint profile")
        if setpoint_share != 0.5:
            raise SceneError(f"{self.origin}: setpoint_share = {quote(setpoint_share)}; expected none on a load step (the "
                             "weight of the setpoint record in a duty cycle's goal = 'mix')")
        super().__post_init__()

    def check_events(self, bad, finite) -> None:
        """At least one final load, each different from the initial one; the step after t = 0,
        the record beyond it."""
        if not self.final_loads:
            raise bad("final_loads", list(self.final_loads), "at least one load")
        for f in self.final_loads:
            if finite("final_loads", f) < 0:
                raise bad("final_loads", f, "loads >= 0 N (compressive)")
            if f == self.initial_load:
                raise bad("final_loads", f, f"a load different from the initial {self.initial_load:g} N")
        if finite("step_time", self.step_time) <= 0:
            raise bad("step_time", self.step_time, "a time > 0 s (the loop starts in steady state before the load step)")
        if finite("duration", self.duration) <= self.step_time + 1e-3:
            raise bad("duration", self.duration, f"a time beyond step_time + 1 ms ({self.step_time + 1e-3:g} s)")

    def check_plant(self, plant: Any, label: Callable[[str, Any], str], rpm_min: float,
                    typed: Mapping[str, str]) -> None:
        """The ``[robust]``/``[uncertainty]`` sections, the loads held, the steps large and few
        enough, the events far enough from the ends (:func:`check_steps_against_plant`)."""
        check_steps_against_plant(self, plant, label, rpm_min, typed)

    @property
    def cases(self) -> list[str]:
        """One label per load step."""
        return [f"step to {f:g} N" for f in self.final_loads]

    def profile_dict(self) -> dict[str, Any]:
        """The duty cycle's keys, unset (the report keeps one layout for both types)."""
        return {"load_profile": None, "setpoint_profile": None, "goal": "auto", "setpoint_weight": 1.0,
                "setpoint_share": 0.5, "profile_source": ""}



#: The scene types a file is read into, one per kind of the registry, in its order (the
#: ``scene_type`` of each of :data:`prsa_ctrl.studies.scenekinds.KINDS`): each says which files
#: are its own (``claims``) and reads them (``from_doc``).
SCENE_TYPES: tuple[type, ...] = (LoadStepScene, DutyCycleScene, MoveScene)


def parse_scene(doc: Mapping[str, Any], origin: str, base: Any = None,
                types: Sequence[type] = SCENE_TYPES) -> Scene | MoveScene:
    """The scene a parsed scene file describes: each scene type is asked whether the document is
    its own (``claims``) and the one that claims it reads it (``from_doc``).

    Parameters
    ----------
    doc : mapping
        The parsed TOML document.
    origin : str
        The file as the messages name it.
    base : path-like, optional
        The folder relative CSV traces are read from.
    types : sequence of type, optional
        The scene types asked (default :data:`SCENE_TYPES`).

    Raises
    ------
    SceneError
        No type or several claim the document (one line naming the file and what marks each
        kind), or the claiming type's own error (the file and the key).
    """
    claimed = [t for t in types if t.claims(doc)]
    if len(claimed) == 1:
        return claimed[0].from_doc(doc, origin, base)
    def marks(kinds: Sequence[type]) -> str:
        return "; ".join(f"a {t.kind_name} scene has {t.marks}" for t in kinds)

    if not claimed:
        raise SceneError(f"{origin}: no scene kind reads this file; expected one of: {marks(types or SCENE_TYPES)}")
    raise SceneError(f"{origin}: read as {len(claimed)} kinds of scene ({', '.join(t.kind_name for t in claimed)}); "
                     f"expected one: {marks(claimed)}")


def load_scene(name_or_path: str | Path | None = None) -> Scene | MoveScene:
    """Load a scene by built-in name (default ``"paper-load-step"``) or path: a load step or a
    duty cycle (:class:`Scene`), or a move (:class:`~prsa_ctrl.studies.movescene.MoveScene`),
    whichever scene type claims the file (:func:`parse_scene`).

    Raises
    ------
    SceneError
        For a missing, unreadable or invalid file, or one no kind or several kinds claim (the
        message names the file and key).
    """
    reader, origin, base = locate_scene(name_or_path)
    return parse_scene(read_scene_doc(reader, origin), origin, base)


def require_speed_scene(scene: Scene | MoveScene) -> Scene:
    """``scene`` if it is a speed-loop scene; a scene of another kind (a move) is refused where a
    load step or duty cycle is needed (``prsa-plot``, the Monte-Carlo study), in the words of its
    type (its ``speed_loop`` and ``speed_loop_refusal``).

    Raises
    ------
    SceneError
        One line naming the file.
    TypeError
        Not a scene (no ``speed_loop``).
    """
    speed_loop = getattr(type(scene), "speed_loop", None)
    if speed_loop is None:
        raise TypeError(f"scene = {type(scene).__name__}; expected a prsa_ctrl scene (prsa_ctrl.load_scene)")
    if not speed_loop:
        raise SceneError(f"{scene.origin}: {scene.speed_loop_refusal}")
    return scene


def choose_fidelity(scene: Scene) -> tuple[Scene, str]:
    """Resolve ``fidelity = "auto"``: the cheapest model that delivers the scene's outputs at its
    accuracy. Per-roller forces need the multi-roller model; contact forces the compliant one;
    speeds and torque alone are served by the rigid model when the scene tolerates its
    measured error (``RIGID_RELATIVE_ERROR`` of the peak drop), else by the compliant model.

    Returns the scene with the fidelity set and a one-line reason.
    """
    if scene.fidelity != "auto":
        return scene, f"{scene.fidelity} (set by the scene)"
    needs = set(scene.outputs)
    if "per_roller_forces" in needs:
        fid, why = "multi-roller", "per-roller contact forces requested"
    elif "contact_forces" in needs:
        fid, why = "compliant", "contact forces requested; rollers identical"
    elif scene.accuracy >= RIGID_RELATIVE_ERROR:
        fid, why = "rigid", (f"speeds/torque only at {scene.accuracy:.0%} accuracy; the rigid model's "
                             f"error is ~{RIGID_RELATIVE_ERROR:.1%} of the drop")
    else:
        fid, why = "compliant", (f"speeds/torque at {scene.accuracy:.1%} accuracy; the rigid model's "
                                 f"~{RIGID_RELATIVE_ERROR:.1%} error is too large")
    return replace(scene, fidelity=fid), f"{fid} ({why})"



def check_against_plant(scene: Scene, plant: Any, typed: Mapping[str, str] | None = None) -> None:
    """Refuse a scene the plant cannot run: a setpoint in the stiction band or beyond
    ``SETPOINT_MAX_RPM``, a load the motor cannot hold, a load step too small or too many
    levels, an event closer to t = 0 or to the end than ``PRE_EVENT_SAMPLES`` /
    ``POST_EVENT_SAMPLES`` controller samples, a record above ``MAX_RECORD_SAMPLES``.

    Parameters
    ----------
    scene : Scene
    plant : Plant
    typed : mapping, optional
        Field name -> how the user typed it (``{"step_time": "--step-time 1e-9"}``); fields not
        in it are named by their scene-file key.

    Raises
    ------
    SceneError
        One line naming the value, the limit and why.
    """
    typed = dict(typed or {})
    keys = {"setpoint_rad_s": "operating.setpoint_rpm", "initial_load": "operating.initial_load_n",
            "final_loads": "operating.final_loads_n", "step_time": "operating.step_time_s",
            "duration": "operating.duration_s"}

    def label(name: str, value: Any) -> str:
        if name in typed:
            return typed[name]
        return f"{scene.origin}: {keys[name]} = {value if isinstance(value, str) else quote(value)}"

    ts = plant.sample_time_s
    check_filters_against_plant(scene.filters, scene.filter_labels, ts, plant.name)
    rpm = scene.setpoint_rpm
    rpm_min = rad_s_to_rpm(STICTION_MARGIN * plant.values["friction.stribeck_velocity_m_s"] / plant.lead_per_rad)
    if not rpm_min <= rpm <= SETPOINT_MAX_RPM:
        raise SceneError(
            f"{label('setpoint_rad_s', f'{rpm:.6g}')}: expected a nut speed in [{rpm_min:.3g}, {SETPOINT_MAX_RPM:g}] rpm "
            f"for {plant.name} (below, the screw moves slower than {STICTION_MARGIN:g} x friction.stribeck_velocity_m_s = "
            f"{plant.values['friction.stribeck_velocity_m_s']:g} m/s and the friction is on the steep part of its Stribeck curve (static to dynamic coefficient), where "
            f"the linear model does not hold; above, beyond roller-screw speed ratings)"
        )
    quantum = 2 * math.pi / (plant.encoder_counts * ts)  # one count per sample, rad/s
    slowest = min(v for _, v in scene.setpoint_points)
    if quantum > slowest:
        raise SceneError(
            f"{plant.origin}: sensor.encoder_counts_per_rev = {plant.encoder_counts}: one count per controller sample is "
            f"{quantum:.4g} rad/s ({rad_s_to_rpm(quantum):.4g} rpm), more than the setpoint {rad_s_to_rpm(slowest):.6g} "
            f"rpm of {scene.origin}: the drive could not measure the speed it controls; expected a finer encoder "
            f"(at least {math.ceil(2 * math.pi / (slowest * ts))} counts per revolution at sensor.sample_time_s = {ts:g} s)")
    scene.check_plant(plant, label, rpm_min, typed)


def check_steps_against_plant(scene: LoadStepScene, plant: Any, label: Callable[[str, Any], str], rpm_min: float,
                              typed: Mapping[str, str]) -> None:
    """The load-step half of :func:`check_against_plant` (``label(field, value)`` names a value
    as typed or by its scene-file key; ``typed``: the fields given on the command line)."""
    ts = plant.sample_time_s
    rpm = scene.setpoint_rpm
    _check_robust_against_plant(scene, plant, rpm_min)
    cap = holding_capacity_n(plant, scene.setpoint_rad_s)
    if cap <= 0:
        raise SceneError(
            f"{label('setpoint_rad_s', f'{rpm:.6g}')}: {plant.name} cannot even turn at {rpm:.6g} rpm: the drag torque "
            f"exceeds drive.torque_limit_n_m = {plant.torque_limit:g} N m"
        )
    if len(scene.final_loads) > MAX_LOAD_LEVELS:
        raise SceneError(f"{label('final_loads', list(scene.final_loads))}: {len(scene.final_loads)} load levels; "
                         f"expected at most {MAX_LOAD_LEVELS}")
    for name, loads in (("initial_load", (scene.initial_load,)), ("final_loads", scene.final_loads)):
        for f in loads:
            if f > cap:
                raise SceneError(
                    f"{label(name, f'{f:g}')}: load {f:g} N out of range for {plant.name}: at {rpm:.6g} rpm the motor "
                    f"holds at most {cap:.0f} N (drive.torque_limit_n_m = {plant.torque_limit:g} N m, lead "
                    f"{plant.lead_m * 1e3:g} mm, efficiency {plant.values['friction.efficiency']:g})"
                )
    if len(set(scene.final_loads)) != len(scene.final_loads):
        raise SceneError(f"{label('final_loads', list(scene.final_loads))}: repeated load level; expected distinct levels")
    for f in scene.final_loads:
        if abs(f - scene.initial_load) < MIN_LOAD_STEP_N:
            raise SceneError(
                f"{label('final_loads', f'{f:g}')}: step of {abs(f - scene.initial_load):.3g} N from "
                f"{scene.initial_load:g} N; expected a load step of at least {MIN_LOAD_STEP_N:g} N"
            )
    before, after = PRE_EVENT_SAMPLES * ts, POST_EVENT_SAMPLES * ts
    if scene.step_time < before * (1 - 1e-9):
        raise SceneError(
            f"{label('step_time', f'{scene.step_time:g}')}: the load step needs at least {PRE_EVENT_SAMPLES} controller "
            f"samples of steady running before it ({before:g} s at sensor.sample_time_s = {ts:g} s); expected a step "
            f"time >= {before:g} s"
        )
    if scene.duration - scene.step_time < after * (1 - 1e-9):
        name = "duration" if "duration" in typed or "step_time" not in typed else "step_time"
        raise SceneError(
            f"{label(name, f'{getattr(scene, name):g}')}: only {scene.duration - scene.step_time:.3g} s after the load "
            f"step; the peak and the recovery need at least {POST_EVENT_SAMPLES} controller samples ({after:g} s at "
            f"sensor.sample_time_s = {ts:g} s); expected duration >= step time + {after:g} s"
        )
    n = scene.duration / ts
    if n > MAX_RECORD_SAMPLES:
        raise SceneError(
            f"{label('duration', f'{scene.duration:g}')}: the record would hold {n:.3g} controller samples "
            f"(sensor.sample_time_s = {ts:g} s); the limit is {MAX_RECORD_SAMPLES} samples, a duration of at most "
            f"{MAX_RECORD_SAMPLES * ts:g} s"
        )



#: Plant keys that set the holding capacity (:func:`holding_capacity_n`) or the lowest speed
#: (``STICTION_MARGIN``): their uncertain supports are checked against the operating range.
_CAPACITY_KEYS = ("drive.torque_limit_n_m", "friction.no_load_torque_n_m", "friction.viscous_n_m_s_per_rad",
                  "friction.efficiency", "friction.stribeck_velocity_m_s")


def _capacity_n(values: Mapping[str, float], lead_per_rad: float, setpoint_rad_s: float) -> float:
    """:func:`holding_capacity_n` from a values mapping (file units)."""
    spare = (values["drive.torque_limit_n_m"] - values["friction.no_load_torque_n_m"]
             - values["friction.viscous_n_m_s_per_rad"] * setpoint_rad_s)
    return spare * values["friction.efficiency"] / lead_per_rad


def _check_robust_against_plant(scene: Scene, plant: Any, rpm_min: float) -> None:
    """The ``[robust]`` operating range and the ``[uncertainty]`` supports against the plant,
    before any work: every ``robust.setpoints_rpm`` in the speed range, every
    ``robust.final_loads_n`` a step of at least ``MIN_LOAD_STEP_N`` the motor can hold at the
    slowest setpoint, the uncertainty model valid (:func:`prsa_ctrl.plant.uncertainty.uncertainty_model`,
    which also checks supports jointly), and at every corner of the supports of the keys that
    set the capacity the loads still held (e.g. an uncertain torque limit 0.3..3 N m)."""
    sections = scene.sections
    if not sections:
        return
    import itertools

    from ..plant.uncertainty import uncertainty_model

    o = scene.origin
    rob = sections.robust or Robust()
    rpms = list(rob.setpoints_rpm) or [scene.setpoint_rpm]
    loads = list(rob.final_loads_n) or list(scene.final_loads)
    for v in rob.setpoints_rpm:
        if not rpm_min <= v <= SETPOINT_MAX_RPM:
            raise SceneError(f"{o}: robust.setpoints_rpm: {v:g} rpm; expected nut speeds in [{rpm_min:.3g}, "
                             f"{SETPOINT_MAX_RPM:g}] rpm for {plant.name} (below, the friction is on the steep part "
                             "of its Stribeck curve; above, beyond roller-screw speed ratings)")
    for f in rob.final_loads_n:
        if abs(f - scene.initial_load) < MIN_LOAD_STEP_N:
            raise SceneError(f"{o}: robust.final_loads_n: {f:g} N is a step of {abs(f - scene.initial_load):.3g} N from "
                             f"operating.initial_load_n = {scene.initial_load:g} N; expected a load step of at least "
                             f"{MIN_LOAD_STEP_N:g} N")
    slowest = rpm_to_rad_s(min(rpms))
    top = max([*loads, scene.initial_load])
    cap = holding_capacity_n(plant, slowest)
    if rob.final_loads_n and max(loads) > cap:
        raise SceneError(f"{o}: robust.final_loads_n: {max(loads):g} N out of range for {plant.name}: at {min(rpms):g} "
                         f"rpm the motor holds at most {cap:.0f} N (drive.torque_limit_n_m = {plant.torque_limit:g} N m); "
                         f"expected loads up to {cap:.0f} N")
    model = uncertainty_model(plant, sections.plant_overrides)
    entries = [e for e in model.entries if e.key in _CAPACITY_KEYS]
    for ends in itertools.product((0, 1), repeat=len(entries)):
        values = dict(plant.values)
        values.update({e.key: (e.low, e.high)[k] for e, k in zip(entries, ends)})
        at = ", ".join(f"{e.key} = {values[e.key]:g}" for e in entries)
        low_rpm = rad_s_to_rpm(STICTION_MARGIN * values["friction.stribeck_velocity_m_s"] / plant.lead_per_rad)
        if min(rpms) < low_rpm:
            raise SceneError(f"{o}: [uncertainty] {at} (a corner of the supports): the slowest setpoint {min(rpms):g} rpm "
                             f"is in the stiction band (below {low_rpm:.3g} rpm); expected a narrower "
                             "friction.stribeck_velocity_m_s support or faster setpoints")
        c = _capacity_n(values, plant.lead_per_rad, slowest)
        if top > c:
            raise SceneError(f"{o}: [uncertainty] {at} (a corner of the supports): the motor holds at most {max(c, 0):.0f} N "
                             f"at {min(rpms):g} rpm, less than the load {top:g} N the scene steps to; expected supports "
                             "that can hold every load (e.g. a torque-limit range whose low end holds the largest load)")

