"""Tuning scenes (``tuning/*.toml``): the operating point, the load step(s) or a duty cycle,
the objective, the robustness limits and what the verification must deliver.

Duty cycles
-----------
Instead of ``initial_load_n`` / ``final_loads_n`` / ``step_time_s`` a scene may describe its
load, and its setpoint, as a profile over the record (``[operating]``):

``load_profile_n = [[t_s, F_n], ...]``
    Piecewise linear. The first row is at ``t_s = 0`` (the steady state the record starts
    in); times increase strictly. A row ``[t_s, F_n]`` ramps linearly from the previous
    row's value to ``F_n`` at ``t_s``; a row ``[t_s, F_n, "step"]`` holds the previous value
    until ``t_s`` and steps to ``F_n`` there. After the last row the value is held.
``load_trace_csv = "file.csv"``
    A measured force trace, path relative to the scene file: a header row with the columns
    ``time_s`` and ``axial_load_n`` (lines starting with ``#`` before it are comments), then
    one row per sample, times strictly increasing from 0, every value finite, loads >= 0 N;
    it is used as a piecewise-linear profile. UTF-8, with or without a byte-order mark (Excel
    exports); at most ``MAX_PROFILE_ROWS`` rows and ``MAX_TRACE_BYTES`` bytes (refused before
    reading, or as soon as the row limit is passed). Errors name the file, line and column
    and the value as typed, also for a value the plant cannot take (a load the motor cannot
    hold). The run starts in steady state at the first row's value: the trace must hold it
    for ``PRE_EVENT_SAMPLES`` controller samples before it first changes (a measured trace
    that is noisy from its second row needs such a steady lead-in; the message says how long).
``setpoint_profile_rpm`` / ``setpoint_trace_csv``
    The same for the nut-speed setpoint (rpm; CSV column ``setpoint_rpm``). A sampled drive
    reads it at each controller sample.

``[tuning] goal`` says what the tuner optimises: ``"load"`` (load rejection on the load
profile at the constant setpoint), ``"setpoint"`` (tracking of the setpoint profile at the
constant load) or ``"mix"`` (both records, weighted ``1 - setpoint_share`` and
``setpoint_share``; both profiles needed). ``setpoint_weight`` is the 2-DOF setpoint weight
``b`` in [0, 1] on the proportional path, ``u = kp (b r - y) + I``; the integral acts on
``r - y``. The objective (``iae``, ``itae`` or ``ise``) integrates the tracking error
``setpoint - speed`` over the whole record.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Mapping

from ..textsafe import quote
from ..errors import SceneError
from ..options import (AGGREGATES, CONTROLLERS, ESTIMATORS, FIDELITIES, MS_MAX_DEFAULT, OBJECTIVES, PEAK_BOUND_RANGE,
                       RAD_S_PER_RPM, RIGID_RELATIVE_ERROR, SETPOINT_RAD_S, rad_s_to_rpm, rpm_to_rad_s)
from ..drive.filters import LoopFilter
from .movescene import MoveScene, parse_move_scene
from .scenesections import Robust, Sections
from .scenefilters import check_filters_against_plant, parse_filters, scene_filters
from .scenefile import (DEFAULT_SCENE, LOAD_CHANGE_TIME_RANGE_S, MAX_LOAD_LEVELS, MAX_RECORD_SAMPLES, MIN_LOAD_STEP_N,
                        POST_EVENT_SAMPLES, PRE_EVENT_SAMPLES, SETPOINT_MAX_RPM, STICTION_MARGIN, builtin_scenes,
                        is_move_scene, locate_scene, read_scene_doc)

#: What a duty-cycle scene tunes for (see the module docstring).
GOALS = ("load", "setpoint", "mix")
#: Most rows of a profile or a CSV trace (one per controller sample at most: 40 000 samples).
MAX_PROFILE_ROWS = 40_000
#: Largest CSV trace file, bytes (40 000 rows of up to ~400 characters; a larger file is refused
#: before it is read).
MAX_TRACE_BYTES = 16 * 1024 * 1024

__all__ = ["Scene", "load_scene", "builtin_scenes", "choose_fidelity", "DEFAULT_SCENE", "OUTPUTS",
           "RIGID_RELATIVE_ERROR", "check_against_plant", "holding_capacity_n", "SETPOINT_MAX_RPM",
           "PRE_EVENT_SAMPLES", "POST_EVENT_SAMPLES", "MAX_RECORD_SAMPLES", "MAX_LOAD_LEVELS", "MIN_LOAD_STEP_N",
           "GOALS", "read_trace_csv", "profile_rows", "is_move_scene", "require_speed_scene"]


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
    mks_max : float, N m s/rad, optional
        Bound on the true peak noise sensitivity ``max |C F S|`` from the measured speed to
        the torque command (:meth:`prsa_ctrl.tuning.LoopModel.noise_peak`), or none.
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
        :mod:`prsa_ctrl.drive.estimator` (filterpy is imported only then).
    feedforward : bool
        Feed the estimated load torque forward (needs ``estimator = "kf"``); its gain is tuned.
    load_change_time_s : float, s
        Load random-walk setting of the Kalman filter.
    load_profile : tuple of (time s, N), optional
        Duty-cycle load, piecewise linear in :class:`prsa_ctrl.sim.engine.PiecewiseLinear`'s
        convention (two points at one time make a step). With a profile, ``initial_load`` is
        its t = 0 value, ``final_loads`` is empty and ``step_time`` is the time of its first
        change (all three are set from the profile).
    setpoint_profile : tuple of (time s, rad/s), optional
        Duty-cycle setpoint, the same way (``setpoint_rad_s`` is its t = 0 value).
    goal : {"auto", "load", "setpoint", "mix"}
        What the tuner optimises on a duty cycle (``"auto"``: from the profiles given).
    setpoint_weight : float
        2-DOF setpoint weight b in [0, 1] on the proportional path.
    setpoint_share : float
        Weight of the setpoint-tracking objective in ``goal = "mix"``, in (0, 1).
    profile_source : str
        Where the profiles came from (reported).
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
    load_profile: tuple[tuple[float, float], ...] | None = None
    setpoint_profile: tuple[tuple[float, float], ...] | None = None
    goal: str = "auto"
    setpoint_weight: float = 1.0
    setpoint_share: float = 0.5
    profile_source: str = ""
    #: Where each point of a CSV trace came from: ``{"load_profile": (file, column, ((line,
    #: typed value), ...))}`` (messages name the line; empty for profiles written in the scene).
    trace_lines: Mapping[str, Any] = field(default_factory=dict, compare=False, hash=False, repr=False)
    #: Speed-measurement and torque-command filters of the drive (``[filters]``,
    #: :mod:`prsa_ctrl.studies.scenefilters`), in the loop models, the verification and the export.
    filters: tuple[LoopFilter, ...] = ()
    #: How messages name each filter's frequency (``"scene.toml: filters.notch[1].centre_hz = 163.0"``).
    filter_labels: tuple[str, ...] = field(default=(), compare=False, hash=False, repr=False)

    def __post_init__(self) -> None:
        o = self.origin
        if not isinstance(self.sections, Sections):
            object.__setattr__(self, "sections", Sections.from_dict(self.sections, o))

        def bad(key: str, value: Any, expected: str) -> SceneError:
            return SceneError(f"{o}: {key} = {quote(value)}; expected {expected}")

        def finite(key: str, value: Any) -> float:
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise bad(key, value, "a finite number")
            return float(value)

        self._check_duty(bad, finite)
        if self.filters or self.filter_labels or not isinstance(self.filters, tuple):
            for name, value in zip(("filters", "filter_labels"), scene_filters(self)):
                object.__setattr__(self, name, value)

        if finite("setpoint_rad_s", self.setpoint_rad_s) <= 0:
            raise bad("setpoint_rpm", float(f"{self.setpoint_rpm:.12g}"), "a positive nut speed in rpm")
        if finite("initial_load", self.initial_load) < 0:
            raise bad("initial_load", self.initial_load, "a load >= 0 N (compressive)")
        if not self.final_loads and not self.is_profile:
            raise bad("final_loads", list(self.final_loads), "at least one load")
        for f in self.final_loads:
            if finite("final_loads", f) < 0:
                raise bad("final_loads", f, "loads >= 0 N (compressive)")
            if f == self.initial_load:
                raise bad("final_loads", f, f"a load different from the initial {self.initial_load:g} N")
        if self.is_profile:
            if finite("duration", self.duration) <= self.profile_end():
                raise bad("duration", self.duration, f"a time beyond the profile's last point at {self.profile_end():g} s")
        elif finite("step_time", self.step_time) <= 0:
            raise bad("step_time", self.step_time, "a time > 0 s (the loop starts in steady state before the load step)")
        if not self.is_profile and finite("duration", self.duration) <= self.step_time + 1e-3:
            raise bad("duration", self.duration, f"a time beyond step_time + 1 ms ({self.step_time + 1e-3:g} s)")
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

    def _check_duty(self, bad, finite) -> None:
        """Validate the duty-cycle fields and derive the step fields from the profiles."""
        if not self.is_profile:
            if self.goal not in ("auto", "load"):
                raise bad("goal", self.goal, "'load' for a load-step scene (setpoint and mix goals need a "
                          "setpoint_profile_rpm / load_profile_n duty cycle)")
            if self.setpoint_weight != 1.0:
                raise bad("setpoint_weight", self.setpoint_weight, "1 without a setpoint profile")
            return
        firsts = []
        for key, prof, unit, lo in (("load_profile", self.load_profile, "N", 0.0),
                                    ("setpoint_profile", self.setpoint_profile, "rad/s", None)):
            if prof is None:
                continue
            pts = _check_points(prof, f"{self.origin}: {key}", unit)
            for _, v in pts:
                if lo is not None and v < lo:
                    raise bad(key, v, f"values >= {lo:g} {unit}")
                if lo is None and v <= 0:
                    raise bad(key, v, "positive nut speeds (rad/s)")
            object.__setattr__(self, key, pts)
            firsts.append(_first_change(pts))
        if self.load_profile is not None:
            object.__setattr__(self, "initial_load", self.load_profile[0][1])
        if self.setpoint_profile is not None:
            object.__setattr__(self, "setpoint_rad_s", self.setpoint_profile[0][1])
        if all(f is None for f in firsts):
            raise bad("load_profile" if self.load_profile is not None else "setpoint_profile",
                      [list(p) for p in (self.load_profile or self.setpoint_profile)][:4],
                      "a profile that changes (a constant is initial_load_n / setpoint_rpm)")
        object.__setattr__(self, "final_loads", ())
        object.__setattr__(self, "step_time", min(f for f in firsts if f is not None))
        have = {"load": self.load_profile is not None, "setpoint": self.setpoint_profile is not None}
        if self.goal == "auto":
            object.__setattr__(self, "goal", "mix" if all(have.values()) else ("load" if have["load"] else "setpoint"))
        if self.goal not in GOALS:
            raise bad("goal", self.goal, "one of load, setpoint, mix")
        need = {"load": "a load profile and no setpoint profile (load rejection at a constant setpoint)",
                "setpoint": "a setpoint profile and no load profile (tracking at a constant load)",
                "mix": "both a load and a setpoint profile"}[self.goal]
        if (self.goal == "mix") != all(have.values()) or (self.goal != "mix" and not have[self.goal]):
            raise bad("goal", self.goal, f"{need}; the scene has "
                      + " and ".join(k + " profile" for k, v in have.items() if v))
        if not 0.0 <= finite("setpoint_weight", self.setpoint_weight) <= 1.0:
            raise bad("setpoint_weight", self.setpoint_weight, "a setpoint weight b in [0, 1]")
        if not 0.0 < finite("setpoint_share", self.setpoint_share) < 1.0:
            raise bad("setpoint_share", self.setpoint_share, "a weight in (0, 1) of the setpoint objective in the mix")
        if self.sections:
            raise SceneError(f"{self.origin}: [spec]/[robust]/[uncertainty] with a duty cycle; expected them in a load-step "
                             "scene (the robust and Monte-Carlo studies run load steps)")
        if self.objective == "ie":
            raise bad("objective", self.objective, "iae, itae or ise on a duty cycle (the signed integral IE "
                      "cancels between its events)")
        if not self.discrete:
            raise bad("discrete", self.discrete, "true on a duty cycle (the tuner's profile model is the sampled drive)")
        if self.estimator != "none":
            raise bad("estimator", self.estimator, "none on a duty cycle (the Kalman-filter loop takes load steps only)")

    @property
    def robust(self) -> dict[str, Any]:
        """Deprecated: the typed :attr:`sections` as the dict of ``parse_scene_sections`` (a copy)."""
        return self.sections.as_dict()

    @property
    def is_profile(self) -> bool:
        """Whether the scene is a duty cycle (a load or setpoint profile) rather than load steps."""
        return self.load_profile is not None or self.setpoint_profile is not None

    @property
    def cases(self) -> list[str]:
        """One label per record the scene tunes and verifies: one per load step, or the duty
        cycle's load and/or setpoint records (``goal``)."""
        if not self.is_profile:
            return [f"step to {f:g} N" for f in self.final_loads]
        return {"load": ["load profile"], "setpoint": ["setpoint profile"],
                "mix": ["load profile", "setpoint profile"]}[self.goal]

    def profile_end(self) -> float:
        """Time of the last breakpoint of the duty cycle, s (0 for a step scene)."""
        return max((p[-1][0] for p in (self.load_profile, self.setpoint_profile) if p is not None), default=0.0)

    @property
    def input_files(self) -> tuple[str, ...]:
        """Resolved paths of the files the scene read besides its own TOML (CSV traces): inputs
        of the run, never outputs."""
        return tuple(info[3] for info in self.trace_lines.values() if len(info) > 3)

    @property
    def setpoint_rpm(self) -> float:
        return rad_s_to_rpm(self.setpoint_rad_s)

    def replace(self, **changes: Any) -> "Scene":
        """Copy with some fields changed (validated again); unknown names are an error."""
        allowed = {f.name for f in fields(self)}
        unknown = sorted(set(changes) - allowed)
        if unknown:
            raise SceneError(f"unknown scene field {quote(unknown[0])}; allowed: {', '.join(sorted(allowed))}")
        return replace(self, **changes)

    def as_dict(self) -> dict[str, Any]:
        d = {("robust" if f.name == "sections" else f.name): getattr(self, f.name)
             for f in fields(self) if f.name != "trace_lines"}
        d["robust"] = self.sections.as_dict()
        d["final_loads"] = list(self.final_loads)
        d["outputs"] = list(self.outputs)
        d["setpoint_rpm"] = self.setpoint_rpm
        for key in ("load_profile", "setpoint_profile"):
            d[key] = None if getattr(self, key) is None else [list(p) for p in getattr(self, key)]
        del d["filter_labels"], d["filters"]  # the filters only where there are some (reports stay as they were)
        d.update({"filters": [lf.as_dict() for lf in self.filters]} if self.filters else {})
        return d


