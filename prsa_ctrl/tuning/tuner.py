"""Optimal PI/PID tuning against load-disturbance metrics under robustness constraints (CasADi).

The tuner works on a *loop model*: the closed loop discretised exactly (zero-order hold of the
plant, the controller's own difference equations), which is affine in the gains, plus the
loop transfer function, which is affine in the gains too. The objective (IE, IAE, ITAE or ISE
of the error after a disturbance step) is a smooth CasADi expression of the gains; Ms (and
optionally Mt) are enforced at every frequency of the loop's grid as ``|1 + L|^2 >= 1/Ms^2``
(with several loops, e.g. robust tuning's scenario models, at ~64 of them per loop plus its
resonance points: the verification below holds the rest).

Guarantees of a :class:`TuningResult` (each one checked after the solve, not assumed):

- **Ms and Mt are the true peaks** of the returned loop: the peaks are located on a dense
  grid refined at the closed-loop poles and polished by a bounded scalar search
  (:meth:`LoopModel.peaks`); where the true peak exceeds the bound, its frequency is added to
  the optimisation problem and the problem is solved again, until the bound holds.
- **Stability** is judged on the closed-loop eigenvalues (never assumed from the open loop),
  so unstable plants that the controller stabilises are tuned; :meth:`LoopModel.stability`
  tells stable, marginal (an undriven integrator, e.g. P-only) and unstable apart.
- **The objective is that of the returned gains**, integrated to infinity: IE and ISE in
  closed form (linear solve, discrete Lyapunov equation), IAE and ITAE summed until a proven
  bound on the remaining tail is below ``TAIL_RTOL`` of the value. For a continuous plant
  (:func:`continuous_loop`, :func:`tune_pid`) it is the CONTINUOUS closed loop's value
  (:meth:`LoopModel.objective_continuous`, IAE/ITAE to ``CONT_RTOL``), not that of the
  sampled stand-in the optimiser works on (which is in ``stats["objective_sampled"]``).
- **Health**: ``result.status`` is ``"optimal"`` only where the first-order optimality
  conditions hold at the returned gains on the TRUE problem (reported objective, true peaks),
  checked by finite differences independently of ipopt's exit (``Tuner._first_order``,
  tolerance ``KKT_TOL``); where they fail after ipopt, a bounded local solve of the true
  problem (``Tuner._polish``) is tried. Anything else says what it is (``"not proven optimal:
  first-order residual ..."``, ``"not converged: scan point kept ..."``) and
  ``result.warnings`` lists every caveat.

Two loop structures:

``continuous``
    any SISO python-control LTI plant (transfer function or state space), continuous PID
    ``kp + ki/s + kd s/(1 + tf s)``, simulated with a fine zero-order hold (:func:`tune_pid`);
``drive``
    the actuator's sampled speed loop exactly as :func:`prsa_ctrl.simulate` runs it: encoder
    angle differenced over one sample, first-order speed filter, PID with Euler integral,
    one-sample computation delay and ZOH (:func:`drive_loop`).

:class:`Tuner` owns the scan grid and the NLP of one loop set and is reusable; :func:`tune_pid`
and :func:`tune_loops` are thin wrappers around it.
"""

from __future__ import annotations

import math
import numbers
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from ..drive.pid import PID
from ..sim.metrics import Margins, margins_from_response
from ..options import CONTROLLERS, OBJECTIVES

__all__ = [
    "LoopModel",
    "TuningResult",
    "Tuner",
    "tune_pid",
    "tune_loops",
    "continuous_loop",
    "drive_loop",
    "OBJECTIVES",
    "STABILITY",
    "TAIL_RTOL",
    "CONT_RTOL",
    "KKT_TOL",
    "MAX_ORDER",
    "MS_RTOL",
]

#: Classes returned by :meth:`LoopModel.stability`.
STABILITY = ("stable", "marginal", "unstable")
#: Relative bound on the objective's tail beyond the summed samples (IAE, ITAE).
TAIL_RTOL = 1e-6
#: Relative tolerance of the Ms/Mt bound: a result with the bound active has its true peak in
#: ``[bound (1 - MS_RTOL), bound]``.
MS_RTOL = 1e-3
#: Relative accuracy of a continuous loop's reported IAE/ITAE (:meth:`LoopModel.objective_continuous`).
CONT_RTOL = 1e-5
#: First-order optimality tolerance (see ``Tuner._first_order``): the largest relative decrease of
#: the objective per unit relative change of the gains that the active constraints may leave.
KKT_TOL = 2e-3
#: Finite-difference step of that check, in log gain.
_FD_STEP = 1e-3
#: Local solves of the true problem after ipopt where the first-order check fails (``Tuner._polish``).
_POLISH_ROUNDS = 3
#: Largest number of step halvings of that integration (each doubles the samples).
_CONT_HALVINGS = 6
#: Eigenvalue modulus tolerance around the unit circle (discrete closed loop).
_UNIT_TOL = 1e-9
#: Largest number of samples a loop model may simulate (memory/time budget).
MAX_STEPS = 200_000
#: Largest number of samples summed for an IAE/ITAE tail (budget).
_TAIL_MAX_STEPS = 1 << 22
#: Frequencies per loop the NLP can add where the verified peak exceeded the bound.
_SLOTS = 12
#: Several loop models (robust tuning): grid rows per loop in the NLP (a coarse subset plus the
#: loop's resonance points; every true peak is still verified on the full grid and beyond), and
#: frequency slots per loop (added in clusters, see ``Tuner._solve_from``).
_MULTI_ROWS = 64
_MULTI_SLOTS = 40
#: Scan points ranked exactly before the start points are chosen (several loops).
_RANK_TOP = 50
#: Restarts from distinct scan points when a solve does not converge.
_STARTS = 3
_IPOPT_MAX_ITER = 400
#: Decades the peak search may extend below a loop model's grid (where |L| < 100 at its low end).
_LOW_DECADES = 8


# --------------------------------------------------------------------------------------------
# argument validation


def _number(name: str, value, *, lo: float = -math.inf, hi: float = math.inf, lo_open: bool = True,
            hi_open: bool = True, allow_inf: bool = False, expected: str | None = None) -> float:
    """``value`` as a float, or ValueError naming ``name`` and the expected range."""
    exp = expected or (
        f"a finite number in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    )
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} = {value!r}; expected {exp}")
    v = float(value)
    if math.isnan(v) or (math.isinf(v) and not (allow_inf and v > 0)):
        raise ValueError(f"{name} = {value!r}; expected {exp}")
    if (v < lo or (lo_open and v == lo)) or (v > hi or (hi_open and v == hi and not math.isinf(v))):
        raise ValueError(f"{name} = {value!r}; expected {exp}")
    return v


def _gain_limit(name: str, value) -> float:
    """Upper gain bound: None or inf for none, else a positive number."""
    if value is None:
        return math.inf
    return _number(name, value, lo=0.0, allow_inf=True, expected="a positive number, inf or None (no bound)")


