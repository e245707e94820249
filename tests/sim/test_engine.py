import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from prsa_ctrl import PID, SimulationError, builtin_plants, energy_balance, load_plant, simulate
from prsa_ctrl.drive.linear_loop import predict_load_step
from prsa_ctrl.plant.linear import linearize
from prsa_ctrl.sim.integrators import SimSettings
from prsa_ctrl.studies.paper import OMEGA_300_RPM, default_pid, load_step_study

STEP = [(0.0, 500.0), (0.1, 1500.0)]


def _out(r, name):
    return np.asarray(r.outputs[r.output_labels.index(name)])


@pytest.mark.parametrize("name", builtin_plants())
def test_paper_validation_steady_speeds_within_0p1_percent(name):
    """Constant 5000 N at 300 rpm (reached after a load step): the compliant model's steady
    cage, roller and screw speeds sit within 0.1 % of the rigid kinematics."""
    p = load_plant(name)
    r = simulate(p, setpoint=OMEGA_300_RPM, load=[(0.0, 500.0), (0.02, 5000.0)], duration=0.4,
                 controller=default_pid(p), fidelity="compliant")
    late = r.time > 0.3
    k = p.kinematics(OMEGA_300_RPM)
    assert _out(r, "nut_speed")[late].mean() == pytest.approx(OMEGA_300_RPM, rel=1e-4)
    for sig, ref in (("cage_speed", k.omega_cage), ("roller_speed", k.omega_roller_rel),
                     ("roller_speed_abs", k.omega_roller_abs), ("screw_velocity", k.v_screw)):
        got = _out(r, sig)[late].mean()
        if float(ref) == 0.0:  # issue 21: a ball screw has no roller outputs (0 in both)
            assert got == 0.0, sig
            continue
        assert abs(got / float(ref) - 1) < 1e-3, (sig, got, float(ref))


@pytest.mark.parametrize("fidelity", ["rigid", "compliant"])
@pytest.mark.parametrize("discrete", [False, True])
def test_energy_balance_closes(paper_plant, fidelity, discrete):
    r = simulate(paper_plant, load=STEP, duration=0.3, controller=default_pid(paper_plant),
                 fidelity=fidelity, discrete=discrete, energy=True)
    e = energy_balance(r)
    assert e["work_load_j"] > 0
    assert e["work_dissipated_j"] > 0
    assert e["work_motor_j"] > e["work_load_j"]
    assert e["relative_residual"] < 1e-4, e


def test_energy_balance_needs_energy_terms(paper_plant):
    r = simulate(paper_plant, duration=0.01, controller=default_pid(paper_plant), fidelity="rigid")
    with pytest.raises(ValueError, match=r"energy=True"):
        energy_balance(r)


@pytest.mark.parametrize("discrete", [False, True])
def test_linear_closed_loop_predicts_peak_drop_within_5_percent(paper_plant, discrete):
    pid = default_pid(paper_plant)
    lin = linearize(paper_plant, OMEGA_300_RPM, 500.0, "compliant", sampled=discrete)
    pred = predict_load_step(lin, pid, 1000.0, 0.1, 0.3)
    r = simulate(paper_plant, setpoint=OMEGA_300_RPM, load=STEP, duration=0.3, controller=pid,
                 fidelity="compliant", discrete=discrete)
    drop_lin = OMEGA_300_RPM - pred.outputs[pred.output_labels.index("nut_speed")].min()
    drop_nl = OMEGA_300_RPM - _out(r, "nut_speed").min()
    assert drop_nl > 0.5
    assert abs(drop_lin / drop_nl - 1) < 0.05, (drop_lin, drop_nl)


def test_table3_scenario_drops_grow_near_linearly(paper_plant):
    rows = load_step_study(paper_plant, duration=0.45)
    drops = np.array([r.drop_nut for r in rows])
    steps = np.array([r.final_load - 500.0 for r in rows])
    assert np.all(np.diff(drops) > 0)
    # Near-linear: the drop per newton of step varies by less than 10 % across the steps.
    per_n = drops / steps
    assert per_n.max() / per_n.min() < 1.10
    for r in rows:
        # Rigid kinematics tie the drops together: cage = ratio * nut, roller = d_S/d_R * cage.
        assert r.drop_cage == pytest.approx(paper_plant.cage_ratio * r.drop_nut, rel=0.02)
        assert r.paper_drops is not None
        f_n, f_s = paper_plant.normal_force_factor()
        assert r.force_nut_mean == pytest.approx(r.final_load * f_n, rel=0.01)
        assert r.force_screw_mean == pytest.approx(r.final_load * f_s, rel=0.01)
        assert r.force_nut_range > 0
        assert r.force_screw_range > 0


