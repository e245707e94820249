"""Figures of a fit (:class:`prsa_ctrl.identification.common.FitResult`): per time-domain record
the measured and simulated nut speed with the residual, per frequency response a Bode overlay.
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
            f = np.asarray(tr["frequency_hz"], float)
            gm, gf = np.asarray(tr["measured"]), np.asarray(tr["model"])
            fig, (ax1, ax2) = plt.subplots(2, 1, sharex=True, figsize=(8, 5.5))
            ax1.semilogx(f, 20 * np.log10(np.abs(gm)), ".", ms=4, color="0.4", label="measured")
            ax1.semilogx(f, 20 * np.log10(np.abs(gf)), "-", color="C0", label="fitted model")
            ax1.set_ylabel("|G| (dB re 1 rad/s per N m)")
            ax1.set_title(f"{name}: fit {result.fit_percent.get(name, float('nan')):.1f} %")
            ax1.legend(loc="best", fontsize=8)
            pm = np.degrees(np.unwrap(np.angle(gm)))
            pf = np.degrees(np.unwrap(np.angle(gf)))
            ax2.semilogx(f, pm, ".", ms=4, color="0.4")
            ax2.semilogx(f, pf, "-", color="C0")
            ax2.set_ylabel("phase (deg)")
            ax2.set_xlabel("frequency (Hz)")
            for ax in (ax1, ax2):
                ax.grid(True, which="both", alpha=0.3)
            fig.tight_layout()
            figs[f"{stem}-bode"] = fig
    return figs


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
