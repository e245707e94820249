"""Figures a control engineer expects: Bode plots of the plant and loop, sensitivity peaks,
load-step responses (nonlinear verification against linear prediction, tuned against
baselines), the tuning landscape, the paper-style gain studies and contact forces.

Every function takes an optional ``ax`` (or ``axes``), returns ``(fig, axes)`` and never calls
``plt.show()``. Figures draw result objects: the numbers they show are computed in
:mod:`prsa_ctrl.studies` (:class:`~prsa_ctrl.studies.responses.FigureData`); the writers that take
a plant or a report get that record from :func:`~prsa_ctrl.studies.responses.design_responses` /
:func:`~prsa_ctrl.studies.responses.report_responses` first. Only :mod:`prsa_ctrl.plots` imports
matplotlib.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Callable, NamedTuple, Sequence

import matplotlib
import matplotlib.pyplot as plt
import matplotlib.patches
import matplotlib.patheffects
import matplotlib.ticker
import numpy as np

from .._lazy import module
from ..options import DEFAULT_FREQUENCY_UNIT, FREQUENCY_UNITS, rad_s_to_rpm
from ..sim.metrics import margins_from_response
from ..studies.scenekinds import problem
from ..studies.responses import (FigureData, Landscape, binding_level, design_responses, duty_input, landscape,
                                 objective_value, report_responses, stable_design_responses)

control = module("control")

__all__ = [
    "design_figures",
    "draw_design_figures",
    "draw_report_figures",
    "bode_plant",
    "bode_loop",
    "sensitivity_plot",
    "load_step_plot",
    "load_step_comparison",
    "duty_cycle_plot",
    "duty_cycle_comparison",
    "baseline_pairs_plot",
    "duty_cycle_pairs_plot",
    "binding_level",
    "tuning_landscape",
    "gain_study_plot",
    "contact_force_plot",
    "step_response_plot",
    "write_standard_plots",
    "write_design_plots",
    "save_figure",
    "FREQUENCY_UNITS",
    "DEFAULT_FREQUENCY_UNIT",
]



def _unit_factor(unit: str) -> float:
    """Factor from rad/s to ``unit`` (:data:`prsa_ctrl.options.FREQUENCY_UNITS`; the axes, the
    crossover and peak labels and the Nyquist mark are drawn in it); ValueError naming it otherwise."""
    if unit not in FREQUENCY_UNITS:
        raise ValueError(f"frequency unit {unit!r}; expected one of {', '.join(FREQUENCY_UNITS)}")
    return FREQUENCY_UNITS[unit]

_COLORS = plt.rcParams["axes.prop_cycle"].by_key()["color"]


def _axes(ax, n: int = 1, sharex: bool = True, figsize=(7.0, 4.5)):
    if ax is not None:
        axes = list(ax) if isinstance(ax, (list, tuple, np.ndarray)) else [ax]
        return axes[0].figure, axes
    fig, axs = plt.subplots(n, 1, sharex=sharex, figsize=figsize, layout="constrained")
    return fig, list(np.atleast_1d(axs))


def save_figure(fig, path: Path) -> list[Path]:
    """Save ``fig`` as PNG (150 dpi) and SVG next to each other; returns both paths."""
    path = Path(path)
    out = []
    for ext in ("png", "svg"):
        p = path.with_suffix(f".{ext}")
        fig.savefig(p, dpi=150)
        out.append(p)
    return out


def _op_text(op) -> str:
    """``"300 rpm, 1000 N"`` from an operating point (``omega_nut`` rad/s, ``load`` N)."""
    if op is None:
        return ""
    if isinstance(op, str):
        return op
    return f"{rad_s_to_rpm(op.omega_nut):.0f} rpm, {op.load:g} N"


def _nyquist(axes, sample_time_s: float | None, unit: str = DEFAULT_FREQUENCY_UNIT) -> None:
    """Mark the Nyquist frequency (``pi/Ts`` rad/s, ``1/(2 Ts)`` Hz) of a sampled loop on every axis."""
    if not sample_time_s:
        return
    wn = math.pi / sample_time_s * _unit_factor(unit)
    text = "pi/Ts" if unit == "rad/s" else "1/(2 Ts)"
    for i, a in enumerate(axes):
        a.axvline(wn, color="0.35", ls="-.", lw=1.0, label=f"Nyquist {text} = {wn:.0f} {unit}" if i == 0 else None)


def _bode_axes(axes, omega, resp, label, color=None, unit: str = DEFAULT_FREQUENCY_UNIT):
    mag = 20 * np.log10(np.abs(resp))
    phase = np.degrees(np.unwrap(np.angle(resp)))
    f = np.asarray(omega, float) * _unit_factor(unit)
    axes[0].semilogx(f, mag, label=label, color=color)
    axes[1].semilogx(f, phase, label=label, color=color)


def bode_plant(sys, omega: np.ndarray | None = None, axes=None, sample_time_s: float | None = None,
               frequency_unit: str = DEFAULT_FREQUENCY_UNIT):
    """Bode plot of nut speed from torque command (rad/s per N m) and from axial load
    (rad/s per N) of a linearised plant (:func:`prsa_ctrl.linearize`).

    Parameters
    ----------
    sys : control.StateSpace
        Linearised plant; its ``operating_point`` (if present) is named in the title.
    omega : array, rad/s, optional
        Frequency grid (default 0.1 .. 1e5 rad/s).
    axes : two matplotlib axes, optional
    sample_time_s : float, s, optional
        Controller sample time of a sampled loop: the Nyquist frequency ``pi/Ts`` is marked.
    frequency_unit : {"Hz", "rad/s"}
        Unit of the frequency axis (:data:`~prsa_ctrl.options.FREQUENCY_UNITS`; the grid ``omega`` is in rad/s
        either way).
    """
    _unit_factor(frequency_unit)
    omega = np.logspace(-1, 5, 600) if omega is None else omega
    fig, axs = _axes(axes, 2, figsize=(7.0, 5.5))
    i_out = sys.output_labels.index("nut_speed")
    for j, (inp, unit) in enumerate((("torque_command", "rad/s per N m"), ("axial_load", "rad/s per N"))):
        k = sys.input_labels.index(inp)
        resp = np.asarray(control.frequency_response(sys[i_out, k], omega).complex).ravel()
        _bode_axes(axs, omega, resp, f"nut speed / {inp.replace('_', ' ')} ({unit})", _COLORS[j], frequency_unit)
    _nyquist(axs, sample_time_s, frequency_unit)
    axs[0].set_ylabel("magnitude (dB)")
    axs[1].set_ylabel("phase (deg)")
    axs[1].set_xlabel(f"frequency ({frequency_unit})")
    op = _op_text(getattr(sys, "operating_point", None))
    axs[0].set_title("Linearised plant" + (f" at {op}" if op else ""))
    axs[0].legend(loc="lower left", fontsize=8)
    for a in axs:
        a.grid(True, which="both", alpha=0.3)
    return fig, axs


def bode_loop(omega, loop, margins=None, axes=None, label: str = "L", operating_point=None,
              sample_time_s: float | None = None, frequency_unit: str = DEFAULT_FREQUENCY_UNIT):
    """Bode plot of the open loop ``L(j omega)`` with gain and phase margins marked.

    Parameters
    ----------
    omega : array, rad/s
    loop : complex array
        ``L(j omega)``.
    margins : Margins, optional
        Computed from ``loop`` if not given.
    operating_point : str or OperatingPoint, optional
        Named in the title (``"300 rpm, 1000 N"``).
    sample_time_s : float, s, optional
        Marks the Nyquist frequency ``pi/Ts`` of a sampled loop.
    frequency_unit : {"Hz", "rad/s"}
        Unit of the frequency axis and of the crossover in the labels (:data:`~prsa_ctrl.options.FREQUENCY_UNITS`;
        ``omega`` is in rad/s either way).
    """
    k = _unit_factor(frequency_unit)
    m = margins or margins_from_response(omega, loop)
    fig, axs = _axes(axes, 2, figsize=(7.0, 5.5))
    _bode_axes(axs, omega, loop, label, unit=frequency_unit)
    wc = m.wc_rad_s * k
    axs[0].axhline(0.0, color="k", lw=0.8)
    axs[1].axhline(-180.0, color="k", lw=0.8)
    # Labels sit on the far side of the reference line from the curve, so they never cross it.
    if math.isfinite(m.pm_deg) and math.isfinite(m.wc_rad_s):
        axs[1].plot([wc, wc], [-180.0, -180.0 + m.pm_deg], color="C3", lw=2)
        axs[1].annotate(f"PM {m.pm_deg:.1f} deg at {wc:.0f} {frequency_unit}", (wc, -180.0), xytext=(0, -6),
                        textcoords="offset points", color="C3", fontsize=8, ha="center", va="top")
    if math.isfinite(m.gm_db):
        phase = np.degrees(np.unwrap(np.angle(loop)))
        i = int(np.argmin(np.abs(phase + 180.0)))
        axs[0].plot([omega[i] * k, omega[i] * k], [0.0, -m.gm_db], color="C2", lw=2)
        axs[0].annotate(f"GM {m.gm_db:.1f} dB", (omega[i] * k, 0.0), xytext=(0, 5),
                        textcoords="offset points", color="C2", fontsize=8, ha="center", va="bottom")
    _nyquist(axs, sample_time_s, frequency_unit)
    if sample_time_s:
        axs[0].legend(loc="lower left", fontsize=8)
    axs[0].set_ylabel("|L| (dB)")
    axs[1].set_ylabel("phase of L (deg)")
    axs[1].set_xlabel(f"frequency ({frequency_unit})")
    op = _op_text(operating_point)
    axs[0].set_title(f"Open loop{' at ' + op if op else ''}\nMs {m.ms:.2f}, crossover {wc:.0f} {frequency_unit}",
                     fontsize=10)
    for a in axs:
        a.grid(True, which="both", alpha=0.3)
    return fig, axs


def sensitivity_plot(omega, loop, ms_max: float | None = None, ax=None, mt_max: float | None = None,
                     sample_time_s: float | None = None, frequency_unit: str = DEFAULT_FREQUENCY_UNIT):
    """|S| and |T| (absolute, log scale) with their peaks Ms, Mt and the bounds on the same scale.

    The peak values are named in the legend (never on the curves); the y-range runs from 0.01
    to above the highest peak or bound so the peaks are always visible. ``omega`` in rad/s; the
    frequency axis and the labels in ``frequency_unit`` (:data:`~prsa_ctrl.options.FREQUENCY_UNITS`).
    """
    f = np.asarray(omega, float) * _unit_factor(frequency_unit)
    fig, (a,) = _axes(ax)
    s = np.abs(1 / (1 + loop))
    t = np.abs(loop / (1 + loop))
    top = 1.0
    for mag, name, sym, c, bound in ((s, "Ms", "S", "C0", ms_max), (t, "Mt", "T", "C1", mt_max)):
        i = int(np.argmax(mag))
        a.loglog(f, mag, color=c, label=f"|{sym}|: {name} = {mag[i]:.3f} at {f[i]:.0f} {frequency_unit}")
        a.plot(f[i], mag[i], "o", color=c)
        top = max(top, mag[i])
        if bound:
            a.axhline(bound, color=c, ls="--", lw=1, label=f"{name} bound {bound:g}")
            top = max(top, bound)
    _nyquist([a], sample_time_s, frequency_unit)
    a.set_ylim(1e-2, top * 1.6)
    a.set_xlabel(f"frequency ({frequency_unit})")
    a.set_ylabel("magnitude (absolute)")
    a.set_title("Sensitivity S and complementary sensitivity T")
    a.grid(True, which="both", alpha=0.3)
    a.legend(fontsize=8, loc="lower left")
    return fig, [a]


def _prediction_series(design, scene, k: int = 0):
    """Linear prediction of a design as time (s) and speed (rad/s)."""
    lp_t = scene.step_time + np.arange(-1, len(design.predicted_error[k])) * design.predicted_h
    start = getattr(design, "predicted_start_speed", math.nan)
    start = start if math.isfinite(start) else scene.setpoint_rad_s
    return lp_t, start + np.concatenate([[0.0], -design.predicted_error[k]])


def _design_label(d, objective: str, k: int | None = 0, scene=None) -> str:
    """``name: Ms 1.40, IAE 0.0265`` (objective of level ``k``, or the aggregate when None)."""
    val = d.objective_verified if k is None else objective_value(d.verified[k], objective)
    unit = _OBJ_UNITS.get(objective, "")
    flagged = ", FLAGGED" if getattr(d, "flags", None) else ""  # failed a health check (autotune.health_flags)
    return f"{d.name}: Ms {d.margins.ms:.2f}, {objective.upper()} {val:.3g}{unit}{flagged}"


_OBJ_UNITS = {"ie": " rad", "iae": " rad", "itae": " rad s", "ise": " rad^2/s"}


def _window(runs_t, metrics, step_time: float, window: float | None, floor: float = 0.02):
    """x-range fitted to the data: from the first sample (at most a tenth of the span before the
    step) to a few recovery times after it, never past the end of the record."""
    rec = [m.recovery_time_s for m in metrics if math.isfinite(m.recovery_time_s)]
    slow = [m.peak_time_s for m in metrics]
    span = window or max(4.0 * max(rec, default=0.0), 8.0 * max(slow, default=0.0), floor)
    t0 = max(min(float(t[0]) for t in runs_t), step_time - 0.1 * span)
    t1 = min(max(float(t[-1]) for t in runs_t), step_time + span)
    return t0, t1


def load_step_plot(design, scene, k: int | None = 0, ax=None, window: float | None = None, torque: bool = True,
                   torque_limit: float | None = None):
    """Verified (nonlinear) and predicted (linear) nut speed after a load step, annotated with
    peak deviation, recovery time and the scene's objective, with the actual motor torque in a
    panel below.

    Parameters
    ----------
    design : Design
        Verified design (:func:`prsa_ctrl.studies.autotune.verify`).
    scene : Scene
    k : int or None
        Load level to show; ``None`` shows every level of the scene, the binding one (largest
        objective) highlighted with its prediction.
    ax : axes, optional
        One axis (speed only) or two (speed, torque).
    window : float, s, optional
        Time shown after the step (default: fitted to the recovery).
    torque : bool
        Draw the torque panel (when the axes are created here).
    torque_limit : float, N m, optional
        Command saturation, drawn in the torque panel when it is within the plotted range.

    Returns
    -------
    fig, [speed axis] or [speed axis, torque axis]
    """
    if ax is None:
        fig, axs = plt.subplots(2 if torque else 1, 1, sharex=True, figsize=(7.0, 6.0 if torque else 4.5),
                                height_ratios=[2.2, 1] if torque else None, layout="constrained")
        axs = list(np.atleast_1d(axs))
    else:
        fig, axs = _axes(ax)
    a = axs[0]
    at = axs[1] if len(axs) > 1 else None
    obj = scene.objective
    levels = list(range(len(design.verified))) if k is None else [k]
    kb = binding_level(design, scene) if k is None else k
    many = len(levels) > 1
    w0 = scene.setpoint_rad_s
    for j in levels:
        t, y = design.verified_runs[j]
        bind = j == kb
        c = "C0" if bind else plt.cm.Greys(0.35 + 0.4 * j / max(len(levels) - 1, 1))
        tag = f" {scene.final_loads[j]:g} N" + (" (binding)" if bind and many else "")
        a.plot(t, y["nut_speed"], color=c, lw=1.8 if bind else 1.0, zorder=3 if bind else 2,
               label=f"verified (nonlinear){tag if many else ''}")
        if at is not None and "motor_torque" in y:
            at.plot(t, y["motor_torque"], color=c, lw=1.5 if bind else 0.9,
                    label=f"motor torque (actual){tag if many else ''}")
    if getattr(design, "predicted_error", None):
        tp, yp = _prediction_series(design, scene, kb)
        a.plot(tp, yp, "--", label="predicted (linear)" + (f" {scene.final_loads[kb]:g} N" if many else ""),
               color="C1", zorder=4)
    m = design.verified[kb]
    a.axhline(w0, color="k", lw=0.6, label="setpoint")
    t_b, y_b = design.verified_runs[kb]
    i_pk = int(np.argmax(np.abs(y_b["nut_speed"] - w0) * (t_b >= scene.step_time)))
    a.plot(t_b[i_pk], y_b["nut_speed"][i_pk], "v" if y_b["nut_speed"][i_pk] < w0 else "^", color="C3",
           label=f"peak deviation {m.peak_drop_rad_s:.3g} rad/s")
    if math.isfinite(m.recovery_time_s):
        a.axvline(scene.step_time + m.recovery_time_s, color="C2", lw=0.8, ls=":",
                  label=f"recovered after {m.recovery_time_s * 1e3:.1f} ms")
    # Metrics box on the side away from the excursion, with room made for it.
    below = y_b["nut_speed"][i_pk] < w0
    lines = [f"{obj.upper()} {objective_value(m, obj):.4g}{_OBJ_UNITS.get(obj, '')}",
             f"peak time {m.peak_time_s * 1e3:.1f} ms",
             f"recovery {m.recovery_time_s * 1e3:.1f} ms" if math.isfinite(m.recovery_time_s) else "no recovery in record"]
    a.text(0.98, 0.04 if below else 0.96, "\n".join(lines), transform=a.transAxes, ha="right",
           va="bottom" if below else "top", fontsize=8, bbox=dict(boxstyle="round", fc="white", alpha=0.9))
    t0, t1 = _window([design.verified_runs[j][0] for j in levels], [design.verified[j] for j in levels],
                     scene.step_time, window)
    a.set_xlim(t0, t1)
    ys = np.concatenate([design.verified_runs[j][1]["nut_speed"] for j in levels])
    lo, hi = float(ys.min()), float(ys.max())
    pad = max(hi - lo, 1e-9)
    a.set_ylim(lo - (0.6 if below else 0.08) * pad, hi + (0.08 if below else 0.6) * pad)
    a.set_ylabel("nut speed (rad/s)")
    loads = "/".join(f"{scene.final_loads[j]:g}" for j in levels)
    a.set_title(f"{design.name}: load {scene.initial_load:g} -> {loads} N"
                + (f"\nbinding level {scene.final_loads[kb]:g} N (largest {obj.upper()}) highlighted" if many else "")
                + "".join(f"\nFLAGGED: {f}" for f in getattr(design, "flags", None) or []),
                fontsize=10, color="C3" if getattr(design, "flags", None) else "k")
    a.grid(True, alpha=0.3)
    a.legend(fontsize=7, loc="lower left" if below else "upper left", ncol=2)
    if at is not None:
        # Colours as in the speed panel (no second legend to cover the curves).
        at.set_ylabel("actual motor\ntorque (N m)")
        at.set_xlabel("time (s)")
        at.grid(True, alpha=0.3)
        lo_t, hi_t = at.get_ylim()
        if torque_limit and torque_limit < hi_t + 0.5 * (hi_t - lo_t):
            at.axhline(torque_limit, color="C3", lw=0.8, ls="--", label=f"torque limit {torque_limit:g} N m")
            at.text(0.99, torque_limit, f"torque limit {torque_limit:g} N m", transform=at.get_yaxis_transform(),
                    ha="right", va="bottom", fontsize=7, color="C3")
    else:
        a.set_xlabel("time (s)")
    return fig, axs


def duty_cycle_plot(design, scene, k: int = 0, torque_limit: float | None = None):
    """A duty-cycle record: the profile (load or setpoint) on top, the speed error ``setpoint -
    speed`` verified (nonlinear) and predicted (linear) in the middle, the motor torque below.

    Parameters
    ----------
    design : Design
        Verified and predicted (:func:`prsa_ctrl.studies.autotune.verify`, :func:`~prsa_ctrl.studies.autotune.predict`).
    scene : Scene
        A duty-cycle scene (:class:`~prsa_ctrl.studies.scenekinds.DutyCycle`).
    k : int
        Record to show (index into ``scene.cases``).
    torque_limit : float, N m, optional
        Drawn in the torque panel when within the plotted range.

    Returns
    -------
    fig, [profile axis, error axis, torque axis]
    """
    case = scene.cases[k]
    fig, axs = plt.subplots(3, 1, sharex=True, figsize=(7.0, 6.5), height_ratios=[1.0, 2.0, 1.2],
                            layout="constrained")
    t, y = design.verified_runs[k]
    prof, label = duty_input(scene, case, t)
    axs[0].plot(t, prof, color="k", lw=1.0)
    axs[0].set_ylabel(label)
    err = y["setpoint"] - y["nut_speed"]
    m = design.verified[k]
    obj = scene.objective
    axs[1].plot(t, err, color="C0", lw=1.0,
                label=f"verified (nonlinear): {obj.upper()} {objective_value(m, obj):.3g}{_OBJ_UNITS.get(obj, '')}")
    if design.predicted_error:
        e_p = design.predicted_error[k]
        axs[1].plot(t[: e_p.size], e_p, "--", color="C1", lw=1.0,
                    label=f"predicted (linear): {obj.upper()} {objective_value(design.predicted[k], obj):.3g}"
                          f"{_OBJ_UNITS.get(obj, '')}")
    axs[1].axhline(0.0, color="k", lw=0.5)
    axs[1].plot([m.peak_time_s + t[0]], [m.peak_deviation_rad_s], "o", color="C3", ms=4,
                label=f"peak error {m.peak_deviation_rad_s:.3g} rad/s")
    axs[1].set_ylabel("speed error (rad/s)")
    axs[1].legend(fontsize=7, loc="best")
    axs[2].plot(t, y["motor_torque"], color="C2", lw=1.0)
    if torque_limit is not None and np.max(np.abs(y["motor_torque"])) > 0.8 * torque_limit:
        axs[2].axhline(torque_limit, color="C3", ls="--", lw=0.8)
    axs[2].set_ylabel("motor torque (N m)")
    axs[2].set_xlabel("time (s)")
    axs[2].set_xlim(float(t[0]), float(t[-1]))
    for a in axs:
        a.grid(True, alpha=0.3)
    axs[0].set_title(f"{design.name}: {case} ({scene.name}), Ms {design.margins.ms:.2f}"
                     + (", FLAGGED" if getattr(design, "flags", None) else ""), fontsize=10)
    return fig, list(axs)


def duty_cycle_comparison(designs: Sequence, scene, k: int = 0, ax=None):
    """Verified speed errors of several designs over a duty-cycle record, each labelled with
    its Ms and the scene's objective."""
    fig, (a,) = _axes(ax)
    for i, d in enumerate(designs):
        t, y = d.verified_runs[k]
        a.plot(t, y["setpoint"] - y["nut_speed"], color=_COLORS[i % len(_COLORS)], lw=0.9,
               label=_design_label(d, scene.objective, k))
    a.axhline(0.0, color="k", lw=0.5)
    a.set_xlabel("time (s)")
    a.set_ylabel("speed error (rad/s)")
    a.set_xlim(float(designs[0].verified_runs[k][0][0]), float(designs[0].verified_runs[k][0][-1]))
    a.set_title(f"{scene.cases[k].capitalize()} of {scene.name} (verified, nonlinear)")
    a.grid(True, alpha=0.3)
    a.legend(fontsize=7, loc="best")
    return fig, [a]


