"""The job every Monte-Carlo worker runs (:mod:`prsa_ctrl.studies.montecarlo`, and its batched path
:mod:`prsa_ctrl.studies.mcbatch`): the picklable job, the per-process plant and scene, the seeded
draw of sample ``i`` and its per-sample verification."""

from __future__ import annotations

import inspect
import math
import warnings
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from ..errors import GeometryWarning, SimulationError
from ..plant.model import register_member
from ..plant.plantfile import Plant
from ..plant.uncertainty import apply
from .autotune import Design, actuator_loops, verify
from .scene import choose_fidelity

__all__ = ["METRICS", "Job", "plant_doc", "prepared", "draw_sample", "evaluate"]

#: Metrics recorded per design and sample (worst over the sample's load steps).
METRICS = ("peak_drop_rad_s", "recovery_time_s", "ie", "iae", "itae", "ise", "overshoot_rad_s",
           "peak_torque_n_m", "steady_state_error_rad_s", "saturated", "ms", "mt")


@dataclass(frozen=True)
class Job:
    """Everything a worker needs, picklable (the Plant's read-only mappings are rebuilt)."""

    token: str
    plant_doc: dict
    scene: Any
    designs: tuple  # (name, PID, estimator)
    unc: Any  # UncertaintyModel
    ops: tuple  # ((setpoint rad/s, final load N), ...)
    spec: dict
    seed: int
    settings: Any = None  # SimSettings of every verification run (None: autotune.verify_settings)
    batched: bool = False  # the batched simulator (prsa_ctrl.sim.batch) with these (fixed-step) settings


_WORKER_CACHE: dict[str, tuple] = {}


def plant_doc(plant) -> dict:
    """The plant as plain data for a worker process (its mappings are read-only proxies)."""
    return {"name": plant.name, "values": dict(plant.values), "sources": dict(plant.sources),
            "origin": plant.origin, "description": plant.description, "mechanism": plant.mechanism,
            "defaulted": frozenset(plant.defaulted), "mechanism_source": plant.mechanism_source}


def prepared(job: Job) -> tuple:
    """The job's plant and resolved scene, built once per worker process."""
    got = _WORKER_CACHE.get(job.token)
    if got is None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", GeometryWarning)
            plant = Plant(**job.plant_doc)
        got = (plant, choose_fidelity(job.scene)[0])
        _WORKER_CACHE.clear()
        _WORKER_CACHE[job.token] = got
    return got


def draw_sample(unc, ops: Sequence, seed: int, index: int) -> tuple[dict[str, float], int, int]:
    """Sample ``index`` of ``seed``: (parameter values in file units, operating-point index,
    per-roller error seed), from ``SeedSequence([seed, index])`` only."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(index)]))
    values = unc.sample(rng)
    op = int(rng.integers(len(ops))) if len(ops) > 1 else 0
    roller_seed = int(rng.integers(2**31 - 1))
    return values, op, roller_seed


def evaluate(job: Job, index: int) -> tuple[int, dict, int, np.ndarray, list]:
    """All designs on sample ``index``: metrics array (designs x METRICS) and error messages."""
    plant, scene = prepared(job)
    values, op, roller_seed = draw_sample(job.unc, job.ops, job.seed, index)
    sp, f1 = job.ops[op]
    p_i = apply(plant, values, name=f"{plant.name} sample {index}") if values else plant
    if values:  # one parametric model (and one compiled law) serves every sample
        register_member(p_i, plant, job.unc.keys)
    sc = scene.replace(setpoint_rad_s=sp, final_loads=(f1,))
    kw = {"seed": roller_seed} if "seed" in inspect.signature(verify).parameters else {}
    kw["settings"] = job.settings
    out = np.full((len(job.designs), len(METRICS)), np.inf)
    errors: list = [None] * len(job.designs)
    loop = None
    for j, (name, pid, est) in enumerate(job.designs):
        try:
            d = verify(Design(name, pid, None, estimator=est), p_i, sc, **kw)
        except SimulationError as exc:
            errors[j] = str(exc).splitlines()[0]
            continue
        row = out[j]
        for k, m in enumerate(METRICS[:10]):
            vals = [abs(float(getattr(x, m))) for x in d.verified]
            row[k] = max(vals)
        if "ms" in job.spec or "mt" in job.spec:
            if loop is None:
                loop = actuator_loops(p_i, sc, estimator=est)[0]
            g = pid.gains
            if loop.is_stable(g):
                row[10], row[11] = loop.sensitivity_peaks(g)
        else:
            row[10] = row[11] = math.nan
    return index, values, op, out, errors
