"""prsa-fit: grey-box calibration round trips (toolkit and independent data), CIs, CLI."""

import json
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from prsa_ctrl import load_plant
from prsa_ctrl.drive.pid import PID
from prsa_ctrl.errors import FitError
from prsa_ctrl.identification.common import DEFAULT_KEYS
from prsa_ctrl.identification.timedomain import fit_plant
from prsa_ctrl.identification.data import design_excitation, record_from_arrays

from independent_actuator import simulate_independent  # noqa: E402

TS = 2.5e-4
DURATION = 0.3  # s per experiment (1200 samples at 4 kHz)
ANGLE_NOISE_RAD = 1e-5  # encoder interpolation noise on top of the 20-bit quantisation

PERTURBED = {
    # the case: inertia -25 %, efficiency 0.88, no-load 0.03, viscous 1.5e-4, current loop 1200 Hz
    "issue": {"nut.inertia_kg_m2": 1.5e-4, "friction.efficiency": 0.88, "friction.no_load_torque_n_m": 0.03,
              "friction.viscous_n_m_s_per_rad": 1.5e-4, "drive.current_loop_bandwidth_hz": 1200.0},
    # other directions
    "heavy-lossy": {"nut.inertia_kg_m2": 2.6e-4, "friction.efficiency": 0.78, "friction.no_load_torque_n_m": 0.012,
                    "friction.viscous_n_m_s_per_rad": 6e-5, "drive.current_loop_bandwidth_hz": 700.0},
    "light-fast": {"nut.inertia_kg_m2": 1.2e-4, "friction.efficiency": 0.92, "friction.no_load_torque_n_m": 0.05,
                   "friction.viscous_n_m_s_per_rad": 2.5e-4, "drive.current_loop_bandwidth_hz": 1600.0},
}


def toolkit_record(plant, kind, seed=0, name=None):
    """One closed-loop experiment simulated by the toolkit (rigid, sampled PI at 4 kHz) as a Record.

    ``kind``: ``multisine`` (speed multisine at a constant 800 N), ``load-steps`` (constant speed,
    load steps 200/1500/300/2500 N), ``staircase`` (speed levels through both directions, 800 N).
    The recorded angle is the 20-bit encoder angle of the state plus Gaussian encoder noise.
    This is the one place that turns a simulation into measured data (switch here when the
    simulator's outputs change).
    """
    from prsa_ctrl.sim.engine import run

    if kind == "multisine":
        t, v = design_excitation("multisine", duration_s=DURATION, sample_time_s=2.5e-3, f_min_hz=5, f_max_hz=150,
                                 amplitude=20, offset=30, seed=seed)
        setpoint, load = list(zip(t.tolist(), v.tolist())), 800.0
    elif kind == "load-steps":
        setpoint = 30.0
        load = [(0.0, 200.0), (0.075, 1500.0), (0.15, 300.0), (0.225, 2500.0)]
    elif kind == "staircase":
        t, v = design_excitation("steps", duration_s=DURATION, sample_time_s=2.5e-3, amplitude=10, offset=20)
        setpoint, load = list(zip(t.tolist(), v.tolist())), 800.0
    else:
        raise ValueError(kind)
    r = run(plant, setpoint=setpoint, load=load, duration=DURATION, controller=PID(0.05, 2.0), fidelity="rigid",
            discrete=True)
    theta = r.states[r.state_labels.index("theta_nut")]
    q = 2 * math.pi / plant.encoder_counts
    rng = np.random.default_rng(seed)
    angle = np.floor((theta + ANGLE_NOISE_RAD * rng.standard_normal(theta.shape)) / q) * q
    return record_from_arrays(name or f"{kind}-{seed}", r.time, r.output("torque_command"), nut_angle_rad=angle,
                              axial_load_n=r.inputs[1])


def _experiments(truth, seed=0):
    return [toolkit_record(truth, k, seed) for k in ("multisine", "load-steps", "staircase")]


def _check_accuracy(result, truth):
    p = result.parameters
    j_true = truth.reflected_inertia_kg_m2
    assert abs(result.reflected_inertia_kg_m2["value"] / j_true - 1) < 0.03
    assert abs(p["nut.inertia_kg_m2"]["value"] / truth.values["nut.inertia_kg_m2"] - 1) < 0.03
    assert abs(p["friction.efficiency"]["value"] - truth.values["friction.efficiency"]) < 0.02
    bw = truth.values["drive.current_loop_bandwidth_hz"]
    assert abs(p["drive.current_loop_bandwidth_hz"]["value"] / bw - 1) < 0.10


