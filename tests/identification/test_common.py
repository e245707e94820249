"""prsa_ctrl.identification.common: FitResult's status (the package's vocabulary) and as_dict."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from prsa_ctrl.identification.common import FitResult
from prsa_ctrl.plant.plantfile import load_plant
from prsa_ctrl.results import check_status, status_head


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
    assert d["status"] == "ok" and d["solver"]["status"] == "converged"
    assert res.report() == d
