import os
import tempfile

# Hypothesis keeps its caches outside the working tree (set before it is imported).
os.environ.setdefault("HYPOTHESIS_STORAGE_DIRECTORY", os.path.join(tempfile.gettempdir(), "prsa-ctrl-hypothesis"))

import matplotlib
import pytest
from hypothesis import settings

# Deterministic property tests that leave no example database in the working directory.
settings.register_profile("prsa", database=None, derandomize=True, deadline=None)
settings.load_profile("prsa")

matplotlib.use("Agg")
os.environ.setdefault("PRSA_FAST", "1")


@pytest.fixture(scope="session")
def paper_plant():
    """The built-in paper plant, loaded once (its geometry note silenced)."""
    import warnings

    from prsa_ctrl import load_plant

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_plant("paper-iprsm")


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    import matplotlib.pyplot as plt

    plt.close("all")


@pytest.fixture
def stand_in(monkeypatch):
    """The tuner replaced by a counting stand-in that fails (exit 3 if a CLI reaches it): a test
    of input checking asserts ``not stand_in``, i.e. the refusal came before any tuning."""
    import prsa_ctrl.studies.autotune as autotune
    from prsa_ctrl import SimulationError

    calls = []

    def fake(*a, **k):
        calls.append(a)
        raise SimulationError("stand-in for the tuner at t = 0 s; remedy: none")

    monkeypatch.setattr(autotune, "tune_actuator", fake)
    monkeypatch.setattr(autotune, "actuator_loops", fake)
    return calls
