"""prsa-fit --frf: frequency-response files, the sampled model response and the FRF-only fit."""

import json
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from prsa_ctrl import load_plant
from prsa_ctrl.drive.pid import PID
from prsa_ctrl.identification.common import FRF_KEYS
from prsa_ctrl.identification.frf import fit_frf, frf_response
from prsa_ctrl.identification.timedomain import fit_plant
from prsa_ctrl.identification.data import DataError, FrfRecord, frf_from_arrays, load_frf

from test_fit import PERTURBED, toolkit_record  # noqa: E402

TS = 2.5e-4
PERIOD_S = 0.125  # multisine period: lines every 8 Hz
PERIODS = 4  # averaged periods (one more is simulated and dropped as the transient)
_RUNS: dict = {}  # simulated drive runs by FRF name, reused by the frf_from_record test


def measured_frf(truth, *, speed=30.0, load=800.0, f_max=600.0, seed=0, name=None) -> FrfRecord:
    """What a drive's built-in Bode measurement gives: a periodic multisine on the speed setpoint
    (closed loop), the FFT of the logged torque command and measured speed (backward difference of
    the 20-bit encoder angle) over whole periods, averaged; H1 and coherence at the excited lines.
    Simulated by the toolkit's sampled loop (rigid), not by the linear model that is fitted."""
    from prsa_ctrl.sim.engine import run

    n = int(round(PERIOD_S / TS))
    k = np.arange(1, int(f_max * PERIOD_S) + 1)
    k = k[k / PERIOD_S >= 8.0]
    ph = np.random.default_rng(seed).uniform(0, 2 * np.pi, len(k))
    t1 = np.arange(n) * TS
    ms = np.sum(np.sin(2 * np.pi * np.outer(t1, k / PERIOD_S) + ph), axis=1)
    sp = speed + 8.0 * np.tile(ms / np.max(np.abs(ms)), PERIODS + 1)
    t = np.arange(len(sp)) * TS
    r = run(truth, setpoint=list(zip(t.tolist(), sp.tolist())), load=load, duration=len(sp) * TS,
            controller=PID(0.05, 2.0), fidelity="rigid", discrete=True)
    _RUNS[name or f"frf-{seed}"] = r
    u = r.output("torque_command")[n:n * (PERIODS + 1)].reshape(PERIODS, n)
    y = r.output("speed_fd")[n:n * (PERIODS + 1)].reshape(PERIODS, n)
    uf, yf = np.fft.rfft(u, axis=1)[:, k], np.fft.rfft(y, axis=1)[:, k]
    suy = np.sum(np.conj(uf) * yf, 0)
    suu, syy = np.sum(np.abs(uf) ** 2, 0), np.sum(np.abs(yf) ** 2, 0)
    return frf_from_arrays(name or f"frf-{seed}", k / PERIOD_S, suy / suu, coherence=np.abs(suy) ** 2 / (suu * syy),
                           speed_rad_s=speed, load_n=load)


@pytest.fixture(scope="module")
def base():
    return load_plant()


@pytest.fixture(scope="module")
def measured(base):
    return {case: measured_frf(base.with_params(PERTURBED[case]), name=case) for case in PERTURBED}


# --- files ------------------------------------------------------------------------------------


def test_polar_and_cartesian_files_round_trip(tmp_path):
    f = np.geomspace(2, 400, 30)
    g = 1.0 / (2.4e-4 * 2j * np.pi * f + 1e-4) * np.exp(-2j * np.pi * f * 2.5e-4)
    coh = np.linspace(0.99, 0.5, 30)
    rec = frf_from_arrays("x", f, g, coherence=coh, speed_rad_s=20.0, load_n=500.0)
    assert rec.dropped == int(np.sum(coh < 0.8)) and rec.n == 30 - rec.dropped
    assert any("coherence below 0.8 dropped" in w for w in rec.warnings)
    rec.to_csv(tmp_path / "polar.csv")
    back = load_frf(tmp_path / "polar.csv", speed_rad_s=20.0, load_n=500.0, coherence_min=0.0)
    np.testing.assert_allclose(back.response, rec.response, rtol=1e-12)
    assert back.speed_rad_s == 20.0 and back.load_n == 500.0
    lines = ["# drive export", "frequency_hz,real,imag"] + [f"{float(a)!r},{float(b.real)!r},{float(b.imag)!r}" for a, b in zip(f, g)]
    (tmp_path / "cart.csv").write_text("\n".join(lines) + "\n")
    cart = load_frf(tmp_path / "cart.csv")
    np.testing.assert_allclose(cart.response, g, rtol=1e-15)
    assert cart.coherence is None and cart.dropped == 0


