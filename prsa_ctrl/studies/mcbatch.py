"""The batched path of the Monte-Carlo verification (:func:`prsa_ctrl.studies.montecarlo.run_monte_carlo`
with ``path="batched"``, its default where :func:`batch_plan` allows it).

Each chunk of samples (one task of the process pool or of Dask) is one batched integration
per operating point and design (:func:`prsa_ctrl.sim.batch.simulate_batch`) with batched
metrics; a sample whose steady state or run fails in the batch runs per sample, which reports
why. Every run compares :data:`BATCH_CHECK_SAMPLES` of its samples (:func:`check_indices`)
with the scene's adaptive reference (:func:`prsa_ctrl.studies.autotune.verify_settings`) and
quotes the largest error; above half the scene's accuracy it doubles the substeps (at most
:data:`BATCH_REFINEMENTS` times, up to 32) and runs again, then falls back to the per-sample
adaptive path, saying so (:func:`batched`). A sample's numbers do not depend on the batch it
runs in (each lane of the batch computes alone), so the backends agree bit for bit and a
replay is exact.
"""

from __future__ import annotations

import math
import time
import warnings
from typing import Sequence

import numpy as np

from ..errors import GeometryWarning, SimulationError
from ..plant.model import register_member
from ..plant.uncertainty import apply
from .autotune import actuator_loops
from .mcjob import METRICS, Job, draw_sample, evaluate, plant_doc, prepared
from .scene import choose_fidelity
from .kindruns import speed_kind

__all__ = ["batch_plan", "batch_settings", "batched", "check_indices", "acting_keys", "evaluate_batch", "BATCH_CHECK_SAMPLES",
           "BATCH_REFINEMENTS", "BATCH_SIZE"]

#: Most samples of a batched run compared with the adaptive reference (:func:`check_indices`:
#: the most extreme sample and each uncertain parameter's smallest and largest; 11 for the
#: paper plant's 5 parameters, ~0.06 s of CPU each).
BATCH_CHECK_SAMPLES = 16
#: Refinements a batched run may make when its check fails (each doubles the substeps).
BATCH_REFINEMENTS = 2
#: Most samples in one batch (one task of the pool or of Dask).
BATCH_SIZE = 512
#: Substeps per controller sample of the batched Radau IIA step (2 stages) at the paper scene's
#: accuracy 1 %; other accuracies scale them by ``(0.01 / accuracy) ** 0.5`` (the measured
#: order of the error on the paper plant is ~2), 2..32. A starting point only: the check of
#: every run decides (and refines).
_BATCH_SUBSTEPS_AT_1_PERCENT = 8


def _batch_layout(plant, scene) -> tuple[float, float, float]:
    """``(pre, duration, offset)`` of the verification run of a load-step scene (as
    ``prsa_ctrl.studies.autotune._simulate``): the step ``pre`` s after the start."""
    from .scenefile import PRE_EVENT_SAMPLES

    pre = min(scene.step_time, PRE_EVENT_SAMPLES * plant.sample_time_s)
    return pre, pre + scene.duration - scene.step_time, scene.step_time - pre


def batch_plan(plant, scene, unc, designs, spec) -> str | None:
    """``None`` when the batched path can run these designs on this scene, else why not."""
    from ..plant.model import parametric_family
    from ..sim.batch import batch_supported

    sc, _ = choose_fidelity(scene)
    if not sc.discrete or not speed_kind(sc).takes("batched"):
        return "batched path: sampled load-step scenes only"
    if getattr(sc, "filters", ()):
        return "batched path: scenes without loop filters"
    if not unc.keys:
        return "batched path: nothing uncertain"
    ts = plant.sample_time_s
    pre, _, _ = _batch_layout(plant, sc)
    if abs(round(pre / ts) * ts - pre) > 1e-9 * ts:
        return "batched path: the load step is not on a controller sample"
    fam = parametric_family(plant, sc.fidelity, unc.keys) if sc.fidelity in ("rigid", "compliant") else None
    if fam is not None and not set(unc.keys) <= set(fam.keys):
        fam = None
    for _, pid, est in designs:
        why = batch_supported(fam, pid, est)
        if why is not None:
            return f"batched path: {why}"
    return None


