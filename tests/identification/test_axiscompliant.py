"""The two-mass linear-axis fit (prsa_ctrl.identification.axiscompliant, ``prsa-fit LOG --log-format F
--fidelity compliant``) on logs of an independent two-mass generator written here.

The generator (:func:`two_mass_log`) writes the equations of motion of two bodies by hand -- the
motor side (the encoder, the drive force, Coulomb + viscous friction per direction with a stick
band) and the load mass, joined by a spring and a damper -- and integrates them with the midpoint
rule on 40 substeps per controller sample (not the toolkit's exact matrix-exponential stepper);
the position-P/velocity-P controller with the two-sample average runs at 1 kHz, a random binary
test signal is added at the drive input, an unlogged white force disturbance (2 N rms) acts on
the motor side, the position is quantised to 50 nm. Optionally a
third mass beyond the load mass, which the toolkit's model does not have.
"""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest

from prsa_ctrl.cli.fit import main as fit_main
from prsa_ctrl.identification.axis import axis_plant_toml, load_axis_plant
from prsa_ctrl.identification.axiscompliant import TWO_MASS_PARAMETERS, axis_frf, fit_two_mass_axis
from prsa_ctrl.identification.logformat import AxisLog, ControllerSpec

import axis_generator as gen  # tests/identification is on sys.path (its profile and placeholder base)
from independent_actuator import modal_damper, two_mass_eom_response

H, GAIN, KP, KV, RES = 1e-3, 30.0, 150.0, 250.0, 5e-8
#: motor side kg, load mass kg, stiffness N/m, damping ratio, Fv+ Fv- N s/m, Fc+ Fc- N
TRUTH = dict(mm=30.0, ml=50.0, k=3.16e6, zeta=0.05, fvp=150.0, fvn=220.0, fcp=15.0, fcn=25.0)


