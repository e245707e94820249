"""Constants and option lists shared by the whole toolkit (light: no heavy imports).

Every default that more than one module needs lives here once, with its unit and its source.
"""

from __future__ import annotations

import math

__all__ = [
    "SETPOINT_RPM",
    "SETPOINT_RAD_S",
    "RAD_S_PER_RPM",
    "OBJECTIVES",
    "FIDELITIES",
    "CONTROLLERS",
    "AGGREGATES",
    "ESTIMATORS",
    "DERIVATIVE_FILTER_SAMPLES",
    "RIGID_RELATIVE_ERROR",
    "rpm_to_rad_s",
    "rad_s_to_rpm",
]

#: The paper's operating speed, rpm (paper text: "300 rpm").
SETPOINT_RPM = 300.0
#: The same in rad/s (31.4159...).
SETPOINT_RAD_S = SETPOINT_RPM * 2.0 * math.pi / 60.0

#: One rpm in rad/s (gains "per rpm" multiply the SI gain by this).
RAD_S_PER_RPM = 2.0 * math.pi / 60.0

#: Integral error criteria the tuner minimises (see :func:`prsa_ctrl.tune_pid`).
OBJECTIVES = ("ie", "iae", "itae", "ise")
#: Model fidelities, cheapest first (see :mod:`prsa_ctrl.model`).
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
