"""Seeded Monte-Carlo verification: yield, reproducibility across backends, interruption."""

from __future__ import annotations

import dataclasses
import json
import shutil
import math
import multiprocessing
import threading
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, strategies as st
from numpy.polynomial.hermite_e import hermegauss
from scipy.stats import norm, truncnorm

from prsa_ctrl.cli.montecarlo import main as mc_main
from prsa_ctrl.cli.tune import main as tune_main
from prsa_ctrl.drive.pid import PID
from prsa_ctrl.identification.axis import PARAMETERS
from prsa_ctrl.plant import load_plant
from prsa_ctrl.plant.plantfile import load_plant
from prsa_ctrl.plant.uncertainty import uncertainty_model
from prsa_ctrl.studies import montecarlo as mc
from prsa_ctrl.studies.montecarlo import draw_sample, run_monte_carlo
from prsa_ctrl.studies.scene import load_scene

# Two designs of the robust scene: a fast one tuned on the nominal plant and a slower one.
FAST = PID(0.0849, 14.67, tf=1e-3)
SLOW = PID(0.0384, 4.68, tf=1e-3)
N = 6


@pytest.fixture(scope="module")
def setup():
    return load_plant(), load_scene("robust-load-step")


@pytest.fixture(scope="module")
def serial(setup):
    p, s = setup
    return mc.run_monte_carlo(p, s, {"fast": FAST, "slow": SLOW}, N, seed=7, backend="serial", quiet=True)


@given(k=st.integers(0, 10_000), extra=st.integers(0, 10_000))
def test_wilson_interval_contains_the_estimate(k, extra):
    n = k + extra
    lo, hi = mc.wilson_interval(k, n)
    assert 0.0 <= lo <= hi <= 1.0
    if n:
        assert lo <= k / n <= hi
        assert hi - lo < 1.0 or n < 4


def test_wilson_matches_the_textbook_value():
    # 95 % Wilson interval of 8/10 (Newcombe 1998, Table I): 0.490 - 0.943
    lo, hi = mc.wilson_interval(8, 10)
    assert (round(lo, 3), round(hi, 3)) == (0.490, 0.943)


def test_sample_depends_only_on_seed_and_index(setup):
    p, s = setup
    unc = uncertainty_model(p, s.sections.plant_overrides)
    ops = [(1.0, 1500.0)]
    a = mc.draw_sample(unc, ops, 3, 17)
    assert a == mc.draw_sample(unc, ops, 3, 17)
    assert a != mc.draw_sample(unc, ops, 3, 18)
    assert a != mc.draw_sample(unc, ops, 4, 17)


def test_report_yield_is_recomputed_from_the_samples(serial, setup):
    p, s = setup
    spec = s.sections.as_dict()["spec"]
    assert serial.complete
    assert serial.n_done == N
    m = serial.samples["metrics"]
    assert m.shape == (N, 2, len(mc.METRICS))
    for j, d in enumerate(serial.designs):
        rows = m[:, j]
        col = {k: rows[:, mc.METRICS.index(k)] for k in mc.METRICS}
        ok = ((col["peak_drop_rad_s"] <= spec["peak_drop_rad_s"]) & (col["recovery_time_s"] <= spec["recovery_time_s"])
              & (col["ms"] <= spec["ms"]) & (col["saturated"] == 0))
        assert d.passed == int(ok.sum())
        assert d.yield_ == pytest.approx(ok.mean())
        assert d.ci95 == mc.wilson_interval(d.passed, N)
        assert d.percentiles["peak_drop_rad_s"]["max"] == pytest.approx(col["peak_drop_rad_s"].max())
    # the slower design drops further and is more robust
    assert np.all(m[:, 1, 0] > m[:, 0, 0])
    assert np.all(m[:, 1, mc.METRICS.index("ms")] < m[:, 0, mc.METRICS.index("ms")])
    text = mc.format_report(serial)
    assert "yield" in text
    assert "95 % CI" in text
    assert "replay: python -m prsa_ctrl.cli.montecarlo" in text
    d = serial.as_dict(include_samples=True)
    json.dumps(d, allow_nan=False)
    assert d["complete"] is True
    assert d["designs"][0]["yield_ci95"][0] <= d["designs"][0]["yield"]


