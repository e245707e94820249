"""prsa_ctrl.reporttext: the one home of the report text that more than one layer prints (the
robust study's report is one text, whether prsa-tune or RobustTuning.format prints it)."""

from __future__ import annotations

import math

import pytest

import prsa_ctrl.cli as cli
from prsa_ctrl import reporttext
from prsa_ctrl.cli import report as cli_report
from prsa_ctrl.drive.pid import PID
from prsa_ctrl.studies import scenereport
from prsa_ctrl.tuning import robust
from prsa_ctrl.tuning.robust import RobustTuning


def _study() -> RobustTuning:
    per = [{"stable": True}, {"stable": True}, {"stable": False}]
    comp = {"objective": "iae", "ms_max": 1.4, "aggregate": "worst", "designs": {
        "nominal": {"all_stable": False, "max_ms": math.inf, "ms_violations": 2, "worst_objective": math.inf,
                    "mean_objective": math.inf, "per_scenario": per},
        "robust": {"all_stable": True, "max_ms": 1.39, "ms_violations": 0, "worst_objective": 0.0812,
                   "mean_objective": 0.05, "per_scenario": [{"stable": True}] * 3}}}
    rec = {"design": "robust", "why": "the nominal design is unstable on 1 scenario model"}
    return RobustTuning(PID(0.085, 14.7), PID(0.045, 6.8), (object(),) * 3, comp, {}, None, recommended=rec)


def test_the_robust_report_is_one_text():
    rt = _study()
    assert rt.format() == reporttext.format_robust(rt)


def test_the_robust_report_reads_as_written():
    assert reporttext.format_robust(_study()).splitlines() == [
        "Robust tuning over 3 scenario models (worst IAE; Ms bound 1.4 on every model)",
        "design   kp     ki    max Ms    models over the Ms bound  worst IAE  mean IAE",
        "-------  -----  ----  --------  ------------------------  ---------  --------",
        "nominal  0.085  14.7  unstable  2                         unstable   unstable",
        "robust   0.045  6.8   1.39      0                         0.0812     0.05",
        "nominal: closed loop unstable on 1 of 3 scenario models",
        "recommended: robust design (the nominal design is unstable on 1 scenario model)",
    ]


def test_the_old_names_are_the_one_home_s():
    assert scenereport.format_robust is reporttext.format_robust
    assert cli.format_robust is reporttext.format_robust
    assert scenereport.table is cli.table is reporttext.table
    with pytest.warns(DeprecationWarning, match="prsa_ctrl.cli.report is deprecated; import table from "
                                                "prsa_ctrl.studies.scenereport"):
        assert cli_report.table is reporttext.table
    assert robust.format_yield_table is reporttext.format_yield_table
