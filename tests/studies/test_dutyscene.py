"""Tests of prsa_ctrl.studies.dutyscene: the duty-cycle scene's keys, and a key of the other
kind refused by name (not dropped) through prsa-tune."""

import pytest

from prsa_ctrl.cli.tune import main
from prsa_ctrl.errors import SceneError
from prsa_ctrl.studies.dutyscene import PROFILE_KEYS
from prsa_ctrl.studies.scene import DutyCycleScene, LoadStepScene, Scene, load_scene

LOAD_STEP = "[operating]\ninitial_load_n = 500.0\nfinal_loads_n = [1500.0]\n"
LOAD_DUTY = "[operating]\nload_profile_n = [[0, 500], [0.01, 500], [0.02, 1500]]\nduration_s = 0.1\n"
SETPOINT_DUTY = ("[operating]\nsetpoint_profile_rpm = [[0, 300], [0.01, 300], [0.02, 400]]\ninitial_load_n = 500.0\n"
                 "duration_s = 0.1\n")


def _refused(tmp_path, capsys, text):
    path = tmp_path / "mine.toml"
    path.write_text(text)
    rc = main(["--scene", str(path)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1, err
    assert "Traceback" not in err[0]
    return err[0]


@pytest.mark.parametrize("key, typed", [("goal", "'load'"), ("goal", "'mix'"), ("setpoint_weight", "1.0"),
                                        ("setpoint_share", "0.3")])
def test_a_duty_cycle_key_in_a_load_step_file_is_refused_by_name(tmp_path, capsys, key, typed):
    err = _refused(tmp_path, capsys, LOAD_STEP + f"[tuning]\n{key} = {typed}\n")
    assert f"mine.toml: tuning.{key} = {typed}: a duty-cycle key" in err
    assert "this scene is a load step" in err


@pytest.mark.parametrize("text, key", [
    (LOAD_DUTY + "final_loads_n = [1500.0]\n", "operating.final_loads_n = [1500.0]: a load-step key"),
    (LOAD_DUTY + "step_time_s = 0.01\n", "operating.step_time_s = 0.01: a load-step key"),
    (LOAD_DUTY + "initial_load_n = 500.0\n", "operating.initial_load_n = 500.0: a load-step key"),
    (SETPOINT_DUTY + "final_loads_n = [900.0]\n", "operating.final_loads_n = [900.0]: a load-step key"),
    (LOAD_DUTY + "[robust]\nsetpoints_rpm = [300.0]\n", "[robust]: a load-step section"),
    (SETPOINT_DUTY + "[spec]\nmax_drop_rpm = 5.0\n", "[spec]: a load-step section"),
])
def test_a_load_step_key_in_a_duty_cycle_file_is_refused_by_name(tmp_path, capsys, text, key):
    err = _refused(tmp_path, capsys, text)
    assert f"mine.toml: {key}" in err
    assert "this scene is a duty cycle (operating." in err


def test_a_setpoint_duty_cycle_keeps_its_constant_load(tmp_path):
    # initial_load_n is the load a setpoint-only duty cycle runs at: taken, not refused.
    path = tmp_path / "sp.toml"
    path.write_text(SETPOINT_DUTY.replace("500.0", "700.0"))
    sc = load_scene(str(path))
    assert isinstance(sc, DutyCycleScene)
    assert sc.initial_load == 700.0


def test_the_duty_cycle_keys_are_taken_by_a_duty_cycle_file(tmp_path):
    path = tmp_path / "d.toml"
    path.write_text(LOAD_DUTY + "[tuning]\ngoal = 'load'\nsetpoint_weight = 0.5\nsetpoint_share = 0.3\n")
    sc = load_scene(str(path))
    assert (sc.goal, sc.setpoint_weight, sc.setpoint_share) == ("load", 0.5, 0.3)
    assert set(PROFILE_KEYS) <= set(sc.as_dict())


def test_a_load_step_scene_refuses_a_setpoint_share_given_in_python():
    with pytest.raises(SceneError, match=r"setpoint_share = 0\.3; expected none on a load step"):
        Scene(setpoint_share=0.3)
    assert type(Scene(setpoint_share=0.5)) is LoadStepScene
