"""Design to the spec: proposals from the linear scenario models, chosen by the nonlinear Monte
Carlo on common samples, reported on fresh ones (issue 34)."""

import numpy as np
import pytest

from prsa_ctrl.drive.pid import PID
from prsa_ctrl.plant.plantfile import load_plant
from prsa_ctrl.studies.scene import load_scene
from spec_scenes import BALL_CUT_SCENE, ROLLER_SPEC_SCENE, check_rule as _check_rule, roller_16k_plant


@pytest.fixture(scope="module")
def roller(tmp_path_factory):
    path = tmp_path_factory.mktemp("designspec") / "rollerscrew-spec.toml"
    path.write_text(ROLLER_SPEC_SCENE, encoding="utf-8")
    return load_plant("rollerscrew-30x5"), load_scene(str(path))


@pytest.fixture(scope="module")
def roller16k(tmp_path_factory):
    """The issue's scene on the roller screw with a 16 kHz speed loop (where the rule of thumb
    reaches ~90 %)."""
    d = tmp_path_factory.mktemp("designspec16k")
    (d / "rs16k.toml").write_text(roller_16k_plant(), encoding="utf-8")
    (d / "scene.toml").write_text(ROLLER_SPEC_SCENE, encoding="utf-8")
    return load_plant(str(d / "rs16k.toml")), load_scene(str(d / "scene.toml"))


def test_linear_yield_grid_agrees_with_an_independent_linear_check(roller16k):
    """The grid's linear yield of each proposed design, recomputed sample by sample from the
    loop's own trajectory (sim.metrics.load_step_metrics) and its true Ms (peak_sensitivity):
    equal, up to samples within 1 % of a bound (the grid's Ms is on the model's frequency grid)."""
    from prsa_ctrl.plant.uncertainty import apply, uncertainty_model
    from prsa_ctrl.sim.metrics import load_step_metrics
    from prsa_ctrl.studies.designspec import linear_yield_grid
    from prsa_ctrl.studies.mcjob import draw_sample
    from prsa_ctrl.studies.paper import default_pid
    from prsa_ctrl.studies.sceneloops import actuator_loops
    from prsa_ctrl.studies.scenerobust import operating_points

    plant, scene = roller16k
    spec = dict(scene.sections.as_dict()["spec"])
    n, seed = 6, 5
    g = linear_yield_grid(plant, scene, [default_pid(plant), PID(0.3, 50.0)], spec, seed=seed, n=n, size=5, picks=3)
    assert g["points"] == 25
    assert g["samples"] == n
    assert 1 <= len(g["designs"]) <= 3
    assert max(g["linear_yield"].values()) == g["best_linear_yield"]
    unc, ops = uncertainty_model(plant, scene.sections.plant_overrides), operating_points(scene)
    for name, pid in g["designs"].items():
        assert pid.kd == 0
        assert 0.15 <= pid.kp <= 1.3  # inside the grid's span: half the smallest .. twice the largest
        passed = unsure = 0
        for i in range(n):
            values, op, _ = draw_sample(unc, ops, seed, i)
            sc = scene.replace(setpoint_rad_s=ops[op][0], final_loads=(ops[op][1],))
            lp = actuator_loops(apply(plant, values), sc)[0]
            assert lp.is_stable(pid.gains)
            e = lp.error(pid.gains)
            t = np.arange(e.size) * lp.h
            m = load_step_metrics(t, sc.setpoint_rad_s - e, sc.setpoint_rad_s, 0.0)
            ratios = [m.peak_drop_rad_s / spec["peak_drop_rad_s"], m.recovery_time_s / spec["recovery_time_s"],
                      lp.peak_sensitivity(pid.gains) / spec["ms"]]
            passed += max(ratios) <= 1.0
            unsure += any(abs(r - 1.0) < 0.01 for r in ratios)
        assert abs(passed / n - g["linear_yield"][name]) <= unsure / n + 1e-12, (name, passed, unsure)



def test_linear_yield_grid_is_the_same_on_two_processes(roller16k):
    """The grid's samples shared between two forked processes (contiguous blocks) give the same
    linear yields, proposals and best yield as one process: each sample is scored alone."""
    from prsa_ctrl.studies.designspec import linear_yield_grid
    from prsa_ctrl.studies.paper import default_pid

    plant, scene = roller16k
    spec = dict(scene.sections.as_dict()["spec"])
    kw = dict(seed=7, n=16, size=4, picks=3)
    one = linear_yield_grid(plant, scene, [default_pid(plant), PID(0.3, 50.0)], spec, workers=1, **kw)
    two = linear_yield_grid(plant, scene, [default_pid(plant), PID(0.3, 50.0)], spec, workers=2, **kw)
    assert one["proposed"]
    assert one["linear_yield"] == two["linear_yield"]
    assert one["proposed"] == two["proposed"]
    assert one["best_linear_yield"] == two["best_linear_yield"]
    assert one["designs"] == two["designs"]


