"""Figures of a Monte-Carlo run (:class:`prsa_ctrl.studies.montecarlo.MonteCarloReport`): drawn
from the report's samples only, nothing computed here."""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np

from ..studies.montecarlo import METRICS

__all__ = ["plot_report"]


def plot_report(report, path=None, metric: str = "peak_drop_rad_s"):
    """Histograms of ``metric`` per design and a parameter-vs-metric scatter (one panel per
    uncertain parameter), spec bound dashed. Returns the figure (saved when ``path`` is given)."""
    s = report.samples
    keys = list(s["values"])
    k = METRICS.index(metric)
    fig, axes = plt.subplots(1, 1 + len(keys), figsize=(4.2 * (1 + len(keys)), 3.4), squeeze=False)
    ax = axes[0, 0]
    for j, name in enumerate(s["design_names"]):
        col = s["metrics"][:, j, k]
        col = col[np.isfinite(col)]
        ax.hist(col, bins=30, alpha=0.6, label=name)
        for kk, key in enumerate(keys):
            axes[0, 1 + kk].scatter(s["values"][key], s["metrics"][:, j, k], s=6, alpha=0.6, label=name)
    for a in axes[0]:
        if metric in report.spec:
            (a.axvline if a is ax else a.axhline)(report.spec[metric], color="k", ls="--", lw=1)
    ax.set_xlabel(metric)
    ax.set_ylabel("samples")
    ax.legend(fontsize=8)
    for kk, key in enumerate(keys):
        axes[0, 1 + kk].set_xlabel(key)
        axes[0, 1 + kk].set_ylabel(metric)
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=120)
    return fig
