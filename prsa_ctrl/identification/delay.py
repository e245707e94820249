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
fits each whole-sample shift the bandwidth leaves room for, starting each from the bandwidth
with the same total lag, and takes the shift with the smallest objective. It is *decided* when
every other fitted shift's objective is at least :data:`DELAY_OBJECTIVE_RATIO` times larger;
otherwise a warning names the shifts that fit alike and the keys whose values move beyond their
95 % intervals between them.
"""

from __future__ import annotations

import math
from typing import Callable

from ..errors import FitError
from ..plant.plantfile import Plant
from .common import FitResult

__all__ = ["CONVENTIONS", "DEFAULT_CONVENTION", "DELAY_OBJECTIVE_RATIO", "MAX_SHIFT", "plant_shift",
           "search_delay", "with_command_delay"]

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
#: Largest shift searched or accepted, samples.
MAX_SHIFT = 10
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
    if plant.command_delay_samples != n or how.startswith("found"):
        with_delay = plant.with_params({"drive.command_delay_samples": n}, name=plant.name)
        sources = dict(with_delay.sources)
        sources["drive.command_delay_samples"] = (f"fit: {how}, {shift} sample(s) from the logged command (logged as "
                                                  f"{command_logged}) to its action")
        plant = Plant(name=with_delay.name, values=with_delay.values, sources=sources, origin=with_delay.origin,
                      description=with_delay.description, uncertainty=with_delay.uncertainty,
                      mechanism=with_delay.mechanism, defaulted=with_delay.defaulted,
                      mechanism_source=with_delay.mechanism_source)
    solver = dict(result.solver)
    solver["command_delay"] = {"shift_samples": int(shift), "command_logged": command_logged,
                               "drive_command_delay_samples": int(n), "how": how,
                               **({"search": solver.pop("delay_search")} if "delay_search" in solver else {})}
    return FitResult(plant, result.parameters, result.reflected_inertia_kg_m2, result.correlation, result.keys,
                     result.fit_percent, warns, solver, result.traces, result.delay,
                     result.not_identified, result.covariance)


def search_delay(fit_at: Callable[[int, Plant], FitResult], plant: Plant, keys, ts: float,
                 max_shift: int = 4) -> tuple[int, FitResult]:
    """Fit every whole-sample shift ``0..max_shift`` the current-loop lag leaves room for and
    return the best ``(shift, result)`` (module docstring).

    Parameters
    ----------
    fit_at : callable
        ``(shift, start plant) -> FitResult``; raises :class:`FitError` when the fit fails.
    plant : Plant
        Base plant (its bandwidth starts the first fit).
    keys : sequence of str
        The fitted keys (with the bandwidth among them, each shift starts from the bandwidth of
        the same total lag; without it every shift starts from the base plant).
    ts : float, s
        Sample time of the records.
    max_shift : int
        Largest shift tried.

    Returns
    -------
    (int, FitResult)
        The shift and its fit; the fit's ``solver["delay_search"]`` lists the objective of every
        shift tried (``None``: the fit failed) and whether the data decided it, and its warnings
        say when they did not.
    """
    if isinstance(max_shift, bool) or not isinstance(max_shift, int) or not 0 <= max_shift <= MAX_SHIFT:
        raise ValueError(f"max_shift = {max_shift!r}; expected an integer 0..{MAX_SHIFT}")
    fits: dict[int, FitResult | None] = {}
    errors: dict[int, str] = {}
    lag = None  # total lag (s) of the first converged fit: current loop + shift
    for shift in range(max_shift + 1):
        start = plant
        if lag is not None and _BW in keys:
            rest = lag - shift * ts
            if rest < _MIN_LAG_SAMPLES * ts:
                break  # no current-loop lag left for this shift or any longer one
            start = plant.with_params({_BW: min(1.0 / (2 * math.pi * rest), 0.9 * 10.0 / ts)})
        try:
            fits[shift] = fit_at(shift, start)
        except FitError as exc:
            fits[shift], errors[shift] = None, str(exc)
            continue
        if lag is None:
            f_c = fits[shift].parameters[_BW]["value"] if _BW in keys else fits[shift].plant.values[_BW]
            lag = shift * ts + 1.0 / (2 * math.pi * f_c)  # the fitted value, also where it is not written
        good = {s: r for s, r in fits.items() if r is not None}
        best = min(good, key=lambda s: good[s].solver["objective"])
        if _BW not in keys and shift >= best + 2:
            break  # two shifts past the best without the bandwidth to trade: the objective only grows
    good = {s: r for s, r in fits.items() if r is not None}
    if not good:
        raise FitError(f"fit did not converge at any command delay 0..{max(fits)} samples: "
                       + "; ".join(f"{s}: {e}" for s, e in errors.items()))
    best = min(good, key=lambda s: good[s].solver["objective"])
    res = good[best]
    f_best = res.solver["objective"]
    close = [s for s in good if s != best and good[s].solver["objective"] < DELAY_OBJECTIVE_RATIO * f_best]
    warns = list(res.warnings)
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
    solver = dict(res.solver)
    solver["delay_search"] = {"objective": {str(s): (None if r is None else float(r.solver["objective"]))
                                            for s, r in sorted(fits.items())},
                              "decided": not close, "ratio_tolerance": DELAY_OBJECTIVE_RATIO}
    out = FitResult(res.plant, res.parameters, res.reflected_inertia_kg_m2, res.correlation, res.keys,
                    res.fit_percent, warns, solver, res.traces, res.delay, res.not_identified,
                    res.covariance)
    return best, out