def test_proposals_tuned_in_two_processes_equal_the_serial_ones(roller):
    """The Ms levels' nominal and robust tunings in forked processes: the same gains and
    statuses as tuned one after another in this process (a tuner's result does not depend on
    what it solved before), in the levels' order."""
    from prsa_ctrl.plant.uncertainty import uncertainty_model
    from prsa_ctrl.studies import designspec
    from prsa_ctrl.studies.scenerobust import scenario_loops, scenarios

    plant, scene = roller
    unc = uncertainty_model(plant, scene.sections.plant_overrides)
    scens = scenarios(plant, scene, unc=unc)
    args = (scenario_loops(plant, scene, scens), scens, unc, scene.objective, scene.controller, scene.mt_max, "worst")
    serial = designspec._tune_levels(args, [1.3, 1.6], 1)
    forked = designspec._tune_levels(args, [1.3, 1.6], 2)
    assert [m for m, _ in forked] == [1.3, 1.6]
    for (m, a), (_, b) in zip(serial, forked):
        assert not isinstance(a, str), a
        assert [(k, p.gains, st) for k, p, st in a] == [(k, p.gains, st) for k, p, st in b], m


def test_design_to_spec_decides_among_the_near_max_designs_on_more_samples(roller16k):
    """A smaller case (one Ms level, 6 screen, 12 decision and 6 fresh samples): the grid's
    proposals are evaluated; the decision runs only designs of (near-)maximal screen yield, on
    the screen's samples and more; the chosen one is the decision's recommendation; the rule
    holds on both tables."""
    from prsa_ctrl.studies.designspec import MAX_FINALISTS, design_to_spec
    from prsa_ctrl.studies.paper import default_pid

    plant, scene = roller16k
    r = design_to_spec(plant, scene, n_search=6, n_decide=12, n_final=6, seed=2, ms_levels=(1.5,),
                       extra={"rule of thumb": default_pid(plant)})
    assert r.grid is not None
    assert r.grid["proposed"]
    assert set(r.grid["proposed"]) <= set(r.designs)
    assert {row["name"] for row in r.search["rows"]} == set(r.designs)
    assert r.chosen is not None
    near = {row["name"] for row in r.search["rows"] if row["near_max"] and row["passed"] > 0}
    if r.decide is None:
        assert len(near) == 1
        assert r.chosen in near
    else:
        rows = r.decide["rows"]
        assert {x["name"] for x in rows} <= near
        assert 2 <= len(rows) <= MAX_FINALISTS
        assert all(x["samples"] == 12 for x in rows)
        assert r.chosen == r.decide["recommended"]
        _check_rule({**r.decide, "table": rows, "name": r.chosen, "design": r.chosen})
    assert r.final_yield.n == 6
    assert r.final_seed == 3
    text = r.format("iae")
    assert "linear-yield grid" in text
    assert f"chosen: {r.chosen}" in text


def _acceptance(plant, scene, *, expect_95: bool):
    """The issue's acceptance on one scene: the recommended design's yield on 200 fresh samples
    is at least the best yield of any design the run evaluated minus the two Wilson 95 %
    half-widths; with ``expect_95`` (the rule of thumb reaches ~90 % or more there) at least 95 %.
    The fresh yield is checked by an independent Monte Carlo of the chosen gains."""
    from prsa_ctrl.studies.designspec import design_to_spec
    from prsa_ctrl.studies.montecarlo import run_monte_carlo, wilson_interval
    from prsa_ctrl.studies.paper import default_pid

    rule = default_pid(plant)
    r = design_to_spec(plant, scene, n_search=40, n_final=200, seed=0, extra={"rule of thumb": rule}, workers=2)
    assert r.chosen is not None
    fy = r.final_yield
    half = lambda k, n: (lambda lo, hi: (hi - lo) / 2)(*wilson_interval(k, n))  # noqa: E731
    tables = [r.search["rows"]] + ([r.decide["rows"]] if r.decide else [])
    for rows in tables:
        for row in rows:
            assert fy.yield_ >= row["yield"] - half(row["passed"], row["samples"]) - half(fy.passed, fy.n) - 1e-12, row
    ref = run_monte_carlo(plant, scene, {"x": r.pid}, 200, seed=1, workers=2, quiet=True,
                          spec=dict(scene.sections.as_dict()["spec"])).designs[0]
    assert (ref.passed, ref.n) == (fy.passed, fy.n)
    text = r.format("iae")
    assert f"* {r.chosen}" in text
    assert f"({fy.passed}/200)" in text
    if expect_95:
        assert fy.yield_ >= 0.95, text
    return r


