"""Seeded Monte-Carlo verification: N nonlinear closed-loop runs of one or more designs over
samples of the plant's uncertainty, the yield against the scene's spec with a Wilson 95 %
interval, metric percentiles and the worst sample with a command that replays it.

Sample ``i`` of seed ``s`` draws everything it needs (parameter values, operating point,
per-roller errors) from ``numpy.random.SeedSequence([s, i])`` alone, and runs in a fresh,
deterministic simulation, so the results are identical - to the last bit - whether the samples
run serially in-process, in a process pool of any size, or on a Dask cluster (``dask`` is
imported only on that path). Samples are sent in chunks (one task per chunk, not per sample);
the job (plant, scene, designs) is sent once per worker.
"""

from __future__ import annotations

import ctypes
import math
import multiprocessing
import os
import signal
import sys
import time
import uuid
import warnings
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from .._lazy import module
from ..drive.pid import PID
from ..errors import GeometryWarning, MonteCarloInterrupted, SimulationError
from ..plant.model import register_member
from ..plant.uncertainty import apply, uncertainty_model
from ..reporttext import format_monte_carlo
from ..results import is_ok, json_safe
from .autotune import FAST_VERIFY, fast_verify_settings, verify_settings
from .mcjob import METRICS, Job, draw_sample, evaluate, plant_doc, prepared
from .scene import choose_fidelity
from .scenerobust import operating_points

dask = module("dask")
distributed = module("dask.distributed")

__all__ = ["MonteCarloReport", "DesignYield", "MonteCarloInterrupted", "run_monte_carlo", "format_report",
           "wilson_interval", "draw_sample", "replay_sample", "scene_options", "verification_settings", "local_cluster",
           "METRICS", "BACKENDS", "sample_passes"]

#: Execution backends.
BACKENDS = ("serial", "process", "dask")
#: Percentiles reported for each metric (plus the maximum).
PERCENTILES = (5, 50, 95)
#: Upper bound on samples in one run (checked before any work).
MAX_SAMPLES = 1_000_000