def test_load_step_is_a_step_not_a_ramp(paper_plant):
    """The load input changes between two consecutive samples; the nut decelerates at once."""
    pid = default_pid(paper_plant)
    r = simulate(paper_plant, load=[(0.0, 500.0), (0.10005, 1500.0)], duration=0.12, dt=1e-4,
                 controller=pid, fidelity="rigid")
    load = np.asarray(r.inputs[1])
    jump = np.flatnonzero(np.diff(load))
    assert len(jump) == 1
    assert load[jump[0]] == 500.0
    assert load[jump[0] + 1] == 1500.0
    t = r.time
    assert np.any(np.isclose(t, 0.10005, atol=1e-12))  # the segment boundary is an output point
    w = _out(r, "nut_speed")
    i = int(np.flatnonzero(np.isclose(t, 0.10005, atol=1e-12))[0])
    assert w[i] == pytest.approx(w[0], abs=1e-6)
    assert w[i + 1] < w[i] - 1e-3


def test_outputs_are_named_and_finite(paper_plant):
    r = simulate(paper_plant, load=STEP, duration=0.15, controller=default_pid(paper_plant))
    for name in ("nut_speed", "cage_speed", "roller_speed", "screw_velocity", "motor_torque",
                 "contact_force_nut", "contact_force_screw"):
        assert np.all(np.isfinite(_out(r, name)))
    assert r.input_labels == ["speed_setpoint", "axial_load"]
    rigid = simulate(paper_plant, load=STEP, duration=0.15, controller=default_pid(paper_plant), fidelity="rigid")
    assert "contact_force_nut" not in rigid.output_labels


def test_p_only_controller_leaves_the_expected_steady_error(paper_plant):
    pid = PID(kp=0.1)
    r = simulate(paper_plant, load=STEP, duration=0.5, controller=pid, fidelity="rigid")
    w = _out(r, "nut_speed")
    tau = _out(r, "motor_torque")
    # Proportional law: torque = kp * error at steady state.
    assert OMEGA_300_RPM - w[-1] == pytest.approx(tau[-1] / pid.kp, rel=1e-4)
    assert (OMEGA_300_RPM - w[-1]) > (OMEGA_300_RPM - w[0])


def test_solver_failure_raises_clear_error(paper_plant):
    with pytest.raises(SimulationError, match=r"integration failed between t = 0\.1 s and t = 0\.2 s from state \[theta_nut=.*remedy"):
        simulate(paper_plant, load=[(0, 500.0), (0.1, 1500.0)], duration=0.3,
                 controller=default_pid(paper_plant), settings=SimSettings(max_steps=10))


