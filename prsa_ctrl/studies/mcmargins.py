"""Ms and Mt of the sampled speed loop for a whole batch of Monte-Carlo samples at once (the
batched path's margins, :func:`prsa_ctrl.studies.mcbatch.evaluate_batch`).

The per-sample path builds, for every sample, the plant's model, its operating point, its
Jacobians, the zero-order-hold discretisation and the loop model
(:func:`prsa_ctrl.studies.sceneloops.actuator_loops`), then
:meth:`prsa_ctrl.tuning.loops.LoopModel.sensitivity_peaks`: about 45 ms of CPU per sample on
``robust-load-step``. Here every step runs over the batch:

- the operating points at the step's mid load: :func:`prsa_ctrl.sim.batch.steady_states`
  (the same damped Newton solve);
- the Jacobians of the parametric family (:func:`prsa_ctrl.plant.model.parametric_family`) at
  them: one CasADi function of ``(x, u, theta)``, built once per family and mapped over the batch;
- the zero-order hold: a stacked matrix exponential (:func:`prsa_ctrl.drive.sampled.expm_stack`,
  Higham's scaling and squaring with the degree-13 Pade approximant, as ``scipy.linalg.expm``);
- the loop: the nominal loop model is the template (its gain matrices and its controller rows
  do not depend on the plant); each sample's plant block replaces the template's;
- the peaks: the same dense grid as ``LoopModel._peak_grid`` (600 log-spaced points, the
  model's grid with the discrete plant's resonance points, the low-frequency extension while
  ``|L| < 100``, the points around every closed-loop pole) and the same polish
  (``prsa_ctrl.tuning.loops.zoom_max`` on the up to six highest local maxima within 1 % of
  the top), with the plant's transfer evaluated in its modal form.

A sample this cannot take (steady state not found, an ill-conditioned modal basis, a
non-finite number) and every design or scene outside the sampled PID loop without filters is
left to the per-sample path, which reports why. Agreement with the per-sample path:
``tests/studies/test_mcmargins.py``.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from ..drive.sampled import expm_stack
from ..tuning.loops import resonance_points, zoom_max
from ..tuning.settings import LOW_DECADES, UNIT_TOL

__all__ = ["expm_stack", "linearise_batch", "loop_batch", "sensitivity_peaks_batch", "MODAL_COND_MAX"]

#: Largest condition number of a sample's modal basis (eigenvectors of its discrete plant)
#: for the modal frequency response; above it the sample goes to the per-sample path. At 1e8
#: the modal sum loses at most about 8 of 16 digits (paper plant: ~1e5).
MODAL_COND_MAX = 1e8

def _jacobian_function(fam):
    """``(x, u, theta) -> (df/dx, df/du, dh/dx)`` of the family, built once per family."""
    import casadi as ca

    fun = fam.cache.get("linearisation")
    if fun is None:
        x, u, th = ca.SX.sym("x", fam.nx), ca.SX.sym("u", 2), ca.SX.sym("th", fam.n_theta)
        xdot, y = fam.f(x, u, th), fam.h(x, u, th)
        fun = ca.Function("linearisation_batch", [x, u, th],
                          [ca.jacobian(xdot, x), ca.jacobian(xdot, u), ca.jacobian(y, x)])
        fam.cache["linearisation"] = fun
    return fun


def linearise_batch(fam, thetas: NDArray[np.float64], omega: float, load: float):
    """Jacobians of the family's members ``thetas`` (``(b, n_theta)``, file units) about their
    steady states at nut speed ``omega`` (rad/s) and axial ``load`` (N), as
    :func:`prsa_ctrl.plant.linear.linear_core` computes them for one plant.

    Returns
    -------
    a : ndarray (b, nx, nx), 1/s
    bu : ndarray (b, nx, 2)
        Per unit torque command (N m) and axial load (N).
    c : ndarray (b, ny, nx)
        Outputs (``fam.output_names``) per state.
    ok : ndarray of bool (b,)
        Steady state found and every Jacobian finite.
    """
    from ..sim.batch import steady_states

    b = thetas.shape[0]
    x, torque, ok = steady_states(fam, thetas, omega, load)
    xs = np.where(ok[:, None], x, 0.0)
    u = np.stack([np.where(ok, torque, 0.0), np.full(b, float(load))])
    fmap = _jacobian_function(fam).map(b, "serial")
    ja, jb, jc = (np.asarray(m) for m in fmap(xs.T, u, thetas.T))
    nx = fam.nx
    a = ja.reshape(nx, b, nx).transpose(1, 0, 2)
    bb = jb.reshape(nx, b, 2).transpose(1, 0, 2)
    c = jc.reshape(-1, b, nx).transpose(1, 0, 2)
    ok = ok & np.all(np.isfinite(a), axis=(1, 2)) & np.all(np.isfinite(bb), axis=(1, 2)) & np.all(
        np.isfinite(c), axis=(1, 2))
    return a, bb, c, ok


def loop_batch(template, a: NDArray, b: NDArray, angle_index: int, command_delay_samples: int) -> dict:
    """The sampled drive loops (:func:`prsa_ctrl.tuning.builders.drive_loop`, no loop filters) of
    the plants ``(a, b)`` (``(s, nx, nx)``, ``(s, nx, 2)``) from the nominal loop ``template``
    (built by ``drive_loop`` on the same drive: its sample time, filters and gain matrices do
    not depend on the plant): the plant block of each sample's one-sample map ``A0`` replaced.

    Returns
    -------
    dict
        ``A0`` (``(s, N, N)``), ``ad``, ``bu``, ``inc_x``, ``inc_u`` (the discrete plant without
        the angle and its increment over a sample), ``n`` (plant states without the angle) and
        ``i_act`` (the state whose command acts on the plant).
    """
    s, nx, _ = a.shape
    ts = template.h
    blk = np.zeros((s, nx + 2, nx + 2))
    blk[:, :nx, :nx] = a * ts
    blk[:, :nx, nx:] = b * ts
    e = expm_stack(blk)
    ad_full, bd_full = e[:, :nx, :nx], e[:, :nx, nx:]
    rest = [i for i in range(nx) if i != angle_index]
    n = len(rest)
    ad = ad_full[:, rest][:, :, rest]
    bu = bd_full[:, rest, 0]
    inc_x, inc_u = ad_full[:, angle_index, rest], bd_full[:, angle_index, 0]
    N = template.A0.shape[0]
    i_act = N - 1 if command_delay_samples else n + 4
    A0 = np.repeat(template.A0[None], s, axis=0)
    A0[:, :n, :n] = ad
    A0[:, :n, i_act] = bu
    A0[:, n, :n] = inc_x
    A0[:, n, i_act] = inc_u
    return {"A0": A0, "ad": ad, "bu": bu, "inc_x": inc_x, "inc_u": inc_u, "n": n, "i_act": i_act}


def _modal(lp: dict):
    """Eigenvalues ``lam`` (s, n) and residues ``res`` (s, n) of ``inc_x (zI - ad)^-1 bu``, and
    whether each sample's discrete plant is finite and its modal basis well conditioned."""
    fin = (np.all(np.isfinite(lp["ad"]), axis=(1, 2)) & np.all(np.isfinite(lp["bu"]), axis=1)
           & np.all(np.isfinite(lp["inc_x"]), axis=1) & np.isfinite(lp["inc_u"]))
    lam, vec = np.linalg.eig(np.where(fin[:, None, None], lp["ad"], 0.0))
    with np.errstate(all="ignore"):
        cond = np.linalg.cond(vec)
        ok = fin & np.isfinite(cond) & (cond <= MODAL_COND_MAX)
        vsafe = np.where(ok[:, None, None], vec, np.eye(vec.shape[1]))
        right = np.linalg.solve(vsafe, np.where(ok[:, None], lp["bu"], 0.0)[..., None].astype(complex))[..., 0]
        left = np.einsum("sj,sjk->sk", np.where(ok[:, None], lp["inc_x"], 0.0).astype(complex), vsafe)
    return lam, left * right, ok


