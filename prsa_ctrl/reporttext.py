"""The one home of the toolkit's report text that more than one layer prints: the table cells
and tables (:func:`fmt`, :func:`fmt_margin`, :func:`table`), the robust study's report
(:func:`format_robust`: ``prsa-tune --robust`` and :meth:`prsa_ctrl.tuning.robust.RobustTuning.format`
print the same text) and its yield table (:func:`format_yield_table`, also the design-to-spec
report's). Light: the standard library only; the formatters read their results' attributes and
dicts, they import no result type.

:mod:`prsa_ctrl.studies.scenereport` (the scene kinds' reports) builds on these and re-exports
them under their old names."""

from __future__ import annotations

import math
from typing import Any, Sequence

__all__ = ["fmt", "fmt_margin", "table", "format_robust", "format_yield_table", "SPEC_LABEL"]

#: Spec item -> short label in the yield table (and the recommendation's reasons).
SPEC_LABEL = {"peak_drop_rad_s": "peak drop", "recovery_time_s": "recovery", "ms": "Ms", "mt": "Mt",
              "no_saturation": "saturation", "finite": "unfinished run"}


def fmt(v) -> str:
    """A table cell: ``-`` for None, yes/no, ``never`` for infinity, 4 significant digits."""
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        if math.isinf(v):
            return "never"
        return f"{v:.4g}"
    return str(v)


def fmt_margin(v: float) -> str:
    """A margin: ``none`` (undefined), ``inf`` or 4 significant digits."""
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "none"
    return "inf" if math.isinf(v) else f"{v:.4g}"


def table(header: Sequence[str], rows: Sequence[Sequence]) -> str:
    """A plain-text table with a header rule, cells through :func:`fmt`."""
    cells = [list(header)] + [[fmt(c) for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def format_yield_table(rec: dict[str, Any], objective: str) -> str:
    """The recommendation's table: design, yield with its Wilson 95 % interval, median objective
    and how often each spec item fails (one line per design, ``*`` the recommended one)."""
    rows = rec.get("table") or []
    if not rows:
        return ""
    w = max(len(r["name"]) for r in rows)
    lines = [f"  {'design':<{w}}  {'yield (95 % interval)':<28} {'median ' + objective.upper():>11}  fails (samples)"]
    for r in rows:
        lo, hi = r["yield_ci95"]
        y = f"{100 * r['yield']:.1f} % ({r['passed']}/{r['samples']}) [{100 * lo:.1f}, {100 * hi:.1f}]"
        o = f"{r['objective_p50']:.4g}" if math.isfinite(r["objective_p50"]) else "-"
        f = r["fails"]
        ftxt = "-" if f is None else (", ".join(f"{SPEC_LABEL.get(k, k)} {v}" for k, v in f.items() if v) or "none")
        mark = "*" if r["name"] == rec.get("name") else " "
        lines.append(f"{mark} {r['name']:<{w}}  {y:<28} {o:>11}  {ftxt}")
    return "\n".join(lines)


def format_robust(rr) -> str:
    """Nominal against robust design on the same scenario models."""
    comp = rr.comparison
    obj = comp["objective"].upper()
    out = [f"Robust tuning over {len(rr.scenarios)} scenario models ({comp.get('aggregate', 'worst')} {obj}; "
           f"Ms bound {comp['ms_max']:g} on every model"
           + (", the scene's [spec] ms: the bound the designs are judged by" if comp.get("ms_source") == "[spec] ms"
              else "") + ")"]
    rows = []
    for name, pid in (("nominal", rr.nominal), ("robust", rr.robust)):
        d = comp["designs"][name]
        bad = "unstable" if not d["all_stable"] else None
        rows.append([name, pid.kp, pid.ki, bad or d["max_ms"], d["ms_violations"], bad or d["worst_objective"],
                     bad or d["mean_objective"]])
    out.append(table(["design", "kp", "ki", "max Ms", "models over the Ms bound", f"worst {obj}", f"mean {obj}"], rows))
    unstable = {name: sum(1 for p in comp["designs"][name]["per_scenario"] if not p["stable"])
                for name in ("nominal", "robust")}
    for name, k in unstable.items():
        if k:
            out.append(f"{name}: closed loop unstable on {k} of {len(rr.scenarios)} scenario models")
    r = rr.recommended or rr.recommend()
    if r.get("table"):
        out.append(f"Designs against the scene's [spec] on the same {r['table'][0]['samples']} Monte-Carlo samples "
                   f"(* recommended: {r['rule']}):")
        out.append(format_yield_table(r, comp["objective"]))
        if r.get("decide_table"):
            out.append(f"The designs of (near-)maximal yield again, on {r['decide_table'][0]['samples']} samples of the "
                       "same seed (the decision; * recommended):")
            out.append(format_yield_table({**r, "table": r["decide_table"]}, comp["objective"]))
    name = r.get("name") or (r["design"] + " design" if r.get("design") else None)
    out.append(f"recommended: {name or 'none'} ({r['why']})")
    return "\n".join(out) + "\n"
