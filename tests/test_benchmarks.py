"""The benchmarks cannot rot (issue 35: ``python benchmarks/bench.py`` crashed in its robust section,
"cannot import name 'scenarios' from 'prsa_ctrl.tuning.robust'", and nothing ran it).

Each runs in ``--fast`` mode (every section at tiny sizes) in a subprocess, from the checkout,
with its output in a temporary folder; the test asserts only that it completes and writes its
JSON with every section: no timing is asserted (speed is measured by the benchmarks themselves,
not by tests). The subprocess timeout only keeps a broken run from hanging the suite.
"""

import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
BENCH = ROOT / "benchmarks"


def _env():
    # the package the tests import (the installed one under scripts/fresh-test.sh), as the README's
    # command runs the benchmarks from a checkout with prsa-ctrl installed
    return {**os.environ, "MPLBACKEND": "Agg", "PYTHONWARNINGS": "ignore"}


def _run(script, tmp_path, *args):
    return subprocess.run([sys.executable, str(BENCH / script), "--fast", "--out", str(tmp_path / "out"), *args],
                          cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=900)


def test_bench_fast_runs_every_section_and_writes_its_json(tmp_path):
    p = _run("bench.py", tmp_path)
    assert p.returncode == 0, (p.returncode, p.stdout[-3000:], p.stderr[-3000:])
    assert "Traceback" not in p.stderr, p.stderr[-3000:]
    data = json.loads((tmp_path / "out" / "bench.json").read_text(encoding="utf-8"))
    assert data["fast"] is True
    sections = {"work_precision", "fidelity_ladder", "tuning", "monte_carlo", "batched_monte_carlo", "robust_tuning",
                "fit", "axis_fit", "cold_cli", "targets"}
    assert sections <= set(data), sorted(sections - set(data))
    assert (tmp_path / "out" / "work_precision.png").stat().st_size > 0
    # the robust section ran its scenario models (the import that crashed)
    assert data["robust_tuning"]["scenarios"] >= 5
    # the batched Monte Carlo ran both paths on the same samples and quoted its measured error
    bm = data["batched_monte_carlo"]
    assert bm["n"] == 16
    assert len(bm["median_s"]) == 3
    assert bm["batched_identical_across_backends"] is True
    assert bm["integration"]["path"] == "batched"
    assert bm["integration"]["relative"] is not None


def test_bench_refuses_a_bad_out_before_any_work(tmp_path):
    (tmp_path / "file").write_text("x")
    p = subprocess.run([sys.executable, str(BENCH / "bench.py"), "--fast", "--out", str(tmp_path / "file")],
                       cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=300)
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 2, p.stderr
    assert len(lines) == 1, p.stderr
    assert lines[0].startswith("bench: error: "), p.stderr
    assert (tmp_path / "file").read_text() == "x"


def _need_browser():
    """One-line skip without Playwright or Chromium (a failure under CI=true, where both are
    installed), as tests/app/test_app_browser.py."""
    missing = []
    if importlib.util.find_spec("playwright") is None:
        missing.append("playwright (pip install '.[app,test]')")
    if not (shutil.which("chromium") or shutil.which("chromium-browser")):
        missing.append("chromium (apt-get install chromium)")
    if missing:
        line = "app benchmark skipped: missing " + " and ".join(missing)
        if os.environ.get("CI") == "true":
            pytest.fail(line.replace("skipped", "cannot run under CI=true"), pytrace=False)
        pytest.skip(line)


def test_app_bench_fast_completes_and_writes_its_json(tmp_path):
    _need_browser()
    p = _run("app_bench.py", tmp_path)
    assert p.returncode == 0, (p.returncode, p.stdout[-3000:], p.stderr[-3000:])
    data = json.loads((tmp_path / "out" / "app_bench.json").read_text(encoding="utf-8"))
    assert data["fast"] is True
    assert data["repeats"] == 1
    assert set(data["median_s"]) == {"start_s", "slider_s", "drag_s", "generic_open_s", "generic_bound_s"}
    assert all(len(v) >= 1 for v in data["runs_s"].values())


@pytest.mark.slow
def test_bench_acceptance_fast_prints_every_target_and_writes_its_json(tmp_path):
    """``bench.py --acceptance`` (the integrator's idle-acceptance command) at tiny sizes: the five
    targets of issue 35 in one table with their spread and verdict, and the JSON; no timing is
    asserted (slow: it runs the yield-driven design and the cold CLI as a user does)."""
    p = _run("bench.py", tmp_path, "--acceptance", "--repeats", "1")
    assert p.returncode == 0, (p.returncode, p.stdout[-3000:], p.stderr[-3000:])
    data = json.loads((tmp_path / "out" / "acceptance.json").read_text(encoding="utf-8"))
    rows = data["acceptance"]["rows"]
    assert set(rows) == {"mc_paper", "mc_robust", "design_to_spec", "work_precision", "cold_ratio", "tuner"}
    for key, r in rows.items():
        # (a value that could not be measured, e.g. no tiny run within 1e-6 rad/s, is null and fails)
        assert (r["median"] is None and r["met"] is False) or r["min"] <= r["median"] <= r["max"], (key, r)
        assert isinstance(r["met"], bool)
        assert f"{key} " in p.stdout
    assert rows["mc_robust"]["ms_per_sample"] is True
    assert rows["mc_paper"]["path"] == "batched"
    assert rows["design_to_spec"]["results"][0]["samples"] == 8


def test_calibration_bench_says_when_the_foreign_axis_data_are_absent(tmp_path):
    """A clean clone (CI) has no ../shared/data: the calibration benchmark says where it looked,
    writes {"skipped": ...} and exits 0; a bad --out is refused before any work."""
    empty = tmp_path / "nothing"
    empty.mkdir()
    p = _run("calibration_bench.py", tmp_path, "--data", str(empty))
    assert p.returncode == 0, (p.stdout[-2000:], p.stderr[-2000:])
    assert "skipped: foreign-axis data not found in " + str(empty) in p.stdout
    assert "--data DIR" in p.stdout
    data = json.loads((tmp_path / "out" / "calibration.json").read_text(encoding="utf-8"))
    assert data["fast"] is True
    assert str(empty) in data["skipped"]
    (tmp_path / "file").write_text("x")
    p = subprocess.run([sys.executable, str(BENCH / "calibration_bench.py"), "--fast", "--out", str(tmp_path / "file")],
                       cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=300)
    assert p.returncode == 2
    assert p.stderr.startswith("calibration_bench: error: --out ")
    assert (tmp_path / "file").read_text() == "x"


@pytest.mark.slow
def test_calibration_bench_fast_times_the_foreign_axis_fits(tmp_path):
    """With the foreign-axis data beside the checkout (or $PRSA_FOREIGN_AXIS): --fast runs the FRF
    fit and a tiny rigid log fit once each and writes their times (no time asserted)."""
    spec = importlib.util.spec_from_file_location("calibration_bench", BENCH / "calibration_bench.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    data, where = mod.find_data(None)
    if data is None:
        pytest.skip(where)
    p = _run("calibration_bench.py", tmp_path)
    assert p.returncode == 0, (p.stdout[-2000:], p.stderr[-2000:])
    assert "Traceback" not in p.stderr, (p.stdout[-2000:], p.stderr[-2000:])
    res = json.loads((tmp_path / "out" / "calibration.json").read_text(encoding="utf-8"))
    assert set(res) >= {"frf", "rigid_logs"}
    assert res["frf"]["runs"][0]["exit"] == 0
    assert all(r["wall_s"] > 0 and r["cpu_s"] >= 0 for s in ("frf", "rigid_logs") for r in res[s]["runs"])
