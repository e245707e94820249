"""From a parametric FRF fit (:mod:`prsa_ctrl.identification.twomass`) to a plant file, for
every mechanism: the structure the data chose (rigid or two-mass) mapped onto the
mechanism's plant keys, with 95 % intervals, as a :class:`~prsa_ctrl.identification.common.FitResult`
(what ``prsa-fit --frf`` writes and reports).

Mapping (``a = L / 2 pi`` the lead per radian; ``J``, ``J_m``, ``J_l``, ``zeta``, ``f_r``,
``f_c``, ``T`` the fitted total, motor-side and load-side inertia, damping ratio, mode,
current loop and delay):

``ball-screw``, ``roller-screw`` (the motor turns the screw)
    rigid: ``axis.motor_inertia_kg_m2 = J - J_screw - m a^2`` (the base's screw inertia and
    moving mass kept) without load; under load (nut loss on the whole force) ``J - J_screw -
    m a^2 / eta``: the motor-side key is set so that the plant's own rigid model, linearised at
    the measurement's speed and load, has the response's inertia (:func:`apparent_inertia`; the
    two-mass mapping likewise sets ``axis.moving_mass_kg``). Two-mass: ``axis.motor_inertia_kg_m2 = J_m - J_screw`` (the screw turns
    with the rotor), ``axis.moving_mass_kg = J_l / a^2``, ``axis.axial_damping_ratio = zeta``
    (the modal damping of the axial mode, the model's definition) and
    ``axis.nut_stiffness_n_per_um`` such that the plant's own compliant model, linearised at the
    measurement's speed and load, has its first axial mode at ``f_r`` (the screw shaft at its
    stroke position and the bearings keep their geometric stiffness: the nut is the least known
    spring of the series; when no nut stiffness in its plausible range places the mode, the nut and
    ``axis.bearing_stiffness_n_per_um`` are scaled together by one factor, :func:`_match_stiffness`; the shaft's own axial mass is in the plant's model, not in the
    two-mass one, hence the match on the plant's model rather than the series formula).
``inverted-roller-screw`` (the motor turns the nut)
    rigid: ``nut.inertia_kg_m2 = J - J_cage (w_P/w_N)^2 - (m_screw + m_rollers) a^2``.
    Two-mass: ``nut.inertia_kg_m2 = J_m - J_cage (w_P/w_N)^2``, ``screw.mass_kg = J_l / a^2 -
    m_rollers``, ``contact.stiffness_n_per_mm_e`` such that the compliant model's first axial
    mode at the measurement's load is at ``f_r``.
``linear-axis`` (load coordinates: force in N, speed in m/s)
    ``axis.mass_kg = J``; two-mass: also ``axis.load_mass_kg = J_l``,
    ``axis.load_stiffness_n_per_um = k = J_l (2 pi f_a)^2`` (1e-6 of N/m) and
    ``axis.axial_damping_ratio = zeta``: the plant's compliant model is then exactly this
    two-mass axis (:mod:`prsa_ctrl.plant.linearaxis`), so the mapping is written as it is.

Every mechanism: ``drive.current_loop_bandwidth_hz = f_c`` and the delay ``T`` as
``drive.command_delay_samples`` whole samples, the rest lumped into the current-loop lag
(:func:`prsa_ctrl.identification.frf.write_delay`). Intervals: delta method on the fit's
covariance; for a stiffness matched to the mode, ``d ln K / d ln f_r`` of the plant's model
times the interval of ``f_r`` (the inertias' share of its uncertainty is left out: say so).
The reflected inertia's interval, and that of the inertia key the response sets, add the spread
of the keys held at base values that one response cannot tell from it (the efficiency; rigid,
the moving mass): :func:`held_key_spread`, :data:`HELD_DEFAULT`.
"""

from __future__ import annotations

import math
import warnings as _warnings
from typing import Mapping, Sequence

import numpy as np

from ..errors import FitError
from ..plant.plantfile import Plant
from ..plant.schema import axial_mode_keys
from .common import FitResult
from .frfcheck import choose_structure_checked, units_line, unexplained_line, unexplained_resonances
from .twomass import StructureChoice, FrfModelFit, physical_values

__all__ = ["fit_frf_structure", "plant_keys_of", "first_mode_hz", "apparent_inertia", "held_key_spread", "HELD_DEFAULT",
           "held_key_sd", "with_held",
           "KEY_UNITS", "FRF_FIT_MIN", "CURRENT_LOOP_BAND",
           "INERTIA_RATIO_MAX", "DELAY_SAMPLES_MAX", "LOW_PHASE_TOL_DEG"]

#: A response that neither model fits to at least this fit % (complex log response,
#: :func:`prsa_ctrl.identification.frf.frf_fit_percent`) is not written into a plant: a
#: rigid model on a clear two-mass response still reaches ~75 %, a right model on a response
#: with 2 % noise ~98 %; below 50 % the response is not torque command -> motor speed of
#: an axis in these units (or its noise swamps it).
FRF_FIT_MIN = 50.0
#: The fitted total inertia must lie within this factor of the base plant's reflected inertia
#: (as the time-domain fit's unit check: a response in deg/s is 57x off, one in rpm 9.5x... the
#: factor catches the former; a wrong base plant too).
INERTIA_RATIO_MAX = 20.0
#: Largest command delay (samples) a written plant may carry (the plant file's plausible range
#: of ``drive.command_delay_samples``).
DELAY_SAMPLES_MAX = 20
#: The response's phase at its lowest frequencies must lie within this many degrees of -90
#: (torque -> speed of an inertia): a sign flip (+90) or an angle/acceleration response is
#: refused before any fit.
LOW_PHASE_TOL_DEG = 60.0
#: A response ending below the base plant's current-loop bandwidth divided by this holds the
#: current loop at the base value (below ~f_c/3 its lag is a pure phase slope, the delay's).
CURRENT_LOOP_BAND = 3.0

#: The spread of a key the fit holds at its base value although the reported inertia depends
#: on it (:func:`held_key_spread`), when the base plant's ``[uncertainty]`` table has none for
#: it: ``key -> (kind, half-width of a uniform distribution, source)``. A response at one
#: operating point shows the inertia the motor feels, ``J_m + m a^2 / eta`` with the nut loss on
#: the whole force (and, two-mass, ``J_m`` and ``m a^2 / eta`` apart): the efficiency (and, for the
#: rigid model, the moving mass) cannot be told from the motor-side inertia, so the total
#: reflected inertia ``J_m + m a^2`` carries their uncertainty.
HELD_DEFAULT = {
    "friction.efficiency": ("absolute", 0.05, "assumption: a screw's catalogue efficiency spans about 0.05 "
                            "(ball screws 0.90 to 0.95, a roller screw's 0.80 to 0.85 or 0.85 to 0.90)"),
    "axis.moving_mass_kg": ("relative", 0.10, "assumption: a moving mass from drawings, +-10 %"),
    "screw.mass_kg": ("relative", 0.10, "assumption: a moving mass from drawings, +-10 %"),
}

