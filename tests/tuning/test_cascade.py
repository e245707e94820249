"""Position loop over the speed loop (prsa_ctrl.tuning.cascade, measurement.PositionLoop, simulation.run
with position=...): steady start, tracking, reversal through stiction, hunting of a position PI,
slower position rate, the move scene, the linear cascade model, joint vs sequential tuning and
the drive export of the position loop."""

import dataclasses
import math
import tomllib

import numpy as np
import pytest

from prsa_ctrl import PID
from prsa_ctrl.io.export import export_cascade
from prsa_ctrl.studies.move import hunting, move_metrics, simulate_move, verify_design
from prsa_ctrl.studies.movescene import load_move_scene
from prsa_ctrl.tuning.cascade import BREAKING_POINTS, CascadeModel, sequential_design, tune_cascade
from prsa_ctrl.errors import SceneError
from prsa_ctrl.io.export import dumps
from prsa_ctrl.drive.measurement import POSITION_SENSORS, PositionLoop
from prsa_ctrl.plant.model import stick_band_rad_s
from prsa_ctrl.drive.motion import out_and_back, s_curve
from prsa_ctrl.sim.engine import run

PI = PID(0.0809, 13.56)


@pytest.fixture(scope="module")
def plant(paper_plant):
    return paper_plant


@pytest.fixture(scope="module")
def scene():
    return load_move_scene("paper-move")


def _err_m(r, plant):
    unit = plant.lead_per_rad if r.info["position_loop"]["measured"] == "nut_angle" else 1.0
    return (r.output("position_reference") - r.output("position_measured")) * unit


def test_paper_move_scene(scene):
    assert (scene.distance_m, scene.max_speed_m_s, scene.load_n) == (0.01, 0.03, 1500.0)
    m = scene.motion()
    # The load appears in the middle of the move and is held; the hold step comes after the move.
    assert scene.load_at_s == pytest.approx(0.5 * (m.t0[0] + m.end_time))
    assert scene.loads() == [(0.0, 0.0), (scene.load_at_s, 1500.0), (scene.hold_step_s, 3000.0)]
    assert m.final_position == pytest.approx(0.01, rel=1e-12)
    assert scene.hold_step_s > m.end_time
    assert POSITION_SENSORS == ("nut_angle", "screw_position")


@pytest.mark.parametrize("edit, match", [
    ('distance_mm = "10"', r"move\.distance_mm = '10'; expected a finite non-zero travel in mm"),
    ("distance_mm = 0.0", r"move\.distance_mm = 0\.0"),
    ("speed_mm_s = 30.0", r"unknown key move\.speed_mm_s"),
    ('profile = "sine"', r"move\.profile = 'sine'; expected one of trapezoidal, s-curve"),
    ('measured = "tacho"', r"move\.measured = 'tacho'"),
    ("position_rate = 0", r"move\.position_rate = 0"),
    ("position_rate = 5", r"move\.position_rate = 5; expected an integer number of speed-loop samples per "
                          r"position-loop sample in \[1, 4\]"),
    ("load_time_s = 5.0", r"move\.load_time_s = 5\.0; expected a time in s inside the move"),
])
def test_move_scene_errors_name_file_and_key(tmp_path, edit, match):
    key = edit.split(" = ")[0]
    lines = [ln for ln in (load_move_scene.__globals__["locate_scene"]("paper-move")[0]).read_text().splitlines()
             if not ln.startswith(key + " ")]
    text = "\n".join(lines).replace("[move]", "[move]\n" + edit, 1)
    f = tmp_path / "bad-move.toml"
    f.write_text(text)
    with pytest.raises(SceneError, match=match) as exc:
        load_move_scene(f)
    assert str(f) in str(exc.value)
    assert "\n" not in str(exc.value)


def test_move_scene_structure_errors(tmp_path):
    f = tmp_path / "m.toml"
    f.write_text('[move]\nprofile = "s-curve"\ndistance_mm = 1.0\nmax_speed_mm_s = 10.0\nacceleration_m_s2 = 1.0\n')
    with pytest.raises(SceneError, match=r"m\.toml: move\.jerk_m_s3 missing"):
        load_move_scene(f)
    f.write_text('[move]\nprofile = "trapezoidal"\ndistance_mm = 1.0\nmax_speed_mm_s = 10.0\n')
    with pytest.raises(SceneError, match=r"move\.acceleration_m_s2 missing"):
        load_move_scene(f)
    f.write_text('[move]\nprofile = "trapezoidal"\n[operating]\nsetpoint_rpm = 300.0\n')
    with pytest.raises(SceneError, match=r"unknown section 'operating'"):
        load_move_scene(f)
    f.write_text('[move]\nprofile = "trapezoidal"\ndistance_mm = 1.0\nmax_speed_mm_s = 10.0\nacceleration_m_s2 = 1.0\n'
                 '[cascade]\nms_max = 0.9\n')
    with pytest.raises(SceneError, match=r"cascade\.ms_max = 0\.9"):
        load_move_scene(f)
    with pytest.raises(SceneError, match="not found"):
        load_move_scene(tmp_path / "none.toml")


def test_position_loop_arguments():
    with pytest.raises(ValueError, match="PositionLoop kv = -1"):
        PositionLoop(kv=-1.0)
    with pytest.raises(ValueError, match="PositionLoop measured = 'x'"):
        PositionLoop(kv=1.0, measured="x")
    with pytest.raises(ValueError, match="PositionLoop rate = 0"):
        PositionLoop(kv=1.0, rate=0)
    with pytest.raises(ValueError, match="kv = ki = 0"):
        PositionLoop(kv=0.0)


def test_run_position_arguments(plant):
    pos = PositionLoop(kv=40.0)
    with pytest.raises(ValueError, match="expected discrete=True"):
        run(plant, controller=PI, position=pos, fidelity="rigid", duration=0.01)
    with pytest.raises(ValueError, match="expected a speed PI"):
        run(plant, controller=PID(0.08), position=pos, fidelity="rigid", discrete=True, duration=0.01)
    with pytest.raises(ValueError, match="expected a PositionLoop"):
        run(plant, controller=PI, motion=s_curve(0.001, 0.01, 0.5, 50.0), fidelity="rigid", discrete=True,
            duration=0.01)


@pytest.mark.parametrize("measured", ["nut_angle", "screw_position"])
def test_holds_at_rest_in_steady_state(plant, measured):
    """No move, 1500 N held from t = 0: the compliant actuator stays exactly where it started
    (the run starts in its steady state; a wrong initial integral or measurement memory would
    move it)."""
    r = run(plant, load=1500.0, duration=0.03, controller=PI, fidelity="compliant", discrete=True,
            position=PositionLoop(kv=40.0, measured=measured))
    x = r.states
    for name in ("theta_nut", "omega_nut", "tau_motor", "delta_screw", "x_roller"):
        row = x[r.state_labels.index(name)]
        assert np.max(np.abs(row - row[0])) <= 1e-9 * max(abs(row[0]), 1e-6), name
    assert np.all(_err_m(r, plant) == 0.0)
    assert np.all(r.output("speed_reference") == 0.0)