def load_step_comparison(designs: Sequence, scene, k: int = 0, ax=None, window: float | None = None):
    """Verified load-step responses of several designs, each labelled with its Ms and the
    scene's objective (draw designs of equal Ms together: see :func:`baseline_pairs_plot`)."""
    fig, (a,) = _axes(ax)
    for i, d in enumerate(designs):
        t, y = d.verified_runs[k]
        a.plot(t, y["nut_speed"], color=_COLORS[i % len(_COLORS)], label=_design_label(d, scene.objective, k))
    a.axhline(scene.setpoint_rad_s, color="k", lw=0.6)
    a.set_xlim(*_window([d.verified_runs[k][0] for d in designs], [d.verified[k] for d in designs],
                        scene.step_time, window, floor=0.03))
    a.set_xlabel("time (s)")
    a.set_ylabel("nut speed (rad/s)")
    a.set_title(f"Load step {scene.initial_load:g} -> {scene.final_loads[k]:g} N (verified, nonlinear)")
    a.grid(True, alpha=0.3)
    a.legend(fontsize=7, loc="lower right")
    return fig, [a]


def _pair_panels(n: int, axes=None):
    """``n`` panels for the baseline/tuned pair plots: a new figure with two columns (the unused
    last panel hidden), or the given axes."""
    if axes is not None:
        return _axes(axes)
    cols = 2 if n > 1 else 1
    rows = math.ceil(n / cols)
    fig, axs = plt.subplots(rows, cols, figsize=(5.2 * cols, 3.4 * rows), layout="constrained", squeeze=False)
    axs = list(axs.ravel())
    for extra in axs[n:]:
        extra.set_visible(False)
    return fig, axs