def batch_settings(accuracy: float, refinements: int = 0):
    """The batched run's fixed-step settings at the scene's ``accuracy`` (relative) after
    ``refinements`` doublings: 2-stage Radau IIA, an even number of substeps (2..32), the
    Jacobian refreshed four times per controller sample (``jacobian_every = substeps / 4``
    where 4 divides the substeps, else at every substep). Measured on the check samples
    against CVODES at 1e-6 (8 substeps): paper scene 0.0037 of the deviation (0.0040 with the
    refresh at every substep, 0.0032 twice per sample), ``robust-load-step`` 0.0016 (0.0016;
    0.0046 twice per sample, too close to the refinement threshold of half the accuracy);
    1.6x fewer operations than at every substep. The check of every run decides."""
    from ..sim.integrators import SimSettings

    sub = math.ceil(_BATCH_SUBSTEPS_AT_1_PERCENT * math.sqrt(0.01 / accuracy)) * 2 ** refinements
    sub = int(min(max(2 * math.ceil(sub / 2), 2), 32))
    return SimSettings(integrator="radau", stages=2, substeps=sub, jacobian_every=sub // 4 if sub % 4 == 0 else 1,
                       jit=True)


def _family(job: Job, plant, scene):
    from ..plant.model import parametric_family

    return parametric_family(plant, scene.fidelity, job.unc.keys)


def evaluate_batch(job: Job, indices: Sequence[int]) -> list:
    """``prsa_ctrl.studies.mcjob.evaluate`` of every sample in ``indices`` with one batched run per operating
    point and design (:func:`prsa_ctrl.sim.batch.simulate_batch`) and batched metrics; a sample
    whose steady state or run fails in the batch is run per sample (which reports why)."""
    from ..sim.batch import load_step_metrics_batch, simulate_batch

    plant, scene = prepared(job)
    fam = _family(job, plant, scene)
    draws = [draw_sample(job.unc, job.ops, job.seed, i) for i in indices]
    nd = len(job.designs)
    out = np.full((len(indices), nd, len(METRICS)), np.inf)
    redo: set[int] = set()
    pre, duration, offset = _batch_layout(plant, scene)
    for op_k in sorted({d[1] for d in draws}):
        sel = [r for r, d in enumerate(draws) if d[1] == op_k]
        sp, f1 = job.ops[op_k]
        thetas = np.array([[draws[r][0].get(k, plant.values[k]) for k in fam.keys] for r in sel], dtype=float)
        direction = 1 if f1 >= scene.initial_load else -1
        for j, (_, pid, _) in enumerate(job.designs):
            br = simulate_batch(fam, thetas, pid, sp, scene.initial_load, f1, pre, duration, job.settings)
            met = load_step_metrics_batch(br.time + offset, np.nan_to_num(br.nut_speed), sp, scene.step_time,
                                          np.nan_to_num(br.motor_torque), plant.torque_limit, direction)
            cols = np.abs(np.stack([met[m] for m in METRICS[:10]], axis=1))
            for r_i, r in enumerate(sel):
                if br.ok[r_i]:
                    out[r, j, :10] = cols[r_i]
                else:
                    redo.add(r)
    rows = []
    margins = "ms" in job.spec or "mt" in job.spec
    left: dict[int, set[int]] = {}  # sample row -> designs whose margins the per-sample path computes
    if margins:
        left = _margins_batched(job, plant, scene, draws, [r for r in range(len(indices)) if r not in redo], out)
    for r, i in enumerate(indices):
        if r in redo:
            rows.append(evaluate(job, i))
            continue
        values, op, _ = draws[r]
        if margins:
            if left.get(r):
                _margins(job, plant, scene, values, op, i, out[r], left[r])
        else:
            out[r, :, 10:12] = math.nan
        rows.append((i, values, op, out[r], [None] * nd))
    return rows


