"""Input signals of a simulation run: profiles (numbers, steps, piecewise-linear ramps) and
their one normalised form.

A profile given to :func:`prsa_ctrl.sim.engine.run` (setpoint in rad/s, load in N) is a
number, a list of ``(time_s, value)`` steps or a :class:`PiecewiseLinear` ramp;
:func:`normalise_profile` checks it once and turns it into a :class:`NormalisedProfile`
(breakpoints, values, slopes and which breakpoints are steps), the form the simulator,
the tuner's scene checks and the figures read.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from numpy.typing import NDArray

from ..options import is_number
from ..tablefile import read_table
from ..textsafe import quote

__all__ = ["PiecewiseLinear", "Profile", "NormalisedProfile", "normalise_profile", "is_number"]


@dataclass(frozen=True)
class PiecewiseLinear:
    """An input profile linear between its points, constant after the last one.

    Parameters
    ----------
    points : sequence of (time_s, value)
        The first at t = 0; times non-decreasing. Two points at the same time make a step
        there (from the first value to the second), so ramps and steps mix:
        ``[(0, 500), (0.1, 500), (0.1, 1500), (0.3, 1000)]`` holds 500 N, steps to 1500 N at
        0.1 s and ramps down to 1000 N at 0.3 s.

    Examples
    --------
    >>> ramp = PiecewiseLinear([(0.0, 500.0), (0.1, 1500.0)])
    >>> ramp.points[-1]
    (0.1, 1500.0)
    """

    points: tuple[tuple[float, float], ...]

    def __post_init__(self) -> None:
        try:
            pts = tuple((float(t), float(v)) for t, v in self.points)
        except (TypeError, ValueError):
            raise ValueError(f"points = {self.points!r}; expected a list of (time_s, value) pairs") from None
        object.__setattr__(self, "points", pts)

    @classmethod
    def from_csv(cls, path: "str | Path", column: str = "axial_load_n", *, max_rows: int = 1_000_000) -> "PiecewiseLinear":
        """A measured trace from a CSV file with a header: ``time_s`` and ``column``.

        Read by :func:`prsa_ctrl.tablefile.read_table` (its rule for byte-order marks, ``#``
        comments, the header, the size and finite numbers). Times must start at 0 and
        increase strictly. The trace is used
        as a piecewise-linear profile (at most one point per controller sample in a sampled
        run: resample faster traces).

        Parameters
        ----------
        path : str or Path
        column : str
            Header of the value column (default ``axial_load_n``, N).
        max_rows : int
            Most data rows accepted (the file size is bounded before reading, at
            ``tablefile.ROW_BYTES_MAX`` bytes a row).

        Raises
        ------
        ValueError
            One line naming the file, the line and the value.
        """
        p = Path(path)
        table = read_table(p, max_rows=max_rows, name=str(p), columns=("time_s", column))
        if "time_s" not in table.columns or column not in table.columns:
            raise ValueError(f"{p} line {table.header_line}: header {quote(','.join(table.header))}; expected columns "
                             f"'time_s' and {quote(column)}")
        ts, vs = table.columns["time_s"], table.columns[column]
        pts: list[tuple[float, float]] = []
        for k, line in enumerate(table.lines):
            t = float(ts[k])
            if pts and t <= pts[-1][0]:
                raise ValueError(f"{p} line {line}: time_s = {t!r} after {pts[-1][0]!r}; expected increasing times")
            pts.append((t, float(vs[k])))
        if len(pts) < 2:
            raise ValueError(f"{p}: {len(pts)} data rows; expected at least 2")
        if pts[0][0] != 0.0:
            raise ValueError(f"{p} line {table.lines[0]}: time_s = {pts[0][0]!r}; expected the trace to start at 0")
        return cls(tuple(pts))


Profile = float | Sequence[tuple[float, float]] | PiecewiseLinear


@dataclass(frozen=True)
class NormalisedProfile:
    """A normalised input profile: at each breakpoint ``t[i]`` the value becomes ``v[i]`` and
    then changes with slope ``s[i]`` (per s) until the next breakpoint. ``jump[i]`` says
    whether the value is discontinuous there (a step event).

    Attributes
    ----------
    t : ndarray, s
        Breakpoints, the first at 0.
    v : ndarray
        Value from each breakpoint on (the profile's unit: rad/s or N).
    s : ndarray
        Slope after each breakpoint, unit per s.
    jump : ndarray of bool
        Whether the value steps at each breakpoint.
    """

    t: NDArray[np.float64]
    v: NDArray[np.float64]
    s: NDArray[np.float64]
    jump: NDArray[np.bool_]

    def at(self, t: NDArray[np.float64] | float) -> NDArray[np.float64]:
        """Value at time(s) ``t`` (after any step at exactly ``t``)."""
        tt = np.asarray(t, dtype=float)
        i = np.clip(np.searchsorted(self.t, tt + 1e-12, side="right") - 1, 0, len(self.t) - 1)
        return self.v[i] + self.s[i] * np.maximum(tt - self.t[i], 0.0)

    def slope_at(self, t: NDArray[np.float64] | float) -> NDArray[np.float64]:
        """Slope (unit per s) at time(s) ``t`` (after any breakpoint at exactly ``t``)."""
        tt = np.asarray(t, dtype=float)
        i = np.clip(np.searchsorted(self.t, tt + 1e-12, side="right") - 1, 0, len(self.t) - 1)
        return self.s[i]

    @property
    def breaks(self) -> NDArray[np.float64]:
        """Breakpoints after t = 0 (steps and kinks)."""
        return self.t[1:]


def normalise_profile(profile: Profile, duration: float, what: str, unit: str) -> NormalisedProfile:
    """Check a profile and bring it into the one normalised form.

    Parameters
    ----------
    profile : float, list of (time_s, value) or PiecewiseLinear
        A constant, steps (piecewise constant) or ramps.
    duration : float, s
        Length of the run: every breakpoint lies before it.
    what, unit : str
        The argument's name and unit, for the error messages.

    Returns
    -------
    NormalisedProfile

    Raises
    ------
    ValueError
        One line naming ``what``, the value given and what was expected.

    Examples
    --------
    >>> p = normalise_profile([(0, 500.0), (0.1, 1500.0)], 0.2, "load", "N")
    >>> float(p.at(0.05)), float(p.at(0.1)), p.jump.tolist()
    (500.0, 1500.0, [False, True])
    """
    linear = isinstance(profile, PiecewiseLinear)
    if is_number(profile):
        pts = [(0.0, float(profile))]  # type: ignore[arg-type]
    else:
        try:
            pts = list(profile.points) if linear else [(float(t), float(v)) for t, v in profile]  # type: ignore
        except (TypeError, ValueError):
            raise ValueError(
                f"{what} = {profile!r}; expected a number ({unit}), a list of (time_s, value) steps or a "
                "PiecewiseLinear profile"
            ) from None
    if not pts:
        raise ValueError(f"{what} = {profile!r}; expected at least one value")
    for t, v in pts:
        if not (math.isfinite(t) and math.isfinite(v)):
            raise ValueError(f"{what} point ({t}, {v}) is not finite; expected finite time (s) and value ({unit})")
    if pts[0][0] != 0.0:
        raise ValueError(f"{what} starts at t = {pts[0][0]} s; expected the first point at t = 0")
    times = [t for t, _ in pts]
    if linear:
        bad = any(b < a for a, b in zip(times, times[1:])) or any(
            a == b == c for a, b, c in zip(times, times[1:], times[2:]))
        if bad or times[-1] >= duration:
            raise ValueError(f"{what} times {times} must not decrease (two equal times make a step, three are "
                             f"ambiguous) and must stay below the duration {duration} s")
    elif any(b <= a for a, b in zip(times, times[1:])) or times[-1] >= duration:
        raise ValueError(f"{what} times {times} must increase strictly and stay below the duration {duration} s")
    # Breakpoints: the first and last value given at each distinct time.
    first: dict[float, float] = {}
    last: dict[float, float] = {}
    for t, v in pts:
        first.setdefault(t, v)
        last[t] = v
    bt = sorted(first)
    bv = [last[t] for t in bt]
    if linear:
        bs = [(first[t1] - bv[i]) / (t1 - bt[i]) for i, t1 in enumerate(bt[1:])] + [0.0]
        bj = [False] + [first[t] != last[t] for t in bt[1:]]
    else:
        bs = [0.0] * len(bt)
        bj = [False] + [True] * (len(bt) - 1)
    return NormalisedProfile(np.array(bt), np.array(bv), np.array(bs), np.array(bj, dtype=bool))
