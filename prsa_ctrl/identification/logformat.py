"""Log descriptions (``prsa-fit --log-format FILE``): logs as drives and test benches write them.

A log description is a small TOML file that says which column (CSV) or variable (MATLAB
``.mat``, read with :func:`scipy.io.loadmat`) holds which signal, in which unit, with which
gain, and which controller was running while the log was written. Example (the EMPS benchmark,
``examples/emps/log.toml``)::

    format = "mat"                  # "mat" or "csv"; default: from the data file's extension
    axis = "linear"                 # load coordinates: position in m, force in N

    [time]
    name = "t"
    unit = "s"                      # s | ms

    [position]                      # measured load position
    name = "qm"
    unit = "m"                      # m | mm | um
    resolution = 5e-8               # optional: encoder quantum, in the same unit

    [reference]                     # position reference given to the controller (optional)
    name = "qg"
    unit = "m"

    [command]                       # controller output as logged
    name = "vir"
    unit = "V"                      # V | A | N (N needs no gain)
    gain = "gtau"                   # N per command unit: a number or a variable of the .mat file
    logged = "as-computed"          # as-computed (default) | as-applied

    [test_signal]                   # additive signal at the drive input (optional)
    name = "pulses_N"
    unit = "V"                      # same unit as the command
    optional = true                 # the column may be absent (then: zero)

    [controller]                    # what ran while logging (optional; without it: open loop)
    structure = "position-p/velocity-p"    # or "position-p/velocity-pi" (with ki)
    kp = "kp"                       # position gain, 1/s
    kv = "kv"                       # velocity gain, command unit per m/s
    velocity_estimate = "average2-difference"   # or "difference"
    saturation = 10.0               # symmetric limit of the controller output, command unit
    sample_time_s = 0.001
    command_delay_samples = 0       # samples between computing a command and applying it
    check_tolerance = 0.03          # largest ||reconstructed - logged|| / ||logged|| of the command

Optional sections ``[speed]`` (measured speed: ``unit`` m/s | mm/s) and ``[load]`` (external
force on the load: ``unit`` N | kN) follow the same pattern.

Coordinates. ``axis = "linear"`` (the default) is a log in load coordinates: position in m (or
mm, um), the command as a force on the load in N (or a unit with a gain in N per unit).
``axis = "rotary"`` is a log in motor coordinates: ``[position]`` the motor (screw) angle in
rad | deg | rev, ``[speed]`` in rad/s | rpm, ``[command]`` the torque command in ``N m`` (or
A | V | % of the rated torque with ``gain`` in N m per unit: rated torque / 100 for %), ``[load]`` the axial load on the nut in N | kN; such a log
has no ``[controller]``, ``[reference]`` or ``[test_signal]`` (the motor-coordinate fit,
:func:`prsa_ctrl.identification.timedomain.fit_plant`, runs open loop from the logged torque
over short multiple-shooting segments). A screw-driven plant works in motor coordinates: a log
in load coordinates is converted for it by :func:`motor_record` with the plant's lead ``a``
(m of travel per rad of the screw): angle = position / a, speed = speed / a, torque command =
force command x a (the force an ideal, lossless screw makes of the torque: the screw's losses
are the plant's friction, not part of the coordinates), axial load unchanged.

The controller, when described, is checked against the log before anything else: the command
it computes from the logged position and reference (plus the test signal) must reproduce the
logged command within ``check_tolerance`` (relative 2-norm error), and better than with the
command shifted by 1 or 2 samples (:data:`ALIGNMENT_RATIO`). This is also how units that disagree with the data
are caught (a position in mm declared as m scales the reconstructed command by 1000): the
message then names the units that would reproduce it. The other velocity estimate
(:data:`VELOCITY_ESTIMATES`) must not fit clearly better either. Without a controller, a position
that moves faster than :data:`MAX_SPEED_M_S` between two samples is refused (a unit or sample
time that disagrees with the data).

The controller law (``k`` = sample, ``dt`` = ``sample_time_s``)::

    qf(k) = (q(k) + q(k-1)) / 2                      # velocity_estimate = "average2-difference"
    dq(k) = (qf(k) - qf(k-1)) / dt                   #   ("difference": dq(k) = (q(k) - q(k-1)) / dt)
    u(k)  = kv * (kp * (r(k) - q(k)) - dq(k)) [+ ki * kv * dt * sum of kp*(r - q) - dq]   # PI: ki
    command(k) = clip(u(k), -saturation, saturation) + test_signal(k)
    force acting on the load from sample k + command_delay_samples on: gain * command(k)

Every problem is a :class:`LogFormatError` (a ``ValueError``) with one line naming the file and
the key, column or variable.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from numpy.typing import NDArray

from ..options import RAD_S_PER_RPM, check_number
from ..tomlfile import read_toml
from ..errors import LogFormatError
from .data import MAX_SAMPLES, MIN_SAMPLES, Record, record_from_arrays
from .logfile import LogFile

__all__ = ["LogFormatError", "LogFormat", "DEFAULT_CSV_FORMAT", "ControllerSpec", "AxisLog", "load_log_format", "load_axis_log",
           "reconstruct_command", "STRUCTURES", "VELOCITY_ESTIMATES", "MAX_SPEED_M_S", "AXES", "motor_record",
           "load_motor_record", "MOTOR_CONVENTION"]

#: Controller structures understood.
STRUCTURES = ("position-p/velocity-p", "position-p/velocity-pi")
#: Velocity estimates of the controller.
VELOCITY_ESTIMATES = ("average2-difference", "difference")
#: Largest relative deviation of a sample interval from the declared sample time.
SAMPLING_TOL = 0.01
#: Largest plausible speed of a linear axis, m/s (linear motors reach ~10 m/s): a log whose
#: position moves faster between two samples has a position unit (or sample time) that
#: disagrees with its data (mm declared as m).
MAX_SPEED_M_S = 50.0
#: A log is refused when the command reconstructed with a shift of 1 or 2 samples matches it
#: with less than this fraction of the described alignment's error (the description is off).
ALIGNMENT_RATIO = 0.5

_POSITION_UNITS = {"m": 1.0, "mm": 1e-3, "um": 1e-6}
_SPEED_UNITS = {"m/s": 1.0, "mm/s": 1e-3}
_TIME_UNITS = {"s": 1.0, "ms": 1e-3}
_FORCE_UNITS = {"N": 1.0, "kN": 1e3}
_COMMAND_UNITS = ("V", "A", "N")
#: Coordinates a log may be in: ``linear`` (load: m, N) and ``rotary`` (motor: rad, N m).
AXES = ("linear", "rotary")
#: ``[command] logged`` -> the motor-coordinate fit's ``command_logged``.
MOTOR_CONVENTION = {"as-computed": "computed", "as-applied": "applied"}
_ANGLE_UNITS = {"rad": 1.0, "deg": math.pi / 180.0, "rev": 2.0 * math.pi}
_ANGULAR_SPEED_UNITS = {"rad/s": 1.0, "rpm": RAD_S_PER_RPM}
#: ``%`` is percent of the rated torque (drive recorders log it so): ``gain`` is N m per %, rated/100.
_TORQUE_COMMAND_UNITS = ("N m", "A", "V", "%")
#: Sections a log in motor coordinates may have (section -> (required, allowed units)).
_ROTARY_SIGNALS = {"time": (True, _TIME_UNITS), "position": (True, _ANGLE_UNITS),
                   "command": (True, _TORQUE_COMMAND_UNITS), "speed": (False, _ANGULAR_SPEED_UNITS),
                   "load": (False, _FORCE_UNITS)}
_SIGNALS = {  # section -> (required, allowed units)
    "time": (True, _TIME_UNITS),
    "position": (True, _POSITION_UNITS),
    "reference": (False, _POSITION_UNITS),
    "command": (True, None),
    "test_signal": (False, None),
    "speed": (False, _SPEED_UNITS),
    "load": (False, _FORCE_UNITS),
}
_TOP_KEYS = {"format", "axis", "description", *_SIGNALS, "controller"}
_SIGNAL_KEYS = {"name", "unit", "resolution", "gain", "logged", "optional"}
_CONTROLLER_KEYS = {"structure", "kp", "kv", "ki", "velocity_estimate", "saturation", "sample_time_s",
                    "command_delay_samples", "check_tolerance"}


@dataclass(frozen=True)
class ControllerSpec:
    """The controller that ran while logging (gains resolved to numbers, SI position units).

    Attributes
    ----------
    structure : str
        One of :data:`STRUCTURES`.
    kp : float
        Position-loop gain, 1/s.
    kv : float
        Velocity-loop gain, command unit per m/s.
    ki : float
        Velocity-loop integral gain, 1/s (0 for a P velocity loop).
    velocity_estimate : str
        One of :data:`VELOCITY_ESTIMATES`.
    saturation : float
        Symmetric limit of the controller output, command unit.
    sample_time_s : float
        Controller sample time, s.
    command_delay_samples : int
        Samples between computing a command and applying it at the drive.
    check_tolerance : float
        Largest relative error of the reconstructed command accepted.
    sources : dict
        Where each value came from (``"log.toml"`` or ``"DATA.mat: kp"``).
    """

    structure: str
    kp: float
    kv: float
    ki: float
    velocity_estimate: str
    saturation: float
    sample_time_s: float
    command_delay_samples: int = 0
    check_tolerance: float = 0.03
    sources: Mapping[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class LogFormat:
    """A parsed log description (:func:`load_log_format`); gains may still be variable names."""

    path: str
    doc: Mapping[str, Any]

    def section(self, name: str) -> Mapping[str, Any] | None:
        return self.doc.get(name)


@dataclass(frozen=True)
class AxisLog:
    """A linear-axis log in SI load coordinates (m, N, s).

    Attributes
    ----------
    name : str
        The log file as given.
    time_s, position_m : ndarray
        Sample times, s (from 0) and measured load position, m.
    command : ndarray
        Controller output as logged, command unit (includes the test signal when there is one).
    command_unit : str
        ``V``, ``A`` or ``N``.
    gain_n_per_unit : float
        Drive gain, N per command unit (force on the load = gain * command).
    reference_m, test_signal, speed_m_s, load_n : ndarray or None
        Position reference, m; additive test signal at the drive input, command unit; measured
        speed, m/s; external force on the load, N.
    controller : ControllerSpec or None
        The controller that ran (None: replays run open loop from the logged command).
    resolution_m : float or None
        Encoder quantum, m (None: not given).
    sample_time_s : float
        Sample time, s.
    command_logged : str
        ``as-computed`` or ``as-applied``.
    sources : dict
        Where the gain and the controller values came from.
    """

    name: str
    time_s: NDArray[np.float64]
    position_m: NDArray[np.float64]
    command: NDArray[np.float64]
    command_unit: str
    gain_n_per_unit: float
    sample_time_s: float
    reference_m: NDArray[np.float64] | None = None
    test_signal: NDArray[np.float64] | None = None
    speed_m_s: NDArray[np.float64] | None = None
    load_n: NDArray[np.float64] | None = None
    controller: ControllerSpec | None = None
    resolution_m: float | None = None
    command_logged: str = "as-computed"
    sources: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        """The arrays checked: one-dimensional, one length (at least 2 samples), finite; the gain
        and sample time finite and > 0. A :class:`ValueError` names the log and the field."""
        n = None
        for k in ("time_s", "position_m", "command", "reference_m", "test_signal", "speed_m_s", "load_n"):
            a = getattr(self, k)
            if a is None and k not in ("time_s", "position_m", "command"):
                continue
            shape = np.shape(a)
            if len(shape) != 1 or (n is not None and shape[0] != n):
                raise ValueError(f"AxisLog {self.name!r}: {k} has shape {shape}; expected "
                                 + ("a one-dimensional array of at least 2 samples" if n is None else f"({n},) like time_s"))
            n = shape[0] if n is None else n
            if n < 2:
                raise ValueError(f"AxisLog {self.name!r}: {k} has {n} sample(s); expected at least 2")
            bad = np.flatnonzero(~np.isfinite(np.asarray(a, dtype=float)))
            if bad.size:
                raise ValueError(f"AxisLog {self.name!r}: {k}[{bad[0]}] = {float(np.asarray(a)[bad[0]])!r}; expected finite values")
        for k in ("gain_n_per_unit", "sample_time_s"):
            check_number(f"AxisLog {self.name!r}: {k}", getattr(self, k), 0.0, lo_open=True)

    @property
    def n(self) -> int:
        """Number of samples."""
        return int(self.time_s.size)

    @property
    def force_n(self) -> NDArray[np.float64]:
        """Logged command as a force on the load, N."""
        return self.gain_n_per_unit * self.command

    def window(self, start: int, stop: int) -> "AxisLog":
        """The samples ``start:stop`` as a log of their own (time restarts at 0)."""
        if not 0 <= start < stop <= self.n or stop - start < MIN_SAMPLES:
            raise ValueError(f"window {start}:{stop} of {self.n} samples; expected at least {MIN_SAMPLES} samples inside")
        cut = {k: (None if getattr(self, k) is None else getattr(self, k)[start:stop])
               for k in ("position_m", "command", "reference_m", "test_signal", "speed_m_s", "load_n")}
        t = self.time_s[start:stop] - self.time_s[start]
        return AxisLog(name=f"{self.name}[{start}:{stop}]", time_s=t, command_unit=self.command_unit,
                       gain_n_per_unit=self.gain_n_per_unit, sample_time_s=self.sample_time_s,
                       controller=self.controller, resolution_m=self.resolution_m,
                       command_logged=self.command_logged, sources=self.sources, **cut)


#: The description of a CSV log with the standard linear-axis columns (no controller: replays run
#: open loop from the logged force): ``time_s``, ``position_m``, ``force_n`` and, optionally,
#: ``reference_m``, ``speed_m_s``, ``load_n``.
DEFAULT_CSV_FORMAT = LogFormat(
    path="standard CSV columns (time_s, position_m, force_n[, reference_m, speed_m_s, load_n])",
    doc={"format": "csv", "axis": "linear", "time": {"name": "time_s", "unit": "s"},
         "position": {"name": "position_m", "unit": "m"}, "command": {"name": "force_n", "unit": "N"},
         "reference": {"name": "reference_m", "unit": "m", "optional": True},
         "speed": {"name": "speed_m_s", "unit": "m/s", "optional": True},
         "load": {"name": "load_n", "unit": "N", "optional": True}})


# --- the description ---------------------------------------------------------------------------


def _err(path: str, where: str, text: str) -> LogFormatError:
    return LogFormatError(f"{path}: {where}: {text}")


def load_log_format(path: str | Path) -> LogFormat:
    """Read and check a log description (keys, units, structure), before any data is read.

    Parameters
    ----------
    path : str or Path
        The TOML file.

    Returns
    -------
    LogFormat

    Raises
    ------
    LogFormatError
        One line naming the file and the key.
    """
    name = str(path)
    p = Path(path)
    if not p.is_file():
        raise LogFormatError(f"--log-format {name!r}: file not found; expected a readable TOML log description")
    try:
        text = p.read_text(encoding="utf-8-sig")  # a byte-order mark, as plant and data files
    except (OSError, UnicodeDecodeError) as exc:
        raise LogFormatError(f"{name}: cannot be read ({exc}); expected a UTF-8 TOML file") from None
    doc = read_toml(text, name, LogFormatError)
    for k in doc:
        if k not in _TOP_KEYS:
            raise _err(name, f"key {k!r}", f"unknown; expected some of {', '.join(sorted(_TOP_KEYS))}")
    fmt = doc.get("format")
    if fmt is not None and fmt not in ("mat", "csv"):
        raise _err(name, f"format = {fmt!r}", "expected \"mat\" or \"csv\"")
    axis = doc.get("axis", "linear")
    if axis not in AXES:
        raise _err(name, f"axis = {axis!r}", "expected \"linear\" (load coordinates m, N) or \"rotary\" (motor "
                   "coordinates rad, N m)")
    signals = _SIGNALS if axis == "linear" else _ROTARY_SIGNALS
    if axis == "rotary":
        extra = [k for k in ("controller", "reference", "test_signal") if k in doc]
        if extra:
            raise _err(name, f"[{extra[0]}] with axis = \"rotary\"", "expected none: a log in motor coordinates is "
                       "fitted open loop from its logged torque command (describe the controller of a linear axis "
                       "log, axis = \"linear\")")
    for sec, (required, units) in signals.items():
        s = doc.get(sec)
        if s is None:
            if required:
                raise _err(name, f"[{sec}]", "missing; expected a section with name and unit")
            continue
        if not isinstance(s, dict):
            raise _err(name, f"{sec}", "expected a [section] with name and unit")
        for k in s:
            if k not in _SIGNAL_KEYS:
                raise _err(name, f"[{sec}] {k}", f"unknown key; expected some of {', '.join(sorted(_SIGNAL_KEYS))}")
        if not isinstance(s.get("name"), str) or not s["name"].strip():
            raise _err(name, f"[{sec}] name", "missing; expected the column or variable name as a string")
        if "optional" in s:
            opt = s["optional"]
            if not isinstance(opt, bool):
                raise _err(name, f"[{sec}] optional = {opt!r}", "expected true or false (a TOML boolean, no quotes)")
            if opt and required:
                raise _err(name, f"[{sec}] optional = true", f"[{sec}] is required; expected no optional key (or false)")
        unit = s.get("unit")
        allowed = units if units is not None else _COMMAND_UNITS
        if unit not in allowed:
            raise _err(name, f"[{sec}] unit = {unit!r}", f"expected one of {', '.join(allowed)}"
                       + (" (axis = \"rotary\": motor coordinates)" if axis == "rotary" else ""))
    cmd = doc["command"]
    own = "N" if axis == "linear" else "N m"
    if cmd["unit"] != own and "gain" not in cmd:
        raise _err(name, f"[command] unit = {cmd['unit']!r}", f"needs gain ({own} per command unit: a number or a "
                   "variable name)")
    if cmd.get("logged", "as-computed") not in ("as-computed", "as-applied"):
        raise _err(name, f"[command] logged = {cmd['logged']!r}", "expected \"as-computed\" or \"as-applied\"")
    ts = doc.get("test_signal")
    if ts is not None and ts["unit"] != cmd["unit"]:
        raise _err(name, f"[test_signal] unit = {ts['unit']!r}", f"expected the command's unit {cmd['unit']!r} (it "
                   "is added to the controller output)")
    res = doc["position"].get("resolution")
    if res is not None:  # an absent key: no resolution given
        check_number(f"{name}: [position] resolution", res, 0.0, lo_open=True, unit="(position unit)", error=LogFormatError)
    ctl = doc.get("controller")
    if ctl is not None:
        _check_controller(name, ctl, has_reference="reference" in doc)
    return LogFormat(path=name, doc=doc)


def _check_controller(name: str, ctl: Any, has_reference: bool) -> None:
    if not isinstance(ctl, dict):
        raise _err(name, "controller", "expected a [controller] section")
    for k in ctl:
        if k not in _CONTROLLER_KEYS:
            raise _err(name, f"[controller] {k}", f"unknown key; expected some of {', '.join(sorted(_CONTROLLER_KEYS))}")
    st = ctl.get("structure")
    if st not in STRUCTURES:
        raise _err(name, f"[controller] structure = {st!r}", f"expected one of {', '.join(STRUCTURES)}")
    if not has_reference:
        raise _err(name, "[controller]", "needs a [reference] section (the position reference the controller followed)")
    need = ["kp", "kv", "saturation", "sample_time_s"] + (["ki"] if st.endswith("pi") else [])
    for k in need:
        if k not in ctl:
            raise _err(name, f"[controller] {k}", "missing; expected the key (a number"
                       + (" or a variable name)" if k in ("kp", "kv", "ki") else ")"))
    if "ki" in ctl and not st.endswith("pi"):
        raise _err(name, "[controller] ki", f"given for structure {st!r}; expected position-p/velocity-pi")
    for k in ("saturation", "sample_time_s"):
        check_number(f"{name}: [controller] {k}", ctl[k], 0.0, lo_open=True, error=LogFormatError)
    ve = ctl.get("velocity_estimate", "average2-difference")
    if ve not in VELOCITY_ESTIMATES:
        raise _err(name, f"[controller] velocity_estimate = {ve!r}", f"expected one of {', '.join(VELOCITY_ESTIMATES)}")
    check_number(f"{name}: [controller] command_delay_samples", ctl.get("command_delay_samples", 0), 0, 10,
                 integer=True, error=LogFormatError)
    check_number(f"{name}: [controller] check_tolerance", ctl.get("check_tolerance", 0.03), 0.0, 1.0, lo_open=True,
                 hi_open=True, error=LogFormatError)


# --- the data ----------------------------------------------------------------------------------


def _wanted(doc: Mapping[str, Any]) -> dict[str, str]:
    """The columns or variables a log description names, each with the key that names it (the
    only ones read)."""
    out: dict[str, str] = {}
    for sec in (*_SIGNALS, *_ROTARY_SIGNALS):
        s = doc.get(sec)
        if isinstance(s, dict) and isinstance(s.get("name"), str):
            out.setdefault(s["name"], f"[{sec}] name")
    cmd = doc.get("command") or {}
    if isinstance(cmd.get("gain"), str):
        out.setdefault(cmd["gain"], "[command] gain")
    for k in ("kp", "kv", "ki"):
        v = (doc.get("controller") or {}).get(k)
        if isinstance(v, str):
            out.setdefault(v, f"[controller] {k}")
    return out


def load_axis_log(path: str | Path, fmt: LogFormat) -> AxisLog:
    """Read a log as its description says, convert it to SI and check it against the controller.

    Parameters
    ----------
    path : str or Path
        The data file (CSV with a header row, or MATLAB v5/v7 ``.mat``).
    fmt : LogFormat
        The description (:func:`load_log_format`).

    Returns
    -------
    AxisLog

    Raises
    ------
    LogFormatError
        One line naming the file and the column, variable or key: missing signals, signals of
        different lengths, non-finite values, a time base that disagrees with the controller's
        sample time, a controller that does not reproduce the logged command.
    """
    if fmt.doc.get("axis", "linear") != "linear":
        raise LogFormatError(f"{fmt.path}: axis = {fmt.doc['axis']!r}: a log in motor coordinates; expected "
                             "axis = \"linear\" for a linear-axis plant (a motor-coordinate log fits a screw-driven "
                             "plant: --plant NAME|PLANT.toml)")
    name, doc, src, t, h, sig = _read(path, fmt)
    pos_unit = _POSITION_UNITS[doc["position"]["unit"]]
    q = sig("position") * pos_unit
    v_peak = float(np.max(np.abs(np.diff(q)))) / h
    if v_peak > MAX_SPEED_M_S:
        raise LogFormatError(f"{name}: [position] {doc['position']['name']!r} (unit {doc['position']['unit']!r}): "
                             f"moves {v_peak:.3g} m/s between two samples of {h:g} s; expected at most "
                             f"{MAX_SPEED_M_S:g} m/s (check the position unit and the sample time)")
    ref = sig("reference")
    ref = None if ref is None else ref * _POSITION_UNITS[doc["reference"]["unit"]]
    cmd_sec = doc["command"]
    cmd = sig("command")
    test = sig("test_signal")
    speed = sig("speed")
    speed = None if speed is None else speed * _SPEED_UNITS[doc["speed"]["unit"]]
    load = sig("load")
    load = None if load is None else load * _FORCE_UNITS[doc["load"]["unit"]]
    sources: dict[str, str] = {}
    if cmd_sec["unit"] == "N":
        gain, sources["gain"] = 1.0, "command logged in N"
    else:
        gain, sources["gain"] = src.scalar("[command] gain", cmd_sec["gain"], fmt.path)
    res = doc["position"].get("resolution")
    controller = None
    ctl_doc = doc.get("controller")
    if ctl_doc:
        vals = {}
        for k in ("kp", "kv", "ki"):
            if k in ctl_doc:
                vals[k], sources[f"controller.{k}"] = src.scalar(f"[controller] {k}", ctl_doc[k], fmt.path)
        controller = ControllerSpec(
            structure=ctl_doc["structure"], kp=vals["kp"], kv=vals["kv"], ki=vals.get("ki", 0.0),
            velocity_estimate=ctl_doc.get("velocity_estimate", "average2-difference"),
            saturation=float(ctl_doc["saturation"]), sample_time_s=h,
            command_delay_samples=int(ctl_doc.get("command_delay_samples", 0)),
            check_tolerance=float(ctl_doc.get("check_tolerance", 0.03)), sources=dict(sources))
    log = AxisLog(name=name, time_s=t - t[0], position_m=q, command=cmd, command_unit=cmd_sec["unit"],
                  gain_n_per_unit=gain, sample_time_s=h, reference_m=ref, test_signal=test, speed_m_s=speed,
                  load_n=load, controller=controller, resolution_m=None if res is None else float(res) * pos_unit,
                  command_logged=cmd_sec.get("logged", "as-computed"), sources=sources)
    if controller is not None:
        _check_reproduction(log, fmt)
    return log


def _read(path: str | Path, fmt: LogFormat):
    """The data file of a log: ``(name, doc, source, time_s, sample_time_s, sig)`` with the time
    checked (sample count, increasing, evenly spaced at the controller's or the median interval)
    and ``sig(section)`` reading a section's signal (None when absent or optional and missing)."""
    name = str(path)
    doc = fmt.doc
    kind = doc.get("format") or ("mat" if name.lower().endswith(".mat") else "csv")
    src = LogFile(name, kind, _wanted(doc))
    t_sec = doc["time"]
    t = src.signal("[time] name", t_sec["name"], None) * _TIME_UNITS[t_sec["unit"]]
    n = t.size
    if n < MIN_SAMPLES or n > MAX_SAMPLES:
        raise LogFormatError(f"{name}: {n} samples; expected {MIN_SAMPLES}..{MAX_SAMPLES}")
    dt = np.diff(t)
    if np.any(dt <= 0):
        k = int(np.flatnonzero(dt <= 0)[0]) + 1
        raise LogFormatError(f"{name}: [time] {t_sec['name']!r} sample {k}: not increasing; expected strictly increasing times")
    ctl_doc = doc.get("controller")
    h = float(ctl_doc["sample_time_s"]) if ctl_doc else float(np.median(dt))
    worst = float(np.max(np.abs(dt - h)) / h)
    if worst > SAMPLING_TOL:
        what = (f"[controller] sample_time_s = {h:g}" if ctl_doc else "its median interval")
        raise LogFormatError(f"{name}: [time] {t_sec['name']!r} (unit {t_sec['unit']!r}): sample interval "
                             f"{float(np.median(dt)):.6g} s deviates {100 * worst:.3g} % from {what}; expected evenly "
                             f"spaced samples within {100 * SAMPLING_TOL:g} % (check the time unit)")

    def sig(sec: str) -> np.ndarray | None:
        s = doc.get(sec)
        if s is None:
            return None
        if s.get("optional") and s["name"] not in src.data:
            return None
        return src.signal(f"[{sec}] name", s["name"], n)

    return name, doc, src, t, h, sig


def motor_record(log: AxisLog, plant) -> Record:
    """A log in load coordinates as a record in the motor coordinates of a screw-driven ``plant``.

    With the plant's lead ``a = plant.lead_per_rad`` (m of travel per rad of the screw): angle =
    position / a (rad), speed = speed / a (rad/s), torque command = force command x a (N m: the
    torque an ideal, lossless screw turns the logged force into; the screw's losses are the
    plant's friction), axial load unchanged (N; 0 when the log has none). The time and the
    convention stay the log's (:data:`MOTOR_CONVENTION`).

    Parameters
    ----------
    log : AxisLog
        A log in load coordinates (:func:`load_axis_log`).
    plant : Plant
        A plant in motor coordinates (any mechanism but ``linear-axis``).

    Returns
    -------
    Record
        Named as the log.

    Raises
    ------
    ValueError
        ``plant`` is a linear axis (it works in load coordinates: fit the log directly).
    """
    _check_motor_plant(plant)
    a = float(plant.lead_per_rad)
    return record_from_arrays(log.name, log.time_s, log.force_n * a, nut_angle_rad=log.position_m / a,
                              nut_speed_rad_s=None if log.speed_m_s is None else log.speed_m_s / a,
                              axial_load_n=0.0 if log.load_n is None else log.load_n)


def _check_motor_plant(plant) -> None:
    if plant.mechanism == "linear-axis":
        raise ValueError(f"plant {plant.name!r} is a linear axis (load coordinates); expected a screw-driven plant "
                         "for a motor-coordinate record (a linear axis fits the load-coordinate log directly)")


def load_motor_record(path: str | Path, fmt: LogFormat, plant) -> tuple[Record, str]:
    """Read a log in either coordinates as a record in ``plant``'s motor coordinates.

    Parameters
    ----------
    path : str or Path
        The data file.
    fmt : LogFormat
        Its description: ``axis = "rotary"`` (motor coordinates, read as they are) or
        ``"linear"`` (load coordinates, :func:`load_axis_log` then :func:`motor_record`).
    plant : Plant
        A screw-driven plant (its lead converts a load-coordinate log).

    Returns
    -------
    (Record, str)
        The record (SI motor coordinates: rad, N m, N) and the log's command convention for
        the fit (``"computed"`` or ``"applied"``, :data:`MOTOR_CONVENTION`).

    Raises
    ------
    LogFormatError
        The log disagrees with its description (one line naming the file and the key or column).
    ValueError
        ``plant`` is a linear axis.
    """
    logged = MOTOR_CONVENTION[fmt.doc["command"].get("logged", "as-computed")]
    if fmt.doc.get("axis", "linear") == "linear":
        return _described_checks(motor_record(load_axis_log(path, fmt), plant), fmt, plant), logged
    _check_motor_plant(plant)  # before any data is read
    name, doc, src, t, h, sig = _read(path, fmt)
    angle = sig("position") * _ANGLE_UNITS[doc["position"]["unit"]]
    cmd_sec = doc["command"]
    gain = 1.0 if cmd_sec["unit"] == "N m" else src.scalar("[command] gain", cmd_sec["gain"], fmt.path)[0]
    speed = sig("speed")
    load = sig("load")
    try:
        rec = record_from_arrays(name, t - t[0], sig("command") * gain, nut_angle_rad=angle,
                                 nut_speed_rad_s=None if speed is None else speed * _ANGULAR_SPEED_UNITS[doc["speed"]["unit"]],
                                 axial_load_n=0.0 if load is None else load * _FORCE_UNITS[doc["load"]["unit"]])
    except ValueError as exc:
        raise LogFormatError(f"{name}: {exc}") from None
    return _described_checks(rec, fmt, plant), logged


def _described_checks(rec: Record, fmt: LogFormat, plant) -> Record:
    """The checks of a record against ``plant`` before a fit, named in the log description's terms.

    * The axial load (the ``[load]`` column) at most
      :data:`prsa_ctrl.identification.common.FRF_LOAD_MAX_RATED` times the plant's
      ``screw.rated_load_n`` (a load in kN declared as N reads 1000 times too large).
    * No unit slip in the torque balance (:func:`prsa_ctrl.identification.common.checked_inputs`):
      its message names the ``[command]`` and ``[position]`` columns and their declared units
      instead of the record's internal columns.

    Raises
    ------
    LogFormatError
        One line naming the log, the column and its declared unit.
    """
    from .common import FRF_LOAD_MAX_RATED, checked_inputs  # casadi: only on the fit's path

    doc, src = fmt.doc, Path(fmt.path).name
    rated = float(plant.rated_load_n)
    peak = float(np.max(np.abs(rec.axial_load_n)))
    if "load" in doc and peak > FRF_LOAD_MAX_RATED * rated:
        raise LogFormatError(f"{rec.name}: the [load] column {doc['load']['name']!r}, declared in "
                             f"{doc['load']['unit']} in {src}, reaches {peak / _FORCE_UNITS[doc['load']['unit']]:.6g} "
                             f"{doc['load']['unit']} ({peak:.6g} N), {peak / rated:.3g} x the plant's "
                             f"screw.rated_load_n {rated:.6g} N; expected at most {FRF_LOAD_MAX_RATED:g} x (the load's "
                             "unit in the description?)")
    try:
        checked_inputs([rec], [], [], plant)
    except ValueError as exc:
        msg = str(exc)
        if "torque balance" not in msg:
            raise LogFormatError(msg) from None
        cmd, pos = doc["command"], doc["position"]
        head = msg.split(": column ")[0].split("; expected")[0].replace(
            "torque_command_n_m", f"the [command] column {cmd['name']!r} ({cmd['unit']})").replace(
            "nut_angle_rad", f"the [position] column {pos['name']!r} ({pos['unit']})")
        raise LogFormatError(f"{head}: one of them is not in the unit {src} declares; expected the units the "
                             "log holds (or, if they are right, the actuator's own plant, --plant)") from None
    return rec


def reconstruct_command(log: AxisLog, position_m: NDArray[np.float64] | None = None,
                        with_test_signal: bool = True) -> NDArray[np.float64]:
    """The command the described controller computes from a position record, command unit.

    Parameters
    ----------
    log : AxisLog
        A log with a controller and a reference.
    position_m : ndarray, optional
        Positions fed to the controller, m (default: the logged ones).
    with_test_signal : bool
        Add the log's test signal (as the drive input and the logged command hold it).

    Returns
    -------
    ndarray
        ``clip(u, -saturation, saturation) + test_signal`` per sample, as computed (no delay).
    """
    c = log.controller
    if c is None or log.reference_m is None:
        raise ValueError(f"log {log.name!r}: no controller or reference; expected a described closed loop")
    q = log.position_m if position_m is None else np.asarray(position_m, dtype=float)
    h = c.sample_time_s
    q1 = np.r_[q[0], q[:-1]]
    if c.velocity_estimate == "average2-difference":
        qf = 0.5 * (q + q1)
        dq = np.diff(np.r_[qf[0], qf]) / h
    else:
        dq = (q - q1) / h
    e_v = c.kp * (log.reference_m - q) - dq
    u = c.kv * e_v
    if c.ki:
        u = u + c.kv * c.ki * h * np.cumsum(e_v)  # no anti-windup: checked against the log
    u = np.clip(u, -c.saturation, c.saturation)
    return u + (0.0 if log.test_signal is None or not with_test_signal else log.test_signal)


def _check_reproduction(log: AxisLog, fmt: LogFormat) -> None:
    c = log.controller
    rec = reconstruct_command(log, with_test_signal=False)
    if log.command_logged == "as-applied" and c.command_delay_samples:  # the controller output d samples late
        d = c.command_delay_samples
        rec = np.r_[np.zeros(d), rec[:-d]]
    if log.test_signal is not None:  # the test signal is logged at the sample it acts in
        rec = rec + log.test_signal
    norm = float(np.linalg.norm(log.command))
    if norm == 0:
        raise LogFormatError(f"{log.name}: [command] {fmt.doc['command']['name']!r} is all zero; expected the "
                             "controller output")
    rel = float(np.linalg.norm(rec - log.command)) / norm
    best = min((float(np.linalg.norm(np.roll(rec, s)[3:-3] - log.command[3:-3])) / norm, s) for s in (-2, -1, 1, 2))
    shift_hint = (f"a shift of {best[1]:+d} samples gives {100 * best[0]:.3g} % (check [command] logged and "
                  "[controller] command_delay_samples)")
    if rel > c.check_tolerance:
        hint = (shift_hint if best[0] <= c.check_tolerance else _unit_hint(log, fmt, norm) or
                "check the gains, the units of [position], [reference] and [command], and the structure")
        raise LogFormatError(f"{fmt.path}: [controller] does not reproduce {Path(log.name).name}'s command "
                             f"{fmt.doc['command']['name']!r}: relative error {100 * rel:.3g} %, expected at most "
                             f"{100 * c.check_tolerance:.3g} % (check_tolerance); {hint}")
    if best[0] < ALIGNMENT_RATIO * rel:
        raise LogFormatError(f"{fmt.path}: [controller] reproduces {Path(log.name).name}'s command "
                             f"{fmt.doc['command']['name']!r} with a relative error of {100 * rel:.3g} %, but {shift_hint}: "
                             "expected the described alignment to fit best")
    other = next(e for e in VELOCITY_ESTIMATES if e != c.velocity_estimate)
    alt = replace(log, controller=replace(c, velocity_estimate=other))
    rel_alt = float(np.linalg.norm(reconstruct_command(alt) - log.command)) / norm
    if c.command_delay_samples == 0 and rel_alt < ALIGNMENT_RATIO * rel:
        raise LogFormatError(f"{fmt.path}: [controller] velocity_estimate = {c.velocity_estimate!r} reproduces "
                             f"{Path(log.name).name}'s command {fmt.doc['command']['name']!r} with a relative error of "
                             f"{100 * rel:.3g} %, but {other!r} gives {100 * rel_alt:.3g} %: expected the described "
                             "velocity estimate to fit best")


def _unit_hint(log: AxisLog, fmt: LogFormat, norm: float) -> str | None:
    """Which position units (of [position] and [reference] together) would make the described
    controller reproduce the command, when the declared ones do not: the hint names them."""
    declared = (fmt.doc["position"]["unit"], fmt.doc["reference"]["unit"])
    for up in _POSITION_UNITS:
        for ur in _POSITION_UNITS:
            if (up, ur) == declared:
                continue
            fp, fr = _POSITION_UNITS[up] / _POSITION_UNITS[declared[0]], _POSITION_UNITS[ur] / _POSITION_UNITS[declared[1]]
            trial = replace(log, position_m=log.position_m * fp, reference_m=log.reference_m * fr)
            rel = float(np.linalg.norm(reconstruct_command(trial) - log.command)) / norm
            if rel <= log.controller.check_tolerance:
                return (f"with [position] unit = {up!r} and [reference] unit = {ur!r} (declared {declared[0]!r} and "
                        f"{declared[1]!r}) it reproduces it within {100 * rel:.3g} %: check the units")
    return None
