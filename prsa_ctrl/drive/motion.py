"""Motion profiles of a positioning move: trapezoidal and S-curve, exact and in closed form.

A profile is a chain of segments of constant jerk; on each the position (m of screw travel),
speed (m/s) and acceleration (m/s^2) are the exact polynomials::

    p(t) = p0 + v0 tau + a0 tau^2/2 + j tau^3/6,   v = v0 + a0 tau + j tau^2/2,   a = a0 + j tau

with ``tau = t - t0``. Each segment starts where the previous one ended (``p``, ``v`` carried
over exactly; ``a`` too except at the acceleration steps of a trapezoidal profile, which has
infinite jerk there). Before the first segment and after the last the axis is at rest.

Planning (rest to rest, symmetric acceleration and deceleration, distance ``D``, speed limit
``V``, acceleration limit ``A``, jerk limit ``J``):

trapezoidal
    ``t_a = V/A``; if ``V^2/A > D`` the speed is not reached: ``V = sqrt(A D)``.
S-curve (seven segments: +J, 0, -J, cruise, -J, 0, +J)
    if ``V J >= A^2`` the acceleration phase lasts ``V/A + A/J`` with ``A`` reached, else
    ``2 sqrt(V/J)`` with peak acceleration ``sqrt(V J)``; if its distance ``V T_acc`` exceeds
    ``D`` the peak speed is lowered to the ``v`` that solves ``v T_acc(v) = D`` (closed form:
    ``v = (-A^2/J + sqrt(A^4/J^2 + 4 A D))/2`` when ``v >= A^2/J``, else ``(D sqrt(J)/2)^(2/3)``).

:func:`out_and_back` chains a move, a dwell at rest and the move back (a reversal).

Examples
--------
>>> m = s_curve(0.01, 0.03, 1.0, 100.0)
>>> p, v, a = m.at([0.0, m.duration])
>>> float(p[-1]), float(v[-1]), float(a[-1])
(0.01, 0.0, 0.0)
>>> round(float(m.at(m.duration / 2)[1]), 6)  # cruising at 30 mm/s
0.03
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..options import check_number

__all__ = ["MotionProfile", "trapezoidal", "s_curve", "out_and_back", "PROFILE_KINDS", "MAX_SEGMENTS"]

#: Kinds of move :func:`plan` knows.
PROFILE_KINDS = ("trapezoidal", "s-curve")
#: Most segments of one profile (a move has at most 7; chains of moves stay far below).
MAX_SEGMENTS = 1000


@dataclass(frozen=True)
class MotionProfile:
    """A chain of constant-jerk segments (see the module docstring).

    Parameters
    ----------
    t0, p0, v0, a0, jerk : tuple of float
        Start time (s), position (m), speed (m/s), acceleration (m/s^2) and jerk (m/s^3) of
        each segment, times increasing.
    end_time : float, s
        End of the last segment; after it the axis rests at the final position.
    """

    t0: tuple[float, ...]
    p0: tuple[float, ...]
    v0: tuple[float, ...]
    a0: tuple[float, ...]
    jerk: tuple[float, ...]
    end_time: float

    @classmethod
    def from_segments(cls, segments: Sequence[tuple[float, float, float | None]], *, start_time: float = 0.0,
                      start_position: float = 0.0) -> "MotionProfile":
        """Chain segments ``(duration s, jerk m/s^3, acceleration m/s^2 at the start or None to
        carry it over)`` from rest at ``start_position`` (m) and ``start_time`` (s).

        Returns
        -------
        MotionProfile

        Raises
        ------
        ValueError
            For a negative or non-finite duration, a non-finite jerk or acceleration, or more
            than :data:`MAX_SEGMENTS` segments.
        """
        if len(segments) > MAX_SEGMENTS:
            raise ValueError(f"{len(segments)} segments; expected at most {MAX_SEGMENTS}")
        t, p, v, a = float(start_time), float(start_position), 0.0, 0.0
        cols: list[list[float]] = [[], [], [], [], []]
        for dur, j, a_start in segments:
            if not (math.isfinite(dur) and dur >= 0 and math.isfinite(j)) \
                    or (a_start is not None and not math.isfinite(a_start)):
                raise ValueError(f"segment ({dur!r}, {j!r}, {a_start!r}); expected a finite duration >= 0 s and "
                                 "finite jerk and acceleration")
            if a_start is not None:
                a = float(a_start)
            if dur == 0:
                continue
            for c, x in zip(cols, (t, p, v, a, j)):
                c.append(x)
            p, v, a = (p + v * dur + a * dur**2 / 2 + j * dur**3 / 6, v + a * dur + j * dur**2 / 2, a + j * dur)
            t += dur
        return cls(*(tuple(c) for c in cols), end_time=t)

    @property
    def duration(self) -> float:
        """End of the motion, s (the axis is at rest afterwards)."""
        return self.end_time

    @property
    def final_position(self) -> float:
        """Position at the end, m."""
        return float(self.at(self.end_time)[0])

    def at(self, t: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Position (m), speed (m/s) and acceleration (m/s^2) at time(s) ``t`` (s).

        Returns
        -------
        p, v, a : ndarray
            Same shape as ``t``; at rest before the first and after the last segment.
        """
        tt = np.asarray(t, dtype=float)
        if not self.t0:
            z = np.zeros_like(tt)
            return z, z.copy(), z.copy()
        t0 = np.asarray(self.t0)
        i = np.clip(np.searchsorted(t0, tt, side="right") - 1, 0, len(t0) - 1)
        # After the end: the state at the end of the last segment, at rest.
        tau = np.clip(tt - t0[i], 0.0, None)
        seg_end = np.append(t0[1:], self.end_time)
        tau = np.minimum(tau, seg_end[i] - t0[i])
        p0, v0, a0, j = (np.asarray(x)[i] for x in (self.p0, self.v0, self.a0, self.jerk))
        p = p0 + v0 * tau + a0 * tau**2 / 2 + j * tau**3 / 6
        v = v0 + a0 * tau + j * tau**2 / 2
        a = a0 + j * tau
        rest = (tt < t0[0]) | (tt >= self.end_time)
        before = tt < t0[0]
        p = np.where(before, self.p0[0], p)
        v = np.where(rest, 0.0, v)
        a = np.where(rest, 0.0, a)
        return p, v, a

    def shifted(self, dt: float, dp: float = 0.0) -> "MotionProfile":
        """The same profile ``dt`` s later and ``dp`` m further."""
        return MotionProfile(tuple(x + dt for x in self.t0), tuple(x + dp for x in self.p0), self.v0, self.a0,
                             self.jerk, self.end_time + dt)

    def then(self, other: "MotionProfile", dwell_s: float = 0.0) -> "MotionProfile":
        """This profile, a dwell at rest of ``dwell_s`` s, then ``other`` (planned from rest at
        0 m, t = 0 s) continuing from this profile's final position."""
        if not (math.isfinite(dwell_s) and dwell_s >= 0):
            raise ValueError(f"dwell_s = {dwell_s!r}; expected a finite time >= 0 s")
        o = other.shifted(self.end_time + dwell_s, self.final_position)
        # Segments are contiguous: the dwell is a segment at rest.
        rest = ((self.end_time,), (self.final_position,), (0.0,), (0.0,), (0.0,)) if dwell_s > 0 else ((),) * 5
        if len(self.t0) + len(o.t0) + 1 > MAX_SEGMENTS:
            raise ValueError(f"{len(self.t0) + len(o.t0) + 1} segments; expected at most {MAX_SEGMENTS}")
        return MotionProfile(self.t0 + rest[0] + o.t0, self.p0 + rest[1] + o.p0, self.v0 + rest[2] + o.v0,
                             self.a0 + rest[3] + o.a0, self.jerk + rest[4] + o.jerk, o.end_time)

    def limits(self) -> dict[str, float]:
        """Peak |speed| (m/s), |acceleration| (m/s^2) and |jerk| (m/s^3), exact (the peaks of
        the polynomials sit at segment ends or at the zero of the speed's derivative)."""
        tt = np.concatenate([np.asarray(self.t0), [self.end_time]])
        p, v, a = self.at(np.nextafter(tt, -np.inf))
        v_peak = max(float(np.max(np.abs(v))), float(np.max(np.abs(np.asarray(self.v0)))) if self.v0 else 0.0)
        for k, j in enumerate(self.jerk):  # interior speed extremum at a = 0
            if j != 0:
                tau = -self.a0[k] / j
                dur = (tt[k + 1] - tt[k])
                if 0 < tau < dur:
                    v_peak = max(v_peak, abs(self.v0[k] + self.a0[k] * tau + j * tau**2 / 2))
        a_ends = [abs(x) for x in self.a0] + [float(np.max(np.abs(a)))]
        return {"speed_m_s": v_peak, "acceleration_m_s2": max(a_ends),
                "jerk_m_s3": max((abs(j) for j in self.jerk), default=0.0)}


