"""Issue 21, part 1: screw axes as a family of mechanisms.

Every expected number below is derived here, independently of prsa_ctrl's formulas: rigid-body
kinematics from rolling without slip, inertias from the bodies' geometry, the axial stiffness from
E A / length of the shaft segments in series with nut and bearing, the axial mode from the
eigenvalues of the mass and stiffness matrices written here.
"""

import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from prsa_ctrl import GeometryWarning, PlantFileError, load_plant, load_scene, tune_actuator
from prsa_ctrl.drive.pid import PID
from prsa_ctrl.plant import linear_core, operating_point, plant_model, steady_torque
from prsa_ctrl.plant.uncertainty import plant_uncertainty
from prsa_ctrl.studies import montecarlo as mc

ROOT = Path(__file__).resolve().parents[2]
STEEL = 7850.0
SCREW_PLANTS = ("ballscrew-32x10", "rollerscrew-30x5")


@pytest.fixture(scope="module")
def plants():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeometryWarning)
        return {n: load_plant(n) for n in (*SCREW_PLANTS, "paper-iprsm")} | {
            "emps": load_plant(ROOT / "examples" / "emps" / "plant.toml")}


def _lead(p):
    return p.values["screw.lead_mm"] * 1e-3 / (2 * math.pi)


def _inertia_from_geometry(p):
    """Rotor + solid steel screw (pi rho d^4 L / 32 over the bearing span) + moving mass a^2."""
    v = p.values
    d, span = v["screw.pitch_diameter_mm"] * 1e-3, v["axis.bearing_span_mm"] * 1e-3
    j_screw = STEEL * math.pi * d**4 / 32 * span if not p.given("axis.screw_inertia_kg_m2") else v["axis.screw_inertia_kg_m2"]
    return v["axis.motor_inertia_kg_m2"] + j_screw + v["axis.moving_mass_kg"] * _lead(p) ** 2


def _model_inertia(p, torques=(0.0, 1.0), load=0.0):
    """The rigid model's inertia from its own equations: two torques at the same sliding speed
    differ in acceleration by dT / J (with the nut loss on the external load only, friction
    does not depend on the torque while sliding)."""
    f = plant_model(p, "rigid").f
    acc = [float(f([0.0, 50.0, t], [0.0, load])[1]) for t in torques]
    return (torques[1] - torques[0]) / (acc[1] - acc[0])


@pytest.mark.parametrize("name", SCREW_PLANTS)
def test_reflected_inertia_and_lead_of_screw_driven_axes(plants, name):
    p = plants[name]
    assert p.screw_driven and p.mechanism == name.split("-")[0].replace("ballscrew", "ball-screw").replace(
        "rollerscrew", "roller-screw")
    j = _inertia_from_geometry(p)
    assert p.reflected_inertia_kg_m2 == pytest.approx(j, rel=1e-12)
    # with the nut loss on the external load only (axis.nut_loss_on_whole_force = 0) the model's
    # inertia is the geometry's; the default (1) is checked in the test below
    assert _model_inertia(p.with_params({"axis.nut_loss_on_whole_force": 0})) == pytest.approx(j, rel=1e-9)
    # lead: the translating member (nut and carriage) moves L per screw turn
    y = plant_model(p, "rigid").h([0.0, 2 * math.pi, 0.0], [0.0, 0.0])
    names = plant_model(p, "rigid").output_names
    assert float(y[names.index("screw_velocity")]) == pytest.approx(p.values["screw.lead_mm"] * 1e-3, rel=1e-12)


