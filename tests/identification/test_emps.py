"""The linear-axis plant, its closed-loop calibration and the EMPS benchmark case.

* A synthetic closed-loop log from an independent generator written here (fine trapezoidal
  substeps with a Karnopp stick band, quantised position, the position-P/velocity-P controller
  with the two-sample average) is recovered within its 95 % intervals, through a CSV file and a
  log description in mm and ms.
* The EMPS record (A. Janot, M. Gautier, M. Brunot, "Data Set and Reference Models of EMPS",
  Nonlinear System Identification Benchmarks workshop, 2019): the two commands of
  examples/emps/README.md end to end, the published model replayed with this code, and the
  benchmark's own replay convention reproduced. Skipped when the data file is absent.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from prsa_ctrl.identification.axis import (DEFAULTS, PARAMETERS, LinearAxisPlant, fit_linear_axis, load_axis_plant,
                               replay_axis)
from prsa_ctrl.cli.fit import main
from prsa_ctrl.identification.logformat import load_axis_log, load_log_format

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "emps"
_CANDIDATES = [ROOT.parent / "shared" / "data" / "emps" / "DATA_EMPS.mat", EXAMPLE / "DATA_EMPS.mat"]
DATA = next((p for p in _CANDIDATES if p.is_file()), None)
needs_data = pytest.mark.skipif(DATA is None, reason="EMPS data absent (../shared/data/emps/ or examples/emps/)")

# Published reference model (benchmark report): M, Fv, Fc, offset
M_REF, FV_REF, FC_REF, OFF_REF = 95.1089, 203.5034, 20.3935, -3.1648

TRUTH = (80.0, 150.0, 220.0, 15.0, 25.0)  # M kg, Fv+ Fv- N s/m, Fc+ Fc- N
KP, KV, GAIN, H, RES = 150.0, 250.0, 30.0, 1e-3, 5e-8


def _profile(rng, n):
    """Bang-bang acceleration moves between random positions in both directions, with rests."""
    r = np.zeros(n)
    x, k = 0.0, 0
    while k < n:
        target = rng.uniform(0.0, 0.2)
        vmax, amax = rng.uniform(0.03, 0.12), rng.uniform(0.5, 2.0)
        dist = abs(target - x)
        ta = vmax / amax
        if dist < vmax * ta:
            ta = math.sqrt(dist / amax)
            vmax = amax * ta
        tc = (dist - vmax * ta) / vmax
        total = 2 * ta + tc
        tt = np.arange(int(total / H) + 1) * H
        pos = np.where(tt < ta, 0.5 * amax * tt ** 2, np.where(tt < ta + tc, 0.5 * amax * ta ** 2 + vmax * (tt - ta),
                                                                dist - 0.5 * amax * np.clip(total - tt, 0, None) ** 2))
        seg = x + math.copysign(1.0, target - x) * pos
        take = min(seg.size, n - k)
        r[k:k + take] = seg[:take]
        k += take
        x = seg[take - 1]
        rest = int(rng.uniform(0.1, 0.3) / H)
        r[k:k + rest] = x
        k += rest
    return r[:n]


def _generate(seed, n=6000, sub=40, pulses=None):
    """Independent closed-loop generator (not the library's exact solution); ``pulses`` (V) is
    added to the controller output at the drive input and is part of the logged command."""
    rng = np.random.default_rng(seed)
    m, fvp, fvn, fcp, fcn = TRUTH
    r = _profile(rng, n)
    x = v = 0.0
    qm, u = np.zeros(n), np.zeros(n)
    qprev = qfprev = 0.0
    hs = H / sub
    for k in range(n):
        qk = RES * math.floor(x / RES + 0.5)
        qm[k] = qk
        qf = 0.5 * (qk + qprev)
        dq = (qf - qfprev) / H
        qprev, qfprev = qk, qf
        u[k] = min(10.0, max(-10.0, KV * (KP * (r[k] - qk) - dq))) + (0.0 if pulses is None else pulses[k])
        f = GAIN * u[k]
        for _ in range(sub):
            if v > 0:
                a = (f - fcp - fvp * v) / m
            elif v < 0:
                a = (f + fcn - fvn * v) / m
            else:
                a = (f - fcp) / m if f > fcp else ((f + fcn) / m if f < -fcn else 0.0)
            vn = v + hs * a
            if v != 0 and vn * v < 0:  # stops inside the substep (Karnopp: stays stopped for its rest)
                x += 0.5 * v * (-v / a)
                v = 0.0
                continue
            x += 0.5 * (v + vn) * hs
            v = vn
    return np.arange(n) * H, qm, r, u


_CSV_FORMAT = """format = "csv"
[time]
name = "time_ms"
unit = "ms"
[position]
name = "pos_mm"
unit = "mm"
resolution = 5e-5
[reference]
name = "ref_mm"
unit = "mm"
[command]
name = "u_V"
unit = "V"
gain = 30.0
[controller]
structure = "position-p/velocity-p"
kp = 150.0
kv = 250.0
saturation = 10.0
sample_time_s = 0.001
check_tolerance = 1e-6
"""


def _base():
    vals = {k: v for k, (v, _) in DEFAULTS.items()}
    srcs = {k: s for k, (_, s) in DEFAULTS.items()}
    vals["axis.mass_kg"], srcs["axis.mass_kg"] = 1.0, "test: placeholder"
    return LinearAxisPlant("base", vals, srcs)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_synthetic_closed_loop_log_recovered_within_its_intervals(tmp_path, seed):
    t, qm, r, u = _generate(seed)
    path = tmp_path / "log.csv"
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["time_ms", "pos_mm", "ref_mm", "u_V"])
        w.writerows(zip((f"{a:.17g}" for a in 1e3 * t), (f"{a:.17g}" for a in 1e3 * qm),
                        (f"{a:.17g}" for a in 1e3 * r), (f"{a:.17g}" for a in u)))
    (tmp_path / "fmt.toml").write_text(_CSV_FORMAT)
    log = load_axis_log(path, load_log_format(tmp_path / "fmt.toml"))
    assert log.resolution_m == pytest.approx(RES)
    fit = fit_linear_axis([log], _base())
    assert (fit.status, fit.solver_status) == ("ok", "converged")  # (status in the vocabulary since issue 33)
    for k, true in zip(PARAMETERS, TRUTH):
        p = fit.parameters[k]
        lo, hi = p["ci95"]
        assert lo <= true <= hi, (k, p)
        assert hi - lo < 0.02 * true, (k, p)  # informative: a broken fit cannot hide behind a wide interval
    assert fit.replays[0].errors_percent["force"] < 1.0


def test_plant_file_round_trip_and_minimal_file(tmp_path):
    from prsa_ctrl.identification.axis import axis_plant_toml

    # the minimal linear-axis file of the package's plant schema (prsa_ctrl.plant.schema.REQUIRED)
    p = tmp_path / "min.toml"
    p.write_text('mechanism = "linear-axis"\n[axis]\nmass_kg = { value = 12.5, source = "test: given" }\n'
                 '[drive]\ngain_n_per_unit = { value = 2.0, source = "t" }\nforce_limit_n = { value = 50.0, source = "t" }\n'
                 '[sensor]\nsample_time_s = { value = 0.001, source = "t" }\n'
                 'encoder_resolution_m = { value = 1e-6, source = "t" }\n')
    plant = load_axis_plant(p)
    assert plant.values["axis.mass_kg"] == 12.5
    assert plant.sources["friction.coulomb_positive_n"].startswith("default:")
    assert plant.values["drive.force_limit_n"] == 50.0
    q = tmp_path / "again.toml"
    q.write_text(axis_plant_toml(plant))
    again = load_axis_plant(q)
    assert dict(again.values) == dict(plant.values) and dict(again.sources) == dict(plant.sources)


@needs_data
def test_emps_fit_and_validate_end_to_end(tmp_path, capsys, emps_fit):
    """The two commands of examples/emps/README.md: the fit (tests/conftest.py: one per session),
    then its validation on the record."""
    fmt = str(EXAMPLE / "log.toml")
    assert emps_fit.code == 0, emps_fit.err
    out, js = emps_fit.toml, emps_fit.json
    rep = json.loads(js.read_text())
    eq = rep["equivalent"]
    for k in ("mass_kg", "viscous_n_s_per_m", "friction_positive_n", "friction_negative_n"):
        lo, hi = eq[k]["ci95"]
        assert lo < eq[k]["value"] < hi
    assert abs(eq["mass_kg"]["value"] / M_REF - 1) < 0.03
    assert abs(eq["viscous_n_s_per_m"]["value"] / FV_REF - 1) < 0.10
    assert eq["friction_positive_n"]["value"] > 0 > eq["friction_negative_n"]["value"]
    plant = load_axis_plant(out)
    assert plant.sources["axis.mass_kg"].startswith("fit: DATA_EMPS.mat")
    traces, rj = tmp_path / "T.csv", tmp_path / "R.json"
    capsys.readouterr()
    assert main(["--validate", str(out), str(DATA), "--log-format", fmt, "--json", str(rj), "--traces", str(traces)]) == 0
    mine = json.loads(rj.read_text())["replay"][0]["errors_percent"]
    ref = replay_axis(load_axis_plant(EXAMPLE / "reference-model.toml"),
                      load_axis_log(DATA, load_log_format(fmt))).errors_percent
    for k in ("position", "velocity", "force"):
        assert mine[k] <= ref[k], (k, mine, ref)
    with traces.open() as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["time_s", "position_measured", "position_simulated", "force_measured", "force_simulated"]
    assert len(rows) == 24841 + 1


@needs_data
@pytest.mark.slow
def test_held_back_replay_no_worse_than_the_published_model(tmp_path, capsys):
    """Issue 32's acceptance for the EMPS example: fitted on the first 60 % of the record
    (``--holdout 0.4``), the plant replays the held-back 40 % no worse than the published model
    replays the same samples (position, velocity, force; README: 0.00080 / 0.130 / 3.78 % against
    0.00106 / 0.134 / 4.70 %)."""
    fmt = str(EXAMPLE / "log.toml")
    js = tmp_path / "h.json"
    assert main([str(DATA), "--log-format", fmt, "--holdout", "0.4", "--out", str(tmp_path / "h.toml"),
                 "--json", str(js)]) == 0, capsys.readouterr().err
    held = json.loads(js.read_text())["holdout"]["replay"][0]
    log = load_axis_log(DATA, load_log_format(fmt))
    start = log.n - int(round(0.4 * log.n))
    assert held["log"].endswith(f"[{start}:{log.n}]")
    ref = replay_axis(load_axis_plant(EXAMPLE / "reference-model.toml"), log.window(start, log.n)).errors_percent
    mine = held["errors_percent"]
    for k in ("position", "velocity", "force"):
        assert mine[k] <= ref[k], (k, mine, ref)
    assert ref["force"] == pytest.approx(4.705, abs=0.005) and mine["force"] == pytest.approx(3.778, abs=0.01)


@needs_data
def test_published_model_replay_and_the_benchmarks_own_convention():
    """This code's replay of the published model, and the benchmark's published replay errors
    (position 0.0138 %, velocity 0.229 %, force 5.85 %) reproduced with the benchmark script's
    conventions: the command applied one sample after it is computed, compared as applied, and a
    simulation sample time of t(10) - t(9) = 0.99998 ms against the logged time base."""
    fmt = load_log_format(EXAMPLE / "log.toml")
    log = load_axis_log(DATA, fmt)
    ref = load_axis_plant(EXAMPLE / "reference-model.toml")
    e = replay_axis(ref, log).errors_percent
    assert e["position"] == pytest.approx(0.001085, rel=0.02)
    assert e["velocity"] == pytest.approx(0.1244, rel=0.02)
    assert e["force"] == pytest.approx(4.571, rel=0.01)
    tec = float(log.time_s[9] - log.time_s[8])
    r_on_sim_clock = np.interp(np.arange(log.n) * tec, log.time_s, log.reference_m)
    bench = dataclasses.replace(
        log, reference_m=r_on_sim_clock, sample_time_s=tec, command_logged="as-applied",
        controller=dataclasses.replace(log.controller, command_delay_samples=1, sample_time_s=tec))
    from prsa_ctrl.identification.axis import measured_velocity, relative_error, simulate_axis

    tr = simulate_axis(ref.theta, bench, x0=(0.0, 0.0))
    vm = measured_velocity(log)
    assert relative_error(log.position_m, tr.position_m) == pytest.approx(0.0138, abs=0.0005)
    assert relative_error(vm, tr.velocity_m_s) == pytest.approx(0.229, abs=0.001)
    assert relative_error(log.force_n, log.gain_n_per_unit * tr.command) == pytest.approx(5.85, abs=0.01)


def test_an_unstable_replay_raises_a_clear_error_not_nan():
    from prsa_ctrl.errors import SimulationError
    from prsa_ctrl.identification.logformat import AxisLog, ControllerSpec
    from prsa_ctrl.identification.axis import simulate_axis

    n = 2000
    t = np.arange(n) * H
    r = np.where(t > 0.01, 0.01, 0.0)
    ctl = ControllerSpec("position-p/velocity-p", 150.0, 250.0, 0.0, "difference", math.inf, H)
    log = AxisLog("unstable", t, np.zeros(n), np.zeros(n), "V", GAIN, H, reference_m=r, controller=ctl)
    with pytest.raises(SimulationError, match="diverged at t ="):
        simulate_axis((0.01, 0.0, 0.0, 0.0, 0.0), log)  # 10 g behind a loop tuned for 80 kg


def test_a_log_described_one_sample_off_is_detected():
    t, qm, r, u = _generate(5, n=4000)
    from prsa_ctrl.identification.logformat import AxisLog, ControllerSpec

    wrong = ControllerSpec("position-p/velocity-p", KP, KV, 0.0, "average2-difference", 10.0, H, command_delay_samples=1)
    log = AxisLog("syn", t, qm, u, "V", GAIN, H, reference_m=r, controller=wrong)
    fit = fit_linear_axis([log], _base())
    costs = fit.delay_costs
    assert set(costs) == {0, 1, 2} and min(costs, key=costs.get) == 0
    assert any("command delay of 0 samples fits better than the described 1" in w for w in fit.warnings)
    right = fit_linear_axis([dataclasses.replace(log, controller=dataclasses.replace(wrong, command_delay_samples=0))],
                            _base())
    assert not any("command delay" in w for w in right.warnings)


def test_a_test_signal_at_the_drive_input_is_replayed(tmp_path):
    """A cross-test-like record: a 0/2 V pulse train (period 0.5 s) added to the controller output
    at the drive input, logged inside the command and in its own column."""
    import scipy.io

    n = 3000
    pulses = np.where((np.arange(n) * H) % 0.5 < 0.1, 2.0, 0.0)
    t, qm, r, u = _generate(7, n=n, pulses=pulses)
    mat = tmp_path / "pulses.mat"
    scipy.io.savemat(mat, {"t": t[:, None], "qm": qm[:, None], "qg": r[:, None], "vir": u[:, None],
                           "pulses_N": pulses[:, None], "gtau": GAIN, "kp": KP, "kv": KV})
    log = load_axis_log(mat, load_log_format(EXAMPLE / "log.toml"))
    assert log.test_signal is not None and log.test_signal.max() == 2.0
    truth = _base().with_values(dict(zip(PARAMETERS, TRUTH)), {k: "test: truth" for k in PARAMETERS})
    with_pulses = replay_axis(truth, log).errors_percent
    without = replay_axis(truth, dataclasses.replace(log, test_signal=None)).errors_percent
    assert with_pulses["force"] < 0.5 and with_pulses["velocity"] < 0.5
    assert without["force"] > 10 * with_pulses["force"]
