"""The delay search (prsa_ctrl.identification.delay.search_delay) on a fake fit: a failed fit at
a shift is a failure of the fit (retried from other starts, the delay left undecided), never
evidence for another shift; a computed command's search starts at one sample."""

import math
import warnings

import numpy as np
import pytest

import foreign_generator as fg
from prsa_ctrl import GeometryWarning, load_plant
from prsa_ctrl.errors import FitError
from prsa_ctrl.identification.common import DEFAULT_KEYS, FitResult
from prsa_ctrl.identification.data import record_from_arrays
from prsa_ctrl.identification.delay import DELAY_OBJECTIVE_RATIO, DELAY_TEST_LEVEL, search_delay, segment_test
from prsa_ctrl.identification.timedomain import fit_plant

BW = "drive.current_loop_bandwidth_hz"
KEYS = ("nut.inertia_kg_m2", BW)


@pytest.fixture(scope="module")
def plant():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeometryWarning)
        return load_plant()


def _result(plant, objective, bw):
    params = {"nut.inertia_kg_m2": {"value": 1e-3, "ci95": [0.9e-3, 1.1e-3], "unit": "kg m^2"},
              BW: {"value": bw, "ci95": [0.5 * bw, 1.5 * bw], "unit": "Hz"}}
    return FitResult(plant, params, {"value": 1e-3, "ci95": [0.9e-3, 1.1e-3], "unit": "kg m^2"}, np.eye(2), KEYS,
                     {}, [], {"objective": objective}, {}, None, {}, None)


def _fake(plant, objectives, fail_starts=None, calls=None):
    """fit_at: the objective per shift; ``fail_starts[shift]`` = how many starts fail first."""
    fail_starts = dict(fail_starts or {})

    def fit_at(shift, start):
        if calls is not None:
            calls.append((shift, start.values[BW]))
        if fail_starts.get(shift, 0) > 0:
            fail_starts[shift] -= 1
            raise FitError(f"fit did not converge at {shift}")
        return _result(plant, objectives[shift], 100.0)  # 100 Hz: lag of ~6 samples at 4 kHz, room for all shifts

    return fit_at


def test_a_failed_fit_is_not_evidence_for_another_shift(plant):
    # shift 1 would be best but its fit fails from every start: 2 is the best of those that converged,
    # and the search must say the delay is NOT decided (the "0: failed, 1: failed, 2: ..." case)
    calls = []
    fit_at = _fake(plant, {0: 50.0, 1: 1.0, 2: 40.0, 3: 90.0, 4: 95.0}, {0: 99, 1: 99}, calls)
    shift, res = search_delay(fit_at, plant, KEYS, 2.5e-4, 4)
    ds = res.solver["delay_search"]
    assert shift == 2
    assert ds["decided"] is False
    assert ds["objective"]["1"] is None
    assert ds["objective"]["0"] is None
    assert int(ds["starts"]["1"]) >= 3  # retried from other starts
    assert len([c for c in calls if c[0] == 1]) == int(ds["starts"]["1"])
    assert any("failed at shifts 0, 1" in w and "no evidence" in w for w in res.warnings)


def test_a_retried_fit_counts_and_the_search_decides(plant):
    fit_at = _fake(plant, {0: 50.0, 1: 1.0, 2: 40.0, 3: 90.0, 4: 95.0}, {1: 1})
    shift, res = search_delay(fit_at, plant, KEYS, 2.5e-4, 4)
    ds = res.solver["delay_search"]
    assert shift == 1
    assert ds["decided"] is True
    assert ds["starts"]["1"] == 2
    assert any("converged from start 2" in w for w in res.warnings)


def test_close_objectives_leave_the_delay_undecided(plant):
    fit_at = _fake(plant, {0: 1.0, 1: 0.99 * DELAY_OBJECTIVE_RATIO, 2: 40.0, 3: 90.0, 4: 95.0})
    shift, res = search_delay(fit_at, plant, KEYS, 2.5e-4, 4)
    assert shift == 0
    assert res.solver["delay_search"]["decided"] is False
    fit_at = _fake(plant, {0: 1.0, 1: 1.01 * DELAY_OBJECTIVE_RATIO, 2: 40.0, 3: 90.0, 4: 95.0})
    shift, res = search_delay(fit_at, plant, KEYS, 2.5e-4, 4)
    assert shift == 0
    assert res.solver["delay_search"]["decided"] is True


def test_a_computed_command_is_searched_from_one_sample(plant):
    calls = []
    fit_at = _fake(plant, {0: 0.5, 1: 1.0, 2: 40.0, 3: 90.0, 4: 95.0}, calls=calls)
    shift, res = search_delay(fit_at, plant, KEYS, 2.5e-4, 4, min_shift=1)
    assert shift == 1
    assert all(c[0] >= 1 for c in calls)
    assert res.solver["delay_search"]["range"] == [1, 4]
    with pytest.raises(ValueError, match="min_shift"):
        search_delay(fit_at, plant, KEYS, 2.5e-4, 2, min_shift=3)


def test_every_shift_failing_is_a_fit_error_naming_them(plant):
    fit_at = _fake(plant, {s: 1.0 for s in range(5)}, {s: 99 for s in range(5)})
    with pytest.raises(FitError, match="any command delay 1..4"):
        search_delay(fit_at, plant, KEYS, 2.5e-4, 4, min_shift=1)


def _fake_logs(plant, per_log):
    """fit_at whose result carries ``objective_per_record``: ``per_log[shift] = {log: objective}``."""

    def fit_at(shift, start):
        r = _result(plant, sum(per_log[shift].values()), 100.0)
        r.solver["objective_per_record"] = dict(per_log[shift])
        return r

    return fit_at


# Objectives of the ball-screw logs of tests/identification/foreign (seed 0, shifts 1 and 2, 0.02 s
# segments, true shift 2) in units of 1e7: the multisine shows the delay, the staircase's misfit
# (standstill friction the model lacks) is alike at both shifts and dominates the sum.
_BS = {0: {"multisine.csv": 90.0, "loadsteps.csv": 30.0, "staircase.csv": 60.0},
       1: {"multisine.csv": 6.5, "loadsteps.csv": 7.464, "staircase.csv": 43.58},
       2: {"multisine.csv": 3.063, "loadsteps.csv": 8.054, "staircase.csv": 45.59},
       3: {"multisine.csv": 40.0, "loadsteps.csv": 20.0, "staircase.csv": 90.0}}


def test_a_log_that_shows_the_delay_decides_it(plant):
    # all logs together: 1 at 57.5, 2 at 56.7 (ratio 1.01, undecided by the pooled rule); the
    # multisine alone fits 2 2.1 x better and no log fits 1 1.5 x better: 2, decided, and it says by what
    per = {s: _BS[s] for s in (0, 1, 2, 3)}
    shift, res = search_delay(_fake_logs(plant, per), plant, KEYS, 1.25e-4, 3)
    ds = res.solver["delay_search"]
    assert shift == 2
    assert ds["decided"] is True
    assert ds["decided_by_logs"]["1"] == ["multisine.csv"]
    assert ds["objective_per_log"]["2"]["multisine.csv"] == pytest.approx(3.063)
    assert any("decided by the logs where it shows" in w and "multisine.csv" in w for w in res.warnings)
    # the staircase made a little worse at 2: the sum now prefers 1, the multisine still decides 2
    per = {s: dict(v) for s, v in per.items()}
    per[2]["staircase.csv"] = 48.0
    assert sum(per[2].values()) > sum(per[1].values())
    shift, res = search_delay(_fake_logs(plant, per), plant, KEYS, 1.25e-4, 3)
    assert shift == 2
    assert res.solver["delay_search"]["decided"] is True


