"""Issue 20 (calibration): identifiability that does not hinge on round-off, honest intervals,
duplicate records, unit and sample-time checks, hostile inputs of prsa-fit, overlay figures
without shooting-join spikes, and the user's [uncertainty] kept."""

import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from prsa_ctrl.identification.timedomain import fit_plant

from test_fit import PERTURBED, toolkit_record  # noqa: E402

TRUTH = PERTURBED["issue"]


@pytest.fixture(scope="module")
def base(paper_plant):
    return paper_plant


@pytest.fixture(scope="module")
def truth(base):
    return base.with_params(TRUTH)


@pytest.fixture(scope="module")
def multisine(truth):
    return toolkit_record(truth, "multisine", seed=0)


def _check_constant_load(result, base):
    p = result.parameters
    for k in ("friction.efficiency", "friction.no_load_torque_n_m"):
        assert p[k]["kept_base"], (k, p[k])
        assert "combination" in p[k]["reason"] and "1e-06" in p[k]["reason"], p[k]["reason"]
        lo, hi = p[k]["ci95"]
        assert lo <= TRUTH[k] <= hi, (k, p[k])  # the honest interval holds the truth
        assert result.plant.values[k] == base.values[k]
        assert result.plant.uncertainty.get(k) == base.uncertainty.get(k)
    # the efficiency's interval is as wide as the data leave it: bounded only by the physical ranges
    lo, hi = p["friction.efficiency"]["ci95"]
    assert hi - lo > 0.15
    assert not p["nut.inertia_kg_m2"]["kept_base"]
    assert abs(p["nut.inertia_kg_m2"]["value"] / TRUTH["nut.inertia_kg_m2"] - 1) < 0.01
    assert result.solver["uninformed_directions"] == 1


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_constant_load_efficiency_unidentified_on_every_seed(base, truth, seed):
    """Item 1 / hostile 5: the decision holds for every seed (on b18c321 seeds 1..3 wrote a
    fitted efficiency with a CI of +/- 6e-6 that missed the truth)."""
    result = fit_plant([toolkit_record(truth, "multisine", seed=seed)], base)
    _check_constant_load(result, base)


@pytest.mark.parametrize("level", [1e-10, 1e-8])
def test_identifiability_survives_a_perturbed_jacobian(base, multisine, monkeypatch, level):
    """The same decision with the scaled Jacobian perturbed far above round-off (a criterion at
    round-off level would flip here on every machine)."""
    import prsa_ctrl.identification.timedomain as F

    split = F.info_split
    rng = np.random.default_rng(7)

    def perturbed(jn):
        return split(jn * (1 + level * rng.standard_normal(jn.shape)))

    monkeypatch.setattr(F, "info_split", perturbed)
    _check_constant_load(fit_plant([multisine], base), base)


def test_info_split_tolerance_is_stated_and_scale_free():
    from prsa_ctrl.identification.common import RANK_RTOL, info_split

    rng = np.random.default_rng(0)
    j = rng.standard_normal((200, 4))
    j[:, 3] = j[:, 2] * (1 + 1e-12)  # exactly collinear up to round-off
    for noise in (0.0, 1e-10, 1e-8):
        jj = j * (1 + noise * rng.standard_normal(j.shape))
        jn = jj / np.linalg.norm(jj, axis=0)
        a_inv, null, ratios = info_split(jn)
        assert null.shape == (4, 1) and abs(abs(null[2, 0]) - abs(null[3, 0])) < 1e-6
        assert np.all(np.isfinite(a_inv)) and np.max(np.abs(a_inv)) < 1e3
    assert 1e-8 < RANK_RTOL < 1e-3
    j[:, 3] = j[:, 2] + 1e-2 * rng.standard_normal(200)  # weakly but truly informed: kept
    _, null, _ = info_split(j / np.linalg.norm(j, axis=0))
    assert null.shape == (4, 0)


# --- item 2 (hostile 9): the same record twice ---------------------------------------------------


