"""Drive units (issue 24, item 1): torque constant from the back-EMF constant (V/krpm or V s/rad,
line-to-line RMS or peak), rated torque alone (per-unit gains), current-based gains (RMS and
peak), the gains in each built-in template's units and the CLI's --motor / --rated-torque.

Every expected number is computed here by hand from the definitions (numbers typed out where
possible), not by calling the conversion under test.
"""

from __future__ import annotations

import json
import math
import tomllib

import pytest

from prsa_ctrl import PID
from prsa_ctrl.drive.measurement import PositionLoop
from prsa_ctrl.io.driveparams import MotorData, drive_units, fill_template, parse_motor, read_parameter_set
from prsa_ctrl.tuning.cascade import CascadeDesign

KP, KI = 0.085, 14.7                 # N m s/rad, N m/rad
DESIGN = CascadeDesign("joint", PID(KP, KI), PositionLoop(kv=102.7, kvff=1.0, kaff=1.0), {}, {}, {}, 0.0)
RPM = 0.10471975511965977            # rad/s per rpm = 2 pi / 60
KRPM = 104.71975511965977            # rad/s in 1000 rpm


@pytest.mark.parametrize("key, value, kt", [
    # k_T = sqrt(3) k_E,LL,rms [V s/rad]: 3 E_ph I = T w with E_ph = E_LL / sqrt(3)
    ("back_emf_v_per_krpm", 60.0, 1.7320508075688772 * 60.0 / KRPM),
    ("back_emf_v_per_krpm_rms", 60.0, 1.7320508075688772 * 60.0 / KRPM),
    # peak line-to-line: E_rms = E_peak / sqrt(2) -> k_T = sqrt(3/2) k_E,peak
    ("back_emf_v_per_krpm_peak", 60.0, 1.224744871391589 * 60.0 / KRPM),
    ("back_emf_v_s_per_rad_rms", 0.5, 1.7320508075688772 * 0.5),
    ("back_emf_v_s_per_rad_peak", 0.5, 1.224744871391589 * 0.5),
])
def test_torque_constant_from_back_emf_conventions(key, value, kt):
    m = parse_motor(f"{key}={value}")
    assert m.torque_constant_n_m_per_a == pytest.approx(kt, rel=1e-14)
    assert ("PEAK" if "peak" in key else "RMS") in m.source


def test_back_emf_60_v_per_krpm_is_0_992_n_m_per_a():
    """A typed-out value: 60 V/krpm (LL RMS) = 0.57296 V s/rad -> 0.99239 N m/A RMS."""
    assert parse_motor("back_emf_v_per_krpm=60").torque_constant_n_m_per_a == pytest.approx(0.992392, abs=1e-6)
    assert MotorData.from_back_emf(0.57295779513, "V s/rad").torque_constant_n_m_per_a == pytest.approx(0.992392,
                                                                                                      abs=1e-6)


def test_current_based_and_per_unit_gains_by_hand():
    """kp = 0.085 N m s/rad, k_T = 0.9 N m/A, T_r = 3 N m, I_r = 4 A, 3000 rpm, 5 pole pairs."""
    m = MotorData(0.9, rated_current_a=4.0, rated_torque_n_m=3.0, rated_speed_rpm=3000.0, pole_pairs=5)
    s = drive_units(PID(KP, KI), m)["speed"]
    assert s["kp_a_per_rad_s"] == pytest.approx(0.0944444444444, rel=1e-11)         # 0.085 / 0.9
    assert s["kp_a_per_rpm"] == pytest.approx(0.00989019909, rel=1e-9)             # 0.085 x 0.10472 / 0.9
    assert s["kp_a_peak_per_rad_s"] == pytest.approx(0.133564614, rel=1e-8)        # 0.0944444 x 1.4142136
    assert s["ki_a_per_rad"] == pytest.approx(16.3333333333, rel=1e-11)            # 14.7 / 0.9
    assert s["kp_rated_torque_per_rad_s"] == pytest.approx(0.0283333333333, rel=1e-11)
    assert s["kp_percent_rated_torque_per_rpm"] == pytest.approx(0.296705972839, rel=1e-10)
    assert s["kp_percent_rated_current_per_rpm"] == pytest.approx(0.247254977, rel=1e-8)  # 100 x A/rpm / 4 A
    assert s["kp_pu"] == pytest.approx(0.085 * 314.159265358979 / 3.0, rel=1e-13)
    assert s["kp_a_per_electrical_rad_s"] == pytest.approx(0.0188888888889, rel=1e-11)
    assert s["tn_ms"] == pytest.approx(5.78231292517, rel=1e-11)                   # 1000 x 0.085 / 14.7
    assert "parallel" in s["convention"] and "series" in s["convention"]


