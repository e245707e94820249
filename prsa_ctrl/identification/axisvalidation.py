"""Validation of a linear-axis fit that can say no (``prsa-fit LOG... --log-format F``, rigid and
``--fidelity compliant``; the app's linear-axis calibration): each log replayed closed loop from
its reference through the plant **as written**, and its residual tested the way an identification
engineer tests a servo axis's model.

The replay residual of a right model is what the model cannot know: the encoder's noise and the
closed loop's response to unlogged disturbances. It is never white in closed loop (the loop filters
the disturbance; measured on the independent generators of the tests, a Ljung-Box Q of 10^4 against
a 5 % limit of 68 for the right model), so whiteness is reported, not tested. What a right model's
residual cannot hold is anything the log's **own excitation** or the **position** predicts:

1. **Residual-excitation cross-correlation** (the classic ``resid`` test in its closed-loop form:
   against the external signals, the reference and the drive's test signal, which the loop does not
   feed back; the command itself is correlated with the residual through the feedback even for a
   right model). :func:`excitation_share`: the share of the one-sample speed residual's power that
   an FIR of the reference's acceleration and the test signal (lags 0..:data:`FIR_LAGS` samples)
   predicts **out of sample** (fitted on alternate blocks of :data:`CV_BLOCK` samples, scored on
   the others, and the other way round): a model that misses a response to the excitation (a mode,
   a delay) leaves a residual the excitation predicts; noise is predicted by nothing (share about 0
   or below). The log fails at :data:`EXCITATION_SHARE`.
2. **A resonance in the residual** (:data:`prsa_ctrl.identification.validation.RESONANCE_SHARE`,
   as the screw path) names the mode a residual that 1. refuses holds (its frequency), and is not a
   test of its own here: in closed loop a resonance the excitation does not predict is the loop's
   response to the encoder's quantisation, not a mode (measured on the noise-free generator of
   tests/identification/axis_generator.py, a rigid axis the model has exactly: 78 % of the speed
   residual within 15 % of 384 Hz at 6.4 x the quantisation floor, none of it predicted by the
   excitation).
3. **A position-periodic force** (cogging, a screw's pitch error, a rail's waviness):
   :func:`periodic_share`: the share of the force residual (logged minus replayed drive force, N)
   while the axis moves that one sinusoid of the position explains, out of sample as in 1., the
   period searched from a third of the travel down to four samples of motion at the peak speed.
   The log fails at :data:`PERIODIC_SHARE`.
4. **The replay error against the noise floor** (the screw path's allowance,
   :mod:`prsa_ctrl.identification.validation`): within
   :data:`~prsa_ctrl.identification.validation.NOISE_FACTOR` x the floor the data show (the
   position's third difference, :func:`prsa_ctrl.identification.validation.noise_floor`), or a
   replay fit of at least :data:`~prsa_ctrl.identification.validation.FIT_MIN_PERCENT`.
5. **A friction law the model lacks** (:mod:`prsa_ctrl.identification.axisfriction`): the
   friction the force balance shows (drive force minus the inertial force), averaged by speed and
   by position, in both halves of the log, against the fitted Coulomb + viscous law: a Stribeck
   rise, a friction not linear in the speed, or one that changes along the travel. The log fails
   when the spread of the departures reaches
   :data:`~prsa_ctrl.identification.axisfriction.FRICTION_DEPARTURE` of the Coulomb level (the
   closed-loop replay hides these: the loop corrects the speed error within a few samples and the
   fit bends its friction terms toward the law it lacks).

Why these thresholds (measured, one log of 3,000 or 6,000 samples at 1 kHz each, the tests'
generators; the EMPS record): a right model leaves an excitation share of -0.06..0.01 and a
periodic share of -0.04..0.03; the EMPS record, fitted rigid, 0.06 and 0.0002; a second mass the
rigid model lacks 0.67, a third mass the two-mass model lacks 0.40 (at 1.7 x the noise floor,
where rule 4 alone passes it), a 50 N cogging force of 20 mm period 0.96. A fifth of the residual
power predicted by something the model should have explained is far from chance and is a model
error a tuner would inherit. The friction test's threshold (5.) is justified in its module.

With more than one log each log left out is replayed by the plant fitted on the others
(leave-one-out) under the same rule. A fit that does not pass has a one-line :func:`diagnosis`
naming the most likely missing physics; ``prsa-fit`` then ends with exit 3 and no plant file
unless ``--force``.
"""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

