"""Is a replay residual's spectral peak a mode or a position-periodic torque? (the screw path's
:func:`prsa_ctrl.identification.validation.diagnosis`).

A torque periodic in the motor angle (cogging: a fixed number of cycles per revolution; a
screw's pitch error) makes a residual peak at ``k w / 2 pi`` Hz that moves with the speed ``w``;
a mode's peak stays at its frequency whatever the speed. Measured on gen_third's ball 40x16 logs
(tests/identification/foreign/gen_third.py, cogging 2 % and 1 % of the rated torque at 6 and
12 per revolution): the load steps at 25 rad/s left 86 % of the rigid plant's replay residual
within 15 % of 23.44 Hz, which the verdict named a second mass; it is the 6-per-revolution
cogging (23.9 Hz), the axis's mode is at 118 Hz.

The test (:func:`periodic_or_mode`): on the samples where the axis moves (above 5 % of its peak
speed), the out-of-sample share of the residual's power that one sinusoid **of the motor angle**
explains (``k`` cycles per revolution searched within the peak's +/- 15 % band at the log's
median speed) against the share one sinusoid **of time** explains (the frequency searched in the
same band). Each share is fitted on alternate blocks of :data:`CV_BLOCK` samples and scored on
the others, and the other way round (``1 - SSE / SST``, :func:`cv_share`, which the linear axis's
``periodic_share`` in :mod:`prsa_ctrl.identification.axisvalidation` scores with too; there the
period is searched over the whole travel against the force residual, here the cycles per revolution within the peak's band against the speed residual, and
compared with a sinusoid of time). Where the speed varies the two differ: the angle's sinusoid
follows a periodic torque, time's a mode. Measured (the ball case): load steps at 24.7..25.1 rad/s,
angle 0.852 at k = 6.000, time 0.787 at 23.83 Hz; the multisine's 121 Hz mode (15.6..24.1 rad/s),
angle 0.022, time 0.195. A log whose speed barely varies cannot tell them apart: the verdict says
so (:data:`MARGIN`) rather than guess.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

__all__ = ["periodic_or_mode", "cv_share", "PERIODIC_SHARE", "MARGIN", "CV_BLOCK"]

#: The angle's sinusoid must explain at least this share of the residual (out of sample) for a
#: position-periodic torque (a fifth: far from chance, 0.02 on a mode's residual).
PERIODIC_SHARE = 0.2
#: ... and this much more than time's sinusoid (out of sample shares); within it the log cannot
#: tell them apart.
MARGIN = 0.03
#: Blocks (samples) of the out-of-sample split.
CV_BLOCK = 250
#: Grid points of each search (cycles per revolution; frequency) over the +/- 15 % band.
_GRID = 241


def cv_share(y: NDArray[np.float64], x: NDArray[np.float64], *, block: int = CV_BLOCK, rcond: float = 1e-9) -> float:
    """Out-of-sample share of ``y``'s power that the columns of ``x`` (and a constant) predict.

    Least squares on alternate blocks of ``block`` samples, scored on the others and the other way
    round: ``1 - SSE / SST`` over both folds (0 or below: ``x`` predicts nothing; 0 when ``y`` has
    fewer than ``4 block`` samples). Singular values of ``x`` below ``rcond`` times the largest are
    dropped. The one out-of-sample share of the residual tests (this module's position-periodic
    test and the linear axis's, :mod:`prsa_ctrl.identification.axisvalidation`).
    """
    n = len(y)
    if n < 4 * block:
        return 0.0
    fold = (np.arange(n) // block) % 2
    a = np.column_stack([np.ones(n), x])
    sse = sst = 0.0
    for f in (0, 1):
        tr, te = fold == f, fold != f
        b = np.linalg.lstsq(a[tr], y[tr], rcond=rcond)[0]
        e = y[te] - a[te] @ b
        sse += float(e @ e)
        sst += float(np.sum((y[te] - y[tr].mean()) ** 2))
    return 1.0 - sse / sst if sst > 0 else 0.0


def _best(y: NDArray[np.float64], phase_per_unit: NDArray[np.float64], grid) -> tuple[float, float]:
    best = (-math.inf, math.nan)
    for g in grid:
        ph = g * phase_per_unit
        s = cv_share(y, np.column_stack([np.sin(ph), np.cos(ph)]))
        if s > best[0]:
            best = (s, float(g))
    return best


def periodic_or_mode(entry: dict, peak_hz: float) -> dict | None:
    """The test of the module docstring on one replay entry (``time_s``, ``measured`` and
    ``model`` speeds in rad/s at the motor, ``skip_samples``) whose residual peaks at
    ``peak_hz`` (Hz).

    Returns
    -------
    dict or None
        ``{"verdict": "periodic" | "mode" | "undecided", "angle_share", "cycles_per_rev",
        "time_share", "time_hz", "speed_rad_s" (median while moving), "speed_range_rad_s"
        ([10th, 90th percentile])}``; None when the log has too few moving samples or no motion.
    """
    t = np.asarray(entry.get("time_s", ()), float)
    meas, model = np.asarray(entry.get("measured", ()), float), np.asarray(entry.get("model", ()), float)
    skip = int(entry.get("skip_samples", 0))
    if t.size < 2 or meas.size != model.size or meas.size != t.size or not peak_hz > 0:
        return None
    ts = float(np.median(np.diff(t)))
    y, w, tt = (meas - model)[skip:], meas[skip:], t[skip:]
    theta = np.cumsum(w) * ts  # the motor angle from the measured speed (its origin cancels in the sinusoid's phase)
    wmax = float(np.max(np.abs(w))) if w.size else 0.0
    moving = np.abs(w) > 0.05 * wmax
    if not wmax > 0 or np.count_nonzero(moving) < 4 * CV_BLOCK:
        return None
    y, theta, tt, wm = y[moving], theta[moving], tt[moving], np.abs(w[moving])
    speed = float(np.median(wm))
    k0 = 2.0 * math.pi * peak_hz / speed
    a_share, k = _best(y, theta, np.linspace(0.85 * k0, 1.15 * k0, _GRID))
    t_share, f = _best(y, 2.0 * math.pi * tt, np.linspace(0.85 * peak_hz, 1.15 * peak_hz, _GRID))
    if a_share >= PERIODIC_SHARE and a_share >= t_share + MARGIN:
        verdict = "periodic"
    elif a_share >= PERIODIC_SHARE and a_share > t_share - MARGIN:
        verdict = "undecided"
    else:
        verdict = "mode"
    return {"verdict": verdict, "angle_share": a_share, "cycles_per_rev": k, "time_share": t_share, "time_hz": f,
            "speed_rad_s": speed, "speed_range_rad_s": [float(np.percentile(wm, 10)), float(np.percentile(wm, 90))]}
