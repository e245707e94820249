"""The README says what the code does: its examples are run and compared with the code's output."""

import contextlib
import io
import re
import tomllib
import warnings
from pathlib import Path

README = Path(__file__).resolve().parent.parent / "README.md"


def _blocks(text, lang):
    """Every fenced code block of one language, in order, with its start offset."""
    return [(m.start(), m.group(1)) for m in re.finditer(rf"```{lang}\n(.*?)```", text, flags=re.S)]


def _subset_mismatches(shown, real, path=""):
    """Keys of ``shown`` whose value differs from ``real`` (``shown`` may leave keys out)."""
    bad = []
    for key, value in shown.items():
        where = f"{path}.{key}" if path else key
        if key not in real:
            bad.append(f"{where}: not in the real export")
        elif isinstance(value, dict):
            bad.extend(_subset_mismatches(value, real[key], where))
        elif value != real[key]:
            bad.append(f"{where}: README {value!r}, real {real[key]!r}")
    return bad


def test_readme_holds_no_editing_leftovers():
    text = README.read_text(encoding="utf-8")
    for marker in ('" of README.md', "from its\nheading up to", "<<<<<<<", ">>>>>>>"):
        assert marker not in text, f"leftover edit instruction or merge marker {marker!r} in README.md"


def test_readme_does_not_deny_what_scene_files_do():
    """Scene files describe ramps and traces (the duty-cycle section); no sentence may deny it."""
    text = " ".join(README.read_text(encoding="utf-8").split())
    assert "load_profile_n" in text and "load_trace_csv" in text
    assert "scene files do not describe" not in text.lower()


def test_readme_export_example_is_what_the_export_writes():
    """The drive-export example: run the README's Python snippet, compare its TOML with the README's."""
    text = README.read_text(encoding="utf-8")
    toml_blocks = [(at, body) for at, body in _blocks(text, "toml") if "prsa-ctrl drive export" in body]
    assert len(toml_blocks) == 1, "the README shows one drive-export example"
    at, shown_text = toml_blocks[0]
    snippet = [body for start, body in _blocks(text, "python") if start < at][-1]
    assert "export_controller" in snippet and "print(dumps(" in snippet
    out = io.StringIO()
    with warnings.catch_warnings(), contextlib.redirect_stdout(out):
        warnings.simplefilter("ignore")
        exec(compile(snippet, "README.md", "exec"), {})
    real = tomllib.loads(out.getvalue())
    shown = tomllib.loads(shown_text)
    assert shown, "the README's example parses to an empty document"
    assert _subset_mismatches(shown, real) == []