def _check_points(points: Any, where: str, unit: str) -> tuple[tuple[float, float], ...]:
    """Validate profile points in the PiecewiseLinear convention (first at t = 0, times
    non-decreasing, at most two at one time = a step)."""
    try:
        pts = tuple((float(t), float(v)) for t, v in points)
    except (TypeError, ValueError):
        raise SceneError(f"{where} = {quote(points)}; expected (time_s, value) pairs") from None
    if len(pts) < 2 or len(pts) > 2 * MAX_PROFILE_ROWS:
        raise SceneError(f"{where}: {len(pts)} points; expected 2 to {MAX_PROFILE_ROWS} rows")
    for i, (t, v) in enumerate(pts):
        if not (math.isfinite(t) and math.isfinite(v)):
            raise SceneError(f"{where}: point {i + 1} = ({quote(t)}, {quote(v)}); expected a finite time (s) and value ({unit})")
    if pts[0][0] != 0.0:
        raise SceneError(f"{where}: first time {quote(pts[0][0])} s; expected 0 (the record starts in steady state)")
    for i in range(1, len(pts)):
        if pts[i][0] < pts[i - 1][0] or (i >= 2 and pts[i][0] == pts[i - 1][0] == pts[i - 2][0]):
            raise SceneError(f"{where}: point {i + 1} at {quote(pts[i][0])} s after {quote(pts[i - 1][0])} s; "
                             "expected increasing times (one repeated time = a step)")
    return pts