@pytest.mark.parametrize("name", SCREW_PLANTS)
def test_nut_loss_on_the_whole_force_through_the_nut(plants, name):
    """Default of ball and roller screws: the nut's loss (1/eta - 1) a |F_s| acts on the whole
    force through the nut, F_s = F_load + m a w' (the carriage's inertial force included). Then a
    torque step while driving forward (F_s > 0, power into the load) meets the inertia
    J + (1/eta - 1) m a^2, and while braking (F_s < 0) J - (1/eta - 1) m a^2: derived here from
    the force balance of the carriage, not from the model's code."""
    p = plants[name]
    assert p.values["axis.nut_loss_on_whole_force"] == 1
    assert p.sources["axis.nut_loss_on_whole_force"].startswith("default:")
    j = _inertia_from_geometry(p)
    extra = (1.0 / p.values["friction.efficiency"] - 1.0) * p.values["axis.moving_mass_kg"] * _lead(p) ** 2
    t_max = p.values["drive.torque_limit_n_m"]
    assert _model_inertia(p, (0.5 * t_max, 0.6 * t_max)) == pytest.approx(j + extra, rel=1e-9)
    assert _model_inertia(p, (-0.6 * t_max, -0.5 * t_max)) == pytest.approx(j - extra, rel=1e-9)
    assert abs(_model_inertia(p, (0.5 * t_max, 0.6 * t_max)) - j) > 0.5 * extra  # the law is in (extra >> 1e-5 j)
    assert extra > 1e-3 * j
    # at steady speed (no acceleration) the force through the nut is the load: the torque that
    # holds the speed is the same under both laws (zero acceleration in the model)
    load = 0.5 * p.values["screw.rated_load_n"]
    t_ss = steady_torque(p, 50.0, load)
    assert t_ss == steady_torque(p.with_params({"axis.nut_loss_on_whole_force": 0}), 50.0, load)
    acc = float(plant_model(p, "rigid").f([0.0, 50.0, t_ss], [t_ss, load])[1])
    assert abs(acc) * j < 1e-9 * t_max


def test_inverted_roller_screw_keeps_the_nut_loss_on_the_external_load(plants):
    """The paper plant (IPRSM) has no such key: its rigid model is unchanged (loss on the
    external load, the source paper's model), so its inertia is the geometry's."""
    p = plants["paper-iprsm"]
    assert "axis.nut_loss_on_whole_force" not in p.values
    assert _model_inertia(p, (0.5, 0.6), load=1000.0) == pytest.approx(p.reflected_inertia_kg_m2, rel=1e-9)


def test_linear_axis_is_its_mass_in_load_coordinates(plants):
    p = plants["emps"]
    assert p.mechanism == "linear-axis" and p.lead_per_rad == pytest.approx(1.0, rel=1e-15)
    assert _model_inertia(p) == pytest.approx(p.values["axis.mass_kg"], rel=1e-9)
    # direction-dependent friction (identification/axis.py's law): F = Fc+ + Fv+ v, v > 0;
    # F = -Fc- + Fv- v, v < 0; written here as the holding force at constant speed, no load
    q = p.with_params({"friction.coulomb_positive_n": 25.0, "friction.coulomb_negative_n": 15.0,
                       "friction.viscous_positive_n_s_per_m": 200.0, "friction.viscous_negative_n_s_per_m": 120.0})
    for v_ms, expected in ((0.1, 25.0 + 200.0 * 0.1), (-0.1, -15.0 - 120.0 * 0.1)):
        assert steady_torque(q, v_ms, 0.0) == pytest.approx(expected, rel=1e-9)
    assert plant_model(q, "compliant").state_names == ("theta_nut", "omega_nut", "tau_motor")
    with pytest.raises(ValueError, match="multi-roller"):
        plant_model(q, "multi-roller")


def test_roller_screw_carrier_speed_from_rolling_without_slip(plants):
    p = plants["rollerscrew-30x5"]
    d_s, d_n, d_r = (p.values[f"{k}.pitch_diameter_mm"] * 1e-3 for k in ("screw", "nut", "roller"))
    w_s = 10.0
    # unknowns: carrier speed wc, absolute roller spin wr. Contact speeds (tangential):
    # screw side: wc (d_s + d_r)/2 - wr d_r/2 = w_s d_s/2 ; nut side (nut still): wc (d_s + d_r)/2 + wr d_r/2 = 0
    A = np.array([[(d_s + d_r) / 2, -d_r / 2], [(d_s + d_r) / 2, d_r / 2]])
    wc, wr = np.linalg.solve(A, [w_s * d_s / 2, 0.0])
    k = p.kinematics(w_s)
    assert float(k.omega_cage) == pytest.approx(wc, rel=1e-12)
    assert float(k.omega_roller_abs) == pytest.approx(wr, rel=1e-12)  # signed: against the orbit
    assert float(k.omega_roller_rel) == pytest.approx(wr - wc, rel=1e-12)
    assert float(plants["ballscrew-32x10"].kinematics(w_s).omega_cage) == 0.0  # no ball-train model


