"""Drive export: the exported discrete controller reproduces the simulated sampled loop."""

import json
import math
import tomllib

import control
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from prsa_ctrl import PID, load_plant, run
from prsa_ctrl.io.export import DISCRETISATIONS, dumps, export_controller, pid_biquad
from prsa_ctrl.drive.filters import FirstOrderLowPass, Notch, SecondOrderLowPass

PLANT = load_plant()
TS = PLANT.sample_time_s


def _exported_law(d, setpoint, measured, integral0, speed_prev0):
    """The drive's speed PID run from the exported dict only (its stated equations)."""
    law = d["speed_controller"]["discrete"]
    ts, kp, ki, kd = law["sample_time_s"], law["kp_n_m_s_per_rad"], law["ki_n_m_per_rad"], law["kd_n_m_s2_per_rad"]
    beta, k_aw, lim = law["beta"], law["anti_windup_gain_per_s"], law["torque_limit_n_m"]
    tau_ff, b = law["feedforward_torque_n_m"], law["setpoint_weight"]
    integral, deriv, w_prev = integral0, 0.0, speed_prev0
    out = np.empty(len(measured))
    for k, (ref, w) in enumerate(zip(setpoint, measured)):
        e = ref - w
        deriv = beta * deriv + (1 - beta) * (w - w_prev) / ts
        u = kp * (b * ref - w) + integral - kd * deriv + tau_ff
        us = min(max(u, -lim), lim)
        integral += ts * (ki * e + k_aw * (us - u))
        w_prev = w
        out[k] = us
    return out


def _round_trip(pid, duration=0.03, load=((0, 500.0), (0.0101, 1500.0)), saturated=False):
    r = run(PLANT, load=list(load), duration=duration, controller=pid, fidelity="rigid", discrete=True)
    u_sim = r.output("torque_command")
    at_limit = np.sum(np.abs(u_sim) >= PLANT.torque_limit * (1 - 1e-12))
    assert (at_limit > 10) if saturated else (at_limit == 0)
    assert np.ptp(u_sim) > 0.3  # the load step moved the command (about 0.5 N m unsaturated)
    d = export_controller(pid, PLANT, fmt="toml")
    d = tomllib.loads(dumps(d, "toml"))  # from the written file
    u = _exported_law(d, r.inputs[0], r.output("speed_measured"), r.states[r.state_labels.index("pid_integral"), 0],
                      r.output("nut_speed")[0])
    # the command computed at sample k is the one applied during sample k + 1
    return np.max(np.abs(u[:-1] - u_sim[1:]))


@pytest.mark.parametrize("pid", [PID(0.085, 14.7), PID(0.06, 9.0, kd=2e-5, tf=5e-4)], ids=["PI", "PID"])
def test_exported_discrete_law_reproduces_the_sampled_run(pid):
    assert _round_trip(pid) < 1e-9


