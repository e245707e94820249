"""The nonlinear plant as a python-control I/O system (for ``interconnect``,
``find_operating_point`` and other interop). The fast path for simulation is
:func:`prsa_ctrl.simulate`; this wrapper evaluates the same CasADi functions."""

from __future__ import annotations

import control
import numpy as np

from .model import INPUTS, plant_model
from .plantfile import Plant

__all__ = ["nonlinear_iosys"]


def nonlinear_iosys(plant: Plant, fidelity: str = "compliant") -> control.NonlinearIOSystem:
    """Open-loop nonlinear plant with inputs ``torque_command`` (N m) and ``axial_load`` (N),
    the model's named states and outputs (``motor_torque`` is the actual torque, N m).

    Parameters
    ----------
    plant : Plant
    fidelity : {"rigid", "compliant"}

    The angles are left out of the states (held at zero): nothing in the rigid and compliant
    models depends on them, and with them no steady state at non-zero speed would exist for
    ``find_operating_point``.

    Examples
    --------
    >>> import control
    >>> from prsa_ctrl import load_plant, nonlinear_iosys
    >>> sys = nonlinear_iosys(load_plant(), "rigid")
    >>> sys.input_labels
    ['torque_command', 'axial_load']
    """
    model = plant_model(plant, fidelity)
    f, h = model.f, model.h
    keep = [i for i, n in enumerate(model.state_names) if not n.startswith("theta_")]

    def full(x):
        xf = np.zeros(model.nx)
        xf[keep] = x
        return xf

    def updfcn(t, x, u, params):
        return np.asarray(f(full(x), u)).ravel()[keep]

    def outfcn(t, x, u, params):
        return np.asarray(h(full(x), u)).ravel()

    outputs = list(model.output_names)
    return control.nlsys(
        updfcn,
        outfcn,
        inputs=list(INPUTS),
        outputs=outputs,
        states=[model.state_names[i] for i in keep],
        name=f"{plant.name}_{fidelity}".replace(".", "_"),
    )
