"""Coverage of the linear-axis fit on 4 kHz closed-loop logs (issue 21: the benchmark's 4 kHz log
had its fitted 95 % intervals miss the truth).

An independent generator written here (numpy only, nothing of prsa_ctrl): a mass with Coulomb and
viscous friction per direction and Karnopp stick, integrated exactly per sample (closed-form
exponential per direction, the stop located in closed form, then stick or breakaway); a 20-bit-like
encoder (5e-8 m quantum, a random grid phase, Gaussian interpolation noise of 0.3 quantum) whose
quantised position the controller uses (position P over velocity P, two-sample averaged velocity,
saturation); moves with random accelerations, lengths and pauses in both directions.

The fast test fits two seeds; the slow one 20 seeds: each key's truth inside its 95 % interval for
>= 18 of 20 seeds, no bias (mean z within 3 / sqrt(20)).

What the benchmark showed (bench.py ``_axis_log_4khz``): its generator's explicit sub-steps
biased the mass (fixed there), and on its log of eight moves with one repeated speed profile the
friction intervals of one direction miss at 2.5-4 standard errors, whichever the encoder grid's
phase (measured with this generator on that move list: 12 of 12 phases): a bias from the
encoder quantisation, which is not white while the axis holds one speed or rests, on a
Coulomb/viscous pair that one speed profile separates only weakly. With varied moves, as here,
the intervals hold at the nominal rate.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from prsa_ctrl.identification.axis import LinearAxisPlant, fit_linear_axis
from prsa_ctrl.identification.logformat import AxisLog, ControllerSpec

TRUTH = (80.0, 150.0, 190.0, 15.0, 18.0)  # M kg, Fv+ Fv- N s/m, Fc+ Fc- N
GAIN, KP, KV, SAT, H, RES = 35.0, 150.0, 250.0, 10.0, 2.5e-4, 5e-8


def _sample(x, v, f, theta, h):
    """Exact motion over one sample of constant force ``f``: (x, v) after ``h``."""
    m, fvp, fvn, fcp, fcn = theta
    left = h
    for _ in range(3):  # slide, stop, break away
        if v == 0.0:
            if -fcn <= f <= fcp:
                return x, 0.0
            s = 1.0 if f > fcp else -1.0
        else:
            s = math.copysign(1.0, v)
        fv, fc = (fvp, fcp) if s > 0 else (fvn, fcn)
        vinf, tau = (f - s * fc) / fv, m / fv
        t_stop = tau * math.log((v - vinf) / -vinf) if s * vinf < 0 else math.inf
        t = min(t_stop, left)
        e = math.exp(-t / tau)
        x += vinf * t + (v - vinf) * tau * (1.0 - e)
        v = 0.0 if t == t_stop else vinf + (v - vinf) * e
        left -= t
        if left <= 0.0:
            break
    return x, v


def _reference(n, seed):
    """Moves in both directions: accelerate a (0.6..1.4 m/s^2, random sign) for d (0.15..0.3 s),
    coast 50 ms, brake for d, pause 50..150 ms."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * H
    acc = np.zeros(n)
    t0 = 0.1
    while t0 < t[-1] - 0.4:
        a = rng.uniform(0.6, 1.4) * rng.choice([-1.0, 1.0])
        d = rng.uniform(0.15, 0.3)
        acc[(t >= t0) & (t < t0 + d)] += a
        acc[(t >= t0 + d + 0.05) & (t < t0 + 2 * d + 0.05)] -= a
        t0 += 2 * d + 0.05 + rng.uniform(0.05, 0.15)
    return 0.05 + np.cumsum(np.cumsum(acc) * H) * H


def generate(seed, duration_s=4.0, theta=TRUTH, noise=0.3):
    """One closed-loop log: time, encoder position, command (V, as computed), reference."""
    n = int(round(duration_s / H)) + 1
    r = _reference(n, seed)
    rng = np.random.default_rng(seed + 10_000)
    off = rng.uniform(0, RES)

    def enc(x):
        return RES * math.floor((x + off + noise * RES * rng.standard_normal()) / RES) - off

    x, v = r[0], 0.0
    qprev = qfprev = enc(x)
    qm, u = np.empty(n), np.empty(n)
    for k in range(n):
        qk = enc(x)
        qf = 0.5 * (qk + qprev)
        dq = (qf - qfprev) / H
        qprev, qfprev, qm[k] = qk, qf, qk
        u[k] = min(SAT, max(-SAT, KV * (KP * (r[k] - qk) - dq)))
        x, v = _sample(x, v, GAIN * u[k], theta, H)
    return np.arange(n) * H, qm, u, r


