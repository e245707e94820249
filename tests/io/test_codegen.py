"""Generated controller code (prsa_ctrl.io.codegen) against the simulator's own per-sample law.

Recorded sampled runs of the paper load-step scene and of the paper move scene give the inputs
(encoder counts, references) and the torque command the simulator applied. The Python
reference law, the C code compiled with the system compiler and the Structured Text (compiled by matiec's
iec2c, the IEC 61131-3 compiler behind Beremiz and OpenPLC, and its C run) each reproduce that
command sequence; the ST's C equals the toolkit's C bit for bit on hostile sequences too.
"""

from __future__ import annotations

import ctypes
import dataclasses
import math
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from prsa_ctrl import PID
from prsa_ctrl.studies.move import simulate_move
from prsa_ctrl.studies.movescene import load_move_scene
from prsa_ctrl.io.codegen import (DriveLaw, ReferenceLaw, c_code, drive_law, export_code, max_relative_difference,
                               replay_inputs, st_code)
from prsa_ctrl.drive.filters import FirstOrderLowPass, LoopFilter, Notch
from prsa_ctrl.drive.friction import FrictionFeedforward
from prsa_ctrl.drive.measurement import PositionLoop
from prsa_ctrl.studies.scene import load_scene
from prsa_ctrl.sim.engine import run

REL = 1e-12  # the bound: max |difference| / max |recorded command|, double
SPEED_PID = PID(0.085, 14.7, kd=2e-5, tf=5e-4)
MOVE_PID = PID(0.0771, 7.07)
FILTERS = (LoopFilter(Notch(1200.0, 300.0, -20.0), "torque_command"),
           LoopFilter(FirstOrderLowPass(800.0), "speed_measurement"))


@pytest.fixture(scope="module")
def plant(paper_plant):
    return paper_plant


@pytest.fixture(scope="module")
def load_step(plant):
    """The paper scene paper-load-step (300 rpm, 500 -> 1500 N at 0.2 s), sampled, compliant
    model, with a speed-measurement low-pass and a torque-command notch; 0.3 s (0.1 s after the step)."""
    sc = load_scene("paper-load-step")
    r = run(plant, setpoint=sc.setpoint_rpm * 2 * math.pi / 60, load=[(0.0, sc.initial_load), (sc.step_time,
            sc.final_loads[0])], duration=0.3, controller=SPEED_PID, fidelity="compliant", discrete=True,
            filters=FILTERS)
    law = drive_law(SPEED_PID, plant, filters=FILTERS)
    return law, replay_inputs(r, plant), r


@pytest.fixture(scope="module")
def move(plant):
    """The paper move scene (10 mm S-curve at 30 mm/s, 1500 N mid-move, 1500 N step while holding)."""
    sc = load_move_scene("paper-move")
    pos = PositionLoop(kv=102.7, kvff=1.0, kaff=1.0, measured=sc.measured, rate=sc.position_rate)
    r = simulate_move(plant, sc, MOVE_PID, pos)
    law = drive_law(MOVE_PID, plant, position=pos)
    return law, replay_inputs(r, plant, sc.motion(), pos), r


@pytest.fixture(scope="module")
def move_scale(plant):
    """A move measured by a linear scale, position loop every 3rd sample with an integral, and filters."""
    sc = load_move_scene("paper-move")
    pos = PositionLoop(kv=60.0, ki=50.0, kvff=1.0, kaff=0.8, measured="screw_position", rate=3)
    r = run(plant, load=sc.loads()[:2], duration=0.25, controller=MOVE_PID, fidelity="compliant", discrete=True,
            position=pos, motion=sc.motion(), filters=FILTERS)
    law = drive_law(MOVE_PID, plant, position=pos, filters=FILTERS)
    return law, replay_inputs(r, plant, sc.motion(), pos), r


@pytest.fixture(scope="module")
def move_delay(plant):
    """A move with the position loop every 2nd sample and its own computation delay of 2
    position-loop samples (issue 34), a position PI and filters."""
    sc = load_move_scene("paper-move")
    pos = PositionLoop(kv=60.0, ki=50.0, kvff=1.0, kaff=0.8, rate=2, delay=2)
    r = run(plant, load=sc.loads()[:2], duration=0.25, controller=MOVE_PID, fidelity="compliant", discrete=True,
            position=pos, motion=sc.motion(), filters=FILTERS)
    law = drive_law(MOVE_PID, plant, position=pos, filters=FILTERS)
    return law, replay_inputs(r, plant, sc.motion(), pos), r


CASES = ("load_step", "move", "move_scale", "move_delay")


def test_position_delay_is_in_the_law_and_the_run(move_delay, plant):
    """The delayed run differs from the undelayed law's replay (the delay matters on this run),
    and the law carries it."""
    law, inp, _ = move_delay
    assert law.position.delay == 2
    assert law.position.rate == 2
    nodelay = dataclasses.replace(law, position=dataclasses.replace(law.position, delay=0))
    assert max_relative_difference(ReferenceLaw(nodelay).run(inp), inp["torque_command"]) > 1e3 * REL


def test_recorded_runs_exercise_the_law(load_step, move):
    """The recorded runs are not trivial: the load step moves the command, the move accelerates
    and saturates nothing, the filters are active."""
    _, inp, _ = load_step
    u = inp["torque_command"]
    assert np.ptp(u) > 0.3
    assert len(u) == 1201
    _, inp, r = move
    assert np.ptp(inp["count"]) > 5e5
    assert np.max(np.abs(inp["acc_ref_m_s2"])) == pytest.approx(0.5)
    assert np.ptp(r.output("torque_feedforward")) > 0.1


@pytest.mark.parametrize("case", CASES)
def test_reference_law_reproduces_the_simulator(case, request):
    law, inp, _ = request.getfixturevalue(case)
    u = ReferenceLaw(law).run(inp)
    assert max_relative_difference(u, inp["torque_command"]) <= REL


def test_reference_law_is_sensitive(load_step, move):
    """A 1e-6 relative change of one gain or filter coefficient shows far above the bound."""
    from dataclasses import replace

    law, inp, _ = load_step
    for changed in (replace(law, ki=law.ki * (1 + 1e-6)), replace(law, kd=law.kd * (1 + 1e-6)),
                    replace(law, torque_biquads=((law.torque_biquads[0][0] * (1 + 1e-6),) + law.torque_biquads[0][1:],))):
        assert max_relative_difference(ReferenceLaw(changed).run(inp), inp["torque_command"]) > 1e3 * REL
    law, inp, _ = move
    changed = replace(law, position=replace(law.position, kaff=law.position.kaff * (1 + 1e-6)))
    assert max_relative_difference(ReferenceLaw(changed).run(inp), inp["torque_command"]) > 1e3 * REL


# --- C ------------------------------------------------------------------------------------------

CC = shutil.which("cc") or shutil.which("gcc")
needs_cc = pytest.mark.skipif(CC is None, reason="no C compiler (cc/gcc) on PATH: generated C not compiled")
STRICT = ["-Wall", "-Wextra", "-Wpedantic", "-Wconversion", "-Wshadow", "-Werror"]

#: One driver for the toolkit's C and for the C matiec makes of the Structured Text: the same
#: per-sample inputs (raw 32-bit counts, references, enable, hold), a run-time parameter change
#: at sample k_change (which: 0 kp, 1 the anti-windup gain, 2 both torque limits, times factor;
#: 3: init again with the initial values, ST: one call with Reset),
#: the output, the fault word and the speed integral of every sample.
DRIVER_ARGS = """int n, const uint32_t *count, const double *r1, const double *r2, const double *r3, const uint32_t *pc,
             const int *enable, const int *hold, uint32_t modulus, int k_change, int which, double factor,
             double *out, uint32_t *fault, double *integ, uint32_t cp, double w0, double i0, double t0, uint32_t pc0"""