# A log fails when one period of the position explains PERIODIC_SHARE of its force residual (3.);
# the out-of-sample split's blocks are CV_BLOCK samples (1., 3.): the position-periodic test's own.
from .periodic import CV_BLOCK, PERIODIC_SHARE, cv_share
from .axisfriction import FRICTION_DEPARTURE, friction_departure, friction_diagnosis, friction_words

__all__ = ["EXCITATION_SHARE", "PERIODIC_SHARE", "FRICTION_DEPARTURE", "FIR_LAGS", "CV_BLOCK", "excitation_share", "periodic_share",
           "speed_entry", "explained", "reasons", "diagnosis", "validate_axis", "refusal_line", "entry_report"]

#: A log fails when the excitation predicts this share of its replay residual (module docstring, 1.).
EXCITATION_SHARE = 0.2
#: Lags (samples) of the excitation's FIR (1.): 40 ms at 1 kHz, a lightly damped 100 Hz mode's decay.
FIR_LAGS = 40
#: At most this many spatial frequencies searched (3.).
_MAX_PERIODS = 2000
#: Singular values below this fraction of the largest are dropped from the out-of-sample least
#: squares: regressors that are (nearly) combinations of each other -- the lags of a reference that is
#: one sinusoid span two dimensions -- carry no independent excitation, and their tiny singular
#: values would turn noise into huge coefficients (measured: a share of -5.7e4 on a cosine reference).
RCOND = 1e-6


def _lagged(s: NDArray[np.float64], lags: int) -> NDArray[np.float64]:
    return np.column_stack([np.r_[np.zeros(k), s[:len(s) - k]] for k in range(lags + 1)])


def excitation_share(residual: NDArray[np.float64], reference_m, test_signal, sample_time_s: float,
                     skip: int) -> float:
    """Share of the one-sample speed residual (``n - 1`` samples, m/s) that an FIR of the
    reference's acceleration and the test signal (lags 0..:data:`FIR_LAGS`) predicts out of
    sample, from sample ``skip`` on (module docstring, 1.); 0 without an excitation."""
    cols = []
    if reference_m is not None:
        r = np.asarray(reference_m, float)
        acc = np.gradient(np.gradient(r, sample_time_s), sample_time_s)[:-1]
        if np.std(acc) > 0:
            cols.append(_lagged(acc / np.std(acc), FIR_LAGS))
    if test_signal is not None:
        d = np.asarray(test_signal, float)[:-1]
        if np.std(d) > 0:
            cols.append(_lagged((d - d.mean()) / np.std(d), FIR_LAGS))
    if not cols:
        return 0.0
    return cv_share(np.asarray(residual, float)[skip:], np.column_stack(cols)[skip:], rcond=RCOND)


def _best_frequency(y: NDArray[np.float64], q: NDArray[np.float64], freqs: NDArray[np.float64]) -> tuple[float, float]:
    """``(explained power, frequency)`` of the one sinusoid of ``q`` among ``freqs`` (cycles per m)
    that explains most of ``y`` (the 2-column least squares of each, by its normal equations)."""
    best, best_f = -math.inf, math.nan
    for a in range(0, len(freqs), 100):
        ph = 2 * math.pi * np.outer(freqs[a:a + 100], q)
        s, c = np.sin(ph), np.cos(ph)
        ss, cc, sc = (s * s).sum(1), (c * c).sum(1), (s * c).sum(1)
        ys, yc = s @ y, c @ y
        det = ss * cc - sc * sc
        with np.errstate(divide="ignore", invalid="ignore"):
            expl = np.where(det > 0, (cc * ys * ys - 2 * sc * ys * yc + ss * yc * yc) / det, 0.0)
        j = int(np.argmax(expl))
        if expl[j] > best:
            best, best_f = float(expl[j]), float(freqs[a + j])
    return best, best_f


