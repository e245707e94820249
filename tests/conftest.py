import os
import tempfile

# Hypothesis keeps its caches outside the working tree (set before it is imported).
os.environ.setdefault("HYPOTHESIS_STORAGE_DIRECTORY", os.path.join(tempfile.gettempdir(), "prsa-ctrl-hypothesis"))
# One OpenBLAS thread: the suite runs one pytest-xdist worker per core, and the toolkit's
# matrices are small (a ZOH's expm of 5..12 states), where OpenBLAS's extra threads only spin:
# the two-mass FRF fit of tests/app/test_session.py took 7.0 s of CPU with the default threads
# and 0.83 s with one, same result. Read when scipy's OpenBLAS loads (after this line; numpy's
# is loaded by pytest's plugins before it) and by every process a test starts (notebook kernels,
# the app server, Sphinx, the command-line runs).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import matplotlib
import pytest
from hypothesis import settings
from shared_runs import share_tunings, tuned_once
from suite_order import costliest_files_first, load_costs, wants_file_order

# Deterministic property tests that leave no example database in the working directory.
settings.register_profile("prsa", database=None, derandomize=True, deadline=None)
settings.load_profile("prsa")

matplotlib.use("Agg")
os.environ.setdefault("PRSA_FAST", "1")


def pytest_configure(config):
    """Under ``-n N --dist loadfile`` the workers' collection order is the queue's
    (``tests/suite_order.py``: costliest file first), so pytest-xdist's reordering by number of
    tests is turned off, unless ``--loadscope-reorder`` was typed."""
    if wants_file_order(config):
        config.option.loadscopereorder = False


def pytest_collection_modifyitems(config, items):
    """On a pytest-xdist worker, the test files in decreasing measured cost, each file's order
    kept (``tests/suite_order.py``); a run in one process keeps pytest's order."""
    if hasattr(config, "workerinput"):
        items[:] = costliest_files_first(items, *load_costs())


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


@pytest.fixture(scope="session")
def paper_report():
    """``tune_actuator`` on the paper plant and the default scene (one full tune and verification),
    made once per session and shared by the tests that assert on it (results are frozen); the
    same run as ``shared_tuning``'s of the default plant and scene."""
    from prsa_ctrl import load_plant, load_scene
    from prsa_ctrl.studies.autotune import tune_actuator

    return tuned_once(tune_actuator, load_plant(), load_scene(), workers=None)


@pytest.fixture(scope="session")
def default_cli_run(tmp_path_factory):
    """One ``prsa-tune --load-step 500:1500`` run (in-process, the paper plant and default scene: the
    README's command) with every output: a JSON report, plots and an export whose file name is 245
    characters long (NAME_MAX is 255).
    Its tuning is ``shared_tuning``'s. Made once per session and shared by the tests that assert
    on its text and files: ``code``,
    ``out`` and ``err`` (the printed text), ``folder``, ``json``, ``plots``, ``export`` (paths)."""
    import contextlib
    import io
    from types import SimpleNamespace

    from prsa_ctrl.cli.tune import main

    folder = tmp_path_factory.mktemp("default-run")
    run = SimpleNamespace(folder=folder, json=folder / "j.json", plots=folder / "pl",
                          export=folder / ("x" * 245 + ".toml"))
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), pytest.MonkeyPatch.context() as mp:
        share_tunings(mp)
        run.code = main(["--load-step", "500:1500", "--json", str(run.json), "--plots", str(run.plots),
                         "--export", str(run.export)])
    run.out, run.err = out.getvalue(), err.getvalue()
    return run


@pytest.fixture(scope="session")
def emps_fit(tmp_path_factory):
    """``prsa-fit examples/emps/DATA_EMPS.mat --log-format examples/emps/log.toml --out F.toml --json
    F.json`` (the README's command; in-process), made once per session and shared by the tests
    that assert on its outputs: ``code``, ``out``, ``err`` (printed text), ``toml`` and ``json``
    (paths). Tests that write files next to the plant copy it into their own folder."""
    import contextlib
    import io
    from pathlib import Path
    from types import SimpleNamespace

    from prsa_ctrl.cli.fit import main

    example = Path(__file__).resolve().parent.parent / "examples" / "emps"
    if not (example / "DATA_EMPS.mat").is_file():
        pytest.skip("examples/emps/DATA_EMPS.mat not in this checkout")
    folder = tmp_path_factory.mktemp("emps-fit")
    run = SimpleNamespace(folder=folder, toml=folder / "F.toml", json=folder / "F.json")
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        run.code = main([str(example / "DATA_EMPS.mat"), "--log-format", str(example / "log.toml"),
                         "--out", str(run.toml), "--json", str(run.json)])
    run.out, run.err = out.getvalue(), err.getvalue()
    return run


@pytest.fixture
def shared_tuning(monkeypatch):
    """``prsa_ctrl.studies.autotune.tune_actuator`` and ``prsa_ctrl.studies.move.tune_move``
    computed once per session for each value of their arguments (plant, scene, workers: compared
    by their pickled bytes, so an option that changes the plant or the scene tunes afresh;
    ``paper_report`` is the same run), for the tests that only read what a command prints and
    writes from the tuning (exports, reports): each run after the first gets the first run's
    result (frozen designs and reports) with its warnings and progress lines again, the rest of
    the command runs as it is. Not for tests of the tuner's paths, of its determinism, of the
    solvers' printed lines (``--verbose``) or of patched internals. Returns the list of calls, ``(key, hit)``."""
    calls: list = []
    share_tunings(monkeypatch, calls)
    return calls