def test_screw_position_is_the_scale_reading(plant):
    """With a linear scale the loop reads x_S = a th_N + x_roller - delta_screw, quantised."""
    pos = PositionLoop(kv=40.0, measured="screw_position", scale_resolution_m=1e-8)
    m = s_curve(2e-4, 0.01, 0.5, 50.0).shifted(0.005)
    r = run(plant, load=[(0, 1000.0)], duration=0.04, controller=PI, fidelity="compliant", discrete=True,
            position=pos, motion=m)
    s = r.states
    xs = plant.lead_per_rad * s[r.state_labels.index("theta_nut")] + s[r.state_labels.index("x_roller")] \
        - s[r.state_labels.index("delta_screw")]
    assert np.allclose(r.output("position_measured"), np.floor(xs / 1e-8) * 1e-8, rtol=0, atol=1e-15)
    # The reference is the profile added to the reading at t = 0.
    assert np.allclose(r.output("position_reference") - r.output("position_measured")[0], m.at(r.time)[0],
                       rtol=0, atol=1e-15)


def test_velocity_feedforward_and_the_kv_following_error(plant):
    """P position loop without feed-forward: at constant speed the speed PI's integral makes
    the speed exact, so kv e = v/a: the following error is v/kv (the definition of Kv).
    With full velocity and acceleration feed-forward it is far smaller."""
    m = s_curve(0.004, 0.02, 0.5, 50.0).shifted(0.005)
    kv = 60.0
    r0 = run(plant, load=0.0, duration=m.end_time, controller=PI, fidelity="rigid", discrete=True,
             position=PositionLoop(kv=kv, kvff=0.0), motion=m)
    cruise = (r0.time > m.t0[0] + 0.14) & (r0.time < m.t0[0] + 0.18)
    assert np.all(m.at(r0.time[cruise])[1] == pytest.approx(0.02, rel=1e-12))
    assert np.mean(_err_m(r0, plant)[cruise]) == pytest.approx(0.02 / kv, rel=0.02)
    r1 = run(plant, load=0.0, duration=m.end_time, controller=PI, fidelity="rigid", discrete=True,
             position=PositionLoop(kv=kv, kvff=1.0, kaff=1.0), motion=m)
    assert np.max(np.abs(_err_m(r1, plant))) < 0.1 * np.max(np.abs(_err_m(r0, plant)))
    # The torque feed-forward is J acc/a exactly.
    acc = m.at(r1.time)[2]
    assert np.allclose(r1.output("torque_feedforward"), plant.reflected_inertia_kg_m2 * acc / plant.lead_per_rad,
                       rtol=1e-12, atol=1e-15)


def test_slower_position_rate_holds_the_reference(plant):
    m = s_curve(5e-4, 0.01, 0.5, 50.0).shifted(0.002)
    r = run(plant, load=0.0, duration=0.03, controller=PI, fidelity="rigid", discrete=True,
            position=PositionLoop(kv=40.0, kvff=1.0, rate=4), motion=m)
    w = r.output("speed_reference")
    k = np.arange(w.size)
    changes = np.flatnonzero(np.diff(w) != 0) + 1
    assert changes.size > 10
    assert np.all(k[changes] % 4 == 0)


def test_reversal_through_stiction_without_hunting(plant):
    """Out and back under 1500 N with a P position loop: the nut reverses in both directions
    through the stick band, settles in the window, creeps in without reversing and does not
    hunt."""
    m = out_and_back("s-curve", 2e-4, 0.01, 0.5, 50.0, dwell_s=0.03).shifted(0.005)
    r = run(plant, load=1500.0, duration=m.end_time + 0.1, controller=PI, fidelity="compliant", discrete=True,
            position=PositionLoop(kv=40.0, kvff=1.0, kaff=1.0), motion=m)
    w = r.output("nut_speed")
    band = stick_band_rad_s(plant)
    assert np.max(w) > 20.0
    assert np.min(w) < -20.0
    end = r.time > m.end_time + 0.05
    e = _err_m(r, plant)
    assert np.max(np.abs(e[end])) < 2e-6
    assert abs(w[end][-1]) < abs(w[end][0]) / 3  # creeping in, decaying
    h = hunting(r.time[end], e[end], w[end], window_m=2e-6, stick_band_rad_s=band)
    assert not h["oscillating"]
    assert h["reversals"] == 0


def test_position_pi_hunts_against_stiction(plant):
    """The classic limit cycle: a position integral winds up while the nut sticks, breaks it
    loose, overshoots and sticks on the other side. The P loop (same kv) settles."""
    m = out_and_back("s-curve", 2e-5, 0.003, 0.5, 50.0, dwell_s=0.05).shifted(0.01)
    out = {}
    for kip in (0.0, 2000.0):
        r = run(plant, load=1500.0, duration=1.6, controller=PI, fidelity="rigid", discrete=True,
                position=PositionLoop(kv=42.0, ki=kip), motion=m)
        tail = r.time > 0.8
        out[kip] = hunting(r.time[tail], _err_m(r, plant)[tail], r.output("nut_speed")[tail], window_m=2e-6,
                           stick_band_rad_s=stick_band_rad_s(plant))
    assert not out[0.0]["oscillating"]
    assert out[0.0]["reversals"] == 0
    assert out[2000.0]["oscillating"]
    assert out[2000.0]["reversals"] >= 5
    assert 0.1 < out[2000.0]["period_s"] < 0.4


def test_hunting_detector_on_synthetic_records():
    t = np.linspace(0.0, 1.0, 4001)
    w = 5.0 * np.sin(2 * np.pi * 5 * t)
    e = 1e-6 * np.cos(2 * np.pi * 5 * t)
    h = hunting(t, e, w, window_m=2e-6, stick_band_rad_s=0.003)
    assert h["oscillating"]
    assert h["reversals"] == 9
    assert h["period_s"] == pytest.approx(0.2, rel=0.01)
    decaying = hunting(t, e * np.exp(-20 * t), w * (t < 0.15), window_m=2e-6, stick_band_rad_s=0.003)
    assert not decaying["oscillating"]


def test_metrics_of_a_move(plant, scene):
    sc = dataclasses.replace(scene, fidelity="rigid")
    r = simulate_move(plant, sc, PI, PositionLoop(kv=42.0, kvff=1.0, kaff=1.0))
    mm = move_metrics(r, plant, sc)
    e = _err_m(r, plant)
    t = r.time
    assert mm.peak_following_error_m == pytest.approx(np.max(np.abs(e[(t >= sc.start_s) & (t < sc.hold_step_s)])))
    assert mm.holding_deviation_m == pytest.approx(np.max(np.abs(e[t >= sc.hold_step_s])))
    assert mm.holding_deviation_m > 0
    assert mm.peak_torque_n_m < plant.torque_limit
    assert math.isfinite(mm.settling_time_s)
    assert mm.final_error_m == pytest.approx(e[-1])
    assert not mm.hunting["oscillating"]


def test_linear_cascade_matches_the_drive_loop_model(plant, scene):
    """The cascade model's speed loop (position loop opened) is the project's drive loop model
    (tuning.drive_loop) of the same plant and PI, to rounding."""
    from prsa_ctrl.plant.linear import linear_core
    from prsa_ctrl.plant.model import plant_model
    from prsa_ctrl.tuning.builders import drive_loop

    sc = dataclasses.replace(scene, fidelity="rigid")
    cm = CascadeModel(plant, sc.cascade_spec())
    model = plant_model(plant, "rigid")
    a, b, c, _, _ = linear_core(plant, cm.w_lin, sc.load_n, "rigid")
    lp = drive_loop(a, b, c[model.output_names.index("nut_speed")], model.index("theta_nut"), ts=plant.sample_time_s,
                    speed_filter=plant.speed_filter_s, tf=1e-3, horizon=0.05, step=100.0)
    w = np.geomspace(1.0, 1e4, 50)
    ours = cm.loops([PI.kp, PI.ki, 40.0, 0.0, 1.0, 1.0], w)["speed_open"]
    theirs = lp.loop_response([PI.kp, PI.ki, 0.0], w)
    assert np.allclose(ours, theirs, rtol=1e-9, atol=0)
    # Closing the position loop changes the inner loop: judged both ways.
    closed = cm.loops([PI.kp, PI.ki, 40.0, 0.0, 1.0, 1.0], w)["speed_closed"]
    assert np.max(np.abs(closed - ours)) > 1e-3 * np.max(np.abs(ours))


