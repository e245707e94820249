"""The open-loop nonlinear plant as a python-control system (``nonlinear_iosys``)."""

import numpy as np
import pytest

from prsa_ctrl import load_plant, nonlinear_iosys, operating_point, run
from prsa_ctrl.plant.model import plant_model


@pytest.mark.parametrize("fidelity", ["rigid", "compliant"])
def test_names_and_equilibrium(fidelity):
    plant = load_plant()
    sys = nonlinear_iosys(plant, fidelity)
    assert sys.input_labels == ["torque_command", "axial_load"]
    assert "theta_nut" not in sys.state_labels
    assert "omega_nut" in sys.state_labels
    assert sys.output_labels == list(plant_model(plant, fidelity).output_names)
    op = operating_point(plant, 31.4159, 1000.0, fidelity)
    keep = [i for i, n in enumerate(plant_model(plant, fidelity).state_names) if not n.startswith("theta_")]
    x0 = op.x[keep]
    # The toolkit's own equilibrium is one of this system's: every rate vanishes there.
    dx = sys._rhs(0.0, x0, [op.torque, 1000.0])
    scale = np.abs(sys._rhs(0.0, x0, [op.torque + 0.1, 1000.0])).max()
    assert np.max(np.abs(dx)) < 1e-9 * scale
    y = sys._out(0.0, x0, [op.torque, 1000.0])
    assert y[sys.output_labels.index("nut_speed")] == pytest.approx(31.4159)


def test_open_loop_response_matches_the_simulator():
    """A torque step on the rigid plant through python-control (LSODA, tight tolerances) and
    through the toolkit's simulator agree."""
    import control

    plant = load_plant()
    sys = nonlinear_iosys(plant, "rigid")
    op = operating_point(plant, 31.4159, 1000.0, "rigid")
    t = np.linspace(0.0, 0.02, 201)
    u = np.vstack([np.full_like(t, op.torque + 0.2), np.full_like(t, 1000.0)])
    resp = control.input_output_response(sys, t, u, X0=op.x[1:], solve_ivp_method="LSODA",
                                         solve_ivp_kwargs={"rtol": 1e-10, "atol": 1e-10})
    ours = run(plant, setpoint=31.4159, load=1000.0, duration=0.02, dt=1e-4, fidelity="rigid", feedforward_torque=0.2,
               settings=__import__("prsa_ctrl").SimSettings(rtol=1e-10, atol=1e-10))
    w_pc = resp.outputs[sys.output_labels.index("nut_speed")]
    w_ours = ours.output("nut_speed")
    assert w_ours[-1] > 31.4159 + 1.0  # the extra torque accelerates the nut
    np.testing.assert_allclose(w_pc, w_ours, rtol=0, atol=1e-6)
