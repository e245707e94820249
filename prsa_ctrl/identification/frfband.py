"""A frequency-response fit on a band: the reduced-order model an identification engineer fits
in the band the loop uses, with the modes above it named, not modelled
(``prsa-fit --frf FRF.csv --frf-band FMIN_HZ,FMAX_HZ``; the library's ``band`` of
:func:`prsa_ctrl.identification.frfplant.fit_frf_structure` and
:func:`prsa_ctrl.identification.calibrate.calibrate_frf`).

* The points inside ``[FMIN, FMAX]`` (Hz, both included) are fitted; the resonance check
  (:mod:`prsa_ctrl.identification.frfcheck`) runs on them, so a band that holds two resonances is
  refused as a whole response is.
* The resonances of the whole response above the band are listed in the report and in the
  written keys' sources (frequency, and that the model omits them). A band that leaves a
  resonance out below it is bad input: above a mode the response is the motor side's alone, and
  the model's inertia would not be the axis's; so is a band that holds a mode but starts above
  its anti-resonance (the lowest point of ``w |G|`` below the mode's peak).
* A resonance omitted **above** the band leaves its tail inside it: below its frequency a mode
  ``r s / (s^2 + w^2)`` of the collocated response is ``(r / w^2) s``, the "upper residual" of
  modal analysis. The models then carry that compliance ``R >= 0``
  (:func:`prsa_ctrl.identification.twomass.fit_frf_model`'s ``upper_residual``) and the
  current loop is held at the base plant's value: in a band that ends below the omitted mode,
  the residual, the current loop's lag and the delay are one lag to first order (magnitude
  ``-(R J + 1 / (2 w_c^2)) w^2``, phase ``-(1 / w_c + T) w``). Measured on
  tests/identification/foreign/gen_third.py's responses (ball 40x16, roller 39x10, seed 0) cut
  at 250..500 Hz: the current loop fitted free with the residual came out 547..3112 Hz against a
  true 800 and 1000 Hz (intervals +-40..150 %), without the residual 317..499 Hz with intervals
  of +-5 % that excluded the truth (the tail taken up as lag); held with the residual, the
  inertia, the mode and the delay are those of the held value.
* The fit %, the intervals and the residual are the band's (the report says so).
* A band that covers every point of the responses changes nothing (the same records are fitted).

Bad input (ValueError, one line naming the value as typed): a band that is not two numbers
``FMIN,FMAX`` with ``0 <= FMIN < FMAX``, one that holds no point of the responses, one that leaves
a resonance out below it or starts above the anti-resonance of one it holds, or fewer points
than twice the parameters of the model it must fit (the fits' own minimum,
:func:`prsa_ctrl.identification.twomass.fit_frf_model`).
"""

from __future__ import annotations

import dataclasses
from typing import Mapping, Sequence

import numpy as np

__all__ = ["parse_band", "apply_band", "band_lines", "band_warnings", "source_note", "omitted_text", "fc_reason", "FLAG"]

#: The flag that gives the band (as the messages name it).
FLAG = "--frf-band"

#: Fitted parameters of each model with the upper residual (twomass: rigid 4, two-mass 7, + 1); a
#: band needs twice the two-mass model's points.
_PARAMS = {"rigid": 5, "two-mass": 8}


def _typed(band, typed: str | None) -> str:
    return typed if typed is not None else f"{band[0]!r},{band[1]!r}"


def parse_band(text: str, flag: str = FLAG) -> tuple[float, float]:
    """``FMIN_HZ,FMAX_HZ`` as typed -> ``(fmin, fmax)`` Hz, or ValueError naming it."""
    from ..options import check_number

    parts = str(text).split(",")
    want = "two frequencies FMIN_HZ,FMAX_HZ with 0 <= FMIN < FMAX, e.g. 1,300"
    if len(parts) != 2:
        raise ValueError(f"{flag} {text!r}: expected {want}")
    vals = []
    for p, which in zip(parts, ("FMIN", "FMAX")):
        try:
            x = float(p)
        except ValueError:
            raise ValueError(f"{flag} {text!r}: {p.strip()!r} is not a number; expected {want}") from None
        vals.append(check_number(f"{flag} {text!r}: {which}", x, 0.0, unit="Hz", typed=p.strip()))
    if not vals[0] < vals[1]:
        raise ValueError(f"{flag} {text!r}: FMIN {vals[0]:g} Hz is not below FMAX {vals[1]:g} Hz (an empty or inverted "
                         f"band); expected {want}")
    return vals[0], vals[1]


