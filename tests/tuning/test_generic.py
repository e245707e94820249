"""tune_pid (prsa_ctrl/tuning/generic.py): cases of issue 34 part 2, each against an independent
reference written here with numpy/scipy only (the exact delay ``e^{-j w L}``, no prsa_ctrl)."""

from __future__ import annotations

import functools
import math

import control
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st
from scipy.linalg import expm, matrix_balance
from scipy.optimize import minimize, minimize_scalar

import prsa_ctrl.tuning.nlp as nlp
import prsa_ctrl.tuning.tuner as tuner
from prsa_ctrl.drive.pid import PID
from prsa_ctrl.tuning import continuous_loop, tune_pid
from prsa_ctrl.tuning.builders import continuous_loop, drive_loop
from prsa_ctrl.tuning.generic import FILTER_DECADES, optimal_filter, tune_loops, tune_pid
from prsa_ctrl.tuning.tuner import Tuner, TuningResult

import independent_tuner as ref

# ---- an independent reference for e^(-L s)/(s - 1) under a PI ------------------------------------

#: Dense grid for the peaks (rad/s) and the imaginary-axis grid of the argument principle.
_W_PEAK = np.logspace(-3, 3, 20000)
_W_ARG = np.linspace(0.0, 400.0, 80001)


@functools.lru_cache(maxsize=8)
def _grid_parts(delay, which):
    """``(s, e^{-s L}, s (s - 1), (s + 1)^2)`` on the peak (``which = "peak"``) or the argument
    grid, computed once per delay instead of in each of the bisections' feasibility checks (the
    same arrays, so the same results)."""
    s = 1j * (_W_PEAK if which == "peak" else _W_ARG)
    return s, np.exp(-s * delay), s * (s - 1.0), (s + 1.0) ** 2


def _ms(kp, ki, delay):
    """Peak of ``|1 / (1 + L)|``, ``L = (kp + ki/s) e^{-L s}/(s - 1)``, on ``_W_PEAK``."""
    s, e_delay, _, _ = _grid_parts(delay, "peak")
    return float(np.max(1.0 / np.abs(1.0 + (kp + ki / s) * e_delay / (s - 1.0))))


def _rhp_roots(kp, ki, delay):
    """Closed-loop roots in the right half plane of ``s (s - 1) + (kp s + ki) e^{-L s} = 0``
    (the exact delay) by the argument principle on ``g = f / (s + 1)^2`` (analytic in the right
    half plane, -> 1 there): ``Z = -(change of arg g along the imaginary axis) / (2 pi)``, the
    two halves of the axis conjugate. Beyond 400 rad/s ``|g - 1| < 0.02`` (no winding left)."""
    s, e_delay, s_sm1, sp1_sq = _grid_parts(delay, "arg")
    g = (s_sm1 + (kp * s + ki) * e_delay) / sp1_sq
    ph = np.unwrap(np.angle(g))
    return int(round(-2.0 * (ph[-1] - ph[0]) / (2.0 * math.pi)))


def _feasible(kp, ki, delay, ms_max):
    # (the cheaper peak first: both must hold, so the order does not change the answer)
    return _ms(kp, ki, delay) <= ms_max and _rhp_roots(kp, ki, delay) == 0


def _max_ki(kp, delay, ms_max, hi=20.0):
    """Largest ki at fixed kp with a stable loop and Ms <= ms_max (bisection from a feasible
    small ki; 0 when none)."""
    lo = 1e-6
    if not _feasible(kp, lo, delay, ms_max):
        return 0.0
    while _feasible(kp, hi, delay, ms_max):
        hi *= 2.0
    for _ in range(36):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if _feasible(kp, mid, delay, ms_max) else (lo, mid)
    return lo


def _best_pi(delay, ms_max):
    """Largest feasible ki over kp: a kp scan, then a bounded search around the best (the best
    feasible point seen is kept)."""
    kps = np.linspace(0.5, 8.0, 31)
    vals = [_max_ki(k, delay, ms_max) for k in kps]
    i = int(np.argmax(vals))
    assert vals[i] > 0, "the reference found no feasible PI"
    best = (float(kps[i]), float(vals[i]))
    r = minimize_scalar(lambda k: -_max_ki(k, delay, ms_max), bounds=(kps[max(i - 1, 0)], kps[min(i + 1, kps.size - 1)]),
                        method="bounded", options={"xatol": 1e-6})
    if -r.fun > best[1]:
        best = (float(r.x), float(-r.fun))
    return best


def test_reference_checks_itself():
    # The argument principle agrees with the roots of the delay-free characteristic polynomial.
    for kp, ki in ((2.0, 0.5), (0.5, 0.5), (3.0, 4.0), (1.5, 0.0001), (0.9, 2.0)):
        n_rhp = int(np.sum(np.roots([1.0, kp - 1.0, ki]).real > 0))
        assert _rhp_roots(kp, ki, 0.0) == n_rhp
    # With the delay: P control at kp <= 1 cannot stabilise 1/(s - 1) (its static loop gain < 1).
    assert _rhp_roots(0.8, 0.01, 0.2) > 0
    assert _rhp_roots(2.0, 0.5, 0.2) == 0


def test_unstable_plant_with_delay_tuned_not_refused():
    """e^(-0.2 s)/(s - 1), PI, IE, Ms <= 2 was refused ("no stabilising PI gains ... on the
    scan"; the scan's time scale came from the grid's lowest frequency): tuned to the
    reference's ki within 0.5 %, its true peak within the bound and the loop stable with the
    exact delay."""
    res = tune_pid(control.tf([1.0], [1.0, -1.0]), objective="ie", ms_max=2.0, delay=0.2)
    assert res.converged, res.status
    kp, ki = res.pid.kp, res.pid.ki
    assert _rhp_roots(kp, ki, 0.2) == 0
    assert _ms(kp, ki, 0.2) <= 2.0 * (1 + 1e-6)
    assert res.ms <= 2.0
    kp_ref, ki_ref = _best_pi(0.2, 2.0)
    assert _feasible(kp_ref, ki_ref, 0.2, 2.0)  # the reference's own point checked
    assert abs(ki / ki_ref - 1.0) < 5e-3, (kp, ki, kp_ref, ki_ref)
    # The issue's figure (an independent brute force): ki 0.997430.
    assert abs(ki / 0.997430 - 1.0) < 5e-3


def test_no_stabilising_pi_says_relaxing_does_not_help():
    # A PI cannot stabilise e^(-2 s)/(s - 1) (delay twice the unstable time constant): the bounds
    # are not the limit, so the message must not ask to relax them.
    with pytest.raises(ValueError) as err:
        tune_pid(control.tf([1.0], [1.0, -1.0]), objective="ie", ms_max=2.0, delay=2.0)
    msg = str(err.value)
    assert msg.startswith("no stabilising PI gains found")
    assert "relaxing them does not help" in msg
    assert "relax the constraints" not in msg
    # The reference agrees: no stabilising PI on a coarse (kp, ki) grid.
    assert not any(_rhp_roots(kp, ki, 2.0) == 0 for kp in np.linspace(0.2, 6.0, 30)
                   for ki in (1e-4, 1e-2, 0.1, 0.5))


def test_bound_below_reach_names_the_least_ms_found():
    # Stabilising PI gains exist, but none with Ms <= 1.2: relaxing helps, and the message says how far.
    with pytest.raises(ValueError) as err:
        tune_pid(control.tf([1.0], [1.0, -1.0]), objective="ie", ms_max=1.2, delay=0.2)
    msg = str(err.value)
    assert "relax the constraints" in msg
    least = float(msg.split("the least Ms among them ")[1].split(":")[0])
    assert 1.2 < least
    # The reference: Ms of a stabilising PI is never below ~1.54 here (a coarse scan finds none under 1.5).
    assert min(_ms(kp, ki, 0.2) for kp in np.linspace(1.1, 4.0, 30) for ki in (1e-3, 0.05, 0.2)
               if _rhp_roots(kp, ki, 0.2) == 0) > 1.5


# ---- a delay far below the loop's time scale (issue 34 part 2) -------------------------------------

def test_tiny_delay_tunes_like_no_delay_within_its_phase():
    """1/(s + 1) with a delay of 1e-10 .. 3e-5 s failed after ~35 s (the exact delayed simulation
    at 8 samples per delay ran out of budget; a 1e-10 s delay's order-6 Pade model could not be
    simulated). It tunes, and the result differs from the delay-free one by an amount first
    order in the delay's phase phi = wc L at the crossover: the relative drop of ki and the
    relative rise of the IAE are each at most 5 phi (measured: about 3.2 phi), and they scale
    with the delay (3e-5 against 1e-5: a ratio of 3 within 10 %)."""
    plant = control.tf([1.0], [1.0, 1.0])
    ref = tune_pid(plant)
    assert ref.converged
    drops = {}
    for delay in (1e-10, 1e-5, 3e-5):
        res = tune_pid(plant, delay=delay)
        assert res.converged, (delay, res.status)
        phi = res.margins[0].wc_rad_s * delay
        d_ki = (ref.pid.ki - res.pid.ki) / ref.pid.ki
        d_iae = (res.objective - ref.objective) / ref.objective
        tol = 5 * phi + 2e-6  # + the tuners' own first-order tolerance
        assert -2e-6 <= d_ki <= tol, (delay, d_ki, phi)
        assert -2e-6 <= d_iae <= tol, (delay, d_iae, phi)
        # What the objective is, stated: the Pade model's (the exact simulation is out of reach).
        assert res.stats["delay_model"]["objective"] == "pade"
        assert any("Pade model of order" in w and "exact delay" in w for w in res.warnings)
        drops[delay] = d_ki
    assert 2.7 <= drops[3e-5] / drops[1e-5] <= 3.3, drops


# ---- the 2-DOF law as stated (issue 34 part 2) ---------------------------------------------------

def _setpoint_step_iae(kp, ki, kd, tf, b, c, t_filter, filter_on_setpoint=False, t_end=80.0, n=40001):
    """IAE of r - y after a unit setpoint step on 1/(s + 1)^3 under ``u = kp (b r - y_f) + ki
    (r - y_f)/s + kd s/(tf s + 1) (c r - y_f)``, ``y_f = F y``, F = 1/(Tf^2 s^2/2 + Tf s + 1)
    (``filter_on_setpoint``: the other reading, ``u = F [kp (b r - y) + ...]``), from the
    closed-loop transfer function (scipy.signal.lsim, exact for a step input; trapezoid rule)."""
    from scipy import signal

    pn, pd = np.array([1.0]), np.polymul(np.polymul([1.0, 1.0], [1.0, 1.0]), [1.0, 1.0])
    fn, fd = np.array([1.0]), np.array([t_filter ** 2 / 2, t_filter, 1.0])
    cd = np.polymul([1.0, 0.0], [tf, 1.0])
    cy = np.polyadd(np.polyadd(np.polymul([kp, 0.0], [tf, 1.0]), [ki * tf, ki]), [kd, 0.0, 0.0])
    cr = np.polyadd(np.polyadd(np.polymul([kp * b, 0.0], [tf, 1.0]), [ki * tf, ki]), [kd * c, 0.0, 0.0])
    den = np.polyadd(np.polymul(np.polymul(pd, cd), fd), np.polymul(np.polymul(pn, cy), fn))
    num = np.polymul(np.polymul(pn, cr), fn if filter_on_setpoint else fd)
    assert np.all(np.roots(den).real < 0)
    t = np.linspace(0.0, t_end, n)
    _, y, _ = signal.lsim((num, den), np.ones_like(t), t)
    e = np.abs(1.0 - y)
    assert e[-1] < 1e-9  # settled: the horizon holds the whole integral
    return float(np.trapezoid(e, t))


def test_setpoint_law_is_the_stated_one():
    """The guide, the docstring and the JSON state ``u = kp (b r - y_f) + ki (r - y_f)/s + kd D(s)
    (c r - y_f)``, ``y_f = F y``: the reported setpoint IAE is that law's (an independent
    simulation of it), and not that of the filter on the setpoint too."""
    res = tune_pid(control.tf([1.0], [1.0, 3.0, 3.0, 1.0]), controller="pid", filter_order=2, filter_tf=0.3,
                   setpoint_weights=True)
    assert res.converged, res.status
    sp, pid = res.setpoint, res.pid
    for b, c, value in ((sp["b"], sp["c"], sp["iae"]), (1.0, 1.0, sp["iae_unweighted"])):
        ref = _setpoint_step_iae(pid.kp, pid.ki, pid.kd, pid.tf, b, c, 0.3)
        other = _setpoint_step_iae(pid.kp, pid.ki, pid.kd, pid.tf, b, c, 0.3, filter_on_setpoint=True)
        assert abs(value / ref - 1.0) < 1e-4, (b, c, value, ref)
        assert abs(other / ref - 1.0) > 1e-2  # the test tells the two readings apart


# ---- a free filter time constant: optimal over the range searched, and the status says so ------------

_W_F = np.logspace(-4, 6, 15000)


@functools.lru_cache(maxsize=4)
def _pi_filter_plant(num, den):
    """``(s, P(s))`` on ``_W_F``: computed once per plant instead of in each of the brute force's
    thousands of feasibility checks (the same arrays, so the same results)."""
    s = 1j * _W_F
    return s, np.polyval(num, s) / np.polyval(den, s)


