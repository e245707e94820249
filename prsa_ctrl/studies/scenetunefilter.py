"""``prsa-tune --tune-filter notch|lowpass``: a filter tuned with the gains on a scene's loops.

The filter's parameters come from :func:`prsa_ctrl.tuning.filtered.tune_filtered` (the speed PI
and the filter in one NLP, Ms and the scene's Mt and Mks bounds on the loops linearised at the initial,
mid and final loads of each step, judged against the gains alone under the same bounds: kept only
if it lowers the objective by at least 1 % and, for a notch, is at least 3 dB deep near the mode).
A kept filter joins the scene's filters; the scene is then tuned, predicted and verified as any
scene with filters (:func:`~prsa_ctrl.studies.autotune.tune_actuator`: its gains are the scene
tuner's with the filter in the loop). A filter that does not help is reported with the reason
and the scene is tuned without it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..errors import SceneError
from ..plant.linear import linear_core
from ..plant.model import plant_model
from ..plant.plantfile import Plant
from ..tuning.filtered import FilteredDesign, loop_builder, tune_filtered
from ..tuning.actuatorloops import derivative_filter_s
from ..tuning.loopmeasure import KalmanEstimate
from ..drive.estimator import design_kf
from ..tuning.tuner import Tuner
from .paper import default_pid
from .scene import Scene, choose_fidelity
from .scenefilters import FILTER_PATHS, filter_rows
from .kindruns import speed_kind
from .sceneloops import loop_spec

__all__ = ["TUNED_FILTERS", "SceneFilterTuning", "check_tune_filter", "tune_scene_filter"]

#: ``--tune-filter`` kinds: the filter tuned (:data:`prsa_ctrl.tuning.filtered.TUNABLE`) and its path.
TUNED_FILTERS = {"notch": ("notch", "torque"), "lowpass": ("lowpass1", "speed"), "lowpass2": ("lowpass2", "speed")}


@dataclass(frozen=True)
class SceneFilterTuning:
    """Outcome of :func:`tune_scene_filter`.

    Attributes
    ----------
    kind : str
        As asked (``"notch"``, ``"lowpass"``, ``"lowpass2"``).
    path : str
        ``"torque"`` (the torque command) or ``"speed"`` (the measured speed).
    design : FilteredDesign
        The joint gains + filter result (``status`` ``"optimal"``, ``"no <kind> helps: ..."``
        or ``"not converged: ..."``).
    reference : FilteredDesign
        The gains alone under the same bounds.
    scene : Scene
        The scene to tune: with the kept filter appended to its filters, or as it was.
    sample_time_s : float, s
    """

    kind: str
    path: str
    design: FilteredDesign
    reference: FilteredDesign
    scene: Scene
    sample_time_s: float

    @property
    def kept(self) -> bool:
        """The tuned filter earned its place and is in :attr:`scene`."""
        return self.design.filter is not None

    @property
    def status(self) -> str:
        return self.design.status

    @property
    def warnings(self) -> tuple[str, ...]:
        return self.design.warnings

    def as_dict(self) -> dict:
        d = self.design
        benefit = (1.0 - d.objective / self.reference.objective) if self.kept and self.reference.objective > 0 else None
        return {"kind": self.kind, "path": self.path, "status": d.status, "kept": self.kept,
                "filter": filter_rows([d.filter], self.sample_time_s)[0] if self.kept else None,
                "rejected_filter": d.stats.get("rejected_filter"),
                "objective_with_filter": d.objective, "objective_gains_alone": self.reference.objective,
                "relative_improvement": benefit,
                "gains_with_filter": d.pid.as_dict(), "gains_alone": self.reference.pid.as_dict(),
                "ms": d.ms, "mks": d.mks, "warnings": list(d.warnings),
                "note": "objective: the load-step IAE to infinity of the loops at each step's mid load (rad); the "
                        "reported gains are then the scene tuner's with the kept filter in the loop"}

    def lines(self) -> list[str]:
        """The text report's lines."""
        d, r = self.design, self.reference
        where = "the torque command" if self.path == "torque" else "the measured speed"
        if self.kept:
            return [f"Filter tuned with the gains ({self.kind} on {where}): {d.status}; IAE to infinity "
                    f"{d.objective:.4g} rad against {r.objective:.4g} rad with the gains alone "
                    f"({100 * (1 - d.objective / r.objective):.1f} % lower), Ms {d.ms:.3f}"
                    + (f", Mks {d.mks:.3g} N m s/rad" if d.mks is not None else "") + "; kept (in the filters above)"]
        return [f"Filter tuned with the gains ({self.kind} on {where}): {d.status}; not kept, the scene "
                "is tuned without it"]


