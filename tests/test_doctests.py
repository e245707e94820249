"""The docstring examples of every module of the installed package are tests too.

Run through the imported package (not the source files) so that the same examples are checked
whether prsa-ctrl is installed normally (as CI does) or in editable mode.
"""

import doctest
import importlib
import pkgutil

import pytest

import prsa_ctrl

MODULES = sorted(m.name for m in pkgutil.walk_packages(prsa_ctrl.__path__, "prsa_ctrl.")
                 if not m.name.startswith(("prsa_ctrl.plants", "prsa_ctrl.scenes", "prsa_ctrl.templates")))


def test_every_module_is_collected():
    assert {"prsa_ctrl.sim.simulate", "prsa_ctrl.tuning.tuner", "prsa_ctrl.plant.plantfile"} <= set(MODULES)
    # The examples are found (a silently empty run would pass every module).
    assert doctest.testmod(importlib.import_module("prsa_ctrl.sim.simulate"), verbose=False).attempted >= 5


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False)
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed in {name}"
