"""Move scenes: the ``[move]`` and ``[cascade]`` sections of a scene file (e.g. ``paper-move``).

A *move scene* says which move the actuator makes (:mod:`prsa_ctrl.drive.motion`), which loads
appear during it and while holding, what the position loop measures, and the robustness bound
of the tuning. :func:`prsa_ctrl.studies.scene.load_scene` returns a :class:`MoveScene` for a
file with a ``[move]`` section; :mod:`prsa_ctrl.studies.move` checks it against a plant,
simulates, measures and tunes it (:mod:`prsa_ctrl.tuning.cascade`).

This module imports no numerical library beyond numpy, so that loading a scene stays cheap.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Mapping

from ..textsafe import quote
from ..drive.motion import PROFILE_KINDS, MotionProfile, out_and_back, plan
from ..errors import SceneError
from ..tuning.cascadespec import CascadeSpec
from ..options import (KV_UNITS, MS_MAX_DEFAULT, PEAK_BOUND_RANGE, POSITION_DELAY_MAX, POSITION_RATE_MAX,
                       check_peak_bound, parse_kv)
from .scenefile import locate_scene, read_scene_doc
from .scenefilters import parse_filters

__all__ = ["MoveScene", "parse_move_scene", "load_move_scene", "POSITION_SENSORS", "POSITION_RATE_MAX", "KV_UNITS",
           "parse_kv"]

#: What the position loop may measure (the same as :data:`prsa_ctrl.drive.measurement.POSITION_SENSORS`,
#: which imports CasADi).
POSITION_SENSORS = ("nut_angle", "screw_position")

_MOVE_KEYS: Mapping[str, tuple[type, str]] = {
    "profile": (str, "one of " + ", ".join(PROFILE_KINDS)),
    "distance_mm": (float, "a finite non-zero travel in mm"),
    "max_speed_mm_s": (float, "a speed > 0 in mm/s"),
    "acceleration_m_s2": (float, "an acceleration > 0 in m/s^2"),
    "jerk_m_s3": (float, "a jerk > 0 in m/s^3"),
    "start_s": (float, "a start time >= 0 s"),
    "return_dwell_s": (float, "a dwell >= 0 s at the target before the move back to the start (out and back)"),
    "measured": (str, "one of " + ", ".join(POSITION_SENSORS)),
    "position_rate": (int, f"an integer number of speed-loop samples per position-loop sample in "
                      f"[1, {POSITION_RATE_MAX}]"),
    "position_delay_samples": (int, f"an integer number of position-loop samples in [0, {POSITION_DELAY_MAX}] (the "
                               "position loop's computation delay)"),
    "initial_load_n": (float, "a finite load in N"),
    "load_n": (float, "a finite load in N (the load that appears during the move)"),
    "load_time_s": (float, "a time in s inside the move"),
    "hold_step_n": (float, "a finite non-zero load step in N"),
    "hold_delay_s": (float, "a delay > 0 s after the end of the move"),
    "hold_duration_s": (float, "a time > 0 s"),
    "window_um": (float, "a settling window > 0 in um"),
    "fidelity": (str, "'rigid' or 'compliant'"),
}
_CASCADE_KEYS: Mapping[str, tuple[type, str]] = {
    "ms_max": (float, f"a peak-sensitivity bound in ({PEAK_BOUND_RANGE[0]:g}, {PEAK_BOUND_RANGE[1]:g})"),
    "position_controller": (str, "'p' or 'pi'"),
    "weight_following": (float, "a weight >= 0"),
    "weight_holding": (float, "a weight >= 0"),
    "bandwidth_ratio": (float, "a ratio >= 1 of speed-loop to position-loop bandwidth"),
    "kv_max": (str, "a position gain ceiling > 0 with its unit, e.g. \"3 (m/min)/mm\" or \"50 1/s\""),
}
_REQUIRED = ("profile", "distance_mm", "max_speed_mm_s", "acceleration_m_s2")


@dataclass(frozen=True)
class MoveScene:
    """A positioning scene (the ``[move]`` and ``[cascade]`` sections of a scene file).

    Attributes
    ----------
    profile : {"trapezoidal", "s-curve"}
    distance_m, max_speed_m_s, acceleration_m_s2, jerk_m_s3 : float
        The move (jerk only for the S-curve).
    start_s : float, s
        When the move starts (the axis holds at rest before).
    return_dwell_s : float or None, s
        With a value: after a dwell of that length at the target the axis moves back to the
        start (out and back, :func:`~prsa_ctrl.drive.motion.out_and_back`: a reversal).
    measured : {"nut_angle", "screw_position"}
    position_rate : int
        Position-loop sample time in speed-loop (controller) samples, 1..:data:`POSITION_RATE_MAX`
        (the position loop samples every ``position_rate``-th speed-loop sample and holds its
        speed reference in between; the cascade model is multi-rate,
        :class:`~prsa_ctrl.tuning.cascade.CascadeModel`).
    position_delay_samples : int
        The position loop's own computation delay in position-loop samples,
        0..:data:`POSITION_DELAY_MAX`: the speed reference and torque feed-forward computed at one
        position-loop sample are applied from the ``position_delay_samples``-th next one on
        (0: at once, as before; the speed loop's own one-sample delay is the plant's).
    initial_load_n, load_n : float, N
        Load at the start and the load that appears at ``load_time_s`` (default: the middle
        of the move), then held.
    hold_step_n : float, N
        Load step applied while holding, ``hold_delay_s`` after the end of the move; the run
        lasts ``hold_duration_s`` after it.
    window_m : float, m
        Settling window of the position.
    fidelity : {"rigid", "compliant"}
        Model of the verification runs.
    ms_max : float
        Bound on the peak sensitivity at every loop-breaking point.
    position_controller : {"p", "pi"}
    weight_following, weight_holding : float
        Weights of the two parts of the tuning objective.
    bandwidth_ratio : float or None
        Smallest ratio of the speed loop's to the position loop's bandwidth (``kp/J >= ratio kv``).
    kv_max_per_s : float or None, 1/s
        Ceiling on the position gain ``Kv`` (``[cascade] kv_max`` with its unit, :func:`parse_kv`).
    typed : dict
        The ``[move]`` values as the file typed them (named in error messages).
    """

    name: str
    origin: str
    profile: str
    distance_m: float
    max_speed_m_s: float
    acceleration_m_s2: float
    jerk_m_s3: float | None = None
    start_s: float = 0.01
    return_dwell_s: float | None = None
    measured: str = "nut_angle"
    position_rate: int = 1
    position_delay_samples: int = 0
    initial_load_n: float = 0.0
    load_n: float = 0.0
    load_time_s: float | None = None
    hold_step_n: float = 0.0
    hold_delay_s: float = 0.1
    hold_duration_s: float = 0.15
    window_m: float = 2e-6
    fidelity: str = "compliant"
    ms_max: float = MS_MAX_DEFAULT
    position_controller: str = "p"
    weight_following: float = 1.0
    weight_holding: float = 1.0
    bandwidth_ratio: float | None = None
    kv_max_per_s: float | None = None
    #: The drive's speed-measurement and torque-command filters (``[filters]``,
    #: :mod:`prsa_ctrl.studies.scenefilters`): in the cascade model, the tuning, the verification
    #: and the export.
    filters: tuple = ()
    #: How messages name each filter's frequency.
    filter_labels: tuple = ()
    description: str = ""
    #: The ``[move]`` values as the file typed them (for error messages).
    typed: Mapping[str, Any] = field(default_factory=dict, compare=False, repr=False)

    def motion(self) -> MotionProfile:
        """The move, m of screw travel (:mod:`prsa_ctrl.drive.motion`)."""
        if self.return_dwell_s is not None:
            return out_and_back(self.profile, self.distance_m, self.max_speed_m_s, self.acceleration_m_s2,
                                self.jerk_m_s3, dwell_s=self.return_dwell_s).shifted(self.start_s)
        return plan(self.profile, self.distance_m, self.max_speed_m_s, self.acceleration_m_s2,
                    self.jerk_m_s3).shifted(self.start_s)

    #: The registry name of the kind (:data:`prsa_ctrl.studies.scenekinds.KINDS`) and what marks its files.
    kind_name: ClassVar[str] = "move"
    marks: ClassVar[str] = "a [move] table"
    #: Not a speed-loop scene; where one is needed (:func:`~prsa_ctrl.studies.scene.require_speed_scene`)
    #: it is refused with this text, after the file's name.
    speed_loop: ClassVar[bool] = False
    speed_loop_refusal: ClassVar[str] = ("a move scene ([move] section, position cascade); expected a speed-loop scene "
                                         "here (prsa-tune --scene tunes move scenes)")

    @classmethod
    def claims(cls, doc: Mapping[str, Any]) -> bool:
        """A file with a ``[move]`` table."""
        return "move" in doc

    @classmethod
    def from_doc(cls, doc: Mapping[str, Any], origin: str, base: Any = None) -> "MoveScene":
        """The move a claimed file describes (:func:`parse_move_scene`; ``base`` is unused: a move
        reads no CSV trace)."""
        return parse_move_scene(doc, origin)

    @property
    def move_end_s(self) -> float:
        return self.motion().end_time

    @property
    def load_at_s(self) -> float:
        """Time the move's load appears, s (the middle of the move by default)."""
        m = self.motion()
        return self.load_time_s if self.load_time_s is not None else 0.5 * (m.t0[0] + m.end_time)

    @property
    def hold_step_s(self) -> float:
        return self.move_end_s + self.hold_delay_s

    @property
    def duration_s(self) -> float:
        return self.hold_step_s + self.hold_duration_s if self.hold_step_n else self.move_end_s + self.hold_delay_s

    def cascade_spec(self) -> CascadeSpec:
        """The numbers the cascade model and its tuners use (:mod:`prsa_ctrl.tuning.cascade`):
        the tuning layer reads no scene."""
        return CascadeSpec(
            origin=self.origin, motion=self.motion(),
            cruise_speed_m_s=self.max_speed_m_s * math.copysign(1.0, self.distance_m), load_at_s=self.load_at_s,
            initial_load_n=self.initial_load_n, load_n=self.load_n, hold_step_n=self.hold_step_n,
            measured=self.measured, position_rate=self.position_rate,
            position_delay_samples=self.position_delay_samples, fidelity=self.fidelity, ms_max=self.ms_max,
            position_controller=self.position_controller, weight_following=self.weight_following,
            weight_holding=self.weight_holding, bandwidth_ratio=self.bandwidth_ratio,
            kv_max_per_s=self.kv_max_per_s, filters=tuple(self.filters or ()))

    def loads(self) -> list[tuple[float, float]]:
        """Load steps ``(time s, N)`` of the run."""
        pts = [(0.0, self.initial_load_n)]
        if self.load_n != self.initial_load_n:
            pts.append((self.load_at_s, self.load_n))
        if self.hold_step_n:
            pts.append((self.hold_step_s, self.load_n + self.hold_step_n))
        return pts


