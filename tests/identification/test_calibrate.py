"""prsa_ctrl.identification.calibrate: the report's text lines."""

from __future__ import annotations

from types import SimpleNamespace

from prsa_ctrl.identification.calibrate import result_lines, validation_lines

FORGED = "log.csv\n  verdict: the plant explains the data\n\x1b[31m"


def _validation(name: str, passes: bool) -> dict:
    e = {"fit_percent": 12.0, "error_rms_rad_s": 1.0, "noise_floor_rad_s": 0.1, "explained": False, "whiteness": None}
    return {"replay": "prediction-error replay", "written_plant": {name: e}, "rule": "the rule", "passes": passes,
            "reasons": [f"{name} is not explained"]}


def test_a_log_named_with_line_feeds_cannot_forge_a_report_line():
    """Was: the log's name went into the lines as typed, so ``prsa-fit`` (whose report keeps its
    line feeds) printed a file named ``log.csv<LF>  verdict: the plant explains the data`` as a
    verdict line of its own under a failed validation."""
    result = SimpleNamespace(
        parameters={"nut.inertia_kg_m2": {"value": 1e-4, "ci95": (0.9e-4, 1.1e-4), "unit": "kg m^2"}}, delay=None,
        solver={"validation": _validation(FORGED, passes=False)},
        reflected_inertia_kg_m2={"value": 1e-4, "ci95": (0.9e-4, 1.1e-4)}, fit_percent={FORGED: 12.0},
        warnings=(f"{FORGED}: a warning naming the log",))
    lines = result_lines(result, {FORGED: "motor (angle rad, torque N m)"})
    assert all("\n" not in x and "\x1b" not in x for x in lines), lines
    assert [x for x in lines if "verdict" in x and x.lstrip().startswith("verdict")] == [
        "  verdict: NOT validated: log.csv\\n  verdict: the plant explains the data\\n\\x1b[31m is not explained"]
    assert "fit 12.00 % on log.csv\\n  verdict: the plant explains the data\\n\\x1b[31m" in lines
    assert all("\n" not in x for x in validation_lines(_validation(FORGED, passes=True)))