def _pi_filter_feasible(num, den, kp, ki, t_f, ms, mt, mks):
    """PI ``kp + ki/s`` behind ``1/(Tf s + 1)``: true peaks on a dense grid and stability from the
    characteristic polynomial (no delay)."""
    s, p = _pi_filter_plant(tuple(num), tuple(den))
    cf = (kp + ki / s) / (t_f * s + 1.0)
    S = 1.0 / (1.0 + p * cf)
    if np.max(np.abs(S)) > ms or np.max(np.abs(p * cf * S)) > mt or np.max(np.abs(cf * S)) > mks:
        return False
    char = np.polyadd(np.polymul(den, np.polymul([1.0, 0.0], [t_f, 1.0])), np.polymul(num, [kp, ki]))
    return bool(np.all(np.roots(char).real < 0))


def _pi_filter_ki_at(num, den, kp, t_f, ms, mt, mks):
    lo, hi = 1e-6, 4.0
    if not _pi_filter_feasible(num, den, kp, lo, t_f, ms, mt, mks):
        return 0.0
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if _pi_filter_feasible(num, den, kp, mid, t_f, ms, mt, mks) else (lo, mid)
    return lo


def _pi_filter_max_ki(num, den, t_f, ms, mt, mks, kps):
    """The largest feasible ki over kp at this Tf (bisection in ki per kp of the grid, from a
    feasible small ki, then a bounded search in kp around the best); the best (kp, ki) seen."""
    vals = [_pi_filter_ki_at(num, den, kp, t_f, ms, mt, mks) for kp in kps]
    i = int(np.argmax(vals))
    best = (float(kps[i]), float(vals[i]))
    r = minimize_scalar(lambda k: -_pi_filter_ki_at(num, den, k, t_f, ms, mt, mks),
                        bounds=(kps[max(i - 1, 0)], kps[min(i + 1, len(kps) - 1)]), method="bounded",
                        options={"xatol": 1e-5, "maxiter": 30})
    if -r.fun > best[1]:
        best = (float(r.x), float(-r.fun))
    return best


def test_free_filter_status_names_its_range_and_is_optimal_over_it():
    """IE with a free measurement filter (issue 34: "optimal" alone for a problem without an
    optimum): the status names the Tf range searched, the result is feasible, and an
    independent brute force over that range finds no larger ki."""
    num, den = [-1.0, 1.0], [1.0, 3.0, 3.0, 1.0]
    ms, mt, mks = 1.4, 1.3, 3.0
    r = tune_pid(control.tf(num, den), objective="ie", ms_max=ms, mt_max=mt, mks_max=mks, filter_order=1)
    fs = r.stats["filter_search"]
    t_lo, t_hi = fs["range_s"]
    assert r.converged
    assert r.status.startswith(f"optimal (over Tf in [{t_lo:.4g}, {t_hi:.4g}] s, the filter's search range")
    assert t_hi / t_lo == pytest.approx(1e4, rel=1e-9)  # four decades, as documented
    t_f = r.filter["tf_s"]
    assert _pi_filter_feasible(num, den, r.pid.kp, r.pid.ki, t_f, ms * (1 + 1e-6), mt * (1 + 1e-6), mks * (1 + 1e-6))
    kps = np.linspace(0.02, 1.5, 38)
    for t in np.geomspace(t_lo, t_hi, 9):
        kp_ref, ki_ref = _pi_filter_max_ki(num, den, t, ms, mt, mks, kps)
        assert _pi_filter_feasible(num, den, kp_ref, ki_ref, t, ms, mt, mks) or ki_ref == 0.0  # checked itself
        assert ki_ref <= r.pid.ki * (1 + 1e-3), (t, kp_ref, ki_ref, r.pid.ki)
    # and at the reported Tf the brute force agrees with the tuner's ki
    assert _pi_filter_max_ki(num, den, t_f, ms, mt, mks, kps)[1] == pytest.approx(r.pid.ki, rel=1e-3)


def test_filter_search_span_is_stated_once():
    """The docstring, the guide and the code give the same span of the Tf search (the docstring
    said five decades while the code searched four)."""
    from pathlib import Path

    from prsa_ctrl.tuning.generic import FILTER_DECADES

    words = {3: "three", 4: "four", 5: "five", 6: "six"}[FILTER_DECADES]
    doc = " ".join(tune_pid.__doc__.split())
    guide = " ".join((Path(__file__).parents[2] / "docs" / "guides" / "generic-tuner.md").read_text().split())
    assert f"{words} decades" in doc
    assert f"{words} decades" in guide
    # the search's span, wherever the docstring and the guide describe the Tf search
    for text in (doc, guide):
        for w in ("three", "four", "five"):
            assert (f"{w} decades" in text) == (w == words), (w, words)


# ------------------------------------------------------------------------------------------------
# Issue 20: "optimal" means optimal, the reported objective is the continuous loop's, and bad
# plants get a clear error.
#
# Every reference here is computed WITHOUT the tuner's internals: Ms from python-control's own
# frequency response of P(s) C(s) on a dense grid plus a bounded scalar refinement, the IAE from
# the closed loop that ``control.feedback`` builds, sampled exactly (matrix exponential) and
# summed by the trapezoid rule, the IE of an input step from the final-value theorem
# (``int e = -1/ki``, exact for any plant with an integrating PI/PID).
# ------------------------------------------------------------------------------------------------

_GRID = [(c, m) for c in ("pi", "pid") for m in (1.4, 2.0)]

s = control.tf("s")
TWO_PI = 2 * math.pi


def servo(j=2.2e-4, delay=0.375e-3, f_cur=1000.0):
    """Speed loop of a screw actuator: inertia ``j`` (kg m^2, issue 20 s.2), a first-order current
    loop of bandwidth ``f_cur`` (Hz) and a 6th-order Pade model of the ``delay`` (s)."""
    num, den = control.pade(delay, 6)
    return control.tf(1, [j, 0]) * control.tf(1, [1 / (TWO_PI * f_cur), 1]) * control.tf(num, den)


def controller(kp, ki, kd, tf):
    return kp + ki / s + kd * s / (tf * s + 1)


def _plant_response(plant, w):
    return np.asarray(control.frequency_response(plant, w).complex).ravel()


def true_ms(plant, kp, ki, kd, tf, w_lo, w_hi, p_dense=None, w_dense=None):
    """Peak of |1/(1 + P C)|: 20 000 log points from python-control, then Brent around the top."""
    if w_dense is None:
        w_dense = np.logspace(math.log10(w_lo), math.log10(w_hi), 20_000)
        p_dense = _plant_response(plant, w_dense)

    def mag(w, p):
        jw = 1j * np.asarray(w, float)
        c = kp + ki / jw + kd * jw / (tf * jw + 1)
        return 1 / np.abs(1 + p * c)

    m = mag(w_dense, p_dense)
    i = int(np.argmax(m))
    lo, hi = math.log(w_dense[max(i - 1, 0)]), math.log(w_dense[min(i + 1, w_dense.size - 1)])
    r = minimize_scalar(lambda x: -mag([math.exp(x)], _plant_response(plant, [math.exp(x)]))[0],
                        method="bounded", bounds=(lo, hi), options={"xatol": 1e-10})
    assert r.success, r.message  # (the grid's value is kept when the refinement finds less)
    return max(float(m[i]), float(-r.fun))


def true_iae(plant, kp, ki, kd, tf, n=4000):
    """IAE of the error after a unit input-disturbance step, from ``control.feedback`` (continuous):
    exact samples ``x_{k+1} = e^{A h} x_k + int e^{A s} ds B``, trapezoid rule (e(0) = 0) over 20
    times the slowest closed-loop time constant, with ``h`` halved once and Richardson
    extrapolation."""
    sys = control.ss(control.feedback(plant, controller(kp, ki, kd, tf)))
    a, b, c = np.asarray(sys.A), np.asarray(sys.B)[:, :1], np.asarray(sys.C)[:1]
    # Balance the companion form (coefficients over ~40 decades with the Pade delay) before expm.
    a, (t, _) = matrix_balance(a, permute=False, separate=True)
    b, c = b / t[:, None], c * t[None, :]
    lam = np.linalg.eigvals(a)
    if np.max(lam.real) >= 0:
        return math.inf
    horizon = 20.0 / np.min(np.abs(lam.real))

    def run(m):
        h = horizon / m
        blk = np.zeros((a.shape[0] + 1, a.shape[0] + 1))
        blk[:-1, :-1], blk[:-1, -1:] = a * h, b * h
        e = expm(blk)
        ad, bd = e[:-1, :-1], e[:-1, -1]
        x, total = np.zeros(a.shape[0]), 0.0
        ys = np.empty(m)
        for k in range(m):
            x = ad @ x + bd
            ys[k] = c[0] @ x
        return h * float(np.sum(np.abs(ys)))  # y(0) = 0; the tail beyond is below e^-20

    i1, i2 = run(n), run(2 * n)
    return i2 + (i2 - i1) / 3.0


def stable(plant, kp, ki, kd, tf):
    """Closed-loop poles of ``control.feedback(P C)`` in the open left half plane."""
    return bool(np.max(control.feedback(plant * controller(kp, ki, kd, tf), 1).poles().real) < 0)


def _pid(r):
    return r.pid.kp, r.pid.ki, r.pid.kd, r.pid.tf


# --------------------------------------------------------------------------------------------
# section 2: the integrating servo class against an independent brute force


def brute_ie(plant, ms_max, tf, use_d, kp_ref, w_lo, w_hi):
    """Largest ki (IE = 1/ki) with a stable loop and Ms <= ms_max.

    For each (kp, kd): Ms of a 49-point log grid of ki (1e-2 .. 1e6) on 20 000 frequencies;
    from the first grid point that is stable and within the bound, upwards to the first that is
    not (a loop cannot turn unstable inside that interval: its Nyquist curve would have to
    cross -1, where Ms is infinite), then bisection. (kp, kd) by a zoom grid: 5 x 5 points
    (kp from 0.25 to 4 times ``kp_ref``, kd from 0 to 16 kp_ref tf at first) around the best,
    the span shrinking by 0.6 where the centre stays best, 10 levels. (With PID the optimum
    sits on a ridge where two peaks of |S| are equal; a grid search may stop short of it.) The reported ki is then checked with the
    refined Ms (:func:`true_ms`)."""
    w = np.logspace(math.log10(w_lo), math.log10(w_hi), 20_000)
    p = _plant_response(plant, w)
    jw = 1j * w

    def ms_dense(kp, ki, kd):
        ki = np.atleast_1d(ki)[:, None]
        c = kp + ki / jw + kd * jw / (tf * jw + 1)
        return np.max(1 / np.abs(1 + p * c), axis=1)

    kis = np.logspace(-2, 6, 49)

    def ki_max(kp, kd):
        if kp <= 0 or kd < 0:
            return 0.0
        ok = ms_dense(kp, kis, kd) <= ms_max
        start = next((i for i in np.flatnonzero(ok) if stable(plant, kp, kis[i], kd, tf)), None)
        if start is None:
            return 0.0
        end = start
        while end + 1 < kis.size and ok[end + 1]:
            end += 1
        lo, hi = kis[end], kis[min(end + 1, kis.size - 1)]
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if ms_dense(kp, mid, kd)[0] <= ms_max else (lo, mid)
        return lo

    kd_span = 16 * kp_ref * tf if use_d else 0.0
    best = max((ki_max(kp, kd), kp, kd) for kp in kp_ref * np.logspace(-0.6, 0.6, 9)
               for kd in (np.linspace(0.0, kd_span, 9) if use_d else [0.0]))
    span = [0.5, 0.5 * kd_span]
    for _ in range(10):
        ki, kp, kd = best
        for a in np.linspace(-1, 1, 5):
            for b in (np.linspace(-1, 1, 5) if use_d else [0.0]):
                kp2, kd2 = kp * math.exp(a * span[0]), max(kd + b * span[1], 0.0)
                best = max(best, (ki_max(kp2, kd2), kp2, kd2))
        if best[1:] == (kp, kd):
            span = [x * 0.6 for x in span]
    ki, kp, kd = best
    while true_ms(plant, kp, ki, kd, tf, w_lo, w_hi, p, w) > ms_max:  # the refined peak decides
        ki *= 1 - 1e-6
    return ki, kp, kd


#: The PID brute force is a zoom search of ~330 bisections on 20 000 frequencies (9.3 s CPU at Ms 1.4):
#: both PID cases are -m slow. The default suite checks the PI's IE against the same brute force at
#: both bounds, the PID's IE optimum by the local search of test_no_better_feasible_point_near_a_reported_optimum
#: ("servo 5e-4, 500 Hz") and test_servo_class_is_reported_optimal, and the PID's IAE against brute_iae.
_GRID_IE = [pytest.param(c, m, marks=pytest.mark.slow) if c == "pid" else (c, m) for c, m in _GRID]


@pytest.mark.parametrize("controller_kind, ms_max", _GRID_IE)
def test_servo_ie_is_optimal_against_a_brute_force(controller_kind, ms_max):
    plant = servo()
    r = tune_pid(plant, objective="ie", controller=controller_kind, ms_max=ms_max)
    kp, ki, kd, tf = _pid(r)
    assert r.status == "optimal", r.status
    assert r.objective == pytest.approx(1.0 / ki, rel=1e-9)  # input step: int e = -1/ki
    ms = true_ms(plant, kp, ki, kd, tf, 1.0, 1e7)
    assert ms <= ms_max * (1 + 1e-9)
    assert ms >= ms_max * (1 - 1e-3)  # the bound is active at this optimum
    assert stable(plant, kp, ki, kd, tf)
    assert r.ms == pytest.approx(ms, rel=1e-6)
    ki_bf, _, _ = brute_ie(plant, ms_max, tf, controller_kind == "pid", kp, 1.0, 1e7)
    # Within 0.5 % of the brute force or better (the tuner's point is independently verified
    # stable and within the bound above; with PID the brute force stops up to 3 % short on the
    # ridge where two peaks of |S| are equal).
    assert ki >= ki_bf * (1 - 5e-3), (ki, ki_bf)
    if controller_kind == "pi":
        assert ki == pytest.approx(ki_bf, rel=5e-3)


