"""Loop models from plants: :func:`continuous_loop` (any SISO LTI plant, continuous PID, optional
exact delay and measurement filter) and :func:`drive_loop` (the actuator's sampled speed loop).
"""

from __future__ import annotations

import math
import numbers
from typing import Sequence
import numpy as np
from numpy.typing import NDArray
from ..drive.sampled import first_order_hold, freq_grid, pid_frequency_parts, pid_rows, ss_response, zoh
from .settings import CONT_RTOL, MAX_STEPS, checked_number, int_steps
from .loops import LoopModel, plant_roots, resonance_points, richardson
from .loopmeasure import EncoderDifference, LoopMeasurement

__all__ = ["continuous_loop", "drive_loop"]  # the rest is the tuner's own machinery, shared between its modules


def continuous_loop(
    plant,
    *,
    tf: float,
    horizon: float,
    n_steps: int = 2000,
    disturbance: str | int | None = None,
    step: float = 1.0,
    omega: NDArray[np.float64] | None = None,
    filter_order: int = 0,
    filter_tf: float | None = None,
    ideal: bool = False,
    delay: float = 0.0,
    delay_order: int = 6,
) -> LoopModel:
    """Loop model of a continuous SISO LTI plant under a continuous PID.

    Parameters
    ----------
    plant : control.LTI
        Transfer function or state space with the control input first. With two inputs the
        second (or the one named ``disturbance``) is the load disturbance; with one input the
        disturbance enters at the plant input. A pole at 0 that the loop cannot move
        (uncontrollable from the control input or unobservable at the output, e.g. a drifting
        angle state under speed feedback) is refused: remove that state first.
    tf : float, s
        Derivative filter time constant.
    horizon : float, s
        Length of the simulated disturbance response (the tuner adds the tail beyond it).
    n_steps : int
        Samples over the horizon (10 .. 200000); the sample is ``horizon / n_steps`` s.
    disturbance : str or int, optional
        Name or index of the disturbance input.
    step : float
        Disturbance step size (in the disturbance input's units), finite and non-zero.
    omega : array, rad/s, optional
        Frequency grid of the Ms/Mt constraints; by default 600 log-spaced points spanning the
        plant's poles and zeros, refined around each of them.
    filter_order : {0, 1, 2}
        Measurement filter on the whole controller, ``C(s) F(s)``: none (0), ``F = 1/(Tf s + 1)``
        (1) or ``F = 1/(Tf^2 s^2/2 + Tf s + 1)`` (2, as Soltesz-Grimholt-Skogestad / Hast et al.
        and JuliaSim's ``filter_order=2``). The controller acts on the filtered measurement;
        the objective is that of the unfiltered output.
    filter_tf : float, s
        The filter's time constant ``Tf`` (needed with ``filter_order`` 1 or 2).
    ideal : bool
        Ideal derivative ``kd s`` (no derivative filter; ``tf`` then plays no part in the law):
        the derivative of the filtered measurement, or with ``filter_order=0`` that of the
        plant output, which needs a plant of relative degree 2 or more.
    delay : float, s
        Output (equivalently input) delay ``e^{-s delay}`` of the plant. The frequency response
        (Ms, Mt, Mks, margins) uses the exact ``e^{-j omega delay}``; the reported IAE/ITAE
        (:meth:`LoopModel.true_objective`) is that of the loop with the exact delay
        (:class:`_DelayedLoop`); the sampled stand-in the optimiser works on, and IE/ISE, use a
        Pade approximant of order ``delay_order`` in series with the plant (IE is exact for any
        order: it is ``|u_ss|/ki``).
    delay_order : int
        Pade order of the delay in the stand-in (1 .. 10; above ~8 its realisation loses
        accuracy in double precision).

    Returns
    -------
    LoopModel

    Examples
    --------
    >>> import control
    >>> lp = continuous_loop(control.tf([1.0], [1.0, 2.0, 1.0]), tf=0.1, horizon=20.0, n_steps=1000)
    >>> lp.stability((1.0, 0.5, 0.0)), round(lp.objective_to_infinity((1.0, 0.5, 0.0), "ie")[0], 6)
    ('stable', 2.0)
    """
    import control

    tf = checked_number("tf", tf, lo=0.0, expected="a positive finite time constant in s")
    horizon = checked_number("horizon", horizon, lo=0.0, expected="a positive finite time in s")
    n_steps = int_steps("n_steps", n_steps)
    step = checked_number("step", step, expected="a finite non-zero step size")
    if step == 0.0:
        raise ValueError("step = 0.0; expected a finite non-zero step size")
    filter_order, filter_tf, ideal, delay, delay_order = check_structure(filter_order, filter_tf, ideal, delay,
                                                                          delay_order)
    sys = control.ss(plant)
    if not sys.isctime():
        raise ValueError(f"plant {sys.name!r} is discrete-time; expected a continuous-time LTI system")
    if sys.noutputs != 1:
        raise ValueError(f"plant has {sys.noutputs} outputs; expected one (SISO feedback path)")
    if sys.ninputs not in (1, 2):
        raise ValueError(f"plant has {sys.ninputs} inputs; expected the control input plus at most a disturbance")
    d_idx = 0
    if disturbance is not None:
        try:
            d_idx = sys.input_labels.index(disturbance) if isinstance(disturbance, str) else int(disturbance)
        except ValueError:
            raise ValueError(f"disturbance = {disturbance!r}; expected one of {sys.input_labels}") from None
        if not 0 <= d_idx < sys.ninputs:
            raise ValueError(f"disturbance = {disturbance!r}; expected an input index below {sys.ninputs}")
    elif sys.ninputs == 2:
        d_idx = 1
    a, b, c, d = (np.asarray(m, dtype=float) for m in (sys.A, sys.B, sys.C, sys.D))
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b)) and np.all(np.isfinite(c)) and np.all(np.isfinite(d))):
        raise ValueError("plant matrices contain inf or NaN; expected finite numbers")
    if np.any(d[:, 0] != 0):
        raise ValueError("plant has direct feed-through from the control input; expected a strictly proper plant")
    if d[0, d_idx] != 0:
        raise ValueError("disturbance feeds through to the output directly; expected a strictly proper path")
    n = a.shape[0]
    if n == 0:
        raise ValueError("plant has no states (zero or a static gain); expected a strictly proper plant with dynamics")
    if n:
        # Balance (diagonal similarity) so that companion forms with widely spread
        # coefficients (fast Pade delays, 1e-6 s lags) discretise and solve accurately.
        from scipy.linalg import matrix_balance

        a, (tb, _) = matrix_balance(a, permute=False, separate=True)
        b = b / tb[:, None]
        c = c * tb[None, :]
    c_plant = c
    if delay > 0:
        # A delay far below the loop's time scale: the lowest Pade order whose phase error is
        # negligible up to the top of the loop's grid (order 6 of a 1e-10 s delay has poles near
        # 1e11 rad/s and a realisation too ill-conditioned to simulate).
        mags = np.abs(np.concatenate(plant_roots(a, b[:, :1], c, d[:, :1])))
        mags = mags[(mags > 0) & np.isfinite(mags)]
        w_top = max(float(mags.max()) if mags.size else 0.0, 1.0 / tf) * 100.0
        if omega is not None:
            w_top = max(w_top, float(np.max(omega)))
        delay_order = pade_order(delay, delay_order, w_top)
    delayed, delay_model = None, None
    if delay > 0:
        exact_ok = exact_delay_affordable(delay, horizon)
        if exact_ok:
            delayed = _delayed_loop(a, b, c, d_idx, step, tf, ideal, filter_order, filter_tf, delay, horizon)
        delay_model = {"delay_s": delay, "pade_order": delay_order, "objective": "exact" if exact_ok else "pade",
                       "w_top": w_top}
    # The delay's Pade model and the measurement filter in series with the plant output (extra
    # plant states): c is then the row of the output the controller measures, c_err that of the
    # (delayed, unfiltered) output the objective integrates; without them both are c.
    a, b, c, c_err = _series_output(a, b, c, delay, delay_order, filter_order, filter_tf)
    n = a.shape[0]
    h = horizon / n_steps
    ad, bd_all = zoh(a, b, h)
    bu, bdist = bd_all[:, :1], bd_all[:, d_idx : d_idx + 1]
    gam = math.exp(-h / tf)
    # Closed-loop state X = [x, I (integral of e), z (derivative filter state)], e = -y.
    N = n + 2
    A0 = np.zeros((N, N))
    A0[:n, :n] = ad
    A0[n, :n] = -h * c[0]
    A0[n, n] = 1.0
    A0[n + 1, :n] = -(1 - gam) * c[0]
    A0[n + 1, n + 1] = gam
    ce = np.zeros(N)
    ce[:n] = -c[0]
    # u = kp e + ki I + kd (e - z)/tf (ideal: kd de/dt, a row over the plant states)
    d_row = _ideal_derivative_row(a, b, c, N) if ideal else (ce - np.eye(N)[n + 1]) / tf
    a_kp = np.zeros((N, N))
    a_kp[:n, :] = bu @ ce[None, :]
    a_ki = np.zeros((N, N))
    a_ki[:n, n] = bu[:, 0]
    a_kd = np.zeros((N, N))
    a_kd[:n, :] = bu @ d_row[None, :]
    bdv = np.zeros(N)
    bdv[:n] = bdist[:, 0] * step
    ce_obj = ce
    if c_err is not c:
        ce_obj = np.zeros(N)
        ce_obj[:n] = -c_err[0]
    poles, zeros = plant_roots(a, b[:, :1], c, d[:, :1])
    if omega is None:
        mags = np.abs(np.concatenate([poles, zeros]))
        mags = mags[(mags > 0) & np.isfinite(mags)]
        mags = mags if mags.size else np.array([1.0 / tf])
        lo = min(mags.min(), 2 * math.pi / horizon) / 100
        hi = max(mags.max(), 1 / tf) * 100
        omega = np.unique(np.concatenate([freq_grid(lo, hi, 600), resonance_points(np.concatenate([poles, zeros]), lo, hi)]))
    else:
        omega = np.asarray(omega, float)
        if omega.ndim != 1 or omega.size < 2 or not np.all(np.isfinite(omega)) or np.any(omega <= 0) or np.any(np.diff(omega) <= 0):
            raise ValueError("omega must be an increasing 1-D array of positive finite frequencies (rad/s)")

    b_u = b[:, :1].copy()
    exact = delay > 0 or filter_order > 0 or ideal
    a_p, b_p = a[: c_plant.shape[1], : c_plant.shape[1]].copy(), b_u[: c_plant.shape[1]].copy()

    def deriv(jw):
        return jw if ideal else jw / (1 + jw * tf)

    def response(w):
        jw = 1j * np.asarray(w, float)
        if not exact:
            p_u = ss_response(a, b_u, c, w)
            return None, np.vstack([p_u, p_u / jw, p_u * jw / (1 + jw * tf)]), None, None
        # Exact: the plant's own response, e^{-j w delay} and the filter (no Pade in frequency).
        p_u = ss_response(a_p, b_p, c_plant, w) * np.exp(-jw * delay) * _filter_response(filter_order, filter_tf, jw)
        return None, np.vstack([p_u, p_u / jw, p_u * deriv(jw)]), None, None

    # The continuous closed loop itself, same state: x' = a x + b u + b_d d, I' = e, z' = (e - z)/tf.
    c0 = np.zeros((N, N))
    c0[:n, :n] = a
    c0[n] = ce
    c0[n + 1] = ce / tf
    c0[n + 1, n + 1] = -1.0 / tf
    c_kp, c_ki, c_kd = (np.zeros((N, N)) for _ in range(3))
    c_kp[:n] = b[:, :1] @ ce[None, :]
    c_ki[:n, n] = b[:, 0]
    c_kd[:n] = b[:, :1] @ d_row[None, :]
    c_bd = np.zeros(N)
    c_bd[:n] = b[:, d_idx] * step
    L = response(omega)[1]

    def noise(w):  # the controller per unit gain, filter included: u = C F (-(y + noise))
        jw = 1j * np.asarray(w, float)
        f = _filter_response(filter_order, filter_tf, jw) if filter_order else 1.0
        return np.vstack([np.ones_like(jw) * f, f / jw, f * deriv(jw)])

    return LoopModel(A0, (a_kp, a_ki, a_kd), bdv, ce_obj, h, n_steps, omega, L, tf, name=sys.name, response=response,
                     continuous=(c0, (c_kp, c_ki, c_kd), c_bd), noise=noise, delayed=delayed,
                     delay_model=delay_model)

