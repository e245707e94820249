"""Monte Carlo on a fitted linear axis (issue 21: the Monte Carlo works for every mechanism;
the last stop left the fitted linear axis untested).

The EMPS record (examples/emps, a real ball-screw axis) is fitted by ``prsa-fit`` into a
``linear-axis`` plant file whose ``[uncertainty]`` holds the fit's 95 % intervals (a normal with
the interval's sigma, truncated at it). ``prsa-tune --monte-carlo`` on it must run, report a
yield with its Wilson interval and draw exactly the fitted uncertainty: checked here against
scipy's truncated normal and the fit's own intervals, independently of the toolkit's sampler.
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import norm, truncnorm

from prsa_ctrl.cli.fit import main as fit_main
from prsa_ctrl.cli.tune import main as tune_main
from prsa_ctrl.identification.axis import PARAMETERS
from prsa_ctrl.plant import load_plant
from prsa_ctrl.plant.uncertainty import uncertainty_model
from prsa_ctrl.studies.montecarlo import draw_sample, run_monte_carlo
from prsa_ctrl.studies.scene import load_scene

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
def fitted(tmp_path_factory):
    d = tmp_path_factory.mktemp("mc-fitted")
    out, js = d / "fitted.toml", d / "fit.json"
    assert fit_main([str(EXAMPLE / "DATA_EMPS.mat"), "--log-format", str(EXAMPLE / "log.toml"), "--out", str(out),
                     "--json", str(js)]) == 0
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
        assert e["dist"] == "normal" and e["truncate"] == pytest.approx(Z95, rel=1e-12)
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
    unc = uncertainty_model(plant, scene)
    n = 4000
    draws = [draw_sample(unc, [(0.05, 40.0)], 7, i)[0] for i in range(n)]
    cols = {k: np.array([s[k] for s in draws]) for k in PARAMETERS}
    for k, x in cols.items():
        v = fit["parameters"][k]["value"]
        lo, hi = fit["parameters"][k]["ci95"]
        sig = (hi - lo) / (2 * Z95)
        ref = truncnorm(-Z95, Z95, loc=v, scale=sig)
        assert lo - 1e-9 * abs(v) <= x.min() and x.max() <= hi + 1e-9 * abs(v), k
        assert x.min() < lo + 0.05 * (hi - lo) and x.max() > hi - 0.05 * (hi - lo), k  # reaches both ends
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
    assert mc.ok and mc.n_done == 6 and not mc.warnings
    y = mc.designs[0]
    assert y.failures == 0 and 0 <= y.passed <= 6 and y.yield_ == y.passed / 6
    assert y.ci95 == pytest.approx(_wilson(y.passed, 6), abs=1e-12)
    per = mc.as_dict(include_samples=True)["per_sample"]
    unc = uncertainty_model(plant, scene)
    for j, i in enumerate(per["index"]):
        want = draw_sample(unc, mc.operating_points, 3, i)[0]
        assert {k: per["parameters"][k][j] for k in want} == pytest.approx(want, rel=1e-15)
    assert set(per["parameters"]) == set(PARAMETERS)
    # the metrics respond to the drawn plant (not one nominal run repeated): the peak force
    # differs between samples
    peak = np.array(per["metrics"][y.name]["peak_torque_n_m"])
    assert np.ptp(peak) > 0
    again = run_monte_carlo(plant, scene, [rep.best], 6, seed=3, backend="serial", progress=False, quiet=True)
    assert again.designs[0].passed == y.passed and again.designs[0].percentiles == y.percentiles


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
    assert "Monte Carlo: 6/6 samples, seed 1" in text and "coordinates: load (position m, force N)" in text
    rep = json.loads(js.read_text())
    assert rep["coordinates"].startswith("load (position m, force N)")
    mc = rep["monte_carlo"]
    assert mc["samples_done"] == 6 and mc["complete"]
    assert set(mc["uncertainty"]) == set(PARAMETERS)
    for k, e in mc["uncertainty"].items():
        assert e["source"].startswith("fit: DATA_EMPS.mat") and e["nominal"] == pytest.approx(plant.values[k])
    for dy in mc["designs"]:
        assert dy["simulation_failures"] == 0
        assert dy["yield"] == dy["passed"] / 6
        assert dy["yield_ci95"] == pytest.approx(list(_wilson(dy["passed"], 6)), abs=1e-12)
