"""The text reports of ``prsa-tune`` and ``prsa-plot``: a speed-loop scene's tuning report
(:func:`format_report`), the robust study (:func:`format_robust`), a move scene's cascade report
(:func:`format_move_report`) and the cells and tables they are made of."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Callable, Sequence

from ..options import RAD_S_PER_RPM, rad_s_to_rpm
from ..reporttext import fmt, fmt_margin, format_robust, table  # re-exported (their one home)
from ..sim.metrics import metric_resolution, relative_difference
from ..textsafe import printable
from .kindruns import speed_kind
from .scenefilters import describe_filters

if TYPE_CHECKING:
    from ..plant.plantfile import Plant
    from .movescene import MoveScene
    from ..tuning.cascade import CascadeDesign

__all__ = ["setpoint_table", "profile_tables", "format_report", "format_robust", "format_move_report", "fmt", "fmt_margin", "table", "scene_header",
           "pct_text", "diff_text", "beaten_text", "format_friction_ff"]


def scene_header(sc, overrides: Sequence[str] = ()) -> str:
    """One line saying what a speed-loop scene asks (``overrides``: the flags that changed it)."""
    bounds = f"Ms <= {sc.ms_max:g}" + (f", Mt <= {sc.mt_max:g}" if sc.mt_max is not None else "") + (
        f", Mks <= {sc.mks_max:g} N m s/rad" if sc.mks_max is not None else "")
    name = f"scene {printable(sc.name)}" + (f" with {printable(' '.join(overrides))}" if overrides else "")
    return speed_kind(sc).header(name, bounds)


def pct_text(diff: float) -> str:
    """A signed percentage to 0.1 %; a difference that rounds to zero is "0.0 %", never "-0.0 %".

    >>> pct_text(-0.04), pct_text(0.04), pct_text(-1.25)
    ('0.0 %', '0.0 %', '-1.2 %')
    """
    text = f"{diff:+.1f}"
    return ("0.0" if float(text) == 0.0 else text) + " %"


def diff_text(p, v, res: float = 0.0) -> str:
    """Difference of the prediction ``p`` from the verified value ``v``: the percentage
    ``(p - v) / |v|`` (:func:`prsa_ctrl.sim.metrics.relative_difference`, the one definition the
    warnings use too) where both values reach the metric's resolution ``res``; below it the
    absolute difference ``p - v`` marked "abs." (a percentage of a value at numerical zero
    means nothing); "-" where undefined.

    >>> diff_text(1.776e-15, 3.829e-06, res=0.0365), diff_text(3.67, 3.651, res=0.0365)
    ('-3.83e-06 abs.', '+0.5 %')
    """
    finite = all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in (p, v))
    if not finite:
        return "-"
    d = relative_difference(p, v)
    # A value at numerical zero against the other (1e-9 of it) gives no percentage either,
    # whatever the resolution given (never "-100 %" for 1.4e-14 against 1.4e-4).
    floor = max(res, 1e-9 * max(abs(p), abs(v)))
    if d is not None and abs(p) >= floor and abs(v) >= floor:
        return pct_text(100 * d)
    return f"{p - v:+.3g} abs."


def _finite_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _resolutions(rep, drop: float, window: float) -> Callable[[str], float]:
    """Metric name -> its resolution in the report's verified runs (:func:`prsa_ctrl.sim.metrics.metric_resolution`)."""
    sc = rep.scene
    return lambda name: metric_resolution(name, accuracy=sc.accuracy, drop_rad_s=drop,
                                          sample_time_s=rep.plant.sample_time_s, window_s=window,
                                          torque_limit_n_m=rep.plant.torque_limit)


_DIFF_NOTE = ("difference = (predicted - verified) / |verified|; where either value is below the metric's resolution "
              "(the verification accuracy in its unit: {speed:.3g} rad/s for speeds, one sample for times) the absolute "
              "difference predicted - verified (abs.)")


