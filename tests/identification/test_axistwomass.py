"""The two-mass linear axis's replay (prsa_ctrl.identification.axistwomass, through
identification.axis.simulate_axis) against an independent event-driven integration written here
(scipy's solve_ivp on the positions of both masses), and the linear-axis fit on a two-mass base."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from prsa_ctrl.identification.axis import LinearAxisPlant, fit_linear_axis, replay_axis, simulate_axis
from prsa_ctrl.identification.axistwomass import TwoMassStepper
from prsa_ctrl.identification.logformat import AxisLog, ControllerSpec

from axis_generator import profile  # tests/identification is on sys.path

THETA = (90.0, 160.0, 230.0, 18.0, 24.0)  # M kg, Fv+ Fv- N s/m, Fc+ Fc- N
ML, K, ZETA = 30.0, 1.5e6, 0.05  # load mass kg, N/m, modal damping (mode ~43 Hz, anti-resonance ~36 Hz)
H = 1e-3


def _independent(force, load, x0=0.0):
    """Motor-side positions at the sample instants: both masses' positions and speeds integrated by
    solve_ivp phase by phase (moving +x, moving -x, motor side stuck), phase changes by its events."""
    m, fvp, fvn, fcp, fcn = THETA
    mm = m - ML
    c = 2 * ZETA * math.sqrt(K * mm * ML / m)
    y = np.array([x0, 0.0, x0, 0.0])  # x_m, v_m, x_l, v_l
    out = []

    def net(y, f):
        return f - K * (y[0] - y[2]) - c * (y[1] - y[3])

    for f, fe in zip(force, load):
        out.append(y[0])
        t, s = 0.0, None
        for _ in range(20):
            if t >= H * (1 - 1e-12):
                break
            if s is None:
                s = 1 if y[1] > 0 else (-1 if y[1] < 0 else (1 if net(y, f) > fcp else (-1 if net(y, f) < -fcn else 0)))

            def rhs(_, z, s=s):
                spring = K * (z[0] - z[2]) + c * (z[1] - z[3])
                al = (spring + fe) / ML
                if s == 0:
                    return [0.0, 0.0, z[3], al]
                fric = fcp + fvp * z[1] if s > 0 else -fcn + fvn * z[1]
                return [z[1], (f - spring - fric) / mm, z[3], al]

            if s == 0:
                y[1] = 0.0
                ev = [lambda _, z: net(z, f) - fcp, lambda _, z: net(z, f) + fcn]
                ev[0].direction, ev[1].direction = 1, -1
            else:
                ev = [lambda _, z, s=s: s * z[1] + 1e-13]  # stops when the speed turns (not at a start from rest)
                ev[0].direction = -1
            for e in ev:
                e.terminal = True
            sol = solve_ivp(rhs, (t, H), y, method="DOP853", rtol=1e-12, atol=1e-15, events=ev)
            y = sol.y[:, -1].copy()
            t = sol.t[-1]
            if sol.status != 1:
                break
            if s == 0:  # broke away, in the direction of the event
                s = 1 if len(sol.t_events[0]) else -1
            else:  # the motor side stops: stuck, or on in the other direction
                y[1] = 0.0
                s = 1 if net(y, f) > fcp else (-1 if net(y, f) < -fcn else 0)
    return np.array(out)


def _log(n, command, reference=None, controller=None, load=None):
    return AxisLog(name="two-mass", time_s=np.arange(n) * H, position_m=np.zeros(n), command=np.asarray(command, float),
                   command_unit="N", gain_n_per_unit=1.0, sample_time_s=H, reference_m=reference, controller=controller,
                   load_n=load, command_logged="as-applied")


def test_the_replay_matches_an_independent_event_driven_integration():
    """A force that drives the axis back and forth through reversals and stick phases (Coulomb 18/24
    N against a 40 N sine with a 15 N offset), an external load on the load mass: the exact
    piecewise solution and solve_ivp with events agree on the motor side's position."""
    n = 700
    t = np.arange(n) * H
    force = 15.0 + 40.0 * np.sin(2 * math.pi * 3.0 * t) + 10.0 * np.sin(2 * math.pi * 41.0 * t)
    load = -5.0 * (t > 0.3)
    tr = simulate_axis(THETA, _log(n, force, load=load), closed_loop=False, second_mass=(ML, K, ZETA))
    ref = _independent(force, load)
    assert np.ptp(ref) > 1e-3
    assert np.any(np.diff(np.sign(np.diff(ref))) != 0)  # it moves and reverses
    assert np.max(np.abs(tr.position_m - ref)) < 1e-10 * np.ptp(ref)  # measured 1e-13
    # the rigid replay of the same force differs by far more: the second mass is in the replay
    rigid = simulate_axis(THETA, _log(n, force, load=load), closed_loop=False)
    assert np.max(np.abs(rigid.position_m - ref)) > 1e3 * np.max(np.abs(tr.position_m - ref))