def test_linear_model_time_response_matches_its_frequency_response(plant, scene):
    """The time-domain closed loop (what the tuner's objective integrates) and the loop
    transfer functions (what its Ms constraints see) are the same system: the steady error of
    the P cascade at constant speed without feed-forward is v/kv in both."""
    sc = dataclasses.replace(scene, fidelity="rigid", load_n=0.0, hold_step_n=100.0)
    cm = CascadeModel(plant, sc.cascade_spec())
    g = [PI.kp, PI.ki, 50.0, 0.0, 0.0, 0.0]
    e = cm.error(g, "move")
    m = sc.motion()
    t = np.arange(e.size) * cm.ts
    cruise = (t > m.t0[0] + 0.15) & (t < m.t0[0] + 0.25)
    assert np.mean(e[cruise]) == pytest.approx(sc.max_speed_m_s / 50.0, rel=0.01)
    assert cm.spectral_radius(g) < 1


@pytest.fixture(scope="module")
def designs(plant, scene):
    sc = dataclasses.replace(scene, fidelity="rigid")
    cm = CascadeModel(plant, sc.cascade_spec())
    seq = sequential_design(plant, sc.cascade_spec(), cm)
    joint = tune_cascade(plant, sc.cascade_spec(), baseline=seq, cm=cm)
    seq, joint = (verify_design(d, plant, sc) for d in (seq, joint))
    return sc, cm, seq, joint


def test_joint_beats_sequential_at_equal_ms(designs):
    sc, cm, seq, joint = designs
    for d in (seq, joint):
        # The reported Ms are the true ones (recomputed here on another dense grid).
        again = cm.ms(d.gains, n_dense=30011)
        for k in BREAKING_POINTS:
            assert d.ms_points[k] <= sc.ms_max * (1 + 1e-5)
            assert again[k] == pytest.approx(d.ms_points[k], rel=1e-4)
        assert d.ms == max(d.ms_points[k] for k in BREAKING_POINTS)
        assert d.status == "ok"
        assert cm.spectral_radius(d.gains) < 1
    assert joint.method == "joint"
    assert joint.objective < seq.objective
    assert joint.linear["rms_following_error_m"] < seq.linear["rms_following_error_m"]
    # ... and on the nonlinear model.
    assert joint.verified.rms_following_error_m < seq.verified.rms_following_error_m
    assert joint.verified.peak_following_error_m < seq.verified.peak_following_error_m
    assert joint.verified.holding_deviation_m < seq.verified.holding_deviation_m


