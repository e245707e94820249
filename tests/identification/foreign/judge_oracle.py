"""The judge's acceptance oracle for prsa-fit on the foreign generators (issue 32, point 4).

Written from the issue's acceptance and the texts prsa-fit prints, without reading the fitting
code. A run is accepted when it exits 0 with a plant file that loads, whose total inertia is
within 3 % with the truth inside its 95 % interval, the delay exact, the current loop within 25 %
and the mode within 5 % where the data hold one; or when it exits 3 with no file and a one-line
diagnosis that is TRUE of the generator that made the data:

- a named frequency (``second mass ... X Hz``, ``resonance(s) ... near X Hz``, ``axial mode at X
  Hz``) within ``MODE_TOLERANCE`` (15 %) of one of the truth's ``modes_hz``; a named
  anti-resonance within 15 % of one of its ``anti_resonances_hz``; a second mass named without a
  frequency only where the truth has a mode;
- ``N (cycles) per revolution`` within ``ORDER_TOLERANCE`` of one of ``periodic_orders_per_rev``;
- units or coordinates blamed only where ``units_right`` / ``coordinates_right`` is False ("the
  units are right" is a finding, not a blame);
- a delay blamed only when the diagnosis says the delay is undecided, or when the delay the run
  reports (its JSON ``solver.command_delay``) is the truth's; a diagnosis that calls the delay
  decided is checked against the truth the same way;
- a friction model blamed where the truth's generator has friction the rigid laws lack (every
  generator here has standstill friction: such a claim cannot be refuted by these data);
- a work or iteration bound, a solver that did not converge or stalled, a numerical failure: a
  diagnosis of cost or of the fit, never of physics. Accepted only for a case the caller lists
  (``cost_allowed``: a documented allowance with its measured time).

Every claim of the line is judged (the most likely one and each ``besides``); one false claim
rejects the refusal.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

#: A named frequency is true within this fraction of a true mode (the modes move with the nut
#: force and position; 15 % is the band prsa-fit's own residual test names).
MODE_TOLERANCE = 0.15
#: A named order (cycles per revolution) is true within this many cycles of a true order.
ORDER_TOLERANCE = 0.1

_FREQ = re.compile(r"(?<![\w.])(\d+(?:\.\d+)?(?:[eE][+-]?\d+)?)\s*Hz\b")
_ORDER = re.compile(r"(?<![\w.])(\d+(?:\.\d+)?)\s*(?:cycles\s+)?per\s+rev(?:olution)?\b")
_COST = re.compile(r"work bound|iteration bound|bound on the (?:fit's )?work|evaluations|did not converge|\bstalled\b|"
                   r"numerical failure|fit failure|least-squares status|gauss-newton status|failed \(\w*error\)|"
                   r"\biterations\b", re.I)
_UNDECIDED = re.compile(r"undecided|could not decide|cannot decide|can't decide|not decided", re.I)
_DECIDED = re.compile(r"\bdelay (?:is |was )?decided\b", re.I)
_RESONANCE_WORDS = ("second mass", "two-mass", "resonance", "axial mode", " mode", "compliant", "stiffness")
_ABOUT_THE_MODEL = re.compile(r"\b(?:written|fitted|base) (?:plant|model)'s mode\b|held at the base plant's values")
_UNITS_RIGHT = re.compile(r"\b(?:units|coordinates) (?:are|is|look) right\b", re.I)


@dataclass
class Claim:
    """One claim of a diagnosis: its kind, its clause, and what it names."""

    kind: str  # "resonance", "periodic", "delay", "friction", "units", "cost"
    text: str
    modes_hz: list = field(default_factory=list)
    anti_resonances_hz: list = field(default_factory=list)
    orders: list = field(default_factory=list)
    undecided: bool = False


def clauses(line: str) -> list[str]:
    """The line split at the semicolons outside parentheses, each clause stripped of the
    ``most likely missing physics:`` and ``besides,`` lead-ins."""
    out, depth, cur = [], 0, []
    for ch in line:
        depth += ch in "([{"
        depth -= ch in ")]}"
        if ch == ";" and depth <= 0:
            out.append("".join(cur))
            cur = []
        else:
            cur.append(ch)
    out.append("".join(cur))
    cleaned = []
    for c in out:
        c = c.strip()
        c = re.sub(r"^prsa-fit:\s*", "", c)
        c = re.sub(r"^(?:.*?most likely missing physics:\s*)", "", c)
        c = re.sub(r"^besides,\s*", "", c)
        if c:
            cleaned.append(c)
    return cleaned


def _named_frequencies(clause: str):
    """(anti-resonances, modes) named in a resonance clause, Hz: each frequency is an
    anti-resonance when the text since the previous frequency names one. Frequencies after
    'kept at' or in a note on the current loop are not claims."""
    anti, modes, start = [], [], 0
    for m in _FREQ.finditer(clause):
        before = clause[start:m.start()].lower()
        start = m.end()
        if "kept at" in before[-12:]:
            continue
        (anti if ("anti-resonance" in before or "antiresonance" in before) else modes).append(float(m.group(1)))
    return anti, modes


def parse_claims(line: str) -> list[Claim]:
    """The claims of a diagnosis line (see the module docstring)."""
    claims = []
    for c in clauses(line):
        low = c.lower()
        if _COST.search(low):
            claims.append(Claim("cost", c))
            continue
        if "current-loop" in low or "current loop" in low:
            continue  # a note on what the misfit leaves unidentified, not a diagnosis
        if _ABOUT_THE_MODEL.search(low):
            continue  # a statement about the written or base plant, not about the data
        label = low.split(":", 1)[0] if ":" in low[:40] else ""
        if _UNITS_RIGHT.search(low) is None and re.search(r"\bunits?\b|\bcoordinates?\b", low):
            claims.append(Claim("units", c))
        if "periodic" in label or _ORDER.search(low):
            claims.append(Claim("periodic", c, orders=[float(x) for x in _ORDER.findall(low)]))
            continue
        if "delay" in label:
            claims.append(Claim("delay", c, undecided=bool(_UNDECIDED.search(low))))
            continue
        body = " " + low.replace("not a resonance", "").replace("no resonance", "")
        if "friction" in label:
            claims.append(Claim("friction", c))
        elif any(w in body for w in _RESONANCE_WORDS):
            anti, modes = _named_frequencies(c)
            claims.append(Claim("resonance", c, modes_hz=modes, anti_resonances_hz=anti))
        elif "friction" in low:
            claims.append(Claim("friction", c))
        if _DECIDED.search(low):
            claims.append(Claim("delay", c, undecided=False))
        elif "delay" in low and _UNDECIDED.search(low):
            claims.append(Claim("delay", c, undecided=True))
    return claims


def _near(value, truths, tol):
    return any(abs(value / t - 1.0) <= tol for t in truths if t)


def judge_diagnosis(line: str, truth: dict, *, run_delay: int | None = None, cost_allowed: bool = False) -> list[str]:
    """Why the refusal ``line`` is not accepted for data of ``truth`` (empty: accepted).

    ``run_delay``: the drive.command_delay_samples the run reports as found (None: it reports
    none). ``cost_allowed``: the case is listed as ending at a bound of the fit's work.
    """
    if "numerical failure" in line.lower() or "traceback" in line.lower():
        return [f"a crash, not a diagnosis: {line[-200:]!r}"]
    claims = parse_claims(line)
    fails = []
    physics = [c for c in claims if c.kind != "cost"]
    costs = [c for c in claims if c.kind == "cost"]
    if costs and not cost_allowed:
        fails.append(f"a diagnosis of cost or of the fit, not of physics (not listed as such): {costs[0].text[:200]!r}")
    if not physics and not costs:
        fails.append(f"exit 3 without a diagnosis naming the missing physics: {line[-200:]!r}")
    modes = [float(f) for f in truth.get("modes_hz", ())]
    antis = [float(f) for f in truth.get("anti_resonances_hz", ())]
    orders = [float(n) for n in truth.get("periodic_orders_per_rev", ())]
    for c in physics:
        if c.kind == "resonance":
            if not modes:
                fails.append(f"names a resonance, the generator's axis has none: {c.text[:160]!r}")
                continue
            for f in c.modes_hz:
                if not _near(f, modes, MODE_TOLERANCE):
                    fails.append(f"names {f:g} Hz, not within 15 % of a true mode {[round(m, 1) for m in modes]}")
            for f in c.anti_resonances_hz:
                if not _near(f, antis, MODE_TOLERANCE):
                    fails.append(f"names an anti-resonance at {f:g} Hz, the truth's are {[round(a, 1) for a in antis]}")
        elif c.kind == "periodic":
            if not c.orders:
                fails.append(f"a position-periodic torque without its order: {c.text[:160]!r}")
            for n in c.orders:
                if not any(abs(n - o) <= ORDER_TOLERANCE for o in orders):
                    fails.append(f"names {n:g} per revolution, the truth's orders are {orders}")
        elif c.kind == "units":
            if truth.get("units_right", True) and truth.get("coordinates_right", True):
                fails.append(f"blames the units or coordinates, which were right: {c.text[:160]!r}")
        elif c.kind == "delay" and not c.undecided:
            if run_delay is None or int(run_delay) != int(truth["drive.command_delay_samples"]):
                fails.append(f"a delay claim the truth does not bear out: the run's delay {run_delay}, "
                              f"the truth's {truth['drive.command_delay_samples']}: {c.text[:120]!r}")
    return fails


def run_delay(report: dict | None):
    """The drive.command_delay_samples a run's JSON reports as found by its delay search, else None
    (a delay the run itself calls undecided, given or the base plant's is no claim of the run's)."""
    cd = ((report or {}).get("solver") or {}).get("command_delay") or {}
    decided = cd.get("decided", (cd.get("search") or {}).get("decided"))
    if decided is False or "given" in str(cd.get("how", "")):
        return None
    status = str(cd.get("status", (cd.get("search") or {}).get("status", "")))
    if status and not status.startswith("decided"):
        return None
    d = cd.get("drive_command_delay_samples")
    return int(d) if isinstance(d, (int, float)) else None


# -- exit 0: the written plant --------------------------------------------------------------------

def value_ci(report, key):
    """(value, 95 % interval) of a key of a prsa-fit JSON report."""
    entry = report.get(key) if key == "reflected_inertia_kg_m2" else report.get("parameters", {}).get(key)
    if entry is None:
        return None, None
    if isinstance(entry, dict):
        return entry.get("value"), entry.get("ci95")
    return float(entry), None


def show_plant(path):
    """``prsa-tune --show-plant`` of a written file: (exit code, text)."""
    exe = shutil.which("prsa-tune", path=os.path.dirname(sys.executable) + os.pathsep + os.environ.get("PATH", ""))
    p = subprocess.run([exe, "--show-plant", str(path)], capture_output=True, text=True, timeout=300)
    return p.returncode, p.stdout + p.stderr


def plant_value(text, key):
    """A key's value in ``--show-plant``'s text, else None."""
    for line in text.splitlines():
        parts = line.split()
        if parts and parts[0] == key and "=" in parts:
            return float(parts[parts.index("=") + 1])
    return None


def reported_mode_hz(report, show_text):
    """The first axial mode the run reports (JSON: any key naming a mode in Hz), else the written
    plant's (``prsa-tune --show-plant``: 'axial mode X Hz')."""
    found = []

    def walk(node):
        if isinstance(node, dict):
            for k, v in node.items():
                kl = str(k).lower()
                if "mode" in kl and "hz" in kl and "anti" not in kl:
                    val = v.get("value") if isinstance(v, dict) else v
                    if isinstance(val, (int, float)):
                        found.append(float(val))
                walk(v)
        elif isinstance(node, list):
            for v in node:
                walk(v)

    walk(report)
    if found:
        return found[0]
    m = re.search(r"axial mode ([0-9.eE+-]+) Hz", show_text or "")
    return float(m.group(1)) if m else None


