"""Constants and option lists shared by the whole toolkit (light: no heavy imports).

Every default that more than one module needs lives here once, with its unit and its source.
"""

from __future__ import annotations

import math
import numbers
from typing import Any, Callable, Mapping

from .textsafe import quote

__all__ = [
    "SETPOINT_RPM",
    "SETPOINT_RAD_S",
    "RAD_S_PER_RPM",
    "SPEED_MAX_RPM",
    "OBJECTIVES",
    "FIDELITIES",
    "CONTROLLERS",
    "AGGREGATES",
    "ESTIMATORS",
    "DERIVATIVE_FILTER_SAMPLES",
    "RIGID_RELATIVE_ERROR",
    "MS_MAX_DEFAULT",
    "PEAK_BOUND_RANGE",
    "check_peak_bound",
    "check_number",
    "is_number",
    "rpm_to_rad_s",
    "rad_s_to_rpm",
    "FREQUENCY_UNITS",
    "DEFAULT_FREQUENCY_UNIT",
    "MOTOR_COORDINATES",
    "LOAD_COORDINATES",
]


def rpm_to_rad_s(rpm: float) -> float:
    """Convert a speed in rpm to rad/s: the toolkit's one definition of the rpm factor (2 pi / 60;
    :data:`RAD_S_PER_RPM` is this of 1 rpm).

    Parameters
    ----------
    rpm : float, rpm

    Examples
    --------
    >>> round(rpm_to_rad_s(300.0), 4)
    31.4159
    """
    return rpm * 2.0 * math.pi / 60.0


def rad_s_to_rpm(rad_s: float) -> float:
    """Convert a speed in rad/s to rpm (the inverse of :func:`rpm_to_rad_s`).

    Parameters
    ----------
    rad_s : float, rad/s
    """
    return rad_s * 60.0 / (2.0 * math.pi)


#: The paper's operating speed, rpm (paper text: "300 rpm").
SETPOINT_RPM = 300.0
#: The same in rad/s (31.4159...).
SETPOINT_RAD_S = rpm_to_rad_s(SETPOINT_RPM)

#: One rpm in rad/s (gains "per rpm" multiply the SI gain by this).
RAD_S_PER_RPM = rpm_to_rad_s(1.0)
#: Highest nut speed the toolkit accepts, rpm (the tuner's limit: a scene's setpoint, an FRF's
#: operating point, an excitation design): roller-screw catalogues rate nut speeds up to ~5000
#: rpm (d n limits of the rolling contacts); the contact models are not validated beyond.
SPEED_MAX_RPM = 6000.0

#: The coordinates a screw-driven plant's numbers are in (reports and JSON say them).
MOTOR_COORDINATES = "motor (angle rad, torque N m)"
#: The coordinates of a linear axis (and of a log described in load coordinates).
LOAD_COORDINATES = "load (position m, force N)"

#: Units of the frequency axes of the Bode and sensitivity figures -> factor from rad/s
#: (:mod:`prsa_ctrl.plots.loop`; ``prsa-plot`` and ``prsa-tune --plots``: ``--frequency-unit``).
#: The data stay in rad/s (SI); only the axes and their labels change.
FREQUENCY_UNITS = {"Hz": 1.0 / (2.0 * math.pi), "rad/s": 1.0}
#: Default unit of those axes (a drive's parameters and a spectrum analyser's axis are in Hz).
DEFAULT_FREQUENCY_UNIT = "Hz"

#: Integral error criteria the tuner minimises (see :func:`prsa_ctrl.tune_pid`).
OBJECTIVES = ("ie", "iae", "itae", "ise")
#: Model fidelities, cheapest first (see :mod:`prsa_ctrl.plant.model`).
FIDELITIES = ("rigid", "compliant", "multi-roller")
#: Speed-controller structures.
CONTROLLERS = ("pi", "pid")
#: How a scene combines the metrics of several load steps.
AGGREGATES = ("sum", "worst")
#: Speed measurements of the sampled drive: the filtered encoder difference, or a Kalman filter.
ESTIMATORS = ("none", "kf")