def brute_iae(plant, ms_max, tf, use_d, g_ref, w_lo, w_hi, rng):
    """Smallest continuous IAE with Ms <= ms_max and a stable loop: 60 random points (seeded
    ``rng``) in +-30 % (log) around ``g_ref`` plus ``g_ref`` itself, then a shrinking compass
    search in log gains from the best; every value it keeps is a feasible, stable point's."""
    w = np.logspace(math.log10(w_lo), math.log10(w_hi), 20_000)
    p = _plant_response(plant, w)
    nv = 3 if use_d else 2

    def f(y):
        kp, ki = g_ref[0] * math.exp(y[0]), g_ref[1] * math.exp(y[1])
        kd = g_ref[2] * math.exp(y[2]) if use_d else 0.0
        # feasible AND stable (a loop can meet Ms on the grid and still be unstable)
        if true_ms(plant, kp, ki, kd, tf, w_lo, w_hi, p, w) > ms_max or not stable(plant, kp, ki, kd, tf):
            return math.inf
        return true_iae(plant, kp, ki, kd, tf)

    pts = [np.zeros(nv)] + [rng.uniform(-0.3, 0.3, nv) for _ in range(60)]
    vals = [f(y) for y in pts]
    y, v = pts[int(np.argmin(vals))], min(vals)
    step = 0.1
    while step > 2e-3:
        moved = False
        for k in range(nv):
            for sgn in (1, -1):
                y2 = y.copy()
                y2[k] += sgn * step
                v2 = f(y2)
                if v2 < v:
                    y, v, moved = y2, v2, True
        if not moved:
            step /= 2
    assert math.isfinite(v), "brute_iae: no feasible stable point"
    return v


#: The same split as ``_GRID_IE``: the PID at Ms 2.0 (the costliest case, ~23 s under load) is -m slow;
#: the default suite checks the PID's IAE against the brute force at Ms 1.4 and the PI at both bounds.
_GRID_IAE = [pytest.param(c, m, marks=pytest.mark.slow) if (c, m) == ("pid", 2.0) else (c, m) for c, m in _GRID]


@pytest.mark.parametrize("controller_kind, ms_max", _GRID_IAE)
def test_servo_iae_is_optimal_against_a_brute_force(controller_kind, ms_max):
    plant = servo()
    r = tune_pid(plant, objective="iae", controller=controller_kind, ms_max=ms_max)
    kp, ki, kd, tf = _pid(r)
    assert r.status == "optimal", r.status
    iae = true_iae(plant, kp, ki, kd, tf)
    assert r.objective == pytest.approx(iae, rel=1e-5)  # the continuous loop's IAE
    ms = true_ms(plant, kp, ki, kd, tf, 1.0, 1e7)
    assert ms <= ms_max * (1 + 1e-9)
    if r.stats["ms_bound_active"]:
        assert ms >= ms_max * (1 - 1e-3)
    best = brute_iae(plant, ms_max, tf, controller_kind == "pid", (kp, ki, kd if kd > 0 else kp * tf),
                     1.0, 1e7, np.random.default_rng(20))
    assert iae == pytest.approx(best, rel=5e-3)


# --------------------------------------------------------------------------------------------
# "optimal" is never reported where a search finds a better feasible point


def _lag_delay(tau):
    num, den = control.pade(1.0, 8)
    return control.tf(num, den) / (tau * s + 1)


SEARCH_CASES = [
    # (name, plant, controller, objective, ms_max, frequency range of the Ms search in rad/s)
    ("servo 2.2e-4", servo(), "pi", "ie", 1.4, (1.0, 1e7)),
    ("servo 1e-3 kg m^2, 1 ms", servo(1e-3, 1e-3), "pi", "iae", 1.4, (1.0, 1e7)),
    ("servo 5e-4, 500 Hz", servo(5e-4, 0.5e-3, 500.0), "pid", "ie", 2.0, (1.0, 1e7)),
    ("servo 2.2e-4 PID IAE", servo(), "pid", "iae", 1.6, (1.0, 1e7)),
    ("1/(s+1)^2", 1 / (s + 1) ** 2, "pid", "ie", 1.4, (1e-3, 1e4)),
    ("resonance", 1 / ((s + 1) * (s**2 / 100 + 0.004 * s + 1)), "pi", "ie", 1.4, (1e-3, 1e4)),
    ("e^-s/(1+s)", _lag_delay(1.0), "pi", "iae", 1.4, (1e-3, 1e4)),
    ("e^-s/(1+8s)", _lag_delay(8.0), "pid", "iae", 1.4, (1e-3, 1e4)),
]


@functools.lru_cache(maxsize=None)
def _search_tuning(name):
    """``tune_pid`` of the ``SEARCH_CASES`` case ``name`` (its plant, controller, objective and Ms
    bound), tuned once per module (results are frozen): the four servo cases are read by
    test_no_better_feasible_point_near_a_reported_optimum and test_servo_class_is_reported_optimal,
    which tuned them each."""
    _, plant, ctrl, obj, ms_max, _ = next(c for c in SEARCH_CASES if c[0] == name)
    return tune_pid(plant, objective=obj, controller=ctrl, ms_max=ms_max)


@pytest.mark.parametrize("case", SEARCH_CASES, ids=[c[0] for c in SEARCH_CASES])
def test_no_better_feasible_point_near_a_reported_optimum(case):
    _, plant, ctrl, obj, ms_max, (w_lo, w_hi) = case
    r = _search_tuning(case[0])
    kp, ki, kd, tf = _pid(r)
    w = np.logspace(math.log10(w_lo), math.log10(w_hi), 20_000)
    p = _plant_response(plant, w)

    def value(g):
        if true_ms(plant, *g, tf, w_lo, w_hi, p, w) > ms_max or not stable(plant, *g, tf):
            return math.inf
        return 1.0 / g[1] if obj == "ie" else true_iae(plant, *g, tf)

    g0 = np.array([kp, ki, kd])
    v0 = value(g0)
    assert math.isfinite(v0)
    assert r.objective == pytest.approx(v0, rel=1e-5)
    if not r.status.startswith("optimal"):
        return  # nothing claimed (the class plants must not land here: see below)
    free = [0, 1] + ([2] if ctrl == "pid" and kd > 0 else [])
    rng = np.random.default_rng(2020)
    trials = []
    for scale in (3e-2, 1e-2, 3e-3):
        for _ in range(12):
            y = np.zeros(3)
            y[free] = rng.uniform(-scale, scale, len(free))
            trials.append(y)
    for k in free:
        for d in (1e-2, -1e-2, 2e-3, -2e-3):
            y = np.zeros(3)
            y[k] = d
            trials.append(y)
            if k != 1:  # move ki with it to stay on an active Ms bound
                for dk in (1e-3, -1e-3, 5e-3, -5e-3):
                    y2 = y.copy()
                    y2[1] = dk
                    trials.append(y2)
    best = min(value(g0 * np.exp(y)) for y in trials)
    assert best >= v0 * (1 - 1e-3), f"{r.status}: a feasible point {100 * (1 - best / v0):.3f} % better"


@pytest.mark.parametrize("case", SEARCH_CASES[:4], ids=[c[0] for c in SEARCH_CASES[:4]])
def test_servo_class_is_reported_optimal(case):
    r = _search_tuning(case[0])
    assert r.status == "optimal"
    assert r.converged
    assert r.stats["first_order"]["ok"]
    assert r.stats["first_order"]["residual"] <= 2e-3


# --------------------------------------------------------------------------------------------
# section 4: the reported IAE is the continuous loop's


def _ivp_iae(plant, kp, ki, kd, tf):
    """IAE by scipy's Radau integrator on the closed loop of ``control.feedback`` (|e| as an
    extra state), to 40 times the slowest closed-loop time constant."""
    from scipy.integrate import solve_ivp

    sys = control.ss(control.feedback(plant, controller(kp, ki, kd, tf)))
    a, b, c = np.asarray(sys.A), np.asarray(sys.B)[:, 0], np.asarray(sys.C)[0]
    a, (t, _) = matrix_balance(a, permute=False, separate=True)
    b, c = b / t, c * t
    t_end = 40.0 / np.min(np.abs(np.linalg.eigvals(a).real))
    sol = solve_ivp(lambda _, x: np.concatenate([a @ x[:-1] + b, [abs(c @ x[:-1])]]), (0.0, t_end),
                    np.zeros(a.shape[0] + 1), method="Radau", rtol=1e-10, atol=1e-14)
    return float(sol.y[-1, -1])


@pytest.mark.parametrize("name, plant, ctrl", [
    ("e^-s/(1+s)", _lag_delay(1.0), "pi"),
    ("e^-s/(1+8s)", _lag_delay(8.0), "pi"),
    ("PID on 1/(s+1)^3", 1 / (s + 1) ** 3, "pid"),
])
def test_reported_iae_is_the_continuous_loops(name, plant, ctrl):
    import warnings

    r = tune_pid(plant, objective="iae", controller=ctrl, ms_max=1.4)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # Radau's finite-difference Jacobian
        ref = _ivp_iae(plant, *_pid(r))
    assert r.objective == pytest.approx(ref, rel=2e-5), (r.objective, ref, r.stats["objective_sampled"])
    # what the optimiser's sampled stand-in says is kept, and it is not what is reported
    assert r.stats["objective_sampled"] != r.objective


# --------------------------------------------------------------------------------------------
# hostile items 8, 16, 20: refused in one line naming the argument, before any work; or tuned


@pytest.mark.parametrize("plant, match", [
    (control.tf(1, np.poly(-np.ones(60))), r"order 60; expected at most MAX_ORDER = 30"),
    (control.ss(np.diag(-np.arange(1.0, 101.0)), np.ones((100, 1)), np.ones((1, 100)), 0), r"order 100; expected at most"),
    (control.ss(np.diag(-np.arange(1.0, 801.0)), np.ones((800, 1)), np.ones((1, 800)), 0), r"order 800; expected at most"),
    (control.tf(2.0, 1.0), r"plant = .* is a static gain"),
    (control.tf(0.0, [1.0, 1.0]), r"plant = .* is zero"),
    (control.tf([np.nan], [1.0, 1.0]), r"plant = .* non-finite \(nan/inf\) coefficients"),
    (control.tf([1.0], [1.0, np.inf]), r"plant = .* non-finite"),
    (1 / (s**2 + 1), r"undamped poles on the imaginary axis at \+-1 rad/s"),
    (None, r"plant = None; expected a python-control LTI"),
    ("1/(s+1)", r"plant = '1/\(s\+1\)'; expected a python-control LTI"),
])
def test_bad_plants_get_one_clear_line(plant, match):
    with pytest.raises(ValueError, match=match) as exc:
        tune_pid(plant)
    assert "\n" not in str(exc.value)


def test_high_order_plant_is_refused_before_any_work(monkeypatch):
    import prsa_ctrl.tuning.generic as generic

    def boom(*args, **kwargs):
        raise AssertionError("work started")

    monkeypatch.setattr(generic, "continuous_loop", boom)
    monkeypatch.setattr(generic, "_phase_frequency", boom)
    with pytest.raises(ValueError, match="MAX_ORDER"):
        tune_pid(control.ss(np.diag(-np.arange(1.0, 801.0)), np.ones((800, 1)), np.ones((1, 800)), 0))


def test_tune_actuator_names_a_missing_plant_or_scene(paper_plant):
    from prsa_ctrl import tune_actuator

    with pytest.raises(TypeError, match=r"plant = None; expected a prsa_ctrl Plant"):
        tune_actuator(None, None)
    with pytest.raises(TypeError, match=r"scene = 'x'; expected a prsa_ctrl Scene"):
        tune_actuator(paper_plant, "x")


P3 = 1 / (s + 1) ** 3
_REF = {}


def _scaled(k):
    """``k P3`` as a state space (a transfer function of gain 1e-200 trips scipy's tf2ss)."""
    a, b, c, d = control.ssdata(control.ss(P3))
    return control.ss(a, b, k * np.asarray(c), d)


def _reference(objective):
    if objective not in _REF:
        _REF[objective] = tune_pid(P3, objective=objective)
    return _REF[objective]


@settings(max_examples=12)
@given(exponent=st.sampled_from([-200, -120, -30, -12, -6, -3, 3, 6, 12, 30, 120, 200]),
       objective=st.sampled_from(["ie", "iae"]))
def test_plant_gain_scales_the_gains_inversely(exponent, objective):
    k = 10.0**exponent
    ref = _reference(objective)
    r = tune_pid(_scaled(k), objective=objective)
    assert r.status == "optimal"
    assert r.pid.kp * k == pytest.approx(ref.pid.kp, rel=1e-6)
    assert r.pid.ki * k == pytest.approx(ref.pid.ki, rel=1e-6)
    assert r.objective / k == pytest.approx(ref.objective, rel=1e-6)
    assert r.ms == pytest.approx(ref.ms, rel=1e-9)


