"""Robust tuning: one NLP over scenario models; generic plant arrays."""

import math

import numpy as np
import pytest

from prsa_ctrl import SceneError
from prsa_ctrl.plant.plantfile import load_plant
from prsa_ctrl.plant.uncertainty import uncertainty_model
from prsa_ctrl.studies.scene import load_scene
from prsa_ctrl.studies.scenerobust import operating_points, scenarios, tune_robust_actuator
from prsa_ctrl.tuning.robust import tune_robust

from spec_scenes import ROLLER_SPEC_SCENE, check_rule as _check_rule


@pytest.fixture(scope="module")
def robust_run():
    return tune_robust_actuator(load_plant(), load_scene("robust-load-step"))


def test_scenarios_are_nominal_vertices_and_samples():
    p, s = load_plant(), load_scene("robust-load-step")
    sc = scenarios(p, s)
    kinds = [x.kind for x in sc]
    assert kinds == ["nominal"] + ["vertex"] * 4 + ["sample"] * 3
    unc = uncertainty_model(p, s.sections.plant_overrides)
    lo = {e.key: e.low for e in unc.entries}
    hi = {e.key: e.high for e in unc.entries}
    assert {tuple(sorted(v.values.items())) for v in sc if v.kind == "vertex"} == {
        tuple(sorted({k: (lo[k] if b else hi[k]) for k, b in zip(sorted(lo), bits)}.items()))
        for bits in [(0, 0), (0, 1), (1, 0), (1, 1)]}
    # seeded: the same scenarios again
    assert [x.values for x in scenarios(p, s)] == [x.values for x in sc]
    assert [x.values for x in scenarios(p, s, seed=2)][5:] != [x.values for x in sc][5:]


def test_scenario_bound_is_checked_before_any_model_is_built():
    p, s = load_plant(), load_scene("robust-load-step")
    with pytest.raises(SceneError, match="max_scenarios"):
        scenarios(p, s, samples=100, max_scenarios=16)


def test_operating_range_crosses_setpoints_and_loads():
    s = load_scene("robust-load-step")
    s2 = s.replace(sections={**s.sections.as_dict(), "robust": {**s.sections.as_dict()["robust"], "setpoints_rpm": [150.0, 300.0],
                                                   "final_loads_n": [1000.0, 2000.0]}})
    ops = operating_points(s2)
    assert len(ops) == 4
    assert ops[0] == (pytest.approx(150 * math.pi / 30), 1000.0)


def test_robust_design_meets_ms_on_every_scenario_and_nominal_does_not(robust_run):
    r = robust_run
    c = r.comparison
    rob, nom = c["designs"]["robust"], c["designs"]["nominal"]
    assert len(rob["per_scenario"]) == len(r.scenarios) == 8
    # Recomputed from the loop models, not read from the tuner's report.
    for lp in r.loops:
        assert lp.is_stable(r.robust.gains)
        assert lp.margins(r.robust.gains).ms <= c["ms_max"] * (1 + 1e-9)
    # The scene's [spec] states Ms <= 1.5: the robust study tunes to it (not [tuning] ms_max 1.4) and says so.
    assert c["ms_max"] == 1.5
    assert c["ms_source"] == "[spec] ms"
    assert load_scene("robust-load-step").ms_max == 1.4
    assert rob["ms_violations"] == 0
    assert rob["all_stable"]
    # The nominal design is fragile on this scene: it breaks the bound at some corners.
    assert nom["ms_violations"] >= 1
    assert nom["max_ms"] > 1.6
    # ... and it meets it on the nominal scenario, where it was tuned.
    nominal_ms = [p["ms"] for p, s in zip(nom["per_scenario"], r.scenarios) if s.kind == "nominal"]
    assert max(nominal_ms) <= c["ms_max"] * (1 + 1e-6)
    # Worst-case objective: the robust design is the optimum over the scenarios, so no design
    # that satisfies every Ms bound - here a down-scaled nominal design - beats it.
    assert rob["worst_objective"] == pytest.approx(max(lp.objective(r.robust.gains, "iae") for lp in r.loops))


