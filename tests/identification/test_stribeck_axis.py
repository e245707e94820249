"""The friction map of a linear axis (load coordinates; issue 21 part 2, the EMPS case): a hand-made
record with a known Stribeck curve gives it back inside the 95 % intervals; the EMPS record's
plateaus (0.042..0.125 m/s) inform Coulomb and viscous per direction but not Stribeck, and
FIT.json says so under "friction_map"."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from prsa_ctrl.identification.axis import load_axis_plant
from prsa_ctrl.identification.friction_map import axis_friction_map

ROOT = Path(__file__).resolve().parents[2]
EMPS = ROOT / "examples" / "emps"
Z95 = 1.959963984540054
TRUTH = {"coulomb_positive_n": 20.0, "coulomb_negative_n": 23.0, "viscous_positive_n_s_per_m": 200.0,
         "viscous_negative_n_s_per_m": 180.0, "stribeck_excess_n": 8.0, "stribeck_velocity_m_s": 0.004}


@pytest.fixture(scope="module")
def axis_plant():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_axis_plant(EMPS / "plant.toml").to_plant()


def _curve(v):
    t = TRUTH
    g = math.exp(-((v / t["stribeck_velocity_m_s"]) ** 2))
    if v > 0:
        return t["coulomb_positive_n"] + t["stribeck_excess_n"] * g + t["viscous_positive_n_s_per_m"] * v
    return -(t["coulomb_negative_n"] + t["stribeck_excess_n"] * g) + t["viscous_negative_n_s_per_m"] * v


def _record(seed, ts=1e-3):
    """Speed plateaus from 0.25 to 10 Stribeck speeds in both directions, 0.6 s each, the force the
    curve plus AR(1) noise (a loop's ripple); positions integrate the speed exactly."""
    rng = np.random.default_rng(seed)
    speeds = [s * m * TRUTH["stribeck_velocity_m_s"] for s in (1, -1) for m in (0.25, 0.5, 1, 1.5, 2.5, 4, 10)]
    n = int(round(0.6 / ts))
    v = np.repeat(speeds, n)
    f = np.array([_curve(x) for x in v])
    e = np.zeros(len(v))
    for k in range(1, len(v)):
        e[k] = 0.7 * e[k - 1] + 0.3 * rng.standard_normal()
    pos = np.concatenate([[0.0], np.cumsum(v[:-1]) * ts])
    return ts * np.arange(len(v)), pos, f + e


def test_hand_made_stribeck_curve_inside_intervals(axis_plant):
    t, pos, force = _record(0)
    m = axis_friction_map("hand", t, pos, force, axis_plant)
    assert m["stribeck"] == "identified" and len(m["plateaus"]) == 14
    for k, want in TRUTH.items():
        p = m["parameters"][k]
        assert p["identified"] and p["ci95"][0] <= want <= p["ci95"][1], (k, p, want)
        assert p["ci95"][1] - p["ci95"][0] < 0.5 * want


def test_hand_made_coverage_over_seeds(axis_plant):
    """40 seeds: each parameter's 95 % interval holds the truth in at least 34 (85 %)."""
    hits = dict.fromkeys(TRUTH, 0)
    for seed in range(40):
        m = axis_friction_map("hand", *_record(seed), axis_plant)
        for k, want in TRUTH.items():
            lo, hi = m["parameters"][k]["ci95"]
            hits[k] += lo <= want <= hi
    assert min(hits.values()) >= 34, hits


def test_one_direction_gives_one_line(axis_plant):
    t, pos, force = _record(0)
    half = len(t) // 2
    m = axis_friction_map("half", t[:half], pos[:half], force[:half], axis_plant)
    assert m["stribeck"] == "not identified" and "in -x" in m["error"] and "\n" not in m["error"]


def test_emps_fit_json_friction_map(tmp_path, capsys):
    from prsa_ctrl.cli.fit import main

    out, js = tmp_path / "F.toml", tmp_path / "F.json"
    assert main([str(EMPS / "DATA_EMPS.mat"), "--log-format", str(EMPS / "log.toml"), "--out", str(out),
                 "--json", str(js)]) == 0
    text = capsys.readouterr().out
    assert "friction map of DATA_EMPS.mat (report; the replay model stays Coulomb + viscous)" in text
    fmap = json.loads(js.read_text())["friction_map"]["DATA_EMPS.mat"]
    assert fmap["stribeck"].startswith("not identified")
    p = fmap["parameters"]
    for k in ("coulomb_positive_n", "coulomb_negative_n", "viscous_positive_n_s_per_m", "viscous_negative_n_s_per_m"):
        assert p[k]["identified"] and p[k]["ci95"][0] < p[k]["value"] < p[k]["ci95"][1]
    for k in ("stribeck_excess_n", "stribeck_velocity_m_s"):
        assert not p[k]["identified"] and p[k]["value"] is None
    # the plateau means against the raw record (force = gain x controller output), numpy only
    from scipy.io import loadmat

    d = loadmat(EMPS / "DATA_EMPS.mat")
    t, force = d["t"].ravel(), d["gtau"].ravel()[0] * d["vir"].ravel()
    qm = d["qm"].ravel()
    speeds = sorted({round(abs(pl["speed_m_s"]), 2) for pl in fmap["plateaus"]})
    assert speeds == [0.04, 0.08, 0.12]  # the reference's 0.0421, 0.0825, 0.1247 m/s
    for pl in fmap["plateaus"]:
        i = int(np.argmin(np.abs(t - pl["start_s"])))
        j = int(np.argmin(np.abs(t - pl["stop_s"])))
        assert (qm[j] - qm[i]) / (t[j] - t[i]) == pytest.approx(pl["speed_m_s"], rel=1e-3)
        raw = float(np.mean(force[i:j]))
        assert pl["friction_n"] == pytest.approx(raw, abs=max(4 * pl["se_n"], 0.3))
