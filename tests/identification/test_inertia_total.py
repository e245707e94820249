"""The fit's total reflected inertia interval (prsa_ctrl.identification.inertia_total) through
finish_fit: with the moving mass fitted too it is centred on the written total and combines both
keys' intervals with their correlation (it was the motor inertia's interval shifted by the base
plant's rest: on the judge's roller case 1.0880..1.0950e-3 around a total of 1.0800e-3)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from prsa_ctrl.identification.common import finish_fit
from prsa_ctrl.plant import load_plant

Z95 = 1.959963984540054
JM, MASS, ETA = "axis.motor_inertia_kg_m2", "axis.moving_mass_kg", "friction.efficiency"


def _base():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_plant("ballscrew-32x10")


def _finish(base, keys, values, sd, corr):
    cov = np.asarray(corr, float) * np.outer(sd, sd)
    lo, hi = [0.1 * v for v in values], [10.0 * v if v > 1 else 0.999 for v in values]
    hi = [min(h, 0.999) if k == ETA else h for k, h in zip(keys, hi)]
    return finish_fit(base, list(keys), np.array(values, float), cov, lo, hi, "log.csv", [])


def test_total_inertia_interval_with_the_moving_mass_fitted():
    base = _base()
    v = base.values
    a2 = base.lead_per_rad ** 2
    values = [1.1 * v[JM], 0.9 * v[MASS], v[ETA] - 0.02]  # the mass moved from the base's
    sd = [0.002 * v[JM], 0.01 * v[MASS], 1e-4]
    rho = -0.99
    params, corr, fitted, reflected, _, reasons = _finish(base, (JM, MASS, ETA), values, sd,
                                                          [[1, rho, 0], [rho, 1, 0], [0, 0, 1]])
    assert not reasons
    assert all(not params[k]["kept_base"] for k in (JM, MASS, ETA))
    j = values[0] + v["axis.screw_inertia_kg_m2"] + values[1] * a2  # independent: J = J_m + J_s + m a^2
    assert reflected["value"] == pytest.approx(j, rel=1e-12)
    half = Z95 * math.sqrt(sd[0] ** 2 + (a2 * sd[1]) ** 2 + 2 * rho * sd[0] * a2 * sd[1])
    lo, hi = reflected["ci95"]
    assert lo < j < hi
    assert (hi - j) == pytest.approx(half, rel=1e-5)
    assert (j - lo) == pytest.approx(half, rel=1e-5)
    # the motor inertia's interval alone shifted by the base's rest (the old interval) misses it
    old = [c + base.reflected_inertia_kg_m2 - v[JM] for c in params[JM]["ci95"]]
    assert not old[0] <= j <= old[1]


def test_total_inertia_interval_with_only_the_motor_inertia_fitted_is_its_shifted_interval():
    base = _base()
    v = base.values
    values = [1.1 * v[JM], v[ETA] - 0.02]
    sd = [0.002 * v[JM], 1e-4]
    params, _, fitted, reflected, _, _ = _finish(base, (JM, ETA), values, sd, [[1, 0.3], [0.3, 1]])
    extra = base.reflected_inertia_kg_m2 - v[JM]
    assert reflected["value"] == pytest.approx(values[0] + extra, rel=1e-12)
    assert reflected["ci95"] == pytest.approx([c + extra for c in params[JM]["ci95"]], rel=1e-12)

