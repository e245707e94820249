"""What the tuning pipeline reads from a speed-loop scene, read in one place: the scene's
problem resolved against the plant (:class:`~prsa_ctrl.studies.kindruns.ResolvedProblem`: the
kind's problem, the fidelities, the duty cycle's sampled records, the steady torque) and the
scene's loop models.

A :class:`~prsa_ctrl.studies.scene.Scene` is a studies-level object; the loop builders of
:mod:`prsa_ctrl.tuning.actuatorloops` take numbers and arrays only. The scene's kind resolves it
(:meth:`~prsa_ctrl.studies.kindruns.StepRuns.resolve`); what differs between the kinds (load
steps or a duty cycle) is asked of the problem (:mod:`prsa_ctrl.studies.kindruns`), not branched
on here.
"""

from __future__ import annotations

from ..plant.plantfile import Plant
from ..tuning.loops import LoopModel
from .kindruns import ResolvedProblem, duty_record, linear_fidelity, speed_kind
from .scene import Scene

__all__ = ["loop_spec", "linear_fidelity", "duty_record", "actuator_loops"]


def loop_spec(plant: Plant, scene: Scene) -> ResolvedProblem:
    """Read a scene once: its kind's problem resolved against the plant, with the scene's
    fidelity as it is (``"auto"`` stays; the loop models read it as compliant): what the loop
    models, the tuner and the prediction need (``speed_kind(scene).resolve(plant,
    choose=False)``). A tuning run resolves the fidelity too
    (:func:`~prsa_ctrl.studies.autotune.resolve_scene`).

    Parameters
    ----------
    plant : Plant
        Its sample time sets the duty cycle's records.
    scene : Scene

    Returns
    -------
    ResolvedProblem

    Raises
    ------
    TypeError
        ``scene`` is not a speed-loop :class:`~prsa_ctrl.studies.scene.Scene`.
    """
    return speed_kind(scene).resolve(plant, choose=False)


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
