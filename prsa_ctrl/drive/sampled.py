"""The one sampled-loop algebra of the drive: zero-order hold, the per-sample PID law as gain
matrices, and the frequency responses of both.

The drive samples every ``Ts`` seconds (``sensor.sample_time_s``), holds its command over the
sample (zero-order hold) and runs the PID ``u = kp e + I - kd d``, ``I += Ts ki e`` on a
derivative filtered with ``beta = exp(-Ts / tf)``. Every linear model of that loop (the
tuner's loop models, the Kalman-filter loop, the FRF fit's sampled response, the drive
filters' ZOH discretisation) takes its discretisation and its PID rows from here, so they all
run the law :func:`prsa_ctrl.sim.engine.run` simulates.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import expm

__all__ = ["expm_stack", "zoh", "pid_rows", "pid_frequency_parts", "ss_response", "freq_grid", "first_order_hold"]


_PADE13 = (64764752532480000.0, 32382376266240000.0, 7771770303897600.0, 1187353796428800.0, 129060195264000.0,
           10559470521600.0, 670442572800.0, 33522128640.0, 1323241920.0, 40840800.0, 960960.0, 16380.0, 182.0, 1.0)
#: Scaling bound of the degree-13 approximant and the constant of its truncation-error term
#: (as scipy.linalg.expm's selection, Al-Mohy and Higham 2009).
_THETA13 = 4.25
_COEF13 = 1.2573361865339437e19


def expm_stack(a: NDArray[np.float64]) -> NDArray[np.float64]:
    """Matrix exponentials of a stack ``a`` (``(b, n, n)``), vectorised over the stack: scaling
    and squaring with the degree-13 Pade approximant, the scaling chosen per matrix as
    ``scipy.linalg.expm`` chooses it (Al-Mohy and Higham 2009: from ``||A^k||_1^(1/k)``,
    k = 6, 8, 10, not from ``||A||``, plus the truncation-error correction on ``|A|^27``), so a
    stiff, non-normal matrix (a contact stiffness) is not over-scaled.

    It is the Monte Carlo's batched exponential (:mod:`prsa_ctrl.studies.mcmargins`). The single
    zero-order holds (:func:`zoh`, :func:`first_order_hold`) keep ``scipy.linalg.expm``: on a
    badly scaled hold block (entries from 1e-20 to 1e33: the servo 2.2e-4 kg m^2 PID case of
    ``tests/tuning/test_generic.py``) this stack's result differed from scipy's by 2.6e-6 of its
    largest entry, enough to move the tuner's IAE by 30 %. scipy's degree-13 step solves its Pade
    system through LAPACK ``getrs`` with a matrix right-hand side, which OpenBLAS runs on all its
    threads even for a 6 x 6 matrix (about 5 ms of CPU per call instead of 10 us on a loaded
    2-core machine, OpenMathLib/OpenBLAS#4387): ``OPENBLAS_NUM_THREADS=1`` removes that cost.
    Agreement with ``scipy.linalg.expm``: ``tests/drive/test_sampled.py``.

    Parameters
    ----------
    a : array (b, n, n)
        Stack of square matrices (dimensionless: a state matrix times a time).

    Returns
    -------
    ndarray (b, n, n)

    Examples
    --------
    >>> import numpy as np
    >>> e = expm_stack(np.array([[[0.0, 1.0], [-1.0, 0.0]]]))   # a rotation by 1 rad
    >>> np.allclose(e[0], [[np.cos(1), np.sin(1)], [-np.sin(1), np.cos(1)]])
    True
    """
    a = np.asarray(a, float)
    b, n, _ = a.shape
    if b == 0:
        return a.copy()
    upper = ~np.any(np.tril(a, -1), axis=(1, 2))
    lower = ~np.any(np.triu(a, 1), axis=(1, 2)) & ~upper
    tri = upper | lower
    if lower.any():  # exp(A^T) = exp(A)^T: a lower triangular matrix is done as an upper one
        a = a.copy()
        a[lower] = np.swapaxes(a[lower], 1, 2)
    c = _PADE13
    x2 = a @ a
    x4 = x2 @ x2
    x6 = x4 @ x2

    def d(m, k):  # ||m||_1^(1/k), the largest absolute column sum (the 1-norm, as scipy's)
        return np.abs(m).sum(axis=1).max(axis=1) ** (1.0 / k)

    d6, d8, d10 = d(x6, 6), d(x4 @ x4, 8), d(x6 @ x4, 10)
    eta = np.minimum(np.maximum(d6, d8), np.maximum(d8, d10))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        s = np.maximum(np.ceil(np.log2(eta / _THETA13)), 0.0)
        s = np.where(np.isfinite(s), s, 0.0)
        abs_a = np.abs(a) * (2.0 ** -s)[:, None, None]
        v1 = abs_a.sum(axis=1)  # 1^T |A|, scaled
        norm_a = v1.max(axis=1)
        v = v1[:, None, :]
        for _ in range(26):
            v = v @ abs_a
        lm = np.ceil(np.log2(v[:, 0].max(axis=1) / norm_a / _COEF13) / 26.0)
        s = s + np.where(np.isfinite(lm), np.maximum(lm, 0.0), 0.0)
    s = s.astype(int)
    f = 2.0 ** -s
    x = a * f[:, None, None]
    x2 = x2 * (f * f)[:, None, None]
    x4 = x4 * (f ** 4)[:, None, None]
    x6 = x6 * (f ** 6)[:, None, None]
    eye = np.eye(n)[None]
    u = x @ (x6 @ (c[13] * x6 + c[11] * x4 + c[9] * x2) + c[7] * x6 + c[5] * x4 + c[3] * x2 + c[1] * eye)
    v = x6 @ (c[12] * x6 + c[10] * x4 + c[8] * x2) + c[6] * x6 + c[4] * x4 + c[2] * x2 + c[0] * eye
    r = np.linalg.solve(v - u, v + u)
    # a triangular matrix (every zero-order-hold block of a scalar system) keeps its diagonal and
    # first off-diagonal exact through the squarings (Al-Mohy and Higham 2009, Code Fragment 2.1,
    # as scipy.linalg.expm): a stiff lag (e^(-1e6)) stays exact, not rounded up by the squarings
    diag_a = np.einsum("bii->bi", a)
    sd_a = np.einsum("bii->bi", a[:, :-1, 1:])
    tri = tri & (s > 0)
    if tri.any():
        np.einsum("bii->bi", r)[tri] = np.exp(diag_a[tri] * f[tri, None])
    for k in range(int(s.max())):
        sel = s > k
        r[sel] = r[sel] @ r[sel]
        fix = sel & tri
        if fix.any():
            h = 2.0 ** -(s[fix] - 1 - k)[:, None]
            dk = diag_a[fix] * h
            np.einsum("bii->bi", r)[fix] = np.exp(dk)
            np.einsum("bii->bi", r[:, :-1, 1:])[fix] = _exp_sinch(dk) * (sd_a[fix] * h)
    if tri.any():
        r[tri] = np.triu(r[tri])
    r[lower] = np.swapaxes(r[lower], 1, 2)
    return r


def _exp_sinch(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(e^x[i+1] - e^x[i]) / (x[i+1] - x[i])`` along the last axis (``e^x[i]`` where they are
    equal): the first off-diagonal of the exponential of a bidiagonal matrix (Higham's formula
    10.42, as scipy.linalg.expm)."""
    ex = np.exp(x)
    dx = np.diff(x, axis=-1)
    same = dx == 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.diff(ex, axis=-1) / np.where(same, 1.0, dx)
    return np.where(same, ex[..., :-1], out)


def zoh(a: ArrayLike, b: ArrayLike, ts: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Exact zero-order-hold discretisation of ``dx/dt = A x + B u`` by the matrix exponential
    (``scipy.linalg.expm``; not :func:`expm_stack`, see there).

    ``exp([[A, B], [0, 0]] Ts) = [[Ad, Bd], [0, I]]``: the input is held over the sample, and
    stiff modes are exact too (``e^{lambda Ts} -> 0``, no step-size limit).

    Parameters
    ----------
    a : array (n, n)
        State matrix, 1/s.
    b : array (n, m)
        Input matrix (state units per input unit and s).
    ts : float, s
        Sample time.

    Returns
    -------
    (ad, bd) : ndarray (n, n), ndarray (n, m)
        State transition over one sample (dimensionless) and the held input's effect (state
        units per input unit).

    Examples
    --------
    >>> ad, bd = zoh([[-10.0]], [[10.0]], 0.1)   # first-order lag, time constant 0.1 s
    >>> round(float(ad[0, 0]), 6), round(float(bd[0, 0]), 6)  # e^-1 and 1 - e^-1
    (0.367879, 0.632121)
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    n, m = a.shape[0], b.shape[1]
    blk = np.zeros((n + m, n + m))
    blk[:n, :n] = a * ts
    blk[:n, n:] = b * ts
    e = expm(blk)
    return e[:n, :n], e[:n, n:]


def pid_rows(n_state: int, i_u: int, i_i: int, e_meas: ArrayLike, d_new: ArrayLike, ts: float,
             ref: ArrayLike | None = None, weight: float = 1.0
             ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Gain matrices of the sampled PID ``u = kp e + I - kd d``, ``I += Ts ki e`` over a loop state.

    A drive loop's one-sample map is ``A(g) = A0 + kp A_kp + ki A_ki + kd A_kd``: affine in the
    gains, which is what the tuner optimises over. The rows ``e_meas`` (the speed error, rad/s)
    and ``d_new`` (the filtered derivative, rad/s^2) are linear functions of the loop state;
    the command (N m) is stored in state ``i_u`` and the integral (N m) in state ``i_i``.

    With a reference row ``ref`` (the setpoint deviation held in the loop state), the 2-DOF law
    ``u = kp (b r - y) + I - kd d``, ``I += Ts ki (r - y)`` with setpoint weight ``b = weight``
    (``e_meas`` is then ``-y``): still affine in the gains.

    Parameters
    ----------
    n_state : int
        Size of the loop state.
    i_u, i_i : int
        Indices of the stored command and of the integral.
    e_meas, d_new : array (n_state,)
        Rows giving the error and the filtered derivative from the loop state.
    ts : float, s
        Sample time.
    ref : array (n_state,), optional
        Row giving the reference from the loop state (2-DOF law).
    weight : float
        Setpoint weight ``b`` of the proportional term (dimensionless).

    Returns
    -------
    (a_kp, a_ki, a_kd) : ndarray (n_state, n_state) each
        Per unit kp (N m s/rad), ki (N m/rad) and kd (N m s^2/rad).

    Examples
    --------
    >>> a_kp, a_ki, a_kd = pid_rows(3, 2, 1, [-1.0, 0.0, 0.0], [0.0, 0.0, 0.0], 1e-3)
    >>> a_kp[2].tolist(), a_ki[1].tolist()
    ([-1.0, 0.0, 0.0], [-0.001, 0.0, 0.0])
    """
    e_meas, d_new = np.asarray(e_meas, float), np.asarray(d_new, float)
    a_kp = np.zeros((n_state, n_state))
    a_kp[i_u] = e_meas
    a_ki = np.zeros((n_state, n_state))
    a_ki[i_i] = ts * e_meas
    a_kd = np.zeros((n_state, n_state))
    a_kd[i_u] = -d_new
    if ref is not None:
        a_kp[i_u] = a_kp[i_u] + weight * np.asarray(ref, float)
        a_ki[i_i] = a_ki[i_i] + ts * np.asarray(ref, float)
    return a_kp, a_ki, a_kd


def pid_frequency_parts(zi: NDArray[np.complex128], ts: float, beta: float) -> list[NDArray[np.complex128]]:
    """Frequency responses of the sampled PID law per unit kp, ki and kd, acting on the measured speed.

    Parameters
    ----------
    zi : array of complex
        ``exp(-j w Ts)`` at the frequencies ``w`` (rad/s) of interest.
    ts : float, s
        Sample time.
    beta : float
        Pole of the derivative filter, ``exp(-Ts / tf)`` (dimensionless).

    Returns
    -------
    list of 3 arrays of complex
        ``[1, Ts z^-1 / (1 - z^-1), (1 - beta)(1 - z^-1) / (Ts (1 - beta z^-1))]``: the
        proportional, integral (N m per rad/s per unit ki) and filtered-derivative parts.

    Examples
    --------
    >>> kp, ki, kd = pid_frequency_parts(np.exp(-1j * np.array([1.0]) * 1e-3), 1e-3, 0.5)
    >>> complex(kp[0]), round(abs(complex(ki[0])), 3)   # the integral ~ 1 / (j w) at low frequency
    ((1+0j), 1.0)
    """
    return [np.ones_like(zi), ts * zi / (1 - zi), (1 - beta) * (1 - zi) / (ts * (1 - beta * zi))]


def ss_response(a: ArrayLike, b: ArrayLike, c: ArrayLike, omega: ArrayLike,
                z_of_w: Callable[[NDArray[np.float64]], NDArray[np.complex128]] | None = None
                ) -> NDArray[np.complex128]:
    """Frequency response ``c (sI - a)^-1 b`` (or ``c (zI - a)^-1 b`` with ``z = z_of_w(omega)``), vectorised.

    Parameters
    ----------
    a : array (n, n)
        State matrix (continuous, 1/s; or discrete, dimensionless, with ``z_of_w``).
    b : array (n,) or (n, m)
        Input matrix; only its first column is used.
    c : array (n,) or (1, n)
        Output row.
    omega : array, rad/s
        Frequencies.
    z_of_w : callable, optional
        ``omega -> z`` for a discrete model (e.g. ``lambda w: np.exp(1j * w * ts)``).

    Returns
    -------
    ndarray of complex
        One value per frequency (output unit per input unit); zeros for an empty state.

    Examples
    --------
    >>> g = ss_response([[-1.0]], [[1.0]], [[1.0]], [0.0, 1.0])   # 1 / (s + 1)
    >>> np.round(g, 3).tolist()
    [(1+0j), (0.5-0.5j)]
    """
    a = np.asarray(a, float)
    w = np.atleast_1d(np.asarray(omega, float))
    if a.shape[0] == 0:  # no state: no dynamic part (checked first: an empty b cannot be reshaped)
        return np.zeros(w.size, complex)
    b = np.asarray(b, float).reshape(a.shape[0], -1)[:, :1]
    c = np.asarray(c, float).reshape(1, -1)
    s = np.asarray(z_of_w(w) if z_of_w else 1j * w, complex)
    m = s[:, None, None] * np.eye(a.shape[0]) - a[None]
    x = np.linalg.solve(m, np.broadcast_to(b.astype(complex), (w.size,) + b.shape))
    return (c[None] @ x)[:, 0, 0]


def freq_grid(w_lo: float, w_hi: float, n: int) -> NDArray[np.float64]:
    """``n`` log-spaced frequencies from ``w_lo`` to ``w_hi`` (rad/s), the loop models' grid.

    Examples
    --------
    >>> freq_grid(1.0, 100.0, 3).tolist()
    [1.0, 10.0, 100.0]
    """
    return np.logspace(math.log10(w_lo), math.log10(w_hi), n)


def first_order_hold(a: ArrayLike, h: float) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Exact discretisation of ``dx/dt = A x + u`` with ``u`` linear between the samples.

    ``x_{k+1} = phi x_k + p0 u_k + p1 u_{k+1}`` (first-order hold, the input interpolated
    linearly over the step), from one matrix exponential of ``[[A h, I h, 0], [0, 0, I h],
    [0, 0, 0]]``.

    Parameters
    ----------
    a : array (n, n)
        State matrix, 1/s.
    h : float, s
        Step.

    Returns
    -------
    (phi, p0, p1) : ndarray (n, n) each
        State transition and the weights of the input at the step's start and end (s).

    Examples
    --------
    >>> phi, p0, p1 = first_order_hold([[-1.0]], 0.1)
    >>> round(float(phi[0, 0]), 6), round(float(p0[0, 0] + p1[0, 0]), 6)  # e^-h, 1 - e^-h
    (0.904837, 0.095163)
    """
    a = np.atleast_2d(np.asarray(a, dtype=float))
    n = a.shape[0]
    big = np.zeros((3 * n, 3 * n))
    big[:n, :n], big[:n, n : 2 * n], big[n : 2 * n, 2 * n :] = a * h, np.eye(n) * h, np.eye(n) * h
    e = expm(big)
    phi, psi0, psi1 = e[:n, :n], e[:n, n : 2 * n], e[:n, 2 * n :] / h  # psi1 = int e^{Ar}(h - r) dr / h
    return phi, psi0 - psi1, psi1