def _first_change(pts: tuple[tuple[float, float], ...]) -> float | None:
    """Time at which a profile first leaves its t = 0 value (None if it never does)."""
    v0 = pts[0][1]
    for i in range(1, len(pts)):
        if pts[i][1] != v0:
            return pts[i - 1][0]
    return None


def profile_rows(rows: Any, where: str, scale: float = 1.0) -> tuple[tuple[float, float], ...]:
    """Profile points from the scene file's rows ``[t_s, value]`` (ramp to the value at
    ``t_s``) or ``[t_s, value, "step"]`` (hold the previous value until ``t_s``, step there).

    Parameters
    ----------
    rows : list of lists
        As written in the file.
    where : str
        ``"<file>: operating.load_profile_n"``, for the messages.
    scale : float
        Factor to SI (e.g. rpm -> rad/s).

    Returns
    -------
    tuple of (time s, value)
        In :class:`prsa_ctrl.sim.engine.PiecewiseLinear`'s convention.

    Examples
    --------
    >>> profile_rows([[0, 500], [0.1, 500], [0.2, 1500], [0.3, 800, "step"]], "demo")
    ((0.0, 500.0), (0.1, 500.0), (0.2, 1500.0), (0.3, 1500.0), (0.3, 800.0))
    """
    if not isinstance(rows, list) or len(rows) < 2:
        raise SceneError(f"{where} = {quote(rows)}; expected a list of at least 2 rows [t_s, value] or [t_s, value, \"step\"]")
    if len(rows) > MAX_PROFILE_ROWS:
        raise SceneError(f"{where}: {len(rows)} rows; expected at most {MAX_PROFILE_ROWS}")
    pts: list[tuple[float, float]] = []
    prev_t = None
    for i, row in enumerate(rows, start=1):
        ok = isinstance(row, list) and len(row) in (2, 3) and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) for x in row[:2]) and (
            len(row) == 2 or row[2] == "step")
        if not ok:
            raise SceneError(f"{where}: row {i} = {quote(row)}; expected [t_s, value] (ramp to value at t_s) or "
                             "[t_s, value, \"step\"] (step to value at t_s)")
        t, v = float(row[0]), float(row[1]) * scale
        if not (math.isfinite(t) and math.isfinite(v)):
            raise SceneError(f"{where}: row {i} = {quote(row)}; expected finite numbers")
        if i == 1:
            if t != 0.0 or len(row) == 3:
                raise SceneError(f"{where}: row 1 = {quote(row)}; expected [0, value] (the steady state the record starts in)")
        elif t <= prev_t:
            raise SceneError(f"{where}: row {i} = {quote(row)}: time {t:g} s after {prev_t:g} s; expected strictly increasing times")
        if len(row) == 3:
            pts.append((t, pts[-1][1]))
        pts.append((t, v))
        prev_t = t
    return tuple(pts)