def beaten_text(c: dict, obj: str) -> str:
    """The verdict of a baseline comparison with its reason when the baseline is not beaten."""
    if c["beaten"]:
        return "yes"
    if c.get("tuned_flags"):
        return "no: tuned design flagged"
    if c["tuned_ms"] > c["baseline_ms"] * (1 + 1e-9):
        return "no: tuned Ms higher"
    if not c["tuned_objective_verified"] < c["baseline_objective_verified"]:
        return f"no: {obj} not lower"
    return "no"


def profile_tables(rep) -> list[str]:
    """Predicted against verified metrics of each duty-cycle record, then its load steps."""
    sc, b = rep.scene, rep.best
    out = []
    fields = [("IAE over the record (rad)", "iae"), ("ITAE (rad s)", "itae"), ("ISE (rad^2/s)", "ise"),
              ("peak error (rad/s)", "peak_deviation_rad_s"), ("peak error time (s)", "peak_time_s"),
              ("RMS error (rad/s)", "rms_error_rad_s"), ("final error (rad/s)", "final_error_rad_s"),
              ("peak torque (N m)", "peak_torque_n_m"), ("time at torque limit", "saturated_fraction")]
    for k, case in enumerate(sc.cases):
        pm, vm = b.predicted[k], b.verified[k]
        res = _resolutions(rep, vm.peak_deviation_rad_s, sc.duration)
        rows = [[lab, getattr(pm, attr), getattr(vm, attr),
                 "-" if attr in ("final_error_rad_s", "saturated_fraction")
                 else diff_text(getattr(pm, attr), getattr(vm, attr), res(attr))]
                for lab, attr in fields]
        out.append(f"Duty cycle, {case} (error = setpoint - speed over the whole record)")
        out.append(table(["metric", "predicted (linear)", "verified (nonlinear)", "difference"], rows))
        out.append(_DIFF_NOTE.format(speed=res("peak_deviation_rad_s")))
        if vm.steps:
            rows = []
            for (t_s, ms_v), ms_p in zip(zip(vm.step_times_s, vm.steps), pm.steps):
                rows.append([f"{t_s:g} s", "up" if ms_v.direction > 0 else "down", ms_p.peak_drop_rad_s,
                             ms_v.peak_drop_rad_s, ms_v.recovery_time_s, ms_v.iae])
            out.append("Load steps in the profile (verified recovery within 5 % of the step's peak, until the next change)")
            out.append(table(["step at", "load", "predicted peak (rad/s)", "verified peak (rad/s)",
                               "recovery (s)", "IAE to next change (rad)"], rows))
        if vm.setpoint_steps:
            out.extend(setpoint_table(pm, vm, res))
        out.append("")
    return out


def setpoint_table(pm, vm, res: Callable[[str], float]) -> list[str]:
    """Setpoint steps of a duty-cycle record: overshoot (%), 10-90 % rise and 2 % settling time,
    predicted (linear) against verified (nonlinear).

    Parameters
    ----------
    pm, vm : ProfileMetrics
        The predicted and the verified metrics of the record (:func:`prsa_ctrl.sim.metrics.profile_metrics`).
    res : callable
        Metric name -> its resolution (s for times), below which a difference is absolute.

    Returns
    -------
    list of str
        The table's lines (a title, then one row per step and quantity).
    """
    rows = []
    pred = dict(zip(pm.setpoint_step_times_s, pm.setpoint_steps))
    for t_s, v in zip(vm.setpoint_step_times_s, vm.setpoint_steps):
        p = pred.get(t_s)
        cells = [("overshoot (%)", "overshoot_percent"), ("rise 10-90 % (s)", "rise_time_s"),
                 ("settling 2 % (s)", "settling_time_s")]
        for lab, attr in cells:
            pv = getattr(p, attr) if p is not None else None
            vv = getattr(v, attr)
            diff = "-" if pv is None or attr == "overshoot_percent" else diff_text(pv, vv, res("recovery_time_s"))
            rows.append([f"{t_s:g} s", f"{rad_s_to_rpm(v.step_rad_s):+.4g} rpm", lab, pv, vv, diff])
    return ["Setpoint steps in the profile (speed response to each step, until the next change)",
            table(["step at", "step", "metric", "predicted (linear)", "verified (nonlinear)", "difference"], rows)]


