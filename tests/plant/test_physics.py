"""Physics of the model: roller axial kinematics of the inverted design, thread friction at
low speed and reversal (Stribeck + Karnopp stiction), bounded operating-point solves."""

import math

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from prsa_ctrl import PID, SimulationError, builtin_plants, energy_balance, load_plant
from prsa_ctrl.plant import model as M
from prsa_ctrl.plant.equilibrium import MAX_NEWTON_ITER, operating_point, steady_torque
from prsa_ctrl.sim.simulate import run

PLANT = load_plant()
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
    assert eta[0] < 0.83 and eta[-1] == pytest.approx(0.85, rel=1e-9)


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
        assert abs(theta) < 1e-9 and abs(omega) < 1e-9, (frac, theta, omega)
    up, down = _hold(fidelity, 1.1), _hold(fidelity, -1.1)
    assert up[1] > 1.0 and down[1] < -1.0  # broke away, in the direction of the net torque
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
    assert w[0] == pytest.approx(0.05, rel=1e-6) and w[-1] == pytest.approx(-0.05, rel=1e-3)
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
        assert str(exc) and "\n" not in str(exc)
        return
    assert 1 <= op.newton_iterations <= MAX_NEWTON_ITER
    assert abs(op.torque) < PLANT.torque_limit and np.all(np.isfinite(op.x))


@pytest.mark.parametrize("seed", range(5))
def test_multi_roller_with_coarse_tolerances_converges_or_says_why(seed):
    """Coarse roller position errors (50 um, the plausible maximum) used to make the CasADi
    Newton spin on a singular Jacobian for tens of seconds; now each solve stops within the
    iteration budget or raises a message naming the tolerance."""
    p = PLANT.with_params({"tolerance.roller_position_std_um": 50.0})
    try:
        op = operating_point(p, W300, 500.0, "multi-roller", seed)
    except SimulationError as exc:
        assert "tolerance.roller_position_std_um" in str(exc) and "Newton" in str(exc)
        return
    assert op.newton_iterations <= MAX_NEWTON_ITER