def test_worst_sample_replays_exactly(serial, setup):
    p, s = setup
    d = serial.designs[0]
    rep = mc.replay_sample(p, s, FAST, serial.seed, d.worst_index)
    row = serial.samples["metrics"][list(serial.samples["index"]).index(d.worst_index), 0]
    assert rep["parameters"] == d.worst_values
    assert np.array_equal(np.array([rep["metrics"][k] for k in mc.METRICS]), row, equal_nan=True)
    # the command line names the same sample and gains
    assert f"--seed {serial.seed} --index {d.worst_index}" in d.replay
    assert repr(FAST.kp) in d.replay


def test_process_pool_gives_bit_identical_results(serial, setup):
    p, s = setup
    par = mc.run_monte_carlo(p, s, {"fast": FAST, "slow": SLOW}, N, seed=7, backend="process", workers=2,
                             chunk=2, quiet=True)
    assert np.array_equal(par.samples["metrics"], serial.samples["metrics"], equal_nan=True)
    assert [d.as_dict() | {"worst_sample": None} for d in par.designs] == \
           [d.as_dict() | {"worst_sample": None} for d in serial.designs]


def test_dask_local_cluster_gives_bit_identical_results(serial, setup):
    distributed = pytest.importorskip("distributed", reason="Dask is an optional extra: pip install 'prsa-ctrl[dask]'")
    p, s = setup
    # A real 2-worker cluster on the loopback address, reached like a remote one (tcp://...).
    # Port 8787 (Dask's default HTTP port) is held busy, as another cluster on the machine would:
    # the cluster must not depend on it (it failed here with "Port 8787 is already in use").
    import socket

    busy = socket.socket()
    try:
        busy.bind(("0.0.0.0", 8787))
        busy.listen()
    except OSError:  # already taken by something else: the same condition
        pass
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, host="127.0.0.1", processes=True,
                                  dashboard_address=None, scheduler_kwargs={"dashboard_address": "127.0.0.1:0"}) as cluster:
        das = mc.run_monte_carlo(p, s, {"fast": FAST, "slow": SLOW}, N, seed=7, scheduler=cluster.scheduler_address,
                                 workers=2, chunk=3, quiet=True)
        # A connected Client is reused (a running cluster: no start-up) and left open.
        with distributed.Client(cluster) as client:
            reused = mc.run_monte_carlo(p, s, {"fast": FAST, "slow": SLOW}, N, seed=7, scheduler=client, chunk=2,
                                        quiet=True)
            assert client.status == "running"
            assert client.submit(sum, [1, 2]).result() == 3
    busy.close()
    assert reused.backend == "dask"
    assert reused.workers == 2
    assert reused.complete
    assert np.array_equal(reused.samples["metrics"], serial.samples["metrics"], equal_nan=True)
    assert das.backend == "dask"
    assert das.complete
    assert np.array_equal(das.samples["metrics"], serial.samples["metrics"], equal_nan=True)
    assert das.samples["values"].keys() == serial.samples["values"].keys()
    for k in das.samples["values"]:
        assert np.array_equal(das.samples["values"][k], serial.samples["values"][k])


def test_ctrl_c_returns_partial_results_marked_incomplete(setup):
    p, s = setup
    calls = []

    def interrupt(done, total):
        calls.append(done)
        if done >= 2:
            raise KeyboardInterrupt

    with pytest.raises(mc.MonteCarloInterrupted) as exc:
        mc.run_monte_carlo(p, s, {"fast": FAST}, 5, seed=1, chunk=1, progress=interrupt)
    rep = exc.value.report
    assert isinstance(exc.value, KeyboardInterrupt)
    assert rep.complete is False
    assert rep.n_done == 2
    assert rep.n == 5
    assert rep.as_dict()["complete"] is False
    assert "INTERRUPTED" in mc.format_report(rep)