def read_trace_csv(path: Path, column: str, where: str, scale: float = 1.0,
                   lines_out: list | None = None) -> tuple[tuple[float, float], ...]:
    """A measured trace from CSV (see the module docstring): strict, one line per problem.

    Parameters
    ----------
    path : Path
    column : str
        ``axial_load_n`` (N, >= 0) or ``setpoint_rpm`` (rpm, > 0 and at most
        ``SETPOINT_MAX_RPM``).
    where : str
        How the scene names the file (for the messages).
    scale : float
        Factor to SI.
    lines_out : list, optional
        Receives ``(line number, value as typed)`` of each point, for later messages.

    Raises
    ------
    SceneError
        Naming the file, the line and the value: a missing column, a non-number, a non-finite
        or out-of-range value, a time that does not increase, a trace that does not start at 0,
        a file above ``MAX_TRACE_BYTES`` or ``MAX_PROFILE_ROWS`` rows (checked before and while
        reading: memory stays bounded).
    """
    from ..tablefile import read_table

    name = path.name
    try:
        exists, regular = path.exists(), path.is_file()
    except OSError as exc:
        raise SceneError(f"{where}: {quote(str(path))} cannot be read ({exc.__class__.__name__}); expected a UTF-8 CSV file") from None
    if not exists:
        raise SceneError(f"{where}: file {quote(str(path))} not found; expected a CSV file next to the scene")
    if not regular:
        raise SceneError(f"{where}: {quote(str(path))} is not a regular file; expected a CSV file")
    table = read_table(path, max_rows=MAX_PROFILE_ROWS, max_bytes=MAX_TRACE_BYTES, name=f"{where}: {name}",
                       columns=("time_s", column), error=SceneError, keep_text=True)
    if "time_s" not in table.columns or column not in table.columns:
        raise SceneError(f"{where}: {name} line {table.header_line}: header {quote(','.join(table.header))}; expected "
                         f"columns 'time_s' and {quote(column)}")
    lo_ok = (lambda v: v >= 0.0, "loads >= 0 N (compressive)") if column == "axial_load_n" else (
        lambda v: 0.0 < v <= SETPOINT_MAX_RPM, f"nut speeds in (0, {SETPOINT_MAX_RPM:g}] rpm")
    ts, vs = table.columns["time_s"], table.columns[column]
    t_typed, v_typed = table.typed["time_s"], table.typed[column]
    pts: list[tuple[float, float]] = []
    for k, j in enumerate(table.lines):
        t, v = float(ts[k]), float(vs[k])
        if not lo_ok[0](v):
            raise SceneError(f"{where}: {name} line {j}: {column} = {v_typed[k]}; expected {lo_ok[1]}")
        if not pts and t != 0.0:
            raise SceneError(f"{where}: {name} line {j}: time_s = {t_typed[k]}; expected the trace to start at 0")
        if pts and t <= pts[-1][0]:
            raise SceneError(f"{where}: {name} line {j}: time_s = {t_typed[k]} after {pts[-1][0]:g}; "
                             "expected strictly increasing times")
        pts.append((t, v * scale))
    if len(pts) < 2:
        raise SceneError(f"{where}: {name} has {len(pts)} data rows; expected at least 2")
    if lines_out is not None:
        lines_out.extend((int(j), v_typed[k]) for k, j in enumerate(table.lines))
    return tuple(pts)


