"""prsa_ctrl.studies.scene: the built-in scenes, scene files and their checks against a plant."""

import math
import re
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from prsa_ctrl import SceneError, load_plant
from prsa_ctrl.cli.tune import main
from prsa_ctrl.studies.scene import (MAX_RECORD_SAMPLES, POST_EVENT_SAMPLES, PRE_EVENT_SAMPLES, Scene, builtin_scenes, check_against_plant, choose_fidelity, holding_capacity_n, load_scene)

SCENE_DIR = Path(__file__).resolve().parents[2] / "tuning"


def test_builtin_scenes_are_the_repository_files():
    assert sorted(p.stem for p in SCENE_DIR.glob("*.toml")) == builtin_scenes()


def test_paper_scene_is_the_papers_step():
    s = load_scene()
    assert s.name == "paper-load-step"
    assert s.setpoint_rad_s == pytest.approx(300 * math.pi / 30)
    assert (s.initial_load, s.final_loads, s.step_time) == (500.0, (1500.0,), 0.2)
    assert s.controller == "pi"
    assert s.discrete
    assert s.fidelity == "auto"
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
    assert scene.fidelity == expected
    assert reason.startswith(expected)


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


# ------------------------------------------------------------------------------------------------
# Silent wrong results (issue 13): events the physics cannot resolve and records above the size
# limit are refused through the API as through the CLI.
# ------------------------------------------------------------------------------------------------

PLANT = load_plant()
TS = PLANT.sample_time_s


def test_pre_event_samples_match_the_verification():
    from prsa_ctrl.studies import autotune

    assert PRE_EVENT_SAMPLES == autotune._PRE_SAMPLES


@settings(max_examples=200)
@given(step=st.floats(1e-12, 20.0), after=st.floats(1e-6, 20.0))
def test_event_timing_and_record_size_are_checked_before_any_run(step, after):
    scene = Scene(step_time=step, duration=step + after + 1.001e-3)
    ok = (step >= PRE_EVENT_SAMPLES * TS and scene.duration - step >= POST_EVENT_SAMPLES * TS
          and scene.duration / TS <= MAX_RECORD_SAMPLES)
    try:
        check_against_plant(scene, PLANT)
    except SceneError as exc:
        assert not ok
        assert "\n" not in str(exc)
        assert "controller samples" in str(exc)
    else:
        assert ok


@settings(max_examples=200)
@given(loads=st.lists(st.floats(0.0, 1e6), min_size=2, max_size=4), rpm=st.floats(0.5, 6000.0))
def test_loads_beyond_the_holding_capacity_are_refused(loads, rpm):
    f0, finals = loads[0], tuple(loads[1:])
    try:
        scene = Scene(setpoint_rad_s=rpm * math.pi / 30, initial_load=f0, final_loads=finals)
    except SceneError:
        return  # a final load equal to the initial one
    cap = holding_capacity_n(PLANT, scene.setpoint_rad_s)
    try:
        check_against_plant(scene, PLANT)
    except SceneError as exc:
        msg = str(exc)
        bad_load = max(loads) > cap
        assert bad_load or rpm < 15.0 or len(set(finals)) < len(finals) or min(abs(f - f0) for f in finals) < 1.0, msg
        if bad_load and rpm >= 15.0:
            assert f"holds at most {cap:.0f} N" in msg
    else:
        assert max(loads) <= cap
        assert rpm >= 14.99


def test_scene_step_at_zero_is_refused_by_the_api():
    with pytest.raises(SceneError, match=r"step_time = 0; expected a time > 0 s"):
        Scene(step_time=0)


# --- Ctrl-C ---------------------------------------------------------------------------------------


# --- one real run: effective scene in the header, JSON like any user file -------------------------


def test_default_scene_passes_the_plant_checks():
    check_against_plant(load_scene(), PLANT)


# ------------------------------------------------------------------------------------------------
# Scene files (issue 13/14): absurd but well-typed values are refused with one line naming key,
# value, plausible range and file.
# ------------------------------------------------------------------------------------------------

ROOT = Path(__file__).resolve().parents[2]
SCENE = (ROOT / "tuning" / "paper-load-step.toml").read_text()
_HC = [HealthCheck.function_scoped_fixture]


def _scene_set(doc: str, key: str, value: str) -> str:
    pat = re.compile(rf"^{key} = [^#\n]*", re.M)
    assert pat.search(doc), key
    return pat.sub(lambda m: f"{key} = {value} ", doc, count=1)


def _one_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err, err
    return lines[0]


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
    assert re.search(match, line), line
    assert str(path) in line, line
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
        assert line.startswith("prsa-tune: error: ")
        assert str(path) in line
        assert not stand_in
    else:
        assert len(stand_in) == 1
        load_scene(path)  # accepted by the scene loader too
    stand_in.clear()


# --- which kind reads a file: each scene type claims its own documents (issue 33) -------------------

