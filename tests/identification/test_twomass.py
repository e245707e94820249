"""The parametric FRF fits (prsa_ctrl.identification.twomass): rigid and two-mass axes with
current loop and delay, intervals that cover, and the structure the data choose.

The truth responses here come from the equations of motion solved in this file (a 2 x 2
complex system per frequency), not from the module's closed form."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from prsa_ctrl.errors import FitError
from prsa_ctrl.identification.twomass import choose_structure, fit_frf_model, two_mass_response

from independent_actuator import two_mass_eom_response

TWO_PI = 2 * math.pi


def _eom_response(f, jm, jl, k, c, b, fc, td):
    """Motor speed / torque command of two inertias on a spring and damper with viscous ``b``, a
    first-order current loop and a delay, solved from the equations of motion
    (tests/independent_actuator.py)."""
    return two_mass_eom_response(f, jm, jl, k, c, b, fc, td)


# a ball-screw-like axis: 3.3e-3 kg m^2 at the motor, 350 kg through 10 mm lead, 124 N/um
A = 0.01 / TWO_PI
TRUTH = dict(jm=3.27e-3, jl=350 * A * A, k=123.7e6 * A * A, zeta=0.03, b=8e-4, fc=1200.0, td=60e-6)


def _damper(t):
    jred = t["jm"] * t["jl"] / (t["jm"] + t["jl"])
    return 2 * t["zeta"] * math.sqrt(t["k"] * jred)


def _truth_modes(t):
    fa = math.sqrt(t["k"] / t["jl"]) / TWO_PI
    return fa, fa * math.sqrt((t["jm"] + t["jl"]) / t["jm"])


F = np.geomspace(5.0, 1500.0, 240)


def _noisy(g, rel, rng):
    """Multiplicative complex noise: ``rel`` RMS on the log magnitude and on the phase (rad)."""
    return g * np.exp(rel * (rng.standard_normal(len(g)) + 1j * rng.standard_normal(len(g))))


def test_closed_form_equals_equations_of_motion():
    t = TRUTH
    g_eom = _eom_response(F, t["jm"], t["jl"], t["k"], _damper(t), t["b"], t["fc"], t["td"])
    g = two_mass_response(F, motor_inertia_kg_m2=t["jm"], load_inertia_kg_m2=t["jl"], stiffness_n_m_per_rad=t["k"],
                          damping_n_m_s_per_rad=_damper(t), viscous_n_m_s_per_rad=t["b"],
                          current_loop_bandwidth_hz=t["fc"], delay_s=t["td"])
    assert np.max(np.abs(g / g_eom - 1)) < 1e-10


def test_sampled_rigid_response_is_the_toolkits():
    """The sampled form (ZOH command, backward-difference speed) agrees with the toolkit's own
    sampled linearisation of a rigid plant (prsa_ctrl.identification.frf.frf_response)."""
    from prsa_ctrl import load_plant
    from prsa_ctrl.identification.frf import frf_response

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p = load_plant("ballscrew-32x10")
    f = np.geomspace(2.0, 0.45 / p.sample_time_s, 60)
    g0 = frf_response(p, f, sample_time_s=p.sample_time_s, speed_rad_s=30.0)
    g = two_mass_response(f, motor_inertia_kg_m2=p.reflected_inertia_kg_m2,
                          viscous_n_m_s_per_rad=p.values["friction.viscous_n_m_s_per_rad"],
                          current_loop_bandwidth_hz=p.values["drive.current_loop_bandwidth_hz"],
                          sample_time_s=p.sample_time_s)
    assert np.max(np.abs(g / g0 - 1)) < 1e-6


def test_two_mass_fit_recovers_the_truth_and_says_why():
    t = TRUTH
    rng = np.random.default_rng(7)
    g = _noisy(_eom_response(F, t["jm"], t["jl"], t["k"], _damper(t), t["b"], t["fc"], t["td"]), 0.02, rng)
    ch = choose_structure((F, g))
    assert ch.structure == "two-mass"
    fa, fr = _truth_modes(t)
    v = ch.two_mass.values
    assert v["total_inertia_kg_m2"]["value"] == pytest.approx(t["jm"] + t["jl"], rel=0.01)
    assert v["resonance_hz"]["value"] == pytest.approx(fr, rel=0.005)
    assert v["antiresonance_hz"]["value"] == pytest.approx(fa, rel=0.005)
    assert v["current_loop_bandwidth_hz"]["value"] == pytest.approx(t["fc"], rel=0.1)
    assert f"{v['resonance_hz']['value']:.4g} Hz" in ch.reason
    assert "rigid model cannot produce" in ch.reason
    # the rigid model is far worse on this response
    assert ch.rigid.fit_percent < ch.two_mass.fit_percent - 10


def test_rigid_response_keeps_the_rigid_structure():
    t = TRUTH
    rng = np.random.default_rng(3)
    j = t["jm"] + t["jl"]
    g = _noisy(_eom_response(F, j, 1e-12, 1e12, 0.0, t["b"], t["fc"], t["td"]), 0.02, rng)
    ch = choose_structure((F, g))
    assert ch.structure == "rigid", ch.reason
    v = ch.rigid.values
    lo, hi = v["total_inertia_kg_m2"]["ci95"]
    assert lo <= j <= hi
    assert v["current_loop_bandwidth_hz"]["value"] == pytest.approx(t["fc"], rel=0.1)


def _coverage_hits(n):
    """Per key, how many of ``n`` noisy draws of the truth's response (2 % noise, seed 2024) have a
    two-mass fit whose 95 % interval holds the truth."""
    t = TRUTH
    g0 = _eom_response(F, t["jm"], t["jl"], t["k"], _damper(t), t["b"], t["fc"], t["td"])
    fa, fr = _truth_modes(t)
    truth = {"total_inertia_kg_m2": t["jm"] + t["jl"], "resonance_hz": fr, "antiresonance_hz": fa,
             "current_loop_bandwidth_hz": t["fc"], "delay_s": t["td"]}
    hits = {k: 0 for k in truth}
    rng = np.random.default_rng(2024)
    for _ in range(n):
        fit = fit_frf_model((F, _noisy(g0, 0.02, rng)), "two-mass")
        for k, x in truth.items():
            lo, hi = fit.values[k]["ci95"]
            hits[k] += lo <= x <= hi
    return hits


def test_the_first_draws_intervals_hold_the_truth():
    """The coverage study's first draw (the default run's guard of its claim; the 150 draws are
    slow): every key's 95 % interval holds the truth."""
    hits = _coverage_hits(1)
    assert all(h == 1 for h in hits.values()), hits