def periodic_share(force_residual_n, position_m, sample_time_s: float, skip: int) -> tuple[float, float]:
    """``(share, period m)``: the one sinusoid of the position that explains most of the force
    residual (N) while the axis moves (above 5 % of its peak speed), and the share of it that
    sinusoid predicts out of sample (module docstring, 3.); ``(0, nan)`` when the axis barely moves."""
    y = np.asarray(force_residual_n, float)[skip:]
    q = np.asarray(position_m, float)[skip:]
    v = np.gradient(q, sample_time_s)
    vmax = float(np.max(np.abs(v))) if q.size else 0.0
    moving = np.abs(v) > 0.05 * vmax
    span = float(np.ptp(q[moving])) if np.any(moving) else 0.0
    if span <= 0 or np.count_nonzero(moving) < 4 * CV_BLOCK:
        return 0.0, math.nan
    y, q = y[moving] - y[moving].mean(), q[moving] - q[moving].min()
    f_lo, f_hi = 3.0 / span, 1.0 / (4.0 * vmax * sample_time_s)  # cycles per m
    if not f_hi > f_lo:
        return 0.0, math.nan
    step = max(0.25 / span, (f_hi - f_lo) / _MAX_PERIODS)
    best, best_f = _best_frequency(y, q, np.arange(f_lo, f_hi, step))
    best_f = _best_frequency(y, q, best_f + step * np.linspace(-1.0, 1.0, 41))[1]  # refined within the grid step
    ph = 2 * math.pi * best_f * q
    return cv_share(y, np.column_stack([np.sin(ph), np.cos(ph)]), rcond=RCOND), 1.0 / best_f


def speed_entry(replay, log, skip: int) -> dict:
    """The validation entry of one closed-loop replay (an
    :class:`~prsa_ctrl.identification.axis.AxisReplay` of ``log``): the one-sample speed of the log
    and of the replay (m/s, under the ``_rad_s`` names of
    :func:`prsa_ctrl.identification.validation.explained`'s entries) from sample ``skip`` on
    (:data:`~prsa_ctrl.identification.axis.METRIC_SKIP_SAMPLES`), the fit %, the error RMS, the
    noise floor, and the structure tests (module docstring): ``excitation_share``,
    ``periodic_share`` and ``periodic_period_m``."""
    from .common import fit_percent
    from .validation import noise_floor

    h = float(log.sample_time_s)
    meas = np.diff(np.asarray(replay.position_measured, float)) / h
    model = np.diff(np.asarray(replay.position_simulated, float)) / h
    finite = bool(np.all(np.isfinite(model)))
    floor = noise_floor(SimpleNamespace(nut_angle_rad=np.asarray(log.position_m, float), sample_time_s=h))
    e = {"finite": finite, "time_s": np.asarray(replay.time_s, float)[1:], "measured": meas, "model": model,
         "skip_samples": skip, "noise_floor_rad_s": floor}
    if not finite:
        return {**e, "fit_percent": -math.inf, "error_rms_rad_s": math.inf}
    a, b = meas[skip:], model[skip:]
    share, period = periodic_share(np.asarray(replay.force_measured) - np.asarray(replay.force_simulated),
                                   log.position_m, h, skip)
    return {**e, "fit_percent": fit_percent(a, b), "error_rms_rad_s": float(np.sqrt(np.mean((a - b) ** 2))),
            "excitation_share": excitation_share(meas - model, log.reference_m, log.test_signal, h, skip),
            "periodic_share": share, "periodic_period_m": period}


