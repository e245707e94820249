"""The fitted plant's ``[uncertainty]`` entries against the base plant's.

A base plant's entry is the user's assumption about a key's spread. An entry with absolute
bounds (``low``/``high``: ``uniform``, ``loguniform``, ...) does not move with the key's value:
when the fit writes a value outside them, the file would not load (its entry's support must
hold the nominal value). Such a value is evidence, not bad input: the data contradict the
stated range. The fit then writes its own entry for the key (centred on the written value, its
interval's spread) or, when the fit has none (a degenerate interval), no entry, and says so in
one line naming the key, the written value with its interval and the support as the base plant
types it (:func:`outside_note`). Whether the plant is written at all is the validation's
decision (exit 3 without ``--force`` when the plant does not explain the data), not this one.
"""

from __future__ import annotations

import math
import warnings
from typing import Any, Mapping, Sequence

import numpy as np

from ..errors import GeometryWarning, PlantFileError
from ..plant.plantfile import Plant
from ..plant.schema import KIND, PLAUSIBLE
from ..plant.uncertainty import CORRELATION_KEY, carry_correlation, inner_truncation, plant_uncertainty

__all__ = ["UNCERTAINTY_MODES", "entry_support", "outside_note", "uncertainty_choice", "hold_written_values",
           "Z95", "physical_range", "uncertainty_entries"]

#: The two-sided 95 % quantile of the normal distribution: a fit's 95 % interval is +/- Z95 sigma.
Z95 = 1.959963984540054

#: What a fit writes into the fitted plant's ``[uncertainty]`` for a fitted key: ``"keep"`` the
#: base plant's own entry (the user's assumption) unless it is narrower than the fit's 95 %
#: interval or does not hold the fitted value (then the fit's entry), and no entry where the base
#: has none; ``"fit"`` the fit's entry for every fitted key.
UNCERTAINTY_MODES = ("keep", "fit")


def entry_support(fitted: Plant, key: str, entry) -> tuple[float, float] | None:
    """Support ``(low, high)`` of a base ``[uncertainty]`` entry around the fitted plant's value
    (None when it is not valid there, e.g. absolute bounds that exclude the fitted value)."""
    try:
        with warnings.catch_warnings():  # the plant's geometry notes were given when it loaded
            warnings.simplefilter("ignore", GeometryWarning)
            p = Plant(name=fitted.name, values=fitted.values, sources=fitted.sources, uncertainty={key: entry})
        (u,) = plant_uncertainty(p).entries
    except (PlantFileError, ValueError):
        return None
    return float(u.low), float(u.high)


def _typed(entry: Mapping[str, Any]) -> str:
    """The entry's spread as the plant file types it (its numbers as given)."""
    fields = [f"{f} = {entry[f]!r}" for f in ("low", "high", "relative", "sigma", "relative_sigma", "truncate")
              if f in entry]
    return f"{entry.get('dist', '?')} " + ", ".join(fields)


def outside_note(key: str, value: float, ci95: Sequence[float] | None, entry: Mapping[str, Any], what: str) -> str:
    """One line: the written ``value`` of ``key`` (with its 95 % interval ``ci95``, when there is
    one) is outside the base plant's ``[uncertainty]`` ``entry`` (as typed), and ``what`` the
    fitted file writes instead."""
    ci = f" (95 % CI {ci95[0]:.6g}..{ci95[1]:.6g})" if ci95 is not None else ""
    return (f"{key} = {value:.6g}{ci} is outside the base plant's [uncertainty] entry ({_typed(entry)}): the data "
            f"contradict the stated range; {what}")


def uncertainty_choice(fitted: Plant, key: str, base_entry, fit_entry, ci95, rng, mode: str):
    """The ``[uncertainty]`` entry written for a fitted key and a note (or None) saying why it
    is not the user's: see :data:`UNCERTAINTY_MODES`. Never narrower than the fit's 95 %
    interval (clipped to the key's physical range ``rng``); never an entry whose support misses
    the written value (the fit's entry, else none)."""
    if base_entry is None and mode == "keep":
        return None, None  # the user assumed no spread there; the fit's own entry only when asked ("fit")
    if base_entry is None or mode == "fit":
        if fit_entry is None:
            return None, (f"{key}: no [uncertainty] entry written (its interval is degenerate or leaves the "
                          "physical range)")
        return fit_entry, None
    support = entry_support(fitted, key, base_entry)
    lo_ci, hi_ci = max(ci95[0], rng[0]), min(ci95[1], rng[1])
    if support is not None and support[1] - support[0] >= (hi_ci - lo_ci) * (1 - 1e-9):
        return base_entry, None
    if support is None:  # the data contradict the user's range: the fit's entry, or none
        value = float(fitted.values[key])
        if fit_entry is None:
            return None, outside_note(key, value, ci95, base_entry, "no [uncertainty] entry written for it (the "
                                      "fit's interval gives no valid one: degenerate or beyond the physical range)")
        return fit_entry, outside_note(key, value, ci95, base_entry, "the fit's entry is written instead")
    why = (f"({support[0]:.6g}..{support[1]:.6g}) is narrower than the fit's 95 % interval "
           f"{lo_ci:.6g}..{hi_ci:.6g}")
    if fit_entry is None:
        return base_entry, f"{key}: the base plant's [uncertainty] entry {why}; kept (the fit's interval is degenerate)"
    return fit_entry, f"{key}: the base plant's [uncertainty] entry {why}: the fit's entry is written instead"


