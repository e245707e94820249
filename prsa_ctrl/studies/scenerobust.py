"""A scene's robust-tuning study: its operating range, its scenario models (nominal point,
vertices and seeded samples of the uncertainty box x operating points) and their loop models,
read from the scene's ``[uncertainty]`` and ``[robust]`` sections; the tuning itself is
:func:`prsa_ctrl.tuning.robust.tune_scenario_loops` (numbers and loop models only).
"""

from __future__ import annotations

import time
from typing import Sequence

import numpy as np

from ..options import rad_s_to_rpm, rpm_to_rad_s
from ..textsafe import quote
from ..errors import SceneError
from ..plant.uncertainty import UncertaintyModel, apply, uncertainty_model
from .scenesections import Robust
from ..tuning.loops import LoopModel
from ..tuning.robust import RobustTuning, Scenario, tune_scenario_loops
from ..tuning.actuatorloops import step_loops
from .kindruns import speed_kind
from .sceneloops import loop_spec

__all__ = ["operating_points", "scenarios", "scenario_loops", "tune_robust_actuator"]

#: Upper bound on scenario models in one NLP (each adds a loop model and its constraints).
MAX_SCENARIOS = 64


def operating_points(scene) -> list[tuple[float, float]]:
    """The scene's operating range: (setpoint rad/s, final load N) for every setpoint in
    ``[robust] setpoints_rpm`` (default the scene's) and every final load in
    ``[robust] final_loads_n`` (default the scene's)."""
    if not speed_kind(scene).takes("robust"):
        raise SceneError(f"{scene.origin}: scene {scene.name} is a duty cycle ({scene.profile_source}); expected a "
                         "load-step scene (the robust and Monte-Carlo studies run load steps)")
    rob = scene.sections.robust or Robust()
    sps = [rpm_to_rad_s(v) for v in rob.setpoints_rpm] or [scene.setpoint_rad_s]
    loads = list(rob.final_loads_n) or list(scene.final_loads)
    for f in loads:
        if f == scene.initial_load:
            raise SceneError(f"{scene.origin}: robust.final_loads_n contains {f:g}; expected loads different "
                             f"from the initial {scene.initial_load:g} N")
    return [(sp, f) for sp in sps for f in loads]


def scenarios(plant, scene, *, unc: UncertaintyModel | None = None, vertices: bool | None = None,
              samples: int | None = None, seed: int | None = None,
              max_scenarios: int | None = None) -> list[Scenario]:
    """Scenario models of a scene: {nominal, box vertices, seeded samples} x operating points.

    Parameters
    ----------
    plant, scene
        The plant (its ``[uncertainty]``) and the scene (its ``[uncertainty]`` and ``[robust]``).
    unc : UncertaintyModel, optional
        Default :func:`prsa_ctrl.plant.uncertainty.uncertainty_model` of plant and scene.
    vertices : bool, optional
        Include the ``2**k`` corners of the box (default ``[robust] vertices`` or true).
    samples : int, optional
        Random interior points (default ``[robust] samples`` or 0), drawn from
        ``SeedSequence([seed, i, 1])`` (a stream distinct from the Monte-Carlo samples').
    max_scenarios : int, optional
        Bound checked before any model is built (default ``[robust] max_scenarios`` or 64).
    """
    rob = scene.sections.robust or Robust()
    unc = uncertainty_model(plant, scene.sections.plant_overrides) if unc is None else unc
    vertices = rob.vertices if vertices is None else vertices
    samples = rob.samples if samples is None else samples
    seed = rob.seed if seed is None else seed
    if max_scenarios is None:
        max_scenarios = MAX_SCENARIOS if rob.max_scenarios is None else rob.max_scenarios
    points: list[tuple[str, str, dict]] = [("nominal", "nominal", {})]
    if vertices and len(unc):
        if 2 ** len(unc) > max_scenarios:
            raise SceneError(f"{scene.origin}: {len(unc)} uncertain parameters have {2 ** len(unc)} vertices, above "
                             f"max_scenarios = {max_scenarios}; expected robust.vertices = false and robust.samples")
        points += [(f"vertex {j}", "vertex", v) for j, v in enumerate(unc.vertices())]
    for i in range(int(samples)):
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), i, 1]))
        points.append((f"sample {i}", "sample", unc.sample(rng)))
    ops = operating_points(scene)
    total = len(points) * len(ops)
    if total > max_scenarios:
        raise SceneError(f"{scene.origin}: {len(points)} parameter points x {len(ops)} operating points = {total} "
                         f"scenario models, above max_scenarios = {max_scenarios}; expected fewer")
    out = []
    for name, kind, vals in points:
        for sp, f1 in ops:
            label = f"{name} @ {rad_s_to_rpm(sp):g} rpm, {f1:g} N" if len(ops) > 1 else name
            out.append(Scenario(label, kind, dict(vals), float(sp), float(f1)))
    return out


