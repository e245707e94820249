"""prsa_ctrl.reporttext: the one home of the report text (the robust study's report is one text,
whether prsa-tune or RobustTuning.format prints it; the Monte-Carlo, design-to-spec, prsa-pid,
paper-row and linear-axis texts live there too)."""

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


def test_the_moved_formatters_keep_their_old_names():
    from prsa_ctrl.cli import pid
    from prsa_ctrl.studies import designspec, montecarlo, paper

    assert montecarlo.format_report is reporttext.format_monte_carlo
    assert paper.format_rows is reporttext.format_rows
    assert pid.format_pid_report is reporttext.format_pid_report
    assert montecarlo.MonteCarloReport.format.__doc__
    assert designspec.DesignToSpec.format.__doc__


def test_no_report_formatter_outside_its_home():
    """Every ``format*`` function outside reporttext (and the scene kinds' own reports:
    studies/scenereport, studies/scenekinds) is a one-statement call of its home."""
    import ast
    import pathlib

    import prsa_ctrl

    root = pathlib.Path(prsa_ctrl.__file__).parent
    homes = {root / "reporttext.py", root / "studies" / "scenereport.py", root / "studies" / "scenekinds.py"}
    fat = []
    for path in root.rglob("*.py"):
        if path in homes:
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.FunctionDef) and node.name.lstrip("_").startswith("format"):
                body = [b for b in node.body if not (isinstance(b, ast.Expr) and isinstance(b.value, ast.Constant))]
                if len(body) > 1 or not isinstance(body[0], ast.Return):
                    fat.append(f"{path.relative_to(root)}:{node.name}")
    assert fat == []


def _replay(log: str, closed: bool = True) -> dict:
    return {"log": log, "replay": "closed loop from the reference" if closed else "open loop from the logged command",
            "errors_percent": {"position": 1.25, "velocity": 12.5, "force": 30.0},
            "fit_percent": {"position": 98.75, "velocity": 87.5, "force": 70.0}}


def test_the_linear_axis_fit_reads_as_written():
    report = {"equivalent": {"mass_kg": {"value": 95.1234567, "unit": "kg", "ci95": [94.0, 96.25]}},
              "replay": [_replay("a.mat")], "holdout": {"replay": [_replay("a.mat")]},
              "friction_map": {"a.mat": {"parameters": {"coulomb_n": {"value": 20.5, "unit": "N", "ci95": [19.0, 22.0]},
                                                        "stribeck_n": {"value": None, "unit": "N", "ci95": [None, None]}},
                                         "stribeck": False}},
              "warnings": ["w1"], "coordinates": "position m, force N"}
    assert reporttext.axis_fit_lines(report) == [
        "mass_kg = 95.1235 kg (95 % CI 94..96.25)",
        "a.mat: replay errors position 1.25 %, velocity 12.5 %, force 30 % (fit 98.750 / 87.500 / 70.000 %; "
        "closed loop from the reference)",
        "held out: a.mat: replay errors position 1.25 %, velocity 12.5 %, force 30 % (fit 98.750 / 87.500 / 70.000 %; "
        "closed loop from the reference)",
        "friction map of a.mat (report; the replay model stays Coulomb + viscous): coulomb_n = 20.5 N "
        "(95 % CI 19..22); Stribeck False",
        "warning: w1",
        "coordinates: position m, force N",
    ]


def test_the_linear_axis_validation_says_which_replay_ran_open_loop():
    lines = reporttext.axis_validation_lines([(_replay("a.mat"), True), (_replay("b.csv", False), False)], "xy")
    assert lines[1].startswith("b.csv: replay errors")
    assert lines[-1] == "coordinates: xy"
    assert lines[2] == ("note: b.csv has no controller description: replayed open loop from the logged command (an "
                        "integrating axis drifts)")
    assert len(lines) == 4
