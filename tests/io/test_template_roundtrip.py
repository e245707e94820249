"""Acceptance of issue 24, "a round trip per template": for each built-in template, export the
filled parameter set to a file, parse the file back (only each parameter's ``value`` and
``unit``), rebuild the controller from it and reproduce the toolkit's torque command on recorded
runs of the simulator's per-sample law: the paper load-step scene (speed PI) and the paper move
scene (cascade, where the template has a position gain), to round-off (1e-12 of the command).

Each template is also round-tripped as a copy with its speed gain in a current-based unit
(A/rpm with the motor's torque constant, or % rated torque per rpm), as a user adapts it.
"""

from __future__ import annotations

import math
import tomllib

import pytest

from prsa_ctrl import PID
from prsa_ctrl.drive.measurement import PositionLoop
from prsa_ctrl.io.codegen import ReferenceLaw, drive_law, max_relative_difference, replay_inputs
from prsa_ctrl.io.driveparams import (MotorData, controller_from_parameter_set, dumps_parameter_set, fill_template,
                                      load_template, read_parameter_set)
from prsa_ctrl.sim.engine import run
from prsa_ctrl.studies.move import simulate_move
from prsa_ctrl.studies.movescene import load_move_scene
from prsa_ctrl.studies.scene import load_scene
from prsa_ctrl.tuning.cascade import CascadeDesign

REL = 1e-12
DESIGN = CascadeDesign("joint", PID(0.0771, 7.07), PositionLoop(kv=102.7, kvff=1.0, kaff=1.0), {}, {}, {}, 0.0)
MOTOR = MotorData(0.9, rated_current_a=4.0, rated_torque_n_m=3.0, rated_speed_rpm=3000.0, pole_pairs=5,
                  source="test motor")


@pytest.fixture(scope="module")
def recorded(paper_plant):
    """Recorded runs of the design: the load step (speed PI alone) and the move (cascade)."""
    sc = load_scene("paper-load-step")
    r = run(paper_plant, setpoint=sc.setpoint_rpm * 2 * math.pi / 60, load=[(0.0, sc.initial_load),
            (sc.step_time, sc.final_loads[0])], duration=0.3, controller=DESIGN.speed, fidelity="compliant",
            discrete=True)
    mv = load_move_scene("paper-move")
    rm = simulate_move(paper_plant, mv, DESIGN.speed, DESIGN.position)
    return replay_inputs(r, paper_plant), replay_inputs(rm, paper_plant, mv.motion(), DESIGN.position)


def _round_trip(tmp_path, name: str, template, plant, recorded, motor=None) -> dict:
    """Export to a file, read the file back, rebuild, replay: the errors (relative)."""
    path = tmp_path / f"{name}.toml"
    path.write_text(dumps_parameter_set(fill_template(template, DESIGN, plant, motor)), encoding="utf-8")
    doc = tomllib.loads(path.read_text(encoding="utf-8"))
    for p in doc["parameter"]:  # the rebuild may use nothing but value and unit
        p.pop("value_si", None)
    tpl = load_template(template) if not isinstance(template, dict) else template
    carries_ff = any(p["quantity"] == "velocity_feedforward" for p in tpl["parameter"])
    pid, pos = controller_from_parameter_set(read_parameter_set(doc),
                                             missing_from=None if carries_ff else DESIGN.position)
    speed_inp, move_inp = recorded
    out = {"speed": max_relative_difference(ReferenceLaw(drive_law(pid, plant)).run(speed_inp),
                                            speed_inp["torque_command"])}
    if pos is not None:
        out["move"] = max_relative_difference(ReferenceLaw(drive_law(pid, plant, position=pos)).run(move_inp),
                                              move_inp["torque_command"])
    return out


def _current_copy(name: str) -> dict:
    """The template as a user adapts it: its speed gain in A/rpm (needs k_T)."""
    doc = load_template(name)
    for p in doc["parameter"]:
        if p["quantity"] == "speed_kp":
            p["unit"] = "A/rpm"
    return doc


def _check(name, tmp_path, paper_plant, recorded, has_position):
    err = _round_trip(tmp_path, name, name, paper_plant, recorded)
    assert err["speed"] <= REL
    assert ("move" in err) is has_position
    if has_position:
        assert err["move"] <= REL
    err = _round_trip(tmp_path, name + "-amps", _current_copy(name), paper_plant, recorded, MOTOR)
    assert err["speed"] <= REL and err.get("move", 0.0) <= REL


def test_round_trip_generic(tmp_path, paper_plant, recorded):
    _check("generic", tmp_path, paper_plant, recorded, has_position=True)


def test_round_trip_cia402(tmp_path, paper_plant, recorded):
    _check("cia402", tmp_path, paper_plant, recorded, has_position=True)


def test_round_trip_siemens_sinamics(tmp_path, paper_plant, recorded):
    _check("siemens-sinamics", tmp_path, paper_plant, recorded, has_position=False)


def test_round_trip_beckhoff_ax8000(tmp_path, paper_plant, recorded):
    _check("beckhoff-ax8000", tmp_path, paper_plant, recorded, has_position=True)


def test_per_unit_copy_round_trips(tmp_path, paper_plant, recorded):
    """% rated torque per rpm with only the rated torque known (no torque constant)."""
    doc = load_template("generic")
    for p in doc["parameter"]:
        if p["quantity"] == "speed_kp":
            p["unit"] = "% rated torque/rpm"
    err = _round_trip(tmp_path, "pu", doc, paper_plant, recorded, MotorData(None, rated_torque_n_m=3.0))
    assert err["speed"] <= REL and err["move"] <= REL


def test_round_trip_is_not_vacuous(tmp_path, paper_plant, recorded):
    """A value changed in the file by one part in a million (or a unit read as another) no
    longer reproduces the command: the check sees what the file says."""
    text = dumps_parameter_set(fill_template("siemens-sinamics", DESIGN, paper_plant))
    doc = tomllib.loads(text)
    doc["parameter"][1]["value"] *= 1 + 1e-6  # p1462
    vals = read_parameter_set(doc)
    pid, _ = controller_from_parameter_set(vals)
    inp = recorded[0]
    assert max_relative_difference(ReferenceLaw(drive_law(pid, paper_plant)).run(inp), inp["torque_command"]) > 1e3 * REL
    doc = tomllib.loads(text)
    doc["parameter"][1]["unit"] = "s"  # ms read as s: Tn 1000 x too long
    pid, _ = controller_from_parameter_set(read_parameter_set(doc))
    assert pid.ki == pytest.approx(DESIGN.speed.ki / 1000, rel=1e-12)