@pytest.mark.slow  # 150 two-mass fits (4.1 s of CPU); its first draw runs by default (above)
def test_intervals_cover_the_truth_about_95_percent():
    """Monte Carlo over noisy synthetic FRFs: the 95 % intervals of the total inertia, the mode
    and the anti-resonance hold the truth in about 95 % of the draws (binomial: 150 draws at
    p = 0.95 give 0.90..0.99 with probability > 99.5 %)."""
    n = 150
    hits = _coverage_hits(n)
    for k, h in hits.items():
        assert 0.90 <= h / n <= 0.99, (k, h)


def test_coherence_weights_the_points():
    """Points of low coherence carry large noise: weighted by coherence, the fit ignores them."""
    t = TRUTH
    rng = np.random.default_rng(11)
    g0 = _eom_response(F, t["jm"], t["jl"], t["k"], _damper(t), t["b"], t["fc"], t["td"])
    coh = np.full(len(F), 0.999)
    bad = rng.random(len(F)) < 0.15
    coh[bad] = 0.3
    g = g0 * np.exp(np.where(bad, 0.5, 0.005) * (rng.standard_normal(len(F)) + 1j * rng.standard_normal(len(F))))
    j = t["jm"] + t["jl"]
    fit_w = fit_frf_model((F, g, coh), "two-mass")
    fit_u = fit_frf_model((F, g), "two-mass")
    err_w = abs(fit_w.value("total_inertia_kg_m2") / j - 1)
    err_u = abs(fit_u.value("total_inertia_kg_m2") / j - 1)
    assert err_w < 0.003
    assert err_w < err_u
    lo, hi = fit_w.values["total_inertia_kg_m2"]["ci95"]
    assert lo <= j <= hi


def test_bad_arguments():
    with pytest.raises(ValueError, match="structure = 'flexible'"):
        fit_frf_model((F, np.ones(len(F), complex)), "flexible")
    with pytest.raises(ValueError, match="expected at least 14"):
        fit_frf_model((F[:5], np.ones(5, complex)), "two-mass")
    with pytest.raises(ValueError, match="non-finite or non-positive"):
        fit_frf_model((np.r_[-1.0, F[1:]], np.ones(len(F), complex)), "rigid")


# a continuous-time two-mass response (the equations of motion above: no sampling, no delay, a
# 1100 Hz current loop), as h9-appaxis wrote it (issue 32's "3.8e8 Hz and -8.4 us" case)
CONT = dict(jm=1.76e-3, jl=1.006e-3, fa=80.0, zeta=0.04, fc=1100.0)
F_CONT = np.geomspace(3.0, 1500.0, 220)


