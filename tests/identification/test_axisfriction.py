"""The linear axis's friction-law test (prsa_ctrl.identification.axisfriction) on force balances
written here by hand: a slow sinusoidal motion ``x = A (1 - cos w t)`` (every speed from standstill
to 126 mm/s, both directions), the drive force ``M a + F_f(v, x)`` logged as the command; the test
against the law that made it finds nothing, against a law that lacks a term it finds that term
where it is. The closed-loop cases (prsa-fit exits 3 naming it) are in test_axisvalidation.py.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from prsa_ctrl.identification.axisfriction import (FRICTION_DEPARTURE, applied_force, friction_departure,
                                                   friction_diagnosis, friction_words)
from prsa_ctrl.identification.logformat import AxisLog, ControllerSpec

H, GAIN, A, W = 1e-3, 30.0, 0.1, 2 * math.pi * 0.2
THETA = (80.0, 150.0, 220.0, 15.0, 25.0)  # M kg, Fv+ Fv- N s/m, Fc+ Fc- N


def _log(stribeck=(0.0, 1.0), slope=0.0, n=20000):
    t = np.arange(n) * H
    x = A * (1 - np.cos(W * t))
    v, a = A * W * np.sin(W * t), A * W * W * np.cos(W * t)
    m, fvp, fvn, fcp, fcn = THETA
    fs, vs = stribeck
    g = 1.0 + slope * (x / (2 * A) - 0.5)
    friction = np.where(v > 0, g * fcp + fvp * v, -g * fcn + fvn * v) + np.sign(v) * fs * np.exp(-(v / vs) ** 2)
    return AxisLog("hand", t, x, (m * a + friction) / GAIN, "V", GAIN, H)


def test_the_law_that_made_the_force_balance_departs_from_it_by_nothing():
    e = friction_departure(THETA, _log())
    assert e["friction_departure"] < 0.02, e["friction_departure"]
    assert friction_words(e) is None
    assert len(e["friction_speed_bins"]) == 12  # six speed bins in each direction, each with both halves
    assert len(e["friction_position_bins"]) == 6


def test_a_stribeck_rise_is_found_at_the_lowest_speeds_and_named():
    """10 N at 5 mm/s beside a Coulomb level of 20 N: the lowest bins (1.26..2.4 mm/s) hold
    10 exp(-(v/vs)^2), 8..9.5 N, in the direction of motion, in both directions."""
    e = friction_departure(THETA, _log(stribeck=(10.0, 0.005)))
    assert e["friction_by"] == "speed"
    low = [b for b in e["friction_speed_bins"] if abs(b["from"]) < 0.0015]
    assert len(low) == 2
    for b in low:
        assert 7.5 < b["excess_n"] < 10.0, b
    assert e["friction_departure"] >= FRICTION_DEPARTURE
    assert e["friction_departure"] == pytest.approx(e["friction_high"]["excess_n"] / 20.0, rel=1e-12)
    assert friction_diagnosis(e, "hand").startswith("Stribeck friction: in hand")


def test_a_coulomb_level_that_changes_along_the_travel_is_found_by_position():
    """Coulomb 0.4x..1.6x over the 0.2 m travel (the law's mean level): the position bins' excess
    runs from about -0.5 x 20 N to +0.5 x 20 N, and the diagnosis names the travel."""
    e = friction_departure(THETA, _log(slope=1.2))
    assert e["friction_by"] == "position"
    ex = [b["excess_n"] for b in e["friction_position_bins"]]
    assert ex == sorted(ex)  # more friction the further along the travel
    assert 0.6 < e["friction_departure"] < 1.2
    assert "changes along the travel" in friction_diagnosis(e, "hand")


def test_the_applied_force_moves_a_command_logged_as_computed_by_the_delay():
    """The controller's output acts two samples after it is logged; the test signal the drive adds
    acts in the sample it is logged in."""
    lg = _log(n=400)
    ctl = ControllerSpec("position-p/velocity-p", 150.0, 250.0, 0.0, "average2-difference", 10.0, H,
                         command_delay_samples=2)
    test = np.zeros(400)
    test[100] = 1.0
    delayed = AxisLog("hand", lg.time_s, lg.position_m, lg.command + test, "V", GAIN, H, reference_m=lg.position_m,
                      test_signal=test, controller=ctl)
    f = applied_force(delayed)  # the computed part two samples late, the test signal as the drive adds it
    assert f[10:] == pytest.approx(GAIN * (lg.command[8:-2] + test[10:]), abs=1e-9)


def test_a_wrong_coulomb_viscous_split_is_named_as_the_fit_not_as_missing_physics():
    """The force balance is Coulomb + viscous, the law tested has +x's Coulomb level 6 N low and its
    viscous term 70 N s/m high (as a fit that held a direction or ended at a bound): the departure
    is a straight line in the speed, which a Coulomb + viscous law explains, and is named so."""
    e = friction_departure((80.0, 220.0, 220.0, 9.0, 25.0), _log())
    assert e["friction_departure"] >= FRICTION_DEPARTURE
    line = friction_diagnosis(e, "hand")
    assert line.startswith("friction as fitted, not missing physics: in hand")
    assert "the fit ended away from it" in line  # the log moves both ways at every speed: nothing undetermined


def test_a_log_at_rest_says_nothing():
    """A log that holds its position (constant, or moving less than its encoder's quantum) shows no
    sliding friction: the test finds nothing (was: the filter's round-off speeds, 1e-11 mm/s, binned
    as motion and the holding force read as a 125 % departure, 'friction as fitted')."""
    n = 5000
    t = np.arange(n) * H
    hold = np.full(n, 5.0 / GAIN)  # a holding force of 5 N, inside the static friction
    for x, res in ((np.full(n, 0.1), None), (0.1 + 1e-9 * np.sin(t), 5e-8)):
        log = AxisLog("rest", t, x, hold, "V", GAIN, H, resolution_m=res)
        e = friction_departure(THETA, log)
        assert e["friction_departure"] == 0.0, e
        assert friction_words(e) is None


def test_a_nearly_frictionless_law_is_judged_against_the_force_balance_scatter():
    """An axis with almost no friction (an air bearing: Coulomb 0.01 N, viscous 0.5 N s/m), its law
    fitted right, 0.5 N rms of force noise: the bins' 0.1 N of chance excess is no departure (was:
    divided by the 0.01 N Coulomb level, 'departs by 1100 %'); a 20 N Stribeck rise the same law
    lacks still fails."""
    n = 20000
    t = np.arange(n) * H
    x = A * (1 - np.cos(W * t))
    v, a = A * W * np.sin(W * t), A * W * W * np.cos(W * t)
    theta = (80.0, 0.5, 0.5, 0.01, 0.01)
    noise = 0.5 * np.random.default_rng(0).standard_normal(n)
    for rise, fails in ((0.0, False), (20.0, True)):
        friction = np.sign(v) * (0.01 + rise * np.exp(-(v / 0.005) ** 2)) + 0.5 * v
        log = AxisLog("air", t, np.round(x / 5e-8) * 5e-8, (80.0 * a + friction + noise) / GAIN, "V", GAIN, H,
                      resolution_m=5e-8)
        e = friction_departure(theta, log)
        assert (e["friction_departure"] >= FRICTION_DEPARTURE) is fails, (rise, e["friction_departure"])


def _one_way_log(n=4000, speed=0.05, accel=0.5):
    """A single move in +x at ``speed`` m/s (ramps at ``accel`` m/s^2), then a rest: the force
    balance of THETA's law; the log never moves the axis in -x."""
    t = np.arange(n) * H
    ta = speed / accel
    v = np.clip(np.minimum(accel * t, accel * (3.0 - t)), 0.0, speed)  # up, cruise, down by 3 s
    x = np.cumsum(v) * H
    a = np.gradient(v, H)
    m, fvp, _, fcp, _ = THETA
    friction = np.where(v > 0, fcp + fvp * v, 0.0)
    assert ta < 0.2
    return AxisLog("oneway", t, x, (m * a + friction) / GAIN, "V", GAIN, H)


def test_a_law_the_log_cannot_determine_is_named_as_the_fit_with_the_remedy():
    """A log that runs one way at one speed (the two-mass fit's seed 14 of test_axiscompliant: +x at
    32..70 mm/s, -x barely), tested against a wrong split of the same friction at that speed
    (Coulomb 0, viscous 700 N s/m: 35 N at 50 mm/s against the force balance's 22.5 N): the
    deficit is the same at every position and at the one speed, which a Coulomb + viscous law
    explains. The diagnosis names the fit and why the log cannot determine it, and the remedy
    (was: "friction that changes along the travel" or "a friction that is not linear in the
    speed", physics the log does not show)."""
    e = friction_departure((80.0, 700.0, 700.0, 0.0, 0.0), _one_way_log())
    assert e["friction_departure"] >= FRICTION_DEPARTURE
    assert e["friction_position_beyond_law_n"] < 0.1 * FRICTION_DEPARTURE * e["friction_level_n"]
    line = friction_diagnosis(e, "oneway", ["friction.coulomb_positive_n ended at its bound (0)"])
    assert line.startswith("friction as fitted, not missing physics: in oneway")
    assert "along the travel" not in line
    assert "not linear in the speed" not in line
    assert "oneway barely moves the axis in -x" in line
    assert "in +x oneway runs at one speed only" in line
    assert "friction.coulomb_positive_n ended at its bound (0)" in line
    assert line.endswith("remedy: a log that moves the axis both ways, over a range of speeds")


def test_a_position_departure_a_refitted_law_leaves_is_still_the_travel():
    """The Coulomb level 0.4x..1.6x along the travel, tested against the right law: once a
    Coulomb + viscous law per direction is refitted to the force balance, the position bins still
    spread by about the departure (the speed does not explain the position)."""
    e = friction_departure(THETA, _log(slope=1.2))
    assert e["friction_position_beyond_law_n"] > FRICTION_DEPARTURE * e["friction_level_n"]
    assert friction_diagnosis(e, "hand", ["friction.coulomb_positive_n ended at its bound (0)"]).startswith(
        "friction that changes along the travel")
