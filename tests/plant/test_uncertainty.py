"""[uncertainty] sections of plants and scenes; [spec] and [robust] scene sections."""

import copy
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from prsa_ctrl import PlantFileError, SceneError
from prsa_ctrl.plant.plantfile import Plant, builtin_plants, load_plant
from prsa_ctrl.studies.scene import _from_doc, load_scene
from prsa_ctrl.plant.uncertainty import parse_scene_sections, uncertainty_model

ROOT = Path(__file__).resolve().parents[2]
_DOC = tomllib.loads((ROOT / "plants" / "paper-iprsm.toml").read_text())
_SCENE = tomllib.loads((ROOT / "tuning" / "robust-load-step.toml").read_text())


def _plant_with(entries, origin="bad-plant.toml"):
    doc = copy.deepcopy(_DOC)
    doc["uncertainty"] = entries
    return Plant.from_dict(doc, origin=origin)


@pytest.mark.parametrize("name", builtin_plants())
def test_builtin_plants_document_their_uncertainty(name):
    p = load_plant(name)
    unc = uncertainty_model(p)
    assert len(unc) >= 2
    for e in unc.entries:
        assert e.source and e.low <= e.nominal <= e.high
        assert e.source.split(":")[0] in ("paper", "assumption", "estimate", "fit") or e.source.startswith("paper")


def test_robust_scene_adds_its_uncertainty_to_the_plants():
    p, s = load_plant(), load_scene("robust-load-step")
    unc = uncertainty_model(p, s)
    e = {x.key: x for x in unc.entries}
    j = p.values["nut.inertia_kg_m2"]
    assert e["nut.inertia_kg_m2"].low == pytest.approx(0.5 * j) and e["nut.inertia_kg_m2"].high == pytest.approx(1.5 * j)
    assert (e["drive.current_loop_bandwidth_hz"].low, e["drive.current_loop_bandwidth_hz"].high) == (500.0, 1500.0)
    assert s.robust["spec"]["peak_drop_rad_s"] > 0 and s.robust["spec"]["no_saturation"] is True


@given(seed=st.integers(0, 2**32), index=st.integers(0, 10**6))
@settings(max_examples=40)
def test_samples_stay_in_the_support_and_are_reproducible(seed, index):
    unc = uncertainty_model(load_plant(), load_scene("robust-load-step"))
    a = unc.sample(np.random.default_rng([seed, index]))
    b = unc.sample(np.random.default_rng([seed, index]))
    assert a == b
    for e in unc.entries:
        assert e.low <= a[e.key] <= e.high


def test_distributions_have_the_stated_shape():
    p = _plant_with({
        "nut.inertia_kg_m2": {"dist": "uniform", "relative": 0.5, "source": "assumption: t"},
        "drive.current_loop_bandwidth_hz": {"dist": "loguniform", "low": 500.0, "high": 2000.0, "source": "assumption: t"},
        "friction.efficiency": {"dist": "normal", "sigma": 0.02, "truncate": 2.0, "source": "assumption: t"},
    })
    unc = uncertainty_model(p)
    rng = np.random.default_rng(3)
    xs = [unc.sample(rng) for _ in range(4000)]
    bw = np.log([x["drive.current_loop_bandwidth_hz"] for x in xs])
    # log-uniform: the log is uniform, so its median is the log-midpoint (1000 Hz)
    assert abs(np.median(bw) - math.log(1000.0)) < 0.05
    eta = np.array([x["friction.efficiency"] for x in xs])
    assert abs(eta.mean() - 0.85) < 0.002 and eta.min() >= 0.81 and eta.max() <= 0.89
    assert 0.015 < eta.std() < 0.02  # truncation at 2 sigma shrinks the std to 0.88 sigma
    assert len(unc.vertices()) == 8


_GOOD = {"dist": "uniform", "relative": 0.2, "source": "assumption: test"}