def test_robust_design_is_a_local_optimum_of_the_worst_case(robust_run):
    r = robust_run
    base = max(lp.objective(r.robust.gains, "iae") for lp in r.loops)
    g0 = np.array(r.robust.gains[:2])
    for dk in ([1.03, 1.0], [1.0, 1.03], [0.97, 1.0], [1.0, 0.97]):
        g = list(g0 * dk) + [0.0]
        feasible = all(lp.is_stable(g) and lp.margins(g).ms <= r.comparison["ms_max"] for lp in r.loops)
        if feasible:
            assert max(lp.objective(g, "iae") for lp in r.loops) >= base * (1 - 1e-3)


def test_generic_plant_array_like_systune(default_robust):
    """Three gains of 1/(s+1)^3 (``_THREE``): the worst-case design holds Ms on every plant, a
    single-plant design does not, and each aggregate is the better one at its own objective (the
    worst-case and mean runs are ``default_robust``'s, shared with the tests below)."""
    import control

    plants = [control.tf([k], [1, 3, 3, 1]) for k in (0.5, 1.0, 2.0)]
    r, _, _ = default_robust("iae", "worst")
    assert len(r.margins) == 3
    assert all(m.ms <= 1.6 * (1 + 1e-9) for m in r.margins)
    from prsa_ctrl.tuning.generic import tune_pid

    single = tune_pid(plants[0], objective="iae", ms_max=1.6, n_steps=400)
    # tuned for the low-gain plant alone, the PI breaks the bound on the high-gain one
    from prsa_ctrl.tuning.builders import continuous_loop

    lp = continuous_loop(control.ss(plants[2]), tf=single.pid.tf, horizon=10.0)
    assert lp.margins(single.pid.gains).ms > 1.6
    mean, _, _ = default_robust("iae", "mean")
    assert np.mean(mean.per_loop) <= np.mean(r.per_loop) * (1 + 1e-3)
    assert max(r.per_loop) <= max(mean.per_loop) * (1 + 1e-3)


@pytest.mark.parametrize("bad, match", [([], "at least one"), ("median", "aggregate")])
def test_generic_bad_arguments(bad, match):
    import control

    with pytest.raises(ValueError, match=match):
        if bad == []:
            tune_robust([])
        else:
            tune_robust([control.tf([1], [1, 1, 1])], aggregate=bad)


#: Three gains of 1/(s+1)^3 under one Ms bound, with a two-rate tail (n_steps 480).
_THREE = dict(ms_max=1.6, n_steps=480)


@pytest.fixture(scope="module")
def default_robust():
    """``default_robust(objective, aggregate)``: the default ``tune_robust`` of the three plants (the
    mapped per-loop objective, the coarse constraint grid), made once per module per case with two
    passive spies recording which objective path ran and how many grid rows each loop held:
    ``(result, used, rows)``. The tests below compare it with the expanded and the full-grid run;
    test_generic_plant_array_like_systune asserts on its worst-case and mean designs."""
    import control

    from prsa_ctrl.tuning import tuner as T

    done = {}

    def run(objective, aggregate):
        if (objective, aggregate) not in done:
            plants = [control.tf([k], [1, 3, 3, 1]) for k in (0.5, 1.0, 2.0)]
            used, rows = [], []
            mapped, coarse_rows = T.Tuner._mapped_objectives, T.Tuner._grid_rows

            def spy_mapped(self, g, eps):
                out = mapped(self, g, eps)
                used.append(out is not None)
                return out

            def spy_rows(self, jl):
                r = coarse_rows(self, jl)
                rows.append((r.size, self.loops[jl].omega.size))
                return r

            with pytest.MonkeyPatch.context() as mp:
                mp.setattr(T.Tuner, "_mapped_objectives", spy_mapped)
                mp.setattr(T.Tuner, "_grid_rows", spy_rows)
                res = tune_robust(plants, objective=objective, aggregate=aggregate, **_THREE)
            done[objective, aggregate] = (res, used, rows)
        return done[objective, aggregate]

    return run