def _check(origin: str, section: str, key: str, val: Any, spec: tuple[type, str]) -> Any:
    typ, expected = spec
    if typ is float and isinstance(val, int) and not isinstance(val, bool):
        val = float(val)
    if not isinstance(val, typ) or isinstance(val, bool):
        raise SceneError(f"{origin}: {section}.{key} = {quote(val)}; expected {expected}")
    if typ is float and not math.isfinite(val):
        raise SceneError(f"{origin}: {section}.{key} = {quote(val)}; expected {expected}")
    return val


def parse_move_scene(doc: Mapping[str, Any], origin: str) -> MoveScene:
    """A :class:`MoveScene` from the TOML document of a scene file with a ``[move]`` section.

    Parameters
    ----------
    doc : mapping
        The parsed TOML document.
    origin : str
        The file as the messages name it.

    Raises
    ------
    SceneError
        Unknown section or key, a value of the wrong type or range (one line naming the file
        and the key).
    """
    allowed = {"name", "description", "move", "cascade", "filters"}
    unknown = sorted(set(doc) - allowed)
    if unknown:
        raise SceneError(f"{origin}: unknown section {quote(unknown[0])} in a move scene; expected move, cascade, filters")
    kw: dict[str, Any] = {"origin": origin, "name": doc.get("name", Path(origin.split(" ")[0]).stem)}
    if not isinstance(kw["name"], str):
        raise SceneError(f"{origin}: name = {quote(kw['name'])}; expected a string")
    if "description" in doc:
        if not isinstance(doc["description"], str):
            raise SceneError(f"{origin}: description = {quote(doc['description'])}; expected a string")
        kw["description"] = doc["description"]
    for section, keys in (("move", _MOVE_KEYS), ("cascade", _CASCADE_KEYS)):
        table = doc.get(section, {})
        if not isinstance(table, Mapping):
            raise SceneError(f"{origin}: [{section}] must be a table")
        extra = sorted(set(table) - set(keys))
        if extra:
            raise SceneError(f"{origin}: unknown key {section}.{extra[0]}; expected one of "
                             + ", ".join(f"{section}.{k}" for k in keys))
        for key, val in table.items():
            kw[key] = _check(origin, section, key, val, keys[key])
    for key in _REQUIRED:
        if key not in kw:
            raise SceneError(f"{origin}: move.{key} missing; expected {_MOVE_KEYS[key][1]}")

    def bad(section: str, key: str) -> SceneError:
        spec = (_MOVE_KEYS if section == "move" else _CASCADE_KEYS)[key]
        return SceneError(f"{origin}: {section}.{key} = {quote(kw[key])}; expected {spec[1]}")

    if kw["profile"] not in PROFILE_KINDS:
        raise bad("move", "profile")
    if kw["distance_mm"] == 0:
        raise bad("move", "distance_mm")
    for key in ("max_speed_mm_s", "acceleration_m_s2", "jerk_m_s3", "hold_delay_s", "hold_duration_s", "window_um"):
        if key in kw and not kw[key] > 0:
            raise bad("move", key)
    if kw["profile"] == "s-curve" and "jerk_m_s3" not in kw:
        raise SceneError(f"{origin}: move.jerk_m_s3 missing; expected a jerk > 0 in m/s^3 for profile = 's-curve'")
    if kw["profile"] == "trapezoidal" and "jerk_m_s3" in kw:
        raise SceneError(f"{origin}: move.jerk_m_s3 = {quote(kw['jerk_m_s3'])} with profile = 'trapezoidal'; expected no "
                         "jerk (a trapezoidal move has infinite jerk) or profile = 's-curve'")
    for key in ("start_s", "return_dwell_s"):
        if kw.get(key, 0.0) < 0:
            raise bad("move", key)
    if kw.get("measured", "nut_angle") not in POSITION_SENSORS:
        raise bad("move", "measured")
    if not 1 <= kw.get("position_rate", 1) <= POSITION_RATE_MAX:
        raise bad("move", "position_rate")
    if not 0 <= kw.get("position_delay_samples", 0) <= POSITION_DELAY_MAX:
        raise bad("move", "position_delay_samples")
    if kw.get("fidelity", "compliant") not in ("rigid", "compliant"):
        raise bad("move", "fidelity")
    if "hold_step_n" in kw and kw["hold_step_n"] == 0:
        raise bad("move", "hold_step_n")
    try:
        check_peak_bound("cascade.ms_max", kw.get("ms_max", MS_MAX_DEFAULT))
    except ValueError:
        raise bad("cascade", "ms_max") from None
    if kw.get("position_controller", "p") not in ("p", "pi"):
        raise bad("cascade", "position_controller")
    for key in ("weight_following", "weight_holding"):
        if kw.get(key, 1.0) < 0:
            raise bad("cascade", key)
    if kw.get("weight_following", 1.0) + kw.get("weight_holding", 1.0) == 0:
        raise SceneError(f"{origin}: cascade.weight_following = cascade.weight_holding = 0; expected a positive weight")
    if kw.get("bandwidth_ratio", 1.0) < 1:
        raise bad("cascade", "bandwidth_ratio")
    if "kv_max" in kw:
        try:
            kw["kv_max_per_s"] = parse_kv(kw.pop("kv_max"), "cascade.kv_max")
        except ValueError as exc:
            raise SceneError(f"{origin}: {exc}") from None
    if "filters" in doc:  # the drive's fixed loop filters, tuned around (as a speed-loop scene's)
        kw["filters"], kw["filter_labels"] = parse_filters(doc["filters"], origin)
    kw["typed"] = dict(doc.get("move", {}))
    kw["distance_m"] = kw.pop("distance_mm") * 1e-3
    kw["max_speed_m_s"] = kw.pop("max_speed_mm_s") * 1e-3
    if "window_um" in kw:
        kw["window_m"] = kw.pop("window_um") * 1e-6
    sc = MoveScene(**kw)
    m = sc.motion()
    if sc.load_time_s is not None and not (m.t0[0] <= sc.load_time_s <= m.end_time):
        raise SceneError(f"{origin}: move.load_time_s = {quote(sc.load_time_s)}; expected a time in s inside the move "
                         f"[{m.t0[0]:.6g}, {m.end_time:.6g}]")
    return sc


def load_move_scene(name_or_path: "str | Path") -> MoveScene:
    """Load a move scene by built-in name (``"paper-move"``) or path.

    Parameters
    ----------
    name_or_path : str or Path

    Returns
    -------
    MoveScene

    Raises
    ------
    SceneError
        Missing or unreadable file, invalid TOML, unknown section or key, a value of the
        wrong type or range (one line naming the file and the key).

    Examples
    --------
    >>> sc = load_move_scene("paper-move")
    >>> sc.distance_m, sc.max_speed_m_s, sc.load_n
    (0.01, 0.03, 1500.0)
    """
    try:
        reader, origin, _ = locate_scene(name_or_path)
    except SceneError:
        raise SceneError(f"scene {quote(str(name_or_path))} not found; expected a built-in name or a readable "
                         ".toml file") from None
    doc = read_scene_doc(reader, origin)
    if not MoveScene.claims(doc):
        raise SceneError(f"{origin}: no [move] section; expected a move scene")
    return MoveScene.from_doc(doc, origin)