#: Delay-line samples per delay of the exact delayed simulation: the halving sequence (each level
#: doubles them) and the fixed level of the first-order check's smooth objective.
_DELAY_LEVELS = (8, 16, 32, 64, 128, 256, 512, 1024)

_DELAY_SMOOTH = 64

#: Largest number of samples one delayed simulation may take (budget).
_DELAY_MAX_STEPS = 1 << 21

#: Largest phase error (rad) of the delay's Pade model up to the loop grid's top at which a lower
#: order than the one asked for is used (:func:`pade_order`).
PADE_PHASE_TOL = 1e-12

def pade_order(delay: float, order: int, w_top: float) -> int:
    """The Pade order used for a ``delay`` (s): the lowest ``n`` <= ``order`` whose phase error
    at ``w_top`` (rad/s), ``(n!)^2 / ((2n)! (2n+1)!) (w_top delay)^(2n+1)`` (the leading term;
    the error grows with frequency), is at most ``PADE_PHASE_TOL``; else ``order`` itself.

    Examples
    --------
    >>> pade_order(1e-10, 6, 1e4), pade_order(1e-5, 6, 1e3), pade_order(1.0, 6, 100.0)
    (1, 2, 6)
    """
    x = w_top * delay
    for n in range(1, order):
        if math.factorial(n) ** 2 / (math.factorial(2 * n) * math.factorial(2 * n + 1)) * x ** (2 * n + 1) <= PADE_PHASE_TOL:
            return n
    return order