def test_duplicate_record_used_once_with_a_warning(base, truth, multisine):
    from dataclasses import replace

    one = fit_plant([multisine], base, keys=("nut.inertia_kg_m2", "drive.current_loop_bandwidth_hz"))
    copy = replace(multisine, name="copy.csv", time_s=multisine.time_s + 5.0)  # same data, shifted clock
    two = fit_plant([multisine, copy], base, keys=("nut.inertia_kg_m2", "drive.current_loop_bandwidth_hz"))
    for k in one.keys:  # not narrowed by sqrt(2)
        assert two.parameters[k]["ci95"] == pytest.approx(one.parameters[k]["ci95"], rel=1e-9)
    assert any("copy.csv holds the same data as multisine-0" in w and "once" in w for w in two.warnings)
    # a validation record that is a fitted one is no validation: said, not counted
    val = fit_plant([multisine], base, keys=("nut.inertia_kg_m2",), validate=[copy])
    assert "copy.csv" not in val.fit_percent and any("copy.csv" in w and "not a validation" in w for w in val.warnings)


def test_duplicate_frf_used_once(base, truth):
    from prsa_ctrl.identification.frf import fit_frf, frf_response
    from prsa_ctrl.identification.data import frf_from_arrays

    f = np.geomspace(5, 600, 40)
    rng = np.random.default_rng(1)
    g = frf_response(truth, f, load_n=800.0) * np.exp(0.02 * (rng.standard_normal(40) + 1j * rng.standard_normal(40)))
    a, b = frf_from_arrays("a.csv", f, g, load_n=800.0), frf_from_arrays("b.csv", f, g, load_n=800.0)
    one, two = fit_frf([a], base), fit_frf([a, b], base)
    for k in one.keys:
        assert two.parameters[k]["ci95"] == pytest.approx(one.parameters[k]["ci95"], rel=1e-6)
    assert any("b.csv holds the same data as a.csv" in w for w in two.warnings)


# --- item 3 (hostile 6): units checked against the plant's physics --------------------------------


def _speed_only(rec, factor=1.0, name="speed.csv"):
    from prsa_ctrl.identification.data import record_from_arrays

    v = np.concatenate([[rec.speed_rad_s[0]], rec.speed_rad_s]) * factor
    return record_from_arrays(name, rec.time_s, rec.torque_command_n_m, nut_speed_rad_s=v, axial_load_n=rec.axial_load_n)


@pytest.mark.parametrize("case", list(PERTURBED))
@pytest.mark.parametrize("kind", ["multisine", "load-steps", "staircase"])
def test_torque_balance_finds_rpm_and_passes_rad_s(base, case, kind):
    from prsa_ctrl.identification.common import _check_units

    rec = toolkit_record(base.with_params(PERTURBED[case]), kind)
    _check_units(rec, base)
    _check_units(_speed_only(rec), base)  # SI speed: accepted
    with pytest.raises(ValueError, match=r"column nut_speed_rad_s looks like speed in rpm"):
        _check_units(_speed_only(rec, 60 / (2 * math.pi)), base)
    with pytest.raises(ValueError, match=r"column torque_command_n_m reaches .* torque limit"):
        from dataclasses import replace

        _check_units(replace(rec, torque_command_n_m=rec.torque_command_n_m * 1e3), base)


