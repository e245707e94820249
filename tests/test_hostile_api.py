"""Silent wrong results, hangs and Ctrl-C (issue 13): events the physics cannot resolve and
records above the size limit are refused through the API as through the CLI; Ctrl-C always
ends a run with exit 130 and one line, also when a solver swallows it."""

import json
import math
import os
import signal
import stat
import subprocess
import sys

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from prsa_ctrl import SceneError, load_plant
from prsa_ctrl.cli.tune import main
from prsa_ctrl.studies.scene import (MAX_RECORD_SAMPLES, POST_EVENT_SAMPLES, PRE_EVENT_SAMPLES, Scene, check_against_plant,
                             holding_capacity_n, load_scene)

PLANT = load_plant()
TS = PLANT.sample_time_s


def test_pre_event_samples_match_the_verification():
    from prsa_ctrl.studies import autotune

    assert PRE_EVENT_SAMPLES == autotune._PRE_SAMPLES


@settings(max_examples=200)
@given(step=st.floats(1e-12, 20.0), after=st.floats(1e-6, 20.0))
def test_event_timing_and_record_size_are_checked_before_any_run(step, after):
    scene = Scene(step_time=step, duration=step + after + 1.001e-3)
    ok = (step >= PRE_EVENT_SAMPLES * TS and scene.duration - step >= POST_EVENT_SAMPLES * TS
          and scene.duration / TS <= MAX_RECORD_SAMPLES)
    try:
        check_against_plant(scene, PLANT)
    except SceneError as exc:
        assert not ok and "\n" not in str(exc) and "controller samples" in str(exc)
    else:
        assert ok


@settings(max_examples=200)
@given(loads=st.lists(st.floats(0.0, 1e6), min_size=2, max_size=4), rpm=st.floats(0.5, 6000.0))
def test_loads_beyond_the_holding_capacity_are_refused(loads, rpm):
    f0, finals = loads[0], tuple(loads[1:])
    try:
        scene = Scene(setpoint_rad_s=rpm * math.pi / 30, initial_load=f0, final_loads=finals)
    except SceneError:
        return  # a final load equal to the initial one
    cap = holding_capacity_n(PLANT, scene.setpoint_rad_s)
    try:
        check_against_plant(scene, PLANT)
    except SceneError as exc:
        msg = str(exc)
        bad_load = max(loads) > cap
        assert bad_load or rpm < 15.0 or len(set(finals)) < len(finals) or min(abs(f - f0) for f in finals) < 1.0, msg
        if bad_load and rpm >= 15.0:
            assert f"holds at most {cap:.0f} N" in msg
    else:
        assert max(loads) <= cap and rpm >= 14.99


def test_scene_step_at_zero_is_refused_by_the_api():
    with pytest.raises(SceneError, match=r"step_time = 0; expected a time > 0 s"):
        Scene(step_time=0)


# --- Ctrl-C ---------------------------------------------------------------------------------------

def test_ctrl_c_during_the_run_exits_130_with_one_line(tmp_path):
    """SIGINT once the tuner has started (the --verbose progress line is the trigger)."""
    out = tmp_path / "r.json"
    proc = subprocess.Popen([sys.executable, "-m", "prsa_ctrl.cli.tune", "--verbose", "--json", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    first = proc.stderr.readline()
    assert first.startswith("prsa-tune: tuning paper-iprsm"), first
    proc.send_signal(signal.SIGINT)
    stdout, rest = proc.communicate(timeout=120)  # safety net only
    assert proc.returncode == 130
    assert rest.strip().splitlines() == ["prsa-tune: interrupted (Ctrl-C); no output written"], rest
    assert stdout == "" and not out.exists() and list(tmp_path.iterdir()) == []


def test_interrupt_swallowed_by_a_solver_still_exits_130(tmp_path, capsys, monkeypatch):
    import prsa_ctrl.studies.autotune as autotune

    def swallowing(*a, **k):  # what IPOPT does: turns SIGINT into a status and returns
        try:
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(10_000):
                pass
        except KeyboardInterrupt:
            pass
        raise RuntimeError("solver returned User_Requested_Stop")

    monkeypatch.setattr(autotune, "tune_actuator", swallowing)
    keep = tmp_path / "keep.json"
    keep.write_text("old")
    assert main(["--json", str(keep)]) == 130
    assert capsys.readouterr().err.strip().splitlines() == ["prsa-tune: interrupted (Ctrl-C); no output written"]
    assert keep.read_text() == "old"


def test_user_requested_stop_status_counts_as_interrupt(capsys, monkeypatch):
    import prsa_ctrl.studies.autotune as autotune

    class Rep:
        def as_dict(self):
            return {"tuning": {"runs": [{"status": "User_Requested_Stop", "iterations": 3}]}}

    monkeypatch.setattr(autotune, "tune_actuator", lambda *a, **k: Rep())
    assert main([]) == 130
    assert capsys.readouterr().err.strip() == "prsa-tune: interrupted (Ctrl-C); no output written"


# --- one real run: effective scene in the header, JSON like any user file -------------------------

def test_mt_max_and_effective_scene_in_header_and_json_mode(tmp_path, capsys):
    out = tmp_path / "r.json"
    mask = os.umask(0o022)
    try:
        rc = main(["--mt-max", "1.3", "--load-step", "500:1200", "--json", str(out)])
    finally:
        os.umask(mask)
    assert rc == 0
    cap = capsys.readouterr()
    head = cap.out.splitlines()[0]
    assert "scene paper-load-step with --load-step 500:1200 --mt-max 1.3" in head
    assert "500 N -> 1200 N" in head and "Mt <= 1.3" in head
    assert "note:" not in cap.err  # the built-in plant's geometry note only with --verbose
    assert stat.S_IMODE(out.stat().st_mode) == 0o644
    d = json.loads(out.read_text())
    assert d["margins"]["mt"] <= 1.3 + 1e-6
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]


def test_default_scene_passes_the_plant_checks():
    check_against_plant(load_scene(), PLANT)
