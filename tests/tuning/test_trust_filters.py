"""Issue 20 (filters, robust tuning, Monte Carlo, export): results that do nothing are never
labelled good, every report section is strict JSON, the exported design is named, SIGTERM
stops the workers, bad filter arguments are named."""

import json
import math
import os
import signal
import subprocess
import sys
import time
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from prsa_ctrl import SceneError, load_plant
from prsa_ctrl.cli.tune import main as tune_main
from prsa_ctrl.drive.filters import METHODS, FirstOrderLowPass, GeneralBiquad, Notch, SecondOrderLowPass
from prsa_ctrl.studies.scene import load_scene



def _builtin_scene_text(name: str) -> str:
    from importlib.resources import files
    from pathlib import Path

    try:
        return (files("prsa_ctrl.scenes") / f"{name}.toml").read_text(encoding="utf-8")
    except ModuleNotFoundError:  # a source checkout on PYTHONPATH: the scenes' source folder
        return (Path(__file__).resolve().parents[2] / "tuning" / f"{name}.toml").read_text(encoding="utf-8")


# --- item 2: filter arguments out of range are named, never "b0 = nan" -------------------------

def test_notch_biquad_at_an_absurd_sample_time_names_ts():
    with pytest.raises(ValueError, match=r"^ts = 1e-300 s for a notch at 500 Hz; expected ts >= "):
        Notch(500.0, 200.0).biquad(1e-300)
    with pytest.raises(ValueError, match=r"^centre_hz = 1e-300; expected a finite number >= 1e-06"):
        Notch(1e-300, 1e-301)
    with pytest.raises(ValueError, match=r"^corner_hz = 1e-300"):
        FirstOrderLowPass(1e-300)


@st.composite
def _filters(draw):
    hz = st.floats(1e-6, 1e9)
    kind = draw(st.sampled_from(["lp1", "lp2", "notch", "biquad"]))
    if kind == "lp1":
        return FirstOrderLowPass(draw(hz))
    if kind == "lp2":
        return SecondOrderLowPass(draw(hz), draw(st.floats(1e-3, 100.0)))
    if kind == "notch":
        c = draw(hz)
        return Notch(c, c * draw(st.floats(1e-3, 4.0)), draw(st.floats(-120.0, 0.0)))
    return GeneralBiquad(draw(hz), draw(st.floats(0.0, 100.0)), draw(hz), draw(st.floats(1e-3, 100.0)))


@settings(max_examples=300, deadline=None, derandomize=True)
@given(f=_filters(), log_ts=st.floats(-310.0, 3.0), method=st.sampled_from(METHODS))
def test_every_filter_biquad_is_finite_with_unit_dc_gain_or_names_its_argument(f, log_ts, method):
    """Any filter the constructors accept, at any sample time (1e-310 .. 1e3 s), with any
    method: a biquad of finite coefficients whose DC gain is 1 within 1e-5, or a ValueError
    naming ``ts`` or the Nyquist frequency (never an internal "b0 = nan")."""
    ts = 10.0 ** log_ts
    try:
        bq = f.biquad(ts, method)
    except ValueError as exc:
        assert str(exc).startswith("ts = ") or "expected below the Nyquist frequency" in str(exc), str(exc)
        return
    c = [bq.b0, bq.b1, bq.b2, bq.a1, bq.a2]
    assert all(math.isfinite(x) for x in c)
    assert abs(bq.dc_gain - 1.0) < 1e-5


# --- item 1: a notch is kept only where it acts on the mode -------------------------------------

@pytest.fixture(scope="module")
def mode163():
    """The heavy-slide plant made heavier and less damped through its own keys: the thread
    contact's axial mode at 163 Hz with damping ratio 0.0005 (linearised at 300 rpm, 1000 N;
    a ~44 dB peak of |L| over its running median), one loop, 50 ms horizon."""
    from prsa_ctrl.tuning.filtered import loop_builder, tune_filtered
    from prsa_ctrl.plant.linear import linear_core
    from prsa_ctrl.plant.model import plant_model
    from prsa_ctrl.plant.uncertainty import apply

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p = apply(load_plant("paper-heavy-slide"), {"screw.mass_kg": 284.0, "contact.damping_n_s_per_mm": 19.6},
                  name="mode-163")
    a, b, c, _, _ = linear_core(p, 31.4159, 1000.0, "compliant")
    lam = np.linalg.eigvals(a)
    osc = lam[(lam.imag > 2 * math.pi * 50) & (lam.imag < 2 * math.pi * 2000)]
    assert osc.size == 1
    f_mode, zeta = abs(osc[0]) / (2 * math.pi), -osc[0].real / abs(osc[0])
    assert abs(f_mode - 163.0) < 1.0 and abs(zeta - 0.0005) < 0.0001
    m = plant_model(p, "compliant")
    bld = loop_builder(a, b, c[m.output_names.index("nut_speed")], m.index("theta_nut"), ts=p.sample_time_s,
                       speed_filter=p.speed_filter_s, tf=1e-3, horizon=0.05, step=1000.0)
    ref = tune_filtered([bld], ts=p.sample_time_s, kind=None, start_gains=(0.01, 1.0))
    assert ref.converged
    return p.sample_time_s, f_mode, bld, ref


