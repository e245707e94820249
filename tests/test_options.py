"""prsa_ctrl.options: the shared constants are defined once and the conversions are exact."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from prsa_ctrl import options

PACKAGE = Path(options.__file__).parent


def test_rpm_conversions_equal_the_inline_formulas_bit_for_bit():
    # the modules that wrote "x * math.pi / 30" and "x * 30 / math.pi" now call these: not one ulp moved
    rng = np.random.default_rng(1)
    xs = [*rng.uniform(-1e4, 1e4, 20_000), *np.exp(rng.uniform(-300, 300, 20_000)), 6000.0, 300.0, 0.0]
    for x in map(float, xs):
        assert options.rpm_to_rad_s(x) == x * math.pi / 30.0
        assert options.rad_s_to_rpm(x) == x * 30 / math.pi
    assert options.RAD_S_PER_RPM == math.pi / 30.0


def test_the_speed_limit_is_the_one_constant():
    from prsa_ctrl.cli.fit import DESIGN_MAX_SPEED_RAD_S
    from prsa_ctrl.identification.common import FRF_SPEED_MAX_RAD_S
    from prsa_ctrl.studies.scenefile import SETPOINT_MAX_RPM

    assert SETPOINT_MAX_RPM == options.SPEED_MAX_RPM
    assert FRF_SPEED_MAX_RAD_S == DESIGN_MAX_SPEED_RAD_S == options.rpm_to_rad_s(options.SPEED_MAX_RPM)


def test_app_fidelities_are_the_options_plus_auto():
    from prsa_ctrl.app.session import FIDELITIES

    assert FIDELITIES == ("auto", *options.FIDELITIES)


def _code_lines(pattern: str, skip=()) -> list[str]:
    out = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE).as_posix()
        if rel in skip:
            continue
        for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            code = line.split("#", 1)[0]
            if re.search(pattern, code):
                out.append(f"{rel}:{i}: {line.strip()}")
    return out


def test_6000_rpm_written_once():
    assert _code_lines(r"\b6000(\.0)?\b") == ["options.py:42: SPEED_MAX_RPM = 6000.0"]


def test_the_rpm_factor_is_not_written_inline_outside_the_scene_modules():
    # studies/scene.py and scenerobust.py (14 lines) are the scene registry's, not changed in this round
    found = _code_lines(r"math\.pi\s*/\s*30|30(\.0)?\s*/\s*math\.pi",
                        skip=("studies/scene.py", "studies/scenerobust.py"))
    assert found == []


def test_peak_bound_range_written_once_outside_the_scene_modules():
    # (1, 10) as numbers in code: only options.PEAK_BOUND_RANGE (studies/scene*.py: the scene
    # registry's, not changed in this round)
    found = _code_lines(r"1(\.0)? < [a-z_.]+ < 10(\.0)?\b|lo=1\.0, hi=10\.0", skip=("studies/scene.py",))
    assert found == []