def two_mass_log(seed, n=3000, delay=0, dither_v=0.5, noise_n=2.0, sub=40, third=None, **over):
    """``(time s, position m, reference m, command V, test signal V)`` of the closed loop on two masses
    (``third=(kg, N/m)``: a third mass on a spring beyond the load mass, lightly damped, which the
    toolkit's model does not have)."""
    p = {**TRUTH, **over}
    mm, ml, k, fvp, fvn, fcp, fcn = (p[x] for x in ("mm", "ml", "k", "fvp", "fvn", "fcp", "fcn"))
    c = modal_damper(k, mm, ml, p["zeta"])
    rng = np.random.default_rng(seed)
    r = np.zeros(n)
    prof = gen.profile(rng, n)  # bang-bang moves in both directions with rests (the axis generator's)
    r[:] = prof
    d = dither_v * np.repeat(rng.choice([-1.0, 1.0], size=n // 5 + 1), 5)[:n]
    disturbance = noise_n * rng.standard_normal(n)  # an unlogged force on the motor side, N (held over a sample)
    xm = vm = xl = vl = x3 = v3 = 0.0
    m3, k3 = third if third is not None else (1.0, 0.0)
    c3 = 2 * 0.02 * math.sqrt(k3 * m3)
    q_log, u_log = np.zeros(n), np.zeros(n)
    qprev = qfprev = 0.0
    pending = [0.0] * delay
    hs = H / sub

    def accelerations(f, xm, vm, xl, vl):
        spring = k * (xm - xl) + c * (vm - vl)
        net = f - spring
        if vm > 0:
            am = (net - fcp - fvp * vm) / mm
        elif vm < 0:
            am = (net + fcn - fvn * vm) / mm
        else:  # at rest: sticks while the net force is inside the band
            am = (net - fcp) / mm if net > fcp else ((net + fcn) / mm if net < -fcn else 0.0)
        return am, (spring - k3 * (xl - x3) - c3 * (vl - v3)) / ml

    for i in range(n):
        q = RES * math.floor(xm / RES + 0.5)
        q_log[i] = q
        qf = 0.5 * (q + qprev)
        dq = (qf - qfprev) / H
        qprev, qfprev = q, qf
        computed = min(10.0, max(-10.0, KV * (KP * (r[i] - q) - dq)))
        pending.append(computed)
        applied = pending.pop(0)
        u_log[i] = computed + d[i]
        f = GAIN * (applied + d[i]) + disturbance[i]
        for _ in range(sub):  # midpoint rule; the motor side stops where its speed would change sign
            am1, al1 = accelerations(f, xm, vm, xl, vl)
            vmh = vm + 0.5 * hs * am1
            if vm != 0 and vmh * vm < 0:
                vmh = 0.0
            am2, al2 = accelerations(f, xm + 0.5 * hs * vm, vmh, xl + 0.5 * hs * vl, vl + 0.5 * hs * al1)
            vmn = vm + hs * am2
            if vm != 0 and vmn * vm < 0:
                vmn = 0.0
            xm += 0.5 * hs * (vm + vmn)
            a3 = (k3 * (xl - x3) + c3 * (vl - v3)) / m3  # the third mass (explicit: slow beside the step)
            x3 += hs * (v3 + 0.5 * hs * a3)
            v3 += hs * a3
            xl += hs * (vl + 0.5 * hs * al2)
            vl += hs * al2
            vm = vmn
    return np.arange(n) * H, q_log, r, u_log, d


def _log(seed, name="syn", delay=0, **kw):
    t, q, r, u, d = two_mass_log(seed, delay=delay, **kw)
    ctl = ControllerSpec("position-p/velocity-p", KP, KV, 0.0, "average2-difference", 10.0, H,
                         command_delay_samples=delay)
    return AxisLog(name, t, q, u, "V", GAIN, H, reference_m=r, test_signal=d, controller=ctl)


def _truth_vector():
    return {"axis.mass_kg": TRUTH["mm"] + TRUTH["ml"], "friction.viscous_positive_n_s_per_m": TRUTH["fvp"],
            "friction.viscous_negative_n_s_per_m": TRUTH["fvn"], "friction.coulomb_positive_n": TRUTH["fcp"],
            "friction.coulomb_negative_n": TRUTH["fcn"], "axis.load_mass_kg": TRUTH["ml"],
            "axis.load_stiffness_n_per_um": TRUTH["k"] * 1e-6, "axis.axial_damping_ratio": TRUTH["zeta"]}


def _modes():
    fa = math.sqrt(TRUTH["k"] / TRUTH["ml"]) / (2 * math.pi)
    return fa, fa * math.sqrt((TRUTH["mm"] + TRUTH["ml"]) / TRUTH["mm"])


def test_the_generator_is_a_two_mass_axis_the_rigid_model_does_not_replay():
    """The logs carry the mode: the indirect FRF of a log has its notch at the truth's
    anti-resonance, and the toolkit's two-mass replay at the truth reproduces the logged command
    (no disturbance) to a few mV where the rigid replay of the same total mass misses it by more than 30 times that."""
    from prsa_ctrl.identification.axis import replay_axis

    log = _log(1, noise_n=0.0)
    f, g, _ = axis_frf([log])
    fa, _ = _modes()
    band = (f > 5) & (f < 200)
    assert abs(f[band][np.argmin(np.abs(g[band]) * f[band])] - fa) < 1.0
    truth = _truth_vector()
    plant = gen.placeholder_base().with_values(truth, {k: "test: truth" for k in truth})
    rigid = plant.with_values({"axis.load_mass_kg": 0.0}, {})
    two, one = replay_axis(plant, log), replay_axis(rigid, log)
    err = [float(np.sqrt(np.mean((r.force_measured - r.force_simulated)[49:] ** 2))) / GAIN for r in (two, one)]
    assert err[0] < 0.01, err
    assert err[1] > 30 * err[0], err


def _base(log):
    from prsa_ctrl.identification.calibrate_axis import axis_base_plant

    return axis_base_plant([log], "log.toml")[0]  # built from what the log says, as prsa-fit builds it


#: The two-mass keys: the truth inside their 95 % intervals. The friction keys are held to 5 % of the
#: truth instead: their intervals under-cover on this generator. Measured over 21 single-log seeds
#: (1-4, 6-10, 14-25; h13-axis, with a prewhitened Newey-West covariance in place of the batch means;
#: the fit keeps the batch means: the Newey-West one left the friction z-scores where they were and
#: narrowed the load mass's interval of
#: test_the_second_mass_starts_from_a_measured_frf_when_the_logs_have_no_test_signal below the truth):
#: 3 did not converge within 40 evaluations; in 4 the logs barely move the axis in -x and Fv-/Fc- are
#: held at the +x start, which was reported with a zero-width "interval" (now none: held, not fitted);
#: of the other 14, Fv- and Fc- are outside in 5 each, always Fv- high and Fc- low (z +2.0..+2.6 and
#: -2.2..-4.3): a bias of the Coulomb/viscous split, not a covariance blind to correlation (the
#: z-scores barely moved from the former batch means', seed 1 Fv- +2.05 -> +2.58). Its two parts
#: (h14-axisfric, seed 1, one fit each): without the disturbance (+0.26 % / -0.16 %) it is this
#: generator's, which stops the motor side at the end of the substep in which its speed changes
#: sign: 400 substeps halve it (+0.13 % / -0.08 %; the toolkit's stepper finds the instant). With
#: the 2 N disturbance (Fv+ +2.3 %, Fv- +3.6 %, Fc+ -2.0 %, Fc- -1.8 %) 400 substeps change nothing
#: (+2.4, +3.5, -2.1, -1.7 %); the disturbance acting only while the axis rests gives most of it
#: (+1.4, +2.8, -1.4, -1.7 %), only while the reference moves less (+1.0, +0.9, -0.8, -0.2 %): at
#: rest the disturbed axis creeps through the stick band where the replay, which has no
#: disturbance, sticks; the fit lowers the Coulomb levels to creep alike and raises the viscous
#: terms to keep the sliding force. Generator and model share the friction law; the bias is the
#: output-error estimator's (a replay without the process noise that a stick band rectifies).
#: Leaving out the rests from the cost (30 ms after the reference stops) does not remove it (seed 1
#: Fc+ z -3.0 -> -2.9). Not fixed. Seeds 1-25 on h14-axisfric (one log each): 4 did not converge
#: (5, 9, 10, 17); 2 are refused by the friction-law test (11, 14: -x held at +x's start, seed 14's
#: written plant Fv+ 1560 N s/m against 150, which exit 0 wrote before); of the 21 converged, truth
#: outside per key M 2, Fv+ 6, Fv- 8 (of 16 fitted), Fc+ 6, Fc- 7 (of 16), m_l 1, k 3, zeta 1. The
#: two-log fit of seeds 4 and 12
#: has the damping outside, 0.0464..0.0496 against 0.05. On dbe3aa7 (h16-axispem) seed 11 passes
#: instead (exit 0; Fv+ +47 %, Fc+ -39 %, truth outside; -x held); seed 14 is refused, its diagnosis now
#: "friction as fitted, not missing physics" (test_a_log_that_cannot_determine_the_friction_...).
#: A prediction-error form was measured and not kept (h16-axispem; scripts/axis-twomass-sweep.py
#: measures this fit): the two-mass model driven open loop by the logged force, its motor side
#: corrected by a 20 Hz fixed-gain observer, the one-step position innovations as the cost, started
#: from this output error. Without the disturbance it is exact (every key's truth inside, friction
#: within 0.01 % on seeds 1, 2, 7, 8, where this fit leaves Fv-/Fc- outside in 3 of 5). With it, on
#: the 19 seeds of 1-25 both fit and pass, the median friction bias falls (Fv+ +1.24 -> +0.39 %, Fv-
#: +1.49 -> +0.45 %, Fc+ -0.95 -> -0.24 %, Fc- -0.99 -> +0.03 %) but the truth stays outside nearly
#: as often (Fv- 8 -> 5 of 16, Fc- 7 -> 7 of 16, Fv+ and Fc+ 4 -> 3 of 19): its intervals are narrower
#: (the mass's +-0.06 % missed the truth by 0.05 % on seed 2, delay 1, failing the test below), seed 11
#: is refused naming "a further mode" the generator has not, and the fit costs 44-65 % more CPU.
TWO_MASS_KEYS = ("axis.mass_kg", "axis.load_mass_kg", "axis.load_stiffness_n_per_um", "axis.axial_damping_ratio")


@pytest.mark.parametrize("seed,delay", [(1, 0), (2, 1)])
def test_two_mass_fit_recovers_the_truth_inside_its_intervals(seed, delay):
    log = _log(seed, delay=delay)
    fit = fit_two_mass_axis([log], _base(log))
    assert fit.passes, fit.validation
    assert fit.status == "ok", fit.validation
    truth = _truth_vector()
    for k in TWO_MASS_PARAMETERS:
        lo, hi = fit.parameters[k]["ci95"]
        if k in TWO_MASS_KEYS:
            assert lo <= truth[k] <= hi, (k, truth[k], lo, hi)
            assert hi - lo < 0.25 * truth[k]  # informative intervals, not wide ones that cover anything
        else:
            assert fit.parameters[k]["value"] == pytest.approx(truth[k], rel=0.05), k
    fa, fr = _modes()
    for key, want in (("antiresonance_hz", fa), ("mode_hz", fr)):
        lo, hi = fit.equivalent[key]["ci95"]
        assert lo <= want <= hi, (key, want, lo, hi)
    # the file written is a two-mass linear-axis plant file that loads with the fitted values
    from prsa_ctrl.identification.axis import LinearAxisPlant

    plant = LinearAxisPlant.from_dict(tomllib.loads(axis_plant_toml(fit.plant)), origin="fitted.toml")
    assert plant.second_mass[0] == pytest.approx(fit.parameters["axis.load_mass_kg"]["value"], rel=1e-12)


def test_the_second_mass_starts_from_a_measured_frf_when_the_logs_have_no_test_signal():
    """No test signal: the logs give no FRF; a measured response (the truth's, written by the
    independent 2 x 2 solution, 2..300 Hz) starts the second mass, and the fit ends at the truth."""
    log = _log(3, dither_v=0.0)
    assert axis_frf([log]) is None
    f = np.geomspace(2.0, 300.0, 150)
    c = modal_damper(TRUTH["k"], TRUTH["mm"], TRUTH["ml"], TRUTH["zeta"])
    g = two_mass_eom_response(f, TRUTH["mm"], TRUTH["ml"], TRUTH["k"], c, b=180.0)
    fit = fit_two_mass_axis([log], _base(log), frf=(f, g))
    assert "measured frequency response" in fit.start_from
    truth = _truth_vector()
    for k in TWO_MASS_KEYS:
        lo, hi = fit.parameters[k]["ci95"]
        assert lo <= truth[k] <= hi, (k, truth[k], lo, hi)
    assert fit.passes


def test_no_start_for_the_second_mass_is_a_fit_error_naming_the_remedies():
    from prsa_ctrl.errors import AxisFitError

    log = _log(3, dither_v=0.0)  # (simulated once: it was twice, for the logs and for the base)
    with pytest.raises(AxisFitError, match="no start for the second mass.*--frf"):
        fit_two_mass_axis([log], _base(log))


# the EMPS-like description of axis_generator, plus the column of the drive's test signal
CSV_FORMAT = gen.DITHER_CSV_FORMAT
_write_csv = gen.write_dither_csv


@pytest.fixture(scope="module")
def described(tmp_path_factory):
    root = tmp_path_factory.mktemp("axis2m")
    (root / "log.toml").write_text(CSV_FORMAT)
    _write_csv(root / "good.csv", two_mass_log(4))
    _write_csv(root / "other.csv", two_mass_log(12))
    return root  # (three.csv, the three-mass log, is written by the slow test that reads it)


def test_prsa_fit_compliant_writes_a_validated_two_mass_plant(described, tmp_path, capsys):
    """Two logs (two seeds): the fit, each log replayed by the written plant and, left out, by the
    plant fitted on the other; mass, load mass and stiffness within 1 % of the truth, the damping
    within 10 % (its interval on these two logs, 0.0464..0.0496, misses the truth 0.05: see
    TWO_MASS_KEYS)."""
    out, js = tmp_path / "fit.toml", tmp_path / "fit.json"
    code = fit_main([str(described / "good.csv"), str(described / "other.csv"), "--log-format",
                     str(described / "log.toml"), "--fidelity", "compliant", "--out", str(out), "--json", str(js)])
    text = capsys.readouterr()
    assert code == 0, text.err
    plant = load_axis_plant(out)
    truth = _truth_vector()
    assert plant.second_mass is not None
    for k in ("axis.mass_kg", "axis.load_mass_kg", "axis.load_stiffness_n_per_um"):
        assert plant.values[k] == pytest.approx(truth[k], rel=0.01)
        assert plant.sources[k].startswith("fit: good.csv")
    import json

    rep = json.loads(js.read_text())
    assert rep["structure"] == "two-mass"
    assert rep["validation"]["passes"] is True
    assert set(rep["validation"]["cross_validation"]) == {str(described / "good.csv"), str(described / "other.csv")}
    assert rep["parameters"]["axis.axial_damping_ratio"]["value"] == pytest.approx(TRUTH["zeta"], rel=0.1)
    assert "validated:" in text.out
    assert "mode_hz" in text.out
    assert text.out.count("left out: ") == 2


@pytest.mark.slow  # two fits of the three-mass log (about 10 s of CPU each)
def test_prsa_fit_compliant_refuses_a_plant_that_does_not_explain_the_log(described, tmp_path, capsys):
    """A third mass (30 kg on 8 N/um beyond the load mass) the model has not, under the rule as users
    get it (prsa_ctrl.identification.axisvalidation). The closed-loop replay is at 1.7 x the log's
    noise floor and fits 99.6 % (the speed loop hides the third mode: the screw path's rule alone
    passed it), but 58 % of the residual lies near 112 Hz, above the floor, and 38 % of it is
    predicted by the test signal and the reference: exit 3, one line naming a further mode, no plant
    file; --force writes it with a header that says so. The same seed without the third mass fits
    (test_prsa_fit_compliant_writes_a_validated_two_mass_plant: good.csv)."""
    out = tmp_path / "fit.toml"
    _write_csv(tmp_path / "three.csv", two_mass_log(4, third=(30.0, 8.0e6)))
    args = [str(tmp_path / "three.csv"), "--log-format", str(described / "log.toml"), "--fidelity", "compliant",
            "--out", str(out)]
    code = fit_main(args)
    err = capsys.readouterr().err
    assert code == 3
    assert not out.exists()
    assert "does not explain the data" in err
    assert "most likely missing physics: a further mode" in err
    assert len([x for x in err.splitlines() if x.startswith("prsa-fit:")]) == 1
    assert fit_main([*args, "--force"]) == 3
    text = out.read_text()
    assert "NOT VALIDATED" in text.split("[axis]")[0]
    assert load_axis_plant(out).second_mass is not None


def test_frf_needs_the_compliant_fit(described, tmp_path, capsys):
    """--frf starts the second mass: refused with the rigid fit (--force is for either fit since the
    rigid fit is validated too: tests/identification/test_axisvalidation.py)."""
    code = fit_main([str(described / "good.csv"), "--log-format", str(described / "log.toml"), "--out",
                     str(tmp_path / "x.toml"), "--frf", str(described / "log.toml")])
    assert code == 2
    assert "expected it with --fidelity compliant" in capsys.readouterr().err


@pytest.mark.slow  # one two-mass fit that ends far off (about 8 s of CPU)
def test_a_log_that_cannot_determine_the_friction_is_refused_naming_the_fit_and_the_remedy():
    """Seed 14 (one log: +x at one speed, -x barely): the fit ends with Fc+ near 0 and Fv+ ten times the
    truth (Fv-, Fc- held at +x's start) and is refused; the diagnosis names the fit's law, why the log
    cannot determine it and the remedy (was: "friction that changes along the travel", which the
    generator does not have)."""
    log = _log(14)
    fit = fit_two_mass_axis([log], _base(log))
    assert not fit.passes
    line = fit.validation["diagnosis"]
    assert line.startswith("friction as fitted, not missing physics: in syn"), line
    assert "along the travel" not in line
    assert "syn barely moves the axis in -x" in line
    assert "friction.coulomb_negative_n held at friction.coulomb_positive_n's start" in line
    assert line.endswith("remedy: a log that moves the axis both ways, over a range of speeds")