def _base():
    vals = {"axis.mass_kg": 50.0, "friction.viscous_positive_n_s_per_m": 100.0,
            "friction.viscous_negative_n_s_per_m": 100.0, "friction.coulomb_positive_n": 10.0,
            "friction.coulomb_negative_n": 10.0, "drive.gain_n_per_unit": GAIN, "drive.force_limit_n": 350.0,
            "sensor.sample_time_s": H, "sensor.encoder_resolution_m": RES}
    return LinearAxisPlant("start", vals, {k: "test: a start far from the truth" for k in vals})


def _fit(seed):
    t, qm, u, r = generate(seed)
    ctl = ControllerSpec("position-p/velocity-p", KP, KV, 0.0, "average2-difference", SAT, H)
    log = AxisLog(f"axis4k-{seed}", t, qm, u, "V", GAIN, H, reference_m=r, controller=ctl, resolution_m=RES)
    res = fit_linear_axis([log], _base())
    z = [(p["value"] - tv) / p["std"] for p, tv in zip(res.parameters.values(), TRUTH)]
    inside = [p["ci95"][0] <= tv <= p["ci95"][1] for p, tv in zip(res.parameters.values(), TRUTH)]
    return res, z, inside


@pytest.mark.parametrize("case", [(20.0, 0.3), (-7.0, -0.05), (30.0, 0.0), (-30.0, 0.0), (0.0, 0.02)])
def test_generator_integrates_exactly(case):
    """The closed-form sample against scipy's adaptive integration of the same law (with the
    stop as an event), over sliding, stopping and breakaway."""
    f, v0 = case
    theta = TRUTH
    h = 0.02
    x1, v1 = _sample(0.0, v0, f, theta, h)

    m, fvp, fvn, fcp, fcn = theta

    def rhs(_, y, s):
        fv, fc = (fvp, fcp) if s > 0 else (fvn, fcn)
        return [y[1], (f - s * fc - fv * y[1]) / m]

    def stop(_, y, s):
        return y[1]
    stop.terminal = True

    t, y = 0.0, np.array([0.0, v0])
    for _ in range(3):
        if y[1] == 0.0:
            if -fcn <= f <= fcp:
                break
            s = 1.0 if f > fcp else -1.0
        else:
            s = math.copysign(1.0, y[1])
        sol = solve_ivp(rhs, (t, h), y, args=(s,), events=stop if y[1] != 0.0 else None, rtol=1e-12, atol=1e-15)
        t, y = sol.t[-1], sol.y[:, -1].copy()
        if sol.status == 1:
            y[1] = 0.0
        if t >= h:
            break
    assert x1 == pytest.approx(y[0], rel=1e-8, abs=1e-14)
    assert v1 == pytest.approx(y[1], rel=1e-8, abs=1e-12)


def test_generator_log_is_quantised_and_reproduced_by_the_controller():
    """The logged position sits on the encoder grid, the axis moves both ways, and the logged
    command is the controller law on the logged positions (the log a drive would write)."""
    t, qm, u, r = generate(3, duration_s=1.5)
    steps = np.diff(qm)
    assert np.allclose(np.round(steps / RES) * RES, steps, rtol=0, atol=1e-12)
    assert np.max(np.diff(qm)) > 0 > np.min(np.diff(qm)) and np.ptp(qm) > 1e-2
    qf = 0.5 * (qm + np.r_[qm[0], qm[:-1]])
    dq = np.diff(np.r_[qf[0], qf]) / H
    np.testing.assert_allclose(u, np.clip(KV * (KP * (r - qm) - dq), -SAT, SAT), rtol=0, atol=1e-9)


@pytest.mark.parametrize("seed", [0, 1])
def test_truth_inside_the_intervals_two_seeds(seed):
    """Every key's truth within 3 standard errors (a wrong model or covariance gives 5..1000;
    the 20-seed rate is the slow test)."""
    res, z, _ = _fit(seed)
    assert (res.status, res.solver_status) == ("ok", "converged")  # (status in the vocabulary since issue 33)
    assert max(abs(x) for x in z) < 3.0, z


@pytest.mark.slow
def test_coverage_over_20_seeds():
    """>= 18 of 20 seeds inside each key's 95 % interval, mean z-score within 3 / sqrt(20) of 0.
    Measured (2026-11-24): inside per key 20/19/18/19/18, mean z -0.37/0.32/-0.09/-0.33/0.08."""
    zs, ins = [], []
    for seed in range(20):
        _, z, inside = _fit(seed)
        zs.append(z)
        ins.append(inside)
    counts = np.sum(ins, axis=0)
    mean_z = np.mean(zs, axis=0)
    print(f"inside per key {counts.tolist()}; mean z {np.round(mean_z, 3).tolist()}; "
          f"sd z {np.round(np.std(zs, axis=0, ddof=1), 3).tolist()}")
    assert np.all(counts >= 18), counts
    assert np.all(np.abs(mean_z) < 3 / math.sqrt(20)), mean_z