@pytest.mark.parametrize("name", SCREW_PLANTS)
def test_forward_and_back_driving_efficiency(plants, name):
    p = plants[name]
    eta, a, w, f = p.values["friction.efficiency"], _lead(p), 40.0, 4000.0
    t0 = steady_torque(p, w, 0.0)
    assert steady_torque(p, w, f) - t0 == pytest.approx(f * a / eta, rel=1e-9)  # motor drives the load
    back = (steady_torque(p, w, -f) - t0) / (-f * a)  # the load drives the motor
    assert back == pytest.approx(p.backdrive_efficiency, rel=1e-9)
    # the catalogue pair (THK): eta = (1 - mu tan b)/(1 + mu/tan b), eta' = (1 - mu/tan b)/(1 + mu tan b)
    tb = p.values["screw.lead_mm"] / (math.pi * p.values["screw.pitch_diameter_mm"])
    mu = tb * (1 - eta) / (eta + tb * tb)  # solves the first formula for mu
    assert (1 - mu * tb) / (1 + mu / tb) == pytest.approx(eta, rel=1e-12)
    assert back == pytest.approx((1 - mu / tb) / (1 + mu * tb), abs=0.003)


def _ea(p):
    v = p.values
    return v["screw.youngs_modulus_gpa"] * 1e9 * math.pi / 4 * (v["screw.root_diameter_mm"] * 1e-3) ** 2


@pytest.mark.parametrize("mounting", ["fixed-free", "fixed-fixed"])
def test_shaft_stiffness_along_the_stroke(plants, mounting):
    p = plants["ballscrew-32x10"].with_params({"axis.fixed_ends": 1 if mounting == "fixed-free" else 2})
    span = p.values["axis.bearing_span_mm"] * 1e-3
    for x_mm in (50.0, 250.0, 500.0, 900.0):
        x = x_mm * 1e-3
        # fixed-free: only the segment from the fixed bearing to the nut is loaded; fixed-fixed: both
        # segments, held at their far ends, push/pull in parallel
        k_shaft = _ea(p) / x if mounting == "fixed-free" else _ea(p) / x + _ea(p) / (span - x)
        assert p.shaft_stiffness_n_per_m(x_mm) == pytest.approx(k_shaft, rel=1e-12)
        k_nut = p.values["axis.nut_stiffness_n_per_um"] * 1e6
        k_brg = p.values["axis.bearing_stiffness_n_per_um"] * 1e6
        series = 1 / (1 / k_shaft + 1 / k_nut + 1 / k_brg)
        assert p.axial_stiffness_n_per_m(x_mm) == pytest.approx(series, rel=1e-12)
        # the compliant model's static deflection: motor-side helix minus carriage = F / k_series
        q = p.with_params({"axis.stroke_position_mm": x_mm})
        op = operating_point(q, 30.0, 5000.0, "compliant")
        m = plant_model(q, "compliant")
        lag = op.x[m.index("delta_screw")] - op.x[m.index("x_roller")]  # a th - x_C
        assert lag == pytest.approx(5000.0 / series, rel=1e-6)


def _modes_hz(p, with_friction=True):
    """Undamped modes of the three bodies written here: q = (a th, u_shaft, x_carriage),
    T = J/a^2 q0'^2/2 + m_sh q1'^2/2 + m q2'^2/2, V = k_H (q0 + q1 - q2)^2/2 + k_B q1^2/2. The
    thread friction proportional to the thread force (forward efficiency eta) scales the rotor's
    row by 1/eta while the motor drives."""
    v, a = p.values, _lead(p)
    span = v["axis.bearing_span_mm"] * 1e-3
    j = v["axis.motor_inertia_kg_m2"] + v["axis.screw_inertia_kg_m2"]
    m_sh = STEEL * math.pi / 4 * (v["screw.root_diameter_mm"] * 1e-3) ** 2 * span
    x = v["axis.stroke_position_mm"] * 1e-3
    k_shaft = _ea(p) / x if v["axis.fixed_ends"] == 1 else _ea(p) * span / (x * (span - x))
    k_h = 1 / (1 / k_shaft + 1 / (v["axis.nut_stiffness_n_per_um"] * 1e6))
    k_b = v["axis.bearing_stiffness_n_per_um"] * 1e6
    M = np.diag([j / a**2, m_sh, v["axis.moving_mass_kg"]])
    g = np.array([1.0, 1.0, -1.0])
    K = k_h * np.outer(g, g) + np.diag([0.0, k_b, 0.0])
    if with_friction:
        K[0] /= v["friction.efficiency"]
    w2 = np.sort(np.abs(np.linalg.eigvals(np.linalg.solve(M, K))))
    return np.sqrt(w2[1:]) / (2 * math.pi)


