"""Measured data for plant calibration: loading and validating drive logs, and experiment design.

A time-domain record is a CSV file with a header row. Standard column names (SI units):

``time_s``
    Sample time, s (strictly increasing, evenly spaced).
``torque_command_n_m``
    Torque command the speed loop sent to the current loop, N m (or ``current_a`` with a
    torque constant, N m/A).
``nut_angle_rad``
    Encoder angle of the nut, rad (may be missing when the speed is given).
``nut_speed_rad_s``
    Measured nut speed, rad/s: the backward difference of the encoder angle over one sample
    (may be missing when the angle is given).
``axial_load_n``
    Axial load on the screw, N (may be missing when it is constant and given separately).

Other header names are mapped with ``columns={"nut_angle_rad": "enc_pos", ...}``. Every error
is a :class:`DataError` (a ``ValueError``) whose one-line message names the file, the column and
the row (the file's line number, header = line 1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import scipy.signal
from numpy.typing import NDArray

from ..errors import DataError
from ..options import check_number, rad_s_to_rpm
from ..tablefile import read_table

__all__ = [
    "Record",
    "STANDARD_COLUMNS",
    "parse_columns",
    "load_record",
    "record_from_arrays",
    "design_excitation",
    "DESIGNS",
    "MIN_SAMPLES",
    "MAX_SAMPLES",
    "FrfRecord",
    "load_frf",
    "frf_from_arrays",
    "frf_from_record",
    "FRF_COLUMNS",
    "COHERENCE_MIN",
]

#: Standard column names of a time-domain record.
STANDARD_COLUMNS = ("time_s", "torque_command_n_m", "nut_angle_rad", "nut_speed_rad_s", "axial_load_n")
_CURRENT = "current_a"
_ALL_COLUMNS = STANDARD_COLUMNS + (_CURRENT,)
#: Fewest samples a record (and a controller log, :mod:`prsa_ctrl.identification.logformat`) may have.
MIN_SAMPLES = 50
#: Largest relative deviation of a sample interval from the median interval.
SAMPLING_TOL = 0.01
#: Largest record (and controller log) length accepted (samples), so every fit and replay is
#: bounded before it starts.
MAX_SAMPLES = 2_000_000
#: Largest data file read (bytes), checked before reading: ``MAX_SAMPLES`` rows of up to 256
#: bytes (a record written with 17 significant digits takes about 120 bytes a row).
MAX_FILE_BYTES = 256 * MAX_SAMPLES
_RPM = rad_s_to_rpm(1.0)  # rpm per rad/s


@dataclass(frozen=True, eq=False)
class Record:
    """One validated time-domain record (SI units, evenly sampled).

    Attributes
    ----------
    name : str
        Where the data came from (file path as the user typed it, or a label).
    time_s : ndarray, s
    torque_command_n_m : ndarray, N m
    nut_angle_rad : ndarray or None, rad
    nut_speed_rad_s : ndarray or None, rad/s
    axial_load_n : ndarray, N
    warnings : tuple of str
        Non-fatal findings (e.g. a load that never changes).
    """

    name: str
    time_s: NDArray[np.float64]
    torque_command_n_m: NDArray[np.float64]
    nut_angle_rad: NDArray[np.float64] | None
    nut_speed_rad_s: NDArray[np.float64] | None
    axial_load_n: NDArray[np.float64]
    warnings: tuple[str, ...] = field(default=())

    @property
    def n(self) -> int:
        """Number of samples."""
        return len(self.time_s)

    @property
    def sample_time_s(self) -> float:
        """Mean sample interval, s."""
        return float((self.time_s[-1] - self.time_s[0]) / (self.n - 1))

    @property
    def speed_rad_s(self) -> NDArray[np.float64]:
        """Measured speed (rad/s, length ``n - 1``, interval k -> k+1): the speed column, or
        the difference of the angle column over one sample."""
        if self.nut_angle_rad is not None:
            return np.diff(self.nut_angle_rad) / np.diff(self.time_s)
        return self.nut_speed_rad_s[1:]

    def to_csv(self, path: str | Path) -> None:
        """Write the record with the standard column names (used by tests and examples)."""
        cols = {"time_s": self.time_s, "torque_command_n_m": self.torque_command_n_m}
        if self.nut_angle_rad is not None:
            cols["nut_angle_rad"] = self.nut_angle_rad
        if self.nut_speed_rad_s is not None:
            cols["nut_speed_rad_s"] = self.nut_speed_rad_s
        cols["axial_load_n"] = self.axial_load_n
        data = np.column_stack(list(cols.values()))
        np.savetxt(path, data, delimiter=",", header=",".join(cols), comments="", fmt="%.17g")


def parse_columns(text: str) -> dict[str, str]:
    """Parse ``name=header,name=header`` into ``{standard name: header in the file}``.

    Examples
    --------
    >>> parse_columns("nut_angle_rad=enc,time_s=t")
    {'nut_angle_rad': 'enc', 'time_s': 't'}
    """
    out: dict[str, str] = {}
    for part in text.split(","):
        name, sep, header = part.partition("=")
        name, header = name.strip(), header.strip()
        if not sep or not name or not header:
            raise DataError(f"--columns {text!r}: {part!r} is not name=header; expected e.g. nut_angle_rad=enc_pos")
        if name not in _ALL_COLUMNS:
            raise DataError(f"--columns {text!r}: unknown name {name!r}; expected one of {', '.join(_ALL_COLUMNS)}")
        if name in out:
            raise DataError(f"--columns {text!r}: {name!r} mapped twice; expected each name once")
        out[name] = header
    return out


def load_record(
    path: str | Path,
    *,
    columns: Mapping[str, str] | None = None,
    torque_constant_n_m_per_a: float | None = None,
    load_n: float | None = None,
    min_samples: int = MIN_SAMPLES,
    sampling_tol: float = SAMPLING_TOL,
) -> Record:
    """Read and validate one time-domain CSV record.

    Parameters
    ----------
    path : str or Path
        CSV file with a header row (comma separated; read by :func:`prsa_ctrl.tablefile.read_table`:
        a byte-order mark, blank rows and ``#`` comment rows are skipped, at most ``MAX_SAMPLES``
        rows and ``MAX_FILE_BYTES`` bytes, every cell a finite number).
    columns : mapping, optional
        ``{standard name: header in the file}`` for files with other header names.
    torque_constant_n_m_per_a : float, optional
        Torque constant, N m/A: the torque command is ``current_a`` times it.
    load_n : float, optional
        Constant axial load, N, when the file has no load column.
    min_samples : int
        Fewest samples accepted.
    sampling_tol : float
        Largest relative deviation of any sample interval from the median one.

    Returns
    -------
    Record

    Raises
    ------
    DataError
        One line naming the file, the column and the row of the first problem.
    """
    name = str(path)
    p = Path(path)
    if not p.is_file():
        raise DataError(f"{name}: data file not found; expected a readable CSV file")
    mapping = dict(columns or {})
    for std in mapping:
        if std not in _ALL_COLUMNS:
            raise DataError(f"{name}: column mapping for unknown name {std!r}; expected one of {', '.join(_ALL_COLUMNS)}")
    reverse = {h: std for std, h in mapping.items()}
    std_names: list[str] = []

    def check_header(header: tuple[str, ...], header_line: int) -> None:
        for std, h in mapping.items():
            if h not in header:
                raise DataError(f"{name}: column {h!r} (mapped to {std}) not in the header; the header has {', '.join(header)}")
        for h in header:
            std = reverse.get(h, h)
            if std not in _ALL_COLUMNS:
                raise DataError(
                    f"{name}: unknown column {h!r} (line {header_line}); expected {', '.join(_ALL_COLUMNS)} "
                    "or a mapping --columns name=header"
                )
            if std in std_names:
                raise DataError(f"{name}: column {h!r} (line {header_line}) gives {std} twice; expected each column once")
            std_names.append(std)

    # the one CSV reader: BOM, comments, size and rows bounded before/while reading, finite numbers
    table = read_table(p, max_rows=MAX_SAMPLES, max_bytes=MAX_FILE_BYTES, name=name, error=DataError,
                       on_header=check_header)
    arrays = {std: table.columns[h] for std, h in zip(std_names, table.header)}
    line_of = [int(x) for x in table.lines]
    headers = {std: h for std, h in zip(std_names, table.header)}
    return _validate(name, arrays, headers, line_of, torque_constant_n_m_per_a, load_n, min_samples, sampling_tol)


def record_from_arrays(
    name: str,
    time_s: Sequence[float],
    torque_command_n_m: Sequence[float],
    *,
    nut_angle_rad: Sequence[float] | None = None,
    nut_speed_rad_s: Sequence[float] | None = None,
    axial_load_n: Sequence[float] | float | None = None,
    min_samples: int = MIN_SAMPLES,
    sampling_tol: float = SAMPLING_TOL,
) -> Record:
    """Validate arrays (SI units, same length) into a :class:`Record`; rows are 0-based indices.

    Examples
    --------
    >>> import numpy as np
    >>> t = np.arange(100) * 2.5e-4
    >>> r = record_from_arrays("demo", t, np.sin(t * 100), nut_angle_rad=np.cos(t * 50), axial_load_n=500.0)
    >>> r.n, r.sample_time_s
    (100, 0.00025)
    """
    arrays = {"time_s": np.asarray(time_s, float), "torque_command_n_m": np.asarray(torque_command_n_m, float)}
    if nut_angle_rad is not None:
        arrays["nut_angle_rad"] = np.asarray(nut_angle_rad, float)
    if nut_speed_rad_s is not None:
        arrays["nut_speed_rad_s"] = np.asarray(nut_speed_rad_s, float)
    load_const = None
    if axial_load_n is not None and np.ndim(axial_load_n) == 0:
        load_const = float(axial_load_n)  # type: ignore[arg-type]
    elif axial_load_n is not None:
        arrays["axial_load_n"] = np.asarray(axial_load_n, float)
    n = len(arrays["time_s"])
    for k, a in arrays.items():
        if a.ndim != 1 or len(a) != n:
            raise DataError(f"{name}: column {k!r} has shape {a.shape}; expected ({n},) like time_s")
    headers = {k: k for k in arrays}
    return _validate(name, arrays, headers, list(range(n)), None, load_const, min_samples, sampling_tol,
                     row_word="row")


def _validate(name, arrays, headers, line_of, k_t, load_n, min_samples, sampling_tol, row_word="line") -> Record:
    k_t = check_number("torque constant (N m/A)", k_t, 0.0, lo_open=True, optional=True, error=DataError)
    load_n = check_number("load", load_n, unit="N", optional=True, error=DataError, expected="a finite axial load in N")
    if "time_s" not in arrays:
        raise DataError(f"{name}: missing required column 'time_s'; expected it (or a mapping --columns time_s=HEADER)")
    if "torque_command_n_m" not in arrays:
        if _CURRENT in arrays and k_t is None:
            raise DataError(f"{name}: column {headers[_CURRENT]!r} is a current; expected a torque constant (--torque-constant N m/A)")
        if _CURRENT not in arrays:
            raise DataError(
                f"{name}: missing required column 'torque_command_n_m'; expected it, or 'current_a' with a torque constant"
            )
    elif _CURRENT in arrays:
        raise DataError(f"{name}: both 'torque_command_n_m' and 'current_a' given; expected one of them")
    if k_t is not None and _CURRENT not in arrays:
        raise DataError(f"{name}: a torque constant of {k_t:g} N m/A (--torque-constant) was given, but the file has no "
                        "current column 'current_a'; expected it only for a log of the current (or a mapping "
                        "--columns current_a=HEADER)")
    if "nut_angle_rad" not in arrays and "nut_speed_rad_s" not in arrays:
        raise DataError(f"{name}: missing column 'nut_angle_rad' or 'nut_speed_rad_s'; expected at least one of them")
    if "axial_load_n" not in arrays and load_n is None:
        raise DataError(f"{name}: missing column 'axial_load_n'; expected it, or a constant load (--load N)")
    if "axial_load_n" in arrays and load_n is not None:
        raise DataError(f"{name}: has an 'axial_load_n' column and a constant load {load_n:g} N was given; expected one of them")
    n = len(arrays["time_s"])
    if n < min_samples:
        raise DataError(f"{name}: {n} samples; expected at least {min_samples}")
    for std, a in arrays.items():
        bad = np.flatnonzero(~np.isfinite(a))
        if bad.size:
            check_number(f"{name} {row_word} {line_of[bad[0]]}: {headers[std]}", float(a[bad[0]]), error=DataError)
    t = arrays["time_s"]
    dt = np.diff(t)
    bad = np.flatnonzero(dt <= 0)
    if bad.size:
        k = bad[0] + 1
        what = "duplicated" if dt[bad[0]] == 0 else "goes backwards"
        raise DataError(
            f"{name}: column {headers['time_s']!r} {row_word} {line_of[k]}: time {float(t[k])!r} s {what}; expected strictly increasing time"
        )
    med = float(np.median(dt))
    dev = np.abs(dt - med) / med
    bad = np.flatnonzero(dev > sampling_tol)
    if bad.size:
        k = bad[0] + 1
        raise DataError(
            f"{name}: column {headers['time_s']!r} {row_word} {line_of[k]}: interval {dt[bad[0]]:.6g} s differs from the "
            f"median {med:.6g} s by {100 * dev[bad[0]]:.2g} %; expected even sampling within {100 * sampling_tol:g} %"
        )
    torque = arrays["torque_command_n_m"] if "torque_command_n_m" in arrays else arrays[_CURRENT] * k_t
    tq_name = "torque_command_n_m" if "torque_command_n_m" in arrays else _CURRENT
    load = arrays["axial_load_n"] if "axial_load_n" in arrays else np.full(n, float(load_n))
    for std, a in ((tq_name, torque), *((k, arrays[k]) for k in ("nut_angle_rad", "nut_speed_rad_s") if k in arrays)):
        if np.ptp(a) <= 1e-12 * max(1.0, float(np.max(np.abs(a)))):
            raise DataError(
                f"{name}: column {headers[std]!r} {row_word}s {line_of[0]}..{line_of[-1]}: constant {float(a[0])!r}; "
                "expected an excited signal (nothing to fit)"
            )
    warns = []
    if "nut_angle_rad" in arrays and "nut_speed_rad_s" in arrays:
        d_angle = np.diff(arrays["nut_angle_rad"]) / dt
        speed = arrays["nut_speed_rad_s"][1:]
        ref = float(np.sqrt(np.mean(d_angle**2)))
        if ref > 0 and float(np.sqrt(np.mean(speed**2))) > 0:
            ratio = float(np.sqrt(np.mean(speed**2))) / ref
            for factor, unit in ((_RPM, "rpm"), (1.0 / _RPM, "rev/s... or the angle in rev")):
                if abs(ratio / factor - 1.0) < 0.1:
                    raise DataError(
                        f"{name}: column {headers['nut_speed_rad_s']!r} {row_word}s {line_of[1]}..{line_of[-1]}: "
                        f"speed is {ratio:.3g} x the angle's derivative (looks like {unit}); expected rad/s "
                        "(convert it or drop the column)"
                    )
            if abs(ratio - 1.0) > 0.25:
                warns.append(f"{name}: speed and angle disagree (RMS ratio {ratio:.3g}); the angle is used for the fit")
    if "axial_load_n" in arrays and np.ptp(load) <= 1e-9 * max(1.0, float(np.max(np.abs(load)))):
        warns.append(f"{name}: axial load constant at {load[0]:g} N")
    return Record(
        name=name,
        time_s=t.copy(),
        torque_command_n_m=np.array(torque, float),
        nut_angle_rad=np.array(arrays["nut_angle_rad"]) if "nut_angle_rad" in arrays else None,
        nut_speed_rad_s=np.array(arrays["nut_speed_rad_s"]) if "nut_speed_rad_s" in arrays else None,
        axial_load_n=np.array(load, float),
        warnings=tuple(warns),
    )


# --- experiment design ------------------------------------------------------------------------

#: Excitation kinds of :func:`design_excitation`.
DESIGNS = ("multisine", "chirp", "steps")


def design_excitation(
    kind: str,
    *,
    duration_s: float = 4.0,
    sample_time_s: float = 2.5e-4,
    f_min_hz: float = 1.0,
    f_max_hz: float = 200.0,
    amplitude: float = 20.0,
    offset: float = 30.0,
    seed: int = 0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Excitation signal for a calibration experiment (speed setpoint in rad/s or torque in N m).

    Parameters
    ----------
    kind : {"multisine", "chirp", "steps"}
        ``multisine``: random-phase multisine (Schroeder-like, seeded) on a log grid of
        frequencies in ``[f_min_hz, f_max_hz]``, RMS ``amplitude / sqrt(2)``; ``chirp``: logarithmic
        sweep; ``steps``: a staircase through both directions (``offset +/- amplitude``,
        ``-offset``, ...), each level held ``duration_s / 8``.
    duration_s, sample_time_s : float, s
    f_min_hz, f_max_hz : float, Hz
    amplitude, offset : float
        Peak excursion and mean, in the unit of the signal (rad/s for a speed setpoint).
    seed : int
        Seed of the multisine phases.

    Returns
    -------
    time_s, value : ndarray

    Examples
    --------
    >>> t, v = design_excitation("steps", duration_s=0.8, sample_time_s=1e-3)
    >>> len(t), float(v.max()) > 0 > float(v.min())
    (800, True)
    """
    if kind not in DESIGNS:
        raise ValueError(f"design = {kind!r}; expected one of {', '.join(DESIGNS)}")
    duration_s = check_number("duration (s)", duration_s, 0.0, lo_open=True, optional=True, error=DataError)
    sample_time_s = check_number("sample time (s)", sample_time_s, 0.0, lo_open=True, optional=True, error=DataError)
    f_min_hz = check_number("minimum frequency (Hz)", f_min_hz, 0.0, lo_open=True, optional=True, error=DataError)
    f_max_hz = check_number("maximum frequency (Hz)", f_max_hz, 0.0, lo_open=True, optional=True, error=DataError)
    amplitude = check_number("amplitude", amplitude, 0.0, lo_open=True, optional=True, error=DataError)
    offset = check_number("offset", offset, error=DataError)
    n = int(round(duration_s / sample_time_s))
    if not MIN_SAMPLES <= n <= MAX_SAMPLES:
        raise ValueError(f"duration {duration_s:g} s at {sample_time_s:g} s gives {n} samples; expected {MIN_SAMPLES}..{MAX_SAMPLES}")
    if not f_min_hz < f_max_hz <= 0.5 / sample_time_s:
        raise ValueError(
            f"frequency band {f_min_hz:g}..{f_max_hz:g} Hz; expected f_min < f_max <= Nyquist {0.5 / sample_time_s:g} Hz"
        )
    t = np.arange(n) * sample_time_s
    if kind == "multisine":
        rng = np.random.default_rng(seed)
        f0 = 1.0 / duration_s
        k = np.unique(np.round(np.geomspace(max(f_min_hz, f0), f_max_hz, 24) / f0).astype(int))
        phases = rng.uniform(0, 2 * np.pi, len(k))
        v = np.sum(np.sin(2 * np.pi * np.outer(t, k * f0) + phases), axis=1)
        v = offset + amplitude * v / np.max(np.abs(v))
    elif kind == "chirp":
        v = offset + amplitude * scipy.signal.chirp(t, f_min_hz, t[-1], f_max_hz, method="logarithmic")
    else:
        levels = np.array([1.0, 0.5, -0.5, -1.0, -0.25, 0.25, 1.0, 0.0])
        idx = np.minimum((t / duration_s * len(levels)).astype(int), len(levels) - 1)
        v = levels[idx] * (abs(offset) + amplitude)
    return t, v