def _finish_pair_panel(a, title: str, ylabel: str, legend_loc: str) -> None:
    """Title, axis labels, grid and legend of one baseline/tuned pair panel."""
    a.set_title(title, fontsize=9)
    a.set_xlabel("time (s)")
    a.set_ylabel(ylabel)
    a.grid(True, alpha=0.3)
    a.legend(fontsize=7, loc=legend_loc)


def _pairs_suptitle(fig, scene, where: str) -> None:
    """The pair figures' title (``where``: e.g. " on the <scene> duty cycle")."""
    mt = getattr(scene, "mt_max", None)
    fig.suptitle(f"Baselines against the tuned design at equal or lower Ms{where}"
                 + (f" (tuned designs also keep Mt <= {mt:g})" if mt else "") + "; verified, nonlinear", fontsize=10)


def baseline_pairs_plot(pairs: Sequence[tuple], scene, k: int | None = None, axes=None):
    """Each baseline beside the tuned design at the same (or lower) Ms: one panel per
    ``(baseline, tuned)`` pair of verified designs, so that a baseline at a higher Ms is never
    compared with the tuned design at the scene's bound.

    Parameters
    ----------
    pairs : sequence of (Design, Design)
        Baseline and its equal-Ms tuned comparison (``ActuatorTuning.comparisons``).
    scene : Scene
    k : int or None
        Load level; ``None``: the binding level of each tuned design.
    """
    n = len(pairs)
    fig, axs = _pair_panels(n, axes)
    obj = scene.objective
    for a, (b, d) in zip(axs, pairs):
        kk = binding_level(d, scene) if k is None else k
        for des, c, ls in ((b, "C7", "-"), (d, "C0", "-")):
            t, y = des.verified_runs[kk]
            a.plot(t, y["nut_speed"], color=c, ls=ls, lw=1.6, label=_design_label(des, obj, kk))
        a.axhline(scene.setpoint_rad_s, color="k", lw=0.6)
        a.set_xlim(*_window([b.verified_runs[kk][0], d.verified_runs[kk][0]], [b.verified[kk], d.verified[kk]],
                            scene.step_time, None, floor=0.03))
        _finish_pair_panel(a, f"vs {b.name}: Ms {b.margins.ms:.2f}, load {scene.initial_load:g} -> "
                              f"{scene.final_loads[kk]:g} N", "nut speed (rad/s)", "lower right")
    if axes is None:
        _pairs_suptitle(fig, scene, "")
    return fig, axs[:n]