def hold_written_values(plant: Plant, keys: Sequence[str] | None, params: Mapping[str, Mapping[str, Any]],
                        fit_entries: Mapping[str, Any]) -> tuple[Plant, list[str]]:
    """``plant`` with the ``[uncertainty]`` entries of ``keys`` that do not hold the key's
    written value replaced by the fit's (``fit_entries``; none where it has none), and one
    note per key replaced (:func:`outside_note`) and per correlation block that loses keys.

    Parameters
    ----------
    plant : Plant
        The plant as written (its values set; its entries the base plant's).
    keys : sequence of str or None
        The keys whose values the fit wrote (None: every key with an entry).
    params : mapping
        Per key its ``ci95`` (file units) where the written value is the fitted one.
    fit_entries : mapping
        The fit's own entries of the keys (e.g.
        :func:`uncertainty_entries`).
    """
    import dataclasses

    base = dict(plant.uncertainty or {})
    unc, notes = dict(base), []
    for k in ([k for k in base if k != CORRELATION_KEY] if keys is None else keys):
        entry = base.get(k)
        if entry is None or entry_support(plant, k, entry) is not None:
            continue
        new = fit_entries.get(k)
        ci = (params.get(k) or {}).get("ci95")
        if new is None:
            del unc[k]
            notes.append(outside_note(k, float(plant.values[k]), ci, entry, "no [uncertainty] entry written for it "
                                      "(the fit's interval gives no valid one: degenerate or beyond the physical range)"))
        else:
            unc[k] = new
            notes.append(outside_note(k, float(plant.values[k]), ci, entry, "the fit's entry is written instead"))
    if not notes:
        return plant, notes
    unc = carry_correlation(unc, base, None, notes)
    return dataclasses.replace(plant, uncertainty=unc), notes


def physical_range(plant: Plant, key: str, lo: float, hi: float) -> tuple[float, float]:
    """Where a fitted key can physically lie, file units: the fit's bounds ``lo..hi``
    (:func:`~prsa_ctrl.identification.common.key_bounds`, e.g. the no-load torque below half the motor's torque limit) within the
    plausible range of :data:`prsa_ctrl.plant.plantfile.PLAUSIBLE`.

    Parameters
    ----------
    plant : Plant
    key : str
        A plant-file key (``"friction.no_load_torque_n_m"``).
    lo, hi : float
        The fit's bounds of the key, file units.

    Returns
    -------
    (float, float)
        The range, file units.
    """
    p_lo, p_hi, _ = PLAUSIBLE.get(key, (-math.inf, math.inf, ""))
    return max(float(lo), float(p_lo)), min(float(hi), float(p_hi))




def uncertainty_entries(fitted: Plant, params: Mapping, names: str, std, ranges=None) -> dict:
    """The fit's own ``[uncertainty]`` entries of the fitted keys (what :func:`~prsa_ctrl.identification.common.finish_fit` writes
    with ``uncertainty="fit"``): a normal distribution with the fit's standard deviation,
    truncated at the 95 % interval (1.96 sigma) or closer where the key's physical range or the
    plant's cross-checks end; a key at a bound of its range (e.g. no-load torque 0) gets a
    uniform distribution from that bound to its interval's far end. Keys whose interval is
    degenerate or invalid are left out (the fit's warnings say why).

    Parameters
    ----------
    fitted : Plant
        The fitted plant (each entry's ends are checked against its cross-checks).
    params : mapping
        Key -> ``{"value": v, "ci95": [lo, hi], ...}``, file units.
    names : str
        The records the fit read, for each entry's ``source``.
    std : sequence of float
        Each key's standard deviation, file units.
    ranges : sequence of (float, float), optional
        Each key's physical range, file units (:func:`physical_range`); no entry reaches beyond it.

    Returns
    -------
    dict
        Key -> ``[uncertainty]`` entry (``dist``, ``sigma`` and ``truncate`` or ``low`` and ``high``,
        ``source``).
    """
    out = {}
    ranges = ranges if ranges is not None else [(-math.inf, math.inf)] * len(params)
    for (k, v), sd, (r_lo, r_hi) in zip(params.items(), std, ranges):
        value = v["value"]
        lo_ci, hi_ci = v["ci95"]
        if not (np.isfinite(sd) and sd > 0):
            continue
        kind = KIND[k]
        floor = 0.0 if kind in ("positive", "non-negative", "fraction in (0, 1]") else -math.inf
        ceil = 1.0 if kind == "fraction in (0, 1]" else math.inf
        floor, ceil = max(floor, r_lo), min(ceil, r_hi)
        if not floor <= value <= ceil:
            continue
        src = f"fit: {names} (95 % CI {lo_ci:.6g}..{hi_ci:.6g}; sigma from the fit's covariance)"
        # never past the range (rounded to 6 decimals inward, checked as the plant-file reader computes it)
        trunc = inner_truncation(value, float(sd), floor, ceil, limit=Z95, open_floor=kind in ("positive", "fraction in (0, 1]"))
        if trunc >= 0.1:
            entry = {"dist": "normal", "sigma": float(sd), "truncate": float(trunc), "source": src}
            ends = (value - entry["truncate"] * sd, value + entry["truncate"] * sd)
        elif kind == "non-negative" and value - floor < 0.1 * sd:
            entry = {"dist": "uniform", "low": float(floor), "high": float(min(max(hi_ci, value + sd), ceil)),
                     "source": src}
            ends = (entry["low"], entry["high"])
        else:
            continue
        try:
            for e in ends:
                fitted.with_params({k: e})
        except PlantFileError:
            continue
        out[k] = entry
    return out
