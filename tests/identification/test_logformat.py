"""Log descriptions (prsa_ctrl.identification.logformat) and the described-log modes of prsa-fit: bad inputs get
one line naming the file and the key, column or variable, exit 2, and nothing is written."""

from __future__ import annotations

import contextlib
import io
import json
import math
import tomllib
import warnings
from pathlib import Path

import numpy as np
import pytest
import scipy.io

from prsa_ctrl.cli.fit import main
from prsa_ctrl.identification.logformat import (LogFormatError, load_axis_log, load_log_format, load_motor_record, motor_record)
from prsa_ctrl.plant import load_plant

from test_fit import _load, _log, _truth  # (tests/identification on sys.path)


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
    assert log.n == t.size
    assert log.gain_n_per_unit == GAIN
    assert log.controller.kp == KP
    assert log.controller.kv == KV
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
    assert err.count("\n") == 1
    assert err.startswith("prsa-fit: error: ")
    assert expect in err
    assert (str(fmt) in err) or (str(mat) in err)
    assert not out.exists()
    assert not js.exists()


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
    assert code == 2
    assert "nope.toml" in err
    assert err.count("\n") == 1
    code, _, err = _run(capsys, [str(d / "nope.mat"), "--log-format", str(fmt), "--out", str(d / "o.toml")])
    assert code == 2
    assert "nope.mat" in err
    assert "not found" in err
    iprsm = tmp_path / "iprsm.toml"
    iprsm.write_text('name = "x"\n[screw]\n')
    code, _, err = _run(capsys, ["--validate", str(iprsm), str(mat), "--log-format", str(fmt), "--traces",
                                 str(d / "t.csv")])
    assert code == 2
    assert "mechanism" in err
    assert str(iprsm) in err
    assert not (d / "t.csv").exists()
    assert not (d / "o.toml").exists()


def test_validate_needs_a_log_format_and_refuses_fit_flags(files, capsys):
    d, mat, fmt, _ = files
    plant = d / "p.toml"
    plant.write_text('mechanism = "linear-axis"\n[axis]\nmass_kg = { value = 10.0, source = "test" }\n'
                     '[drive]\ngain_n_per_unit = { value = 2.0, source = "t" }\nforce_limit_n = { value = 50.0, source = "t" }\n'
                     '[sensor]\nsample_time_s = { value = 0.001, source = "t" }\n'
                     'encoder_resolution_m = { value = 1e-6, source = "t" }\n')
    code, _, err = _run(capsys, ["--validate", str(plant), str(mat)])
    assert code == 2
    assert "--log-format" in err
    assert str(mat) in err
    code, _, err = _run(capsys, ["--validate", str(plant), str(mat), "--log-format", str(fmt), "--out", str(d / "x.toml")])
    assert code == 2
    assert "--out" in err
    assert not (d / "x.toml").exists()
    code, _, err = _run(capsys, [str(mat), "--log-format", str(fmt), "--out", str(d / "x.toml"), "--traces", "t.csv"])
    assert code == 2
    assert "--traces" in err


def test_output_path_checked_before_the_fit(files, capsys):
    d, mat, fmt, _ = files
    code, _, err = _run(capsys, [str(mat), "--log-format", str(fmt), "--out", str(d / "no" / "dir" / "x.toml")])
    assert code == 2
    assert "--out" in err
    assert "does not exist" in err
    code, _, err = _run(capsys, [str(mat), "--log-format", str(fmt), "--out", str(mat)])
    assert code == 2
    assert "input file" in err


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
    assert e["position"] < 1e-9
    assert e["velocity"] < 1e-9
    assert e["force"] == 0.0
    assert "open loop" in out


def test_as_applied_log_with_a_delay_is_reconstructed_with_the_shift(files):
    d, mat, fmt, (t, qm, qg, vir) = files
    late = np.r_[0.0, vir[:-1]]
    scipy.io.savemat(mat, {"t": t[:, None], "qm": qm[:, None], "qg": qg[:, None], "vir": late[:, None],
                           "gtau": GAIN, "kp": KP, "kv": KV})
    text = GOOD.replace('gain = "gtau"', 'gain = "gtau"\nlogged = "as-applied"') + "command_delay_samples = 1\n"
    fmt.write_text(text)
    log = load_axis_log(mat, load_log_format(fmt))
    assert log.command_logged == "as-applied"
    assert log.controller.command_delay_samples == 1


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
    assert len(err) == 1
    assert "--log-format" in err[0]
    assert "record.mat" in err[0]
    assert not out.exists()


# --- memory bounds, what a variable is, description keys (issue 31) ------------------------------

def _mat_vars(files, **extra):
    d, mat, fmt, (t, qm, qg, vir) = files
    return {"t": t[:, None], "qm": qm[:, None], "qg": qg[:, None], "vir": vir[:, None], "gtau": GAIN, "kp": KP,
            "kv": KV, **extra}


def _peak_bytes(fn):
    import tracemalloc

    tracemalloc.start()
    try:
        fn()
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return peak


@pytest.mark.parametrize("first", [True, False])
def test_a_mat_log_reads_only_the_named_variables(files, first):
    """An unused compressed 4000 x 4000 uint8 variable (16 MB, 128 MB as float) is never loaded,
    before or after the named ones (was: every variable loaded and up-cast: 145 MB peak here, 3.6 GB
    for a 20000 x 20000 one in a 0.98 MB file)."""
    d, mat, fmt, _ = files
    junk = {"junk": np.zeros((4000, 4000), np.uint8)}
    named = _mat_vars(files)
    scipy.io.savemat(mat, {**junk, **named} if first else {**named, **junk}, do_compression=True)
    del junk
    assert mat.stat().st_size < 1_000_000
    got = {}
    peak = _peak_bytes(lambda: got.setdefault("log", load_axis_log(mat, load_log_format(fmt))))
    assert got["log"].n == 400
    assert peak < 4_000_000, peak  # not even the 16 MB of the unused variable's own bytes


