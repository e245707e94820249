"""The band-limited FRF fit (prsa_ctrl.identification.frfband, prsa-fit --frf-band): on the third
generator's responses (tests/identification/foreign/gen_third.py: an axial mode and a coupling
mode above it, physics the models lack) the band the refusal names gives the judge's numbers
(the total inertia within 3 % with the truth inside its interval, the mode within 5 %, the
current loop within 25 %, the delay exact); without it the refusal names the band; a band
that holds both modes is refused; bad bands are bad input; a band over every point changes
nothing."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from prsa_ctrl.errors import FitError
from prsa_ctrl.identification.calibrate import calibrate_frf
from prsa_ctrl.identification.frfband import parse_band

from foreign import gen_third as g3


@pytest.fixture(scope="module")
def third(tmp_path_factory):
    return {n: g3.generate(tmp_path_factory.mktemp(n), n, seed=0, experiments=(), frf=True) for n in g3.CASES}


def _cal(s, **kw):
    t = s["truth"]
    return calibrate_frf([s["frf"]], str(s["base"]), name="fitted", speed_rad_s=t["frf_speed_rad_s"],
                         load_n=t["frf_load_n"], command_logged=t["command_logged"], **kw)


def _refusal_band(s):
    with pytest.raises(FitError) as ei:
        _cal(s)
    msg = str(ei.value)
    m = re.search(r"--frf-band ([0-9.e+-]+),([0-9.e+-]+)$", msg)
    assert m, msg
    return msg, float(m.group(1)), float(m.group(2))


@pytest.mark.parametrize("name", list(g3.CASES))
def test_the_refusal_names_the_band_that_leaves_the_second_mode_out(third, name):
    s = third[name]
    t = s["truth"]
    msg, lo, hi = _refusal_band(s)
    assert "2 resonances" in msg
    f = np.loadtxt(s["frf"], delimiter=",", skiprows=1)
    kept = f[f[:, 3] >= 0.8, 0]  # (the points the default --coherence-min keeps)
    assert lo <= kept.min()
    # the band holds the first axial mode and its anti-resonance, and ends well below the coupling's mode
    assert 1.5 * t["first_mode_hz"] < hi < math.sqrt(t["first_mode_hz"] * t["second_mode_hz"]) * 1.05
    assert hi < 0.5 * t["second_mode_hz"]


@pytest.mark.parametrize("fidelity", [None, "compliant"])
@pytest.mark.parametrize("name", list(g3.CASES))
def test_the_band_fit_meets_the_judges_rule(third, name, fidelity):
    """The band the refusal named: exit-0 numbers within the judge's rule
    (tests/identification/test_foreign_generators.py::_acceptance)."""
    s = third[name]
    t = s["truth"]
    _, lo, hi = _refusal_band(s)
    typed = f"{lo:g},{hi:g}"
    cal = _cal(s, fidelity=fidelity, band=parse_band(typed), typed={"--frf-band": repr(typed)})
    assert cal.failure is None
    assert cal.plant_text is not None
    r = cal.result.reflected_inertia_kg_m2
    jt = t["reflected_inertia_kg_m2"]
    assert abs(r["value"] / jt - 1) < 0.03, (r, jt)
    assert r["ci95"][0] <= jt <= r["ci95"][1], (r, jt)
    pv = cal.result.plant.values
    assert abs(pv["drive.current_loop_bandwidth_hz"] / t["drive.current_loop_bandwidth_hz"] - 1) <= 0.25
    assert pv["drive.command_delay_samples"] == t["drive.command_delay_samples"]
    mode = cal.report["axial_mode_hz"]["value"]
    assert abs(mode / t["first_mode_hz"] - 1) < 0.05
    # the mode the response shows, with its interval
    fm = cal.report["frf_axial_mode_hz"]
    assert fm["ci95"][0] < fm["value"] < fm["ci95"][1]
    assert abs(fm["value"] / t["first_mode_hz"] - 1) < 0.05
    # the band and the omitted coupling mode are in the report, the lines and the written sources
    band = cal.report["frf_band"]
    assert band["band_hz"] == [lo, hi]
    (om,) = band["omitted"]
    assert om["side"] == "above"
    assert abs(om["frequency_hz"] / t["second_mode_hz"] - 1) < 0.15
    assert cal.lines[0].startswith(f"band: {lo:g}..{hi:g} Hz")
    assert "omitted by the model" in cal.lines[1]
    assert any("fit %, the intervals and the structure test are the band's" in w for w in cal.result.warnings)
    src = cal.result.plant.sources["axis.motor_inertia_kg_m2"]
    assert f"in the band {lo:g}..{hi:g} Hz" in src
    assert "omits the response's resonance near" in src
    assert f"in the band {lo:g}..{hi:g} Hz" in cal.plant_text
    # the current loop is held at the base value, and said why
    assert any("not refitted to the band" in w for w in cal.result.warnings) == (cal.choice.structure == "two-mass")
    assert any(w.startswith("drive.current_loop_bandwidth_hz kept at the base value") and "not identified in the band"
               in w for w in cal.result.warnings)
    # the fit % is on the band's points only (a fit over the coupling mode would not reach it)
    (pct,) = cal.result.fit_percent.values()
    assert pct > 90.0


@pytest.mark.parametrize("name", list(g3.CASES))
def test_a_band_that_holds_both_modes_is_refused(third, name):
    s = third[name]
    t = s["truth"]
    top = 1.5 * t["second_mode_hz"]  # (both modes and the falling side of the second inside)
    with pytest.raises(FitError, match="2 resonances"):
        _cal(s, band=(0.0, top))


def test_bad_bands_are_bad_input(third):
    s = third["ball-40x16"]
    for text, words in (("300,100", "not below"), ("100,100", "not below"), ("1", "expected two frequencies"),
                        ("a,3", "'a' is not a number"), ("-1,300", "FMIN = -1; expected a finite number >= 0 Hz"),
                        ("nan,300", "FMIN = nan; expected"), ("1,inf", "FMAX = inf; expected"),
                        ("1,1e400", "FMAX = 1e400; expected")):
        with pytest.raises(ValueError, match=re.escape(words)) as ei:
            parse_band(text)
        assert str(ei.value).startswith(f"--frf-band {text!r}: ")  # (was '--frf-band = ...' for nan, inf, -1)
        assert "\n" not in str(ei.value)
    for band, words in (((5000.0, 6000.5), "no point of the responses"), ((100.0, 120.0), "expected at least 16"),
                        ((200.0, 1700.0), "lies below the band")):
        typed = f"{band[0]:g},{band[1]:g}"
        with pytest.raises(ValueError, match=re.escape(words)) as ei:
            _cal(s, band=band, typed={"--frf-band": repr(typed)})
        assert str(ei.value).startswith(f"--frf-band {typed!r}: ")


def _one_resonance_bode(tmp_path):
    """The FRF file of an independent two-mass axis (tests/independent_actuator.py) with one
    resonance, on the ball screw's base plant, continuous (sample time 0), 3..1500 Hz."""
    from prsa_ctrl import load_plant
    from prsa_ctrl.identification.data import frf_from_arrays

    from independent_actuator import modal_damper, two_mass_eom_response

    base = load_plant("ballscrew-32x10")
    a = base.lead_per_rad
    j0 = base.reflected_inertia_kg_m2
    jm, jl = 0.7 * j0, 0.4 * j0
    fa = math.sqrt(0.5 * base.axial_stiffness_n_per_m() * a * a / jl) / (2 * math.pi)
    k = jl * (2 * math.pi * fa) ** 2
    f = np.geomspace(3.0, 1500.0, 160)
    rng = np.random.default_rng(5)
    g = two_mass_eom_response(f, jm, jl, k, modal_damper(k, jm, jl, 0.04), fc_hz=1100.0)
    g = g * np.exp(0.01 * (rng.standard_normal(len(f)) + 1j * rng.standard_normal(len(f))))
    path = tmp_path / "bode.csv"
    frf_from_arrays("two-mass", f, g, sample_time_s=0.0).to_csv(path)
    return path