def trapezoidal(distance_m: float, max_speed_m_s: float, acceleration_m_s2: float) -> MotionProfile:
    """Rest-to-rest trapezoidal move (infinite jerk at the corners).

    Parameters
    ----------
    distance_m : float, m
        Signed travel (non-zero).
    max_speed_m_s : float, m/s
    acceleration_m_s2 : float, m/s^2

    Returns
    -------
    MotionProfile

    Examples
    --------
    >>> m = trapezoidal(0.01, 0.03, 0.5)
    >>> round(m.duration, 6)  # 10 mm / 30 mm/s + 30 mm/s / 0.5 m/s^2
    0.393333
    """
    d = float(distance_m)
    if isinstance(distance_m, bool) or not math.isfinite(d) or d == 0:
        raise ValueError(f"distance_m = {distance_m!r}; expected a finite non-zero travel in m")
    v = check_number("max_speed_m_s", max_speed_m_s, 0.0, unit="m/s", lo_open=True)
    acc = check_number("acceleration_m_s2", acceleration_m_s2, 0.0, unit="m/s^2", lo_open=True)
    s, dist = math.copysign(1.0, d), abs(d)
    if v * v / acc > dist:
        v = math.sqrt(acc * dist)
    ta = v / acc
    tc = dist / v - ta
    return MotionProfile.from_segments([(ta, 0.0, s * acc), (max(tc, 0.0), 0.0, 0.0), (ta, 0.0, -s * acc)])