@pytest.mark.parametrize("compressed", [True, False])
def test_a_named_variable_above_the_sample_bound_is_refused_before_it_is_read(files, compressed):
    d, mat, fmt, _ = files
    scipy.io.savemat(mat, _mat_vars(files, vir=np.zeros((2001, 1000))), do_compression=compressed)  # 16 MB
    with pytest.raises(LogFormatError) as info:
        load_axis_log(mat, load_log_format(fmt))
    assert "variable 'vir' ([command] name) has shape 2001x1000 (2001000 values); expected at most 2000000" in str(info.value)
    peak = _peak_bytes(lambda: pytest.raises(LogFormatError, load_axis_log, mat, load_log_format(fmt)))
    assert peak < 2_000_000, peak  # its 16 MB never read


@pytest.mark.parametrize("value,what", [
    ({"a": 1.0}, "holds a MATLAB struct"),
    (np.array([np.zeros(3), np.ones(2)], dtype=object), "holds a MATLAB cell array"),
    ("fast", "holds text (a MATLAB char array)"),
    ("complex", "holds complex numbers (class double)"),
])
def test_a_named_variable_that_is_not_real_numbers_says_what_it_is(files, capsys, value, what):
    """Was: "names variable 'qm', not in the file; it has gtau, kp, ..." for a struct, cell or complex."""
    d, mat, fmt, (t, qm, qg, vir) = files
    scipy.io.savemat(mat, _mat_vars(files, qm=qm[:, None] * (1 + 1j) if isinstance(value, str) and value == "complex"
                                    else value))
    code, _, err = _run(capsys, [str(mat), "--log-format", str(fmt), "--out", str(d / "fitted.toml")])
    assert code == 2
    assert err.count("\n") == 1
    assert f"{mat}: variable 'qm' ([position] name) {what}; expected a real numeric vector" in err
    assert not (d / "fitted.toml").exists()


