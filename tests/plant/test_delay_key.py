"""The plant key ``drive.command_delay_samples`` (issue 21, section 2): its default and source,
its checks, and that the simulator, the drive loop model and the tuner use it, each against an
independent computation (numpy/scipy only)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.linalg import expm

from prsa_ctrl.drive.measurement import PositionLoop
from prsa_ctrl.drive.motion import trapezoidal
from prsa_ctrl.drive.pid import PID
from prsa_ctrl.errors import PlantFileError
from prsa_ctrl.plant import describe_plant, load_plant
from prsa_ctrl.plant.linear import linearize
from prsa_ctrl.sim.engine import run
from prsa_ctrl.tuning import drive_loop, tune_loops

KEY = "drive.command_delay_samples"


@pytest.fixture(scope="module")
def plant():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_plant()


def test_default_source_and_show(plant):
    assert plant.values[KEY] == 0 and plant.command_delay_samples == 0  # the paper plant gives it
    assert plant.sources[KEY].startswith("assumption:")
    ball = load_plant("ballscrew-32x10")  # a catalogue plant that leaves it out
    assert ball.values[KEY] == 0 and not ball.given(KEY)
    assert ball.sources[KEY].startswith("default:") and "computation delay" in ball.sources[KEY]
    line = next(ln for ln in describe_plant(ball).splitlines() if KEY in ln)
    assert " 0 samples" in line and "default" in line
    assert plant.with_params({KEY: 2}).command_delay_samples == 2


@pytest.mark.parametrize("bad", [-1, 1.5, 21, True, "2"])
def test_bad_values_refused(plant, bad):
    with pytest.raises(PlantFileError, match=KEY):
        plant.with_params({KEY: bad})


@pytest.mark.parametrize("nd", [1, 2])
def test_simulator_shift_exactly_n_samples(plant, nd):
    """Open loop (a position loop whose only action is the acceleration feed-forward, a speed PI
    of negligible gain): with nd samples of command delay every torque is the delay-free run's,
    nd samples later (the plant starts at rest, so the runs are time shifts of each other)."""
    runs = {}
    for n in (0, nd):
        p = plant.with_params({KEY: n})
        runs[n] = run(p, setpoint=0.0, load=0.0, duration=0.04, controller=PID(0.0, 1e-12), fidelity="rigid",
                      discrete=True, position=PositionLoop(kv=1e-6, kvff=0.0, kaff=1.0),
                      motion=trapezoidal(0.001, 0.04, 2.0))
    # the controller's output (the logged command, convention "applied") is the same in both runs
    np.testing.assert_allclose(runs[nd].output("torque_command"), runs[0].output("torque_command"), rtol=0, atol=1e-9)
    for label in ("motor_torque", "nut_speed"):
        y0, y2 = runs[0].output(label), runs[nd].output(label)
        scale = float(np.max(np.abs(y0)))
        assert scale > 0.01
        assert np.max(np.abs(y2[nd:] - y0[:-nd])) < 1e-9 * scale, label
        if label != "nut_speed":  # a torque step: a shift by one sample less would be seen
            assert np.max(np.abs(y2[nd - 1:] - y0[:len(y0) - nd + 1])) > 0.05 * scale, label


def test_simulator_closed_loop_sampled_runs(plant):
    """A closed-loop sampled run (the shared, chunked law) with 1 sample of delay runs and is
    slower to reject a load step than without (the delay costs phase)."""
    peak = {}
    for n in (0, 1):
        r = run(plant.with_params({KEY: n}), setpoint=30.0, load=[(0.0, 200.0), (0.01, 2500.0)], duration=0.06,
                controller=PID(0.05, 2.0), fidelity="rigid", discrete=True)
        w = r.output("nut_speed")
        peak[n] = float(30.0 - np.min(w))
    assert peak[1] > peak[0] > 0


# --- the loop model, against an independent sampled loop ----------------------------------
J, TC, TS, TF_SPEED = 2e-3, 1.6e-4, 2.5e-4, 2e-4  # kg m^2, s, s, s


def _plant_ab():
    """Inertia with a first-order current loop; states (tau, omega, theta), inputs (command, load torque)."""
    a = np.array([[-1 / TC, 0.0, 0.0], [1 / J, 0.0, 0.0], [0.0, 1.0, 0.0]])
    b = np.array([[1 / TC, 0.0], [0.0, -1 / J], [0.0, 0.0]])
    return a, b


def _loop(n):
    a, b = _plant_ab()
    return drive_loop(a, b, np.array([0.0, 1.0, 0.0]), 2, ts=TS, speed_filter=TF_SPEED, tf=4 * TS, horizon=0.05,
                      step=1.0, command_delay_samples=n)


def _independent_l(kp, ki, n, w):
    """L(e^{jwT}) of the sampled speed loop written out here: ZOH plant (scipy expm), backward
    difference and first-order filter on the angle, PI ``u = kp e + I, I += T ki e``, one
    computation delay and n command-delay samples."""
    a, b = _plant_ab()
    m = np.zeros((4, 4))
    m[:3, :3], m[:3, 3] = a * TS, b[:, 0] * TS
    e = expm(m)
    ad, bd = e[:3, :3], e[:3, 3]
    z = np.exp(1j * w * TS)
    p = np.array([np.array([0, 0, 1.0]) @ np.linalg.solve(zk * np.eye(3) - ad, bd) for zk in z])
    al = np.exp(-TS / TF_SPEED)
    meas = (1 - 1 / z) / TS * (1 - al) / (1 - al / z)
    c = kp + ki * TS / z / (1 - 1 / z)
    return c * meas * z ** (-(1 + n)) * p


def _independent_error(kp, ki, n, steps):
    """The load-step response (1 N m at k = 0) of the same loop, simulated sample by sample."""
    a, b = _plant_ab()
    m = np.zeros((5, 5))
    m[:3, :3], m[:3, 3:] = a * TS, b * TS
    e = expm(m)
    ad, bu, bl = e[:3, :3], e[:3, 3], e[:3, 4]
    al = np.exp(-TS / TF_SPEED)
    x, th_prev, wf, integ = np.zeros(3), 0.0, 0.0, 0.0
    line = [0.0] * (n + 1)  # computation delay + n command-delay samples
    out = []
    for _ in range(steps):
        wf = al * wf + (1 - al) * (x[2] - th_prev) / TS
        th_prev = x[2]
        err = -wf
        u = kp * err + integ
        integ += TS * ki * err
        x = ad @ x + bu * line[0] + bl * 1.0
        line = line[1:] + [u]
        out.append(x[1])
    return -np.array(out)


def test_loop_frequency_response_has_the_delay():
    w = np.geomspace(10.0, 0.99 * np.pi / TS, 200)
    for n in (0, 2):
        lp = _loop(n)
        _, parts, _, _ = lp.response(w)
        l_model = 0.3 * parts[0] + 40.0 * parts[1]
        np.testing.assert_allclose(l_model, _independent_l(0.3, 40.0, n, w), rtol=1e-7, atol=1e-12)
    l0 = _loop(0).response(w)[1]
    l2 = _loop(2).response(w)[1]
    np.testing.assert_allclose(l2, l0 * np.exp(-2j * w * TS)[None, :], rtol=1e-12, atol=1e-15)


def test_loop_time_response_has_the_delay():
    lp = _loop(2)
    err = lp.error((0.3, 40.0, 0.0))
    ref = _independent_error(0.3, 40.0, 2, len(err) + 2)
    # LoopModel's e[k] is the speed error at sample k (e[0] = 0 before the step acts)
    scale = float(np.max(np.abs(ref)))
    assert scale > 0
    np.testing.assert_allclose(err[1:], ref[: len(err) - 1], rtol=0, atol=1e-9 * scale)
    # the delay-free model differs from this response (so the comparison can fail)
    assert np.max(np.abs(_loop(0).error((0.3, 40.0, 0.0))[1:] - ref[: len(err) - 1])) > 0.01 * scale


def test_tuner_ms_on_the_delayed_loop():
    lp = _loop(2)
    res = tune_loops([lp], objective="iae", controller="pi", ms_max=1.5)
    kp, ki = res.pid.kp, res.pid.ki
    w = np.geomspace(1.0, np.pi / TS * (1 - 1e-9), 200_001)
    ms2 = float(np.max(np.abs(1 / (1 + _independent_l(kp, ki, 2, w)))))
    ms0 = float(np.max(np.abs(1 / (1 + _independent_l(kp, ki, 0, w)))))
    assert res.margins[0].ms == pytest.approx(ms2, rel=2e-4)
    assert ms2 <= 1.5 * (1 + 1e-3)
    assert abs(ms0 - ms2) > 0.05  # the delay matters for these gains: ignoring it would be seen


def test_linearize_carries_the_delay(plant):
    """The continuous linear model's command delay (Pade) is (1.5 + n) Ts: its phase at a low
    frequency falls by n Ts w more than without the key."""
    w = 2 * np.pi * 20.0
    ph = {}
    for n in (0, 3):
        sys = linearize(plant.with_params({KEY: n}), omega_nut=30.0, load=1000.0, fidelity="rigid", sampled=True)
        ph[n] = np.angle(complex(sys(1j * w)[0, 0])) if sys.noutputs > 1 else np.angle(complex(sys(1j * w)))
    d = np.angle(np.exp(1j * (ph[3] - ph[0])))
    assert d == pytest.approx(-3 * plant.sample_time_s * w, rel=1e-3)


def test_export_states_the_delay(plant):
    from prsa_ctrl.io.export import export_controller

    for n in (0, 2):
        out = export_controller(PID(0.05, 2.0), plant.with_params({KEY: n}), fmt="json")
        assert out["command_delay_samples"] == n and "drive.command_delay_samples" in out["command_delay_note"]


def test_cascade_model_carries_the_delay(plant):
    """The cascade tuner's model: its speed loop equals the drive loop with the same delay (which
    the tests above check independently), and its time-domain closed loop has the delay line."""
    import dataclasses

    from prsa_ctrl.plant.model import plant_model
    from prsa_ctrl.plant.linear import linear_core
    from prsa_ctrl.studies.movescene import load_move_scene
    from prsa_ctrl.tuning.cascade import CascadeModel

    sc = dataclasses.replace(load_move_scene("paper-move"), fidelity="rigid")
    g = [0.0809, 13.56, 40.0, 0.0, 1.0, 1.0]
    w = np.geomspace(1.0, 1e4, 50)
    models = {}
    for n in (0, 2):
        p = plant.with_params({KEY: n})
        cm = CascadeModel(p, sc.cascade_spec())
        model = plant_model(p, "rigid")
        a, b, c, _, _ = linear_core(p, cm.w_lin, sc.load_n, "rigid")
        lp = drive_loop(a, b, c[model.output_names.index("nut_speed")], model.index("theta_nut"), ts=p.sample_time_s,
                        speed_filter=p.speed_filter_s, tf=1e-3, horizon=0.05, step=100.0, command_delay_samples=n)
        np.testing.assert_allclose(cm.loops(g, w)["speed_open"], lp.loop_response(g[:2] + [0.0], w), rtol=1e-9)
        models[n] = cm
    assert models[2].nX == models[0].nX + 2
    e0, e2 = models[0].error(g, "move"), models[2].error(g, "move")
    assert np.all(np.isfinite(e2)) and np.max(np.abs(e2 - e0)) > 1e-3 * np.max(np.abs(e0))
