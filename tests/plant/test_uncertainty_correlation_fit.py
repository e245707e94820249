"""The rotary fit writes its correlation (issue 21): ``prsa-fit --uncertainty-from-fit`` on
three logs of a perturbed paper plant writes, in the fitted plant's ``[uncertainty]``, the
correlation of the keys written with the fit's own entry, computed here from the covariance in
the fit's JSON report (numpy); the file reads back to the same numbers; the default mode (the
base's entries kept, no fit entry for a key the base left without one) writes none but keeps
the base's own correlation where its keys' entries are unchanged.
"""

from __future__ import annotations

import json
import tomllib

import numpy as np

from prsa_ctrl.cli.fit import main as fit_main
from prsa_ctrl.plant import load_plant
from prsa_ctrl.plant.uncertainty import uncertainty_model

from identification.test_fit import base, csv_files  # noqa: F401  (module fixtures: three toolkit logs)

from test_uncertainty_correlation import PAPER


def test_rotary_fit_writes_the_covariance_correlation(csv_files, tmp_path):  # noqa: F811
    _, paths = csv_files
    out, rep = tmp_path / "fitted.toml", tmp_path / "fit.json"
    assert fit_main([*paths, "--out", str(out), "--json", str(rep), "--uncertainty-from-fit"]) == 0
    report = json.loads(rep.read_text())
    doc = tomllib.loads(out.read_text())
    corr = doc["uncertainty"]["correlation"]
    cov = report["covariance"]
    fitted = [k for k, v in report["parameters"].items() if not v["kept_base"] and k in doc["uncertainty"]
              and doc["uncertainty"][k]["source"].startswith("fit: ")]
    assert corr["keys"] == fitted and len(fitted) >= 4
    idx = [cov["keys"].index(k) for k in fitted]
    c = np.array(cov["matrix"])[np.ix_(idx, idx)]
    sd = np.sqrt(np.diag(c))
    assert np.max(np.abs(np.array(corr["matrix"]) - c / np.outer(sd, sd))) < 1e-12
    plant = load_plant(out)
    assert plant.uncertainty["correlation"] == corr  # read back to every digit
    m = uncertainty_model(plant)
    assert [c.keys for c in m.correlations] == [tuple(fitted)]


def test_default_mode_keeps_the_bases_correlation(csv_files, tmp_path):  # noqa: F811
    """The paper base with a correlation between two keys the fit does not touch
    (contact stiffness and roller position error): kept as it is; between a fitted key (its
    entry replaced by the fit's) and an untouched one: dropped with it."""
    _, paths = csv_files
    keep = ('correlation = { keys = ["contact.stiffness_n_per_mm_e", "tolerance.roller_position_std_um"], '
            'matrix = [[1.0, 0.25], [0.25, 1.0]], source = "estimate: test" }\n')
    base_file = tmp_path / "base.toml"
    base_file.write_text(PAPER.read_text() + keep)
    out = tmp_path / "fitted.toml"
    assert fit_main([*paths, "--plant", str(base_file), "--out", str(out)]) == 0
    got = tomllib.loads(out.read_text())["uncertainty"]["correlation"]
    assert got == {"keys": ["contact.stiffness_n_per_mm_e", "tolerance.roller_position_std_um"],
                   "matrix": [[1.0, 0.25], [0.25, 1.0]], "source": "estimate: test"}
    cut = ('correlation = { keys = ["nut.inertia_kg_m2", "contact.stiffness_n_per_mm_e"], '
           'matrix = [[1.0, 0.25], [0.25, 1.0]], source = "estimate: test" }\n')
    base_file.write_text(PAPER.read_text().replace(
        '"nut.inertia_kg_m2" = { dist = "uniform", relative = 0.3,', '"nut.inertia_kg_m2" = { dist = "uniform", low = 1.9e-4, high = 2.1e-4,')
        + cut)
    out2, rep2 = tmp_path / "fitted2.toml", tmp_path / "fit2.json"
    assert fit_main([*paths, "--plant", str(base_file), "--out", str(out2), "--json", str(rep2)]) == 0
    assert any("correlation (estimate: test): dropped for nut.inertia_kg_m2 (its entry is no longer" in w
               for w in json.loads(rep2.read_text())["warnings"])
    unc2 = tomllib.loads(out2.read_text())["uncertainty"]
    assert unc2["nut.inertia_kg_m2"]["source"].startswith("fit: ")  # excludes the fitted value: replaced
    assert "correlation" not in unc2
    load_plant(out2)
