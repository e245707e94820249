"""The one home of the toolkit's report text: the table cells and tables (:func:`fmt`,
:func:`fmt_margin`, :func:`table`, :func:`format_rows`), the robust study's report
(:func:`format_robust`: ``prsa-tune --robust`` and :meth:`prsa_ctrl.tuning.robust.RobustTuning.format`
print the same text) and its yield table (:func:`format_yield_table`, also the design-to-spec
report's), the Monte-Carlo report (:func:`format_monte_carlo`,
:meth:`~prsa_ctrl.studies.montecarlo.MonteCarloReport.format`), the design-to-spec report
(:func:`format_design_to_spec`, :meth:`~prsa_ctrl.studies.designspec.DesignToSpec.format`) and
``prsa-pid``'s report (:func:`format_pid_report`). Light: the standard library only; the
formatters read their results' attributes and dicts, they import no result type. The modules
that had these formatters re-export them under their old names.

:mod:`prsa_ctrl.studies.scenereport` (the scene kinds' reports) builds on these and re-exports
them under their old names."""

from __future__ import annotations

import math
from typing import Any, Sequence

__all__ = ["fmt", "fmt_margin", "table", "format_robust", "format_yield_table", "SPEC_LABEL", "format_monte_carlo",
           "format_design_to_spec", "format_pid_report", "format_rows", "axis_replay_line", "axis_fit_lines",
           "axis_validation_lines", "axis_verdict_lines"]

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


def format_monte_carlo(report) -> str:
    """The Monte-Carlo report (:class:`prsa_ctrl.studies.montecarlo.MonteCarloReport`) as plain
    text: yield with its Wilson 95 % interval, percentiles and the worst sample of each design."""
    head = (f"Monte Carlo: {report.n_done}/{report.n} samples, seed {report.seed}, backend {report.backend} "
            f"({report.workers} worker{'s' if report.workers != 1 else ''}), {report.wall_time_s:.1f} s"
            + ("" if report.complete else "  ** INTERRUPTED: partial results **"))
    lines = [head]
    spec = ", ".join(f"{k} <= {v:g}" if k != "no_saturation" else f"no_saturation = {str(v).lower()}"
                     for k, v in report.spec.items())
    lines.append(f"spec: {spec or '(none: yield counts finished simulations)'}")
    ig = report.integration or {}
    if ig.get("integrator"):
        what = f"{ig.get('path', 'per-sample')} {ig['integrator']}" + (
            f", {ig['substeps']} steps per controller sample" if ig.get("substeps") else "")
        if ig.get("relative") is not None:
            where = (f"on {len(ig['check_samples'])} check samples against the adaptive reference"
                     if ig.get("check_samples") is not None else "at the one-off check points")
            what += f"; measured error {ig['relative']:.2g} of the deviation {where}, accuracy {ig['accuracy']:g}"
        elif ig.get("reason"):
            what += f" ({ig['reason']})"
        lines.append(f"integration: {what}")
    joint = [k for k, e in report.uncertainty.items() if "correlation" in e]  # prsa_ctrl.plant.uncertainty
    if joint:
        lines.append(f"drawn jointly (Gaussian copula of the [uncertainty] correlation): {', '.join(joint)}")
    lines += [f"note: {n}" for n in dict.fromkeys(e["correlation_note"] for e in report.uncertainty.values()
                                                 if "correlation_note" in e)]
    for d in report.designs:
        lo, hi = d.ci95
        lines.append(f"  {d.name}: yield {100 * d.yield_:.1f} % ({d.passed}/{d.n}), 95 % CI [{100 * lo:.1f}, "
                     f"{100 * hi:.1f}] %" + (f", {d.failures} simulation failures" if d.failures else ""))
        for met in ("peak_drop_rad_s", "recovery_time_s", "iae", "peak_torque_n_m", "ms"):
            if met in d.percentiles:
                p = d.percentiles[met]
                lines.append(f"    {met:<17} p5 {p['p5']:.4g}  p50 {p['p50']:.4g}  p95 {p['p95']:.4g}  max {p['max']:.4g}")
        if d.worst_index is not None:
            vals = ", ".join(f"{k} = {v:.4g}" for k, v in d.worst_values.items())
            lines.append(f"    worst sample #{d.worst_index}: {vals}")
            lines.append(f"    replay: {d.replay}")
    return "\n".join(lines)


