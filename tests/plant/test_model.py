"""prsa_ctrl.plant.model: the multi-roller model and the Stribeck drag of the model."""

from __future__ import annotations

import math
import warnings

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from prsa_ctrl import PID, SimulationError, builtin_plants, energy_balance, load_plant, simulate
from prsa_ctrl.drive.friction import FrictionFeedforward
from prsa_ctrl.errors import PlantFileError
from prsa_ctrl.plant import model as M, steady_torque
from prsa_ctrl.plant.equilibrium import MAX_NEWTON_ITER, operating_point
from prsa_ctrl.plant.model import RollerErrors, drag_breakaway_excess, plant_model
from prsa_ctrl.plant.uncertainty import apply
from prsa_ctrl.sim.engine import run
from prsa_ctrl.sim.integrators import SimSettings
from prsa_ctrl.studies.paper import default_pid

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
    assert a == b
    assert a != c
    assert abs(np.mean(a.position_nut)) < 1e-15
    assert np.std(a.position_nut) > 0
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
    assert base.values[KEY] == base.values["friction.no_load_torque_n_m"]
    assert not base.given(KEY)
    assert base.sources[KEY].startswith("default: no breakaway excess")
    assert drag_breakaway_excess(base) is None
    moved = base.with_params({"friction.no_load_torque_n_m": 0.05})
    assert moved.values[KEY] == 0.05
    assert drag_breakaway_excess(moved) is None
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
        assert (acc > 0) == moves
        assert moves or acc == 0.0


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
    assert fitted.values[KEY] == 0.03
    assert any("raised to it" in w for w in warns)


def test_direction_dependent_viscous(base):
    """friction.viscous_offset_n_m_s_per_rad: b + b_o forward, b - b_o backward, in the model's steady
    torque and the feed-forward; 0 (default) is the old law; |b_o| <= b is checked."""
    key = "friction.viscous_offset_n_m_s_per_rad"
    assert base.values[key] == 0.0
    assert not base.given(key)
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


# ---- folded from test_physics.py:
# Physics of the model: roller axial kinematics of the inverted design, thread friction at
# low speed and reversal (Stribeck + Karnopp stiction), bounded operating-point solves.

W300 = 31.4159


def _implied_efficiency(plant, omega, f1=1000.0, f2=2000.0):
    """Load power over the load-dependent input power, a dF / d tau (drag cancels)."""
    return plant.lead_per_rad * (f2 - f1) / (steady_torque(plant, omega, f2) - steady_torque(plant, omega, f1))


def _breakaway(plant, load):
    f_n, f_s = plant.normal_force_factor()
    v = plant.values
    return plant.slip_arm_m * v["friction.static"] * abs(load) * (f_n + f_s) + v["friction.no_load_torque_n_m"]


# --- friction: Stribeck curve with Karnopp stiction ------------------------------------------


@pytest.mark.parametrize("name", builtin_plants())
def test_efficiency_at_speed_is_the_plant_value(name):
    p = load_plant(name)
    assert _implied_efficiency(p, W300) == pytest.approx(p.values["friction.efficiency"], rel=1e-9)


@pytest.mark.parametrize("omega", [0.05, 0.01])
def test_low_speed_efficiency_drops_to_the_static_level_in_both_directions(omega):
    """The old smooth sign gave 0.93 (0.05 rad/s) and 0.98 (0.01 rad/s): losses vanished.
    Now the load-dependent losses sit on the static branch of the Stribeck curve:
    1/eta - 1 = (1/eta_0 - 1) mu(v)/mu_d with mu(v) -> mu_s."""
    eta0 = PLANT.values["friction.efficiency"]
    mu_s, mu_d = PLANT.values["friction.static"], PLANT.values["friction.dynamic"]
    mu = float(M.stribeck_coefficient(PLANT, PLANT.lead_per_rad * omega))
    expected = 1.0 / (1.0 + (1.0 / eta0 - 1.0) * mu / mu_d)
    fwd = _implied_efficiency(PLANT, omega)
    assert fwd == pytest.approx(expected, rel=1e-9)
    assert fwd < eta0 - 0.02  # below the at-speed value, not rising toward 1
    assert mu == pytest.approx(mu_s, rel=0.01)
    # Reverse direction, mirrored load: the same efficiency.
    assert _implied_efficiency(PLANT, -omega, -1000.0, -2000.0) == pytest.approx(fwd, rel=1e-12)
    # The compliant model needs the same torque at steady state, in both directions.
    for w, f in ((omega, 1500.0), (-omega, -1500.0)):
        op = operating_point(PLANT, w, f, "compliant")
        assert op.torque == pytest.approx(steady_torque(PLANT, w, f), rel=1e-9)


