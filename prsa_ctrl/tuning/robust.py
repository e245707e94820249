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
from ..results import is_converged, is_ok, json_safe
from .loops import LoopModel
from .tuner import TuningResult
from .builders import continuous_loop
from .generic import tune_loops

control = module("control")

__all__ = ["Scenario", "RobustTuning", "tune_scenario_loops", "compare_designs", "tune_robust"]

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
        m = lp.margins(g)
        per.append({"scenario": lp.name, "stable": bool(stable), "ms": float(m.ms) if stable else math.inf,
                    "mt": float(m.mt) if stable else math.inf,
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
        """The PID of design ``name`` (``"nominal"`` or ``"robust"``)."""
        return {"nominal": self.nominal, "robust": self.robust}[name]

    def with_recommendation(self, monte_carlo=None, names: dict | None = None) -> "RobustTuning":
        """A copy of the study with :attr:`recommended` = :meth:`recommend` ``(monte_carlo, names)``."""
        return replace(self, recommended=self.recommend(monte_carlo, names))

    def recommend(self, monte_carlo=None, names: dict | None = None) -> dict[str, Any]:
        """The design to use, ranked by the yield against the scene's ``[spec]`` -- the spec
        the designs are judged by (the study is not changed: :meth:`with_recommendation`
        returns one that keeps it in :attr:`recommended`).

        With a Monte-Carlo report: the design (nominal or robust) with the most samples
        inside the spec; a tie goes to fewer scenario models over the Ms bound, then the
        lower worst-case objective. A design that meets the spec on no sample is never
        recommended (``design`` None). Without one: the spec is not checked; the ranking is
        the scenario models' Ms bound, then the worst-case objective, and ``yield`` is None.

        Parameters
        ----------
        monte_carlo : MonteCarloReport, optional
        names : dict, optional
            This study's design name -> its name in the Monte-Carlo report (default
            ``"nominal design"``, ``"robust design"``).

        Returns
        -------
        dict
            ``design`` (``"nominal"``, ``"robust"`` or None), ``gains``, ``yield`` (fraction)
            with ``passed``/``samples``/``yield_ci95``, ``basis`` and ``why`` (one sentence).
        """
        names = names or {"nominal": "nominal design", "robust": "robust design"}
        comp = self.comparison["designs"]
        lin = {k: (comp[k]["ms_violations"], comp[k]["worst_objective"]) for k in ("nominal", "robust")}
        obj = self.comparison["objective"].upper()
        ylds = {}
        if monte_carlo is not None:
            by_name = {d.name: d for d in monte_carlo.designs}
            ylds = {k: by_name[v] for k, v in names.items() if v in by_name and by_name[v].n > 0}
        if len(ylds) == 2:
            order = sorted(ylds, key=lambda k: (-ylds[k].passed, *lin[k]))
            best, other = order
            yb, yo = ylds[best], ylds[other]
            rec: dict[str, Any] = {"basis": f"Monte-Carlo yield against the scene's [spec] ({yb.n} samples)"}
            txt = {k: f"{k} {100 * ylds[k].yield_:.1f} % ({ylds[k].passed}/{ylds[k].n})" for k in ylds}
            if yb.passed == 0:
                rec.update(design=None, why=f"neither design meets the spec on any sample ({txt[best]}, {txt[other]}); "
                           "widen the spec or narrow the uncertainty")
                return rec
            if yb.passed > yo.passed:
                why = f"higher yield: {txt[best]} against {txt[other]}"
            else:
                why = (f"equal yield ({txt[best]}, {txt[other]}); {best} has "
                       + ("fewer models over the Ms bound" if lin[best][0] < lin[other][0] else f"the lower worst {obj}"))
            if yb.passed < yb.n:
                why += f"; {yb.n - yb.passed} of {yb.n} samples still fail the spec"
            rec.update(design=best, gains=self.design(best).as_dict(), **{"yield": yb.yield_}, passed=yb.passed,
                       samples=yb.n, yield_ci95=list(yb.ci95), why=why)
        else:
            best = min(("robust", "nominal"), key=lambda k: lin[k])
            other = "nominal" if best == "robust" else "robust"
            def worst(k: str) -> str:
                return f"worst {obj} {lin[k][1]:.4g}" if math.isfinite(lin[k][1]) else "unstable on a model"
            why = (f"{best}: {lin[best][0]} of {len(self.scenarios)} scenario models over the Ms bound, {worst(best)} "
                   f"({other}: {lin[other][0]}, {worst(other)}); the [spec] was not checked (no Monte Carlo run)")
            rec = {"basis": "scenario models (Ms bound, then the worst-case objective); spec not checked",
                   "design": best, "gains": self.design(best).as_dict(), "yield": None, "why": why}
        return rec

    def format(self) -> str:
        c = self.comparison
        lines = [f"{len(self.scenarios)} scenario models; objective {c['objective'].upper()}, Ms <= {c['ms_max']:g}",
                 f"{'design':<10} {'kp':>9} {'ki':>9} {'max Ms':>7} {'Ms viol.':>8} {'worst':>10} {'mean':>10}"]
        for name, d in c["designs"].items():
            lines.append(f"{name:<10} {d['gains']['kp']:9.4g} {d['gains']['ki']:9.4g} {d['max_ms']:7.3f} "
                         f"{d['ms_violations']:8d} {d['worst_objective']:10.4g} {d['mean_objective']:10.4g}")
        r = self.recommended or self.recommend()
        lines.append(f"recommended: {r['design'] + ' design' if r.get('design') else 'none'} ({r['why']})")
        return "\n".join(lines)


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
