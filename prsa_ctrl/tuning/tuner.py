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
import time
from dataclasses import dataclass, field
from typing import Sequence
import casadi as ca
import numpy as np
from numpy.typing import NDArray
from ..drive.pid import PID
from ..errors import NoStabilisingGains
from ..sim.metrics import Margins
from ..options import CONTROLLERS, MS_MAX_DEFAULT, OBJECTIVES
from ..results import freeze, is_converged, json_safe
from .settings import CONT_RTOL, KKT_TOL, MULTI_ROWS, MULTI_SLOTS, POLISH_ROUNDS, RANK_TOP, SLOTS, STARTS, TAIL_RTOL, UNIT_TOL, check_bounds, check_mks, gain_limit
from .loops import LoopModel
from .objectives import combined, ie_batch, rank_batch
from .nlp import Candidate, NLPBuilder, NLPParts
from .optimality import OptimalityChecks

__all__ = ["TuningResult", "Tuner"]


@dataclass(frozen=True)
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
        Whether ``status`` starts with ``"optimal"`` (a property: derived from ``status``,
        :func:`prsa_ctrl.results.is_converged`).
    warnings : tuple of str
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
        ``u = kp (b r - y_f) + ki int (r - y_f) + kd D (c r - y_f)`` with ``y_f = F y`` the
        measured output (the measurement filter ``F`` on it, not on ``r``), their ``goal``, the setpoint
        step's ``iae`` with them and ``iae_unweighted`` (b = c = 1), and the ``overshoot``.
    """

    pid: PID
    objective: float
    kind: str
    per_loop: list[float]
    margins: list[Margins]
    stats: dict = field(default_factory=dict)
    status: str = "optimal"
    warnings: tuple[str, ...] = ()
    mks: float | None = None
    filter: dict | None = None
    setpoint: dict | None = None

    def __post_init__(self) -> None:
        # read-only all the way down (FrozenList / FrozenDict / read-only arrays; they pickle)
        for name in ("per_loop", "margins", "stats", "filter", "setpoint"):
            object.__setattr__(self, name, freeze(getattr(self, name)))

    @property
    def converged(self) -> bool:
        """Whether ``status`` is a verified optimum."""
        return is_converged(self.status)

    def as_dict(self) -> dict:
        """The result as plain data (gains, objective, peaks, status, warnings, stats)."""
        return {"pid": {"kp": self.pid.kp, "ki": self.pid.ki, "kd": self.pid.kd, "tf": self.pid.tf, "kff": self.pid.kff},
                "objective": self.objective, "kind": self.kind, "per_loop": list(self.per_loop),
                "ms": self.ms, "mt": self.mt, "mks": self.mks, "status": self.status, "converged": self.converged,
                "warnings": list(self.warnings), "filter": self.filter, "setpoint": self.setpoint,
                "stats": json_safe(self.stats)}

    @property
    def ms(self) -> float:
        """Largest true peak sensitivity over the loops."""
        return max(m.ms for m in self.margins)

    @property
    def mt(self) -> float:
        """Largest true peak complementary sensitivity over the loops."""
        return max(m.mt for m in self.margins)

class Tuner(NLPBuilder, OptimalityChecks):
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
    >>> from prsa_ctrl.tuning.builders import continuous_loop
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
        self._boundary: NDArray[np.float64] | None = None  # D-decomposition points, once added

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

    #: D-decomposition points: frequencies of the boundary curve, ki levels, kp samples per interval.
    _BOUNDARY_W = 20000
    _BOUNDARY_LEVELS = 15
    _BOUNDARY_SAMPLES = 7
    _BOUNDARY_CROSSINGS = 8
    _BOUNDARY_MAX = 3000

    def boundary_points(self) -> NDArray[np.float64]:
        """Gains inside every region of the (kp, ki) plane (kd = 0) that the stabilising-set
        boundary delimits, from the reference loop's exact frequency response (filters and
        exact delay included): a point where the closed loop changes stability has a root
        ``s = j w`` of ``1 + L = 0``; with ``L = kp L_p + ki L_i`` (kd = 0) that is two real
        equations ``kp Re L_p + ki Re L_i = -1``, ``kp Im L_p + ki Im L_i = 0``, so the
        complex-root boundary is the curve ``(kp(w), ki(w))`` and the real-root boundary
        (``s = 0``) the line ``ki = 0``. At each of ``_BOUNDARY_LEVELS`` ki levels (spread over
        its first lobe, and a few more over all its positive ki) the curve's crossings split
        the kp axis into intervals of constant stability; ``_BOUNDARY_SAMPLES`` kp values
        inside each of the intervals between the ``_BOUNDARY_CROSSINGS`` smallest crossings
        (and below the first, above the last of them) are returned as rows ``(kp, ki, 0[, 0])``. Their stability
        and peaks are decided by the tuner like any scan point. Empty where the loop has no
        frequency-response function or a gain-dependent denominator (estimator loops)."""
        lp = self.loops[0]
        ng = lp.n_gains
        if lp.response is None or lp.N0 is not None or lp.D is not None or lp.D0 is not None:
            return np.zeros((0, ng))
        lo = lp.omega[0] / 10.0
        hi = lp.nyquist * (1 - 1e-9) if lp.nyquist else lp.omega[-1] * 10.0
        w = np.logspace(math.log10(lo), math.log10(hi), self._BOUNDARY_W)
        _, lw, _, _ = lp.parts_at(w)
        a, b = lw[0], lw[1]
        with np.errstate(all="ignore"):
            det = a.real * b.imag - b.real * a.imag
            kp_w = -b.imag / det
            ki_w = a.imag / det
        good = np.isfinite(kp_w) & np.isfinite(ki_w)
        pos = ki_w[good & (ki_w > 0) & (kp_w > 0)]
        if not pos.size:
            return np.zeros((0, ng))
        # ki levels: across the first lobe of the curve (from its low-frequency end to where ki
        # first returns to 0, the region a delay or a right-half-plane pole leaves stabilisable),
        # and across every positive ki it reaches.
        run = good & (ki_w > 0) & (kp_w > 0)
        first = np.flatnonzero(run)
        stop = np.flatnonzero(~run[first[0]:])
        lobe = ki_w[first[0]: first[0] + (stop[0] if stop.size else run.size)]
        k1 = float(np.max(lobe))
        levels = np.unique(np.concatenate([
            k1 * np.logspace(-3.0, math.log10(0.98), self._BOUNDARY_LEVELS),
            np.exp(np.quantile(np.log(pos), np.linspace(0.0, 1.0, 6)))]))
        rows = []
        for lev in levels:
            x = np.where(good, ki_w - lev, np.nan)
            j = np.flatnonzero(np.isfinite(x[:-1]) & np.isfinite(x[1:]) & (np.sign(x[:-1]) != np.sign(x[1:])))
            t = x[j] / (x[j] - x[j + 1])
            kc = kp_w[j] + t * (kp_w[j + 1] - kp_w[j])
            kc = np.unique(kc[np.isfinite(kc) & (kc > 0)])[: self._BOUNDARY_CROSSINGS]
            if not kc.size:
                continue
            edges = np.concatenate([[kc[0] / 100.0], kc, [kc[-1] * 100.0]])
            for k0, k1 in zip(edges[:-1], edges[1:]):
                # strictly inside: the interval's ends are boundary points (marginal loops)
                for kp in np.exp(np.linspace(math.log(k0), math.log(k1), self._BOUNDARY_SAMPLES + 2)[1:-1]):
                    rows.append((kp, lev))
            if len(rows) > self._BOUNDARY_MAX:
                break
        pts = np.zeros((min(len(rows), self._BOUNDARY_MAX), ng))
        if len(pts):
            pts[:, :2] = np.asarray(rows[: len(pts)])
        return pts

    def _add_boundary_points(self) -> bool:
        """Append :meth:`boundary_points` to the scan (once); whether any were added."""
        if self._boundary is not None:
            return False
        self._boundary = self.boundary_points()
        if not self._boundary.size:
            return False
        sc = self._scan_data()
        nl = len(self.loops)
        extra = self._boundary
        sc["grid"] = np.vstack([sc["grid"], extra])
        sc["ms"] = np.concatenate([sc["ms"], self._scan_peak(extra, "ms")])
        for key in ("mt", "mks"):
            if sc.get(key) is not None:
                sc[key] = np.concatenate([sc[key], self._scan_peak(extra, key)])
        sc["stable"] = np.hstack([sc["stable"], np.full((nl, len(extra)), -1, np.int8)])
        sc["obj"] = np.hstack([sc["obj"], np.full((nl, len(extra)), np.nan)])
        return True

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
                    if key == "mks" and lp.D is not None:  # C F S = g.K / (D0 + g.D + N0 + g.N)
                        m = np.abs((gg[:, : kn.shape[0]] @ kn) / (pd0 + gg @ pld + pn0 + gg @ pln))
                    elif key == "mks":
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
        points taken in order of that bound, until ``RANK_TOP`` points are known stable in
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
        if nl == 1 or not self.worst_case or cand.size <= RANK_TOP:
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
            self._evaluate(range(nl), cand[pos : pos + RANK_TOP])
            pos += RANK_TOP
            done = cand[:pos][np.all(sc["stable"][:, cand[:pos]] == 1, axis=0)]
            if pos >= cand.size or np.sum(self._aggregate(done) <= lb[pos]) >= RANK_TOP:
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
                sc["stable"][j, todo] = np.max(np.abs(np.linalg.eigvals(a)), axis=1) < 1.0 - UNIT_TOL
            todo = idx[(sc["stable"][j, idx] == 1) & np.isnan(sc["obj"][j, idx])]
            if todo.size:
                sc["obj"][j, todo] = ie_batch(lp, grid[todo]) if self.objective == "ie" else rank_batch(lp, grid[todo], self.objective)

    def _aggregate(self, idx: NDArray[np.int64], loops: Sequence[int] | None = None) -> NDArray[np.float64]:
        """Worst-case or weighted objective of scan points ``idx`` over ``loops`` (default all;
        a subset gives a lower bound: the objectives are non-negative)."""
        loops = list(range(len(self.loops))) if loops is None else list(loops)
        vals = self._scan_data()["obj"][np.ix_(loops, idx)]
        return vals.max(axis=0) if self.worst_case else self.weights[loops] @ vals

    def _starts(self, order: NDArray[np.int64]) -> list[NDArray]:
        """Up to ``STARTS`` scan points, best first, at least 0.25 decade apart in (kp, ki)."""
        grid = self._scan_data()["grid"]
        chosen: list[int] = []
        for i in order[:400]:
            lg = np.log10(grid[i, :2])
            if all(np.max(np.abs(lg - np.log10(grid[c, :2]))) > 0.25 for c in chosen):
                chosen.append(int(i))
            if len(chosen) == STARTS:
                break
        return [grid[i].copy() for i in chosen]

    # ---- NLP ----------------------------------------------------------------------------

    def _nlp(self, has_mt: bool, has_noise: bool, has_mks: bool = False) -> NLPParts:
        key = (has_mt, has_noise) + ((True,) if has_mks else ())
        if key not in self._nlps:
            self._nlps[key] = self._build_nlp(has_mt, has_noise, has_mks)
        return self._nlps[key]

    def _grid_rows(self, jl: int) -> NDArray[np.int64]:
        """Indices of loop ``jl``'s grid frequencies that are NLP constraint rows: all of them
        for one loop; with several loops (M scenario models: M x 500 rows made each ipopt
        iteration ~8x dearer) about ``MULTI_ROWS`` evenly spread in log frequency plus every
        point inserted at a resonance (a grid gap under half the median). Points left out are
        still checked: the verification after each solve finds the true peak of every loop on
        a denser grid and adds it (with neighbours) as a constraint, so the result honours the
        bounds as with the full grid."""
        w = self.loops[jl].omega
        if len(self.loops) == 1 or w.size <= MULTI_ROWS:
            return np.arange(w.size)
        gap = np.diff(np.log(w))
        fine = np.flatnonzero(gap < 0.5 * np.median(gap))
        keep = np.unique(np.concatenate([np.round(np.linspace(0, w.size - 1, MULTI_ROWS)).astype(int), fine, fine + 1]))
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
        return SLOTS if len(self.loops) == 1 else MULTI_SLOTS

    def _n_slot(self, mks: bool = False) -> int:
        """Numbers per extra frequency: N0, D0 (re, im), L and D per gain (re, im), and with an
        Mks bound the noise path ``C F`` per gain (re, im)."""
        return 4 + (6 if mks else 4) * self.loops[0].n_gains


    def _value(self, gains) -> float:
        """Aggregated objective over the loops' horizons (for ranking and scaling)."""
        vals = [lp.objective_to_infinity(gains, "ie")[0] if self.objective == "ie" else lp.objective(gains, self.objective)
                for lp in self.loops]
        return combined(vals, self.weights, self.worst_case)

    def _solve_from(self, nlp: NLPParts, g0, ms_max, mt_max, noise, hi, typical,
                    mks_max=None) -> tuple[Candidate | None, dict]:
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
                return Candidate(gains, dict(st), pks, math.nan, active, bool(st["success"])), info
            if full:
                info["result"] = f"true peak above the bound after {nlp.n_slots} added frequencies"
                return None, info
            info["rounds"] += 1
            x0 = list(xs)
        info["result"] = "bound not met after the refinement budget"
        return None, info

    # ---- verification of optimality -------------------------------------------------------


    # ---- public --------------------------------------------------------------------------

    def tune(
        self,
        *,
        ms_max: float = MS_MAX_DEFAULT,
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
            until it holds). Needs loops with a noise path (``continuous_loop``, ``drive_loop`` with the
            encoder's speed measurement).

        Returns
        -------
        TuningResult
        """
        t_start = time.perf_counter()
        ms_max, mt_max, noise = check_bounds(ms_max, mt_max, max_noise_gain)
        mks_max = check_mks(mks_max)
        if mks_max is not None and any(lp.noise is None or lp.response is None for lp in self.loops):
            raise ValueError("mks_max given for loops without a noise path; expected continuous_loop or drive_loop models")
        ng = self.loops[0].n_gains
        hi = [gain_limit("kp_max", kp_max), gain_limit("ki_max", ki_max),
              gain_limit("kd_max", kd_max) if self.use_d else 0.0, 1.0][:ng]
        ms_eff = ms_max * (1 - 1e-6)
        mt_eff = mt_max * (1 - 1e-6) if mt_max is not None else None
        mks_eff = mks_max * (1 - 1e-6) if mks_max is not None else None
        order = self._ranked(ms_eff, mt_eff, noise, hi, mks_eff)
        if not order.size and self._add_boundary_points():
            order = self._ranked(ms_eff, mt_eff, noise, hi, mks_eff)
        if not order.size:
            sc = self._scan_data()
            probe = np.flatnonzero(sc["ms"] <= ms_eff)[:20]
            if probe.size and all(any(lp.stability(sc["grid"][i]) == "marginal" for lp in self.loops) for i in probe):
                raise ValueError(
                    "every scanned gain leaves a closed-loop pole on the stability boundary: the plant has a "
                    "pole the loop cannot move (e.g. an angle state under speed feedback); expected a plant without it"
                )
            bounds = (f"Ms <= {ms_max:g}" + (f", Mt <= {mt_max:g}" if mt_max is not None else "")
                      + (f", kp + kd/tf <= {noise:g}" if noise is not None else "")
                      + (f", Mks <= {mks_max:g}" if mks_max is not None else "")
                      + "".join(f", {n}_max = {lim:g}" for n, lim in zip(("kp", "ki", "kd")[: 3 if self.use_d else 2], hi)
                              if math.isfinite(lim)))
            every = np.arange(len(sc["grid"]))
            self._evaluate(range(len(self.loops)), every)
            stable = every[np.all(sc["stable"][:, every] == 1, axis=0)]
            where = ("on the scan and inside the stabilising-set boundary (D-decomposition of 1 + L(j w) = 0 at "
                     "kd = 0)" if self._boundary is not None and self._boundary.size else "on the scan")
            if not stable.size:
                # Relaxing the bounds cannot help here: no gain found stabilises the loop at all.
                raise NoStabilisingGains(
                    f"no stabilising {self.controller.upper()} gains found {where}, whatever the bounds ({bounds}): "
                    "relaxing them does not help; the plant needs another controller structure (or is "
                    "reverse-acting: negate it)")
            least = float(np.min(sc["ms"][stable]))
            raise NoStabilisingGains(
                f"no stabilising {self.controller.upper()} gains meet {bounds} {where}; {stable.size} stabilising "
                f"gains were found, the least Ms among them {least:.4g}: relax the constraints"
                + (f" (Ms above {least:.4g})" if least > ms_max else ""))
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
                    best = Candidate(np.array(g, float), {"return_status": "scan point kept", "iter_count": 0},
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
        for _ in range(POLISH_ROUNDS):
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
            objective=combined(inf_vals, self.weights, self.worst_case),
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
                "objective_sampled": combined(sampled, self.weights, self.worst_case),
                "objective_horizon": combined(hor_vals, self.weights, self.worst_case),
                "horizon_short": horizon_short,
                "tail_bound": float(max(tails)),
                "horizon_s": float(self.loops[0].n_steps * self.loops[0].h),
                "wall_time_s": time.perf_counter() - t_start,
            },
            status=status,
            warnings=tuple(warnings),
        )
