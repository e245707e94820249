"""prsa_ctrl.plant.plantfile: absurd but well-typed plant values (issue 13/14) are refused with one
line naming key, value, plausible range and file; every built-in plant is plausible."""

import math
import re
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from prsa_ctrl import PlantFileError, load_plant
from prsa_ctrl.cli.tune import main
from prsa_ctrl.plant.plantfile import PLAUSIBLE, SCHEMA

ROOT = Path(__file__).resolve().parents[2]
PAPER = (ROOT / "plants" / "paper-iprsm.toml").read_text()
_HC = [HealthCheck.function_scoped_fixture]


def _set(doc: str, section: str, key: str, value: str) -> str:
    pat = re.compile(r"(\[" + section + r"\][^\[]*?^" + key + r" = (?:\{ value = )?)[^,\n]+", re.S | re.M)
    if not pat.search(doc):  # a key newer than the file (issue 21: it defaults): added to its section
        doc = re.sub(r"^\[" + section + r"\]\n", lambda m: m.group(0) + f'{key} = {{ value = 0, source = "test" }}\n',
                     doc, count=1, flags=re.M)
    assert pat.search(doc), (section, key)
    return pat.sub(lambda m: m.group(1) + value, doc, count=1)


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




def test_a_plant_file_beyond_the_size_bound_is_refused_before_it_is_read(tmp_path, monkeypatch):
    """A valid plant file padded with comments past 1 MB: one line naming the file and its size,
    the text never read. Was: read and parsed (an 8 MB base took prsa-fit 60 s instead of 3 s,
    two tomlkit passes)."""
    from prsa_ctrl.plant import plantfile

    text = plantfile.plant_file_path().read_text(encoding="utf-8")
    big = tmp_path / "big.toml"
    big.write_text("# padding\n" * (plantfile.PLANT_FILE_BYTES_MAX // 10) + text, encoding="utf-8")
    size = big.stat().st_size
    monkeypatch.setattr(Path, "read_text", lambda *a, **k: pytest.fail("the file was read"))
    with pytest.raises(PlantFileError) as exc:
        load_plant(str(big))
    assert str(exc.value) == f"{big}: {size} bytes; expected a plant file of at most 1000000 bytes"
    monkeypatch.undo()
    small = tmp_path / "small.toml"
    small.write_text("# padding\n" * (plantfile.PLANT_FILE_BYTES_MAX // 10 - len(text) // 10 - 1) + text,
                     encoding="utf-8")
    assert small.stat().st_size <= plantfile.PLANT_FILE_BYTES_MAX
    assert load_plant(str(small)).values == load_plant().values  # at the bound: loads