_ORPHAN_SCRIPT = """
import multiprocessing, os, sys
from prsa_ctrl.studies import montecarlo as mc
from prsa_ctrl.drive.pid import PID
from prsa_ctrl.plant.plantfile import load_plant
from prsa_ctrl.studies.scene import load_scene

def interrupt(done, total):
    if done >= 1:
        print(" ".join(str(c.pid) for c in multiprocessing.active_children()), flush=True)
        raise KeyboardInterrupt

try:
    mc.run_monte_carlo(load_plant(), load_scene("robust-load-step"), {"a": PID(0.05, 5.0, tf=1e-3)}, 200,
                       backend="process", workers=2, chunk=10, integrator="reference", progress=interrupt)
except mc.MonteCarloInterrupted:
    pass
os._exit(130)  # as prsa-tune ends after Ctrl-C: no atexit hooks
"""


def test_ctrl_c_in_a_process_pool_leaves_no_worker_running(tmp_path):
    """After Ctrl-C the pool's workers (which ignore SIGINT) are stopped, also when the process
    then ends at once as the CLI does: none keeps computing queued chunks as an orphan."""
    import os
    import subprocess
    import sys
    import time

    out = tmp_path / "pids.txt"
    with open(out, "w") as f:
        proc = subprocess.run([sys.executable, "-c", _ORPHAN_SCRIPT], stdout=f, stderr=subprocess.DEVNULL,
                              timeout=300, cwd=tmp_path)
    assert proc.returncode == 130
    pids = [int(x) for x in out.read_text().split()]
    assert len(pids) == 2

    def running(pid):
        try:
            with open(f"/proc/{pid}/status") as st:
                return not any(line.startswith("State:") and "Z" in line for line in st)
        except FileNotFoundError:
            return False

    # Terminated workers end at once; a step budget (200 polls), not a clock, bounds the wait.
    for _ in range(200):
        if not any(running(p) for p in pids):
            break
        time.sleep(0.1)
    alive = [p for p in pids if running(p)]
    for p in alive:
        os.kill(p, 9)
    assert not alive


@pytest.mark.parametrize("kw, match", [
    ({"n": 0}, "n = 0"),
    ({"n": 2.5}, "n = 2.5"),
    ({"seed": -1}, "seed = -1"),
    ({"backend": "gpu"}, "backend = 'gpu'"),
    ({"scheduler": "http://x"}, "scheduler = 'http://x'"),
    ({"backend": "serial", "scheduler": "local"}, "needs backend"),
    ({"workers": 0}, "workers = 0"),
    ({"chunk": 0}, "chunk = 0"),
])
def test_bad_arguments_are_named(setup, kw, match):
    p, s = setup
    args = {"n": 2, "seed": 0, **kw}
    with pytest.raises(ValueError, match=match):
        mc.run_monte_carlo(p, s, {"fast": FAST}, quiet=True, **args)


def test_progress_bar_is_silent_off_a_terminal(setup, capsys):
    p, s = setup
    mc.run_monte_carlo(p, s, {"fast": FAST}, 1, seed=0)
    assert capsys.readouterr().err == ""


def test_progress_bar_draws_when_asked(capsys):
    bar = mc._Progress(4, True)
    bar.update(4)
    bar.close()
    err = capsys.readouterr().err
    assert "4/4" in err
    assert err.endswith("\n")


def test_figures(serial, tmp_path):
    from prsa_ctrl.plots.montecarlo import plot_report  # moved out of studies: figures live in plots/

    fig = plot_report(serial, tmp_path / "mc.png")
    assert (tmp_path / "mc.png").stat().st_size > 0
    assert len(fig.axes) == 3


