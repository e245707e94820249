"""The drive law as plain numbers: the dataclasses :func:`prsa_ctrl.io.codegen.drive_law` fills
and the code writers (:mod:`prsa_ctrl.io.codetext`) read."""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["DriveLaw", "PositionLaw", "FilterSpec", "Biquad"]

Biquad = tuple[float, float, float, float, float]


@dataclass(frozen=True)
class FilterSpec:
    """A loop filter as the generated code's coefficient function recomputes it.

    Attributes
    ----------
    description : str
        Kind, parameters and discretisation, one line.
    num, den : tuple of float
        ``(n2, n1, n0)``, ``(d2, d1, d0)`` of ``H(s)``, s in rad/s.
    tustin : bool
        True: Tustin, ``K = w0/tan(w0 Ts/2)`` with ``w0 = 2 pi prewarp_hz`` (``prewarp_hz = 0``:
        ``K = 2/Ts``); False (ZOH, matched): the code keeps the exported coefficients.
    prewarp_hz : float, Hz
    """

    description: str
    num: tuple[float, float, float]
    den: tuple[float, float, float]
    tustin: bool
    prewarp_hz: float


@dataclass(frozen=True)
class PositionLaw:
    """The position loop's numbers (see :class:`prsa_ctrl.drive.measurement.PositionLoop`).

    Attributes
    ----------
    measured : {"nut_angle", "screw_position"}
    rate : int
        Position-loop sample time in controller samples.
    kv : float, 1/s
    ki : float, 1/s^2
    kvff, kaff : float
        Velocity and acceleration feed-forward gains (dimensionless).
    lead_m_per_rad : float, m/rad
    inertia_kg_m2 : float, kg m^2
        Reflected inertia ``J`` of the acceleration feed-forward.
    unit_m : float
        Metres of screw travel per unit of the measured position (lead per rad, or 1 for m).
    err_to_rad : float
        Nut radians per unit of the measured position's error (1, or 1/lead).
    per_count : float
        Measured unit per count: rad per encoder count, or the scale's resolution in m.
    friction : tuple of float or None
        Friction feed-forward ``(C+, C-, S+, S-, w_s, V+, V-, gain)``
        (:meth:`prsa_ctrl.drive.friction.FrictionFeedforward.key`), or None.
    delay : int
        The position loop's computation delay in position-loop samples (its outputs wait in a
        line of that many pending pairs; 0: applied at once).
    """

    measured: str
    rate: int
    kv: float
    ki: float
    kvff: float
    kaff: float
    lead_m_per_rad: float
    inertia_kg_m2: float
    unit_m: float
    err_to_rad: float
    per_count: float
    friction: tuple[float, ...] | None = None
    delay: int = 0


@dataclass(frozen=True)
class DriveLaw:
    """Every number of the sampled drive's per-sample law (SI; see the module docstring).

    Attributes
    ----------
    ts : float, s
    torque_limit_n_m : float, N m
    rad_per_count : float, rad
    speed_filter_a : float
        ``a = exp(-Ts/tau_w)`` of the drive's speed filter.
    kp, ki, kd, tf : float
        Speed PI(D) in N m s/rad, N m/rad, N m s^2/rad, s.
    torque_ff_n_m : float, N m
        Constant torque added to the command.
    speed_biquads, torque_biquads : tuple of (b0, b1, b2, a1, a2)
        Filters on the measured speed and on the torque command, in order.
    position : PositionLaw or None
    delay_samples : {0, 1}
        1: the step returns the command computed at the previous sample (the simulator's
        one-sample computation delay); 0: the command just computed.
    setpoint_weight : float
        2-DOF weight ``b`` of the speed reference in the proportional term,
        ``u = kp (b w_ref - w) + I ...`` (1: the 1-DOF law; see :mod:`prsa_ctrl.io.export`).
    plant : str
        Plant name (for the header comment; made inert in every format it reaches).
    speed_filter_specs, torque_filter_specs : tuple of FilterSpec
        The continuous filters behind the biquads and their discretisation (for the code's
        coefficient function and the headers); empty for a law built by hand.
    assumptions : tuple of (str, str, str)
        ``(what, value, source)`` of every plant value the gains depend on (headers;
        :func:`plant_assumptions`).
    """

    ts: float
    torque_limit_n_m: float
    rad_per_count: float
    speed_filter_a: float
    kp: float
    ki: float
    kd: float
    tf: float
    torque_ff_n_m: float = 0.0
    speed_biquads: tuple[Biquad, ...] = ()
    torque_biquads: tuple[Biquad, ...] = ()
    position: PositionLaw | None = None
    delay_samples: int = 1
    setpoint_weight: float = 1.0
    plant: str = ""
    speed_filter_specs: tuple[FilterSpec, ...] = ()
    torque_filter_specs: tuple[FilterSpec, ...] = ()
    assumptions: tuple[tuple[str, str, str], ...] = ()

    @property
    def beta(self) -> float:
        """Derivative-filter pole ``exp(-Ts/tf)``."""
        return math.exp(-self.ts / self.tf)

    @property
    def anti_windup_per_s(self) -> float:
        """``k_aw = ki/max(kp, 1e-9)`` (1/s)."""
        return self.ki / max(self.kp, 1e-9)