#: Derivative-filter time constant of the tuned PID, in controller samples: ``tf = 4 Ts``
#: (a design choice: the filter corner stays a factor 4 below the sampling rate).
DERIVATIVE_FILTER_SAMPLES = 4

#: Nut-speed error of the rigid fidelity relative to the peak drop on the paper's load step
#: (sampled loop), measured against the multi-roller model by ``prsa-bench`` (fidelity ladder:
#: 0.101 rad/s of 3.64 rad/s = 2.78 %, rounded up). A scene whose ``accuracy`` is at least this
#: may be verified on the rigid model.
RIGID_RELATIVE_ERROR = 0.028

#: Default bound on the peak sensitivity Ms = max|1/(1 + L)| (Astrom-Hagglund's robust
#: range 1.2-2.0; 1.4 keeps a gain margin of at least 3.5 and a phase margin of at least 41 deg).
MS_MAX_DEFAULT = 1.4
#: Largest position-loop sample time of a cascade, in speed-loop samples (``[move]
#: position_rate``; the multi-rate cascade model lifts the loop to N x N matrices, and the joint
#: NLP's constraints grow as N^4: N = 4 tunes in about 30 s, N = 8 did not finish in minutes).
POSITION_RATE_MAX = 4
#: Largest computation delay of the position loop, in position-loop samples (``[move]
#: position_delay_samples``: the speed reference computed at one position-loop sample is applied
#: that many position-loop samples later).
POSITION_DELAY_MAX = 4
#: Units of a position gain ``kv_max`` and their factor to 1/s: ``(m/min)/mm`` is the speed in
#: m/min per mm of following error (1 (m/min)/mm = 1000/60 1/s = 16.67 1/s).
KV_UNITS: Mapping[str, float] = {"1/s": 1.0, "(m/min)/mm": 1000.0 / 60.0}


def parse_kv(value: Any, where: str = "kv_max") -> float:
    """A position gain typed with its unit, in 1/s.

    Parameters
    ----------
    value : str
        ``"<number> <unit>"`` with the unit one of :data:`KV_UNITS` (``"3 (m/min)/mm"``,
        ``"50 1/s"``); a finite number > 0.
    where : str
        The value's name in the error message.

    Returns
    -------
    float, 1/s

    Raises
    ------
    ValueError
        One line naming the value as typed and what was expected.

    Examples
    --------
    >>> round(parse_kv("3 (m/min)/mm"), 6), parse_kv("50 1/s")
    (50.0, 50.0)
    """
    expected = ("expected a position gain > 0 with its unit, e.g. \"3 (m/min)/mm\" or \"50 1/s\" (units: "
                + ", ".join(KV_UNITS) + ")")
    if not isinstance(value, str):
        raise ValueError(f"{where} = {value!r}; {expected}")
    parts = value.strip().split(None, 1)
    unit = parts[1].replace(" ", "") if len(parts) == 2 else ""
    try:
        number = float(parts[0]) if parts else math.nan
    except ValueError:
        number = math.nan
    if unit not in KV_UNITS or not math.isfinite(number) or not number > 0 \
            or not math.isfinite(number * KV_UNITS[unit]):
        raise ValueError(f"{where} = {value!r}; {expected}")
    return number * KV_UNITS[unit]



def is_number(v: Any) -> bool:
    """True for a real number (int or float, NumPy ones too), False for bools and anything else."""
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and type(v).__name__ != "bool_"


def _bound_text(lo: float, hi: float, lo_open: bool, hi_open: bool, unit: str) -> str:
    parts = []
    if math.isfinite(lo):
        parts.append(f"{'>' if lo_open else '>='} {lo:g}")
    if math.isfinite(hi):
        parts.append(f"{'<' if hi_open else '<='} {hi:g}")
    text = " and ".join(parts)
    if not text:
        return f"({unit})" if unit else ""
    return " ".join(x for x in (text, unit) if x)


