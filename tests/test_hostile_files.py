"""Plant and scene files (issue 13/14): absurd but well-typed values are refused with one line
naming key, value, plausible range and file; solver chatter never reaches the user as such."""

import math
import re
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from prsa_ctrl import PlantFileError, SimulationError, load_plant
from prsa_ctrl.cli.tune import main
from prsa_ctrl.plant.plantfile import PLAUSIBLE, SCHEMA
from prsa_ctrl.studies.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent
PAPER = (ROOT / "plants" / "paper-iprsm.toml").read_text()
SCENE = (ROOT / "tuning" / "paper-load-step.toml").read_text()
_HC = [HealthCheck.function_scoped_fixture]


def _set(doc: str, section: str, key: str, value: str) -> str:
    pat = re.compile(r"(\[" + section + r"\][^\[]*?^" + key + r" = (?:\{ value = )?)[^,\n]+", re.S | re.M)
    if not pat.search(doc):  # a key newer than the file (issue 21: it defaults): added to its section
        doc = re.sub(r"^\[" + section + r"\]\n", lambda m: m.group(0) + f'{key} = {{ value = 0, source = "test" }}\n',
                     doc, count=1, flags=re.M)
    assert pat.search(doc), (section, key)
    return pat.sub(lambda m: m.group(1) + value, doc, count=1)


def _scene_set(doc: str, key: str, value: str) -> str:
    pat = re.compile(rf"^{key} = [^#\n]*", re.M)
    assert pat.search(doc), key
    return pat.sub(lambda m: f"{key} = {value} ", doc, count=1)



def _one_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.mark.parametrize("section, key, value", [
    ("nut", "inertia_kg_m2", "1e308"),
    ("nut", "inertia_kg_m2", "1500.0"),
    ("contact", "stiffness_n_per_mm_e", "1e-300"),
    ("thread", "engaged_threads", "9200000000000000000"),
    ("drive", "torque_limit_n_m", "1e30"),
    ("friction", "creep_velocity_m_s", "1e-12"),
    ("sensor", "sample_time_s", "1.0"),
    ("sensor", "sample_time_s", "1e-9"),
])
def test_absurd_plant_values_name_key_value_range_and_file(tmp_path, capsys, stand_in, section, key, value):
    path = tmp_path / "my.toml"
    path.write_text(_set(PAPER, section, key, value))
    json_out = tmp_path / "keep.json"
    json_out.write_text("old")
    assert main(["--plant", str(path), "--json", str(json_out)]) == 2
    line = _one_line(capsys)
    lo, hi, _ = PLAUSIBLE[f"{section}.{key}"]
    assert str(path) in line and f"{section}.{key} = " in line and f"[{lo:g}, {hi:g}]" in line, line
    assert "ms_max" not in line and not stand_in and json_out.read_text() == "old"


@settings(max_examples=80, suppress_health_check=_HC)
@given(key=st.sampled_from(sorted(k for k in PLAUSIBLE if k.split(".")[1] in SCHEMA.get(k.split(".")[0], {}))), exponent=st.integers(-300, 300), mantissa=st.floats(1.0, 9.99))
def test_any_plant_value_is_accepted_in_range_or_refused_by_key(tmp_path_factory, key, exponent, mantissa):
    section, sub = key.split(".")
    value = mantissa * 10.0**exponent if exponent > -300 else 0.0
    if SCHEMA[section][sub] == "positive integer":
        value = float(min(int(value), 2**62)) if math.isfinite(value) else value
    text = repr(int(value)) if SCHEMA[section][sub] == "positive integer" and math.isfinite(value) else repr(value)
    path = tmp_path_factory.mktemp("p") / "h.toml"
    path.write_text(_set(PAPER, section, sub, text))
    lo, hi, _ = PLAUSIBLE[key]
    try:
        load_plant(path)
    except PlantFileError as exc:
        msg = str(exc)
        assert "\n" not in msg and str(path) in msg
        if not lo <= float(text) <= hi:
            assert f"{key} = " in msg, msg  # out of range: this key is named
    else:
        assert lo <= float(text) <= hi


