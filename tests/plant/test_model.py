"""prsa_ctrl.plant.model: the multi-roller model and the Stribeck drag of the model."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from prsa_ctrl import PID, energy_balance, load_plant, simulate
from prsa_ctrl.drive.friction import FrictionFeedforward
from prsa_ctrl.errors import PlantFileError
from prsa_ctrl.plant import load_plant, steady_torque
from prsa_ctrl.plant.model import RollerErrors, drag_breakaway_excess, plant_model

PLANT = load_plant()
STEP = [(0.0, 500.0), (0.02, 1500.0)]


@pytest.fixture(scope="module")
def runs():
    pid = PID(0.085, 14.7)
    kw = dict(load=STEP, duration=0.08, controller=pid, dt=5e-5, energy=True)
    return simulate(PLANT, fidelity="multi-roller", seed=3, **kw), simulate(PLANT, fidelity="compliant", **kw)


def _y(r, name):
    return np.asarray(r.outputs[r.output_labels.index(name)])


def test_per_roller_forces_share_the_load_unevenly_and_sum_to_the_total(runs):
    mr, _ = runs
    late = mr.time > 0.06
    per = np.array([_y(mr, f"contact_force_nut_{i + 1}")[late] for i in range(PLANT.n_rollers)])
    total = _y(mr, "contact_force_nut")[late]
    np.testing.assert_allclose(per.sum(axis=0), total, rtol=1e-9)
    means = per.mean(axis=1)
    assert means.max() / means.mean() > 1.2  # position errors make load sharing non-uniform
    # Runout makes each loaded roller's force fluctuate once per spin while the total stays
    # steady; rollers whose position error exceeds the deflection carry nothing.
    loaded = means > 1.0
    assert loaded.sum() >= PLANT.n_rollers // 2
    assert np.ptp(per[loaded], axis=1).min() > 10 * np.ptp(total)


def test_identical_rollers_reduce_to_the_compliant_model():
    perfect = PLANT.with_params({"tolerance.roller_position_std_um": 0.0, "tolerance.roller_runout_um": 0.0})
    pid = PID(0.085, 14.7)
    a = simulate(perfect, load=STEP, duration=0.05, controller=pid, fidelity="multi-roller")
    b = simulate(perfect, load=STEP, duration=0.05, controller=pid, fidelity="compliant")
    assert np.max(np.abs(_y(a, "nut_speed") - _y(b, "nut_speed"))) < 1e-6
    np.testing.assert_allclose(_y(a, "contact_force_screw"), _y(b, "contact_force_screw"), rtol=1e-5)


def test_nut_speed_close_to_compliant_and_energy_closes(runs):
    mr, co = runs
    drop_mr = 31.4159 - _y(mr, "nut_speed").min()
    drop_co = 31.4159 - _y(co, "nut_speed").min()
    assert abs(drop_mr / drop_co - 1) < 0.01
    assert energy_balance(mr)["relative_residual"] < 1e-4


def test_errors_are_seeded_and_zero_mean():
    a, b, c = RollerErrors.draw(PLANT, 1), RollerErrors.draw(PLANT, 1), RollerErrors.draw(PLANT, 2)
    assert a == b and a != c
    assert abs(np.mean(a.position_nut)) < 1e-15 and np.std(a.position_nut) > 0
    assert plant_model(PLANT, "multi-roller", 1) is plant_model(PLANT, "multi-roller", 1)


def test_multi_roller_cannot_be_linearised():
    from prsa_ctrl import linearize

    with pytest.raises(ValueError, match=r"fidelity = 'multi-roller'; expected 'rigid' or 'compliant'"):
        linearize(PLANT, 31.4, 1000.0, "multi-roller")


# ------------------------------------------------------------------------------------------------
# The no-load drag's breakaway excess (friction.no_load_breakaway_torque_n_m, issue 21): the
# default leaves every plant as it was; with it the generator's Stribeck law on the WHOLE Coulomb
# level, ``(T0 + c_F |F|) (1 + (r - 1) exp(-(w/w_s)^2))``, is the plant's exactly (mu_s = r mu_d,
# T_s0 = r T0, v_s = w_s a); breakaway and feed-forward follow the same law.
# ------------------------------------------------------------------------------------------------

KEY = "friction.no_load_breakaway_torque_n_m"


@pytest.fixture(scope="module")
def base():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_plant()


def _generator_plant(base, r=1.4, w_s=0.25, t0=0.025, eta=0.86, b=1.5e-4, t_off=0.006):
    a = base.lead_per_rad
    mu_d = base.values["friction.dynamic"]
    return base.with_params({"friction.no_load_torque_n_m": t0, KEY: r * t0, "friction.static": r * mu_d,
                             "friction.stribeck_velocity_m_s": w_s * a, "friction.efficiency": eta,
                             "friction.viscous_n_m_s_per_rad": b, "friction.torque_offset_n_m": t_off})


def test_default_is_no_excess_and_follows_the_no_load_torque(base):
    assert base.values[KEY] == base.values["friction.no_load_torque_n_m"] and not base.given(KEY)
    assert base.sources[KEY].startswith("default: no breakaway excess")
    assert drag_breakaway_excess(base) is None
    moved = base.with_params({"friction.no_load_torque_n_m": 0.05})
    assert moved.values[KEY] == 0.05 and drag_breakaway_excess(moved) is None
    # a given value equal to the no-load torque is the same law, to the bit
    same = base.with_params({KEY: base.values["friction.no_load_torque_n_m"]})
    m0, m1 = plant_model(base, "rigid"), plant_model(same, "rigid")
    for x, u in (([0.0, 0.3, 0.1], [0.05, 800.0]), ([0.0, -2.0, -0.4], [0.0, -300.0]), ([0.0, 1e-9, 0.0], [0.0, 0.0])):
        assert np.array_equal(np.asarray(m0.f(x, u)), np.asarray(m1.f(x, u)))


def test_range_checks(base):
    with pytest.raises(PlantFileError, match=r"no_load_breakaway_torque_n_m = 0\.001 N m is below"):
        base.with_params({KEY: 0.001})
    with pytest.raises(PlantFileError, match="not below drive.torque_limit_n_m"):
        base.with_params({KEY: 50.0})


@pytest.mark.parametrize("w", [0.05, 0.1, 0.25, 0.5, -0.3, -1.0, 2.0, 20.0])
@pytest.mark.parametrize("load", [0.0, 500.0, 1500.0])
def test_generator_law_is_the_plant_law(base, w, load):
    """Steady torque of the toolkit's model against the generator's formula in numpy."""
    r, w_s, t0, eta, b, t_off = 1.4, 0.25, 0.025, 0.86, 1.5e-4, 0.006
    p = _generator_plant(base, r, w_s, t0, eta, b, t_off)
    a = base.lead_per_rad
    c_f = a * (1 / eta - 1)
    level = (t0 + c_f * abs(load)) * (1 + (r - 1) * math.exp(-(w / w_s) ** 2))
    want = a * load + math.copysign(level, w) + b * w + t_off
    assert steady_torque(p, w, load) == pytest.approx(want, rel=1e-9, abs=1e-12)


def test_breakaway_holds_below_and_moves_above(base):
    p = _generator_plant(base)
    a, load = base.lead_per_rad, 1000.0
    c_f = a * (1 / 0.86 - 1)
    breakaway = 1.4 * (0.025 + c_f * load)  # beyond the load torque and the offset
    m = plant_model(p, "rigid")
    for frac, moves in ((0.98, False), (1.02, True)):
        tau = a * load + 0.006 + frac * breakaway
        acc = float(m.f([0.0, 0.0, tau], [tau, load])[1])
        assert (acc > 0) == moves and (moves or acc == 0.0)


def test_feedforward_carries_the_drag_excess(base):
    p = _generator_plant(base)
    ff = FrictionFeedforward.from_plant(p, 500.0)
    a = base.lead_per_rad
    c_f = a * (1 / 0.86 - 1)
    assert ff.stribeck_positive_n_m == pytest.approx(0.4 * (0.025 + c_f * 500.0), rel=1e-9)
    for w in (0.1, 0.4, -0.2):  # the curve is the plant's sliding friction less the load torque
        assert float(ff.torque(w)) == pytest.approx(steady_torque(p, w, 500.0) - a * 500.0, rel=1e-9)


def test_a_fit_of_the_drag_above_a_given_breakaway_raises_it(base):
    """A plant that gives the breakaway level, fitted to a higher no-load torque: the breakaway is
    raised to it with a warning (no PlantFileError in the middle of a fit), and prsa-fit writes it."""
    import numpy as np

    from prsa_ctrl.identification.common import finish_fit

    given = base.with_params({KEY: 0.021})
    keys = ("friction.no_load_torque_n_m",)
    warns = []
    params, _, fitted, *_ = finish_fit(given, keys, np.array([0.03]), np.array([[1e-8]]), np.array([0.0]),
                                       np.array([1.0]), "log", warns)
    assert fitted.values[KEY] == 0.03 and any("raised to it" in w for w in warns)


def test_direction_dependent_viscous(base):
    """friction.viscous_offset_n_m_s_per_rad: b + b_o forward, b - b_o backward, in the model's steady
    torque and the feed-forward; 0 (default) is the old law; |b_o| <= b is checked."""
    key = "friction.viscous_offset_n_m_s_per_rad"
    assert base.values[key] == 0.0 and not base.given(key)
    b, b_o = 4e-4, 1.5e-4
    p = base.with_params({"friction.viscous_n_m_s_per_rad": b, key: b_o})
    q = base.with_params({"friction.viscous_n_m_s_per_rad": b})
    for w in (3.0, -3.0, 40.0, -40.0):
        extra = (b + b_o if w > 0 else b - b_o) * w - b * w
        assert steady_torque(p, w, 300.0) - steady_torque(q, w, 300.0) == pytest.approx(extra, rel=1e-9)
    ff = FrictionFeedforward.from_plant(p, 0.0)
    assert (ff.viscous_positive_n_m_s_per_rad, ff.viscous_negative_n_m_s_per_rad) == pytest.approx((b + b_o, b - b_o))
    with pytest.raises(PlantFileError, match="exceeds friction.viscous_n_m_s_per_rad"):
        base.with_params({"friction.viscous_n_m_s_per_rad": b, key: -5e-4})
