"""Write tests/suite_costs.json, the measured cost of every test file, from a run's per-test times.

The table orders the test files for pytest-xdist's workers, costliest first
(tests/suite_order.py). Refresh it when files were added or their cost moved much:

    bash scripts/fresh-test.sh --junitxml=/tmp/suite.xml      # or: pytest -q -n 2 --dist loadfile --junitxml=...
    python scripts/suite-costs.py /tmp/suite.xml > tests/suite_costs.json

Each file's cost is the sum of its tests' seconds, rounded to 0.1 s; ``mean_per_test_s`` (the whole
run's seconds per test) estimates a file the table does not know yet. The input is either pytest's
JUnit report (each test's ``time``: wall seconds of the call with its setup and teardown, so a
module's shared run counts in the file that makes it; test files found from the class names,
``tests.app.test_app`` or ``tests.app.test_app.TestClass``, relative to the current folder: run it
from the checkout's root), or JSON lines ``{"id": NODE_ID, "cpu": SECONDS}`` (a ``.jsonl`` file: each
test's CPU time, its process and the children it waited for, as a per-test CPU plugin writes them).
Wall seconds are right on an idle machine; on a loaded one they rank the files by how long they
waited, and CPU seconds rank them better. The order only needs the files' ranks, not exact seconds.
"""

from __future__ import annotations

import json
import sys
import xml.etree.ElementTree as ET
from pathlib import Path


def test_file(classname: str, root: Path) -> str | None:
    """The test file of a JUnit class name: the longest dotted prefix that is a ``.py`` file under
    ``root`` (``tests.app.test_app.TestX`` -> ``tests/app/test_app.py``)."""
    parts = classname.split(".")
    for n in range(len(parts), 0, -1):
        rel = "/".join(parts[:n]) + ".py"
        if (root / rel).is_file():
            return rel
    return None


def _junit_times(junit: Path, root: Path):
    """``(test file, seconds)`` of every test case of a JUnit report that ran (skipped ones left out)."""
    for case in ET.parse(junit).getroot().iter("testcase"):
        if case.find("skipped") is not None:
            continue
        f = case.get("file") or test_file(case.get("classname", ""), root)
        if f is not None:
            yield f, float(case.get("time", "0") or 0.0)


def _jsonl_times(path: Path):
    """``(test file, seconds)`` of every line ``{"id": NODE_ID, "cpu": SECONDS}``."""
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.strip():
            row = json.loads(line)
            yield row["id"].split("::", 1)[0], float(row["cpu"])


def costs(report: Path, root: Path) -> dict:
    """The cost table of a JUnit XML report, or of JSON lines of per-test CPU seconds (a ``.jsonl``
    file): ``files_s`` (costliest first), ``mean_per_test_s``, ``tests``, ``source``."""
    files: dict[str, float] = {}
    n = 0
    total = 0.0
    jsonl = report.suffix == ".jsonl"
    for f, t in (_jsonl_times(report) if jsonl else _junit_times(report, root)):
        files[f] = files.get(f, 0.0) + t
        total += t
        n += 1
    if not n:
        raise SystemExit(f"suite-costs: error: {report}: no test with a test file under {root}; expected a "
                         "pytest --junitxml report run from this checkout, or JSON lines of per-test CPU seconds")
    ranked = dict(sorted(((f, round(s, 1)) for f, s in files.items()), key=lambda kv: (-kv[1], kv[0])))
    kind = "per-test CPU seconds (JSON lines)" if jsonl else "a pytest --junitxml report (wall seconds)"
    return {"source": f"scripts/suite-costs.py from {kind}, summed per test file",
            "tests": n, "mean_per_test_s": round(total / n, 4), "files_s": ranked}


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: python scripts/suite-costs.py REPORT.xml|TIMES.jsonl > tests/suite_costs.json", file=sys.stderr)
        return 2
    try:
        table = costs(Path(argv[0]), Path.cwd())
    except (OSError, ET.ParseError, ValueError, KeyError, TypeError, AttributeError) as e:
        print(f"suite-costs: error: {argv[0]}: {e}; expected a pytest --junitxml report or JSON lines "
              '{"id": NODE_ID, "cpu": SECONDS}', file=sys.stderr)
        return 2
    json.dump(table, sys.stdout, indent=1)
    sys.stdout.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
