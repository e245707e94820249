"""Issue 24: notch and low-pass filters from a scene's ``[filters]`` table and ``prsa-tune
--filter``, in the loop models, the tuner, the prediction, the verification, the report, the
JSON and the export; bad entries refused in one line naming the file, the key and the value."""

import json
import math
import tomllib
import warnings

import numpy as np
import pytest

from prsa_ctrl import PID, load_plant
from prsa_ctrl.cli.tune import main
from prsa_ctrl.drive.filters import FirstOrderLowPass, LoopFilter, Notch, SecondOrderLowPass
from prsa_ctrl.errors import SceneError
from prsa_ctrl.plant.linear import linear_core
from prsa_ctrl.plant.model import plant_model
from prsa_ctrl.sim.engine import run
from prsa_ctrl.sim.metrics import load_step_metrics
from prsa_ctrl.studies.autotune import Design, predict, verify, verify_settings
from prsa_ctrl.studies.scene import check_against_plant, load_scene
from prsa_ctrl.studies.scenefilters import filter_entry, parse_filter_flag, parse_filters
from prsa_ctrl.studies.sceneloops import actuator_loops
from prsa_ctrl.tuning.filtered import loop_builder
from prsa_ctrl.tuning.tuner import Tuner

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    HEAVY = load_plant("paper-heavy-slide")
    PAPER = load_plant()
TS = PAPER.sample_time_s
#: The notch of docs/guides/filters.md (tune_filtered with the gains, heavy slide) and its PI.
NOTCH = LoopFilter(Notch(234.70921126764233, 35.23186297447368, -39.99999069182893), "torque_command")
PI_NOTCH = PID(0.04057480192257684, 4.008310897790402)

GOOD = """
name = "filtered"
[operating]
setpoint_rpm = 300.0
initial_load_n = 500.0
final_loads_n = [1500.0]
step_time_s = 0.05
duration_s = 0.15
[verify]
fidelity = "rigid"
"""


def _scene_file(tmp_path, filters_toml: str, name="s.toml"):
    path = tmp_path / name
    path.write_text(GOOD + filters_toml, encoding="utf-8")
    return path


# --- the schema ---------------------------------------------------------------------------------

def test_scene_file_filters_are_the_drive_filters(tmp_path):
    path = _scene_file(tmp_path, """
[[filters.notch]]
path = "torque"
centre_hz = 163
width_hz = 40.0
depth_db = -20.0
[[filters.lowpass]]
path = "speed"
corner_hz = 400.0
[[filters.lowpass]]
path = "torque"
corner_hz = 900.0
order = 2
damping = 0.5
""")
    sc = load_scene(str(path))
    assert sc.filters == (LoopFilter(Notch(163.0, 40.0, -20.0), "torque_command"),
                          LoopFilter(FirstOrderLowPass(400.0), "speed_measurement"),
                          LoopFilter(SecondOrderLowPass(900.0, 0.5), "torque_command"))
    assert sc.filter_labels == (f"{path}: filters.notch[1].centre_hz = 163", f"{path}: filters.lowpass[1].corner_hz = 400.0",
                                f"{path}: filters.lowpass[2].corner_hz = 900.0")
    # the same filters from the command-line syntax, key by key
    flags = ["notch:path=torque,centre_hz=163,width_hz=40,depth_db=-20", "lowpass:path=speed,corner_hz=400",
             "lowpass:path=torque,corner_hz=900,order=2,damping=0.5"]
    assert tuple(parse_filter_flag(f)[0] for f in flags) == sc.filters
    # defaults: depth -20 dB, order 1, Butterworth damping for order 2
    assert filter_entry("notch", {"path": "speed", "centre_hz": 100.0, "width_hz": 10.0}, "x").filter.depth_db == -20.0
    lp2 = filter_entry("lowpass", {"path": "speed", "corner_hz": 100.0, "order": 2}, "x").filter
    assert lp2 == SecondOrderLowPass(100.0, 1 / math.sqrt(2))
    # a scene without filters reports as it always did (no key)
    assert "filters" not in load_scene().as_dict()
    assert "filters" in sc.as_dict()


