"""The README says what the code does: its examples are run and compared with the code's output."""

import contextlib
import importlib.util
import io
import os
import re
import shlex
import shutil
import subprocess
import sys
import tomllib
import warnings
from pathlib import Path

import pytest

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
    assert "load_profile_n" in text
    assert "load_trace_csv" in text
    assert "scene files do not describe" not in text.lower()


def test_readme_export_example_is_what_the_export_writes():
    """The drive-export example: run the README's Python snippet, compare its TOML with the README's."""
    text = README.read_text(encoding="utf-8")
    toml_blocks = [(at, body) for at, body in _blocks(text, "toml") if "prsa-ctrl drive export" in body]
    assert len(toml_blocks) == 1, "the README shows one drive-export example"
    at, shown_text = toml_blocks[0]
    snippet = [body for start, body in _blocks(text, "python") if start < at][-1]
    assert "export_controller" in snippet
    assert "print(dumps(" in snippet
    out = io.StringIO()
    with warnings.catch_warnings(), contextlib.redirect_stdout(out):
        warnings.simplefilter("ignore")
        exec(compile(snippet, "README.md", "exec"), {})
    real = tomllib.loads(out.getvalue())
    shown = tomllib.loads(shown_text)
    assert shown, "the README's example parses to an empty document"
    assert _subset_mismatches(shown, real) == []


# --- every snippet of the README is run (or, for install and test commands, checked) ---------

ROOT = README.parent
_TEXT = README.read_text(encoding="utf-8")
_PYTHON = [body for _, body in _blocks(_TEXT, "python")]
#: The shell blocks, each a list of its command lines (a block's lines run in order in one folder,
#: so that a line may read what an earlier line of its block wrote).
_SHELL = [[line.strip() for line in body.splitlines() if line.strip() and not line.strip().startswith("#")]
          for _, body in _blocks(_TEXT, "bash")]
#: The documentation build of tests/test_docs.py (kept equal to its BUILD_ARGS, checked below).
_DOCS_BUILD = ["-W", "--keep-going", "-b", "html", "docs"]


def test_readme_is_short():
    n = len(_TEXT.splitlines())
    assert n < 250, f"README.md has {n} lines; the manual is docs/, the README stays under 250"


@pytest.mark.parametrize("index", range(len(_PYTHON)))
def test_readme_python_snippet_runs(index, tmp_path, monkeypatch, paper_report):
    """Each snippet runs and prints no nan. Its ``tune_actuator(plant, paper-load-step)`` on the
    built-in paper plant is answered by the same call made once per session (tests/conftest.py's
    ``paper_report``; the tuning is deterministic); any other call runs as written."""
    import prsa_ctrl
    from prsa_ctrl import load_plant, load_scene
    from prsa_ctrl.studies.autotune import tune_actuator

    plant0, scene0 = load_plant(), load_scene()  # paper_report's arguments

    def tune_once(plant, scene, workers=None):
        same = (plant.name == plant0.name and dict(plant.values) == dict(plant0.values)
                and dict(plant.sources) == dict(plant0.sources) and scene == scene0)
        return paper_report if same else tune_actuator(plant, scene, workers)

    monkeypatch.setattr(prsa_ctrl, "tune_actuator", tune_once)
    monkeypatch.chdir(tmp_path)
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(_PYTHON[index], f"README.md python snippet {index + 1}", "exec"), {})
    assert "nan" not in out.getvalue().lower()


