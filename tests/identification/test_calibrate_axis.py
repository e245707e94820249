"""Calibration from described logs as a library call (prsa_ctrl.identification.calibrate_axis):
the EMPS record (a linear axis, MATLAB .mat, read through examples/emps/log.toml) gives what
``prsa-fit DATA_EMPS.mat --log-format log.toml --out ... --json ...`` prints and writes; the base
plant built from the logs refuses a disagreeing --plant fact with the command's line."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from prsa_ctrl.identification.calibrate_axis import axis_base_plant, calibrate_described

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "emps"
_CANDIDATES = [ROOT.parent / "shared" / "data" / "emps" / "DATA_EMPS.mat", EXAMPLE / "DATA_EMPS.mat"]
DATA = next((p for p in _CANDIDATES if p.is_file()), None)
FORMAT = EXAMPLE / "log.toml"
needs_data = pytest.mark.skipif(DATA is None or not FORMAT.is_file(),
                                reason="EMPS data or its description absent (../shared/data/emps/, examples/emps/)")


def _command_run(request, tmp_path):
    """``(plant file, JSON report, printed lines but the "wrote" ones)`` of ``prsa-fit DATA
    --log-format FORMAT --out ... --json ...``: the session's run of that command when it reads
    these data (tests/conftest.py's emps_fit; this test ran its own), else one run here."""
    import contextlib
    import io

    from prsa_ctrl.cli.fit import main

    if DATA == EXAMPLE / "DATA_EMPS.mat":
        run = request.getfixturevalue("emps_fit")
        assert run.code == 0, run.err
        out, rep, text = run.toml, run.json, run.out
    else:
        out, rep, buf = tmp_path / "emps-fitted.toml", tmp_path / "r.json", io.StringIO()
        with contextlib.redirect_stdout(buf):
            assert main([str(DATA), "--log-format", str(FORMAT), "--out", str(out), "--json", str(rep)]) == 0
        text = buf.getvalue()
    return out, rep, [x for x in text.splitlines() if not x.startswith("wrote ")]


@needs_data
def test_a_described_mat_log_of_a_linear_axis_is_the_commands_fit(request, tmp_path):
    from prsa_ctrl.identification.axis import load_axis_plant

    out, rep, printed = _command_run(request, tmp_path)
    got = calibrate_described([str(DATA)], str(FORMAT), name=out.stem)  # (the command names it after --out)
    assert got.plant_text == out.read_text()  # the same plant file, byte for byte
    assert list(got.lines) == printed
    want = json.loads(rep.read_text())
    assert json.loads(json.dumps({k: v for k, v in got.report.items() if k != "fit_percent"}, default=str)) == want
    # the replay the report's fit % is, and a plant that loads as the linear axis it is
    (r,) = want["replay"]
    assert got.report["fit_percent"] == {r["log"]: r["fit_percent"]["velocity"]}
    assert r["fit_percent"]["velocity"] > 99
    p = load_axis_plant(out)
    assert p.values["axis.mass_kg"] == pytest.approx(want["parameters"]["axis.mass_kg"]["value"], rel=1e-12)
    # labels name the log in the results (the app names it as uploaded)
    named = calibrate_described([str(DATA)], str(FORMAT), name="x", labels=["upload.mat"])
    assert [r["log"] for r in named.report["replay"]] == ["upload.mat"]
    assert str(DATA) not in " ".join(named.lines)


@needs_data
def test_the_built_base_refuses_a_plant_whose_log_facts_disagree(tmp_path):
    from prsa_ctrl.identification.logformat import load_axis_log, load_log_format

    logs = [load_axis_log(DATA, load_log_format(FORMAT))]
    base, notes = axis_base_plant(logs, str(FORMAT))
    assert base.values["drive.gain_n_per_unit"] == logs[0].gain_n_per_unit
    assert notes == []
    plant = (EXAMPLE / "plant.toml").read_text().replace("sample_time_s = { value = 0.001", "sample_time_s = { value = 0.002")
    (tmp_path / "p.toml").write_text(plant)
    if "0.002" not in plant:
        pytest.skip("examples/emps/plant.toml states no sample time in the expected form")
    with pytest.raises(ValueError, match=r"^--plant .*p\.toml: sensor\.sample_time_s = 0\.002 s disagrees with 0\.001 s"):
        axis_base_plant(logs, str(FORMAT), str(tmp_path / "p.toml"))


def test_bad_arguments():
    with pytest.raises(ValueError, match="labels: 2 for 1 logs"):
        calibrate_described(["a.csv"], "f.toml", name="x", labels=["a", "b"])
