"""The judge's acceptance oracle itself (``foreign/judge_oracle.py``), on literal diagnosis lines.

A refusal (exit 3) is accepted only when its diagnosis is true of the generator that made the
data: a named frequency within 15 % of a true mode, an order per revolution equal to a true
cogging order, units blamed only when they were wrong, a delay only when undecided or right, a
work bound only where the case is listed. The lines below are prsa-fit's own wording (copied from
its runs on these generators, file paths shortened), true and false; the two wrong reasons main
gave last stop ("check the response's units" with the units right; "second mass ... 23.44 Hz"
that was the 6-per-revolution cogging) must be rejected. Fast: no fit runs here.
"""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from foreign import gen_ballscrew as bs
from foreign import gen_judge as gj
from foreign import gen_rollerscrew as rs
from foreign import gen_third as g3
from foreign.judge_oracle import acceptance, clauses, judge_diagnosis, parse_claims, run_delay

BALL3 = g3.truth("ball-40x16")  # modes 118.0 and 949 Hz, cogging 6 and 12 per rev
ROLLER3 = g3.truth("roller-39x10")  # modes 135.0 and 711 Hz
JUDGE_ROLLER_2M = gj.truth(gj.CASES["roller-2mass-d1-applied-si"])  # mode 161.3 Hz, anti-resonance 137.8 Hz
JUDGE_BALL_RIGID = gj.truth(gj.CASES["ball-rigid-d2-applied-si"])  # no mode, delay 1

NOT_EXPLAINED = "prsa-fit: the fitted plant does not explain the data; most likely missing physics: "
NO_FILE = " (no plant file written; --force writes it)"
COGGING_AS_MODE = (NOT_EXPLAINED + "second mass: 86 % of the replay residual of /t/data/loadsteps.csv lies within 15 % "
                   "of 23.44 Hz, a resonance the rigid model lacks (fit --fidelity compliant, or an FRF with the axial "
                   "mode); the current-loop bandwidth is not identified under this misfit (kept at 1000 Hz): its whole "
                   "lag at 23.44 Hz is 1.3 deg, small beside the up to 180 deg of the resonance the model lacks" + NO_FILE)
UNITS_BLAMED = ("prsa-fit: rigid FRF fit did not converge: least-squares status 0 (The maximum number of function "
                "evaluations is exceeded.) after 4000 evaluations; remedy: check the response's units ((rad/s)/(N m))")
COGGING_NAMED = (NOT_EXPLAINED + "position-periodic torque: 86 % of the replay residual of /t/loadsteps.csv lies within "
                 "15 % of 23.44 Hz and one sinusoid of the motor angle at 6.00 cycles per revolution explains 85 % of "
                 "it out of sample, one of time at 23.85 Hz 79 %; besides, second mass: 55 % of the replay residual of "
                 "/t/multisine.csv lies within 15 % of 121.1 Hz, a resonance the rigid model lacks (fit --fidelity "
                 "compliant, or an FRF with the axial mode)" + NO_FILE)
TWO_RESONANCES = ("prsa-fit: the response shows 2 resonances, near 117.2 Hz (30.6 dB, 106 x the noise) and 951.2 Hz "
                  "(18.5 dB, 63.9 x the noise); neither FRF model has two; the units are right (1.12 x the base "
                  "plant's low-frequency inertia)")
RIGID_REFUSED = ("prsa-fit: rigid model refused: the response shows an anti-resonance at 137.8 Hz and an axial mode at "
                 "161.4 Hz that the rigid model cannot produce (rigid fit 68.47 %, residual 0.389; two-mass fit 98.39 %, "
                 "residual 0.0199; F = 5.533e+04, p = 0; the mode changes the response by up to 20.8 dB, 120 x the "
                 "noise); fit it with --fidelity compliant (the two-mass axis)")
DELAY_UNDECIDED = (NOT_EXPLAINED + "delay: the delay search could not decide the command delay (0: 8.432e+05, 1: "
                   "3.392e+05, 2: 3.753e+05); give --delay-samples or --command-logged as the drive logs it" + NO_FILE)
FRICTION_DELAY_DECIDED = (NOT_EXPLAINED + "friction model: the replay residual is not a resonance and the delay is "
                          "decided; look at standstill, reversals and load changes (Stribeck keys, "
                          "friction.torque_offset_n_m, a load-dependent loss)" + NO_FILE)
