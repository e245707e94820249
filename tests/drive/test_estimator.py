"""Kalman filter (filterpy) speed/load estimation and load feed-forward."""

import sys

import numpy as np
import pytest
from scipy.stats import chi2

from prsa_ctrl import PID, load_plant
from prsa_ctrl.drive.estimator import design_kf
from prsa_ctrl.tuning.actuatorloops import kf_drive_loop
from prsa_ctrl.plant.linear import linear_core
from prsa_ctrl.plant.model import plant_model
from prsa_ctrl.sim.integrators import SimSettings
from prsa_ctrl.sim.engine import run
from prsa_ctrl.tuning.builders import drive_loop
from prsa_ctrl.tuning.generic import tune_loops

PLANT = load_plant()
SETTINGS = SimSettings(rtol=1e-6, atol=1e-6)
W0 = 31.4159


def test_steady_state_gain_matches_filterpy_recursion():
    kf = design_kf(PLANT)
    f = kf.make_filter(np.zeros(4))
    f.P = np.diag([1e-6, 1.0, 1.0, 1.0])
    for _ in range(3000):
        f.update(np.array([[0.0]]))
        f.predict(u=np.array([[0.0]]))
    np.testing.assert_allclose(f.P, kf.P, rtol=1e-6, atol=1e-14)


def test_noise_covariances_come_from_the_sensor_model():
    kf = design_kf(PLANT)
    q = 2 * np.pi / PLANT.encoder_counts
    assert kf.R == pytest.approx(q * q / 12)
    coarse = design_kf(PLANT.with_params({"sensor.encoder_counts_per_rev": 2**14}))
    assert coarse.R == pytest.approx(kf.R * (2**20 / 2**14) ** 2)
    assert coarse.K[1, 0] < kf.K[1, 0]  # a coarser encoder is trusted less
    with pytest.raises(ValueError, match=r"load_change_time_s = -1; expected a positive time in s"):
        design_kf(PLANT, -1)


def test_filter_consistency_nees_in_its_band():
    """Linear plant, the filter's own noise model, seeded: the normalised estimation error of
    the angle-speed pair stays within its chi-square band."""
    kf = design_kf(PLANT)
    rng = np.random.default_rng(7)
    f = kf.make_filter(np.zeros(4))
    x = np.zeros(4)
    lam, vec = np.linalg.eigh(kf.Q)
    L = vec * np.sqrt(np.clip(lam, 0.0, None))  # Q is rank-deficient: sample through its eigenbasis
    nees = []
    for k in range(3000):
        z = x[0] + rng.normal(0.0, np.sqrt(kf.R))
        f.update(np.array([[z]]))
        if k > 200:
            e = (x - f.x.ravel())[:2]
            nees.append(float(e @ np.linalg.solve(f.P[:2, :2], e)))
        u = 0.3 * np.sin(k / 50.0)
        f.predict(u=np.array([[u]]))
        x = kf.F @ x + kf.G.ravel() * u + L @ rng.normal(size=4)
    mean = np.mean(nees)
    lo, hi = chi2.ppf([0.005, 0.995], 2 * len(nees)) / len(nees)
    assert lo < mean < hi, (mean, lo, hi)


def test_feedforward_sign_and_units():
    """At steady state the load estimate equals the motor torque (N m) that holds the load, and
    feeding it forward with kff = 1 leaves the integrator with nothing to hold."""
    pid = PID(0.1, 20.0, kff=1.0)
    r = run(PLANT, setpoint=W0, load=[(0.0, 500.0), (0.002, 1500.0)], duration=0.15, controller=pid,
            settings=SETTINGS, discrete=True, measurement="kf", torque_noise=True)
    tl = r.output("load_torque_estimate")
    tau = r.output("motor_torque")
    late = r.time > 0.12
    assert np.mean(tl[late]) == pytest.approx(np.mean(tau[late]), rel=0.02)
    assert np.mean(tl[late]) > np.mean(tl[r.time < 0.002]) > 0  # more load, larger positive estimate
    # The integrator holds only what the feed-forward misses (a wrong kff sign would leave it
    # holding twice the load torque, ~0.9 N m).
    integral = r.states[r.state_labels.index("pid_integral")]
    assert abs(np.mean(integral[late])) < 0.02 * np.mean(tau[late])


