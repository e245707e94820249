"""Adaptive RODAS4 integrator of the continuous loop (``SimSettings(integrator="rodas")``).

RODAS4 (Hairer & Wanner, Solving ODEs II, section IV.7; the coefficients of Hairer's ``rodas.f``
in the form of Sandu et al.'s KPP ``Rosenbrock`` code): a 6-stage Rosenbrock method of order 4 with
an embedded order-3 error estimate, L-stable and stiffly accurate. Each step evaluates the exact
Jacobian once, factorises ``I / (h gamma) - J`` once (the package's sparse LU kernels) and solves
six linear systems: no Newton iteration, no convergence test. The step size is controlled by the
weighted RMS norm of the error estimate with ``rtol``/``atol`` on the scaled states, as CVODES's
(accept when it is <= 1; the new step is ``h * min(6, max(0.2, 0.9 err^-1/4))``, at most the
same after a rejection). Steps are shortened to land exactly on every output point.

Why it exists: on the compliant plants the closed loop has a lightly damped mode near the imaginary
axis (e.g. 2.7 kHz, damping ratio 0.03, on the paper plant), on which SUNDIALS' BDF orders 3-5 are
not stable: after the transient CVODES keeps 20-30 us steps that the solution no longer needs, and
each of its right-hand-side callbacks pays CasADi's per-callback timing (two process-CPU clock
system calls). The L-stable RODAS4 takes the steps the accuracy needs, and ``chunk`` attempts run
as one CasADi function (``mapaccum``), compiled with ``SimSettings(jit=True)``, so there is no
callback per step. Measured on the paper load step in ``docs/benchmarks.md``.
"""

from __future__ import annotations

from typing import Callable

import casadi as ca
import numpy as np

__all__ = ["RODAS4", "rodas_attempt", "RodasSegment", "CHUNK_ATTEMPTS"]

#: RODAS4 in KPP form: stage times ``alpha`` and ``gamma_i`` (fractions of the step), the strictly
#: lower triangular ``a`` and ``c`` (row by row: (2,1), (3,1), (3,2), ...), the solution weights
#: ``m`` and the error weights ``e``.
RODAS4 = {
    "alpha": (0.0, 0.386, 0.21, 0.63, 1.0, 1.0),
    "gamma": (0.25, -0.1043, 0.1035, -0.0362, 0.0, 0.0),
    "a": (1.544, 0.9466785280815826, 0.2557011698983284, 3.314825187068521, 2.896124015972201,
          0.9986419139977817, 1.221224509226641, 6.019134481288629, 12.53708332932087, -0.6878860361058950,
          1.221224509226641, 6.019134481288629, 12.53708332932087, -0.6878860361058950, 1.0),
    "c": (-5.6688, -2.430093356833875, -0.2063599157091915, -0.1073529058151375, -9.594562251023355,
          -20.47028614809616, 7.496443313967647, -10.24680431464352, -33.99990352819905, 11.70890893206160,
          8.083246795921522, -7.981132988064893, -31.52159432874371, 16.31930543123136, -6.058818238834054),
    "m": (1.221224509226641, 6.019134481288629, 12.53708332932087, -0.6878860361058950, 1.0, 1.0),
    "e": (0.0, 0.0, 0.0, 0.0, 0.0, 1.0),
}
_STAGES = 6
#: Attempts (accepted or rejected steps) chained in one call of the compiled function.
CHUNK_ATTEMPTS = 64
#: Smallest step, as a fraction of the segment, before the run is declared failed.
_H_MIN = 1e-13
#: A step that would end within this fraction of itself before an output point is taken to it.
_LAND = 1e-3


