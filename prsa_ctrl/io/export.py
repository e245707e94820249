"""Export of the tuned speed controller (and filters) for a drive, as JSON or TOML.

:func:`export_controller` gathers everything a drive needs to run the speed PI(D) at its
sample time ``Ts`` (s); :func:`dumps` writes it (TOML by hand, readable with ``tomllib``).

Continuous form (SI, derivative on the measured speed ``w``, error ``e = w_ref - w``)::

    u = kp e + ki integral(e) - kd s/(1 + tf s) w + tau_ff           C(s) = kp + ki/s + kd s/(1 + tf s)

Vendor forms: ``Kp`` [N m s/rad], ``Tn = kp/ki`` [s] (integral/reset time), ``Kp`` per rpm
[N m/rpm] ``= kp 2 pi/60``, ``Tv = kd/kp`` [s] (derivative time), per-unit gains on a rated
torque ``T_r`` and speed ``w_r``: ``Kp_pu = kp w_r/T_r``, ``Ki_pu = ki w_r/T_r`` [1/s]. ``Kv``
[1/s] is the position-loop gain: it belongs to a cascade export and is absent (TOML) or null
(JSON) for the speed-only design.

Discrete law exactly as the simulator's sampled drive runs it at sample ``k`` (time ``k Ts``)::

    e[k]   = w_ref[k] - w[k]
    d[k]   = beta d[k-1] + (1 - beta) (w[k] - w[k-1]) / Ts          beta = exp(-Ts/tf)
    u[k]   = kp (b w_ref[k] - w[k]) + I[k] - kd d[k] + tau_ff      (b = 1: kp e[k])
    us[k]  = min(max(u[k], -u_max), u_max)
    I[k+1] = I[k] + Ts (ki e[k] + (ki/kp) (us[k] - u[k]))          (explicit Euler, tracking anti-windup)
    the command us[k] is applied over [(k+1) Ts, (k+2) Ts)          (one-sample computation delay, ZOH)

with the 2-DOF setpoint weight ``b`` (``setpoint_weight``, dimensionless, 1 unless a duty
cycle's ``[tuning] setpoint_weight`` sets it; the simulator runs ``b != 1`` as the 1-DOF law on
the setpoint through :func:`prsa_ctrl.studies.autotune.setpoint_prefilter`, the same law while the
command is within the limit), i.e. from the error
``C(z) = kp + ki Ts/(z - 1) + kd (1 - beta)(z - 1)/(Ts (z - beta))`` (the same as
:meth:`prsa_ctrl.drive.pid.PID.to_tf` with ``dt = Ts``). ``w`` is the drive's speed
measurement: the backward difference of the quantised encoder angle through a first-order
low-pass ``w[k] = a w[k-1] + (1 - a)(theta[k] - theta[k-1])/Ts``, ``a = exp(-Ts/tau_w)``.

Alternative discretisations of ``C(s)`` as one biquad ``(b0 + b1/z + b2/z^2)/(1 + a1/z + a2/z^2)``
(``b`` in N m s/rad, acting on the error; with ``kd > 0`` these put the derivative on the
error): forward Euler ``s = (z - 1)/Ts``, backward Euler ``s = (z - 1)/(Ts z)``, Tustin
``s = (2/Ts)(z - 1)/(z + 1)``.

Examples
--------
>>> from prsa_ctrl import load_plant, PID
>>> d = export_controller(PID(0.085, 14.7), load_plant(), fmt="toml")
>>> d["speed_controller"]["vendor"]["tn_s"] == 0.085 / 14.7
True
>>> import tomllib
>>> tomllib.loads(dumps(d, "toml")) == d
True
"""

from __future__ import annotations

import json
import math
from typing import TYPE_CHECKING, Any, Iterable

import numpy as np

from ..drive.pid import PID
from ..options import RAD_S_PER_RPM, check_number
from ..drive.filters import Filter, FirstOrderLowPass

if TYPE_CHECKING:
    from ..plant.plantfile import Plant
    from ..tuning.cascade import CascadeDesign

__all__ = ["export_controller", "export_cascade", "dumps", "FORMATS", "FILTER_PLACES", "pid_biquad",
           "simulated_biquad", "DISCRETISATIONS", "POSITION_LAW", "toml_value", "toml_string", "export_assumptions"]

#: Output formats of :func:`dumps`.
FORMATS = ("json", "toml")
#: Where a filter sits in the loop.
FILTER_PLACES = ("torque_command", "speed_measurement")
#: Substitutions ``s = N(z)/D(z)`` (``N``, ``D`` as coefficients of ``z^1, z^0``, times ``1/Ts``).
DISCRETISATIONS = {
    "forward_euler": ("s = (z - 1)/Ts", (1.0, -1.0), (0.0, 1.0)),
    "backward_euler": ("s = (z - 1)/(Ts z)", (1.0, -1.0), (1.0, 0.0)),
    "tustin": ("s = (2/Ts) (z - 1)/(z + 1)", (2.0, -2.0), (1.0, 1.0)),
}