def _continuous_response(seed=9):
    t = CONT
    k = t["jl"] * (TWO_PI * t["fa"]) ** 2
    c = 2 * t["zeta"] * math.sqrt(k * t["jm"] * t["jl"] / (t["jm"] + t["jl"]))
    g = _eom_response(F_CONT, t["jm"], t["jl"], k, c, 0.0, t["fc"], 0.0)
    return _noisy(g, 0.01, np.random.default_rng(seed))


def test_a_continuous_response_fitted_as_sampled_ends_at_the_bounds_and_says_so():
    """Read as the drive's sampled response (125 us: the model then lags one sample more than the
    data), the unbounded fit took the current loop to 3.8e8 Hz with a zero-width interval and the
    delay to -8.4 us. The delay is bounded at 0 (a command does not act before it is given) and the
    current loop at 20 x the top frequency: both end there, reported 'at its bound: not identified
    by these data' with no interval. Fitted as what it is (continuous), nothing is at a bound and
    the intervals hold the truth of the equations of motion."""
    from prsa_ctrl.identification.twomass import AT_BOUND_NOTE, CURRENT_LOOP_MAX_FACTOR

    g = _continuous_response()
    ch = choose_structure((F_CONT, g), sample_time_s=1.25e-4)
    assert ch.structure == "two-mass", ch.reason
    for fit in (ch.rigid, ch.two_mass):
        d, fc = fit.values["delay_s"], fit.values["current_loop_bandwidth_hz"]
        assert d["value"] >= 0.0
        if d.get("at_bound"):
            assert d["at_bound"] == "lower"
            assert d["value"] == 0.0
            assert d["ci95"] is None
            assert d["note"] == AT_BOUND_NOTE
            assert d["unbounded_value"] < 0
            assert "delay_s" in fit.held
        assert fc["value"] <= CURRENT_LOOP_MAX_FACTOR * F_CONT[-1] * (1 + 1e-12)
    two = ch.two_mass.values
    assert two["delay_s"]["at_bound"] == "lower"
    assert two["delay_s"]["unbounded_value"] < 0
    assert two["current_loop_bandwidth_hz"]["at_bound"] == "upper"
    assert two["current_loop_bandwidth_hz"]["ci95"] is None
    assert two["current_loop_bandwidth_hz"]["value"] == pytest.approx(CURRENT_LOOP_MAX_FACTOR * F_CONT[-1])
    assert any(AT_BOUND_NOTE in w and w.startswith("delay_s = 0 s") for w in ch.two_mass.warnings)
    # fitted as continuous, the truth is recovered with intervals that hold it
    ch0 = choose_structure((F_CONT, g), sample_time_s=0.0)
    v = ch0.two_mass.values
    assert ch0.structure == "two-mass"
    assert not ch0.two_mass.held
    t = CONT
    truth = {"current_loop_bandwidth_hz": t["fc"], "antiresonance_hz": t["fa"],
             "resonance_hz": t["fa"] * math.sqrt((t["jm"] + t["jl"]) / t["jm"]),
             "total_inertia_kg_m2": t["jm"] + t["jl"], "delay_s": 0.0}
    for k, x in truth.items():
        lo, hi = v[k]["ci95"]
        assert lo <= x <= hi, (k, x, v[k])
    assert v["current_loop_bandwidth_hz"]["value"] == pytest.approx(t["fc"], rel=0.02)


def _judge_two_mass(name, seed):
    """The judge's two-mass response (tests/identification/foreign/gen_judge.py: its own formula
    with the nut loss on the whole force, ZOH and backward difference, 2 % magnitude and 0.02 rad
    phase noise drawn as its bode.csv draws them) and its truth."""
    from foreign import gen_judge as gj

    from prsa_ctrl.identification.data import frf_from_arrays

    case = gj.CASES[name]
    f = gj.frf_band(case)
    h = gj.frf(case, f)
    rng = np.random.default_rng([seed, 99, list(gj.CASES).index(name)])
    mag = np.abs(h) * (1.0 + 0.02 * rng.standard_normal(f.size))
    ph = np.unwrap(np.angle(h)) + 0.02 * rng.standard_normal(f.size)
    ts = case.mech.ts
    return frf_from_arrays("bode", f, mag * np.exp(1j * ph), sample_time_s=ts), ts, gj.truth(case)


_MODES = (("resonance_hz", "first_mode_hz"), ("antiresonance_hz", "anti_resonance_hz"))