def _lower(values, i: int, j: int) -> float:
    """Entry (i, j), 1-based with i > j, of a strictly lower triangular matrix stored row by row."""
    return values[(i - 1) * (i - 2) // 2 + j - 1]


def rodas_attempt(f: ca.Function, nz: int, npar: int, lu_kernels) -> ca.Function:
    """One attempted RODAS4 step of ``f(z, p, tau) -> dz/dtau`` towards the next output point.

    ``(st = [tau, h_try, z], p, cfg = [n_out, rtol, atol]) -> (st', hit)``: from normalised time
    ``tau`` (0..1 over the segment) with the proposed step ``h_try``; the step is shortened to the
    next of the ``n_out`` equally spaced output points when it would reach it. An accepted step
    advances ``tau`` and ``z``; a rejected one (error norm > 1 or not finite) keeps them and
    proposes a shorter step. ``hit`` is 1 when the step was accepted on an output point. Once
    ``tau`` reached 1 the attempt changes nothing (so a chunk of attempts can run past the end).
    ``lu_kernels(sparsity) -> (factor, solve)`` gives the sparse LU of the step's matrix (the
    simulator's, :mod:`prsa_ctrl.sim.integrators`).
    """
    alpha, gamma = RODAS4["alpha"], RODAS4["gamma"]
    st = ca.SX.sym("st", 2 + nz)
    p = ca.SX.sym("p", npar)
    cfg = ca.SX.sym("cfg", 3)
    n_out, rtol, atol = cfg[0], cfg[1], cfg[2]
    tau, h_try, z = st[0], st[1], st[2:]
    zs, ps, ts = ca.SX.sym("z", nz), ca.SX.sym("p", npar), ca.SX.sym("t")
    rate = f(zs, ps, ts)
    jac = ca.Function("rodas_dfdz", [zs, ps, ts], [ca.jacobian(rate, zs)])
    dfdt = ca.Function("rodas_dfdt", [zs, ps, ts], [ca.jacobian(rate, ts)])
    active = tau < 1.0 - 1e-12
    g_next = ca.fmin((ca.floor(tau * n_out + 1e-9) + 1.0) / n_out, 1.0)
    remain = g_next - tau
    capped = h_try * (1.0 + _LAND) >= remain
    h = ca.if_else(capped, remain, h_try)
    j_sym = ca.SX.sym("j", jac.sparsity_out(0))
    hg = ca.SX.sym("hg")
    iter_mat = ca.Function("rodas_matrix", [j_sym, hg], [ca.SX.eye(nz) / hg - j_sym])
    factor, solve = lu_kernels(iter_mat.sparsity_out(0))
    lu = factor(iter_mat(jac(z, p, tau), h * gamma[0]))
    d_t = dfdt(z, p, tau)
    k: list = []
    for i in range(1, _STAGES + 1):
        y = z
        for j in range(1, i):
            y = y + _lower(RODAS4["a"], i, j) * k[j - 1]
        rhs = f(y, p, tau + alpha[i - 1] * h) + gamma[i - 1] * h * d_t
        for j in range(1, i):
            rhs = rhs + (_lower(RODAS4["c"], i, j) / h) * k[j - 1]
        k.append(solve(lu, rhs))
    z1 = z + sum(RODAS4["m"][j] * k[j] for j in range(_STAGES))
    z_err = sum(RODAS4["e"][j] * k[j] for j in range(_STAGES) if RODAS4["e"][j])
    weight = atol + rtol * ca.fmax(ca.fabs(z), ca.fabs(z1))
    err0 = ca.sqrt(ca.sumsqr(z_err / weight) / nz)
    # NaN and inf compare false with inf (``x == x`` would not do: CasADi simplifies it to 1, and
    # fmax(NaN, 1e-10) is 1e-10, so a step with a NaN stage would be accepted)
    finite = ca.logic_and(err0 < ca.inf, ca.sumsqr(z1) < ca.inf)
    err = ca.if_else(finite, ca.fmax(err0, 1e-10), 1e10)
    ok = ca.logic_and(ca.logic_and(err <= 1.0, finite), active)
    fac = ca.fmin(6.0, ca.fmax(0.2, 0.9 * err ** -0.25))
    fac = ca.if_else(ok, fac, ca.fmin(fac, 1.0))
    h_new = h * fac
    h_new = ca.if_else(ca.logic_and(ok, capped), ca.fmax(h_new, h_try), h_new)  # a landing keeps the pace
    h_new = ca.if_else(active, h_new, h_try)
    tau1 = ca.if_else(ok, ca.if_else(capped, g_next, tau + h), tau)
    z_next = ca.if_else(ok, z1, z)
    hit = ca.logic_and(ok, capped)
    return ca.Function("rodas_attempt", [st, p, cfg], [ca.vertcat(tau1, h_new, z_next), hit],
                       ["st", "p", "cfg"], ["st1", "hit"])


class RodasSegment:
    """The continuous loop over one segment with ``n_out`` equally spaced outputs, integrated by
    RODAS4: called like the SUNDIALS integrators of :func:`~prsa_ctrl.sim.integrators.continuous_integrator`,
    ``segment(x0=z, p=par) -> {"xf": states at the n_out output points (nz x n_out)}``.

    Parameters
    ----------
    chunk : casadi.Function
        ``CHUNK_ATTEMPTS`` attempts chained: ``(st, p, cfg) -> (st per attempt, hit per attempt)``.
    nz : int
        Scaled states.
    n_out : int
        Output points (the segment's end is the last).
    rtol, atol : float
        Tolerances on the scaled states.
    max_attempts : int
        Bound on the attempts of one segment (``SimSettings.max_steps`` per output point); more
        raise ``RuntimeError``, as does a step below 1e-13 of the segment or a non-finite state.

    Attributes
    ----------
    stats : dict
        The last call's ``attempts`` (evaluated, including those after the end in the last chunk),
        ``accepted``, ``calls`` and ``h_last`` (fraction of the segment).
    """

    def __init__(self, chunk: ca.Function, nz: int, n_out: int, rtol: float, atol: float, max_attempts: int) -> None:
        self.chunk, self.nz, self.n_out = chunk, nz, n_out
        self.cfg = np.array([float(n_out), rtol, atol])
        self.max_attempts = int(max_attempts)
        self.stats: dict = {}

    def __call__(self, x0, p, check: "Callable[[float, np.ndarray], None] | None" = None) -> dict:
        """Integrate from ``x0`` (scaled states) with the segment's parameters ``p``; ``check(tau, z)``,
        when given, is called before every chunk after the first with the segment fraction reached and
        the scaled state there, and may raise to stop the run (the simulator's wall-time budget)."""
        z0 = np.asarray(x0, dtype=float).ravel()
        pp = np.asarray(p, dtype=float).ravel()
        # The chunk is called through a buffer of this call's own arrays (no conversion to and
        # from CasADi matrices per chunk): the parameters and settings repeated per attempt (column-
        # major, one attempt per row here), the carried state, and the states and landings out.
        n = CHUNK_ATTEMPTS
        st = np.concatenate([[0.0, min(1e-6, 1.0 / self.n_out)], z0])
        p_rep, cfg_rep = np.tile(pp, (n, 1)), np.tile(self.cfg, (n, 1))
        sts, hit = np.zeros((n, st.size)), np.zeros(n)
        buf, evaluate = self.chunk.buffer()
        buf.set_arg(0, memoryview(st))
        buf.set_arg(1, memoryview(p_rep))
        buf.set_arg(2, memoryview(cfg_rep))
        buf.set_res(0, memoryview(sts))
        buf.set_res(1, memoryview(hit))
        rows, calls, accepted = [], 0, 0
        while st[0] < 1.0 - 1e-12:
            if calls * n >= self.max_attempts:
                raise RuntimeError(f"RODAS4: more than {self.max_attempts} step attempts in one segment "
                                   f"(at {st[0]:.6g} of it); raise SimSettings.max_steps or loosen rtol/atol")
            if check is not None and calls:
                check(float(st[0]), st[2:].copy())
            tau0 = st[0]
            evaluate()
            calls += 1
            rows.append(sts[hit > 0.5])  # (a copy)
            taus = sts[:, 0]
            accepted += int(np.count_nonzero(np.diff(taus, prepend=tau0) > 0))
            st[:] = sts[-1]  # the next chunk starts where this one ended (st is the buffer's input)
            if not np.all(np.isfinite(st)):
                raise RuntimeError(f"RODAS4: the state stopped being finite at {st[0]:.6g} of the segment (step size "
                                   f"{st[1]:.3g} of it): the solution blows up")
            if not st[1] >= _H_MIN:
                raise RuntimeError(f"RODAS4: step size {st[1]:.3g} of the segment at {st[0]:.6g} of it (below 1e-13): "
                                   f"rtol = {self.cfg[1]:g}, atol = {self.cfg[2]:g} below what double precision "
                                   "resolves, the solution blowing up or the model too stiff")
        xs = np.vstack(rows).T
        if xs.shape[1] != self.n_out or abs(xs[0, -1] - 1.0) > 1e-12:
            raise RuntimeError(f"RODAS4: {xs.shape[1]} output points reached; expected {self.n_out}")
        self.stats = {"attempts": calls * n, "accepted": accepted, "calls": calls, "h_last": float(st[1])}
        return {"xf": xs[2:]}