@pytest.fixture(scope="module")
def base():
    return load_plant()


def _z_scores(result, truth):
    """(fitted - truth) / (CI half-width / 1.96) per fitted key."""
    out = {}
    for k, v in result.parameters.items():
        lo, hi = v["ci95"]
        out[k] = (v["value"] - truth.values[k]) / ((hi - lo) / 2 / 1.959963984540054)
    return out


@pytest.mark.parametrize("case", [
    "issue",
    "heavy-lossy",
    # the third direction takes a second solver attempt (~10 s): with the slow studies
    pytest.param("light-fast", marks=pytest.mark.slow),
])
def test_toolkit_round_trip(base, case):
    truth = base.with_params(PERTURBED[case])
    result = fit_plant(_experiments(truth), base)
    assert result.solver["status"] == "converged"
    _check_accuracy(result, truth)
    # The fitted plant is the base plant with exactly the fitted values, each with its fit source.
    for k in DEFAULT_KEYS:
        assert result.plant.values[k] == result.parameters[k]["value"]
        assert result.plant.sources[k].startswith("fit: multisine-0, load-steps-0, staircase-0 (95 % CI ")
        lo, hi = result.parameters[k]["ci95"]
        assert lo < result.parameters[k]["value"] < hi
    # Honest intervals: every estimate within 3.5 of its own standard errors of the truth (the
    # white-residual intervals of the first version were off by 4 to 30 standard errors here).
    z = _z_scores(result, truth)
    assert all(abs(v) < 3.5 for v in z.values()), z
    assert not any("too narrow" in w for w in result.warnings)
    # Standstill and reversals of the staircase are left out and said so.
    assert result.solver["left_out_samples"] > 0
    assert any("left out" in w for w in result.warnings)
    assert all(f > 95.0 for f in result.fit_percent.values())
    corr = result.correlation
    assert corr.shape == (5, 5) and np.allclose(np.diag(corr), 1.0) and np.allclose(corr, corr.T)


def test_reversals_left_out_and_segments_cut_there(base):
    """The staircase reverses faster than one sample: the sign change alone marks it, and no
    segment spans a reversal."""
    from prsa_ctrl.identification.common import default_min_speed
    from prsa_ctrl.identification.shooting import reference_trajectory, shooting_segments

    truth = base.with_params(PERTURBED["issue"])
    rec = toolkit_record(truth, "staircase")
    ref = reference_trajectory(rec, base)
    segs, left = shooting_segments([rec], 400, [ref], default_min_speed(base))
    v = rec.speed_rad_s
    for sg in segs:
        seg_v = v[sg.k0:sg.k0 + sg.n]
        assert np.all(seg_v > 0) or np.all(seg_v < 0)
        assert np.min(np.abs(seg_v)) > 0.5 * default_min_speed(base)
    assert 0 < left < 0.3 * (rec.n - 1)
    segs0, left0 = shooting_segments([rec], 400, [ref], 0.0)
    assert left0 == 0 and sum(sg.n for sg in segs0) == rec.n - 1
    with pytest.raises(ValueError, match="min_speed_rad_s = -1"):
        fit_plant([rec], base, min_speed_rad_s=-1.0)


def test_coloured_noise_widens_the_intervals(base):
    """Strongly coloured angle noise (AR(1), pole 0.95): the HAC covariance widens the intervals
    several times over the white-noise ones and the report warns that they stay optimistic."""
    from scipy.signal import lfilter

    truth = base.with_params(PERTURBED["issue"])
    start = truth.with_params({"nut.inertia_kg_m2": 1.8e-4, "drive.current_loop_bandwidth_hz": 1000.0})
    rec0 = toolkit_record(truth, "multisine")
    col = lfilter([0.05], [1, -0.95], np.random.default_rng(101).standard_normal(rec0.n)) * 2e-4
    rec = record_from_arrays("coloured", rec0.time_s, rec0.torque_command_n_m, nut_angle_rad=rec0.nut_angle_rad + col,
                             axial_load_n=rec0.axial_load_n)
    keys = ["nut.inertia_kg_m2", "drive.current_loop_bandwidth_hz"]
    res = fit_plant([rec], start, keys=keys)
    assert res.solver["ci_widening_vs_white"] > 2.0
    assert res.solver["residual_autocorrelation_lag1"] > 0.5
    assert any("strongly coloured" in w for w in res.warnings)
    white = fit_plant([rec0], start, keys=keys)
    assert white.solver["ci_widening_vs_white"] < 1.3
    assert not any("strongly coloured" in w for w in white.warnings)
    for k in keys:
        lo, hi = res.parameters[k]["ci95"]
        assert lo <= truth.values[k] <= hi