def test_overload_is_reported_not_nan(paper_plant):
    with pytest.raises(SimulationError, match=r"needs .* N m, beyond the motor limit of 3 N m"):
        simulate(paper_plant, load=20000.0, duration=0.1, controller=default_pid(paper_plant))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"duration": -1.0}, r"duration = -1\.0; expected a finite number > 0 and <= 1e\+06 s"),
        ({"duration": float("nan")}, r"duration = nan; expected a finite number"),
        ({"duration": 1.0, "dt": 1e-10}, r"duration 1 s at dt = 1e-10 s gives 1e\+10 output points; expected at most 2e\+06"),
        ({"discrete": True, "duration": 1e5}, r"duration 100000 s at the sample time 0\.00025 s gives .* output points"),
        ({"measurement": "ekf", "discrete": True}, r"measurement = 'ekf'; expected 'encoder', 'kf'"),
        ({"measurement": "kf"}, r"estimators and noise belong to the sampled loop"),
        ({"controller": PID(0.1, 1.0, kff=0.5), "discrete": True}, r"PID kff = 0\.5 needs a load-torque estimate"),
        ({"load": [(0.0, 500.0), (0.01005, 900.0), (0.0101, 1000.0)], "discrete": True},
         r"two load changes inside the sample starting at 0\.01 s"),
        ({"load": [(0.1, 500.0)]}, r"load starts at t = 0\.1 s; expected the first point at t = 0"),
        ({"load": [(0.0, float("nan"))]}, r"load point \(0\.0, nan\) is not finite"),
        ({"load": "heavy"}, r"load = 'heavy'; expected a number \(N\)"),
        ({"setpoint": [(0.0, 1.0), (0.0, 2.0)]}, r"setpoint times \[0\.0, 0\.0\] must increase"),
        ({"fidelity": "exact"}, r"fidelity = 'exact'; expected one of rigid, compliant"),
        ({"dt": 0.0}, r"dt = 0\.0; expected 0 < dt"),
    ],
)
def test_bad_simulate_arguments(paper_plant, kwargs, match):
    args = {"duration": 0.1, "controller": PID(0.1, 1.0)}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        simulate(paper_plant, **args)


@pytest.mark.parametrize("kwargs, match", [
    ({"kp": -1.0}, r"PID kp = -1\.0; expected a finite number >= 0"),
    ({"kp": 1.0, "ki": float("inf")}, r"PID ki = inf"),
    ({"kp": 1.0, "tf": 0.0}, r"PID tf = 0\.0; expected a finite time constant > 0 s"),
])
def test_bad_pid(kwargs, match):
    with pytest.raises(ValueError, match=match):
        PID(**kwargs)


def test_bad_settings():
    with pytest.raises(ValueError, match=r"integrator = 'rk4'; expected one of cvodes, idas"):
        SimSettings(integrator="rk4")
    with pytest.raises(ValueError, match=r"rtol = 0; expected a tolerance in \(0, 1\)"):
        SimSettings(rtol=0)


def test_idas_and_cvodes_agree(paper_plant):
    pid = default_pid(paper_plant)
    a = simulate(paper_plant, load=STEP, duration=0.2, controller=pid, settings=SimSettings("cvodes"))
    b = simulate(paper_plant, load=STEP, duration=0.2, controller=pid, settings=SimSettings("idas"))
    assert np.max(np.abs(_out(a, "nut_speed") - _out(b, "nut_speed"))) < 1e-5


# --- the one sampled-loop simulator: events, signs, steady starts ---------------------------------

TS = 0.25e-3


@pytest.mark.parametrize("t_step", [0.0101, 0.0011, 0.01, 0.1000625, 0.10012])
def test_off_grid_load_step_acts_within_one_sample(paper_plant, t_step):
    """A load step between controller samples acts on the plant at its own time: the speed
    leaves its steady value in the first sample after the step, never at a chunk boundary."""
    from prsa_ctrl.sim.engine import run

    dur = t_step + 0.02
    r = run(paper_plant, load=[(0.0, 500.0), (t_step, 1500.0)], duration=dur, controller=PID(0.085, 14.7),
            fidelity="rigid", discrete=True)
    w = r.output("nut_speed")
    left = np.flatnonzero(np.abs(w - w[0]) > 0.02)
    assert left.size, "the step never reached the plant"
    onset = r.time[left[0]]
    assert t_step < onset <= t_step + TS + 1e-12, (t_step, onset)
    # The step's size is the same wherever it falls: 20 ms later the drop is the on-grid one.
    ref = run(paper_plant, load=[(0.0, 500.0), (0.01, 1500.0)], duration=0.03, controller=PID(0.085, 14.7),
              fidelity="rigid", discrete=True)
    assert w.min() == pytest.approx(ref.output("nut_speed").min(), abs=0.02)
    ev = r.info["events"]
    assert ev == [{"input": "axial_load", "time_s": t_step, "acts_at_s": t_step}]
    load = r.inputs[1]
    assert np.all(load[r.time < t_step - 1e-12] == 500.0)
    assert np.all(load[r.time >= t_step] == 1500.0)