def apply_band(frf: Sequence, band: tuple[float, float], *, typed: str | None = None) -> tuple[list, dict | None]:
    """The responses cut to ``band`` (Hz) and what the cut leaves out.

    Parameters
    ----------
    frf : sequence of FrfRecord
    band : (float, float), Hz
        ``(fmin, fmax)``, both included.
    typed : str, optional
        The band as the user typed it (the messages name it).

    Returns
    -------
    (list of FrfRecord, dict or None)
        The records inside the band and ``{"band_hz", "points", "of", "omitted", "above"}``
        (``omitted``: the whole responses' resonances outside the band,
        :func:`prsa_ctrl.identification.frfcheck.resonances`; ``above``: some lie above it);
        ``(frf, None)`` unchanged when the band covers every point.

    Raises
    ------
    ValueError
        An empty or inverted band, none of the responses' points inside, or fewer than the model
        needs (one line naming the band as typed).
    """
    from ..options import check_number
    from .frfcheck import resonances

    shown = _typed(band, typed)
    lo = check_number(FLAG, band[0], 0.0, typed=shown, expected="a band 0 <= FMIN < FMAX Hz")
    hi = check_number(FLAG, band[1], 0.0, typed=shown, expected="a band 0 <= FMIN < FMAX Hz")
    if not lo < hi:
        raise ValueError(f"{FLAG} {shown}: FMIN {lo:g} Hz is not below FMAX {hi:g} Hz (an empty or inverted band); "
                         "expected 0 <= FMIN < FMAX")
    frf = list(frf)
    f_all = np.concatenate([np.asarray(fr.frequency_hz, float) for fr in frf])
    inside = [(fr.frequency_hz >= lo) & (fr.frequency_hz <= hi) for fr in frf]
    n_in, n_all = int(sum(int(np.count_nonzero(m)) for m in inside)), len(f_all)
    if n_in == n_all:
        return frf, None
    need = 2 * _PARAMS["two-mass"]  # (the structure test fits the two-mass model whatever the fidelity)
    if n_in == 0:
        raise ValueError(f"{FLAG} {shown}: no point of the responses lies in it (they span "
                         f"{float(np.min(f_all)):.4g}..{float(np.max(f_all)):.4g} Hz); expected a band inside the data")
    if n_in < need:
        raise ValueError(f"{FLAG} {shown}: {n_in} point(s) of the responses lie in it; expected at least {need} (twice "
                         f"the two-mass model's {need // 2} parameters with the modes above the band: the structure "
                         "test fits it)")
    cut = []
    for fr, m in zip(frf, inside):
        if not np.any(m):
            continue
        coh = None if fr.coherence is None else np.asarray(fr.coherence)[m]
        cut.append(dataclasses.replace(fr, frequency_hz=np.asarray(fr.frequency_hz)[m],
                                       response=np.asarray(fr.response)[m], coherence=coh))
    found = resonances(frf)
    omitted = [dict(r, side="above" if r["frequency_hz"] > hi else "below")
               for r in found if not lo <= r["frequency_hz"] <= hi]
    below = [r for r in omitted if r["side"] == "below"]
    if below:  # above a mode the response's low-frequency inertia is the motor side's, not the axis's
        raise ValueError(f"{FLAG} {shown}: the response's resonance near {below[0]['frequency_hz']:.4g} Hz lies below "
                         "the band: above a mode the response is the motor side's alone, so the model's inertia would "
                         "not be the axis's; expected a band from the responses' lowest frequencies that holds the "
                         "first resonance or ends below it")
    # a mode inside the band needs the anti-resonance below it inside too (the trough of w |G|
    # below the peak): a band that starts above it sees the motor side alone at its lowest points
    inner = [r["frequency_hz"] for r in found if lo <= r["frequency_hz"] <= hi]
    if inner:
        f_r = inner[0]
        troughs = [t for t in (_trough_below(fr, f_r) for fr in frf) if t is not None]
        f_all_in = f_all[(f_all >= lo) & (f_all <= hi)]
        if troughs and not np.any(f_all_in < min(troughs)):  # (the trough needs a point of the band below it)
            raise ValueError(f"{FLAG} {shown}: it holds the response's resonance near {f_r:.4g} Hz but not the "
                             f"anti-resonance below it (near {min(troughs):.4g} Hz): the response at the band's lowest "
                             "points is the motor side's alone, so the model's inertia would not be the axis's; "
                             "expected a band that starts below the anti-resonance (from the responses' lowest "
                             "frequencies) or ends below the resonance")
    info = {"band_hz": [float(lo), float(hi)], "typed": shown, "points": n_in, "of": n_all,
            "omitted": omitted, "above": any(r["side"] == "above" for r in omitted)}
    return cut, info