def exact_delay_affordable(delay: float, horizon: float) -> bool:
    """Whether the exact delayed simulation (:class:`_DelayedLoop`) of a loop with this ``delay``
    (s) over about ``horizon`` (s) fits its budget at the level the first-order check uses:
    ``horizon / delay x _DELAY_SMOOTH`` samples within ``_DELAY_MAX_STEPS`` (a horizon of up to
    32768 delays). A delay far below the loop's time scale (e.g. 1e-5 s on a loop settling in
    seconds: 400000 delays) does not, and the simulation used to run out of budget and fail:
    its objective is then that of the Pade model, which the tuner states."""
    return horizon / delay * _DELAY_SMOOTH <= _DELAY_MAX_STEPS

class _DelayedLoop:
    """The continuous closed loop with the plant's EXACT output delay ``L``:
    ``X' = M(g) X + Q(g) x(t - L) + b_d`` over ``X = [x (plant), f (measurement filter), I, z]``,
    error ``e(t) = -c x(t - L)``, from rest (``x(t) = 0`` for ``t <= 0``).

    Simulated exactly up to the interpolation of the delayed state: the step is ``h = L/m``
    (so the delay is exactly ``m`` samples) and the delayed input ``Q x(t - L)`` is linear
    between its samples (first-order hold, integrated exactly with one matrix exponential):
    O(h^2). :meth:`objective` doubles ``m`` along ``_DELAY_LEVELS`` until two successive IAE/ITAE
    agree within ``rtol`` and returns the finer value with the Richardson estimate
    ``|I_h/2 - I_h|/3`` (trapezoid rule on the samples; the kinks of ``e`` at multiples of ``L``
    fall on samples). It runs in blocks (at least one delay and 1/16 of the stand-in's horizon)
    until the blocks decay geometrically and the geometric tail of the last ratio is below 1e-7
    of the sum (an estimate, not a bound), within ``_DELAY_MAX_STEPS`` samples."""

    def __init__(self, m0, mg, q0, qg, bd, c, delay: float, horizon: float) -> None:
        self.m0, self.mg, self.q0, self.qg, self.bd, self.c = m0, mg, q0, qg, bd, c
        self.delay, self.horizon = delay, horizon
        self.m_smooth = _DELAY_SMOOTH
        self._memo: dict = {}

    def _value(self, g, kind: str, m: int) -> tuple[float, float]:
        """IAE/ITAE to infinity at ``m`` samples per delay, and the estimated tail."""
        key = (g.tobytes(), kind, m)
        if key in self._memo:
            return self._memo[key]
        mm = self.m0 + sum(gi * a for gi, a in zip(g, self.mg))
        qq = self.q0 + sum(gi * a for gi, a in zip(g, self.qg))
        N, n = mm.shape[0], qq.shape[1]
        h = self.delay / m
        phi, p0, p1 = first_order_hold(mm, h)
        hist = [np.zeros((1, n))]  # x_j, j = 0 .. k (plant part)
        X = np.zeros(N)
        total, prev_b, k = 0.0, None, 0
        ratios: list = []
        out = (math.inf, math.inf)
        # Blocks of one delay (m steps): the delayed input of the block is known from the past.
        per = max(1, int(math.ceil(self.horizon / 16.0 / self.delay)))  # delays per ratio block
        acc, n_acc = 0.0, 0
        while k < _DELAY_MAX_STEPS:
            past = np.arange(k - m, k + 1)  # x(t - L) at the block's m + 1 sample times
            xd = np.zeros((m + 1, n))
            ok = past >= 0
            if np.any(ok):
                allx = np.vstack(hist)  # rows: x_j for j = k + 1 - len .. k
                xd[ok] = allx[past[ok] - (k + 1 - allx.shape[0])]
            v = xd @ qq.T + self.bd
            gin = v[:-1] @ p0.T + v[1:] @ p1.T
            xs = np.empty((m + 1, N))
            xs[0] = X
            for j in range(m):
                X = phi @ X + gin[j]
                xs[j + 1] = X
            if not np.all(np.isfinite(X)) or np.abs(X).max() > 1e150:
                break
            # e(t) = -c x(t - L): the IAE is that of c x; for the ITAE its time is t + L.
            y = np.abs(xs[:-1, :n] @ self.c)
            tk = np.arange(k, k + m) * h + self.delay
            acc += h * float(np.sum(y if kind == "iae" else tk * y))
            hist.append(xs[1:, :n])
            hist = hist[-2:]  # the last delay (and more) is all the next block needs
            k += m
            n_acc += 1
            if n_acc < per:
                continue
            b, acc, n_acc = acc, 0.0, 0
            total += b
            if prev_b is not None and prev_b > 0:
                ratios.append(b / prev_b)
            prev_b = b
            if len(ratios) >= 3 and max(ratios[-3:]) < 1.0 and k * h > self.horizon / 4:
                r = max(ratios[-3:])
                tail = b * r / (1.0 - r)
                if tail <= 1e-7 * total:
                    out = (total, tail)
                    break
        self._memo[key] = out
        return out

    def objective(self, g, kind: str, rtol: float = CONT_RTOL, levels=None) -> tuple[float, float]:
        """IAE or ITAE of the exact delayed loop and its error estimate (Richardson over
        successive levels of ``_DELAY_LEVELS``; with ``levels``, over those, or the one value)."""
        g = np.asarray(g, float)
        levels = _DELAY_LEVELS if levels is None else levels
        return richardson((self._value(g, kind, m) for m in levels), rtol)