def test_off_grid_setpoint_step_is_read_at_the_next_sample(paper_plant):
    from prsa_ctrl.sim.engine import run

    r = run(paper_plant, setpoint=[(0.0, 30.0), (0.0101, 31.0)], load=500.0, duration=0.02,
            controller=PID(0.085, 14.7), fidelity="rigid", discrete=True)
    assert r.info["events"][0]["acts_at_s"] == pytest.approx(0.01025)
    sp = r.inputs[0]
    k = int(np.flatnonzero(sp == 31.0)[0])
    assert r.time[k] == pytest.approx(0.01025)
    # The command responds at that sample (the PID sees the new error) and is applied one
    # sample later (computation delay).
    u = r.output("torque_command")
    assert u[k] == pytest.approx(u[0], abs=1e-3)
    assert u[k + 1] > u[0] + 0.05


def _verify_step(plant, f0, f1):
    from prsa_ctrl.sim.metrics import load_step_metrics
    from prsa_ctrl.sim.engine import run

    r = run(plant, load=[(0.0, f0), (0.002, f1)], duration=0.2, controller=PID(0.085, 14.7),
            fidelity="rigid", discrete=True)
    return load_step_metrics(r.time, r.output("nut_speed"), OMEGA_300_RPM, 0.002, r.output("motor_torque"),
                             plant.torque_limit, direction=1 if f1 >= f0 else -1)


def test_load_decrease_metrics_are_signed(paper_plant):
    """1500 -> 500 N speeds the nut up: the excursion is a rise of the same size as the
    500 -> 1500 N drop (near-linear loop), and the integral error is negative."""
    up = _verify_step(paper_plant, 500.0, 1500.0)
    down = _verify_step(paper_plant, 1500.0, 500.0)
    assert up.peak_deviation_rad_s < -1.0
    assert down.peak_deviation_rad_s > 1.0
    assert down.peak_drop_rad_s == pytest.approx(up.peak_drop_rad_s, rel=0.1)
    assert down.ie < 0 < up.ie
    assert down.iae == pytest.approx(up.iae, rel=0.1)
    assert down.direction == -1
    assert up.direction == 1
    assert down.recovery_time_s == pytest.approx(up.recovery_time_s, rel=0.2)


@pytest.mark.parametrize("measurement, kff", [("encoder", 0.0), ("kf", 0.0), ("kf", 0.8)])
def test_p_only_sampled_loop_starts_in_steady_state(paper_plant, measurement, kff):
    """No input change: a P-only loop (with or without the observer's feed-forward) must stay
    where it started, i.e. the initial integral and speed are the loop's true steady state."""
    from prsa_ctrl.sim.engine import run

    r = run(paper_plant, load=1000.0, duration=0.05, controller=PID(0.1, kff=kff), fidelity="rigid",
            discrete=True, measurement=measurement)
    w = r.output("nut_speed")
    # (encoder quantisation alone moves it by a few mrad/s; a wrong start would move it by rad/s)
    assert np.max(np.abs(w - w[0])) < 0.01, np.max(np.abs(w - w[0]))
    tau = r.output("motor_torque")
    # Steady P-only law: kp (ref - w) + kff * load estimate = torque (means over the run, as
    # quantisation dithers the single samples).
    law = 0.1 * (OMEGA_300_RPM - w.mean()) + kff * r.output("load_torque_estimate").mean()
    assert law == pytest.approx(tau.mean(), rel=2e-3)


def test_simulate_is_run_as_time_response(paper_plant):
    import inspect

    from prsa_ctrl.sim.engine import run

    kw = dict(load=STEP, duration=0.12, controller=default_pid(paper_plant), fidelity="rigid", discrete=True,
              energy=True)
    r = run(paper_plant, **kw)
    resp = simulate(paper_plant, **kw)
    np.testing.assert_array_equal(resp.outputs, r.outputs)
    assert list(resp.output_labels) == list(r.output_labels)
    assert resp.info["events"] == r.info["events"]
    assert energy_balance(resp) == energy_balance(r)
    assert type(resp).__name__ == "SimResponse"
    assert "energy" in type(resp).__annotations__
    assert "plant" in inspect.signature(simulate).parameters


# --- ramps and duty cycles --------------------------------------------------------------------

