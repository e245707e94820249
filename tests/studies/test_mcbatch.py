"""The batched Monte-Carlo path (prsa_ctrl.studies.mcbatch) against the per-sample path."""

import numpy as np
import pytest

from prsa_ctrl.drive.pid import PID
from prsa_ctrl.plant.plantfile import load_plant
from prsa_ctrl.plant.uncertainty import uncertainty_model
from prsa_ctrl.studies import montecarlo as mc
from prsa_ctrl.studies.scene import load_scene

FAST = PID(0.0849, 14.67, tf=1e-3)


@pytest.fixture(scope="module")
def setup():
    return load_plant(), load_scene("robust-load-step")


@pytest.fixture(scope="module")
def paper_both():
    from prsa_ctrl.studies.paper import default_pid

    p, s = load_plant(), load_scene("paper-load-step")
    pid = default_pid(p)
    kw = dict(seed=3, backend="serial", quiet=True, spec={})
    return (mc.run_monte_carlo(p, s, {"paper": pid}, 20, **kw),
            mc.run_monte_carlo(p, s, {"paper": pid}, 20, integrator="fast", path="per-sample", **kw),
            s)


def test_batched_monte_carlo_equals_the_per_sample_path(paper_both):
    """Against the per-sample fast path (the Jacobian at every substep; the batched one shares
    it over a quarter of a controller sample): the nut speed of both is within the scene's accuracy of
    the reference, so their metrics agree within the bounds that accuracy gives (the speed
    metrics within ``accuracy x drop``, the integrals within that times the record's length)."""
    batched, per_sample, scene = paper_both
    assert batched.integration["path"] == "batched"
    assert per_sample.integration["path"] == "per-sample"
    # same seeds, same samples
    assert np.array_equal(batched.samples["index"], per_sample.samples["index"])
    for k in batched.samples["values"]:
        assert np.array_equal(batched.samples["values"][k], per_sample.samples["values"][k])
    mb, mp = batched.samples["metrics"][:, 0, :10], per_sample.samples["metrics"][:, 0, :10]
    assert np.all(np.isfinite(mb))
    assert np.ptp(mb[:, 0]) > 0.1  # 20 different, finished samples
    drop = mp[:, mc.METRICS.index("peak_drop_rad_s")]
    acc, span = scene.accuracy, scene.duration - scene.step_time
    sse = np.abs(mp[:, mc.METRICS.index("steady_state_error_rad_s")])
    bound = {"peak_drop_rad_s": acc * drop, "overshoot_rad_s": acc * drop, "steady_state_error_rad_s": acc * drop,
             "ie": acc * drop * span, "iae": acc * drop * span, "itae": acc * drop * span ** 2 / 2,
             "ise": acc * drop * span * (2 * drop + acc * drop + 2 * sse),
             "peak_torque_n_m": acc * mp[:, mc.METRICS.index("peak_torque_n_m")], "saturated": 0 * drop}
    for k, m in enumerate(mc.METRICS[:10]):
        if m == "recovery_time_s":  # a sample time at most, where the band is crossed between samples
            assert np.all(np.abs(mb[:, k] - mp[:, k]) <= 0.25e-3 + 1e-12), m
        else:
            assert np.all(np.abs(mb[:, k] - mp[:, k]) <= bound[m]), m
    # and not identical: the schemes differ (a batched path that ran the per-sample one would not)
    assert np.max(np.abs(mb[:, 0] - mp[:, 0])) > 1e-6
    assert batched.designs[0].yield_ == per_sample.designs[0].yield_


def test_batched_chunk_equals_the_per_sample_run_of_the_same_scheme(paper_both):
    """A chunk of the batched path (one batched run, batched metrics) against the per-sample
    verification with the same fixed-step settings (shared Jacobian included): the same
    numbers to rounding."""
    from dataclasses import replace

    from prsa_ctrl.studies import mcbatch
    from prsa_ctrl.studies.mcjob import Job, evaluate, plant_doc
    from prsa_ctrl.studies.paper import default_pid

    _, _, scene = paper_both
    p = load_plant()
    unc = uncertainty_model(p, scene.sections.plant_overrides)
    settings = mcbatch.batch_settings(scene.accuracy)
    assert settings.jacobian_every == settings.substeps // 4 > 1
    job = Job("same-scheme", plant_doc(p), scene, (("paper", default_pid(p), "none"),), unc,
              tuple(mc.operating_points(scene)), {}, 3, settings, batched=True)
    idx = [0, 5, 11]
    got = mcbatch.evaluate_batch(job, idx)
    ref = [evaluate(replace(job, batched=False), i) for i in idx]
    for g, r in zip(got, ref):
        assert g[0] == r[0]
        assert g[1] == r[1]
        mb, mp = g[3][0, :10], r[3][0, :10]
        drop = mp[mc.METRICS.index("peak_drop_rad_s")]
        assert drop > 1.0
        for k, m in enumerate(mc.METRICS[:10]):
            scale = {"peak_drop_rad_s": drop, "overshoot_rad_s": drop, "steady_state_error_rad_s": drop,
                     "peak_torque_n_m": 1.0}.get(m, abs(mp[k]) + 1e-300)
            if m == "recovery_time_s":
                assert abs(mb[k] - mp[k]) <= 0.25e-3 + 1e-12, m
            else:
                assert abs(mb[k] - mp[k]) <= 1e-6 * scale, m


