"""Steady operating points of the actuator: constant nut speed under a constant axial load.

Every solve is bounded: the torque a steady state needs is computed first from the rigid
model (closed form, no iteration) and checked against the motor's torque limit, so absurd
loads or speeds are refused with a message naming the value and the limit before any Newton
step; the Newton solve itself stops after :data:`MAX_NEWTON_ITER` iterations.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from ..errors import SimulationError
from ..options import check_number
from .model import NUT_LOSS_KEY, PlantModel, nut_loss_on_whole_force, plant_model, screw_axis_springs, stick_band_rad_s
from .plantfile import Plant

__all__ = ["OperatingPoint", "operating_point", "steady_torque", "MAX_NEWTON_ITER"]

#: Iteration budget of the operating-point Newton solve (it converges in 3-12 iterations from
#: the quasi-static guess on every built-in plant and fidelity).
MAX_NEWTON_ITER = 50


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
    newton_iterations : int
        Newton iterations the solve took (at most :data:`MAX_NEWTON_ITER`).
    """

    x: NDArray[np.float64]
    torque: float
    omega_nut: float
    load: float
    newton_iterations: int = 0


_SOLVERS: "weakref.WeakKeyDictionary[PlantModel, dict[bool, ca.Function]]" = weakref.WeakKeyDictionary()


def _free(model: PlantModel) -> list[int]:
    """States solved for: every state but the angles and the (given) nut speed."""
    return [i for i, n in enumerate(model.state_names) if not n.startswith("theta_") and n != "omega_nut"]


def _solver(model: PlantModel, rest: bool) -> ca.Function:
    """Residual and Jacobian ``(z, p) -> (g, dg/dz)`` for the free states plus the torque
    command (``rest=False``), or, at rest, for the free states alone with the torque command
    given (stiction makes the nut equation hold for any torque within breakaway, so it is
    dropped and the torque is a parameter)."""
    per_model = _SOLVERS.setdefault(model, {})
    if rest in per_model:
        return per_model[rest]
    fam = getattr(model, "family", None)
    if fam is not None:  # a member of a parametric family: the family's solver with its values
        if ("solver", rest) not in fam.cache:
            fam.cache[("solver", rest)] = _solver(fam, rest)
        fun_theta, theta = fam.cache[("solver", rest)], ca.DM(list(model.theta))
        per_model[rest] = fun = lambda z, par: fun_theta(z, par, theta)
        return fun
    n_theta = getattr(model, "n_theta", None)  # the family model itself: theta is an input
    theta = ca.SX.sym("theta", n_theta) if n_theta is not None else None
    free = _free(model)
    z = ca.SX.sym("z", len(free) + (0 if rest else 1))
    par = ca.SX.sym("p", 3)  # omega_nut, load, torque command (used at rest only)
    x = [0] * model.nx
    x[model.index("omega_nut")] = par[0]
    for k, i in enumerate(free):
        x[i] = z[k]
    x = ca.vertcat(*x)
    rhs = model.f(x, ca.vertcat(par[2] if rest else z[-1], par[1]), *([] if theta is None else [theta]))
    skip = ("omega_nut",) if rest else ()
    eqs = ca.vertcat(*[rhs[i] for i, n in enumerate(model.state_names)
                       if not n.startswith("theta_") and n not in skip])
    fun = ca.Function("g", [z, par] + ([] if theta is None else [theta]), [eqs, ca.jacobian(eqs, z)])
    per_model[rest] = fun
    return fun


def _newton(fun: ca.Function, z0: NDArray[np.float64], par: list[float], scale: NDArray[np.float64]):
    """Damped Newton (Deuflhard's natural monotonicity test on the scaled step), at most
    :data:`MAX_NEWTON_ITER` iterations and 12 halvings per iteration. Returns the root and the
    iteration count, or raises :class:`RuntimeError` with the reason."""
    z = np.array(z0, dtype=float)
    for it in range(1, MAX_NEWTON_ITER + 1):
        g, jac = (np.asarray(v, dtype=float) for v in fun(z, par))
        g = g.ravel()
        if not (np.all(np.isfinite(g)) and np.all(np.isfinite(jac))):
            raise RuntimeError(f"non-finite residual or Jacobian at iteration {it}")
        if np.linalg.cond(jac) > 1e15:
            # A continuum of equilibria (e.g. the roller assembly floating in its backlash at
            # exactly 0 N): the minimum-norm Newton step goes to the nearest one; if it does not
            # close the residual, a body has lost all its contacts.
            dz = np.linalg.lstsq(jac, -g, rcond=None)[0]
            g_new = np.asarray(fun(z + dz, par)[0], dtype=float).ravel()
            g_ref = np.abs(jac) @ np.abs(scale) + np.abs(g)
            if np.all(np.isfinite(g_new)) and np.all(np.abs(g_new) <= 1e-9 * np.maximum(g_ref, 1e-300)):
                return z + dz, it
            raise RuntimeError(f"singular Jacobian at iteration {it} (a body lost all its contacts)")
        dz = np.linalg.solve(jac, -g)
        size = np.linalg.norm(dz / scale)
        if size < 1e-10:
            return z + dz, it
        alpha = 1.0
        for _ in range(12):
            z_new = z + alpha * dz
            g_new = np.asarray(fun(z_new, par)[0], dtype=float).ravel()
            if np.all(np.isfinite(g_new)) and np.linalg.norm(np.linalg.solve(jac, -g_new) / scale) <= (
                1.0 - 0.5 * alpha
            ) * size:
                break
            alpha *= 0.5
        else:
            raise RuntimeError(f"no descent along the Newton step at iteration {it}")
        z = z_new
    raise RuntimeError(f"no convergence in {MAX_NEWTON_ITER} iterations")


