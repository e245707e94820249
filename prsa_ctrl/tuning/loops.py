"""The loop model the tuner works on (:class:`LoopModel`): exact sampled closed loop affine in the
gains, its true peaks, objectives and stability, and the numerics behind them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence
import numpy as np
from numpy.typing import NDArray
from ..sim.metrics import Margins, margins_from_response
from ..options import OBJECTIVES
from ..drive.sampled import zoh
from .settings import CONT_HALVINGS, CONT_RTOL, LOW_DECADES, TAIL_MAX_STEPS, TAIL_RTOL, UNIT_TOL

__all__ = ["LoopModel"]  # the rest is the tuner's own machinery, shared between its modules


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
    #: A continuous loop with a plant delay: ``delay_s``, ``pade_order`` (of the stand-in's Pade
    #: model, :func:`~prsa_ctrl.tuning.builders.pade_order`), ``objective`` (``"exact"`` where
    #: IAE/ITAE are those of the exact delayed loop, ``"pade"`` where the delay is too far below
    #: the loop's time scale to simulate exactly and they are the Pade model's) and ``w_top``
    #: (rad/s, up to where the Pade phase error is bounded).
    delay_model: dict | None = None

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
        # a robust set, a low-gain design): extend by decades, at most LOW_DECADES, 40 points each.
        lo_g = lo
        for _ in range(LOW_DECADES):
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
        (:func:`drive_loop` and :func:`continuous_loop` set it). A loop with a denominator part
        (the Kalman filter's, ``L = g.N / (1 + g.D)``): ``C F S = g.K / (1 + g.D + g.N)``, the
        command's response to the noise with the filter's own feedback of the command
        (:meth:`~prsa_ctrl.tuning.loopmeasure.KalmanEstimate.noise`)."""
        if self.noise is None:
            raise ValueError(f"loop {self.name!r} has no noise-gain response; expected a drive_loop or continuous_loop model")
        w = np.atleast_1d(np.asarray(omega, float))
        g = self.gvec(gains)
        if self.D is not None:
            n0, ln, d0, ld = self.parts_at(w)
            return (g @ np.asarray(self.noise(w), complex)) / (d0 + g @ ld + n0 + g @ ln)
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

    def magnitude_gradient(self, gains: Sequence[float], key: str, omega: NDArray[np.float64]) -> NDArray[np.float64]:
        """Derivative of ``|S|`` (``key`` "ms"), ``|T|`` ("mt") or ``|C F S|`` ("mks") with respect to
        the gains at the fixed frequencies ``omega`` (rad/s; needs ``response``, and ``noise`` for
        "mks"), in closed form: with ``N = N0 + g.L`` and ``D = D0 + g.D`` (so ``L = N/D``), ``S =
        D/(D + N)``, ``T = N/(D + N)`` and ``C F S = (g.K) M/(D + N)`` (``M = D``, or 1 for a loop
        with a denominator part, as :meth:`noise_response`), and ``d|h| = Re(conj(h) dh)/|h|``.

        At the frequency of a peak this is the derivative of the peak itself (Danskin's theorem:
        the peak's frequency shift adds nothing to first order), which is what ``Tuner._polish``
        uses instead of differencing the peak searches.

        Returns
        -------
        (n_gains, n_omega) array
            Per unit of each gain (loop units), magnitude units per gain unit.
        """
        if key not in ("ms", "mt", "mks"):
            raise ValueError(f"key = {key!r}; expected 'ms', 'mt' or 'mks'")
        g = self.gvec(gains)
        w = np.atleast_1d(np.asarray(omega, float))
        n0, ln, d0, ld = self.parts_at(w)
        num, den = n0 + g @ ln, d0 + g @ ld
        q = den + num
        if key == "ms":
            h, dh = den / q, (ld * num - den * ln) / q**2
        elif key == "mt":
            h, dh = num / q, (ln * den - num * ld) / q**2
        else:
            if self.noise is None:
                raise ValueError(f"loop {self.name!r} has no noise-gain response; expected a drive_loop or continuous_loop model")
            k = np.asarray(self.noise(w), complex)
            gk = g @ k
            m, dm = (np.ones_like(den), np.zeros_like(ld)) if self.D is not None else (den, ld)
            h = gk * m / q
            dh = (k * m + gk * dm) / q - gk * m * (ld + ln) / q**2
        return np.real(np.conj(h) * dh) / np.abs(h)

    def margins(self, gains: Sequence[float], peaks: dict | None = None) -> Margins:
        """Ms, Mt (true peaks, see :meth:`peaks`; pass its result as ``peaks`` to reuse it),
        gain and phase margins and crossover."""
        pk = self.peaks(gains) if peaks is None or "mt" not in peaks else peaks
        exact = None
        if self.response is not None:  # the crossings located on the exact response
            g = self.gvec(gains)
            exact = lambda wv: self.loop_response(g, wv)  # noqa: E731
        m = margins_from_response(pk["omega"], pk["L"], response=exact)
        return replace(m, ms=max(m.ms, pk["ms"]), mt=max(m.mt, pk["mt"]))

    def peak_sensitivity(self, gains: Sequence[float]) -> float:
        """``margins(gains).ms`` (the true Ms, dimensionless), the same number, without the
        gain and phase margins and Mt that :meth:`margins` also computes (their crossings'
        bisections are most of its cost): for screening many gains by Ms."""
        pk = self.peaks(gains, mt=False)
        return max(float(np.abs(1.0 / (1.0 + np.asarray(pk["L"], dtype=complex))).max()), pk["ms"])

    def sensitivity_peaks(self, gains: Sequence[float]) -> tuple[float, float]:
        """``(margins(gains).ms, margins(gains).mt)`` (the true Ms and Mt, dimensionless), the
        same numbers computed the same way, without the gain and phase margins' bisections on
        the exact response (most of :meth:`margins`' cost): for the Monte Carlo's and the
        robust summary's Ms/Mt of many samples."""
        pk = self.peaks(gains)
        L = np.asarray(pk["L"], dtype=complex)
        return (max(float(np.abs(1.0 / (1.0 + L)).max()), pk["ms"]),
                max(float(np.abs(L / (1.0 + L)).max()), pk["mt"]))

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
        return self.spectral_radius(gains) < 1.0 - UNIT_TOL

    def stability(self, gains: Sequence[float]) -> str:
        """``"stable"``, ``"marginal"`` or ``"unstable"`` from the closed-loop eigenvalues.

        Marginal: no eigenvalue outside the unit circle, and those on it (within 1e-9) are
        semisimple (bounded response), e.g. the PID's integral state that P-only (``ki = 0``)
        leaves undriven: the loop settles but keeps a steady error. A repeated eigenvalue on
        the circle with a Jordan block (unbounded ramp) is unstable.

        Examples
        --------
        >>> import control
        >>> from prsa_ctrl.tuning.builders import continuous_loop
        >>> lp = continuous_loop(control.tf([1.0], [1.0, 1.0]), tf=0.01, horizon=10.0, n_steps=200)
        >>> lp.stability((1.0, 1.0, 0.0)), lp.stability((1.0, 0.0, 0.0)), lp.stability((0.0, -5.0, 0.0))
        ('stable', 'marginal', 'unstable')
        """
        a = self.a_cl(gains)
        lam = np.linalg.eigvals(a)
        r = np.abs(lam)
        if np.all(r < 1.0 - UNIT_TOL):
            return "stable"
        if np.any(r > 1.0 + UNIT_TOL):
            return "unstable"
        on = lam[r >= 1.0 - UNIT_TOL]
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
            try:
                return float(total + h * _gramian_form(a, self.Ce, z)), 0.0
            except _TailBudgetError:  # a pole too near the unit circle: marginal
                return math.inf, math.inf
        return block_sum(a, self.Ce, z, k, total, h, kind, rtol)

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
        successive values agree within ``rtol`` (at most ``CONT_HALVINGS`` times), and return
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
        return richardson((self._sampled_continuous(acl, bdc, kind, self.h / 2.0**i, min(rtol, TAIL_RTOL))
                           for i in range(CONT_HALVINGS + 1)), rtol)

    def _sampled_continuous(self, acl, bdc, kind: str, h: float, rtol: float) -> tuple[float, float]:
        """``h sum |e_k|`` (IAE) or ``h sum t_k |e_k|`` (ITAE) of the continuous loop ``acl``
        sampled exactly every ``h`` s, to infinity (tail bounded below ``rtol``)."""
        ad, bd = zoh(acl, bdc[:, None], h)
        x_inf = np.linalg.solve(np.eye(ad.shape[0]) - ad, bd[:, 0])
        return block_sum(ad, self.Ce, -x_inf, 0, 0.0, h, kind, rtol)

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
            x, v = zoom_max(lambda xs: self._magnitude(g, key, np.exp(xs)), lo, hi)
        else:
            x, v = zoom_max(lambda xs: f(self.loop_response(g, np.exp(xs))), lo, hi)
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


