"""Duty-cycle scenes: :class:`DutyCycleScene`, a speed-loop scene whose load and/or setpoint
follow a profile over the record, with its validation, its check against a plant and the readers
of its profiles (rows written in the scene, CSV traces).


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
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, ClassVar, Mapping

from ..errors import SceneError
from ..options import RAD_S_PER_RPM, rad_s_to_rpm
from ..textsafe import quote
from .scenebase import Scene, holding_capacity_n
from .scenefile import MAX_RECORD_SAMPLES, POST_EVENT_SAMPLES, PRE_EVENT_SAMPLES, SETPOINT_MAX_RPM

__all__ = ["DutyCycleScene", "GOALS", "MAX_PROFILE_ROWS", "MAX_TRACE_BYTES", "profile_rows", "read_trace_csv",
           "duty_fields", "PROFILE_KEYS", "PROFILE_SOURCES", "refuse_other_kind_keys"]

#: What a duty-cycle scene tunes for (see the module docstring).
GOALS = ("load", "setpoint", "mix")
#: Most rows of a profile or a CSV trace (one per controller sample at most: 40 000 samples).
MAX_PROFILE_ROWS = 40_000
#: Largest CSV trace file, bytes (40 000 rows of up to ~400 characters; a larger file is refused
#: before it is read).
MAX_TRACE_BYTES = 16 * 1024 * 1024
#: The ``[tuning]`` keys only a duty cycle reads: a load-step scene file that sets one is refused
#: (:func:`refuse_other_kind_keys`; before the split a load step echoed them in its report and
#: used none of them).
PROFILE_KEYS = ("goal", "setpoint_weight", "setpoint_share")
#: The ``[operating]`` keys that make a scene file a duty cycle (a load or setpoint profile).
PROFILE_SOURCES = ("load_profile_n", "load_trace_csv", "setpoint_profile_rpm", "setpoint_trace_csv")
#: What a duty-cycle file may not set, ``(where, key, why)``: load-step keys and sections (a
#: load profile also sets the initial load; a setpoint profile alone keeps ``initial_load_n``,
#: the constant load it runs at).
_STEP_ONLY = (("operating", "final_loads_n", "the loads come from the load profile (a setpoint profile alone runs at "
               "the constant initial_load_n)"),
              ("operating", "step_time_s", "the events are the profiles' changes"),
              ("operating", "initial_load_n", "the load profile's first row is the initial load"),
              (None, "spec", "the robust and Monte-Carlo studies run load steps"),
              (None, "robust", "the robust and Monte-Carlo studies run load steps"),
              (None, "uncertainty", "the robust and Monte-Carlo studies run load steps"))


def refuse_other_kind_keys(doc: Mapping[str, Any], origin: str) -> None:
    """Refuse a scene file key that the file's kind does not take, rather than drop it: the duty
    cycle's ``[tuning]`` keys (:data:`PROFILE_KEYS`) in a load-step file, the load-step keys and
    the ``[spec]``/``[robust]``/``[uncertainty]`` sections in a duty-cycle file (``[operating]
    initial_load_n`` only with a load profile).

    Raises
    ------
    SceneError
        One line naming the key as written in the file, the kind that takes it and this file's kind.
    """
    op = doc.get("operating", {})
    op = op if isinstance(op, Mapping) else {}
    tuning = doc.get("tuning", {})
    tuning = tuning if isinstance(tuning, Mapping) else {}
    given = [k for k in PROFILE_SOURCES if k in op]
    if not given:
        for key in PROFILE_KEYS:
            if key in tuning:
                raise SceneError(
                    f"{origin}: tuning.{key} = {quote(tuning[key])}: a duty-cycle key (taken by a scene with a load or "
                    f"setpoint profile: operating.{', operating.'.join(PROFILE_SOURCES)}); this scene is a load step "
                    f"(no load or setpoint profile); expected no tuning.{key} here")
        return
    kind = f"this scene is a duty cycle (operating.{', operating.'.join(given)})"
    has_load = "load_profile_n" in op or "load_trace_csv" in op
    for section, key, why in _STEP_ONLY:
        if section is None and key in doc:
            raise SceneError(f"{origin}: [{key}]: a load-step section ({why}); {kind}; expected no [{key}] here")
        if section is not None and key in op and (key != "initial_load_n" or has_load):
            raise SceneError(f"{origin}: {section}.{key} = {quote(op[key])}: a load-step key; {kind}: {why}; "
                             f"expected no {section}.{key} here")


@dataclass(frozen=True)
class DutyCycleScene(Scene):
    """A duty cycle: the load and/or the setpoint follow a profile over the record (see the
    module docstring); the shared fields are :class:`~prsa_ctrl.studies.scenebase.Scene`'s.

    ``initial_load`` is the load profile's t = 0 value, ``setpoint_rad_s`` the setpoint
    profile's, ``final_loads`` is empty and ``step_time`` is the time of the profiles' first
    change (all set from the profiles).

    Parameters
    ----------
    load_profile : tuple of (time s, N), optional
        Duty-cycle load, piecewise linear in :class:`prsa_ctrl.sim.engine.PiecewiseLinear`'s
        convention (two points at one time make a step).
    setpoint_profile : tuple of (time s, rad/s), optional
        Duty-cycle setpoint, the same way (at least one of the two profiles).
    goal : {"auto", "load", "setpoint", "mix"}
        What the tuner optimises (``"auto"``: from the profiles given).
    setpoint_weight : float
        2-DOF setpoint weight b in [0, 1] on the proportional path.
    setpoint_share : float
        Weight of the setpoint-tracking objective in ``goal = "mix"``, in (0, 1).
    profile_source : str
        Where the profiles came from (reported).
    trace_lines : mapping
        Where each point of a CSV trace came from: ``{"load_profile": (file, column, ((line,
        typed value), ...), resolved path)}`` (messages name the line; empty for profiles
        written in the scene).
    """

    load_profile: tuple[tuple[float, float], ...] | None = None
    setpoint_profile: tuple[tuple[float, float], ...] | None = None
    goal: str = "auto"
    setpoint_weight: float = 1.0
    setpoint_share: float = 0.5
    profile_source: str = ""
    trace_lines: Mapping[str, Any] = field(default_factory=dict, compare=False, hash=False, repr=False)

    #: The registry name of the kind (:data:`prsa_ctrl.studies.scenekinds.KINDS`) and what marks its files.
    kind_name: ClassVar[str] = "duty-cycle"
    marks: ClassVar[str] = f"a load or setpoint profile in [operating] ({', '.join(PROFILE_SOURCES)})"

    @classmethod
    def describes(cls, given: Mapping[str, Any]) -> bool:
        """A load or a setpoint profile given."""
        return given.get("load_profile") is not None or given.get("setpoint_profile") is not None

    @classmethod
    def claims(cls, doc: Mapping[str, Any]) -> bool:
        """A file with a profile key in ``[operating]`` (:data:`PROFILE_SOURCES`)."""
        op = doc.get("operating")
        return isinstance(op, Mapping) and any(k in op for k in PROFILE_SOURCES)

    @classmethod
    def refuse_foreign(cls, doc: Mapping[str, Any], origin: str) -> None:
        """A load-step key or section is refused by name (:func:`refuse_other_kind_keys`)."""
        refuse_other_kind_keys(doc, origin)

    @classmethod
    def own_fields(cls, kw: dict, origin: str, base: Any) -> None:
        """The profiles and CSV traces of ``[operating]`` as profile fields (:func:`duty_fields`)."""
        duty_fields(kw, origin, base)

    def check_kind(self, bad, finite) -> None:
        """Validate the profiles and the duty cycle's tuning keys; derive ``initial_load``,
        ``setpoint_rad_s``, ``final_loads`` (empty) and ``step_time`` from the profiles."""
        if self.load_profile is None and self.setpoint_profile is None:
            raise bad("load_profile", None, "a load or a setpoint profile (a duty cycle)")
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

    def check_events(self, bad, finite) -> None:
        """The record ends after the profiles' last point."""
        if finite("duration", self.duration) <= self.profile_end():
            raise bad("duration", self.duration, f"a time beyond the profile's last point at {self.profile_end():g} s")

    def check_plant(self, plant: Any, label: Callable[[str, Any], str], rpm_min: float,
                    typed: Mapping[str, str]) -> None:
        """Every setpoint of the profile in the speed range, every load held, the events far
        enough from the ends and each other (:func:`check_profile_against_plant`)."""
        check_profile_against_plant(self, plant, label, rpm_min)

    @property
    def cases(self) -> list[str]:
        """The duty cycle's load and/or setpoint records (``goal``)."""
        return {"load": ["load profile"], "setpoint": ["setpoint profile"],
                "mix": ["load profile", "setpoint profile"]}[self.goal]

    def profile_dict(self) -> dict[str, Any]:
        return {"load_profile": None if self.load_profile is None else [list(p) for p in self.load_profile],
                "setpoint_profile": None if self.setpoint_profile is None else [list(p) for p in self.setpoint_profile],
                "goal": self.goal, "setpoint_weight": self.setpoint_weight, "setpoint_share": self.setpoint_share,
                "profile_source": self.profile_source}

    @property
    def setpoint_points(self) -> tuple[tuple[float, float], ...]:
        return self.setpoint_profile or ((0.0, self.setpoint_rad_s),)

    @property
    def design_setpoint_weight(self) -> float:
        """``setpoint_weight`` with a setpoint profile, else 1 (b acts on setpoint changes only)."""
        return float(self.setpoint_weight) if self.setpoint_profile is not None else 1.0

    def profile_end(self) -> float:
        """Time of the last breakpoint of the duty cycle, s."""
        return max((p[-1][0] for p in (self.load_profile, self.setpoint_profile) if p is not None), default=0.0)

    @property
    def input_files(self) -> tuple[str, ...]:
        return tuple(info[3] for info in self.trace_lines.values() if len(info) > 3)


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


def _trace_point(scene: "DutyCycleScene", key: str, index: int) -> str | None:
    """``file line N: column = typed`` for point ``index`` of a profile read from CSV."""
    info = scene.trace_lines.get(key)
    prof = getattr(scene, key)
    if not info or prof is None or len(info[2]) != len(prof) or not 0 <= index < len(prof):
        return None
    line, typed = info[2][index]
    return f"{info[0]} line {line}: {info[1]} = {typed}"



def duty_fields(kw: dict, origin: str, base: Any) -> None:
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



def check_profile_against_plant(scene: DutyCycleScene, plant: Any, label, rpm_min: float) -> None:
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
