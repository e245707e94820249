"""Figures a control engineer expects: Bode plots of the plant and loop, sensitivity peaks,
load-step responses (nonlinear verification against linear prediction, tuned against
baselines), the tuning landscape, the paper-style gain studies and contact forces.

Every function takes an optional ``ax`` (or ``axes``), returns ``(fig, axes)`` and never calls
``plt.show()``. This module is the only one that imports matplotlib.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import matplotlib
import matplotlib.pyplot as plt
import matplotlib.patheffects
import matplotlib.ticker
import numpy as np

__all__ = [
    "bode_plant",
    "bode_loop",
    "sensitivity_plot",
    "load_step_plot",
    "load_step_comparison",
    "tuning_landscape",
    "gain_study_plot",
    "contact_force_plot",
    "step_response_plot",
    "write_standard_plots",
    "write_design_plots",
    "save_figure",
]

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


def _bode_axes(axes, omega, resp, label, color=None):
    mag = 20 * np.log10(np.abs(resp))
    phase = np.degrees(np.unwrap(np.angle(resp)))
    axes[0].semilogx(omega, mag, label=label, color=color)
    axes[1].semilogx(omega, phase, label=label, color=color)


def bode_plant(sys, omega: np.ndarray | None = None, axes=None):
    """Bode plot of nut speed from motor torque (rad/s per N m) and from axial load
    (rad/s per N) of a linearised plant (:func:`prsa_ctrl.linearize`)."""
    import control

    omega = np.logspace(-1, 5, 600) if omega is None else omega
    fig, axs = _axes(axes, 2, figsize=(7.0, 5.5))
    i_out = sys.output_labels.index("nut_speed")
    for j, (inp, unit) in enumerate((("torque_command", "rad/s per N m"), ("axial_load", "rad/s per N"))):
        k = sys.input_labels.index(inp)
        resp = np.asarray(control.frequency_response(sys[i_out, k], omega).complex).ravel()
        _bode_axes(axs, omega, resp, f"nut speed / {inp.replace('_', ' ')} ({unit})", _COLORS[j])
    axs[0].set_ylabel("magnitude (dB)")
    axs[1].set_ylabel("phase (deg)")
    axs[1].set_xlabel("frequency (rad/s)")
    axs[0].set_title("Linearised plant")
    axs[0].legend(loc="lower left", fontsize=8)
    for a in axs:
        a.grid(True, which="both", alpha=0.3)
    return fig, axs


def bode_loop(omega, loop, margins=None, axes=None, label: str = "L"):
    """Bode plot of the open loop ``L(j omega)`` with gain and phase margins marked."""
    from .metrics import margins_from_response

    m = margins or margins_from_response(omega, loop)
    fig, axs = _axes(axes, 2, figsize=(7.0, 5.5))
    _bode_axes(axs, omega, loop, label)
    axs[0].axhline(0.0, color="k", lw=0.8)
    axs[1].axhline(-180.0, color="k", lw=0.8)
    if math.isfinite(m.pm_deg) and math.isfinite(m.wc_rad_s):
        axs[1].plot([m.wc_rad_s, m.wc_rad_s], [-180.0, -180.0 + m.pm_deg], color="C3", lw=2)
        axs[1].annotate(f"PM {m.pm_deg:.1f} deg", (m.wc_rad_s, -180 + m.pm_deg / 2), xytext=(6, 0),
                        textcoords="offset points", color="C3", fontsize=8, va="center")
    if math.isfinite(m.gm_db):
        phase = np.degrees(np.unwrap(np.angle(loop)))
        i = int(np.argmin(np.abs(phase + 180.0)))
        axs[0].plot([omega[i], omega[i]], [0.0, -m.gm_db], color="C2", lw=2)
        axs[0].annotate(f"GM {m.gm_db:.1f} dB", (omega[i], -m.gm_db / 2), xytext=(6, 0),
                        textcoords="offset points", color="C2", fontsize=8, va="center")
    axs[0].set_ylabel("|L| (dB)")
    axs[1].set_ylabel("phase of L (deg)")
    axs[1].set_xlabel("frequency (rad/s)")
    axs[0].set_title(f"Open loop: Ms {m.ms:.2f}, crossover {m.wc_rad_s:.0f} rad/s")
    for a in axs:
        a.grid(True, which="both", alpha=0.3)
    return fig, axs


def sensitivity_plot(omega, loop, ms_max: float | None = None, ax=None):
    """|S| and |T| (dB) with their peaks Ms, Mt marked (and the Ms bound, if given)."""
    fig, (a,) = _axes(ax)
    s = np.abs(1 / (1 + loop))
    t = np.abs(loop / (1 + loop))
    a.semilogx(omega, 20 * np.log10(s), label="|S|")
    a.semilogx(omega, 20 * np.log10(t), label="|T|")
    for mag, name, c in ((s, "Ms", "C0"), (t, "Mt", "C1")):
        i = int(np.argmax(mag))
        a.plot(omega[i], 20 * np.log10(mag[i]), "o", color=c)
        a.annotate(f"{name} = {mag[i]:.2f}", (omega[i], 20 * np.log10(mag[i])), xytext=(5, 5),
                   textcoords="offset points", color=c, fontsize=8)
    if ms_max:
        a.axhline(20 * np.log10(ms_max), color="C3", ls="--", lw=1, label=f"Ms bound {ms_max:g}")
    a.set_xlabel("frequency (rad/s)")
    a.set_ylabel("magnitude (dB)")
    a.set_title("Sensitivity S and complementary sensitivity T")
    a.grid(True, which="both", alpha=0.3)
    a.legend(fontsize=8)
    return fig, [a]


def _prediction_series(design, scene, k: int = 0):
    """Linear prediction of a design as time (s) and speed (rad/s)."""
    lp_t = scene.step_time + np.arange(-1, len(design.predicted_error[k])) * design.predicted_h
    return lp_t, scene.setpoint_rad_s + np.concatenate([[0.0], -design.predicted_error[k]])


def load_step_plot(design, scene, k: int = 0, ax=None, window: float | None = None):
    """Verified (nonlinear) and predicted (linear) nut speed for one load step, annotated with
    peak drop, recovery time and IAE."""
    fig, (a,) = _axes(ax)
    t, y = design.verified_runs[k]
    a.plot(t, y["nut_speed"], label="verified (nonlinear)", color="C0")
    if getattr(design, "predicted_error", None) is not None:
        tp, yp = _prediction_series(design, scene, k)
        a.plot(tp, yp, "--", label="predicted (linear)", color="C1")
    m = design.verified[k]
    a.axhline(scene.setpoint_rad_s, color="k", lw=0.6)
    tmin = scene.step_time + m.peak_time_s
    a.annotate(f"peak drop {m.peak_drop_rad_s:.2f} rad/s", (tmin, scene.setpoint_rad_s - m.peak_drop_rad_s),
               xytext=(10, -4), textcoords="offset points", fontsize=8)
    txt = f"IAE {m.iae:.4g} rad\nrecovery {m.recovery_time_s * 1e3:.1f} ms" if math.isfinite(m.recovery_time_s) else f"IAE {m.iae:.4g} rad\nno recovery in record"
    a.text(0.98, 0.05, txt, transform=a.transAxes, ha="right", va="bottom", fontsize=8,
           bbox=dict(boxstyle="round", fc="white", alpha=0.8))
    if math.isfinite(m.recovery_time_s):
        a.axvline(scene.step_time + m.recovery_time_s, color="C2", lw=0.8, ls=":")
    span = window or max(6 * max(m.recovery_time_s if math.isfinite(m.recovery_time_s) else 0.0, m.peak_time_s * 4), 0.02)
    a.set_xlim(scene.step_time - 0.1 * span, scene.step_time + span)
    a.set_xlabel("time (s)")
    a.set_ylabel("nut speed (rad/s)")
    a.set_title(f"{design.name}: load {scene.initial_load:g} -> {scene.final_loads[k]:g} N")
    a.grid(True, alpha=0.3)
    a.legend(fontsize=8, loc="upper right")
    return fig, [a]


def load_step_comparison(designs: Sequence, scene, k: int = 0, ax=None, window: float | None = None):
    """Verified load-step responses of several designs (tuned against baselines)."""
    fig, (a,) = _axes(ax)
    worst = 0.0
    for i, d in enumerate(designs):
        t, y = d.verified_runs[k]
        m = d.verified[k]
        a.plot(t, y["nut_speed"], color=_COLORS[i % len(_COLORS)],
               label=f"{d.name} (Ms {d.margins.ms:.2f}, IAE {m.iae:.3g})")
        worst = max(worst, m.recovery_time_s if math.isfinite(m.recovery_time_s) else 0.0)
    a.axhline(scene.setpoint_rad_s, color="k", lw=0.6)
    span = window or min(max(3 * worst, 0.03), scene.duration - scene.step_time)
    a.set_xlim(scene.step_time - 0.05 * span, scene.step_time + span)
    a.set_xlabel("time (s)")
    a.set_ylabel("nut speed (rad/s)")
    a.set_title(f"Load step {scene.initial_load:g} -> {scene.final_loads[k]:g} N (verified, nonlinear)")
    a.grid(True, alpha=0.3)
    a.legend(fontsize=7, loc="lower right")
    return fig, [a]


def tuning_landscape(loop, objective: str, ms_max: float, optimum=None, baselines=(), ax=None, n: int = 40):
    """Objective contours over (kp, ki) for a loop model with the Ms = ms_max boundary, the
    unstable region, the optimum and baselines (``(name, PID)`` pairs) marked."""
    fig, (a,) = _axes(ax, figsize=(7.0, 6.0))
    pts = [optimum] + [p for _, p in baselines] if optimum is not None else [p for _, p in baselines]
    kp0 = np.median([p.kp for p in pts]) if pts else 1.0
    ki0 = np.median([p.ki for p in pts]) if pts else 1.0
    kps = kp0 * np.logspace(-1, math.log10(4), n)
    kis = ki0 * np.logspace(-1.5, 1, n)
    KP, KI = np.meshgrid(kps, kis)
    grid = np.column_stack([KP.ravel(), KI.ravel(), np.zeros(KP.size)])
    n0, ln, d0, ld = loop.parts()
    L = (n0 + grid @ ln) / (d0 + grid @ ld)
    ms = np.max(1 / np.abs(1 + L), axis=1).reshape(KP.shape)
    stable = np.array([loop.is_stable(g) for g in grid]).reshape(KP.shape)
    obj = np.full(KP.shape, np.nan)
    idx = np.flatnonzero(stable.ravel())
    if idx.size:
        obj.ravel()[idx] = loop.objectives(grid[idx], objective)
    cs = a.contourf(KP, KI, np.log10(obj), levels=20, cmap="viridis")
    fig.colorbar(cs, ax=a, label=f"log10 {objective.upper()}")
    halo = [matplotlib.patheffects.withStroke(linewidth=3.5, foreground="k")]
    a.contour(KP, KI, ms, levels=[ms_max], colors="w", linewidths=2).set(path_effects=halo)
    a.contourf(KP, KI, (~stable).astype(float), levels=[0.5, 1.5], colors="none", hatches=["//"])
    a.plot([], [], color="w", lw=2, path_effects=halo, label=f"Ms = {ms_max:g} boundary")
    if optimum is not None:
        a.plot(optimum.kp, optimum.ki, "r*", ms=14, label="optimum")
    for i, (name, p) in enumerate(baselines):
        a.plot(p.kp, p.ki, "o", color=_COLORS[(i + 1) % len(_COLORS)], mec="w", label=name)
    a.set_xscale("log")
    a.set_yscale("log")
    for axis in (a.xaxis, a.yaxis):
        axis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
        axis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        axis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    a.set_xlabel("kp (N m s/rad)")
    a.set_ylabel("ki (N m/rad)")
    a.set_title(f"Tuning landscape: {objective.upper()} (hatched: unstable)")
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


def contact_force_plot(time, outputs: dict, ax=None, window: tuple[float, float] | None = None):
    """Total normal thread-contact forces (N) of the nut-roller and screw-roller interfaces."""
    fig, (a,) = _axes(ax)
    a.plot(time, outputs["contact_force_nut"], label="nut-roller")
    a.plot(time, outputs["contact_force_screw"], "--", label="screw-roller")
    if window:
        a.set_xlim(*window)
    a.set_xlabel("time (s)")
    a.set_ylabel("total normal contact force (N)")
    a.set_title("Thread contact forces over the load step")
    a.grid(True, alpha=0.3)
    a.legend(fontsize=8)
    return fig, [a]


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


def write_standard_plots(report, directory: Path) -> list[Path]:
    """The standard figure set of a tuning report, as PNG and SVG files in ``directory``."""
    from .autotune import _linear_fidelity
    from .linear import linearize

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    sc, best = report.scene, report.best
    files: list[Path] = []
    lp = report.loops[0]
    figs = {
        "plant_bode": bode_plant(linearize(report.plant, sc.setpoint_rad_s, sc.initial_load, _linear_fidelity(sc),
                                           sampled=sc.discrete))[0],
        "loop_bode": bode_loop(lp.omega, lp.loop_response(best.pid.gains), best.margins)[0],
        "sensitivity": sensitivity_plot(lp.omega, lp.loop_response(best.pid.gains), sc.ms_max)[0],
        "load_step": load_step_plot(best, sc)[0],
        "baselines": load_step_comparison([best, *report.baselines], sc)[0],
        "landscape": tuning_landscape(lp, sc.objective, sc.ms_max, best.pid, [(b.name, b.pid) for b in report.baselines])[0],
    }
    if sc.fidelity in ("compliant", "multi-roller"):
        # Contact modes ring at kHz: a continuous run on a fine grid shows them unaliased.
        from .simulation import simulate

        pre = min(sc.step_time, 2e-3)
        r = simulate(report.plant, setpoint=sc.setpoint_rad_s, load=[(0.0, sc.initial_load), (pre, sc.final_loads[0])],
                     duration=pre + 0.03, controller=best.pid, dt=1e-5)
        y = dict(zip(r.output_labels, np.asarray(r.outputs)))
        t = np.asarray(r.time) + sc.step_time - pre
        figs["contact_forces"] = contact_force_plot(t, y)[0]
    for name, fig in figs.items():
        files += save_figure(fig, directory / name)
        plt.close(fig)
    return files


def write_design_plots(plant, scene, pid, directory: Path) -> list[Path]:
    """Bode, sensitivity, load-step and setpoint-step figures for given gains (no tuning)."""
    import control

    from .autotune import Design, _linear_fidelity, _predict, actuator_loops, verify
    from .linear import closed_loop, linearize
    from .scene import choose_fidelity
    from .simulation import simulate

    scene, _ = choose_fidelity(scene)
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    loops = actuator_loops(plant, scene)
    lp = loops[0]
    g = pid.gains
    if not lp.is_stable(g):
        raise ValueError(f"the loop with {pid} is unstable on {plant.name}; expected stabilising gains")
    design = Design("given gains", pid, lp.margins(g))
    _predict(design, loops, plant, scene)
    verify(design, plant, scene)
    sys = linearize(plant, scene.setpoint_rad_s, scene.initial_load, _linear_fidelity(scene), sampled=scene.discrete)
    # Setpoint step of +10 %: nonlinear run and the linear closed loop's prediction.
    w0, dw, t_step, span = scene.setpoint_rad_s, 0.1 * scene.setpoint_rad_s, 0.005, 0.1
    r = simulate(plant, setpoint=[(0.0, w0), (t_step, w0 + dw)], load=scene.initial_load, duration=t_step + span,
                 controller=pid, fidelity=scene.fidelity, discrete=scene.discrete)
    cl = closed_loop(sys, pid)
    tl = np.linspace(0.0, span, 2001)
    lin = control.step_response(cl, T=tl, input=0)
    y_lin = w0 + dw * np.asarray(lin.outputs).reshape(cl.noutputs, -1)[cl.output_labels.index("nut_speed")]
    figs = {
        "plant_bode": bode_plant(sys)[0],
        "loop_bode": bode_loop(lp.omega, lp.loop_response(g), design.margins)[0],
        "sensitivity": sensitivity_plot(lp.omega, lp.loop_response(g), scene.ms_max)[0],
        "load_step": load_step_plot(design, scene)[0],
        "setpoint_step": step_response_plot(
            np.asarray(r.time), np.asarray(r.outputs[0]), tl + t_step, y_lin, setpoint=None,
            title=f"Setpoint step {w0:.2f} -> {w0 + dw:.2f} rad/s",
        )[0],
    }
    files: list[Path] = []
    for name, fig in figs.items():
        files += save_figure(fig, directory / name)
        plt.close(fig)
    return files