BAD_ENTRIES = [
    # (the [filters] text, the key named, the value as written)
    ('[[filters.notch]]\npath = "motor"\ncentre_hz = 200.0\nwidth_hz = 40.0', "filters.notch[1].path", "'motor'"),
    ('[[filters.notch]]\npath = "torque"\ncentre_hz = -200.0\nwidth_hz = 40.0', "filters.notch[1].centre_hz", "-200.0"),
    ('[[filters.lowpass]]\npath = "speed"\ncorner_hz = -1\n', "filters.lowpass[1].corner_hz", "-1"),
    ('[[filters.notch]]\npath = "torque"\ncentre_hz = 2500.0\nwidth_hz = 40.0', "filters.notch[1].centre_hz", "2500.0"),
    ('[[filters.lowpass]]\npath = "speed"\ncorner_hz = 2000.0\n', "filters.lowpass[1].corner_hz", "2000.0"),
    ('[[filters.notch]]\npath = "torque"\ncentre_hz = 200.0\nwidth_hz = 40.0\ndepth_db = 6.0',
     "filters.notch[1].depth_db", "6.0"),
    ('[[filters.notch]]\npath = "torque"\ncentre_hz = 200.0\nwidth_hz = 40.0\nq = 3.0', "filters.notch[1].q", "3.0"),
    ('[[filters.lowpass]]\npath = "speed"\ncorner_hz = 200.0\norder = 3', "filters.lowpass[1].order", "3"),
    ('[[filters.notch]]\npath = "torque"\ncentre_hz = "200"\nwidth_hz = 40.0', "filters.notch[1].centre_hz", "'200'"),
    ('[[filters.notch]]\npath = "torque"\ncentre_hz = 200.0\nwidth_hz = 0.0', "filters.notch[1].width_hz", "0.0"),
    ('[[filters.bandpass]]\npath = "torque"\ncentre_hz = 200.0', "filters.bandpass", ""),
    ('[[filters.notch]]\npath = "torque"\nwidth_hz = 40.0', "filters.notch[1]: centre_hz missing", ""),
]


