"""prsa_ctrl.results (issue 22): result objects with one shape (frozen, ``status`` from one vocabulary, ``warnings``,
``as_dict``), verification that returns new objects, and figures that only draw."""

import dataclasses
import inspect
import math

import numpy as np
import pytest

from prsa_ctrl.drive.filters import LoopFilter, Notch
from prsa_ctrl.drive.pid import PID
from prsa_ctrl.identification.axis import AxisFit
from prsa_ctrl.identification.common import FitResult
from prsa_ctrl.results import STATUSES, is_converged, is_ok, status_head
from prsa_ctrl.studies import autotune, montecarlo, responses
from prsa_ctrl.studies.autotune import ActuatorTuning, Design, actuator_loops, checked, predict, verify
from prsa_ctrl.studies.axistune import AxisRetuning
from prsa_ctrl.studies.montecarlo import DesignYield, MonteCarloReport
from prsa_ctrl.studies.scene import load_scene
from prsa_ctrl.tuning.filtered import FilteredDesign
from prsa_ctrl.tuning.robust import RobustTuning


@pytest.fixture(scope="module")
def small(paper_plant):
    """The paper plant, a short rigid load-step scene, its loops and the paper's PI predicted."""
    scene = load_scene().replace(duration=0.3, fidelity="rigid", accuracy=0.05)
    loops = actuator_loops(paper_plant, scene)
    pid = PID(0.085, 14.7, tf=4 * paper_plant.sample_time_s)
    d = predict(Design("paper PI", pid, loops[0].margins(pid.gains)), loops, paper_plant, scene)
    return paper_plant, scene, loops, d


def test_verify_returns_a_new_design_and_leaves_its_argument(small):
    plant, scene, _, d = small
    before = dataclasses.asdict(d)
    v = verify(d, plant, scene)
    assert v is not d
    assert d.verified == ()
    assert d.verified_runs == ()
    assert math.isnan(d.objective_verified)
    assert dataclasses.asdict(d).keys() == before.keys()
    assert d.status == "unverified"
    assert len(v.verified) == len(scene.final_loads)
    assert v.objective_verified > 0
    assert v.status == "ok"
    assert v.ok
    assert v.pid == d.pid
    assert v.predicted == d.predicted
    c = checked(v, plant, scene)
    assert c is not v
    assert c.flags == ()
    assert v.flags == ()


def test_predict_returns_a_new_design(small):
    plant, scene, loops, d = small
    bare = Design("x", d.pid, d.margins)
    p = predict(bare, loops, plant, scene)
    assert bare.predicted == ()
    assert math.isnan(bare.objective_predicted)
    assert p.objective_predicted == pytest.approx(d.objective_predicted, rel=0, abs=0)


@pytest.mark.parametrize("cls", [Design, ActuatorTuning, FilteredDesign, RobustTuning, MonteCarloReport, DesignYield,
                                 FitResult, AxisFit, AxisRetuning])
def test_results_are_frozen_with_status_warnings_and_as_dict(cls):
    assert dataclasses.is_dataclass(cls)
    assert cls.__dataclass_params__.frozen
    names = {f.name for f in dataclasses.fields(cls)} | {n for n, _ in inspect.getmembers(cls)}
    if cls is not DesignYield:
        assert {"status", "warnings", "as_dict"} <= names, cls
        # converged / ok are derived from status (properties), never stored beside it
        fields = {f.name for f in dataclasses.fields(cls)}
        assert "converged" not in fields
        assert "ok" not in fields
        assert isinstance(getattr(cls, "ok"), property)


def test_frozen_design_rejects_assignment(small):
    with pytest.raises(dataclasses.FrozenInstanceError):
        small[3].flags = ("x",)


def test_status_vocabulary():
    assert status_head("optimal") == "optimal"
    assert is_converged("optimal (acceptable level)")
    assert status_head("not proven optimal: residual 3e-2 > 1e-3") == "not proven optimal"
    assert not is_converged("not proven optimal: residual")
    assert not is_ok("not converged: x")
    assert status_head("no lowpass1 helps: the objective is not 1 % below") == "no <kind> helps"
    assert is_ok("ok")
    assert not is_ok("flagged: the nut reverses")
    assert status_head("interrupted: 2 of 5 samples")
    for bad in ("fine", "optimalish", "", "flagged nut"):
        with pytest.raises(ValueError, match="status = "):
            status_head(bad)
    assert set(STATUSES) >= {"optimal", "not converged", "ok", "flagged", "unverified", "interrupted"}


