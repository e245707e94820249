"""Validation of a time-domain fit that can say no: the replay of every log through the plant as
written, residual whiteness, leave-one-out cross-validation and the verdict.

Replay. A screw-axis log of the motor-coordinate mode holds the torque command, not the
reference the speed loop followed, and no description of that loop: a closed-loop replay from
the reference is not possible, and an open-loop simulation from the logged command drifts on an
integrating axis (any torque bias integrates twice; a drift says nothing about the fit). The
replay is therefore in **prediction-error form**: the plant's own equations driven by the logged
command (held over the sample, ``shift`` samples late) and load, with a weak output injection of
the measured angle,

    theta' = omega + l1 (theta_m - theta),   omega' = f_omega(x, u) + l2 (theta_m - theta),

``l1 = 2 w_o``, ``l2 = w_o^2`` (a critically damped error loop of :data:`OBSERVER_HZ`). Over
the bandwidth of a servo axis's speed loop (tens of Hz) and above, the replayed response to the
command is the model's own; below ``OBSERVER_HZ`` the measured angle holds the replay (a
constant torque error leaves a constant angle offset, no speed error): no drift. It is a
stricter test than a closed-loop replay, whose speed loop hides model errors below its own
bandwidth. A log whose description (load coordinates) gives the controller and the reference is
replayed in closed loop from the reference instead (:func:`closed_loop_replay`), as the
linear-axis mode replays its plant (:func:`prsa_ctrl.identification.axis.replay_axis`).

Metrics per log, on the nut speed over each sample interval (one-sample angle difference), from
sample :data:`SKIP_S` on: the replay fit % (:func:`~prsa_ctrl.identification.common.fit_percent`),
the replay error RMS and the log's own noise floor (:func:`noise_floor`).

Verdict (:func:`verdict`). A log is explained when its replay error is within
:data:`NOISE_FACTOR` times its noise floor, **or** its replay fit % is at least
:data:`FIT_MIN_PERCENT` and its residual holds no resonance (less than :data:`RESONANCE_SHARE`
of its power within +/- 15 % of one frequency above 10 Hz: :func:`resonance`). A log with little
motion -- a constant speed with load steps -- has a small fit % even when replayed at the noise;
a two-mass axis replayed by a rigid plant has a high fit % (the mode is a small part of the
motion) and a residual that is mostly the mode: measured on independent logs, the residual of a
rigid plant on a two-mass axis held 55-86 % of its power at the mode, on a rigid axis 1-2 %
(at 5-42 x the noise floor). A compliant plant has the mode, and near it its replay is so
sensitive to the mode's placement that its largest residual sits there even with the mode where
the data have it: there the resonance is not one it lacks when the mode bracket places it (the log
replayed worse with the mode moved 5 % down and up: :mod:`prsa_ctrl.identification.modebracket`,
:func:`bracket_modes`). The fit passes when every fitted log is explained by the plant as
written, each left-out log by the plant fitted on the others (with more than one log), and the
written plant replays no log more than :data:`WRITTEN_TOLERANCE_POINTS` worse than the free fit.
Why these numbers: 50 % fit means the replay error is half the log's own variation -- a model
that misses half of what the command does cannot be tuned on; a model that is right leaves the
sensor's noise (the floor) plus what it does not model, and three times the floor is the
allowance for the unmodelled (filters, small compliance) at which a residual is still mostly
noise. Where the verdict is no, :func:`diagnosis` names the most likely missing physics.

Whiteness (reported, not part of the verdict): the autocorrelation of each log's replay residual
at lags :data:`ACF_LAGS` against the 95 % band ``1.96 / sqrt(N)`` and the Ljung-Box test over
lags 1..50 at 5 % (:func:`whiteness`). A right model's residuals are
not white either (the one-sample angle difference colours the encoder noise, lag 1 = -0.5; the
output injection colours the process noise), so it is evidence, not a test to fail on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from ..plant.plantfile import Plant
from .common import fit_percent, symbolic_rhs, uncertainty_entries
from .compliant import compliant_reference
from .data import Record
from .fituncertainty import hold_written_values
from .modebracket import MODE_BRACKET

__all__ = ["OBSERVER_HZ", "FIT_MIN_PERCENT", "NOISE_FACTOR", "RESONANCE_SHARE", "FIT_FAILURE", "refusal", "resonance", "WRITTEN_TOLERANCE_POINTS", "ACF_LAGS", "SKIP_S",
           "REPLAY_MODE", "replay_records", "noise_floor", "whiteness", "explained", "verdict", "diagnosis",
           "validate_fit", "bracket_modes", "delay_confirmed", "ClosedLoop", "closed_loop_of", "closed_loop_replay", "CLOSED_LOOP_MODE"]

#: Bandwidth of the prediction-error replay's output injection, Hz (module docstring).
OBSERVER_HZ = 2.0
#: A log is explained when its replay fit % reaches this ...
FIT_MIN_PERCENT = 50.0
#: ... or its replay error RMS is within this factor of its noise floor.
NOISE_FACTOR = 3.0
#: Above the noise allowance, a residual holding this share of its power within +/- 15 % of one
#: frequency above 10 Hz is a resonance the model lacks: the log is not explained, whatever its fit %.
RESONANCE_SHARE = 1.0 / 3.0
#: How :func:`diagnosis` begins when the fit could not be validated because a fit failed (no
#: evidence about the physics); :func:`refusal` then says "could not be validated".
FIT_FAILURE = "fit failure, not missing physics"
#: The written plant may replay a log this many fit-% points worse than the free fit, no more.
WRITTEN_TOLERANCE_POINTS = 2.0
#: Lags (samples) of the reported residual autocorrelation.
ACF_LAGS = (1, 2, 5, 10, 20, 50)
#: Samples of the first this many seconds (at least 20 samples) are left out of the metrics: the
#: replay starts from the measured angle and a speed estimate, and the states the log does not
#: measure settle.
SKIP_S = 0.02
#: What the report says about the replay.
CLOSED_LOOP_MODE = ("closed-loop replay from the reference with the log's described controller (the plant as "
                    "the tuner sees it, the speed and position loops closed as they ran)")
REPLAY_MODE = (f"prediction-error replay: the plant driven by the logged command and load with the measured angle "
               f"fed back at {OBSERVER_HZ:g} Hz (no reference or controller is described in these logs, so no "
               "closed-loop replay; no open-loop drift)")


def noise_floor(rec: Record) -> float:
    """The noise of the log's one-sample speed, rad/s: ``sqrt(2) sigma / Ts`` with ``sigma`` the
    angle's white noise (quantisation and any other), estimated from the third difference of
    the angle (``var = 20 sigma^2`` for white noise) as the 10th percentile over blocks of 256
    samples (blocks where the motion is smoothest, so that the motion's own third difference
    does not count as noise). A log without an angle column: the speed's second difference
    (``var = 6 sigma_v^2``) the same way."""
    if rec.nut_angle_rad is not None:
        d = np.diff(rec.nut_angle_rad, 3)
        var_factor, to_speed = 20.0, math.sqrt(2.0) / rec.sample_time_s
    else:
        d = np.diff(rec.nut_speed_rad_s, 2)
        var_factor, to_speed = 6.0, 1.0
    block = 256
    nb = len(d) // block
    if nb == 0:
        v = float(np.var(d))
    else:
        v = float(np.percentile(np.var(d[:nb * block].reshape(nb, block), axis=1), 10))
    return math.sqrt(max(v, 0.0) / var_factor) * to_speed


def _integrator(plant: Plant, fidelity: str, observer_hz: float):
    f, names = symbolic_rhs(plant, (), fidelity)
    nx = len(names)
    i_th, i_w = names.index("theta_nut"), names.index("omega_nut")
    w_o = 2 * math.pi * observer_hz
    l1, l2 = 2.0 * w_o, w_o * w_o
    x = ca.SX.sym("x", nx)  # x[i_th] is the angle error e = theta - theta_m(t)
    p = ca.SX.sym("p", 5)  # command, load, h, theta_m at the step start, theta_m increment over the step
    t = ca.SX.sym("t")
    u, load, h, th0, dth = p[0], p[1], p[2], p[3], p[4]
    e = x[i_th]
    full = ca.vertcat(*[th0 + t * dth + e if i == i_th else x[i] for i in range(nx)])
    dx = f(full, ca.vertcat(u, load), ca.DM.zeros(0))
    rows = []
    for i in range(nx):
        if i == i_th:
            rows.append(h * (dx[i] - l1 * e) - dth)
        elif i == i_w:
            rows.append(h * (dx[i] - l2 * e))
        else:
            rows.append(h * dx[i])
    # one 3-stage Radau IIA step per sample (order 5, L-stable: the current loop and Karnopp's
    # stick band are stiff), two where the plant's current loop is faster than a sample
    fe = 1 if plant.current_loop_time_constant_s >= 0.25 * plant.sample_time_s else 2
    step = ca.integrator("replay", "collocation", {"x": x, "p": p, "t": t, "ode": ca.vertcat(*rows)}, 0.0, 1.0,
                         {"collocation_scheme": "radau", "interpolation_order": 3, "number_of_finite_elements": fe,
                          "rootfinder": "newton", "rootfinder_options": {"abstol": 1e-12, "max_iter": 50}})
    return step, names, i_th, i_w


@dataclass(frozen=True)
class ClosedLoop:
    """A log's described controller and reference (load coordinates, SI), for the closed-loop
    replay of a screw-driven plant (:func:`closed_loop_replay`); from :func:`closed_loop_of`."""

    controller: Any  # prsa_ctrl.identification.logformat.ControllerSpec
    reference_m: NDArray[np.float64]
    test_signal: NDArray[np.float64] | None
    gain_n_per_unit: float
    command_logged: str  # "as-computed" | "as-applied"


def closed_loop_of(log) -> "ClosedLoop | None":
    """The closed-loop description of an :class:`~prsa_ctrl.identification.logformat.AxisLog`
    (None without a controller or a reference)."""
    if getattr(log, "controller", None) is None or getattr(log, "reference_m", None) is None:
        return None
    return ClosedLoop(log.controller, np.asarray(log.reference_m, float),
                      None if log.test_signal is None else np.asarray(log.test_signal, float),
                      float(log.gain_n_per_unit), log.command_logged)


def _plant_step(plant: Plant, fidelity: str):
    """One sample of the plant (``x, [torque command, load, h] -> x``), 3-stage Radau IIA."""
    f, names = symbolic_rhs(plant, (), fidelity)
    x = ca.SX.sym("x", len(names))
    p = ca.SX.sym("p", 3)
    fe = 1 if plant.current_loop_time_constant_s >= 0.25 * plant.sample_time_s else 2
    step = ca.integrator("cl_step", "collocation", {"x": x, "p": p, "ode": p[2] * f(x, p[:2], ca.DM.zeros(0))}, 0.0, 1.0,
                         {"collocation_scheme": "radau", "interpolation_order": 3, "number_of_finite_elements": fe,
                          "rootfinder": "newton", "rootfinder_options": {"abstol": 1e-12, "max_iter": 50}})
    return step, names


def closed_loop_replay(plant: Plant, rec: Record, cl: ClosedLoop, shift: int, fidelity: str = "rigid") -> dict:
    """Replay ``rec`` through ``plant`` in closed loop from the reference with the log's
    controller (the law of :mod:`prsa_ctrl.identification.logformat`, in load coordinates:
    position ``q = a theta``), the test signal added at the drive input; the force command
    ``gain (u + test)`` turns into the torque command ``a`` times it (the record's own
    conversion) and acts ``shift`` samples after it is computed (a log of the applied command:
    plus the controller's ``command_delay_samples``). Starts at the first logged angle and speed.

    Returns the same entry as :func:`replay_records` (``"replay"``: closed loop)."""
    step, names = _plant_step(plant, fidelity)
    i_th, i_w, i_tau = names.index("theta_nut"), names.index("omega_nut"), names.index("tau_motor")
    a = float(plant.lead_per_rad)
    c = cl.controller
    n, h = rec.n, float(rec.sample_time_s)
    # the command computed at k acts from k + shift (the fit's: logged -> action); a log of the
    # applied command logged it the controller's command_delay_samples after computing it
    delay = int(shift) + (int(c.command_delay_samples) if cl.command_logged == "as-applied" else 0)
    test = np.zeros(n) if cl.test_signal is None else cl.test_signal
    ref, load, logged = cl.reference_m, rec.axial_load_n, rec.torque_command_n_m
    th_m = rec.nut_angle_rad if rec.nut_angle_rad is not None else \
        np.concatenate([[0.0], np.cumsum(rec.nut_speed_rad_s[1:] * np.diff(rec.time_s))])
    x = _start_state(plant, names, rec, th_m)
    x[i_th], x[i_w] = float(th_m[0]), float(rec.speed_rad_s[0])
    x[i_tau] = float(np.clip(logged[0], -plant.torque_limit, plant.torque_limit))
    theta = np.empty(n)
    torque = np.empty(n)
    q_prev = qf_prev = a * x[i_th]  # the law's start (reconstruct_command): q(-1) = q(0), the sum from 0
    integ = 0.0
    avg = c.velocity_estimate == "average2-difference"
    ok = True
    for k in range(n):
        theta[k] = x[i_th]
        q = a * x[i_th]
        if avg:
            qf = 0.5 * (q + q_prev)
            dq = (qf - qf_prev) / h
            qf_prev = qf
        else:
            dq = (q - q_prev) / h
        q_prev = q
        ev = c.kp * (ref[k] - q) - dq
        u = c.kv * ev
        if c.ki:
            integ += c.ki * h * ev
            u += c.kv * integ
        u = min(max(u, -c.saturation), c.saturation)
        torque[k] = cl.gain_n_per_unit * (u + test[k]) * a
        if k == n - 1:
            break
        j = k - delay
        applied = torque[j] if j >= 0 else float(logged[0])
        try:
            x = np.asarray(step(x0=x, p=[applied, float(load[k]), float(rec.time_s[k + 1] - rec.time_s[k])])["xf"],
                           float).ravel()
        except RuntimeError:
            ok = False
            break
        if not np.all(np.isfinite(x)):
            ok = False
            break
    skip = max(20, int(round(SKIP_S / h)))
    mode = CLOSED_LOOP_MODE
    entry = {"replay": mode, "skip_samples": skip, "noise_floor_rad_s": noise_floor(rec)}
    if not ok:
        return {**entry, "finite": False, "fit_percent": -math.inf, "error_rms_rad_s": math.inf}
    meas = rec.speed_rad_s
    model = np.diff(theta) / np.diff(rec.time_s)
    a_, b_ = meas[skip:], model[skip:]
    return {**entry, "finite": True, "time_s": rec.time_s[1:], "measured": meas, "model": model,
            "fit_percent": fit_percent(a_, b_), "error_rms_rad_s": float(np.sqrt(np.mean((a_ - b_) ** 2)))}


def _start_state(plant: Plant, names: Sequence[str], rec: Record, theta_rad: NDArray[np.float64]) -> NDArray[np.float64]:
    """A replay's initial state: zero, but the compliant screw-driven model's unmeasured states
    (carriage speed, spring deflections) at their quasi-static values at the log's first sample,
    the fit's own reference (:func:`~prsa_ctrl.identification.compliant.compliant_reference`).
    Left at zero they start a carriage at rest under a turning screw: on the foreign feed axis
    (30 rad/s, 350 kg) that transient at the output injection's 2 Hz held the first half of every
    replay at 0.75-1.6 rad/s of error (loadsteps.csv at 44 x its noise floor, read as a missing
    friction law); from the quasi-static state the same plant replays each log at 1.2-1.4 x."""
    x0 = np.zeros(len(names))
    if len(theta_rad) >= 2:
        ref = compliant_reference(plant, names, rec.time_s, np.gradient(theta_rad, rec.time_s), rec.axial_load_n)
        for k, v in ref.items():
            x0[names.index(k)] = float(v[0])
    return x0


def replay_records(plant: Plant, records: Sequence[Record], shift: int, fidelity: str = "rigid",
                   observer_hz: float = OBSERVER_HZ, check=None, closed_loops=None) -> dict:
    """Replay each record through ``plant`` in prediction-error form (module docstring).

    Parameters
    ----------
    plant : Plant
    records : sequence of Record
    shift : int
        Samples from the logged command to the sample it is held from (the fit's shift).
    fidelity : str
    observer_hz : float, Hz
        Bandwidth of the measured angle's injection.
    check : callable, optional
        Called after every record (interrupts).
    closed_loops : mapping, optional
        ``{record name: ClosedLoop}``: those records are replayed in closed loop from the
        reference (:func:`closed_loop_replay`) instead.

    Returns
    -------
    dict
        ``{record name: {"time_s", "measured", "model" (rad/s, nut speed over each interval),
        "fit_percent", "error_rms_rad_s", "noise_floor_rad_s", "skip_samples", "replay",
        "finite"}}``. A replay that leaves the finite numbers has ``"finite": False``, fit %
        ``-inf`` and no traces.
    """
    step, names, i_th, i_w = _integrator(plant, fidelity, observer_hz)
    out = {}
    for rec in records:
        cl = (closed_loops or {}).get(rec.name)
        if cl is not None:
            out[rec.name] = closed_loop_replay(plant, rec, cl, shift, fidelity)
            if check is not None:
                check()
            continue
        n = rec.n
        if rec.nut_angle_rad is not None:  # the measured angle (or the integrated measured speed)
            th = rec.nut_angle_rad.astype(float)
        else:
            th = np.concatenate([[0.0], np.cumsum(rec.nut_speed_rad_s[1:] * np.diff(rec.time_s))])
        ks = np.arange(n - 1)
        kd = np.clip(ks - int(shift), 0, None)
        pu = np.vstack([rec.torque_command_n_m[kd], rec.axial_load_n[ks], np.diff(rec.time_s), th[:-1], np.diff(th)])
        x0 = _start_state(plant, names, rec, th)
        x0[i_w] = float(rec.speed_rad_s[0])
        x0[names.index("tau_motor")] = float(np.clip(rec.torque_command_n_m[0], -plant.torque_limit, plant.torque_limit))
        skip = max(20, int(round(SKIP_S / rec.sample_time_s)))
        meas = rec.speed_rad_s
        entry = {"replay": REPLAY_MODE, "skip_samples": skip, "noise_floor_rad_s": noise_floor(rec)}
        try:
            xs = np.asarray(step.mapaccum("replay_acc", len(ks), ["x0"], ["xf"])(x0=x0, p=pu)["xf"], float)
            e = np.concatenate([[0.0], xs[i_th]])
            model = meas + np.diff(e) / np.diff(rec.time_s)
            ok = bool(np.all(np.isfinite(model)))
        except RuntimeError:
            ok = False
        if check is not None:
            check()
        if not ok:
            out[rec.name] = {**entry, "finite": False, "fit_percent": -math.inf, "error_rms_rad_s": math.inf}
            continue
        a, b = meas[skip:], model[skip:]
        out[rec.name] = {**entry, "finite": True, "time_s": rec.time_s[1:], "measured": meas, "model": model,
                         "fit_percent": fit_percent(a, b), "error_rms_rad_s": float(np.sqrt(np.mean((a - b) ** 2)))}
    return out


def whiteness(residual: NDArray[np.float64], lags: Sequence[int] = ACF_LAGS) -> dict:
    """Residual whiteness: the autocorrelation at ``lags`` with the 95 % band ``1.96 / sqrt(N)``
    of white noise, and the Ljung-Box portmanteau test over lags ``1..max(lags)``
    (``Q = N (N + 2) sum rho_l^2 / (N - l)`` against the 95 % quantile of chi-square with
    ``max(lags)`` degrees of freedom; G. M. Ljung, G. E. P. Box, Biometrika 65(2) 1978):
    ``white`` when ``Q`` is below it (a 5 % false alarm on white noise)."""
    from scipy.stats import chi2

    r = np.asarray(residual, float)
    r = r - r.mean()
    den = float(r @ r)
    n = len(r)
    top = int(max(lags))
    rho = np.array([(float(r[l:] @ r[:-l]) / den if den > 0 and n > l else 0.0) for l in range(1, top + 1)])
    q = float(n * (n + 2) * np.sum(rho**2 / np.maximum(n - np.arange(1, top + 1), 1)))
    limit = float(chi2.ppf(0.95, top))
    return {"lags": list(map(int, lags)), "acf": {int(l): float(rho[l - 1]) for l in lags},
            "band": 1.96 / math.sqrt(max(n, 1)), "ljung_box_q": q, "ljung_box_limit": limit,
            "ljung_box_lags": top, "white": q <= limit}


def resonance(entry: dict) -> tuple[float, float]:
    """``(frequency Hz, share)`` of the largest spectral peak above 10 Hz of a finite replay's
    residual and the share of its power within +/- 15 % of it (:func:`_peak`; computed once and
    kept in the entry)."""
    if "resonance" not in entry:
        t = np.asarray(entry.get("time_s", ()), dtype=float)
        res = (np.asarray(entry["measured"]) - np.asarray(entry["model"]))[entry["skip_samples"]:]
        ts = float(np.median(np.diff(t))) if t.size > 1 else 0.0
        entry["resonance"] = _peak(res, ts) if ts > 0 and res.size > 16 else (0.0, 0.0)
    return entry["resonance"]


def explained(entry: dict) -> bool:
    """Whether one replay explains its log (module docstring: the noise floor; else fit % and no
    resonance in the residual)."""
    if not entry.get("finite", False):
        return False
    if entry["error_rms_rad_s"] <= NOISE_FACTOR * entry["noise_floor_rad_s"]:
        return True
    if (entry.get("mode_bracket") or {}).get("placed"):  # the residual's resonance is the plant's own mode, placed
        return entry["fit_percent"] >= FIT_MIN_PERCENT
    return entry["fit_percent"] >= FIT_MIN_PERCENT and resonance(entry)[1] < RESONANCE_SHARE


def delay_confirmed(search: dict | None) -> bool:
    """Whether the mode bracket (:func:`bracket_modes`) may judge a compliant plant's residual at
    its mode: the delay was given (``search`` None), or the search fitted every other shift with an
    objective at least its ``ratio_tolerance`` times the best's or left it out for lack of
    current-loop lag; not when a shift failed, was stopped by the work bound, or only the paired
    segment test refuted it. Why: the bracket tests the mode with the other keys held, and a wrong
    delay is absorbed near the mode too. Measured (h16-logsmode, seed 0): the second generator's
    roller screw (tests/identification/foreign/gen_rollerscrew.py), logs alone, compliant: shift 1
    decided by the segment test at an objective ratio of 1.29 against a true 2; with the bracket
    its written plant explained every log and only a cross-validation fit that did not converge
    refused it. The judge's roller screws (ratio 1.77, or every other shift without lag) were
    right."""
    if search is None:
        return True
    if not search.get("decided", False) or search.get("failed") or search.get("stopped_by_work_bound"):
        return False
    obj = {k: v for k, v in (search.get("objective") or {}).items() if v is not None}
    if not obj or len(obj) < len(search.get("objective") or {}):
        return False
    best = min(obj.values())
    tol = float(search.get("ratio_tolerance", 1.5))
    others = [v for v in obj.values() if v != best]
    return len(others) == len(obj) - 1 and all(v >= tol * best for v in others)


def bracket_modes(plant: Plant, records: Sequence[Record], entries: dict, shift: int, fidelity: str, check=None,
                  closed_loops=None) -> None:
    """Put the mode bracket (:func:`prsa_ctrl.identification.modebracket.mode_bracket`) in each
    entry of a compliant plant's replay that only its residual's resonance refuses (fit % at least
    :data:`FIT_MIN_PERCENT`, error above the noise allowance): where the plant's own mode is
    placed, :func:`explained` does not read that resonance as one the model lacks."""
    if fidelity != "compliant":
        return
    from .modebracket import mode_bracket

    def replay(p, rec):
        return replay_records(p, [rec], shift, fidelity, check=check, closed_loops=closed_loops)[rec.name]

    for rec in records:
        e = entries.get(rec.name)
        if e is None or explained(e) or not e.get("finite") or e["fit_percent"] < FIT_MIN_PERCENT:
            continue
        b = mode_bracket(plant, rec, e, replay, resonance(e)[0])
        if b is not None:
            e["mode_bracket"] = b


def verdict(written: dict, free: dict, loo: dict | None) -> tuple[bool, list[str]]:
    """``(passes, reasons)``: every log explained by the written plant, the written plant within
    :data:`WRITTEN_TOLERANCE_POINTS` of the free fit on each log, each left-out log explained by
    the plant fitted on the others (``loo``: ``{name: replay entry or {"failed": reason}}``)."""
    reasons = []
    for name, e in written.items():
        if not explained(e):
            reasons.append(f"{name}: the written plant replays it at {e['fit_percent']:.1f} % (error "
                           f"{e['error_rms_rad_s']:.3g} rad/s, {e['error_rms_rad_s'] / max(e['noise_floor_rad_s'], 1e-300):.3g} x "
                           f"its noise floor {e['noise_floor_rad_s']:.3g} rad/s" + _resonance_text(e) + "); expected "
                           f"<= {NOISE_FACTOR:g} x the floor, or >= {FIT_MIN_PERCENT:g} % with no resonance in the residual")
        f = free.get(name)
        if f is not None and e.get("finite") and e["fit_percent"] < f["fit_percent"] - WRITTEN_TOLERANCE_POINTS:
            reasons.append(f"{name}: the written plant replays it at {e['fit_percent']:.1f} %, the free fit at "
                           f"{f['fit_percent']:.1f} % (tolerance {WRITTEN_TOLERANCE_POINTS:g} points)")
    for name, e in (loo or {}).items():
        if "failed" in e:
            reasons.append(f"{name}: the fit on the other logs failed ({e['failed']})")
        elif not explained(e):
            reasons.append(f"{name}: left out, the plant fitted on the other logs replays it at "
                           f"{e['fit_percent']:.1f} % ({e['error_rms_rad_s'] / max(e['noise_floor_rad_s'], 1e-300):.3g} x "
                           "its noise floor)")
    return not reasons, reasons


def _resonance_text(e: dict) -> str:
    if not e.get("finite") or e["fit_percent"] < FIT_MIN_PERCENT:
        return ""
    placed = (e.get("mode_bracket") or {}).get("placed")
    if placed:
        return ""
    fp, share = resonance(e)
    return (f"; {100 * share:.0f} % of the residual within 15 % of {fp:.4g} Hz, a resonance"
            if share >= RESONANCE_SHARE else "")


def _peak(residual: NDArray[np.float64], ts: float) -> tuple[float, float]:
    """Frequency (Hz) of the residual's largest spectral peak above 10 Hz and the share of the
    residual power within +/- 15 % of it."""
    from scipy.signal import welch

    f, p = welch(residual, fs=1.0 / ts, nperseg=min(len(residual), 2048))
    band = f > 10.0
    if not np.any(band) or float(np.sum(p)) <= 0:
        return 0.0, 0.0
    fb, pb = f[band], p[band]
    fp = float(fb[int(np.argmax(pb))])
    near = (f > 0.85 * fp) & (f < 1.15 * fp)
    return fp, float(np.sum(p[near]) / np.sum(p))


def _current_loop_hidden(result, fp: float) -> str:
    """What a resonance at ``fp`` (Hz) the model lacks does to a current-loop bandwidth the fit did
    not identify: the loop's whole lag at ``fp`` (at the written, base value) beside the up to
    180 deg a resonance turns the phase ('' when the bandwidth was identified). Measured on the
    foreign feed axis (tests/identification/foreign, 110 Hz mode, 800 Hz loop, 4 kHz): with the
    true two-mass physics the multisine alone sets the bandwidth to +-7.7 % (95 %, noise only,
    inertia free, delay given); the rigid model's misfit of the mode is 127 x the angle a +25 %
    bandwidth moves and, projected on it, would move the bandwidth by a factor e^2.2."""
    bw = "drive.current_loop_bandwidth_hz"
    plant = getattr(result, "plant", None)
    fc = plant.values.get(bw) if plant is not None and bw in (getattr(result, "not_identified", None) or {}) else None
    if not fc or not fc > 0:
        return ""
    lag = math.degrees(math.atan(fp / fc))
    return (f"; the current-loop bandwidth is not identified under this misfit (kept at {fc:.4g} Hz): its whole lag "
            f"at {fp:.4g} Hz is {lag:.1f} deg, small beside the up to 180 deg of the resonance the model lacks")


def diagnosis(written: dict, delay_search: dict | None, result, loo: dict | None = None) -> str:
    """One line naming the most likely missing physics of a fit whose written plant does not
    explain the data, tested in this order:

    1. wrong units or coordinates: every log replayed below 0 %, or the inertia at a bound of
       its range;
    2. a second mass: a log the written plant does not explain whose replay residual is a
       resonance (one spectral peak above 10 Hz holding :data:`RESONANCE_SHARE` or more of the
       residual power). Tested before the delay: a rigid model of a two-mass axis misfits
       every candidate delay, so an undecided delay search is then a consequence of the
       missing mode, not its cause;
    3. the delay: the delay search undecided or failed;
    4. a failure of the fit, not of the physics: a cross-validation refit (``loo``: ``{name:
       replay entry or {"failed": reason}}``) that did not converge from any of its starts while
       the written plant explains every log: nothing in the data is then evidence of missing
       physics;
    5. else the friction model (the residual largest where the speed is low or the load changes).

    The residual's peak is :func:`resonance`'s (each entry's ``time_s`` gives its sample time), the
    one the verdict judged.
    """
    bad = {n: e for n, e in written.items() if not explained(e)}
    fits = [e["fit_percent"] for e in written.values()]
    j_key = next((k for k in result.keys if k.endswith("inertia_kg_m2")), None)
    at_bound = j_key is not None and "bound" in str(result.not_identified.get(j_key, ""))
    if (fits and max(fits) < 0.0) or at_bound:
        return ("wrong units or coordinates: " + ("the inertia ends at a bound of its range" if at_bound else
                "no log is replayed better than its mean") + " (check the torque unit, --torque-constant, the angle "
                "unit and --log-format)")
    def peak_of(logs: dict):
        # the verdict's own peak (resonance(): each entry's sample time from its time_s, kept in the entry)
        peaks = [(*reversed(resonance(e)), n) for n, e in logs.items() if e.get("finite")]
        return max(peaks) if peaks else None

    def second_mass(share, fp, n):
        # the top peak named as what it is (a mode, or a torque periodic in the motor angle), and the other kind
        # where another log's residual holds it: both are named
        periodic = _position_periodic(written.get(n), share, fp, n)
        first = periodic or mode_text(share, fp, n)
        for s2, f2, m in sorted(((*reversed(resonance(e)), m) for m, e in bad.items() if m != n and e.get("finite")),
                                reverse=True):
            if s2 < RESONANCE_SHARE:
                break
            other = _position_periodic(written.get(m), s2, f2, m)
            if bool(other) != bool(periodic) and not (other or "").startswith("second mass or"):
                return first + "; besides, " + (other or mode_text(s2, f2, m))
        return first

    def mode_text(share, fp, n):
        if (getattr(result, "solver", None) or {}).get("fidelity") == "compliant":  # the model has the mode: not where the data have it
            return _mode_misplaced(result, share, fp, n, written.get(n))
        return (f"second mass: {100 * share:.0f} % of the replay residual of {n} lies within 15 % of {fp:.4g} Hz, "
                "a resonance the rigid model lacks (fit --fidelity compliant, or an FRF with the axial mode)"
                + _current_loop_hidden(result, fp))

    top = peak_of(bad)
    if top is not None and top[0] >= RESONANCE_SHARE:
        return second_mass(*top)
    if delay_search is not None and not delay_search.get("decided", True):
        return ("delay: the delay search could not decide the command delay (" + ", ".join(
            f"{s}: {'failed' if v is None else f'{v:.4g}'}" for s, v in delay_search.get("objective", {}).items())
            + "); give --delay-samples or --command-logged as the drive logs it")
    failed = {n: e["failed"] for n, e in (loo or {}).items() if "failed" in e}
    if failed and not bad:
        n, why = next(iter(failed.items()))
        why = why.split("; remedy")[0][:200]
        return (f"{FIT_FAILURE}: the cross-validation fit on the logs other than {n} did not "
                f"converge ({why}); the written plant explains every log, so the data give no evidence of "
                "missing physics; rerun with --no-cross-validation to accept it unvalidated, or give more or longer logs")
    if not bad:
        top = peak_of(written)
        if top is not None and top[0] >= RESONANCE_SHARE:
            return second_mass(*top)
    return ("friction model: the replay residual is not a resonance and the delay search singled out one delay; look at standstill, "
            "reversals and load changes (Stribeck keys, friction.torque_offset_n_m, a load-dependent loss)"
            + (f" (besides, the cross-validation fit without {', '.join(failed)} did not converge: a failure of the "
               "fit, not evidence about the physics)" if failed else ""))


def _position_periodic(entry: dict | None, share: float, fp: float, n: str) -> str:
    """The diagnosis of a residual peak that follows the motor angle, not time
    (:func:`prsa_ctrl.identification.periodic.periodic_or_mode`): a position-periodic torque
    (cogging, a pitch error), or '' when the peak is a mode's (or the log cannot tell them apart:
    then the words say so)."""
    from .periodic import periodic_or_mode

    pm = periodic_or_mode(entry, fp) if entry is not None and entry.get("finite") else None
    if pm is None or pm["verdict"] == "mode":
        return ""
    lo, hi = pm["speed_range_rad_s"]
    nums = (f"one sinusoid of the motor angle at {pm['cycles_per_rev']:.2f} cycles per revolution explains "
            f"{100 * pm['angle_share']:.0f} % of it out of sample, one of time at {pm['time_hz']:.4g} Hz "
            f"{100 * pm['time_share']:.0f} % (speed {lo:.3g}..{hi:.3g} rad/s)")
    if pm["verdict"] == "periodic":
        return (f"position-periodic torque: {100 * share:.0f} % of the replay residual of {n} lies within 15 % of "
                f"{fp:.4g} Hz and {nums}: a torque ripple of {pm['cycles_per_rev']:.1f} per revolution, cogging or "
                "the screw's lead deviation, that the plant's models lack, not a mode")
    return (f"second mass or position-periodic torque: {100 * share:.0f} % of the replay residual of {n} lies within "
            f"15 % of {fp:.4g} Hz, {pm['cycles_per_rev']:.2f} cycles per revolution at its speed, and {nums}: its "
            "speed varies too little to tell a mode from a torque ripple (cogging); the logs at other speeds decide "
            "(a staircase), or fit --fidelity compliant")


#: Keys that place a screw-driven compliant plant's axial mode (its stiffness and the masses on
#: either side of it are the inertia keys the time-domain fit fits anyway).
MODE_KEYS = ("axis.nut_stiffness_n_per_um", "axis.bearing_stiffness_n_per_um", "axis.moving_mass_kg",
             "contact.stiffness_n_per_mm_e")


def _mode_misplaced(result, share: float, fp: float, n: str, entry: dict | None = None) -> str:
    """The diagnosis of a compliant fit whose replay residual is a resonance: the model has an
    axial mode, but not at the data's. Measured on the judge's roller-2mass-d1-applied-si logs
    (tests/identification/foreign/gen_judge.py, truth 161.3 Hz at its multisine's 2000 N) fitted
    compliant without ``--frf``: the mode keys stayed the datasheet's (series formula 134.9 Hz) and
    96 % of the multisine's residual lay within 15 % of 150.4 Hz; the rigid model's diagnosis
    ("the rigid model lacks it, fit --fidelity compliant") named the flag already given."""
    plant = getattr(result, "plant", None)
    fitted = set(getattr(result, "keys", ()) or ())
    screw = plant is not None and getattr(plant, "screw_driven", False)
    placed = [k for k in MODE_KEYS if plant is not None and k in plant.values and k not in fitted
              and k.startswith("axis.") == screw]
    where = ""
    if plant is not None and getattr(plant, "screw_driven", False):
        try:
            where = (f"; the written plant's mode is at {plant.axial_mode_hz():.4g} Hz by the series formula (no load, "
                     "no nut loss)")
        except (ValueError, KeyError, ZeroDivisionError):
            where = ""
    from .compliant import LOGS_RESPONSE

    seeded = [k for k in placed if str(plant.sources.get(k, "")).startswith("two-mass fit of")]
    base = [k for k in placed if k not in seeded]
    logs = [k for k in seeded if str(plant.sources.get(k, "")).startswith(f"two-mass fit of {LOGS_RESPONSE}")]
    measured = [k for k in seeded if k not in logs]
    held = ((f"; {', '.join(measured)} from the measured response's two-mass fit" if measured else "")
            + (f"; {', '.join(logs)} from the two-mass fit of the logs' own response (through their speed loop), "
               "held by the fit" if logs else "")
            + (f"; {', '.join(base)} held at the base plant's values (not fitted: give the measured frequency "
               "response beside the logs, --frf FRF.csv, so the fit starts from its mode, or fit them with --fit)"
               if base else ""))
    moved = ""
    b = (entry or {}).get("mode_bracket") or {}
    err = (entry or {}).get("error_rms_rad_s")
    sides = [(s, b[s]["error_rms_rad_s"]) for s in ("below", "above")
             if isinstance(b.get(s), dict) and b[s].get("error_rms_rad_s") is not None]
    better = [s for s, v in sides if err is not None and v < err]
    if better:  # the mode bracket's side that replays the log better: where the data put the mode
        side = min(better, key=dict(sides).get)
        moved = (f"; the log is replayed better with the plant's mode moved {100 * MODE_BRACKET:g} % "
                 f"{'lower' if side == 'below' else 'higher'} (the mode bracket)")
    return (f"axial mode: {100 * share:.0f} % of the replay residual of {n} lies within 15 % of {fp:.4g} Hz, a "
            f"resonance the compliant model does not place there{where}{moved}{held}" + _current_loop_hidden(result, fp))


def refusal(diag: str) -> str:
    """The verdict's words for a fit that does not pass, with its :func:`diagnosis`: a fit that
    failed is not a plant that does not explain the data."""
    if diag.startswith(FIT_FAILURE):
        return f"the fitted plant could not be validated: {diag}"
    return f"the fitted plant does not explain the data; most likely missing physics: {diag}"


def _entry_report(e: dict) -> dict:
    """The JSON part of one replay entry (no traces)."""
    out = {k: e[k] for k in ("fit_percent", "error_rms_rad_s", "noise_floor_rad_s", "skip_samples", "finite") if k in e}
    out["explained"] = explained(e)
    if e.get("finite"):
        out["whiteness"] = whiteness((e["measured"] - e["model"])[e["skip_samples"]:])
        out["residual_peak_hz"], out["residual_peak_share"] = resonance(e)
    if "mode_bracket" in e:
        out["mode_bracket"] = e["mode_bracket"]
    return out


def validate_fit(result, records: Sequence[Record], validate: Sequence[Record], shift: int, fidelity: str,
                 refit=None, check=None, base: Plant | None = None, closed_loops=None):
    """The validated :class:`~prsa_ctrl.identification.common.FitResult` of a time-domain fit.

    1. Every record (fitted and ``validate``) is replayed through the plant as written
       (:func:`replay_records`); its fit % replaces the shooting segments' in ``fit_percent``
       (those move to ``solver["fit_percent_segments"]``) and its trace is the figures'
       ``"simulated"`` one.
    2. Keys kept at the base value (not identifiable): the plant with the free values is
       replayed too; where the written plant replays a record more than
       :data:`WRITTEN_TOLERANCE_POINTS` worse, the free values are written instead (their
       sources and a warning say why): a written plant is never worse on the user's logs than
       the free fit beyond that tolerance.
    3. With ``refit`` (``(records, start plant, attempt) -> FitResult`` at the same delay, one
       Gauss-Newton attempt of the time-domain fit's list, 0 the cautious trust region after a
       state-only warm-up, 2 the bold one) and more than one record: leave-one-out
       cross-validation, each record replayed by the plant fitted on the others (started from
       the fitted plant; a fit that fails there is retried from the ``base`` plant, then from the
       fitted plant with bolder steps; one that fails from every start fails the
       cross-validation, and the diagnosis names it a failure of the fit, not missing physics,
       when the written plant explains every log).
    4. :func:`verdict` (and a delay search that did not decide the delay: no pass either) and,
       when it is no, :func:`diagnosis`; all in ``solver["validation"]``
       (``passes``, ``reasons``, ``diagnosis``, per log the metrics and residual whiteness, the
       rule with its thresholds).
    """
    import dataclasses
    import copy

    from ..errors import FitError, PlantFileError
    from .delay import undecided_by_rejection

    recs_all = [*records, *validate]
    plant = result.plant
    params = copy.deepcopy(result.parameters)
    warns = list(result.warnings)
    cls = dict(closed_loops or {})
    written = replay_records(plant, recs_all, shift, fidelity, check=check, closed_loops=cls)
    kept = [k for k in result.keys if params[k].get("kept_base")]
    free = {}
    free_plant = None
    if kept:
        try:
            free_plant = plant.with_params({k: params[k]["value"] for k in kept}, name=plant.name)
        except (PlantFileError, ValueError):
            free_plant = None
        if free_plant is not None:
            free = replay_records(free_plant, records, shift, fidelity, check=check, closed_loops=cls)
            worse = {n: (written[n]["fit_percent"], f["fit_percent"]) for n, f in free.items()
                     if f.get("finite") and written[n]["fit_percent"] < f["fit_percent"] - WRITTEN_TOLERANCE_POINTS}
            if worse:
                why = "; ".join(f"{n} {a:.1f} % with the base values, {b:.1f} % free" for n, (a, b) in worse.items())
                srcs = dict(free_plant.sources)
                for k in kept:
                    srcs[k] = (f"fit: not identifiable alone ({params[k].get('reason', '')}); written all the same: with "
                               f"the base value the plant replays the logs worse than the free fit ({why}; tolerance "
                               f"{WRITTEN_TOLERANCE_POINTS:g} points)")
                    params[k]["kept_base"] = False
                    params[k]["written_although_not_identified"] = params[k].pop("reason", "")
                    params[k].pop("written", None)
                plant = dataclasses.replace(free_plant, sources=srcs)
                warns.append(f"{', '.join(kept)}: not identifiable, but the base value{'s' if len(kept) > 1 else ''} "
                             f"replay{'' if len(kept) > 1 else 's'} the logs worse than the free fit ({why}): the free "
                             "values are written (their intervals are wide: record the excitation named above)")
                written = {**{n: free[n] for n in free},
                           **replay_records(plant, list(validate), shift, fidelity, check=check, closed_loops=cls)}
    search = (result.solver.get("command_delay") or {}).get("search")
    bracket = delay_confirmed(search)
    if bracket:
        bracket_modes(plant, recs_all, written, shift, fidelity, check=check, closed_loops=cls)
    loo = None
    if refit is not None and len(records) > 1:
        loo = {}
        start = free_plant if free_plant is not None else plant
        # a failed fit is retried: from the base plant, then from the fitted plant with a bolder
        # trust region; a fit that fails from every start is a failure of the fit, not of the physics
        starts = [(start, 0, "the fitted plant"), *(() if base is None else ((base, 0, "the base plant"),)),
                  (start, 2, "the fitted plant, bolder steps")]
        for i, rec in enumerate(records):
            others = [r for j, r in enumerate(records) if j != i]
            errors = []
            for st, attempt, _ in starts:
                try:
                    r_i = refit(others, st, attempt)
                except (FitError, ValueError) as exc:
                    errors.append(str(exc)[:300])
                    continue
                e = replay_records(r_i.plant, [rec], shift, fidelity, check=check, closed_loops=cls)[rec.name]
                if bracket:
                    bracket_modes(r_i.plant, [rec], {rec.name: e}, shift, fidelity, check=check, closed_loops=cls)
                e["plant"] = {k: r_i.plant.values[k] for k in r_i.keys if k in r_i.plant.values}
                e["starts"] = len(errors) + 1
                loo[rec.name] = e
                break
            else:
                loo[rec.name] = {"failed": f"from {len(errors)} starts ({', '.join(w for *_, w in starts)}): "
                                           f"{errors[-1]}"}
    passes, reasons = verdict(written, free, loo)
    if search is not None and not search.get("decided", True):
        # a plant whose delay the data do not decide is not validated either: the current-loop
        # bandwidth trades against it (a one-sample error moves it by a factor of 2 or 3)
        passes = False
        reasons.append("the command delay is not decided by the data (objective per delay: " + ", ".join(
            f"{s_}: {'failed' if v is None else f'{v:.4g}'}" for s_, v in search.get("objective", {}).items())
            + f"; tolerance: a factor {search.get('ratio_tolerance')}); give --delay-samples N if you know it")
    diag = None if passes else diagnosis(written, search, result, loo)
    # a delay the search decided with the model this validation rejects for missing physics is undecided
    # (and one decided with a model a fit failure left unvalidated: the fit at the delay failed)
    failed_fit = not passes and diag.startswith(FIT_FAILURE)
    rejected = None if passes else undecided_by_rejection(result.solver.get("command_delay"), diag, failed=failed_fit)
    if rejected is not None:
        warns = [w for w in warns if not w.startswith("the command delay is decided by")] + [rejected[1]]
        key = "drive.command_delay_samples"
        if key in plant.sources:  # a file written all the same (--force) says it too
            plant = dataclasses.replace(plant, sources={**plant.sources, key: plant.sources[key] + (
                "; not decided: preferred by a model that could not be validated (a fit at the delay failed)"
                if failed_fit else "; not decided: preferred by a model the data reject")})
    # every [uncertainty] entry must hold the value written (a user's absolute bounds may not: the
    # data contradict them): the fit's own entry where the written value is the fitted one, else none
    own = {k: params[k] for k in result.keys if k in plant.values and plant.values[k] == params[k]["value"]}
    sds = [(v["ci95"][1] - v["ci95"][0]) / (2 * 1.959963984540054) for v in own.values()]
    plant, notes = hold_written_values(plant, None, own, uncertainty_entries(plant, own, ", ".join(r.name for r in records), sds))
    warns.extend(notes)
    fit_pct = dict(result.fit_percent)
    traces = {n: dict(t) for n, t in result.traces.items()}
    for n, e in written.items():
        fit_pct[n] = round(float(e["fit_percent"]), 3) if math.isfinite(e["fit_percent"]) else e["fit_percent"]
        if e.get("finite"):
            traces.setdefault(n, {"time_s": e["time_s"], "measured": e["measured"], "model": e["model"]})
            traces[n]["simulated"] = {"time_s": e["time_s"], "measured": e["measured"], "model": e["model"],
                                      "label": ("plant as written, closed-loop replay from the reference"
                                                if e["replay"] == CLOSED_LOOP_MODE else
                                                f"plant as written, prediction-error replay ({OBSERVER_HZ:g} Hz)")}
    solver = dict(result.solver)
    if rejected is not None:
        solver["command_delay"] = rejected[0]
    solver["fit_percent_segments"] = {n: result.fit_percent[n] for n in written if n in result.fit_percent}
    modes = sorted({e["replay"] for e in written.values()})
    solver["validation"] = {
        "replay": "; ".join(modes),
        "replay_per_log": {n: e["replay"] for n, e in written.items()},
        "passes": passes,
        "reasons": reasons,
        "diagnosis": diag,
        "written_plant": {n: _entry_report(e) for n, e in written.items()},
        "free_fit": {n: _entry_report(e) for n, e in free.items()},
        "cross_validation": None if loo is None else {
            n: ({"failed": e["failed"]} if "failed" in e else {**_entry_report(e), "plant": e["plant"]})
            for n, e in loo.items()},
        "rule": (f"the delay decided by the search (when searched; a delay the search decided with a model this "
                 f"validation rejects for missing physics, or cannot run on because a fit at the delay failed, is "
                 f"reported undecided); every log explained by the written plant (replay fit >= {FIT_MIN_PERCENT:g} % or replay error <= "
                 f"{NOISE_FACTOR:g} x the log's noise floor), the written plant within {WRITTEN_TOLERANCE_POINTS:g} "
                 "fit-% points of the free fit on each log, and with more than one log each left-out log explained by "
                 "the plant fitted on the others; a compliant plant's residual resonance at its own mode is not one it "
                 f"lacks when the log is replayed worse with that mode moved {100 * MODE_BRACKET:g} % down and up (the "
                 "mode bracket, only with the delay given or decided by the objective ratio); residual whiteness (lags "
                 f"{', '.join(map(str, ACF_LAGS))}, band 1.96/sqrt(N); Ljung-Box over lags 1..{max(ACF_LAGS)} at 5 %) is "
                 "reported, not tested"),
    }
    if not passes:
        warns.append(f"validation failed: {reasons[0]}" + (f" (and {len(reasons) - 1} more)" if len(reasons) > 1 else "")
                     + ("; " + diag if diag.startswith(FIT_FAILURE) else f"; most likely missing physics: {diag}"))
    return dataclasses.replace(result, plant=plant, parameters=params, fit_percent=fit_pct, warnings=warns,
                               solver=solver, traces=traces)
