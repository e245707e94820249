"""prsa_ctrl.cli.common: the shared command frame (issue 33/31 items: a closed standard output
ends a command quietly; ``--quiet`` silences the notes of stray warnings)."""

import os
import signal
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

from prsa_ctrl.cli import common
from prsa_ctrl.cli.common import EXIT_BROKEN_PIPE, EXIT_NUMERICAL, EXIT_OK, Run, invoke_inner

ROOT = Path(__file__).resolve().parents[2]


def _closed_stdout(args, unbuffered=False):
    """Run ``python -m`` a command with its standard output a real pipe whose read end is closed
    before the command writes: (exit code, stderr)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    env["PYTHONPATH"] = str(ROOT)
    if unbuffered:
        env["PYTHONUNBUFFERED"] = "1"
    proc = subprocess.Popen([sys.executable, "-m", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
                            cwd=ROOT)
    proc.stdout.close()  # the reader goes away (as ``| head -0`` would)
    try:
        err = proc.stderr.read().decode()
        return proc.wait(timeout=300), err
    finally:
        proc.kill()
        proc.stderr.close()


def test_broken_pipe_code_is_the_sigpipe_convention():
    import signal

    assert EXIT_BROKEN_PIPE == 128 + signal.SIGPIPE == 141


@pytest.mark.parametrize("unbuffered", [False, True])
def test_show_plant_into_a_closed_pipe_ends_quietly(unbuffered):
    code, err = _closed_stdout(["prsa_ctrl.cli.tune", "--show-plant", "paper-iprsm"], unbuffered)
    assert code == EXIT_BROKEN_PIPE
    assert err == ""  # no traceback, no "failed (BrokenPipeError)", no "Exception ignored"


@pytest.mark.parametrize("module", ["prsa_ctrl.cli.tune", "prsa_ctrl.cli.plot", "prsa_ctrl.cli.fit", "prsa_ctrl.cli.pid"])
def test_every_command_into_a_closed_pipe_ends_quietly(module):
    code, err = _closed_stdout([module, "--help"])
    assert code in (EXIT_OK, EXIT_BROKEN_PIPE)  # argparse's help printer drops write errors itself: 0
    assert err == ""


def test_a_broken_pipe_that_is_not_stdout_is_still_a_failure(capsys):
    def body(run, argv):
        raise BrokenPipeError(32, "Broken pipe")  # a worker's or a socket's pipe, stdout fine

    with warnings.catch_warnings():
        warnings.simplefilter("always")
        code = invoke_inner(Run("prsa-x"), [], body)
    assert code == EXIT_NUMERICAL
    assert "failed (BrokenPipeError)" in capsys.readouterr().err


def _warning_body(run, argv):
    run.quiet = "--quiet" in argv  # as the commands set it from their parsed flags
    warnings.warn("a stray warning", UserWarning)
    return EXIT_OK


@pytest.mark.parametrize("quiet", [False, True])
def test_quiet_suppresses_the_notes_of_stray_warnings(quiet, capsys):
    with warnings.catch_warnings():
        warnings.simplefilter("always")  # not the suite's "error": a stray warning as a user meets it
        code = invoke_inner(Run("prsa-x"), ["--quiet"] if quiet else [], _warning_body)
    assert code == EXIT_OK
    err = capsys.readouterr().err
    assert err == ("" if quiet else "prsa-x: note: UserWarning: a stray warning\n")


@pytest.mark.parametrize("quiet", [False, True])
def test_prsa_tune_quiet_sets_the_frame_quiet(quiet, capsys, monkeypatch):
    import prsa_ctrl.plant.describe as describe
    from prsa_ctrl.cli.tune import main

    def show(name):
        warnings.warn("stray from the plant", UserWarning)
        return "plant text"

    monkeypatch.setattr(describe, "show_plant", show)
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        assert main(["--show-plant", "paper-iprsm", *(["--quiet"] if quiet else [])]) == EXIT_OK
    err = capsys.readouterr().err
    assert ("note: UserWarning: stray from the plant" in err) is (not quiet)


def test_pid_quiet_is_read_by_the_frame():
    import inspect

    from prsa_ctrl.cli import pid

    assert "run.quiet = args.quiet" in inspect.getsource(pid)  # the same line as prsa-tune's (tested above)
    assert common.Run("x").quiet is False


# ------------------------------------------------------------------------------------------------
# Issue 20: an interrupted in-process command gives SIGTERM its old handler back.
# ------------------------------------------------------------------------------------------------

# --- item 2: filter arguments out of range are named, never "b0 = nan" -------------------------


# --- item 1: a notch is kept only where it acts on the mode -------------------------------------


# --- items 3, 4, 5: robust study -> recommended design, strict JSON, named export ----------------


# --- item 7: the Monte-Carlo replay on a duty scene ----------------------------------------------


# --- item 6: SIGTERM during a Monte-Carlo process pool -------------------------------------------


def test_an_interrupted_command_does_not_leave_sigterm_ignored():
    """After an interrupted in-process command SIGTERM has its old handler again: an ignored
    SIGTERM would be inherited by every later child process (whose workers then survive
    ``terminate()``)."""
    from prsa_ctrl.cli import common as cli

    def body(run, argv):
        run.interrupted = True
        raise KeyboardInterrupt

    old_int, old_term = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    try:
        assert cli.invoke_inner(cli.Run("prsa-tune"), [], body) == cli.EXIT_INTERRUPTED
        assert signal.getsignal(signal.SIGTERM) is old_term
    finally:
        signal.signal(signal.SIGINT, old_int)
        signal.signal(signal.SIGTERM, old_term)


# --- failures classified by type and origin, never by message ------------------------------------

def _raised(fn):
    try:
        fn()
    except BaseException as exc:  # noqa: BLE001
        return exc
    raise AssertionError("did not raise")


def test_our_own_value_error_is_shown_even_when_it_says_nan_or_overflow():
    from prsa_ctrl.options import check_number

    exc = _raised(lambda: check_number("load", float("nan")))
    assert common.describe_failure(exc, "tuning") == (EXIT_NUMERICAL, "numerical failure: load = nan; expected a finite number")
    exc = _raised(lambda: check_number("gain", "overflow"))
    assert common.describe_failure(exc, "tuning")[1] == "numerical failure: gain = 'overflow'; expected a finite number"


def test_foreign_errors_name_the_step_and_the_library_not_its_message():
    import numpy as np
    import scipy.linalg

    exc = _raised(lambda: scipy.linalg.solve(np.array([[np.nan]]), np.array([1.0])))
    assert common.raised_in(exc).startswith("numpy.")  # scipy's input check, raised in numpy
    code, line = common.describe_failure(exc, "tuning")
    assert code == EXIT_NUMERICAL
    assert line.startswith("numerical failure: tuning failed in numpy (ValueError); check")
    assert "nan" not in line.lower()
    exc = _raised(lambda: np.linalg.inv(np.zeros((2, 2))))
    assert common.describe_failure(exc, "tuning")[1].startswith(
        "numerical failure: tuning produced non-finite numbers (LinAlgError)")
    exc = _raised(lambda: 1.0 / 0.0)
    assert "(ZeroDivisionError)" in common.describe_failure(exc, "tuning")[1]


def test_memory_input_and_unknown_errors_by_type():
    from prsa_ctrl.errors import SceneError

    assert common.describe_failure(MemoryError(), "x")[0] == common.EXIT_BAD_INPUT
    assert common.describe_failure(SceneError("s.toml: bad"), "x") == (common.EXIT_BAD_INPUT, "error: s.toml: bad")
    line = common.describe_failure(_raised(lambda: {}["k"]), "x")[1]
    assert line == "numerical failure: x failed (KeyError); rerun with --verbose for details"
    # the words alone classify nothing: an unknown error saying "overflow" is still unknown
    assert common.describe_failure(KeyError("overflow"), "x")[1].endswith("failed (KeyError); rerun with --verbose for details")


def test_a_progress_line_during_captured_solver_output_reaches_the_terminal_once():
    """``--verbose`` progress said while the solvers' output is captured goes to the terminal's
    stderr, not among the captured solver lines (was shown again as 'prog: solver: prog: ...')."""
    code = ("from prsa_ctrl.cli.common import Run, native_output, progress\n"
            "run, lines = Run('prog'), []\n"
            "with native_output(run, lines):\n"
            "    progress(run, True, 'step one')\n"
            "    print('solver says hi')\n"
            "print('captured:', lines)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stderr.splitlines() == ["prog: step one"]
    captured = out.stdout.strip().splitlines()[-1]
    assert "solver says hi" in captured
    assert "step one" not in captured


# --- argv read once: a flag that keeps its text as typed -----------------------------------------

def _typed_parser():
    p = common.Parser(prog="t")
    p.add_argument("--offset", action=common.KeepTyped, type=common.number("--offset", 0.0, 10.0, "rad/s", "a speed"),
                   default=3.0)
    p.add_argument("--count", action=common.KeepTyped, type=int, default=1)
    return p


@pytest.mark.parametrize("argv, value, typed", [
    ([], 3.0, None),  # the default: no text
    (["--offset", "1e0"], 1.0, "1e0"),
    (["--offset=0002.50"], 2.5, "0002.50"),
    (["--offset", "1", "--offset", " 4"], 4.0, " 4"),  # the last one, as argparse takes it
    (["--off", "5"], 5.0, "5"),  # argparse's prefixes: the same flag
])
def test_keep_typed_stores_the_value_and_the_text(argv, value, typed):
    args = _typed_parser().parse_args(argv)
    assert args.offset == value
    assert common.typed_text(args, "offset") == typed


@pytest.mark.parametrize("argv, message", [
    (["--offset", "11"], "--offset 11 rad/s: expected a speed in [0, 10] rad/s"),
    (["--offset", "x"], "--offset 'x': expected a speed in [0, 10] rad/s"),
    (["--count", "2.5"], "argument --count: invalid int value: '2.5'"),
])
def test_keep_typed_errors_read_as_argparse_own(argv, message):
    plain = common.Parser(prog="t")  # the same flags without the action: the same one line
    plain.add_argument("--offset", type=common.number("--offset", 0.0, 10.0, "rad/s", "a speed"), default=3.0)
    plain.add_argument("--count", type=int, default=1)
    for p in (_typed_parser(), plain):
        with pytest.raises(common.UsageError) as exc:
            p.parse_args(argv)
        assert str(exc.value) == message


def test_status_says_interrupted_is_deprecated_and_walks_no_result():
    with pytest.warns(DeprecationWarning, match="status_says_interrupted is deprecated"):
        assert common.status_says_interrupted({"status": "User_Requested_Stop"}) is False  # no dict walk


def test_flag_value_is_gone():
    """argv is read once, through argparse (``KeepTyped``): the hand reader of argv went."""
    assert not hasattr(common, "flag_value")
