"""Grey-box calibration of a plant from measured drive data (output error, confidence intervals).

The model is the toolkit's own CasADi model (:mod:`prsa_ctrl.model`) with the fitted plant
values as symbols, so the fitted plant is exactly what the tuner uses. Each record is cut into
multiple-shooting segments (each with its own free initial state, so that an open-loop
integration of the recorded torque command cannot drift over a long record); every sample
interval is one 3-stage Radau IIA collocation step (order 5, L-stable for the stiff friction
and current loop) with the recorded command held (zero-order hold) and the recorded load.
The residual is the measured encoder angle minus the model angle at every sample (or, without
an angle column, the measured speed minus the model's one-sample angle difference), weighted
by the encoder quantisation noise ``q / sqrt(12)``. The whole problem -- scaled, bounded
parameters, segment initial states and collocation states -- is solved by ipopt with exact
CasADi derivatives.

Confidence: the sensitivity of the residuals to the parameters (and the segment initial
states) follows from the collocation equations by the implicit-function theorem; with the
residual variance it gives the covariance, 95 % intervals (normal approximation), the
correlation matrix and identifiability warnings.
"""

from __future__ import annotations

import math
import warnings as _warnings
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from .fitdata import Record
from .plant import Plant

__all__ = ["fit_plant", "FitResult", "FitError", "FITTABLE", "DEFAULT_KEYS", "fit_percent"]

#: Plant keys the fit can estimate: unit and meaning (bounds and scales: :func:`_bounds`).
FITTABLE: Mapping[str, tuple[str, str]] = {
    "nut.inertia_kg_m2": ("kg m^2", "nut plus rotor inertia"),
    "friction.efficiency": ("-", "forward efficiency"),
    "friction.no_load_torque_n_m": ("N m", "no-load (Coulomb) drag torque"),
    "friction.viscous_n_m_s_per_rad": ("N m s/rad", "viscous coefficient"),
    "drive.current_loop_bandwidth_hz": ("Hz", "current-loop bandwidth"),
}
#: Keys fitted when none are chosen.
DEFAULT_KEYS = tuple(FITTABLE)

# 3-stage Radau IIA (order 5): stage times and coefficients; the last stage is the step end.
_S6 = math.sqrt(6.0)
_RADAU_C = ((4 - _S6) / 10, (4 + _S6) / 10, 1.0)
_RADAU_A = (
    ((88 - 7 * _S6) / 360, (296 - 169 * _S6) / 1800, (-2 + 3 * _S6) / 225),
    ((296 + 169 * _S6) / 1800, (88 + 7 * _S6) / 360, (-2 - 3 * _S6) / 225),
    ((16 - _S6) / 36, (16 + _S6) / 36, 1 / 9),
)
_Z95 = 1.959963984540054
#: Budget of one fit: total sample intervals of all records.
MAX_INTERVALS = 200_000


class FitError(RuntimeError):
    """The fit did not converge; the message names the solver status and a remedy."""


@dataclass(frozen=True, eq=False)
class FitResult:
    """Result of :func:`fit_plant`.

    Attributes
    ----------
    plant : Plant
        The base plant with the fitted values (``Plant.with_params``); sources say ``fit: ...``.
    parameters : dict
        ``{key: {"value": v, "ci95": [lo, hi], "unit": u}}`` in file units.
    reflected_inertia_kg_m2 : dict
        The total inertia at the nut in the same form, kg m^2.
    correlation : ndarray
        Correlation matrix of the fitted parameters (order of ``keys``).
    keys : tuple of str
    fit_percent : dict
        ``{record name: fit %}``: ``100 (1 - |v - v_model| / |v - mean(v)|)`` on the nut speed
        (one-sample angle difference) over the shooting segments.
    warnings : list of str
    solver : dict
        Solver name, status, iterations, final objective, residual standard deviation (in the
        unit of the residual), number of residuals, segments.
    """

    plant: Plant
    parameters: dict
    reflected_inertia_kg_m2: dict
    correlation: NDArray[np.float64]
    keys: tuple[str, ...]
    fit_percent: dict
    warnings: list
    solver: dict
    traces: dict = field(default_factory=dict, repr=False)

    def report(self) -> dict:
        """JSON-ready report (stable keys: ``parameters``, ``reflected_inertia_kg_m2``,
        ``fit_percent``, ``warnings``, ``solver``, plus ``correlation``)."""
        return {
            "parameters": self.parameters,
            "reflected_inertia_kg_m2": self.reflected_inertia_kg_m2,
            "fit_percent": self.fit_percent,
            "warnings": list(self.warnings),
            "solver": self.solver,
            "correlation": {"keys": list(self.keys), "matrix": np.round(self.correlation, 6).tolist()},
        }