def wilson_interval(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion ``k/n`` (95 % for the default ``z``).

    Examples
    --------
    >>> lo, hi = wilson_interval(50, 100)
    >>> round(lo, 4), round(hi, 4)
    (0.4038, 0.5962)
    >>> wilson_interval(0, 0)
    (0.0, 1.0)
    """
    if n <= 0:
        return 0.0, 1.0
    p = k / n
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    # exact ends at k = 0 and k = n (the formula gives them up to rounding)
    return (0.0 if k == 0 else max(0.0, centre - half)), (1.0 if k == n else min(1.0, centre + half))


# --- the job each worker runs: prsa_ctrl.studies.mcjob (shared with the batched path) ------------

_Job, _plant_doc, _prepared, _evaluate = Job, plant_doc, prepared, evaluate


#: Integrator choices of :func:`run_monte_carlo`.
INTEGRATOR_CHOICES = ("auto", "fast", "reference")
_SETTINGS_CACHE: dict = {}


def verification_settings(plant, scene, unc, ops: Sequence, pid, integrator: str = "auto") -> tuple[Any, dict]:
    """The integrator settings of every Monte-Carlo verification run, and why.

    ``"reference"``: the scene's adaptive integrator (:func:`prsa_ctrl.studies.autotune.verify_settings`).
    ``"fast"``: :data:`prsa_ctrl.studies.autotune.FAST_VERIFY` without a measurement (a replay of a run
    that measured it). ``"auto"``: the compiled fixed-step :data:`prsa_ctrl.studies.autotune.FAST_VERIFY`
    where its nut-speed error against a tight CVODES reference (rtol = atol = 1e-9) is inside
    half the scene's accuracy at every check point: the nominal plant, the two extreme corners
    of the uncertainty box (every parameter at its low end, every one at its high end) and each
    parameter alone at its low and its high end, at the first and last operating point, with
    ``pid``; else the reference. (On the paper plant the worst point is the stiffest contact
    alone, not a corner.) Not a bound over the whole box: the largest measured error is
    reported. Deterministic (every worker and a replay make the same choice); measured once
    per process.

    Returns
    -------
    (SimSettings, dict)
        The settings and a record: ``integrator``, the largest measured ``relative`` error
        (``None`` when not measured), the ``accuracy`` and the ``reason``.
    """
    if integrator not in INTEGRATOR_CHOICES:
        raise ValueError(f"integrator = {integrator!r}; expected one of {', '.join(INTEGRATOR_CHOICES)}")
    sc, _ = choose_fidelity(scene)
    reference = verify_settings(sc)
    if integrator == "reference":
        return reference, {"integrator": reference.integrator, "rtol": reference.rtol, "relative": None,
                           "accuracy": sc.accuracy, "reason": "integrator = 'reference'"}
    if integrator == "fast":
        return FAST_VERIFY, {"integrator": "radau", "stages": FAST_VERIFY.stages, "substeps": FAST_VERIFY.substeps,
                             "jit": FAST_VERIFY.jit, "relative": None, "accuracy": sc.accuracy,
                             "reason": "integrator = 'fast'"}
    key = (tuple(sorted(plant.values.items())), repr(sc), repr(unc.as_dict()), tuple(ops), repr(pid))
    if key in _SETTINGS_CACHE:
        return _SETTINGS_CACHE[key]
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeometryWarning)
        points = [apply(plant, {})]  # a copy: the nominal plant's own model stays as it is
    register_member(points[0], plant, unc.keys)
    if unc.keys:
        corners = [{e.key: getattr(e, end) for e in unc.entries} for end in ("low", "high")]
        corners += [{e.key: getattr(e, end)} for e in unc.entries for end in ("low", "high")]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", GeometryWarning)
            for c in corners:
                points.append(apply(plant, c))
                register_member(points[-1], plant, unc.keys)  # shares the samples' compiled law
    worst, fast = 0.0, None
    try:
        for p_k in points:
            for sp, f1 in dict.fromkeys([ops[0], ops[-1]]):
                fast, meas = fast_verify_settings(sc.replace(setpoint_rad_s=sp, final_loads=(f1,)), p_k, pid)
                if fast is None:
                    raise _NotFast(meas.get("reason") or f"fixed-step error {meas['relative']:.3g} of the deviation "
                                   f"above half the accuracy {sc.accuracy:g}")
                worst = max(worst, meas["relative"])
        out = (fast, {"integrator": fast.integrator, "stages": fast.stages, "substeps": fast.substeps,
                      "jit": fast.jit, "relative": worst, "accuracy": sc.accuracy, "check_points": len(points),
                      "check_s": time.perf_counter() - t0,
                      "reason": "fixed-step error inside half the accuracy at every check point"})
    except _NotFast as exc:
        out = (reference, {"integrator": reference.integrator, "rtol": reference.rtol, "relative": None,
                           "accuracy": sc.accuracy, "reason": str(exc)})
    except SimulationError as exc:
        out = (reference, {"integrator": reference.integrator, "rtol": reference.rtol, "relative": None,
                           "accuracy": sc.accuracy, "reason": f"fixed-step check failed: {str(exc).splitlines()[0]}"})
    _SETTINGS_CACHE[key] = out
    return out


class _NotFast(Exception):
    pass


#: Paths of :func:`run_monte_carlo`: one batched integration per chunk of samples
#: (:mod:`prsa_ctrl.sim.batch`, driven by :mod:`prsa_ctrl.studies.mcbatch`) or one per sample.
PATHS = ("batched", "per-sample")


def _run_chunk(job: _Job, indices: Sequence[int]) -> list:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeometryWarning)
        if job.batched:
            from .mcbatch import evaluate_batch

            return evaluate_batch(job, indices)
        return [_evaluate(job, i) for i in indices]


_POOL_JOB: _Job | None = None


def _pool_init(job: _Job, parent: int | None = None) -> None:
    global _POOL_JOB
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C
    _end_with_parent(parent)
    _POOL_JOB = job


def _end_with_parent(parent: int | None) -> None:
    """Linux: have the kernel send this worker SIGKILL when its parent process dies (killed by
    a signal it does not handle, e.g. SIGTERM or SIGKILL), so no worker outlives the run as an
    orphan; elsewhere (or without ``parent``) a no-op."""
    if parent is None or not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # best effort: the parent's handlers stop the workers too
        return
    if os.getppid() != parent:  # the parent died before prctl took effect
        os._exit(1)


def _pool_chunk(indices: Sequence[int]) -> list:
    assert _POOL_JOB is not None
    return _run_chunk(_POOL_JOB, indices)


# --- report --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class DesignYield:
    """Monte-Carlo outcome of one design."""

    name: str
    gains: dict
    passed: int
    n: int
    yield_: float
    ci95: tuple[float, float]
    percentiles: dict
    worst_index: int | None
    worst_values: dict
    worst_metrics: dict
    failures: int
    replay: str

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "gains": self.gains, "passed": self.passed, "samples": self.n,
                "yield": self.yield_, "yield_ci95": list(self.ci95), "percentiles": self.percentiles,
                "worst_sample": {"index": self.worst_index, "parameters": self.worst_values,
                                 "metrics": self.worst_metrics, "replay": self.replay},
                "simulation_failures": self.failures}


@dataclass(frozen=True)
class MonteCarloReport:
    """Result of :func:`run_monte_carlo` (frozen). ``complete`` is false when the run was
    interrupted (then ``n_done < n`` and the yields cover only the finished samples).

    ``status`` is ``"ok"`` for a complete run and ``"interrupted: <done> of <n> samples"``
    otherwise (:data:`prsa_ctrl.results.STATUSES`); ``warnings`` name the designs whose
    runs failed to simulate on some samples.
    """

    n: int
    n_done: int
    seed: int
    backend: str
    workers: int
    complete: bool
    spec: dict
    uncertainty: dict
    operating_points: list
    designs: list[DesignYield]
    wall_time_s: float
    samples: dict = field(default_factory=dict, repr=False)  # index, values, op, metrics arrays
    integration: dict = field(default_factory=dict)  # the verification runs' integrator and its measured error

    @property
    def status(self) -> str:
        return "ok" if self.complete else f"interrupted: {self.n_done} of {self.n} samples"

    @property
    def ok(self) -> bool:
        return is_ok(self.status)

    @property
    def warnings(self) -> tuple[str, ...]:
        return tuple(f"{d.name}: {d.failures} of {d.n} samples failed to simulate" for d in self.designs if d.failures)

    def as_dict(self, include_samples: bool = False) -> dict[str, Any]:
        d = {"samples": self.n, "samples_done": self.n_done, "seed": self.seed, "backend": self.backend,
             "workers": self.workers, "complete": self.complete, "spec": self.spec,
             "uncertainty": self.uncertainty, "operating_points": self.operating_points,
             "designs": [x.as_dict() for x in self.designs], "wall_time_s": self.wall_time_s,
             "sample_seed": "numpy.random.SeedSequence([seed, index])", "integration": self.integration}
        if include_samples:
            s = self.samples
            d["per_sample"] = {"index": s["index"].tolist(), "operating_point": s["op"].tolist(),
                               "parameters": {k: v.tolist() for k, v in s["values"].items()},
                               "metrics": {name: {m: _json_list(s["metrics"][:, j, k]) for k, m in enumerate(METRICS)}
                                           for j, name in enumerate(s["design_names"])}}
        return json_safe(d)

    def format(self) -> str:
        """The plain-text summary ``prsa-tune --monte-carlo`` prints
        (:func:`prsa_ctrl.reporttext.format_monte_carlo`, its one home)."""
        return format_monte_carlo(self)


def _json_list(a) -> list:
    return [None if not math.isfinite(float(x)) else float(x) for x in a]


def sample_passes(metrics: np.ndarray, spec: Mapping[str, Any], torque_limit: float) -> tuple[np.ndarray, np.ndarray]:
    """Pass flags and severity of Monte-Carlo samples against a yield spec.

    Parameters
    ----------
    metrics : ndarray
        Rows of samples, columns :data:`METRICS` (SI units).
    spec : mapping
        Metric name -> upper bound (its unit), and ``no_saturation`` (bool).
    torque_limit : float, N m
        The motor's torque limit (the severity of a saturated sample).

    Returns
    -------
    (ndarray of bool, ndarray of float)
        Whether each sample passes, and its severity: the largest value/bound ratio (> 1 fails;
        inf for a non-finite metric or a saturated sample).
    """
    ok = np.all(np.isfinite(metrics[:, :10]), axis=1)
    sev = np.where(ok, 0.0, np.inf)
    for k, bound in spec.items():
        if k == "no_saturation":
            if bound:
                sat = metrics[:, METRICS.index("saturated")] > 0
                ok &= ~sat
                sev = np.maximum(sev, np.where(sat, np.inf, metrics[:, METRICS.index("peak_torque_n_m")] / torque_limit))
            continue
        col = metrics[:, METRICS.index(k)]
        ok &= col <= bound
        sev = np.maximum(sev, col / bound)
    return ok, sev


def _identity(plant, scene) -> tuple[str, str]:
    p = plant.name if plant.origin.endswith("(built-in)") else plant.origin
    s = scene.name if scene.origin.endswith("(built-in)") else scene.origin
    return p, s


def _replay_cmd(plant, scene, seed: int, index: int, pid, settings=None) -> str:
    p, s = _identity(plant, scene)
    g = {k: float(v) for k, v in pid.as_dict().items()}
    integ = "fast" if settings is not None and settings.integrator == "radau" else "reference"
    cmd = (f"python -m prsa_ctrl.cli.montecarlo --plant {p} --scene {s} --seed {seed} --index {index} "
           f"--integrator {integ} --kp {g['kp']!r} --ki {g['ki']!r} --kd {g['kd']!r} --tf {g['tf']!r}")
    return cmd + (f" --kff {g['kff']!r}" if g.get("kff") else "")


def _build_report(job: _Job, plant, scene, rows: list, n: int, backend: str, workers: int, complete: bool,
                  wall: float, integration: dict) -> MonteCarloReport:
    rows = sorted(rows, key=lambda r: r[0])
    idx = np.array([r[0] for r in rows], dtype=int)
    ops = np.array([r[2] for r in rows], dtype=int)
    metrics = np.stack([r[3] for r in rows]) if rows else np.zeros((0, len(job.designs), len(METRICS)))
    keys = list(job.unc.keys)
    values = {k: np.array([r[1][k] for r in rows]) for k in keys}
    out = []
    for j, (name, pid, _) in enumerate(job.designs):
        m = metrics[:, j, :]
        ok, sev = sample_passes(m, job.spec, plant.torque_limit) if len(rows) else (np.zeros(0, bool), np.zeros(0))
        if not job.spec and len(rows):
            sev = m[:, METRICS.index(scene.objective)]
        k = int(ok.sum())
        pct = {}
        for c, met in enumerate(METRICS):
            col = m[:, c]
            if not len(col) or np.all(np.isnan(col)):
                continue
            col = col[~np.isnan(col)]
            pct[met] = {f"p{q}": float(np.percentile(col, q, method="inverted_cdf")) for q in PERCENTILES}
            pct[met]["max"] = float(np.max(col))
        w = int(np.argmax(sev)) if len(rows) else None
        # A failed run leaves every metric at inf; a run that never recovers only its recovery time.
        failures = int(np.sum(~np.isfinite(m[:, METRICS.index("peak_drop_rad_s")]))) if len(rows) else 0
        out.append(DesignYield(
            name, pid.as_dict(), k, len(rows), k / len(rows) if len(rows) else math.nan,
            wilson_interval(k, len(rows)), pct,
            int(idx[w]) if w is not None else None,
            {kk: float(values[kk][w]) for kk in keys} if w is not None else {},
            {met: float(m[w, c]) for c, met in enumerate(METRICS)} if w is not None else {},
            failures,
            _replay_cmd(plant, scene, job.seed, int(idx[w]), pid, job.settings) if w is not None else ""))
    return MonteCarloReport(
        n, len(rows), job.seed, backend, workers, complete, dict(job.spec), job.unc.as_dict(),
        [{"setpoint_rad_s": a, "final_load_n": b} for a, b in job.ops], tuple(out), wall,
        {"index": idx, "op": ops, "values": values, "metrics": metrics, "design_names": [d[0] for d in job.designs],
         "metric_names": list(METRICS)},
        integration)


#: The Monte-Carlo report's text (:func:`prsa_ctrl.reporttext.format_monte_carlo`, its one home).
format_report = format_monte_carlo


# --- progress ------------------------------------------------------------------------------------

class _Progress:
    """A small stderr progress bar (only on a terminal, never when quiet)."""

    def __init__(self, total: int, enabled: bool | None, label: str = "Monte Carlo") -> None:
        self.total, self.done, self.label = total, 0, label
        self.enabled = (sys.stderr.isatty() if enabled is None else bool(enabled)) and total > 0
        self._last = -1.0

    def update(self, k: int) -> None:
        self.done += k
        if not self.enabled:
            return
        now = time.monotonic()
        if now - self._last < 0.1 and self.done < self.total:
            return
        self._last = now
        frac = self.done / self.total
        bar = "#" * int(30 * frac)
        sys.stderr.write(f"\r{self.label} [{bar:<30}] {self.done}/{self.total}")
        sys.stderr.flush()

    def close(self) -> None:
        if self.enabled:
            sys.stderr.write("\n")
            sys.stderr.flush()


# --- driver --------------------------------------------------------------------------------------

def _as_design_tuples(designs) -> tuple:
    out = []
    items = designs.items() if isinstance(designs, Mapping) else [(getattr(d, "name", f"design {i}"), d)
                                                                   for i, d in enumerate(designs)]
    for name, d in items:
        if isinstance(d, PID):
            out.append((str(name), d, "none"))
        elif hasattr(d, "pid"):
            out.append((str(getattr(d, "name", name)), d.pid, getattr(d, "estimator", "none")))
        else:
            raise ValueError(f"design {name!r} = {d!r}; expected a PID or an autotune.Design")
    if not out:
        raise ValueError("designs = []; expected at least one design")
    return tuple(out)


def run_monte_carlo(
    plant,
    scene,
    designs,
    n: int,
    seed: int = 0,
    backend: str | None = None,
    scheduler: Any = None,
    workers: int | None = None,
    chunk: int | None = None,
    progress: bool | Callable[[int, int], None] | None = None,
    quiet: bool = False,
    spec: Mapping[str, Any] | None = None,
    unc=None,
    integrator: str = "auto",
    path: str | None = None,
) -> MonteCarloReport:
    """Verify designs on ``n`` seeded samples of the plant's (and scene's) uncertainty.

    Parameters
    ----------
    plant, scene
        Plant (``[uncertainty]``) and scene (``[uncertainty]``, ``[spec]``, ``[robust]``
        operating range); fidelity as the scene's verification (:func:`prsa_ctrl.studies.scene.choose_fidelity`).
    designs : list of Design or PID, or dict name -> PID
        Designs to verify on the same samples.
    n : int
        Number of samples (1..1e6).
    seed : int
        Sample ``i`` uses ``SeedSequence([seed, i])`` only.
    backend : {"serial", "process", "dask"}, optional
        Default "dask" when ``scheduler`` is given, else "process" with ``workers > 1``, else "serial".
    scheduler : str or dask.distributed.Client, optional
        ``"local"`` (start a LocalCluster of ``workers`` processes on 127.0.0.1 for this call),
        a scheduler address ``tcp://HOST:8786`` (checked first, within 5 s: a Dask scheduler must
        answer there, :func:`prsa_ctrl.studies.daskprobe.probe_scheduler`), or a connected
        ``Client`` (reused, left open: several runs on one running cluster skip its ~1 s start-up).
    workers : int, optional
        Processes for "process"/"local" (default: CPU count).
    chunk : int, optional
        Samples per task (default ``n / (8 workers)`` clipped to 8..64); does not change results.
    progress : bool or callable, optional
        Stderr bar (default: when stderr is a terminal and not ``quiet``), or ``f(done, total)``.
    spec : dict, optional
        Bounds (default the scene's ``[spec]``).
    integrator : {"auto", "reference"}
        ``"auto"``: the compiled fixed-step integrator where its measured error is inside the
        scene's accuracy (:func:`verification_settings`, quoted in ``report.integration``),
        else the scene's adaptive one; ``"reference"``: always the adaptive one, per sample.
    path : {"batched", "per-sample"}, optional
        ``"batched"`` (the default where :func:`prsa_ctrl.studies.mcbatch.batch_plan` allows it; with ``integrator`` other
        than ``"reference"``): each chunk of samples is one batched integration
        (:mod:`prsa_ctrl.sim.batch`; the pool and Dask distribute batches), with the Radau
        substeps chosen from the scene's accuracy; every run compares
        :data:`~prsa_ctrl.studies.mcbatch.BATCH_CHECK_SAMPLES` of its samples (:func:`~prsa_ctrl.studies.mcbatch.check_indices`) with the scene's
        adaptive reference and reports the largest error (``report.integration``); above half
        the accuracy it doubles the substeps (at most :data:`~prsa_ctrl.studies.mcbatch.BATCH_REFINEMENTS` times, up to
        32) and runs again, and then falls back to the per-sample adaptive path, saying so.
        ``"per-sample"``: one integration per sample (the path before batching). Same seeds,
        same samples on both paths; results agree within the stated accuracy.

    Returns
    -------
    MonteCarloReport
        ``.as_dict()`` for JSON, :func:`format_report` for text.

    Raises
    ------
    MonteCarloInterrupted
        On Ctrl-C, with the partial report (``complete = False``).
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not 1 <= n <= MAX_SAMPLES:
        raise ValueError(f"n = {n!r}; expected a number of samples in 1..{MAX_SAMPLES}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed = {seed!r}; expected an integer >= 0")
    if backend is None:
        backend = "dask" if scheduler else ("process" if (workers or 1) > 1 else "serial")
    if backend not in BACKENDS:
        raise ValueError(f"backend = {backend!r}; expected one of {', '.join(BACKENDS)}")
    if backend == "dask" and not scheduler:
        scheduler = "local"
    if scheduler is not None and backend != "dask":
        raise ValueError(f"scheduler = {scheduler!r} needs backend = 'dask' (got {backend!r})")
    if scheduler is not None and not _is_client(scheduler) and (not isinstance(scheduler, str) or (
            scheduler != "local" and not scheduler.startswith(("tcp://", "tls://", "inproc://")))):
        raise ValueError(f"scheduler = {scheduler!r}; expected 'local', an address like tcp://HOST:8786 "
                         "or a dask.distributed.Client")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or not 1 <= workers <= 512):
        raise ValueError(f"workers = {workers!r}; expected an integer 1..512")
    if chunk is not None and (isinstance(chunk, bool) or not isinstance(chunk, int) or not 1 <= chunk <= 10_000):
        raise ValueError(f"chunk = {chunk!r}; expected an integer 1..10000")
    if isinstance(scheduler, str) and scheduler.startswith("tcp://"):
        _check_scheduler_address(scheduler)
    if _is_client(scheduler):
        workers = len(scheduler.scheduler_info().get("workers", {})) or 1
    workers = workers or (1 if backend == "serial" else (os.cpu_count() or 1))
    spec = dict(scene.sections.spec_bounds if spec is None else spec)
    unc = uncertainty_model(plant, scene.sections.plant_overrides) if unc is None else unc
    design_tuples = _as_design_tuples(designs)
    ops = tuple(operating_points(scene))
    if path is not None and path not in PATHS:
        raise ValueError(f"path = {path!r}; expected one of {', '.join(PATHS)}")
    if integrator not in INTEGRATOR_CHOICES:
        raise ValueError(f"integrator = {integrator!r}; expected one of {', '.join(INTEGRATOR_CHOICES)}")
    bar = _Progress(n, False if quiet else (progress if isinstance(progress, bool) else None))
    callback = progress if callable(progress) else None
    rows: list = []

    def took(res: list) -> None:
        rows.extend(res)
        bar.update(len(res))
        if callback is not None:
            callback(len(rows), n)

    def execute(job: _Job, chunks: list, side=None) -> None:
        if backend == "serial":
            for c in chunks:
                took(_run_chunk(job, c))
            if side is not None:
                side()
        elif backend == "process":
            _run_process(job, chunks, workers, took, side)
        else:
            _run_dask(job, chunks, workers, scheduler, took, side)

    token = uuid.uuid4().hex
    t0 = time.perf_counter()
    why = None
    if path != "per-sample" and integrator != "reference":
        from .mcbatch import batch_plan, batched

        why = batch_plan(plant, scene, unc, design_tuples, spec)
    integration: dict = {}
    job = None
    complete = False
    try:
        if path != "per-sample" and integrator != "reference" and why is None:
            # With a progress bar or callback (the app, a terminal): at least 8 batches, so that
            # progress shows and a cancel keeps the finished ones; else as few as the workers allow.
            interactive = bar.enabled or callback is not None
            size_b = chunk or (max(1, math.ceil(n / max(8, workers))) if interactive else None)
            job, integration = batched(plant, scene, unc, design_tuples, ops, spec, int(seed), n, size_b, workers,
                                        token, execute, rows, bar)
        if job is None:  # the per-sample path (asked for, not possible, or the batched check failed)
            failed = dict(integration)  # the batched check's record, when it failed
            settings, integration = verification_settings(plant, scene, unc, ops, design_tuples[0][1],
                                                          "reference" if failed else integrator)
            integration = dict(integration, path="per-sample", **failed)
            if why is not None:
                integration["batch_reason"] = why
            job = _Job(token, _plant_doc(plant), scene, design_tuples, unc, ops, spec, int(seed), settings)
            size = chunk or int(min(64, max(8, math.ceil(n / (8 * workers)))))
            rows.clear()
            bar.done = 0
            execute(job, [list(range(a, min(a + size, n))) for a in range(0, n, size)])
        complete = len(rows) == n
    except KeyboardInterrupt:
        bar.close()
        job = job or _Job(token, _plant_doc(plant), scene, design_tuples, unc, ops, spec, int(seed), None)
        rep = _build_report(job, plant, scene, rows, n, backend, workers, False, time.perf_counter() - t0,
                            integration)
        raise MonteCarloInterrupted(rep) from None
    bar.close()
    return _build_report(job, plant, scene, rows, n, backend, workers, complete, time.perf_counter() - t0,
                         integration)


