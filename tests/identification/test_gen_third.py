"""The third foreign generator itself (``foreign/gen_third.py``): checks against formulas written
out here, not against the simulator's own helpers.

The generator is three bodies (rotor, screw behind a torsional coupling, carriage on an axial
spring whose stiffness moves with the nut), cogging, the power-screw nut loss and a discrete PI
speed loop. Here: the steady torque balance of the load steps, the measured FRF against the
analytic chain and its low-frequency asymptote ``1/(J s)``, the first axial mode by the
characteristic cubic against the simulator's own linearisation and the FRF's peak, the delays of
the two logging conventions, the non-SI log against the simulated SI values, determinism in the
seed and the base plant as a user's nominal file. prsa-fit's acceptance on these cases is in
``test_foreign_generators.py`` (``test_prsa_fit_acceptance_on_the_third_generator``, slow).
"""

from __future__ import annotations

import dataclasses
import math
import os
import shutil
import subprocess
import sys
import tomllib

import numpy as np
import pytest

from foreign import gen_third as g3

TWO_PI = 2.0 * math.pi
NAMES = list(g3.CASES)


@pytest.fixture(scope="module")
def sets(tmp_path_factory):
    return {n: g3.generate(tmp_path_factory.mktemp(n), n, seed=0) for n in NAMES}


def _read_si(s):
    """The log files as a user reads them, in SI: (time s, command N m, angle rad, load N), the
    non-SI one through its description's units (ms, rev, % of the rated torque with the gain, kN)."""
    out = {}
    for kind, path in s["logs"].items():
        data = np.genfromtxt(path, delimiter=",", names=True)
        if s["log_format"] is None:
            out[kind] = (data["time_s"], data["torque_command_n_m"], data["nut_angle_rad"], data["axial_load_n"])
        else:
            desc = tomllib.loads(s["log_format"].read_text())
            assert desc["time"]["unit"] == "ms"
            gain = desc["command"]["gain"]
            out[kind] = (data["t_ms"] * 1e-3, data["torque_pct"] * gain, data["motor_rev"] * TWO_PI,
                         data["force_kn"] * 1e3)
    return out


def _geometry(c):
    """Lead per radian, forward efficiency by the power-screw formula and the total inertia at
    the motor, written out from the case's dimensions."""
    a = c.lead_m / TWO_PI
    lam = math.atan(c.lead_m / (math.pi * c.d_nominal_m))
    eta_f = math.tan(lam) / math.tan(lam + math.atan(c.mu_thread))
    j_screw = math.pi * 7850.0 * c.d_nominal_m ** 4 * c.span_m / 32.0 + c.j_hub_screw
    return a, eta_f, c.j_rotor + c.j_hub_motor, j_screw


@pytest.mark.parametrize("name", NAMES)
def test_load_step_plateaus_hold_the_power_screw_torque_balance(name, sets):
    # on each load level's last 0.1 s (the speed loop settled), cut to whole cogging periods
    # (6 per rev): mean command = motor friction (Coulomb, Stribeck, viscous) + a F / eta_f,
    # eta_f = tan(lam) / tan(lam + atan(mu)); a missing efficiency or Coulomb level is 0.3 N m off
    c = g3.CASES[name]
    t, u, ang, load = _read_si(sets[name])["loadsteps"]
    a, eta_f, _, _ = _geometry(c)
    levels = []
    for t0, t1 in ((0.1, 0.2), (0.35, 0.45), (0.6, 0.7), (0.88, 1.0)):
        i0, i1 = int(round(t0 / c.ts)), min(int(round(t1 / c.ts)), len(t) - 1)
        per = TWO_PI / 6.0
        whole = math.floor((ang[i1] - ang[i0]) / per) * per
        i1 = i0 + int(np.argmin(np.abs(ang[i0:i1 + 1] - ang[i0] - whole)))
        w = (ang[i1] - ang[i0]) / (t[i1] - t[i0])
        force = float(np.mean(load[i0:i1]))
        expected = (c.t_coulomb + (c.t_static - c.t_coulomb) * math.exp(-(w / c.w_stribeck) ** 2) + c.b_viscous * w
                    + a * force / eta_f)
        levels.append(force)
        assert abs(np.mean(u[i0:i1]) - expected) < 0.012, (t0, w, force, np.mean(u[i0:i1]), expected)
    assert max(levels) - min(levels) > 0.5 * c.frf_load


