"""What the tuning pipeline reads from a speed-loop scene, read in one place: the resolved
numbers of the scene's problem (plain numbers and the duty cycle's sampled records) and the
scene's loop models.

A :class:`~prsa_ctrl.studies.scene.Scene` is a studies-level object; the loop builders of
:mod:`prsa_ctrl.tuning.actuatorloops` take numbers and arrays only. :func:`loop_spec` reads the
scene once into the internal :class:`LoopSpec` of the pipeline of
:mod:`prsa_ctrl.studies.autotune`; what differs between the kinds (load steps or a duty cycle)
is asked of the spec's ``problem`` (:mod:`prsa_ctrl.studies.kindruns`), not branched on here.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from ..plant.equilibrium import operating_point
from ..plant.plantfile import Plant
from ..tuning.loops import LoopModel
from .kindruns import duty_record, speed_kind
from .scene import Scene

__all__ = ["LoopSpec", "loop_spec", "linear_fidelity", "duty_record", "actuator_loops"]


@dataclass(frozen=True)
class LoopSpec:
    """Every number the tuning pipeline reads from a speed-loop scene (frozen), under the
    scene's names, with the scene's problem (its kind).

    Internal to the pipeline: built by :func:`loop_spec`; the stages of
    :func:`~prsa_ctrl.studies.autotune.tune_actuator` read this object instead of the scene. The
    public functions (:func:`actuator_loops`, ``autotune.predict``, ``verify``, ...) take the
    scene.
    """

    setpoint_rad_s: float  #: nut-speed setpoint, rad/s
    initial_load: float  #: axial load before the step (duty cycle: at t = 0), N
    final_loads: tuple[float, ...]  #: axial load after each step, N (one loop per value)
    step_time: float  #: time of the load step, s
    duration: float  #: end of the record, s
    fidelity: str  #: the simulator's fidelity (as resolved by ``choose_fidelity``)
    linear_fidelity: str  #: the fidelity the loop models are linearised at (:func:`linear_fidelity`)
    discrete: bool  #: sampled drive (True) or continuous controller
    estimator: str  #: speed measurement: ``"none"`` or ``"kf"``
    feedforward: bool  #: load feed-forward from the Kalman filter's load estimate
    load_change_time_s: float  #: the Kalman filter's load-change time scale, s
    setpoint_weight: float  #: 2-DOF setpoint weight b
    problem: Any = field(repr=False, compare=False)  #: the scene's kind (:func:`~prsa_ctrl.studies.kindruns.speed_kind`)
    cases: tuple[str, ...]  #: one label per loop / verified record
    records: tuple[dict, ...]  #: the problem's sampled records (duty cycle: :func:`duty_record` per case)
    objective: str  #: "ie", "iae", "itae" or "ise"
    aggregate: str  #: "sum" or "worst" over the loops
    goal: str  #: duty cycle: "load", "setpoint" or "mix"
    setpoint_share: float  #: duty cycle, goal "mix": weight of the setpoint record
    controller: str  #: "pi" or "pid"
    ms_max: float  #: peak-sensitivity bound
    mt_max: float | None  #: peak complementary-sensitivity bound
    mks_max: float | None  #: peak noise-sensitivity bound, N m s/rad
    candidates: int  #: designs verified per run
    accuracy: float  #: relative accuracy the verification is held to
    steady_torque_n_m: float  #: motor torque holding the setpoint at the initial load, N m (linear fidelity)
    filters: tuple = ()  #: the drive's loop filters (:class:`~prsa_ctrl.drive.filters.LoopFilter`), in every loop and run

    def loop_models(self, plant: Plant, estimator: str | None = None) -> list[LoopModel]:
        """The problem's loop models (:func:`actuator_loops`) from the resolved numbers."""
        return self.problem.loop_models(plant, self, self.estimator if estimator is None else estimator)


def linear_fidelity(scene: Scene) -> str:
    """The fidelity the loop models are linearised at: the scene's, except that the
    multi-roller model (periodic in the cage angle) is replaced by the compliant model, its
    mean behaviour.

    Parameters
    ----------
    scene : Scene

    Returns
    -------
    str
    """
    return "compliant" if scene.fidelity in ("multi-roller", "auto") else scene.fidelity


def loop_spec(plant: Plant, scene: Scene) -> LoopSpec:
    """Read a scene once: the numbers the loop models, the tuner, the prediction and the
    verification need.

    Parameters
    ----------
    plant : Plant
        Its sample time sets the duty cycle's records.
    scene : Scene
        Resolve ``fidelity = "auto"`` first (:func:`~prsa_ctrl.studies.scene.choose_fidelity`)
        when the spec is used for verification.

    Returns
    -------
    LoopSpec

    Raises
    ------
    TypeError
        ``scene`` is not a speed-loop :class:`~prsa_ctrl.studies.scene.Scene`.
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"scene = {type(scene).__name__}; expected a prsa_ctrl Scene (prsa_ctrl.load_scene)")
    prob = speed_kind(scene)
    lin = linear_fidelity(scene)
    return LoopSpec(
        setpoint_rad_s=scene.setpoint_rad_s, initial_load=scene.initial_load, final_loads=tuple(scene.final_loads),
        step_time=scene.step_time, duration=scene.duration, fidelity=scene.fidelity,
        linear_fidelity=lin, discrete=scene.discrete, estimator=scene.estimator,
        feedforward=scene.feedforward, load_change_time_s=scene.load_change_time_s,
        problem=prob, cases=tuple(scene.cases), records=prob.records(plant), **prob.tuning_fields(),
        objective=scene.objective, aggregate=scene.aggregate,
        controller=scene.controller, ms_max=scene.ms_max, mt_max=scene.mt_max, mks_max=scene.mks_max,
        candidates=scene.candidates, accuracy=scene.accuracy,
        steady_torque_n_m=operating_point(plant, scene.setpoint_rad_s, scene.initial_load, lin).torque,
        filters=tuple(getattr(scene, "filters", ())))


def actuator_loops(plant: Plant, scene: Scene, estimator: str | None = None) -> list[LoopModel]:
    """One loop model per final load, linearised at the mid load of the step (the response
    to a step is the same from any linearisation point; the mid load keeps the Jacobians
    closest to both ends); a duty cycle: one per record, linearised at the middle of its
    range. ``estimator`` (default: the scene's) selects the speed measurement: ``"none"`` for
    the drive's filtered difference, ``"kf"`` for the Kalman filter (with the load
    feed-forward gain as a fourth tuned gain when the scene asks for feed-forward).

    Parameters
    ----------
    plant : Plant
    scene : Scene
    estimator : {"none", "kf"}, optional

    Returns
    -------
    list of LoopModel
        Sampled drive loops (``scene.discrete``) or continuous loops, one per final load or record.
    """
    return loop_spec(plant, scene).loop_models(plant, estimator)
