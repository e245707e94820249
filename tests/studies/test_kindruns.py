"""What differs between the speed-loop kinds (issue 33): asked of the kind, not branched on."""

import ast
import dataclasses
from pathlib import Path

import numpy as np
import pytest

import prsa_ctrl
from prsa_ctrl.drive.pid import PID
from prsa_ctrl.studies.kindruns import STEP_STUDIES, DutyRecord, ProfileRuns, StepRuns, duty_record, speed_kind
from prsa_ctrl.studies.movescene import load_move_scene
from prsa_ctrl.studies.scene import load_scene
from prsa_ctrl.studies.scenekinds import DutyCycle, LoadStep, problem
from prsa_ctrl.studies.sceneloops import loop_spec

PKG = Path(prsa_ctrl.__file__).parent


def test_speed_kind_is_the_registry_kind_of_a_speed_scene():
    assert type(speed_kind(load_scene())) is StepRuns
    assert type(speed_kind(load_scene("duty-ramp"))) is ProfileRuns
    # the registry's problems are the same kinds with the studies and the report added
    assert isinstance(problem(load_scene()), StepRuns)
    assert isinstance(problem(load_scene("duty-ramp")), ProfileRuns)
    assert speed_kind(load_scene()).name == LoadStep.name
    assert speed_kind(load_scene("duty-ramp")).name == DutyCycle.name


def test_speed_kind_refuses_a_move_scene():
    with pytest.raises(TypeError, match="expected a prsa_ctrl Scene"):
        speed_kind(load_move_scene("paper-move"))


def test_a_duty_cycle_takes_no_load_step_study():
    step, duty = speed_kind(load_scene()), speed_kind(load_scene("duty-ramp"))
    assert all(step.takes(s) for s in STEP_STUDIES)
    assert not any(duty.takes(s) for s in STEP_STUDIES)


def test_aggregate_mix_weighs_the_records_by_the_setpoint_share(paper_plant):
    sc = load_scene("duty-ramp").replace(goal="mix", setpoint_profile=((0.0, 31.4), (0.05, 40.0)), setpoint_share=0.25)
    spec = loop_spec(paper_plant, sc)
    assert spec.problem.aggregate([4.0, 8.0], spec) == pytest.approx(0.75 * 4.0 + 0.25 * 8.0)
    assert spec.problem.tuner_weights(spec) == [0.75, 0.25]
    worst = loop_spec(paper_plant, sc.replace(aggregate="worst"))
    assert worst.problem.aggregate([4.0, 8.0], worst) == 8.0


def test_load_steps_sum_and_take_no_tuner_weights(paper_plant):
    spec = loop_spec(paper_plant, load_scene("paper-table3").replace(aggregate="sum"))
    assert spec.problem.aggregate([1.0, 2.0, 4.0], spec) == 7.0
    assert spec.problem.tuner_weights(spec) is None
    assert spec.records == ()


def test_a_p_only_design_starts_below_the_setpoint_on_load_steps_only(paper_plant):
    p_only = type("D", (), {"pid": PID(0.06, 0.0), "estimator": "none"})()
    step = loop_spec(paper_plant, load_scene().replace(fidelity="rigid"))
    w, _ = step.problem.start(paper_plant, step, p_only)
    assert w < step.scene.setpoint_rad_s
    duty = loop_spec(paper_plant, load_scene("duty-ramp").replace(fidelity="rigid"))
    assert duty.problem.start(paper_plant, duty, p_only) == (duty.scene.setpoint_rad_s, duty.steady_torque_n_m)


def test_the_integral_warning_is_the_duty_cycles_only():
    slow = type("D", (), {"pid": PID(0.08, 1e-3)})()
    assert speed_kind(load_scene()).integral_warning(slow) is None
    assert "longer than the record" in speed_kind(load_scene("duty-ramp")).integral_warning(slow)


def test_headers_say_each_kind():
    assert " -> 1500 N at " in speed_kind(load_scene()).header("scene x", "Ms <= 1.4")
    assert ": duty cycle (" in speed_kind(load_scene("duty-ramp")).header("scene x", "Ms <= 1.4")


def _tests_scene_type(path: Path) -> bool:
    """Whether a module reads ``is_profile`` or asks ``isinstance(x, LoadStepScene/DutyCycleScene/MoveScene)``."""
    for n in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(n, ast.Attribute) and n.attr == "is_profile":
            return True
        if isinstance(n, ast.Call) and getattr(n.func, "id", None) == "isinstance" and len(n.args) == 2:
            if {getattr(x, "id", getattr(x, "attr", None)) for x in ast.walk(n.args[1])} & {"LoadStepScene",
                                                                                           "DutyCycleScene",
                                                                                           "MoveScene"}:
                return True
    return False


