"""prsa_ctrl.identification.compliant: the unmeasured states of the compliant screw-driven model
along a log (the time-domain fit's reference) and their scales."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest

from prsa_ctrl.plant import load_plant
from prsa_ctrl.plant.equilibrium import operating_point
from prsa_ctrl.plant.model import plant_model
from prsa_ctrl.identification.compliant import COMPLIANT_STATES, compliant_reference, compliant_scales


@pytest.mark.parametrize("name", ["ballscrew-32x10", "rollerscrew-30x5"])
def test_reference_at_steady_speed_is_the_models_own_equilibrium(name):
    """At constant speed and load the reference equals the compliant model's operating point
    (solved from the model's equations, not from the reference's formula)."""
    p = load_plant(name)
    m = plant_model(p, "compliant")
    w, load = 30.0, 0.4 * p.values["screw.rated_load_n"]
    op = operating_point(p, w, load, "compliant")
    t = np.arange(50) * 1e-4
    ref = compliant_reference(p, m.state_names, t, np.full(50, w), np.full(50, load))
    assert set(ref) == set(COMPLIANT_STATES)
    for k in COMPLIANT_STATES:
        scale = compliant_scales(p, m.state_names, w)[k]
        assert scale > 0
        np.testing.assert_allclose(ref[k], op.x[m.index(k)], rtol=1e-6, atol=1e-9 * scale)
    # a constant acceleration adds the carriage's inertial force to the spring's
    acc = 2000.0
    ref2 = compliant_reference(p, m.state_names, t, w + acc * t, np.full(50, load))
    extra = p.values["axis.moving_mass_kg"] * p.lead_per_rad * acc
    np.testing.assert_allclose(ref2["delta_screw"][5:-5] / ref["delta_screw"][5:-5], (load + extra) / load, rtol=1e-9)


def test_other_models_get_no_reference():
    p = load_plant()  # the inverted roller screw: its compliant states are the thread contacts'
    names = plant_model(p, "compliant").state_names
    assert compliant_reference(p, names, np.arange(5.0), np.ones(5), np.zeros(5)) == {}
    assert compliant_scales(p, names, 10.0) == {}
    q = load_plant("ballscrew-32x10")
    assert compliant_reference(q, plant_model(q, "rigid").state_names, np.arange(5.0), np.ones(5), np.zeros(5)) == {}


@pytest.mark.slow
@pytest.mark.parametrize("which", ["rs", "fa"])
def test_seed_from_frf_puts_the_plants_mode_at_the_measured_one(which, tmp_path):
    """The independent generators' datasheet plants put the first axial mode 45 % (roller screw)
    and 24 % (feed axis) too high; seeded from their measured FRF the plant's own compliant model
    has it within 5 % of the generator's truth, and each seeded key names the FRF as its source."""
    from foreign import gen_feedaxis_load as fa
    from foreign import gen_rollerscrew as rs

    from prsa_ctrl.identification.compliant import seed_from_frf, seed_keys
    from prsa_ctrl.identification.data import load_frf
    from prsa_ctrl.identification.frfplant import first_mode_hz

    s = (rs if which == "rs" else fa).generate(tmp_path, seed=0)
    t = s["truth"]
    base = load_plant(str(s["base"]))
    op = dict(speed_rad_s=t["frf_speed_rad_s"], load_n=t["frf_load_n"])
    assert abs(first_mode_hz(base, **op) / t["first_mode_hz"] - 1) > 0.2  # the start is far off
    frf = load_frf(s["frf"], **op)
    how = t.get("command_logged", "applied")
    seeded, note = seed_from_frf(base, [frf], how)
    assert abs(first_mode_hz(seeded, **op) / t["first_mode_hz"] - 1) < 0.05, note
    changed = [k for k in seed_keys(base) if seeded.values[k] != base.values[k]]
    assert "axis.nut_stiffness_n_per_um" in changed
    for k in changed:
        assert seeded.sources[k].startswith("two-mass fit of the measured response, ")
    assert "starts from the two-mass fit" in note


ROOT = Path(__file__).resolve().parents[2]
FOREIGN = next((d for d in (Path(os.environ.get("PRSA_FOREIGN_AXIS", "/nonexistent")),
                            ROOT.parent / "shared" / "data" / "foreign-axis",
                            ROOT.parent.parent / "shared" / "data" / "foreign-axis") if (d / "staircase.csv").exists()),
               None)


