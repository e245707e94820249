"""Issue 22: a scene's path from ``tune_actuator`` to the report. The scene is a studies-level
object: its kind resolves it once (``ResolvedProblem``, ``prsa_ctrl.studies.kindruns``) and the tuning layer gets
numbers and arrays only, so that no tuning module imports the studies, takes a ``scene``
parameter or reads a scene's attributes (checked at run time: every attribute read of a scene
object during a tune is traced to the module that made it)."""

import ast
import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import pytest

import prsa_ctrl
from prsa_ctrl.drive.pid import PID
from prsa_ctrl.studies import autotune
from prsa_ctrl.studies.autotune import Design, checked, checked_all, predict, predict_all, verify, verify_all
from prsa_ctrl.studies.movescene import MoveScene
from prsa_ctrl.studies.scene import DutyCycleScene, Scene, load_scene
from prsa_ctrl.studies.kindruns import ResolvedProblem
from prsa_ctrl.studies.sceneloops import actuator_loops, duty_record, linear_fidelity, loop_spec
from prsa_ctrl.studies.scenerobust import scenario_loops, scenarios

PKG = Path(prsa_ctrl.__file__).parent
TUNING = sorted((PKG / "tuning").glob("*.py"))


def _tree(path: Path) -> ast.AST:
    return ast.parse(path.read_text(encoding="utf-8"))


@pytest.mark.parametrize("path", TUNING, ids=lambda p: p.name)
def test_no_tuning_module_imports_the_studies(path):
    for node in ast.walk(_tree(path)):
        if isinstance(node, ast.ImportFrom):
            mod = node.module or ""
            top = mod.split(".")[0] if node.level == 2 else (mod.split(".")[1] if mod.startswith("prsa_ctrl.") else "")
            assert top != "studies", f"tuning/{path.name} imports {'.' * node.level}{mod}"
            if node.level == 1:
                assert mod.split(".")[0] != "studies", f"tuning/{path.name} imports .{mod}"
        elif isinstance(node, ast.Import):
            for a in node.names:
                assert not a.name.startswith("prsa_ctrl.studies"), f"tuning/{path.name} imports {a.name}"


#: Layers that may read a scene (studies and up); every module of the others is "below studies".
ABOVE = ("studies/", "io/", "plots/", "cli/", "app/")


def _scene_reads(run, classes=(Scene, ResolvedProblem, MoveScene)):
    """Run ``run()`` with every attribute read of a scene object recorded: the set of
    (module, function) of prsa_ctrl below the studies layer that read one (directly, by
    ``getattr`` duck typing, or through anything that holds the object)."""
    root = str(PKG) + "/"
    reads: set[tuple[str, str]] = set()
    saved = {cls: cls.__dict__.get("__getattribute__") for cls in classes}

    def spy(cls):
        base = cls.__getattribute__

        def get(self, name):
            f = sys._getframe(1)
            path = f.f_code.co_filename
            if path.startswith(root) and not path[len(root):].startswith(ABOVE):
                reads.add((path[len(root):], f.f_code.co_name))
            return base(self, name)
        return get

    for cls in classes:
        cls.__getattribute__ = spy(cls)
    try:
        out = run()
    finally:
        for cls, orig in saved.items():
            if orig is None:
                del cls.__getattribute__
            else:
                cls.__getattribute__ = orig
    return reads, out


#: Below the studies, the modules that still read a scene at run time (each entry goes when
#: its reader takes the scene's numbers instead: the scene registry of issue 33). (The plant
#: layer's uncertainty model read ``scene.robust`` by duck typing until the scene's sections
#: became types; the cascade model read the MoveScene until it took a CascadeSpec.)
STILL_READ: set = set()


def test_a_tune_reads_no_scene_below_the_studies(paper_plant):
    """Run time, not parameter names: a whole load-step tune (predict, verify, report) and the
    loop models of a Kalman-filter, a duty-cycle and a robust scene; no module below studies/
    reads the scene, except the exact list above."""
    step = load_scene().replace(duration=0.3, fidelity="rigid", accuracy=0.05)
    kf = load_scene().replace(fidelity="rigid", estimator="kf", feedforward=True)
    duty = load_scene("duty-ramp").replace(fidelity="rigid")
    robust = load_scene("robust-load-step").replace(fidelity="rigid")

    def work():
        rep = autotune.tune_actuator(paper_plant, step, workers=1)
        loops = [actuator_loops(paper_plant, s) for s in (kf, duty)]
        loops.append(scenario_loops(paper_plant, robust, scenarios(paper_plant, robust)[:2]))
        return rep, loops

    reads, (rep, loops) = _scene_reads(work)
    assert rep.best.verified is not None
    assert [len(x) for x in loops] == [len(kf.final_loads), len(duty.cases), 2]
    assert reads == STILL_READ


