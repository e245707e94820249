"""The package's structure (issue 22), held for every module: under 1,000 lines, no private
name crossing a module boundary, imports only down the layers and never in a circle, the
zero-order hold and the Radau IIA tableau written once, figures apart from the fits, every
exception in prsa_ctrl.errors."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

import prsa_ctrl
from prsa_ctrl.errors import SceneError

PKG = Path(prsa_ctrl.__file__).parent
AREA = sorted(PKG.rglob("*.py"))
#: Layers, lowest first: a module may import from its own layer or below (docs/development/layout.md).
LAYERS = [("errors", "options", "results", "_lazy", "textsafe", "tomlfile", "tablefile", "reporttext"), ("plant",), ("drive",), ("sim",), ("tuning",),
          ("identification",), ("studies",), ("io",), ("plots",), ("cli",), ("app",)]
RANK = {name: i for i, names in enumerate(LAYERS) for name in names}
#: Where the whole drive/sim/identification area may discretise with expm / write the Radau tableau.
ZOH_HOME = PKG / "drive" / "sampled.py"
RADAU_HOME = PKG / "sim" / "integrators.py"


def _tree(path: Path) -> ast.AST:
    return ast.parse(path.read_text(encoding="utf-8"))


def _imports(path: Path):
    for node in ast.walk(_tree(path)):
        if isinstance(node, ast.ImportFrom):
            yield node.level, node.module or "", [a.name for a in node.names]
        elif isinstance(node, ast.Import):
            for a in node.names:
                yield 0, a.name, []


def test_the_split_modules_exist_and_stay_small():
    for rel in ("sim/integrators.py", "sim/signals.py", "sim/engine.py", "identification/common.py",
                "identification/timedomain.py", "identification/frf.py", "plots/fit.py", "drive/sampled.py"):
        assert (PKG / rel).is_file(), rel
    assert not (PKG / "identification" / "fit.py").exists()
    for path in AREA:
        n = len(path.read_text(encoding="utf-8").splitlines())
        assert n < 1000, f"{path.relative_to(PKG)}: {n} lines"


@pytest.mark.parametrize("path", AREA, ids=lambda p: str(p.relative_to(PKG)))
def test_no_private_name_imported_across_modules(path):
    for level, module, names in _imports(path):
        if level or module.startswith("prsa_ctrl"):
            private = [n for n in names if n.startswith("_") and not n.startswith("__")]
            assert not private, f"{path.relative_to(PKG)} imports {private} from {'.' * level}{module}"


TESTS = Path(__file__).resolve().parent
#: Private names a test may still import, as "tests/<file>: prsa_ctrl.<module>.<name>" (none:
#: a test uses the public name, or tests an internal through the public function that calls it).
PRIVATE_IMPORTS_ALLOWED: frozenset = frozenset()


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def _private_imports(path: Path):
    """``(line, "prsa_ctrl.module.name")`` of every import of a private name or module of the
    package in ``path``, however it is written (``from``, ``import``, aliased, inside a function)."""
    for node in ast.walk(_tree(path)):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").split(".")[0] == "prsa_ctrl":
            in_private = any(_private(x) for x in node.module.split("."))
            for a in node.names:
                if in_private or _private(a.name):
                    yield node.lineno, f"{node.module}.{a.name}"
        elif isinstance(node, ast.Import):
            for a in node.names:
                parts = a.name.split(".")
                if parts[0] == "prsa_ctrl" and any(_private(x) for x in parts):
                    yield node.lineno, a.name


def test_no_test_imports_a_private_name_of_the_package():
    """Issue 33: the tests use public names (22 private imports in 12 files before)."""
    found = [f"{p.relative_to(TESTS.parent)}:{line}: {name}" for p in sorted(TESTS.rglob("*.py"))
             for line, name in _private_imports(p)
             if f"{p.relative_to(TESTS.parent)}: {name}" not in PRIVATE_IMPORTS_ALLOWED]
    assert found == []


def test_the_private_import_rule_sees_every_form(tmp_path):
    src = tmp_path / "t.py"
    src.write_text("from prsa_ctrl.x import a, _b\nimport prsa_ctrl._lazy\nfrom prsa_ctrl._lazy import f\n"
                   "import prsa_ctrl.tuning.loops as loops\nfrom other import _z\n"
                   "def g():\n    from prsa_ctrl.y import (c,\n        _d as e)\n    from prsa_ctrl import __version__\n")
    assert [n for _, n in _private_imports(src)] == ["prsa_ctrl.x._b", "prsa_ctrl._lazy", "prsa_ctrl._lazy.f",
                                                       "prsa_ctrl.y._d"]


def test_zero_order_hold_and_radau_tableau_written_once():
    for path in AREA:
        src = path.read_text(encoding="utf-8")
        uses_expm = any("expm" in names or module.endswith("expm") for _, module, names in _imports(path))
        # the home also writes the Monte Carlo's batched exponential (expm_stack)
        assert (uses_expm or "def expm_stack(" in src) == (path == ZOH_HOME), f"{path.relative_to(PKG)}: expm"
        assert ("sqrt(6" in src) == (path == RADAU_HOME), f"{path.relative_to(PKG)}: Radau IIA coefficients"


def test_identification_never_imports_matplotlib():
    for path in (PKG / "identification").glob("*.py"):
        mods = [module for _, module, _ in _imports(path)]
        assert not any(m.startswith("matplotlib") for m in mods), path.name
    code = ("import sys, prsa_ctrl.identification as I; [getattr(I, n) for n in I.__all__]; "
            "print(any(m.startswith('matplotlib') for m in sys.modules))")
    out = subprocess.run([sys.executable, "-W", "ignore", "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_fit_exceptions_live_in_errors_and_stay_importable():
    import prsa_ctrl.errors as errors
    import prsa_ctrl.identification as ident

    assert ident.FitError is errors.FitError
    assert ident.DataError is errors.DataError
    assert prsa_ctrl.FitError is errors.FitError
    assert issubclass(errors.DataError, ValueError)
    assert issubclass(errors.FitError, RuntimeError)
    assert {"FitError", "DataError"} <= set(errors.__all__)


def test_one_definition_of_the_record_length_limits():
    import prsa_ctrl.identification.data as data
    import prsa_ctrl.identification.logformat as logformat

    src = (PKG / "identification" / "logformat.py").read_text(encoding="utf-8")
    assert "MIN_SAMPLES =" not in src
    assert "MAX_SAMPLES =" not in src
    assert logformat.MIN_SAMPLES is data.MIN_SAMPLES
    assert logformat.MAX_SAMPLES is data.MAX_SAMPLES


def test_public_names_of_the_split_resolve():
    import prsa_ctrl.identification as ident
    import prsa_ctrl.plots as plots
    import prsa_ctrl.sim as sim

    for pkg in (sim, ident):
        for name in pkg.__all__:
            assert getattr(pkg, name) is not None, f"{pkg.__name__}.{name}"
    assert {"fit_figures", "figure_names"} <= set(plots.__all__)
    for name in ("simulate", "run", "SimRun", "SimSettings", "PiecewiseLinear", "energy_balance", "fit_plant",
                 "fit_frf", "FitResult", "FitError"):
        assert getattr(prsa_ctrl, name) is not None


def _part(module: str) -> str:
    """prsa_ctrl.tuning.loops -> tuning; prsa_ctrl.errors -> errors."""
    return module.split(".")[1] if module.count(".") else "__init__"


def _runtime_imports(path: Path):
    """(importing module, imported module, names) of every relative import outside TYPE_CHECKING."""
    tree = _tree(path)
    guarded = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.dump(node.test)
               for n in ast.walk(node)}
    mod = ".".join(path.relative_to(PKG.parent).with_suffix("").parts)
    pkg = mod if path.name == "__init__.py" else mod.rsplit(".", 1)[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level and id(node) not in guarded:
            base = pkg.split(".")[: len(pkg.split(".")) - (node.level - 1)]
            yield mod.removesuffix(".__init__"), ".".join(base + ([node.module] if node.module else [])), node


def test_imports_run_down_the_layers_only():
    up = []
    for path in AREA:
        if path.name == "__init__.py":
            continue  # the lazy export tables name their own modules
        for mod, target, node in _runtime_imports(path):
            a, b = _part(mod), _part(target)
            if a in RANK and b in RANK and RANK[b] > RANK[a]:
                up.append(f"{mod} -> {target}")
    assert not up, up


def test_no_import_circle_between_modules():
    graph: dict[str, set[str]] = {}
    for path in AREA:
        for mod, target, node in _runtime_imports(path):
            names = [a.name for a in node.names]
            targets = {f"{target}.{n}" for n in names} | {target}
            graph.setdefault(mod, set()).update(t for t in targets if t != mod)
    modules = set(graph)
    state: dict[str, int] = {}

    def visit(m, trail):
        state[m] = 1
        for t in graph.get(m, ()):
            t = t if t in modules else None
            if t is None or t.endswith("__init__"):
                continue
            if state.get(t) == 1:
                raise AssertionError(" -> ".join(trail + [m, t]))
            if state.get(t) is None:
                visit(t, trail + [m])
        state[m] = 2

    for m in sorted(modules):
        if state.get(m) is None and not m.endswith("__init__") and m != "prsa_ctrl":
            visit(m, [])


def test_every_exception_class_lives_in_errors():
    for path in AREA:
        if path.name == "errors.py":
            continue
        for node in ast.walk(_tree(path)):
            if isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
                bases = {getattr(b, "id", getattr(b, "attr", "")) for b in node.bases}
                assert not bases & {"Exception", "ValueError", "RuntimeError", "KeyboardInterrupt", "UserWarning"} \
                    or path.parent.name == "app", f"{path.relative_to(PKG)}: {node.name}"


def test_paths_computed_from_a_module_file_point_where_they_did_before_the_move():
    """Modules moved one folder down (issue 22): the checkout's built-in folders and the
    package root that no output may be written into are still found."""
    from prsa_ctrl.io.output import package_roots
    from prsa_ctrl.plant.plantfile import builtin_root

    assert builtin_root("no_such_package_for_this_test", "plants") == PKG.resolve().parent / "plants"
    assert str(PKG.resolve()) in package_roots()


# ---- folded from test_pipeline_split.py:
# Issue 22, one pipeline and one CLI layer: the split of the cascade module, one loader and one
# prsa-tune path for both kinds of scene, the CLI's shared layer, the layers of the import graph.

SRC_PKG = Path(__file__).resolve().parent.parent / "prsa_ctrl"


def _imports_resolved(path: Path):
    """(module imported, names) of every import statement of a module, relative ones resolved."""
    parts = path.relative_to(SRC_PKG.parent).with_suffix("").parts
    package = parts[:-1] if parts[-1] != "__init__" else parts[:-1]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = package[:len(package) - node.level + 1] if node.level else ()
            mod = ".".join([*base, *(node.module.split(".") if node.module else [])])
            yield mod, [a.name for a in node.names]
        elif isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, []


MY_MODULES = ["cli/common.py", "cli/tune.py", "cli/plot.py", "cli/inputs.py", "cli/report.py", "cli/montecarlo.py",
              "cli/fit.py", "cli/axis.py", "studies/move.py", "studies/movescene.py", "studies/scenefile.py",
              "studies/scene.py", "tuning/cascade.py", "io/export.py", "plots/move.py", "studies/accuracy.py",
              "identification/synthetic.py"]
#: Private names still crossing a module boundary: none (tests/test_structure.py holds the whole package to it).
KNOWN: set = set()


@pytest.mark.parametrize("rel", MY_MODULES)
def test_no_private_name_crosses_into_the_split_modules(rel):
    bad = [(mod, n) for mod, names in _imports_resolved(SRC_PKG / rel) for n in names
           if n.startswith("_") and not n.startswith("__") and mod.startswith("prsa_ctrl") and (mod, n) not in KNOWN]
    assert not bad, bad


def test_the_cascade_tuner_imports_nothing_above_it():
    """tuning/cascade.py imports no cli/, io/, plots/ or studies/ module (type-checking imports
    aside): the CLI, export, figures and the move scene's runs moved up to their layers."""
    for path in [SRC_PKG / "tuning" / "cascade.py"]:
        tree = ast.parse(path.read_text())
        guarded = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If)
                   and "TYPE_CHECKING" in ast.dump(node.test) for n in ast.walk(node)}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and id(node) not in guarded and node.level == 2:
                above = ("cli", "io", "plots", "app", "studies")
                assert (node.module or "").split(".")[0] not in above, (path.name, node.module)


