"""Design to the spec (issue 34): search a family of designs proposed by the linear scenario
models for the one that meets the scene's ``[spec]`` most often on the nonlinear Monte Carlo.

1. *Propose*: the nominal and the robust (every scenario model) tunings of
   :func:`prsa_ctrl.tuning.robust.tune_scenario_loops` at a sequence of Ms bounds, plus any
   given designs (the baselines), plus the best gains of a grid scored by their *linear*
   yield: the fraction of the search samples on whose own linearised loop model the gains
   meet the spec's peak drop, recovery time and Ms (:func:`linear_yield_grid`). The tunings
   optimise an objective under an Ms bound, not the yield; without the grid the family can
   miss the region where most samples pass (on the 16 kHz roller-screw scene of the tests the
   tuned family stays below the rule of thumb's yield).
2. *Screen*: every proposal runs on the same ``n_search`` nonlinear Monte-Carlo samples
   (common random numbers: seed ``seed``); :func:`prsa_ctrl.tuning.robust.rank_by_yield`
   marks the designs of (near-)maximal yield.
3. *Decide*: with more than one such design, those (at most :data:`MAX_FINALISTS`, highest
   yield first) run on ``n_decide`` samples of the same seed (the screen's samples and more)
   and the rule chooses again: (near-)maximal yield, then the lowest median objective. On the
   few screen samples the intervals are wide, and the lowest objective among the designs
   within them is the most aggressive one, near the edge of the spec; the larger decision
   sample narrows the intervals before the objective breaks the tie.
4. *Report*: the chosen design runs again on ``n_final`` fresh samples (seed ``seed + 1``, a
   stream the search did not use); that run's yield and Wilson interval are the reported ones.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from ..results import is_ok, json_safe
from ..reporttext import format_design_to_spec
from ..tuning.robust import rank_by_yield, tune_scenario_loops
from ..plant.uncertainty import uncertainty_model
from .scenerobust import scenario_loops, scenarios

__all__ = ["DesignToSpec", "design_to_spec", "linear_yield_grid", "MS_LEVELS", "MAX_PROPOSALS", "MAX_FINALISTS",
           "GRID_SIZE", "GRID_PICKS"]

#: Default Ms bounds of the proposed family (each gives a nominal and a robust design).
MS_LEVELS = (1.2, 1.3, 1.4, 1.5, 1.6, 1.8)
#: Upper bound on the designs the search evaluates (checked before any tuning).
MAX_PROPOSALS = 32
#: Designs of (near-)maximal screen yield carried to the decision run (highest yield first).
MAX_FINALISTS = 4
#: Points per axis of the linear-yield grid (kp x ki/kp), and the designs it proposes.
GRID_SIZE = 12
GRID_PICKS = 3
#: Samples at most of each of the design-to-spec's Monte-Carlo runs (search, decision, final check).
SAMPLES_MAX = 100_000


@dataclass(frozen=True)
class DesignToSpec:
    """Result of :func:`design_to_spec` (frozen).

    ``chosen`` is the name of the design the search chose (None when no proposal met the spec
    on any search sample); ``pid`` its gains; ``search`` the ranking on the search samples
    (:func:`prsa_ctrl.tuning.robust.rank_by_yield`); ``final`` the Monte-Carlo report of the
    chosen design on fresh samples (None without a choice): its yield is the reported one.
    """

    chosen: str | None
    pid: Any
    designs: dict  # name -> PID of every evaluated proposal
    search: dict
    search_seed: int
    final: Any
    final_seed: int
    skipped: tuple = ()  # (name, why) of proposals not evaluated (tuning not ok)
    timing_s: dict = field(default_factory=dict)
    decide: dict | None = None  # the ranking of the finalists on the decision samples (None: one finalist)
    grid: dict | None = None  # the linear-yield grid's summary (linear_yield_grid), None without one

    @property
    def final_yield(self):
        """The chosen design's DesignYield on the fresh samples (None without a choice)."""
        return self.final.designs[0] if self.final is not None else None

    def as_dict(self) -> dict[str, Any]:
        fy = self.final_yield
        return json_safe({
            "chosen": self.chosen, "gains": self.pid.as_dict() if self.pid is not None else None,
            "yield": fy.yield_ if fy else None, "passed": fy.passed if fy else None,
            "samples": fy.n if fy else None, "yield_ci95": list(fy.ci95) if fy else None,
            "final_seed": self.final_seed, "search_seed": self.search_seed,
            "search": {k: v for k, v in self.search.items()},
            "decide": dict(self.decide) if self.decide else None,
            "grid": {k: v for k, v in self.grid.items() if k != "designs"} if self.grid else None,
            "skipped": [{"design": n, "why": w} for n, w in self.skipped], "timing_s": self.timing_s})

    def format(self, objective: str) -> str:
        """The design-to-spec report (:func:`prsa_ctrl.reporttext.format_design_to_spec`, its one home)."""
        return format_design_to_spec(self, objective)

