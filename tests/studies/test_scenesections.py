"""The typed study sections of a scene (prsa_ctrl.studies.scenesections)."""

import dataclasses

import pytest

from prsa_ctrl.errors import SceneError
from prsa_ctrl.plant.plantfile import load_plant
from prsa_ctrl.plant.uncertainty import Uncertainty, uncertainty_model
from prsa_ctrl.studies.scene import load_scene
from prsa_ctrl.studies.scenesections import Robust, Sections, Spec, parse_scene_sections


def test_robust_scene_sections_are_typed_and_frozen():
    s = load_scene("robust-load-step").sections
    assert isinstance(s.spec, Spec)
    assert isinstance(s.robust, Robust)
    assert isinstance(s.uncertainty, Uncertainty)
    assert s.robust.setpoints_rpm == (300.0,)
    assert s.robust.final_loads_n == (1500.0,)
    assert s.robust.monte_carlo == 1000
    assert s.robust.plant_uncertainty is False
    assert s.spec.bounds["peak_drop_rad_s"] == 10.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.robust.seed = 2
    with pytest.raises(TypeError):
        s.spec.bounds["ms"] = 2.0


def test_sections_round_trip_the_validated_dict():
    doc = {"spec": {"ms": 1.5, "no_saturation": True, "yield": 0.9},
           "robust": {"seed": 3, "setpoints_rpm": [100, 300]},
           "uncertainty": {"nut.inertia_kg_m2": {"dist": "uniform", "relative": 0.1, "source": "test"}}}
    d = parse_scene_sections(doc, "s.toml")
    s = Sections.from_dict(d, "s.toml")
    assert s.as_dict() == d
    assert s.yield_target == 0.9
    assert s.robust.given == ("seed", "setpoints_rpm")
    assert s.robust.vertices is True  # the default where the file is silent
    assert s.plant_overrides.origin == "s.toml"


def test_empty_sections_are_falsy_and_add_nothing():
    s = load_scene("paper-load-step").sections
    assert not s
    assert s.as_dict() == {}
    assert s.spec_bounds == {}
    assert s.plant_overrides == Uncertainty({}, s.origin, True)


def test_plant_overrides_carry_the_plant_uncertainty_switch():
    plant = load_plant()
    scene = load_scene("robust-load-step")
    with_plant = uncertainty_model(plant, dataclasses.replace(scene.sections.plant_overrides, plant_uncertainty=True))
    alone = uncertainty_model(plant, scene.sections.plant_overrides)
    assert {e.key for e in alone.entries} == {"nut.inertia_kg_m2", "drive.current_loop_bandwidth_hz"}
    assert {e.key for e in alone.entries} <= {e.key for e in with_plant.entries}


def test_uncertainty_model_reads_no_scene():
    with pytest.raises(TypeError, match="expected an Uncertainty"):
        uncertainty_model(load_plant(), load_scene("robust-load-step"))


def test_bad_section_is_named():
    with pytest.raises(SceneError, match="robust.seed"):
        Sections.parse({"robust": {"seed": -1}}, "s.toml")


def test_a_scene_with_sections_pickles_for_the_process_pools():
    import pickle

    scene = load_scene("robust-load-step")
    back = pickle.loads(pickle.dumps(scene))
    assert back.sections == scene.sections
    assert back.sections.as_dict() == scene.sections.as_dict()
    assert dict(back.sections.spec.bounds) == dict(scene.sections.spec.bounds)
