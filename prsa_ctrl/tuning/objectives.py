"""Objective helpers of the tuner: smoothed absolute values, two-rate error sums, the scan's batch
objectives and the steady command.
"""

from __future__ import annotations

import math
import casadi as ca
import numpy as np
from numpy.typing import NDArray
from .loops import LoopModel

__all__ = []  # the rest is the tuner's own machinery, shared between its modules


def smooth_abs(x, eps):
    return ca.sqrt(x * x + eps * eps) - eps

def _two_rate(n_steps: int, n_fine: int = 200, m: int = 8) -> tuple[int, int]:
    """Samples simulated at full rate, and the stride on the tail, for the NLP's objective."""
    return (n_steps, 1) if n_steps <= 2 * n_fine else (n_fine, m)

def two_rate_error(acl, bd, ce, n_steps: int, profile: NDArray[np.float64] | None = None):
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

def steady_command(lp: LoopModel) -> float | None:
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

def free_gains(use_d: bool, n_gains: int) -> list[int]:
    """Indices of the optimised gains: kp, ki, (kd), (kff)."""
    return [0, 1] + ([2] if use_d else []) + ([3] if n_gains == 4 else [])

def combined(vals, weights, worst):
    vals = np.asarray(vals, float)
    return float(vals.max()) if worst else float(np.dot(weights, vals))

def ie_batch(lp: LoopModel, grid: NDArray) -> NDArray:
    """Exact IE (to infinity) of every row of ``grid`` (stable rows; batched linear solves)."""
    g = np.asarray(grid, float)[:, : lp.n_gains]
    a = lp.A0[None] + np.einsum("bi,ijk->bjk", g, np.stack(lp.A))
    m = np.eye(lp.A0.shape[0])[None] - a
    b = np.broadcast_to(lp.Bd, (len(g), lp.Bd.size))[..., None]
    s = np.linalg.solve(m, np.linalg.solve(m, b))[..., 0]
    return np.abs(lp.h * s @ lp.Ce)

def rank_batch(lp: LoopModel, grid: NDArray, kind: str) -> NDArray:
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