_RPM = RAD_S_PER_RPM  # rad/s per rpm


def _pid_s_polynomials(pid: PID) -> tuple[list[float], list[float]]:
    """Minimal ``C(s) = num(s)/den(s)``, coefficients highest power first."""
    kp, ki, kd, tf = float(pid.kp), float(pid.ki), float(pid.kd), float(pid.tf)
    if kd > 0:  # kp + ki/s + kd s/(1 + tf s) over s (1 + tf s)
        if ki > 0:
            return [kp * tf + kd, kp + ki * tf, ki], [tf, 1.0, 0.0]
        return [kp * tf + kd, kp], [tf, 1.0]
    if ki > 0:
        return [kp, ki], [1.0, 0.0]
    return [kp], [1.0]


def pid_biquad(pid: PID, ts: float, method: str) -> dict[str, float]:
    """``C(s) = kp + ki/s + kd s/(1 + tf s)`` discretised by substitution (see
    :data:`DISCRETISATIONS`) as normalised biquad coefficients.

    For ``C(s) = sum c_i s^i / sum g_i s^i`` of order ``n`` and ``s = N(z)/(Ts D(z))``:
    ``num(z) = sum c_i Ts^-i N^i D^(n-i)``, likewise ``den``, both divided by the leading
    coefficient of ``den``; missing powers are zero (a PI is first order: ``b2 = a2 = 0``).

    Parameters
    ----------
    pid : PID
    ts : float, s
    method : {"forward_euler", "backward_euler", "tustin"}

    Returns
    -------
    dict
        ``b0, b1, b2`` (N m s/rad) and ``a1, a2`` (dimensionless).

    Examples
    --------
    >>> c = pid_biquad(PID(0.085, 14.7), 2.5e-4, "forward_euler")
    >>> round(c["b0"], 6), round(c["b1"], 6), c["a1"]
    (0.085, -0.081325, -1.0)
    """
    if not isinstance(pid, PID):
        raise ValueError(f"pid = {pid!r}; expected a prsa_ctrl.PID")
    if isinstance(ts, bool) or not isinstance(ts, (int, float)) or not math.isfinite(ts) or ts <= 0:
        raise ValueError(f"ts = {ts!r}; expected a finite sample time > 0 s")
    if method not in DISCRETISATIONS:
        raise ValueError(f"method = {method!r}; expected one of {', '.join(DISCRETISATIONS)}")
    _, nz, dz = DISCRETISATIONS[method]
    num, den = _pid_s_polynomials(pid)
    n = len(den) - 1
    npoly, dpoly = np.array(nz) / ts, np.array(dz)

    def sub(c: list[float]) -> np.ndarray:
        c = [0.0] * (n + 1 - len(c)) + list(c)
        out = np.zeros(n + 1)
        for i, ci in enumerate(reversed(c)):  # ci multiplies s^i
            out = out + ci * np.convolve(_pow(npoly, i), _pow(dpoly, n - i))  # length n + 1
        return out

    b, a = sub(num), sub(den)
    b, a = b / a[0], a / a[0]
    b = np.concatenate([b, np.zeros(3 - len(b))])
    a = np.concatenate([a, np.zeros(3 - len(a))])
    return {"b0": float(b[0]), "b1": float(b[1]), "b2": float(b[2]), "a1": float(a[1]), "a2": float(a[2])}


def simulated_biquad(pid: PID, ts: float) -> dict[str, float]:
    """The sampled drive's law as one biquad on the error, for a constant setpoint (then the
    derivative of ``-w`` is the derivative of ``e``): ``C(z) = kp + ki Ts/(z - 1) + kd g (z - 1)/(z - beta)``,
    ``g = (1 - beta)/Ts``, ``beta = exp(-Ts/tf)``, over the common denominator ``(z - 1)(z - beta)``
    (``z - 1`` for a PI, ``z - beta`` for a PD, ``1`` for a P).

    Parameters
    ----------
    pid : PID
    ts : float, s

    Returns
    -------
    dict
        ``b0, b1, b2`` (N m s/rad), ``a1, a2``.

    Examples
    --------
    >>> c = simulated_biquad(PID(0.085, 14.7), 2.5e-4)
    >>> round(c["b0"], 6), round(c["b1"], 6), c["a1"], c["a2"]
    (0.085, -0.081325, -1.0, 0.0)
    """
    kp, ki, kd = float(pid.kp), float(pid.ki), float(pid.kd)
    beta = math.exp(-ts / float(pid.tf))
    g = (1.0 - beta) / ts
    if kd > 0 and ki > 0:
        b = np.polyadd(np.polyadd(kp * np.poly([1.0, beta]), ki * ts * np.array([1.0, -beta])),
                       kd * g * np.poly([1.0, 1.0]))
        a = np.poly([1.0, beta])
    elif kd > 0:
        b, a = np.array([kp + kd * g, -kp * beta - kd * g]), np.array([1.0, -beta])
    elif ki > 0:
        b, a = np.array([kp, ki * ts - kp]), np.array([1.0, -1.0])
    else:
        b, a = np.array([kp]), np.array([1.0])
    b = np.concatenate([b, np.zeros(3 - len(b))])
    a = np.concatenate([a, np.zeros(3 - len(a))])
    return {"b0": float(b[0]), "b1": float(b[1]), "b2": float(b[2]), "a1": float(a[1]), "a2": float(a[2])}