def test_batched_monte_carlo_quotes_its_measured_error(paper_both):
    batched, _, scene = paper_both
    ig = batched.integration
    assert ig["path"] == "batched"
    assert ig["integrator"] == "radau"
    assert ig["substeps"] == 8
    assert ig["jacobian_every"] == 2
    assert 3 <= len(ig["checks"]) <= 11
    assert sorted(c["index"] for c in ig["checks"]) == ig["check_samples"]
    assert ig["relative"] == max(c["relative"] for c in ig["checks"]) <= 0.5 * scene.accuracy
    assert ig["relative"] > 0  # measured, not assumed
    assert ig["reference"]["integrator"] == "cvodes"
    line = [x for x in mc.format_report(batched).splitlines() if x.startswith("integration: ")]
    assert line
    assert f"measured error {ig['relative']:.2g} of the deviation on {len(ig['checks'])} check samples" in line[0]


def test_batched_check_that_fails_falls_back_to_the_per_sample_reference(setup, monkeypatch):
    from prsa_ctrl.studies import mcbatch

    p, s = setup
    monkeypatch.setattr(mcbatch, "_BATCH_SUBSTEPS_AT_1_PERCENT", 1)  # 1 then 2 substeps: too coarse
    monkeypatch.setattr(mcbatch, "BATCH_REFINEMENTS", 1)
    rep = mc.run_monte_carlo(p, s, {"fast": FAST}, 3, seed=1, backend="serial", quiet=True, spec={})
    ig = rep.integration
    assert ig["path"] == "per-sample"
    assert ig["integrator"] == "cvodes"
    assert "batched check failed" in ig["reason"]
    assert ig["batched_relative"] > 0.5 * s.accuracy
    assert rep.complete
    assert np.all(np.isfinite(rep.samples["metrics"][:, 0, :10]))


def test_check_samples_are_the_extremes_and_seeded(setup):
    from prsa_ctrl.studies import mcbatch

    p, s = setup
    unc = uncertainty_model(p, s.sections.plant_overrides)
    ops = [(1.0, 1500.0)]
    a = mcbatch.check_indices(unc, ops, 4, 200)
    assert a == mcbatch.check_indices(unc, ops, 4, 200)
    assert len(set(a)) == len(a) <= 1 + 2 * len(unc.keys)
    assert mcbatch.check_indices(unc, ops, 4, 1) == [0]
    vals = [mc.draw_sample(unc, ops, 4, i)[0] for i in range(200)]
    score = np.zeros(200)
    for k in unc.keys:
        col = np.array([v[k] for v in vals])
        assert int(np.argmin(col)) in a
        assert int(np.argmax(col)) in a  # every parameter's two ends
        score += np.abs(np.argsort(np.argsort(col)) / 199 - 0.5)
    assert int(np.argmax(score)) in a  # and the most extreme sample overall
    assert len(mcbatch.check_indices(unc, ops, 4, 200, k=2)) == 2


def test_check_ignores_parameters_the_model_does_not_read(setup):
    from prsa_ctrl.plant.model import parametric_family
    from prsa_ctrl.studies import mcbatch

    p, s = setup[0], load_scene("paper-load-step")  # the plant's own five uncertain values
    unc = uncertainty_model(p, s.sections.plant_overrides)
    fam = parametric_family(p, "compliant", unc.keys)
    acting = mcbatch.acting_keys(fam)
    assert "contact.stiffness_n_per_mm_e" in acting
    assert "nut.inertia_kg_m2" in acting
    assert "tolerance.roller_position_std_um" not in acting  # multi-roller only
    a = mcbatch.check_indices(unc, [(1.0, 1500.0)], 4, 200, keys=acting)
    assert len(a) <= 1 + 2 * len(acting) < 1 + 2 * len(unc.keys)