def test_every_builtin_plant_is_plausible():
    from prsa_ctrl.plant.plantfile import builtin_plants

    for name in builtin_plants():
        p = load_plant(name)
        for key, (lo, hi, why) in PLAUSIBLE.items():
            if key in p.values:  # issue 21: the keys of the plant's mechanism
                assert lo <= p.values[key] <= hi and why


@pytest.mark.parametrize("edit, match", [
    (lambda d: _scene_set(d, "step_time_s", "0.0"), r"step_time = 0\.0; expected a time > 0 s"),
    (lambda d: _scene_set(d, "step_time_s", "0.001"),
     r"operating\.step_time_s = 0\.001: the load step needs at least 8 controller samples"),
    (lambda d: _scene_set(d, "setpoint_rpm", "-300.0"), r"operating\.setpoint_rpm = -300\.0; expected a nut speed in \(0, 6000\] rpm"),
    (lambda d: _scene_set(d, "setpoint_rpm", "1e308"), r"operating\.setpoint_rpm = 1e\+308; expected"),
    (lambda d: _scene_set(d, "final_loads_n", "[1e300]"), r"operating\.final_loads_n = 1e\+300: load 1e\+300 N out of range"),
    (lambda d: _scene_set(d, "duration_s", "1e6"), r"operating\.duration_s = 1e\+06: the record would hold"),
])
def test_bad_scene_values_exit_2_at_load_time(tmp_path, capsys, stand_in, edit, match):
    path = tmp_path / "scene.toml"
    path.write_text(edit(SCENE))
    assert main(["--scene", str(path)]) == 2
    line = _one_line(capsys)
    assert re.search(match, line) and str(path) in line, line
    assert not stand_in


@settings(max_examples=60, suppress_health_check=_HC)
@given(key=st.sampled_from(["setpoint_rpm", "initial_load_n", "step_time_s", "duration_s"]),
       value=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10**20, 10**20)))
def test_any_scene_number_is_refused_in_one_line_or_runs(tmp_path_factory, capsys, stand_in, key, value):
    if isinstance(value, float) and not math.isfinite(value):
        text = {"nan": "nan", "inf": "inf", "-inf": "-inf"}[repr(value)]
    else:
        text = repr(value)
    path = tmp_path_factory.mktemp("s") / "s.toml"
    path.write_text(_scene_set(SCENE, key, text))
    rc = main(["--scene", str(path)])
    line = _one_line(capsys)
    assert rc in (2, 3)
    if rc == 2:
        assert line.startswith("prsa-tune: error: ") and str(path) in line and not stand_in
    else:
        assert len(stand_in) == 1
        load_scene(path)  # accepted by the scene loader too
    stand_in.clear()


def test_solver_chatter_becomes_one_note_or_nothing(tmp_path, capfd, monkeypatch):
    """C-level output of the solvers (written to descriptors 1 and 2) is captured; on failure
    the user sees the one error line only."""
    import os

    import prsa_ctrl.studies.autotune as autotune

    def chatty(*a, **k):
        for i in range(1000):
            os.write(2, f"CasADi - WARNING(\"solver:nlp_g failed: NaN detected for output g\") [{i}]\n".encode())
            os.write(1, b"******************************************************************************\n")
        raise SimulationError("integration failed at t = 0.2 s from state [...]; remedy: tighten the tolerance")

    monkeypatch.setattr(autotune, "tune_actuator", chatty)
    assert main(["--load-step", "500:1500"]) == 3
    out, err = capfd.readouterr()
    assert "CasADi" not in err and "****" not in out
    assert err.strip().splitlines() == ["prsa-tune: numerical failure: integration failed at t = 0.2 s from state [...]; "
                                        "remedy: tighten the tolerance"]