def _pow(p: np.ndarray, k: int) -> np.ndarray:
    out = np.array([1.0])
    for _ in range(k):
        out = np.convolve(out, p)  # keeps leading zeros (np.polymul would trim them)
    return out


def placed_loop_filters(filters: Iterable) -> list:
    """The export's filters as :class:`prsa_ctrl.drive.filters.LoopFilter` (a bare Filter sits on
    the torque command, Tustin prewarped, as :func:`export_controller` states it)."""
    from ..drive.filters import LoopFilter

    out = []
    for item in filters:
        if isinstance(item, LoopFilter):
            out.append(item)
        elif isinstance(item, Filter):
            out.append(LoopFilter(item))
        elif isinstance(item, tuple) and len(item) == 2:
            out.append(LoopFilter(item[1], item[0]))
    return out


def _placed_filters(filters: Iterable) -> list[tuple[str, Filter, str]]:
    """``(place, filter, method the simulator runs)``; a ``LoopFilter`` keeps its own place and
    discretisation, a bare Filter sits on the torque command (Tustin, prewarped)."""
    from ..drive.filters import LoopFilter

    out = []
    for item in filters:
        if isinstance(item, LoopFilter):
            out.append((item.place, item.filter,
                        "biquad_tustin_prewarped" if item.method == "tustin" and item.prewarp else
                        ("biquad_" + item.method if item.method != "tustin" else "biquad_tustin")))
            continue
        place, f = ("torque_command", item) if isinstance(item, Filter) else (
            item if isinstance(item, tuple) and len(item) == 2 else (None, item))
        if place not in FILTER_PLACES or not isinstance(f, Filter):
            raise ValueError(f"filters entry {item!r}; expected a Filter or a (place, Filter) pair with place one "
                             f"of {', '.join(FILTER_PLACES)}")
        out.append((place, f, "biquad_tustin_prewarped"))
    return out


def export_assumptions(plant: "Plant", filters: Iterable = (), position: Any = None) -> dict:
    """What the exported gains assume about the plant and the drive (the ``assumptions`` table
    of every drive export and parameter set; the C/ST/XML headers say the same).

    Parameters
    ----------
    plant : Plant
    filters : iterable
        The loop filters as :func:`prsa_ctrl.drive.filters.loop_filters` takes them.
    position : PositionLoop, optional

    Returns
    -------
    dict
        SI numbers (names end in their unit), the discretisation of every filter, the source of
        each plant value (text from the plant file) and one sentence on what changes if the
        drive's rates differ.
    """
    from ..drive.filters import loop_filters
    from .codegen import plant_assumptions, position_law

    ts = float(plant.sample_time_s)
    lfs = loop_filters(filters, ts)
    bw = float(plant.values["drive.current_loop_bandwidth_hz"])
    drive_delay = int(plant.command_delay_samples)
    text = plant_assumptions(plant, None if position is None else position_law(position, plant), lfs, 1)
    sources = {k: str(plant.sources.get(k, "default")) for k in (
        "sensor.sample_time_s", "drive.current_loop_bandwidth_hz", "drive.command_delay_samples",
        "sensor.encoder_counts_per_rev", "sensor.speed_filter_time_constant_s", "drive.torque_limit_n_m")}
    out: dict[str, Any] = {
        "loop_period_s": ts,
        "loop_rate_hz": 1.0 / ts,
        "reflected_inertia_kg_m2": float(plant.reflected_inertia_kg_m2),
        "current_loop_bandwidth_hz": bw,
        "current_loop_time_constant_s": 1.0 / (2.0 * math.pi * bw),
        "computation_delay_samples": 1,
        "drive_delay_samples": drive_delay,
        "command_delay_samples": 1 + drive_delay,
        "command_delay_s": (1 + drive_delay) * ts,
        "encoder_counts_per_rev": int(plant.encoder_counts),
        "encoder_rad_per_count": 2.0 * math.pi / plant.encoder_counts,
        "speed_filter_time_constant_s": float(plant.speed_filter_s),
        "speed_filter_discretisation": "pole-matched: w[k] = a w[k-1] + (1 - a)(theta[k] - theta[k-1])/Ts, "
                                       "a = exp(-Ts/tau)",
        "speed_controller_discretisation": "explicit Euler integral ki Ts/(z - 1); derivative filter pole-matched, "
                                           "beta = exp(-Ts/tf)",
        "torque_limit_n_m": float(plant.torque_limit),
        "filters": [t[1] for t in text if t[0].startswith("filter ")],
        "if_rates_differ": dict((k, v) for k, v, _ in text)["if the drive's rates differ"],
        "sources": sources,
    }
    if position is not None:
        out["position_loop_period_s"] = ts * int(position.rate)
        # the position loop's own computation delay, which the drive must have for the gains to hold
        out["position_delay_samples"] = int(getattr(position, "delay", 0))
        out["position_delay_s"] = out["position_delay_samples"] * ts * int(position.rate)
    return out