def _run_process(job: _Job, chunks: list, workers: int, took, side=None) -> None:
    """Chunks on a process pool; ``side()`` (optional) runs in this process while they do."""
    if workers <= 1:
        for c in chunks:
            took(_run_chunk(job, c))
        if side is not None:
            side()
        return
    method = "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context(method),
                               initializer=_pool_init, initargs=(job, os.getpid()))
    finished = False
    try:
        pending = {pool.submit(_pool_chunk, c) for c in chunks}
        if side is not None:
            side()
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for f in done:
                took(f.result())
        finished = True
    except BaseException:
        # Ctrl-C, SIGTERM or a failed chunk: stop the workers now (they ignore SIGINT, may have
        # inherited an ignored SIGTERM, and a chunk already queued would keep them running after
        # this process has exited). They only compute: SIGKILL loses nothing.
        for proc in list((getattr(pool, "_processes", None) or {}).values()):
            proc.kill()
        raise
    finally:
        # Every chunk done: wait for the idle workers to exit, so that no pool thread is left for
        # the interpreter's exit (shutdown(wait=False) there raced with it: "Exception ignored in
        # threading._shutdown ... Bad file descriptor" after a finished run, CPython gh-83279).
        pool.shutdown(wait=finished, cancel_futures=not finished)


def local_cluster(workers: int):
    """A Dask LocalCluster of ``workers`` single-threaded processes on 127.0.0.1."""
    cluster_class = distributed.LocalCluster  # imported before the config is changed, as Dask expects
    # The workers' statistical profiler (a stack sample every 10 ms) costs ~3 % of a worker's
    # CPU; nothing reads it here.
    with dask.config.set({"distributed.worker.profile.enabled": False}):
        return cluster_class(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                            dashboard_address=None,  # no dashboard; its HTTP server on a free port,
                            scheduler_kwargs={"dashboard_address": "127.0.0.1:0"})  # not 8787 (may be taken)


