"""Drive units and vendor parameter sets: the tuned loops in the units a drive takes.

**Motor data** (:class:`MotorData`): torque constant ``k_T`` (N m per A RMS; or from the
back-EMF constant ``k_E``, line-to-line, RMS or peak, in V/krpm or V s/rad: for a sinusoidal
permanent-magnet motor the power balance ``3 E_ph,rms I_rms = T w`` with ``E_ph = E_LL/sqrt(3)``
gives ``k_T = sqrt(3) k_E,LL,rms`` (k_E in V s/rad) ``= sqrt(3/2) k_E,LL,peak``; one V/krpm is
``1/(1000 2 pi/60)`` V s/rad), rated current (A RMS), rated torque (N m), rated speed (rpm) and
pole pairs. From Python
(``MotorData(...)``), a small TOML file with a ``[motor]`` table (:func:`load_motor`), a
``key=value,...`` text (:func:`parse_motor`, the CLI's ``--motor``), or the plant's values
``motor.<key>`` when a plant schema carries them (:func:`motor_from_plant`; the current schema has
no motor section, so this returns None there).

**Drive units** (:func:`drive_units`): the speed PI as current per speed (A/(rad/s), A/rpm), per
unit of rated torque, and the position loop's ``Kv`` in 1/s and (m/min)/mm, with the
conventions stated in the output.

**Vendor parameter sets** are data files (``prsa_ctrl/templates/*.toml``, or any copy the user
edits): each ``[[parameter]]`` names a drive object (index or parameter number), the toolkit
quantity it holds (:data:`QUANTITIES`), the unit the drive expects (:data:`UNIT_FACTORS` gives
the conversion), whether the index and unit were confirmed in the vendor's public documentation,
and the source. A parameter marked ``confirmed = true`` must cite where (:func:`citation_problems`:
an https page, or a ``document`` naming the manual and its edition or version); one that does not
is listed as not confirmed in the filled set. :func:`fill_template` writes the values;
:func:`read_parameter_set` converts a filled file back to SI and
:func:`controller_from_parameter_set` rebuilds the controller from it.

Examples
--------
>>> m = MotorData.from_back_emf(75.0, rated_torque_n_m=3.0)
>>> round(m.torque_constant_n_m_per_a, 4)
1.2405
>>> round(drive_units(PID(0.085, 14.7), m)["speed"]["kp_a_per_rad_s"], 5)
0.06852
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, fields
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

from ..drive.pid import PID
from ..options import RAD_S_PER_RPM, check_number
from ..textsafe import quote
from ..tomlfile import read_toml

if TYPE_CHECKING:
    from .measurement import PositionLoop
    from ..plant.plantfile import Plant

__all__ = ["MotorData", "MOTOR_PLAUSIBLE", "MOTOR_TORQUE_CONSISTENCY", "BACK_EMF_UNITS", "BACK_EMF_KEYS", "load_motor", "parse_motor", "motor_from_plant", "drive_units", "QUANTITIES", "UNIT_FACTORS",
           "INTEGER_TYPES", "FILTER_QUANTITIES", "filter_fields",
           "builtin_templates", "load_template", "citation_problems", "fill_template", "read_parameter_set",
           "controller_from_parameter_set", "dumps_parameter_set"]

_RPM = RAD_S_PER_RPM  # rad/s per rpm


#: Plausible motor data (inclusive bounds, in the key's unit): from miniature servo motors
#: (k_T ~ 1 mN m/A, 0.1 A, 1 mN m) to large direct-drive torque motors (k_T of several hundred
#: N m/A, 10 kN m, kA drives); outside, the number is a typing or unit error (1e-300 V/krpm gave
#: kp = 5e300 A/(rad/s)). Back-EMF constants are bounded through the torque constant they give.
MOTOR_PLAUSIBLE: Mapping[str, tuple[float, float, str]] = {
    "torque_constant_n_m_per_a": (1e-4, 1e3, "N m/A"),
    "rated_current_a": (1e-3, 1e4, "A"),
    "rated_torque_n_m": (1e-4, 1e5, "N m"),
    "rated_speed_rpm": (1.0, 1e5, "rpm"),
}
#: Largest factor between k_T x I_rated and the rated torque (either way): data sheets agree
#: within about 20 % (k_T of the cold motor, iron losses and saturation at rated speed); a
#: factor 1.5 also lets an RMS/peak mix-up of the current (sqrt 2) through, not a unit error.
MOTOR_TORQUE_CONSISTENCY = 1.5


def _plausible(name: str, value: float, shown: str, unit: str | None = None) -> None:
    """Refuse a motor value outside :data:`MOTOR_PLAUSIBLE` (``shown``: the value as typed)."""
    if name in BACK_EMF_KEYS:
        bu, convention = BACK_EMF_KEYS[name]
        per_kt = BACK_EMF_UNITS[bu] / math.sqrt(3.0) * (math.sqrt(2.0) if convention == "peak" else 1.0)
        lo, hi, _ = MOTOR_PLAUSIBLE["torque_constant_n_m_per_a"]
        kt = value / per_kt
        if not lo <= kt <= hi:
            raise ValueError(f"{name} = {shown} {bu} gives a torque constant of {kt:.3g} N m/A; expected "
                             f"{lo * per_kt:.3g}..{hi * per_kt:.3g} {bu} (a torque constant of {lo:g}..{hi:g} N m/A)")
        return
    if name in MOTOR_PLAUSIBLE:
        lo, hi, u = MOTOR_PLAUSIBLE[name]
        if not lo <= value <= hi:
            raise ValueError(f"{name} = {shown} {u}; expected a plausible motor value in {lo:g}..{hi:g} {u}")


def _consistent(kt: float | None, current: float | None, torque: float | None, where: str = "") -> None:
    """k_T x I_rated within a factor :data:`MOTOR_TORQUE_CONSISTENCY` of the rated torque."""
    if kt is None or current is None or torque is None:
        return
    ratio = kt * current / torque
    f = MOTOR_TORQUE_CONSISTENCY
    if not 1.0 / f <= ratio <= f:
        raise ValueError(f"{where}torque constant x rated current = {kt:.6g} N m/A x {current:.6g} A = "
                         f"{kt * current:.6g} N m against rated_torque_n_m = {torque:.6g} N m (a factor {ratio:.3g}); "
                         f"expected them within a factor {f:g} of each other")


@dataclass(frozen=True)
class MotorData:
    """Motor data the drive units need (SI; currents RMS).

    Parameters
    ----------
    torque_constant_n_m_per_a : float or None, N m/A
        Torque per RMS phase current (None: only the per-unit gains, from ``rated_torque_n_m``,
        can be computed).
    rated_current_a : float, A, optional
    rated_torque_n_m : float, N m, optional
    rated_speed_rpm : float, rpm, optional
    pole_pairs : int, optional
        For drives whose speeds are electrical (rad/s electrical = pole_pairs x mechanical).
    source : str
        Where the numbers come from (data sheet, measurement).
    """

    torque_constant_n_m_per_a: float | None
    rated_current_a: float | None = None
    rated_torque_n_m: float | None = None
    rated_speed_rpm: float | None = None
    pole_pairs: int | None = None
    source: str = ""

    def __post_init__(self) -> None:
        if self.torque_constant_n_m_per_a is not None:
            check_number("torque_constant_n_m_per_a", self.torque_constant_n_m_per_a, 0.0, unit="N m/A", lo_open=True)
        elif self.rated_torque_n_m is None:
            raise ValueError("torque_constant_n_m_per_a = None and rated_torque_n_m = None; expected the torque "
                             "constant (or a back-EMF constant) or at least the rated torque")
        for name, unit in (("rated_current_a", "A"), ("rated_torque_n_m", "N m"), ("rated_speed_rpm", "rpm")):
            if getattr(self, name) is not None:
                check_number(name, getattr(self, name), 0.0, unit=unit, lo_open=True)
        for name in MOTOR_PLAUSIBLE:
            v = getattr(self, name)
            if v is not None:
                _plausible(name, float(v), f"{v!r}")
        _consistent(self.torque_constant_n_m_per_a, self.rated_current_a, self.rated_torque_n_m)
        if self.pole_pairs is not None and (isinstance(self.pole_pairs, bool) or not isinstance(self.pole_pairs, int)
                                            or not 1 <= self.pole_pairs <= 1000):
            raise ValueError(f"pole_pairs = {self.pole_pairs!r}; expected an integer in [1, 1000]")

    @classmethod
    def from_back_emf(cls, back_emf: float, unit: str = "V/krpm", convention: str = "rms", **kwargs: Any) -> "MotorData":
        """From the line-to-line back-EMF constant ``k_E``.

        Parameters
        ----------
        back_emf : float
            ``k_E`` in ``unit``, line-to-line.
        unit : {"V/krpm", "V s/rad"}
            Volts per 1000 rpm, or volts per rad/s (= V s/rad).
        convention : {"rms", "peak"}
            Whether ``k_E`` gives the RMS or the peak line-to-line voltage.
        **kwargs
            The other :class:`MotorData` fields.

        Returns
        -------
        MotorData
            ``k_T = sqrt(3) k_E,rms = sqrt(3/2) k_E,peak`` (``k_E`` in V s/rad; N m per A RMS;
            sinusoidal PM motor, no losses).
        """
        if unit not in BACK_EMF_UNITS:
            raise ValueError(f"unit = {unit!r}; expected one of {', '.join(BACK_EMF_UNITS)}")
        if convention not in ("rms", "peak"):
            raise ValueError(f"convention = {convention!r}; expected 'rms' or 'peak' (line-to-line)")
        ke = check_number("back_emf", back_emf, 0.0, unit=unit, lo_open=True)
        ke_v_s_per_rad = ke / BACK_EMF_UNITS[unit]
        kt = math.sqrt(3.0) * ke_v_s_per_rad / (math.sqrt(2.0) if convention == "peak" else 1.0)
        kwargs.setdefault("source", f"from back-EMF {ke:g} {unit} (line-to-line {convention.upper()}): k_T = "
                          + ("sqrt(3) k_E,rms" if convention == "rms" else "sqrt(3/2) k_E,peak") + " (k_E in V s/rad)")
        return cls(kt, **kwargs)


#: Back-EMF units: unit -> its value for 1 V s/rad (1 V s/rad = 1000 rpm x 2 pi/60 V/krpm).
BACK_EMF_UNITS: Mapping[str, float] = {"V s/rad": 1.0, "V/krpm": 1000.0 * _RPM}
#: Back-EMF keys of a motor table / ``--motor`` (line-to-line): key -> (unit, convention).
#: ``back_emf_v_per_krpm`` (no suffix) is line-to-line RMS, as most servo data sheets give it.
BACK_EMF_KEYS: Mapping[str, tuple[str, str]] = {
    "back_emf_v_per_krpm": ("V/krpm", "rms"), "back_emf_v_per_krpm_rms": ("V/krpm", "rms"),
    "back_emf_v_per_krpm_peak": ("V/krpm", "peak"), "back_emf_v_s_per_rad_rms": ("V s/rad", "rms"),
    "back_emf_v_s_per_rad_peak": ("V s/rad", "peak"),
}


_MOTOR_KEYS = {f.name for f in fields(MotorData)} | set(BACK_EMF_KEYS)


def _motor_from_mapping(d: Mapping[str, Any], where: str, typed: Mapping[str, str] | None = None) -> MotorData:
    """``typed``: each key's value as the user typed it (``--motor``), for the messages."""
    unknown = sorted(set(d) - _MOTOR_KEYS)
    if unknown:
        raise ValueError(f"{where}: unknown motor key {quote(unknown[0])}; expected {', '.join(sorted(_MOTOR_KEYS))}")
    d = dict(d)
    for k, v in d.items():  # each value in its range, named as typed, before any conversion
        if k in MOTOR_PLAUSIBLE or k in BACK_EMF_KEYS:
            shown = (typed or {}).get(k, quote(v))
            try:
                try:
                    check_number(k, v, 0.0, unit=BACK_EMF_KEYS[k][0] if k in BACK_EMF_KEYS else MOTOR_PLAUSIBLE[k][2], lo_open=True)
                except ValueError as exc:
                    raise ValueError(str(exc).replace(f"{k} = {quote(v)};", f"{k} = {shown};", 1)) from None
                _plausible(k, float(v), shown)
            except ValueError as exc:
                raise ValueError(f"{where}: {exc}") from None
    given = [k for k in ("torque_constant_n_m_per_a", *BACK_EMF_KEYS) if k in d]
    if len(given) > 1:
        raise ValueError(f"{where}: both {given[0]} and {given[1]}; expected one of them")
    if not given and "rated_torque_n_m" not in d:
        raise ValueError(f"{where}: no torque_constant_n_m_per_a (or back_emf_*) and no rated_torque_n_m; expected the "
                         "motor's torque constant (current-based gains) or rated torque (per-unit gains)")
    try:
        if given and given[0] in BACK_EMF_KEYS:
            unit, convention = BACK_EMF_KEYS[given[0]]
            return MotorData.from_back_emf(d.pop(given[0]), unit, convention, **d)
        d.setdefault("torque_constant_n_m_per_a", None)
        return MotorData(**d)
    except (ValueError, TypeError) as exc:  # the motor's own checks (consistency of k_T, I_rated, T_rated)
        raise ValueError(f"{where}: {exc}") from None