def _resonance(e: dict) -> tuple[float, float]:
    """``(frequency Hz, share)`` of the residual's largest peak above 10 Hz (module docstring, 2.)."""
    from .validation import resonance

    return resonance(e)


def structure(e: dict) -> list[str]:
    """What the residual of a finite entry holds that the model should have explained (module
    docstring, 1. and 3.), as words; empty when nothing."""
    out = []
    if e.get("excitation_share", 0.0) >= EXCITATION_SHARE:
        out.append(f"{100 * e['excitation_share']:.0f} % of the residual predicted by the reference and test signal")
    if e.get("periodic_share", 0.0) >= PERIODIC_SHARE:
        out.append(f"{100 * e['periodic_share']:.0f} % of the force residual periodic in the position (period "
                   f"{1e3 * e['periodic_period_m']:.4g} mm)")
    words = friction_words(e)
    if words:
        out.append(words)
    return out


def explained(e: dict) -> bool:
    """Whether one replay entry explains its log (module docstring): finite, no structure in its
    residual (1., 3.), and its error within the noise allowance or its fit % high enough (4.)."""
    from .validation import FIT_MIN_PERCENT, NOISE_FACTOR

    if not e.get("finite", False) or structure(e):
        return False
    return e["error_rms_rad_s"] <= NOISE_FACTOR * e["noise_floor_rad_s"] or e["fit_percent"] >= FIT_MIN_PERCENT


def entry_report(e: dict) -> dict:
    """The JSON part of one entry (no traces): the metrics, the structure tests and the residual's
    whiteness (reported, not tested)."""
    from .validation import resonance, whiteness

    out = {"fit_percent": e["fit_percent"], "error_rms_m_s": e["error_rms_rad_s"],
           "noise_floor_m_s": e["noise_floor_rad_s"], "skip_samples": e["skip_samples"], "explained": explained(e)}
    if e["finite"]:
        out["residual_peak_hz"], out["residual_peak_share"] = resonance(e)
        out["excitation_share"] = e["excitation_share"]
        out["periodic_share"], out["periodic_period_m"] = e["periodic_share"], e["periodic_period_m"]
        out["whiteness"] = whiteness((e["measured"] - e["model"])[e["skip_samples"]:])
    if "friction_departure" in e:
        out.update({k: e[k] for k in ("friction_departure", "friction_by", "friction_level_n", "friction_peak_speed_m_s",
                                      "friction_position_beyond_law_n", "friction_high",
                                      "friction_low", "friction_speed_bins", "friction_position_bins")})
    return out


def reasons(written: Mapping[str, dict], loo: Mapping[str, dict] | None) -> list[str]:
    """Why the fit does not pass (empty when it does): per log not explained by the written plant,
    or, left out, by the plant fitted on the others."""
    from .validation import FIT_MIN_PERCENT, NOISE_FACTOR

    def why(e):
        ratio = e["error_rms_rad_s"] / max(e["noise_floor_rad_s"], 1e-300)
        held = structure(e) if e["finite"] else []
        return (f"{e['fit_percent']:.1f} % (error {e['error_rms_rad_s']:.3g} m/s, {ratio:.3g} x its noise floor "
                f"{e['noise_floor_rad_s']:.3g} m/s" + "".join(f"; {w}" for w in held) + ")")
    expected = (f"; expected no structure in the residual and <= {NOISE_FACTOR:g} x the floor or >= "
                f"{FIT_MIN_PERCENT:g} %")
    out = [f"{n}: the written plant replays it at {why(e)}{expected}" for n, e in written.items() if not explained(e)]
    for n, e in (loo or {}).items():
        if "failed" in e:
            out.append(f"{n}: the fit on the other logs failed ({e['failed']})")
        elif not explained(e):
            out.append(f"{n}: left out, the plant fitted on the other logs replays it at {why(e)}")
    return out