WORK_BOUND = ("prsa-fit: the compliant fit stopped at its work bound (208 of 208 Gauss-Newton iterations over the 28797 "
              "sample intervals of the logs, set before the fit); the axial-mode keys were held at the base plant's "
              "values (no measured frequency response to start them from: --frf FRF.csv), and a misplaced axial mode "
              "keeps a compliant fit iterating; its last failure: fit did not converge at any command delay")
# the third generator's ball screw, --fidelity compliant (h14-oracle's run of main a8f75f1)
COMPLIANT_AT_BOUND = (NOT_EXPLAINED + "position-periodic torque: 81 % of the replay residual of /t/loadsteps.csv lies "
                      "within 15 % of 23.44 Hz and one sinusoid of the motor angle at 6.00 cycles per revolution explains "
                      "73 % of it out of sample, one of time at 23.85 Hz 68 % (speed 24.7..25.1 rad/s): a torque ripple of "
                      "6.0 per revolution, cogging or the screw's lead deviation, that the plant's models lack, not a mode; "
                      "besides, axial mode: 72 % of the replay residual of /t/multisine.csv lies within 15 % of 121.1 Hz, a "
                      "resonance the compliant model does not place there; the written plant's mode is at 226.6 Hz by the "
                      "series formula (no load, no nut loss); axis.nut_stiffness_n_per_um, axis.bearing_stiffness_n_per_um, "
                      "axis.moving_mass_kg held at the base plant's values (not fitted: give the measured frequency "
                      "response beside the logs, --frf FRF.csv, so the fit starts from its mode, or fit them with --fit); "
                      "the compliant fit stopped at its work bound (469 of 469 Gauss-Newton iterations over the 12797 "
                      "sample intervals of the logs, set before the fit) before every fit of the run finished: those it "
                      "stopped count as failed" + NO_FILE)
CRASH = "prsa-fit: numerical failure: prsa-fit --frf b.csv failed (KeyError); rerun with --verbose"


def test_the_two_wrong_reasons_of_last_stop_are_rejected():
    # the 6-per-revolution cogging at 25 rad/s (23.9 Hz) called a second mass: the modes are 118 and 949 Hz
    fails = judge_diagnosis(COGGING_AS_MODE, BALL3)
    assert any("23.44 Hz, not within 15 % of a true mode" in f for f in fails), fails
    # the units blamed when they were right (and a solver's evaluation limit is not physics)
    fails = judge_diagnosis(UNITS_BLAMED, BALL3)
    assert any("blames the units" in f for f in fails), fails
    assert any("cost or of the fit" in f for f in fails), fails


def test_the_true_diagnoses_of_the_same_runs_are_accepted():
    assert judge_diagnosis(COGGING_NAMED, BALL3) == []
    assert judge_diagnosis(TWO_RESONANCES, BALL3) == []
    assert judge_diagnosis(RIGID_REFUSED, JUDGE_ROLLER_2M) == []


def test_a_named_frequency_is_judged_against_the_generator_that_made_the_data():
    line = NOT_EXPLAINED + "second mass: 76 % of the replay residual of m.csv lies within 15 % of 150.4 Hz, a resonance the rigid model lacks" + NO_FILE
    assert judge_diagnosis(line, JUDGE_ROLLER_2M) == []  # 161.3 Hz loaded, 157.5 without the loss
    assert judge_diagnosis(line, ROLLER3) == []  # its modes are 129..135 and 710 Hz: 150.4 is 11 % above 135.0
    assert judge_diagnosis(line.replace("150.4", "160.0"), JUDGE_ROLLER_2M) == []
    assert judge_diagnosis(line.replace("150.4", "160.0"), ROLLER3)  # 18.5 % above 135.0
    assert judge_diagnosis(line, JUDGE_BALL_RIGID)  # a rigid axis has no resonance at all
    assert judge_diagnosis(line, bs.truth("applied"))
    plain = "prsa-fit: bode.csv needs a second mass (--fidelity compliant)"
    assert judge_diagnosis(plain, rs.truth()) == []
    assert judge_diagnosis(plain, JUDGE_BALL_RIGID)


def test_the_fifteen_percent_band_is_the_boundary():
    # the judge's roller: modes 161.27 (loaded) and 157.53 Hz (lossless)
    line = NOT_EXPLAINED + "second mass: 60 % of the replay residual of m.csv lies within 15 % of {} Hz" + NO_FILE
    assert judge_diagnosis(line.format(0.86 * 157.53), JUDGE_ROLLER_2M) == []
    assert judge_diagnosis(line.format(0.84 * 157.53), JUDGE_ROLLER_2M)
    assert judge_diagnosis(line.format(1.14 * 161.27), JUDGE_ROLLER_2M) == []
    assert judge_diagnosis(line.format(1.16 * 161.27), JUDGE_ROLLER_2M)