def _delayed_loop(a, b, c, d_idx: int, step: float, tf: float, ideal: bool, filter_order: int, filter_tf,
                  delay: float, horizon: float) -> _DelayedLoop:
    """The loop of :func:`continuous_loop` with the exact delay on the plant output (see
    :class:`_DelayedLoop`); ``a, b, c`` the balanced plant without the delay or the filter."""
    n = a.shape[0]
    if filter_order:
        af, bf, cf = _filter_ss(filter_order, filter_tf)
    else:
        af, bf, cf = np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0))
    nf = af.shape[0]
    N = n + nf + 2
    i_i, i_z = n + nf, n + nf + 1
    E, Ed = np.zeros(N), np.zeros(n)  # the measured error em = E X + Ed x(t - L)
    if filter_order:
        E[n : n + nf] = -cf[0]
    else:
        Ed = -c[0].copy()
    ez = np.eye(N)[i_z]
    if ideal and filter_order:  # d em/dt = -cf (af f + bf c x(t - L))
        DX, Dx = np.zeros(N), -float(cf[0] @ bf[:, 0]) * c[0]
        DX[n : n + nf] = -(cf[0] @ af)
    elif ideal:  # -c a x(t - L) (relative degree 2 or more, checked by the stand-in)
        DX, Dx = np.zeros(N), -(c[0] @ a)
    else:
        DX, Dx = (E - ez) / tf, Ed / tf
    m0 = np.zeros((N, N))
    m0[:n, :n] = a
    m0[n : n + nf, n : n + nf] = af
    m0[i_i] = E
    m0[i_z] = (E - ez) / tf
    q0 = np.zeros((N, n))
    q0[n : n + nf] = bf @ c
    q0[i_i] = Ed
    q0[i_z] = Ed / tf
    mg, qg = [], []
    for row_x, row_d in ((E, Ed), (np.eye(N)[i_i], np.zeros(n)), (DX, Dx)):
        mk, qk = np.zeros((N, N)), np.zeros((N, n))
        mk[:n] = np.outer(b[:, 0], row_x)
        qk[:n] = np.outer(b[:, 0], row_d)
        mg.append(mk)
        qg.append(qk)
    bd = np.zeros(N)
    bd[:n] = b[:, d_idx] * step
    return _DelayedLoop(m0, tuple(mg), q0, tuple(qg), bd, c[0].copy(), delay, horizon)