def diagnosis(written: Mapping[str, dict], mode_hz: float | None, loo: Mapping[str, dict] | None = None,
              unidentified: Sequence[str] = ()) -> str:
    """One line naming the most likely missing physics of a fit whose written plant does not
    explain the logs, tested in this order: wrong units or coordinates (no log replayed better than
    its mean); a response the model lacks (a residual the excitation predicts; a mode, named with
    its frequency, when that residual is a resonance: ``mode_hz`` None for a rigid plant, else its
    fitted mode); a position-periodic force; a friction law the model lacks (a Stribeck rise, a
    friction not linear in the speed or changing along the travel: :mod:`.axisfriction`);
    a failure of the fit (a cross-validation fit that failed while every log is explained); else
    the friction model. ``unidentified``: the fit's friction keys held or at a bound, as words (a
    friction law the force balance shows but the fit missed names them)."""
    from .validation import FIT_FAILURE, RESONANCE_SHARE

    bad = {n: e for n, e in written.items() if not explained(e)}
    if written and max(e["fit_percent"] for e in written.values()) < 0.0:
        return ("wrong units or coordinates: no log is replayed better than its mean (check the command's gain and "
                "unit, the position unit and the controller in --log-format)")
    judged = [(n, e) for n, e in (bad or written).items() if e["finite"]]
    rigid = mode_hz is None
    model = "the rigid model" if rigid else f"the two-mass model (mode {mode_hz:.4g} Hz)"
    remedy = ("fit --fidelity compliant, with --frf or a test signal" if rigid else
              "a third mass, or a second mass the start missed: give --frf with the axial mode")
    exc = sorted(((e.get("excitation_share", 0.0), n, e) for n, e in judged), key=lambda x: x[0], reverse=True)
    if exc and exc[0][0] >= EXCITATION_SHARE:
        share, n, e = exc[0]
        fp, peak = _resonance(e)
        said = f"{100 * share:.0f} % of the replay residual of {n} is predicted by the reference and test signal"
        if peak >= RESONANCE_SHARE:  # a response to the excitation that is a resonance: a mode, located
            return (f"{'second mass' if rigid else 'a further mode'}: {said}, and {100 * peak:.0f} % of it lies within "
                    f"15 % of {fp:.4g} Hz, a resonance {model} does not reproduce ({remedy})")
        return (f"unmodelled dynamics: {said}, a response {model} lacks (a {'second' if rigid else 'further'} mass: "
                f"{remedy}; or the command delay, [controller] command_delay_samples)")
    per = sorted(((e.get("periodic_share", 0.0), e.get("periodic_period_m", math.nan), n) for n, e in judged),
                 reverse=True)
    if per and per[0][0] >= PERIODIC_SHARE:
        share, period, n = per[0]
        return (f"position-periodic force: {100 * share:.0f} % of the force residual of {n} while it moves follows "
                f"one period of {1e3 * period:.4g} mm of the position (cogging, a pitch error or a waviness; the model "
                "has no force that depends on the position)")
    fr = sorted(((e.get("friction_departure", 0.0), n) for n, e in judged), reverse=True)
    if fr and fr[0][0] >= FRICTION_DEPARTURE:
        return friction_diagnosis(dict(judged)[fr[0][1]], fr[0][1], unidentified)
    failed = {n: e["failed"] for n, e in (loo or {}).items() if "failed" in e}
    if failed and not bad:
        n, why = next(iter(failed.items()))
        return (f"{FIT_FAILURE}: the fit on the logs other than {n} did not converge ({why[:200]}); the written plant "
                "explains every log, so the data give no evidence of missing physics")
    return ("friction model: the replay residual is neither a resonance, nor predicted by the excitation, nor periodic "
            "in the position; look at standstill, reversals and load changes (the model is Coulomb + viscous per "
            "direction), or the command delay ([controller] command_delay_samples)")


