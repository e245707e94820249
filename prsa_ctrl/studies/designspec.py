"""Design to the spec (issue 34): search a family of designs proposed by the linear scenario
models for the one that meets the scene's ``[spec]`` most often on the nonlinear Monte Carlo.

1. *Propose*: the nominal and the robust (every scenario model) tunings of
   :func:`prsa_ctrl.tuning.robust.tune_scenario_loops` at a sequence of Ms bounds, plus any
   given designs (the baselines).
2. *Decide*: every proposal runs on the same ``n_search`` nonlinear Monte-Carlo samples
   (common random numbers: seed ``seed``) and :func:`prsa_ctrl.tuning.robust.rank_by_yield`
   chooses: (near-)maximal yield, then the lowest median objective.
3. *Report*: the chosen design runs again on ``n_final`` fresh samples (seed ``seed + 1``, a
   stream the search did not use); that run's yield and Wilson interval are the reported ones.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Sequence

from ..results import is_ok, json_safe
from ..tuning.robust import format_yield_table, rank_by_yield, tune_scenario_loops
from ..plant.uncertainty import uncertainty_model
from .scenerobust import scenario_loops, scenarios

__all__ = ["DesignToSpec", "design_to_spec", "MS_LEVELS", "MAX_PROPOSALS"]

#: Default Ms bounds of the proposed family (each gives a nominal and a robust design).
MS_LEVELS = (1.2, 1.3, 1.4, 1.5, 1.6, 1.8)
#: Upper bound on the designs the search evaluates (checked before any tuning).
MAX_PROPOSALS = 32


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
            "skipped": [{"design": n, "why": w} for n, w in self.skipped], "timing_s": self.timing_s})

    def format(self, objective: str) -> str:
        s = self.search
        n = s["rows"][0]["samples"] if s.get("rows") else 0
        lines = [f"Design to the spec: {len(self.designs)} designs on the same {n} search samples (seed "
                 f"{self.search_seed}); * chosen: {s.get('rule', '')}", format_yield_table(
                     {"table": s.get("rows"), "name": self.chosen}, objective)]
        lines += [f"  not evaluated: {n_} ({w})" for n_, w in self.skipped]
        fy = self.final_yield
        if fy is None:
            lines.append(f"chosen: none ({s.get('why', '')})")
        else:
            lo, hi = fy.ci95
            lines.append(f"chosen: {self.chosen}: yield {100 * fy.yield_:.1f} % ({fy.passed}/{fy.n}), 95 % CI "
                         f"[{100 * lo:.1f}, {100 * hi:.1f}] % on {fy.n} fresh samples (seed {self.final_seed}, not "
                         "used by the search)")
            if s.get("limit"):
                lines.append(f"the target yield {100 * s['target']:.1f} % is not reached on the search samples: "
                             f"the limit is {s['limit']['text']}")
        return "\n".join(lines)


def design_to_spec(plant, scene, *, n_search: int = 40, n_final: int = 200, seed: int = 0,
                   ms_levels: Sequence[float] | None = None, extra: dict | None = None,
                   workers: int | None = None, quiet: bool = True) -> DesignToSpec:
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

    Returns
    -------
    DesignToSpec
    """
    from .montecarlo import run_monte_carlo

    for name, v in (("n_search", n_search), ("n_final", n_final)):
        if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 100_000:
            raise ValueError(f"{name} = {v!r}; expected a number of samples in 1..100000")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed = {seed!r}; expected an integer >= 0")
    levels = tuple(MS_LEVELS if ms_levels is None else ms_levels)
    if not levels or any(isinstance(m, bool) or not isinstance(m, (int, float)) or not math.isfinite(m) or m <= 1
                         for m in levels):
        raise ValueError(f"ms_levels = {levels!r}; expected Ms bounds > 1")
    extra = dict(extra or {})
    if 2 * len(levels) + len(extra) > MAX_PROPOSALS:
        raise ValueError(f"{2 * len(levels)} tuned + {len(extra)} given designs; expected at most {MAX_PROPOSALS}")
    t0 = time.perf_counter()
    unc = uncertainty_model(plant, scene)
    scens = scenarios(plant, scene, unc=unc)
    loops = scenario_loops(plant, scene, scens)
    rob = (getattr(scene, "robust", None) or {}).get("robust", {})
    aggregate = rob.get("aggregate", "worst")
    designs: dict = {}
    skipped: list = []
    for m in sorted(set(float(x) for x in levels)):
        try:
            rt = tune_scenario_loops(loops, scens, unc=unc, objective=scene.objective, controller=scene.controller,
                                     ms_max=m, mt_max=scene.mt_max, aggregate=aggregate)
        except (ValueError, RuntimeError) as e:  # a bound no gains meet: say so, go on
            skipped.append((f"tunings at Ms <= {m:g}", str(e).splitlines()[0]))
            continue
        for k, pid in (("nominal", rt.nominal), ("robust", rt.robust)):
            name = f"{k} (Ms <= {m:g})"
            status = rt.results[k].status
            if not is_ok(status):
                skipped.append((name, status))
            elif not any(_same(pid, p) for p in designs.values()):
                designs[name] = pid
    for name, pid in extra.items():
        if not any(_same(pid, p) for p in designs.values()) and getattr(pid, "kff", 0) == 0:
            designs[name] = pid
    t1 = time.perf_counter()
    if not designs:
        raise ValueError("no design to evaluate: " + "; ".join(f"{n}: {w}" for n, w in skipped))
    spec = dict((getattr(scene, "robust", None) or {}).get("spec", {}))
    target = ((getattr(scene, "robust", None) or {}).get("spec_yield") or {}).get("yield")
    kw = {"workers": workers or 1, "quiet": quiet}
    search_mc = run_monte_carlo(plant, scene, designs, n_search, seed=seed, unc=unc, spec=spec, **kw)
    ranked = rank_by_yield(search_mc, scene.objective, target=target)
    t2 = time.perf_counter()
    chosen = ranked["recommended"] if ranked else None
    final = None
    if chosen is not None:
        final = run_monte_carlo(plant, scene, {chosen: designs[chosen]}, n_final, seed=seed + 1, unc=unc,
                                spec=spec, **kw)
    t3 = time.perf_counter()
    return DesignToSpec(chosen, designs.get(chosen), designs, ranked or {"rows": [], "why": "no finished sample"},
                        seed, final, seed + 1, tuple(skipped),
                        {"propose": t1 - t0, "search": t2 - t1, "final": t3 - t2})


def _same(a, b) -> bool:
    return all(getattr(a, k) == getattr(b, k) for k in ("kp", "ki", "kd", "tf", "kff"))
