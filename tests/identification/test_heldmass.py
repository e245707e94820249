"""The held moving mass's share of a time-domain fit's total inertia
(prsa_ctrl.identification.heldmass): the plant's own spread of the mass or +-10 % uniform, times
the bound a^2 (1/eta - 1), checked against the rigid model's accelerations."""

from __future__ import annotations

import dataclasses
import math
import warnings

import pytest

from prsa_ctrl.identification.heldmass import held_mass_spread
from prsa_ctrl.plant import load_plant
from prsa_ctrl.plant.model import plant_model

JM, MASS, ETA = "axis.motor_inertia_kg_m2", "axis.moving_mass_kg", "friction.efficiency"


def _base():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_plant("ballscrew-32x10")


def test_held_mass_spread_is_the_nut_loss_bound_and_matches_the_rigid_model():
    with_entry = _base()
    (e,) = held_mass_spread(with_entry, with_entry, (JM, ETA))
    assert "[uncertainty] entry" in e["source"]
    assert e["sd"] > 0  # the plant's own spread of the mass
    base = dataclasses.replace(with_entry, uncertainty={})  # without one: the stated +-10 % uniform
    v = base.values
    a2 = base.lead_per_rad ** 2
    loss = 1.0 / v[ETA] - 1.0
    (e,) = held_mass_spread(base, base, (JM, ETA))
    assert e["key"] == MASS
    assert e["sd"] == pytest.approx(0.1 * v[MASS] / math.sqrt(3.0), rel=1e-12)
    assert e["sensitivity_kg_m2_per_unit"] == pytest.approx(a2 * loss, rel=1e-12)
    assert e["sd_kg_m2"] == pytest.approx(e["sd"] * a2 * loss, rel=1e-12)
    assert held_mass_spread(base, base, (JM, MASS, ETA)) == []
    old_law = base.with_params({"axis.nut_loss_on_whole_force": 0}, name=base.name)
    assert held_mass_spread(old_law, old_law, (JM, ETA)) == []
    # The bound is the model's: a mass dm high with the motor inertia dm a^2 (1 + L) low gives the
    # same acceleration while the motor drives the carriage (nut force > 0, speed > 0) and a total
    # inertia lower by dm a^2 L; while the carriage drives the motor the two differ.
    dm = 0.05 * v[MASS]
    other = base.with_params({MASS: v[MASS] + dm, JM: v[JM] - dm * a2 * (1.0 + loss)}, name=base.name)
    assert other.reflected_inertia_kg_m2 - base.reflected_inertia_kg_m2 == pytest.approx(-dm * a2 * loss, rel=1e-9)
    wdot = {}
    for name, p in (("base", base), ("other", other)):
        f = plant_model(p, "rigid").f
        for case, (tau, load) in {"driving": (3.0, 200.0), "braking": (-3.0, 200.0)}.items():
            wdot[name, case] = float(f([0.0, 50.0, tau], [tau, load])[1])
    assert wdot["other", "driving"] == pytest.approx(wdot["base", "driving"], rel=1e-9)
    assert abs(wdot["other", "braking"] / wdot["base", "braking"] - 1.0) > 1e-3