def test_efficiency_curve_is_monotone_from_static_to_dynamic():
    speeds = [0.01, 0.05, 0.2, 0.5, 1.0, 3.0, W300]
    eta = [_implied_efficiency(PLANT, w) for w in speeds]
    assert all(b >= a - 1e-12 for a, b in zip(eta, eta[1:]))
    assert eta[0] < 0.83
    assert eta[-1] == pytest.approx(0.85, rel=1e-9)


def _hold(fidelity, frac, load=1500.0, t_end=0.2):
    """Integrate the open-loop plant from rest at a constant torque command of
    load L/(2 pi) + frac * breakaway; return the final nut angle and speed."""
    m = M.plant_model(PLANT, fidelity)
    x, u = ca.MX.sym("x", m.nx), ca.MX.sym("u", 2)
    integ = ca.integrator("hold", "cvodes", {"x": x, "p": u, "ode": m.f(x, u)}, 0.0, t_end,
                          {"abstol": 1e-10, "reltol": 1e-8})
    tau = load * PLANT.lead_per_rad + frac * _breakaway(PLANT, load)
    x0 = operating_point(PLANT, 0.0, load, fidelity).x.copy()
    x0[m.index("tau_motor")] = tau
    xf = np.asarray(integ(x0=x0, p=[tau, load])["xf"]).ravel()
    return xf[m.index("theta_nut")], xf[m.index("omega_nut")]


@pytest.mark.parametrize("fidelity", ["rigid", "compliant"])
def test_stiction_holds_below_breakaway_and_releases_above_symmetrically(fidelity):
    for frac in (0.9, -0.9):
        theta, omega = _hold(fidelity, frac)
        assert abs(theta) < 1e-9, (frac, theta, omega)
        assert abs(omega) < 1e-9, (frac, theta, omega)
    up, down = _hold(fidelity, 1.1), _hold(fidelity, -1.1)
    assert up[1] > 1.0
    assert down[1] < -1.0  # broke away, in the direction of the net torque
    assert up[0] == pytest.approx(-down[0], rel=1e-3)  # reversal symmetric


_RIGID = M.plant_model(PLANT, "rigid")
_RIGID_JAC = ca.Function("dfdxu", [_RIGID.x, _RIGID.u], [ca.jacobian(_RIGID.xdot, ca.vertcat(_RIGID.x, _RIGID.u))])


@settings(max_examples=60, deadline=None, derandomize=True)
@given(
    st.floats(-50.0, 50.0, allow_nan=False),
    st.floats(-3.0, 3.0, allow_nan=False),
    st.floats(-6000.0, 6000.0, allow_nan=False),
    st.sampled_from([0.0, 1e-4, 3.1e-3, 5e-3, 6.3e-3]),
)
def test_rigid_model_is_odd_and_its_jacobian_finite(omega, tau, load, near_zero):
    """Reversal symmetry f(-x, -u) = -f(x, u), and finite Jacobians everywhere, including
    exactly at rest and at the stick-band edges (|omega| = w_b, 2 w_b)."""
    m, jac = _RIGID, _RIGID_JAC
    for w in (omega, near_zero, -near_zero):
        x, u = np.array([0.3, w, tau]), np.array([tau, load])
        np.testing.assert_allclose(np.asarray(m.f(-x, -u)).ravel(), -np.asarray(m.f(x, u)).ravel(), rtol=1e-12,
                                   atol=1e-9)
        assert np.all(np.isfinite(np.asarray(jac(x, u))))


def test_compliant_jacobian_is_finite_at_rest_and_at_band_edges():
    m = M.plant_model(PLANT, "compliant")
    jac = ca.Function("dfdxu", [m.x, m.u], [ca.jacobian(m.xdot, ca.vertcat(m.x, m.u))])
    op = operating_point(PLANT, 0.0, 1500.0, "compliant")
    band = M.stick_band_rad_s(PLANT)
    for w in (0.0, band, -band, 2 * band, 1.5 * band):
        x = op.x.copy()
        x[m.index("omega_nut")] = w
        assert np.all(np.isfinite(np.asarray(jac(x, [op.torque, 1500.0]))))


