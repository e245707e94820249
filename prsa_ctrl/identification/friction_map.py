"""The friction curve from steady-speed plateaus (numpy/scipy only): the Stribeck keys.

The time-domain fit (:func:`prsa_ctrl.identification.timedomain.fit_plant`) leaves out the
data below a minimum speed (three Stribeck velocities plus Karnopp's blend band): one collocation
step per sample cannot resolve stick-slip. The Stribeck keys (``friction.static``,
``friction.stribeck_velocity_m_s``, ``friction.no_load_breakaway_torque_n_m``) live exactly
there; they come from this module instead, on the steady parts of the records, where the
torque balance needs no dynamics at all.

Plateaus (:func:`find_plateaus`)
    Over a record the interval speed (angle difference over one sample) is smoothed by a moving
    mean of :data:`SMOOTH_S`. A plateau is a maximal stretch in which the smoothed speed stays
    within ``max(PLATEAU_RTOL |v|, atol)`` of its value at the stretch's start (``atol``: two
    encoder counts over the smoothing window, :data:`PLATEAU_ATOL_COUNTS`), keeps its sign and
    lies outside Karnopp's stick band. The first :data:`SETTLE_FRACTION` of the stretch (the
    transient after the speed change) and one smoothing window at each end are dropped; what
    is left must last :data:`MIN_PLATEAU_S` and hold :data:`BATCHES` batches of at least
    :data:`MIN_BATCH_SAMPLES` samples. Per plateau: the mean speed (angle travelled over the
    time), the mean axial load and its magnitude, the mean motor torque (the command through the
    plant's current loop: at steady state its mean, corrected by ``J dv/dt`` for the small
    speed change across the plateau) and the friction torque, the motor torque less the load
    torque through the screw ``a F``. Its standard error comes from :data:`BATCHES` batch means
    (the within-plateau scatter with its autocorrelation: the quantisation, the speed loop),
    never below :data:`SE_FLOOR_FRACTION` of the torque limit.

The law (:func:`plateau_torque`)
    The plant's sliding friction at steady speed (:mod:`prsa_ctrl.plant.model`), per plateau::

        T_f(w, F) = sign(w) [c_F |F| (1 + (mu_s/mu_d - 1) g) + T_0 + (T_s0 - T_0) g] + b w + b_o |w| + T_o
        g = exp(-(a w / v_s)^2),   c_F = a (1/eta - 1)

    in the plant keys ``friction.efficiency`` (``eta``), ``no_load_torque_n_m`` (``T_0``),
    ``viscous_n_m_s_per_rad`` (``b``), ``viscous_offset_n_m_s_per_rad`` (``b_o``), ``torque_offset_n_m`` (``T_o``), ``static`` (``mu_s``),
    ``stribeck_velocity_m_s`` (``v_s``) and ``no_load_breakaway_torque_n_m`` (``T_s0``); the
    Gaussian exponent 2 is the model's. ``mu_s`` and ``T_s0`` are separated only by plateaus at
    two or more loads (one load informs their sum).

The fit (:func:`fit_friction_map`)
    Weighted nonlinear least squares (``scipy.optimize.least_squares``, trust-region reflective
    within each key's bounds, at most :data:`MAX_NFEV` evaluations) of the chosen keys, the
    others held at the plant's values. Covariance ``s^2 (J^T W J)^-1`` with ``s^2`` the reduced
    chi-square when above 1 (a misfit widens the intervals, never narrows them). Below 1 the
    standard errors stand: batch means over-estimate the error of a plateau mean whose noise is
    differenced (quantised speed through a PI loop) by up to sqrt(batches), so the intervals are
    then conservative; scaling them down by the residuals was tried and is not safe: on the
    foreign generator's staircase (reduced chi-square ~0.1) a common bias of 1e-4 relative in
    the plateau torques (the drive's, not noise) then put the breakaway level 2.2 standard
    errors off. When the held
    keys come with a covariance (the time-domain fit's), it is propagated: ``G C G^T`` added,
    ``G`` the sensitivity of the fitted keys to the held ones (the implicit-function theorem
    of the weighted normal equations), so the intervals are not conditional on them. The
    identifiability decision is the time-domain fit's (:func:`prsa_ctrl.identification.common.info_split`
    on the column-scaled Jacobian, :data:`~prsa_ctrl.identification.common.RANK_RTOL`, and the
    interval rules of :func:`~prsa_ctrl.identification.common.finish_fit`), plus the data
    rule of the Stribeck keys: without a plateau below :data:`STRIBECK_REGION` Stribeck speeds
    they are not identified, whatever the numbers (their interval is their physical range, the
    plant keeps the base value, a warning says which plateaus to record).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from ..plant.model import stick_band_rad_s
from ..plant.plantfile import Plant
from ..plant.schema import BREAKAWAY_KEY
from .common import FitResult, finish_fit, info_split, key_bounds, motor_torque
from .data import Record

__all__ = ["Plateau", "FrictionMap", "STRIBECK_KEYS", "LAW_KEYS", "PLATEAU_RTOL", "PLATEAU_ATOL_COUNTS", "SMOOTH_S",
           "SETTLE_FRACTION", "MIN_PLATEAU_S", "BATCHES", "MIN_BATCH_SAMPLES", "MAX_PLATEAUS", "MAX_NFEV",
           "STRIBECK_REGION", "SE_FLOOR_FRACTION", "find_plateaus", "plateau_torque", "fit_friction_map",
           "stribeck_stage", "stribeck_rounds", "AXIS_CURVE", "axis_friction_map"]

#: The Stribeck keys: fitted on plateaus (this module), never by the time-domain fit.
STRIBECK_KEYS = ("friction.static", "friction.stribeck_velocity_m_s", BREAKAWAY_KEY)
#: Every key of the steady friction law (:func:`plateau_torque`).
LAW_KEYS = ("friction.efficiency", "friction.no_load_torque_n_m", "friction.viscous_n_m_s_per_rad",
            "friction.torque_offset_n_m", "friction.viscous_offset_n_m_s_per_rad") + STRIBECK_KEYS
#: A plateau's smoothed speed stays within this fraction of its speed...
PLATEAU_RTOL = 0.05
#: ... or within this many encoder counts over the smoothing window, whichever is larger.
PLATEAU_ATOL_COUNTS = 2.0
#: Moving-mean window of the speed for the plateau search, s.
SMOOTH_S = 0.01
#: Part of a steady stretch dropped at its start (the transient after the speed change).
SETTLE_FRACTION = 0.2
#: Shortest plateau (after the drops), s.
MIN_PLATEAU_S = 0.1
#: Batches of the batch-means standard error, and the fewest samples per batch.
BATCHES = 10
MIN_BATCH_SAMPLES = 20
#: At most this many plateaus over all records (the longest kept).
MAX_PLATEAUS = 500
#: Function evaluations of the least-squares fit, at most.
MAX_NFEV = 400
#: Plateaus below this many Stribeck speeds ``v_s / a`` inform the Stribeck keys.
STRIBECK_REGION = 3.0
#: Smallest standard error of a plateau's friction torque, a fraction of the torque limit (a
#: perfectly quiet command still carries its own resolution).
SE_FLOOR_FRACTION = 1e-7

_Z95 = 1.959963984540054


@dataclass(frozen=True)
class Plateau:
    """One steady-speed plateau of a record (SI units: s, rad/s, N, N m)."""

    record: str
    start_s: float
    stop_s: float
    samples: int
    speed_rad_s: float
    load_n: float
    abs_load_n: float
    motor_torque_n_m: float
    friction_n_m: float
    se_n_m: float

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass(frozen=True, eq=False)
class FrictionMap:
    """Result of :func:`fit_friction_map`.

    Attributes
    ----------
    keys : tuple of str
        The fitted keys.
    values : ndarray
        Fitted values (file units), order of ``keys``.
    covariance : ndarray
        Their covariance (file units), with the held keys' covariance propagated when given.
    held_sensitivity : ndarray
        ``d values / d held`` (``len(keys) x len(held)``), the held keys in ``held``.
    held : tuple of str
    lower, upper : ndarray
        Bounds of the fitted keys (file units).
    null : ndarray
        Directions the data do not inform (columns, file units; :func:`info_split`).
    ratios : ndarray
        Singular values of the column-scaled Jacobian over the largest.
    plateaus : list of Plateau
    chi2_reduced : float
        Weighted residual sum of squares over its degrees of freedom (nan without any).
    in_stribeck_region : int
        Plateaus below :data:`STRIBECK_REGION` fitted Stribeck speeds.
    warnings : list of str
    status : str
        The least-squares solver's message.
    """

    keys: tuple
    values: NDArray[np.float64]
    covariance: NDArray[np.float64]
    held_sensitivity: NDArray[np.float64]
    held: tuple
    lower: NDArray[np.float64]
    upper: NDArray[np.float64]
    null: NDArray[np.float64]
    ratios: NDArray[np.float64]
    plateaus: list
    chi2_reduced: float
    in_stribeck_region: int
    warnings: list = field(default_factory=list)
    status: str = ""


# --- plateaus -------------------------------------------------------------------------------------

def _moving_mean(x: NDArray[np.float64], w: int) -> NDArray[np.float64]:
    """Centred moving mean over ``w`` samples (shorter at the ends), same length as ``x``."""
    c = np.concatenate([[0.0], np.cumsum(x)])
    i = np.arange(len(x))
    lo = np.clip(i - w // 2, 0, len(x))
    hi = np.clip(lo + w, 0, len(x))
    lo = np.clip(hi - w, 0, None)
    return (c[hi] - c[lo]) / (hi - lo)


def _steady_runs(vs: NDArray[np.float64], atol: float, rtol: float, still: float) -> list[tuple[int, int]]:
    """Maximal runs ``[i, j)`` where ``vs`` stays within ``max(rtol |ref|, atol)`` of ``ref = vs[i]``
    with one sign and ``|ref| > still`` (one pass: O(len(vs)))."""
    runs, i, n = [], 0, len(vs)
    while i < n:
        ref = vs[i]
        tol = max(rtol * abs(ref), atol)
        j = i + 1
        if abs(ref) > still:
            while j < n and abs(vs[j] - ref) <= tol and vs[j] * ref > 0:
                j += 1
            runs.append((i, j))
        i = j
    return runs


def find_plateaus(record: Record, plant: Plant, *, rtol: float = PLATEAU_RTOL, min_duration_s: float = MIN_PLATEAU_S,
                  smooth_s: float = SMOOTH_S) -> list[Plateau]:
    """The steady-speed plateaus of ``record`` (criteria in the module docstring).

    Parameters
    ----------
    record : Record
    plant : Plant
        Lead (load torque), current loop (motor torque), inertia (``J dv/dt``), encoder
        resolution (speed tolerance), stick band (standstill is no plateau), torque limit.
    rtol : float
        Speed tolerance, fraction of the plateau's speed.
    min_duration_s : float, s
        Shortest plateau kept.
    smooth_s : float, s
        Moving-mean window of the speed.

    Returns
    -------
    list of Plateau
        In time order; empty when the record has none.
    """
    for name, val in (("rtol", rtol), ("min_duration_s", min_duration_s), ("smooth_s", smooth_s)):
        if isinstance(val, bool) or not isinstance(val, (int, float)) or not (math.isfinite(val) and val > 0):
            raise ValueError(f"{name} = {val!r}; expected a number > 0")
    ts = record.sample_time_s
    v = record.speed_rad_s  # interval k -> k+1
    if len(v) < 2:
        return []
    w = max(3, int(round(smooth_s / ts)))
    vs = _moving_mean(v, w)
    atol = PLATEAU_ATOL_COUNTS * 2 * math.pi / plant.encoder_counts / (w * ts)
    still = max(2.0 * stick_band_rad_s(plant), atol)
    tau = motor_torque(record, plant)
    a = plant.lead_per_rad
    floor = SE_FLOOR_FRACTION * plant.torque_limit
    need = max(int(math.ceil(min_duration_s / ts)), BATCHES * MIN_BATCH_SAMPLES)
    out = []
    for i, j in _steady_runs(vs, atol, rtol, still):
        i0 = i + int(math.ceil(SETTLE_FRACTION * (j - i))) + w
        j0 = j - w
        m = j0 - i0
        if m < need:
            continue
        f = record.axial_load_n[i0:j0]
        # the torque acting over interval k is the motor torque between samples k and k+1
        t_int = 0.5 * (tau[i0:j0] + tau[i0 + 1:j0 + 1])
        fr = t_int - a * 0.5 * (f + record.axial_load_n[i0 + 1:j0 + 1])
        speed = float(np.mean(v[i0:j0]))
        accel = (vs[j0 - 1] - vs[i0]) / ((j0 - 1 - i0) * ts)
        corr = plant.reflected_inertia_kg_m2 * accel
        lb = m // BATCHES
        means = fr[: lb * BATCHES].reshape(BATCHES, lb).mean(axis=1)
        se = max(float(np.std(means, ddof=1)) / math.sqrt(BATCHES), floor)
        out.append(Plateau(record=record.name, start_s=float(record.time_s[i0]), stop_s=float(record.time_s[j0]),
                           samples=int(m), speed_rad_s=speed, load_n=float(np.mean(f)),
                           abs_load_n=float(np.mean(np.abs(f))), motor_torque_n_m=float(np.mean(t_int) - corr),
                           friction_n_m=float(np.mean(fr) - corr), se_n_m=se))
    return out


# --- the law --------------------------------------------------------------------------------------

def plateau_torque(values: Mapping[str, float], plant: Plant, speed_rad_s, abs_load_n) -> NDArray[np.float64]:
    """Friction torque (N m; the motor torque less the load torque ``a F``) of the plant's law at
    steady nut speed ``speed_rad_s`` (rad/s, outside the stick band) and axial load magnitude
    ``abs_load_n`` (N), with the friction keys of ``values`` (file units; others the plant's)."""
    def val(k):
        return values[k] if k in values else plant.values[k]

    w = np.asarray(speed_rad_s, float)
    f_abs = np.asarray(abs_load_n, float)
    a = plant.lead_per_rad
    eta, mu_d = val("friction.efficiency"), plant.values["friction.dynamic"]
    lossless = eta >= 1.0 or mu_d == 0.0
    c_f = 0.0 if lossless else a * (1.0 / eta - 1.0)
    ratio = 1.0 if lossless else val("friction.static") / mu_d
    t0 = val("friction.no_load_torque_n_m")
    ts0 = val(BREAKAWAY_KEY)
    g = np.exp(-((a * w / val("friction.stribeck_velocity_m_s")) ** 2))
    level = c_f * f_abs * (1.0 + (ratio - 1.0) * g) + t0 + (ts0 - t0) * g
    return (np.sign(w) * level + val("friction.viscous_n_m_s_per_rad") * w + val("friction.torque_offset_n_m")
            + val("friction.viscous_offset_n_m_s_per_rad") * np.abs(w))


def _held_keys(plant: Plant, keys: Sequence[str]) -> tuple[str, ...]:
    return tuple(k for k in LAW_KEYS if k not in keys and k in plant.values)


def _bounds(plant: Plant, keys: Sequence[str]) -> tuple[NDArray, NDArray, NDArray]:
    ts = plant.sample_time_s
    b = [key_bounds(plant, k, ts) for k in keys]
    return (np.array([x[0] for x in b]), np.array([x[1] for x in b]), np.array([x[2] for x in b]))


def _jacobian(fun, x: NDArray[np.float64], steps: NDArray[np.float64]) -> NDArray[np.float64]:
    """Central differences of ``fun`` at ``x`` (one column per entry of ``x``)."""
    cols = []
    for i, h in enumerate(steps):
        e = np.zeros_like(x)
        e[i] = h
        cols.append((fun(x + e) - fun(x - e)) / (2 * h))
    return np.column_stack(cols) if cols else np.zeros((len(fun(x)), 0))


def _wls(resid, x0, lo, hi, scale):
    """Bounded weighted least squares in scaled units (``resid(s)``: weighted residuals, ``s`` =
    value / ``scale``): the solution, the reduced chi-square, the Jacobian, its column norms, the
    rank-revealing split (:func:`info_split`) and the covariance (file units, widened by the
    reduced chi-square when above 1)."""
    sol = least_squares(resid, x0, bounds=(lo / scale, hi / scale), x_scale=1.0, method="trf", max_nfev=MAX_NFEV,
                        xtol=1e-12, ftol=1e-12, gtol=1e-12)
    s_hat = sol.x
    r = resid(s_hat)
    dof = len(r) - len(s_hat)
    chi2 = float(r @ r / dof) if dof > 0 else math.nan
    j_s = _jacobian(resid, s_hat, np.full(len(s_hat), 1e-6))
    norms = np.linalg.norm(j_s, axis=0)
    norms = np.where(norms > 0, norms, 1.0)
    a_inv, null_n, ratios = info_split(j_s / norms)
    cov_s = a_inv / np.outer(norms, norms)
    if math.isfinite(chi2) and chi2 > 1.0:
        cov_s = cov_s * chi2
    return sol, s_hat, chi2, j_s, norms, a_inv, null_n, ratios, cov_s * np.outer(scale, scale)


def fit_friction_map(plateaus: Sequence[Plateau], plant: Plant, keys: Sequence[str] = STRIBECK_KEYS, *,
                     held_covariance: NDArray[np.float64] | None = None) -> FrictionMap:
    """Weighted least squares of the friction law on ``plateaus`` (module docstring).

    Parameters
    ----------
    plateaus : sequence of Plateau
        From :func:`find_plateaus`.
    plant : Plant
        Values of the keys not fitted (held), bounds, the lead.
    keys : sequence of str
        Keys to fit, some of :data:`LAW_KEYS`.
    held_covariance : ndarray, optional
        Covariance (file units) of the held keys (:attr:`FrictionMap.held` order): propagated
        into the fitted keys' covariance. None: the intervals are conditional on the held values.

    Returns
    -------
    FrictionMap
    """
    keys = tuple(keys)
    if not keys or len(set(keys)) != len(keys) or any(k not in LAW_KEYS for k in keys):
        raise ValueError(f"keys = {keys!r}; expected some of {', '.join(LAW_KEYS)}, each once")
    if plant.mechanism == "linear-axis":
        raise ValueError("a linear-axis plant; expected a rotary plant (the linear axis's friction keys are per "
                         "direction: prsa_ctrl.identification.axis)")
    plateaus = list(plateaus)
    if not plateaus:
        raise ValueError("plateaus = []; expected at least one steady-speed plateau (record constant speeds)")
    held = _held_keys(plant, keys)
    w = np.array([p.speed_rad_s for p in plateaus])
    f_abs = np.array([p.abs_load_n for p in plateaus])
    y = np.array([p.friction_n_m for p in plateaus])
    se = np.array([p.se_n_m for p in plateaus])
    lo, hi, scale = _bounds(plant, keys)
    x0 = np.clip(np.array([plant.values[k] for k in keys]), lo, hi) / scale

    def resid_all(s_fit, held_vals):
        vals = dict(zip(keys, s_fit * scale))
        vals.update(zip(held, held_vals))
        return (plateau_torque(vals, plant, w, f_abs) - y) / se

    h0 = np.array([plant.values[k] for k in held])
    sol, s_hat, chi2, j_s, norms, a_inv, null_n, ratios, cov = _wls(lambda s: resid_all(s, h0), x0, lo, hi, scale)
    sens = np.zeros((len(keys), len(held)))
    if held:
        # steps on each held key's fit scale (a key at 0, e.g. an offset, still gets a usable step)
        h_steps = np.array([1e-6 * key_bounds(plant, k, plant.sample_time_s)[2] for k in held])
        j_h = _jacobian(lambda hv: resid_all(s_hat, hv), h0, h_steps)
        sens = -(a_inv / np.outer(norms, norms).clip(1e-300)) @ (j_s.T @ j_h) * scale[:, None]
        if held_covariance is not None:
            hc = np.asarray(held_covariance, float)
            if hc.shape != (len(held), len(held)):
                raise ValueError(f"held_covariance of shape {hc.shape}; expected {(len(held), len(held))} "
                                 f"(the held keys {', '.join(held)})")
            cov = cov + sens @ hc @ sens.T
    null = null_n / norms[:, None] * scale[:, None]
    values = s_hat * scale
    vs_hat = dict(zip(keys, values)).get("friction.stribeck_velocity_m_s", plant.values["friction.stribeck_velocity_m_s"])
    region = STRIBECK_REGION * vs_hat / plant.lead_per_rad
    n_region = int(np.sum(np.abs(w) < region))
    warns = []
    if math.isfinite(chi2) and chi2 > _CHI2_WARN:
        warns.append(f"the friction law fits the plateaus with a reduced chi-square of {chi2:.3g} (expected ~1): the "
                     "intervals are widened by its square root; the friction keys held at the plant's values may be off "
                     "(fit them too: friction.no_load_torque_n_m, friction.torque_offset_n_m, friction.efficiency, "
                     "friction.viscous_n_m_s_per_rad), or plateaus drift, or the log misses a load")
    return FrictionMap(keys, values, cov, sens, held, lo, hi, null, ratios, plateaus, chi2, n_region, warns,
                       str(sol.message))


# --- the stage of fit_plant ----------------------------------------------------------------------

def _remedy(plant: Plant, w_s: float) -> str:
    levels = ", ".join(f"{m * w_s:.3g}" for m in (0.3, 0.6, 1.0, 1.5, 2.5, 5.0))
    return (f"record a low-speed staircase: plateaus of at least {max(MIN_PLATEAU_S, 0.5):g} s at about {levels} rad/s "
            f"(0.3..5 Stribeck speeds of the base plant, w_s = {w_s:.3g} rad/s) in both directions, at two axial loads "
            "or more (to separate friction.static from the drag's breakaway)")


def _td_covariance(result: FitResult, held: Sequence[str]) -> NDArray[np.float64]:
    """Covariance of the held keys from the time-domain result (its honest standard deviations,
    half the 95 % interval over 1.96, and its correlation); 0 for keys it did not fit."""
    idx = {k: i for i, k in enumerate(result.keys)}
    sd = np.zeros(len(held))
    for n, k in enumerate(held):
        if k in idx and not result.parameters[k].get("kept_base"):
            lo, hi = result.parameters[k]["ci95"]
            v = result.parameters[k]["value"]
            sd[n] = max(hi - v, v - lo) / _Z95
    corr = np.eye(len(held))
    for a_, ka in enumerate(held):
        for b_, kb in enumerate(held):
            if ka in idx and kb in idx:
                corr[a_, b_] = result.correlation[idx[ka], idx[kb]]
    return corr * np.outer(sd, sd)


def _restored(plant: Plant, base: Plant, keys: Sequence[str]) -> Plant:
    """``plant`` with the base plant's values and sources of ``keys`` (a round-2 start carries
    round 1's values; a key not identified keeps the base's). A defaulted breakaway level follows
    the plant's no-load torque."""
    if all(plant.values[k] == base.values[k] and plant.sources[k] == base.sources[k] for k in keys):
        return plant
    values, sources, defaulted = dict(plant.values), dict(plant.sources), set(plant.defaulted)
    for k in keys:
        values[k], sources[k] = base.values[k], base.sources[k]
        defaulted.discard(k)
        if k in base.defaulted:
            defaulted.add(k)
            if k == BREAKAWAY_KEY:
                values[k] = values["friction.no_load_torque_n_m"]
        elif k == BREAKAWAY_KEY and values[k] < values["friction.no_load_torque_n_m"]:
            values[k] = values["friction.no_load_torque_n_m"]  # the start at least the fitted drag
            sources[k] = f"{base.sources[k]} (raised to the fitted friction.no_load_torque_n_m)"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the base plant's geometry notes were given when it loaded
        return Plant(name=plant.name, values=values, sources=sources, origin=plant.origin,
                     description=plant.description, uncertainty=plant.uncertainty, mechanism=plant.mechanism,
                     defaulted=frozenset(defaulted), mechanism_source=plant.mechanism_source)


def stribeck_stage(result: FitResult | None, records: Sequence[Record], base: Plant, keys: Sequence[str], *,
                   keep_unidentified: bool = True, uncertainty: str = "keep") -> FitResult:
    """The Stribeck keys of :func:`prsa_ctrl.identification.timedomain.fit_plant` from the
    plateaus of ``records``, given the time-domain fit ``result`` (its plant's values, their
    covariance propagated); returns ``result`` with the keys added (values, intervals,
    identifiability, the fitted plant's values and sources) and ``solver["friction_map"]``."""
    keys = tuple(keys)
    if result is None:  # only Stribeck keys: the base plant's other values, nothing time-domain fitted
        j = base.reflected_inertia_kg_m2
        result = FitResult(base, {}, {"value": j, "ci95": [j, j], "unit": "kg m^2"}, np.zeros((0, 0)), (), {},
                           [w for r in records for w in r.warnings],
                           {"name": "none: only Stribeck keys (friction map on the plateaus)", "status": "n/a"})
    plant = _restored(result.plant, base, keys)
    names = ", ".join(r.name for r in records)
    warns = list(result.warnings)
    plateaus = [p for rec in records for p in find_plateaus(rec, plant)]
    if len(plateaus) > MAX_PLATEAUS:
        plateaus = sorted(sorted(plateaus, key=lambda p: -p.samples)[:MAX_PLATEAUS], key=lambda p: (p.record, p.start_s))
        warns.append(f"more than {MAX_PLATEAUS} plateaus: the {MAX_PLATEAUS} longest used")
    w_s_base = base.values["friction.stribeck_velocity_m_s"] / base.lead_per_rad
    ts = plant.sample_time_s
    lo, hi, _ = _bounds(plant, keys)
    info = {"plateaus": [p.as_dict() for p in plateaus], "keys": list(keys),
            "criteria": {"speed_rtol": PLATEAU_RTOL, "speed_atol_counts_per_window": PLATEAU_ATOL_COUNTS,
                         "smoothing_s": SMOOTH_S, "settle_fraction_dropped": SETTLE_FRACTION,
                         "min_plateau_s": MIN_PLATEAU_S, "batches": BATCHES,
                         "stribeck_region_speeds": STRIBECK_REGION}}
    fm = None
    if len(plateaus) > len(keys):
        held = _held_keys(plant, keys)
        fm = fit_friction_map(plateaus, plant, keys, held_covariance=_td_covariance(result, held))
        values, cov, null, ratios = fm.values, fm.covariance, fm.null, fm.ratios
        warns += fm.warnings
        region = fm.in_stribeck_region
        info.update(chi2_reduced=fm.chi2_reduced, status=fm.status, in_stribeck_region=region,
                    intervals=("unconditional: the covariance of the time-domain keys " + ", ".join(
                        k for k in held if k in result.keys) + " propagated (first order)")
                    if any(k in result.keys for k in held) else "conditional on the base plant's friction keys "
                    "(none of them fitted)")
    else:
        values = np.array([plant.values[k] for k in keys])
        cov = np.zeros((len(keys), len(keys)))
        null, ratios, region = np.zeros((len(keys), 0)), np.zeros(len(keys)), 0
    why = None
    if fm is None:
        why = (f"{len(plateaus)} steady-speed plateau{'s' if len(plateaus) != 1 else ''} in {names}; expected more "
               f"than {len(keys)}")
    elif region == 0:
        why = (f"no plateau below {STRIBECK_REGION:g} Stribeck speeds ({STRIBECK_REGION:g} x "
               f"{fm.values[keys.index('friction.stribeck_velocity_m_s')] / plant.lead_per_rad if 'friction.stribeck_velocity_m_s' in keys else w_s_base:.3g} rad/s)"
               f"; the slowest of {len(plateaus)} at {min(abs(p.speed_rad_s) for p in plateaus):.3g} rad/s")
    if why is not None:  # the data rule: every key on an uninformed direction, the range its interval
        values = np.array([plant.values[k] for k in keys])
        cov = np.zeros((len(keys), len(keys)))
        null = np.diag(np.maximum(hi - lo, 1e-300))
        ratios = np.zeros(len(keys))
    params, corr, fitted, _, _, reasons = finish_fit(plant, keys, values, cov, lo, hi, names, warns, ts,
                                                     keep_unidentified, null, ratios, uncertainty)
    if why is not None:
        reason = f"{why}: {_remedy(base, w_s_base)}"
        warns[:] = [x for x in warns if not any(x.startswith(f"{k} ") for k in keys)]
        for k in keys:
            params[k]["reason"] = reasons[k] = reason
            if keep_unidentified:
                params[k].update(kept_base=True, written=plant.values[k])
        warns.append(f"{', '.join(keys)} not identified, kept at the base values ({reason})")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the base plant's geometry notes were given when it loaded
        fitted = dataclasses.replace(fitted, name=plant.name)
    n_all = len(result.keys) + len(keys)
    corr_all = np.eye(n_all)
    corr_all[: len(result.keys), : len(result.keys)] = result.correlation
    corr_all[len(result.keys):, len(result.keys):] = corr
    if fm is not None and why is None and result.keys:  # cov(stribeck, td) = G cov(held, td)
        c_td = _td_covariance(result, result.keys)
        rows = np.array([c_td[result.keys.index(k)] if k in result.keys else np.zeros(len(result.keys))
                         for k in fm.held]).reshape(len(fm.held), len(result.keys))
        cross = fm.held_sensitivity @ rows
        sd_s = np.sqrt(np.clip(np.diag(cov), 0, None))
        sd_t = np.sqrt(np.clip(np.diag(c_td), 0, None))
        with np.errstate(invalid="ignore", divide="ignore"):
            c = np.nan_to_num(cross / np.outer(sd_s, sd_t))
        corr_all[len(result.keys):, : len(result.keys)] = c
        corr_all[: len(result.keys), len(result.keys):] = c.T
    solver = dict(result.solver)
    solver["friction_map"] = info
    return dataclasses.replace(result, plant=fitted, parameters={**result.parameters, **params},
                               correlation=corr_all, keys=(*result.keys, *keys), warnings=warns, solver=solver,
                               not_identified={**result.not_identified, **reasons})


def stribeck_rounds(fit_rest, records: Sequence[Record], base: Plant, keys: Sequence[str], delay_samples=None, *,
                    keep_unidentified: bool = True, uncertainty: str = "keep") -> FitResult:
    """The Stribeck keys with the time-domain fit of the others, in two rounds.

    Round 1: ``fit_rest(base, delay_samples)`` (the time-domain fit of the other keys; None:
    there are none), then :func:`stribeck_stage`. The time-domain model uses the Stribeck curve
    too (above the minimum speed its tail is small, but long steady data resolve it: with the
    base plant's Stribeck values the foreign-log fit's efficiency sat 4.6 standard errors off),
    so when round 1 identified any Stribeck key, round 2 refits the others from the base plant
    with those values (the delay round 1 found, no second search) and runs the stage again. The
    report's ``solver["friction_map"]["rounds"]`` says how many ran.
    """
    keys = tuple(keys)
    res = fit_rest(base, delay_samples) if fit_rest is not None else None
    out = stribeck_stage(res, records, base, keys, keep_unidentified=keep_unidentified, uncertainty=uncertainty)
    found = {k: out.parameters[k]["value"] for k in keys if not out.parameters[k].get("kept_base")}
    rounds = 1
    if fit_rest is not None and found:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the base plant's geometry notes were given when it loaded
            start = base.with_params(found, name=base.name)
        cd = res.solver.get("command_delay")
        res2 = fit_rest(start, cd["shift_samples"] if cd is not None else delay_samples)
        if cd is not None:  # as round 1 found it: its statement, warning and source
            key = "drive.command_delay_samples"
            extra = [w for w in res.warnings if w.startswith("the logged command acts") and w not in res2.warnings]
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                p2 = res2.plant
                p2 = Plant(name=p2.name, values=p2.values, sources={**p2.sources, key: res.plant.sources[key]},
                           origin=p2.origin, description=p2.description, uncertainty=p2.uncertainty,
                           mechanism=p2.mechanism, defaulted=p2.defaulted, mechanism_source=p2.mechanism_source)
            res2 = dataclasses.replace(res2, plant=p2, warnings=[*res2.warnings, *extra],
                                       solver={**res2.solver, "command_delay": cd})
        out = stribeck_stage(res2, records, base, keys, keep_unidentified=keep_unidentified, uncertainty=uncertainty)
        rounds = 2
    out.solver["friction_map"]["rounds"] = rounds
    return out


# --- a linear axis in load coordinates (the EMPS case) ---------------------------------------------

#: Parameters of the load-side friction curve (:func:`axis_friction_map`), unit.
AXIS_CURVE = {"coulomb_positive_n": "N", "coulomb_negative_n": "N", "viscous_positive_n_s_per_m": "N s/m",
              "viscous_negative_n_s_per_m": "N s/m", "stribeck_excess_n": "N", "stribeck_velocity_m_s": "m/s"}


#: Reduced chi-square of a plateau fit above which a warning says the friction law misses the data.
_CHI2_WARN = 4.0
#: Plateau fields of a linear axis (load coordinates) under their unit names: the plateau search
#: works in the plant's coordinates, which for a linear axis are m/s and N.
_AXIS_PLATEAU_FIELDS = {"speed_rad_s": "speed_m_s", "motor_torque_n_m": "force_n", "friction_n_m": "friction_n",
                        "se_n_m": "se_n"}


def _axis_curve(p: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Friction force (N) at speed ``v`` (m/s): ``Fc+ + Fs g + Fv+ v`` moving in +x, ``-(Fc- + Fs g)
    + Fv- v`` in -x, ``g = exp(-(v/v_s)^2)``; ``p`` in :data:`AXIS_CURVE` order."""
    fcp, fcn, fvp, fvn, fs, vs = p
    g = np.exp(-((v / vs) ** 2))
    return np.where(v > 0, fcp + fs * g + fvp * v, -(fcn + fs * g) + fvn * v)


def axis_friction_map(name: str, time_s, position_m, force_n, plant: Plant) -> dict:
    """The friction curve of a linear axis (load coordinates: m, N) from the steady-speed plateaus
    of one record, for a report (the replay model of the axis stays Coulomb + viscous).

    Plateaus as :func:`find_plateaus` (``plant``: the axis as a :class:`Plant`, its mass, encoder
    resolution and current loop; the force through that loop); the curve of :data:`AXIS_CURVE`
    by weighted least squares, 95 % intervals (the covariance widened by the reduced chi-square
    when above 1), identifiability as :func:`fit_friction_map` plus the Stribeck data rule. When
    the Stribeck terms are not identified, the Coulomb and viscous terms are refitted without
    them and reported with their intervals.

    Returns
    -------
    dict
        ``parameters`` (``{name: {"value", "ci95", "unit", "identified", ...}}``), ``plateaus``
        (in load coordinates: ``speed_m_s``, ``force_n``, ``friction_n``, ``se_n`` besides the
        times and loads), ``chi2_reduced``, ``warnings`` (a reduced chi-square above 4),
        ``stribeck`` (identified or why not), ``note``, ``criteria``.
    """
    arrays = {"time_s": time_s, "position_m": position_m, "force_n": force_n}
    shapes = {k: np.shape(a) for k, a in arrays.items()}
    if len(set(shapes.values())) != 1 or len(shapes["time_s"]) != 1 or shapes["time_s"][0] < 2:
        raise ValueError(f"{name}: time_s, position_m and force_n have shapes "
                         f"{', '.join(str(s) for s in shapes.values())}; expected one-dimensional arrays of one length, "
                         "at least 2 samples")
    for k, a in arrays.items():
        bad = np.flatnonzero(~np.isfinite(np.asarray(a, float)))
        if bad.size:
            raise ValueError(f"{name}: {k}[{bad[0]}] = {float(np.asarray(a, float)[bad[0]])!r}; expected finite values")
    rec = Record(name, np.asarray(time_s, float), np.asarray(force_n, float), np.asarray(position_m, float), None,
                 np.zeros(len(time_s)))
    plateaus = find_plateaus(rec, plant)
    out = {"note": "friction force per direction from the log's steady-speed plateaus (mean force less the "
                   "inertia's share over each plateau); a report only: the replay model stays Coulomb + viscous",
           "plateaus": [{_AXIS_PLATEAU_FIELDS.get(k, k): x for k, x in p.as_dict().items()} for p in plateaus],
           "warnings": [],
           "criteria": {"speed_rtol": PLATEAU_RTOL, "smoothing_s": SMOOTH_S, "settle_fraction_dropped": SETTLE_FRACTION,
                        "min_plateau_s": MIN_PLATEAU_S, "batches": BATCHES, "stribeck_region_speeds": STRIBECK_REGION}}
    v = np.array([p.speed_rad_s for p in plateaus])
    y = np.array([p.friction_n_m for p in plateaus])
    se = np.array([p.se_n_m for p in plateaus])
    if np.sum(v > 0) < 2 or np.sum(v < 0) < 2:
        out["stribeck"] = "not identified"
        out["error"] = (f"{int(np.sum(v > 0))} plateau(s) moving in +x and {int(np.sum(v < 0))} in -x; expected at "
                        "least two at different speeds in each direction")
        return out
    f_lim = plant.torque_limit
    vmax = float(np.max(np.abs(v)))
    lo = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 1e-7])
    hi = np.array([f_lim, f_lim, 10 * f_lim / vmax, 10 * f_lim / vmax, f_lim, 1.0])
    scale = np.array([max(float(np.mean(np.abs(y))), 1e-9)] * 2 + [max(float(np.mean(np.abs(y))) / vmax, 1e-9)] * 2
                     + [max(float(np.mean(np.abs(y))), 1e-9), float(np.min(np.abs(v)))])
    x0 = np.array([0.5, 0.5, 0.5, 0.5, 0.1, 1.0])

    def fit(free):
        def resid(s):
            p = np.where(free, 0.0, 0.0)
            p[free] = s * scale[free]
            if not free[4]:
                p[5] = 1.0
            return (_axis_curve(p, v) - y) / se
        return _wls(resid, x0[free], lo[free], hi[free], scale[free])

    names = list(AXIS_CURVE)
    free = np.ones(6, bool)
    sol, s_hat, chi2, _, _, _, null_n, ratios, cov = fit(free)
    vals = s_hat * scale
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    region = int(np.sum(np.abs(v) < STRIBECK_REGION * vals[5]))
    why = None
    if null_n.shape[1]:
        why = f"the plateaus inform only a combination of the Stribeck terms (singular value ratio {float(np.min(ratios)):.1e})"
    elif region == 0 or region == len(v):
        why = (f"{region} of {len(v)} plateaus below {STRIBECK_REGION:g} Stribeck speeds ({STRIBECK_REGION:g} x "
               f"{vals[5]:.3g} m/s): the curve needs plateaus inside and outside that region")
    elif any(_Z95 * sd[i] > 0.5 * abs(vals[i]) or vals[i] <= lo[i] * (1 + 1e-6) + 1e-15 for i in (4, 5)):
        why = "the Stribeck excess or velocity has a 95 % interval wider than +/- 50 % of its value or ends at a bound"
    if why is not None:
        free = np.array([True, True, True, True, False, False])
        sol, s_hat, chi2, _, _, _, null_n, ratios, cov_f = fit(free)
        vals = np.zeros(6)
        vals[free] = s_hat * scale[free]
        sd = np.zeros(6)
        sd[free] = np.sqrt(np.clip(np.diag(cov_f), 0, None))
        out["stribeck"] = (f"not identified: {why}; record plateaus from ~0.3 to ~5 Stribeck speeds in both "
                           "directions (a low-speed staircase below the slowest plateau here, "
                           f"{float(np.min(np.abs(v))):.3g} m/s)")
    else:
        out["stribeck"] = "identified"
    params = {}
    for i, k in enumerate(names):
        ident = bool(free[i]) and not (null_n.shape[1] and np.any(np.abs(null_n[list(np.flatnonzero(free)).index(i)])
                                                                   > 1e-3))
        entry = {"value": float(vals[i]), "ci95": [float(vals[i] - _Z95 * sd[i]), float(vals[i] + _Z95 * sd[i])],
                 "unit": AXIS_CURVE[k], "identified": ident}
        if not free[i]:
            entry.update(ci95=[float(lo[i]), float(hi[i])], value=None)
        params[k] = entry
    if math.isfinite(chi2) and chi2 > _CHI2_WARN:
        out["warnings"].append(f"{Path(name).name}: the friction curve fits the plateaus with a reduced chi-square of "
                               f"{chi2:.3g} (expected ~1, warned above {_CHI2_WARN:g}): its intervals are widened by "
                               "its square root; the curve misses the plateaus (plateaus drift, or the friction "
                               "depends on position or load)")
    out.update(parameters=params, chi2_reduced=chi2, solver=str(sol.message),
               interval_method="weighted least squares on the plateau means (batch-means standard errors), "
                               "covariance widened by the reduced chi-square when above 1")
    return out