def format_design_to_spec(dts, objective: str) -> str:
    """The design-to-spec report (``prsa-tune --design-to-spec``): the designs on the common search
    samples with their yields, what was not evaluated, the linear-yield grid, the decision run and the
    chosen design's yield on fresh samples (:class:`prsa_ctrl.studies.designspec.DesignToSpec`)."""
    s = dts.search
    n = s["rows"][0]["samples"] if s.get("rows") else 0
    lines = [f"Design to the spec: {len(dts.designs)} designs on the same {n} search samples (seed "
             f"{dts.search_seed}); * chosen: {s.get('rule', '')}", format_yield_table(
                 {"table": s.get("rows"), "name": dts.chosen}, objective)]
    lines += [f"  not evaluated: {n_} ({w})" for n_, w in dts.skipped]
    if dts.grid:
        g = dts.grid
        lines.append(f"  linear-yield grid: {g['points']} gains on the {g['samples']} search samples' own linear "
                     f"models, best linear yield {100 * g['best_linear_yield']:.1f} %; proposed: "
                     + ", ".join(g["proposed"]))
    d = dts.decide
    if d:
        nd = d["rows"][0]["samples"] if d.get("rows") else 0
        lines.append(f"Decision among the {len(d.get('rows', []))} designs of (near-)maximal screen yield on "
                     f"{nd} samples of the same seed {dts.search_seed} (* chosen):")
        lines.append(format_yield_table({"table": d.get("rows"), "name": dts.chosen}, objective))
    fy = dts.final_yield
    if fy is None:
        lines.append(f"chosen: none ({s.get('why', '')})")
    else:
        lo, hi = fy.ci95
        lines.append(f"chosen: {dts.chosen}: yield {100 * fy.yield_:.1f} % ({fy.passed}/{fy.n}), 95 % CI "
                     f"[{100 * lo:.1f}, {100 * hi:.1f}] % on {fy.n} fresh samples (seed {dts.final_seed}, not "
                     "used by the search)")
        lim = (dts.decide or s).get("limit")
        if lim:
            lines.append(f"the target yield {100 * (dts.decide or s)['target']:.1f} % is not reached on the "
                         f"{'decision' if dts.decide else 'search'} samples: the limit is {lim['text']}")
    return "\n".join(lines)


def _pid_num(x, unit: str = "") -> str:
    """A prsa-pid number: ``none``, ``inf`` or 6 significant digits with its unit."""
    if x is None:
        return "none"
    if isinstance(x, float) and not math.isfinite(x):
        return "inf"
    return f"{x:.6g}" + (f" {unit}" if unit else "")


