"""Issue 25, the ideal PID ``kp + ki/s + kd s`` (``tune_pid(..., controller="pid", ideal=True)``),
IE objective (max ki) under Ms (and Mt): the MIGO problem of Panagopoulos, Astrom and Hagglund
(IEE Proc. CTA 149(1), 2002) without its extra constraints.

No published ideal-PID case with its plant, bounds and printed gains could be found to
reproduce (the search, and what came closest, is in docs/guides/generic-tuner.md, "Ideal PID").
This file holds the next-best evidence, on three plants not used elsewhere (a non-minimum-phase
zero, an integrator with Mt active, a lightly damped pair): a brute force written here with numpy
and scipy only -- every point of a (kp, kd) grid gets its largest feasible ki by a scan and a
bisection on a frequency grid, stability from the characteristic polynomial -- polished by SLSQP
from the best grid point; and the TRUE Ms, Mt of the tuner's gains on a dense grid refined near
each peak. A fourth case (Ms = 1.6 on 1/(s+1)^3) pins what the tuner may and may not say where it
falls short of the optimum.
"""

import math

import control
import numpy as np
import pytest
from scipy.optimize import minimize, minimize_scalar

import independent_tuner as ref
from prsa_ctrl.tuning import tune_pid

#: The brute force's frequency grid (rad/s): six decades around the loops' dynamics.
W_BF = np.logspace(-3, 3, 4000)
#: The polish's frequency grid (rad/s): one constraint per frequency and bound.
W_POLISH = np.logspace(-3, 3, 8000)
#: The ki scan of the brute force before the bisection.
KI_SCAN = np.logspace(-3, 2.5, 45)


def _loop(num, den, kp, ki, kd, w):
    s = 1j * np.asarray(w, float)
    return np.polyval(num, s) / np.polyval(den, s) * (kp + ki / s + kd * s)


def _true_peaks(num, den, kp, ki, kd):
    """(Ms, Mt) of the ideal-PID loop: a 200001-point log grid over 1e-4..1e4 rad/s, each peak
    then located by a bounded scalar search in log(omega) between its grid neighbours."""
    w = np.logspace(-4, 4, 200_001)
    out = []
    for f in (lambda L: 1 / (1 + L), lambda L: L / (1 + L)):
        mag = np.abs(f(_loop(num, den, kp, ki, kd, w)))
        i = int(np.argmax(mag))
        lo, hi = math.log(w[max(i - 2, 0)]), math.log(w[min(i + 2, w.size - 1)])
        r = minimize_scalar(lambda x: -abs(f(_loop(num, den, kp, ki, kd, [math.exp(x)])[0])),
                            bounds=(lo, hi), method="bounded", options={"xatol": 1e-12})
        out.append(max(float(mag[i]), float(-r.fun)))
    return tuple(out)


def _feasible(num, den, p, kp, kis, kd, ms, mt):
    """Which of the ``kis`` meet |S| <= ms (and |T| <= mt) on W_BF with a stable closed loop."""
    L = p[None, :] * (kp + kis[:, None] / (1j * W_BF)[None, :] + kd * (1j * W_BF)[None, :])
    a = np.abs(1 + L)
    ok = np.all(a * ms >= 1, axis=1)
    if mt is not None:
        ok &= np.all(np.abs(L) <= mt * a, axis=1)
    return np.array([bool(o) and ref.stable(num, den, kp, k, kd) for o, k in zip(ok, kis)])


def _max_ki(num, den, p, kp, kd, ms, mt):
    """The largest feasible ki at (kp, kd): the top feasible point of KI_SCAN, then bisection in
    log ki towards the next scan point (40 halvings); 0 where no scanned ki is feasible."""
    m = _feasible(num, den, p, kp, KI_SCAN, kd, ms, mt)
    if not m.any():
        return 0.0
    j = int(np.flatnonzero(m)[-1])
    assert j < KI_SCAN.size - 1, "the ki scan is too short for this plant"
    lo, hi = KI_SCAN[j], KI_SCAN[j + 1]
    for _ in range(40):
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if _feasible(num, den, p, kp, np.array([mid]), kd, ms, mt)[0] else (lo, mid)
    return lo


def _grid_best(num, den, ms, mt, kp_hi, kd_hi, n=12):
    """Exhaustive (kp, kd) grid over (0, kp_hi] x [0, kd_hi]: ((kp, ki, kd) of the best point,
    the largest ki found anywhere)."""
    p = np.polyval(num, 1j * W_BF) / np.polyval(den, 1j * W_BF)
    best = (0.0, None)
    for kp in np.linspace(0.0, kp_hi, n + 1)[1:]:
        for kd in np.linspace(0.0, kd_hi, n + 1):
            ki = _max_ki(num, den, p, kp, kd, ms, mt)
            if ki > best[0]:
                best = (ki, (float(kp), float(ki), float(kd)))
    return best[1], best[0]


def _polish(num, den, ms, mt, start, cell):
    """SLSQP on the problem discretised on W_POLISH (``|1 + L|^2 Ms^2 >= 1``, ``|L|^2 <= Mt^2
    |1 + L|^2`` per frequency), max ki, from the grid's best point and kept within two grid
    cells of it in kp and kd (the discretised constraints alone do not keep the loop stable)."""
    s = 1j * W_POLISH
    p = np.polyval(num, s) / np.polyval(den, s)

    def cons(x):
        L = p * (x[0] + x[1] / s + x[2] * s)
        a = np.abs(1 + L) ** 2
        return np.concatenate([a * ms * ms - 1.0] + ([] if mt is None else [mt * mt * a - np.abs(L) ** 2]))

    kp, ki, kd = start
    box = [(max(kp - 2 * cell[0], 1e-9), kp + 2 * cell[0]), (ki, 3 * ki), (max(kd - 2 * cell[1], 0.0), kd + 2 * cell[1])]
    r = minimize(lambda x: -x[1], start, method="SLSQP", constraints=[{"type": "ineq", "fun": cons}],
                 bounds=box, options={"maxiter": 500, "ftol": 1e-14})
    assert r.success, r.message
    return tuple(float(v) for v in r.x), box