def test_filtered_design_status_and_filter_as_dict():
    pid = PID(0.1, 10.0)
    lf = LoopFilter(Notch(300.0, 90.0, -20.0), "torque_command")
    assert lf.as_dict(2.5e-4) == lf.to_dict(2.5e-4)
    assert lf.as_dict()["kind"] == "notch"  # to_dict: deprecated alias
    good = FilteredDesign(pid, lf, 0.01, 1.4, 0.1, "optimal")
    assert good.converged
    assert good.ok
    assert good.as_dict()["filter"] == lf.as_dict()
    assert good.as_dict()["warnings"] == []
    bad = FilteredDesign(pid, None, 0.01, 1.4, 0.1, "not converged: ipopt failed", warnings=("x",))
    assert not bad.converged
    assert not bad.ok
    assert bad.as_dict()["warnings"] == ["x"]
    rejected = FilteredDesign(pid, None, 0.01, 1.4, 0.1, "no notch helps: too shallow",
                              {"reference_status": "optimal"})
    assert rejected.converged
    assert rejected.ok


def test_robust_recommendation_returns_a_new_study():
    comp = {"objective": "iae", "ms_max": 1.4, "designs": {
        "nominal": {"ms_violations": 2, "worst_objective": 0.03}, "robust": {"ms_violations": 0, "worst_objective": 0.08}}}
    rt = RobustTuning(PID(0.085, 14.7), PID(0.045, 6.8), (object(),) * 3, comp, {}, None)
    rec = rt.recommend(None)
    assert rt.recommended == {}
    assert rec["design"] == "robust"
    rt2 = rt.with_recommendation(None)
    assert rt2 is not rt
    assert rt2.recommended == rec
    assert rt.recommended == {}
    assert rt.status == "optimal"
    assert rt.warnings == ()


def test_monte_carlo_report_status():
    y = DesignYield("a", {}, 1, 2, 0.5, (0.1, 0.9), {}, None, {}, {}, 1, "")
    full = MonteCarloReport(2, 2, 0, "serial", 1, True, {}, {}, [], (y,), 0.0)
    part = dataclasses.replace(full, n=5, complete=False)
    assert full.status == "ok"
    assert full.ok
    assert part.status == "interrupted: 2 of 5 samples"
    assert not part.ok
    assert full.warnings == ("a: 1 of 2 samples failed to simulate",)


def test_figures_only_draw(small, monkeypatch):
    """The figure data is computed in studies; drawing it calls no simulation, tuning or verification."""
    import matplotlib.pyplot as plt

    from prsa_ctrl.plots import loop

    plant, scene, loops, d = small
    data = responses.design_responses(plant, scene, d.pid, loops=loops)
    assert data.design.verified
    assert data.setpoint_step is not None
    assert data.stability == "stable"

    def boom(*a, **k):
        raise AssertionError("a figure computed")

    from prsa_ctrl.sim import engine

    for mod, names in ((responses, ("verify", "predict", "simulate", "actuator_loops", "linearize")),
                       (autotune, ("verify", "predict", "actuator_loops")),
                       (engine, ("run",)),  # the kinds' runs (studies/kindruns.py) import it when they run
                       (loop, ("design_responses", "report_responses", "stable_design_responses"))):
        for n in names:
            monkeypatch.setattr(mod, n, boom)
    figs = loop.draw_design_figures(data)
    assert set(figs) == {"plant_bode", "loop_bode", "sensitivity", "load_step", "setpoint_step"}
    same = loop.design_figures(data)  # a FigureData is drawn as it is
    assert set(same) == set(figs)
    for f in (*figs.values(), *same.values()):
        plt.close(f)