def s_curve(distance_m: float, max_speed_m_s: float, acceleration_m_s2: float, jerk_m_s3: float) -> MotionProfile:
    """Rest-to-rest jerk-limited (seven-segment) move, planned in closed form (module docstring).

    Parameters
    ----------
    distance_m : float, m
        Signed travel (non-zero).
    max_speed_m_s : float, m/s
    acceleration_m_s2 : float, m/s^2
    jerk_m_s3 : float, m/s^3

    Returns
    -------
    MotionProfile
    """
    d = float(distance_m)
    if isinstance(distance_m, bool) or not math.isfinite(d) or d == 0:
        raise ValueError(f"distance_m = {distance_m!r}; expected a finite non-zero travel in m")
    v = check_number("max_speed_m_s", max_speed_m_s, 0.0, unit="m/s", lo_open=True)
    acc = check_number("acceleration_m_s2", acceleration_m_s2, 0.0, unit="m/s^2", lo_open=True)
    jerk = check_number("jerk_m_s3", jerk_m_s3, 0.0, unit="m/s^3", lo_open=True)
    s, dist = math.copysign(1.0, d), abs(d)

    def t_acc(vv: float) -> float:
        return vv / acc + acc / jerk if vv * jerk >= acc * acc else 2.0 * math.sqrt(vv / jerk)

    if v * t_acc(v) > dist:
        v1 = (-acc * acc / jerk + math.sqrt(acc**4 / jerk**2 + 4.0 * acc * dist)) / 2.0
        v = v1 if v1 * jerk >= acc * acc else (dist * math.sqrt(jerk) / 2.0) ** (2.0 / 3.0)
    if v * jerk >= acc * acc:
        tj, ta = acc / jerk, v / acc - acc / jerk
    else:
        tj, ta = math.sqrt(v / jerk), 0.0
    tc = max(dist / v - t_acc(v), 0.0)
    j = s * jerk
    return MotionProfile.from_segments([(tj, j, 0.0), (ta, 0.0, None), (tj, -j, None), (tc, 0.0, 0.0),
                                        (tj, -j, 0.0), (ta, 0.0, None), (tj, j, None)])


def plan(kind: str, distance_m: float, max_speed_m_s: float, acceleration_m_s2: float,
         jerk_m_s3: float | None = None) -> MotionProfile:
    """One move of ``kind`` (``"trapezoidal"`` or ``"s-curve"``, which needs ``jerk_m_s3``).

    Returns
    -------
    MotionProfile
    """
    if kind == "trapezoidal":
        return trapezoidal(distance_m, max_speed_m_s, acceleration_m_s2)
    if kind == "s-curve":
        if jerk_m_s3 is None:
            raise ValueError("kind = 's-curve' needs jerk_m_s3; expected a jerk limit in m/s^3")
        return s_curve(distance_m, max_speed_m_s, acceleration_m_s2, jerk_m_s3)
    raise ValueError(f"kind = {kind!r}; expected one of {', '.join(PROFILE_KINDS)}")


def out_and_back(kind: str, distance_m: float, max_speed_m_s: float, acceleration_m_s2: float,
                 jerk_m_s3: float | None = None, *, dwell_s: float = 0.0, start_s: float = 0.0) -> MotionProfile:
    """A move of ``distance_m`` (m), a dwell of ``dwell_s`` (s) at rest, and the move back to
    the start (a reversal), starting at ``start_s`` (s).

    Returns
    -------
    MotionProfile

    Examples
    --------
    >>> m = out_and_back("trapezoidal", 0.001, 0.01, 0.5, dwell_s=0.0)
    >>> abs(m.final_position) < 1e-15, round(float(np.max(m.at(np.linspace(0, m.duration, 101))[0])), 6)
    (True, 0.001)
    """
    go = plan(kind, distance_m, max_speed_m_s, acceleration_m_s2, jerk_m_s3)
    back = plan(kind, -distance_m, max_speed_m_s, acceleration_m_s2, jerk_m_s3)
    return go.then(back, dwell_s).shifted(float(start_s)) if start_s else go.then(back, dwell_s)
