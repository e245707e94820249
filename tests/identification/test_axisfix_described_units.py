"""A load-coordinate log fitted with a screw plant (prsa-fit LOG --log-format F --plant SCREW):
a [load] declared in kN for a log in N is refused before the fit, naming the column, its declared
unit and the plant's rated load; a [position] declared in mm for a log in m is refused naming the
description's columns and units, not the record's internal columns."""

from __future__ import annotations

import numpy as np
import pytest

from prsa_ctrl.cli.fit import main
from prsa_ctrl.identification.logformat import LogFormatError, load_log_format, load_motor_record

from test_loadcoords_screw import LOAD_TOML, _write_logs  # noqa: E402  (tests/identification on sys.path)


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
    assert code == 2 and "\n" not in err and not out.exists()
    assert "[load] column 'fz'" in err and "kN" in err and f"{peak_kn:.6g} kN" in err and f"{rated:.6g} N" in err
    with pytest.raises(LogFormatError, match="rated_load_n"):
        load_motor_record(d / "load.csv", load_log_format(d / "f.toml"), base)
    # the same log with its load in N passes the check
    code, err, _ = _fit(d, LOAD_TOML, d / "load.csv", capsys)
    assert code == 0, err


def test_position_in_m_declared_as_mm_names_the_description(logs, capsys):
    d, base = logs
    raw = np.loadtxt(d / "load.csv", delimiter=",", skiprows=1)
    raw[:, 1] *= 1e-3  # the log now holds metres; its description still says mm
    np.savetxt(d / "load-m.csv", raw, delimiter=",", header="t,x_mm,f_n,fz", comments="", fmt="%.17g")
    code, err, out = _fit(d, LOAD_TOML, d / "load-m.csv", capsys)
    assert code == 2 and "\n" not in err and not out.exists()
    assert "[position] column 'x_mm' (mm)" in err and "[command] column 'f_n' (N)" in err and "f.toml" in err
    assert "torque_command_n_m" not in err and "nut_angle_rad" not in err
