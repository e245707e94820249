"""Acceptance "Foreign logs" of issue 21: logs written by an independent drive simulator
(foreign_generator.py: numpy/scipy only, not the toolkit's simulator) with a transport delay and
the computation delay, asymmetric Stribeck friction, encoder quantisation, a closed PI speed
loop, load steps 500 -> 1500 -> 0 N, a speed staircase through both directions and a multisine.

The fit must converge, find the delay, get the current-loop bandwidth within 10 % and hold the
truth in its 95 % intervals; a log whose command convention is off by one sample is detected.
The 20-seed coverage study is ``-m slow``; the default run fits one seed.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from prsa_ctrl.identification.common import DEFAULT_KEYS
from prsa_ctrl.identification.data import record_from_arrays
from prsa_ctrl.identification.timedomain import fit_plant
from prsa_ctrl.plant import load_plant

import foreign_generator as fg  # noqa: E402  (tests/identification is on sys.path)

BW = "drive.current_loop_bandwidth_hz"
DELAY = "drive.command_delay_samples"


@pytest.fixture(scope="module")
def base():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_plant()


def _axis(base, **kw):
    return fg.Axis(lead_m_per_rad=base.lead_per_rad, counts_per_rev=base.encoder_counts, **kw)


def _truth(base, ax: fg.Axis) -> dict:
    """The generator's axis in plant keys: the nut inertia is the total less what the rest of
    the base plant's mechanism reflects (rollers, cage, translating screw)."""
    rest = base.reflected_inertia_kg_m2 - base.values["nut.inertia_kg_m2"]
    return {"nut.inertia_kg_m2": ax.inertia_kg_m2 - rest, "friction.efficiency": ax.efficiency,
            "friction.no_load_torque_n_m": ax.no_load_torque_n_m,
            "friction.viscous_n_m_s_per_rad": ax.viscous_n_m_s_per_rad, BW: ax.bandwidth_hz,
            "friction.torque_offset_n_m": ax.offset_torque_n_m}


def _records(logs):
    return [record_from_arrays(lg.name, lg.time_s, lg.command_n_m, nut_angle_rad=lg.angle_rad, axial_load_n=lg.load_n)
            for lg in logs]


def _fit(base, ax, seed, duration_s=1.5, convention="applied", command_logged="applied", **kw):
    truth = _truth(base, ax)
    recs = _records(fg.logs(ax, seed, duration_s=duration_s, convention=convention))
    res = fit_plant(recs, base, keys=tuple(truth), delay_samples="find", command_logged=command_logged, **kw)
    return res, truth


_ONE_SEED: dict = {}


def one_seed_fit(base):
    """``(axis, result, truth)`` of the default run's one-seed fit (seed 3, 0.5 s of each of the
    three logs, one sample of transport delay), made once per session and shared by
    test_one_seed_all_three_logs and the covariance tests of tests/identification/test_common.py."""
    if not _ONE_SEED:
        ax = _axis(base, transport_samples=1)
        _ONE_SEED["fit"] = (ax, *_fit(base, ax, seed=3, duration_s=0.5))
    return _ONE_SEED["fit"]


def _z(res, truth) -> dict:
    """(fitted - true) in standard errors of the fit (half the 95 % interval / 1.96)."""
    out = {}
    for k, v in truth.items():
        lo, hi = res.parameters[k]["ci95"]
        out[k] = (res.parameters[k]["value"] - v) / max((hi - lo) / (2 * 1.959964), 1e-300)
    return out


