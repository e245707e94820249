"""Parametric fits of a measured frequency response (torque command -> motor speed) whose
structure the data choose: the **rigid axis** and the **two-mass axis**, each with the
current-loop lag and a command delay.

Models (motor coordinates: torque in N m, speed in rad/s; the current loop a first-order lag
``1 / (1 + s / w_c)``, the delay ``exp(-s T)``)::

    rigid      G(s) = 1 / (J s + b)
    two-mass   G(s) = (J_l s^2 + c s + k) / ((J_m s + b)(J_l s^2 + c s + k) + J_l s (c s + k))

``J = J_m + J_l`` the total inertia at the motor, ``J_m`` the motor side (rotor, coupling, and
for a screw-driven axis the screw's rotation), ``J_l`` the load side reflected to the motor
(a translating mass ``m`` through the lead ``a = L / 2 pi``: ``m a^2``), ``k`` the torsional
equivalent of the axial stiffness (``k_axial a^2``), ``c = 2 zeta sqrt(k J_m J_l / J)`` (``zeta``
the modal damping ratio of the axial mode, the plant's ``axis.axial_damping_ratio``), ``b`` the
viscous friction on the motor side. The response has an anti-resonance (zero pair) at
``f_a = sqrt(k / J_l) / 2 pi`` and the axial mode (pole pair) at ``f_r = f_a sqrt(J / J_m)``.

The fit (:func:`fit_frf_model`) works on the complex logarithm of the response (log magnitude
in nepers and wrapped phase in radians), each point weighted by ``sqrt(gamma^2 / (1 - gamma^2))``
when a coherence ``gamma^2`` is given (the log-response variance is proportional to
``(1 - gamma^2) / gamma^2``, Bendat & Piersol). Parameters are fitted as
``ln J, ln f_a, ln (J_l / J_m), ln zeta, ln f_c, T, b`` (rigid: ``ln J, ln f_c, T, b``), so
positive quantities stay positive without bounds and their intervals are the exponentials of
symmetric intervals on the logarithms. Starting values do not depend on luck: the total inertia
from the low-frequency asymptote ``|G| -> 1 / (J w)``, the current loop and delay from a bounded
grid on the high-frequency phase and magnitude, the anti-resonance and the mode from the notch
and the peak of the response divided by the rigid fit, the damping from a bounded grid; then
Levenberg-Marquardt. 95 % intervals come from the Jacobian at the optimum and the residual
variance (delta method for derived values, Student t quantile).

Two entries are bounded (:func:`_solve_bounded`, an active set around Levenberg-Marquardt):
the delay ``T >= 0`` and the current loop ``f_c <= CURRENT_LOOP_MAX_FACTOR x`` the highest
frequency. The delay cannot be negative: the models hold the whole lag a drive's measurement
has (the current loop, and in the sampled form the command held over a sample and the speed's
backward difference), so a lead left over means the response is not what the model assumes
(a continuous-time response read as sampled at the drive's rate, a speed estimated otherwise,
a phase shifted by the analyser), not a command acting before it is given. A solve that ends
beyond a bound is solved again with that entry held at the bound; the entry is then reported
``at_bound`` with :data:`AT_BOUND_NOTE` and no interval (the others' intervals hold it there).

:func:`choose_structure` fits both and lets the data decide (:class:`StructureChoice`): the
two-mass model is needed when it explains the response significantly better (F-test of the
nested models at ``STRUCTURE_ALPHA``) and substantially better (at most ``STRUCTURE_RSS_RATIO``
of the rigid residual left), its anti-resonance and mode lie inside the measured band, the mode
is a resonance (damping at most ``STRUCTURE_ZETA_MAX``) and it changes the response by more
than ``STRUCTURE_EFFECT`` times the fit's noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np
from numpy.typing import NDArray

from ..errors import FitError

__all__ = ["physical_values", "FrfModelFit", "StructureChoice", "fit_frf_model", "choose_structure", "model_response",
           "two_mass_response", "STRUCTURES", "STRUCTURE_ALPHA", "STRUCTURE_EFFECT", "STRUCTURE_RSS_RATIO",
           "STRUCTURE_ZETA_MAX", "MAX_NFEV", "CURRENT_LOOP_MAX_FACTOR", "AT_BOUND_NOTE", "low_band_inertias",
           "RESIDUAL_REF_HZ"]

#: The parametric structures.
STRUCTURES = ("rigid", "two-mass")
#: Significance level of the F-test rigid vs two-mass (a resonance is a large effect: the
#: level only guards against noise).
STRUCTURE_ALPHA = 1e-4
#: The mode must change the response (largest |log(G_two-mass / G_rigid)| over the measured
#: band) by more than this many times the residual standard deviation of the two-mass fit.
STRUCTURE_EFFECT = 3.0
#: The two-mass model must leave at most this fraction of the rigid model's residual sum of
#: squares (a mode is a large effect: a model mismatch at the band's edge improves the fit by
#: a few per cent, a real mode by one or two orders of magnitude).
STRUCTURE_RSS_RATIO = 0.5
#: Largest damping ratio of a mode the structure test accepts (an overdamped pole pair makes no
#: resonance peak: it is a lag, not an axial mode).
STRUCTURE_ZETA_MAX = 0.3
#: Budget of model evaluations per least-squares solve (the model is a closed form: each costs
#: microseconds per point).
MAX_NFEV = 4000
#: Upper bound of a fitted current loop, as a multiple of the response's highest frequency. Above
#: it the lag changes the phase at the top frequency by under 3 deg (``arctan(1/20)``) and the
#: magnitude by 0.1 %, as a delay of ``1 / (2 pi f_c)`` does: the data cannot tell the current loop
#: from the delay, and an unbounded fit runs off to 1e8 Hz with a zero-width interval.
CURRENT_LOOP_MAX_FACTOR = 20.0
#: How a value held at a bound of the fit is reported (its ``note``; its ``ci95`` is None).
AT_BOUND_NOTE = "at its bound: not identified by these data"

_Z95 = 1.959963984540054
_TWO_PI = 2.0 * math.pi

#: Parameter names of each structure (the fitted vector).
_THETA = {
    "rigid": ("ln_total_inertia", "ln_current_loop_hz", "delay_s", "viscous_scaled"),
    "two-mass": ("ln_total_inertia", "ln_antiresonance_hz", "ln_inertia_ratio", "ln_damping_ratio",
                 "ln_current_loop_hz", "delay_s", "viscous_scaled"),
}

#: The upper residual's fitted entry ``x`` (module docstring, :func:`fit_frf_model` with
#: ``upper_residual``): ``R = x / (J (2 pi RESIDUAL_REF_HZ)^2)``, the share of the inertia's
#: response that the modes above the band add at this frequency (Hz); its scale only.
RESIDUAL_REF_HZ = 1000.0
#: Starts of the upper residual's scaled entry (each solved, the best optimum kept): none, and the
#: tails the modes of a coupling or a motor mount leave below them (measured on gen_third's
#: responses cut between their two modes: 0.1..1).
RESIDUAL_STARTS = (0.0, 0.3, 1.0, 3.0)

#: Reported values: name -> unit.
UNITS = {
    "total_inertia_kg_m2": "kg m^2",
    "motor_inertia_kg_m2": "kg m^2",
    "load_inertia_kg_m2": "kg m^2",
    "stiffness_n_m_per_rad": "N m/rad",
    "damping_n_m_s_per_rad": "N m s/rad",
    "damping_ratio": "-",
    "antiresonance_hz": "Hz",
    "resonance_hz": "Hz",
    "current_loop_bandwidth_hz": "Hz",
    "delay_s": "s",
    "viscous_n_m_s_per_rad": "N m s/rad",
    "upper_residual_rad_per_n_m": "rad/(N m)",
}


def _names(structure: str, residual: bool) -> tuple:
    """The fitted vector's entries (:data:`_THETA`, the upper residual's last when fitted)."""
    return _THETA[structure] + (("residual_scaled",) if residual else ())


def two_mass_response(frequency_hz, *, motor_inertia_kg_m2: float, load_inertia_kg_m2: float = 0.0,
                      stiffness_n_m_per_rad: float = math.inf, damping_n_m_s_per_rad: float = 0.0,
                      viscous_n_m_s_per_rad: float = 0.0, current_loop_bandwidth_hz: float = math.inf,
                      delay_s: float = 0.0, sample_time_s: float = 0.0,
                      upper_residual_rad_per_n_m: float = 0.0) -> NDArray[np.complex128]:
    """Frequency response torque command (N m) -> motor speed (rad/s) of a two-mass axis.

    Parameters
    ----------
    frequency_hz : array, Hz
    motor_inertia_kg_m2 : float, kg m^2
        Motor side ``J_m`` (the whole inertia when ``load_inertia_kg_m2`` is 0 or the
        stiffness infinite: the rigid axis).
    load_inertia_kg_m2 : float, kg m^2
        Load side reflected to the motor ``J_l``.
    stiffness_n_m_per_rad : float, N m/rad
        Torsional stiffness between them (``inf``: rigid, ``J_m + J_l`` as one inertia).
    damping_n_m_s_per_rad : float, N m s/rad
        Damper in parallel with the spring.
    viscous_n_m_s_per_rad : float, N m s/rad
        Viscous friction on the motor side.
    current_loop_bandwidth_hz : float, Hz
        First-order current loop (``inf``: none).
    delay_s : float, s
        Command delay.
    sample_time_s : float, s
        0: the continuous response; > 0: as a drive measures it, command held over a sample
        and speed the backward difference of the sampled angle (the delay then multiplies it
        as ``exp(-s T)``).
    upper_residual_rad_per_n_m : float, rad/(N m)
        The compliance ``R`` of modes above the measured band (their "upper residual": below its
        frequency a mode ``r s / (s^2 + w^2)`` of the collocated response is ``(r / w^2) s``):
        the motor angle gains ``R`` times the torque, the response ``R s`` ahead of the current
        loop and the delay (0: none).

    Returns
    -------
    ndarray of complex, (rad/s)/(N m)

    Examples
    --------
    >>> g = two_mass_response([1.0], motor_inertia_kg_m2=1e-3)
    >>> round(float(abs(g[0])) * 2 * math.pi * 1e-3, 6)  # 1 / (J w)
    1.0
    """
    f = np.asarray(frequency_hz, float)
    jm, jl, k, c = float(motor_inertia_kg_m2), float(load_inertia_kg_m2), float(stiffness_n_m_per_rad), \
        float(damping_n_m_s_per_rad)
    b, fc, td, ts = float(viscous_n_m_s_per_rad), float(current_loop_bandwidth_hz), float(delay_s), float(sample_time_s)
    rigid = jl == 0.0 or math.isinf(k)
    res = float(upper_residual_rad_per_n_m)
    if rigid:
        jm = jm + jl
    s = 1j * _TWO_PI * f
    if ts <= 0:
        if rigid:
            g = 1.0 / (jm * s + b)
        else:
            n = jl * s * s + c * s + k
            g = n / ((jm * s + b) * n + jl * s * (c * s + k))
        if res:
            g = g + res * s
        if math.isfinite(fc):
            g = g / (1.0 + s / (_TWO_PI * fc))
    else:
        from ..drive.sampled import zoh

        wc = _TWO_PI * fc if math.isfinite(fc) else None
        # states: [theta_m, omega_m, (theta_l, omega_l,) tau]
        if rigid:
            a = np.array([[0.0, 1.0, 0.0], [0.0, -b / jm, 1.0 / jm], [0.0, 0.0, 0.0]])
        else:
            a = np.array([[0.0, 1.0, 0.0, 0.0, 0.0],
                          [-k / jm, -(b + c) / jm, k / jm, c / jm, 1.0 / jm],
                          [0.0, 0.0, 0.0, 1.0, 0.0],
                          [k / jl, c / jl, -k / jl, -c / jl, 0.0],
                          [0.0, 0.0, 0.0, 0.0, 0.0]])
        bb = np.zeros((a.shape[0], 1))
        if wc is None:  # no current loop: the torque is the command (a fast lag of 1e-9 s stands in)
            wc = 1e9
        a[-1, -1] = -wc
        bb[-1, 0] = wc
        phi, gam = zoh(a, bb, ts)
        z = np.exp(s * ts)
        nx = a.shape[0]
        rhs = np.broadcast_to(gam[:, :1].astype(complex), (len(z), nx, 1))
        x = np.linalg.solve(z[:, None, None] * np.eye(nx)[None] - phi[None], rhs)[:, :, 0]
        th = x[:, 0] + res * x[:, -1] if res else x[:, 0]  # (the angle gains R times the torque state)
        g = (1.0 - 1.0 / z) / ts * th
    if td:
        g = g * np.exp(-s * td)
    return g


def _exp(x: float) -> float:
    """``exp`` clipped to the float range (a diverging solve meets a large residual, not an
    OverflowError)."""
    return math.exp(min(max(float(x), -700.0), 700.0))


def physical_values(structure: str, theta: NDArray[np.float64], b_scale: float) -> dict:
    """The physical values of a fitted vector ``theta`` (SI; see the module docstring;
    ``b_scale``: N m s/rad per unit of its scaled viscous entry, :attr:`FrfModelFit.b_scale`; one
    entry more than :data:`_THETA` holds: the upper residual's, :data:`RESIDUAL_REF_HZ`)."""
    if len(theta) == len(_THETA[structure]) + 1:
        out = physical_values(structure, theta[:-1], b_scale)
        out["upper_residual_rad_per_n_m"] = float(theta[-1]) / (out["total_inertia_kg_m2"]
                                                                 * (_TWO_PI * RESIDUAL_REF_HZ) ** 2)
        return out
    exp = _exp
    if structure == "rigid":
        j, lfc, td, bs = theta
        j = exp(j)
        return {"total_inertia_kg_m2": j, "motor_inertia_kg_m2": j, "current_loop_bandwidth_hz": exp(lfc),
                "delay_s": float(td), "viscous_n_m_s_per_rad": float(bs) * b_scale}
    lj, lfa, lr, lz, lfc, td, bs = theta
    j, fa, r, zeta = exp(lj), exp(lfa), exp(lr), exp(lz)
    jm = j / (1.0 + r)
    jl = j - jm
    wa = _TWO_PI * fa
    k = jl * wa * wa
    c = 2.0 * zeta * math.sqrt(max(k * jm * jl / j, 0.0))
    return {"total_inertia_kg_m2": j, "motor_inertia_kg_m2": jm, "load_inertia_kg_m2": jl,
            "stiffness_n_m_per_rad": k, "damping_n_m_s_per_rad": c, "damping_ratio": zeta,
            "antiresonance_hz": fa, "resonance_hz": fa * math.sqrt(1.0 + r),
            "current_loop_bandwidth_hz": exp(lfc), "delay_s": float(td),
            "viscous_n_m_s_per_rad": float(bs) * b_scale}


def model_response(structure: str, values: Mapping[str, float], frequency_hz, sample_time_s: float = 0.0):
    """The response of a fitted model (``values`` as :attr:`FrfModelFit.values` holds them,
    plain numbers or ``{"value": ...}``), (rad/s)/(N m)."""
    v = {k: (x["value"] if isinstance(x, Mapping) else x) for k, x in values.items()}
    common = dict(viscous_n_m_s_per_rad=v["viscous_n_m_s_per_rad"],
                  current_loop_bandwidth_hz=v["current_loop_bandwidth_hz"], delay_s=v["delay_s"],
                  sample_time_s=sample_time_s, upper_residual_rad_per_n_m=v.get("upper_residual_rad_per_n_m", 0.0))
    if structure == "rigid":
        return two_mass_response(frequency_hz, motor_inertia_kg_m2=v["total_inertia_kg_m2"], **common)
    return two_mass_response(frequency_hz, motor_inertia_kg_m2=v["motor_inertia_kg_m2"],
                             load_inertia_kg_m2=v["load_inertia_kg_m2"], stiffness_n_m_per_rad=v["stiffness_n_m_per_rad"],
                             damping_n_m_s_per_rad=v["damping_n_m_s_per_rad"], **common)


@dataclass(frozen=True, eq=False)
class FrfModelFit:
    """A parametric model fitted to a frequency response (:func:`fit_frf_model`).

    Attributes
    ----------
    structure : {"rigid", "two-mass"}
    values : dict
        ``{name: {"value": v, "ci95": [lo, hi], "unit": u}}`` (SI; :data:`UNITS`): total,
        motor-side and load-side inertia, stiffness and damping (two-mass), damping ratio,
        anti-resonance and mode (Hz), current-loop bandwidth, delay, viscous friction.
    theta, covariance : ndarray
        The fitted vector (module docstring) and its covariance.
    residual_std : float
        Standard deviation of the weighted log-response residual (nepers/radians).
    rss : float
        Weighted residual sum of squares.
    n_residuals : int
    fit_percent : float
        ``100 (1 - ||log G - log G_model|| / ||log G - mean log G||)`` (unweighted, complex log).
    nfev : int
    sample_time_s : float
        0 for the continuous model, else the sampled one's sample time.
    warnings : list of str
    held : tuple of str
        Values held, not fitted: given by the caller (``"fixed": True``) or ended at a bound
        (``"at_bound"``, :data:`AT_BOUND_NOTE`); their ``ci95`` is None.
    """

    structure: str
    values: dict
    theta: NDArray[np.float64]
    covariance: NDArray[np.float64]
    residual_std: float
    rss: float
    n_residuals: int
    fit_percent: float
    nfev: int
    sample_time_s: float
    b_scale: float
    warnings: list = field(default_factory=list)
    held: tuple = ()

    def response(self, frequency_hz) -> NDArray[np.complex128]:
        """The fitted model's response at ``frequency_hz`` (Hz), (rad/s)/(N m)."""
        return model_response(self.structure, self.values, frequency_hz, self.sample_time_s)

    def value(self, name: str) -> float:
        return float(self.values[name]["value"])

    def as_dict(self) -> dict:
        """JSON-ready summary."""
        return {"structure": self.structure, "values": self.values, "residual_std": self.residual_std,
                "n_residuals": self.n_residuals, "fit_percent": self.fit_percent, "evaluations": self.nfev,
                "sample_time_s": self.sample_time_s, "held": list(self.held), "warnings": list(self.warnings)}

    report = as_dict  # its former name


def _arrays(frf) -> tuple:
    """Frequencies, responses and weights of one or more FRF records (or ``(f, g[, coherence])``)."""
    recs = frf if isinstance(frf, (list, tuple)) and frf and hasattr(frf[0], "frequency_hz") else [frf]
    fs, gs, ws = [], [], []
    for r in recs:
        if hasattr(r, "frequency_hz"):
            f, g, coh = r.frequency_hz, r.response, r.coherence
        else:
            f, g, coh = r[0], r[1], (r[2] if len(r) > 2 else None)
        f, g = np.asarray(f, float), np.asarray(g, complex)
        if f.ndim != 1 or f.shape != g.shape or len(f) == 0:
            raise ValueError(f"frequency response of {len(f)} frequencies and {np.size(g)} values; expected two "
                             "1-D arrays of the same length > 0")
        if not (np.all(np.isfinite(f)) and np.all(f > 0) and np.all(np.isfinite(g)) and np.all(g != 0)):
            raise ValueError("frequency response with a non-finite or non-positive frequency or a zero/non-finite "
                             "value; expected frequencies > 0 Hz and finite, non-zero responses")
        if coh is None:
            w = np.ones(len(f))
        else:
            c = np.clip(np.asarray(coh, float), 1e-6, 0.999)
            w = np.sqrt(c / (1.0 - c))
        fs.append(f)
        gs.append(g)
        ws.append(w)
    f, g, w = np.concatenate(fs), np.concatenate(gs), np.concatenate(ws)
    return f, g, w / np.max(w)


def low_band_inertias(frequency_hz: NDArray[np.float64], response: NDArray[np.complex128]) -> NDArray[np.float64]:
    """The apparent inertia ``1 / (w |G|)`` (kg m^2; load coordinates: kg) over the lowest quarter
    of a response's points (at least 3), ``frequency_hz`` sorted ascending: the low-frequency
    asymptote ``|G| -> 1 / (J w)`` of both the rigid and the two-mass axis, whose median is the
    start of the FRF fits and the units check's inertia
    (:func:`prsa_ctrl.identification.frfcheck.low_frequency_inertia`)."""
    f, g = np.asarray(frequency_hz, float), np.asarray(response, complex)
    n = max(3, len(f) // 4)
    return 1.0 / (_TWO_PI * f[:n] * np.abs(g[:n]))


def _log_resid(gm: NDArray[np.complex128], g: NDArray[np.complex128], w: NDArray[np.float64]) -> NDArray[np.float64]:
    d = np.log(gm) - np.log(g)
    return np.concatenate([w * d.real, w * np.angle(np.exp(1j * d.imag))])


def _median_filter(x: NDArray[np.float64], k: int = 5) -> NDArray[np.float64]:
    h = k // 2
    xp = np.pad(x, h, mode="edge")
    return np.median(np.lib.stride_tricks.sliding_window_view(xp, k), axis=1)


def _lag_delay_start(f, g_rel, w, f_cl_grid) -> tuple[float, float, float]:
    """Current-loop bandwidth and delay from ``g_rel`` (the response over the mechanical start
    model): a bounded grid of bandwidths, for each the delay of least squares on the remaining
    phase (clipped at 0). Returns ``(f_c, T, cost)`` of the best."""
    om = _TWO_PI * f
    ph = np.unwrap(np.angle(g_rel))
    # the mechanical start model is rough at low frequencies: its phase offset is removed there
    lm = np.log(np.abs(g_rel))
    best = None
    for fc in f_cl_grid:
        lag_ph = -np.arctan(f / fc)
        lag_m = -0.5 * np.log1p((f / fc) ** 2)
        rest = ph - lag_ph
        # unwrap ambiguity: shift the whole phase by multiples of 2 pi to start near 0
        rest = rest - _TWO_PI * np.round(np.median(rest[: max(3, len(rest) // 10)]) / _TWO_PI)
        td = max(float(np.sum(w**2 * om * -rest) / np.sum(w**2 * om * om)), 0.0)
        mres = lm - lag_m
        mres = mres - np.average(mres, weights=w**2)
        cost = float(np.sum(w**2 * (rest + om * td) ** 2) + np.sum(w**2 * mres**2))
        if best is None or cost < best[2]:
            best = (float(fc), td, cost)
    return best


def _solve(structure, theta0, f, g, w, ts, b_scale, max_nfev, fixed=()):
    """Levenberg-Marquardt on the entries of ``theta0`` not in ``fixed`` (indices held at their
    start). Returns ``(sol, resid, free)``: ``sol.x`` the full vector, ``resid`` of the full
    vector, ``free`` the fitted indices."""
    from scipy.optimize import least_squares

    theta0 = np.asarray(theta0, float)
    free = np.array([i for i in range(len(theta0)) if i not in set(fixed)], int)

    def resid(th):
        v = physical_values(structure, th, b_scale)
        with np.errstate(all="ignore"):
            gm = model_response(structure, v, f, ts)
        if not np.all(np.isfinite(gm)) or np.any(gm == 0):
            return np.full(2 * len(f), 1e3)
        return _log_resid(gm, g, w)

    def resid_free(x):
        th = theta0.copy()
        th[free] = x
        return resid(th)

    sol = least_squares(resid_free, theta0[free], method="lm", x_scale="jac", max_nfev=max_nfev, xtol=1e-12,
                        ftol=1e-12)
    full = theta0.copy()
    full[free] = sol.x
    sol.x = full
    return sol, resid, free


def _solve_bounded(structure, theta0, f, g, w, ts, b_scale, max_nfev, fixed=()):
    """:func:`_solve` with the delay bounded below by 0 and the current loop above by
    :data:`CURRENT_LOOP_MAX_FACTOR` times the highest frequency (module docstring): a solve that
    ends beyond a bound is solved again from its end with that entry held at the bound; a held
    entry whose cost falls when it moves off the bound into the feasible side is released
    (first-order check). At most four solves. Returns ``(sol, resid, free, at_bound)``,
    ``at_bound``: ``{index: ("lower" | "upper", unbounded value)}`` (``sol.nfev`` the total)."""
    names = _names(structure, len(theta0) > len(_THETA[structure]))
    i_fc, i_td = names.index("ln_current_loop_hz"), names.index("delay_s")
    bound = {i_td: ("lower", 0.0), i_fc: ("upper", math.log(CURRENT_LOOP_MAX_FACTOR * float(np.max(f))))}
    if "residual_scaled" in names:  # an upper residual is a compliance: >= 0
        bound[names.index("residual_scaled")] = ("lower", 0.0)
    held = set(fixed)
    th = np.asarray(theta0, float).copy()
    for i, (side, b) in bound.items():
        if i not in held:
            th[i] = max(th[i], b) if side == "lower" else min(th[i], b)
    at: dict = {}
    nfev = 0
    for _ in range(4):
        sol, resid, free = _solve(structure, th, f, g, w, ts, b_scale, max_nfev, tuple(held))
        nfev += int(sol.nfev)
        x = np.asarray(sol.x, float)
        beyond = {i: (side, b) for i, (side, b) in bound.items()
                  if i not in held and (x[i] < b if side == "lower" else x[i] > b)}
        released = []
        for i in list(at):  # first-order check: does the cost fall off the bound, on the feasible side?
            side, b = bound[i]
            step = 1e-6 * max(abs(b), 1.0) * (1.0 if side == "lower" else -1.0)
            xp = x.copy()
            xp[i] += step
            r0, r1 = resid(x), resid(xp)
            if float(r1 @ r1) < float(r0 @ r0) * (1.0 - 1e-12):
                released.append(i)
        if not beyond and not released:
            break
        th = x.copy()
        for i, (side, b) in beyond.items():
            th[i] = b
            held.add(i)
            at[i] = (side, float(x[i]))
        for i in released:
            held.discard(i)
            at.pop(i)
    else:
        raise FitError(f"{structure} FRF fit: the bounds of the delay and the current loop did not settle in four "
                       "solves; remedy: check the response's units ((rad/s)/(N m)) and its phase")
    sol.nfev = nfev
    return sol, resid, free, at


def _jacobian(resid, theta: NDArray[np.float64]) -> NDArray[np.float64]:
    """Central-difference Jacobian of the residual (steps relative to each entry's scale)."""
    cols = []
    for i in range(len(theta)):
        h = 1e-6 * max(abs(theta[i]), 1.0)
        tp, tm = theta.copy(), theta.copy()
        tp[i] += h
        tm[i] -= h
        cols.append((resid(tp) - resid(tm)) / (2 * h))
    return np.stack(cols, axis=1)


def _fit_percent(g, gm) -> float:
    """Fit % on the complex log response, NaN for a response that does not vary (the rule of
    :func:`prsa_ctrl.identification.frf.frf_fit_percent`, repeated here without its CasADi import)."""
    lm, lg = np.log(g), np.log(gm)
    d = np.angle(np.exp(1j * (lm.imag - lg.imag)))
    err = np.sqrt(np.sum((lm.real - lg.real) ** 2 + d**2))
    ph = np.unwrap(lm.imag)
    ref = np.sqrt(np.sum((lm.real - lm.real.mean()) ** 2 + (ph - ph.mean()) ** 2))
    return float(100.0 * (1.0 - err / ref)) if ref > 1e-6 * math.sqrt(len(lm)) else float("nan")


def _finish(structure, sol, resid, f, g, w, ts, b_scale, free=None, at_bound=None) -> FrfModelFit:
    from scipy.stats import t as student_t

    theta = np.asarray(sol.x, float)
    free = np.arange(len(theta)) if free is None else np.asarray(free, int)
    r = resid(theta)
    if not np.all(np.isfinite(r)):
        raise FitError(f"{structure} FRF fit ended on a non-finite residual; remedy: check the response's units "
                       "((rad/s)/(N m)) and that it is torque command -> motor speed")

    def resid_free(x):
        th = theta.copy()
        th[free] = x
        return resid(th)

    jac = _jacobian(resid_free, theta[free])
    n, npar = len(r), len(theta)
    dof = max(n - len(free), 1)
    rss = float(r @ r)
    s2 = rss / dof
    cov = np.zeros((npar, npar))
    try:
        cov[np.ix_(free, free)] = s2 * np.linalg.pinv(jac.T @ jac, rcond=1e-13)
    except np.linalg.LinAlgError as exc:
        raise FitError(f"{structure} FRF fit: the Jacobian at the optimum has no inverse ({exc})") from exc
    q = float(student_t.ppf(0.975, dof))
    vals = physical_values(structure, theta, b_scale)
    out = {}
    warns = []
    for name, v in vals.items():
        # gradient of the value (of its logarithm for positive values) w.r.t. theta
        positive = name not in ("delay_s", "viscous_n_m_s_per_rad", "upper_residual_rad_per_n_m")
        grad = np.zeros(npar)
        for i in range(npar):
            h = 1e-6 * max(abs(theta[i]), 1.0)
            tp, tm = theta.copy(), theta.copy()
            tp[i] += h
            tm[i] -= h
            vp, vm = physical_values(structure, tp, b_scale)[name], physical_values(structure, tm, b_scale)[name]
            grad[i] = ((math.log(vp) - math.log(vm)) if positive else (vp - vm)) / (2 * h)
        sd = float(math.sqrt(max(grad @ cov @ grad, 0.0)))
        if positive:
            ci = [v * _exp(-q * sd), v * _exp(q * sd)]  # (clipped: a value the data barely inform)
        else:
            ci = [v - q * sd, v + q * sd]
        out[name] = {"value": float(v), "ci95": [float(ci[0]), float(ci[1])], "unit": UNITS[name]}
    with np.errstate(all="ignore"):
        gm = model_response(structure, vals, f, ts)
    fmax = float(np.max(f))
    names = _names(structure, len(theta) > len(_THETA[structure]))
    at_bound = dict(at_bound or {})
    held_names = []
    for i in range(npar):
        if i in free:
            continue
        name = {"ln_current_loop_hz": "current_loop_bandwidth_hz", "delay_s": "delay_s",
                "residual_scaled": "upper_residual_rad_per_n_m"}[names[i]]
        held_names.append(name)
        e = out[name]
        e["ci95"] = None  # held: no interval (a zero-width one would pretend a precision the data do not give)
        if i in at_bound:
            side, x_free = at_bound[i]
            e["at_bound"] = side
            e["note"] = AT_BOUND_NOTE
            if name == "upper_residual_rad_per_n_m":
                e["unbounded_value"] = float(x_free)  # (scaled: no compliance of modes above the band shows)
            elif name == "delay_s":
                e["unbounded_value"] = float(x_free)
                warns.append(f"delay_s = 0 s, {AT_BOUND_NOTE} (the unbounded fit wanted {x_free:.4g} s, a lead: the "
                             "response lags its command less than the model's current loop"
                             + (f" and one sample of {ts:g} s (command held, speed differenced)" if ts > 0 else "")
                             + " do; a continuous-time response read as sampled at the drive's rate, or a speed not "
                             "the backward difference of the sampled angle, does that: give its own sample time, 0 for a "
                             "continuous one, prsa-fit --frf-sample-time); the other intervals hold it at 0")
            else:
                e["unbounded_value"] = _exp(x_free)
                warns.append(f"current_loop_bandwidth_hz = {e['value']:.4g} Hz, {AT_BOUND_NOTE} (the unbounded fit "
                             f"ran to {_exp(x_free):.4g} Hz; the bound is {CURRENT_LOOP_MAX_FACTOR:g} x the highest "
                             f"frequency {fmax:.4g} Hz, above which its lag is a delay's): measure up to the "
                             "current-loop bandwidth or hold it (the other intervals hold it there)")
        else:
            e["fixed"] = True
            e["note"] = "held, not fitted"
    fc = out["current_loop_bandwidth_hz"]
    if "current_loop_bandwidth_hz" not in held_names and (fc["value"] > 5.0 * fmax or fc["ci95"][1] > 20.0 * fc["value"]):
        warns.append(f"current_loop_bandwidth_hz = {fc['value']:.4g} Hz is not identified by a response that ends at "
                     f"{fmax:.4g} Hz (95 % CI {fc['ci95'][0]:.4g}..{fc['ci95'][1]:.4g} Hz): measure up to the "
                     "current-loop bandwidth")
    return FrfModelFit(structure, out, theta, cov, float(math.sqrt(s2)), rss, n, _fit_percent(g, gm),
                       int(sol.nfev), float(ts), float(b_scale), warns, tuple(held_names))


def fit_frf_model(frf, structure: str = "two-mass", *, sample_time_s: float = 0.0,
                  current_loop_bandwidth_hz: float | None = None, max_nfev: int = MAX_NFEV,
                  _rigid: FrfModelFit | None = None, upper_residual: bool = False) -> FrfModelFit:
    """Fit the rigid or the two-mass model to a frequency response (module docstring).

    Parameters
    ----------
    frf : FrfRecord, sequence of FrfRecord, or ``(frequency_hz, response[, coherence])``
        Torque command (N m) -> motor speed (rad/s); several records are fitted jointly.
    structure : {"rigid", "two-mass"}
    sample_time_s : float, s
        0 (default): the continuous model; > 0: the drive's sampled response
        (:func:`two_mass_response`).
    current_loop_bandwidth_hz : float, Hz, optional
        Hold the current loop at this value instead of fitting it (a response that ends far
        below the current loop cannot tell it from the delay).
    max_nfev : int
        Budget of model evaluations of the least-squares solve.
    upper_residual : bool
        Also fit the compliance ``R >= 0`` of modes above the measured band
        (:func:`two_mass_response`'s ``upper_residual_rad_per_n_m``, the value
        ``upper_residual_rad_per_n_m``): a response cut below a mode the model lacks keeps that
        mode's tail ``R s``, which the current loop and the inertia would otherwise take up.
        Its starts :data:`RESIDUAL_STARTS` (with the damping grid's, two-mass) ranked by their
        residual, the best two solved and the better optimum kept.

    Returns
    -------
    FrfModelFit

    Raises
    ------
    ValueError
        An unknown structure, fewer points than twice the parameters, or unusable arrays.
    FitError
        The least-squares solve did not converge.
    """
    if structure not in STRUCTURES:
        raise ValueError(f"structure = {structure!r}; expected one of {', '.join(STRUCTURES)}")
    if not (isinstance(max_nfev, int) and 10 <= max_nfev <= 10**6):
        raise ValueError(f"max_nfev = {max_nfev!r}; expected an integer 10..1e6")
    if not (math.isfinite(sample_time_s) and sample_time_s >= 0):
        raise ValueError(f"sample_time_s = {sample_time_s!r}; expected a finite number >= 0 s")
    fixed_fc = current_loop_bandwidth_hz
    if fixed_fc is not None and not (math.isfinite(fixed_fc) and fixed_fc > 0):
        raise ValueError(f"current_loop_bandwidth_hz = {fixed_fc!r}; expected a finite number > 0 Hz or None")
    f, g, w = _arrays(frf)
    order = np.argsort(f)
    f, g, w = f[order], g[order], w[order]
    npar = len(_names(structure, upper_residual))
    if len(f) < 2 * npar:
        raise ValueError(f"{len(f)} frequency points for the {structure} model; expected at least {2 * npar}")
    om = _TWO_PI * f
    appar = 1.0 / (om * np.abs(g))  # apparent inertia: J at low frequency for both structures
    j0 = float(np.median(low_band_inertias(f, g)))
    b_scale = j0 * float(om[0])
    fmax = float(f[-1])
    fc_grid = np.geomspace(0.05 * fmax, 20.0 * fmax, 31)
    if structure == "rigid":
        g_rel = g * (1j * om * j0)
        fc, td, _ = _lag_delay_start(f, g_rel, w, fc_grid if fixed_fc is None else [fixed_fc])
        starts = [np.array([math.log(j0), math.log(fc), td, 0.0] + ([] if x_r is None else [x_r]))
                  for x_r in (RESIDUAL_STARTS if upper_residual else (None,))]
        if len(starts) > 1:  # the two best starts of the residual, each solved: the better optimum is kept
            _, resid_start, _ = _solve("rigid", starts[0], f, g, w, sample_time_s, b_scale, 1)
            starts = sorted(starts, key=lambda th: float(resid_start(th) @ resid_start(th)))[:2]
        best = None
        for theta0 in starts:
            got = _solve_bounded("rigid", theta0, f, g, w, sample_time_s, b_scale, max_nfev,
                                 () if fixed_fc is None else (1,))
            if best is None or (np.all(np.isfinite(got[0].fun)) and got[0].cost < best[0].cost):
                best = got
        sol, resid, free, at = best
        if not sol.success:
            raise FitError(f"rigid FRF fit did not converge: least-squares status {sol.status} ({sol.message}) after "
                           f"{sol.nfev} evaluations; remedy: check the response's units ((rad/s)/(N m))")
        return _finish("rigid", sol, resid, f, g, w, sample_time_s, b_scale, free, at)
    rig = _rigid if _rigid is not None else fit_frf_model(frf, "rigid", sample_time_s=sample_time_s, max_nfev=max_nfev,
                                                          current_loop_bandwidth_hz=fixed_fc, upper_residual=upper_residual)
    # the mode shows as a notch (anti-resonance) then a peak (resonance) of the response over the rigid fit
    q = np.log(np.abs(g / rig.response(f)))
    qs = _median_filter(q, 5) if len(q) >= 5 else q
    inner = slice(1, len(f) - 1) if len(f) > 4 else slice(0, len(f))
    idx = np.arange(len(f))[inner]
    i_a = int(idx[np.argmin(qs[inner])])
    after = idx[idx > i_a]
    i_r = int(after[np.argmax(qs[after])]) if len(after) else min(i_a + 1, len(f) - 1)
    fa0 = float(f[i_a])
    fr0 = float(f[i_r]) if f[i_r] > fa0 * 1.001 else fa0 * 1.2
    r0 = float(np.clip((fr0 / fa0) ** 2 - 1.0, 1e-3, 1e3))
    low = f < 0.5 * fa0
    jt0 = float(np.median(appar[low])) if np.count_nonzero(low) >= 3 else rig.value("total_inertia_kg_m2")
    b0 = 0.0
    jm0 = jt0 / (1.0 + r0)
    jl0 = jt0 - jm0
    k0 = jl0 * (_TWO_PI * fa0) ** 2
    starts = []
    resid_start = None
    for zeta in (0.003, 0.01, 0.03, 0.1, 0.3):  # bounded grid of the damping at the picked notch and peak
        # the current loop and the delay of this start: the grid on the response over its mechanical part
        c0 = 2.0 * zeta * math.sqrt(k0 * jm0 * jl0 / jt0)
        with np.errstate(all="ignore"):
            g_mech = two_mass_response(f, motor_inertia_kg_m2=jm0, load_inertia_kg_m2=jl0, stiffness_n_m_per_rad=k0,
                                       damping_n_m_s_per_rad=c0, sample_time_s=sample_time_s)
        away = (f < 0.7 * fa0) | (f > 1.4 * fa0 * math.sqrt(1.0 + r0))  # off the mode: its start is rough there
        if np.count_nonzero(away) < 4:
            away = np.ones(len(f), bool)
        fc0, td0, _ = _lag_delay_start(f[away], (g / g_mech)[away], w[away],
                                       fc_grid if fixed_fc is None else [fixed_fc])
        th = np.array([math.log(jt0), math.log(fa0), math.log(r0), math.log(zeta), math.log(fc0), td0, b0])
        if resid_start is None:
            _, resid_start, _ = _solve("two-mass", th, f, g, w, sample_time_s, b_scale, 1)
        for x_r in (RESIDUAL_STARTS if upper_residual else (None,)):
            th_r = th if x_r is None else np.append(th, x_r)
            r = resid_start(th_r)
            starts.append((float(r @ r), th_r))
    starts.sort(key=lambda t: t[0])
    best = None
    for _, th in starts[:2]:  # the two best grid points, each solved: the better optimum is kept
        sol, resid, free, at = _solve_bounded("two-mass", th, f, g, w, sample_time_s, b_scale, max_nfev,
                                              () if fixed_fc is None else (4,))
        if np.all(np.isfinite(sol.fun)) and (best is None or sol.cost < best[0].cost):
            best = (sol, resid, free, at)
    sol, resid, free, at = best
    if not sol.success:
        raise FitError(f"two-mass FRF fit did not converge: least-squares status {sol.status} ({sol.message}) after "
                       f"{sol.nfev} evaluations; remedy: check the response's units ((rad/s)/(N m))")
    return _finish("two-mass", sol, resid, f, g, w, sample_time_s, b_scale, free, at)


@dataclass(frozen=True, eq=False)
class StructureChoice:
    """Which structure the response needs (:func:`choose_structure`).

    Attributes
    ----------
    structure : {"rigid", "two-mass"}
        The one chosen.
    rigid, two_mass : FrfModelFit
        Both fits (``two_mass`` None when it failed; ``reason`` says why).
    f_statistic, p_value : float
        F-test of the nested models (two-mass has 3 more parameters).
    effect : float
        Largest ``|log(G_two-mass / G_rigid)|`` over the measured band over the two-mass fit's
        residual standard deviation.
    in_band : bool
        Anti-resonance and mode of the two-mass fit inside the measured band.
    reason : str
        One sentence saying why (with the numbers).
    """

    structure: str
    rigid: FrfModelFit
    two_mass: FrfModelFit | None
    f_statistic: float
    p_value: float
    effect: float
    in_band: bool
    reason: str

    @property
    def chosen(self) -> FrfModelFit:
        return self.two_mass if self.structure == "two-mass" else self.rigid

    def as_dict(self) -> dict:
        """JSON-ready choice: the structure, why, the F-test and both fits."""
        return {"structure": self.structure, "reason": self.reason, "f_statistic": self.f_statistic,
                "p_value": self.p_value, "effect_over_noise": self.effect, "in_band": self.in_band,
                "rigid": self.rigid.as_dict(), "two_mass": None if self.two_mass is None else self.two_mass.as_dict()}

    report = as_dict  # its former name


def choose_structure(frf, *, sample_time_s: float = 0.0, current_loop_bandwidth_hz: float | None = None,
                     max_nfev: int = MAX_NFEV, upper_residual: bool = False) -> StructureChoice:
    """Fit the rigid and the two-mass model and let the data choose (module docstring).

    Parameters
    ----------
    frf : FrfRecord, sequence of FrfRecord, or ``(frequency_hz, response[, coherence])``
    sample_time_s : float, s
        See :func:`fit_frf_model`.
    current_loop_bandwidth_hz : float, Hz, optional
        Held, not fitted (:func:`fit_frf_model`).
    max_nfev : int
    upper_residual : bool
        Both models with the upper residual of modes above the band (:func:`fit_frf_model`).

    Returns
    -------
    StructureChoice
    """
    from scipy.stats import f as f_dist

    rig = fit_frf_model(frf, "rigid", sample_time_s=sample_time_s, max_nfev=max_nfev,
                        current_loop_bandwidth_hz=current_loop_bandwidth_hz, upper_residual=upper_residual)
    f, g, _ = _arrays(frf)
    try:
        two = fit_frf_model(frf, "two-mass", sample_time_s=sample_time_s, max_nfev=max_nfev, _rigid=rig,
                            current_loop_bandwidth_hz=current_loop_bandwidth_hz, upper_residual=upper_residual)
    except FitError as exc:
        return StructureChoice("rigid", rig, None, float("nan"), float("nan"), 0.0, False,
                               f"the two-mass fit failed ({exc})")
    n = rig.n_residuals
    extra = 3  # anti-resonance, inertia ratio, damping
    dof = max(n - len(two.theta) + len(two.held), 1)
    f_stat = max((rig.rss - two.rss) / extra, 0.0) / max(two.rss / dof, 1e-300)
    p = float(f_dist.sf(f_stat, extra, dof))
    fa, fr = two.value("antiresonance_hz"), two.value("resonance_hz")
    in_band = bool(np.min(f) < min(fa, fr) and max(fa, fr) < np.max(f))
    fs = np.sort(f)
    dense = np.unique(np.concatenate([fs, np.geomspace(fs[0], fs[-1], 2000)]))
    with np.errstate(all="ignore"):
        eff = float(np.max(np.abs(np.log(two.response(dense) / rig.response(dense)))))
    effect = eff / max(two.residual_std, 1e-300)
    nums = (f"rigid fit {rig.fit_percent:.2f} %, residual {rig.residual_std:.3g}; two-mass fit {two.fit_percent:.2f} %, "
            f"residual {two.residual_std:.3g}; F = {f_stat:.4g}, p = {p:.3g}; the mode changes the response by up to "
            f"{20 / math.log(10) * eff:.3g} dB, {effect:.3g} x the noise")
    ratio = two.rss / max(rig.rss, 1e-300)
    zeta = two.value("damping_ratio")
    if p < STRUCTURE_ALPHA and in_band and effect > STRUCTURE_EFFECT and ratio <= STRUCTURE_RSS_RATIO \
            and zeta <= STRUCTURE_ZETA_MAX:
        return StructureChoice("two-mass", rig, two, f_stat, p, effect, in_band,
                               f"the response shows an anti-resonance at {fa:.4g} Hz and an axial mode at {fr:.4g} Hz "
                               f"that the rigid model cannot produce ({nums})")
    why = []
    if not p < STRUCTURE_ALPHA:
        why.append(f"the two-mass model is not significantly better (p = {p:.3g} >= {STRUCTURE_ALPHA:g})")
    if not in_band:
        why.append(f"its anti-resonance {fa:.4g} Hz and mode {fr:.4g} Hz are not both inside the measured band "
                   f"{np.min(f):.4g}..{np.max(f):.4g} Hz")
    if not effect > STRUCTURE_EFFECT:
        why.append(f"the mode changes the response by only {effect:.3g} x the noise (<= {STRUCTURE_EFFECT:g})")
    if not ratio <= STRUCTURE_RSS_RATIO:
        why.append(f"it leaves {100 * ratio:.3g} % of the rigid model's residual (more than "
                   f"{100 * STRUCTURE_RSS_RATIO:g} %: no mode explains the misfit)")
    if not zeta <= STRUCTURE_ZETA_MAX:
        why.append(f"its pole pair is damped {zeta:.3g} (> {STRUCTURE_ZETA_MAX:g}: a lag, not a resonance)")
    return StructureChoice("rigid", rig, two, f_stat, p, effect, in_band,
                           "; ".join(why) + f" ({nums})")