def _gains_alone_grid_best(lp, ms_max=1.4):
    """Independent check: the best IAE (to infinity) of the gains alone on a 25 x 25 grid."""
    best = math.inf
    for kp in np.logspace(-2.5, -0.5, 25):
        for ki in np.logspace(-1.5, 1.5, 25):
            g = np.r_[kp, ki, 0.0]
            if lp.stability(g) == "stable" and lp.peaks(g)["ms"] <= ms_max:
                best = min(best, lp.objective_to_infinity(g, "iae")[0])
    return best


def test_notch_started_at_the_mode_acts_on_it_and_pays(mode163):
    from prsa_ctrl.tuning.filtered import tune_filtered

    ts, f_mode, bld, ref = mode163
    n = tune_filtered([bld], ts=ts, kind="notch", start_gains=(ref.pid.kp, ref.pid.ki), reference=ref)
    assert n.status == "optimal" and n.converged and n.filter is not None
    f = n.filter.filter
    # acts on the mode: centre within 1.5x of it, a real depth, >= 3 dB less loop gain at the mode
    assert abs(math.log(f.centre_hz / f_mode)) < math.log(1.5)
    assert f.depth_db <= -3.0
    att_db = 20 * math.log10(abs(n.filter.biquad(ts).frequency_response([2 * math.pi * f_mode])[0]))
    assert att_db <= -3.0
    # true loop quantities of the returned design, recomputed
    lp = bld(n.filter)
    g = n.pid.gains
    assert lp.stability(g) == "stable" and lp.peaks(g)["ms"] <= 1.4
    assert abs(lp.objective_to_infinity(g, "iae")[0] - n.objective) <= 1e-9 * n.objective
    # and it pays: well below anything the gains alone reach within the same Ms bound
    assert n.objective < 0.5 * _gains_alone_grid_best(bld(None))


def test_notch_that_cannot_reach_the_mode_is_not_labelled_optimal(mode163):
    """Search box 221-884 Hz (a start at 442 Hz), the mode at 163 Hz outside it: the old tuner
    returned the 442 Hz notch as "optimal"; now the status says no notch helps and why, and
    the design returned is the gains alone."""
    from prsa_ctrl.tuning.filtered import tune_filtered

    ts, f_mode, bld, ref = mode163
    n = tune_filtered([bld], ts=ts, kind="notch", start_gains=(ref.pid.kp, ref.pid.ki),
                      start_filter=(442.0, 0.3 * 442.0, -20.0), reference=ref)
    assert n.status != "optimal"
    if n.filter is not None:  # a kept notch must act on the mode
        f = n.filter.filter
        assert f.depth_db <= -3.0 and abs(math.log(f.centre_hz / f_mode)) < math.log(1.5)
    assert n.status.startswith("no notch helps: ") and "away from the mode" in n.status
    assert n.filter is None and n.pid == ref.pid and n.objective == ref.objective and n.converged
    assert n.stats["rejected_filter"]["kind"] == "notch"


# --- items 3, 4, 5: robust study -> recommended design, strict JSON, named export ----------------

def _robust_scene(tmp_path, name, *, relative=0.5, setpoints="[300.0]", spec=None, mc=0, bandwidth=True):
    src = _builtin_scene_text("robust-load-step")
    src = src.replace('relative = 0.5,', f'relative = {relative},')
    if not bandwidth:
        src = "\n".join(l for l in src.splitlines() if not l.startswith('"drive.current_loop_bandwidth_hz"'))
    if spec is not None:
        head, rest = src.split("[spec]", 1)
        src = head + "[spec]\n" + spec + "\n\n[robust]" + rest.split("[robust]", 1)[1]
    src = src.replace("setpoints_rpm = [300.0]", f"setpoints_rpm = {setpoints}")
    src = src.replace("monte_carlo = 1000", f"monte_carlo = {mc}")
    path = tmp_path / f"{name}.toml"
    path.write_text(src, encoding="utf-8")
    return str(path)


