"""Issue 22 in the simulator, identification and sampled-loop area: modules under 1,000 lines,
no private name crossing a module boundary, the zero-order hold and the Radau IIA tableau
written once, figures apart from the fits, the fit exceptions in prsa_ctrl.errors."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

import prsa_ctrl

PKG = Path(prsa_ctrl.__file__).parent
AREA = sorted([*(PKG / "sim").glob("*.py"), *(PKG / "identification").glob("*.py"), PKG / "drive" / "sampled.py",
               PKG / "drive" / "estimator.py", PKG / "drive" / "filters.py", PKG / "plots" / "fit.py"])
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


def test_zero_order_hold_and_radau_tableau_written_once():
    for path in AREA:
        src = path.read_text(encoding="utf-8")
        uses_expm = any("expm" in names or module.endswith("expm") for _, module, names in _imports(path))
        assert uses_expm == (path == ZOH_HOME), f"{path.relative_to(PKG)}: expm"
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

    assert ident.FitError is errors.FitError and ident.DataError is errors.DataError
    assert prsa_ctrl.FitError is errors.FitError
    assert issubclass(errors.DataError, ValueError) and issubclass(errors.FitError, RuntimeError)
    assert {"FitError", "DataError"} <= set(errors.__all__)


def test_one_definition_of_the_record_length_limits():
    import prsa_ctrl.identification.data as data
    import prsa_ctrl.identification.logformat as logformat

    src = (PKG / "identification" / "logformat.py").read_text(encoding="utf-8")
    assert "MIN_SAMPLES =" not in src and "MAX_SAMPLES =" not in src
    assert logformat.MIN_SAMPLES is data.MIN_SAMPLES and logformat.MAX_SAMPLES is data.MAX_SAMPLES


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
