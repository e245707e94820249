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
A | V with ``gain`` in N m per unit), ``[load]`` the axial load on the nut in N | kN; such a log
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

import csv
import math
import struct
import tomllib
import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import scipy.io
from numpy.typing import NDArray

from ..errors import LogFormatError
from .data import MAX_FILE_BYTES, MAX_SAMPLES, MIN_SAMPLES, Record, record_from_arrays

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
_ANGULAR_SPEED_UNITS = {"rad/s": 1.0, "rpm": math.pi / 30.0}
_TORQUE_COMMAND_UNITS = ("N m", "A", "V")
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
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)) or not (math.isfinite(v) and v > 0):
                raise ValueError(f"AxisLog {self.name!r}: {k} = {v!r}; expected a finite number > 0")

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
        doc = tomllib.loads(p.read_text(encoding="utf-8-sig"))  # a byte-order mark, as plant and data files
    except (OSError, UnicodeDecodeError) as exc:
        raise LogFormatError(f"{name}: cannot be read ({exc}); expected a UTF-8 TOML file") from None
    except tomllib.TOMLDecodeError as exc:
        raise LogFormatError(f"{name}: invalid TOML ({exc})") from None
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
    if res is not None and not _is_positive_number(res):
        raise _err(name, f"[position] resolution = {res!r}", "expected a number > 0 (position unit)")
    ctl = doc.get("controller")
    if ctl is not None:
        _check_controller(name, ctl, has_reference="reference" in doc)
    return LogFormat(path=name, doc=doc)


def _is_positive_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0


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
            raise _err(name, f"[controller] {k}", "missing; expected a number" + (" or a variable name"
                                                                                  if k in ("kp", "kv", "ki") else ""))
    if "ki" in ctl and not st.endswith("pi"):
        raise _err(name, "[controller] ki", f"given for structure {st!r}; expected position-p/velocity-pi")
    for k in ("saturation", "sample_time_s"):
        if not _is_positive_number(ctl[k]):
            raise _err(name, f"[controller] {k} = {ctl[k]!r}", "expected a number > 0")
    ve = ctl.get("velocity_estimate", "average2-difference")
    if ve not in VELOCITY_ESTIMATES:
        raise _err(name, f"[controller] velocity_estimate = {ve!r}", f"expected one of {', '.join(VELOCITY_ESTIMATES)}")
    d = ctl.get("command_delay_samples", 0)
    if isinstance(d, bool) or not isinstance(d, int) or not 0 <= d <= 10:
        raise _err(name, f"[controller] command_delay_samples = {d!r}", "expected an integer 0..10")
    tol = ctl.get("check_tolerance", 0.03)
    if not _is_positive_number(tol) or tol >= 1:
        raise _err(name, f"[controller] check_tolerance = {tol!r}", "expected a number in (0, 1)")


# --- the data ----------------------------------------------------------------------------------


#: MATLAB array classes (mxArray class numbers of the v5 format).
_MAT_CLASSES = {1: "cell", 2: "struct", 3: "object", 4: "char", 5: "sparse", 6: "double", 7: "single", 8: "int8",
                9: "uint8", 10: "int16", 11: "uint16", 12: "int32", 13: "uint32", 14: "int64", 15: "uint64",
                16: "function", 17: "opaque"}
