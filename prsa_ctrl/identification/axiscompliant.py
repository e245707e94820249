"""The time-domain fit of a **two-mass linear axis** (``prsa-fit LOG... --log-format F --fidelity
compliant``): the motor side, the load mass, the stiffness and the damping between them fitted on
the closed-loop replay of the logs, then validated so that it can say no.

Model: :mod:`prsa_ctrl.identification.axistwomass` (the motor side ``M - m_l`` with the axis's
friction and the logged position, the load mass ``m_l`` beyond a spring ``k`` N/m and a damper of
modal damping ratio ``zeta``), replayed closed loop from the reference with the log's controller
(:func:`prsa_ctrl.identification.axis.simulate_axis`).

1. **Starts that do not depend on luck.** Mass and friction from inverse-dynamic least squares
   (:func:`prsa_ctrl.identification.axis.start_estimate`); the second mass from a two-mass fit of a
   frequency response (:func:`prsa_ctrl.identification.twomass.fit_frf_model`, force -> speed in
   load coordinates: (m/s)/N is (rad/s)/(N m) at 1 m per rad): a measured one when given
   (``frf``), else the one the logs give (:func:`axis_frf`: the indirect closed-loop estimate
   through the test signal at the drive input, an independent signal the loop does not feed
   back), else the base plant's own second mass.
2. **Output error**: ``m_m = M - m_l, Fv+, Fv-, Fc+, Fc-, m_l, k, zeta`` minimise the position and
   force errors of every log's replay, each weighted by its RMS at the start (as the rigid fit,
   :func:`prsa_ctrl.identification.axis.fit_linear_axis`), bounded trust region, a bound on the
   replays. 95 % intervals from the sandwich covariance with a batch-means long-run variance
   (:func:`prsa_ctrl.identification.covariance.batch_covariance`) and Student's t; derived values (the
   total mass, the anti-resonance, the mode) by the delta method.
3. **Validation** (:func:`prsa_ctrl.identification.axisvalidation.validate_axis`, the rigid fit's
   too): each log's closed-loop replay of the plant **as written** is explained when nothing in its
   residual is what the model should have explained (a share predicted by the excitation, a
   resonance above the noise floor, a force periodic in the position) and its error is within the
   screw path's allowance; with more than one log each log left out is replayed by the plant fitted
   on the others (leave-one-out). Every fitted key is written as fitted (the written plant *is* the
   free fit). A fit that does not pass has a diagnosis naming the most likely missing physics;
   ``prsa-fit`` then ends with exit 3 and no plant file unless ``--force``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from ..errors import AxisFitError
from .axis import (METRIC_SKIP_SAMPLES, PARAMETERS, AxisReplay, LinearAxisPlant, check_force_limit, normal_entry,
                   replay_axis, simulate_axis, start_estimate)
from .covariance import batch_covariance, t95
from .axisvalidation import diagnosis, refusal_line, validate_axis
from .logformat import AxisLog

__all__ = ["TWO_MASS_PARAMETERS", "TwoMassAxisFit", "fit_two_mass_axis", "axis_frf", "second_mass_start",
           "diagnosis", "refusal_line", "MAX_EVALUATIONS"]

#: The fitted keys of the two-mass axis, in this order (plant keys; ``axis.mass_kg`` the total).
TWO_MASS_PARAMETERS = (*PARAMETERS, "axis.load_mass_kg", "axis.load_stiffness_n_per_um", "axis.axial_damping_ratio")
_UNITS = {"axis.mass_kg": "kg", "friction.viscous_positive_n_s_per_m": "N s/m",
          "friction.viscous_negative_n_s_per_m": "N s/m", "friction.coulomb_positive_n": "N",
          "friction.coulomb_negative_n": "N", "axis.load_mass_kg": "kg", "axis.load_stiffness_n_per_um": "N/um",
          "axis.axial_damping_ratio": "-"}
#: Default bound on the output-error fit's residual evaluations (each Jacobian adds one replay per
#: fitted value).
MAX_EVALUATIONS = 40
#: The plant schema's range of the damping ratio (the fit's bounds).
_ZETA_RANGE = (1e-4, 1.0)
_Z95 = 1.959963984540054


def axis_frf(logs: Sequence[AxisLog], nperseg: int | None = None):
    """The frequency response force -> speed ((m/s)/N) of closed-loop logs, with its coherence.

    The indirect (two-step) estimate through the test signal ``r`` the drive adds to the
    controller's output: ``G = S_rv / S_rF`` (Welch, Hann, 50 % overlap, linear detrend), ``F`` the
    logged force (drive gain x command, which holds ``r``), ``v`` the one-sample position
    difference (m/s) beside the command of the same sample, as
    :func:`prsa_ctrl.plots.fit.log_response` pairs them. ``r`` is not fed back by the loop, so the
    estimate is not biased by the loop's noise (the open-loop ``S_Fv / S_FF`` is). The coherence is
    the smaller of ``r``'s with ``F`` and with ``v``. Bins from the second up to ``0.45 / Ts`` where
    ``r`` has power (above 1e-3 of its largest), averaged over the logs (each weighted by its
    ``S_rF`` magnitude).

    Returns
    -------
    (frequency_hz, response, coherence) or None
        None when no log has a test signal, or the logs are under 256 samples.
    """
    from scipy.signal import csd, welch

    parts = []
    for lg in logs:
        if lg.test_signal is None or lg.n < 256 or not np.any(lg.test_signal != lg.test_signal[0]):
            continue
        ts = float(lg.sample_time_s)
        r = np.asarray(lg.test_signal, float)[1:]
        f_n = lg.gain_n_per_unit * np.asarray(lg.command, float)[1:]
        v = np.diff(np.asarray(lg.position_m, float)) / ts
        n = len(r)
        seg = int(min(4096, max(256, 2 ** int(math.floor(math.log2(max(n // 2, 1))))))) if nperseg is None else nperseg
        kw = dict(fs=1.0 / ts, window="hann", nperseg=min(seg, n), noverlap=min(seg, n) // 2, detrend="linear")
        f, p_rr = welch(r, **kw)
        p_ff, p_vv = welch(f_n, **kw)[1], welch(v, **kw)[1]
        s_rf, s_rv = csd(r, f_n, **kw)[1], csd(r, v, **kw)[1]
        keep = (np.arange(len(f)) >= 2) & (f <= 0.45 / ts) & (p_rr > 1e-3 * np.max(p_rr[1:]))
        keep &= (p_ff > 0) & (p_vv > 0) & (np.abs(s_rf) > 0)
        with np.errstate(all="ignore"):
            coh = np.minimum(np.abs(s_rf) ** 2 / (p_rr * p_ff), np.abs(s_rv) ** 2 / (p_rr * p_vv))
        parts.append((f, keep, s_rf, s_rv, np.clip(coh, 0.0, 1.0)))
    if not parts:
        return None
    f = parts[0][0]
    same = [p for p in parts if p[0].shape == f.shape and np.allclose(p[0], f)]
    keep = np.logical_and.reduce([p[1] for p in same])
    if np.count_nonzero(keep) < 14:
        return None
    s_rf = sum(p[2] for p in same)
    s_rv = sum(p[3] for p in same)
    coh = np.mean([p[4] for p in same], axis=0)
    g = s_rv[keep] / s_rf[keep]
    ok = np.isfinite(g) & (g != 0)
    return f[keep][ok], g[ok], np.clip(coh[keep][ok], 0.0, 0.999)


def second_mass_start(logs: Sequence[AxisLog], base: LinearAxisPlant, frf=None):
    """The start of the second mass: ``((m_l kg, k N/m, zeta), source, FrfModelFit or None)``.

    From the two-mass fit of ``frf`` (a measured response: an ``FrfRecord``, a sequence of them,
    or ``(frequency_hz, response[, coherence])`` in (m/s)/N) when given, else of :func:`axis_frf`
    of the logs, else the base plant's second mass. The load mass is the response's load-side
    mass, the stiffness from its anti-resonance ``k = m_l (2 pi f_a)^2``. :class:`AxisFitError`
    when none gives one.
    """
    from ..errors import FitError
    from .twomass import fit_frf_model

    why = []
    cands = [("the measured frequency response", frf, 0.0)] if frf is not None else []
    est = axis_frf(logs)
    if est is not None and frf is None:
        cands.append(("the logs' frequency response (through the test signal)", est, float(logs[0].sample_time_s)))
    elif frf is None:
        why.append("the logs have no test signal at the drive input to estimate a frequency response from")
    for what, data, ts in cands:
        try:
            fit = fit_frf_model(data, "two-mass", sample_time_s=ts)
        except (FitError, ValueError) as exc:
            why.append(f"the two-mass fit of {what} failed ({exc})")
            continue
        jt, jl = fit.value("total_inertia_kg_m2"), fit.value("load_inertia_kg_m2")
        fa, zeta = fit.value("antiresonance_hz"), fit.value("damping_ratio")
        if not (jt > 0 and 0 < jl < jt and fa > 0 and math.isfinite(zeta)):
            why.append(f"the two-mass fit of {what} gives no usable second mass")
            continue
        ml = jl
        k = ml * (2.0 * math.pi * fa) ** 2
        zeta = min(max(zeta, _ZETA_RANGE[0]), 0.5)
        return (ml, k, zeta), (f"{what}: anti-resonance {fa:.4g} Hz, mode {fit.value('resonance_hz'):.4g} Hz, load "
                               f"share {jl / jt:.4g}, damping {zeta:.3g}"), fit
    if base.second_mass is not None:
        return base.second_mass, "the base plant's second mass", None
    raise AxisFitError("no start for the second mass: " + "; ".join(why) + "; expected --frf FRF.csv (force -> speed, "
                       "(m/s)/N), a log with a test signal at the drive input, or a base plant with "
                       "axis.load_mass_kg > 0")


@dataclass(frozen=True)
class TwoMassAxisFit:
    """Result of :func:`fit_two_mass_axis` (the keys of :meth:`as_dict` are those of
    :meth:`prsa_ctrl.identification.axis.AxisFit.as_dict`, plus ``start_from`` and ``validation``).

    Attributes
    ----------
    plant : LinearAxisPlant
        The fitted two-mass axis (``axis.load_mass_kg`` > 0).
    parameters : dict
        Per key of :data:`TWO_MASS_PARAMETERS`: value, 95 % interval, std, unit, start.
    equivalent : dict
        Derived values with 95 % intervals (total and motor-side mass, the anti-resonance and the
        mode in Hz, friction equivalents).
    replays : list of AxisReplay
        Each log replayed closed loop through the plant as written.
    validation : dict
        ``passes``, ``reasons``, ``diagnosis`` (None when it passes), per log the replay metrics,
        the cross-validation and the rule.
    """

    plant: LinearAxisPlant
    parameters: Mapping[str, Mapping[str, Any]]
    equivalent: Mapping[str, Mapping[str, Any]]
    replays: Sequence[AxisReplay]
    covariance: NDArray[np.float64]
    blocks: int
    status: str
    iterations: int
    warnings: Sequence[str]
    cost: float
    message: str
    start_from: str
    validation: Mapping[str, Any] = field(default_factory=dict)
    frf_fit: Any = None

    @property
    def ok(self) -> bool:
        from ..results import is_ok

        return is_ok(self.status)

    @property
    def passes(self) -> bool:
        return bool(self.validation.get("passes"))

    def as_dict(self) -> dict:
        """JSON-ready report (see the class docstring)."""
        from .axis import COORDINATES, MECHANISM

        sd = np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
        idx = [j for j in range(len(TWO_MASS_PARAMETERS)) if sd[j] > 0]
        corr = self.covariance[np.ix_(idx, idx)] / np.outer(sd[idx], sd[idx])
        np.fill_diagonal(corr, 1.0)
        return {"mechanism": MECHANISM, "coordinates": COORDINATES, "status": self.status,
                "solver_status": "converged", "iterations": self.iterations, "cost": self.cost,
                "solver_message": self.message, "structure": "two-mass",
                "method": "output error of the closed-loop replay from the reference of the two-mass axis (position "
                          "and force, each weighted by its residual RMS at the start); mass and friction started from "
                          "inverse-dynamic least squares, the second mass from " + self.start_from + "; 95 % "
                          "intervals from the sandwich covariance with a batch-means long-run variance of the scores "
                          f"({self.blocks} contiguous blocks, Student's t with {self.blocks - 1} degrees of freedom)",
                "start_from": self.start_from,
                "frf_fit": None if self.frf_fit is None else self.frf_fit.as_dict(),
                "parameters": {k: dict(v) for k, v in self.parameters.items()},
                "equivalent": {k: dict(v) for k, v in self.equivalent.items()},
                "covariance": {"keys": list(TWO_MASS_PARAMETERS),
                               "units": [_UNITS[k] for k in TWO_MASS_PARAMETERS], "matrix": self.covariance.tolist()},
                "correlation": {"keys": [TWO_MASS_PARAMETERS[j] for j in idx], "matrix": corr.tolist()},
                "replay": [r.as_dict() for r in self.replays], "validation": dict(self.validation),
                "warnings": list(self.warnings)}


def _theta(x: NDArray[np.float64]):
    """``(rigid theta, second mass)`` of the fitted vector ``[m_m, Fv+, Fv-, Fc+, Fc-, m_l, k N/m, zeta]``."""
    # (a friction term held at 0 may sit a rounding below it inside its bounds)
    return (x[0] + x[5], *np.maximum(x[1:5], 0.0)), (float(x[5]), float(x[6]), float(x[7]))


def _residuals(x, logs, flim, starts, sig, skip):
    theta, second = _theta(x)
    out_p, out_f = [], []
    for lg, x0 in zip(logs, starts):
        tr = simulate_axis(theta, lg, force_limit_n=flim, x0=x0, second_mass=second)
        out_p.append(tr.position_m[skip:] - lg.position_m[skip:])
        out_f.append(lg.gain_n_per_unit * (tr.command[skip:] - lg.command[skip:]))
    return np.concatenate(out_p), np.concatenate(out_f)


def _solve(logs, x0, lb, ub, flim, starts, sig, skip, max_evaluations):
    from scipy.optimize import least_squares

    def resid(x):
        p, f = _residuals(x, logs, flim, starts, sig, skip)
        return np.concatenate([p / sig[0], f / sig[1]])

    return least_squares(resid, x0, bounds=(lb, ub), x_scale=np.maximum(np.abs(x0), 1e-3 * np.abs(x0).max()),
                         diff_step=1e-6, method="trf", max_nfev=max_evaluations, xtol=1e-10, ftol=1e-10, gtol=1e-10)


def _derived(p: NDArray[np.float64], cov: NDArray[np.float64], z: float) -> dict:
    """Derived values with 95 % intervals (delta method, numerical gradient) of the reported vector
    ``p`` (:data:`TWO_MASS_PARAMETERS` order; stiffness in N/um)."""
    from .axis import SMALL_SPEED_M_S

    vs = SMALL_SPEED_M_S

    def fa(q):
        return math.sqrt(q[6] * 1e6 / q[5]) / (2 * math.pi)

    def fr(q):
        return fa(q) * math.sqrt(q[0] / (q[0] - q[5]))

    funcs = {
        "mass_kg": (lambda q: q[0], "kg", "total moving mass (motor side + load mass)"),
        "motor_side_mass_kg": (lambda q: q[0] - q[5], "kg", "the motor side's mass (with the encoder and the friction)"),
        "load_mass_kg": (lambda q: q[5], "kg", "the load mass beyond the spring"),
        "stiffness_n_per_um": (lambda q: q[6], "N/um", "the spring between them"),
        "damping_ratio": (lambda q: q[7], "-", "modal damping ratio of the axial mode"),
        "antiresonance_hz": (fa, "Hz", "sqrt(k / m_l) / 2 pi"),
        "mode_hz": (fr, "Hz", "the axial mode, sqrt(k M / (m_m m_l)) / 2 pi"),
        "viscous_n_s_per_m": (lambda q: 0.5 * (q[1] + q[2]), "N s/m", "mean of the two directions' viscous coefficients"),
        "friction_positive_n": (lambda q: q[3] + vs * q[1], "N", f"friction force at +{vs:g} m/s (signed)"),
        "friction_negative_n": (lambda q: -q[4] - vs * q[2], "N", f"friction force at -{vs:g} m/s (signed)"),
        "offset_n": (lambda q: 0.5 * (q[3] - q[4]), "N", "constant force offset: (Fc+ - Fc-)/2"),
    }
    out = {}
    for k, (fn, unit, meaning) in funcs.items():
        v = float(fn(p))
        g = np.zeros(len(p))
        for j in range(len(p)):
            dp = 1e-6 * max(abs(p[j]), 1e-9)
            q = p.copy()
            q[j] += dp
            g[j] = (fn(q) - v) / dp
        sd = float(math.sqrt(max(g @ cov @ g, 0.0)))
        out[k] = {"value": v, "ci95": [v - z * sd, v + z * sd], "std": sd, "unit": unit, "meaning": meaning}
    return out


def fit_two_mass_axis(logs: Sequence[AxisLog], base: LinearAxisPlant, *, frf=None,
                      max_evaluations: int = MAX_EVALUATIONS, name: str = "fitted",
                      cross_validate: bool = True) -> TwoMassAxisFit:
    """Fit a two-mass linear axis on closed-loop logs and validate it (module docstring).

    Parameters
    ----------
    logs : sequence of AxisLog
        Closed-loop logs: each needs its controller and reference (the replay is the closed loop).
    base : LinearAxisPlant
        Supplies the drive gain, force limit and sensor; its second mass is the last start.
    frf : FrfRecord, sequence of FrfRecord, or (frequency_hz, response[, coherence]), optional
        A measured frequency response force -> speed ((m/s)/N) whose two-mass fit starts the
        second mass.
    max_evaluations : int
        Bound on the residual evaluations of each output-error fit (an integer >= 1).
    name : str
        The fitted plant's name.
    cross_validate : bool
        With more than one log, refit on all but one and replay the one left out.

    Returns
    -------
    TwoMassAxisFit
        ``validation["passes"]`` False (``status`` flagged) when the written plant does not
        explain the logs: the caller writes no plant file then (``prsa-fit``'s exit 3).

    Raises
    ------
    AxisFitError
        No start for the second mass, or the fit did not converge within the bound.
    ValueError
        No logs, a log without its controller or reference, a force limit below the logged
        forces, or a bad ``max_evaluations``.
    """
    if not logs:
        raise ValueError("logs: expected at least one log")
    if isinstance(max_evaluations, bool) or not isinstance(max_evaluations, (int, np.integer)) or max_evaluations < 1:
        raise ValueError(f"max_evaluations = {max_evaluations!r}; expected an integer >= 1")
    for lg in logs:
        if lg.controller is None or lg.reference_m is None:
            raise ValueError(f"{lg.name}: no controller or reference in its description; expected a closed-loop log "
                             "([controller] and [reference]) for the two-mass fit, which replays the closed loop")
    flim = base.values.get("drive.force_limit_n", math.inf)
    check_force_limit(flim, logs, f"base plant {base.name!r}")
    theta0, informed = start_estimate(logs, base)
    base_theta = base.theta
    warnings = []
    theta0[1:] = np.maximum(theta0[1:], 0.0)
    mirrored = {}
    for j in np.flatnonzero(~informed):
        other = {1: 2, 2: 1, 3: 4, 4: 3}[int(j)]
        if informed[other]:  # held at the other direction's start (the replay still moves a little this way:
            theta0[j] = theta0[other]  # dither, overshoot; a friction-free direction would run away there)
            mirrored[int(j)] = PARAMETERS[other]
            warnings.append(f"{PARAMETERS[j]}: the logs barely move the axis in that direction; held at the other "
                            f"direction's start {theta0[j]:.6g} (not fitted)")
        else:
            warnings.append(f"{PARAMETERS[j]}: the logs never move the axis in that direction; kept the base value "
                            f"{base_theta[j]:.6g}")
    second, start_from, frf_fit = second_mass_start(logs, base, frf)
    if frf_fit is not None:  # the response's low-frequency asymptote: the total mass, unbiased by the mode
        theta0[0] = frf_fit.value("total_inertia_kg_m2")  # (inverse dynamics on a two-mass axis sees less of it)
    ml0 = min(second[0], 0.95 * theta0[0])
    x0 = np.array([theta0[0] - ml0, *theta0[1:5], ml0, second[1], min(max(second[2], 2 * _ZETA_RANGE[0]), 0.9)])
    skip = METRIC_SKIP_SAMPLES
    starts = [(float(lg.position_m[0]), 0.0) for lg in logs]
    p0, f0 = _residuals(x0, logs, flim, starts, (1.0, 1.0), skip)
    sig = (math.sqrt(np.mean(p0 ** 2)) or 1e-12, math.sqrt(np.mean(f0 ** 2)) or 1e-12)
    free = np.array([True, *informed[1:], True, True, True])
    lb = np.array([1e-3 * x0[0], 0, 0, 0, 0, 1e-3 * x0[5], 1e-3 * x0[6], _ZETA_RANGE[0]])
    ub = np.array([np.inf] * 7 + [_ZETA_RANGE[1]])

    def solve(fit_logs, fit_starts, start):
        lo, hi = lb.copy(), ub.copy()
        lo[~free] = np.maximum(start[~free] - 1e-12 * (1 + abs(start[~free])), lb[~free])  # held (never below 0)
        hi[~free] = np.maximum(start[~free], lb[~free]) + 1e-12 * (1 + abs(start[~free]))
        return _solve(fit_logs, np.clip(start, lb, ub), lo, hi, flim, fit_starts, sig, skip, max_evaluations)

    sol = solve(logs, starts, x0)
    if sol.status <= 0:
        raise AxisFitError(f"two-mass output-error fit did not converge within {max_evaluations} evaluations (cost "
                           f"{sol.cost:.6g}); expected logs whose controller description reproduces the command, and a "
                           "second mass the start can reach (--frf with the axial mode)")
    x = sol.x
    n_time = sum(lg.n - skip for lg in logs)
    # columns scaled to relative changes first: a stiffness of 1e6 N/m beside a mass of 10 kg would
    # otherwise put J'J's eigenvalues 1e12 apart, and the pseudo-inverse would drop the stiffness's
    scale = np.maximum(np.abs(x[free]), 1e-9)
    cov_s, blocks = batch_covariance(np.asarray(sol.jac)[:, free] * scale, sol.fun, n_time)
    cov_x_free = cov_s * np.outer(scale, scale)
    z = t95(blocks - 1)
    cov_x = np.zeros((8, 8))
    cov_x[np.ix_(free, free)] = cov_x_free
    # reported vector p = [M, Fv+, Fv-, Fc+, Fc-, m_l, k N/um, zeta] = T x
    T = np.eye(8)
    T[0, 5] = 1.0
    T[6, 6] = 1e-6
    p = T @ x
    p[1:5] = np.maximum(p[1:5], 0.0)  # a friction term at its bound 0 may sit a rounding below it
    cov = T @ cov_x @ T.T
    names = ", ".join(Path(lg.name).name for lg in logs)
    params, values, sources, unc = {}, {}, {}, {}
    x0p = T @ x0
    for j, k in enumerate(TWO_MASS_PARAMETERS):
        sd = float(math.sqrt(max(cov[j, j], 0.0)))
        v = float(p[j])
        lo, hi = v - z * sd, v + z * sd
        entry = {"value": v, "ci95": [lo, hi], "std": sd, "unit": _UNITS[k], "start": float(x0p[j])}
        if j < 5 and not informed[j]:  # held, not fitted: no interval (was a zero-width one that excluded the truth)
            entry.update(ci95=None, std=None, note="held, not fitted: no interval")
            entry["kept_base"] = j not in mirrored
            sources[k] = (f"held at the start of {mirrored[j]} (inverse dynamics on {names}): the logs barely move "
                          "the axis in this direction" if j in mirrored else base.sources[k])
        else:
            sources[k] = f"fit: {names} (95 % CI {lo:.6g}..{hi:.6g}; closed-loop output error, two-mass axis)"
            e = normal_entry(v, z * sd / _Z95, k in ("axis.mass_kg", "axis.load_mass_kg",
                                                     "axis.load_stiffness_n_per_um"), f"fit: {names} (95 % CI "
                                                                                      f"{lo:.6g}..{hi:.6g})")
            if e is not None and k != "axis.axial_damping_ratio":
                unc[k] = e
        at_bound = (x[j] <= lb[j] * (1 + 1e-9) + 1e-12) or (x[j] >= ub[j] * (1 - 1e-9))
        if at_bound and free[j]:
            entry["at_bound"] = True
            warnings.append(f"{k} ended at a bound of the fit ({v:.6g} {_UNITS[k]}): not identified by these logs")
        params[k], values[k] = entry, v
    what = (f"two-mass linear axis calibrated by prsa-fit from {names} (closed-loop output error; the second mass "
            f"started from {start_from})")
    fitted = LinearAxisPlant(name=name, values={**base.values, **values}, sources={**base.sources, **sources},
                             description=f"{base.description}; {what}" if base.description else what,
                             command_unit=base.command_unit, uncertainty=unc)
    replays = [replay_axis(fitted, lg) for lg in logs]
    derived = _derived(p, cov, z)
    unidentified = [f"{k} held at {mirrored[j]}'s start" if j in mirrored else f"{k} kept at the base value"
                    for j, k in enumerate(PARAMETERS) if not informed[j]]
    unidentified += [f"{k} ended at a bound of the fit ({params[k]['value']:.6g})" for k in PARAMETERS[1:]
                     if params[k].get("at_bound")]
    validation = validate_axis(fitted, logs, replays, replay_axis, skip,
                               refit=_refit(fitted, solve, x) if cross_validate else None,
                               mode_hz=derived["mode_hz"]["value"], unidentified=unidentified)
    flags = [] if validation["passes"] else [f"validation failed: {validation['reasons'][0]}"]
    flags += [f"{k} ended at a bound" for k, e in params.items() if e.get("at_bound")]
    status = "flagged: " + "; ".join(flags) if flags else "ok"
    if not validation["passes"]:
        warnings.append(f"validation failed: {validation['reasons'][0]}" + (
            f" (and {len(validation['reasons']) - 1} more)" if len(validation["reasons"]) > 1 else "")
            + f"; most likely missing physics: {validation['diagnosis']}")
    return TwoMassAxisFit(fitted, params, derived, replays, cov, blocks, status, int(sol.nfev), warnings,
                          float(sol.cost), str(sol.message), start_from, validation, frf_fit)


def _refit(fitted: LinearAxisPlant, solve, x):
    """The cross-validation's refit: the two-mass fit on other logs, started at ``x``."""
    def refit(others):
        sol = solve(others, [(float(o.position_m[0]), 0.0) for o in others], x)
        if sol.status <= 0:
            raise AxisFitError(f"did not converge: {sol.message}")
        theta, second = _theta(sol.x)
        return fitted.with_values({**dict(zip(PARAMETERS, map(float, theta))), "axis.load_mass_kg": second[0],
                                   "axis.load_stiffness_n_per_um": second[1] * 1e-6,
                                   "axis.axial_damping_ratio": second[2]}, {})
    return refit
