"""The documentation site builds with warnings as errors, and its API reference holds every public name.

The build is the one the README documents (``sphinx-build -W --keep-going -b html docs OUT``), run
once per module in a subprocess, with its output and doctrees in a temporary folder outside the
checkout. Without Sphinx (``pip install ".[docs]"``) the tests skip, except under ``CI=true``,
where they fail: CI must build the docs.
"""

import importlib
import inspect
import os
import pkgutil
import posixpath
import subprocess
import sys
from pathlib import Path

import pytest

import prsa_ctrl

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
#: The README's build command, less the output folder (tests/test_readme.py checks it is the same).
BUILD_ARGS = ["-W", "--keep-going", "-b", "html"]


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    try:
        import sphinx  # noqa: F401
    except ImportError:
        if os.environ.get("CI") == "true":
            pytest.fail("sphinx is not installed under CI=true: the docs must be built (pip install '.[docs]')")
        pytest.skip("sphinx not installed: pip install '.[docs]' to build the documentation")
    out = tmp_path_factory.mktemp("docs")
    html = out / "html"
    env = {**os.environ, "MPLBACKEND": "Agg"}
    # cwd outside the checkout: ``python -m`` puts the cwd first on sys.path, and the build must
    # document the installed package.
    proc = subprocess.run([sys.executable, "-m", "sphinx", *BUILD_ARGS, "-q", "-d", str(out / "doctrees"),
                           str(DOCS), str(html)], cwd=out, env=env, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, f"sphinx-build failed (exit {proc.returncode}):\n{proc.stdout}\n{proc.stderr}"
    assert ROOT not in html.parents, "the build must write outside the checkout"
    return html


def _inventory(html):
    from sphinx.util.inventory import InventoryFile

    with open(html / "objects.inv", "rb") as f:
        inv = InventoryFile.load(f, "", posixpath.join)
    data = getattr(inv, "data", inv)  # Sphinx >= 8.2 returns an object with .data
    return {name for kind, entries in data.items() if kind.startswith("py:") for name in entries}


def _subpackages():
    """Every subpackage of prsa_ctrl with public names (data folders such as plants/ have none)."""
    out = []
    for m in pkgutil.iter_modules(prsa_ctrl.__path__):
        if m.ispkg:
            mod = importlib.import_module(f"prsa_ctrl.{m.name}")
            if getattr(mod, "__all__", None):
                out.append(mod)
    return out


def _reference_modules():
    """What the API reference documents: every subpackage, and the plain modules errors and options."""
    return [*_subpackages(), importlib.import_module("prsa_ctrl.errors"), importlib.import_module("prsa_ctrl.options")]


def _documented_as(module, name):
    """The names under which ``module.name`` may appear in the reference: the public path, or,
    where a submodule of the same name shadows it, the path of the module that defines it."""
    obj = getattr(module, name)
    if inspect.ismodule(obj) and hasattr(obj, name):
        return {f"{obj.__name__}.{name}"}
    return {f"{module.__name__}.{name}"}


def test_site_builds_with_warnings_as_errors(site):
    for page in ("index", "getting-started", "guides/cli", "guides/plant-files", "guides/scenes",
                 "guides/calibration", "guides/cascade", "guides/export", "explanation/physics",
                 "explanation/guarantees", "benchmarks", "api/index", "tutorials/index"):
        assert (site / f"{page}.html").is_file(), f"{page} not built"
    text = (site / "guides" / "plant-files.html").read_text(encoding="utf-8")
    # The key table is generated from the code: every key of every section is on the page.
    from prsa_ctrl.plant import SCHEMA

    missing = [f"{s}.{k}" for s, keys in SCHEMA.items() for k in keys if f"{s}.{k}" not in text]
    assert missing == [], f"plant keys missing from the plant-file guide: {missing}"


def test_every_public_name_is_in_the_api_reference(site):
    documented = _inventory(site)
    missing = []
    for mod in _reference_modules():
        if mod.__name__ not in documented:
            missing.append(f"{mod.__name__} (no page)")
        for name in mod.__all__:
            if not _documented_as(mod, name) & documented:
                missing.append(f"{mod.__name__}.{name}")
    assert missing == [], f"public names missing from the API reference: {missing}"


def test_every_top_level_name_is_listed_and_linked(site):
    documented = _inventory(site)
    index = (site / "api" / "index.html").read_text(encoding="utf-8")
    missing = [n for n in prsa_ctrl.__all__ if f"prsa_ctrl.{n}" not in index]
    assert missing == [], f"top-level names missing from the API index: {missing}"
    # Each is documented: on its module's page, or (exported at the top only) on the index.
    for n in prsa_ctrl.__all__:
        homes = {f"prsa_ctrl.{n}"}.union(*(_documented_as(mod, n) for mod in _reference_modules() if n in mod.__all__))
        assert homes & documented, f"prsa_ctrl.{n}: documented nowhere"


def test_every_notebook_is_a_tutorial(site):
    notebooks = sorted(p.stem for p in (ROOT / "notebooks").glob("*.ipynb"))
    assert notebooks, "no notebooks found"
    linked = sorted(p.stem for p in (DOCS / "tutorials").glob("*.ipynb"))
    assert linked == notebooks, "docs/tutorials/ must link every notebook of notebooks/ (ln -s ../../notebooks/X.ipynb)"
    for name in notebooks:
        assert (DOCS / "tutorials" / f"{name}.ipynb").resolve() == (ROOT / "notebooks" / f"{name}.ipynb").resolve()
        assert (site / "tutorials" / f"{name}.html").is_file(), f"tutorial {name} not rendered"


def test_docs_pages_hold_no_editing_leftovers():
    """No page keeps an editing instruction or a merge marker (the README once kept one at a heading)."""
    bad = []
    for page in DOCS.rglob("*.md"):
        text = page.read_text(encoding="utf-8")
        for marker in ('" of README.md', "from its\nheading up to", "<<<<<<<", ">>>>>>>", "\n=======\n"):
            if marker in text:
                bad.append(f"{page.relative_to(ROOT)}: {marker!r}")
    assert bad == []