def test_an_anti_resonance_is_judged_against_the_anti_resonances():
    swapped = RIGID_REFUSED.replace("anti-resonance at 137.8 Hz", "anti-resonance at 175.0 Hz")
    assert any("anti-resonance at 175 Hz" in f for f in judge_diagnosis(swapped, JUDGE_ROLLER_2M))


def test_every_claim_of_the_line_is_judged_not_only_the_first():
    # a true cogging order beside a false mode (the besides clause) rejects the refusal
    line = COGGING_NAMED.replace("121.1 Hz", "60.5 Hz")
    assert any("60.5 Hz" in f for f in judge_diagnosis(line, BALL3))
    # and a wrong order beside a true mode
    line = COGGING_NAMED.replace("6.00 cycles per revolution", "5.00 cycles per revolution")
    assert any("5 per revolution" in f for f in judge_diagnosis(line, BALL3))
    assert judge_diagnosis(COGGING_NAMED.replace("6.00 cycles", "12.00 cycles"), BALL3) == []
    # an order per revolution on a generator without cogging
    assert judge_diagnosis(COGGING_NAMED, JUDGE_ROLLER_2M)


def test_notes_on_the_current_loop_and_the_time_frequency_are_not_claims():
    claims = parse_claims(COGGING_AS_MODE)
    assert [c.kind for c in claims] == ["resonance"]
    assert claims[0].modes_hz == [23.44]  # not the 1000 Hz the current loop was kept at
    periodic = parse_claims(COGGING_NAMED)
    assert [c.kind for c in periodic] == ["periodic", "resonance"]
    assert periodic[0].orders == [6.0]  # the 23.44 and 23.85 Hz of its clause are the residual's, not modes
    assert periodic[1].modes_hz == [121.1]


def test_clauses_split_only_outside_parentheses():
    parts = clauses(RIGID_REFUSED)
    assert len(parts) == 2
    assert parts[0].startswith("rigid model refused")
    assert "F = 5.533e+04" in parts[0]


def test_units_are_blamed_only_when_they_were_wrong():
    assert "units" not in [c.kind for c in parse_claims(TWO_RESONANCES)]  # "the units are right" is no blame
    blame = "prsa-fit: the response's low-frequency inertia is 1000 x the base plant's: check the response's units"
    assert any("blames the units" in f for f in judge_diagnosis(blame, BALL3))
    wrong_units = {**BALL3, "units_right": False}
    assert judge_diagnosis(blame, wrong_units) == []
    coords = "prsa-fit: the fitted plant does not explain the data; most likely missing physics: wrong coordinates: the load is not in motor coordinates"
    assert judge_diagnosis(coords, BALL3)
    assert judge_diagnosis(coords, {**BALL3, "coordinates_right": False}) == []


def test_a_delay_is_accepted_when_undecided_or_right():
    assert judge_diagnosis(DELAY_UNDECIDED, JUDGE_BALL_RIGID) == []
    # an honest "undecided" beside a true resonance (the delay report of a rejected model)
    line = NOT_EXPLAINED + "second mass: 70 % of the replay residual of m.csv lies within 15 % of 150.4 Hz; the command delay is undecided: the plant at 1 sample is rejected by its validation" + NO_FILE
    assert [c.kind for c in parse_claims(line)] == ["resonance", "delay"]
    assert judge_diagnosis(line, JUDGE_ROLLER_2M) == []
    # "the delay is decided" is a claim the truth checks: the judge's roller delay is 0 samples
    assert judge_diagnosis(FRICTION_DELAY_DECIDED, JUDGE_ROLLER_2M, run_delay=0) == []
    assert any("delay claim" in f for f in judge_diagnosis(FRICTION_DELAY_DECIDED, JUDGE_ROLLER_2M, run_delay=1))
    assert any("delay claim" in f for f in judge_diagnosis(FRICTION_DELAY_DECIDED, JUDGE_ROLLER_2M, run_delay=None))
    blamed = NOT_EXPLAINED + "delay: the logged command acts 0 samples after it is logged; expected --command-logged applied" + NO_FILE
    assert judge_diagnosis(blamed, JUDGE_BALL_RIGID, run_delay=0)
    assert judge_diagnosis(blamed, JUDGE_BALL_RIGID, run_delay=1) == []