def richardson(evaluations, rtol: float) -> tuple[float, float]:
    """Value and error estimate of a second-order integration refined by step halving.

    ``evaluations`` yields ``(value, tail)`` at successively halved steps; the error of the
    latest is ``|value - previous| / 3`` (Richardson, second order) plus its tail bound. Stops
    at the first one within ``rtol`` (relative); ``(inf, inf)`` for a non-finite value.
    """
    prev, val, err = None, math.inf, 0.0
    for val, tail in evaluations:
        if not math.isfinite(val):
            return math.inf, math.inf
        if prev is not None:
            err = abs(val - prev) / 3.0 + tail
            if err <= rtol * val:
                return val, err
        prev = val
    return val, err


def _polished_peak(f, w: NDArray[np.float64], mag: NDArray[np.float64]) -> tuple[float, float]:
    """The peak of ``f(omega)`` (a magnitude, vectorised over rad/s) given its values ``mag`` on
    the grid ``w``: the up to six highest local maxima within 1 % of the grid's top, each
    polished by :func:`zoom_max` between its neighbours. Returns ``(peak, omega)``; the grid's
    top when the search finds nothing higher."""
    top = float(mag.max())
    left = np.concatenate([[-np.inf], mag[:-1]])
    right = np.concatenate([mag[1:], [-np.inf]])
    cand = np.flatnonzero((mag >= left) & (mag >= right) & (mag >= 0.99 * top))
    cand = cand[np.argsort(-mag[cand])][:6]
    lo = np.log(w[np.maximum(cand - 1, 0)])
    hi = np.log(w[np.minimum(cand + 1, w.size - 1)])
    x, v = zoom_max(lambda xs: f(np.exp(xs)), lo, hi)
    i = int(np.argmax(v)) if v.size else -1
    if v.size and v[i] > top:
        return float(v[i]), float(math.exp(x[i]))
    return top, float(w[np.argmax(mag)])

