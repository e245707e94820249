"""The linear-axis fit (prsa_ctrl.identification.axis): its inputs checked before any replay, a base
plant's values and uncertainty kept, the plant file it writes, coverage on 4 kHz logs.

The closed-loop calibration and the EMPS benchmark case:

* A synthetic closed-loop log from an independent generator (tests/identification/axis_generator.py:
  fine trapezoidal substeps with a Karnopp stick band, quantised position, the position-P/velocity-P
  controller with the two-sample average) is recovered within its 95 % intervals, through a CSV
  file and a log description in mm and ms.
* The EMPS record (A. Janot, M. Gautier, M. Brunot, "Data Set and Reference Models of EMPS",
  Nonlinear System Identification Benchmarks workshop, 2019): the two commands of
  examples/emps/README.md end to end, the published model replayed with this code, and the
  benchmark's own replay convention reproduced. Skipped when the data file is absent.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.io import savemat

from prsa_ctrl.cli.fit import main, main as fit_main
from prsa_ctrl.cli.tune import main as tune_main
from prsa_ctrl.errors import SimulationError
from prsa_ctrl.identification.axis import (DEFAULTS, PARAMETERS, LinearAxisPlant, axis_plant_toml, fit_linear_axis,
                                           load_axis_plant, logged_force_peak, measured_velocity, relative_error,
                                           replay_axis, simulate_axis)
from prsa_ctrl.identification.logformat import AxisLog, ControllerSpec, load_axis_log, load_log_format
from prsa_ctrl.plant import describe_plant, linear_core, load_plant
from prsa_ctrl.plant.model import plant_model
from prsa_ctrl.plant.schema import DEFAULTS as SCHEMA_DEFAULTS

import axis_generator as gen  # tests/identification is on sys.path

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "emps"
_CANDIDATES = [ROOT.parent / "shared" / "data" / "emps" / "DATA_EMPS.mat", EXAMPLE / "DATA_EMPS.mat"]
DATA = next((p for p in _CANDIDATES if p.is_file()), None)
needs_data = pytest.mark.skipif(DATA is None, reason="EMPS data absent (../shared/data/emps/ or examples/emps/)")

# Published reference model (benchmark report): M, Fv, Fc, offset
M_REF, FV_REF, FC_REF, OFF_REF = 95.1089, 203.5034, 20.3935, -3.1648


def _base_with_limit(tmp_path, limit_n: float) -> Path:
    text = (EXAMPLE / "plant.toml").read_text()
    assert "force_limit_n = { value = 351.5065188248547" in text
    p = tmp_path / f"base-{limit_n:g}.toml"
    p.write_text(text.replace("force_limit_n = { value = 351.5065188248547", f"force_limit_n = {{ value = {limit_n!r}"))
    return p


@pytest.fixture(scope="module")
def emps_log():
    if DATA is None:
        pytest.skip("EMPS data absent")
    return load_axis_log(DATA, load_log_format(EXAMPLE / "log.toml"))


@needs_data
def test_logged_force_peak_is_the_largest_gain_times_command(emps_log):
    peak, where = logged_force_peak([emps_log])
    assert peak == pytest.approx(float(np.max(np.abs(emps_log.gain_n_per_unit * emps_log.command))), rel=0, abs=0)
    assert 150.0 < peak < 155.0
    assert where == emps_log.name  # the EMPS record peaks at 152.05 N


@needs_data
@pytest.mark.parametrize("limit", [130.0, 100.0])
def test_a_force_limit_below_the_logged_forces_is_refused_by_the_api(emps_log, tmp_path, limit):
    base = load_axis_plant(_base_with_limit(tmp_path, limit))
    with pytest.raises(ValueError, match=rf"force_limit_n = {limit:g} N is below the largest logged force 152\.0\d N"):
        fit_linear_axis([emps_log], base, check_delay=False)


@needs_data
@pytest.mark.parametrize("limit", [130.0, 120.0, 100.0])
def test_prsa_fit_refuses_a_base_force_limit_below_the_logged_forces(tmp_path, capsys, limit):
    """Was: 130 N fitted a mass of 91.97 kg (against 95.33 kg), 120 N 88.35 kg, 100 N ended in
    "did not converge" (exit 3). Now exit 2 before the fit, both forces named, nothing written."""
    base = _base_with_limit(tmp_path, limit)
    out = tmp_path / "fitted.toml"
    code = main([str(DATA), "--log-format", str(EXAMPLE / "log.toml"), "--plant", str(base), "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert len(err.splitlines()) == 1
    assert f"--plant {base}" in err
    assert f"drive.force_limit_n = {limit:g} N" in err
    assert "152.05 N" in err
    assert "DATA_EMPS.mat" in err
    assert not out.exists()


@pytest.fixture(scope="module")
def limit_fits(emps_log, tmp_path_factory):
    """``(a, b)``: the EMPS record fitted on the example's plant without a force limit and with
    one just above the logged peak, made once per module: the force-limit test compares them,
    test_axis_fit_as_dict_carries_the_status reads ``b`` (it fitted the example's plant afresh)."""
    peak, _ = logged_force_peak([emps_log])
    base = load_axis_plant(_base_with_limit(tmp_path_factory.mktemp("limit"), 351.5065188248547))
    unlimited = dataclasses.replace(base, values={**base.values, "drive.force_limit_n": math.inf})
    just_above = dataclasses.replace(base, values={**base.values, "drive.force_limit_n": peak * 1.001})
    return fit_linear_axis([emps_log], unlimited, check_delay=False), fit_linear_axis([emps_log], just_above,
                                                                                      check_delay=False)


@needs_data
def test_a_force_limit_above_the_logged_forces_fits_as_without_a_limit(limit_fits):
    """A limit the log never reaches must not change the fit (the drive applied every logged force)."""
    a, b = limit_fits
    for k, v in a.parameters.items():
        lo, hi = v["ci95"]
        assert abs(b.parameters[k]["value"] - v["value"]) < 0.01 * (hi - lo), k
    assert 95.0 < a.parameters["axis.mass_kg"]["value"] < 95.7  # the published 95.11 kg within the fit's interval


def test_a_coulomb_interval_reaching_zero_is_written_inside_the_range(tmp_path):
    """The fitted entry of a friction key whose interval reaches 0: its truncation is rounded
    inward (was round(trunc, 6), here 1.234568 sigma: a support from -1e-07 N, file refused)."""
    import tomllib

    from prsa_ctrl.identification.axis import normal_entry, axis_plant_toml

    value, sigma = 1.2345679, 1.0
    assert value - round(value / sigma * (1 - 1e-9), 6) * sigma < 0  # what the old rule wrote
    entry = normal_entry(value, sigma, False, "fit: test")
    assert entry["truncate"] == 1.234567
    assert value - entry["truncate"] * sigma >= 0
    assert normal_entry(value, 0.0, False, "fit: test") is None
    assert normal_entry(0.05, 1.0, False, "fit: test") is None  # < 0.1 sigma above the bound
    base = load_axis_plant(EXAMPLE / "plant.toml")
    plant = dataclasses.replace(base, values={**base.values, "friction.coulomb_negative_n": value},
                                uncertainty={"friction.coulomb_negative_n": entry})
    p = tmp_path / "fitted.toml"
    p.write_text(axis_plant_toml(plant))
    back = load_axis_plant(p)  # the file reader checks the support against the key's range
    assert tomllib.loads(p.read_text())["uncertainty"]["friction.coulomb_negative_n"]["truncate"] == 1.234567
    assert back.uncertainty["friction.coulomb_negative_n"]["truncate"] == 1.234567


def test_a_two_mass_axis_file_round_trips_and_a_rigid_one_stays_as_it_was(tmp_path):
    """The two-mass keys of a linear axis (the FRF fit's mode: axis.load_mass_kg,
    axis.load_stiffness_n_per_um, axis.axial_damping_ratio) are written with their sources and
    read back; a rigid axis (load mass 0, the default) writes none of them."""
    import tomllib

    from prsa_ctrl.identification.axis import AxisPlantError, axis_plant_toml

    base = load_axis_plant(EXAMPLE / "plant.toml")
    rigid = tomllib.loads(axis_plant_toml(base))
    assert set(rigid["axis"]) == {"mass_kg"}
    assert base.values["axis.load_mass_kg"] == 0.0
    two = {"axis.load_mass_kg": 0.3 * base.values["axis.mass_kg"], "axis.load_stiffness_n_per_um": 2.5,
           "axis.axial_damping_ratio": 0.04}
    plant = base.with_values(two, {k: f"fit: two-mass FRF ({k})" for k in two})
    p = tmp_path / "two.toml"
    p.write_text(axis_plant_toml(plant))
    back = load_axis_plant(p)
    for k, v in two.items():
        assert back.values[k] == pytest.approx(v, rel=1e-12)
        assert back.sources[k] == f"fit: two-mass FRF ({k})"
    assert back.to_plant().values["axis.load_stiffness_n_per_um"] == pytest.approx(2.5)
    bad = tmp_path / "bad.toml"
    bad.write_text(p.read_text().replace(f"load_mass_kg = {{ value = {two['axis.load_mass_kg']!r}",
                                         f"load_mass_kg = {{ value = {2 * base.values['axis.mass_kg']!r}"))
    assert bad.read_text() != p.read_text()
    with pytest.raises(AxisPlantError, match="axis.load_mass_kg = .* is not below axis.mass_kg"):
        load_axis_plant(bad)


def test_the_screw_fit_entries_never_cross_the_range():
    """The motor-coordinate fit's entries (identification.common) round inward too."""
    from prsa_ctrl.identification.fituncertainty import uncertainty_entries
    from prsa_ctrl.plant.plantfile import load_plant

    plant = load_plant("paper-iprsm")
    key = "friction.viscous_n_m_s_per_rad"  # non-negative
    value, sd = 1.2345679e-4, 1e-4
    assert value - round(value / sd * (1 - 1e-9), 6) * sd < 0  # what the old rule wrote
    fitted = plant.with_params({key: value})
    out = uncertainty_entries(fitted, {key: {"value": value, "ci95": [value - 1.96 * sd, value + 1.96 * sd]}},
                               "t.csv", [sd])
    e = out[key]
    assert e["dist"] == "normal"
    assert value - e["truncate"] * e["sigma"] >= 0
    assert e["truncate"] == 1.234567
    fitted.with_params({key: value - e["truncate"] * e["sigma"]})  # the support's end is a valid plant


@needs_data
def test_refitting_with_the_own_fitted_plant_as_base_is_written(emps_fit, tmp_path, capsys):
    """Was: exit 2 after the whole fit, "'axis.mass_kg' appears twice (in two blocks)". The first
    fit is the session's (tests/conftest.py's emps_fit: the README's command; this test ran its own
    with the example's plant as --plant)."""
    import tomllib

    fmt = str(EXAMPLE / "log.toml")
    assert emps_fit.code == 0, emps_fit.err
    first, second = emps_fit.toml, tmp_path / "second.toml"
    capsys.readouterr()
    code = main([str(DATA), "--log-format", fmt, "--plant", str(first), "--out", str(second)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    a, b = (tomllib.loads(p.read_text()) for p in (first, second))
    corr = b["uncertainty"]["correlation"]
    assert isinstance(corr, dict)
    assert sorted(corr["keys"]) == sorted(a["uncertainty"]["correlation"]["keys"])
    assert corr["matrix"] == a["uncertainty"]["correlation"]["matrix"]  # the same data, the same fit
    assert b["axis"]["mass_kg"]["value"] == a["axis"]["mass_kg"]["value"]
    assert "the new correlation block holds them" in captured.out
    load_axis_plant(second)


@needs_data
@pytest.mark.parametrize("bad", [0, -1, 2.5, True])
def test_max_evaluations_is_checked_before_the_fit(emps_log, bad):
    """Was: scipy's own message ("max_nfev ...") for 0."""
    base = load_axis_plant(EXAMPLE / "plant.toml")
    with pytest.raises(ValueError, match=rf"max_evaluations = {bad!r}; expected an integer >= 1"):
        fit_linear_axis([emps_log], base, max_evaluations=bad)


def test_axis_fit_status_is_in_the_vocabulary_and_names_what_failed():
    from prsa_ctrl.identification.axis import AxisReplay, axis_fit_status
    from prsa_ctrl.results import status_head

    z = np.zeros(3)
    good = AxisReplay("a.csv", True, z, z, z, z, z, z, z, {"position": 1.0}, {"position": 99.0})
    bad = AxisReplay("b.csv", True, z, z, z, z, z, z, z, {"position": float("nan")}, {"position": 99.0})
    assert axis_fit_status([good], []) == "ok"
    flagged = axis_fit_status([good, bad], ["friction.coulomb_positive_n"])
    assert status_head(flagged) == "flagged"
    assert "b.csv" in flagged
    assert "friction.coulomb_positive_n" in flagged
    assert "a.csv" not in flagged


@needs_data
def test_axis_fit_as_dict_carries_the_status(limit_fits):
    from prsa_ctrl.results import check_status

    fit = limit_fits[1]  # the example's plant, its force limit just above the logged peak
    d = fit.as_dict()
    assert d["status"] == fit.status == check_status(fit.status)
    assert d["solver_status"] == "converged"
    assert fit.report() == d  # the former name


# ------------------------------------------------------------------------------------------------
# Linear-axis fit (prsa-fit --log-format) with a --plant base: the base's values, description
# and [uncertainty] entries on unfitted keys are kept, a disagreeing drive gain is refused, a
# disagreeing force limit is kept with a warning; FIT.json carries the covariance and correlation
# matrices the plant file's intervals and correlation block come from.
# ------------------------------------------------------------------------------------------------

BASE = """name = "mine"
description = "MY BASE"
mechanism = "linear-axis"
coordinates = "load"
[axis]
mass_kg = {{ value = 70.0, source = "guess" }}
[drive]
gain_n_per_unit = {{ value = {gain}, source = "my base" }}
force_limit_n = {{ value = 500.0, source = "my base limit" }}
command_unit = "V"
[sensor]
sample_time_s = {{ value = 0.001, source = "my base" }}
encoder_resolution_m = {{ value = 5e-8, source = "my base" }}
[uncertainty]
"axis.mass_kg" = {{ dist = "uniform", low = 60.0, high = 80.0, source = "payload" }}
"drive.gain_n_per_unit" = {{ dist = "uniform", relative = 0.05, source = "amplifier tolerance" }}
"""


@pytest.fixture(scope="module")
def logdir(tmp_path_factory):
    d = tmp_path_factory.mktemp("axisbase")
    t, qm, r, u = gen.closed_loop_log(0, n=3000)
    with (d / "log.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["time_ms", "pos_mm", "ref_mm", "u_V"])
        w.writerows(zip(*(map(repr, map(float, a)) for a in (1e3 * t, 1e3 * qm, 1e3 * r, u))))
    (d / "fmt.toml").write_text(gen.CSV_FORMAT)
    return d


def _run(d, gain, tag, capsys):
    (d / f"base-{tag}.toml").write_text(BASE.format(gain=gain))
    out, js = d / f"fit-{tag}.toml", d / f"fit-{tag}.json"
    capsys.readouterr()
    rc = main([str(d / "log.csv"), "--log-format", str(d / "fmt.toml"), "--plant", str(d / f"base-{tag}.toml"),
               "--out", str(out), "--json", str(js)])
    return rc, out, js, capsys.readouterr()


def test_base_values_and_uncertainty_kept_and_covariance_reported(logdir, capsys):
    rc, out, js, cap = _run(logdir, 30.0, "ok", capsys)
    assert rc == 0, cap.err
    doc = tomllib.loads(out.read_text())
    assert doc["description"].startswith("MY BASE")
    assert doc["drive"]["gain_n_per_unit"] == {"value": 30.0, "source": "my base"}
    assert doc["drive"]["force_limit_n"] == {"value": 500.0, "source": "my base limit"}  # base kept ...
    rep = json.loads(js.read_text())
    warn = [w for w in rep["warnings"] if w.startswith("drive.force_limit_n")]
    assert len(warn) == 1
    assert "500" in warn[0]
    assert "300" in warn[0]  # ... with a warning naming both (10 V x 30 N/V)
    assert "warning: drive.force_limit_n" in cap.out
    unc = doc["uncertainty"]
    assert unc["drive.gain_n_per_unit"] == {"dist": "uniform", "relative": 0.05, "source": "amplifier tolerance"}
    assert unc["axis.mass_kg"]["dist"] == "normal"  # a fitted key: the fit's interval replaces the base's entry
    # covariance: the matrix the intervals come from
    cov = rep["covariance"]
    c = np.array(cov["matrix"])
    assert cov["keys"] == list(rep["parameters"])
    assert len(cov["units"]) == len(cov["keys"])
    assert np.allclose(c, c.T)
    for i, k in enumerate(cov["keys"]):
        p = rep["parameters"][k]
        if p.get("kept_base"):  # kept, not fitted: no interval (was a zero-width one)
            assert p["std"] is None
            assert c[i, i] == 0.0
            continue
        assert np.isclose(np.sqrt(c[i, i]), p["std"], rtol=1e-12)
    # correlation: independent from the covariance, and the same as the plant file's block
    keys = rep["correlation"]["keys"]
    idx = [cov["keys"].index(k) for k in keys]
    sub = c[np.ix_(idx, idx)]
    ref = sub / np.sqrt(np.outer(np.diag(sub), np.diag(sub)))
    r = np.array(rep["correlation"]["matrix"])
    assert np.allclose(r, ref, atol=1e-12)
    assert np.allclose(np.diag(r), 1.0)
    assert np.max(np.abs(ref - np.eye(len(keys)))) > 0.05  # the check is not vacuous
    block = unc["correlation"]
    pos = [keys.index(k) for k in block["keys"]]
    assert np.allclose(np.array(block["matrix"]), r[np.ix_(pos, pos)], atol=1e-9)


def test_base_gain_disagreeing_with_the_log_is_refused(logdir, capsys):
    rc, out, js, cap = _run(logdir, 31.0, "bad", capsys)
    assert rc == 2
    line = cap.err.strip()
    assert "\n" not in line
    assert "drive.gain_n_per_unit" in line
    assert "31" in line
    assert "30" in line
    assert not out.exists()
    assert not js.exists()


# ------------------------------------------------------------------------------------------------
# Coverage of the linear-axis fit on 4 kHz closed-loop logs (issue 21: the benchmark's 4 kHz log
# had its fitted 95 % intervals miss the truth).
#
# An independent generator written here (numpy only, nothing of prsa_ctrl): a mass with Coulomb and
# viscous friction per direction and Karnopp stick, integrated exactly per sample (closed-form
# exponential per direction, the stop located in closed form, then stick or breakaway); a 20-bit-like
# encoder (5e-8 m quantum, a random grid phase, Gaussian interpolation noise of 0.3 quantum) whose
# quantised position the controller uses (position P over velocity P, two-sample averaged velocity,
# saturation); moves with random accelerations, lengths and pauses in both directions.
#
# The fast test fits two seeds; the slow one 20 seeds: each key's truth inside its 95 % interval for
# >= 18 of 20 seeds, no bias (mean z within 3 / sqrt(20)).
#
# What the benchmark showed (bench.py ``_axis_log_4khz``): its generator's explicit sub-steps
# biased the mass (fixed there), and on its log of eight moves with one repeated speed profile the
# friction intervals of one direction miss at 2.5-4 standard errors, whichever the encoder grid's
# phase (measured with this generator on that move list: 12 of 12 phases): a bias from the
# encoder quantisation, which is not white while the axis holds one speed or rests, on a
# Coulomb/viscous pair that one speed profile separates only weakly. With varied moves, as here,
# the intervals hold at the nominal rate.
# ------------------------------------------------------------------------------------------------

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
    assert np.max(np.diff(qm)) > 0 > np.min(np.diff(qm))
    assert np.ptp(qm) > 1e-2
    qf = 0.5 * (qm + np.r_[qm[0], qm[:-1]])
    dq = np.diff(np.r_[qf[0], qf]) / H
    np.testing.assert_allclose(u, np.clip(KV * (KP * (r - qm) - dq), -SAT, SAT), rtol=0, atol=1e-9)


@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.slow)])
def test_truth_inside_the_intervals_two_seeds(seed):
    """Every key's truth within 3 standard errors (a wrong model or covariance gives 5..1000;
    the 20-seed rate is the slow test). Seed 0 in the default run, seed 1 with the slow studies
    (the same claim on another seed: an evidence study)."""
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


# ------------------------------------------------------------------------------------------------
# One plant description (issue 21, EMPS): the plant file prsa-fit writes for a linear axis is a
# plant file of the toolkit (schema defaults and sources, load_plant, --show-plant, linearisation,
# simulation), and reports say the coordinates.
# ------------------------------------------------------------------------------------------------

EMPS_MAT = EXAMPLE / "DATA_EMPS.mat"
needs_emps_mat = pytest.mark.skipif(not EMPS_MAT.is_file(), reason="examples/emps/DATA_EMPS.mat not in this checkout")


@pytest.fixture(scope="module")
def fitted(emps_fit):
    """prsa-fit on the EMPS record (tests/conftest.py: one fit per session): (plant file, FIT.json)."""
    assert emps_fit.code == 0, emps_fit.err
    return emps_fit.toml, json.loads(emps_fit.json.read_text())


def test_the_axis_defaults_are_the_schemas():
    assert set(DEFAULTS) == set(PARAMETERS[1:])
    for k, v in DEFAULTS.items():
        assert v == SCHEMA_DEFAULTS[k]


@needs_emps_mat
def test_fitted_file_is_a_toolkit_plant_file(fitted, capsys):
    out, rep = fitted
    assert rep["coordinates"] == "load (position m, force N)"
    assert rep["mechanism"] == "linear-axis"
    axis = load_axis_plant(out)
    plant = load_plant(out)
    assert plant.mechanism == "linear-axis"
    for k, v in axis.values.items():  # the same values and sources through both readers
        assert plant.values[k] == v
        assert plant.sources[k] == axis.sources[k]
    assert plant.values["axis.mass_kg"] == pytest.approx(rep["equivalent"]["mass_kg"]["value"], rel=1e-12)
    assert plant.sources["friction.efficiency"].startswith("derived:")
    assert dict(axis.to_plant().values) == dict(plant.values)
    lines = describe_plant(plant).splitlines()
    assert lines[2] == "coordinates: load (position m, force N)"
    assert describe_plant(load_plant()).splitlines()[2] == "coordinates: motor (angle rad, torque N m)"
    capsys.readouterr()
    assert tune_main(["--show-plant", str(out)]) == 0
    shown = capsys.readouterr().out
    assert "coordinates: load (position m, force N)" in shown
    assert "fit: DATA_EMPS.mat" in shown


@needs_emps_mat
def test_fitted_plant_linearises_and_simulates(fitted):
    out, _ = fitted
    plant = load_plant(out)
    v = plant.values
    names = plant_model(plant, "rigid").state_names
    i_v = names.index("omega_nut")
    for speed, fv in ((1e-3, v["friction.viscous_positive_n_s_per_m"]), (-1e-3, v["friction.viscous_negative_n_s_per_m"])):
        a, b, *_ = linear_core(plant, speed, 0.0, "rigid")
        assert a[i_v, i_v] == pytest.approx(-fv / v["axis.mass_kg"], rel=1e-9)  # m/s per m/s: load coordinates
        assert b[i_v, 1] == pytest.approx(-1.0 / v["axis.mass_kg"], rel=1e-9)  # an axial load of 1 N, against +x
    from prsa_ctrl.drive.pid import PID
    from prsa_ctrl.sim.engine import run

    r = run(plant, setpoint=0.05, load=0.0, duration=0.3, controller=PID(4000.0, 40000.0), fidelity="rigid",
            discrete=True)
    speed = r.states[r.state_labels.index("omega_nut")]
    assert np.all(np.isfinite(speed))
    assert abs(speed[-1] - 0.05) < 0.005  # m/s


@needs_emps_mat
def test_validate_json_names_the_coordinates(fitted, tmp_path, capsys):
    out, _ = fitted
    rj = tmp_path / "R.json"
    capsys.readouterr()
    assert fit_main(["--validate", str(out), str(EMPS_MAT), "--log-format", str(EXAMPLE / "log.toml"), "--json", str(rj)]) == 0
    assert "coordinates: load (position m, force N)" in capsys.readouterr().out
    rep = json.loads(rj.read_text())
    assert rep["coordinates"] == "load (position m, force N)"
    assert rep["mechanism"] == "linear-axis"


def _free_mass_log(tmp_path, f0):
    """(log.csv, fmt.toml) of a free 4 kg mass pushed by +-f0 N (a 2 Hz square wave), 3 s at 1 ms,
    exact over each held sample, with its log description (no [controller])."""
    n, h, m = 3000, 1e-3, 4.0
    t = np.arange(n) * h
    f = f0 * np.sign(np.sin(2 * math.pi * 2.0 * t))
    v, x = np.zeros(n), np.zeros(n)
    for k in range(n - 1):  # a free mass, exact over each held sample
        v[k + 1] = v[k] + f[k] / m * h
        x[k + 1] = x[k] + v[k] * h + 0.5 * f[k] / m * h * h
    path = tmp_path / "log.csv"
    path.write_text("time_s,position_m,speed_m_s,force_n\n"
                    + "".join(f"{a:.17g},{b:.17g},{c:.17g},{d:.17g}\n" for a, b, c, d in zip(t, x, v, f)))
    fmt = tmp_path / "fmt.toml"
    fmt.write_text('format = "csv"\n[time]\nname = "time_s"\nunit = "s"\n[position]\nname = "position_m"\nunit = "m"\n'
                   '[speed]\nname = "speed_m_s"\nunit = "m/s"\n[command]\nname = "force_n"\nunit = "N"\n')
    return path, fmt


def test_a_fit_without_a_controller_writes_a_loadable_plant(tmp_path, capsys):
    """No --plant and no controller: the force limit is estimated from the log (and says so), so the
    written file has every required key."""
    f0 = 2.0
    path, fmt = _free_mass_log(tmp_path, f0)
    out = tmp_path / "F.toml"
    code = fit_main([str(path), "--log-format", str(fmt), "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    plant = load_plant(out)
    assert plant.values["drive.force_limit_n"] == pytest.approx(f0, rel=1e-12)
    assert plant.sources["drive.force_limit_n"].startswith("estimate: largest force in log.csv")
    assert plant.values["axis.mass_kg"] == pytest.approx(4.0, rel=1e-3)  # _free_mass_log's mass


def test_a_tiny_viscous_term_replays_as_none():
    """The stop time of a decelerating axis with a viscous term ``k = Fv/M`` is ``-log1p(k v/a)/k``:
    with ``log(1 + k v/a)`` a tiny ``Fv`` (as a fit at its bound 0 probes it) lost every digit and
    the replay jumped by percent."""
    from prsa_ctrl.identification.axis import simulate_axis
    from prsa_ctrl.identification.logformat import AxisLog

    n, h = 1500, 1e-3
    t = np.arange(n) * h
    f = 2.0 * np.sign(np.sin(2 * math.pi * 2.0 * t))  # accelerate, brake to rest, again
    log = AxisLog("brake", t, np.zeros(n), f, "N", 1.0, h)
    ref = simulate_axis((4.0, 0.0, 0.0, 1e-3, 0.0), log, x0=(0.0, 0.0)).position_m
    for fv in (1e-13, 1e-9):
        x = simulate_axis((4.0, fv, 0.0, 1e-3, 0.0), log, x0=(0.0, 0.0)).position_m
        assert np.max(np.abs(x - ref)) < 1e-9 * np.max(np.abs(ref)) + 1e-3 * fv


def test_validate_plots_the_replay_and_the_frequency_response_beside_the_logs(logdir, capsys):
    """prsa-fit --validate PLANT LOG --plots DIR (linear axis): per log the replay overlay and the
    frequency-response overlay (the log's beside the replay's, Hz axis), both PNG files named."""
    rc, out, _, cap = _run(logdir, 30.0, "plots", capsys)
    assert rc == 0, cap.err
    figs = logdir / "figs-validate"
    rc = main(["--validate", str(out), str(logdir / "log.csv"), "--log-format", str(logdir / "fmt.toml"),
               "--plots", str(figs)])
    text = capsys.readouterr()
    assert rc == 0, text.err
    names = sorted(p.name for p in figs.iterdir())
    assert names == ["replay-1-log.csv.png", "response-1-log.csv.png"], names
    assert all((figs / n).stat().st_size > 10_000 and str(figs / n) in text.out for n in names)


# --- the closed-loop calibration on the independent generator's logs, and the EMPS case ----------

# seed 0 in the default run; seeds 1 and 2, the same claim on other logs, with the slow studies
@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.slow), pytest.param(2, marks=pytest.mark.slow)])
def test_synthetic_closed_loop_log_recovered_within_its_intervals(tmp_path, seed):
    t, qm, r, u = gen.closed_loop_log(seed)
    path = tmp_path / "log.csv"
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["time_ms", "pos_mm", "ref_mm", "u_V"])
        w.writerows(zip((f"{a:.17g}" for a in 1e3 * t), (f"{a:.17g}" for a in 1e3 * qm),
                        (f"{a:.17g}" for a in 1e3 * r), (f"{a:.17g}" for a in u)))
    (tmp_path / "fmt.toml").write_text(gen.CSV_FORMAT)
    log = load_axis_log(path, load_log_format(tmp_path / "fmt.toml"))
    assert log.resolution_m == pytest.approx(gen.RES)
    fit = fit_linear_axis([log], gen.placeholder_base())
    assert (fit.status, fit.solver_status) == ("ok", "converged")  # (status in the vocabulary since issue 33)
    for k, true in zip(PARAMETERS, gen.TRUTH):
        p = fit.parameters[k]
        lo, hi = p["ci95"]
        assert lo <= true <= hi, (k, p)
        assert hi - lo < 0.02 * true, (k, p)  # informative: a broken fit cannot hide behind a wide interval
    assert fit.replays[0].errors_percent["force"] < 1.0