HARNESS = """
#include "{name}.h"
void run_all({args})
{{
    {name}_params p;
    {name}_state s;
    int k;
    {name}_params_default(&p);
    p.count_modulus = modulus;
    {pmod}
    {name}_init(&p, &s, cp, ({name}_real)w0, ({name}_real)i0, ({name}_real)t0{pc0});
    for (k = 0; k < n; k++) {{
        if (k == k_change && which == 0) p.kp = ({name}_real)((double)p.kp * factor);
        if (k == k_change && which == 1) p.k_aw = ({name}_real)((double)p.k_aw * factor);
        if (k == k_change && which == 2) {{
            p.torque_max = ({name}_real)((double)p.torque_max * factor);
            p.torque_min = ({name}_real)((double)p.torque_min * factor);
        }}
        if (k == k_change && which == 3) {name}_init(&p, &s, cp, ({name}_real)w0, ({name}_real)i0, ({name}_real)t0{pc0});
        out[k] = (double){name}_step(&p, &s, {step}, enable[k], hold[k]);
        fault[k] = s.fault;
        integ[k] = (double)s.integral;
    }}
    (void)r1; (void)r2; (void)r3; (void)pc; (void)pc0;
}}
"""

MATIEC_HARNESS = """
#include <stdint.h>
#include <string.h>
#include "iec_std_lib.h"
TIME __CURRENT_TIME;
BOOL __DEBUG;
#include "POUS.h"
#include "POUS.c"
void run_all({args})
{{
    {FB} fb;
    int k;
    memset(&fb, 0, sizeof fb);  /* matiec's init ORs the flags: start from zero, as a PLC's static data */
    {FB}_init__(&fb, 0);
    fb.RESET.value = 1;
    fb.INITCOUNTPREV.value = (DINT)cp; fb.INITSPEED.value = ({R})w0; fb.INITINTEGRAL.value = ({R})i0;
    fb.INITTORQUE.value = ({R})t0;
    fb.COUNTMODULUS.value = modulus;
    {pmod}
    {FB}_body__(&fb);
    fb.RESET.value = 0;
    for (k = 0; k < n; k++) {{
        if (k == k_change && which == 0) fb.P_KP.value = ({R})((double)fb.P_KP.value * factor);
        if (k == k_change && which == 1) fb.P_K_AW.value = ({R})((double)fb.P_K_AW.value * factor);
        if (k == k_change && which == 2) {{
            fb.P_TORQUE_MAX.value = ({R})((double)fb.P_TORQUE_MAX.value * factor);
            fb.P_TORQUE_MIN.value = ({R})((double)fb.P_TORQUE_MIN.value * factor);
        }}
        if (k == k_change && which == 3) {{ fb.RESET.value = 1; {FB}_body__(&fb); fb.RESET.value = 0; }}
        fb.ENCCOUNT.value = (DINT)count[k];
        {inputs}
        fb.ENABLE.value = (BOOL)(enable[k] != 0); fb.HOLD.value = (BOOL)(hold[k] != 0);
        {FB}_body__(&fb);
        out[k] = (double)fb.TORQUECMD.value;
        fault[k] = (uint32_t)fb.FAULT.value;
        integ[k] = (double)fb.S_INTEGRAL.value;
    }}
    (void)r1; (void)r2; (void)r3; (void)pc; (void)pc0;
}}
"""


def _compile_so(sources, lib, flags=(), include=()):
    cmd = [CC, "-O2", "-fPIC", "-shared", "-ffp-contract=off", *flags, *(f"-I{d}" for d in include), "-o", str(lib),
           *map(str, sources), "-lm"]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    return ctypes.CDLL(str(lib))


#: Driver libraries built in this session, by the exact text of every source compiled into them
#: (the generated code and the harness; the compiler and flags are fixed per kind): an export
#: byte for byte equal to one built before is loaded from that build, not compiled again. The
#: same law reaches several tests (each case's C in the C, the Structured Text and the wrap
#: tests; load_step's law is the speed_pid_filters variant, move_scale's cascade_scale_filters):
#: each assertion still runs the library of exactly its law's text. A build that fails raises
#: and is not kept. The libraries hold no writable statics (test_c_compiles_strictly_everywhere)
#: and the harness's state is local to each run, so a run cannot see an earlier one.
_BUILT: dict[tuple, ctypes.CDLL] = {}


def _build(law: DriveLaw, tmp_path, real: str, name: str | None = None):
    name = name or f"drv_{real}"
    h, c = c_code(law, name=name, real=real)
    tmp_path.mkdir(parents=True, exist_ok=True)
    (tmp_path / f"{name}.h").write_text(h)
    (tmp_path / f"{name}.c").write_text(c)
    p = law.position
    scale = p is not None and p.measured == "screw_position"
    step = ("count[k], r1[k]" if p is None else
            f"count[k], ({name}_real)r1[k], ({name}_real)r2[k], ({name}_real)r3[k]" + (", pc[k]" if scale else ""))
    if p is None:
        step = f"count[k], ({name}_real)r1[k]"
    harness = HARNESS.format(name=name, args=DRIVER_ARGS, step=step, pc0=", pc0" if scale else "",
                             pmod="p.position_modulus = modulus;" if scale else "")
    (tmp_path / "harness.c").write_text(harness)
    key = ("c", name, h, c, harness)
    if key not in _BUILT:
        _BUILT[key] = _compile_so([tmp_path / f"{name}.c", tmp_path / "harness.c"], tmp_path / f"lib{name}.so",
                                  ["-std=c99", *STRICT[:4]])
    return _BUILT[key]


def _sequence(law: DriveLaw, inp: dict, **kw) -> dict:
    """The driver's inputs from replay_inputs' dict (counts as raw 32-bit words)."""
    n = len(inp["count"])
    zero = np.zeros(n)
    seq = {"count": np.asarray(inp["count"], np.int64), "r1": inp.get("speed_ref_rad_s", inp.get("pos_ref_m", zero)),
           "r2": inp.get("vel_ref_m_s", zero), "r3": inp.get("acc_ref_m_s2", zero),
           "pc": np.asarray(inp.get("position_count", np.zeros(n, np.int64)), np.int64),
           "enable": np.ones(n, np.int32), "hold": np.zeros(n, np.int32), "modulus": 0, "k_change": -1,
           "which": 0, "factor": 1.0, "cp": inp["init"]["count_prev"], "w0": inp["init"]["speed0_rad_s"],
           "i0": inp["init"]["integral0_n_m"], "t0": inp["init"]["torque0_n_m"],
           "pc0": inp["init"].get("position_zero_count", 0)}
    seq.update(kw)
    return seq


def _drive(lib, seq: dict, integral: bool = False) -> tuple[np.ndarray, ...]:
    """Run a built driver (toolkit C or matiec C) on a sequence: (outputs, fault words[, speed
    integral])."""
    n = len(seq["count"])
    d = ctypes.POINTER(ctypes.c_double)
    u32 = ctypes.POINTER(ctypes.c_uint32)
    i32 = ctypes.POINTER(ctypes.c_int)
    raw = lambda a: np.ascontiguousarray(np.asarray(a, np.int64) & 0xFFFFFFFF, np.uint32)  # noqa: E731
    arrs = [raw(seq["count"]), *(np.ascontiguousarray(seq[k], float) for k in ("r1", "r2", "r3")), raw(seq["pc"]),
            np.ascontiguousarray(seq["enable"], np.int32), np.ascontiguousarray(seq["hold"], np.int32)]
    out, fault, integ = np.zeros(n), np.zeros(n, np.uint32), np.zeros(n)
    lib.run_all.restype = None
    lib.run_all.argtypes = [ctypes.c_int, u32, d, d, d, u32, i32, i32, ctypes.c_uint32, ctypes.c_int, ctypes.c_int,
                            ctypes.c_double, d, u32, d, ctypes.c_uint32, ctypes.c_double, ctypes.c_double,
                            ctypes.c_double, ctypes.c_uint32]
    lib.run_all(n, arrs[0].ctypes.data_as(u32), *(a.ctypes.data_as(d) for a in arrs[1:4]), arrs[4].ctypes.data_as(u32),
                arrs[5].ctypes.data_as(i32), arrs[6].ctypes.data_as(i32), seq["modulus"], seq["k_change"],
                seq["which"], seq["factor"], out.ctypes.data_as(d), fault.ctypes.data_as(u32), integ.ctypes.data_as(d),
                seq["cp"] & 0xFFFFFFFF, seq["w0"], seq["i0"], seq["t0"], seq["pc0"] & 0xFFFFFFFF)
    return (out, fault, integ) if integral else (out, fault)