def test_recommend_ranks_by_the_yield_against_the_spec():
    """Unit check of the ranking: robust 10/200 against nominal 132/200 recommends the nominal
    design; both at 0 recommends none; without Monte Carlo the spec is said to be unchecked."""
    from prsa_ctrl.drive.pid import PID
    from prsa_ctrl.studies.montecarlo import DesignYield, wilson_interval
    from prsa_ctrl.tuning.robust import RobustTuning

    comp = {"objective": "iae", "ms_max": 1.4, "designs": {
        "nominal": {"ms_violations": 2, "worst_objective": 0.03}, "robust": {"ms_violations": 0, "worst_objective": 0.08}}}
    rt = RobustTuning(PID(0.085, 14.7), PID(0.045, 6.8), [object()] * 12, comp, {}, None)

    class MC:
        def __init__(self, k_nom, k_rob, n=200):
            self.designs = [DesignYield(name, {}, k, n, k / n, wilson_interval(k, n), {}, None, {}, {}, 0, "")
                            for name, k in (("nominal design", k_nom), ("robust design", k_rob))]

    r = rt.recommend(MC(132, 10))
    assert r["design"] == "nominal" and r["yield"] == 0.66 and r["passed"] == 132 and r["samples"] == 200
    assert "66.0 % (132/200)" in r["why"] and "5.0 % (10/200)" in r["why"]
    # Frozen study: recommend() leaves it as it is; with_recommendation() returns a copy that keeps it.
    assert rt.recommended == {} and rt.with_recommendation(MC(132, 10)).recommended == r
    assert rt.recommend(MC(10, 132))["design"] == "robust"
    none = rt.recommend(MC(0, 0))
    assert none["design"] is None and "no design meets the spec on any sample" in none["why"]
    lin = rt.recommend(None)
    assert lin["design"] == "robust" and lin["yield"] is None and "not checked" in lin["why"]


def test_report_json_and_export_name_the_recommended_design(tmp_path, capsys):
    """Inertia +-50 %, two setpoints, a peak-drop spec: the report and the JSON recommend a
    design of (near-)maximal Monte-Carlo yield among every design the run evaluated (issue 34:
    no other design's yield above it by more than the two Wilson half-widths), with its yield
    and why; --export writes that design and says so."""
    from prsa_ctrl.studies.montecarlo import wilson_interval

    scene = _robust_scene(tmp_path, "two-sp", setpoints="[300.0, 600.0]", spec="peak_drop_rad_s = 5.2",
                          bandwidth=False)
    out = tmp_path / "r.json"
    exp = tmp_path / "drive.toml"
    code = tune_main(["--scene", scene, "--monte-carlo", "24", "--seed", "1", "--workers", "2",
                      "--json", str(out), "--export", str(exp)])
    text = capsys.readouterr().out
    assert code == 0
    d = json.loads(out.read_text())
    ylds = {x["name"]: x for x in d["monte_carlo"]["designs"]}
    assert {"nominal design", "robust design"} <= set(ylds) and len(ylds) > 2  # baselines ranked too
    rec = d["recommended"]
    assert rec == d["robust"]["recommended"]
    me = ylds[rec["name"]]
    assert rec["yield"] == me["yield"] and rec["passed"] == me["passed"] and rec["gains"]["kp"] == me["gains"]["kp"]
    h = lambda k: (lambda lo, hi: (hi - lo) / 2)(*wilson_interval(k, 24))  # noqa: E731
    assert all((y["passed"] - me["passed"]) / 24 <= h(y["passed"]) + h(me["passed"]) + 1e-12 for y in ylds.values())
    assert f"recommended: {rec['name']} (" in text and f"* {rec['name']}" in text
    import tomllib

    t = tomllib.loads(exp.read_text())
    assert t["design"]["name"] == rec["name"] and t["design"]["yield"] == me["yield"]
    assert t["speed_controller"]["continuous"]["kp_n_m_s_per_rad"] == me["gains"]["kp"]
    assert f"drive export: {exp} holds the design '{rec['name']}', recommended by the robust study" in text


def test_unstable_scenario_is_reported_and_the_json_is_written(tmp_path, capsys):
    """Inertia relative 0.8: the nominal design is unstable on a scenario model; the run ends
    with exit 0, a strict-JSON report (null for the infinite Ms, stable = false) and a text
    line naming the unstable models; --export holds the recommended (robust) design."""
    scene = _robust_scene(tmp_path, "r08", relative=0.8)
    out = tmp_path / "r.json"
    exp = tmp_path / "drive.json"
    code = tune_main(["--scene", scene, "--json", str(out), "--export", str(exp)])
    text = capsys.readouterr().out
    assert code == 0
    d = json.loads(out.read_text(), parse_constant=lambda c: pytest.fail(f"non-finite {c} in the JSON"))
    per = d["robust"]["comparison"]["designs"]["nominal"]["per_scenario"]
    bad = [p for p in per if not p["stable"]]
    assert bad and all(p["ms"] is None for p in bad)
    assert "nominal: closed loop unstable on" in text
    rec = d["recommended"]
    assert rec["design"] == "robust" and rec["yield"] is None and "not checked" in rec["why"]
    e = json.loads(exp.read_text())
    assert e["design"]["name"] == "robust design"
    assert e["speed_controller"]["continuous"]["kp_n_m_s_per_rad"] == d["robust"]["robust_gains"]["kp"]