def _chain_frf(c, f_hz):
    """The measured FRF's model, written out: the rotor, the coupling (spring + damper), the screw,
    the nut driving (torque a F / eta_f) and the carriage on the axial spring at the FRF's
    position, times the drive's sampling (command held over a sample, speed the backward
    difference: each (1 - e^-sT)/(sT)), the delay logged-to-action and the current loop."""
    a, eta_f, j_m, j_s = _geometry(c)
    s = 1j * TWO_PI * np.asarray(f_hz)
    x = c.frf_position_m
    k = 1.0 / (1.0 / c.k_nut + 1.0 / c.k_bearing + x / (206e9 * math.pi * c.d_root_m ** 2 / 4.0))
    c_ax = 2.0 * c.zeta_axial * math.sqrt(k * c.mass_kg)
    c_c = 2.0 * c.zeta_coupling * math.sqrt(c.k_coupling * j_m * j_s / (j_m + j_s))
    z_k = k / s + c_ax
    z_nut = (a / eta_f) * a * z_k / (1.0 + z_k / (c.mass_kg * s))
    z_c = c.k_coupling / s + c_c
    g = 1.0 / (j_m * s + c.b_viscous + z_c * (1.0 - z_c / (j_s * s + z_nut + z_c)))
    d = c.delay_samples + (1 if c.command_logged == "computed" else 0)
    hold = (1.0 - np.exp(-s * c.ts)) / (s * c.ts)
    return g * np.exp(-s * d * c.ts) * hold ** 2 / (1.0 + s / (TWO_PI * c.current_bw_hz))


def _bode(s):
    data = np.genfromtxt(s["frf"], delimiter=",", names=True)
    g = 10 ** (data["magnitude_db"] / 20) * np.exp(1j * np.radians(data["phase_deg"]))
    return data["frequency_hz"], g, data["coherence"]


@pytest.mark.parametrize("name", NAMES)
def test_frf_low_frequency_asymptote_is_one_over_j_s(name, sets):
    # below a sixth of the mode the measured response, its sampling, delay and current loop
    # divided out, is 1/(J s) with J = J_m + J_s + m a^2 / eta_f (the FRF is taken at load, the
    # nut driving: the inertial force pays the thread loss too)
    c = g3.CASES[name]
    f, g, coh = _bode(sets[name])
    a, eta_f, j_m, j_s = _geometry(c)
    j_eff = j_m + j_s + c.mass_kg * a * a / eta_f
    s = 1j * TWO_PI * f
    d = c.delay_samples + (1 if c.command_logged == "computed" else 0)
    corr = np.exp(-s * d * c.ts) * ((1.0 - np.exp(-s * c.ts)) / (s * c.ts)) ** 2 / (1.0 + s / (TWO_PI * c.current_bw_hz))
    sel = (f > 12.0) & (f < sets[name]["truth"]["first_mode_hz"] / 5.0) & (coh > 0.95)
    assert sel.sum() >= 3
    ratio = g[sel] * s[sel] * j_eff / corr[sel]
    assert abs(np.median(np.abs(ratio)) - 1.0) < 0.03, np.abs(ratio)
    assert np.max(np.abs(np.degrees(np.angle(ratio)))) < 5.0


@pytest.mark.parametrize("name", NAMES)
def test_measured_frf_agrees_with_the_analytic_chain(name, sets):
    # the closed-loop FRF experiment (periodic dither, cogging, friction, quantised encoder)
    # against the linear chain written above, where the coherence is high, off the first mode's
    # +-15 % (the carriage travels during the measurement: the mode moves)
    c = g3.CASES[name]
    f, g, coh = _bode(sets[name])
    fm = sets[name]["truth"]["first_mode_hz"]
    sel = (f > 25.0) & (f < 400.0) & (coh > 0.98) & (np.abs(f / fm - 1.0) > 0.15)
    assert sel.sum() >= 20
    ratio = g[sel] / _chain_frf(c, f[sel])
    dev = np.abs(np.log(np.abs(ratio)))
    assert np.median(dev) < 0.015, dev
    assert np.max(dev) < 0.06, dev
    assert np.max(np.abs(np.degrees(np.angle(ratio)))) < 5.0