def export_controller(
    pid: PID,
    plant: "Plant",
    *,
    fmt: str,
    rated_torque_n_m: float | None = None,
    rated_speed_rpm: float | None = None,
    filters: Iterable = (),
    setpoint_weight: float = 1.0,
    design: dict | None = None,
) -> dict:
    """Everything a drive needs for the speed PI(D) and its filters at the plant's sample time.

    Parameters
    ----------
    pid : PID
        Speed controller (SI gains).
    plant : Plant
        Gives the sample time ``sample_time_s`` (s), the torque limit (N m), the encoder
        resolution and the speed-filter time constant (s).
    fmt : {"json", "toml"}
        Target format: TOML has no null, so fields that do not apply (``kv_per_s``,
        ``tn_s`` of a P controller) are left out there and null in JSON.
    rated_torque_n_m : float, N m, optional
    rated_speed_rpm : float, rpm, optional
        Rated motor torque and speed; both give the per-unit gains.
    filters : iterable of Filter or (place, Filter)
        Extra filters, ``place`` one of ``"torque_command"`` (default) and
        ``"speed_measurement"``; each is exported continuous and as biquads at the sample time.
    setpoint_weight : float
        2-DOF setpoint weight ``b`` in [0, 1] (dimensionless) of the proportional term,
        ``u = kp (b w_ref - w) + I`` (the scene's ``[tuning] setpoint_weight``; 1: the 1-DOF law).
    design : dict, optional
        Which design the file holds and why (``name``, ``why`` and optional ``basis``,
        ``yield``: str or float), written as the ``design`` table (e.g. the robust study's
        recommended design).

    Returns
    -------
    dict
        Nested plain data (str, float, int, bool, lists, dicts); every numeric field's name
        ends in its unit (``_s``, ``_n_m``, ``_per_s``, ...) or is documented as
        dimensionless in the ``units`` table.

    Raises
    ------
    ValueError
        For a bad argument (one line naming it and what was expected) or a filter frequency
        at or above the Nyquist frequency.
    """
    from .. import __version__
    from ..plant.plantfile import Plant

    if not isinstance(pid, PID):
        raise ValueError(f"pid = {pid!r}; expected a prsa_ctrl.PID")
    if not isinstance(plant, Plant):
        raise ValueError(f"plant = {plant!r}; expected a Plant (see prsa_ctrl.load_plant)")
    if fmt not in FORMATS:
        raise ValueError(f"fmt = {fmt!r}; expected one of {', '.join(FORMATS)}")
    t_r = check_number("rated_torque_n_m", rated_torque_n_m, 0.0, unit="N m", lo_open=True, optional=True)
    n_r = check_number("rated_speed_rpm", rated_speed_rpm, 0.0, unit="rpm", lo_open=True, optional=True)
    if (t_r is None) != (n_r is None):
        raise ValueError(f"rated_torque_n_m = {rated_torque_n_m!r}, rated_speed_rpm = {rated_speed_rpm!r}; "
                         "expected both (for the per-unit gains) or neither")
    if pid.kff > 0:
        raise ValueError(f"PID kff = {pid.kff:g}; expected 0 (the export covers the encoder-difference speed "
                         "measurement; the Kalman load-torque feed-forward is not exported)")
    if isinstance(setpoint_weight, bool) or not isinstance(setpoint_weight, (int, float)) \
            or not 0.0 <= setpoint_weight <= 1.0:
        raise ValueError(f"setpoint_weight = {setpoint_weight!r}; expected a setpoint weight b in [0, 1]")
    b_w = float(setpoint_weight)
    if design is not None and (not isinstance(design, dict) or not isinstance(design.get("name"), str) or not all(
            isinstance(v, (str, float, int)) and not isinstance(v, bool) for v in design.values())):
        raise ValueError(f"design = {design!r}; expected a dict with a 'name' and str or number values")
    filters = list(filters)
    placed = _placed_filters(filters)
    null = fmt == "json"

    def opt(d: dict, key: str, value: Any) -> None:
        if value is not None or null:
            d[key] = value

    ts = float(plant.sample_time_s)
    kp, ki, kd, tf, kff = (float(v) for v in (pid.kp, pid.ki, pid.kd, pid.tf, pid.kff))
    beta = math.exp(-ts / tf)
    tau_w = float(plant.speed_filter_s)
    speed_filter = FirstOrderLowPass.from_time_constant(tau_w)
    counts = int(plant.encoder_counts)

    continuous = {
        "transfer_function": "C(s) = kp + ki/s + kd s/(1 + tf s), error e = w_ref - w; derivative on the measured "
                             "speed w (no setpoint kick); 2-DOF: u = kp (b w_ref - w) + ki integral(e) - kd s/(1 + tf s) w "
                             "with b = setpoint_weight",
        "setpoint_weight": b_w,
        "kp_n_m_s_per_rad": kp,
        "ki_n_m_per_rad": ki,
        "kd_n_m_s2_per_rad": kd,
        "tf_s": tf,
        "kff": kff,
    }
    vendor: dict[str, Any] = {
        "kp_n_m_s_per_rad": kp,
        "kp_n_m_per_rpm": kp * _RPM,
    }
    opt(vendor, "tn_s", kp / ki if ki > 0 and kp > 0 else None)
    opt(vendor, "tv_s", kd / kp if kd > 0 and kp > 0 else None)
    vendor["ki_n_m_per_rpm_s"] = ki * _RPM
    opt(vendor, "kv_per_s", None)
    vendor["note"] = ("Tn = kp/ki (integral/reset time), Tv = kd/kp (derivative time), per-rpm gains use 1 rpm = "
                      "2 pi/60 rad/s; Kv (position-loop gain, 1/s) applies to the position loop of a cascade "
                      "export and is " + ("null" if null else "absent") + " for this speed-only design")
    law = {
        "sample_time_s": ts,
        "integrator": "explicit (forward) Euler: I[k+1] = I[k] + Ts (ki e[k] + k_aw (us[k] - u[k])); "
                      "ki/s -> ki Ts/(z - 1)",
        "derivative_filter": "d[k] = beta d[k-1] + (1 - beta) (w[k] - w[k-1])/Ts, beta = exp(-Ts/tf) "
                             "(pole matched at exp(-Ts/tf))",
        "equations": [
            "e[k] = w_ref[k] - w[k]",
            "d[k] = beta d[k-1] + (1 - beta) (w[k] - w[k-1]) / Ts",
            "u[k] = kp (b w_ref[k] - w[k]) + I[k] - kd d[k] + tau_ff   (b = setpoint_weight; b = 1: kp e[k])",
            "us[k] = min(max(u[k], -torque_limit), torque_limit)",
            "I[k+1] = I[k] + Ts (ki e[k] + k_aw (us[k] - u[k]))",
            "us[k] is applied over [(k+1) Ts, (k+2) Ts) (one-sample computation delay, zero-order hold)",
        ],
        "transfer_function": "C(z) = kp + ki Ts/(z - 1) + kd (1 - beta)(z - 1)/(Ts (z - beta)) (unsaturated, "
                             "derivative term on -w)",
        "kp_n_m_s_per_rad": kp,
        "ki_n_m_per_rad": ki,
        "kd_n_m_s2_per_rad": kd,
        "tf_s": tf,
        "setpoint_weight": b_w,
        "setpoint_weight_note": "b of u = kp (b w_ref - w) + I (dimensionless); the integral acts on the whole error "
                                "e = w_ref - w. The simulator runs b != 1 as this speed PI with b = 1 on the setpoint "
                                "filtered by F(z) = (b kp (1 - 1/z) + Ts ki/z)/(kp (1 - 1/z) + Ts ki/z) "
                                "(prsa_ctrl.studies.autotune.setpoint_prefilter): the same command while it is within the "
                                "torque limit; in steady state at w_ref = w the integral holds I = u - kp (b - 1) w_ref",
        "beta": beta,
        "integral_gain_ts_ki_n_m_s_per_rad": ts * ki,
        "anti_windup_gain_per_s": ki / max(kp, 1e-9),
        "anti_windup_note": "k_aw = ki/kp (tracking time Tn = kp/ki); kp is floored at 1e-9 N m s/rad",
        "torque_limit_n_m": float(plant.torque_limit),
        "computation_delay_samples": 1,
        "feedforward_torque_n_m": 0.0,
        "error_biquad": simulated_biquad(pid, ts),
        "error_biquad_note": "the same law as one biquad on e for a constant setpoint: u[k] = b0 e[k] + b1 e[k-1] "
                             "+ b2 e[k-2] - a1 u[k-1] - a2 u[k-2] (unsaturated; b in N m s/rad; with "
                             "setpoint_weight != 1 it describes the response to the measurement only)",
    }
    alternatives: dict[str, Any] = {
        "note": "C(s) discretised by substitution as one biquad on the error e (derivative on the error too): "
                "u[k] = b0 e[k] + b1 e[k-1] + b2 e[k-2] - a1 u[k-1] - a2 u[k-2]; b in N m s/rad, a "
                "dimensionless; with kd = 0 the PI is first order (b2 = a2 = 0)",
    }
    for name, (formula, _, _) in DISCRETISATIONS.items():
        c = pid_biquad(pid, ts, name)
        entry: dict[str, Any] = {"substitution": formula, **c}
        if kd > 0:  # image of the derivative-filter pole s = -1/tf: N(z) = s Ts D(z)
            _, (n1, n0), (d1, d0) = DISCRETISATIONS[name]
            sp = -ts / tf
            entry["derivative_pole"] = (sp * d0 - n0) / (n1 - sp * d1)
            entry["stable"] = bool(abs(entry["derivative_pole"]) < 1.0)
        alternatives[name] = entry

    speed_controller: dict[str, Any] = {
        "continuous": continuous,
        "vendor": vendor,
    }
    if t_r is not None and n_r is not None:
        w_r = n_r * _RPM
        speed_controller["per_unit"] = {
            "rated_torque_n_m": t_r,
            "rated_speed_rpm": n_r,
            "rated_speed_rad_s": w_r,
            "kp_pu": kp * w_r / t_r,
            "ki_pu_per_s": ki * w_r / t_r,
            "kd_pu_s": kd * w_r / t_r,
            "note": "torque in units of the rated torque, speed in units of the rated speed: "
                    "Kp_pu = kp w_r/T_r (dimensionless), Ki_pu = ki w_r/T_r (1/s), Kd_pu = kd w_r/T_r (s)",
        }
    speed_controller["discrete"] = law
    speed_controller["alternatives"] = alternatives

    a = math.exp(-ts / tau_w)
    measurement = {
        "kind": "encoder_difference",
        "formula": "w[k] = a w[k-1] + (1 - a) (theta_q[k] - theta_q[k-1]) / Ts, a = exp(-Ts/tau)",
        "encoder_counts_per_rev": counts,
        "quantisation_rad": 2.0 * math.pi / counts,
        "filter_time_constant_s": tau_w,
        "filter_corner_hz": speed_filter.corner_hz,
        "a": a,
        "biquad": speed_filter.biquad(ts, "matched").as_dict(),
        "biquad_note": "the same low-pass as a biquad (matched, zero at z = 0): b0 = 1 - a, a1 = -a",
    }

    out: dict[str, Any] = {
        "format": "prsa-ctrl drive export",
        "format_version": 1,
        "prsa_ctrl_version": __version__,
        "plant": plant.name,
        "loop": "speed",
        **({"design": dict(design)} if design is not None else {}),
        "sample_time_s": ts,
        "torque_limit_n_m": float(plant.torque_limit),
        "command_delay_samples": plant.command_delay_samples,
        "command_delay_note": "the plant's drive.command_delay_samples: samples the drive adds between us[k] leaving "
                              "the controller and the current loop acting on it (beyond the one-sample computation "
                              "delay of the law); the design was tuned and verified with it",
        "units": {
            "speed": "rad/s (nut/motor shaft)",
            "torque": "N m (torque command)",
            "kp": "N m s/rad",
            "ki": "N m/rad",
            "kd": "N m s^2/rad",
            "setpoint_weight": "dimensionless (2-DOF weight b of the setpoint in the proportional term)",
            "biquad": "b0..b2 in output per input unit, a1, a2 dimensionless, a0 = 1",
        },
        "speed_measurement": measurement,
        "speed_controller": speed_controller,
        "assumptions": export_assumptions(plant, placed_loop_filters(filters)),
    }
    if placed:
        out["filters"] = [
            {
                "place": place,
                **f.to_dict(),
                "sample_time_s": ts,
                "biquad_tustin_prewarped": f.biquad(ts, "tustin", True).as_dict(),
                "biquad_zoh": f.biquad(ts, "zoh").as_dict(),
                "biquad_matched": f.biquad(ts, "matched").as_dict(),
                "formula": "y[k] = b0 x[k] + b1 x[k-1] + b2 x[k-2] - a1 y[k-1] - a2 y[k-2]; tustin: s = K (z - 1)/"
                           "(z + 1), K = w0/tan(w0 Ts/2) at the corner/centre w0; zoh: step invariant; matched: "
                           "z = exp(s Ts), zeros at infinity at z = 0, DC gain matched",
                **({"biquad_tustin": f.biquad(ts, "tustin", False).as_dict()} if sim == "biquad_tustin" else {}),
                "simulated": True,
                "simulated_biquad": sim,
            }
            for place, f, sim in placed
        ]
        out["filters_note"] = (
            "the sampled-loop simulator runs each filter as its simulated_biquad, in the order listed: "
            "speed_measurement filters on w[k] before the PID (e, I and the derivative all use the filtered speed); "
            "torque_command filters on us[k], then min(max(y, -torque_limit), torque_limit) is stored and applied "
            "over the next sample (the biquad recursion keeps its unlimited y)")
    return out