@pytest.mark.slow
@pytest.mark.skipif(FOREIGN is None, reason="foreign-axis data absent ($PRSA_FOREIGN_AXIS or ../shared/data/foreign-axis)")
def test_compliant_fit_of_the_foreign_feed_axis_logs_meets_the_acceptance_or_says_why(tmp_path, capsys):
    """Issue 32's acceptance on the foreign feed axis's three logs, two-mass time-domain fit as its
    README says (command logged as computed: one sample; the response beside the logs seeds the
    axial mode): exit 0 with a plant whose reflected inertia is within 3 % with the truth
    (4.1563e-3 kg m^2) inside its interval, the shift exact and the first axial mode within 5 %;
    or exit 3 with a one-line diagnosis and no plant file (a stall names the step still asked for)."""
    from prsa_ctrl.cli.fit import main
    from prsa_ctrl.identification import axial_mode

    logs = [str(FOREIGN / f) for f in ("multisine.csv", "loadsteps.csv", "staircase.csv")]
    out, rep = tmp_path / "fa.toml", tmp_path / "fa.json"
    rc = main([*logs, "--plant", str(FOREIGN / "feed-axis.toml"), "--fidelity", "compliant", "--command-logged",
               "computed", "--frf", str(FOREIGN / "bode.csv"), "--delay-samples", "1", "--out", str(out),
               "--json", str(rep)])
    err = capsys.readouterr().err
    a = 0.01 / (2 * math.pi)
    j_rot = 2.3e-3 + 9.6973e-4
    j_true = j_rot + 350 * a * a
    f_true = math.sqrt(123.7e6 / 350) / (2 * math.pi) * math.sqrt(j_true / j_rot)  # README's two-mass values
    if rc == 0:
        r = json.loads(rep.read_text())
        j = r["reflected_inertia_kg_m2"]
        assert abs(j["value"] / j_true - 1) < 0.03, j
        assert j["ci95"][0] <= j_true <= j["ci95"][1], j
        assert r["solver"]["command_delay"]["shift_samples"] == 1
        fitted = load_plant(str(out))
        assert fitted.command_delay_samples == 0
        # the README's mode is the FRF's, at 30 rad/s and 0 N (the mode moves with the nut force)
        assert abs(axial_mode(fitted, speed_rad_s=30.0, load_n=0.0)["resonance_hz"] / f_true - 1) < 0.05
    else:
        assert rc == 3, (rc, err[-2000:])
        assert not out.exists(), (rc, err[-2000:])
        last = [ln for ln in err.splitlines() if ln.startswith("prsa-fit:")][-1]
        assert len(last) > 20
        if "did not converge" in err:
            assert "standard errors" in err  # a stall says how far from a first-order point it stopped


def test_a_compliant_fit_with_process_noise_converges_on_its_default_segments():
    """COMPLIANT_SEGMENT_S: a two-mass log whose axial force carries white noise the log does not
    record (30 N per sample on the carriage: process noise, which an output-error model does not
    have) -- on the default 0.05 s segments the compliant fit converges at a first-order point with
    every true value inside its 95 % interval. (On 0.1 s segments it stalled when measured, the
    collocation defects standing in for the noise; that is the optimiser's path on one processor,
    so it is not asserted.)"""
    from prsa_ctrl.drive.pid import PID
    from prsa_ctrl.identification.compliant import COMPLIANT_SEGMENT_S
    from prsa_ctrl.identification.data import record_from_arrays
    from prsa_ctrl.identification.timedomain import fit_plant
    from prsa_ctrl.sim.engine import run

    p = load_plant("ballscrew-32x10")
    truth = p.with_params({"axis.motor_inertia_kg_m2": 1.1 * p.values["axis.motor_inertia_kg_m2"],
                           "drive.current_loop_bandwidth_hz": 1200.0}, name=p.name)
    rng = np.random.default_rng(0)
    dur = 0.4
    t = np.arange(int(round(dur / p.sample_time_s))) * p.sample_time_s
    force = 1000.0 + 30.0 * rng.standard_normal(t.size)
    r = run(truth, setpoint=[(0.0, 30.0), (0.1, 45.0), (0.2, 25.0), (0.3, 40.0)], load=list(zip(t.tolist(), force.tolist())),
            duration=dur, controller=PID(0.5, 50.0), fidelity="compliant", discrete=True)
    theta = r.states[r.state_labels.index("theta_nut")]
    q = 2 * math.pi / p.encoder_counts
    angle = np.floor((theta + 2e-6 * rng.standard_normal(theta.shape)) / q) * q
    rec = record_from_arrays("noisy-force", r.time, r.output("torque_command"), nut_angle_rad=angle,
                             axial_load_n=np.full(theta.shape, 1000.0))  # the log holds the force without its noise
    keys = ("axis.motor_inertia_kg_m2", "friction.efficiency", "drive.current_loop_bandwidth_hz",
            "friction.no_load_torque_n_m")
    res = fit_plant([rec], p, keys=keys, fidelity="compliant", delay_samples=0, validation=False)
    assert res.solver["segment_s"] == COMPLIANT_SEGMENT_S
    assert res.solver["status"] == "converged"
    for k in keys:
        lo, hi = res.parameters[k]["ci95"]
        assert lo <= truth.values[k] <= hi, (k, res.parameters[k], truth.values[k])


