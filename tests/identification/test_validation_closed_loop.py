"""The closed-loop replay of a screw-driven plant from a described controller and reference
(prsa_ctrl.identification.validation.closed_loop_replay), on a log from a generator written here:
a rigid ball-screw axis in numpy (RK4, the nut loss on the whole force through the nut solved by
fixed-point iteration, tanh-smoothed friction sign), under the position-P / velocity-PI law of
prsa_ctrl.identification.logformat, the command computed at k acting from k + 1."""

import math
import warnings

import numpy as np
import pytest

from prsa_ctrl import GeometryWarning, load_plant
from prsa_ctrl.identification.data import record_from_arrays
from prsa_ctrl.identification.logformat import ControllerSpec
from prsa_ctrl.identification.validation import CLOSED_LOOP_MODE, ClosedLoop, closed_loop_replay, explained

KP, KV, KI = 50.0, 2.5e5, 30.0  # 1/s, N/(m/s), 1/s: ~40 Hz velocity loop on ~1000 kg reflected


def _generate(v, n=6000, seed=0):
    """Rigid ball screw (motor coordinates inside, load coordinates logged); ``v``: plant values."""
    rng = np.random.default_rng(seed)
    ts = v["ts"]
    a = v["lead"] / (2 * math.pi)
    jt = v["jm"] + v["js"] + v["m"] * a * a
    tc = 1.0 / (2 * math.pi * v["fc"])
    q_res = 2 * math.pi / 2**20
    t = np.arange(n) * ts
    ref = 0.048 * t + 0.0005 * np.sin(2 * math.pi * 5 * t) + 0.0001 * np.sin(2 * math.pi * 23 * t)
    load = np.where(t < 0.25, 500.0, np.where(t < 0.5, 3000.0, 1200.0))

    def rates(x, u, f):
        w, tq = x[1], x[2]
        s = math.tanh(w / 0.05)
        dw = 0.0
        for _ in range(30):  # fixed point: the loss on |F_s|, F_s = F + m a w'
            fs = f + v["m"] * a * dw
            dw = (tq - a * f - v["b"] * w - s * (v["t0"] + (1 / v["eta"] - 1) * a * abs(fs))) / jt
        return np.array([w, dw, (u - tq) / tc])

    x = np.array([0.0, 0.048 / a, 0.0])
    pos, cmd = np.empty(n), np.empty(n)
    integ, pending = 0.0, 0.0
    for k in range(n):
        th_meas = math.floor(x[0] / q_res) * q_res
        q = a * th_meas
        pos[k] = q
        if k == 0:
            q_prev = q  # the law's start: no velocity estimate before the first sample
        dq = (q - q_prev) / ts
        q_prev = q
        ev = KP * (ref[k] - q) - dq
        integ += KI * ts * ev
        u = min(max(KV * (ev + integ), -8000.0), 8000.0)
        cmd[k] = u
        tq_cmd = pending * a  # computed at k - 1, acts from k
        pending = u
        h = ts / 4
        for _ in range(4):
            k1 = rates(x, tq_cmd, load[k])
            k2 = rates(x + 0.5 * h * k1, tq_cmd, load[k])
            k3 = rates(x + 0.5 * h * k2, tq_cmd, load[k])
            k4 = rates(x + h * k3, tq_cmd, load[k])
            x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return t, pos, cmd, ref, load + 2.0 * rng.standard_normal(n)


@pytest.fixture(scope="module")
def setup():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeometryWarning)
        base = load_plant("ballscrew-32x10")
    vals = {"ts": base.sample_time_s, "lead": 0.01, "jm": 1.2e-3, "js": base.values["axis.screw_inertia_kg_m2"],
            "m": 200.0, "fc": 2000.0, "b": 5e-4, "t0": 0.3, "eta": 0.9}
    t, pos, cmd, ref, load = _generate(vals)
    a = base.lead_per_rad
    rec = record_from_arrays("closed", t, cmd * a, nut_angle_rad=pos / a, axial_load_n=load)
    ctl = ControllerSpec(structure="position-p/velocity-pi", kp=KP, kv=KV, ki=KI, velocity_estimate="difference",
                         saturation=8000.0, sample_time_s=vals["ts"], command_delay_samples=1, check_tolerance=0.05,
                         sources={})
    return base, rec, ClosedLoop(ctl, ref, None, 1.0, "as-computed")


def test_the_true_plant_replays_the_closed_loop(setup):
    base, rec, cl = setup
    e = closed_loop_replay(base, rec, cl, shift=1)
    assert e["replay"] == CLOSED_LOOP_MODE and e["finite"]
    assert e["fit_percent"] > 95.0 and explained(e)


def test_a_wrong_plant_replays_the_closed_loop_worse(setup):
    """The closed loop hides an inertia error below its bandwidth, so the test is relative: a plant
    with twice the rotor inertia and the old nut law replays clearly worse than the truth."""
    base, rec, cl = setup
    good = closed_loop_replay(base, rec, cl, shift=1)
    bad = closed_loop_replay(base.with_params({"axis.motor_inertia_kg_m2": 4 * 1.2e-3, "friction.efficiency": 0.6}),
                             rec, cl, shift=1)
    assert bad["error_rms_rad_s"] > 2.0 * good["error_rms_rad_s"]
    late = closed_loop_replay(base, rec, cl, shift=3)  # the wrong delay, too
    assert late["error_rms_rad_s"] > good["error_rms_rad_s"]


FORMAT = """axis = "linear"
[time]
name = "time_s"
unit = "s"
[position]
name = "position_m"
unit = "m"
[reference]
name = "reference_m"
unit = "m"
[command]
name = "force_n"
unit = "N"
logged = "as-computed"
[load]
name = "load_n"
unit = "N"
[controller]
structure = "position-p/velocity-pi"
kp = 50.0
kv = 2.5e5
ki = 30.0
velocity_estimate = "difference"
saturation = 8000.0
sample_time_s = 1.25e-4
command_delay_samples = 1
"""


@pytest.mark.slow
def test_cli_validates_a_described_log_in_closed_loop(setup, tmp_path, capsys):
    """prsa-fit LOG --log-format F --plant ballscrew-32x10: the log's controller and reference are
    described, so the validation replays the closed loop (the report says so) and passes."""
    import json

    from prsa_ctrl.cli.fit import main

    base, rec, cl = setup
    a = base.lead_per_rad
    log = tmp_path / "log.csv"
    rows = ["time_s,position_m,reference_m,force_n,load_n"]
    rows += [f"{t:.17g},{q:.17g},{r:.17g},{f:.17g},{l:.17g}" for t, q, r, f, l in
             zip(rec.time_s, rec.nut_angle_rad * a, cl.reference_m, rec.torque_command_n_m / a, rec.axial_load_n)]
    log.write_text("\n".join(rows) + "\n")
    fmt = tmp_path / "log.toml"
    fmt.write_text(FORMAT)
    out, js = tmp_path / "fit.toml", tmp_path / "fit.json"
    code = main([str(log), "--log-format", str(fmt), "--plant", "ballscrew-32x10", "--out", str(out), "--json", str(js)])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    v = json.loads(js.read_text())["solver"]["validation"]
    assert v["replay_per_log"][str(log)] == CLOSED_LOOP_MODE and v["passes"]
    assert v["written_plant"][str(log)]["fit_percent"] > 95.0
    assert "closed-loop replay from the reference" in cap.out
