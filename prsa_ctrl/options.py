"""Constants and option lists shared by the whole toolkit (light: no heavy imports).

Every default that more than one module needs lives here once, with its unit and its source.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

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
    "rpm_to_rad_s",
    "rad_s_to_rpm",
    "FREQUENCY_UNITS",
    "DEFAULT_FREQUENCY_UNIT",
]

#: The paper's operating speed, rpm (paper text: "300 rpm").
SETPOINT_RPM = 300.0
#: The same in rad/s (31.4159...).
SETPOINT_RAD_S = SETPOINT_RPM * 2.0 * math.pi / 60.0

#: One rpm in rad/s (gains "per rpm" multiply the SI gain by this).
RAD_S_PER_RPM = 2.0 * math.pi / 60.0
#: Highest nut speed the toolkit accepts, rpm (the tuner's limit: a scene's setpoint, an FRF's
#: operating point, an excitation design): roller-screw catalogues rate nut speeds up to ~5000
#: rpm (d n limits of the rolling contacts); the contact models are not validated beyond.
SPEED_MAX_RPM = 6000.0

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
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (lo < float(value) < hi):
        raise ValueError(f"{name} = {value!r}; expected {expected}")
    return float(value)


def rpm_to_rad_s(rpm: float) -> float:
    """Convert a speed in rpm to rad/s.

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
    """Convert a speed in rad/s to rpm.

    Parameters
    ----------
    rad_s : float, rad/s
    """
    return rad_s * 60.0 / (2.0 * math.pi)
