"""prsa_ctrl.identification.timedomain: the delay search's short segments and the objective per
record (issue 32: the ball-screw logs' delay was undecided on 0.1 s segments)."""

import math

import numpy as np
import pytest

from prsa_ctrl.identification import gaussnewton as gn
from prsa_ctrl.identification import timedomain as td
from prsa_ctrl.identification.common import FitResult
from prsa_ctrl.identification.synthetic import fit_record

BW = "drive.current_loop_bandwidth_hz"


@pytest.fixture(scope="module")
def sim():
    return fit_record(0.5)


@pytest.fixture(scope="module")
def inertia_fit(sim):
    """The inertia-only fit of ``sim`` at shift 0 without validation, made once per module: the
    reference of the kink and stall tests (each fitted it afresh)."""
    rec, truth = sim
    return td.fit_plant([rec], truth, keys=("nut.inertia_kg_m2",), delay_samples=0, validation=False)


def test_search_segment_is_short_but_not_below_forty_samples():
    assert td.search_segment_s(0.1, 1.25e-4) == td.SEARCH_SEGMENT_S == 0.02
    assert td.search_segment_s(0.01, 1.25e-4) == 0.01  # never longer than the fit's own
    assert td.search_segment_s(0.1, 1e-3) == pytest.approx(0.04)  # 40 samples at 1 kHz


def test_the_search_fits_short_segments_and_the_result_the_asked_ones(sim, monkeypatch):
    rec, truth = sim
    calls = []

    checks = []  # check of the plant as written: only on the asked segments (the search's are refitted)

    def fake(records, plant, *, segment_s, delay_samples, keys, **kw):
        calls.append((delay_samples, segment_s))
        checks.append(kw.get("check_written", True))
        keys = td.default_keys(plant) if keys is None else keys
        f = {1: 10.0, 2: 1.0, 3: 30.0}.get(delay_samples, 50.0)  # shift 2 the best by far
        params = {k: {"value": plant.values[k], "ci95": [0.5 * plant.values[k], 1.5 * plant.values[k]], "unit": ""}
                  for k in keys}
        params[BW]["value"] = 100.0
        return FitResult(plant, params, {"value": 1.0, "ci95": [0.9, 1.1]}, np.eye(len(keys)), tuple(keys), {}, [],
                         {"objective": f, "objective_per_record": {rec.name: f}, "segment_s": segment_s}, {}, None, {},
                         None)

    monkeypatch.setattr(td, "_fit_records", fake)
    res = td.fit_plant([rec], truth, delay_samples="find", max_delay_samples=3, segment_s=0.1, validation=False)
    search = [c for c in calls[:-1]]
    ts = rec.sample_time_s
    assert search
    assert all(seg == td.search_segment_s(0.1, ts) < 0.1 for _, seg in search)
    assert calls[-1] == (2, 0.1)  # the fit at the found shift on the asked segments
    assert checks == [False] * len(search) + [True]
    cd = res.solver["command_delay"]
    assert cd["shift_samples"] == 2
    assert cd["search"]["decided"] is True
    assert cd["search"]["segment_s"] == td.search_segment_s(0.1, ts)
    assert res.solver["segment_s"] == 0.1
    # segments no longer than the search's: no second fit
    calls.clear()
    checks.clear()
    td.fit_plant([rec], truth, delay_samples="find", max_delay_samples=3, segment_s=0.01, validation=False)
    assert all(seg == 0.01 for _, seg in calls)
    assert len(calls) == len({d for d, _ in calls})
    assert checks
    assert all(checks)