def test_replay_command_line(serial, capsys):
    d = serial.designs[0]
    args = d.replay.split()[3:]
    assert mc_main(args) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["index"] == d.worst_index
    assert (math.isclose(out["metrics"]["peak_drop_rad_s"],
                                                           d.worst_metrics["peak_drop_rad_s"], rel_tol=0, abs_tol=0))
    assert mc_main(["--seed", "1", "--index", "0", "--kp", "-1", "--ki", "1"]) == 2
    assert "kp = -1" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------------
# Monte Carlo on a fitted linear axis (issue 21: the Monte Carlo works for every mechanism;
# the last stop left the fitted linear axis untested).
#
# The EMPS record (examples/emps, a real ball-screw axis) is fitted by ``prsa-fit`` into a
# ``linear-axis`` plant file whose ``[uncertainty]`` holds the fit's 95 % intervals (a normal with
# the interval's sigma, truncated at it). ``prsa-tune --monte-carlo`` on it must run, report a
# yield with its Wilson interval and draw exactly the fitted uncertainty: checked here against
# scipy's truncated normal and the fit's own intervals, independently of the toolkit's sampler.
# ------------------------------------------------------------------------------------------------

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "emps"
needs_data = pytest.mark.skipif(not (EXAMPLE / "DATA_EMPS.mat").is_file(), reason="EMPS data absent")
Z95 = 1.959963984540054

#: A load step on the axis in load coordinates (1 m per rad): 50 mm/s, a 40 N step at 20 ms.
SCENE = """name = "axis-load-step"
[operating]
setpoint_rpm = 0.477464829275686   # 0.05 m/s (a linear axis turns 1 rad per m: rpm = m/s x 30 / pi)
initial_load_n = 0.0
final_loads_n = [40.0]
step_time_s = 0.02
duration_s = 0.1
[tuning]
objective = "iae"
controller = "pi"
ms_max = 1.4
candidates = 1
[verify]
fidelity = "rigid"
discrete = true
[spec]
peak_drop_rad_s = 0.004   # m/s
recovery_time_s = 0.05
ms = 1.5
"""


@pytest.fixture(scope="module")
def fitted(tmp_path_factory, emps_fit):
    """prsa-fit on the EMPS record (tests/conftest.py: one fit per session), its plant file copied
    into this module's folder as fitted.toml beside the scene."""
    assert emps_fit.code == 0, emps_fit.err
    d = tmp_path_factory.mktemp("mc-fitted")
    out, js = d / "fitted.toml", emps_fit.json
    shutil.copyfile(emps_fit.toml, out)
    (d / "scene.toml").write_text(SCENE)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plant = load_plant(out)
    return d, plant, json.loads(js.read_text())


def _wilson(k, n, z=Z95):
    """Reference Wilson score interval."""
    p = k / n
    c = (p + z * z / (2 * n)) / (1 + z * z / n)
    h = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return (0.0 if k == 0 else c - h), (1.0 if k == n else c + h)


@needs_data
def test_fitted_uncertainty_is_the_fits_intervals(fitted):
    """Every fitted key has an [uncertainty] entry whose +-1.96 sigma is exactly its 95 % interval."""
    _, plant, fit = fitted
    assert plant.mechanism == "linear-axis"
    for k in PARAMETERS:
        e = plant.uncertainty[k]
        lo, hi = fit["parameters"][k]["ci95"]
        assert e["dist"] == "normal"
        assert e["truncate"] == pytest.approx(Z95, rel=1e-12)
        assert plant.values[k] == pytest.approx(fit["parameters"][k]["value"], rel=1e-12)
        assert plant.values[k] - Z95 * e["sigma"] == pytest.approx(lo, rel=1e-9)
        assert plant.values[k] + Z95 * e["sigma"] == pytest.approx(hi, rel=1e-9)