def check_structure(filter_order, filter_tf, ideal, delay, delay_order):
    """The loop-structure arguments of :func:`continuous_loop` checked (ValueError naming one)."""
    if isinstance(filter_order, bool) or filter_order not in (0, 1, 2):
        raise ValueError(f"filter_order = {filter_order!r}; expected 0 (none), 1 or 2")
    if filter_order:
        filter_tf = checked_number("filter_tf", filter_tf, lo=0.0, expected="a positive finite time constant in s")
    if not isinstance(ideal, (bool, np.bool_)):
        raise ValueError(f"ideal = {ideal!r}; expected True or False")
    delay = checked_number("delay", delay, lo=0.0, lo_open=False, expected="a finite delay >= 0 s")
    if isinstance(delay_order, bool) or not isinstance(delay_order, numbers.Integral) or not 1 <= delay_order <= 10:
        raise ValueError(f"delay_order = {delay_order!r}; expected an integer in [1, 10]")
    return int(filter_order), filter_tf, bool(ideal), delay, int(delay_order)

def _filter_ss(order: int, t: float) -> tuple[NDArray, NDArray, NDArray]:
    """State space ``(A, B, C)`` of the measurement filter 1/(t s + 1) or 1/(t^2 s^2/2 + t s + 1)."""
    if order == 1:
        return np.array([[-1.0 / t]]), np.array([[1.0 / t]]), np.array([[1.0]])
    return (np.array([[0.0, 1.0], [-2.0 / (t * t), -2.0 / t]]), np.array([[0.0], [2.0 / (t * t)]]),
            np.array([[1.0, 0.0]]))

def _filter_response(order: int, t: float | None, jw) -> NDArray[np.complex128]:
    """``F(j omega)`` of the measurement filter (1 without one)."""
    if not order:
        return np.ones_like(jw)
    return 1.0 / (t * jw + 1.0) if order == 1 else 1.0 / (t * t * jw * jw / 2.0 + t * jw + 1.0)

def _series_output(a, b, c, delay: float, delay_order: int, filter_order: int, filter_tf):
    """The plant ``(a, b, c)`` with the delay's Pade model and the measurement filter in series
    with its output: ``(a, b, c_measured, c_objective)`` (the last is ``c`` itself, the same
    object, when neither is present)."""
    c_err = c
    if delay > 0:
        import control

        num, den = control.pade(delay, delay_order)
        pd = control.ss(control.tf(num, den))
        ap, bp, cp, dp = (np.asarray(m, float) for m in (pd.A, pd.B, pd.C, pd.D))
        from scipy.linalg import matrix_balance

        ap, (tp, _) = matrix_balance(ap, permute=False, separate=True)
        bp, cp = bp / tp[:, None], cp * tp[None, :]
        a, b, c = _cascade(a, b, c, ap, bp, cp, float(dp[0, 0]))
        c_err = c
    if filter_order:
        af, bf, cf = _filter_ss(filter_order, filter_tf)
        a, b, c_meas = _cascade(a, b, c, af, bf, cf, 0.0)
        return a, b, c_meas, np.hstack([c, np.zeros((1, af.shape[0]))])
    return a, b, c, c_err

def _cascade(a, b, c, a2, b2, c2, d2: float):
    """``(a, b, c)`` followed by ``(a2, b2, c2, d2)`` on its output: the series system's matrices."""
    n, m = a.shape[0], a2.shape[0]
    big = np.zeros((n + m, n + m))
    big[:n, :n] = a
    big[n:, :n] = b2 @ c
    big[n:, n:] = a2
    return big, np.vstack([b, np.zeros((m, b.shape[1]))]), np.hstack([d2 * c, c2])

def _ideal_derivative_row(a, b, c, n_total: int) -> NDArray[np.float64]:
    """The error's time derivative ``-c (a x + b u)`` as a row over the closed-loop state, which
    needs ``c b = 0`` (relative degree 2 or more from the control input to the measurement)."""
    if abs(float(c[0] @ b[:, 0])) > 1e-12 * max(float(np.abs(c).max() * np.abs(b).max()), 1e-300):
        raise ValueError("ideal = True on a measurement of relative degree 1 (the ideal derivative feeds the "
                         "control input through); expected a measurement filter (filter_order=1 or 2) or a plant "
                         "of relative degree 2 or more")
    row = np.zeros(n_total)
    row[: a.shape[0]] = -(c[0] @ a)
    return row