def test_rated_torque_alone_gives_per_unit_gains_only():
    m = parse_motor("rated_torque_n_m=3")
    s = drive_units(PID(KP, KI), m)["speed"]
    assert s["kp_percent_rated_torque_per_rpm"] == pytest.approx(100 * KP * RPM / 3.0, rel=1e-15)
    assert "kp_a_per_rad_s" not in s
    with pytest.raises(ValueError, match=r"needs the motor's torque constant"):
        tpl = {"template": {"name": "t"}, "parameter": [{"index": "x", "name": "x", "quantity": "speed_kp",
                                                          "unit": "A/rpm", "datatype": "f", "confirmed": True,
                                                          "source": "test"}]}
        fill_template(tpl, PID(KP, KI), _plant(), m)
    with pytest.raises(ValueError, match="torque_constant_n_m_per_a = None and rated_torque_n_m = None"):
        MotorData(None)


def _plant():
    from prsa_ctrl import load_plant

    return load_plant()


@pytest.mark.parametrize("name, expected", [
    # each template's unit, by hand: Beckhoff 0x3140:01 N m s/rad, 0x3140:02 s, 0x30C0:01 1/s
    ("beckhoff-ax8000", {"0x3140:01": 0.085, "0x3140:02": 0.085 / 14.7, "0x30C0:01": 102.7,
                         "0x3163:05": 0, "0x3183:05": 0}),
    # SINAMICS p1460 N m s (per rad/s), p1462 ms
    ("siemens-sinamics", {"p1460": 0.085, "p1462": 1000 * 0.085 / 14.7}),
    # CiA 402 placeholders (N m s/rad, ms, 1/s) until the drive's manual says otherwise
    ("cia402", {"0x60F9:01": 0.085, "0x60F9:02": 1000 * 0.085 / 14.7, "0x60FB:01": 102.7}),
    ("generic", {"speed.Kp": 0.085, "speed.Tn": 1000 * 0.085 / 14.7, "position.Kv": 102.7,
                 "position.Kv_m_min_per_mm": 102.7 * 0.06, "position.velocity_feedforward": 100.0,
                 "position.acceleration_feedforward": 100.0}),
])
def test_template_values_in_their_units(name, expected):
    filled = fill_template(name, DESIGN, _plant())
    got = {p["index"]: p["value"] for p in filled["parameter"] if p.get("applies")}
    for idx, v in expected.items():
        assert got[idx] == pytest.approx(v, rel=1e-14), (name, idx)


def test_cli_rated_torque_and_peak_back_emf(tmp_path, shared_tuning):
    from prsa_ctrl.cli.tune import main

    out = tmp_path / "u.json"
    assert main(["--quiet", "--export", str(out), "--rated-torque", "3", "--motor", "back_emf_v_per_krpm_peak=60",
                 "--json", str(tmp_path / "r.json")]) == 0
    gains = json.loads((tmp_path / "r.json").read_text())["best"]["gains"]
    du = json.loads(out.read_text())["drive_units"]
    kt = math.sqrt(1.5) * 60.0 / KRPM
    assert du["motor"]["torque_constant_n_m_per_a"] == pytest.approx(kt, rel=1e-14)
    assert du["speed"]["kp_a_per_rpm"] == pytest.approx(gains["kp"] * RPM / kt, rel=1e-14)
    assert du["speed"]["kp_percent_rated_torque_per_rpm"] == pytest.approx(100 * gains["kp"] * RPM / 3.0, rel=1e-14)
    # --rated-torque alone: per-unit gains, no current-based ones
    out2 = tmp_path / "u2.toml"
    assert main(["--quiet", "--export", str(out2), "--rated-torque", "3"]) == 0
    sp = tomllib.loads(out2.read_text())["drive_units"]["speed"]
    assert "kp_percent_rated_torque_per_rpm" in sp and "kp_a_per_rpm" not in sp


