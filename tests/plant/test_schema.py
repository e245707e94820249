"""Issue 21, part 1: minimal plant files, documented defaults with their sources, --show-plant."""

import math
import tomllib
import warnings
from pathlib import Path

import pytest

from prsa_ctrl import GeometryWarning, PlantFileError, load_plant
from prsa_ctrl.cli.tune import main as tune_main
from prsa_ctrl.plant import describe_plant
from prsa_ctrl.plant.describe import used_keys
from prsa_ctrl.plant.schema import DEFAULTS, KIND, MECHANISMS, REQUIRED, keys_of

PLANT_DIR = Path(__file__).resolve().parents[2] / "plants"

MINIMAL_IPRSM = '''
name = "mini"
[screw]
lead_mm = { value = 2.0, source = "test" }
[nut]
inertia_kg_m2 = { value = 2.0e-4, source = "test" }
[drive]
torque_limit_n_m = { value = 3.0, source = "test" }
[sensor]
sample_time_s = { value = 2.5e-4, source = "test" }
encoder_counts_per_rev = { value = 1048576, source = "test" }
'''

MINIMAL_BALL = '''
name = "mini-ball"
mechanism = "ball-screw"
[screw]
lead_mm = { value = 10.0, source = "test" }
[axis]
motor_inertia_kg_m2 = { value = 1.2e-3, source = "test" }
moving_mass_kg = { value = 150.0, source = "test" }
[drive]
torque_limit_n_m = { value = 20.0, source = "test" }
[sensor]
sample_time_s = { value = 1.25e-4, source = "test" }
encoder_counts_per_rev = { value = 8388608, source = "test" }
'''


def _write(tmp_path, text, name="p.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_every_key_of_every_mechanism_is_required_or_has_a_default_with_a_source():
    for mech in MECHANISMS:
        for key in keys_of(mech):
            assert key in KIND
            if key in REQUIRED[mech]:
                continue
            assert key in DEFAULTS, (mech, key)
            src = DEFAULTS[key][1]
            src = src if isinstance(src, str) else src.get(mech, src.get("*"))
            assert src.startswith(("default: ", "derived: ", "assumption: ")), (mech, key, src)


def test_minimal_inverted_file_loads_and_sources_say_default(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error", GeometryWarning)  # the defaulted geometry closes exactly
        p = load_plant(_write(tmp_path, MINIMAL_IPRSM))
    assert p.mechanism == "inverted-roller-screw"
    assert set(p.values) == set(keys_of("inverted-roller-screw"))
    given = {k for k in p.values if p.given(k)}
    assert given == set(REQUIRED["inverted-roller-screw"])
    for k in p.values:
        assert p.sources[k] == "test" if k in given else p.sources[k].startswith(("default: ", "assumption: "))
    v = p.values
    # rules: meshing threads and the inverted design's matching rule close the geometry
    assert v["nut.lead_mm"] == v["screw.lead_mm"] == 2.0
    assert v["roller.pitch_diameter_mm"] * v["screw.starts"] == pytest.approx(v["screw.pitch_diameter_mm"])
    assert v["nut.pitch_diameter_mm"] == pytest.approx(v["screw.pitch_diameter_mm"] + 2 * v["roller.pitch_diameter_mm"])
    # the rated load default is what the torque limit drives through the screw
    assert v["screw.rated_load_n"] == pytest.approx(3.0 * 2 * math.pi * 0.85 / 2e-3)
    assert p.geometry.messages == ()


def test_existing_files_are_unchanged_and_fully_given():
    for name in ("paper-iprsm", "iprsm-60", "iprsm-90", "paper-heavy-slide"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", GeometryWarning)
            p = load_plant(name)
        doc = tomllib.loads((PLANT_DIR / f"{name}.toml").read_text())
        file_values = {f"{s}.{k}": float(e["value"]) for s, t in doc.items() if isinstance(t, dict) and s != "uncertainty"
                       for k, e in t.items()}
        # the keys newer than these files (issue 21): the breakaway level follows the no-load torque,
        # the viscous offset is 0
        file_values["friction.no_load_breakaway_torque_n_m"] = file_values["friction.no_load_torque_n_m"]
        file_values["friction.viscous_offset_n_m_s_per_rad"] = 0.0
        assert dict(p.values) == file_values
        assert p.defaulted == {"friction.no_load_breakaway_torque_n_m", "friction.viscous_offset_n_m_s_per_rad"}
        assert p.mechanism == "inverted-roller-screw"


def test_minimal_ball_screw_file_loads_with_defaults(tmp_path):
    p = load_plant(_write(tmp_path, MINIMAL_BALL))
    assert p.mechanism == "ball-screw"
    assert p.screw_driven
    assert {k for k in p.values if p.given(k)} == set(REQUIRED["ball-screw"])
    v = p.values
    assert v["screw.pitch_diameter_mm"] == pytest.approx(32.0)  # 3.2 x lead
    assert v["axis.stroke_position_mm"] == pytest.approx(0.5 * v["axis.bearing_span_mm"])
    assert p.sources["axis.fixed_ends"].startswith("default: fixed-free")
    assert p.sources["nut.inertia_kg_m2"].startswith("derived: ")
    # a default that derives from another value follows an override of it
    q = p.with_params({"axis.bearing_span_mm": 500.0})
    assert q.values["axis.stroke_position_mm"] == 250.0
    assert q.values["axis.screw_inertia_kg_m2"] == pytest.approx(v["axis.screw_inertia_kg_m2"] * 500.0 / v["axis.bearing_span_mm"])
    assert q.given("axis.bearing_span_mm")
    assert not q.given("axis.stroke_position_mm")


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda t: t.replace('mechanism = "ball-screw"', 'mechanism = "ballscrew"'),
         r"p\.toml: mechanism = 'ballscrew'; expected one of 'inverted-roller-screw', 'roller-screw', 'ball-screw', 'linear-axis'"),
        (lambda t: t.replace('moving_mass_kg = { value = 150.0, source = "test" }\n', ""),
         r"p\.toml: missing key axis\.moving_mass_kg; expected it for mechanism = 'ball-screw' \(required: "),
        (lambda t: t.replace('lead_mm = { value = 10.0, source = "test" }\n', ""),
         r"p\.toml: missing key screw\.lead_mm; expected it for mechanism = 'ball-screw'"),
        (lambda t: t.replace('mechanism = "ball-screw"', 'mechanism = "ball-screw"\nmounting = "fixed-loose"'),
         r"p\.toml: mounting = 'fixed-loose'; expected one of 'fixed-free', 'fixed-fixed'"),
        (lambda t: t.replace('[drive]', '[roller]\ncount = { value = 8, source = "x" }\n[drive]').replace(
            'mechanism = "ball-screw"\n', ""),
         r"p\.toml: unknown section 'axis'.*a section of mechanism roller-screw, ball-screw"),
        (lambda t: t.replace("[axis]\n", "[axis]\nstroke_position_mm = { value = 5000.0, source = \"x\" }\n"),
         r"p\.toml: axis\.stroke_position_mm = 5000 mm is not inside axis\.bearing_span_mm"),
    ],
)
def test_bad_mechanism_and_missing_keys_are_one_line_naming_file_and_key(tmp_path, edit, match):
    with pytest.raises(PlantFileError, match=match) as err:
        load_plant(_write(tmp_path, edit(MINIMAL_BALL)))
    assert "\n" not in str(err.value)