@pytest.mark.slow
def test_acceptance_roller_screw_16k_reaches_95_percent_where_the_rule_of_thumb_nearly_does(roller16k):
    """Issue 34's case on a 16 kHz speed loop: the rule of thumb passes ~90 %; the recommended
    design reaches >= 95 % on 200 fresh samples and the rule of thumb does not beat it."""
    r = _acceptance(*roller16k, expect_95=True)
    rule = next(row for row in r.search["rows"] if row["name"] == "rule of thumb")
    assert rule["yield"] >= 0.85  # the case the acceptance is about: the rule of thumb nearly meets the spec


@pytest.mark.slow
def test_acceptance_roller_screw_built_in(roller):
    """Issue 34's case on the built-in 4 kHz roller screw (the rule of thumb fails Ms there)."""
    _acceptance(*roller, expect_95=False)


@pytest.mark.slow
def test_acceptance_ball_screw_cut(tmp_path):
    """A feed axis entering a cut (BALL_CUT_SCENE): the rule of thumb breaks Ms on every sample;
    the recommended design is within the intervals of the best."""
    path = tmp_path / "ballscrew-cut-spec.toml"
    path.write_text(BALL_CUT_SCENE, encoding="utf-8")
    r = _acceptance(load_plant("ballscrew-32x10"), load_scene(str(path)), expect_95=False)
    assert next(row for row in r.search["rows"] if row["name"] == "rule of thumb")["passed"] == 0


@pytest.fixture(scope="module")
def no_grid(roller):
    """One design to the spec without the linear-yield grid and without a decision round
    (``n_decide`` = ``n_search``: 4 search and 4 fresh samples, two Ms levels and a given design),
    shared by the test of the choice and the test of ``grid=False`` (each ran its own: the level
    tunings cost most of a run)."""
    from prsa_ctrl.studies.designspec import design_to_spec

    plant, scene = roller
    extra = {"rule of thumb": PID(0.6361989083357843, 79.94711266598183)}
    return design_to_spec(plant, scene, n_search=4, n_decide=4, n_final=4, seed=3, ms_levels=(1.4, 1.5), extra=extra,
                          grid=False)


def test_design_to_spec_without_the_grid_proposes_none_of_its_designs(no_grid):
    assert no_grid.grid is None
    assert not any(k.startswith("linear-yield grid") for k in no_grid.designs)


def test_design_to_spec_decides_on_more_samples_only_when_asked_for_more_than_the_search(no_grid):
    assert no_grid.decide is None


def test_design_to_spec_chooses_by_the_rule_and_reports_fresh_samples(roller, no_grid):
    from prsa_ctrl.plant.uncertainty import uncertainty_model
    from prsa_ctrl.studies.montecarlo import draw_sample, run_monte_carlo
    from prsa_ctrl.studies.scenerobust import operating_points

    plant, scene = roller
    r = no_grid
    # nominal and robust at two Ms bounds, plus the given design (unless a duplicate)
    assert set(r.designs) >= {"rule of thumb"}
    assert len(r.designs) >= 3
    names = {row["name"] for row in r.search["rows"]}
    assert names == set(r.designs)
    if r.chosen is None:
        assert all(row["passed"] == 0 for row in r.search["rows"])
        assert r.final is None
        return
    _check_rule({**r.search, "table": r.search["rows"], "name": r.chosen, "design": r.chosen})
    # the reported yield is an independent Monte Carlo's of the chosen gains on seed + 1 ...
    ref = run_monte_carlo(plant, scene, {"x": r.pid}, 4, seed=4, workers=1, quiet=True).designs[0]
    fy = r.final_yield
    assert (fy.passed, fy.n, fy.ci95) == (ref.passed, ref.n, ref.ci95)
    assert r.final_seed == 4
    # ... whose samples are not the search's
    unc, ops = uncertainty_model(plant, scene.sections.plant_overrides), tuple(operating_points(scene))
    for i in range(4):
        assert draw_sample(unc, ops, 3, i)[0] != draw_sample(unc, ops, 4, i)[0]
    text = r.format("iae")
    assert f"* {r.chosen}" in text
    assert "fresh samples (seed 4, not used by the search)" in text