#: Keys that set the drive loop's own constants (sample time, filters, delay): a sample that
#: varies them has its own loop structure, so its margins are the per-sample path's.
_LOOP_KEYS = ("sensor.", "drive.command_delay_samples")


def _margins_batched(job: Job, plant, scene, draws, rows: list[int], out: np.ndarray) -> dict[int, set[int]]:
    """Ms and Mt of the designs on the samples ``rows`` batched (:mod:`prsa_ctrl.studies.mcmargins`),
    into ``out``; returns, per row, the designs left to the per-sample path (:func:`_margins`):
    a Kalman-filter design, a sample whose batched operating point, Jacobians or modal form
    failed, or every one where the nominal loop built batched differs from ``drive_loop``'s."""
    from ..plant.model import parametric_family
    from .mcmargins import linearise_batch, loop_batch, sensitivity_peaks_batch
    from .sceneloops import linear_fidelity

    nd = len(job.designs)
    want = {r: {j for j in range(nd) if np.all(np.isfinite(out[r, j, :10]))} for r in rows}
    want = {r: js for r, js in want.items() if js}
    lin = linear_fidelity(scene)
    fam = parametric_family(plant, lin, job.unc.keys) if lin in ("rigid", "compliant") else None
    if (fam is None or not set(job.unc.keys) <= set(fam.keys) or getattr(scene, "filters", ())
            or any(k.startswith(_LOOP_KEYS) for k in job.unc.keys)):
        return want
    left: dict[int, set[int]] = {}
    nominal = np.array([fam.theta_of(plant)], dtype=float)
    for op_k in sorted({draws[r][1] for r in want}):
        sel = [r for r in want if draws[r][1] == op_k]
        sp, f1 = job.ops[op_k]
        sc = scene.replace(setpoint_rad_s=sp, final_loads=(f1,))
        thetas = np.array([[draws[r][0].get(k, plant.values[k]) for k in fam.keys] for r in sel], dtype=float)
        a, b, c, ok = linearise_batch(fam, np.vstack([thetas, nominal]), sp, 0.5 * (scene.initial_load + f1))
        for j, (_, pid, est) in enumerate(job.designs):
            todo = [q for q, r in enumerate(sel) if j in want[r]]
            if not todo:
                continue
            template = actuator_loops(plant, sc, estimator="none")[0] if (est or scene.estimator) == "none" else None
            lp = None
            if template is not None and ok[-1]:
                lp = loop_batch(template, a[todo + [len(sel)]], b[todo + [len(sel)]], fam.index("theta_nut"),
                                plant.command_delay_samples)
                scale = float(np.max(np.abs(template.A0)))
                if lp["A0"].shape[1:] != template.A0.shape or not np.allclose(
                        lp["A0"][-1], template.A0, rtol=1e-6, atol=1e-9 * scale):
                    lp = None
            if lp is None:
                for q in todo:
                    left.setdefault(sel[q], set()).add(j)
                continue
            ms, mt, good = sensitivity_peaks_batch(template, lp, pid.gains, plant.speed_filter_s,
                                                   plant.command_delay_samples)
            for t, q in enumerate(todo):
                r = sel[q]
                if good[t] and ok[q]:
                    out[r, j, 10], out[r, j, 11] = ms[t], mt[t]
                else:
                    left.setdefault(r, set()).add(j)
    return left