#: Units of the keys this module writes.
KEY_UNITS = {
    "axis.motor_inertia_kg_m2": "kg m^2", "nut.inertia_kg_m2": "kg m^2", "axis.moving_mass_kg": "kg",
    "axis.nut_stiffness_n_per_um": "N/um", "axis.bearing_stiffness_n_per_um": "N/um", "axis.axial_damping_ratio": "-", "screw.mass_kg": "kg",
    "contact.stiffness_n_per_mm_e": "N/mm^e", "axis.mass_kg": "kg", "drive.current_loop_bandwidth_hz": "Hz",
    "axis.load_mass_kg": "kg", "axis.load_stiffness_n_per_um": "N/um",
    "drive.command_delay_s": "s",
}


def _check_low_phase(frf) -> None:
    """Refuse a response whose low-frequency phase is not that of an inertia (about -90 deg)."""
    for fr in frf:
        n = max(3, min(10, fr.n // 10))
        ph = float(np.degrees(np.angle(np.mean(np.exp(1j * np.angle(fr.response[:n]))))))
        if abs(ph + 90.0) > LOW_PHASE_TOL_DEG:
            raise FitError(f"no plant written: {fr.name}: the phase at its lowest frequencies "
                           f"({fr.frequency_hz[0]:.4g}..{fr.frequency_hz[n - 1]:.4g} Hz) is {ph:.0f} deg; expected about "
                           "-90 deg (torque command -> motor speed of an inertia): a sign flip gives +90, a position "
                           "response -180, an acceleration response 0")


def _stiffness_key(plant: Plant) -> str | None:
    """The spring a response's mode is matched by first (:data:`prsa_ctrl.plant.schema.AXIAL_MODE_KEYS`)."""
    springs = axial_mode_keys(plant.mechanism, "springs")
    return springs[0] if springs else None


def first_mode_hz(plant: Plant, keys: Sequence[str] = (), values: Sequence[float] = (), *,
                  speed_rad_s: float = 30.0, load_n: float = 800.0) -> float:
    """Undamped frequency (Hz) of the first oscillatory pole pair of the plant's compliant model
    linearised at ``speed_rad_s`` and ``load_n``, with ``keys`` set to ``values`` (file units).

    Raises
    ------
    ValueError
        The mechanism has no compliant model with an axial mode, or no oscillatory pole.
    """
    from .frf import linearised

    lin = linearised(plant, tuple(keys), "compliant")
    if lin.rigid:
        raise ValueError(f"mechanism = {plant.mechanism!r} has no axial mode in its model; expected a screw mechanism")
    a, _ = lin(speed_rad_s, load_n, np.asarray(values, float))
    ev = np.linalg.eigvals(a)
    osc = sorted((e for e in ev if e.imag > 1e-3 * abs(e)), key=abs)
    if not osc:
        raise ValueError(f"{plant.name}: no oscillatory axial mode at {load_n:g} N")
    return float(abs(osc[0]) / (2 * math.pi))


def apparent_inertia(plant: Plant, keys: Sequence[str] = (), values: Sequence[float] = (), *,
                     speed_rad_s: float = 30.0, load_n: float = 800.0) -> float:
    """The inertia the motor feels (kg m^2; load coordinates: kg) in the plant's rigid model
    linearised at ``speed_rad_s`` and ``load_n``, with ``keys`` set to ``values``: ``1 / (d omega_dot
    / d tau)``. With the nut loss on the whole force it is ``J_m + m a^2 / eta``, not the reflected
    inertia ``J_m + m a^2`` (what a response at that operating point shows at low frequency)."""
    from .frf import linearised

    lin = linearised(plant, tuple(keys), "rigid")
    a, _ = lin(speed_rad_s, load_n, np.asarray(values, float))
    return float(1.0 / a[lin.i_w, lin.names.index("tau_motor")])


def _loaded(plant: Plant, load_n: float) -> bool:
    """Whether the operating point carries an external load through a screw's nut (then the loss
    on the whole force is linear, ``1/eta`` on the inertial force too). Without load the nut force
    is the inertial force alone and its loss ``|a F_s|`` is rectified: no share of it in the
    fundamental, the response shows ``J_m + m a^2`` (the closed form), and the plant's
    linearisation sits on the kink of ``|F_s|``."""
    return plant.mechanism != "linear-axis" and abs(load_n) > 1e-6 * plant.rated_load_n


def _adjust_key(plant: Plant, structure: str) -> str:
    """The inertia key the response's low-frequency inertia sets: the motor side for the rigid
    model, the load side for the two-mass one (whose motor side the mode fixes)."""
    if plant.mechanism == "linear-axis":
        return "axis.mass_kg"
    if structure == "rigid":
        return "axis.motor_inertia_kg_m2" if plant.screw_driven else "nut.inertia_kg_m2"
    return "axis.moving_mass_kg" if plant.screw_driven else "screw.mass_kg"


def _match_apparent(plant: Plant, key: str, value: float, held: Mapping[str, float], target: float,
                    speed: float, load: float) -> float:
    """``key``'s value (from ``value``) that makes the plant's :func:`apparent_inertia` at the
    operating point ``target``, with ``held`` keys set: exact in two secant steps (the apparent
    inertia is affine in an inertia or a mass)."""
    hk = tuple(held)
    keys = (*hk, key)
    hv = [float(held[k]) for k in hk]
    x = float(value)
    for _ in range(2):
        j0 = apparent_inertia(plant, keys, [*hv, x], speed_rad_s=speed, load_n=load)
        eps = 1e-4 * abs(x) if x else 1e-9
        slope = (apparent_inertia(plant, keys, [*hv, x + eps], speed_rad_s=speed, load_n=load) - j0) / eps
        if not (math.isfinite(slope) and slope > 0):
            raise FitError(f"the plant's apparent inertia does not grow with {key} at {load:g} N (slope {slope:.3g}); "
                           "expected an inertia or mass key")
        x = x + (target - j0) / slope
    return x


def held_key_sd(plant: Plant, key: str) -> tuple[float, str]:
    """Standard deviation (file units) of a held key: from the base plant's ``[uncertainty]``
    entry (the distribution's own, by quadrature of its inverse CDF) when it has one, else
    :data:`HELD_DEFAULT`'s uniform; and its source."""
    from ..errors import PlantFileError
    from ..plant.uncertainty import parse_entries, resolve_entry

    table = getattr(plant, "uncertainty", None) or {}
    if table:
        try:  # this key's entry alone (the others may no longer hold the fitted values)
            flat = parse_entries(table, plant.origin)
            e = resolve_entry(key, flat[key], plant.values[key], plant.origin, PlantFileError) if key in flat else None
        except PlantFileError:
            e = None  # its support no longer holds the value: the default below
        if e is not None:
            u = (np.arange(2000) + 0.5) / 2000
            x = np.asarray(e.ppf(u), float)
            return float(np.std(x)), f"the base plant's [uncertainty] entry ({e.source})"
    kind, hw, src = HELD_DEFAULT[key]
    v = plant.values[key]
    if kind == "relative":
        return abs(v) * hw / math.sqrt(3.0), src
    lo, hi = max(v - hw, 0.2), min(v + hw, 1.0)  # an efficiency stays in (0.2, 1]
    return (hi - lo) / math.sqrt(12.0), src


def held_key_spread(plant: Plant, fitted_keys: Sequence[str], structure: str, *, speed_rad_s: float,
                    load_n: float) -> list[dict]:
    """What the keys a response cannot inform, held at their base values, add to the written
    plant's reflected inertia (:data:`HELD_DEFAULT`): per held key its standard deviation ``sd``
    and the sensitivity ``d J / d key`` of the reflected inertia with the response held fixed
    (the apparent inertia at the operating point re-matched through :func:`_adjust_key`'s key),
    by central differences on the plant's own model.

    Returns
    -------
    list of dict
        ``{"key", "value", "sd", "sensitivity_kg_m2_per_unit", "sd_kg_m2", "source"}`` (file units).
    """
    if not _loaded(plant, load_n):
        return []
    adj = _adjust_key(plant, structure)
    vals = plant.values
    target = apparent_inertia(plant, speed_rad_s=speed_rad_s, load_n=load_n)
    out = []
    for key in HELD_DEFAULT:
        if key in fitted_keys or key == adj or key not in vals:
            continue
        if structure != "rigid" and key != "friction.efficiency":
            continue  # the two-mass fit sets the load side itself
        if key == ("screw.mass_kg" if plant.screw_driven else "axis.moving_mass_kg"):
            continue  # derived in this mechanism (the translating member is the other key)
        sd, src = held_key_sd(plant, key)
        if not sd > 0:
            continue
        h = 0.05 * sd
        js, adjs = [], []
        for x in (vals[key] - h, vals[key] + h):
            a = _match_apparent(plant, adj, vals[adj], {key: x}, target, speed_rad_s, load_n)
            with _warnings.catch_warnings():
                _warnings.simplefilter("ignore")
                js.append(plant.with_params({key: x, adj: a}).reflected_inertia_kg_m2)
            adjs.append(a)
        sens = (js[1] - js[0]) / (2 * h)
        sens_a = (adjs[1] - adjs[0]) / (2 * h)
        out.append({"key": key, "value": float(vals[key]), "sd": float(sd), "sensitivity_kg_m2_per_unit": float(sens),
                    "sd_kg_m2": float(abs(sens) * sd), "adjusted_key": adj, "adjusted_sensitivity": float(sens_a),
                    "adjusted_sd": float(abs(sens_a) * sd), "source": src})
    return out


def with_held(reflected: dict, spread: Sequence[dict]) -> dict:
    """The reflected inertia's 95 % interval widened by the held keys' spread: variances added
    (the fit's from its interval, ``(hi - lo) / (2 x 1.96)``), normal quantile."""
    j = float(reflected["value"])
    lo, hi = reflected["ci95"]
    sd_fit = (hi - lo) / (2 * _Z95)
    sd = math.sqrt(sd_fit**2 + sum(e["sd_kg_m2"] ** 2 for e in spread))
    out = dict(reflected)
    out["ci95"] = [j - _Z95 * sd, j + _Z95 * sd]
    out["ci95_fit_only"] = [float(lo), float(hi)]
    out["held_keys"] = [dict(e) for e in spread]
    out["interval"] = ("the fit's interval with the spread of the keys held at base values added in quadrature "
                       "(normal quantile): " + ", ".join(f"{e['key']} sd {e['sd']:.3g} ({e['source']})" for e in spread)
                       if spread else "the fit's interval (no held key moves the reflected inertia)")
    return out


_Z95 = 1.959963984540054


def _direct(plant: Plant, structure: str, v: Mapping[str, float], op: tuple[float, float] | None = None) -> dict:
    """The plant keys that follow from the fitted values in closed form (file units); with the
    operating point ``op = (speed, load)`` the inertia key :func:`_adjust_key` names then matched so
    that the plant's apparent inertia there is the fitted total (the nut loss on the inertial
    force: ``J_m + m a^2 / eta``, not ``J_m + m a^2``)."""
    out = _direct_closed(plant, structure, v)
    if op is not None and _loaded(plant, op[1]):
        adj = _adjust_key(plant, structure)
        held = {k: out[k] for k in out if k != adj and k in plant.values and k != "drive.current_loop_bandwidth_hz"
                and k != "axis.axial_damping_ratio"}
        out[adj] = _match_apparent(plant, adj, out[adj], held, v["total_inertia_kg_m2"], op[0], op[1])
    return out


def _direct_closed(plant: Plant, structure: str, v: Mapping[str, float]) -> dict:
    """The closed-form part of :func:`_direct`."""
    vals, a2 = plant.values, plant.lead_per_rad**2
    out = {}
    if plant.mechanism == "linear-axis":  # load coordinates: kg m^2 per rad^2 = kg, N m/rad = N/m
        out["axis.mass_kg"] = v["total_inertia_kg_m2"]
        if structure == "two-mass":
            out["axis.load_mass_kg"] = v["load_inertia_kg_m2"]
            out["axis.load_stiffness_n_per_um"] = v["stiffness_n_m_per_rad"] * 1e-6
            out["axis.axial_damping_ratio"] = v["damping_ratio"]
    elif plant.screw_driven:
        js = vals["axis.screw_inertia_kg_m2"]
        if structure == "rigid":
            out["axis.motor_inertia_kg_m2"] = v["total_inertia_kg_m2"] - js - vals["axis.moving_mass_kg"] * a2
        else:
            out["axis.motor_inertia_kg_m2"] = v["motor_inertia_kg_m2"] - js
            out["axis.moving_mass_kg"] = v["load_inertia_kg_m2"] / a2
            out["axis.axial_damping_ratio"] = v["damping_ratio"]
    else:
        rot = plant.cage_inertia_kg_m2 * plant.cage_ratio**2
        if structure == "rigid":
            out["nut.inertia_kg_m2"] = v["total_inertia_kg_m2"] - (plant.reflected_inertia_kg_m2 - vals["nut.inertia_kg_m2"])
        else:
            out["nut.inertia_kg_m2"] = v["motor_inertia_kg_m2"] - rot
            out["screw.mass_kg"] = v["load_inertia_kg_m2"] / a2 - plant.roller_assembly_mass_kg
    out["drive.current_loop_bandwidth_hz"] = v["current_loop_bandwidth_hz"]
    return out


def _match_stiffness(plant: Plant, direct: Mapping[str, float], target_hz: float, speed: float, load: float):
    """The stiffness keys' values that put the plant's first axial mode at ``target_hz`` (with
    the directly mapped inertias), and ``d ln K / d ln f`` of their common factor; ``None`` when no
    value in the keys' plausible ranges does.

    The nut (the contacts of an inverted roller screw) first: the least known spring of the series.
    A screw-driven axis whose shaft and bearings in series are already softer than the response
    says (measured: the judge's roller screw, shaft 431 N/um and bearings 900 N/um against a true
    axial 300 N/um: no nut stiffness up to 1e5 N/um reaches its 161 Hz) has the nut and the
    bearings scaled together by one factor (both catalogue springs, their ratio kept; the shaft's
    geometry is not a guess)."""
    springs = axial_mode_keys(plant.mechanism, "springs")
    inert = [k for k in axial_mode_keys(plant.mechanism, "inertias") if k in direct]
    found = _match_scaled(plant, inert, [direct[k] for k in inert], springs[:1], target_hz, speed, load)
    if found is None and len(springs) > 1:  # (the series spring scaled with the nut: the bearings)
        found = _match_scaled(plant, inert, [direct[k] for k in inert], springs, target_hz, speed, load)
    return found


def _match_scaled(plant: Plant, inert, fixed, skeys, target_hz: float, speed: float, load: float):
    """:func:`_match_stiffness` with the keys ``skeys`` scaled together from their base values
    (one factor, 25-point scan of its logarithm over the keys' plausible ranges, then Brent)."""
    from scipy.optimize import brentq

    from ..plant.schema import PLAUSIBLE

    k0 = [float(plant.values[k]) for k in skeys]
    keys = (*inert, *skeys)

    def mode(lnc):
        return first_mode_hz(plant, keys, [*fixed, *(math.exp(lnc) * k for k in k0)], speed_rad_s=speed, load_n=load)

    lo = max(math.log(PLAUSIBLE[k][0] / v) for k, v in zip(skeys, k0))
    hi = min(math.log(PLAUSIBLE[k][1] / v) for k, v in zip(skeys, k0))
    if not lo < hi:
        return None
    grid = np.linspace(lo, hi, 25)
    vals = []
    for g in grid:
        try:
            vals.append(mode(g) - target_hz)
        except (ValueError, FitError, np.linalg.LinAlgError):
            vals.append(float("nan"))
    vals = np.asarray(vals)
    brk = [i for i in range(len(grid) - 1) if np.isfinite(vals[i]) and np.isfinite(vals[i + 1])
           and vals[i] * vals[i + 1] <= 0]
    if not brk:
        return None
    i = brk[0]
    lnc = brentq(lambda x: mode(x) - target_hz, grid[i], grid[i + 1], xtol=1e-10, maxiter=100)
    h = 1e-3
    slope = (math.log(mode(lnc + h)) - math.log(mode(lnc - h))) / (2 * h)  # d ln f / d ln c
    return {k: math.exp(lnc) * v for k, v in zip(skeys, k0)}, 1.0 / slope


def plant_keys_of(plant: Plant, fit: FrfModelFit, *, speed_rad_s: float, load_n: float):
    """The plant keys a fit maps to (module docstring), with 95 % intervals and covariance.

    Returns
    -------
    (values, ci95, cov, keys, warnings)
        ``values``: ``{key: value}`` (file units); ``ci95``: ``{key: [lo, hi]}``; ``cov``: the
        covariance of ``keys`` (file units); ``warnings``: list of str (keys not written and why).
    """
    theta, cov_t = fit.theta, fit.covariance
    structure = fit.structure
    v0 = physical_values(structure, theta, fit.b_scale)
    op = (speed_rad_s, load_n)
    direct = _direct(plant, structure, v0, op)
    warns = []
    keys = list(direct)
    # gradients of the direct keys w.r.t. theta (numerical, central)
    grads = np.zeros((len(keys), len(theta)))
    for i in range(len(theta)):
        h = 1e-6 * max(abs(theta[i]), 1.0)
        tp, tm = theta.copy(), theta.copy()
        tp[i] += h
        tm[i] -= h
        dp = _direct(plant, structure, physical_values(structure, tp, fit.b_scale), op)
        dm = _direct(plant, structure, physical_values(structure, tm, fit.b_scale), op)
        grads[:, i] = [(dp[k] - dm[k]) / (2 * h) for k in keys]
    values = dict(direct)
    skey = _stiffness_key(plant)
    if structure == "two-mass" and skey is not None:
        bad = [k for k in axial_mode_keys(plant.mechanism, "inertias") if k in direct and not direct[k] > 0]
        match = None
        if not bad:
            try:
                match = _match_stiffness(plant, direct, v0["resonance_hz"], speed_rad_s, load_n)
            except (ValueError, FitError) as exc:
                warns.append(f"{skey} not written: the plant's compliant model could not be matched to the mode "
                             f"{v0['resonance_hz']:.4g} Hz ({exc})")
        if match is None and not bad:
            warns.append(f"{skey} not written: no value in its plausible range (nor the nut and the bearings scaled "
                         f"together) puts the plant's first axial mode at the fitted {v0['resonance_hz']:.4g} Hz (the "
                         "screw shaft at its stroke position is softer than the response says: check "
                         "axis.stroke_position_mm and screw.root_diameter_mm)")
        elif match is not None:
            k_vals, dlnk_dlnf = match
            g_f = np.zeros(len(theta))
            for i in range(len(theta)):
                h = 1e-6 * max(abs(theta[i]), 1.0)
                tp, tm = theta.copy(), theta.copy()
                tp[i] += h
                tm[i] -= h
                g_f[i] = (math.log(physical_values(structure, tp, fit.b_scale)["resonance_hz"])
                          - math.log(physical_values(structure, tm, fit.b_scale)["resonance_hz"])) / (2 * h)
            for k, k_val in k_vals.items():
                keys.append(k)
                values[k] = k_val
                grads = np.vstack([grads, k_val * dlnk_dlnf * g_f])
            names_k = " and ".join(k_vals)
            warns.append(f"{names_k}: {'their intervals count' if len(k_vals) > 1 else 'its interval counts'} only "
                         f"the mode's uncertainty (d ln K / d ln f_r = {dlnk_dlnf:.3g} of the plant's model), not the "
                         "inertias'")
            if len(k_vals) > 1:
                c = k_vals[skey] / plant.values[skey]
                warns.append(f"{names_k} scaled together by {c:.4g} from the base values: no nut stiffness in its "
                             f"plausible range puts the plant's first axial mode at the fitted "
                             f"{v0['resonance_hz']:.4g} Hz (the shaft and the bearings in series are softer than the "
                             "response says); the screw shaft's geometry is kept")
        for k in bad:
            warns.append(f"{k} = {direct[k]:.4g} from the fitted inertias is not > 0: the base plant's other "
                         "inertias (screw, cage, rollers) exceed what the response shows on that side; check them")
    elif structure == "two-mass" and plant.mechanism == "linear-axis":
        warns.append(f"the response shows a mode at {v0['resonance_hz']:.4g} Hz (anti-resonance "
                     f"{v0['antiresonance_hz']:.4g} Hz): written as axis.load_mass_kg, axis.load_stiffness_n_per_um "
                     "(anti-resonance^2 x load mass) and axis.axial_damping_ratio: the plant's compliant model is "
                     "then this two-mass axis (simulation, linearisation, prsa-axis and the time-domain fit's "
                     "replay); its rigid model keeps the whole mass axis.mass_kg as one body")
    cov = grads @ cov_t @ grads.T
    from scipy.stats import t as student_t

    q = float(student_t.ppf(0.975, max(fit.n_residuals - len(theta), 1)))
    ci = {}
    for i, k in enumerate(keys):
        sd = math.sqrt(max(cov[i, i], 0.0))
        ci[k] = [values[k] - q * sd, values[k] + q * sd]
    return values, ci, cov, keys, warns


def fit_frf_structure(frf, plant: Plant, *, fidelity: str | None = None, command_logged: str = "applied",
                      uncertainty: str = "keep", refine: bool = True, band: tuple[float, float] | None = None,
                      band_typed: str | None = None) -> tuple[FitResult, StructureChoice]:
    """Fit a measured frequency response with the structure the data choose and map it onto
    the plant's keys (module docstring).

    Parameters
    ----------
    frf : sequence of FrfRecord
        Torque command -> motor speed, at one operating point (the first record's speed and
        load are the linearisation's).
    plant : Plant
        Base plant (mechanism, the inertias the fit does not see, geometry).
    fidelity : {None, "rigid", "compliant"}
        None: the structure the data choose. ``"rigid"``: the rigid model, refused (FitError
        naming the mode and ``--fidelity compliant``) when the response shows a mode.
        ``"compliant"``: the two-mass model.
    command_logged : {"applied", "computed"}
        How the command was logged (the fitted delay less one sample when computed).
    uncertainty : {"keep", "fit"}
        The written keys' ``[uncertainty]`` entries: the base plant's kept (``keep``, the
        default; replaced by the fit's where it is narrower than the 95 % interval or does not
        hold the value) or the fit's (``fit``).
    refine : bool
        For a two-mass response of a screw mechanism, fit the plant's own compliant model from the
        mapping (:func:`_refine`; default) instead of writing the mapping itself.
    band : (float, float), Hz, optional
        Fit the points inside ``[fmin, fmax]`` only (:mod:`prsa_ctrl.identification.frfband`:
        the resonances outside it named, the tail of those above it fitted as an upper
        residual and the current loop held at the base value); ``band_typed`` the band as the
        user typed it (``--frf-band``), for the messages.

    Returns
    -------
    (FitResult, StructureChoice)

    Raises
    ------
    FitError
        A fit did not converge, or the rigid model was asked for a response with a mode.
    """
    from .common import checked_inputs, frf_sample_time, uncertainty_entries
    from .delay import frf_delay_record
    from .fituncertainty import uncertainty_choice
    from .frf import frf_fit_percent, write_delay

    frf = list(frf)
    if not frf:
        raise ValueError("frf = []; expected at least one frequency response")
    if fidelity not in (None, "rigid", "compliant"):
        raise ValueError(f"fidelity = {fidelity!r}; expected None, 'rigid' or 'compliant'")
    frf = checked_inputs([], [], frf, plant)[2]
    ts_set = {frf_sample_time(fr, plant) for fr in frf}
    if len(ts_set) != 1:
        raise ValueError(f"frequency responses at sample times {sorted(ts_set)} s; expected one sample time")
    ts = ts_set.pop()
    load0 = frf[0].load_n
    if fidelity == "compliant" and plant.mechanism == "inverted-roller-screw" and abs(load0) < 1e-9 * plant.rated_load_n:
        raise ValueError(f"load_n = {load0!r} for a compliant frequency response; expected the measurement's axial load "
                         "(> 0 N, --frf-load): without load the thread contacts sit in the backlash and no axial mode "
                         "exists")
    from . import frfband

    frf, band_info = (frf, None) if band is None else frfband.apply_band(frf, band, typed=band_typed)
    upper = bool(band_info and band_info["above"])  # (a band that covers every point changes nothing)
    _check_low_phase(frf)
    f_top = max(float(np.max(fr.frequency_hz)) for fr in frf)
    fc_base = plant.values["drive.current_loop_bandwidth_hz"]
    fix_fc = fc_base if f_top < fc_base / CURRENT_LOOP_BAND or upper else None
    choice = _choose(frf, plant, ts, fix_fc, upper)
    speed, load = frf[0].speed_rad_s, frf[0].load_n
    warns = [w for fr in frf for w in fr.warnings] + frfband.band_warnings(band_info)
    fc_why = frfband.fc_reason(band_info, fc_base) if upper else (
        f"the responses end at {f_top:.4g} Hz, below 1/{CURRENT_LOOP_BAND:g} of it, where the current loop's lag "
        "cannot be told from the delay (held there in the fit; measure up to the current loop to fit it)")
    fc_fit = (choice.two_mass if fidelity == "compliant" and choice.two_mass is not None else choice.chosen).values[
        "current_loop_bandwidth_hz"]
    if fix_fc is None and fc_fit.get("at_bound"):  # not identified: the base value held, and the fit made again
        fix_fc = fc_base
        # not the unbounded fit's end: past the bound the lag is a delay's, the cost flat, and where the
        # solver stops there (1e7 or 4e8 Hz) is its path, not the data
        fc_why = (f"the fit's current loop ran to its bound {fc_fit['value']:.4g} Hz ({fc_fit['note']}; unbounded it "
                  "runs on past it), so the base value is held and the responses fitted again with it")
        choice = _choose(frf, plant, ts, fix_fc, upper)
    if fidelity == "rigid" and choice.structure == "two-mass":
        raise FitError(f"rigid model refused: {choice.reason}; fit it with --fidelity compliant (the two-mass axis)")
    if fidelity == "compliant" and choice.structure == "rigid":
        if choice.two_mass is None:
            raise FitError(f"two-mass FRF fit failed: {choice.reason}")
        warns.append(f"--fidelity compliant on a response that does not need it ({choice.reason}); the two-mass "
                     "values below rest on no visible mode")
    fit = choice.two_mass if fidelity == "compliant" else choice.chosen
    j_fit, j_base = fit.value("total_inertia_kg_m2"), plant.reflected_inertia_kg_m2
    if not 1.0 / INERTIA_RATIO_MAX <= j_fit / j_base <= INERTIA_RATIO_MAX:
        raise FitError(f"no plant written: the response's inertia {j_fit:.4g} kg m^2 is {j_fit / j_base:.3g} x the base "
                       f"plant's {j_base:.4g} kg m^2 (outside 1/{INERTIA_RATIO_MAX:g}..{INERTIA_RATIO_MAX:g}); expected "
                       "the response in (rad/s)/(N m) at the motor (not deg/s, rpm or load coordinates) and a base "
                       "plant of this axis (--plant)")
    d_samples = fit.value("delay_s") / (ts if ts > 0 else plant.sample_time_s)
    if d_samples > DELAY_SAMPLES_MAX:
        raise FitError(f"no plant written: the response lags its command by {d_samples:.3g} samples beyond the current "
                       f"loop (more than {DELAY_SAMPLES_MAX}, the plant file's plausible drive delay); expected a "
                       "response of torque command -> motor speed of this drive (check the sample time and that the "
                       "phase is not shifted)")
    finite = all(math.isfinite(v["value"]) for v in fit.values.values())
    extra = unexplained_resonances(frf, fit) if finite else []
    if extra:  # a mode the model lacks, named before the fit % it spoils (not the units: their check is above)
        raise FitError(unexplained_line(frf, fit, extra, ts if ts > 0 else plant.sample_time_s))
    best = max((x.fit_percent for x in (choice.rigid, choice.two_mass) if x is not None and math.isfinite(x.fit_percent)),
               default=float("nan"))
    if not best >= FRF_FIT_MIN or not finite:
        units_ok, units = units_line(frf, j_base)
        raise FitError(f"no plant written: neither the rigid nor the two-mass model explains the response (best fit "
                       + (f"{best:.1f} %" if math.isfinite(best) else "n/a: the response does not vary")
                       + f", expected at least {FRF_FIT_MIN:g} %); expected torque command (N m) -> motor speed "
                       "(rad/s), falling as 1/(J w) at low frequency with a phase near -90 deg: "
                       + ("check the units, the sign and that the columns are magnitude_db and phase_deg (or real, "
                          "imag)" if not units_ok else f"{units}; check the sign and that the columns are magnitude_db "
                          "and phase_deg (or real, imag)"))
    warns += list(fit.warnings)
    values, ci, cov, keys, map_warns = plant_keys_of(plant, fit, speed_rad_s=speed, load_n=load)
    warns += map_warns
    if fix_fc is not None:
        warns.append(f"drive.current_loop_bandwidth_hz kept at the base value {fc_base:.6g} Hz: {fc_why}")
        i = keys.index("drive.current_loop_bandwidth_hz")
        keep = [j for j in range(len(keys)) if j != i]
        cov = cov[np.ix_(keep, keep)]
        keys = [k for k in keys if k != "drive.current_loop_bandwidth_hz"]
        values = {k: values[k] for k in keys}
    from ..plant.schema import PLAUSIBLE as _PL

    bad = [k for k in keys if not values[k] > 0]
    for k in keys:
        lo_p, hi_p = _PL.get(k, (0.0, math.inf))[:2]
        if k not in bad and not lo_p <= values[k] <= hi_p:
            bad.append(k)
            warns.append(f"{k} = {values[k]:.4g} from the fit is outside its plausible range [{lo_p:g}, {hi_p:g}]: "
                         "the base value is kept (the response does not inform it)")
    if bad:
        keys = [k for k in keys if k not in bad]
        idx = [i for i, k in enumerate(values) if k in keys]
        cov = cov[np.ix_(idx, idx)]
        values = {k: values[k] for k in keys}
    names = ", ".join(fr.name for fr in frf) + frfband.source_note(band_info)
    d = fit.values["delay_s"]
    ts_w = ts if ts > 0 else plant.sample_time_s
    delay = {"value": d["value"], "ci95": d["ci95"], "unit": "s", "samples": d["value"] / ts_w}
    if d.get("at_bound"):
        delay.update(at_bound=d["at_bound"], note=d["note"], unbounded_value=d["unbounded_value"])
    offset = {"applied": 0, "computed": 1}.get(command_logged)
    if offset is None:
        raise ValueError(f"command_logged = {command_logged!r}; expected 'applied' or 'computed'")
    in_ci = d["ci95"] is not None and d["ci95"][0] <= offset * ts_w <= d["ci95"][1]
    delay_to_write = not (in_ci or d["value"] <= offset * ts_w)  # (a delay held at its bound 0 is none)
    overrides = dict(values)
    if not delay_to_write:  # no delay beyond the computation delay the log's convention implies
        how = (f"95 % CI {d['ci95'][0]:.4g}..{d['ci95'][1]:.4g}" if d["ci95"] is not None else
               f"{d['note']}, the unbounded fit {d['unbounded_value']:.4g} s" if d.get("at_bound") else "held")
        delay["plant_file"] = (f"the fitted delay {d['value']:.4g} s ({how}) "
                               f"is no longer than the {offset} sample(s) a command logged as {command_logged} "
                               "implies: drive.command_delay_samples = 0, the current loop as fitted")
        delay["written"] = {"drive.command_delay_samples": 0,
                            "drive.current_loop_bandwidth_hz": values.get("drive.current_loop_bandwidth_hz", fc_base)}
        if plant.values["drive.command_delay_samples"] != 0:
            overrides["drive.command_delay_samples"] = 0
    with _warnings.catch_warnings():
        _warnings.simplefilter("ignore")
        fitted = plant.with_params(overrides, name=f"{plant.name}-fit")
    spread = held_key_spread(fitted, keys, fit.structure, speed_rad_s=speed, load_n=load)
    adj = spread[0]["adjusted_key"] if spread else None
    if adj in keys:  # the key the response's inertia sets carries the held keys' spread too
        i = keys.index(adj)
        extra = sum(e["adjusted_sd"] ** 2 for e in spread)
        sd_fit = (ci[adj][1] - ci[adj][0]) / 2
        q_t = sd_fit / math.sqrt(cov[i, i]) if cov[i, i] > 0 else _Z95
        cov = cov.copy()
        cov[i, i] += extra
        ci[adj] = [values[adj] - q_t * math.sqrt(cov[i, i]), values[adj] + q_t * math.sqrt(cov[i, i])]
        warns.append(f"{adj}: its interval includes the spread of the keys held at base values ("
                     + ", ".join(f"{e['key']} sd {e['sd']:.3g}" for e in spread) + "), which one response cannot "
                     "tell from it")
    srcs = dict(fitted.sources)
    if "drive.command_delay_samples" in overrides:
        srcs["drive.command_delay_samples"] = f"fit: {names} (no command delay beyond the computation delay)"
    params = {}
    for k in keys:
        lo, hi = ci[k]
        params[k] = {"value": float(values[k]), "ci95": [float(lo), float(hi)], "unit": KEY_UNITS[k], "kept_base": False}
        srcs[k] = f"fit: {names} (95 % CI {lo:.6g}..{hi:.6g}; {fit.structure} model of the frequency response)"
    base_unc = dict(getattr(plant, "uncertainty", None) or {})
    unc = {k: v for k, v in base_unc.items() if k not in keys}
    std = [math.sqrt(max(cov[i, i], 0.0)) for i in range(len(keys))]
    from ..plant.schema import PLAUSIBLE

    ranges = [PLAUSIBLE.get(k, (0.0, math.inf))[:2] for k in keys]
    fit_unc = uncertainty_entries(fitted, params, names, std, ranges)
    for k, rng in zip(keys, ranges):
        choice_u, note = uncertainty_choice(fitted, k, base_unc.get(k), fit_unc.get(k), params[k]["ci95"], rng,
                                             uncertainty)
        if choice_u is not None:
            unc[k] = choice_u
        if note:
            warns.append(note)
    fitted = Plant(name=fitted.name, values=fitted.values, sources=srcs, origin=fitted.origin,
                   description=f"{plant.name} fitted by prsa-fit to {names}", uncertainty=unc,
                   mechanism=fitted.mechanism, defaulted=fitted.defaulted, mechanism_source=fitted.mechanism_source)
    start = fitted
    if delay_to_write:
        fitted, delay = write_delay(fitted, delay, ts_w, command_logged, warns)
    jt = fit.values["total_inertia_kg_m2"]
    j_w = float(fitted.reflected_inertia_kg_m2)
    # the written reflected inertia differs from the response's total by what the held keys make
    # of it (the nut loss on the inertial force): the fit's interval moves with it
    reflected = {"value": j_w, "ci95": [j_w - (jt["value"] - jt["ci95"][0]), j_w + (jt["ci95"][1] - jt["value"])],
                 "unit": "kg m^2", "fitted_total": jt["value"],
                 "apparent_inertia_note": ("the response's low-frequency inertia is the one the motor feels at the "
                                           "operating point (the nut loss on the whole force included), not the "
                                           "reflected inertia")}
    reflected = with_held(reflected, spread)
    fit_pct, traces = {}, {}
    for fr in frf:
        g = fit.response(fr.frequency_hz)
        fit_pct[fr.name] = round(frf_fit_percent(fr.response, g), 3)
        models = {f"rigid ({choice.rigid.fit_percent:.1f} %)": choice.rigid.response(fr.frequency_hz)}
        if choice.two_mass is not None:
            models[f"two-mass ({choice.two_mass.fit_percent:.1f} %)"] = choice.two_mass.response(fr.frequency_hz)
        traces[fr.name] = {"frequency_hz": fr.frequency_hz, "measured": fr.response, "model": g, "models": models,
                           "chosen": fit.structure, "coherence": fr.coherence}
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    with np.errstate(all="ignore"):
        corr = np.nan_to_num(cov / np.outer(sd, sd))
    solver = {
        "name": "Levenberg-Marquardt on the log frequency response (scipy), rigid and two-mass models",
        "status": "converged",
        "iterations": int(fit.nfev),
        "objective": float(0.5 * fit.rss),
        "residual_std": fit.residual_std,
        "residual_unit": "log response (coherence weighted)",
        "residuals": fit.n_residuals,
        "fidelity": "compliant" if fit.structure == "two-mass" else "rigid",
        "covariance": "classic (residual variance x inverse Gauss-Newton matrix), delta method for the plant keys",
        "structure": choice.as_dict(),
        "frf_model": {k: dict(v) for k, v in fit.values.items()},
    }
    solver["command_delay"] = frf_delay_record(delay, fitted, ts_w, command_logged,
                                               loop_held="drive.current_loop_bandwidth_hz" not in keys)
    if band_info:
        solver["frf_band"] = dict(band_info)
    result = FitResult(fitted, params, reflected, corr, tuple(keys), fit_pct, warns, solver, traces, delay, {}, None)
    skey = _stiffness_key(plant)
    if refine and fit.structure == "two-mass" and skey is not None and skey in keys:
        if upper:
            result.warnings.append("the plant's own compliant model is not refitted to the band (it has no upper "
                                   "residual for the modes above it, which its delay and inertia would take up): the "
                                   "two-mass model's mapping is written")
        else:
            result = _refine(result, start, frf, fit, choice, keys, ts_w, command_logged, uncertainty, names)
    return result, choice


def _choose(frf, plant: Plant, ts: float, fix_fc: float | None, upper: bool = False) -> StructureChoice:
    """:func:`~prsa_ctrl.identification.twomass.choose_structure`, its solver's failure diagnosed from the data
    (:func:`prsa_ctrl.identification.frfcheck.failure_diagnosis`: units, resonances, or the solver)."""
    return choose_structure_checked(frf, plant.reflected_inertia_kg_m2, sample_time_s=ts,
                                    current_loop_bandwidth_hz=fix_fc, upper_residual=upper)


def _refine(direct: FitResult, start: Plant, frf, fit: FrfModelFit, choice: StructureChoice, keys, ts: float,
            command_logged: str, uncertainty: str, names: str) -> FitResult:
    """The plant's own compliant model fitted to the responses (:func:`prsa_ctrl.identification.frf.fit_frf`)
    from the two-mass mapping (``start``): the plant's model differs from a two-mass axis (the
    screw shaft's axial mass, the thread loss on the whole nut force at load, the inverted
    screw's rollers and cage), so the keys that make *it* explain the data are its own fit's;
    the two-mass values are its start and the evidence for the structure. Falls back to the
    mapping (a warning says why) when that fit fails or explains the data worse."""
    import dataclasses

    from .common import DELAY_KEY
    from .frf import fit_frf

    # (the bearings, when scaled with the nut, keep the mapping's value: the response shows the series alone)
    fkeys = [k for k in keys if k not in ("drive.current_loop_bandwidth_hz", *axial_mode_keys(start.mechanism, "springs")[1:])] + (
        ["drive.current_loop_bandwidth_hz"] if "drive.current_loop_bandwidth_hz" in keys else []) + [DELAY_KEY]
    try:
        start = _match_modes(start, fit, frf[0].speed_rad_s, frf[0].load_n)
    except (FitError, ValueError, np.linalg.LinAlgError):
        pass  # the mapping's start (the mode alone matched) stays
    n0 = int(min(max(round(fit.value("delay_s") / ts), 0), 10)) if ts > 0 else 0
    try:
        res = fit_frf(frf, start.with_params({}, name=start.name), keys=fkeys, fidelity="compliant",
                      delay_samples=n0, command_logged=command_logged, uncertainty=uncertainty, scan_stiffness=False,
                      max_nfev=400, scan_delay=False)  # (n0: the structure fit's delay, a start in its period)
    except (FitError, ValueError, np.linalg.LinAlgError) as exc:
        return dataclasses.replace(direct, warnings=[*direct.warnings, f"the plant's own compliant model could not be "
                                                     f"fitted from the two-mass start ({' '.join(str(exc).split())}): "
                                                     "the two-mass mapping is written"])
    worst = min(res.fit_percent[fr.name] - direct.fit_percent[fr.name] for fr in frf)
    if worst < -1.0:
        return dataclasses.replace(direct, warnings=[*direct.warnings, f"the plant's own compliant model fits the "
                                                     f"response {-worst:.1f} points worse than the two-mass model: the "
                                                     "two-mass mapping is written"])
    solver = dict(res.solver)
    solver["structure"] = direct.solver["structure"]
    solver["frf_model"] = direct.solver["frf_model"]
    if "frf_band" in direct.solver:  # (the band the two-mass fit read: the report's band and its lines)
        solver["frf_band"] = direct.solver["frf_band"]
    solver["start"] = {k: v["value"] for k, v in direct.parameters.items()}
    solver["name"] = (f"{res.solver['name']}, the plant's compliant model from the two-mass fit's mapping "
                      "(Levenberg-Marquardt on the log response)")
    traces = {}
    for name, tr in res.traces.items():
        d = direct.traces.get(name, {})
        models = dict(d.get("models", {}))
        models[f"plant model as written ({res.fit_percent[name]:.1f} %)"] = tr["model"]
        traces[name] = {**tr, "models": models, "chosen": "two-mass"}
    warns = [w for w in direct.warnings if "its interval counts only the mode" not in w]
    spread = held_key_spread(res.plant, res.keys, "two-mass", speed_rad_s=frf[0].speed_rad_s, load_n=frf[0].load_n)
    reflected = with_held(_reflected(res), spread)
    res = _widen_adjusted(res, spread, start, names, uncertainty)
    return dataclasses.replace(res, warnings=[*warns, *[w for w in res.warnings if w not in warns]], solver=solver,
                               traces=traces, reflected_inertia_kg_m2=reflected)


def _widen_adjusted(res: FitResult, spread: Sequence[dict], start: Plant, names: str, uncertainty: str) -> FitResult:
    """``res`` with the interval (report, covariance and ``[uncertainty]`` entry) of the key the
    response's inertia sets widened by the held keys' spread (variances added)."""
    import dataclasses

    from ..plant.schema import PLAUSIBLE
    from .common import uncertainty_entries
    from .fituncertainty import uncertainty_choice

    if not spread or spread[0]["adjusted_key"] not in res.parameters or spread[0]["adjusted_key"] not in res.keys:
        return res
    adj = spread[0]["adjusted_key"]
    p = dict(res.parameters[adj])
    v, (lo, hi) = float(p["value"]), p["ci95"]
    sd = math.sqrt(((hi - lo) / (2 * _Z95)) ** 2 + sum(e["adjusted_sd"] ** 2 for e in spread))
    p["ci95"] = [v - _Z95 * sd, v + _Z95 * sd]
    p["ci95_fit_only"] = [float(lo), float(hi)]
    p["held_keys"] = [e["key"] for e in spread]
    params = {**res.parameters, adj: p}
    cov = res.covariance
    if cov is not None:
        cov = np.array(cov, float)
        i = res.keys.index(adj)
        cov[i, i] = sd * sd
    rng = PLAUSIBLE.get(adj, (0.0, math.inf))[:2]
    plant = res.plant
    fit_unc = uncertainty_entries(plant, {adj: p}, names, [sd], [rng])
    choice_u, note = uncertainty_choice(plant, adj, (start.uncertainty or {}).get(adj), fit_unc.get(adj), p["ci95"], rng,
                                        uncertainty)
    warns = [*res.warnings, f"{adj}: its interval includes the spread of the keys held at base values ("
             + ", ".join(f"{e['key']} sd {e['sd']:.3g}" for e in spread) + "), which one response cannot tell from it"]
    if choice_u is not None:
        unc = dict(plant.uncertainty or {})
        unc[adj] = choice_u
        plant = Plant(name=plant.name, values=plant.values, sources=plant.sources, origin=plant.origin,
                      description=plant.description, uncertainty=unc, mechanism=plant.mechanism,
                      defaulted=plant.defaulted, mechanism_source=plant.mechanism_source)
    if note:
        warns.append(note)
    corr = res.correlation
    if cov is not None:
        sds = np.sqrt(np.clip(np.diag(cov), 0, None))
        with np.errstate(all="ignore"):
            corr = np.nan_to_num(cov / np.outer(sds, sds))
    return dataclasses.replace(res, plant=plant, parameters=params, covariance=cov, correlation=corr, warnings=warns)


def _plant_features(plant: Plant, keys, values, speed: float, load: float, f0_hz: float):
    """Apparent inertia at ``f0_hz`` (``Im(1/G(jw))/w``, kg m^2), first anti-resonance and first
    axial mode (Hz) of the plant's compliant model linearised at ``speed``, ``load``."""
    from scipy.linalg import eigvals

    from .frf import linearised

    lin = linearised(plant, tuple(keys), "compliant")
    a, b = lin(speed, load, np.asarray(values, float))
    nx = a.shape[0]
    c = np.zeros(nx)
    c[lin.i_w] = 1.0
    w0 = 2 * math.pi * f0_hz
    g = c @ np.linalg.solve(1j * w0 * np.eye(nx) - a, b[:, 0].astype(complex))
    j_app = float((1.0 / g).imag / w0)
    ev = np.linalg.eigvals(a)
    osc = sorted((e for e in ev if e.imag > 1e-3 * abs(e)), key=abs)
    mm = np.block([[a, b[:, :1]], [c[None, :], np.zeros((1, 1))]])
    nn = np.zeros_like(mm)
    nn[:nx, :nx] = np.eye(nx)
    with np.errstate(all="ignore"):
        zs = eigvals(mm, nn)
    zs = sorted((z for z in zs if np.isfinite(z) and z.imag > 1e-3 * abs(z)), key=abs)
    if not osc or not zs:
        raise ValueError("no axial mode or anti-resonance in the plant's linearised model")
    return j_app, float(abs(zs[0]) / (2 * math.pi)), float(abs(osc[0]) / (2 * math.pi))


def _match_modes(start: Plant, fit: FrfModelFit, speed: float, load: float) -> Plant:
    """``start`` with its motor-side inertia, load-side mass and stiffness keys set so that the
    plant's own linearised model has the fitted two-mass model's apparent inertia (at a tenth of
    the anti-resonance), anti-resonance and mode: three equations, three unknowns (bounded
    least squares on their logarithms, from ``start``)."""
    from scipy.optimize import least_squares

    from .twomass import model_response

    keys = axial_mode_keys(start.mechanism, "inertias") + axial_mode_keys(start.mechanism, "springs")[:1]
    fa, fr = fit.value("antiresonance_hz"), fit.value("resonance_hz")
    f0 = 0.1 * fa
    v = {k: x["value"] for k, x in fit.values.items()}
    v["delay_s"] = 0.0
    g0 = model_response("two-mass", v, [f0], 0.0)[0]
    j_target = float((1.0 / g0).imag / (2 * math.pi * f0))
    target = np.log([j_target, fa, fr])
    x0 = np.log([start.values[k] for k in keys])

    def resid(x):
        try:
            return np.log(_plant_features(start, keys, np.exp(x), speed, load, f0)) - target
        except (ValueError, FitError, np.linalg.LinAlgError):
            return np.full(3, 10.0)

    sol = least_squares(resid, x0, bounds=(x0 - math.log(10.0), x0 + math.log(10.0)), max_nfev=60, xtol=1e-10)
    if not np.all(np.abs(sol.fun) < 1e-3):
        raise FitError("the plant's model cannot take the fitted inertia, anti-resonance and mode together")
    with _warnings.catch_warnings():
        _warnings.simplefilter("ignore")
        return start.with_params(dict(zip(keys, (float(x) for x in np.exp(sol.x)))), name=start.name)


def _reflected(res: FitResult) -> dict:
    """The written plant's reflected inertia with its 95 % interval from the fit's covariance of
    every written key it depends on (delta method: central differences of
    :attr:`Plant.reflected_inertia_kg_m2`)."""
    p = res.plant
    j = float(p.reflected_inertia_kg_m2)
    keys = [k for k in res.plant_keys if k in p.values]
    if res.covariance is None or not keys:
        return dict(res.reflected_inertia_kg_m2)
    idx = [res.keys.index(k) for k in keys]
    cov = np.asarray(res.covariance, float)[np.ix_(idx, idx)]
    grad = np.zeros(len(keys))
    with _warnings.catch_warnings():
        _warnings.simplefilter("ignore")
        for i, k in enumerate(keys):
            v = p.values[k]
            h = 1e-6 * abs(v)
            jp = p.with_params({k: v + h}).reflected_inertia_kg_m2
            jm = p.with_params({k: v - h}).reflected_inertia_kg_m2
            grad[i] = (jp - jm) / (2 * h)
    sd = math.sqrt(max(float(grad @ cov @ grad), 0.0))
    return {"value": j, "ci95": [j - 1.959963984540054 * sd, j + 1.959963984540054 * sd], "unit": "kg m^2"}
