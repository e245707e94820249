"""Tuning scenes (``tuning/*.toml``): the operating point, the load step(s), the objective,
the robustness limits and what the verification must deliver."""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Mapping

from .errors import SceneError
from .options import AGGREGATES, CONTROLLERS, ESTIMATORS, FIDELITIES, OBJECTIVES, RIGID_RELATIVE_ERROR
from .plant import _builtin_root

__all__ = ["Scene", "load_scene", "builtin_scenes", "choose_fidelity", "DEFAULT_SCENE", "OUTPUTS",
           "RIGID_RELATIVE_ERROR", "check_against_plant", "holding_capacity_n", "SETPOINT_MAX_RPM",
           "PRE_EVENT_SAMPLES", "POST_EVENT_SAMPLES", "MAX_RECORD_SAMPLES", "MAX_LOAD_LEVELS", "MIN_LOAD_STEP_N"]


DEFAULT_SCENE = "paper-load-step"

#: Highest nut-speed setpoint accepted, rpm: roller-screw catalogues rate nut speeds up to
#: ~5000 rpm (d n limits of the rolling contacts); the contact models are not validated beyond.
SETPOINT_MAX_RPM = 6000.0
#: Lowest setpoint as a multiple of the speed at which the screw moves at the Stribeck velocity:
#: at 1x (3 rpm on paper-iprsm) the verified run of the paper plant goes non-finite, at 3x
#: (10 rpm) it is fine; 5x keeps a margin.
STICTION_MARGIN = 5.0
#: Controller samples of steady running needed before an event (load step): the verification
#: starts this many samples before it (``autotune._PRE_SAMPLES``) so that the sampled
#: controller, the speed filter and the ZOH are in their steady state when the load moves.
PRE_EVENT_SAMPLES = 8
#: Controller samples needed after the event: the fastest closed loop a sampled drive reaches
#: has a time constant of ~10 samples (crossover <= ~0.1 / Ts); the peak and the recovery need
#: at least 8 such time constants in the record.
POST_EVENT_SAMPLES = 80
#: Largest record, in controller samples over the whole duration: the tuner's prediction and
#: the verification record hold one point per sample and per load level (40 000 samples =
#: 10 s at 4 kHz, ~8 s of run time per verified second today).
MAX_RECORD_SAMPLES = 40_000
#: Most load levels per scene (each costs a linearisation, a tuner horizon and verified runs).
MAX_LOAD_LEVELS = 20
#: Smallest load step, N: smaller steps drown in the encoder quantisation and the metrics
#: become relative differences of numbers at numerical zero.
MIN_LOAD_STEP_N = 1.0

#: Outputs a scene may ask for; ``nut_speed`` and ``motor_torque`` are always computed.
OUTPUTS = (
    "nut_speed",
    "motor_torque",
    "cage_speed",
    "roller_speed",
    "screw_velocity",
    "contact_forces",
    "per_roller_forces",
)

_SECTIONS: Mapping[str, Mapping[str, type | tuple]] = {
    "operating": {
        "setpoint_rpm": float,
        "initial_load_n": float,
        "final_loads_n": list,
        "step_time_s": float,
        "duration_s": float,
    },
    "tuning": {
        "objective": str,
        "controller": str,
        "ms_max": float,
        "mt_max": float,
        "aggregate": str,
        "candidates": int,
    },
    "verify": {"fidelity": str, "discrete": bool, "accuracy": float},
    "estimator": {"kind": str, "feedforward": bool, "load_change_time_s": float},
    "outputs": {"needed": list},
}


