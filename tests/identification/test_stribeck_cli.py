"""prsa-fit with the Stribeck keys (issue 21 part 2): values with intervals in the text and --json,
the fitted plant file carries them with "fit: ..." sources and loads; a log without low-speed
plateaus reports them not identifiable in one warning line and keeps the base values."""

from __future__ import annotations

import json
import tomllib
import warnings
from pathlib import Path

import pytest

from prsa_ctrl.cli.fit import main, plant_toml
from prsa_ctrl.identification.data import record_from_arrays
from prsa_ctrl.plant import load_plant
from prsa_ctrl.plant.plantfile import plant_file_path

import foreign_generator as fg  # noqa: E402  (tests/identification is on sys.path)

KEYS = "friction.static,friction.stribeck_velocity_m_s,friction.no_load_breakaway_torque_n_m"


@pytest.fixture(scope="module")
def base():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_plant()


def _csv(base, tmp_path, log):
    path = tmp_path / f"{log.name}.csv"
    record_from_arrays(log.name, log.time_s, log.command_n_m, nut_angle_rad=log.angle_rad,
                       axial_load_n=log.load_n).to_csv(path)
    return str(path)


def _truth_plant_file(base, ax, tmp_path):
    """The base plant file with the generator's other friction keys (what a time-domain fit gives)."""
    held = {"friction.efficiency": ax.efficiency, "friction.no_load_torque_n_m": ax.no_load_torque_n_m,
            "friction.viscous_n_m_s_per_rad": ax.viscous_n_m_s_per_rad,
            "friction.torque_offset_n_m": ax.offset_torque_n_m}
    plant = base.with_params(held)
    text = plant_toml(Path(plant_file_path()).read_text(), plant, "held", list(held))
    path = tmp_path / "held.toml"
    path.write_text(text)
    return str(path)


def test_prsa_fit_stribeck_keys(base, tmp_path, capsys):
    ax = fg.Axis(lead_m_per_rad=base.lead_per_rad, counts_per_rev=base.encoder_counts)
    data = _csv(base, tmp_path, fg.low_speed_log(ax, 0))
    out, js = tmp_path / "fitted.toml", tmp_path / "r.json"
    plant = _truth_plant_file(base, ax, tmp_path)
    assert main([data, "--plant", plant, "--fit", KEYS, "--out", str(out), "--json", str(js)]) == 0
    text = capsys.readouterr().out
    for k in KEYS.split(","):
        assert f"{k} = " in text and "(95 % CI " in text
    assert "friction map: 22 steady-speed plateau(s)" in text and "conditional on the base plant" in text
    report = json.loads(js.read_text())
    doc = tomllib.loads(out.read_text())
    for k in KEYS.split(","):
        p = report["parameters"][k]
        assert p["kept_base"] is False and p["ci95"][0] < p["value"] < p["ci95"][1]
        section, sub = k.split(".")
        assert doc[section][sub]["value"] == pytest.approx(p["value"], rel=1e-12)
        assert doc[section][sub]["source"].startswith(f"fit: {data} (95 % CI")
    assert len(report["solver"]["friction_map"]["plateaus"]) == 22
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fitted = load_plant(out)
    assert fitted.values["friction.no_load_breakaway_torque_n_m"] > fitted.values["friction.no_load_torque_n_m"]


def test_prsa_fit_without_low_speed_plateaus(base, tmp_path, capsys):
    ax = fg.Axis(lead_m_per_rad=base.lead_per_rad, counts_per_rev=base.encoder_counts)
    data = _csv(base, tmp_path, fg.simulate(ax, *fg.staircase(6000, ax.sample_time_s), seed=1, name="stair"))
    out = tmp_path / "fitted.toml"
    assert main([data, "--fit", KEYS, "--out", str(out)]) == 0
    text = capsys.readouterr().out
    notes = [line for line in text.splitlines() if line.startswith("warning: ") and "not identified" in line]
    assert len(notes) == 1 and "no plateau below 3 Stribeck speeds" in notes[0] and "low-speed staircase" in notes[0]
    for k in KEYS.split(","):
        assert f"{k} = " in text and "not identifiable, the plant keeps the base value" in text
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fitted = load_plant(out)
    for k in KEYS.split(","):
        assert fitted.values[k] == base.values[k] and not fitted.sources[k].startswith("fit:")