def test_the_trace_sees_a_read_below_the_studies(paper_plant):
    """The instrument itself: a tuning-layer function that reads a scene is seen (so an empty
    set above means no read, not a blind trace)."""
    from prsa_ctrl.tuning import loops as tuning_loops

    scene = load_scene()

    def work():
        code = compile("def peek(s):\n    return s.setpoint_rpm\n", tuning_loops.__file__, "exec")
        ns: dict = {}
        exec(code, ns)
        return ns["peek"](scene)

    reads, out = _scene_reads(work)
    assert out == scene.setpoint_rpm
    assert reads == {("tuning/loops.py", "peek")}


def test_the_move_cascade_reads_no_scene(paper_plant):
    """The move scene's cascade (tuning/cascade.py) takes the scene's numbers
    (``MoveScene.cascade_spec``): building the model and tuning the sequential design read
    nothing of the MoveScene below studies/, seen at run time."""
    from prsa_ctrl.studies.movescene import load_move_scene
    from prsa_ctrl.tuning.cascade import CascadeModel, sequential_design

    spec = load_move_scene("paper-move").cascade_spec()

    def work():
        model = CascadeModel(paper_plant, spec, fidelity="rigid", n_grid=40)
        return model, sequential_design(paper_plant, spec, model)

    reads, (model, seq) = _scene_reads(work)
    assert seq.method == "sequential"
    assert reads == STILL_READ


def test_the_move_cascade_receives_no_scene(paper_plant):
    """A whole move tune (``studies.move.tune_move``'s linear part): no tuning function is
    entered with a MoveScene argument."""
    from prsa_ctrl.studies.movescene import MoveScene, load_move_scene
    from prsa_ctrl.tuning import cascade

    scene = load_move_scene("paper-move")

    def run():
        spec = scene.cascade_spec()
        cm = cascade.CascadeModel(paper_plant, spec, fidelity="rigid", n_grid=40)
        return cascade.sequential_design(paper_plant, spec, cm)

    hits, seq = _tuning_frames_that_receive((MoveScene,), run)
    assert seq.method == "sequential"
    assert hits == set()


def _tuning_frames_that_receive(kinds: tuple, run):
    """Run ``run()`` and return every (module, function) of prsa_ctrl/tuning entered with an
    argument of one of ``kinds`` (or a list/tuple/dict holding one)."""
    root = str(PKG / "tuning")
    hits = set()

    def holds(v, depth=1):
        if isinstance(v, kinds):
            return True
        if depth and isinstance(v, (list, tuple)):
            return any(holds(x, depth - 1) for x in v[:32])
        if depth and isinstance(v, dict):
            return any(holds(x, depth - 1) for x in list(v.values())[:32])
        return False

    def prof(frame, event, arg):
        if event != "call" or not frame.f_code.co_filename.startswith(root):
            return
        co = frame.f_code
        n = co.co_argcount + co.co_kwonlyargcount + bool(co.co_flags & 4) + bool(co.co_flags & 8)
        if any(holds(frame.f_locals.get(name)) for name in co.co_varnames[:n]):
            hits.add((Path(co.co_filename).name, co.co_name))

    sys.setprofile(prof)
    try:
        out = run()
    finally:
        sys.setprofile(None)
    return hits, out


def test_building_the_loops_hands_the_tuning_layer_no_scene(paper_plant):
    """At run time: the loop models of a load-step, a Kalman-filter, a duty-cycle and a robust
    scene are built without any tuning function receiving the scene or its spec."""
    step = load_scene().replace(fidelity="rigid")
    kf = step.replace(estimator="kf", feedforward=True)
    duty = load_scene("duty-ramp").replace(fidelity="rigid")
    robust = load_scene("robust-load-step").replace(fidelity="rigid")

    def build():
        loops = [actuator_loops(paper_plant, s) for s in (step, kf, duty)]
        loops.append(scenario_loops(paper_plant, robust, scenarios(paper_plant, robust)[:2]))
        return loops

    hits, loops = _tuning_frames_that_receive((Scene, ResolvedProblem), build)
    assert hits == set()
    assert [len(x) for x in loops] == [len(step.final_loads), len(kf.final_loads), len(duty.cases), 2]