# --- cascade (position loop over the speed loop) ------------------------------------------------

#: The position loop's per-sample law as the drive export states it (``position_controller.law``):
#: each right-hand side is an expression in the exported fields of ``position_controller`` and
#: the signals ``p_ref, p_meas, v_ref, acc_ref, I_prev`` (the same law as
#: :meth:`prsa_ctrl.drive.measurement.PositionLoop.update`).
POSITION_LAW = {
    "e": "(p_ref - p_meas) * error_to_rad",
    "I": "I_prev + sample_time_s * ki_per_s2 * e",
    "w_ref": "kv_per_s * e + I + velocity_feedforward * v_ref / lead_m_per_rad",
    "tau_ff": "torque_per_acceleration_n_m_s2_per_rad * acc_ref / lead_m_per_rad",
}


def export_cascade(design: "CascadeDesign", plant: "Plant", *, fmt: str,
                   friction_table_speed_rad_s: float | None = None) -> dict:
    """Drive export of a cascade: the speed PI as :func:`prsa_ctrl.io.export.export_controller`
    gives it, plus the position loop (``Kv`` [1/s], integral gain, feed-forward gains, the
    acceleration feed-forward as a torque per acceleration, the position-loop sample time and
    the discrete law).

    Parameters
    ----------
    design : CascadeDesign
        With a friction feed-forward in its position loop (``PositionLoop.friction``), the
        export carries its formula and coefficients (``position_controller.friction_feedforward``).
    plant : Plant
    fmt : {"json", "toml"}
    friction_table_speed_rad_s : float, rad/s, optional
        Also tabulate the friction feed-forward from minus to plus this nut speed (21 points).

    Returns
    -------
    dict
    """
    filters = tuple(getattr(design, "filters", ()))
    out = export_controller(design.speed, plant, fmt=fmt, **({"filters": filters} if filters else {}))
    pos = design.position
    ts = plant.sample_time_s
    tp = ts * pos.rate
    a = plant.lead_per_rad
    inertia = float(plant.reflected_inertia_kg_m2)
    out["loop"] = "position over speed"
    ctrl = out["speed_controller"]
    if "vendor" in ctrl and isinstance(ctrl["vendor"], dict):
        ctrl["vendor"]["kv_per_s"] = float(pos.kv)
        ctrl["vendor"]["note"] = ("Tn = kp/ki (integral/reset time), Tv = kd/kp (derivative time), per-rpm gains use "
                                  "1 rpm = 2 pi/60 rad/s; Kv = kv_per_s is the gain of the position loop over this "
                                  "speed loop (see position_controller)")
    law = dict(POSITION_LAW)
    out["assumptions"] = export_assumptions(plant, (), pos)
    out["position_controller"] = {
        "measured": pos.measured,
        "sample_time_s": tp,
        "delay_samples": int(pos.delay),  # its own computation delay, in position-loop samples
        "delay_s": tp * int(pos.delay),
        "kv_per_s": float(pos.kv),
        "kv_m_min_per_mm": float(pos.kv) * 60.0 / 1000.0,  # (m/min of speed) per mm of error
        "ki_per_s2": float(pos.ki),
        "tn_s": float(pos.kv / pos.ki) if pos.ki > 0 else None,
        "velocity_feedforward": float(pos.kvff),
        "acceleration_feedforward": float(pos.kaff),
        "reflected_inertia_kg_m2": inertia,
        "torque_per_acceleration_n_m_s2_per_rad": float(pos.kaff) * inertia,
        "lead_m_per_rad": a,
        "error_to_rad": 1.0 if pos.measured == "nut_angle" else 1.0 / a,
        "law": law,
        "formula": "; ".join(f"{k}[k] = {v}" for k, v in law.items())
                   + " (p_ref, p_meas in the measured unit: rad of the nut for nut_angle, m for screw_position; "
                     "v_ref in m/s, acc_ref in m/s^2 of screw travel; I_prev = I[k-1], 0 at rest); w_ref (rad/s) "
                     "is the speed PI's reference and tau_ff (N m) is added to its command u[k]; both held for "
                     "sample_time_s. torque_per_acceleration_n_m_s2_per_rad already contains "
                     "acceleration_feedforward (= acceleration_feedforward reflected_inertia_kg_m2): do not "
                     "multiply by it again",
        "discretisation": "explicit sum for the integral (I updated with e[k] before use), zero-order hold of w_ref "
                          "and tau_ff over sample_time_s" + (
                              f"; w_ref and tau_ff computed at position-loop sample k are applied from sample k + "
                              f"{int(pos.delay)} on (delay_samples: the position loop's computation delay)"
                              if pos.delay else "; applied at the sample they are computed at (delay_samples 0)"),
    }
    if pos.friction is not None:  # issue 24: the plant's friction curve fed forward from the reference speed
        out["position_controller"]["friction_feedforward"] = pos.friction.as_dict(friction_table_speed_rad_s)
        out["position_controller"]["friction_feedforward"]["note"] = (
            "add tau_f(w) to tau_ff at every position-loop sample, w = v_ref / lead_m_per_rad (rad/s of the nut): "
            "the plant's sliding friction at the reference speed")
    if fmt == "toml":
        out["position_controller"] = {k: v for k, v in out["position_controller"].items() if v is not None}
    return out


