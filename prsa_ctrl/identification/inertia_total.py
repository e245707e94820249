"""The 95 % interval of a fit's total reflected inertia (kg m^2) from every fitted key it depends on.

The total at the motor, ``prsa_ctrl.plant.plantfile.Plant.reflected_inertia_kg_m2``, is a sum
of the rotating inertia and of the translating masses times the lead squared (``J = J_m + J_s +
m a^2`` on a ball or roller screw). When the fit estimates only the rotating inertia the
total's interval is that key's shifted by the fixed rest. When it also estimates a key of the
rest (``axis.moving_mass_kg``: with the nut loss on the whole force the loss on the carriage's
inertial force separates it from the motor's inertia) the two are strongly anti-correlated and
the total's interval is the linear (delta-method) combination of their intervals with the fit's
correlation: shifting the rotating inertia's interval alone would centre it on the wrong total.
"""

from __future__ import annotations

import math
import warnings
from typing import Mapping, Sequence

import numpy as np

from ..errors import PlantFileError
from ..plant.plantfile import Plant

__all__ = ["reflected_interval"]


def _gradient(plant: Plant, key: str) -> float:
    """``d J / d key`` of the plant's total reflected inertia (kg m^2 per the key's file unit),
    by a one-sided difference (``J`` is linear in every inertia and mass key, so exact to
    round-off): forward, or backward where the step up leaves the plant file's cross-checks (a
    fitted drag that raised the breakaway to itself: a step up in the drag puts it above)."""
    v = float(plant.values[key])
    h = 1e-6 * max(abs(v), 1e-9)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            moved = plant.with_params({key: v + h}).reflected_inertia_kg_m2
        except PlantFileError:
            h = -h
            moved = plant.with_params({key: v + h}).reflected_inertia_kg_m2
    return (float(moved) - float(plant.reflected_inertia_kg_m2)) / h


def reflected_interval(fitted: Plant, j_key: str, keys: Sequence[str], params: Mapping[str, dict],
                       corr: np.ndarray) -> list[float]:
    """95 % interval ``[lo, hi]`` (kg m^2) of ``fitted``'s total reflected inertia.

    Parameters
    ----------
    fitted : Plant
        The written plant (fitted values; keys not identified at their base values, which
        contribute nothing to the interval, as the written values are then the base's).
    j_key : str
        The mechanism's rotating-inertia key (``axis.motor_inertia_kg_m2`` or ``nut.inertia_kg_m2``).
    keys : sequence of str
        The fit's keys, in the order of ``corr``'s rows.
    params : mapping
        Per key ``{"value", "ci95", ...}`` (file units); plant keys carry ``kept_base`` (only
        those with ``kept_base`` False enter).
    corr : ndarray
        The fit's correlation matrix of ``keys``.

    Returns
    -------
    list of float
        With ``j_key`` the only fitted key ``J`` depends on: its interval shifted by the rest of
        ``J`` (its asymmetric extent kept). With more: ``J +/- sqrt(s^T R s)``, ``s_i = (dJ/dk_i) h_i``,
        ``h_i`` key ``i``'s larger 95 % half-width, ``R`` the correlation. No fitted key: ``[J, J]``.
    """
    j = float(fitted.reflected_inertia_kg_m2)
    idx = [i for i, k in enumerate(keys) if params.get(k, {}).get("kept_base") is False]  # fitted and written
    grads = {i: _gradient(fitted, keys[i]) for i in idx}
    used = [i for i in idx if grads[i] != 0.0]
    if not used:
        return [j, j]
    if [keys[i] for i in used] == [j_key]:
        lo, hi = params[j_key]["ci95"]
        extra = j - float(fitted.values[j_key])
        return [lo + extra, hi + extra]
    half = np.array([max(params[keys[i]]["ci95"][1] - params[keys[i]]["value"],
                         params[keys[i]]["value"] - params[keys[i]]["ci95"][0]) for i in used])
    s = np.array([grads[i] for i in used]) * half
    r = np.asarray(corr, float)[np.ix_(used, used)]
    width = math.sqrt(max(float(s @ r @ s), 0.0))
    return [j - width, j + width]