def _trace_point(scene: "Scene", key: str, index: int) -> str | None:
    """``file line N: column = typed`` for point ``index`` of a profile read from CSV."""
    info = scene.trace_lines.get(key)
    prof = getattr(scene, key)
    if not info or prof is None or len(info[2]) != len(prof) or not 0 <= index < len(prof):
        return None
    line, typed = info[2][index]
    return f"{info[0]} line {line}: {info[1]} = {typed}"


def _from_doc(doc: Mapping[str, Any], origin: str, base: Any = None) -> Scene:
    unknown = sorted(set(doc) - set(_SECTIONS) - {"name", "description", "spec", "robust", "uncertainty", "filters"})
    if unknown:
        raise SceneError(f"{origin}: unknown section {quote(unknown[0])}; expected one of "
                         f"{', '.join([*_SECTIONS, 'spec', 'robust', 'uncertainty', 'filters'])}")
    kw: dict[str, Any] = {"origin": origin}
    if "filters" in doc:
        kw["filters"], kw["filter_labels"] = parse_filters(doc["filters"], origin)
    if "name" in doc:
        if not isinstance(doc["name"], str):
            raise SceneError(f"{origin}: name = {quote(doc['name'])}; expected a string")
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
                raise SceneError(f"{origin}: {section}.{key} = {quote(val)}; expected a {typ.__name__}")
            kw[key] = val
    mapping = {
        "setpoint_rpm": ("setpoint_rad_s", rpm_to_rad_s),
        "initial_load_n": ("initial_load", float),
        "final_loads_n": ("final_loads", lambda v: tuple(v)),
        "step_time_s": ("step_time", float),
        "duration_s": ("duration", float),
        "needed": ("outputs", lambda v: tuple(v)),
        "kind": ("estimator", str),
    }
    _duty_from_doc(kw, origin, base)
    rpm = kw.get("setpoint_rpm")
    if rpm is not None and not (math.isfinite(rpm) and 0 < rpm <= SETPOINT_MAX_RPM):
        raise SceneError(f"{origin}: operating.setpoint_rpm = {quote(rpm)}; expected a nut speed in (0, {SETPOINT_MAX_RPM:g}] rpm")
    for old, (new, conv) in mapping.items():
        if old in kw:
            kw[new] = conv(kw.pop(old))
    if {"spec", "robust", "uncertainty"} & set(doc):
        kw["sections"] = Sections.parse(doc, origin)
    return Scene(**kw)