def test_plant_file_round_trip_and_minimal_file(tmp_path):
    # the minimal linear-axis file of the package's plant schema (prsa_ctrl.plant.schema.REQUIRED)
    p = tmp_path / "min.toml"
    p.write_text('mechanism = "linear-axis"\n[axis]\nmass_kg = { value = 12.5, source = "test: given" }\n'
                 '[drive]\ngain_n_per_unit = { value = 2.0, source = "t" }\nforce_limit_n = { value = 50.0, source = "t" }\n'
                 '[sensor]\nsample_time_s = { value = 0.001, source = "t" }\n'
                 'encoder_resolution_m = { value = 1e-6, source = "t" }\n')
    plant = load_axis_plant(p)
    assert plant.values["axis.mass_kg"] == 12.5
    assert plant.sources["friction.coulomb_positive_n"].startswith("default:")
    assert plant.values["drive.force_limit_n"] == 50.0
    q = tmp_path / "again.toml"
    q.write_text(axis_plant_toml(plant))
    again = load_axis_plant(q)
    assert dict(again.values) == dict(plant.values)
    assert dict(again.sources) == dict(plant.sources)


@needs_data
def test_emps_fit_and_validate_end_to_end(tmp_path, capsys, emps_fit):
    """The two commands of examples/emps/README.md: the fit (tests/conftest.py: one per session),
    then its validation on the record."""
    fmt = str(EXAMPLE / "log.toml")
    assert emps_fit.code == 0, emps_fit.err
    out, js = emps_fit.toml, emps_fit.json
    rep = json.loads(js.read_text())
    eq = rep["equivalent"]
    for k in ("mass_kg", "viscous_n_s_per_m", "friction_positive_n", "friction_negative_n"):
        lo, hi = eq[k]["ci95"]
        assert lo < eq[k]["value"] < hi
    assert abs(eq["mass_kg"]["value"] / M_REF - 1) < 0.03
    assert abs(eq["viscous_n_s_per_m"]["value"] / FV_REF - 1) < 0.10
    assert eq["friction_positive_n"]["value"] > 0 > eq["friction_negative_n"]["value"]
    # the friction-law test sees EMPS's friction is not Coulomb + viscous (about 3 N below the line at
    # 3..6 mm/s, measured 0.19 of the Coulomb level) and lets it pass, as the published model has that law
    from prsa_ctrl.identification.axisfriction import FRICTION_DEPARTURE

    entry = next(iter(rep["validation"]["written_plant"].values()))
    assert 0.1 < entry["friction_departure"] < FRICTION_DEPARTURE
    plant = load_axis_plant(out)
    assert plant.sources["axis.mass_kg"].startswith("fit: DATA_EMPS.mat")
    traces, rj = tmp_path / "T.csv", tmp_path / "R.json"
    capsys.readouterr()
    assert main(["--validate", str(out), str(DATA), "--log-format", fmt, "--json", str(rj), "--traces", str(traces)]) == 0
    mine = json.loads(rj.read_text())["replay"][0]["errors_percent"]
    ref = replay_axis(load_axis_plant(EXAMPLE / "reference-model.toml"),
                      load_axis_log(DATA, load_log_format(fmt))).errors_percent
    for k in ("position", "velocity", "force"):
        assert mine[k] <= ref[k], (k, mine, ref)
    with traces.open() as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["time_s", "position_measured", "position_simulated", "force_measured", "force_simulated"]
    assert len(rows) == 24841 + 1