#: Each comparison below re-runs the robust NLP the slow way (an evidence study of the fast path):
#: the default suite checks both claims on the worst case (one default_robust run shared by the two;
#: the mean aggregate's design is checked by test_generic_plant_array_like_systune), the ITAE mean
#: case of each (its own default_robust run) is -m slow.
_MAPPED_CASES = [("iae", "worst"), pytest.param("itae", "mean", marks=pytest.mark.slow)]
_COARSE_CASES = [("iae", "worst"), pytest.param("itae", "mean", marks=pytest.mark.slow)]


@pytest.mark.parametrize("objective, aggregate", _MAPPED_CASES)
def test_mapped_per_loop_objective_is_the_expanded_one(monkeypatch, default_robust, objective, aggregate):
    """The robust NLP's objective from one per-loop function mapped over the scenarios (built
    once) reaches the same design as the per-scenario expansion it replaces."""
    import control

    from prsa_ctrl.tuning import tuner as T

    plants = [control.tf([k], [1, 3, 3, 1]) for k in (0.5, 1.0, 2.0)]
    fast, used, _ = default_robust(objective, aggregate)
    assert used
    assert all(used)
    monkeypatch.setattr(T.Tuner, "_mapped_objectives", lambda self, g, eps: None)
    slow = tune_robust(plants, objective=objective, aggregate=aggregate, **_THREE)
    np.testing.assert_allclose(fast.pid.gains, slow.pid.gains, rtol=1e-6)
    np.testing.assert_allclose(fast.per_loop, slow.per_loop, rtol=1e-6)


@pytest.mark.parametrize("objective, aggregate", _COARSE_CASES)
def test_coarse_constraint_grid_reaches_the_full_grid_design(monkeypatch, default_robust, objective, aggregate):
    """With several loops the NLP holds Ms on ~64 grid rows per loop (plus resonance points)
    and adds the verified true peaks with their neighbours; the design honours the bound on
    every loop's true peak and is as good as with every grid row in the NLP."""
    import control

    from prsa_ctrl.tuning import builders, settings, tuner as T

    plants = [control.tf([k], [1, 3, 3, 1]) for k in (0.5, 1.0, 2.0)]
    coarse, _, rows = default_robust(objective, aggregate)
    assert rows
    assert all(n <= settings.MULTI_ROWS + 40 < n_all for n, n_all in rows)
    monkeypatch.setattr(T.Tuner, "_grid_rows", lambda self, jl: np.arange(self.loops[jl].omega.size))
    full = tune_robust(plants, objective=objective, aggregate=aggregate, **_THREE)
    assert coarse.converged
    assert full.converged
    for r in (coarse, full):
        for p, m in zip(plants, r.margins):
            lp = builders.continuous_loop(control.ss(p), tf=r.pid.tf, horizon=10.0)
            assert lp.margins(r.pid.gains).ms <= 1.6 * (1 + 1e-9)
            assert m.ms <= 1.6 * (1 + 1e-9)
    assert coarse.objective <= full.objective * (1 + 1e-4)


def test_lower_bound_ranking_keeps_the_exact_top(monkeypatch):
    """With several loops and the worst-case objective the scan ranks by lower bounds and
    simulates every loop only where the top of the order is decided: that top is the one of
    the full ranking (the mean objective ranks every point, as one loop does)."""
    from prsa_ctrl.tuning import builders, generic, settings, tuner as T
    from prsa_ctrl.studies.scenerobust import scenario_loops

    p, s = load_plant(), load_scene("robust-load-step")
    loops = scenario_loops(p, s, scenarios(p, s))
    for worst in (True, False):
        fast = T.Tuner(loops, objective="iae", worst_case=worst)
        top = fast._ranked(1.4 * (1 - 1e-6), None, None, [math.inf, math.inf])
        evaluated = int(np.sum(~np.isnan(fast._scan_data()["obj"])))
        monkeypatch.setattr(T, "RANK_TOP", 10**9)
        ref = T.Tuner(loops, objective="iae", worst_case=worst)
        full = ref._ranked(1.4 * (1 - 1e-6), None, None, [math.inf, math.inf])
        monkeypatch.undo()
        if worst:
            assert evaluated < int(np.sum(~np.isnan(ref._scan_data()["obj"])))  # it did skip work
            k = T.RANK_TOP
            assert full.size > top.size >= k
            assert np.array_equal(top[:k], full[:k])
        else:
            assert np.array_equal(top, full)


