"""Issue 22, one pipeline and one CLI layer: the split of the cascade module, one loader and one
prsa-tune path for both kinds of scene, the CLI's shared layer, the layers of the import graph."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from prsa_ctrl.errors import SceneError

PKG = Path(__file__).resolve().parent.parent / "prsa_ctrl"


def _imports(path: Path):
    """(module imported, names) of every import statement of a module, relative ones resolved."""
    parts = path.relative_to(PKG.parent).with_suffix("").parts
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
    bad = [(mod, n) for mod, names in _imports(PKG / rel) for n in names
           if n.startswith("_") and not n.startswith("__") and mod.startswith("prsa_ctrl") and (mod, n) not in KNOWN]
    assert not bad, bad


def test_the_cascade_tuner_imports_nothing_above_it():
    """tuning/cascade.py imports no cli/, io/, plots/ or studies/ module (type-checking imports
    aside): the CLI, export, figures and the move scene's runs moved up to their layers."""
    for path in [PKG / "tuning" / "cascade.py"]:
        tree = ast.parse(path.read_text())
        guarded = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If)
                   and "TYPE_CHECKING" in ast.dump(node.test) for n in ast.walk(node)}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and id(node) not in guarded and node.level == 2:
                above = ("cli", "io", "plots", "app", "studies")
                assert (node.module or "").split(".")[0] not in above, (path.name, node.module)


def test_cli_modules_do_not_import_each_other_in_a_circle():
    edges = {}
    for path in (PKG / "cli").glob("*.py"):
        edges[path.stem] = {mod.split(".")[-1] for mod, _ in _imports(path) if mod.startswith("prsa_ctrl.cli.")}
    assert "tune" not in edges["common"] and "tune" not in edges["plot"] and "tune" not in edges["report"]
    assert not any("tune" in v for k, v in edges.items() if k != "tune"), edges


def test_one_loader_for_both_kinds_of_scene():
    from prsa_ctrl.studies.movescene import MoveScene
    from prsa_ctrl.studies.scene import Scene, load_scene, require_speed_scene
    from prsa_ctrl.studies.scenefile import is_move_scene

    move, speed = load_scene("paper-move"), load_scene("paper-load-step")
    assert isinstance(move, MoveScene) and isinstance(speed, Scene)
    assert is_move_scene("paper-move") and not is_move_scene("paper-load-step") and not is_move_scene("nope")
    assert require_speed_scene(speed) is speed
    with pytest.raises(SceneError, match="a move scene"):
        require_speed_scene(move)


def test_prsa_tune_has_one_main_and_no_second_one_for_moves():
    import prsa_ctrl.cli.tune as tune
    import prsa_ctrl.tuning.cascade as cascade

    assert not hasattr(cascade, "main_move") and not hasattr(tune, "main_move")
    assert tune.MOVE_FLAGS[:2] == ("plant", "scene")


@pytest.mark.parametrize("argv", [["prsa_ctrl.cli.tune", "--ms-max", "0.5"], ["prsa_ctrl.cli.plot", "--kp", "x"],
                                  ["prsa_ctrl.cli.fit", "--design", "chirp", "--out", "x.csv", "--duration", "-1"]])
def test_bad_flags_are_refused_before_casadi_is_imported(argv, tmp_path):
    code = ("import runpy, sys\nmod = sys.argv[1]; sys.argv = ['x', *sys.argv[2:]]\n"
            "try:\n    runpy.run_module(mod, run_name='__main__')\n"
            "except SystemExit as e:\n    print('exit', e.code, 'casadi' in sys.modules)\n")
    p = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert p.stdout.strip() == "exit 2 False", (p.stdout, p.stderr[-500:])