class _SymbolicPlant(Plant):
    """A plant whose fitted values are CasADi symbols (the model equations accept them)."""

    @property
    def slip_arm_m(self):  # same formula as Plant.slip_arm_m without the numeric branch
        eta = self.values["friction.efficiency"]
        mu = self.values["friction.dynamic"]
        if mu == 0.0:
            return 0.0
        f_n, f_s = self.normal_force_factor()
        return self.lead_per_rad * (1.0 / eta - 1.0) / (mu * (f_n + f_s))


def _symbolic_rhs(plant: Plant, keys: Sequence[str], fidelity: str):
    """``(x, u, p) -> xdot`` of the toolkit's model with the values of ``keys`` as ``p``."""
    import casadi as ca

    from . import model as m

    p = ca.SX.sym("p", len(keys))
    values = dict(plant.values)
    for i, k in enumerate(keys):
        values[k] = p[i]
    with _warnings.catch_warnings():
        _warnings.simplefilter("ignore")
        sym = _SymbolicPlant(name=plant.name, values=values, sources=plant.sources, origin=plant.origin)
    names = m.plant_model(plant, fidelity).state_names
    x = ca.SX.sym("x", len(names))
    u = ca.SX.sym("u", 2)
    builders = {"rigid": getattr(m, "_rigid", None), "compliant": getattr(m, "_compliant", None)}
    build = builders.get(fidelity)
    if build is None:
        raise ValueError(f"fidelity = {fidelity!r}; expected 'rigid' or 'compliant' for a fit")
    try:
        xdot = build(sym, x, u)[0]
    except TypeError as exc:  # an equation that needs a numeric value of a fitted key
        raise ValueError(f"the {fidelity} model cannot take {', '.join(keys)} as fitted symbols ({exc}); "
                         "expected fewer --fit keys") from None
    return ca.Function("f", [x, u, p], [xdot]), names


def _bounds(plant: Plant, key: str, ts: float) -> tuple[float, float, float]:
    """Lower bound, upper bound and scale (file units) of a fitted key."""
    v = plant.values[key]
    t_max = plant.torque_limit
    if key == "nut.inertia_kg_m2":
        return 0.05 * v, 20.0 * v, v
    if key == "friction.efficiency":
        return 0.3, 0.995, 1.0
    if key == "friction.no_load_torque_n_m":
        return 0.0, 0.5 * t_max, max(v, 0.01 * t_max)
    if key == "friction.viscous_n_m_s_per_rad":
        return 0.0, 0.01 * t_max, max(v, 1e-5 * t_max)
    if key == "drive.current_loop_bandwidth_hz":
        return 10.0, min(1e5, 10.0 / ts), v
    raise ValueError(f"--fit key {key!r}; expected one of {', '.join(FITTABLE)}")


@dataclass
class _Seg:
    rec: int
    k0: int  # first sample of the segment
    n: int  # intervals


def _segments(records: Sequence[Record], segment_samples: int) -> list[_Seg]:
    segs = []
    for r, rec in enumerate(records):
        n_int = rec.n - 1
        n_seg = max(1, int(round(n_int / segment_samples)))
        edges = np.linspace(0, n_int, n_seg + 1).round().astype(int)
        segs += [_Seg(r, int(a), int(b - a)) for a, b in zip(edges[:-1], edges[1:])]
    return segs


def _reference(rec: Record, plant: Plant) -> NDArray[np.float64]:
    """Data-based reference trajectory (nx=3 rigid-like rows: angle, speed, torque) per sample."""
    t = rec.time_s
    if rec.nut_angle_rad is not None:
        theta = rec.nut_angle_rad.astype(float)
    else:
        theta = np.concatenate([[0.0], np.cumsum(rec.nut_speed_rad_s[1:] * np.diff(t))])
    omega = np.gradient(theta, t)
    a = math.exp(-(t[1] - t[0]) / plant.current_loop_time_constant_s)
    cmd = np.clip(rec.torque_command_n_m, -plant.torque_limit, plant.torque_limit)
    tau = np.empty_like(cmd)
    tau[0] = cmd[0]
    for k in range(1, len(cmd)):
        tau[k] = a * tau[k - 1] + (1 - a) * cmd[k - 1]
    return np.vstack([theta, omega, tau])