def test_objective_per_record_adds_up_to_the_objective(sim):
    from dataclasses import replace

    rec, truth = sim
    n = rec.n // 2

    def part(name, sl):
        return replace(rec, name=name, time_s=rec.time_s[sl], torque_command_n_m=rec.torque_command_n_m[sl],
                       nut_angle_rad=rec.nut_angle_rad[sl], axial_load_n=rec.axial_load_n[sl],
                       nut_speed_rad_s=None if rec.nut_speed_rad_s is None else rec.nut_speed_rad_s[sl])

    a, b = part("a", slice(0, n)), part("b", slice(n, rec.n))
    res = td.fit_plant([a, b], truth, keys=["nut.inertia_kg_m2"], delay_samples=0, validation=False)
    per = res.solver["objective_per_record"]
    assert set(per) == {"a", "b"}
    assert sum(per.values()) == pytest.approx(res.solver["objective"], rel=1e-9)
    assert all(math.isfinite(v) and v > 0 for v in per.values())
    # the delay search's paired test: each record's segments, in time order, add up to its share
    segs = res.solver["objective_per_segment"]
    assert {k: sum(v) for k, v in segs.items()} == {k: pytest.approx(v, rel=1e-9) for k, v in per.items()}
    assert sum(len(v) for v in segs.values()) == res.solver["segments"]
    alone = td.fit_plant([a], truth, keys=["nut.inertia_kg_m2"], delay_samples=0, validation=False)
    assert alone.solver["objective_per_record"] == {"a": pytest.approx(alone.solver["objective"], rel=1e-9)}


def test_a_stuck_line_search_is_a_solution_only_at_a_tiny_defect_and_step():
    se = np.array([1e-3, 2e-2])
    ok = gn.converged_at_kink(4e-7, np.array([1e-5, -1e-4]), se, 1e-8)
    assert ok is True
    # the defect above the tolerance, or a step the linearisation still asks for: not a solution
    assert gn.converged_at_kink(2 * gn.KINK_CONSTRAINT_TOL, np.array([1e-5, -1e-4]), se, 1e-8) is False
    assert gn.converged_at_kink(4e-7, np.array([2e-4, 0.0]), se, 1e-8) is False  # 0.2 standard errors
    assert gn.converged_at_kink(float("nan"), np.zeros(2), se, 1e-8) is False
    assert gn.converged_at_kink(4e-7, np.zeros(0), None, 1e-8) is True  # states only


def test_a_fit_whose_line_search_cannot_improve_a_converged_point_reports_it(sim, inertia_fit, monkeypatch):
    # Every trial point with a defect below 1e-7 is refused (as at a kink of the friction law,
    # where Newton steps flip sides): the iterate holds the equations and the step is small, so
    # the fit converges and says so; with the tolerance at zero the same run fails as before.
    rec, truth = sim
    keys = ("nut.inertia_kg_m2",)
    res = inertia_fit
    assert res.solver["converged_at_kink"] is False
    orig = td._Problem._merit_terms
    state = {"n": 0}

    def refuse(self, V, X0, s):
        state["n"] += 1
        g, f = orig(self, V, X0, s)
        return (g, f) if g > 1e-7 else (10.0 * g + 1.0, 10.0 * f + 1.0)  # finite, never better

    monkeypatch.setattr(td._Problem, "_merit_terms", refuse)
    monkeypatch.setattr(td, "FIRST_ORDER_WINDOW", 10**6)  # the kink rule alone (the stall rule has its own test)
    out = td.fit_plant([rec], truth, keys=keys, delay_samples=0, validation=False)
    assert out.solver["converged_at_kink"] is True
    assert out.parameters["nut.inertia_kg_m2"]["value"] == pytest.approx(
        res.parameters["nut.inertia_kg_m2"]["value"], rel=1e-6)
    # with the kink rule and the first-order rule of a stall both off (no defect within their
    # reach), the same run fails as before
    monkeypatch.setattr(gn, "KINK_CONSTRAINT_TOL", 0.0)
    monkeypatch.setattr(gn, "FIRST_ORDER_G_MAX", 0.0)
    state["n"] = 0
    with pytest.raises(td.FitError, match="line search failed"):
        td.fit_plant([rec], truth, keys=keys, delay_samples=0, validation=False)


