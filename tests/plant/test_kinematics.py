import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from prsa_ctrl import builtin_plants, load_plant
from prsa_ctrl.studies.paper import OMEGA_300_RPM, PAPER_TABLE2, kinematics_table

PLANTS = builtin_plants()
# issue 21: the closed form below is the inverted roller screw's (tests/test_mechanisms.py has the others)
INVERTED = [n for n in PLANTS if load_plant(n).mechanism == "inverted-roller-screw"]


def _closed_form(values, w):
    """The kinematic relations written out independently from the file values (mm)."""
    d_s = values["screw.pitch_diameter_mm"]
    d_n = values["nut.pitch_diameter_mm"]
    d_r = values["roller.pitch_diameter_mm"]
    lead = values["screw.starts"] * values["screw.lead_mm"] / values["screw.starts"]
    w_p = d_n / (d_n + d_s) * w
    return w_p, w_p * d_s / d_r, w_p * (d_s + d_r) / d_r, lead * 1e-3 * w / (2 * math.pi)


@pytest.mark.parametrize("name", INVERTED)
def test_kinematics_equal_closed_form(name):
    p = load_plant(name)
    w = np.array([-400.0, -1.0, 1e-3, 31.4159, 300.0])
    k = p.kinematics(w)
    expected = _closed_form(p.values, w)
    for got, exp in zip((k.omega_cage, k.omega_roller_rel, k.omega_roller_abs, k.v_screw), expected):
        np.testing.assert_allclose(got, exp, rtol=1e-12, atol=0)


def test_errata_numbers_at_300_rpm(paper_plant):
    k = paper_plant.kinematics(OMEGA_300_RPM)
    assert float(k.omega_cage) == pytest.approx(19.06, abs=0.005)
    assert float(k.omega_roller_abs) == pytest.approx(93.2, abs=0.05)
    assert float(k.omega_roller_rel) == pytest.approx(74.1, abs=0.05)
    assert float(k.v_screw) * 1e3 == pytest.approx(10.0, abs=0.005)


def test_absolute_spin_equals_nut_half_ratio_when_geometry_closes():
    p = load_plant("iprsm-60")  # d_N = d_S + 2 d_R exactly
    k = p.kinematics(10.0)
    assert float(k.omega_roller_abs) == pytest.approx(10.0 * p.d_nut_m / (2 * p.d_roller_m), rel=1e-12)


def test_table2_side_by_side(paper_plant):
    rows = {r["quantity"]: r for r in kinematics_table(paper_plant)}
    assert set(rows) == set(PAPER_TABLE2)
    assert rows["omega_cage"]["paper_theory"] == 30.30
    assert rows["omega_cage"]["ours_theory"] == pytest.approx(19.06, abs=0.005)
    # The paper's "theoretical" values all correspond to a nut speed near 50 rad/s, not 31.42.
    for r in rows.values():
        assert 49.0 < r["paper_implied_nut_speed"] < 52.0
        assert r["paper_theory_vs_ours"] > 0.5


@settings(max_examples=200, deadline=None, derandomize=True)
@given(st.floats(-1e4, 1e4, allow_nan=False, allow_subnormal=False), st.sampled_from(PLANTS))
def test_kinematics_properties(w, name):
    p = load_plant(name)
    k = p.kinematics(w)
    # Linear in nut speed, cage slower than nut, spin relations consistent.
    assert float(k.omega_cage) == pytest.approx(p.cage_ratio * w, rel=1e-12, abs=1e-300)
    assert abs(float(k.omega_cage)) <= abs(w)
    assert float(k.omega_roller_abs - k.omega_roller_rel) == pytest.approx(float(k.omega_cage), rel=1e-9, abs=1e-9)
    assert np.sign(float(k.v_screw)) == np.sign(w)