def test_independent_generator_is_fitted(base):
    truth = base.with_params(PERTURBED["issue"])
    n = int(round(0.4 / TS))
    t = np.arange(n) * TS
    _, sp = design_excitation("multisine", duration_s=n * TS, sample_time_s=TS, f_min_hz=5, f_max_hz=150,
                              amplitude=20, offset=30)
    load = np.select([t < 0.1, t < 0.2, t < 0.3], [200.0, 1500.0, 300.0], 2500.0)
    d = simulate_independent(
        inertia_kg_m2=truth.reflected_inertia_kg_m2, lead_m=truth.lead_m, efficiency=0.88, no_load_torque_n_m=0.03,
        viscous_n_m_s_per_rad=1.5e-4, current_loop_bandwidth_hz=1200.0, torque_limit_n_m=truth.torque_limit,
        setpoint_rad_s=sp, load_n=load, sample_time_s=TS, seed=1)
    rec = record_from_arrays("independent", d["time_s"], d["torque_command_n_m"], nut_angle_rad=d["nut_angle_rad"],
                             axial_load_n=d["axial_load_n"])
    result = fit_plant([rec], base)
    _check_accuracy(result, truth)
    assert abs(result.parameters["friction.no_load_torque_n_m"]["value"] - 0.03) < 0.005
    # Model error (other friction smoothing, noisy load input) makes the residual coloured: the
    # HAC intervals widen many times over the white-noise ones and still hold the truth.
    assert result.solver["ci_widening_vs_white"] > 5.0
    assert any("strongly coloured" in w for w in result.warnings)
    for k in DEFAULT_KEYS:
        lo, hi = result.parameters[k]["ci95"]
        assert lo <= truth.values[k] <= hi, k


def test_constant_load_leaves_efficiency_unidentified(base):
    truth = base.with_params(PERTURBED["issue"])
    result = fit_plant([toolkit_record(truth, "multisine")], base)
    text = " ".join(result.warnings)
    assert "friction.efficiency" in text
    # but the inertia and the current loop are still found
    assert abs(result.parameters["nut.inertia_kg_m2"]["value"] / 1.5e-4 - 1) < 0.03
    # Review finding 2: what the data cannot inform keeps the base value and source; the report says why.
    p = result.parameters
    assert p["friction.efficiency"]["kept_base"] and "friction.efficiency" in result.kept_base
    assert any(w in p["friction.efficiency"]["reason"] for w in ("physical range", "bound", "correlated"))
    assert not p["nut.inertia_kg_m2"]["kept_base"] and "nut.inertia_kg_m2" in result.plant_keys
    for k in result.kept_base:
        assert result.plant.values[k] == base.values[k] == p[k]["written"]
        assert result.plant.sources[k] == base.sources[k] and k not in result.plant_keys
        assert result.plant.uncertainty.get(k) == base.uncertainty.get(k)  # the base's entry, not the fit's
    assert result.plant.values["nut.inertia_kg_m2"] == p["nut.inertia_kg_m2"]["value"]
    # the written plant's own fit % is reported beside the free fit's
    assert set(result.solver["fit_percent_written"]) == set(result.fit_percent)
    # without the option every fitted value is written (the old behaviour, for studies)
    raw = fit_plant([toolkit_record(truth, "multisine")], base, keep_unidentified=False)
    assert not raw.kept_base and raw.plant.values["friction.efficiency"] == raw.parameters["friction.efficiency"]["value"]


