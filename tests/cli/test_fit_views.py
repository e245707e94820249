"""prsa-fit's figures and views (prsa_ctrl.cli.fit): ``--frequency-unit`` reaches the Bode
figures, ``--json`` carries the three views (replay, frequency response, residuals) with the
verdict, and the data in them are the fit's own (the replay recomputed independently from the
written plant file)."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

pytest.importorskip("matplotlib")


def _syn_frf(path, n=60, seed=3):
    """A frequency response of the paper plant (2 % noise) with a coherence column, one point
    below the default threshold 0.8."""
    from prsa_ctrl import load_plant
    from prsa_ctrl.identification.data import frf_from_arrays
    from prsa_ctrl.identification.frf import frf_response

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p = load_plant()
    f = np.geomspace(5, 1000, n)
    rng = np.random.default_rng(seed)
    g = frf_response(p, f, speed_rad_s=30.0) * np.exp(0.02 * (rng.standard_normal(n) + 1j * rng.standard_normal(n)))
    coh = np.clip(0.97 + 0.01 * rng.standard_normal(n), 0, 1)
    coh[5] = 0.5
    frf_from_arrays("syn", f, g, coherence=coh).to_csv(path)


def test_frf_fit_figures_in_the_unit_asked_and_views_with_coherence(tmp_path, monkeypatch, capsys):
    import prsa_ctrl.plots.fit as P
    from prsa_ctrl.cli.fit import main

    csv = tmp_path / "syn.csv"
    _syn_frf(csv)
    units = []
    draw = P.fit_figures

    def spy(result, frequency_unit="Hz", records=()):
        units.append(frequency_unit)
        return draw(result, frequency_unit, records)

    monkeypatch.setattr(P, "fit_figures", spy)
    rep, figs = tmp_path / "r.json", tmp_path / "figs"
    assert main(["--frf", str(csv), "--out", str(tmp_path / "o.toml"), "--json", str(rep), "--plots", str(figs),
                 "--frequency-unit", "rad/s"]) == 0
    assert units == ["rad/s"] and (figs / "syn-bode.png").stat().st_size > 10_000
    views = json.loads(rep.read_text())["views"]
    assert views["replay"] == {} and views["verdict"]["validated"] is None  # an FRF fit has no time-domain replay
    (v,) = views["frf"].values()
    raw = np.genfromtxt(csv, delimiter=",", names=True)
    keep = raw["coherence"] >= 0.8
    np.testing.assert_allclose(v["frequency_hz"], raw["frequency_hz"][keep], rtol=1e-15)
    np.testing.assert_allclose(v["coherence"], raw["coherence"][keep], rtol=1e-15)
    np.testing.assert_allclose(v["measured"]["magnitude_db"], raw["magnitude_db"][keep], rtol=1e-12, atol=1e-12)
    labels = list(v["models"])
    assert labels[0].startswith("rigid (") and v["models"][labels[-1]]["written"] is True
    assert not any(m["written"] for m in list(v["models"].values())[:-1])
    capsys.readouterr()


def test_frequency_unit_refused_with_one_line(tmp_path, capsys):
    from prsa_ctrl.cli.fit import main

    csv = tmp_path / "syn.csv"
    _syn_frf(csv)
    out = tmp_path / "o.toml"
    assert main(["--frf", str(csv), "--out", str(out), "--plots", str(tmp_path / "f"), "--frequency-unit", "kHz"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--frequency-unit" in err[0] and "'kHz'" in err[0] and "rad/s" in err[0]
    assert not out.exists() and not (tmp_path / "f").exists()


def test_time_domain_views_are_the_replay_of_the_written_plant(tmp_path, capsys):
    """Two simulated logs (one fitted, one --validate): the JSON views hold each log's replay
    (prediction-error: these logs describe no controller), equal to a replay of the written
    plant file run here, the residual, the verdict, and each log's frequency response beside
    the written plant's."""
    from prsa_ctrl import load_plant
    from prsa_ctrl.cli.fit import main
    from prsa_ctrl.identification.data import load_record
    from prsa_ctrl.identification.frf import frf_response
    from prsa_ctrl.identification.synthetic import fit_record
    from prsa_ctrl.identification.validation import REPLAY_MODE, replay_records

    paths = []
    for seed in (1, 2):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            rec, _ = fit_record(1.0, seed=seed)
        paths.append(tmp_path / f"log{seed}.csv")
        rec.to_csv(paths[-1])
    out, rep, figs = tmp_path / "fitted.toml", tmp_path / "r.json", tmp_path / "figs"
    assert main([str(paths[0]), "--validate", str(paths[1]), "--out", str(out), "--json", str(rep),
                 "--plots", str(figs)]) == 0
    assert "plots: " + ", ".join(str(figs / n) for n in ("log1-fit.png", "log2-fit.png", "log1-frf.png",
                                                          "log2-frf.png")) in capsys.readouterr().out
    assert sorted(q.name for q in figs.iterdir()) == ["log1-fit.png", "log1-frf.png", "log2-fit.png", "log2-frf.png"]
    report = json.loads(rep.read_text())
    views = report["views"]
    assert views["verdict"]["validated"] is True and views["verdict"]["diagnosis"] is None
    assert views["verdict"]["replay"] == REPLAY_MODE
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plant = load_plant(out)
    shift = report["solver"]["command_delay"]["shift_samples"]
    for path in paths:
        name = str(path)
        r = views["replay"][name]
        assert r["mode"] == "prediction-error" and "prediction-error replay" in r["label"]
        assert r["explained"] is True and r["fit_percent"] == report["fit_percent"][name]
        rec = load_record(path)
        again = replay_records(plant, [rec], shift)[name]  # the written file, replayed independently
        idx = np.arange(0, len(again["time_s"]), r["every"])
        assert len(r["time_s"]) <= 2000 and r["every"] == -(-len(again["time_s"]) // 2000)
        np.testing.assert_allclose(r["time_s"], again["time_s"][idx], rtol=1e-15)
        np.testing.assert_allclose(r["measured_rad_s"], again["measured"][idx], rtol=1e-15)
        np.testing.assert_allclose(r["model_rad_s"], again["model"][idx], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(r["residual_rad_s"], (again["measured"] - again["model"])[idx], atol=1e-9)
        f = views["frf"][name]
        assert "H1 estimate" in f["source"] and len(f["frequency_hz"]) >= 20
        ((label, m),) = f["models"].items()
        assert m["written"] is True and label.startswith("plant as written") and f["fit_percent"] is None
        fq = np.asarray(f["frequency_hz"])
        g = frf_response(plant, fq, speed_rad_s=float(np.mean(rec.speed_rad_s)), load_n=float(np.mean(rec.axial_load_n)),
                         sample_time_s=rec.sample_time_s, delay_samples=shift)  # independently, from the file
        np.testing.assert_allclose(m["magnitude_db"], 20 * np.log10(np.abs(g)), rtol=1e-9, atol=1e-9)
        # where the log's estimate holds, the written plant follows it (a sample of delay more: ~30 deg off)
        sure = np.asarray(f["coherence"]) > 0.9
        assert np.count_nonzero(sure) >= 20
        assert np.median(np.abs(np.asarray(f["residual"]["magnitude_db"])[sure])) < 1.0
        assert np.median(np.abs(np.asarray(f["residual"]["phase_deg"])[sure])) < 5.0