def _run_c(lib, law: DriveLaw, inp: dict) -> np.ndarray:
    return _drive(lib, _sequence(law, inp))[0]


@needs_cc
@pytest.mark.parametrize("case", CASES)
def test_c_double_reproduces_the_simulator(case, request, tmp_path):
    law, inp, _ = request.getfixturevalue(case)
    u = _run_c(_build(law, tmp_path, "double"), law, inp)
    assert max_relative_difference(u, inp["torque_command"]) <= REL
    assert max_relative_difference(u, ReferenceLaw(law).run(inp)) <= REL


@needs_cc
@pytest.mark.parametrize("case", ("load_step", "move"))
def test_c_float_compiles_and_tracks(case, request, tmp_path):
    """In float the same code follows the double command to float round-off accumulated over the
    run (1e-3 of the command's range), not bit for bit."""
    law, inp, _ = request.getfixturevalue(case)
    u = _run_c(_build(law, tmp_path, "float"), law, inp)
    assert max_relative_difference(u, inp["torque_command"]) < 1e-3


@needs_cc
def test_c_catches_a_changed_constant(load_step, tmp_path):
    from dataclasses import replace

    law, inp, _ = load_step
    u = _run_c(_build(replace(law, ki=law.ki * (1 + 1e-6)), tmp_path, "double"), law, inp)
    assert max_relative_difference(u, inp["torque_command"]) > 1e3 * REL


# --- Structured Text, compiled by matiec's iec2c ---------------------------------------------------

def _find_matiec() -> tuple[Path | None, str]:
    """matiec's folder (iec2c and lib/): PRSA_MATIEC_DIR when it holds a build, else the shared
    build script (shared/tools/matiec/build.sh above the checkout: builds once, cached). Returns
    (folder or None, why not)."""
    env = os.environ.get("PRSA_MATIEC_DIR")
    if env and (Path(env) / "iec2c").is_file() and (Path(env) / "lib").is_dir():
        return Path(env), ""
    script = next((d / "shared" / "tools" / "matiec" / "build.sh" for d in Path(__file__).resolve().parents
                   if (d / "shared" / "tools" / "matiec" / "build.sh").is_file()), None)
    if script is None:
        return None, "no matiec build (PRSA_MATIEC_DIR) and no shared/tools/matiec/build.sh above the checkout"
    res = subprocess.run(["bash", str(script)], capture_output=True, text=True, timeout=900)
    lines = res.stdout.strip().splitlines()
    if res.returncode != 0 or not lines or not (Path(lines[-1]) / "iec2c").is_file():
        return None, f"{script} failed (exit {res.returncode}): {' '.join(res.stderr.split())[-300:]}"
    return Path(lines[-1]), ""


@pytest.fixture(scope="session")
def matiec():
    """matiec's folder; skips without it, fails under CI=true (CI must compile every ST export)."""
    d, why = _find_matiec()
    if d is None:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(f"matiec's iec2c is needed under CI=true to compile the Structured Text exports: {why}")
        pytest.skip(f"matiec's iec2c not available: {why}")
    if CC is None:
        pytest.skip("no C compiler for matiec's C")
    return d