def test_no_matplotlib_outside_plots_in_studies_and_tuning():
    import pathlib

    import prsa_ctrl

    root = pathlib.Path(prsa_ctrl.__file__).parent
    for rel in ("studies/autotune.py", "studies/montecarlo.py", "studies/responses.py", "studies/paper.py",
                "tuning/filtered.py", "tuning/robust.py", "tuning/actuatorloops.py"):
        text = (root / rel).read_text()
        assert "import matplotlib" not in text, rel
        assert 'module("matplotlib' not in text, rel
        assert "from ..io" not in text, rel
        assert "import _predict" not in text, rel
        assert len(text.splitlines()) < 1000, rel


def test_report_pairs_come_from_the_report(small):
    """The comparison designs are verified once by tune_actuator and kept in the report (the
    figures used to tune and verify them again)."""
    plant, scene, loops, d = small
    v = checked(verify(d, plant, scene), plant, scene)
    b = checked(verify(Design("base", PID(0.05, 5.0), loops[0].margins((0.05, 5.0, 0.0))), plant, scene),
                plant, scene)
    above = dataclasses.replace(v, name="tuned (Ms <= 1.6)")
    comp = {"baseline": "base", "tuned": above.name, "tuned_gains": above.pid.as_dict()}
    rep = ActuatorTuning(plant, scene, v, (v,), (b,), (comp,), {}, {}, (), tuple(loops), "",
                         comparison_designs=(above,))
    (pair,) = rep.comparison_pairs()
    assert pair[0] is b
    assert pair[1].pid == above.pid
    assert pair[1].verified_runs
    assert np.isfinite(rep.best.objective_verified)


def test_report_figures_only_draw(small, monkeypatch):
    """A report's figure data (loop response, landscape, baseline pairs) is computed once in
    studies; drawing it evaluates no loop model grid, simulation or verification."""
    import matplotlib.pyplot as plt

    from prsa_ctrl.plots import loop

    plant, scene, loops, d = small
    v = checked(verify(d, plant, scene), plant, scene)
    b = checked(verify(Design("base", PID(0.05, 5.0), loops[0].margins((0.05, 5.0, 0.0))), plant, scene),
                plant, scene)
    comp = {"baseline": "base", "tuned": v.name, "tuned_gains": v.pid.as_dict()}
    rep = ActuatorTuning(plant, scene, v, (v,), (b,), (comp,), {}, {}, (), tuple(loops), "")
    data = responses.report_responses(rep)
    assert data.landscape is not None
    assert data.landscape.objective.shape == (40, 40)
    assert len(data.pairs) == 1

    def boom(*a, **k):
        raise AssertionError("a figure computed")

    for n in ("landscape", "report_responses", "design_responses"):
        monkeypatch.setattr(loop, n, boom)
    for n in ("verify", "predict", "simulate", "landscape"):
        monkeypatch.setattr(responses, n, boom)
    figs = loop.draw_report_figures(data)
    assert set(figs) == {"plant_bode", "loop_bode", "sensitivity", "landscape", "load_step", "baselines"}
    for f in figs.values():
        plt.close(f)


# --- issue 31: frozen all the way down (read-only mappings, lists and arrays that still pickle) -----

def _mutations(obj):
    """Every way of changing a container in place, each expected to raise TypeError/ValueError."""
    if isinstance(obj, np.ndarray):
        def write():
            obj[...] = 0
        return [write]
    if isinstance(obj, dict):
        k = next(iter(obj), "k")
        return [lambda: obj.__setitem__("new", 1), lambda: obj.pop(k), lambda: obj.update(x=1), obj.clear,
                lambda: obj.setdefault("new", 1), lambda: obj.__delitem__(k), obj.popitem]
    if isinstance(obj, list):
        return [lambda: obj.append(1), lambda: obj.__setitem__(0, 1), lambda: obj.extend([1]), obj.clear,
                lambda: obj.insert(0, 1), obj.pop, obj.sort, obj.reverse]
    raise AssertionError(f"not a container: {type(obj)}")


def _assert_read_only(obj, what):
    before = repr(obj)
    for change in _mutations(obj):
        with pytest.raises((TypeError, ValueError)):
            change()
    assert repr(obj) == before, what