def format_pid_report(data: dict) -> str:
    """The text report of ``prsa-pid`` from :func:`prsa_ctrl.cli.pid.result_data`."""
    pl, c, st, ob, mg = data["plant"], data["controller"], data["standard"], data["objective"], data["margins"]
    opt = data["options"]
    lines = [f"plant       P(s) = {pl['text']}" + (f" * exp(-{pl['delay_s']:g} s)" if pl["delay_s"] else ""),
             f"            num {pl['num']}  den {pl['den']}  (load: {pl['load']})",
             f"problem     min {ob['kind'].upper()}  s.t.  Ms <= {opt['ms_max']:g}"
             + (f", Mt <= {opt['mt_max']:g}" if opt["mt_max"] is not None else "")
             + (f", Mks <= {opt['mks_max']:g}" if opt["mks_max"] is not None else "")
             + (f", kp + kd/tf <= {opt['max_noise_gain']:g}" if opt["max_noise_gain"] is not None else ""),
             f"controller  {opt['controller'].upper()}, derivative {c['derivative']}"
             + (f", filter order {c['filter_order']}" if c["filter_order"] else ", no measurement filter"),
             f"  parallel  kp = {_pid_num(c['kp'])}   ki = {_pid_num(c['ki'])} 1/s   kd = {_pid_num(c['kd'])} s",
             f"  standard  K = {_pid_num(st['K'])}   Ti = {_pid_num(st['Ti_s'], 's')}   Td = {_pid_num(st['Td_s'], 's')}"
             + (f"   N = {_pid_num(st['N'])}" if "N" in st else "")]
    if c["tf_s"] is not None:
        lines.append(f"  derivative filter  tf = {_pid_num(c['tf_s'], 's')}  (kd s/(tf s + 1))")
    if c["filter_order"]:
        search = (data.get("stats") or {}).get("filter_search") or {}
        rng = search.get("range_s")
        how = "given" if opt["filter_tf_s"] is not None else (
            f"optimised over Tf in [{rng[0]:.4g}, {rng[1]:.4g}] s" if rng else "optimised")
        lines.append(f"  measurement filter F = " + ("1/(Tf s + 1)" if c["filter_order"] == 1 else
                                                      "1/(Tf^2 s^2/2 + Tf s + 1)")
                     + f", Tf = {_pid_num(c['filter_tf_s'], 's')} ({how})")
    if data["setpoint"]:
        sp = data["setpoint"]
        lines.append(f"  setpoint weights b = {sp['b']:.4g}, c = {sp['c']:.4g}: setpoint-step IAE {sp['iae']:.6g} "
                     f"(b = c = 1: {sp['iae_unweighted']:.6g}), overshoot {100 * sp['overshoot']:.3g} %")
    lines += [f"objective   {ob['kind'].upper()} = {_pid_num(ob['value'])}",
              f"            {ob['evaluation']}",
              f"peaks       Ms = {_pid_num(data['ms'])}   Mt = {_pid_num(data['mt'])}   Mks = {_pid_num(data['mks'])}  (true peaks"
              + (", exact delay)" if pl["delay_s"] else ")"),
              f"margins     GM = {_pid_num(mg['gm_db'], 'dB') if math.isfinite(mg['gm_db']) else 'inf (no phase crossover)'}   PM = {_pid_num(mg['pm_deg'], 'deg')}   crossover "
              f"{_pid_num(mg['wc_rad_s'], 'rad/s')} = {_pid_num(mg['wc_hz'], 'Hz')}",
              f"status      {data['status']}"]
    lines += [f"warning     {w}" for w in data["warnings"]]
    return "\n".join(lines)


def format_rows(rows: Sequence[dict[str, object]], floatfmt: str = "{:.4g}") -> str:
    """Plain-text table of dict rows (same keys in every row).

    Parameters
    ----------
    rows : sequence of dict
    floatfmt : str
        Format of float cells.

    Examples
    --------
    >>> print(format_rows([{"a": 1.23456, "b": "x"}]))
    a      b
    1.235  x
    """
    if not rows:
        return ""
    keys = list(rows[0])
    cells = [[k for k in keys]] + [
        [floatfmt.format(r[k]) if isinstance(r[k], float) else str(r[k]) for k in keys] for r in rows
    ]
    widths = [max(len(c[i]) for c in cells) for i in range(len(keys))]
    return "\n".join("  ".join(c[i].ljust(widths[i]) for i in range(len(keys))).rstrip() for c in cells)


def axis_replay_line(rep: dict[str, Any], prefix: str = "") -> str:
    """One linear-axis replay (:meth:`prsa_ctrl.identification.axis.AxisReplay.as_dict`): its
    errors and fit (%) and how it was replayed."""
    e, f = rep["errors_percent"], rep["fit_percent"]
    return (f"{prefix}{rep['log']}: replay errors position {e['position']:.4g} %, velocity {e['velocity']:.4g} %, "
            f"force {e['force']:.4g} % (fit {f['position']:.3f} / {f['velocity']:.3f} / {f['force']:.3f} %; "
            f"{rep['replay']})")