def acceptance(proc, out, json_path, truth, *, mode_expected: bool, must_fit: bool = False, cost_allowed: bool = False):
    """The issue's acceptance on one prsa-fit run: the list of failures (empty: accepted) and a
    summary row for the report. ``must_fit``: exit 3 is not accepted (the compliant FRF fit of a
    two-mass axis: the data have the structure the run asks for). ``cost_allowed``: a refusal at a
    bound of the fit's work is accepted (the case is listed as such)."""
    fails = []
    row = {"exit": proc.returncode}
    if "Traceback" in proc.stderr:
        fails.append("traceback on stderr")
    if proc.returncode == 3:
        lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
        diag = lines[-1] if lines else ""
        report = json.loads(Path(json_path).read_text()) if Path(json_path).exists() else None
        row.update(diagnosis=diag, run_delay=run_delay(report), delay_truth=truth["drive.command_delay_samples"])
        if must_fit:
            fails.append(f"exit 3 on data of the model class the run asked for: {diag[-200:]!r}")
        else:
            fails.extend(judge_diagnosis(diag, truth, run_delay=row["run_delay"], cost_allowed=cost_allowed))
        if Path(out).exists():
            fails.append("exit 3 but a plant file was written")
        return fails, row
    if proc.returncode != 0:
        fails.append(f"exit {proc.returncode} (expected 0 or 3): {proc.stderr.strip()[-300:]}")
        return fails, row
    if not Path(out).exists():
        fails.append("exit 0 without a plant file")
        return fails, row
    rc, show = show_plant(out)
    if rc != 0:
        fails.append(f"the written plant does not load: {show.strip()[-300:]}")
    report = json.loads(Path(json_path).read_text())
    j, ci = value_ci(report, "reflected_inertia_kg_m2")
    jt = truth["reflected_inertia_kg_m2"]
    row.update(inertia=j, ci=ci, inertia_truth=jt, parameters=report.get("parameters"),
               fit_percent=report.get("fit_percent"), delay_report=report.get("solver", {}).get("command_delay"))
    if j is None:
        fails.append("no reflected inertia reported")
    else:
        if abs(j / jt - 1.0) > 0.03:
            fails.append(f"reflected inertia {j:.5g} is {100 * (j / jt - 1):+.2f} % off the truth {jt:.5g} (3 % allowed)")
        if not ci or not (ci[0] <= jt <= ci[1]):
            fails.append(f"truth {jt:.5g} outside the 95 % interval {ci}")
    fc = plant_value(show, "drive.current_loop_bandwidth_hz")
    fct = truth["drive.current_loop_bandwidth_hz"]
    row.update(current_loop=fc, current_loop_truth=fct)
    if fc is None or abs(fc / fct - 1.0) > 0.25:
        fails.append(f"current loop {fc} Hz against {fct} Hz (25 % allowed)")
    nd = plant_value(show, "drive.command_delay_samples")
    row.update(delay=nd, delay_truth=truth["drive.command_delay_samples"])
    if nd is None or int(round(nd)) != truth["drive.command_delay_samples"]:
        fails.append(f"drive.command_delay_samples {nd} against {truth['drive.command_delay_samples']}")
    if mode_expected:
        fm = reported_mode_hz(report, show)
        row.update(mode=fm, mode_truth=truth["first_mode_hz"])
        if fm is None or abs(fm / truth["first_mode_hz"] - 1.0) > 0.05:
            fails.append(f"first axial mode {fm} Hz against {truth['first_mode_hz']:.4g} Hz (5 % allowed)")
    return fails, row