def test_a_stall_at_a_first_order_point_converges_and_one_elsewhere_fails(sim, inertia_fit, monkeypatch):
    """The rule of a stall (prsa_ctrl.identification.gaussnewton): a fit whose line search stops at
    the optimum (every trial point with a defect below 1e-7 refused, the kink rule off) converges,
    says so and reports what a full convergence reports; a fit whose iteration budget ends one
    parameter step after a start 25 % off fails, and its message gives the step still asked for."""
    rec, truth = sim
    keys = ("nut.inertia_kg_m2",)
    ref = inertia_fit
    assert ref.solver["stall"] is None
    orig = td._Problem._merit_terms

    def refuse(self, V, X0, s):
        g, f = orig(self, V, X0, s)
        return (g, f) if g > 1e-7 else (10.0 * g + 1.0, 10.0 * f + 1.0)  # finite, never better

    monkeypatch.setattr(td._Problem, "_merit_terms", refuse)
    monkeypatch.setattr(td, "converged_at_kink", lambda *a: False)
    out = td.fit_plant([rec], truth, keys=keys, delay_samples=0, validation=False)
    stall = out.solver["stall"]
    assert stall["status"] in ("line search failed", "stalled at a first-order point")
    assert out.solver["converged_at_kink"] is False
    assert out.solver["status"] == "converged"
    assert stall["step_standard_errors"] <= gn.FIRST_ORDER_TOL
    assert stall["constraint_residual"] <= gn.FIRST_ORDER_G_MAX
    v, v_ref = out.parameters[keys[0]], ref.parameters[keys[0]]
    half = 0.5 * (v_ref["ci95"][1] - v_ref["ci95"][0])
    assert abs(v["value"] - v_ref["value"]) <= 0.1 * half
    monkeypatch.undo()
    start = truth.with_params({keys[0]: 1.25 * truth.values[keys[0]]})
    with pytest.raises(td.FitError, match=r"stopped 'maximum iterations' where the step still asked for is .* standard errors"):
        td.fit_plant([rec], start, keys=keys, delay_samples=0, validation=False, max_iter=1)


@pytest.mark.parametrize("fidelity, expected", [("rigid", td.SEGMENT_S), ("compliant", 0.05)])
def test_the_default_segment_depends_on_the_fidelity(sim, monkeypatch, fidelity, expected):
    """Without segment_s the fit's segments are 0.1 s, a compliant fit's 0.05 s
    (prsa_ctrl.identification.compliant.COMPLIANT_SEGMENT_S: the compliant equations are less
    linear over a segment); a given length is kept."""
    from prsa_ctrl.identification.common import default_keys
    from prsa_ctrl.identification.compliant import COMPLIANT_SEGMENT_S

    rec, truth = sim
    seen = []

    def fake(records, plant, *, segment_s, **kw):
        seen.append(segment_s)
        raise td.FitError("stop")

    monkeypatch.setattr(td, "_fit_records", fake)
    # (the keys given: a compliant fit with the default keys and nothing to place its mode from is
    # refused before it starts, compliant.unplaced_mode)
    keys = default_keys(truth)
    with pytest.raises(td.FitError):
        td.fit_plant([rec], truth, keys=keys, fidelity=fidelity, delay_samples=0, validation=False)
    assert seen == [expected]
    assert COMPLIANT_SEGMENT_S == 0.05
    assert td.SEGMENT_S == 0.1
    with pytest.raises(td.FitError):
        td.fit_plant([rec], truth, keys=keys, fidelity=fidelity, delay_samples=0, validation=False, segment_s=0.02)
    assert seen[-1] == 0.02


def _with_a_kept_key(monkeypatch, key):
    """finish_fit as the fit calls it, with ``key`` reported not identified (kept at the base value)."""
    orig = td.finish_fit

    def kept(plant, keys, *a, **kw):
        out = orig(plant, keys, *a, **kw)
        out[0][key]["kept_base"] = True
        return out

    monkeypatch.setattr(td, "finish_fit", kept)