@pytest.mark.parametrize("fidelity", ["rigid", "compliant"])
def test_energy_balance_closes_through_a_speed_reversal(fidelity):
    """0.05 rad/s forward, then -0.05 rad/s: the nut crosses the stick band; the dissipated
    power includes the Stribeck/Karnopp friction."""
    r = run(PLANT, setpoint=[(0.0, 0.05), (0.05, -0.05)], load=500.0, duration=0.3,
            controller=PID(0.085, 14.7), fidelity=fidelity, energy=True)
    w = np.asarray(r.outputs[list(r.output_labels).index("nut_speed")])
    assert w[0] == pytest.approx(0.05, rel=1e-6)
    assert w[-1] == pytest.approx(-0.05, rel=1e-3)
    e = energy_balance(r)
    assert e["work_dissipated_j"] > 0
    assert e["relative_residual"] < 1e-4, e


# --- roller axial kinematics of the inverted design ------------------------------------------


def _with_assumption(roller_axial):
    """A fresh plant whose cached compliant model uses the given roller axial assumption."""
    p = load_plant()
    if roller_axial != "screw":
        M._CACHE.setdefault(p, {})[("compliant", 0)] = M._build(p, "compliant", 0, roller_axial)
    return p


def _steady(p, load):
    m = M.plant_model(p, "compliant")
    op = operating_point(p, W300, load)
    d_n, d_s = p.d_nut_m, p.d_screw_m
    w_n, w_p = op.x[m.index("omega_nut")], op.x[m.index("omega_cage")]
    v_slip = 0.5 * d_n * w_n - 0.5 * (d_n + d_s) * w_p
    y = np.asarray(m.h(op.x, [op.torque, load])).ravel()
    n_trac = max(y[m.output_names.index("contact_force_nut")], 0.0) + p.values["friction.traction_preload_n"]
    traction_torque = 0.5 * d_n * p.values["friction.dynamic"] * math.tanh(
        v_slip / p.values["friction.creep_velocity_m_s"]) * n_trac
    jac = np.asarray(ca.Function("A", [m.x, m.u], [ca.jacobian(m.xdot, m.x)])(op.x, [op.torque, load]))
    ev = np.linalg.eigvals(jac[1:, 1:])
    modes_hz = np.sort(np.abs(ev[ev.imag > 1.0])) / (2 * math.pi)
    return {
        "v_roller": op.x[m.index("v_roller")],
        "v_screw": op.x[m.index("v_screw")],
        "omega_cage": w_p,
        "traction_torque": traction_torque,
        "modes_hz": modes_hz,
    }


def test_roller_axial_assumption_difference():
    """Mechanism (rollers travel with the screw) vs the former assumption (rollers stay with the
    nut, the screw advances along the cage's helix). Measured at 300 rpm, 5000 N."""
    load = 5000.0
    new, old = _steady(_with_assumption("screw"), load), _steady(_with_assumption("nut"), load)
    a = PLANT.lead_per_rad
    k = PLANT.kinematics(W300)
    # Which body the rollers move with.
    assert new["v_roller"] == pytest.approx(new["v_screw"], rel=1e-9)
    assert abs(old["v_roller"]) < 1e-12
    # Which contact carries the load torque: the nut-roller helix (new) or the cage traction (old).
    assert abs(new["traction_torque"]) < 1e-9
    assert old["traction_torque"] == pytest.approx(a * load, rel=1e-3)
    # Consequence: the old model's screw and cage lag the rigid kinematics by the traction creep.
    assert new["v_screw"] == pytest.approx(float(k.v_screw), rel=1e-9)
    assert new["omega_cage"] == pytest.approx(float(k.omega_cage), rel=1e-9)
    assert 1e-4 < 1 - old["v_screw"] / float(k.v_screw) < 1e-3
    # The axial modes do not tell the two apart (the nut's reflected mass, ~2000 kg, is a wall
    # at these frequencies): same frequencies within 0.1 %.
    for f in (1500.0, load):
        m_new = _steady(_with_assumption("screw"), f)["modes_hz"]
        m_old = _steady(_with_assumption("nut"), f)["modes_hz"]
        assert len(m_new) == len(m_old) >= 1
        np.testing.assert_allclose(m_new, m_old, rtol=1e-3)
        assert 2000 < m_new[0] < 4000