def test_uncertainty_entries_stay_in_the_physical_range(base):
    """Review finding 2: an interval reaching past the key's physical range (no-load torque up
    to 3.6 N m on a 3 N m motor) never becomes a wider [uncertainty] entry."""
    from prsa_ctrl.identification.common import _physical_range, _uncertainty_entries, key_bounds

    k = "friction.no_load_torque_n_m"
    lo, hi, _ = key_bounds(base, k, TS)
    rng = _physical_range(base, k, lo, hi)
    assert rng == (0.0, 0.5 * base.torque_limit)
    for value, sd in ((0.1, 1.8), (0.0005, 0.02), (0.3, 0.1)):
        params = {k: {"value": value, "ci95": [value - 1.96 * sd, value + 1.96 * sd], "unit": "N m"}}
        (entry,) = _uncertainty_entries(base, params, "x.csv", [sd], [rng]).values()
        top = entry["high"] if entry["dist"] == "uniform" else value + entry["truncate"] * entry["sigma"]
        bottom = entry["low"] if entry["dist"] == "uniform" else value - entry["truncate"] * entry["sigma"]
        assert rng[0] <= bottom and top <= rng[1] * (1 + 1e-12), (value, sd, entry)


def test_cli_keeps_unidentified_keys_at_base_and_prints_clean(base, tmp_path, capsys):
    """Review findings 2, 3, 5 on one constant-load multisine."""
    from prsa_ctrl.cli.fit import main

    truth = base.with_params(PERTURBED["issue"])
    csv = tmp_path / "ms.csv"
    toolkit_record(truth, "multisine").to_csv(csv)
    out, rep = tmp_path / "o16.toml", tmp_path / "o16.json"
    assert main([str(csv), "--out", str(out), "--json", str(rep)]) == 0
    cap = capsys.readouterr()
    doc, report = tomllib.loads(out.read_text()), json.loads(rep.read_text())
    base_doc = tomllib.loads((Path(__file__).resolve().parents[2] / "plants" / "paper-iprsm.toml").read_text())
    kept = [k for k, v in report["parameters"].items() if v["kept_base"]]
    assert "friction.efficiency" in kept
    for k in kept:
        sec, key = k.split(".")
        assert doc[sec][key] == base_doc[sec][key]  # value and source as in the base file
        assert report["parameters"][k]["reason"]
        assert not doc["uncertainty"].get(k, {}).get("source", "").startswith("fit:")
    # every [uncertainty] entry the fit wrote lies within the key's plausible range
    from prsa_ctrl.plant.plantfile import PLAUSIBLE
    from prsa_ctrl.plant.uncertainty import plant_uncertainty

    for u in plant_uncertainty(load_plant(out)).entries:
        if u.source.startswith("fit:"):
            lo, hi, _ = PLAUSIBLE[u.key]
            assert lo <= u.low and u.high <= hi
    assert doc["nut"]["inertia_kg_m2"]["source"].startswith("fit: ")
    # finding 5: a fitted description, no dangling unit dash
    assert "ms.csv" in doc["description"] and "prsa-fit" in doc["description"]
    assert " - (95 % CI" not in cap.out and "friction.efficiency = " in cap.out
    assert "not identifiable, the plant keeps the base value 0.85" in cap.out
    # finding 3: no Python warning format on stderr; the built-in geometry note only with --verbose
    assert "GeometryWarning" not in cap.err and "plant = cls(" not in cap.err and "geometry" not in cap.err
    # (the log's delay given: an inertia-only fit of this record does not decide it by the search's
    # factor 1.5, and an undecided delay is not validated -- exit 3 -- since prsa-fit's validation)
    assert main([str(csv), "--out", str(tmp_path / "v.toml"), "--verbose", "--fit", "nut.inertia_kg_m2",
                 "--delay-samples", "0"]) == 0
    err = capsys.readouterr().err.splitlines()
    # --verbose: the notes and the progress line that says the fit has started (Ctrl-C tests wait for it)
    assert err and all(line.startswith(("prsa-fit: note: ", "prsa-fit: fitting ")) for line in err)
    assert sum(line.startswith("prsa-fit: fitting ") for line in err) == 1
    assert any("geometry does not close" in line for line in err)


