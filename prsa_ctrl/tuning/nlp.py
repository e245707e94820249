"""The CasADi NLP of the tuner (:class:`NLPBuilder`, a mixin of :class:`~prsa_ctrl.tuning.tuner.Tuner`).
"""

from __future__ import annotations

from dataclasses import dataclass
import casadi as ca
import numpy as np
from numpy.typing import NDArray
from .settings import IPOPT_MAX_ITER
from .objectives import free_gains, smooth_abs, steady_command, two_rate_error

__all__ = []  # the rest is the tuner's own machinery, shared between its modules


@dataclass(eq=False)
class NLPParts:
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
class Candidate:
    gains: NDArray
    stats: dict
    peaks: list
    value: float
    ms_active: bool
    converged: bool

class NLPBuilder:
    """The CasADi NLP of a :class:`~prsa_ctrl.tuning.tuner.Tuner` (a mixin: it uses the tuner's scan and loops)."""

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
        e, k, w = two_rate_error(acl, bd, ce, n_steps)
        tk, wk = ca.DM(k).T * h, ca.DM(w).T * h
        j = {"iae": ca.sum2(wk * smooth_abs(e, e_s)), "itae": ca.sum2(wk * tk * smooth_abs(e, e_s)),
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

    def _build_nlp(self, has_mt: bool, has_noise: bool, has_mks: bool = False) -> NLPParts:
        """NLP in scaled gains ``v`` with parameters ``p = [scale (ng), eps (per loop), j_ref,
        1/Ms^2, 1/Mt^2, extra frequencies (per loop, n_slots x (4 + 4 ng), with an Mks bound
        4 + 6 ng) and row scales (per loop), 1/Mks^2 (with an Mks bound)]``."""
        loops = self.loops
        ng, nl = loops[0].n_gains, len(loops)
        free = free_gains(self.use_d, ng)
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
            elif self.objective == "ie" and steady_command(lp) is not None:
                # A continuous loop: the Euler integral state sums the error, I_inf = h sum e_k, and
                # at steady state ki I_inf = u_ss, the plant's steady command against the
                # disturbance (gain-free): IE = |u_ss| / ki exactly, no ill-conditioned solve.
                J = smooth_abs(steady_command(lp) / g[1], eps[jl])
            elif self.objective == "ie":
                # Exact IE to infinity: h Ce (I - A)^-1 (I - A)^-1 b (zero steady error under
                # integral action), as two solves: the product (I - A)^2 squares the condition
                # number (~1e65 for a 6th-order Pade delay at a 1e-5 s sample) and its symbolic QR
                # returned an IE 400x too small that jumped between iterates (issue 20).
                a_s, b_s = ca.SX.sym("A", N, N), ca.SX.sym("b", N)
                m_s = ca.SX.eye(N) - a_s
                ief = ca.Function("ie", [a_s, b_s], [-lp.h * ca.mtimes(ce.T, ca.solve(m_s, ca.solve(m_s, b_s)))])
                J = smooth_abs(ief(acl, bd), eps[jl])
            else:
                # Two rates (a profile loop: its own input at every sample, all at full rate); the
                # reported objective is always the full one to infinity.
                e, k, w = two_rate_error(acl, bd, ce, lp.n_steps, lp.profile)
                tk, wk = ca.DM(lp.h * k).T, ca.DM(lp.h * w).T
                J = {
                    "iae": ca.sum2(wk * smooth_abs(e, eps[jl])),
                    "itae": ca.sum2(wk * tk * smooth_abs(e, eps[jl])),
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
                # |C F S| <= Mks: |N + D|^2 - |D|^2 |g K|^2 / Mks^2 >= 0, K the noise path per gain
                # (a loop with a denominator part, the Kalman filter's: C F S = g.K / (N + D), so
                # |N + D|^2 - |g K|^2 / Mks^2 >= 0; LoopModel.noise_response).
                kg = np.asarray(lp.noise(lp.omega[rows[jl]]), complex)
                k_re, k_im = ca.mtimes(ca.DM(kg.real.T), g), ca.mtimes(ca.DM(kg.imag.T), g)
                q_kr, q_ki = q[4 + 4 * ng : 4 + 5 * ng, :], q[4 + 5 * ng : 4 + 6 * ng, :]
                sk_re, sk_im = ca.mtimes(gt, q_kr), ca.mtimes(gt, q_ki)
                kk = ca.vertcat(k_re * k_re + k_im * k_im, (sk_re * sk_re + sk_im * sk_im).T)
                norm_k = p[off + n_sl * ns + 2 * n_c : off + n_sl * ns + 3 * n_c]
                cons_k.append((ww - inv_mks2 * (kk if lp.D is not None else dd * kk)) * norm_k)
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
        ip = {"print_level": 0, "sb": "yes", "max_iter": IPOPT_MAX_ITER, "tol": 1e-8,
              "hessian_approximation": "limited-memory"}
        # Trial points with an unstable loop overflow the objective; ipopt backs off from them,
        # and CasADi's warning per evaluation (thousands in a warm-started re-solve) says nothing.
        base = {"print_time": False, "error_on_fail": False, "show_eval_warnings": False}
        # Expanding to SX costs ~0.5 s once per Tuner but makes each solve ~10x faster; mapped
        # per-loop objectives are SX already (expanding would unroll the map); profile loops: below.
        # One loop (no warm re-solves): only ipopt's x, lam_g and stats are read, so CasADi's
        # post-solve recomputation of f, g, lam_x and lam_p (the function "nlp_grad", a reverse
        # sweep over the whole objective: about half of the build's time) is not built. The
        # warm re-solves of several loops start from lam_x: they keep it.
        post = {"no_nlp_grad": True, "calc_f": False, "calc_g": False, "calc_lam_x": False,
                "calc_lam_p": False} if nl == 1 else {}
        # A profile loop (a duty cycle, a logged trajectory) runs every sample at full rate: its
        # SX expansion unrolls the whole horizon, and building the solvers on it grew with the
        # samples (notebook 11's 6200-sample log: 4.0 s of a 4.9 s retune_axis, two solvers at
        # 2 s each), more than the slower MX evaluation of its mapaccum costs over a solve.
        expand = mapped is None and not any(lp.profile is not None for lp in loops)
        solver = ca.nlpsol("tuner", "ipopt", {"x": var, "p": p, "f": f, "g": ca.vertcat(*cons)},
                           {**base, **post, "expand": expand, "ipopt": ip})
        warm = None
        if nl > 1:
            fun = ca.Function("tuner_nlp", [var, p], [f, ca.vertcat(*cons)], ["x", "p"], ["f", "g"])
            if expand:
                fun = fun.expand()
            # Re-solves after a verification round start from the previous solution and its
            # multipliers (a few constraint rows changed); built on first use.
            warm = (fun, {**base, "ipopt": {**ip, "warm_start_init_point": "yes", "warm_start_bound_push": 1e-9,
                                            "warm_start_mult_bound_push": 1e-9, "warm_start_slack_bound_push": 1e-9}})
        return NLPParts(solver, free, [r.size for r in rows], has_mt, has_noise, n_sl, warm, has_mks=has_mks)

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
                dk = 1.0 if lp.D is not None else np.abs(dv) ** 2  # the row's |D|^2 factor (above)
                out.append(1.0 / np.maximum(wv + dk * np.abs(kv) ** 2 * inv_mks2, 1e-300))
        if mks:
            out.append(np.array([inv_mks2]))
        return np.concatenate(out)