def test_an_empty_or_cut_mat_file_is_bad_input(files, capsys):
    """Was: an empty .mat "failed (MatReadError)", exit 3 with no file or key named."""
    d, mat, fmt, _ = files
    whole = mat.read_bytes()
    for data, expect in ((b"", "(an empty file)"), (whole[:100], "cannot be read as a MATLAB .mat file"),
                         (whole[:len(whole) // 2], "runs past the end of the file")):
        mat.write_bytes(data)
        code, _, err = _run(capsys, [str(mat), "--log-format", str(fmt), "--out", str(d / "fitted.toml")])
        assert code == 2, err
        assert err.count("\n") == 1, err
        assert err.startswith(f"prsa-fit: error: {mat}: cannot be read as a MATLAB .mat file")
        assert expect in err


def test_a_v4_and_an_uncompressed_mat_file_still_load(files):
    d, mat, fmt, (t, qm, qg, vir) = files
    for kw in ({"format": "4"}, {"do_compression": False}):
        scipy.io.savemat(mat, _mat_vars(files, junk=np.zeros((300, 300))), **kw)
        log = load_axis_log(mat, load_log_format(fmt))
        np.testing.assert_array_equal(log.position_m, qm)
        assert log.gain_n_per_unit == GAIN
        assert log.controller.kv == KV


def _csv_files(files, extra_header="", extra_cells=""):
    d, mat, fmt, (t, qm, qg, vir) = files
    csv = d / "log.csv"
    rows = [f"t,qm,qg,vir{extra_header}"] + [f"{a:.17g},{b:.17g},{c:.17g},{e:.17g}{extra_cells}" for a, b, c, e in zip(t, qm, qg, vir)]
    csv.write_text("\n".join(rows) + "\n")
    (d / "csv.toml").write_text(GOOD.replace('format = "mat"', 'format = "csv"').replace('"gtau"', "35.0")
                                .replace('"kp"', "160.0").replace('"kv"', "240.0"))
    return csv, d / "csv.toml"


def test_the_described_csv_reader_keeps_only_the_named_columns(files):
    """Unused columns are not parsed (text allowed there); a duplicate unused name is no error."""
    csv, fmt = _csv_files(files, ",note,note", ",ok,also text")
    log = load_axis_log(csv, load_log_format(fmt))
    np.testing.assert_array_equal(log.position_m, files[3][1])


def test_a_duplicate_named_csv_column_is_refused(files, capsys):
    """Was: the last of two 'qm' columns used, silently."""
    csv, fmt = _csv_files(files, ",qm", ",0")
    code, _, err = _run(capsys, [str(csv), "--log-format", str(fmt), "--out", str(csv.parent / "fitted.toml")])
    assert code == 2
    assert err.count("\n") == 1
    assert f"{csv}: column 'qm' ([position] name) appears twice in the header (columns 2 and 5, line 1)" in err


def test_the_described_csv_reader_is_streamed_and_refused_at_the_row_limit(tmp_path, monkeypatch):
    """Rows past the limit are never held (was: the whole file read into lists, then refused: 695 MB
    for 3 M rows): here 200 000 rows of 6 columns against a limit of 1000."""
    import prsa_ctrl.identification.logfile as lfile
    import prsa_ctrl.identification.logformat as lf

    monkeypatch.setattr(lfile, "MAX_SAMPLES", 1000)
    n = 200_000
    t = np.arange(n) * 1e-3
    p = tmp_path / "long.csv"
    with p.open("w") as fh:
        fh.write("time_s,position_m,force_n,a,b,c\n")
        for k in range(0, n, 10_000):
            block = t[k:k + 10_000]
            fh.write("".join(f"{x:.17g},{x * 0.5:.17g},{1.0 + x:.17g},1,2,3\n" for x in block))
    with pytest.raises(LogFormatError, match=r"long\.csv: more than 1000 data rows \(line 1002\); expected at most 1000"):
        lf.load_axis_log(p, lf.DEFAULT_CSV_FORMAT)
    peak = _peak_bytes(lambda: pytest.raises(LogFormatError, lf.load_axis_log, p, lf.DEFAULT_CSV_FORMAT))
    assert peak < 1_000_000, peak  # the file's 200 000 rows would take tens of MB as lists


def test_a_log_file_above_the_record_paths_byte_limit_is_refused_before_reading(files, monkeypatch):
    import prsa_ctrl.identification.logfile as lfile

    d, mat, fmt, _ = files
    monkeypatch.setattr(lfile, "MAX_FILE_BYTES", 1000)
    with pytest.raises(LogFormatError, match=rf"{mat.stat().st_size} bytes; expected at most 1000 bytes"):
        load_axis_log(mat, load_log_format(fmt))


@pytest.mark.parametrize("old,new,expect", [
    ('[time]\nname = "t"', '[time]\noptional = true\nname = "t"', "[time] optional = true: [time] is required"),
    ('optional = true', 'optional = "no"', "[test_signal] optional = 'no': expected true or false"),
    ('optional = true', 'optional = 1', "[test_signal] optional = 1: expected true or false"),
])
def test_optional_is_a_boolean_of_an_optional_section(files, capsys, old, new, expect):
    """Was: optional = true on [time] "failed (TypeError)" (exit 3); optional = "no" read as true."""
    d, mat, fmt, _ = files
    fmt.write_text(GOOD.replace(old, new))
    code, _, err = _run(capsys, [str(mat), "--log-format", str(fmt), "--out", str(d / "fitted.toml")])
    assert code == 2
    assert err.count("\n") == 1
    assert f"{fmt}: {expect}" in err


def test_optional_false_and_a_byte_order_mark_are_accepted(files):
    """A description saved with a UTF-8 BOM loads, as plant, scene and data files do (was refused)."""
    d, mat, fmt, _ = files
    fmt.write_bytes(b"\xef\xbb\xbf" + GOOD.replace('name = "t"', 'name = "t"\noptional = false').encode())
    log = load_axis_log(mat, load_log_format(fmt))
    assert log.n == 400


def test_axis_log_checks_its_arrays():
    """Was: a raw IndexError (or a silent misfit) for arrays of different lengths."""
    from prsa_ctrl.identification.logformat import AxisLog

    t = np.arange(100) * 1e-3
    AxisLog("ok", t, np.zeros(100), np.zeros(100), "V", 1.0, 1e-3)
    for kwargs, expect in (({"position_m": np.zeros(99)}, r"position_m has shape \(99,\); expected \(100,\) like time_s"),
                           ({"reference_m": np.zeros(3)}, r"reference_m has shape \(3,\); expected \(100,\)"),
                           ({"command": np.full(100, np.nan)}, r"command\[0\] = nan; expected finite values"),
                           ({"time_s": np.zeros(0), "position_m": np.zeros(0), "command": np.zeros(0)}, "at least 2"),
                           ({"gain_n_per_unit": 0.0}, r"gain_n_per_unit = 0.0; expected a finite number > 0"),
                           ({"sample_time_s": float("inf")}, r"sample_time_s = inf")):
        args = {"name": "bad", "time_s": t, "position_m": np.zeros(100), "command": np.zeros(100), "command_unit": "V",
                "gain_n_per_unit": 1.0, "sample_time_s": 1e-3, **kwargs}
        with pytest.raises(ValueError, match=expect):
            AxisLog(**args)


def test_a_holdout_that_leaves_too_few_samples_names_the_flag_and_the_log(files, capsys):
    """Was: "window 360:400 of 400 samples; expected at least 50 samples inside" (no flag, no log)."""
    d, mat, fmt, _ = files
    code, _, err = _run(capsys, [str(mat), "--log-format", str(fmt), "--holdout", "0.1", "--out", str(d / "f.toml")])
    assert code == 2
    assert err.count("\n") == 1
    assert (f"--holdout 0.1: {mat} has 400 samples, which leaves 40 held out and 360 to fit; expected a fraction that "
            "leaves at least 50 samples in each part") in err
    assert not (d / "f.toml").exists()


def test_a_rotary_description_with_a_byte_order_mark_is_fitted_in_motor_coordinates(tmp_path):
    """The mode choice reads the description as load_log_format does (a BOM made it the linear path)."""
    from prsa_ctrl.cli.axis import motor_log_mode

    fmt = tmp_path / "rotary.toml"
    fmt.write_bytes(b"\xef\xbb\xbf" + b'axis = "rotary"\n[time]\nname = "t"\nunit = "s"\n')
    assert motor_log_mode(["log.csv", "--log-format", str(fmt), "--out", "o.toml"])


@pytest.mark.parametrize("fmt_kw", [{}, {"format": "4"}])
def test_a_missing_variable_lists_the_first_50_names_of_a_large_file(files, fmt_kw):
    d, mat, fmt, _ = files
    many = {f"v{i}": np.zeros(1) for i in range(80)}
    named = _mat_vars(files)
    del named["qm"]
    scipy.io.savemat(mat, {**many, **named}, **fmt_kw)
    with pytest.raises(LogFormatError) as info:
        load_axis_log(mat, load_log_format(fmt))
    msg = str(info.value)
    assert "names variable 'qm', not in the file; it has v0, v1," in msg
    assert msg.endswith("v49, ... (86 in all)")


# ------------------------------------------------------------------------------------------------
# A load-coordinate log fitted with a screw plant (prsa-fit LOG --log-format F --plant SCREW):
# a [load] declared in kN for a log in N is refused before the fit, naming the column, its declared
# unit and the plant's rated load; a [position] declared in mm for a log in m is refused naming the
# description's columns and units, not the record's internal columns.
# ------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    d = tmp_path_factory.mktemp("units")
    base, rec, a = _write_logs(d, "ballscrew-32x10", duration_s=0.5)
    return d, base


def _fit(d, fmt_text, csv, capsys):
    (d / "f.toml").write_text(fmt_text)
    out = d / f"out-{csv.stem}-{len(list(d.glob('out-*')))}.toml"
    capsys.readouterr()
    code = main([str(csv), "--log-format", str(d / "f.toml"), "--plant", "ballscrew-32x10", "--out", str(out)])
    return code, capsys.readouterr().err.strip(), out


def test_load_in_kN_declared_is_refused_before_the_fit(logs, capsys):
    d, base = logs
    raw = np.loadtxt(d / "load.csv", delimiter=",", skiprows=1)
    peak_kn = float(np.max(np.abs(raw[:, 3])))  # the file's load column, read as kN
    rated = base.values["screw.rated_load_n"]
    assert 1e3 * peak_kn > 2 * rated > peak_kn  # the log itself is plausible, its kN reading is not
    code, err, out = _fit(d, LOAD_TOML.replace('unit = "N"\n', 'unit = "kN"\n', 2).replace(
        '[command]\nname = "f_n"\nunit = "kN"', '[command]\nname = "f_n"\nunit = "N"'), d / "load.csv", capsys)
    assert code == 2
    assert "\n" not in err
    assert not out.exists()
    assert "[load] column 'fz'" in err
    assert "kN" in err
    assert f"{peak_kn:.6g} kN" in err
    assert f"{rated:.6g} N" in err
    with pytest.raises(LogFormatError, match="rated_load_n"):
        load_motor_record(d / "load.csv", load_log_format(d / "f.toml"), base)
    # the same log with its load in N passes the check (prsa-fit on it, exit 0, is
    # test_fits_in_both_coordinates_agree below)
    (d / "f-n.toml").write_text(LOAD_TOML)
    rec, _ = load_motor_record(d / "load.csv", load_log_format(d / "f-n.toml"), base)
    assert np.max(np.abs(rec.axial_load_n)) == pytest.approx(peak_kn, rel=1e-12)  # read in N as written


def test_position_in_m_declared_as_mm_names_the_description(logs, capsys):
    d, base = logs
    raw = np.loadtxt(d / "load.csv", delimiter=",", skiprows=1)
    raw[:, 1] *= 1e-3  # the log now holds metres; its description still says mm
    np.savetxt(d / "load-m.csv", raw, delimiter=",", header="t,x_mm,f_n,fz", comments="", fmt="%.17g")
    code, err, out = _fit(d, LOAD_TOML, d / "load-m.csv", capsys)
    assert code == 2
    assert "\n" not in err
    assert not out.exists()
    assert "[position] column 'x_mm' (mm)" in err
    assert "[command] column 'f_n' (N)" in err
    assert "f.toml" in err
    assert "torque_command_n_m" not in err
    assert "nut_angle_rad" not in err


# ------------------------------------------------------------------------------------------------
# Acceptance "Bad logs" (issue 21) on the EMPS record and a synthetic CSV: wrong variable names,
# units that disagree with the data, a controller description that cannot reproduce the logged
# command: one line naming the file and the column or key, exit 2, nothing written.
# ------------------------------------------------------------------------------------------------

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "emps"
DATA = EXAMPLE / "DATA_EMPS.mat"
EMPS_LOG_TOML = (EXAMPLE / "log.toml").read_text()
needs_data = pytest.mark.skipif(not DATA.is_file(), reason="examples/emps/DATA_EMPS.mat not in this checkout")


def _run_fit(capsys, argv):
    capsys.readouterr()
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _sub(old: str, new: str, count: int = 1) -> str:
    text = EMPS_LOG_TOML.replace(old, new, count)
    assert text != EMPS_LOG_TOML, old
    return text


POSITION = '[position]                 # load position from the motor encoder (50 000 counts/rev)\nname = "qm"\nunit = "m"'
REFERENCE = '[reference]                # position reference given to the controller\nname = "qg"\nunit = "m"'

CASES = {
    # wrong variable names: the message names the key and the variable, and lists what the file has
    "time name": (_sub('name = "t"', 'name = "time"'), "[time] name names variable 'time', not in the file"),
    "position name": (_sub('name = "qm"', 'name = "q"'), "[position] name names variable 'q', not in the file"),
    "reference name": (_sub('name = "qg"', 'name = "qref"'), "[reference] name names variable 'qref', not in the file"),
    "command name": (_sub('name = "vir"', 'name = "u"'), "[command] name names variable 'u', not in the file"),
    "gain name": (_sub('gain = "gtau"', 'gain = "g_tau"'), "[command] gain names variable 'g_tau', not in the file"),
    "kp name": (_sub('kp = "kp"', 'kp = "Kp"'), "[controller] kp names variable 'Kp', not in the file"),
    "required test signal": (_sub("optional = true", "optional = false"), "[test_signal] name names variable 'pulses_N'"),
    # units that disagree with the data: the controller no longer reproduces the command, and the
    # message names the units that would
    "position in m declared mm": (_sub(POSITION, POSITION.replace('unit = "m"', 'unit = "mm"')),
                                  "with [position] unit = 'm' and [reference] unit = 'm' (declared 'mm' and 'm')"),
    "reference in m declared um": (_sub(REFERENCE, REFERENCE.replace('unit = "m"', 'unit = "um"')),
                                   "with [position] unit = 'm' and [reference] unit = 'm' (declared 'm' and 'um')"),
    "both in m declared mm": (_sub('unit = "m"', 'unit = "mm"', -1),
                              "with [position] unit = 'm' and [reference] unit = 'm' (declared 'mm' and 'mm')"),
    "time in s declared ms": (_sub('name = "t"\nunit = "s"', 'name = "t"\nunit = "ms"'),
                              "[time] 't' (unit 'ms'): sample interval 9.99984e-07 s deviates"),
    "sample time": (_sub("sample_time_s = 0.001", "sample_time_s = 0.002"), "from [controller] sample_time_s = 0.002"),
    # controller descriptions that cannot reproduce the logged command
    "kv": (_sub('kv = "kv"', "kv = 120.0"), "[controller] does not reproduce DATA_EMPS.mat's command 'vir'"),
    "saturation": (_sub("saturation = 10.0", "saturation = 2.0"), "[controller] does not reproduce"),
    "velocity estimate": (_sub('velocity_estimate = "average2-difference"', 'velocity_estimate = "difference"'),
                          "[controller] velocity_estimate = 'difference' reproduces DATA_EMPS.mat's command 'vir' with "
                          "a relative error of 3.31 %, but 'average2-difference' gives 0.684 %"),
    "structure": (_sub('structure = "position-p/velocity-p"', 'structure = "position-pi"'),
                  "[controller] structure = 'position-pi'"),
}


@needs_data
@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_emps_description_is_one_line_exit_2_nothing_written(tmp_path, capsys, case):
    text, expect = CASES[case]
    fmt = tmp_path / "log.toml"
    fmt.write_text(text)
    out, js = tmp_path / "F.toml", tmp_path / "FIT.json"
    code, stdout, err = _run_fit(capsys, [DATA, "--log-format", fmt, "--out", out, "--json", js])
    assert code == 2, (case, err, stdout)
    assert err.count("\n") == 1
    assert err.startswith("prsa-fit: error: ")
    assert "Traceback" not in err
    assert expect in err, err
    assert str(fmt) in err or str(DATA) in err
    assert not out.exists()
    assert not js.exists()
    # the same with --validate: the replay's outputs are not written either
    plant = EXAMPLE / "reference-model.toml"
    traces, rj = tmp_path / "T.csv", tmp_path / "R.json"
    code, _, err = _run_fit(capsys, ["--validate", plant, DATA, "--log-format", fmt, "--traces", traces, "--json", rj])
    assert code == 2
    assert err.count("\n") == 1
    assert expect in err
    assert not traces.exists()
    assert not rj.exists()


def test_position_unit_without_a_controller_is_checked_by_its_speed(tmp_path, capsys):
    """A CSV log without a controller whose position is in mm but declared in m: 0.3 m/s becomes
    300 m/s between samples, beyond any linear axis."""
    n, h = 400, 1e-3
    t = np.arange(n) * h
    x_mm = 1e3 * 0.3 * t  # 0.3 m/s in mm
    path = tmp_path / "log.csv"
    path.write_text("t,x,f\n" + "".join(f"{a:.9g},{b:.9g},1.0\n" for a, b in zip(t, x_mm)))
    fmt = tmp_path / "fmt.toml"
    body = ('format = "csv"\naxis = "linear"\n[time]\nname = "t"\nunit = "s"\n[position]\nname = "x"\nunit = "{u}"\n'
            '[command]\nname = "f"\nunit = "N"\n')
    fmt.write_text(body.format(u="m"))
    out = tmp_path / "F.toml"
    code, _, err = _run_fit(capsys, [path, "--log-format", fmt, "--out", out])
    assert code == 2
    assert err.count("\n") == 1
    assert "[position] 'x' (unit 'm'): moves 300 m/s between two samples of 0.001 s; expected at most 50 m/s" in err
    assert str(path) in err
    assert not out.exists()
    from prsa_ctrl.identification.logformat import load_axis_log, load_log_format

    fmt.write_text(body.format(u="mm"))
    log = load_axis_log(path, load_log_format(fmt))  # declared right: accepted
    assert np.allclose(np.diff(log.position_m) / h, 0.3)


# ------------------------------------------------------------------------------------------------
# A log in load coordinates for a screw-driven plant (issue 21: "a plant works in motor
# coordinates (rad, N m) or, for a linear axis, in load coordinates (m, N); a log in either is
# accepted; reports and exports say which").
#
# A closed-loop log of a perturbed built-in ball screw and roller screw (the toolkit's simulator,
# motor coordinates) is written twice: in motor coordinates (time in ms, angle in deg, torque in
# N m) and in load coordinates (time in s, position in mm = lead x angle, force in N = torque /
# lead). ``prsa-fit LOG --log-format F --plant P`` fits both; the two fits agree to the round-off
# of the unit conversions, and the output and the JSON say the plant's coordinates and how each
# log was converted. The conversion itself is checked against numpy arithmetic written here.
# ------------------------------------------------------------------------------------------------

MOTOR_TOML = """axis = "rotary"
[time]
name = "t_ms"
unit = "ms"
[position]
name = "angle_deg"
unit = "deg"
[command]
name = "torque"
unit = "N m"
logged = "as-applied"
[load]
name = "fz"
unit = "N"
"""
LOAD_TOML = """axis = "linear"
[time]
name = "t"
unit = "s"
[position]
name = "x_mm"
unit = "mm"
[command]
name = "f_n"
unit = "N"
logged = "as-applied"
[load]
name = "fz"
unit = "N"
"""


def _write_logs(tmp_path, name: str, duration_s: float = 1.0):
    """The same run in motor and in load coordinates (CSV, 17 digits) with their descriptions."""
    base = _load(name)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        truth = base.with_params(_truth(base))
    rec = _log(truth, duration_s=duration_s)
    a = 1e-3 * base.values["screw.lead_mm"] / (2 * math.pi)  # m of travel per rad, from the file's lead
    motor, load = tmp_path / "motor.csv", tmp_path / "load.csv"
    np.savetxt(motor, np.column_stack([rec.time_s * 1e3, np.degrees(rec.nut_angle_rad), rec.torque_command_n_m,
                                       rec.axial_load_n]), delimiter=",", header="t_ms,angle_deg,torque,fz",
               comments="", fmt="%.17g")
    np.savetxt(load, np.column_stack([rec.time_s, 1e3 * a * rec.nut_angle_rad, rec.torque_command_n_m / a,
                                      rec.axial_load_n]), delimiter=",", header="t,x_mm,f_n,fz", comments="",
               fmt="%.17g")
    (tmp_path / "motor.toml").write_text(MOTOR_TOML)
    (tmp_path / "load.toml").write_text(LOAD_TOML)
    return base, rec, a


def test_motor_record_is_the_lead_conversion(tmp_path):
    """angle = x / a, torque = F a, load as logged: against numpy on the written files."""
    base, rec, a = _write_logs(tmp_path, "ballscrew-32x10", duration_s=0.2)
    assert base.lead_per_rad == pytest.approx(a, rel=1e-15)
    fmt = load_log_format(tmp_path / "load.toml")
    got, logged = load_motor_record(tmp_path / "load.csv", fmt, base)
    assert logged == "applied"
    raw = np.loadtxt(tmp_path / "load.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(got.nut_angle_rad, raw[:, 1] * 1e-3 / a, rtol=1e-15, atol=0)
    np.testing.assert_allclose(got.torque_command_n_m, raw[:, 2] * a, rtol=1e-15, atol=0)
    np.testing.assert_array_equal(got.axial_load_n, raw[:, 3])
    # and back to what the simulator wrote, to the round-off of two conversions
    np.testing.assert_allclose(got.nut_angle_rad, rec.nut_angle_rad, rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(got.torque_command_n_m, rec.torque_command_n_m, rtol=1e-14, atol=1e-16)
    mot, _ = load_motor_record(tmp_path / "motor.csv", load_log_format(tmp_path / "motor.toml"), base)
    raw_m = np.loadtxt(tmp_path / "motor.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(mot.time_s, raw_m[:, 0] * 1e-3 - raw_m[0, 0] * 1e-3, rtol=0, atol=1e-15)
    np.testing.assert_allclose(mot.nut_angle_rad, raw_m[:, 1] * math.pi / 180, rtol=1e-15, atol=0)
    # the AxisLog route gives the same record
    via = motor_record(load_axis_log(tmp_path / "load.csv", fmt), base)
    np.testing.assert_array_equal(via.nut_angle_rad, got.nut_angle_rad)


def test_a_torque_in_percent_of_rated_is_converted_with_its_gain(tmp_path):
    """Drive recorders log the torque command in % of the rated torque: ``unit = "%"`` with
    ``gain`` = rated torque / 100 N m per % gives N m (against numpy on the written file); without
    a gain it is refused naming the unit."""
    base, rec, a = _write_logs(tmp_path, "ballscrew-32x10", duration_s=0.2)
    rated = 4.5
    raw = np.loadtxt(tmp_path / "motor.csv", delimiter=",", skiprows=1)
    raw[:, 2] = 100.0 * raw[:, 2] / rated
    np.savetxt(tmp_path / "pct.csv", raw, delimiter=",", header="t_ms,angle_deg,torque,fz", comments="", fmt="%.17g")
    (tmp_path / "pct.toml").write_text(MOTOR_TOML.replace('unit = "N m"', f'unit = "%"\ngain = {rated / 100!r}'))
    got, _ = load_motor_record(tmp_path / "pct.csv", load_log_format(tmp_path / "pct.toml"), base)
    np.testing.assert_allclose(got.torque_command_n_m, raw[:, 2] * (rated / 100), rtol=1e-15, atol=0)
    np.testing.assert_allclose(got.torque_command_n_m, rec.torque_command_n_m, rtol=1e-13, atol=1e-15)
    (tmp_path / "nogain.toml").write_text(MOTOR_TOML.replace('unit = "N m"', 'unit = "%"'))
    with pytest.raises(LogFormatError, match=r"\[command\] unit = '%'.*needs gain \(N m per command unit"):
        load_log_format(tmp_path / "nogain.toml")


@pytest.fixture(scope="module")
def coordinate_fits(tmp_path_factory):
    """``get(name) -> (folder, base, lead a, {which: (exit code, printed text)})``: prsa-fit on the
    motor- and the load-coordinate log of one 0.6 s run of the plant ``name`` (the logs, fits and
    JSON in the folder), each made once per module. test_fits_in_both_coordinates_agree asserts
    their agreement; test_plain_csv_and_rotary_description_give_the_same_fit compares the ball
    screw's motor fit with the plain CSV's (each test ran that motor fit itself)."""
    made: dict = {}

    def get(name):
        if name not in made:
            d = tmp_path_factory.mktemp(f"coordinates-{name}")
            base, _, a = _write_logs(d, name, duration_s=0.6)
            runs = {}
            for which in ("motor", "load"):
                buf = io.StringIO()
                with contextlib.redirect_stdout(buf):
                    code = main([str(d / f"{which}.csv"), "--log-format", str(d / f"{which}.toml"), "--plant", name,
                                 "--out", str(d / f"{which}-fit.toml"), "--json", str(d / f"{which}.json")])
                runs[which] = (code, buf.getvalue())
            made[name] = (d, base, a, runs)
        return made[name]

    return get


@pytest.mark.parametrize("name", ["ballscrew-32x10", "rollerscrew-30x5"])
def test_fits_in_both_coordinates_agree(coordinate_fits, name):
    """prsa-fit on the motor- and the load-coordinate log of one run: the same fitted values and
    intervals to 1e-10 (the logs differ by the round-off of deg/mm and the lead, ~1e-16 relative;
    measured: 4e-14 for the ball screw), the same delay, the coordinates said in the output and
    the JSON, and the written plant loads as the same mechanism. The agreement does not depend on
    the log's length: 0.6 s of the run, as the plain-CSV test below (was 1 s)."""
    tmp_path, base, a, runs = coordinate_fits(name)
    out = {}
    for which in ("motor", "load"):
        code, text = runs[which]
        assert code == 0, text
        assert "coordinates: motor (angle rad, torque N m)" in text
        out[which] = (json.loads((tmp_path / f"{which}.json").read_text()), text)
    (jm, tm), (jl, tl) = out["motor"], out["load"]
    assert f"load (position m, force N), converted with the lead {a:.9g} m/rad" in tl
    assert "logged in motor (angle rad, torque N m)" in tm
    assert jm["coordinates"]["plant"] == jl["coordinates"]["plant"] == "motor (angle rad, torque N m)"
    assert list(jl["coordinates"]["logs"].values())[0].startswith("load (position m, force N)")
    assert jm["parameters"].keys() == jl["parameters"].keys()
    for k, pm in jm["parameters"].items():
        pl = jl["parameters"][k]
        assert pl["value"] == pytest.approx(pm["value"], rel=1e-10), k
        assert pl["ci95"] == pytest.approx(pm["ci95"], rel=1e-10), k
    assert jm["solver"]["command_delay"]["shift_samples"] == jl["solver"]["command_delay"]["shift_samples"] == 1
    for which in ("motor", "load"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fitted = load_plant(tmp_path / f"{which}-fit.toml")
        assert fitted.mechanism == base.mechanism
        assert fitted.command_delay_samples == 1
        assert "mechanism" in tomllib.loads((tmp_path / f"{which}-fit.toml").read_text())


def test_plain_csv_and_rotary_description_give_the_same_fit(coordinate_fits, tmp_path, capsys):
    """The rotary description only renames and converts units: the standard-column CSV of the
    same data fits to the same numbers (and its output states the coordinates too). The rotary
    fit is the module's ball-screw motor-coordinate fit (coordinate_fits)."""
    logs, _, _, runs = coordinate_fits("ballscrew-32x10")
    std = tmp_path / "std.csv"
    raw = np.loadtxt(logs / "motor.csv", delimiter=",", skiprows=1)
    np.savetxt(std, np.column_stack([raw[:, 0] * 1e-3, np.radians(raw[:, 1]), raw[:, 2], raw[:, 3]]), delimiter=",",
               header="time_s,nut_angle_rad,torque_command_n_m,axial_load_n", comments="", fmt="%.17g")
    assert main([str(std), "--plant", "ballscrew-32x10", "--out", str(tmp_path / "a.toml"), "--json",
                 str(tmp_path / "a.json")]) == 0
    ta = capsys.readouterr().out
    code, text = runs["motor"]
    assert code == 0, text
    assert "coordinates: motor (angle rad, torque N m)" in ta
    ja, jb = json.loads((tmp_path / "a.json").read_text()), json.loads((logs / "motor.json").read_text())
    for k in ja["parameters"]:
        assert jb["parameters"][k]["value"] == pytest.approx(ja["parameters"][k]["value"], rel=1e-10), k


BAD = [
    ("rotary-controller", MOTOR_TOML + "[controller]\nstructure = \"position-p/velocity-p\"\n", [],
     "[controller] with axis = \"rotary\""),
    ("rotary-unit", MOTOR_TOML.replace('unit = "deg"', 'unit = "m"'), [], "[position] unit = 'm'"),
    ("rotary-gain", MOTOR_TOML.replace('unit = "N m"', 'unit = "A"'), [], "needs gain (N m per command unit"),
    ("axis", MOTOR_TOML.replace('axis = "rotary"', 'axis = "polar"'), [], "axis = 'polar'"),
    ("convention", MOTOR_TOML, ["--command-logged", "computed"], "--command-logged computed"),
    ("columns", MOTOR_TOML, ["--columns", "time_s=t"], "--columns with --log-format"),
    ("column", MOTOR_TOML.replace('name = "torque"', 'name = "tq"'), [], "'tq', not in the file"),
]


@pytest.mark.parametrize("case,toml,extra,match", BAD, ids=[b[0] for b in BAD])
def test_bad_descriptions_one_line_exit_2_nothing_written(tmp_path, capsys, case, toml, extra, match):
    _write_logs(tmp_path, "ballscrew-32x10", duration_s=0.1)
    (tmp_path / "bad.toml").write_text(toml)
    out = tmp_path / "fit.toml"
    code = main([str(tmp_path / "motor.csv"), "--log-format", str(tmp_path / "bad.toml"), "--plant", "ballscrew-32x10",
                 "--out", str(out), *extra])
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert len(err.splitlines()) == 1, err
    assert match in err, err
    assert not out.exists()


def test_an_frf_file_may_go_beside_described_logs(tmp_path):
    """``--frf`` names its own file (frequency, magnitude, phase): it is not a column of the
    described logs, so it is accepted beside ``--log-format`` (was refused 'expected the log
    description to say which column holds what'), and the records are the description's."""
    import argparse

    from prsa_ctrl.cli.axis import motor_records

    base, rec, _ = _write_logs(tmp_path, "ballscrew-32x10", duration_s=0.1)
    args = argparse.Namespace(columns=None, torque_constant=None, load=None, frf=[str(tmp_path / "bode.csv")],
                              log_format=str(tmp_path / "motor.toml"), command_logged=None,
                              data=[str(tmp_path / "motor.csv")], validate=[])
    records, validate, logged, _ = motor_records(args, base)
    assert (len(records), validate, logged) == (1, [], "applied")
    np.testing.assert_allclose(records[0].torque_command_n_m, rec.torque_command_n_m, rtol=1e-14, atol=1e-16)


def test_a_linear_axis_plant_refuses_a_motor_log(tmp_path):
    """A linear axis works in load coordinates: a motor-coordinate log is refused for it (and by
    the linear-axis reader), one line naming why."""
    from prsa_ctrl.plant import Plant

    _write_logs(tmp_path, "ballscrew-32x10", duration_s=0.1)

    doc = {"name": "lin", "mechanism": "linear-axis", "axis": {"mass_kg": {"value": 10.0, "source": "test"}},
           "drive": {"gain_n_per_unit": {"value": 1.0, "source": "test"}, "force_limit_n": {"value": 100.0, "source": "test"}},
           "sensor": {"sample_time_s": {"value": 1.25e-4, "source": "test"},
                      "encoder_resolution_m": {"value": 1e-7, "source": "test"}}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plant = Plant.from_dict(doc, origin="test")
    with pytest.raises(ValueError, match="is a linear axis"):
        load_motor_record(tmp_path / "motor.csv", load_log_format(tmp_path / "motor.toml"), plant)
    with pytest.raises(LogFormatError, match="axis = 'rotary'"):
        load_axis_log(tmp_path / "motor.csv", load_log_format(tmp_path / "motor.toml"))


# --- the numbers of a description: checked by options.check_number (one line, the value as typed) --

@pytest.mark.parametrize("line, value, expected", [
    ("saturation = 10.0", "saturation = 0", "[controller] saturation = 0; expected a finite number > 0"),
    ("saturation = 10.0", "saturation = true", "[controller] saturation = True; expected a finite number > 0"),
    ("saturation = 10.0", 'saturation = "10"', "[controller] saturation = '10'; expected a finite number > 0"),
    ("sample_time_s = 0.001", "sample_time_s = nan", "[controller] sample_time_s = nan; expected a finite number > 0"),
    ("sample_time_s = 0.001", "sample_time_s = 0.001\ncommand_delay_samples = 11",
     "[controller] command_delay_samples = 11; expected an integer >= 0 and <= 10"),
    ("sample_time_s = 0.001", "sample_time_s = 0.001\ncommand_delay_samples = 1.0",
     "[controller] command_delay_samples = 1.0; expected an integer >= 0 and <= 10"),
    ("sample_time_s = 0.001", "sample_time_s = 0.001\ncheck_tolerance = 1",
     "[controller] check_tolerance = 1; expected a finite number > 0 and < 1"),
    ('name = "qm"\nunit = "m"', 'name = "qm"\nunit = "m"\nresolution = -1e-6',
     "[position] resolution = -1e-06; expected a finite number > 0 (position unit)"),
])
def test_a_bad_number_in_a_description_is_named_with_its_value_and_range(files, line, value, expected):
    d, mat, fmt, _ = files
    text = GOOD.replace(line, value, 1)
    assert text != GOOD
    fmt.write_text(text)
    with pytest.raises(LogFormatError) as info:
        load_log_format(fmt)
    assert str(info.value) == f"{fmt}: {expected}"


def test_a_variable_name_in_a_csv_description_is_refused_as_typed(files):
    csv, fmt = _csv_files(files)
    fmt.write_text(fmt.read_text().replace("gain = 35.0", 'gain = "gtau"'))
    with pytest.raises(LogFormatError) as info:
        load_axis_log(csv, load_log_format(fmt))
    assert str(info.value) == (f"{fmt}: [command] gain = 'gtau'; expected a finite number > 0 "
                               "(variable names work for .mat files only)")


def test_a_non_positive_scalar_variable_is_named_with_the_variable(files):
    d, mat, fmt, _ = files
    scipy.io.savemat(mat, {**_mat_vars(files), "gtau": np.array([[-2.0]])})
    with pytest.raises(LogFormatError) as info:
        load_axis_log(mat, load_log_format(fmt))
    assert str(info.value) == f"{mat}: [command] gain = -2.0 (variable 'gtau'); expected a finite number > 0"