def test_cli_modules_do_not_import_each_other_in_a_circle():
    edges = {}
    for path in (SRC_PKG / "cli").glob("*.py"):
        edges[path.stem] = {mod.split(".")[-1] for mod, _ in _imports_resolved(path) if mod.startswith("prsa_ctrl.cli.")}
    assert "tune" not in edges["common"]
    assert "tune" not in edges["plot"]
    assert "tune" not in edges["report"]
    assert not any("tune" in v for k, v in edges.items() if k != "tune"), edges


def test_one_loader_for_both_kinds_of_scene():
    from prsa_ctrl.studies.movescene import MoveScene
    from prsa_ctrl.studies.scene import Scene, load_scene, require_speed_scene

    move, speed = load_scene("paper-move"), load_scene("paper-load-step")
    assert isinstance(move, MoveScene)
    assert isinstance(speed, Scene)
    assert require_speed_scene(speed) is speed
    with pytest.raises(SceneError, match="a move scene"):
        require_speed_scene(move)


def test_prsa_tune_has_one_main_and_no_second_one_for_moves():
    import prsa_ctrl.cli.tune as tune
    import prsa_ctrl.tuning.cascade as cascade

    assert not hasattr(cascade, "main_move")
    assert not hasattr(tune, "main_move")
    assert tune.MOVE_FLAGS[:2] == ("plant", "scene")