@dataclass(frozen=True)
class Scene:
    """A load-step tuning scenario (SI units; the file uses rpm for the setpoint).

    Parameters
    ----------
    setpoint_rad_s : float, rad/s
        Nut-speed setpoint.
    initial_load : float, N
        Axial load before the step (steady state).
    final_loads : tuple of float, N
        Load(s) after the step; several levels are tuned jointly (``aggregate``).
    step_time : float, s
    duration : float, s
        End of the record (the step response lasts ``duration - step_time``).
    objective : {"ie", "iae", "itae", "ise"}
    controller : {"pi", "pid"}
    ms_max, mt_max : float
        Robustness bounds (``mt_max`` optional).
    aggregate : {"sum", "worst"}
        How several load levels are combined.
    candidates : int
        How many tuned candidates are verified on the nonlinear simulator.
    fidelity : {"auto", "rigid", "compliant", "multi-roller"}
        Fidelity of the verification; ``"auto"`` picks the cheapest that delivers ``outputs``
        at ``accuracy`` (see :func:`choose_fidelity`).
    discrete : bool
        Verify with the sampled controller, ZOH and quantised encoder.
    accuracy : float
        Relative accuracy the verified metrics need (fraction of the peak drop); it also sets
        the integrator tolerance.
    outputs : tuple of str
        Signals the scene needs (see ``OUTPUTS``).
    estimator : {"none", "kf"}
        Speed measurement: the drive's filtered backward difference, or the Kalman filter of
        :mod:`prsa_ctrl.estimator` (filterpy is imported only then).
    feedforward : bool
        Feed the estimated load torque forward (needs ``estimator = "kf"``); its gain is tuned.
    load_change_time_s : float, s
        Load random-walk setting of the Kalman filter.
    """

    name: str = "custom"
    setpoint_rad_s: float = 300.0 * math.pi / 30.0
    initial_load: float = 500.0
    final_loads: tuple[float, ...] = (1500.0,)
    step_time: float = 0.2
    duration: float = 0.5
    objective: str = "iae"
    controller: str = "pi"
    ms_max: float = 1.4
    mt_max: float | None = None
    aggregate: str = "sum"
    candidates: int = 3
    fidelity: str = "auto"
    discrete: bool = True
    accuracy: float = 0.01
    outputs: tuple[str, ...] = ("nut_speed", "motor_torque")
    estimator: str = "none"
    feedforward: bool = False
    load_change_time_s: float = 1.0
    origin: str = "<scene>"
    #: Validated ``[spec]``, ``[robust]`` and ``[uncertainty]`` sections (see
    #: :func:`prsa_ctrl.uncertainty.parse_scene_sections`); empty when the file has none.
    robust: Mapping[str, Any] = field(default_factory=dict, compare=False, hash=False)

    def __post_init__(self) -> None:
        o = self.origin

        def bad(key: str, value: Any, expected: str) -> SceneError:
            return SceneError(f"{o}: {key} = {value!r}; expected {expected}")

        def finite(key: str, value: Any) -> float:
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise bad(key, value, "a finite number")
            return float(value)

        if finite("setpoint_rad_s", self.setpoint_rad_s) <= 0:
            raise bad("setpoint_rpm", float(f"{self.setpoint_rpm:.12g}"), "a positive nut speed in rpm")
        if finite("initial_load", self.initial_load) < 0:
            raise bad("initial_load", self.initial_load, "a load >= 0 N (compressive)")
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
        if self.objective not in OBJECTIVES:
            raise bad("objective", self.objective, "one of ie, iae, itae, ise")
        if self.controller not in CONTROLLERS:
            raise bad("controller", self.controller, "pi or pid")
        if not 1.0 < finite("ms_max", self.ms_max) < 10.0:
            raise bad("ms_max", self.ms_max, "a number in (1, 10)")
        if self.mt_max is not None and not 1.0 < finite("mt_max", self.mt_max) < 10.0:
            # Mt = max|T| >= |T(0)| = 1 with integral action: a bound <= 1 cannot be met.
            raise bad("mt_max", self.mt_max, "a number in (1, 10)")
        if self.aggregate not in AGGREGATES:
            raise bad("aggregate", self.aggregate, "sum or worst")
        if isinstance(self.candidates, bool) or not isinstance(self.candidates, int) or not 1 <= self.candidates <= 10:
            raise bad("candidates", self.candidates, "an integer 1..10")
        if self.fidelity not in ("auto", *FIDELITIES):
            raise bad("fidelity", self.fidelity, "auto, rigid, compliant or multi-roller")
        if not 1e-6 <= finite("accuracy", self.accuracy) <= 0.5:
            raise bad("accuracy", self.accuracy, "a relative accuracy in [1e-6, 0.5]")
        if not isinstance(self.discrete, bool):
            raise bad("discrete", self.discrete, "true or false")
        for out in self.outputs:
            if out not in OUTPUTS:
                raise bad("outputs", out, f"one of {', '.join(OUTPUTS)}")
        if self.estimator not in ESTIMATORS:
            raise bad("estimator", self.estimator, "none or kf")
        if not isinstance(self.feedforward, bool):
            raise bad("feedforward", self.feedforward, "true or false")
        if self.feedforward and self.estimator != "kf":
            raise bad("feedforward", self.feedforward, "estimator = kf (the load torque comes from the filter)")
        if self.estimator == "kf" and not self.discrete:
            raise bad("estimator", self.estimator, "discrete = true (the filter runs at the sample time)")
        if finite("load_change_time_s", self.load_change_time_s) <= 0:
            raise bad("load_change_time_s", self.load_change_time_s, "a positive time in s")

    @property
    def setpoint_rpm(self) -> float:
        return self.setpoint_rad_s * 30.0 / math.pi

    def replace(self, **changes: Any) -> "Scene":
        """Copy with some fields changed (validated again); unknown names are an error."""
        allowed = {f.name for f in fields(self)}
        unknown = sorted(set(changes) - allowed)
        if unknown:
            raise SceneError(f"unknown scene field {unknown[0]!r}; allowed: {', '.join(sorted(allowed))}")
        return replace(self, **changes)

    def as_dict(self) -> dict[str, Any]:
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d["final_loads"] = list(self.final_loads)
        d["outputs"] = list(self.outputs)
        d["setpoint_rpm"] = self.setpoint_rpm
        return d