def _exported_position_law(pc, p_ref, p_meas, v_ref, acc_ref):
    """The position law evaluated from the exported ``law`` expressions and fields only."""
    fields = {k: v for k, v in pc.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
    law = pc["law"]
    assert set(law) == {"e", "I", "w_ref", "tau_ff"}
    for k, expr in law.items():  # the human formula states the same law
        assert f"{k}[k] = {expr}" in pc["formula"]
    integ, w_ref, tau_ff = 0.0, np.empty(p_ref.size), np.empty(p_ref.size)
    for k in range(p_ref.size):
        env = {**fields, "p_ref": p_ref[k], "p_meas": p_meas[k], "v_ref": v_ref[k], "acc_ref": acc_ref[k],
               "I_prev": integ}
        for name in ("e", "I", "w_ref", "tau_ff"):
            env[name] = eval(law[name], {"__builtins__": {}}, env)  # noqa: S307 - our own export
        integ, w_ref[k], tau_ff[k] = env["I"], env["w_ref"], env["tau_ff"]
    return w_ref, tau_ff


def test_position_export_reproduces_the_simulated_law(plant, designs):
    """Round trip: the exported position law (its ``law`` expressions over the exported fields,
    nothing from the plant), run on the positions the drive measured, gives the speed references,
    the torque feed-forward and, through the exported speed PI, the torque command of the
    simulated loop to 1e-9."""
    sc, cm, seq, joint = designs
    # A position PI and a partial acceleration feed-forward, so that the exported integral and
    # the feed-forward gain (applied once) are exercised.
    joint = dataclasses.replace(joint, position=dataclasses.replace(joint.position, ki=800.0, kaff=0.6))
    for fmt in ("toml", "json"):
        d = export_cascade(joint, plant, fmt=fmt)
        d = tomllib.loads(dumps(d, "toml")) if fmt == "toml" else __import__("json").loads(dumps(d, "json"))
        pc = d["position_controller"]
        assert pc["kv_per_s"] == joint.position.kv
        assert pc["sample_time_s"] == plant.sample_time_s
        assert "absent" not in d["speed_controller"]["vendor"]["note"]
        r = simulate_move(plant, sc, joint.speed, joint.position, duration=0.3, loads=sc.loads()[:2])
        _, v_ref, acc_ref = sc.motion().at(r.time)
        w_ref, tau_ff = _exported_position_law(pc, r.output("position_reference"), r.output("position_measured"),
                                               v_ref, acc_ref)
        assert np.allclose(w_ref, r.output("speed_reference"), rtol=1e-9, atol=1e-9 * np.max(np.abs(w_ref)))
        assert np.max(np.abs(tau_ff)) > 0.05
        assert np.allclose(tau_ff, r.output("torque_feedforward"), rtol=1e-9, atol=1e-12)
        # The whole torque command through the exported speed PI (explicit Euler, anti-windup).
        law = d["speed_controller"]["discrete"]
        kp, ki, k_aw, lim = (law[k] for k in ("kp_n_m_s_per_rad", "ki_n_m_per_rad", "anti_windup_gain_per_s",
                                              "torque_limit_n_m"))
        integ = r.states[r.state_labels.index("pid_integral"), 0]
        us = np.empty(w_ref.size)
        for k, (wr, w, ff) in enumerate(zip(w_ref, r.output("speed_measured"), tau_ff)):
            e = wr - w
            u = kp * e + integ + ff
            us[k] = min(max(u, -lim), lim)
            integ += law["sample_time_s"] * (ki * e + k_aw * (us[k] - u))
        tc = r.output("torque_command")  # the command computed at sample k is applied at k + 1
        assert np.max(np.abs(us[:-1] - tc[1:])) < 1e-9 * max(1.0, np.max(np.abs(tc)))


def test_position_export_with_a_delay_reproduces_the_simulated_law(plant, designs):
    """The exported position law at its own sample time (every 2nd sample), its outputs applied
    ``delay_samples`` position samples later as the export states, from the exported fields only:
    the simulated speed references and feed-forward of a run with that delay, to 1e-9."""
    sc, cm, seq, joint = designs
    pos = dataclasses.replace(joint.position, ki=800.0, kaff=0.6, rate=2, delay=2)
    design = dataclasses.replace(joint, position=pos)
    pc = tomllib.loads(dumps(export_cascade(design, plant, fmt="toml"), "toml"))["position_controller"]
    n_rate = round(pc["sample_time_s"] / plant.sample_time_s)
    assert (n_rate, pc["delay_samples"]) == (2, 2)
    assert pc["delay_s"] == pytest.approx(4 * plant.sample_time_s)
    r = simulate_move(plant, sc, joint.speed, pos, duration=0.3, loads=sc.loads()[:2])
    _, v_ref, acc_ref = sc.motion().at(r.time)
    k = np.arange(0, r.time.size, n_rate)  # the position-loop samples
    w_p, t_p = _exported_position_law(pc, r.output("position_reference")[k], r.output("position_measured")[k],
                                      v_ref[k], acc_ref[k])
    d = pc["delay_samples"]
    w_applied = np.repeat(np.concatenate([np.zeros(d), w_p[:-d]]), n_rate)[:r.time.size]
    t_applied = np.repeat(np.concatenate([np.zeros(d), t_p[:-d]]), n_rate)[:r.time.size]
    w_sim = r.output("speed_reference")
    assert np.allclose(w_applied, w_sim, rtol=1e-9, atol=1e-9 * np.max(np.abs(w_sim)))
    assert np.allclose(t_applied, r.output("torque_feedforward"), rtol=1e-9, atol=1e-12)
    # the delay shows: the undelayed law is far from the run
    w_now = np.repeat(w_p, n_rate)[:r.time.size]
    assert np.max(np.abs(w_now - w_sim)) > 1e-3 * np.max(np.abs(w_sim))


def test_cli_move_scene_bad_flags_exit_2(tmp_path, capsys):
    from prsa_ctrl.cli.tune import main

    assert main(["--scene", "paper-move", "--export", str(tmp_path / "drive.txt")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "--export" in err
    assert "drive.txt" in err
    assert main(["--scene", "paper-move", "--setpoint-rpm", "100.0"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("prsa-tune: error: --setpoint-rpm 100.0 does not apply to a move scene")
    assert not (tmp_path / "drive.txt").exists()


def test_speed_loop_scene_loader_points_to_the_move_scene():
    """One loader for both kinds (issue 22): a [move] scene loads as a MoveScene; where a
    speed-loop scene is needed it is refused with the message the loader gave before."""
    from prsa_ctrl.studies.movescene import MoveScene
    from prsa_ctrl.studies.scene import load_scene, require_speed_scene

    sc = load_scene("paper-move")
    assert isinstance(sc, MoveScene)
    assert sc == load_move_scene("paper-move")
    with pytest.raises(SceneError, match=r"paper-move\.toml \(built-in\): a move scene"):
        require_speed_scene(sc)


def test_screw_side_error_shows_the_thread_deflection(plant, scene):
    """Nut-angle feedback holds the nut exactly, but the 1500 N step compresses the threads:
    the screw's true position is off by the extra deflection, which a linear scale would see."""
    m_short = dataclasses.replace(scene, distance_m=2e-4, start_s=0.005, hold_delay_s=0.02, hold_duration_s=0.06)
    r = simulate_move(plant, m_short, PI, PositionLoop(kv=40.0, kvff=1.0, kaff=1.0))
    mm = move_metrics(r, plant, m_short)
    x = r.states
    ds = x[r.state_labels.index("x_roller")] - x[r.state_labels.index("delta_screw")]
    # Screw error = nut-side error plus the change of the contact deflection since t = 0.
    count_m = plant.lead_per_rad * 2 * math.pi / plant.encoder_counts  # the encoder reading is quantised
    assert mm.screw_final_error_m == pytest.approx(mm.final_error_m - (ds[-1] - ds[0]), rel=0, abs=count_m)
    assert abs(ds[-1] - ds[0]) > 1e-7


def test_bandwidth_ratio_option(plant, designs):
    sc, cm, seq, joint = designs
    sc5 = dataclasses.replace(sc, bandwidth_ratio=5.0)
    d = tune_cascade(plant, sc5.cascade_spec(), baseline=seq, cm=cm)
    assert d.method == "joint"
    assert d.speed.kp / plant.reflected_inertia_kg_m2 >= 5.0 * d.position.kv * (1 - 1e-6)
    assert joint.speed.kp / plant.reflected_inertia_kg_m2 < 5.0 * joint.position.kv  # the option is active
    assert max(d.ms_points[k] for k in BREAKING_POINTS) <= sc.ms_max * (1 + 1e-5)
    # A constraint can only cost: the ratio-limited design is no better than the free one.
    assert d.objective >= joint.objective * (1 - 1e-6)


def test_gains_are_projected_onto_the_nlp_bounds():
    """Ipopt's result may sit a hair outside a bound (kaff = -9e-9 for a 1 um move): the design
    is built from the projected gains, which PositionLoop accepts."""
    from prsa_ctrl.tuning.cascade import gains_from_solution

    lbx, ubx = [1e-3, 1e-3, 1e-3, 0.0, 0.0], [1e3, 1e3, 1e3, 1.5, 1.5]
    x, g = gains_from_solution([0.5, 2.0, 1e3 + 1e-9, 1.5 + 2e-9, -9.2e-9], lbx, ubx, [0, 1, 2, 4, 5],
                                [0.08, 10.0, 40.0, 160.0, 1.0, 1.0])
    assert list(x) == [0.5, 2.0, 1e3, 1.5, 0.0]
    assert g[5] == 0.0
    assert g[4] == 1.5
    assert g[2] == 4e4
    assert g[3] == 0.0
    PositionLoop(kv=g[2], ki=g[3], kvff=g[4], kaff=g[5])  # no error


def test_cli_move_scene_plots_quiet_json_export(tmp_path, capsys):
    """A short rigid move through prsa-tune: --quiet prints nothing, --plots writes the move and
    hold figures (PNG + SVG), --json and --export hold both designs and the joint law."""
    import json

    from prsa_ctrl.studies.scenefile import locate_scene as _scene_path
    from prsa_ctrl.cli.tune import main

    text = _scene_path("paper-move")[0].read_text()
    for key, value in (("distance_mm", "2.0"), ("fidelity", '"rigid"'), ("hold_duration_s", "0.06"),
                       ("hold_delay_s", "0.03")):
        text = "\n".join(f"{key} = {value}" if ln.startswith(key + " ") else ln for ln in text.splitlines())
    f = tmp_path / "short.toml"
    f.write_text(text)
    out = tmp_path / "figs"
    rc = main(["--scene", str(f), "--quiet", "--plots", str(out), "--json", str(tmp_path / "c.json"),
               "--export", str(tmp_path / "d.toml")])
    cap = capsys.readouterr()
    assert rc == 0
    assert cap.out == ""
    assert cap.err == ""
    assert sorted(p.name for p in out.iterdir()) == ["hold.png", "hold.svg", "move.png", "move.svg"]
    assert all(p.stat().st_size > 1000 for p in out.iterdir())
    data = json.loads((tmp_path / "c.json").read_text())
    for name in ("sequential", "joint"):
        assert max(data[name]["ms"][k] for k in BREAKING_POINTS) <= 1.4 * (1 + 1e-5)
    pc = tomllib.loads((tmp_path / "d.toml").read_text())["position_controller"]
    assert pc["kv_per_s"] == data["joint"]["position"]["kv_per_s"]
    assert "kaff" not in pc["law"]["tau_ff"]
    assert "acceleration_feedforward" not in pc["law"]["tau_ff"]


def test_text_report_names_every_bound_and_the_position_integral(plant, designs):
    from prsa_ctrl.studies.scenereport import format_move_report

    sc, cm, seq, joint = designs
    pi = dataclasses.replace(joint, position=dataclasses.replace(joint.position, ki=800.0))
    text = format_move_report(plant, dataclasses.replace(sc, position_controller="pi"), [seq, pi])
    assert "speed loop (position loop closed / opened), position loop, torque command" in text
    assert f"torque command {pi.ms_points['torque']:.3f}" in text
    assert "ki 800 1/s^2" in text
    lin, ver = joint.linear["holding_deviation_m"], joint.verified.holding_deviation_m
    assert f"holding deviation {lin * 1e6:.3f} um ({lin / ver:.2g} x the verified)" in text
    assert "ki 800" not in format_move_report(plant, sc, [seq, joint])


# --- the position loop at its own sample time (issue 34, section 3) ---------------------------

def _biquad_run(coef, mem, x):
    b0, b1, b2, a1, a2 = coef
    y = b0 * x + b1 * mem[0] + b2 * mem[1] - a1 * mem[2] - a2 * mem[3]
    mem[:] = [x, mem[0], y, mem[2]]
    return y


def _simulate_multirate(plant, cm, g, n_rate, omega, where, samples, biquads=(), p_delay=0):
    """An independent simulation of the linear multi-rate cascade (this test's own code: the
    plant discretised here with scipy's expm, the drive's per-sample law written out), with a
    complex sinusoid ``exp(j omega k Ts)`` added at one loop-breaking point: ``torque`` (the
    controller's command, before its delay), ``speed_closed`` (the filtered speed the PI reads)
    or ``position`` (the position the position loop reads, at its own samples). Returns the
    signal at the breaking point (command + disturbance, and so on), one per speed sample.
    ``biquads``: ``(place, (b0, b1, b2, a1, a2))`` loop filters, direct form I, on the filtered
    speed (``speed_measurement``) or on the command (``torque_command``). ``p_delay``: the
    position loop's computation delay, in position-loop samples (its output enters a queue at
    each position-loop sample and leaves it ``p_delay`` position-loop samples later)."""
    from scipy.linalg import expm

    from prsa_ctrl.plant.linear import linear_core
    from prsa_ctrl.plant.model import plant_model

    ts, a = plant.sample_time_s, plant.lead_per_rad
    A, B, _, _, _ = linear_core(plant, cm.w_lin, cm.load_lin, "rigid")
    n = A.shape[0]
    E = expm(np.block([[A, B[:, :1]], [np.zeros((1, n + 1))]]) * ts)
    Ad, bu = E[:n, :n], E[:n, n]
    c = np.eye(n)[plant_model(plant, "rigid").index("theta_nut")]
    alpha = math.exp(-ts / plant.speed_filter_s)
    kp, ki, kv, kip = g[:4]
    tp = n_rate * ts
    line = [0j] * (1 + plant.command_delay_samples)  # computation delay + the drive's command delay
    x = np.zeros(n, complex)
    th_prev = w_f = i_s = i_p = w_ref = 0j
    queue = [0j] * p_delay
    out = np.zeros(samples, complex)
    mems = [[0j] * 4 for _ in biquads]
    for k in range(samples):
        d = np.exp(1j * omega * k * ts)
        theta = c @ x
        w_f = alpha * w_f + (1 - alpha) * (theta - th_prev) / ts
        th_prev = theta
        if k % n_rate == 0:
            p_read = theta + (d if where == "position" else 0)
            e = 0 - p_read
            i_p = i_p + tp * kip * e
            queue.append(kv * e + i_p)
            w_ref = queue.pop(0)
            if where == "position":
                out[k] = p_read
        w_m = w_f
        for (place, coef), mem in zip(biquads, mems):
            if place == "speed_measurement":
                w_m = _biquad_run(coef, mem, w_m)
        w_used = w_m + (d if where == "speed_closed" else 0)
        u = kp * (w_ref - w_used) + i_s
        i_s = i_s + ts * ki * (w_ref - w_used)
        u_total = u + (d if where == "torque" else 0)
        if where == "torque":
            out[k] = u_total
        elif where == "speed_closed":
            out[k] = w_used
        u_cmd = u_total
        for (place, coef), mem in zip(biquads, mems):
            if place == "torque_command":
                u_cmd = _biquad_run(coef, mem, u_cmd)
        line.insert(0, u_cmd)
        x = Ad @ x + bu * line.pop()
    return out


def _two_filters():
    from prsa_ctrl.studies.scenefilters import parse_filters

    return parse_filters({"notch": [{"path": "torque", "centre_hz": 1200.0, "width_hz": 300.0, "depth_db": -20.0}],
                          "lowpass": [{"path": "speed", "corner_hz": 900.0, "order": 2}]}, "test")


@pytest.mark.parametrize("n_rate, filtered, p_delay", [(2, False, 0), (3, False, 0), (2, True, 0), (1, True, 0),
                                                       (2, False, 1), (1, False, 2), (3, True, 1)])
def test_multirate_model_matches_an_independent_simulation(plant, scene, n_rate, filtered, p_delay):
    """The lifted loop model of a position loop every N speed samples (CascadeModel at
    position_rate = N) against a direct simulation of the linear multi-rate loop: a sinusoid
    injected at each breaking point, in steady state, gives over a position period exactly
    the lifted sensitivity ``M^-1`` times the input's lifted vector (the scalar ``1/(1 + L_p)``
    at the position loop), at frequencies below and above the position loop's Nyquist; with a
    torque notch and a speed low-pass (the scene's fixed filters) in the loop too; and with the
    position loop's own computation delay (``position_delay_samples``)."""
    sc = dataclasses.replace(scene, fidelity="rigid", position_rate=n_rate, position_delay_samples=p_delay)
    if filtered:
        f, labels = _two_filters()
        sc = dataclasses.replace(sc, filters=f, filter_labels=labels)
    cm = CascadeModel(plant, sc.cascade_spec())
    ts = plant.sample_time_s
    bqs = [(lf.place, tuple(getattr(lf.biquad(ts), k) for k in ("b0", "b1", "b2", "a1", "a2"))) for lf in sc.filters]
    assert len(bqs) == (2 if filtered else 0)
    g = [PI.kp, PI.ki, 70.0, 2000.0, 1.0, 1.0]  # a position PI, so that its slow integral is checked too
    assert cm.delay == p_delay
    assert cm.spectral_radius(g) < 0.995
    samples = 4200 - 4200 % n_rate
    tp = n_rate * plant.sample_time_s
    for omega in (150.0, 700.0, 0.8 * math.pi / tp):
        zp = np.exp(1j * omega * tp)
        M = cm.return_differences(g, np.array([omega]))
        for where in ("torque", "speed_closed"):
            y = _simulate_multirate(plant, cm, g, n_rate, omega, where, samples, bqs, p_delay)
            v = np.exp(1j * omega * np.arange(n_rate) * plant.sample_time_s)
            predicted = np.linalg.solve(M[where][0], v)
            last = samples // n_rate - 1
            got = y[last * n_rate:(last + 1) * n_rate] / zp ** last
            assert np.allclose(got, predicted, rtol=1e-7, atol=1e-9 * np.max(np.abs(predicted))), (where, omega)
        y = _simulate_multirate(plant, cm, g, n_rate, omega, "position", samples, bqs, p_delay)
        last = samples // n_rate - 1
        got = y[last * n_rate] / zp ** last
        assert got == pytest.approx(1 / (1 + cm.position_loop(g, np.array([omega]))[0]), rel=1e-7)
    if p_delay:  # the delay is in the model: without it the position loop's sensitivity differs
        y = _simulate_multirate(plant, cm, g, n_rate, 700.0, "position", samples, bqs, p_delay)
        zp = np.exp(1j * 700.0 * tp)
        got = y[(samples // n_rate - 1) * n_rate] / zp ** (samples // n_rate - 1)
        nodelay = CascadeModel(plant, dataclasses.replace(sc, position_delay_samples=0).cascade_spec())
        assert abs(got - 1 / (1 + nodelay.position_loop(g, np.array([700.0]))[0])) > 1e-3 * abs(got)
    if n_rate > 1 and not p_delay:
        # The model's peaks are those sensitivities' maxima: the slow loop sees more than the fast one.
        fast = CascadeModel(plant, dataclasses.replace(sc, position_rate=1).cascade_spec()).ms(g)
        slow = cm.ms(g)
        assert slow["speed_open"] == pytest.approx(fast["speed_open"], rel=1e-12)
        assert slow["position"] > fast["position"]


def test_multirate_time_model_is_the_simulated_law(plant, scene):
    """The tuner's time-domain model at position_rate = 2 (its objective) is the simulator's law
    linearised: the steady following error at constant speed without feed-forward is v/kv, and a
    slower position loop shifts the error it gives over the move (it is not the rate-1 model)."""
    sc = dataclasses.replace(scene, fidelity="rigid", load_n=0.0, hold_step_n=100.0, position_rate=2)
    cm = CascadeModel(plant, sc.cascade_spec())
    g = [PI.kp, PI.ki, 50.0, 0.0, 0.0, 0.0]
    e = cm.error(g, "move")
    m = sc.motion()
    t = np.arange(e.size) * cm.ts
    cruise = (t > m.t0[0] + 0.15) & (t < m.t0[0] + 0.25)
    assert np.mean(e[cruise]) == pytest.approx(sc.max_speed_m_s / 50.0, rel=0.01)
    e1 = CascadeModel(plant, dataclasses.replace(sc, position_rate=1).cascade_spec()).error(g, "move")
    assert np.max(np.abs(e - e1)) > 1e-3 * np.max(np.abs(e1))
    # Against the nonlinear simulator's rigid run of the same gains: the error through the move
    # agrees to the friction's linearisation (a few per cent of the peak).
    r = simulate_move(plant, sc, PID(PI.kp, PI.ki), PositionLoop(kv=50.0, kvff=0.0, kaff=0.0, rate=2))
    e_nl = _err_m(r, plant)[:e.size]
    assert np.max(np.abs(e_nl - e)) < 0.05 * np.max(np.abs(e))


@pytest.mark.parametrize("n_rate, p_delay", [(1, 1), (2, 1), (2, 2)])
def test_position_delay_time_model_is_the_simulated_law(plant, scene, n_rate, p_delay):
    """The tuner's time-domain model with the position loop's own delay is the simulator's law
    (PositionLoop(delay=...)) linearised: over the move, the linear and the nonlinear rigid runs
    of the same gains agree to the friction's linearisation, and the delay is in both (the
    undelayed model differs from the delayed run by more than that)."""
    sc = dataclasses.replace(scene, fidelity="rigid", load_n=0.0, hold_step_n=100.0, position_rate=n_rate,
                             position_delay_samples=p_delay)
    cm = CascadeModel(plant, sc.cascade_spec())
    g = [PI.kp, PI.ki, 50.0, 0.0, 0.0, 0.0]
    e = cm.error(g, "move")
    r = simulate_move(plant, sc, PID(PI.kp, PI.ki), PositionLoop(kv=50.0, kvff=0.0, kaff=0.0, rate=n_rate,
                                                                 delay=p_delay))
    e_nl = _err_m(r, plant)[:e.size]
    e0 = CascadeModel(plant, dataclasses.replace(sc, position_delay_samples=0).cascade_spec()).error(g, "move")
    assert np.max(np.abs(e_nl - e)) < 0.05 * np.max(np.abs(e))
    assert np.max(np.abs(e_nl - e0)) > 4 * np.max(np.abs(e_nl - e))


def test_position_delay_memory_and_arguments():
    """The delay's memory (pending pairs, newest first) and its bounds, named as typed."""
    p = PositionLoop(kv=10.0, delay=2)
    assert p.memory_names[4:] == ("pending_speed_reference_1", "pending_torque_feedforward_1",
                                  "pending_speed_reference_2", "pending_torque_feedforward_2")
    assert p.initial() == [0.0] * 8
    assert PositionLoop(kv=10.0).memory_names[4:] == ()
    assert p.key() != PositionLoop(kv=10.0).key()
    for bad in (-1, 9, 1.0, True):
        with pytest.raises(ValueError, match=f"delay = {bad!r}"):
            PositionLoop(kv=10.0, delay=bad)


def _short_move(tmp_path, name, edits, cascade_lines=()):
    from prsa_ctrl.studies.scenefile import locate_scene as _scene_path

    text = _scene_path("paper-move")[0].read_text()
    for key, value in (("distance_mm", "2.0"), ("fidelity", '"rigid"'), ("hold_duration_s", "0.06"),
                       ("hold_delay_s", "0.03")) + tuple(edits):
        text = "\n".join(f"{key} = {value}" if ln.startswith(key + " ") else ln for ln in text.splitlines())
    text = text.replace("[cascade]", "[cascade]\n" + "\n".join(cascade_lines), 1)
    f = tmp_path / name
    f.write_text(text)
    return f


def test_cli_cascade_at_the_drive_rates_with_a_kv_ceiling(tmp_path, capsys, plant):
    """Acceptance (issue 34, section 3): position_rate = 2 and kv_max = "4 (m/min)/mm" tuned by
    prsa-tune, verified on the nonlinear model, with the position loop's own sample time in every
    export format (TOML, JSON, C, ST)."""
    import json

    from prsa_ctrl.cli.tune import main

    f = _short_move(tmp_path, "rate2.toml", [("position_rate", "2"), ("hold_delay_s", "0.08")], ['kv_max = "4 (m/min)/mm"'])
    # the drive's fixed filters, tuned around (item 3): a torque notch and a speed low-pass
    f.write_text(f.read_text() + '\n[[filters.notch]]\npath = "torque"\ncentre_hz = 1200.0\nwidth_hz = 300.0\n'
                 '[[filters.lowpass]]\npath = "speed"\ncorner_hz = 900.0\norder = 2\n')
    # one prsa-tune run (the CLI's code path for the ST); the TOML, JSON and C below are the
    # library's exports of the design the JSON reports (a second run for the TOML tuned the same
    # scene again; the CLI's TOML of a move scene: test_cli_move_scene_plots_quiet_json_export)
    rc = main(["--scene", str(f), "--quiet", "--json", str(tmp_path / "c.json"), "--export", str(tmp_path / "drive.st")])
    assert rc == 0
    assert capsys.readouterr().err == ""
    data = json.loads((tmp_path / "c.json").read_text())
    ts = plant.sample_time_s
    sc = load_move_scene(f)
    assert [lf.place for lf in sc.filters] == ["torque_command", "speed_measurement"]
    cm = CascadeModel(plant, sc.cascade_spec())
    for name in ("sequential", "joint"):
        d = data[name]
        assert [x["place"] for x in d["filters"]] == ["torque_command", "speed_measurement"]
        assert d["position"]["rate"] == 2
        assert d["position"]["kv_per_s"] <= 4 * 1000 / 60 * (1 + 1e-9)
        assert max(d["ms"][k] for k in BREAKING_POINTS) <= 1.4 * (1 + 1e-5)
        assert d["verified"] is not None
        assert d["verified"]["settling_time_s"] is not None
        g = [d["speed"]["kp"], d["speed"]["ki"], d["position"]["kv_per_s"], d["position"]["ki_per_s2"],
             d["position"]["kvff"], d["position"]["kaff"]]
        assert cm.spectral_radius(g) < 1
        # the reported peaks are the multi-rate model's, recomputed on another grid
        again = cm.ms(g, n_dense=12007)
        for k in BREAKING_POINTS:
            assert again[k] == pytest.approx(d["ms"][k], rel=1e-4)
    # the ceiling binds the joint design (it reaches 98 1/s without it)
    assert data["joint"]["position"]["kv_per_s"] == pytest.approx(4 * 1000 / 60, rel=1e-6)
    assert data["joint"]["verified"]["rms_following_error_m"] < data["sequential"]["verified"]["rms_following_error_m"]
    # the other formats of the same design (what --export d.toml / d.json / drive.c write)
    from prsa_ctrl.io.codegen import code_texts
    from prsa_ctrl.io.export import dumps as _dumps

    d = data["joint"]
    from prsa_ctrl.tuning.cascade import cascade_design

    design = cascade_design(cm, "joint", [d["speed"]["kp"], d["speed"]["ki"], d["position"]["kv_per_s"], 0.0,
                                   d["position"]["kvff"], d["position"]["kaff"]], 0.0)
    assert design.position.rate == 2
    assert len(design.filters) == 2
    exported = tomllib.loads(_dumps(export_cascade(design, plant, fmt="toml"), "toml"))
    pc = exported["position_controller"]
    assert pc["sample_time_s"] == 2 * ts
    assert pc["kv_m_min_per_mm"] == pytest.approx(4.0, rel=1e-6)
    assert len(exported["filters"]) == 2
    assert json.loads(_dumps(export_cascade(design, plant, fmt="json"), "json"))["position_controller"][
        "sample_time_s"] == 2 * ts
    for ext in ("c", "st"):
        code = ("".join(code_texts(design, plant, tmp_path / "drive.c", filters=design.filters).values())
                if ext == "c" else (tmp_path / "drive.st").read_text())
        assert f"every 2 sample(s) (position-loop sample time {2 * ts:g} s" in code
        # the position-loop rate is a run-time parameter of the generated law, written as 2
        assert ("p->position_rate = 2;" if ext == "c" else "P_POSITION_RATE : DINT := 2;") in code
        assert ("phase + 1 >= p->position_rate" if ext == "c" else "t_Phase + 1 >= P_POSITION_RATE") in code
        assert (("p->sf0_b0" in code and "p->tf0_b0" in code) if ext == "c" else
                ("P_SF0_B0" in code and "P_TF0_B0" in code))  # both filters in the generated law


def test_cli_cascade_with_the_position_loops_own_delay(tmp_path, capsys, plant):
    """position_rate = 2 with position_delay_samples = 1 (issue 34): tuned by prsa-tune with the
    delay in the model (the reported peaks are the delayed model's; the undelayed model's differ),
    verified on the nonlinear model, and the delay in every export (TOML, JSON, C, ST)."""
    import json

    from prsa_ctrl.io.codegen import code_texts

    from prsa_ctrl.cli.tune import main

    f = _short_move(tmp_path, "delay.toml", [("position_rate", "2 \nposition_delay_samples = 1"),
                                              ("hold_delay_s", "0.08")])
    sc = load_move_scene(f)
    assert sc.position_rate == 2
    assert sc.position_delay_samples == 1
    # one prsa-tune run (the CLI's code path for the ST); the TOML, JSON and C below are the
    # library's exports of the design the JSON reports (a second run tuned the same scene again)
    rc = main(["--scene", str(f), "--quiet", "--json", str(tmp_path / "c.json"), "--export", str(tmp_path / "drive.st")])
    assert rc == 0
    assert capsys.readouterr().err == ""
    data = json.loads((tmp_path / "c.json").read_text())
    cm = CascadeModel(plant, sc.cascade_spec())
    cm0 = CascadeModel(plant, dataclasses.replace(sc, position_delay_samples=0).cascade_spec())
    for name in ("sequential", "joint"):
        d = data[name]
        assert d["position"]["rate"] == 2
        assert d["position"]["delay_samples"] == 1
        assert max(d["ms"][k] for k in BREAKING_POINTS) <= 1.4 * (1 + 1e-5)
        assert d["verified"] is not None
        assert d["verified"]["settling_time_s"] is not None
        g = [d["speed"]["kp"], d["speed"]["ki"], d["position"]["kv_per_s"], d["position"]["ki_per_s2"],
             d["position"]["kvff"], d["position"]["kaff"]]
        again, undelayed = cm.ms(g, n_dense=12007), cm0.ms(g, n_dense=12007)
        for k in BREAKING_POINTS:
            assert again[k] == pytest.approx(d["ms"][k], rel=1e-4)
        assert undelayed["position"] < again["position"] * (1 - 1e-3)  # the delay costs margin: it is modelled
    ts = plant.sample_time_s
    from prsa_ctrl.tuning.cascade import cascade_design

    d = data["joint"]
    design = cascade_design(cm, "joint", [d["speed"]["kp"], d["speed"]["ki"], d["position"]["kv_per_s"], 0.0,
                                   d["position"]["kvff"], d["position"]["kaff"]], 0.0)
    assert design.position.delay == 1
    pc = tomllib.loads(dumps(export_cascade(design, plant, fmt="toml"), "toml"))["position_controller"]
    assert pc["delay_samples"] == 1
    assert pc["delay_s"] == pytest.approx(2 * ts)
    assert pc["sample_time_s"] == 2 * ts
    assert "applied from sample k + 1 on" in pc["discretisation"]
    assert json.loads(dumps(export_cascade(design, plant, fmt="json"), "json"))["position_controller"][
        "delay_samples"] == 1
    c = "".join(code_texts(design, plant, tmp_path / "drive.c").values())
    st = (tmp_path / "drive.st").read_text()
    for code in (c, st):
        assert "its outputs applied 1 position-loop sample(s) after they are computed" in code
    assert "w_ref = pw1; tau_p = pt1;" in c
    assert "s->pend_w1 = pw1;" in c
    assert "t_WRef := t_PendW1; t_TauP := t_PendT1;" in st
    assert "s_PendW1 := t_PendW1;" in st


@pytest.mark.parametrize("value", ["5", "-1", "1.5", "true"])
def test_position_delay_refused_in_one_line(tmp_path, capsys, value):
    from prsa_ctrl.cli.tune import main

    f = _short_move(tmp_path, "bad.toml", [("position_rate", f"1\nposition_delay_samples = {value}")])
    assert main(["--scene", str(f), "--export", str(tmp_path / "d.toml")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "position_delay_samples" in err
    assert value in err.lower()
    assert "Traceback" not in err
    assert not (tmp_path / "d.toml").exists()


@pytest.mark.parametrize("line, match", [
    ('kv_max = "3"', r"cascade\.kv_max = '3'; expected a position gain > 0 with its unit"),
    ('kv_max = "3 m/s"', r"cascade\.kv_max = '3 m/s'; expected"),
    ('kv_max = "-2 1/s"', r"cascade\.kv_max = '-2 1/s'; expected"),
    ('kv_max = "nan (m/min)/mm"', r"cascade\.kv_max = 'nan \(m/min\)/mm'; expected"),
    ("kv_max = 3.0", r"cascade\.kv_max = 3\.0; expected a position gain ceiling > 0 with its unit"),
])
def test_kv_max_refused_in_one_line(tmp_path, capsys, line, match):
    from prsa_ctrl.cli.tune import main

    f = _short_move(tmp_path, "bad.toml", [], [line])
    with pytest.raises(SceneError, match=match) as exc:
        load_move_scene(f)
    assert "\n" not in str(exc.value)
    assert main(["--scene", str(f), "--export", str(tmp_path / "d.toml")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "kv_max" in err
    assert "Traceback" not in err
    assert not (tmp_path / "d.toml").exists()


def test_kv_max_units_and_the_python_api(plant, scene):
    from prsa_ctrl.options import parse_kv
    from prsa_ctrl.tuning.cascade import kv_ceiling

    assert parse_kv("3 (m/min)/mm") == pytest.approx(50.0, rel=1e-15)
    assert parse_kv("2.5 1/s") == 2.5
    assert parse_kv(" 1  (m/min) / mm ") == pytest.approx(1000 / 60)
    assert kv_ceiling(scene.cascade_spec()) == math.inf
    assert kv_ceiling(scene.cascade_spec(), 30.0) == 30.0
    assert kv_ceiling(dataclasses.replace(scene, kv_max_per_s=20.0).cascade_spec()) == 20.0
    assert kv_ceiling(scene.cascade_spec(), "2 (m/min)/mm") == pytest.approx(100 / 3)
    for bad in (0.0, -1.0, math.inf, math.nan, True, "2 mm"):
        with pytest.raises(ValueError, match="kv_max = "):
            kv_ceiling(scene.cascade_spec(), bad)
    # the ceiling bounds the sequential rule too (it picks crossover/10 = 39 1/s without it)
    sc = dataclasses.replace(scene, fidelity="rigid", position_rate=2)
    seq = sequential_design(plant, sc.cascade_spec(), kv_max="1.2 (m/min)/mm")
    assert seq.position.kv == pytest.approx(20.0)
    assert any("ceiling" in n for n in seq.notes)
    assert seq.position.rate == 2
    assert seq.ms <= sc.ms_max * (1 + 1e-5)


def test_report_names_the_rate_the_ceiling_and_the_filters(plant, designs):
    from prsa_ctrl.studies.scenereport import format_move_report

    sc, cm, seq, joint = designs
    f, labels = _two_filters()
    text = format_move_report(plant, dataclasses.replace(sc, position_rate=2, kv_max_per_s=50.0, filters=f,
                                                         filter_labels=labels), [seq, joint])
    ts_us = plant.sample_time_s * 1e6
    assert f"position loop every 2 speed-loop samples (Tp = {2 * ts_us:g} us over Ts = {ts_us:g} us)" in text
    assert "kv_max = 50 1/s (3 (m/min)/mm)" in text
    assert f"joint {joint.position.kv * 0.06:.4g} (m/min)/mm" in text
    assert "at 1200 Hz on the torque command" in text
    assert "at 900 Hz on the speed measurement" in text
    plain = format_move_report(plant, sc, [seq, joint])
    assert "speed-loop samples" not in plain
    assert "kv_max" not in plain
    assert "filters" not in plain


def test_move_scene_filter_beyond_nyquist_refused(tmp_path, capsys):
    from prsa_ctrl.cli.tune import main

    f = _short_move(tmp_path, "nyq.toml", [("position_rate", "2")])
    f.write_text(f.read_text() + '\n[[filters.lowpass]]\npath = "speed"\ncorner_hz = 2500.0\n')
    assert main(["--scene", str(f), "--export", str(tmp_path / "d.toml")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "corner_hz = 2500.0" in err
    assert "Traceback" not in err
    assert not (tmp_path / "d.toml").exists()


@pytest.mark.parametrize("rate", [1, 2])
def test_kept_responses_give_the_peaks_of_a_fresh_computation(plant, scene, rate):
    """``CascadeModel`` keeps the gain-free responses of its dense grids (``ms`` evaluates the same
    frequencies, 20000 by default, at every gain): the peaks at other gains after the first call are the same
    numbers, bit for bit, as a model that keeps nothing, and the kept arrays cannot be written."""
    sc = dataclasses.replace(scene, position_rate=rate)
    cm, bare = CascadeModel(plant, sc.cascade_spec()), CascadeModel(plant, sc.cascade_spec())
    bare._CACHE_MIN = 10**9  # keeps nothing
    for g in ([0.08, 7.0, 60.0, 0.0, 1.0, 1.0], [0.05, 11.0, 25.0, 3.0, 1.0, 0.0], [0.12, 4.0, 90.0, 0.0, 0.5, 1.0]):
        assert cm.ms(g, n_dense=2000) == bare.ms(g, n_dense=2000)  # a dense grid of 2000 (kept from 64)
    assert cm._resp_cache
    assert not bare._resp_cache
    kept = next(iter(cm._resp_cache.values()))
    with pytest.raises(ValueError, match="read-only"):
        next(v for v in kept.values() if isinstance(v, np.ndarray))[0] = 0
    assert len(cm._resp_cache) <= cm._CACHE_MAX


def _peaks_one_point_at_a_time(cm, g, n_dense=20000):
    """``CascadeModel.ms`` as it was written before its golden section searches ran in lockstep:
    each breaking point's search alone, one frequency per sensitivity call."""
    out, grids = {}, {}
    for name in BREAKING_POINTS:
        nyq = math.pi / (cm.ts if (name == "speed_open" or cm.rate == 1) else cm.tp)
        if nyq not in grids:
            w = np.unique(np.concatenate([np.geomspace(1e-2, nyq * 0.99999, n_dense), cm.omega[cm.omega < nyq]]))
            grids[nyq] = (w, cm.sensitivity(g, w, [k for k in BREAKING_POINTS if cm.rate == 1 or
                                                   (k == "speed_open") == (nyq == math.pi / cm.ts)]))
        w, sens = grids[nyq]
        s = sens[name]
        i = int(np.argmax(s))
        a_, b_ = w[max(i - 1, 0)], w[min(i + 1, w.size - 1)]

        def f(x):
            return float(cm.sensitivity(g, np.array([x]), (name,))[name][0])

        gr = (math.sqrt(5) - 1) / 2
        for _ in range(60):
            c_, d_ = b_ - gr * (b_ - a_), a_ + gr * (b_ - a_)
            if f(c_) > f(d_):
                b_ = d_
            else:
                a_ = c_
        wm = 0.5 * (a_ + b_)
        best = max((s[i], w[i]), (f(wm), wm))
        out[name], out[f"w_{name}"] = float(best[0]), float(best[1])
    return out


@pytest.mark.parametrize("rate", [1, 2])
def test_peaks_searched_in_lockstep_are_those_searched_one_at_a_time(plant, scene, rate):
    """``ms`` runs the four breaking points' golden section searches in lockstep (one
    sensitivity call per step): the peaks and their frequencies are the same numbers, bit for
    bit, as the searches run one point and one frequency at a time."""
    cm = CascadeModel(plant, dataclasses.replace(scene, position_rate=rate).cascade_spec())
    for g in ([0.08, 7.0, 60.0, 0.0, 1.0, 1.0], [0.05, 11.0, 25.0, 3.0, 1.0, 0.0]):
        assert cm.ms(g, n_dense=2000) == _peaks_one_point_at_a_time(cm, g, n_dense=2000)