def test_objective_beyond_double_precision_is_refused():
    with pytest.raises(ValueError, match=r"leave double precision"):
        tune_pid(_scaled(1e200), objective="ise")


def test_a_non_finite_objective_is_never_reported(monkeypatch):
    from prsa_ctrl.tuning.loops import LoopModel

    monkeypatch.setattr(LoopModel, "true_objective", lambda self, gains, kind: (math.nan, 0.0))
    with pytest.raises(ValueError, match="objective is not finite"):
        tune_pid(P3, objective="ie")


# ------------------------------------------------------------------------------------------------
# Fast companions of the slow Tf-optimised filter tests (tests/tuning/test_generic.py, each
# ~30-60 s because every Tf point is a full tuning): the search over the measurement filter's time
# constant (``generic.optimal_filter``: log scan, bounded Brent search, its own first-order check,
# the end-of-range warning, infeasible points) run on stand-in tunings whose objective is a known
# function of Tf, so that the answer is known exactly.
# ------------------------------------------------------------------------------------------------

def _solver(f, calls, bad=lambda t: False, unconverged=lambda t: False):
    """``solve(Tf, horizon)`` whose result has the objective ``f(Tf)`` (ValueError where ``bad``)."""
    def solve(t, hor):
        calls.append(t)
        if bad(t):
            raise ValueError("infeasible")
        status = "not converged: stand-in" if unconverged(t) else "optimal"
        return TuningResult(pid=PID(1.0, 1.0), objective=f(t), kind="ie", per_loop=[f(t)], margins=[],
                            stats={"tf_seen": t}, status=status), hor
    return solve


T_REF = 1.0
LO = T_REF * 10.0 ** -FILTER_DECADES


def test_interior_minimum_is_found_and_proven():
    t_opt = 0.0123
    calls = []
    res, hor = optimal_filter(_solver(lambda t: 1.0 + (math.log(t / t_opt)) ** 2, calls), 7.0, T_REF)
    fs = res.stats["filter_search"]
    assert hor == 7.0
    assert res.converged
    assert fs["first_order_ok"]
    assert not fs["at_bound"]
    # Optimal for the problem searched, which the status names (issue 34: never "optimal" alone).
    assert res.status == f"optimal (over Tf in [{LO:.4g}, {T_REF:.4g}] s, the filter's search range)"
    assert math.log(fs["tf_s"] / t_opt) == pytest.approx(0.0, abs=3e-3)  # Brent's 2e-3 in log Tf
    assert res.stats["tf_seen"] == fs["tf_s"]  # the result returned is the tuning at that Tf
    assert fs["evaluations"] == len(calls) <= 7 + 20 + 2  # bounded before it starts
    assert fs["range_s"] == pytest.approx([LO, T_REF], rel=1e-12)


def test_kink_minimum_counts_as_a_minimum():
    """Where the active peak changes, the objective has a kink: no descent direction either way."""
    t_k = 0.002
    res, _ = optimal_filter(_solver(lambda t: 1.0 + 0.1 * abs(math.log(t / t_k)), []), 1.0, T_REF)
    fs = res.stats["filter_search"]
    assert fs["first_order_ok"]
    assert res.status.startswith("optimal (over Tf in [")
    assert math.log(fs["tf_s"] / t_k) == pytest.approx(0.0, abs=3e-3)


def test_a_filter_that_only_costs_ends_at_the_small_end_with_a_warning():
    res, _ = optimal_filter(_solver(lambda t: 1.0 + t, []), 1.0, T_REF)
    fs = res.stats["filter_search"]
    assert fs["at_bound"]
    assert fs["tf_s"] == pytest.approx(LO, rel=1e-9)
    # The end of the range is where the objective is least: optimal over the range, and the
    # status says that it keeps improving beyond its lower end.
    assert res.status == (f"optimal (over Tf in [{LO:.4g}, {T_REF:.4g}] s, the filter's search range (at its lower "
                          "end: the objective keeps improving beyond it))")
    assert any("end of its search range" in w for w in res.warnings)


def test_ie_improving_with_tf_names_the_range_and_points_to_iae():
    """IE with a free filter can improve without end as Tf grows (issue 34: ki 0.630 reported
    "optimal" on e^(-s)/(s+1) while ki 1.051 is feasible at Tf = 71 s): the result is the best
    over the range, its status names the range and its upper end, and a warning points to IAE."""
    res, _ = optimal_filter(_solver(lambda t: 1.0 / (1.0 + t), []), 1.0, T_REF)
    fs = res.stats["filter_search"]
    assert fs["at_bound"]
    assert fs["tf_s"] == pytest.approx(T_REF, rel=1e-9)
    assert "over Tf in [" in res.status
    assert "upper end" in res.status
    assert res.converged
    assert any("IAE gives a bounded problem" in w for w in res.warnings)
    assert "search range" in fs["problem"]


def test_infeasible_and_unconverged_points_count_as_infinite():
    # Only Tf in [1e-3, 1e-1] is feasible; below 3e-3 the tunings are not proven optimal.
    calls = []
    solve = _solver(lambda t: 1.0 + (math.log(t / 0.01)) ** 2, calls, bad=lambda t: not 1e-3 <= t <= 1e-1,
                    unconverged=lambda t: t < 3e-3)
    res, _ = optimal_filter(solve, 1.0, T_REF)
    fs = res.stats["filter_search"]
    assert res.converged
    assert math.log(fs["tf_s"] / 0.01) == pytest.approx(0.0, abs=3e-3)


def test_no_feasible_filter_is_one_value_error():
    with pytest.raises(ValueError, match="no filter time constant"):
        optimal_filter(_solver(lambda t: 1.0, [], bad=lambda t: True), 1.0, T_REF)


def test_a_remaining_descent_is_reported_not_optimal():
    """A narrow dip just beside the point the search settled on (which neither the scan nor the
    bounded search sampled) is caught by the one-sided slope check (steps of 0.02 in log Tf):
    the result is flagged, not called optimal."""
    smooth = lambda t: 1.0 + (math.log(t / 0.05)) ** 2  # noqa: E731
    calls = []
    first, _ = optimal_filter(_solver(smooth, calls), 1.0, T_REF)
    x_best = math.log(first.stats["filter_search"]["tf_s"])
    centre, half = x_best + 0.02, 0.004
    assert all(abs(math.log(t) - centre) > half for t in calls[:-2])  # the search itself never went there

    def dipped(t):
        return smooth(t) - 0.01 * max(0.0, 1.0 - abs(math.log(t) - centre) / half)

    res, _ = optimal_filter(_solver(dipped, []), 1.0, T_REF)
    fs = res.stats["filter_search"]
    assert fs["tf_s"] == pytest.approx(math.exp(x_best), rel=1e-12)  # same path to the same point
    assert fs["slope_up"] < 0
    assert not fs["first_order_ok"]
    assert res.status.startswith("not proven optimal")
    assert not res.converged
    assert any("not proven optimal" in w for w in res.warnings)


def test_a_very_fast_filter_tunes_without_numerical_noise():
    """Tf = 1e-4 s (the small end of the search range on 1/(s+1)^3): the filter's states are ~1e-90
    after one step, which made scipy's balancing warn "invalid value encountered in cast" (a
    note in every `prsa-pid --filter-order` run). No warning now (warnings are errors here), and
    the result is verified as before."""
    import warnings

    import control

    from prsa_ctrl.tuning import tune_pid

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = tune_pid(control.tf([1], [1, 3, 3, 1]), controller="pid", filter_order=2, filter_tf=1e-4, mks_max=5.0)
    assert r.status == "optimal"
    assert r.filter["tf_s"] == 1e-4
    assert r.ms <= 1.4
    assert r.mks <= 5.0


def test_nothing_stabilising_at_any_tf_does_not_ask_to_relax():
    msg = "no stabilising PI gains found on the scan, whatever the bounds (Ms <= 1.4): relaxing them does not help"

    def solve(t, hor):
        raise ValueError(msg)

    with pytest.raises(ValueError) as err:
        optimal_filter(solve, 1.0, T_REF)
    assert str(err.value).startswith(msg)
    assert "relax the constraints" not in str(err.value)


# ------------------------------------------------------------------------------------------------
# Issue 25: exact plant delays in tune_pid (delay=L): e^{-jwL} in every frequency response, the
# IAE of the loop with the exact delay, margins on the exact delay; against a 6th-order Pade model
# of the same plant and independent references (tests/independent_tuner.py).
# ------------------------------------------------------------------------------------------------

P0 = control.tf([1.0], [1.0, 1.0])


def _pade6():
    num, den = control.pade(1.0, 6)
    return P0 * control.tf(num, den)


@functools.lru_cache(maxsize=2)
def _exact_delay_tuning(objective):
    """``tune_pid(P0, objective=objective, delay=1.0, ms_max=1.4)`` (e^-s/(1 + s) with its exact
    delay, at the default Ms bound), tuned once per objective for the tests that read it (a frozen
    TuningResult): the IAE tuning was made three times, the IE tuning twice."""
    return tune_pid(P0, objective=objective, delay=1.0, ms_max=1.4)


@pytest.mark.parametrize("objective", ["ie", "iae"])
def test_exact_delay_agrees_with_pade6_model(objective):
    """e^-s/(1 + s): the exact delay and the 6th-order Pade model agree within 1e-4 on Ms and ki
    (a 6th-order Pade's phase error is below 1e-9 rad up to 2 rad/s, where the design lives)."""
    r = _exact_delay_tuning(objective)  # the default Ms bound, 1.4, as the Pade model's below
    rp = tune_pid(_pade6(), objective=objective)
    assert r.status == "optimal"
    assert rp.status == "optimal"
    assert abs(r.ms - rp.ms) <= 1e-4
    assert abs(r.pid.ki - rp.pid.ki) <= 1e-4 * rp.pid.ki


def test_ie_optimum_matches_brute_force_with_exact_delay():
    r = _exact_delay_tuning("ie")  # Ms <= 1.4
    kp, ki = ref.best_pi([1.0], [1.0, 1.0], 1.4, delay=1.0, kp_hi=2.0)
    assert r.pid.ki == pytest.approx(ki, rel=1e-4)
    pk = ref.peaks(ref.loop_parts([1.0], [1.0, 1.0], 1.0), ref.controller(r.pid.kp, r.pid.ki))
    assert r.ms == pytest.approx(pk[0], rel=1e-6)


def test_reported_iae_is_that_of_the_exact_delay():
    """The reported IAE is the exact delayed loop's (method-of-steps reference to 1e-5), not the
    Pade stand-in's (which is 0.35 % higher at these gains)."""
    r = _exact_delay_tuning("iae")
    exact = ref.delayed_pi_iae(r.pid.kp, r.pid.ki, 1.0, 1.0, 80.0)
    assert r.objective == pytest.approx(exact, rel=2e-5)
    assert r.stats["objective_pade"] > r.objective * 1.001
    assert r.stats["delay_s"] == 1.0


def test_margins_on_the_exact_delay():
    r = _exact_delay_tuning("iae")
    pm, gm = ref.margins_exact([1.0], [1.0, 1.0], r.pid.kp, r.pid.ki, 1.0)
    m = r.margins[0]
    assert m.pm_deg == pytest.approx(pm, abs=0.01)
    assert m.gm_db == pytest.approx(gm, abs=0.01)


def test_delayed_iae_converges_at_second_order():
    """The delayed simulation's error falls 4x per halving of its step (first-order hold of the
    delayed state, trapezoid rule): the Richardson estimate it reports is justified."""
    lp = continuous_loop(P0, tf=0.07, horizon=100.0, n_steps=2000, delay=1.0)
    g = np.array([0.365, 0.373, 0.0])
    v = [lp.delayed._value(g, "iae", m)[0] for m in (16, 32, 64, 128)]
    d = np.diff(v)
    assert np.all(np.abs(d[1:] / d[:-1] - 0.25) < 0.02)


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf"), "1"])
def test_bad_delay_is_refused(bad):
    with pytest.raises(ValueError, match="delay"):
        tune_pid(P0, delay=bad)


@pytest.mark.parametrize("bad", [0, 11, 2.5, True])
def test_bad_delay_order_is_refused(bad):
    with pytest.raises(ValueError, match="delay_order"):
        tune_pid(P0, delay=1.0, delay_order=bad)


# ------------------------------------------------------------------------------------------------
# Issue 25: the measurement filter on the whole controller, C(s) F(s) with F = 1/(Tf s + 1) or
# 1/(Tf^2 s^2/2 + Tf s + 1) (Hast, Astrom, Bernhardsson, Boyd, "PID design by convex-concave
# optimization", ECC 2013; Soltesz, Grimholt, Skogestad; JuliaSim AutoTuningProblem2), with the
# ideal PID kp + ki/s + kd s, IE objective (max ki) under Ms, Mt, Mks bounds, against an independent
# solve of the discretised semi-infinite problem by sequential quadratic programming
# (tests/independent_tuner.py ``best_filtered_pid``: only a start that reports success, is
# feasible on an independent dense grid and gives a stable loop is kept; it raises otherwise).
# ------------------------------------------------------------------------------------------------

