"""prsa_ctrl.cli.pid (issue 25: ``prsa-pid``, the generic tuner on the command line).

The JSON must round-trip: each design is rebuilt here from its JSON alone (plant coefficients,
delay, gains, derivative and measurement filters) and its Ms, Mt, Mks and margins recomputed
with numpy (exact delay ``exp(-j w L)``, a dense grid refined by a bounded scalar search),
independently of prsa_ctrl. Bad input is one line, exit 2, before any heavy import.
"""

import json
import math
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import brentq, minimize_scalar

from prsa_ctrl.cli.pid import PLANT_ORDER_MAX, parse_plant, pid_main

ROOT = Path(__file__).resolve().parents[2]


# --- the independent frequency-domain check -------------------------------------------------------

def _parts(d: dict):
    """P(jw) and C(jw) F(jw) of the JSON ``d`` as functions of w (rad/s)."""
    pl, c = d["plant"], d["controller"]
    num, den, delay = np.array(pl["num"]), np.array(pl["den"]), pl["delay_s"]

    def p(w):
        s = 1j * np.asarray(w, float)
        return np.polyval(num, s) / np.polyval(den, s) * np.exp(-s * delay)

    def cf(w):
        s = 1j * np.asarray(w, float)
        deriv = s if c["tf_s"] is None else s / (c["tf_s"] * s + 1)
        out = c["kp"] + c["ki"] / s + c["kd"] * deriv
        t = c["filter_tf_s"]
        if c["filter_order"] == 1:
            out = out / (t * s + 1)
        elif c["filter_order"] == 2:
            out = out / (t * t * s * s / 2 + t * s + 1)
        return out

    return p, cf


def _peak(f, w):
    """max f on the grid ``w``, refined by a bounded search in log w around the grid maximum."""
    v = f(w)
    i = int(np.argmax(v))
    lo, hi = math.log(w[max(i - 1, 0)]), math.log(w[min(i + 1, w.size - 1)])
    r = minimize_scalar(lambda x: -f(np.array([math.exp(x)]))[0], bounds=(lo, hi), method="bounded",
                        options={"xatol": 1e-12})
    assert r.success, r.message  # (the grid's value is kept when the refinement finds less)
    return max(float(v[i]), -float(r.fun))


def independent_peaks(d: dict) -> dict:
    p, cf = _parts(d)
    w = np.logspace(-6, 7, 400_001)

    def S(x):
        return 1 / (1 + p(x) * cf(x))

    ms = _peak(lambda x: np.abs(S(x)), w)
    mt = _peak(lambda x: np.abs(1 - S(x)), w)
    mks = _peak(lambda x: np.abs(cf(x) * S(x)), w)
    # Gain crossover (the first |L| = 1 from above) and phase margin; gain margin over every -180 deg crossing.
    lmag = lambda x: np.abs(p(x) * cf(x))  # noqa: E731
    g = np.log(lmag(w))
    j = np.flatnonzero((g[:-1] > 0) & (g[1:] <= 0))[0]
    wc = brentq(lambda x: math.log(lmag(np.array([x]))[0]), w[j], w[j + 1], xtol=1e-14, rtol=1e-14)
    pm = 180 + math.degrees(float(np.angle(p(np.array([wc])) * cf(np.array([wc])))[0]))  # folded to (-180, 180]
    pm = pm - 360 if pm > 180 else pm
    phase = np.unwrap(np.angle(p(w) * cf(w)))
    x = (phase + np.pi) / (2 * np.pi)
    k = np.flatnonzero(np.floor(x[:-1]) != np.floor(x[1:]))  # crossings of -180 deg (mod 360)
    gms = []
    for i in k:
        def im(xw):
            return float(np.imag(p(np.array([xw])) * cf(np.array([xw])))[0])
        try:
            w180 = brentq(im, w[i], w[i + 1], xtol=1e-14, rtol=1e-14)
        except ValueError:
            continue
        val = p(np.array([w180]))[0] * cf(np.array([w180]))[0]
        if val.real < 0:
            gms.append(-20 * math.log10(abs(val)))
    return {"ms": ms, "mt": mt, "mks": mks, "wc": wc, "pm": pm,
            "gm": min(gms) if gms else math.inf}


def _run(tmp_path, argv, capsys):
    out = tmp_path / "r.json"
    code = pid_main([*argv, "--json", str(out)])
    text = capsys.readouterr().out
    return code, json.loads(out.read_text()), text