def design_to_spec(plant, scene, *, n_search: int = 40, n_final: int = 200, seed: int = 0,
                   ms_levels: Sequence[float] | None = None, extra: dict | None = None,
                   workers: int | None = None, quiet: bool = True, n_decide: int | None = None,
                   grid: bool = True, robust=None) -> DesignToSpec:
    """The design that meets the scene's ``[spec]`` most often over its ``[uncertainty]``.

    Parameters
    ----------
    plant, scene
        Plant and load-step scene with ``[spec]`` (and ``[uncertainty]``, ``[robust]``).
    n_search, n_final : int
        Monte-Carlo samples of the search (common to every proposal) and of the final check of
        the chosen design (fresh: seed ``seed + 1``), 1..100000 each.
    seed : int
        The search's Monte-Carlo seed (>= 0).
    ms_levels : sequence of float, optional
        Ms bounds (each > 1) of the proposed nominal and robust tunings (default
        :data:`MS_LEVELS`).
    extra : dict, optional
        Further designs (name -> PID), e.g. the baselines, evaluated alongside.
    workers : int, optional
        Processes of the Monte Carlo (default 1: serial).
    n_decide : int, optional
        Samples of the decision run among the designs of (near-)maximal screen yield (same
        seed; default ``3 n_search``; at most 100000; a value <= ``n_search`` skips it).
    grid : bool
        Propose the best gains of the linear-yield grid (:func:`linear_yield_grid`) too.
    robust : RobustTuning, optional
        A robust study of the same plant and scene
        (:func:`prsa_ctrl.studies.scenerobust.tune_robust_actuator`): its scenarios, scenario
        loop models and uncertainty model are reused (not rebuilt), and so are its tuners
        (:func:`prsa_ctrl.tuning.generic.tune_loops` keeps the recent ones).

    With ``workers`` > 1 the proposals' tunings run in that many forked processes (each Ms
    level in one; the same gains as serially: a tuner's result does not depend on what it
    solved before), and so do the Monte-Carlo runs.

    Returns
    -------
    DesignToSpec
    """
    from .montecarlo import run_monte_carlo

    n_decide = 3 * n_search if n_decide is None and isinstance(n_search, int) else n_decide
    for name, v in (("n_search", n_search), ("n_final", n_final), ("n_decide", n_decide)):
        if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= SAMPLES_MAX:
            raise ValueError(f"{name} = {v!r}; expected a number of samples in 1..{SAMPLES_MAX}")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed = {seed!r}; expected an integer >= 0")
    levels = tuple(MS_LEVELS if ms_levels is None else ms_levels)
    if not levels or any(isinstance(m, bool) or not isinstance(m, (int, float)) or not math.isfinite(m) or m <= 1
                         for m in levels):
        raise ValueError(f"ms_levels = {levels!r}; expected Ms bounds > 1")
    extra = dict(extra or {})
    n_grid = GRID_PICKS if grid else 0
    if 2 * len(levels) + len(extra) + n_grid > MAX_PROPOSALS:
        raise ValueError(f"{2 * len(levels)} tuned + {n_grid} grid + {len(extra)} given designs; expected at most "
                         f"{MAX_PROPOSALS}")
    t0 = time.perf_counter()
    if robust is not None and getattr(robust, "loops", None):
        unc, scens, loops = robust.uncertainty, list(robust.scenarios), list(robust.loops)
    else:
        unc = uncertainty_model(plant, scene.sections.plant_overrides)
        scens = scenarios(plant, scene, unc=unc)
        loops = scenario_loops(plant, scene, scens)
    aggregate = scene.sections.robust.aggregate if scene.sections.robust is not None else "worst"
    designs: dict = {}
    skipped: list = []
    tune_args = (loops, scens, unc, scene.objective, scene.controller, scene.mt_max, aggregate)
    for m, out in _tune_levels(tune_args, sorted(set(float(x) for x in levels)), workers or 1):
        if isinstance(out, str):  # a bound no gains meet: say so, go on
            skipped.append((f"tunings at Ms <= {m:g}", out))
            continue
        for k, pid, status in out:
            name = f"{k} (Ms <= {m:g})"
            if not is_ok(status):
                skipped.append((name, status))
            elif not any(_same(pid, p) for p in designs.values()):
                designs[name] = pid
    for name, pid in extra.items():
        if not any(_same(pid, p) for p in designs.values()) and getattr(pid, "kff", 0) == 0:
            designs[name] = pid
    spec = scene.sections.spec_bounds
    target = scene.sections.yield_target
    t1 = time.perf_counter()
    grid_info = None
    if grid and designs:
        grid_info = linear_yield_grid(plant, scene, list(designs.values()), spec, seed=seed, n=n_search, unc=unc,
                                      workers=workers or 1)
        for name, pid in grid_info["designs"].items():
            if not any(_same(pid, p) for p in designs.values()):
                designs[name] = pid
    tg = time.perf_counter()
    if not designs:
        raise ValueError("no design to evaluate: " + "; ".join(f"{n}: {w}" for n, w in skipped))
    kw = {"workers": workers or 1, "quiet": quiet}
    search_mc = run_monte_carlo(plant, scene, designs, n_search, seed=seed, unc=unc, spec=spec, **kw)
    ranked = rank_by_yield(search_mc, scene.objective, target=target)
    t2 = time.perf_counter()
    chosen = ranked["recommended"] if ranked else None
    decide = None
    if chosen is not None and n_decide > n_search:
        pool = sorted((r for r in ranked["rows"] if r["near_max"] and r["passed"] > 0),
                      key=lambda r: (-r["passed"], r["objective_p50"]))[:MAX_FINALISTS]
        if len(pool) > 1:
            dec_mc = run_monte_carlo(plant, scene, {r["name"]: designs[r["name"]] for r in pool}, n_decide, seed=seed,
                                     unc=unc, spec=spec, **kw)
            decide = rank_by_yield(dec_mc, scene.objective, target=target)
            if decide is not None and decide["recommended"] is not None:
                chosen = decide["recommended"]
    t3 = time.perf_counter()
    final = None
    if chosen is not None:
        final = run_monte_carlo(plant, scene, {chosen: designs[chosen]}, n_final, seed=seed + 1, unc=unc,
                                spec=spec, **kw)
    t4 = time.perf_counter()
    return DesignToSpec(chosen, designs.get(chosen), designs, ranked or {"rows": [], "why": "no finished sample"},
                        seed, final, seed + 1, tuple(skipped),
                        {"propose": t1 - t0, "grid": tg - t1, "search": t2 - tg, "decide": t3 - t2, "final": t4 - t3},
                        decide, grid_info)