STARTS = [(kp, ki, kd, t) for kp in (0.5, 1.5) for ki in (0.3, 1.0) for kd in (0.5, 1.5) for t in (0.05, 0.3)]
# (den, filter order, Ms, Mt, Mks, Tf near the optimum, s): three plants, both orders.
CASES = [
    ([1, 3, 3, 1], 1, 1.4, None, 3.0, 0.74),
    ([1, 3, 3, 1], 2, 1.4, None, 3.0, 0.47),
    ([1, 2, 1], 2, 1.4, None, 5.0, 0.34),
    ([0.2, 1.2, 1], 2, 1.4, 1.3, 5.0, 0.076),
]
IDS = [f"{c[0]}-F{c[1]}" for c in CASES]


def _check_true_peaks(r, den, order, ms, mt, mks):
    """Reported Ms/Mt/Mks are the true peaks of the FILTERED loop (independent dense grid)."""
    t = r.filter["tf_s"]
    pk = ref.peaks(ref.loop_parts([1], den), ref.controller(r.pid.kp, r.pid.ki, r.pid.kd, 0.0, (order, t)))
    assert r.ms == pytest.approx(pk[0], rel=1e-4)
    assert r.mt == pytest.approx(pk[1], rel=1e-4)
    assert r.mks == pytest.approx(pk[2], rel=1e-4)
    assert r.ms <= ms
    assert mt is None or r.mt <= mt
    assert r.mks <= mks
    assert r.mks >= mks * (1 - 1e-3)  # the noise bound is what limits the design


@pytest.mark.parametrize("den, order, ms, mt, mks, t", CASES, ids=IDS)
def test_fixed_filter_matches_reference(den, order, ms, mt, mks, t):
    r = tune_pid(control.tf([1], den), objective="ie", controller="pid", ideal=True, ms_max=ms, mt_max=mt,
                 mks_max=mks, filter_order=order, filter_tf=t)
    assert r.status == "optimal"
    assert r.filter == {"order": order, "tf_s": t, "derivative": "ideal"}
    _check_true_peaks(r, den, order, ms, mt, mks)
    import math

    kp, ki, kd, _ = ref.best_filtered_pid([1], den, order, ms, mt, mks, STARTS, log_tf=math.log(t))
    assert r.objective == pytest.approx(1.0 / ki, rel=5e-3)
    assert r.pid.ki == pytest.approx(ki, rel=1e-3)


@pytest.mark.slow
@pytest.mark.parametrize("den, order, ms, mt, mks, t", CASES, ids=IDS)
def test_optimised_filter_matches_reference(den, order, ms, mt, mks, t):
    """Tf a decision variable (~40 s each): the tuner's (gains, Tf) against the reference with
    Tf free as well."""
    r = tune_pid(control.tf([1], den), objective="ie", controller="pid", ideal=True, ms_max=ms, mt_max=mt,
                 mks_max=mks, filter_order=order)
    assert r.converged
    assert r.status.startswith("optimal (over Tf in [")
    assert r.stats["filter_search"]["first_order_ok"]
    assert not r.stats["filter_search"]["at_bound"]
    _check_true_peaks(r, den, order, ms, mt, mks)
    kp, ki, kd, t_ref = ref.best_filtered_pid([1], den, order, ms, mt, mks, STARTS)
    assert r.objective == pytest.approx(1.0 / ki, rel=5e-3)
    assert r.filter["tf_s"] == pytest.approx(t_ref, rel=0.05)


@pytest.mark.slow
def test_filter_that_only_costs_goes_to_the_end_of_its_range():
    """PI on 1/(4s + 1) under Ms = Mt = 1.2, Mks = 10: the Mks peak is mid-frequency, a filter
    only adds phase lag, so the optimal Tf is at the small end of the range, and the objective is
    no better than without a filter (ki 13.739)."""
    r = tune_pid(control.tf([1], [4, 1]), objective="ie", ms_max=1.2, mt_max=1.2, mks_max=10.0, filter_order=1)
    fs = r.stats["filter_search"]
    # Near the small end the objective is flat to the inner solves' resolution (~1e-5): within
    # the lowest tenth of a decade of the range, its value that of no filter within 1e-3.
    assert r.filter["tf_s"] <= fs["range_s"][0] * 10 ** 0.1 * (1 + 1e-9)
    assert fs["at_bound"] == any("end of its search range" in w for w in r.warnings)
    assert 13.7392 * (1 - 1e-3) <= r.pid.ki <= 13.7392 * (1 + 1e-4)


@pytest.mark.parametrize("kw, match", [
    (dict(filter_order=3), "filter_order"),
    (dict(filter_order=True), "filter_order"),
    (dict(filter_order=1, filter_tf=0.0), "filter_tf"),
    (dict(filter_order=1, filter_tf=float("nan")), "filter_tf"),
    (dict(filter_tf=0.1), "filter_tf"),
    (dict(ideal=True), "ideal"),
    (dict(ideal="yes", controller="pid"), "ideal"),
    (dict(ideal=True, controller="pid", mks_max=3.0), "mks_max"),
])
def test_bad_structure_arguments_are_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        tune_pid(control.tf([1], [1, 3, 3, 1]), **kw)


def test_ideal_derivative_needs_relative_degree_two_without_filter():
    with pytest.raises(ValueError, match="relative degree"):
        tune_pid(control.tf([1], [4, 1]), controller="pid", ideal=True)


# ------------------------------------------------------------------------------------------------
# Issue 25: the ideal PID kp + ki/s + kd s (no derivative filter), IE objective (max ki) under
# Ms (and Mt), the MIGO problem of Panagopoulos, Astrom and Hagglund ("Design of PID controllers
# based on constrained optimization", IEE Proc. CTA 149(1), 2002). No published table with
# numbers was at hand to cite (see the issue-25 report), so the reference here is an independent
# solve of the discretised problem by sequential quadratic programming from several starts
# (tests/independent_tuner.py ``best_ideal_pid``). The reference checks itself (issue 31): it keeps
# only a start that reports success, is feasible on an independent dense grid and gives a stable
# loop, and raises instead of returning anything else (tests/test_independent_tuner.py breaks it
# on purpose).
# ------------------------------------------------------------------------------------------------

# Four starts: the reference keeps the best verified one, so one start that fails on some
# processor (issue 31: "Inequality constraints incompatible" on an AMD EPYC) leaves three.
IDEAL_STARTS = [(0.5, 0.3, 0.5), (1.5, 0.8, 1.5), (1.0, 0.5, 1.0), (2.0, 1.0, 2.0)]


@pytest.mark.parametrize("den, ms, mt", [([1, 3, 3, 1], 1.4, None), ([1, 4, 6, 4, 1], 1.4, 1.4)])
def test_ideal_pid_matches_reference(den, ms, mt):
    r = tune_pid(control.tf([1], den), objective="ie", controller="pid", ideal=True, ms_max=ms, mt_max=mt)
    assert r.status == "optimal"
    assert r.filter == {"order": 0, "tf_s": None, "derivative": "ideal"}
    # True peaks of the ideal law (independent grid), within the bounds.
    pk = ref.peaks(ref.loop_parts([1], den), ref.controller(r.pid.kp, r.pid.ki, r.pid.kd))
    # (the reference grid's top is within 1e-4 of the polished peak, and never above it)
    assert r.ms == pytest.approx(pk[0], rel=1e-4)
    assert r.mt == pytest.approx(pk[1], rel=1e-4)
    assert r.ms >= pk[0] * (1 - 1e-12)
    assert r.mt >= pk[1] * (1 - 1e-12)
    assert r.ms <= ms
    assert mt is None or r.mt <= mt
    # |C S| grows as kd omega: an unfiltered ideal PID has no finite noise sensitivity.
    assert r.mks == math.inf
    assert any("ideal derivative" in w for w in r.warnings)
    (kp, ki, kd), _ = ref.best_ideal_pid([1], den, ms, mt, IDEAL_STARTS)
    assert r.objective == pytest.approx(1.0 / ki, rel=5e-3)
    assert r.pid.ki == pytest.approx(ki, rel=1e-3)


# ------------------------------------------------------------------------------------------------
# Issue 25: the Mks bound (true peak of |C S|) of the generic tuner against an independent brute
# force (tests/independent_tuner.py, which does not call prsa_ctrl).
# ------------------------------------------------------------------------------------------------

# (num, den, Ms, Mt, Mks, kp search range of the brute force); Mks active in every case.
MKS_CASES = [
    ([1], [4, 1], 1.2, 1.2, 10.0, 20.0),  # the issue's case: ki 13.739 by brute force
    ([1], [1, 3, 3, 1], 1.4, None, 1.05, 5.0),
    ([1], [1, 2, 1], 1.4, None, 2.0, 10.0),
    ([1], [0.2, 1.2, 1], 1.4, 1.3, 3.0, 20.0),
    ([-0.5, 1], [1, 2, 1], 1.6, None, 1.2, 5.0),  # right-half-plane zero
    ([1], [1, 1, 0], 1.4, None, 0.5, 10.0),  # integrator
]


@functools.lru_cache(maxsize=None)
def _best_pi_once(num, den, ms, mt, mks, kp_hi):
    """``ref.best_pi`` once per problem in the module (a deterministic function of it; 1.8 s of CPU
    on the issue's case, which two tests read). ``num``, ``den``: tuples, passed on as lists."""
    return ref.best_pi(list(num), list(den), ms, mt, mks, kp_hi=kp_hi)


def test_issue_case_reference_value():
    """The brute force alone reproduces the issue's number (ki = 13.739)."""
    kp, ki = _best_pi_once((1,), (4, 1), 1.2, 1.2, 10.0, 20.0)
    assert ki == pytest.approx(13.739, abs=5e-4)
    ms, mt, mks = ref.peaks(ref.loop_parts([1], [4, 1]), ref.controller(kp, ki))
    assert mt <= 1.2 + 1e-9
    assert mks <= 10.0 + 1e-9


@pytest.mark.parametrize("num, den, ms, mt, mks, kp_hi", MKS_CASES, ids=[str(c[:2]) for c in MKS_CASES])
def test_mks_bound_matches_brute_force(num, den, ms, mt, mks, kp_hi):
    r = tune_pid(control.tf(num, den), objective="ie", ms_max=ms, mt_max=mt, mks_max=mks)
    assert r.status == "optimal"
    # The reported Mks is the true peak (independent grid) and within 0.1 % of the bound.
    p = ref.loop_parts(num, den)
    ms_r, mt_r, mks_r = ref.peaks(p, ref.controller(r.pid.kp, r.pid.ki))
    assert r.mks == pytest.approx(mks_r, rel=1e-4)
    assert mks * (1 - 1e-3) <= r.mks <= mks
    assert r.ms <= ms
    assert ms_r <= ms * (1 + 1e-6)
    if mt is not None:
        assert r.mt <= mt
        assert mt_r <= mt * (1 + 1e-6)
    # The objective (IE = 1/ki) within 0.5 % of the brute-force optimum (and not better than it
    # beyond the brute force's own resolution).
    _, ki_bf = _best_pi_once(tuple(num), tuple(den), ms, mt, mks, kp_hi)
    assert r.objective == pytest.approx(1.0 / ki_bf, rel=5e-3)
    assert r.pid.ki <= ki_bf * (1 + 1e-4)


def test_max_noise_gain_is_kept_and_bounds_kp_not_mks():
    """``max_noise_gain`` still bounds kp + kd/tf (unchanged); on the issue's case its true Mks
    is 10.28, above the bound: the reason for ``mks_max``."""
    r = tune_pid(control.tf([1], [4, 1]), objective="ie", ms_max=1.2, mt_max=1.2, max_noise_gain=10.0)
    assert r.pid.kp + r.pid.kd / r.pid.tf <= 10.0 * (1 + 1e-9)
    assert r.mks == pytest.approx(10.28, abs=0.01)


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf"), "10", True])
def test_bad_mks_max_is_refused(bad):
    with pytest.raises(ValueError, match="mks_max"):
        tune_pid(control.tf([1], [4, 1]), mks_max=bad)


# ------------------------------------------------------------------------------------------------
# Issue 25, the ideal PID ``kp + ki/s + kd s`` (``tune_pid(..., controller="pid", ideal=True)``),
# IE objective (max ki) under Ms (and Mt), the design of Panagopoulos, Astrom and Hagglund's MIGO
# family (IEE Proc. CTA 149(1), 2002).
#
# No published ideal-PID case with its plant, bounds and printed gains could be found to
# reproduce (the search, and what came closest, is in docs/guides/generic-tuner.md). This file
# holds the next-best evidence, on plants not used elsewhere (a non-minimum-phase zero, an
# integrator with Mt active, a lightly damped pair, and Ms = 1.6 alone on 1/(s+1)^3, whose
# optimum has a sharp peak the tuner used to stop short of):
#
# * the TRUE Ms and Mt of the tuner's gains, on a dense grid refined near each peak;
# * a brute force written here with numpy and scipy only. At fixed (ki, kd) each frequency's
#   bound is a quadratic inequality in kp, so the allowed kp form exact windows (the complement
#   of a union of intervals); a (ki, kd) is feasible where a window's midpoint gives a stable
#   closed loop (characteristic polynomial). The largest feasible ki is found for every kd of a
#   grid (a scan, then bisection), then refined in kd by a bounded scalar search. Its bounds
#   hold on a finite frequency grid only, a relaxation: its optimum may sit a little ABOVE the
#   true one, never below it (where the search is global).
# ------------------------------------------------------------------------------------------------

#: The brute force's frequencies (rad/s): six decades around the plants' dynamics.
W_BF = np.logspace(-3, 3, 8000)
#: The ki scan of the brute force before the bisection.
KI_SCAN = np.logspace(-3, 2.5, 45)


