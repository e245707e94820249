"""The pytest-xdist file order (tests/suite_order.py) and its cost table (scripts/suite-costs.py)."""

import importlib.util
import json
from pathlib import Path
from types import SimpleNamespace

from suite_order import COSTS_PATH, costliest_files_first, file_of, load_costs, wants_file_order

ROOT = Path(__file__).resolve().parent.parent


def _items(*ids):
    return [SimpleNamespace(nodeid=i) for i in ids]


def test_files_go_costliest_first_each_keeping_its_order():
    items = _items("a.py::t1", "b.py::t1", "a.py::t2", "c.py::t[x::y]", "b.py::t2", "a.py::t3")
    got = [i.nodeid for i in costliest_files_first(items, {"a.py": 1.0, "b.py": 5.0, "c.py": 3.0}, 0.1)]
    assert got == ["b.py::t1", "b.py::t2", "c.py::t[x::y]", "a.py::t1", "a.py::t2", "a.py::t3"]


def test_a_file_missing_from_the_table_costs_its_tests_times_the_mean():
    items = _items("old.py::t", "new.py::t1", "new.py::t2", "new.py::t3")
    # 3 tests x 1.0 s = 3.0 s > 2.0 s: the new file first; at 0.5 s per test (1.5 s) it comes after
    assert [i.nodeid for i in costliest_files_first(items, {"old.py": 2.0}, 1.0)][0] == "new.py::t1"
    assert [i.nodeid for i in costliest_files_first(items, {"old.py": 2.0}, 0.5)][0] == "old.py::t"


def test_ties_keep_the_collection_order_and_no_item_is_lost_or_doubled():
    items = _items("z.py::t", "y.py::t", "x.py::t1", "x.py::t2")
    got = costliest_files_first(items, {}, 1.0)
    assert [i.nodeid for i in got] == ["x.py::t1", "x.py::t2", "z.py::t", "y.py::t"]
    assert sorted(id(i) for i in got) == sorted(id(i) for i in items)


def test_file_of_splits_at_the_first_separator():
    assert file_of("tests/app/test_app.py::TestX::test_y[a::b]") == "tests/app/test_app.py"


def test_the_stored_table_names_existing_files_and_a_mean(tmp_path):
    files, per_test = load_costs()
    assert files, COSTS_PATH
    assert all((ROOT / f).is_file() for f in files), [f for f in files if not (ROOT / f).is_file()]
    assert per_test > 0
    (tmp_path / "bad.json").write_text("{not json")
    assert load_costs(tmp_path / "bad.json") == ({}, 1.0)  # unreadable: pytest-xdist's order by test count
    assert load_costs(tmp_path / "absent.json") == ({}, 1.0)


def test_the_order_is_asked_of_xdist_only_for_file_or_scope_queues():
    def config(dist, *args):
        return SimpleNamespace(option=SimpleNamespace(dist=dist), invocation_params=SimpleNamespace(args=args))

    assert wants_file_order(config("loadfile", "-n", "2", "--dist", "loadfile"))
    assert wants_file_order(config("loadscope"))
    assert not wants_file_order(config("no"))  # -n 0, or no pytest-xdist
    assert not wants_file_order(config("load"))
    assert not wants_file_order(config("loadfile", "--loadscope-reorder"))  # xdist's own order asked for by name
    assert not wants_file_order(SimpleNamespace(option=SimpleNamespace(), invocation_params=SimpleNamespace(args=())))


def test_the_costs_script_sums_a_junit_report_per_file(tmp_path):
    spec = importlib.util.spec_from_file_location("suite_costs", ROOT / "scripts" / "suite-costs.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    (tmp_path / "tests" / "app").mkdir(parents=True)
    (tmp_path / "tests" / "app" / "test_a.py").write_text("")
    (tmp_path / "tests" / "test_b.py").write_text("")
    junit = tmp_path / "j.xml"
    junit.write_text(
        '<testsuites><testsuite name="pytest">'
        '<testcase classname="tests.app.test_a" name="t1" time="1.2"/>'
        '<testcase classname="tests.app.test_a.TestK" name="t2" time="2.0"/>'
        '<testcase classname="tests.test_b" name="t" time="0.5"/>'
        '<testcase classname="tests.test_b" name="s" time="9.0"><skipped/></testcase>'
        '</testsuite></testsuites>')
    table = mod.costs(junit, tmp_path)
    assert table["files_s"] == {"tests/app/test_a.py": 3.2, "tests/test_b.py": 0.5}
    assert list(table["files_s"]) == ["tests/app/test_a.py", "tests/test_b.py"]  # costliest first
    assert table["tests"] == 3
    assert table["mean_per_test_s"] == round(3.7 / 3, 4)
    written = tmp_path / "costs.json"
    written.write_text(json.dumps(table))
    assert load_costs(written) == (table["files_s"], table["mean_per_test_s"])


def test_the_costs_script_reads_per_test_cpu_lines_too(tmp_path):
    spec = importlib.util.spec_from_file_location("suite_costs", ROOT / "scripts" / "suite-costs.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    lines = tmp_path / "cpu.jsonl"
    lines.write_text('{"id": "tests/a.py::t[x::y]", "cpu": 1.0}\n{"id": "tests/b.py::t", "cpu": 4.0}\n'
                     '{"id": "tests/a.py::u", "cpu": 0.5}\n\n')
    table = mod.costs(lines, tmp_path)
    assert table["files_s"] == {"tests/b.py": 4.0, "tests/a.py": 1.5}
    assert list(table["files_s"]) == ["tests/b.py", "tests/a.py"]
    assert table["mean_per_test_s"] == round(5.5 / 3, 4)
    assert mod.main([str(tmp_path / "absent.jsonl")]) == 2