def _duty_from_doc(kw: dict, origin: str, base: Any) -> None:
    """Turn the duty-cycle keys of ``[operating]`` into profile fields (in place)."""
    rpm_scale = RAD_S_PER_RPM
    sources = []
    for what, rows_key, csv_key, column, scale, field_name in (
            ("load", "load_profile_n", "load_trace_csv", "axial_load_n", 1.0, "load_profile"),
            ("setpoint", "setpoint_profile_rpm", "setpoint_trace_csv", "setpoint_rpm", rpm_scale, "setpoint_profile")):
        rows, csv_name = kw.pop(rows_key, None), kw.pop(csv_key, None)
        if rows is not None and csv_name is not None:
            raise SceneError(f"{origin}: operating.{rows_key} and operating.{csv_key} both given; expected one {what} profile")
        if rows is not None:
            kw[field_name] = profile_rows(rows, f"{origin}: operating.{rows_key}", scale)
            sources.append(f"{what}: {len(rows)} rows in the scene")
        elif csv_name is not None:
            where = f"{origin}: operating.{csv_key} = {quote(csv_name)}"
            if base is None or not csv_name.strip():
                raise SceneError(f"{where}: expected a CSV path relative to a scene file")
            path = Path(csv_name)
            path = path if path.is_absolute() else base / csv_name
            lines: list = []
            kw[field_name] = read_trace_csv(Path(str(path)), column, where, scale, lines)
            kw.setdefault("trace_lines", {})[field_name] = (csv_name, column, tuple(lines), os.path.realpath(str(path)))
            sources.append(f"{what}: {csv_name} ({len(kw[field_name])} rows)")
    if "load_profile" in kw:
        for key in ("initial_load_n", "final_loads_n", "step_time_s"):
            if key in kw:
                raise SceneError(f"{origin}: operating.{key} with a load profile; expected the load from the profile alone "
                                 "(its first row is the initial load, its changes are the events)")
    if "setpoint_profile" in kw and "setpoint_rpm" in kw:
        raise SceneError(f"{origin}: operating.setpoint_rpm with a setpoint profile; expected the setpoint from the profile "
                         "alone (its first row is the initial setpoint)")
    if "setpoint_profile" in kw and "load_profile" not in kw:
        for key in ("final_loads_n", "step_time_s"):
            if key in kw:
                raise SceneError(f"{origin}: operating.{key} with a setpoint profile; expected initial_load_n alone "
                                 "(the load is constant while the setpoint follows its profile)")
    if sources:
        kw["profile_source"] = "; ".join(sources)
    for key in ("setpoint_profile",):
        if key in kw:
            top = max(v for _, v in kw[key]) / rpm_scale
            if top > SETPOINT_MAX_RPM:
                raise SceneError(f"{origin}: operating.setpoint_profile_rpm reaches {top:.6g} rpm; expected at most "
                                 f"{SETPOINT_MAX_RPM:g} rpm")