def _margins(job: Job, plant, scene, values, op: int, index: int, out: np.ndarray, designs=None) -> None:
    """Ms and Mt of every design (or of the ``designs``' indices) on sample ``index`` (as
    ``prsa_ctrl.studies.mcjob.evaluate``), into ``out``."""
    sp, f1 = job.ops[op]
    p_i = apply(plant, values, name=f"{plant.name} sample {index}") if values else plant
    if values:
        register_member(p_i, plant, job.unc.keys)
    sc = scene.replace(setpoint_rad_s=sp, final_loads=(f1,))
    loop = None
    for j, (_, pid, est) in enumerate(job.designs):
        if not np.all(np.isfinite(out[j, :10])) or (designs is not None and j not in designs):
            continue
        if loop is None:
            loop = actuator_loops(p_i, sc, estimator=est)[0]
        g = pid.gains
        if loop.is_stable(g):
            out[j, 10], out[j, 11] = loop.sensitivity_peaks(g)


#: The check samples are chosen among the first this many samples of a run (drawing them is
#: ~50 us each; a run of 1e6 samples does not draw them all twice).
CHECK_CANDIDATES = 4096


def acting_keys(fam) -> tuple[str, ...]:
    """The family's parameters its equations depend on (e.g. the roller tolerances act on the
    multi-roller model only): the others cannot change a sample's error."""
    import casadi as ca

    x, u, th = ca.SX.sym("x", fam.nx), ca.SX.sym("u", 2), ca.SX.sym("th", fam.n_theta)
    rhs = fam.f(x, u, th)
    return tuple(k for i, k in enumerate(fam.keys) if ca.depends_on(rhs, th[i]))


def check_indices(unc, ops, seed: int, n: int, k: int | None = None, keys=None) -> list[int]:
    """The samples of a run that a batched run compares with the adaptive reference, chosen
    among its first :data:`CHECK_CANDIDATES`: the most extreme sample (largest sum over the
    uncertain parameters of the distance of its rank from the middle rank) and, for every
    uncertain parameter, the samples with its smallest and its largest value (the fixed step's
    error grows towards one end of some parameter: on the paper plant the stiffest contact,
    rank correlation 0.95 over 24 samples), at most ``k`` (default
    :data:`BATCH_CHECK_SAMPLES`) in that order; ties to the lower index. ``keys``: the
    parameters to look at (default all; a batched run passes :func:`acting_keys`). Not a bound
    over every sample: the measured error is reported as measured."""
    k = BATCH_CHECK_SAMPLES if k is None else k
    m = min(n, CHECK_CANDIDATES)
    if m <= 1:
        return list(range(m))
    vals = [draw_sample(unc, ops, seed, i)[0] for i in range(m)]
    score = np.zeros(m)
    picks: list[int] = []
    for key in (unc.keys if keys is None else [q for q in unc.keys if q in keys]):
        col = np.array([v[key] for v in vals], dtype=float)
        ranks = np.argsort(np.argsort(col, kind="stable"), kind="stable") / (m - 1)
        score += np.abs(ranks - 0.5)
        picks += [int(np.argmin(col)), int(np.argmax(col))]
    order = [int(np.lexsort((np.arange(m), -score))[0])] + picks
    return sorted(list(dict.fromkeys(order))[:k])


def _check_batch(job: Job, indices: Sequence[int]) -> list[dict]:
    """The batched run of each sample in ``indices`` against the scene's adaptive reference
    run of the same sample (first design): the largest nut-speed difference relative to the
    reference's largest deviation from its start (the measure of
    :func:`prsa_ctrl.sim.engine.fixed_step_error`)."""
    from ..sim.batch import simulate_batch
    from ..sim.engine import run
    from .autotune import verify_settings

    plant, scene = prepared(job)
    fam = _family(job, plant, scene)
    pre, duration, _ = _batch_layout(plant, scene)
    _, pid, _ = job.designs[0]
    reference = verify_settings(scene)
    out = []
    for i in indices:
        values, op, roller_seed = draw_sample(job.unc, job.ops, job.seed, i)
        sp, f1 = job.ops[op]
        p_i = apply(plant, values, name=f"{plant.name} sample {i}")
        register_member(p_i, plant, job.unc.keys)
        try:
            w_ref = run(p_i, setpoint=sp, load=[(0.0, scene.initial_load), (pre, f1)], duration=duration,
                        controller=pid, fidelity=scene.fidelity, discrete=True, settings=reference,
                        seed=roller_seed).output("nut_speed")
        except SimulationError as exc:
            out.append({"index": int(i), "relative": None, "error": str(exc).splitlines()[0]})
            continue
        theta = np.array([[values.get(k, plant.values[k]) for k in fam.keys]], dtype=float)
        br = simulate_batch(fam, theta, pid, sp, scene.initial_load, f1, pre, duration, job.settings)
        dev = float(np.max(np.abs(w_ref - w_ref[0])))
        err = float(np.max(np.abs(br.nut_speed[0] - w_ref))) if br.ok[0] else math.inf
        out.append({"index": int(i), "relative": err / dev if dev > 0 else math.inf, "max_error_rad_s": err,
                    "max_deviation_rad_s": dev})
    return out