def _judge_response(name, tmp_path):
    """(base plant, FrfRecord, truth's first mode in Hz, operating point) of the judge's two-mass
    case ``name`` (tests/identification/foreign/gen_judge.py: its own equations of motion, not the
    toolkit's model): its measured response with 2 % noise, read as prsa-fit reads it."""
    from foreign import gen_judge as gj

    from prsa_ctrl.identification.data import load_frf

    s = gj.generate(tmp_path, name, seed=0, experiments=())
    t = s["truth"]
    op = dict(speed_rad_s=t["frf_speed_rad_s"], load_n=t["frf_load_n"])
    return load_plant(str(s["base"])), load_frf(s["frf"], **op), t["first_mode_hz"], op, t["command_logged"]


def _inverted_response():
    """The same for an inverted roller screw: two inertias on a spring written in
    tests/independent_actuator.py (not the plant's model), its mode 25 % above the base's."""
    import warnings

    from independent_actuator import modal_damper, two_mass_eom_response

    from prsa_ctrl.identification.data import frf_from_arrays

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        base = load_plant("paper-iprsm").with_params({"screw.mass_kg": 30.0, "contact.stiffness_n_per_mm_e": 3e4})
    op = dict(speed_rad_s=30.0, load_n=800.0)
    from prsa_ctrl.identification.frfplant import first_mode_hz

    f_base = first_mode_hz(base, **op)
    j0 = base.reflected_inertia_kg_m2
    jm, jl = 0.7 * j0, 0.4 * j0
    f_r = 1.25 * f_base
    k = (2 * math.pi * f_r) ** 2 / (1 / jm + 1 / jl)
    f = np.geomspace(3.0, 0.4 / base.sample_time_s, 220)
    g = two_mass_eom_response(f, jm, jl, k, modal_damper(k, jm, jl, 0.04), fc_hz=1100.0)
    rng = np.random.default_rng(3)
    g = g * np.exp(0.01 * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)))
    return base, frf_from_arrays("two-mass", f, g, sample_time_s=0.0, **op), f_r, op, "applied"


@pytest.mark.parametrize("case", ["ball-2mass-d1-computed-si", "roller-2mass-d1-applied-si", "inverted-roller-screw"])
def test_the_seed_puts_the_plants_mode_at_an_independent_two_mass_response_for_every_screw_mechanism(case, tmp_path):
    """seed_from_frf on a response the toolkit's model did not make: the seeded plant's own axial
    mode (identification.axial_mode at the response's point) is within 5 % of the truth, with the
    stiffness key(s) written from the fit (their source says so); with the stiffness left at the
    base's it is not. The judge's roller screw: its shaft and bearings in series (431 and 900
    N/um) are softer than its true 300 N/um, so no nut stiffness places the mode; the nut and the
    bearings are scaled together (the seed wrote the moving mass and damping alone before)."""
    from prsa_ctrl.identification import axial_mode
    from prsa_ctrl.identification.compliant import seed_from_frf, seed_keys

    base, frf, f_true, op, how = (_inverted_response() if case == "inverted-roller-screw"
                                  else _judge_response(case, tmp_path))

    def mode(p):
        return axial_mode(p, **op)["resonance_hz"]

    seeded, note = seed_from_frf(base, [frf], how)
    assert abs(mode(seeded) / f_true - 1) < 0.05, note
    stiff = [k for k in ("axis.nut_stiffness_n_per_um", "axis.bearing_stiffness_n_per_um", "contact.stiffness_n_per_mm_e")
             if k in seed_keys(base) and seeded.values[k] != base.values[k]]
    assert stiff, note
    for k in stiff:
        assert seeded.sources[k].startswith("two-mass fit of"), seeded.sources[k]
    if case.startswith("roller"):
        assert stiff == ["axis.nut_stiffness_n_per_um", "axis.bearing_stiffness_n_per_um"]
    # a broken seed: the stiffness left at the base's (each key alone, then all) misses the mode
    for keys in [*([k] for k in stiff), stiff]:
        broken = seeded.with_params({k: base.values[k] for k in keys}, name=base.name)
        assert abs(mode(broken) / f_true - 1) > 0.05, keys


