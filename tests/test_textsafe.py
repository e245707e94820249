"""User text on its way to a terminal (issue 31): control characters of a plant, scene or file
name are escaped in everything the commands print; a value is quoted as a bounded excerpt; a
numpy warning never prints its source line before a one-line error."""

from __future__ import annotations

import os
import subprocess
import sys
import unicodedata
import warnings
from pathlib import Path

import pytest

from prsa_ctrl.cli.common import EXIT_BAD_INPUT, EXIT_OK, Run, echo, invoke_inner
from prsa_ctrl.cli.tune import main as tune_main
from prsa_ctrl.textsafe import MESSAGE_CHARS_MAX, printable, quote

ROOT = Path(__file__).resolve().parents[1]
PAPER = (ROOT / "plants" / "paper-iprsm.toml").read_text(encoding="utf-8")
SCENE = (ROOT / "tuning" / "paper-load-step.toml").read_text(encoding="utf-8")
#: Window title, clear screen, red text, cursor home, bell, CR overwrite, C1 CSI, bidi override.
EVIL = "\x1b]0;pwned\x07\x1b[2J\x1b[31mRED\x1b[H\r\x9b31m\u202eevil"


def _terminal_safe(text: str, multiline: bool) -> bool:
    """No character of category Cc (C0, DEL, C1) but LF/TAB in multi-line output, no bidi control."""
    allowed = {"\n", "\t"} if multiline else set()
    return all((unicodedata.category(c) != "Cc" or c in allowed) and not (0x202A <= ord(c) <= 0x202E)
               for c in text)


# --- the helpers ----------------------------------------------------------------------------------

def test_printable_escapes_every_control_character_and_keeps_the_rest():
    every = "".join(chr(i) for i in range(0x20)) + "\x7f" + "".join(chr(i) for i in range(0x80, 0xA0))
    out = printable(every + "ok é µ 中")
    assert _terminal_safe(out, multiline=False)
    assert out.endswith("ok é µ 中")
    assert out.startswith("\\x00\\x01")
    assert "\\x1b" in out
    assert "\\x9b" in out
    assert "\\n" in out
    assert printable("a\nb\tc", multiline=True) == "a\nb\tc"
    assert printable("a\nb\tc\x1b") == "a\\nb\\tc\\x1b"
    assert printable("\u202eevil\u2066") == "\\u202eevil\\u2066"
    assert printable("\udcff.toml") == "\\udcff.toml"  # an undecodable file name (surrogateescape)


def test_printable_bounds_the_length_keeping_both_ends():
    text = "start " + "x" * 100_000 + " end"
    out = printable(text, limit=300)
    assert len(out) <= 300
    assert out.startswith("start ")
    assert out.endswith(" end")
    assert "100010 characters" in out


def test_quote_is_repr_when_short_and_a_bounded_excerpt_otherwise():
    for v in ("a'b", 1.5, [1, 2], {"a": 1}, None, 10 ** 30):
        assert quote(v) == repr(v)
    q = quote([1500.0] * 100_000)
    assert len(q) < 300
    assert q.startswith("[1500.0, 1500.0")
    assert "100000 entries" in q
    assert "401 digits" in quote(10 ** 400)
    assert len(quote(10 ** 400)) < 100
    huge = quote(10 ** 5000)  # beyond the digit limit of str(int)
    assert "integer of about 500" in huge
    assert len(huge) < 60


# --- the commands ---------------------------------------------------------------------------------

def test_show_plant_escapes_name_and_description(tmp_path, capsys):
    f = tmp_path / "evil.toml"
    f.write_text(PAPER.replace('name = "paper-iprsm"', f"name = {_toml(EVIL)}")
                 .replace('description = "Inverted', f'description = {_toml(EVIL)[:-1]} Inverted'), encoding="utf-8")
    capsys.readouterr()
    assert tune_main(["--show-plant", str(f)]) == EXIT_OK
    out = capsys.readouterr().out
    assert _terminal_safe(out, multiline=True), repr(out[:300])
    first = out.splitlines()[0]
    assert first.startswith("plant \\x1b]0;pwned\\x07\\x1b[2J")
    assert "\\u202eevil" in first
    assert "Inverted" in first