def _ramp_runs(paper_plant, discrete):
    """A 500 -> 1500 N ramp with both kinks between samples, against the same ramp as steps
    on the sample grid holding the ramp's value at each sample's midpoint (second-order close)
    and at its start (what ignoring the slope inside a sample would give, first order)."""
    from prsa_ctrl.sim.signals import PiecewiseLinear
    from prsa_ctrl.sim.engine import run

    t0, t1, dur = 0.0101, 0.0601, 0.08
    # A 26-bit encoder: the 20-bit quantum would dither the two runs apart by ~1e-3 rad/s.
    paper_plant = paper_plant.with_params({"sensor.encoder_counts_per_rev": 2**26})
    kw = dict(duration=dur, controller=PID(0.085, 14.7), fidelity="rigid", discrete=discrete,
              settings=SimSettings(rtol=1e-10, atol=1e-10))
    ramp = run(paper_plant, load=PiecewiseLinear([(0.0, 500.0), (t0, 500.0), (t1, 1500.0)]), **kw)

    def f(t):
        return 500.0 + 1000.0 * np.clip((t - t0) / (t1 - t0), 0.0, 1.0)

    grid = np.arange(0.0, dur - 1e-12, TS)
    mid = run(paper_plant, load=[(float(t), float(f(t + TS / 2))) for t in grid], **kw)
    left = run(paper_plant, load=[(float(t), float(f(t))) for t in grid], **kw)
    return ramp, mid, left, f


@pytest.mark.parametrize("discrete", [True, False])
def test_load_ramp_is_integrated_exactly(paper_plant, discrete):
    ramp, mid, left, f = _ramp_runs(paper_plant, discrete)
    np.testing.assert_allclose(ramp.inputs[1], f(ramp.time), rtol=0, atol=1e-9)
    w = ramp.output("nut_speed")
    err_mid = np.max(np.abs(w - np.interp(ramp.time, mid.time, mid.output("nut_speed"))))
    err_left = np.max(np.abs(w - np.interp(ramp.time, left.time, left.output("nut_speed"))))
    assert OMEGA_300_RPM - w.min() > 0.5  # the ramp loads the loop
    assert err_mid < 5e-4, err_mid  # the midpoint steps are second-order close: ~2e-4 of a 0.52 rad/s drop
    assert err_left > 5 * err_mid, (err_left, err_mid)  # a slope-blind run would be this far off
    assert ramp.info["events"] == []  # kinks are not steps


def test_mixed_steps_and_ramps_and_profile_errors(paper_plant):
    from prsa_ctrl.sim.signals import PiecewiseLinear
    from prsa_ctrl.sim.engine import run

    prof = PiecewiseLinear([(0.0, 500.0), (0.01, 500.0), (0.01, 1500.0), (0.03, 1000.0)])
    r = run(paper_plant, load=prof, duration=0.04, controller=PID(0.085, 14.7), fidelity="rigid", discrete=True)
    assert r.info["events"] == [{"input": "axial_load", "time_s": 0.01, "acts_at_s": 0.01}]
    assert r.inputs[1][r.time >= 0.03][0] == pytest.approx(1000.0)
    k = int(np.argmin(np.abs(r.time - 0.02)))
    assert r.inputs[1][k] == pytest.approx(1250.0)
    for pts, match in [
        ([(0.0, 1.0), (0.2, 2.0), (0.1, 3.0)], r"must not decrease"),
        ([(0.0, 1.0), (0.1, 2.0), (0.1, 3.0), (0.1, 4.0)], r"three are ambiguous"),
        ([(0.0, 1.0), (0.1, float("inf"))], r"is not finite"),
        ("ramp", r"expected a list of \(time_s, value\) pairs"),
    ]:
        with pytest.raises(ValueError, match=match):
            run(paper_plant, load=PiecewiseLinear(pts), duration=0.2, controller=PID(0.1, 1.0), fidelity="rigid")