# --- frequency-response data ------------------------------------------------------------------

#: Column names of a frequency-response file: ``frequency_hz`` and either magnitude/phase or
#: real/imaginary part, optionally ``coherence``.
FRF_COLUMNS = ("frequency_hz", "magnitude_db", "phase_deg", "real", "imag", "coherence")
#: Points with a lower coherence are dropped (and counted in the record's warnings).
COHERENCE_MIN = 0.8
#: Fewest frequency points a response must keep.
MIN_FRF_POINTS = 5


@dataclass(frozen=True, eq=False)
class FrfRecord:
    """A measured frequency response from torque command (N m) to nut speed (rad/s).

    Attributes
    ----------
    name : str
    frequency_hz : ndarray, Hz
        Strictly increasing, > 0.
    response : ndarray of complex, (rad/s)/(N m)
    coherence : ndarray or None
    speed_rad_s : float, rad/s
        Mean nut speed of the measurement (the operating point of the linearisation).
    load_n : float, N
        Axial load during the measurement.
    dropped : int
        Points dropped for coherence below the threshold.
    warnings : tuple of str
    sample_time_s : float or None, s
        Sample time of the drive that measured it (None: the plant's ``sensor.sample_time_s``;
        0: a continuous-time response).
    """

    name: str
    frequency_hz: NDArray[np.float64]
    response: NDArray[np.complex128]
    coherence: NDArray[np.float64] | None
    speed_rad_s: float
    load_n: float
    dropped: int = 0
    warnings: tuple[str, ...] = field(default=())
    sample_time_s: float | None = None

    @property
    def n(self) -> int:
        """Number of frequency points kept."""
        return len(self.frequency_hz)

    def to_csv(self, path: str | Path) -> None:
        """Write the response as ``frequency_hz, magnitude_db, phase_deg[, coherence]``."""
        cols = {"frequency_hz": self.frequency_hz, "magnitude_db": 20 * np.log10(np.abs(self.response)),
                "phase_deg": np.degrees(np.unwrap(np.angle(self.response)))}
        if self.coherence is not None:
            cols["coherence"] = self.coherence
        data = np.column_stack(list(cols.values()))
        np.savetxt(path, data, delimiter=",", header=",".join(cols), comments="", fmt="%.17g")