CASES = {
    # the issue's Mks case: PI on 1/(4s+1), Ms = Mt = 1.2, Mks = 10 (ki 13.739 by brute force)
    "pi-mks": ["--plant", "1/(4s+1)", "--objective", "ie", "--ms-max", "1.2", "--mt-max", "1.2", "--mks-max", "10"],
    "ideal": ["--plant", "1/(s+1)^3", "--controller", "pid", "--ideal", "--objective", "ie"],
    "filter2": ["--plant", "1/(s+1)^3", "--controller", "pid", "--filter-order", "2", "--filter-tf", "0.2",
                "--mks-max", "5", "--setpoint-weights"],
    "delay": ["--num", "1", "--den", "1", "1", "--delay", "1", "--controller", "pid", "--objective", "iae",
              "--tf", "0.05"],
    # ideal PID behind a first-order measurement filter (Mks finite and bounded), given Tf
    "ideal-f1": ["--plant", "1/(s+1)^3", "--controller", "pid", "--ideal", "--filter-order", "1", "--filter-tf", "0.74",
                 "--mks-max", "3", "--objective", "ie"],
    "reverse": ["--num", "-2", "--den", "1", "3", "3", "1", "--objective", "ie", "--mt-max", "1.3"],
    # open-loop unstable: negative static gain, yet positive gains (no sign flip); GM < 0 dB
    "unstable": ["--plant", "1/((s-1)(0.1s+1))"],
    # issue 34: open-loop unstable with a delay (was refused, exit 3), and a delay far below the
    # loop's time scale (was a failure after ~35 s)
    "unstable-delay": ["--plant", "1/(s-1)", "--delay", "0.2", "--objective", "ie", "--ms-max", "2"],
    "tiny-delay": ["--plant", "1/(s+1)", "--delay", "1e-5"],
}


@pytest.fixture(scope="module")
def case_run():
    """``case_run(name, tmp_path, capsys)``: the prsa-pid run of ``CASES[name]``, made once per module
    (each is a full tuning) and shared by every test that asserts on it: (exit code, JSON, stdout)."""
    done = {}

    def run(name, tmp_path, capsys):
        if name not in done:
            done[name] = _run(tmp_path, CASES[name], capsys)
        return done[name]

    return run


@pytest.mark.parametrize("name", list(CASES))
def test_json_round_trips_to_the_true_peaks(name, tmp_path, capsys, case_run):
    code, d, text = case_run(name, tmp_path, capsys)
    assert code == 0
    assert d["status"] == "optimal"
    assert d["converged"]
    ref = independent_peaks(d)
    for key in ("ms", "mt"):
        assert d[key] == pytest.approx(ref[key], rel=1e-4), key
    if name == "ideal":
        assert d["mks"] is None
        assert "Mks = inf" in text  # |C S| grows as kd w: infinite, JSON null
    else:
        assert d["mks"] == pytest.approx(ref["mks"], rel=1e-4)
    m = d["margins"]
    assert m["wc_rad_s"] == pytest.approx(ref["wc"], rel=1e-4)
    assert m["wc_hz"] == pytest.approx(ref["wc"] / (2 * math.pi), rel=1e-4)
    assert m["pm_deg"] == pytest.approx(ref["pm"], abs=1e-2)
    if math.isfinite(ref["gm"]):
        assert m["gm_db"] == pytest.approx(ref["gm"], abs=1e-2)
    else:
        assert m["gm_db"] is None
        assert "GM = inf" in text
    # the bounds hold on the independent peaks
    opt = d["options"]
    assert ref["ms"] <= opt["ms_max"] * (1 + 1e-6)
    assert opt["mt_max"] is None or ref["mt"] <= opt["mt_max"] * (1 + 1e-6)
    assert opt["mks_max"] is None or ref["mks"] <= opt["mks_max"] * (1 + 1e-6)
    # standard form is the parallel form rewritten
    c, st = d["controller"], d["standard"]
    assert st["K"] == c["kp"]
    assert st["Ti_s"] == pytest.approx(c["kp"] / c["ki"], rel=1e-12)
    assert st["Td_s"] == pytest.approx(c["kd"] / c["kp"], rel=1e-12, abs=0.0)
    assert f"kp = {c['kp']:.6g}" in text
    assert f"Ms = {d['ms']:.6g}" in text
    assert "status      optimal" in text


def test_the_issue_mks_case_matches_the_brute_force(tmp_path, capsys, case_run):
    _, d, _ = case_run("pi-mks", tmp_path, capsys)
    assert d["controller"]["ki"] == pytest.approx(13.739, rel=1e-3)  # issue 25: brute force ki 13.739
    assert d["objective"]["value"] == pytest.approx(1 / d["controller"]["ki"], rel=1e-9)  # IE = 1/ki exactly