def test_measured_force_trace_from_csv(paper_plant, tmp_path):
    from prsa_ctrl.sim.signals import PiecewiseLinear
    from prsa_ctrl.sim.engine import run

    f = tmp_path / "trace.csv"
    t = np.arange(0.0, 0.04, 1e-3)
    force = 500.0 + 800.0 * np.sin(2 * np.pi * 25.0 * t) ** 2
    f.write_text("time_s,axial_load_n\n" + "".join(f"{a:.6f},{b:.6f}\n" for a, b in zip(t, force)))
    prof = PiecewiseLinear.from_csv(f)
    r = run(paper_plant, load=prof, duration=0.045, controller=PID(0.085, 14.7), fidelity="rigid", discrete=True)
    on = r.time <= t[-1]
    np.testing.assert_allclose(r.inputs[1][on], np.interp(r.time[on], t, force), rtol=0, atol=1e-6)
    # the refusals of a bad trace file: tests/sim/test_signals.py


def test_zero_load_start_is_a_steady_state(paper_plant):
    """At exactly 0 N the roller assembly floats in its backlash (a continuum of equilibria):
    the operating point is the nearest one, and the loop starts steady from it."""
    from prsa_ctrl import operating_point
    from prsa_ctrl.sim.engine import run

    op = operating_point(paper_plant, OMEGA_300_RPM, 0.0, "compliant")
    assert op.torque > 0  # the no-load torque
    r = run(paper_plant, load=[(0.0, 0.0), (0.01, 1500.0)], duration=0.03, controller=PID(0.085, 14.7),
            discrete=True, energy=True)
    w = r.output("nut_speed")
    assert np.max(np.abs(w[r.time < 0.01] - w[0])) < 0.01
    assert w.min() < w[0] - 1.0


# ---- folded from test_stress.py:
# Numerical stress: every case returns finite results that close the energy balance, or raises
# the clear SimulationError; none returns NaN or hangs (a wall-time budget bounds every run).

PLANT = load_plant()


def _log(lo, hi):
    return st.floats(math.log10(lo), math.log10(hi)).map(lambda v: 10.0**v)


def _check(run, tol):
    """One stress case: either the clear one-line SimulationError of a failed integration, or
    finite results whose energy balance closes to what the tolerance promises.

    The runs here switch the simulator's own energy audit off (``energy_tol = inf``), so the
    balance is checked independently: a dynamics or energy-accounting bug (a wrong sign in a
    dissipated power, a force missing from one body) leaves a residual far above the bound.
    At the loosest tolerance (1e-3) the balance is not promised (it is the case the audit
    exists for), only finiteness.
    """
    try:
        r = run()
    except SimulationError as exc:
        msg = str(exc)
        assert msg.startswith("integration failed between t = "), msg
        assert "remedy: " in msg, msg
        assert "\n" not in msg, msg
        return "error"
    assert np.all(np.isfinite(r.outputs))
    assert np.all(np.isfinite(r.states))
    e = energy_balance(r)
    if tol <= 1e-6:
        assert e["relative_residual"] < 1e-4, e
    return "ok"


#: The contact grid's cases: stiffness, exponent, damping and penetration of the thread contact,
#: the PI (or none), the load after the step (times the rated load) and the tolerance.
_CONTACT_CASES = dict(
    k=_log(1e3, 1e7),
    e=st.floats(1.0, 2.2),
    c=st.one_of(st.just(0.0), _log(1e-2, 500.0)),
    d=_log(1e-4, 1.0),
    kp=st.one_of(st.just(0.0), _log(1e-3, 1e3)),
    ki=st.one_of(st.just(0.0), _log(1e-2, 1e3)),
    final=st.floats(0.0, 10.0),
    tol=st.sampled_from([1e-3, 1e-6, 1e-8, 1e-10]),
)


def _contact_case(k, e, c, d, kp, ki, final, tol):
    plant = PLANT.with_params({
        "contact.stiffness_n_per_mm_e": k, "contact.exponent": e,
        "contact.damping_n_s_per_mm": c, "contact.penetration_mm": d,
    })
    pid = PID(kp, ki) if kp > 0 or ki > 0 else None
    s = SimSettings(rtol=tol, atol=tol, max_wall_s=60.0, energy_tol=math.inf)
    _check(lambda: simulate(plant, load=[(0.0, 500.0), (0.005, final * plant.rated_load_n)], duration=0.02,
                            controller=pid, energy=True, settings=s), tol)


