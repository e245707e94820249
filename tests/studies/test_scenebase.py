"""The shared sections of the speed-loop scene types (``studies/scenebase.py``): ``Scene(**fields)``
builds the type the fields describe, the types keep one report layout, the deprecated
``Scene.robust`` warns."""

import dataclasses
import pickle

import pytest

from prsa_ctrl.errors import SceneError
from prsa_ctrl.studies.dutyscene import DutyCycleScene
from prsa_ctrl.studies.scene import LoadStepScene, Scene, load_scene
from prsa_ctrl.studies.scenebase import scene_type

RAMP = ((0.0, 500.0), (0.01, 500.0), (0.05, 1500.0))


def test_scene_builds_the_type_its_fields_describe():
    assert type(Scene()) is LoadStepScene
    assert type(Scene(load_profile=RAMP, duration=0.1)) is DutyCycleScene
    assert type(Scene(setpoint_profile=((0.0, 30.0), (0.02, 30.0), (0.03, 40.0)), duration=0.1)) is DutyCycleScene
    assert isinstance(Scene(), Scene)
    assert isinstance(Scene(load_profile=RAMP, duration=0.1), Scene)


def test_every_built_in_speed_scene_is_one_of_the_two_types():
    assert type(load_scene("paper-load-step")) is LoadStepScene
    assert type(load_scene("robust-load-step")) is LoadStepScene
    assert type(load_scene("duty-ramp")) is DutyCycleScene
    assert type(load_scene("duty-trace")) is DutyCycleScene


def test_scene_type_names_the_one_type_that_describes_the_fields():
    assert scene_type({}) is LoadStepScene
    assert scene_type({"load_profile": RAMP}) is DutyCycleScene
    assert scene_type({"load_profile": None, "setpoint_profile": None}) is LoadStepScene


def test_a_copy_keeps_its_type_through_replace_and_pickle():
    duty = load_scene("duty-ramp")
    assert type(duty.replace(ms_max=1.6)) is DutyCycleScene
    assert type(dataclasses.replace(load_scene(), ms_max=1.6)) is LoadStepScene
    assert pickle.loads(pickle.dumps(duty)) == duty
    assert type(pickle.loads(pickle.dumps(load_scene()))) is LoadStepScene


def test_a_load_step_has_no_profile_fields():
    names = {f.name for f in dataclasses.fields(LoadStepScene)}
    assert not names & {"load_profile", "setpoint_profile", "goal", "setpoint_weight", "setpoint_share",
                        "profile_source", "trace_lines"}
    with pytest.raises(SceneError, match="unknown scene field 'load_profile'"):
        load_scene().replace(load_profile=RAMP)


def test_a_load_step_refuses_a_duty_cycle_goal_and_weight():
    with pytest.raises(SceneError, match=r"goal = 'mix'; expected 'load' for a load-step scene"):
        Scene(goal="mix")
    with pytest.raises(SceneError, match=r"setpoint_weight = 0\.5; expected 1 without a setpoint profile"):
        Scene(setpoint_weight=0.5)
    assert Scene(goal="load").design_setpoint_weight == 1.0


def test_a_duty_cycle_without_a_profile_is_refused():
    duty = load_scene("duty-ramp")
    with pytest.raises(SceneError, match="load_profile = None; expected a load or a setpoint profile"):
        dataclasses.replace(duty, load_profile=None)


def test_both_types_report_one_layout():
    step, duty = load_scene().as_dict(), load_scene("duty-ramp").as_dict()
    assert list(step) == list(duty)
    assert step["load_profile"] is None
    assert step["goal"] == "auto"
    assert step["final_loads"] == [1500.0]
    assert duty["final_loads"] == []
    assert duty["goal"] == "load"
    assert duty["load_profile"][0] == [0.0, 500.0]


def test_robust_is_deprecated_and_still_the_sections_dict():
    s = load_scene("robust-load-step")
    with pytest.warns(DeprecationWarning, match="Scene.robust is deprecated"):
        old = s.robust
    assert old == s.sections.as_dict()
    assert old["spec"]["peak_drop_rad_s"] == 10.0



_SHARED = {"tuning": {"objective": "ise", "ms_max": 1.5}, "verify": {"fidelity": "rigid", "accuracy": 0.05},
           "outputs": {"needed": ["nut_speed", "motor_torque"]}, "name": "shared"}


def test_both_kinds_read_the_shared_sections_of_a_file_alike():
    """``Scene.from_doc`` reads the sections both kinds share; each type then reads its own
    ``[operating]`` keys (``own_fields``): load steps in N and s, a profile in (s, N) rows."""
    step = LoadStepScene.from_doc({**_SHARED, "operating": {"final_loads_n": [900, 1200], "step_time_s": 0.1}}, "a.toml")
    duty = DutyCycleScene.from_doc({**_SHARED, "operating": {"load_profile_n": [[0.0, 500.0], [0.05, 800.0]],
                                                              "duration_s": 0.2}}, "b.toml")
    assert type(step) is LoadStepScene
    assert type(duty) is DutyCycleScene
    for sc in (step, duty):
        assert (sc.name, sc.objective, sc.ms_max, sc.fidelity, sc.accuracy) == ("shared", "ise", 1.5, "rigid", 0.05)
    assert step.final_loads == (900.0, 1200.0)
    assert step.step_time == 0.1
    assert step.origin == "a.toml"
    assert duty.load_profile == ((0.0, 500.0), (0.05, 800.0))
    assert duty.duration == 0.2
    assert duty.final_loads == ()


def test_each_kind_refuses_the_other_kinds_keys_by_name_when_reading_a_file():
    with pytest.raises(SceneError, match=r"^a\.toml: tuning\.goal = 'mix': a duty-cycle key"):
        LoadStepScene.from_doc({"tuning": {"goal": "mix"}}, "a.toml")
    with pytest.raises(SceneError, match=r"^b\.toml: operating\.final_loads_n = \[1000\]: a load-step key"):
        DutyCycleScene.from_doc({"operating": {"load_profile_n": [[0.0, 500.0], [0.05, 800.0]],
                                               "final_loads_n": [1000]}}, "b.toml")