#: The arguments of the proposals' tunings, set before the worker processes fork (they inherit
#: it: the loop models hold closures, which do not pickle).
_LEVEL_ARGS: list = []


def _tune_level(m: float):
    """``(m, [(kind, PID, status)])`` of the nominal and robust tunings at Ms <= ``m``, or ``(m,
    why)`` where no gains meet the bound (:data:`_LEVEL_ARGS` holds the rest)."""
    loops, scens, unc, objective, controller, mt_max, aggregate = _LEVEL_ARGS[0]
    try:
        rt = tune_scenario_loops(loops, scens, unc=unc, objective=objective, controller=controller, ms_max=m,
                                 mt_max=mt_max, aggregate=aggregate)
    except (ValueError, RuntimeError) as e:
        return m, str(e).splitlines()[0]
    return m, [(k, pid, rt.results[k].status) for k, pid in (("nominal", rt.nominal), ("robust", rt.robust))]


def _tune_levels(args: tuple, levels: list, workers: int) -> list:
    """:func:`_tune_level` of every level, in order: in up to ``workers`` forked processes (where
    the platform forks and there are two levels or more), else serially."""
    import multiprocessing

    _LEVEL_ARGS[:] = [args]
    try:
        if workers <= 1 or len(levels) < 2 or "fork" not in multiprocessing.get_all_start_methods():
            return [_tune_level(m) for m in levels]
        from concurrent.futures import ProcessPoolExecutor

        # One level at a time to whichever process is free.
        with ProcessPoolExecutor(max_workers=min(workers, len(levels)),
                                 mp_context=multiprocessing.get_context("fork")) as pool:
            return list(pool.map(_tune_level, levels))
    finally:
        _LEVEL_ARGS.clear()


def _same(a, b) -> bool:
    return all(getattr(a, k) == getattr(b, k) for k in ("kp", "ki", "kd", "tf", "kff"))


