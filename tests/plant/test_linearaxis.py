"""The two-mass linear axis (prsa_ctrl.plant.linearaxis): the compliant model of a linear axis with
a load mass, checked against the two-mass equations written here (no toolkit model code)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from prsa_ctrl import load_plant
from prsa_ctrl.plant import linear_core
from prsa_ctrl.plant.linearaxis import is_two_mass_axis
from prsa_ctrl.plant.model import plant_model
from prsa_ctrl.plant.plantfile import Plant

from independent_actuator import modal_damper, two_mass_eom_response

TWO_PI = 2 * math.pi
M, ML, K_UM, ZETA, FC = 120.0, 45.0, 3.0, 0.04, 800.0  # kg, kg, N/um, -, Hz


def _axis(load_mass: float = ML) -> Plant:
    doc = {"name": "two-mass-test", "mechanism": "linear-axis",
           "axis": {"mass_kg": {"value": M, "source": "test"}, "load_mass_kg": {"value": load_mass, "source": "test"},
                    "load_stiffness_n_per_um": {"value": K_UM, "source": "test"},
                    "axial_damping_ratio": {"value": ZETA, "source": "test"}},
           "friction": {"viscous_positive_n_s_per_m": {"value": 150.0, "source": "test"},
                        "viscous_negative_n_s_per_m": {"value": 150.0, "source": "test"},
                        "coulomb_positive_n": {"value": 20.0, "source": "test"},
                        "coulomb_negative_n": {"value": 20.0, "source": "test"}},
           "drive": {"gain_n_per_unit": {"value": 35.0, "source": "test"}, "force_limit_n": {"value": 400.0, "source": "test"},
                     "current_loop_bandwidth_hz": {"value": FC, "source": "test"}},
           "sensor": {"sample_time_s": {"value": 1e-3, "source": "test"},
                      "encoder_resolution_m": {"value": 5e-8, "source": "test"}}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return Plant.from_dict(doc, origin="test")


def _independent(f_hz, b):
    """Motor speed / force command (m/s per N) of two masses on a spring-damper, viscous ``b`` on the
    motor side, a first-order current loop: the 2 x 2 equations of motion solved at each frequency
    (tests/independent_actuator.py, in load coordinates: masses in kg, stiffness in N/m)."""
    mm, k = M - ML, K_UM * 1e6
    return two_mass_eom_response(f_hz, mm, ML, k, modal_damper(k, mm, ML, ZETA), b, FC)


def test_the_compliant_model_of_a_linear_axis_with_a_load_mass_is_the_two_mass_axis():
    p = _axis()
    assert is_two_mass_axis(p)
    assert not is_two_mass_axis(_axis(0.0))
    assert plant_model(p, "compliant").state_names == ("theta_nut", "omega_nut", "delta_screw", "v_screw", "tau_motor")
    assert plant_model(p, "rigid").state_names == ("theta_nut", "omega_nut", "tau_motor")
    assert plant_model(_axis(0.0), "compliant").state_names == ("theta_nut", "omega_nut", "tau_motor")
    a, b, c, d, _ = linear_core(p, 0.05, 0.0, "compliant")
    # resonance sqrt(k / m_red), m_red = m_m m_l / M, and anti-resonance sqrt(k / m_l), written out here
    mm, k = M - ML, K_UM * 1e6
    f_res, f_anti = math.sqrt(k / (mm * ML / M)) / TWO_PI, math.sqrt(k / ML) / TWO_PI
    ev = np.linalg.eigvals(a)
    osc = [e for e in ev if e.imag > 1e-3 * abs(e)]
    assert len(osc) == 1
    assert abs(osc[0]) / TWO_PI == pytest.approx(f_res, rel=2e-3)  # viscous friction on the motor side shifts it slightly
    # the frequency response torque -> motor speed equals the independent two-mass equations
    i_w = plant_model(p, "compliant").state_names.index("omega_nut")
    f = np.array([2.0, 10.0, 0.9 * f_anti, f_anti, 0.5 * (f_anti + f_res), f_res, 1.2 * f_res, 200.0])
    g = np.array([np.linalg.solve(1j * TWO_PI * fi * np.eye(a.shape[0]) - a, b[:, 0])[i_w] for fi in f])
    assert np.allclose(g, _independent(f, 150.0), rtol=1e-9, atol=0)
    # the response's zero pair (the invariant zeros of force command -> motor speed) is undamped at
    # sqrt(k / m_l): the roots of m_l s^2 + c s + k
    from scipy.linalg import eigvals

    n = a.shape[0]
    cm = np.zeros(n)
    cm[i_w] = 1.0
    zs = eigvals(np.block([[a, b[:, :1]], [cm[None, :], np.zeros((1, 1))]]),
                 np.block([[np.eye(n), np.zeros((n, 1))], [np.zeros((1, n + 1))]]))
    zs = [z for z in zs if np.isfinite(z) and z.imag > 1e-3 * abs(z)]
    assert len(zs) == 1
    assert abs(zs[0]) / TWO_PI == pytest.approx(f_anti, rel=1e-9)


def test_the_load_acts_on_the_load_mass_and_the_spring_carries_it():
    """At steady speed under an external load F the spring is compressed by F / k and the drive
    force is friction plus F (the static balance of both masses, written here)."""
    p = _axis()
    m = plant_model(p, "compliant")
    v, load = 0.05, 80.0
    tau = 20.0 + 150.0 * v + load
    x = np.array([0.0, v, load / (K_UM * 1e6), v, tau])
    xdot = np.asarray(m.f(x, [tau, load]), float).ravel()
    assert xdot[0] == pytest.approx(v)
    assert xdot[2] == pytest.approx(0.0, abs=1e-15)
    assert xdot[1] == pytest.approx(0.0, abs=1e-9)
    assert xdot[3] == pytest.approx(0.0, abs=1e-9)
    # power balance: the stored energy's rate is the motor power less the load's and the dissipation
    xt = np.array([0.0, 0.07, 3e-5, 0.02, 150.0])
    stored, p_motor, p_load, p_diss = (float(z) for z in np.asarray(m.power(xt, [150.0, 30.0]), float).ravel())
    dx = np.asarray(m.f(xt, [150.0, 30.0]), float).ravel()
    mm, k = M - ML, K_UM * 1e6
    d_stored = mm * xt[1] * dx[1] + ML * xt[3] * dx[3] + k * xt[2] * dx[2]
    assert d_stored == pytest.approx(p_motor - p_load - p_diss, rel=1e-9)
    assert stored == pytest.approx(0.5 * mm * 0.07**2 + 0.5 * ML * 0.02**2 + 0.5 * k * 9e-10, rel=1e-12)


def test_a_screw_plant_is_never_a_two_mass_axis():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert not is_two_mass_axis(load_plant("ballscrew-32x10"))


def test_the_simulator_runs_the_two_mass_axis_with_its_energy_balanced():
    """A load step on the two-mass axis in the speed loop (the one simulator, compliant fidelity):
    the work of the drive equals the load's, the dissipated and the stored change (to the
    integrator's tolerance), and the speed dips differently from the rigid axis of the same mass."""
    from prsa_ctrl.drive.pid import PID
    from prsa_ctrl.sim.engine import energy_balance, run

    p = _axis()
    kw = dict(setpoint=0.05, load=[(0, 0.0), (0.05, 80.0)], duration=0.2, controller=PID(3000.0, 30000.0), energy=True)
    two, rigid = run(p, fidelity="compliant", **kw), run(p, fidelity="rigid", **kw)
    bal = energy_balance(two)
    assert abs(bal["relative_residual"]) < 1e-6
    assert bal["work_load_j"] > 0.1
    w2, w1 = (np.asarray(r.to_response().outputs[0]) for r in (two, rigid))
    assert abs(w2.min() - w1.min()) > 1e-2 * (0.05 - w1.min())