def duty_cycle_pairs_plot(pairs: Sequence[tuple], scene, k: int | None = None, axes=None):
    """The duty-cycle form of :func:`baseline_pairs_plot`: each baseline beside the tuned
    design at the same (or lower) Ms, one panel per ``(baseline, tuned)`` pair, showing the
    verified speed error ``setpoint - speed`` over the record (labels: Ms and the scene's
    objective), so that a baseline at a higher Ms is never compared with the tuned design at
    the scene's bound.

    Parameters
    ----------
    pairs : sequence of (Design, Design)
        Baseline and its equal-Ms tuned comparison (``ActuatorTuning.comparisons``), verified
        on the duty cycle.
    scene : Scene
        A duty-cycle scene (:class:`~prsa_ctrl.studies.scenekinds.DutyCycle`).
    k : int or None
        Record (index into ``scene.cases``); ``None``: the binding record of each tuned design.

    Returns
    -------
    fig, list of axes (one per pair)
    """
    n = len(pairs)
    fig, axs = _pair_panels(n, axes)
    obj = scene.objective
    for a, (b, d) in zip(axs, pairs):
        kk = binding_level(d, scene) if k is None else k
        for des, c in ((b, "C7"), (d, "C0")):
            t, y = des.verified_runs[kk]
            a.plot(t, y["setpoint"] - y["nut_speed"], color=c, lw=1.2, label=_design_label(des, obj, kk))
        a.axhline(0.0, color="k", lw=0.5)
        t0 = b.verified_runs[kk][0]
        a.set_xlim(float(t0[0]), float(t0[-1]))
        _finish_pair_panel(a, f"vs {b.name}: Ms {b.margins.ms:.2f}, {scene.cases[kk]}", "speed error (rad/s)", "best")
    if axes is None:
        _pairs_suptitle(fig, scene, f" on the {scene.name} duty cycle")
    return fig, axs[:n]