@needs_data
@pytest.mark.slow
def test_held_back_replay_no_worse_than_the_published_model(tmp_path, capsys):
    """Issue 32's acceptance for the EMPS example: fitted on the first 60 % of the record
    (``--holdout 0.4``), the plant replays the held-back 40 % no worse than the published model
    replays the same samples (position, velocity, force; README: 0.00080 / 0.130 / 3.78 % against
    0.00106 / 0.134 / 4.70 %)."""
    fmt = str(EXAMPLE / "log.toml")
    js = tmp_path / "h.json"
    assert main([str(DATA), "--log-format", fmt, "--holdout", "0.4", "--out", str(tmp_path / "h.toml"),
                 "--json", str(js)]) == 0, capsys.readouterr().err
    held = json.loads(js.read_text())["holdout"]["replay"][0]
    log = load_axis_log(DATA, load_log_format(fmt))
    start = log.n - int(round(0.4 * log.n))
    assert held["log"].endswith(f"[{start}:{log.n}]")
    ref = replay_axis(load_axis_plant(EXAMPLE / "reference-model.toml"), log.window(start, log.n)).errors_percent
    mine = held["errors_percent"]
    for k in ("position", "velocity", "force"):
        assert mine[k] <= ref[k], (k, mine, ref)
    assert ref["force"] == pytest.approx(4.705, abs=0.005)
    assert mine["force"] == pytest.approx(3.778, abs=0.01)