@pytest.mark.parametrize("name", NAMES)
def test_first_mode_formula_matches_the_simulators_linearisation_and_the_frf_peak(name, sets):
    c = g3.CASES[name]
    t = sets[name]["truth"]
    lin_hz, zeta = g3.linearised_modes_hz(c, c.frf_speed, c.frf_load, c.frf_position_m)
    # the truth's mode (the characteristic cubic, undamped) against the linearised |lambda|
    assert abs(lin_hz[0] / t["first_mode_hz"] - 1.0) < 0.005, (lin_hz, t["first_mode_hz"])
    assert abs(lin_hz[1] / t["second_mode_hz"] - 1.0) < 0.005
    # the coupling mode is a second, higher mode
    assert t["second_mode_hz"] > 4.0 * t["first_mode_hz"]
    # the FRF's resonance peak within two bins of the formula
    f, g, _ = _bode(sets[name])
    band = (f > 0.85 * t["first_mode_hz"]) & (f < 1.2 * t["first_mode_hz"])
    f_peak = f[band][np.argmax(np.abs(g[band]))]
    assert abs(f_peak - t["first_mode_hz"]) <= 2.0 * (f[1] - f[0]) + 0.01 * t["first_mode_hz"], (f_peak, t["first_mode_hz"])


@pytest.mark.parametrize("name", NAMES)
def test_truth_lists_every_peak_and_notch_of_the_analytic_chain(name):
    # the judge's oracle reads modes_hz and anti_resonances_hz: the peaks and notches of the chain
    # written above (nut driving), nearly undamped, each within 0.3 % of one of them, two of each
    c = dataclasses.replace(g3.CASES[name], zeta_axial=1e-4, zeta_coupling=1e-4, b_viscous=0.0)
    t = g3.truth(name)
    f = np.arange(40.0, 1500.0, 0.01)
    mag = np.abs(_chain_frf(c, f)) * f  # times f: the integrator's slope off, peaks and notches stay
    inner = mag[1:-1]
    peaks = f[1:-1][(inner > mag[:-2]) & (inner > mag[2:])]
    notches = f[1:-1][(inner < mag[:-2]) & (inner < mag[2:])]
    assert peaks.size == 2
    assert notches.size == 2
    for fp in peaks:
        assert min(abs(fp / m - 1.0) for m in t["modes_hz"]) < 3e-3, (fp, t["modes_hz"])
    for fn in notches:
        assert min(abs(fn / m - 1.0) for m in t["anti_resonances_hz"]) < 3e-3, (fn, t["anti_resonances_hz"])
    assert t["periodic_orders_per_rev"] == (6, 12)  # cog6 and cog12 of the case


@pytest.mark.parametrize("name", NAMES)
def test_first_mode_moves_with_the_nut_position(name):
    # k(x) = 1 / (1/k_nut + 1/k_bearing + x / (E A)), here for a nut 0.1 m from the fixed bearing
    # and at the end of the span; the linearisation moves with it
    c = g3.CASES[name]
    near, far = g3.mode_formula_hz(c, 0.1)[0], g3.mode_formula_hz(c, c.span_m)[0]
    assert near > 1.15 * far
    lin_far = g3.linearised_modes_hz(c, c.frf_speed, c.frf_load, c.span_m)[0][0]
    assert abs(lin_far / far - 1.0) < 0.005
    ea = 206e9 * math.pi * c.d_root_m ** 2 / 4.0
    k_end = 1.0 / (1.0 / c.k_nut + 1.0 / c.k_bearing + c.span_m / ea)
    assert abs(g3.stiffness(c, c.span_m) / k_end - 1.0) < 1e-12


@pytest.mark.parametrize("name", NAMES)
def test_truth_total_inertia_and_delay_conventions(name, sets):
    c = g3.CASES[name]
    t = sets[name]["truth"]
    a, _, j_m, j_s = _geometry(c)
    assert abs(t["reflected_inertia_kg_m2"] / (j_m + j_s + c.mass_kg * a * a) - 1.0) < 1e-12
    run = sets[name]["runs"]["multisine"]
    if c.command_logged == "computed":
        assert np.array_equal(run["logged"], run["u"])
        assert t["delay_logged_to_action_samples"] == c.delay_samples + 1
    else:
        assert np.array_equal(run["logged"][1:], run["u"][:-1])
        assert t["delay_logged_to_action_samples"] == c.delay_samples


@pytest.mark.parametrize("name", NAMES)
def test_a_command_pulse_reaches_the_motor_torque_after_the_stated_delay(name):
    # speed loop off (kp = ki = 0, no noise), one dither pulse at sample k0: the motor torque
    # (current loop output) first moves at k0 + 1 + n + 1 (computed at k0, entering the current
    # loop over [k0 + 1 + n, k0 + 2 + n)); and the logged command as the case logs it
    c = dataclasses.replace(g3.CASES[name], kp=0.0, ki=0.0, torque_noise=0.0, load_noise_n=0.0, cog6=0.0, cog12=0.0)
    n, k0 = 40, 10
    d = np.zeros(n)
    d[k0] = 1.0
    r = g3.simulate(c, np.full(n, 20.0), np.full(n, 500.0), d, q0=0.5, rng=np.random.default_rng(0))
    dev = np.abs(r["tau"] - r["tau"][0]) > 1e-9
    assert int(np.argmax(dev)) == k0 + 2 + c.delay_samples
    logged_at = int(np.argmax(np.abs(r["logged"] - r["logged"][0]) > 0.5))
    assert int(np.argmax(dev)) - 1 - logged_at == g3.truth(name)["delay_logged_to_action_samples"]


