"""Batched sampled-loop runs (prsa_ctrl.sim.batch) against the per-sample simulator."""

import warnings

import numpy as np
import pytest

from prsa_ctrl.drive.pid import PID
from prsa_ctrl.errors import GeometryWarning
from prsa_ctrl.plant.equilibrium import operating_point
from prsa_ctrl.plant.model import parametric_family, register_member
from prsa_ctrl.plant.plantfile import load_plant
from prsa_ctrl.plant.uncertainty import apply, uncertainty_model
from prsa_ctrl.sim.batch import batch_supported, load_step_metrics_batch, simulate_batch, steady_states
from prsa_ctrl.sim.engine import run
from prsa_ctrl.sim.integrators import SimSettings
from prsa_ctrl.sim.metrics import load_step_metrics
from prsa_ctrl.studies.scene import load_scene

PID_PAPER = PID(0.0849, 14.67)
W0 = 31.41592653589793
FIXED = SimSettings(integrator="radau", stages=2, substeps=4)  # interpreted: no compiler in the test
KEYS_SCENE = "paper-load-step"


@pytest.fixture(scope="module")
def family():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeometryWarning)
        plant = load_plant()
    unc = uncertainty_model(plant, load_scene(KEYS_SCENE).sections.plant_overrides)
    fam = parametric_family(plant, "compliant", unc.keys)
    rng = np.random.default_rng(5)
    values = [unc.sample(rng) for _ in range(4)]
    # the corners of the box too: the stiffest and softest contact, the extreme inertias
    values += [{e.key: getattr(e, end) for e in unc.entries} for end in ("low", "high")]
    thetas = np.array([[v.get(k, plant.values[k]) for k in fam.keys] for v in values])
    return plant, unc, fam, values, thetas


def _member(plant, unc, values):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeometryWarning)
        p = apply(plant, values)
    register_member(p, plant, unc.keys)
    return p


def test_family_is_in_scope(family):
    _, _, fam, _, _ = family
    assert batch_supported(fam, PID_PAPER) is None
    assert "integral" in batch_supported(fam, PID(0.1, 0.0))
    assert "estimator" in batch_supported(fam, PID_PAPER, "kf")
    assert batch_supported(None, PID_PAPER) is not None


def test_steady_states_equal_the_per_sample_operating_points(family):
    plant, unc, fam, values, thetas = family
    x, tau, ok = steady_states(fam, thetas, W0, 500.0)
    assert ok.all()
    for i, v in enumerate(values):
        op = operating_point(_member(plant, unc, v), W0, 500.0, "compliant")
        assert np.allclose(x[i], op.x, rtol=1e-9, atol=1e-12)
        assert tau[i] == pytest.approx(op.torque, rel=1e-9)
    # the samples differ: a batch that ignored theta would give equal rows
    assert np.ptp(tau) > 1e-3


def test_batched_run_equals_the_per_sample_runs(family):
    plant, unc, fam, values, thetas = family
    pre, dur = 0.002, 0.03
    br = simulate_batch(fam, thetas, PID_PAPER, W0, 500.0, 1500.0, pre, dur, FIXED)
    assert br.ok.all()
    assert br.nut_speed.shape == (len(values), br.time.size)
    for i, v in enumerate(values):
        r = run(_member(plant, unc, v), setpoint=W0, load=[(0.0, 500.0), (pre, 1500.0)], duration=dur,
                controller=PID_PAPER, fidelity="compliant", discrete=True, settings=FIXED)
        assert np.array_equal(r.time, br.time)
        w = r.output("nut_speed")
        drop = np.max(np.abs(w - w[0]))
        assert drop > 1.0  # the step did something
        # same arithmetic (theta as parameters instead of constant states): rounding level
        assert np.max(np.abs(br.nut_speed[i] - w)) <= 1e-9 * drop
        assert np.max(np.abs(br.motor_torque[i] - r.output("motor_torque"))) <= 1e-9
    assert np.ptp(br.nut_speed.min(axis=1)) > 1e-3  # the samples' responses differ


def test_a_shared_jacobian_is_the_per_sample_scheme_and_changes_the_run(family):
    """``jacobian_every`` (the batched Monte Carlo refreshes the Jacobian four times per controller
    sample): the batched run equals the per-sample simulator with the same settings, and
    differs from the refresh at every substep (the setting is not ignored) by less than the
    paper scene's accuracy (1 % of the deviation)."""
    plant, unc, fam, values, thetas = family
    pre, dur = 0.002, 0.03
    shared = SimSettings(integrator="radau", stages=2, substeps=4, jacobian_every=2)
    a = simulate_batch(fam, thetas, PID_PAPER, W0, 500.0, 1500.0, pre, dur, shared)
    b = simulate_batch(fam, thetas, PID_PAPER, W0, 500.0, 1500.0, pre, dur, FIXED)
    drop = np.max(np.abs(b.nut_speed - b.nut_speed[:, :1]))
    for i in (0, len(values) - 1):
        r = run(_member(plant, unc, values[i]), setpoint=W0, load=[(0.0, 500.0), (pre, 1500.0)], duration=dur,
                controller=PID_PAPER, fidelity="compliant", discrete=True, settings=shared)
        assert np.max(np.abs(a.nut_speed[i] - r.output("nut_speed"))) <= 1e-9 * drop
    diff = np.max(np.abs(a.nut_speed - b.nut_speed))
    assert 1e-7 * drop < diff < 0.01 * drop