#: The report line of a linear axis (load coordinates, 1 m of travel per radian).
_LOAD_COORDINATES = ("coordinates: load (position m, force N): read rad as m, rad/s as m/s, N m as N and "
                    "N m s/rad as N s/m (a linear axis moves 1 m per radian)")


def format_report(rep, overrides: Sequence[str] = ()) -> str:
    """Readable text report of an :class:`~prsa_ctrl.studies.autotune.ActuatorTuning`; ``overrides``
    are the command-line flags that changed the scene (named in the header)."""
    sc, b = rep.scene, rep.best
    obj = sc.objective.upper()
    label = b.name[len("tuned "):] if b.name.startswith("tuned ") else f"({b.name})"
    out = [
        f"prsa-tune: plant {printable(rep.plant.name)}, {scene_header(sc, overrides)}",
        f"verification: {rep.fidelity_reason}; {'sampled controller (ZOH, quantised encoder)' if sc.discrete else 'continuous controller'}",
        *([_LOAD_COORDINATES] if rep.plant.mechanism == "linear-axis" else []),
        "",
        f"Tuned {sc.controller.upper()} {label}: kp = {b.pid.kp:.5g} N m s/rad, ki = {b.pid.ki:.5g} N m/rad"
        + (f", kd = {b.pid.kd:.5g} N m s^2/rad (tf {b.pid.tf:g} s)" if b.pid.kd else "")
        + (f", load feed-forward gain kff = {b.pid.kff:.3g}" if sc.feedforward else ""),
        f"Margins: Ms {b.margins.ms:.3f}, Mt {b.margins.mt:.3f}, GM {fmt(b.margins.gm_db)} dB, "
        f"PM {fmt(b.margins.pm_deg)} deg, crossover {fmt(b.margins.wc_rad_s)} rad/s"
        + (f" ({b.margins.wc_rad_s / (2 * math.pi):.4g} Hz)" if _finite_number(b.margins.wc_rad_s) else ""),
        "Drive terms: "
        + (f"sample time {rep.plant.sample_time_s * 1e3:.4g} ms, " if sc.discrete else "continuous controller, ")
        + (f"integral time Ti = kp/ki = {b.pid.kp / b.pid.ki * 1e3:.4g} ms, " if b.pid.ki > 0 else "no integral action, ")
        + f"kp = {b.pid.kp * RAD_S_PER_RPM:.4g} N m/rpm",
        *(f"Filter: {line}" for line in describe_filters(sc.filters, rep.plant.sample_time_s)),
        f"Status: {rep.status}",
        "",
    ]
    fields = [
        ("peak drop (rad/s)", "peak_drop_rad_s"),
        ("peak time (s)", "peak_time_s"),
        ("recovery time (s)", "recovery_time_s"),
        ("IE (rad)", "ie"),
        ("IAE (rad)", "iae"),
        ("ITAE (rad s)", "itae"),
        ("ISE (rad^2/s)", "ise"),
        ("steady-state error (rad/s)", "steady_state_error_rad_s"),
        ("overshoot (rad/s)", "overshoot_rad_s"),
        ("peak torque (N m)", "peak_torque_n_m"),
        ("torque saturated", "saturated"),
    ]
    out.extend(_RECORD_TABLES.get(speed_kind(sc).name, _no_tables)(rep))
    for k, f1 in enumerate(sc.final_loads):
        pm, vm = b.predicted[k], b.verified[k]
        res = _resolutions(rep, vm.peak_drop_rad_s, sc.duration - sc.step_time)
        rows = []
        for lab, attr in fields:
            p, v = getattr(pm, attr), getattr(vm, attr)
            rows.append([lab, p, v, diff_text(p, v, res(attr))])
        out.append(f"Load step {sc.initial_load:g} -> {f1:g} N")
        out.append(table(["metric", "predicted (linear)", "verified (nonlinear)", "difference"], rows))
        out.append(_DIFF_NOTE.format(speed=res("peak_drop_rad_s")))
        out.append("")
    rows = []
    comp = {c["baseline"]: c for c in rep.comparisons}
    for d in rep.baselines:
        c = comp[d.name]
        rows.append([d.name, d.pid.kp, d.pid.ki, d.margins.ms, d.objective_verified,
                     c.get("tuned", "-"), c["tuned_objective_verified"], c["tuned_ms"], beaten_text(c, obj)])
    out.append(f"Baselines ({obj}, verified; each compared with a tuned design at equal or better Ms, named as the "
               "tuner names it)")
    out.append(table(["baseline", "kp", "ki", "Ms", obj, "compared with", f"its {obj}", "its Ms", "beaten"], rows))
    out.append("")
    t = rep.timing_s
    out.append(
        f"Run time: linearise {t['linearize']:.2f} s, tune {t['tune']:.2f} s, verify {t['verify']:.2f} s, "
        f"total {t['total']:.2f} s" + (f" (process {t['process']:.2f} s)" if "process" in t else "")
    )
    if b.estimation:
        e = b.estimation[0]
        out.append(
            f"Speed estimation (verified run): Kalman filter RMS error {e['kf_speed_rms_rad_s']:.4g} rad/s, "
            f"finite difference {e['fd_speed_rms_rad_s']:.4g} rad/s"
        )
    for w in rep.warnings:
        out.append(f"warning: {w}")
    return "\n".join(out)