def test_export_with_load_feedforward_is_refused_up_front(tmp_path, capsys):
    exp = tmp_path / "ff.toml"
    code = tune_main(["--scene", "paper-load-step", "--estimator", "kf", "--feedforward", "--export", str(exp)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--export" in err[0] and "--feedforward" in err[0]
    assert not exp.exists()


# --- item 7: the Monte-Carlo replay on a duty scene ----------------------------------------------

def test_monte_carlo_replay_on_a_duty_scene_is_one_line(capsys):
    from prsa_ctrl.cli.montecarlo import main as mc_main
    from prsa_ctrl.studies.scenerobust import operating_points

    code = mc_main(["--scene", "duty-trace", "--seed", "0", "--index", "0", "--kp", "0.05", "--ki", "5"])
    err = [l for l in capsys.readouterr().err.splitlines() if l.startswith("error")]
    assert code == 2 and len(err) == 1 and "duty cycle" in err[0] and "load-step scene" in err[0]
    with pytest.raises(SceneError, match="is a duty cycle"):
        operating_points(load_scene("duty-trace"))


# --- item 6: SIGTERM during a Monte-Carlo process pool -------------------------------------------

def _children(pid):
    try:
        with open(f"/proc/{pid}/task/{pid}/children") as f:
            return [int(x) for x in f.read().split()]
    except FileNotFoundError:
        return []


def _running(pid):
    try:
        with open(f"/proc/{pid}/status") as st_:
            return not any(line.startswith("State:") and "Z" in line for line in st_)
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_sigterm_in_a_monte_carlo_pool_stops_the_workers_and_says_so(tmp_path):
    """prsa-tune with a Monte-Carlo process pool of 2 workers gets SIGTERM once the pool runs
    (the second set of worker processes, after the verification's): exit 143 with one line,
    and no worker survives (a step budget of polls bounds every wait, no clock is read)."""
    scene = _robust_scene(tmp_path, "mc", mc=400)
    out, err = tmp_path / "out.txt", tmp_path / "err.txt"
    with open(out, "w") as fo, open(err, "w") as fe:
        proc = subprocess.Popen([sys.executable, "-c", "import sys; from prsa_ctrl.cli.tune import main; sys.exit(main())",
                                 "--scene", scene, "--workers", "2", "--json", str(tmp_path / "r.json")],
                                stdout=fo, stderr=fe, cwd=tmp_path)
        first: set = set()
        pool: list = []
        for _ in range(6000):  # step budget: 6000 polls of 20 ms at most
            kids = _children(proc.pid)
            if not first and len(kids) >= 2:
                first = set(kids)  # the verification's workers
            elif first:
                pool = [k for k in kids if k not in first]
                if len(pool) >= 2:
                    break
            if proc.poll() is not None:
                break
            time.sleep(0.02)
        assert len(pool) >= 2, "the Monte-Carlo pool never started"
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(timeout=120)
    alive = pool
    for _ in range(200):  # step budget (200 polls)
        alive = [p for p in pool if _running(p)]
        if not alive:
            break
        time.sleep(0.1)
    for p in alive:
        os.kill(p, signal.SIGKILL)
    assert not alive
    lines = [l for l in err.read_text().splitlines() if l.strip()]
    assert code == 143 and lines[-1] == "prsa-tune: interrupted (SIGTERM); no output written"
    assert not (tmp_path / "r.json").exists()


def test_an_interrupted_command_does_not_leave_sigterm_ignored():
    """After an interrupted in-process command SIGTERM has its old handler again: an ignored
    SIGTERM would be inherited by every later child process (whose workers then survive
    ``terminate()``)."""
    from prsa_ctrl.cli import common as cli

    def body(run, argv):
        run.interrupted = True
        raise KeyboardInterrupt

    old_int, old_term = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    try:
        assert cli.invoke_inner(cli.Run("prsa-tune"), [], body) == cli.EXIT_INTERRUPTED
        assert signal.getsignal(signal.SIGTERM) is old_term
    finally:
        signal.signal(signal.SIGINT, old_int)
        signal.signal(signal.SIGTERM, old_term)
