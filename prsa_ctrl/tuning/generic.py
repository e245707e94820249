"""The generic tuner's entry points: :func:`tune_pid` (any SISO plant; Mks bound, measurement
filter, ideal PID, 2-DOF weights, exact delays) and :func:`tune_loops` (given loop models).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Callable, Sequence
import numpy as np
from ..drive.pid import PID
from ..options import CONTROLLERS, MS_MAX_DEFAULT, OBJECTIVES
from ..drive.sampled import ss_response, zoh
from .settings import CONT_HALVINGS, CONT_RTOL, KKT_TOL, TAIL_RTOL, check_bounds, check_mks, checked_number, gain_limit, int_steps
from .loops import LoopModel, block_sum, plant_roots
from .builders import PADE_PHASE_TOL, check_structure, continuous_loop
from .tuner import Tuner, TuningResult

__all__ = ["tune_loops", "tune_pid", "MAX_ORDER", "FILTER_DECADES", "optimal_filter"]


# The Tuners of the last tune_loops calls, most recent first (strong references to their loops,
# compared by identity, so an id can never be reused): a performance memo only, since a Tuner's
# result does not depend on what it solved before. More than one: the robust tunings alternate
# the nominal and the all-scenario loops at each Ms level (the design to the spec tunes six).
_RECENT: list = []
_RECENT_MAX = 4

def tune_loops(
    loops: Sequence[LoopModel],
    *,
    objective: str = "iae",
    controller: str = "pi",
    ms_max: float = MS_MAX_DEFAULT,
    mt_max: float | None = None,
    max_noise_gain: float | None = None,
    kp_max: float | None = None,
    ki_max: float | None = None,
    kd_max: float | None = None,
    weights: Sequence[float] | None = None,
    worst_case: bool = False,
    mks_max: float | None = None,
) -> TuningResult:
    """Optimise PI/PID gains for one or several loop models: ``Tuner(loops, ...).tune(...)``.

    Parameters
    ----------
    loops : sequence of LoopModel
        Loop models of the same structure (e.g. one per load level).
    objective, controller, weights, worst_case
        See :class:`Tuner`.
    ms_max, mt_max, max_noise_gain, kp_max, ki_max, kd_max, mks_max
        See :meth:`Tuner.tune`.

    Returns
    -------
    TuningResult

    Examples
    --------
    >>> import control
    >>> lp = continuous_loop(control.tf([1.0], [1.0, 2.0, 1.0]), tf=0.1, horizon=40.0, n_steps=400)
    >>> r = tune_loops([lp], objective="ie", ms_max=1.4)
    >>> r.converged, round(r.ms, 4), abs(r.objective * r.pid.ki - 1) < 1e-9
    (True, 1.4, True)
    """
    loops = tuple(loops)
    try:
        w_key = None if weights is None else tuple(float(x) for x in weights)
    except (TypeError, ValueError):
        w_key = object()  # never equal: the Tuner below reports the bad weights
    key = (objective, controller, w_key, worst_case)
    tuner = None
    for k, (old_loops, old_key, old) in enumerate(_RECENT):
        if old_key == key and len(old_loops) == len(loops) and all(a is b for a, b in zip(old_loops, loops)):
            tuner = old
            del _RECENT[k]
            break
    if tuner is None:
        tuner = Tuner(loops, objective=objective, controller=controller, weights=weights, worst_case=worst_case)
    _RECENT[:] = [(loops, key, tuner), *_RECENT[: _RECENT_MAX - 1]]
    return tuner.tune(ms_max=ms_max, mt_max=mt_max, max_noise_gain=max_noise_gain,
                      kp_max=kp_max, ki_max=ki_max, kd_max=kd_max, mks_max=mks_max)

def _phase_frequency(a, b, c, d, delay: float = 0.0) -> tuple[float | None, float]:
    """Frequency (rad/s) where the plant's phase (with its exact delay, s) crosses -135 deg (first
    from above, else the first crossing), on a grid spanning its poles and zeros; and the phase
    (rad) at the top. Where it never crosses: None if the phase stays above -135 deg, else the
    frequency of its highest point (nearest -135 deg; e.g. ``e^(-0.2 s)/(s - 1)``, whose phase
    rises from -180 deg to -140 deg near 2 rad/s, the loop's time scale), or the grid's lowest
    frequency if it never rises."""
    poles, zeros = plant_roots(a, b, c, d)
    mags = np.abs(np.concatenate([poles, zeros]))
    mags = mags[(mags > 0) & np.isfinite(mags)]
    if not mags.size:
        mags = np.array([1.0])
    w = np.logspace(math.log10(mags.min() / 1e3), math.log10(mags.max() * 1e3), 4000)
    resp = ss_response(a, b, c, w) + d[0, 0]
    if delay > 0:
        resp = resp * np.exp(-1j * w * delay)
    ph = np.unwrap(np.angle(resp))
    x = ph + 0.75 * np.pi
    cross = np.flatnonzero(np.sign(x[:-1]) != np.sign(x[1:]))
    if not cross.size:
        if x[0] > 0:
            return None, float(ph[-1])
        # Below -135 deg everywhere (e.g. an unstable pole with a delay, e^(-0.2 s)/(s - 1)): the
        # loop's time scale is where the phase comes nearest -135 deg (its highest point), not the
        # grid's lowest frequency (a horizon of 40000 s for a loop crossing over at 2 rad/s).
        top = int(np.argmax(ph))
        return float(w[top] if ph[top] > ph[0] + 1e-3 else w[0]), float(ph[-1])
    desc = cross[x[cross] > 0]
    i = desc[0] if desc.size else cross[0]
    return float(w[i + 1]), float(ph[-1])

def tune_pid(
    plant,
    *,
    objective: str = "iae",
    controller: str = "pi",
    ms_max: float = MS_MAX_DEFAULT,
    mt_max: float | None = None,
    max_noise_gain: float | None = None,
    disturbance: str | int | None = None,
    step: float = 1.0,
    horizon: float | None = None,
    tf: float | None = None,
    n_steps: int = 2000,
    kp_max: float | None = None,
    ki_max: float | None = None,
    kd_max: float | None = None,
    mks_max: float | None = None,
    filter_order: int = 0,
    filter_tf: float | None = None,
    ideal: bool = False,
    delay: float = 0.0,
    delay_order: int = 6,
    setpoint_weights: bool = False,
) -> TuningResult:
    """Tune a PI (default) or PID for load-disturbance rejection on any SISO LTI plant.

    Parameters
    ----------
    plant : control.LTI
        Continuous transfer function or state space; control input first, optional second
        (or ``disturbance``-named) input for the load; one output. Open-loop unstable plants
        are fine (stability is judged on the closed loop). At most ``MAX_ORDER`` (30) states,
        finite coefficients, dynamics from the control input to the output and no undamped
        poles on the imaginary axis (other than at 0); anything else is refused with a
        ValueError before any work. A plant whose gain is far from 1 (e.g. 1e-12 or 1e200) is
        tuned as ``P/k0`` and its gains scaled back (they scale inversely with the plant gain).
    objective : {"ie", "iae", "itae", "ise"}
        Integral (to infinity) of the error after a disturbance step of size ``step``.
    controller : {"pi", "pid"}
        PID uses a derivative filter with time constant ``tf`` (s).
    ms_max, mt_max : float
        Bounds on the true peak sensitivity and (optionally) complementary sensitivity, in
        (1, 10).
    max_noise_gain : float, optional
        Bound on the controller's high-frequency gain ``kp + kd/tf`` (plant-input units per
        output unit), needed where robustness alone does not limit the gains (the plant's phase
        stays above -135 deg at high frequency). It bounds the controller alone at infinite
        frequency, not the loop's noise gain ``max |C S|`` (which may be larger: use
        ``mks_max`` for that).
    mks_max : float, optional
        Bound on the true peak noise sensitivity ``Mks = max over omega of |C(j omega) S(j
        omega)|`` (plant-input units per output unit) of the loop as tuned; the peak is found
        on a dense grid refined near it (six decades beyond the plant's dynamics, where ``|C
        S|`` tends to its high-frequency limit). Given, it replaces the default noise-gain bound.
        With a measurement filter, ``C`` is the controller with its filter, ``C F``.
    filter_order : {0, 1, 2}
        Measurement filter on the whole controller, ``C(s) F(s)`` with ``F = 1/(Tf s + 1)`` (1)
        or ``1/(Tf^2 s^2/2 + Tf s + 1)`` (2); 0: none (the default, as before).
    filter_tf : float, s, optional
        The filter's time constant; by default (None) a decision variable: the objective's
        optimum over ``Tf`` in ``[10^-4 t_ref, t_ref]`` with ``t_ref = 1 / w135`` (``horizon /
        100`` where the phase stays above -135 deg; ``FILTER_DECADES`` = four decades; a
        log scan then a bounded Brent search, each point a full tuning), reported in
        ``result.filter``. The result is optimal for that range only, and its status says so
        (``"optimal (over Tf in [a, b] s, the filter's search range)"``, and where the best Tf
        is at an end of the range, that the objective keeps improving beyond it): with IE the
        problem over all Tf need not have an optimum at all.
    ideal : bool
        Ideal derivative ``kd s`` (PID without a derivative filter; ``tf`` unused). Without a
        measurement filter it needs a plant of relative degree 2 or more and no ``mks_max``
        (``|C S|`` then grows without bound with frequency, so the reported Mks is inf).
    delay : float, s
        Exact plant delay ``e^{-s delay}`` (on the plant output, so on the control and the
        disturbance path alike). Ms, Mt, Mks and the margins use the exact ``e^{-j omega
        delay}``. The reported IAE/ITAE is that of the loop with the exact delay (simulated
        with the delay an exact number of samples and the delayed state interpolated linearly
        between them, the step halved to ``CONT_RTOL``; :class:`_DelayedLoop`), and the
        first-order check and polish use it; the ipopt stand-in uses a Pade model of order
        ``delay_order`` (``stats["objective_pade"]`` its value at the result). IE is exact
        either way (``|u_ss|/ki``); ISE is that of the Pade model, its change with the order
        + 2 in ``stats["delay_pade_change"]`` (a warning above 1e-4). A delay far below the
        loop's time scale is a numerical edge, not a failure: the Pade model takes the lowest
        order whose phase error stays below ``PADE_PHASE_TOL`` up to the loop grid's top
        (:func:`~prsa_ctrl.tuning.builders.pade_order`), and where the exact simulation would
        exceed its budget (:func:`~prsa_ctrl.tuning.builders.exact_delay_affordable`; e.g. 1e-5 s
        on a loop settling in seconds) the IAE/ITAE is that of the Pade model, with a warning
        giving the delay's phase at the crossover; ``stats["delay_model"]`` says which.
    delay_order : int
        Pade order of the delay in the ipopt stand-in (1 .. 10, default 6; lower for a delay far
        below the loop's time scale, see ``delay``).
    setpoint_weights : bool
        After the load-disturbance design, 2-DOF setpoint weights ``b`` (and ``c`` for a PID
        with a filtered derivative; 0 otherwise) in [0, 1] of the law ``u = kp (b r - y_f) + ki
        (r - y_f)/s + kd D(s) (c r - y_f)``, ``y_f = F(s) y`` (the measurement filter acts on the
        measurement only, the setpoint ``r`` is not filtered; ``D = s/(tf s + 1)``, or ``s`` when
        ``ideal``), for the least IAE of ``r - y`` after a unit setpoint step, the gains fixed (the weights do not enter the loop transfer, so
        Ms, Mt, Mks and the load response are unchanged); in ``result.setpoint``. With a delay
        the setpoint response uses the Pade model of order ``delay_order``.
    disturbance : str or int, optional
        Name or index of the disturbance input (default: the second input, else the control
        input).
    step : float
        Disturbance step size (disturbance-input units), finite and non-zero.
    horizon : float, s, optional
        Simulated response length (the tail beyond it is added exactly or bounded); by default
        40 / w135, with w135 where the plant's phase crosses -135 deg (where it stays below,
        where it comes nearest; :func:`_phase_frequency`), lengthened up to 16x
        while the horizon holds less than 99.9 % of the objective.
    tf : float, s, optional
        Derivative filter time constant; by default 0.1 / w135.
    n_steps : int
        Samples over the horizon (10 .. 200000).
    kp_max, ki_max, kd_max : float, optional
        Upper gain bounds (None or inf: none).

    Returns
    -------
    TuningResult
        ``objective`` is that of the CONTINUOUS closed loop with the returned gains (IE and
        ISE in closed form, IAE and ITAE integrated to a relative ``CONT_RTOL``), not that of
        the sampled stand-in the optimiser works on (``stats["objective_sampled"]``);
        ``status`` is ``"optimal"`` only where an independent first-order check of the true
        problem holds (see :class:`TuningResult`).

    Examples
    --------
    >>> import control
    >>> r = tune_pid(control.tf([1], [1, 3, 3, 1]), objective="ie", ms_max=1.6)
    >>> r.status, r.ms <= 1.6, r.pid.ki > 0.4
    ('optimal', True, True)
    """
    import control

    if objective not in OBJECTIVES:
        raise ValueError(f"objective = {objective!r}; expected one of {', '.join(OBJECTIVES)}")
    if controller not in CONTROLLERS:
        raise ValueError(f"controller = {controller!r}; expected 'pi' or 'pid'")
    check_bounds(ms_max, mt_max, max_noise_gain)
    mks_max = check_mks(mks_max)
    filter_order, _, ideal, delay, delay_order = check_structure(
        filter_order, 1.0 if filter_tf is None else filter_tf, ideal, delay, delay_order)
    if filter_tf is not None and not filter_order:
        raise ValueError(f"filter_tf = {filter_tf!r} without a filter; expected filter_order = 1 or 2")
    if not isinstance(setpoint_weights, (bool, np.bool_)):
        raise ValueError(f"setpoint_weights = {setpoint_weights!r}; expected True or False")
    if ideal and controller != "pid":
        raise ValueError("ideal = True with controller = 'pi'; expected controller = 'pid' (the ideal derivative)")
    if ideal and not filter_order and mks_max is not None:
        raise ValueError("mks_max with an ideal PID and no measurement filter: |C S| grows without bound with "
                         "frequency; expected filter_order = 1 or 2")
    step = checked_number("step", step, expected="a finite non-zero step size")
    if step == 0.0:
        raise ValueError("step = 0.0; expected a finite non-zero step size")
    if horizon is not None:
        horizon = checked_number("horizon", horizon, lo=0.0, expected="a positive finite time in s")
    if tf is not None:
        tf = checked_number("tf", tf, lo=0.0, expected="a positive finite time constant in s")
    n_steps = int_steps("n_steps", n_steps)
    limits = {k: gain_limit(k, v) for k, v in (("kp_max", kp_max), ("ki_max", ki_max), ("kd_max", kd_max))}
    sys = _checked_plant(plant)
    # Scale invariance: a plant of gain k0 far from 1 is tuned as P/k0 (L = (P/k0)(k0 C), the same
    # loop), its gains divided by k0 and its objective multiplied by k0 (ISE: k0^2) after.
    k0 = _gain_scale(sys)
    if k0 != 1.0:
        sys = control.ss(sys.A, sys.B, np.asarray(sys.C) / k0, np.asarray(sys.D) / k0,
                         inputs=sys.input_labels, outputs=sys.output_labels, name=sys.name)
        limits = {k: v * k0 for k, v in limits.items()}
        if max_noise_gain is not None:
            max_noise_gain = float(max_noise_gain) * k0
        if mks_max is not None:
            mks_max = mks_max * k0
    a, b, c, d = (np.asarray(m, dtype=float) for m in (sys.A, sys.B, sys.C, sys.D))
    auto_horizon = horizon is None
    default_note = None
    if horizon is None or tf is None or max_noise_gain is None or (filter_order and filter_tf is None):
        w135, ph_top = _phase_frequency(a, b[:, :1], c, d[:, :1], delay)
        unbounded = (ph_top > -0.75 * np.pi + 1e-3 and max_noise_gain is None and mks_max is None
                     and not math.isfinite(limits["kp_max"]))
        if unbounded or (w135 is None and (horizon is None or tf is None)):
            # Robustness alone does not limit the gains (Ms -> 1 as they grow, e.g. 1/(s-1)): the
            # default design puts the crossover about a decade above the plant's fastest pole or
            # zero w0, by bounding the controller's high-frequency gain at 10 / |P(j w0)|.
            poles, zeros = plant_roots(a, b[:, :1], c, d[:, :1])
            mags = np.abs(np.concatenate([poles, zeros]))
            mags = mags[(mags > 0) & np.isfinite(mags)]
            w0 = float(mags.max()) if mags.size else 1.0
            p0 = abs(complex(ss_response(a, b[:, :1], c, np.array([w0]))[0] + d[0, 0]))
            if max_noise_gain is None and mks_max is None and not math.isfinite(limits["kp_max"]):
                max_noise_gain = 10.0 / p0
                default_note = (f"robustness alone does not limit the gains of this plant (phase "
                                f"{math.degrees(ph_top):.0f} deg at high frequency): tuned with the default noise-gain "
                                f"bound max_noise_gain = 10/|P(j w0)| = {max_noise_gain / k0:.4g} at w0 = {w0:.4g} rad/s "
                                "(crossover about a decade above the plant's fastest pole or zero); pass "
                                "max_noise_gain= to choose")
            if w135 is None:
                horizon = horizon if horizon is not None else 4.0 / w0
                tf = tf if tf is not None else 0.01 / w0
        if w135 is not None:
            horizon = horizon if horizon is not None else 40.0 / w135
            tf = tf if tf is not None else 0.1 / w135
    structure = {"filter_order": filter_order, "ideal": ideal, "delay": delay, "delay_order": delay_order}
    bounds = {"ms_max": ms_max, "mt_max": mt_max, "max_noise_gain": max_noise_gain, "mks_max": mks_max, **limits}

    def solve(t_filter, hor):
        """One tuning at the filter time constant ``t_filter``; the horizon lengthened as before."""
        res = None
        for _ in range(3):
            loop = continuous_loop(sys, tf=tf, horizon=hor, n_steps=n_steps, disturbance=disturbance, step=step,
                                   **({**structure, "filter_tf": t_filter} if (filter_order or ideal or delay) else {}))
            res = Tuner([loop], objective=objective, controller=controller).tune(**bounds)
            if not (auto_horizon and res.stats["horizon_short"]):
                break
            hor *= 4.0
        return res, hor

    if filter_order and filter_tf is None:
        res, horizon = optimal_filter(solve, horizon, 1.0 / (w135 if w135 is not None else 100.0 / horizon))
    else:
        res, horizon = solve(filter_tf, horizon)
    if filter_order or ideal or delay:
        res = _with_structure(res, sys, tf, horizon, n_steps, disturbance, step, {**structure, "filter_tf": filter_tf},
                              objective)
    if setpoint_weights:
        t_f = res.filter["tf_s"] if res.filter else None
        loop = continuous_loop(sys, tf=tf, horizon=horizon, n_steps=n_steps, disturbance=disturbance, step=step,
                               **{**structure, "filter_tf": t_f})
        res = replace(res, setpoint=_setpoint_weights(loop, (res.pid.kp, res.pid.ki, res.pid.kd), ideal))
    if k0 != 1.0:
        res = _rescaled(res, k0, limits)
    if default_note is not None:
        res = replace(res, warnings=(default_note, *res.warnings))
    return res

#: The filter time constant's search range (tune_pid, ``filter_tf=None``): these decades below 1/w135.
FILTER_DECADES = 4

#: Log-scan points over that range before the bounded Brent search.
_FILTER_SCAN = 7

def optimal_filter(solve: Callable, horizon: float, t_ref: float) -> tuple[TuningResult, float]:
    """The measurement filter's time constant as a decision variable: the tuned objective (each
    value a full tuning by ``solve(Tf, horizon)``) scanned on ``_FILTER_SCAN`` log points over
    ``[t_ref 10^-FILTER_DECADES, t_ref]``, then minimised by a bounded Brent search (log Tf,
    2e-3 absolute, at most 20 evaluations) between the best point's neighbours. Its own
    first-order check: neither one-sided slope of the objective in log Tf (steps of +-0.02,
    relative to the objective) may fall below ``-KKT_TOL`` (no descent direction; a kink where
    the active peak changes is a minimum too), except outwards at an end of the range; else
    the status says so. Results not proven optimal or infeasible count as infinite.

    Parameters
    ----------
    solve : callable
        ``solve(tf_s, horizon_s) -> TuningResult``: one tuning at the filter time constant.
    horizon : float, s
    t_ref : float, s
        Top of the search range (``1/w135``).

    Returns
    -------
    (TuningResult, float)
        The best tuning and its filter time constant, s.
    """
    from scipy.optimize import minimize_scalar

    cache: dict = {}
    errors: list = []

    def value(lt: float) -> float:
        key = float(lt)
        if key not in cache:
            try:
                r, hor = solve(math.exp(key), horizon)
                cache[key] = (r.objective if r.converged else math.inf, r, hor)
            except ValueError as exc:
                errors.append(str(exc))
                cache[key] = (math.inf, None, None)
        return cache[key][0]

    lo_all, hi_all = math.log(t_ref) - FILTER_DECADES * math.log(10.0), math.log(t_ref)
    grid = np.linspace(lo_all, hi_all, _FILTER_SCAN)
    vals = np.array([value(x) for x in grid])
    if not np.any(np.isfinite(vals)):
        span = f"[{math.exp(lo_all):.4g}, {math.exp(hi_all):.4g}] s"
        if len(errors) == len(grid) and all("does not help" in e for e in errors):
            # Nothing stabilises the loop at any Tf of the range: the bounds are not the limit.
            raise ValueError(f"{errors[0]} (at every filter time constant in {span})")
        raise ValueError(f"no filter time constant in {span} gives a tuning proven optimal under the bounds; "
                         "relax the constraints or pass filter_tf=")
    i = int(np.argmin(vals))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    minimize_scalar(value, bounds=(lo, hi), method="bounded", options={"xatol": 2e-3, "maxiter": 20})
    best = min(cache, key=lambda k: cache[k][0])
    v0, res, hor = cache[best]
    at_lo, at_hi = best - lo_all < 0.02, hi_all - best < 0.02
    up = (value(best + 0.02) - v0) / (0.02 * v0) if not at_hi else math.inf
    down = (value(best - 0.02) - v0) / (0.02 * v0) if not at_lo else math.inf
    slope = min(up, down)  # the steepest descent the objective allows (negative: it can still decrease)
    at_bound = at_lo or at_hi
    ok = slope >= -KKT_TOL
    t_lo, t_hi = math.exp(lo_all), math.exp(hi_all)
    span = f"Tf in [{t_lo:.4g}, {t_hi:.4g}] s"
    info = {"tf_s": math.exp(best), "range_s": [t_lo, t_hi], "evaluations": len(cache),
            "slope_up": up, "slope_down": down, "at_bound": at_bound, "first_order_ok": ok,
            "problem": f"the gains and the filter time constant over {span} (the search range)"}
    stats = {**res.stats, "filter_search": info}
    res = replace(res, stats=stats)
    if not ok:
        res = replace(res, status=f"not proven optimal: objective slope {slope:.3g} per unit log Tf below -{KKT_TOL:g} "
                                  f"at the filter time constant {math.exp(best):.6g} s (searched {span})",
                      warnings=(*res.warnings, "the filter time constant is not proven optimal (see stats['filter_search'])"))
    elif res.converged:
        # Optimal for the problem searched, which the status names: the optimum over all Tf may
        # lie outside the range, or not exist (IE: e.g. e^(-s)/(s+1), an ideal PID with a 2nd-order
        # filter under Ms, Mt, Mks, whose ki keeps growing with Tf).
        end = (" (at its " + ("upper" if at_hi else "lower") + " end: the objective keeps improving beyond it)"
               if at_bound else "")
        res = replace(res, status=f"optimal (over {span}, the filter's search range{end})")
    if ok and at_bound:
        res = replace(res, warnings=(*res.warnings,
            f"the filter time constant {math.exp(best):.4g} s is at an end of its search range "
            f"[{t_lo:.4g}, {t_hi:.4g}] s (the objective keeps improving that way)"
            + ("; with IE the problem over all Tf need not have an optimum (the gains may scale with Tf at the "
               "same Ms, Mt, Mks): IAE gives a bounded problem" if res.kind == "ie" and at_hi else "")))
    return res, hor

def _with_structure(res: TuningResult, sys, tf: float, horizon: float, n_steps: int, disturbance, step: float,
                    structure: dict, objective: str) -> TuningResult:
    """``res`` with its loop structure stated: ``filter`` (order, Tf, derivative ideal or filtered),
    the delay's Pade check (the objective recomputed with the Pade order + 2:
    ``stats["delay_pade_change"]``, relative; a warning above 1e-4) and, for an ideal PID
    without a measurement filter, Mks = inf (|C S| grows as kd omega)."""
    warnings = list(res.warnings)
    stats = dict(res.stats)
    order, ideal, delay = structure["filter_order"], structure["ideal"], structure["delay"]
    t_filter = stats.get("filter_search", {}).get("tf_s", structure.get("filter_tf"))
    filt = None
    if order or ideal:
        filt = {"order": order, "tf_s": t_filter if order else None,
                "derivative": "ideal" if ideal else "filtered"}
    mks = res.mks
    if ideal:
        warnings.append("ideal derivative: the law is kp + ki/s + kd s" + (" times the filter F(s)" if order else "")
                        + "; pid.tf is not part of it")
        if not order and res.pid.kd > 0:
            mks = math.inf
    if delay > 0:
        g = (res.pid.kp, res.pid.ki, res.pid.kd)
        stats["delay_s"] = delay
        model = continuous_loop(sys, tf=tf, horizon=horizon, n_steps=n_steps, disturbance=disturbance, step=step,
                                **{**structure, "filter_tf": t_filter}).delay_model
        stats["delay_model"] = dict(model)
        if model["pade_order"] < structure["delay_order"]:
            warnings.append(f"the delay {delay:.3g} s is far below the loop's time scale: its Pade model has order "
                            f"{model['pade_order']} (not {structure['delay_order']}; phase error below "
                            f"{PADE_PHASE_TOL:g} rad up to {model['w_top']:.3g} rad/s)")
        if model["objective"] == "pade" and objective in ("iae", "itae"):
            wc = res.margins[0].wc_rad_s
            phase = f"{wc * delay:.3g} rad at the crossover {wc:.4g} rad/s" if math.isfinite(wc) else "unknown"
            warnings.append(f"the delay {delay:.3g} s is too far below the loop's time scale to simulate exactly (its "
                            f"phase: {phase}): the {objective.upper()} is that of its Pade model of order "
                            f"{model['pade_order']}; Ms, Mt, Mks and the margins use the exact delay")
        if objective == "ise":
            # ISE is computed on the Pade model: its change with the order + 2 says how exact it is.
            loop = continuous_loop(sys, tf=tf, horizon=horizon, n_steps=n_steps, disturbance=disturbance, step=step,
                                   **{**structure, "delay_order": structure["delay_order"] + 2, "filter_tf": t_filter})
            change = abs(loop.objective_continuous(g, objective)[0] - res.objective) / res.objective
            stats["delay_pade_change"] = change
            if change > 1e-4:
                warnings.append(f"the ISE changes by {100 * change:.3g} % with the delay's Pade order "
                                f"{structure['delay_order']} -> {structure['delay_order'] + 2}; raise delay_order")
        elif objective in ("iae", "itae"):
            # Reported: the exact delayed loop's; what the optimiser's Pade stand-in says of it:
            loop = continuous_loop(sys, tf=tf, horizon=horizon, n_steps=n_steps, disturbance=disturbance, step=step,
                                   **{**structure, "filter_tf": t_filter})
            stats["objective_pade"] = loop.objective_continuous(g, objective)[0]
    return replace(res, filter=filt, mks=mks, stats=stats, warnings=tuple(warnings))

#: Setpoint-weight search: samples of the basis responses per loop-model sample, and the grid of
#: the scan over b (and c) before the local refinement.
_SP_GRID = 41

def _setpoint_basis(lp: LoopModel, gains):
    """Closed loop ``X' = A X + (B0 + b Bb + c Bc) r`` of a unit setpoint step under the 2-DOF law
    ``u = kp (b r - y_f) + ki int (r - y_f) + kd D(c r - y_f)`` (``y_f`` the measured output; the
    derivative filter state driven by ``c r - y_f``), from the continuous loop of ``lp``:
    ``(A, B0, Bb, Bc)``; the output is ``-Ce X`` (``Ce`` the load loop's error row)."""
    c0, mats, _ = lp.continuous
    g = lp.gvec(gains)
    acl = c0 + sum(gi * m for gi, m in zip(g, mats))
    N = acl.shape[0]
    n, i_i, i_z = N - 2, N - 2, N - 1
    bu = mats[1][:n, i_i]
    b0, bb, bc = np.zeros(N), np.zeros(N), np.zeros(N)
    b0[i_i] = 1.0  # the integral acts on r - y_f
    bb[:n] = g[0] * bu
    bc[:n] = g[2] * bu / lp.tf
    bc[i_z] = 1.0 / lp.tf
    return acl, b0, bb, bc

def _setpoint_iae(acl, bsum, cy, h: float, rtol: float) -> tuple[float, float]:
    """IAE of ``e = 1 - cy X`` after a unit setpoint step (``X' = acl X + bsum``, from rest),
    sampled exactly every ``h`` and summed by the trapezoid rule to infinity, halving ``h``
    until two values agree within ``rtol`` (Richardson estimate, at most ``CONT_HALVINGS``)."""
    prev, val, err = None, math.inf, math.inf
    for _ in range(CONT_HALVINGS + 1):
        ad, bd = zoh(acl, bsum[:, None], h)
        x_inf = np.linalg.solve(np.eye(ad.shape[0]) - ad, bd[:, 0])
        # e_k = 1 - cy X_k = -cy (X_k - x_inf) (zero steady error); e_0 = 1: the trapezoid halves it.
        val, tail = block_sum(ad, -cy, -x_inf, 0, 0.0, h, "iae", min(rtol, TAIL_RTOL))
        val -= 0.5 * h
        if prev is not None:
            err = abs(val - prev) / 3.0 + tail
            if err <= rtol * val:
                break
        prev = val
        h /= 2.0
    return val, err

def _setpoint_weights(lp: LoopModel, gains, ideal: bool) -> dict:
    """2-DOF setpoint weights for the load-optimal ``gains`` (fixed: b and c do not enter the loop
    transfer, so Ms/Mt/Mks and the load response are unchanged). Goal: the least IAE of the
    error ``r - y`` after a unit setpoint step. The error is affine in (b, c), so that IAE is
    convex in them: a scan of ``_SP_GRID`` points per weight in [0, 1] on the sampled basis
    responses, then a Nelder-Mead search from the best point on the same samples (weights
    clipped to [0, 1]), and the result's IAE recomputed to ``CONT_RTOL`` (:func:`_setpoint_iae`). ``c`` is 0 for an
    ideal derivative (a setpoint step would give an impulse) and for a PI."""
    from scipy.optimize import minimize

    acl, b0, bb, bc = _setpoint_basis(lp, gains)
    cy = -lp.Ce  # the output row over X (Ce is the load error row, -y)
    h = lp.h / 4.0
    n_s = 4 * lp.n_steps
    N = acl.shape[0]
    basis = []
    for bvec in (b0, bb, bc):
        ad, bd = zoh(acl, bvec[:, None], h)
        x = np.zeros(N)
        ys = np.empty(n_s)
        for k in range(n_s):
            ys[k] = cy @ x
            x = ad @ x + bd[:, 0]
        basis.append(ys)
    use_c = lp.gvec(gains)[2] > 0 and not ideal
    wts = np.full(n_s, h)
    wts[0] = 0.5 * h

    def iae(b, c):
        return float(wts @ np.abs(1.0 - basis[0] - b * basis[1] - c * basis[2]))

    # Scan (vectorised over the grid), then Nelder-Mead from the best grid point, clipped to [0, 1].
    grid = np.linspace(0.0, 1.0, _SP_GRID)
    bs, cs = np.meshgrid(grid, grid if use_c else np.array([0.0]), indexing="ij")
    bs, cs = bs.ravel(), cs.ravel()
    vals = np.concatenate([wts @ np.abs(1.0 - basis[0][:, None] - basis[1][:, None] * bs[None, j : j + 200]
                                        - basis[2][:, None] * cs[None, j : j + 200]) for j in range(0, bs.size, 200)])
    i = int(np.argmin(vals))
    x0 = np.array([bs[i], cs[i]])[: 2 if use_c else 1]

    def f(x):
        x = np.clip(x, 0.0, 1.0)
        return iae(x[0], x[1] if use_c else 0.0)

    r = minimize(f, x0, method="Nelder-Mead", options={"xatol": 1e-7, "fatol": 1e-12, "maxfev": 400})
    x = np.clip(r.x, 0.0, 1.0) if f(r.x) <= vals[i] else x0
    b, c = float(x[0]), float(x[1]) if use_c else 0.0
    val, err = _setpoint_iae(acl, b0 + b * bb + c * bc, cy, lp.h, CONT_RTOL)
    one = _setpoint_iae(acl, b0 + bb + (bc if use_c else 0.0), cy, lp.h, CONT_RTOL)[0]
    y = basis[0] + b * basis[1] + c * basis[2]
    return {"b": b, "c": c, "goal": "least IAE of r - y after a unit setpoint step, load-optimal gains fixed",
            "iae": val, "iae_error": err, "iae_unweighted": one, "overshoot": max(float(np.max(y)) - 1.0, 0.0)}

#: Largest plant order :func:`tune_pid` accepts (states of its state-space realisation): the
#: tuner's work grows as the cube of the order (order 20: ~3 s, 30: ~30 s, 100: ~2 min, 800: 38 GiB).
MAX_ORDER = 30

#: Plant gains |P(j w_ref)| outside [1/_GAIN_SPAN, _GAIN_SPAN] are normalised (see tune_pid).
_GAIN_SPAN = 1e3

def _checked_plant(plant):
    """``plant`` as a continuous SISO state space with finite matrices and dynamics, or a
    ValueError naming ``plant`` and what was expected (one line, before any work)."""
    import control

    desc = " ".join(repr(plant).split())  # one line
    if len(desc) > 200:
        desc = desc[:200] + "..."
    if not isinstance(plant, control.LTI):
        raise ValueError(f"plant = {desc}; expected a python-control LTI system (tf or ss)")
    if isinstance(plant, control.TransferFunction):
        coefs = [np.asarray(x, float) for row in (plant.num, plant.den) for r in row for x in r]
        if not all(np.all(np.isfinite(x)) for x in coefs):
            raise ValueError(f"plant = {desc} has non-finite (nan/inf) coefficients; expected finite numbers")
    if plant.noutputs != 1:
        raise ValueError(f"plant has {plant.noutputs} outputs; expected one (SISO feedback path)")
    if isinstance(plant, control.TransferFunction):
        den = np.trim_zeros(np.atleast_1d(np.asarray(plant.den[0][0], float)), "f")
        if den.size - 1 > MAX_ORDER:
            raise ValueError(f"plant of order {den.size - 1}; expected at most MAX_ORDER = {MAX_ORDER} states "
                             "(reduce it first, e.g. control.balred or control.minreal)")
    try:
        sys = control.ss(plant)
    except (ValueError, TypeError, ArithmeticError, np.linalg.LinAlgError) as exc:
        raise ValueError(f"plant = {desc} has no state-space realisation ({exc}); expected a proper "
                         "continuous LTI system with finite coefficients") from None
    if not sys.isctime():
        raise ValueError(f"plant {sys.name!r} is discrete-time; expected a continuous-time LTI system")
    a, b, c, d = (np.asarray(m, dtype=float) for m in (sys.A, sys.B, sys.C, sys.D))
    n = a.shape[0]
    if n > MAX_ORDER:
        raise ValueError(f"plant of order {n}; expected at most MAX_ORDER = {MAX_ORDER} states "
                         "(reduce it first, e.g. control.balred or control.minreal)")
    if not all(np.all(np.isfinite(m)) for m in (a, b, c, d)):
        raise ValueError("plant matrices contain inf or NaN; expected finite numbers")
    if n == 0 or not np.any(b[:, 0]) or not np.any(c):
        kind = "zero" if not np.any(d) else "a static gain"
        raise ValueError(f"plant = {desc} is {kind} (no dynamics from the control input to the output); "
                         "expected a strictly proper plant with dynamics")
    lam = np.linalg.eigvals(a)
    osc = lam[(np.abs(lam) > 0) & (np.abs(lam.real) <= 1e-12 * np.abs(lam))]
    if osc.size:
        raise ValueError(f"plant has undamped poles on the imaginary axis at +-{np.abs(osc.imag).max():.6g} rad/s; "
                         "expected damped poles (the loop response is infinite there), e.g. a damping ratio of 1e-6")
    return sys

def _gain_scale(sys) -> float:
    """1, or the plant's gain ``|P(j w_ref)|`` (``w_ref`` the geometric mean of its extreme
    pole/zero magnitudes) where that lies outside ``[1/_GAIN_SPAN, _GAIN_SPAN]``; a ValueError
    where it is not a finite positive number (a plant too small or large for double precision)."""
    a, b, c, d = (np.asarray(m, dtype=float) for m in (sys.A, sys.B, sys.C, sys.D))
    poles, zeros = plant_roots(a, b[:, :1], c, d[:, :1])
    mags = np.abs(np.concatenate([poles, zeros]))
    mags = mags[(mags > 0) & np.isfinite(mags)]
    w_ref = math.sqrt(float(mags.min()) * float(mags.max())) if mags.size else 1.0
    with np.errstate(all="ignore"):
        k0 = abs(complex(ss_response(a, b[:, :1], c, np.array([w_ref]))[0] + d[0, 0]))
    if not (math.isfinite(k0) and k0 > 0 and math.isfinite(1 / k0)):
        raise ValueError(f"plant gain |P(j {w_ref:.4g})| = {k0:.3g} is not a finite positive number in double "
                         "precision; expected a plant of finite, non-zero gain")
    return 1.0 if 1 / _GAIN_SPAN <= k0 <= _GAIN_SPAN else k0

def _rescaled(res: TuningResult, k0: float, limits: dict) -> TuningResult:
    """A result of the normalised plant ``P/k0`` in the units of ``P``: gains / k0, objectives
    * k0 (ISE * k0^2); a ValueError where a number leaves double precision."""
    f = k0 * k0 if res.kind == "ise" else k0
    pid = res.pid
    gains = [pid.kp / k0, pid.ki / k0, pid.kd / k0]
    obj = res.objective * f
    if not (all(math.isfinite(x) for x in gains) and math.isfinite(obj)) or (pid.ki > 0 and gains[1] == 0.0):
        raise ValueError(f"plant gain {k0:.3g}: the tuned gains or the {res.kind.upper()} ({res.objective:.3g} x {f:.3g}) "
                         "leave double precision; expected a plant gain nearer 1 (rescale its units)")
    stats = dict(res.stats)
    for key in ("objective_horizon", "objective_sampled", "tail_bound", "objective_pade"):
        if key in stats:
            stats[key] = stats[key] * f
    names = ("kp", "ki", "kd")
    warnings = [w for w in res.warnings if not any(w.startswith(f"{n} = ") for n in names)]
    for i, n in enumerate(names):
        lim = limits[f"{n}_max"]
        if math.isfinite(lim) and lim > 0 and gains[i] * k0 >= lim * (1 - 1e-6):
            warnings.append(f"{n} = {gains[i]:.6g} is at its bound {n}_max = {lim / k0:g}")
    return replace(res, pid=PID(gains[0], gains[1], gains[2], tf=pid.tf, kff=pid.kff), objective=obj,
                   mks=None if res.mks is None else res.mks / k0,
                   per_loop=[v * f for v in res.per_loop], stats=stats, warnings=tuple(warnings))
