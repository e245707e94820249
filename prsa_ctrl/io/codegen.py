"""The complete discrete controller of the drive as code: dependency-free C and IEC 61131-3 ST.

:func:`drive_law` collects, as plain numbers, everything the sampled drive of
:mod:`prsa_ctrl.sim.engine` computes at each controller sample (``simulation._sample_law``):
the encoder-difference speed measurement with its first-order filter, the speed-measurement
biquads, the speed PI(D) with back-calculation anti-windup, the torque-command biquads, the
torque limit and the one-sample computation delay, and (for a cascade) the position loop with
velocity and acceleration feed-forward. :func:`c_code` writes it as a C99 header and source
(``float`` or ``double``), :func:`st_code` as an IEC 61131-3 Structured Text FUNCTION_BLOCK
(``REAL`` or ``LREAL``); :func:`export_code` writes either, chosen by the file suffix (``.c``
writes the source and its header beside it, ``.st`` the function block).

Per sample ``k`` (time ``k Ts``), with ``n[k]`` the encoder count (``q = 2 pi/counts_per_rev``
rad per count)::

    w_raw = a w_raw' + (1 - a) ((n[k] - n[k-1]) q) / Ts          a = exp(-Ts/tau_w), drive speed filter
    w     = speed-measurement biquads of w_raw (in order)           y = b0 x + b1 x1 + b2 x2 - a1 y1 - a2 y2
    d     = beta d' + (1 - beta) (w - w') / Ts                       beta = exp(-Ts/tf)   (kd = 0: unused)
    position loop (cascade, every rate-th sample, held between):
      e_p    = (p_ref/unit - (m[k] - m0) r) err_to_rad             m: position counts (encoder or scale), r: m or rad per count
      I_p    = I_p + Tp kip e_p
      w_ref  = kv e_p + I_p + kvff v_ref / lead
      tau_p  = (kaff J) acc_ref / lead (+ tau_f(vel_ref / lead), the friction feed-forward if any)
    e     = w_ref - w
    u     = kp (b w_ref - w) + I - kd d + (tau_ff + tau_p)           b: 2-DOF setpoint weight (1: kp e)
    us    = min(max(u, -T_max), T_max)
    I     = I + Ts (ki e + k_aw (us - u))                            k_aw = ki/max(kp, 1e-9)
    uf    = min(max(torque-command biquads of us, -T_max), T_max)
    return the command stored at the previous sample (one-sample computation delay), store uf

(``'`` marks the value of the previous sample.) By default (``differences="counts"``) the speed
and position differences are taken in integer counts, so the code keeps its resolution over any
travel also in ``float``; the simulator takes them from the angles in rad, which differs by
round-off only (measured 6.2e-13 of the largest command in double on the paper move scene).
``differences="angle"`` writes the simulator's own operations: in double the generated code
then reproduces the simulator's command bit for bit (compiled with ``-ffp-contract=off``).

:class:`ReferenceLaw` runs the same law in Python exactly as the simulator writes it (angles in
rad, the simulator's order of operations): it reproduces a recorded run's torque command
bit for bit or to round-off (:func:`replay_inputs` takes the inputs from a run).

Examples
--------
>>> from prsa_ctrl import load_plant, PID
>>> law = drive_law(PID(0.085, 14.7), load_plant())
>>> h, c = c_code(law, name="spd")
>>> "void spd_init(" in h and "spd_real spd_step(spd_state *s" in h
True
>>> "FUNCTION_BLOCK spd" in st_code(law, name="spd")
True
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Sequence

import numpy as np

from ..drive.pid import PID

if TYPE_CHECKING:
    from ..tuning.cascade import CascadeDesign
    from ..drive.measurement import PositionLoop
    from .output import Transaction
    from ..plant.plantfile import Plant
    from ..sim.engine import SimRun

__all__ = ["DriveLaw", "PositionLaw", "drive_law", "ReferenceLaw", "replay_inputs", "c_code", "st_code",
           "export_code", "code_texts", "code_files", "check_code_export", "write_code_export", "CODE_SUFFIXES",
           "REAL_TYPES"]

#: File suffixes :func:`export_code` writes (``--export PATH.c`` / ``PATH.st``).
CODE_SUFFIXES = (".c", ".st")
#: Floating-point types of the generated code: C type -> ST type.
REAL_TYPES = {"double": "LREAL", "float": "REAL"}

_Biquad = tuple[float, float, float, float, float]


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
        Plant name (for the header comment).
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
    speed_biquads: tuple[_Biquad, ...] = ()
    torque_biquads: tuple[_Biquad, ...] = ()
    position: PositionLaw | None = None
    delay_samples: int = 1
    setpoint_weight: float = 1.0
    plant: str = ""

    @property
    def beta(self) -> float:
        """Derivative-filter pole ``exp(-Ts/tf)``."""
        return math.exp(-self.ts / self.tf)

    @property
    def anti_windup_per_s(self) -> float:
        """``k_aw = ki/max(kp, 1e-9)`` (1/s)."""
        return self.ki / max(self.kp, 1e-9)


def _finite(name: str, v: Any, lo: float = -math.inf, lo_open: bool = False) -> float:
    ok = not isinstance(v, bool) and isinstance(v, (int, float, np.integer, np.floating)) and math.isfinite(float(v)) \
        and (float(v) > lo if lo_open else float(v) >= lo)
    if not ok:
        raise ValueError(f"{name} = {v!r}; expected a finite number {'>' if lo_open else '>='} {lo:g}")
    return float(v)


def position_law(position: "PositionLoop", plant: "Plant") -> PositionLaw:
    """The numbers of a :class:`~prsa_ctrl.drive.measurement.PositionLoop` on ``plant``."""
    a = float(plant.lead_per_rad)
    unit = position.unit_m(a)
    nut = position.measured == "nut_angle"
    return PositionLaw(position.measured, int(position.rate), float(position.kv), float(position.ki),
                       float(position.kvff), float(position.kaff), a, float(plant.reflected_inertia_kg_m2), unit,
                       unit / a, 2.0 * math.pi / plant.encoder_counts if nut else float(position.scale_resolution_m),
                       None if position.friction is None else position.friction.key())


def _friction_torque(fr: tuple[float, ...], w: float) -> float:
    """The friction feed-forward at nut speed ``w`` with the simulator's operations
    (:meth:`prsa_ctrl.drive.friction.FrictionFeedforward.symbolic`)."""
    cp, cn, sp, sn, ws, vp, vn, g = fr
    shape = math.exp(-((w / ws) * (w / ws)))
    if w > 0:
        return g * (cp + sp * shape + vp * w)
    if w < 0:
        return g * -(cn + sn * shape - vn * w)
    return 0.0


def drive_law(controller: "PID | CascadeDesign", plant: "Plant", *, filters: Iterable = (),
              position: "PositionLoop | None" = None, feedforward_torque_n_m: float = 0.0,
              delay_samples: int = 1, setpoint_weight: float = 1.0) -> DriveLaw:
    """The sampled drive's complete per-sample law for ``controller`` on ``plant``.

    Parameters
    ----------
    controller : PID or CascadeDesign
        The speed PI(D), or a cascade design (its speed PI and position loop).
    plant : Plant
        Sample time (s), torque limit (N m), encoder counts per rev, speed-filter time constant (s).
    filters : iterable of LoopFilter, (place, Filter) or Filter
        Loop filters, as :func:`prsa_ctrl.sim.engine.run` takes them (a bare Filter sits on
        the torque command), each run as its :meth:`LoopFilter.biquad`.
    position : PositionLoop, optional
        Position loop over the speed PI (taken from a CascadeDesign when not given).
    feedforward_torque_n_m : float, N m
        Constant torque feed-forward (``run(feedforward_torque=...)``).
    delay_samples : {0, 1}
        Computation delay of the returned command (1: as simulated).
    setpoint_weight : float
        2-DOF setpoint weight ``b`` in [0, 1] (the scene's ``[tuning] setpoint_weight``).

    Returns
    -------
    DriveLaw
    """
    from ..drive.filters import loop_filters
    from ..plant.plantfile import Plant

    if not isinstance(plant, Plant):
        raise ValueError(f"plant = {plant!r}; expected a Plant (see prsa_ctrl.load_plant)")
    if not isinstance(controller, PID):
        speed, pos = getattr(controller, "speed", None), getattr(controller, "position", None)
        if not isinstance(speed, PID):
            raise ValueError(f"controller = {controller!r}; expected a PID or a CascadeDesign")
        controller, position = speed, position if position is not None else pos
    if controller.kff > 0:
        raise ValueError(f"PID kff = {controller.kff:g}; expected 0 (the generated code uses the encoder-difference "
                         "speed measurement; the Kalman load-torque feed-forward is not generated)")
    if delay_samples not in (0, 1) or isinstance(delay_samples, bool):
        raise ValueError(f"delay_samples = {delay_samples!r}; expected 0 or 1")
    b = _finite("setpoint_weight", setpoint_weight, 0.0)
    if b > 1.0:
        raise ValueError(f"setpoint_weight = {setpoint_weight!r}; expected a setpoint weight b in [0, 1]")
    ts = float(plant.sample_time_s)
    lfs = loop_filters(filters, ts)
    bq = {pl: tuple(tuple(lf.biquad(ts).as_dict().values()) for lf in lfs if lf.place == pl)
          for pl in ("speed_measurement", "torque_command")}
    pos = None
    if position is not None:
        from ..drive.measurement import PositionLoop

        if not isinstance(position, PositionLoop):
            raise ValueError(f"position = {position!r}; expected a PositionLoop")
        pos = position_law(position, plant)
    return DriveLaw(ts, float(plant.torque_limit), 2.0 * math.pi / plant.encoder_counts,
                    math.exp(-ts / float(plant.speed_filter_s)), float(controller.kp), float(controller.ki),
                    float(controller.kd), float(controller.tf), _finite("feedforward_torque_n_m", feedforward_torque_n_m),
                    bq["speed_measurement"], bq["torque_command"], pos, int(delay_samples), b, plant.name)


# --- the law in Python, exactly as the simulator writes it ---------------------------------------

class ReferenceLaw:
    """The drive's per-sample law in Python with the simulator's operations and their order
    (angles in rad, as ``simulation._sample_law``); reproduces a recorded sampled run's
    ``torque_command`` to round-off.

    Parameters
    ----------
    law : DriveLaw
    """

    def __init__(self, law: DriveLaw) -> None:
        if not isinstance(law, DriveLaw):
            raise ValueError(f"law = {law!r}; expected a DriveLaw (see drive_law)")
        self.law = law

    def init(self, count_prev: int, speed0_rad_s: float, integral0_n_m: float, torque0_n_m: float,
             position_zero_count: int = 0) -> None:
        """Steady state: previous encoder count, speed (rad/s), PI integral (N m), the command
        being applied (N m) and, for a cascade, the position count the reference starts from."""
        lw = self.law
        self.th_prev = math.floor(count_prev) * lw.rad_per_count
        self.w_filt, self.w_prev, self.deriv = float(speed0_rad_s), float(speed0_rad_s), 0.0
        self.integral, self.u_pend = float(integral0_n_m), float(torque0_n_m)
        self.mem_s = [[self.w_filt] * 4 for _ in lw.speed_biquads]
        self.mem_t = [[self.u_pend] * 4 for _ in lw.torque_biquads]
        self.p0 = position_zero_count * lw.position.per_count if lw.position is not None else 0.0
        self.p_int = self.w_ref = self.tau_p = 0.0
        self.k = 0

    @staticmethod
    def _biquad(x: float, m: list[float], c: _Biquad) -> float:
        y = c[0] * x + c[1] * m[0] + c[2] * m[1] - c[3] * m[2] - c[4] * m[3]
        m[:] = [x, m[0], y, m[2]]
        return y

    def step(self, count: int, speed_ref_rad_s: float = 0.0, pos_ref_m: float = 0.0, vel_ref_m_s: float = 0.0,
             acc_ref_m_s2: float = 0.0, position_count: int | None = None) -> float:
        """One sample: the command to apply until the next one (N m)."""
        lw = self.law
        ts = lw.ts
        theta_q = math.floor(count) * lw.rad_per_count
        a = lw.speed_filter_a
        w = a * self.w_filt + (1 - a) * (theta_q - self.th_prev) / ts
        self.w_filt = w
        for c, m in zip(lw.speed_biquads, self.mem_s):
            w = self._biquad(w, m, c)
        beta = math.exp(-ts / lw.tf)
        deriv = beta * self.deriv + (1 - beta) * (w - self.w_prev) / ts
        ref, tau_ff = speed_ref_rad_s, lw.torque_ff_n_m
        pl = lw.position
        if pl is not None:
            if self.k % pl.rate == 0:
                p_meas = theta_q if position_count is None else math.floor(position_count) * pl.per_count
                p_ref = self.p0 + pos_ref_m / pl.unit_m
                e = (p_ref - p_meas) * pl.err_to_rad
                self.p_int = self.p_int + 1.0 * (pl.rate * ts) * pl.ki * e
                self.w_ref = pl.kv * e + self.p_int + pl.kvff * vel_ref_m_s / pl.lead_m_per_rad
                self.tau_p = pl.kaff * pl.inertia_kg_m2 * acc_ref_m_s2 / pl.lead_m_per_rad
                if pl.friction is not None:
                    self.tau_p = self.tau_p + _friction_torque(pl.friction, vel_ref_m_s / pl.lead_m_per_rad)
            ref, tau_ff = self.w_ref, tau_ff + self.tau_p
        err = ref - w
        u = lw.kp * (lw.setpoint_weight * ref - w) + self.integral - lw.kd * deriv + tau_ff
        lim = lw.torque_limit_n_m
        us = min(max(u, -lim), lim)
        self.integral = self.integral + ts * (lw.ki * err + lw.ki / max(lw.kp, 1e-9) * (us - u))
        uf = us
        if lw.torque_biquads:
            for c, m in zip(lw.torque_biquads, self.mem_t):
                uf = self._biquad(uf, m, c)
            uf = min(max(uf, -lim), lim)
        self.th_prev, self.deriv, self.w_prev = theta_q, deriv, w
        self.k += 1
        out, self.u_pend = self.u_pend, uf
        return out if lw.delay_samples == 1 else uf

    def run(self, inputs: dict) -> np.ndarray:
        """Initialise from ``inputs["init"]`` and step over the sequences of :func:`replay_inputs`."""
        self.init(**inputs["init"])
        n = len(inputs["count"])
        cols = [inputs.get(k) for k in ("speed_ref_rad_s", "pos_ref_m", "vel_ref_m_s", "acc_ref_m_s2",
                                        "position_count")]
        out = np.empty(n)
        for k in range(n):  # bounded by the recorded run
            out[k] = self.step(int(inputs["count"][k]), *(0.0 if c is None else float(c[k]) for c in cols[:4]),
                               None if cols[4] is None else int(cols[4][k]))
        return out


def replay_inputs(run: "SimRun", plant: "Plant", motion=None, position: "PositionLoop | None" = None) -> dict:
    """The per-sample inputs of a recorded sampled run as the drive reads them, and its
    initial state: ``count`` (encoder counts, int64), ``speed_ref_rad_s`` (speed runs), the
    motion's ``pos_ref_m``, ``vel_ref_m_s``, ``acc_ref_m_s2`` and (``screw_position``) the
    linear scale's ``position_count`` (cascade runs), ``init`` (keyword arguments of
    :meth:`ReferenceLaw.init`) and ``torque_command`` (the recorded command, N m).

    Parameters
    ----------
    run : SimRun
        A sampled run (``discrete=True``) without torque noise.
    plant : Plant
    motion : MotionProfile, optional
        The move of a cascade run (m).
    position : PositionLoop, optional
        The cascade run's position loop.
    """
    if not run.info.get("discrete"):
        raise ValueError("run is continuous; expected a sampled run (discrete=True)")
    if run.info.get("measurement") != "encoder":
        raise ValueError(f"run measured the speed with {run.info.get('measurement')!r}; expected the encoder difference "
                         "(measurement='encoder'), the law the generated code runs")
    q = 2.0 * math.pi / plant.encoder_counts
    names = list(run.state_labels)
    xs = np.asarray(run.states)
    theta = xs[names.index("theta_nut")]
    count = np.floor(theta / q).astype(np.int64)
    w0 = float(xs[names.index("speed_filtered"), 0])
    ts = plant.sample_time_s
    init = {"count_prev": int(math.floor((float(theta[0]) - w0 * ts) / q)), "speed0_rad_s": w0,
            "integral0_n_m": float(xs[names.index("pid_integral"), 0]),
            "torque0_n_m": float(run.output("torque_command")[0])}
    out: dict[str, Any] = {"count": count, "init": init, "torque_command": np.asarray(run.output("torque_command"))}
    t = np.asarray(run.time)
    if position is None:
        out["speed_ref_rad_s"] = np.asarray(run.inputs[0], float)
        return out
    p, v, a = motion.at(t) if motion is not None else (np.zeros_like(t),) * 3
    out.update(pos_ref_m=p, vel_ref_m_s=v, acc_ref_m_s2=a)
    if position.measured == "nut_angle":
        init["position_zero_count"] = int(count[0])
    else:
        x_s = plant.lead_per_rad * theta
        if "delta_screw" in names:
            x_s = x_s + xs[names.index("x_roller")] - xs[names.index("delta_screw")]
        pc = np.floor(x_s / position.scale_resolution_m).astype(np.int64)
        out["position_count"] = pc
        init["position_zero_count"] = int(pc[0])
    return out


# --- code writers -------------------------------------------------------------------------------

def _lit(v: float) -> str:
    """A floating literal that reads back as exactly ``v`` (double)."""
    r = repr(float(v))
    if not math.isfinite(float(v)):
        raise ValueError(f"constant {v!r}; expected a finite number")
    return r if any(c in r for c in ".e") else r + ".0"


def _check_name(name: str) -> str:
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]{0,40}", name):
        raise ValueError(f"name = {name!r}; expected an identifier (letters, digits, _; at most 41 characters)")
    return name


def _check_real(real: str) -> str:
    if real not in REAL_TYPES:
        raise ValueError(f"real = {real!r}; expected one of {', '.join(REAL_TYPES)}")
    return real


def _check_differences(differences: str) -> bool:
    if differences not in ("counts", "angle"):
        raise ValueError(f"differences = {differences!r}; expected 'counts' or 'angle'")
    return differences == "counts"


def _constants(law: DriveLaw) -> list[tuple[str, float, str]]:
    """``(NAME, value, comment)`` of every constant the code uses."""
    c = [("TS", law.ts, "sample time, s"),
         ("T_MAX", law.torque_limit_n_m, "torque limit, N m"),
         ("RAD_PER_COUNT", law.rad_per_count, "encoder: rad per count (2 pi/counts per rev)"),
         ("A_W", law.speed_filter_a, "speed filter a = exp(-Ts/tau_w)"),
         ("ONE_MINUS_A_W", 1 - law.speed_filter_a, "1 - a"),
         ("KP", law.kp, "speed PI proportional gain, N m s/rad"),
         ("B_SP", law.setpoint_weight, "2-DOF setpoint weight b (u = kp (b w_ref - w) + I ...)"),
         ("KI", law.ki, "speed PI integral gain, N m/rad"),
         ("KD", law.kd, "derivative gain, N m s^2/rad (on the measured speed)"),
         ("BETA", law.beta, "derivative filter beta = exp(-Ts/tf)"),
         ("ONE_MINUS_BETA", 1 - law.beta, "1 - beta"),
         ("K_AW", law.anti_windup_per_s, "anti-windup (back-calculation) gain ki/kp, 1/s"),
         ("TAU_FF", law.torque_ff_n_m, "constant torque feed-forward, N m")]
    for place, bqs in (("SF", law.speed_biquads), ("TF", law.torque_biquads)):
        for i, b in enumerate(bqs):
            for k, v in zip(("B0", "B1", "B2", "A1", "A2"), b):
                c.append((f"{place}{i}_{k}", v, f"{'speed-measurement' if place == 'SF' else 'torque-command'} "
                                                f"biquad {i + 1}: {k.lower()}"))
    p = law.position
    if p is not None:
        c += [("TP_KIP", (p.rate * law.ts) * p.ki, "position-loop sample time x position integral gain, 1/s"),
              ("KV", p.kv, "position gain Kv, 1/s"),
              ("KVFF", p.kvff, "velocity feed-forward gain"),
              ("KAFF_J", p.kaff * p.inertia_kg_m2, "acceleration feed-forward kaff J, kg m^2"),
              ("LEAD", p.lead_m_per_rad, "screw lead per nut radian, m/rad"),
              ("UNIT_M", p.unit_m, "m of travel per unit of the measured position"),
              ("ERR_TO_RAD", p.err_to_rad, "nut rad per unit of position error"),
              ("POS_PER_COUNT", p.per_count, "measured position per count (rad or m)")]
        if p.friction is not None:
            c += [(f"FR_{k}", v, f"friction feed-forward: {what}") for k, v, what in zip(
                ("CP", "CN", "SP", "SN", "WS", "VP", "VN", "G"), p.friction,
                ("Coulomb level, positive direction, N m", "Coulomb level, negative direction, N m",
                 "Stribeck excess, positive direction, N m", "Stribeck excess, negative direction, N m",
                 "Stribeck speed, rad/s", "viscous, positive direction, N m s/rad",
                 "viscous, negative direction, N m s/rad", "gain (1 = the plant's full friction model)"))]
    return c


def _header_comment(law: DriveLaw, lang: str) -> list[str]:
    from .. import __version__

    p = law.position
    lines = [f"Generated by prsa-ctrl {__version__} (prsa_ctrl.io.codegen) for plant {law.plant!r}: the complete "
             "discrete controller of the sampled drive, the same per-sample law as the toolkit's simulator.",
             (f"Call step() every Ts = {law.ts!r} s (fixed), after init()." if lang == "c" else
              f"Call the block every Ts = {law.ts!r} s (a cyclic task of that period), once with Reset := TRUE "
              "first.") + " Units: SI (rad, rad/s, N m, m, m/s, m/s^2).",
             "Per sample: encoder difference in counts -> speed filter (a) -> speed-measurement biquads -> "
             + ("position loop (Kv, integral, velocity and acceleration feed-forward) -> " if p else "")
             + "speed PI with back-calculation anti-windup (k_aw = ki/kp) -> torque limit -> torque-command "
               "biquads -> torque limit.",
             ("Returned: " if lang == "c" else "TorqueCmd: ") + ("the command computed at the previous call (one-sample computation delay: write it to "
                             "the current loop at the start of the sample)." if law.delay_samples else
                             "the command computed now (no computation delay)."),
             f"Biquads: y = b0 x + b1 x1 + b2 x2 - a1 y1 - a2 y2 (direct form I), {len(law.speed_biquads)} on the "
             f"speed, {len(law.torque_biquads)} on the torque command."]
    if p and p.friction is not None:
        lines.append("Friction feed-forward from the reference speed w = vel_ref/LEAD (the plant's sliding friction): "
                     "w > 0: FR_G (FR_CP + FR_SP exp(-(w/FR_WS)^2) + FR_VP w); w < 0: -FR_G (FR_CN + FR_SN "
                     "exp(-(w/FR_WS)^2) - FR_VN w); w = 0: 0; added to the acceleration feed-forward"
                     + ("; needs <math.h> (exp; link with -lm)." if lang == "c" else " (EXP)."))
    if p:
        lines.append(f"Position loop: measured {p.measured}, every {p.rate} sample(s) (position-loop sample time "
                     f"{p.rate * law.ts!r} s over the speed loop's {law.ts!r} s); "
                     + ("position counts are the encoder counts" if p.measured == "nut_angle"
                        else f"position counts of the linear scale ({p.per_count!r} m each)")
                     + "; references in m, m/s, m/s^2 of screw travel from the position at init.")
    if lang == "c":
        lines.append("Compile without floating-point contraction (-ffp-contract=off) to reproduce the toolkit's "
                     "round-off; with it only the last bits differ.")
    return lines


def c_code(law: DriveLaw, *, name: str = "prsa_ctrl", real: str = "double", header: str | None = None,
           differences: str = "counts") -> tuple[str, str]:
    """The law as C99: ``(header text, source text)``.

    The header declares ``<name>_real`` (``float`` or ``double``), the state struct
    ``<name>_state`` and::

        void <name>_init(<name>_state *s, int64_t count_prev, <name>_real speed0, <name>_real integral0,
                         <name>_real torque0[, int64_t position_zero_count]);
        <name>_real <name>_step(<name>_state *s, int64_t count, <name>_real speed_ref);           speed loop
        <name>_real <name>_step(<name>_state *s, int64_t count, <name>_real pos_ref, <name>_real vel_ref,
                                <name>_real acc_ref[, int64_t position_count]);                   cascade

    (``position_count`` only with a linear scale). No library beyond ``<stdint.h>``.

    Parameters
    ----------
    law : DriveLaw
    name : str
        Prefix of every identifier (a C identifier).
    real : {"double", "float"}
    header : str, optional
        File name the source includes (default ``<name>.h``).
    differences : {"counts", "angle"}
        ``"counts"``: speed and position differences in integer counts (full resolution at
        any travel, also in float; the drive's choice); ``"angle"``: as the simulator, from the
        angles in rad (double: the simulator's command bit for bit).

    Returns
    -------
    tuple of str
    """
    if not isinstance(law, DriveLaw):
        raise ValueError(f"law = {law!r}; expected a DriveLaw (see drive_law)")
    n, real = _check_name(name), _check_real(real)
    by_counts = _check_differences(differences)
    header = header or f"{n}.h"
    R = f"{n}_real"
    p = law.position
    ns, nt = len(law.speed_biquads), len(law.torque_biquads)
    scale = p is not None and p.measured != "nut_angle"
    fric = p is not None and p.friction is not None
    step_args = (f"int64_t count, {R} speed_ref" if p is None else
                 f"int64_t count, {R} pos_ref, {R} vel_ref, {R} acc_ref" + (", int64_t position_count" if scale else ""))
    init_args = f"int64_t count_prev, {R} speed0, {R} integral0, {R} torque0" + (
        ", int64_t position_zero_count" if p is not None else "")
    guard = f"{n.upper()}_H"
    h = ["/*", *[" * " + s for s in _header_comment(law, "c")], " */", f"#ifndef {guard}", f"#define {guard}", "",
         "#include <stdint.h>", *(["#include <math.h>"] if fric else []), "", f"typedef {real} {R};", "",
         "typedef struct {",
         "    int64_t count_prev;      /* encoder count at the previous sample */",
         f"    {R} w_filt;            /* drive speed filter output, rad/s */",
         f"    {R} w_prev;            /* speed the PI used at the previous sample, rad/s */",
         f"    {R} deriv;             /* filtered derivative of the speed, rad/s^2 */",
         f"    {R} integral;          /* PI integral, N m */",
         f"    {R} u_pending;         /* command computed at the previous sample, N m */"]
    if ns:
        h.append(f"    {R} sf[{ns}][4];          /* speed-measurement biquads: x1, x2, y1, y2 */")
    if nt:
        h.append(f"    {R} tf[{nt}][4];          /* torque-command biquads: x1, x2, y1, y2 */")
    if p is not None:
        h += ["    int64_t position_zero;  /* position count the reference starts from */",
              "    int32_t phase;          /* samples since the last position-loop sample */",
              f"    {R} p_integral;        /* position-loop integral, rad/s */",
              f"    {R} w_ref;             /* speed reference, held between position samples, rad/s */",
              f"    {R} tau_p;             /* acceleration feed-forward torque, held, N m */"]
    h += [f"    {R} speed;             /* diagnostics: filtered speed of this sample, rad/s */",
          f"    {R} command_unfiltered; /* diagnostics: limited PI command before the torque filters, N m */",
          f"}} {n}_state;", "",
          f"/* Initialise at a steady state: previous encoder count, speed (rad/s), PI integral (N m), the command",
          "   being applied (N m)" + (", and the position count the reference (0 m) starts from." if p else ".")
          + " At rest: count_prev = the count now, speed0 = 0, integral0 = torque0 = the holding torque. */",
          f"void {n}_init({n}_state *s, {init_args});", "",
          "/* One sample; returns the torque command (N m). " + (
              "speed_ref in rad/s of the motor. */" if p is None else
              "pos_ref (m), vel_ref (m/s), acc_ref (m/s^2) of screw travel. */"),
          f"{R} {n}_step({n}_state *s, {step_args});", "", f"#endif /* {guard} */", ""]
    c = ["/*", *[" * " + s for s in _header_comment(law, "c")], " */", f'#include "{header}"', ""]
    for cname, v, comment in _constants(law):
        c.append(f"static const {R} {cname} = ({R}){_lit(v)}; /* {comment} */")
    c += ["", f"static {R} clamp({R} x) {{ return x > T_MAX ? T_MAX : (x < -T_MAX ? -T_MAX : x); }}", ""]
    if fric:
        c += [f"static {R} friction_ff({R} w)", "{", f"    {R} x = w / FR_WS;", f"    {R} shape = ({R})exp(-(x * x));",
              "    if (w > 0) return FR_G * (FR_CP + FR_SP * shape + FR_VP * w);",
              "    if (w < 0) return FR_G * -(FR_CN + FR_SN * shape - FR_VN * w);", f"    return ({R})0;", "}", ""]
    if ns or nt:
        c += [f"static {R} biquad({R} x, {R} *m, {R} b0, {R} b1, {R} b2, {R} a1, {R} a2)", "{",
              f"    {R} y = b0 * x + b1 * m[0] + b2 * m[1] - a1 * m[2] - a2 * m[3];",
              "    m[1] = m[0]; m[0] = x; m[3] = m[2]; m[2] = y;", "    return y;", "}", ""]
    c += [f"void {n}_init({n}_state *s, {init_args})", "{",
          "    s->count_prev = count_prev;", "    s->w_filt = speed0;", "    s->w_prev = speed0;",
          f"    s->deriv = ({R})0;", "    s->integral = integral0;", "    s->u_pending = torque0;",
          "    s->speed = speed0;", "    s->command_unfiltered = torque0;"]
    for i in range(ns):
        c.append(f"    s->sf[{i}][0] = s->sf[{i}][1] = s->sf[{i}][2] = s->sf[{i}][3] = speed0;")
    for i in range(nt):
        c.append(f"    s->tf[{i}][0] = s->tf[{i}][1] = s->tf[{i}][2] = s->tf[{i}][3] = torque0;")
    if p is not None:
        c += ["    s->position_zero = position_zero_count;", "    s->phase = 0;", f"    s->p_integral = ({R})0;",
              f"    s->w_ref = ({R})0;", f"    s->tau_p = ({R})0;"]
    c += ["}", "", f"{R} {n}_step({n}_state *s, {step_args})", "{",
          f"    {R} w, d, e, u, us, uf, out;", f"    {R} ref = {'speed_ref' if p is None else f'({R})0'};",
          f"    {R} tau_ff = TAU_FF;",
          f"    /* encoder difference in counts (keeps full resolution at any travel) */",
          f"    w = A_W * s->w_filt + ONE_MINUS_A_W * (({R})(count - s->count_prev) * RAD_PER_COUNT) / TS;" if by_counts
          else f"    w = A_W * s->w_filt + ONE_MINUS_A_W * (({R})count * RAD_PER_COUNT - ({R})s->count_prev * "
               "RAD_PER_COUNT) / TS;",
          "    s->w_filt = w;"]
    for i in range(ns):
        c.append(f"    w = biquad(w, s->sf[{i}], SF{i}_B0, SF{i}_B1, SF{i}_B2, SF{i}_A1, SF{i}_A2);")
    c += ["    d = BETA * s->deriv + ONE_MINUS_BETA * (w - s->w_prev) / TS;"]
    if p is not None:
        pc = "position_count" if scale else "count"
        c += [f"    if (s->phase == 0) {{  /* position-loop sample */",
              f"        {R} ep = (pos_ref / UNIT_M - ({R})({pc} - s->position_zero) * POS_PER_COUNT) * ERR_TO_RAD;"
              if by_counts else f"        {R} ep = ((({R})s->position_zero * POS_PER_COUNT + pos_ref / UNIT_M) - "
                                f"({R}){pc} * POS_PER_COUNT) * ERR_TO_RAD;",
              "        s->p_integral = s->p_integral + TP_KIP * ep;",
              "        s->w_ref = KV * ep + s->p_integral + KVFF * vel_ref / LEAD;",
              "        s->tau_p = KAFF_J * acc_ref / LEAD" + (" + friction_ff(vel_ref / LEAD);" if fric else ";"), "    }",
              f"    s->phase = s->phase + 1 >= {p.rate} ? 0 : s->phase + 1;",
              "    ref = s->w_ref;", "    tau_ff = tau_ff + s->tau_p;"]
    c += ["    e = ref - w;", "    u = KP * (B_SP * ref - w) + s->integral - KD * d + tau_ff;", "    us = clamp(u);",
          "    s->integral = s->integral + TS * (KI * e + K_AW * (us - u));", "    uf = us;"]
    for i in range(nt):
        c.append(f"    uf = biquad(uf, s->tf[{i}], TF{i}_B0, TF{i}_B1, TF{i}_B2, TF{i}_A1, TF{i}_A2);")
    if nt:
        c.append("    uf = clamp(uf);")
    c += ["    s->count_prev = count;", "    s->deriv = d;", "    s->w_prev = w;", "    s->speed = w;",
          "    s->command_unfiltered = us;",
          "    out = s->u_pending;" if law.delay_samples else "    out = uf;",
          "    s->u_pending = uf;", "    return out;", "}", ""]
    return "\n".join(h), "\n".join(c)


def st_code(law: DriveLaw, *, name: str = "PrsaCtrl", real: str = "double", differences: str = "counts") -> str:
    """The law as an IEC 61131-3 Structured Text FUNCTION_BLOCK.

    Inputs: ``Reset`` (BOOL: load the ``Init*`` values and output ``InitTorque``), ``EncCount``
    (LINT, encoder counts), ``SpeedRef`` (rad/s; speed loop) or ``PosRef`` (m), ``VelRef`` (m/s),
    ``AccRef`` (m/s^2) (cascade) and ``PosCount`` (LINT, linear-scale counts); ``Init*`` as
    :meth:`ReferenceLaw.init`. Output ``TorqueCmd`` (N m) and diagnostics ``Speed``,
    ``CommandUnfiltered``. Call once per sample time from a cyclic task of period ``Ts``.

    Parameters
    ----------
    law : DriveLaw
    name : str
        Name of the function block.
    real : {"double", "float"}
        ``LREAL`` or ``REAL``.
    differences : {"counts", "angle"}
        As :func:`c_code`.
    """
    if not isinstance(law, DriveLaw):
        raise ValueError(f"law = {law!r}; expected a DriveLaw (see drive_law)")
    n, R = _check_name(name), REAL_TYPES[_check_real(real)]
    by_counts = _check_differences(differences)
    p = law.position
    ns, nt = len(law.speed_biquads), len(law.torque_biquads)
    scale = p is not None and p.measured != "nut_angle"
    out = [f"FUNCTION_BLOCK {n}", *["(* " + s.replace("(*", "( *").replace("*)", "* )") + " *)"
                                    for s in _header_comment(law, "st")],
           "VAR_INPUT",
           "    Reset : BOOL := FALSE;          (* TRUE: initialise from the Init* inputs *)",
           "    EncCount : LINT := 0;           (* encoder counts *)"]
    if p is None:
        out.append(f"    SpeedRef : {R} := 0.0;          (* speed reference, rad/s *)")
    else:
        out += [f"    PosRef : {R} := 0.0;            (* position reference, m of screw travel from the start *)",
                f"    VelRef : {R} := 0.0;            (* speed reference, m/s *)",
                f"    AccRef : {R} := 0.0;            (* acceleration reference, m/s^2 *)"]
        if scale:
            out.append("    PosCount : LINT := 0;           (* linear-scale counts *)")
    out += ["    InitCountPrev : LINT := 0;      (* encoder count at the previous sample *)",
            f"    InitSpeed : {R} := 0.0;         (* rad/s *)",
            f"    InitIntegral : {R} := 0.0;      (* N m *)",
            f"    InitTorque : {R} := 0.0;        (* command being applied, N m *)"]
    if p is not None:
        out.append("    InitPosZero : LINT := 0;        (* position count the reference starts from *)")
    out += ["END_VAR", "VAR_OUTPUT", f"    TorqueCmd : {R} := 0.0;         (* N m *)",
            f"    Speed : {R} := 0.0;             (* filtered speed, rad/s *)",
            f"    CommandUnfiltered : {R} := 0.0; (* limited PI command before the torque filters, N m *)",
            "END_VAR", "VAR", "    CountPrev : LINT := 0;", f"    WFilt : {R} := 0.0;", f"    WPrev : {R} := 0.0;",
            f"    Deriv : {R} := 0.0;", f"    Integral : {R} := 0.0;", f"    UPending : {R} := 0.0;"]
    for i in range(ns):
        out.append(f"    SF{i}_X1, SF{i}_X2, SF{i}_Y1, SF{i}_Y2 : {R} := 0.0;")
    for i in range(nt):
        out.append(f"    TF{i}_X1, TF{i}_X2, TF{i}_Y1, TF{i}_Y2 : {R} := 0.0;")
    if p is not None:
        out += ["    PosZero : LINT := 0;", "    Phase : DINT := 0;", f"    PIntegral : {R} := 0.0;",
                f"    WRef : {R} := 0.0;", f"    TauP : {R} := 0.0;", f"    Ep : {R} := 0.0;"]
        if p.friction is not None:
            out.append(f"    FrW, FrX, TauFr : {R} := 0.0;")
    out += [f"    W, D, E, U, Us, Uf, Y, Ref, TauFF : {R} := 0.0;", "END_VAR", "VAR CONSTANT"]
    for cname, v, comment in _constants(law):
        out.append(f"    {cname} : {R} := {_lit(v)}; (* {comment} *)")
    out += ["END_VAR", "", "IF Reset THEN", "    CountPrev := InitCountPrev;", "    WFilt := InitSpeed;",
            "    WPrev := InitSpeed;", "    Deriv := 0.0;", "    Integral := InitIntegral;", "    UPending := InitTorque;"]
    for i in range(ns):
        out.append(f"    SF{i}_X1 := InitSpeed; SF{i}_X2 := InitSpeed; SF{i}_Y1 := InitSpeed; SF{i}_Y2 := InitSpeed;")
    for i in range(nt):
        out.append(f"    TF{i}_X1 := InitTorque; TF{i}_X2 := InitTorque; TF{i}_Y1 := InitTorque; "
                   f"TF{i}_Y2 := InitTorque;")
    if p is not None:
        out += ["    PosZero := InitPosZero;", "    Phase := 0;", "    PIntegral := 0.0;", "    WRef := 0.0;",
                "    TauP := 0.0;"]
    out += ["    TorqueCmd := InitTorque;", "    Speed := InitSpeed;", "    CommandUnfiltered := InitTorque;",
            "    RETURN;", "END_IF;", "",
            "(* encoder difference in counts *)",
            f"W := A_W * WFilt + ONE_MINUS_A_W * (LINT_TO_{R}(EncCount - CountPrev) * RAD_PER_COUNT) / TS;" if by_counts
            else f"W := A_W * WFilt + ONE_MINUS_A_W * (LINT_TO_{R}(EncCount) * RAD_PER_COUNT - LINT_TO_{R}(CountPrev) "
                 "* RAD_PER_COUNT) / TS;",
            "WFilt := W;"]
    for i in range(ns):
        out += [f"Y := SF{i}_B0 * W + SF{i}_B1 * SF{i}_X1 + SF{i}_B2 * SF{i}_X2 - SF{i}_A1 * SF{i}_Y1 - SF{i}_A2 * SF{i}_Y2;",
                f"SF{i}_X2 := SF{i}_X1; SF{i}_X1 := W; SF{i}_Y2 := SF{i}_Y1; SF{i}_Y1 := Y;", "W := Y;"]
    out.append("D := BETA * Deriv + ONE_MINUS_BETA * (W - WPrev) / TS;")
    if p is None:
        out += ["Ref := SpeedRef;", "TauFF := TAU_FF;"]
    else:
        pc = "PosCount" if scale else "EncCount"
        out += ["IF Phase = 0 THEN (* position-loop sample *)",
                f"    Ep := (PosRef / UNIT_M - LINT_TO_{R}({pc} - PosZero) * POS_PER_COUNT) * ERR_TO_RAD;" if by_counts
                else f"    Ep := ((LINT_TO_{R}(PosZero) * POS_PER_COUNT + PosRef / UNIT_M) - LINT_TO_{R}({pc}) * "
                     "POS_PER_COUNT) * ERR_TO_RAD;",
                "    PIntegral := PIntegral + TP_KIP * Ep;",
                "    WRef := KV * Ep + PIntegral + KVFF * VelRef / LEAD;",
                *(["    FrW := VelRef / LEAD;", "    FrX := FrW / FR_WS;", "    TauFr := 0.0;",
                    "    IF FrW > 0.0 THEN", "        TauFr := FR_G * (FR_CP + FR_SP * EXP(-(FrX * FrX)) + FR_VP * FrW);",
                    "    END_IF;", "    IF FrW < 0.0 THEN",
                    "        TauFr := FR_G * -(FR_CN + FR_SN * EXP(-(FrX * FrX)) - FR_VN * FrW);", "    END_IF;",
                    "    TauP := KAFF_J * AccRef / LEAD + TauFr;"] if p.friction is not None else
                  ["    TauP := KAFF_J * AccRef / LEAD;"]), "END_IF;",
                "Phase := Phase + 1;", f"IF Phase >= {p.rate} THEN", "    Phase := 0;", "END_IF;",
                "Ref := WRef;", "TauFF := TAU_FF + TauP;"]
    out += ["E := Ref - W;", "U := KP * (B_SP * Ref - W) + Integral - KD * D + TauFF;", "Us := MIN(MAX(U, -T_MAX), T_MAX);",
            "Integral := Integral + TS * (KI * E + K_AW * (Us - U));", "Uf := Us;"]
    for i in range(nt):
        out += [f"Y := TF{i}_B0 * Uf + TF{i}_B1 * TF{i}_X1 + TF{i}_B2 * TF{i}_X2 - TF{i}_A1 * TF{i}_Y1 - TF{i}_A2 * TF{i}_Y2;",
                f"TF{i}_X2 := TF{i}_X1; TF{i}_X1 := Uf; TF{i}_Y2 := TF{i}_Y1; TF{i}_Y1 := Y;", "Uf := Y;"]
    if nt:
        out.append("Uf := MIN(MAX(Uf, -T_MAX), T_MAX);")
    out += ["CountPrev := EncCount;", "Deriv := D;", "WPrev := W;", "Speed := W;", "CommandUnfiltered := Us;"]
    out += (["TorqueCmd := UPending;", "UPending := Uf;"] if law.delay_samples else
            ["TorqueCmd := Uf;", "UPending := Uf;"])
    out += ["END_FUNCTION_BLOCK", ""]
    return "\n".join(out)


def export_code(controller: "PID | CascadeDesign | DriveLaw", plant: "Plant | None", path: "str | Path", *,
                filters: Iterable = (), real: str = "double", name: str | None = None,
                delay_samples: int = 1, differences: str = "counts", setpoint_weight: float = 1.0) -> list[Path]:
    """Write the controller as code, chosen by the suffix of ``path``: ``.c`` writes the C source
    and its header (``.h``) beside it, ``.st`` the Structured Text function block.

    Parameters
    ----------
    controller : PID, CascadeDesign or DriveLaw
    plant : Plant or None
        Needed unless ``controller`` is a DriveLaw.
    path : str or Path
    filters : iterable
        Loop filters (see :func:`drive_law`).
    real : {"double", "float"}
    name : str, optional
        Identifier prefix (C) or function-block name (ST); default the file's stem when it is an
        identifier, else ``prsa_ctrl``.
    delay_samples : {0, 1}
    differences : {"counts", "angle"}
        See :func:`c_code`.
    setpoint_weight : float
        2-DOF setpoint weight b in [0, 1] (see :func:`drive_law`).

    Returns
    -------
    list of Path
        The files written.
    """
    texts = code_texts(controller, plant, path, filters=filters, real=real, name=name, delay_samples=delay_samples,
                       differences=differences, setpoint_weight=setpoint_weight)
    for f, text in texts.items():
        f.write_text(text)
    return list(texts)


def code_texts(controller: "PID | CascadeDesign | DriveLaw", plant: "Plant | None", path: "str | Path", *,
               filters: Iterable = (), real: str = "double", name: str | None = None, delay_samples: int = 1,
               differences: str = "counts", setpoint_weight: float = 1.0) -> dict[Path, str]:
    """What :func:`export_code` writes: ``{file: text}`` (same parameters)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in CODE_SUFFIXES:
        raise ValueError(f"path = {str(path)!r}; expected a file name ending in {' or '.join(CODE_SUFFIXES)}")
    _check_real(real)
    _check_differences(differences)
    law = controller if isinstance(controller, DriveLaw) else drive_law(
        controller, plant, filters=filters, delay_samples=delay_samples, setpoint_weight=setpoint_weight)
    if name is None:
        name = path.stem if re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]{0,40}", path.stem) else "prsa_ctrl"
    if suffix == ".st":
        return {path: st_code(law, name=name, real=real, differences=differences)}
    hpath = path.with_suffix(".h")
    h, c = c_code(law, name=name, real=real, header=hpath.name, differences=differences)
    return {path: c, hpath: h}


def code_files(path: "str | Path") -> list[Path]:
    """The files :func:`export_code` writes for ``path`` (the source and its header for ``.c``)."""
    path = Path(path)
    return [path, path.with_suffix(path.suffix[:-1] + "h")] if path.suffix.lower() == ".c" else [path]


def check_code_export(path: "str | os.PathLike", inputs: Iterable = (), flag: str = "--export") -> None:
    """Check, before any work, that every file a code export writes (``.c`` and its ``.h``, or
    ``.st``) can be written and is no input (one-line :class:`prsa_ctrl.io.output.OutputError`)."""
    from .output import check_writable

    for f in code_files(path):
        check_writable(f if f == Path(path) else str(f), list(inputs), flag if f == Path(path) else f"{flag} (header)")


def stage_code_export(outputs: "Transaction", path: "str | os.PathLike", controller: "PID | CascadeDesign",
                      plant: "Plant", flag: str = "--export", *, filters: Iterable = (), real: str = "double",
                      setpoint_weight: float = 1.0) -> list[Path]:
    """Stage the code export's files (:func:`code_texts`) in an output transaction
    (:class:`prsa_ctrl.io.output.Transaction`): written with the run's other outputs, all or none.
    Returns the files staged."""
    texts = code_texts(controller, plant, os.fspath(path), filters=filters, real=real, setpoint_weight=setpoint_weight)
    for f, text in texts.items():
        outputs.stage(f, lambda tmp, text=text: tmp.write_text(text, encoding="utf-8"), flag)
    return list(texts)


def write_code_export(path: "str | os.PathLike", controller: "PID | CascadeDesign", plant: "Plant", inputs: Iterable = (),
                      flag: str = "--export", *, filters: Iterable = (), real: str = "double",
                      setpoint_weight: float = 1.0) -> list[Path]:
    """The code export written on its own (source and header all or none, never onto an input).
    Returns the files written."""
    from .output import Transaction

    with Transaction(inputs) as outputs:
        files = stage_code_export(outputs, path, controller, plant, flag, filters=filters, real=real,
                                  setpoint_weight=setpoint_weight)
        outputs.commit()
    return files


def max_relative_difference(a: Sequence[float], b: Sequence[float]) -> float:
    """``max |a - b| / max |b|`` (0 for two zero sequences)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    scale = float(np.max(np.abs(b))) if b.size else 0.0
    d = float(np.max(np.abs(a - b))) if a.size else 0.0
    return d / scale if scale > 0 else d