def test_roller_axial_assumption_is_validated():
    with pytest.raises(ValueError, match=r"roller_axial = 'cage'; expected 'screw' or 'nut'"):
        M._build(PLANT, "compliant", 0, "cage")


# --- bounded operating-point solves ----------------------------------------------------------


@pytest.mark.parametrize("load", [1e20, 1e30, 1e300, -1e20])
def test_absurd_loads_name_the_load_the_motor_can_hold(load):
    with pytest.raises(SimulationError, match=r"at .*N needs .* beyond the motor limit of 3 N m .*"
                                              r"holds loads up to -?[0-9.e+]+ N: lower the load"):
        operating_point(PLANT, W300, load)


def test_absurd_speed_and_non_finite_inputs():
    with pytest.raises(SimulationError, match=r"even unloaded this speed needs .* N m: lower the speed"):
        operating_point(PLANT, 1e300, 500.0)
    with pytest.raises(ValueError, match=r"load = nan; expected a finite number \(N\)"):
        operating_point(PLANT, W300, float("nan"))
    with pytest.raises(ValueError, match=r"omega_nut = inf; expected a finite number \(rad/s\)"):
        operating_point(PLANT, math.inf, 500.0)
    with pytest.raises(ValueError, match=r"omega_nut = 0\.001 rad/s lies in the stick band"):
        operating_point(PLANT, 1e-3, 500.0)


def test_the_limit_named_in_the_message_is_the_true_limit():
    msg = ""
    try:
        operating_point(PLANT, W300, 1e9)
    except SimulationError as exc:
        msg = str(exc)
    f_max = float(msg.split("holds loads up to ")[1].split(" N")[0])
    assert abs(steady_torque(PLANT, W300, f_max) - PLANT.torque_limit) < 1e-3
    operating_point(PLANT, W300, 0.999 * f_max, "rigid")  # just inside: solves
    with pytest.raises(SimulationError):
        operating_point(PLANT, W300, 1.001 * f_max, "rigid")


@settings(max_examples=40, deadline=None, derandomize=True)
@given(st.floats(-1e6, 1e6, allow_nan=False), st.floats(-1e4, 1e4, allow_nan=False))
def test_operating_point_is_bounded_for_any_speed_and_load(omega, load):
    try:
        op = operating_point(PLANT, omega, load, "compliant")
    except (ValueError, SimulationError) as exc:
        assert str(exc)
        assert "\n" not in str(exc)
        return
    assert 1 <= op.newton_iterations <= MAX_NEWTON_ITER
    assert abs(op.torque) < PLANT.torque_limit
    assert np.all(np.isfinite(op.x))


@pytest.mark.parametrize("seed", range(5))
def test_multi_roller_with_coarse_tolerances_converges_or_says_why(seed):
    """Coarse roller position errors (50 um, the plausible maximum) used to make the CasADi
    Newton spin on a singular Jacobian for tens of seconds; now each solve stops within the
    iteration budget or raises a message naming the tolerance."""
    p = PLANT.with_params({"tolerance.roller_position_std_um": 50.0})
    try:
        op = operating_point(p, W300, 500.0, "multi-roller", seed)
    except SimulationError as exc:
        assert "tolerance.roller_position_std_um" in str(exc)
        assert "Newton" in str(exc)
        return
    assert op.newton_iterations <= MAX_NEWTON_ITER


# ---- folded from test_parametric.py:
# Parametric plant families: one model (and one compiled sampled-loop law) for the samples of a
# Monte-Carlo run, the same equations as a direct build of each sample.

KEYS = ("contact.stiffness_n_per_mm_e", "drive.current_loop_bandwidth_hz", "friction.efficiency",
        "nut.inertia_kg_m2")
VALUES = {"contact.stiffness_n_per_mm_e": 1.7e5, "drive.current_loop_bandwidth_hz": 640.0,
          "friction.efficiency": 0.8, "nut.inertia_kg_m2": 1.6e-4}


def _member(values, keys=KEYS):
    p = apply(PLANT, values)
    M.register_member(p, PLANT, keys)
    return p


