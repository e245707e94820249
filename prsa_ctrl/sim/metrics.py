"""Load-step and robustness metrics.

Sign convention: the speed error is ``e = setpoint - speed`` (rad/s), so a load increase that
slows the nut gives a positive error and a positive IE, and a load decrease (the nut speeds
up) a negative one; peak excursion, overshoot and recovery follow the step's direction. Integrals run from the step to the end
of the record, with time measured from the step for ITAE.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from typing import Sequence

__all__ = [
    "LoadStepMetrics",
    "SetpointStepMetrics",
    "setpoint_step_metrics",
    "ProfileMetrics",
    "Margins",
    "load_step_metrics",
    "profile_metrics",
    "margins_from_response",
    "DEFAULT_BAND",
    "relative_difference",
    "metric_resolution",
]

#: Recovery band: the error must stay within this fraction of the peak drop (around the
#: setpoint) from the recovery time to the end of the record.
DEFAULT_BAND = 0.05


def relative_difference(predicted: float, verified: float) -> float | None:
    """The one definition of "difference" in reports and warnings: ``(predicted - verified) /
    |verified|``, how far the linear prediction is from the verified (nonlinear) value, as a
    fraction; ``None`` where it is undefined (a non-finite value, a verified value of zero).

    Examples
    --------
    >>> relative_difference(1.1, 1.0), relative_difference(1.0, 0.0)
    (0.10000000000000009, None)
    """
    if isinstance(predicted, bool) or isinstance(verified, bool):
        return None
    try:
        p, v = float(predicted), float(verified)
    except (TypeError, ValueError):
        return None
    if not (math.isfinite(p) and math.isfinite(v)) or v == 0:
        return None
    return (p - v) / abs(v)


#: Metric name -> its kind, for :func:`metric_resolution`.
_KINDS = {"peak_drop_rad_s": "speed", "peak_deviation_rad_s": "speed", "steady_state_error_rad_s": "speed",
          "overshoot_rad_s": "speed", "rms_error_rad_s": "speed", "final_error_rad_s": "speed",
          "peak_time_s": "time", "recovery_time_s": "time", "ie": "ie", "iae": "ie", "itae": "itae", "ise": "ise",
          "peak_torque_n_m": "torque"}


def metric_resolution(name: str, *, accuracy: float, drop_rad_s: float, sample_time_s: float, window_s: float,
                      torque_limit_n_m: float) -> float:
    """Smallest value of a metric that a verified run resolves: the verification's accuracy
    expressed in the metric's unit. A relative difference between a prediction and a verified
    value means something only where both exceed it.

    Parameters
    ----------
    name : str
        Metric attribute (``"steady_state_error_rad_s"``, ``"iae"``, ...).
    accuracy : float
        The scene's relative accuracy (a fraction of the peak drop).
    drop_rad_s : float, rad/s
        The verified peak drop (deviation) the accuracy refers to.
    sample_time_s : float, s
        Controller sample time (the time grid of the sampled record).
    window_s : float, s
        Length of the integration window (step to the end of the record).
    torque_limit_n_m : float, N m

    Returns
    -------
    float
        Speeds: ``accuracy * drop`` (rad/s); times: one sample (s); IE/IAE: the speed
        resolution over one sample (rad); ITAE: that times the window (rad s); ISE: the squared
        speed resolution over one sample (rad^2/s); torques: 0.1 % of the torque limit (N m);
        0 for an unknown name.

    Examples
    --------
    >>> metric_resolution("steady_state_error_rad_s", accuracy=0.01, drop_rad_s=3.65, sample_time_s=2.5e-4,
    ...                   window_s=0.3, torque_limit_n_m=3.0)
    0.0365
    """
    w = accuracy * abs(drop_rad_s)
    return {"speed": w, "time": sample_time_s, "ie": w * sample_time_s, "itae": w * sample_time_s * window_s,
            "ise": w * w * sample_time_s, "torque": 1e-3 * torque_limit_n_m}.get(_KINDS.get(name, ""), 0.0)


@dataclass(frozen=True)
class LoadStepMetrics:
    """Disturbance-rejection metrics of one load step (signed for load decreases).

    A load increase slows the nut (the speed *drops*), a decrease speeds it up (the speed
    *rises*); ``direction`` says which, and every metric follows it.

    Attributes
    ----------
    peak_drop_rad_s : float
        Size of the largest excursion of the speed from its last pre-step sample (the setpoint
        when the record starts at the step) in the disturbance's direction, rad/s (>= 0): the
        drop for a load increase, the rise for a decrease.
    peak_deviation_rad_s : float
        The same excursion, signed: speed minus pre-step speed at the extreme (negative for a
        drop, positive for a rise), rad/s.
    peak_time_s : float
        Time from the step to the extreme, s.
    recovery_time_s : float
        Time from the step after which ``|e|`` stays within the band, s (``inf`` if never).
    ie, iae, itae, ise : float
        Integrals of e, |e|, t|e| and e^2 after the step (rad, rad, rad s, rad^2/s); ``ie`` is
        negative when the speed rises above the setpoint.
    steady_state_error_rad_s : float
        Mean error over the last 10 % of the record, rad/s.
    overshoot_rad_s : float
        Largest excursion past the setpoint on the other side after the extreme (a rise above
        it after a drop, a fall below it after a rise), rad/s (>= 0).
    peak_torque_n_m : float
        Largest |motor torque| after the step, N m (``nan`` when no torque was given).
    saturated : bool
        Whether the torque reached the limit (within 0.1 %).
    direction : int
        +1 for a load increase (speed drops), -1 for a decrease (speed rises).
    """

    peak_drop_rad_s: float
    peak_time_s: float
    recovery_time_s: float
    ie: float
    iae: float
    itae: float
    ise: float
    steady_state_error_rad_s: float
    overshoot_rad_s: float
    peak_torque_n_m: float
    saturated: bool
    peak_deviation_rad_s: float = 0.0
    direction: int = 1

    def as_dict(self) -> dict[str, float | bool | None]:
        """JSON-friendly dict (``inf``/``nan`` become ``None``)."""
        out: dict[str, float | bool | None] = {}
        for k, v in asdict(self).items():
            out[k] = None if isinstance(v, float) and not math.isfinite(v) else v
        return out


def _trapz(y: NDArray[np.float64], t: NDArray[np.float64]) -> float:
    return float(np.sum(0.5 * (y[1:] + y[:-1]) * np.diff(t)))


def load_step_metrics(
    time: ArrayLike,
    speed: ArrayLike,
    setpoint: float,
    step_time: float,
    torque: ArrayLike | None = None,
    torque_limit: float | None = None,
    band: float = DEFAULT_BAND,
    direction: int | None = None,
) -> LoadStepMetrics:
    """Metrics of a speed response to a load step at ``step_time``.

    Parameters
    ----------
    time : array, s
    speed : array, rad/s
    setpoint : float, rad/s
    step_time : float, s
        Time of the load step; it must lie within the record, with at least two samples after it.
    torque : array, N m, optional
    torque_limit : float, N m, optional
    band : float
        Recovery band as a fraction of the peak excursion (default 5 %).
    direction : {1, -1}, optional
        +1 for a load increase (the speed drops), -1 for a decrease (it rises). Default: the
        sign of the larger excursion of the response.

    Examples
    --------
    >>> import numpy as np
    >>> t = np.linspace(0, 10, 10001)
    >>> bump = np.where(t >= 1, (t - 1) * np.exp(-(t - 1)), 0)
    >>> m = load_step_metrics(t, 1 - bump, 1.0, 1.0)
    >>> round(m.peak_drop_rad_s, 4), round(m.peak_time_s, 3), round(m.ie, 3)
    (0.3679, 1.0, 0.999)
    >>> up = load_step_metrics(t, 1 + bump, 1.0, 1.0, direction=-1)
    >>> round(up.peak_deviation_rad_s, 4), round(up.ie, 3)
    (0.3679, -0.999)
    """
    t = np.asarray(time, dtype=float)
    y = np.asarray(speed, dtype=float)
    if t.ndim != 1 or t.shape != y.shape or t.size < 3:
        raise ValueError(f"time and speed must be 1-D arrays of equal length >= 3; got {t.shape} and {y.shape}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(y))):
        raise ValueError("time and speed must be finite")
    if np.any(np.diff(t) <= 0):
        raise ValueError("time must increase strictly")
    if not (isinstance(step_time, (int, float, np.floating)) and math.isfinite(step_time)):
        raise ValueError(f"step_time = {step_time!r} s; expected a finite time inside the record")
    after = t >= step_time
    if after.sum() < 2:
        raise ValueError(f"step_time = {step_time!r} s; expected a time inside the record [{t[0]}, {t[-1]}] s")
    if not 0 < band < 1:
        raise ValueError(f"band = {band!r}; expected a fraction in (0, 1)")
    if direction not in (None, 1, -1):
        raise ValueError(f"direction = {direction!r}; expected 1 (load increase), -1 (decrease) or None")
    before = ~after
    y_pre = float(y[before][-1]) if before.any() else float(setpoint)
    ta, ya = t[after], y[after]
    ts = ta - ta[0]
    e = setpoint - ya
    if direction is None:
        direction = 1 if (y_pre - ya.min()) >= (ya.max() - y_pre) else -1
    # In the disturbance's own direction: s * (y_pre - y) grows as the speed departs.
    dev = direction * (y_pre - ya)
    i_ext = int(np.argmax(dev))
    drop = max(float(dev[i_ext]), 0.0)
    tol = band * drop
    outside = np.flatnonzero(np.abs(e) > tol) if drop > 0 else np.array([], dtype=int)
    if outside.size == 0:
        recovery = 0.0
    elif outside[-1] == e.size - 1:
        recovery = math.inf
    else:
        recovery = float(ts[outside[-1] + 1])
    tail = ts >= 0.9 * ts[-1]
    overshoot = max(float(np.max(-direction * (setpoint - ya[i_ext:]))), 0.0)
    if torque is not None:
        tq = np.abs(np.asarray(torque, dtype=float)[after])
        peak_t = float(tq.max())
        sat = bool(torque_limit is not None and peak_t >= 0.999 * torque_limit)
    else:
        peak_t, sat = math.nan, False
    return LoadStepMetrics(
        peak_drop_rad_s=drop,
        peak_time_s=float(ts[i_ext]),
        recovery_time_s=recovery,
        ie=_trapz(e, ta),
        iae=_trapz(np.abs(e), ta),
        itae=_trapz(ts * np.abs(e), ta),
        ise=_trapz(e * e, ta),
        steady_state_error_rad_s=float(e[tail].mean()),
        overshoot_rad_s=overshoot,
        peak_torque_n_m=peak_t,
        saturated=sat,
        peak_deviation_rad_s=-direction * drop,
        direction=direction,
    )


#: Settling band of a setpoint step: the speed stays within this fraction of the step size.
SETTLING_BAND = 0.02


@dataclass(frozen=True)
class SetpointStepMetrics:
    """Setpoint-step response metrics (the step response a drive engineer reads).

    Attributes
    ----------
    step_rad_s : float
        Size of the setpoint step (signed), rad/s.
    overshoot_percent : float
        Largest excursion beyond the new setpoint in the step's direction, % of the step
        size (0 when the speed never passes it).
    rise_time_s : float
        10 % to 90 % rise time: from the first crossing of 10 % of the step to the first
        crossing of 90 %, s (linear interpolation between samples; ``inf`` if 90 % is never reached).
    settling_time_s : float
        2 % settling time: from the step until the speed stays within 2 % of the step size
        around the new setpoint up to the end of the window, s (interpolated; ``inf`` if it is
        outside at the end).
    """

    step_rad_s: float
    overshoot_percent: float
    rise_time_s: float
    settling_time_s: float

    def as_dict(self) -> dict[str, float | None]:
        return {k: (None if not math.isfinite(v) else v) for k, v in asdict(self).items()}


def _crossing(t: NDArray[np.float64], x: NDArray[np.float64], level: float) -> float:
    """First time ``x`` reaches ``level`` (from below), linearly interpolated; ``inf`` if never."""
    idx = np.nonzero(x >= level)[0]
    if idx.size == 0:
        return math.inf
    k = int(idx[0])
    if k == 0:
        return float(t[0])
    return float(t[k - 1] + (level - x[k - 1]) * (t[k] - t[k - 1]) / (x[k] - x[k - 1]))


def setpoint_step_metrics(time: ArrayLike, speed: ArrayLike, step_time_s: float, initial_rad_s: float,
                          final_rad_s: float, band: float = SETTLING_BAND) -> SetpointStepMetrics:
    """Overshoot (%), 10-90 % rise time and settling time of a setpoint step.

    Parameters
    ----------
    time : array, s
        The window: from (at or before) the step to the next change or the end of the record.
    speed : array, rad/s
    step_time_s : float, s
    initial_rad_s, final_rad_s : float, rad/s
        Setpoint before and after the step (not equal).
    band : float
        Settling band, fraction of the step size (2 %).

    Returns
    -------
    SetpointStepMetrics

    Examples
    --------
    >>> import numpy as np
    >>> t = np.linspace(0.0, 1.0, 100001)
    >>> m = setpoint_step_metrics(t, 1.0 - np.exp(-t / 0.05), 0.0, 0.0, 1.0)
    >>> round(m.rise_time_s, 5), round(m.settling_time_s, 5), m.overshoot_percent   # 0.05 ln 9, 0.05 ln 50
    (0.10986, 0.1956, 0.0)
    """
    t = np.asarray(time, dtype=float)
    y = np.asarray(speed, dtype=float)
    if t.ndim != 1 or t.shape != y.shape or t.size < 3 or not (np.all(np.isfinite(t)) and np.all(np.isfinite(y))):
        raise ValueError(f"time and speed must be finite 1-D arrays of equal length >= 3; got {t.shape} and {y.shape}")
    step = float(final_rad_s) - float(initial_rad_s)
    if not math.isfinite(step) or step == 0:
        raise ValueError(f"initial_rad_s = {initial_rad_s!r}, final_rad_s = {final_rad_s!r}; expected a setpoint step "
                         "(two different finite values)")
    sel = t >= step_time_s
    t, y = t[sel], y[sel]
    if t.size < 3:
        raise ValueError(f"step_time_s = {step_time_s!r}; expected a time with at least 3 samples after it")
    x = (y - initial_rad_s) / step  # normalised: 0 before, 1 at the new setpoint, rising
    t90 = _crossing(t, x, 0.9)
    rise = t90 - _crossing(t, x, 0.1) if math.isfinite(t90) else math.inf
    overshoot = max(0.0, float(np.max(x)) - 1.0) * 100.0
    outside = np.nonzero(np.abs(x - 1.0) > band)[0]
    if outside.size == 0:
        settle = 0.0
    elif outside[-1] == t.size - 1:
        settle = math.inf
    else:
        k = int(outside[-1])  # last sample outside; interpolate where |x - 1| comes back to the band
        d0, d1 = abs(x[k] - 1.0), abs(x[k + 1] - 1.0)
        settle = float(t[k] + (d0 - band) * (t[k + 1] - t[k]) / (d0 - d1) - step_time_s)
    return SetpointStepMetrics(step, overshoot, rise, settle)


def _setpoint_steps(t: NDArray[np.float64], r: NDArray[np.float64]) -> list[tuple[float, float, float]]:
    """Setpoint steps of a sampled profile, ``(time s, before, after)``: a change between two
    samples with the setpoint held on the sample before and after (a ramp changes on every
    sample and is no step)."""
    d = np.diff(r)
    out = []
    for k in np.nonzero(d != 0)[0]:
        held_before = k == 0 or d[k - 1] == 0
        held_after = k + 1 >= d.size or d[k + 1] == 0
        if held_before and held_after:
            out.append((float(t[k + 1]), float(r[k]), float(r[k + 1])))
    return out


@dataclass(frozen=True)
class ProfileMetrics:
    """Tracking metrics of a duty-cycle record (load and/or setpoint profile).

    The error is ``e = setpoint - speed`` at every sample of the whole record (the setpoint
    as the scene's profile gives it at that time), so the integrals cover every event of the
    duty cycle; time for ITAE runs from the start of the record.

    Attributes
    ----------
    ie, iae, itae, ise : float
        Integrals of e, |e|, t|e| and e^2 over the record (rad, rad, rad s, rad^2/s).
    peak_deviation_rad_s : float
        The error of largest magnitude, signed (positive: the nut is slower than the
        setpoint), rad/s.
    peak_time_s : float
        When it happens, s from the start of the record.
    rms_error_rad_s : float
        Root-mean-square error over the record, rad/s.
    final_error_rad_s : float
        Mean error over the last 10 % of the record, rad/s.
    peak_torque_n_m : float
        Largest |motor torque|, N m (``nan`` without a torque record).
    saturated_fraction : float
        Fraction of the samples with the torque at its limit (within 0.1 %).
    saturated : bool
        Whether the torque reached the limit.
    steps : tuple of LoadStepMetrics
        The load-step metrics of every load step of the profile, each over the window from
        the step to the next change of the profile (or the end of the record).
    step_times_s : tuple of float
        The times of those steps, s.
    setpoint_steps : tuple of SetpointStepMetrics
        Overshoot, rise and settling time of every setpoint step of the profile (a jump
        between held values), each over the window to the next change (or the end).
    setpoint_step_times_s : tuple of float
        The times of those steps, s.
    """

    ie: float
    iae: float
    itae: float
    ise: float
    peak_deviation_rad_s: float
    peak_time_s: float
    rms_error_rad_s: float
    final_error_rad_s: float
    peak_torque_n_m: float
    saturated_fraction: float
    saturated: bool
    steps: tuple = ()
    step_times_s: tuple = ()
    setpoint_steps: tuple = ()
    setpoint_step_times_s: tuple = ()

    @property
    def peak_drop_rad_s(self) -> float:
        """``|peak_deviation_rad_s|`` (the size of the largest error), rad/s."""
        return abs(self.peak_deviation_rad_s)

    def as_dict(self) -> dict:
        """JSON-friendly dict (``inf``/``nan`` become ``None``; steps as dicts)."""
        out: dict = {}
        for k in ("ie", "iae", "itae", "ise", "peak_deviation_rad_s", "peak_time_s", "rms_error_rad_s",
                  "final_error_rad_s", "peak_torque_n_m", "saturated_fraction", "saturated"):
            v = getattr(self, k)
            out[k] = None if isinstance(v, float) and not math.isfinite(v) else v
        out["steps"] = [dict(m.as_dict(), time_s=t) for m, t in zip(self.steps, self.step_times_s)]
        out["setpoint_steps"] = [dict(m.as_dict(), time_s=t) for m, t in zip(self.setpoint_steps,
                                                                             self.setpoint_step_times_s)]
        return out


def profile_metrics(
    time: ArrayLike,
    speed: ArrayLike,
    setpoint: ArrayLike,
    torque: ArrayLike | None = None,
    torque_limit: float | None = None,
    load_steps: Sequence[tuple[float, float]] = (),
    breaks: Sequence[float] = (),
    band: float = DEFAULT_BAND,
) -> ProfileMetrics:
    """Metrics of a speed record under a duty cycle.

    Parameters
    ----------
    time : array, s
    speed : array, rad/s
    setpoint : array, rad/s
        The setpoint at each time (a profile evaluated at ``time``), or a constant.
    torque : array, N m, optional
    torque_limit : float, N m, optional
    load_steps : sequence of (time s, signed size N)
        The load steps of the profile; each gets :func:`load_step_metrics` on its window.
    breaks : sequence of float, s
        Every change of the profiles (steps and ramp kinks): a step's window ends at the next.
    band : float
        Recovery band of the step metrics.

    Examples
    --------
    >>> import numpy as np
    >>> t = np.linspace(0.0, 1.0, 1001)
    >>> m = profile_metrics(t, np.where(t < 0.5, 10.0, 9.0), 10.0)
    >>> round(m.iae, 3), m.peak_deviation_rad_s, round(m.final_error_rad_s, 3)
    (0.5, 1.0, 1.0)
    """
    t = np.asarray(time, dtype=float)
    y = np.asarray(speed, dtype=float)
    r = np.broadcast_to(np.asarray(setpoint, dtype=float), y.shape)
    if t.ndim != 1 or t.shape != y.shape or t.size < 3:
        raise ValueError(f"time and speed must be 1-D arrays of equal length >= 3; got {t.shape} and {y.shape}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(y)) and np.all(np.isfinite(r))):
        raise ValueError("time, speed and setpoint must be finite")
    if np.any(np.diff(t) <= 0):
        raise ValueError("time must increase strictly")
    e = r - y
    tt = t - t[0]
    i_pk = int(np.argmax(np.abs(e)))
    tail = tt >= 0.9 * tt[-1]
    if torque is not None:
        tq = np.abs(np.asarray(torque, dtype=float))
        peak_t = float(tq.max())
        frac = float(np.mean(tq >= 0.999 * torque_limit)) if torque_limit is not None else 0.0
    else:
        peak_t, frac = math.nan, 0.0
    steps, times = [], []
    cuts = sorted(float(b) for b in breaks)
    for t_s, size in load_steps:
        nxt = next((b for b in cuts if b > t_s + 1e-12), math.inf)
        win = (t >= t_s - (t[1] - t[0]) * 1.5) & (t < nxt)
        if np.sum(t[win] >= t_s) < 3:
            continue
        steps.append(load_step_metrics(t[win], y[win], float(r[win][-1]), t_s,
                                       None if torque is None else np.asarray(torque, float)[win], torque_limit,
                                       band=band, direction=1 if size > 0 else -1))
        times.append(float(t_s))
    sp_steps, sp_times = [], []
    if r.ndim == 1 and r.shape == t.shape:
        for t_s, r0, r1 in _setpoint_steps(t, r):
            nxt = next((b for b in cuts if b > t_s + 1e-12), math.inf)
            win = (t >= t_s) & (t < nxt)
            if np.sum(win) >= 3:
                sp_steps.append(setpoint_step_metrics(t[win], y[win], t_s, r0, r1, SETTLING_BAND))
                sp_times.append(t_s)
    return ProfileMetrics(
        ie=_trapz(e, t), iae=_trapz(np.abs(e), t), itae=_trapz(tt * np.abs(e), t), ise=_trapz(e * e, t),
        peak_deviation_rad_s=float(e[i_pk]), peak_time_s=float(tt[i_pk]),
        rms_error_rad_s=float(np.sqrt(np.mean(e * e))), final_error_rad_s=float(e[tail].mean()),
        peak_torque_n_m=peak_t, saturated_fraction=frac, saturated=frac > 0,
        steps=tuple(steps), step_times_s=tuple(times),
        setpoint_steps=tuple(sp_steps), setpoint_step_times_s=tuple(sp_times),
    )


@dataclass(frozen=True)
class Margins:
    """Robustness of a loop ``L`` from its frequency response on a dense grid.

    Attributes
    ----------
    ms, mt : float
        Peak sensitivity max|1/(1+L)| and peak complementary sensitivity max|L/(1+L)|.
    gm_db : float
        Gain margin, dB (``inf`` if the phase never crosses -180 deg).
    pm_deg : float
        Phase margin, degrees (``inf`` if |L| never crosses 1).
    wc_rad_s : float
        Gain-crossover frequency, rad/s (``nan`` if none).
    """

    ms: float
    mt: float
    gm_db: float
    pm_deg: float
    wc_rad_s: float

    def as_dict(self) -> dict[str, float | None]:
        return {k: (None if not math.isfinite(v) else v) for k, v in asdict(self).items()}


def _bisect(f, lo: NDArray, hi: NDArray, f_lo: NDArray, n: int = 60) -> NDArray:
    """Roots of ``f`` (array in, array out) bracketed by ``[lo, hi]`` (``f_lo``: its values at
    ``lo``), vectorised over the brackets: ``n`` bisections, fewer where a bisection leaves every
    bracket as it was (the brackets are adjacent floating-point numbers: every further bisection
    would evaluate ``f`` at the same points and change nothing, so the result is the same)."""
    lo, hi = lo.copy(), hi.copy()
    for _ in range(n):
        mid = 0.5 * (lo + hi)
        same = np.sign(f(mid)) == np.sign(f_lo)
        new_lo, new_hi = np.where(same, mid, lo), np.where(same, hi, mid)
        if np.array_equal(new_lo, lo) and np.array_equal(new_hi, hi):
            break
        lo, hi = new_lo, new_hi
    return 0.5 * (lo + hi)


def _exact_margins(f, w: NDArray[np.float64], L: NDArray[np.complex128]) -> tuple[float, float, float]:
    """Gain margin (dB), phase margin (deg) and gain crossover (rad/s) of the loop ``f(omega)``
    (exact ``L(j omega)``, vectorised), chosen as :func:`margins_from_response`
    chooses them on the grid ``(w, L)`` (the smallest over all crossings), each crossing located
    by bisection in log frequency between its grid neighbours (to ~1e-15 relative)."""
    lm, phase = np.log(np.abs(L)), np.unwrap(np.angle(L))
    x = np.log(w)
    pm, wc = math.inf, math.nan
    i = np.flatnonzero(np.sign(lm[:-1]) * np.sign(lm[1:]) < 0)
    if i.size:
        r = _bisect(lambda xs: np.log(np.abs(f(np.exp(xs)))), x[i], x[i + 1], lm[i])
        ph = phase[i] + np.angle(f(np.exp(r)) / L[i])
        mar = np.degrees(np.mod(ph + math.pi, 2 * math.pi))
        mar = np.where(mar <= 180, mar, mar - 360)
        j = int(np.argmin(np.abs(mar)))
        pm, wc = float(mar[j]), float(math.exp(r[j]))
    gm = math.inf
    k = np.floor((phase + math.pi) / (2 * math.pi))
    i = np.flatnonzero(np.diff(k) != 0)
    if i.size:
        target = np.maximum(k[i], k[i + 1]) * 2 * math.pi - math.pi
        r = _bisect(lambda xs: phase[i] + np.angle(f(np.exp(xs)) / L[i]) - target, x[i], x[i + 1], phase[i] - target)
        m = np.abs(f(np.exp(r)))
        m = m[m > 0]
        if m.size:
            gm = float(np.min(-20 * np.log10(m)))
    return gm, pm, wc


def margins_from_response(omega: ArrayLike, loop: ArrayLike, response=None) -> Margins:
    """Ms, Mt, gain and phase margins and crossover from ``L(j omega)`` on a dense grid.

    Parameters
    ----------
    omega : array, rad/s
        Increasing frequencies.
    loop : array of complex
        Loop transfer ``L(j omega)`` at those frequencies.
    response : callable, optional
        The exact loop transfer, ``response(omega array) -> L array``: each crossing the grid
        brackets is then located by bisection on it (to ~1e-15 relative) instead of by linear
        interpolation (off by up to ~1e-4 relative in the crossover frequency).

    The smallest margins over all crossings are reported (python-control's
    ``stability_margins`` alone can report an infinite stability margin where the grid misses
    the peak).
    """
    w = np.asarray(omega, dtype=float)
    L = np.asarray(loop, dtype=complex)
    s_mag = np.abs(1.0 / (1.0 + L))
    t_mag = np.abs(L / (1.0 + L))
    if response is not None:
        gm, pm, wc = _exact_margins(response, w, L)
        return Margins(ms=float(s_mag.max()), mt=float(t_mag.max()), gm_db=gm, pm_deg=pm, wc_rad_s=wc)
    mag = np.abs(L)
    phase = np.unwrap(np.angle(L))
    # Gain crossovers: |L| crosses 1.
    pm, wc = math.inf, math.nan
    lm = np.log(mag)
    for i in np.flatnonzero(np.sign(lm[:-1]) * np.sign(lm[1:]) < 0):
        f = lm[i] / (lm[i] - lm[i + 1])
        ph = phase[i] + f * (phase[i + 1] - phase[i])
        margin = math.degrees((ph + math.pi) % (2 * math.pi))
        margin = margin if margin <= 180 else margin - 360
        if abs(margin) < abs(pm):
            pm, wc = margin, float(w[i] + f * (w[i + 1] - w[i]))
    # Phase crossovers: phase crosses -180 deg (mod 360).
    gm = math.inf
    k = np.floor((phase + math.pi) / (2 * math.pi))
    for i in np.flatnonzero(np.diff(k) != 0):
        target = (max(k[i], k[i + 1])) * 2 * math.pi - math.pi
        f = (target - phase[i]) / (phase[i + 1] - phase[i])
        m = mag[i] + f * (mag[i + 1] - mag[i])
        gm = min(gm, -20 * math.log10(m)) if m > 0 else gm
    return Margins(ms=float(s_mag.max()), mt=float(t_mag.max()), gm_db=gm, pm_deg=pm, wc_rad_s=wc)