_MOVE = '[move]\nprofile = "trapezoidal"\ndistance_mm = 10.0\nmax_speed_mm_s = 30.0\nacceleration_m_s2 = 1.0\n'
_LOAD_PROFILE = "[operating]\nload_profile_n = [[0.0, 500.0], [0.1, 500.0], [0.1, 900.0, \"step\"]]\nduration_s = 0.3\n"


@pytest.mark.parametrize("doc, claimant", [
    ({}, "LoadStepScene"),
    ({"operating": {"final_loads_n": [1500.0]}}, "LoadStepScene"),
    ({"operating": {"setpoint_trace_csv": "t.csv"}}, "DutyCycleScene"),
    ({"operating": {"load_profile_n": []}}, "DutyCycleScene"),
    ({"move": {}}, "MoveScene"),
    ({"move": {}, "operating": {"final_loads_n": [1.0]}}, "MoveScene"),
    ({"operating": 3}, "LoadStepScene"),  # not a table: the load step reads it and says so
])
def test_exactly_one_scene_type_claims_each_kind_of_document(doc, claimant):
    from prsa_ctrl.studies.scene import SCENE_TYPES

    assert [t.__name__ for t in SCENE_TYPES if t.claims(doc)] == [claimant]


def test_the_scene_types_are_the_registrys_in_its_order():
    from prsa_ctrl.studies.scene import SCENE_TYPES
    from prsa_ctrl.studies.scenekinds import KINDS

    assert SCENE_TYPES == tuple(k.scene_type for k in KINDS.values())
    assert [t.kind_name for t in SCENE_TYPES] == list(KINDS)


def test_every_builtin_scene_is_read_by_the_type_that_claims_it():
    from prsa_ctrl.studies.scene import SCENE_TYPES
    from prsa_ctrl.studies.scenefile import locate_scene, read_scene_doc

    for name in builtin_scenes():
        doc = read_scene_doc(*locate_scene(name)[:2])
        claimed = [t for t in SCENE_TYPES if t.claims(doc)]
        assert len(claimed) == 1, name
        assert type(load_scene(name)) is claimed[0], name


def test_the_registry_says_which_scenes_are_moves_and_which_are_speed_loops():
    """What ``scenefile.is_move_scene`` answered (it is gone): the scene type that claims a file.
    The move files are told by their text (a ``[move]`` table), independently of the types."""
    import prsa_ctrl.studies as studies
    from prsa_ctrl.studies.scene import SCENE_TYPES, require_speed_scene
    from prsa_ctrl.studies.scenefile import locate_scene

    assert not hasattr(studies, "is_move_scene")
    by_text = {n for n in builtin_scenes()
               if re.search(r"^\[move\]", locate_scene(n)[0].read_text(encoding="utf-8"), re.M)}
    assert "paper-move" in by_text
    assert {n for n in builtin_scenes() if load_scene(n).kind_name == "move"} == by_text
    assert load_scene(None).kind_name == "load-step"
    assert [t.speed_loop for t in SCENE_TYPES] == [True, True, False]
    for name in builtin_scenes():
        scene = load_scene(name)
        if name in by_text:
            with pytest.raises(SceneError) as err:
                require_speed_scene(scene)
            assert str(err.value) == (f"{name}.toml (built-in): a move scene ([move] section, position cascade); "
                                      "expected a speed-loop scene here (prsa-tune --scene tunes move scenes)")
        else:
            assert require_speed_scene(scene) is scene
    with pytest.raises(TypeError, match="scene = dict; expected a prsa_ctrl scene"):
        require_speed_scene({"move": {}})
    with pytest.raises(SceneError):
        load_scene("nope")


def test_a_document_two_kinds_claim_is_refused_naming_both(tmp_path):
    path = tmp_path / "both.toml"
    path.write_text(_MOVE + _LOAD_PROFILE)
    with pytest.raises(SceneError) as err:
        load_scene(path)
    text = str(err.value)
    assert "\n" not in text
    assert text.startswith(f"{path}: read as 2 kinds of scene (duty-cycle, move); expected one")
    assert "load_profile_n" in text
    assert "[move] table" in text


def test_a_document_no_kind_claims_is_refused_naming_what_each_kind_has():
    from prsa_ctrl.studies.movescene import MoveScene
    from prsa_ctrl.studies.scene import parse_scene

    with pytest.raises(SceneError, match=r"^x\.toml: no scene kind reads this file; expected one of: a move scene has "
                                         r"a \[move\] table$"):
        parse_scene({"operating": {"final_loads_n": [900.0]}}, "x.toml", types=(MoveScene,))


def test_an_ambiguous_scene_file_exits_2_in_one_line_before_any_run(tmp_path, capsys, stand_in):
    path = tmp_path / "both.toml"
    path.write_text(_MOVE + _LOAD_PROFILE)
    assert main(["--scene", str(path)]) == 2
    line = _one_line(capsys)
    assert line.startswith(f"prsa-tune: error: {path}: read as 2 kinds of scene (duty-cycle, move)"), line
    assert not stand_in