def tuning_landscape(loop, objective: str, ms_max: float, optimum=None, baselines=(), ax=None, n: int = 40,
                     mt_max: float | None = None, aggregate: str = "sum"):
    """Objective contours over (kp, ki) for a loop model with the Ms = ms_max boundary (and
    Mt = mt_max when given), the unstable region, the optimum and baselines (``(name, PID)``
    pairs) marked.

    ``loop`` is a :class:`~prsa_ctrl.studies.responses.Landscape` (drawn as it is), or a loop
    model or a list of them (one per load level), evaluated by
    :func:`~prsa_ctrl.studies.responses.landscape` around the optimum and baselines: the
    objective is then their ``aggregate`` ("sum" or "worst") and Ms, Mt the largest over the
    levels, as the tuner sees them. Grid points where any level is unstable are left out of the
    coloured contours, so the hatched background shows through exactly there (the contours stop
    at the last grid cell with all four corners stable).
    """
    land = loop if isinstance(loop, Landscape) else landscape(
        loop, objective, ([optimum] if optimum is not None else []) + [p for _, p in baselines], n, aggregate)
    fig, (a,) = _axes(ax, figsize=(7.0, 6.0))
    KP, KI = np.meshgrid(land.kp, land.ki)
    kps, kis, obj, ms, mt, stable = land.kp, land.ki, land.objective, land.ms, land.mt, land.stable
    # Unstable background: hatched grey behind the contours.
    a.add_patch(matplotlib.patches.Rectangle((0, 0), 1, 1, transform=a.transAxes, facecolor="0.88",
                                             edgecolor="0.5", hatch="//", lw=0, zorder=0))
    cs = a.contourf(KP, KI, np.log10(obj), levels=20, cmap="viridis", zorder=1)
    what = (objective.upper() if land.levels == 1
            else f"{land.aggregate} of {objective.upper()} over {land.levels} levels")
    fig.colorbar(cs, ax=a, label=f"log10 {what}")
    halo = [matplotlib.patheffects.withStroke(linewidth=3.5, foreground="k")]
    ms_c = np.where(stable.reshape(KP.shape), ms, np.nan)
    a.contour(KP, KI, ms_c, levels=[ms_max], colors="w", linewidths=2, zorder=2).set(path_effects=halo)
    a.plot([], [], color="w", lw=2, path_effects=halo, label=f"Ms = {ms_max:g} boundary")
    if mt_max:
        mt_c = np.where(stable.reshape(KP.shape), mt, np.nan)
        a.contour(KP, KI, mt_c, levels=[mt_max], colors="C1", linewidths=2, linestyles="--", zorder=2)
        a.plot([], [], color="C1", lw=2, ls="--", label=f"Mt = {mt_max:g} boundary")
    if optimum is not None:
        a.plot(optimum.kp, optimum.ki, "r*", ms=14, label="optimum", zorder=5)
    for i, (name, p) in enumerate(baselines):
        a.plot(p.kp, p.ki, "o", color=_COLORS[(i + 1) % len(_COLORS)], mec="w", label=name, zorder=5)
    a.set_xscale("log")
    a.set_yscale("log")
    a.set_xlim(kps[0], kps[-1])
    a.set_ylim(kis[0], kis[-1])
    for axis in (a.xaxis, a.yaxis):
        axis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
        axis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        axis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    a.set_xlabel("kp (N m s/rad)")
    a.set_ylabel("ki (N m/rad)")
    a.set_title(f"Tuning landscape: {objective.upper()} (hatched grey: unstable)")
    a.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=3, frameon=False)
    return fig, [a]