def _scale(model: PlantModel, rest: bool, torque_scale: float) -> NDArray[np.float64]:
    """Typical magnitudes of the unknowns (for the Newton step norm)."""
    p = model.plant
    per_contact = p.rated_load_n * max(p.normal_force_factor()) / p.n_contacts
    defl = (per_contact / p.contact_stiffness_si) ** (1.0 / p.values["contact.exponent"])
    typical = {"omega_cage": 100.0, "x_roller": defl, "v_roller": p.lead_per_rad * 100.0,
               "delta_screw": defl, "v_screw": p.lead_per_rad * 100.0, "tau_motor": torque_scale}
    typical.update(model.state_scales or {})  # a screw-driven axis: its spring deflections
    out = [typical.get(model.state_names[i], 1.0) for i in _free(model)]
    return np.array(out if rest else out + [torque_scale])


def _guess(model: PlantModel, omega: float, load: float) -> NDArray[np.float64]:
    p = model.plant
    k = p.kinematics(omega)
    x = np.zeros(model.nx)
    x[model.index("omega_nut")] = omega
    names = model.state_names
    f_n, f_s = p.normal_force_factor()
    if p.screw_driven and "delta_screw" in names:  # the springs carry the load (model._screw_driven)
        k_h, _, k_b, _, _ = (float(z) for z in screw_axis_springs(p))
        x[model.index("v_screw")] = float(k.v_screw)
        x[model.index("delta_screw")] = load / k_h
        x[model.index("x_roller")] = -load / k_b
    elif "omega_cage" in names:
        c_b = math.cos(p.flank_angle_rad)
        k_si, e = p.contact_stiffness_si, p.values["contact.exponent"]

        def axial(fac: float, cos_l: float) -> float:
            per_contact = abs(load) * fac / p.n_contacts
            pen = (per_contact / k_si) ** (1.0 / e) / (c_b * cos_l)
            # A pulling load engages the opposite flank, beyond the axial backlash.
            return pen if load >= 0 else -(pen + p.values["thread.backlash_mm"] * 1e-3)

        x[model.index("omega_cage")] = float(k.omega_cage)
        x[model.index("v_screw")] = float(k.v_screw)
        x[model.index("v_roller")] = float(k.v_screw)  # the rollers travel with the screw
        x[model.index("x_roller")] = -axial(f_n, math.cos(p.helix_nut_rad))
        x[model.index("delta_screw")] = axial(f_s, math.cos(p.helix_screw_rad))
    return x


def steady_torque(plant: Plant, omega_nut: float, load: float) -> float:
    """Motor torque (N m) that holds the nut at constant ``omega_nut`` (rad/s) against the axial
    ``load`` (N), from the rigid model in closed form (no iteration, no torque limit check).

    At rest (``omega_nut == 0``) stiction holds any torque within the breakaway torque; the
    friction-free hold ``load L/(2 pi)`` is returned. The compliant models need the same torque
    at steady state (same friction law on the same normal forces).

    Raises
    ------
    ValueError
        For a non-finite speed or load, or a speed inside the stick band
        ``0 < |omega_nut| < 2 w_b`` (the nut sticks there: no constant-speed steady state).

    Examples
    --------
    >>> from prsa_ctrl import load_plant
    >>> round(steady_torque(load_plant(), 31.4159, 5000.0), 4)   # 0.85 efficient, plus drag
    1.8956
    """
    omega = check_number("omega_nut", omega_nut, unit="rad/s")
    f = check_number("load", load, unit="N")
    if omega == 0.0:
        return f * plant.lead_per_rad
    band = stick_band_rad_s(plant)
    if abs(omega) < 2.0 * band:
        raise ValueError(
            f"omega_nut = {omega_nut!r} rad/s lies in the stick band |omega| < {2 * band:.3g} rad/s "
            f"(screw slower than 2 x friction.transition_velocity_m_s = "
            f"{2 * plant.values['friction.transition_velocity_m_s']:g} m/s), where the nut sticks; "
            "expected 0 (at rest) or a speed outside the band"
        )
    if nut_loss_on_whole_force(plant):
        # at constant speed the force through the nut is the load: the law with the loss on
        # the external load gives the same holding torque, and its friction does not depend on
        # the acceleration (the one evaluation below needs that)
        plant = plant.with_params({NUT_LOSS_KEY: 0}, name=plant.name)
    rigid = plant_model(plant, "rigid")
    # Outside the stick band the rigid nut equation is J dw/dt = tau - T(w, load): one
    # evaluation at tau = 0 gives the holding torque exactly (no difference quotient).
    with np.errstate(all="ignore"):
        acc0 = float(rigid.f([0.0, omega, 0.0], [0.0, f])[1])
    return -acc0 * plant.reflected_inertia_kg_m2


