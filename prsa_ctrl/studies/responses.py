"""What the standard figures of a design show, computed here so that :mod:`prsa_ctrl.plots`
only draws: loop responses, the linearised plant, the predicted and verified design, the
baseline comparisons, a +10 % setpoint step and the contact forces of a continuous run.

:func:`design_responses` serves given gains (``prsa-plot``), :func:`report_responses` a
tuning report (``prsa-tune --plots``); both return a frozen :class:`FigureData`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._lazy import module
from ..options import rad_s_to_rpm
from ..drive.pid import PID
from ..drive.linear_loop import closed_loop
from ..plant.linear import linearize
from ..plant.plantfile import Plant
from ..sim.metrics import Margins
from ..sim.signals import PiecewiseLinear, normalise_profile
from ..sim.engine import simulate
from .autotune import ActuatorTuning, Design, actuator_loops, linear_fidelity, predict, verify
from .scene import Scene, choose_fidelity
from .kindruns import speed_kind

control = module("control")

__all__ = ["FigureData", "SetpointStep", "ContactRun", "Landscape", "landscape", "design_responses", "stable_design_responses",
           "report_responses", "binding_level",
           "objective_value", "duty_input", "SETPOINT_STEP_FRACTION", "CONTACT_RUN_S"]

#: Size of the setpoint step of :func:`design_responses`, relative to the scene's setpoint.
SETPOINT_STEP_FRACTION = 0.1
#: Time after the load step simulated for the contact-force figure, s (continuous run, 10 us grid).
CONTACT_RUN_S = 0.03


@dataclass(frozen=True)
class SetpointStep:
    """A setpoint step at the scene's initial load: nonlinear run and linear closed loop.

    Attributes
    ----------
    time_s, speed_rad_s : array
        Nonlinear run (s, rad/s).
    linear_time_s, linear_speed_rad_s : array
        Linear closed loop's step response, shifted to the step time (s, rad/s).
    from_rad_s, to_rad_s : float
        Setpoint before and after the step, rad/s.
    load_n : float
        Axial load, N.
    """

    time_s: np.ndarray
    speed_rad_s: np.ndarray
    linear_time_s: np.ndarray
    linear_speed_rad_s: np.ndarray
    from_rad_s: float
    to_rad_s: float
    load_n: float


@dataclass(frozen=True)
class ContactRun:
    """Thread contact forces over a load step, from a continuous run on a fine grid.

    Attributes
    ----------
    time_s : array, s
    outputs : dict
        Simulator outputs (``contact_force_nut``, ``contact_force_screw`` in N, ...).
    static_n : (float, float)
        Static normal force of the nut and screw interfaces at the final load, N.
    final_load_n : float
        Final load of the step, N.
    """

    time_s: np.ndarray
    outputs: dict
    static_n: tuple[float, float]
    final_load_n: float


@dataclass(frozen=True)
class Landscape:
    """The objective and the peaks Ms, Mt over a (kp, ki) grid, ``kd = 0`` (:func:`landscape`).

    Attributes
    ----------
    kp : array, N m s/rad
        Grid axis (``n`` values).
    ki : array, N m/rad
        Grid axis (``n`` values).
    objective : array
        Shape ``(n_ki, n_kp)``: the objective (aggregated over the levels), nan where a level is
        unstable.
    ms, mt : array
        Same shape: the largest Ms and Mt over the levels on the loops' frequency grids.
    stable : bool array
        Same shape: every level stable.
    aggregate : {"sum", "worst"}
    levels : int
        Loop models (load levels) aggregated.
    """

    kp: np.ndarray
    ki: np.ndarray
    objective: np.ndarray
    ms: np.ndarray
    mt: np.ndarray
    stable: np.ndarray
    aggregate: str
    levels: int


def landscape(loops, objective: str, centre=(), n: int = 40, aggregate: str = "sum") -> Landscape:
    """Evaluate the loop models over a log grid of (kp, ki) around the median of ``centre``.

    Parameters
    ----------
    loops : LoopModel or list of LoopModel
        One per load level.
    objective : str
        One of :data:`prsa_ctrl.options.OBJECTIVES`.
    centre : sequence of PID
        Designs the grid is centred on (kp from 0.1 to 4 x, ki from 0.03 to 10 x their median);
        none: kp, ki around 1.
    n : int
        Grid points per axis.
    aggregate : {"sum", "worst"}
        How the levels' objectives combine.

    Returns
    -------
    Landscape
    """
    loops = list(loops) if isinstance(loops, (list, tuple)) else [loops]
    pts = list(centre)
    kp0 = np.median([p.kp for p in pts]) if pts else 1.0
    ki0 = np.median([p.ki for p in pts]) if pts else 1.0
    kps = kp0 * np.logspace(-1, math.log10(4), n)
    kis = ki0 * np.logspace(-1.5, 1, n)
    KP, KI = np.meshgrid(kps, kis)
    grid = np.column_stack([KP.ravel(), KI.ravel(), np.zeros(KP.size)])
    ms = np.zeros(KP.size)
    mt = np.zeros(KP.size)
    stable = np.ones(KP.size, bool)
    for lp in loops:
        n0, ln, d0, ld = lp.parts()
        L = (n0 + grid @ ln) / (d0 + grid @ ld)
        ms = np.maximum(ms, np.max(1 / np.abs(1 + L), axis=1))
        mt = np.maximum(mt, np.max(np.abs(L / (1 + L)), axis=1))
        stable &= np.array([lp.is_stable(g) for g in grid])
    obj = np.full(KP.size, np.nan)
    idx = np.flatnonzero(stable)
    if idx.size:
        vals = np.array([lp.objectives(grid[idx], objective) for lp in loops])
        obj[idx] = vals.max(axis=0) if aggregate == "worst" else vals.sum(axis=0)
    return Landscape(kps, kis, *(v.reshape(KP.shape) for v in (obj, ms, mt, stable)), aggregate, len(loops))


@dataclass(frozen=True)
class FigureData:
    """Everything the standard figures draw (frozen; computed by :func:`design_responses` or
    :func:`report_responses`).

    Attributes
    ----------
    plant : Plant
    scene : Scene
        With its fidelity resolved (:func:`~prsa_ctrl.studies.scene.choose_fidelity`).
    design : Design
        The design drawn: predicted and verified unless ``stability`` is ``"unstable"``.
    stability : {"stable", "marginal", "unstable"}
    plant_linear : control.StateSpace
        The plant linearised at the scene's setpoint and initial load.
    level : int
        Load level of the frequency plots (a report: the binding level).
    omega : array, rad/s
    loop : complex array
        Open loop ``L(j omega)`` of ``design`` at ``level``.
    margins : Margins
    sample_time_s : float or None
        Controller sample time of a sampled loop (Nyquist marked), None for a continuous one.
    loops : tuple of LoopModel
    baselines : tuple of Design
        A report's verified baselines (empty for given gains).
    pairs : tuple of (Design, Design)
        ``(baseline, verified tuned design at equal or lower Ms)`` (:meth:`ActuatorTuning.comparison_pairs`).
    setpoint_step : SetpointStep or None
    contact : ContactRun or None
    landscape : Landscape or None
        A report's objective over kp-ki around the best design and the baselines.
    """

    plant: Plant
    scene: Scene
    design: Design
    stability: str
    plant_linear: Any
    level: int
    omega: np.ndarray
    loop: np.ndarray
    margins: Margins
    sample_time_s: float | None
    loops: tuple = field(default=(), repr=False)
    baselines: tuple = field(default=(), repr=False)
    pairs: tuple = field(default=(), repr=False)
    setpoint_step: SetpointStep | None = field(default=None, repr=False)
    contact: ContactRun | None = field(default=None, repr=False)
    landscape: Landscape | None = field(default=None, repr=False)


def objective_value(metrics, objective: str) -> float:
    """The scene's objective from one level's metrics (IAE where the metrics lack it)."""
    return float(getattr(metrics, objective, getattr(metrics, "iae")))


def binding_level(design: Design, scene: Scene) -> int:
    """Index of the load level whose verified objective is largest (the worst case that
    binds a ``worst`` aggregate and dominates a ``sum``)."""
    vals = [objective_value(m, scene.objective) for m in design.verified]
    return int(np.argmax(vals)) if vals else 0


def duty_input(scene: Scene, case: str, t: np.ndarray) -> tuple[np.ndarray, str]:
    """The profile a duty-cycle record follows, at times ``t`` (s): load (N) or setpoint (rpm),
    with its axis label."""
    if case == "load profile":
        prof = normalise_profile(PiecewiseLinear(scene.load_profile), float(t[-1]) + 1.0, "load", "N")
        return prof.at(t), "axial load (N)"
    prof = normalise_profile(PiecewiseLinear(scene.setpoint_profile), float(t[-1]) + 1.0, "setpoint", "rad/s")
    return rad_s_to_rpm(prof.at(t)), "setpoint (rpm)"


def _plant_linear(plant: Plant, scene: Scene):
    return linearize(plant, scene.setpoint_rad_s, scene.initial_load, linear_fidelity(scene), sampled=scene.discrete)


def _setpoint_step(plant: Plant, scene: Scene, pid: PID, sys) -> SetpointStep:
    """+10 % setpoint step at the initial load: nonlinear run and the linear closed loop."""
    w0, dw, t_step, span = scene.setpoint_rad_s, SETPOINT_STEP_FRACTION * scene.setpoint_rad_s, 0.005, 0.1
    r = simulate(plant, setpoint=[(0.0, w0), (t_step, w0 + dw)], load=scene.initial_load, duration=t_step + span,
                 controller=pid, fidelity=scene.fidelity, discrete=scene.discrete)
    cl = closed_loop(sys, pid)
    tl = np.linspace(0.0, span, 2001)
    lin = control.step_response(cl, T=tl, input=0)
    y_lin = w0 + dw * np.asarray(lin.outputs).reshape(cl.noutputs, -1)[cl.output_labels.index("nut_speed")]
    return SetpointStep(np.asarray(r.time), np.asarray(r.outputs[0]), tl + t_step, y_lin, w0, w0 + dw,
                        scene.initial_load)


def _contact_run(plant: Plant, scene: Scene, pid: PID, level: int) -> ContactRun:
    """Continuous run on a 10 us grid over the step to ``scene.final_loads[level]``: the contact
    modes ring at kHz and show unaliased."""
    f1 = scene.final_loads[level]
    pre = min(scene.step_time, 2e-3)
    r = simulate(plant, setpoint=scene.setpoint_rad_s, load=[(0.0, scene.initial_load), (pre, f1)],
                 duration=pre + CONTACT_RUN_S, controller=pid, dt=1e-5)
    y = dict(zip(r.output_labels, np.asarray(r.outputs)))
    k_n, k_s = plant.normal_force_factor()
    return ContactRun(np.asarray(r.time) + scene.step_time - pre, y, (f1 * k_n, f1 * k_s), f1)


def design_responses(plant: Plant, scene: Scene, pid: PID, stability: str | None = None,
                     loops: list | None = None) -> FigureData:
    """What the figures of given gains show (no tuning): loop response at the first load
    level, the predicted and verified design and a +10 % setpoint step (the last two only
    for a loop that is not unstable: its time responses diverge).

    Parameters
    ----------
    plant : Plant
    scene : Scene
    pid : PID
    stability : {"stable", "marginal", "unstable"}, optional
        The loop's class (default: from the loop model).
    loops : list of LoopModel, optional
        The scene's loop models (default :func:`~prsa_ctrl.studies.autotune.actuator_loops`).

    Returns
    -------
    FigureData
    """
    scene, _ = choose_fidelity(scene)
    loops = actuator_loops(plant, scene) if loops is None else loops
    lp = loops[0]
    g = pid.gains
    stability = stability or (lp.stability(g) if hasattr(lp, "stability") else
                              ("stable" if lp.is_stable(g) else "unstable"))
    design = Design("given gains", pid, lp.margins(g))
    sys = _plant_linear(plant, scene)
    step = None
    if stability != "unstable":
        design = verify(predict(design, loops, plant, scene), plant, scene)
        step = _setpoint_step(plant, scene, pid, sys)
    return FigureData(plant, scene, design, stability, sys, 0, lp.omega, lp.loop_response(g), design.margins,
                      plant.sample_time_s if scene.discrete else None, tuple(loops), setpoint_step=step)


def stable_design_responses(plant: Plant, scene: Scene, pid: PID) -> FigureData:
    """:func:`design_responses` of stabilising gains.

    Raises
    ------
    ValueError
        If the gains do not stabilise the loop (first load level).
    """
    scene, _ = choose_fidelity(scene)
    loops = actuator_loops(plant, scene)
    if not loops[0].is_stable(pid.gains):
        raise ValueError(f"the loop with {pid} is unstable on {plant.name}; expected stabilising gains")
    return design_responses(plant, scene, pid, "stable", loops)


def report_responses(report: ActuatorTuning) -> FigureData:
    """What the standard figures of a tuning report show: the best design's loop response at
    its binding load level, the plant linearised at the initial load, the baseline pairs and,
    for a compliant model and a load-step scene, a continuous run's contact forces.

    Parameters
    ----------
    report : ActuatorTuning

    Returns
    -------
    FigureData
    """
    sc, best, plant = report.scene, report.best, report.plant
    kb = binding_level(best, sc)
    lp = report.loops[kb] if len(report.loops) > kb else report.loops[0]
    g = best.pid.gains
    contact = None
    if sc.fidelity in ("compliant", "multi-roller") and speed_kind(sc).takes("contact-run"):
        contact = _contact_run(plant, sc, best.pid, kb)
    land = landscape(list(report.loops), sc.objective, [best.pid, *(b.pid for b in report.baselines)],
                     aggregate=sc.aggregate)
    return FigureData(plant, sc, best, "stable", _plant_linear(plant, sc), kb, lp.omega, lp.loop_response(g),
                      lp.margins(g), plant.sample_time_s if sc.discrete else None, tuple(report.loops),
                      tuple(report.baselines), tuple(report.comparison_pairs()), contact=contact, landscape=land)
