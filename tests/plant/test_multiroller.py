import numpy as np
import pytest

from prsa_ctrl import PID, energy_balance, load_plant, simulate
from prsa_ctrl.plant.model import RollerErrors, plant_model

PLANT = load_plant()
STEP = [(0.0, 500.0), (0.02, 1500.0)]


@pytest.fixture(scope="module")
def runs():
    pid = PID(0.085, 14.7)
    kw = dict(load=STEP, duration=0.08, controller=pid, dt=5e-5, energy=True)
    return simulate(PLANT, fidelity="multi-roller", seed=3, **kw), simulate(PLANT, fidelity="compliant", **kw)


def _y(r, name):
    return np.asarray(r.outputs[r.output_labels.index(name)])


def test_per_roller_forces_share_the_load_unevenly_and_sum_to_the_total(runs):
    mr, _ = runs
    late = mr.time > 0.06
    per = np.array([_y(mr, f"contact_force_nut_{i + 1}")[late] for i in range(PLANT.n_rollers)])
    total = _y(mr, "contact_force_nut")[late]
    np.testing.assert_allclose(per.sum(axis=0), total, rtol=1e-9)
    means = per.mean(axis=1)
    assert means.max() / means.mean() > 1.2  # position errors make load sharing non-uniform
    # Runout makes each loaded roller's force fluctuate once per spin while the total stays
    # steady; rollers whose position error exceeds the deflection carry nothing.
    loaded = means > 1.0
    assert loaded.sum() >= PLANT.n_rollers // 2
    assert np.ptp(per[loaded], axis=1).min() > 10 * np.ptp(total)


def test_identical_rollers_reduce_to_the_compliant_model():
    perfect = PLANT.with_params({"tolerance.roller_position_std_um": 0.0, "tolerance.roller_runout_um": 0.0})
    pid = PID(0.085, 14.7)
    a = simulate(perfect, load=STEP, duration=0.05, controller=pid, fidelity="multi-roller")
    b = simulate(perfect, load=STEP, duration=0.05, controller=pid, fidelity="compliant")
    assert np.max(np.abs(_y(a, "nut_speed") - _y(b, "nut_speed"))) < 1e-6
    np.testing.assert_allclose(_y(a, "contact_force_screw"), _y(b, "contact_force_screw"), rtol=1e-5)


def test_nut_speed_close_to_compliant_and_energy_closes(runs):
    mr, co = runs
    drop_mr = 31.4159 - _y(mr, "nut_speed").min()
    drop_co = 31.4159 - _y(co, "nut_speed").min()
    assert abs(drop_mr / drop_co - 1) < 0.01
    assert energy_balance(mr)["relative_residual"] < 1e-4


def test_errors_are_seeded_and_zero_mean():
    a, b, c = RollerErrors.draw(PLANT, 1), RollerErrors.draw(PLANT, 1), RollerErrors.draw(PLANT, 2)
    assert a == b and a != c
    assert abs(np.mean(a.position_nut)) < 1e-15 and np.std(a.position_nut) > 0
    assert plant_model(PLANT, "multi-roller", 1) is plant_model(PLANT, "multi-roller", 1)


def test_multi_roller_cannot_be_linearised():
    from prsa_ctrl import linearize

    with pytest.raises(ValueError, match=r"fidelity = 'multi-roller'; expected 'rigid' or 'compliant'"):
        linearize(PLANT, 31.4, 1000.0, "multi-roller")
