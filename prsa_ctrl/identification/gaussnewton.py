"""Numerical pieces of the time-domain fit's Gauss-Newton solver
(:mod:`prsa_ctrl.identification.timedomain`).

* :class:`Buffered`: a CasADi function evaluated straight from and into NumPy arrays;
* :func:`condense`: each multiple-shooting segment's initial state eliminated from the
  linearised least-squares problem (the parameters' Schur complement).
"""

from __future__ import annotations

import numpy as np

__all__ = ["Buffered", "condense"]


class Buffered:
    """A CasADi function evaluated straight from and into NumPy arrays (``Function.buffer``).

    Inputs are taken in column-major order and checked for size; outputs are new flat
    column-major arrays of the outputs' nonzeros (dense outputs: every entry).
    """

    def __init__(self, fun):
        self.fun = fun
        self.n_in = [int(fun.nnz_in(i)) for i in range(fun.n_in())]
        self.n_out = [int(fun.nnz_out(i)) for i in range(fun.n_out())]

    def __call__(self, *args):
        if len(args) != len(self.n_in):
            raise ValueError(f"{self.fun.name()}: {len(args)} inputs; expected {len(self.n_in)}")
        flat = [np.ascontiguousarray(np.asarray(a, dtype=float).ravel(order="F")) for a in args]
        for i, (a, n) in enumerate(zip(flat, self.n_in)):
            if a.size != n:  # the buffer interface reads exactly n values: never hand it fewer
                raise ValueError(f"{self.fun.name()}: input {i} has {a.size} values; expected {n}")
        outs = [np.empty(n) for n in self.n_out]
        buf, evaluate = self.fun.buffer()  # a fresh buffer per call: thread-safe, references held here
        for i, a in enumerate(flat):
            buf.set_arg(i, a)
        for i, o in enumerate(outs):
            buf.set_res(i, o)
        evaluate()
        return outs


def condense(lin, rtol: float | None = None):
    """Eliminate each segment's initial state from the linearised least-squares problem.

    Returns the parameter Jacobian and residual with the initial-state directions projected
    out (their normal equations are the Schur complement for the parameters) and, per segment,
    a function giving the initial-state step for a parameter step.

    ``rtol``: None (the rigid model's) keeps every initial-state direction the unpivoted QR
    finds above ``1e-12`` of its largest diagonal; a number keeps the directions whose singular
    value is above ``rtol`` times the largest (SVD) and holds the others at the current state
    (the minimum-norm step): the compliant model's fast axial modes (the shaft on its bearing at
    ~2 kHz) reach the measured angle 1e-8..1e-6 as strongly as the angle itself, and an
    unregularised step along them is 1e5 state scales large and lands far outside the
    linearisation's validity (the Gauss-Newton line search then only creeps).
    """
    js_parts, r_parts, backs = [], [], []
    for r_lin, j_s, j_x, _ in lin:
        if rtol is None:
            q, rr = np.linalg.qr(j_x)
            keep = np.abs(np.diag(rr)) > 1e-12 * max(1.0, float(np.max(np.abs(rr))))
            q, rr = q[:, keep], rr[np.ix_(keep, keep)]

            def back(d_s, q=q, rr=rr, keep=keep, r_lin=r_lin, j_s=j_s):
                out = np.zeros(len(keep))
                out[keep] = -np.linalg.solve(rr, q.T @ (r_lin + j_s @ d_s))
                return out
        else:
            u, sv, vt = np.linalg.svd(j_x, full_matrices=False)
            keep = sv > rtol * max(float(sv[0]) if len(sv) else 0.0, 1e-300)
            q, sk, vk = u[:, keep], sv[keep], vt[keep]

            def back(d_s, q=q, sk=sk, vk=vk, r_lin=r_lin, j_s=j_s):
                return -(vk.T @ ((q.T @ (r_lin + j_s @ d_s)) / sk))
        js_parts.append(j_s - q @ (q.T @ j_s))
        r_parts.append(r_lin - q @ (q.T @ r_lin))
        backs.append(back)
    return np.vstack(js_parts), np.concatenate(r_parts), backs