@needs_data
def test_monte_carlo_draws_the_fitted_uncertainty(fitted):
    """4000 draws of the Monte Carlo's own sampler (the seeds its runs use): each key inside the
    fit's 95 % interval and spread over it, mean and standard deviation those of scipy's normal
    truncated at the interval (to 5 standard errors), keys drawn with the fit's correlation."""
    d, plant, fit = fitted
    scene = load_scene(d / "scene.toml")
    unc = uncertainty_model(plant, scene.sections.plant_overrides)
    n = 4000
    draws = [draw_sample(unc, [(0.05, 40.0)], 7, i)[0] for i in range(n)]
    cols = {k: np.array([s[k] for s in draws]) for k in PARAMETERS}
    for k, x in cols.items():
        v = fit["parameters"][k]["value"]
        lo, hi = fit["parameters"][k]["ci95"]
        sig = (hi - lo) / (2 * Z95)
        ref = truncnorm(-Z95, Z95, loc=v, scale=sig)
        assert lo - 1e-9 * abs(v) <= x.min(), k
        assert x.max() <= hi + 1e-9 * abs(v), k
        assert x.min() < lo + 0.05 * (hi - lo), k
        assert x.max() > hi - 0.05 * (hi - lo), k  # reaches both ends
        se_mean = ref.std() / math.sqrt(n)
        assert abs(x.mean() - ref.mean()) < 5 * se_mean, k
        # standard error of a sample std of n normal-ish draws: ~ std / sqrt(2 n)
        assert abs(x.std(ddof=1) / ref.std() - 1) < 5 / math.sqrt(2 * n), k
        # and the truncated normal's std is below the untruncated sigma by the known factor
        phi, big = norm.pdf(Z95), 2 * norm.cdf(Z95) - 1
        assert ref.std() == pytest.approx(sig * math.sqrt(1 - 2 * Z95 * phi / big), rel=1e-9)
    # the keys are drawn with the fit's correlation (Gaussian copula): the normal scores of the
    # draws have the correlation the fitted file writes (standard error (1 - r^2) / sqrt(n))
    corr = plant.uncertainty["correlation"]
    assert corr["keys"] == list(PARAMETERS)
    scores = []
    for k, x in cols.items():
        v = fit["parameters"][k]["value"]
        lo, hi = fit["parameters"][k]["ci95"]
        scores.append(norm.ppf(truncnorm(-Z95, Z95, loc=v, scale=(hi - lo) / (2 * Z95)).cdf(x)))
    c = np.corrcoef(np.array(scores))
    r = np.array(corr["matrix"])
    assert np.all(np.abs(c - r) < 5 * (1 - r ** 2) / math.sqrt(n) + 1e-12)


@needs_data
def test_monte_carlo_runs_and_reports_yield(fitted):
    """A small seeded run of the tuned design on the fitted axis: every sample simulates, the
    yield and its Wilson interval are right, each sample's parameters are the sampler's draws
    for its seed, and the same seed gives the same report."""
    from prsa_ctrl.studies.autotune import tune_actuator

    d, plant, _ = fitted
    scene = load_scene(d / "scene.toml")
    rep = tune_actuator(plant, scene, workers=1)
    mc = run_monte_carlo(plant, scene, [rep.best], 6, seed=3, backend="serial", progress=False, quiet=True)
    assert mc.ok
    assert mc.n_done == 6
    assert not mc.warnings
    y = mc.designs[0]
    assert y.failures == 0
    assert 0 <= y.passed <= 6
    assert y.yield_ == y.passed / 6
    assert y.ci95 == pytest.approx(_wilson(y.passed, 6), abs=1e-12)
    per = mc.as_dict(include_samples=True)["per_sample"]
    unc = uncertainty_model(plant, scene.sections.plant_overrides)
    for j, i in enumerate(per["index"]):
        want = draw_sample(unc, mc.operating_points, 3, i)[0]
        assert {k: per["parameters"][k][j] for k in want} == pytest.approx(want, rel=1e-15)
    assert set(per["parameters"]) == set(PARAMETERS)
    # the metrics respond to the drawn plant (not one nominal run repeated): the peak force
    # differs between samples
    peak = np.array(per["metrics"][y.name]["peak_torque_n_m"])
    assert np.ptp(peak) > 0
    again = run_monte_carlo(plant, scene, [rep.best], 6, seed=3, backend="serial", progress=False, quiet=True)
    assert again.designs[0].passed == y.passed
    assert again.designs[0].percentiles == y.percentiles


