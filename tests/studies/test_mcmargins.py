"""Batched Ms/Mt of the Monte Carlo (prsa_ctrl.studies.mcmargins) against each sample's own loop model."""

import warnings

import numpy as np
import pytest
from scipy.linalg import expm

from prsa_ctrl.errors import GeometryWarning
from prsa_ctrl.plant.model import parametric_family, register_member
from prsa_ctrl.plant.plantfile import load_plant
from prsa_ctrl.plant.uncertainty import apply, uncertainty_model
from prsa_ctrl.studies import mcbatch, mcmargins
from prsa_ctrl.studies import montecarlo as mc
from prsa_ctrl.studies.mcjob import draw_sample
from prsa_ctrl.studies.scene import choose_fidelity, load_scene
from prsa_ctrl.studies.sceneloops import actuator_loops

#: Batched against per-sample Ms/Mt, relative: measured 9.4e-11 over 200 samples of
#: robust-load-step (the matrix exponential and the modal sum round differently from scipy's
#: expm and a solve per frequency; the polish converges to ~1e-12 of the peak either way).
RTOL = 1e-8


@pytest.fixture(scope="module")
def robust():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeometryWarning)
        plant = load_plant()
    scene = choose_fidelity(load_scene("robust-load-step"))[0]
    unc = uncertainty_model(plant, scene.sections.plant_overrides)
    return plant, scene, unc


def _pid(plant):
    from prsa_ctrl.studies.paper import default_pid

    return default_pid(plant)


def test_expm_stack_equals_scipy_on_stiff_and_plain_matrices(robust):
    plant, scene, _ = robust
    from prsa_ctrl.plant.linear import linear_core

    a, b, *_ = linear_core(plant, scene.setpoint_rad_s, 1000.0, "compliant")
    n, ts = a.shape[0], plant.sample_time_s
    stiff = np.zeros((n + 2, n + 2))
    stiff[:n, :n], stiff[:n, n:] = a * ts, b * ts  # the zero-order-hold block: norm ~3e6
    rng = np.random.default_rng(0)
    mats = [stiff, np.zeros((n + 2, n + 2))] + [rng.normal(size=(n + 2, n + 2)) * s for s in (1e-3, 0.5, 3.0, 40.0)]
    got = mcmargins.expm_stack(np.stack(mats))
    for m, e in zip(mats, got):
        ref = expm(m)
        assert np.max(np.abs(e - ref)) <= 1e-9 * max(1.0, np.max(np.abs(ref)))


def test_batched_margins_equal_each_samples_loop_model(robust):
    """20 samples: the batched loop's one-sample map, stability and Ms/Mt against the loop model
    the per-sample path builds for each sample (``actuator_loops`` on the sample's plant), at
    the paper design and at a design three times as fast (unstable on part of the samples)."""
    plant, scene, unc = robust
    f1 = scene.final_loads[0]
    sc = scene.replace(final_loads=(f1,))
    fam = parametric_family(plant, "compliant", unc.keys)
    draws = [draw_sample(unc, ((scene.setpoint_rad_s, f1),), 7, i)[0] for i in range(20)]
    thetas = np.array([[d.get(k, plant.values[k]) for k in fam.keys] for d in draws])
    a, b, _, ok = mcmargins.linearise_batch(fam, thetas, scene.setpoint_rad_s, 0.5 * (scene.initial_load + f1))
    assert ok.all()
    template = actuator_loops(plant, sc, estimator="none")[0]
    lp = mcmargins.loop_batch(template, a, b, fam.index("theta_nut"), plant.command_delay_samples)
    pid = _pid(plant)
    fast = (3 * pid.gains[0], 9 * pid.gains[1], 0.0)
    stable_seen = {True: 0, False: 0}
    for gains in (pid.gains, fast):
        ms, mt, good = mcmargins.sensitivity_peaks_batch(template, lp, gains, plant.speed_filter_s,
                                                         plant.command_delay_samples)
        assert good.all()
        for i, values in enumerate(draws):
            p_i = apply(plant, values, name=f"sample {i}")
            register_member(p_i, plant, unc.keys)
            loop = actuator_loops(p_i, sc, estimator="none")[0]
            assert np.allclose(lp["A0"][i], loop.A0, rtol=1e-7, atol=1e-12 * np.abs(loop.A0).max())
            stable = loop.is_stable(gains)
            stable_seen[stable] += 1
            if not stable:
                assert ms[i] == mt[i] == np.inf
                continue
            want = loop.sensitivity_peaks(gains)
            assert ms[i] == pytest.approx(want[0], rel=RTOL)
            assert mt[i] == pytest.approx(want[1], rel=RTOL)
    assert stable_seen[True] >= 20
    assert stable_seen[False] >= 1  # both branches checked


def test_batched_monte_carlo_margins_equal_the_per_sample_path(robust):
    """The Monte Carlo of robust-load-step (its [spec] bounds Ms): the batched run's Ms/Mt
    against the per-sample path's (same seed, same samples)."""
    plant, _, _ = robust
    scene = load_scene("robust-load-step")
    pid = _pid(plant)
    kw = dict(seed=11, backend="serial", quiet=True)
    bat = mc.run_monte_carlo(plant, scene, {"paper": pid}, 10, **kw)
    per = mc.run_monte_carlo(plant, scene, {"paper": pid}, 10, integrator="fast", path="per-sample", **kw)
    assert bat.integration["path"] == "batched"
    assert per.integration["path"] == "per-sample"
    for k in bat.samples["values"]:
        assert np.array_equal(bat.samples["values"][k], per.samples["values"][k])
    i_ms = mc.METRICS.index("ms")
    mb, mp = bat.samples["metrics"][:, 0, i_ms:i_ms + 2], per.samples["metrics"][:, 0, i_ms:i_ms + 2]
    assert np.all(np.isfinite(mb))
    assert np.ptp(mb[:, 0]) > 0.05
    np.testing.assert_allclose(mb, mp, rtol=RTOL)