@settings(max_examples=5, suppress_health_check=[HealthCheck.too_slow])
@given(**_CONTACT_CASES)
def test_compliant_contact_grid(k, e, c, d, kp, ki, final, tol):
    """The stress property on 5 cases of the grid (the default suite's guard; the 14-case study
    is test_compliant_contact_grid_study, marked slow)."""
    _contact_case(k, e, c, d, kp, ki, final, tol)


@pytest.mark.slow
@settings(max_examples=14, suppress_health_check=[HealthCheck.too_slow])
@given(**_CONTACT_CASES)
def test_compliant_contact_grid_study(k, e, c, d, kp, ki, final, tol):
    """The same property on 14 cases (the evidence study; the default suite runs 5)."""
    _contact_case(k, e, c, d, kp, ki, final, tol)


@settings(max_examples=6, suppress_health_check=[HealthCheck.too_slow])
@given(
    kp=_log(1e-3, 1e3),
    ki=st.one_of(st.just(0.0), _log(1e-2, 1e3)),
    final=st.floats(0.0, 10.0),
    horizon=st.floats(0.5, 10.0),
    tol=st.sampled_from([1e-3, 1e-6, 1e-8]),
)
def test_long_horizons_rigid(kp, ki, final, horizon, tol):
    s = SimSettings(rtol=tol, atol=tol, max_wall_s=60.0, energy_tol=math.inf)
    _check(lambda: simulate(PLANT, load=[(0.0, 500.0), (0.1, final * PLANT.rated_load_n)], duration=horizon, dt=1e-3,
                            controller=PID(kp, ki), fidelity="rigid", energy=True, settings=s), tol)


def test_loose_tolerance_that_breaks_the_energy_balance_is_reported():
    plant = PLANT.with_params({"contact.stiffness_n_per_mm_e": 1e3, "contact.exponent": 1.0,
                               "contact.damping_n_s_per_mm": 0.0, "contact.penetration_mm": 1.0})
    s = SimSettings(rtol=1e-3, atol=1e-3)
    with pytest.raises(SimulationError, match=r"untrustworthy integration between t = 0 s and t = 0\.02 s .*energy balance residual.*remedy: tighten rtol/atol \(now 0\.001/0\.001\)"):
        simulate(plant, load=[(0.0, 500.0), (0.005, 0.0)], duration=0.02, energy=True, settings=s)
    # Tighter tolerance: the same case closes.
    r = simulate(plant, load=[(0.0, 500.0), (0.005, 0.0)], duration=0.02, energy=True,
                 settings=SimSettings(rtol=1e-8, atol=1e-8))
    assert energy_balance(r)["relative_residual"] < 1e-6


class _FakeClock:
    """A clock that advances one second each time it is read: the budget is hit after a
    known number of checks, whatever the machine's speed."""

    def __init__(self) -> None:
        self.now = 0.0
        self.reads = 0

    def __call__(self) -> float:
        self.reads += 1
        self.now += 1.0
        return self.now


@pytest.mark.parametrize("discrete", [False, True])
def test_wall_time_budget_raises_instead_of_hanging(discrete):
    """With a 3.5 s budget on a clock that ticks 1 s per read, the run stops at its fourth
    budget check (between integration chunks of at most 0.1 s of simulated time) and says
    where, long before the end of the 1 s run."""
    clock = _FakeClock()
    s = SimSettings(max_wall_s=3.5, clock=clock)
    with pytest.raises(SimulationError, match=r"run stopped at t = 0\.[0-3]\d* s: wall-time budget max_wall_s = 3\.5 s "
                                              r"used up after 4 s \(state \[theta_nut=.*remedy: raise max_wall_s"):
        simulate(PLANT, load=[(0.0, 500.0), (0.01, 1500.0)], duration=1.0, controller=PID(0.085, 14.7), settings=s,
                 fidelity="rigid", discrete=discrete)
    assert clock.reads == 5  # the start, then four checks (the last one fails)


def test_extreme_stiffness_linearises_with_finite_jacobians():
    from prsa_ctrl import linearize

    for k in (1e3, 1e7):
        for e in (1.0, 2.2):
            P = linearize(PLANT.with_params({"contact.stiffness_n_per_mm_e": k, "contact.exponent": e}), 31.4, 1000.0)
            assert np.all(np.isfinite(P.A))
