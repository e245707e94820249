"""Parametric plant families: one model (and one compiled sampled-loop law) for the samples of a
Monte-Carlo run, the same equations as a direct build of each sample."""

import numpy as np
import pytest

from prsa_ctrl import load_plant
from prsa_ctrl.plant import model as M
from prsa_ctrl.studies.paper import default_pid
from prsa_ctrl.sim.integrators import SimSettings
from prsa_ctrl.sim.engine import run
from prsa_ctrl.plant.uncertainty import apply

PLANT = load_plant()
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
    assert m.family is not None and set(m.family.keys) == set(KEYS)
    assert m.theta == tuple(VALUES[k] for k in m.family.keys)
    for x, u in M._test_points(m.state_names, 4):
        for a, b in ((m.f, direct.f), (m.h, direct.h), (m.power, direct.power)):
            va, vb = np.asarray(a(x, u), float), np.asarray(b(x, u), float)
            np.testing.assert_allclose(va, vb, rtol=1e-12, atol=1e-12 * np.max(np.abs(vb)))


def test_keys_used_as_numbers_are_not_parameters():
    # the flank angle enters through math.cos: it cannot be a parameter, and a member
    # differing in it gets its own, direct model; sensor keys are never parameters
    fam = M.parametric_family(PLANT, "compliant", ("thread.flank_angle_deg", "nut.inertia_kg_m2", "sensor.sample_time_s"))
    assert fam is not None and fam.keys == ("nut.inertia_kg_m2",)
    p = _member({"thread.flank_angle_deg": PLANT.values["thread.flank_angle_deg"] + 1.0},
                ("thread.flank_angle_deg", "nut.inertia_kg_m2", "sensor.sample_time_s"))
    assert M.plant_model(p, "compliant").family is None


def test_member_run_shares_one_law_and_matches_the_direct_run():
    kw = dict(setpoint=31.4159, load=[(0, 500.0), (0.002, 1500.0)], duration=0.03, controller=default_pid(PLANT),
              fidelity="compliant", discrete=True, settings=SimSettings(integrator="radau", substeps=2))
    a, b = _member(VALUES), _member({**VALUES, "nut.inertia_kg_m2": 1.1e-4})
    ra, rb = run(a, **kw), run(b, **kw)
    direct = run(apply(PLANT, VALUES), **kw)
    from prsa_ctrl.sim.integrators import _BUILT

    built_a = _BUILT[M.plant_model(a, "compliant")][("member", False)]
    built_b = _BUILT[M.plant_model(b, "compliant")][("member", False)]
    assert built_a.sampled is built_b.sampled  # one set of functions for the family
    assert ra.states.shape == direct.states.shape and ra.state_labels == direct.state_labels
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
    assert fast.integration["integrator"] == "radau" and ref.integration["integrator"] == "cvodes"
    assert fast.integration["relative"] <= 0.5 * scene.accuracy
    assert fast.as_dict()["integration"]["check_points"] == 7  # nominal, 2 corners, 2 x 2 single ends
    k = mc.METRICS.index("peak_drop_rad_s")
    drop_f, drop_r = fast.samples["metrics"][:, 0, k], ref.samples["metrics"][:, 0, k]
    assert np.all(np.abs(drop_f - drop_r) <= scene.accuracy * drop_r)
    assert "--integrator fast" in fast.designs[0].replay
    # the batched default checks its own samples against the adaptive reference
    ig = batched.integration
    assert ig["path"] == "batched" and ig["check_samples"] and set(ig["check_samples"]) <= {0, 1, 2}
    assert 0 < ig["relative"] <= 0.5 * scene.accuracy
    drop_b = batched.samples["metrics"][:, 0, k]
    assert np.all(np.abs(drop_b - drop_r) <= scene.accuracy * drop_r)
