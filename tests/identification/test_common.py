"""prsa_ctrl.identification.common: FitResult's status (the package's vocabulary) and as_dict."""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest
from scipy.stats import chi2

from prsa_ctrl.identification.common import FITTABLE, FitResult
from prsa_ctrl.identification.data import frf_from_arrays
from prsa_ctrl.identification.frf import fit_frf, frf_response
from prsa_ctrl.io.output import json_safe
from prsa_ctrl.plant.plantfile import load_plant
from prsa_ctrl.results import check_status, status_head

from test_delay import one_seed_fit


def _result(validation=None) -> FitResult:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plant = load_plant()
    solver = {"status": "converged"}
    if validation is not None:
        solver["validation"] = validation
    return FitResult(plant=plant, parameters={}, reflected_inertia_kg_m2={"value": 1.0, "ci95": [1.0, 1.0]},
                     correlation=np.eye(0), keys=(), fit_percent={}, warnings=[], solver=solver)


@pytest.mark.parametrize("validation,head", [
    ({"passes": True}, "ok"),
    ({"passes": False, "diagnosis": "a missing axial compliance"}, "flagged"),
    (None, "unverified"),
])
def test_status_is_in_the_vocabulary(validation, head):
    res = _result(validation)
    assert status_head(check_status(res.status)) == head


def test_flagged_status_names_the_diagnosis():
    res = _result({"passes": False, "diagnosis": "a missing axial compliance"})
    assert res.status.endswith("(a missing axial compliance)")


def test_as_dict_carries_the_status_and_report_is_its_alias():
    res = _result({"passes": True})
    d = res.as_dict()
    assert d["status"] == "ok"
    assert d["solver"]["status"] == "converged"
    assert res.report() == d


# ------------------------------------------------------------------------------------------------
# prsa_ctrl.identification.common (FitResult): joint confidence statements of a fit (issue 21: six marginal 95 % intervals hold a true point
# jointly only ~74 % of the time; the joint 95 % region is the covariance ellipsoid).
#
# ``FitResult.covariance`` (file units of the keys) is the matrix the intervals come from, and
# ``FitResult.joint_distance2`` is the squared Mahalanobis distance, checked here against a numpy
# computation written in the test. The 20-seed coverage of the ellipsoid is the slow study in
# test_delay.py (its foreign-log section, ``-m slow``); this file fits one short seed.
# ------------------------------------------------------------------------------------------------

Z95 = 1.959963984540054


@pytest.fixture(scope="module")
def base():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_plant()


@pytest.fixture(scope="module")
def fitted(base):
    """The one-seed fit of test_delay.py's foreign-log section (one fit per session): (result, truth)."""
    _, res, truth = one_seed_fit(base)
    return res, truth


def _mahalanobis2(values, truth, cov):
    """Reference: (v - t)^T C^-1 (v - t) by numpy's solve."""
    d = np.asarray(values, float) - np.asarray(truth, float)
    return float(d @ np.linalg.solve(cov, d))


def test_covariance_is_the_one_the_intervals_come_from(fitted):
    res, truth = fitted
    c = res.covariance
    n = len(res.keys)
    assert c.shape == (n, n)
    np.testing.assert_allclose(c, c.T, rtol=0, atol=1e-12 * np.max(np.abs(np.diag(c))))
    assert np.all(np.linalg.eigvalsh(c / np.sqrt(np.outer(np.diag(c), np.diag(c)))) > 0)
    sd = np.sqrt(np.diag(c))
    for i, k in enumerate(res.keys):
        v = res.parameters[k]["value"]
        lo, hi = res.parameters[k]["ci95"]
        assert lo == pytest.approx(v - Z95 * sd[i], rel=1e-12, abs=1e-12 * abs(v))
        assert hi == pytest.approx(v + Z95 * sd[i], rel=1e-12, abs=1e-12 * abs(v))
    np.testing.assert_allclose(res.correlation, c / np.outer(sd, sd), rtol=0, atol=1e-12)