def _trough_below(fr, f_r: float) -> float | None:
    """The frequency (Hz) of the lowest ``w |G|`` of the record ``fr`` below ``f_r`` Hz (the
    anti-resonance below a collocated mode), or None with fewer than 2 points there."""
    f = np.asarray(fr.frequency_hz, float)
    m = f < f_r
    if np.count_nonzero(m) < 2:
        return None
    return float(f[m][np.argmin(f[m] * np.abs(np.asarray(fr.response)[m]))])


def omitted_text(info: Mapping) -> str:
    """``the resonance(s) near X Hz above/below the band`` (empty when none)."""
    rs = info.get("omitted") or []
    if not rs:
        return ""
    return ("the model omits the response's resonance" + ("s" if len(rs) > 1 else "") + " near "
            + " and ".join(f"{r['frequency_hz']:.4g} Hz ({r['height_db']:.3g} dB, {r['side']} the band)" for r in rs))


def source_note(info: Mapping | None) -> str:
    """What the written keys' sources add after the responses' names (empty without a band)."""
    if not info:
        return ""
    lo, hi = info["band_hz"]
    om = omitted_text(info)
    return f" in the band {lo:.6g}..{hi:.6g} Hz" + (f" ({om})" if om else "")


def band_warnings(info: Mapping | None) -> list[str]:
    """The report's warnings of a band fit."""
    if not info:
        return []
    lo, hi = info["band_hz"]
    out = [f"fitted on the band {lo:.6g}..{hi:.6g} Hz only ({FLAG} {info['typed']}: {info['points']} of {info['of']} "
           "points): the fit %, the intervals and the structure test are the band's"]
    om = omitted_text(info)
    if om:
        out.append(f"{om}: the written plant does not have "
                   + ("them" if len(info["omitted"]) > 1 else "it")
                   + (" (the fit carries the tail of the modes above the band as an upper residual, "
                      "upper_residual_rad_per_n_m, which the plant file has no key for)" if info["above"] else ""))
    return out


def band_lines(info: Mapping | None) -> list[str]:
    """The report's text lines of a band fit (none without one)."""
    if not info:
        return []
    lo, hi = info["band_hz"]
    out = [f"band: {lo:.6g}..{hi:.6g} Hz ({info['points']} of {info['of']} points; fit % and intervals on the band only)"]
    for r in info.get("omitted") or []:
        out.append(f"  resonance near {r['frequency_hz']:.4g} Hz ({r['height_db']:.3g} dB, {r['over_noise']:.3g} x the "
                   f"noise), {r['side']} the band: omitted by the model")
    return out


def fc_reason(info: Mapping, fc_base: float) -> str:
    """Why the band fit holds the current loop at the base value (module docstring)."""
    lo, hi = info["band_hz"]
    above = min(r["frequency_hz"] for r in info["omitted"] if r["side"] == "above")
    return (f"the band ends at {hi:.4g} Hz below the omitted resonance near {above:.4g} Hz, whose tail (the upper "
            "residual, fitted) and the current loop's lag and the delay are one lag there to first order: the current "
            f"loop is not identified in the band, so the base value {fc_base:.6g} Hz is held (the delay fitted with it)")

