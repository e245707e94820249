"""prsa_ctrl.identification.compliant: the unmeasured states of the compliant screw-driven model
along a log (the time-domain fit's reference) and their scales."""

from __future__ import annotations

import numpy as np
import pytest

from prsa_ctrl.plant import load_plant
from prsa_ctrl.plant.equilibrium import operating_point
from prsa_ctrl.plant.model import plant_model
from prsa_ctrl.identification.compliant import COMPLIANT_STATES, compliant_reference, compliant_scales


@pytest.mark.parametrize("name", ["ballscrew-32x10", "rollerscrew-30x5"])
def test_reference_at_steady_speed_is_the_models_own_equilibrium(name):
    """At constant speed and load the reference equals the compliant model's operating point
    (solved from the model's equations, not from the reference's formula)."""
    p = load_plant(name)
    m = plant_model(p, "compliant")
    w, load = 30.0, 0.4 * p.values["screw.rated_load_n"]
    op = operating_point(p, w, load, "compliant")
    t = np.arange(50) * 1e-4
    ref = compliant_reference(p, m.state_names, t, np.full(50, w), np.full(50, load))
    assert set(ref) == set(COMPLIANT_STATES)
    for k in COMPLIANT_STATES:
        scale = compliant_scales(p, m.state_names, w)[k]
        assert scale > 0
        np.testing.assert_allclose(ref[k], op.x[m.index(k)], rtol=1e-6, atol=1e-9 * scale)
    # a constant acceleration adds the carriage's inertial force to the spring's
    acc = 2000.0
    ref2 = compliant_reference(p, m.state_names, t, w + acc * t, np.full(50, load))
    extra = p.values["axis.moving_mass_kg"] * p.lead_per_rad * acc
    np.testing.assert_allclose(ref2["delta_screw"][5:-5] / ref["delta_screw"][5:-5], (load + extra) / load, rtol=1e-9)


def test_other_models_get_no_reference():
    p = load_plant()  # the inverted roller screw: its compliant states are the thread contacts'
    names = plant_model(p, "compliant").state_names
    assert compliant_reference(p, names, np.arange(5.0), np.ones(5), np.zeros(5)) == {}
    assert compliant_scales(p, names, 10.0) == {}
    q = load_plant("ballscrew-32x10")
    assert compliant_reference(q, plant_model(q, "rigid").state_names, np.arange(5.0), np.ones(5), np.zeros(5)) == {}