@pytest.mark.parametrize("text, match", [
    ("frequency_hz,magnitude_db\n1,2\n", "magnitude_db,phase_deg"),
    ("frequency_hz,magnitude_db,phase_deg,real,imag\n1,2,3,4,5\n", "one pair"),
    ("frequency_hz,gain_db,phase_deg\n1,2,3\n", "unknown column 'gain_db'"),
    ("frequency_hz,real,imag\n1,2,3\n2,2,nan\n", "line 3: imag = 'nan'; expected a finite number"),
    ("frequency_hz,real,imag\n1,2,3\n1,2,3\n3,1,1\n4,1,1\n5,1,1\n6,1,1\n", "line 3: 1.0 Hz after 1.0 Hz"),
    ("frequency_hz,real,imag\n-1,2,3\n", "line 2: -1.0 Hz"),
    ("frequency_hz,real,imag,coherence\n" + "".join(f"{i},1,1,0.5\n" for i in range(1, 9)), "0 frequency points left"),
    ("frequency_hz,real,imag,coherence\n1,1,1,1.5\n", "column 'coherence' line 2: 1.5"),
])
def test_bad_frf_files_one_line(tmp_path, text, match):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(DataError, match=match) as err:
        load_frf(p)
    assert str(p) in str(err.value) and "\n" not in str(err.value)


def test_nyquist_checked():
    with pytest.raises(DataError, match="Nyquist"):
        frf_from_arrays("x", np.linspace(10, 2500, 10), np.ones(10), sample_time_s=2.5e-4)


# --- model response ---------------------------------------------------------------------------


def test_model_response_is_the_inertia_and_current_loop(base):
    """Continuous response: 1/(J s + b) times the first-order current loop, to 1e-3."""
    f = np.array([5.0, 50.0, 500.0])
    g = frf_response(base, f, sample_time_s=0.0)
    s = 2j * np.pi * f
    wc = 2 * np.pi * base.values["drive.current_loop_bandwidth_hz"]
    ideal = 1.0 / (base.reflected_inertia_kg_m2 * s) * wc / (s + wc)
    np.testing.assert_allclose(np.abs(g / ideal), 1.0, atol=1e-2)
    # The sampled response adds the hold and the backward difference: about one sample of delay.
    gs = frf_response(base, f)
    extra = np.angle(gs / g)
    np.testing.assert_allclose(extra, -2 * np.pi * f * TS, rtol=0.02)


def test_sampled_model_matches_simulated_measurement(base, measured):
    """The fitted model's sampled response is what the simulated drive measures (truth plant)."""
    truth = base.with_params(PERTURBED["issue"])
    fr = measured["issue"]
    g = frf_response(truth, fr.frequency_hz, speed_rad_s=fr.speed_rad_s, load_n=fr.load_n)
    assert np.median(np.abs(fr.response / g - 1)) < 0.005
    assert np.max(np.abs(fr.response / g - 1)) < 0.03


# --- FRF-only fit -----------------------------------------------------------------------------


@pytest.mark.parametrize("case", list(PERTURBED))
def test_frf_only_fit_recovers_inertia_and_bandwidth(base, measured, case):
    truth = base.with_params(PERTURBED[case])
    res = fit_frf([measured[case]], base)
    assert res.keys == FRF_KEYS
    j = res.reflected_inertia_kg_m2
    assert abs(j["value"] / truth.reflected_inertia_kg_m2 - 1) < 0.05  # issue 11: within 5 %
    bw = res.parameters["drive.current_loop_bandwidth_hz"]
    assert abs(bw["value"] / truth.values["drive.current_loop_bandwidth_hz"] - 1) < 0.15  # within 15 %
    assert j["ci95"][0] < j["value"] < j["ci95"][1]
    assert res.fit_percent[case] > 95.0
    # Not fitted: the base plant's values, and the fitted plant carries the fit's sources.
    assert res.plant.values["friction.efficiency"] == base.values["friction.efficiency"]
    assert res.plant.sources["nut.inertia_kg_m2"].startswith(f"fit: {case} (95 % CI ")


def test_frf_ci_is_honest_on_a_noisy_measurement(base):
    """Multiplicative noise on the response (3 % RMS, seeded): the truth lies within the CIs and the
    CIs are wider than the error they must cover, but not absurdly wide."""
    truth = base.with_params(PERTURBED["issue"])
    f = np.arange(8.0, 600.0, 8.0)
    g = frf_response(truth, f, speed_rad_s=30.0, load_n=800.0)
    rng = np.random.default_rng(3)
    noisy = g * np.exp(0.03 * (rng.standard_normal(len(f)) + 1j * rng.standard_normal(len(f))))
    res = fit_frf([frf_from_arrays("noisy", f, noisy, speed_rad_s=30.0, load_n=800.0)], base)
    for k in FRF_KEYS:
        lo, hi = res.parameters[k]["ci95"]
        assert lo <= truth.values[k] <= hi, k
        assert (hi - lo) / truth.values[k] < 0.2


def test_frf_validates_a_time_domain_fit(base, measured):
    truth = base.with_params(PERTURBED["issue"])
    recs = [toolkit_record(truth, k) for k in ("multisine", "load-steps")]
    res = fit_plant(recs, base, frf=[measured["issue"]])
    assert res.fit_percent["issue"] > 95.0
    tr = res.traces["issue"]
    assert tr["model"].shape == tr["measured"].shape == measured["issue"].frequency_hz.shape


def test_frf_fit_bad_arguments(base, measured):
    with pytest.raises(ValueError, match="at least one frequency response"):
        fit_frf([], base)
    with pytest.raises(ValueError, match="fit key 'nut.mass'"):
        fit_frf([measured["issue"]], base, keys=["nut.mass"])


