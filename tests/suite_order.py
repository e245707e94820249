"""The order in which pytest-xdist's workers get the test files: the costliest first.

Under the README's command (``pytest -n N --dist loadfile``) a test file runs whole on one
worker, and the files are handed out from a queue as workers run low. pytest-xdist's own queue
puts the files with the most tests first; a file with few but costly tests (the documentation
build, the notebooks, the benchmarks, the browser tests) came late, and one worker ran it alone
while the others had finished. Queued costliest first (the "longest processing time first" rule),
the last files handed out are the cheap ones and the workers finish together.

The cost of a file is read from ``tests/suite_costs.json`` (seconds per file, measured:
``scripts/suite-costs.py`` writes it from a run's JUnit XML, see its docstring); a file missing
from the table (a new one) is estimated as its number of tests times the table's mean cost per
test. The order inside a file is kept. Used by ``tests/conftest.py`` on pytest-xdist workers
only: a run in one process (``-n 0``, or without pytest-xdist) keeps pytest's own order.
"""

from __future__ import annotations

import json
from pathlib import Path

#: The measured cost table (``scripts/suite-costs.py`` writes it).
COSTS_PATH = Path(__file__).resolve().parent / "suite_costs.json"


def load_costs(path: Path = COSTS_PATH) -> tuple[dict[str, float], float]:
    """``(seconds by test file path relative to the rootdir, mean seconds per test)`` from the cost
    table; ``({}, 1.0)`` when the table is absent or unreadable (every file then estimated by its
    number of tests: pytest-xdist's own order)."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        files = {str(k): float(v) for k, v in doc["files_s"].items()}
        per_test = float(doc["mean_per_test_s"])
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}, 1.0
    return files, per_test


def file_of(nodeid: str) -> str:
    """The test file of a node id (``tests/app/test_app.py::test_x[a::b]`` -> ``tests/app/test_app.py``):
    the scope pytest-xdist's ``--dist loadfile`` groups by."""
    return nodeid.split("::", 1)[0]


def costliest_files_first(items: list, costs: dict[str, float], per_test_s: float) -> list:
    """``items`` grouped by file, the files in decreasing cost (ties: the order in which they
    were collected), the order inside each file kept. A file missing from ``costs`` costs its
    number of tests times ``per_test_s``."""
    groups: dict[str, list] = {}
    for item in items:
        groups.setdefault(file_of(item.nodeid), []).append(item)
    rank = {f: i for i, f in enumerate(groups)}

    def cost(f):
        return costs.get(f, len(groups[f]) * per_test_s)

    order = sorted(groups, key=lambda f: (-cost(f), rank[f]))
    return [item for f in order for item in groups[f]]


def wants_file_order(config) -> bool:
    """Whether this run hands whole files (or classes) to pytest-xdist workers from a queue
    (``--dist loadfile`` or ``loadscope``) and did not ask for pytest-xdist's own queue order by
    name (``--loadscope-reorder`` typed)."""
    dist = getattr(config.option, "dist", "no")
    typed = "--loadscope-reorder" in config.invocation_params.args
    return dist in ("loadfile", "loadscope") and not typed