@pytest.fixture(scope="module")
def judge_logs(tmp_path_factory):
    """``get(name)``: the judge's case ``name`` generated at seed 0 (gen_judge.generate: on a
    two-mass case its three logs, on a rigid one the multisine and the staircase), once per module
    and case: the two tests of the logs' own response read the same logs (each generated them;
    the generator runs each log from its own seed, so a log is the same whichever others are made)."""
    from foreign import gen_judge as gj

    made: dict = {}

    def get(name):
        if name not in made:
            exps = gj.EXPERIMENTS if gj.CASES[name].two_mass else ("multisine", "staircase")
            made[name] = gj.generate(tmp_path_factory.mktemp(name), name, seed=0, experiments=exps)
        return made[name]

    return get


@pytest.mark.parametrize("name", ["ball-2mass-d1-computed-si", "roller-2mass-d1-applied-si", "roller-rigid-d1-applied-si"])
def test_the_logs_own_response_seeds_the_compliant_fit_where_the_loop_is_described(name, judge_logs):
    """Without a measured response, the logs' own (joint input-output through the described speed
    loop: closedloop.frf_from_logs) starts the compliant fit where it shows a mode: on the judge's
    two-mass logs the start's mode is within 5 % of the truth's (the roller screw's multisine reaches 150 Hz, its mode 161 Hz: the anti-resonance in
    the band places it). On a rigid axis, and without the loop, the keys stay the base's and the
    note says why; without the loop and with no constant-reference log to identify it from (no
    load-step log here) the fit is refused (h15-direct: the start stayed the base's before)."""
    from prsa_ctrl.errors import FitError

    from prsa_ctrl.identification import axial_mode
    from prsa_ctrl.identification.closedloop import SpeedLoop
    from prsa_ctrl.identification.compliant import compliant_start
    from prsa_ctrl.identification.data import load_record

    s = judge_logs(name)
    t = s["truth"]
    base = load_plant(str(s["base"]))
    recs = [load_record(s["logs"][e]) for e in ("multisine", "staircase")]
    sl = t["speed_loop"]
    loop = SpeedLoop(sl["kp"], sl["ki"], t["sensor.sample_time_s"], sl["tau_filter_s"], t["command_logged"])
    start, keys, note = compliant_start(base, recs, [], None, t["command_logged"], loop)
    assert keys is None  # the default keys (the mode's keep the start's values)
    if t["two_mass"]:
        assert "axis.nut_stiffness_n_per_um" in note.split("; ")[-1], note
        assert "keep the response's values" in note
        mode = axial_mode(start, speed_rad_s=30.0, load_n=t["frf_load_n"])["resonance_hz"]
        assert abs(mode / t["first_mode_hz"] - 1) < 0.05, note
        assert abs(axial_mode(base, speed_rad_s=30.0, load_n=t["frf_load_n"])["resonance_hz"] / t["first_mode_hz"] - 1) > 0.1
        assert start.sources["axis.nut_stiffness_n_per_um"].startswith("two-mass fit of")
        # the source names the response the fit read: the logs' own, not a measured one (h16-logsmode)
        assert start.sources["axis.nut_stiffness_n_per_um"].startswith("two-mass fit of the logs' own response, ")
    else:
        assert start is base
        assert "shows none" in note
    with pytest.raises(FitError) as info:
        compliant_start(base, recs, [], None, t["command_logged"], None)
    assert "no loop described: --speed-loop" in str(info.value)
    assert "no log identifies the speed loop (" in str(info.value)
    same, keys0, why = compliant_start(base, recs, [], ("axis.motor_inertia_kg_m2",), t["command_logged"], None)
    assert same is base  # (--fit keys: no identification, the base's mode kept, no note)
    assert why is None


