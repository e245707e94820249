"""Acceptance "Bad logs" (issue 21) on the EMPS record and a synthetic CSV: wrong variable names,
units that disagree with the data, a controller description that cannot reproduce the logged
command: one line naming the file and the column or key, exit 2, nothing written."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from prsa_ctrl.cli.fit import main

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "emps"
DATA = EXAMPLE / "DATA_EMPS.mat"
GOOD = (EXAMPLE / "log.toml").read_text()
needs_data = pytest.mark.skipif(not DATA.is_file(), reason="examples/emps/DATA_EMPS.mat not in this checkout")


def _run(capsys, argv):
    capsys.readouterr()
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _sub(old: str, new: str, count: int = 1) -> str:
    text = GOOD.replace(old, new, count)
    assert text != GOOD, old
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
    code, stdout, err = _run(capsys, [DATA, "--log-format", fmt, "--out", out, "--json", js])
    assert code == 2, (case, err, stdout)
    assert err.count("\n") == 1 and err.startswith("prsa-fit: error: ") and "Traceback" not in err
    assert expect in err, err
    assert str(fmt) in err or str(DATA) in err
    assert not out.exists() and not js.exists()
    # the same with --validate: the replay's outputs are not written either
    plant = EXAMPLE / "reference-model.toml"
    traces, rj = tmp_path / "T.csv", tmp_path / "R.json"
    code, _, err = _run(capsys, ["--validate", plant, DATA, "--log-format", fmt, "--traces", traces, "--json", rj])
    assert code == 2 and err.count("\n") == 1 and expect in err
    assert not traces.exists() and not rj.exists()


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
    code, _, err = _run(capsys, [path, "--log-format", fmt, "--out", out])
    assert code == 2 and err.count("\n") == 1
    assert "[position] 'x' (unit 'm'): moves 300 m/s between two samples of 0.001 s; expected at most 50 m/s" in err
    assert str(path) in err and not out.exists()
    from prsa_ctrl.identification.logformat import load_axis_log, load_log_format

    fmt.write_text(body.format(u="mm"))
    log = load_axis_log(path, load_log_format(fmt))  # declared right: accepted
    assert np.allclose(np.diff(log.position_m) / h, 0.3)