def check_number(name: str, value: Any, lo: float = -math.inf, hi: float = math.inf, *, unit: str = "",
                 lo_open: bool = False, hi_open: bool = False, integer: bool = False, optional: bool = False,
                 error: Callable[[str], Exception] = ValueError, typed: str | None = None,
                 expected: str | None = None) -> Any:
    """The one number validator: ``value`` as a checked float (or int), or one line naming it.

    Every module that takes a number from a user (a file, a flag, an argument) checks it here,
    so that every refusal reads the same: ``NAME = VALUE; expected a finite number > LO and
    <= HI UNIT``, with the value as typed.

    Parameters
    ----------
    name : str
        The value's name as the user knows it (a key, a flag, an argument; may carry its file).
    value : int or float (NumPy ones too) or None
        The value. Bools, strings and anything else are refused.
    lo, hi : float
        Bounds, in ``unit``; an infinite bound is not checked nor named.
    unit : str
        Unit of the bounds, shown after them.
    lo_open, hi_open : bool
        Exclude the bound (``>`` / ``<``) instead of including it (``>=`` / ``<=``).
    integer : bool
        Accept integers only (``3.0`` is not one) and return an ``int``.
    optional : bool
        Accept ``None`` and return it.
    error : exception class
        Raised with the one-line message (:class:`ValueError` or one of its subclasses in
        :mod:`prsa_ctrl.errors`).
    typed : str, optional
        The value as the user typed it, if it was text (a flag's argument); shown instead of
        ``repr(value)``.
    expected : str, optional
        What was expected, in words, instead of the description made from the bounds
        (``"a sample time > 0 s or None (continuous)"``).

    Returns
    -------
    float or int or None

    Raises
    ------
    ValueError (or ``error``)
        ``"NAME = VALUE; expected ..."``.

    Examples
    --------
    >>> check_number("ts", 0.00025, 0.0, 1e3, unit="s", lo_open=True)
    0.00025
    >>> check_number("ts", 0, 0.0, 1e3, unit="s", lo_open=True)
    Traceback (most recent call last):
    ...
    ValueError: ts = 0; expected a finite number > 0 and <= 1000 s
    >>> check_number("count", 2.5, 1, integer=True)
    Traceback (most recent call last):
    ...
    ValueError: count = 2.5; expected an integer >= 1
    """
    if value is None and optional:
        return None
    bounds = _bound_text(lo, hi, lo_open, hi_open, unit)
    expected = expected or (("None or " if optional else "") + ("an integer" if integer else "a finite number")
                            + (f" {bounds}" if bounds else ""))
    ok = is_number(value) and (isinstance(value, numbers.Integral) if integer else True)
    if ok:
        try:
            v = float(value)
        except OverflowError:  # an int beyond the float range
            v = math.inf if value > 0 else -math.inf
        ok = math.isfinite(v) and (v > lo if lo_open else v >= lo) and (v < hi if hi_open else v <= hi)
    if not ok:
        if typed is None:
            typed = quote(value)
        raise error(f"{name} = {typed}; expected {expected}")
    return int(value) if integer else v


#: Open interval in which a peak bound (Ms, Mt) is accepted: at 1 no controller is feasible,
#: above 10 the bound no longer means robustness.
PEAK_BOUND_RANGE = (1.0, 10.0)


def check_peak_bound(name: str, value, *, optional: bool = False) -> float | None:
    """A peak bound (Ms, Mt) as a float in :data:`PEAK_BOUND_RANGE`, or a ValueError naming it.

    Parameters
    ----------
    name : str
        The argument's name, used in the message.
    value : float or None
        The bound, dimensionless.
    optional : bool
        Accept ``None`` (no bound).

    Examples
    --------
    >>> check_peak_bound("ms_max", 1.4)
    1.4
    >>> check_peak_bound("ms_max", 0.9)
    Traceback (most recent call last):
    ...
    ValueError: ms_max = 0.9; expected a number in (1, 10)
    """
    lo, hi = PEAK_BOUND_RANGE
    if value is None and optional:
        return None
    expected = f"a number in ({lo:g}, {hi:g})" + (" or None" if optional else "")
    try:
        return check_number(name, value, lo, hi, lo_open=True, hi_open=True)
    except ValueError:
        raise ValueError(f"{name} = {value!r}; expected {expected}") from None