class _Response:
    """``L(w)`` of the samples' loops at frequencies ``w`` (rad/s) for fixed gains: the plant's
    modal sum times the drive's sample-independent factors (as ``drive_loop``'s ``response``)."""

    def __init__(self, lam, res, inc_u, gains, ts: float, alpha: float, beta: float, n_dl: int):
        self.lam, self.res, self.inc_u = lam, res, inc_u
        self.g, self.ts, self.alpha, self.beta, self.n_dl = gains, ts, alpha, beta, n_dl

    def __call__(self, w: NDArray[np.float64], rows: NDArray[np.int64]) -> NDArray[np.complex128]:
        """``L`` at ``w`` (``(r, m)``) of the samples ``rows`` (``(r,)``)."""
        ts = self.ts
        zi = np.exp(-1j * w * ts)
        z = 1.0 / zi
        lam, res = self.lam[rows], self.res[rows]
        g = np.zeros(w.shape, complex)
        for k in range(lam.shape[1]):
            g += res[:, k, None] / (z - lam[:, k, None])
        p_inc = zi * (g + self.inc_u[rows, None])
        meas = (1 - self.alpha) / (1 - self.alpha * zi) / ts
        base = zi ** (1 + self.n_dl) * meas * p_inc
        kp, ki, kd = self.g
        pid = kp + ki * (ts * zi / (1 - zi)) + kd * ((1 - self.beta) * (1 - zi) / (ts * (1 - self.beta * zi)))
        return base * pid