def scenario_loops(plant, scene, scens: Sequence[Scenario]) -> list[LoopModel]:
    """One loop model per scenario (linearised at the scenario's mid load and setpoint)."""
    spec = loop_spec(plant, scene)
    sc = spec.scene
    horizon = sc.duration - sc.step_time
    kf_time = sc.load_change_time_s if sc.estimator == "kf" else None
    cache: dict = {}
    loops: list[LoopModel] = []
    for s in scens:
        key = tuple(sorted(s.values.items()))
        if key not in cache:
            cache[key] = apply(plant, s.values) if s.values else plant
        loops += step_loops(cache[key], setpoint_rad_s=s.setpoint_rad_s, initial_load_n=sc.initial_load,
                            final_loads_n=(s.final_load,), fidelity=spec.linear_fidelity, horizon_s=horizon,
                            discrete=sc.discrete, kf_load_change_time_s=kf_time, feedforward=sc.feedforward,
                            filters=tuple(sc.filters))
    return loops


def tune_robust_actuator(plant, scene, *, scens: Sequence[Scenario] | None = None,
                         aggregate: str | None = None) -> RobustTuning:
    """Tune the nominal design (nominal plant at the scene's operating points) and the robust
    design (every scenario model, one NLP), and compare them on all scenario models.

    Parameters
    ----------
    plant, scene
        Plant and scene (``[uncertainty]``, ``[robust]`` sections; Ms/Mt bounds from
        ``[spec]`` where it states them, else ``[tuning]``).
    scens : list of Scenario, optional
        Default :func:`scenarios`.
    aggregate : {"worst", "mean"}, optional
        Objective over scenarios (default ``[robust] aggregate`` or "worst").

    The Ms (Mt) bound of both designs is the scene's ``[spec]`` one where the spec states it
    (the bound the designs are judged by), else ``[tuning]`` ``ms_max`` (``mt_max``);
    ``comparison["ms_source"]`` (``"mt_source"``) says which.

    Returns
    -------
    RobustTuning
        Both designs, the comparison (per-scenario Ms and objective) and timings (s).
    """
    aggregate = aggregate or (scene.sections.robust or Robust()).aggregate
    if aggregate not in ("worst", "mean"):
        raise ValueError(f"aggregate = {quote(aggregate)}; expected 'worst' or 'mean'")
    unc = uncertainty_model(plant, scene.sections.plant_overrides)
    scens = list(scens) if scens is not None else scenarios(plant, scene, unc=unc)
    t0 = time.perf_counter()
    loops = scenario_loops(plant, scene, scens)
    spec = scene.sections.spec_bounds
    ms_max, ms_source = ((spec["ms"], "[spec] ms") if "ms" in spec else (scene.ms_max, "[tuning] ms_max"))
    mt_max, mt_source = ((spec["mt"], "[spec] mt") if "mt" in spec else (scene.mt_max, "[tuning] mt_max"))
    rt = tune_scenario_loops(loops, scens, unc=unc, objective=scene.objective, controller=scene.controller,
                             ms_max=ms_max, mt_max=mt_max, aggregate=aggregate,
                             timing_s={"linearize": time.perf_counter() - t0})
    rt.comparison["ms_source"] = ms_source
    if mt_max is not None:
        rt.comparison["mt_source"] = mt_source
    return rt