@pytest.mark.parametrize("text, key, value", BAD_ENTRIES, ids=[b[1] + b[2] for b in BAD_ENTRIES])
def test_bad_filter_entries_get_one_line_and_exit_2(tmp_path, capsys, stand_in, text, key, value):
    path = _scene_file(tmp_path, text + "\n")
    rc = main(["--scene", str(path), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2, err
    assert len(err) == 1, err
    assert "Traceback" not in err[0], err
    assert str(path) in err[0], err[0]
    assert key in err[0], err[0]
    assert f"= {value}" in err[0] if value else True, err[0]
    assert not stand_in  # refused before any tuning


@pytest.mark.parametrize("flag, key", [
    ("notch:path=motor,centre_hz=200,width_hz=40", "path = motor"),
    ("notch:path=torque,centre_hz=-200,width_hz=40", "centre_hz = -200"),
    ("notch:path=torque,centre_hz=2500,width_hz=40", "centre_hz = 2500"),
    ("notch:path=torque,centre_hz=200,width_hz=40,depth_db=+6", "depth_db = +6"),
    ("notch:path=torque,centre_hz=200,width_hz=40,quality=3", "quality = 3"),
    ("notch:path=torque,centre_hz=200,width_hz=40,width_hz=3", "width_hz given twice"),
    ("lowpass:path=speed,corner_hz=1e9", "corner_hz = 1e9; expected a frequency below the Nyquist"),
    ("lowpass:path=speed,corner_hz=100,order=1,damping=0.7", "damping = 0.7"),
    ("bandpass:path=speed,corner_hz=100", "expected notch:"),
    ("notch", "expected notch:"),
])
def test_bad_filter_flags_get_one_line_and_exit_2(capsys, stand_in, flag, key):
    rc = main(["--filter", flag, "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2, err
    assert len(err) == 1, err
    assert err[0].startswith("prsa-tune: error: --filter"), err
    assert key in err[0], err[0]
    assert not stand_in, err[0]


@pytest.mark.parametrize("flag, typed", [
    ("notch:path=torque,centre_hz=1999.99,width_hz=40", "centre_hz = 1999.99"),
    ("lowpass:path=speed,corner_hz=1999.999", "corner_hz = 1999.999"),
    ("lowpass:path=speed,corner_hz=1980.01,order=2", "corner_hz = 1980.01"),
])
def test_a_filter_within_the_margin_of_nyquist_is_refused_before_tuning(capsys, stand_in, flag, typed):
    """Issue 31: a notch at 1999.99 Hz (a low-pass at 1999.999 Hz) on the 4 kHz paper plant ran
    prsa-tune for > 400 s. Now one line naming the value as typed, the Nyquist frequency and the
    margin (1 %: at most 1980 Hz), exit 2, before any tuning."""
    rc = main(["--filter", flag, "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2, err
    assert len(err) == 1, err
    assert "Traceback" not in err[0], err
    assert f"--filter {flag!r}: {typed}; expected a frequency below the Nyquist frequency 2000 Hz" in err[0], err[0]
    assert "by at least 1% of it (at most 1980 Hz)" in err[0], err[0]
    assert not stand_in


def test_the_api_refuses_a_filter_within_the_margin_before_tuning(monkeypatch):
    """tune_actuator refuses it while building the loop models: the tuner is never built."""
    import prsa_ctrl.studies.autotune as autotune

    built = []
    monkeypatch.setattr(autotune, "Tuner", lambda *a, **k: built.append(a) or (_ for _ in ()).throw(AssertionError))
    sc = load_scene().replace(filters=(LoopFilter(Notch(1999.99, 40.0), "torque_command"),))
    with pytest.raises(ValueError, match=r"notch frequency 1999.99 Hz at ts = 0.00025 s; expected below the Nyquist "
                                         r"frequency 2000 Hz by at least 1% of it \(at most 1980 Hz\)"):
        autotune.tune_actuator(PAPER, sc)
    assert not built


def test_a_filter_at_the_margin_is_accepted(tmp_path):
    sc = load_scene(str(_scene_file(tmp_path, '[[filters.notch]]\npath = "torque"\ncentre_hz = 1980.0\n'
                                             'width_hz = 40.0\n')))
    check_against_plant(sc, PAPER)


def test_filters_are_refused_where_the_loop_has_none(tmp_path, capsys, stand_in):
    path = _scene_file(tmp_path, '[[filters.lowpass]]\npath = "speed"\ncorner_hz = 300.0\n')
    with pytest.raises(SceneError, match="discrete = false with filters"):
        load_scene(str(path)).replace(discrete=False)
    with pytest.raises(SceneError, match="filters"):
        load_scene().replace(filters=("notch",))
    with pytest.raises(SceneError, match="filters.notch = "):
        parse_filters({"notch": {"path": "torque"}}, "x.toml")
    assert not stand_in


def test_a_kalman_filter_scene_keeps_its_filters_in_its_loop_models(tmp_path):
    """The Kalman-filter loop takes the scene's filters (it used to refuse them): two biquads of
    4 states each, less the stored previous speed (the speed biquad's memory holds it), and a
    different load-step response than without them."""
    path = _scene_file(tmp_path, '[[filters.lowpass]]\npath = "speed"\ncorner_hz = 300.0\n'
                                 '[[filters.notch]]\npath = "torque"\ncentre_hz = 900.0\nwidth_hz = 300.0\n')
    sc = load_scene(str(path)).replace(estimator="kf")
    check_against_plant(sc, PAPER)
    with_f = actuator_loops(PAPER, sc)
    without = actuator_loops(PAPER, sc.replace(filters=(), filter_labels=()))
    assert [lp.A0.shape[0] - lp0.A0.shape[0] for lp, lp0 in zip(with_f, without)] == [7] * len(without)
    gains = (0.05, 5.0, 0.0)
    e1, e0 = with_f[0].error(gains), without[0].error(gains)
    assert np.max(np.abs(e1 - e0)) > 0.01 * np.max(np.abs(e0))


def test_nyquist_is_the_plants(tmp_path):
    """Above Nyquist is judged at the plant's sample time: 1500 Hz runs at 0.25 ms (Nyquist
    2 kHz) and is refused at 0.5 ms (1 kHz)."""
    from prsa_ctrl.plant.uncertainty import apply

    sc = load_scene(str(_scene_file(tmp_path, '[[filters.lowpass]]\npath = "speed"\ncorner_hz = 1500.0\n')))
    check_against_plant(sc, PAPER)
    slow = apply(PAPER, {"sensor.sample_time_s": 5e-4})
    with pytest.raises(SceneError, match=r"filters.lowpass\[1\].corner_hz = 1500.0; expected a frequency below the "
                                         r"Nyquist frequency 1000 Hz"):
        check_against_plant(sc, slow)


# --- the pipeline -------------------------------------------------------------------------------

def _python_path_loop(plant, load_mid, step, horizon, filters):
    """Today's Python path (docs/guides/filters.md): the linearised plant, tuning.filtered's
    loop_builder with the filters fixed."""
    m = plant_model(plant, "compliant")
    a, b, c, _, _ = linear_core(plant, 300 * math.pi / 30, load_mid, "compliant")
    build = loop_builder(a, b, c[m.output_names.index("nut_speed")], m.index("theta_nut"), ts=plant.sample_time_s,
                         speed_filter=plant.speed_filter_s, tf=4 * plant.sample_time_s, horizon=horizon, step=step,
                         fixed=filters)
    return build(None)


def test_heavy_slide_scene_loop_is_the_python_paths():
    """The built-in heavy-slide scene's notch gives the loop model of today's Python path
    (loop_builder with the notch): the same matrices, frequency response and trajectory."""
    sc = load_scene("paper-heavy-slide")
    assert sc.filters == (NOTCH,)
    [lp] = actuator_loops(HEAVY, sc)
    ref = _python_path_loop(HEAVY, 1000.0, 1000.0, sc.duration - sc.step_time, [NOTCH])
    np.testing.assert_array_equal(lp.A0, ref.A0)
    for x, y in zip(lp.A, ref.A):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(lp.L, ref.L)
    g = np.r_[PI_NOTCH.kp, PI_NOTCH.ki, 0.0]
    np.testing.assert_array_equal(lp.error(g), ref.error(g))
    # the notch is really in it: without it the loop differs
    bare = _python_path_loop(HEAVY, 1000.0, 1000.0, sc.duration - sc.step_time, [])
    assert bare.A0.shape != lp.A0.shape


def _python_path_verified(plant, pid, scene, filters, duration):
    """Today's Python path of a verified run: sim.run with the filters, then the load-step metrics."""
    pre = min(scene.step_time, 8 * plant.sample_time_s)
    r = run(plant, setpoint=scene.setpoint_rad_s, load=[(0.0, scene.initial_load), (pre, scene.final_loads[0])],
            duration=pre + duration - scene.step_time, controller=pid, fidelity="compliant", discrete=True,
            filters=filters, settings=verify_settings(scene))
    t = np.asarray(r.time) + scene.step_time - pre
    y = dict(zip(r.output_labels, np.asarray(r.outputs)))
    return load_step_metrics(t, y["nut_speed"], scene.setpoint_rad_s, scene.step_time, y["motor_torque"],
                             plant.torque_limit, direction=1)


def test_heavy_slide_verified_result_is_the_python_paths():
    """A given PI verified on the heavy-slide scene (its notch from the file) = the Python path's
    nonlinear run with that notch, to round-off (0.1 s of the record here; the whole record in
    the slow test)."""
    sc = load_scene("paper-heavy-slide").replace(duration=0.15)
    lp = actuator_loops(HEAVY, sc)
    d = verify(predict(Design("notch PI", PI_NOTCH, lp[0].margins(PI_NOTCH.gains)), lp, HEAVY, sc), HEAVY, sc)
    ref = _python_path_verified(HEAVY, PI_NOTCH, sc, [NOTCH], sc.duration)
    for k, v in ref.as_dict().items():
        got = d.verified[0].as_dict()[k]
        assert got == pytest.approx(v, rel=1e-12, abs=1e-15), k
    bare = _python_path_verified(HEAVY, PI_NOTCH, sc, None, sc.duration)
    assert abs(bare.iae - ref.iae) > 1e-3 * ref.iae  # the notch changed the run


def test_heavy_slide_scene_end_to_end_is_the_python_path(tmp_path):
    """prsa-tune --plant paper-heavy-slide --scene paper-heavy-slide: the tuned gains are the
    Tuner's on the Python path's loop (loop_builder + notch) and the verified metrics its
    nonlinear run's, to round-off; the JSON and the export carry the notch in drive terms."""
    out, exp = tmp_path / "r.json", tmp_path / "e.toml"
    assert main(["--plant", "paper-heavy-slide", "--scene", "paper-heavy-slide", "--json", str(out), "--export",
                 str(exp), "--quiet", "--workers", "1"]) == 0
    rep = json.loads(out.read_text())
    sc = load_scene("paper-heavy-slide")
    ref_loop = _python_path_loop(HEAVY, 1000.0, 1000.0, sc.duration - sc.step_time, [NOTCH])
    res = Tuner([ref_loop], objective="iae", controller="pi").tune(ms_max=1.4)
    assert rep["gains"]["kp"] == pytest.approx(res.pid.kp, rel=1e-12)
    assert rep["gains"]["ki"] == pytest.approx(res.pid.ki, rel=1e-12)
    ref = _python_path_verified(HEAVY, PID(rep["gains"]["kp"], rep["gains"]["ki"], tf=4 * TS), sc, [NOTCH],
                                sc.duration)
    for k, v in ref.as_dict().items():
        assert rep["verified"][k] == pytest.approx(v, rel=1e-12, abs=1e-15), k
    [row] = rep["filters"]
    bq = NOTCH.biquad(TS)
    assert row["path"] == "torque"
    assert row["centre_hz"] == NOTCH.filter.centre_hz
    assert [row["biquad"][k] for k in ("b0", "b1", "b2", "a1", "a2")] == [bq.b0, bq.b1, bq.b2, bq.a1, bq.a2]
    exported = tomllib.loads(exp.read_text())
    assert "notch" in json.dumps(exported)


def test_filter_json_and_report_lines(tmp_path, capsys, monkeypatch):
    """The report's filter lines and the JSON rows give the parameters and the biquad the drive
    runs (recomputed here from the Tustin formula with prewarping)."""
    from prsa_ctrl.studies.scenefilters import describe_filters, filter_rows

    lf = LoopFilter(Notch(300.0, 60.0, -20.0), "speed_measurement")
    [row] = filter_rows([lf], TS)
    w0 = 2 * math.pi * 300.0
    k = w0 / math.tan(w0 * TS / 2)
    zeta, g = 60.0 / 600.0, 0.1
    n = [k * k / w0**2 + 2 * g * zeta * k / w0 + 1, 2 * (1 - k * k / w0**2), k * k / w0**2 - 2 * g * zeta * k / w0 + 1]
    d = [k * k / w0**2 + 2 * zeta * k / w0 + 1, 2 * (1 - k * k / w0**2), k * k / w0**2 - 2 * zeta * k / w0 + 1]
    want = [n[0] / d[0], n[1] / d[0], n[2] / d[0], d[1] / d[0], d[2] / d[0]]
    got = [row["biquad"][k] for k in ("b0", "b1", "b2", "a1", "a2")]
    assert got == pytest.approx(want, rel=1e-12)
    assert row["path"] == "speed"
    assert row["depth_db"] == -20.0
    [line] = describe_filters([lf], TS)
    assert line.startswith("notch on the speed measurement: centre 300 Hz, width 60 Hz (Q 5), depth -20 dB")


@pytest.mark.parametrize("value, typed, shown", [(True, None, "True"), ("100", None, "'100'"), (float("inf"), None, "inf"),
                                                 (float("nan"), {"centre_hz": "nan"}, "nan")])
def test_a_filter_number_is_checked_by_the_one_validator(value, typed, shown):
    """Every number of an entry goes through options.check_number: the entry, the key and the
    value as typed (the flag's text when there is one)."""
    with pytest.raises(SceneError) as exc:
        filter_entry("notch", {"path": "speed", "centre_hz": value, "width_hz": 10.0}, "s.toml: filters.notch[1]",
                     typed=typed)
    assert str(exc.value) == f"s.toml: filters.notch[1].centre_hz = {shown}; expected a finite number"