# (key, entry) pairs that must be rejected, each with a token the message must name.
_bad_entries = st.one_of(
    st.builds(lambda r: ("nut.inertia_kg_m2", {**_GOOD, "relative": r}),
              st.one_of(st.floats(max_value=-1e-9, allow_nan=False, allow_infinity=False), st.floats(min_value=1.0, max_value=1e6))),
    st.builds(lambda s: ("nut.inertia_kg_m2", {"dist": "normal", "sigma": s, "truncate": 3.0, "source": "a: b"}),
              st.floats(max_value=0.0, allow_nan=False, allow_infinity=False)),
    st.builds(lambda t: ("nut.inertia_kg_m2", {"dist": "normal", "relative_sigma": 0.1, "truncate": t, "source": "a: b"}),
              st.one_of(st.floats(max_value=0.0, allow_nan=False, allow_infinity=False), st.floats(min_value=6.001, max_value=1e9))),
    # normal that reaches non-positive inertia: nominal 2e-4, 3 sigma >= nominal
    st.builds(lambda s: ("nut.inertia_kg_m2", {"dist": "normal", "sigma": s, "truncate": 3.0, "source": "a: b"}),
              st.floats(min_value=0.7e-4, max_value=1.0)),
    st.builds(lambda lo: ("drive.current_loop_bandwidth_hz", {"dist": "loguniform", "low": lo, "high": 2000.0, "source": "a: b"}),
              st.floats(max_value=0.0, allow_nan=False, allow_infinity=False)),
    st.builds(lambda lo, hi: ("drive.current_loop_bandwidth_hz", {"dist": "uniform", "low": lo, "high": hi, "source": "a: b"}),
              st.floats(min_value=1001.0, max_value=1e5), st.floats(min_value=1.0, max_value=999.0)),
    # efficiency above 1 is not physical
    st.builds(lambda r: ("friction.efficiency", {**_GOOD, "relative": r}), st.floats(min_value=0.18, max_value=0.99)),
    st.builds(lambda d: ("nut.inertia_kg_m2", {**_GOOD, "dist": d}), st.text(min_size=0, max_size=8).filter(
        lambda d: d not in ("uniform", "normal", "loguniform"))),
    st.builds(lambda k: (k, dict(_GOOD)), st.sampled_from(["nut.mass_kg", "roller.count", "screw.starts", "foo.bar"])),
    st.builds(lambda s: ("nut.inertia_kg_m2", {**_GOOD, "source": s}), st.sampled_from(["", "   ", 3])),
    st.builds(lambda v: ("nut.inertia_kg_m2", {**_GOOD, "relative": v}), st.sampled_from([True, "0.2", float("nan"), float("inf")])),
    # static friction below dynamic at the low end of the support (a cross-check of the plant)
    st.builds(lambda r: ("friction.static", {**_GOOD, "relative": r}), st.floats(min_value=0.17, max_value=0.99)),
)


@given(_bad_entries)
@settings(max_examples=80)
def test_bad_plant_uncertainty_names_key_and_file(bad):
    key, entry = bad
    with pytest.raises(PlantFileError) as exc:
        _plant_with({key: entry})
    msg = str(exc.value)
    assert msg.startswith("bad-plant.toml: ") and key in msg and "\n" not in msg


@given(_bad_entries)
@settings(max_examples=40)
def test_bad_scene_uncertainty_names_key_and_file(bad):
    key, entry = bad
    doc = copy.deepcopy(_SCENE)
    doc["uncertainty"] = {key: entry}
    with pytest.raises(SceneError) as exc:
        s = _from_doc(doc, "bad-scene.toml")
        uncertainty_model(load_plant(), s)
    assert str(exc.value).startswith("bad-scene.toml: ") and key in str(exc.value)


@pytest.mark.parametrize("section, key, value", [
    ("spec", "peak_drop_rad_s", -1.0),
    ("spec", "peak_drop_rad_s", "5"),
    ("spec", "ms", 0.9),
    ("spec", "no_saturation", 1),
    ("spec", "overshot", 1.0),
    ("robust", "aggregate", "median"),
    ("robust", "samples", -1),
    ("robust", "samples", 1.5),
    ("robust", "setpoints_rpm", []),
    ("robust", "final_loads_n", [-5.0]),
    ("robust", "monte_carlo", True),
    ("robust", "seedz", 1),
])
def test_bad_spec_or_robust_entry_names_key_and_file(section, key, value):
    doc = copy.deepcopy(_SCENE)
    doc[section][key] = value
    with pytest.raises(SceneError) as exc:
        _from_doc(doc, "bad-scene.toml")
    msg = str(exc.value)
    assert msg.startswith("bad-scene.toml: ") and f"{section}.{key}" in msg


def test_scene_sections_round_trip():
    out = parse_scene_sections(_SCENE, "x.toml")
    assert set(out) == {"spec", "robust", "uncertainty"}
    assert out["robust"]["monte_carlo"] == 1000 and out["robust"]["aggregate"] == "worst"


def test_plants_without_uncertainty_still_load_and_overrides_keep_it():
    doc = copy.deepcopy(_DOC)
    doc.pop("uncertainty", None)
    p = Plant.from_dict(doc)
    assert len(uncertainty_model(p)) == 0
    q = load_plant().with_params({"nut.inertia_kg_m2": 3e-4})
    assert q.uncertainty == load_plant().uncertainty