@pytest.mark.parametrize("b", [0.0, 0.5])
def test_setpoint_weight_round_trip_against_the_prefiltered_run(b):
    """A 2-DOF setpoint weight b != 1: the exported law ``u = kp (b r - y) + I`` on the raw
    setpoint gives the command of the simulated loop, which runs the 1-DOF PI on the setpoint
    through autotune.setpoint_prefilter (as the duty-cycle verification does)."""
    from prsa_ctrl.studies.autotune import setpoint_prefilter
    from prsa_ctrl.sim.signals import PiecewiseLinear

    pid = PID(0.085, 14.7)
    n = 160
    t = np.arange(n) * TS
    r_raw = np.where(t >= 0.01, 40.0, 30.0)  # a 10 rad/s setpoint step at sample 40
    rf = setpoint_prefilter(r_raw, pid, TS, b)
    assert np.max(np.abs(rf - r_raw)) > 1.0  # the weight changes the setpoint seen by the PI
    r = run(PLANT, setpoint=PiecewiseLinear(tuple(zip(t.tolist(), rf.tolist()))), load=500.0,
            duration=n * TS, controller=pid, fidelity="rigid", discrete=True)
    u_sim = r.output("torque_command")[:n]
    assert np.max(np.abs(u_sim)) < PLANT.torque_limit
    assert np.ptp(u_sim) > 0.1  # moved by the step, unsaturated
    assert np.allclose(r.inputs[0][: u_sim.size], rf[: u_sim.size], rtol=0, atol=1e-9)
    for fmt in ("toml", "json"):
        d = export_controller(pid, PLANT, fmt=fmt, setpoint_weight=b)
        d = tomllib.loads(dumps(d, "toml")) if fmt == "toml" else json.loads(dumps(d, "json"))
        assert d["speed_controller"]["continuous"]["setpoint_weight"] == b
        assert "setpoint_weight" in d["units"]
        # Both start in steady state at the command u0: the 1-DOF integral is u0, the 2-DOF
        # one u0 - kp (b - 1) r0 (the proportional term is kp (b - 1) r0 there).
        u0 = r.states[r.state_labels.index("pid_integral"), 0]
        u = _exported_law(d, r_raw[: u_sim.size], r.output("speed_measured")[: u_sim.size],
                          u0 - pid.kp * (b - 1) * r_raw[0], r.output("nut_speed")[0])
        assert np.max(np.abs(u[:-1] - u_sim[1:])) < 1e-9
    # ... and the 1-DOF export (b = 1) does not reproduce it.
    d1 = export_controller(pid, PLANT, fmt="json")
    u1 = _exported_law(d1, r_raw[: u_sim.size], r.output("speed_measured")[: u_sim.size], u0, r.output("nut_speed")[0])
    assert np.max(np.abs(u1[:-1] - u_sim[1:])) > 0.1


def test_round_trip_holds_through_saturation():
    """A 9 kN load pulse drives the command into the 3 N m limit: the anti-windup path of the
    exported law (k_aw = ki/kp) reproduces the simulated command too."""
    err = _round_trip(PID(0.085, 14.7), duration=0.04, load=((0, 500.0), (0.0101, 9000.0), (0.02, 500.0)),
                      saturated=True)
    assert err < 1e-9


@settings(max_examples=15, deadline=None, derandomize=True)
@given(kp=st.floats(0.04, 0.15), ki=st.floats(2.0, 25.0), kd=st.sampled_from([0.0, 1e-5, 3e-5]),
       tf=st.floats(2.5e-4, 2e-3))
def test_hypothesis_round_trip_over_gains(kp, ki, kd, tf):
    assert _round_trip(PID(kp, ki, kd=kd, tf=tf), duration=0.02) < 1e-9


def _coeffs(tfz):
    num, den = np.trim_zeros(np.asarray(tfz.num[0][0], float), "f"), np.asarray(tfz.den[0][0], float)
    return num / den[0], den / den[0]


def _pad(v):
    return np.concatenate([v, np.zeros(3 - len(v))])


@pytest.mark.parametrize("pid", [PID(0.085), PID(0.085, 14.7), PID(0.06, 9.0, kd=2e-5, tf=5e-4),
                                 PID(0.06, 0.0, kd=2e-5, tf=5e-4)], ids=["P", "PI", "PID", "PD"])
@pytest.mark.parametrize("method, c2d", [("forward_euler", "euler"), ("backward_euler", "backward_diff"),
                                         ("tustin", "tustin")])
def test_alternative_forms_match_python_control_c2d(pid, method, c2d):
    d = export_controller(pid, PLANT, fmt="json")
    got = d["speed_controller"]["alternatives"][method]
    cz = control.sample_system(pid.to_tf(), TS, c2d)
    num, den = _coeffs(cz)
    mine = np.r_[[got[k] for k in ("b0", "b1", "b2")], 1.0, got["a1"], got["a2"]]
    if pid.ki > 0 or pid.kd > 0:  # (python-control keeps a P as 0.085 (z - 1)/(z - 1))
        ref = np.r_[_pad(num), _pad(den)]
        assert np.max(np.abs(mine - ref)) <= 1e-12 * np.max(np.abs(ref))
    z = np.exp(1j * 2 * math.pi * np.geomspace(1.0, 0.45 / TS, 100) * TS)
    c_z = (got["b0"] + got["b1"] / z + got["b2"] / z**2) / (1 + got["a1"] / z + got["a2"] / z**2)
    np.testing.assert_allclose(c_z, cz(z), rtol=1e-12)
    assert got["substitution"] == DISCRETISATIONS[method][0]


