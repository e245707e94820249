"""Figures of a fit (:class:`prsa_ctrl.identification.common.FitResult`): per time-domain record
the measured and simulated nut speed with the residual, per frequency response a Bode overlay
(data beside the fitted models, Hz axis, residual below).
Figures only: everything they show was computed by the fit (``FitResult.traces``).
"""

from __future__ import annotations

import re
from pathlib import PurePath
from typing import Sequence

import numpy as np

from .._lazy import module
from ..identification.common import FitResult

plt = module("matplotlib.pyplot")

__all__ = ["fit_figures", "figure_names"]

def _figure_stem(name: str, used: set) -> str:
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", PurePath(name).stem) or "data"
    out, i = stem, 2
    while out in used:
        out, i = f"{stem}-{i}", i + 1
    used.add(out)
    return out


def fit_figures(result: FitResult) -> dict:
    """Figures of a fit: per time-domain record the measured and simulated nut speed with the
    residual below; per frequency response a Bode overlay (measured vs fitted model).

    Parameters
    ----------
    result : FitResult

    Returns
    -------
    dict
        ``{file stem: matplotlib Figure}`` (``<record>-fit`` and ``<response>-bode``); the
        caller saves and closes them.
    """
    figs, used = {}, set()
    for name, tr in result.traces.items():
        stem = _figure_stem(name, used)
        if "time_s" in tr:
            t, meas, mod, label, joins = _overlay_data(tr)
            fig, (ax1, ax2) = plt.subplots(2, 1, sharex=True, figsize=(8, 5.5), height_ratios=(2, 1))
            ax1.plot(t, meas, lw=0.8, color="0.5", label="measured (angle difference)")
            ax1.plot(t, mod, lw=1.0, color="C0", label=label)
            for tj in joins:  # only when the shooting segments themselves are shown
                ax1.axvline(tj, color="C1", lw=0.4, alpha=0.5)
            ax1.set_ylabel("nut speed (rad/s)")
            ax1.set_title(f"{name}: fit {result.fit_percent.get(name, float('nan')):.1f} %")
            ax1.legend(loc="best", fontsize=8)
            ax2.plot(t, meas - mod, lw=0.6, color="C3")
            ax2.axhline(0.0, color="0.3", lw=0.5)
            ax2.set_ylabel("residual (rad/s)")
            ax2.set_xlabel("time (s)")
            for ax in (ax1, ax2):
                ax.grid(True, alpha=0.3)
            fig.tight_layout()
            figs[f"{stem}-fit"] = fig
        else:
            figs[f"{stem}-bode"] = _bode_figure(name, tr, result.fit_percent.get(name, float("nan")))
    return figs


def _bode_figure(name: str, tr: dict, fit_pct: float):
    """Bode overlay of a frequency response: the data (points) beside the fitted models (lines:
    the written plant's and, from an FRF-only fit, the rigid and the two-mass models), Hz axis,
    and the residual of the written model (log magnitude in dB, phase in degrees) below."""
    f = np.asarray(tr["frequency_hz"], float)
    gm, gf = np.asarray(tr["measured"]), np.asarray(tr["model"])
    models = dict(tr.get("models") or {})
    fig, (ax1, ax2, ax3) = plt.subplots(3, 1, sharex=True, figsize=(8, 7.5), height_ratios=(2, 2, 1.3))
    ax1.semilogx(f, 20 * np.log10(np.abs(gm)), ".", ms=4, color="0.4", label="measured")
    pm = np.degrees(np.unwrap(np.angle(gm)))
    ax2.semilogx(f, pm, ".", ms=4, color="0.4")
    lines = [(label, g, dict(lw=0.9, ls="--")) for label, g in models.items() if not label.startswith("plant model")]
    lines.append(("fitted plant as written" if models else "fitted model", gf, dict(lw=1.4, ls="-")))
    for i, (label, g, style) in enumerate(lines):
        g = np.asarray(g)
        ax1.semilogx(f, 20 * np.log10(np.abs(g)), color=f"C{i}", label=label, **style)
        # the model's phase on the branch of the measured one (no 360 deg jumps between them)
        ph = np.degrees(np.angle(g * np.exp(-1j * np.radians(pm)))) + pm
        ax2.semilogx(f, ph, color=f"C{i}", **style)
    ax1.set_ylabel("|G| (dB re 1 rad/s per N m)")
    chosen = tr.get("chosen")
    ax1.set_title(f"{name}: fit {fit_pct:.1f} %" + (f" (structure: {chosen})" if chosen else ""))
    ax1.legend(loc="best", fontsize=8)
    ax2.set_ylabel("phase (deg)")
    d = np.log(gm / gf)
    ax3.semilogx(f, 20 / np.log(10) * d.real, ".-", ms=3, lw=0.6, color="C3", label="magnitude (dB)")
    ax3b = ax3.twinx()
    ax3b.semilogx(f, np.degrees(np.angle(np.exp(1j * d.imag))), ".-", ms=3, lw=0.6, color="C4", label="phase (deg)")
    ax3.axhline(0.0, color="0.3", lw=0.5)
    ax3.set_ylabel("residual (dB)", color="C3")
    ax3b.set_ylabel("residual (deg)", color="C4")
    ax3.set_xlabel("frequency (Hz)")
    for ax in (ax1, ax2, ax3):
        ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    return fig


def _overlay_data(tr: dict):
    """What a record's overlay figure plots: ``(time_s, measured, model, model label, join
    times)``. The model is the continuous replay of the plant as written when there is one
    (the validation's, :mod:`prsa_ctrl.identification.validation`, labelled with its mode: no
    segment joins, so no resets that look like model error);
    otherwise the shooting segments, each drawn apart (NaN between them) with its start marked.
    Gaps in the data (left-out stretches) are broken with NaN too."""
    sim = tr.get("simulated")
    if sim is not None:
        t, meas, mod = (np.asarray(sim[k], float) for k in ("time_s", "measured", "model"))
        breaks, joins = np.zeros(0, int), []
        label = sim.get("label", "fitted plant, one continuous simulation")
    else:
        t, meas, mod = (np.asarray(tr[k], float) for k in ("time_s", "measured", "model"))
        breaks = np.asarray(tr.get("joins", np.zeros(0, int)), int)
        joins = [float(t[j]) for j in breaks]
        label = "fitted model (shooting segments; each starts at a marked join)"
    gap = np.flatnonzero(np.diff(t) > 1.5 * float(np.median(np.diff(t))))
    cut = np.union1d(gap + 1, breaks)
    return (*(np.insert(a, cut, np.nan) for a in (t, meas, mod)), label, joins)


def figure_names(names: Sequence[str], frf_names: Sequence[str] = ()) -> list[str]:
    """File stems :func:`fit_figures` will use for these record and response names (in order:
    fitted and validation records, then responses), so output paths can be checked first."""
    used: set = set()
    return [f"{_figure_stem(n, used)}-fit" for n in names] + [f"{_figure_stem(n, used)}-bode" for n in frf_names]