def test_no_module_outside_the_registry_branches_on_the_duty_cycle():
    """The speed-loop scene types are told apart by the registry alone (each kind's
    ``scene_type``, its ``accepts``): ``is_profile`` is gone, and no module names a scene type in
    an ``isinstance`` (issue 33; a move says it is no speed loop by its ``speed_loop``)."""
    from prsa_ctrl.studies.dutyscene import DutyCycleScene
    from prsa_ctrl.studies.movescene import MoveScene
    from prsa_ctrl.studies.scene import LoadStepScene, Scene
    from prsa_ctrl.studies.scenekinds import KINDS

    assert not hasattr(Scene, "is_profile")
    assert not hasattr(load_scene("duty-ramp"), "is_profile")
    readers = {p.relative_to(PKG).as_posix() for p in PKG.rglob("*.py") if _tests_scene_type(p)}
    assert readers == set()
    assert {k: v.scene_type for k, v in KINDS.items()} == {"load-step": LoadStepScene, "duty-cycle": DutyCycleScene,
                                                            "move": MoveScene}
    assert [k for k, v in KINDS.items() if v.accepts(load_scene("duty-ramp"))] == ["duty-cycle"]
    assert [k for k, v in KINDS.items() if v.accepts(load_scene())] == ["load-step"]


def test_the_duty_records_are_sampled_at_the_plant_period(paper_plant):
    spec = loop_spec(paper_plant, load_scene("duty-ramp"))
    for rec in spec.records:
        assert np.allclose(np.diff(rec.time_s), paper_plant.sample_time_s)


def test_a_duty_record_is_typed_frozen_and_read_by_attribute(paper_plant):
    """The duty-ramp file's own numbers: steps of -1000 N at 0.10 s and +1500 N at 0.13 s, changes
    at 0.02, 0.07, 0.10, 0.13 and 0.17 s, loads 500..2500 N (linearised at 1500 N), 300 rpm."""
    scene = load_scene("duty-ramp")
    rec = duty_record(paper_plant, scene, "load profile")
    assert type(rec) is DutyRecord
    assert rec.case == "load profile"
    np.testing.assert_allclose(rec.load_steps, ((0.10, -1000.0), (0.13, 1500.0)), rtol=1e-12)
    assert rec.breaks_s == pytest.approx((0.02, 0.07, 0.10, 0.13, 0.17))
    assert rec.f_lin_n == 1500.0
    assert rec.w_lin_rad_s == pytest.approx(300.0 * np.pi / 30.0, rel=1e-15)
    assert rec.setpoint_sequence_rad_s is None
    assert rec.load_sequence_n.size == rec.time_s.size - 1
    assert np.all(rec.setpoint_at_rad_s == rec.w_lin_rad_s)
    with pytest.raises(TypeError):
        rec["t"]  # noqa: B018 - a record is read by attribute, not indexed
    with pytest.raises(dataclasses.FrozenInstanceError):
        rec.f_lin_n = 0.0
    for arr in (rec.time_s, rec.setpoint_at_rad_s, rec.load_sequence_n):
        with pytest.raises(ValueError, match="read-only"):
            arr[0] = 1.0


def test_a_setpoint_record_reads_the_profile_at_each_sample(paper_plant):
    sc = load_scene("duty-ramp").replace(goal="mix", setpoint_profile=((0.0, 31.4), (0.05, 40.0)))
    rec = duty_record(paper_plant, sc, "setpoint profile")
    t = rec.time_s
    by_hand = np.where(t < 0.05, 31.4 + (40.0 - 31.4) * t / 0.05, 40.0)
    np.testing.assert_allclose(rec.setpoint_at_rad_s, by_hand, rtol=1e-12)
    assert rec.setpoint_sequence_rad_s[0] == 0.0
    np.testing.assert_allclose(rec.setpoint_sequence_rad_s[1:], by_hand[1:] - 31.4, rtol=1e-12, atol=1e-12)
    assert rec.load_sequence_n is None
    assert rec.load_n == sc.initial_load
    assert rec.w_lin_rad_s == pytest.approx(0.5 * (31.4 + 40.0))
    assert rec.load_steps == ()
    with pytest.raises(ValueError, match="case = 'bogus'"):
        duty_record(paper_plant, sc, "bogus")