def test_slot_budget_holds_ms_and_mt_with_resonances_near_nyquist():
    """Two delayed plants with a zeta = 0.005 resonance near the sampling Nyquist, Ms and Mt
    bounded: the added frequencies (start peaks of Ms and Mt, then clusters at new violations)
    fit the budget, and the design is the full grid's (an independent reviewer's case: with
    20 slots it fell back to a scan point 60 % worse)."""
    import control

    from prsa_ctrl.tuning import builders, generic, settings, tuner as T

    s = control.tf("s")
    nn, dd = control.pade(0.3, 3)
    delay = control.tf(nn, dd)
    p0 = delay / (s + 1)
    w = np.logspace(-3, 3, 20000)
    ph = np.unwrap(np.angle(control.frequency_response(p0, w).complex.ravel()))
    h = 40 / w[np.flatnonzero(ph <= -0.75 * np.pi)[0]] / 200
    wr = 0.8 * np.pi / h
    plants = [p0 * wr**2 / (s**2 + 0.01 * wr * s + wr**2),
              2 * delay / (s + 1) * (1.2 * wr) ** 2 / (s**2 + 0.01 * 1.2 * wr * s + (1.2 * wr) ** 2)]
    kw = dict(objective="iae", ms_max=1.5, mt_max=1.3, n_steps=200)
    coarse = tune_robust(plants, **kw)
    assert coarse.converged, coarse.status
    assert all(m.ms <= 1.5 * (1 + 1e-9) and m.mt <= 1.3 * (1 + 1e-9) for m in coarse.margins)
    generic._RECENT.clear()
    orig = T.Tuner._grid_rows
    try:
        T.Tuner._grid_rows = lambda self, jl: np.arange(self.loops[jl].omega.size)
        full = tune_robust(plants, **kw)
    finally:
        T.Tuner._grid_rows = orig
        generic._RECENT.clear()
    assert coarse.objective <= full.objective * (1 + 1e-4)


@pytest.mark.parametrize("bad, match", [
    ("zero", "no states"), ("generator", None), ("string", r"plants\[1\] = 'x'"), ("scalar", "plants = 5")])
def test_generic_plant_list_inputs(bad, match):
    import control

    s = control.tf("s")
    p = 1 / (s + 1) ** 2
    arg = {"zero": [p, 0 * p], "generator": (x for x in [p, 0.5 * p]), "string": [p, "x"], "scalar": 5}[bad]
    if match is None:  # any iterable of plants is taken
        assert tune_robust(arg, n_steps=300).converged
    else:
        with pytest.raises(ValueError, match=match):
            tune_robust(arg, n_steps=300)


# --- issue 34 (1): the recommendation ranks every design the run evaluated by its yield --------


def _fake_mc(passes: dict, n: int = 200, iae: dict | None = None, seed: int = 0):
    """A Monte-Carlo report of designs on the same ``n`` samples: ``passes[name]`` samples pass
    (the first ones of a seeded permutation shared by all designs, so a design with more passes
    passes a superset -- common random numbers); a failing sample breaks the peak drop (odd
    samples) or Ms (even)."""
    from prsa_ctrl.studies.montecarlo import METRICS, DesignYield, MonteCarloReport, sample_passes, wilson_interval

    spec = {"peak_drop_rad_s": 12.0, "ms": 1.5, "no_saturation": True}
    order = np.random.default_rng(seed).permutation(n)
    metrics = np.zeros((n, len(passes), len(METRICS)))
    designs = []
    for j, (name, k) in enumerate(passes.items()):
        m = metrics[:, j, :]
        m[:, METRICS.index("peak_drop_rad_s")] = 10.0
        m[:, METRICS.index("ms")] = 1.3
        m[:, METRICS.index("iae")] = (iae or {}).get(name, 0.1)
        bad = order[k:]
        m[bad[bad % 2 == 1], METRICS.index("peak_drop_rad_s")] = 13.0
        m[bad[bad % 2 == 0], METRICS.index("ms")] = 1.8
        ok = sample_passes(m, spec, 12.0)[0]
        assert int(ok.sum()) == k
        pct = {"iae": {"p5": m[0, METRICS.index("iae")], "p50": m[0, METRICS.index("iae")]}}
        designs.append(DesignYield(name, {"kp": 1.0 + j, "ki": 1.0, "kd": 0.0, "tf": 0.0, "kff": 0.0}, k, n, k / n,
                                   wilson_interval(k, n), pct, None, {}, {}, 0, ""))
    return MonteCarloReport(n, n, 0, "serial", 1, True, spec, {}, [], designs, 0.0,
                            {"index": np.arange(n), "op": np.zeros(n, int), "values": {}, "metrics": metrics,
                             "design_names": list(passes), "metric_names": list(METRICS)})