def load_scene(name_or_path: str | Path | None = None) -> Scene | MoveScene:
    """Load a scene by built-in name (default ``"paper-load-step"``) or path: a speed-loop
    scene (:class:`Scene`), or a move scene (:class:`~prsa_ctrl.studies.move.MoveScene`) for a
    file with a ``[move]`` section (:func:`~prsa_ctrl.studies.scenefile.is_move_scene`).

    Raises
    ------
    SceneError
        For a missing, unreadable or invalid file (the message names the file and key).
    """
    reader, origin, base = locate_scene(name_or_path)
    doc = read_scene_doc(reader, origin)
    if "move" in doc:  # a position-cascade scene
        return parse_move_scene(doc, origin)
    return _from_doc(doc, origin, base)


def require_speed_scene(scene: Scene | MoveScene) -> Scene:
    """``scene`` if it is a speed-loop scene; a move scene is refused where a load step or duty
    cycle is needed (``prsa-plot``, the Monte-Carlo study).

    Raises
    ------
    SceneError
        One line naming the file.
    """
    if isinstance(scene, MoveScene):
        raise SceneError(f"{scene.origin}: a move scene ([move] section, position cascade); expected a speed-loop "
                         "scene here (prsa-tune --scene tunes move scenes)")
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


def holding_capacity_n(plant: Any, setpoint_rad_s: float) -> float:
    """Largest axial load, N, the motor can hold at a nut speed (rad/s) at constant speed:
    ``(T_max - T_0 - b w) 2 pi eta / L`` with the torque limit ``T_max``, the no-load torque
    ``T_0``, the viscous coefficient ``b``, the forward efficiency ``eta`` and the lead ``L``
    (the rigid operating point of :mod:`prsa_ctrl.plant.equilibrium`, solved for the load).

    Examples
    --------
    >>> from prsa_ctrl import load_plant
    >>> round(holding_capacity_n(load_plant(), rpm_to_rad_s(300)))
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
    slowest = min(v for _, v in (scene.setpoint_profile or ((0.0, scene.setpoint_rad_s),)))
    if quantum > slowest:
        raise SceneError(
            f"{plant.origin}: sensor.encoder_counts_per_rev = {plant.encoder_counts}: one count per controller sample is "
            f"{quantum:.4g} rad/s ({rad_s_to_rpm(quantum):.4g} rpm), more than the setpoint {rad_s_to_rpm(slowest):.6g} "
            f"rpm of {scene.origin}: the drive could not measure the speed it controls; expected a finer encoder "
            f"(at least {math.ceil(2 * math.pi / (slowest * ts))} counts per revolution at sensor.sample_time_s = {ts:g} s)")
    if scene.is_profile:
        _check_profile_against_plant(scene, plant, label, rpm_min)
        return
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


def _check_profile_against_plant(scene: Scene, plant: Any, label, rpm_min: float) -> None:
    """The duty-cycle half of :func:`check_against_plant`: every setpoint of the profile in the
    speed range, every load within what the motor holds at the slowest setpoint of the
    profile, at least ``PRE_EVENT_SAMPLES`` samples of steady running before the first change
    and ``POST_EVENT_SAMPLES`` after the last one, breakpoints at least one controller sample
    apart (the sampled run splits a sample at one load change at most), the record within
    ``MAX_RECORD_SAMPLES``."""
    ts = plant.sample_time_s
    o = scene.origin
    sp = scene.setpoint_profile or ((0.0, scene.setpoint_rad_s),)
    rpms = [rad_s_to_rpm(v) for _, v in sp]
    lo_rpm, hi_rpm = min(rpms), max(rpms)
    if scene.setpoint_profile is not None and not rpm_min <= lo_rpm <= hi_rpm <= SETPOINT_MAX_RPM:
        bad_i = next(i for i, r in enumerate(rpms) if not rpm_min <= r <= SETPOINT_MAX_RPM)
        at = _trace_point(scene, "setpoint_profile", bad_i)
        if at:
            raise SceneError(
                f"{o}: operating.setpoint_trace_csv: {at}; expected nut speeds in [{rpm_min:.3g}, {SETPOINT_MAX_RPM:g}] "
                f"rpm for {plant.name} (below, the friction is on the steep part of its Stribeck curve, where the "
                "linear model does not hold)")
        raise SceneError(
            f"{o}: operating.setpoint_profile_rpm spans {lo_rpm:.6g} to {hi_rpm:.6g} rpm; expected nut speeds in "
            f"[{rpm_min:.3g}, {SETPOINT_MAX_RPM:g}] rpm for {plant.name} (below, the friction is on the steep part of "
            "its Stribeck curve, where the linear model does not hold)")
    slowest = min(v for _, v in sp)
    cap = holding_capacity_n(plant, slowest)
    loads = [v for _, v in scene.load_profile] if scene.load_profile is not None else [scene.initial_load]
    key = "operating.load_profile_n" if scene.load_profile is not None else "operating.initial_load_n"
    if max(loads) > cap:
        at = _trace_point(scene, "load_profile", loads.index(max(loads)))
        if at:
            raise SceneError(
                f"{o}: operating.load_trace_csv: {at}; out of range for {plant.name}: at {rad_s_to_rpm(slowest):.6g} "
                f"rpm the motor holds at most {cap:.0f} N (drive.torque_limit_n_m = {plant.torque_limit:g} N m)")
        raise SceneError(
            f"{o}: {key} reaches {max(loads):g} N; out of range for {plant.name}: at {rad_s_to_rpm(slowest):.6g} rpm the "
            f"motor holds at most {cap:.0f} N (drive.torque_limit_n_m = {plant.torque_limit:g} N m)")
    before, after = PRE_EVENT_SAMPLES * ts, POST_EVENT_SAMPLES * ts
    if scene.step_time < before * (1 - 1e-9):
        first = [(k, p) for k, p in (("load_profile", scene.load_profile), ("setpoint_profile", scene.setpoint_profile))
                 if p is not None and _first_change(p) is not None and _first_change(p) < before * (1 - 1e-9)]
        key, prof = first[0]
        i = next(i for i in range(1, len(prof)) if prof[i][1] != prof[0][1])
        info = scene.trace_lines.get(key)
        if info and len(info[2]) == len(prof):
            fix = (f"start the trace {info[0]} with a steady lead-in: hold the first value ({info[1]} = "
                   f"{info[2][0][1]}) for at least {before:g} s, e.g. add a row at time_s = {before:g} with the first "
                   f"value and shift the later rows by {before:g} s (line {info[2][i][0]} is the first change)")
        else:
            fix = (f"add a row [{before:g}, first value] before the first change and shift the later rows by "
                   f"{before:g} s")
        raise SceneError(
            f"{o}: the {key.replace('_', ' ')} first changes at {scene.step_time:g} s; the run starts in steady state at "
            f"the first value and needs at least {PRE_EVENT_SAMPLES} controller samples of it ({before:g} s at "
            f"sensor.sample_time_s = {ts:g} s) before the first change: {fix}")
    end = scene.profile_end()
    if scene.duration - end < after * (1 - 1e-9):
        raise SceneError(
            f"{label('duration', f'{scene.duration:g}')}: the profile's last point is at {end:g} s; the response to it "
            f"needs {POST_EVENT_SAMPLES} controller samples ({after:g} s); expected duration >= {end + after:g} s")
    for name, prof in (("load_profile_n", scene.load_profile), ("setpoint_profile_rpm", scene.setpoint_profile)):
        if prof is None:
            continue
        times = sorted({t for t, _ in prof})
        gaps = [b - a for a, b in zip(times, times[1:])]
        if gaps and min(gaps) < ts * (1 - 1e-9):
            i = gaps.index(min(gaps))
            raise SceneError(
                f"{o}: operating.{name.replace('_n', '').replace('_rpm', '')} points at {times[i]:g} s and {times[i + 1]:g} s "
                f"are {min(gaps):.3g} s apart; expected at least one controller sample ({ts:g} s): resample the trace")
    n = scene.duration / ts
    if n > MAX_RECORD_SAMPLES:
        raise SceneError(
            f"{label('duration', f'{scene.duration:g}')}: the record would hold {n:.3g} controller samples; the limit "
            f"is {MAX_RECORD_SAMPLES} samples, a duration of at most {MAX_RECORD_SAMPLES * ts:g} s")
