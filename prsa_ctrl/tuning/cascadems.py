"""The Ms constraints of a multi-rate position cascade (:func:`multirate_constraints`), written
in CasADi expressions of the gains as pairs ``(re, im)``: the complex algebra they need
(:func:`cplx_mul`, :func:`abs2`) and the positive-semidefinite test of a lifted return
difference (:func:`psd_conditions`). :func:`prsa_ctrl.tuning.cascade.tune_cascade` imposes them;
split from :mod:`prsa_ctrl.tuning.cascade`.
"""

from __future__ import annotations

import casadi as ca
import numpy as np
from numpy.typing import NDArray

__all__ = ["cplx_mul", "abs2", "psd_conditions", "multirate_constraints"]


def cplx_mul(a, b) -> tuple:
    """The product of two complex numbers given as pairs ``(re, im)`` (CasADi or numbers)."""
    return (a[0] * b[0] - a[1] * b[1], a[0] * b[1] + a[1] * b[0])


def abs2(a):
    """``|a|^2`` of a complex number given as a pair ``(re, im)``."""
    return a[0] ** 2 + a[1] ** 2


def _cm_const(v) -> tuple:
    return (ca.DM(np.real(v)), ca.DM(np.imag(v)))


def _cadd(*xs) -> tuple:
    return (sum(x[0] for x in xs), sum(x[1] for x in xs))


def _cscale(a, k) -> tuple:
    return (a[0] * k, a[1] * k)


def _cmatmul(X, Y) -> list:
    n, m, p = len(X), len(Y), len(Y[0])
    return [[_cadd(*[cplx_mul(X[i][k], Y[k][j]) for k in range(m)]) for j in range(p)] for i in range(n)]


def psd_conditions(M, mu_c2, norm) -> list:
    """Conditions ``e_k(H) >= 0`` (k = 1..N) for ``H = (M^H M - mu_c2 I)/norm`` to be positive
    semi-definite, i.e. ``sigma_min(M)^2 >= mu_c2``: the coefficients of ``det(lambda I + H)``
    (elementary symmetric functions of its real eigenvalues), from the power sums ``tr H^j``
    by Newton's identities. ``M`` a list of lists of (re, im) columns over the frequencies."""
    N = len(M)
    MH = [[(M[j][i][0], -M[j][i][1]) for j in range(N)] for i in range(N)]
    H = _cmatmul(MH, M)
    H = [[_cscale(_cadd(H[i][j], ((-mu_c2 if i == j else 0.0), 0.0)), 1.0 / norm) for j in range(N)]
         for i in range(N)]
    powers, Hk = [], H
    for k in range(N):
        if k:
            Hk = _cmatmul(Hk, H)
        powers.append(sum(Hk[i][i][0] for i in range(N)))
    e = [1.0]
    for k in range(1, N + 1):
        e.append(sum((-1) ** (i - 1) * e[k - i] * powers[i - 1] for i in range(1, k + 1)) / k)
    return e[1:]


