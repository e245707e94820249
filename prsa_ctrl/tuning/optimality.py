"""The tuner's independent first-order check on the true problem and its bounded polish
(:class:`OptimalityChecks`, a mixin of :class:`~prsa_ctrl.tuning.tuner.Tuner`).
"""

from __future__ import annotations

import math
import numpy as np
from numpy.typing import NDArray
from .settings import FD_STEP, KKT_TOL, MS_RTOL, POLISH_FEAS_TOL, POLISH_PATIENCE, POLISH_STALL_RTOL
from .loops import zoom_max
from .objectives import combined, free_gains

__all__ = []  # the rest is the tuner's own machinery, shared between its modules


def nnls(a: NDArray[np.float64], b: NDArray[np.float64], max_iter: int | None = None) -> NDArray[np.float64]:
    """``argmin ||a x - b||`` over ``x >= 0``: the Lawson-Hanson active-set method in numpy.

    The first-order check's multipliers (a handful of columns); ``scipy.optimize.nnls``
    solves the same convex problem, but importing :mod:`scipy.optimize` costs more than a
    whole tuning of the paper scene's NLP solve (about 0.15 s of a cold ``prsa-tune``), and
    this check runs on every tuning. The minimum residual is unique; the solution agrees
    with SciPy's to rounding (``tests/tuning/test_optimality.py`` compares them).

    Parameters
    ----------
    a : (m, n) array
    b : (m,) array
    max_iter : int, optional
        Bound on the outer iterations (each adds one column to the passive set); default
        ``3 n``, as SciPy's. Reaching it returns the last feasible iterate.

    Returns
    -------
    x : (n,) array, ``x >= 0``
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    m, n_all = a.shape
    # The problem in unit columns (x >= 0 is invariant under a positive column scale; a zero
    # column takes no part and stays at 0).
    norms = np.linalg.norm(a, axis=0)
    cols = np.flatnonzero(norms > 0)
    a = a[:, cols] / norms[cols]
    n = cols.size
    x = np.zeros(n)
    passive = np.zeros(n, dtype=bool)
    # A column enters while it lowers the residual by more than rounding, relative to b.
    tol = np.full(n, 10.0 * np.finfo(float).eps * max(m, n_all) * max(float(np.linalg.norm(b)), 1e-300))
    for _ in range(3 * n_all if max_iter is None else max_iter):
        w = a.T @ (b - a @ x)  # the negative gradient: a column that lowers the residual has w > 0
        w[passive] = -np.inf
        j = int(np.argmax(w - tol)) if n else 0
        if not n or not w[j] > tol[j]:
            break
        passive[j] = True
        for _inner in range(3 * n):
            z = np.zeros(n)
            z[passive] = np.linalg.lstsq(a[:, passive], b, rcond=None)[0]
            if np.all(z[passive] > 0):
                x = z
                break
            # Step from x towards z until the first passive variable reaches 0; drop it.
            neg = np.flatnonzero(passive & (z <= 0))
            gap = x[neg] - z[neg]  # >= 0: x >= 0 >= z there
            ratio = np.where(gap > 0, x[neg] / np.where(gap > 0, gap, 1.0), 0.0)
            k = int(np.argmin(ratio))
            x = x + ratio[k] * (z - x)
            x[neg[k]] = 0.0
            passive &= x > 0
            x[~passive] = 0.0
            if not passive.any():
                break
    out = np.zeros(n_all)
    out[cols] = x / norms[cols]
    return out


class OptimalityChecks:
    """The independent first-order check and the bounded polish of a :class:`~prsa_ctrl.tuning.tuner.Tuner`
    (a mixin: it uses the tuner's loops and scan)."""

    def _first_order(self, gains, ms_max, mt_max, noise, hi, typical, mks_max=None) -> dict:
        """First-order optimality of ``gains`` checked on the TRUE problem, independently of
        ipopt: the reported objective (:meth:`LoopModel.true_objective`, at a fixed resolution
        so that it is smooth) and the true local peaks of |S| and |T| (each a constraint of
        its own), differentiated by central differences of ``FD_STEP`` in log gain (a gain at
        0 by a forward difference of ``FD_STEP`` times its typical size).

        Active set: peaks (of |S|, |T| and, with ``mks_max``, |C F S|) within ``MS_RTOL`` of their bound, the noise and upper gain bounds
        within 1e-6, gains at 0; with ``worst_case``, every loop within 1e-3 of the worst.
        Stationarity: the residual ``min || sum_j lam_j grad log f_j + sum_i mu_i grad c_i ||``
        over ``lam, mu >= 0``, ``sum lam = 1`` (``c_i`` the constraints relative to their bound),
        i.e. the largest first-order relative decrease of the objective per unit relative change
        of the gains that the active constraints allow; where the objective has a kink (one
        objective, not worst-case), its gradient may be anything between its one-sided differences. Returns ``{"ok": residual <= KKT_TOL,
        "residual", "active"}``."""
        loops, kind = self.loops, self.objective
        ng = loops[0].n_gains
        g0 = loops[0].gvec(gains)
        free = free_gains(self.use_d, ng)
        typical = loops[0].gvec(typical)
        steps = []  # per free gain: (index, log variable?, step)
        for i in free:
            if g0[i] > 0:
                steps.append((i, True, FD_STEP))
            else:
                steps.append((i, False, FD_STEP * (typical[i] if typical[i] > 0 else 1.0)))

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
                    out[k] = lo_s[k] = hi_s[k] = (fun(moved(k, 1.0)) - f0) / FD_STEP  # per FD_STEP of the typical size
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
        coef = nnls(A, b)
        res = float(np.linalg.norm(G @ coef[: G.shape[1]] + C @ coef[G.shape[1]:]))
        if res > KKT_TOL and box is not None:
            # A kink (the IAE where a lobe of |e| vanishes): the objective's slopes lie between its
            # backward and forward differences, so the distance from 0 of {g + C mu : lo <= g <=
            # hi, mu >= 0} is the residual (for a smooth objective the box is O(FD_STEP) wide).
            from scipy.optimize import lsq_linear

            nv, nc = len(steps), C.shape[1]
            lb = np.concatenate([box[0], np.zeros(nc)])
            ub = np.concatenate([box[1] + 1e-15, np.full(nc, np.inf)])
            sol = lsq_linear(np.hstack([np.eye(nv), C]), np.zeros(nv), bounds=(lb, ub), tol=1e-14)
            res = min(res, float(np.linalg.norm(sol.x[:nv] + C @ sol.x[nv:])))
        return {"ok": res <= KKT_TOL, "residual": res, "active": names + active,
                "gradient": [float(x) for x in (G @ np.full(G.shape[1], 1.0 / G.shape[1]))]}

    def _polish(self, gains, ms_max, mt_max, noise, hi, mks_max=None) -> NDArray | None:
        """A local solve of the TRUE problem from ``gains`` (SLSQP in log gains): the reported
        objective (:meth:`LoopModel._smooth_objective`, differentiated by central differences of
        ``FD_STEP / 10``) under the top peak of |S| (and |T|, |C F S|) and every local one within
        10 % of its bound, each tracked in a bracket of +-0.3 in log frequency around where it
        was (differentiated in closed form at the peak's frequency,
        :meth:`LoopModel.magnitude_gradient`), the noise bound and the gain bounds. The ipopt
        solve works on a stand-in (sampled loop, smoothed ``|e|``, two-rate samples, the bound on
        fixed frequencies), whose optimum can miss the true one's first-order conditions; this
        step closes that gap. Gains at 0 stay at 0. Returns the polished gains (the best feasible
        iterate, see ``POLISH_PATIENCE``) if they are stable, within the true bounds (re-verified
        on the full peak search) and better, else None. Bounded: 25 SLSQP iterations."""
        from scipy.optimize import minimize

        loops, kind = self.loops, self.objective
        ng = loops[0].n_gains
        g0 = loops[0].gvec(gains)
        idx = [i for i in free_gains(self.use_d, ng) if g0[i] > 0]
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

        # Each point's values are computed once (SLSQP asks for the objective and the
        # constraints at the same points, and the Jacobians of both at the same steps).
        memo_obj: dict = {}
        memo_peak: dict = {}

        def peaks_at(y):
            """Tracked peaks relative to their bounds and their frequencies (rad/s)."""
            key_y = y[: len(idx)].tobytes()
            if key_y not in memo_peak:
                g = gains_of(y)
                vals, ws = [], []
                for lp, key, bound, lw in tracked:
                    x, v = zoom_max(lambda xs, lp=lp, key=key: lp._magnitude(g, key, np.exp(xs)),
                                    np.array([lw - 0.3]), np.array([lw + 0.3]))
                    vals.append(float(v[0]) / bound)
                    ws.append(math.exp(float(x[0])))
                memo_peak[key_y] = (np.array(vals), ws)
            return memo_peak[key_y]

        f_ref = [max(lp._smooth_objective(g0, kind), 1e-300) for lp in loops]
        nv = len(idx) + (1 if self.worst_case else 0)

        def objs(y):
            key_y = y[: len(idx)].tobytes()
            if key_y not in memo_obj:
                g = gains_of(y)
                if any(lp.stability(g) != "stable" for lp in loops):
                    memo_obj[key_y] = np.full(len(loops), 1e3)
                else:
                    memo_obj[key_y] = np.array([lp._smooth_objective(g, kind) / fr for lp, fr in zip(loops, f_ref)])
            return memo_obj[key_y]

        w = self.weights

        def fun(y):
            return y[-1] if self.worst_case else float(np.dot(w, objs(y) * f_ref) / np.dot(w, f_ref))

        def noise_margin(y):
            """The noise bound's row (none without one), a hair inside, as the ipopt solve."""
            if noise is None:
                return np.zeros(0)
            g = gains_of(y)
            return np.array([1.0 - 1e-7 - (g[0] + g[2] / loops[0].tf) / noise])

        def cons(y):
            c = [1.0 - peaks_at(y)[0]]
            if self.worst_case:
                c.append(y[-1] - objs(y))
            c.append(noise_margin(y))
            return np.concatenate(c)

        d = FD_STEP / 10

        def obj_jac(y):
            """d objs / d y by central differences of ``d`` (only the objective is differenced)."""
            cols = []
            for k in range(len(idx)):
                e = np.zeros(nv)
                e[k] = d
                cols.append((objs(y + e) - objs(y - e)) / (2 * d))
            return np.array(cols).T  # (loops, len(idx))

        def fun_jac(y):
            if self.worst_case:
                out = np.zeros(nv)
                out[-1] = 1.0
                return out
            return (np.asarray(w) * f_ref) @ obj_jac(y) / np.dot(w, f_ref)

        def cons_jac(y):
            """The peaks' rows in closed form (:meth:`LoopModel.magnitude_gradient` at each
            tracked peak's frequency, per unit log gain), the worst-case rows from
            :func:`obj_jac`, the noise row exactly (it is linear in the gains)."""
            g = gains_of(y)
            _, ws = peaks_at(y)
            rows = []
            for (lp, key, bound, _), wk in zip(tracked, ws):
                row = np.zeros(nv)
                row[: len(idx)] = -lp.magnitude_gradient(g, key, np.array([wk]))[idx, 0] * g[idx] / bound
                rows.append(row)
            if self.worst_case:
                dj = obj_jac(y)
                for j in range(len(loops)):
                    row = np.zeros(nv)
                    row[: len(idx)] = -dj[j]
                    row[-1] = 1.0
                    rows.append(row)
            if noise is not None:
                row = np.zeros(nv)
                coef = np.zeros(ng)
                coef[0], coef[2] = 1.0, 1.0 / loops[0].tf
                row[: len(idx)] = -(coef[idx] * g[idx]) / noise
                rows.append(row)
            return np.array(rows).reshape(len(rows), nv)

        def value(y):
            """The polished measure at ``y`` (the worst loop's with ``worst_case``), inf where
            ``y`` breaks a tracked peak or the noise bound by more than ``POLISH_FEAS_TOL``."""
            c = np.concatenate([1.0 - peaks_at(y)[0], noise_margin(y)])
            if c.size and not np.min(c) >= -POLISH_FEAS_TOL:
                return math.inf
            return float(np.max(objs(y))) if self.worst_case else fun(y)

        y0 = np.zeros(nv)
        if self.worst_case:
            y0[-1] = float(np.max(objs(y0)))
        # The best feasible iterate is kept, and the solve stops once POLISH_PATIENCE iterations
        # in a row have not lowered it by POLISH_STALL_RTOL (SLSQP's own ftol = 1e-12 test is
        # below the objective's accuracy, so it wandered about the optimum to its iteration
        # bound and returned its last iterate, not its best).
        best = {"y": y0, "v": value(y0), "stall": 0}

        def watch(yk):
            yk = np.array(yk, float)
            v = value(yk)
            if v < best["v"]:
                # (a first feasible point after an infeasible start is an improvement, not a stall)
                big = not math.isfinite(best["v"]) or best["v"] - v > POLISH_STALL_RTOL * abs(best["v"])
                best["y"], best["v"], best["stall"] = yk, v, 0 if big else best["stall"] + 1
            elif best["y"] is not y0:  # (no patience counted before a first feasible improvement)
                best["stall"] += 1
            if best["stall"] >= POLISH_PATIENCE:
                raise StopIteration

        # A local step (a factor e^0.25 per gain at most): the tracked peaks stay in their brackets.
        bounds = [(-0.25, min(0.25, math.log(hi[i] / g0[i])) if math.isfinite(hi[i]) else 0.25) for i in idx]
        if self.worst_case:
            bounds.append((0.0, None))
        with np.errstate(all="ignore"):
            try:
                r = minimize(fun, y0, jac=fun_jac, method="SLSQP", bounds=bounds, callback=watch,
                             constraints=[{"type": "ineq", "fun": cons, "jac": cons_jac}],
                             options={"maxiter": 25, "ftol": 1e-12})
                if np.all(np.isfinite(r.x)):
                    watch_last = value(np.asarray(r.x, float))
                    if watch_last < best["v"]:
                        best["y"], best["v"] = np.asarray(r.x, float), watch_last
            except StopIteration:  # SciPy releases that do not stop on it themselves
                pass
            except (ValueError, np.linalg.LinAlgError, ArithmeticError):
                return None
        if not math.isfinite(best["v"]) or best["y"] is y0:
            return None
        g = gains_of(best["y"])
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
        old = combined([lp._smooth_objective(g0, kind) for lp in loops], w, self.worst_case)
        new = combined([lp._smooth_objective(g, kind) for lp in loops], w, self.worst_case)
        return g if new < old else None