def _published_loop(num, den, kp, ki, kd, w):
    s = 1j * np.asarray(w, float)
    return np.polyval(num, s) / np.polyval(den, s) * (kp + ki / s + kd * s)


def _true_peaks(num, den, kp, ki, kd):
    """(Ms, Mt) of the ideal-PID loop: a 200001-point log grid over 1e-4..1e4 rad/s, each peak
    then located by a bounded scalar search in log(omega) between its grid neighbours."""
    w = np.logspace(-4, 4, 200_001)
    out = []
    for f in (lambda L: 1 / (1 + L), lambda L: L / (1 + L)):
        mag = np.abs(f(_published_loop(num, den, kp, ki, kd, w)))
        i = int(np.argmax(mag))
        lo, hi = math.log(w[max(i - 2, 0)]), math.log(w[min(i + 2, w.size - 1)])
        r = minimize_scalar(lambda x: -abs(f(_published_loop(num, den, kp, ki, kd, [math.exp(x)])[0])),
                            bounds=(lo, hi), method="bounded", options={"xatol": 1e-12})
        assert r.success, r.message  # (the grid's value is kept when the refinement finds less)
        out.append(max(float(mag[i]), float(-r.fun)))
    return tuple(out)


def _kp_windows(p, ki, kd, ms, mt, kp_hi):
    """The kp in (0, kp_hi] meeting the bounds on W_BF at (ki, kd), as intervals. With
    ``L = kp P + c``, ``c = P (ki/s + kd s)``: ``|1 + L|^2 >= 1/Ms^2`` and ``(Mt^2 - 1) |L|^2 +
    2 Mt^2 Re L + Mt^2 >= 0`` (i.e. ``|L| <= Mt |1 + L|``) are quadratics in kp with a positive
    leading coefficient, each forbidding the interval between its real roots."""
    s = 1j * W_BF
    c = p * (ki / s + kd * s)
    quads = [(np.abs(p) ** 2, 2 * np.real((1 + c) * np.conj(p)), np.abs(1 + c) ** 2 - ms**-2)]
    if mt is not None:
        m2 = mt * mt
        quads.append(((m2 - 1) * np.abs(p) ** 2, 2 * (m2 - 1) * np.real(c * np.conj(p)) + 2 * m2 * np.real(p),
                      (m2 - 1) * np.abs(c) ** 2 + 2 * m2 * np.real(c) + m2))
    lo, hi = [], []
    for a, b, k in quads:
        d = b * b - 4 * a * k
        m = d > 0
        r = np.sqrt(d[m])
        lo.append((-b[m] - r) / (2 * a[m]))
        hi.append((-b[m] + r) / (2 * a[m]))
    lo, hi = np.concatenate(lo), np.concatenate(hi)
    order = np.argsort(lo)
    reach = np.maximum.accumulate(hi[order])  # the union's right edge so far
    g_lo = np.maximum(np.concatenate([[0.0], reach]), 0.0)
    g_hi = np.minimum(np.concatenate([lo[order], [kp_hi]]), kp_hi)
    keep = g_hi > g_lo
    return list(zip(g_lo[keep], g_hi[keep]))


def _published_feasible(num, den, p, ki, kd, ms, mt, kp_hi):
    return any(ref.stable(num, den, 0.5 * (a + b), ki, kd) for a, b in _kp_windows(p, ki, kd, ms, mt, kp_hi)[:20])


def _published_max_ki(num, den, p, kd, ms, mt, kp_hi):
    """The largest feasible ki at kd: the top feasible point of KI_SCAN, then 36 bisections in
    log ki towards the next scan point; 0 where no scanned ki is feasible."""
    ok = [_published_feasible(num, den, p, k, kd, ms, mt, kp_hi) for k in KI_SCAN]
    if not any(ok):
        return 0.0
    j = max(i for i, v in enumerate(ok) if v)
    assert j < KI_SCAN.size - 1, "the ki scan is too short for this plant"
    lo, hi = KI_SCAN[j], KI_SCAN[j + 1]
    for _ in range(36):
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if _published_feasible(num, den, p, mid, kd, ms, mt, kp_hi) else (lo, mid)
    return lo


def _brute_force(num, den, ms, mt, kp_hi, kd_hi, n=24):
    """(best ki on the kd grid, (ki, kd) refined, the refinement's kd bracket)."""
    p = np.polyval(num, 1j * W_BF) / np.polyval(den, 1j * W_BF)
    kds = np.linspace(0.0, kd_hi, n + 1)
    vals = [_published_max_ki(num, den, p, kd, ms, mt, kp_hi) for kd in kds]
    i = int(np.argmax(vals))
    bracket = (kds[max(i - 1, 0)], kds[min(i + 1, n)])
    r = minimize_scalar(lambda kd: -_published_max_ki(num, den, p, kd, ms, mt, kp_hi), bounds=bracket, method="bounded",
                        options={"xatol": 1e-7 * kd_hi})
    assert r.success, r.message
    # Every value is a verified-feasible ki (_published_max_ki bisects on the feasibility test); the
    # refinement is kept only where it is no worse than the grid's best.
    refined = (float(-r.fun), float(r.x)) if -r.fun >= vals[i] else (float(vals[i]), float(kds[i]))
    return vals[i], refined, bracket


# (num, den, Ms bound, Mt bound, the brute force's box: kp in (0, kp_hi], kd in [0, kd_hi]), the
# box set by hand, wide enough that the optimum lies well inside it.
PUBLISHED_CASES = [
    pytest.param([-0.5, 1.0], [1.0, 3.0, 3.0, 1.0], 1.4, None, 3.0, 3.0, id="nmp-zero"),
    pytest.param([1.0], [1.0, 2.0, 1.0, 0.0], 1.4, 1.3, 3.0, 5.0, id="integrator-Mt"),
    pytest.param([1.0], [1.0, 1.4, 1.4, 1.0], 1.4, None, 2.0, 3.0, id="light-damping"),
    # Ms alone on 1/(s+1)^3: the optimum has closed-loop damping ~0.1 (Mt ~ 2.35) and a sharp Ms
    # peak that moves with the gains. With 12 extra NLP frequencies (settings.SLOTS) every ipopt
    # run ran out of them and the tuner returned a scan point, ki = 5.84, "not converged"; the
    # optimum is ki = 15.53.
    pytest.param([1.0], [1.0, 3.0, 3.0, 1.0], 1.6, None, 10.0, 12.0, id="ms1.6-sharp-peak"),
]


@pytest.mark.parametrize("num, den, ms, mt, kp_hi, kd_hi", PUBLISHED_CASES)
def test_ideal_pid_against_brute_force(num, den, ms, mt, kp_hi, kd_hi):
    r = tune_pid(control.tf(num, den), objective="ie", controller="pid", ideal=True, ms_max=ms, mt_max=mt)
    assert r.status == "optimal"
    assert r.filter == {"order": 0, "tf_s": None, "derivative": "ideal"}
    kp, ki, kd = r.pid.kp, r.pid.ki, r.pid.kd
    # The reported peaks are the true peaks of the ideal law, and within the bounds.
    t_ms, t_mt = _true_peaks(num, den, kp, ki, kd)
    assert r.ms == pytest.approx(t_ms, rel=1e-6)
    assert r.mt == pytest.approx(t_mt, rel=1e-6)
    assert t_ms <= ms * (1 + 1e-9)
    assert mt is None or t_mt <= mt * (1 + 1e-9)
    assert ref.stable(num, den, kp, ki, kd)
    assert r.objective == pytest.approx(1.0 / ki, rel=1e-12)  # IE of a unit load step: 1/ki
    assert 0 < kp < kp_hi
    assert 0 < kd < kd_hi
    # The brute force: its kd grid never beats the tuner by more than its frequency grid's
    # slack, and refined it lands on the tuner's optimum, from above (a relaxation) by at most
    # 3e-4 (measured: 2e-5 to 6e-5), at the same kd (within 1e-2; measured up to 2.7e-3).
    grid_ki, (bki, bkd), bracket = _brute_force(num, den, ms, mt, kp_hi, kd_hi)
    assert grid_ki <= bki
    assert 0.9 * ki <= grid_ki
    assert ki <= bki * (1 + 1e-6)
    assert bki <= ki * (1 + 3e-4)
    assert bkd == pytest.approx(kd, rel=1e-2)  # ki is flat in kd at the top: kd is known less well
    assert bracket[0] < bkd < bracket[1]


# ------------------------------------------------------------------------------------------------

P3_TF = control.tf([1.0], [1.0, 3.0, 3.0, 1.0])
MATLAB_PI = (1.14, 0.454, 0.0)  # pidtune(1/(s+1)^3, 'pi') as published


def _ms_dense(plant, pid):
    w = np.logspace(-4, 4, 40000)
    C = control.tf([pid.kp, pid.ki], [1.0, 0.0])
    L = np.asarray(control.frequency_response(plant * C, w).complex).ravel()
    return float(np.max(np.abs(1 / (1 + L))))


def test_beats_matlab_pidtune_at_the_same_ms():
    loop = continuous_loop(control.ss(P3_TF), tf=0.1, horizon=40.0, n_steps=2000)
    ms_matlab = loop.margins(MATLAB_PI).ms
    ie_matlab = loop.objective(MATLAB_PI, "ie")
    assert ms_matlab == pytest.approx(1.63, abs=0.01)
    assert ie_matlab == pytest.approx(1 / 0.454, rel=1e-3)  # IE = 1/ki for a unit input step
    res = tune_pid(P3_TF, objective="ie", ms_max=ms_matlab, n_steps=2000)
    assert res.ms <= ms_matlab
    assert _ms_dense(P3_TF, res.pid) <= ms_matlab * (1 + 1e-3)
    assert res.objective < ie_matlab
    assert res.objective == pytest.approx(1 / res.pid.ki, rel=1e-9)  # IE to infinity, exact
    assert res.stats["status"] == "Solve_Succeeded"
    assert res.status == "optimal"
    assert res.converged
    assert not res.warnings
    assert res.ms == pytest.approx(_ms_dense(P3_TF, res.pid), rel=1e-4)  # the reported Ms is the true one


def test_pid_improves_on_pi_at_equal_ms():
    pi = tune_pid(P3_TF, objective="iae", ms_max=1.4, n_steps=800)
    pid = tune_pid(P3_TF, objective="iae", ms_max=1.4, controller="pid", n_steps=800)
    assert pid.pid.kd > 0
    assert pid.ms <= 1.4
    assert pid.objective < pi.objective


def test_noise_gain_bound_limits_gains():
    res = tune_pid(P3_TF, objective="iae", ms_max=1.8, max_noise_gain=0.3, n_steps=800)
    assert res.pid.kp <= 0.3 * (1 + 1e-6)


@functools.lru_cache(maxsize=1)
def _mt_bounded_tuning():
    """``tune_pid(1/(s+1)^3, objective="iae", ms_max=2.0, mt_max=1.1, n_steps=800)``, tuned once for
    the two tests of its Mt bound (a frozen TuningResult; it was tuned in each)."""
    return tune_pid(P3_TF, objective="iae", ms_max=2.0, mt_max=1.1, n_steps=800)


def test_mt_bound_is_respected():
    res = _mt_bounded_tuning()
    assert max(m.mt for m in res.margins) <= 1.1


def _closed_loop_stable(plant, pid):
    C = control.tf([pid.kd + pid.kp * pid.tf, pid.kp + pid.ki * pid.tf, pid.ki], [pid.tf, 1.0, 0.0])
    cl = control.feedback(plant * C, 1)
    return bool(np.all(np.real(cl.poles()) < 0))


@settings(max_examples=6, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.floats(0.2, 5.0),  # gain
    st.floats(0.05, 3.0),  # second time constant
    st.floats(0.01, 1.0),  # third time constant
    st.one_of(st.just(0.0), st.floats(0.05, 0.8)),  # right-half-plane zero time constant
    st.sampled_from(["iae", "ie", "ise"]),
    st.floats(1.2, 2.0),
)
def test_tuner_never_returns_an_unstable_loop(k, t2, t3, tz, objective, ms_max):
    num = [-k * tz, k] if tz > 0 else [k]
    plant = control.tf(num, np.polymul([1.0, 1.0], np.polymul([t2, 1.0], [t3, 1.0])))
    res = tune_pid(plant, objective=objective, ms_max=ms_max, n_steps=600)
    assert _closed_loop_stable(plant, res.pid)
    assert res.ms <= ms_max


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"objective": "iaee"}, r"objective = 'iaee'; expected one of ie, iae, itae, ise"),
        ({"controller": "pd"}, r"controller = 'pd'; expected 'pi' or 'pid'"),
        ({"ms_max": 0.9}, r"ms_max = 0\.9; expected a number in \(1, 10\)"),
        ({"mt_max": 0.1}, r"mt_max = 0\.1"),
        ({"max_noise_gain": -1.0}, r"max_noise_gain = -1\.0"),
        ({"step": float("nan")}, r"^step = nan; expected a finite non-zero step size"),
        ({"kp_max": -1.0}, r"^kp_max = -1\.0; expected a positive number"),
        ({"tf": 0.0}, r"^tf = 0\.0; expected a positive finite time constant in s"),
    ],
)
def test_bad_tuner_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        tune_pid(P3_TF, n_steps=200, **kwargs)


