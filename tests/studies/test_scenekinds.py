"""The registry of scene kinds (prsa_ctrl.studies.scenekinds): which kind each built-in scene
is, that dispatch goes through the registry, and what each problem type and report provide.
The behaviour of each kind's run is pinned by the CLI tests (tests/cli/test_tune.py)."""

import dataclasses

import pytest

from prsa_ctrl.errors import SceneError, UsageError
from prsa_ctrl.plant.plantfile import load_plant
from prsa_ctrl.studies.movescene import MoveScene
from prsa_ctrl.studies.scene import Scene, builtin_scenes, load_scene
from prsa_ctrl.studies.scenekinds import (KINDS, MOVE_FLAGS, DutyCycle, LoadStep, Move, MoveReport, SpeedReport,
                                          TuneOptions, file_kind, kind_of, problem)

EXPECTED = {"paper-load-step": "load-step", "paper-table3": "load-step", "robust-load-step": "load-step",
            "paper-heavy-slide": "load-step", "duty-ramp": "duty-cycle", "duty-trace": "duty-cycle",
            "paper-move": "move", "paper-slow-reversal": "move"}


def test_registry_names_three_kinds():
    assert KINDS == {"load-step": LoadStep, "duty-cycle": DutyCycle, "move": Move}
    for name, kind in KINDS.items():
        assert kind.name == name


def test_every_builtin_scene_has_exactly_one_kind():
    assert set(builtin_scenes()) == set(EXPECTED)
    for name, kind in EXPECTED.items():
        scene = load_scene(name)
        assert kind_of(scene) == kind, name
        assert [k for k, t in KINDS.items() if t.accepts(scene)] == [kind], name
        assert type(problem(scene)) is KINDS[kind]


def test_a_kalman_filter_scene_is_a_load_step_problem():
    scene = load_scene("paper-load-step").replace(estimator="kf", feedforward=True)
    assert kind_of(scene) == "load-step"


def test_problems_are_frozen_and_refuse_a_scene_of_another_kind():
    p = problem(load_scene("paper-load-step"))
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.scene = None
    with pytest.raises(SceneError, match="not a load-step scene; expected duty-cycle"):
        LoadStep(load_scene("duty-ramp"))
    with pytest.raises(SceneError, match="not a move scene; expected load-step"):
        Move(load_scene("paper-load-step"))


def test_kind_of_refuses_what_is_not_a_scene():
    with pytest.raises(TypeError, match="expected a Scene or a MoveScene"):
        kind_of({"name": "paper-load-step"})


def test_resolve_fixes_fidelity_and_records_once():
    plant = load_plant()
    scene, reason, spec = problem(load_scene("duty-ramp")).resolve(plant)
    assert scene.fidelity != "auto" and reason
    assert spec.problem.name == "duty-cycle" and len(spec.records) == len(scene.cases)
    assert spec.fidelity == scene.fidelity
    scene, _, spec = problem(load_scene("paper-table3")).resolve(plant)
    assert spec.records == () and spec.final_loads == (1000.0, 1500.0, 2000.0)
    move = load_scene("paper-move")
    assert problem(move).resolve(plant) is move


def test_reports_of_each_kind_own_json_text_and_export():
    for report in (SpeedReport, MoveReport):
        for method in ("as_dict", "format", "export_target", "file_lines"):
            assert callable(getattr(report, method)), (report, method)
    assert MoveReport.status == "ok" and MoveReport.timing_s is None


def test_options_are_frozen_with_quiet_defaults():
    o = TuneOptions()
    assert o.progress("x") is None and o.checkpoint() is None
    with pytest.raises(dataclasses.FrozenInstanceError):
        o.robust = True


def test_scene_types_are_the_registry_inputs():
    assert isinstance(load_scene("paper-move"), MoveScene)
    assert isinstance(load_scene("duty-ramp"), Scene)


def test_file_kind_reads_the_sections_before_loading():
    assert file_kind("paper-move") is Move
    assert file_kind("paper-load-step") is LoadStep
    assert file_kind("duty-ramp") is LoadStep  # both speed-loop kinds load alike; told apart once loaded
    assert file_kind("no-such-scene") is LoadStep  # its loader reports the missing file


def test_a_move_refuses_the_first_flag_it_does_not_honour_as_typed():
    given = [("plant", "--plant paper"), ("seed", "--seed 3"), ("robust", "--robust")]
    with pytest.raises(UsageError) as exc:
        Move.refuse_flags(given, "paper-move")
    assert str(exc.value) == ("--seed 3 does not apply to a move scene (paper-move); expected only --plant, --json, "
                              "--export, --plots, --quiet and --verbose")
    Move.refuse_flags([(dest, f"--{dest}") for dest in MOVE_FLAGS], "paper-move")  # every honoured flag passes
    assert LoadStep.flags is None and DutyCycle.flags is None and Move.flags == MOVE_FLAGS


def test_a_move_loads_scene_first_then_refuses_then_the_plant(tmp_path):
    """The order of a move's checks decides the message when several fail: a broken scene
    file before a refused flag, a refused flag before a missing plant."""
    never = pytest.fail
    with pytest.raises(UsageError, match="--seed 3 does not apply"):
        Move.load("paper-move", str(tmp_path / "no-plant.toml"), [("seed", "--seed 3")], never)
    bad = tmp_path / "bad-move.toml"
    bad.write_text("[move]\nprofile = 'trapezoidal'\n", encoding="utf-8")
    with pytest.raises(SceneError, match="bad-move.toml"):
        Move.load(str(bad), None, [("seed", "--seed 3")], never)
    plant, scene, typed = Move.load("paper-move", None, [("plant", "--plant paper")], never)
    assert isinstance(scene, MoveScene) and typed == [] and plant.name


def test_a_speed_loop_scene_is_loaded_by_the_command_overrides():
    sentinel = object()
    assert LoadStep.load("paper-load-step", None, [("seed", "--seed 3")], lambda: sentinel) is sentinel