def _is_client(x) -> bool:
    """A connected dask.distributed Client (duck-typed: Dask is imported only on its path)."""
    return not isinstance(x, str) and callable(getattr(x, "submit", None)) and callable(getattr(x, "scatter", None))


def _check_scheduler_address(address: str) -> None:
    """A ``tcp://HOST:PORT`` scheduler answers as one within ``SCHEDULER_TIMEOUT_S``
    (:func:`prsa_ctrl.studies.daskprobe.probe_scheduler`), before any work: Dask's own client
    waits without a limit for a listener that never speaks."""
    from urllib.parse import urlsplit

    from .daskprobe import SCHEDULER_TIMEOUT_S, SchedulerProbeError, probe_scheduler

    try:
        parts = urlsplit(address)
        host, port = parts.hostname, parts.port
    except ValueError:
        host = port = None
    if not host or port is None or parts.path not in ("", "/"):
        raise ValueError(f"scheduler = {address!r}; expected an address like tcp://HOST:8786")
    try:
        probe_scheduler(host, port, SCHEDULER_TIMEOUT_S)
    except SchedulerProbeError as exc:
        raise ValueError(f"scheduler = {address!r}: not a Dask scheduler / no answer within "
                         f"{SCHEDULER_TIMEOUT_S:g} s: {exc}") from None