@needs_data
def test_prsa_tune_monte_carlo_on_the_fitted_file(fitted, capsys):
    """The CLI: prsa-tune --monte-carlo on the fitted plant file reports the yields, the fitted
    uncertainty with its sources, and the coordinates (text and JSON)."""
    d, plant, _ = fitted
    js = d / "tune.json"
    code = tune_main(["--plant", str(d / "fitted.toml"), "--scene", str(d / "scene.toml"), "--monte-carlo", "6",
                      "--seed", "1", "--workers", "1", "--json", str(js)])
    text = capsys.readouterr().out
    assert code == 0, text
    assert "Monte Carlo: 6/6 samples, seed 1" in text
    assert "coordinates: load (position m, force N)" in text
    rep = json.loads(js.read_text())
    assert rep["coordinates"].startswith("load (position m, force N)")
    mc = rep["monte_carlo"]
    assert mc["samples_done"] == 6
    assert mc["complete"]
    assert set(mc["uncertainty"]) == set(PARAMETERS)
    for k, e in mc["uncertainty"].items():
        assert e["source"].startswith("fit: DATA_EMPS.mat")
        assert e["nominal"] == pytest.approx(plant.values[k])
    for dy in mc["designs"]:
        assert dy["simulation_failures"] == 0
        assert dy["yield"] == dy["passed"] / 6
        assert dy["yield_ci95"] == pytest.approx(list(_wilson(dy["passed"], 6)), abs=1e-12)


# ------------------------------------------------------------------------------------------------
# Monte Carlo on the EMPS fitted plant with the fit's correlations (issue 21).
#
# ``prsa-fit`` on the EMPS record (examples/emps) writes the correlation of the fitted keys into
# ``[uncertainty]``; ``prsa-tune --monte-carlo`` draws them jointly (Gaussian copula). Checked here:
# the written matrix reproduces the fit's own delta-method standard deviations of its load-side
# equivalents (FIT.json ``equivalent``), and the friction force at 0.05 m/s drawn jointly has the
# spread of an independent quadrature reference and stays inside the fit's delta-method interval,
# where independent draws spill far out of it.
# ------------------------------------------------------------------------------------------------

SPEED = 0.05  # m/s
N_DRAWS = 2000
FCP, FVP, FVN, FCN = ("friction.coulomb_positive_n", "friction.viscous_positive_n_s_per_m",
                      "friction.viscous_negative_n_s_per_m", "friction.coulomb_negative_n")
#: gradient of the signed friction force at +-SPEED over PARAMETERS (M, Fv+, Fv-, Fc+, Fc-)
GRAD = {+1: np.array([0.0, SPEED, 0.0, 1.0, 0.0]), -1: np.array([0.0, 0.0, -SPEED, 0.0, -1.0])}


def _force(s, d):
    return s[FCP] + SPEED * s[FVP] if d > 0 else -(s[FCN] + SPEED * s[FVN])