def test_cli_rpm_speed_without_angle_exit_2_one_line(multisine, tmp_path, capsys):
    from prsa_ctrl.cli.fit import main

    csv = tmp_path / "rpm.csv"
    _speed_only(multisine, 60 / (2 * math.pi)).to_csv(csv)
    out = tmp_path / "o.toml"
    assert main([str(csv), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nut_speed_rad_s" in err[0] and "rpm" in err[0] and "Traceback" not in err[0]
    assert not out.exists()


# --- item 4 (hostile 7): sample time and Nyquist -----------------------------------------------------


def test_sample_time_compared_with_the_plant(base, multisine, tmp_path, capsys):
    from dataclasses import replace

    from prsa_ctrl.cli.fit import main

    fast = replace(multisine, time_s=multisine.time_s * 1e-9)
    with pytest.raises(ValueError, match=r"time_s .* sample time of 2\.5e-13 s; expected the plant's sensor"):
        fit_plant([fast], base)
    csv = tmp_path / "ns.csv"
    fast.to_csv(csv)
    assert main([str(csv), "--out", str(tmp_path / "o.toml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "time_s" in err[0] and "1 %" in err[0]
    assert list(tmp_path.iterdir()) == [csv]


def test_frf_points_above_nyquist_dropped_with_a_note(base, truth):
    from prsa_ctrl.identification.frf import fit_frf, frf_response
    from prsa_ctrl.identification.data import frf_from_arrays

    nyq = 0.5 / base.sample_time_s
    f = np.geomspace(5, 3 * nyq, 60)
    g = frf_response(truth, f, load_n=800.0, sample_time_s=0.0)  # what an analyser beyond the drive sees
    full = fit_frf([frf_from_arrays("wide.csv", f, g, load_n=800.0)], base)
    below = f < nyq
    ref = fit_frf([frf_from_arrays("wide.csv", f[below], g[below], load_n=800.0)], base)
    assert any("wide.csv" in w and "Nyquist" in w and f"{int(np.sum(~below))} points" in w for w in full.warnings)
    assert np.max(full.traces["wide.csv"]["frequency_hz"]) < nyq
    for k in full.keys:
        assert full.parameters[k]["value"] == pytest.approx(ref.parameters[k]["value"], rel=1e-9)


# --- item 6: overlay figures without shooting-join spikes ---------------------------------------------


def _independent_record(truth):
    from independent_actuator import simulate_independent

    from prsa_ctrl.identification.data import design_excitation, record_from_arrays

    ts = 2.5e-4
    n = int(round(0.4 / ts))
    t = np.arange(n) * ts
    _, sp = design_excitation("multisine", duration_s=n * ts, sample_time_s=ts, f_min_hz=5, f_max_hz=150,
                              amplitude=20, offset=30)
    load = np.select([t < 0.1, t < 0.2, t < 0.3], [200.0, 1500.0, 300.0], 2500.0)
    d = simulate_independent(
        inertia_kg_m2=truth.reflected_inertia_kg_m2, lead_m=truth.lead_m, efficiency=0.88, no_load_torque_n_m=0.03,
        viscous_n_m_s_per_rad=1.5e-4, current_loop_bandwidth_hz=1200.0, torque_limit_n_m=truth.torque_limit,
        setpoint_rad_s=sp, load_n=load, sample_time_s=ts, seed=1)
    return record_from_arrays("independent", d["time_s"], d["torque_command_n_m"], nut_angle_rad=d["nut_angle_rad"],
                              axial_load_n=d["axial_load_n"])


def test_overlay_shows_one_continuous_simulation(base, truth):
    """On b18c321 the overlay drew the shooting segments: at a join the model jumped by 2.5 rad/s
    (the measured speed never changes by more than 1.4 rad/s in a sample) and the residual panel
    showed 2.3 rad/s there."""
    from prsa_ctrl.plots.fit import fit_figures

    rec = _independent_record(truth)
    result = fit_plant([rec], base)
    fig = fit_figures(result)["independent-fit"]
    ax1, ax2 = fig.axes[:2]
    meas, model = (np.asarray(line.get_ydata(), float) for line in ax1.lines[:2])
    t = np.asarray(ax1.lines[1].get_xdata(), float)
    assert np.all(np.isfinite(model)) and np.all(np.isfinite(t))  # one run, no segment breaks
    assert t[0] <= rec.time_s[1] + 1e-12 and t[-1] == pytest.approx(rec.time_s[-1])  # the whole record
    step_model, step_meas = np.max(np.abs(np.diff(model))), np.max(np.abs(np.diff(meas)))
    assert step_model <= 1.2 * step_meas, (step_model, step_meas)
    resid = np.asarray(ax2.lines[0].get_ydata(), float)
    assert np.max(np.abs(resid)) < 1.0
    np.testing.assert_allclose(resid, meas - model)
    # the label names the run drawn: one replay of the plant as written (prediction-error form here:
    # no controller is described), not the shooting segments
    label = ax1.get_legend().get_texts()[1].get_text()
    assert "plant as written" in label and "replay" in label, label


# --- item 7: the user's [uncertainty] kept ----------------------------------------------------------------


@pytest.fixture(scope="module")
def three_records(truth):
    return [toolkit_record(truth, k) for k in ("multisine", "load-steps", "staircase")]


def test_fitted_plant_keeps_the_users_uncertainty(base, three_records):
    """On b18c321 the fitted plant's [uncertainty] for the inertia was the fit's own sigma (a
    +/- 0.001 % spread), replacing the user's +/- 30 %: Monte Carlo on it showed no spread."""
    from prsa_ctrl.plant.uncertainty import plant_uncertainty

    res = fit_plant(three_records, base)
    assert "nut.inertia_kg_m2" in res.plant_keys
    for k in res.plant_keys:
        if k in base.uncertainty:
            assert res.plant.uncertainty[k] == base.uncertainty[k], k
    model = {u.key: u for u in plant_uncertainty(res.plant).entries}
    j = model["nut.inertia_kg_m2"]
    lo, hi = res.parameters["nut.inertia_kg_m2"]["ci95"]
    assert j.high - j.low >= hi - lo and j.high - j.low > 0.5 * res.plant.values["nut.inertia_kg_m2"]
    # asked for, the fit's own entries
    own = fit_plant(three_records, base, uncertainty="fit")
    assert own.plant.uncertainty["nut.inertia_kg_m2"]["source"].startswith("fit: ")
    with pytest.raises(ValueError, match="uncertainty = 'mine'"):
        fit_plant(three_records, base, uncertainty="mine")


def test_an_assumption_narrower_than_the_fit_is_replaced(base, three_records):
    from prsa_ctrl.plant.plantfile import Plant
    from prsa_ctrl.plant.uncertainty import plant_uncertainty

    narrow = {**base.uncertainty, "drive.current_loop_bandwidth_hz": {
        "dist": "uniform", "relative": 1e-6, "source": "assumption: far too sure"}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        b2 = Plant(name=base.name, values=base.values, sources=base.sources, uncertainty=narrow)
    res = fit_plant(three_records, b2)
    k = "drive.current_loop_bandwidth_hz"
    assert res.plant.uncertainty[k]["source"].startswith("fit: ")
    assert any(k in w and "narrower than the fit's 95 % interval" in w for w in res.warnings)
    (u,) = [u for u in plant_uncertainty(res.plant).entries if u.key == k]
    lo, hi = res.parameters[k]["ci95"]
    assert u.high - u.low >= (hi - lo) * (1 - 1e-6)


def test_cli_keeps_the_base_uncertainty_lines(three_records, tmp_path):
    import tomllib

    from prsa_ctrl.cli.fit import main
    from prsa_ctrl.plant.plantfile import plant_file_path

    paths = []
    for r in three_records:
        p = tmp_path / f"{r.name}.csv"
        r.to_csv(p)
        paths.append(str(p))
    out = tmp_path / "mine.toml"
    assert main([*paths, "--out", str(out)]) == 0
    base_text = plant_file_path().read_text()
    base_unc = base_text[base_text.index("[uncertainty]"):]
    assert out.read_text().endswith(base_unc)  # every line of the user's section as written
    doc = tomllib.loads(out.read_text())
    assert doc["nut"]["inertia_kg_m2"]["source"].startswith("fit: ")


# --- item 5: hostile inputs of prsa-fit ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def one_csv(multisine, tmp_path_factory):
    p = tmp_path_factory.mktemp("one") / "ms.csv"
    multisine.to_csv(p)
    return str(p)


def _run(argv):
    """prsa-fit's exit code; a KeyboardInterrupt that escapes main (b18c321) counts as a failure."""
    from prsa_ctrl.cli.fit import main

    try:
        return main(argv)
    except KeyboardInterrupt:
        return "KeyboardInterrupt escaped"


def test_ctrl_c_exit_130_one_line_nothing_left(one_csv, tmp_path, capsys, monkeypatch):
    import prsa_ctrl.identification.timedomain as F
    import prsa_ctrl.plots.fit as P

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    out, plots = tmp_path / "o.toml", tmp_path / "plots"
    monkeypatch.setattr(F, "fit_plant", interrupted)
    assert _run([one_csv, "--out", str(out)]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "interrupted" in err[0] and "Traceback" not in err[0]
    monkeypatch.undo()
    monkeypatch.setattr(P, "fit_figures", interrupted)  # Ctrl-C while the figures are drawn
    assert _run([one_csv, "--out", str(out), "--plots", str(plots), "--fit", "nut.inertia_kg_m2"]) == 130
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


def _variants(text):
    """Valid TOML spellings of the built-in plant file that the line rewrite did not know."""
    key = 'inertia_kg_m2 = { value = 2.0e-4, source = "assumption: nut sleeve plus frameless rotor of a ~60 mm stator (catalogue rotors 1e-4 to 3e-4 kg m^2)" }'
    assert key in text
    dotted = ('inertia_kg_m2.value = 2.0e-4\ninertia_kg_m2.source = "assumption: nut sleeve plus frameless rotor of a '
              '~60 mm stator (catalogue rotors 1e-4 to 3e-4 kg m^2)"')
    return {
        "trailing-comment": text.replace(key, key + "  # measured 2024"),
        "dotted": text.replace(key, dotted),
        "header-comment": text.replace("[nut]\n", "[nut] # the nut\n"),
        "spaced-header": text.replace("[nut]\n", "[ nut ]\n"),
    }


@pytest.mark.parametrize("variant", ["trailing-comment", "dotted", "header-comment", "spaced-header"])
def test_cli_writes_the_fit_for_every_toml_spelling(variant, one_csv, tmp_path, capsys):
    import tomllib

    from prsa_ctrl.plant.plantfile import load_plant as lp
    from prsa_ctrl.plant.plantfile import plant_file_path

    text = _variants(plant_file_path().read_text())[variant]
    base_file = tmp_path / "base.toml"
    base_file.write_text(text)
    tomllib.loads(text)  # valid TOML
    out = tmp_path / "fitted.toml"
    # (the log's delay given: an inertia-only fit does not decide it, and an undecided delay is
    # not validated -- exit 3 -- since prsa-fit's validation; this test is about TOML spellings)
    code = _run([one_csv, "--plant", str(base_file), "--out", str(out), "--fit", "nut.inertia_kg_m2",
                 "--delay-samples", "0"])
    assert code == 0, capsys.readouterr().err
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fitted = lp(str(out))
    assert abs(fitted.values["nut.inertia_kg_m2"] / TRUTH["nut.inertia_kg_m2"] - 1) < 0.05
    assert fitted.sources["nut.inertia_kg_m2"].startswith("fit: ")
    assert fitted.uncertainty == lp(str(base_file)).uncertainty


def test_plant_toml_keeps_layout_where_it_can(base):
    from prsa_ctrl.cli.fit import plant_toml
    from prsa_ctrl.plant.plantfile import plant_file_path

    text = _variants(plant_file_path().read_text())["trailing-comment"]
    p = base.with_params({"nut.inertia_kg_m2": 1.6e-4})
    out = plant_toml(text, p, "x", ["nut.inertia_kg_m2"])
    assert "# measured 2024" in out and "Written by prsa-fit" not in out
    # dotted keys are kept too since the writer edits the TOML document (tomlkit; was: written afresh)
    dotted = plant_toml(_variants(plant_file_path().read_text())["dotted"], p, "x", ["nut.inertia_kg_m2"])
    assert "Written by prsa-fit" not in dotted
    assert "inertia_kg_m2.value = 0.00016\n" in dotted


def _no_fit(monkeypatch):
    import prsa_ctrl.identification.timedomain as F

    def fail(*a, **k):
        raise AssertionError("the fit ran before the output paths were checked")

    monkeypatch.setattr(F, "fit_plant", fail)


@pytest.mark.parametrize("which", ["--out", "--json"])
@pytest.mark.parametrize("kind", ["loop", "long"])
def test_cli_bad_output_paths_refused_before_the_fit(one_csv, tmp_path, capsys, monkeypatch, which, kind):
    import os

    _no_fit(monkeypatch)
    work = tmp_path / "w"
    work.mkdir()
    if kind == "loop":
        bad = work / "loop.json"
        os.symlink(work / "loop2.json", bad)
        os.symlink(bad, work / "loop2.json")
    else:
        bad = work / ("x" * 245 + ".json")
    argv = [one_csv, "--out", str(work / "o.toml"), "--json", str(work / "r.json"), "--plots", str(work / "pl")]
    argv[argv.index(which) + 1] = str(bad)
    assert _run(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and which in err[0] and "Traceback" not in err[0], err
    assert not (work / "pl").exists() and not (work / "o.toml").exists()


@pytest.mark.parametrize("flag,value", [("--frf-speed", "0"), ("--frf-speed", "1e6"), ("--frf-load", "1e9")])
def test_cli_frf_operating_point_checked(flag, value, tmp_path, capsys, monkeypatch, base, truth):
    from prsa_ctrl.identification.frf import frf_response
    from prsa_ctrl.identification.data import frf_from_arrays

    _no_fit(monkeypatch)
    f = np.geomspace(5, 600, 30)
    csv = tmp_path / "frf.csv"
    frf_from_arrays("frf", f, frf_response(truth, f, load_n=800.0)).to_csv(csv)
    assert _run(["--frf", str(csv), "--frf-load", "800", "--out", str(tmp_path / "o.toml"), flag, value]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{flag} {value}" in err[0], err


def test_huge_log_refused_before_reading(tmp_path, monkeypatch):
    import prsa_ctrl.tablefile as tablefile
    from prsa_ctrl.identification.data import DataError, load_frf, load_record

    big = tmp_path / "big.csv"
    with open(big, "wb") as fh:  # sparse: 2 GB on paper, nothing on disk
        fh.truncate(2 * 1024**3)

    def no_reading(*a, **k):
        raise AssertionError("the file was read")

    monkeypatch.setattr(tablefile.csv, "reader", no_reading)  # the one CSV reader's
    for load in (load_record, load_frf):
        with pytest.raises(DataError, match=r"2147483648 bytes; expected at most"):
            load(big)


def test_constant_frf_gives_no_absurd_fit_percent(tmp_path, capsys):
    from prsa_ctrl.identification.data import frf_from_arrays

    f = np.geomspace(5, 600, 30)
    csv = tmp_path / "const.csv"
    frf_from_arrays("c", f, np.full(30, 0.5 + 0j)).to_csv(csv)
    # issue 32: a response that is not torque -> speed of an inertia (phase 0 here) writes no
    # plant (was: exit 0 with "fit n/a"); one line, never an absurd number
    assert _run(["--frf", str(csv), "--out", str(tmp_path / "o.toml")]) == 3
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no plant written" in err and "e+" not in err and "e17" not in err
    assert not (tmp_path / "o.toml").exists()


@pytest.mark.parametrize("speed,load,match", [(0.0, 800.0, "speed = 0.0"), (1e6, 800.0, "speed = 1000000.0"),
                                              (30.0, 1e9, "load = 1000000000.0")])
def test_fit_frf_operating_point_checked(base, truth, speed, load, match):
    from prsa_ctrl.identification.frf import fit_frf, frf_response
    from prsa_ctrl.identification.data import frf_from_arrays

    f = np.geomspace(5, 600, 30)
    fr = frf_from_arrays("op.csv", f, frf_response(truth, f, load_n=800.0), speed_rad_s=speed, load_n=load)
    with pytest.raises(ValueError, match=f"op.csv: {match}; expected"):
        fit_frf([fr], base)