def frf_from_arrays(
    name: str,
    frequency_hz: Sequence[float],
    response: Sequence[complex],
    *,
    coherence: Sequence[float] | None = None,
    speed_rad_s: float = 30.0,
    load_n: float = 0.0,
    coherence_min: float = COHERENCE_MIN,
    row_of: Sequence[int] | None = None,
    row_word: str = "row",
    column: str = "frequency_hz",
    sample_time_s: float | None = None,
) -> FrfRecord:
    """Validate a frequency response (torque command -> nut speed) into an :class:`FrfRecord`.

    Parameters
    ----------
    name : str
        Label (file name) used in messages.
    frequency_hz : sequence of float, Hz
    response : sequence of complex, (rad/s)/(N m)
    coherence : sequence of float in [0, 1], optional
        Points below ``coherence_min`` are dropped and counted.
    speed_rad_s : float, rad/s
        Nut speed at which the response was measured (operating point).
    load_n : float, N
        Axial load during the measurement.
    coherence_min : float
        Points with a lower coherence are dropped.
    sample_time_s : float, s, optional
        Sample time of the drive's measurement (None: the plant's; 0: continuous).

    Examples
    --------
    >>> import numpy as np
    >>> f = np.geomspace(1, 300, 20)
    >>> g = 1 / (2.4e-4 * 2j * np.pi * f)
    >>> frf_from_arrays("demo", f, g, coherence=np.r_[np.ones(19), 0.3]).dropped
    1
    """
    f = np.asarray(frequency_hz, float)
    g = np.asarray(response, complex)
    rows = list(row_of) if row_of is not None else list(range(len(f)))
    if f.ndim != 1 or g.shape != f.shape:
        raise DataError(f"{name}: response has shape {g.shape}; expected {f.shape} like frequency_hz")
    speed_rad_s = check_number(f"{name}: speed (rad/s)", speed_rad_s, error=DataError)
    load_n = check_number(f"{name}: load (N)", load_n, error=DataError)
    coherence_min = check_number(f"{name}: coherence threshold", coherence_min, 0.0, 1.0, hi_open=True, error=DataError)
    bad = np.flatnonzero(~np.isfinite(f) | ~np.isfinite(g))
    if bad.size:
        raise DataError(f"{name}: {row_word} {rows[bad[0]]}: not a finite number; expected finite frequency and response")
    bad = np.flatnonzero(f <= 0)
    if bad.size:
        raise DataError(f"{name}: column {column!r} {row_word} {rows[bad[0]]}: {float(f[bad[0]])!r} Hz; expected a frequency > 0")
    bad = np.flatnonzero(np.diff(f) <= 0)
    if bad.size:
        k = bad[0] + 1
        raise DataError(f"{name}: column {column!r} {row_word} {rows[k]}: {float(f[k])!r} Hz after {float(f[k - 1])!r} Hz; "
                        "expected strictly increasing frequencies")
    bad = np.flatnonzero(np.abs(g) == 0)
    if bad.size:
        raise DataError(f"{name}: {row_word} {rows[bad[0]]}: zero response; expected a magnitude > 0")
    coh = None
    dropped = 0
    warns = []
    if coherence is not None:
        coh = np.asarray(coherence, float)
        if coh.shape != f.shape:
            raise DataError(f"{name}: coherence has shape {coh.shape}; expected {f.shape} like frequency_hz")
        bad = np.flatnonzero(~np.isfinite(coh) | (coh < 0) | (coh > 1))
        if bad.size:
            raise DataError(f"{name}: column 'coherence' {row_word} {rows[bad[0]]}: {float(coh[bad[0]])!r}; expected 0..1")
        keep = coh >= coherence_min
        dropped = int(np.sum(~keep))
        if dropped:
            warns.append(f"{name}: {dropped} of {len(f)} points with coherence below {coherence_min:g} dropped")
        f, g, coh = f[keep], g[keep], coh[keep]
    if len(f) < MIN_FRF_POINTS:
        raise DataError(f"{name}: {len(f)} frequency points left (after the coherence threshold {coherence_min:g}); "
                        f"expected at least {MIN_FRF_POINTS}")
    if sample_time_s is not None and (isinstance(sample_time_s, bool) or not math.isfinite(sample_time_s)
                                      or sample_time_s < 0):
        raise DataError(f"{name}: sample time {sample_time_s!r}; expected a time >= 0 s")
    if sample_time_s and f[-1] >= 0.5 / sample_time_s:
        raise DataError(f"{name}: frequency {f[-1]:g} Hz at or above the Nyquist frequency {0.5 / sample_time_s:g} Hz "
                        f"of the {sample_time_s:g} s sample time; expected lower frequencies")
    return FrfRecord(name, f, g, coh, float(speed_rad_s), float(load_n), dropped, tuple(warns),
                     None if sample_time_s is None else float(sample_time_s))