def test_mode_and_anti_resonance_intervals_hold_an_independent_axis_truth():
    """One seed of the judge's two-mass ball screw: the mode and the anti-resonance the report
    gives (delta method on the fit's covariance) hold the generator's formulas, with intervals
    narrower than 1 % (the slow test counts the coverage over 20 seeds)."""
    fr, ts, t = _judge_two_mass("ball-2mass-d1-computed-si", 0)
    ch = choose_structure([fr], sample_time_s=ts)
    assert ch.structure == "two-mass", ch.reason
    for key, tkey in _MODES:
        v = ch.two_mass.values[key]
        lo, hi = v["ci95"]
        assert lo <= t[tkey] <= hi, (key, v, t[tkey])
        assert (hi - lo) / v["value"] < 0.01


@pytest.mark.slow
@pytest.mark.parametrize("name", ["ball-2mass-d1-computed-si", "roller-2mass-d2-computed-nonsi",
                                  "roller-2mass-d1-applied-si"])
def test_mode_and_anti_resonance_intervals_cover_over_20_seeds(name):
    """Coverage of the 95 % intervals of the mode and the anti-resonance over seeds 0..19 of the
    judge's response: at least 17 of 20 (binomial at p = 0.95: P(X <= 16) = 1.6 %). Measured
    (h14-band): ball 20 and 19, roller d2 19 and 20, roller d1 18 and 18."""
    hits = {key: 0 for key, _ in _MODES}
    for seed in range(20):
        fr, ts, t = _judge_two_mass(name, seed)
        ch = choose_structure([fr], sample_time_s=ts)
        assert ch.structure == "two-mass", (seed, ch.reason)
        for key, tkey in _MODES:
            lo, hi = ch.two_mass.values[key]["ci95"]
            hits[key] += lo <= t[tkey] <= hi
    for key, h in hits.items():
        assert h >= 17, (name, key, hits)


def _with_residual(f, j, b, r, fc, td):
    """A rigid axis with the compliance ``r`` of a mode above the band (its tail ``r s``), a
    current loop and a delay, written out here."""
    s = 1j * TWO_PI * np.asarray(f, float)
    return (1.0 / (j * s + b) + r * s) / (1.0 + s / (TWO_PI * fc)) * np.exp(-s * td)


def test_upper_residual_is_the_tail_r_s_ahead_of_the_current_loop():
    f = np.geomspace(5.0, 800.0, 50)
    g = two_mass_response(f, motor_inertia_kg_m2=4e-3, viscous_n_m_s_per_rad=1e-3, current_loop_bandwidth_hz=900.0,
                          delay_s=1e-4, upper_residual_rad_per_n_m=2e-6)
    assert np.max(np.abs(g / _with_residual(f, 4e-3, 1e-3, 2e-6, 900.0, 1e-4) - 1)) < 1e-12
    # the sampled form at low frequency tends to the continuous one (hold and difference: half a sample each)
    ts = 1e-5
    gs = two_mass_response(f[:10], motor_inertia_kg_m2=4e-3, viscous_n_m_s_per_rad=1e-3, current_loop_bandwidth_hz=900.0,
                           upper_residual_rad_per_n_m=2e-6, sample_time_s=ts)
    gc = _with_residual(f[:10], 4e-3, 1e-3, 2e-6, 900.0, ts)
    assert np.max(np.abs(gs / gc - 1)) < 1e-3


def test_the_upper_residual_is_fitted_with_an_interval_that_holds_it():
    """A response with a mode's tail above it: fitted with the upper residual, the inertia, the
    residual and the current loop hold their truths; without it, the current loop takes the tail
    up (its interval misses the truth)."""
    j, b, r, fc, td = 4e-3, 1e-3, 0.3 / (4e-3 * (TWO_PI * 1000.0) ** 2), 1200.0, 1e-4
    f = np.geomspace(5.0, 1500.0, 200)
    g = _noisy(_with_residual(f, j, b, r, fc, td), 0.01, np.random.default_rng(21))
    fit = fit_frf_model((f, g), "rigid", upper_residual=True)
    for key, x in (("total_inertia_kg_m2", j), ("upper_residual_rad_per_n_m", r), ("current_loop_bandwidth_hz", fc),
                   ("delay_s", td)):
        lo, hi = fit.values[key]["ci95"]
        assert lo <= x <= hi, (key, fit.values[key], x)
    plain = fit_frf_model((f, g), "rigid")
    assert "upper_residual_rad_per_n_m" not in plain.values
    lo, hi = plain.values["current_loop_bandwidth_hz"]["ci95"]
    assert not lo <= fc <= hi