def test_the_plant_as_written_is_checked_from_the_free_fits_states(sim, monkeypatch):
    # With a key kept at its base value, the plant as written is run on the fit's segments; that
    # states-only solve starts from the free fit's states (the plants differ only in the kept
    # key), not from the data reference (where, on the ball-screw logs at seed 1, a segment's
    # start settled in the stick band and the check stalled: the cross-validation fit failed).
    rec, truth = sim
    keys = ("nut.inertia_kg_m2", "friction.viscous_n_m_s_per_rad")
    _with_a_kept_key(monkeypatch, keys[1])
    calls = []
    orig = td._Problem.solve

    def spy(self, *a, **kw):
        out = orig(self, *a, **kw)
        calls.append((kw.get("fixed"), kw.get("init"), out))
        return out

    monkeypatch.setattr(td._Problem, "solve", spy)
    start = truth.with_params({keys[1]: 2.0 * truth.values[keys[1]]})  # the written value differs from the free one
    res = td.fit_plant([rec], start, keys=keys, delay_samples=0, validation=False)
    free = [c for c in calls if not c[0]]
    fixed = [c for c in calls if c[0]]
    assert len(free) == 1
    assert len(fixed) == 1
    init = fixed[0][1]
    assert init is not None
    assert np.array_equal(init[0], free[0][2]["V"])
    assert np.array_equal(init[1], free[0][2]["X0"])
    assert fixed[0][2]["status"] == "converged"
    assert "fit_percent_written" in res.solver


def test_a_written_plant_check_that_fails_is_reported_not_a_failed_fit(sim, monkeypatch):
    rec, truth = sim
    keys = ("nut.inertia_kg_m2", "friction.viscous_n_m_s_per_rad")
    ref = td.fit_plant([rec], truth, keys=keys, delay_samples=0, validation=False)
    _with_a_kept_key(monkeypatch, keys[1])
    orig = td._Problem.solve

    def stall_when_fixed(self, *a, **kw):
        if kw.get("fixed"):
            raise td.FitError("fit did not converge: Gauss-Newton status 'stalled' after 18 iterations")
        return orig(self, *a, **kw)

    monkeypatch.setattr(td._Problem, "solve", stall_when_fixed)
    res = td.fit_plant([rec], truth, keys=keys, delay_samples=0, validation=False)
    assert "fit_percent_written" not in res.solver
    assert any("was not followed on the fit's segments" in w and "stalled" in w for w in res.warnings)
    # the free fit itself is the one without the check
    assert res.parameters[keys[0]]["value"] == pytest.approx(ref.parameters[keys[0]]["value"], rel=1e-12)


@pytest.fixture(scope="module")
def roller_logs(tmp_path_factory):
    """The foreign roller-screw logs (tests/identification/foreign/gen_rollerscrew.py, seed 0:
    two-mass, two delays, filtered speed) in the base plant's motor coordinates, and that plant."""
    from foreign import gen_rollerscrew as rs
    from prsa_ctrl import load_plant
    from prsa_ctrl.identification.logformat import load_log_format, load_motor_record

    s = rs.generate(tmp_path_factory.mktemp("rs"), seed=0)
    plant = load_plant(s["base"])
    fmt = load_log_format(s["log_format"])
    return [load_motor_record(s["logs"][n], fmt, plant)[0] for n in ("multisine", "loadsteps", "staircase")], plant