def builtin_scenes() -> list[str]:
    root = _builtin_root("prsa_ctrl.scenes", "tuning")
    return sorted(p.name[:-5] for p in root.iterdir() if p.name.endswith(".toml"))


def _from_doc(doc: Mapping[str, Any], origin: str) -> Scene:
    unknown = sorted(set(doc) - set(_SECTIONS) - {"name", "description", "spec", "robust", "uncertainty"})
    if unknown:
        raise SceneError(f"{origin}: unknown section {unknown[0]!r}; expected one of {', '.join([*_SECTIONS, 'spec', 'robust', 'uncertainty'])}")
    kw: dict[str, Any] = {"origin": origin}
    if "name" in doc:
        if not isinstance(doc["name"], str):
            raise SceneError(f"{origin}: name = {doc['name']!r}; expected a string")
        kw["name"] = doc["name"]
    for section, keys in _SECTIONS.items():
        table = doc.get(section, {})
        if not isinstance(table, Mapping):
            raise SceneError(f"{origin}: [{section}] must be a table")
        extra = sorted(set(table) - set(keys))
        if extra:
            raise SceneError(
                f"{origin}: unknown key {section}.{extra[0]}; expected one of "
                f"{', '.join(f'{section}.{k}' for k in keys)}"
            )
        for key, typ in keys.items():
            if key not in table:
                continue
            val = table[key]
            ok = isinstance(val, typ) and not (typ in (float, int) and isinstance(val, bool))
            if typ is float and isinstance(val, int) and not isinstance(val, bool):
                val, ok = float(val), True
            if not ok:
                raise SceneError(f"{origin}: {section}.{key} = {val!r}; expected a {typ.__name__}")
            kw[key] = val
    mapping = {
        "setpoint_rpm": ("setpoint_rad_s", lambda v: v * math.pi / 30.0),
        "initial_load_n": ("initial_load", float),
        "final_loads_n": ("final_loads", lambda v: tuple(v)),
        "step_time_s": ("step_time", float),
        "duration_s": ("duration", float),
        "needed": ("outputs", lambda v: tuple(v)),
        "kind": ("estimator", str),
    }
    rpm = kw.get("setpoint_rpm")
    if rpm is not None and not (math.isfinite(rpm) and 0 < rpm <= SETPOINT_MAX_RPM):
        raise SceneError(f"{origin}: operating.setpoint_rpm = {rpm!r}; expected a nut speed in (0, {SETPOINT_MAX_RPM:g}] rpm")
    for old, (new, conv) in mapping.items():
        if old in kw:
            kw[new] = conv(kw.pop(old))
    if {"spec", "robust", "uncertainty"} & set(doc):
        from .uncertainty import parse_scene_sections

        kw["robust"] = parse_scene_sections(doc, origin)
    return Scene(**kw)