@pytest.mark.parametrize("name", ["ball-2mass-d1-computed-si", "roller-2mass-d1-applied-si"])
def test_the_logs_alone_place_the_mode_through_the_speed_loop_their_load_step_log_gives(name, judge_logs):
    """No measured response and no loop described: the judge's constant-speed load-step log gives
    the speed loop (closedloop.speed_loop_from_logs), the joint input-output response of the other
    logs through it starts the compliant fit, and the start's mode is within 5 % of the truth's
    (measured from the files, seeds 0 and 1: +0.9 % ball, +1.1 / +1.4 % roller; the datasheet's
    +15.9 % and -14.6 %). unplaced_mode lets it through; the note names the log and the loop."""
    from prsa_ctrl.identification import axial_mode
    from prsa_ctrl.identification.compliant import compliant_start, unplaced_mode
    from prsa_ctrl.identification.data import load_record

    s = judge_logs(name)
    t = s["truth"]
    base = load_plant(str(s["base"]))
    recs = [load_record(s["logs"][e]) for e in ("multisine", "loadsteps", "staircase")]
    assert unplaced_mode(base, recs, [], None) is None
    start, keys, note = compliant_start(base, recs, [], None, t["command_logged"], None)
    assert keys is None
    assert note.startswith("speed loop identified from the constant-reference log ")
    assert "loadsteps.csv: kp " in note
    mode = axial_mode(start, speed_rad_s=30.0, load_n=t["frf_load_n"])["resonance_hz"]
    assert abs(mode / t["first_mode_hz"] - 1) < 0.05, note
    assert abs(axial_mode(base, speed_rad_s=30.0, load_n=t["frf_load_n"])["resonance_hz"] / t["first_mode_hz"] - 1) > 0.1
    assert start.sources["axis.nut_stiffness_n_per_um"].startswith("two-mass fit of")


def test_a_loop_identified_from_the_logs_whose_response_places_no_mode_refuses_the_fit(tmp_path):
    """The third generator's ball screw (tests/identification/foreign/gen_third.py): its load-step
    log gives the speed loop, but the logs' response through it shows the axial mode and the
    coupling's (116.7 and 978.5 Hz): no two-mass start, so the compliant fit is refused with
    unplaced_mode's text, the identified loop and why (it started from the datasheet's mode
    before, 9.7 % off)."""
    from foreign import gen_third as g3

    from prsa_ctrl.errors import FitError
    from prsa_ctrl.identification.compliant import compliant_start
    from prsa_ctrl.identification.data import load_record

    s = g3.generate(tmp_path, "ball-40x16", seed=0, frf=False)
    base = load_plant(str(s["base"]))
    recs = [load_record(p) for p in s["logs"].values()]
    with pytest.raises(FitError) as info:
        compliant_start(base, recs, [], None, s["case"].command_logged, None)
    text = str(info.value)
    assert text.startswith("the compliant fit needs its axial mode placed from a frequency response")
    assert "the speed loop identified from the constant-reference log " in text
    assert "2 resonances" in text
    # it does not say the loop was missing, nor offer the logs a flag of --frf's alone
    assert "no loop described" not in text
    assert "fits a measured response, --frf FRF.csv, in that band" in text
    assert not text.rstrip(")").rstrip().endswith(("--frf-band 4.35,337", "337"))


@pytest.mark.parametrize("name", ["ballscrew-32x10", "rollerscrew-30x5", "paper-iprsm"])
def test_the_axial_mode_keys_are_one_table_that_moves_each_mechanisms_mode(name):
    """compliant.seed_keys and the FRF seed's spring read one table (plant.schema.AXIAL_MODE_KEYS),
    and the table is the physics: a stiffer spring raises the plant's first axial mode, a heavier
    inertia on either side lowers it (the compliant model linearised, not the table's word)."""
    from prsa_ctrl.identification.compliant import seed_keys
    from prsa_ctrl.identification.frfplant import first_mode_hz
    from prsa_ctrl.plant.schema import axial_mode_keys, keys_of

    p = load_plant(name)
    assert seed_keys(p) == axial_mode_keys(p.mechanism)
    assert set(seed_keys(p)) <= set(keys_of(p.mechanism))
    f0 = first_mode_hz(p)
    for k in axial_mode_keys(p.mechanism, "springs"):
        assert first_mode_hz(p, (k,), (4.0 * p.values[k],)) > 1.01 * f0, k
    near, far = axial_mode_keys(p.mechanism, "inertias")
    assert first_mode_hz(p, (far,), (4.0 * p.values[far],)) < 0.99 * f0
    # (the inverted screw's nut is far heavier than its translating screw: it barely moves the mode)
    assert first_mode_hz(p, (near,), (4.0 * p.values[near],)) < f0