@needs_data
def test_fit_writes_the_correlation_of_its_covariance(fitted):  # noqa: F811
    """The written matrix over the five fitted keys: exactly symmetric, unit diagonal, the
    strong viscous/Coulomb anti-correlation of each direction, and with the JSON's standard
    deviations it gives the fit's delta-method standard deviation of every load-side
    equivalent (g' S R S g = std^2, computed by the fit from its covariance)."""
    _, plant, fit = fitted
    corr = plant.uncertainty["correlation"]
    assert corr["keys"] == list(PARAMETERS)
    assert corr["source"].startswith("fit: DATA_EMPS.mat")
    r = np.array(corr["matrix"])
    assert np.all(r == r.T)
    assert np.all(np.diag(r) == 1.0)
    assert np.linalg.eigvalsh(r).min() > 0
    i = {k: j for j, k in enumerate(PARAMETERS)}
    assert r[i[FVP], i[FCP]] < -0.8
    assert r[i[FVN], i[FCN]] < -0.8
    sd = np.array([fit["parameters"][k]["std"] for k in PARAMETERS])
    c = np.outer(sd, sd) * r
    vs = 1e-3  # the equivalents' small speed (axis.SMALL_SPEED_M_S), written out
    combos = {"friction_positive_n": [0, vs, 0, 1, 0], "friction_negative_n": [0, 0, -vs, 0, -1],
              "viscous_n_s_per_m": [0, 0.5, 0.5, 0, 0], "coulomb_n": [0, 0, 0, 0.5, 0.5], "offset_n": [0, 0, 0, 0.5, -0.5]}
    for name, g in combos.items():
        g = np.array(g, float)
        assert math.sqrt(g @ c @ g) == pytest.approx(fit["equivalent"][name]["std"], rel=1e-9), name


def _copula_std(s_c, s_v, rho, trunc, w_c, w_v):
    """Standard deviation of w_c x_c + w_v x_v for two normals truncated at +-trunc sigma
    (sigmas s_c, s_v) joined by a Gaussian copula with correlation rho, by 2-D Gauss-Hermite
    quadrature (independent of the sampler): x = s h(z), h(z) = truncnorm.ppf(Phi(z))."""
    z, w = hermegauss(80)
    w = w / w.sum()
    t = truncnorm(-trunc, trunc)
    h = lambda x: t.ppf(np.clip(norm.cdf(x), 1e-300, 1.0))  # noqa: E731
    var_h = t.var()
    z1, z2 = np.meshgrid(z, z, indexing="ij")
    ww = np.outer(w, w)
    cov_h = float(np.sum(ww * h(z1) * h(rho * z1 + math.sqrt(1 - rho * rho) * z2)))
    return math.sqrt(w_c ** 2 * s_c ** 2 * var_h + w_v ** 2 * s_v ** 2 * var_h + 2 * w_c * w_v * s_c * s_v * cov_h)


@needs_data
def test_friction_at_50_mm_s_drawn_jointly_matches_the_fits_interval(fitted):  # noqa: F811
    """2000 draws of the Monte Carlo's sampler, jointly and (the old way) independently: the
    joint draws of the friction force at +-0.05 m/s have the standard deviation of the
    quadrature reference (5 standard errors), stay inside the fit's delta-method 95 % interval
    of that force (>= 95 % of draws; the marginals are truncated at their intervals) and span
    most of it; the independent draws are far wider and leave it."""
    d, plant, fit = fitted
    scene = load_scene(d / "scene.toml")
    unc = uncertainty_model(plant, scene.sections.plant_overrides)
    ind = dataclasses.replace(unc, correlations=())
    par = fit["parameters"]
    r = np.array(plant.uncertainty["correlation"]["matrix"])
    i = {k: j for j, k in enumerate(PARAMETERS)}
    sd = np.array([par[k]["std"] for k in PARAMETERS])
    theta = np.array([par[k]["value"] for k in PARAMETERS])
    ents = {e.key: e for e in unc.entries}
    for direction, (kc, kv) in ((+1, (FCP, FVP)), (-1, (FCN, FVN))):
        g = GRAD[direction]
        val, sd_f = float(g @ theta), math.sqrt(g @ (np.outer(sd, sd) * r) @ g)
        half = (par[kc]["ci95"][1] - par[kc]["value"]) / par[kc]["std"] * sd_f  # Student's t x sd, as the fit's intervals
        joint = np.array([_force(draw_sample(unc, [(0.05, 40.0)], 21, k)[0], direction) for k in range(N_DRAWS)])
        alone = np.array([_force(draw_sample(ind, [(0.05, 40.0)], 21, k)[0], direction) for k in range(N_DRAWS)])
        ref = _copula_std(ents[kc].sigma, ents[kv].sigma, r[i[kc], i[kv]], (ents[kc].high - ents[kc].nominal) / ents[kc].sigma,
                          direction, direction * SPEED)
        assert abs(joint.std(ddof=1) / ref - 1) < 5 / math.sqrt(2 * N_DRAWS), (direction, joint.std(), ref)
        inside = np.mean(np.abs(joint - val) <= half)
        inside_alone = np.mean(np.abs(alone - val) <= half)
        assert inside >= 0.95, (inside, inside_alone)
        assert inside_alone < 0.9, (inside, inside_alone)
        lo, hi = np.percentile(joint, [2.5, 97.5])
        assert 0.75 * half < (hi - lo) / 2 <= half
        assert alone.std() > 1.5 * joint.std()