def drive_loop(
    a: NDArray,
    b: NDArray,
    c_speed: NDArray,
    angle_index: int,
    *,
    ts: float,
    speed_filter: float | None = None,
    tf: float,
    horizon: float,
    step: float | None = None,
    omega: NDArray[np.float64] | None = None,
    name: str = "drive",
    outputs: dict[str, NDArray] | None = None,
    load_sequence: NDArray[np.float64] | None = None,
    setpoint_sequence: NDArray[np.float64] | None = None,
    setpoint_weight: float = 1.0,
    filters: Sequence = (),
    command_delay_samples: int = 0,
    measurement: LoopMeasurement | None = None,
) -> LoopModel:
    """Loop model of the sampled drive (see module docstring) around a continuous linear plant:
    the one builder of the sampled speed loop, with a pluggable speed measurement.

    Parameters
    ----------
    a, b : arrays
        Continuous plant with inputs (torque command N m, axial load N); one state is the nut
        angle (rad), which the encoder measures.
    c_speed : array
        Row picking the nut speed (rad/s), the performance output.
    angle_index : int
        Index of the nut-angle state. The angle itself drifts (a pure integrator that nothing
        feeds back on): with the encoder's difference the loop keeps only its increment over
        the last sample; with the Kalman filter only the error of the filter's angle estimate.
    ts : float, s
        Controller sample time.
    speed_filter : float, s
        First-order speed-filter time constant of the encoder's difference (the default
        measurement, :class:`~prsa_ctrl.tuning.loopmeasure.EncoderDifference`); leave it out
        with a ``measurement``.
    tf : float, s
        Derivative filter time constant.
    horizon : float, s
        Response length the tuner simulates (it adds the tail beyond it).
    step : float, N
        Load step size (a step loop; leave it out for a duty-cycle loop).
    omega : array, rad/s, optional
        Constraint grid; by default 500 log-spaced points from 0.1 rad/s to the Nyquist
        frequency ``pi/ts`` (with the encoder's difference, plus points at and around the
        sampled plant's resonances).
    load_sequence : array, N, optional
        Duty cycle: the load's deviation from its t = 0 value averaged over each sample
        interval ``[k Ts, (k + 1) Ts)``, one per sample of the horizon (``round(horizon/ts)``).
        The zero-order-hold input of the mean is exact for the integral of the load over the
        sample, so a step between samples or a ramp enters with its exact impulse.
    setpoint_sequence : array, rad/s, optional
        Duty cycle: the setpoint's deviation from its t = 0 value as the controller reads it at
        each sample ``k = 0 .. n_steps`` (first entry 0). The loop then carries the reference
        as a state and its error is the tracking error ``r - speed``.
    setpoint_weight : float
        2-DOF setpoint weight ``b`` in [0, 1] on the proportional path,
        ``u = kp (b r - y) + I``, ``I += Ts ki (r - y)`` (1: the plain PID).
    filters : sequence of LoopFilter or (place, DiscreteBiquad) pairs
        Loop filters run as the sampled simulator runs them: ``speed_measurement`` biquads on
        the measured speed before the PID, ``torque_command`` biquads on the PID's command
        before the computation delay (each with 4 states, direct form I). A ``LoopFilter`` is
        discretised at ``ts``.
    command_delay_samples : int
        The drive's command delay beyond the one-sample computation delay, samples (the plant's
        ``drive.command_delay_samples``): the command computed at sample ``k`` acts from
        ``k + 1 + n``, a line of ``n`` states after the others; the loop's frequency response
        carries the extra ``z^-n = e^{-j w n Ts}``.
    measurement : LoopMeasurement, optional
        The speed measurement block (:mod:`prsa_ctrl.tuning.loopmeasure`): by default the
        encoder's filtered difference with ``speed_filter``;
        :class:`~prsa_ctrl.tuning.loopmeasure.KalmanEstimate` for the Kalman filter (with its
        load feed-forward gain ``kff`` as a fourth gain when asked).

    Returns
    -------
    LoopModel
        Sampled (``nyquist = pi/ts``) with an exact frequency-response function; a profile
        loop (``profile`` set) with one of the sequences.

    Examples
    --------
    A 0.01 kg m^2 inertia (speed state, angle state) at Ts = 1 ms:

    >>> import numpy as np
    >>> a = np.array([[0.0, 0.0], [1.0, 0.0]]); b = np.array([[100.0, -100.0], [0.0, 0.0]])
    >>> lp = drive_loop(a, b, np.array([1.0, 0.0]), 1, ts=1e-3, speed_filter=1e-3, tf=4e-3, horizon=0.2, step=1.0)
    >>> lp.nyquist == np.pi / 1e-3, lp.stability((0.5, 20.0, 0.0))
    (True, 'stable')
    """
    ts = checked_number("ts", ts, lo=0.0, expected="a positive finite sample time in s")
    if measurement is None:
        if speed_filter is None:
            raise ValueError("speed_filter = None; expected the speed-filter time constant in s (or a measurement block)")
        speed_filter = checked_number("speed_filter", speed_filter, lo=0.0,
                                      expected="a positive finite time constant in s")
        measurement = EncoderDifference(speed_filter)
    elif not isinstance(measurement, LoopMeasurement):
        raise ValueError(f"measurement = {measurement!r}; expected a LoopMeasurement block (prsa_ctrl.tuning.loopmeasure)")
    elif speed_filter is not None:
        raise ValueError(f"speed_filter = {speed_filter!r} with measurement {type(measurement).__name__}; expected "
                         "one of them (the block carries its own filtering)")
    meas = measurement
    tf = checked_number("tf", tf, lo=0.0, expected="a positive finite time constant in s")
    horizon = checked_number("horizon", horizon, lo=0.0, expected="a positive finite time in s")
    duty = load_sequence is not None or setpoint_sequence is not None
    if duty:
        step = 0.0 if step is None else checked_number("step", step, expected="a finite step size in N")
    elif step is None:
        raise ValueError("step = None; expected a load step size in N (or a load_sequence / setpoint_sequence)")
    else:
        step = checked_number("step", step, expected="a finite step size in N")
    n_steps = max(10, int(round(horizon / ts)))
    if n_steps > MAX_STEPS:
        raise ValueError(f"horizon = {horizon!r} s is {n_steps} samples of {ts:g} s; expected at most {MAX_STEPS}")
    b_w = checked_number("setpoint_weight", setpoint_weight, lo=0.0, hi=1.0, lo_open=False, hi_open=False,
                  expected="a setpoint weight b in [0, 1]")
    seq_d = seq_r = None
    if load_sequence is not None:
        seq_d = np.asarray(load_sequence, float)
        if seq_d.shape != (n_steps,) or not np.all(np.isfinite(seq_d)):
            raise ValueError(f"load_sequence of shape {seq_d.shape}; expected {n_steps} finite loads in N "
                             f"(one per sample of the {horizon:g} s horizon)")
    if setpoint_sequence is not None:
        seq_r = np.asarray(setpoint_sequence, float)
        if seq_r.shape != (n_steps + 1,) or not np.all(np.isfinite(seq_r)) or seq_r[0] != 0.0:
            raise ValueError(f"setpoint_sequence of shape {seq_r.shape}; expected {n_steps + 1} finite setpoint "
                             "deviations in rad/s starting at 0 (one per sample, both ends included)")
    if isinstance(command_delay_samples, bool) or not isinstance(command_delay_samples, numbers.Integral) \
            or not 0 <= command_delay_samples <= 20:
        raise ValueError(f"command_delay_samples = {command_delay_samples!r}; expected an integer 0..20")
    n_dl = int(command_delay_samples)
    fl = _loop_biquads(filters, ts)
    ad_full, bd_full = zoh(np.asarray(a, float), np.asarray(b, float), ts)
    if meas.keeps_angle:  # the whole plant; the drift of the angle is removed at the end
        ad, bu, bdist = ad_full, bd_full[:, 0], bd_full[:, 1]
        n = ad.shape[0]
        c_w = np.asarray(c_speed, float).ravel()
        i_th = angle_index
        i_m = n  # the block's states
        c_ang, inc_u, inc_d = np.eye(n)[angle_index], 0.0, 0.0
    else:  # the plant without the angle, then the angle's increment over the last sample
        rest = [i for i in range(ad_full.shape[0]) if i != angle_index]
        ad = ad_full[np.ix_(rest, rest)]
        bu, bdist = bd_full[rest, 0], bd_full[rest, 1]
        c_ang, inc_u, inc_d = ad_full[angle_index, rest], bd_full[angle_index, 0], bd_full[angle_index, 1]
        n = len(rest)
        c_w = np.asarray(c_speed, float).ravel()[rest]
        i_th = n
        i_m = n + 1
    beta = math.exp(-ts / tf)
    speed_filters = any(place == "speed_measurement" for place, _ in fl)
    has_prev = not meas.keeps_previous_speed and not speed_filters  # a state for the previous measured speed
    # X = [plant part, measurement states, dfilt, I, (w_prev), u_pending, (r), filters, delay line]
    i_d = i_m + meas.n_states
    i_i = i_d + 1
    i_wp = i_i + 1
    i_u = i_i + 1 + has_prev
    i_r = i_u + 1  # reference (setpoint deviation) state of a setpoint duty cycle
    i_f = i_u + 1 + (seq_r is not None)  # 4 states per loop filter: x1, x2, y1, y2
    i_dl = i_f + 4 * len(fl)  # the command delay line: n_dl states, the last one drives the plant
    N = i_dl + n_dl
    i_act = i_dl + n_dl - 1 if n_dl else i_u  # the command acting on the plant over this sample
    E = np.eye(N)
    meas_rows, w_meas, w_prev, load_row = meas.rows(E, i_th, i_m, i_u, ts)
    filt_rows: dict[int, NDArray] = {}  # state index -> its next-value row (gain-free filters)
    w_pid, w_pid_prev = w_meas, (w_prev if meas.keeps_previous_speed else E[i_wp])
    for j, (place, bq) in enumerate(fl):
        if place == "speed_measurement":
            k = i_f + 4 * j
            y = bq.b0 * w_pid + bq.b1 * E[k] + bq.b2 * E[k + 1] - bq.a1 * E[k + 2] - bq.a2 * E[k + 3]
            filt_rows.update({k: w_pid, k + 1: E[k], k + 2: y, k + 3: E[k + 2]})
            w_pid, w_pid_prev = y, E[k + 2]
    d_new = beta * E[i_d] + (1 - beta) * (w_pid - w_pid_prev) / ts
    e_meas = -w_pid
    A0 = np.zeros((N, N))
    A0[:n, :n] = ad
    A0[:n, i_act] = bu
    if not meas.keeps_angle:
        A0[i_th, :n] = c_ang
        A0[i_th, i_act] = inc_u
    for j in range(n_dl):
        A0[i_dl + j, i_u if j == 0 else i_dl + j - 1] = 1.0
    for k, row in meas_rows.items():
        A0[k] = row
    A0[i_d] = d_new
    A0[i_i, i_i] = 1.0
    if has_prev:
        A0[i_wp] = w_meas
    A0[i_u, i_i] = 1.0  # u = kp e + I - kd d (+ kff * load estimate)
    a_kp, a_ki, a_kd = pid_rows(N, i_u, i_i, e_meas, d_new, ts, ref=E[i_r] if seq_r is not None else None,
                                weight=b_w)
    for k, row in filt_rows.items():
        A0[k] = row
    mats = (A0, a_kp, a_ki, a_kd)
    if meas.feedforward:
        a_ff = np.zeros((N, N))
        a_ff[i_u] = load_row
        mats += (a_ff,)
    cmd = [m[i_u].copy() for m in mats]  # the PID's command, one row per (gain-free, kp, ki, kd[, kff]) part
    for j, (place, bq) in enumerate(fl):
        if place == "torque_command":
            k = i_f + 4 * j
            for part, m in zip(cmd, mats):
                m[k] = part
            A0[k + 1], A0[k + 3] = E[k], E[k + 2]
            rest_row = bq.b1 * E[k] + bq.b2 * E[k + 1] - bq.a1 * E[k + 2] - bq.a2 * E[k + 3]
            cmd = [bq.b0 * part + (rest_row if q == 0 else 0.0) for q, part in enumerate(cmd)]
            for part, m in zip(cmd, mats):
                m[k + 2] = part
    for part, m in zip(cmd, mats):
        m[i_u] = part
    bdv = np.zeros(N)
    bdv[:n] = bdist * step
    if not meas.keeps_angle:
        bdv[i_th] = inc_d * step
    ce = np.zeros(N)
    ce[:n] = -c_w
    profile = None
    if duty:
        # Per-sample inputs; Bd becomes the representative step (largest deviation from t = 0).
        profile = np.zeros((n_steps, N))
        if seq_d is not None:
            profile[:, :n] = seq_d[:, None] * bdist[None, :]
            big = float(seq_d[np.argmax(np.abs(seq_d))])
            bdv[:n] = bdist * big
            if not meas.keeps_angle:
                profile[:, i_th] = seq_d * inc_d
                bdv[i_th] = inc_d * big
        if seq_r is not None:
            profile[:, i_r] = seq_r[1:]
            ce[i_r] = 1.0
            bdv[i_r] = float(seq_r[np.argmax(np.abs(seq_r))])
    if meas.keeps_angle:
        extra = {}
        for k, r in (outputs or {}).items():
            row = np.zeros(N)
            row[:n] = np.asarray(r, float).ravel()
            extra[k] = row
        mats, bdv, ce, extra, profile = _without_drift(mats, bdv, ce, extra, profile, angle_index, i_m)
    else:
        extra = {
            k: np.concatenate([np.asarray(r, float).ravel()[rest], np.zeros(N - n)]) for k, r in (outputs or {}).items()
        }
    nyq = math.pi / ts
    if omega is None:
        omega = meas.grid(ad, ts)
    plant = (ad, bu, c_ang, inc_u, ts)

    def filt(w):  # all filters, the speed ones, the torque ones (None: no such filter)
        return (_filters_response(fl, w),
                _filters_response([f for f in fl if f[0] == "speed_measurement"], w) if speed_filters else None,
                _filters_response([f for f in fl if f[0] == "torque_command"], w)
                if any(f[0] == "torque_command" for f in fl) else None)

    def parts(zi):
        return pid_frequency_parts(zi, ts, beta)

    def response(w):
        L_, D_ = meas.response(w, plant, n_dl, parts, filt)
        return None, L_, None, D_

    def noise(w):
        return meas.noise(w, ts, parts, filt)

    _, L, _, D = response(omega)
    has_noise = meas.noise(omega[:1], ts, parts, filt) is not None
    return LoopModel(mats[0], tuple(mats[1:]), bdv, ce, ts, n_steps, omega, L, tf, name=name, outputs=extra,
                     response=response, nyquist=nyq, profile=profile, noise=noise if has_noise else None,
                     **({"N0": None, "D0": None, "D": D} if D is not None else {}))


