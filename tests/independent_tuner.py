"""Independent brute-force references for the generic tuner (issue 25).

Nothing here calls prsa_ctrl: the loop is evaluated from the plant's polynomial coefficients
(numpy.polyval) on a dense log grid, the delay as the exact ``exp(-j w L)``, and the optima are
found by bisection / bounded scalar search in scipy. The objective is IE after a unit load step
at the plant input, which for a controller with integral action is exactly ``1/ki``: the
optimum is the largest feasible ``ki``.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize_scalar

#: Dense grid (rad/s) for the peaks: 12000 points over 9 decades plus the high-frequency limit.
W = np.logspace(-4, 5, 12000)


def loop_parts(num, den, delay=0.0, w=W):
    """P(jw) of num/den (highest power first) with an exact delay."""
    s = 1j * w
    return np.polyval(num, s) / np.polyval(den, s) * np.exp(-s * delay)


def controller(kp, ki, kd=0.0, tf=0.0, filt=None, w=W):
    """C(jw) F(jw): PID kp + ki/s + kd s/(1 + tf s) times the filter ``filt = (order, Tf)``."""
    s = 1j * w
    c = kp + ki / s + kd * s / (1 + tf * s)
    if filt is not None:
        order, t = filt
        c = c / ((t * s + 1) if order == 1 else (t * t * s * s / 2 + t * s + 1))
    return c


def peaks(p, c):
    """(Ms, Mt, Mks) on the grid, the last one also at the high-frequency limit."""
    L = p * c
    S = 1 / (1 + L)
    return float(np.max(np.abs(S))), float(np.max(np.abs(L * S))), float(np.max(np.abs(c * S)))


def stable(num, den, kp, ki, kd=0.0, tf=0.0, filt=None):
    """Closed-loop stability from the characteristic polynomial (rational loops only)."""
    s_poly = np.array([1.0, 0.0])
    # C = (kd s^2 + (kp + kd?)..): build C F as a ratio of polynomials
    cn = np.polyadd(np.polymul([kp, ki], [tf, 1.0]), [kd, 0.0, 0.0])
    cd = np.polymul(s_poly, [tf, 1.0])
    if filt is not None:
        order, t = filt
        cd = np.polymul(cd, [t, 1.0] if order == 1 else [t * t / 2, t, 1.0])
    char = np.polyadd(np.polymul(den, cd), np.polymul(num, cn))
    return bool(np.all(np.roots(np.trim_zeros(char, "f")).real < 0))


def max_ki(num, den, kp, ms, mt=None, mks=None, kd=0.0, tf=0.0, filt=None, delay=0.0, p=None):
    """Largest ki (bisection in log ki) meeting the bounds at fixed kp, kd; 0 if none."""
    p = loop_parts(num, den, delay) if p is None else p

    def ok(ki):
        m = peaks(p, controller(kp, ki, kd, tf, filt))
        good = m[0] <= ms and (mt is None or m[1] <= mt) and (mks is None or m[2] <= mks)
        return good and (delay > 0 or stable(num, den, kp, ki, kd, tf, filt))

    lo, hi = 1e-6, 1e4
    if not ok(lo):
        return 0.0
    for _ in range(70):
        mid = np.sqrt(lo * hi)
        lo, hi = (mid, hi) if ok(mid) else (lo, mid)
    return lo


def best_pi(num, den, ms, mt=None, mks=None, filt=None, delay=0.0, kp_hi=50.0, n=300):
    """Brute-force IE-optimal PI: kp on a grid, then a bounded scalar search around the best."""
    p = loop_parts(num, den, delay)
    kps = np.linspace(kp_hi / n, kp_hi, n)
    vals = [max_ki(num, den, k, ms, mt, mks, filt=filt, delay=delay, p=p) for k in kps]
    i = int(np.argmax(vals))
    lo, hi = kps[max(i - 1, 0)], kps[min(i + 1, n - 1)]
    r = minimize_scalar(lambda k: -max_ki(num, den, k, ms, mt, mks, filt=filt, delay=delay, p=p),
                        bounds=(lo, hi), method="bounded", options={"xatol": 1e-7 * kp_hi})
    return float(r.x), float(-r.fun)


def best_pi_filtered(num, den, order, ms, mt, mks, t_lo, t_hi, kp_hi=50.0):
    """Brute-force IE-optimal PI with the filter time constant also searched (golden section in
    log Tf on top of :func:`best_pi`)."""
    def neg(lt):
        return -best_pi(num, den, ms, mt, mks, filt=(order, float(np.exp(lt))), kp_hi=kp_hi, n=60)[1]

    r = minimize_scalar(neg, bounds=(np.log(t_lo), np.log(t_hi)), method="bounded", options={"xatol": 1e-4})
    t = float(np.exp(r.x))
    kp, ki = best_pi(num, den, ms, mt, mks, filt=(order, t), kp_hi=kp_hi)
    return t, kp, ki


def best_filtered_pid(num, den, order, ms, mt, mks, starts, w=None, log_tf=None):
    """IE-optimal ideal PID times the filter ``F`` of ``order`` (Tf free, or fixed at
    ``exp(log_tf)``) by SLSQP on the semi-infinite problem discretised on a dense grid: one smooth
    constraint per frequency for each bound (``|1 + L|^2 >= 1/Ms^2``, ``|L|^2 <= Mt^2 |1 + L|^2``,
    ``|C F|^2 <= Mks^2 |1 + L|^2``), from each of ``starts`` (kp, ki, kd, Tf); the best verified
    point (peaks re-evaluated on :data:`W`). Returns ``(kp, ki, kd, Tf)``."""
    from scipy.optimize import minimize

    w = np.logspace(-3, 3, 3000) if w is None else w
    p = loop_parts(num, den, w=w)
    s = 1j * w

    def parts(x):
        kp, ki, kd = x[:3]
        t = np.exp(x[3]) if log_tf is None else np.exp(log_tf)
        c = controller(kp, ki, kd, 0.0, (order, t), w=w)
        L = p * c
        return c, L

    def cons(x):
        c, L = parts(x)
        a = np.abs(1 + L) ** 2
        out = [a * ms * ms - 1.0]
        if mt is not None:
            out.append(mt * mt * a - np.abs(L) ** 2)
        if mks is not None:
            out.append((mks * mks * a - np.abs(c) ** 2) / mks ** 2)
        return np.concatenate(out)

    best = None
    for x0 in starts:
        x0 = np.array([x0[0], x0[1], x0[2], np.log(x0[3])], float)
        if log_tf is not None:
            x0[3] = log_tf
        r = minimize(lambda x: -x[1], x0, method="SLSQP", constraints=[{"type": "ineq", "fun": cons}],
                     bounds=[(0, None), (1e-6, None), (0, None), (-12, 3)], options={"maxiter": 300, "ftol": 1e-12})
        x = r.x
        t = np.exp(x[3]) if log_tf is None else np.exp(log_tf)
        pk = peaks(loop_parts(num, den), controller(x[0], x[1], x[2], 0.0, (order, t)))
        tol = 1 + 1e-4  # the 3000-point grid of the solve vs the dense grid of the check
        ok = pk[0] <= ms * tol and (mt is None or pk[1] <= mt * tol) and (mks is None or pk[2] <= mks * tol)
        ok = ok and stable(num, den, x[0], x[1], x[2], 0.0, (order, t))
        if ok and (best is None or x[1] > best[1]):
            best = (float(x[0]), float(x[1]), float(x[2]), float(t))
    return best


def delayed_pi_iae(kp, ki, tau, delay, t_end):
    """IAE of the load-step response of ``e^{-s delay}/(tau s + 1)`` under the PI ``kp + ki/s``,
    by the method of steps (scipy solve_ivp, rtol 1e-11, dense output per delay interval):
    ``x' = (-x + u + 1)/tau``, ``u = kp e + ki I``, ``I' = e``, ``e(t) = -x(t - delay)``; the IAE is
    ``int_0^t_end |x|`` (the error is the plant state delayed)."""
    from scipy.integrate import quad, solve_ivp

    pieces = []  # dense outputs of x over [k delay, (k + 1) delay]

    def x_past(t):
        if t <= 0:
            return 0.0
        k = min(int(t // delay), len(pieces) - 1)
        return float(pieces[k](t)[0])

    state = np.zeros(2)
    t0 = 0.0
    while t0 < t_end:
        def rhs(t, z):
            e = -x_past(t - delay)
            return [(-z[0] + kp * e + ki * z[1] + 1.0) / tau, e]

        sol = solve_ivp(rhs, (t0, t0 + delay), state, rtol=1e-11, atol=1e-13, dense_output=True)
        pieces.append(sol.sol)
        state = sol.y[:, -1]
        t0 += delay
    total = 0.0
    for k, p in enumerate(pieces):
        total += quad(lambda t: abs(p(t)[0]), k * delay, (k + 1) * delay, limit=200, epsabs=1e-13, epsrel=1e-11)[0]
    return total


def margins_exact(num, den, kp, ki, delay, w=None):
    """Phase margin (deg) and gain margin (dB) of ``(kp + ki/s) P e^{-s delay}`` on a dense
    grid (interpolated crossings)."""
    w = np.logspace(-3, 2, 200000) if w is None else w
    L = loop_parts(num, den, delay, w) * controller(kp, ki, w=w)
    mag = np.abs(L)
    i = np.flatnonzero((mag[:-1] >= 1) & (mag[1:] < 1))[0]
    ph = np.unwrap(np.angle(L))
    pm = 180.0 + np.degrees(np.interp(0.0, [np.log(mag[i + 1]), np.log(mag[i])][::-1], [ph[i + 1], ph[i]][::-1]))
    j = np.flatnonzero((ph[:-1] > -np.pi) & (ph[1:] <= -np.pi))[0]
    f = (ph[j] + np.pi) / (ph[j] - ph[j + 1])
    gm = -20 * np.log10(mag[j] + f * (mag[j + 1] - mag[j]))
    return float(pm), float(gm)


def setpoint_iae(num, den, kp, ki, kd, tf, b, c, t_end=80.0, n=80001):
    """IAE of r - y after a unit setpoint step under ``u = kp (b r - y) + ki/s (r - y) + kd s/(1 +
    tf s) (c r - y)``, from the closed-loop transfer function (scipy.signal.lsim on a dense grid,
    trapezoid rule)."""
    from scipy import signal

    pn, pd = np.asarray(num, float), np.asarray(den, float)
    # Controller polynomials over the common denominator s (tf s + 1).
    cd = np.polymul([1.0, 0.0], [tf, 1.0])
    c_fb = np.polyadd(np.polyadd(np.polymul([kp, 0.0], [tf, 1.0]), [ki * tf, ki]), [kd, 0.0, 0.0])
    c_r = np.polyadd(np.polyadd(np.polymul([kp * b, 0.0], [tf, 1.0]), [ki * tf, ki]), [kd * c, 0.0, 0.0])
    den_cl = np.polyadd(np.polymul(pd, cd), np.polymul(pn, c_fb))
    num_cl = np.polymul(pn, c_r)
    t = np.linspace(0.0, t_end, n)
    _, y, _ = signal.lsim((num_cl, den_cl), np.ones_like(t), t)
    return float(np.trapezoid(np.abs(1.0 - y), t)), float(np.max(y) - 1.0)


def best_ideal_pid(num, den, ms, mt, starts, w=None):
    """IE-optimal ideal PID ``kp + ki/s + kd s`` (no filter) under Ms (and Mt) by SLSQP on the
    grid-discretised semi-infinite problem from each start; the best point with its peaks on
    :data:`W`: ``((kp, ki, kd), (Ms, Mt))``."""
    from scipy.optimize import minimize

    w = np.logspace(-3, 3, 4000) if w is None else w
    p = loop_parts(num, den, w=w)

    def cons(x):
        L = p * controller(x[0], x[1], x[2], w=w)
        a = np.abs(1 + L) ** 2
        out = [a * ms * ms - 1.0]
        if mt is not None:
            out.append(mt * mt * a - np.abs(L) ** 2)
        return np.concatenate(out)

    best = None
    for x0 in starts:
        r = minimize(lambda x: -x[1], x0, method="SLSQP", constraints=[{"type": "ineq", "fun": cons}],
                     bounds=[(0, None), (1e-6, None), (0, None)], options={"maxiter": 300, "ftol": 1e-12})
        if best is None or r.x[1] > best[1]:
            best = r.x
    pk = peaks(loop_parts(num, den), controller(*best))
    return tuple(float(v) for v in best), pk[:2]