def fit_plant(
    records: Sequence[Record],
    plant: Plant | None = None,
    *,
    keys: Sequence[str] | None = None,
    fidelity: str = "rigid",
    validate: Sequence[Record] = (),
    segment_s: float = 0.1,
    delay_samples: int = 0,
    substeps: int = 1,
    max_iter: int = 50,
    tol: float = 1e-8,
) -> FitResult:
    """Fit plant parameters to measured time-domain records (output error through the model).

    Parameters
    ----------
    records : sequence of Record
        Records to fit (see :func:`prsa_ctrl.fitdata.load_record`); they share the parameters.
    plant : Plant, optional
        Base plant (default: the built-in default plant); its values are the initial guess and
        its sensor's encoder resolution sets the residual weights.
    keys : sequence of str, optional
        Plant keys to fit (default :data:`DEFAULT_KEYS`).
    fidelity : {"rigid", "compliant"}
        Model fidelity.
    validate : sequence of Record
        Records not fitted; their fit % is reported (only the segments' initial states are fitted).
    segment_s : float, s
        Length of a multiple-shooting segment.
    substeps : int
        Radau IIA steps per sample interval (more resolve fast friction transitions at speed
        reversals better; cost grows in proportion).
    delay_samples : int
        Samples between a logged command and the sample it acts from (0: the logged command
        is held over the interval that follows it, as in the toolkit's simulator).
    max_iter : int
        ipopt iteration budget.
    tol : float
        ipopt convergence tolerance.

    Returns
    -------
    FitResult

    Raises
    ------
    ValueError
        Bad arguments (unknown key, too long records, ...).
    FitError
        The solver did not converge (status and remedy in the message).
    """
    from .plant import load_plant

    plant = load_plant() if plant is None else plant
    records = list(records)
    if not records:
        raise ValueError("records = []; expected at least one data record")
    keys = tuple(DEFAULT_KEYS if keys is None else keys)
    if not keys:
        raise ValueError("keys = (); expected at least one plant key to fit")
    for k in keys:
        if k not in FITTABLE:
            raise ValueError(f"fit key {k!r}; expected one of {', '.join(FITTABLE)}")
    if len(set(keys)) != len(keys):
        raise ValueError(f"fit keys {', '.join(keys)}; expected each key once")
    if not (isinstance(delay_samples, int) and 0 <= delay_samples <= 10):
        raise ValueError(f"delay_samples = {delay_samples!r}; expected an integer 0..10")
    if not (isinstance(substeps, int) and 1 <= substeps <= 8):
        raise ValueError(f"substeps = {substeps!r}; expected an integer 1..8")
    if not (math.isfinite(segment_s) and segment_s > 0):
        raise ValueError(f"segment_s = {segment_s!r}; expected a time > 0 s")
    ts = records[0].sample_time_s
    for rec in (*records, *validate):
        if abs(rec.sample_time_s / ts - 1) > 1e-3:
            raise ValueError(f"{rec.name}: sample time {rec.sample_time_s:g} s differs from {ts:g} s of "
                             f"{records[0].name}; expected one sample time for all records")
    total = sum(r.n - 1 for r in (*records, *validate))
    if total > MAX_INTERVALS:
        raise ValueError(f"records hold {total} sample intervals; expected at most {MAX_INTERVALS} (shorten them)")
    bounds = [_bounds(plant, k, ts) for k in keys]
    s0 = np.array([plant.values[k] / b[2] for k, b in zip(keys, bounds)])
    lo = np.array([b[0] / b[2] for b in bounds])
    hi = np.array([b[1] / b[2] for b in bounds])
    s0 = np.clip(s0, lo, hi)
    scales = np.array([b[2] for b in bounds])

    fit_run = _Problem(plant, keys, scales, fidelity, records, ts, segment_s, delay_samples, substeps)
    try:  # two bounded attempts: a cautious and a bolder trust region for the parameter steps
        sol = fit_run.solve(s0, lo, hi, max_iter, tol, fixed=False, box=0.3)
    except FitError:
        sol = fit_run.solve(s0, lo, hi, max_iter, tol, fixed=False, box=1.0)
    s_opt = sol["s"]
    cov_s, sigma, n_res, jac_cols = fit_run.covariance(sol)
    values = s_opt * scales
    cov = cov_s * np.outer(scales, scales)
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(std, std)
    corr = np.nan_to_num(corr)
    names = ", ".join(r.name for r in records)
    params = {}
    warns: list[str] = [
        # Measured on synthetic data (tests/test_fit.py, PRSA_SLOW=1): the residual is dominated by
        # model error at zero-speed crossings, not white noise, and the truth fell inside these
        # intervals for 3 of 75 estimates. Said on every fit until the intervals are corrected.
        "the 95 % intervals assume white residuals and are too narrow when the model is not exact "
        "(on synthetic data they held the truth for 3 of 75 estimates): read them as lower bounds"
    ]
    for rec in (*records, *validate):
        warns += list(rec.warnings)
    overrides = {}
    for i, k in enumerate(keys):
        unit = FITTABLE[k][0]
        ci = [float(values[i] - _Z95 * std[i]), float(values[i] + _Z95 * std[i])]
        params[k] = {"value": float(values[i]), "ci95": ci, "unit": unit}
        overrides[k] = float(values[i])
        width = _Z95 * std[i]
        if not np.isfinite(width) or width > 0.5 * max(abs(values[i]), 1e-3 * (hi[i] - lo[i]) * scales[i]):
            warns.append(f"{k} is not identifiable from this data (95 % CI +/- {width:.3g} {unit} around "
                         f"{values[i]:.4g}): {_REMEDY_KEY.get(k, 'excite it more')}")
        if values[i] <= lo[i] * scales[i] * (1 + 1e-6) + 1e-15 or values[i] >= hi[i] * scales[i] * (1 - 1e-6):
            warns.append(f"{k} = {values[i]:.4g} {unit} is at its bound [{lo[i] * scales[i]:.4g}, {hi[i] * scales[i]:.4g}]")
    for i in range(len(keys)):
        for j in range(i + 1, len(keys)):
            if abs(corr[i, j]) > 0.95:
                warns.append(f"{keys[i]} and {keys[j]} are strongly correlated ({corr[i, j]:+.3f}): "
                             "the data cannot separate them")
    fitted = plant.with_params(overrides, name=f"{plant.name}-fit")
    srcs = dict(fitted.sources)
    for k in keys:
        lo_ci, hi_ci = params[k]["ci95"]
        srcs[k] = f"fit: {names} (95 % CI {lo_ci:.6g}..{hi_ci:.6g})"
    fitted = Plant(name=fitted.name, values=fitted.values, sources=srcs, origin=fitted.origin,
                   description=fitted.description)
    extra = plant.reflected_inertia_kg_m2 - plant.values["nut.inertia_kg_m2"]
    j_ref = fitted.reflected_inertia_kg_m2
    if "nut.inertia_kg_m2" in params:
        ci = [c + extra for c in params["nut.inertia_kg_m2"]["ci95"]]
    else:
        ci = [j_ref, j_ref]
    reflected = {"value": float(j_ref), "ci95": ci, "unit": "kg m^2"}
    fit_pct = dict(sol["fit_percent"])
    for rec in validate:
        vrun = _Problem(fitted, keys, scales, fidelity, [rec], ts, segment_s, delay_samples, substeps)
        vsol = vrun.solve(s_opt, s_opt, s_opt, max_iter, tol, fixed=True)
        fit_pct.update(vsol["fit_percent"])
    solver = {
        "name": "constrained Gauss-Newton (multiple shooting, Radau IIA collocation per sample, exact CasADi derivatives)",
        "status": sol["status"],
        "iterations": sol["iterations"],
        "objective": sol["objective"],
        "residual_std": float(sigma),
        "residual_unit": fit_run.residual_unit,
        "residuals": int(n_res),
        "segments": len(fit_run.segs),
        "fidelity": fidelity,
    }
    return FitResult(fitted, params, reflected, corr, keys, fit_pct, warns, solver, sol["traces"])