def gain_study_plot(runs: Sequence[tuple[str, np.ndarray, np.ndarray]], setpoint: float, title: str, ax=None,
                    window: tuple[float, float] | None = None):
    """Paper-style gain study: several ``(label, time s, nut speed rad/s)`` responses."""
    fig, (a,) = _axes(ax)
    for i, (label, t, w) in enumerate(runs):
        a.plot(t, w, color=plt.cm.viridis(i / max(len(runs) - 1, 1)), label=label)
    a.axhline(setpoint, color="k", lw=0.6)
    if window:
        a.set_xlim(*window)
    a.set_xlabel("time (s)")
    a.set_ylabel("nut speed (rad/s)")
    a.set_title(title)
    a.grid(True, alpha=0.3)
    a.legend(fontsize=8)
    return fig, [a]


def contact_force_plot(time, outputs: dict, ax=None, window: tuple[float, float] | None = None,
                       static: tuple[float, float] | None = None):
    """Total normal thread-contact forces (N) of the nut-roller and screw-roller interfaces.

    The two forces differ by well under 1 % (the helix angles barely change
    ``F/(cos beta cos lambda)``), so with the axes created here a second panel shows their
    difference, nut minus screw, which is what tells the interfaces apart.

    Parameters
    ----------
    time : array, s
    outputs : dict
        ``contact_force_nut`` and ``contact_force_screw`` arrays (N).
    ax : axes, optional
        One axis (forces only) or two (forces, difference).
    window : (float, float), s, optional
    static : (float, float), N, optional
        Static (mean) normal force of the nut and screw interfaces after the step, drawn as
        dotted lines (e.g. ``load * plant.normal_force_factor()``); default: the mean of each
        force over the last quarter of the record.
    """
    if ax is None:
        fig, axs = plt.subplots(2, 1, sharex=True, figsize=(7.0, 5.5), height_ratios=[2, 1], layout="constrained")
        axs = list(axs)
    else:
        fig, axs = _axes(ax)
    a = axs[0]
    time = np.asarray(time)
    f_n = np.asarray(outputs["contact_force_nut"])
    f_s = np.asarray(outputs["contact_force_screw"])
    if static is None:
        late = time >= time[0] + 0.75 * (time[-1] - time[0])
        static = (float(f_n[late].mean()), float(f_s[late].mean()))
        how = "mean of last quarter"
    else:
        how = "static"
    a.plot(time, f_n, color="C0", lw=1.4, label="nut-roller")
    a.plot(time, f_s, color="C1", lw=1.0, ls="--", label="screw-roller")
    a.axhline(static[0], color="C0", ls=":", lw=1.2, label=f"nut {how} {static[0]:.1f} N")
    a.axhline(static[1], color="C1", ls=":", lw=1.2, label=f"screw {how} {static[1]:.1f} N")
    a.set_ylabel("total normal contact force (N)")
    a.set_title("Thread contact forces over the load step")
    a.grid(True, alpha=0.3)
    a.legend(fontsize=8, loc="lower right", ncol=2)
    if len(axs) > 1:
        axs[1].plot(time, f_n - f_s, color="C2", label="nut - screw")
        axs[1].axhline(static[0] - static[1], color="C2", ls=":", lw=1.2,
                       label=f"{how} difference {static[0] - static[1]:.2f} N")
        axs[1].set_ylabel("difference (N)")
        axs[1].grid(True, alpha=0.3)
        axs[1].legend(fontsize=8, loc="lower right")
    axs[-1].set_xlabel("time (s)")
    if window:
        a.set_xlim(*window)
    else:
        a.set_xlim(time[0], time[-1])
    return fig, axs