@needs_data
def test_published_model_replay_and_the_benchmarks_own_convention():
    """This code's replay of the published model, and the benchmark's published replay errors
    (position 0.0138 %, velocity 0.229 %, force 5.85 %) reproduced with the benchmark script's
    conventions: the command applied one sample after it is computed, compared as applied, and a
    simulation sample time of t(10) - t(9) = 0.99998 ms against the logged time base."""
    fmt = load_log_format(EXAMPLE / "log.toml")
    log = load_axis_log(DATA, fmt)
    ref = load_axis_plant(EXAMPLE / "reference-model.toml")
    e = replay_axis(ref, log).errors_percent
    assert e["position"] == pytest.approx(0.001085, rel=0.02)
    assert e["velocity"] == pytest.approx(0.1244, rel=0.02)
    assert e["force"] == pytest.approx(4.571, rel=0.01)
    tec = float(log.time_s[9] - log.time_s[8])
    r_on_sim_clock = np.interp(np.arange(log.n) * tec, log.time_s, log.reference_m)
    bench = dataclasses.replace(
        log, reference_m=r_on_sim_clock, sample_time_s=tec, command_logged="as-applied",
        controller=dataclasses.replace(log.controller, command_delay_samples=1, sample_time_s=tec))
    tr = simulate_axis(ref.theta, bench, x0=(0.0, 0.0))
    vm = measured_velocity(log)
    assert relative_error(log.position_m, tr.position_m) == pytest.approx(0.0138, abs=0.0005)
    assert relative_error(vm, tr.velocity_m_s) == pytest.approx(0.229, abs=0.001)
    assert relative_error(log.force_n, log.gain_n_per_unit * tr.command) == pytest.approx(5.85, abs=0.01)


