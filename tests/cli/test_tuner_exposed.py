"""Issue 25: the Mks bound exposed in prsa-tune (--mks-max) and in the app (an Mks input, the true
Mks of every design)."""

import json
from dataclasses import replace

import pytest

from prsa_ctrl import load_plant, load_scene
from prsa_ctrl.cli.tune import main
from prsa_ctrl.studies.autotune import actuator_loops
from prsa_ctrl.tuning import Tuner

MKS = 0.094  # N m s/rad; the unbounded paper design has a true Mks of 0.1176


@pytest.fixture(scope="module")
def loops():
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plant, scene = load_plant(), load_scene()
        return actuator_loops(plant, scene)


@pytest.mark.parametrize("text", ["0", "-1", "abc", "inf", "nan"])
def test_bad_mks_flag_is_one_line_exit_2(text, capsys):
    assert main(["--mks-max", text]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--mks-max" in err[0] and "noise-sensitivity bound" in err[0]


def test_prsa_tune_mks_max_bounds_the_true_mks(tmp_path, loops, capsys):
    out = tmp_path / "r.json"
    assert main(["--scene", "paper-load-step", "--mks-max", str(MKS), "--json", str(out), "--quiet"]) == 0
    rep = json.loads(out.read_text())
    assert rep["scene"]["mks_max"] == MKS
    g = [rep["gains"][k] for k in ("kp", "ki", "kd")]
    mks = max(lp.noise_peak(g)["mks"] for lp in loops)
    assert mks <= MKS * (1 + 1e-9)


def test_tuner_on_drive_loops_honours_mks(loops):
    tu = Tuner(loops, objective="iae")
    free = tu.tune(ms_max=1.4)
    assert free.mks > MKS  # the bound is active
    r = tu.tune(ms_max=1.4, mks_max=MKS)
    assert r.status == "optimal"
    assert MKS * (1 - 1e-3) <= r.mks <= MKS
    assert r.mks == pytest.approx(max(lp.noise_peak(r.pid.gains)["mks"] for lp in loops), rel=1e-12)
    assert r.objective >= free.objective


def test_app_mks_bound_and_code(loops):
    from prsa_ctrl.app.session import AppInputError, AppSession

    s = AppSession()
    try:
        st = replace(s.default_settings(), mks_max=MKS)
        v = s.tuned(st)
        assert v.mks is not None and MKS * (1 - 1e-3) <= v.mks <= MKS
        cli, py = s.code(st)
        assert f"--mks-max {MKS:g}" in cli and f"mks_max={MKS!r}" in py
        with pytest.raises(AppInputError, match="Mks bound"):
            s.tuned(replace(st, mks_max=-1.0))
    finally:
        s.close()