def step_response_plot(time, nonlinear, linear_time=None, linear=None, setpoint=None, ax=None,
                       title: str = "Setpoint step response"):
    """Nut speed after a setpoint step: nonlinear simulation and, if given, linear prediction."""
    fig, (a,) = _axes(ax)
    a.plot(time, nonlinear, label="nonlinear")
    if linear is not None:
        a.plot(linear_time, linear, "--", label="linear")
    if setpoint is not None:
        a.axhline(setpoint, color="k", lw=0.6, label="setpoint")
    a.set_xlabel("time (s)")
    a.set_ylabel("nut speed (rad/s)")
    a.set_title(title)
    a.grid(True, alpha=0.3)
    a.legend(fontsize=8)
    return fig, [a]


def _mid_load_text(scene, k: int) -> str:
    return problem(scene).operating_text(k)


def _save_all(figs: dict, directory: Path) -> list[Path]:
    """Save every figure as PNG and SVG into ``directory`` (created) and close it."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    files: list[Path] = []
    for name, fig in figs.items():
        files += save_figure(fig, directory / name)
        plt.close(fig)
    return files


def _frequency_figures(data: FigureData, unit: str = DEFAULT_FREQUENCY_UNIT) -> dict:
    """Plant Bode, loop Bode and sensitivity figures of a :class:`FigureData`, frequency axes in ``unit``."""
    sc, ts = data.scene, data.sample_time_s
    figs = {
        "plant_bode": bode_plant(data.plant_linear, sample_time_s=ts, frequency_unit=unit)[0],
        "loop_bode": bode_loop(data.omega, data.loop, data.margins, operating_point=_mid_load_text(sc, data.level),
                               sample_time_s=ts, frequency_unit=unit)[0],
        "sensitivity": sensitivity_plot(data.omega, data.loop, sc.ms_max, mt_max=sc.mt_max, sample_time_s=ts,
                                        frequency_unit=unit)[0],
    }
    figs["sensitivity"].axes[0].set_title(f"S and T at {_mid_load_text(sc, data.level)}", fontsize=10)
    return figs


def _time_figures(data: FigureData, k: int | None) -> dict:
    """The verified design's duty-cycle records, or its load step(s) (``k``: level, None all)."""
    return _panel(data, "time_figures")(data, k)


def _step_time_figures(data: FigureData, k: int | None) -> dict:
    return {"load_step": load_step_plot(data.design, data.scene, k=k, torque_limit=data.plant.torque_limit)[0]}


def _duty_time_figures(data: FigureData, k: int | None) -> dict:
    sc, d = data.scene, data.design
    return {"duty_cycle" + ("" if len(sc.cases) == 1 else "_" + case.split()[0]):
            duty_cycle_plot(d, sc, i, torque_limit=data.plant.torque_limit)[0] for i, case in enumerate(sc.cases)}


def _baselines_figure(data: FigureData) -> object:
    """The baselines against the tuned designs at equal Ms (the pairs), or all on one axis."""
    pairs, sc = list(data.pairs), data.scene
    return (_panel(data, "pairs")(pairs, sc)[0] if pairs
            else _panel(data, "comparison")([data.design, *data.baselines], sc, k=data.level)[0])


def draw_report_figures(data: FigureData, frequency_unit: str = DEFAULT_FREQUENCY_UNIT) -> dict:
    """The standard figure set of a tuning report (see :func:`write_standard_plots`), drawn from
    :func:`~prsa_ctrl.studies.responses.report_responses`, frequency axes in ``frequency_unit``
    (:data:`~prsa_ctrl.options.FREQUENCY_UNITS`); figure name -> Figure."""
    sc, best = data.scene, data.design
    figs = _frequency_figures(data, frequency_unit)
    figs["landscape"] = tuning_landscape(data.landscape, sc.objective, sc.ms_max, best.pid,
                                         [(b.name, b.pid) for b in data.baselines], mt_max=sc.mt_max)[0]
    figs.update(_time_figures(data, None if len(sc.final_loads) > 1 else 0))
    figs["baselines"] = _baselines_figure(data)
    if data.contact is not None:
        c = data.contact
        fig, axs = contact_force_plot(c.time_s, c.outputs, static=c.static_n)
        axs[0].set_title(f"Thread contact forces, load {sc.initial_load:g} -> {c.final_load_n:g} N at "
                         f"{rad_s_to_rpm(sc.setpoint_rad_s):.0f} rpm")
        figs["contact_forces"] = fig
    return figs