def test_a_band_over_every_point_changes_nothing(tmp_path):
    """One resonance (an independent two-mass axis, tests/independent_actuator.py): a band that
    covers every point gives the same plant file and report, bit for bit."""
    path = _one_resonance_bode(tmp_path)
    plain = calibrate_frf([path], "ballscrew-32x10", name="fitted", sample_time_s=0.0)
    banded = calibrate_frf([path], "ballscrew-32x10", name="fitted", sample_time_s=0.0, band=(0.0, 2000.0))
    assert plain.plant_text == banded.plant_text
    assert json.dumps(plain.report, sort_keys=True, default=str) == json.dumps(banded.report, sort_keys=True, default=str)
    assert plain.lines == banded.lines



def test_a_band_below_every_resonance_is_reported_after_the_compliant_refit(tmp_path):
    """A band that leaves out only the points above 1000 Hz (no resonance above it, so the
    plant's own compliant model is refitted to the two-mass mapping): the report and its lines
    still name the band (the refit's solver dropped it, so neither did)."""
    banded = calibrate_frf([_one_resonance_bode(tmp_path)], "ballscrew-32x10", name="fitted", sample_time_s=0.0,
                           band=(0.0, 1000.0))
    assert banded.report["frf_band"]["band_hz"] == [0.0, 1000.0]
    assert any(line.startswith("band: 0..1000 Hz") for line in banded.lines)