def test_feedforward_cuts_the_verified_drop_by_30_percent_at_the_same_ms():
    a, b, c, _, _ = linear_core(PLANT, W0, 1000.0, "compliant")
    m = plant_model(PLANT, "compliant")
    cs = c[m.output_names.index("nut_speed")]
    plain = drive_loop(a, b, cs, m.index("theta_nut"), ts=PLANT.sample_time_s, speed_filter=PLANT.speed_filter_s,
                       tf=1e-3, horizon=0.3, step=1000.0)
    kf = design_kf(PLANT)
    ff = kf_drive_loop(a, b, cs, m.index("theta_nut"), kf, tf=1e-3, horizon=0.3, step=1000.0, feedforward=True)
    pi = tune_loops([plain], ms_max=1.4).pid
    res = tune_loops([ff], ms_max=1.4)
    assert res.ms <= 1.4
    assert res.pid.kff > 0
    load = [(0.0, 500.0), (0.002, 1500.0)]
    from prsa_ctrl.sim.engine import run

    r_pi = run(PLANT, setpoint=W0, load=load, duration=0.1, controller=pi, discrete=True, settings=SETTINGS)
    r_ff = run(PLANT, setpoint=W0, load=load, duration=0.1, controller=res.pid, kf=kf, settings=SETTINGS,
               discrete=True, measurement="kf")
    drop_pi = W0 - r_pi.output("nut_speed").min()
    drop_ff = W0 - r_ff.output("nut_speed").min()
    assert drop_ff < 0.7 * drop_pi, (drop_ff, drop_pi)


def test_kf_speed_error_against_finite_differences_with_a_14_bit_encoder():
    """With a 14-bit encoder (16384 counts/rev) the filtered speed beats backward differences
    at the same 4 kHz rate by at least 5x in RMS over the paper step."""
    plant = PLANT.with_params({"sensor.encoder_counts_per_rev": 2**14})
    r = run(plant, setpoint=W0, load=[(0.0, 500.0), (0.002, 1500.0)], duration=0.202,
            controller=PID(0.085, 14.7), settings=SETTINGS, discrete=True, measurement="kf", torque_noise=True)
    w = r.output("nut_speed")
    kf_rms = np.sqrt(np.mean((r.output("speed_measured") - w) ** 2))
    fd_rms = np.sqrt(np.mean((r.output("speed_fd") - w) ** 2))
    assert fd_rms > 5 * kf_rms, (kf_rms, fd_rms)


def test_in_loop_filter_is_filterpys_filter():
    """The fixed-gain filter inside the sampled loop gives, sample by sample, what filterpy's
    own KalmanFilter gives on the same quantised angles and applied commands (started in its
    steady state, the recursion keeps the steady gain)."""
    kf = design_kf(PLANT)
    r = run(PLANT, setpoint=W0, load=[(0.0, 500.0), (0.002, 1500.0)], duration=0.03, controller=PID(0.085, 14.7),
            settings=SETTINGS, discrete=True, measurement="kf", torque_noise=True, fidelity="rigid")
    q = 2 * np.pi / PLANT.encoder_counts
    theta_q = np.floor(r.states[r.state_labels.index("theta_nut")] / q) * q
    u = r.output("torque_command")
    f = kf.make_filter(r.states[r.state_labels.index("kf_angle"):][:4, 0])
    speeds, loads = [], []
    for k in range(len(r.time)):
        f.update(np.array([[theta_q[k]]]))
        speeds.append(f.x[1, 0])
        loads.append(f.x[3, 0])
        f.predict(u=np.array([[u[k]]]))
    np.testing.assert_allclose(r.output("speed_measured"), speeds, rtol=0, atol=1e-9)
    np.testing.assert_allclose(r.output("load_torque_estimate"), loads, rtol=0, atol=1e-9)


def test_estimator_arguments():
    with pytest.raises(ValueError, match=r"measurement = 'ekf'; expected 'encoder', 'kf' or a SpeedMeasurement"):
        run(PLANT, setpoint=W0, load=500.0, duration=0.01, controller=PID(0.1, 1.0), discrete=True,
            measurement="ekf")
    with pytest.raises(ValueError, match=r"PID kff = 0\.5 needs a load-torque estimate"):
        run(PLANT, setpoint=W0, load=500.0, duration=0.01, controller=PID(0.1, 1.0, kff=0.5), discrete=True)


def test_filterpy_is_imported_only_with_an_estimator(tmp_path):
    import subprocess

    code = ("import sys, warnings; warnings.simplefilter('ignore');"
            "from prsa_ctrl.cli.tune import main; main(['--quiet', '--duration', '0.25']);"
            "print(sorted(m for m in ('filterpy', 'matplotlib', 'control', 'prsa_ctrl.plots.loop') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "[]"