def write_standard_plots(report, directory: Path, frequency_unit: str = DEFAULT_FREQUENCY_UNIT) -> list[Path]:
    """The standard figure set of a tuning report, as PNG and SVG files in ``directory``.

    Parameters
    ----------
    report : ActuatorTuning or FigureData
        A report is turned into its :class:`~prsa_ctrl.studies.responses.FigureData` by
        :func:`~prsa_ctrl.studies.responses.report_responses` first.
    directory : Path
        Created if missing.
    frequency_unit : {"Hz", "rad/s"}
        Unit of the Bode and sensitivity frequency axes (:data:`~prsa_ctrl.options.FREQUENCY_UNITS`).

    Files: ``plant_bode``, ``loop_bode``, ``sensitivity`` (at the binding load level),
    ``load_step`` (every load level, binding one highlighted, torque below), ``baselines`` (each
    baseline beside the tuned design at equal or lower Ms), ``landscape`` (objective over
    kp-ki with the Ms and, if set, Mt boundaries) and, for compliant models, ``contact_forces``.
    A duty-cycle scene gets ``duty_cycle`` (``duty_cycle_load`` / ``duty_cycle_setpoint`` for a
    mix) instead of ``load_step``, and ``baselines`` as the verified errors over its record, each
    baseline beside the tuned design at equal or lower Ms (:func:`duty_cycle_pairs_plot`).
    """
    _unit_factor(frequency_unit)  # before any work
    data = report if isinstance(report, FigureData) else report_responses(report)
    return _save_all(draw_report_figures(data, frequency_unit), directory)


def draw_design_figures(data: FigureData, frequency_unit: str = DEFAULT_FREQUENCY_UNIT) -> dict:
    """Bode, sensitivity, load-step and setpoint-step figures of given gains, drawn from
    :func:`~prsa_ctrl.studies.responses.design_responses`, frequency axes in ``frequency_unit``
    (:data:`~prsa_ctrl.options.FREQUENCY_UNITS`); figure name -> Figure.

    Marginal and unstable loops are drawn with a red warning title; an unstable one gets the
    frequency plots only (its time responses diverge).
    """
    sc, pid = data.scene, data.design.pid
    figs = _frequency_figures(data, frequency_unit)
    label = {"marginal": "marginally stable closed loop", "unstable": "UNSTABLE closed loop"}.get(data.stability)
    if label:
        for fig in figs.values():
            fig.suptitle(f"{label}: kp = {pid.kp:g}, ki = {pid.ki:g}, kd = {pid.kd:g}", color="tab:red", fontsize=10)
    if data.stability == "unstable" or data.setpoint_step is None:
        return figs
    figs.update(_time_figures(data, None if len(sc.final_loads) > 1 else 0))
    st = data.setpoint_step
    figs["setpoint_step"] = step_response_plot(
        st.time_s, st.speed_rad_s, st.linear_time_s, st.linear_speed_rad_s, setpoint=None,
        title=f"Setpoint step {st.from_rad_s:.2f} -> {st.to_rad_s:.2f} rad/s at {st.load_n:g} N"
              + (f" ({label})" if label else ""),
    )[0]
    return figs


def design_figures(plant, scene=None, pid=None, stability: str | None = None, loops=None,
                   frequency_unit: str = DEFAULT_FREQUENCY_UNIT) -> dict:
    """Bode, sensitivity, load-step and setpoint-step figures for given gains (no tuning).

    Parameters
    ----------
    plant : Plant or FigureData
        A :class:`~prsa_ctrl.studies.responses.FigureData` is drawn as it is; a plant (with
        ``scene``, ``pid`` and optionally ``stability``, ``loops``) is first turned into one by
        :func:`~prsa_ctrl.studies.responses.design_responses`.
    scene : Scene
    pid : PID
    stability : {"stable", "marginal", "unstable"}, optional
        The loop's class (default: from the loop model).
    loops : list of LoopModel, optional
        The scene's loop models (default :func:`prsa_ctrl.studies.autotune.actuator_loops`).
    frequency_unit : {"Hz", "rad/s"}
        Unit of the Bode and sensitivity frequency axes (:data:`~prsa_ctrl.options.FREQUENCY_UNITS`).

    Returns
    -------
    dict
        Figure name -> matplotlib Figure.
    """
    _unit_factor(frequency_unit)  # before any work
    data = plant if isinstance(plant, FigureData) else design_responses(plant, scene, pid, stability, loops)
    return draw_design_figures(data, frequency_unit)


def write_design_plots(plant, scene, pid, directory: Path, frequency_unit: str = DEFAULT_FREQUENCY_UNIT) -> list[Path]:
    """:func:`design_figures` of stabilising gains
    (:func:`~prsa_ctrl.studies.responses.stable_design_responses`), saved as PNG and SVG into
    ``directory``.

    Parameters
    ----------
    plant, scene, pid
        As :func:`design_figures`.
    directory : Path
        Created if missing.
    frequency_unit : {"Hz", "rad/s"}
        Unit of the Bode and sensitivity frequency axes (:data:`~prsa_ctrl.options.FREQUENCY_UNITS`).

    Raises
    ------
    ValueError
        If the gains do not stabilise the loop.
    """
    _unit_factor(frequency_unit)  # before any work
    return _save_all(draw_design_figures(stable_design_responses(plant, scene, pid), frequency_unit), directory)


class _Panels(NamedTuple):
    """A scene kind's time-response figures (:attr:`~prsa_ctrl.studies.kindruns.StepRuns.plot_panels`),
    by the names of this module's functions (looked up when drawn)."""

    time_figures: str  #: (FigureData, level or None) -> {name: Figure}
    pairs: str  #: the baselines against their equal-Ms tuned designs
    comparison: str  #: every design on one axis


#: Figure set per kind (``problem(scene).plot_panels``): load steps or a duty cycle's records.
PANELS = {"load-step": _Panels("_step_time_figures", "baseline_pairs_plot", "load_step_comparison"),
          "duty-cycle": _Panels("_duty_time_figures", "duty_cycle_pairs_plot", "duty_cycle_comparison")}


def _panel(data: FigureData, role: str) -> Callable:
    """The function drawing ``role`` (a field of :class:`_Panels`) for the kind of ``data.scene``."""
    return globals()[getattr(PANELS[problem(data.scene).plot_panels], role)]