def _without_drift(mats, bdv, ce, extra, profile, angle_index: int, i_est: int):
    """The loop in coordinates without the common drift of the angle and its estimate: the
    estimate (state ``i_est``) is replaced by its error ``estimate - angle``, then the angle is
    deleted (refused if anything depends on the absolute angle)."""
    N = bdv.size
    M = np.eye(N)
    M[i_est, angle_index] = -1.0
    Mi = np.linalg.inv(M)
    keep = [i for i in range(N) if i != angle_index]
    out = []
    for A_ in mats:
        At = M @ A_ @ Mi
        col = np.delete(At[:, angle_index], angle_index)
        if np.max(np.abs(col)) > 1e-9 * max(1.0, np.max(np.abs(At))):
            raise ArithmeticError("the loop depends on the absolute angle; expected only angle differences")
        out.append(At[np.ix_(keep, keep)])
    if profile is not None:
        profile = (profile @ M.T)[:, keep]
    return (tuple(out), (M @ bdv)[keep], (ce @ Mi)[keep], {k: (r @ Mi)[keep] for k, r in extra.items()}, profile)

def _loop_biquads(filters, ts: float) -> list:
    """``[(place, DiscreteBiquad)]`` from LoopFilter items or ``(place, DiscreteBiquad)`` pairs."""
    from ..drive.filters import PLACES, DiscreteBiquad, LoopFilter

    out = []
    for item in filters or ():
        if isinstance(item, LoopFilter):
            out.append((item.place, item.biquad(ts)))
        elif isinstance(item, tuple) and len(item) == 2 and item[0] in PLACES and isinstance(item[1], DiscreteBiquad):
            if abs(item[1].ts - ts) > 1e-12 * ts:
                raise ValueError(f"filter biquad at ts = {item[1].ts!r} s; expected the loop's sample time {ts!r} s")
            out.append(item)
        else:
            raise ValueError(f"filter = {item!r}; expected a LoopFilter or a (place, DiscreteBiquad) pair")
    return out

def _filters_response(fl: list, w: NDArray[np.float64]) -> NDArray[np.complex128]:
    """Product of the loop filters' frequency responses at ``w`` (rad/s)."""
    out = np.ones(np.shape(w), complex)
    for _, bq in fl:
        out = out * bq.frequency_response(w)
    return out