def test_an_unstable_replay_raises_a_clear_error_not_nan():
    n = 2000
    t = np.arange(n) * gen.H
    r = np.where(t > 0.01, 0.01, 0.0)
    ctl = ControllerSpec("position-p/velocity-p", 150.0, 250.0, 0.0, "difference", math.inf, gen.H)
    log = AxisLog("unstable", t, np.zeros(n), np.zeros(n), "V", gen.GAIN, gen.H, reference_m=r, controller=ctl)
    with pytest.raises(SimulationError, match="diverged at t ="):
        simulate_axis((0.01, 0.0, 0.0, 0.0, 0.0), log)  # 10 g behind a loop tuned for 80 kg


def test_a_log_described_one_sample_off_is_detected():
    t, qm, r, u = gen.closed_loop_log(5, n=4000)
    wrong = ControllerSpec("position-p/velocity-p", gen.KP, gen.KV, 0.0, "average2-difference", 10.0, gen.H,
                           command_delay_samples=1)
    log = AxisLog("syn", t, qm, u, "V", gen.GAIN, gen.H, reference_m=r, controller=wrong)
    fit = fit_linear_axis([log], gen.placeholder_base())
    costs = fit.delay_costs
    assert set(costs) == {0, 1, 2}
    assert min(costs, key=costs.get) == 0
    assert any("command delay of 0 samples fits better than the described 1" in w for w in fit.warnings)
    right = fit_linear_axis([dataclasses.replace(log, controller=dataclasses.replace(wrong, command_delay_samples=0))],
                            gen.placeholder_base())
    assert not any("command delay" in w for w in right.warnings)