def batched(plant, scene, unc, designs, ops, spec, seed: int, n: int, chunk, workers: int, token: str, execute,
             rows: list, bar) -> tuple:
    """The batched runs with their check (see :func:`prsa_ctrl.studies.montecarlo.run_monte_carlo`'s ``path``): ``(job,
    integration)``, or ``(None, integration)`` with the reason when the check failed after
    every refinement (the caller then runs the per-sample path)."""
    from ..sim.batch import lane_function
    from .autotune import verify_settings

    sc, _ = choose_fidelity(scene)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeometryWarning)
        fam = _family(Job("", plant_doc(plant), sc, designs, unc, ops, spec, seed), plant, sc)
    checks = check_indices(unc, ops, seed, n, keys=acting_keys(fam))
    n_chunks = max(workers, math.ceil(n / BATCH_SIZE))
    size = chunk or max(1, math.ceil(n / n_chunks))
    chunks = [list(range(a, min(a + size, n))) for a in range(0, n, size)]
    reference = verify_settings(sc)
    worst = math.inf
    for refinement in range(BATCH_REFINEMENTS + 1):
        settings = batch_settings(sc.accuracy, refinement)
        job = Job(token, plant_doc(plant), scene, designs, unc, ops, spec, seed, settings, batched=True)
        plant_w, scene_w = prepared(job)
        lane_function(_family(job, plant_w, scene_w), settings)  # built (compiled) once, before any fork
        result: dict = {}

        def side() -> None:
            t = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", GeometryWarning)
                result["checks"] = _check_batch(job, checks)
            result["check_s"] = time.perf_counter() - t

        rows.clear()
        bar.done = 0
        execute(job, chunks, side)
        errs = [c["relative"] for c in result["checks"] if c["relative"] is not None]
        worst = max(errs) if errs else math.inf
        record = {"path": "batched", "integrator": "radau", "stages": settings.stages, "substeps": settings.substeps,
                  "jacobian_every": settings.jacobian_every,
                  "jit": settings.jit, "relative": worst if math.isfinite(worst) else None, "accuracy": sc.accuracy,
                  "check_samples": checks, "checks": result["checks"], "check_s": result["check_s"],
                  "reference": {"integrator": reference.integrator, "rtol": reference.rtol, "atol": reference.atol},
                  "refinements": refinement, "batch_size": size,
                  "note": "error measured on the check samples against the adaptive reference, not a bound over "
                          "every sample"}
        if worst <= 0.5 * sc.accuracy:
            record["reason"] = (f"batched fixed-step error {worst:.2g} of the deviation on {len(checks)} check samples, "
                                f"inside half the accuracy {sc.accuracy:g}")
            return job, record
        if settings.substeps >= 32:
            break
    reason = (f"batched check failed: measured error {worst:.3g} of the deviation above half the accuracy "
              f"{sc.accuracy:g} after {refinement} refinement(s); per-sample adaptive path")
    return None, {"reason": reason, "batched_relative": worst if math.isfinite(worst) else None}