def _fit_fast_loop(roller_logs, **kw):
    """The delay search's fit at shift 3 on its 0.02 s segments, started (as the search starts
    it) from the current loop of the same total lag as the fit at shift 1: 10 kHz. On the
    multisine log alone (was the three logs: 12.0 s of CPU, now 5.1 s, measured under load): it
    fails the same way without either fix of 9f8c5eb (without the held last attempt: 'stalled'
    after 37 iterations; with the stall window opened at the warm-up: 'stalled' after 19)."""
    records, plant = roller_logs
    start = plant.with_params({BW: 1.0e4})
    return td._fit_records(records[:1], start, frf=(), keys=None, fidelity="rigid", validate=(), segment_s=0.02,
                           delay_samples=3, substeps=1, max_iter=50, tol=1e-8, min_speed_rad_s=None,
                           keep_unidentified=True, simulate=False, check_written=False, base=plant, **kw)


def test_a_current_loop_that_settles_within_a_sample_leaves_the_state_steps_short(roller_logs):
    """At 10 kHz the initial torque of a segment reaches its angles 4e-7 as strongly as the
    angle does: a step that kept that direction was so long that the collocation residual rose
    to 112 and stalled there even with the parameters held; the rigid fit's last attempt holds
    it (gaussnewton.RIGID_X0_RTOL)."""
    from prsa_ctrl.identification.common import default_keys, key_bounds

    records, plant = roller_logs
    start = plant.with_params({BW: 1.0e4})
    keys = default_keys(plant)
    scales = np.array([key_bounds(start, k, records[0].sample_time_s)[2] for k in keys])
    run = td._Problem(plant.with_params({BW: 1.0e4}), keys, scales, "rigid", records, records[0].sample_time_s, 0.02,
                      3, 1, td.default_min_speed(plant))
    s0 = np.array([start.values[k] for k in keys]) / scales
    run.step_rtol = gn.RIGID_X0_RTOL
    sol = run.solve(s0, s0, s0, 50, 1e-8, fixed=True)  # raises FitError when it stalls
    assert sol["status"] == "converged"


def test_the_search_fit_at_a_fast_current_loop_converges_from_its_first_start(roller_logs):
    """The roller-screw logs' delay search failed at shift 3 from every start (4 starts x 3
    attempts): besides the long state steps, the stall test compared the constraint residual
    with the warm-up's (the equations solved with the parameters held, ~1e-11), so an attempt
    still closing in was given up at iteration warm + 16. Now the first start converges."""
    res = _fit_fast_loop(roller_logs)  # raises FitError when every attempt fails
    assert res.solver["status"] == "converged"
    bw = res.parameters[BW]
    assert bw["value"] > 1.0e4  # the shift leaves almost no lag for the loop: it goes fast
    assert math.isfinite(res.solver["objective"])


def test_a_rigid_fit_whose_defect_plateaus_takes_the_full_step(sim, monkeypatch):
    """A line search that accepts only short steps lowering the objective while the largest
    defect stays put (the foreign feed axis's first attempt: 0.0927 for 18 iterations, then
    given up) takes the full Newton step at once (gaussnewton.PLATEAU_ITERATIONS), a
    non-monotone step of the bounded budget the failed line search has: here every trial is
    accepted and the defect never falls, so the budget runs out ('line search failed') before
    the iteration budget, below the general stall test's 15 iterations."""
    rec, truth = sim
    orig = td._Problem.linearise

    def plateau(self, V, X0, s):
        res, lin = orig(self, V, X0, s)
        return np.full_like(res, 0.05), lin  # the defect never falls (above FIRST_ORDER_G_MAX)

    monkeypatch.setattr(td._Problem, "linearise", plateau)
    monkeypatch.setattr(td._Problem, "_merit_terms", lambda self, V, X0, s: (0.05, 0.0))  # every trial accepted
    assert gn.PLATEAU_ITERATIONS + 4 + 4 < td.STALL_ITERATIONS
    with pytest.raises(td.FitError, match="status 'line search failed'"):
        td.fit_plant([rec], truth, keys=("nut.inertia_kg_m2",), delay_samples=0, validation=False,
                     max_iter=td.STALL_ITERATIONS - 4)