def test_pure_integrator_gets_the_stated_default_bound():
    """1/s: robustness alone never limits the gains, so the default design bounds the
    controller's high-frequency gain (10/|P(j w0)| = 10 at w0 = 1 rad/s) and says so."""
    r = tune_pid(control.tf([1.0], [1.0, 0.0]))
    assert r.status == "optimal"
    assert r.pid.kp == pytest.approx(10.0, rel=1e-5)
    assert r.ms <= 1.4 * (1 + 1e-9)
    assert "default noise-gain bound max_noise_gain = 10/|P(j w0)| = 10 at w0 = 1 rad/s" in r.warnings[0]
    explicit = tune_pid(control.tf([1.0], [1.0, 0.0]), max_noise_gain=3.0, horizon=10.0, tf=0.01)
    assert explicit.pid.kp == pytest.approx(3.0, rel=1e-5)
    assert not explicit.warnings[:1] == r.warnings[:1]


def test_discrete_and_mimo_plants_are_rejected():
    with pytest.raises(ValueError, match=r"discrete-time"):
        tune_pid(control.c2d(P3_TF, 0.1), horizon=10.0, tf=0.1)
    with pytest.raises(ValueError, match=r"2 outputs; expected one"):
        tune_pid(control.ss(np.eye(2) * -1, np.eye(2), np.eye(2), np.zeros((2, 2))), horizon=10.0, tf=0.1)


# ------------------------------------------------------------------------------------------------
# Issue 25: 2-DOF setpoint weights after the load-disturbance design. Goal (stated in the result):
# the least IAE of r - y after a unit setpoint step with the load-optimal gains fixed. Checked
# against an independent search on closed-loop transfer functions (tests/independent_tuner.py).
# ------------------------------------------------------------------------------------------------

P3_COEFFS = ([1.0], [1.0, 3.0, 3.0, 1.0])


def test_pi_weight_b_matches_independent_search():
    num, den = [1.0], [4.0, 1.0]
    r = tune_pid(control.tf(num, den), objective="iae", ms_max=1.2, mt_max=1.2, mks_max=10.0, setpoint_weights=True)
    sp = r.setpoint
    assert sp["c"] == 0.0
    assert "setpoint step" in sp["goal"]
    p = r.pid
    f = lambda b: ref.setpoint_iae(num, den, p.kp, p.ki, 0.0, p.tf, b, 0.0, t_end=20.0, n=8001)[0]
    best = minimize_scalar(f, bounds=(0.0, 1.0), method="bounded", options={"xatol": 1e-6})
    # The reference checks itself: converged, and no worse than any point of a grid over [0, 1].
    assert best.success, best.message
    assert best.fun <= min(f(b) for b in np.linspace(0.0, 1.0, 21))
    assert sp["b"] == pytest.approx(best.x, abs=2e-3)
    assert sp["iae"] == pytest.approx(f(sp["b"]), rel=1e-4)
    assert sp["iae"] <= sp["iae_unweighted"]
    assert sp["iae_unweighted"] == pytest.approx(f(1.0), rel=1e-4)
    # The weights leave the feedback loop alone: same gains and peaks as without them.
    r0 = tune_pid(control.tf(num, den), objective="iae", ms_max=1.2, mt_max=1.2, mks_max=10.0)
    assert (r0.pid.kp, r0.pid.ki, r0.pid.kd) == (p.kp, p.ki, p.kd)
    assert r0.ms == r.ms
    assert r0.mks == r.mks
    assert r0.setpoint is None


def test_pid_weights_b_c_match_independent_search():
    r = tune_pid(control.tf(*P3_COEFFS), objective="iae", controller="pid", setpoint_weights=True)
    sp, p = r.setpoint, r.pid
    f = lambda x: ref.setpoint_iae(*P3_COEFFS, p.kp, p.ki, p.kd, p.tf, x[0], min(max(x[1], 0.0), 1.0), t_end=40.0, n=4001)[0] \
        + 1e3 * (max(x[0] - 1, 0) + max(-x[0], 0) + max(x[1] - 1, 0) + max(-x[1], 0))
    # IAE is convex in (b, c) (the error is affine in them): one local search finds the minimum.
    # (with maxfev 120 it stopped unconverged; 152 evaluations measured)
    best = minimize(f, [0.5, 0.5], method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-8, "maxfev": 600})
    assert best.success, best.message  # the reference checks itself: converged, within the box
    assert 0.0 <= best.x[0] <= 1.0
    assert 0.0 <= best.x[1] <= 1.0
    assert sp["iae"] <= best.fun * (1 + 1e-4)  # no worse than the independent search
    assert sp["iae"] == pytest.approx(f([sp["b"], sp["c"]]), rel=1e-4)
    assert sp["iae"] < sp["iae_unweighted"]


def test_setpoint_weights_flag_is_checked():
    with pytest.raises(ValueError, match="setpoint_weights"):
        tune_pid(control.tf(*P3_COEFFS), setpoint_weights="yes")


# ------------------------------------------------------------------------------------------------
# The generic tuner's guarantees (issue 9 section 2, issue 13 arguments, issue 14 health).
#
# Every reference value here is computed independently of the tuner: peaks of |S| and |T| on a
# 200 000-point grid of the plant's own polynomials plus a bounded Brent search, closed-loop
# poles from python-control, objectives from a loop simulated over a much longer horizon.
# ------------------------------------------------------------------------------------------------

RESONANT = 1 / ((s + 1) * (s**2 / 100 + 0.004 * s + 1))  # zeta = 0.02 at 10 rad/s
P2 = 1 / (s + 1) ** 2


def _loop_poly(plant, pid):
    """Numerator and denominator polynomials of L = P C for the continuous PI/PID."""
    num, den = (np.atleast_1d(np.squeeze(x)) for x in control.tfdata(plant)[:2])
    c_num = np.polyadd(np.polymul([pid.kp, pid.ki], [pid.tf, 1.0]), [pid.kd, 0.0, 0.0])
    c_den = np.polymul([1.0, 0.0], [pid.tf, 1.0])
    return np.polymul(num, c_num), np.polymul(den, c_den)


def true_peaks(plant, pid, w_lo=1e-4, w_hi=1e4):
    """(Ms, Mt): 200k log-spaced points, then Brent around the best point (independent of the
    tuner's own peak search)."""
    ln, ld = _loop_poly(plant, pid)

    def mags(w):
        jw = 1j * np.asarray(w, float)
        L = np.polyval(ln, jw) / np.polyval(ld, jw)
        return 1 / np.abs(1 + L), np.abs(L / (1 + L))

    w = np.logspace(math.log10(w_lo), math.log10(w_hi), 200_000)
    out = []
    for k in (0, 1):
        m = mags(w)[k]
        i = int(np.argmax(m))
        r = minimize_scalar(lambda x: -mags([math.exp(x)])[k][0], method="bounded",
                            bounds=(math.log(w[max(i - 1, 0)]), math.log(w[min(i + 1, w.size - 1)])),
                            options={"xatol": 1e-12})
        assert r.success, r.message  # (the grid's value is kept when the refinement finds less)
        out.append(max(float(m[i]), float(-r.fun)))
    return tuple(out)


def control_pid(g, tf):
    from prsa_ctrl.drive.pid import PID

    return PID(g[0], g[1], g[2], tf=tf)


def closed_loop_poles(plant, pid):
    ln, ld = _loop_poly(plant, pid)
    return np.roots(np.polyadd(ld, ln))


# ---- 1. the reported Ms/Mt are the true ones, and the bound holds to 0.1 % -------------------

@pytest.fixture(scope="module")
def resonant_ie():
    return tune_pid(RESONANT, ms_max=1.4, objective="ie")


def test_resonance_true_ms_is_reported_and_at_the_bound(resonant_ie):
    """A grid-only Ms (the old tuner) gives a true Ms of 1.438 here and fails both checks."""
    r = resonant_ie
    ms_true, mt_true = true_peaks(RESONANT, r.pid)
    assert r.status == "optimal"
    assert r.converged
    assert ms_true <= 1.4 * (1 + 1e-9)
    assert ms_true >= 1.4 * (1 - 1e-3)  # the active bound holds to 0.1 %
    assert r.ms == pytest.approx(ms_true, rel=1e-7)
    assert r.mt == pytest.approx(mt_true, rel=1e-7)
    assert np.all(closed_loop_poles(RESONANT, r.pid).real < 0)


def test_resonance_objective_is_the_objective_of_the_gains(resonant_ie):
    """IE of a PI after a unit input step is exactly 1/ki; the horizon-truncated sum is not."""
    r = resonant_ie
    assert r.objective == pytest.approx(1 / r.pid.ki, rel=1e-7)
    assert abs(r.stats["objective_horizon"] / r.objective - 1) > 1e-2  # the horizon alone is wrong here


def test_mt_bound_is_the_true_mt():
    p3 = 1 / (s + 1) ** 3  # P3_TF
    r = _mt_bounded_tuning()
    ms_true, mt_true = true_peaks(p3, r.pid)
    assert mt_true <= 1.1 * (1 + 1e-9)
    assert mt_true >= 1.1 * (1 - 1e-3)
    assert r.mt == pytest.approx(mt_true, rel=1e-7)
    assert r.ms == pytest.approx(ms_true, rel=1e-7)


def test_sampled_loop_peak_matches_a_dense_search():
    """Discrete (sampled) loop: the peak up to Nyquist equals a 200k-point search + Brent."""
    a = np.array([[-5.0, 0.0], [1.0, 0.0]])
    b = np.array([[100.0, -100.0], [0.0, 0.0]])
    lp = drive_loop(a, b, np.array([1.0, 0.0]), 1, ts=1e-3, speed_filter=1e-3, tf=4e-3, horizon=0.2, step=1.0)
    g = (0.9, 40.0, 0.0)
    w = np.linspace(1e-2, math.pi / 1e-3, 200_000)
    sm = 1 / np.abs(1 + lp.loop_response(g, w))
    i = int(np.argmax(sm))
    r = minimize_scalar(lambda x: -1 / abs(1 + lp.loop_response(g, np.array([x]))[0]), method="bounded",
                        bounds=(w[max(i - 1, 0)], w[min(i + 1, w.size - 1)]), options={"xatol": 1e-10})
    assert r.success, r.message
    assert lp.peaks(g)["ms"] == pytest.approx(max(sm[i], -r.fun), rel=1e-9)
    assert lp.margins(g).ms == pytest.approx(max(sm[i], -r.fun), rel=1e-9)


# ---- 2. the scan follows the plant -----------------------------------------------------------

def test_default_bounds_work_and_kp_max_does_not_change_the_optimum():
    rs = [tune_pid(P2, ms_max=1.4, kp_max=k) for k in (None, 10.0, 1e4)]
    for r in rs:
        assert r.status == "optimal"
        assert r.ms <= 1.4
        assert r.ms >= 1.4 * (1 - 1e-3)
    for r in rs[1:]:
        assert r.pid.kp == pytest.approx(rs[0].pid.kp, rel=1e-5)
        assert r.pid.ki == pytest.approx(rs[0].pid.ki, rel=1e-5)
    assert 0 < rs[0].pid.kp < 3.58  # inside the Ms-feasible kp interval of the issue


def test_open_loop_unstable_plants_are_tuned():
    p = 1 / ((s - 1) * (0.1 * s + 1))
    r = tune_pid(p)
    assert r.status == "optimal"
    assert np.all(closed_loop_poles(p, r.pid).real < 0)
    assert true_peaks(p, r.pid)[0] <= 1.4 * (1 + 1e-9)
    r1 = tune_pid(1 / (s - 1), max_noise_gain=10.0)
    assert r1.status == "optimal"
    assert r1.pid.kp <= 10.0 * (1 + 1e-9)
    assert np.all(closed_loop_poles(1 / (s - 1), r1.pid).real < 0)
    # Default arguments: robustness alone does not bound the gains of 1/(s-1) (Ms -> 1 as they
    # grow), so the default design bounds the controller's high-frequency gain at
    # 10/|P(j w0)| (w0 = 1 rad/s, the unstable pole) and says so.
    r2 = tune_pid(1 / (s - 1))
    assert r2.status == "optimal"
    assert np.all(closed_loop_poles(1 / (s - 1), r2.pid).real < 0)
    assert r2.pid.kp <= 10.0 * np.sqrt(2.0) * (1 + 1e-9)
    assert r2.pid.kp > 1.0
    assert "default noise-gain bound" in r2.warnings[0]
    assert true_peaks(1 / (s - 1), r2.pid)[0] <= 1.4 * (1 + 1e-9)


def test_lags_with_delay_from_microseconds_to_hours_scale_exactly():
    """exp(-0.1 T s)/(T s + 1): the tuned loop is the same up to time scaling (kp equal, ki T
    equal, IAE / T equal) whether T is 1e-6 s or 1e4 s."""
    out = []
    for T in (1e-6, 1e4):
        n, d = control.pade(0.1 * T, 3)
        r = tune_pid(control.tf(n, d) / (T * s + 1))
        assert r.status == "optimal"
        assert r.ms <= 1.4
        assert r.ms >= 1.4 * (1 - 1e-3)
        out.append((r.pid.kp, r.pid.ki * T, r.objective / T))
    assert out[0] == pytest.approx(out[1], rel=1e-3)


# ---- 3. objective to infinity ----------------------------------------------------------------