def test_generator_is_independent_and_physical(base):
    """The generator's own checks: at constant speed and load its steady torque is the
    screw's (load / efficiency + Coulomb level + offset + viscous); the log is quantised."""
    ax = _axis(base, transport_samples=1)
    n = 2000
    log = fg.simulate(ax, np.full(n, 40.0), np.full(n, 1000.0), seed=1)
    steady = ax.lead_m_per_rad * 1000.0 / ax.efficiency + ax.no_load_torque_n_m + ax.offset_torque_n_m \
        + ax.viscous_n_m_s_per_rad * 40.0
    assert np.mean(log.command_n_m[n // 2:]) == pytest.approx(steady, rel=2e-3)
    q = 2 * math.pi / ax.counts_per_rev
    assert np.allclose(np.round(log.angle_rad / q) * q, log.angle_rad, rtol=0, atol=1e-12)
    # the computed command leads the applied one by exactly one sample
    log_c = fg.simulate(ax, np.full(n, 40.0), np.full(n, 1000.0), seed=1, convention="computed")
    np.testing.assert_array_equal(log_c.command_n_m[:-1], log.command_n_m[1:])


def test_one_seed_all_three_logs(base):
    """Load steps, staircase and multisine together (the issue: the fit stalled on the first
    two and put 650 Hz at 334 Hz on the third): converged, delay 1 sample found, bandwidth
    within 10 %, every key within 4 standard errors of the truth."""
    ax, res, truth = one_seed_fit(base)
    cd = res.solver["command_delay"]
    assert res.solver["status"] == "converged"
    assert cd["shift_samples"] == 1 and cd["search"]["decided"] and res.plant.values[DELAY] == 1
    assert res.plant.sources[DELAY].startswith("fit: found")
    obj = cd["search"]["objective"]
    assert obj["0"] > 10 * obj["1"]  # the delay-free hypothesis fits far worse
    assert abs(res.parameters[BW]["value"] / ax.bandwidth_hz - 1) < 0.10
    z = _z(res, truth)
    assert all(abs(v) < 4 for v in z.values()), z


def test_command_logged_as_computed_is_detected(base):
    """The issue's second case: a drive logging the command as computed, true 1100 Hz and no
    transport delay. Said to be 'applied' (the default), the fit finds the extra sample, keeps
    the bandwidth right and warns with the other convention's reading; said to be 'computed', the
    plant gets no command delay."""
    ax = _axis(base, transport_samples=0, bandwidth_hz=1100.0)
    n = 2000
    sp, ld = fg.multisine(n, ax.sample_time_s, seed=5)
    log = fg.simulate(ax, sp, ld, seed=5, name="ms-computed", convention="computed")
    rec = _records([log])
    keys = DEFAULT_KEYS  # what prsa-fit fits by default
    res = fit_plant(rec, base, keys=keys, delay_samples="find")
    assert res.solver["command_delay"]["shift_samples"] == 1
    assert res.plant.values[DELAY] == 1
    assert abs(res.parameters[BW]["value"] / 1100.0 - 1) < 0.10
    assert any("--command-logged computed" in w and "it is 0" in w for w in res.warnings)
    # the old behaviour, a fixed shift of 0, fits far worse (it reported 592 Hz for this case)
    obj = res.solver["command_delay"]["search"]["objective"]
    assert obj["0"] > 10 * obj["1"]
    res_c = fit_plant(rec, base, keys=keys, delay_samples=1, command_logged="computed")
    assert res_c.plant.values[DELAY] == 0 and abs(res_c.parameters[BW]["value"] / 1100.0 - 1) < 0.10


def test_computed_with_too_short_a_delay_refused(base):
    """A log said to hold the computed command whose command acts at once is contradictory."""
    from prsa_ctrl.errors import FitError

    ax = _axis(base, transport_samples=0, bandwidth_hz=1100.0)
    # 600 samples of the multisine (was 2000): the refusal is reached the same way (the fit from
    # 1 sample on fails, the one at 0 samples converges) and its message is the same; the
    # contradiction is in the first sample of delay, not in the record's length
    n = 600
    sp, ld = fg.multisine(n, ax.sample_time_s, seed=6)
    rec = _records([fg.simulate(ax, sp, ld, seed=6, convention="applied")])
    with pytest.raises(FitError, match="--command-logged applied"):
        fit_plant(rec, base, delay_samples="find", command_logged="computed")
    with pytest.raises(ValueError, match="command_logged = 'applied'"):  # refused before any fit
        fit_plant(rec, base, delay_samples=0, command_logged="computed")


@pytest.mark.slow
def test_coverage_over_20_seeds(base):
    """The acceptance numbers: every key's truth inside its 95 % interval for >= 18 of 20 seeds,
    the bandwidth within 10 % and the delay found in every seed.

    Jointly: the truth of all six keys inside the joint 95 % confidence region (the ellipsoid
    ``FitResult.joint_distance2 <= chi2(6).ppf(0.95)``) for >= 18 of 20 seeds. The box of the six
    marginal intervals is reported but not held to 95 %: with independent estimates it holds
    the truth 0.95^6 = 74 % of the time. No bias: over the 20 seeds each key's mean z-score
    (error over its standard error) lies within 3 / sqrt(20) of 0, and the mean squared
    distance within 3 standard deviations of chi2(6)'s mean 6 (sd sqrt(12 / 20)).
    Measured (2026-11-24): per key 20/18/18/18/18/19, box 13, ellipsoid 19, mean z -0.27..0.19,
    mean distance 6.44."""
    from scipy.stats import chi2

    ax = _axis(base, transport_samples=1)
    keys = list(_truth(base, ax))
    inside = {k: 0 for k in keys}
    box = ellipsoid = 0
    zs, d2s = [], []
    limit = chi2(len(keys)).ppf(0.95)
    for seed in range(20):
        res, truth = _fit(base, ax, seed)
        assert res.solver["command_delay"]["shift_samples"] == 1, seed
        assert abs(res.parameters[BW]["value"] / ax.bandwidth_hz - 1) < 0.10, seed
        ins = {k: res.parameters[k]["ci95"][0] <= v <= res.parameters[k]["ci95"][1] for k, v in truth.items()}
        for k in keys:
            inside[k] += ins[k]
        box += all(ins.values())
        d2 = res.joint_distance2(truth)
        ellipsoid += d2 <= limit
        zs.append([_z(res, truth)[k] for k in keys])
        d2s.append(d2)
    mean_z = {k: round(float(m), 3) for k, m in zip(keys, np.mean(zs, axis=0))}
    print(f"per key {inside}; joint box {box}/20; joint ellipsoid {ellipsoid}/20; mean z {mean_z}; "
          f"mean distance^2 {np.mean(d2s):.3f}")
    assert all(c >= 18 for c in inside.values()), inside
    assert ellipsoid >= 18, (ellipsoid, d2s)
    assert all(abs(m) < 3 / math.sqrt(20) for m in mean_z.values()), mean_z
    assert abs(np.mean(d2s) - len(keys)) < 3 * math.sqrt(2 * len(keys) / 20), d2s


def test_cli_writes_the_found_delay(base, tmp_path, capsys):
    """prsa-fit on a foreign log: the found delay is in the plant file prsa-tune loads, the
    convention flag moves it by one sample, a bad convention is one line and exit 2."""
    import tomllib

    from prsa_ctrl.cli.fit import main

    ax = _axis(base, transport_samples=1, bandwidth_hz=900.0)
    n = 2000
    sp, ld = fg.multisine(n, ax.sample_time_s, seed=8)
    log = fg.simulate(ax, sp, ld, seed=8, convention="computed")
    csv = tmp_path / "log.csv"
    np.savetxt(csv, np.column_stack([log.time_s, log.command_n_m, log.angle_rad, log.load_n]), delimiter=",",
               header="time_s,torque_command_n_m,nut_angle_rad,axial_load_n", comments="", fmt="%.17g")
    out = tmp_path / "fit.toml"
    assert main([str(csv), "--out", str(out), "--command-logged", "computed"]) == 0
    text = capsys.readouterr().out
    assert "command delay: 2 sample(s)" in text and "drive.command_delay_samples = 1" in text
    doc = tomllib.loads(out.read_text())
    assert doc["drive"]["command_delay_samples"]["value"] == 1
    fitted = load_plant(out)
    assert fitted.command_delay_samples == 1
    assert abs(fitted.values[BW] / 900.0 - 1) < 0.10
    bad = tmp_path / "bad.toml"
    assert main([str(csv), "--out", str(bad), "--command-logged", "sometimes"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--command-logged" in err and not bad.exists()