@pytest.mark.slow
@pytest.mark.parametrize("name", list(g3.CASES))
def test_the_band_fit_over_20_seeds(tmp_path, name):
    """Seeds 0..19 of the third generator, the band each refusal names: the judge's rule every
    time, and the interval of the mode the response shows (the two-mass model with the upper
    residual) holds the three-body truth in at least 17 of 20 (binomial at p = 0.95: P(X <= 16)
    = 1.6 %). Measured (h14-band): the rule 20 of 20 on both cases, the interval 20 of 20; the
    inertia -0.78..-0.88 % (ball) and -1.21..-1.55 % (roller)."""
    hits = 0
    for seed in range(20):
        s = g3.generate(tmp_path / str(seed), name, seed=seed, experiments=(), frf=True)
        t = s["truth"]
        _, lo, hi = _refusal_band(s)
        cal = _cal(s, band=(lo, hi))
        r = cal.result.reflected_inertia_kg_m2
        jt = t["reflected_inertia_kg_m2"]
        assert abs(r["value"] / jt - 1) < 0.03, (seed, r, jt)
        assert r["ci95"][0] <= jt <= r["ci95"][1], (seed, r, jt)
        pv = cal.result.plant.values
        assert abs(pv["drive.current_loop_bandwidth_hz"] / t["drive.current_loop_bandwidth_hz"] - 1) <= 0.25, seed
        assert pv["drive.command_delay_samples"] == t["drive.command_delay_samples"], seed
        assert abs(cal.report["axial_mode_hz"]["value"] / t["first_mode_hz"] - 1) < 0.05, seed
        fm = cal.report["frf_axial_mode_hz"]
        hits += fm["ci95"][0] <= t["first_mode_hz"] <= fm["ci95"][1]
    assert hits >= 17, hits


@pytest.mark.parametrize("name", list(g3.CASES))
def test_a_band_that_starts_at_the_first_mode_is_refused(third, name):
    """A band from the first mode's peak, or from between it and its anti-resonance (two-mass
    estimate from the truth, f sqrt(J_m / J)), holds the peak but not the trough below it: the
    response at its lowest points is the motor side's alone, as above a mode left out below the
    band (was: exit 0 from the peak, 'no key identifiable' on the ball screw and the delay and
    current loop written from the mode's upper side; exit 3 from between, for another reason)."""
    from prsa_ctrl.identification.frfcheck import resonances
    from prsa_ctrl.identification.data import load_frf

    s = third[name]
    _, _, hi = _refusal_band(s)
    first = resonances(load_frf(s["frf"]))[0]["frequency_hz"]
    t = s["truth"]
    anti = t["first_mode_hz"] * math.sqrt(t["motor_side_inertia_kg_m2"] / t["reflected_inertia_kg_m2"])
    for lo in (first, 0.97 * first, 0.5 * (anti + first)):  # (from between: was exit 3 for another reason)
        typed = f"{lo:g},{hi:g}"
        with pytest.raises(ValueError, match="not the anti-resonance below it") as ei:
            _cal(s, band=(lo, hi), typed={"--frf-band": repr(typed)})
        msg = str(ei.value)
        assert msg.startswith(f"--frf-band {typed!r}: ")
        assert "\n" not in msg
