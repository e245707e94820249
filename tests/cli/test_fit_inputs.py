"""prsa-fit (prsa_ctrl.cli.fit): inputs that used to be accepted silently or reported as an
internal error are one line naming the flag or file, exit 2, nothing written."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from prsa_ctrl.cli.fit import main
from prsa_ctrl.identification.data import record_from_arrays

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture()
def record(tmp_path):
    t = np.arange(400) * 2.5e-4
    rec = record_from_arrays("r", t, 0.1 + 0.05 * np.sin(2 * np.pi * 20 * t),
                             nut_angle_rad=30 * t + 0.1 * np.sin(2 * np.pi * 10 * t), axial_load_n=500.0)
    p = tmp_path / "rec.csv"
    rec.to_csv(p)
    return p


def _run(capsys, argv):
    code = main(argv)
    return code, capsys.readouterr().err


def test_a_linear_axis_plant_as_the_base_of_a_screw_fit_is_bad_input(record, tmp_path, capsys):
    """Was: "value = {'value': 35.15..., 'source': ...}; expected a number, string, bool or list"
    (the TOML writer's own message)."""
    base = ROOT / "examples" / "emps" / "plant.toml"
    out = tmp_path / "fitted.toml"
    code, err = _run(capsys, [str(record), "--plant", str(base), "--out", str(out)])
    assert code == 2 and err.count("\n") == 1, err
    assert f"--plant {base}: mechanism = \"linear-axis\"" in err and "--log-format" in err
    assert not out.exists()


def test_a_torque_constant_without_a_current_column_is_bad_input(record, tmp_path, capsys):
    out = tmp_path / "fitted.toml"
    code, err = _run(capsys, [str(record), "--torque-constant", "0.5", "--out", str(out)])
    assert code == 2 and err.count("\n") == 1, err
    assert f"{record}: a torque constant of 0.5 N m/A (--torque-constant) was given" in err
    assert not out.exists()