def load_frf(
    path: str | Path,
    *,
    speed_rad_s: float = 30.0,
    load_n: float = 0.0,
    coherence_min: float = COHERENCE_MIN,
    sample_time_s: float | None = None,
) -> FrfRecord:
    """Read a frequency-response CSV (torque command -> nut speed, (rad/s)/(N m)).

    Columns: ``frequency_hz`` and ``magnitude_db, phase_deg`` (dB of (rad/s)/(N m), degrees) or
    ``real, imag``, optionally ``coherence`` (0..1). Read by :func:`prsa_ctrl.tablefile.read_table`
    (a byte-order mark, blank rows and ``#`` comment rows skipped, every cell a finite number).

    Parameters
    ----------
    path : str or Path
    speed_rad_s : float, rad/s
        Nut speed during the measurement.
    load_n : float, N
        Axial load during the measurement.
    coherence_min : float
        Points with a lower coherence are dropped.
    sample_time_s : float, s, optional
        Sample time of the drive's measurement (None: the plant's; 0: continuous).

    Returns
    -------
    FrfRecord

    Raises
    ------
    DataError
        One line naming the file, column and line of the first problem.
    """
    name = str(path)
    p = Path(path)
    if not p.is_file():
        raise DataError(f"{name}: frequency-response file not found; expected a readable CSV file")

    def check_header(header: tuple[str, ...], header_line: int) -> None:
        for h in header:
            if h not in FRF_COLUMNS:
                raise DataError(f"{name}: unknown column {h!r} (line {header_line}); expected {', '.join(FRF_COLUMNS)}")
        if len(set(header)) != len(header):
            raise DataError(f"{name}: a column appears twice in the header (line {header_line}); expected each once")
        if "frequency_hz" not in header or ({"magnitude_db", "phase_deg"} <= set(header)) == ({"real", "imag"} <= set(header)):
            raise DataError(f"{name}: header {', '.join(header)}; expected frequency_hz with magnitude_db,phase_deg "
                            "or with real,imag (one pair)")

    # the one CSV reader: BOM, comments, size and rows bounded before/while reading, finite numbers
    table = read_table(p, max_rows=MAX_SAMPLES, max_bytes=MAX_FILE_BYTES, name=name, error=DataError,
                       on_header=check_header)
    col = dict(table.columns)
    polar = {"magnitude_db", "phase_deg"} <= set(col)
    if polar:
        g = 10 ** (col["magnitude_db"] / 20) * np.exp(1j * np.radians(col["phase_deg"]))
    else:
        g = col["real"] + 1j * col["imag"]
    return frf_from_arrays(name, col["frequency_hz"], g, coherence=col.get("coherence"), speed_rad_s=speed_rad_s,
                           load_n=load_n, coherence_min=coherence_min, row_of=[int(x) for x in table.lines], row_word="line",
                           sample_time_s=sample_time_s)