def test_cli_frf_only_writes_plant_json_and_bode(base, measured, tmp_path):
    from prsa_ctrl.cli.fit import main

    fr = measured["light-fast"]
    path = tmp_path / "bode.csv"
    fr.to_csv(path)
    out, rep, plots = tmp_path / "frf-fit.toml", tmp_path / "r.json", tmp_path / "figs"
    assert main(["--frf", str(path), "--frf-load", "800", "--out", str(out), "--json", str(rep),
                 "--plots", str(plots)]) == 0
    report = json.loads(rep.read_text())
    assert set(report["parameters"]) == set(FRF_KEYS)
    truth = base.with_params(PERTURBED["light-fast"])
    assert abs(report["reflected_inertia_kg_m2"]["value"] / truth.reflected_inertia_kg_m2 - 1) < 0.05
    doc = tomllib.loads(out.read_text())
    assert doc["drive"]["current_loop_bandwidth_hz"]["source"].startswith(f"fit: {path} (95 % CI ")
    assert doc["uncertainty"]["drive.current_loop_bandwidth_hz"]["dist"] == "normal"
    assert [p.name for p in plots.iterdir()] == ["bode-bode.png"]
    assert (plots / "bode-bode.png").stat().st_size > 10_000
    assert math.isfinite(report["fit_percent"][str(path)])


def test_frf_from_a_logged_periodic_record(base, measured):
    """frf_from_record on the drive's log gives the same response as the FFT written in this test."""
    from prsa_ctrl.identification.data import frf_from_record, record_from_arrays

    truth = base.with_params(PERTURBED["issue"])
    r = _RUNS["issue"]  # the drive run behind measured["issue"]
    theta = r.states[r.state_labels.index("theta_nut")]
    q = 2 * math.pi / truth.encoder_counts
    rec = record_from_arrays("log", r.time, r.output("torque_command"), nut_angle_rad=np.floor(theta / q) * q,
                             axial_load_n=r.inputs[1])
    fr = frf_from_record(rec, PERIOD_S, f_max_hz=600.0)
    ref = measured["issue"]
    assert fr.n == ref.n and np.allclose(fr.frequency_hz, ref.frequency_hz)
    assert np.median(np.abs(fr.response / ref.response - 1)) < 0.01
    assert abs(fr.speed_rad_s - 30.0) < 0.5 and fr.load_n == 800.0
    with pytest.raises(DataError, match="fewer than 3 periods"):
        frf_from_record(rec, 1.0)



def test_cli_frf_bad_input_exit_2_nothing_written(tmp_path, capsys):
    from prsa_ctrl.cli.fit import main

    bad = tmp_path / "bode.csv"
    bad.write_text("frequency_hz,magnitude_db,phase_deg\n10,20,-90\n5,14,-91\n")
    out = tmp_path / "o.toml"
    assert main(["--frf", str(bad), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(bad) in err and "line 3" in err
    assert main(["--frf", str(bad), "--out", str(out), "--coherence-min", "1.5"]) == 2
    assert "--coherence-min" in capsys.readouterr().err
    assert main(["--frf", str(bad), "--validate", str(bad), "--out", str(out)]) == 2
    assert main(["--frf", str(bad), "--out", str(out), "--plots", str(bad)]) == 2  # a file, not a directory
    assert "--plots" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bode.csv"]


@pytest.mark.parametrize("logged,samples,n_written", [
    ("applied", 1.9996, 2), ("applied", 2.0004, 2), ("computed", 2.9995, 2), ("applied", 2.4, 2), ("applied", 2.6, 3),
    ("computed", 0.98, 0)])
def test_write_delay_takes_the_nearest_whole_sample_and_lumps_the_remainder_into_the_lag(logged, samples, n_written):
    """A fitted delay a hair under two samples is two samples (the floor wrote one and put a whole
    sample into the current loop, 322 Hz against a true 650 Hz on a foreign roller screw); the
    remainder, of either sign, moves the written bandwidth by exactly the lag it stands for."""
    import warnings as _w

    from prsa_ctrl.identification.frf import write_delay

    with _w.catch_warnings():
        _w.simplefilter("ignore")
        base = load_plant("ballscrew-32x10").with_params({"drive.current_loop_bandwidth_hz": 1000.0})
    ts = base.sample_time_s
    warns = []
    out, d = write_delay(base, {"value": samples * ts, "ci95": [samples * ts, samples * ts]}, ts, logged, warns)
    assert out.values["drive.command_delay_samples"] == n_written
    rest = samples * ts - ({"applied": 0, "computed": 1}[logged] + n_written) * ts
    assert abs(rest) <= 0.5 * ts + 1e-15
    # the written lag is the fitted current loop's plus the remainder, independently recomputed
    assert 1.0 / (2 * math.pi * out.values["drive.current_loop_bandwidth_hz"]) == pytest.approx(
        1.0 / (2 * math.pi * 1000.0) + rest, rel=1e-9)
    assert d["written"]["drive.command_delay_samples"] == n_written
    assert not warns