def _tuning_result(small):
    from prsa_ctrl.tuning.generic import tune_loops

    plant, scene, loops, _ = small
    return tune_loops(loops[:1], ms_max=1.4, controller="pi")


def test_plant_uncertainty_values_and_sources_are_read_only_and_pickle(paper_plant):
    import pickle

    p = paper_plant
    assert isinstance(p.uncertainty, dict)
    assert p.uncertainty  # still a dict to everything that reads it
    for what, m in (("uncertainty", p.uncertainty), ("values", p.values), ("sources", p.sources),
                    ("an uncertainty entry", next(iter(p.uncertainty.values())))):
        _assert_read_only(m, what)
    q = pickle.loads(pickle.dumps(p))  # plain pickle: a process pool with spawn (was: cannot pickle mappingproxy)
    assert q.uncertainty == p.uncertainty
    assert q.values == p.values
    assert q.sources == p.sources
    _assert_read_only(q.uncertainty, "unpickled uncertainty")
    assert p.with_params({"nut.inertia_kg_m2": 3e-4}).uncertainty == p.uncertainty
    mutable = dict(p.uncertainty)  # a copy is the user's to change
    mutable["x"] = 1
    assert "x" not in p.uncertainty


def test_simrun_arrays_and_info_are_read_only_also_after_pickling(paper_plant):
    import pickle

    from prsa_ctrl.sim.engine import run

    r = run(paper_plant, duration=0.01, controller=PID(0.085, 14.7), fidelity="rigid", energy=True)
    for what in ("time", "outputs", "states", "inputs"):
        a = getattr(r, what)
        assert isinstance(a, np.ndarray), what
        assert not a.flags.writeable, what
        _assert_read_only(a, what)
    assert not r.output("nut_speed").flags.writeable  # a row of a read-only array is read-only
    _assert_read_only(r.info, "info")
    _assert_read_only(r.energy, "energy")
    assert all(not v.flags.writeable for v in r.energy.values() if isinstance(v, np.ndarray))
    s = pickle.loads(pickle.dumps(r))
    assert all(not getattr(s, n).flags.writeable for n in ("time", "outputs", "states", "inputs"))
    assert np.array_equal(s.outputs, r.outputs)
    assert s.info == r.info
    _assert_read_only(s.info, "unpickled info")
    assert s.to_response() is not None


def test_tuning_result_containers_are_read_only_and_pickle(small):
    import copy
    import json
    import pickle

    res = _tuning_result(small)
    assert res.per_loop == list(res.per_loop)
    assert len(res.margins) == 1  # equal to plain lists
    for what in ("per_loop", "margins", "stats"):
        _assert_read_only(getattr(res, what), what)
    nested = [v for v in res.stats.values() if isinstance(v, (dict, list))]
    assert nested  # e.g. first_order
    for v in nested:
        _assert_read_only(v, "a nested stats entry")
    json.dumps(res.as_dict(), allow_nan=False)
    for twin in (pickle.loads(pickle.dumps(res)), copy.deepcopy(res)):
        assert twin.pid == res.pid
        assert twin.per_loop == res.per_loop
        assert twin.stats == res.stats
        _assert_read_only(twin.stats, "copied stats")
        _assert_read_only(twin.per_loop, "copied per_loop")
    assert dataclasses.asdict(res)["per_loop"] == list(res.per_loop)


def test_every_report_method_is_an_alias_of_as_dict():
    """``as_dict()`` is the one name of a result's JSON-ready form; where a class had ``report()``
    it stays as the same function (its former name), and no class defines its own ``report``."""
    import ast
    import pathlib

    import prsa_ctrl
    from prsa_ctrl.identification.axis import AxisReplay
    from prsa_ctrl.identification.twomass import FrfModelFit, StructureChoice

    for cls in (FitResult, AxisFit, AxisReplay, FrfModelFit, StructureChoice):
        assert cls.report is cls.as_dict, cls
    own = []
    for path in pathlib.Path(prsa_ctrl.__file__).parent.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ClassDef):
                own += [f"{path.name}:{node.name}" for f in node.body
                        if isinstance(f, ast.FunctionDef) and f.name == "report"]
    assert own == []