def test_error_lines_escape_a_file_name_and_a_value(tmp_path, capsys):
    bad = tmp_path / f"p{EVIL}.toml"
    bad.write_text("not toml [", encoding="utf-8")
    capsys.readouterr()
    assert tune_main(["--show-plant", str(bad)]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert err.count("\n") == 1, repr(err)
    assert _terminal_safe(err.rstrip("\n"), multiline=False), repr(err)
    assert "p\\x1b]0;pwned\\x07" in err
    assert "invalid TOML" in err
    scene = tmp_path / "s.toml"
    scene.write_text(SCENE.replace('objective = "iae"', f"objective = {_toml(EVIL)}"), encoding="utf-8")
    assert tune_main(["--scene", str(scene)]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert err.count("\n") == 1, repr(err)
    assert _terminal_safe(err.rstrip("\n"), multiline=False), repr(err)
    assert "objective" in err, repr(err)


def test_report_header_escapes_plant_and_scene_names(tmp_path):
    from prsa_ctrl.studies.scenereport import scene_header
    from prsa_ctrl.studies.scene import load_scene

    f = tmp_path / "s.toml"
    f.write_text(SCENE.replace('name = "paper-load-step"', f"name = {_toml(EVIL)}"), encoding="utf-8")
    head = scene_header(load_scene(str(f)))
    assert _terminal_safe(head, multiline=False)
    assert "\\x1b]0;pwned" in head


def test_prsa_fit_error_line_escapes_the_file_name(tmp_path, capsys):
    from prsa_ctrl.cli.fit import main as fit_main

    log = tmp_path / f"log{EVIL}.csv"
    log.write_text("no,columns\n1,2\n", encoding="utf-8")
    capsys.readouterr()
    rc = fit_main([str(log), "--plant", "paper-iprsm", "--out", str(tmp_path / "o.toml")])
    err = capsys.readouterr().err
    assert rc == EXIT_BAD_INPUT, repr(err)
    assert err.count("\n") == 1, repr(err)
    assert _terminal_safe(err.rstrip("\n"), False), repr(err)
    assert not (tmp_path / "o.toml").exists()


def test_echo_keeps_report_lines_and_makes_stderr_one_bounded_line(capsys):
    echo("line 1\n\x1b[2Jline 2")
    echo("note\nsecond" + "y" * 10_000, file=sys.stderr)
    cap = capsys.readouterr()
    assert cap.out == "line 1\n\\x1b[2Jline 2\n"
    assert cap.err.count("\n") == 1
    assert cap.err.startswith("note\\nsecond")
    assert len(cap.err) <= MESSAGE_CHARS_MAX + 1


def test_a_100000_entry_value_gives_a_short_error(tmp_path, capsys):
    f = tmp_path / "many.toml"
    f.write_text(SCENE.replace("final_loads_n = [1500.0]", "final_loads_n = [" + ", ".join(["1500.0"] * 100_000) + "]"))
    capsys.readouterr()
    assert tune_main(["--scene", str(f)]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert err.count("\n") == 1, len(err)
    assert len(err) < 600, len(err)  # was 800,097 characters
    assert "operating.final_loads_n = [1500.0, 1500.0" in err
    assert "100000 entries" in err


# --- warnings at the command boundary -------------------------------------------------------------

def _warn_then(code):
    def body(run, argv):
        warnings.warn("overflow encountered in divide", RuntimeWarning)
        if code:  # the toolkit's own error type: failures are classified by type and origin (issue 33)
            from prsa_ctrl.errors import SceneError

            raise SceneError("bad input")
        return EXIT_OK
    return body


def test_a_stray_warning_is_a_note_after_success_and_nothing_before_an_error(capsys):
    warnings.simplefilter("default")  # as a command runs (pytest turns warnings into errors); undone by pytest
    assert invoke_inner(Run("prog"), [], _warn_then(False)) == EXIT_OK
    err = capsys.readouterr().err
    assert err == "prog: note: RuntimeWarning: overflow encountered in divide\n"
    assert invoke_inner(Run("prog"), [], _warn_then(True)) != EXIT_OK
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "RuntimeWarning" not in err
    assert "bad input" in err
    with warnings.catch_warnings(record=True) as outer:  # the caller's filters are left alone
        warnings.simplefilter("always")
        warnings.warn("outside", UserWarning)
    assert len(outer) == 1


@pytest.mark.parametrize("argv", [["--plant", "1e300/(1e-300s+1)"], ["--plant", "1e-300/(1e300s+1)"]])
def test_prsa_pid_prints_no_warning_before_its_one_line(argv, tmp_path):
    """In a real process (pytest's own warning capture would hide the difference in-process)."""
    code = "import sys\nfrom prsa_ctrl.cli.pid import pid_main\nsys.exit(pid_main(sys.argv[1:]))\n"
    env = {**os.environ, "PYTHONWARNINGS": ""}
    p = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, cwd=tmp_path,
                       timeout=120, env=env)
    assert p.returncode == EXIT_BAD_INPUT, p.stderr
    assert len(p.stderr.splitlines()) == 1, p.stderr
    assert p.stderr.startswith("prsa-pid: error: --plant"), p.stderr


def _toml(text: str) -> str:
    """A TOML basic string holding ``text`` (control characters as \\uXXXX escapes)."""
    return '"' + "".join(f"\\u{ord(c):04x}" if unicodedata.category(c) == "Cc" or c in '"\\' else c
                         for c in text) + '"'
