"""The friction feed-forward in the generated code (issue 24, item 4): C (compiled with the system
compiler) and Structured Text (compiled by matiec's iec2c, tests/io/test_codegen.iec2c) reproduce the
simulator's torque command on a recorded run of paper-slow-reversal with the feed-forward on."""

from __future__ import annotations

import numpy as np
import pytest

from prsa_ctrl import PID
from prsa_ctrl.drive.friction import FrictionFeedforward
from prsa_ctrl.drive.measurement import PositionLoop
from prsa_ctrl.io.codegen import ReferenceLaw, c_code, drive_law, max_relative_difference, replay_inputs, st_code
from prsa_ctrl.studies.move import simulate_move
from prsa_ctrl.studies.movescene import load_move_scene
from test_codegen import REL, _build, _build_st, _run_c, _run_st, matiec, needs_cc  # noqa: F401

SPEED = PID(0.0771, 7.07)


@pytest.fixture(scope="module")
def reversal(paper_plant):
    sc = load_move_scene("paper-slow-reversal")
    pos = PositionLoop(kv=102.7, kvff=1.0, kaff=1.0, friction=FrictionFeedforward.from_plant(paper_plant, 1500.0))
    r = simulate_move(paper_plant, sc, SPEED, pos)
    return drive_law(SPEED, paper_plant, position=pos), replay_inputs(r, paper_plant, sc.motion(), pos), r


def test_reference_law_with_friction(reversal, paper_plant):
    law, inp, r = reversal
    assert law.position.friction is not None
    u = ReferenceLaw(law).run(inp)
    assert max_relative_difference(u, inp["torque_command"]) <= REL
    # the feed-forward matters on this run: without it the law gives another command
    from dataclasses import replace

    bare = replace(law, position=replace(law.position, friction=None))
    assert max_relative_difference(ReferenceLaw(bare).run(inp), inp["torque_command"]) > 1e-2


@needs_cc
def test_c_with_friction_reproduces_the_simulator(reversal, tmp_path):
    law, inp, _ = reversal
    h, c = c_code(law, name="fr")
    assert "#include <math.h>" in c and "fr_friction_(p, vel_ref / p->lead)" in c
    u = _run_c(_build(law, tmp_path, "double"), law, inp)
    assert max_relative_difference(u, inp["torque_command"]) <= REL


def test_structured_text_with_friction_reproduces_the_simulator(reversal, matiec, tmp_path):
    law, inp, _ = reversal
    text = st_code(law, name="FrCtrl")
    assert "EXP(-(t_FrX * t_FrX))" in text
    u = _run_st(_build_st(matiec, law, tmp_path, "double", name="FrCtrl"), law, inp)
    assert max_relative_difference(u, inp["torque_command"]) <= REL


def test_code_without_friction_has_no_exp(paper_plant):
    law = drive_law(SPEED, paper_plant, position=PositionLoop(kv=102.7))
    h, c = c_code(law)
    assert "friction" not in c and "EXP" not in st_code(law)
