"""Warm starts of the time-domain fit's states (:mod:`prsa_ctrl.identification.timedomain`).

A fit's unknowns are the parameters, each multiple-shooting segment's initial state and the
collocation states of every sample interval. A fit that repeats another on the same records
-- the fit at the delay the search found, on longer segments, after the search's fit on short
ones; a cross-validation refit on all logs but one, after the fit on all logs -- can start its
states from the other's solution instead of from the data-based reference, and so needs fewer
Gauss-Newton iterations (each one a linearisation of every interval). The solution it reaches
is the same: only the start of the iteration differs (the parameters start where the caller
says, usually the other fit's values).

The states are kept per record name and sample (:func:`states_of`), so that a fit on other
segments (shorter or longer ones) or on a subset of the records finds them
(:func:`initial_states`); a record, interval or sample the other fit did not cover starts from
the reference as before.
"""

from __future__ import annotations

import numpy as np

__all__ = ["states_of", "initial_states"]


def _names_unique(records) -> bool:
    names = [r.name for r in records]
    return len(set(names)) == len(names)


def states_of(problem, V, X0) -> dict:
    """The physical states of a fit's solution per record: ``{record name: (K, x)}`` with ``K``
    the collocation stage states of every sample interval, shape ``(nx, stages, intervals)``,
    and ``x`` the state at every sample, shape ``(nx, samples)`` (each segment's initial state,
    then its intervals' end states); NaN where the fit left the record out. Empty when two
    records share a name (they could not be told apart)."""
    recs = problem.records
    if not _names_unique(recs):
        return {}
    nx, ns = problem.nx, problem.ns
    K = problem.XR + np.asarray(V, float).reshape(problem.M * ns, nx).T * problem.S[:, None]
    x0 = problem.XR0 + np.asarray(X0, float).reshape(len(problem.segs), nx).T * problem.S[:, None]
    out = {r.name: (np.full((nx, ns, r.n - 1), np.nan), np.full((nx, r.n), np.nan)) for r in recs}
    for g, sg in enumerate(problem.segs):
        k_all, x_all = out[recs[sg.rec].name]
        m0 = problem.first[g]
        blk = K[:, m0 * ns:(m0 + sg.n) * ns].reshape(nx, sg.n, ns).transpose(0, 2, 1)
        k_all[:, :, sg.k0:sg.k0 + sg.n] = blk
        x_all[:, sg.k0] = x0[:, g]
        x_all[:, sg.k0 + 1:sg.k0 + sg.n + 1] = blk[:, ns - 1, :]
    return out


def initial_states(problem, states: dict | None):
    """Scaled initial ``(V, X0)`` of ``problem`` from ``states`` (:func:`states_of` of another
    fit of the same records, same model): each interval and segment start the other fit covered
    takes its state there, the rest start from the reference (zero deviation). ``None`` when
    ``states`` is empty, when the problem's records share a name, or when the shapes differ
    (another model or records of other lengths)."""
    if not states or not _names_unique(problem.records):
        return None
    nx, ns = problem.nx, problem.ns
    V = np.zeros((problem.M, ns, nx))
    X0 = np.zeros((len(problem.segs), nx))
    xr = problem.XR.reshape(nx, problem.M, ns)
    used = False
    for g, sg in enumerate(problem.segs):
        rec = problem.records[sg.rec]
        got = states.get(rec.name)
        if got is None:
            continue
        k_all, x_all = got
        if k_all.shape != (nx, ns, rec.n - 1) or x_all.shape != (nx, rec.n):
            return None
        m0 = problem.first[g]
        blk = k_all[:, :, sg.k0:sg.k0 + sg.n]  # (nx, ns, n)
        ok = np.all(np.isfinite(blk), axis=(0, 1))
        dv = (blk.transpose(2, 1, 0) - xr[:, m0:m0 + sg.n, :].transpose(1, 2, 0)) / problem.S[None, None, :]
        V[m0:m0 + sg.n][ok] = dv[ok]
        x_start = x_all[:, sg.k0]
        if np.all(np.isfinite(x_start)):
            X0[g] = (x_start - problem.XR0[:, g]) / problem.S
        used = used or bool(ok.any())
    if not used:
        return None
    return V.reshape(-1), X0.reshape(-1)