@settings(max_examples=40, deadline=None, derandomize=True)
@given(kp=st.floats(1e-3, 10.0), ki=st.floats(0.0, 1e3), kd=st.floats(0.0, 1e-3), tf=st.floats(1e-4, 1e-2),
       ts=st.floats(5e-5, 1e-3))
def test_hypothesis_exported_forms_equal_the_pid_transfer_functions(kp, ki, kd, tf, ts):
    pid = PID(kp, ki, kd=kd, tf=tf)
    # the simulator's law, from the exported numbers, equals PID.to_tf(dt) (the tuner's model)
    law = export_controller(pid, PLANT, fmt="json")["speed_controller"]["discrete"]
    ts_l = law["sample_time_s"]
    z = np.exp(1j * 2 * math.pi * np.geomspace(1.0, 0.45 / ts_l, 50) * ts_l)
    law_terms = np.array([np.full_like(z, law["kp_n_m_s_per_rad"]), law["integral_gain_ts_ki_n_m_s_per_rad"] / (z - 1),
                          law["kd_n_m_s2_per_rad"] * (1 - law["beta"]) * (z - 1) / (ts_l * (z - law["beta"]))])
    c_law = law_terms.sum(axis=0)
    tf_z = pid.to_tf(ts_l)
    num, den = np.asarray(tf_z.num[0][0], float), np.asarray(tf_z.den[0][0], float)
    # The polynomial form loses digits near z = 1 (integrator, slow derivative pole): bound the
    # difference by the conditioning of both evaluations (a wrong law is off by O(1)).
    kappa = (np.polyval(np.abs(num), np.abs(z)) / np.abs(np.polyval(num, z))
             + np.polyval(np.abs(den), np.abs(z)) / np.abs(np.polyval(den, z)))
    err = np.abs(c_law - tf_z(z)) / np.abs(law_terms).sum(axis=0)
    assert np.all(err < 1e-10 + 100 * np.finfo(float).eps * kappa), float(err.max())
    # the substitution forms equal C(s) at s = N(z)/(Ts D(z))
    for name, (_, (n1, n0), (d1, d0)) in DISCRETISATIONS.items():
        c = pid_biquad(pid, ts, name)
        zz = np.exp(1j * 2 * math.pi * np.geomspace(1.0, 0.45 / ts, 50) * ts)
        s = (n1 * zz + n0) / (ts * (d1 * zz + d0))
        terms = np.array([np.full_like(s, kp), ki / s, kd * s / (1 + tf * s)])
        c_s = terms.sum(axis=0)
        c_z = (c["b0"] + c["b1"] / zz + c["b2"] / zz**2) / (1 + c["a1"] / zz + c["a2"] / zz**2)
        # Two evaluations of a sum whose terms can cancel: the rounding error scales with the
        # terms' magnitudes, not with their (possibly much smaller) sum, and the biquad's own
        # evaluation near z = 1 (integrator, slow derivative pole) has the condition number
        # kappa of its numerator and denominator polynomials; a wrong formula is off by O(Ts).
        num = c["b0"] + c["b1"] / zz + c["b2"] / zz**2
        den = 1 + c["a1"] / zz + c["a2"] / zz**2
        kappa = ((abs(c["b0"]) + abs(c["b1"]) + abs(c["b2"])) / np.abs(num)
                 + (1 + abs(c["a1"]) + abs(c["a2"])) / np.abs(den))
        err = np.abs(c_z - c_s) / np.abs(terms).sum(axis=0)
        bound = 1e-9 + 100 * np.finfo(float).eps * kappa
        assert np.all(err < bound), (name, err.max(), float(np.max(err / bound)))


@pytest.mark.parametrize("pid", [PID(0.085), PID(0.085, 14.7), PID(0.06, 9.0, kd=2e-5, tf=5e-4),
                                 PID(0.06, 0.0, kd=2e-5, tf=5e-4)], ids=["P", "PI", "PID", "PD"])
def test_error_biquad_is_the_simulated_law(pid):
    """The exported biquad of the simulated law equals PID.to_tf(dt) (the sampled C(z))."""
    got = export_controller(pid, PLANT, fmt="toml")["speed_controller"]["discrete"]["error_biquad"]
    num, den = _coeffs(pid.to_tf(TS))
    mine = np.r_[[got[k] for k in ("b0", "b1", "b2")], 1.0, got["a1"], got["a2"]]
    ref = np.r_[_pad(num), _pad(den)]
    assert np.max(np.abs(mine - ref)) <= 1e-12 * np.max(np.abs(ref))