@pytest.mark.parametrize("argv, match", [
    (["--rated-torque", "0"], "--rated-torque 0 N m: expected a torque"),
    (["--rated-torque", "x"], "--rated-torque 'x'"),
    (["--rated-torque", "2", "--motor", "torque_constant_n_m_per_a=1,rated_torque_n_m=3"],
     "--rated-torque 2 differs from the --motor rated_torque_n_m = 3"),
    (["--motor", "back_emf_v_per_krpm=60,torque_constant_n_m_per_a=1"], "both torque_constant_n_m_per_a and "
                                                                         "back_emf_v_per_krpm"),
])
def test_cli_bad_drive_unit_flags_one_line(argv, match, tmp_path, capsys, monkeypatch):
    from prsa_ctrl.cli.tune import main

    monkeypatch.chdir(tmp_path)
    assert main(argv + ["--export", "x.json"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and match in err[0], err
    assert not list(tmp_path.iterdir())


def test_read_back_with_rated_torque_only_units():
    """A parameter set in % rated torque per rpm reads back with the file's [motor] table."""
    tpl = {"template": {"name": "t"}, "parameter": [{"index": "Kp", "name": "Kp", "quantity": "speed_kp",
                                                      "unit": "% rated torque/rpm", "datatype": "f",
                                                      "confirmed": True, "source": "test"}]}
    filled = fill_template(tpl, PID(KP, KI), _plant(), MotorData(None, rated_torque_n_m=3.0))
    assert filled["parameter"][0]["value"] == pytest.approx(0.296705972839, rel=1e-10)
    assert read_parameter_set(filled)["speed_kp"] == pytest.approx(KP, rel=1e-15)


@pytest.mark.parametrize("unit", sorted(__import__("prsa_ctrl.io.driveparams", fromlist=["UNIT_FACTORS"]).UNIT_FACTORS))
def test_every_unit_reads_back_to_si(unit):
    """Each unit a template may use: written from SI and read back gives the SI value (1e-15),
    and the value written is SI x the factor the unit's definition gives (typed here)."""
    from prsa_ctrl.io.driveparams import QUANTITIES, UNIT_FACTORS

    hand = {"N m s/rad": 1.0, "N m/rpm": RPM, "A/(rad/s)": 1 / 0.9, "mA/(rad/s)": 1000 / 0.9, "A/rpm": RPM / 0.9,
            "A peak/(rad/s)": 1.4142135623730951 / 0.9, "A peak/rpm": 1.4142135623730951 * RPM / 0.9,
            "rated torque/(rad/s)": 1 / 3.0, "% rated torque/rpm": 100 * RPM / 3.0, "N m/rad": 1.0, "A/rad": 1 / 0.9,
            "s": 1.0, "ms": 1e3, "0.1 ms": 1e4, "us": 1e6, "1/s": 1.0, "(m/min)/mm": 0.06, "1000/min": 0.06,
            "1/s^2": 1.0, "1": 1.0, "%": 100.0, "N m s^2/rad": 1.0, "A s^2/rad": 1 / 0.9,
            "0.1 mA/(rad/s)": 1e4 / 0.9, "0.01 ms": 1e5, "N m": 1.0, "per mille rated torque": 1000 / 3.0, "Hz": 1.0}
    si_unit = UNIT_FACTORS[unit][0]
    quantity = next(q for q, (u, _) in QUANTITIES.items() if u == si_unit and not q.startswith("torque_filter_type"))
    tpl = {"template": {"name": "t"}, "parameter": [{"index": "x", "name": "x", "quantity": quantity, "unit": unit,
                                                      "datatype": "f", "confirmed": True, "source": "test", "filter": 1}]}
    design = DESIGN if quantity not in ("speed_kp", "speed_ki", "speed_tn", "sample_time") else PID(KP, KI)
    motor = MotorData(0.9, rated_torque_n_m=3.0)
    from prsa_ctrl.drive.filters import LoopFilter, Notch

    filled = fill_template(tpl, design, _plant(), motor, filters=[LoopFilter(Notch(1200.0, 300.0, -20.0))])
    prm = filled["parameter"][0]
    if not prm["applies"]:
        pytest.skip(f"{quantity} does not apply to this design")
    assert prm["value"] == pytest.approx(prm["value_si"] * hand[unit], rel=1e-14)
    key = f"{quantity}[1]" if quantity.startswith("torque_filter_") else quantity  # one per filter number
    assert read_parameter_set(filled)[key] == pytest.approx(prm["value_si"], rel=1e-15)