_MAT_NUMERIC = {"double", "single", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64", "logical"}
#: Largest variable header (flags, dimensions, name) of a .mat file read, bytes.
_MAT_HEADER_BYTES = 4096
_MI_MATRIX, _MI_COMPRESSED = 14, 15
#: Most variables a .mat log may hold (each header is read); names listed in a message.
_MAT_MAX_VARIABLES, _NAMES_SHOWN = 100_000, 50


@dataclass(frozen=True)
class _MatVar:
    """One variable of a v5 .mat file, from its header: class, complex flag, shape and where its
    element is (``start``: its tag, ``end``: past its data; ``compressed``: a zlib element)."""

    name: str
    kind: str
    complex: bool
    shape: tuple[int, ...]
    start: int
    end: int
    compressed: bool
    header_bytes: int

    @property
    def size(self) -> int:
        return math.prod(self.shape)


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


class _Source:
    """The columns (CSV) or variables (.mat) of one data file that its description names.

    Memory is bounded before anything is read: the file at most
    :data:`prsa_ctrl.identification.data.MAX_FILE_BYTES`; a CSV file is streamed, only the named
    columns kept, refused at its row ``MAX_SAMPLES + 1``; a .mat file's variable headers are read
    first (class, complex flag, shape: a compressed one decompressed only as far as its header)
    and only the named variables are decompressed and loaded, each refused before that when it
    is not real numbers or holds more than :data:`prsa_ctrl.identification.data.MAX_SAMPLES`
    values. ``names`` lists every column or variable of the file (for messages).
    """

    def __init__(self, path: str, fmt: str, wanted: Mapping[str, str] | None = None):
        self.path, self.fmt = path, fmt
        self.wanted = dict(wanted or {})
        p = Path(path)
        if not p.is_file():
            raise LogFormatError(f"{path}: log file not found; expected a readable {fmt} file")
        try:
            size = p.stat().st_size
        except OSError as exc:
            raise LogFormatError(f"{path}: cannot be read ({exc.strerror or exc}); expected a readable {fmt} file") from None
        if size > MAX_FILE_BYTES:
            raise LogFormatError(f"{path}: {size} bytes; expected at most {MAX_FILE_BYTES} bytes (cut the log)")
        self.all_names: list[str] = []  # (the first _NAMES_SHOWN of a .mat file's)
        self.names_total = 0
        self.kinds: dict[str, str] = {}  # variables that are not real numbers: what they are
        self.data: dict[str, np.ndarray] = self._read_mat(p, size) if fmt == "mat" else self._read_csv(p)

    # --- .mat ------------------------------------------------------------------------------------

    def _bad_mat(self, text: str) -> LogFormatError:
        return LogFormatError(f"{self.path}: cannot be read as a MATLAB .mat file ({text}); expected a MATLAB v4 or "
                              "v5/v7 .mat file")

    def _read_mat(self, p: Path, size: int) -> dict[str, np.ndarray]:
        from scipy.io.matlab import MatReadError, matfile_version

        if size == 0:
            raise self._bad_mat("an empty file")
        try:
            with p.open("rb") as fh:
                major, _ = matfile_version(fh)
        except (MatReadError, OSError, ValueError, TypeError, IndexError, struct.error) as exc:
            raise self._bad_mat(str(exc) or type(exc).__name__) from None
        if major == 2:
            raise LogFormatError(f"{self.path}: MATLAB v7.3 (HDF5) file; expected a v5/v7 .mat file (save with "
                                 "-v7)")
        try:
            raw = self._read_mat4(p, size) if major == 0 else self._read_mat5(p, size)
        except LogFormatError:
            raise
        except (MatReadError, OSError, ValueError, TypeError, KeyError, IndexError, struct.error, zlib.error,
                NotImplementedError, AttributeError) as exc:
            raise self._bad_mat(str(exc) or type(exc).__name__) from None
        out = {}
        for k, v in raw.items():
            if k.startswith("__") or k not in self.wanted:
                continue
            if not isinstance(v, np.ndarray) or v.dtype.kind not in "fiub":
                what = "complex numbers" if isinstance(v, np.ndarray) and v.dtype.kind == "c" else \
                    f"a MATLAB {type(v).__name__ if not isinstance(v, np.ndarray) else v.dtype.name} array"
                raise self._not_numbers(k, what)
            out[k] = np.asarray(v, dtype=float)
        return out

    def _not_numbers(self, var: str, what: str) -> LogFormatError:
        return LogFormatError(f"{self.path}: variable {var!r} ({self.wanted.get(var, 'named')}) holds {what}; expected "
                              "a real numeric vector or scalar (double, single, integer or logical)")

    def _check_var(self, name: str, kind: str, complex_: bool, shape: tuple[int, ...]) -> None:
        """A named variable checked from its header, before its data are read."""
        if kind not in _MAT_NUMERIC:
            what = {"char": "text (a MATLAB char array)", "cell": "a MATLAB cell array", "sparse": "a MATLAB sparse matrix",
                    "struct": "a MATLAB struct"}.get(kind, f"a MATLAB {kind}")
            raise self._not_numbers(name, what)
        if complex_:
            raise self._not_numbers(name, f"complex numbers (class {kind})")
        n = math.prod(shape)
        if n > MAX_SAMPLES:
            raise LogFormatError(f"{self.path}: variable {name!r} ({self.wanted[name]}) has shape "
                                 f"{'x'.join(map(str, shape))} ({n} values); expected at most {MAX_SAMPLES} values (one "
                                 "per sample; cut the log)")

    def _read_mat4(self, p: Path, size: int) -> dict:
        """A v4 file (never compressed): every variable's 20-byte header read, the named ones
        checked, then only those loaded (from memory)."""
        import io

        chunks, seen, count, pos = [], set(), 0, 0
        with p.open("rb") as fh:
            while pos + 20 <= size:
                count += 1
                if count > _MAT_MAX_VARIABLES:
                    raise self._bad_mat(f"more than {_MAT_MAX_VARIABLES} variables")
                fh.seek(pos)
                raw = fh.read(20)
                for endian in "<>":
                    mopt, rows, cols, imagf, namlen = struct.unpack(endian + "5i", raw)
                    if 0 <= mopt < 5000 and mopt // 100 % 10 == 0:
                        break
                else:
                    raise self._bad_mat(f"no MATLAB v4 variable header at byte {pos}")
                itemsize = {0: 8, 1: 4, 2: 4, 3: 2, 4: 2, 5: 1}.get(mopt // 10 % 10)
                if itemsize is None or min(rows, cols, namlen) < 0 or namlen > 4096:
                    raise self._bad_mat(f"a bad MATLAB v4 variable header at byte {pos}")
                name = fh.read(namlen).rstrip(b"\0").decode("latin1")
                end = pos + 20 + namlen + rows * cols * itemsize * (2 if imagf else 1)
                if end > size:
                    raise self._bad_mat(f"the variable at byte {pos} runs past the end of the file")
                if len(self.all_names) < _NAMES_SHOWN:
                    self.all_names.append(name)
                if name in self.wanted:
                    if name in seen:
                        raise LogFormatError(f"{self.path}: variable {name!r} ({self.wanted[name]}) appears twice in "
                                             "the file; expected each name once")
                    seen.add(name)
                    kind = {0: "double", 1: "char", 2: "sparse"}.get(mopt % 10, f"type {mopt % 10}")
                    self._check_var(name, kind, bool(imagf), (rows, cols))
                    fh.seek(pos)
                    chunks.append(fh.read(end - pos))
                pos = end
        self.names_total = count
        return scipy.io.loadmat(io.BytesIO(b"".join(chunks))) if chunks else {}

    def _read_mat5(self, p: Path, size: int) -> dict:
        """A v5/v7 file: every variable's header read (a compressed one decompressed only to
        :data:`_MAT_HEADER_BYTES`), the named ones checked, then only those decompressed (each
        bounded by its shape) and loaded from memory."""
        import io

        with p.open("rb") as fh:
            head = fh.read(128)
            endian = {b"IM": "<", b"MI": ">"}.get(head[126:128])
            if endian is None:
                raise self._bad_mat("no endian indicator in its header")
            variables, count = [], 0
            pos = 128
            while pos + 8 <= size:
                count += 1
                if count > _MAT_MAX_VARIABLES:
                    raise self._bad_mat(f"more than {_MAT_MAX_VARIABLES} variables")
                fh.seek(pos)
                mdtype, nbytes = struct.unpack(endian + "II", fh.read(8))
                end = pos + 8 + nbytes
                if mdtype not in (_MI_MATRIX, _MI_COMPRESSED):
                    raise self._bad_mat(f"data element of type {mdtype} at byte {pos}, expected a matrix")
                if end > size:
                    raise self._bad_mat(f"the element at byte {pos} runs past the end of the file")
                v = self._mat5_header(fh, endian, pos, end, mdtype == _MI_COMPRESSED)
                if len(self.all_names) < _NAMES_SHOWN:
                    self.all_names.append(v.name)
                if v.name in self.wanted:  # only these are kept
                    variables.append(v)
                pos = end
            self.names_total = count
            chunks, seen = [head], set()
            for v in variables:
                if v.name not in self.wanted:
                    continue
                if v.name in seen:
                    raise LogFormatError(f"{self.path}: variable {v.name!r} ({self.wanted[v.name]}) appears twice in the "
                                         "file; expected each name once")
                seen.add(v.name)
                self._check_var(v.name, v.kind, v.complex, v.shape)
                chunks.append(self._mat5_element(fh, endian, v))
        if len(chunks) == 1:
            return {}
        return scipy.io.loadmat(io.BytesIO(b"".join(chunks)))

    @staticmethod
    def _inflate(fh, start: int, end: int, limit: int) -> bytes:
        """The decompressed bytes of the zlib stream in ``[start, end)`` of the file, at most
        ``limit + 1`` of them (so that more than ``limit`` is seen)."""
        d = zlib.decompressobj()
        out = []
        got = 0
        fh.seek(start)
        left = end - start
        pending = b""
        while got <= limit:
            if not pending:
                if left <= 0:
                    break
                pending = fh.read(min(65536, left))
                left -= len(pending)
                if not pending:
                    break
            chunk = d.decompress(pending, limit + 1 - got)
            pending = d.unconsumed_tail
            out.append(chunk)
            got += len(chunk)
            if d.eof:
                break
        return b"".join(out)

    def _mat5_header(self, fh, endian: str, pos: int, end: int, compressed: bool) -> _MatVar:
        if compressed:
            raw = self._inflate(fh, pos + 8, end, _MAT_HEADER_BYTES)
            mdtype, _ = struct.unpack(endian + "II", raw[:8])
            if mdtype != _MI_MATRIX:
                raise self._bad_mat(f"compressed element at byte {pos} holds type {mdtype}, expected a matrix")
            body = raw[8:]
        else:
            fh.seek(pos + 8)
            body = fh.read(min(end - pos - 8, _MAT_HEADER_BYTES))
        if not body:  # an empty matrix element (MATLAB writes these for empty arrays)
            return _MatVar("", "double", False, (0, 0), pos, end, compressed, 0)
        off = 0
        fields = []
        for _ in range(3):  # array flags, dimensions, name
            if off + 8 > len(body):
                raise self._bad_mat(f"the variable header at byte {pos} is longer than {_MAT_HEADER_BYTES} bytes or cut")
            first = struct.unpack(endian + "I", body[off:off + 4])[0]
            if first >> 16:  # a small data element: type and length in one word, data in the next
                n = first >> 16
                fields.append(body[off + 4:off + 4 + n])
                off += 8
            else:
                n = struct.unpack(endian + "I", body[off + 4:off + 8])[0]
                if off + 8 + n > len(body):
                    raise self._bad_mat(f"the variable header at byte {pos} is longer than {_MAT_HEADER_BYTES} bytes "
                                        "or cut")
                fields.append(body[off + 8:off + 8 + n])
                off += 8 + (n + 7) // 8 * 8
        flags = struct.unpack(endian + "I", fields[0][:4])[0]
        kind = "logical" if flags >> 9 & 1 else _MAT_CLASSES.get(flags & 0xFF, f"class {flags & 0xFF}")
        dims = tuple(struct.unpack(endian + f"{len(fields[1]) // 4}i", fields[1][:len(fields[1]) // 4 * 4]))
        if any(d < 0 for d in dims):
            raise self._bad_mat(f"negative dimensions {dims} at byte {pos}")
        return _MatVar(fields[2].decode("latin1"), kind, bool(flags >> 11 & 1), dims, pos, end, compressed, off)

    def _mat5_element(self, fh, endian: str, v: _MatVar) -> bytes:
        """A named variable's element, uncompressed, its size bounded by its shape (8 bytes a value
        at most, plus its header and padding)."""
        bound = v.header_bytes + 16 + 8 * v.size + 8
        if v.compressed:
            raw = self._inflate(fh, v.start + 8, v.end, bound + 8)
            if len(raw) > bound + 8:
                raise self._bad_mat(f"variable {v.name!r} decompresses to more than its shape "
                                    f"{'x'.join(map(str, v.shape))} holds")
            return raw
        if v.end - v.start > bound + 8:
            raise self._bad_mat(f"variable {v.name!r} takes {v.end - v.start} bytes, more than its shape "
                                f"{'x'.join(map(str, v.shape))} holds")
        fh.seek(v.start)
        return fh.read(v.end - v.start)

    # --- CSV -------------------------------------------------------------------------------------

    def _read_csv(self, p: Path) -> dict[str, np.ndarray]:
        """Streamed: the header, then the named columns only, one row at a time into arrays; a
        file with more than ``MAX_SAMPLES`` data rows is refused at its row ``MAX_SAMPLES + 1``."""
        from array import array

        header: list[str] | None = None
        cols: dict[str, tuple[int, array]] = {}
        n = 0
        try:
            with p.open(newline="", encoding="utf-8-sig") as fh:
                for line, row in enumerate(csv.reader(fh), start=1):
                    if not row or not any(c.strip() for c in row) or row[0].lstrip().startswith("#"):
                        continue
                    if header is None:
                        header = [h.strip() for h in row]
                        self.all_names = header
                        for c, h in enumerate(header):
                            if h in self.wanted:
                                if h in cols:
                                    raise LogFormatError(
                                        f"{self.path}: column {h!r} ({self.wanted[h]}) appears twice in the header "
                                        f"(columns {cols[h][0] + 1} and {c + 1}, line {line}); expected each name once")
                                cols[h] = (c, array("d"))
                        continue
                    n += 1
                    if n > MAX_SAMPLES:
                        raise LogFormatError(f"{self.path}: more than {MAX_SAMPLES} data rows (line {line}); expected "
                                             f"at most {MAX_SAMPLES} (cut the log)")
                    if len(row) != len(header):
                        raise LogFormatError(f"{self.path}: line {line} has {len(row)} fields; expected {len(header)} "
                                             "like the header")
                    for h, (c, values) in cols.items():
                        try:
                            values.append(float(row[c]))
                        except ValueError:
                            raise LogFormatError(f"{self.path}: column {h!r} line {line}: {row[c].strip()!r} is not a "
                                                 "number; expected a finite number") from None
        except (OSError, UnicodeDecodeError, csv.Error) as exc:
            raise LogFormatError(f"{self.path}: cannot be read ({exc}); expected a UTF-8 CSV file") from None
        if header is None:
            raise LogFormatError(f"{self.path}: no header row; expected a CSV header naming the columns")
        return {h: np.frombuffer(values, dtype=float).copy() for h, (c, values) in cols.items()}

    def names(self) -> str:
        """The file's columns or variables for a message (the first :data:`_NAMES_SHOWN`)."""
        total = max(self.names_total, len(self.all_names))
        shown = ", ".join(self.all_names[:_NAMES_SHOWN]) or "nothing"
        return shown + (f", ... ({total} in all)" if total > _NAMES_SHOWN else "")

    def signal(self, key: str, var: str, n: int | None) -> np.ndarray:
        what = "column" if self.fmt == "csv" else "variable"
        if var not in self.data:
            raise LogFormatError(f"{self.path}: {key} names {what} {var!r}, not in the file; it has {self.names()}")
        v = self.data[var]
        if v.ndim == 2 and 1 in v.shape:
            v = v.ravel()
        if v.ndim != 1 or v.size < 2:
            raise LogFormatError(f"{self.path}: {what} {var!r} ({key}) has shape {self.data[var].shape}; expected a "
                                 "vector (one value per sample)")
        if n is not None and v.size != n:
            raise LogFormatError(f"{self.path}: {what} {var!r} ({key}) has {v.size} samples; expected {n} like the time")
        bad = np.flatnonzero(~np.isfinite(v))
        if bad.size:
            raise LogFormatError(f"{self.path}: {what} {var!r} ({key}) sample {bad[0]}: {v[bad[0]]}; expected finite values")
        return v.astype(float)

    def scalar(self, key: str, value: Any, fmt_path: str) -> tuple[float, str]:
        """A number given in the description, or the name of a scalar variable of the file."""
        if isinstance(value, str):
            if self.fmt != "mat":
                raise LogFormatError(f"{fmt_path}: {key} = {value!r}: variable names work for .mat files only; "
                                     "expected a number")
            if value not in self.data:
                raise LogFormatError(f"{self.path}: {key} names variable {value!r}, not in the file; it has {self.names()}")
            v = self.data[value]
            if v.size != 1:
                raise LogFormatError(f"{self.path}: variable {value!r} ({key}) has shape {v.shape}; expected a scalar")
            x, src = float(v.ravel()[0]), f"{Path(self.path).name}: {value}"
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            x, src = float(value), Path(fmt_path).name
        else:
            raise LogFormatError(f"{fmt_path}: {key} = {value!r}; expected a number or a variable name")
        if not math.isfinite(x) or x <= 0:
            raise LogFormatError(f"{self.path if isinstance(value, str) else fmt_path}: {key} = {x!r}"
                                 f"{' (variable ' + repr(value) + ')' if isinstance(value, str) else ''}; expected a "
                                 "finite number > 0")
        return x, src


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
    src = _Source(name, kind, _wanted(doc))
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