def test_a_log_that_contradicts_leaves_the_delay_undecided(plant):
    # the load steps fit 1 at least 1.5 x better while the multisine fits 2 2.1 x better: no decision
    per = {s: dict(v) for s, v in _BS.items()}
    per[1]["loadsteps.csv"] = 8.054 / 1.6
    shift, res = search_delay(_fake_logs(plant, per), plant, KEYS, 1.25e-4, 3)
    ds = res.solver["delay_search"]
    assert ds["decided"] is False
    assert any("not decided" in w for w in res.warnings)
    # no log shows it: undecided as before (the pooled ratio alone)
    per = {s: {"a.csv": v, "b.csv": v} for s, v in {0: 30.0, 1: 1.2, 2: 1.0, 3: 30.0}.items()}
    shift, res = search_delay(_fake_logs(plant, per), plant, KEYS, 1.25e-4, 3)
    assert shift == 2
    assert res.solver["delay_search"]["decided"] is False
    assert res.solver["delay_search"]["decided_by_logs"] == {"0": ["a.csv", "b.csv"], "3": ["a.csv", "b.csv"]}


def test_a_failed_shift_still_leaves_it_undecided_with_a_log_that_shows_it(plant):
    per = {s: _BS[s] for s in (0, 1, 2, 3)}
    ok = _fake_logs(plant, per)

    def fit_at(shift, start):
        if shift == 3:
            raise FitError("fit did not converge at 3")
        return ok(shift, start)

    shift, res = search_delay(fit_at, plant, KEYS, 1.25e-4, 3)
    assert shift == 2
    assert res.solver["delay_search"]["decided"] is False


@pytest.mark.slow
@pytest.mark.parametrize("how", ["applied", "computed"])
def test_ball_screw_logs_refute_every_shorter_delay(how, tmp_path):
    # Evidence (issue 32): the foreign ball-screw logs (tests/identification/foreign, seed
    # $PRSA_FOREIGN_SEED), true shift 2 applied / 3 computed. On 0.1 s segments the search found
    # 1 and 2 within 1 % and failed at 0 and 3; now every shift converges, the best is the true
    # one and every shorter shift is refuted (all logs together or by a log of its own).
    import os
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from foreign import gen_ballscrew as bs

    from prsa_ctrl.identification.data import load_record
    from prsa_ctrl.identification.timedomain import fit_plant

    s = bs.generate(tmp_path, seed=int(os.environ.get("PRSA_FOREIGN_SEED", "0")))
    truth = s["truth"][how]
    recs = [load_record(s["logs"][how][n]) for n in ("multisine", "loadsteps", "staircase")]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeometryWarning)
        base = load_plant(s["base"])
    res = fit_plant(recs, base, delay_samples="find", command_logged=how, validation=False)
    cd = res.solver["command_delay"]
    search = cd["search"]
    true_shift = truth["delay_logged_to_action_samples"]  # (the computed log's one sample included)
    assert cd["shift_samples"] == true_shift, search["objective"]
    assert all(v is not None for v in search["objective"].values()), search["failed"]
    f = {int(k): v for k, v in search["objective"].items()}
    for shorter in range(search["range"][0], true_shift):
        assert f[shorter] >= DELAY_OBJECTIVE_RATIO * f[true_shift] or str(shorter) in search["decided_by_logs"], shorter
    # and the longer shift (within 1.5 x on every log: 1.04..1.13 on seed 0) by the paired segment
    # test: every log fits it worse, t over the 150 segments well past the critical value
    longer = true_shift + 1
    assert search["decided"] is True, search["segment_test"]
    assert longer in search["decided_by_test"], search["segment_test"]
    st = search["segment_test"][str(longer)]
    assert st["t"] >= st["critical_t"]
    assert st["logs_preferring_it"] == []
    assert all(v["ratio"] > 1.0 for v in st["per_log"].values())


def _fake_segments(plant, per_seg):
    """fit_at whose result carries per-segment objectives: ``per_seg[shift] = {log: [objective per segment]}``."""

    def fit_at(shift, start):
        segs = {n: [float(x) for x in v] for n, v in per_seg[shift].items()}
        r = _result(plant, sum(sum(v) for v in segs.values()), 100.0)
        r.solver["objective_per_record"] = {n: sum(v) for n, v in segs.items()}
        r.solver["objective_per_segment"] = segs
        return r

    return fit_at


def _segments(seed, n, level, spread):
    rng = np.random.default_rng(seed)
    return level * (1.0 + spread * rng.standard_normal(n))


def test_segment_test_is_the_paired_t_of_the_segment_differences():
    from scipy import stats

    b = {"a.csv": [1.0, 2.0, 3.0, 4.0, 5.0, 6.0], "b.csv": [2.0, 2.0, 2.0, 2.0, 2.0, 2.0]}
    s = {"a.csv": [1.1, 2.3, 3.0, 4.2, 5.1, 6.4], "b.csv": [2.1, 2.0, 2.2, 2.05, 1.9, 2.3]}
    out = segment_test(s, b)
    d = np.concatenate([np.subtract(s[n], b[n]) for n in ("a.csv", "b.csv")])
    ref = stats.ttest_1samp(d, 0.0, alternative="greater")  # an independent computation of the same test
    assert out["segments"] == 12
    assert out["t"] == pytest.approx(float(ref.statistic), rel=1e-12)
    assert out["p_one_sided"] == pytest.approx(float(ref.pvalue), rel=1e-9)
    assert out["ratio"] == pytest.approx(sum(map(sum, s.values())) / sum(map(sum, b.values())))
    assert segment_test(b, s)["t"] == pytest.approx(-out["t"])  # symmetric
    # one log only
    assert segment_test(s, b, ["a.csv"]) is None  # 6 segments: fewer than MIN_TEST_SEGMENTS
    # segments that do not pair up, or no spread of the differences: no test
    assert segment_test({"a.csv": [1.0] * 11}, {"a.csv": [1.0] * 12}) is None
    assert segment_test({"a.csv": [2.0] * 12}, {"a.csv": [1.0] * 12}) is None