def multirate_constraints(cm, g, g0, omega: NDArray[np.float64], m2: float) -> list:
    """The Ms constraints of a multi-rate cascade (``position_rate = N > 1``) at the
    position-loop frequencies ``omega`` (rad/s), each >= 0 where the bound ``m2 = Ms^2`` holds:

    * speed loop opened, ``m2 |1 + W G C_s|^2 - 1`` at each of the N aliases (the whole
      speed-loop frequency range);
    * position loop, ``m2 |D + C_p sum_k h_k n_k prod_{j != k} d_j|^2 - |D|^2`` (the alias sum of
      :meth:`CascadeModel.position_loop` over the common denominator ``D = prod d_k``);
    * torque and speed loop closed: the lifted return difference ``M`` has ``sigma_min(M)^2 >=
      1/m2`` (:func:`psd_conditions`; the speed_closed one scaled by ``|1 + b^T a|^2``),
      normalised per frequency by the baseline ``g0``'s ``|M|_F^2`` (a positive constant).

    ``cm`` is the cascade's :class:`~prsa_ctrl.tuning.cascade.CascadeModel`; this module reads
    only its ``rate``, ``lifted_parts`` and ``return_differences``, and does not import
    ``cascade`` (which imports it).
    """
    N = cm.rate
    Lp = cm.lifted_parts(omega)
    kp, ki, kv, kip = g[0], g[1], g[2], g[3]
    mu = 1.0 / m2
    cons = []
    # speed loop opened, at every alias
    cs_k, r_k, d_k, n_k = [], [], [], []
    for k in range(N):
        csi = _cm_const(Lp["cs_i"][k])
        cs = (kp + ki * csi[0], ki * csi[1])
        r = cplx_mul(_cm_const(Lp["r"][k]), cs)
        cons.append(m2 * abs2((1 + r[0], r[1])) - 1)
        cs_k.append(cs)
        d_k.append((1 + r[0], r[1]))
        n_k.append(cplx_mul(_cm_const(Lp["Gp"][k] * Lp["h"][k]), cs))
    # position loop at its own sample time (alias sum over a common denominator)
    cpi = _cm_const(Lp["cp_i"])
    cp = cplx_mul((kv + kip * cpi[0], kip * cpi[1]), _cm_const(Lp["dp"]))
    D = d_k[0]
    for k in range(1, N):
        D = cplx_mul(D, d_k[k])
    num = (0.0, 0.0)
    for k in range(N):
        t = n_k[k]
        for j in range(N):
            if j != k:
                t = cplx_mul(t, d_k[j])
        num = _cadd(num, t)
    one_l = _cadd(D, cplx_mul(cp, num))
    cons.append(m2 * abs2(one_l) - abs2(D))
    # lifted matrices
    A = [[_cm_const(Lp["A"][:, i, j]) for j in range(N)] for i in range(N)]
    B = [[_cadd(((kp if i == j else 0.0), 0.0), _cscale(_cm_const(Lp["Lc"][:, i, j]), ki)) for j in range(N)]
         for i in range(N)]
    a = [_cadd(*B[i]) for i in range(N)]
    b = [cplx_mul(cp, _cm_const(Lp["c"][:, j])) for j in range(N)]
    eye = [[((1.0 if i == j else 0.0), 0.0) for j in range(N)] for i in range(N)]
    BA, AB = _cmatmul(B, A), _cmatmul(A, B)
    Mt = [[_cadd(eye[i][j], BA[i][j], cplx_mul(a[i], b[j])) for j in range(N)] for i in range(N)]
    c1 = _cadd((1.0, 0.0), *[cplx_mul(b[j], a[j]) for j in range(N)])
    Aa = [_cadd(*[cplx_mul(A[i][j], a[j]) for j in range(N)]) for i in range(N)]
    bB = [_cadd(*[cplx_mul(b[i], B[i][j]) for i in range(N)]) for j in range(N)]
    P = [[_cadd(cplx_mul(c1, _cadd(eye[i][j], AB[i][j])), _cscale(cplx_mul(Aa[i], bB[j]), -1.0)) for j in range(N)]
         for i in range(N)]
    # per-frequency normalisation from the baseline (positive constants; feasibility unchanged)
    Md = cm.return_differences(g0, omega)
    ft = np.maximum(np.sum(np.abs(Md["torque"]) ** 2, axis=(1, 2)) / N, 1e-12)
    cons += psd_conditions(Mt, mu, ca.DM(ft))
    c1_abs2 = abs2(c1)
    Pn = [[P[i][j] for j in range(N)] for i in range(N)]
    H_sc = psd_conditions(Pn, mu * c1_abs2, 1.0)
    # normalise the speed_closed conditions by the baseline's value of |c1|^2 |M|_F^2 (k-th power)
    B0 = float(g0[0]) * np.eye(N)[None] + float(g0[1]) * Lp["Lc"]
    b0 = ((float(g0[2]) + float(g0[3]) * Lp["cp_i"]) * Lp["dp"])[:, None] * Lp["c"]
    c0 = np.maximum(np.abs(1 + np.einsum("wi,wi->w", b0, B0 @ np.ones(N))) ** 2, 1e-12)
    fs = np.maximum(np.sum(np.abs(Md["speed_closed"]) ** 2, axis=(1, 2)) / N, 1e-12) * c0
    cons += [h / ca.DM(fs ** (k + 1)) for k, h in enumerate(H_sc)]
    return cons