def format_move_report(plant: "Plant", scene: "MoveScene", designs: "list[CascadeDesign]", prog: str = "prsa-tune") -> str:
    """The text report of a move scene: each design's gains, its true Ms at the four
    loop-breaking points, the verified (nonlinear) metrics and the linear model's.

    Returns
    -------
    str
    """
    w_lin = scene.max_speed_m_s / plant.lead_per_rad
    lines = [f"{prog}: plant {printable(plant.name)}, move scene {printable(scene.name)}: {scene.distance_m * 1e3:g} mm at "
             f"{scene.max_speed_m_s * 1e3:g} mm/s ({scene.profile})"
             + (", out and back" if scene.return_dwell_s is not None else "")
             + (f", load {scene.load_n:g} N throughout, " if scene.load_n == scene.initial_load_n else
                f", load {scene.load_n:g} N at {scene.load_at_s:.4g} s, ") +
             f"hold step {scene.hold_step_n:g} N; Ms <= {scene.ms_max:g} at each loop-breaking point: speed loop "
             "(position loop closed / opened), position loop, torque command (both loops broken at the plant input)"]
    if plant.mechanism == "linear-axis":
        lines.append(_LOAD_COORDINATES)
    ts = plant.sample_time_s
    if scene.position_rate > 1:  # issue 34: the position loop at the drive's rate
        lines.append(f"  position loop every {scene.position_rate} speed-loop samples (Tp = {scene.position_rate * ts * 1e6:g} us "
                     f"over Ts = {ts * 1e6:g} us), modelled as the sampled multi-rate loop: the position loop's Ms at "
                     "its own rate, the speed loop (position loop closed) and torque command's as the peak gain of "
                     "the periodic loop's sensitivity")
    if getattr(scene, "position_delay_samples", 0):
        d = scene.position_delay_samples
        lines.append(f"  position loop's own computation delay: {d} position-loop sample(s) "
                     f"({d * scene.position_rate * ts * 1e6:g} us), in the loop model, the tuning, the nonlinear "
                     "runs and the exports")
    if scene.kv_max_per_s is not None:
        lines.append(f"  position gain ceiling kv_max = {scene.kv_max_per_s:.6g} 1/s "
                     f"({scene.kv_max_per_s * 0.06:.4g} (m/min)/mm); Kv of each design: "
                     + ", ".join(f"{d.method} {d.position.kv * 0.06:.4g} (m/min)/mm" for d in designs))
    if scene.filters:
        lines.append("  fixed loop filters (tuned around, verified and exported): "
                     + "; ".join(f"{lf.filter.__class__.__name__} at {lf.filter.characteristic_hz:g} Hz on the "
                                 f"{lf.place.replace('_', ' ')}" for lf in scene.filters))
    for d in designs:
        v = d.verified
        ki = f", ki {d.position.ki:.4g} 1/s^2" if scene.position_controller == "pi" or d.position.ki > 0 else ""
        lines.append(
            f"  {d.method:10s} kp {d.speed.kp:.4g} N m s/rad, ki {d.speed.ki:.4g} N m/rad, Kv {d.position.kv:.4g} 1/s"
            f"{ki}, kvff {d.position.kvff:.3g}, kaff {d.position.kaff:.3g}; Ms speed(closed/open) "
            f"{d.ms_points['speed_closed']:.3f}/{d.ms_points['speed_open']:.3f}, position {d.ms_points['position']:.3f}, torque command "
            f"{d.ms_points['torque']:.3f}")
        if v is not None:
            lines.append(
                f"  {'':10s} verified ({scene.fidelity}): following error peak {v.peak_following_error_m * 1e6:.3f} um, "
                f"RMS {v.rms_following_error_m * 1e6:.3f} um; holding deviation {v.holding_deviation_m * 1e6:.3f} um; "
                f"settling {v.settling_time_s * 1e3:.2f} ms; overshoot {v.overshoot_m * 1e6:.3f} um; peak torque "
                f"{v.peak_torque_n_m:.3f} N m; hunting {'YES' if v.hunting['oscillating'] else 'no'}")
        lin = d.linear
        ratio = (f" ({lin['holding_deviation_m'] / v.holding_deviation_m:.2g} x the verified)"
                 if v is not None and v.holding_deviation_m > 0 else "")
        lines.append(
            f"  {'':10s} linear model the tuner optimises (linearised at the cruise speed {w_lin:.4g} rad/s, "
            f"{scene.load_n:g} N): following error peak {lin['peak_following_error_m'] * 1e6:.3f} um, RMS "
            f"{lin['rms_following_error_m'] * 1e6:.3f} um; holding deviation {lin['holding_deviation_m'] * 1e6:.3f} um"
            f"{ratio}: at rest the nut sticks, which the linearisation at speed does not see; the verified "
            "numbers are the truth")
        if v is not None and v.screw_final_error_m is not None and scene.measured == "nut_angle":
            lines.append(f"  {'':10s} screw (load side, not seen by the nut encoder): holding "
                         f"deviation {v.screw_holding_deviation_m * 1e6:.3f} um, final error "
                         f"{v.screw_final_error_m * 1e6:.3f} um")
    for d in designs:
        lines += [f"  note ({d.method}): {n}" for n in d.notes]
    return "\n".join(lines)


