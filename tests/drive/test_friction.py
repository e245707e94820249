"""Friction feed-forward (issue 24, item 4): the plant file's friction curve fed forward from the
profile's speed in the drive's sampled law.

* The curve equals the plant's own sliding friction at the reference speed: against a formula
  written here from the plant file's keys and against the rigid model's steady holding torque
  (prsa_ctrl.plant.equilibrium.steady_torque minus the load torque).
* The simulator applies it: the sampled law's reported torque feed-forward is
  ``kaff J a_ref/a + tau_f(v_ref/a)`` at every sample, computed here from the profile.
* It reduces the following error where friction dominates (paper-slow-reversal: 1 mm out and
  back at 2 mm/s under 1500 N) on the nonlinear (compliant) simulator, RMS and peak.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from prsa_ctrl import PID, load_plant
from prsa_ctrl.drive.friction import FrictionFeedforward
from prsa_ctrl.drive.measurement import PositionLoop
from prsa_ctrl.plant.equilibrium import steady_torque
from prsa_ctrl.sim.engine import run
from prsa_ctrl.studies.move import friction_feedforward_effect, following_error_m, simulate_move
from prsa_ctrl.studies.movescene import load_move_scene
from prsa_ctrl.tuning.cascade import CascadeDesign

ROOT = Path(__file__).resolve().parents[2]
DESIGN = CascadeDesign("joint", PID(0.0771, 7.07), PositionLoop(kv=102.7, kvff=1.0, kaff=1.0), {}, {}, {}, 0.0)


@pytest.fixture(scope="module")
def plant():
    with pytest.warns(Warning):  # the paper plant's geometry note
        return load_plant()


def _paper_friction(plant, w, load):
    """Sliding thread friction of the paper plant from its file keys (independent of the code):
    the slip arm k follows from the forward efficiency eta = F a / (F a + k mu_d F (f_N + f_S)),
    the Stribeck coefficient is mu_d + (mu_s - mu_d) exp(-(a w / v_s)^2)."""
    v = plant.values
    a = v["screw.lead_mm"] * 1e-3 / (2 * math.pi) if "screw.lead_mm" in v else plant.lead_per_rad
    f_sum = sum(plant.normal_force_factor())
    eta, mu_s, mu_d = v["friction.efficiency"], v["friction.static"], v["friction.dynamic"]
    k = a * (1 / eta - 1) / (mu_d * f_sum)
    mu = mu_d + (mu_s - mu_d) * math.exp(-((a * w / v["friction.stribeck_velocity_m_s"]) ** 2))
    return math.copysign(k * mu * abs(load) * f_sum + v["friction.no_load_torque_n_m"], w) \
        + v["friction.viscous_n_m_s_per_rad"] * w


@pytest.mark.parametrize("load", [0.0, 500.0, 1500.0, -2000.0])
def test_equals_the_plant_friction_at_the_reference_speed(plant, load):
    ff = FrictionFeedforward.from_plant(plant, load)
    for w in (-94.2, -6.28, -0.5, -0.05, 0.05, 0.5, 6.28, 94.2):
        hand = _paper_friction(plant, w, load)
        model = steady_torque(plant, w, load) - load * plant.lead_per_rad
        assert float(ff.torque(w)) == pytest.approx(hand, rel=1e-12, abs=1e-15), (load, w)
        assert float(ff.torque(w)) == pytest.approx(model, rel=1e-9, abs=1e-12), (load, w)
    assert float(ff.torque(0.0)) == 0.0


def test_linear_axis_coulomb_and_viscous_per_direction():
    p = load_plant(ROOT / "examples" / "emps" / "plant.toml")
    v = p.values
    ff = FrictionFeedforward.from_plant(p)
    for w in (0.01, 0.2):
        assert float(ff.torque(w)) == pytest.approx(v["friction.coulomb_positive_n"]
                                                    + v["friction.viscous_positive_n_s_per_m"] * w, rel=1e-12)
        assert float(ff.torque(-w)) == pytest.approx(-v["friction.coulomb_negative_n"]
                                                     - v["friction.viscous_negative_n_s_per_m"] * w, rel=1e-12)
        assert float(ff.torque(w)) == pytest.approx(steady_torque(p, w, 0.0), rel=1e-9)
        assert float(ff.torque(-w)) == pytest.approx(steady_torque(p, -w, 0.0), rel=1e-9)


def test_asymmetric_curve_and_gain():
    ff = FrictionFeedforward(0.1, 0.3, 0.05, 0.07, 2.0, 0.01, 0.02, gain=0.5)
    w = np.array([-4.0, -2.0, 0.0, 2.0, 4.0])
    hand = [0.5 * -(0.3 + 0.07 * math.exp(-4.0) + 0.02 * 4.0), 0.5 * -(0.3 + 0.07 * math.exp(-1.0) + 0.02 * 2.0),
            0.0, 0.5 * (0.1 + 0.05 * math.exp(-1.0) + 0.01 * 2.0), 0.5 * (0.1 + 0.05 * math.exp(-4.0) + 0.01 * 4.0)]
    np.testing.assert_allclose(ff.torque(w), hand, rtol=1e-15)
    d = ff.as_dict(4.0, points=5)
    np.testing.assert_allclose([row[1] for row in d["table_speed_rad_s_torque_n_m"]], hand, rtol=1e-15)
    assert "exp(-(w/w_s)^2)" in d["formula"]


@pytest.mark.parametrize("kwargs, match", [
    ({"coulomb_positive_n_m": -0.1}, "coulomb_positive_n_m = -0.1; expected a finite number >= 0"),
    ({"stribeck_speed_rad_s": 0.0}, "stribeck_speed_rad_s = 0.0; expected a finite number > 0"),
    ({"gain": 3.0}, "gain = 3.0; expected a finite number in \\[0, 2\\]"),
    ({"viscous_negative_n_m_s_per_rad": float("nan")}, "viscous_negative_n_m_s_per_rad = nan"),
])
def test_bad_curve_one_line(kwargs, match):
    base = {"coulomb_positive_n_m": 0.1, "coulomb_negative_n_m": 0.1}
    with pytest.raises(ValueError, match=match):
        FrictionFeedforward(**{**base, **kwargs})
    with pytest.raises(ValueError, match="PositionLoop friction = 'x'; expected a FrictionFeedforward"):
        PositionLoop(kv=100.0, friction="x")
    with pytest.raises(ValueError, match="load_n = nan"):
        FrictionFeedforward.from_plant(load_plant(ROOT / "examples" / "emps" / "plant.toml"), float("nan"))


def test_the_sampled_law_adds_it_from_the_reference_speed(plant):
    """Reported torque feed-forward = kaff J a_ref/a + tau_f(v_ref/a), sample by sample."""
    sc = load_move_scene("paper-slow-reversal")
    ff = FrictionFeedforward.from_plant(plant, 1500.0)
    pos = replace(DESIGN.position, friction=ff)
    r = run(plant, load=1500.0, duration=0.08, controller=DESIGN.speed, fidelity="rigid", discrete=True,
            position=pos, motion=sc.motion())
    _, v_ref, a_ref = sc.motion().at(r.time)
    a, j = plant.lead_per_rad, plant.reflected_inertia_kg_m2
    expected = a_ref * j / a + np.array([_paper_friction(plant, w, 1500.0) if w != 0 else 0.0 for w in v_ref / a])
    assert np.count_nonzero(v_ref) > 100
    np.testing.assert_allclose(r.output("torque_feedforward"), expected, rtol=1e-12, atol=1e-15)


def test_it_reduces_the_following_error_where_friction_dominates(plant):
    """paper-slow-reversal on the compliant model: measured RMS 0.507 -> 0.082 um and peak
    3.77 -> 0.60 um with the full curve; asserted: both at least halved."""
    sc = load_move_scene("paper-slow-reversal")
    eff = friction_feedforward_effect(DESIGN, plant, sc)
    off, on = eff["without"], eff["with"]
    assert on["rms_following_error_m"] < 0.5 * off["rms_following_error_m"]
    assert on["peak_following_error_m"] < 0.5 * off["peak_following_error_m"]
    assert eff["rms_ratio"] == pytest.approx(on["rms_following_error_m"] / off["rms_following_error_m"], rel=1e-15)
    # the metrics are the run's own: recompute the RMS over the move from the run
    r = eff["design"].run
    m = sc.motion()
    sel = (r.time >= m.t0[0]) & (r.time <= m.end_time)
    e = following_error_m(r, plant)[sel]
    assert math.sqrt(float(np.mean(e**2))) == pytest.approx(on["rms_following_error_m"], rel=1e-9)
    assert eff["design"].position.friction is not None
    assert DESIGN.position.friction is None


def test_half_the_curve_is_between(plant):
    """A monotone check of cause and effect: feeding half the curve forward lands between none
    and the full curve (RMS)."""
    sc = load_move_scene("paper-slow-reversal")
    full = friction_feedforward_effect(DESIGN, plant, sc)
    half = friction_feedforward_effect(DESIGN, plant, sc, gain=0.5)
    assert full["with"]["rms_following_error_m"] < half["with"]["rms_following_error_m"] \
        < half["without"]["rms_following_error_m"]


def test_scene_reversal_key():
    sc = load_move_scene("paper-slow-reversal")
    m = sc.motion()
    t = np.linspace(m.t0[0], m.end_time, 2001)
    p, v, _ = m.at(t)
    assert abs(m.final_position) < 1e-15
    assert max(p) == pytest.approx(1e-3, rel=1e-12)
    assert v.min() == pytest.approx(-2e-3, rel=1e-12)
    assert v.max() == pytest.approx(2e-3, rel=1e-12)
    assert sc.loads() == [(0.0, 1500.0)]


def test_simulate_move_without_friction_is_unchanged(plant):
    """The field defaults to None: a position loop without it gives the run it gave before
    (same compiled law key as a loop built without the argument)."""
    sc = load_move_scene("paper-move")
    r = simulate_move(plant, sc, DESIGN.speed, DESIGN.position, duration=0.02, loads=[(0.0, 0.0)])
    r2 = simulate_move(plant, sc, DESIGN.speed, replace(DESIGN.position, friction=None), duration=0.02,
                       loads=[(0.0, 0.0)])
    np.testing.assert_array_equal(r.output("torque_command"), r2.output("torque_command"))


def test_overshoot_of_an_out_and_back_move_is_measured_on_the_way_back(plant):
    """The last move of paper-slow-reversal goes back (negative): overshoot is travel below the
    start, i.e. a positive error reference - measured after the profile ends."""
    from prsa_ctrl.studies.move import move_metrics

    sc = load_move_scene("paper-slow-reversal")
    r = simulate_move(plant, sc, DESIGN.speed, DESIGN.position)
    e = following_error_m(r, plant)
    after = r.time >= sc.motion().end_time
    assert move_metrics(r, plant, sc).overshoot_m == pytest.approx(max(0.0, float(np.max(e[after]))), rel=1e-15)