def test_vendor_and_per_unit_forms():
    pid = PID(0.085, 14.7, kd=1e-5, tf=5e-4)
    d = export_controller(pid, PLANT, fmt="json", rated_torque_n_m=3.0, rated_speed_rpm=3000.0)
    v, pu = d["speed_controller"]["vendor"], d["speed_controller"]["per_unit"]
    assert v["kp_n_m_s_per_rad"] == 0.085
    assert v["tn_s"] == pytest.approx(0.085 / 14.7, rel=1e-15)
    assert v["tv_s"] == pytest.approx(1e-5 / 0.085, rel=1e-15)
    assert v["kp_n_m_per_rpm"] == pytest.approx(0.085 * 2 * math.pi / 60, rel=1e-15)
    assert v["kv_per_s"] is None
    assert "position loop" in v["note"]
    w_r = 3000.0 * 2 * math.pi / 60
    assert pu["kp_pu"] == pytest.approx(0.085 * w_r / 3.0, rel=1e-15)
    assert pu["ki_pu_per_s"] == pytest.approx(14.7 * w_r / 3.0, rel=1e-15)
    law = d["speed_controller"]["discrete"]
    assert law["beta"] == math.exp(-TS / 5e-4)
    assert law["anti_windup_gain_per_s"] == pytest.approx(14.7 / 0.085, rel=1e-15)
    assert law["computation_delay_samples"] == 1
    assert d["sample_time_s"] == TS
    assert d["plant"] == PLANT.name
    assert d["prsa_ctrl_version"]
    m = d["speed_measurement"]
    a = math.exp(-TS / PLANT.speed_filter_s)
    assert m["a"] == a
    assert m["biquad"]["a1"] == pytest.approx(-a, rel=1e-15)
    assert m["biquad"]["b0"] == pytest.approx(1 - a, rel=1e-15)
    # the P controller has no reset time: null in JSON, absent in TOML (no null there)
    assert export_controller(PID(0.085), PLANT, fmt="json")["speed_controller"]["vendor"]["tn_s"] is None
    t = export_controller(PID(0.085), PLANT, fmt="toml")["speed_controller"]["vendor"]
    assert "tn_s" not in t
    assert "kv_per_s" not in t


def test_text_round_trips_and_filters():
    filters = [Notch(1200.0, 300.0, -20.0), ("speed_measurement", SecondOrderLowPass(1500.0, 0.7)),
               ("torque_command", FirstOrderLowPass(900.0))]
    pid = PID(0.085, 14.7, kd=1e-5, tf=5e-4)
    dt = export_controller(pid, PLANT, fmt="toml", rated_torque_n_m=3.0, rated_speed_rpm=3000.0, filters=filters)
    text = dumps(dt, "toml")
    assert tomllib.loads(text) == dt
    dj = export_controller(pid, PLANT, fmt="json", filters=filters)
    assert json.loads(dumps(dj, "json")) == dj
    f = dt["filters"]
    assert [x["place"] for x in f] == ["torque_command", "speed_measurement", "torque_command"]
    assert f[0]["biquad_tustin_prewarped"] == Notch(1200.0, 300.0, -20.0).biquad(TS).as_dict()
    assert f[2]["biquad_matched"] == FirstOrderLowPass(900.0).biquad(TS, "matched").as_dict()
    with pytest.raises(ValueError, match=r"kv_per_s = None; expected a number, string, bool or list"):
        dumps({"a": {"kv_per_s": None}}, "toml")