def test_a_linear_axis_has_no_axial_mode_keys():
    from prsa_ctrl.plant.schema import MECHANISMS, axial_mode_keys

    assert axial_mode_keys("linear-axis") == ()
    assert all(axial_mode_keys(m) for m in MECHANISMS if m != "linear-axis")


def test_a_compliant_fit_with_nothing_to_place_its_mode_is_refused_before_any_work(monkeypatch):
    """Default keys, logs, no measured response and no described speed loop: the mode keys would
    stay the datasheet's (a misplaced mode keeps a compliant fit iterating to its work bound), so
    fit_plant refuses at once, naming both flags; --fit keys, a response or a loop lift it."""
    import prsa_ctrl.identification.timedomain as td
    from prsa_ctrl.errors import FitError
    from prsa_ctrl.identification.compliant import unplaced_mode
    from prsa_ctrl.identification.data import record_from_arrays

    p = load_plant("ballscrew-32x10")
    t = np.arange(400) * p.sample_time_s
    rec = record_from_arrays("log", t, 0.1 * np.sin(200 * t), nut_angle_rad=30.0 * t, axial_load_n=np.full(t.size, 500.0))
    built = []
    monkeypatch.setattr(td, "_Problem", lambda *a, **k: built.append(1))  # (no fit may start)
    with pytest.raises(FitError) as info:
        td.fit_plant([rec], p, fidelity="compliant", delay_samples="find")
    text = str(info.value)
    assert "no loop described: --speed-loop" in text
    assert "--frf" in text
    assert "axis.nut_stiffness_n_per_um" in text
    assert "no log identifies the speed loop (log: no motor angle or fewer than 512 samples)" in text
    assert built == []
    assert unplaced_mode(p, [rec], [], ("axis.motor_inertia_kg_m2",)) is None  # --fit: the user's keys
    assert unplaced_mode(p, [rec], ["bode"], None) is None
    assert unplaced_mode(p, [rec], [], None, speed_loop=object()) is None
    assert unplaced_mode(p, [], [], None) is None  # (an FRF-only fit has no logs to refuse)


def test_a_base_plant_whose_mode_a_measurement_placed_is_not_refused():
    """The two-step workflow: prsa-fit --frf bode.csv --out p.toml writes the mode keys with 'fit: ...'
    sources, then prsa-fit logs.csv --plant p.toml --fidelity compliant starts from them (was:
    refused, saying the base plant's mode keys are its datasheet's)."""
    import dataclasses

    from prsa_ctrl.identification.compliant import seed_keys, unplaced_mode
    from prsa_ctrl.identification.data import record_from_arrays

    p = load_plant("ballscrew-32x10")
    t = np.arange(400) * p.sample_time_s
    rec = record_from_arrays("log", t, 0.1 * np.sin(200 * t), nut_angle_rad=30.0 * t, axial_load_n=np.full(t.size, 500.0))
    assert unplaced_mode(p, [rec], [], None) is not None  # (the datasheet's mode: refused)
    key = "axis.nut_stiffness_n_per_um"
    assert key in seed_keys(p)
    placed = dataclasses.replace(p, sources={**p.sources, key: "fit: bode.csv (two-mass model of the frequency response)"})
    assert unplaced_mode(placed, [rec], [], None) is None


def test_a_base_plant_whose_mode_a_measurement_placed_starts_the_fit_from_it():
    """The same two-step workflow through the fit's start: with no log giving the speed loop,
    compliant_start keeps the measured mode keys (it raised the refusal after h15-direct's loop
    identification, though unplaced_mode let the run through)."""
    import dataclasses

    from prsa_ctrl.errors import FitError
    from prsa_ctrl.identification.compliant import compliant_start
    from prsa_ctrl.identification.data import record_from_arrays

    p = load_plant("ballscrew-32x10")
    t = np.arange(400) * p.sample_time_s
    rec = record_from_arrays("log", t, 0.1 * np.sin(200 * t), nut_angle_rad=30.0 * t, axial_load_n=np.full(t.size, 500.0))
    with pytest.raises(FitError, match="needs its axial mode placed"):
        compliant_start(p, [rec], [], None, "applied")
    key = "axis.nut_stiffness_n_per_um"
    placed = dataclasses.replace(p, sources={**p.sources, key: "fit: bode.csv (two-mass model of the frequency response)"})
    start, keys, note = compliant_start(placed, [rec], [], None, "applied")
    assert start is placed
    assert "a measurement placed" in note