def iec2c(matiec: Path, text: str, folder: Path) -> Path:
    """Compile ``text`` with iec2c into ``folder``; assert exit 0 (the error lines in the message)."""
    folder.mkdir(parents=True, exist_ok=True)
    st = folder / "fb.st"
    st.write_text(text)
    res = subprocess.run([str(matiec / "iec2c"), "-I", str(matiec / "lib"), "-T", str(folder), str(st)],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, f"iec2c refused the Structured Text: {res.stdout}{res.stderr}"
    return folder


def _build_st(matiec: Path, law: DriveLaw, tmp_path, real: str, name: str = "StCtrl", text: str | None = None):
    """matiec's C of the Structured Text (``text``, default the law's export) with the driver
    harness, as a loaded library; an ST text and harness built before in this session is loaded
    from that build (``_BUILT``: iec2c accepted exactly this text there)."""
    text = text if text is not None else st_code(law, name=name, real=real)
    harness = _st_harness(law, real, name)
    key = ("st", str(matiec), text, harness)
    if key not in _BUILT:
        out = iec2c(matiec, text, tmp_path / "iec")
        (out / "harness.c").write_text(harness)
        _BUILT[key] = _compile_so([out / "harness.c"], out / "libst.so", ["-std=gnu99", "-w"], [matiec / "lib" / "C", out])
    return _BUILT[key]


def _st_harness(law: DriveLaw, real: str, name: str) -> str:
    p = law.position
    R = "LREAL" if real == "double" else "REAL"
    if p is None:
        inputs = f"fb.SPEEDREF.value = ({R})r1[k];"
    else:
        inputs = f"fb.POSREF.value = ({R})r1[k]; fb.VELREF.value = ({R})r2[k]; fb.ACCREF.value = ({R})r3[k];"
        if p.measured == "screw_position":
            inputs += " fb.POSCOUNT.value = (DINT)pc[k];"
    pmod = "fb.POSMODULUS.value = modulus; fb.INITPOSCOUNT.value = (DINT)pc0;" if (
        p is not None and p.measured == "screw_position") else ""
    return MATIEC_HARNESS.format(FB=name.upper(), R=R, args=DRIVER_ARGS, inputs=inputs, pmod=pmod)


def _run_st(lib, law: DriveLaw, inp: dict) -> np.ndarray:
    return _drive(lib, _sequence(law, inp))[0]


def _hostile(law: DriveLaw, n: int = 3000, seed: int = 3, base: int = 2**31 - 40000) -> dict:
    """A synthetic run that exercises every path: a motion whose 32-bit count crosses 2^31 (as a
    signed INTEGER32), a speed reversal, NaN and inf references, enable off and on, hold, a kp
    change at run time and, for a cascade, a moving position reference."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * law.ts
    theta = 40.0 * np.sin(2 * np.pi * 3.0 * t) + 5.0 * t  # rad
    count = base + np.floor(theta / law.rad_per_count).astype(np.int64) + rng.integers(-2, 3, n)
    seq = {"count": count, "r1": 100.0 * np.sin(2 * np.pi * 2.0 * t), "r2": np.zeros(n), "r3": np.zeros(n),
           "pc": np.zeros(n, np.int64), "enable": np.ones(n, np.int32), "hold": np.zeros(n, np.int32), "modulus": 0,
           "k_change": 2200, "which": 0, "factor": 1.25, "cp": int(count[0]), "w0": 0.0, "i0": 0.1, "t0": 0.1, "pc0": 0}
    if law.position is not None:
        lead = law.position.lead_m_per_rad
        seq["r1"] = lead * 40.0 * np.sin(2 * np.pi * 3.0 * t) + lead * 5.0 * t
        seq["r2"] = np.gradient(seq["r1"], law.ts)
        seq["r3"] = np.gradient(seq["r2"], law.ts)
        if law.position.measured == "screw_position":
            seq["pc"] = base + np.floor(lead * theta / law.position.per_count).astype(np.int64)
            seq["pc0"] = int(seq["pc"][0])
    seq["r1"] = seq["r1"].copy()
    seq["r1"][1000] = np.nan
    seq["r1"][1001] = np.inf
    seq["r2"][1300] = -np.inf
    seq["enable"][1500:1600] = 0
    seq["r1"][1550] = np.nan  # a fault while disabled: still 0 N m
    seq["hold"][1800:1900] = 1
    return seq


def _variants():
    """Every kind of export: loops, filters at both places and in series, a derivative, zero delay,
    a setpoint weight, cascades on the encoder and on a linear scale, friction feed-forward."""
    from prsa_ctrl.drive.filters import SecondOrderLowPass
    from prsa_ctrl.drive.friction import FrictionFeedforward

    two = FILTERS + (LoopFilter(SecondOrderLowPass(1500.0, 0.7), "torque_command", method="matched"),
                     LoopFilter(Notch(600.0, 100.0, -10.0), "speed_measurement", method="tustin", prewarp=False))
    return {
        "speed_pi": lambda pl: drive_law(PID(0.085, 14.7), pl),
        "speed_pid_filters": lambda pl: drive_law(SPEED_PID, pl, filters=FILTERS),
        "speed_four_filters": lambda pl: drive_law(SPEED_PID, pl, filters=two, setpoint_weight=0.5),
        "speed_no_delay": lambda pl: drive_law(PID(0.085, 14.7), pl, delay_samples=0, feedforward_torque_n_m=0.2),
        "cascade_encoder": lambda pl: drive_law(MOVE_PID, pl, position=PositionLoop(kv=102.7, kvff=1.0, kaff=1.0)),
        "cascade_scale_filters": lambda pl: drive_law(MOVE_PID, pl, filters=FILTERS, position=PositionLoop(
            kv=60.0, ki=50.0, kvff=1.0, kaff=0.8, measured="screw_position", rate=3)),
        "cascade_friction": lambda pl: drive_law(MOVE_PID, pl, position=PositionLoop(
            kv=102.7, kvff=1.0, kaff=1.0, friction=FrictionFeedforward.from_plant(pl, 1500.0))),
        "cascade_delay": lambda pl: drive_law(MOVE_PID, pl, filters=FILTERS, position=PositionLoop(
            kv=60.0, ki=50.0, kvff=1.0, kaff=0.8, rate=2, delay=3)),
    }


VARIANTS = tuple(_variants())


@pytest.mark.parametrize("real", ("double", "float"))
@pytest.mark.parametrize("variant", VARIANTS)
def test_every_st_export_compiles_with_iec2c_and_equals_the_c(variant, real, plant, matiec, tmp_path):
    """Each Structured Text export compiles with iec2c; the C matiec makes of it, run on a hostile
    sequence (a count crossing 2^31, NaN/inf references, enable, hold, a kp change at run time),
    gives the toolkit C's outputs and fault words bit for bit (also with friction in float, where
    the toolkit calls expf and matiec's EXP rounds exp of double: equal on these runs)."""
    law = _variants()[variant](plant)
    st = _build_st(matiec, law, tmp_path / "st", real)
    c = _build(law, tmp_path, real)
    seq = _hostile(law)
    u_st, f_st = _drive(st, seq)
    u_c, f_c = _drive(c, seq)
    assert np.all(np.isfinite(u_c))
    assert np.ptp(u_c) > 0.05
    assert f_c[999] == 0
    assert f_c[1000] == 1
    assert f_c[-1] == 1
    np.testing.assert_array_equal(f_st, f_c)
    np.testing.assert_array_equal(u_st, u_c)
    # init again at sample 2500 (after the NaN): the same in both, the fault word cleared
    u_c3, f_c3 = _drive(c, dict(seq, k_change=2500, which=3))
    u_st3, f_st3 = _drive(st, dict(seq, k_change=2500, which=3))
    np.testing.assert_array_equal(u_st3, u_c3)
    np.testing.assert_array_equal(f_st3, f_c3)
    assert f_c3[2499] == 1
    assert not f_c3[2500:].any()
    # single-turn counts (20 bits): the same run, counts modulo 2^20, in both
    single = dict(seq, count=seq["count"] % 2**20, pc=seq["pc"] % 2**20, modulus=2**20, cp=seq["cp"] % 2**20,
                  pc0=seq["pc0"] % 2**20)
    u_c1, _ = _drive(c, single)
    u_st1, _ = _drive(st, single)
    np.testing.assert_array_equal(u_c1, u_c)
    np.testing.assert_array_equal(u_st1, u_st)


@pytest.mark.parametrize("real", ("double", "float"))
@pytest.mark.parametrize("case", CASES)
def test_structured_text_reproduces_the_simulator(case, real, request, matiec, tmp_path):
    """matiec's C of the ST export on the recorded runs: the toolkit C's command bit for bit, and
    so the simulator's (double: 1e-12 of the largest command; float: 1e-3, float round-off)."""
    law, inp, _ = request.getfixturevalue(case)
    u = _run_st(_build_st(matiec, law, tmp_path / "st", real), law, inp)
    np.testing.assert_array_equal(u, _run_c(_build(law, tmp_path, real), law, inp))
    assert max_relative_difference(u, inp["torque_command"]) <= (REL if real == "double" else 1e-3)


def test_structured_text_catches_a_changed_constant(load_step, matiec, tmp_path):
    law, inp, _ = load_step
    text = st_code(law, name="StCtrl")
    bad = re.sub(r"(P_KI : LREAL := )([0-9.E+-]+)", lambda m: m.group(1) + repr(float(m.group(2)) * (1 + 1e-6)), text)
    assert bad != text
    u = _run_st(_build_st(matiec, law, tmp_path, "double", text=bad), law, inp)
    assert max_relative_difference(u, inp["torque_command"]) > 1e3 * REL


def test_iec2c_refuses_what_the_standard_forbids(matiec, tmp_path):
    """The compiler is a real check: the two defects of issue 36 (a local named like the standard
    block INTEGRAL, a real literal without a decimal point) are refused."""
    ok = "FUNCTION_BLOCK Fb\nVAR\n    s_Integral : LREAL := 1.0E-7;\nEND_VAR\ns_Integral := s_Integral;\nEND_FUNCTION_BLOCK\n"
    iec2c(matiec, ok, tmp_path / "ok")
    for bad in (ok.replace("s_Integral", "Integral"), ok.replace("1.0E-7", "1e-07")):
        with pytest.raises(AssertionError, match="iec2c refused"):
            iec2c(matiec, bad, tmp_path / "bad")


def test_st_literals_and_names_are_iec(load_step):
    law, _, _ = load_step
    from prsa_ctrl.io.codegen import IEC_RESERVED, iec_real

    assert iec_real(1e-07) == "1.0E-7"
    assert iec_real(5e-05) == "5.0E-5"
    assert float(iec_real(1 / 3)) == 1 / 3
    for real in ("double", "float"):
        text = st_code(law, name="SpeedCtrl", real=real)
        code = re.sub(r"\(\*.*?\*\)", " ", text, flags=re.S)
        assert not re.search(r"(?<![\w.#])\d+[eE][+-]?\d+", code)  # no literal like 1e-07
        for m in re.finditer(r"^\s+(\w+)\s*:", code, flags=re.M):
            assert m.group(1).upper() not in IEC_RESERVED
    assert "LREAL" not in st_code(law, real="float")
    with pytest.raises(ValueError, match="name = 'Integral'"):
        st_code(law, name="Integral")


# --- C for firmware: strict compilers, cppcheck, NaN, wrap-around, anti-windup, run-time parameters ----

CLANG = shutil.which("clang")
CPPCHECK = shutil.which("cppcheck")


def _write_c(law: DriveLaw, folder, name: str, real: str):
    folder.mkdir(parents=True, exist_ok=True)
    h, c = c_code(law, name=name, real=real)
    (folder / f"{name}.h").write_text(h)
    (folder / f"{name}.c").write_text(c)
    return folder / f"{name}.c"


@needs_cc
@pytest.mark.parametrize("variant", VARIANTS)
def test_c_compiles_strictly_everywhere(variant, plant, tmp_path):
    """Every export, float and double: gcc (and clang) in C99 and C11 with -Wall -Wextra
    -Wpedantic -Wconversion -Wshadow -Werror (float: also -Wdouble-promotion, i.e. no double
    arithmetic); the header from C++ (extern "C"); two exports in one unity build; no writable
    statics, no 64-bit integers; cppcheck clean when installed."""
    law = _variants()[variant](plant)
    srcs = [_write_c(law, tmp_path, f"u_{real}", real) for real in ("double", "float")]
    for cc in filter(None, (CC, CLANG)):
        for std in ("c99", "c11"):
            for src in srcs:
                extra = ["-Wdouble-promotion"] if "float" in src.name else []
                res = subprocess.run([cc, f"-std={std}", *STRICT, *extra, "-c", str(src), "-o", str(tmp_path / "x.o")],
                                     capture_output=True, text=True, timeout=120)
                assert res.returncode == 0, f"{cc} -std={std} {src.name}: {res.stderr}"
    text = srcs[1].read_text()
    code = re.sub(r"/\*.*?\*/", " ", text, flags=re.S)
    assert "int64" not in code
    assert "double" not in code
    assert "expf(" in code.replace("tanf(", "expf(")
    static_object = r"\bstatic\b[^;(){}]*[;=\[{]"  # a static object, not a function
    assert len(re.findall(static_object, "static int x;\nstatic float z[3];\nstatic int f(int a)\n{")) == 2
    statics = re.findall(static_object, code)
    assert not statics, statics
    assert len(re.findall(r"\bstatic\b", code)) >= 3, statics
    (tmp_path / "unity.c").write_text('#include "u_double.c"\n#include "u_float.c"\n')
    res = subprocess.run([CC, "-std=c99", *STRICT, "-c", str(tmp_path / "unity.c"), "-o", str(tmp_path / "u.o")],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    cxx = shutil.which("g++") or shutil.which("clang++")
    if cxx:
        (tmp_path / "use.cpp").write_text('#include "u_double.h"\n#include "u_float.h"\n'
                                          "int main() { u_float_params p; u_float_params_default(&p); return 0; }\n")
        res = subprocess.run([cxx, "-std=c++11", "-Wall", "-Wextra", "-Werror", "-c", str(tmp_path / "use.cpp"), "-o",
                              str(tmp_path / "use.o")], capture_output=True, text=True, timeout=120)
        assert res.returncode == 0, res.stderr
    if CPPCHECK:
        res = subprocess.run([CPPCHECK, "--enable=warning,style,performance,portability", "--std=c99", "--quiet",
                              "--error-exitcode=1", "--inline-suppr", *map(str, srcs)],
                             capture_output=True, text=True, timeout=300)
        assert res.returncode == 0, res.stderr
        assert not res.stderr.strip(), res.stderr


@pytest.fixture(scope="module")
def pid_lib(load_step, tmp_path_factory):
    law, inp, _ = load_step
    d = tmp_path_factory.mktemp("fw")
    return {real: _build(law, _mk(d / real), real) for real in ("double", "float")}


def _mk(d):
    d.mkdir(parents=True, exist_ok=True)
    return d


@needs_cc
@pytest.mark.parametrize("real", ("double", "float"))
def test_c_nan_input_sets_the_fault_and_holds_a_finite_command(load_step, pid_lib, real):
    """A NaN (then inf) speed reference at one sample: fault bit 1 from there on, the command of
    that sample is the last one returned, the integral is unchanged (not latched), every output
    is finite and the run rejoins the clean run (within 1e-3 of the command range after 100 ms)."""
    law, inp, _ = load_step
    seq = _sequence(law, inp)
    clean, f0, i0 = _drive(pid_lib[real], seq, True)
    bad = dict(seq, r1=np.array(seq["r1"], float))
    bad["r1"][600] = np.nan
    bad["r1"][601] = np.inf
    u, f, integ = _drive(pid_lib[real], bad, True)
    assert not f0.any()
    assert np.all(f[:600] == 0)
    assert np.all(f[600:] == 1)
    assert np.all(np.isfinite(u))
    assert np.all(np.isfinite(integ))
    assert u[600] == u[599]
    assert u[601] == u[599]
    assert integ[600] == integ[599]
    assert integ[601] == integ[599]
    np.testing.assert_array_equal(u[:600], clean[:600])
    assert np.max(np.abs(u[1000:] - clean[1000:])) < 1e-3 * np.ptp(clean)


@needs_cc
@pytest.mark.parametrize("real", ("double", "float"))
@pytest.mark.parametrize("case", ("load_step", "move_scale"))
def test_c_counts_wrapping_give_no_kick(case, real, request, tmp_path):
    """The same run with the 32-bit counter crossing 2^31 (INTEGER32 wrap), crossing 2^32
    (UNSIGNED32 wrap) and as a 20-bit single-turn count (modulus 2^20): the outputs are those of
    the unwrapped run, bit for bit (no torque kick at the wrap)."""
    law, inp, _ = request.getfixturevalue(case)
    lib = _build(law, tmp_path, real)
    seq = _sequence(law, inp)
    ref, _ = _drive(lib, seq)
    c = np.asarray(seq["count"])
    for base, modulus in ((2**31 - int(c[len(c) // 2]), 0), (2**32 - int(c[len(c) // 2]), 0), (0, 2**20)):
        m = modulus or 2**62
        pc = np.asarray(seq["pc"])
        shifted = dict(seq, count=(c + base) % m, cp=(seq["cp"] + base) % m, pc=(pc + base) % m,
                       pc0=(seq["pc0"] + base) % m, modulus=modulus)
        if modulus == 0:  # the raw 32-bit word really crosses the boundary during the run
            w = (c + base) & 0xFFFFFFFF
            assert np.ptp(w) > 2**31 or (w.min() < 2**31 <= w.max())
        u, f = _drive(lib, shifted)
        assert not f.any()
        np.testing.assert_array_equal(u, ref)


@needs_cc
def test_c_anti_windup_and_runtime_limits(plant, tmp_path):
    """A speed step far beyond what the torque limit can follow: with the back-calculation
    anti-windup the integral never exceeds the limit (it converges monotonically to the limited
    command), without it (k_aw set to 0 at run time) it winds up past 5x the limit; the run
    equals the Python reference law. Torque limits halved at run time take effect at the next
    sample."""
    law = drive_law(PID(0.085, 14.7), plant)
    n = 2000
    seq = {"count": np.zeros(n, np.int64), "r1": np.where(np.arange(n) < 1200, 500.0, 0.0), "r2": np.zeros(n),
           "r3": np.zeros(n), "pc": np.zeros(n, np.int64), "enable": np.ones(n, np.int32), "hold": np.zeros(n, np.int32),
           "modulus": 0, "k_change": -1, "which": 0, "factor": 1.0, "cp": 0, "w0": 0.0, "i0": 0.0, "t0": 0.0, "pc0": 0}
    lib = _build(law, tmp_path, "double")
    u, _, integ = _drive(lib, seq, True)
    tmax = law.torque_limit_n_m
    assert np.max(np.abs(u)) == tmax
    assert np.max(integ) <= tmax * (1 + 1e-12)
    assert np.max(integ) > 0.99 * tmax
    ref = ReferenceLaw(law)
    ref.init(0, 0.0, 0.0, 0.0)
    np.testing.assert_allclose(u, [ref.step(0, r) for r in seq["r1"]], rtol=0, atol=1e-12)
    _, _, wound = _drive(lib, dict(seq, k_change=0, which=1, factor=0.0), True)
    assert np.max(wound) > 5 * tmax
    u2, _ = _drive(lib, dict(seq, k_change=300, which=2, factor=0.5))
    np.testing.assert_array_equal(u2[:301], u[:301])
    assert np.max(np.abs(u2[302:])) == 0.5 * tmax
    assert np.max(np.abs(u[302:1200])) == tmax


@needs_cc
def test_c_enable_hold_reinit_and_bad_limits(load_step, tmp_path):
    """Enable false: output 0 and integral 0 from that sample; hold: the integral stays constant;
    init again: the run restarts exactly as a fresh one (fault cleared); torque_min > torque_max
    at run time: fault bit 4 and the held command."""
    law, inp, _ = load_step
    lib = _build(law, tmp_path, "double")
    seq = _sequence(law, inp)
    en = np.ones(len(seq["count"]), np.int32)
    en[300:400] = 0
    hold = np.zeros_like(en)
    hold[600:700] = 1
    u, f, integ = _drive(lib, dict(seq, enable=en, hold=hold), True)
    assert np.all(u[300:400] == 0.0)
    assert np.all(integ[300:400] == 0.0)
    assert not f.any()
    r_nan = np.array(seq["r1"], float)
    r_nan[350] = np.nan  # a fault while disabled: the output stays 0 N m
    u_n, f_n = _drive(lib, dict(seq, r1=r_nan, enable=en, hold=hold))
    assert np.all(u_n[300:400] == 0.0)
    assert f_n[349] == 0
    assert f_n[350] == 1
    assert np.all(integ[600:700] == integ[599])
    assert integ[701] != integ[699]
    assert np.all(np.isfinite(u))
    assert np.max(np.abs(u[400:])) <= law.torque_limit_n_m
    u_bad, f_bad = _drive(lib, dict(seq, k_change=500, which=2, factor=-1.0))
    assert np.all(f_bad[500:] == 4)
    assert np.all(u_bad[500:] == u_bad[499])
    # re-init in the middle of a run (after a NaN set the fault): from there the outputs are those
    # of a fresh run started at that sample with the same initial values, and the fault is cleared
    seq_nan = dict(seq, r1=np.array(seq["r1"], float))
    seq_nan["r1"][10] = np.nan
    k = 700
    u1, f1 = _drive(lib, dict(seq_nan, k_change=k, which=3))
    fresh = {key: (val[k:] if isinstance(val, np.ndarray) else val) for key, val in seq.items()}
    u_fresh, f_fresh = _drive(lib, fresh)
    assert f1[k - 1] == 1
    assert not f1[k:].any()
    assert not f_fresh.any()
    np.testing.assert_array_equal(u1[k:], u_fresh)


PARAMS_PROBE = """
#include <math.h>
#include <stdio.h>
#include "{name}.h"
int main(void)
{{
    {name}_params a, b;
    {name}_physical ph;
    int rc;
    double worst = 0.0, d;
    {name}_params_default(&a);
    {name}_params_default(&b);
    {name}_physical_default(&ph);
    {change}
    rc = {name}_params_compute(&b, &ph);
{compare}
    printf("%d %.17g\\n", rc, worst);
    ph.ts_s = ({name}_real)-1;
    rc = {name}_params_compute(&b, &ph);
    printf("%d\\n", rc);
    return 0;
}}
"""


def _probe(law: DriveLaw, target: DriveLaw, tmp_path, change: str = "", real: str = "double") -> tuple[int, float, int]:
    """Compile a probe that computes the parameters from ``law``'s physical values (after the C
    statements ``change``) and compares them with ``target``'s exported parameters."""
    from prsa_ctrl.io.codetext import law_constants as _consts

    name = "pp"
    _write_c(law, tmp_path, name, real)
    tv = {k: v for k, v, _ in _consts(target)}
    cmp = "\n".join(f"    d = fabs((double)b.{k} - ({tv[k]!r})) / fmax(fabs({tv[k]!r}), 1e-300); if (d > worst) worst = d;"
                    for k in tv if tv[k] != 0.0) + "\n    (void)a;"
    (tmp_path / "probe.c").write_text(PARAMS_PROBE.format(name=name, change=change, compare=cmp))
    exe = tmp_path / "probe"
    res = subprocess.run([CC, "-std=c99", "-O1", "-o", str(exe), str(tmp_path / "probe.c"), str(tmp_path / f"{name}.c"),
                          "-lm"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    out = subprocess.run([str(exe)], capture_output=True, text=True, timeout=60).stdout.split()
    return int(out[0]), float(out[1]), int(out[2])


@needs_cc
def test_c_parameters_computed_from_physical_values(plant, tmp_path):
    """params_compute from the exported physical values gives the exported coefficients (speed
    filter, derivative filter, anti-windup, Tustin-prewarped notch and low-pass, position loop)
    to 1e-13 relative in double; retuning kp and moving the notch from 1200 to 900 Hz in C gives
    the coefficients Python computes for that design; a bad physical value is refused (< 0)."""
    filters = (LoopFilter(Notch(1200.0, 300.0, -20.0), "torque_command"),
               LoopFilter(FirstOrderLowPass(800.0), "speed_measurement"))
    pos = PositionLoop(kv=60.0, ki=50.0, kvff=1.0, kaff=0.8, measured="screw_position", rate=3)
    law = drive_law(SPEED_PID, plant, filters=filters, position=pos)
    rc, worst, bad = _probe(law, law, tmp_path / "same")
    assert rc == 0
    assert worst < 1e-13
    assert bad < 0
    new = (LoopFilter(Notch(900.0, 300.0, -20.0), "torque_command"), filters[1])
    target = drive_law(PID(0.1, 14.7, kd=2e-5, tf=5e-4), plant, filters=new, position=pos)
    spec = target.torque_filter_specs[0]
    change = "ph.kp = 0.1;\n" + "\n".join(f"    ph.tf[0].num[{k}] = {spec.num[k]!r}; ph.tf[0].den[{k}] = {spec.den[k]!r};"
                                          for k in range(3)) + f"\n    ph.tf[0].prewarp_hz = {spec.prewarp_hz!r};"
    rc, worst, _ = _probe(law, target, tmp_path / "retuned", change)
    assert rc == 0
    assert worst < 1e-13
    rc, worst, _ = _probe(law, law, tmp_path / "moved", change)
    assert worst > 1e-3  # the probe sees the change
    rc, worst, _ = _probe(law, law, tmp_path / "float", real="float")
    assert rc == 0
    assert worst < 1e-5


# --- export_code and bad input -------------------------------------------------------------------

def test_export_code_writes_by_suffix(plant, tmp_path):
    files = export_code(SPEED_PID, plant, tmp_path / "drive.c", filters=FILTERS)
    assert [f.name for f in files] == ["drive.c", "drive.h"]
    assert '#include "drive.h"' in files[0].read_text()
    assert "drive_step(" in files[1].read_text()
    files = export_code(SPEED_PID, plant, tmp_path / "Speed Loop.st", real="float")
    assert files[0].read_text().startswith("FUNCTION_BLOCK prsa_ctrl")


def test_export_code_of_a_cascade_design(plant, tmp_path):
    from prsa_ctrl.tuning.cascade import CascadeDesign

    d = CascadeDesign("joint", MOVE_PID, PositionLoop(kv=102.7, kvff=1.0, kaff=1.0), {}, {}, {}, 0.0)
    law = drive_law(d, plant)
    assert law.position is not None
    assert law.position.kv == 102.7
    text = export_code(d, plant, tmp_path / "cascade.st")[0].read_text()
    assert "PosRef" in text
    assert "P_KAFF_J" in text


@pytest.mark.parametrize("kwargs, match", [
    ({"real": "long double"}, "real = 'long double'"),
    ({"name": "1abc"}, "name = '1abc'"),
    ({"differences": "angle"}, "differences = 'angle'"),
    ({"name": "a__b"}, "name = 'a__b'"),
    ({"name": "PID"}, "name = 'PID'"),
])
def test_bad_arguments_name_themselves(plant, kwargs, match):
    law = drive_law(SPEED_PID, plant)
    with pytest.raises(ValueError, match=re.escape(match)):
        c_code(law, **kwargs)


def test_bad_export_arguments(plant, tmp_path):
    with pytest.raises(ValueError, match="expected a file name ending in .c or .st or .xml"):
        export_code(SPEED_PID, plant, tmp_path / "drive.cpp")
    with pytest.raises(ValueError, match="PID kff"):
        drive_law(PID(0.085, 14.7, kff=1.0), plant)
    with pytest.raises(ValueError, match="delay_samples = 2"):
        drive_law(SPEED_PID, plant, delay_samples=2)
    assert not list(tmp_path.iterdir())


def test_zero_delay_returns_the_command_just_computed(load_step):
    from dataclasses import replace

    law, inp, _ = load_step
    u0 = ReferenceLaw(replace(law, delay_samples=0)).run(inp)
    assert max_relative_difference(u0[:-1], inp["torque_command"][1:]) <= REL


@pytest.mark.parametrize("b", [0.0, 0.5])
def test_setpoint_weight_against_the_prefiltered_run(plant, b, tmp_path):
    """b != 1: the generated law on the raw setpoint gives the command of the simulated loop,
    which runs the 1-DOF PI on the setpoint through autotune.setpoint_prefilter (the same
    command while unsaturated; the prefilter's algebra differs from the 2-DOF law in round-off)."""
    from prsa_ctrl.studies.autotune import setpoint_prefilter
    from prsa_ctrl.sim.signals import PiecewiseLinear

    pid, ts, n = PID(0.085, 14.7), plant.sample_time_s, 160
    t = np.arange(n) * ts
    r_raw = np.where(t >= 0.01, 40.0, 30.0)
    rf = setpoint_prefilter(r_raw, pid, ts, b)
    r = run(plant, setpoint=PiecewiseLinear(tuple(zip(t.tolist(), rf.tolist()))), load=500.0, duration=n * ts,
            controller=pid, fidelity="rigid", discrete=True)
    inp = {k: (v[:n] if isinstance(v, np.ndarray) else v) for k, v in replay_inputs(r, plant).items()}
    assert np.max(np.abs(inp["speed_ref_rad_s"] - rf)) < 1e-9
    assert np.max(np.abs(rf - r_raw)) > 1.0
    inp["speed_ref_rad_s"] = r_raw
    inp["init"]["integral0_n_m"] -= pid.kp * (b - 1) * r_raw[0]
    law = drive_law(pid, plant, setpoint_weight=b)
    u = ReferenceLaw(law).run(inp)
    assert max_relative_difference(u, inp["torque_command"]) < 1e-9
    if CC is not None:
        assert max_relative_difference(_run_c(_build(law, tmp_path, "double"), law, inp), inp["torque_command"]) < 1e-9
    d, _ = _find_matiec()
    if d is not None and CC is not None:
        u_st = _run_st(_build_st(d, law, tmp_path / "st", "double"), law, inp)
        assert max_relative_difference(u_st, inp["torque_command"]) < 1e-9
    from dataclasses import replace

    assert max_relative_difference(ReferenceLaw(replace(law, setpoint_weight=1.0)).run(inp), inp["torque_command"]) > 0.05


# --- prsa-tune --export PATH.c / PATH.st --------------------------------------------------------

def test_cli_export_c_writes_source_and_header(tmp_path, capsys, shared_tuning):
    from prsa_ctrl.cli.tune import main

    out = tmp_path / "speed.c"
    assert main(["--quiet", "--export", str(out), "--json", str(tmp_path / "r.json")]) == 0
    assert out.exists()
    assert (tmp_path / "speed.h").exists()
    import json

    best = json.loads((tmp_path / "r.json").read_text())["best"]
    kp = float(re.search(r"p->kp = \(speed_real\)([0-9.E+-]+);", out.read_text()).group(1))
    assert kp == best["gains"]["kp"]
    assert best["gains"]["b"] == 1.0
    if CC is not None:
        res = subprocess.run([CC, "-std=c99", *STRICT, "-c", str(out), "-o",
                              str(tmp_path / "speed.o")], capture_output=True, text=True, timeout=120)
        assert res.returncode == 0, res.stderr


def test_cli_export_st_float(tmp_path, matiec, shared_tuning):
    from prsa_ctrl.cli.tune import main

    out = tmp_path / "Speed.st"
    assert main(["--quiet", "--export", str(out), "--export-real", "float"]) == 0
    text = out.read_text()
    assert text.startswith("FUNCTION_BLOCK Speed")
    assert "LREAL" not in text
    iec2c(matiec, text, tmp_path / "iec")


def test_cli_export_bad_suffix_and_header_onto_an_input(tmp_path, capsys):
    from prsa_ctrl.cli.tune import main

    assert main(["--export", str(tmp_path / "x.cpp")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "expected a path ending in .json, .toml, .c, .st or .xml" in err[0]
    plant = tmp_path / "mine.h"  # a plant file whose name the header of --export mine.c would take
    from prsa_ctrl.plant.plantfile import plant_file_path

    plant.write_text(plant_file_path("paper-iprsm").read_text())
    before = plant.read_text()
    assert main(["--plant", str(plant), "--export", str(tmp_path / "mine.c")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "mine.h" in err[0]
    assert "--export (header)" in err[0]
    assert plant.read_text() == before
    assert not (tmp_path / "mine.c").exists()


def test_cli_move_scene_export_st(tmp_path, matiec, shared_tuning):
    """The cascade of the move scene as a function block (position loop with feed-forward)."""
    from prsa_ctrl.cli.tune import main

    out = tmp_path / "Axis.st"
    assert main(["--scene", "paper-move", "--quiet", "--export", str(out), "--json", str(tmp_path / "m.json")]) == 0
    import json

    joint = json.loads((tmp_path / "m.json").read_text())["joint"]
    text = out.read_text()
    kv = float(re.search(r"P_KV : LREAL := ([0-9.E+-]+);", text).group(1))
    assert kv == joint["position"]["kv_per_s"]
    iec2c(matiec, text, tmp_path / "iec")


def test_replay_refuses_runs_the_code_does_not_describe(plant):
    r = run(plant, load=500.0, duration=0.01, controller=PID(0.085, 14.7), fidelity="rigid")
    with pytest.raises(ValueError, match="run is continuous"):
        replay_inputs(r, plant)
    r = run(plant, load=500.0, duration=0.01, controller=PID(0.085, 14.7), fidelity="rigid", discrete=True,
            measurement="kf")
    with pytest.raises(ValueError, match="run measured the speed with 'kf'"):
        replay_inputs(r, plant)


# --- inert text: hostile plant names in every code format -----------------------------------------

#: Names a plant file may carry: comment and string delimiters of C, ST and XML, line breaks,
#: quotes, backslashes, a character outside the Basic Multilingual Plane, control characters.
HOSTILE_NAMES = ('Axis 3 */ __asm__("id"); /* rev B', "Axis (* x *) END_FUNCTION_BLOCK", "Axis *) RETURN; (*",
                 "line\nbreak #include <stdio.h>", "q\"uote'd \\ back\\slash", "cdata ]]> <x/> &amp; --",
                 "emoji \U0001F600 axis", "ctrl \x00\x07\x1b\x7f\u2028 end", "trigraph ??/\n*/", "//\r\n*/ x")


def _strip_c_comments(text: str) -> str:
    return re.sub(r"/\*.*?\*/", "/**/", text, flags=re.S)


def _strip_st_comments(text: str) -> str:
    return re.sub(r"\(\*.*?\*\)", "(**)", text, flags=re.S)


@pytest.mark.parametrize("hostile", HOSTILE_NAMES)
def test_hostile_plant_names_stay_in_comments(plant, hostile, tmp_path):
    """A hostile plant name changes nothing but comment text: with the comments taken out, the C
    and the ST equal those of a plain name, every comment closes where the writer closes it,
    the C compiles strictly (gcc) and holds no trace of the injected code outside comments."""
    bad = drive_law(SPEED_PID, plant.with_params({}, name=hostile), filters=FILTERS,
                    position=PositionLoop(kv=102.7, kvff=1.0, kaff=1.0))
    good = drive_law(SPEED_PID, plant.with_params({}, name="plain"), filters=FILTERS,
                     position=PositionLoop(kv=102.7, kvff=1.0, kaff=1.0))
    for real in ("double", "float"):
        hb, cb = c_code(bad, name="ax", real=real)
        hg, cg = c_code(good, name="ax", real=real)
        assert _strip_c_comments(hb) == _strip_c_comments(hg)
        assert _strip_c_comments(cb) == _strip_c_comments(cg)
        for text in (hb, cb):
            assert all(ord(ch) < 128 and (ch >= " " or ch == "\n") for ch in text)
            assert text.count("/*") == text.count("*/")  # no comment opened or closed inside one
            assert "asm" not in _strip_c_comments(text)
            assert "??/" not in text
        sb, sg = st_code(bad, name="Ax", real=real), st_code(good, name="Ax", real=real)
        assert _strip_st_comments(sb) == _strip_st_comments(sg)
        assert sb.count("(*") == sb.count("*)")
        assert all(ord(ch) < 128 for ch in sb)
    if CC is not None:
        src = _write_c(bad, tmp_path, "ax", "double")
        res = subprocess.run([CC, "-std=c99", *STRICT, "-c", str(src), "-o", str(tmp_path / "ax.o")],
                             capture_output=True, text=True, timeout=120)
        assert res.returncode == 0, res.stderr
        syms = subprocess.run(["nm", str(tmp_path / "ax.o")], capture_output=True, text=True).stdout
        assert "asm" not in syms
        assert "id" not in re.findall(r"\b\w+\b", syms)


def test_hostile_plant_name_st_compiles(plant, matiec, tmp_path):
    """The ST with the worst names compiles with iec2c (comments are closed where they should be)."""
    for i, hostile in enumerate(HOSTILE_NAMES):
        law = drive_law(SPEED_PID, plant.with_params({}, name=hostile), filters=FILTERS)
        iec2c(matiec, st_code(law, name="Ax"), tmp_path / f"n{i}")


def test_inert_text_and_code_names():
    from prsa_ctrl.io.codetext import inert_text, is_code_name

    assert inert_text("Axis 3 */ x /* y") == "Axis 3 \\u{2a}\\u{2f} x \\u{2f}\\u{2a} y"
    assert inert_text("a--b") == "a-\\u{2d}b"
    assert inert_text("\U0001F600") == "\\u{1f600}"
    assert inert_text("x" * 300).endswith("...")
    assert len(inert_text("x" * 300)) == 203
    assert [is_code_name(n) for n in ("Axis", "PID", "integral", "a__b", "_x", "x_", "Ax_1")] == [
        True, False, False, False, False, False, True]


def test_export_code_file_names(plant, tmp_path):
    """A file stem that is a keyword or a standard block name falls back to prsa_ctrl; a header
    name that could end the #include is refused before anything is written."""
    assert export_code(SPEED_PID, plant, tmp_path / "PID.st")[0].read_text().startswith("FUNCTION_BLOCK prsa_ctrl")
    from prsa_ctrl.io.codegen import check_code_export
    from prsa_ctrl.errors import OutputError

    with pytest.raises(OutputError, match="expected a file name without quotes"):
        check_code_export(tmp_path / 'a".c')
    assert len(list(tmp_path.iterdir())) == 1


SUBNORMAL_PROBE = """
#include <math.h>
#include <stdio.h>
#include "{name}.h"
static int sub(double x) {{ return fpclassify(x) == FP_SUBNORMAL; }}
static int subf(float x) {{ return fpclassify(x) == FP_SUBNORMAL; }}
int main(void)
{{
    {name}_params p;
    {name}_state s;
    int k, i, bad = 0, zero = 0;
    uint32_t count = 1000u;
    {name}_params_default(&p);
    {name}_init(&p, &s, count, ({name}_real)0, ({name}_real)0, ({name}_real)0);
    for (k = 0; k < 40000; k++) {{
        if (k < 200) count += 40u;  /* a short move, then rest: every filter state decays */
        (void){name}_step(&p, &s, count, ({name}_real)0, 1, 0);
        bad += {sub}(s.w_filt) || {sub}(s.deriv) || {sub}(s.w_prev) || {sub}(s.integral) || {sub}(s.u_pending);
        for (i = 0; i < {ns}; i++) bad += {sub}(s.sf[i][0]) || {sub}(s.sf[i][1]) || {sub}(s.sf[i][2]) || {sub}(s.sf[i][3]);
        for (i = 0; i < {nt}; i++) bad += {sub}(s.tf[i][0]) || {sub}(s.tf[i][1]) || {sub}(s.tf[i][2]) || {sub}(s.tf[i][3]);
    }}
    zero = s.w_filt == 0 && s.deriv == 0;
    printf("%d %d\\n", bad, zero);
    return 0;
}}
"""


@needs_cc
@pytest.mark.parametrize("real", ("double", "float"))
@pytest.mark.parametrize("kd", (2e-5, 0.0))
def test_c_states_never_subnormal_at_rest(plant, real, kd, tmp_path):
    """After a move the axis rests for 10 s: no state of the C code is ever subnormal (tiny states
    are flushed to 0; kd = 0 skips the derivative path), and the speed filter and derivative end
    at exactly 0. The same decay without the flush does pass through subnormal numbers (checked
    on the speed filter's recursion, a = exp(-Ts/tau), in the same type)."""
    from prsa_ctrl.drive.filters import SecondOrderLowPass

    filters = (LoopFilter(Notch(1200.0, 300.0, -20.0), "torque_command"),
               LoopFilter(SecondOrderLowPass(600.0, 0.7), "speed_measurement"))
    law = drive_law(PID(0.085, 14.7, kd=kd, tf=5e-4), plant, filters=filters)
    _write_c(law, tmp_path, "sn", real)
    sub = "sub" if real == "double" else "subf"
    (tmp_path / "probe.c").write_text(SUBNORMAL_PROBE.format(name="sn", sub=sub, ns=1, nt=1))
    exe = tmp_path / "probe"
    res = subprocess.run([CC, "-std=c99", "-O1", "-o", str(exe), str(tmp_path / "probe.c"), str(tmp_path / "sn.c"),
                          "-lm"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    bad, zero = map(int, subprocess.run([str(exe)], capture_output=True, text=True, timeout=60).stdout.split())
    assert bad == 0
    assert zero == 1
    dt = np.float64 if real == "double" else np.float32
    a, w, seen = dt(law.speed_filter_a), dt(1.0), 0
    for _ in range(4000):  # the unflushed recursion: w = a w (count constant)
        w = dt(a * w)
        seen += 0 < abs(w) < np.finfo(dt).tiny
    assert seen > 0


# ---- the friction feed-forward in the generated code (issue 24, item 4; was test_drive2_friction_code) ----
# C (compiled with the system compiler) and Structured Text (compiled by matiec's iec2c) reproduce the
# simulator's torque command on a recorded run of paper-slow-reversal with the feed-forward on.

#: The speed PI of the friction feed-forward run (paper-slow-reversal).
REVERSAL_PID = PID(0.0771, 7.07)


@pytest.fixture(scope="module")
def reversal(paper_plant):
    sc = load_move_scene("paper-slow-reversal")
    pos = PositionLoop(kv=102.7, kvff=1.0, kaff=1.0, friction=FrictionFeedforward.from_plant(paper_plant, 1500.0))
    r = simulate_move(paper_plant, sc, REVERSAL_PID, pos)
    return drive_law(REVERSAL_PID, paper_plant, position=pos), replay_inputs(r, paper_plant, sc.motion(), pos), r


def test_reference_law_with_friction(reversal, paper_plant):
    law, inp, r = reversal
    assert law.position.friction is not None
    u = ReferenceLaw(law).run(inp)
    assert max_relative_difference(u, inp["torque_command"]) <= REL
    # the feed-forward matters on this run: without it the law gives another command
    bare = dataclasses.replace(law, position=dataclasses.replace(law.position, friction=None))
    assert max_relative_difference(ReferenceLaw(bare).run(inp), inp["torque_command"]) > 1e-2


@needs_cc
def test_c_with_friction_reproduces_the_simulator(reversal, tmp_path):
    law, inp, _ = reversal
    h, c = c_code(law, name="fr")
    assert "#include <math.h>" in c
    assert "fr_friction_(p, vel_ref / p->lead)" in c
    u = _run_c(_build(law, tmp_path, "double"), law, inp)
    assert max_relative_difference(u, inp["torque_command"]) <= REL


def test_structured_text_with_friction_reproduces_the_simulator(reversal, matiec, tmp_path):
    law, inp, _ = reversal
    text = st_code(law, name="FrCtrl")
    assert "EXP(-(t_FrX * t_FrX))" in text
    u = _run_st(_build_st(matiec, law, tmp_path, "double", name="FrCtrl"), law, inp)
    assert max_relative_difference(u, inp["torque_command"]) <= REL


def test_code_without_friction_has_no_exp(paper_plant):
    law = drive_law(REVERSAL_PID, paper_plant, position=PositionLoop(kv=102.7))
    h, c = c_code(law)
    assert "friction" not in c
    assert "EXP" not in st_code(law)
