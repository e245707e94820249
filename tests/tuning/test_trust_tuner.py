"""Issue 20: "optimal" means optimal, the reported objective is the continuous loop's, and bad
plants get a clear error.

Every reference here is computed WITHOUT the tuner's internals: Ms from python-control's own
frequency response of P(s) C(s) on a dense grid plus a bounded scalar refinement, the IAE from
the closed loop that ``control.feedback`` builds, sampled exactly (matrix exponential) and
summed by the trapezoid rule, the IE of an input step from the final-value theorem
(``int e = -1/ki``, exact for any plant with an integrating PI/PID).
"""

import math

import control
import numpy as np
import pytest
from scipy.linalg import expm, matrix_balance
from scipy.optimize import minimize_scalar

from prsa_ctrl.tuning.generic import tune_pid

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


@pytest.mark.parametrize("controller_kind, ms_max", _GRID)
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


@pytest.mark.parametrize("controller_kind, ms_max", _GRID)
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


@pytest.mark.parametrize("case", SEARCH_CASES, ids=[c[0] for c in SEARCH_CASES])
def test_no_better_feasible_point_near_a_reported_optimum(case):
    _, plant, ctrl, obj, ms_max, (w_lo, w_hi) = case
    r = tune_pid(plant, objective=obj, controller=ctrl, ms_max=ms_max)
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
    _, plant, ctrl, obj, ms_max, _ = case
    r = tune_pid(plant, objective=obj, controller=ctrl, ms_max=ms_max)
    assert r.status == "optimal" and r.converged and r.stats["first_order"]["ok"]
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


from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


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