def test_the_resolved_problem_reads_the_scene_once_and_copies_none_of_its_fields(paper_plant):
    """Issue 33: the resolved problem is the kind's problem on the scene as run plus what the plant
    fixes (the duty cycle's records are ``duty_record``'s, the linearisation fidelity, the steady
    torque): no field mirrors a scene field (``LoopSpec`` is gone), and only a scene resolves
    (no function takes a scene or its resolved problem)."""
    from prsa_ctrl.studies.dutyscene import DutyCycleScene as Duty
    from prsa_ctrl.studies.kindruns import ProfileRuns, StepRuns
    from prsa_ctrl.studies.scene import LoadStepScene

    own = {f.name for f in dataclasses.fields(ResolvedProblem)}
    assert own == {"problem", "fidelity_reason", "linear_fidelity", "records", "steady_torque_n_m"}
    for scene_type in (LoadStepScene, Duty):
        assert not own & {f.name for f in dataclasses.fields(scene_type)}, scene_type
    for scene, kind in ((load_scene().replace(fidelity="multi-roller"), StepRuns), (load_scene("duty-ramp"), ProfileRuns)):
        spec = loop_spec(paper_plant, scene)
        with pytest.raises(TypeError, match="expected a prsa_ctrl Scene"):
            loop_spec(paper_plant, spec)
        assert type(spec.problem) is kind
        assert spec.problem.scene is scene
        assert spec.scene is scene
        assert spec.fidelity_reason == ""  # loop_spec keeps the scene's fidelity as it is
        assert spec.linear_fidelity == linear_fidelity(scene)
        assert spec.linear_fidelity == ("compliant" if scene.fidelity in ("multi-roller", "auto") else scene.fidelity)
        if isinstance(scene, DutyCycleScene):
            for case, rec in zip(scene.cases, spec.records):
                ref = duty_record(paper_plant, scene, case)
                assert rec.case == case
                for k in ("time_s", "setpoint_at_rad_s"):
                    np.testing.assert_array_equal(getattr(rec, k), getattr(ref, k))
        else:
            assert spec.records == ()
        assert math.isfinite(spec.steady_torque_n_m)
        assert spec.steady_torque_n_m > 0


def test_resolving_chooses_the_fidelity_once_and_says_why(paper_plant):
    """``resolve(plant)`` fixes ``fidelity = "auto"`` (``choose_fidelity``) in the problem's scene
    and keeps the reason; the scene it was asked of is left as it is."""
    from prsa_ctrl.studies.kindruns import speed_kind
    from prsa_ctrl.studies.scene import choose_fidelity

    scene = load_scene().replace(fidelity="auto")
    res = speed_kind(scene).resolve(paper_plant)
    want, why = choose_fidelity(scene)
    assert res.scene == want
    assert res.scene.fidelity != "auto"
    assert res.fidelity_reason == why
    assert scene.fidelity == "auto"
    assert res.linear_fidelity == linear_fidelity(want)
    set_by_file = load_scene().replace(fidelity="rigid")
    res = speed_kind(set_by_file).resolve(paper_plant)
    assert res.scene is set_by_file
    assert res.fidelity_reason == "rigid (set by the scene)"


def test_the_public_stages_take_a_scene_not_its_spec(paper_plant):
    """Issue 33: the spec is the pipeline's own; ``verify`` and the batched stages refuse it
    (they resolve the scene's fidelity themselves)."""
    spec = loop_spec(paper_plant, load_scene().replace(fidelity="auto"))
    d = Design("x", PID(0.08, 14.0), None)
    with pytest.raises(TypeError, match="expected a prsa_ctrl Scene"):
        verify(d, paper_plant, spec)
    with pytest.raises(TypeError, match="expected a prsa_ctrl Scene"):
        verify_all([d], paper_plant, spec, workers=1)


def test_the_batched_stages_equal_the_one_design_functions(paper_plant):
    """``predict_all``, ``verify_all`` (serial) and ``checked_all`` give, design by design,
    exactly what ``predict``, ``verify`` and ``checked`` give (the stages only reorder work)."""
    scene = load_scene().replace(duration=0.3, fidelity="rigid", accuracy=0.05)
    loops = actuator_loops(paper_plant, scene)
    pids = [PID(0.085, 14.7), PID(0.05, 5.0), PID(0.06, 0.0)]  # the last is P-only (own start point)
    designs = [Design(f"d{i}", p, loops[0].margins(p.gains)) for i, p in enumerate(pids)]
    batch = predict_all(designs, loops, paper_plant, scene)
    one = [predict(d, loops, paper_plant, scene) for d in designs]
    for a, b in zip(batch, one):
        assert a.objective_predicted == b.objective_predicted
        assert a.predicted == b.predicted
        assert a.predicted_start_speed == b.predicted_start_speed
    assert batch[2].predicted_start_speed < scene.setpoint_rad_s  # P-only settles below the setpoint
    vb = checked_all(verify_all(batch, paper_plant, scene, workers=1), paper_plant, scene)
    vo = [checked(verify(d, paper_plant, scene), paper_plant, scene) for d in one]
    for a, b in zip(vb, vo):
        assert a.objective_verified == b.objective_verified
        assert a.verified == b.verified
        assert a.flags == b.flags
        assert a.warnings == b.warnings
        assert a.status == b.status


def test_public_names_still_resolve():
    import prsa_ctrl.studies as studies
    import prsa_ctrl.tuning as tuning

    assert studies.actuator_loops is actuator_loops is autotune.actuator_loops
    assert studies.duty_record is duty_record
    assert studies.linear_fidelity is linear_fidelity
    assert prsa_ctrl.tune_robust_actuator is studies.tune_robust_actuator
    for gone in ("actuator_loops", "duty_record", "linear_fidelity", "tune_robust_actuator", "scenarios"):
        assert not hasattr(tuning, gone), gone
    assert callable(tuning.step_loops)
    assert callable(tuning.profile_loops)
    assert callable(tuning.tune_scenario_loops)