def test_a_key_of_another_mechanism_is_refused_with_a_hint(tmp_path):
    text = MINIMAL_IPRSM.replace("[drive]", "[axis]\nmoving_mass_kg = { value = 1.0, source = \"x\" }\n[drive]")
    with pytest.raises(PlantFileError, match=r"unknown section 'axis'"):
        load_plant(_write(tmp_path, text))
    text = MINIMAL_IPRSM.replace("[drive]", "[screw]\n") if False else MINIMAL_IPRSM.replace(
        'lead_mm = { value = 2.0, source = "test" }', 'lead_mm = { value = 2.0, source = "test" }\nroot_diameter_mm = { value = 1.5, source = "x" }')
    with pytest.raises(PlantFileError, match=r"unknown key screw\.root_diameter_mm; .*belongs to mechanism roller-screw, ball-screw"):
        load_plant(_write(tmp_path, text))


def test_describe_plant_lists_every_value_with_unit_and_source(tmp_path):
    p = load_plant(_write(tmp_path, MINIMAL_BALL))
    text = describe_plant(p)
    lines = text.splitlines()
    assert lines[1] == "mechanism: ball-screw (plant file)"
    for key in used_keys(p):  # the keys the mechanism uses (issue 33: no roller keys for a ball screw)
        row = next(ln for ln in lines if ln.strip().startswith(key + " "))
        tag = "given" if p.given(key) else ("derived" if p.sources[key].startswith("derived") else "default")
        assert f" {tag} " in row
        assert p.sources[key] in row
    row = next(ln for ln in lines if ln.strip().startswith("axis.moving_mass_kg "))
    assert " kg " in row
    assert "150" in row


def test_show_plant_flag_prints_and_exits_zero(tmp_path, capsys):
    assert tune_main(["--show-plant", str(_write(tmp_path, MINIMAL_BALL))]) == 0
    out = capsys.readouterr().out
    assert "mechanism: ball-screw" in out
    assert "axis.stroke_position_mm" in out
    assert "default: nut at mid-span" in out
    assert tune_main(["--show-plant", "paper-iprsm"]) == 0
    out = capsys.readouterr().out
    assert "geometry note: geometry does not close" in out
    assert "paper Table 1" in out
    assert tune_main(["--show-plant", str(tmp_path / "nope.toml")]) == 2
    err = capsys.readouterr().err
    assert "nope.toml' not found" in err
    assert "Traceback" not in err
