"""The sections every speed-loop scene has, whatever its kind: the base :class:`Scene` of the two
frozen scene types, :class:`~prsa_ctrl.studies.scene.LoadStepScene` (load steps, ``[operating]
final_loads_n``) and :class:`~prsa_ctrl.studies.dutyscene.DutyCycleScene` (a load and/or setpoint
profile).

Each type validates its own fields (:meth:`Scene.check_events`, :meth:`Scene.check_kind`) and
checks itself against a plant (:meth:`Scene.check_plant`); the base validates the sections they
share (setpoint, objective, robustness bounds, verification, estimator, filters). Each type says
which scene files are its own (:meth:`Scene.claims`, asked by
:func:`~prsa_ctrl.studies.scene.parse_scene`) and reads its own keys of one
(:meth:`Scene.own_fields`); :meth:`Scene.from_doc` reads the sections they share. Calling
``Scene(...)`` builds the type the fields describe (``load_profile`` or ``setpoint_profile``
given: a duty cycle, else load steps): each type says which fields are its own
(:meth:`Scene.describes`), so the base names no kind.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from typing import Any, Callable, ClassVar, Mapping

from ..errors import SceneError
from ..options import (AGGREGATES, CONTROLLERS, ESTIMATORS, FIDELITIES, MS_MAX_DEFAULT, OBJECTIVES, PEAK_BOUND_RANGE,
                       SETPOINT_RAD_S, rad_s_to_rpm, rpm_to_rad_s)
from ..textsafe import quote
from ..drive.filters import LoopFilter
from .scenefile import LOAD_CHANGE_TIME_RANGE_S, SETPOINT_MAX_RPM
from .scenefilters import parse_filters, scene_filters
from .scenesections import Sections

__all__ = ["Scene", "OUTPUTS", "SCENE_FILE_KEYS", "holding_capacity_n", "field_checks", "scene_type"]

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

#: The report's keys of the shared fields, in the order of the JSON (``as_dict``).
_HEAD = ("name", "setpoint_rad_s", "initial_load", "final_loads", "step_time", "duration", "objective", "controller",
         "ms_max", "mt_max", "mks_max", "aggregate", "candidates", "fidelity", "discrete", "accuracy", "outputs",
         "estimator", "feedforward", "load_change_time_s", "origin")


#: The tables and keys of a speed-loop scene file with their TOML types (both kinds': each
#: refuses the other's by name first, :meth:`Scene.refuse_foreign`), besides ``name``,
#: ``description``, ``[filters]`` and the ``[spec]``/``[robust]``/``[uncertainty]`` sections.
SCENE_FILE_KEYS: Mapping[str, Mapping[str, type | tuple]] = {
    "operating": {
        "setpoint_rpm": float,
        "initial_load_n": float,
        "final_loads_n": list,
        "step_time_s": float,
        "duration_s": float,
        "load_profile_n": list,
        "load_trace_csv": str,
        "setpoint_profile_rpm": list,
        "setpoint_trace_csv": str,
    },
    "tuning": {
        "objective": str,
        "controller": str,
        "ms_max": float,
        "mt_max": float,
        "mks_max": float,
        "aggregate": str,
        "candidates": int,
        "goal": str,
        "setpoint_weight": float,
        "setpoint_share": float,
    },
    "verify": {"fidelity": str, "discrete": bool, "accuracy": float},
    "estimator": {"kind": str, "feedforward": bool, "load_change_time_s": float},
    "outputs": {"needed": list},
}

#: File keys both kinds read -> (field, conversion); each kind converts its own (:meth:`Scene.own_fields`).
_SHARED_KEYS: Mapping[str, tuple[str, Callable[[Any], Any]]] = {
    "setpoint_rpm": ("setpoint_rad_s", rpm_to_rad_s),
    "initial_load_n": ("initial_load", float),
    "duration_s": ("duration", float),
    "needed": ("outputs", lambda v: tuple(v)),
    "kind": ("estimator", str),
}


def field_checks(origin: str) -> tuple[Callable[[str, Any, str], SceneError], Callable[[str, Any], float]]:
    """``(bad, finite)`` for the messages of a scene's field checks: ``bad(key, value, expected)``
    is the one-line :class:`~prsa_ctrl.errors.SceneError`; ``finite(key, value)`` the value as a
    float, or that error for a non-number."""

    def bad(key: str, value: Any, expected: str) -> SceneError:
        return SceneError(f"{origin}: {key} = {quote(value)}; expected {expected}")

    def finite(key: str, value: Any) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise bad(key, value, "a finite number")
        return float(value)

    return bad, finite


def holding_capacity_n(plant: Any, setpoint_rad_s: float) -> float:
    """Largest axial load, N, the motor can hold at a nut speed (rad/s) at constant speed:
    ``(T_max - T_0 - b w) 2 pi eta / L`` with the torque limit ``T_max``, the no-load torque
    ``T_0``, the viscous coefficient ``b``, the forward efficiency ``eta`` and the lead ``L``
    (the rigid operating point of :mod:`prsa_ctrl.plant.equilibrium`, solved for the load).

    Examples
    --------
    >>> from prsa_ctrl import load_plant
    >>> from prsa_ctrl.options import rpm_to_rad_s
    >>> round(holding_capacity_n(load_plant(), rpm_to_rad_s(300)))
    7949
    """
    v = plant.values
    spare = plant.torque_limit - v["friction.no_load_torque_n_m"] - v["friction.viscous_n_m_s_per_rad"] * setpoint_rad_s
    return spare * v["friction.efficiency"] / plant.lead_per_rad


def scene_type(given: Mapping[str, Any]) -> type:
    """The scene type (a subclass of :class:`Scene`) that constructor fields ``given`` describe:
    the one whose :meth:`Scene.describes` answers yes.

    Raises
    ------
    TypeError
        None or several do (the types are defined in :mod:`prsa_ctrl.studies.scene`, which
        imports them all).
    """
    found = [t for t in Scene._types if t.describes(given)]
    if len(found) != 1:
        raise TypeError(f"Scene(**fields): {len(found)} scene types describe these fields; expected one (import "
                        "prsa_ctrl.studies.scene, which defines the load-step and duty-cycle types)")
    return found[0]


@dataclass(frozen=True)
class Scene:
    """A speed-loop tuning scenario (SI units; the file uses rpm for the setpoint): the base of
    :class:`~prsa_ctrl.studies.scene.LoadStepScene` and
    :class:`~prsa_ctrl.studies.dutyscene.DutyCycleScene`, the name both answer to
    (``isinstance(scene, Scene)``: a speed-loop scene, not a move).

    ``Scene(**fields)`` builds the type the fields describe: a duty cycle when a
    ``load_profile`` or ``setpoint_profile`` is given, else load steps (``Scene()`` is the
    default load step).

    Parameters
    ----------
    setpoint_rad_s : float, rad/s
        Nut-speed setpoint (a duty cycle: its setpoint profile's t = 0 value).
    initial_load : float, N
        Axial load before the first event (steady state).
    final_loads : tuple of float, N
        Load(s) after the step; several levels are tuned jointly (``aggregate``); empty for a
        duty cycle.
    step_time : float, s
        Time of the load step (a duty cycle: of its profiles' first change).
    duration : float, s
        End of the record.
    objective : {"ie", "iae", "itae", "ise"}
    controller : {"pi", "pid"}
    ms_max, mt_max : float
        Robustness bounds (``mt_max`` optional).
    mks_max : float, N m s/rad, optional
        Bound on the true peak noise sensitivity ``max |C F S|`` from the measured speed to
        the torque command (:meth:`prsa_ctrl.tuning.LoopModel.noise_peak`), or none.
    aggregate : {"sum", "worst"}
        How several load levels are combined.
    candidates : int
        How many tuned candidates are verified on the nonlinear simulator.
    fidelity : {"auto", "rigid", "compliant", "multi-roller"}
        Fidelity of the verification; ``"auto"`` picks the cheapest that delivers ``outputs``
        at ``accuracy`` (see :func:`~prsa_ctrl.studies.scene.choose_fidelity`).
    discrete : bool
        Verify with the sampled controller, ZOH and quantised encoder.
    accuracy : float
        Relative accuracy the verified metrics need (fraction of the peak drop); it also sets
        the integrator tolerance.
    outputs : tuple of str
        Signals the scene needs (see ``OUTPUTS``).
    estimator : {"none", "kf"}
        Speed measurement: the drive's filtered backward difference, or the Kalman filter of
        :mod:`prsa_ctrl.drive.estimator` (filterpy is imported only then).
    feedforward : bool
        Feed the estimated load torque forward (needs ``estimator = "kf"``); its gain is tuned.
    load_change_time_s : float, s
        Load random-walk setting of the Kalman filter.
    origin : str
        How messages name the scene (its file).
    """

    name: str = "custom"
    setpoint_rad_s: float = SETPOINT_RAD_S
    initial_load: float = 500.0
    final_loads: tuple[float, ...] = (1500.0,)
    step_time: float = 0.2
    duration: float = 0.5
    objective: str = "iae"
    controller: str = "pi"
    ms_max: float = MS_MAX_DEFAULT
    mt_max: float | None = None
    mks_max: float | None = None
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
    #: Typed ``[spec]``, ``[robust]``, ``[uncertainty]`` (:class:`~prsa_ctrl.studies.scenesections.Sections`,
    #: parsed once; a dict of ``parse_scene_sections`` is converted); falsy when the file has none.
    sections: Sections = field(default_factory=Sections, compare=False, hash=False)
    #: Speed-measurement and torque-command filters of the drive (``[filters]``,
    #: :mod:`prsa_ctrl.studies.scenefilters`), in the loop models, the verification and the export.
    filters: tuple[LoopFilter, ...] = ()
    #: How messages name each filter's frequency (``"scene.toml: filters.notch[1].centre_hz = 163.0"``).
    filter_labels: tuple[str, ...] = field(default=(), compare=False, hash=False, repr=False)

    #: The scene types (subclasses), for ``Scene(**fields)``: each says which fields describe it.
    _types: ClassVar[list] = []
    #: A speed-loop scene (load steps or a duty cycle): what
    #: :func:`~prsa_ctrl.studies.scene.require_speed_scene` asks of a scene's type.
    speed_loop: ClassVar[bool] = True

    def __init_subclass__(cls, **kw: Any) -> None:
        super().__init_subclass__(**kw)
        Scene._types.append(cls)

    def __new__(cls, *args: Any, **kw: Any):
        return super().__new__(scene_type(kw) if cls is Scene else cls)

    @classmethod
    def describes(cls, given: Mapping[str, Any]) -> bool:
        """Whether constructor fields ``given`` describe a scene of this type (each type's own)."""
        raise NotImplementedError

    # --- reading a scene file -------------------------------------------------------------------------

    @classmethod
    def claims(cls, doc: Mapping[str, Any]) -> bool:
        """Whether a parsed scene file (its TOML document) is a scene of this type."""
        raise NotImplementedError

    @classmethod
    def refuse_foreign(cls, doc: Mapping[str, Any], origin: str) -> None:
        """Refuse, by name, a key of the file that the other speed-loop kind takes."""
        raise NotImplementedError

    @classmethod
    def own_fields(cls, kw: dict, origin: str, base: Any) -> None:
        """Turn this type's own keys of ``[operating]`` (read and type-checked into ``kw`` under
        their file names) into its fields, in place (``base``: the folder CSV traces are read from)."""
        raise NotImplementedError

    @classmethod
    def from_doc(cls, doc: Mapping[str, Any], origin: str, base: Any = None) -> "Scene":
        """The scene of this type a claimed file describes (:meth:`claims`): the sections both
        kinds share, then the type's own keys (:meth:`own_fields`), validated on construction.

        Parameters
        ----------
        doc : mapping
            The parsed TOML document.
        origin : str
            The file as the messages name it.
        base : path-like, optional
            The folder relative CSV traces are read from.

        Raises
        ------
        SceneError
            One line naming the file, the key as written and what was expected.
        """
        keys_of = SCENE_FILE_KEYS
        unknown = sorted(set(doc) - set(keys_of) - {"name", "description", "spec", "robust", "uncertainty", "filters"})
        if unknown:
            raise SceneError(f"{origin}: unknown section {quote(unknown[0])}; expected one of "
                             f"{', '.join([*keys_of, 'spec', 'robust', 'uncertainty', 'filters'])}")
        cls.refuse_foreign(doc, origin)
        kw: dict[str, Any] = {"origin": origin}
        if "filters" in doc:
            kw["filters"], kw["filter_labels"] = parse_filters(doc["filters"], origin)
        if "name" in doc:
            if not isinstance(doc["name"], str):
                raise SceneError(f"{origin}: name = {quote(doc['name'])}; expected a string")
            kw["name"] = doc["name"]
        for section, keys in keys_of.items():
            table = doc.get(section, {})
            if not isinstance(table, Mapping):
                raise SceneError(f"{origin}: [{section}] must be a table")
            extra = sorted(set(table) - set(keys))
            if extra:
                raise SceneError(f"{origin}: unknown key {section}.{extra[0]}; expected one of "
                                 f"{', '.join(f'{section}.{k}' for k in keys)}")
            for key, typ in keys.items():
                if key not in table:
                    continue
                val = table[key]
                ok = isinstance(val, typ) and not (typ in (float, int) and isinstance(val, bool))
                if typ is float and isinstance(val, int) and not isinstance(val, bool):
                    val, ok = float(val), True
                if not ok:
                    raise SceneError(f"{origin}: {section}.{key} = {quote(val)}; expected a {typ.__name__}")
                kw[key] = val
        cls.own_fields(kw, origin, base)
        rpm = kw.get("setpoint_rpm")
        if rpm is not None and not (math.isfinite(rpm) and 0 < rpm <= SETPOINT_MAX_RPM):
            raise SceneError(f"{origin}: operating.setpoint_rpm = {quote(rpm)}; expected a nut speed in (0, "
                             f"{SETPOINT_MAX_RPM:g}] rpm")
        for old, (new, conv) in _SHARED_KEYS.items():
            if old in kw:
                kw[new] = conv(kw.pop(old))
        if {"spec", "robust", "uncertainty"} & set(doc):
            kw["sections"] = Sections.parse(doc, origin)
        return cls(**kw)


    def __post_init__(self) -> None:
        o = self.origin
        if not isinstance(self.sections, Sections):
            object.__setattr__(self, "sections", Sections.from_dict(self.sections, o))
        bad, finite = field_checks(o)
        self.check_kind(bad, finite)
        if self.filters or self.filter_labels or not isinstance(self.filters, tuple):
            for name, value in zip(("filters", "filter_labels"), scene_filters(self)):
                object.__setattr__(self, name, value)

        if finite("setpoint_rad_s", self.setpoint_rad_s) <= 0:
            raise bad("setpoint_rpm", float(f"{self.setpoint_rpm:.12g}"), "a positive nut speed in rpm")
        if finite("initial_load", self.initial_load) < 0:
            raise bad("initial_load", self.initial_load, "a load >= 0 N (compressive)")
        self.check_events(bad, finite)
        if self.objective not in OBJECTIVES:
            raise bad("objective", self.objective, "one of ie, iae, itae, ise")
        if self.controller not in CONTROLLERS:
            raise bad("controller", self.controller, "pi or pid")
        lo, hi = PEAK_BOUND_RANGE
        if not lo < finite("ms_max", self.ms_max) < hi:
            raise bad("ms_max", self.ms_max, f"a number in ({lo:g}, {hi:g})")
        if self.mt_max is not None and not lo < finite("mt_max", self.mt_max) < hi:
            # Mt = max|T| >= |T(0)| = 1 with integral action: a bound <= 1 cannot be met.
            raise bad("mt_max", self.mt_max, f"a number in ({lo:g}, {hi:g})")
        if self.mks_max is not None and not finite("mks_max", self.mks_max) > 0.0:
            raise bad("mks_max", self.mks_max, "a positive noise-sensitivity bound in N m s/rad")
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
        lo, hi = LOAD_CHANGE_TIME_RANGE_S
        if not lo <= finite("load_change_time_s", self.load_change_time_s) <= hi:
            raise bad("estimator.load_change_time_s", self.load_change_time_s,
                      f"a positive time in [{lo:g}, {hi:g}] s (the Kalman filter's load random-walk time: from a few controller "
                      "samples to a load that practically never changes; beyond, its process noise underflows)")

    # --- what each type answers for itself --------------------------------------------------------

    def check_kind(self, bad, finite) -> None:
        """Validate the type's own fields before the shared ones (a duty cycle also derives
        ``initial_load``, ``final_loads`` and ``step_time`` from its profiles here)."""

    def check_events(self, bad, finite) -> None:
        """Validate the events of the record (load steps, or the profiles' end) against ``duration``."""
        raise NotImplementedError

    def check_plant(self, plant: Any, label: Callable[[str, Any], str], rpm_min: float,
                    typed: Mapping[str, str]) -> None:
        """The type's half of :func:`~prsa_ctrl.studies.scene.check_against_plant` (``label(field,
        value)`` names a value as typed or by its scene-file key; ``typed``: the fields given on
        the command line, as typed; ``rpm_min``: the slowest setpoint the plant runs, rpm)."""
        raise NotImplementedError

    @property
    def cases(self) -> list[str]:
        """One label per record the scene tunes and verifies."""
        raise NotImplementedError

    def profile_dict(self) -> dict[str, Any]:
        """The duty-cycle keys of the report (``load_profile`` ... ``profile_source``)."""
        raise NotImplementedError

    @property
    def setpoint_points(self) -> tuple[tuple[float, float], ...]:
        """The setpoint over the record, ``((t s, rad/s), ...)`` (a constant: one point)."""
        return ((0.0, self.setpoint_rad_s),)

    @property
    def design_setpoint_weight(self) -> float:
        """The 2-DOF setpoint weight the design runs with (1 unless a setpoint profile sets it)."""
        return 1.0

    def profile_end(self) -> float:
        """Time of the last breakpoint of a duty cycle, s (0 for load steps)."""
        return 0.0

    @property
    def input_files(self) -> tuple[str, ...]:
        """Resolved paths of the files the scene read besides its own TOML (CSV traces): inputs
        of the run, never outputs."""
        return ()

    # --- shared ---------------------------------------------------------------------------------------

    @property
    def setpoint_rpm(self) -> float:
        return rad_s_to_rpm(self.setpoint_rad_s)

    @property
    def robust(self) -> dict[str, Any]:
        """Deprecated (warns): the typed :attr:`sections` as the dict of ``parse_scene_sections``
        (a copy); read ``scene.sections`` (``.spec``, ``.robust``, ``.uncertainty``) instead."""
        import warnings

        warnings.warn("Scene.robust is deprecated; use Scene.sections (typed [spec], [robust], [uncertainty]) or "
                      "Scene.sections.as_dict()", DeprecationWarning, stacklevel=2)
        return self.sections.as_dict()

    def replace(self, **changes: Any) -> "Scene":
        """Copy with some fields changed (validated again); unknown names are an error."""
        allowed = {f.name for f in fields(self)}
        unknown = sorted(set(changes) - allowed)
        if unknown:
            raise SceneError(f"unknown scene field {quote(unknown[0])}; allowed: {', '.join(sorted(allowed))}")
        return replace(self, **changes)

    def as_dict(self) -> dict[str, Any]:
        """The scene in the JSON report: every field of both types in one layout (the other
        type's keys at their unset values), the setpoint also in rpm, the filters where there are
        some."""
        d = {k: getattr(self, k) for k in _HEAD}
        d["robust"] = self.sections.as_dict()
        d.update(self.profile_dict())
        d["final_loads"] = list(self.final_loads)
        d["outputs"] = list(self.outputs)
        d["setpoint_rpm"] = self.setpoint_rpm
        d.update({"filters": [lf.as_dict() for lf in self.filters]} if self.filters else {})
        return d