def axis_fit_lines(report: dict[str, Any]) -> list[str]:
    """The linear-axis fit's report text (``prsa-fit --mechanism linear-axis``) from its JSON report
    (:meth:`prsa_ctrl.identification.axis.AxisFit.as_dict` with ``friction_map``, optional
    ``holdout`` and the base plant's notes among the ``warnings``): the load-side equivalents with
    their intervals, each replay, each held-out replay, each log's friction map, the warnings and
    the coordinates."""
    lines = []
    for k, v in report["equivalent"].items():
        lo, hi = v["ci95"]
        lines.append(f"{k} = {v['value']:.6g} {v['unit']} (95 % CI {lo:.6g}..{hi:.6g})")
    cd = report.get("command_delay")
    if cd is not None:  # (identification.delay.axis_delay_record)
        lines.append(f"command delay: {cd['drive_command_delay_samples']} sample(s) ({cd['how']}; {cd['status']})")
    lines += [axis_replay_line(r) for r in report["replay"]]
    lines += [axis_replay_line(h, prefix="held out: ") for h in report.get("holdout", {}).get("replay", [])]
    for log_name, fmap in report["friction_map"].items():
        pars = fmap.get("parameters", {})
        lines.append(f"friction map of {log_name} (report; the replay model stays Coulomb + viscous): "
                     + ", ".join(f"{k} = {v['value']:.4g} {v['unit']} (95 % CI {v['ci95'][0]:.4g}..{v['ci95'][1]:.4g})"
                                 for k, v in pars.items() if v["value"] is not None)
                     + f"; Stribeck {fmap.get('stribeck')}" + (f"; {fmap['error']}" if "error" in fmap else ""))
    lines += [f"warning: {w}" for w in report["warnings"]]
    lines.append(f"coordinates: {report['coordinates']}")
    return lines


def axis_verdict_lines(validation: dict[str, Any]) -> list[str]:
    """The two-mass linear-axis fit's validation text
    (:func:`prsa_ctrl.identification.axiscompliant.fit_two_mass_axis`'s ``validation``): the
    verdict, then per log (and per log left out) its replay fit %, error and noise floor (m/s)."""
    def row(name: str, e: dict[str, Any], what: str) -> str:
        if "failed" in e:
            return f"{what}{name}: the fit on the other logs failed ({e['failed']})"
        ratio = e["error_rms_m_s"] / max(e["noise_floor_m_s"], 1e-300)
        return (f"{what}{name}: replayed at {e['fit_percent']:.2f} % (error {e['error_rms_m_s']:.3g} m/s, {ratio:.3g} x "
                f"its noise floor {e['noise_floor_m_s']:.3g} m/s){'' if e['explained'] else ': not explained'}")
    head = ("validated: the plant as written explains every log (closed-loop replay from the reference)"
            if validation["passes"] else f"not validated: {validation['reasons'][0]}")
    lines = [head, *(row(n, e, "replay of ") for n, e in validation["written_plant"].items())]
    lines += [row(n, e, "left out: ") for n, e in (validation.get("cross_validation") or {}).items()]
    return lines


def axis_validation_lines(replays: Sequence[tuple[dict[str, Any], bool]], coordinates: str) -> list[str]:
    """The linear-axis validation's report text (``prsa-fit --validate``): per ``(replay dict,
    closed_loop)`` its line and, for an open-loop replay, why; then the coordinates."""
    lines = []
    for rep, closed_loop in replays:
        lines.append(axis_replay_line(rep))
        if not closed_loop:
            lines.append(f"note: {rep['log']} has no controller description: replayed open loop from the logged "
                         "command (an integrating axis drifts)")
    lines.append(f"coordinates: {coordinates}")
    return lines