@pytest.mark.parametrize(("change", "match"), [
    ({"case": "load"}, "case = 'load'; expected one of"),
    ({"load_sequence_n": np.zeros(3)}, r"load_sequence_n has shape \(3,\); expected 4 samples"),
    ({"load_sequence_n": None}, "load_sequence_n = None; expected 4 samples for a load profile"),
    ({"setpoint_sequence_rad_s": np.zeros(5)}, "setpoint_sequence_rad_s given for a load profile; expected None"),
    ({"setpoint_at_rad_s": [1.0, 1.0, np.nan, 1.0, 1.0]}, r"setpoint_at_rad_s\[2\] = nan; expected finite numbers"),
    ({"time_s": [0.0, 1.0, 1.0, 2.0, 3.0]}, "time_s runs .*expected increasing sample times from 0 s"),
    ({"f_lin_n": float("inf")}, "f_lin_n = inf; expected a finite number"),
    ({"load_n": "heavy"}, "load_n = 'heavy'; expected a finite number"),
    ({"breaks_s": (0.1, None)}, "breaks_s = None; expected a finite number"),
])
def test_a_duty_record_refuses_what_it_cannot_be(change, match):
    good = dict(case="load profile", time_s=np.arange(5) * 0.1, setpoint_at_rad_s=np.ones(5), load_n=500.0,
                setpoint_rad_s=1.0, load_sequence_n=np.zeros(4), setpoint_sequence_rad_s=None, load_steps=((0.1, 5.0),),
                breaks_s=(0.1,), w_lin_rad_s=1.0, f_lin_n=500.0)
    DutyRecord(**good)
    with pytest.raises(ValueError, match=match):
        DutyRecord(**{**good, **change})


def test_every_kind_says_what_it_is_and_a_move_takes_no_speed_study():
    move = problem(load_move_scene("paper-move"))
    assert move.described == "a move (cascade) scene"
    assert not any(move.takes(s) for s in STEP_STUDIES)
    assert problem(load_scene("duty-ramp")).described.startswith("a duty cycle (")
    assert problem(load_scene()).described == "a load-step scene"


def test_a_duty_cycle_tunes_and_verifies_through_the_kalman_filter(paper_plant):
    """A mix duty cycle (load and setpoint profiles, b = 0.5) with the Kalman filter and its load
    feed-forward: the loop models measure through the filter, the verified runs do too, and the
    linear prediction agrees with the nonlinear verification."""
    from prsa_ctrl.studies.autotune import tune_actuator
    from prsa_ctrl.studies.dutyscene import profile_rows
    from prsa_ctrl.studies.scene import Scene

    scene = Scene(load_profile=profile_rows([[0, 500], [0.005, 500], [0.015, 1500, "step"]], "x"),
                  setpoint_profile=profile_rows([[0, 30.0], [0.005, 30.0], [0.008, 33.0, "step"]], "x"),
                  duration=0.04, setpoint_weight=0.5, setpoint_share=0.25, candidates=1, fidelity="rigid",
                  accuracy=0.05, estimator="kf", feedforward=True)
    spec = loop_spec(paper_plant, scene)
    kf_loops, plain = spec.loop_models(paper_plant), spec.loop_models(paper_plant, estimator="none")
    assert [lp.name for lp in kf_loops] == ["load profile (KF)", "setpoint profile (KF)"]
    gains = (0.1, 20.0, 0.0)
    for a, b in zip(kf_loops, plain):
        ea, eb = a.error(gains), b.error(gains)
        assert np.max(np.abs(ea - eb)) > 1e-2 * np.max(np.abs(eb))
    rep = tune_actuator(paper_plant, scene, workers=1)
    best = rep.best
    assert best.estimator == "kf"
    assert best.pid.kff > 0
    assert len(best.verified) == 2
    assert len(best.estimation) == 2
    for e in best.estimation:  # the verified runs measured through the filter
        assert e["kf_speed_rms_rad_s"] < e["fd_speed_rms_rad_s"]
    assert best.objective_verified == pytest.approx(0.75 * best.verified[0].iae + 0.25 * best.verified[1].iae,
                                                    rel=1e-12)
    assert best.objective_verified == pytest.approx(best.objective_predicted, rel=0.02)
    assert any(b.name.startswith("tuned PI alone") for b in rep.baselines)
