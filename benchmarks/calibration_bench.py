"""Calibration benchmark (not a test): run time of ``prsa-fit`` on the foreign feed axis.

``python benchmarks/calibration_bench.py [--data DIR] [--out DIR] [--repeats N] [--fast] [--skip ...]``
times, as a user runs them (``prsa-fit`` in a child process, imports included), the fits issue
32's acceptance names on the foreign ball-screw feed axis (``../shared/data/foreign-axis/``, its
README: three logs, the command logged as computed, a measured frequency response):

- **frf**: ``prsa-fit --frf bode.csv --plant feed-axis.toml --fidelity compliant`` (the
  frequency-response fit, two-mass);
- **rigid_logs**: ``prsa-fit multisine.csv loadsteps.csv staircase.csv --plant feed-axis.toml
  --command-logged computed`` (the three-log time-domain fit, delay searched, validated and
  cross-validated);
- **compliant_logs**: the same with ``--fidelity compliant --frf bode.csv --delay-samples 1``
  (the two-mass time-domain fit started from the response's two-mass fit, the README's delay).

Each is run ``repeats`` times (default 3); the JSON (``calibration.json``) holds every run's
wall time, CPU time of the child (user + system), exit code, the load average before and after
(``os.getloadavg``: the machine's other work), the one-line outcome and, from the fit's JSON
report, the reflected inertia, the command delay and the axial mode; the medians and
min..max are printed. The acceptance's figure is 60 s per fit on the 2-core machine; nothing is
asserted here.

The data are found by ``--data DIR``, else ``$PRSA_FOREIGN_AXIS``, else ``../shared/data/foreign-axis``
beside the checkout (or beside its parent). Without them the benchmark says so, writes
``{"skipped": reason}`` and exits 0: a clean clone (CI) does not hold them.

``--fast`` (CI, tests/test_benchmarks.py): one run of the FRF fit and of a rigid fit of the
multisine's first 0.25 s at ``--delay-samples 1`` without validation figures; its figures mean
nothing (``calibration.json["fast"]`` is true).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FILES = ("multisine.csv", "loadsteps.csv", "staircase.csv", "bode.csv", "feed-axis.toml")
SECTIONS = ("frf", "rigid_logs", "compliant_logs")
#: The child: ``prsa-fit`` of the package the benchmark imports (the checkout's or the installed one).
CHILD = "import sys; from prsa_ctrl.cli.fit import main; sys.exit(main(sys.argv[1:]))"


def find_data(given: str | None) -> tuple[Path | None, str]:
    """The foreign-axis folder and how it was found, or None and where it was looked for."""
    env = os.environ.get("PRSA_FOREIGN_AXIS")
    candidates = [Path(given)] if given else ([Path(env)] if env else
                                              [ROOT.parent / "shared" / "data" / "foreign-axis",
                                               ROOT.parent.parent / "shared" / "data" / "foreign-axis"])
    for d in candidates:
        if all((d / f).is_file() for f in FILES):
            return d, str(d)
    how = "--data" if given else ("$PRSA_FOREIGN_AXIS" if env else "the default places")
    return None, (f"foreign-axis data not found in {', '.join(str(c) for c in candidates)} ({how}; expected "
                  f"{', '.join(FILES)}): give --data DIR or set PRSA_FOREIGN_AXIS")


def _cases(d: Path, fast: bool, work: Path) -> dict[str, list[str]]:
    plant = ["--plant", str(d / "feed-axis.toml")]
    logs = [str(d / f) for f in FILES[:3]]
    if fast:
        head = work / "multisine-head.csv"
        lines = (d / "multisine.csv").read_text(encoding="utf-8").splitlines()
        head.write_text("\n".join(lines[:2001]) + "\n", encoding="utf-8")  # header + 0.25 s at 8 kHz
        return {"frf": ["--frf", str(d / "bode.csv"), *plant, "--fidelity", "compliant"],
                "rigid_logs": [str(head), *plant, "--command-logged", "computed", "--delay-samples", "1",
                               "--no-cross-validation"]}
    return {"frf": ["--frf", str(d / "bode.csv"), *plant, "--fidelity", "compliant"],
            "rigid_logs": [*logs, *plant, "--command-logged", "computed"],
            "compliant_logs": [*logs, *plant, "--command-logged", "computed", "--fidelity", "compliant",
                               "--frf", str(d / "bode.csv"), "--delay-samples", "1"]}


def _summary(report: Path) -> dict:
    if not report.is_file():
        return {}
    r = json.loads(report.read_text(encoding="utf-8"))
    out = {}
    j = r.get("reflected_inertia_kg_m2")
    if isinstance(j, dict):
        out["reflected_inertia_kg_m2"] = {"value": j.get("value"), "ci95": j.get("ci95")}
    sv = r.get("solver") or {}
    cd = sv.get("command_delay") or {}
    if "shift_samples" in cd:
        out["command_shift_samples"] = cd["shift_samples"]
    for k in ("frf_axial_mode_hz", "axial_mode_hz"):
        if isinstance(r.get(k), dict):
            out[k] = r[k].get("value")
    for k in ("status", "iterations", "attempts", "stall"):
        if k in sv:
            out[f"solver_{k}"] = sv[k]
    return out


def run_case(args: list[str], work: Path, tag: str) -> dict:
    """One ``prsa-fit`` run in a child process: wall and child CPU time, exit code, outcome."""
    out, rep = work / f"{tag}.toml", work / f"{tag}.json"
    for p in (out, rep):
        p.unlink(missing_ok=True)
    load0 = os.getloadavg()
    c0 = os.times()
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-c", CHILD, *args, "--out", str(out), "--json", str(rep)],
                       capture_output=True, text=True, env={**os.environ, "MPLBACKEND": "Agg"})
    wall = time.perf_counter() - t0
    c1 = os.times()
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()] or [ln for ln in p.stdout.splitlines() if ln.strip()]
    return {"exit": p.returncode, "wall_s": wall,
            "cpu_s": (c1.children_user - c0.children_user) + (c1.children_system - c0.children_system),
            "load_before": list(load0), "load_after": list(os.getloadavg()),
            "plant_written": out.is_file(), "last_line": lines[-1][:400] if lines else "", **_summary(rep)}


def _spread(values) -> dict:
    v = [float(x) for x in values]
    return {"median": statistics.median(v), "min": min(v), "max": max(v)} if v else {}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="calibration_bench", description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None, help="the foreign-axis folder (default $PRSA_FOREIGN_AXIS, "
                    "else ../shared/data/foreign-axis beside the checkout)")
    ap.add_argument("--out", default="bench-results", help="folder for calibration.json (created if missing)")
    ap.add_argument("--repeats", type=int, default=None, help="runs per fit, median reported (default 3; 1 with --fast)")
    ap.add_argument("--fast", action="store_true", help="tiny sizes for CI (the figures mean nothing)")
    ap.add_argument("--skip", nargs="*", default=[], choices=SECTIONS)
    a = ap.parse_args(argv)
    out_dir = Path(a.out)
    if out_dir.exists() and not out_dir.is_dir():
        print(f"calibration_bench: error: --out {a.out}: not a folder; expected a folder for calibration.json",
              file=sys.stderr)
        return 2
    repeats = a.repeats if a.repeats is not None else (1 if a.fast else 3)
    if repeats < 1:
        print(f"calibration_bench: error: --repeats {repeats}: expected at least 1", file=sys.stderr)
        return 2
    out_dir.mkdir(parents=True, exist_ok=True)
    data, where = find_data(a.data)
    result: dict = {"fast": a.fast, "repeats": repeats, "cpu_count": os.cpu_count()}
    if data is None:
        print(f"calibration_bench: skipped: {where}")
        result["skipped"] = where
        (out_dir / "calibration.json").write_text(json.dumps(result, indent=2), encoding="utf-8")
        return 0
    result["data"] = where
    if a.fast:
        print("--fast: tiny sizes; the figures below mean nothing")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for name, args in _cases(data, a.fast, work).items():
            if name in a.skip:
                continue
            runs = [run_case(args, work, name) for _ in range(repeats)]
            result[name] = {"command": ["prsa-fit", *args], "runs": runs,
                            "wall_s": _spread(r["wall_s"] for r in runs), "cpu_s": _spread(r["cpu_s"] for r in runs)}
            w, c = result[name]["wall_s"], result[name]["cpu_s"]
            print(f"{name:15s} wall {w['median']:7.1f} s ({w['min']:.1f}..{w['max']:.1f})  CPU {c['median']:7.1f} s  "
                  f"exit {[r['exit'] for r in runs]}  load {runs[-1]['load_after'][0]:.1f}")
    (out_dir / "calibration.json").write_text(json.dumps(result, indent=2, default=str), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