def check_tune_filter(scene, kind: str) -> None:
    """Refuse ``--tune-filter`` where the filter tuner does not apply (one line).

    Raises
    ------
    SceneError
        An unknown kind, a duty cycle or a continuous loop.
    """
    if kind not in TUNED_FILTERS:
        raise SceneError(f"--tune-filter {kind}: expected one of {', '.join(TUNED_FILTERS)}")
    if not speed_kind(scene).takes("tune-filter"):
        raise SceneError(f"--tune-filter {kind}: scene {scene.name} is a duty cycle; expected a load-step scene (the "
                         "filter tuner's objective is the load step)")
    if not scene.discrete:
        raise SceneError(f"--tune-filter {kind}: expected a sampled loop (discrete = true; the filters run at the "
                         "sample time)")


def tune_scene_filter(plant: Plant, scene: Scene, kind: str) -> SceneFilterTuning:
    """Tune a filter with the gains on the scene's load steps (module docstring).

    Parameters
    ----------
    plant : Plant
    scene : Scene
        A sampled load-step scene; its own filters stay fixed. With the Kalman filter
        (``estimator = "kf"``) the loops measure the speed with it (and tune its load
        feed-forward gain with the PI when the scene feeds the load forward); the filter tuner's
        Ms rows then carry the loop's denominator part
        (:func:`prsa_ctrl.tuning.filtered.sensitivity_rows`).
    kind : {"notch", "lowpass", "lowpass2"}
        A notch on the torque command, or a first- / second-order low-pass on the measured speed.

    Returns
    -------
    SceneFilterTuning
    """
    check_tune_filter(scene, kind)
    tuned_kind, path = TUNED_FILTERS[kind]
    resolved, _ = choose_fidelity(scene)
    spec = loop_spec(plant, resolved)
    sc = spec.scene
    model = plant_model(plant, spec.linear_fidelity)
    i_speed = model.output_names.index("nut_speed")
    ts = plant.sample_time_s
    if sc.estimator == "kf":
        meas = {"measurement": KalmanEstimate(design_kf(plant, sc.load_change_time_s), sc.feedforward)}
    else:
        meas = {"speed_filter": plant.speed_filter_s}

    def builder(load: float, step: float, name: str):
        a, b, c, _, _ = linear_core(plant, sc.setpoint_rad_s, load, spec.linear_fidelity)
        return loop_builder(a, b, c[i_speed], model.index("theta_nut"), ts=ts, tf=derivative_filter_s(plant),
                            horizon=sc.duration - sc.step_time, step=step, fixed=tuple(sc.filters), name=name,
                            command_delay_samples=plant.command_delay_samples, **meas)

    f0 = sc.initial_load
    objective = [builder(0.5 * (f0 + f1), f1 - f0, f"step to {f1:g} N") for f1 in sc.final_loads]
    constraint = [builder(load, f1 - f0, f"{load:g} N") for f1 in sc.final_loads for load in (f0, f1)]
    start = Tuner(spec.loop_models(plant), objective=sc.objective, controller="pi").tune(ms_max=sc.ms_max).pid
    if not (start.kp > 0 and start.ki > 0 and math.isfinite(start.kp) and math.isfinite(start.ki)):
        start = default_pid(plant)
    common = dict(ts=ts, ms_max=sc.ms_max, mt_max=sc.mt_max, max_noise_gain=sc.mks_max,
                  start_kff=min(max(start.kff, 0.0), 1.0) if sc.feedforward else 0.0)
    ref = tune_filtered(objective, constraint, kind=None, start_gains=(start.kp, start.ki), **common)
    des = tune_filtered(objective, constraint, kind=tuned_kind, place=FILTER_PATHS[path],
                        start_gains=(ref.pid.kp, ref.pid.ki), reference=ref, **common)
    out = scene
    if des.filter is not None:
        freq = des.filter.filter.characteristic_hz
        out = scene.replace(filters=(*scene.filters, des.filter),
                            filter_labels=(*scene.filter_labels, f"--tune-filter {kind}: tuned at {freq:.6g} Hz"))
    return SceneFilterTuning(kind, path, des, ref, out, ts)