# --- writers -----------------------------------------------------------------------------------

def toml_string(s: str, ascii_only: bool = True, where: str = "value") -> str:
    r"""``s`` as a TOML basic string that ``tomllib`` reads back as exactly ``s``
    (:func:`prsa_ctrl.plant.writer.toml_string`, the package's one TOML string writer: quotes,
    backslashes, control characters, bidirectional marks escaped, and with ``ascii_only``
    every non-ASCII character too).

    Raises
    ------
    ValueError
        A lone surrogate (no Unicode scalar value, not representable in TOML), naming ``where``.

    >>> print(toml_string('a"b\\c'), toml_string("\U0001F600"), toml_string("\x7f"))
    "a\"b\\c" "\U0001F600" "\u007F"
    """
    from ..plant.writer import toml_string as one

    return one(s, where, ascii_only=ascii_only)


def toml_value(v: Any, where: str = "value", *, ascii_only: bool = True) -> str:
    """A TOML value: bool, integer, finite float (all digits, ``repr``), string
    (:func:`toml_string`: ASCII with ``\\uXXXX``/``\\UXXXXXXXX`` escapes unless ``ascii_only`` is
    false), or a list of those (:func:`prsa_ctrl.plant.writer.data_value`: the package's one
    TOML writer).

    Raises
    ------
    ValueError
        A non-finite number, None or another type, naming ``where``.

    >>> toml_value([1, 2.5, "x"]), toml_value(True), toml_value("µ", ascii_only=False)
    ('[1, 2.5, "x"]', 'true', '"µ"')
    """
    from ..plant.writer import data_value

    return data_value(v, where, ascii_only=ascii_only)