def test_cli_same_path_and_design_bounds_refused_before_work(csv_files, tmp_path, capsys, monkeypatch):
    """Review findings 1 and 4: one line, exit 2, nothing written, no fit started."""
    import prsa_ctrl.identification.timedomain as fit_mod
    from prsa_ctrl.cli.fit import main

    _, paths = csv_files
    monkeypatch.setattr(fit_mod, "fit_plant", lambda *a, **k: pytest.fail("the fit ran"))
    same = tmp_path / "o4.toml"
    for argv in ([paths[0], "--out", str(same), "--json", str(same)],
                 [paths[0], "--out", str(same), "--json", str(tmp_path / "." / "o4.toml")],
                 [paths[0], "--out", str(same), "--plots", str(same)]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "name the same path" in err, err
    assert not same.exists()
    exc = tmp_path / "exc.csv"
    for argv, text in ((["--amplitude", "1e9"], "--amplitude 1e9 with --offset 30 (default): the setpoint reaches"),
                       (["--offset", "-700"], "expected |offset| + amplitude <= 628.319 rad/s"),
                       (["--json", str(tmp_path / "j.json")], "--json"),
                       (["--duration", "-1"], "prsa-fit: error: --duration '-1': expected a finite number > 0")):
        assert main(["--design", "chirp", "--out", str(exc), *argv]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and text in err, err
        assert "--duration: --duration" not in err
    assert not exc.exists() and not (tmp_path / "j.json").exists()
    assert main(["--design", "chirp", "--out", str(exc), "--amplitude", "590", "--offset", "-38", "--duration", "0.1"]) == 0


def test_validation_record_and_fixed_keys(base):
    truth = base.with_params(PERTURBED["issue"])
    fit_on = toolkit_record(truth, "load-steps", name="A")
    other = toolkit_record(truth, "multisine", name="B")
    result = fit_plant([fit_on], base, keys=["nut.inertia_kg_m2", "friction.efficiency", "drive.current_loop_bandwidth_hz",
                                             "friction.no_load_torque_n_m"], validate=[other])
    assert set(result.parameters) == {"nut.inertia_kg_m2", "friction.efficiency", "drive.current_loop_bandwidth_hz",
                                      "friction.no_load_torque_n_m"}
    assert result.plant.values["friction.viscous_n_m_s_per_rad"] == base.values["friction.viscous_n_m_s_per_rad"]
    assert set(result.fit_percent) == {"A", "B"} and result.fit_percent["B"] > 90.0


def test_bad_arguments_and_non_convergence(base):
    rec = toolkit_record(base, "multisine")
    with pytest.raises(ValueError, match="fit key 'nut.mass'"):
        fit_plant([rec], base, keys=["nut.mass"])
    with pytest.raises(ValueError, match="at least one data record"):
        fit_plant([], base)
    with pytest.raises(FitError, match="did not converge.*remedy"):
        fit_plant([rec], base, max_iter=1)


@pytest.mark.slow  # 20-seed CI coverage study (~6 min)
@pytest.mark.parametrize("case", list(PERTURBED))
def test_ci_coverage_over_20_seeds(base, case):
    """Issue 11: for each parameter, the truth inside its 95 % CI in >= 90 % of 20 seeds."""
    truth = base.with_params(PERTURBED[case])
    inside = dict.fromkeys(DEFAULT_KEYS, 0)
    for seed in range(20):
        result = fit_plant(_experiments(truth, seed), base)
        _check_accuracy(result, truth)
        for k, v in result.parameters.items():
            lo, hi = v["ci95"]
            inside[k] += lo <= truth.values[k] <= hi
    assert all(n >= 18 for n in inside.values()), inside


# --- command line ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def csv_files(base, tmp_path_factory):
    d = tmp_path_factory.mktemp("fitdata")
    truth = base.with_params(PERTURBED["issue"])
    paths = []
    for kind in ("multisine", "load-steps", "staircase"):
        p = d / f"{kind}.csv"
        toolkit_record(truth, kind).to_csv(p)
        paths.append(str(p))
    return d, paths


def test_cli_fit_writes_plant_and_report_and_tune_uses_it(csv_files, tmp_path):
    from prsa_ctrl.cli.tune import main as tune_main
    from prsa_ctrl.cli.fit import main

    _, paths = csv_files
    out, rep, figs = tmp_path / "my-actuator.toml", tmp_path / "report.json", tmp_path / "figs"
    # --uncertainty-from-fit: the fit's intervals as [uncertainty] (issue 20: the default keeps the user's)
    assert main([*paths, "--out", str(out), "--json", str(rep), "--plots", str(figs), "--uncertainty-from-fit"]) == 0
    doc = tomllib.loads(out.read_text())
    assert doc["name"] == "my-actuator"
    src = doc["nut"]["inertia_kg_m2"]["source"]
    assert src.startswith("fit: ") and "multisine.csv" in src and "(95 % CI " in src
    report = json.loads(rep.read_text())
    assert set(report) >= {"parameters", "reflected_inertia_kg_m2", "fit_percent", "warnings", "solver"}
    spread = report["solver"]["between_logs"]  # three logs: the delete-one-log test of the covariance ran
    assert spread["logs"] == 3 and len(spread["heterogeneity_ratio"]) == len(spread["inflated"]) == len(DEFAULT_KEYS)
    assert spread["threshold"] == pytest.approx(2.9957322735539895)
    for k in DEFAULT_KEYS:
        assert set(report["parameters"][k]) == {"value", "ci95", "unit", "kept_base"}
        assert report["parameters"][k]["kept_base"] is False  # three experiments inform every key
    assert doc["nut"]["inertia_kg_m2"]["value"] == report["parameters"]["nut.inertia_kg_m2"]["value"]
    assert set(report["fit_percent"]) == set(paths)
    assert abs(report["reflected_inertia_kg_m2"]["value"] / load_plant(out).reflected_inertia_kg_m2 - 1) < 1e-12
    # Each fitted key's CI is its [uncertainty] entry (a normal truncated at the 95 % interval),
    # replacing the base file's assumption; keys not fitted keep theirs.
    from prsa_ctrl.plant.uncertainty import plant_uncertainty

    unc = {u.key: u for u in plant_uncertainty(load_plant(out)).entries}
    for k in DEFAULT_KEYS:
        lo, hi = report["parameters"][k]["ci95"]
        assert unc[k].source.startswith("fit: ") and unc[k].dist in ("normal", "uniform")
        assert unc[k].low >= lo * (1 - 1e-9) - 1e-15 and unc[k].high <= hi * (1 + 1e-9) + 1e-15
    assert unc["nut.inertia_kg_m2"].dist == "normal"
    assert math.isclose(unc["nut.inertia_kg_m2"].low, report["parameters"]["nut.inertia_kg_m2"]["ci95"][0], rel_tol=1e-6)
    assert unc["contact.stiffness_n_per_mm_e"].source.startswith("assumption:")
    # Residual and overlay figures, one per record.
    # (and each record's own frequency response beside the written plant's)
    assert sorted(q.name for q in figs.iterdir()) == ["load-steps-fit.png", "load-steps-frf.png", "multisine-fit.png",
                                                      "multisine-frf.png", "staircase-fit.png", "staircase-frf.png"]
    assert all(q.stat().st_size > 10_000 for q in figs.iterdir())
    # The tuner takes the fitted plant directly.
    assert tune_main(["--plant", str(out), "--quiet", "--duration", "0.25", "--json", str(tmp_path / "t.json")]) == 0


def test_cli_bad_input_exit_2_nothing_written(csv_files, tmp_path, capsys):
    from prsa_ctrl.cli.fit import main

    d, paths = csv_files
    bad = tmp_path / "bad.csv"
    text = Path(paths[0]).read_text().splitlines()
    text[5] = text[5].replace(text[5].split(",")[1], "nan", 1)
    bad.write_text("\n".join(text) + "\n")
    out = tmp_path / "o.toml"
    assert main([str(bad), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(bad) in err and "torque_command_n_m" in err and "line 6" in err
    assert main([paths[0], "--out", str(out), "--fit", "nut.inertia_kg_m2,bogus"]) == 2
    assert "bogus" in capsys.readouterr().err
    assert main([paths[0], "--out", paths[0]]) == 2  # never overwrite an input
    assert main([paths[0], "--out", str(tmp_path / "missing-dir" / "o.toml")]) == 2
    assert not out.exists() and [p.name for p in tmp_path.iterdir()] == ["bad.csv"]


def test_cli_non_convergence_exit_3(csv_files, tmp_path, monkeypatch, capsys):
    import prsa_ctrl.identification.timedomain as fit_mod
    from prsa_ctrl.cli.fit import main

    _, paths = csv_files
    real = fit_mod.fit_plant
    monkeypatch.setattr(fit_mod, "fit_plant", lambda *a, **k: real(*a, **{**k, "max_iter": 1}))
    out = tmp_path / "o.toml"
    assert main([paths[0], "--out", str(out)]) == 3
    assert "ipopt" not in (err := capsys.readouterr().err) and "remedy" in err
    assert not out.exists()


def test_cli_design(tmp_path):
    from prsa_ctrl.cli.fit import main

    out = tmp_path / "excitation.csv"
    assert main(["--design", "multisine", "--out", str(out), "--duration", "0.5", "--f-max", "100"]) == 0
    data = np.loadtxt(out, delimiter=",", comments="#", skiprows=2)
    assert data.shape == (2000, 2)
    assert main(["--design", "chirp", "--out", str(out), "--f-max", "5000"]) == 2


def test_plant_toml_adds_an_uncertainty_section_when_the_base_has_none(base):
    from prsa_ctrl.cli.fit import _base_text, plant_toml
    from prsa_ctrl.plant.plantfile import Plant
    from prsa_ctrl.plant.uncertainty import check_plant_uncertainty

    text, _ = _base_text(None)
    no_unc = text[:text.index("[uncertainty]")]
    truth = base.with_params(PERTURBED["issue"])
    res = fit_plant([toolkit_record(truth, "multisine")], base, keys=["nut.inertia_kg_m2"], uncertainty="fit")
    out = plant_toml(no_unc, res.plant, "mine", res.keys)
    doc = tomllib.loads(out)
    assert doc["nut"]["inertia_kg_m2"]["value"] == res.parameters["nut.inertia_kg_m2"]["value"]
    model = check_plant_uncertainty(Plant.from_dict(doc, origin="mine.toml"))
    (entry,) = [e for e in model.entries if e.key == "nut.inertia_kg_m2"]
    lo, hi = res.parameters["nut.inertia_kg_m2"]["ci95"]
    assert math.isclose(entry.low, lo, rel_tol=1e-9) and math.isclose(entry.high, hi, rel_tol=1e-9)
    # with the base's section: the fitted key's assumption is replaced, the others are kept as written
    full = plant_toml(text, res.plant, "mine", res.keys)
    unc_lines = [ln for ln in full[full.index("[uncertainty]"):].splitlines() if "=" in ln]
    base_lines = [ln for ln in text[text.index("[uncertainty]"):].splitlines() if "=" in ln]
    assert [ln for ln in unc_lines if ln.startswith('"nut.')][0].count("fit: multisine-0") == 1
    assert [ln for ln in base_lines if not ln.startswith('"nut.')] == [ln for ln in unc_lines if not ln.startswith('"nut.')]


def test_long_record_converges_in_the_first_attempt():
    # Issue 11's run-time record, 1 s of it (4001 samples): the first attempt (state-only warm-up
    # before the parameters move) converges; moving the parameters at once stalled after 16
    # iterations before a second attempt converged in 9. An iteration budget, not a clock.
    from prsa_ctrl.identification.synthetic import FIT_TRUTH, fit_record

    rec, truth = fit_record(1.0)
    assert rec.n == 4001
    res = fit_plant([rec])
    assert res.solver["status"] == "converged"
    assert res.solver["attempts"] == 1 and res.solver["iterations_all_attempts"] <= 12
    for k, v in FIT_TRUTH.items():
        assert abs(res.parameters[k]["value"] / v - 1) < 1e-3, k


def test_buffered_evaluation_matches_casadi_and_checks_sizes():
    import casadi as ca

    from prsa_ctrl.identification.gaussnewton import Buffered as _Buffered

    x, p = ca.SX.sym("x", 2), ca.SX.sym("p")
    e = ca.vertcat(p * x[0] ** 2, ca.sin(x[1]))
    f = ca.Function("f", [x, p], [e, ca.densify(ca.jacobian(e, x))]).map("fm", "serial", 3, [1], [])
    xs = np.array([[1.0, 2.0, 3.0], [0.1, 0.2, 0.3]])
    res, jac = _Buffered(f)(xs, 2.0)
    want_res, want_jac = (np.asarray(o) for o in f(xs, 2.0))
    assert np.array_equal(res.reshape(2, 3, order="F"), want_res)
    assert np.array_equal(jac.reshape(2, 6, order="F"), want_jac)
    with pytest.raises(ValueError, match="input 0 has 4 values; expected 6"):
        _Buffered(f)(xs[:, :2], 2.0)