def linear_yield_grid(plant, scene, designs: Sequence, spec: dict, *, seed: int, n: int, unc=None,
                      size: int = GRID_SIZE, picks: int = GRID_PICKS, workers: int = 1) -> dict[str, Any]:
    """Gains scored by their *linear* yield on the Monte-Carlo samples ``0..n-1`` of ``seed``.

    Each sample's plant and operating point (:func:`prsa_ctrl.studies.mcjob.draw_sample`, the
    Monte Carlo's own draw) gives its own linearised loop model
    (:func:`prsa_ctrl.studies.sceneloops.actuator_loops`, the model the Monte Carlo measures
    Ms on). On a ``size x size`` grid of kp (N m s/rad) and ki/kp (1/s), log-spaced from half
    the smallest to twice the largest of ``designs`` (kd = 0), every sample's linear response
    gives its peak drop (rad/s), recovery time (s; the error back inside 5 % of the peak drop,
    :data:`prsa_ctrl.sim.metrics.DEFAULT_BAND`, to the end of the horizon) and Ms (on the
    model's frequency grid); a sample passes where the loop is stable and every one of those
    the spec bounds is met (saturation is left to the nonlinear runs). The linear yield is the
    fraction of samples passing.

    Proposed (at most ``picks``): among the gains of maximal linear yield, the one of the lowest
    median objective, the one with the most room (lowest 90th percentile over the samples of
    the largest metric/bound ratio) and the one of the highest linear yield next to it
    (``size`` and ``picks`` bounded: 2..40 and 0..8). ``workers``: processes that share the
    samples (the same numbers as one).

    Returns
    -------
    dict
        ``designs`` (name -> PID), ``proposed`` (names), ``linear_yield`` (name -> fraction),
        ``points``, ``samples`` and ``best_linear_yield``.
    """
    from ..drive.pid import PID
    from .scenerobust import operating_points

    if not (2 <= size <= 40 and 0 <= picks <= 8 and 1 <= n <= 100_000):
        raise ValueError(f"size = {size!r}, picks = {picks!r}, n = {n!r}; expected 2..40, 0..8 and 1..100000")
    pis = [d for d in designs if d.kp > 0 and d.ki > 0 and math.isfinite(d.kp) and math.isfinite(d.ki)]
    empty = {"designs": {}, "proposed": [], "linear_yield": {}, "points": 0, "samples": n, "best_linear_yield": 0.0}
    if not pis or picks == 0:
        return empty
    unc = uncertainty_model(plant, scene.sections.plant_overrides) if unc is None else unc
    ops = operating_points(scene)
    kps = np.geomspace(0.5 * min(d.kp for d in pis), 2.0 * max(d.kp for d in pis), size)
    rats = np.geomspace(0.5 * min(d.ki / d.kp for d in pis), 2.0 * max(d.ki / d.kp for d in pis), size)
    tf = pis[0].tf
    G = np.array([(kp, kp * r, 0.0) for kp in kps for r in rats])
    bounds = {k: float(spec[k]) for k in ("peak_drop_rad_s", "recovery_time_s", "ms") if k in spec}
    ratio, obj = _grid_scores((plant, scene, unc, ops, seed, G, bounds), n, workers)
    passed = np.sum(ratio <= 1.0, axis=0)
    top = int(passed.max())
    out = dict(empty, points=len(G), best_linear_yield=top / n)
    if top == 0:
        return out
    at_top = np.flatnonzero(passed == top)
    med = np.median(obj, axis=0)
    room = np.percentile(ratio, 90, axis=0, method="inverted_cdf")
    chosen: list[int] = []
    for idx in (at_top[np.argmin(med[at_top])], at_top[np.argmin(room[at_top])],
                int(np.lexsort((med, -passed))[min(len(at_top), len(G) - 1)])):
        if int(idx) not in chosen and len(chosen) < picks:
            chosen.append(int(idx))
    designs_out, lin = {}, {}
    for idx in chosen:
        kp, ki = float(G[idx, 0]), float(G[idx, 1])
        name = f"linear-yield grid {100 * passed[idx] / n:.0f} % (kp {kp:.4g}, ki {ki:.4g})"
        designs_out[name], lin[name] = PID(kp, ki, 0.0, tf), float(passed[idx] / n)
    out.update(designs=designs_out, proposed=list(designs_out), linear_yield=lin)
    return out


#: The linear-yield grid's arguments, set before its worker processes fork (they inherit it).
_GRID_ARGS: list = []