def _run_dask(job: _Job, chunks: list, workers: int, scheduler, took, side=None) -> None:
    try:
        Client, as_completed = distributed.Client, distributed.as_completed
    except ImportError:
        raise ValueError("scheduler needs Dask: pip install \"prsa-ctrl[dask]\" (dask[distributed])") from None

    cluster = None
    own = not _is_client(scheduler)
    if not own:
        client = scheduler
    elif scheduler == "local":
        cluster = local_cluster(workers)
        client = Client(cluster)
    else:
        client = Client(scheduler, timeout=30)
    try:
        job_f = client.scatter(job, broadcast=True)  # sent once per worker
        futures = [client.submit(_run_chunk, job_f, c, pure=False) for c in chunks]
        if side is not None:
            side()
        try:
            for f in as_completed(futures):
                took(f.result())
        except BaseException:
            client.cancel(futures)
            raise
    finally:
        if own:
            client.close()
        if cluster is not None:
            cluster.close()


def scene_options(scene) -> dict[str, int]:
    """The scene's Monte-Carlo options: ``{"samples": [robust] monte_carlo (0 = off),
    "seed": [robust] seed}`` (defaults 0 and 0), for ``prsa-tune`` without ``--monte-carlo``.

    Examples
    --------
    >>> from prsa_ctrl.studies.scene import load_scene
    >>> scene_options(load_scene("robust-load-step"))
    {'samples': 1000, 'seed': 1}
    """
    rob = scene.sections.robust
    return {"samples": int(rob.monte_carlo), "seed": int(rob.seed)} if rob is not None else {"samples": 0, "seed": 0}