def test_iae_includes_the_tail_beyond_the_horizon():
    """The reported IAE equals the sum over a horizon 64x longer (same sample; the slowest
    closed-loop mode decays with a ~6.4 s time constant, so 256 s leaves e^-40)."""
    lp = continuous_loop(RESONANT, tf=0.01, horizon=4.0, n_steps=2000)
    g = (0.08, 1.0, 0.0)
    long = continuous_loop(RESONANT, tf=0.01, horizon=256.0, n_steps=128000)
    val, tail = lp.objective_to_infinity(g, "iae")
    assert lp.objective(g, "iae") < 0.95 * val  # the horizon alone misses > 5 %
    assert val == pytest.approx(long.objective(g, "iae"), rel=1e-6)
    assert tail <= 1e-6 * val
    ise, _ = lp.objective_to_infinity(g, "ise")
    assert ise == pytest.approx(long.objective(g, "ise"), rel=1e-6)
    itae, _ = lp.objective_to_infinity(g, "itae")
    assert itae == pytest.approx(long.objective(g, "itae"), rel=1e-5)


# ---- 4. a reusable Tuner, no hidden state ------------------------------------------------------

def test_reused_tuner_equals_a_fresh_one():
    lp = continuous_loop(1 / (s + 1) ** 3, tf=0.1, horizon=40.0, n_steps=600)
    t = Tuner([lp], objective="iae")
    first = t.tune(ms_max=1.6)
    second = t.tune(ms_max=1.3, kp_max=50.0)
    fresh = Tuner([lp], objective="iae").tune(ms_max=1.3, kp_max=50.0)
    again = t.tune(ms_max=1.6)
    assert second.pid == fresh.pid
    assert second.objective == fresh.objective
    assert again.pid == first.pid
    assert first.pid.kp > second.pid.kp
    # tune_loops is a thin wrapper: the same numbers
    assert tune_loops([lp], objective="iae", ms_max=1.3, kp_max=50.0).pid == fresh.pid



def test_multi_loop_true_ms_holds_on_every_plant_and_a_reused_tuner_equals_a_fresh_one():
    """Several loops (robust tuning): the NLP holds Ms on a coarse subset of each grid plus the
    verified peaks; every plant's independently searched peak is within the bound, and a
    Tuner reused at another bound (its ranking caches) gives the fresh Tuner's design."""
    plants = [1 / ((s + 1) * (s**2 / w**2 + 2 * z * s / w + 1)) for w, z in ((8.0, 0.03), (10.0, 0.02), (13.0, 0.05))]
    loops = [continuous_loop(p, tf=0.05, horizon=30.0, n_steps=900) for p in plants]
    t = Tuner(loops, objective="iae", worst_case=True)
    first = t.tune(ms_max=1.5)
    second = t.tune(ms_max=1.3)
    fresh = Tuner(loops, objective="iae", worst_case=True).tune(ms_max=1.3)
    assert second.pid == fresh.pid
    assert second.objective == fresh.objective
    for r, bound in ((first, 1.5), (second, 1.3)):
        assert r.converged
        for p in plants:
            ms, _ = true_peaks(p, r.pid)
            assert ms <= bound * (1 + 1e-6)
    assert max(true_peaks(p, first.pid)[0] for p in plants) == pytest.approx(1.5, rel=1e-4)  # active


def test_peaks_and_crossover_below_the_model_grid_are_found():
    """A low-gain design puts the crossover and a sharp |S| resonance decades below the loop
    model's grid (the slow plant of a robust set): the peak search extends below the grid
    while |L| < 100 there, so Ms, Mt and the crossover are the true ones (the independent
    200k-point search from 1e-7 rad/s)."""
    from prsa_ctrl.drive.pid import PID

    plant = 5e-5 / (s * (s + 1))
    lp = continuous_loop(plant, tf=0.1, horizon=40.0, n_steps=800)
    pid = PID(1.18e-3, 1.30e-4, 0.0, tf=0.1)
    assert lp.omega[0] / 10 > 1e-4  # the resonance (~8e-5 rad/s) is below the model's grid
    ms, mt = true_peaks(plant, pid, w_lo=1e-7, w_hi=1e3)
    assert ms > 100  # a sharp low-frequency resonance
    m = lp.margins(pid.gains)
    assert m.ms == pytest.approx(ms, rel=1e-6)
    assert m.mt == pytest.approx(mt, rel=1e-6)
    # a crossover below the grid: a PI on 1/(s+1)^2 with tiny gains crosses at ~ ki rad/s
    plant2 = 1 / (s + 1) ** 2
    lp2 = continuous_loop(plant2, tf=0.1, horizon=40.0, n_steps=800)
    pid2 = PID(1e-4, 1e-6, 0.0, tf=0.1)
    ln, ld = _loop_poly(plant2, pid2)
    w = np.logspace(-8, -1, 700_001)
    mag = np.abs(np.polyval(ln, 1j * w) / np.polyval(ld, 1j * w))
    wc = w[np.flatnonzero(np.diff(np.sign(mag - 1)))[0]]
    assert wc < lp2.omega[0] / 10
    m2 = lp2.margins(pid2.gains)
    assert m2.wc_rad_s == pytest.approx(wc, rel=1e-4)
    assert 0.99 < m2.mt <= true_peaks(plant2, pid2, w_lo=1e-9, w_hi=1e3)[1] * (1 + 1e-9)


def test_trajectory_memo_returns_fresh_arrays():
    lp = continuous_loop(P2, tf=0.1, horizon=20.0, n_steps=300)
    g = (1.0, 0.5, 0.0)
    e = lp.error(g)
    e[:] = 1e9  # a caller scribbling on its copy
    assert np.array_equal(lp.error(g), lp._trajectory(g)["error"])
    for k in range(6):  # bounded: the memo keeps a few trajectories
        lp.error((1.0 + k, 0.5, 0.0))
    assert len(lp._memo["trajectory"]) <= 4


# ---- 5. stability classes ----------------------------------------------------------------------

def test_stability_classes():
    lp = continuous_loop(1 / (s + 1), tf=0.01, horizon=10.0, n_steps=200)
    assert lp.stability((1.0, 1.0, 0.0)) == "stable"
    assert lp.stability((1.0, 0.0, 0.0)) == "marginal"  # P only: the integral state stays put
    assert not lp.is_stable((1.0, 0.0, 0.0))
    assert lp.stability((0.0, -5.0, 0.0)) == "unstable"
    a = np.array([[0.0, 0.0], [1.0, 0.0]])
    b = np.array([[100.0, -100.0], [0.0, 0.0]])
    dl = drive_loop(a, b, np.array([1.0, 0.0]), 1, ts=1e-3, speed_filter=1e-3, tf=4e-3, horizon=0.2, step=1.0)
    assert dl.stability((0.5, 0.0, 0.0)) == "marginal"
    assert dl.stability((0.5, 20.0, 0.0)) == "stable"
    assert dl.stability((50.0, 20.0, 0.0)) == "unstable"
    assert lp.objective_to_infinity((1.0, 0.0, 0.0), "iae") == (math.inf, math.inf)


# ---- 6. continuous loops of a drive without the angle state ------------------------------------

def _drive_ss(with_angle: bool):
    """Inertia 2e-3 kg m^2 with viscous loss, 1 kHz current loop, 0.5 ms speed filter; inputs
    (torque command N m, load torque N m); output the filtered speed (rad/s)."""
    j, c, wc, tfil = 2e-3, 1e-3, 2 * math.pi * 1000, 5e-4
    a = np.array([[-c / j, 1 / j, 0.0], [0.0, -wc, 0.0], [1 / tfil, 0.0, -1 / tfil]])
    b = np.array([[0.0, -1 / j], [wc, 0.0], [0.0, 0.0]])
    cc = np.array([[0.0, 0.0, 1.0]])
    if with_angle:
        a = np.block([[a, np.zeros((3, 1))], [np.array([[1.0, 0, 0]]), np.zeros((1, 1))]])
        b = np.vstack([b, np.zeros((1, 2))])
        cc = np.hstack([cc, np.zeros((1, 1))])
    return control.ss(a, b, cc, np.zeros((1, 2)))


def test_continuous_drive_loop_is_tunable_without_the_angle_state():
    lp = continuous_loop(_drive_ss(False), tf=1e-3, horizon=0.1, n_steps=1000, step=1.0)
    r = tune_loops([lp], ms_max=1.4)
    assert r.status == "optimal"
    assert lp.stability(r.pid.gains) == "stable"
    assert 1.4 * (1 - 1e-3) <= r.ms <= 1.4
    with_angle = continuous_loop(_drive_ss(True), tf=1e-3, horizon=0.1, n_steps=1000, step=1.0)
    assert with_angle.stability(r.pid.gains) == "marginal"
    with pytest.raises(ValueError, match=r"pole the loop cannot move"):
        tune_loops([with_angle], ms_max=1.4)


# ---- 7. every numeric argument is validated ------------------------------------------------------

BAD = {
    "ms_max": [math.nan, math.inf, -1.0, 1.0, 10.0, 0.0, "1.4", True, None],
    "mt_max": [math.nan, math.inf, 0.5, 1.0, 11.0, "x", False],
    "max_noise_gain": [math.nan, math.inf, 0.0, -1.0, "big"],
    "step": [math.nan, math.inf, -math.inf, 0.0, "1", None],
    "horizon": [math.nan, math.inf, 0.0, -3.0, "10"],
    "tf": [math.nan, math.inf, 0.0, -0.1],
    "n_steps": [0, 5, 1.5, 10**9, math.nan, True],
    "kp_max": [math.nan, -1.0, 0.0, -math.inf, "10"],
    "ki_max": [math.nan, -2.0, 0.0],
    "kd_max": [math.nan, -2.0, 0.0],
}
_P3 = control.tf([1.0], [1.0, 3.0, 3.0, 1.0])
_LOOP = continuous_loop(_P3, tf=0.1, horizon=20.0, n_steps=100)


@settings(max_examples=60, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from(sorted(BAD)).flatmap(lambda k: st.tuples(st.just(k), st.sampled_from(BAD[k]))))
def test_bad_numeric_arguments_name_the_argument(arg):
    name, value = arg
    with pytest.raises(ValueError, match=rf"^{name} = "):
        tune_pid(_P3, controller="pid", **{name: value})
    if name in ("ms_max", "mt_max", "max_noise_gain", "kp_max", "ki_max", "kd_max"):
        with pytest.raises(ValueError, match=rf"^{name} = "):
            Tuner([_LOOP], controller="pid").tune(**{name: value})
        with pytest.raises(ValueError, match=rf"^{name} = "):
            tune_loops([_LOOP], controller="pid", **{name: value})


@pytest.mark.parametrize("weights", [[math.nan], [-1.0], [0.0], [1.0, 1.0], "a"])
def test_bad_weights(weights):
    with pytest.raises(ValueError, match=r"^weights = "):
        Tuner([_LOOP], weights=weights)
    with pytest.raises(ValueError, match=r"^weights = "):
        tune_loops([_LOOP], weights=weights)


# ---- 8. health: converged optimum or a loud status ------------------------------------------------

def test_issue14_inertia_plant_converges_at_the_bound_and_beats_a_grid():
    n, d = control.pade(0.375e-3, 3)
    p = 1 / (2e-3 * s) * 1 / (s / (2 * math.pi * 1000) + 1) * control.tf(n, d)
    r = tune_pid(p, ms_max=1.4)
    assert r.status == "optimal"
    assert r.converged
    assert not r.warnings
    ms_true = true_peaks(p, r.pid, 1.0, 1e6)[0]
    assert 1.4 * (1 - 1e-3) <= ms_true <= 1.4 * (1 + 1e-9)
    # A plain 21 x 25 grid around the result on the same loop model, keeping Ms <= 1.4.
    lp = continuous_loop(p, tf=r.pid.tf, horizon=r.stats["horizon_s"], n_steps=2000)
    pts = [(kp, ki, 0.0) for kp in r.pid.kp * np.logspace(-0.5, 0.5, 21) for ki in r.pid.ki * np.logspace(-1.0, 0.5, 25)]
    # grid Ms > 1.4 implies true Ms > 1.4: a valid (cheap) pre-filter
    ok = [g for g in pts if np.max(1 / np.abs(1 + lp.loop_response(g))) <= 1.4 and lp.stability(g) == "stable"]
    # (issue 20: the reported IAE is the continuous loop's, so the grid is judged on it too)
    vals = sorted((lp.objective_continuous(g, "iae")[0], g) for g in ok)
    # the best grid point whose true Ms (independent dense search) honours the bound
    best = next(v for v, g in vals if true_peaks(p, control_pid(g, r.pid.tf), 1.0, 1e6)[0] <= 1.4)
    assert len(vals) > 50
    assert math.isfinite(best)
    assert r.objective <= best * (1 + 1e-9)
    assert r.objective == pytest.approx(lp.objective_continuous(r.pid.gains, "iae")[0], rel=1e-9)


def test_unconverged_solve_says_so(monkeypatch):
    monkeypatch.setattr(nlp, "IPOPT_MAX_ITER", 1)
    monkeypatch.setattr(tuner, "POLISH_ROUNDS", 0)  # (issue 20: the polish would reach the optimum)
    lp = continuous_loop(_P3, tf=0.1, horizon=40.0, n_steps=400)
    r = Tuner([lp], objective="iae").tune(ms_max=1.4)
    assert not r.converged
    # issue 20: "optimal" is decided by the first-order check on the true problem, not ipopt's exit
    assert r.status.startswith("not proven optimal: ")
    assert "Maximum_Iterations_Exceeded" in r.status
    assert r.warnings
    assert "not proven optimal" in r.warnings[0]
    assert r.ms <= 1.4  # still a verified point
