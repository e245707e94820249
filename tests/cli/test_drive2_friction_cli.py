"""prsa-tune --friction-ff (issue 24, item 4): the friction feed-forward verified on a move scene,
reported, and exported with the design (formula and table in .toml/.json; code in .c/.st)."""

from __future__ import annotations

import json
import math
import tomllib

import numpy as np
import pytest

from prsa_ctrl import PID
from prsa_ctrl.cli.report import format_friction_ff
from prsa_ctrl.cli.tune import main
from prsa_ctrl.drive.friction import FrictionFeedforward
from prsa_ctrl.drive.measurement import PositionLoop
from prsa_ctrl.io.export import dumps, export_cascade
from prsa_ctrl.studies.move import friction_feedforward_effect
from prsa_ctrl.studies.movescene import load_move_scene
from prsa_ctrl.tuning.cascade import CascadeDesign

DESIGN = CascadeDesign("joint", PID(0.0771, 7.07), PositionLoop(kv=102.7, kvff=1.0, kaff=1.0), {}, {}, {}, 0.0)


def test_friction_ff_refused_on_a_speed_scene(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["--friction-ff", "--json", "r.json"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--friction-ff does not apply to the speed-loop scene paper-load-step" in err[0]
    assert not list(tmp_path.iterdir())


def test_report_lines_and_export_of_a_fixed_design(paper_plant):
    """The report's numbers are the effect's, and the export's formula coefficients and table
    are the curve's (the table recomputed here from the coefficients)."""
    sc = load_move_scene("paper-slow-reversal")
    eff = friction_feedforward_effect(DESIGN, paper_plant, sc)
    text = format_friction_ff(eff, "compliant")
    a, b = eff["without"], eff["with"]
    assert f"RMS {a['rms_following_error_m'] * 1e6:.3f} um without, {b['rms_following_error_m'] * 1e6:.3f} um with" in text
    assert f"peak {a['peak_following_error_m'] * 1e6:.3f} um without" in text
    w_max = sc.max_speed_m_s / paper_plant.lead_per_rad
    d = tomllib.loads(dumps(export_cascade(eff["design"], paper_plant, fmt="toml", friction_table_speed_rad_s=w_max),
                            "toml"))
    fr = d["position_controller"]["friction_feedforward"]
    table = np.array(fr["table_speed_rad_s_torque_n_m"])
    assert table[0, 0] == pytest.approx(-w_max) and table[-1, 0] == pytest.approx(w_max) and len(table) == 21
    for w, tau in table:
        c, s_, v = (fr["coulomb_positive_n_m"], fr["stribeck_positive_n_m"], fr["viscous_positive_n_m_s_per_rad"]) \
            if w > 0 else (fr["coulomb_negative_n_m"], fr["stribeck_negative_n_m"], fr["viscous_negative_n_m_s_per_rad"])
        hand = 0.0 if w == 0 else math.copysign(c + s_ * math.exp(-(w / fr["stribeck_speed_rad_s"]) ** 2) + v * abs(w), w)
        assert tau == pytest.approx(fr["gain"] * hand, rel=1e-14, abs=1e-300)
    assert fr["coulomb_positive_n_m"] == FrictionFeedforward.from_plant(paper_plant, 1500.0).coulomb_positive_n_m
    # without the feed-forward the export has no such block
    assert "friction_feedforward" not in export_cascade(DESIGN, paper_plant, fmt="json")["position_controller"]


@pytest.mark.slow
def test_cli_friction_ff_on_paper_slow_reversal(tmp_path, capsys):
    """The whole path: tune the cascade, verify with and without, report, JSON, export (~20 s)."""
    out, rep, code = tmp_path / "d.json", tmp_path / "r.json", tmp_path / "d.c"
    assert main(["--scene", "paper-slow-reversal", "--friction-ff", "--json", str(rep), "--export", str(out)]) == 0
    text = capsys.readouterr().out
    fr = json.loads(rep.read_text())["friction_feedforward"]
    assert fr["with"]["rms_following_error_m"] < 0.5 * fr["without"]["rms_following_error_m"]
    assert fr["with"]["peak_following_error_m"] < 0.5 * fr["without"]["peak_following_error_m"]
    assert "friction feed-forward (plant paper-iprsm friction keys at an axial load of 1500 N)" in text
    assert json.loads(out.read_text())["position_controller"]["friction_feedforward"]["gain"] == 1.0
    assert main(["--quiet", "--scene", "paper-slow-reversal", "--friction-ff", "--export", str(code)]) == 0
    assert "d_friction_(p, vel_ref / p->lead)" in code.read_text()  # issue 36: run-time parameters, prefixed names