# --- replay, figures ----------------------------------------------------------------------------

def replay_sample(plant, scene, pid, seed: int, index: int, integrator: str = "auto",
                  path: str | None = None) -> dict[str, Any]:
    """Re-run one sample of one design: its parameter values, operating point and metrics
    (with the integrator choice :func:`run_monte_carlo` made for that design first in line:
    the batched path where it applies, as the run's default, whose samples are independent
    of the batch they run in, so the replay is exact; a run that had to refine its substeps
    or fall back replays with ``path="per-sample"`` within the stated accuracy)."""
    unc = uncertainty_model(plant, scene.sections.plant_overrides)
    ops = tuple(operating_points(scene))
    spec = scene.sections.spec_bounds
    designs = (("replay", pid, "none"),)
    if path is not None and path not in PATHS:
        raise ValueError(f"path = {path!r}; expected one of {', '.join(PATHS)}")
    from .mcbatch import batch_plan, batch_settings

    if path != "per-sample" and integrator != "reference" and batch_plan(plant, scene, unc, designs, spec) is None:
        job = _Job("replay-" + uuid.uuid4().hex, _plant_doc(plant), scene, designs, unc, ops, spec, int(seed),
                   batch_settings(choose_fidelity(scene)[0].accuracy), batched=True)
    else:
        settings, _ = verification_settings(plant, scene, unc, ops, pid, integrator)
        job = _Job("replay-" + uuid.uuid4().hex, _plant_doc(plant), scene, designs, unc, ops, spec, int(seed),
                   settings)
    i, values, op, m, err = _run_chunk(job, [index])[0]
    ok, sev = sample_passes(m, job.spec, plant.torque_limit)
    return {"index": i, "parameters": values, "operating_point": job.ops[op],
            "metrics": dict(zip(METRICS, map(float, m[0]))), "passes_spec": bool(ok[0]), "error": err[0]}