def _study():
    from prsa_ctrl.drive.pid import PID
    from prsa_ctrl.tuning.robust import RobustTuning

    comp = {"objective": "iae", "ms_max": 1.4, "designs": {
        "nominal": {"ms_violations": 2, "worst_objective": 0.03}, "robust": {"ms_violations": 0, "worst_objective": 0.08}}}
    return RobustTuning(PID(0.43, 75.0), PID(0.27, 34.0), [object()] * 24, comp, {}, None)


def test_recommendation_is_the_issue_tables_best_design_not_the_better_of_two():
    """The issue's table (nominal 132/200, robust 10/200, PM 60 deg 178/200, rule of thumb
    195/200): the rule of thumb is recommended, exported and named; the table counts each spec
    item's failures."""
    from prsa_ctrl.drive.pid import PID
    from prsa_ctrl.tuning.robust import format_yield_table

    mc = _fake_mc({"nominal design": 132, "robust design": 10, "PM 60 deg": 178, "rule of thumb": 195})
    others = {"PM 60 deg": PID(0.37, 34.0), "rule of thumb": PID(0.64, 80.0)}
    rt = _study().with_recommendation(mc, others=others)
    rec = rt.recommended
    assert rec["design"] == "rule of thumb"
    assert rec["name"] == "rule of thumb"
    assert rec["passed"] == 195
    assert rec["yield"] == 0.975
    assert rt.design(rec["design"]) is others["rule of thumb"]
    assert rec["gains"]["kp"] == 0.64
    _check_rule(rec)
    rows = {r["name"]: r for r in rec["table"]}
    # 68 failing samples of the nominal design split by the seeded permutation into drop / Ms
    order = np.random.default_rng(0).permutation(200)[132:]
    assert rows["nominal design"]["fails"] == {"finite": 0, "peak_drop_rad_s": int(np.sum(order % 2 == 1)),
                                               "ms": int(np.sum(order % 2 == 0)), "no_saturation": 0}
    assert not rows["nominal design"]["near_max"]
    assert rows["rule of thumb"]["near_max"]
    text = format_yield_table(rec, "iae")
    assert "* rule of thumb" in text
    assert "97.5 % (195/200) [94.3, 98.9]" in text
    assert "highest yield: rule of thumb 97.5 % (195/200)" in rec["why"]


@pytest.mark.parametrize("k_other, recommended", [(194, "other"), (186, "leader")])
def test_near_maximal_yield_goes_to_the_lower_objective_only_within_the_intervals(k_other, recommended):
    """194 against 195 of 200 on the same samples is a tie within the noise: the lower median
    IAE wins. 186 against 195 (the 9 extra failures all on samples the leader passes: paired,
    significant) is not, though within the two Wilson half-widths: the leader stays."""
    mc = _fake_mc({"nominal design": 100, "robust design": 50, "leader": 195, "other": k_other},
                  iae={"leader": 0.2, "other": 0.1})
    rec = _study().recommend(mc)
    assert rec["name"] == recommended
    _check_rule(rec)


def test_no_design_meets_the_spec_recommends_none():
    rec = _study().recommend(_fake_mc({"nominal design": 0, "robust design": 0, "x": 0}))
    assert rec["design"] is None
    assert "no design meets the spec on any sample" in rec["why"]


