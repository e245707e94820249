"""Multiple-shooting segments and the data-based reference trajectory of the time-domain fit
(:mod:`prsa_ctrl.identification.timedomain`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from ..plant.plantfile import Plant
from .data import Record

__all__ = ["MIN_SEGMENT", "Seg", "shooting_segments", "reference_trajectory"]

#: Shortest multiple-shooting segment (sample intervals); shorter stretches of usable data are left out.
MIN_SEGMENT = 20


@dataclass
class Seg:
    rec: int
    k0: int  # first sample of the segment
    n: int  # intervals


def shooting_segments(records: Sequence[Record], segment_samples: int, refs=None, min_speed_rad_s: float = 0.0,
                      margin: int = 2) -> tuple[list[Seg], int]:
    """Multiple-shooting segments of about ``segment_samples`` intervals, and the samples left out.

    Intervals where the (smoothed) data speed is below ``min_speed_rad_s`` within ``margin``
    samples (speed reversals, standstill) are left out: there the friction law is not smooth
    (Karnopp stick band, Stribeck drop) and one collocation step per sample misses the
    stick-slip transition, a model error that would bias the fit and make its residuals
    coloured. Every stretch in between starts a segment of its own with a free initial state.
    Stretches shorter than ``MIN_SEGMENT`` intervals are left out too.
    """
    segs, left_out = [], 0
    for r, rec in enumerate(records):
        n_int = rec.n - 1
        ok = np.ones(n_int, bool)
        if refs is not None and min_speed_rad_s > 0:
            # mean speed over each interval (angle difference), lightly smoothed against noise
            v = np.diff(refs[r][0]) / np.diff(rec.time_s)
            v = np.convolve(v, np.ones(3) / 3, mode="same") if len(v) >= 3 else v
            slow = np.abs(v) < min_speed_rad_s
            flip = np.signbit(v[:-1]) != np.signbit(v[1:])  # a reversal faster than one sample
            slow[:-1] |= flip
            slow[1:] |= flip
            if margin:
                slow = np.convolve(slow.astype(float), np.ones(2 * margin + 1), mode="same") > 0
            ok = ~slow
        edges = np.flatnonzero(np.diff(np.concatenate([[0], ok.astype(int), [0]])))
        for a, b in zip(edges[::2], edges[1::2]):
            if b - a < MIN_SEGMENT:
                continue
            n_seg = max(1, int(round((b - a) / segment_samples)))
            cuts = np.linspace(a, b, n_seg + 1).round().astype(int)
            segs += [Seg(r, int(c0), int(c1 - c0)) for c0, c1 in zip(cuts[:-1], cuts[1:])]
        left_out += n_int - int(ok.sum()) + sum(int(b - a) for a, b in zip(edges[::2], edges[1::2]) if b - a < MIN_SEGMENT)
    return segs, left_out


def reference_trajectory(rec: Record, plant: Plant) -> NDArray[np.float64]:
    """Data-based reference trajectory (nx=3 rigid-like rows: angle, speed, torque) per sample."""
    t = rec.time_s
    if rec.nut_angle_rad is not None:
        theta = rec.nut_angle_rad.astype(float)
    else:
        theta = np.concatenate([[0.0], np.cumsum(rec.nut_speed_rad_s[1:] * np.diff(t))])
    omega = np.gradient(theta, t)
    a = math.exp(-(t[1] - t[0]) / plant.current_loop_time_constant_s)
    cmd = np.clip(rec.torque_command_n_m, -plant.torque_limit, plant.torque_limit)
    tau = np.empty_like(cmd)
    tau[0] = cmd[0]
    for k in range(1, len(cmd)):
        tau[k] = a * tau[k - 1] + (1 - a) * cmd[k - 1]
    return np.vstack([theta, omega, tau])