@pytest.mark.parametrize("kw, match", [({"n_search": 0}, "n_search = 0"), ({"n_final": True}, "n_final = True"),
                                       ({"seed": -1}, "seed = -1"), ({"ms_levels": (1.0,)}, "ms_levels"),
                                       ({"ms_levels": (float("nan"),)}, "ms_levels"),
                                       ({"n_decide": 0}, "n_decide = 0"), ({"n_decide": 2.5}, "n_decide = 2.5")])
def test_design_to_spec_bad_arguments_are_named_before_any_work(roller, kw, match):
    from prsa_ctrl.studies.designspec import design_to_spec

    with pytest.raises(ValueError, match=match):
        design_to_spec(*roller, **kw)


@pytest.mark.parametrize("argv, match", [
    (["--scene", "paper-load-step", "--design-to-spec"], "has no [spec] section"),
    (["--scene", "robust-load-step", "--design-to-spec", "--monte-carlo", "0"], "--monte-carlo 0"),
    (["--scene", "paper-move", "--design-to-spec"], "--design-to-spec does not apply to a move scene"),
    # was exit 3 ("numerical failure: n_final = 100001") after the robust tuning had run
    (["--scene", "robust-load-step", "--design-to-spec", "--monte-carlo", "100001"],
     "--design-to-spec with --monte-carlo 100001; expected a sample count of the final check in 1..100000"),
])
def test_cli_design_to_spec_refusals_are_one_line_exit_2(argv, match, capsys):
    from prsa_ctrl.cli.tune import main as tune_main

    code = tune_main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert len(err) == 1, err
    assert match in err[0], err


def test_cli_design_to_spec_refuses_a_scene_sample_count_beyond_the_study_before_any_work(tmp_path, capsys, monkeypatch):
    """A scene's ``[robust] monte_carlo`` up to 1000000 is a valid scene (a plain Monte Carlo),
    beyond the design-to-spec's 100000 per run: refused up front naming the scene's value (was
    exit 3 after the robust tuning)."""
    from prsa_ctrl.cli.tune import main as tune_main
    from pathlib import Path

    from prsa_ctrl.studies import scenerobust

    text = (Path(__file__).resolve().parents[2] / "tuning" / "robust-load-step.toml").read_text(encoding="utf-8")
    assert "monte_carlo = 1000" in text
    path = tmp_path / "big.toml"
    path.write_text(text.replace("monte_carlo = 1000", "monte_carlo = 500000"), encoding="utf-8")
    monkeypatch.setattr(scenerobust, "tune_robust_actuator", lambda *a, **k: pytest.fail("the study started"))
    code = tune_main(["--scene", str(path), "--design-to-spec"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert (err == ["prsa-tune: error: --design-to-spec: the scene robust-load-step has [robust] "
                                 "monte_carlo = 500000; expected a sample count of the final check in 1..100000 "
                                 "(or --monte-carlo N)"]), err


@pytest.mark.slow
def test_cli_design_to_spec_exports_the_chosen_design(roller, tmp_path, capsys):
    """``prsa-tune --design-to-spec`` on the roller-screw scene, 8 final samples: the JSON's
    recommendation is the search's choice with the fresh samples' yield, the export holds it."""
    import json
    import tomllib

    from prsa_ctrl.cli.tune import main as tune_main

    path = tmp_path / "rollerscrew-spec.toml"
    path.write_text(ROLLER_SPEC_SCENE, encoding="utf-8")
    out, exp = tmp_path / "r.json", tmp_path / "drive.toml"
    code = tune_main(["--plant", "rollerscrew-30x5", "--scene", str(path), "--design-to-spec", "--monte-carlo", "8",
                      "--workers", "2", "--json", str(out), "--export", str(exp)])
    text = capsys.readouterr().out
    assert code == 0, text
    d = json.loads(out.read_text())
    dts, rec = d["design_to_spec"], d["recommended"]
    assert rec["name"] == dts["chosen"]
    assert rec["passed"] == dts["passed"]
    assert rec["samples"] == 8
    assert dts["final_seed"] != dts["search_seed"]
    assert [x["name"] for x in d["monte_carlo"]["designs"]] == [dts["chosen"]]
    _check_rule({**dts["search"], "table": dts["search"]["rows"], "name": dts["chosen"], "design": dts["chosen"]})
    t = tomllib.loads(exp.read_text())
    assert t["design"]["name"] == dts["chosen"]
    assert t["speed_controller"]["continuous"]["kp_n_m_s_per_rad"] == dts["gains"]["kp"]