def _roller_run(tmp_path):
    path = tmp_path / "rollerscrew-spec.toml"
    path.write_text(ROLLER_SPEC_SCENE, encoding="utf-8")
    plant, scene = load_plant("rollerscrew-30x5"), load_scene(str(path))
    rt = tune_robust_actuator(plant, scene)
    return plant, scene, rt


def test_roller_screw_scene_recommendation_holds_on_the_monte_carlo_table(tmp_path):
    """The roller-screw scene: nominal, robust and the PM 60 deg / rule-of-thumb baselines on
    the same 6 nonlinear samples; the recommendation obeys the rule on the table's own numbers
    and its yield equals the Monte Carlo's for that design."""
    from prsa_ctrl.drive.pid import PID
    from prsa_ctrl.studies.montecarlo import run_monte_carlo
    from prsa_ctrl.tuning.robust import format_yield_table

    plant, scene, rt = _roller_run(tmp_path)

    # PM 60 deg and rule of thumb of the CLI's baselines on this scene (kp N m s/rad, ki N m/rad)
    others = {"PM 60 deg": PID(0.3704355255110466, 34.09808499371941),
              "rule of thumb": PID(0.6361989083357843, 79.94711266598183)}
    designs = {"nominal design": rt.nominal, "robust design": rt.robust, **others}
    mc = run_monte_carlo(plant, scene, designs, 6, seed=1, workers=1, quiet=True)
    rec = rt.with_recommendation(mc, others=others).recommended
    print(format_yield_table(rec, "iae"), rec["why"])
    assert rt.comparison["ms_max"] == 1.5
    assert rt.comparison["ms_source"] == "[spec] ms"
    _check_rule(rec)
    y = {d.name: d for d in mc.designs}
    assert rec["passed"] == y[rec["name"]].passed
    assert rec["samples"] == 6
    assert {r["name"] for r in rec["table"]} == set(designs)


@pytest.mark.slow
def test_roller_screw_cli_recommends_and_exports_by_the_rule(tmp_path, capsys):
    """``prsa-tune`` on the roller-screw scene, 60 samples: the JSON's recommendation obeys the
    rule against every design of the Monte-Carlo table, the text shows the table, and the
    export holds the recommended design's gains."""
    import json
    import tomllib

    from prsa_ctrl.cli.tune import main as tune_main

    path = tmp_path / "rollerscrew-spec.toml"
    path.write_text(ROLLER_SPEC_SCENE, encoding="utf-8")
    out, exp = tmp_path / "r.json", tmp_path / "drive.toml"
    code = tune_main(["--plant", "rollerscrew-30x5", "--scene", str(path), "--monte-carlo", "60", "--workers", "2",
                      "--json", str(out), "--export", str(exp)])
    text = capsys.readouterr().out
    assert code == 0
    d = json.loads(out.read_text())
    rec = d["recommended"]
    mc = {x["name"]: x for x in d["monte_carlo"]["designs"]}
    assert {r["name"] for r in rec["table"]} == set(mc)
    _check_rule(rec)
    assert rec["passed"] == mc[rec["name"]]["passed"]
    assert "* " + rec["name"] in text
    assert f"recommended: {rec['name']}" in text
    t = tomllib.loads(exp.read_text())
    assert t["design"]["name"] == rec["name"]
    assert t["speed_controller"]["continuous"]["kp_n_m_s_per_rad"] == mc[rec["name"]]["gains"]["kp"]


# --- issue 34 (3): a target yield no design reaches names the limiting spec item ---------------