def load_motor(path: "str | Path") -> MotorData:
    """Motor data from a TOML file with a ``[motor]`` table (keys as :class:`MotorData`, or
    ``back_emf_v_per_krpm`` instead of the torque constant)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"motor file {str(path)!r}: {' '.join(str(exc).split())}; expected a TOML file with a "
                         "[motor] table") from None
    doc = read_toml(text, f"motor file {str(path)!r}", ValueError)
    if not isinstance(doc.get("motor"), dict):
        raise ValueError(f"motor file {str(path)!r} has no [motor] table; expected one")
    return _motor_from_mapping(doc["motor"], f"motor file {str(path)!r}")


def parse_motor(text: str) -> MotorData:
    """Motor data from ``path.toml`` or ``key=value,key=value`` (the CLI's ``--motor``)."""
    if not isinstance(text, str) or not text.strip():
        raise ValueError(f"motor = {text!r}; expected a TOML file or key=value,... (e.g. torque_constant_n_m_per_a=0.9)")
    if "=" not in text:
        return load_motor(text)
    d: dict[str, Any] = {}
    typed: dict[str, str] = {}
    for item in text.split(","):
        key, sep, val = item.partition("=")
        key = key.strip()
        try:
            num = float(val)
        except ValueError:
            num = None
        if not sep or num is None:
            raise ValueError(f"motor {quote(item.strip())}; expected key=number")
        if key in d:  # the last one won silently
            raise ValueError(f"motor key {quote(key)} given twice ({key}={typed[key]} and {key}={val.strip()}); "
                             "expected each key once")
        d[key] = int(num) if key == "pole_pairs" and num.is_integer() else num
        typed[key] = val.strip()
    return _motor_from_mapping(d, f"motor {quote(text)}", typed)


def motor_from_plant(plant: "Plant") -> MotorData | None:
    """Motor data from the plant's values ``motor.<key>`` (file units as the keys say), when the
    plant schema has them; None otherwise."""
    vals = {k.split(".", 1)[1]: v for k, v in getattr(plant, "values", {}).items() if k.startswith("motor.")}
    if not vals:
        return None
    if "pole_pairs" in vals:
        vals["pole_pairs"] = int(vals["pole_pairs"])
    vals = {k: v for k, v in vals.items() if k in _MOTOR_KEYS}
    return _motor_from_mapping(vals, f"plant {plant.name} [motor]")


# --- drive units -------------------------------------------------------------------------------

def drive_units(pid: PID, motor: MotorData | None = None, position: "PositionLoop | None" = None,
                inertia_kg_m2: float | None = None) -> dict:
    """The speed PI (and a position loop) in the units drives use, with the conventions.

    Parameters
    ----------
    pid : PID
        Speed PI(D), SI gains on the motor shaft (N m s/rad, N m/rad).
    motor : MotorData, optional
        Needed for the current-based and per-unit gains.
    position : PositionLoop, optional
    inertia_kg_m2 : float, kg m^2, optional
        Reflected inertia of the acceleration feed-forward.

    Returns
    -------
    dict
        ``speed`` (and ``position``) blocks; every key ends in its unit.
    """
    if not isinstance(pid, PID):
        raise ValueError(f"pid = {pid!r}; expected a prsa_ctrl.PID")
    kp, ki = float(pid.kp), float(pid.ki)
    speed: dict[str, Any] = {
        "convention": "ideal (parallel-equivalent) PI: u = Kp (e + (1/Tn) integral(e)) = kp e + ki integral(e), "
                      "Tn = kp/ki the integral (reset) time; a series PI Kp' (1 + 1/(Ti s)) with the same Kp, Ti = Tn "
                      "is the same controller; a parallel PI with Ki given directly takes ki",
        "kp_n_m_s_per_rad": kp, "kp_n_m_per_rpm": kp * _RPM, "ki_n_m_per_rad": ki,
        "tn_s": kp / ki if ki > 0 else None, "tn_ms": 1e3 * kp / ki if ki > 0 else None,
    }
    out: dict[str, Any] = {"speed": speed}
    if motor is not None:
        kt = motor.torque_constant_n_m_per_a
        if kt is not None:
            speed.update(kp_a_per_rad_s=kp / kt, kp_a_per_rpm=kp * _RPM / kt, ki_a_per_rad=ki / kt,
                         kp_a_peak_per_rad_s=math.sqrt(2.0) * kp / kt, kp_a_peak_per_rpm=math.sqrt(2.0) * kp * _RPM / kt,
                         torque_constant_n_m_per_a=kt)
            if motor.pole_pairs:
                speed["kp_a_per_electrical_rad_s"] = kp / kt / motor.pole_pairs
            if motor.rated_current_a:
                ir = motor.rated_current_a
                speed["kp_percent_rated_current_per_rpm"] = 100.0 * kp * _RPM / kt / ir
        if motor.rated_torque_n_m:
            tr = motor.rated_torque_n_m
            speed.update(kp_rated_torque_per_rad_s=kp / tr, kp_percent_rated_torque_per_rpm=100.0 * kp * _RPM / tr)
            if motor.rated_speed_rpm:
                wr = motor.rated_speed_rpm * _RPM
                speed.update(kp_pu=kp * wr / tr, ki_pu_per_s=ki * wr / tr)
        speed["units_note"] = ("currents RMS unless *_a_peak_* (peak = sqrt(2) RMS, sinusoidal); A/(rad/s) = "
                               "(N m s/rad)/k_T; A/rpm = A/(rad/s) x 2 pi/60; per unit of rated torque: torque command "
                               "in units of T_rated per rad/s of speed error; % rated current per rpm: 100 A/rpm / "
                               "I_rated; *_pu: torque in T_rated per speed in rated speed (Kp_pu = kp w_r/T_r, "
                               "dimensionless; Ki_pu = ki w_r/T_r, 1/s); electrical rad/s = pole pairs x mechanical")
    if position is not None:
        kv = float(position.kv)
        pos: dict[str, Any] = {
            "convention": "P (or PI) on the position error: speed reference = Kv e + ki integral(e) + kvff v_ref; "
                          "Kv [1/s] = speed per position error in consistent units (screw m/s per m = nut rad/s per "
                          "rad); (m/min)/mm = 0.06 x 1/s (also written 1000/min)",
            "kv_per_s": kv, "kv_m_min_per_mm": kv * 60.0 / 1000.0, "ki_per_s2": float(position.ki),
            "velocity_feedforward": float(position.kvff), "acceleration_feedforward": float(position.kaff),
        }
        if inertia_kg_m2 is not None:
            j = check_number("inertia_kg_m2", inertia_kg_m2, 0.0, unit="kg m^2", lo_open=True)
            pos["torque_per_acceleration_n_m_s2_per_rad"] = float(position.kaff) * j
            if motor is not None and motor.torque_constant_n_m_per_a is not None:
                pos["current_per_acceleration_a_s2_per_rad"] = float(position.kaff) * j / motor.torque_constant_n_m_per_a
        out["position"] = pos
    return out


# --- vendor parameter sets -----------------------------------------------------------------------

#: Toolkit quantities a parameter may hold: name -> (SI unit, description).
QUANTITIES: Mapping[str, tuple[str, str]] = {
    "speed_kp": ("N m s/rad", "speed PI proportional gain kp"),
    "speed_ki": ("N m/rad", "speed PI integral gain ki"),
    "speed_tn": ("s", "speed PI integral (reset) time Tn = kp/ki"),
    "position_kv": ("1/s", "position gain Kv"),
    "position_ki": ("1/s^2", "position-loop integral gain"),
    "velocity_feedforward": ("1", "velocity feed-forward gain (1 = full)"),
    "acceleration_feedforward": ("1", "acceleration feed-forward gain (1 = the reflected inertia)"),
    "torque_per_acceleration": ("N m s^2/rad", "acceleration feed-forward kaff J"),
    "sample_time": ("s", "speed-loop sample time"),
    "torque_limit": ("N m", "torque limit, positive direction (the plant's drive.torque_limit_n_m)"),
    "torque_limit_lower": ("N m", "torque limit, negative direction (minus the plant's torque limit)"),
    "speed_filter_time": ("s", "time constant of the speed-measurement low-pass (sensor.speed_filter_time_constant_s)"),
    "feedforward_torque": ("N m", "constant torque feed-forward of the export (0 unless given); the cyclic "
                                  "feed-forward torque of a cascade is written to the same object every cycle"),
    "torque_filter_type": ("1", "kind of the torque-command filter number `filter` (the template's `enum` maps "
                                "none, lowpass1, lowpass2, notch, biquad to the drive's code)"),
    "torque_filter_lp_hz": ("Hz", "natural frequency of the denominator (low-pass part) of torque filter `filter`"),
    "torque_filter_lp_damping": ("1", "damping of the denominator of torque filter `filter`"),
    "torque_filter_hp_hz": ("Hz", "natural frequency of the numerator of torque filter `filter`"),
    "torque_filter_hp_damping": ("1", "damping of the numerator of torque filter `filter`"),
}

#: Quantities of the torque-command filter number ``filter`` (1-based) of a template entry.
FILTER_QUANTITIES = tuple(q for q in QUANTITIES if q.startswith("torque_filter_"))

#: Integer data types a template may declare: name -> (lowest, highest) value. A value for such a
#: parameter is rounded to the nearest integer, checked against this range (and the template's
#: min/max), and the rounding error is reported.
INTEGER_TYPES: Mapping[str, tuple[int, int]] = {
    **{n: (-2**7, 2**7 - 1) for n in ("INT8", "SINT", "INTEGER8")},
    **{n: (0, 2**8 - 1) for n in ("UINT8", "USINT", "UNSIGNED8", "BYTE")},
    **{n: (-2**15, 2**15 - 1) for n in ("INT16", "INT", "INTEGER16", "ENUM (INT16)")},
    **{n: (0, 2**16 - 1) for n in ("UINT16", "UINT", "UNSIGNED16", "WORD")},
    **{n: (-2**31, 2**31 - 1) for n in ("INT32", "DINT", "INTEGER32")},
    **{n: (0, 2**32 - 1) for n in ("UINT32", "UDINT", "UNSIGNED32", "DWORD")},
}

#: Units a parameter may be given in: unit -> (SI unit, what it needs, factor): drive value =
#: SI value x factor x (1/k_T if it needs "kt", 1/T_rated if "rated_torque").
UNIT_FACTORS: Mapping[str, tuple[str, str, float]] = {
    "N m s/rad": ("N m s/rad", "", 1.0),
    "N m/rpm": ("N m s/rad", "", _RPM),
    "A/(rad/s)": ("N m s/rad", "kt", 1.0),
    "mA/(rad/s)": ("N m s/rad", "kt", 1e3),
    "A/rpm": ("N m s/rad", "kt", _RPM),
    "A peak/(rad/s)": ("N m s/rad", "kt", math.sqrt(2.0)),
    "A peak/rpm": ("N m s/rad", "kt", math.sqrt(2.0) * _RPM),
    "rated torque/(rad/s)": ("N m s/rad", "rated_torque", 1.0),
    "% rated torque/rpm": ("N m s/rad", "rated_torque", 100.0 * _RPM),
    "N m/rad": ("N m/rad", "", 1.0),
    "A/rad": ("N m/rad", "kt", 1.0),
    "s": ("s", "", 1.0),
    "ms": ("s", "", 1e3),
    "0.1 ms": ("s", "", 1e4),
    "us": ("s", "", 1e6),
    "1/s": ("1/s", "", 1.0),
    "(m/min)/mm": ("1/s", "", 0.06),
    "1000/min": ("1/s", "", 0.06),
    "1/s^2": ("1/s^2", "", 1.0),
    "1": ("1", "", 1.0),
    "%": ("1", "", 100.0),
    "N m s^2/rad": ("N m s^2/rad", "", 1.0),
    "A s^2/rad": ("N m s^2/rad", "kt", 1.0),
    "0.1 mA/(rad/s)": ("N m s/rad", "kt", 1e4),
    "0.01 ms": ("s", "", 1e5),
    "N m": ("N m", "", 1.0),
    "per mille rated torque": ("N m", "rated_torque", 1000.0),
    "Hz": ("Hz", "", 1.0),
}

_TEMPLATE_KEYS = ("index", "name", "quantity", "unit", "datatype", "confirmed", "source")  # + optional min, max


def builtin_templates() -> list[str]:
    """Names of the parameter-set templates shipped in ``prsa_ctrl/templates``."""
    return sorted(p.name[:-5] for p in resources.files("prsa_ctrl").joinpath("templates").iterdir()
                  if p.name.endswith(".toml"))


def _template_text(name_or_path: "str | Path") -> tuple[str, str]:
    p = Path(name_or_path)
    if p.suffix == ".toml" and p.exists():
        return p.read_text(encoding="utf-8"), str(p)
    if str(name_or_path) in builtin_templates():
        f = resources.files("prsa_ctrl").joinpath("templates", f"{name_or_path}.toml")
        return f.read_text(encoding="utf-8"), f"template {name_or_path}"
    raise ValueError(f"template {str(name_or_path)!r}; expected a template file (.toml) or one of "
                     f"{', '.join(builtin_templates())}")


def load_template(name_or_path: "str | Path") -> dict:
    """A parameter-set template (built-in name or path), checked: every parameter names a known
    quantity and unit of the same SI dimension and says whether it was confirmed."""
    text, origin = _template_text(name_or_path)
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{origin}: {' '.join(str(exc).split())}; expected TOML") from None
    if not isinstance(doc.get("template"), dict) or not isinstance(doc.get("parameter"), list) or not doc["parameter"]:
        raise ValueError(f"{origin}: expected a [template] table and [[parameter]] entries")
    for i, prm in enumerate(doc["parameter"]):
        where = f"{origin}: parameter {i + 1} ({prm.get('index', '?')})"
        missing = [k for k in _TEMPLATE_KEYS if k not in prm]
        if missing:
            raise ValueError(f"{where} lacks {', '.join(missing)}; expected {', '.join(_TEMPLATE_KEYS)}")
        if prm["quantity"] not in QUANTITIES:
            raise ValueError(f"{where}: quantity {prm['quantity']!r}; expected one of {', '.join(QUANTITIES)}")
        if prm["unit"] not in UNIT_FACTORS:
            raise ValueError(f"{where}: unit {prm['unit']!r}; expected one of {', '.join(UNIT_FACTORS)}")
        if UNIT_FACTORS[prm["unit"]][0] != QUANTITIES[prm["quantity"]][0]:
            raise ValueError(f"{where}: unit {prm['unit']!r} is not a unit of {prm['quantity']} "
                             f"({QUANTITIES[prm['quantity']][0]})")
        if not isinstance(prm["confirmed"], bool):
            raise ValueError(f"{where}: confirmed = {prm['confirmed']!r}; expected true or false")
    doc["template"].setdefault("origin", origin)
    return doc


_EDITION_WORDS = ("edition", "version", "firmware", "release", "revision")


def citation_problems(template: Mapping[str, Any]) -> list[str]:
    """The parameters of a loaded template that claim ``confirmed = true`` without a citation.

    A confirmed parameter cites its source: an ``https://`` page in ``source`` or ``document``,
    or a ``document`` that names the manual and its edition or version (one of the words
    edition, version, firmware, release, revision). A template whose ``[template]`` table sets
    ``self_defined = true`` (units the toolkit defines itself, e.g. ``generic``) has nothing
    vendor-specific to confirm and is exempt.

    Returns
    -------
    list of str
        One line per offending parameter: its index and what is missing (empty: all cited).
    """
    return [f"{quote(prm.get('index', '?'))}: confirmed = true without a citation (expected an https page in "
            "source, or a document naming the manual and its edition or version)" for prm in _uncited(template)]


def _uncited(template: Mapping[str, Any]) -> list[Mapping[str, Any]]:
    if template.get("template", {}).get("self_defined") is True:
        return []
    out = []
    for prm in template.get("parameter", []):
        if prm.get("confirmed") is not True:
            continue
        src, doc = str(prm.get("source", "")), str(prm.get("document", ""))
        if "https://" in src or "https://" in doc:
            continue
        if doc.strip() and any(w in doc.lower() for w in _EDITION_WORDS):
            continue
        out.append(prm)
    return out


def _factor(unit: str, motor: MotorData | None, where: str) -> float:
    _, needs, f = UNIT_FACTORS[unit]
    if needs == "kt":
        if motor is None or motor.torque_constant_n_m_per_a is None:
            raise ValueError(f"{where}: unit {unit!r} needs the motor's torque constant; expected motor data "
                             "(--motor / motor=MotorData(...))")
        return f / motor.torque_constant_n_m_per_a
    if needs == "rated_torque":
        if motor is None or motor.rated_torque_n_m is None:
            raise ValueError(f"{where}: unit {unit!r} needs the motor's rated torque; expected motor data with "
                             "rated_torque_n_m")
        return f / motor.rated_torque_n_m
    return f


def _si_values(pid: PID, position: "PositionLoop | None", plant: "Plant") -> dict[str, float | None]:
    kp, ki = float(pid.kp), float(pid.ki)
    j = float(plant.reflected_inertia_kg_m2)
    pos = position
    return {"speed_kp": kp, "speed_ki": ki, "speed_tn": kp / ki if ki > 0 else None,
            "position_kv": None if pos is None else float(pos.kv),
            "position_ki": None if pos is None else float(pos.ki),
            "velocity_feedforward": None if pos is None else float(pos.kvff),
            "acceleration_feedforward": None if pos is None else float(pos.kaff),
            "torque_per_acceleration": None if pos is None else float(pos.kaff) * j,
            "sample_time": float(plant.sample_time_s)}


def filter_fields(lf: Any) -> dict[str, float | str]:
    """A loop filter's numerator and denominator as natural frequency (Hz) and damping:
    ``{"kind", "lp_hz", "lp_damping", "hp_hz", "hp_damping"}`` (``lp``: the denominator,
    ``hp``: the numerator; a first-order part has no damping, a constant numerator no ``hp``)."""
    f = lf.filter
    (n2, n1, n0), (d2, d1, d0) = f.coefficients()
    out: dict[str, float | str] = {"kind": f.kind}
    for tag, (a2, a1, a0) in (("lp", (d2, d1, d0)), ("hp", (n2, n1, n0))):
        if a2 != 0.0:
            out[f"{tag}_hz"] = math.sqrt(a0 / a2) / (2.0 * math.pi)
            out[f"{tag}_damping"] = a1 / (2.0 * math.sqrt(a0 * a2))
        elif a1 != 0.0:
            out[f"{tag}_hz"] = (a0 / a1) / (2.0 * math.pi)
    return out


def _filter_value(prm: Mapping[str, Any], torque_filters: list) -> float | None:
    """The value of a ``torque_filter_*`` parameter for filter number ``prm["filter"]``."""
    i = prm.get("filter")
    if isinstance(i, bool) or not isinstance(i, int) or i < 1:
        raise ValueError(f"parameter {prm.get('index')}: filter = {i!r}; expected the filter's number (1, 2, ...) for "
                         f"quantity {prm['quantity']}")
    field = prm["quantity"][len("torque_filter_"):]
    if field == "type":
        enum = prm.get("enum")
        if not isinstance(enum, dict) or not all(isinstance(v, int) for v in enum.values()):
            raise ValueError(f"parameter {prm.get('index')}: expected an enum table (filter kind -> integer code)")
        kind = "none" if i > len(torque_filters) else torque_filters[i - 1].filter.kind
        if kind not in enum:
            raise ValueError(f"parameter {prm.get('index')}: the drive has no code for a {kind} filter (enum: "
                             f"{', '.join(enum)}); expected a filter the drive offers")
        return float(enum[kind])
    if i > len(torque_filters):
        return None
    return filter_fields(torque_filters[i - 1]).get(field)  # type: ignore[return-value]


def _rounding_margins(params: list, pid: PID, plant: "Plant", lfs: Any, motor: MotorData | None) -> dict | None:
    """The speed loop's margins with the exact and with the rounded gains, when rounding to an
    integer type changed a speed-loop gain (None otherwise). Linear sampled loop of the plant
    (rigid), with the export's filters (:func:`prsa_ctrl.tuning.actuatorloops.step_loops`)."""
    rounded = [p for p in params if "rounding" in p and p["quantity"] in ("speed_kp", "speed_ki", "speed_tn")]
    if not rounded:
        return None
    vals = read_parameter_set({"parameter": params}, motor)
    kp = vals.get("speed_kp", float(pid.kp))
    ki = vals["speed_ki"] if "speed_ki" in vals else (kp / vals["speed_tn"] if "speed_tn" in vals else float(pid.ki))
    from ..tuning.actuatorloops import step_loops

    lp = step_loops(plant, setpoint_rad_s=10.0, initial_load_n=0.0, final_loads_n=[1.0], fidelity="rigid",
                    horizon_s=0.02, filters=list(lfs))[0]
    g0 = (float(pid.kp), float(pid.ki), float(pid.kd))
    g1 = (kp, ki, float(pid.kd))
    m0, m1 = lp.margins(g0), lp.margins(g1)
    out = {"exact_gains": {"kp_n_m_s_per_rad": g0[0], "ki_n_m_per_rad": g0[1]},
           "rounded_gains": {"kp_n_m_s_per_rad": g1[0], "ki_n_m_per_rad": g1[1]},
           "exact": {k: v for k, v in m0.as_dict().items() if v is not None},
           "rounded": {k: v for k, v in m1.as_dict().items() if v is not None},
           "note": "speed loop (rigid plant, sampled, with the export's filters) with the exact gains and with the "
                   "gains the rounded integers give back; ms/mt peak sensitivities, gm_db gain margin, pm_deg phase "
                   "margin, wc_rad_s crossover"}
    out["change"] = {k: out["rounded"][k] - out["exact"][k] for k in out["exact"] if k in out["rounded"]}
    return out


def fill_template(template: "str | Path | dict", controller: "PID | Any", plant: "Plant",
                  motor: MotorData | None = None, *, filters: Any = (), feedforward_torque_n_m: float = 0.0) -> dict:
    """The template with each parameter's ``value`` in its unit (and ``value_si``).

    Parameters
    ----------
    template : str, Path or dict
        Built-in name, a template file, or a loaded template.
    controller : PID or CascadeDesign
    plant : Plant
    motor : MotorData, optional
        Needed for current-based or per-unit units. Default: :func:`motor_from_plant`.
    filters : iterable
        The loop filters (:func:`prsa_ctrl.drive.filters.loop_filters`); the torque-command ones
        fill the ``torque_filter_*`` parameters (``filter`` = their number, 1-based).
    feedforward_torque_n_m : float, N m
        Constant torque feed-forward (the ``feedforward_torque`` quantity).

    Returns
    -------
    dict
        Plain data (write it with :func:`dumps_parameter_set`). A position-loop parameter of a
        speed-only design gets ``applies = false`` and no value. A parameter of an integer
        data type (:data:`INTEGER_TYPES`) holds the rounded integer and a ``rounding`` table:
        the exact value, the error in the parameter's unit and in SI, and, when a speed-loop
        gain was rounded, the speed loop's margins with the exact and the rounded gains
        (``rounding_margins`` of the set).
    """
    doc = template if isinstance(template, dict) else load_template(template)
    pid, pos = (controller, None) if isinstance(controller, PID) else (getattr(controller, "speed", None),
                                                                        getattr(controller, "position", None))
    if not isinstance(pid, PID):
        raise ValueError(f"controller = {controller!r}; expected a PID or a CascadeDesign")
    motor = motor if motor is not None else motor_from_plant(plant)
    from ..drive.filters import loop_filters

    lfs = loop_filters(filters, float(plant.sample_time_s))
    torque_filters = [lf for lf in lfs if lf.place == "torque_command"]
    si = _si_values(pid, pos, plant)
    si.update(torque_limit=float(plant.torque_limit), torque_limit_lower=-float(plant.torque_limit),
              speed_filter_time=float(plant.speed_filter_s), feedforward_torque=float(feedforward_torque_n_m))
    from .. import __version__

    out = {"template": dict(doc["template"]),
           "export": {"prsa_ctrl_version": __version__, "plant": plant.name, "sample_time_s": float(plant.sample_time_s),
                      "note": "value is in the parameter's unit, value_si in the quantity's SI unit; a drive that "
                              "stores the value in a narrower type (REAL32, scaled integers) rounds it"},
           "parameter": []}
    if motor is not None:
        out["motor"] = {k: v for k, v in motor.__dict__.items() if v is not None and v != ""}
    from .export import export_assumptions

    out["assumptions"] = export_assumptions(plant, (), pos)
    for i, prm in enumerate(doc["parameter"]):
        entry = {k: prm[k] for k in prm if k not in ("value", "value_si", "applies", "rounding")}
        q = prm["quantity"]
        v = _filter_value(prm, torque_filters) if q in FILTER_QUANTITIES else si[q]
        if v is not None and prm.get("optional") is True:  # left out when its motor data is missing
            try:
                _factor(prm["unit"], motor, "")
            except ValueError as exc:
                entry["applies"] = False
                entry["missing"] = str(exc).split(": ", 1)[-1]
                out["parameter"].append(entry)
                continue
        if v is None:
            entry["applies"] = False
        else:
            exact = v * _factor(prm["unit"], motor, f"parameter {prm['index']}")
            value: float | int = exact
            lo, hi = prm.get("min", -math.inf), prm.get("max", math.inf)
            dtype = str(prm["datatype"]).upper()
            if dtype in INTEGER_TYPES:
                tlo, thi = INTEGER_TYPES[dtype]
                lo, hi = max(lo, tlo), min(hi, thi)
                if not math.isfinite(exact) or not lo - 0.5 <= exact < hi + 0.5:
                    raise ValueError(f"parameter {prm['index']} ({prm['name']}) = {exact:.6g} {prm['unit']}; expected "
                                     f"a value that rounds into [{lo:g}, {hi:g}] ({prm['datatype']} and the template's "
                                     "range)")
                value = int(math.floor(exact + 0.5))
                err = value - exact
                entry["rounding"] = {"exact_value": exact, "error": err, "error_si": err / (exact / v) if exact else 0.0,
                                     "relative_error": err / exact if exact else 0.0,
                                     "note": f"{prm['datatype']}: rounded to the nearest integer; error = value - "
                                             "exact_value in the parameter's unit, error_si in the quantity's SI unit"}
            elif not lo <= exact <= hi:
                raise ValueError(f"parameter {prm['index']} ({prm['name']}) = {exact:.6g} {prm['unit']}; expected a value "
                                 f"in [{lo:g}, {hi:g}] as the template says the drive accepts")
            entry["value"] = value
            entry["value_si"] = v
            entry["si_unit"] = QUANTITIES[q][0]
            entry["applies"] = True
        out["parameter"].append(entry)
    margins = _rounding_margins(out["parameter"], pid, plant, lfs, motor)
    if margins is not None:
        out["rounding_margins"] = margins
    unc = _uncited(doc)
    uncited = {i for i, prm in enumerate(doc["parameter"]) if any(prm is u for u in unc)}
    parts = [", ".join(p["index"] for i, p in enumerate(out["parameter"]) if not p["confirmed"] or i in uncited)]
    if not doc["template"].get("speed_pi_form_confirmed", True):
        parts.append("the PI form (speed_pi_form)")
    parts = [x for x in parts if x]
    if parts:
        out["export"]["not_confirmed"] = (f"check before use: {' and '.join(parts)}: not confirmed in the vendor's "
                                          "public documentation (see each source)")
    return out


def read_parameter_set(data: "dict | str | Path", motor: MotorData | None = None) -> dict[str, float]:
    """SI values of a filled parameter set (dict, TOML text or file), from each parameter's
    ``value`` and ``unit`` only (``value_si`` is ignored): ``{quantity: value}``. Motor data for
    current-based units comes from ``motor`` or the file's ``[motor]`` table."""
    if isinstance(data, Path) or (isinstance(data, str) and data.endswith(".toml") and "\n" not in data):
        data = Path(data).read_text(encoding="utf-8")
    if isinstance(data, str):
        data = tomllib.loads(data)
    if motor is None and isinstance(data.get("motor"), dict):
        motor = _motor_from_mapping({k: v for k, v in data["motor"].items()}, "parameter set [motor]")
    out: dict[str, float] = {}
    rounded: set[str] = set()
    for prm in data.get("parameter", []):
        if not prm.get("applies", True) or "value" not in prm:
            continue
        if prm["unit"] not in UNIT_FACTORS or prm["quantity"] not in QUANTITIES:
            raise ValueError(f"parameter {prm.get('index')}: unit {prm['unit']!r} / quantity {prm['quantity']!r}; "
                             "expected those of a template")
        v = float(prm["value"]) / _factor(prm["unit"], motor, f"parameter {prm.get('index')}")
        q = prm["quantity"]
        if q in FILTER_QUANTITIES:  # one per filter: keyed by its number
            q = f"{q}[{prm.get('filter')}]"
        if "rounding" in prm:  # an integer's rounded value: a value given exactly elsewhere in the set wins
            rounded.add(q)
            out.setdefault(q, v)
            continue
        if q in rounded:
            out[q] = v
            rounded.discard(q)
            continue
        if q in out and abs(v - out[q]) > 1e-9 * max(abs(v), abs(out[q])):
            raise ValueError(f"parameter {prm.get('index')}: {q} = {v:.12g} {QUANTITIES[q][0]} differs from the "
                             f"{out[q]:.12g} another parameter of the set gives; expected one value")
        out.setdefault(q, v)
    return out


def controller_from_parameter_set(values: Mapping[str, float], *, measured: str = "nut_angle", rate: int = 1,
                                  missing_from: "PositionLoop | None" = None) -> tuple[PID, "PositionLoop | None"]:
    """The speed PI (and position loop) a parameter set describes, from :func:`read_parameter_set`.

    ``ki`` is ``speed_ki`` or ``speed_kp/speed_tn``; the acceleration feed-forward comes from
    ``acceleration_feedforward`` (dimensionless; a set with only ``torque_per_acceleration``
    needs the inertia to rebuild it and is refused). Position-loop quantities the set does not
    carry (a vendor set without feed-forward objects) come from ``missing_from`` (the drive's
    other settings), else 0."""
    if "speed_kp" not in values:
        raise ValueError("parameter set has no speed_kp; expected the speed controller's proportional gain")
    kp = values["speed_kp"]
    ki = values["speed_ki"] if "speed_ki" in values else (kp / values["speed_tn"] if "speed_tn" in values else 0.0)
    pid = PID(kp, ki)
    if "position_kv" not in values:
        return pid, None
    from ..drive.measurement import PositionLoop

    if "acceleration_feedforward" not in values and "torque_per_acceleration" in values:
        raise ValueError("parameter set gives the acceleration feed-forward as a torque per acceleration only; expected "
                         "acceleration_feedforward too (or rebuild it with the inertia)")
    base = {"position_ki": 0.0, "velocity_feedforward": 0.0, "acceleration_feedforward": 0.0}
    if missing_from is not None:
        base = {"position_ki": missing_from.ki, "velocity_feedforward": missing_from.kvff,
                "acceleration_feedforward": missing_from.kaff}
    v = {**base, **values}
    return pid, PositionLoop(kv=v["position_kv"], ki=v["position_ki"], kvff=v["velocity_feedforward"],
                             kaff=v["acceleration_feedforward"], measured=measured, rate=rate)


def dumps_parameter_set(filled: dict) -> str:
    """A filled parameter set as TOML (readable with ``tomllib``; see :func:`prsa_ctrl.io.export.dumps`)."""
    from .export import dumps

    d = {"format": "prsa-ctrl drive parameter set", **filled}
    return dumps(d, "toml")


# --- prsa-tune hooks ------------------------------------------------------------------------------

def check_cli_options(args: Any) -> tuple[MotorData | None, dict | None]:
    """``--motor`` and ``--export-template`` of ``prsa-tune``, checked before any tuning: the
    motor data and the loaded template (ValueError with one line naming the value as typed)."""
    motor_text, tpl_name = getattr(args, "motor", None), getattr(args, "export_template", None)
    export = getattr(args, "export", None)
    motor = None
    if motor_text is not None:
        try:
            motor = parse_motor(motor_text)
        except ValueError as exc:
            msg = str(exc).removeprefix(f"motor {quote(motor_text)}: ")  # named once, as the flag
            raise ValueError(f"--motor {quote(motor_text)}: {msg}") from None
    rated = getattr(args, "rated_torque", None)
    if rated is not None:
        check_number("--rated-torque", rated, 0.0, unit="N m", lo_open=True)
        if motor is None:
            motor = MotorData(None, rated_torque_n_m=float(rated), source="--rated-torque")
        elif motor.rated_torque_n_m is not None and motor.rated_torque_n_m != float(rated):
            raise ValueError(f"--rated-torque {rated:g} differs from the --motor rated_torque_n_m = "
                             f"{motor.rated_torque_n_m:g}; expected one rated torque")
        else:
            from dataclasses import replace

            try:
                motor = replace(motor, rated_torque_n_m=float(rated))
            except ValueError as exc:  # with the motor's torque constant and rated current
                raise ValueError(f"--rated-torque {rated:g} with --motor {quote(motor_text)}: {exc}") from None
    template = None
    if tpl_name is not None:
        if export is None or Path(export).suffix.lower() not in (".toml", ".json"):
            raise ValueError(f"--export-template {tpl_name!r} needs --export PATH.toml or PATH.json; expected the "
                             "file the filled parameter set is written to")
        try:
            template = load_template(tpl_name)
        except ValueError as exc:
            raise ValueError(f"--export-template {tpl_name!r}: {exc}") from None
    return motor, template


def cli_export_data(args: Any, exported: dict, controller: "PID | Any", plant: "Plant", *, filters: Any = ()) -> dict:
    """What ``--export PATH.toml|.json`` writes given ``--motor``/``--export-template``: the filled
    parameter set (with ``--export-template``), else the drive export with a ``drive_units``
    block (with ``--motor``), else ``exported`` unchanged."""
    motor, template = check_cli_options(args)
    motor = motor if motor is not None else motor_from_plant(plant)
    if template is not None:
        return {"format": "prsa-ctrl drive parameter set", **fill_template(template, controller, plant, motor,
                                                                            filters=filters)}
    if motor is None:
        return exported
    pid, pos = (controller, None) if isinstance(controller, PID) else (controller.speed, controller.position)
    out = dict(exported)
    out["drive_units"] = drive_units(pid, motor, pos, float(plant.reflected_inertia_kg_m2) if pos is not None else None)
    out["drive_units"]["motor"] = {k: v for k, v in motor.__dict__.items() if v is not None and v != ""}
    if getattr(args, "export", "").lower().endswith(".toml"):
        out["drive_units"] = _drop_none(out["drive_units"])
    return out


def _drop_none(d: Any) -> Any:
    if isinstance(d, dict):
        return {k: _drop_none(v) for k, v in d.items() if v is not None}
    return d
