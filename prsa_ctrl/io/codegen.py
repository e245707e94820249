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

(``'`` marks the value of the previous sample.) The speed and position differences are taken in
integer counts from raw 32-bit counters, wrap-safe (a multi-turn counter wrapping at 2^32, also a
signed INTEGER32 such as CiA 402 0x6064 crossing 2^31, or a single-turn counter in ``[0, N)``
with ``N`` counts per revolution); the simulator takes them from the angles in rad, which differs
by round-off only (measured below 1e-12 of the largest command in double on the paper scenes,
``tests/io/test_codegen.py``). In ``float`` the position error is formed in float: its
resolution is 2^-24 of the travel from the start (measured: up to 81 counts at 1 m of travel
of the paper plant, 20-bit encoder, 2 mm lead; the reference in m is itself a float); use
``double`` for long travel in float-capable firmware (the speed loop is not affected).

The generated code is for firmware and PLCs: run-time parameters (gains, limits, filter
coefficients; C also computes them from physical values), enable and hold inputs, a sticky fault
word with a defined, finite output on a non-finite input or result (the sample is skipped: the
last command is held, no state changes), flushing of tiny states (no subnormal numbers), unique
internal names, ``extern "C"`` and float-only arithmetic in the float build. The Structured
Text compiles with matiec's ``iec2c`` and its C equals the toolkit's C bit for bit
(``tests/io/test_codegen.py``); :func:`prsa_ctrl.io.plcopen.plcopen_xml` writes the function
block as PLCopen XML (``export_code`` with a ``.xml`` path).
User text (the plant name) reaches every file only through :func:`inert_text`.

:class:`ReferenceLaw` runs the same law in Python exactly as the simulator writes it (angles in
rad, the simulator's order of operations): it reproduces a recorded run's torque command
bit for bit or to round-off (:func:`replay_inputs` takes the inputs from a run).

Examples
--------
>>> from prsa_ctrl import load_plant, PID
>>> law = drive_law(PID(0.085, 14.7), load_plant())
>>> h, c = c_code(law, name="spd")
>>> "void spd_init(" in h and "spd_real spd_step(const spd_params *p, spd_state *s" in h
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
from ..options import check_number
from .drivelaw import Biquad as _Biquad, DriveLaw, FilterSpec, PositionLaw  # noqa: F401
from .codetext import IEC_RESERVED, REAL_TYPES, c_code, iec_real, inert_text, is_code_name, check_header_name, st_code, st_parts  # noqa: F401

if TYPE_CHECKING:
    from ..tuning.cascade import CascadeDesign
    from ..drive.measurement import PositionLoop
    from .output import Transaction
    from ..plant.plantfile import Plant
    from ..sim.engine import SimRun

__all__ = ["DriveLaw", "PositionLaw", "drive_law", "ReferenceLaw", "replay_inputs", "c_code", "st_code",
           "export_code", "code_texts", "code_files", "check_code_export", "write_code_export", "CODE_SUFFIXES",
           "REAL_TYPES", "FilterSpec", "inert_text", "iec_real", "plant_assumptions", "IEC_RESERVED"]

#: File suffixes :func:`export_code` writes (``--export PATH.c`` / ``PATH.st`` / ``PATH.xml``).
CODE_SUFFIXES = (".c", ".st", ".xml")

def position_law(position: "PositionLoop", plant: "Plant") -> PositionLaw:
    """The numbers of a :class:`~prsa_ctrl.drive.measurement.PositionLoop` on ``plant``."""
    a = float(plant.lead_per_rad)
    unit = position.unit_m(a)
    nut = position.measured == "nut_angle"
    return PositionLaw(position.measured, int(position.rate), float(position.kv), float(position.ki),
                       float(position.kvff), float(position.kaff), a, float(plant.reflected_inertia_kg_m2), unit,
                       unit / a, 2.0 * math.pi / plant.encoder_counts if nut else float(position.scale_resolution_m),
                       None if position.friction is None else position.friction.key(), int(position.delay))


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
    b = check_number("setpoint_weight", setpoint_weight, 0.0)
    if b > 1.0:
        raise ValueError(f"setpoint_weight = {setpoint_weight!r}; expected a setpoint weight b in [0, 1]")
    ts = float(plant.sample_time_s)
    lfs = loop_filters(filters, ts)
    bq = {pl: tuple(tuple(lf.biquad(ts).as_dict().values()) for lf in lfs if lf.place == pl)
          for pl in ("speed_measurement", "torque_command")}
    specs = {pl: tuple(_filter_spec(lf) for lf in lfs if lf.place == pl) for pl in ("speed_measurement", "torque_command")}
    pos = None
    if position is not None:
        from ..drive.measurement import PositionLoop

        if not isinstance(position, PositionLoop):
            raise ValueError(f"position = {position!r}; expected a PositionLoop")
        pos = position_law(position, plant)
    return DriveLaw(ts, float(plant.torque_limit), 2.0 * math.pi / plant.encoder_counts,
                    math.exp(-ts / float(plant.speed_filter_s)), float(controller.kp), float(controller.ki),
                    float(controller.kd), float(controller.tf), check_number("feedforward_torque_n_m", feedforward_torque_n_m),
                    bq["speed_measurement"], bq["torque_command"], pos, int(delay_samples), b, plant.name,
                    specs["speed_measurement"], specs["torque_command"],
                    plant_assumptions(plant, pos, [lf for lf in lfs], int(delay_samples)))


def _filter_spec(lf: Any) -> FilterSpec:
    f = lf.filter
    (n2, n1, n0), (d2, d1, d0) = f.coefficients()
    pars = ", ".join(f"{k} = {v:.6g}" for k, v in f.parameters().items())
    how = ("Tustin prewarped at %.6g Hz" % f.characteristic_hz if lf.method == "tustin" and lf.prewarp else
           "Tustin (s = (2/Ts)(z - 1)/(z + 1))" if lf.method == "tustin" else
           "zero-order hold (step invariant)" if lf.method == "zoh" else "matched pole-zero (z = exp(s Ts))")
    return FilterSpec(f"{f.kind} ({pars}) on the {lf.place.replace('_', ' ')}: {how}", (float(n2), float(n1), float(n0)),
                      (float(d2), float(d1), float(d0)), lf.method == "tustin",
                      float(f.characteristic_hz) if lf.method == "tustin" and lf.prewarp else 0.0)


def plant_assumptions(plant: "Plant", pos: "PositionLaw | None", lfs: Sequence[Any] = (),
                      delay_samples: int = 1) -> tuple[tuple[str, str, str], ...]:
    """What the gains assume about the plant and the drive: ``((what, value, source), ...)``;
    ``source`` is the plant file's source text of the value (user text: every writer passes it
    through :func:`inert_text`), empty for what the toolkit itself decides. Written into every
    export (C and ST headers, PLCopen XML, TOML/JSON; see :func:`assumption_lines`)."""
    ts = float(plant.sample_time_s)
    src = plant.sources

    def s(key: str) -> str:
        return str(src.get(key, "")) if key in src else "default"

    bw = float(plant.values["drive.current_loop_bandwidth_hz"])
    dly = int(plant.command_delay_samples)
    tot = dly + int(delay_samples)
    out = [("loop period", f"Ts = {ts:.6g} s ({1.0 / ts:.6g} Hz), the speed-loop sample time", s("sensor.sample_time_s")),
           ("reflected inertia", f"J = {float(plant.reflected_inertia_kg_m2):.6g} kg m^2 at the motor shaft (derived "
                                 f"from the plant's masses and inertias, mechanism {plant.mechanism})", ""),
           ("current-loop bandwidth", f"{bw:.6g} Hz (first-order lag, time constant {1.0 / (2 * math.pi * bw):.6g} s)",
            s("drive.current_loop_bandwidth_hz")),
           ("command delay", f"{tot} sample(s) = {tot * ts:.6g} s from the measurement to the current loop: "
                             f"{delay_samples} of computation (this code) + {dly} of the drive",
            s("drive.command_delay_samples")),
           ("encoder resolution", f"{int(plant.encoder_counts)} counts/rev = {2 * math.pi / plant.encoder_counts:.6g} "
                                  "rad/count", s("sensor.encoder_counts_per_rev")),
           ("speed measurement", f"backward difference of the counts through a first-order low-pass tau = "
                                 f"{float(plant.speed_filter_s):.6g} s, discretised pole-matched (a = exp(-Ts/tau))",
            s("sensor.speed_filter_time_constant_s")),
           ("torque limit", f"{float(plant.torque_limit):.6g} N m", s("drive.torque_limit_n_m")),
           ("speed PI(D) discretisation", "explicit Euler integral (ki Ts/(z - 1)), derivative filter pole-matched "
                                          "(beta = exp(-Ts/tf))", "")]
    for i, lf in enumerate(lfs):
        out.append((f"filter {i + 1}", _filter_spec(lf).description, ""))
    if pos is not None:
        out.append(("position loop", f"every {pos.rate} sample(s) (Tp = {pos.rate * ts:.6g} s), measured {pos.measured}, "
                                     "explicit integral, zero-order hold of its outputs", ""))
    out.append(("if the drive's rates differ", "the gains were tuned for exactly this period and delay: a drive whose "
                "loop runs at another period, or a fieldbus or PLC adding cycles between measurement and current loop, "
                "is a different plant (phase margin lost: about 360 deg x f_c x the added delay at the crossover "
                "frequency f_c), so re-export for its period and delay (plant keys sensor.sample_time_s, "
                "drive.command_delay_samples) instead of reusing these numbers", ""))
    return tuple(out)


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
        self.pending = [(0.0, 0.0)] * (lw.position.delay if lw.position is not None else 0)
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
                if pl.delay:  # the position loop's computation delay: the oldest pending pair is applied
                    self.pending = [(self.w_ref, self.tau_p)] + self.pending
                    self.w_ref, self.tau_p = self.pending.pop()
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


def export_code(controller: "PID | CascadeDesign | DriveLaw", plant: "Plant | None", path: "str | Path", *,
                filters: Iterable = (), real: str = "double", name: str | None = None,
                delay_samples: int = 1, differences: str = "counts", setpoint_weight: float = 1.0) -> list[Path]:
    """Write the controller as code, chosen by the suffix of ``path``: ``.c`` writes the C source
    and its header (``.h``) beside it, ``.st`` the Structured Text function block, ``.xml`` the
    same block as PLCopen TC6 XML (:func:`prsa_ctrl.io.plcopen.plcopen_xml`).

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
        identifier that is no IEC keyword or standard block name, else ``prsa_ctrl``.
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
    if real not in REAL_TYPES:
        raise ValueError(f"real = {real!r}; expected one of {', '.join(REAL_TYPES)}")
    if differences != "counts":
        raise ValueError(f"differences = {differences!r}; expected 'counts' (wrap-safe integer differences; the "
                         "'angle' variant, which needed unwrapped 64-bit counts, was removed)")
    law = controller if isinstance(controller, DriveLaw) else drive_law(
        controller, plant, filters=filters, delay_samples=delay_samples, setpoint_weight=setpoint_weight)
    if name is None:  # the file's stem when it is a safe identifier (no keyword, no standard block name)
        name = path.stem if is_code_name(path.stem) else "prsa_ctrl"
    if suffix == ".st":
        return {path: st_code(law, name=name, real=real, differences=differences)}
    if suffix == ".xml":
        from .plcopen import plcopen_xml

        return {path: plcopen_xml(law, name=name, real=real)}
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

    if Path(path).suffix.lower() == ".c":
        from ..errors import OutputError

        try:
            check_header_name(Path(path).with_suffix(".h").name)
        except ValueError as exc:
            raise OutputError(f"{flag} {os.fspath(path)!r}: {exc}") from None
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