@pytest.mark.parametrize("fidelity", ["rigid", "compliant"])
def test_member_model_is_the_direct_build(fidelity):
    p = _member(VALUES)
    m = M.plant_model(p, fidelity)
    direct = M._build(apply(PLANT, VALUES), fidelity)
    assert m.family is not None
    assert set(m.family.keys) == set(KEYS)
    assert m.theta == tuple(VALUES[k] for k in m.family.keys)
    for x, u in M._test_points(m.state_names, 4):
        for a, b in ((m.f, direct.f), (m.h, direct.h), (m.power, direct.power)):
            va, vb = np.asarray(a(x, u), float), np.asarray(b(x, u), float)
            np.testing.assert_allclose(va, vb, rtol=1e-12, atol=1e-12 * np.max(np.abs(vb)))


def test_keys_used_as_numbers_are_not_parameters():
    # the flank angle enters through math.cos: it cannot be a parameter, and a member
    # differing in it gets its own, direct model; sensor keys are never parameters
    fam = M.parametric_family(PLANT, "compliant", ("thread.flank_angle_deg", "nut.inertia_kg_m2", "sensor.sample_time_s"))
    assert fam is not None
    assert fam.keys == ("nut.inertia_kg_m2",)
    p = _member({"thread.flank_angle_deg": PLANT.values["thread.flank_angle_deg"] + 1.0},
                ("thread.flank_angle_deg", "nut.inertia_kg_m2", "sensor.sample_time_s"))
    assert M.plant_model(p, "compliant").family is None


def test_member_run_shares_one_law_and_matches_the_direct_run():
    kw = dict(setpoint=31.4159, load=[(0, 500.0), (0.002, 1500.0)], duration=0.03, controller=default_pid(PLANT),
              fidelity="compliant", discrete=True, settings=SimSettings(integrator="radau", substeps=2))
    a, b = _member(VALUES), _member({**VALUES, "nut.inertia_kg_m2": 1.1e-4})
    ra, rb = run(a, **kw), run(b, **kw)
    direct = run(apply(PLANT, VALUES), **kw)
    from prsa_ctrl.sim.integrators import build

    built_a = build(M.plant_model(a, "compliant"), False, shared=True)  # the runs' cached functions
    built_b = build(M.plant_model(b, "compliant"), False, shared=True)
    assert built_a.sampled is built_b.sampled  # one set of functions for the family
    assert len(built_a.sampled) > 0  # the runs filled the family's functions (only a shared run does)
    assert ra.states.shape == direct.states.shape
    assert ra.state_labels == direct.state_labels
    np.testing.assert_allclose(ra.outputs, direct.outputs, rtol=1e-9, atol=1e-9)
    assert not np.allclose(ra.output("nut_speed"), rb.output("nut_speed"))  # the parameters act


def test_monte_carlo_quotes_its_integrator_and_agrees_with_the_reference():
    from prsa_ctrl.studies import montecarlo as mc
    from prsa_ctrl.drive.pid import PID
    from prsa_ctrl.studies.scene import load_scene

    scene = load_scene("robust-load-step")
    pid = PID(0.0849, 14.67, tf=1e-3)
    fast = mc.run_monte_carlo(PLANT, scene, {"fast": pid}, 3, seed=5, quiet=True, spec={}, path="per-sample")
    batched = mc.run_monte_carlo(PLANT, scene, {"fast": pid}, 3, seed=5, quiet=True, spec={})
    ref = mc.run_monte_carlo(PLANT, scene, {"fast": pid}, 3, seed=5, quiet=True, spec={}, integrator="reference")
    assert fast.integration["integrator"] == "radau"
    assert ref.integration["integrator"] == "cvodes"
    assert fast.integration["relative"] <= 0.5 * scene.accuracy
    assert fast.as_dict()["integration"]["check_points"] == 7  # nominal, 2 corners, 2 x 2 single ends
    k = mc.METRICS.index("peak_drop_rad_s")
    drop_f, drop_r = fast.samples["metrics"][:, 0, k], ref.samples["metrics"][:, 0, k]
    assert np.all(np.abs(drop_f - drop_r) <= scene.accuracy * drop_r)
    assert "--integrator fast" in fast.designs[0].replay
    # the batched default checks its own samples against the adaptive reference
    ig = batched.integration
    assert ig["path"] == "batched"
    assert ig["check_samples"]
    assert set(ig["check_samples"]) <= {0, 1, 2}
    assert 0 < ig["relative"] <= 0.5 * scene.accuracy
    drop_b = batched.samples["metrics"][:, 0, k]
    assert np.all(np.abs(drop_b - drop_r) <= scene.accuracy * drop_r)