def test_a_test_signal_at_the_drive_input_is_replayed(tmp_path):
    """A cross-test-like record: a 0/2 V pulse train (period 0.5 s) added to the controller output
    at the drive input, logged inside the command and in its own column."""
    n = 3000
    pulses = np.where((np.arange(n) * gen.H) % 0.5 < 0.1, 2.0, 0.0)
    t, qm, r, u = gen.closed_loop_log(7, n=n, pulses=pulses)
    mat = tmp_path / "pulses.mat"
    savemat(mat, {"t": t[:, None], "qm": qm[:, None], "qg": r[:, None], "vir": u[:, None],
                           "pulses_N": pulses[:, None], "gtau": gen.GAIN, "kp": gen.KP, "kv": gen.KV})
    log = load_axis_log(mat, load_log_format(EXAMPLE / "log.toml"))
    assert log.test_signal is not None
    assert log.test_signal.max() == 2.0
    truth = gen.placeholder_base().with_values(dict(zip(PARAMETERS, gen.TRUTH)), {k: "test: truth" for k in PARAMETERS})
    with_pulses = replay_axis(truth, log).errors_percent
    without = replay_axis(truth, dataclasses.replace(log, test_signal=None)).errors_percent
    assert with_pulses["force"] < 0.5
    assert with_pulses["velocity"] < 0.5
    assert without["force"] > 10 * with_pulses["force"]