def load_scene(name_or_path: str | Path | None = None) -> Scene:
    """Load a scene by built-in name (default ``"paper-load-step"``) or path.

    Raises
    ------
    SceneError
        For a missing, unreadable or invalid file (the message names the file and key).
    """
    text = str(name_or_path if name_or_path is not None else DEFAULT_SCENE)
    if isinstance(name_or_path, Path) or text.endswith(".toml") or "/" in text:
        path = Path(text).expanduser()
        origin = str(path)
        if not path.is_file():
            raise SceneError(f"scene file {text!r} not found; expected a readable .toml file")
        reader = path
    else:
        reader = _builtin_root("prsa_ctrl.scenes", "tuning") / f"{text}.toml"
        origin = f"{text}.toml (built-in)"
        if not reader.is_file():
            raise SceneError(f"unknown scene {text!r}; expected a built-in name ({', '.join(builtin_scenes())}) or a .toml path")
    try:
        doc = tomllib.loads(reader.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneError(f"{origin}: cannot be read ({exc.__class__.__name__}); expected a UTF-8 TOML file") from None
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"{origin}: invalid TOML ({exc})") from None
    return _from_doc(doc, origin)


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


def holding_capacity_n(plant: Any, setpoint_rad_s: float) -> float:
    """Largest axial load, N, the motor can hold at a nut speed (rad/s) at constant speed:
    ``(T_max - T_0 - b w) 2 pi eta / L`` with the torque limit ``T_max``, the no-load torque
    ``T_0``, the viscous coefficient ``b``, the forward efficiency ``eta`` and the lead ``L``
    (the rigid operating point of :mod:`prsa_ctrl.equilibrium`, solved for the load).

    Examples
    --------
    >>> from prsa_ctrl import load_plant
    >>> round(holding_capacity_n(load_plant(), 300 * math.pi / 30))
    7949
    """
    v = plant.values
    spare = plant.torque_limit - v["friction.no_load_torque_n_m"] - v["friction.viscous_n_m_s_per_rad"] * setpoint_rad_s
    return spare * v["friction.efficiency"] / plant.lead_per_rad


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
        return f"{scene.origin}: {keys[name]} = {value}"

    ts = plant.sample_time_s
    rpm = scene.setpoint_rpm
    rpm_min = STICTION_MARGIN * plant.values["friction.stribeck_velocity_m_s"] / plant.lead_per_rad * 30.0 / math.pi
    if not rpm_min <= rpm <= SETPOINT_MAX_RPM:
        raise SceneError(
            f"{label('setpoint_rad_s', f'{rpm:.6g}')}: expected a nut speed in [{rpm_min:.3g}, {SETPOINT_MAX_RPM:g}] rpm "
            f"for {plant.name} (below, the screw moves slower than {STICTION_MARGIN:g} x friction.stribeck_velocity_m_s = "
            f"{plant.values['friction.stribeck_velocity_m_s']:g} m/s and the friction is in its stiction transition, where "
            f"the linear model does not hold; above, beyond roller-screw speed ratings)"
        )
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