def zoom_max(f, lo: NDArray, hi: NDArray, n: int = 41, passes: int = 7) -> tuple[NDArray, NDArray]:
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

def block_sum(a: NDArray, ce: NDArray, z: NDArray, k: int, total: float, h: float, kind: str,
               rtol: float) -> tuple[float, float]:
    """IAE or ITAE of ``e_j = ce a^(j-k) z`` from sample ``k`` on, added to ``total``: summed in
    blocks of 256 samples until the Cauchy-Schwarz tail bound (see
    :meth:`LoopModel.objective_to_infinity`) is below ``rtol`` of the sum (or ``2^22``
    samples: at most ``TAIL_MAX_STEPS/256`` blocks). Returns ``(value, tail_bound)``; ``(inf,
    inf)`` for a loop whose tail cannot be bounded within that budget (a pole too near the unit
    circle, :class:`_TailBudgetError`), as for a marginal loop."""
    n = a.shape[0]
    rho = float(np.max(np.abs(np.linalg.eigvals(a))))
    r = 0.5 * (1.0 + rho)
    q = r * r
    blk = 256
    # rows[j] = ce a^j, j < blk, by doubling (8 products of the rows so far with a^(2^i)
    # instead of 256 vector-matrix products one by one; equal to rounding).
    rows = np.asarray(ce, float).reshape(1, n)
    a_blk = np.asarray(a, float)
    while rows.shape[0] < blk:
        rows = np.vstack([rows, rows @ a_blk])
        a_blk = a_blk @ a_blk
    try:
        gram = _gramian(a / r, ce)
    except _TailBudgetError:  # a pole too near the unit circle to bound the tail: marginal
        return math.inf, math.inf
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
        if tail <= rtol * total or k >= TAIL_MAX_STEPS:
            return total, tail

def _gramian_form(a: NDArray, c: NDArray, z: NDArray) -> float:
    """``sum_k (c a^k z)^2`` for a stable ``a``: ``z' P z`` with ``a' P a - P + c' c = 0``, solved
    on the diagonally balanced ``a`` (states of very different scales) and checked by its
    residual; a poorly solved equation falls back to summing the series by doubling (bounded:
    :func:`_series_gramian`)."""
    return _gramian(a, c)(z)


class _TailBudgetError(ValueError):  # internal: block_sum and objective_to_infinity turn it into inf
    """The series ``sum_k (a^k)' c' c a^k`` does not converge within the sample budget
    (``TAIL_MAX_STEPS``): the loop has a pole too close to the unit circle to integrate its error
    to infinity. Its message says so in one line."""


#: Doublings of :func:`_series_gramian` at most: ``2^GRAMIAN_DOUBLINGS`` samples, the tail budget
#: ``TAIL_MAX_STEPS`` (each doubling is three n x n matrix products).
GRAMIAN_DOUBLINGS = int(TAIL_MAX_STEPS).bit_length() - 1