@needs_data
def test_prsa_tune_monte_carlo_8_on_the_correlated_fit(fitted, capsys):  # noqa: F811
    """prsa-tune --monte-carlo 8 on the fitted file: runs, every sample simulates, and the JSON
    states each key's correlations as the file writes them."""
    d, plant, _ = fitted
    js = d / "tune-corr.json"
    code = tune_main(["--plant", str(d / "fitted.toml"), "--scene", str(d / "scene.toml"), "--monte-carlo", "8",
                      "--seed", "2", "--workers", "1", "--json", str(js)])
    text = capsys.readouterr().out
    assert code == 0, text
    assert "Monte Carlo: 8/8 samples, seed 2" in text
    assert f"drawn jointly (Gaussian copula of the [uncertainty] correlation): {', '.join(sorted(PARAMETERS))}" in text
    mc = json.loads(js.read_text())["monte_carlo"]
    assert mc["samples_done"] == 8
    assert mc["complete"]
    corr = plant.uncertainty["correlation"]
    for a, k in enumerate(corr["keys"]):
        want = {o: corr["matrix"][a][b] for b, o in enumerate(corr["keys"]) if b != a}
        assert mc["uncertainty"][k]["correlation"]["with"] == want
    for dy in mc["designs"]:
        assert dy["simulation_failures"] == 0


# ------------------------------------------------------------------------------------------------
# The process-pool Monte Carlo leaves nothing running once it has returned.
#
# A finished run used ``ProcessPoolExecutor.shutdown(wait=False)``: the pool's management thread
# and workers were still alive when ``run_monte_carlo`` returned, and at interpreter exit they
# raced with ``threading._shutdown`` ("Exception ignored ... Bad file descriptor" printed after a
# successful ``prsa-tune --monte-carlo`` in about a quarter of the runs). The check here is
# deterministic: right after the call, no pool thread and no worker process may be left.
# ------------------------------------------------------------------------------------------------

def test_finished_process_pool_run_leaves_no_thread_and_no_worker():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plant = load_plant()
    scene = load_scene("robust-load-step")
    before = {t.ident for t in threading.enumerate()}
    rep = mc.run_monte_carlo(plant, scene, {"design": PID(0.0849, 14.67, tf=1e-3)}, 4, seed=2, backend="process",
                             workers=2, chunk=2, quiet=True, progress=False, spec={})
    assert rep.samples["metrics"].shape[0] == 4
    left = [t for t in threading.enumerate() if t.ident not in before and t.is_alive()]
    assert left == [], f"pool threads still running after the run: {[t.name for t in left]}"
    assert multiprocessing.active_children() == []