def test_the_run_delay_read_from_a_report():
    found = {"solver": {"command_delay": {"shift_samples": 2, "drive_command_delay_samples": 1, "how": "found by the delay search"}}}
    assert run_delay(found) == 1
    assert run_delay({"solver": {"command_delay": {"drive_command_delay_samples": 0, "how": "given"}}}) is None
    assert run_delay({"solver": {"command_delay": {"drive_command_delay_samples": 1, "decided": False}}}) is None
    # the search's own verdict (prsa-fit writes it under command_delay.search)
    undecided = {"shift_samples": 1, "drive_command_delay_samples": 0, "how": "found by the delay search", "search": {"decided": False}}
    assert run_delay({"solver": {"command_delay": undecided}}) is None
    undecided["search"]["decided"] = True
    assert run_delay({"solver": {"command_delay": undecided}}) == 0
    assert run_delay(None) is None


def test_a_work_bound_is_cost_not_physics_unless_the_case_is_listed():
    fails = judge_diagnosis(WORK_BOUND, JUDGE_ROLLER_2M)
    assert any("cost or of the fit" in f for f in fails), fails
    assert judge_diagnosis(WORK_BOUND, JUDGE_ROLLER_2M, cost_allowed=True) == []
    # a bound named inside a delay statement is still a bound
    line = DELAY_UNDECIDED.replace("2: 3.753e+05", "2: stopped at the work bound")
    assert judge_diagnosis(line, JUDGE_BALL_RIGID)
    # a crash is never accepted, listed or not
    assert judge_diagnosis(CRASH, JUDGE_ROLLER_2M, cost_allowed=True)


def test_a_true_diagnosis_that_names_the_work_bound_is_accepted_only_where_listed():
    # its claims are true (6 per revolution; 121.1 Hz against the 118.0 Hz mode); the written
    # plant's own mode (226.6 Hz here: 126.6 in the run) is a statement about the model, not a claim
    kinds = [c.kind for c in parse_claims(COMPLIANT_AT_BOUND)]
    assert kinds == ["periodic", "resonance", "cost"]
    assert judge_diagnosis(COMPLIANT_AT_BOUND, BALL3, cost_allowed=True) == []
    assert judge_diagnosis(COMPLIANT_AT_BOUND, BALL3)


def test_a_line_without_physics_is_rejected():
    assert judge_diagnosis("prsa-fit: the fitted plant does not explain the data" + NO_FILE, BALL3)
    assert judge_diagnosis("", BALL3)


def test_acceptance_reads_the_last_stderr_line_and_the_file_left_behind(tmp_path):
    out, js = tmp_path / "fitted.toml", tmp_path / "r.json"
    proc = SimpleNamespace(returncode=3, stderr="prsa-fit: warning: something\n" + COGGING_AS_MODE + "\n")
    fails, row = acceptance(proc, out, js, BALL3, mode_expected=False)
    assert row["diagnosis"] == COGGING_AS_MODE
    assert fails
    ok = SimpleNamespace(returncode=3, stderr=COGGING_NAMED + "\n")
    assert acceptance(ok, out, js, BALL3, mode_expected=False)[0] == []
    js.write_text('{"solver": {"command_delay": {"drive_command_delay_samples": 0, "how": "found by the delay search"}}}')
    friction = SimpleNamespace(returncode=3, stderr=FRICTION_DELAY_DECIDED + "\n")
    fails, row = acceptance(friction, out, js, JUDGE_ROLLER_2M, mode_expected=False)
    assert row["run_delay"] == 0
    assert fails == []
    out.write_text("x")
    assert any("plant file was written" in f for f in acceptance(ok, out, js, BALL3, mode_expected=False)[0])


@pytest.mark.parametrize("truth", [BALL3, ROLLER3, JUDGE_ROLLER_2M, rs.truth()], ids=["ball3", "roller3", "judge", "rs"])
def test_the_truths_list_their_first_mode_among_the_modes(truth):
    assert any(abs(f / truth["first_mode_hz"] - 1.0) < 1e-12 for f in truth["modes_hz"])
    assert truth["units_right"] is True


def test_an_frf_delay_the_run_calls_undecided_is_no_claim_of_the_run():
    # an FRF fit's record has a status and no 'decided' key (delay.frf_delay_record)
    frf = {"drive_command_delay_samples": 1, "status": "undecided: its 95 % interval 0.4..1.6 samples"}
    assert run_delay({"solver": {"command_delay": frf}}) is None


def test_an_frf_delay_the_run_decided_is_its_claim():
    frf = {"drive_command_delay_samples": 1, "status": "decided"}
    assert run_delay({"solver": {"command_delay": frf}}) == 1