_REMEDY_KEY = {
    "friction.efficiency": "record with load changes (load steps) so that load-dependent friction shows",
    "friction.no_load_torque_n_m": "record speed reversals (a staircase through both directions)",
    "friction.viscous_n_m_s_per_rad": "record several speed levels",
    "drive.current_loop_bandwidth_hz": "excite higher frequencies (multisine up to a few hundred Hz) or fix it with --fit",
    "nut.inertia_kg_m2": "excite accelerations (multisine or speed steps)",
}


def fit_percent(measured: NDArray[np.float64], model: NDArray[np.float64]) -> float:
    """Normalised-RMS fit, % : ``100 (1 - |y - y_model| / |y - mean(y)|)``.

    Examples
    --------
    >>> fit_percent(np.array([1.0, 2.0, 3.0]), np.array([1.0, 2.0, 3.0]))
    100.0
    """
    den = float(np.linalg.norm(measured - np.mean(measured)))
    if den == 0:
        return float("nan")
    return float(100.0 * (1.0 - np.linalg.norm(measured - model) / den))


class _Problem:
    """Collocation equations, residuals and the constrained Gauss-Newton solver of a fit.

    Unknowns (all scaled): ``V`` the stage states of every sample interval (deviations from a
    data-based reference, in units of ``state_scale``), ``X0`` each segment's initial state,
    ``s`` the parameters in units of their scale. The residuals are linear in ``V`` and ``X0``;
    each Gauss-Newton step linearises the collocation equations, eliminates ``V`` segment by
    segment (sparse LU of the block-bidiagonal equations) and solves a small bounded linear
    least-squares problem for ``(s, X0)``.
    """

    def __init__(self, plant, keys, scales, fidelity, records, ts, segment_s, delay, substeps=1):
        import casadi as ca

        self.plant, self.records, self.ts = plant, records, ts
        self.scales = np.asarray(scales, float)
        f, names = _symbolic_rhs(plant, keys, fidelity)
        self.names = names
        nx = self.nx = len(names)
        npar = self.npar = len(keys)
        self.i_th = i_th = names.index("theta_nut")
        i_w, i_tau = names.index("omega_nut"), names.index("tau_motor")
        self.nsub = nsub = int(substeps)
        self.ns = ns = 3 * nsub  # collocation stages per sample interval
        seg_n = max(2, int(round(segment_s / ts)))
        self.segs = segs = _segments(records, seg_n)
        q = 2 * math.pi / plant.encoder_counts
        self.sigma0 = max(q / math.sqrt(12.0), 1e-9)
        refs = [_reference(r, plant) for r in records]
        w_scale = max(max(float(np.max(np.abs(r[1]))) for r in refs), 1.0)
        sc = np.ones(nx)
        sc[i_th] = max(w_scale * ts, 1e-6)
        sc[i_w] = 0.1 * w_scale
        sc[i_tau] = 0.1 * plant.torque_limit
        self.S = sc
        uu, hh, xr0, xrs = [], [], [], []
        for sg in segs:
            rec, ref = records[sg.rec], refs[sg.rec]
            ks = np.arange(sg.k0, sg.k0 + sg.n)
            kd = np.clip(ks - delay, 0, None)
            uu.append(np.vstack([rec.torque_command_n_m[kd], rec.axial_load_n[ks]]))
            hh.append(np.diff(rec.time_s)[ks])
            full = np.zeros((nx, rec.n))
            full[[i_th, i_w, i_tau]] = ref
            xr0.append(full[:, sg.k0])
            st = [full[:, ks] + (m + c) / nsub * (full[:, ks + 1] - full[:, ks]) for m in range(nsub) for c in _RADAU_C]
            xrs.append(np.stack(st, axis=1).reshape(nx, ns * sg.n, order="F"))
        self.U, self.H = np.hstack(uu), np.concatenate(hh)
        self.XR, self.XR0 = np.hstack(xrs), np.column_stack(xr0)
        self.M = M = self.U.shape[1]
        self.use_angle = all(r.nut_angle_rad is not None for r in records)
        self.residual_unit = "rad (encoder angle)" if self.use_angle else "rad/s (speed)"
        # One interval: scaled collocation residual and its Jacobians, mapped over all intervals.
        xs = ca.SX.sym("xs", nx)
        K = ca.SX.sym("K", nx, ns)
        u = ca.SX.sym("u", 2)
        h = ca.SX.sym("h")
        p = ca.SX.sym("p", npar)
        fk = [f(K[:, j], u, p) for j in range(ns)]
        rows = []
        for m in range(nsub):  # nsub Radau steps of h / nsub, each from the previous step's end
            x_start = xs if m == 0 else K[:, 3 * m - 1]
            for j in range(3):
                acc = sum(_RADAU_A[j][l] * fk[3 * m + l] for l in range(3))
                rows.append((K[:, 3 * m + j] - x_start - (h / nsub) * acc) / ca.DM(sc))
        res = ca.vertcat(*rows)
        kv = ca.vec(K)
        fun = ca.Function("coll", [xs, K, u, h, p],
                          [res, ca.jacobian(res, kv), ca.jacobian(res, xs), ca.jacobian(res, p)])
        self.blocks = fun.map(M, "serial")
        # Segment bookkeeping: first interval and sample offsets.
        self.first = np.cumsum([0] + [sg.n for sg in segs[:-1]])
        n3 = ns * nx
        # Sparse pattern of one segment's block-bidiagonal equations (same for all lengths n).
        self._patterns = {}
        self.n3 = n3

    # --- evaluation -----------------------------------------------------------------------
    def _physical(self, V, X0):
        nx, M = self.nx, self.M
        K = self.XR + V.reshape(M * self.ns, nx).T * self.S[:, None]
        x0 = self.XR0 + X0.reshape(len(self.segs), nx).T * self.S[:, None]
        return K, x0

    def _starts(self, K, x0):
        ends = K[:, self.ns - 1::self.ns]
        xs = np.empty((self.nx, self.M))
        for g, sg in enumerate(self.segs):
            m0 = self.first[g]
            xs[:, m0] = x0[:, g]
            xs[:, m0 + 1:m0 + sg.n] = ends[:, m0:m0 + sg.n - 1]
        return xs

    def thetas(self, V, X0):
        """Model angle (rad) at every sample of every segment, segment after segment."""
        K, x0 = self._physical(V, X0)
        ends = K[self.i_th, self.ns - 1::self.ns]
        out = []
        for g, sg in enumerate(self.segs):
            m0 = self.first[g]
            out.append(np.concatenate([[x0[self.i_th, g]], ends[m0:m0 + sg.n]]))
        return out

    def residuals(self, V, X0):
        """Weighted residual vectors per segment (dimensionless: in units of the quantisation noise)."""
        out = []
        for g, (sg, th) in enumerate(zip(self.segs, self.thetas(V, X0))):
            rec = self.records[sg.rec]
            if self.use_angle:
                out.append((th - rec.nut_angle_rad[sg.k0:sg.k0 + sg.n + 1]) / self.sigma0)
            else:
                h = np.diff(rec.time_s[sg.k0:sg.k0 + sg.n + 1])
                meas = rec.nut_speed_rad_s[sg.k0 + 1:sg.k0 + sg.n + 1]
                out.append((np.diff(th) / h - meas) / (self.sigma0 / self.ts))
        return out

    def _a_matrices(self, g):
        """d(residual)/d(V of the segment) (sparse) and d(residual)/d(X0 of the segment) (dense)."""
        from scipy.sparse import csr_matrix

        sg = self.segs[g]
        nx, n3, n = self.nx, self.n3, sg.n
        col_end = np.arange(n) * n3 + (self.ns - 1) * nx + self.i_th  # end-stage angle of each interval
        w = self.S[self.i_th] / self.sigma0
        if self.use_angle:
            a_v = csr_matrix((np.full(n, w), (np.arange(1, n + 1), col_end)), shape=(n + 1, n * n3))
            a_x = np.zeros((n + 1, nx))
            a_x[0, self.i_th] = w
        else:
            h = np.diff(self.records[sg.rec].time_s[sg.k0:sg.k0 + n + 1])
            wv = w * self.ts / h
            rows = np.concatenate([np.arange(n), np.arange(1, n)])
            cols = np.concatenate([col_end, col_end[:-1]])
            vals = np.concatenate([wv, -wv[1:]])
            a_v = csr_matrix((vals, (rows, cols)), shape=(n, n * n3))
            a_x = np.zeros((n, nx))
            a_x[0, self.i_th] = -wv[0]
        return a_v, a_x

    def linearise(self, V, X0, s):
        """Constraint residual, and per segment: the condensed residual and Jacobian columns."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.linalg import splu

        nx, n3, npar, M = self.nx, self.n3, self.npar, self.M
        K, x0 = self._physical(V, X0)
        xs = self._starts(K, x0)
        res, jk, jxs, jp = self.blocks(xs, K, self.U, self.H[None, :], s * self.scales)
        res = np.asarray(res)  # n3 x M
        jk = np.asarray(jk).reshape(n3, M, n3)  # rows, interval, cols
        jxs = np.asarray(jxs).reshape(n3, M, nx)
        jp = np.asarray(jp).reshape(n3, M, npar)
        if not (np.all(np.isfinite(res)) and np.all(np.isfinite(jk)) and np.all(np.isfinite(jp))):
            bad = int(np.argmax(~np.all(np.isfinite(res), axis=0)))
            raise FitError(f"model not finite at interval {bad} (t = {bad * self.ts:.6g} s); remedy: check the "
                           "data's units and sample time, or start from a closer base plant (--plant)")
        jk = jk * np.tile(self.S, self.ns)[None, None, :]
        jxs = jxs * self.S[None, None, :]
        jp = jp * self.scales[None, None, :]
        resid = self.residuals(V, X0)
        out = []
        for g, sg in enumerate(self.segs):
            m0, n = self.first[g], sg.n
            sl = slice(m0, m0 + n)
            # Block-bidiagonal equations of the segment.
            ii, jj = np.meshgrid(np.arange(n3), np.arange(n3), indexing="ij")
            rows = [(np.arange(n)[:, None, None] * n3 + ii[None]).ravel()]
            cols = [(np.arange(n)[:, None, None] * n3 + jj[None]).ravel()]
            vals = [np.moveaxis(jk[:, sl, :], 1, 0).ravel()]
            if n > 1:
                ia, ib = np.meshgrid(np.arange(n3), np.arange(nx), indexing="ij")
                rows.append((np.arange(1, n)[:, None, None] * n3 + ia[None]).ravel())
                cols.append((np.arange(n - 1)[:, None, None] * n3 + (self.ns - 1) * nx + ib[None]).ravel())
                vals.append(np.moveaxis(jxs[:, m0 + 1:m0 + n, :], 1, 0).ravel())
            gv = coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                            shape=(n * n3, n * n3)).tocsc()
            g_res = res[:, sl].T.ravel()
            g_s = np.moveaxis(jp[:, sl, :], 1, 0).reshape(n * n3, npar)
            g_x0 = np.zeros((n * n3, nx))
            g_x0[:n3] = jxs[:, m0, :]
            try:
                lu = splu(gv)
                z = lu.solve(np.column_stack([g_res, g_s, g_x0]))
            except RuntimeError as exc:
                raise FitError(f"collocation equations singular in segment {g} ({exc}); remedy: shorter "
                               "segments or a closer base plant (--plant)") from None
            if not np.all(np.isfinite(z)):
                raise FitError(f"collocation equations singular in segment {g}; remedy: shorter segments "
                               "or a closer base plant (--plant)")
            a_v, a_x = self._a_matrices(g)
            r_lin = resid[g] - a_v @ z[:, 0]
            j_s = -(a_v @ z[:, 1:1 + npar])
            j_x = a_x - a_v @ z[:, 1 + npar:]
            out.append((r_lin, j_s, j_x, z))
        return res, out

    def _segment_terms(self, V, X0, s):
        """Per segment: largest scaled collocation residual and objective at a trial point."""
        nseg = len(self.segs)
        try:
            K, x0 = self._physical(V, X0)
            r = np.abs(np.asarray(self.blocks(self._starts(K, x0), K, self.U, self.H[None, :], s * self.scales)[0]))
        except RuntimeError:
            return np.full(nseg, np.inf), np.full(nseg, np.inf)
        g = np.array([float(np.max(r[:, self.first[i]:self.first[i] + sg.n])) for i, sg in enumerate(self.segs)])
        f = np.array([0.5 * float(e @ e) for e in self.residuals(V, X0)])
        bad = ~(np.isfinite(g) & np.isfinite(f))
        g[bad], f[bad] = np.inf, np.inf
        return g, f

    def _merit_terms(self, V, X0, s):
        """Largest scaled collocation residual and the objective at a trial point."""
        try:
            K, x0 = self._physical(V, X0)
            r = np.asarray(self.blocks(self._starts(K, x0), K, self.U, self.H[None, :], s * self.scales)[0])
            g = float(np.max(np.abs(r)))
            f = 0.5 * sum(float(e @ e) for e in self.residuals(V, X0))
        except RuntimeError:
            return float("inf"), float("inf")
        return (g, f) if np.isfinite(g) and np.isfinite(f) else (float("inf"), float("inf"))

    def solve(self, s0, lo, hi, max_iter, tol, fixed, box=0.3):
        from scipy.optimize import lsq_linear

        nx, nseg, npar = self.nx, len(self.segs), self.npar
        V = np.zeros(self.n3 * self.M)
        X0 = np.zeros(nx * nseg)
        s = np.array(s0, float)
        status, it = "maximum iterations", 0
        free_steps = 3
        # Warm-up: a few steps on the states alone (parameters held) bring the trajectories
        # close to the data before the parameters move.
        warm = 0
        g_norm = f_val = float("nan")
        for it in range(1, int(max_iter) + warm + 1):
            res, lin = self.linearise(V, X0, s)
            g_norm = float(np.max(np.abs(res)))
            f_val = 0.5 * sum(float(r @ r) for r in self.residuals(V, X0))
            js, rv, backs = _condense(lin)
            if fixed or npar == 0 or it <= warm:
                d_s = np.zeros(npar)
            else:
                cn = np.linalg.norm(js, axis=0)
                cn[cn == 0] = 1.0
                # ``box``: trust region of one step, in units of the parameter scales
                lb_s, ub_s = np.maximum(lo - s, -box), np.minimum(hi - s, box)
                sol = lsq_linear(js / cn, -rv, bounds=(lb_s * cn, ub_s * cn), method="bvls", max_iter=100)
                d_s = sol.x / cn
            d_x0 = np.concatenate([back(d_s) for back in backs])
            step = {"s": d_s, "X0": d_x0}
            step["V"] = np.concatenate([
                -(z[:, 0] + z[:, 1:1 + npar] @ d_s + z[:, 1 + npar:] @ d_x0[g * nx:(g + 1) * nx])
                for g, (*_, z) in enumerate(lin)])
            alpha, accepted = 1.0, False
            for _ in range(12):
                V1, X1, s1 = V + alpha * step["V"], X0 + alpha * step["X0"], np.clip(s + alpha * d_s, lo, hi)
                g1, f1 = self._merit_terms(V1, X1, s1)
                if np.isfinite(g1) and (g1 < (1 - 1e-4 * alpha) * g_norm
                                        or (g1 <= max(g_norm, 1e-8) and f1 <= f_val * (1 + 1e-9) + 1e-12)):
                    accepted = True
                    break
                alpha *= 0.5
            if not accepted:  # a bounded number of full (non-monotone) steps, then give up
                free_steps -= 1
                if free_steps < 0:
                    status = "line search failed"
                    break
                alpha = 1.0
                V1, X1, s1 = V + step["V"], X0 + step["X0"], np.clip(s + d_s, lo, hi)
                g1, f1 = self._merit_terms(V1, X1, s1)
                if not np.isfinite(g1):
                    status = "diverged"
                    break
            V, X0, s = V1, X1, s1
            small = float(np.max(np.abs(alpha * d_s))) if npar else 0.0
            if it > warm and accepted and g1 < 1e-8 and small < tol and float(np.max(np.abs(alpha * step["X0"]))) < 1e-3:
                status = "converged"
                g_norm, f_val = g1, f1
                break
        else:
            if not np.isfinite(g_norm):
                status = "diverged"
        if status != "converged":
            raise FitError(
                f"fit did not converge: Gauss-Newton status {status!r} after {it} iterations (constraint residual "
                f"{g_norm:.3g}); remedy: check the data (units, that the command drives this actuator, sample time), "
                "fit fewer parameters (--fit), start from a closer base plant (--plant) or use shorter segments"
            )
        self._final = (V, X0, s)
        out = {"V": V, "X0": X0, "s": s, "status": status, "iterations": it, "objective": f_val}
        out["fit_percent"], out["traces"] = self._fit_percent(self.thetas(V, X0))
        return out

    def _fit_percent(self, thetas):
        """Speed fit % per record from the model angles at the samples of each segment."""
        per: dict[str, tuple] = {}
        for sg, th in zip(self.segs, thetas):
            rec = self.records[sg.rec]
            v_model = np.diff(th) / np.diff(rec.time_s[sg.k0:sg.k0 + sg.n + 1])
            v_meas = rec.speed_rad_s[sg.k0:sg.k0 + sg.n]
            m, mm, tt = per.setdefault(rec.name, ([], [], []))
            m.append(v_meas)
            mm.append(v_model)
            tt.append(rec.time_s[sg.k0 + 1:sg.k0 + sg.n + 1])
        out, traces = {}, {}
        for name, (m, mm, tt) in per.items():
            a, b = np.concatenate(m), np.concatenate(mm)
            out[name] = round(fit_percent(a, b), 3)
            traces[name] = {"time_s": np.concatenate(tt), "measured": a, "model": b}
        return out, traces

    def covariance(self, sol):
        """Covariance of the scaled parameters, residual std (residual unit), residual count, columns."""
        V, X0, s = sol["V"], sol["X0"], sol["s"]
        nx, nseg, npar = self.nx, len(self.segs), self.npar
        _, lin = self.linearise(V, X0, s)
        js, r, _ = _condense(lin)
        n_rows = len(r)
        n_cols = npar + nx * nseg
        dof = max(n_rows - n_cols, 1)
        s2 = float(r @ r) / dof
        cn = np.linalg.norm(js, axis=0)
        cn[cn == 0] = 1.0
        inv = np.linalg.pinv((js / cn).T @ (js / cn), rcond=1e-12, hermitian=True) / np.outer(cn, cn)
        cov = s2 * inv
        unit_sigma = self.sigma0 if self.use_angle else self.sigma0 / self.ts
        return cov, math.sqrt(s2) * unit_sigma, n_rows, n_cols


def _condense(lin):
    """Eliminate each segment's initial state from the linearised least-squares problem.

    Returns the parameter Jacobian and residual with the initial-state directions projected
    out (their normal equations are the Schur complement for the parameters) and, per segment,
    a function giving the initial-state step for a parameter step.
    """
    js_parts, r_parts, backs = [], [], []
    for r_lin, j_s, j_x, _ in lin:
        q, rr = np.linalg.qr(j_x)
        keep = np.abs(np.diag(rr)) > 1e-12 * max(1.0, float(np.max(np.abs(rr))))
        q, rr = q[:, keep], rr[np.ix_(keep, keep)]
        js_parts.append(j_s - q @ (q.T @ j_s))
        r_parts.append(r_lin - q @ (q.T @ r_lin))

        def back(d_s, q=q, rr=rr, keep=keep, r_lin=r_lin, j_s=j_s):
            out = np.zeros(len(keep))
            out[keep] = -np.linalg.solve(rr, q.T @ (r_lin + j_s @ d_s))
            return out

        backs.append(back)
    return np.vstack(js_parts), np.concatenate(r_parts), backs
