"""Speed measurements of the sampled drive, as pluggable blocks of the one sampled-loop law.

The drive samples the quantised encoder angle once per controller sample. A measurement block
turns that angle into the speed the PID acts on (and, for an observer, an estimate of the load
torque). Each block is written in CasADi so the whole per-sample law of
:mod:`prsa_ctrl.sim.engine` (quantise, measure, PID, one-sample delay, integrate the plant) is
one compiled function, whichever measurement is plugged in.

A block has a memory vector (carried from sample to sample) and two steps:

``update(mem, theta_q, theta_prev_q) -> (speed rad/s, load torque estimate N m, mem)``
    at the sampling instant, with the new and previous quantised angles (rad);
``predict(mem, u_applied) -> mem``
    over the sample, knowing the torque command applied during it (N m).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import casadi as ca

from ..options import check_number
from .friction import FrictionFeedforward

if TYPE_CHECKING:
    from .estimator import KFDesign
    from ..plant.plantfile import Plant

__all__ = ["SpeedMeasurement", "EncoderDifference", "KalmanSpeed", "measurement_for", "PositionLoop",
           "POSITION_SENSORS"]

#: What a position loop can measure: the nut angle from the motor encoder (rad) or the screw
#: position from a linear scale on the screw (m).
POSITION_SENSORS = ("nut_angle", "screw_position")


class SpeedMeasurement:
    """Interface of a speed-measurement block (see the module docstring)."""

    #: Short name stored in the run's ``info``.
    name: str = ""
    #: Names of the memory entries (they become state rows of a sampled run).
    memory_names: tuple[str, ...] = ()
    #: Whether the block estimates the load torque (needed by load feed-forward, ``kff > 0``).
    estimates_load: bool = False

    def initial(self, theta: float, omega: float, torque: float) -> list[float]:
        """Memory at a steady state with nut angle ``theta`` (rad), speed ``omega`` (rad/s) and
        torque ``torque`` (N m, motor torque equal to the load torque)."""
        raise NotImplementedError

    def update(self, mem: ca.SX, theta_q: ca.SX, theta_prev_q: ca.SX) -> tuple[Any, Any, ca.SX]:
        raise NotImplementedError

    def predict(self, mem: ca.SX, u_applied: ca.SX) -> ca.SX:
        raise NotImplementedError

    def key(self) -> tuple:
        """Identity of the compiled law (blocks with equal keys share one CasADi function)."""
        raise NotImplementedError


@dataclass(frozen=True)
class EncoderDifference(SpeedMeasurement):
    """The drive's standard measurement: backward difference of the quantised angle over one
    sample, through a first-order low-pass of time constant ``filter_s`` (exact discretisation
    ``w_f <- a w_f + (1 - a) w_diff`` with ``a = exp(-Ts / filter_s)``).

    Parameters
    ----------
    ts : float, s
        Controller sample time.
    filter_s : float, s
        Speed-filter time constant.
    """

    ts: float
    filter_s: float
    name = "encoder"
    memory_names = ("speed_filtered",)

    def initial(self, theta: float, omega: float, torque: float) -> list[float]:
        return [omega]

    def update(self, mem, theta_q, theta_prev_q):
        alpha = math.exp(-self.ts / self.filter_s)
        w_f = alpha * mem[0] + (1 - alpha) * (theta_q - theta_prev_q) / self.ts
        return w_f, 0.0, ca.vertcat(w_f)

    def predict(self, mem, u_applied):
        return mem

    def key(self) -> tuple:
        return ("encoder", self.ts, self.filter_s)


@dataclass(frozen=True, eq=False)
class KalmanSpeed(SpeedMeasurement):
    """Steady-state Kalman filter of :func:`prsa_ctrl.drive.estimator.design_kf`: state
    ``[angle rad, speed rad/s, motor torque N m, load torque N m]``, updated with the quantised
    angle and propagated with the applied command.

    Started in steady state with the design's steady-state covariance, filterpy's
    predict/update recursion keeps that covariance and gain, so this fixed-gain form is the
    same filter (tested against filterpy).
    """

    design: "KFDesign"
    name = "kf"
    memory_names = ("kf_angle", "kf_speed", "kf_motor_torque", "kf_load_torque")
    estimates_load = True

    def initial(self, theta: float, omega: float, torque: float) -> list[float]:
        return [theta, omega, torque, torque]

    def update(self, mem, theta_q, theta_prev_q):
        k = self.design.K.ravel()
        innov = theta_q - mem[0]
        post = ca.vertcat(*[mem[i] + float(k[i]) * innov for i in range(4)])
        return post[1], post[3], post

    def predict(self, mem, u_applied):
        f, g = self.design.F, self.design.G.ravel()
        return ca.vertcat(*[sum(float(f[r, c]) * mem[c] for c in range(4)) + float(g[r]) * u_applied
                            for r in range(4)])

    def key(self) -> tuple:
        d = self.design
        return ("kf", d.ts, tuple(d.K.ravel()), tuple(d.F.ravel()), tuple(d.G.ravel()))


def measurement_for(plant: "Plant", kind: "str | SpeedMeasurement", kf: "KFDesign | None" = None) -> SpeedMeasurement:
    """The measurement block named ``kind`` for ``plant``.

    Parameters
    ----------
    plant : Plant
    kind : {"encoder", "kf"} or SpeedMeasurement
        ``"encoder"``: filtered backward difference (the drive's default); ``"kf"``: the Kalman
        filter ``kf`` (default :func:`prsa_ctrl.drive.estimator.design_kf` of the plant).
    kf : KFDesign, optional
    """
    if isinstance(kind, SpeedMeasurement):
        return kind
    if kind == "encoder":
        return EncoderDifference(plant.sample_time_s, plant.speed_filter_s)
    if kind == "kf":
        if kf is None:
            from .estimator import design_kf

            kf = design_kf(plant)
        if abs(kf.ts - plant.sample_time_s) > 1e-12 * plant.sample_time_s:
            raise ValueError(f"Kalman filter sample time {kf.ts} s differs from the plant's {plant.sample_time_s} s")
        return KalmanSpeed(kf)
    raise ValueError(f"measurement = {kind!r}; expected 'encoder', 'kf' or a SpeedMeasurement")



@dataclass(frozen=True)
class PositionLoop:
    """The position loop of the drive, an outer block of the one sampled-loop law.

    Every ``rate``-th controller sample (the position-loop sample ``Tp = rate Ts``) it reads the
    position, compares it with the motion profile's position and computes the speed reference
    of the speed PI, held until its next sample::

        e      = (p_ref - p_meas) / a                      position error in nut radians
        I     <- I + Tp ki e                               (PI only)
        w_ref  = kv e + I + kvff v_ref / a                 nut speed reference, rad/s
        tau_ff = kaff J a_ref / a (+ tau_f(v_ref / a))     torque feed-forward, N m

    with ``a`` the lead per radian (m/rad; ``a = 1`` when the nut angle itself is the loop's
    unit), ``J`` :attr:`Plant.reflected_inertia_kg_m2` and ``p_ref, v_ref, a_ref`` the profile's
    position (m), speed (m/s) and acceleration (m/s^2). Expressing the error in nut radians
    makes ``kv`` the vendor's ``Kv`` [1/s] whichever position is measured.

    Parameters
    ----------
    kv : float, 1/s
        Position gain (``Kv``): nut speed reference per nut-angle error.
    ki : float, 1/s^2
        Integral gain of a position PI (0: P).
    kvff : float
        Velocity feed-forward gain (dimensionless, 1 = full).
    kaff : float
        Acceleration (torque) feed-forward gain (dimensionless, 1 = the reflected inertia).
    measured : {"nut_angle", "screw_position"}
        ``nut_angle``: the quantised motor encoder (the speed loop's sensor);
        ``screw_position``: a linear scale on the screw of resolution ``scale_resolution_m``,
        which sees the thread-contact deflection the encoder does not.
    rate : int
        Position-loop sample time in controller samples (1 = every sample).
    delay : int
        The position loop's own computation delay in position-loop samples (0..8): the speed
        reference and torque feed-forward computed at one position-loop sample are applied from
        the ``delay``-th next one on (a line of ``delay`` pending pairs, shifted at each
        position-loop sample); 0 applies them at once.
    scale_resolution_m : float, m
        Resolution of the linear scale (``measured="screw_position"`` only).
    friction : FrictionFeedforward, optional
        Friction feed-forward ``tau_f`` at the profile's nut speed ``v_ref / a``
        (:class:`~prsa_ctrl.drive.friction.FrictionFeedforward`, e.g. ``from_plant(plant, load)``);
        None: none.

    Examples
    --------
    >>> PositionLoop(kv=100.0, kvff=1.0).memory_names
    ('position_integral', 'speed_reference', 'torque_feedforward', 'position_error')
    """

    kv: float
    ki: float = 0.0
    kvff: float = 1.0
    kaff: float = 0.0
    measured: str = "nut_angle"
    rate: int = 1
    scale_resolution_m: float = 1e-7
    friction: "FrictionFeedforward | None" = None
    delay: int = 0
    name = "position"
    #: Per-sample inputs of the block: position (loop unit), speed (m/s), acceleration (m/s^2)
    #: of the profile, 1 at a position-loop sample (else 0), then kv, ki, kvff, kaff (parameters,
    #: so that one compiled law serves every gain set).
    n_inputs = 8

    def __post_init__(self) -> None:
        check_number("PositionLoop kv", self.kv, 0.0, unit="1/s")
        check_number("PositionLoop ki", self.ki, 0.0, unit="1/s^2")
        check_number("PositionLoop kvff", self.kvff, 0.0, 2.0)
        check_number("PositionLoop kaff", self.kaff, 0.0, 2.0)
        if self.kv == 0 and self.ki == 0:
            raise ValueError("PositionLoop kv = ki = 0; expected a position gain kv > 0 (or ki > 0)")
        if self.measured not in POSITION_SENSORS:
            raise ValueError(f"PositionLoop measured = {self.measured!r}; expected one of {', '.join(POSITION_SENSORS)}")
        if isinstance(self.rate, bool) or not isinstance(self.rate, int) or not 1 <= self.rate <= 1000:
            raise ValueError(f"PositionLoop rate = {self.rate!r}; expected an integer number of controller samples "
                             "in [1, 1000]")
        if isinstance(self.delay, bool) or not isinstance(self.delay, int) or not 0 <= self.delay <= 8:
            raise ValueError(f"PositionLoop delay = {self.delay!r}; expected an integer number of position-loop samples "
                             "in [0, 8]")
        check_number("PositionLoop scale_resolution_m", self.scale_resolution_m, 0.0, 1e-3, unit="m", lo_open=True)
        if self.friction is not None and not isinstance(self.friction, FrictionFeedforward):
            raise ValueError(f"PositionLoop friction = {self.friction!r}; expected a FrictionFeedforward or None")

    def unit_m(self, lead_per_rad: float) -> float:
        """Metres of screw travel per unit of the measured position (``a`` for the nut angle in
        rad, 1 for the screw position in m)."""
        return lead_per_rad if self.measured == "nut_angle" else 1.0

    @property
    def memory_names(self) -> tuple[str, ...]:
        """The block's memory: integral, held speed reference and torque feed-forward, held
        error, then (with a delay) the pending speed references and feed-forwards, newest first."""
        pend = tuple(f"pending_{k}_{i + 1}" for i in range(self.delay) for k in ("speed_reference", "torque_feedforward"))
        return ("position_integral", "speed_reference", "torque_feedforward", "position_error") + pend

    def initial(self) -> list[float]:
        """Memory at rest on the profile's start (no error, no integral, no reference)."""
        return [0.0] * len(self.memory_names)

    def update(self, mem, p_meas, inputs, ts: float, lead_per_rad: float, inertia: float):
        """One controller sample: ``(speed reference rad/s, torque feed-forward N m, memory)``.

        ``p_meas`` in the measured unit (rad or m), ``inputs`` the block's per-sample inputs,
        ``ts`` the controller sample time (s), ``lead_per_rad`` (m/rad), ``inertia`` (kg m^2).
        """
        a = lead_per_rad
        p_ref, v_ref, acc_ref, active = inputs[0], inputs[1], inputs[2], inputs[3]
        kv, ki, kvff, kaff = inputs[4], inputs[5], inputs[6], inputs[7]
        e_rad = (p_ref - p_meas) * (self.unit_m(a) / a)
        integral = mem[0] + active * (self.rate * ts) * ki * e_rad
        w_ref = kv * e_rad + integral + kvff * v_ref / a
        tau_ff = kaff * inertia * acc_ref / a
        if self.friction is not None:
            tau_ff = tau_ff + self.friction.symbolic(v_ref / a)
        pend = []
        if self.delay:  # the line of pending outputs: the oldest is applied, the new one enters
            line = [(mem[4 + 2 * i], mem[5 + 2 * i]) for i in range(self.delay)]
            new = [(w_ref, tau_ff)] + line[:-1]
            w_ref, tau_ff = line[-1]
            pend = [ca.if_else(active > 0.5, nw, old) for (nw_, nt_), (ow_, ot_) in zip(new, line)
                    for nw, old in ((nw_, ow_), (nt_, ot_))]
        w_ref = ca.if_else(active > 0.5, w_ref, mem[1])
        tau_ff = ca.if_else(active > 0.5, tau_ff, mem[2])
        e_keep = ca.if_else(active > 0.5, e_rad, mem[3])
        return w_ref, tau_ff, ca.vertcat(integral, w_ref, tau_ff, e_keep, *pend)

    def key(self) -> tuple:
        return ("position", self.measured, self.rate, self.scale_resolution_m,
                None if self.friction is None else self.friction.key(), self.delay)

    @property
    def gains(self) -> list[float]:
        """``[kv, ki, kvff, kaff]``, the per-sample gain inputs."""
        return [float(self.kv), float(self.ki), float(self.kvff), float(self.kaff)]