@needs_data
def test_a_fitted_mass_outside_the_users_bounds_is_named_and_written_with_the_fits_entry(emps_log, tmp_path):
    """A base whose [uncertainty] bounds for the mass (98..110 kg around its 100 kg) exclude what
    the EMPS data say (95.1 kg published): one warning names the key, its interval and the bounds
    as typed; the written file carries the fit's entry and loads."""
    base = load_axis_plant(EXAMPLE / "plant.toml")
    typed = {"dist": "uniform", "low": 98, "high": 110, "source": "assumption: too sure"}
    base = dataclasses.replace(base, uncertainty={"axis.mass_kg": typed})
    fit = fit_linear_axis([emps_log], base, check_delay=False)
    m = fit.plant.values["axis.mass_kg"]
    assert not 98 <= m <= 110  # the premise: the data contradict the stated range
    (line,) = [w for w in fit.warnings if w.startswith("axis.mass_kg = ")]
    assert "outside the base plant's [uncertainty] entry (uniform low = 98, high = 110)" in line
    path = tmp_path / "fitted.toml"
    path.write_text(axis_plant_toml(fit.plant), encoding="utf-8")
    back = load_axis_plant(path)
    entry = back.uncertainty["axis.mass_kg"]
    assert entry["source"].startswith("fit: ")
    assert entry["truncate"] * entry["sigma"] > 0