def test_target_yield_not_reached_names_the_limit_and_by_how_much():
    """Target 0.95, best 178/200: the recommended design's most frequent failure is named with
    its p95 against the bound, checked here from the per-sample metrics."""
    from prsa_ctrl.studies.montecarlo import METRICS

    mc = _fake_mc({"nominal design": 132, "robust design": 10, "PM 60 deg": 178})
    rec = _study().recommend(mc, target=0.95)
    assert rec["name"] == "PM 60 deg"
    assert rec["reached"] is False
    assert rec["target"] == 0.95
    lim = rec["limit"]
    m = mc.samples["metrics"][:, 2, :]
    drop, ms = m[:, METRICS.index("peak_drop_rad_s")], m[:, METRICS.index("ms")]
    k_drop, k_ms = int(np.sum(drop > 12)), int(np.sum(ms > 1.5))
    item, col, bound = ("peak_drop_rad_s", drop, 12.0) if k_drop >= k_ms else ("ms", ms, 1.5)
    assert lim["item"] == item
    assert lim["fails"] == max(k_drop, k_ms)
    assert lim["value"] == np.sort(col)[math.ceil(0.95 * 200) - 1]
    assert lim["value"] > bound
    assert lim["yield_without_it"] == pytest.approx(1 - min(k_drop, k_ms) / 200)
    assert "no design reaches the target yield 95.0 %" in rec["why"]
    assert lim["text"] in rec["why"]
    assert _study().recommend(mc, target=0.85)["reached"] is True
    assert "limit" not in _study().recommend(mc, target=0.85)


@pytest.mark.parametrize("bad", [0, 1, 1.5, -0.1, True, "0.95"])
def test_spec_yield_is_a_probability(bad):
    from prsa_ctrl.studies.scenesections import parse_scene_sections

    with pytest.raises(SceneError, match=r"s.toml: spec.yield = .*expected a target probability in \(0, 1\)"):
        parse_scene_sections({"spec": {"yield": bad, "ms": 1.5}}, "s.toml")
    ok = parse_scene_sections({"spec": {"yield": 0.95, "ms": 1.5}}, "s.toml")
    assert ok["spec"] == {"ms": 1.5}
    assert ok["spec_yield"] == {"yield": 0.95}


# ------------------------------------------------------------------------------------------------
# Issue 20: the recommended design is ranked by its yield against the spec.
# ------------------------------------------------------------------------------------------------

# --- item 2: filter arguments out of range are named, never "b0 = nan" -------------------------


# --- item 1: a notch is kept only where it acts on the mode -------------------------------------


# --- items 3, 4, 5: robust study -> recommended design, strict JSON, named export ----------------


def test_recommend_ranks_by_the_yield_against_the_spec():
    """Unit check of the ranking: robust 10/200 against nominal 132/200 recommends the nominal
    design; both at 0 recommends none; without Monte Carlo the spec is said to be unchecked."""
    from prsa_ctrl.drive.pid import PID
    from prsa_ctrl.studies.montecarlo import DesignYield, wilson_interval
    from prsa_ctrl.tuning.robust import RobustTuning

    comp = {"objective": "iae", "ms_max": 1.4, "designs": {
        "nominal": {"ms_violations": 2, "worst_objective": 0.03}, "robust": {"ms_violations": 0, "worst_objective": 0.08}}}
    rt = RobustTuning(PID(0.085, 14.7), PID(0.045, 6.8), [object()] * 12, comp, {}, None)

    class MC:
        def __init__(self, k_nom, k_rob, n=200):
            self.designs = [DesignYield(name, {}, k, n, k / n, wilson_interval(k, n), {}, None, {}, {}, 0, "")
                            for name, k in (("nominal design", k_nom), ("robust design", k_rob))]

    r = rt.recommend(MC(132, 10))
    assert r["design"] == "nominal"
    assert r["yield"] == 0.66
    assert r["passed"] == 132
    assert r["samples"] == 200
    assert "66.0 % (132/200)" in r["why"]
    assert "5.0 % (10/200)" in r["why"]
    # Frozen study: recommend() leaves it as it is; with_recommendation() returns a copy that keeps it.
    assert rt.recommended == {}
    assert rt.with_recommendation(MC(132, 10)).recommended == r
    assert rt.recommend(MC(10, 132))["design"] == "robust"
    none = rt.recommend(MC(0, 0))
    assert none["design"] is None
    assert "no design meets the spec on any sample" in none["why"]
    lin = rt.recommend(None)
    assert lin["design"] == "robust"
    assert lin["yield"] is None
    assert "not checked" in lin["why"]


# --- item 7: the Monte-Carlo replay on a duty scene ----------------------------------------------


# --- item 6: SIGTERM during a Monte-Carlo process pool -------------------------------------------
