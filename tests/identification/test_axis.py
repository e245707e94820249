"""The linear-axis fit (prsa_ctrl.identification.axis): its inputs checked before any replay."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from prsa_ctrl.cli.fit import main
from prsa_ctrl.identification.axis import fit_linear_axis, load_axis_plant, logged_force_peak
from prsa_ctrl.identification.logformat import load_axis_log, load_log_format

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "emps"
_CANDIDATES = [ROOT.parent / "shared" / "data" / "emps" / "DATA_EMPS.mat", EXAMPLE / "DATA_EMPS.mat"]
DATA = next((p for p in _CANDIDATES if p.is_file()), None)
needs_data = pytest.mark.skipif(DATA is None, reason="EMPS data absent (../shared/data/emps/ or examples/emps/)")


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
    assert 150.0 < peak < 155.0 and where == emps_log.name  # the EMPS record peaks at 152.05 N


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
    assert f"--plant {base}" in err and f"drive.force_limit_n = {limit:g} N" in err
    assert "152.05 N" in err and "DATA_EMPS.mat" in err
    assert not out.exists()


@needs_data
def test_a_force_limit_above_the_logged_forces_fits_as_without_a_limit(emps_log, tmp_path):
    """A limit the log never reaches must not change the fit (the drive applied every logged force)."""
    peak, _ = logged_force_peak([emps_log])
    base = load_axis_plant(_base_with_limit(tmp_path, 351.5065188248547))
    unlimited = dataclasses.replace(base, values={**base.values, "drive.force_limit_n": math.inf})
    just_above = dataclasses.replace(base, values={**base.values, "drive.force_limit_n": peak * 1.001})
    a = fit_linear_axis([emps_log], unlimited, check_delay=False)
    b = fit_linear_axis([emps_log], just_above, check_delay=False)
    for k, v in a.parameters.items():
        lo, hi = v["ci95"]
        assert abs(b.parameters[k]["value"] - v["value"]) < 0.01 * (hi - lo), k
    assert 95.0 < a.parameters["axis.mass_kg"]["value"] < 95.7  # the published 95.11 kg within the fit's interval


def test_a_coulomb_interval_reaching_zero_is_written_inside_the_range(tmp_path):
    """The fitted entry of a friction key whose interval reaches 0: its truncation is rounded
    inward (was round(trunc, 6), here 1.234568 sigma: a support from -1e-07 N, file refused)."""
    import tomllib

    from prsa_ctrl.identification.axis import _normal_entry, axis_plant_toml

    value, sigma = 1.2345679, 1.0
    assert value - round(value / sigma * (1 - 1e-9), 6) * sigma < 0  # what the old rule wrote
    entry = _normal_entry(value, sigma, False, "fit: test")
    assert entry["truncate"] == 1.234567 and value - entry["truncate"] * sigma >= 0
    assert _normal_entry(value, 0.0, False, "fit: test") is None
    assert _normal_entry(0.05, 1.0, False, "fit: test") is None  # < 0.1 sigma above the bound
    base = load_axis_plant(EXAMPLE / "plant.toml")
    plant = dataclasses.replace(base, values={**base.values, "friction.coulomb_negative_n": value},
                                uncertainty={"friction.coulomb_negative_n": entry})
    p = tmp_path / "fitted.toml"
    p.write_text(axis_plant_toml(plant))
    back = load_axis_plant(p)  # the file reader checks the support against the key's range
    assert tomllib.loads(p.read_text())["uncertainty"]["friction.coulomb_negative_n"]["truncate"] == 1.234567
    assert back.uncertainty["friction.coulomb_negative_n"]["truncate"] == 1.234567


def test_the_screw_fit_entries_never_cross_the_range():
    """The motor-coordinate fit's entries (identification.common) round inward too."""
    from prsa_ctrl.identification.common import _uncertainty_entries
    from prsa_ctrl.plant.plantfile import load_plant

    plant = load_plant("paper-iprsm")
    key = "friction.viscous_n_m_s_per_rad"  # non-negative
    value, sd = 1.2345679e-4, 1e-4
    assert value - round(value / sd * (1 - 1e-9), 6) * sd < 0  # what the old rule wrote
    fitted = plant.with_params({key: value})
    out = _uncertainty_entries(fitted, {key: {"value": value, "ci95": [value - 1.96 * sd, value + 1.96 * sd]}},
                               "t.csv", [sd])
    e = out[key]
    assert e["dist"] == "normal" and value - e["truncate"] * e["sigma"] >= 0 and e["truncate"] == 1.234567
    fitted.with_params({key: value - e["truncate"] * e["sigma"]})  # the support's end is a valid plant


@needs_data
def test_refitting_with_the_own_fitted_plant_as_base_is_written(tmp_path, capsys):
    """Was: exit 2 after the whole fit, "'axis.mass_kg' appears twice (in two blocks)"."""
    import tomllib

    fmt = str(EXAMPLE / "log.toml")
    first, second = tmp_path / "first.toml", tmp_path / "second.toml"
    assert main([str(DATA), "--log-format", fmt, "--plant", str(EXAMPLE / "plant.toml"), "--out", str(first)]) == 0
    capsys.readouterr()
    code = main([str(DATA), "--log-format", fmt, "--plant", str(first), "--out", str(second)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    a, b = (tomllib.loads(p.read_text()) for p in (first, second))
    corr = b["uncertainty"]["correlation"]
    assert isinstance(corr, dict) and sorted(corr["keys"]) == sorted(a["uncertainty"]["correlation"]["keys"])
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
    assert "b.csv" in flagged and "friction.coulomb_positive_n" in flagged and "a.csv" not in flagged


@needs_data
def test_axis_fit_as_dict_carries_the_status(emps_log):
    from prsa_ctrl.results import check_status

    fit = fit_linear_axis([emps_log], load_axis_plant(EXAMPLE / "plant.toml"), check_delay=False)
    d = fit.as_dict()
    assert d["status"] == fit.status == check_status(fit.status)
    assert d["solver_status"] == "converged"
    assert fit.report() == d  # the former name