def _series_gramian(ab: NDArray, cb: NDArray, max_doublings: int = GRAMIAN_DOUBLINGS) -> tuple[NDArray, int]:
    """``P = sum_k (ab^k)' cb' cb ab^k`` by doubling, the fallback of :func:`_gramian`.

    ``P_1 = cb' cb``, ``P_2N = P_N + (ab^N)' P_N ab^N`` with ``ab^2N = (ab^N)^2``: after ``d``
    doublings ``P`` holds the first ``2^d`` terms. What is left, ``(ab^M)' P_inf ab^M`` (``M =
    2^d``), is at most ``||ab^M||^2 / (1 - ||ab^M||^2)`` of ``||P_M||`` (2-norms); the sum stops
    when ``||ab^M||^2 <= 1e-16``, so the work is bounded by ``max_doublings`` doublings
    (``2^max_doublings`` samples, ``3 max_doublings`` matrix products) whatever the poles; it was
    a sample-by-sample sum of up to 2^22 steps per call (issue 31: a filter just below Nyquist,
    a closed-loop pole near z = -1, hung prsa-tune for minutes).

    Returns
    -------
    p : ndarray
        The Gramian (relative truncation error below 1e-16).
    doublings : int
        Doublings done (the work).

    Raises
    ------
    _TailBudgetError
        Not converged after ``max_doublings``: ``|z|^(2^(max_doublings + 1)) > 1e-16`` for a
        pole ``z``, i.e. within about ``37/2^(max_doublings + 1)`` of the unit circle (4.4e-6
        for the default 22).
    """
    p = np.outer(cb, cb)
    m = np.array(ab, dtype=float)  # ab^N, N = 2^d
    for d in range(1, max_doublings + 1):
        p = p + m.T @ p @ m
        m = m @ m
        if not np.all(np.isfinite(p)) or not np.all(np.isfinite(m)):
            break
        if np.linalg.norm(m, 2) ** 2 <= 1e-16:
            return p, d
    rho = float(np.max(np.abs(np.linalg.eigvals(ab)))) if np.all(np.isfinite(ab)) else math.nan
    raise _TailBudgetError(f"the closed loop has a pole at |z| = {rho:.9g}, within {1.0 - rho:.2g} of the unit "
                          f"circle: its error sum to infinity does not converge within 2^{max_doublings} samples "
                          "(the tail budget TAIL_MAX_STEPS); move a filter away from the Nyquist frequency or "
                          "damp the loop")


def _gramian(a: NDArray, c: NDArray) -> Callable:
    """``z -> sum_k (c a^k z)^2`` (see :func:`_gramian_form`), the Lyapunov equation solved once
    (or, where its residual check fails, the series summed once by :func:`_series_gramian`)."""
    import warnings

    from scipy.linalg import LinAlgWarning, matrix_balance, solve_discrete_lyapunov

    # A state that a step leaves ~1e-90 of (a fast measurement filter's, e.g. Tf = 1e-4 s)
    # makes scipy's balancing cast -inf to int on the way ("invalid value encountered in
    # cast"); its scaling is still finite, and the solution is checked by its residual below.
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        ab, (tb, _) = matrix_balance(a, permute=False, separate=True)
    cb = c * tb

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LinAlgWarning)
        p = solve_discrete_lyapunov(ab.T, np.outer(cb, cb))
    res = ab.T @ p @ ab - p + np.outer(cb, cb)
    if not (np.all(np.isfinite(p)) and np.max(np.abs(res)) <= 1e-9 * max(np.max(np.abs(p)), 1e-300)):
        p, _ = _series_gramian(ab, cb)
    return lambda z: float((z / tb) @ p @ (z / tb))

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

def resonance_points(lam: NDArray[np.complex128], lo: float, hi: float) -> NDArray[np.float64]:
    """Frequencies (rad/s) at and around continuous poles/zeros ``lam``: |lam| and, for
    lightly damped pairs, the damped frequency with neighbours a damping width apart."""
    lam = lam[np.isfinite(lam) & (np.abs(lam) > 0)]
    pts = [np.abs(lam)]
    wd, sig = np.abs(lam.imag), np.abs(lam.real)
    osc = wd > 0
    pts.append((wd[osc][:, None] + sig[osc][:, None] * np.array([-2.0, -1.0, -0.5, 0.0, 0.5, 1.0, 2.0])).ravel())
    p = np.concatenate(pts) if pts else np.array([])
    return p[(p > lo) & (p < hi)]

def plant_roots(a, b, c, d) -> tuple[NDArray, NDArray]:
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