def test_non_si_log_reads_back_to_the_simulated_si_values(sets):
    s = sets["roller-39x10"]
    c = g3.CASES["roller-39x10"]
    t, u, ang, load = _read_si(s)["multisine"]
    run = s["runs"]["multisine"]
    assert np.max(np.abs(t - np.arange(len(t)) * c.ts)) < 1e-6
    assert np.max(np.abs(u - run["logged"])) < 1e-6 * c.rated_torque
    assert np.max(np.abs(ang - run["angle"])) < 1e-8
    assert np.max(np.abs(load - run["load"])) < 1e-3
    desc = tomllib.loads(s["log_format"].read_text())
    assert desc["command"]["logged"] == "as-applied"
    assert g3.CASES["roller-39x10"].command_logged == "applied"


@pytest.mark.parametrize("name", NAMES)
def test_angle_is_whole_counts_and_the_staircase_breaks_away_from_rest(name, sets):
    c = g3.CASES[name]
    _, _, ang, _ = _read_si(sets[name])["staircase"]
    counts = ang * c.counts_per_rev / TWO_PI
    assert np.max(np.abs(counts - np.round(counts))) < 1e-3
    rest = ang[: int(0.09 / c.ts)]
    assert np.ptp(rest) < 0.01  # held at rest by the loop under load
    i0, i1 = int(0.25 / c.ts), int(0.35 / c.ts)
    assert abs((ang[i1] - ang[i0]) / (0.1) / 8.0 - 1.0) < 0.05  # broke away: the 8 rad/s level held
    assert np.min(np.diff(ang)) < 0.0  # and both directions


def test_generator_is_deterministic_in_the_seed(tmp_path):
    a = g3.generate(tmp_path / "a", "ball-40x16", seed=3, experiments=("loadsteps",), frf=False)
    b = g3.generate(tmp_path / "b", "ball-40x16", seed=3, experiments=("loadsteps",), frf=False)
    c = g3.generate(tmp_path / "c", "ball-40x16", seed=4, experiments=("loadsteps",), frf=False)
    assert a["logs"]["loadsteps"].read_bytes() == b["logs"]["loadsteps"].read_bytes()
    assert a["logs"]["loadsteps"].read_bytes() != c["logs"]["loadsteps"].read_bytes()
    assert a["base"].read_bytes() == c["base"].read_bytes()


PRSA_TUNE = shutil.which("prsa-tune", path=os.path.dirname(sys.executable) + os.pathsep + os.environ.get("PATH", ""))


@pytest.mark.skipif(PRSA_TUNE is None, reason="the prsa-tune console script is not installed")
@pytest.mark.parametrize("name", NAMES)
def test_base_plant_loads_and_is_nominal_not_the_truth(name, tmp_path):
    # the datasheet plant: the inertia, current loop and datasheet axial mode are not the truth's
    s = g3.generate(tmp_path, name, seed=0, experiments=(), frf=False)
    p = subprocess.run([PRSA_TUNE, "--show-plant", str(s["base"])], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr

    def value(key):
        for line in p.stdout.splitlines():
            parts = line.split()
            if parts and parts[0] == key:
                return float(parts[2])
        raise AssertionError(f"{key} not listed")

    t = s["truth"]
    c = g3.CASES[name]
    j = value("axis.motor_inertia_kg_m2") + value("axis.screw_inertia_kg_m2") + value("axis.moving_mass_kg") * (c.lead_m / TWO_PI) ** 2
    assert abs(j / t["reflected_inertia_kg_m2"] - 1.0) > 0.02
    assert abs(value("drive.current_loop_bandwidth_hz") / t["drive.current_loop_bandwidth_hz"] - 1.0) > 0.15
    assert value("drive.command_delay_samples") != t["drive.command_delay_samples"]
    mode = float(p.stdout.split("axial mode ")[1].split()[0])
    assert abs(mode / t["first_mode_hz"] - 1.0) > 0.05
