import math
from pathlib import Path

import pytest

from prsa_ctrl import SceneError
from prsa_ctrl.studies.scene import Scene, builtin_scenes, choose_fidelity, load_scene

SCENE_DIR = Path(__file__).resolve().parents[2] / "tuning"


def test_builtin_scenes_are_the_repository_files():
    assert sorted(p.stem for p in SCENE_DIR.glob("*.toml")) == builtin_scenes()


def test_paper_scene_is_the_papers_step():
    s = load_scene()
    assert s.name == "paper-load-step"
    assert s.setpoint_rad_s == pytest.approx(300 * math.pi / 30)
    assert (s.initial_load, s.final_loads, s.step_time) == (500.0, (1500.0,), 0.2)
    assert s.controller == "pi" and s.discrete and s.fidelity == "auto"
    # Speeds to 1 % need the compliant model (the rigid one is ~3.5 % off the drop).
    assert choose_fidelity(s)[0].fidelity == "compliant"


@pytest.mark.parametrize(
    "changes, expected",
    [
        ({"outputs": ("nut_speed",), "accuracy": 0.1}, "rigid"),
        ({"outputs": ("nut_speed",), "accuracy": 0.01}, "compliant"),
        ({"outputs": ("nut_speed", "contact_forces"), "accuracy": 0.2}, "compliant"),
        ({"outputs": ("per_roller_forces",)}, "multi-roller"),
        ({"fidelity": "rigid", "outputs": ("contact_forces",)}, "rigid"),
    ],
)
def test_choose_fidelity_picks_the_cheapest_that_delivers(changes, expected):
    scene, reason = choose_fidelity(Scene().replace(**changes))
    assert scene.fidelity == expected and reason.startswith(expected)


@pytest.mark.parametrize(
    "text, match",
    [
        ("[operating]\nsetpoint_rmp = 300\n", r"unknown key operating\.setpoint_rmp; expected one of operating\.setpoint_rpm"),
        ("[operating]\ninitial_load_n = 'heavy'\n", r"operating\.initial_load_n = 'heavy'; expected a float"),
        ("[operating]\nfinal_loads_n = [-10.0]\n", r"final_loads = -10\.0; expected loads >= 0 N"),
        ("[operating]\nfinal_loads_n = [500.0]\n", r"expected a load different from the initial 500 N"),
        ("[tuning]\nobjective = 'mse'\n", r"objective = 'mse'; expected one of ie, iae, itae, ise"),
        ("[tuning]\nms_max = 0.8\n", r"ms_max = 0\.8; expected a number in \(1, 10\)"),
        ("[operating]\nstep_time_s = 1.0\nduration_s = 0.5\n", r"duration = 0\.5; expected a time beyond step_time"),
        ("[outputs]\nneeded = ['torque']\n", r"outputs = 'torque'; expected one of nut_speed"),
        ("[verify]\ndiscrete = 1\n", r"verify\.discrete = 1; expected a bool"),
        ("[extras]\n", r"unknown section 'extras'"),
        ("[operating\n", r"invalid TOML"),
    ],
)
def test_bad_scene_files(tmp_path, text, match):
    path = tmp_path / "bad-scene.toml"
    path.write_text(text)
    with pytest.raises(SceneError, match=match) as err:
        load_scene(path)
    assert "bad-scene.toml" in str(err.value)


def test_unknown_scene_and_field():
    with pytest.raises(SceneError, match=r"unknown scene 'nope'; expected a built-in name \([^)]*paper-load-step"):
        load_scene("nope")
    with pytest.raises(SceneError, match=r"unknown scene field 'ms'; allowed: "):
        Scene().replace(ms=1.3)


@pytest.mark.parametrize(
    "changes, match",
    [
        ({"estimator": "ekf"}, r"estimator = 'ekf'; expected none or kf"),
        ({"feedforward": True}, r"feedforward = True; expected estimator = kf"),
        ({"estimator": "kf", "discrete": False}, r"expected discrete = true"),
        ({"estimator": "kf", "load_change_time_s": 0.0}, r"load_change_time_s = 0\.0; expected a positive time"),
    ],
)
def test_estimator_fields_are_validated(changes, match):
    with pytest.raises(SceneError, match=match):
        Scene().replace(**changes)