def _check_torque_limit(plant: Plant, omega: float, load: float, needed: float) -> None:
    limit = plant.torque_limit
    if math.isfinite(needed) and abs(needed) < limit:
        return
    # Largest load of the same sign the limit holds at this speed: the holding torque is
    # affine in the load for a given speed and load sign (friction ~ |load|).
    sign = 1.0 if load >= 0 else -1.0
    ref = sign * plant.rated_load_n
    t0, t1 = steady_torque(plant, omega, 0.0), steady_torque(plant, omega, ref)
    slope = (t1 - t0) / ref
    what = f"holding {omega:g} rad/s at {load:g} N needs "
    what += f"{needed:.3g} N m" if math.isfinite(needed) else "an unbounded torque"
    what += f", beyond the motor limit of {limit:g} N m (drive.torque_limit_n_m)"
    if abs(t0) >= limit:
        hint = f"; even unloaded this speed needs {t0:.3g} N m: lower the speed"
    else:
        f_max = (math.copysign(limit, slope * sign) - t0) / slope if slope != 0 else math.inf
        hint = f"; at this speed the motor holds loads up to {f_max:.4g} N: lower the load"
    raise SimulationError(what + hint)


def _solve(model: PlantModel, omega: float, load: float, torque: float) -> OperatingPoint:
    """Newton solve of ``model`` at speed ``omega`` and ``load`` from the quasi-static guess,
    with ``torque`` the rigid holding torque (the guess, or the given command at rest)."""
    rest = omega == 0.0
    fun = _solver(model, rest)
    free = _free(model)
    x0 = _guess(model, omega, load)
    x0[model.index("tau_motor")] = torque
    z0 = x0[free] if rest else np.append(x0[free], torque)
    try:
        with np.errstate(all="ignore"):
            z, iters = _newton(fun, z0, [omega, load, torque], _scale(model, rest, model.plant.torque_limit))
    except (RuntimeError, np.linalg.LinAlgError) as exc:
        raise SimulationError(
            f"no steady state at nut speed {omega:g} rad/s and load {load:g} N "
            f"(Newton from torque guess {torque:.4g} N m: {exc}); check that the load is within the "
            "plant's rating and that the roller tolerances (tolerance.roller_position_std_um) keep every "
            "roller in contact"
        ) from None
    x = x0.copy()
    x[free] = z[: len(free)]
    tau = torque if rest else float(z[-1])
    if not np.all(np.isfinite(x)) or not math.isfinite(tau):
        raise SimulationError(
            f"no finite steady state at nut speed {omega:g} rad/s and load {load:g} N; "
            "check that the load is within the plant's rating"
        )
    return OperatingPoint(x=x, torque=tau, omega_nut=omega, load=load, newton_iterations=iters)


def operating_point(
    plant: Plant, omega_nut: float, load: float, fidelity: str = "compliant", seed: int = 0
) -> OperatingPoint:
    """Equilibrium at constant nut speed ``omega_nut`` (rad/s) and axial load ``load`` (N).

    For the multi-roller fidelity this is the balance at cage angle 0 (the roller runout makes
    the true steady state periodic). At rest (``omega_nut = 0``) the torque is the
    friction-free hold (see :func:`steady_torque`).

    Parameters
    ----------
    plant : Plant
    omega_nut : float
        Nut speed, rad/s: 0 (at rest) or outside the stick band.
    load : float
        Axial load, N (positive opposes forward screw motion).
    fidelity : {"rigid", "compliant", "multi-roller"}
    seed : int
        Seed of the roller errors (multi-roller only).

    Returns
    -------
    OperatingPoint

    Raises
    ------
    ValueError
        For a non-finite speed or load, or a speed inside the stick band.
    SimulationError
        If the motor's torque limit cannot hold the load at this speed (the message gives the
        largest load it holds, N), or the Newton solve does not converge within
        :data:`MAX_NEWTON_ITER` iterations.

    Examples
    --------
    >>> from prsa_ctrl import load_plant
    >>> op = operating_point(load_plant(), 31.4159, 1500.0)
    >>> round(op.torque, 4), op.newton_iterations <= MAX_NEWTON_ITER
    (0.5849, True)
    """
    omega = check_number("omega_nut", omega_nut, unit="rad/s")
    f = check_number("load", load, unit="N")
    needed = steady_torque(plant, omega, f)
    _check_torque_limit(plant, omega, f, needed)
    return _solve(plant_model(plant, fidelity, seed), omega, f, needed)