def frf_from_record(
    record: Record,
    period_s: float,
    *,
    skip_periods: int = 1,
    f_max_hz: float | None = None,
    coherence_min: float = COHERENCE_MIN,
    power_floor: float = 1e-3,
) -> FrfRecord:
    """Frequency response torque command -> measured speed from a record of a periodic excitation.

    The record (e.g. a multisine on the speed setpoint with the drive's loop closed, period
    ``period_s``) is cut into whole periods after ``skip_periods`` transient ones; per period the
    FFT of the logged command and of the measured speed (the angle's backward difference) are
    taken, and at every line whose command power is above ``power_floor`` times the largest,
    the H1 estimate ``sum(conj(U) Y) / sum(|U|^2)`` and the coherence over the periods. The
    operating point is the record's mean speed and load.

    Parameters
    ----------
    record : Record
    period_s : float, s
        Period of the excitation (a whole number of samples).
    skip_periods : int
        Leading periods dropped (transient).
    f_max_hz : float, Hz, optional
        Highest line kept (default: below Nyquist).
    coherence_min : float
        Lines with a lower coherence are dropped (needs at least two periods).
    power_floor : float
        Relative command power below which a line counts as not excited.

    Returns
    -------
    FrfRecord
    """
    ts = record.sample_time_s
    n = int(round(period_s / ts))
    if not (math.isfinite(period_s) and period_s > 0) or abs(n * ts - period_s) > 1e-6 * period_s or n < 8:
        raise DataError(f"{record.name}: period {period_s!r} s; expected a whole number (>= 8) of {ts:g} s samples")
    if not (isinstance(skip_periods, int) and skip_periods >= 0):
        raise DataError(f"{record.name}: skip_periods = {skip_periods!r}; expected an integer >= 0")
    speed = np.concatenate([[np.nan], record.speed_rad_s])  # sample k: (angle_k - angle_k-1) / ts
    m = (record.n - 1) // n - skip_periods  # sample 0 has no speed: start at 1
    if m < 2:
        raise DataError(f"{record.name}: {record.n} samples hold fewer than {skip_periods + 2} periods of {period_s:g} s; "
                        "expected a longer record (two periods at least after the skipped ones)")
    start = 1 + skip_periods * n
    u = record.torque_command_n_m[start:start + m * n].reshape(m, n)
    y = speed[start:start + m * n].reshape(m, n)
    uf, yf = np.fft.rfft(u, axis=1)[:, 1:], np.fft.rfft(y, axis=1)[:, 1:]
    f = np.arange(1, uf.shape[1] + 1) / period_s
    suu, syy = np.sum(np.abs(uf) ** 2, 0), np.sum(np.abs(yf) ** 2, 0)
    suy = np.sum(np.conj(uf) * yf, 0)
    keep = (suu > power_floor * np.max(suu)) & (f < 0.5 / ts) & (f <= (f_max_hz or np.inf))
    if not np.any(keep):
        raise DataError(f"{record.name}: no excited line; expected a periodic excitation of period {period_s:g} s")
    coh = np.abs(suy[keep]) ** 2 / (suu[keep] * syy[keep])
    return frf_from_arrays(record.name, f[keep], suy[keep] / suu[keep], coherence=coh,
                           speed_rad_s=float(np.mean(speed[start:start + m * n])),
                           load_n=float(np.mean(record.axial_load_n[start:start + m * n])),
                           coherence_min=coherence_min, sample_time_s=ts)