@pytest.mark.parametrize("name", SCREW_PLANTS)
def test_axial_mode_moves_with_the_stroke_position(plants, name):
    base = plants[name].with_params({"axis.axial_damping_ratio": 1e-4})
    span = base.values["axis.bearing_span_mm"]
    found = []
    for x_mm in (0.1 * span, 0.5 * span, 0.9 * span):
        p = base.with_params({"axis.stroke_position_mm": x_mm})
        A = linear_core(p, 40.0, 2000.0, "compliant")[0]
        lam = np.linalg.eigvals(A)
        osc = np.sort(np.abs(lam[lam.imag > 1.0]))  # |lambda| = undamped frequency of each pair
        modes = _modes_hz(p)
        assert osc / (2 * math.pi) == pytest.approx(modes, rel=1e-4)
        # the two-mass estimate (massless shaft, no friction) is within 3 % of the lowest mode
        assert p.axial_mode_hz() == pytest.approx(_modes_hz(p, with_friction=False)[0], rel=0.03)
        found.append(modes[0])
    if base.values["axis.fixed_ends"] == 1:  # fixed-free: softer the farther the nut from the bearing
        assert found[0] > found[1] > found[2]
    else:  # fixed-fixed: softest at mid-span, symmetric
        assert found[1] < found[0] and found[1] < found[2]
    assert max(found) / min(found) > 1.15  # the stroke matters (1.20 for the ball screw, 10 % to 90 %)


def test_multi_roller_fidelity_is_refused_for_screw_driven_axes(plants):
    with pytest.raises(ValueError, match=r"multi-roller.*expected 'rigid' or 'compliant' for mechanism = 'ball-screw'"):
        plant_model(plants["ballscrew-32x10"], "multi-roller")


def test_derived_keys_cannot_be_set_silently(plants):
    with pytest.raises(PlantFileError, match=r"nut\.inertia_kg_m2 = 0\.01 cannot be set: it is derived: axis\.motor_inertia"):
        plants["ballscrew-32x10"].with_params({"nut.inertia_kg_m2": 0.01})


@pytest.mark.parametrize("name", SCREW_PLANTS)
def test_load_step_tune_and_verify(plants, name):
    p = plants[name]
    scene = load_scene().replace(candidates=1, step_time=0.02, duration=0.08)
    rep = tune_actuator(p, scene, workers=1)
    best = rep.best
    assert best.tuner_status == "optimal"
    assert best.margins.ms <= scene.ms_max * (1 + 1e-3)
    assert rep.scene.fidelity == "compliant"  # verified on the model with the axial spring
    assert not best.flags and not best.verified[0].saturated
    # the linear prediction and the nonlinear verification agree
    assert best.objective_verified == pytest.approx(best.objective_predicted, rel=0.05)
    assert best.verified[0].peak_drop_rad_s == pytest.approx(best.predicted[0].peak_drop_rad_s, rel=0.05)
    assert math.isfinite(best.verified[0].recovery_time_s)


def test_monte_carlo_with_the_stroke_position_uncertain(plants):
    p = plants["ballscrew-32x10"]
    unc = plant_uncertainty(p)
    assert "axis.stroke_position_mm" in unc.keys
    scene = load_scene().replace(step_time=0.02, duration=0.08)
    rep = mc.run_monte_carlo(p, scene, {"tuned": PID(1.32, 261.5, tf=5e-4)}, 4, seed=3, backend="serial", quiet=True)
    x = rep.samples["values"]["axis.stroke_position_mm"]
    assert len(set(np.round(x, 6))) == 4 and np.all((x >= 50.0) & (x <= 950.0))
    d = rep.designs[0]
    assert rep.complete and d.failures == 0 and d.passed == d.n == 4  # no spec: every simulation finished
    peaks = rep.samples["metrics"][:, 0, 0]
    assert np.all(np.isfinite(peaks)) and np.all(peaks > 0)
    # each sample's plant has its own axial mode (the stroke reaches the model)
    modes = [p.with_params({"axis.stroke_position_mm": float(xi),
                            "axis.moving_mass_kg": float(m)}).axial_mode_hz()
             for xi, m in zip(x, rep.samples["values"]["axis.moving_mass_kg"])]
    assert max(modes) / min(modes) > 1.05
    # robust tuning's vertices span the stroke's ends
    ends = sorted({v["axis.stroke_position_mm"] for v in unc.vertices()})
    assert ends == [50.0, 950.0]