def validate_axis(fitted, logs: Sequence, replays: Sequence, replay: Callable, skip: int,
                  refit: Callable[[Sequence], Any] | None = None, mode_hz: float | None = None,
                  unidentified: Sequence[str] = ()) -> dict:
    """The validation of a fitted linear axis (module docstring).

    Parameters
    ----------
    fitted : LinearAxisPlant
        The plant as written.
    logs, replays : sequences of AxisLog and AxisReplay
        The fitted logs and their closed-loop replays through ``fitted``.
    replay : callable
        ``replay(plant, log) -> AxisReplay`` (:func:`prsa_ctrl.identification.axis.replay_axis`).
    skip : int
        Samples left out at the start of every metric
        (:data:`prsa_ctrl.identification.axis.METRIC_SKIP_SAMPLES`).
    refit : callable, optional
        ``refit(other logs) -> LinearAxisPlant`` (raising ``AxisFitError`` or ``ValueError`` when it
        fails): with more than one log, each log left out is replayed by the plant fitted on the others.
    mode_hz : float, optional
        The fitted axial mode, Hz (a two-mass plant; None: rigid).
    unidentified : sequence of str, optional
        The fit's friction keys the logs left undetermined (held, kept or at a bound), as words for
        the diagnosis.

    Returns
    -------
    dict
        ``passes``, ``reasons``, ``diagnosis`` (None when it passes), ``written_plant`` and
        ``cross_validation`` per log (:func:`entry_report`), ``replay``, ``rule``, ``explained``.
    """
    from ..errors import AxisFitError, SimulationError
    from .validation import FIT_MIN_PERCENT, NOISE_FACTOR

    written = {r.name: {**speed_entry(r, lg, skip), **friction_departure(fitted.theta, lg)}
               for r, lg in zip(replays, logs)}
    loo = None
    if refit is not None and len(logs) > 1:
        loo = {}
        for i, lg in enumerate(logs):
            try:
                plant = refit([o for j, o in enumerate(logs) if j != i])
                loo[lg.name] = {**speed_entry(replay(plant, lg), lg, skip), **friction_departure(plant.theta, lg)}
            except (AxisFitError, SimulationError, ValueError) as exc:
                loo[lg.name] = {"failed": str(exc)[:300]}
    why = reasons(written, loo)
    passes = not why
    return {"passes": passes, "reasons": why,
            "diagnosis": None if passes else diagnosis(written, mode_hz, loo, unidentified),
            "replay": "closed-loop replay from the reference with the log's described controller (the plant as written)",
            "written_plant": {n: entry_report(e) for n, e in written.items()},
            "cross_validation": None if loo is None else {
                n: ({"failed": e["failed"]} if "failed" in e else entry_report(e)) for n, e in loo.items()},
            "rule": (f"every log explained by the written plant: nothing in its replay residual the model should have "
                     f"explained (< {100 * EXCITATION_SHARE:g} % of it predicted out of sample by the reference and test "
                     f"signal, lags 0..{FIR_LAGS} samples; < {100 * PERIODIC_SHARE:g} % of the force residual periodic "
                     f"in the position; the force balance's friction within {100 * FRICTION_DEPARTURE:g} % of the "
                     "Coulomb level of the fitted law at every speed and position, in both halves of the log), and a one-sample speed replay error <= {NOISE_FACTOR:g} x the log's noise floor or a "
                     f"fit >= {FIT_MIN_PERCENT:g} %; with more than one log each left-out log explained by the plant "
                     "fitted on the others; residual whiteness is reported, not tested (never white in closed loop)"),
            "explained": {n: explained(e) for n, e in written.items()}}


def refusal_line(fit) -> str | None:
    """The one line of a fit whose validation failed (None when it passed)."""
    if fit.validation.get("passes"):
        return None
    from .validation import refusal

    return refusal(fit.validation.get("diagnosis") or "no validation was run")
