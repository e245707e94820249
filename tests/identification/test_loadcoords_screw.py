"""A log in load coordinates for a screw-driven plant (issue 21: "a plant works in motor
coordinates (rad, N m) or, for a linear axis, in load coordinates (m, N); a log in either is
accepted; reports and exports say which").

A closed-loop log of a perturbed built-in ball screw and roller screw (the toolkit's simulator,
motor coordinates) is written twice: in motor coordinates (time in ms, angle in deg, torque in
N m) and in load coordinates (time in s, position in mm = lead x angle, force in N = torque /
lead). ``prsa-fit LOG --log-format F --plant P`` fits both; the two fits agree to the round-off
of the unit conversions, and the output and the JSON say the plant's coordinates and how each
log was converted. The conversion itself is checked against numpy arithmetic written here.
"""

from __future__ import annotations

import json
import math
import tomllib
import warnings

import numpy as np
import pytest

from prsa_ctrl.cli.fit import main
from prsa_ctrl.identification.logformat import (LogFormatError, load_axis_log, load_log_format, load_motor_record,
                                                motor_record)
from prsa_ctrl.plant import load_plant

from test_fit_roundtrip_mechanisms import _load, _log, _truth  # noqa: E402  (tests/identification on sys.path)

MOTOR_TOML = """axis = "rotary"
[time]
name = "t_ms"
unit = "ms"
[position]
name = "angle_deg"
unit = "deg"
[command]
name = "torque"
unit = "N m"
logged = "as-applied"
[load]
name = "fz"
unit = "N"
"""
LOAD_TOML = """axis = "linear"
[time]
name = "t"
unit = "s"
[position]
name = "x_mm"
unit = "mm"
[command]
name = "f_n"
unit = "N"
logged = "as-applied"
[load]
name = "fz"
unit = "N"
"""


def _write_logs(tmp_path, name: str, duration_s: float = 1.0):
    """The same run in motor and in load coordinates (CSV, 17 digits) with their descriptions."""
    base = _load(name)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        truth = base.with_params(_truth(base))
    rec = _log(truth, duration_s=duration_s)
    a = 1e-3 * base.values["screw.lead_mm"] / (2 * math.pi)  # m of travel per rad, from the file's lead
    motor, load = tmp_path / "motor.csv", tmp_path / "load.csv"
    np.savetxt(motor, np.column_stack([rec.time_s * 1e3, np.degrees(rec.nut_angle_rad), rec.torque_command_n_m,
                                       rec.axial_load_n]), delimiter=",", header="t_ms,angle_deg,torque,fz",
               comments="", fmt="%.17g")
    np.savetxt(load, np.column_stack([rec.time_s, 1e3 * a * rec.nut_angle_rad, rec.torque_command_n_m / a,
                                      rec.axial_load_n]), delimiter=",", header="t,x_mm,f_n,fz", comments="",
               fmt="%.17g")
    (tmp_path / "motor.toml").write_text(MOTOR_TOML)
    (tmp_path / "load.toml").write_text(LOAD_TOML)
    return base, rec, a