@pytest.mark.parametrize("argv", [["prsa_ctrl.cli.tune", "--ms-max", "0.5"], ["prsa_ctrl.cli.plot", "--kp", "x"],
                                  ["prsa_ctrl.cli.fit", "--design", "chirp", "--out", "x.csv", "--duration", "-1"]])
def test_bad_flags_are_refused_before_casadi_is_imported(argv, tmp_path):
    code = ("import runpy, sys\nmod = sys.argv[1]; sys.argv = ['x', *sys.argv[2:]]\n"
            "try:\n    runpy.run_module(mod, run_name='__main__')\n"
            "except SystemExit as e:\n    print('exit', e.code, 'casadi' in sys.modules)\n")
    p = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert p.stdout.strip() == "exit 2 False", (p.stdout, p.stderr[-500:])


def _and_chain_asserts(root: Path) -> list[str]:
    """``file:line`` of every ``assert a and b`` under *root* (one claim per assert: the failing
    clause is the one pytest reports)."""
    out = []
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Assert) and isinstance(node.test, ast.BoolOp) and isinstance(node.test.op, ast.And):
                out.append(f"{path.relative_to(root.parent)}:{node.lineno}")
    return out


def test_every_assert_of_the_suite_makes_one_claim():
    # issue 33: an `and` chain hides which clause failed; write one assert per claim
    assert _and_chain_asserts(Path(__file__).parent) == []


def test_the_one_claim_rule_sees_an_and_chain(tmp_path):
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "test_x.py").write_text("def test_x():\n    assert 1 and (2 or 3)\n    assert 1\n")
    assert _and_chain_asserts(tmp_path / "tests") == ["tests/test_x.py:2"]