def format_friction_ff(effect: dict, fidelity: str) -> str:
    """The friction feed-forward lines of a move report (``prsa-tune --friction-ff``): the curve
    and the verified following error of the joint design without and with it.

    Parameters
    ----------
    effect : dict
        :func:`prsa_ctrl.studies.move.friction_feedforward_effect`.
    fidelity : str
        Model of the verification runs.

    Returns
    -------
    str
    """
    ff, a, b = effect["feedforward"], effect["without"], effect["with"]
    lines = [f"  friction feed-forward ({ff['source']}): Coulomb +{ff['coulomb_positive_n_m']:.4g} / "
             f"-{ff['coulomb_negative_n_m']:.4g} N m, Stribeck +{ff['stribeck_positive_n_m']:.4g} / "
             f"-{ff['stribeck_negative_n_m']:.4g} N m over {ff['stribeck_speed_rad_s']:.4g} rad/s, viscous "
             f"{ff['viscous_positive_n_m_s_per_rad']:.4g} / {ff['viscous_negative_n_m_s_per_rad']:.4g} N m s/rad, "
             f"gain {ff['gain']:g}"]
    for what, key, ratio in (("RMS", "rms_following_error_m", effect["rms_ratio"]),
                             ("peak", "peak_following_error_m", effect["peak_ratio"])):
        change = f" ({ratio:.3g} x)" if ratio is not None else ""
        lines.append(f"  {'':10s} joint design verified ({fidelity}): following error {what} {a[key] * 1e6:.3f} um "
                     f"without, {b[key] * 1e6:.3f} um with{change}")
    return "\n".join(lines)


def _no_tables(rep) -> list[str]:
    return []


#: The tables of a kind's records besides the load steps' (kind name -> tables of a report).
_RECORD_TABLES = {"duty-cycle": profile_tables}
