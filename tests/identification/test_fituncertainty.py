"""A fitted value outside the base plant's [uncertainty] support: evidence, said in one line,
and never a plant file that does not load (the fit's entry, or none)."""

import tomllib
import warnings

import pytest

from prsa_ctrl import load_plant
from prsa_ctrl.identification.calibrate import fitted_plant_text
from prsa_ctrl.identification.fituncertainty import entry_support, hold_written_values, uncertainty_choice
from prsa_ctrl.identification.synthetic import FIT_TRUTH, fit_record
from prsa_ctrl.identification.timedomain import fit_plant
from prsa_ctrl.plant.plantfile import Plant, plant_file_path
from prsa_ctrl.plant.uncertainty import plant_uncertainty

BW = "drive.current_loop_bandwidth_hz"
J = "nut.inertia_kg_m2"


def _plant(values=None, uncertainty=None):
    p = load_plant()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        q = p.with_params(values or {})
        return Plant(name=q.name, values=q.values, sources=q.sources, description=q.description,
                     uncertainty={**p.uncertainty, **(uncertainty or {})}, mechanism=q.mechanism,
                     defaulted=q.defaulted)


def test_the_paper_plants_bandwidth_entry_has_absolute_bounds():
    # the premise of the bug: an entry that does not move with the value
    p = _plant({BW: 85.3479})
    entry = p.uncertainty[BW]
    assert {"low", "high"} <= set(entry)
    assert not entry["low"] <= 85.3479 <= entry["high"]
    assert entry_support(p, BW, entry) is None
    assert entry_support(_plant(), BW, entry) == (entry["low"], entry["high"])


def test_a_written_value_outside_the_support_gets_the_fits_entry_or_none():
    p = _plant({BW: 85.3479})
    typed = p.uncertainty[BW]
    ci = {BW: {"ci95": [40.0, 130.0]}}
    fit_entry = {"dist": "normal", "sigma": 22.96, "truncate": 1.959963984540054, "source": "fit: x.csv"}
    held, notes = hold_written_values(p, None, ci, {BW: fit_entry})
    assert held.uncertainty[BW] == fit_entry
    (note,) = notes  # one line: the key, the value with its interval, the support as typed
    assert note.startswith(f"{BW} = 85.3479 (95 % CI 40..130) is outside the base plant's [uncertainty] entry")
    assert f"low = {typed['low']!r}, high = {typed['high']!r}" in note
    assert "\n" not in note
    assert plant_uncertainty(held).entries  # loads: every support holds its value
    # the fit has no entry for it (a kept key, a degenerate interval): no entry rather than a false one
    dropped, notes = hold_written_values(p, [BW], {}, {})
    assert BW not in dropped.uncertainty
    assert "no [uncertainty] entry written" in notes[0]
    assert {u.key for u in plant_uncertainty(dropped).entries} == set(p.uncertainty) - {BW}
    # the entries that hold their values are left alone, and so is a plant without a conflict
    assert {k: v for k, v in dropped.uncertainty.items()} == {k: v for k, v in p.uncertainty.items() if k != BW}
    same, none = hold_written_values(_plant(), None, {}, {})
    assert none == []
    assert same.uncertainty == _plant().uncertainty


def test_uncertainty_choice_never_keeps_an_entry_that_misses_the_value():
    """Was: with a degenerate fit interval the user's entry was kept even where its absolute
    bounds missed the fitted value (a file that does not load)."""
    p = _plant({BW: 85.3479})
    entry, note = uncertainty_choice(p, BW, p.uncertainty[BW], None, [85.0, 85.7], (10.0, 1e4), "keep")
    assert entry is None
    assert note.startswith(f"{BW} = 85.3479 (95 % CI 85..85.7) is outside")
    fit_entry = {"dist": "uniform", "low": 80.0, "high": 90.0, "source": "fit"}
    entry, note = uncertainty_choice(p, BW, p.uncertainty[BW], fit_entry, [80.0, 90.0], (10.0, 1e4), "keep")
    assert entry is fit_entry
    assert "the fit's entry is written instead" in note


def test_a_fit_outside_the_users_support_writes_a_file_that_loads(tmp_path):
    """A base plant whose [uncertainty] support for the inertia excludes the truth (the user's
    range is wrong): the fitted inertia is the truth's, its entry the fit's, the warning names it,
    and the file written loads with every entry holding its value."""
    rec, truth = fit_record(0.3, seed=2)
    lo, hi = 1.8e-4, 2.4e-4  # around the base's 2e-4; the truth is 1.5e-4 (the other keys the truth's)
    base = _plant({**FIT_TRUTH, J: 2e-4}, {J: {"dist": "uniform", "low": lo, "high": hi, "source": "assumption: wrong"}})
    assert not lo <= FIT_TRUTH[J] <= hi
    res = fit_plant([rec], base, keys=[J])
    value = res.plant.values[J]
    ci = res.parameters[J]["ci95"]
    assert ci[0] <= FIT_TRUTH[J] <= ci[1]
    assert ci[1] < lo  # the data contradict the stated range
    notes = [w for w in res.warnings if w.startswith(f"{J} = ") and "outside the base plant's" in w]
    assert len(notes) == 1
    assert f"{value:.6g}" in notes[0]
    assert "low = 0.00018, high = 0.00024" in notes[0]
    entry = res.plant.uncertainty[J]
    assert entry["source"].startswith("fit: ")
    text = fitted_plant_text(res, base, plant_file_path().read_text(encoding="utf-8"), "fitted", rec.name)
    path = tmp_path / "fitted.toml"
    path.write_text(text, encoding="utf-8")
    back = load_plant(str(path))
    assert back.values[J] == pytest.approx(value, rel=1e-12)
    (u,) = [u for u in plant_uncertainty(back).entries if u.key == J]
    assert u.low <= value <= u.high
    assert u.low <= FIT_TRUTH[J] <= u.high
    assert tomllib.loads(text)["uncertainty"][J]["source"].startswith("fit: ")
