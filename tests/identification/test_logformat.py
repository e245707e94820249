"""Log descriptions (prsa_ctrl.identification.logformat) and the described-log modes of prsa-fit: bad inputs get
one line naming the file and the key, column or variable, exit 2, and nothing is written."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.io

from prsa_ctrl.cli.fit import main
from prsa_ctrl.identification.logformat import LogFormatError, load_axis_log, load_log_format

KP, KV, GAIN, H = 160.0, 240.0, 35.0, 1e-3

GOOD = """format = "mat"
[time]
name = "t"
unit = "s"
[position]
name = "qm"
unit = "m"
[reference]
name = "qg"
unit = "m"
[command]
name = "vir"
unit = "V"
gain = "gtau"
[test_signal]
name = "pulses"
unit = "V"
optional = true
[controller]
structure = "position-p/velocity-p"
kp = "kp"
kv = "kv"
velocity_estimate = "average2-difference"
saturation = 10.0
sample_time_s = 0.001
"""


def _controller_output(qm, qg):
    """The described controller written out once more, independently of the library."""
    out = np.empty_like(qm)
    for k in range(qm.size):
        q1 = qm[k - 1] if k >= 1 else qm[0]
        q2 = qm[k - 2] if k >= 2 else q1 if k == 1 else qm[0]
        dq = ((qm[k] + q1) / 2 - (q1 + q2) / 2) / H
        out[k] = min(10.0, max(-10.0, KV * (KP * (qg[k] - qm[k]) - dq)))
    return out


@pytest.fixture()
def files(tmp_path):
    rng = np.random.default_rng(3)
    n = 400
    t = np.arange(n) * H
    qg = 0.05 * (1 - np.cos(2 * np.pi * t / 0.4))
    qm = np.round((qg - 2e-4 * np.sin(2 * np.pi * t / 0.4) + 2e-6 * rng.standard_normal(n)) / 5e-8) * 5e-8
    vir = _controller_output(qm, qg)
    mat = tmp_path / "log.mat"
    scipy.io.savemat(mat, {"t": t[:, None], "qm": qm[:, None], "qg": qg[:, None], "vir": vir[:, None],
                           "gtau": GAIN, "kp": KP, "kv": KV})
    fmt = tmp_path / "fmt.toml"
    fmt.write_text(GOOD)
    return tmp_path, mat, fmt, (t, qm, qg, vir)


def _run(capsys, argv):
    code = main(argv)
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def test_good_description_loads_in_si(files):
    d, mat, fmt, (t, qm, qg, vir) = files
    log = load_axis_log(mat, load_log_format(fmt))
    assert log.n == t.size and log.gain_n_per_unit == GAIN
    assert log.controller.kp == KP and log.controller.kv == KV
    assert log.test_signal is None  # optional, absent
    np.testing.assert_allclose(log.force_n, GAIN * vir)
    assert log.sources["controller.kp"] == "log.mat: kp"


def test_csv_in_mm_with_numeric_gains(files):
    d, mat, fmt, (t, qm, qg, vir) = files
    csv = d / "log.csv"
    rows = ["time_ms,pos_mm,ref_mm,u_V"] + [f"{a * 1e3:.17g},{b * 1e3:.17g},{c * 1e3:.17g},{e:.17g}" for a, b, c, e in zip(t, qm, qg, vir)]
    csv.write_text("\n".join(rows) + "\n")
    text = (GOOD.replace('format = "mat"', 'format = "csv"').replace('"t"', '"time_ms"').replace('unit = "s"', 'unit = "ms"')
            .replace('"qm"', '"pos_mm"').replace('"qg"', '"ref_mm"').replace('unit = "m"', 'unit = "mm"')
            .replace('"vir"', '"u_V"').replace('"gtau"', "35.0").replace('"kp"', "160.0").replace('"kv"', "240.0"))
    (d / "csv.toml").write_text(text)
    log = load_axis_log(csv, load_log_format(d / "csv.toml"))
    np.testing.assert_allclose(log.position_m, qm, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(log.time_s, t, atol=1e-12)


@pytest.mark.parametrize("old,new,expect", [
    ('name = "qm"', 'name = "qx"', "variable 'qx', not in the file"),
    ('[position]\nname = "qm"\nunit = "m"', '[position]\nname = "qm"\nunit = "inch"', "[position] unit = 'inch'"),
    ('[position]\nname = "qm"\nunit = "m"', '[position]\nname = "qm"\nunit = "mm"', "[controller] does not reproduce"),
    ('kv = "kv"', "kv = 100.0", "[controller] does not reproduce"),
    ('unit = "s"', 'unit = "ms"', "[time] 't' (unit 'ms')"),
    ('gain = "gtau"', 'gain = "gtauu"', "variable 'gtauu', not in the file"),
    ('gain = "gtau"\n', "", "needs gain"),
    ('[test_signal]\nname = "pulses"\nunit = "V"', '[test_signal]\nname = "pulses"\nunit = "N"', "[test_signal] unit"),
    ('structure = "position-p/velocity-p"', 'structure = "pid"', "[controller] structure = 'pid'"),
    ("saturation = 10.0", "saturation = -1.0", "[controller] saturation = -1.0"),
    ("sample_time_s = 0.001", "sample_time_s = 0.002", "deviates"),
    ('format = "mat"', 'format = "mat"\ncolour = "red"', "key 'colour'"),
    ('[reference]\nname = "qg"\nunit = "m"\n', "", "needs a [reference] section"),
])
def test_bad_description_is_one_line_exit_2_nothing_written(files, capsys, old, new, expect):
    d, mat, fmt, _ = files
    text = GOOD.replace(old, new)
    assert text != GOOD
    fmt.write_text(text)
    out, js = d / "fitted.toml", d / "fit.json"
    code, stdout, err = _run(capsys, [str(mat), "--log-format", str(fmt), "--out", str(out), "--json", str(js)])
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("prsa-fit: error: ")
    assert expect in err
    assert (str(fmt) in err) or (str(mat) in err)
    assert not out.exists() and not js.exists()


def test_reproduction_error_names_the_shift_when_the_log_is_one_sample_late(files, capsys):
    d, mat, fmt, (t, qm, qg, vir) = files
    late = np.r_[vir[0], vir[:-1]]  # logged as applied one sample later
    scipy.io.savemat(mat, {"t": t[:, None], "qm": qm[:, None], "qg": qg[:, None], "vir": late[:, None],
                           "gtau": GAIN, "kp": KP, "kv": KV})
    with pytest.raises(LogFormatError, match=r"shift of \+1 samples"):
        load_axis_log(mat, load_log_format(fmt))


def test_missing_files_and_wrong_plant_mechanism(files, capsys, tmp_path):
    d, mat, fmt, _ = files
    code, _, err = _run(capsys, [str(mat), "--log-format", str(d / "nope.toml"), "--out", str(d / "o.toml")])
    assert code == 2 and "nope.toml" in err and err.count("\n") == 1
    code, _, err = _run(capsys, [str(d / "nope.mat"), "--log-format", str(fmt), "--out", str(d / "o.toml")])
    assert code == 2 and "nope.mat" in err and "not found" in err
    iprsm = tmp_path / "iprsm.toml"
    iprsm.write_text('name = "x"\n[screw]\n')
    code, _, err = _run(capsys, ["--validate", str(iprsm), str(mat), "--log-format", str(fmt), "--traces",
                                 str(d / "t.csv")])
    assert code == 2 and "mechanism" in err and str(iprsm) in err
    assert not (d / "t.csv").exists() and not (d / "o.toml").exists()


def test_validate_needs_a_log_format_and_refuses_fit_flags(files, capsys):
    d, mat, fmt, _ = files
    plant = d / "p.toml"
    plant.write_text('mechanism = "linear-axis"\n[axis]\nmass_kg = { value = 10.0, source = "test" }\n'
                     '[drive]\ngain_n_per_unit = { value = 2.0, source = "t" }\nforce_limit_n = { value = 50.0, source = "t" }\n'
                     '[sensor]\nsample_time_s = { value = 0.001, source = "t" }\n'
                     'encoder_resolution_m = { value = 1e-6, source = "t" }\n')
    code, _, err = _run(capsys, ["--validate", str(plant), str(mat)])
    assert code == 2 and "--log-format" in err and str(mat) in err
    code, _, err = _run(capsys, ["--validate", str(plant), str(mat), "--log-format", str(fmt), "--out", str(d / "x.toml")])
    assert code == 2 and "--out" in err and not (d / "x.toml").exists()
    code, _, err = _run(capsys, [str(mat), "--log-format", str(fmt), "--out", str(d / "x.toml"), "--traces", "t.csv"])
    assert code == 2 and "--traces" in err


def test_output_path_checked_before_the_fit(files, capsys):
    d, mat, fmt, _ = files
    code, _, err = _run(capsys, [str(mat), "--log-format", str(fmt), "--out", str(d / "no" / "dir" / "x.toml")])
    assert code == 2 and "--out" in err and "does not exist" in err
    code, _, err = _run(capsys, [str(mat), "--log-format", str(fmt), "--out", str(mat)])
    assert code == 2 and "input file" in err


def test_a_loose_tolerance_still_refuses_a_log_that_fits_better_shifted(files):
    d, mat, fmt, (t, qm, qg, vir) = files
    late = np.r_[vir[0], vir[:-1]]
    scipy.io.savemat(mat, {"t": t[:, None], "qm": qm[:, None], "qg": qg[:, None], "vir": late[:, None],
                           "gtau": GAIN, "kp": KP, "kv": KV})
    fmt.write_text(GOOD + "check_tolerance = 0.9\n")
    with pytest.raises(LogFormatError, match=r"a shift of \+1 samples gives .*expected the described alignment"):
        load_axis_log(mat, load_log_format(fmt))


def test_validate_a_standard_csv_without_a_description_runs_open_loop(tmp_path, capsys):
    """Standard columns (time_s, position_m, speed_m_s, force_n): replayed open loop from the logged
    force; a free mass under a constant force is reproduced exactly (exact zero-order-hold replay)."""
    n, m, f = 200, 2.0, 4.0
    t = np.arange(n) * H
    x = 0.5 * f / m * t ** 2
    path = tmp_path / "free.csv"
    v = f / m * t  # the logged speed also sets the replay's initial speed (0 here)
    path.write_text("time_s,position_m,speed_m_s,force_n\n"
                    + "".join(f"{a:.17g},{b:.17g},{c:.17g},{f}\n" for a, b, c in zip(t, x, v)))
    plant = tmp_path / "p.toml"
    plant.write_text(f'mechanism = "linear-axis"\n[axis]\nmass_kg = {{ value = {m}, source = "test" }}\n'
                     '[drive]\ngain_n_per_unit = { value = 1.0, source = "t" }\nforce_limit_n = { value = 1e6, source = "t" }\n'
                     '[sensor]\nsample_time_s = { value = 0.001, source = "t" }\n'
                     'encoder_resolution_m = { value = 1e-9, source = "t" }\n')
    rj = tmp_path / "r.json"
    code, out, err = _run(capsys, ["--validate", str(plant), str(path), "--json", str(rj)])
    assert code == 0, err
    import json

    rep = json.loads(rj.read_text())["replay"][0]
    assert rep["replay"] == "open loop from the logged command"
    e = rep["errors_percent"]
    assert e["position"] < 1e-9 and e["velocity"] < 1e-9 and e["force"] == 0.0
    assert "open loop" in out


def test_as_applied_log_with_a_delay_is_reconstructed_with_the_shift(files):
    d, mat, fmt, (t, qm, qg, vir) = files
    late = np.r_[0.0, vir[:-1]]
    scipy.io.savemat(mat, {"t": t[:, None], "qm": qm[:, None], "qg": qg[:, None], "vir": late[:, None],
                           "gtau": GAIN, "kp": KP, "kv": KV})
    text = GOOD.replace('gain = "gtau"', 'gain = "gtau"\nlogged = "as-applied"') + "command_delay_samples = 1\n"
    fmt.write_text(text)
    log = load_axis_log(mat, load_log_format(fmt))
    assert log.command_logged == "as-applied" and log.controller.command_delay_samples == 1


def test_a_pi_velocity_loop_is_reconstructed(files):
    d, mat, fmt, (t, qm, qg, vir) = files
    ki = 20.0
    u, integ = np.empty_like(qm), 0.0
    for k in range(qm.size):  # u = kv (e_v + ki * dt * sum of e_v), e_v = kp (qg - qm) - dq
        q1 = qm[k - 1] if k else qm[0]
        q2 = qm[k - 2] if k >= 2 else q1 if k == 1 else qm[0]
        ev = KP * (qg[k] - qm[k]) - ((qm[k] + q1) / 2 - (q1 + q2) / 2) / H
        integ += ki * H * ev
        u[k] = min(10.0, max(-10.0, KV * (ev + integ)))
    scipy.io.savemat(mat, {"t": t[:, None], "qm": qm[:, None], "qg": qg[:, None], "vir": u[:, None],
                           "gtau": GAIN, "kp": KP, "kv": KV})
    fmt.write_text(GOOD.replace("position-p/velocity-p", "position-p/velocity-pi") + "ki = 20.0\ncheck_tolerance = 1e-9\n")
    log = load_axis_log(mat, load_log_format(fmt))
    assert log.controller.ki == ki
    fmt.write_text(GOOD.replace("position-p/velocity-p", "position-p/velocity-pi") + "ki = 40.0\n")
    with pytest.raises(LogFormatError, match="does not reproduce"):
        load_axis_log(mat, load_log_format(fmt))


def test_a_mat_log_without_a_log_description_is_one_line(tmp_path, capsys):
    """A .mat log given to prsa-fit without --log-format: one line pointing at --log-format, exit 2
    (it used to be parsed as a CSV: "'utf-8' codec can't decode byte ...")."""
    from prsa_ctrl.cli.fit import main

    log = tmp_path / "record.mat"
    log.write_bytes(b"MATLAB 5.0 MAT-file" + bytes(200))
    out = tmp_path / "fitted.toml"
    assert main([str(log), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--log-format" in err[0] and "record.mat" in err[0]
    assert not out.exists()