@pytest.mark.parametrize("kwargs, match", [
    ({"fmt": "yaml"}, r"fmt = 'yaml'; expected one of json, toml"),
    ({"fmt": "toml", "rated_torque_n_m": -1.0, "rated_speed_rpm": 3000.0}, r"rated_torque_n_m = -1.0; expected"),
    ({"fmt": "toml", "rated_torque_n_m": 3.0}, r"expected both \(for the per-unit gains\) or neither"),
    ({"fmt": "toml", "filters": ["notch"]}, r"filters entry 'notch'; expected a Filter or a \(place, Filter\)"),
    ({"fmt": "toml", "filters": [("speed", Notch(100.0, 10.0))]}, r"filters entry \('speed'"),
    ({"fmt": "toml", "filters": [Notch(2100.0, 100.0)]}, r"notch frequency 2100 Hz at ts = 0.00025 s; expected "
                                                         r"below the Nyquist frequency 2000 Hz"),
    ({"fmt": "toml", "setpoint_weight": 1.5}, r"setpoint_weight = 1\.5; expected a setpoint weight b in \[0, 1\]"),
])
def test_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match) as info:
        export_controller(PID(0.085, 14.7), PLANT, **kwargs)
    assert "\n" not in str(info.value)
    with pytest.raises(ValueError, match=r"PID kff = 0.5; expected 0"):
        export_controller(PID(0.085, 14.7, kff=0.5), PLANT, fmt="json")
    with pytest.raises(ValueError, match=r"ts = 0; expected a finite sample time > 0 s"):
        pid_biquad(PID(0.085), 0, "tustin")
    with pytest.raises(ValueError, match=r"method = 'zoh'; expected one of forward_euler, backward_euler, tustin"):
        pid_biquad(PID(0.085), TS, "zoh")
    with pytest.raises(ValueError, match=r"pid = 0.085; expected a prsa_ctrl.PID"):
        export_controller(0.085, PLANT, fmt="json")
    with pytest.raises(ValueError, match=r"fmt = 'xml'"):
        dumps({}, "xml")


# --- inert text: hostile names in TOML and JSON (issue 36) ----------------------------------------

HOSTILE = ('Axis 3 */ __asm__("id"); /* rev B', "emoji \U0001F600 axis", "line\nbreak\r\n[table]\nx = 1",
           'q"uote\'d \\ back\\slash', "cdata ]]> (* *) --", "ctrl \x00\x07\x1b\x7f\u2028 end", "\U0010FFFF")


@pytest.mark.parametrize("name", HOSTILE)
def test_hostile_plant_name_round_trips_in_toml_and_json(name):
    """A plant name with any of these characters (a non-BMP emoji made the TOML unparseable
    before) parses back to the same name from TOML and JSON, for the speed export and the
    cascade, and adds no key or table to the file."""
    from prsa_ctrl.drive.measurement import PositionLoop
    from prsa_ctrl.io.export import export_cascade
    from prsa_ctrl.tuning.cascade import CascadeDesign

    plant = PLANT.with_params({}, name=name)
    for fmt in ("toml", "json"):
        for d in (export_controller(PID(0.085, 14.7), plant, fmt=fmt, filters=[Notch(1200.0, 300.0, -20.0)],
                                    design={"name": name, "why": name}),
                  export_cascade(CascadeDesign("joint", PID(0.0771, 7.07), PositionLoop(kv=102.7), {}, {}, {}, 0.0),
                                 plant, fmt=fmt)):
            text = dumps(d, fmt)
            back = tomllib.loads(text) if fmt == "toml" else json.loads(text)
            assert back == d
            assert back["plant"] == name
            if fmt == "toml":  # ASCII only, and one line per scalar: nothing of the name begins a line
                assert all(ord(c) < 128 for c in text)
                assert "\nx = 1" not in text
                assert "\n[table]" not in text


def test_toml_strings_refuse_lone_surrogates_and_keep_non_ascii_when_asked():
    from prsa_ctrl.io.export import toml_string, toml_value

    assert tomllib.loads("x = " + toml_value("µ \U0001F600 \x7f", ascii_only=False))["x"] == "µ \U0001F600 \x7f"
    assert toml_string("\U0001F600") == '"\\U0001F600"'
    with pytest.raises(ValueError, match="lone surrogate U\\+D800"):
        toml_string("a\ud800")
    with pytest.raises(ValueError):
        dumps({"plant": "a\udfff"}, "toml")


# --- what the gains assume, in every export (issue 36) -------------------------------------------