def test_reverse_acting_plant_gets_negative_gains(tmp_path, capsys, case_run):
    _, d, text = case_run("reverse", tmp_path, capsys)
    c = d["controller"]
    assert c["kp"] < 0
    assert c["ki"] < 0
    assert any("tuned as -P" in w for w in d["warnings"])
    # -P with the negated gains is the same loop: the positive plant's design is its mirror image
    _, d2, _ = _run(tmp_path, ["--num", "2", "--den", "1", "3", "3", "1", "--objective", "ie", "--mt-max", "1.3"],
                    capsys)
    assert d2["controller"]["kp"] == pytest.approx(-c["kp"], rel=1e-9)
    assert d2["controller"]["ki"] == pytest.approx(-c["ki"], rel=1e-9)


def test_unstable_plant_keeps_positive_gains(tmp_path, capsys, case_run):
    _, d, _ = case_run("unstable", tmp_path, capsys)
    c = d["controller"]
    assert c["kp"] > 0
    assert c["ki"] > 0
    assert not any("tuned as -P" in w for w in d["warnings"])
    assert d["margins"]["gm_db"] < 0  # a lower gain margin: the loop tolerates a gain decrease of that much


def test_filtered_design_reports_filters_and_weights(tmp_path, capsys, case_run):
    _, d, text = case_run("filter2", tmp_path, capsys)
    c = d["controller"]
    assert c["filter_order"] == 2
    assert c["filter_tf_s"] == 0.2
    assert c["derivative"] == "filtered"
    assert c["tf_s"] > 0
    assert 0 <= c["b"] <= 1
    assert 0 <= c["c"] <= 1
    assert d["setpoint"]["iae"] <= d["setpoint"]["iae_unweighted"]
    assert "Tf = 0.2 s (given)" in text
    assert "setpoint weights b =" in text
    assert d["standard"]["N"] == pytest.approx(d["standard"]["Td_s"] / c["tf_s"], rel=1e-12)


def test_delay_report_says_exact(tmp_path, capsys, case_run):
    _, d, text = case_run("delay", tmp_path, capsys)
    assert d["plant"]["delay_s"] == 1.0
    assert d["margins"]["delay"] == "exact"
    assert d["controller"]["tf_s"] == 0.05
    assert d["options"]["tf_s"] == 0.05  # --tf is the derivative filter
    assert "exact delay" in d["objective"]["evaluation"]
    assert "exp(-1 s)" in text


# --- the plant text ---------------------------------------------------------------------------------

@pytest.mark.parametrize("text, num, den", [
    ("1/(4s+1)", [1], [4, 1]),
    ("2(s+1)/(s^2+3s+1)", [2, 2], [1, 3, 1]),
    ("1/(s+1)^3", [1], [1, 3, 3, 1]),
    ("(s + 0.5) / ((s+1)(2s+1)(s+3))", [1, 0.5], np.polymul(np.polymul([1, 1], [2, 1]), [1, 3])),
    ("-1.5e-1/(s**2 + .4 s + 1)", [-0.15], [1, 0.4, 1]),
    ("1/(s(s+1))", [1], [1, 1, 0]),
    ("3/(s+1) + 1/(s+2)", [4, 7], [1, 3, 2]),
    ("(1/(s+1)) * (1/(s+2)) - 0", [1], [1, 3, 2]),
])
def test_plant_parser_reads_rational_functions(text, num, den):
    n, d, _ = parse_plant(text)
    den = np.asarray(den, float)
    assert np.allclose(n, np.asarray(num, float) / den[0], rtol=1e-14)
    assert np.allclose(d, den / den[0], rtol=1e-14)


def test_plant_order_limit_is_the_tuners():
    from prsa_ctrl.tuning.generic import MAX_ORDER

    assert PLANT_ORDER_MAX == MAX_ORDER


def test_console_script_is_registered():
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts["prsa-pid"] == "prsa_ctrl.cli.pid:pid_main"


# --- bad input: one line, exit 2, before the tune -----------------------------------------------

