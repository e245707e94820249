"""Robust tuning: one set of gains for M scenario models at once (one CasADi/ipopt NLP).

A *scenario* is one point of the plant's uncertainty (the nominal point, the vertices of the
uncertainty box, seeded samples of it) at one operating point of the scene's range (setpoint
speed x final load). Each scenario becomes a loop model; :func:`tune_scenario_loops` (through
:func:`prsa_ctrl.tuning.generic.tune_loops`) then optimises shared gains with the Ms (and Mt) bound on
every scenario and the worst-case or mean objective. :func:`tune_robust` is the generic form for
a list of python-control plants (like systune's plant arrays). A scene's scenarios and their
loop models are read in :mod:`prsa_ctrl.studies.scenerobust`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any, Sequence

import numpy as np

from .._lazy import module
from ..options import MS_MAX_DEFAULT
from ..plant.uncertainty import UncertaintyModel
from ..reporttext import SPEC_LABEL, format_robust, format_yield_table  # format_yield_table re-exported
from ..results import is_converged, is_ok, json_safe
from .loops import LoopModel
from .tuner import TuningResult
from .builders import continuous_loop
from .generic import tune_loops

control = module("control")

__all__ = ["Scenario", "RobustTuning", "tune_scenario_loops", "compare_designs", "tune_robust", "rank_by_yield",
           "format_yield_table"]

@dataclass(frozen=True)
class Scenario:
    """One scenario model: parameter values (file units, only the uncertain keys), setpoint
    (rad/s) and final load (N)."""

    name: str
    kind: str  # "nominal", "vertex" or "sample"
    values: dict
    setpoint_rad_s: float
    final_load: float

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "kind": self.kind, "values": dict(self.values),
                "setpoint_rad_s": self.setpoint_rad_s, "final_load_n": self.final_load}


def _summary(pid, loops: Sequence[LoopModel], objective: str) -> dict[str, Any]:
    g = pid.gains if hasattr(pid, "gains") else pid
    per = []
    for lp in loops:
        stable = lp.is_stable(g)
        ms, mt = lp.sensitivity_peaks(g)
        per.append({"scenario": lp.name, "stable": bool(stable), "ms": float(ms) if stable else math.inf,
                    "mt": float(mt) if stable else math.inf,
                    objective: float(lp.objective(g, objective)) if stable else math.inf})
    objs = np.array([p[objective] for p in per])
    return {"per_scenario": per, "max_ms": float(max(p["ms"] for p in per)),
            "worst_objective": float(objs.max()), "mean_objective": float(objs.mean()),
            "all_stable": all(p["stable"] for p in per)}


def compare_designs(designs: dict, loops: Sequence[LoopModel], scens: Sequence[Scenario], objective: str,
                    ms_max: float) -> dict[str, Any]:
    """Side-by-side linear metrics of several designs (``name -> PID``) on the same scenarios:
    per-scenario Ms, Mt, objective and stability, the worst/mean objective, max Ms, and how
    many scenarios break the Ms bound."""
    out: dict[str, Any] = {"objective": objective, "ms_max": ms_max, "scenarios": [s.as_dict() for s in scens],
                           "designs": {}}
    for name, pid in designs.items():
        summ = _summary(pid, loops, objective)
        for p, s in zip(summ["per_scenario"], scens):
            p["scenario"] = s.name
        summ["ms_violations"] = sum(1 for p in summ["per_scenario"] if not p["ms"] <= ms_max * (1 + 1e-9))
        summ["gains"] = pid.as_dict()
        out["designs"][name] = summ
    return out


@dataclass(frozen=True)
class RobustTuning:
    """Nominal and robust designs of a scene and their comparison on the same scenario models
    (frozen: :meth:`with_recommendation` returns a new study with :attr:`recommended` set).

    ``status`` is ``"optimal"`` when both tunings are verified optima, else ``"not converged:
    ..."`` naming the design(s) that are not (:data:`prsa_ctrl.results.STATUSES`); ``warnings``
    are the two tunings' warnings, each prefixed with its design's name.
    """

    nominal: Any  # PID
    robust: Any  # PID
    scenarios: tuple[Scenario, ...]
    comparison: dict
    timing_s: dict
    uncertainty: UncertaintyModel
    results: dict = field(default_factory=dict, repr=False)  # name -> TuningResult
    loops: tuple = field(default=(), repr=False)
    recommended: dict = field(default_factory=dict)  # see :meth:`recommend`
    others: dict = field(default_factory=dict, repr=False)  # Monte-Carlo name -> PID of the other designs

    @property
    def status(self) -> str:
        bad = [f"{k} {r.status}" for k, r in self.results.items() if not is_converged(r.status)]
        return "not converged: " + "; ".join(bad) if bad else "optimal"

    @property
    def converged(self) -> bool:
        """Both designs are verified optima."""
        return is_converged(self.status)

    @property
    def ok(self) -> bool:
        return is_ok(self.status)

    @property
    def warnings(self) -> tuple[str, ...]:
        return tuple(f"{k} design: {w}" for k, r in self.results.items() for w in r.warnings)

    def as_dict(self) -> dict[str, Any]:
        """Plain data for strict JSON (through :func:`prsa_ctrl.results.json_safe`: an unstable
        scenario's infinite Ms/objective becomes null, its ``stable`` flag says why)."""
        return json_safe({"nominal_gains": self.nominal.as_dict(), "robust_gains": self.robust.as_dict(),
                          "recommended": self.recommended or self.recommend(),
                          "uncertainty": self.uncertainty.as_dict(), "comparison": self.comparison,
                          "timing_s": self.timing_s,
                          "solver": {k: {kk: r.stats.get(kk) for kk in ("status", "iterations", "wall_time_s")}
                                     for k, r in self.results.items()}})

    def design(self, name: str):
        """The PID of design ``name`` (``"nominal"``, ``"robust"`` or the Monte-Carlo name of
        another design passed to :meth:`with_recommendation`)."""
        return {"nominal": self.nominal, "robust": self.robust, **self.others}[name]

    def with_recommendation(self, monte_carlo=None, names: dict | None = None,
                            others: dict | None = None, target: float | None = None) -> "RobustTuning":
        """A copy of the study with :attr:`recommended` = :meth:`recommend` ``(monte_carlo,
        names)`` and the other designs (Monte-Carlo name -> PID) the recommendation may name."""
        new = replace(self, others=dict(others or {}))
        return replace(new, recommended=new.recommend(monte_carlo, names, target))

    def recommend(self, monte_carlo=None, names: dict | None = None,
                  target: float | None = None) -> dict[str, Any]:
        """The design to use, ranked by the yield against the scene's ``[spec]`` -- the spec
        the designs are judged by (the study is not changed: :meth:`with_recommendation`
        returns one that keeps it in :attr:`recommended`).

        With a Monte-Carlo report: every design it evaluated on the same samples (nominal,
        robust and the others, e.g. baselines and candidates, given to
        :meth:`with_recommendation`) is ranked by :func:`rank_by_yield`: the recommendation is
        never below another design's yield by more than the two yields' Wilson 95 %
        half-widths added; among the designs of (near-)maximal yield, the lowest median
        objective. A design that meets the spec on no sample is never recommended
        (``design`` None); ``table`` holds every design's yield, interval, median objective
        and spec-item failures. Without one: the spec is not checked; the ranking is
        the scenario models' Ms bound, then the worst-case objective, and ``yield`` is None.

        Parameters
        ----------
        monte_carlo : MonteCarloReport, optional
        names : dict, optional
            This study's design name -> its name in the Monte-Carlo report (default
            ``"nominal design"``, ``"robust design"``).
        target : float, optional
            The spec's target yield (``[spec] yield``): where no design reaches it, ``limit``
            names the limiting spec item (:func:`rank_by_yield`).

        Returns
        -------
        dict
            ``design`` (``"nominal"``, ``"robust"``, another design's Monte-Carlo name, or
            None), ``name`` (its name in the report), ``gains``, ``yield`` (fraction) with
            ``passed``/``samples``/``yield_ci95``, ``basis``, ``why`` (one sentence) and, with
            a Monte-Carlo report, ``table`` and ``rule``.
        """
        names = names or {"nominal": "nominal design", "robust": "robust design"}
        comp = self.comparison["designs"]
        lin = {k: (comp[k]["ms_violations"], comp[k]["worst_objective"]) for k in ("nominal", "robust")}
        obj = self.comparison["objective"].upper()
        ranked = None
        if monte_carlo is not None:
            ranked = rank_by_yield(monte_carlo, self.comparison["objective"],
                                   lin={names[k]: lin[k] for k in lin if k in names}, target=target)
        if ranked is not None and sum(1 for r in ranked["rows"] if r["name"] in names.values()) == 2:
            back = {v: k for k, v in names.items()}
            rec: dict[str, Any] = {"basis": ranked["basis"], "table": ranked["rows"], "rule": ranked["rule"]}
            rec.update({k: ranked[k] for k in ("target", "reached", "limit") if k in ranked})
            best = ranked["recommended"]
            if best is None:
                rec.update(design=None, name=None, why=ranked["why"])
                return rec
            row = next(r for r in ranked["rows"] if r["name"] == best)
            key = back.get(best, best)
            try:
                gains = self.design(key).as_dict()
            except KeyError:
                gains = dict(row["gains"])
            rec.update(design=key, name=best, gains=gains, **{"yield": row["yield"]}, passed=row["passed"],
                       samples=row["samples"], yield_ci95=list(row["yield_ci95"]), why=ranked["why"])
        else:
            best = min(("robust", "nominal"), key=lambda k: lin[k])
            other = "nominal" if best == "robust" else "robust"
            def worst(k: str) -> str:
                return f"worst {obj} {lin[k][1]:.4g}" if math.isfinite(lin[k][1]) else "unstable on a model"
            why = (f"{best}: {lin[best][0]} of {len(self.scenarios)} scenario models over the Ms bound, {worst(best)} "
                   f"({other}: {lin[other][0]}, {worst(other)}); the [spec] was not checked (no Monte Carlo run)")
            rec = {"basis": "scenario models (Ms bound, then the worst-case objective); spec not checked",
                   "design": best, "name": f"{best} design", "gains": self.design(best).as_dict(), "yield": None, "why": why}
        return rec

    def format(self) -> str:
        """The robust study's report, the text ``prsa-tune --robust`` prints
        (:func:`prsa_ctrl.reporttext.format_robust`, its one home)."""
        return format_robust(self)


#: z of a two-sided 95 % interval (the Wilson intervals' and the paired comparison's).
_Z95 = 1.959963984540054


def _spec_failures(metrics: np.ndarray, spec: dict, names: Sequence[str]) -> dict[str, np.ndarray]:
    """Per spec item, which samples (rows of ``metrics``, samples x ``names``) break it;
    ``finite``: a run with a non-finite metric other than Ms/Mt (failed to simulate or never
    re-entered the band), which fails the spec whatever it states (as
    :func:`prsa_ctrl.studies.montecarlo.run_monte_carlo` counts)."""
    names = list(names)
    run_cols = [i for i, n in enumerate(names) if n not in ("ms", "mt")]
    out = {"finite": ~np.all(np.isfinite(metrics[:, run_cols]), axis=1)}
    for k, bound in spec.items():
        if k == "no_saturation":
            if bound:
                out[k] = metrics[:, names.index("saturated")] > 0
            continue
        col = metrics[:, names.index(k)]
        out[k] = ~(col <= bound)
    return out


def rank_by_yield(monte_carlo, objective: str, lin: dict | None = None,
                  target: float | None = None) -> dict[str, Any] | None:
    """Rank every design of a Monte-Carlo report by its yield against the spec, and choose one.

    The recommendation is a design of (near-)maximal yield: one whose yield is below no other
    design's by more than the two yields' Wilson 95 % half-widths added, and -- where the
    per-sample outcomes are known (the designs ran on the same samples: common random
    numbers) -- not significantly below any other in the paired comparison (discordant samples
    ``b`` other-only, ``c`` this-only: ``b - c <= 1.96 sqrt(b + c)``). Among those, the lowest
    median objective on the nonlinear runs, then the most samples inside the spec, then
    (``lin``) fewer scenario models over the Ms bound and the lower worst-case objective.
    A design that meets the spec on no sample is never recommended.

    Parameters
    ----------
    monte_carlo : MonteCarloReport
        Its ``designs`` (yields) and, when present, ``samples`` (per-sample metrics) and ``spec``.
    objective : str
        Metric of the median objective (``"iae"``, ...).
    lin : dict, optional
        Monte-Carlo name -> (models over the Ms bound, worst-case objective) for the designs
        of a robust study (last tie-break).
    target : float, optional
        The spec's target yield (``[spec] yield``, a fraction). When no design reaches it,
        ``limit`` names the spec item the recommended design fails most often, its value at
        the target's percentile against the bound, and the yield without that item.

    Returns
    -------
    dict or None
        ``rows`` (one per design: ``name``, ``gains``, ``passed``, ``samples``, ``yield``,
        ``yield_ci95``, ``objective_p50``, ``fails`` = spec item -> samples breaking it, or
        None when unknown, ``near_max``), ``recommended`` (a name or None), ``why``, ``basis``
        and ``rule`` (and ``target``, ``reached`` and ``limit`` with a target); None when the
        report has no finished sample.
    """
    designs = [d for d in monte_carlo.designs if d.n > 0]
    if not designs:
        return None
    lin = lin or {}
    samples = getattr(monte_carlo, "samples", None) or {}
    spec = dict(getattr(monte_carlo, "spec", None) or {})
    flags: dict[str, np.ndarray] = {}
    fails: dict[str, dict | None] = {d.name: None for d in designs}
    if "metrics" in samples and "design_names" in samples and "metric_names" in samples:
        names = list(samples["design_names"])
        for d in designs:
            if d.name in names:
                m = samples["metrics"][:, names.index(d.name), :]
                per = _spec_failures(m, spec, samples["metric_names"])
                ok = ~np.any(np.stack(list(per.values())), axis=0)
                if int(ok.sum()) != d.passed:  # the report's own count: never two answers
                    raise ValueError(f"{d.name}: {int(ok.sum())} samples pass from the per-sample metrics, "
                                     f"{d.passed} in the report")
                flags[d.name] = ok
                fails[d.name] = {k: int(v.sum()) for k, v in per.items()}
    half = {d.name: (d.ci95[1] - d.ci95[0]) / 2 for d in designs}

    def obj_p50(d) -> float:
        v = (d.percentiles.get(objective) or {}).get("p50")
        return float(v) if v is not None and math.isfinite(v) else math.inf

    def paired_ok(d, o) -> bool:
        if d.name not in flags or o.name not in flags:
            return True
        b = int(np.sum(flags[o.name] & ~flags[d.name]))
        c = int(np.sum(flags[d.name] & ~flags[o.name]))
        return b - c <= _Z95 * math.sqrt(b + c)

    near = {d.name: all(o.yield_ - d.yield_ <= half[o.name] + half[d.name] + 1e-12 and paired_ok(d, o)
                        for o in designs if o is not d) for d in designs}
    rows = [{"name": d.name, "gains": dict(d.gains), "passed": d.passed, "samples": d.n, "yield": d.yield_,
             "yield_ci95": list(d.ci95), "objective_p50": obj_p50(d), "fails": fails[d.name],
             "near_max": near[d.name]} for d in designs]
    n = designs[0].n
    rule = ("a design of (near-)maximal yield: below no other design by more than the two Wilson 95 % "
            "half-widths added" + (", nor significantly below any in the paired comparison on the same samples"
                                   if flags else "") + f"; then the lowest median {objective.upper()}")
    basis = f"Monte-Carlo yield against the scene's [spec] ({n} samples, {len(designs)} designs, same samples)"
    top = max(d.passed for d in designs)
    txt = {d.name: f"{d.name} {100 * d.yield_:.1f} % ({d.passed}/{d.n})" for d in designs}
    if top == 0:
        return {"rows": rows, "recommended": None, "basis": basis, "rule": rule,
                "why": f"no design meets the spec on any sample ({', '.join(txt.values())}); "
                       "widen the spec or narrow the uncertainty"}
    pool = [d for d in designs if near[d.name] and d.passed > 0]
    best = min(pool, key=lambda d: (obj_p50(d), -d.passed, *lin.get(d.name, (0, 0.0))))
    leader = max(designs, key=lambda d: d.passed)
    if best.passed == top:
        why = f"highest yield: {txt[best.name]}" + (
            f" against {', '.join(txt[d.name] for d in designs if d is not best)}" if len(designs) > 1 else "")
    else:
        why = (f"{txt[best.name]} is within the 95 % intervals of the highest yield ({txt[leader.name]}) "
               f"and has the lower median {objective.upper()} ({_obj_text(best, obj_p50)} against "
               f"{_obj_text(leader, obj_p50)})")
    if best.passed < best.n:
        why += f"; {best.n - best.passed} of {best.n} samples still fail the spec"
        f = fails[best.name]
        if f:
            why += " (" + ", ".join(f"{SPEC_LABEL.get(k, k)} {v}" for k, v in f.items() if v) + ")"
    out = {"rows": rows, "recommended": best.name, "basis": basis, "rule": rule, "why": why}
    if target is not None:
        out["target"] = float(target)
        out["reached"] = any(d.yield_ >= target for d in designs)
        if not out["reached"]:
            out["limit"] = _limit(samples, best.name, spec, target, flags.get(best.name))
            lim = out["limit"]
            out["why"] += (f"; no design reaches the target yield {100 * target:.1f} % (best "
                           f"{100 * leader.yield_:.1f} %)" + (f": the limit is {lim['text']}" if lim else ""))
    return out


def _limit(samples: dict, name: str, spec: dict, target: float, ok) -> dict[str, Any] | None:
    """The spec item that limits design ``name``'s yield: the one most samples break; its
    value at the target's percentile against its bound, and the yield were that item dropped."""
    if ok is None:
        return None
    names = list(samples["design_names"])
    metric_names = list(samples["metric_names"])
    m = samples["metrics"][:, names.index(name), :]
    per = _spec_failures(m, spec, metric_names)
    item = max(per, key=lambda k: int(per[k].sum()))
    k = int(per[item].sum())
    if k == 0:
        return None
    others = np.zeros(len(m), bool)
    for kk, v in per.items():
        if kk != item:
            others |= v
    lim: dict[str, Any] = {"design": name, "item": item, "fails": k, "samples": len(m),
                           "yield_without_it": float(np.mean(~others))}
    q = 100 * target
    label = SPEC_LABEL.get(item, item)
    if item in ("finite", "no_saturation"):
        what = "runs that did not finish" if item == "finite" else "saturated runs"
        lim["text"] = f"{label} ({what}: {k} of {len(m)} samples on {name})"
    else:
        col = m[:, metric_names.index(item)]
        v = float(np.percentile(np.where(np.isnan(col), np.inf, col), q, method="inverted_cdf"))
        lim.update(percentile=q, value=v, bound=float(spec[item]))
        lim["text"] = (f"{label} p{q:g} {v:.4g} {'>' if v > spec[item] else '<='} {spec[item]:g} on {name} ({k} of {len(m)} samples; "
                       f"{100 * lim['yield_without_it']:.1f} % without this item)")
    return lim


def _obj_text(d, obj_p50) -> str:
    v = obj_p50(d)
    return f"{v:.4g}" if math.isfinite(v) else "not finite"


def tune_scenario_loops(loops: Sequence[LoopModel], scens: Sequence[Scenario], *, unc: UncertaintyModel,
                        objective: str, controller: str, ms_max: float, mt_max: float | None = None,
                        aggregate: str = "worst", timing_s: dict | None = None) -> RobustTuning:
    """Tune the nominal design (the nominal scenarios' loops) and the robust design (every
    scenario's loop, one NLP), and compare them on all scenario loops.

    Parameters
    ----------
    loops : list of LoopModel
        One loop model per scenario, in the order of ``scens``.
    scens : list of Scenario
    unc : UncertaintyModel
        The uncertainty the scenarios sample (kept in the result).
    objective, controller : str
        Tuning objective (``"iae"``, ...) and structure (``"pi"``, ``"pid"``).
    ms_max, mt_max : float
        Sensitivity bounds on every scenario loop.
    aggregate : {"worst", "mean"}
        Objective over the scenarios.
    timing_s : dict, optional
        Timings measured before (s); the tunings' are added.

    Returns
    -------
    RobustTuning
    """
    if aggregate not in ("worst", "mean"):
        raise ValueError(f"aggregate = {aggregate!r}; expected 'worst' or 'mean'")
    timing = dict(timing_s or {})
    common = dict(objective=objective, controller=controller, ms_max=ms_max, mt_max=mt_max)
    nominal_idx = [i for i, s in enumerate(scens) if s.kind == "nominal"]
    t1 = time.perf_counter()
    nom = tune_loops([loops[i] for i in nominal_idx], worst_case=aggregate == "worst", **common)
    timing["tune_nominal"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    rob_res = tune_loops(loops, worst_case=aggregate == "worst", **common)
    timing["tune_robust"] = time.perf_counter() - t2
    comp = compare_designs({"nominal": nom.pid, "robust": rob_res.pid}, loops, scens, objective, ms_max)
    comp["aggregate"] = aggregate
    return RobustTuning(nom.pid, rob_res.pid, tuple(scens), comp, timing, unc, {"nominal": nom, "robust": rob_res},
                        tuple(loops))


def tune_robust(
    plants: Sequence[Any],
    *,
    objective: str = "iae",
    controller: str = "pi",
    ms_max: float = MS_MAX_DEFAULT,
    mt_max: float | None = None,
    aggregate: str = "worst",
    weights: Sequence[float] | None = None,
    horizon: float | None = None,
    tf: float | None = None,
    n_steps: int = 2000,
    step: float = 1.0,
    disturbance: str | int | None = None,
    max_noise_gain: float | None = None,
) -> TuningResult:
    """One PI/PID for a list of SISO python-control plants (systune-style plant array): Ms
    (Mt) bound on every plant, worst-case or (weighted) mean objective, one ipopt NLP.

    Parameters
    ----------
    plants : list of control.LTI
        Continuous plants; control input first, optional load-disturbance input.
    aggregate : {"worst", "mean"}
        Objective over the plants.
    horizon, tf : float, s, optional
        Objective horizon and derivative filter; by default from the first plant (40 / w135,
        0.1 / w135, where its phase reaches -135 deg), as :func:`prsa_ctrl.tune_pid` does.

    Returns
    -------
    TuningResult
        ``margins`` and ``per_loop`` hold one entry per plant.

    Examples
    --------
    >>> import control
    >>> ps = [control.tf([k], [1, 3, 3, 1]) for k in (0.5, 1.0, 2.0)]
    >>> r = tune_robust(ps, objective="iae", ms_max=1.6)
    >>> all(m.ms <= 1.6 + 1e-6 for m in r.margins)
    True
    """
    if isinstance(plants, (str, bytes)) or not hasattr(plants, "__iter__"):
        raise ValueError(f"plants = {plants!r}; expected a list of python-control LTI plants")
    plants = list(plants)
    if not plants:
        raise ValueError("plants = []; expected at least one LTI plant")
    for i, p in enumerate(plants):
        if not isinstance(p, control.LTI):
            raise ValueError(f"plants[{i}] = {p!r}; expected a python-control LTI plant (tf or ss)")
    if aggregate not in ("worst", "mean"):
        raise ValueError(f"aggregate = {aggregate!r}; expected 'worst' or 'mean'")
    if len(plants) > 256:
        raise ValueError(f"{len(plants)} plants; expected at most 256 in one NLP")
    sys0 = control.ss(plants[0])
    if horizon is None or tf is None:
        w = np.logspace(-4, 4, 4000)
        resp = np.asarray(control.frequency_response(
            control.ss(sys0.A, sys0.B[:, :1], sys0.C, sys0.D[:, :1]), w).complex).ravel()
        below = np.flatnonzero(np.unwrap(np.angle(resp)) <= -0.75 * np.pi)
        if below.size == 0:
            raise ValueError("the first plant's phase never reaches -135 deg; pass horizon= (s), tf= (s) "
                             "and max_noise_gain=")
        w135 = w[below[0]]
        horizon = 40.0 / w135 if horizon is None else horizon
        tf = 0.1 / w135 if tf is None else tf
    loops = [continuous_loop(p, tf=tf, horizon=horizon, n_steps=n_steps, step=step, disturbance=disturbance)
             for p in plants]
    # One frequency grid for all plants keeps the constraints comparable.
    return tune_loops(loops, objective=objective, controller=controller, ms_max=ms_max, mt_max=mt_max,
                      weights=weights, worst_case=aggregate == "worst", max_noise_gain=max_noise_gain)