def _rows_sorted_unique(w: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Each row of ``w`` sorted with its duplicates and NaN moved to the end (as NaN), and the
    count of its distinct values."""
    w = np.sort(w, axis=1)
    dup = np.zeros(w.shape, bool)
    dup[:, 1:] = w[:, 1:] == w[:, :-1]
    w = np.where(dup, np.nan, w)
    w = np.sort(w, axis=1)
    return w, np.sum(np.isfinite(w), axis=1)


def _polish(resp: _Response, w, L, count, mag_of) -> NDArray[np.float64]:
    """Per row, as ``prsa_ctrl.tuning.loops._polished_peak`` then ``sensitivity_peaks``:
    the grid's top, raised to the polished peak of the up to six highest local maxima within
    1 % of it where that is higher."""
    s, m = w.shape
    with np.errstate(all="ignore"):
        mag = np.where(np.isfinite(w), mag_of(L), -np.inf)
    mag = np.where(np.isnan(mag), -np.inf, mag)
    top = mag.max(axis=1)
    left = np.concatenate([np.full((s, 1), -np.inf), mag[:, :-1]], axis=1)
    right = np.concatenate([mag[:, 1:], np.full((s, 1), -np.inf)], axis=1)
    cand = (mag >= left) & (mag >= right) & (mag >= 0.99 * top[:, None]) & np.isfinite(mag)
    score = np.where(cand, mag, -np.inf)
    order = np.argsort(-score, axis=1, kind="stable")[:, :6]
    picked = np.take_along_axis(score, order, axis=1) > -np.inf
    rows, col = np.nonzero(picked)
    idx = order[rows, col]
    lo = np.log(w[rows, np.maximum(idx - 1, 0)])
    hi = np.log(w[rows, np.minimum(idx + 1, count[rows] - 1)])
    out = top.copy()
    if rows.size:
        def f(xs):
            x = xs.reshape(rows.size, -1)
            return mag_of(resp(np.exp(x), rows)).ravel()

        _, v = zoom_max(f, lo, hi)
        best = np.full(s, -np.inf)
        np.maximum.at(best, rows, np.where(np.isnan(v), -np.inf, v))
        out = np.maximum(top, best)
    return out


def sensitivity_peaks_batch(template, lp: dict, gains, speed_filter_s: float, command_delay_samples: int):
    """Ms and Mt (true peaks, dimensionless) of every sample's loop at ``gains`` (kp, ki, kd):
    ``LoopModel.sensitivity_peaks`` of each, with the same grid and polish (see the module's
    docstring); ``inf`` where the closed loop is not stable. ``ok`` (bool per sample) is
    False where the modal form is ill conditioned or a number is not finite: those samples are
    the per-sample path's.

    Returns
    -------
    ms, mt : ndarray (s,)
    ok : ndarray of bool (s,)
    """
    g = np.zeros(template.n_gains)
    vals = np.asarray(gains, float)[: template.n_gains]
    g[: vals.size] = vals
    A0 = lp["A0"]
    s = A0.shape[0]
    a_cl = A0 + np.einsum("i,ijk->jk", g, np.stack(template.A))[None]
    ok = np.all(np.isfinite(a_cl), axis=(1, 2))
    a_cl = np.where(ok[:, None, None], a_cl, 0.0)
    poles = np.linalg.eigvals(a_cl)
    stable = ok & (np.max(np.abs(poles), axis=1) < 1.0 - UNIT_TOL)
    lam, res, ok_m = _modal(lp)
    ok &= ok_m
    ms, mt = np.full(s, np.inf), np.full(s, np.inf)
    run = np.flatnonzero(stable & ok)
    if run.size == 0:
        return ms, mt, ok
    ts = template.h
    nyq = template.nyquist
    resp = _Response(lam[run], res[run], lp["inc_u"][run], g[:3], ts, math.exp(-ts / speed_filter_s),
                     math.exp(-ts / template.tf), command_delay_samples)
    r = np.arange(run.size)
    # The model's grid (drive_loop's default omega): 500 log points and the resonance points of
    # the discrete plant's continuous-equivalent poles.
    with np.errstate(all="ignore"):
        lam_r = lam[run]
        cont = np.where(np.abs(lam_r) > 1e-300, np.log(lam_r.astype(complex)) / ts, np.nan)
    grid = np.logspace(math.log10(1e-1), math.log10(nyq * 0.999), 500)
    res_pts = [resonance_points(c[np.isfinite(c)], 1e-1, nyq * 0.999) for c in cont]
    width = max((p.size for p in res_pts), default=0)
    res_mat = np.full((run.size, width), np.nan)
    for i, p in enumerate(res_pts):
        res_mat[i, : p.size] = p
    omega, _ = _rows_sorted_unique(np.concatenate([np.broadcast_to(grid, (run.size, grid.size)), res_mat], axis=1))
    lo = float(omega[0, 0]) / 10.0
    if not np.all(omega[:, 0] == omega[0, 0]):
        ok[run] = False  # a model grid not starting at 0.1 rad/s: not drive_loop's; the per-sample path
        return ms, mt, ok
    w_d = np.logspace(math.log10(lo), math.log10(nyq), 600)
    # Below the model's grid, as _peak_grid: by decades while |L| < 100 (at most LOW_DECADES).
    lows = [lo]
    for _ in range(LOW_DECADES):
        lows.append(lows[-1] / 10.0)
    with np.errstate(all="ignore"):
        l_low = np.abs(resp(np.broadcast_to(np.array(lows[:LOW_DECADES]), (run.size, LOW_DECADES)), r))
    stop = np.where(~(l_low < 100.0), np.arange(LOW_DECADES)[None, :], LOW_DECADES).min(axis=1)
    low_rows = np.full((run.size, 40 * LOW_DECADES), np.nan)
    for k in range(1, LOW_DECADES + 1):
        sel = stop == k
        if sel.any():
            lo_g = lows[k]
            pts = np.logspace(math.log10(lo_g), math.log10(lo), int(round(40 * math.log10(lo / lo_g))) + 1)[:-1]
            low_rows[sel, : pts.size] = pts
    lo_g = np.array(lows)[stop]
    lam_cl = poles[run]
    with np.errstate(all="ignore"):
        keep = np.abs(lam_cl) > 1e-300
        wd = np.abs(np.angle(lam_cl)) / ts
        sig = np.abs(np.log(np.abs(lam_cl))) / ts
        extra = (wd[:, :, None] + sig[:, :, None] * np.array([-2.0, -1.0, -0.5, -0.2, 0.0, 0.2, 0.5, 1.0, 2.0]))
        extra = np.where(keep[:, :, None], extra, np.nan).reshape(run.size, -1)
        extra = np.where((extra > lo_g[:, None]) & (extra < nyq), extra, np.nan)
    w, count = _rows_sorted_unique(np.concatenate([np.broadcast_to(w_d, (run.size, w_d.size)), omega, low_rows,
                                                   extra], axis=1))
    w = w[:, : int(count.max())]
    with np.errstate(all="ignore"):
        L = resp(np.where(np.isfinite(w), w, 1.0), r)
        fin = np.all(np.isfinite(L) | ~np.isfinite(w), axis=1)
        ms_r = _polish(resp, w, L, count, lambda v: 1 / np.abs(1 + v))
        mt_r = _polish(resp, w, L, count, lambda v: np.abs(v / (1 + v)))
    good = fin & np.isfinite(ms_r) & np.isfinite(mt_r)
    ok[run[~good]] = False
    ms[run[good]], mt[run[good]] = ms_r[good], mt_r[good]
    return ms, mt, ok
