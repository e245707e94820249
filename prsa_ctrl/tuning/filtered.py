"""Speed-loop gains tuned together with a notch or low-pass filter, under Ms and noise-gain bounds.

A drive places a notch at a structural resonance, or a low-pass on the measured speed, so that
the speed PI can run higher gains. This module tunes the filter's parameters *together with*
the gains in one CasADi/ipopt NLP, like JuliaSim's filter tuning, on the same sampled loop
model the gains-only tuner uses (:func:`prsa_ctrl.tuning.builders.drive_loop`, which runs the filters
exactly as the simulator's per-sample law does), and verifies the result the same way:

- **objective**: IAE of the load step on the objective loops (linearised at the step's mid
  load), summed to infinity for the report (:meth:`LoopModel.objective_to_infinity`);
- **Ms**: ``|1 + L| >= 1/Ms`` on every constraint loop's grid, then the true peak
  (:meth:`LoopModel.peaks`) of the loop *with the tuned filter*; a violated bound adds its
  frequency to the NLP and solves again (like :class:`prsa_ctrl.tuning.tuner.Tuner`);
- **Mt** (optional): ``|T| = |L/(1 + L)| <= Mt`` the same way;
- **Mks** (optional): the noise gain ``Mks = max |C F S|`` from a speed-measurement noise
  (rad/s, on the raw encoder difference; the Kalman filter's loop: the angle noise it updates
  with, as that difference reads it) to the torque command (N m), ``F`` every filter on the
  path (the drive's speed filter and the loop filters), ``S = 1/(1 + L)``, up to Nyquist
  (:meth:`LoopModel.noise_peak`); verified and refined the same way. (The gains-only
  :class:`~prsa_ctrl.tuning.tuner.Tuner`'s ``max_noise_gain`` is the controller's high-frequency
  gain ``kp + kd/tf``; with filters that number no longer describes the noise path, so this
  module bounds ``max |C F S|`` for the gains-only design as well: equal bounds, same
  definition.)
- **stability** from the closed-loop eigenvalues of every loop.

How the filter enters the NLP: the discrete biquad (Tustin prewarped at the centre/corner,
the coefficients the export writes) is a CasADi expression of the filter's parameters; the
loop model's matrices are affine in the biquad's coefficients for fixed gains (one tuned
filter), so ``A(g, c) = A0(c) + sum g_i A_i(c)`` is assembled from :func:`drive_loop` evaluated
at the coefficient basis (the loop is written once, in :func:`drive_loop`), and its frequency
response is ``L = F_c(z) L_rest`` with the encoder's measurement. With the Kalman filter's
(:class:`~prsa_ctrl.tuning.loopmeasure.KalmanEstimate`) the loop has a denominator part,
``L = F_c g.N / (1 + F_c g.D)``, and with its load feed-forward a fourth gain ``kff`` (tuned with
kp and ki; a speed-path filter does not act on its part): the Ms rows
(:func:`sensitivity_rows`) are exact for both, and so are its Mt and Mks rows; which gain parts the
filter multiplies is read off the loop itself (:func:`filtered_gains`).
:func:`tune_filtered` with ``kind=None`` solves the same problem with the gains alone.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from ..drive.pid import PID
from ..options import MS_MAX_DEFAULT, check_peak_bound
from ..results import is_converged, status_head
from ..drive.filters import PLACES, DiscreteBiquad, FirstOrderLowPass, LoopFilter, Notch, SecondOrderLowPass
from .loops import LoopModel
from .builders import drive_loop
from .loopmeasure import LoopMeasurement
# Private helpers of the tuner's NLP, until tuning/tuner.py makes them public (h-tuner25).
from .objectives import smooth_abs, two_rate_error

__all__ = ["TUNABLE", "FilteredDesign", "tune_filtered", "FilterBounds", "loop_builder", "dominant_resonance_hz",
           "sensitivity_rows", "filtered_gains"]

#: Filters whose parameters the NLP tunes, and their parameters.
TUNABLE = {"notch": ("centre_hz", "width_hz", "depth_db"), "lowpass1": ("corner_hz",),
           "lowpass2": ("corner_hz",)}
_MAX_ROUNDS = 12
#: A tuned filter is kept only if it lowers the objective by at least this fraction against the
#: gains alone under the same bounds (else the status says that no filter helps).
MIN_BENEFIT = 0.01
#: A tuned notch is kept only if it is at least this deep (dB) ...
MIN_NOTCH_DEPTH_DB = 3.0
#: ... and its centre lies within this factor of a loop's dominant resonance (the mode).
MODE_FACTOR = 1.5
_HESSIAN = "limited-memory"  # measured faster than "exact" on the heavy-slide case (13 s vs 22 s)
_IPOPT_MAX_ITER = 500


@dataclass(frozen=True)
class FilterBounds:
    """Search box of the tuned filter.

    Parameters
    ----------
    centre_hz : (float, float), Hz
        Notch centre (or low-pass corner) range.
    width_ratio : (float, float)
        Notch width as a fraction of its centre (``width_hz / centre_hz``).
    depth_db : (float, float), dB
        Notch depth range (<= 0).
    """

    centre_hz: tuple[float, float]
    width_ratio: tuple[float, float] = (0.05, 2.0)
    depth_db: tuple[float, float] = (-40.0, 0.0)

    def __post_init__(self) -> None:
        for name, (lo, hi), lim in (("centre_hz", self.centre_hz, (0.0, math.inf)),
                                     ("width_ratio", self.width_ratio, (0.0, 4.0)),
                                     ("depth_db", self.depth_db, (-120.0, 0.0))):
            ok = all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in (lo, hi))
            if not ok or not (lim[0] <= lo < hi <= lim[1]) or (name != "depth_db" and lo <= 0):
                raise ValueError(f"FilterBounds {name} = {(lo, hi)!r}; expected lo < hi within "
                                 f"[{lim[0]:g}, {lim[1]:g}]" + (" and lo > 0" if name != "depth_db" else ""))


@dataclass(frozen=True)
class FilteredDesign:
    """Outcome of :func:`tune_filtered`.

    Attributes
    ----------
    pid : PID
        Tuned speed PI.
    filter : LoopFilter or None
        Tuned filter (None: gains alone).
    objective : float
        Sum of the objective loops' IAE to infinity (rad, of the nut speed).
    ms : float
        Largest true Ms over the constraint loops (with the filter).
    mks : float or None
        Largest true noise gain ``max |C F S|`` (N m per rad/s) over the constraint loops (None:
        loops without a noise path).
    status : str
        ``"optimal"``: a converged ipopt solve whose verified bounds hold and, with a filter,
        a filter that earns its place (:func:`tune_filtered`); ``"no <kind> helps: <why>"``:
        the best filter found does not (too shallow, away from the mode or no lower
        objective than the gains alone), so the design returned is the gains alone
        (``filter`` None) and the rejected filter is in ``stats["rejected_filter"]``;
        ``"not converged: ..."`` (vocabulary: :data:`prsa_ctrl.results.STATUSES`).
    stats : dict
        Rounds, iterations, added frequencies, wall time (s), the active bounds; with a filter
        also ``reference_objective`` / ``reference_status`` (the gains alone) and
        ``mode_hz`` (each loop's dominant resonance).
    warnings : tuple of str
        Every caveat of the result, one line each (a rejected filter, a design that is not a
        verified optimum).
    """

    pid: PID
    filter: LoopFilter | None
    objective: float
    ms: float
    mks: float | None
    status: str
    stats: dict = field(default_factory=dict)
    warnings: tuple[str, ...] = ()

    @property
    def converged(self) -> bool:
        """The returned design is a verified optimum (with its filter, or the gains alone when no
        filter helps: then the gains alone's own status, ``stats["reference_status"]``, decides)."""
        if status_head(self.status) == "no <kind> helps":
            return self.stats.get("reference_status") == "optimal"
        return is_converged(self.status)

    @property
    def ok(self) -> bool:
        """The design may be reported as good: :attr:`converged` (the returned design is a
        verified optimum)."""
        return self.converged

    def as_dict(self) -> dict:
        return {"pid": self.pid.as_dict(), "filter": self.filter.as_dict() if self.filter else None,
                "objective": self.objective, "ms": self.ms, "mks": self.mks, "status": self.status,
                "stats": {k: v for k, v in self.stats.items() if k != "runs"}, "warnings": list(self.warnings)}


def _sx_biquad(kind: str, theta, ts: float):
    """Tustin biquad ``[b0, b1, b2, a1, a2]`` (prewarped at the centre/corner) as CasADi
    expressions of the filter parameters ``theta`` (the formula of :meth:`Filter.biquad`)."""
    f0 = theta[0]
    w0 = 2 * math.pi * f0
    k = w0 / ca.tan(w0 * ts / 2)
    if kind == "lowpass1":  # H = 1/(1 + s/w0): b = [1, 1], a = [k/w0 + 1, 1 - k/w0]
        a0 = k / w0 + 1.0
        return [1.0 / a0, 1.0 / a0, 0.0, (1.0 - k / w0) / a0, 0.0]
    if kind == "lowpass2":
        n2, n1, n0 = 0.0, 0.0, 1.0
        d2, d1, d0 = 1.0 / w0**2, 2.0 / math.sqrt(2.0) / w0, 1.0
    else:  # notch
        zeta = theta[1] / (2 * f0)
        g = 10 ** (theta[2] / 20)
        n2, n1, n0 = 1.0 / w0**2, 2 * g * zeta / w0, 1.0
        d2, d1, d0 = 1.0 / w0**2, 2 * zeta / w0, 1.0
    kk = k * k
    b = [n2 * kk + n1 * k + n0, 2 * (n0 - n2 * kk), n2 * kk - n1 * k + n0]
    a = [d2 * kk + d1 * k + d0, 2 * (d0 - d2 * kk), d2 * kk - d1 * k + d0]
    return [b[0] / a[0], b[1] / a[0], b[2] / a[0], a[1] / a[0], a[2] / a[0]]


def _filter_of(kind: str, theta: Sequence[float]):
    if kind == "notch":
        return Notch(float(theta[0]), float(theta[1]), float(theta[2]))
    if kind == "lowpass1":
        return FirstOrderLowPass(float(theta[0]))
    return SecondOrderLowPass(float(theta[0]))


def dominant_resonance_hz(lp: LoopModel, band_hz: tuple[float, float] | None = None) -> float:
    """Frequency (Hz) of the largest peak of ``|L|`` per unit ``kp`` relative to the rigid
    trend (``|L_kp| omega``, flat for an inertia), below Nyquist: where a notch belongs."""
    w = np.logspace(math.log10(lp.omega[0]), math.log10(0.98 * lp.nyquist), 4000)
    mag = np.abs(lp.parts_at(w)[1][0]) * w
    f = w / (2 * math.pi)
    if band_hz is not None:
        keep = (f >= band_hz[0]) & (f <= band_hz[1])
        f, mag = f[keep], mag[keep]
    # peak relative to a smooth trend: ratio to the running median over a decade
    lg = np.log(mag)
    trend = np.array([np.median(lg[max(0, i - 300): i + 300]) for i in range(lg.size)])
    return float(f[int(np.argmax(lg - trend))])


def _resonance_band(lp: LoopModel) -> NDArray[np.float64]:
    """Constraint frequencies (rad/s) packed around the lightly damped (zeta < 0.1) poles of
    the loop's open loop (gain-free part), up to 20 % either side: a resonance whose peak is
    ~2 zeta wide is then never missed between grid points."""
    lam = np.linalg.eigvals(lp.A0)
    lam = lam[(np.abs(lam) > 1e-12) & (np.abs(lam.imag) > 1e-9)]
    s = np.log(lam.astype(complex)) / lp.h
    wd, zeta = np.abs(s.imag), -s.real / np.maximum(np.abs(s), 1e-300)
    keep = (zeta < 0.1) & (wd < 0.98 * lp.nyquist) & (wd > lp.omega[0])
    x = np.concatenate([-np.logspace(-4, math.log10(0.2), 60), [0.0], np.logspace(-4, math.log10(0.2), 60)])
    pts = (wd[keep][:, None] * (1.0 + x[None, :])).ravel()
    return np.unique(pts[(pts > lp.omega[0]) & (pts < 0.999 * lp.nyquist)])


def loop_builder(a, b, c_speed, angle_index: int, *, ts: float, speed_filter: float | None = None, tf: float,
                 horizon: float, step: float, fixed: Sequence[LoopFilter] = (), name: str = "drive",
                 command_delay_samples: int = 0, measurement: LoopMeasurement | None = None) -> Callable:
    """``biquad or None -> LoopModel``: :func:`prsa_ctrl.tuning.builders.drive_loop` of a linearised
    plant with the ``fixed`` filters and, when given, one more ``(place, DiscreteBiquad)``.

    The speed is measured by the encoder's filtered difference (``speed_filter``, s) or by the
    ``measurement`` block (:mod:`prsa_ctrl.tuning.loopmeasure`, e.g. the Kalman filter's
    :class:`~prsa_ctrl.tuning.loopmeasure.KalmanEstimate`, whose loop response has a
    denominator part and, with its feed-forward, a fourth gain ``kff``); give one of them."""
    meas = {"speed_filter": speed_filter} if measurement is None else {"measurement": measurement}
    if measurement is not None and speed_filter is not None:
        raise ValueError(f"speed_filter = {speed_filter!r} with measurement {type(measurement).__name__}; expected "
                         "one of them (the block carries its own filtering)")

    def build(extra=None) -> LoopModel:
        fl = list(fixed) + ([extra] if extra is not None else [])
        return drive_loop(a, b, c_speed, angle_index, ts=ts, tf=tf, horizon=horizon, step=step, name=name,
                          filters=fl, command_delay_samples=command_delay_samples, **meas)
    return build


@dataclass
class _Basis:
    """A loop's matrices affine in the tuned biquad's coefficients, and its filter-free parts."""

    A0: list  # [c-free, per coefficient (5)]
    A: list  # per gain: [c-free, per coefficient]
    lp_rest: LoopModel  # the loop with an identity biquad: L_rest, noise_rest
    lp: LoopModel
    #: Per gain: whether the tuned biquad multiplies its parts of the loop response (``L_i``,
    #: ``D_i``): every gain's with the encoder; not the Kalman filter's feed-forward gain's
    #: with a filter on the measured speed (the load estimate does not pass it).
    on_filter: tuple = ()


def filtered_gains(rest: LoopModel, zero: LoopModel) -> tuple[bool, ...]:
    """Per gain, whether the tuned biquad multiplies its loop-response parts ``L_i``, ``D_i``.

    ``rest`` and ``zero`` are the loop built with the identity and with the zero biquad in the
    tuned place: the parts the biquad multiplies vanish with the zero biquad, the others are
    the identity biquad's (checked at three frequencies; anything else is a loop the rows of
    :func:`sensitivity_rows` do not describe: ``ArithmeticError``)."""
    w = rest.omega[[0, rest.omega.size // 2, -1]]
    n0r, lr, d0r, dr = rest.parts_at(w)
    n0z, lz, d0z, dz = zero.parts_at(w)
    if not (np.allclose(n0z, n0r, rtol=1e-9, atol=0) and np.allclose(d0z, d0r, rtol=1e-9, atol=0)):
        raise ArithmeticError("the tuned filter changes the loop's gain-free response parts; expected it on a "
                              "gain's path only")
    out = []
    for j in range(rest.n_gains):
        scale = max(np.max(np.abs(lr[j])), np.max(np.abs(dr[j])), 1e-300)
        if max(np.max(np.abs(lz[j])), np.max(np.abs(dz[j]))) <= 1e-12 * scale:
            out.append(True)
        elif np.allclose(lz[j], lr[j], rtol=1e-9, atol=1e-12 * scale) and np.allclose(dz[j], dr[j], rtol=1e-9,
                                                                                       atol=1e-12 * scale):
            out.append(False)
        else:
            raise ArithmeticError(f"gain {j}'s loop response is neither multiplied by the tuned filter nor free of "
                                  "it; expected one of them")
    return tuple(out)


def _basis(build: Callable, place: str | None, ts: float) -> _Basis:
    ident = build((place, DiscreteBiquad(1.0, 0.0, 0.0, 0.0, 0.0, ts))) if place else build(None)
    if place is None:
        return _Basis([ident.A0], [[a] for a in ident.A], ident, ident, (True,) * ident.n_gains)  # no biquad
    zero = build((place, DiscreteBiquad(0.0, 0.0, 0.0, 0.0, 0.0, ts)))
    a0 = [zero.A0]
    ai = [[m] for m in zero.A]
    for j in range(5):
        c = [0.0] * 5
        c[j] = 1.0
        lj = build((place, DiscreteBiquad(*c, ts)))
        a0.append(lj.A0 - zero.A0)
        for i, m in enumerate(lj.A):
            ai[i].append(m - zero.A[i])
    return _Basis(a0, ai, ident, zero, filtered_gains(ident, zero))


def _within(pk: dict, ms_max: float, mt_max: float | None) -> bool:
    return pk["ms"] <= ms_max and (mt_max is None or pk["mt"] <= mt_max)


def _design_loops(build: Callable, kind: str | None, place: str | None, theta, ts: float) -> LoopModel:
    if kind is None:
        return build(None)
    return build(LoopFilter(_filter_of(kind, theta), place))


def _cmul(a, b):
    """``a b`` of complex columns held as ``(re, im)`` pairs (CasADi or NumPy)."""
    return a[0] * b[0] - a[1] * b[1], a[0] * b[1] + a[1] * b[0]


def _cabs2(a):
    return a[0] * a[0] + a[1] * a[1]


def sensitivity_rows(rest: LoopModel, on_filter: Sequence[bool], coef: Sequence, gains, tuned: Sequence[int],
                     w: NDArray[np.float64], ts: float, *, inv_ms2: float, mks: float | None = None,
                     g_start: NDArray[np.float64], mt: float | None = None):
    """The filter tuner's frequency rows (CasADi, each ``>= 0`` where the bound holds) at ``w``
    (rad/s) of the loop ``rest`` (its identity-biquad build) with one more biquad.

    The biquad ``F = Nc/Dc``, ``Nc = b0 + b1 z^-1 + b2 z^-2``, ``Dc = 1 + a1 z^-1 + a2 z^-2``
    (``coef`` = ``[b0, b1, b2, a1, a2]``, CasADi expressions; empty: no biquad), multiplies the
    response parts ``L_i``, ``D_i`` of each gain ``i`` with ``on_filter[i]``. With ``P_i = Nc``
    there and ``Dc`` elsewhere, the loop ``L = (N0 + sum g_i F_i L_i) / (D0 + sum g_i F_i D_i)``
    (:class:`~prsa_ctrl.tuning.loops.LoopModel`) has, exactly,

    ``1 + L = num / den``, ``num = Dc (D0 + N0) + sum P_i g_i (L_i + D_i)``,
    ``den = Dc D0 + sum P_i g_i D_i``,

    so ``|S| <= Ms`` is ``|num|^2 - |den|^2 / Ms^2 >= 0`` and, as ``T = L/(1 + L) = (num - den) /
    num``, ``|T| <= Mt`` is ``Mt^2 |num|^2 - |num - den|^2 >= 0`` (the encoder's loop, ``N0 = 0``,
    ``D0 = 1``, ``D = 0``: ``|Dc + Nc g.L|^2 - |Dc|^2/Ms^2``; the Kalman filter's: ``D != 0``,
    and with its feed-forward on a speed-path filter, the ``kff`` part is not filtered). With
    ``mks``, as ``C F S = sum g_i F_i K_i / (D0 + N0 + sum g_i F_i (L_i + D_i)) = sum P_i g_i K_i /
    num`` (``K`` = ``rest.noise``, filtered as ``L``), the row ``Mks^2 |num|^2 - |sum P_i g_i K_i|^2
    >= 0`` bounds ``|C F S|`` (the encoder's loop: ``Mks^2 |num|^2 - |Nc g.K|^2``).

    Parameters
    ----------
    rest : LoopModel
        The loop with an identity biquad in the tuned place (needs ``response``).
    on_filter : sequence of bool
        Per gain of ``rest``.
    coef : sequence
        The biquad's 5 coefficients (CasADi), or empty.
    gains : casadi.SX
        The loop's gain vector (``rest.n_gains`` entries).
    tuned : sequence of int
        Indices of the gains that are not zero.
    w : array, rad/s
    ts : float, s
    inv_ms2 : float
        ``1 / Ms^2``.
    mks : float, optional, N m s/rad
    mt : float, optional
        The Mt bound (its rows follow the Ms rows).
    g_start : array
        Start gains (row scaling only: each row is divided by its size at the start without
        the biquad).

    Returns
    -------
    casadi.SX
        ``w.size`` Ms rows, then ``w.size`` Mt rows with ``mt``, then ``w.size`` Mks rows with
        ``mks``.
    """
    n0, lr, d0, dr = rest.parts_at(w)
    idx = list(tuned)
    zi = np.exp(-1j * w * ts)
    if len(coef):
        n_re = coef[0] + coef[1] * ca.DM(zi.real) + coef[2] * ca.DM((zi * zi).real)
        n_im = coef[1] * ca.DM(zi.imag) + coef[2] * ca.DM((zi * zi).imag)
        d_re = 1.0 + coef[3] * ca.DM(zi.real) + coef[4] * ca.DM((zi * zi).real)
        d_im = coef[3] * ca.DM(zi.imag) + coef[4] * ca.DM((zi * zi).imag)
    else:
        n_re, n_im, d_re, d_im = ca.DM.ones(w.size), ca.DM.zeros(w.size), ca.DM.ones(w.size), ca.DM.zeros(w.size)
    gv = ca.vertcat(*[gains[i] for i in idx])
    gs = np.asarray(g_start, float)[idx]
    plain = (not np.any(dr[idx]) and np.all(d0 == 1.0) and not np.any(n0)
             and all(on_filter[i] for i in idx))
    if plain:  # the encoder's loop: 1 + L = (Dc + Nc g.L) / Dc
        G = np.asarray(lr[idx], complex)
        g_re = ca.DM(G.real.T) @ gv
        g_im = ca.DM(G.imag.T) @ gv
        ng_re, ng_im = n_re * g_re - n_im * g_im, n_re * g_im + n_im * g_re
        s_re, s_im = d_re + ng_re, d_im + ng_im
        ww = s_re * s_re + s_im * s_im
        dd = d_re * d_re + d_im * d_im
        # row scale at the start point: 1/(|1 + L0|^2 + 1) in units of |D|^2
        l0 = gs @ G  # start point without the tuned filter (row scaling only)
        sc = 1.0 / (np.abs(1 + l0) ** 2 + 1.0)
        rows = [(ww - inv_ms2 * dd) * ca.DM(sc)]
        if mt is not None:  # T = Nc g.L / (Dc + Nc g.L)
            sc_t = 1.0 / (mt**2 * np.abs(1 + l0) ** 2 + np.abs(l0) ** 2)
            rows.append((mt**2 * ww - (ng_re * ng_re + ng_im * ng_im)) * ca.DM(sc_t))
        if mks is not None:
            K = np.asarray(rest.noise(w)[idx], complex)
            k_re, k_im = ca.DM(K.real.T) @ gv, ca.DM(K.imag.T) @ gv
            nk_re, nk_im = n_re * k_re - n_im * k_im, n_re * k_im + n_im * k_re
            k0 = np.abs(gs @ K) ** 2
            sc2 = 1.0 / (mks**2 * np.abs(1 + l0) ** 2 + k0 + 1e-300)
            rows.append((mks**2 * ww - (nk_re * nk_re + nk_im * nk_im)) * ca.DM(sc2))
        return ca.vertcat(*rows)
    nc, dc = (n_re, n_im), (d_re, d_im)

    def dm(x):
        return ca.DM(x.real), ca.DM(x.imag)

    def wsum(parts, on: bool):
        """``P sum g_i parts_i`` over the tuned gains on (``P = Nc``) or off (``Dc``) the filter."""
        sel = [k for k, i in enumerate(idx) if bool(on_filter[i]) == on]
        if not sel:
            return None
        P = np.asarray(parts[[idx[k] for k in sel]], complex)
        gsel = ca.vertcat(*[gv[k] for k in sel])
        return _cmul(nc if on else dc, (ca.DM(P.real.T) @ gsel, ca.DM(P.imag.T) @ gsel))

    def total(first, parts):
        out = first
        for term in (wsum(parts, True), wsum(parts, False)):
            if term is not None:
                out = (out[0] + term[0], out[1] + term[1])
        return out

    num = total(_cmul(dc, dm(d0 + n0)), lr + dr)
    den = total(_cmul(dc, dm(d0)), dr)
    # row scale at the start point without the biquad: 1/(|num0|^2 + |den0|^2)
    num0 = d0 + n0 + gs @ (lr + dr)[idx]
    den0 = d0 + gs @ dr[idx]
    sc = 1.0 / (np.abs(num0) ** 2 + np.abs(den0) ** 2)
    rows = [(_cabs2(num) - inv_ms2 * _cabs2(den)) * ca.DM(sc)]
    if mt is not None:
        sc_t = 1.0 / (mt**2 * np.abs(num0) ** 2 + np.abs(num0 - den0) ** 2)
        rows.append((mt**2 * _cabs2(num) - _cabs2((num[0] - den[0], num[1] - den[1]))) * ca.DM(sc_t))
    if mks is not None:
        K = np.asarray(rest.noise(w), complex)
        k0 = np.abs(gs @ K[idx]) ** 2
        sc_k = 1.0 / (mks**2 * np.abs(num0) ** 2 + k0 + 1e-300)
        rows.append((mks**2 * _cabs2(num) - _cabs2(total((ca.DM.zeros(w.size), ca.DM.zeros(w.size)), K)))
                    * ca.DM(sc_k))
    return ca.vertcat(*rows)


def tune_filtered(
    objective_builders: Sequence[Callable],
    constraint_builders: Sequence[Callable] = (),
    *,
    ts: float,
    kind: str | None = "notch",
    place: str = "torque_command",
    start_gains: Sequence[float],
    start_filter: Sequence[float] | None = None,
    bounds: FilterBounds | None = None,
    ms_max: float = MS_MAX_DEFAULT,
    max_noise_gain: float | None = None,
    reference: FilteredDesign | None = None,
    start_kff: float = 0.0,
    mt_max: float | None = None,
) -> FilteredDesign:
    """Tune the speed PI (kp, ki) and, with ``kind``, one filter's parameters in one NLP.

    Parameters
    ----------
    objective_builders : sequence of callables
        :func:`loop_builder` results whose load-step IAE is summed (the objective); their
        loops are constrained too.
    constraint_builders : sequence of callables
        Further loops (e.g. linearised at the step's initial and final loads) that only carry
        the Ms / Mks constraints.
    ts : float, s
        Sample time.
    kind : {"notch", "lowpass1", "lowpass2"} or None
        Tuned filter (None: the gains alone, same problem otherwise).
    place : {"torque_command", "speed_measurement"}
    start_gains : (kp, ki)
        Start point (N m s/rad, N m/rad), e.g. the gains-only optimum.
    mt_max : float, optional
        Bound on the true Mt of every loop, in (1, 10) (rows and verification as Ms).
    start_kff : float
        Start of the load feed-forward gain ``kff`` in [0, 1] (loops of the Kalman filter with
        its feed-forward, which carry it as a fourth gain; then tuned with kp and ki). Loops
        without it take 0 only.
    start_filter : sequence of float, optional
        Start parameters (``TUNABLE[kind]``: Hz, Hz, dB); default: notch at the dominant
        resonance of the first loop, width 0.3 x centre, -20 dB; low-pass corner at 0.25 x
        Nyquist.
    bounds : FilterBounds, optional
        Default: centre within 0.5 .. 2 x the start and below 0.45/ts.
    ms_max : float
        Bound on the true Ms of every loop, in (1, 10).
    max_noise_gain : float, optional
        Bound on the true ``Mks = max |C F S|`` (N m per rad/s) of every loop; needs loops with
        a noise path (the encoder's measurement or the Kalman filter's,
        :meth:`~prsa_ctrl.tuning.loops.LoopModel.noise_response`).
    reference : FilteredDesign, optional
        The gains-alone design of the same loops and bounds (``kind=None``), to judge the
        filter against; computed here when not given.

    Returns
    -------
    FilteredDesign
        With a filter, ``status`` is ``"optimal"`` only if the verified filter design earns its
        place: its objective is at least ``MIN_BENEFIT`` (1 %) below the gains alone's under
        the same bounds and, for a notch, it is at least ``MIN_NOTCH_DEPTH_DB`` (3 dB) deep
        with its centre within a factor ``MODE_FACTOR`` (1.5) of a loop's dominant resonance
        (:func:`dominant_resonance_hz`). Otherwise the gains-alone design is returned with the
        status ``"no <kind> helps: <why>"`` -- never a 0 dB notch, or a notch away from the
        mode, labelled optimal.
    """
    t0 = time.perf_counter()
    if reference is not None and not (isinstance(reference, FilteredDesign) and reference.filter is None):
        raise ValueError(f"reference = {reference!r}; expected the FilteredDesign of tune_filtered(kind=None)")
    if kind is not None and kind not in TUNABLE:
        raise ValueError(f"kind = {kind!r}; expected one of {', '.join(TUNABLE)} or None")
    if place not in PLACES:
        raise ValueError(f"place = {place!r}; expected one of {', '.join(PLACES)}")
    check_peak_bound("ms_max", ms_max)
    if mt_max is not None:
        check_peak_bound("mt_max", mt_max)
    if max_noise_gain is not None and not (isinstance(max_noise_gain, (int, float)) and math.isfinite(max_noise_gain)
                                           and max_noise_gain > 0):
        raise ValueError(f"max_noise_gain = {max_noise_gain!r}; expected a positive finite number (N m s/rad) or None")
    g0 = np.asarray(start_gains, float)[:2]
    if g0.shape != (2,) or not np.all(np.isfinite(g0)) or np.any(g0 <= 0):
        raise ValueError(f"start_gains = {start_gains!r}; expected (kp, ki) > 0")
    if isinstance(start_kff, bool) or not isinstance(start_kff, (int, float)) or not 0.0 <= start_kff <= 1.0:
        raise ValueError(f"start_kff = {start_kff!r}; expected a load feed-forward gain in [0, 1]")
    builders = list(objective_builders) + list(constraint_builders)
    n_obj = len(objective_builders)
    if n_obj == 0:
        raise ValueError("objective_builders is empty; expected at least one loop")
    pl = place if kind is not None else None
    bases = [_basis(b, pl, ts) for b in builders]
    n_g = bases[0].lp_rest.n_gains
    if any(bs.lp_rest.n_gains != n_g for bs in bases):
        raise ValueError("loops with and without the load feed-forward gain; expected the same gains in every loop")
    ff = n_g == 4  # the Kalman filter's load feed-forward: kff tuned with kp and ki
    if not ff and start_kff != 0.0:
        raise ValueError(f"start_kff = {start_kff!r} for loops without a feed-forward gain; expected 0")
    tuned = (0, 1, 3) if ff else (0, 1)
    has_noise = all(bs.lp_rest.noise is not None for bs in bases)
    if max_noise_gain is not None and not has_noise:
        raise ValueError(f"max_noise_gain = {max_noise_gain!r} for loops without a noise path; expected None")

    def full(kp_, ki_, kff_=0.0):
        """The loops' gain vector (kp, ki, kd = 0[, kff])."""
        return np.array([kp_, ki_, 0.0, kff_] if ff else [kp_, ki_, 0.0], float)
    nyq_hz = 0.5 / ts
    if kind is not None:
        names = TUNABLE[kind]
        if start_filter is None:
            if kind == "notch":
                f0 = dominant_resonance_hz(bases[0].lp_rest)
                start_filter = (f0, 0.3 * f0, -20.0)
            else:
                start_filter = (0.25 * nyq_hz,)
        th0 = np.asarray(start_filter, float)
        if th0.shape != (len(names),) or not np.all(np.isfinite(th0)):
            raise ValueError(f"start_filter = {start_filter!r}; expected {len(names)} numbers ({', '.join(names)})")
        _filter_of(kind, th0).biquad(ts)  # validates (Nyquist, ranges) with one line
        if bounds is None:
            bounds = FilterBounds((0.5 * th0[0], min(2.0 * th0[0], 0.9 * nyq_hz)))
        if not isinstance(bounds, FilterBounds):
            raise ValueError(f"bounds = {bounds!r}; expected a FilterBounds")
        if bounds.centre_hz[1] >= nyq_hz:
            raise ValueError(f"bounds centre_hz = {bounds.centre_hz!r}; expected below the Nyquist frequency {nyq_hz:g} Hz")
    else:
        names, th0 = (), np.zeros(0)

    # A feasible start: the given gains scaled down until every loop is stable within Ms
    # (and Mks) with the start filter (kp by 0.7, ki by 0.49, at most 30 times; with an Mks bound
    # the load feed-forward gain by 0.7 too: its path from the encoder noise does not scale with kp).
    kff0 = start_kff
    for _ in range(30):
        lps = [_design_loops(b, kind, place, th0, ts) for b in builders]
        gg = full(g0[0], g0[1], kff0)
        ok = all(lp.stability(gg) == "stable" and _within(lp.peaks(gg), ms_max, mt_max)
                 and (max_noise_gain is None or lp.noise_peak(gg)["mks"] <= max_noise_gain) for lp in lps)
        if ok:
            break
        g0 = g0 * np.array([0.7, 0.49])  # kp s, ki s^2: the PI corner keeps its place below crossover
        kff0 = kff0 * 0.7 if max_noise_gain is not None else kff0
    else:
        raise ValueError(f"start_gains = {tuple(start_gains)!r}: no scaled-down start meets Ms <= {ms_max:g}"
                         + (f", Mt <= {mt_max:g}" if mt_max is not None else "")
                         + (f", Mks <= {max_noise_gain:g}" if max_noise_gain is not None else "")
                         + "; expected stabilising start gains")

    # ---- decision variables: v = [kp/kp0, ki/ki0, log(f/f0), (log(width ratio), depth/20)]
    nth = len(names)
    v = ca.SX.sym("v", 2 + nth + ff)  # kff (the feed-forward loops) last
    kp, ki = v[0] * g0[0], v[1] * g0[1]
    g = ca.vertcat(kp, ki, 0.0, v[2 + nth]) if ff else ca.vertcat(kp, ki, 0.0)
    if kind is not None:
        f0 = th0[0] * ca.exp(v[2])
        theta = [f0]
        if kind == "notch":
            theta += [f0 * (th0[1] / th0[0]) * ca.exp(v[3]), 20.0 * v[4]]
        coef = _sx_biquad(kind, theta, ts)
    else:
        coef = []

    def x_of(gains, th):
        out = [gains[0] / g0[0], gains[1] / g0[1]]
        if kind is not None:
            out.append(math.log(th[0] / th0[0]))
            if kind == "notch":
                out += [math.log((th[1] / th[0]) / (th0[1] / th0[0])), th[2] / 20.0]
        return out + ([gains[3]] if ff else [])

    def theta_of(x):
        if kind is None:
            return []
        f = th0[0] * math.exp(x[2])
        th = [f]
        if kind == "notch":
            th += [f * (th0[1] / th0[0]) * math.exp(x[3]), 20.0 * x[4]]
        return th

    lbx, ubx = [1e-6, 1e-6], [ca.inf, ca.inf]
    if kind is not None:
        lbx.append(math.log(bounds.centre_hz[0] / th0[0]))
        ubx.append(math.log(bounds.centre_hz[1] / th0[0]))
        if kind == "notch":
            r0 = th0[1] / th0[0]
            lbx += [math.log(bounds.width_ratio[0] / r0), bounds.depth_db[0] / 20.0]
            ubx += [math.log(bounds.width_ratio[1] / r0), bounds.depth_db[1] / 20.0]
    if ff:  # kff in [0, 1], as the gains-only tuner
        lbx.append(0.0)
        ubx.append(1.0)

    def a_cl(bs: _Basis):
        def aff(mats):
            m = ca.DM(mats[0])
            for j, cj in enumerate(coef):
                m = m + cj * ca.DM(mats[1 + j])
            return m
        return aff(bs.A0) + sum(g[i] * aff(bs.A[i]) for i in tuned)

    # ---- objective (two-rate IAE over the horizon, as the gains-only Tuner)
    start_loops = lps
    g_start = full(g0[0], g0[1], kff0)
    eps = [1e-3 * max(float(np.max(np.abs(lp.error(g_start)))), 1e-300) for lp in start_loops[:n_obj]]
    j_ref = max(sum(lp.objective(g_start, "iae") for lp in start_loops[:n_obj]), 1e-300)
    objs = []
    for jl in range(n_obj):
        bs, lp = bases[jl], start_loops[jl]
        acl = a_cl(bs)
        e, _, w = two_rate_error(acl, ca.DM(lp.Bd), ca.DM(lp.Ce), lp.n_steps)
        objs.append(ca.sum2(ca.DM(lp.h * w).T * smooth_abs(e, eps[jl])))
    f_obj = sum(objs) / j_ref

    def freq_cons(bs: _Basis, w: NDArray, inv_ms2: float, mks: float | None, mt: float | None):
        return sensitivity_rows(bs.lp_rest, bs.on_filter, coef, g, tuned, w, ts, inv_ms2=inv_ms2, mks=mks,
                                g_start=g_start, mt=mt)

    # Seed the added frequencies with the start's true peaks (the optimum's are usually near).
    extra_w: list[list[float]] = [[lp.peaks(g_start)["w_ms"]] for lp in lps]
    dense = [_resonance_band(bs.lp_rest) for bs in bases]
    ms_eff = ms_max * (1 - 1e-5)
    mks_eff = max_noise_gain * (1 - 1e-5) if max_noise_gain is not None else None
    stats: dict = {"rounds": 0, "iterations": 0, "added_frequencies_rad_s": extra_w, "phases": []}
    eff = {"ms": ms_eff, "mks": mks_eff, "mt": mt_max * (1 - 1e-5) if mt_max is not None else None}

    def solve(x0, lo, up):
        """Rounds of solve, verify, add the violating frequency; (status, best or None)."""
        status, best = "not converged: no solve", None
        for rnd in range(_MAX_ROUNDS + 1):
            cons = []
            for bs, ew, dw in zip(bases, extra_w, dense):
                w = np.unique(np.concatenate([bs.lp_rest.omega[::3], dw, np.asarray(ew, float)]))
                cons.append(freq_cons(bs, w, eff["ms"] ** -2, eff["mks"], eff["mt"]))
            solver = ca.nlpsol("filtertune", "ipopt", {"x": v, "f": f_obj, "g": ca.vertcat(*cons)},
                               {"print_time": False, "error_on_fail": False,
                                "ipopt": {"print_level": 0, "sb": "yes", "max_iter": _IPOPT_MAX_ITER, "tol": 1e-8,
                                          "mu_strategy": "adaptive", "hessian_approximation": _HESSIAN}})
            sol = solver(x0=x0, lbx=lo, ubx=up, lbg=0.0, ubg=ca.inf)
            st = solver.stats()
            stats["iterations"] += int(st["iter_count"])
            stats["ipopt"] = st["return_status"]
            xs = np.asarray(sol["x"]).ravel()
            if not np.all(np.isfinite(xs)):
                return "not converged: non-finite solver output", None
            # ipopt may step a hair past a bound (bound_relax_factor)
            xs = np.minimum(np.maximum(xs, np.asarray(lo, float)), np.asarray([u if u != ca.inf else np.inf for u in up]))
            gains = full(xs[0] * g0[0], xs[1] * g0[1], xs[2 + nth] if ff else 0.0)
            th = theta_of(xs)
            loops = [_design_loops(b, kind, place, th, ts) for b in builders]
            if any(lp.stability(gains) != "stable" for lp in loops):
                return "not converged: unstable closed loop at the solver's point", None
            pks = [lp.peaks(gains) for lp in loops]
            nks = [lp.noise_peak(gains) if has_noise else {"mks": None, "w_mks": None} for lp in loops]
            viol = False
            for j, (pk, nk) in enumerate(zip(pks, nks)):
                if pk["ms"] > ms_max:
                    viol = True
                    if any(abs(pk["w_ms"] / w - 1) < 1e-7 for w in extra_w[j]):
                        eff["ms"] *= (ms_max / pk["ms"]) * (1 - 1e-6)
                    else:
                        extra_w[j].append(pk["w_ms"])
                if mt_max is not None and pk["mt"] > mt_max:
                    viol = True
                    if any(abs(pk["w_mt"] / w - 1) < 1e-7 for w in extra_w[j]):
                        eff["mt"] *= (mt_max / pk["mt"]) * (1 - 1e-6)
                    else:
                        extra_w[j].append(pk["w_mt"])
                if max_noise_gain is not None and nk["mks"] > max_noise_gain:
                    viol = True
                    if any(abs(nk["w_mks"] / w - 1) < 1e-7 for w in extra_w[j]):
                        eff["mks"] *= (max_noise_gain / nk["mks"]) * (1 - 1e-6)
                    else:
                        extra_w[j].append(nk["w_mks"])
            x0 = list(xs)
            if not viol:
                obj = sum(lp.objective_to_infinity(gains, "iae")[0] for lp in loops[:n_obj])
                status = "optimal" if st["success"] else f"not converged: {st['return_status']}"
                return status, (gains, th, loops, pks, nks, obj, xs)
            stats["rounds"] += 1
        return f"not converged: true peak above the bound after {_MAX_ROUNDS} refinements", None

    # Phase 1 (with a filter): the gains alone with the filter held at its start, so that phase 2
    # (everything free) starts where the filter already pays (from the gains-only start, a deep
    # notch costs phase at crossover before the gains can rise: a local optimum at 0 dB).
    x_start = x_of(g_start, th0)
    results = []
    if kind is not None:
        held = x_start[2:2 + nth]
        status1, r1 = solve(x_start, lbx[:2] + held + lbx[2 + nth:], ubx[:2] + held + ubx[2 + nth:])
        stats["phases"].append(status1)
        if r1 is not None:
            results.append((status1, r1))
            x_start = list(r1[6])
    status, best = solve(x_start, lbx, ubx)
    stats["phases"].append(status)
    if best is not None:
        results.append((status, best))
    if results:
        conv = [r for r in results if r[0] == "optimal"] or results
        status, best = min(conv, key=lambda r: r[1][5])
    else:
        best = None
    stats["wall_time_s"] = time.perf_counter() - t0
    if best is None:
        raise ValueError(f"filter tuning found no verified design ({status}); relax ms_max/max_noise_gain or the "
                         "filter bounds")
    gains, th, loops, pks, nks, obj, _ = best
    lf = LoopFilter(_filter_of(kind, th), place) if kind is not None else None
    stats["w_ms_rad_s"] = [pk["w_ms"] for pk in pks]
    stats["w_mks_rad_s"] = [nk["w_mks"] for nk in nks]
    stats["per_loop_ms"] = [pk["ms"] for pk in pks]
    stats["per_loop_mt"] = [pk["mt"] for pk in pks]
    stats["mt"] = max(stats["per_loop_mt"])
    stats["per_loop_mks"] = [nk["mks"] for nk in nks]
    pid = PID(float(gains[0]), float(gains[1]), tf=float(loops[0].tf), kff=float(gains[3]) if ff else 0.0)
    design = FilteredDesign(pid, lf, float(obj), float(max(pk["ms"] for pk in pks)),
                            float(max(nk["mks"] for nk in nks)) if has_noise else None, status, stats,
                            _status_warnings(status))
    if kind is None:
        return design
    if reference is None:
        try:
            reference = tune_filtered(objective_builders, constraint_builders, ts=ts, kind=None, place=place,
                                      start_gains=start_gains, ms_max=ms_max, max_noise_gain=max_noise_gain,
                                      start_kff=start_kff, mt_max=mt_max)
        except ValueError:  # no verified gains-alone design: the filter is judged on its own
            reference = None
    modes = [dominant_resonance_hz(bs.lp_rest) for bs in bases]
    return _judged(design, reference, kind, modes)


def _judged(design: FilteredDesign, reference: FilteredDesign | None, kind: str, modes: list[float]) -> FilteredDesign:
    """``design`` if its filter earns its place (see :func:`tune_filtered`), else the gains-alone
    ``reference`` with the status ``"no <kind> helps: <why>"``."""
    f = design.filter.filter
    ref_obj = reference.objective if reference is not None else math.inf
    stats = {**design.stats, "mode_hz": modes, "reference_objective": ref_obj,
             "reference_status": reference.status if reference is not None else "no verified design"}
    design = replace(design, stats=stats)
    why = []
    if isinstance(f, Notch):
        near = min(modes, key=lambda m: abs(math.log(f.centre_hz / m)))
        if -f.depth_db < MIN_NOTCH_DEPTH_DB:
            why.append(f"its depth {f.depth_db:.3g} dB is shallower than -{MIN_NOTCH_DEPTH_DB:g} dB")
        if abs(math.log(f.centre_hz / near)) > math.log(MODE_FACTOR):
            why.append(f"its centre {f.centre_hz:.4g} Hz is more than {MODE_FACTOR:g}x away from the mode at "
                       f"{near:.4g} Hz")
    if not design.objective <= (1.0 - MIN_BENEFIT) * ref_obj:
        why.append(f"the objective {design.objective:.4g} is not {100 * MIN_BENEFIT:g} % below the gains alone's "
                   f"{ref_obj:.4g} (same bounds)")
    if not why or reference is None:
        if why:  # nothing to fall back on: keep the filter, say what is wrong with it
            status = (f"not converged: the {kind} does not earn its place ({'; '.join(why)}) and the gains "
                      "alone have no verified design")
            design = replace(design, status=status, warnings=_status_warnings(status))
        return design
    desc = ", ".join(f"{k} {v:.4g}" for k, v in f.parameters().items() if k != "quality")
    rej = dict(reference.stats)
    rej.update(mode_hz=modes, reference_objective=ref_obj, reference_status=reference.status,
               rejected_filter={**design.filter.as_dict(), "objective": design.objective, "ms": design.ms,
                                "mks": design.mks, "status": design.status},
               wall_time_s=reference.stats.get("wall_time_s", 0.0) + stats.get("wall_time_s", 0.0))
    status = f"no {kind} helps: the best {kind} found ({desc}) is rejected: {'; '.join(why)}; returned the gains alone"
    return FilteredDesign(reference.pid, None, reference.objective, reference.ms, reference.mks, status, rej,
                          (*reference.warnings, status))


def _status_warnings(status: str) -> tuple[str, ...]:
    """The one-line caveat of a design whose status is not a verified optimum (else none)."""
    return () if is_converged(status) else (f"filter tuning {status}",)