def test_a_consistently_worse_longer_shift_is_refuted_by_the_segment_test(plant):
    # Shift 3 fits 5 % worse than 2 on every segment of every log (with a 2 % segment-to-segment
    # spread): far inside the ratio 1.5, but 150 paired segments refute it; 0 and 1 are refuted by
    # the ratio. The delay is decided at 2, and the report says by which test.
    base = {n: _segments(i, 50, lv, 0.3) for i, (n, lv) in enumerate((("m.csv", 6e5), ("l.csv", 1.6e6), ("s.csv", 9e6)))}
    per = {2: base,
           3: {n: v * 1.05 * (1 + 0.02 * np.random.default_rng(10 + i).standard_normal(v.size))
               for i, (n, v) in enumerate(base.items())},
           0: {n: v * 3.0 for n, v in base.items()},
           1: {n: v * 2.0 for n, v in base.items()}}
    shift, res = search_delay(_fake_segments(plant, per), plant, KEYS, 1.25e-4, 3)
    ds = res.solver["delay_search"]
    assert shift == 2
    assert ds["decided"] is True
    assert ds["decided_by_test"] == [3]
    t3 = ds["segment_test"]["3"]
    assert t3["refutes"]
    assert t3["t"] > t3["critical_t"] > 2.0
    assert t3["segments"] == 150
    assert ds["test_level"] == DELAY_TEST_LEVEL
    assert any("paired segment test" in w and "shift 3 against 2" in w for w in res.warnings)
    # without the per-segment objectives (the ratio rule alone) the same fits stay undecided
    bare = _fake_segments(plant, per)

    def no_segments(shift, start):
        r = bare(shift, start)
        del r.solver["objective_per_segment"]
        return r

    shift, res = search_delay(no_segments, plant, KEYS, 1.25e-4, 3)
    assert shift == 2
    assert res.solver["delay_search"]["decided"] is False


def test_differences_within_the_segment_noise_leave_the_delay_undecided(plant):
    # shift 3's segments differ from 2's by noise of zero mean (the two fit alike): not refuted
    base = {"m.csv": _segments(1, 60, 1e6, 0.3), "l.csv": _segments(2, 60, 2e6, 0.3)}
    noise = np.random.default_rng(3)
    per = {2: base, 3: {n: v * (1 + 0.05 * noise.standard_normal(v.size)) for n, v in base.items()},
           1: {n: v * 2.0 for n, v in base.items()}}
    per[3] = {n: v * (sum(base[n]) / sum(v)) * 1.0001 for n, v in per[3].items()}  # the sum a hair worse
    shift, res = search_delay(_fake_segments(plant, per), plant, KEYS, 1.25e-4, 3, min_shift=1)
    ds = res.solver["delay_search"]
    assert shift == 2
    assert ds["decided"] is False
    assert abs(ds["segment_test"]["3"]["t"]) < ds["segment_test"]["3"]["critical_t"]
    assert not ds["segment_test"]["3"]["refutes"]


def test_a_log_whose_own_test_prefers_the_other_shift_leaves_it_undecided(plant):
    # pooled, shift 3 is worse (the big log); but the small log's segments prefer 3 significantly:
    # the model's misfit, not the delay, may drive either, so the test does not decide
    base = {"m.csv": _segments(4, 50, 1e6, 0.2), "l.csv": _segments(5, 50, 4e6, 0.2)}
    per = {2: base, 3: {"m.csv": base["m.csv"] * 0.9, "l.csv": base["l.csv"] * 1.08},
           1: {n: v * 2.0 for n, v in base.items()}}
    shift, res = search_delay(_fake_segments(plant, per), plant, KEYS, 1.25e-4, 3, min_shift=1)
    ds = res.solver["delay_search"]
    t3 = ds["segment_test"]["3"]
    assert t3["t"] > t3["critical_t"]  # the pooled test alone would refute it
    assert t3["logs_preferring_it"] == ["m.csv"]
    assert not t3["refutes"]
    assert shift == 2
    assert ds["decided"] is False
    assert any("cannot decide the command delay either" in w and "m.csv" in w for w in res.warnings)


def _one_log_shows_it(prefer_other=False):
    """Shift 2 against 1: the small log m.csv fits 2 worse by 30 % on every segment (5 % spread);
    the two large logs scatter with zero-mean differences 200 times m.csv's effect per segment
    (noise or misfit the shift does not change). With ``prefer_other`` s.csv's own segments
    prefer shift 2 (8 % better on each, 20 % spread)."""
    rng = np.random.default_rng(21)
    base = {"m.csv": _segments(6, 60, 1e3, 0.3), "l.csv": _segments(7, 60, 1e5, 0.3), "s.csv": _segments(8, 60, 1e5, 0.3)}
    two = {"m.csv": base["m.csv"] * 1.3 * (1 + 0.05 * rng.standard_normal(60))}
    for n in ("l.csv", "s.csv"):
        d = 6e4 * rng.standard_normal(60)
        two[n] = base[n] + (d - d.mean())
    if prefer_other:
        two["s.csv"] = base["s.csv"] * 0.92 * (1 + 0.2 * rng.standard_normal(60))
        two["l.csv"] = two["l.csv"] + (sum(base["s.csv"]) - sum(two["s.csv"])) / 60 * 1.01
    return {1: base, 2: two, 0: {n: v * 2.0 for n, v in base.items()}}


def test_one_log_that_shows_the_delay_decides_it_when_the_others_only_scatter(plant):
    # The judge's ball-rigid-d2-applied-si logs ended exit 3 "could not decide" (shift 2 with a
    # 7.9 kHz current loop against the true 1: the multisine alone t = 5.39 over 60 segments,
    # pooled with the load steps and the staircase t = 2.29 against the critical 2.60). The
    # pooled test adds the other logs' scatter to the differences; one log's own test, at the
    # level over every log and shift, refutes shift 2 here while no log prefers it.
    per = _one_log_shows_it()
    shift, res = search_delay(_fake_segments(plant, per), plant, KEYS, 1.25e-4, 2, min_shift=0)
    ds = res.solver["delay_search"]
    t2 = ds["segment_test"]["2"]
    assert t2["t"] < t2["critical_t"]  # the pooled test alone leaves it undecided
    assert 1.0 < ds["objective"]["2"] / ds["objective"]["1"] < DELAY_OBJECTIVE_RATIO
    from scipy import stats

    crit_alone = float(stats.t.isf(DELAY_TEST_LEVEL / (2 * 3), 59))  # 2 other shifts x 3 logs
    assert t2["per_log"]["m.csv"]["critical_t_alone"] == pytest.approx(crit_alone)
    assert t2["per_log"]["m.csv"]["t"] > crit_alone
    assert t2["logs_refuting_it"] == ["m.csv"]
    assert t2["refutes"]
    assert t2["logs_preferring_it"] == []
    assert shift == 1
    assert ds["decided"] is True
    assert ds["decided_by_test"] == [2]
    assert any("m.csv alone t = " in w and "shift 2 against 1" in w for w in res.warnings)


def test_one_log_refuting_a_shift_another_log_prefers_leaves_it_undecided(plant):
    per = _one_log_shows_it(prefer_other=True)
    shift, res = search_delay(_fake_segments(plant, per), plant, KEYS, 1.25e-4, 2, min_shift=0)
    ds = res.solver["delay_search"]
    t2 = ds["segment_test"]["2"]
    assert t2["logs_refuting_it"] == ["m.csv"]
    assert t2["logs_preferring_it"] == ["s.csv"]
    assert not t2["refutes"]
    assert shift == 1
    assert ds["decided"] is False


