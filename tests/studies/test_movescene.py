"""The move scene type (``studies/movescene.py``): which files it claims and how it reads them."""

import pytest

from prsa_ctrl.errors import SceneError
from prsa_ctrl.studies.movescene import MoveScene, load_move_scene, parse_move_scene
from prsa_ctrl.studies.scenefile import locate_scene, read_scene_doc


def _doc(name):
    return read_scene_doc(*locate_scene(name)[:2])


def test_a_move_claims_the_files_with_a_move_table_only():
    assert MoveScene.claims(_doc("paper-move"))
    assert MoveScene.claims(_doc("paper-slow-reversal"))
    assert not MoveScene.claims(_doc("paper-load-step"))
    assert not MoveScene.claims(_doc("duty-ramp"))
    assert MoveScene.claims({"move": {}})
    assert not MoveScene.claims({})


def test_a_move_reads_its_file_as_parse_move_scene_does():
    doc = _doc("paper-move")
    assert MoveScene.from_doc(doc, "m.toml") == parse_move_scene(doc, "m.toml")
    assert load_move_scene("paper-move") == parse_move_scene(doc, "paper-move.toml (built-in)")


def test_load_move_scene_refuses_a_file_a_move_does_not_claim():
    with pytest.raises(SceneError, match=r"paper-load-step\.toml \(built-in\): no \[move\] section; expected a move scene"):
        load_move_scene("paper-load-step")
