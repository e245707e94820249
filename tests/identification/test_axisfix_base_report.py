"""Linear-axis fit (prsa-fit --log-format) with a --plant base: the base's values, description
and [uncertainty] entries on unfitted keys are kept, a disagreeing drive gain is refused, a
disagreeing force limit is kept with a warning; FIT.json carries the covariance and correlation
matrices the plant file's intervals and correlation block come from."""

from __future__ import annotations

import csv
import json
import tomllib

import numpy as np
import pytest

from prsa_ctrl.cli.fit import main

from test_emps import _CSV_FORMAT, _generate  # noqa: E402  (tests/identification is on sys.path)

BASE = """name = "mine"
description = "MY BASE"
mechanism = "linear-axis"
coordinates = "load"
[axis]
mass_kg = {{ value = 70.0, source = "guess" }}
[drive]
gain_n_per_unit = {{ value = {gain}, source = "my base" }}
force_limit_n = {{ value = 500.0, source = "my base limit" }}
command_unit = "V"
[sensor]
sample_time_s = {{ value = 0.001, source = "my base" }}
encoder_resolution_m = {{ value = 5e-8, source = "my base" }}
[uncertainty]
"axis.mass_kg" = {{ dist = "uniform", low = 60.0, high = 80.0, source = "payload" }}
"drive.gain_n_per_unit" = {{ dist = "uniform", relative = 0.05, source = "amplifier tolerance" }}
"""


@pytest.fixture(scope="module")
def logdir(tmp_path_factory):
    d = tmp_path_factory.mktemp("axisbase")
    t, qm, r, u = _generate(0, n=3000)
    with (d / "log.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["time_ms", "pos_mm", "ref_mm", "u_V"])
        w.writerows(zip(*(map(repr, map(float, a)) for a in (1e3 * t, 1e3 * qm, 1e3 * r, u))))
    (d / "fmt.toml").write_text(_CSV_FORMAT)
    return d


def _run(d, gain, tag, capsys):
    (d / f"base-{tag}.toml").write_text(BASE.format(gain=gain))
    out, js = d / f"fit-{tag}.toml", d / f"fit-{tag}.json"
    capsys.readouterr()
    rc = main([str(d / "log.csv"), "--log-format", str(d / "fmt.toml"), "--plant", str(d / f"base-{tag}.toml"),
               "--out", str(out), "--json", str(js)])
    return rc, out, js, capsys.readouterr()


def test_base_values_and_uncertainty_kept_and_covariance_reported(logdir, capsys):
    rc, out, js, cap = _run(logdir, 30.0, "ok", capsys)
    assert rc == 0, cap.err
    doc = tomllib.loads(out.read_text())
    assert doc["description"].startswith("MY BASE")
    assert doc["drive"]["gain_n_per_unit"] == {"value": 30.0, "source": "my base"}
    assert doc["drive"]["force_limit_n"] == {"value": 500.0, "source": "my base limit"}  # base kept ...
    rep = json.loads(js.read_text())
    warn = [w for w in rep["warnings"] if w.startswith("drive.force_limit_n")]
    assert len(warn) == 1 and "500" in warn[0] and "300" in warn[0]  # ... with a warning naming both (10 V x 30 N/V)
    assert "warning: drive.force_limit_n" in cap.out
    unc = doc["uncertainty"]
    assert unc["drive.gain_n_per_unit"] == {"dist": "uniform", "relative": 0.05, "source": "amplifier tolerance"}
    assert unc["axis.mass_kg"]["dist"] == "normal"  # a fitted key: the fit's interval replaces the base's entry
    # covariance: the matrix the intervals come from
    cov = rep["covariance"]
    c = np.array(cov["matrix"])
    assert cov["keys"] == list(rep["parameters"]) and len(cov["units"]) == len(cov["keys"])
    assert np.allclose(c, c.T)
    for i, k in enumerate(cov["keys"]):
        p = rep["parameters"][k]
        assert np.isclose(np.sqrt(c[i, i]), p["std"], rtol=1e-12)
    # correlation: independent from the covariance, and the same as the plant file's block
    keys = rep["correlation"]["keys"]
    idx = [cov["keys"].index(k) for k in keys]
    sub = c[np.ix_(idx, idx)]
    ref = sub / np.sqrt(np.outer(np.diag(sub), np.diag(sub)))
    r = np.array(rep["correlation"]["matrix"])
    assert np.allclose(r, ref, atol=1e-12) and np.allclose(np.diag(r), 1.0)
    assert np.max(np.abs(ref - np.eye(len(keys)))) > 0.05  # the check is not vacuous
    block = unc["correlation"]
    pos = [keys.index(k) for k in block["keys"]]
    assert np.allclose(np.array(block["matrix"]), r[np.ix_(pos, pos)], atol=1e-9)


def test_base_gain_disagreeing_with_the_log_is_refused(logdir, capsys):
    rc, out, js, cap = _run(logdir, 31.0, "bad", capsys)
    assert rc == 2
    line = cap.err.strip()
    assert "\n" not in line and "drive.gain_n_per_unit" in line and "31" in line and "30" in line
    assert not out.exists() and not js.exists()
