"""Steady operating points of the actuator: constant nut speed under a constant axial load."""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from .errors import SimulationError
from .model import PlantModel, plant_model
from .plant import Plant

__all__ = ["OperatingPoint", "operating_point"]


@dataclass(frozen=True)
class OperatingPoint:
    """Equilibrium of the open-loop plant.

    Attributes
    ----------
    x : ndarray
        Plant state (``model.state_names``; ``theta_nut`` = 0).
    torque : float, N m
        Torque command (= motor torque) holding the speed.
    omega_nut : float, rad/s
    load : float, N
    """

    x: NDArray[np.float64]
    torque: float
    omega_nut: float
    load: float


_SOLVERS: "weakref.WeakKeyDictionary[PlantModel, ca.Function]" = weakref.WeakKeyDictionary()


def _solver(model: PlantModel) -> ca.Function:
    if model in _SOLVERS:
        return _SOLVERS[model]
    # Unknowns: every state but the angle and the nut speed, plus the torque command.
    free = [i for i, n in enumerate(model.state_names) if not n.startswith("theta_") and n != "omega_nut"]
    z = ca.SX.sym("z", len(free) + 1)
    par = ca.SX.sym("p", 2)  # omega_nut, load
    x = [0] * model.nx
    x[model.index("omega_nut")] = par[0]
    for k, i in enumerate(free):
        x[i] = z[k]
    x = ca.vertcat(*x)
    rhs = model.f(x, ca.vertcat(z[-1], par[1]))
    eqs = ca.vertcat(*[rhs[i] for i in range(model.nx) if not model.state_names[i].startswith("theta_")])
    g = ca.Function("g", [z, par], [eqs])
    solver = ca.rootfinder(
        "eq", "newton", g, {"abstol": 1e-10, "max_iter": 200, "error_on_fail": True}
    )
    _SOLVERS[model] = solver
    object.__setattr__(model, "_free", free)
    return solver


def _guess(model: PlantModel, omega: float, load: float) -> NDArray[np.float64]:
    p = model.plant
    k = p.kinematics(omega)
    x = np.zeros(model.nx)
    x[model.index("omega_nut")] = omega
    names = model.state_names
    f_n, f_s = p.normal_force_factor()
    if "omega_cage" in names:
        c_b = math.cos(p.flank_angle_rad)
        k_si, e = p.contact_stiffness_si, p.values["contact.exponent"]

        def axial(fac: float, cos_l: float) -> float:
            per_contact = abs(load) * fac / p.n_contacts
            pen = (per_contact / k_si) ** (1.0 / e) / (c_b * cos_l)
            # A pulling load engages the opposite flank, beyond the axial backlash.
            return pen if load >= 0 else -(pen + p.values["thread.backlash_mm"] * 1e-3)

        x[model.index("omega_cage")] = float(k.omega_cage)
        x[model.index("v_screw")] = float(k.v_screw)
        x[model.index("x_roller")] = -axial(f_n, math.cos(p.helix_nut_rad))
        x[model.index("delta_screw")] = axial(f_s, math.cos(p.helix_screw_rad))
    return x


def operating_point(
    plant: Plant, omega_nut: float, load: float, fidelity: str = "compliant", seed: int = 0
) -> OperatingPoint:
    """Equilibrium at constant nut speed ``omega_nut`` (rad/s) and axial load ``load`` (N).

    For the multi-roller fidelity this is the balance at cage angle 0 (the roller runout makes
    the true steady state periodic).

    Raises
    ------
    SimulationError
        If no equilibrium exists within the motor's torque limit.
    """
    rigid = plant_model(plant, "rigid")
    # The rigid nut equation is affine in the motor torque and its steady torque equals the
    # compliant one (same friction law), so the torque limit is checked before any Newton step.
    x_r = np.array([0.0, omega_nut, 0.0])
    acc0 = float(rigid.f(x_r, [0.0, load])[1])
    x_r[2] = 1.0
    acc1 = float(rigid.f(x_r, [0.0, load])[1])
    needed = -acc0 / (acc1 - acc0)
    if abs(needed) >= plant.torque_limit:
        raise SimulationError(
            f"holding {omega_nut:g} rad/s at {load:g} N needs {needed:.3g} N m, beyond the motor "
            f"limit of {plant.torque_limit:g} N m (drive.torque_limit_n_m); lower the load"
        )
    model = plant_model(plant, fidelity, seed)
    solver = _solver(model)
    free = model._free  # type: ignore[attr-defined]
    x0 = _guess(model, omega_nut, load)
    x0[model.index("tau_motor")] = needed
    z0 = np.append(x0[free], x0[model.index("tau_motor")])
    try:
        z = np.asarray(solver(z0, [omega_nut, load])).ravel()
    except RuntimeError as exc:
        raise SimulationError(
            f"no steady state at nut speed {omega_nut:g} rad/s and load {load:g} N "
            f"(Newton failed from torque guess {z0[-1]:.4g} N m: {str(exc).splitlines()[-1]}); "
            "check that the load is within the plant's rating"
        ) from None
    x = x0.copy()
    x[free] = z[:-1]
    torque = float(z[-1])
    return OperatingPoint(x=x, torque=torque, omega_nut=float(omega_nut), load=float(load))
