"""What a measured frequency response (torque command -> motor speed) shows before and beside a
parametric fit: its resonances, found on the data alone, and its low-frequency inertia against
the base plant's. The FRF path (:func:`prsa_ctrl.identification.frfplant.fit_frf_structure`)
uses them to say what it sees instead of guessing:

* a fit whose solver fails is diagnosed from the data: a units check that fails (the inertia of
  the low-frequency asymptote ``|G| -> 1 / (J w)`` far from the base plant's) blames the units;
  a response with more resonances than the models hold (the rigid axis none, the two-mass axis
  one) is named with their frequencies; otherwise the failure is reported as the solver's;
* a fit that converged is refused when the response shows a resonance its model lacks (a second
  mode above the first axial mode, e.g. a coupling's): the fit then bends its current loop,
  delay and inertia to absorb it (measured on gen_third's roller 39x10: current loop -25 %,
  delay 1 sample against 2, inertia -5 %, or with the two-mass model +28 %).

Resonances (:func:`resonances`): local maxima of ``ln(w |G|)`` (the inverse apparent inertia,
nepers), which falls monotonically for a rigid axis with a current-loop lag and delay (their
magnitude is flat or falling, the sampled forms too), and rises to a peak at each mode after its
anti-resonance. A maximum counts when its prominence is at least :data:`RESONANCE_NOISE` times
the response's point-to-point noise (the robust spread of the differences of ``ln(w |G|)``
between neighbouring frequencies, over sqrt 2) **and** at least :data:`RESONANCE_MIN_DB`.
Measured on the 12 foreign FRFs of tests/identification/test_foreign_generators.py at seeds 0, 1
and 2: the axial modes stand 57..142 x the noise and 19..33 dB high, the coupling modes of
gen_third 25..64 x and 11..19 dB; the largest noise maximum 6.8 x and 2.4 dB.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

__all__ = ["choose_structure_checked", "suggested_band", "resonances", "low_frequency_inertia", "unexplained_resonances",
           "failure_diagnosis", "units_line", "unexplained_line", "RESONANCE_NOISE", "RESONANCE_MIN_DB", "MODE_MATCH", "SAME_RESONANCE",
           "UNITS_RATIO"]

#: A maximum of ``ln(w |G|)`` is a resonance when its prominence is at least this many times the
#: response's point-to-point noise (module docstring: noise maxima reach 6.8 x, modes 25 x and more).
RESONANCE_NOISE = 15.0
#: ... and at least this high (dB): noise maxima reach 2.4 dB, the weakest coupling mode 11 dB.
RESONANCE_MIN_DB = 4.0
#: Peaks of different records within this fraction of each other are one resonance, seen in each
#: (the logs' own responses: one per log, the same axis). Why 5 %: the mode moves with the
#: operating point (the judge's ball screw: 132.3 Hz driving the load, 130.8 Hz lossless, 1.1 %;
#: its roller screw 161.3 and 157.5 Hz, 2.4 %) and the peak sits on each record's grid; distinct
#: modes of one axis lie far further apart (gen_third: the axial mode at 116.7 Hz, the coupling's at
#: 978.5 Hz). Within one record, peaks are never merged. Without it, the second generator's feed
#: axis (multisine and staircase responses, both peaking at 110.8 Hz) counted one resonance twice
#: and was refused for "2 resonances ... up to the geometric mean of 110.8 and 110.8 Hz".
SAME_RESONANCE = 0.05
#: A resonance of the data is the fitted model's mode when their frequencies agree within this
#: fraction (the peak of ``w |G|`` sits near, not at, the modal frequency: damping, the grid).
MODE_MATCH = 0.15
#: The units check: the low-frequency inertia of the response within this factor of the base
#: plant's reflected inertia (deg/s is 57 x off, rpm 9.5 x, a load-side response a^2 x; a base
#: plant of another axis typically several x).
UNITS_RATIO = 3.0

_NP_TO_DB = 20.0 / math.log(10.0)


def _records(frf) -> list:
    out = []
    for r in frf if isinstance(frf, (list, tuple)) else [frf]:
        f, g = np.asarray(r.frequency_hz, float), np.asarray(r.response, complex)
        ok = np.isfinite(f) & (f > 0) & np.isfinite(g) & (g != 0)
        o = np.argsort(f[ok])
        out.append((f[ok][o], g[ok][o]))
    return out


def resonances(frf) -> list[dict]:
    """The resonances the response shows (module docstring), lowest frequency first; a resonance
    seen in several records (peaks of different records within :data:`SAME_RESONANCE`) counts
    once, as its most prominent peak.

    Parameters
    ----------
    frf : FrfRecord or sequence of FrfRecord
        Torque command (N m) -> motor speed (rad/s); each record searched on its own.

    Returns
    -------
    list of dict
        ``{"frequency_hz", "height_db", "over_noise"}``: the peak's frequency (Hz, the grid
        point), its prominence (dB of ``w |G|``) and that prominence over the noise (-).
        Empty for a record of fewer than 8 points.
    """
    from scipy.signal import find_peaks

    found = []
    for rec, (f, g) in enumerate(_records(frf)):
        if len(f) < 8:
            continue
        y = np.log(2.0 * math.pi * f * np.abs(g))
        d = np.diff(y)
        noise = 1.4826 * float(np.median(np.abs(d - np.median(d)))) / math.sqrt(2.0)
        need = max(RESONANCE_NOISE * noise, RESONANCE_MIN_DB / _NP_TO_DB)
        idx, props = find_peaks(y, prominence=need)
        for i, p in zip(idx, props["prominences"]):
            found.append((rec, {"frequency_hz": float(f[i]), "height_db": float(p * _NP_TO_DB),
                                "over_noise": float(p / noise) if noise > 0 else math.inf}))
    kept: list[tuple[int, dict]] = []
    for rec, r in sorted(found, key=lambda x: -x[1]["height_db"]):  # the most prominent peak of a resonance first
        if not any(k != rec and abs(math.log(r["frequency_hz"] / q["frequency_hz"])) <= math.log1p(SAME_RESONANCE)
                   for k, q in kept):
            kept.append((rec, r))
    return sorted((r for _, r in kept), key=lambda r: r["frequency_hz"])


def low_frequency_inertia(frf) -> float:
    """The response's inertia at low frequency, ``1 / (w |G|)`` (kg m^2, or kg for a linear
    axis), the median over the lowest quarter of each record's points (at least 3,
    :func:`prsa_ctrl.identification.twomass.low_band_inertias`, the FRF fits' start): the
    asymptote of both the rigid and the two-mass axis."""
    from .twomass import low_band_inertias

    vals = [low_band_inertias(f, g) for f, g in _records(frf)]
    return float(np.median(np.concatenate(vals))) if vals else float("nan")


def unexplained_resonances(frf, fit) -> list[dict]:
    """The resonances of the response (:func:`resonances`) that the fitted model lacks: all of
    them for the rigid model, all but the one within :data:`MODE_MATCH` of the two-mass model's
    mode (``fit``: a :class:`~prsa_ctrl.identification.twomass.FrfModelFit`)."""
    found = resonances(frf)
    if fit.structure != "two-mass" or not found:
        return found
    fr = fit.value("resonance_hz")
    near = min(found, key=lambda r: abs(math.log(r["frequency_hz"] / fr)))
    if abs(near["frequency_hz"] / fr - 1.0) > MODE_MATCH:
        return found
    return [r for r in found if r is not near]


def _named(rs: Sequence[dict]) -> str:
    return " and ".join(f"{r['frequency_hz']:.4g} Hz ({r['height_db']:.3g} dB, {r['over_noise']:.3g} x the noise)"
                        for r in rs)


def units_line(frf, reflected_inertia: float) -> tuple[bool, str]:
    """``(passes, words)`` of the units check (:data:`UNITS_RATIO`) against the base plant's
    reflected inertia (kg m^2)."""
    j = low_frequency_inertia(frf)
    ratio = j / reflected_inertia if reflected_inertia > 0 else float("nan")
    ok = bool(math.isfinite(ratio) and 1.0 / UNITS_RATIO <= ratio <= UNITS_RATIO)
    return ok, (f"the response's low-frequency inertia 1/(w |G|) = {j:.4g} is {ratio:.3g} x the base plant's "
                f"{reflected_inertia:.4g} kg m^2 (units check {'passed' if ok else 'failed'}: "
                f"1/{UNITS_RATIO:g}..{UNITS_RATIO:g})")


def unexplained_line(frf, fit, found: Sequence[dict], sample_time_s: float = 0.0) -> str:
    """The refusal of a converged fit whose model lacks the resonances ``found`` (one line)."""
    first = [r for r in resonances(frf) if r not in found]
    what = (f" above the first axial mode near {first[0]['frequency_hz']:.4g} Hz" if first else "")
    model = ("the two-mass model holds one mode" if fit.structure == "two-mass" else "the rigid model holds none")
    fc = fit.values["current_loop_bandwidth_hz"]
    d = fit.value("delay_s")
    delay = f"{d / sample_time_s:.3g} samples" if sample_time_s > 0 else f"{d:.3g} s"
    return (f"no plant written: the response shows {'a resonance' if len(found) == 1 else 'resonances'}{what} that "
            f"the {fit.structure} fit does not explain, near {_named(found)} ({model}); fitted over "
            f"{'it' if len(found) == 1 else 'them'}, the model's inertia ({fit.value('total_inertia_kg_m2'):.4g}), "
            f"current loop ({fc['value']:.4g} Hz{', held' if fc.get('ci95') is None else ''}) and delay ({delay}) "
            "take up what it cannot explain, so none of them can be trusted; a second mode (a coupling's, the "
            "motor's mount) is physics the plant's models lack: fit the time-domain logs, or measure with that mode "
            "out of the band")


def _down(x: float) -> float:
    """``x`` > 0 rounded down to three significant digits."""
    e = 10.0 ** (math.floor(math.log10(x)) - 2)
    return math.floor(x / e * (1 + 1e-12)) * e


def suggested_band(frf, found: Sequence[dict]) -> tuple[float, float]:
    """The band (Hz) that keeps the lowest resonance of ``found`` and leaves out the next: from the
    responses' lowest frequency up to the geometric mean of the two resonances, or the
    anti-resonance between them (the lowest ``w |G|`` there: the next mode's notch) when that is
    lower; three significant digits, rounded down (the lowest point stays inside)."""
    f1, f2 = found[0]["frequency_hz"], found[1]["frequency_hz"]
    top = math.sqrt(f1 * f2)
    lows = []
    for f, g in _records(frf):
        between = (f > f1) & (f < f2)
        if np.any(between):
            y = np.log(f[between] * np.abs(g[between]))
            top = min(top, float(f[between][int(np.argmin(y))]))
        if len(f):
            lows.append(float(f[0]))
    lo = min(lows) if lows else 0.0
    return (_down(lo) if lo > 0 else 0.0), _down(top)


def _beyond_models(found: Sequence[dict], units: str, solver: str | None = None, frf=None) -> str:
    band = ""
    if frf is not None:
        lo, hi = suggested_band(frf, found)
        band = (f"; fit the model in the band below the mode above the first (from the data: up to the geometric "
                f"mean of {found[0]['frequency_hz']:.4g} and {found[1]['frequency_hz']:.4g} Hz, or below the "
                f"anti-resonance between them): --frf-band {lo:g},{hi:g}")
    return (f"no plant written: the response shows {len(found)} resonances, near {_named(found)}; the rigid model "
            "holds none and the two-mass model one (the first axial mode), so "
            + (f"the fit cannot follow the one above it and its solver stopped ({solver})" if solver else
               "a fit over the one above it would take it up in its current loop, delay and inertia (not fitted)")
            + f"; the units are right ({units}): a second mode (a coupling's, the motor's mount) is physics the "
            "plant's models lack" + (band or ": fit the time-domain logs, or measure with that mode out of the band"))


def failure_diagnosis(frf, reflected_inertia: float, exc: BaseException) -> str:
    """The one line of an FRF fit whose solver failed (``exc``): what the data show.

    Parameters
    ----------
    frf : sequence of FrfRecord
    reflected_inertia : float, kg m^2
        The base plant's reflected inertia at the motor.
    exc : BaseException
        The solver's failure (its words are kept, after the diagnosis).
    """
    ok, units = units_line(frf, reflected_inertia)
    found = resonances(frf)
    solver = " ".join(str(exc).split()).split("; remedy:")[0]  # (its remedy guessed the units: the check says)
    if not ok:
        return (f"no plant written: {units}; expected the response in (rad/s)/(N m) at the motor (not deg/s, rpm or "
                f"load coordinates) and a base plant of this axis (--plant); the fit: {solver}")
    if len(found) >= 2:
        return _beyond_models(found, units, solver, frf)
    return (f"no plant written: the FRF fit's solver failed ({solver}); not the units ({units}) and no resonance "
            "beyond the models' (" + (f"one near {_named(found)}" if found else "none") + "): a failure of the solver "
            "on this response; remedy: rerun with --verbose and report it with the response")


def choose_structure_checked(frf, reflected_inertia: float, *, sample_time_s: float = 0.0,
                             current_loop_bandwidth_hz: float | None = None, upper_residual: bool = False):
    """:func:`prsa_ctrl.identification.twomass.choose_structure`, a solver failure re-raised as
    :func:`failure_diagnosis`'s line (FitError, the solver's as its cause); ``reflected_inertia``
    (kg m^2) the base plant's, for the units check. A response with two resonances or more (and
    units that pass their check) is refused before any fit: neither model holds more than one, so
    the fit's verdict is known (:func:`unexplained_resonances` would refuse it) and its solver's
    budget (4000 evaluations on gen_third's ball 40x16, 4.8 s CPU) is spared; the refusal names
    the band that leaves the second out (:func:`suggested_band`, ``--frf-band``). ``upper_residual``:
    the models carry the tail of modes above the band
    (:func:`prsa_ctrl.identification.twomass.fit_frf_model`)."""
    from ..errors import FitError
    from .twomass import choose_structure

    found = resonances(frf)
    if len(found) >= 2:  # more modes than either model holds: refused before a fit that would take them up
        ok, units = units_line(frf, reflected_inertia)
        if ok:  # (else the caller's inertia check names the units)
            raise FitError(_beyond_models(found, units, frf=frf))
    try:
        return choose_structure(frf, sample_time_s=sample_time_s, current_loop_bandwidth_hz=current_loop_bandwidth_hz,
                                upper_residual=upper_residual)
    except FitError as exc:
        raise FitError(failure_diagnosis(frf, reflected_inertia, exc)) from exc