def test_the_stepper_refuses_a_load_mass_not_below_the_axis_mass():
    with pytest.raises(ValueError, match="expected 0 < load mass < the axis's mass"):
        TwoMassStepper(THETA, 95.0, K, ZETA, H)
    with pytest.raises(ValueError, match="stiffness > 0"):
        TwoMassStepper(THETA, ML, -1.0, ZETA, H)


def _closed_loop_log(seed=3, n=3000):
    rng = np.random.default_rng(seed)
    ref = profile(rng, n)
    ctrl = ControllerSpec(structure="position-p/velocity-p", kp=60.0, kv=900.0, ki=0.0,
                          velocity_estimate="average2-difference", saturation=400.0, sample_time_s=H,
                          command_delay_samples=0, check_tolerance=0.03, sources={})
    log = _log(n, np.zeros(n), reference=ref, controller=ctrl)
    tr = simulate_axis(THETA, log, second_mass=(ML, K, ZETA))
    return dataclasses.replace(log, position_m=tr.position_m, command=tr.command)


def _base(second: bool) -> LinearAxisPlant:
    vals = {"axis.mass_kg": 70.0, "friction.viscous_positive_n_s_per_m": 100.0,
            "friction.viscous_negative_n_s_per_m": 100.0, "friction.coulomb_positive_n": 10.0,
            "friction.coulomb_negative_n": 10.0, "drive.gain_n_per_unit": 1.0, "drive.force_limit_n": 1e4,
            "sensor.sample_time_s": H, "sensor.encoder_resolution_m": 1e-9}
    if second:
        vals.update({"axis.load_mass_kg": ML, "axis.load_stiffness_n_per_um": K * 1e-6, "axis.axial_damping_ratio": ZETA})
    return LinearAxisPlant("base", vals, {k: "test" for k in vals}, command_unit="N")


@pytest.mark.slow
def test_a_two_mass_base_is_fitted_on_its_two_mass_replay():
    """A closed-loop log of the two-mass axis (its own exact replay: a round trip): the fit on a base
    carrying the second mass recovers M and the friction, and its plant replays the log exactly;
    the rigid base's fit on the same log is left with a residual the second mass explains."""
    log = _closed_loop_log()
    two = fit_linear_axis([log], _base(True), check_delay=False)
    for j, x in enumerate(THETA):
        assert two.plant.theta[j] == pytest.approx(x, rel=1e-4)
    assert two.plant.second_mass == pytest.approx((ML, K, ZETA))
    assert "two-mass axis" in two.plant.description
    rep = replay_axis(two.plant, log)
    assert rep.errors_percent["position"] < 1e-6
    assert rep.report()["replay"] == f"closed loop from the reference, two-mass axis (30 kg beyond {K * 1e-6:g} N/um, damping 0.05)"
    rigid = fit_linear_axis([log], _base(False), check_delay=False)
    assert replay_axis(rigid.plant, log).errors_percent["force"] > 1e3 * replay_axis(two.plant, log).errors_percent["force"]