def test_motor_record_is_the_lead_conversion(tmp_path):
    """angle = x / a, torque = F a, load as logged: against numpy on the written files."""
    base, rec, a = _write_logs(tmp_path, "ballscrew-32x10", duration_s=0.2)
    assert base.lead_per_rad == pytest.approx(a, rel=1e-15)
    fmt = load_log_format(tmp_path / "load.toml")
    got, logged = load_motor_record(tmp_path / "load.csv", fmt, base)
    assert logged == "applied"
    raw = np.loadtxt(tmp_path / "load.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(got.nut_angle_rad, raw[:, 1] * 1e-3 / a, rtol=1e-15, atol=0)
    np.testing.assert_allclose(got.torque_command_n_m, raw[:, 2] * a, rtol=1e-15, atol=0)
    np.testing.assert_array_equal(got.axial_load_n, raw[:, 3])
    # and back to what the simulator wrote, to the round-off of two conversions
    np.testing.assert_allclose(got.nut_angle_rad, rec.nut_angle_rad, rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(got.torque_command_n_m, rec.torque_command_n_m, rtol=1e-14, atol=1e-16)
    mot, _ = load_motor_record(tmp_path / "motor.csv", load_log_format(tmp_path / "motor.toml"), base)
    raw_m = np.loadtxt(tmp_path / "motor.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(mot.time_s, raw_m[:, 0] * 1e-3 - raw_m[0, 0] * 1e-3, rtol=0, atol=1e-15)
    np.testing.assert_allclose(mot.nut_angle_rad, raw_m[:, 1] * math.pi / 180, rtol=1e-15, atol=0)
    # the AxisLog route gives the same record
    via = motor_record(load_axis_log(tmp_path / "load.csv", fmt), base)
    np.testing.assert_array_equal(via.nut_angle_rad, got.nut_angle_rad)


@pytest.mark.parametrize("name", ["ballscrew-32x10", "rollerscrew-30x5"])
def test_fits_in_both_coordinates_agree(tmp_path, capsys, name):
    """prsa-fit on the motor- and the load-coordinate log of one run: the same fitted values and
    intervals to 1e-10 (the logs differ by the round-off of deg/mm and the lead, ~1e-16 relative;
    measured: 4e-14 for the ball screw), the same delay, the coordinates said in the output and
    the JSON, and the written plant loads as the same mechanism."""
    base, _, a = _write_logs(tmp_path, name)
    out = {}
    for which in ("motor", "load"):
        code = main([str(tmp_path / f"{which}.csv"), "--log-format", str(tmp_path / f"{which}.toml"), "--plant", name,
                     "--out", str(tmp_path / f"{which}-fit.toml"), "--json", str(tmp_path / f"{which}.json")])
        text = capsys.readouterr().out
        assert code == 0, text
        assert "coordinates: motor (angle rad, torque N m)" in text
        out[which] = (json.loads((tmp_path / f"{which}.json").read_text()), text)
    (jm, tm), (jl, tl) = out["motor"], out["load"]
    assert f"load (position m, force N), converted with the lead {a:.9g} m/rad" in tl
    assert "logged in motor (angle rad, torque N m)" in tm
    assert jm["coordinates"]["plant"] == jl["coordinates"]["plant"] == "motor (angle rad, torque N m)"
    assert list(jl["coordinates"]["logs"].values())[0].startswith("load (position m, force N)")
    assert jm["parameters"].keys() == jl["parameters"].keys()
    for k, pm in jm["parameters"].items():
        pl = jl["parameters"][k]
        assert pl["value"] == pytest.approx(pm["value"], rel=1e-10), k
        assert pl["ci95"] == pytest.approx(pm["ci95"], rel=1e-10), k
    assert jm["solver"]["command_delay"]["shift_samples"] == jl["solver"]["command_delay"]["shift_samples"] == 1
    for which in ("motor", "load"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fitted = load_plant(tmp_path / f"{which}-fit.toml")
        assert fitted.mechanism == base.mechanism
        assert fitted.command_delay_samples == 1
        assert "mechanism" in tomllib.loads((tmp_path / f"{which}-fit.toml").read_text())


def test_plain_csv_and_rotary_description_give_the_same_fit(tmp_path, capsys):
    """The rotary description only renames and converts units: the standard-column CSV of the
    same data fits to the same numbers (and its output states the coordinates too)."""
    base, rec, _ = _write_logs(tmp_path, "ballscrew-32x10", duration_s=0.6)
    std = tmp_path / "std.csv"
    raw = np.loadtxt(tmp_path / "motor.csv", delimiter=",", skiprows=1)
    np.savetxt(std, np.column_stack([raw[:, 0] * 1e-3, np.radians(raw[:, 1]), raw[:, 2], raw[:, 3]]), delimiter=",",
               header="time_s,nut_angle_rad,torque_command_n_m,axial_load_n", comments="", fmt="%.17g")
    assert main([str(std), "--plant", "ballscrew-32x10", "--out", str(tmp_path / "a.toml"), "--json",
                 str(tmp_path / "a.json")]) == 0
    ta = capsys.readouterr().out
    assert main([str(tmp_path / "motor.csv"), "--log-format", str(tmp_path / "motor.toml"), "--plant",
                 "ballscrew-32x10", "--out", str(tmp_path / "b.toml"), "--json", str(tmp_path / "b.json")]) == 0
    assert "coordinates: motor (angle rad, torque N m)" in ta
    ja, jb = (json.loads((tmp_path / f"{x}.json").read_text()) for x in "ab")
    for k in ja["parameters"]:
        assert jb["parameters"][k]["value"] == pytest.approx(ja["parameters"][k]["value"], rel=1e-10), k


BAD = [
    ("rotary-controller", MOTOR_TOML + "[controller]\nstructure = \"position-p/velocity-p\"\n", [],
     "[controller] with axis = \"rotary\""),
    ("rotary-unit", MOTOR_TOML.replace('unit = "deg"', 'unit = "m"'), [], "[position] unit = 'm'"),
    ("rotary-gain", MOTOR_TOML.replace('unit = "N m"', 'unit = "A"'), [], "needs gain (N m per command unit"),
    ("axis", MOTOR_TOML.replace('axis = "rotary"', 'axis = "polar"'), [], "axis = 'polar'"),
    ("convention", MOTOR_TOML, ["--command-logged", "computed"], "--command-logged computed"),
    ("columns", MOTOR_TOML, ["--columns", "time_s=t"], "--columns with --log-format"),
    ("column", MOTOR_TOML.replace('name = "torque"', 'name = "tq"'), [], "'tq', not in the file"),
]


@pytest.mark.parametrize("case,toml,extra,match", BAD, ids=[b[0] for b in BAD])
def test_bad_descriptions_one_line_exit_2_nothing_written(tmp_path, capsys, case, toml, extra, match):
    _write_logs(tmp_path, "ballscrew-32x10", duration_s=0.1)
    (tmp_path / "bad.toml").write_text(toml)
    out = tmp_path / "fit.toml"
    code = main([str(tmp_path / "motor.csv"), "--log-format", str(tmp_path / "bad.toml"), "--plant", "ballscrew-32x10",
                 "--out", str(out), *extra])
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert len(err.splitlines()) == 1 and match in err, err
    assert not out.exists()


def test_a_linear_axis_plant_refuses_a_motor_log(tmp_path):
    """A linear axis works in load coordinates: a motor-coordinate log is refused for it (and by
    the linear-axis reader), one line naming why."""
    from prsa_ctrl.plant import Plant

    _write_logs(tmp_path, "ballscrew-32x10", duration_s=0.1)

    doc = {"name": "lin", "mechanism": "linear-axis", "axis": {"mass_kg": {"value": 10.0, "source": "test"}},
           "drive": {"gain_n_per_unit": {"value": 1.0, "source": "test"}, "force_limit_n": {"value": 100.0, "source": "test"}},
           "sensor": {"sample_time_s": {"value": 1.25e-4, "source": "test"},
                      "encoder_resolution_m": {"value": 1e-7, "source": "test"}}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plant = Plant.from_dict(doc, origin="test")
    with pytest.raises(ValueError, match="is a linear axis"):
        load_motor_record(tmp_path / "motor.csv", load_log_format(tmp_path / "motor.toml"), plant)
    with pytest.raises(LogFormatError, match="axis = 'rotary'"):
        load_axis_log(tmp_path / "motor.csv", load_log_format(tmp_path / "motor.toml"))
