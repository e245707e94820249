import math
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from prsa_ctrl import GeometryWarning, PlantFileError, builtin_plants, load_plant
from prsa_ctrl.plant.plantfile import SCHEMA, Plant
from prsa_ctrl.plant.schema import FINITE, KIND, keys_of

PLANT_DIR = Path(__file__).resolve().parents[2] / "plants"
ALL_PLANTS = builtin_plants()


def test_builtin_plants_are_the_repository_files():
    assert sorted(p.stem for p in PLANT_DIR.glob("*.toml")) == ALL_PLANTS
    assert {"paper-iprsm", "iprsm-60", "iprsm-90"} <= set(ALL_PLANTS)


def test_default_plant_is_paper_and_matches_table1():
    p = load_plant()
    assert p.name == "paper-iprsm"
    v = p.values
    assert (v["screw.pitch_diameter_mm"], v["nut.pitch_diameter_mm"], v["roller.pitch_diameter_mm"]) == (14.0, 21.6, 3.6)
    assert (v["screw.lead_mm"], v["nut.lead_mm"], v["roller.lead_mm"]) == (2.0, 2.0, 0.5)
    assert (v["screw.starts"], v["nut.starts"], v["roller.starts"], v["roller.count"]) == (4, 4, 1, 10)
    assert v["contact.stiffness_n_per_mm_e"] == 1e5 and v["contact.exponent"] == 1.5
    assert v["contact.damping_n_s_per_mm"] == 50 and v["contact.penetration_mm"] == 0.2
    assert v["friction.static"] == 0.3 and v["friction.dynamic"] == 0.25
    # SI conversion of K: N/mm^1.5 -> N/m^1.5 multiplies by 1000^1.5.
    assert p.contact_stiffness_si == pytest.approx(1e5 * 1000**1.5, rel=1e-15)


@pytest.mark.parametrize("name", ALL_PLANTS)
def test_every_parameter_has_a_source(name):
    p = load_plant(name)
    assert set(p.sources) == set(keys_of(p.mechanism))  # issue 21: the keys of the plant's mechanism
    for key, src in p.sources.items():
        if p.mechanism == "inverted-roller-screw" and key == "friction.no_load_breakaway_torque_n_m":
            # the keys newer than these complete files: documented defaults
            assert not p.given(key) and src.startswith("default: no breakaway excess"), key
        elif p.mechanism == "inverted-roller-screw" and key == "friction.viscous_offset_n_m_s_per_rad":
            assert not p.given(key) and src.startswith("default: symmetric viscous friction"), key
        elif name == "paper-iprsm":
            assert src.startswith(("paper", "assumption: ")), key
        elif p.mechanism == "inverted-roller-screw":
            assert src.startswith(("estimate: ", "assumption: ", "paper")), key
        else:  # issue 21: catalogue values, and documented defaults for the keys the file leaves out
            assert src.startswith(("catalogue", "assumption: ") if p.given(key) else ("default: ", "derived: ", "assumption: ")), key


def test_paper_geometry_residual_is_reported():
    with pytest.warns(GeometryWarning, match=r"\+0\.400 mm"):
        p = load_plant(PLANT_DIR / "paper-iprsm.toml")
    g = p.geometry
    assert g.closure_residual_m == pytest.approx(0.4e-3, abs=1e-12)
    assert g.screw_match_residual_m == pytest.approx(-0.4e-3, abs=1e-12)
    assert g.nut_match_residual_m == pytest.approx(0.0, abs=1e-12)
    assert math.degrees(g.helix_nut_rad) == pytest.approx(1.688, abs=1e-3)
    assert math.degrees(g.helix_screw_rad) == pytest.approx(2.604, abs=1e-3)


@pytest.mark.parametrize("name", ["iprsm-60", "iprsm-90"])
def test_estimated_plants_close_exactly(name, recwarn):
    p = load_plant(name)
    assert abs(p.geometry.closure_residual_m) < 1e-12
    assert not [w for w in recwarn if issubclass(w.category, GeometryWarning)]


def _write_modified(tmp_path, edit) -> Path:
    doc = (PLANT_DIR / "paper-iprsm.toml").read_text()
    path = tmp_path / "bad-plant.toml"
    path.write_text(edit(doc))
    return path


