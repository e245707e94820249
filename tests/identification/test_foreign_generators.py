"""The foreign log generators of ``tests/identification/foreign/`` and prsa-fit's acceptance on them.

Issue 32, part 6. The generators share no code with the toolkit and were written without reading
its fitting code; see ``foreign/__init__.py``.

(a) Fast tests of the generators themselves, against formulas written out here (not the
    simulator's own helpers): the steady torque balance of the load steps, the FRF's
    low-frequency asymptote, the axial mode and anti-resonance of the two-mass axis, the
    closed-loop FRF experiment against the analytic FRF, determinism in the seed.
(b) Acceptance (``@pytest.mark.slow``): ``prsa-fit`` (the console script, a subprocess) on the
    generated logs and FRFs, checked against the truth as issue 32 states it: the total
    reflected inertia within 3 % with the truth inside the reported 95 % interval, the current
    loop within 25 %, the command delay exact, the first axial mode within 5 % where the data
    contain it; exit 0 with a plant file that loads, or exit 3 with a one-line diagnosis and no
    file; never exit 0 with an inertia the interval does not cover. The rule is the judge's
    oracle, ``foreign/judge_oracle.py`` (tested in ``test_judge_oracle.py``): a refusal counts only
    when its diagnosis is true of the generator (the named mode, the order per revolution, the
    units, the delay against the truth); a work bound is cost, accepted only where listed.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from foreign import _axis
from foreign import gen_ballscrew as bs
from foreign import gen_feedaxis_load as fa
from foreign import gen_judge as gj
from foreign import gen_rollerscrew as rs
from foreign import gen_third as g3
from foreign.judge_oracle import acceptance

# ---------------------------------------------------------------------------------------------
# (a) the generators


@pytest.fixture(scope="module")
def rs_set(tmp_path_factory):
    return rs.generate(tmp_path_factory.mktemp("rollerscrew"), seed=0)


@pytest.fixture(scope="module")
def bs_set(tmp_path_factory):
    return bs.generate(tmp_path_factory.mktemp("ballscrew"), seed=0)


@pytest.fixture(scope="module")
def fa_set(tmp_path_factory):
    return fa.generate(tmp_path_factory.mktemp("feedaxis"), seed=0)


def _read(path):
    """A generated CSV as {header: array}."""
    with open(path) as fh:
        names = fh.readline().strip().split(",")
    data = np.loadtxt(path, delimiter=",", skiprows=1)
    return {n: data[:, i] for i, n in enumerate(names)}


def _rs_si(path):
    """The roller-screw log in SI, converted from its units (ms, deg, rpm, % of rated, kN)."""
    d = _read(path)
    t = rs.truth()
    return {"time_s": d["t_ms"] / 1e3, "angle_rad": np.radians(d["pos_deg"]),
            "speed_rad_s": d["speed_rpm"] * math.pi / 30.0,
            "torque_n_m": d["torque_pct"] / 100.0 * t["rated_torque_n_m"], "load_n": d["load_kN"] * 1e3,
            **({"dither_n_m": d["dither_pct"] / 100.0 * t["rated_torque_n_m"]} if "dither_pct" in d else {})}


def _bs_si(path):
    """The ball-screw log (SI, the toolkit's default columns)."""
    d = _read(path)
    return {"time_s": d["time_s"], "angle_rad": d["nut_angle_rad"], "torque_n_m": d["torque_command_n_m"],
            "load_n": d["axial_load_n"], **({"dither_n_m": d["torque_dither_n_m"]} if "torque_dither_n_m" in d else {})}


def _fa_si(path):
    """The feed-axis log converted from load coordinates (mm, N) to motor coordinates."""
    d = _read(path)
    a = fa.truth()["screw.lead_mm"] / 1e3 / (2 * math.pi)
    return {"time_s": d["time_s"], "angle_rad": d["position_mm"] / 1e3 / a, "torque_n_m": d["force_command_n"] * a,
            "load_n": d["load_n"], **({"dither_n_m": d["dither_n"] * a} if "dither_n" in d else {})}


def _set(which, rs_set, bs_set, fa_set):
    """(generator, truth, {experiment: SI log}, delay of the logged command in samples)."""
    if which == "rollerscrew":
        return rs, rs_set["truth"], {k: _rs_si(v) for k, v in rs_set["logs"].items()}, 2
    if which == "ballscrew":
        return bs, bs_set["truth"]["computed"], {k: _bs_si(v) for k, v in bs_set["logs"]["computed"].items()}, 3
    return fa, fa_set["truth"], {k: _fa_si(v) for k, v in fa_set["logs"].items()}, 1


WHICH = ["rollerscrew", "ballscrew", "feedaxis"]


def _steady_torque(truth, w, force):
    """Torque that holds speed w > 0 (rad/s, far above the Stribeck speed) against force > 0 (N),
    written from the truth: Coulomb forward + viscous + the nut force over the efficiency."""
    a = truth["screw.lead_mm"] / 1e3 / (2 * math.pi)
    coulomb_fwd = truth["friction.no_load_torque_n_m"] + truth["friction.torque_offset_n_m"]
    return coulomb_fwd + truth["friction.viscous_n_m_s_per_rad"] * w + a * force / truth["friction.efficiency"]


def _plateau_means(log, edges, ts):
    """Mean logged torque and load over the last 40 % of each [t0, t1) plateau, and the torque's
    standard error from 10 batch means (the loop's noise is coloured)."""
    out = []
    for t0, t1 in edges:
        i0, i1 = int(round((t0 + 0.6 * (t1 - t0)) / ts)), int(round(t1 / ts))
        tq = log["torque_n_m"][i0:i1]
        batches = np.array_split(tq, 10)
        se = np.std([b.mean() for b in batches], ddof=1) / math.sqrt(10)
        out.append((tq.mean(), log["load_n"][i0:i1].mean(), se))
    return out


@pytest.mark.parametrize("which", WHICH)
def test_load_step_plateaus_hold_the_analytic_torque_balance(which, rs_set, bs_set, fa_set):
    # At constant speed each load plateau's mean command is Coulomb + viscous + a F / eta (the
    # nut loss on the whole force: here the load alone, the speed being constant).
    gen, truth, logs, _ = _set(which, rs_set, bs_set, fa_set)
    log = logs["loadsteps"]
    n_step = gen.N_SAMPLES // 4
    ts = truth["sensor.sample_time_s"]
    edges = [(i * n_step * ts, (i + 1) * n_step * ts) for i in range(4)]
    forces = {"rollerscrew": [0.0, 3000.0, 800.0, 3000.0], "ballscrew": [0.0, 1500.0, 300.0, 1500.0],
              "feedaxis": [0.0, 4000.0, 1000.0, 4000.0]}[which]
    w = {"feedaxis": 25.0}.get(which, 30.0)
    for (tq, load, se), f in zip(_plateau_means(log, edges, ts), forces):
        assert abs(load - f) < 3.0  # the load cell's mean (noise 5..10 N over >= 800 samples)
        expected = _steady_torque(truth, w, f) if f > 0 else (
            truth["friction.no_load_torque_n_m"] + truth["friction.torque_offset_n_m"]
            + truth["friction.viscous_n_m_s_per_rad"] * w)
        # 4 standard errors plus the quantised speed's bias bound (one count per sample through kp)
        tol = 4.0 * se + 2e-3
        assert abs(tq - expected) < tol, (which, f, tq, expected, tol)
    # a broken balance (no loss on the nut force) is far outside that tolerance
    a = truth["screw.lead_mm"] / 1e3 / (2 * math.pi)
    assert a * forces[1] * (1 / truth["friction.efficiency"] - 1) > 50 * 2e-3


@pytest.mark.parametrize("which", WHICH)
def test_frf_low_frequency_asymptote_is_one_over_j_s(which):
    gen = {"rollerscrew": rs, "ballscrew": bs, "feedaxis": fa}[which]
    truth = gen.truth()
    ax = gen.AXIS
    f = np.array([2.0, 5.0])
    w = 2 * math.pi * f
    # lossless, frictionless axis: |H| -> 1 / (J_total w), J_total = J_m + m a^2 from the truth
    ideal = _axis.Axis(**{**ax.__dict__, "efficiency": 1.0, "viscous_n_m_s_per_rad": 0.0})
    j_total = truth["nut.inertia_kg_m2"] + truth["axis.moving_mass_kg"] * (truth["screw.lead_mm"] / 1e3 / (2 * math.pi)) ** 2
    assert j_total == pytest.approx(truth["reflected_inertia_kg_m2"], rel=1e-12)
    h = _axis.frf(ideal, gen.DRIVE, gen.SENSORS, f, truth["frf_load_n"], 2)
    assert np.abs(h) * w * j_total == pytest.approx([1.0, 1.0], abs=2e-3)
    # phase: -90 deg of the integrator less the lags, to first order in w: the delay (2 samples),
    # half a sample of hold, half a sample of the backward difference, the current loop
    lag = w * (3.0 * truth["sensor.sample_time_s"] + 1.0 / (2 * math.pi * truth["drive.current_loop_bandwidth_hz"]))
    assert np.angle(h) == pytest.approx(-math.pi / 2 - lag, abs=2e-3)
    # the data's axis under load: the loss on the whole nut force makes it J_m + m a^2 / eta
    fx, hx, _ = gen.bode("applied") if which == "ballscrew" else gen.bode()
    j_lf = truth["nut.inertia_kg_m2"] + (truth["reflected_inertia_kg_m2"] - truth["nut.inertia_kg_m2"]) / truth["friction.efficiency"]
    b = truth["friction.viscous_n_m_s_per_rad"]
    assert abs(hx[0]) * math.hypot(j_lf * 2 * math.pi * fx[0], b) == pytest.approx(1.0, abs=3e-3)
    assert j_lf == pytest.approx(truth["frf_low_frequency_inertia_kg_m2"], rel=1e-12)


@pytest.mark.parametrize("gen", [rs, fa], ids=["rollerscrew", "feedaxis"])
def test_two_mass_mode_and_anti_resonance_equal_the_analytic_formulas(gen):
    truth = gen.truth()
    ax = gen.AXIS
    a = truth["screw.lead_mm"] / 1e3 / (2 * math.pi)
    k, m, jm, eta = truth["axial_stiffness_n_per_m"], truth["axis.moving_mass_kg"], truth["nut.inertia_kg_m2"], truth["friction.efficiency"]
    f_mode = math.sqrt(k * (a * a / (eta * jm) + 1.0 / m)) / (2 * math.pi)
    f_anti = math.sqrt(k / m) / (2 * math.pi)
    assert truth["first_mode_hz"] == pytest.approx(f_mode, rel=1e-12)
    assert truth["anti_resonance_hz"] == pytest.approx(f_anti, rel=1e-12)
    assert truth["first_mode_lossless_hz"] == pytest.approx(math.sqrt(k * (a * a / jm + 1.0 / m)) / (2 * math.pi), rel=1e-12)
    # the response's peak and notch, nearly undamped, sit on them (the current loop and the
    # sampling shift a peak of damping 1e-4 by far less than 0.2 %)
    light = _axis.Axis(**{**ax.__dict__, "damping_n_s_per_m": ax.damping_n_s_per_m * 2.5e-3})
    f = np.linspace(80.0, 220.0, 28001)
    mag = np.abs(_axis.frf(light, gen.DRIVE, gen.SENSORS, f, truth["frf_load_n"], 2))
    peak = f[np.argmax(mag)]
    notch = f[np.argmin(mag)]
    assert peak == pytest.approx(f_mode, rel=2e-3)
    assert notch == pytest.approx(f_anti, rel=2e-3)
    # and the mode lies inside the data's band (the FRF file, the time-domain multisine's reach)
    assert 5.0 < f_anti < f_mode < 1800.0


def _closed_loop_frf(log, ts, period_s, n_periods):
    """FRF torque command -> backward-difference speed from a periodic dither, last n periods:
    the DFT of both at the dither's lines (the dither the independent signal: Y D* / U D*)."""
    n_per = int(round(period_s / ts))
    ang = log["angle_rad"]
    y = np.diff(ang, prepend=ang[0]) / ts
    sl = slice(ang.size - n_periods * n_per, ang.size)
    u, y, d = log["torque_n_m"][sl], y[sl], log["dither_n_m"][sl]
    U, Y, D = (np.fft.rfft(v) for v in (u, y, d))
    freqs = np.fft.rfftfreq(u.size, ts)
    lines = np.abs(D) > 0.05 * np.abs(D).max()
    return freqs[lines], (Y[lines] * np.conj(D[lines])) / (U[lines] * np.conj(D[lines]))


@pytest.mark.parametrize("which", WHICH)
def test_closed_loop_frf_experiment_agrees_with_the_analytic_frf(which, rs_set, bs_set, fa_set):
    # The time-domain simulator (RK4, quantised encoder, nonlinear friction, the loop) measured as
    # a user would measure it agrees with the exact linear part written to the FRF file.
    gen, _, logs, delay = _set(which, rs_set, bs_set, fa_set)
    log = logs["frf_experiment"]
    ts = gen.TS
    # the dither's period is 0.2 s; the first period (the transient from its start) is left out
    f, g = _closed_loop_frf(log, ts, 0.2, int(round(gen.N_SAMPLES * ts / 0.2)) - 1)
    # lines between the speed loop's bandwidth region and where the encoder's quantisation
    # swamps the response (|H| 0.1 rad/s per N m at 0.3..0.4 N m spread over 60 lines)
    keep = (f >= 10.0) & (f <= (1200.0 if which == "ballscrew" else 800.0))
    f, g = f[keep], g[keep]
    h = _axis.frf(gen.AXIS, gen.DRIVE, gen.SENSORS, f, gen.FRF_LOAD_N, delay)
    rel = np.abs(g / h - 1.0)
    assert f.size >= 30
    assert np.median(rel) < 0.03, np.median(rel)
    assert np.percentile(rel, 90) < 0.10, np.percentile(rel, 90)
    # one sample more or less of delay is clearly worse above 300 Hz (the FRF pins the delay)
    hi = f > 300.0
    for wrong in (delay - 1, delay + 1):
        hw = _axis.frf(gen.AXIS, gen.DRIVE, gen.SENSORS, f, gen.FRF_LOAD_N, wrong)
        assert np.median(np.abs(g[hi] / hw[hi] - 1.0)) > 5 * np.median(rel[hi])


def test_generators_are_deterministic_in_the_seed(tmp_path, rs_set, bs_set, fa_set):
    again_rs = rs.generate(tmp_path / "rs", seed=0)
    for name, path in rs_set["logs"].items():
        assert Path(path).read_bytes() == again_rs["logs"][name].read_bytes(), name
    assert Path(rs_set["frf"]).read_bytes() == again_rs["frf"].read_bytes()
    other = rs.generate(tmp_path / "rs1", seed=1)
    assert other["logs"]["multisine"].read_bytes() != again_rs["logs"]["multisine"].read_bytes()
    assert other["frf"].read_bytes() != again_rs["frf"].read_bytes()
    again_fa = fa.generate(tmp_path / "fa", seed=0)
    for name, path in fa_set["logs"].items():
        assert Path(path).read_bytes() == again_fa["logs"][name].read_bytes(), name
    assert Path(fa_set["frf"]).read_bytes() == again_fa["frf"].read_bytes()
    again_bs = bs.generate(tmp_path / "bs", seed=0)
    for how in ("applied", "computed"):
        for name, path in bs_set["logs"][how].items():
            assert Path(path).read_bytes() == again_bs["logs"][how][name].read_bytes(), (how, name)
        assert Path(bs_set["frf"][how]).read_bytes() == again_bs["frf"][how].read_bytes()


def test_applied_and_computed_logs_are_one_sample_apart(bs_set):
    for name in ("multisine", "loadsteps", "staircase"):
        ap = _bs_si(bs_set["logs"]["applied"][name])["torque_n_m"]
        co = _bs_si(bs_set["logs"]["computed"][name])["torque_n_m"]
        assert np.array_equal(ap[1:], co[:-1]), name
        assert not np.array_equal(ap, co)
    t = bs_set["truth"]
    assert t["applied"]["delay_logged_to_action_samples"] == 2
    assert t["computed"]["delay_logged_to_action_samples"] == 3
    assert t["applied"]["drive.command_delay_samples"] == t["computed"]["drive.command_delay_samples"] == 2


def test_roller_screw_log_units_and_description(rs_set):
    # the log is in ms, deg, rpm, % of rated torque and kN, and its description says so
    d = _read(rs_set["logs"]["loadsteps"])
    assert np.diff(d["t_ms"]) == pytest.approx(0.25)
    si = _rs_si(rs_set["logs"]["loadsteps"])
    w = np.diff(si["angle_rad"]) / np.diff(si["time_s"])
    assert np.median(w) == pytest.approx(30.0, rel=0.01)
    assert np.median(si["speed_rad_s"]) == pytest.approx(30.0, rel=0.01)
    assert np.max(np.abs(d["torque_pct"])) > 100.0  # above the rated torque in the 3000 N steps
    text = rs_set["log_format"].read_text()
    for token in ('unit = "ms"', 'unit = "deg"', 'unit = "rpm"', 'unit = "%"', 'unit = "kN"', 'logged = "as-computed"'):
        assert token in text
    # the quantised angle: every value is a whole number of encoder counts
    counts = si["angle_rad"] / (2 * math.pi / rs.SENSORS.counts_per_rev)
    assert np.max(np.abs(counts - np.round(counts))) < 1e-3


@pytest.mark.parametrize("which", WHICH)
def test_base_plant_loads_and_is_nominal_not_the_truth(which, rs_set, bs_set, fa_set):
    from prsa_ctrl.plant import load_plant

    s = {"rollerscrew": rs_set, "ballscrew": bs_set, "feedaxis": fa_set}[which]
    truth = {"rollerscrew": rs, "ballscrew": bs, "feedaxis": fa}[which].truth()
    plant = load_plant(str(s["base"]))
    assert plant is not None
    text = Path(s["base"]).read_text()
    # the datasheet values differ from the truth where a user cannot know it
    assert f"moving_mass_kg = {{ value = {truth['axis.moving_mass_kg']}" not in text
    assert f"efficiency = {{ value = {truth['friction.efficiency']}" not in text
    assert "command_delay_samples" not in text


@pytest.mark.parametrize("which", WHICH)
def test_staircase_starts_at_rest_and_breaks_away_through_the_standstill_friction(which, rs_set, bs_set, fa_set):
    # from rest the torque must exceed the breakaway level before the axis turns
    gen, truth, logs, _ = _set(which, rs_set, bs_set, fa_set)
    log = logs["staircase"]
    moved = np.argmax(np.abs(log["angle_rad"]) > 20 * 2 * math.pi / gen.SENSORS.counts_per_rev)
    assert moved > 0
    assert abs(log["angle_rad"][0]) < 1e-5
    assert np.max(log["torque_n_m"][: moved + 3]) > truth["friction.no_load_breakaway_torque_n_m"]


# ---------------------------------------------------------------------------------------------
# (b) acceptance of prsa-fit on the foreign sets (issue 32)

PRSA_FIT = shutil.which("prsa-fit", path=os.path.dirname(sys.executable) + os.pathsep + os.environ.get("PATH", ""))


def _run(args, cwd, timeout=3600):
    """prsa-fit on ``args``; the CompletedProcess carries ``cpu_s``, the child's CPU time (user+sys, s)."""
    import resource

    env = dict(os.environ)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    proc = subprocess.run([PRSA_FIT, *map(str, args)], cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    proc.cpu_s = round((after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), 1)
    return proc


# Refusals at a bound of the fit's work (a diagnosis of cost, not of physics: foreign/judge_oracle.py),
# accepted only for the cases listed here, each with its measured run (case id as in the table).
# Measured by h14-oracle on main a8f75f1, seed 0, one run at a time on the loaded 2-core machine
# (load 5..18), CPU user+sys of prsa-fit (the pytest run's in brackets, data generation included).
# The five logs-compliant runs without --frf that were listed here (the work bound, 136-179 s CPU each) now
# end exit 3 at once, about 1 s, "the compliant fit needs its axial mode placed from a frequency response"
# (compliant.unplaced_mode), which the oracle reads as a claim that the data hold a mode: entries removed.
# After h15-direct the speed loop identified from the load-step log places the mode instead, and those runs fit
# from it and end exit 3 naming the axial mode (judge roller d1 62 s, ball d1 154 s, rollerscrew 107 s of the
# pytest run's CPU; feedaxis refused, 5 s): a physics claim the oracle checks, still no cost allowance.
# The judge's ball-2mass-d1-computed-si logs-compliant-frf, listed on a8f75f1 (exit 3, 159.1 s CPU: 'delay: could
# not decide (1: 1.27e+06, 2: failed)', shift 2 stopped at the work bound), passes the rule after h14-compfit
# (exit 0, 128.1 s CPU, J 2.92017e-3 in 2.91273..2.92762e-3, truth 2.92018e-3; mode 131.8 Hz): removed.
COST_BOUND_ALLOWED: dict[str, str] = {
    # h16-logsmode (the mode bracket, identification/modebracket.py): on main this run ended exit 3 'axial mode: 38 %
    # ...', a claim the trace found false for the judge's cases (their modes within 1-2 %). With the bracket the written
    # plant explains every log (J 1.07891e-3, CI 1.07282..1.08501e-3, truth 1.08035e-3; shift 2, the delay exact), and
    # the cross-validation fit without multisine.csv reached 'maximum iterations' after 53 iterations (constraint
    # residual 6.5e-5) from all three starts: exit 3 'fit failure, not missing physics', no file, 104.2 s CPU.
    "judge:roller-2mass-d2-computed-nonsi--logs-compliant-frf": "a cross-validation fit at its iteration bound, 104.2 s",
    # h16-logsmode: on main this run was refused in about 1 s for 'two resonances ... up to the geometric mean of
    # 110.8 and 110.8 Hz' (one resonance counted in the multisine's and the staircase's response: a false claim).
    # Counted once (frfcheck.SAME_RESONANCE), the logs' response places the mode and the compliant fit runs: shift 1
    # stopped by its candidate's work bound, shift 0 fitted (current loop 361.7 Hz against 800, the delay one sample
    # short: a wrong plant), refused 'axial mode: 86 % ... within 15 % of 107.4 Hz' (multisine 32.6 x its floor, 70 %;
    # loadsteps 6.7 x, 86 %) with 'the compliant fit stopped at its work bound (417 of 417 Gauss-Newton iterations)'
    # beside it: exit 3, no file, 136.1 s CPU (the mode bracket does not judge it: a shift was stopped).
    "feedaxis-logs-compliant": "the compliant fit at its work bound (417 iterations) beside a true axial-mode claim, 136 s",
}


def _record(name, args, row, fails, proc=None, js=None):
    """Append the run's row to $PRSA_FOREIGN_TABLE (a JSON-lines file) when set: the report's table,
    with the run's CPU time, the tail of its stderr and its JSON report's status and delay."""
    target = os.environ.get("PRSA_FOREIGN_TABLE")
    if target:
        if proc is not None:
            row = {**row, "cpu_s": getattr(proc, "cpu_s", None), "stderr_tail": proc.stderr[-3000:]}
            if js is not None and Path(js).exists():
                rep = json.loads(Path(js).read_text())
                row.update(json_status=rep.get("status"), json_inertia=rep.get("reflected_inertia_kg_m2"),
                           json_command_delay=(rep.get("solver") or {}).get("command_delay"))
        with open(target, "a") as fh:
            fh.write(json.dumps({"case": name, "args": [str(a) for a in args], **row, "fails": fails}, default=str) + "\n")


CASES = {
    # name: (set, how the command is built, mode expected in the data)
    "rollerscrew-logs": ("rs", "logs", False),
    "rollerscrew-logs-compliant": ("rs", "logs-compliant", True),
    "rollerscrew-frf-rigid": ("rs", "frf", False),
    "rollerscrew-frf-compliant": ("rs", "frf-compliant", True),
    "ballscrew-logs-applied": ("bs-applied", "logs", False),
    "ballscrew-logs-computed": ("bs-computed", "logs", False),
    "ballscrew-frf-applied": ("bs-applied", "frf", False),
    "ballscrew-frf-computed": ("bs-computed", "frf", False),
    "feedaxis-logs": ("fa", "logs", False),
    "feedaxis-logs-compliant": ("fa", "logs-compliant", True),
    "feedaxis-frf-rigid": ("fa", "frf", False),
    "feedaxis-frf-compliant": ("fa", "frf-compliant", True),
}


def _command(case, tmp_path):
    """The prsa-fit arguments of a case, on data of seed $PRSA_FOREIGN_SEED (default 0: the noise
    differs per seed, the truth not)."""
    which, kind, _ = CASES[case]
    seed = int(os.environ.get("PRSA_FOREIGN_SEED", "0"))
    out, js = tmp_path / "fitted.toml", tmp_path / "report.json"
    if which in ("rs", "fa"):
        gen = rs if which == "rs" else fa
        s = gen.generate(tmp_path / "data", seed=seed)
        truth, how = s["truth"], s["truth"]["command_logged"]
        logs = [s["logs"][n] for n in ("multisine", "loadsteps", "staircase")]
        frf = s["frf"]
        described = ["--log-format", s["log_format"]]
    else:
        how = which.split("-")[1]
        s = bs.generate(tmp_path / "data", seed=seed)
        truth = s["truth"][how]
        logs = [s["logs"][how][n] for n in ("multisine", "loadsteps", "staircase")]
        frf = s["frf"][how]
        described = []
    if kind.startswith("logs"):
        # a described log says how the command is logged; plain SI logs take the flag
        flag = [] if described else ["--command-logged", how]
        args = [*logs, *described, *flag, "--plant", s["base"], "--out", out, "--json", js]
        if kind == "logs-compliant":  # the mode reported at the truth's point (it moves with the nut force)
            args += ["--fidelity", "compliant", "--frf-speed", truth["frf_speed_rad_s"], "--frf-load", truth["frf_load_n"]]
    else:
        args = ["--frf", frf, "--frf-speed", truth["frf_speed_rad_s"], "--frf-load", truth["frf_load_n"],
                "--command-logged", how, "--plant", s["base"], "--out", out, "--json", js]
        if kind == "frf-compliant":
            args += ["--fidelity", "compliant"]
    return args, out, js, truth


# Runs of CASES that violate the rule at seed 0 (measured; findings, not tolerances), as JUDGE_XFAIL.
# (rollerscrew-logs-compliant, h13-modefit: exit 3 at the compliant fit's work bound, 417 iterations over its
# 14 397 intervals, naming the held mode keys and --frf; 150 s CPU user+sys of the pytest run at load ~10,
# where it had been stopped unfinished after 13 min of CPU. On a8f75f1 both at the work bound (h14-oracle: 137.1 and 136.2 s CPU).
# h14-compfit: both logs-compliant kinds (no --frf, no loop described) now end exit 3 at once, "no loop
# described: --speed-loop KP,KI[,TAU_S] ... or --frf FRF.csv" (compliant.unplaced_mode), no file, 1.2-1.3 s
# CPU user+sys of prsa-fit each, seed 0. h15-direct: rollerscrew-logs-compliant fits from the mode placed by
# the loop identified from its load-step log and ends exit 3 "axial mode", 107 s; feedaxis refused, 5 s.)
FOREIGN_XFAIL: dict[str, str] = {}


def _foreign_params():
    seed0 = os.environ.get("PRSA_FOREIGN_SEED", "0") == "0"
    for case in sorted(CASES):
        reason = FOREIGN_XFAIL.get(case) if seed0 else None
        yield pytest.param(case, marks=[pytest.mark.xfail(strict=True, reason=reason)] if reason else [], id=case)


@pytest.mark.slow
@pytest.mark.skipif(PRSA_FIT is None, reason="the prsa-fit console script is not installed")
@pytest.mark.parametrize("case", list(_foreign_params()))
def test_prsa_fit_acceptance_on_foreign_sets(case, tmp_path):
    args, out, js, truth = _command(case, tmp_path)
    proc = _run(args, tmp_path)
    fails, row = acceptance(proc, out, js, truth, mode_expected=CASES[case][2], must_fit=CASES[case][1] == "frf-compliant",
                            cost_allowed=case in COST_BOUND_ALLOWED)
    _record(case, args, row, fails, proc, js)
    assert not fails, f"{case}: " + "; ".join(fails) + f"\nstderr: {proc.stderr.strip()[-600:]}"


@pytest.mark.slow
@pytest.mark.skipif(PRSA_FIT is None, reason="the prsa-fit console script is not installed")
def test_the_seed_1_ball_screw_logs_are_cross_validated_not_a_fit_failure(tmp_path, monkeypatch):
    # The ball-screw logs at seed 1 ended exit 3 "fit failure, not missing physics": the
    # cross-validation fit without loadsteps.csv converged, but its check of the plant as
    # written (drag and viscous kept) started from the data reference and stalled in a segment
    # starting in the stick band. The check now starts from the free fit's states.
    monkeypatch.setenv("PRSA_FOREIGN_SEED", "1")
    args, out, js, truth = _command("ballscrew-logs-applied", tmp_path)
    proc = _run(args, tmp_path)
    fails, row = acceptance(proc, out, js, truth, mode_expected=False)
    assert not fails, "; ".join(fails) + f"\nstderr: {proc.stderr.strip()[-600:]}"
    assert "fit failure" not in proc.stderr
    if proc.returncode == 0:  # every left-out log was refitted (none failed)
        cv = json.loads(Path(js).read_text())["solver"]["validation"]["cross_validation"]
        assert all("failed" not in e for e in cv.values())


def test_the_acceptance_oracle_refuses_what_the_issue_refuses(tmp_path, rs_set):
    # The checker of (b) bites: a crash reported as exit 3, a file left behind, an exit 0 whose
    # interval misses the truth, a wrong delay or current loop are each a failure; a refusal that
    # names the missing physics, with no file, is accepted.
    from types import SimpleNamespace

    truth = rs_set["truth"]
    out, js = tmp_path / "fitted.toml", tmp_path / "r.json"
    crash = SimpleNamespace(returncode=3, stderr="prsa-fit: numerical failure: prsa-fit --frf b.csv failed (KeyError); rerun with --verbose\n")
    assert acceptance(crash, out, js, truth, mode_expected=False)[0]
    refusal = SimpleNamespace(returncode=3, stderr="prsa-fit: bode.csv has a resonance at 150 Hz the rigid model cannot produce: a second mass (--fidelity compliant)\n")
    assert acceptance(refusal, out, js, truth, mode_expected=False)[0] == []
    assert acceptance(refusal, out, js, truth, mode_expected=True, must_fit=True)[0]
    out.write_text("x")
    assert acceptance(refusal, out, js, truth, mode_expected=False)[0]  # a file left behind
    # exit 0: the base plant with the truth's delay and current loop written, the inertia reported
    jt = truth["reflected_inertia_kg_m2"]
    text = Path(rs_set["base"]).read_text().replace(
        'current_loop_bandwidth_hz = { value = 1000.0', f'command_delay_samples = {{ value = {truth["drive.command_delay_samples"]}, source = "fit" }}\ncurrent_loop_bandwidth_hz = {{ value = {truth["drive.current_loop_bandwidth_hz"]}')
    out.write_text(text)
    ok = SimpleNamespace(returncode=0, stderr="")
    js.write_text(json.dumps({"reflected_inertia_kg_m2": {"value": jt * 1.01, "ci95": [jt * 0.99, jt * 1.03]}}))
    fails, row = acceptance(ok, out, js, truth, mode_expected=False)
    assert fails == [], fails
    assert row["delay"] == truth["drive.command_delay_samples"]
    js.write_text(json.dumps({"reflected_inertia_kg_m2": {"value": jt * 1.01, "ci95": [jt * 1.005, jt * 1.015]}}))
    assert any("outside the 95 % interval" in f for f in acceptance(ok, out, js, truth, mode_expected=False)[0])
    js.write_text(json.dumps({"reflected_inertia_kg_m2": {"value": jt * 1.05, "ci95": [jt * 0.9, jt * 1.1]}}))
    assert any("3 % allowed" in f for f in acceptance(ok, out, js, truth, mode_expected=False)[0])
    out.write_text(Path(rs_set["base"]).read_text())  # base delay 0, current loop 1000 Hz (+54 %)
    js.write_text(json.dumps({"reflected_inertia_kg_m2": {"value": jt, "ci95": [jt * 0.99, jt * 1.01]}}))
    fails = acceptance(ok, out, js, truth, mode_expected=True)[0]
    assert any("current loop" in f for f in fails)
    assert any("command_delay_samples" in f for f in fails)
    assert any("axial mode" in f for f in fails)  # the base's mode (catalogue stiffness) is not the truth's


# ---------------------------------------------------------------------------------------------
# (c) the judge's generator (foreign/gen_judge.py): written without reading the fitting code, the
# plant model or the generators above; its own checks here, then prsa-fit's acceptance on it.


@pytest.fixture(scope="module")
def judge_roller_rigid_loadsteps():
    return gj.run(gj.CASES["roller-rigid-d1-applied-si"], "loadsteps", seed=0)


def test_judge_load_step_plateaus_hold_the_torque_balance_with_the_loss_on_the_nut_force(judge_roller_rigid_loadsteps):
    # At constant forward speed the applied command averages to T_c + b w + a F / eta on every
    # load plateau (the Stribeck term is gone at 30 rad/s): written out here from the case's numbers.
    log, m = judge_roller_rigid_loadsteps, gj.ROLLER
    a = m.lead_m / (2 * math.pi)
    n = log["time_s"].size
    for i, force in enumerate(m.steps):
        i0, i1 = i * (n // 4) + int(0.6 * (n // 4)), (i + 1) * (n // 4)
        tq = log["applied_n_m"][i0:i1]
        batches = np.array_split(tq, 10)
        se = np.std([b.mean() for b in batches], ddof=1) / math.sqrt(10)
        expected = m.t_coulomb + m.viscous * 30.0 + a * force / m.eta
        assert abs(tq.mean() - expected) < 4 * se + 2e-3, (force, tq.mean(), expected, se)
        # the loss on the load alone (eta = 1) is far outside that tolerance at load
        if force > 0:
            assert abs(tq.mean() - (m.t_coulomb + m.viscous * 30.0 + a * force)) > 20 * (4 * se + 2e-3)
    # the speed is held at the reference on the last plateau (the loop is stable)
    assert np.mean(np.diff(log["true_angle_rad"][-400:])) / m.ts == pytest.approx(30.0, rel=2e-3)


def test_judge_applied_log_is_the_computed_log_one_sample_later(judge_roller_rigid_loadsteps):
    log = judge_roller_rigid_loadsteps
    assert np.array_equal(log["applied_n_m"][1:], log["computed_n_m"][:-1])
    for name, case in gj.CASES.items():
        t = gj.truth(case)
        assert t["drive.command_delay_samples"] == case.delay - 1
        assert t["delay_logged_to_action_samples"] == (case.delay if case.logged == "computed" else case.delay - 1)


def test_judge_quantised_angle_is_whole_counts_and_the_staircase_breaks_away_from_rest():
    case = gj.CASES["roller-rigid-d1-applied-si"]
    log = gj.run(case, "staircase", seed=0)
    q = 2 * math.pi / case.mech.counts
    counts = log["angle_rad"] / q
    assert np.max(np.abs(counts - np.round(counts))) < 1e-6
    moved = int(np.argmax(np.abs(log["true_angle_rad"] - log["true_angle_rad"][0]) > 20 * q))
    assert moved > 0
    # the drive had to exceed the standstill (Stribeck) level, above the Coulomb level, to move
    assert np.max(log["applied_n_m"][: moved + 1]) > case.mech.t_coulomb
    assert np.max(np.abs(log["applied_n_m"][: moved + 1])) < case.mech.torque_limit


@pytest.mark.parametrize("name", ["ball-2mass-d1-computed-si", "roller-2mass-d2-computed-nonsi"])
def test_judge_frf_asymptote_mode_and_anti_resonance_from_formulas(name):
    case = gj.CASES[name]
    m, t = case.mech, gj.truth(case)
    a = m.lead_m / (2 * math.pi)
    jms = m.j_motor + m.j_screw
    # low frequency: 1 / (J_lf s + b), J_lf = J_ms + m a^2 / eta (the loss on the whole nut force)
    f = np.array([1.0, 2.0])
    h = gj.frf(case, f)
    j_lf = jms + m.mass * a * a / m.eta
    assert np.abs(h) * np.hypot(j_lf * 2 * math.pi * f, m.viscous) == pytest.approx([1.0, 1.0], abs=2e-3)
    # phase lag to first order: delay + hold + backward difference + current loop
    w = 2 * math.pi * f
    lag = w * ((t["delay_logged_to_action_samples"] + 1.0) * m.ts + 1.0 / (2 * math.pi * m.f_current))
    assert np.angle(h) == pytest.approx(-math.pi / 2 + np.arctan(m.viscous / (j_lf * w)) - lag, abs=2e-3)
    # peak and notch of a nearly undamped copy sit on the formulas
    from dataclasses import replace

    light = gj.Case(replace(m, zeta=1e-4), True, case.delay, case.logged, case.units)
    fg = np.linspace(60.0, 260.0, 40001)
    mag = np.abs(gj.frf(light, fg))
    f_mode = math.sqrt(m.k_axial * (a * a / (m.eta * jms) + 1.0 / m.mass)) / (2 * math.pi)
    f_anti = math.sqrt(m.k_axial / m.mass) / (2 * math.pi)
    assert fg[np.argmax(mag)] == pytest.approx(f_mode, rel=2e-3)
    assert fg[np.argmin(mag)] == pytest.approx(f_anti, rel=2e-3)
    assert t["first_mode_hz"] == pytest.approx(f_mode, rel=1e-12)
    assert t["anti_resonance_hz"] == pytest.approx(f_anti, rel=1e-12)
    assert t["reflected_inertia_kg_m2"] == pytest.approx(jms + m.mass * a * a, rel=1e-12)


def test_judge_non_si_log_reads_through_its_description_as_the_si_log(tmp_path):
    # the ms / deg / % of rated torque / kN log, read by the toolkit's described-log reader (the
    # user's path), is the simulated run in SI
    from prsa_ctrl.identification import load_log_format, load_motor_record
    from prsa_ctrl.plant import load_plant

    name = "ball-rigid-d1-computed-nonsi"
    case = gj.CASES[name]
    log = gj.run(case, "loadsteps", seed=0)
    path = tmp_path / "loadsteps.csv"
    gj.write_log(case, log, path)
    (tmp_path / "base.toml").write_text(gj.base_plant_text(case))
    (tmp_path / "log.toml").write_text(gj.LOG_FORMAT_NONSI.format(gain=case.mech.rated_torque / 100.0, logged="as-computed"))
    header = path.read_text().splitlines()[0]
    assert header == "t_ms,motor_pos_deg,torque_pct_rated,load_kN"
    rec, conv = load_motor_record(path, load_log_format(tmp_path / "log.toml"), load_plant(str(tmp_path / "base.toml")))
    assert conv == "computed"
    assert rec.time_s == pytest.approx(log["time_s"], abs=1e-12)
    assert rec.nut_angle_rad == pytest.approx(log["angle_rad"], rel=1e-9, abs=1e-12)  # 10 digits of deg
    assert rec.torque_command_n_m == pytest.approx(log["computed_n_m"], rel=1e-8, abs=1e-10)
    assert rec.axial_load_n == pytest.approx(log["load_n"], rel=1e-8, abs=1e-6)


def test_judge_generator_is_deterministic_and_its_base_plant_is_nominal(tmp_path):
    from prsa_ctrl.plant import load_plant

    case = gj.CASES["roller-rigid-d1-applied-si"]
    one, two = gj.run(case, "multisine", 0), gj.run(case, "multisine", 0)
    assert np.array_equal(one["angle_rad"], two["angle_rad"])
    assert np.array_equal(one["applied_n_m"], two["applied_n_m"])
    assert not np.array_equal(one["applied_n_m"], gj.run(case, "multisine", 1)["applied_n_m"])
    for name, c in gj.CASES.items():
        p = tmp_path / f"{name}.toml"
        p.write_text(gj.base_plant_text(c))
        plant = load_plant(str(p))
        assert plant is not None
        text = p.read_text()
        assert f"motor_inertia_kg_m2 = {{ value = {0.9 * c.mech.j_motor:.6g}" in text  # -10 %
        assert abs(float(text.split("efficiency = { value = ")[1].split(",")[0]) - c.mech.eta) == pytest.approx(0.02)
        assert "command_delay_samples" not in text


# prsa-fit on the judge's cases: time-domain logs (rigid fidelity, as the docs' first command),
# the FRF with the structure the data choose, and on the two-mass axes the same logs with
# --fidelity compliant (logs-compliant: the compliant time-domain fit on its 0.05 s segments, the
# delay searched, no FRF beside the logs; logs-compliant-frf: the same with the measured response
# beside them, whose two-mass fit starts the axial mode) and the FRF with --fidelity compliant and
# --fidelity rigid. The rule is the issue's, never today's numbers.
JUDGE_KINDS = {name: (("logs", "logs-compliant", "logs-compliant-frf", "frf", "frf-compliant", "frf-rigid") if c.two_mass
                      else ("logs", "frf"))
               for name, c in gj.CASES.items()}

# Runs that violate the rule on main 1dddb38 at seed 0 (measured; the report's table): findings,
# not tolerances. strict: a fix makes them XPASS and fails the run until the mark is removed.
JUDGE_XFAIL = {
    # roller-rigid-d1-applied-si and ball-rigid-d1-computed-nonsi logs were marked here (exit 0 with the
    # truth outside the inertia's interval: -0.24 %, CI +-0.12 %, and -0.11 %, CI +-0.022 %) until the
    # time-domain fit's total inertia interval took the held moving mass's spread (heldmass.py).
    # The bias was common to the three logs, which no covariance can show (h9-interval, measured on
    # the final fits' Jacobians): the delete-one-log spread (identification/covariance.py) is within
    # the logs' noise (ratios 0.03..1.3 against the heterogeneity threshold 3.0), and the segment-wise
    # score covariance equals the HAC one. On the ball case with the generator's process torque noise
    # off: -0.089 %; and its load-cell noise off too: -0.078 %; Stribeck off: -0.089 %; the nut loss
    # nearly off (eta 0.995): -0.011 %, truth inside; 3 Radau steps per sample instead of 1: -0.089 %
    # (the same to 1e-7). The bias sits in the load-dependent nut loss path, not in the integration.
    # Not the smoothing band of |F_s| (plant/nutloss.py): the rigid model has the exact law, its
    # state derivative the same to the bit at 5 % or 0.2 % (tests/plant/test_nutloss.py). The cause
    # (h9-nutband, measured): the base plant's axis.moving_mass_kg is 5 % high and held; with the loss
    # on the whole force the motor sees J_ms + m a^2 (1 + L) when driving (L = 1/eta - 1), so the fit
    # moves J_ms by -dm a^2 (1 + L), the total by -dm a^2 L / J: predicted -0.113 % (ball) and -0.240 %
    # (roller), measured -0.113 % and -0.243 %. With the base's mass at the truth: roller -0.017 %
    # inside (CI 1.07889..1.08144e-3), ball -0.034 % (CI 2.91854..2.91982e-3, still outside). With
    # --fit adding axis.moving_mass_kg (and the total's interval from both keys, inertia_total.py):
    # ball -0.069 % (CI 2.91376..2.92258e-3, mass 306.4 kg CI 278.9..334.0, truth 300), roller
    # -0.030 % (CI 1.07948..1.08059e-3, mass 401.9 kg CI 397.2..406.6, truth 400): truth inside.
    # With the default keys and the held mass's spread (+-10 % uniform, sensitivity a^2 L): ball -0.113 %
    # (CI 2.90898..2.92477e-3), roller -0.243 % (CI 1.07142..1.08404e-3), exit 0 with the truth inside;
    # seed 1: roller -0.045 % inside (CI 1.07364..1.08610e-3), ball exit 3 'delay' (as before).
    # ball-2mass-d1-computed-si and roller-2mass-d1-applied-si logs (exit 0 with a rigid plant of a
    # two-mass axis at fit >= 50 %) were marked here until the verdict refused a residual that is a
    # resonance (validation.RESONANCE_SHARE): both now end exit 3 'second mass' with no file (rerun:
    # 65 % of the ball case's load-step residual within 15 % of 132.8 Hz, 86 % of the roller case's
    # multisine residual within 15 % of 150.4 Hz)
    # logs-compliant (h11-twomass, measured on a loaded machine, CPU user+sys of prsa-fit): both roller
    # cases end exit 3 with a diagnosis naming the mode, no file (accepted by the rule, not exit 0):
    # the compliant fit holds the base plant's mode keys (series mode 134.9 Hz, truth 161.3 Hz at 2000 N)
    # and 95-96 % of the multisine's residual lies within 15 % of 150.4 Hz. d1-applied: J 1.07629e-3
    # (CI 1.06145..1.09114e-3, truth 1.08035e-3 inside), shift 0 exact, 152 s CPU; d2-computed-nonsi: shift 1
    # against the true 2 (objective 1.2515e7 vs 1.3574e7) with the current loop at 336 Hz (truth 700):
    # the misplaced mode, not the delay, 182 s CPU. With --frf bode.csv beside the d1 logs the seed wrote
    # the moving mass (411 kg) and damping but not the nut stiffness, and the fit ends exit 3 the same way
    # (131 s CPU). ball-2mass-d1-computed-si: 17 min idle, exit 3 'axial mode'.
    # h13-modefit (CPU user+sys on the shared 2-core machine at load ~11): the compliant run's work is
    # bounded before it starts (identification/workbudget.py). ball-2mass-d1-computed-si logs-compliant:
    # exit 3 at the bound (208 iterations over its 28 797 intervals) naming the held mode keys and --frf,
    # 175 s CPU for the whole pytest run (the data's generation included), 8:54 wall. roller-2mass-d1-applied-si
    # logs-compliant on main before the bound: exit 3 'axial mode', 123 s CPU (its bound, 417 iterations over
    # its 14 397 intervals, about what that run spent; not rerun). The seed now writes the stiffness (the
    # roller screw's shaft and bearings in series are softer than its true 300 N/um: the nut and the
    # bearings scaled together), so logs-compliant-frf (bode.csv beside the logs) on roller-2mass-d1-applied-si:
    # exit 0, J 1.07899e-3 (CI 1.07278..1.08521e-3, truth 1.08035e-3 inside, -0.13 %), shift 0 exact, current
    # loop 707.6 Hz (700), mode 162.08 Hz (161.27, +0.5 %), 97 s CPU of prsa-fit. ball-2mass-d1-computed-si
    # logs-compliant-frf: exit 3 'delay' (accepted by the rule): shift 1 fitted (J 2.92059e-3, CI
    # 2.91308..2.92810e-3, truth 2.92018e-3 inside; current loop 1118.5 Hz against 1100), shift 2 stopped by
    # the bound (its 208 iterations spent), so the search could not refute it; 171 s CPU of prsa-fit.
    # roller-2mass-d2-computed-nonsi logs-compliant-frf: exit 3 'friction model' (accepted by the rule, no file),
    # 99 s CPU of the pytest run.
    # (h14-compfit's instant refusal below was replaced by h15-direct: the loop identified from the load-step log
    # places the mode; judge roller d1 logs-compliant exit 3 'axial mode', written 159 Hz vs 161.3, 62 s; ball d1 132 Hz
    # vs 132.3, 154 s; CPU of the pytest run.)
    # h14-compfit (seed 0, one traced prsa-fit, CPU user+sys at load 10-17 on the 2-core machine): every
    # logs-compliant kind (no --frf, no loop described) ends exit 3 at once, "no loop described: --speed-loop
    # KP,KI[,TAU_S] ... or --frf FRF.csv" (compliant.unplaced_mode), no file: ball-2mass-d1 1.17 s, roller d1
    # 1.14 s, roller d2 1.28 s (ball was 175 s at the work bound). ball-2mass-d1-computed-si logs-compliant-frf:
    # exit 0, accepted: J 2.92017e-3 (CI 2.91273..2.92763e-3, truth 2.92018e-3), current loop 1119.9 Hz (1100),
    # the delay exact, mode 131.78 Hz (132.32); shift 2 stopped at its candidate's share of the bound (69 of 208
    # iterations over the logs: workbudget.candidate_bound) and named, the delay decided among the converged;
    # 180 of 208 passes; A/B back to back against a8f75f1 at load 2-4: 127.8 s CPU (a8f75f1: exit 3 'delay',
    # 156.8 s). roller-2mass-d1-applied-si logs-compliant-frf: exit 0, values identical to a8f75f1's (J 1.07899e-3,
    # CI 1.07278..1.08521e-3, 707.6 Hz, mode 162.08 Hz); 183 passes (was 299, 255 of them in the refit at the
    # found shift failing from both starts, now capped at a third of the bound; the search's fit is written as
    # before); A/B back to back: 55.6 s CPU (a8f75f1: 93.8 s). The ball case stays above the issue's 60 s: an
    # iteration over its 28 800 intervals costs about 0.5 s of CPU (CasADi's Jacobian blocks and their batched
    # inverses, linear in the intervals), and the run needs 180 of them.
}


def _judge_command(name, kind, tmp_path):
    """prsa-fit arguments of one judge run, on data of seed $PRSA_FOREIGN_SEED (default 0)."""
    seed = int(os.environ.get("PRSA_FOREIGN_SEED", "0"))
    exps = gj.EXPERIMENTS if kind.startswith("logs") else ()
    s = gj.generate(tmp_path / "data", name, seed=seed, experiments=exps)
    t = s["truth"]
    out, js = tmp_path / "fitted.toml", tmp_path / "report.json"
    if kind.startswith("logs"):
        logs = [s["logs"][n] for n in gj.EXPERIMENTS]
        how = ["--log-format", s["log_format"]] if s["log_format"] else ["--command-logged", t["command_logged"]]
        args = [*logs, *how, "--plant", s["base"], "--out", out, "--json", js]
        if kind.startswith("logs-compliant"):  # the mode reported at the truth's point (it moves with the nut force)
            args += ["--fidelity", "compliant", "--frf-speed", t["frf_speed_rad_s"], "--frf-load", t["frf_load_n"]]
        if kind == "logs-compliant-frf":  # the measured response beside the logs: the compliant fit starts from its mode
            args += ["--frf", s["frf"]]
    else:
        args = ["--frf", s["frf"], "--frf-speed", t["frf_speed_rad_s"], "--frf-load", t["frf_load_n"],
                "--command-logged", t["command_logged"], "--plant", s["base"], "--out", out, "--json", js]
        if kind != "frf":
            args += ["--fidelity", kind.split("-")[1]]
    return args, out, js, t


def _judge_params():
    # the marks were measured on seed 0 (the default); on another seed the rule is asserted bare
    # (seed 1 measured: roller-rigid-d1-applied-si logs accepted, -0.045 % inside its interval;
    # ball-rigid-d1-computed-nonsi logs exit 3 'delay', accepted)
    seed0 = os.environ.get("PRSA_FOREIGN_SEED", "0") == "0"
    for name, kinds in JUDGE_KINDS.items():
        for kind in kinds:
            reason = JUDGE_XFAIL.get((name, kind)) if seed0 else None
            marks = [pytest.mark.xfail(strict=True, reason=reason)] if reason else []
            yield pytest.param(name, kind, marks=marks, id=f"{name}--{kind}")


@pytest.mark.slow
@pytest.mark.skipif(PRSA_FIT is None, reason="the prsa-fit console script is not installed")
@pytest.mark.parametrize("name,kind", list(_judge_params()))
def test_prsa_fit_acceptance_on_the_judges_cases(name, kind, tmp_path):
    # exit 0 with a file whose total inertia is within 3 % with the truth inside its 95 %
    # interval, the delay exact, the current loop within 25 %, the mode within 5 % where the
    # data hold one; or exit 3 with no file and a one-line diagnosis. Never exit 0 with the
    # inertia outside its interval.
    args, out, js, truth = _judge_command(name, kind, tmp_path)
    proc = _run(args, tmp_path)
    fails, row = acceptance(proc, out, js, truth, mode_expected=truth["two_mass"],
                            cost_allowed=f"judge:{name}--{kind}" in COST_BOUND_ALLOWED)
    _record(f"judge:{name}--{kind}", args, row, fails, proc, js)
    assert not fails, f"{name} {kind}: " + "; ".join(fails) + f"\nstderr: {proc.stderr.strip()[-600:]}"


# ------------------------------------------------------------------------------------------------
# The third generator (foreign/gen_third.py, h13-gen3): three bodies (rotor, coupling, screw,
# carriage), the axial stiffness moving with the nut along a screw held at the motor end, cogging,
# the power-screw law of the nut loss, a discrete PI speed loop. Its kinds: the three logs rigid
# (logs) and --fidelity compliant (logs-compliant, the mode reported at the FRF's point), the FRF
# with the structure the data choose (frf) and --fidelity compliant (frf-compliant). The rule is
# acceptance, the judge's. Every case's data hold the first axial mode (the logs' torque dither
# and the FRF excite it).
THIRD_KINDS = ("logs", "logs-compliant", "frf", "frf-compliant")

# Runs that violate the rule on main aca0656 at seed 0 (measured once each, one prsa-fit at a time,
# CPU user+sys of prsa-fit; the h13-gen3 report's table): findings, not tolerances. strict: a fix
# makes them XPASS and fails the run until the mark is removed. Truths: roller-39x10 total
# inertia 4.31284e-3 kg m^2, current loop 1000 Hz, command delay 2 samples (logged as applied),
# first axial mode 135.02 Hz at 10 rad/s, 4000 N, nut 0.60 m from the fixed bearing; the
# coupling mode at 711 Hz is in the response too.
# Accepted on aca0656 (exit 3, no file), by the rule's words only: ball-40x16 frf and frf-compliant
# ended "rigid FRF fit did not converge ... 4000 evaluations; remedy: check the response's units"
# (a solver failure; the units are right; now named as the second resonance, THIRD_XFAIL); ball-40x16 logs
# (h13-frfdiag, the verdict's entries of aca0656's fit re-diagnosed: now "position-periodic torque: 86 % of
# the replay residual of loadsteps.csv lies within 15 % of 23.44 Hz and one sinusoid of the motor angle at
# 6.00 cycles per revolution explains 85 % of it out of sample, one of time at 23.85 Hz 79 % ...; besides,
# second mass: 55 % of the replay residual of multisine.csv lies within 15 % of 121.1 Hz"; without cogging
# "second mass: 74 % ... multisine.csv ... 121.1 Hz" as before); ball-40x16 logs ended before "second mass: 86 % of the replay
# residual of loadsteps.csv within 15 % of 23.44 Hz" (the 6-per-rev cogging at 25 rad/s is 23.9 Hz;
# the axial mode is 118 Hz), 53 s CPU; roller-39x10 logs "second mass ... 144 Hz" (right), 86 s (h13-frfdiag,
# re-diagnosed: "second mass: 46 % ... multisine.csv ... 144 Hz ...; besides, position-periodic torque: 46 %
# ... loadsteps.csv ... 21.97 Hz ... 6.00 cycles per revolution explains 49 % ..., one of time 17 %").
# logs-compliant (both): stopped at 20 min of wall time on aca0656 (load ~14, ~5 min CPU); on a8f75f1 exit 3 at the work bound (h14-oracle, 141.8 and 179.0 s CPU); h14-compfit: exit 3
# at once, "no loop described: --speed-loop KP,KI[,TAU_S] ... or --frf FRF.csv" (the kind gives neither:
# compliant.unplaced_mode), no file, 1.15 and 1.18 s CPU user+sys of prsa-fit (ball-40x16, roller-39x10, seed 0).
# h15-direct: the loop identified from the load-step log gives a response with the coupling's resonance beside the
# axial one (ball 116.7 and 978.5 Hz; roller 5 resonances), so both are refused naming the loop and why.
# Diagnostics (h13-gen3, not marks): with the coupling 100x stiffer (its mode above Nyquist) both
# FRFs pass the rule (ball -0.73 %, CI holds the truth, 797 Hz, delay 1, mode 118.28 vs 118.35 Hz;
# roller -0.79 %, 1001 Hz, delay 2, mode 135.85 vs 135.88 Hz): the second, higher mode is what
# breaks the FRF path. Without cogging the ball logs end exit 3 "second mass ... 121.1 Hz" (right)
# in 9.5 s CPU, the free fit's inertia +0.23 % with the truth inside its interval.
THIRD_XFAIL: dict[tuple[str, str], str] = {
    # roller-39x10 frf and frf-compliant were marked here (exit 0: -4.97 % inertia, 745.9 Hz, delay 1
    # against 2; compliant +28.3 % with the truth outside its interval, moving mass 999 kg, mode 117.14 Hz)
    # until the FRF path refused a response with a resonance its model lacks (identification/frfcheck.py,
    # h13-frfdiag): both now end exit 3, no file, before any fit, "the response shows 2 resonances, near
    # 134.3 Hz (24.8 dB, 64.9 x the noise) and 754.4 Hz (11.6 dB, 30.4 x the noise) ... the units are right
    # (... 1.15 x the base plant's ...)", 1.1 s CPU; the ball-40x16 FRFs the same, "117.2 Hz (30.6 dB, 106 x
    # the noise) and 951.2 Hz (18.5 dB, 63.9 x)", units 1.12 x, 1.1 s CPU (was 4.8 s and "check the
    # response's units")
}


def _third_command(name, kind, tmp_path):
    """prsa-fit arguments of one gen_third run, on data of seed $PRSA_FOREIGN_SEED (default 0)."""
    seed = int(os.environ.get("PRSA_FOREIGN_SEED", "0"))
    logs_kind = kind.startswith("logs")
    s = g3.generate(tmp_path / "data", name, seed=seed, experiments=g3.EXPERIMENTS if logs_kind else (),
                    frf=not logs_kind)
    t = s["truth"]
    out, js = tmp_path / "fitted.toml", tmp_path / "report.json"
    if logs_kind:
        logs = [s["logs"][n] for n in g3.EXPERIMENTS]
        how = ["--log-format", s["log_format"]] if s["log_format"] else ["--command-logged", t["command_logged"]]
        args = [*logs, *how, "--plant", s["base"], "--out", out, "--json", js]
        if kind == "logs-compliant":
            args += ["--fidelity", "compliant", "--frf-speed", t["frf_speed_rad_s"], "--frf-load", t["frf_load_n"]]
    else:
        args = ["--frf", s["frf"], "--frf-speed", t["frf_speed_rad_s"], "--frf-load", t["frf_load_n"],
                "--command-logged", t["command_logged"], "--plant", s["base"], "--out", out, "--json", js]
        if kind == "frf-compliant":
            args += ["--fidelity", "compliant"]
    return args, out, js, t


def _third_params():
    seed0 = os.environ.get("PRSA_FOREIGN_SEED", "0") == "0"
    for name in g3.CASES:
        for kind in THIRD_KINDS:
            reason = THIRD_XFAIL.get((name, kind)) if seed0 else None
            marks = [pytest.mark.xfail(strict=True, reason=reason)] if reason else []
            yield pytest.param(name, kind, marks=marks, id=f"{name}--{kind}")


@pytest.mark.slow
@pytest.mark.skipif(PRSA_FIT is None, reason="the prsa-fit console script is not installed")
@pytest.mark.parametrize("name,kind", list(_third_params()))
def test_prsa_fit_acceptance_on_the_third_generator(name, kind, tmp_path):
    # the judge's rule (acceptance) on gen_third's data: exit 0 with the total inertia within
    # 3 % and the truth inside its 95 % interval, the delay exact, the current loop within 25 %,
    # the first axial mode within 5 %; or exit 3 with no file and a one-line diagnosis
    args, out, js, truth = _third_command(name, kind, tmp_path)
    proc = _run(args, tmp_path)
    fails, row = acceptance(proc, out, js, truth, mode_expected=truth["two_mass"],
                            cost_allowed=f"third:{name}--{kind}" in COST_BOUND_ALLOWED)
    _record(f"third:{name}--{kind}", args, row, fails, proc, js)
    if kind.startswith("frf") and proc.returncode == 3:  # a diagnosis that is true: the units are right, and the
        # response holds the coupling mode above the first axial mode, which neither FRF model has
        assert "check the response's units" not in proc.stderr
        assert "units check failed" not in proc.stderr
        assert "resonance" in proc.stderr
        assert "2 resonances" not in proc.stderr or "--frf-band " in proc.stderr  # (h14-band: the band to type)
    if (name, kind) == ("ball-40x16", "logs") and proc.returncode == 3:  # its load steps' residual is the cogging
        assert "position-periodic torque" in proc.stderr
        assert "6.00 cycles per revolution" in proc.stderr
    assert not fails, f"{name} {kind}: " + "; ".join(fails) + f"\nstderr: {proc.stderr.strip()[-600:]}"
