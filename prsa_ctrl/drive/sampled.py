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

__all__ = ["zoh", "pid_rows", "pid_frequency_parts", "ss_response", "freq_grid", "first_order_hold"]


def zoh(a: ArrayLike, b: ArrayLike, ts: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Exact zero-order-hold discretisation of ``dx/dt = A x + B u`` by the matrix exponential.

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
