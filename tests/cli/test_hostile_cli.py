"""Tracebacks and unclear messages (issue 13): every flag value of prsa-tune / prsa-plot is
refused in one line naming what was typed, in the user's unit, with exit 2 -- or accepted.

The expensive work is replaced by a stand-in that counts its calls and fails with a
SimulationError (exit 3): a refused input must never reach it (a step budget of zero), an
accepted one must reach it. Validity is judged by an independent oracle."""

import math
import re

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from prsa_ctrl import SimulationError
from prsa_ctrl.cli.tune import main, plot_main

PAPER_CAPACITY_N = (3.0 - 0.02 - 1e-4 * 300 * math.pi / 30) * 0.85 * 2 * math.pi / 2e-3  # at 300 rpm
STICTION_RPM = 5 * 1e-4 / (2e-3 / (2 * math.pi)) * 30 / math.pi  # screw slower than 5x the Stribeck velocity



def _outcome(capsys, rc, calls, prog="prsa-tune"):
    cap = capsys.readouterr()
    lines = cap.err.strip().splitlines()
    assert "Traceback" not in cap.err and len(lines) == 1, cap.err
    if rc == 2:
        assert lines[0].startswith(f"{prog}: error: ") and not calls, (lines, calls)
    else:
        assert rc == 3 and len(calls) == 1 and "stand-in" in lines[0], (rc, lines)
    calls.clear()
    return lines[0]


# --- load-step strings --------------------------------------------------------------------------

_num_text = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-10, 10_000).map(str),
    st.sampled_from(["", " ", "1e20", "1e300", "1e-300", "-0", "0x10", "1_000", "nan", "inf", "-inf", "abc",
                     "500", "1500", "7900", "8000", "\u0661\u0665\u0660\u0660"]),
)
_load_step = st.one_of(
    st.tuples(_num_text, st.lists(_num_text, min_size=1, max_size=4)).map(lambda t: f"{t[0]}:{','.join(t[1])}"),
    st.text(alphabet="0123456789:,.-e ", max_size=14),
)


def _oracle_load_step(text):
    parts = text.split(":")
    if len(parts) != 2:
        return False
    try:
        vals = [float(parts[0])] + [float(p) for p in parts[1].split(",")]
    except ValueError:
        return False
    f0, finals = vals[0], vals[1:]
    if not all(math.isfinite(v) and 0 <= v <= PAPER_CAPACITY_N for v in vals):
        return False
    return len(set(finals)) == len(finals) and all(abs(f - f0) >= 1.0 for f in finals)