# (num, den, Ms bound, Mt bound, the brute force's box kp_hi, kd_hi): the box is set by hand,
# wide enough that the optimum lies well inside it.
CASES = [
    pytest.param([-0.5, 1.0], [1.0, 3.0, 3.0, 1.0], 1.4, None, 3.0, 3.0, id="nmp-zero"),
    pytest.param([1.0], [1.0, 2.0, 1.0, 0.0], 1.4, 1.3, 3.0, 5.0, id="integrator-Mt"),
    pytest.param([1.0], [1.0, 1.4, 1.4, 1.0], 1.4, None, 2.0, 3.0, id="light-damping"),
]


@pytest.mark.parametrize("num, den, ms, mt, kp_hi, kd_hi", CASES)
def test_ideal_pid_against_brute_force(num, den, ms, mt, kp_hi, kd_hi):
    r = tune_pid(control.tf(num, den), objective="ie", controller="pid", ideal=True, ms_max=ms, mt_max=mt)
    assert r.status == "optimal"
    assert r.filter == {"order": 0, "tf_s": None, "derivative": "ideal"}
    kp, ki, kd = r.pid.kp, r.pid.ki, r.pid.kd
    # The reported peaks are the true peaks of the ideal law, and within the bounds.
    t_ms, t_mt = _true_peaks(num, den, kp, ki, kd)
    assert r.ms == pytest.approx(t_ms, rel=1e-6) and r.mt == pytest.approx(t_mt, rel=1e-6)
    assert t_ms <= ms * (1 + 1e-9) and (mt is None or t_mt <= mt * (1 + 1e-9))
    assert ref.stable(num, den, kp, ki, kd)
    assert r.objective == pytest.approx(1.0 / ki, rel=1e-12)  # IE of a unit load step: 1/ki
    # No point of the brute-force grid beats the tuner (its grid may miss a peak by ~1e-4 and so
    # allow a slightly larger ki; 1e-3 covers that), and the grid is not trivially poor.
    start, grid_ki = _grid_best(num, den, ms, mt, kp_hi, kd_hi)
    assert grid_ki <= ki * (1 + 1e-3)
    assert grid_ki >= 0.85 * ki
    # Polished from the best grid point, the brute force lands on the tuner's optimum (its own
    # peaks on a 8000-point grid, so up to ~2e-5 above the bound in truth: 3e-4 on ki covers it),
    # stable, inside its box, at the bounds.
    (bkp, bki, bkd), box = _polish(num, den, ms, mt, start, (kp_hi / 12, kd_hi / 12))
    assert bki == pytest.approx(ki, rel=3e-4)
    assert bkp == pytest.approx(kp, rel=1e-2) and bkd == pytest.approx(kd, rel=1e-2)
    assert box[0][0] < bkp < box[0][1] and box[2][0] < bkd < box[2][1] and bki < box[1][1]
    assert ref.stable(num, den, bkp, bki, bkd)
    b_ms, b_mt = _true_peaks(num, den, bkp, bki, bkd)
    assert b_ms == pytest.approx(ms, rel=1e-4) and (mt is None or b_mt == pytest.approx(mt, rel=1e-4))


def test_no_optimal_claim_below_a_feasible_brute_force_point():
    """1/(s+1)^3 with Ms <= 1.6 only: a feasible ideal PID with ki ~ 14.5 exists (found by the
    grid, its true Ms checked here), well above what the tuner returns today (ki ~ 5.84, status
    "not converged: scan point kept": its ipopt runs end with the true peak above the bound after
    the added frequencies are used up). Whatever the tuner returns must be feasible, and it may
    call it optimal only if it is not below that point."""
    num, den, ms = [1.0], [1.0, 3.0, 3.0, 1.0], 1.6
    r = tune_pid(control.tf(num, den), objective="ie", controller="pid", ideal=True, ms_max=ms)
    t_ms, _ = _true_peaks(num, den, r.pid.kp, r.pid.ki, r.pid.kd)
    assert t_ms <= ms * (1 + 1e-9) and r.ms == pytest.approx(t_ms, rel=1e-6)
    assert ref.stable(num, den, r.pid.kp, r.pid.ki, r.pid.kd)
    # The brute-force point, 0.5 % of margin taken off its ki against the grid's peak miss.
    p = np.polyval(num, 1j * W_BF) / np.polyval(den, 1j * W_BF)
    kp, kd = 16.0 / 3.0, 9.6  # the best (kp, kd) of a 15 x 16 grid over (0, 10] x [0, 12]
    ki = 0.995 * _max_ki(num, den, p, kp, kd, ms, None)
    assert ki > 14.0
    b_ms, _ = _true_peaks(num, den, kp, ki, kd)
    assert b_ms <= ms and ref.stable(num, den, kp, ki, kd)
    if r.status.startswith("optimal"):
        assert r.pid.ki >= ki * (1 - 1e-3)
    else:
        assert r.status.startswith("not converged") and any("not a proven optimum" in w for w in r.warnings)