def test_a_linear_axis_report_carries_the_described_delay_as_given(logdir, capsys):
    """Issue 32 ("a report that is true"): the linear-axis fit's JSON and text state the command
    delay in the delay vocabulary (they had no delay record): the log description's
    [controller] command_delay_samples, "given", with the fit's check of its neighbours."""
    from prsa_ctrl.identification.delay import delay_status_head

    described = load_axis_log(logdir / "log.csv", load_log_format(logdir / "fmt.toml")).controller.command_delay_samples
    rc, out, js, cap = _run(logdir, 30.0, "delay", capsys)
    assert rc == 0, cap.err
    cd = json.loads(js.read_text())["command_delay"]
    assert delay_status_head(cd["status"]) == "given"
    assert cd["drive_command_delay_samples"] == described
    assert "[controller] command_delay_samples" in cd["how"]
    assert f"{described + 1}: " in cd["how"]  # a neighbour the fit checked
    line = next(ln for ln in cap.out.splitlines() if ln.startswith("command delay:"))
    assert line.endswith("; given)")


def test_a_linear_axis_log_without_a_controller_leaves_the_delay_undecided(tmp_path, capsys):
    # no [controller]: the replay takes the logged force to act at once; nothing decided that, and the record says so
    from prsa_ctrl.identification.delay import delay_status_head

    path, fmt = _free_mass_log(tmp_path, 2.0)
    js = tmp_path / "F.json"
    assert fit_main([str(path), "--log-format", str(fmt), "--out", str(tmp_path / "F.toml"), "--json", str(js)]) == 0
    cd = json.loads(js.read_text())["command_delay"]
    assert delay_status_head(cd["status"]) == "undecided"
    assert "no [controller] command_delay_samples" in cd["status"]
    assert cd["drive_command_delay_samples"] == 0
    assert "command delay: 0 sample(s) (not described" in capsys.readouterr().out