def _grid_scores(args: tuple, n: int, workers: int) -> tuple[np.ndarray, np.ndarray]:
    """``(ratio, obj)``, shape ``(n, points)``, of :func:`linear_yield_grid` (see there): samples
    ``0..n-1`` in up to ``workers`` forked processes (contiguous blocks; where the platform forks
    and there are 16 samples or more), else serially. The same numbers either way."""
    import multiprocessing

    workers = min(workers, n // 8)
    _GRID_ARGS[:] = [args]
    try:
        if workers <= 1 or "fork" not in multiprocessing.get_all_start_methods():
            parts = [_grid_block((0, n))]
        else:
            from concurrent.futures import ProcessPoolExecutor

            edges = np.linspace(0, n, workers + 1).round().astype(int)
            with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("fork")) as pool:
                parts = list(pool.map(_grid_block, [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]))
    finally:
        _GRID_ARGS.clear()
    return np.vstack([p[0] for p in parts]), np.vstack([p[1] for p in parts])


def _grid_block(span: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``(ratio, obj)`` of the samples ``span[0]..span[1]-1`` (:data:`_GRID_ARGS` holds the rest)."""
    from ..plant.uncertainty import apply
    from ..sim.metrics import DEFAULT_BAND
    from .mcjob import draw_sample
    from .sceneloops import actuator_loops

    plant, scene, unc, ops, seed, G, bounds = _GRID_ARGS[0]
    lo, hi = span
    ratio = np.zeros((hi - lo, len(G)))
    obj = np.zeros((hi - lo, len(G)))
    for i in range(lo, hi):
        values, op, _ = draw_sample(unc, ops, seed, i)
        p_i = apply(plant, values) if values else plant
        sc = scene.replace(setpoint_rad_s=ops[op][0], final_loads=(ops[op][1],))
        lp = actuator_loops(p_i, sc, estimator="none")[0]
        gi = G[:, : lp.n_gains] if lp.n_gains <= 3 else np.pad(G, ((0, 0), (0, lp.n_gains - 3)))
        a = lp.A0[None] + np.einsum("bi,ijk->bjk", gi, np.stack(lp.A))
        if lp.continuous is None and lp.nyquist is not None:
            stable = np.max(np.abs(np.linalg.eigvals(a)), axis=1) < 1.0
        else:
            stable = np.array([lp.is_stable(g) for g in gi])
        x = np.zeros((len(G), lp.A0.shape[0], 1))
        e = np.empty((len(G), lp.n_steps))
        ce = np.asarray(lp.Ce, float)
        for k in range(lp.n_steps):
            e[:, k] = x[:, :, 0] @ ce
            x = np.matmul(a, x)
            x[:, :, 0] += lp._input(k)
        sgn = np.where(e.max(axis=1) >= -e.min(axis=1), 1.0, -1.0)
        drop = np.max(e * sgn[:, None], axis=1)
        outside = np.abs(e) > DEFAULT_BAND * drop[:, None]
        last = np.where(outside.any(axis=1), lp.n_steps - 1 - np.argmax(outside[:, ::-1], axis=1), -1)
        rec = np.where(last < 0, 0.0, np.where(last == lp.n_steps - 1, np.inf, (last + 1) * lp.h))
        n0, ln, d0, ld = lp.parts()
        # Term by term (a float (points x gains) @ complex (gains x freqs) product went through
        # a complex GEMM: 31 ms a sample of CPU on the 2-core machine, against about 1 ms).
        num, den = np.broadcast_to(n0, (len(G), n0.size)).copy(), np.broadcast_to(d0, (len(G), d0.size)).copy()
        for k in range(gi.shape[1]):
            num += gi[:, k, None] * ln[k]
            den += gi[:, k, None] * ld[k]
        L = num / den
        ms = np.max(np.abs(1.0 / (1.0 + L)), axis=1)
        r = np.zeros(len(G))
        for key, v in (("peak_drop_rad_s", drop), ("recovery_time_s", rec), ("ms", ms)):
            if key in bounds:
                r = np.maximum(r, v / bounds[key])
        ratio[i - lo] = np.where(stable & np.isfinite(r), r, np.inf)
        obj[i - lo] = np.where(stable, _horizon_objective(e, lp.h, scene.objective), np.inf)
    return ratio, obj


def _horizon_objective(e, h: float, kind: str):
    """The objective of each row of ``e`` over the horizon (rectangle rule at the sample time)."""
    t = np.arange(e.shape[1]) * h
    f = {"iae": np.abs(e), "ie": e, "ise": e * e, "itae": t * np.abs(e)}.get(kind, np.abs(e))
    return np.sum(f, axis=1) * h