def test_compiled_run_with_a_command_delay_equals_the_numpy_law(family):
    """The generated C law's delay line (a ring buffer) against the numpy law's list, with a
    drive command delay of 2 samples, on 9 samples (a full and a padded block of lanes)."""
    from prsa_ctrl.sim import batch

    plant, unc, _, _, thetas = family
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeometryWarning)
        delayed = apply(plant, {"drive.command_delay_samples": 2})
    fam = parametric_family(delayed, "compliant", unc.keys)
    assert fam.plant.command_delay_samples == 2
    th = np.vstack([thetas, thetas[:3] * [1.01, 1.0, 0.99, 1.02, 1.0]])[:9]
    jit = SimSettings(integrator="radau", stages=2, substeps=4, jacobian_every=2, jit=True)
    if batch.lane_function(fam, jit) is None:
        pytest.skip("no C compiler")
    interp = SimSettings(integrator="radau", stages=2, substeps=4, jacobian_every=2)
    a = simulate_batch(fam, th, PID_PAPER, W0, 500.0, 1500.0, 0.002, 0.02, jit)
    b = simulate_batch(fam, th, PID_PAPER, W0, 500.0, 1500.0, 0.002, 0.02, interp)
    assert a.ok.all()
    assert b.ok.all()
    drop = np.max(np.abs(b.nut_speed - b.nut_speed[:, :1]))
    assert np.max(np.abs(a.nut_speed - b.nut_speed)) <= 1e-9 * drop
    assert np.max(np.abs(a.motor_torque - b.motor_torque)) <= 1e-9
    # the delay acts: the same samples without it respond otherwise
    c = simulate_batch(parametric_family(plant, "compliant", unc.keys), th, PID_PAPER, W0, 500.0, 1500.0, 0.002,
                       0.02, jit)
    assert np.max(np.abs(c.nut_speed - a.nut_speed)) > 1e-3 * drop


def test_batched_metrics_equal_the_per_sample_metrics(family):
    rng = np.random.default_rng(0)
    t = np.linspace(0.0, 0.05, 201)
    y = 31.4 - np.where(t >= 0.01, 3.0 * rng.uniform(0.5, 1.5, (5, 1)) * (t - 0.01) * 100 * np.exp(-(t - 0.01) * 100), 0.0)
    y[3] += 0.2 * np.where(t > 0.04, 1.0, 0.0)  # one that does not recover
    tq = 0.2 + rng.uniform(0, 3.5, (5, t.size))
    got = load_step_metrics_batch(t, y, 31.4, 0.01, tq, 3.0, 1)
    for i in range(5):
        ref = load_step_metrics(t, y[i], 31.4, 0.01, tq[i], 3.0, direction=1)
        for k, v in got.items():
            assert float(v[i]) == float(getattr(ref, k)), k  # the same numbers, not just close


def test_bad_batch_input_is_refused(family):
    _, _, fam, _, thetas = family
    with pytest.raises(ValueError, match="thetas"):
        simulate_batch(fam, thetas[:, :2], PID_PAPER, W0, 500.0, 1500.0, 0.002, 0.01, FIXED)
    with pytest.raises(ValueError, match="radau"):
        simulate_batch(fam, thetas, PID_PAPER, W0, 500.0, 1500.0, 0.002, 0.01, SimSettings())
    with pytest.raises(ValueError, match="step_at"):
        simulate_batch(fam, thetas, PID_PAPER, W0, 500.0, 1500.0, 0.0021, 0.01, FIXED)
    bad = thetas.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="finite"):
        simulate_batch(fam, bad, PID_PAPER, W0, 500.0, 1500.0, 0.002, 0.01, FIXED)


def test_a_sample_without_steady_state_is_flagged_not_nan_silently(family):
    plant, unc, fam, values, thetas = family
    # a load the motor cannot hold: every sample is flagged (the per-sample path says why)
    x, tau, ok = steady_states(fam, thetas, W0, 1e6)
    assert not ok.any()


def test_compiled_lanes_equal_the_mapped_casadi_step(family):
    """The lane-parallel C step (jit, the Monte Carlo's default) against the interpreted CasADi
    step mapped over the batch: 9 samples, so a block of 8 lanes and a padded one."""
    from prsa_ctrl.sim import batch

    _, _, fam, _, thetas = family
    th = np.vstack([thetas, thetas[:3] * [1.01, 1.0, 0.99, 1.02, 1.0]])[:9]
    jit = SimSettings(integrator="radau", stages=2, substeps=4, jit=True)
    if batch.lane_function(fam, jit) is None:
        pytest.skip("no C compiler")
    a = simulate_batch(fam, th, PID_PAPER, W0, 500.0, 1500.0, 0.002, 0.02, jit)
    b = simulate_batch(fam, th, PID_PAPER, W0, 500.0, 1500.0, 0.002, 0.02, FIXED)
    assert a.ok.all()
    assert b.ok.all()
    drop = np.max(np.abs(b.nut_speed - b.nut_speed[:, :1]))
    assert np.max(np.abs(a.nut_speed - b.nut_speed)) <= 1e-9 * drop
    assert np.max(np.abs(a.motor_torque - b.motor_torque)) <= 1e-9


def test_an_empty_batch_is_refused(family):
    _, _, fam, _, thetas = family
    with pytest.raises(ValueError, match="thetas"):
        simulate_batch(fam, thetas[:0], PID_PAPER, W0, 500.0, 1500.0, 0.002, 0.01, FIXED)


def test_a_batched_run_is_read_only(family):
    _, _, fam, _, thetas = family
    br = simulate_batch(fam, thetas[:2], PID_PAPER, W0, 500.0, 1500.0, 0.002, 0.005, FIXED)
    with pytest.raises(ValueError):
        br.nut_speed[0, 0] = 0.0