def _set(section, key, value):
    def edit(doc):
        pat = re.compile(r"(\[" + section + r"\][^\[]*?^" + key + r" = \{ value = )[^,]+", re.S | re.M)
        assert pat.search(doc)
        return pat.sub(lambda m: m.group(1) + value, doc, count=1)

    return edit


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda d: d.replace("[cage]", 'colour_rgb = { value = 1, source = "x" }\n[cage]'), r"unknown key roller\.colour_rgb"),
        (lambda d: d.replace("[cage]", "[gearbox]\n[cage]"), r"unknown section 'gearbox'"),
        (_set("screw", "pitch_diameter_mm", "-14.0"), r"screw\.pitch_diameter_mm = -14\.0; expected a finite positive number"),
        (_set("nut", "inertia_kg_m2", "nan"), r"nut\.inertia_kg_m2 = nan; expected a finite"),
        (_set("contact", "exponent", "inf"), r"contact\.exponent = inf; expected a finite"),
        (_set("nut", "pitch_diameter_mm", "12.0"), r"nut\.pitch_diameter_mm = 12\.0 must exceed screw\.pitch_diameter_mm"),
        (_set("roller", "count", "0"), r"roller\.count = 0; expected a positive integer"),
        (_set("roller", "count", "40"), r"roller\.count = 40 rollers .* do not fit"),
        (_set("roller", "lead_mm", "0.7"), r"roller pitch 0\.7 mm"),
        (_set("friction", "efficiency", "1.2"), r"friction\.efficiency = 1\.2; expected a fraction"),
        (_set("friction", "static", "0.1"), r"friction\.static = 0\.1 is below friction\.dynamic"),
        (_set("contact", "exponent", "0.8"), r"contact\.exponent = 0\.8; expected >= 1"),
        (_set("roller", "pitch_diameter_mm", "6.0"), r"roller\.pitch_diameter_mm = 6\.0 cannot fit"),
        # issue 21: screw.mass_kg now has a documented default; a required key is still refused
        (lambda d: re.sub(r"^inertia_kg_m2 = .*\n", "", d, count=1, flags=re.M), r"missing key nut\.inertia_kg_m2; expected it"),
        (lambda d: d.replace('source = "paper Table 1 (Quantity)"', 'source = ""'), r"roller\.count\.source = ''"),
        (lambda d: d.replace("[drive]", "[drive\n"), r"invalid TOML"),
    ],
)
def test_bad_plant_files_name_key_and_file(tmp_path, edit, match):
    path = _write_modified(tmp_path, edit)
    with pytest.raises(PlantFileError, match=match) as err:
        load_plant(path)
    assert "bad-plant.toml" in str(err.value)
    assert "\n" not in str(err.value)


def test_unknown_plant_names_the_value_and_choices():
    with pytest.raises(PlantFileError, match=r"unknown plant 'nope'; expected a built-in name \(ballscrew-32x10, iprsm-60, iprsm-90, paper-heavy-slide, paper-iprsm, rollerscrew-30x5\)"):
        load_plant("nope")
    with pytest.raises(PlantFileError, match=r"plant file 'missing\.toml' not found"):
        load_plant("missing.toml")


def test_overrides_copy_and_reject_unknown_keys(paper_plant):
    stiff = paper_plant.with_params({"contact.stiffness_n_per_mm_e": 1e6})
    assert stiff.values["contact.stiffness_n_per_mm_e"] == 1e6
    assert paper_plant.values["contact.stiffness_n_per_mm_e"] == 1e5
    with pytest.raises(PlantFileError, match=r"unknown parameter 'contact.stifness'; allowed: screw\.pitch_diameter_mm"):
        paper_plant.with_params({"contact.stifness": 1.0})
    with pytest.raises(PlantFileError, match=r"contact\.damping_n_s_per_mm = -1; expected a finite non-negative number"):
        paper_plant.with_params({"contact.damping_n_s_per_mm": -1})


def test_installed_copy_is_found_from_any_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert load_plant().name == "paper-iprsm"


_DOC = tomllib.loads((PLANT_DIR / "iprsm-60.toml").read_text())
_KEYS = [(s, k) for s, keys in SCHEMA.items() for k in keys]


@settings(max_examples=150, deadline=None, derandomize=True)
@given(
    st.sampled_from(_KEYS),
    st.one_of(
        st.floats(allow_nan=True, allow_infinity=True, width=64),
        st.integers(-5, 10**7),
        st.text(max_size=3),
        st.booleans(),
    ),
)
def test_validation_either_accepts_or_raises_plant_file_error(key, value):
    doc = {s: (dict(v) if isinstance(v, dict) else v) for s, v in _DOC.items()}
    section, sub = key
    doc[section] = {k: dict(v) for k, v in doc[section].items()}
    doc[section].setdefault(sub, {"source": "test"})["value"] = value  # (a key newer than the file: added)
    try:
        p = Plant.from_dict(doc, origin="prop.toml")
    except PlantFileError as exc:
        assert "prop.toml" in str(exc)
        return
    v = p.values[f"{section}.{sub}"]
    # (a signed key, friction.torque_offset_n_m, may be negative: the schema's kind "finite")
    assert math.isfinite(v) and (v >= 0 or KIND[f"{section}.{sub}"] == FINITE)
    assert np.isfinite(p.slip_arm_m)