def _int_steps(name: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or not 10 <= value <= MAX_STEPS:
        raise ValueError(f"{name} = {value!r}; expected an integer in [10, {MAX_STEPS}] (samples)")
    return int(value)


def _check_mks(mks_max) -> float | None:
    """``mks_max`` as a float, None for no bound, or a ValueError naming it."""
    if mks_max is None:
        return None
    return _number("mks_max", mks_max, lo=0.0, expected="a positive finite number or None")


def _check_bounds(ms_max, mt_max, max_noise_gain):
    ms = _number("ms_max", ms_max, lo=1.0, hi=10.0, expected="a number in (1, 10)")
    mt = None if mt_max is None else _number("mt_max", mt_max, lo=1.0, hi=10.0,
                                              expected="a number in (1, 10) or None")
    nz = None if max_noise_gain is None else _number(
        "max_noise_gain", max_noise_gain, lo=0.0, expected="a positive finite number or None")
    return ms, mt, nz


# --------------------------------------------------------------------------------------------
# the loop model


@dataclass(frozen=True, eq=False)
class LoopModel:
    """Closed loop affine in the gains g = (kp, ki, kd[, kff]).

    ``X[k+1] = (A0 + sum_i g_i A_i) X[k] + Bd``: response to a disturbance step of the stated
    size from zero initial deviation, sampled every ``h`` s; the error is ``e[k] = Ce X[k]``.
    A *profile* loop (``profile`` set, shape ``(n_steps, N)``) takes one input per sample
    instead, ``X[k+1] = A X[k] + profile[k]``, held at ``profile[-1]`` after the horizon: a
    load or setpoint duty cycle (by linearity, any sum of scaled, shifted steps and ramps);
    its ``Bd`` is then a representative step (the profile's largest deviation held from the
    start), which the tuner's scan uses only to rank start points.
    The loop transfer at the grid frequencies ``omega`` (rad/s) is
    ``L = (N0 + sum_i g_i L_i) / (D0 + sum_i g_i D_i)``: numerator and denominator are affine in
    the gains (``N0 = 0``, ``D = 1`` for a plain PID loop; an estimator whose prediction uses the
    applied torque makes the denominator depend on them).

    ``response`` (optional) evaluates ``(N0, L, D0, D)`` at any frequencies (rad/s; ``None``
    entries take the plain-loop defaults); with it, :meth:`peaks` and :meth:`margins` locate
    the true Ms/Mt peaks off the grid. ``nyquist`` (rad/s) marks a sampled loop, whose
    frequency response is periodic above it.
    """

    A0: NDArray[np.float64]
    A: tuple[NDArray[np.float64], ...]
    Bd: NDArray[np.float64]
    Ce: NDArray[np.float64]
    h: float
    n_steps: int
    omega: NDArray[np.float64]
    L: NDArray[np.complex128]  # shape (n_gains, n_omega)
    tf: float
    name: str = "loop"
    outputs: dict = field(default_factory=dict)  # extra named rows over X (e.g. torque)
    N0: NDArray[np.complex128] | None = None  # gain-free part of the numerator
    D0: NDArray[np.complex128] | None = None  # gain-free part of the denominator (default 1)
    D: NDArray[np.complex128] | None = None  # gain parts of the denominator, shape (n_gains, n_omega)
    response: Callable | None = None  # omega (rad/s) -> (N0, L, D0, D) off the grid
    nyquist: float | None = None  # rad/s, sampled loops
    _memo: dict = field(default_factory=dict, repr=False)  # gain-free responses on fixed grids
    profile: NDArray[np.float64] | None = None  # per-sample input (n_steps, N) of a profile loop
    noise: Callable | None = None  # omega (rad/s) -> (n_gains, n_omega): C F per unit gain (noise_peak)
    #: A continuous loop's own closed loop ``(A0c, (A_kp, A_ki, A_kd), Bdc)``: ``x' = (A0c + sum g_i
    #: A_i) x + Bdc`` from rest, error ``Ce x`` (same state as the sampled stand-in); with it
    #: :meth:`objective_continuous` integrates the continuous loop itself.
    continuous: tuple | None = None
    #: A continuous loop with an exact plant delay (:class:`_DelayedLoop`): its objective is
    #: that of the loop with the exact delay (the sampled stand-in and ``continuous`` carry a
    #: Pade model of it).
    delayed: object | None = None

    def __post_init__(self) -> None:
        if self.profile is not None:
            prof = np.asarray(self.profile, float)
            if prof.shape != (self.n_steps, self.A0.shape[0]) or not np.all(np.isfinite(prof)):
                raise ValueError(f"profile of shape {prof.shape}; expected finite numbers of shape "
                                 f"({self.n_steps}, {self.A0.shape[0]}) (one input per sample over the horizon)")
            object.__setattr__(self, "profile", prof)

    def _input(self, k: int) -> NDArray[np.float64]:
        """Additive input of the transition ``k -> k + 1`` (``Bd``, or the profile's row ``k``;
        after the horizon the profile's last row)."""
        if self.profile is None:
            return self.Bd
        return self.profile[min(k, self.n_steps - 1)]

    # ---- frequency domain ----------------------------------------------------------------

    def _fill(self, n0, ln, d0, ld, n: int):
        return (
            np.zeros(n, complex) if n0 is None else np.asarray(n0, complex),
            np.asarray(ln, complex),
            np.ones(n, complex) if d0 is None else np.asarray(d0, complex),
            np.zeros((self.n_gains, n), complex) if ld is None else np.asarray(ld, complex),
        )

    def parts(self) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """``(N0, L, D0, D)`` on the grid, with the defaults of a plain loop filled in."""
        return self._fill(self.N0, self.L, self.D0, self.D, self.omega.size)

    def parts_at(self, omega: NDArray[np.float64]) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """``(N0, L, D0, D)`` at arbitrary frequencies (rad/s); needs ``response``."""
        if self.response is None:
            raise ValueError(f"loop {self.name!r} has no frequency-response function; expected one for off-grid frequencies")
        w = np.atleast_1d(np.asarray(omega, float))
        return self._fill(*self.response(w), w.size)

    @property
    def n_gains(self) -> int:
        """3 (kp, ki, kd) or 4 (and the load feed-forward gain kff)."""
        return len(self.A)

    def gvec(self, gains: Sequence[float]) -> NDArray[np.float64]:
        """Gains padded with zeros to ``n_gains`` entries."""
        g = np.zeros(self.n_gains)
        vals = np.asarray(gains, dtype=float)[: self.n_gains]
        g[: vals.size] = vals
        return g

    def loop_response(self, gains: Sequence[float], omega: NDArray[np.float64] | None = None) -> NDArray[np.complex128]:
        """``L(j omega)`` on the grid, or at ``omega`` (rad/s, needs ``response``)."""
        n0, ln, d0, ld = self.parts() if omega is None else self.parts_at(omega)
        g = self.gvec(gains)
        return (n0 + g @ ln) / (d0 + g @ ld)

    def _peak_grid(self, gains) -> tuple[NDArray[np.float64], NDArray[np.complex128]]:
        """Dense frequencies for the peak search and ``L`` there: a 600-point log grid a decade
        beyond the model's grid (up to Nyquist on sampled loops), the model's grid, and points
        around every closed-loop pole's frequency (where sharp resonance peaks sit), extended
        below the grid while ``|L| < 100`` there. The gain-free parts on the fixed points are
        computed once per loop model."""
        lo = self.omega[0] / 10.0
        hi = self.nyquist if self.nyquist else self.omega[-1] * 10.0
        fixed = self._memo.get("dense")
        if fixed is None:
            w_d = np.logspace(math.log10(lo), math.log10(hi), 600)
            pd = self.parts_at(w_d)
            pm = self.parts()
            fixed = (np.concatenate([w_d, self.omega]),) + tuple(np.concatenate([a, b], axis=-1) for a, b in zip(pd, pm))
            self._memo["dense"] = fixed
        g = self.gvec(gains)
        # Below the model's grid: while |L| < 100 at the low end (|T| not yet within 1 % of its
        # low-frequency limit), the crossover and |S| or |T| peaks may lie lower (a slow plant in
        # a robust set, a low-gain design): extend by decades, at most _LOW_DECADES, 40 points each.
        lo_g = lo
        for _ in range(_LOW_DECADES):
            if not abs(self.loop_response(g, np.array([lo_g]))[0]) < 100.0:
                break
            lo_g /= 10.0
        low = np.logspace(math.log10(lo_g), math.log10(lo), int(round(40 * math.log10(lo / lo_g))) + 1)[:-1]
        lam = self.poles(gains)
        lam = lam[np.abs(lam) > 1e-300]
        wd = np.abs(np.angle(lam)) / self.h
        sig = np.abs(np.log(np.abs(lam))) / self.h
        extra = (wd[:, None] + sig[:, None] * np.array([-2.0, -1.0, -0.5, -0.2, 0.0, 0.2, 0.5, 1.0, 2.0])).ravel()
        extra = np.concatenate([low, extra[(extra > lo_g) & (extra < hi)]])
        w = np.concatenate([fixed[0], extra])
        n0, ln, d0, ld = fixed[1:]
        L = (n0 + g @ ln) / (d0 + g @ ld)
        if extra.size:
            L = np.concatenate([L, self.loop_response(g, extra)])
        w, idx = np.unique(w, return_index=True)
        return w, L[idx]

    def peaks(self, gains: Sequence[float], *, mt: bool = True) -> dict:
        """True peaks of ``|S| = |1/(1+L)|`` and ``|T| = |L/(1+L)|`` (``mt=False``: Ms only,
        no ``mt``/``w_mt`` keys).

        Returns a dict with ``ms``, ``w_ms`` (rad/s), ``mt``, ``w_mt`` (rad/s), ``exact``
        (False when the loop has no ``response`` and only its grid is searched), and the
        dense ``omega``/``L`` used (for margins and plots). Each local maximum within 1 % of
        the largest grid value is polished by a vectorised zoom search in log frequency
        between its grid neighbours (to ~1e-12 in log frequency), so the result is the peak
        to ~1e-12 relative (the dense grid and the closed-loop pole points ensure that every
        peak has a grid neighbour within its width).
        """
        g = self.gvec(gains)
        if self.response is None:
            L = self.loop_response(g)
            s, t = 1 / np.abs(1 + L), np.abs(L / (1 + L))
            return {"ms": float(s.max()), "w_ms": float(self.omega[np.argmax(s)]), "mt": float(t.max()),
                    "w_mt": float(self.omega[np.argmax(t)]), "exact": False, "omega": self.omega, "L": L}
        w, L = self._peak_grid(g)
        out = {"exact": True, "omega": w, "L": L}
        funcs = {"ms": lambda Lv: 1 / np.abs(1 + Lv), "mt": lambda Lv: np.abs(Lv / (1 + Lv))}
        if not mt:
            del funcs["mt"]
        for key, f in funcs.items():
            out[key], out["w_" + key] = _polished_peak(lambda wv: f(self.loop_response(g, wv)), w, f(L))
        return out

    def noise_response(self, gains: Sequence[float], omega: NDArray[np.float64]) -> NDArray[np.complex128]:
        """Noise-to-command transfer ``C F S`` at ``omega`` (rad/s): from a measurement noise
        (output units; a drive loop: rad/s added to the raw encoder-difference speed) to the
        control signal (plant-input units; a drive loop: the torque command, N m); ``F`` is
        every filter on the path (a drive loop: its speed filter and loop filters; a continuous
        loop: its measurement filter, if any) and ``S = 1/(1 + L)``. Needs ``noise``
        (:func:`drive_loop` and :func:`continuous_loop` set it)."""
        if self.noise is None:
            raise ValueError(f"loop {self.name!r} has no noise-gain response; expected a drive_loop or continuous_loop model")
        w = np.atleast_1d(np.asarray(omega, float))
        g = self.gvec(gains)
        return (g @ np.asarray(self.noise(w), complex)) / (1.0 + self.loop_response(g, w))

    def noise_peak(self, gains: Sequence[float]) -> dict:
        """True peak noise gain ``Mks = max |C F S|`` (N m per rad/s; see
        :meth:`noise_response`) up to Nyquist, located like :meth:`peaks` (dense grid refined
        at the closed-loop poles, polished by a zoom search). Returns ``{"mks", "w_mks"}``
        (rad/s). A continuous loop (no Nyquist frequency) is also searched six decades above
        its dense grid, where ``|C F S|`` approaches its high-frequency limit (e.g. ``kp + kd/tf``
        of a PID with a derivative filter and no measurement filter)."""
        g = self.gvec(gains)
        w = self._noise_grid(g)
        mks, w_mks = _polished_peak(lambda wv: np.abs(self.noise_response(g, wv)), w,
                                    np.abs(self.noise_response(g, w)))
        return {"mks": mks, "w_mks": w_mks}

    def _noise_grid(self, g) -> NDArray[np.float64]:
        """The peak grid (:meth:`_peak_grid`), extended six decades up on a continuous loop."""
        w, _ = self._peak_grid(g)
        if self.nyquist is None:
            w = np.concatenate([w, w[-1] * np.logspace(0.0, 6.0, 121)[1:]])
        return w

    def _magnitude(self, g, key: str, w: NDArray[np.float64]) -> NDArray[np.float64]:
        """``|S|`` (``key`` "ms"), ``|T|`` ("mt") or ``|C F S|`` ("mks") at ``w`` (rad/s)."""
        if key == "mks":
            return np.abs(self.noise_response(g, w))
        Lv = self.loop_response(g, w)
        return 1 / np.abs(1 + Lv) if key == "ms" else np.abs(Lv / (1 + Lv))

    def margins(self, gains: Sequence[float], peaks: dict | None = None) -> Margins:
        """Ms, Mt (true peaks, see :meth:`peaks`; pass its result as ``peaks`` to reuse it),
        gain and phase margins and crossover."""
        pk = self.peaks(gains) if peaks is None or "mt" not in peaks else peaks
        m = margins_from_response(pk["omega"], pk["L"])
        return replace(m, ms=max(m.ms, pk["ms"]), mt=max(m.mt, pk["mt"]))

    # ---- time domain ---------------------------------------------------------------------

    def a_cl(self, gains: Sequence[float]) -> NDArray[np.float64]:
        """Closed-loop step matrix ``A0 + sum g_i A_i``."""
        return self.A0 + sum(g * a for g, a in zip(self.gvec(gains), self.A))

    def poles(self, gains: Sequence[float]) -> NDArray[np.complex128]:
        """Eigenvalues of the closed-loop step matrix (discrete poles, sample ``h``)."""
        return np.linalg.eigvals(self.a_cl(gains))

    def spectral_radius(self, gains: Sequence[float]) -> float:
        """Largest closed-loop eigenvalue modulus."""
        return float(np.max(np.abs(self.poles(gains))))

    def is_stable(self, gains: Sequence[float]) -> bool:
        """Asymptotically stable (every closed-loop eigenvalue strictly inside the unit circle)."""
        return self.spectral_radius(gains) < 1.0 - _UNIT_TOL

    def stability(self, gains: Sequence[float]) -> str:
        """``"stable"``, ``"marginal"`` or ``"unstable"`` from the closed-loop eigenvalues.

        Marginal: no eigenvalue outside the unit circle, and those on it (within 1e-9) are
        semisimple (bounded response), e.g. the PID's integral state that P-only (``ki = 0``)
        leaves undriven: the loop settles but keeps a steady error. A repeated eigenvalue on
        the circle with a Jordan block (unbounded ramp) is unstable.

        Examples
        --------
        >>> import control
        >>> lp = continuous_loop(control.tf([1.0], [1.0, 1.0]), tf=0.01, horizon=10.0, n_steps=200)
        >>> lp.stability((1.0, 1.0, 0.0)), lp.stability((1.0, 0.0, 0.0)), lp.stability((0.0, -5.0, 0.0))
        ('stable', 'marginal', 'unstable')
        """
        a = self.a_cl(gains)
        lam = np.linalg.eigvals(a)
        r = np.abs(lam)
        if np.all(r < 1.0 - _UNIT_TOL):
            return "stable"
        if np.any(r > 1.0 + _UNIT_TOL):
            return "unstable"
        on = lam[r >= 1.0 - _UNIT_TOL]
        n = a.shape[0]
        scale = max(1.0, float(np.linalg.norm(a, 2)))
        seen: list = []
        for l0 in on:
            if any(abs(l0 - s) < 1e-6 for s in seen):
                continue
            seen.append(l0)
            m_alg = int(np.sum(np.abs(on - l0) < 1e-6))
            sv = np.linalg.svd(a - l0 * np.eye(n), compute_uv=False)
            if int(np.sum(sv <= 1e-7 * scale)) < m_alg:
                return "unstable"
        return "marginal"

    def error(self, gains: Sequence[float]) -> NDArray[np.float64]:
        """Error sequence e[0..N-1] over the model's horizon (numeric)."""
        return self.trajectory(gains)["error"]

    def objective(self, gains: Sequence[float], kind: str) -> float:
        """Objective over the model's horizon ``n_steps h`` (see :meth:`objective_to_infinity`
        for the integral to infinity that :class:`TuningResult` reports)."""
        return _objective_numeric(self.error(gains), self.h, kind)

    def objectives(self, gains: NDArray[np.float64], kind: str) -> NDArray[np.float64]:
        """Horizon objective for each row of ``gains`` (batched simulation)."""
        g = np.asarray(gains, float)[:, : self.n_gains]
        a = self.A0[None] + np.einsum("bi,ijk->bjk", g, np.stack(self.A))
        x = np.zeros((len(g), self.A0.shape[0]))
        e = np.empty((len(g), self.n_steps))
        for k in range(self.n_steps):
            e[:, k] = x @ self.Ce
            x = np.einsum("bjk,bk->bj", a, x) + self._input(k)
        return np.array([_objective_numeric(row, self.h, kind) for row in e])

    def objective_to_infinity(self, gains: Sequence[float], kind: str, rtol: float = TAIL_RTOL) -> tuple[float, float]:
        """Objective integrated to infinity, and a bound on what it leaves out.

        IE (``h |sum e_k|``) and ISE are exact: with ``x_inf = (I - A)^-1 b`` and zero steady
        error, ``sum e_k = -Ce (I - A)^-1 x_inf`` and ``sum e_k^2 = x_inf' P x_inf`` (discrete
        Lyapunov ``A' P A - P + Ce' Ce = 0``). IAE and ITAE are summed in blocks until the
        Cauchy-Schwarz bound of the tail, ``sqrt(z' P_r z) sqrt(sum r^2k w_k^2)`` with
        ``P_r`` the Lyapunov solution of ``A/r`` (``rho < r < 1``), is below ``rtol`` of the
        sum (or ``2^22`` samples are summed). An unstable or marginal loop, or one with a
        steady error, gives ``(inf, inf)``.

        Returns
        -------
        value : float
            Objective (units of the error integral, e.g. rad for IAE of a speed error).
        tail_bound : float
            Upper bound on the part not summed (0 for IE and ISE).
        """
        if kind not in OBJECTIVES:
            raise ValueError(f"objective = {kind!r}; expected one of {', '.join(OBJECTIVES)}")
        if kind == "ie" and self.profile is not None:
            raise ValueError(f"objective 'ie' on the profile loop {self.name!r}: the signed integral of a duty "
                             "cycle's error cancels between its events; expected iae, itae or ise")
        if self.stability(gains) != "stable":
            return math.inf, math.inf
        a = self.a_cl(gains)
        n = a.shape[0]
        eye = np.eye(n)
        b_end = self._input(self.n_steps)
        x_inf = np.linalg.solve(eye - a, b_end)
        e_inf = float(self.Ce @ x_inf)
        e_hor = self.error(gains)
        if abs(e_inf) > 1e-9 * max(float(np.max(np.abs(e_hor))), 1e-300):
            return math.inf, math.inf
        h = self.h
        # z_k = x_k - x_inf, e_k = Ce z_k: from k = 0 (a step loop starts at z = -x_inf), or,
        # for a profile loop, from the end of the horizon (its samples summed as they are).
        z, k, total = -x_inf, 0, 0.0
        if self.profile is not None:
            x = np.zeros(n)
            for j in range(self.n_steps):
                x = a @ x + self.profile[j]
            z, k = x - x_inf, self.n_steps
            total = _objective_numeric(e_hor, h, kind)
        if kind == "ie":
            return abs(float(-h * self.Ce @ np.linalg.solve(eye - a, x_inf))), 0.0
        if kind == "ise":
            return float(total + h * _gramian_form(a, self.Ce, z)), 0.0
        return _block_sum(a, self.Ce, z, k, total, h, kind, rtol)

    def objective_continuous(self, gains: Sequence[float], kind: str, rtol: float = CONT_RTOL) -> tuple[float, float]:
        """Objective of the CONTINUOUS closed loop (``continuous`` set: :func:`continuous_loop`)
        integrated to infinity, and an estimate of its error.

        The sampled stand-in (:meth:`objective_to_infinity`: ZOH plant, Euler integral, the PID
        held over each sample) differs from the continuous loop by O(h) (0.06 % .. 1 % of the
        IAE on the test plants). Here IE and ISE are closed forms of the continuous loop
        (``Ce A^-1 A^-1 b``, continuous Lyapunov equation); IAE and ITAE sample the exact
        continuous response ``x(k h) = e^{A h} x((k-1) h) + int_0^h e^{A s} ds b`` and sum
        ``h |e_k|`` (the trapezoid rule: ``e(0) = 0`` and the tail vanishes; the tail beyond the
        samples is bounded as in :meth:`objective_to_infinity`), halving ``h`` until two
        successive values agree within ``rtol`` (at most ``_CONT_HALVINGS`` times), and return
        the finer value with the Richardson error estimate ``|I_h/2 - I_h| / 3``.

        Returns
        -------
        value : float
            Objective (``inf`` for an unstable loop).
        error : float
            Estimated absolute error of ``value`` (0 for IE and ISE, up to round-off).
        """
        if self.continuous is None:
            raise ValueError(f"loop {self.name!r} has no continuous closed loop; expected a continuous_loop model")
        if kind not in OBJECTIVES:
            raise ValueError(f"objective = {kind!r}; expected one of {', '.join(OBJECTIVES)}")
        a0, mats, bdc = self.continuous
        g = self.gvec(gains)
        acl = a0 + sum(gi * m for gi, m in zip(g, mats))
        if not np.all(np.isfinite(acl)) or np.max(np.linalg.eigvals(acl).real) >= 0.0:
            return math.inf, math.inf
        x_inf = -np.linalg.solve(acl, bdc)
        if abs(float(self.Ce @ x_inf)) > 1e-9 * max(float(np.max(np.abs(self.error(g)))), 1e-300):
            return math.inf, math.inf  # a steady error
        if kind == "ie":
            return abs(float(self.Ce @ np.linalg.solve(acl, x_inf))), 0.0
        if kind == "ise":
            from scipy.linalg import solve_continuous_lyapunov

            p = solve_continuous_lyapunov(acl.T, -np.outer(self.Ce, self.Ce))
            return float(x_inf @ p @ x_inf), 0.0
        h, prev = self.h, None
        for _ in range(_CONT_HALVINGS + 1):
            val, tail = self._sampled_continuous(acl, bdc, kind, h, min(rtol, TAIL_RTOL))
            if not math.isfinite(val):
                return math.inf, math.inf
            if prev is not None:
                err = abs(val - prev) / 3.0 + tail
                if err <= rtol * val:
                    return val, err
            prev = val
            h /= 2.0
        return val, err

    def _sampled_continuous(self, acl, bdc, kind: str, h: float, rtol: float) -> tuple[float, float]:
        """``h sum |e_k|`` (IAE) or ``h sum t_k |e_k|`` (ITAE) of the continuous loop ``acl``
        sampled exactly every ``h`` s, to infinity (tail bounded below ``rtol``)."""
        ad, bd = _zoh(acl, bdc[:, None], h)
        x_inf = np.linalg.solve(np.eye(ad.shape[0]) - ad, bd[:, 0])
        return _block_sum(ad, self.Ce, -x_inf, 0, 0.0, h, kind, rtol)

    def true_objective(self, gains: Sequence[float], kind: str) -> tuple[float, float]:
        """The objective :class:`TuningResult` reports: the continuous loop's
        (:meth:`objective_continuous`) where the model has one, else the sampled loop's
        (:meth:`objective_to_infinity`, exact for a sampled drive loop). Returns ``(value,
        error)``: the error estimate (continuous) or the tail bound (sampled)."""
        if self.delayed is not None and kind in ("iae", "itae"):
            return self.delayed.objective(self.gvec(gains), kind)
        if self.continuous is not None:
            return self.objective_continuous(gains, kind)
        return self.objective_to_infinity(gains, kind)

    def _smooth_objective(self, gains: Sequence[float], kind: str) -> float:
        """The true objective at a fixed resolution (the model's sample ``h``, tail to 1e-10), a
        smooth function of the gains for finite differences (:func:`_first_order_check`)."""
        if self.delayed is not None and kind in ("iae", "itae"):
            return self.delayed.objective(self.gvec(gains), kind, levels=(self.delayed.m_smooth,))[0]
        if self.continuous is None or kind in ("ie", "ise"):
            return self.true_objective(gains, kind)[0] if self.continuous is not None else \
                self.objective_to_infinity(gains, kind, rtol=1e-10)[0]
        a0, mats, bdc = self.continuous
        acl = a0 + sum(gi * m for gi, m in zip(self.gvec(gains), mats))
        if not np.all(np.isfinite(acl)) or np.max(np.linalg.eigvals(acl).real) >= 0.0:
            return math.inf
        return self._sampled_continuous(acl, bdc, kind, self.h / 2.0, 1e-10)[0]

    def local_peaks(self, gains: Sequence[float], key: str, floor: float) -> list[tuple[float, float]]:
        """Every local maximum of ``|S|`` (``key`` "ms"), ``|T|`` ("mt") or ``|C F S|`` ("mks") at or above ``floor``:
        ``[(value, omega rad/s)]``, each polished like :meth:`peaks` (several near-equal peaks
        make the peak a non-smooth function of the gains; each one is a constraint of its own)."""
        g = self.gvec(gains)
        f = (lambda Lv: 1 / np.abs(1 + Lv)) if key == "ms" else (lambda Lv: np.abs(Lv / (1 + Lv)))
        if key == "mks":  # |C F S|: needs ``noise`` and ``response``
            w = self._noise_grid(g)
            mag = self._magnitude(g, key, w)
        elif self.response is None:
            w, L = self.omega, self.loop_response(g)
            mag = f(L)
        else:
            w, L = self._peak_grid(g)
            mag = f(L)
        left = np.concatenate([[-np.inf], mag[:-1]])
        right = np.concatenate([mag[1:], [-np.inf]])
        cand = np.flatnonzero((mag >= left) & (mag >= right) & (mag >= 0.99 * floor))
        if self.response is None or not cand.size:
            return [(float(mag[i]), float(w[i])) for i in cand if mag[i] >= floor]
        lo = np.log(w[np.maximum(cand - 1, 0)])
        hi = np.log(w[np.minimum(cand + 1, w.size - 1)])
        if key == "mks":
            x, v = _zoom_max(lambda xs: self._magnitude(g, key, np.exp(xs)), lo, hi)
        else:
            x, v = _zoom_max(lambda xs: f(self.loop_response(g, np.exp(xs))), lo, hi)
        out = []
        for i, c in enumerate(cand):
            val, wv = (float(v[i]), float(math.exp(x[i]))) if v[i] > mag[c] else (float(mag[c]), float(w[c]))
            if val >= floor:
                out.append((val, wv))
        return out

    def active_band(self, gains: Sequence[float], key: str, floor: float, n: int = 7,
                    rel: float = 1e-4) -> NDArray[np.float64]:
        """Frequencies (rad/s) near the peaks of ``|S|`` (``key`` "ms"), ``|T|`` ("mt") or ``|C F S|`` ("mks") at or
        above ``floor``: around each such local peak, up to ``n`` points spread over the band
        (+-0.1 in log frequency searched on 401 points) where the magnitude stays within
        ``rel`` of the peak, the peak included. A flat or double peak (the optimum of a peak-constrained
        design often touches the bound at a degenerate point) is then represented by the
        constraint gradients of both its sides (the epsilon-active set of the semi-infinite
        constraint)."""
        g = self.gvec(gains)
        out = []
        for vp, wp in self.local_peaks(g, key, floor):
            if self.response is None:
                out.append(wp)
                continue
            ws = wp * np.exp(np.linspace(-0.1, 0.1, 401))
            inside = ws[self._magnitude(g, key, ws) >= vp * (1 - rel)]
            if inside.size > n:
                inside = inside[np.round(np.linspace(0, inside.size - 1, n)).astype(int)]
            out.extend(list(inside) + [wp])
        return np.unique(np.asarray(out, float))

    def trajectory(self, gains: Sequence[float]) -> dict[str, NDArray[np.float64]]:
        """Error and the named extra outputs over the horizon (deviations from steady state).
        The last few trajectories are kept (the tuner asks for the same gains' objective,
        smoothing scale and reported value in turn); each call returns fresh arrays."""
        key = self.gvec(gains).tobytes()
        memo = self._memo.setdefault("trajectory", {})
        if key not in memo:
            memo[key] = self._trajectory(gains)
            while len(memo) > 4:
                memo.pop(next(iter(memo)))
        return {k: v.copy() for k, v in memo[key].items()}

    def _trajectory(self, gains: Sequence[float]) -> dict[str, NDArray[np.float64]]:
        a = self.a_cl(gains)
        x = np.zeros(self.A0.shape[0])
        xs = np.empty((self.n_steps, x.size))
        for k in range(self.n_steps):
            xs[k] = x
            x = a @ x + self._input(k)
        out = {"error": xs @ self.Ce}
        out.update({name: xs @ row for name, row in self.outputs.items()})
        return out


def _polished_peak(f, w: NDArray[np.float64], mag: NDArray[np.float64]) -> tuple[float, float]:
    """The peak of ``f(omega)`` (a magnitude, vectorised over rad/s) given its values ``mag`` on
    the grid ``w``: the up to six highest local maxima within 1 % of the grid's top, each
    polished by :func:`_zoom_max` between its neighbours. Returns ``(peak, omega)``; the grid's
    top when the search finds nothing higher."""
    top = float(mag.max())
    left = np.concatenate([[-np.inf], mag[:-1]])
    right = np.concatenate([mag[1:], [-np.inf]])
    cand = np.flatnonzero((mag >= left) & (mag >= right) & (mag >= 0.99 * top))
    cand = cand[np.argsort(-mag[cand])][:6]
    lo = np.log(w[np.maximum(cand - 1, 0)])
    hi = np.log(w[np.minimum(cand + 1, w.size - 1)])
    x, v = _zoom_max(lambda xs: f(np.exp(xs)), lo, hi)
    i = int(np.argmax(v)) if v.size else -1
    if v.size and v[i] > top:
        return float(v[i]), float(math.exp(x[i]))
    return top, float(w[np.argmax(mag)])


def _zoom_max(f, lo: NDArray, hi: NDArray, n: int = 41, passes: int = 7) -> tuple[NDArray, NDArray]:
    """Maxima of ``f`` (array in, array out) on the intervals ``[lo, hi]``, vectorised over the
    intervals: ``n`` samples per interval, then the interval shrinks to the two spacings
    around the best sample, ``passes`` times (a factor (n - 1)/2 per pass: 20^7 ~ 1e9, so a
    bracket of 0.05 in log frequency ends below 1e-10)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    if lo.size == 0:
        return lo, lo
    t = np.linspace(0.0, 1.0, n)
    best_x, best_v = lo.copy(), np.full(lo.size, -np.inf)
    for _ in range(passes):
        x = lo[:, None] + (hi - lo)[:, None] * t[None, :]
        v = np.asarray(f(x.ravel()), float).reshape(x.shape)
        i = np.argmax(v, axis=1)
        r = np.arange(lo.size)
        better = v[r, i] > best_v
        best_x = np.where(better, x[r, i], best_x)
        best_v = np.where(better, v[r, i], best_v)
        dx = (hi - lo) / (n - 1)
        lo, hi = np.maximum(x[r, i] - dx, lo), np.minimum(x[r, i] + dx, hi)
    return best_x, best_v


def _block_sum(a: NDArray, ce: NDArray, z: NDArray, k: int, total: float, h: float, kind: str,
               rtol: float) -> tuple[float, float]:
    """IAE or ITAE of ``e_j = ce a^(j-k) z`` from sample ``k`` on, added to ``total``: summed in
    blocks of 256 samples until the Cauchy-Schwarz tail bound (see
    :meth:`LoopModel.objective_to_infinity`) is below ``rtol`` of the sum (or ``2^22``
    samples). Returns ``(value, tail_bound)``."""
    n = a.shape[0]
    rho = float(np.max(np.abs(np.linalg.eigvals(a))))
    r = 0.5 * (1.0 + rho)
    q = r * r
    blk = 256
    rows = np.empty((blk, n))
    row = ce.astype(float).copy()
    for j in range(blk):
        rows[j] = row
        row = row @ a
    a_blk = np.linalg.matrix_power(a, blk)
    gram = _gramian(a / r, ce)
    while True:
        e = rows @ z
        if kind == "iae":
            total += h * float(np.sum(np.abs(e)))
        else:
            total += h * float(np.sum(h * (k + np.arange(blk)) * np.abs(e)))
        k += blk
        z = a_blk @ z
        zz = max(gram(z), 0.0)
        if kind == "iae":
            tail = h * math.sqrt(zz / (1.0 - q))
        else:
            t_n = h * k
            s0, s1, s2 = 1 / (1 - q), q / (1 - q) ** 2, q * (1 + q) / (1 - q) ** 3
            tail = h * math.sqrt(zz * (t_n * t_n * s0 + 2 * t_n * h * s1 + h * h * s2))
        if tail <= rtol * total or k >= _TAIL_MAX_STEPS:
            return total, tail


def _gramian_form(a: NDArray, c: NDArray, z: NDArray) -> float:
    """``sum_k (c a^k z)^2`` for a stable ``a``: ``z' P z`` with ``a' P a - P + c' c = 0``, solved
    on the diagonally balanced ``a`` (states of very different scales) and checked by its
    residual; a poorly solved equation falls back to summing the series (bounded)."""
    return _gramian(a, c)(z)


def _gramian(a: NDArray, c: NDArray) -> Callable:
    """``z -> sum_k (c a^k z)^2`` (see :func:`_gramian_form`), the Lyapunov equation solved once."""
    import warnings

    from scipy.linalg import LinAlgWarning, matrix_balance, solve_discrete_lyapunov

    ab, (tb, _) = matrix_balance(a, permute=False, separate=True)
    cb = c * tb

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LinAlgWarning)
        p = solve_discrete_lyapunov(ab.T, np.outer(cb, cb))
    res = ab.T @ p @ ab - p + np.outer(cb, cb)
    if np.all(np.isfinite(p)) and np.max(np.abs(res)) <= 1e-9 * max(np.max(np.abs(p)), 1e-300):
        return lambda z: float((z / tb) @ p @ (z / tb))

    def series(z):
        zb = z / tb
        total, x = 0.0, zb.copy()  # fallback: sum the series in blocks (bounded budget)
        for _ in range(_TAIL_MAX_STEPS // 64):
            for _ in range(64):
                v = float(cb @ x)
                total += v * v
                x = ab @ x
            if float(x @ x) <= 1e-30 * max(float(zb @ zb), 1e-300):
                break
        return total

    return series


def _objective_numeric(e: NDArray[np.float64], h: float, kind: str) -> float:
    t = h * np.arange(e.size)
    return float(
        {
            "ie": abs(np.sum(e) * h),
            "iae": np.sum(np.abs(e)) * h,
            "itae": np.sum(t * np.abs(e)) * h,
            "ise": np.sum(e * e) * h,
        }[kind]
    )


def _zoh(a: NDArray, b: NDArray, h: float) -> tuple[NDArray, NDArray]:
    """Exact zero-order-hold discretisation (handles stiff modes: e^{lambda h} -> 0)."""
    from scipy.linalg import expm

    n, m = a.shape[0], b.shape[1]
    blk = np.zeros((n + m, n + m))
    blk[:n, :n] = a * h
    blk[:n, n:] = b * h
    e = expm(blk)
    return e[:n, :n], e[:n, n:]


def _freq_grid(w_lo: float, w_hi: float, n: int) -> NDArray[np.float64]:
    return np.logspace(math.log10(w_lo), math.log10(w_hi), n)


def _ss_response(a, b, c, omega, z_of_w=None) -> NDArray[np.complex128]:
    """Frequency response c (sI - a)^-1 b (or (zI - a)^-1 b with z = z_of_w(omega)), vectorised."""
    a = np.asarray(a, float)
    b = np.asarray(b, float).reshape(a.shape[0], -1)[:, :1]
    c = np.asarray(c, float).reshape(1, -1)
    w = np.atleast_1d(np.asarray(omega, float))
    if a.shape[0] == 0:
        return np.zeros(w.size, complex)
    s = np.asarray(z_of_w(w) if z_of_w else 1j * w, complex)
    m = s[:, None, None] * np.eye(a.shape[0]) - a[None]
    x = np.linalg.solve(m, np.broadcast_to(b.astype(complex), (w.size,) + b.shape))
    return (c[None] @ x)[:, 0, 0]


def _resonance_points(lam: NDArray[np.complex128], lo: float, hi: float) -> NDArray[np.float64]:
    """Frequencies (rad/s) at and around continuous poles/zeros ``lam``: |lam| and, for
    lightly damped pairs, the damped frequency with neighbours a damping width apart."""
    lam = lam[np.isfinite(lam) & (np.abs(lam) > 0)]
    pts = [np.abs(lam)]
    wd, sig = np.abs(lam.imag), np.abs(lam.real)
    osc = wd > 0
    pts.append((wd[osc][:, None] + sig[osc][:, None] * np.array([-2.0, -1.0, -0.5, 0.0, 0.5, 1.0, 2.0])).ravel())
    p = np.concatenate(pts) if pts else np.array([])
    return p[(p > lo) & (p < hi)]


def _plant_roots(a, b, c, d) -> tuple[NDArray, NDArray]:
    """Poles and finite transmission zeros of a SISO state-space path."""
    n = a.shape[0]
    poles = np.linalg.eigvals(a) if n else np.array([], complex)
    if n == 0:
        return poles, np.array([], complex)
    m = np.block([[a, b], [c, d]])
    nn = np.zeros_like(m)
    nn[:n, :n] = np.eye(n)
    from scipy.linalg import eigvals

    with np.errstate(all="ignore"):
        z = eigvals(m, nn)
    z = z[np.isfinite(z) & (np.abs(z) < 1e300)]
    return poles, z


def continuous_loop(
    plant,
    *,
    tf: float,
    horizon: float,
    n_steps: int = 2000,
    disturbance: str | int | None = None,
    step: float = 1.0,
    omega: NDArray[np.float64] | None = None,
    filter_order: int = 0,
    filter_tf: float | None = None,
    ideal: bool = False,
    delay: float = 0.0,
    delay_order: int = 6,
) -> LoopModel:
    """Loop model of a continuous SISO LTI plant under a continuous PID.

    Parameters
    ----------
    plant : control.LTI
        Transfer function or state space with the control input first. With two inputs the
        second (or the one named ``disturbance``) is the load disturbance; with one input the
        disturbance enters at the plant input. A pole at 0 that the loop cannot move
        (uncontrollable from the control input or unobservable at the output, e.g. a drifting
        angle state under speed feedback) is refused: remove that state first.
    tf : float, s
        Derivative filter time constant.
    horizon : float, s
        Length of the simulated disturbance response (the tuner adds the tail beyond it).
    n_steps : int
        Samples over the horizon (10 .. 200000); the sample is ``horizon / n_steps`` s.
    disturbance : str or int, optional
        Name or index of the disturbance input.
    step : float
        Disturbance step size (in the disturbance input's units), finite and non-zero.
    omega : array, rad/s, optional
        Frequency grid of the Ms/Mt constraints; by default 600 log-spaced points spanning the
        plant's poles and zeros, refined around each of them.
    filter_order : {0, 1, 2}
        Measurement filter on the whole controller, ``C(s) F(s)``: none (0), ``F = 1/(Tf s + 1)``
        (1) or ``F = 1/(Tf^2 s^2/2 + Tf s + 1)`` (2, as Soltesz-Grimholt-Skogestad / Hast et al.
        and JuliaSim's ``filter_order=2``). The controller acts on the filtered measurement;
        the objective is that of the unfiltered output.
    filter_tf : float, s
        The filter's time constant ``Tf`` (needed with ``filter_order`` 1 or 2).
    ideal : bool
        Ideal derivative ``kd s`` (no derivative filter; ``tf`` then plays no part in the law):
        the derivative of the filtered measurement, or with ``filter_order=0`` that of the
        plant output, which needs a plant of relative degree 2 or more.
    delay : float, s
        Output (equivalently input) delay ``e^{-s delay}`` of the plant. The frequency response
        (Ms, Mt, Mks, margins) uses the exact ``e^{-j omega delay}``; the reported IAE/ITAE
        (:meth:`LoopModel.true_objective`) is that of the loop with the exact delay
        (:class:`_DelayedLoop`); the sampled stand-in the optimiser works on, and IE/ISE, use a
        Pade approximant of order ``delay_order`` in series with the plant (IE is exact for any
        order: it is ``|u_ss|/ki``).
    delay_order : int
        Pade order of the delay in the stand-in (1 .. 10; above ~8 its realisation loses
        accuracy in double precision).

    Returns
    -------
    LoopModel

    Examples
    --------
    >>> import control
    >>> lp = continuous_loop(control.tf([1.0], [1.0, 2.0, 1.0]), tf=0.1, horizon=20.0, n_steps=1000)
    >>> lp.stability((1.0, 0.5, 0.0)), round(lp.objective_to_infinity((1.0, 0.5, 0.0), "ie")[0], 6)
    ('stable', 2.0)
    """
    import control

    tf = _number("tf", tf, lo=0.0, expected="a positive finite time constant in s")
    horizon = _number("horizon", horizon, lo=0.0, expected="a positive finite time in s")
    n_steps = _int_steps("n_steps", n_steps)
    step = _number("step", step, expected="a finite non-zero step size")
    if step == 0.0:
        raise ValueError("step = 0.0; expected a finite non-zero step size")
    filter_order, filter_tf, ideal, delay, delay_order = _check_structure(filter_order, filter_tf, ideal, delay,
                                                                          delay_order)
    sys = control.ss(plant)
    if not sys.isctime():
        raise ValueError(f"plant {sys.name!r} is discrete-time; expected a continuous-time LTI system")
    if sys.noutputs != 1:
        raise ValueError(f"plant has {sys.noutputs} outputs; expected one (SISO feedback path)")
    if sys.ninputs not in (1, 2):
        raise ValueError(f"plant has {sys.ninputs} inputs; expected the control input plus at most a disturbance")
    d_idx = 0
    if disturbance is not None:
        try:
            d_idx = sys.input_labels.index(disturbance) if isinstance(disturbance, str) else int(disturbance)
        except ValueError:
            raise ValueError(f"disturbance = {disturbance!r}; expected one of {sys.input_labels}") from None
        if not 0 <= d_idx < sys.ninputs:
            raise ValueError(f"disturbance = {disturbance!r}; expected an input index below {sys.ninputs}")
    elif sys.ninputs == 2:
        d_idx = 1
    a, b, c, d = (np.asarray(m, dtype=float) for m in (sys.A, sys.B, sys.C, sys.D))
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b)) and np.all(np.isfinite(c)) and np.all(np.isfinite(d))):
        raise ValueError("plant matrices contain inf or NaN; expected finite numbers")
    if np.any(d[:, 0] != 0):
        raise ValueError("plant has direct feed-through from the control input; expected a strictly proper plant")
    if d[0, d_idx] != 0:
        raise ValueError("disturbance feeds through to the output directly; expected a strictly proper path")
    n = a.shape[0]
    if n == 0:
        raise ValueError("plant has no states (zero or a static gain); expected a strictly proper plant with dynamics")
    if n:
        # Balance (diagonal similarity) so that companion forms with widely spread
        # coefficients (fast Pade delays, 1e-6 s lags) discretise and solve accurately.
        from scipy.linalg import matrix_balance

        a, (tb, _) = matrix_balance(a, permute=False, separate=True)
        b = b / tb[:, None]
        c = c * tb[None, :]
    c_plant = c
    delayed = None
    if delay > 0:
        delayed = _delayed_loop(a, b, c, d_idx, step, tf, ideal, filter_order, filter_tf, delay, horizon)
    # The delay's Pade model and the measurement filter in series with the plant output (extra
    # plant states): c is then the row of the output the controller measures, c_err that of the
    # (delayed, unfiltered) output the objective integrates; without them both are c.
    a, b, c, c_err = _series_output(a, b, c, delay, delay_order, filter_order, filter_tf)
    n = a.shape[0]
    h = horizon / n_steps
    ad, bd_all = _zoh(a, b, h)
    bu, bdist = bd_all[:, :1], bd_all[:, d_idx : d_idx + 1]
    gam = math.exp(-h / tf)
    # Closed-loop state X = [x, I (integral of e), z (derivative filter state)], e = -y.
    N = n + 2
    A0 = np.zeros((N, N))
    A0[:n, :n] = ad
    A0[n, :n] = -h * c[0]
    A0[n, n] = 1.0
    A0[n + 1, :n] = -(1 - gam) * c[0]
    A0[n + 1, n + 1] = gam
    ce = np.zeros(N)
    ce[:n] = -c[0]
    # u = kp e + ki I + kd (e - z)/tf (ideal: kd de/dt, a row over the plant states)
    d_row = _ideal_derivative_row(a, b, c, N) if ideal else (ce - np.eye(N)[n + 1]) / tf
    a_kp = np.zeros((N, N))
    a_kp[:n, :] = bu @ ce[None, :]
    a_ki = np.zeros((N, N))
    a_ki[:n, n] = bu[:, 0]
    a_kd = np.zeros((N, N))
    a_kd[:n, :] = bu @ d_row[None, :]
    bdv = np.zeros(N)
    bdv[:n] = bdist[:, 0] * step
    ce_obj = ce
    if c_err is not c:
        ce_obj = np.zeros(N)
        ce_obj[:n] = -c_err[0]
    poles, zeros = _plant_roots(a, b[:, :1], c, d[:, :1])
    if omega is None:
        mags = np.abs(np.concatenate([poles, zeros]))
        mags = mags[(mags > 0) & np.isfinite(mags)]
        mags = mags if mags.size else np.array([1.0 / tf])
        lo = min(mags.min(), 2 * math.pi / horizon) / 100
        hi = max(mags.max(), 1 / tf) * 100
        omega = np.unique(np.concatenate([_freq_grid(lo, hi, 600), _resonance_points(np.concatenate([poles, zeros]), lo, hi)]))
    else:
        omega = np.asarray(omega, float)
        if omega.ndim != 1 or omega.size < 2 or not np.all(np.isfinite(omega)) or np.any(omega <= 0) or np.any(np.diff(omega) <= 0):
            raise ValueError("omega must be an increasing 1-D array of positive finite frequencies (rad/s)")

    b_u = b[:, :1].copy()
    exact = delay > 0 or filter_order > 0 or ideal
    a_p, b_p = a[: c_plant.shape[1], : c_plant.shape[1]].copy(), b_u[: c_plant.shape[1]].copy()

    def deriv(jw):
        return jw if ideal else jw / (1 + jw * tf)

    def response(w):
        jw = 1j * np.asarray(w, float)
        if not exact:
            p_u = _ss_response(a, b_u, c, w)
            return None, np.vstack([p_u, p_u / jw, p_u * jw / (1 + jw * tf)]), None, None
        # Exact: the plant's own response, e^{-j w delay} and the filter (no Pade in frequency).
        p_u = _ss_response(a_p, b_p, c_plant, w) * np.exp(-jw * delay) * _filter_response(filter_order, filter_tf, jw)
        return None, np.vstack([p_u, p_u / jw, p_u * deriv(jw)]), None, None

    # The continuous closed loop itself, same state: x' = a x + b u + b_d d, I' = e, z' = (e - z)/tf.
    c0 = np.zeros((N, N))
    c0[:n, :n] = a
    c0[n] = ce
    c0[n + 1] = ce / tf
    c0[n + 1, n + 1] = -1.0 / tf
    c_kp, c_ki, c_kd = (np.zeros((N, N)) for _ in range(3))
    c_kp[:n] = b[:, :1] @ ce[None, :]
    c_ki[:n, n] = b[:, 0]
    c_kd[:n] = b[:, :1] @ d_row[None, :]
    c_bd = np.zeros(N)
    c_bd[:n] = b[:, d_idx] * step
    L = response(omega)[1]

    def noise(w):  # the controller per unit gain, filter included: u = C F (-(y + noise))
        jw = 1j * np.asarray(w, float)
        f = _filter_response(filter_order, filter_tf, jw) if filter_order else 1.0
        return np.vstack([np.ones_like(jw) * f, f / jw, f * deriv(jw)])

    return LoopModel(A0, (a_kp, a_ki, a_kd), bdv, ce_obj, h, n_steps, omega, L, tf, name=sys.name, response=response,
                     continuous=(c0, (c_kp, c_ki, c_kd), c_bd), noise=noise, delayed=delayed)


#: Delay-line samples per delay of the exact delayed simulation: the halving sequence (each level
#: doubles them) and the fixed level of the first-order check's smooth objective.
_DELAY_LEVELS = (8, 16, 32, 64, 128, 256, 512, 1024)
_DELAY_SMOOTH = 64
#: Largest number of samples one delayed simulation may take (budget).
_DELAY_MAX_STEPS = 1 << 21


class _DelayedLoop:
    """The continuous closed loop with the plant's EXACT output delay ``L``:
    ``X' = M(g) X + Q(g) x(t - L) + b_d`` over ``X = [x (plant), f (measurement filter), I, z]``,
    error ``e(t) = -c x(t - L)``, from rest (``x(t) = 0`` for ``t <= 0``).

    Simulated exactly up to the interpolation of the delayed state: the step is ``h = L/m``
    (so the delay is exactly ``m`` samples) and the delayed input ``Q x(t - L)`` is linear
    between its samples (first-order hold, integrated exactly with one matrix exponential):
    O(h^2). :meth:`objective` doubles ``m`` along ``_DELAY_LEVELS`` until two successive IAE/ITAE
    agree within ``rtol`` and returns the finer value with the Richardson estimate
    ``|I_h/2 - I_h|/3`` (trapezoid rule on the samples; the kinks of ``e`` at multiples of ``L``
    fall on samples). It runs in blocks (at least one delay and 1/16 of the stand-in's horizon)
    until the blocks decay geometrically and the geometric tail of the last ratio is below 1e-7
    of the sum (an estimate, not a bound), within ``_DELAY_MAX_STEPS`` samples."""

    def __init__(self, m0, mg, q0, qg, bd, c, delay: float, horizon: float) -> None:
        self.m0, self.mg, self.q0, self.qg, self.bd, self.c = m0, mg, q0, qg, bd, c
        self.delay, self.horizon = delay, horizon
        self.m_smooth = _DELAY_SMOOTH
        self._memo: dict = {}

    def _value(self, g, kind: str, m: int) -> tuple[float, float]:
        """IAE/ITAE to infinity at ``m`` samples per delay, and the estimated tail."""
        from scipy.linalg import expm

        key = (g.tobytes(), kind, m)
        if key in self._memo:
            return self._memo[key]
        mm = self.m0 + sum(gi * a for gi, a in zip(g, self.mg))
        qq = self.q0 + sum(gi * a for gi, a in zip(g, self.qg))
        N, n = mm.shape[0], qq.shape[1]
        h = self.delay / m
        big = np.zeros((3 * N, 3 * N))
        big[:N, :N], big[:N, N : 2 * N], big[N : 2 * N, 2 * N :] = mm * h, np.eye(N) * h, np.eye(N) * h
        e = expm(big)
        phi, psi0, psi1 = e[:N, :N], e[:N, N : 2 * N], e[:N, 2 * N :] / h  # psi1 = int e^{Mr}(h - r) dr / h
        p0, p1 = psi0 - psi1, psi1
        hist = [np.zeros((1, n))]  # x_j, j = 0 .. k (plant part)
        X = np.zeros(N)
        total, prev_b, k = 0.0, None, 0
        ratios: list = []
        out = (math.inf, math.inf)
        # Blocks of one delay (m steps): the delayed input of the block is known from the past.
        per = max(1, int(math.ceil(self.horizon / 16.0 / self.delay)))  # delays per ratio block
        acc, n_acc = 0.0, 0
        while k < _DELAY_MAX_STEPS:
            past = np.arange(k - m, k + 1)  # x(t - L) at the block's m + 1 sample times
            xd = np.zeros((m + 1, n))
            ok = past >= 0
            if np.any(ok):
                allx = np.vstack(hist)  # rows: x_j for j = k + 1 - len .. k
                xd[ok] = allx[past[ok] - (k + 1 - allx.shape[0])]
            v = xd @ qq.T + self.bd
            gin = v[:-1] @ p0.T + v[1:] @ p1.T
            xs = np.empty((m + 1, N))
            xs[0] = X
            for j in range(m):
                X = phi @ X + gin[j]
                xs[j + 1] = X
            if not np.all(np.isfinite(X)) or np.abs(X).max() > 1e150:
                break
            # e(t) = -c x(t - L): the IAE is that of c x; for the ITAE its time is t + L.
            y = np.abs(xs[:-1, :n] @ self.c)
            tk = np.arange(k, k + m) * h + self.delay
            acc += h * float(np.sum(y if kind == "iae" else tk * y))
            hist.append(xs[1:, :n])
            hist = hist[-2:]  # the last delay (and more) is all the next block needs
            k += m
            n_acc += 1
            if n_acc < per:
                continue
            b, acc, n_acc = acc, 0.0, 0
            total += b
            if prev_b is not None and prev_b > 0:
                ratios.append(b / prev_b)
            prev_b = b
            if len(ratios) >= 3 and max(ratios[-3:]) < 1.0 and k * h > self.horizon / 4:
                r = max(ratios[-3:])
                tail = b * r / (1.0 - r)
                if tail <= 1e-7 * total:
                    out = (total, tail)
                    break
        self._memo[key] = out
        return out

    def objective(self, g, kind: str, rtol: float = CONT_RTOL, levels=None) -> tuple[float, float]:
        """IAE or ITAE of the exact delayed loop and its error estimate (Richardson over
        successive levels of ``_DELAY_LEVELS``; with ``levels``, over those, or the one value)."""
        g = np.asarray(g, float)
        levels = _DELAY_LEVELS if levels is None else levels
        prev, val, err = None, math.inf, 0.0
        for m in levels:
            val, tail = self._value(g, kind, m)
            if not math.isfinite(val):
                return math.inf, math.inf
            if prev is not None:
                err = abs(val - prev) / 3.0 + tail
                if err <= rtol * val:
                    return val, err
            prev = val
        return val, err


def _delayed_loop(a, b, c, d_idx: int, step: float, tf: float, ideal: bool, filter_order: int, filter_tf,
                  delay: float, horizon: float) -> _DelayedLoop:
    """The loop of :func:`continuous_loop` with the exact delay on the plant output (see
    :class:`_DelayedLoop`); ``a, b, c`` the balanced plant without the delay or the filter."""
    n = a.shape[0]
    if filter_order:
        af, bf, cf = _filter_ss(filter_order, filter_tf)
    else:
        af, bf, cf = np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0))
    nf = af.shape[0]
    N = n + nf + 2
    i_i, i_z = n + nf, n + nf + 1
    E, Ed = np.zeros(N), np.zeros(n)  # the measured error em = E X + Ed x(t - L)
    if filter_order:
        E[n : n + nf] = -cf[0]
    else:
        Ed = -c[0].copy()
    ez = np.eye(N)[i_z]
    if ideal and filter_order:  # d em/dt = -cf (af f + bf c x(t - L))
        DX, Dx = np.zeros(N), -float(cf[0] @ bf[:, 0]) * c[0]
        DX[n : n + nf] = -(cf[0] @ af)
    elif ideal:  # -c a x(t - L) (relative degree 2 or more, checked by the stand-in)
        DX, Dx = np.zeros(N), -(c[0] @ a)
    else:
        DX, Dx = (E - ez) / tf, Ed / tf
    m0 = np.zeros((N, N))
    m0[:n, :n] = a
    m0[n : n + nf, n : n + nf] = af
    m0[i_i] = E
    m0[i_z] = (E - ez) / tf
    q0 = np.zeros((N, n))
    q0[n : n + nf] = bf @ c
    q0[i_i] = Ed
    q0[i_z] = Ed / tf
    mg, qg = [], []
    for row_x, row_d in ((E, Ed), (np.eye(N)[i_i], np.zeros(n)), (DX, Dx)):
        mk, qk = np.zeros((N, N)), np.zeros((N, n))
        mk[:n] = np.outer(b[:, 0], row_x)
        qk[:n] = np.outer(b[:, 0], row_d)
        mg.append(mk)
        qg.append(qk)
    bd = np.zeros(N)
    bd[:n] = b[:, d_idx] * step
    return _DelayedLoop(m0, tuple(mg), q0, tuple(qg), bd, c[0].copy(), delay, horizon)


def _check_structure(filter_order, filter_tf, ideal, delay, delay_order):
    """The loop-structure arguments of :func:`continuous_loop` checked (ValueError naming one)."""
    if isinstance(filter_order, bool) or filter_order not in (0, 1, 2):
        raise ValueError(f"filter_order = {filter_order!r}; expected 0 (none), 1 or 2")
    if filter_order:
        filter_tf = _number("filter_tf", filter_tf, lo=0.0, expected="a positive finite time constant in s")
    if not isinstance(ideal, (bool, np.bool_)):
        raise ValueError(f"ideal = {ideal!r}; expected True or False")
    delay = _number("delay", delay, lo=0.0, lo_open=False, expected="a finite delay >= 0 s")
    if isinstance(delay_order, bool) or not isinstance(delay_order, numbers.Integral) or not 1 <= delay_order <= 10:
        raise ValueError(f"delay_order = {delay_order!r}; expected an integer in [1, 10]")
    return int(filter_order), filter_tf, bool(ideal), delay, int(delay_order)


def _filter_ss(order: int, t: float) -> tuple[NDArray, NDArray, NDArray]:
    """State space ``(A, B, C)`` of the measurement filter 1/(t s + 1) or 1/(t^2 s^2/2 + t s + 1)."""
    if order == 1:
        return np.array([[-1.0 / t]]), np.array([[1.0 / t]]), np.array([[1.0]])
    return (np.array([[0.0, 1.0], [-2.0 / (t * t), -2.0 / t]]), np.array([[0.0], [2.0 / (t * t)]]),
            np.array([[1.0, 0.0]]))


def _filter_response(order: int, t: float | None, jw) -> NDArray[np.complex128]:
    """``F(j omega)`` of the measurement filter (1 without one)."""
    if not order:
        return np.ones_like(jw)
    return 1.0 / (t * jw + 1.0) if order == 1 else 1.0 / (t * t * jw * jw / 2.0 + t * jw + 1.0)


def _series_output(a, b, c, delay: float, delay_order: int, filter_order: int, filter_tf):
    """The plant ``(a, b, c)`` with the delay's Pade model and the measurement filter in series
    with its output: ``(a, b, c_measured, c_objective)`` (the last is ``c`` itself, the same
    object, when neither is present)."""
    c_err = c
    if delay > 0:
        import control

        num, den = control.pade(delay, delay_order)
        pd = control.ss(control.tf(num, den))
        ap, bp, cp, dp = (np.asarray(m, float) for m in (pd.A, pd.B, pd.C, pd.D))
        from scipy.linalg import matrix_balance

        ap, (tp, _) = matrix_balance(ap, permute=False, separate=True)
        bp, cp = bp / tp[:, None], cp * tp[None, :]
        a, b, c = _cascade(a, b, c, ap, bp, cp, float(dp[0, 0]))
        c_err = c
    if filter_order:
        af, bf, cf = _filter_ss(filter_order, filter_tf)
        a, b, c_meas = _cascade(a, b, c, af, bf, cf, 0.0)
        return a, b, c_meas, np.hstack([c, np.zeros((1, af.shape[0]))])
    return a, b, c, c_err


def _cascade(a, b, c, a2, b2, c2, d2: float):
    """``(a, b, c)`` followed by ``(a2, b2, c2, d2)`` on its output: the series system's matrices."""
    n, m = a.shape[0], a2.shape[0]
    big = np.zeros((n + m, n + m))
    big[:n, :n] = a
    big[n:, :n] = b2 @ c
    big[n:, n:] = a2
    return big, np.vstack([b, np.zeros((m, b.shape[1]))]), np.hstack([d2 * c, c2])


def _ideal_derivative_row(a, b, c, n_total: int) -> NDArray[np.float64]:
    """The error's time derivative ``-c (a x + b u)`` as a row over the closed-loop state, which
    needs ``c b = 0`` (relative degree 2 or more from the control input to the measurement)."""
    if abs(float(c[0] @ b[:, 0])) > 1e-12 * max(float(np.abs(c).max() * np.abs(b).max()), 1e-300):
        raise ValueError("ideal = True on a measurement of relative degree 1 (the ideal derivative feeds the "
                         "control input through); expected a measurement filter (filter_order=1 or 2) or a plant "
                         "of relative degree 2 or more")
    row = np.zeros(n_total)
    row[: a.shape[0]] = -(c[0] @ a)
    return row


def _pid_rows(n_state: int, i_u: int, i_i: int, e_meas, d_new, ts: float, ref=None, weight: float = 1.0):
    """Gain matrices of the sampled PID ``u = kp e + I - kd d``, ``I += Ts ki e``: rows ``e_meas``
    (error) and ``d_new`` (filtered derivative) over the loop state; shared by every drive loop
    so that they all run the law :func:`prsa_ctrl.sim.engine.simulate` runs.

    With a reference row ``ref`` (the setpoint deviation held in the loop state), the 2-DOF law
    ``u = kp (b r - y) + I - kd d``, ``I += Ts ki (r - y)`` with setpoint weight ``b = weight``
    (``e_meas`` is then ``-y``): still affine in the gains."""
    a_kp = np.zeros((n_state, n_state))
    a_kp[i_u] = e_meas
    a_ki = np.zeros((n_state, n_state))
    a_ki[i_i] = ts * e_meas
    a_kd = np.zeros((n_state, n_state))
    a_kd[i_u] = -d_new
    if ref is not None:
        a_kp[i_u] = a_kp[i_u] + weight * np.asarray(ref, float)
        a_ki[i_i] = a_ki[i_i] + ts * np.asarray(ref, float)
    return a_kp, a_ki, a_kd


def _pid_frequency_parts(zi, ts: float, beta: float) -> list:
    """Frequency responses of the same law per unit kp, ki, kd (``zi = exp(-j w Ts)``), acting
    on the measured speed."""
    return [np.ones_like(zi), ts * zi / (1 - zi), (1 - beta) * (1 - zi) / (ts * (1 - beta * zi))]


def drive_loop(
    a: NDArray,
    b: NDArray,
    c_speed: NDArray,
    angle_index: int,
    *,
    ts: float,
    speed_filter: float,
    tf: float,
    horizon: float,
    step: float | None = None,
    omega: NDArray[np.float64] | None = None,
    name: str = "drive",
    outputs: dict[str, NDArray] | None = None,
    load_sequence: NDArray[np.float64] | None = None,
    setpoint_sequence: NDArray[np.float64] | None = None,
    setpoint_weight: float = 1.0,
    filters: Sequence = (),
) -> LoopModel:
    """Loop model of the sampled drive (see module docstring) around a continuous linear plant.

    Parameters
    ----------
    a, b : arrays
        Continuous plant with inputs (torque command N m, axial load N); one state is the nut
        angle (rad), which the encoder measures.
    c_speed : array
        Row picking the nut speed (rad/s), the performance output.
    angle_index : int
        Index of the nut-angle state. The angle itself drifts (a pure integrator that nothing
        feeds back on), so the loop keeps only its increment over the last sample, which is
        what the backward-difference speed estimate uses.
    ts : float, s
        Controller sample time.
    speed_filter : float, s
        First-order speed-filter time constant.
    tf : float, s
        Derivative filter time constant.
    horizon : float, s
        Response length the tuner simulates (it adds the tail beyond it).
    step : float, N
        Load step size (a step loop; leave it out for a duty-cycle loop).
    omega : array, rad/s, optional
        Constraint grid; by default 500 log-spaced points from 0.1 rad/s to the Nyquist
        frequency ``pi/ts``, plus points at and around the sampled plant's resonances.
    load_sequence : array, N, optional
        Duty cycle: the load's deviation from its t = 0 value averaged over each sample
        interval ``[k Ts, (k + 1) Ts)``, one per sample of the horizon (``round(horizon/ts)``).
        The zero-order-hold input of the mean is exact for the integral of the load over the
        sample, so a step between samples or a ramp enters with its exact impulse.
    setpoint_sequence : array, rad/s, optional
        Duty cycle: the setpoint's deviation from its t = 0 value as the controller reads it at
        each sample ``k = 0 .. n_steps`` (first entry 0). The loop then carries the reference
        as a state and its error is the tracking error ``r - speed``.
    setpoint_weight : float
        2-DOF setpoint weight ``b`` in [0, 1] on the proportional path,
        ``u = kp (b r - y) + I``, ``I += Ts ki (r - y)`` (1: the plain PID).
    filters : sequence of LoopFilter or (place, DiscreteBiquad) pairs
        Loop filters run as the sampled simulator runs them: ``speed_measurement`` biquads on
        the filtered speed before the PID, ``torque_command`` biquads on the PID's command
        before the computation delay (each with 4 states, direct form I). A ``LoopFilter`` is
        discretised at ``ts``.

    Returns
    -------
    LoopModel
        Sampled (``nyquist = pi/ts``) with an exact frequency-response function; a profile
        loop (``profile`` set) with one of the sequences.

    Examples
    --------
    A 0.01 kg m^2 inertia (speed state, angle state) at Ts = 1 ms:

    >>> import numpy as np
    >>> a = np.array([[0.0, 0.0], [1.0, 0.0]]); b = np.array([[100.0, -100.0], [0.0, 0.0]])
    >>> lp = drive_loop(a, b, np.array([1.0, 0.0]), 1, ts=1e-3, speed_filter=1e-3, tf=4e-3, horizon=0.2, step=1.0)
    >>> lp.nyquist == np.pi / 1e-3, lp.stability((0.5, 20.0, 0.0))
    (True, 'stable')
    """
    ts = _number("ts", ts, lo=0.0, expected="a positive finite sample time in s")
    speed_filter = _number("speed_filter", speed_filter, lo=0.0, expected="a positive finite time constant in s")
    tf = _number("tf", tf, lo=0.0, expected="a positive finite time constant in s")
    horizon = _number("horizon", horizon, lo=0.0, expected="a positive finite time in s")
    duty = load_sequence is not None or setpoint_sequence is not None
    if duty:
        step = 0.0 if step is None else _number("step", step, expected="a finite step size in N")
    elif step is None:
        raise ValueError("step = None; expected a load step size in N (or a load_sequence / setpoint_sequence)")
    else:
        step = _number("step", step, expected="a finite step size in N")
    n_steps = max(10, int(round(horizon / ts)))
    if n_steps > MAX_STEPS:
        raise ValueError(f"horizon = {horizon!r} s is {n_steps} samples of {ts:g} s; expected at most {MAX_STEPS}")
    b_w = _number("setpoint_weight", setpoint_weight, lo=0.0, hi=1.0, lo_open=False, hi_open=False,
                  expected="a setpoint weight b in [0, 1]")
    seq_d = seq_r = None
    if load_sequence is not None:
        seq_d = np.asarray(load_sequence, float)
        if seq_d.shape != (n_steps,) or not np.all(np.isfinite(seq_d)):
            raise ValueError(f"load_sequence of shape {seq_d.shape}; expected {n_steps} finite loads in N "
                             f"(one per sample of the {horizon:g} s horizon)")
    if setpoint_sequence is not None:
        seq_r = np.asarray(setpoint_sequence, float)
        if seq_r.shape != (n_steps + 1,) or not np.all(np.isfinite(seq_r)) or seq_r[0] != 0.0:
            raise ValueError(f"setpoint_sequence of shape {seq_r.shape}; expected {n_steps + 1} finite setpoint "
                             "deviations in rad/s starting at 0 (one per sample, both ends included)")
    fl = _loop_biquads(filters, ts)
    ad_full, bd_full = _zoh(np.asarray(a, float), np.asarray(b, float), ts)
    rest = [i for i in range(ad_full.shape[0]) if i != angle_index]
    ad = ad_full[np.ix_(rest, rest)]
    bu, bdist = bd_full[rest, 0], bd_full[rest, 1]
    inc_x, inc_u, inc_d = ad_full[angle_index, rest], bd_full[angle_index, 0], bd_full[angle_index, 1]
    n = len(rest)
    c_w = np.asarray(c_speed, float).ravel()[rest]
    alpha = math.exp(-ts / speed_filter)
    beta = math.exp(-ts / tf)
    # X = [x (without the angle), angle increment over the last sample, w_f, dfilt, I, u_pending]
    i_th, i_wf, i_d, i_i, i_u = n, n + 1, n + 2, n + 3, n + 4
    i_r = n + 5  # reference (setpoint deviation) state of a setpoint duty cycle
    i_f = n + 5 + (seq_r is not None)  # 4 states per loop filter: x1, x2, y1, y2
    N = i_f + 4 * len(fl)
    E = np.eye(N)
    w_m = E[i_th] / ts  # backward-difference speed
    w_f_new = alpha * E[i_wf] + (1 - alpha) * w_m
    filt_rows: dict[int, NDArray] = {}  # state index -> its next-value row (gain-free filters)
    w_pid, w_pid_prev = w_f_new, E[i_wf]
    for j, (place, bq) in enumerate(fl):
        if place == "speed_measurement":
            k = i_f + 4 * j
            y = bq.b0 * w_pid + bq.b1 * E[k] + bq.b2 * E[k + 1] - bq.a1 * E[k + 2] - bq.a2 * E[k + 3]
            filt_rows.update({k: w_pid, k + 1: E[k], k + 2: y, k + 3: E[k + 2]})
            w_pid, w_pid_prev = y, E[k + 2]
    d_new = beta * E[i_d] + (1 - beta) * (w_pid - w_pid_prev) / ts
    e_meas = -w_pid
    A0 = np.zeros((N, N))
    A0[:n, :n] = ad
    A0[:n, i_u] = bu
    A0[i_th, :n] = inc_x
    A0[i_th, i_u] = inc_u
    A0[i_wf] = w_f_new
    A0[i_d] = d_new
    A0[i_i, i_i] = 1.0
    A0[i_u, i_i] = 1.0  # u = kp e + I - kd d
    a_kp, a_ki, a_kd = _pid_rows(N, i_u, i_i, e_meas, d_new, ts, ref=E[i_r] if seq_r is not None else None,
                                 weight=b_w)
    for k, row in filt_rows.items():
        A0[k] = row
    mats = (A0, a_kp, a_ki, a_kd)
    cmd = [m[i_u].copy() for m in mats]  # the PID's command, one row per (gain-free, kp, ki, kd) part
    for j, (place, bq) in enumerate(fl):
        if place == "torque_command":
            k = i_f + 4 * j
            for part, m in zip(cmd, mats):
                m[k] = part
            A0[k + 1], A0[k + 3] = E[k], E[k + 2]
            rest_row = bq.b1 * E[k] + bq.b2 * E[k + 1] - bq.a1 * E[k + 2] - bq.a2 * E[k + 3]
            cmd = [bq.b0 * part + (rest_row if q == 0 else 0.0) for q, part in enumerate(cmd)]
            for part, m in zip(cmd, mats):
                m[k + 2] = part
    for part, m in zip(cmd, mats):
        m[i_u] = part
    bdv = np.zeros(N)
    bdv[:n] = bdist * step
    bdv[i_th] = inc_d * step
    ce = np.zeros(N)
    ce[:n] = -c_w
    profile = None
    if duty:
        # Per-sample inputs; Bd becomes the representative step (largest deviation from t = 0).
        profile = np.zeros((n_steps, N))
        if seq_d is not None:
            profile[:, :n] = seq_d[:, None] * bdist[None, :]
            profile[:, i_th] = seq_d * inc_d
            big = float(seq_d[np.argmax(np.abs(seq_d))])
            bdv[:n], bdv[i_th] = bdist * big, inc_d * big
        if seq_r is not None:
            profile[:, i_r] = seq_r[1:]
            ce[i_r] = 1.0
            bdv[i_r] = float(seq_r[np.argmax(np.abs(seq_r))])
    nyq = math.pi / ts
    if omega is None:
        lam = np.linalg.eigvals(ad) if n else np.array([], complex)
        lam = lam[np.abs(lam) > 1e-300]
        cont = np.log(lam.astype(complex)) / ts  # continuous-equivalent poles
        omega = np.unique(np.concatenate([_freq_grid(1e-1, nyq * 0.999, 500), _resonance_points(cont, 1e-1, nyq * 0.999)]))
    def response(w):
        w = np.asarray(w, float)
        zi = np.exp(-1j * w * ts)
        # Torque command -> angle increment: z^-1 (inc_x (zI - Ad)^-1 bu + inc_u).
        p_inc = zi * (_ss_response(ad, bu[:, None], inc_x[None, :], w, lambda x: np.exp(1j * x * ts)) + inc_u)
        meas = (1 - alpha) / (1 - alpha * zi) / ts
        f_loop = _filters_response(fl, w)
        base = zi * meas * p_inc * f_loop  # computation delay, filters, backward difference, plant
        return None, np.vstack([base * c for c in _pid_frequency_parts(zi, ts, beta)]), None, None

    def noise(w):
        w = np.asarray(w, float)
        zi = np.exp(-1j * w * ts)
        f_all = (1 - alpha) / (1 - alpha * zi) * _filters_response(fl, w)
        return np.vstack([f_all * c for c in _pid_frequency_parts(zi, ts, beta)])

    L = response(omega)[1]
    extra = {
        k: np.concatenate([np.asarray(r, float).ravel()[rest], np.zeros(N - n)]) for k, r in (outputs or {}).items()
    }
    return LoopModel(A0, (a_kp, a_ki, a_kd), bdv, ce, ts, n_steps, omega, L, tf, name=name, outputs=extra,
                     response=response, nyquist=nyq, profile=profile, noise=noise)


def _loop_biquads(filters, ts: float) -> list:
    """``[(place, DiscreteBiquad)]`` from LoopFilter items or ``(place, DiscreteBiquad)`` pairs."""
    from ..drive.filters import PLACES, DiscreteBiquad, LoopFilter

    out = []
    for item in filters or ():
        if isinstance(item, LoopFilter):
            out.append((item.place, item.biquad(ts)))
        elif isinstance(item, tuple) and len(item) == 2 and item[0] in PLACES and isinstance(item[1], DiscreteBiquad):
            if abs(item[1].ts - ts) > 1e-12 * ts:
                raise ValueError(f"filter biquad at ts = {item[1].ts!r} s; expected the loop's sample time {ts!r} s")
            out.append(item)
        else:
            raise ValueError(f"filter = {item!r}; expected a LoopFilter or a (place, DiscreteBiquad) pair")
    return out


def _filters_response(fl: list, w: NDArray[np.float64]) -> NDArray[np.complex128]:
    """Product of the loop filters' frequency responses at ``w`` (rad/s)."""
    out = np.ones(np.shape(w), complex)
    for _, bq in fl:
        out = out * bq.frequency_response(w)
    return out


@dataclass
class TuningResult:
    """Outcome of a tuning run.

    Attributes
    ----------
    pid : PID
        Tuned gains (SI units of the loop).
    objective : float
        Objective of ``pid`` integrated to infinity (weighted sum or worst case over the
        loops): for a continuous loop that of the continuous closed loop to a relative
        ``CONT_RTOL`` (:meth:`LoopModel.objective_continuous`; the sampled stand-in's value is
        ``stats["objective_sampled"]``), for a sampled drive loop that of the sampled loop
        itself (:meth:`LoopModel.objective_to_infinity`).
    kind : str
        The objective's name (ie, iae, itae, ise).
    per_loop : list of float
        Objective of each loop (to infinity).
    margins : list of Margins
        Robustness of each loop; ``ms``/``mt`` are the true peaks (:meth:`LoopModel.peaks`).
    stats : dict
        Solver status (ipopt's ``status``), iterations, wall time (s), runs, the horizon-only
        objective, the objective's tail bound (continuous loops: its error estimate), the
        verification rounds, ``first_order`` (``ok``, ``residual``, the ``active`` set of the
        independent optimality check) and ``polished`` (whether the local solve of the true
        problem moved the gains).
    status : str
        ``"optimal"`` where the first-order optimality conditions of the true problem hold at
        ``pid`` within ``KKT_TOL`` (whatever ipopt's exit status), otherwise
        ``"not proven optimal: <residual> (ipopt: <status>)"`` or ``"not converged: scan point
        kept ..."``.
    converged : bool
        Whether ``status`` starts with ``"optimal"``.
    warnings : list of str
        Every caveat of the result, one line each.
    mks : float or None
        True peak noise sensitivity ``max |C F S|`` over the loops (:meth:`LoopModel.noise_peak`;
        control-signal units per measured-output unit), None where a loop has no noise path.
    filter : dict or None
        :func:`tune_pid` with a measurement filter or an ideal derivative: ``order`` (0, 1, 2),
        ``tf_s`` (the filter's time constant, s; None without a filter) and ``derivative``
        (``"ideal"`` or ``"filtered"``); the law is ``C(s) F(s)``.
    setpoint : dict or None
        :func:`tune_pid` with ``setpoint_weights=True``: the 2-DOF weights ``b``, ``c`` of
        ``u = kp (b r - y) + ki int (r - y) + kd D(c r - y)``, their ``goal``, the setpoint
        step's ``iae`` with them and ``iae_unweighted`` (b = c = 1), and the ``overshoot``.
    """

    pid: PID
    objective: float
    kind: str
    per_loop: list[float]
    margins: list[Margins]
    stats: dict = field(default_factory=dict)
    status: str = "optimal"
    converged: bool = True
    warnings: list[str] = field(default_factory=list)
    mks: float | None = None
    filter: dict | None = None
    setpoint: dict | None = None

    @property
    def ms(self) -> float:
        """Largest true peak sensitivity over the loops."""
        return max(m.ms for m in self.margins)

    @property
    def mt(self) -> float:
        """Largest true peak complementary sensitivity over the loops."""
        return max(m.mt for m in self.margins)


def _smooth_abs(x, eps):
    return ca.sqrt(x * x + eps * eps) - eps


def _two_rate(n_steps: int, n_fine: int = 200, m: int = 8) -> tuple[int, int]:
    """Samples simulated at full rate, and the stride on the tail, for the NLP's objective."""
    return (n_steps, 1) if n_steps <= 2 * n_fine else (n_fine, m)


def _two_rate_error(acl, bd, ce, n_steps: int, profile: NDArray[np.float64] | None = None):
    """The error ``e = ce' x`` of the sampled loop ``x[k+1] = acl x[k] + b[k]`` from rest, as a
    CasADi row ``e[1..]`` (``e[0] = 0``): every sample over the transient, then every ``m``-th
    sample on the tail through the exact ``m``-step map (:func:`_two_rate`). ``b = bd`` at every
    sample (a step), or ``profile`` (a duty cycle: one input row per sample, all at full rate).

    Returns ``(e, k, w)``: the error row, each value's sample index and its weight in samples
    (multiply both by the sample time)."""
    n = bd.numel()
    n_fine, m = _two_rate(n_steps) if profile is None else (n_steps, 1)
    xs, bs = ca.SX.sym("x", n), ca.SX.sym("b", n)
    a_s = ca.SX.sym("A", acl.sparsity())
    traj = ca.Function("stepf", [xs, a_s, bs], [ca.mtimes(a_s, xs) + bs]).mapaccum("traj", n_fine - 1)(
        ca.DM.zeros(n), acl, bd if profile is None else ca.DM(profile[: n_fine - 1].T))
    e = ca.mtimes(ce.T, traj)  # e[1..n_fine-1]; e[0] = 0
    k, w = np.arange(1, n_fine, dtype=float), np.ones(n_fine - 1)
    n_coarse = (n_steps - n_fine) // m
    if n_coarse > 0:
        a_m, b_m = acl, bd
        for _ in range(int(math.log2(m))):
            a_m, b_m = ca.mtimes(a_m, a_m), ca.mtimes(a_m, b_m) + b_m
        a_ms = ca.SX.sym("Am", a_m.sparsity())
        tail = ca.Function("stepm", [xs, a_ms, bs], [ca.mtimes(a_ms, xs) + bs]).mapaccum("tail", n_coarse)(
            traj[:, -1], a_m, b_m)
        e = ca.horzcat(e, ca.mtimes(ce.T, tail))
        k = np.concatenate([k, n_fine - 1 + m * np.arange(1, n_coarse + 1)])
        w = np.concatenate([w, np.full(n_coarse, float(m))])
    return e, k, w


def _steady_command(lp: LoopModel) -> float | None:
    """Steady control command ``u_ss`` (plant-input units) that holds a continuous loop's plant
    at zero output against its disturbance step: ``a x + b u + b_d = 0``, ``c x = 0``; None for
    a loop without a continuous model or where that system is singular (no unique ``u_ss``)."""
    if lp.continuous is None:
        return None
    memo = lp._memo
    if "u_ss" not in memo:
        c0, mats, bdc = lp.continuous
        n = c0.shape[0] - 2
        k = np.zeros((n + 1, n + 1))
        k[:n, :n] = c0[:n, :n]
        k[:n, n] = mats[1][:n, n]
        k[n, :n] = lp.Ce[:n]
        rhs = np.concatenate([-bdc[:n], [0.0]])
        try:
            sol = np.linalg.solve(k, rhs)
            ok = np.all(np.isfinite(sol)) and np.linalg.norm(k @ sol - rhs) <= 1e-9 * max(np.linalg.norm(rhs), 1e-300)
        except np.linalg.LinAlgError:
            ok = False
        memo["u_ss"] = float(sol[n]) if ok else None
    return memo["u_ss"]


def _free_gains(use_d: bool, n_gains: int) -> list[int]:
    """Indices of the optimised gains: kp, ki, (kd), (kff)."""
    return [0, 1] + ([2] if use_d else []) + ([3] if n_gains == 4 else [])


def _combined(vals, weights, worst):
    vals = np.asarray(vals, float)
    return float(vals.max()) if worst else float(np.dot(weights, vals))


def _ie_batch(lp: LoopModel, grid: NDArray) -> NDArray:
    """Exact IE (to infinity) of every row of ``grid`` (stable rows; batched linear solves)."""
    g = np.asarray(grid, float)[:, : lp.n_gains]
    a = lp.A0[None] + np.einsum("bi,ijk->bjk", g, np.stack(lp.A))
    m = np.eye(lp.A0.shape[0])[None] - a
    b = np.broadcast_to(lp.Bd, (len(g), lp.Bd.size))[..., None]
    s = np.linalg.solve(m, np.linalg.solve(m, b))[..., 0]
    return np.abs(lp.h * s @ lp.Ce)


def _rank_batch(lp: LoopModel, grid: NDArray, kind: str) -> NDArray:
    """Horizon objective of every row of ``grid`` on the NLP's two-rate samples (ranking only)."""
    n_fine, m = _two_rate(lp.n_steps)
    g = np.asarray(grid, float)[:, : lp.n_gains]
    a = lp.A0[None] + np.einsum("bi,ijk->bjk", g, np.stack(lp.A))
    x = np.zeros((len(g), lp.A0.shape[0]))
    es, ts, ws = [], [], []
    for k in range(n_fine):
        es.append(x @ lp.Ce)
        ts.append(k * lp.h)
        ws.append(lp.h)
        x = np.einsum("bjk,bk->bj", a, x) + lp.Bd
    n_coarse = (lp.n_steps - n_fine) // m
    if n_coarse > 0:
        a_m, b_m = a, np.broadcast_to(lp.Bd, x.shape).copy()
        for _ in range(int(math.log2(m))):
            a_m, b_m = a_m @ a_m, np.einsum("bjk,bk->bj", a_m, b_m) + b_m
        x = x - 0.0
        # x is the state at n_fine; step on with stride m
        x_prev = x
        for j in range(n_coarse):
            es.append(x_prev @ lp.Ce)
            ts.append((n_fine + j * m) * lp.h)
            ws.append(m * lp.h)
            x_prev = np.einsum("bjk,bk->bj", a_m, x_prev) + b_m
    e = np.array(es).T
    t, wts = np.array(ts), np.array(ws)
    if kind == "iae":
        return np.abs(e) @ wts
    if kind == "itae":
        return (np.abs(e) * t) @ wts
    if kind == "ise":
        return (e * e) @ wts
    return np.abs(e @ wts)


@dataclass(eq=False)
class _NLP:
    solver: ca.Function
    free: list
    n_omega: list
    has_mt: bool
    has_noise: bool
    n_slots: int
    warm_nlp: tuple | None = None  # (nlp function, options) of the warm-start solver
    _warm: ca.Function | None = None
    has_mks: bool = False  # rows |C F S| <= Mks after the Ms (and Mt) rows of each loop

    @property
    def n_kinds(self) -> int:
        """Peak constraints per frequency row: Ms, and Mt and Mks where bounded."""
        return 1 + int(self.has_mt) + int(self.has_mks)

    def warm(self) -> ca.Function:
        """The warm-start solver (same problem), built on first use."""
        if self._warm is None:
            self._warm = ca.nlpsol("tuner_warm", "ipopt", *self.warm_nlp)
        return self._warm


@dataclass
class _Candidate:
    gains: NDArray
    stats: dict
    peaks: list
    value: float
    ms_active: bool
    converged: bool


class Tuner:
    """Reusable PI/PID tuner of one loop set: owns the scan grid and the NLP.

    The scan grid (gains parameterised by crossover frequency and integral/derivative ratios)
    and the NLP structure depend only on the loops, the objective and the controller; the
    bounds, the start point, the scaling and the smoothing are numbers of each :meth:`tune`
    call. So a Tuner gives the same result for the same call whatever it solved before, and
    retuning at another bound skips the (~0.5 s) NLP construction.

    Parameters
    ----------
    loops : sequence of LoopModel
        One or several loop models of the same structure (e.g. one per load level).
    objective : {"ie", "iae", "itae", "ise"}
        Integral of the error after the disturbance step.
    controller : {"pi", "pid"}
        PID adds the filtered derivative (the loop's ``tf``, s).
    weights : sequence of float, optional
        Non-negative weights of the loops' objectives (default: equal, summing to 1).
    worst_case : bool
        Minimise the largest loop objective instead of the weighted sum.

    Examples
    --------
    >>> import control
    >>> lp = continuous_loop(control.tf([1.0], [1.0, 3.0, 3.0, 1.0]), tf=0.1, horizon=40.0, n_steps=400)
    >>> tuner = Tuner([lp], objective="ie")
    >>> a, b = tuner.tune(ms_max=1.4), tuner.tune(ms_max=1.6)
    >>> a.status, round(a.ms, 4), b.pid.ki > a.pid.ki
    ('optimal', 1.4, True)
    """

    def __init__(self, loops: Sequence[LoopModel], *, objective: str = "iae", controller: str = "pi",
                 weights: Sequence[float] | None = None, worst_case: bool = False) -> None:
        if objective not in OBJECTIVES:
            raise ValueError(f"objective = {objective!r}; expected one of {', '.join(OBJECTIVES)}")
        if controller not in CONTROLLERS:
            raise ValueError(f"controller = {controller!r}; expected 'pi' or 'pid'")
        loops = tuple(loops)
        if not loops or not all(isinstance(lp, LoopModel) for lp in loops):
            raise ValueError(f"loops = {loops!r}; expected a non-empty sequence of LoopModel")
        if len({lp.n_gains for lp in loops}) != 1:
            raise ValueError("loops mix plain and feed-forward structures; expected one structure")
        if weights is None:
            w = np.ones(len(loops)) / len(loops)
        else:
            try:
                w = np.asarray(weights, float)
            except (TypeError, ValueError):
                raise ValueError(f"weights = {weights!r}; expected {len(loops)} non-negative finite numbers") from None
            if w.shape != (len(loops),) or not np.all(np.isfinite(w)) or np.any(w < 0) or not w.sum() > 0:
                raise ValueError(f"weights = {list(np.atleast_1d(w))}; expected {len(loops)} non-negative finite numbers, not all 0")
        if not isinstance(worst_case, (bool, np.bool_)):
            raise ValueError(f"worst_case = {worst_case!r}; expected True or False")
        self.loops = loops
        self.objective = objective
        self.controller = controller
        self.use_d = controller == "pid"
        self.weights = w
        self.worst_case = bool(worst_case)
        self._scan: dict | None = None
        self._nlps: dict = {}

    # ---- scan ---------------------------------------------------------------------------

    @property
    def scan_grid(self) -> NDArray[np.float64]:
        """Gains of the scan (rows kp, ki, kd[, kff]), built from the loops alone."""
        return self._scan_data()["grid"]

    def _scan_data(self) -> dict:
        if self._scan is None:
            self._scan = self._build_scan()
        return self._scan

    def _build_scan(self) -> dict:
        """Gains placed by crossover frequency: for each of 30 frequencies ``wc`` spanning the
        reference loop's grid, integral ratios ``ki = r wc kp`` and derivative ratios
        ``kd = q kp / wc``, ``kp`` solves ``|L(j wc)| = 1``. Scale-free: it follows the plant
        whatever its time constants or gain, and stable or not in open loop."""
        ref = self.loops[0]
        ng = ref.n_gains
        n0, ln, d0, ld = ref.parts()
        w = ref.omega
        idx = np.unique(np.round(np.linspace(0, w.size - 1, 30)).astype(int))
        rs = np.logspace(-3, 0.5, 25)
        qs = np.concatenate([[0.0], np.logspace(-2, 0.5, 6)]) if self.use_d else np.array([0.0])
        kffs = np.array([0.0, 0.1, 0.2, 0.35, 0.5, 0.75, 1.0]) if ng == 4 else np.array([0.0])
        J, R, Q, F = (x.ravel() for x in np.meshgrid(np.arange(idx.size), rs, qs, kffs, indexing="ij"))
        col = idx[J]
        wc = w[col]
        a = ln[0, col] + R * wc * ln[1, col] + Q / wc * ln[2, col]
        bb = ld[0, col] + R * wc * ld[1, col] + Q / wc * ld[2, col]
        c0 = n0[col] + (F * ln[3, col] if ng == 4 else 0.0)
        e0 = d0[col] + (F * ld[3, col] if ng == 4 else 0.0)
        a2 = np.abs(a) ** 2 - np.abs(bb) ** 2
        a1 = 2.0 * np.real(c0 * np.conj(a) - e0 * np.conj(bb))
        a0 = np.abs(c0) ** 2 - np.abs(e0) ** 2
        with np.errstate(all="ignore"):
            sq = np.sqrt(np.maximum(a1 * a1 - 4 * a2 * a0, 0.0))
            quad = np.abs(a2) > 1e-12 * (np.abs(a1) + np.abs(a0) + 1e-300)
            r1 = np.where(quad, (-a1 - sq) / (2 * a2), -a0 / a1)
            r2 = np.where(quad, (-a1 + sq) / (2 * a2), np.inf)
            ok_disc = (a1 * a1 - 4 * a2 * a0 >= 0) | ~quad
            r1 = np.where(ok_disc & (r1 > 0) & np.isfinite(r1), r1, np.inf)
            r2 = np.where(ok_disc & (r2 > 0) & np.isfinite(r2), r2, np.inf)
            kp = np.minimum(r1, r2)
        valid = np.isfinite(kp) & (kp > 0)
        kp, R, Q, F, wc = kp[valid], R[valid], Q[valid], F[valid], wc[valid]
        grid = np.column_stack([kp, kp * R * wc, kp * Q / wc, F])[:, :ng]
        # Gains below every crossover (|L| < 1 everywhere; e.g. under a tight noise bound):
        # kp down to 1e-3 of the smallest crossover gain, integral corners across the grid.
        if kp.size:
            k_lo = float(kp.min()) * np.logspace(-3, 0, 6)
            zs = w[idx[::2]]
            KL, Z, FL = (x.ravel() for x in np.meshgrid(k_lo, zs, kffs, indexing="ij"))
            low = np.column_stack([KL, KL * Z, np.zeros_like(KL), FL])[:, :ng]
            grid = np.vstack([grid, low])
        nl = len(self.loops)
        return {"grid": grid, "ms": self._scan_peak(grid, "ms"), "mt": None,
                "stable": np.full((nl, len(grid)), -1, np.int8), "obj": np.full((nl, len(grid)), np.nan)}

    def _scan_peak(self, grid: NDArray[np.float64], key: str) -> NDArray[np.float64]:
        """Largest |S| (``key`` "ms"), |T| ("mt") or |C F S| ("mks") over every loop's grid, per
        scan point."""
        out = np.zeros(len(grid))
        for lp in self.loops:
            pn0, pln, pd0, pld = lp.parts()
            kn = np.asarray(lp.noise(lp.omega), complex) if key == "mks" else None
            for s in range(0, len(grid), 1000):
                gg = grid[s : s + 1000]
                with np.errstate(all="ignore"):
                    L = (pn0 + gg @ pln) / (pd0 + gg @ pld)
                    if key == "mks":
                        m = np.abs((gg[:, : kn.shape[0]] @ kn) / (1 + L))
                    else:
                        m = 1 / np.abs(1 + L) if key == "ms" else np.abs(L / (1 + L))
                    out[s : s + 1000] = np.maximum(out[s : s + 1000], np.max(m, axis=1))
        out[~np.isfinite(out)] = np.inf
        return out

    def _scan_mt(self) -> NDArray[np.float64]:
        """The scan's Mt (computed on the first call with an Mt bound)."""
        sc = self._scan_data()
        if sc["mt"] is None:
            sc["mt"] = self._scan_peak(sc["grid"], "mt")
        return sc["mt"]

    def _scan_mks(self) -> NDArray[np.float64]:
        """The scan's Mks on the loops' grids (computed on the first call with an Mks bound)."""
        sc = self._scan_data()
        if sc.get("mks") is None:
            sc["mks"] = self._scan_peak(sc["grid"], "mks")
        return sc["mks"]

    def _ranked(self, ms_eff, mt_eff, noise, hi, mks_eff=None) -> NDArray[np.int64]:
        """Scan indices within the bounds, stable in every loop, best objective first.

        With several loops and the worst-case objective (robust tuning: the ranking simulated
        every loop at every scan point, ~0.4 s for 16 loops) the order is exact only where it
        is used (a mean over loops has no useful bound; it ranks every point): the reference
        loop and the loop that is worst at its best point are simulated everywhere, which
        bounds every point's aggregate from below; the other loops are simulated in batches of
        points taken in order of that bound, until ``_RANK_TOP`` points are known stable in
        every loop with an aggregate no larger than any unsimulated point's bound. Those points
        come first, in exact order; the other fully simulated ones follow; points never
        simulated in every loop are left out."""
        sc = self._scan_data()
        grid = sc["grid"]
        ok = sc["ms"] <= ms_eff
        if mt_eff is not None:
            ok &= self._scan_mt() <= mt_eff
        if noise is not None:
            ok &= grid[:, 0] + (grid[:, 2] / self.loops[0].tf) <= noise
        if mks_eff is not None:
            ok &= self._scan_mks() <= mks_eff
        for i, lim in enumerate(hi):
            ok &= grid[:, i] <= lim
        cand = np.flatnonzero(ok)
        nl = len(self.loops)
        if nl == 1 or not self.worst_case or cand.size <= _RANK_TOP:
            self._evaluate(range(nl), cand)
            idx = cand[np.all(sc["stable"][:, cand] == 1, axis=0)]
            return idx[np.argsort(self._aggregate(idx), kind="stable")]
        self._evaluate([0], cand)
        cand = cand[sc["stable"][0, cand] == 1]
        if not cand.size:
            return cand
        best0 = cand[int(np.argmin(sc["obj"][0, cand]))]
        self._evaluate(range(nl), np.array([best0]))
        hard = int(np.argmax(np.where(sc["stable"][:, best0] == 1, sc["obj"][:, best0], np.inf)))
        self._evaluate([hard], cand)
        cand = cand[sc["stable"][hard, cand] == 1]
        part = [0] if hard == 0 else [0, hard]
        lb = self._aggregate(cand, part)
        cand = cand[np.argsort(lb, kind="stable")]
        lb = np.sort(lb, kind="stable")
        pos, done = 0, cand[:0]
        while pos < cand.size:
            self._evaluate(range(nl), cand[pos : pos + _RANK_TOP])
            pos += _RANK_TOP
            done = cand[:pos][np.all(sc["stable"][:, cand[:pos]] == 1, axis=0)]
            if pos >= cand.size or np.sum(self._aggregate(done) <= lb[pos]) >= _RANK_TOP:
                break
        return done[np.argsort(self._aggregate(done), kind="stable")]

    def _evaluate(self, loops, idx: NDArray[np.int64]) -> None:
        """Stability, and the ranking objective where stable, of scan points ``idx`` in the
        loops ``loops`` (cached: each (loop, point) is computed once per Tuner)."""
        sc = self._scan_data()
        grid = sc["grid"]
        for j in loops:
            lp = self.loops[j]
            todo = idx[sc["stable"][j, idx] < 0]
            if todo.size:
                g = grid[todo][:, : lp.n_gains]
                a = lp.A0[None] + np.einsum("bi,ijk->bjk", g, np.stack(lp.A))
                sc["stable"][j, todo] = np.max(np.abs(np.linalg.eigvals(a)), axis=1) < 1.0 - _UNIT_TOL
            todo = idx[(sc["stable"][j, idx] == 1) & np.isnan(sc["obj"][j, idx])]
            if todo.size:
                sc["obj"][j, todo] = _ie_batch(lp, grid[todo]) if self.objective == "ie" else _rank_batch(lp, grid[todo], self.objective)

    def _aggregate(self, idx: NDArray[np.int64], loops: Sequence[int] | None = None) -> NDArray[np.float64]:
        """Worst-case or weighted objective of scan points ``idx`` over ``loops`` (default all;
        a subset gives a lower bound: the objectives are non-negative)."""
        loops = list(range(len(self.loops))) if loops is None else list(loops)
        vals = self._scan_data()["obj"][np.ix_(loops, idx)]
        return vals.max(axis=0) if self.worst_case else self.weights[loops] @ vals

    def _starts(self, order: NDArray[np.int64]) -> list[NDArray]:
        """Up to ``_STARTS`` scan points, best first, at least 0.25 decade apart in (kp, ki)."""
        grid = self._scan_data()["grid"]
        chosen: list[int] = []
        for i in order[:400]:
            lg = np.log10(grid[i, :2])
            if all(np.max(np.abs(lg - np.log10(grid[c, :2]))) > 0.25 for c in chosen):
                chosen.append(int(i))
            if len(chosen) == _STARTS:
                break
        return [grid[i].copy() for i in chosen]

    # ---- NLP ----------------------------------------------------------------------------

    def _nlp(self, has_mt: bool, has_noise: bool, has_mks: bool = False) -> _NLP:
        key = (has_mt, has_noise) + ((True,) if has_mks else ())
        if key not in self._nlps:
            self._nlps[key] = self._build_nlp(has_mt, has_noise, has_mks)
        return self._nlps[key]

    def _grid_rows(self, jl: int) -> NDArray[np.int64]:
        """Indices of loop ``jl``'s grid frequencies that are NLP constraint rows: all of them
        for one loop; with several loops (M scenario models: M x 500 rows made each ipopt
        iteration ~8x dearer) about ``_MULTI_ROWS`` evenly spread in log frequency plus every
        point inserted at a resonance (a grid gap under half the median). Points left out are
        still checked: the verification after each solve finds the true peak of every loop on
        a denser grid and adds it (with neighbours) as a constraint, so the result honours the
        bounds as with the full grid."""
        w = self.loops[jl].omega
        if len(self.loops) == 1 or w.size <= _MULTI_ROWS:
            return np.arange(w.size)
        gap = np.diff(np.log(w))
        fine = np.flatnonzero(gap < 0.5 * np.median(gap))
        keep = np.unique(np.concatenate([np.round(np.linspace(0, w.size - 1, _MULTI_ROWS)).astype(int), fine, fine + 1]))
        return keep

    def _nlp_parts(self, jl: int) -> tuple:
        """Loop ``jl``'s ``(N0, L, D0, D)`` on its NLP rows (:meth:`_grid_rows`)."""
        parts, rows = self.loops[jl].parts(), self._grid_rows(jl)
        return parts if rows.size == self.loops[jl].omega.size else tuple(x[..., rows] for x in parts)

    @staticmethod
    def _grid_step(lp: LoopModel) -> float:
        """Median step of ``lp``'s grid in log frequency."""
        return float(np.median(np.diff(np.log(lp.omega)))) if lp.omega.size > 1 else 0.05

    def _cluster(self, lp: LoopModel, w: float) -> list[float]:
        """``w`` (rad/s) and its neighbours one and two median grid steps of ``lp`` away
        (multi-loop slots: the coarse NLP grid leaves a moving peak between its rows; five
        points at the full grid's spacing hold it the way the full grid does)."""
        r = math.exp(self._grid_step(lp))
        return [w * r**k for k in (-2, -1, 0, 1, 2)]

    def _n_slots(self) -> int:
        return _SLOTS if len(self.loops) == 1 else _MULTI_SLOTS

    def _n_slot(self, mks: bool = False) -> int:
        """Numbers per extra frequency: N0, D0 (re, im), L and D per gain (re, im), and with an
        Mks bound the noise path ``C F`` per gain (re, im)."""
        return 4 + (6 if mks else 4) * self.loops[0].n_gains

    def _mapped_objectives(self, g, eps) -> list | None:
        """The time-domain objective of every loop from ONE per-loop function mapped over the
        loops (robust tuning: M scenario models of one structure), or ``None`` where that does
        not apply (one loop, the "ie" objective, duty-cycle profiles, loops of different sizes
        or horizons), in which case each loop is expanded as before.

        The per-loop function (the two-rate trajectory of ``_build_nlp``, the loop's matrices
        as inputs on the union of their sparsity patterns) is expanded to SX once; the NLP then
        stays MX (``expand=False``), so building it costs one loop, not M (measured on 16
        scenarios of robust-load-step: 18 s -> 1 s, same solution to ~1e-10)."""
        loops = self.loops
        if self.objective not in ("iae", "itae", "ise") or len(loops) < 2 \
                or any(lp.profile is not None for lp in loops):
            return None
        lp0 = loops[0]
        n, ng, n_steps = lp0.A0.shape[0], lp0.n_gains, lp0.n_steps
        if any(lp.A0.shape[0] != n or lp.n_steps != n_steps or lp.n_gains != ng for lp in loops):
            return None
        pattern = np.zeros((n, n), bool)
        for lp in loops:
            pattern |= np.asarray(lp.A0) != 0
            for a in lp.A:
                pattern |= np.asarray(a) != 0
        rows, cols = np.nonzero(pattern)
        sp = ca.Sparsity.triplet(n, n, [int(i) for i in rows], [int(j) for j in cols])
        gs = ca.SX.sym("g", ng)
        a0 = ca.SX.sym("a0", sp)
        ai = [ca.SX.sym(f"a{i}", sp) for i in range(ng)]
        bd, ce, e_s, h = ca.SX.sym("bd", n), ca.SX.sym("ce", n), ca.SX.sym("eps"), ca.SX.sym("h")
        acl = a0 + sum(gs[i] * ai[i] for i in range(ng))
        e, k, w = _two_rate_error(acl, bd, ce, n_steps)
        tk, wk = ca.DM(k).T * h, ca.DM(w).T * h
        j = {"iae": ca.sum2(wk * _smooth_abs(e, e_s)), "itae": ca.sum2(wk * tk * _smooth_abs(e, e_s)),
             "ise": ca.sum2(wk * e * e)}[self.objective]
        per_loop = ca.Function("loop_objective", [gs, a0, *ai, bd, ce, e_s, h], [j])
        nl = len(loops)

        def cat(mats):
            return ca.horzcat(*[ca.project(ca.DM(np.asarray(a, float)), sp) for a in mats])

        row = per_loop.map(nl)(
            ca.repmat(g, 1, nl), cat([lp.A0 for lp in loops]), *[cat([lp.A[i] for lp in loops]) for i in range(ng)],
            ca.horzcat(*[ca.DM(np.asarray(lp.Bd, float).ravel()) for lp in loops]),
            ca.horzcat(*[ca.DM(np.asarray(lp.Ce, float).ravel()) for lp in loops]),
            ca.vertcat(*[eps[k] for k in range(nl)]).T, ca.DM([float(lp.h) for lp in loops]).T)
        return [row[k] for k in range(nl)]

    def _build_nlp(self, has_mt: bool, has_noise: bool, has_mks: bool = False) -> _NLP:
        """NLP in scaled gains ``v`` with parameters ``p = [scale (ng), eps (per loop), j_ref,
        1/Ms^2, 1/Mt^2, extra frequencies (per loop, n_slots x (4 + 4 ng), with an Mks bound
        4 + 6 ng) and row scales (per loop), 1/Mks^2 (with an Mks bound)]``."""
        loops = self.loops
        ng, nl = loops[0].n_gains, len(loops)
        free = _free_gains(self.use_d, ng)
        nv = len(free)
        ns = self._n_slot(has_mks)
        v = ca.MX.sym("v", nv)
        n_sl = self._n_slots()
        per_loop = [n_sl * ns + (3 if has_mks else 2) * (self._grid_rows(jl).size + n_sl) for jl in range(nl)]
        p = ca.MX.sym("p", ng + nl + 3 + sum(per_loop) + (1 if has_mks else 0))
        inv_mks2 = p[-1] if has_mks else None
        scale, eps, j_ref = p[:ng], p[ng : ng + nl], p[ng + nl]
        inv_ms2, inv_mt2 = p[ng + nl + 1], p[ng + nl + 2]
        offs = np.concatenate([[ng + nl + 3], ng + nl + 3 + np.cumsum(per_loop)]).astype(int)
        g_list = [ca.MX(0.0)] * ng
        for j, i in enumerate(free):
            g_list[i] = v[j] * scale[i]
        g = ca.vertcat(*g_list)
        cons_s, cons_t, cons_k, objs = [], [], [], []
        rows = [self._grid_rows(jl) for jl in range(nl)]
        mapped = self._mapped_objectives(g, eps)
        for jl, lp in enumerate(loops):
            N = lp.A0.shape[0]
            acl = ca.DM(lp.A0) + sum(g[i] * ca.DM(lp.A[i]) for i in range(ng))
            bd = ca.DM(lp.Bd)
            ce = ca.DM(lp.Ce)
            if mapped is not None:
                J = mapped[jl]
            elif self.objective == "ie" and _steady_command(lp) is not None:
                # A continuous loop: the Euler integral state sums the error, I_inf = h sum e_k, and
                # at steady state ki I_inf = u_ss, the plant's steady command against the
                # disturbance (gain-free): IE = |u_ss| / ki exactly, no ill-conditioned solve.
                J = _smooth_abs(_steady_command(lp) / g[1], eps[jl])
            elif self.objective == "ie":
                # Exact IE to infinity: h Ce (I - A)^-1 (I - A)^-1 b (zero steady error under
                # integral action), as two solves: the product (I - A)^2 squares the condition
                # number (~1e65 for a 6th-order Pade delay at a 1e-5 s sample) and its symbolic QR
                # returned an IE 400x too small that jumped between iterates (issue 20).
                a_s, b_s = ca.SX.sym("A", N, N), ca.SX.sym("b", N)
                m_s = ca.SX.eye(N) - a_s
                ief = ca.Function("ie", [a_s, b_s], [-lp.h * ca.mtimes(ce.T, ca.solve(m_s, ca.solve(m_s, b_s)))])
                J = _smooth_abs(ief(acl, bd), eps[jl])
            else:
                # Two rates (a profile loop: its own input at every sample, all at full rate); the
                # reported objective is always the full one to infinity.
                e, k, w = _two_rate_error(acl, bd, ce, lp.n_steps, lp.profile)
                tk, wk = ca.DM(lp.h * k).T, ca.DM(lp.h * w).T
                J = {
                    "iae": ca.sum2(wk * _smooth_abs(e, eps[jl])),
                    "itae": ca.sum2(wk * tk * _smooth_abs(e, eps[jl])),
                    "ise": ca.sum2(wk * e * e),
                }[self.objective]
            objs.append(J)
            # 1 + L = (D + N)/D and L = N/D, with N and D affine in the gains.
            n0, ln, d0, ld = self._nlp_parts(jl)

            def affine(c0, cg):
                return (ca.DM(c0.real) + ca.mtimes(ca.DM(cg.real.T), g), ca.DM(c0.imag) + ca.mtimes(ca.DM(cg.imag.T), g))

            w_re, w_im = affine(n0 + d0, ln + ld)
            d_re, d_im = affine(d0, ld)
            n_re, n_im = affine(n0, ln)
            # Extra frequencies (parameters): columns [n0 re, im, d0 re, im, ln re, ln im, ld re, ld im].
            off = int(offs[jl])
            q = ca.reshape(p[off : off + n_sl * ns], ns, n_sl)
            n_c = rows[jl].size + n_sl
            norm_s = p[off + n_sl * ns : off + n_sl * ns + n_c]
            norm_t = p[off + n_sl * ns + n_c : off + n_sl * ns + 2 * n_c]
            q_n0r, q_n0i, q_d0r, q_d0i = q[0, :], q[1, :], q[2, :], q[3, :]
            q_lnr, q_lni = q[4 : 4 + ng, :], q[4 + ng : 4 + 2 * ng, :]
            q_ldr, q_ldi = q[4 + 2 * ng : 4 + 3 * ng, :], q[4 + 3 * ng : 4 + 4 * ng, :]
            gt = g.T
            sn_re, sn_im = q_n0r + ca.mtimes(gt, q_lnr), q_n0i + ca.mtimes(gt, q_lni)
            sd_re, sd_im = q_d0r + ca.mtimes(gt, q_ldr), q_d0i + ca.mtimes(gt, q_ldi)
            sw_re, sw_im = sn_re + sd_re, sn_im + sd_im
            # |N + D|^2 - |D|^2/Ms^2 >= 0 (|1 + L| >= 1/Ms) and |N + D|^2 - |N|^2/Mt^2 >= 0
            # (|L/(1 + L)| <= Mt): polynomial in the gains, each row scaled by its size at the
            # start point (parameters), so no row is huge where |L| is large or tiny.
            ww = ca.vertcat(w_re * w_re + w_im * w_im, (sw_re * sw_re + sw_im * sw_im).T)
            dd = ca.vertcat(d_re * d_re + d_im * d_im, (sd_re * sd_re + sd_im * sd_im).T)
            cons_s.append((ww - inv_ms2 * dd) * norm_s)
            if has_mt:
                nn = ca.vertcat(n_re * n_re + n_im * n_im, (sn_re * sn_re + sn_im * sn_im).T)
                cons_t.append((ww - inv_mt2 * nn) * norm_t)
            if has_mks:
                # |C F S| <= Mks: |N + D|^2 - |D|^2 |g K|^2 / Mks^2 >= 0, K the noise path per gain.
                kg = np.asarray(lp.noise(lp.omega[rows[jl]]), complex)
                k_re, k_im = ca.mtimes(ca.DM(kg.real.T), g), ca.mtimes(ca.DM(kg.imag.T), g)
                q_kr, q_ki = q[4 + 4 * ng : 4 + 5 * ng, :], q[4 + 5 * ng : 4 + 6 * ng, :]
                sk_re, sk_im = ca.mtimes(gt, q_kr), ca.mtimes(gt, q_ki)
                kk = ca.vertcat(k_re * k_re + k_im * k_im, (sk_re * sk_re + sk_im * sk_im).T)
                norm_k = p[off + n_sl * ns + 2 * n_c : off + n_sl * ns + 3 * n_c]
                cons_k.append((ww - inv_mks2 * dd * kk) * norm_k)
        cons = []
        for jl in range(nl):
            cons.append(cons_s[jl])
            if has_mt:
                cons.append(cons_t[jl])
            if has_mks:
                cons.append(cons_k[jl])
        if has_noise:
            cons.append(g[0] + g[2] / loops[0].tf)
        if self.worst_case:
            t = ca.MX.sym("t")
            var, f = ca.vertcat(v, t), t / j_ref
            cons += [t - J for J in objs]
        else:
            var, f = v, sum(float(w) * J for w, J in zip(self.weights, objs)) / j_ref
        ip = {"print_level": 0, "sb": "yes", "max_iter": _IPOPT_MAX_ITER, "tol": 1e-8,
              "hessian_approximation": "limited-memory"}
        # Trial points with an unstable loop overflow the objective; ipopt backs off from them,
        # and CasADi's warning per evaluation (thousands in a warm-started re-solve) says nothing.
        base = {"print_time": False, "error_on_fail": False, "show_eval_warnings": False}
        # Expanding to SX costs ~0.5 s once per Tuner but makes each solve ~10x faster; mapped
        # per-loop objectives are SX already (expanding would unroll the map).
        solver = ca.nlpsol("tuner", "ipopt", {"x": var, "p": p, "f": f, "g": ca.vertcat(*cons)},
                           {**base, "expand": mapped is None, "ipopt": ip})
        warm = None
        if nl > 1:
            fun = ca.Function("tuner_nlp", [var, p], [f, ca.vertcat(*cons)], ["x", "p"], ["f", "g"])
            if mapped is None:
                fun = fun.expand()
            # Re-solves after a verification round start from the previous solution and its
            # multipliers (a few constraint rows changed); built on first use.
            warm = (fun, {**base, "ipopt": {**ip, "warm_start_init_point": "yes", "warm_start_bound_push": 1e-9,
                                            "warm_start_mult_bound_push": 1e-9, "warm_start_slack_bound_push": 1e-9}})
        return _NLP(solver, free, [r.size for r in rows], has_mt, has_noise, n_sl, warm, has_mks=has_mks)

    def _params(self, scale, eps, j_ref, inv_ms2, inv_mt2, slots, g0, inv_mks2=None) -> NDArray:
        mks = inv_mks2 is not None
        ns = self._n_slot(mks)
        out = [np.asarray(scale, float), np.asarray(eps, float), np.array([j_ref, inv_ms2, inv_mt2])]
        g0 = self.loops[0].gvec(g0)
        for jl, (lp, ws) in enumerate(zip(self.loops, slots)):
            blk = np.zeros((self._n_slots(), ns))
            blk[:, 0] = 0.5  # unused slot: L = 0.5, |S| = 2/3, |T| = 1/3, always feasible
            blk[:, 2] = 1.0
            if ws:
                n0, ln, d0, ld = lp.parts_at(np.asarray(ws, float))
                kn = np.asarray(lp.noise(np.asarray(ws, float)), complex) if mks else None
                for k in range(len(ws)):
                    blk[k] = np.concatenate([[n0[k].real, n0[k].imag, d0[k].real, d0[k].imag],
                                             ln[:, k].real, ln[:, k].imag, ld[:, k].real, ld[:, k].imag]
                                            + ([kn[:, k].real, kn[:, k].imag] if mks else []))
            out.append(blk.ravel())
            # Row scales: 1 / (|N + D|^2 + |D|^2) and 1 / (|N + D|^2 + |N|^2) at the start point.
            pn0, pln, pd0, pld = self._nlp_parts(jl)
            ng = len(g0)
            s_n = blk[:, 0] + 1j * blk[:, 1] + (blk[:, 4 : 4 + ng] + 1j * blk[:, 4 + ng : 4 + 2 * ng]) @ g0
            s_d = blk[:, 2] + 1j * blk[:, 3] + (blk[:, 4 + 2 * ng : 4 + 3 * ng] + 1j * blk[:, 4 + 3 * ng : 4 + 4 * ng]) @ g0
            nv = np.concatenate([pn0 + g0 @ pln, s_n])
            dv = np.concatenate([pd0 + g0 @ pld, s_d])
            wv = np.abs(nv + dv) ** 2
            out.append(1.0 / np.maximum(wv + np.abs(dv) ** 2, 1e-300))
            out.append(1.0 / np.maximum(wv + np.abs(nv) ** 2, 1e-300))
            if mks:  # 1 / (|N + D|^2 + |D|^2 |g K|^2 / Mks^2) at the start point
                rows_w = lp.omega[self._grid_rows(jl)]
                kv = np.concatenate([g0 @ np.asarray(lp.noise(rows_w), complex),
                                     (blk[:, 4 + 4 * ng : 4 + 5 * ng] + 1j * blk[:, 4 + 5 * ng :]) @ g0])
                out.append(1.0 / np.maximum(wv + np.abs(dv) ** 2 * np.abs(kv) ** 2 * inv_mks2, 1e-300))
        if mks:
            out.append(np.array([inv_mks2]))
        return np.concatenate(out)

    def _value(self, gains) -> float:
        """Aggregated objective over the loops' horizons (for ranking and scaling)."""
        vals = [lp.objective_to_infinity(gains, "ie")[0] if self.objective == "ie" else lp.objective(gains, self.objective)
                for lp in self.loops]
        return _combined(vals, self.weights, self.worst_case)

    def _solve_from(self, nlp: _NLP, g0, ms_max, mt_max, noise, hi, typical,
                    mks_max=None) -> tuple[_Candidate | None, dict]:
        """ipopt from one scan point, then verify (stability, true peaks) and re-solve with the
        frequencies where a true peak exceeded its bound, until the bounds hold."""
        loops = self.loops
        ng = loops[0].n_gains
        free = nlp.free
        g0 = loops[0].gvec(g0)
        # Scale each gain by its start value, but not below a tenth of its typical size among
        # the best scan points (a start at a tiny kp would make kp ~ 1e3 in scaled units).
        typical = loops[0].gvec(typical)
        scale = np.maximum(g0, 0.1 * typical)
        scale = np.where(scale > 0, scale, 1.0)
        if self.use_d and g0[2] <= 0:
            scale[2] = scale[0] / max(scale[1] / scale[0], 1e-300)  # kd ~ kp^2/ki
        if ng == 4:
            scale[3] = 1.0
        if self.objective == "ie":
            eps = [1e-9 * max(lp.objective_to_infinity(g0, "ie")[0], 1e-300) for lp in loops]
        else:
            eps = [1e-3 * max(float(np.max(np.abs(lp.error(g0)))), 1e-300) for lp in loops]
        j_ref = max(self._value(g0), 1e-300)
        lo = [0.0] * ng
        if self.objective == "ie":
            lo[1] = 1e-6 * g0[1]  # IE needs integral action
        lbx = [lo[i] / scale[i] for i in free]
        ubx = [min(hi[i] / scale[i], 1e300) if math.isfinite(hi[i]) else ca.inf for i in free]
        x0 = [g0[i] / scale[i] for i in free]
        if self.worst_case:
            x0.append(self._value(g0) / j_ref * 1.001)
            lbx.append(0.0)
            ubx.append(ca.inf)
        # Seed the extra frequencies with the start's true peaks (the optimum's peaks are
        # usually near them), so that most solves verify at once. With several loops (a coarse
        # grid in the NLP) each added frequency comes with its full-grid neighbours: a peak
        # that moves with the gains is then held in one or two rounds, not five.
        multi = nlp.warm_nlp is not None
        slots: list[list[float]] = []
        for lp in loops:
            if multi and lp.response is not None:  # the grid's top is near enough for a cluster's centre
                w_d, l_d = lp._peak_grid(g0)
                ws0 = {float(w_d[np.argmax(1 / np.abs(1 + l_d))])} | (
                    {float(w_d[np.argmax(np.abs(l_d / (1 + l_d)))])} if mt_max is not None else set())
            else:
                pk0 = lp.peaks(g0, mt=mt_max is not None)
                ws0 = {pk0["w_ms"]} | ({pk0["w_mt"]} if mt_max is not None else set()) if pk0["exact"] else set()
            if mks_max is not None:
                ws0 |= {lp.noise_peak(g0)["w_mks"]}
            slots.append(sorted({w for w0 in ws0 for w in (self._cluster(lp, w0) if multi else [w0])}))
        ms_eff = ms_max * (1 - 1e-5)
        mt_eff = mt_max * (1 - 1e-5) if mt_max is not None else None
        mks_eff = mks_max * (1 - 1e-5) if mks_max is not None else None
        info: dict = {"start": [float(x) for x in g0], "iterations": 0, "rounds": 0}
        sol: dict = {}
        for rnd in range(2 * nlp.n_slots + 1):
            lbg = [0.0] * sum((n_w + nlp.n_slots) * nlp.n_kinds for n_w in nlp.n_omega)
            ubg = [ca.inf] * len(lbg)
            if nlp.has_noise:
                lbg.append(-ca.inf)
                ubg.append(noise * (1 - 1e-7))  # a hair inside, so the result honours it exactly
            if self.worst_case:
                lbg += [0.0] * len(loops)
                ubg += [ca.inf] * len(loops)
            prm = self._params(scale, eps, j_ref, ms_eff**-2, (mt_eff or 1.0) ** -2, slots, g0,
                               None if mks_eff is None else mks_eff**-2)
            if rnd and multi:
                warm = nlp.warm()
                sol = warm(x0=x0, p=prm, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg, lam_x0=sol["lam_x"], lam_g0=sol["lam_g"])
                st = warm.stats()
            else:
                sol = nlp.solver(x0=x0, p=prm, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
                st = nlp.solver.stats()
            info["iterations"] += int(st["iter_count"])
            info["status"] = st["return_status"]
            xs = np.asarray(sol["x"]).ravel()
            if not np.all(np.isfinite(xs)):
                info["result"] = "non-finite solver output"
                return None, info
            gains = np.zeros(ng)
            for j, i in enumerate(free):
                gains[i] = min(max(xs[j] * scale[i], 0.0), hi[i])
            stab = [lp.stability(gains) for lp in loops]
            if any(s != "stable" for s in stab):
                info["result"] = f"{'unstable' if 'unstable' in stab else 'marginal'} closed loop"
                return None, info
            if noise is not None and gains[0] + gains[2] / loops[0].tf > noise * (1 + 1e-9):
                info["result"] = "noise bound not met"
                return None, info
            pks = [lp.peaks(gains, mt=mt_max is not None) for lp in loops]
            if mks_max is not None:
                for lp, pk in zip(loops, pks):
                    pk.update(lp.noise_peak(gains))
            viol, grid_only_bad, full = False, False, False
            for j, pk in enumerate(pks):
                bad_s = pk["ms"] > ms_max
                bad_t = mt_max is not None and pk["mt"] > mt_max
                bad_k = mks_max is not None and pk["mks"] > mks_max
                if not pk["exact"]:
                    grid_only_bad |= bad_s or bad_t or bad_k
                    continue
                for bad, key in ((bad_s, "ms"), (bad_t, "mt"), (bad_k, "mks")):
                    if not bad:
                        continue
                    viol = True
                    w_pk = pk["w_" + key]
                    if any(abs(w_pk / w0 - 1) < 1e-7 for w0 in slots[j]):
                        # Already constrained there: the solve's tolerance, tighten the bound.
                        if key == "ms":
                            ms_eff *= (ms_max / pk["ms"]) * (1 - 1e-6)
                        elif key == "mt":
                            mt_eff *= (mt_max / pk["mt"]) * (1 - 1e-6)
                        else:
                            mks_eff *= (mks_max / pk["mks"]) * (1 - 1e-6)
                    else:
                        # A new region gets the peak with its neighbours; a peak inside a region
                        # already held (it moved by less than the cluster's span) only itself.
                        near = multi and any(abs(math.log(w_pk / w0)) < 2.5 * self._grid_step(loops[j])
                                             for w0 in slots[j])
                        new = [w for w in (self._cluster(loops[j], w_pk) if multi and not near else [w_pk])
                               if not any(abs(w / w0 - 1) < 1e-7 for w0 in slots[j])]
                        if len(slots[j]) + len(new) > nlp.n_slots:
                            new = [w_pk]  # no room for the neighbours: the peak alone
                        full |= len(slots[j]) + len(new) > nlp.n_slots
                        slots[j] += new
            if grid_only_bad:
                info["result"] = "bound not met on the loop's grid"
                return None, info
            if not viol:
                lam = np.asarray(sol["lam_g"]).ravel()
                n_s = [n_w + nlp.n_slots for n_w in nlp.n_omega]
                idx, active = 0, False
                for n in n_s:
                    active |= bool(np.any(lam[idx : idx + n] < -1e-8))
                    idx += n * nlp.n_kinds
                info["result"] = "verified"
                return _Candidate(gains, dict(st), pks, math.nan, active, bool(st["success"])), info
            if full:
                info["result"] = f"true peak above the bound after {nlp.n_slots} added frequencies"
                return None, info
            info["rounds"] += 1
            x0 = list(xs)
        info["result"] = "bound not met after the refinement budget"
        return None, info

    # ---- verification of optimality -------------------------------------------------------

    def _first_order(self, gains, ms_max, mt_max, noise, hi, typical, mks_max=None) -> dict:
        """First-order optimality of ``gains`` checked on the TRUE problem, independently of
        ipopt: the reported objective (:meth:`LoopModel.true_objective`, at a fixed resolution
        so that it is smooth) and the true local peaks of |S| and |T| (each a constraint of
        its own), differentiated by central differences of ``_FD_STEP`` in log gain (a gain at
        0 by a forward difference of ``_FD_STEP`` times its typical size).

        Active set: peaks (of |S|, |T| and, with ``mks_max``, |C F S|) within ``MS_RTOL`` of their bound, the noise and upper gain bounds
        within 1e-6, gains at 0; with ``worst_case``, every loop within 1e-3 of the worst.
        Stationarity: the residual ``min || sum_j lam_j grad log f_j + sum_i mu_i grad c_i ||``
        over ``lam, mu >= 0``, ``sum lam = 1`` (``c_i`` the constraints relative to their bound),
        i.e. the largest first-order relative decrease of the objective per unit relative change
        of the gains that the active constraints allow; where the objective has a kink (one
        objective, not worst-case), its gradient may be anything between its one-sided differences. Returns ``{"ok": residual <= KKT_TOL,
        "residual", "active"}``."""
        from scipy.optimize import nnls

        loops, kind = self.loops, self.objective
        ng = loops[0].n_gains
        g0 = loops[0].gvec(gains)
        free = _free_gains(self.use_d, ng)
        typical = loops[0].gvec(typical)
        steps = []  # per free gain: (index, log variable?, step)
        for i in free:
            if g0[i] > 0:
                steps.append((i, True, _FD_STEP))
            else:
                steps.append((i, False, _FD_STEP * (typical[i] if typical[i] > 0 else 1.0)))

        def moved(k, sign):
            g = g0.copy()
            i, logv, d = steps[k]
            g[i] = g[i] * math.exp(sign * d) if logv else g[i] + max(sign, 0.0) * d
            return g

        def grad(fun, sided=False):
            """Central differences; with ``sided``, also the backward and forward ones (lo, hi)."""
            out, lo_s, hi_s = (np.empty(len(steps)) for _ in range(3))
            f0 = None
            for k, (i, logv, d) in enumerate(steps):
                if logv:
                    fp, fm = fun(moved(k, 1.0)), fun(moved(k, -1.0))
                    out[k] = (fp - fm) / (2 * d)
                    if sided:
                        f0 = fun(g0) if f0 is None else f0
                        lo_s[k], hi_s[k] = sorted(((f0 - fm) / d, (fp - f0) / d))
                    else:
                        lo_s[k] = hi_s[k] = out[k]
                else:
                    f0 = fun(g0) if f0 is None else f0
                    out[k] = lo_s[k] = hi_s[k] = (fun(moved(k, 1.0)) - f0) / _FD_STEP  # per _FD_STEP of the typical size
            return (out, lo_s, hi_s) if sided else out

        vals = [lp._smooth_objective(g0, kind) for lp in loops]
        if not all(math.isfinite(v) and v > 0 for v in vals):
            return {"ok": False, "residual": math.inf, "active": [], "reason": "objective not finite and positive"}
        pieces, names, box = [], [], None
        if self.worst_case:
            top = max(vals)
            for j, lp in enumerate(loops):
                if vals[j] >= top * (1 - 1e-3):
                    pieces.append(grad(lambda g, lp=lp: lp._smooth_objective(g, kind)) / top)
                    names.append(f"objective of loop {lp.name!r}")
        else:
            tot = float(np.dot(self.weights, vals))
            gc, g_lo, g_hi = grad(lambda g: float(np.dot(self.weights, [lp._smooth_objective(g, kind) for lp in loops])),
                                  sided=True)
            pieces.append(gc / tot)
            box = (g_lo / tot, g_hi / tot)
            names.append("objective")
        cons, active = [], []
        for lp in loops:
            for key, bound in (("ms", ms_max), ("mt", mt_max), ("mks", mks_max)):
                if bound is None:
                    continue
                for w in lp.active_band(g0, key, bound * (1 - MS_RTOL)):
                    if key == "ms":
                        cfun = lambda g, lp=lp, w=w: 1 / abs(1 + lp.loop_response(g, np.array([w]))[0])
                    elif key == "mks":
                        cfun = lambda g, lp=lp, w=w: abs(lp.noise_response(g, np.array([w]))[0])
                    else:
                        cfun = lambda g, lp=lp, w=w: abs(1 / (1 + 1 / lp.loop_response(g, np.array([w]))[0]))
                    if lp.response is None:
                        continue  # grid-only loops: no off-grid response to differentiate
                    cons.append(grad(cfun) / bound)
                    active.append(f"{dict(ms='Ms', mt='Mt', mks='Mks')[key]} of loop {lp.name!r} at {w:.6g} rad/s")
        jac_lin = np.zeros((ng, len(steps)))  # d g_i / d variable
        for k, (i, logv, d) in enumerate(steps):
            jac_lin[i, k] = g0[i] if logv else (typical[i] if typical[i] > 0 else 1.0)
        if noise is not None and g0[0] + g0[2] / loops[0].tf >= noise * (1 - 1e-6):
            row = np.zeros(ng)
            row[0], row[2] = 1.0, 1.0 / loops[0].tf
            cons.append(row @ jac_lin / noise)
            active.append("noise gain bound")
        for k, (i, logv, d) in enumerate(steps):
            if math.isfinite(hi[i]) and g0[i] >= hi[i] * (1 - 1e-6):
                cons.append(jac_lin[i] / hi[i])
                active.append(f"gain {('kp', 'ki', 'kd', 'kff')[i]} at its upper bound")
            if not logv:
                e = np.zeros(len(steps))
                e[k] = -1.0
                cons.append(e)
                active.append(f"gain {('kp', 'ki', 'kd', 'kff')[i]} at 0")
        G = np.column_stack(pieces)
        C = np.column_stack(cons) if cons else np.zeros((len(steps), 0))
        wsum = 1e3
        A = np.vstack([np.hstack([G, C]), np.concatenate([np.full(G.shape[1], wsum), np.zeros(C.shape[1])])])
        b = np.concatenate([np.zeros(len(steps)), [wsum]])
        coef, _ = nnls(A, b)
        res = float(np.linalg.norm(G @ coef[: G.shape[1]] + C @ coef[G.shape[1]:]))
        if res > KKT_TOL and box is not None:
            # A kink (the IAE where a lobe of |e| vanishes): the objective's slopes lie between its
            # backward and forward differences, so the distance from 0 of {g + C mu : lo <= g <=
            # hi, mu >= 0} is the residual (for a smooth objective the box is O(_FD_STEP) wide).
            from scipy.optimize import lsq_linear

            nv, nc = len(steps), C.shape[1]
            lb = np.concatenate([box[0], np.zeros(nc)])
            ub = np.concatenate([box[1] + 1e-15, np.full(nc, np.inf)])
            sol = lsq_linear(np.hstack([np.eye(nv), C]), np.zeros(nv), bounds=(lb, ub), tol=1e-14)
            res = min(res, float(np.linalg.norm(sol.x[:nv] + C @ sol.x[nv:])))
        return {"ok": res <= KKT_TOL, "residual": res, "active": names + active,
                "gradient": [float(x) for x in (G @ np.full(G.shape[1], 1.0 / G.shape[1]))]}

    def _polish(self, gains, ms_max, mt_max, noise, hi, mks_max=None) -> NDArray | None:
        """A local solve of the TRUE problem from ``gains`` (SLSQP in log gains, central
        differences of ``_FD_STEP / 10``): the reported objective (:meth:`LoopModel.
        _smooth_objective`) under the top peak of |S| (and |T|) and every local one within 10 % of its bound,
        each tracked in a bracket of +-0.3 in log frequency around where it was, the noise bound
        and the gain bounds. The ipopt solve works on a stand-in (sampled loop, smoothed
        ``|e|``, two-rate samples, the bound on fixed frequencies), whose optimum can miss the
        true one's first-order conditions; this step closes that gap. Gains at 0 stay at 0.
        Returns the polished gains if they are stable, within the true bounds (re-verified on
        the full peak search) and better, else None. Bounded: 25 SLSQP iterations."""
        from scipy.optimize import minimize

        loops, kind = self.loops, self.objective
        ng = loops[0].n_gains
        g0 = loops[0].gvec(gains)
        idx = [i for i in _free_gains(self.use_d, ng) if g0[i] > 0]
        if not idx:
            return None
        ms_eff = ms_max * (1 - 1e-5)
        mt_eff = None if mt_max is None else mt_max * (1 - 1e-5)
        mks_eff = None if mks_max is None else mks_max * (1 - 1e-5)

        def gains_of(y):
            g = g0.copy()
            g[idx] = g0[idx] * np.exp(y[: len(idx)])
            return g

        tracked = []  # (loop, key, bound, log omega)
        for lp in loops:
            if lp.response is None:
                return None
            pk0 = lp.peaks(g0, mt=mt_eff is not None)
            if mks_eff is not None:
                pk0.update(lp.noise_peak(g0))
            for key, bound in (("ms", ms_eff), ("mt", mt_eff), ("mks", mks_eff)):
                if bound is not None:  # the top peak and every local peak within 10 % of the bound
                    floor = min(0.9 * bound, pk0[key] * (1 - 1e-9))
                    tracked += [(lp, key, bound, math.log(w)) for _, w in lp.local_peaks(g0, key, floor)]

        def peak_vals(g):
            out = []
            for lp, key, bound, lw in tracked:
                f = (lambda Lv: 1 / np.abs(1 + Lv)) if key == "ms" else (lambda Lv: np.abs(Lv / (1 + Lv)))
                if key == "mks":
                    _, v = _zoom_max(lambda xs: lp._magnitude(g, key, np.exp(xs)), np.array([lw - 0.3]), np.array([lw + 0.3]))
                else:
                    _, v = _zoom_max(lambda xs: f(lp.loop_response(g, np.exp(xs))), np.array([lw - 0.3]), np.array([lw + 0.3]))
                out.append(float(v[0]) / bound)
            return np.array(out)

        f_ref = [max(lp._smooth_objective(g0, kind), 1e-300) for lp in loops]
        nv = len(idx) + (1 if self.worst_case else 0)

        def objs(y):
            g = gains_of(y)
            if any(lp.stability(g) != "stable" for lp in loops):
                return np.full(len(loops), 1e3)
            return np.array([lp._smooth_objective(g, kind) / fr for lp, fr in zip(loops, f_ref)])

        w = self.weights

        def fun(y):
            return y[-1] if self.worst_case else float(np.dot(w, objs(y) * f_ref) / np.dot(w, f_ref))

        def cons(y):
            g = gains_of(y)
            c = [1.0 - peak_vals(g)]
            if self.worst_case:
                c.append(y[-1] - objs(y))
            if noise is not None:  # a hair inside, as the ipopt solve
                c.append(np.array([1.0 - 1e-7 - (g[0] + g[2] / loops[0].tf) / noise]))
            return np.concatenate(c) if c else np.zeros(0)

        d = _FD_STEP / 10

        def jac(fn, vector):
            def jf(y):
                cols = []
                for k in range(nv):
                    e = np.zeros(nv)
                    e[k] = d
                    cols.append((np.atleast_1d(fn(y + e)) - np.atleast_1d(fn(y - e))) / (2 * d))
                return np.array(cols).T if vector else np.array([c[0] for c in cols])
            return jf

        y0 = np.zeros(nv)
        if self.worst_case:
            y0[-1] = float(np.max(objs(y0)))
        # A local step (a factor e^0.25 per gain at most): the tracked peaks stay in their brackets.
        bounds = [(-0.25, min(0.25, math.log(hi[i] / g0[i])) if math.isfinite(hi[i]) else 0.25) for i in idx]
        if self.worst_case:
            bounds.append((0.0, None))
        with np.errstate(all="ignore"):
            try:
                r = minimize(fun, y0, jac=jac(fun, False), method="SLSQP", bounds=bounds,
                             constraints=[{"type": "ineq", "fun": cons, "jac": jac(cons, True)}],
                             options={"maxiter": 25, "ftol": 1e-12})
            except (ValueError, np.linalg.LinAlgError, ArithmeticError):
                return None
        if not np.all(np.isfinite(r.x)):
            return None
        g = gains_of(r.x)
        g = np.minimum(g, np.where(np.isfinite(hi), hi, np.inf))
        if any(lp.stability(g) != "stable" for lp in loops):
            return None
        for lp in loops:
            pk = lp.peaks(g, mt=mt_max is not None)
            if pk["ms"] > ms_max or (mt_max is not None and pk["mt"] > mt_max):
                return None
            if mks_max is not None and lp.noise_peak(g)["mks"] > mks_max:
                return None
        if noise is not None and g[0] + g[2] / loops[0].tf > noise * (1 + 1e-9):
            return None
        old = _combined([lp._smooth_objective(g0, kind) for lp in loops], w, self.worst_case)
        new = _combined([lp._smooth_objective(g, kind) for lp in loops], w, self.worst_case)
        return g if new < old else None

    # ---- public --------------------------------------------------------------------------

    def tune(
        self,
        *,
        ms_max: float = 1.4,
        mt_max: float | None = None,
        max_noise_gain: float | None = None,
        kp_max: float | None = None,
        ki_max: float | None = None,
        kd_max: float | None = None,
        mks_max: float | None = None,
    ) -> TuningResult:
        """Optimal gains under the bounds; see :class:`TuningResult` for what is guaranteed.

        Parameters
        ----------
        ms_max : float
            Bound on the true peak sensitivity max|1/(1 + L)|, in (1, 10).
        mt_max : float, optional
            Bound on the true peak complementary sensitivity, in (1, 10).
        max_noise_gain : float, optional
            Bound on the controller's high-frequency gain ``kp + kd/tf`` (loop units, e.g.
            N m s/rad), needed where robustness alone does not limit the gains. It bounds
            the controller alone at infinite frequency, not the noise gain of the loop: for
            that, use ``mks_max``.
        kp_max, ki_max, kd_max : float, optional
            Upper gain bounds (loop units; None or inf: none). The result does not depend on
            them once they exceed the optimum.
        mks_max : float, optional
            Bound on the true peak noise sensitivity ``Mks = max over frequency of |C F S|``
            (:meth:`LoopModel.noise_peak`; loop units: control signal per measured-output unit,
            e.g. N m s/rad), the loop as tuned including every filter on the noise path;
            enforced like Ms (grid rows, then the true peak verified and its frequency added
            until it holds). Needs loops with a noise path (``continuous_loop``, ``drive_loop``).

        Returns
        -------
        TuningResult
        """
        t_start = time.perf_counter()
        ms_max, mt_max, noise = _check_bounds(ms_max, mt_max, max_noise_gain)
        mks_max = _check_mks(mks_max)
        if mks_max is not None and any(lp.noise is None or lp.response is None for lp in self.loops):
            raise ValueError("mks_max given for loops without a noise path; expected continuous_loop or drive_loop models")
        ng = self.loops[0].n_gains
        hi = [_gain_limit("kp_max", kp_max), _gain_limit("ki_max", ki_max),
              _gain_limit("kd_max", kd_max) if self.use_d else 0.0, 1.0][:ng]
        ms_eff = ms_max * (1 - 1e-6)
        mt_eff = mt_max * (1 - 1e-6) if mt_max is not None else None
        mks_eff = mks_max * (1 - 1e-6) if mks_max is not None else None
        order = self._ranked(ms_eff, mt_eff, noise, hi, mks_eff)
        if not order.size:
            sc = self._scan_data()
            probe = np.flatnonzero(sc["ms"] <= ms_eff)[:20]
            if probe.size and all(any(lp.stability(sc["grid"][i]) == "marginal" for lp in self.loops) for i in probe):
                raise ValueError(
                    "every scanned gain leaves a closed-loop pole on the stability boundary: the plant has a "
                    "pole the loop cannot move (e.g. an angle state under speed feedback); expected a plant without it"
                )
            raise ValueError(
                f"no stabilising {self.controller.upper()} gains meet Ms <= {ms_max:g}"
                + (f", Mt <= {mt_max:g}" if mt_max is not None else "")
                + (f", kp + kd/tf <= {noise:g}" if noise is not None else "")
                + (f", Mks <= {mks_max:g}" if mks_max is not None else "")
                + " on the scan; relax the constraints"
            )
        nlp = self._nlp(mt_max is not None, noise is not None, mks_max is not None)
        runs, cands = [], []
        typical = np.max(self._scan_data()["grid"][order[:20]], axis=0)
        for g0 in self._starts(order):
            cand, info = self._solve_from(nlp, g0, ms_max, mt_max, noise, hi, typical, mks_max)
            runs.append(info)
            if cand is not None:
                cand.value = self._value(cand.gains)
                cands.append(cand)
                if cand.converged:
                    break
        warnings: list[str] = []
        conv = [c for c in cands if c.converged]
        ipopt_status = runs[0].get("status", "not run") if runs else "not run"
        if conv:
            best = min(conv, key=lambda c: c.value)
            status = "optimal" if best.stats["return_status"] == "Solve_Succeeded" else "optimal (acceptable level)"
            ipopt_status = best.stats["return_status"]
        elif cands:
            best = min(cands, key=lambda c: c.value)
            ipopt_status = best.stats["return_status"]
            status = f"not converged: {ipopt_status}"
        else:
            best = None
            for i in order[:50]:
                g = self._scan_data()["grid"][i]
                pks = [lp.peaks(g) for lp in self.loops]
                if all(pk["ms"] <= ms_max and (mt_max is None or pk["mt"] <= mt_max) for pk in pks) and (
                        mks_max is None or all(lp.noise_peak(g)["mks"] <= mks_max for lp in self.loops)):
                    best = _Candidate(np.array(g, float), {"return_status": "scan point kept", "iter_count": 0},
                                      pks, self._value(g), False, False)
                    break
            if best is None:
                raise ValueError(
                    f"no {self.controller.upper()} gains verified within Ms <= {ms_max:g}"
                    + (f", Mt <= {mt_max:g}" if mt_max is not None else "")
                    + f" (solver runs: {'; '.join(r.get('result', '?') for r in runs)}); relax the constraints"
                )
            status = f"not converged: scan point kept (ipopt: {ipopt_status}; {runs[0].get('result', '') if runs else ''})"
        gains, peaks = best.gains, best.peaks
        # "optimal" is decided here, on the true problem, not by ipopt's exit status.
        first = self._first_order(gains, ms_max, mt_max, noise, hi, typical, mks_max)
        polished = False
        for _ in range(_POLISH_ROUNDS):
            if first["ok"] or best.stats.get("return_status") == "scan point kept":
                break
            pol = self._polish(gains, ms_max, mt_max, noise, hi, mks_max)
            if pol is None:
                break
            gains, polished = pol, True
            peaks = [lp.peaks(gains) for lp in self.loops]
            first = self._first_order(gains, ms_max, mt_max, noise, hi, typical, mks_max)
        if first["ok"]:
            status = "optimal"
        elif best.stats.get("return_status") != "scan point kept":
            status = (f"not proven optimal: first-order residual {first['residual']:.3g} > {KKT_TOL:g} at the "
                      f"returned gains (ipopt: {ipopt_status})")
        margins = [lp.margins(gains, pk) for lp, pk in zip(self.loops, peaks)]
        converged = status.startswith("optimal")
        if not converged:
            warnings.append(f"tuner {status}; the gains are the best verified point found, not a proven optimum")
        inf_vals, tails, hor_vals, sampled = [], [], [], []
        for lp in self.loops:
            v, tb = lp.true_objective(gains, self.objective)
            inf_vals.append(v)
            tails.append(tb)
            hor_vals.append(lp.objective(gains, self.objective))
            sampled.append(lp.objective_to_infinity(gains, self.objective)[0] if lp.continuous is not None else v)
        if not all(math.isfinite(v) for v in inf_vals):
            raise ValueError("the tuned loop's objective is not finite (an ill-conditioned plant model?); "
                             "expected a plant whose closed loop the tuner can evaluate")
        horizon_short = False
        if self.objective != "ie":
            for lp, v, hv in zip(self.loops, sampled, hor_vals):
                if v > 0 and (v - hv) > 1e-3 * v:
                    horizon_short = True
                    warnings.append(
                        f"loop {lp.name!r}: its horizon {lp.n_steps * lp.h:.4g} s holds {100 * hv / v:.2f} % of the "
                        f"{self.objective.upper()}; the optimiser saw the truncated objective (a longer horizon may give better gains)"
                    )
        for lp, tb, v in zip(self.loops, tails, inf_vals):
            if lp.continuous is not None:
                if tb > CONT_RTOL * v:
                    warnings.append(f"loop {lp.name!r}: the continuous {self.objective.upper()}'s error estimate "
                                    f"{tb:.3g} exceeds {CONT_RTOL:g} of the value")
            elif tb > TAIL_RTOL * v:
                warnings.append(f"loop {lp.name!r}: the {self.objective.upper()} tail bound {tb:.3g} exceeds {TAIL_RTOL:g} of the value")
        if not all(pk["exact"] for pk in best.peaks):
            warnings.append("Ms/Mt verified on the loop's frequency grid only (a loop model has no frequency-response function)")
        names = ("kp", "ki", "kd", "kff")
        for i, lim in enumerate(hi[:3]):
            if math.isfinite(lim) and lim > 0 and gains[i] >= lim * (1 - 1e-6):
                warnings.append(f"{names[i]} = {gains[i]:.6g} is at its bound {names[i]}_max = {lim:g}")
        pid = PID(float(gains[0]), float(gains[1]), float(gains[2]), tf=float(self.loops[0].tf),
                  kff=float(gains[3]) if len(gains) > 3 else 0.0)
        mks = None
        if all(lp.noise is not None and lp.response is not None for lp in self.loops):
            mks = max(lp.noise_peak(gains)["mks"] for lp in self.loops)
        return TuningResult(
            mks=mks,
            pid=pid,
            objective=_combined(inf_vals, self.weights, self.worst_case),
            kind=self.objective,
            per_loop=[float(v) for v in inf_vals],
            margins=margins,
            stats={
                "solver": "ipopt",
                "status": ipopt_status,
                "iterations": sum(r.get("iterations", 0) for r in runs),
                "runs": runs,
                "scan_points": int(order.size),
                "ms_bound_active": any(a.startswith("Ms") for a in first["active"]),
                "first_order": {k: first[k] for k in ("ok", "residual", "active")},
                "polished": polished,
                "objective_sampled": _combined(sampled, self.weights, self.worst_case),
                "objective_horizon": _combined(hor_vals, self.weights, self.worst_case),
                "horizon_short": horizon_short,
                "tail_bound": float(max(tails)),
                "horizon_s": float(self.loops[0].n_steps * self.loops[0].h),
                "wall_time_s": time.perf_counter() - t_start,
            },
            status=status,
            converged=converged,
            warnings=warnings,
        )


# The Tuner of the last tune_loops call (strong references to its loops, compared by identity,
# so an id can never be reused): a performance memo only, since a Tuner's result does not depend
# on what it solved before.
_RECENT: list = []


def tune_loops(
    loops: Sequence[LoopModel],
    *,
    objective: str = "iae",
    controller: str = "pi",
    ms_max: float = 1.4,
    mt_max: float | None = None,
    max_noise_gain: float | None = None,
    kp_max: float | None = None,
    ki_max: float | None = None,
    kd_max: float | None = None,
    weights: Sequence[float] | None = None,
    worst_case: bool = False,
    mks_max: float | None = None,
) -> TuningResult:
    """Optimise PI/PID gains for one or several loop models: ``Tuner(loops, ...).tune(...)``.

    Parameters
    ----------
    loops : sequence of LoopModel
        Loop models of the same structure (e.g. one per load level).
    objective, controller, weights, worst_case
        See :class:`Tuner`.
    ms_max, mt_max, max_noise_gain, kp_max, ki_max, kd_max, mks_max
        See :meth:`Tuner.tune`.

    Returns
    -------
    TuningResult

    Examples
    --------
    >>> import control
    >>> lp = continuous_loop(control.tf([1.0], [1.0, 2.0, 1.0]), tf=0.1, horizon=40.0, n_steps=400)
    >>> r = tune_loops([lp], objective="ie", ms_max=1.4)
    >>> r.converged, round(r.ms, 4), abs(r.objective * r.pid.ki - 1) < 1e-9
    (True, 1.4, True)
    """
    loops = tuple(loops)
    try:
        w_key = None if weights is None else tuple(float(x) for x in weights)
    except (TypeError, ValueError):
        w_key = object()  # never equal: the Tuner below reports the bad weights
    key = (objective, controller, w_key, worst_case)
    tuner = None
    if _RECENT:
        old_loops, old_key, old = _RECENT[0]
        if old_key == key and len(old_loops) == len(loops) and all(a is b for a, b in zip(old_loops, loops)):
            tuner = old
    if tuner is None:
        tuner = Tuner(loops, objective=objective, controller=controller, weights=weights, worst_case=worst_case)
        _RECENT[:] = [(loops, key, tuner)]
    return tuner.tune(ms_max=ms_max, mt_max=mt_max, max_noise_gain=max_noise_gain,
                      kp_max=kp_max, ki_max=ki_max, kd_max=kd_max, mks_max=mks_max)


def _phase_frequency(a, b, c, d, delay: float = 0.0) -> tuple[float | None, float]:
    """Frequency (rad/s) where the plant's phase (with its exact delay, s) crosses -135 deg (first
    from above, else the first crossing), on a grid spanning its poles and zeros; and the phase
    (rad) at the top."""
    poles, zeros = _plant_roots(a, b, c, d)
    mags = np.abs(np.concatenate([poles, zeros]))
    mags = mags[(mags > 0) & np.isfinite(mags)]
    if not mags.size:
        mags = np.array([1.0])
    w = np.logspace(math.log10(mags.min() / 1e3), math.log10(mags.max() * 1e3), 4000)
    resp = _ss_response(a, b, c, w) + d[0, 0]
    if delay > 0:
        resp = resp * np.exp(-1j * w * delay)
    ph = np.unwrap(np.angle(resp))
    x = ph + 0.75 * np.pi
    cross = np.flatnonzero(np.sign(x[:-1]) != np.sign(x[1:]))
    if not cross.size:
        return (None if x[0] > 0 else float(w[0])), float(ph[-1])
    desc = cross[x[cross] > 0]
    i = desc[0] if desc.size else cross[0]
    return float(w[i + 1]), float(ph[-1])


def tune_pid(
    plant,
    *,
    objective: str = "iae",
    controller: str = "pi",
    ms_max: float = 1.4,
    mt_max: float | None = None,
    max_noise_gain: float | None = None,
    disturbance: str | int | None = None,
    step: float = 1.0,
    horizon: float | None = None,
    tf: float | None = None,
    n_steps: int = 2000,
    kp_max: float | None = None,
    ki_max: float | None = None,
    kd_max: float | None = None,
    mks_max: float | None = None,
    filter_order: int = 0,
    filter_tf: float | None = None,
    ideal: bool = False,
    delay: float = 0.0,
    delay_order: int = 6,
    setpoint_weights: bool = False,
) -> TuningResult:
    """Tune a PI (default) or PID for load-disturbance rejection on any SISO LTI plant.

    Parameters
    ----------
    plant : control.LTI
        Continuous transfer function or state space; control input first, optional second
        (or ``disturbance``-named) input for the load; one output. Open-loop unstable plants
        are fine (stability is judged on the closed loop). At most ``MAX_ORDER`` (30) states,
        finite coefficients, dynamics from the control input to the output and no undamped
        poles on the imaginary axis (other than at 0); anything else is refused with a
        ValueError before any work. A plant whose gain is far from 1 (e.g. 1e-12 or 1e200) is
        tuned as ``P/k0`` and its gains scaled back (they scale inversely with the plant gain).
    objective : {"ie", "iae", "itae", "ise"}
        Integral (to infinity) of the error after a disturbance step of size ``step``.
    controller : {"pi", "pid"}
        PID uses a derivative filter with time constant ``tf`` (s).
    ms_max, mt_max : float
        Bounds on the true peak sensitivity and (optionally) complementary sensitivity, in
        (1, 10).
    max_noise_gain : float, optional
        Bound on the controller's high-frequency gain ``kp + kd/tf`` (plant-input units per
        output unit), needed where robustness alone does not limit the gains (the plant's phase
        stays above -135 deg at high frequency). It bounds the controller alone at infinite
        frequency, not the loop's noise gain ``max |C S|`` (which may be larger: use
        ``mks_max`` for that).
    mks_max : float, optional
        Bound on the true peak noise sensitivity ``Mks = max over omega of |C(j omega) S(j
        omega)|`` (plant-input units per output unit) of the loop as tuned; the peak is found
        on a dense grid refined near it (six decades beyond the plant's dynamics, where ``|C
        S|`` tends to its high-frequency limit). Given, it replaces the default noise-gain bound.
        With a measurement filter, ``C`` is the controller with its filter, ``C F``.
    filter_order : {0, 1, 2}
        Measurement filter on the whole controller, ``C(s) F(s)`` with ``F = 1/(Tf s + 1)`` (1)
        or ``1/(Tf^2 s^2/2 + Tf s + 1)`` (2); 0: none (the default, as before).
    filter_tf : float, s, optional
        The filter's time constant; by default (None) a decision variable: the objective's
        optimum over ``Tf`` (a log scan over five decades below ``1/w135`` then a bounded
        Brent search, each point a full tuning), reported in ``result.filter``.
    ideal : bool
        Ideal derivative ``kd s`` (PID without a derivative filter; ``tf`` unused). Without a
        measurement filter it needs a plant of relative degree 2 or more and no ``mks_max``
        (``|C S|`` then grows without bound with frequency, so the reported Mks is inf).
    delay : float, s
        Exact plant delay ``e^{-s delay}`` (on the plant output, so on the control and the
        disturbance path alike). Ms, Mt, Mks and the margins use the exact ``e^{-j omega
        delay}``. The reported IAE/ITAE is that of the loop with the exact delay (simulated
        with the delay an exact number of samples and the delayed state interpolated linearly
        between them, the step halved to ``CONT_RTOL``; :class:`_DelayedLoop`), and the
        first-order check and polish use it; the ipopt stand-in uses a Pade model of order
        ``delay_order`` (``stats["objective_pade"]`` its value at the result). IE is exact
        either way (``|u_ss|/ki``); ISE is that of the Pade model, its change with the order
        + 2 in ``stats["delay_pade_change"]`` (a warning above 1e-4).
    delay_order : int
        Pade order of the delay in the ipopt stand-in (1 .. 10, default 6).
    setpoint_weights : bool
        After the load-disturbance design, 2-DOF setpoint weights ``b`` (and ``c`` for a PID
        with a filtered derivative; 0 otherwise) in [0, 1] for the least IAE of ``r - y`` after
        a unit setpoint step, the gains fixed (the weights do not enter the loop transfer, so
        Ms, Mt, Mks and the load response are unchanged); in ``result.setpoint``. With a delay
        the setpoint response uses the Pade model of order ``delay_order``.
    disturbance : str or int, optional
        Name or index of the disturbance input (default: the second input, else the control
        input).
    step : float
        Disturbance step size (disturbance-input units), finite and non-zero.
    horizon : float, s, optional
        Simulated response length (the tail beyond it is added exactly or bounded); by default
        40 / w135, with w135 where the plant's phase crosses -135 deg, lengthened up to 16x
        while the horizon holds less than 99.9 % of the objective.
    tf : float, s, optional
        Derivative filter time constant; by default 0.1 / w135.
    n_steps : int
        Samples over the horizon (10 .. 200000).
    kp_max, ki_max, kd_max : float, optional
        Upper gain bounds (None or inf: none).

    Returns
    -------
    TuningResult
        ``objective`` is that of the CONTINUOUS closed loop with the returned gains (IE and
        ISE in closed form, IAE and ITAE integrated to a relative ``CONT_RTOL``), not that of
        the sampled stand-in the optimiser works on (``stats["objective_sampled"]``);
        ``status`` is ``"optimal"`` only where an independent first-order check of the true
        problem holds (see :class:`TuningResult`).

    Examples
    --------
    >>> import control
    >>> r = tune_pid(control.tf([1], [1, 3, 3, 1]), objective="ie", ms_max=1.6)
    >>> r.status, r.ms <= 1.6, r.pid.ki > 0.4
    ('optimal', True, True)
    """
    import control

    if objective not in OBJECTIVES:
        raise ValueError(f"objective = {objective!r}; expected one of {', '.join(OBJECTIVES)}")
    if controller not in CONTROLLERS:
        raise ValueError(f"controller = {controller!r}; expected 'pi' or 'pid'")
    _check_bounds(ms_max, mt_max, max_noise_gain)
    mks_max = _check_mks(mks_max)
    filter_order, _, ideal, delay, delay_order = _check_structure(
        filter_order, 1.0 if filter_tf is None else filter_tf, ideal, delay, delay_order)
    if filter_tf is not None and not filter_order:
        raise ValueError(f"filter_tf = {filter_tf!r} without a filter; expected filter_order = 1 or 2")
    if not isinstance(setpoint_weights, (bool, np.bool_)):
        raise ValueError(f"setpoint_weights = {setpoint_weights!r}; expected True or False")
    if ideal and controller != "pid":
        raise ValueError("ideal = True with controller = 'pi'; expected controller = 'pid' (the ideal derivative)")
    if ideal and not filter_order and mks_max is not None:
        raise ValueError("mks_max with an ideal PID and no measurement filter: |C S| grows without bound with "
                         "frequency; expected filter_order = 1 or 2")
    step = _number("step", step, expected="a finite non-zero step size")
    if step == 0.0:
        raise ValueError("step = 0.0; expected a finite non-zero step size")
    if horizon is not None:
        horizon = _number("horizon", horizon, lo=0.0, expected="a positive finite time in s")
    if tf is not None:
        tf = _number("tf", tf, lo=0.0, expected="a positive finite time constant in s")
    n_steps = _int_steps("n_steps", n_steps)
    limits = {k: _gain_limit(k, v) for k, v in (("kp_max", kp_max), ("ki_max", ki_max), ("kd_max", kd_max))}
    sys = _checked_plant(plant)
    # Scale invariance: a plant of gain k0 far from 1 is tuned as P/k0 (L = (P/k0)(k0 C), the same
    # loop), its gains divided by k0 and its objective multiplied by k0 (ISE: k0^2) after.
    k0 = _gain_scale(sys)
    if k0 != 1.0:
        sys = control.ss(sys.A, sys.B, np.asarray(sys.C) / k0, np.asarray(sys.D) / k0,
                         inputs=sys.input_labels, outputs=sys.output_labels, name=sys.name)
        limits = {k: v * k0 for k, v in limits.items()}
        if max_noise_gain is not None:
            max_noise_gain = float(max_noise_gain) * k0
        if mks_max is not None:
            mks_max = mks_max * k0
    a, b, c, d = (np.asarray(m, dtype=float) for m in (sys.A, sys.B, sys.C, sys.D))
    auto_horizon = horizon is None
    default_note = None
    if horizon is None or tf is None or max_noise_gain is None or (filter_order and filter_tf is None):
        w135, ph_top = _phase_frequency(a, b[:, :1], c, d[:, :1], delay)
        unbounded = (ph_top > -0.75 * np.pi + 1e-3 and max_noise_gain is None and mks_max is None
                     and not math.isfinite(limits["kp_max"]))
        if unbounded or (w135 is None and (horizon is None or tf is None)):
            # Robustness alone does not limit the gains (Ms -> 1 as they grow, e.g. 1/(s-1)): the
            # default design puts the crossover about a decade above the plant's fastest pole or
            # zero w0, by bounding the controller's high-frequency gain at 10 / |P(j w0)|.
            poles, zeros = _plant_roots(a, b[:, :1], c, d[:, :1])
            mags = np.abs(np.concatenate([poles, zeros]))
            mags = mags[(mags > 0) & np.isfinite(mags)]
            w0 = float(mags.max()) if mags.size else 1.0
            p0 = abs(complex(_ss_response(a, b[:, :1], c, np.array([w0]))[0] + d[0, 0]))
            if max_noise_gain is None and mks_max is None and not math.isfinite(limits["kp_max"]):
                max_noise_gain = 10.0 / p0
                default_note = (f"robustness alone does not limit the gains of this plant (phase "
                                f"{math.degrees(ph_top):.0f} deg at high frequency): tuned with the default noise-gain "
                                f"bound max_noise_gain = 10/|P(j w0)| = {max_noise_gain / k0:.4g} at w0 = {w0:.4g} rad/s "
                                "(crossover about a decade above the plant's fastest pole or zero); pass "
                                "max_noise_gain= to choose")
            if w135 is None:
                horizon = horizon if horizon is not None else 4.0 / w0
                tf = tf if tf is not None else 0.01 / w0
        if w135 is not None:
            horizon = horizon if horizon is not None else 40.0 / w135
            tf = tf if tf is not None else 0.1 / w135
    structure = {"filter_order": filter_order, "ideal": ideal, "delay": delay, "delay_order": delay_order}
    bounds = {"ms_max": ms_max, "mt_max": mt_max, "max_noise_gain": max_noise_gain, "mks_max": mks_max, **limits}

    def solve(t_filter, hor):
        """One tuning at the filter time constant ``t_filter``; the horizon lengthened as before."""
        res = None
        for _ in range(3):
            loop = continuous_loop(sys, tf=tf, horizon=hor, n_steps=n_steps, disturbance=disturbance, step=step,
                                   **({**structure, "filter_tf": t_filter} if (filter_order or ideal or delay) else {}))
            res = Tuner([loop], objective=objective, controller=controller).tune(**bounds)
            if not (auto_horizon and res.stats["horizon_short"]):
                break
            hor *= 4.0
        return res, hor

    if filter_order and filter_tf is None:
        res, horizon = _optimal_filter(solve, horizon, 1.0 / (w135 if w135 is not None else 100.0 / horizon))
    else:
        res, horizon = solve(filter_tf, horizon)
    if filter_order or ideal or delay:
        res = _with_structure(res, sys, tf, horizon, n_steps, disturbance, step, {**structure, "filter_tf": filter_tf},
                              objective)
    if setpoint_weights:
        t_f = res.filter["tf_s"] if res.filter else None
        loop = continuous_loop(sys, tf=tf, horizon=horizon, n_steps=n_steps, disturbance=disturbance, step=step,
                               **{**structure, "filter_tf": t_f})
        res = replace(res, setpoint=_setpoint_weights(loop, (res.pid.kp, res.pid.ki, res.pid.kd), ideal))
    if k0 != 1.0:
        res = _rescaled(res, k0, limits)
    if default_note is not None:
        res.warnings.insert(0, default_note)
    return res


#: The filter time constant's search range (tune_pid, ``filter_tf=None``): these decades below 1/w135.
_FILTER_DECADES = 4
#: Log-scan points over that range before the bounded Brent search.
_FILTER_SCAN = 7


def _optimal_filter(solve: Callable, horizon: float, t_ref: float) -> tuple[TuningResult, float]:
    """The measurement filter's time constant as a decision variable: the tuned objective (each
    value a full tuning by ``solve(Tf, horizon)``) scanned on ``_FILTER_SCAN`` log points over
    ``[t_ref 10^-_FILTER_DECADES, t_ref]``, then minimised by a bounded Brent search (log Tf,
    2e-3 absolute, at most 20 evaluations) between the best point's neighbours. Its own
    first-order check: neither one-sided slope of the objective in log Tf (steps of +-0.02,
    relative to the objective) may fall below ``-KKT_TOL`` (no descent direction; a kink where
    the active peak changes is a minimum too), except outwards at an end of the range; else
    the status says so. Results not proven optimal or infeasible count as infinite."""
    from scipy.optimize import minimize_scalar

    cache: dict = {}

    def value(lt: float) -> float:
        key = float(lt)
        if key not in cache:
            try:
                r, hor = solve(math.exp(key), horizon)
                cache[key] = (r.objective if r.converged else math.inf, r, hor)
            except ValueError:
                cache[key] = (math.inf, None, None)
        return cache[key][0]

    lo_all, hi_all = math.log(t_ref) - _FILTER_DECADES * math.log(10.0), math.log(t_ref)
    grid = np.linspace(lo_all, hi_all, _FILTER_SCAN)
    vals = np.array([value(x) for x in grid])
    if not np.any(np.isfinite(vals)):
        raise ValueError(f"no filter time constant in [{math.exp(lo_all):.4g}, {math.exp(hi_all):.4g}] s gives a "
                         "tuning proven optimal under the bounds; relax the constraints or pass filter_tf=")
    i = int(np.argmin(vals))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    minimize_scalar(value, bounds=(lo, hi), method="bounded", options={"xatol": 2e-3, "maxiter": 20})
    best = min(cache, key=lambda k: cache[k][0])
    v0, res, hor = cache[best]
    at_lo, at_hi = best - lo_all < 0.02, hi_all - best < 0.02
    up = (value(best + 0.02) - v0) / (0.02 * v0) if not at_hi else math.inf
    down = (value(best - 0.02) - v0) / (0.02 * v0) if not at_lo else math.inf
    slope = min(up, down)  # the steepest descent the objective allows (negative: it can still decrease)
    at_bound = at_lo or at_hi
    ok = slope >= -KKT_TOL
    info = {"tf_s": math.exp(best), "range_s": [math.exp(lo_all), math.exp(hi_all)], "evaluations": len(cache),
            "slope_up": up, "slope_down": down, "at_bound": at_bound, "first_order_ok": ok}
    stats = {**res.stats, "filter_search": info}
    res = replace(res, stats=stats)
    if not ok:
        res = replace(res, status=f"not proven optimal: objective slope {slope:.3g} per unit log Tf below -{KKT_TOL:g} "
                                  f"at the filter time constant {math.exp(best):.6g} s", converged=False,
                      warnings=res.warnings + ["the filter time constant is not proven optimal (see stats['filter_search'])"])
    elif at_bound:
        res = replace(res, warnings=res.warnings + [
            f"the filter time constant {math.exp(best):.4g} s is at an end of its search range "
            f"[{math.exp(lo_all):.4g}, {math.exp(hi_all):.4g}] s (the objective keeps improving that way)"])
    return res, hor


def _with_structure(res: TuningResult, sys, tf: float, horizon: float, n_steps: int, disturbance, step: float,
                    structure: dict, objective: str) -> TuningResult:
    """``res`` with its loop structure stated: ``filter`` (order, Tf, derivative ideal or filtered),
    the delay's Pade check (the objective recomputed with the Pade order + 2:
    ``stats["delay_pade_change"]``, relative; a warning above 1e-4) and, for an ideal PID
    without a measurement filter, Mks = inf (|C S| grows as kd omega)."""
    warnings = list(res.warnings)
    stats = dict(res.stats)
    order, ideal, delay = structure["filter_order"], structure["ideal"], structure["delay"]
    t_filter = stats.get("filter_search", {}).get("tf_s", structure.get("filter_tf"))
    filt = None
    if order or ideal:
        filt = {"order": order, "tf_s": t_filter if order else None,
                "derivative": "ideal" if ideal else "filtered"}
    mks = res.mks
    if ideal:
        warnings.append("ideal derivative: the law is kp + ki/s + kd s" + (" times the filter F(s)" if order else "")
                        + "; pid.tf is not part of it")
        if not order and res.pid.kd > 0:
            mks = math.inf
    if delay > 0:
        g = (res.pid.kp, res.pid.ki, res.pid.kd)
        stats["delay_s"] = delay
        if objective == "ise":
            # ISE is computed on the Pade model: its change with the order + 2 says how exact it is.
            loop = continuous_loop(sys, tf=tf, horizon=horizon, n_steps=n_steps, disturbance=disturbance, step=step,
                                   **{**structure, "delay_order": structure["delay_order"] + 2, "filter_tf": t_filter})
            change = abs(loop.objective_continuous(g, objective)[0] - res.objective) / res.objective
            stats["delay_pade_change"] = change
            if change > 1e-4:
                warnings.append(f"the ISE changes by {100 * change:.3g} % with the delay's Pade order "
                                f"{structure['delay_order']} -> {structure['delay_order'] + 2}; raise delay_order")
        elif objective in ("iae", "itae"):
            # Reported: the exact delayed loop's; what the optimiser's Pade stand-in says of it:
            loop = continuous_loop(sys, tf=tf, horizon=horizon, n_steps=n_steps, disturbance=disturbance, step=step,
                                   **{**structure, "filter_tf": t_filter})
            stats["objective_pade"] = loop.objective_continuous(g, objective)[0]
    return replace(res, filter=filt, mks=mks, stats=stats, warnings=warnings)


#: Setpoint-weight search: samples of the basis responses per loop-model sample, and the grid of
#: the scan over b (and c) before the local refinement.
_SP_GRID = 41


def _setpoint_basis(lp: LoopModel, gains):
    """Closed loop ``X' = A X + (B0 + b Bb + c Bc) r`` of a unit setpoint step under the 2-DOF law
    ``u = kp (b r - y_f) + ki int (r - y_f) + kd D(c r - y_f)`` (``y_f`` the measured output; the
    derivative filter state driven by ``c r - y_f``), from the continuous loop of ``lp``:
    ``(A, B0, Bb, Bc)``; the output is ``-Ce X`` (``Ce`` the load loop's error row)."""
    c0, mats, _ = lp.continuous
    g = lp.gvec(gains)
    acl = c0 + sum(gi * m for gi, m in zip(g, mats))
    N = acl.shape[0]
    n, i_i, i_z = N - 2, N - 2, N - 1
    bu = mats[1][:n, i_i]
    b0, bb, bc = np.zeros(N), np.zeros(N), np.zeros(N)
    b0[i_i] = 1.0  # the integral acts on r - y_f
    bb[:n] = g[0] * bu
    bc[:n] = g[2] * bu / lp.tf
    bc[i_z] = 1.0 / lp.tf
    return acl, b0, bb, bc


def _setpoint_iae(acl, bsum, cy, h: float, rtol: float) -> tuple[float, float]:
    """IAE of ``e = 1 - cy X`` after a unit setpoint step (``X' = acl X + bsum``, from rest),
    sampled exactly every ``h`` and summed by the trapezoid rule to infinity, halving ``h``
    until two values agree within ``rtol`` (Richardson estimate, at most ``_CONT_HALVINGS``)."""
    prev, val, err = None, math.inf, math.inf
    for _ in range(_CONT_HALVINGS + 1):
        ad, bd = _zoh(acl, bsum[:, None], h)
        x_inf = np.linalg.solve(np.eye(ad.shape[0]) - ad, bd[:, 0])
        # e_k = 1 - cy X_k = -cy (X_k - x_inf) (zero steady error); e_0 = 1: the trapezoid halves it.
        val, tail = _block_sum(ad, -cy, -x_inf, 0, 0.0, h, "iae", min(rtol, TAIL_RTOL))
        val -= 0.5 * h
        if prev is not None:
            err = abs(val - prev) / 3.0 + tail
            if err <= rtol * val:
                break
        prev = val
        h /= 2.0
    return val, err


def _setpoint_weights(lp: LoopModel, gains, ideal: bool) -> dict:
    """2-DOF setpoint weights for the load-optimal ``gains`` (fixed: b and c do not enter the loop
    transfer, so Ms/Mt/Mks and the load response are unchanged). Goal: the least IAE of the
    error ``r - y`` after a unit setpoint step. The error is affine in (b, c), so that IAE is
    convex in them: a scan of ``_SP_GRID`` points per weight in [0, 1] on the sampled basis
    responses, then a Nelder-Mead search from the best point on the same samples (weights
    clipped to [0, 1]), and the result's IAE recomputed to ``CONT_RTOL`` (:func:`_setpoint_iae`). ``c`` is 0 for an
    ideal derivative (a setpoint step would give an impulse) and for a PI."""
    from scipy.optimize import minimize

    acl, b0, bb, bc = _setpoint_basis(lp, gains)
    cy = -lp.Ce  # the output row over X (Ce is the load error row, -y)
    h = lp.h / 4.0
    n_s = 4 * lp.n_steps
    N = acl.shape[0]
    basis = []
    for bvec in (b0, bb, bc):
        ad, bd = _zoh(acl, bvec[:, None], h)
        x = np.zeros(N)
        ys = np.empty(n_s)
        for k in range(n_s):
            ys[k] = cy @ x
            x = ad @ x + bd[:, 0]
        basis.append(ys)
    use_c = lp.gvec(gains)[2] > 0 and not ideal
    wts = np.full(n_s, h)
    wts[0] = 0.5 * h

    def iae(b, c):
        return float(wts @ np.abs(1.0 - basis[0] - b * basis[1] - c * basis[2]))

    # Scan (vectorised over the grid), then Nelder-Mead from the best grid point, clipped to [0, 1].
    grid = np.linspace(0.0, 1.0, _SP_GRID)
    bs, cs = np.meshgrid(grid, grid if use_c else np.array([0.0]), indexing="ij")
    bs, cs = bs.ravel(), cs.ravel()
    vals = np.concatenate([wts @ np.abs(1.0 - basis[0][:, None] - basis[1][:, None] * bs[None, j : j + 200]
                                        - basis[2][:, None] * cs[None, j : j + 200]) for j in range(0, bs.size, 200)])
    i = int(np.argmin(vals))
    x0 = np.array([bs[i], cs[i]])[: 2 if use_c else 1]

    def f(x):
        x = np.clip(x, 0.0, 1.0)
        return iae(x[0], x[1] if use_c else 0.0)

    r = minimize(f, x0, method="Nelder-Mead", options={"xatol": 1e-7, "fatol": 1e-12, "maxfev": 400})
    x = np.clip(r.x, 0.0, 1.0) if f(r.x) <= vals[i] else x0
    b, c = float(x[0]), float(x[1]) if use_c else 0.0
    val, err = _setpoint_iae(acl, b0 + b * bb + c * bc, cy, lp.h, CONT_RTOL)
    one = _setpoint_iae(acl, b0 + bb + (bc if use_c else 0.0), cy, lp.h, CONT_RTOL)[0]
    y = basis[0] + b * basis[1] + c * basis[2]
    return {"b": b, "c": c, "goal": "least IAE of r - y after a unit setpoint step, load-optimal gains fixed",
            "iae": val, "iae_error": err, "iae_unweighted": one, "overshoot": max(float(np.max(y)) - 1.0, 0.0)}


#: Largest plant order :func:`tune_pid` accepts (states of its state-space realisation): the
#: tuner's work grows as the cube of the order (order 20: ~3 s, 30: ~30 s, 100: ~2 min, 800: 38 GiB).
MAX_ORDER = 30
#: Plant gains |P(j w_ref)| outside [1/_GAIN_SPAN, _GAIN_SPAN] are normalised (see tune_pid).
_GAIN_SPAN = 1e3


def _checked_plant(plant):
    """``plant`` as a continuous SISO state space with finite matrices and dynamics, or a
    ValueError naming ``plant`` and what was expected (one line, before any work)."""
    import control

    desc = " ".join(repr(plant).split())  # one line
    if len(desc) > 200:
        desc = desc[:200] + "..."
    if not isinstance(plant, control.LTI):
        raise ValueError(f"plant = {desc}; expected a python-control LTI system (tf or ss)")
    if isinstance(plant, control.TransferFunction):
        coefs = [np.asarray(x, float) for row in (plant.num, plant.den) for r in row for x in r]
        if not all(np.all(np.isfinite(x)) for x in coefs):
            raise ValueError(f"plant = {desc} has non-finite (nan/inf) coefficients; expected finite numbers")
    if plant.noutputs != 1:
        raise ValueError(f"plant has {plant.noutputs} outputs; expected one (SISO feedback path)")
    if isinstance(plant, control.TransferFunction):
        den = np.trim_zeros(np.atleast_1d(np.asarray(plant.den[0][0], float)), "f")
        if den.size - 1 > MAX_ORDER:
            raise ValueError(f"plant of order {den.size - 1}; expected at most MAX_ORDER = {MAX_ORDER} states "
                             "(reduce it first, e.g. control.balred or control.minreal)")
    try:
        sys = control.ss(plant)
    except (ValueError, TypeError, ArithmeticError, np.linalg.LinAlgError) as exc:
        raise ValueError(f"plant = {desc} has no state-space realisation ({exc}); expected a proper "
                         "continuous LTI system with finite coefficients") from None
    if not sys.isctime():
        raise ValueError(f"plant {sys.name!r} is discrete-time; expected a continuous-time LTI system")
    a, b, c, d = (np.asarray(m, dtype=float) for m in (sys.A, sys.B, sys.C, sys.D))
    n = a.shape[0]
    if n > MAX_ORDER:
        raise ValueError(f"plant of order {n}; expected at most MAX_ORDER = {MAX_ORDER} states "
                         "(reduce it first, e.g. control.balred or control.minreal)")
    if not all(np.all(np.isfinite(m)) for m in (a, b, c, d)):
        raise ValueError("plant matrices contain inf or NaN; expected finite numbers")
    if n == 0 or not np.any(b[:, 0]) or not np.any(c):
        kind = "zero" if not np.any(d) else "a static gain"
        raise ValueError(f"plant = {desc} is {kind} (no dynamics from the control input to the output); "
                         "expected a strictly proper plant with dynamics")
    lam = np.linalg.eigvals(a)
    osc = lam[(np.abs(lam) > 0) & (np.abs(lam.real) <= 1e-12 * np.abs(lam))]
    if osc.size:
        raise ValueError(f"plant has undamped poles on the imaginary axis at +-{np.abs(osc.imag).max():.6g} rad/s; "
                         "expected damped poles (the loop response is infinite there), e.g. a damping ratio of 1e-6")
    return sys


def _gain_scale(sys) -> float:
    """1, or the plant's gain ``|P(j w_ref)|`` (``w_ref`` the geometric mean of its extreme
    pole/zero magnitudes) where that lies outside ``[1/_GAIN_SPAN, _GAIN_SPAN]``; a ValueError
    where it is not a finite positive number (a plant too small or large for double precision)."""
    a, b, c, d = (np.asarray(m, dtype=float) for m in (sys.A, sys.B, sys.C, sys.D))
    poles, zeros = _plant_roots(a, b[:, :1], c, d[:, :1])
    mags = np.abs(np.concatenate([poles, zeros]))
    mags = mags[(mags > 0) & np.isfinite(mags)]
    w_ref = math.sqrt(float(mags.min()) * float(mags.max())) if mags.size else 1.0
    with np.errstate(all="ignore"):
        k0 = abs(complex(_ss_response(a, b[:, :1], c, np.array([w_ref]))[0] + d[0, 0]))
    if not (math.isfinite(k0) and k0 > 0 and math.isfinite(1 / k0)):
        raise ValueError(f"plant gain |P(j {w_ref:.4g})| = {k0:.3g} is not a finite positive number in double "
                         "precision; expected a plant of finite, non-zero gain")
    return 1.0 if 1 / _GAIN_SPAN <= k0 <= _GAIN_SPAN else k0


def _rescaled(res: TuningResult, k0: float, limits: dict) -> TuningResult:
    """A result of the normalised plant ``P/k0`` in the units of ``P``: gains / k0, objectives
    * k0 (ISE * k0^2); a ValueError where a number leaves double precision."""
    f = k0 * k0 if res.kind == "ise" else k0
    pid = res.pid
    gains = [pid.kp / k0, pid.ki / k0, pid.kd / k0]
    obj = res.objective * f
    if not (all(math.isfinite(x) for x in gains) and math.isfinite(obj)) or (pid.ki > 0 and gains[1] == 0.0):
        raise ValueError(f"plant gain {k0:.3g}: the tuned gains or the {res.kind.upper()} ({res.objective:.3g} x {f:.3g}) "
                         "leave double precision; expected a plant gain nearer 1 (rescale its units)")
    stats = dict(res.stats)
    for key in ("objective_horizon", "objective_sampled", "tail_bound", "objective_pade"):
        if key in stats:
            stats[key] = stats[key] * f
    names = ("kp", "ki", "kd")
    warnings = [w for w in res.warnings if not any(w.startswith(f"{n} = ") for n in names)]
    for i, n in enumerate(names):
        lim = limits[f"{n}_max"]
        if math.isfinite(lim) and lim > 0 and gains[i] * k0 >= lim * (1 - 1e-6):
            warnings.append(f"{n} = {gains[i]:.6g} is at its bound {n}_max = {lim / k0:g}")
    return replace(res, pid=PID(gains[0], gains[1], gains[2], tf=pid.tf, kff=pid.kff), objective=obj,
                   mks=None if res.mks is None else res.mks / k0,
                   per_loop=[v * f for v in res.per_loop], stats=stats, warnings=warnings)