def test_samples_the_batch_cannot_take_go_to_the_per_sample_margins(robust, monkeypatch):
    """An ill-conditioned modal basis (here: every one, the bound set to 0) sends the sample to
    the per-sample loop model, which gives the same numbers."""
    plant, _, _ = robust
    scene = load_scene("robust-load-step")
    pid = _pid(plant)
    kw = dict(seed=2, backend="serial", quiet=True)
    ref = mc.run_monte_carlo(plant, scene, {"paper": pid}, 6, **kw)
    calls = []
    real = mcbatch._margins
    monkeypatch.setattr(mcmargins, "MODAL_COND_MAX", 0.0)
    monkeypatch.setattr(mcbatch, "_margins", lambda *a, **k: calls.append(a[5]) or real(*a, **k))
    got = mc.run_monte_carlo(plant, scene, {"paper": pid}, 6, **kw)
    assert sorted(calls) == list(range(6))
    i_ms = mc.METRICS.index("ms")
    np.testing.assert_allclose(got.samples["metrics"][:, 0, i_ms:i_ms + 2], ref.samples["metrics"][:, 0, i_ms:i_ms + 2],
                               rtol=RTOL)


def test_batched_margins_do_not_depend_on_the_batch(robust):
    """A sample's Ms/Mt are the same bits in a batch of 24, in batches of 5 and replayed alone
    (each row of the batch computes alone: the backends agree bit for bit, a replay is exact)."""
    plant, _, _ = robust
    scene = load_scene("robust-load-step")
    pid = _pid(plant)
    kw = dict(seed=4, backend="serial", quiet=True)
    one = mc.run_monte_carlo(plant, scene, {"paper": pid}, 12, chunk=12, **kw)
    five = mc.run_monte_carlo(plant, scene, {"paper": pid}, 12, chunk=5, **kw)
    assert np.array_equal(one.samples["metrics"], five.samples["metrics"])
    i_ms = mc.METRICS.index("ms")
    assert np.all(np.isfinite(one.samples["metrics"][:, 0, i_ms]))
    r = mc.replay_sample(plant, scene, pid, 4, 7)
    assert r["metrics"]["ms"] == one.samples["metrics"][7, 0, i_ms]
    assert r["metrics"]["mt"] == one.samples["metrics"][7, 0, i_ms + 1]


@pytest.mark.parametrize("case", ["rigid", "command delay 2"])
def test_batched_margins_on_a_rigid_scene_and_a_delayed_drive(robust, monkeypatch, case):
    """The rigid loop (another family) and a drive with 2 samples of command delay (a delay
    line in the loop's state, the plant's command column moved): batched, nothing left to the
    per-sample path, Ms/Mt as the per-sample loop models give them."""
    plant, _, _ = robust
    scene = load_scene("robust-load-step")
    if case == "rigid":
        scene = scene.replace(fidelity="rigid")
    else:
        plant = plant.with_params({"drive.command_delay_samples": 2})
    pid = _pid(load_plant())
    kw = dict(seed=1, backend="serial", quiet=True)
    left = {}
    real = mcbatch._margins_batched
    monkeypatch.setattr(mcbatch, "_margins_batched", lambda *a: left.update(real(*a)) or {})
    bat = mc.run_monte_carlo(plant, scene, {"paper": pid}, 6, **kw)
    assert bat.integration["path"] == "batched"
    assert not left
    monkeypatch.setattr(mcbatch, "_margins_batched",
                        lambda job, plant, scene, draws, rows, out: {r: set(range(len(job.designs))) for r in rows})
    per = mc.run_monte_carlo(plant, scene, {"paper": pid}, 6, **kw)
    i_ms = mc.METRICS.index("ms")
    mb, mp = bat.samples["metrics"][:, 0, i_ms:i_ms + 2], per.samples["metrics"][:, 0, i_ms:i_ms + 2]
    assert np.all(np.isfinite(mb))
    np.testing.assert_allclose(mb, mp, rtol=RTOL)


def test_a_non_finite_sample_is_flagged_not_raised(robust):
    """A sample whose linearisation is not finite (a failed steady state) is flagged for the
    per-sample path; the others' numbers do not change."""
    plant, scene, unc = robust
    f1 = scene.final_loads[0]
    fam = parametric_family(plant, "compliant", unc.keys)
    thetas = np.array([[draw_sample(unc, ((scene.setpoint_rad_s, f1),), 0, i)[0].get(k, plant.values[k])
                        for k in fam.keys] for i in range(3)])
    a, b, _, ok = mcmargins.linearise_batch(fam, thetas, scene.setpoint_rad_s, 0.5 * (scene.initial_load + f1))
    template = actuator_loops(plant, scene.replace(final_loads=(f1,)), estimator="none")[0]
    args = (fam.index("theta_nut"), plant.command_delay_samples)
    clean = mcmargins.sensitivity_peaks_batch(template, mcmargins.loop_batch(template, a, b, *args), _pid(plant).gains,
                                              plant.speed_filter_s, plant.command_delay_samples)
    a[1, 2, 3] = np.nan
    ms, mt, good = mcmargins.sensitivity_peaks_batch(template, mcmargins.loop_batch(template, a, b, *args),
                                                     _pid(plant).gains, plant.speed_filter_s,
                                                     plant.command_delay_samples)
    assert clean[2].all()
    assert good.tolist() == [True, False, True]
    assert ms[[0, 2]].tolist() == clean[0][[0, 2]].tolist()
    assert mt[[0, 2]].tolist() == clean[1][[0, 2]].tolist()
