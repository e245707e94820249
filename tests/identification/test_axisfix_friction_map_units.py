"""The linear-axis friction map (identification/friction_map.axis_friction_map) reports its
plateaus under load-coordinate names (m/s, N) and warns when the reduced chi-square of the curve
exceeds 4 (recomputed here from the plateau table and the reported curve, numpy only)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from prsa_ctrl.identification.friction_map import axis_friction_map

from test_stribeck_axis import _record, axis_plant  # noqa: F401,E402  (fixture; tests/identification on sys.path)


def _chi2(m):
    """Reduced chi-square of the reported curve on the reported plateaus."""
    p = {k: (e["value"] or 0.0) for k, e in m["parameters"].items()}
    vs = p["stribeck_velocity_m_s"] or 1.0
    r = []
    for pl in m["plateaus"]:
        v = pl["speed_m_s"]
        g = math.exp(-((v / vs) ** 2))
        f = (p["coulomb_positive_n"] + p["stribeck_excess_n"] * g + p["viscous_positive_n_s_per_m"] * v if v > 0
             else -(p["coulomb_negative_n"] + p["stribeck_excess_n"] * g) + p["viscous_negative_n_s_per_m"] * v)
        r.append((f - pl["friction_n"]) / pl["se_n"])
    free = sum(e["value"] is not None for e in m["parameters"].values())
    return float(np.sum(np.square(r)) / (len(r) - free))


def test_plateaus_in_load_units_and_no_warning_on_a_good_fit(axis_plant):  # noqa: F811
    m = axis_friction_map("hand", *_record(0), axis_plant)
    for pl in m["plateaus"]:
        assert {"speed_m_s", "force_n", "friction_n", "se_n"} <= set(pl)
        assert not {"speed_rad_s", "motor_torque_n_m", "friction_n_m", "se_n_m"} & set(pl)
    assert m["chi2_reduced"] == pytest.approx(_chi2(m), rel=1e-6)
    assert m["chi2_reduced"] < 4 and m["warnings"] == []


def test_a_bad_curve_fit_warns_above_four(axis_plant):  # noqa: F811
    t, pos, force = _record(0)
    v = np.gradient(pos, t)
    force = force + 6.0 * (np.abs(v) > 0.035)  # the two fastest plateaus off the friction law by 6 N
    m = axis_friction_map("bumpy", t, pos, force, axis_plant)
    chi2 = _chi2(m)
    assert m["chi2_reduced"] == pytest.approx(chi2, rel=1e-6) and chi2 > 4
    assert len(m["warnings"]) == 1 and f"{chi2:.3g}" in m["warnings"][0] and "bumpy" in m["warnings"][0]


def test_emps_fit_json_carries_the_friction_map_warning(tmp_path, capsys):
    from test_stribeck_axis import EMPS

    from prsa_ctrl.cli.fit import main

    js = tmp_path / "F.json"
    assert main([str(EMPS / "DATA_EMPS.mat"), "--log-format", str(EMPS / "log.toml"), "--out", str(tmp_path / "F.toml"),
                 "--json", str(js)]) == 0
    import json

    rep = json.loads(js.read_text())
    fmap = rep["friction_map"]["DATA_EMPS.mat"]
    assert fmap["chi2_reduced"] == pytest.approx(_chi2(fmap), rel=1e-6) and fmap["chi2_reduced"] > 4  # 6.96
    assert fmap["warnings"] and fmap["warnings"][0] in rep["warnings"]
    assert f"warning: {fmap['warnings'][0]}" in capsys.readouterr().out


def test_empty_or_mismatched_arrays_are_one_value_error(axis_plant):  # noqa: F811
    """Was: a raw numpy error from deep inside the plateau search."""
    t, pos, force = _record(0)
    for args, expect in ((([], [], []), r"shapes \(0,\), \(0,\), \(0,\)"),
                         ((t, pos[:-1], force), "expected one-dimensional arrays of one length"),
                         ((t, pos, np.where(np.arange(t.size) == 7, np.nan, force)), r"force_n\[7\] = nan")):
        with pytest.raises(ValueError, match=expect):
            axis_friction_map("bad", *args, axis_plant)