def dumps(data: dict, fmt: str) -> str:
    """The export ``data`` as JSON or TOML text.

    TOML is written by :func:`prsa_ctrl.plant.writer.data_lines` (scalars, lists of scalars,
    tables, arrays of tables) so that
    ``tomllib.loads(dumps(d, "toml")) == d`` for any export dict; floats keep all digits
    (``repr``).

    Parameters
    ----------
    data : dict
        From :func:`export_controller` (or any dict of plain data).
    fmt : {"json", "toml"}

    Returns
    -------
    str
        Text ending with a newline.

    Raises
    ------
    ValueError
        Unknown ``fmt``; for TOML, a null or non-finite value (named by its key path).
    """
    if fmt not in FORMATS:
        raise ValueError(f"fmt = {fmt!r}; expected one of {', '.join(FORMATS)}")
    if not isinstance(data, dict):
        raise ValueError(f"data = {type(data).__name__}; expected a dict")
    if fmt == "json":
        try:
            return json.dumps(data, indent=2, allow_nan=False) + "\n"
        except ValueError as exc:
            raise ValueError(f"export data: {exc}; expected finite numbers") from None
    from .codetext import inert_text

    from ..plant.writer import data_lines  # the package's one TOML writer

    lines = [f"# {inert_text(data.get('format', 'prsa-ctrl export'), 80)} (TOML)", *data_lines(data)]
    return "\n".join(lines) + "\n"