BAD = [
    (["--num", "1", "x", "--den", "4", "1"], "--num 'x'"),
    (["--num", "1", "--den", "4", "nan"], "--den 'nan'"),
    (["--num", "1", "2", "--den", "1", "1"], "not strictly proper"),
    (["--plant", "s/(s+1)"], "not strictly proper"),
    (["--plant", "1/(4s+1"], "unbalanced parenthesis"),
    (["--plant", "1/(4s+1)*exp(-s)"], "give a delay with --delay"),
    (["--plant", "import os"], "'i'"),
    (["--plant", "1/(s^2+1)"], "undamped poles"),
    (["--plant", "1/(s+1)^31"], "exponent '31'"),
    (["--plant", "1/((s+1)^16 (s+2)^15)"], "order 31"),
    (["--plant", "0/(s+1)"], "the plant is zero"),
    (["--plant", "1/(4s+1)", "--delay", "-1"], "--delay -1"),
    (["--plant", "1/(4s+1)", "--delay", "abc"], "--delay 'abc'"),
    (["--plant", "1/(4s+1)", "--ms-max", "10"], "--ms-max 10"),
    (["--plant", "1/(4s+1)", "--ms-max", "1"], "--ms-max 1"),
    (["--plant", "1/(4s+1)", "--ms-max", "0.5"], "--ms-max 0.5"),
    (["--plant", "1/(4s+1)", "--mt-max", "11"], "--mt-max 11"),
    (["--plant", "1/(4s+1)", "--mks-max", "0"], "--mks-max 0"),
    (["--plant", "1/(4s+1)", "--ideal"], "--ideal with --controller pi"),
    (["--plant", "1/(4s+1)", "--ideal", "--controller", "pid"], "relative degree 1"),
    (["--plant", "1/(s+1)^2", "--ideal", "--controller", "pid", "--mks-max", "3"], "--mks-max 3 with --ideal"),
    (["--plant", "1/(4s+1)", "--filter-tf", "0.1"], "--filter-tf 0.1 without a filter"),
    (["--plant", "1/(4s+1)", "--tf", "0.1"], "--tf 0.1 with --controller pi"),
    (["--plant", "1/(4s+1)", "--filter-order", "3"], "--filter-order"),
    (["--plant", "1/(4s+1)", "--objective", "iea"], "'iea'"),
    (["--plant", "1/(4s+1)", "--json", "/nonexistent-dir/r.json"], "/nonexistent-dir"),
    (["--num", "1"], "without --den"),
    ([], "no plant"),
]


@pytest.mark.parametrize("argv, named", BAD)
def test_bad_input_is_one_line_exit_2(argv, named, capsys, monkeypatch):
    import prsa_ctrl.cli.pid as pid

    monkeypatch.setattr(pid, "_tune", lambda *a: pytest.fail("tuned despite bad input"))
    assert pid_main(argv) == 2
    cap = capsys.readouterr()
    lines = cap.err.strip().splitlines()
    assert len(lines) == 1, cap.err
    assert lines[0].startswith("prsa-pid: error: "), cap.err
    assert named in lines[0], cap.err
    assert cap.out == ""
    assert "Traceback" not in cap.err


def test_unwritable_output_is_refused_before_any_heavy_import(tmp_path):
    code = ("import runpy, sys\nsys.argv = ['prsa-pid', *sys.argv[1:]]\n"
            "try:\n    runpy.run_module('prsa_ctrl.cli.pid', run_name='__main__')\n"
            "except SystemExit as e:\n    print('exit', e.code, 'casadi' in sys.modules, 'control' in sys.modules)\n")
    for argv in (["--plant", "1/(4s+1)", "--json", str(tmp_path / "no" / "r.json")],
                 ["--num", "1", "x", "--den", "1", "1"], ["--plant", "1/(s+1)", "--ideal"]):
        p = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, cwd=tmp_path,
                           timeout=120)
        assert p.stdout.strip() == "exit 2 False False", (argv, p.stdout, p.stderr[-500:])
        assert len(p.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "no").exists()


def test_tiny_delay_and_the_law_are_stated(tmp_path, capsys, case_run):
    """A 1e-5 s delay on 1/(s+1): the objective's evaluation says it is the Pade model's (the
    exact simulation is out of reach), and ``controller.law`` is the law the code implements
    (the measurement filter on y only; tests/tuning/test_generic.py simulates it)."""
    code, d, text = case_run("tiny-delay", tmp_path, capsys)
    assert code == 0
    assert d["converged"]
    assert "Pade model of order" in d["objective"]["evaluation"]
    assert d["stats"]["delay_model"]["objective"] == "pade"
    assert d["controller"]["law"].startswith("u = kp (b r - y_f) + ki (r - y_f)/s + kd D(s) (c r - y_f), y_f = F(s) y")
    assert "Pade model of order" in text


@pytest.mark.parametrize("flag", ["--objective", "--controller", "--filter-order"])
def test_a_choice_flag_given_a_value_that_starts_with_a_minus_names_it(capsys, flag):
    # "--objective -x" said only "argument --objective: expected one argument"
    assert pid_main(["--plant", "1/(s+1)", flag, "-x"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert "'-x'" in err, err
