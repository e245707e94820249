"""Monte Carlo on the EMPS fitted plant with the fit's correlations (issue 21).

``prsa-fit`` on the EMPS record (examples/emps) writes the correlation of the fitted keys into
``[uncertainty]``; ``prsa-tune --monte-carlo`` draws them jointly (Gaussian copula). Checked here:
the written matrix reproduces the fit's own delta-method standard deviations of its load-side
equivalents (FIT.json ``equivalent``), and the friction force at 0.05 m/s drawn jointly has the
spread of an independent quadrature reference and stays inside the fit's delta-method interval,
where independent draws spill far out of it.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from numpy.polynomial.hermite_e import hermegauss
from scipy.stats import norm, truncnorm

from prsa_ctrl.cli.tune import main as tune_main
from prsa_ctrl.identification.axis import PARAMETERS
from prsa_ctrl.plant.uncertainty import uncertainty_model
from prsa_ctrl.studies.montecarlo import draw_sample
from prsa_ctrl.studies.scene import load_scene

from test_mc_fitted_axis import fitted, needs_data  # noqa: F401  (module fixture: prsa-fit on the EMPS record)

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
    assert corr["keys"] == list(PARAMETERS) and corr["source"].startswith("fit: DATA_EMPS.mat")
    r = np.array(corr["matrix"])
    assert np.all(r == r.T) and np.all(np.diag(r) == 1.0) and np.linalg.eigvalsh(r).min() > 0
    i = {k: j for j, k in enumerate(PARAMETERS)}
    assert r[i[FVP], i[FCP]] < -0.8 and r[i[FVN], i[FCN]] < -0.8
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
    unc = uncertainty_model(plant, scene)
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
        assert inside >= 0.95 and inside_alone < 0.9, (inside, inside_alone)
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
    assert mc["samples_done"] == 8 and mc["complete"]
    corr = plant.uncertainty["correlation"]
    for a, k in enumerate(corr["keys"]):
        want = {o: corr["matrix"][a][b] for b, o in enumerate(corr["keys"]) if b != a}
        assert mc["uncertainty"][k]["correlation"]["with"] == want
    for dy in mc["designs"]:
        assert dy["simulation_failures"] == 0