def test_every_export_states_its_assumptions(tmp_path):
    """The TOML/JSON exports, a filled parameter set and the C, ST and XML headers state the loop
    period, inertia, current-loop bandwidth, delay (samples and seconds), encoder resolution,
    each filter's discretisation and what changes if the drive's rates differ, with the plant's
    numbers (a plant with 2345 Hz and two drive delay samples shows them)."""
    from prsa_ctrl.drive.filters import LoopFilter
    from prsa_ctrl.drive.measurement import PositionLoop
    from prsa_ctrl.io.codegen import c_code, drive_law, st_code
    from prsa_ctrl.io.driveparams import dumps_parameter_set, fill_template
    from prsa_ctrl.io.export import export_cascade
    from prsa_ctrl.io.plcopen import plcopen_xml
    from prsa_ctrl.tuning.cascade import CascadeDesign

    plant = PLANT.with_params({"drive.current_loop_bandwidth_hz": 2345.0, "drive.command_delay_samples": 2})
    filters = [LoopFilter(Notch(1200.0, 300.0, -20.0), "torque_command"),
               LoopFilter(FirstOrderLowPass(800.0), "speed_measurement", method="zoh")]
    pos = PositionLoop(kv=102.7, kvff=1.0, kaff=1.0, rate=2)
    tables = [tomllib.loads(dumps(export_controller(PID(0.085, 14.7), plant, fmt="toml", filters=filters), "toml")),
              json.loads(dumps(export_cascade(CascadeDesign("j", PID(0.0771, 7.07), pos, {}, {}, {}, 0.0), plant,
                                              fmt="json"), "json")),
              tomllib.loads(dumps_parameter_set(fill_template("generic", PID(0.085, 14.7), plant)))]
    for d in tables:
        a = d["assumptions"]
        assert a["loop_period_s"] == TS
        assert a["current_loop_bandwidth_hz"] == 2345.0
        assert a["reflected_inertia_kg_m2"] == plant.reflected_inertia_kg_m2
        assert a["command_delay_samples"] == 3
        assert a["command_delay_s"] == pytest.approx(3 * TS, rel=1e-15)
        assert a["encoder_counts_per_rev"] == plant.encoder_counts
        assert "re-export" in a["if_rates_differ"]
        assert a["sources"]["drive.current_loop_bandwidth_hz"] == plant.sources["drive.current_loop_bandwidth_hz"]
    assert [f.split(":")[-1].strip() for f in tables[0]["assumptions"]["filters"]] == [
        "Tustin prewarped at 1200 Hz", "zero-order hold (step invariant)"]
    assert tables[1]["assumptions"]["position_loop_period_s"] == 2 * TS
    law = drive_law(PID(0.085, 14.7), plant, filters=filters, position=pos)
    for text in (c_code(law)[0], c_code(law)[1], st_code(law), plcopen_xml(law)):
        for needle in ("loop period: Ts = 0.00025 s (4000 Hz)", "current-loop bandwidth: 2345 Hz",
                       f"reflected inertia: J = {plant.reflected_inertia_kg_m2:.6g} kg m^2",
                       "command delay: 3 sample(s) = 0.00075 s", "encoder resolution: 1048576 counts/rev",
                       "Tustin prewarped at 1200 Hz", "zero-order hold", "if the drive's rates differ",
                       "position loop: every 2 sample(s)"):
            assert needle in text, needle


@pytest.mark.parametrize("delay", [0, 2])
def test_cascade_exports_and_parameter_sets_carry_the_position_delay(delay):
    """The position loop's own computation delay is part of what the gains assume: the cascade
    export and a vendor parameter set of the same design say it in samples and seconds."""
    from prsa_ctrl.drive.measurement import PositionLoop
    from prsa_ctrl.io.driveparams import dumps_parameter_set, fill_template
    from prsa_ctrl.io.export import export_cascade
    from prsa_ctrl.tuning.cascade import CascadeDesign

    design = CascadeDesign("j", PID(0.0771, 7.07), PositionLoop(kv=102.7, kvff=1.0, kaff=1.0, rate=2, delay=delay),
                           {}, {}, {}, 0.0)
    for a in (json.loads(dumps(export_cascade(design, PLANT, fmt="json"), "json"))["assumptions"],
              tomllib.loads(dumps_parameter_set(fill_template("generic", design, PLANT)))["assumptions"]):
        assert a["position_delay_samples"] == delay
        assert a["position_delay_s"] == pytest.approx(delay * 2 * TS, rel=1e-15)