def test_joint_distance_matches_numpy_and_truth_is_inside(fitted):
    res, truth = fitted
    keys = list(truth)
    idx = [res.keys.index(k) for k in keys]
    v = [res.parameters[k]["value"] for k in keys]
    ref = _mahalanobis2(v, [truth[k] for k in keys], res.covariance[np.ix_(idx, idx)])
    got = res.joint_distance2(truth)
    assert got == pytest.approx(ref, rel=1e-9)
    assert got <= chi2(len(keys)).ppf(0.95)  # this seed's truth lies in the joint 95 % region
    # a marginal: one key's distance is its z-score squared
    k = keys[2]
    i = res.keys.index(k)
    z = (truth[k] - res.parameters[k]["value"]) / math.sqrt(res.covariance[i, i])
    assert res.joint_distance2({k: truth[k]}) == pytest.approx(z * z, rel=1e-12)
    # the fitted point itself is at distance 0; a point 3 sigma out along one key is at 9
    assert res.joint_distance2({kk: res.parameters[kk]["value"] for kk in keys}) == 0.0
    assert res.joint_distance2({k: res.parameters[k]["value"] + 3 * math.sqrt(res.covariance[i, i])}) == \
        pytest.approx(9.0, rel=1e-9)  # (value + 3 sigma) - value loses a few digits


def test_joint_distance_takes_the_correlation_into_account(fitted):
    """Two strongly correlated keys: a point along the correlation is nearer than its z-scores
    say, one across it farther (the box and the ellipsoid differ)."""
    res, _ = fitted
    c = res.covariance
    corr = np.abs(res.correlation - np.eye(len(res.keys)))
    i, j = np.unravel_index(int(np.argmax(corr)), corr.shape)
    r = res.correlation[i, j]
    assert abs(r) > 0.3  # the fit has correlated keys
    ki, kj = res.keys[i], res.keys[j]
    si, sj = math.sqrt(c[i, i]), math.sqrt(c[j, j])
    vi, vj = res.parameters[ki]["value"], res.parameters[kj]["value"]
    along = res.joint_distance2({ki: vi + si, kj: vj + math.copysign(sj, r)})
    across = res.joint_distance2({ki: vi + si, kj: vj - math.copysign(sj, r)})
    assert along == pytest.approx(2 / (1 + abs(r)), rel=1e-9)  # (1, +-1) in units of sigma
    assert across == pytest.approx(2 / (1 - abs(r)), rel=1e-9)


def test_report_carries_the_covariance_with_units(fitted):
    res, _ = fitted
    rep = json.loads(json.dumps(json_safe(res.report())))
    cv = rep["covariance"]
    assert cv["keys"] == list(res.keys)
    assert cv["units"] == [FITTABLE[k][0] for k in res.keys]
    np.testing.assert_allclose(np.array(cv["matrix"]), res.covariance, rtol=1e-15, atol=0)


def test_joint_distance_bad_arguments(fitted):
    res, _ = fitted
    with pytest.raises(ValueError, match="point keys"):
        res.joint_distance2({})
    with pytest.raises(ValueError, match="nut.mass"):
        res.joint_distance2({"nut.mass": 1.0})


def test_frf_fit_exposes_its_covariance(base):
    """The FRF fit's covariance gives its intervals too, and the truth of a noisy measurement
    lies in the joint region of inertia and bandwidth."""
    truth = base.with_params({"nut.inertia_kg_m2": 1.2 * base.values["nut.inertia_kg_m2"],
                              "drive.current_loop_bandwidth_hz": 800.0})
    f = np.arange(8.0, 600.0, 8.0)
    g = frf_response(truth, f, speed_rad_s=30.0, load_n=800.0)
    rng = np.random.default_rng(3)
    noisy = g * np.exp(0.03 * (rng.standard_normal(len(f)) + 1j * rng.standard_normal(len(f))))
    res = fit_frf([frf_from_arrays("noisy", f, noisy, speed_rad_s=30.0, load_n=800.0)], base)
    sd = np.sqrt(np.diag(res.covariance))
    for i, k in enumerate(res.keys):
        lo, hi = res.parameters[k]["ci95"]
        assert hi - lo == pytest.approx(2 * Z95 * sd[i], rel=1e-12)
    point = {k: truth.values[k] for k in res.keys}
    assert res.joint_distance2(point) <= chi2(len(point)).ppf(0.95)