@pytest.mark.slow
def test_the_judges_ball_screw_logs_with_two_samples_of_delay_decide_their_shift(tmp_path):
    # The judge's ball-rigid-d2-applied-si logs (tests/identification/foreign/gen_judge.py: two
    # samples from computation to action, the command logged as applied, so it acts one sample
    # after its row: shift 1, drive.command_delay_samples 1) ended exit 3 "could not decide the
    # command delay (0: 8.43e5, 1: 3.39e5, 2: 3.75e5)": shift 2 with a 7.9 kHz current loop has
    # the same total lag, the multisine alone refutes it, all logs pooled did not.
    import os
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from foreign import gen_judge as gj

    from prsa_ctrl.identification.data import load_record

    s = gj.generate(tmp_path, "ball-rigid-d2-applied-si", seed=int(os.environ.get("PRSA_FOREIGN_SEED", "0")))
    truth = s["truth"]
    recs = [load_record(s["logs"][n]) for n in gj.EXPERIMENTS]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeometryWarning)
        base = load_plant(s["base"])
    res = fit_plant(recs, base, delay_samples="find", command_logged="applied", validation=False)
    cd = res.solver["command_delay"]
    search = cd["search"]
    assert cd["shift_samples"] == truth["delay_logged_to_action_samples"] == 1, search["objective"]
    assert cd["drive_command_delay_samples"] == truth["drive.command_delay_samples"]
    assert search["decided"] is True, search["segment_test"]
    f = {int(k): v for k, v in search["objective"].items()}
    assert all(v is not None for v in f.values())
    assert min(f, key=f.get) == 1
    assert "2" in {str(x) for x in search["decided_by_test"]} or f[2] >= DELAY_OBJECTIVE_RATIO * f[1]
    jt = truth["reflected_inertia_kg_m2"]
    lo, hi = res.reflected_inertia_kg_m2["ci95"]
    assert abs(res.reflected_inertia_kg_m2["value"] / jt - 1) < 0.03
    assert lo <= jt <= hi
    fc = res.plant.values[BW]
    assert abs(fc / truth[BW] - 1) < 0.25


# ---- folded from test_foreign_logs.py:
# Acceptance "Foreign logs" of issue 21: logs written by an independent drive simulator
# (foreign_generator.py: numpy/scipy only, not the toolkit's simulator) with a transport delay and
# the computation delay, asymmetric Stribeck friction, encoder quantisation, a closed PI speed
# loop, load steps 500 -> 1500 -> 0 N, a speed staircase through both directions and a multisine.
#
# The fit must converge, find the delay, get the current-loop bandwidth within 10 % and hold the
# truth in its 95 % intervals; a log whose command convention is off by one sample is detected.
# The 20-seed coverage study is ``-m slow``; the default run fits one seed.

DELAY = "drive.command_delay_samples"


@pytest.fixture(scope="module")
def base():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_plant()


def _axis(base, **kw):
    return fg.Axis(lead_m_per_rad=base.lead_per_rad, counts_per_rev=base.encoder_counts, **kw)


def _truth(base, ax: fg.Axis) -> dict:
    """The generator's axis in plant keys: the nut inertia is the total less what the rest of
    the base plant's mechanism reflects (rollers, cage, translating screw)."""
    rest = base.reflected_inertia_kg_m2 - base.values["nut.inertia_kg_m2"]
    return {"nut.inertia_kg_m2": ax.inertia_kg_m2 - rest, "friction.efficiency": ax.efficiency,
            "friction.no_load_torque_n_m": ax.no_load_torque_n_m,
            "friction.viscous_n_m_s_per_rad": ax.viscous_n_m_s_per_rad, BW: ax.bandwidth_hz,
            "friction.torque_offset_n_m": ax.offset_torque_n_m}


def _records(logs):
    return [record_from_arrays(lg.name, lg.time_s, lg.command_n_m, nut_angle_rad=lg.angle_rad, axial_load_n=lg.load_n)
            for lg in logs]


def _fit(base, ax, seed, duration_s=1.5, convention="applied", command_logged="applied", **kw):
    truth = _truth(base, ax)
    recs = _records(fg.logs(ax, seed, duration_s=duration_s, convention=convention))
    res = fit_plant(recs, base, keys=tuple(truth), delay_samples="find", command_logged=command_logged, **kw)
    return res, truth


_ONE_SEED: dict = {}


def one_seed_fit(base):
    """``(axis, result, truth)`` of the default run's one-seed fit (seed 3, 0.5 s of each of the
    three logs, one sample of transport delay), made once per session and shared by
    test_one_seed_all_three_logs and the covariance tests of tests/identification/test_common.py."""
    if not _ONE_SEED:
        ax = _axis(base, transport_samples=1)
        _ONE_SEED["fit"] = (ax, *_fit(base, ax, seed=3, duration_s=0.5))
    return _ONE_SEED["fit"]


def _z(res, truth) -> dict:
    """(fitted - true) in standard errors of the fit (half the 95 % interval / 1.96)."""
    out = {}
    for k, v in truth.items():
        lo, hi = res.parameters[k]["ci95"]
        out[k] = (res.parameters[k]["value"] - v) / max((hi - lo) / (2 * 1.959964), 1e-300)
    return out