def _extras():
    return set(tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"])


def _script(name):
    found = shutil.which(name, path=os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")]))
    assert found, f"{name} is not installed next to {sys.executable}"
    return found


def _check_install(words):
    """``pip install .`` or ``pip install ".[extra,...]"``, every extra defined in pyproject.toml."""
    assert words[:2] == ["pip", "install"], f"unexpected install command {words}"
    assert len(words) == 3, f"unexpected install command {words}"
    target = words[2]
    assert target == "." or (target.startswith(".[") and target.endswith("]")), target
    unknown = set(target[2:-1].split(",")) - _extras() if target != "." else set()
    assert not unknown, f"README installs extras that pyproject.toml does not define: {unknown}"


def _runs_a_command(block):
    return any(p.strip().startswith("prsa-") for line in block for p in line.split("&&"))


#: The console scripts of the README's commands and their argument parsers.
_PARSERS = {"prsa-tune": "prsa_ctrl.cli.tune:build_parser", "prsa-plot": "prsa_ctrl.cli.plot:build_plot_parser",
            "prsa-pid": "prsa_ctrl.cli.pid:build_pid_parser", "prsa-fit": "prsa_ctrl.cli.fit:build_parser"}


def test_readme_commands_are_accepted_by_their_parsers():
    """Every prsa-* line of the README names an installed command whose parser accepts it as
    written, and every examples/ path it names exists. (The blocks that run the commands are the
    slow test below; what each command does is asserted in the default suite by the command's
    own tests: the default run with --load-step 500:1500 and every output in tests/conftest.py's
    default_cli_run, prsa-plot in tests/cli/test_plot.py, duty-ramp in
    tests/studies/test_scenekinds.py, this prsa-pid case in tests/cli/test_pid.py (pi-mks), the EMPS
    fit and --show-plant in tests/identification/test_axis.py.)"""
    import importlib

    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    seen = 0
    for block in _SHELL:
        for part in (p.strip() for line in block for p in line.split("&&")):
            words = shlex.split(part)
            if not words[0].startswith("prsa-"):
                continue
            assert words[0] in _PARSERS, f"README runs {words[0]}: add its parser to _PARSERS"
            module, builder = _PARSERS[words[0]].split(":")
            assert scripts[words[0]].split(":")[0] == module, (words[0], scripts[words[0]])
            parser = getattr(importlib.import_module(module), builder)()
            try:
                parser.parse_args(words[1:])
            except SystemExit as exc:
                pytest.fail(f"{part}: refused by its parser (exit {exc.code})")
            for w in words[1:]:
                if w.startswith("examples/"):
                    assert (ROOT / w).exists(), f"{part}: {w} not in the repository"
            seen += 1
    assert seen >= 5


@pytest.mark.parametrize("block", [pytest.param(b, marks=pytest.mark.slow) if _runs_a_command(b) else b
                                   for b in _SHELL], ids=[b[0][:40] for b in _SHELL])
def test_readme_shell_block_runs_or_is_checked(block, tmp_path):
    """Install commands name real extras; the test command is the one CI runs; the docs build is
    test_docs.py's; every prsa-* command runs (exit 0) and writes what it says, in a temp dir, the
    lines of one block in order; paths into the repository's examples/ are read from the checkout.
    The blocks that run commands (each a full run of the installed script) are ``-m slow``."""
    for part in (p.strip() for line in block for p in line.split("&&")):
        words = [str(ROOT / w) if w.startswith("examples/") else w for w in shlex.split(part)]
        if words[:2] == ["pip", "install"]:
            _check_install(words)
        elif words == ["bash", "scripts/fresh-test.sh"]:
            assert (ROOT / "scripts" / "fresh-test.sh").is_file()
            assert "bash scripts/fresh-test.sh" in (ROOT / ".ci" / "run").read_text()
        elif words[0] == "sphinx-build":
            assert words[1:-1] == _DOCS_BUILD, words
            assert not words[-1].startswith(("docs", ".")), words
            spec = importlib.util.spec_from_file_location("_test_docs", ROOT / "tests" / "test_docs.py")
            docs_test = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(docs_test)
            assert docs_test.BUILD_ARGS + ["docs"] == _DOCS_BUILD
        elif words[0].startswith("prsa-"):
            env = {**os.environ, "MPLBACKEND": "Agg"}
            proc = subprocess.run([_script(words[0]), *words[1:]], cwd=tmp_path, env=env, capture_output=True,
                                  text=True, timeout=300)
            assert proc.returncode == 0, f"{part}: exit {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
            for flag in ("--json", "--export", "--plots", "--out"):
                if flag in words:
                    target = tmp_path / words[words.index(flag) + 1]
                    assert target.exists(), f"{part}: {flag} wrote nothing"
        else:
            pytest.fail(f"README shell line not covered by the tests: {part!r}")


def test_readme_links_resolve():
    """Every relative link of the README names a file of the repository (the docs pages)."""
    bad = []
    for target in re.findall(r"\]\(([^)]+)\)", _TEXT):
        if target.startswith(("http://", "https://", "#")):
            continue
        if not (ROOT / target.split("#")[0]).exists():
            bad.append(target)
    assert bad == [], f"README links to missing files: {bad}"