@settings(max_examples=150, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(_load_step)
def test_load_step_strings_are_refused_in_one_line_or_run(capsys, stand_in, text):
    rc = main(["--load-step", text])
    line = _outcome(capsys, rc, stand_in)
    assert (rc == 3) == _oracle_load_step(text), (text, line)
    if rc == 2:
        assert "--load-step" in line


@pytest.mark.parametrize("text", ["1e20:1", "500:1e300", "500:90000", "-5:10"])
def test_same_bad_load_same_exit_code_in_both_tools(capsys, stand_in, text):
    assert main(["--load-step", text]) == 2
    tune_line = _outcome(capsys, 2, stand_in)
    assert plot_main(["--kp", "0.085", "--load-step", text]) == 2
    plot_line = _outcome(capsys, 2, stand_in, "prsa-plot")
    assert repr(text) in tune_line and repr(text) in plot_line
    assert "ZeroDivision" not in tune_line + plot_line


def test_load_beyond_the_torque_limit_names_value_and_limit_in_newtons(capsys, stand_in):
    assert main(["--load-step", "500:8000"]) == 2
    line = _outcome(capsys, 2, stand_in)
    assert re.search(r"load 8000 N out of range for paper-iprsm: at 300 rpm the motor holds at most 7949 N", line)


# --- numeric flags ------------------------------------------------------------------------------

_FLAGS = {  # flag -> oracle of validity on the paper plant and scene (step 0.2 s, duration 0.5 s)
    "--setpoint-rpm": lambda v: STICTION_RPM <= v <= 6000,
    "--step-time": lambda v: 0.002 <= v <= 0.5 - 0.02,
    "--duration": lambda v: 0.2 + 0.02 <= v <= 10.0,
    "--ms-max": lambda v: 1 < v < 10,
    "--mt-max": lambda v: 1 < v < 10,
}


@settings(max_examples=200, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(flag=st.sampled_from(sorted(_FLAGS)),
       value=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.floats(-1e4, 1e4),
                       st.sampled_from([0.0, -300.0, 1e308, 1e-9, 0.0011, 1e9, 1.0, 1.4])))
def test_numeric_flags_refused_in_the_users_unit_or_run(capsys, stand_in, flag, value):
    text = repr(value)
    rc = main([flag, text])
    line = _outcome(capsys, rc, stand_in)
    ok = math.isfinite(value) and _FLAGS[flag](value)
    assert (rc == 3) == ok, (flag, text, line)
    if rc == 2:
        assert f"{flag} {text}" in line, line  # the value as typed, after the flag
        if flag == "--setpoint-rpm":
            assert "rad/s" not in line and "setpoint = " not in line
            assert "rpm" in line


@settings(max_examples=60, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(flag=st.sampled_from(["--setpoint-rpm", "--duration", "--kp", "--ki", "--kd", "--workers", "--ms-max"]),
       text=st.text(max_size=8))
def test_junk_flag_text_never_tracebacks(capsys, stand_in, flag, text):
    argv = ["--kp", "0.085", flag, text] if flag in ("--ki", "--kd") else [flag, text]
    prog, fn = ("prsa-plot", plot_main) if flag in ("--kp", "--ki", "--kd") else ("prsa-tune", main)
    rc = fn(argv)
    assert rc in (2, 3)
    _outcome(capsys, rc, stand_in, prog)


def test_minus_300_rpm_is_reported_in_rpm(capsys, stand_in):
    assert main(["--setpoint-rpm", "-300"]) == 2
    assert _outcome(capsys, 2, stand_in) == "prsa-tune: error: --setpoint-rpm -300 rpm: expected a nut speed in (0, 6000] rpm"


@pytest.mark.parametrize("argv, match", [
    (["--step-time", "1e-9"], r"at least 8 controller samples .* before it \(0\.002 s"),
    (["--step-time", "0.0011", "--duration", "0.3"], r"--step-time 0\.0011: .*expected a step time >= 0\.002 s"),
    (["--step-time", "0.49"], r"--step-time 0\.49: only 0\.01 s after the load step; .* at least 80 controller samples"),
    (["--duration", "1e9"], r"--duration 1e9 s: expected a time in \(0, 10000\] s"),
    (["--duration", "100"], r"--duration 100: the record would hold 4e\+05 controller samples .* limit is 40000"),
    (["--duration", "0.1"], r"--duration 0\.1: the record ends at 0\.1 s, before the load step at 0\.2 s"),
    (["--workers", "0"], r"--workers 0: expected an integer 1\.\.64"),
    (["--objective", "mse"], r"invalid choice: 'mse'"),
    (["--dur", "1"], r"unrecognized arguments: --dur"),
    (["--duration=--"], r"--duration '--': expected a value"),
    (["--setpoint-rpm", "--"], r"--setpoint-rpm '--': expected a value"),
])
def test_events_and_sizes_the_physics_cannot_serve_are_refused(capsys, stand_in, argv, match):
    assert main(argv) == 2
    line = _outcome(capsys, 2, stand_in)
    assert re.search(match, line), line


@pytest.mark.parametrize("exc, code, hidden", [
    (ValueError("Array must not contain infs or NaNs"), 3, "Array must not"),
    (RuntimeError("Failed to find a finite solution."), 3, "finite solution"),
    (ValueError("Maximum allowed dimension exceeded"), 2, "dimension"),
    (MemoryError(), 2, "MemoryError"),
    (ZeroDivisionError("float division by zero"), 3, "float division"),
])
def test_internal_messages_are_translated_at_the_boundary(capsys, monkeypatch, exc, code, hidden):
    import prsa_ctrl.studies.autotune as autotune

    def fake(*a, **k):
        raise exc

    monkeypatch.setattr(autotune, "tune_actuator", fake)
    assert main(["--load-step", "500:1500"]) == code
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and hidden not in lines[0] and "Traceback" not in err
    assert "paper-iprsm" in lines[0] and "500 N -> 1500 N" in lines[0]


def test_geometry_note_never_precedes_an_error(capsys, stand_in):
    assert main(["--load-step", "500:abc"]) == 2
    err = capsys.readouterr().err
    assert "note:" not in err and len(err.strip().splitlines()) == 1


def test_help_describes_every_option(capsys):
    from prsa_ctrl.cli.tune import build_parser, build_plot_parser

    for parser in (build_parser(), build_plot_parser()):
        for action in parser._actions:
            assert action.help, action.option_strings
    assert plot_main(["--help"]) == 0
    text = capsys.readouterr().out
    assert "default: ./prsa-plots" in re.sub(r"\s+", " ", text).replace("prsa- plots", "prsa-plots")
    assert "--plots DIR" in text and "Exit codes" in text


# --- move scenes (prsa_ctrl.tuning.cascade.main_move) and duty-cycle details -----------------------------

@pytest.fixture
def cascade_stand_in(monkeypatch):
    """The cascade's expensive work replaced by a counting stand-in (exit 3 if reached)."""
    import prsa_ctrl.tuning.cascade as cascade

    calls = []

    def fake(*a, **k):
        calls.append(a)
        raise SimulationError("stand-in for the cascade tuner at t = 0 s; remedy: none")

    monkeypatch.setattr(cascade, "CascadeModel", fake)
    return calls


def _move_file(tmp_path, **edits):
    from prsa_ctrl.studies.scenefile import locate_scene as _scene_path

    text = _scene_path("paper-move")[0].read_text()
    for key, value in edits.items():
        text = re.sub(rf"(?m)^{key} = .*$", f"{key} = {value}", text)
    f = tmp_path / "move.toml"
    f.write_text(text)
    return str(f)


@pytest.mark.parametrize("key, value, match", [
    ("position_rate", "5", r"move\.position_rate = 5; expected an integer number of speed-loop samples per "
                           r"position-loop sample in \[1, 4\]"),
    ("position_rate", "2.0", r"move\.position_rate = 2\.0; expected an integer number"),
    ("load_n", "9000.0", r"move\.load_n = 9000\.0: moving at 30 mm/s .* beyond the motor limit of 3 N m"),
    ("hold_step_n", "8000.0", r"move\.hold_step_n = 8000\.0: holding 9500 N at rest .* beyond the motor limit"),
    ("max_speed_mm_s", "1e6", r"move\.max_speed_mm_s = 1000000\.0: expected a speed in \[0\.5, 200\] mm/s"),
    ("max_speed_mm_s", "0.01", r"move\.max_speed_mm_s = 0\.01: expected a speed in"),
    ("distance_mm", "1000.0", r"move\.distance_mm = 1000\.0: the run would last 33\.\d+ s .* limit is 40000 samples"),
    ("distance_mm", "1e9", r"move\.distance_mm = 1000000000\.0: the run would last"),
    ("hold_duration_s", "20.0", r"move\.hold_duration_s = 20\.0: the run would last"),
])
def test_move_scene_beyond_the_plant_is_refused_before_tuning(capsys, tmp_path, cascade_stand_in, key, value, match):
    rc = main(["--scene", _move_file(tmp_path, **{key: value})])
    line = _outcome(capsys, rc, cascade_stand_in)
    assert rc == 2 and re.search(match, line), line


def test_paper_move_reaches_the_tuner(capsys, cascade_stand_in):
    assert main(["--scene", "paper-move"]) == 3 and len(cascade_stand_in) == 1
    capsys.readouterr()


@pytest.mark.parametrize("argv, flag", [
    (["--estimator", "kf"], "--estimator kf"), (["--seed", "3"], "--seed 3"), (["--workers", "2"], "--workers 2"),
    (["--feedforward"], "--feedforward"), (["--accept-unconverged"], "--accept-unconverged"),
    (["--robust"], "--robust"), (["--ms-max", "1.3"], "--ms-max 1.3"), (["--setpoint-rpm", "100"], "--setpoint-rpm 100"),
    (["--monte-carlo", "5"], "--monte-carlo 5"), (["--objective", "ise"], "--objective ise"),
])
def test_move_scene_refuses_flags_it_does_not_honour(capsys, cascade_stand_in, argv, flag):
    rc = main(["--scene", "paper-move", *argv])
    line = _outcome(capsys, rc, cascade_stand_in)
    assert f"{flag} does not apply to a move scene (paper-move)" in line


def test_move_scene_outputs_must_differ(capsys, tmp_path, cascade_stand_in):
    same = str(tmp_path / "x.toml")
    rc = main(["--scene", "paper-move", "--export", same, "--json", same])
    assert "name the same path" in _outcome(capsys, rc, cascade_stand_in)
    rc = main(["--scene", "paper-move", "--plots", str(tmp_path / "p"), "--json", str(tmp_path / "p")])
    assert "name the same path" in _outcome(capsys, rc, cascade_stand_in)
    assert not (tmp_path / "x.toml").exists() and not (tmp_path / "p").exists()


def _duty_scene(tmp_path):
    f = tmp_path / "duty.toml"
    f.write_text('name = "duty"\n[operating]\ninitial_load_n = 500.0\n'
                 'setpoint_profile_rpm = [[0.0, 300.0], [0.05, 400.0, "step"]]\nduration_s = 0.2\n'
                 '[tuning]\nsetpoint_weight = 0.5\n[verify]\nfidelity = "rigid"\ndiscrete = true\n')
    return str(f)


def test_kalman_filter_on_a_duty_cycle_names_the_real_reason(capsys, tmp_path, stand_in):
    rc = main(["--scene", _duty_scene(tmp_path), "--estimator", "kf"])
    line = _outcome(capsys, rc, stand_in)
    assert "--estimator kf" in line and "Kalman-filter loop" in line and "load steps only" in line
    assert "expected its profile to set" not in line


def test_percent_differences_never_print_minus_zero():
    from prsa_ctrl.cli.report import diff_text as _diff_text, pct_text as _pct_text

    assert _diff_text(0.99999, 1.0) == "0.0 %" and _diff_text(1.00001, 1.0) == "0.0 %"
    assert _pct_text(-0.04) == "0.0 %" and _pct_text(-0.0) == "0.0 %" and _pct_text(-0.06) == "-0.1 %" and _pct_text(2.0) == "+2.0 %"


def test_json_gains_carry_the_setpoint_weight(tmp_path):
    from prsa_ctrl.cli.tune import _add_setpoint_weight
    from prsa_ctrl.studies.scene import load_scene

    data = {"gains": {"kp": 0.1, "ki": 10.0}, "units": {"kp": "N m s/rad"},
            "best": {"gains": {"kp": 0.1, "ki": 10.0}}, "baselines": [{"gains": {"kp": 0.2, "ki": 1.0}}]}
    _add_setpoint_weight(data, load_scene(_duty_scene(tmp_path)))
    assert data["gains"]["b"] == data["best"]["gains"]["b"] == data["baselines"][0]["gains"]["b"] == 0.5
    assert "b" in data["units"]
    data = {"gains": {"kp": 0.1, "ki": 10.0}}
    _add_setpoint_weight(data, load_scene("paper-load-step"))
    assert data["gains"]["b"] == 1.0