def test_generator_is_independent_and_physical(base):
    """The generator's own checks: at constant speed and load its steady torque is the
    screw's (load / efficiency + Coulomb level + offset + viscous); the log is quantised."""
    ax = _axis(base, transport_samples=1)
    n = 2000
    log = fg.simulate(ax, np.full(n, 40.0), np.full(n, 1000.0), seed=1)
    steady = ax.lead_m_per_rad * 1000.0 / ax.efficiency + ax.no_load_torque_n_m + ax.offset_torque_n_m \
        + ax.viscous_n_m_s_per_rad * 40.0
    assert np.mean(log.command_n_m[n // 2:]) == pytest.approx(steady, rel=2e-3)
    q = 2 * math.pi / ax.counts_per_rev
    assert np.allclose(np.round(log.angle_rad / q) * q, log.angle_rad, rtol=0, atol=1e-12)
    # the computed command leads the applied one by exactly one sample
    log_c = fg.simulate(ax, np.full(n, 40.0), np.full(n, 1000.0), seed=1, convention="computed")
    np.testing.assert_array_equal(log_c.command_n_m[:-1], log.command_n_m[1:])


def test_one_seed_all_three_logs(base):
    """Load steps, staircase and multisine together (the issue: the fit stalled on the first
    two and put 650 Hz at 334 Hz on the third): converged, delay 1 sample found, bandwidth
    within 10 %, every key within 4 standard errors of the truth."""
    ax, res, truth = one_seed_fit(base)
    cd = res.solver["command_delay"]
    assert res.solver["status"] == "converged"
    assert cd["shift_samples"] == 1
    assert cd["search"]["decided"]
    assert res.plant.values[DELAY] == 1
    assert res.plant.sources[DELAY].startswith("fit: found")
    obj = cd["search"]["objective"]
    assert obj["0"] > 10 * obj["1"]  # the delay-free hypothesis fits far worse
    assert abs(res.parameters[BW]["value"] / ax.bandwidth_hz - 1) < 0.10
    z = _z(res, truth)
    assert all(abs(v) < 4 for v in z.values()), z


def test_command_logged_as_computed_is_detected(base):
    """The issue's second case: a drive logging the command as computed, true 1100 Hz and no
    transport delay. Said to be 'applied' (the default), the fit finds the extra sample, keeps
    the bandwidth right and warns with the other convention's reading; said to be 'computed', the
    plant gets no command delay."""
    ax = _axis(base, transport_samples=0, bandwidth_hz=1100.0)
    n = 2000
    sp, ld = fg.multisine(n, ax.sample_time_s, seed=5)
    log = fg.simulate(ax, sp, ld, seed=5, name="ms-computed", convention="computed")
    rec = _records([log])
    keys = DEFAULT_KEYS  # what prsa-fit fits by default
    res = fit_plant(rec, base, keys=keys, delay_samples="find")
    assert res.solver["command_delay"]["shift_samples"] == 1
    assert res.plant.values[DELAY] == 1
    assert abs(res.parameters[BW]["value"] / 1100.0 - 1) < 0.10
    assert any("--command-logged computed" in w and "it is 0" in w for w in res.warnings)
    # the old behaviour, a fixed shift of 0, fits far worse (it reported 592 Hz for this case)
    obj = res.solver["command_delay"]["search"]["objective"]
    assert obj["0"] > 10 * obj["1"]
    res_c = fit_plant(rec, base, keys=keys, delay_samples=1, command_logged="computed")
    assert res_c.plant.values[DELAY] == 0
    assert abs(res_c.parameters[BW]["value"] / 1100.0 - 1) < 0.10


def test_computed_with_too_short_a_delay_refused(base):
    """A log said to hold the computed command whose command acts at once is contradictory."""
    from prsa_ctrl.errors import FitError

    ax = _axis(base, transport_samples=0, bandwidth_hz=1100.0)
    # 300 samples of the multisine (was 2000, then 600): the refusal is reached the same way (the
    # fit from 1 sample on fails, the one at 0 samples converges) and its message is the same; the
    # contradiction is in the first sample of delay, not in the record's length (300: 4.5 s of CPU,
    # 600: 7.0 s; without the convention's check, delay.check_convention, the search's failure is
    # raised instead and this test fails). The search
    # ends at 1 sample (max_delay_samples=1, was the default 4): from 1 sample on every fit
    # fails, so shifts 2..4 only added 18 more failing fits (12 s of this test's 15.5 s CPU)
    # before the same refusal with the same message ("from 1 samples on: the fit failed")
    n = 300
    sp, ld = fg.multisine(n, ax.sample_time_s, seed=6)
    rec = _records([fg.simulate(ax, sp, ld, seed=6, convention="applied")])
    with pytest.raises(FitError, match="--command-logged applied"):
        fit_plant(rec, base, delay_samples="find", command_logged="computed", max_delay_samples=1)
    with pytest.raises(ValueError, match="command_logged = 'applied'"):  # refused before any fit
        fit_plant(rec, base, delay_samples=0, command_logged="computed")


@pytest.mark.slow
def test_coverage_over_20_seeds(base):
    """The acceptance numbers: every key's truth inside its 95 % interval for >= 18 of 20 seeds,
    the bandwidth within 10 % and the delay found in every seed.

    Jointly: the truth of all six keys inside the joint 95 % confidence region (the ellipsoid
    ``FitResult.joint_distance2 <= chi2(6).ppf(0.95)``) for >= 18 of 20 seeds. The box of the six
    marginal intervals is reported but not held to 95 %: with independent estimates it holds
    the truth 0.95^6 = 74 % of the time. No bias: over the 20 seeds each key's mean z-score
    (error over its standard error) lies within 3 / sqrt(20) of 0, and the mean squared
    distance within 3 standard deviations of chi2(6)'s mean 6 (sd sqrt(12 / 20)).
    Measured (2026-11-24): per key 20/18/18/18/18/19, box 13, ellipsoid 19, mean z -0.27..0.19,
    mean distance 6.44."""
    from scipy.stats import chi2

    ax = _axis(base, transport_samples=1)
    keys = list(_truth(base, ax))
    inside = {k: 0 for k in keys}
    box = ellipsoid = 0
    zs, d2s = [], []
    limit = chi2(len(keys)).ppf(0.95)
    for seed in range(20):
        res, truth = _fit(base, ax, seed)
        assert res.solver["command_delay"]["shift_samples"] == 1, seed
        assert abs(res.parameters[BW]["value"] / ax.bandwidth_hz - 1) < 0.10, seed
        ins = {k: res.parameters[k]["ci95"][0] <= v <= res.parameters[k]["ci95"][1] for k, v in truth.items()}
        for k in keys:
            inside[k] += ins[k]
        box += all(ins.values())
        d2 = res.joint_distance2(truth)
        ellipsoid += d2 <= limit
        zs.append([_z(res, truth)[k] for k in keys])
        d2s.append(d2)
    mean_z = {k: round(float(m), 3) for k, m in zip(keys, np.mean(zs, axis=0))}
    print(f"per key {inside}; joint box {box}/20; joint ellipsoid {ellipsoid}/20; mean z {mean_z}; "
          f"mean distance^2 {np.mean(d2s):.3f}")
    assert all(c >= 18 for c in inside.values()), inside
    assert ellipsoid >= 18, (ellipsoid, d2s)
    assert all(abs(m) < 3 / math.sqrt(20) for m in mean_z.values()), mean_z
    assert abs(np.mean(d2s) - len(keys)) < 3 * math.sqrt(2 * len(keys) / 20), d2s


def test_cli_writes_the_found_delay(base, tmp_path, capsys):
    """prsa-fit on a foreign log: the found delay is in the plant file prsa-tune loads, the
    convention flag moves it by one sample, a bad convention is one line and exit 2."""
    import tomllib

    from prsa_ctrl.cli.fit import main

    ax = _axis(base, transport_samples=1, bandwidth_hz=900.0)
    n = 2000
    sp, ld = fg.multisine(n, ax.sample_time_s, seed=8)
    log = fg.simulate(ax, sp, ld, seed=8, convention="computed")
    csv = tmp_path / "log.csv"
    np.savetxt(csv, np.column_stack([log.time_s, log.command_n_m, log.angle_rad, log.load_n]), delimiter=",",
               header="time_s,torque_command_n_m,nut_angle_rad,axial_load_n", comments="", fmt="%.17g")
    out = tmp_path / "fit.toml"
    assert main([str(csv), "--out", str(out), "--command-logged", "computed"]) == 0
    text = capsys.readouterr().out
    assert "command delay: 2 sample(s)" in text
    assert "drive.command_delay_samples = 1" in text
    doc = tomllib.loads(out.read_text())
    assert doc["drive"]["command_delay_samples"]["value"] == 1
    fitted = load_plant(out)
    assert fitted.command_delay_samples == 1
    assert abs(fitted.values[BW] / 900.0 - 1) < 0.10
    bad = tmp_path / "bad.toml"
    assert main([str(csv), "--out", str(bad), "--command-logged", "sometimes"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "--command-logged" in err
    assert not bad.exists()


def test_the_found_shift_is_refitted_once_from_the_search_values_on_the_base(plant):
    # The refit at the found shift starts from the search's values of the keys it identified,
    # with the base plant as its base (a key the data do not inform keeps the base's value, not
    # the search's) and the search's states; it is not done a second time when a key ends up not
    # identified. A refit that fails from there is done again from the base plant, cold.
    from prsa_ctrl.identification.delay import refit_found

    search = _result(plant.with_params({"nut.inertia_kg_m2": 1e-3, BW: 700.0}), 5.0, 700.0)
    search.solver["delay_search"] = {"objective": {"1": 5.0}}
    search.parameters[BW]["kept_base"] = True  # the search did not identify the bandwidth
    calls = []

    def fit_at(shift, start, base=None, warm=False):
        calls.append((shift, start, base, warm))
        if fail and len(calls) == 1:
            raise FitError("stalled")
        out = _result(start if base is None else base, 4.0, 900.0)
        out.parameters[BW]["kept_base"] = True
        return out

    fail = False
    out = refit_found(fit_at, search, 1, plant)
    assert len(calls) == 1
    shift, start, base, warm = calls[0]
    assert shift == 1
    assert base is plant
    assert warm is True
    assert start.values["nut.inertia_kg_m2"] == 1e-3  # the search's identified value
    assert start.values[BW] == plant.values[BW]  # not the search's unidentified one
    assert out.solver["delay_search"]["objective"] == {"1": 5.0}
    calls.clear()
    fail = True
    out = refit_found(fit_at, search, 1, plant)
    assert [(s, st is plant, b, w) for s, st, b, w in calls] == [(1, False, plant, True), (1, True, None, False)]
    assert out.solver["objective"] == 4.0


def test_a_retry_start_is_never_written_as_the_base_value(plant, tmp_path, capsys, monkeypatch):
    """A search start other than the base plant (here the retry at half the base current loop,
    after the first start is made to fail) gives only the start of the fitted keys: the current
    loop, which this slow multisine (5..30 Hz) does not inform beside the friction the fit holds
    at the base's values (the truth's differ), is written and reported at the user's base value
    with its source, never at the retry's 500 Hz (it was, and the validation then failed on the
    plant with a 500 Hz loop)."""
    import json
    import tomllib

    import prsa_ctrl.identification.timedomain as td
    from prsa_ctrl.cli.fit import main
    from prsa_ctrl.drive.pid import PID
    from prsa_ctrl.identification.data import design_excitation
    from prsa_ctrl.plant.plantfile import plant_file_path
    from prsa_ctrl.sim.engine import run

    truth = plant.with_params({"nut.inertia_kg_m2": 1.5e-4, "friction.efficiency": 0.88,
                               "friction.no_load_torque_n_m": 0.03, "friction.viscous_n_m_s_per_rad": 1.5e-4,
                               BW: 1200.0})
    t, v = design_excitation("multisine", duration_s=0.3, sample_time_s=2.5e-3, f_min_hz=5, f_max_hz=30,
                             amplitude=20, offset=30, seed=0)
    r = run(truth, setpoint=list(zip(t.tolist(), v.tolist())), load=800.0, duration=0.3, controller=PID(0.05, 2.0),
            fidelity="rigid", discrete=True)
    q = 2 * math.pi / truth.encoder_counts
    theta = r.states[r.state_labels.index("theta_nut")]
    angle = np.floor((theta + 1e-5 * np.random.default_rng(0).standard_normal(theta.shape)) / q) * q
    csv = tmp_path / "slow.csv"
    record_from_arrays("slow", r.time, r.output("torque_command"), nut_angle_rad=angle,
                       axial_load_n=r.inputs[1]).to_csv(csv)
    fit_records, starts = td._fit_records, []

    def first_start_fails(records, start, **kw):
        starts.append(start.values[BW])
        if len(starts) == 1:
            raise FitError("fit did not converge (the test's failure of the first start)")
        return fit_records(records, start, **kw)

    monkeypatch.setattr(td, "_fit_records", first_start_fails)
    out, rep = tmp_path / "o.toml", tmp_path / "o.json"
    # --segment 0.02: the search's own fit is the result (no refit on longer segments)
    code = main([str(csv), "--out", str(out), "--json", str(rep), "--fit", f"nut.inertia_kg_m2,{BW}",
                 "--segment", "0.02", "--force"])
    cap = capsys.readouterr()
    assert code in (0, 3), cap.err
    assert starts[:2] == [plant.values[BW], 0.5 * plant.values[BW]]  # the forced failure, then the retry
    report = json.loads(rep.read_text())
    assert report["solver"]["command_delay"]["search"]["starts"]["0"] == 2
    assert report["parameters"][BW]["kept_base"]
    assert report["parameters"][BW]["written"] == plant.values[BW]
    doc = tomllib.loads(out.read_text())
    base_doc = tomllib.loads(plant_file_path().read_text())
    assert doc["drive"]["current_loop_bandwidth_hz"] == base_doc["drive"]["current_loop_bandwidth_hz"]
    (line,) = [ln for ln in cap.out.splitlines() if ln.strip().startswith(f"{BW} = ")]
    assert f"the plant keeps the base value {plant.values[BW]:.6g} Hz" in line
    assert f"{0.5 * plant.values[BW]:.6g}" not in line
    assert f"kept at the base value {0.5 * plant.values[BW]:.6g}" not in cap.out + cap.err
    assert f"converged from start 2 (the base plant with the current loop at {0.5 * plant.values[BW]:.6g} Hz)" in cap.out


def test_the_refit_at_the_found_shift_keeps_the_searchs_retry_warning(plant):
    """A shift whose search fit converged only from another start says so in the final report,
    after the refit on the asked segments (the warning was dropped there)."""
    from prsa_ctrl.identification.delay import refit_found

    search = _result(plant, 5.0, 700.0)
    search.solver["delay_search"] = {"objective": {"0": 5.0}}
    search.warnings.extend(["the fit at shift 0 converged from start 2 (the base plant with the current loop at 500 Hz)",
                            "a note of the search's own short segments"])

    def fit_at(shift, start, base=None, warm=False):
        return _result(start if base is None else base, 4.0, 900.0)

    out = refit_found(fit_at, search, 0, plant)
    assert any("converged from start 2" in w for w in out.warnings)
    assert not any("short segments" in w for w in out.warnings)


def _delay_line(res) -> str:
    from prsa_ctrl.identification.calibrate import result_lines

    return next(ln for ln in result_lines(res, {}) if ln.startswith("command delay:"))


def test_a_delay_decided_by_a_model_its_validation_rejects_is_reported_undecided(base):
    """Issue 32, point 4: a report that tells the truth. On the independent generator's logs (seed
    3, true shift 1) fitted with the inertia held 30 % off (a model the data reject), the search's
    objectives single out a shift -- that model's preference, not the data's delay. The delay is
    then reported undecided, in the result's dict and in the text report, with the search's
    objective per delay still shown; the validation's diagnosis is named."""
    from prsa_ctrl.identification.delay import DELAY_STATUSES, delay_status_head

    ax = _axis(base, transport_samples=1)
    truth = _truth(base, ax)
    recs = _records(fg.logs(ax, 3, duration_s=0.5))
    held = "nut.inertia_kg_m2"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        wrong = base.with_params({held: 1.3 * truth[held]}, name=base.name)
    res = fit_plant(recs, wrong, keys=tuple(k for k in truth if k != held), delay_samples="find")
    v = res.solver["validation"]
    assert v["passes"] is False
    cd = res.as_dict()["solver"]["command_delay"]
    assert delay_status_head(cd["status"]) == "undecided"
    assert "cannot be told apart with a model the data reject" in cd["status"]
    assert v["diagnosis"] in cd["status"]
    assert cd["search"]["status"] == cd["status"]
    assert cd["search"]["decided"] is False
    assert cd["search"]["preferred_by_rejected_model"] == cd["shift_samples"]
    fitted = {k: x for k, x in cd["search"]["objective"].items() if x is not None}
    assert len(fitted) >= 2  # the per-delay table is kept
    line = _delay_line(res)
    assert line.startswith("command delay: undecided, fitted at")
    assert "cannot be told apart with a model the data reject" in line
    assert all(f"{k}: {x:.6g}" in line for k, x in fitted.items())
    assert not any(w.startswith("the command delay is decided by") for w in res.warnings)
    assert any(w.startswith("the command delay is not decided") for w in res.warnings)
    assert set(DELAY_STATUSES) == {"decided", "undecided", "given", "base plant's"}


def test_a_delay_decided_by_a_model_the_data_accept_stays_decided(base):
    """The same generator and search with every key fitted (the model explains the logs): the true
    delay, status "decided" in the dict and the text report."""
    ax, res, _ = one_seed_fit(base)
    assert res.solver["validation"]["passes"] is True
    cd = res.as_dict()["solver"]["command_delay"]
    assert cd["status"] == "decided"
    assert cd["search"]["status"] == "decided"
    assert cd["shift_samples"] == 1
    assert "preferred_by_rejected_model" not in cd["search"]
    line = _delay_line(res)
    assert line.startswith("command delay: 1 sample(s)")
    assert "(found by the delay search, decided; objective per delay" in line


def test_the_delay_status_vocabulary():
    from prsa_ctrl.identification.delay import delay_status_head

    assert delay_status_head("decided") == "decided"
    assert delay_status_head("undecided: shift 2 fits within a factor 1.5 of the best, 1") == "undecided"
    assert delay_status_head("given") == "given"
    for bad in ("decidedly", "maybe: 1", "Decided"):
        with pytest.raises(ValueError, match="delay status"):
            delay_status_head(bad)


@pytest.mark.slow
def test_the_two_mass_roller_screw_logs_leave_the_delay_undecided(tmp_path, capsys):
    """The second generator's roller screw (tests/identification/foreign/gen_rollerscrew.py: two
    masses, a 152 Hz axial mode, two delays, true shift 2): the rigid model's search preferred a
    shift (1 on main a8f75f1, reported "decided"), the validation rejects that model for the
    second mass, so prsa-fit reports the delay undecided with the objective per delay, exit 3
    and no file (39 s of CPU)."""
    import json

    from foreign import gen_rollerscrew as rs
    from prsa_ctrl.cli.fit import main

    s = rs.generate(tmp_path / "data", seed=0)
    out, js = tmp_path / "fitted.toml", tmp_path / "report.json"
    args = [*(str(s["logs"][n]) for n in ("multisine", "loadsteps", "staircase")), "--log-format", str(s["log_format"]),
            "--plant", str(s["base"]), "--out", str(out), "--json", str(js)]
    assert main(args) == 3
    assert not out.exists()
    text = capsys.readouterr().out
    rep = json.loads(js.read_text())
    cd = rep["solver"]["command_delay"]
    assert cd["status"].startswith("undecided: the delays ")
    assert "cannot be told apart with a model the data reject: second mass" in cd["status"]
    assert cd["search"]["decided"] is False
    assert sum(v is not None for v in cd["search"]["objective"].values()) >= 2
    assert "command delay: undecided, fitted at" in text


def test_a_written_undecided_delay_says_so_in_its_source(plant):
    """--force writes a plant whose delay the search left undecided: its source says so, as the
    report's status does (was: 'fit: found by the delay search, 0 sample(s) ...', as if decided;
    only a delay made undecided by the validation's rejection said it)."""
    from prsa_ctrl.identification.delay import delay_status_head, with_command_delay

    key = "drive.command_delay_samples"
    for ratio, head in ((0.99, "undecided"), (1.01, "decided")):
        fit_at = _fake(plant, {0: 1.0, 1: ratio * DELAY_OBJECTIVE_RATIO, 2: 40.0, 3: 90.0, 4: 95.0})
        shift, res = search_delay(fit_at, plant, KEYS, 2.5e-4, 4)
        out = with_command_delay(res, shift, "applied", "found by the delay search")
        assert delay_status_head(out.solver["command_delay"]["status"]) == head
        assert ("undecided" in out.plant.sources[key]) is (head == "undecided"), out.plant.sources[key]


def _searched(plant, shift=1, refit_failed=None):
    """A fit whose delay search decided ``shift`` (the record as with_command_delay makes it)."""
    from prsa_ctrl.identification.delay import with_command_delay

    search = {"objective": {"0": 9.0, "1": 1.0, "2": 8.0}, "decided": True, "status": "decided", "range": [0, 2],
              "ratio_tolerance": DELAY_OBJECTIVE_RATIO}
    if refit_failed:
        search["refit_failed"] = refit_failed
    res = FitResult(plant, {}, {"value": 1.0, "ci95": [1.0, 1.0], "unit": "kg m^2"}, np.eye(0), (), {},
                    ["the command delay is decided by the paired segment test: shift 0 against 1: ..."],
                    {"delay_search": search}, {}, None, {}, None)
    return with_command_delay(res, shift, "applied", "found by the delay search")


@pytest.fixture(scope="module")
def explained_pair(plant):
    """Two logs of one plant (the independent generator's) that the plant explains, and the plant."""
    import dataclasses

    from independent_actuator import multisine_load_step_record

    truth = plant.with_params({"nut.inertia_kg_m2": 1.5e-4, "friction.efficiency": 0.88,
                               "friction.no_load_torque_n_m": 0.03, "friction.viscous_n_m_s_per_rad": 1.5e-4,
                               BW: 1200.0, "drive.command_delay_samples": 1})
    rec = multisine_load_step_record(truth, 2.5e-4)
    return truth, [rec, dataclasses.replace(rec, name="again")]


def test_a_delay_whose_validation_a_failed_fit_stopped_is_undecided(explained_pair):
    """Issue 32 ("a report that is true"): the plant at the decided delay explains both logs, but
    the cross-validation refit at that delay fails from every start, so the validation cannot run
    ("fit failure, not missing physics"). The delay was decided with a model nothing validated:
    its status is now undecided, naming the failed fit (it stayed "decided" beside that refusal)."""
    from prsa_ctrl.errors import FitError
    from prsa_ctrl.identification.delay import delay_status_head
    from prsa_ctrl.identification.validation import FIT_FAILURE, validate_fit

    truth, recs = explained_pair

    def never(recs_, start, attempt=0):
        raise FitError("fit did not converge: Gauss-Newton status 'stalled' after 19 iterations")

    out = validate_fit(_searched(truth), recs, [], 1, "rigid", never, base=truth)
    v = out.solver["validation"]
    assert v["diagnosis"].startswith(FIT_FAILURE)
    assert all(e["explained"] for e in v["written_plant"].values())
    cd = out.as_dict()["solver"]["command_delay"]
    assert delay_status_head(cd["status"]) == "undecided"
    assert cd["status"].startswith(f"undecided: the fit at it failed ({FIT_FAILURE}")
    assert cd["search"]["decided"] is False
    assert cd["search"]["status"] == cd["status"]
    assert cd["search"]["preferred_by_unvalidated_model"] == 1
    assert "preferred_by_rejected_model" not in cd["search"]
    assert "could not be validated" in out.plant.sources["drive.command_delay_samples"]
    assert not any(w.startswith("the command delay is decided by") for w in out.warnings)
    assert any(w.startswith("the command delay is not decided") and "could not be validated" in w for w in out.warnings)
    assert _delay_line(out).startswith("command delay: undecided, fitted at 1 sample(s)")


def test_a_delay_whose_validation_passes_stays_decided(explained_pair):
    # the same logs and plant with a cross-validation refit that converges: decided, as before
    from prsa_ctrl.identification.validation import validate_fit

    truth, recs = explained_pair

    def refit(recs_, start, attempt=0):
        return _with_plant(_searched(truth), truth)

    out = validate_fit(_searched(truth), recs, [], 1, "rigid", refit, base=truth)
    assert out.solver["validation"]["passes"] is True
    assert out.solver["command_delay"]["status"] == "decided"


def _with_plant(res, plant):
    import dataclasses

    return dataclasses.replace(res, plant=plant)


def test_a_failed_refit_at_the_found_shift_is_named_in_the_delay_record(plant, explained_pair):
    """delay.refit_found: the refit on the asked segments fails from both starts, the search's
    converged values at the shift are kept. The delay record says so ("refit_failed", and the
    text line); the validation then judges those values: a plant it cannot validate (the
    cross-validation refit fails too) leaves the delay undecided, one it passes keeps it decided."""
    from prsa_ctrl.errors import FitError
    from prsa_ctrl.identification.delay import delay_status_head, refit_found, with_command_delay
    from prsa_ctrl.identification.validation import validate_fit

    truth, recs = explained_pair
    search = _result(truth, 5.0, 1200.0)
    search.solver["delay_search"] = {"objective": {"0": 9.0, "1": 5.0}, "decided": True, "status": "decided",
                                     "range": [0, 1], "ratio_tolerance": DELAY_OBJECTIVE_RATIO}

    def fails(shift, start, base=None, warm=False):
        raise FitError("the fit stopped at its candidate's work bound")

    kept = refit_found(fails, search, 1, truth)
    assert kept.solver["objective"] == 5.0  # the search's own fit
    assert "work bound" in kept.solver["delay_search"]["refit_failed"]
    res = with_command_delay(kept, 1, "applied", "found by the delay search")
    cd = res.as_dict()["solver"]["command_delay"]
    assert cd["status"] == "decided"
    assert "work bound" in cd["search"]["refit_failed"]
    assert "the refit at it on the asked segments failed" in _delay_line(res)

    def never(recs_, start, attempt=0):
        raise FitError("fit did not converge")

    unvalidated = validate_fit(res, recs, [], 1, "rigid", never, base=truth)
    assert delay_status_head(unvalidated.solver["command_delay"]["status"]) == "undecided"
    validated = validate_fit(res, recs, [], 1, "rigid", lambda r, s, a=0: _with_plant(res, truth), base=truth)
    assert validated.solver["validation"]["passes"] is True
    assert validated.solver["command_delay"]["status"] == "decided"


def test_an_frf_delay_is_decided_only_when_its_interval_stays_within_half_a_sample(plant):
    """delay.frf_delay_record: the whole samples written (beyond the convention's offset) are
    decided when both ends of the continuous delay's 95 % interval lie within half a sample of them;
    an interval reaching past, or a delay held at its bound (no interval), leaves it undecided."""
    from prsa_ctrl.identification.delay import delay_status_head, frf_delay_record

    ts = 2.5e-4
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        one = plant.with_params({"drive.command_delay_samples": 1})
    inside = frf_delay_record({"value": 2.0 * ts, "ci95": [1.52 * ts, 2.48 * ts]}, one, ts, "computed")
    assert inside["status"] == "decided"
    assert inside["shift_samples"] == 2
    assert inside["continuous"]["ci95_samples"] == pytest.approx([1.52, 2.48])
    past = frf_delay_record({"value": 2.0 * ts, "ci95": [1.52 * ts, 2.52 * ts]}, one, ts, "computed")
    assert delay_status_head(past["status"]) == "undecided"
    assert "nearest 1..2" in past["status"]
    held = frf_delay_record({"value": 0.0, "ci95": None, "at_bound": "lower", "note": "at its bound"}, one, ts, "applied")
    assert held["status"].startswith("undecided: the fit holds the delay at its lower bound, 0 s")
    assert held["continuous"]["ci95_s"] is None
    loop = frf_delay_record({"value": 2.0 * ts, "ci95": [1.9 * ts, 2.1 * ts]}, one, ts, "computed", loop_held=True)
    assert "the current loop held, not fitted" in loop["how"]


@pytest.mark.parametrize("ci", [[-math.inf, math.inf], [math.nan, math.nan], [2.0e-4, math.inf]])
def test_an_frf_delay_with_an_unbounded_interval_is_undecided_not_a_crash(plant, ci):
    """A continuous delay whose covariance gives no finite interval (finish_fit's width can be
    non-finite): frf_delay_record took int(floor(inf)) and raised; it is now undecided, with no
    interval in the record, and the record is valid JSON without NaN (the report's writer
    refuses NaN and inf)."""
    import json

    from prsa_ctrl.identification.delay import delay_status_head, frf_delay_record

    ts = 2.5e-4
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        one = plant.with_params({"drive.command_delay_samples": 1})
    rec = frf_delay_record({"value": 2.4e-4, "ci95": ci}, one, ts, "applied")
    assert delay_status_head(rec["status"]) == "undecided"
    assert rec["continuous"]["ci95_s"] is None
    assert json.loads(json.dumps(rec, allow_nan=False))["shift_samples"] == 1


def test_an_frf_delays_undecided_interval_is_stated_in_the_frame_of_its_counts(plant):
    """The undecided status names the interval beyond the logging convention's offset, the frame
    of the whole counts it names: a computed command (offset 1) fitted at 1.52..2.52 samples in all
    is 0.52..1.52 beyond it, nearest 1..2 (it printed 1.52..2.52 "beyond the 1" beside "nearest
    1..2"). An interval below the convention's offset (0.35..0.45 samples in all, a command logged
    as computed: written as no delay) says so; it read "holds delays nearest 0, not within half a
    sample of the 0 written"."""
    from prsa_ctrl.identification.delay import delay_status_head, frf_delay_record

    ts = 2.5e-4
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        one = plant.with_params({"drive.command_delay_samples": 1})
        none = plant.with_params({"drive.command_delay_samples": 0})
    past = frf_delay_record({"value": 2.0 * ts, "ci95": [1.52 * ts, 2.52 * ts]}, one, ts, "computed")
    assert "interval 0.52..1.52 samples (beyond the 1 of a command logged as computed)" in past["status"]
    below = frf_delay_record({"value": 0.4 * ts, "ci95": [0.35 * ts, 0.45 * ts]}, none, ts, "computed")
    assert delay_status_head(below["status"]) == "undecided"
    assert "nearest" not in below["status"]
    assert "below the 1 sample(s) a command logged as computed implies" in below["status"]
