"""The linear axis's validation (prsa_ctrl.identification.axisvalidation): ``prsa-fit LOG --log-format
F`` ends with exit 3, one line naming what the plant does not explain and no plant file, on logs of
an independent generator whose physics the fit lacks; the same logs without that physics fit.

The generator (:func:`axis_log`) is written here from the equations of motion, numpy only: a mass
with Coulomb + viscous friction per direction and a stick band, optionally a position-periodic
cogging force ``A sin(2 pi x / p)`` or a second mass on a lightly damped spring beyond it (neither
is in the rigid model), integrated with the midpoint rule on 40 substeps per 1 kHz sample (not the
toolkit's exact stepper); the position-P/velocity-P controller with the two-sample average, a random
binary test signal at the drive input, an unlogged white force disturbance (2 N rms), the position
quantised to 50 nm. Friction laws the model lacks, written here: a Stribeck rise
``Fc + Fs exp(-(v/vs)^2)`` (breakaway ``Fc + Fs``), a Coulomb level that changes linearly along
the travel; and a profile of slow moves (:func:`slow_profile`, 2..120 mm/s) such as a friction
identification runs.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from prsa_ctrl.cli.fit import main as fit_main
from prsa_ctrl.identification.axis import PARAMETERS, load_axis_plant
from prsa_ctrl.identification.axisvalidation import (EXCITATION_SHARE, FRICTION_DEPARTURE, PERIODIC_SHARE,
                                                     excitation_share, periodic_share)

import axis_generator as gen  # tests/identification is on sys.path (the reference profile, the CSV description)

H, GAIN, KP, KV, RES = 1e-3, 30.0, 150.0, 250.0, 5e-8
TRUTH = (80.0, 150.0, 220.0, 15.0, 25.0)  # M kg, Fv+ Fv- N s/m, Fc+ Fc- N


def slow_profile(rng, n):
    """Moves at speeds log-uniform in 2..120 mm/s (accelerations 0.5..2 m/s^2), each 0.2..0.6 s at its
    speed (at most 0.1 m), in both directions within 0..0.2 m, with rests of 50..150 ms."""
    r = np.zeros(n)
    x, k = 0.0, 0
    while k < n:
        vmax, amax = math.exp(rng.uniform(math.log(0.002), math.log(0.12))), rng.uniform(0.5, 2.0)
        dist = min(rng.uniform(0.2, 0.6) * vmax, 0.1)
        up = x + dist <= 0.2 and (x - dist < 0 or rng.random() < 0.5)
        pos = gen.trapezoid(dist, vmax, amax)
        seg = x + (pos if up else -pos)
        take = min(seg.size, n - k)
        r[k:k + take] = seg[:take]
        k += take
        x = seg[take - 1]
        rest = int(rng.uniform(0.05, 0.15) / H)
        r[k:k + rest] = x
        k += rest
    return r[:n]


def axis_log(seed, n=6000, sub=40, cogging=None, second=None, noise_n=2.0, dither_v=0.5, stribeck=None,
             coulomb_slope=0.0, slow=False):
    """``(time s, position m, reference m, command V, test signal V)`` of the closed loop;
    ``cogging=(N, period m)``, ``second=(kg, N/m)`` (a mass on a spring beyond the axis, damping ratio 0.02),
    ``stribeck=(Fs N, vs m/s)`` (both directions), ``coulomb_slope`` (the Coulomb levels times
    ``1 + coulomb_slope (x / 0.2 m - 0.5)``), ``slow`` (:func:`slow_profile` in place of the random moves)."""
    rng = np.random.default_rng(seed)
    m, fvp, fvn, fcp0, fcn0 = TRUTH
    fs, vs = stribeck if stribeck is not None else (0.0, 1.0)
    r = slow_profile(rng, n) if slow else gen.profile(rng, n)
    d = dither_v * np.repeat(rng.choice([-1.0, 1.0], size=n // 5 + 1), 5)[:n]
    disturbance = noise_n * rng.standard_normal(n)
    m2, k2 = second if second is not None else (1.0, 0.0)
    c2 = 2 * 0.02 * math.sqrt(k2 * m2)
    x = v = x2 = v2 = 0.0
    qm, u = np.zeros(n), np.zeros(n)
    qprev = qfprev = 0.0
    hs = H / sub

    def accelerations(f, x, v, x2, v2):
        net = f - k2 * (x - x2) - c2 * (v - v2)
        if cogging is not None:
            net += cogging[0] * math.sin(2 * math.pi * x / cogging[1])
        g = 1.0 + coulomb_slope * (x / 0.2 - 0.5)
        fcp, fcn = g * fcp0, g * fcn0
        if v > 0:
            a = (net - fcp - fs * math.exp(-(v / vs) ** 2) - fvp * v) / m
        elif v < 0:
            a = (net + fcn + fs * math.exp(-(v / vs) ** 2) - fvn * v) / m
        else:  # at rest: sticks while the net force is inside the band (breakaway Fc + Fs)
            a = (net - fcp - fs) / m if net > fcp + fs else ((net + fcn + fs) / m if net < -fcn - fs else 0.0)
        return a, (k2 * (x - x2) + c2 * (v - v2)) / m2

    for k in range(n):
        q = RES * math.floor(x / RES + 0.5)
        qm[k] = q
        qf = 0.5 * (q + qprev)
        dq = (qf - qfprev) / H
        qprev, qfprev = q, qf
        u[k] = min(10.0, max(-10.0, KV * (KP * (r[k] - q) - dq))) + d[k]
        f = GAIN * u[k] + disturbance[k]
        for _ in range(sub):  # midpoint rule; the axis stops where its speed would change sign
            a1, b1 = accelerations(f, x, v, x2, v2)
            vh = v + 0.5 * hs * a1
            if v != 0 and vh * v < 0:
                vh = 0.0
            a2, b2 = accelerations(f, x + 0.5 * hs * v, vh, x2 + 0.5 * hs * v2, v2 + 0.5 * hs * b1)
            vn = v + hs * a2
            if v != 0 and vn * v < 0:
                vn = 0.0
            x += 0.5 * hs * (v + vn)
            v = vn
            x2 += hs * (v2 + 0.5 * hs * b2)
            v2 += hs * b2
    return np.arange(n) * H, qm, r, u, d


# the generator's description (axis_generator's, mm and ms) plus the test signal's column
CSV_FORMAT = gen.DITHER_CSV_FORMAT
_write = gen.write_dither_csv


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    root = tmp_path_factory.mktemp("axisval")
    (root / "log.toml").write_text(CSV_FORMAT)
    for name, kw in (("plain", {}), ("cogging", {"cogging": (50.0, 0.02)}), ("second", {"second": (30.0, 8.0e6)})):
        _write(root / f"{name}.csv", axis_log(2, **kw))  # one seed: the same reference, test signal and disturbance
    return root


def _fit(logs, tmp_path, name, *extra):
    out = tmp_path / f"{name}.toml"
    code = fit_main([str(logs / f"{name}.csv"), "--log-format", str(logs / "log.toml"), "--out", str(out), *extra])
    return code, out


def test_the_logs_without_the_extra_physics_fit_with_the_truth_inside_the_intervals(logs, tmp_path, capsys):
    import json

    js = tmp_path / "plain.json"
    code, out = _fit(logs, tmp_path, "plain", "--json", str(js))
    text = capsys.readouterr()
    assert code == 0, text.err
    assert "validated: the plant as written explains every log" in text.out
    rep = json.loads(js.read_text())
    assert rep["validation"]["passes"] is True
    for k, true in zip(PARAMETERS, TRUTH):
        lo, hi = rep["parameters"][k]["ci95"]
        assert lo <= true <= hi, (k, true, lo, hi)
    entry = next(iter(rep["validation"]["written_plant"].values()))
    assert entry["excitation_share"] < EXCITATION_SHARE / 2
    assert entry["periodic_share"] < PERIODIC_SHARE / 2
    assert load_axis_plant(out).values["axis.mass_kg"] == pytest.approx(TRUTH[0], rel=0.01)


def test_a_cogging_force_is_refused_naming_its_period(logs, tmp_path, capsys):
    """50 N of cogging with a 20 mm period (the friction is 15-25 N): the closed-loop replay fits
    the speed at 99 % and the old rule passed it; the force residual is periodic in the position."""
    code, out = _fit(logs, tmp_path, "cogging")
    err = capsys.readouterr().err
    assert code == 3
    assert not out.exists()
    lines = [x for x in err.splitlines() if x.startswith("prsa-fit:")]
    assert len(lines) == 1, err
    assert "most likely missing physics: position-periodic force" in lines[0]
    period_mm = float(lines[0].split("one period of ")[1].split(" mm")[0])
    assert period_mm == pytest.approx(20.0, rel=0.03)
    assert "no plant file written" in lines[0]


def test_a_second_mass_the_rigid_model_lacks_is_refused(logs, tmp_path, capsys):
    code, out = _fit(logs, tmp_path, "second")
    err = capsys.readouterr().err
    assert code == 3
    assert not out.exists()
    line = next(x for x in err.splitlines() if x.startswith("prsa-fit:"))
    assert "most likely missing physics: second mass" in line
    assert "--fidelity compliant" in line


@pytest.fixture(scope="module")
def friction_logs(tmp_path_factory):
    root = tmp_path_factory.mktemp("axisfric")
    (root / "log.toml").write_text(CSV_FORMAT)
    _write(root / "slow.csv", axis_log(1, slow=True))
    _write(root / "stribeck.csv", axis_log(1, slow=True, stribeck=(20.0, 0.005)))  # the same seed: same moves, noise
    _write(root / "tight.csv", axis_log(2, coulomb_slope=1.2))  # logs["plain"] with a Coulomb level 0.4x..1.6x
    return root


def test_slow_moves_without_a_friction_law_the_model_lacks_fit_with_the_truth_inside(friction_logs, tmp_path, capsys):
    """Moves at 2..120 mm/s, Coulomb + viscous friction: exit 0, every key's truth inside its interval,
    the friction test far from its threshold (measured 0.065 on this seed; 0.06..0.10 on seeds 1-6)."""
    import json

    js = tmp_path / "slow.json"
    code, out = _fit(friction_logs, tmp_path, "slow", "--json", str(js))
    text = capsys.readouterr()
    assert code == 0, text.err
    rep = json.loads(js.read_text())
    for k, true in zip(PARAMETERS, TRUTH):
        lo, hi = rep["parameters"][k]["ci95"]
        assert lo <= true <= hi, (k, true, lo, hi)
    entry = next(iter(rep["validation"]["written_plant"].values()))
    assert entry["friction_departure"] < FRICTION_DEPARTURE / 2
    assert out.exists()


def test_a_stribeck_rise_is_refused_naming_it(friction_logs, tmp_path, capsys):
    """The same moves with a 20 N Stribeck rise at 5 mm/s (the closed-loop replay fits 99 %: the loop
    corrects the speed error within a few samples, and the fit raises its Coulomb level to 29.5 N
    against 20): exit 3, one line naming Stribeck friction and where, no plant file."""
    code, out = _fit(friction_logs, tmp_path, "stribeck")
    err = capsys.readouterr().err
    assert code == 3
    assert not out.exists()
    lines = [x for x in err.splitlines() if x.startswith("prsa-fit:")]
    assert len(lines) == 1, err
    assert "most likely missing physics: Stribeck friction" in lines[0]
    assert "mm/s" in lines[0]
    assert "no plant file written" in lines[0]


def test_a_friction_that_changes_along_the_travel_is_refused(friction_logs, tmp_path, capsys):
    """logs["plain"] with its Coulomb levels 0.4x at one end of the travel and 1.6x at the other
    (which test_the_logs_without_the_extra_physics_fit_with_the_truth_inside_the_intervals fits):
    exit 3, the diagnosis names a friction that changes along the travel, no plant file."""
    code, out = _fit(friction_logs, tmp_path, "tight")
    err = capsys.readouterr().err
    assert code == 3
    assert not out.exists()
    line = next(x for x in err.splitlines() if x.startswith("prsa-fit:"))
    assert "most likely missing physics: friction that changes along the travel" in line


def test_force_writes_the_refused_plant_with_a_header_that_says_so(logs, tmp_path, capsys):
    code, out = _fit(logs, tmp_path, "cogging", "--force")
    capsys.readouterr()
    assert code == 3
    text = out.read_text()
    assert "NOT VALIDATED" in text.split("[axis]")[0]
    assert "position-periodic force" in text.split("[axis]")[0]
    assert load_axis_plant(out).values["axis.mass_kg"] > 0


def test_the_excitation_share_is_chance_on_noise_and_high_on_a_response_to_it():
    """White noise beside a reference and a test signal: predicted by nothing (share about 0); a
    residual that is a lightly damped 100 Hz response to the test signal plus as much noise: about half."""
    rng = np.random.default_rng(0)
    n = 6000
    r = gen.profile(rng, n)
    d = np.repeat(rng.choice([-1.0, 1.0], size=n // 5 + 1), 5)[:n]
    noise = rng.standard_normal(n - 1)
    assert abs(excitation_share(noise, r, d, H, 49)) < 0.05
    from scipy.signal import lfilter

    w, z = 2 * math.pi * 100 * H, 0.05
    pole = math.exp(-z * w)
    mode = lfilter([1.0, -1.0], [1.0, -2 * pole * math.cos(w), pole * pole], d)[:-1]
    mode *= np.std(noise) / np.std(mode)
    share = excitation_share(mode + noise, r, d, H, 49)
    assert 0.35 < share < 0.6, share


def test_the_periodic_share_finds_a_period_of_the_position_and_not_one_in_noise():
    rng = np.random.default_rng(1)
    n = 6000
    q = gen.profile(rng, n)
    noise = 5.0 * rng.standard_normal(n)
    share, _ = periodic_share(noise, q, H, 49)
    assert share < 0.05
    share, period = periodic_share(noise + 5.0 * np.sin(2 * math.pi * q / 0.013), q, H, 49)
    assert period == pytest.approx(0.013, rel=0.01)
    assert 0.25 < share < 0.42, share  # a third of the power is the sinusoid's (12.5 N^2 beside 25 N^2 of noise)


def _fit_seed(seed):
    from prsa_ctrl.identification.axis import fit_linear_axis
    from prsa_ctrl.identification.calibrate_axis import axis_base_plant
    from prsa_ctrl.identification.logformat import AxisLog, ControllerSpec

    t, q, r, u, d = axis_log(seed)
    ctl = ControllerSpec("position-p/velocity-p", KP, KV, 0.0, "average2-difference", 10.0, H)
    log = AxisLog(f"seed-{seed}", t, q, u, "V", GAIN, H, reference_m=r, test_signal=d, controller=ctl, resolution_m=RES)
    fit = fit_linear_axis([log], axis_base_plant([log], "log.toml")[0])
    inside = [fit.parameters[k]["ci95"][0] <= tv <= fit.parameters[k]["ci95"][1] for k, tv in zip(PARAMETERS, TRUTH)]
    z = [(fit.parameters[k]["value"] - tv) / fit.parameters[k]["std"] for k, tv in zip(PARAMETERS, TRUTH)]
    return fit, inside, z


@pytest.mark.slow  # 20 generator logs and fits (about 4 s of CPU each)
def test_interval_coverage_over_20_seeds_with_an_unlogged_disturbance():
    """The rigid fit's 95 % intervals on logs whose residual is correlated over hundreds of samples
    (the 2 N disturbance; a position the stick band holds off its reference for a whole rest): each
    key's truth inside in >= 18 of 20 seeds, mean z within 3 / sqrt(20) of 0 (the rule of
    test_axis.test_coverage_over_20_seeds). Measured with the former batch means over 10 blocks:
    inside per key 15/15/13/14/13, the z-scores' standard deviation 2.1-4.8 (a covariance blind to
    the long correlation); Newey-West alone 18/19/20/19/19; the covariance that holds both
    (axis.score_covariance) 19/20/20/20/20, mean z 0.13/0.19/0.41/-0.22/-0.47, sd z
    1.27/0.72/0.64/0.79/0.78 (and on test_axis's 4 kHz exact generator 20/20/20/20/20)."""
    ins, zs = [], []
    for seed in range(1, 21):
        fit, inside, z = _fit_seed(seed)
        assert fit.passes, (seed, fit.validation["reasons"])  # no physics missing: never refused
        ins.append(inside)
        zs.append(z)
    counts = np.sum(ins, axis=0)
    mean_z = np.mean(zs, axis=0)
    print(f"inside per key {counts.tolist()}; mean z {np.round(mean_z, 3).tolist()}; "
          f"sd z {np.round(np.std(zs, axis=0, ddof=1), 3).tolist()}")
    assert np.all(counts >= 18), counts
    assert np.all(np.abs(mean_z) < 3 / math.sqrt(20)), mean_z


@pytest.mark.slow  # 18 generator logs and fits (about 1.5 s of CPU each)
def test_the_friction_tests_threshold_over_seeds():
    """The measurements behind prsa_ctrl.identification.axisfriction.FRICTION_DEPARTURE, seeds 1-6:
    the right model on slow moves (measured 0.057..0.101) and on the random moves (0.005..0.024) stays
    below half of it; a 20 N Stribeck rise at 5 mm/s on slow moves (0.356..0.612) reaches it, and the
    fitted plant is refused."""
    from prsa_ctrl.identification.axis import fit_linear_axis
    from prsa_ctrl.identification.calibrate_axis import axis_base_plant
    from prsa_ctrl.identification.logformat import AxisLog, ControllerSpec

    def departure(seed, **kw):
        t, q, r, u, d = axis_log(seed, **kw)
        ctl = ControllerSpec("position-p/velocity-p", KP, KV, 0.0, "average2-difference", 10.0, H)
        log = AxisLog(f"seed-{seed}", t, q, u, "V", GAIN, H, reference_m=r, test_signal=d, controller=ctl,
                      resolution_m=RES)
        fit = fit_linear_axis([log], axis_base_plant([log], "log.toml")[0], check_delay=False)
        return fit, next(iter(fit.validation["written_plant"].values()))["friction_departure"]

    for seed in range(1, 7):
        for kw in ({}, {"slow": True}):
            fit, dep = departure(seed, **kw)
            assert dep < FRICTION_DEPARTURE / 2, (seed, kw, dep)
        fit, dep = departure(seed, slow=True, stribeck=(20.0, 0.005))
        assert dep >= FRICTION_DEPARTURE, (seed, dep)
        assert not fit.passes
