"""Generated controller code (prsa_ctrl.io.codegen) against the simulator's own per-sample law.

Recorded sampled runs of the paper load-step scene and of the paper move scene give the inputs
(encoder counts, references) and the torque command the simulator applied. The Python
reference law, the C code compiled with the system compiler and the Structured Text (run by
the small ST-subset translator below) each reproduce that command sequence.
"""

from __future__ import annotations

import ctypes
import math
import re
import shutil
import subprocess

import numpy as np
import pytest

from prsa_ctrl import PID
from prsa_ctrl.studies.move import simulate_move
from prsa_ctrl.studies.movescene import load_move_scene
from prsa_ctrl.io.codegen import (DriveLaw, ReferenceLaw, c_code, drive_law, export_code, max_relative_difference,
                               replay_inputs, st_code)
from prsa_ctrl.drive.filters import FirstOrderLowPass, LoopFilter, Notch
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


CASES = ("load_step", "move", "move_scale")


def test_recorded_runs_exercise_the_law(load_step, move):
    """The recorded runs are not trivial: the load step moves the command, the move accelerates
    and saturates nothing, the filters are active."""
    _, inp, _ = load_step
    u = inp["torque_command"]
    assert np.ptp(u) > 0.3 and len(u) == 1201
    _, inp, r = move
    assert np.ptp(inp["count"]) > 5e5 and np.max(np.abs(inp["acc_ref_m_s2"])) == pytest.approx(0.5)
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

HARNESS = """
#include "{name}.h"
void run_all(int n, const int64_t *count, const double *r1, const double *r2, const double *r3,
             const int64_t *pc, double *out, int64_t cp, double w0, double i0, double t0, int64_t pz)
{{
    {name}_state s;
    int k;
    {init};
    for (k = 0; k < n; k++) out[k] = (double){name}_step(&s, {step});
    (void)r1; (void)r2; (void)r3; (void)pc; (void)pz;
}}
"""


def _build(law: DriveLaw, tmp_path, real: str, differences: str = "counts"):
    name = f"drv_{real}_{differences}"
    h, c = c_code(law, name=name, real=real, differences=differences)
    (tmp_path / f"{name}.h").write_text(h)
    (tmp_path / f"{name}.c").write_text(c)
    p = law.position
    init = f"{name}_init(&s, cp, w0, i0, t0" + (", pz)" if p is not None else ")")
    step = ("count[k], r1[k]" if p is None else
            "count[k], r1[k], r2[k], r3[k]" + (", pc[k]" if p.measured == "screw_position" else ""))
    (tmp_path / "harness.c").write_text(HARNESS.format(name=name, init=init, step=step))
    lib = tmp_path / f"lib{name}.so"
    cmd = [CC, "-std=c99", "-O2", "-fPIC", "-shared", "-ffp-contract=off", "-Wall", "-Wextra", "-Werror", "-pedantic",
           "-o", str(lib), str(tmp_path / f"{name}.c"), str(tmp_path / "harness.c")]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    return ctypes.CDLL(str(lib))


def _run_c(lib, law: DriveLaw, inp: dict) -> np.ndarray:
    n = len(inp["count"])
    d = ctypes.POINTER(ctypes.c_double)
    i64 = ctypes.POINTER(ctypes.c_int64)
    zero = np.zeros(n)
    arrs = [np.ascontiguousarray(inp["count"], np.int64)]
    if law.position is None:
        arrs += [np.ascontiguousarray(inp["speed_ref_rad_s"], float), zero, zero]
    else:
        arrs += [np.ascontiguousarray(inp[k], float) for k in ("pos_ref_m", "vel_ref_m_s", "acc_ref_m_s2")]
    arrs.append(np.ascontiguousarray(inp.get("position_count", np.zeros(n, np.int64)), np.int64))
    out = np.zeros(n)
    init = inp["init"]
    lib.run_all.restype = None
    lib.run_all.argtypes = [ctypes.c_int, i64, d, d, d, i64, d, ctypes.c_int64, ctypes.c_double, ctypes.c_double,
                            ctypes.c_double, ctypes.c_int64]
    lib.run_all(n, arrs[0].ctypes.data_as(i64), *(a.ctypes.data_as(d) for a in arrs[1:4]), arrs[4].ctypes.data_as(i64),
                out.ctypes.data_as(d), init["count_prev"], init["speed0_rad_s"], init["integral0_n_m"],
                init["torque0_n_m"], init.get("position_zero_count", 0))
    return out


@needs_cc
@pytest.mark.parametrize("differences", ("counts", "angle"))
@pytest.mark.parametrize("case", CASES)
def test_c_double_reproduces_the_simulator(case, differences, request, tmp_path):
    law, inp, _ = request.getfixturevalue(case)
    lib = _build(law, tmp_path, "double", differences)
    u = _run_c(lib, law, inp)
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


# --- Structured Text, translated back to Python ---------------------------------------------------

_TYPES = {"LREAL": float, "LINT": int, "DINT": int, "BOOL": bool}


def st_to_python(text: str):
    """Translate the ST subset the generator writes (declarations with initial values,
    assignments, IF/THEN/END_IF, RETURN, + - * /, MIN, MAX, EXP, LINT_TO_LREAL, comparisons) into a
    Python class; anything else raises."""
    text = re.sub(r"\(\*.*?\*\)", " ", text, flags=re.S)
    m = re.fullmatch(r"\s*FUNCTION_BLOCK\s+(\w+)(.*)END_FUNCTION_BLOCK\s*", text, flags=re.S)
    assert m, "not one FUNCTION_BLOCK"
    body = m.group(2)
    decls: dict[str, tuple[str, str, object]] = {}
    for sec, block in re.findall(r"(VAR_INPUT|VAR_OUTPUT|VAR CONSTANT|VAR)\s(.*?)END_VAR", body, flags=re.S):
        for stmt in filter(None, (s.strip() for s in block.split(";"))):
            mm = re.fullmatch(r"([\w\s,]+):\s*(\w+)\s*(?::=\s*(.+))?", stmt, flags=re.S)
            assert mm, f"declaration {stmt!r}"
            typ = mm.group(2)
            conv = _TYPES[typ]
            init = mm.group(3).strip() if mm.group(3) else None
            val = conv(init == "TRUE") if typ == "BOOL" else conv(float(init) if typ == "LREAL" else int(init)) \
                if init is not None else conv()
            for nm in mm.group(1).split(","):
                decls[nm.strip()] = (sec, typ, val)
    code = body[body.rfind("END_VAR") + len("END_VAR"):]
    lines, indent = [], 1

    def expr(e: str) -> str:
        e = e.strip()
        if not re.fullmatch(r"[\w\s.+\-*/(),<>=]*", e):
            raise AssertionError(f"expression outside the subset: {e!r}")
        e = re.sub(r"\bLINT_TO_LREAL\b", "float", e)
        e = re.sub(r"\bMIN\b", "min", re.sub(r"\bMAX\b", "max", e))
        e = re.sub(r"\bEXP\b", "exp", e)
        e = re.sub(r"(?<![<>:=])=(?!=)", "==", e)
        for w in re.findall(r"\b[A-Za-z_]\w*\b", e):
            assert w in decls or w in ("float", "min", "max", "exp"), f"unknown name {w!r}"
        return e

    for stmt in (s.strip() for s in code.split(";")):
        while stmt:
            mi = re.match(r"IF\s+(.*?)\s+THEN\b", stmt, flags=re.S)
            if mi:
                lines.append("    " * indent + f"if {expr(mi.group(1))}:")
                indent += 1
                stmt = stmt[mi.end():].strip()
                continue
            if stmt == "END_IF":
                indent -= 1
            elif stmt == "RETURN":
                lines.append("    " * indent + "return")
            else:
                ma = re.fullmatch(r"(\w+)\s*:=\s*(.+)", stmt, flags=re.S)
                assert ma, f"statement outside the subset: {stmt!r}"
                assert ma.group(1) in decls and decls[ma.group(1)][0] not in ("VAR CONSTANT", "VAR_INPUT"), ma.group(1)
                lines.append("    " * indent + f"{ma.group(1)} = {expr(ma.group(2))}")
            stmt = ""
    assert indent == 1, "unbalanced IF/END_IF"
    names = [k for k, v in decls.items() if v[0] != "VAR CONSTANT"]
    src = "def call():\n    global " + ", ".join(names) + "\n" + "\n".join(lines) + "\n"
    env = {k: v[2] for k, v in decls.items()} | {"exp": math.exp}
    exec(compile(src, "<st>", "exec"), env)  # noqa: S102 - the test's own translation of generated ST
    return env, {k: v[0] for k, v in decls.items()}


def _run_st(text: str, law: DriveLaw, inp: dict) -> np.ndarray:
    env, sec = st_to_python(text)
    init = inp["init"]
    env.update(Reset=True, InitCountPrev=init["count_prev"], InitSpeed=init["speed0_rad_s"],
               InitIntegral=init["integral0_n_m"], InitTorque=init["torque0_n_m"])
    if law.position is not None:
        env["InitPosZero"] = init["position_zero_count"]
    env["call"]()
    env["Reset"] = False
    n = len(inp["count"])
    out = np.empty(n)
    for k in range(n):
        env["EncCount"] = int(inp["count"][k])
        if law.position is None:
            env["SpeedRef"] = float(inp["speed_ref_rad_s"][k])
        else:
            env.update(PosRef=float(inp["pos_ref_m"][k]), VelRef=float(inp["vel_ref_m_s"][k]),
                       AccRef=float(inp["acc_ref_m_s2"][k]))
            if "position_count" in inp:
                env["PosCount"] = int(inp["position_count"][k])
        env["call"]()
        out[k] = env["TorqueCmd"]
    return out


@pytest.mark.parametrize("differences", ("counts", "angle"))
@pytest.mark.parametrize("case", CASES)
def test_structured_text_reproduces_the_simulator(case, differences, request):
    law, inp, _ = request.getfixturevalue(case)
    text = st_code(law, name="SpeedCtrl", real="double", differences=differences)
    u = _run_st(text, law, inp)
    assert max_relative_difference(u, inp["torque_command"]) <= REL


def test_structured_text_catches_a_changed_constant(load_step):
    law, inp, _ = load_step
    text = st_code(law, name="SpeedCtrl")
    bad = re.sub(r"(K_AW : LREAL := )([0-9.e+-]+)", lambda m: m.group(1) + repr(float(m.group(2)) * 1.001), text)
    bad = re.sub(r"(KI : LREAL := )([0-9.e+-]+)", lambda m: m.group(1) + repr(float(m.group(2)) * (1 + 1e-6)), bad)
    assert bad != text
    assert max_relative_difference(_run_st(bad, law, inp), inp["torque_command"]) > 1e3 * REL


def test_st_translator_refuses_what_it_does_not_know():
    with pytest.raises(AssertionError):
        st_to_python("FUNCTION_BLOCK X\nVAR\n A : LREAL := 0.0;\nEND_VAR\nA := SQRT(A);\nEND_FUNCTION_BLOCK\n")
    with pytest.raises(AssertionError):
        st_to_python("FUNCTION_BLOCK X\nVAR\n A : LREAL := 0.0;\nEND_VAR\nWHILE A < 1.0 DO A := A + 1.0; END_WHILE;\n"
                     "END_FUNCTION_BLOCK\n")


def test_real_float_types_in_st(load_step):
    law, _, _ = load_step
    text = st_code(law, name="SpeedCtrl", real="float")
    assert "LREAL" not in text and "LINT_TO_REAL(" in text and " : REAL := " in text


# --- export_code and bad input -------------------------------------------------------------------

def test_export_code_writes_by_suffix(plant, tmp_path):
    files = export_code(SPEED_PID, plant, tmp_path / "drive.c", filters=FILTERS)
    assert [f.name for f in files] == ["drive.c", "drive.h"]
    assert '#include "drive.h"' in files[0].read_text() and "drive_step(" in files[1].read_text()
    files = export_code(SPEED_PID, plant, tmp_path / "Speed Loop.st", real="float")
    assert files[0].read_text().startswith("FUNCTION_BLOCK prsa_ctrl")


def test_export_code_of_a_cascade_design(plant, tmp_path):
    from prsa_ctrl.tuning.cascade import CascadeDesign

    d = CascadeDesign("joint", MOVE_PID, PositionLoop(kv=102.7, kvff=1.0, kaff=1.0), {}, {}, {}, 0.0)
    law = drive_law(d, plant)
    assert law.position is not None and law.position.kv == 102.7
    text = export_code(d, plant, tmp_path / "cascade.st")[0].read_text()
    assert "PosRef" in text and "KAFF_J" in text


@pytest.mark.parametrize("kwargs, match", [
    ({"real": "long double"}, "real = 'long double'"),
    ({"name": "1abc"}, "name = '1abc'"),
    ({"differences": "rad"}, "differences = 'rad'"),
])
def test_bad_arguments_name_themselves(plant, kwargs, match):
    law = drive_law(SPEED_PID, plant)
    with pytest.raises(ValueError, match=re.escape(match)):
        c_code(law, **kwargs)


def test_bad_export_arguments(plant, tmp_path):
    with pytest.raises(ValueError, match="expected a file name ending in .c or .st"):
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
    assert np.max(np.abs(inp["speed_ref_rad_s"] - rf)) < 1e-9 and np.max(np.abs(rf - r_raw)) > 1.0
    inp["speed_ref_rad_s"] = r_raw
    inp["init"]["integral0_n_m"] -= pid.kp * (b - 1) * r_raw[0]
    law = drive_law(pid, plant, setpoint_weight=b)
    u = ReferenceLaw(law).run(inp)
    assert max_relative_difference(u, inp["torque_command"]) < 1e-9
    if CC is not None:
        assert max_relative_difference(_run_c(_build(law, tmp_path, "double"), law, inp), inp["torque_command"]) < 1e-9
    assert max_relative_difference(_run_st(st_code(law), law, inp), inp["torque_command"]) < 1e-9
    from dataclasses import replace

    assert max_relative_difference(ReferenceLaw(replace(law, setpoint_weight=1.0)).run(inp), inp["torque_command"]) > 0.05


# --- prsa-tune --export PATH.c / PATH.st --------------------------------------------------------

def test_cli_export_c_writes_source_and_header(tmp_path, capsys):
    from prsa_ctrl.cli.tune import main

    out = tmp_path / "speed.c"
    assert main(["--quiet", "--export", str(out), "--json", str(tmp_path / "r.json")]) == 0
    assert out.exists() and (tmp_path / "speed.h").exists()
    import json

    best = json.loads((tmp_path / "r.json").read_text())["best"]
    kp = float(re.search(r"KP = \(speed_real\)([0-9.e+-]+);", out.read_text()).group(1))
    assert kp == best["gains"]["kp"] and best["gains"]["b"] == 1.0
    if CC is not None:
        res = subprocess.run([CC, "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-c", str(out), "-o",
                              str(tmp_path / "speed.o")], capture_output=True, text=True, timeout=120)
        assert res.returncode == 0, res.stderr


def test_cli_export_st_float(tmp_path):
    from prsa_ctrl.cli.tune import main

    out = tmp_path / "Speed.st"
    assert main(["--quiet", "--export", str(out), "--export-real", "float"]) == 0
    text = out.read_text()
    assert text.startswith("FUNCTION_BLOCK Speed") and "LREAL" not in text
    st_to_python(text.replace("REAL", "LREAL").replace("LINT_TO_LLREAL", "LINT_TO_LREAL"))  # parses in the subset


def test_cli_export_bad_suffix_and_header_onto_an_input(tmp_path, capsys):
    from prsa_ctrl.cli.tune import main

    assert main(["--export", str(tmp_path / "x.cpp")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "expected a path ending in .json, .toml, .c or .st" in err[0]
    plant = tmp_path / "mine.h"  # a plant file whose name the header of --export mine.c would take
    from prsa_ctrl.plant.plantfile import plant_file_path

    plant.write_text(plant_file_path("paper-iprsm").read_text())
    before = plant.read_text()
    assert main(["--plant", str(plant), "--export", str(tmp_path / "mine.c")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "mine.h" in err[0] and "--export (header)" in err[0]
    assert plant.read_text() == before and not (tmp_path / "mine.c").exists()


def test_cli_move_scene_export_st(tmp_path):
    """The cascade of the move scene as a function block (position loop with feed-forward)."""
    from prsa_ctrl.cli.tune import main

    out = tmp_path / "Axis.st"
    assert main(["--scene", "paper-move", "--quiet", "--export", str(out), "--json", str(tmp_path / "m.json")]) == 0
    import json

    joint = json.loads((tmp_path / "m.json").read_text())["joint"]
    text = out.read_text()
    kv = float(re.search(r"KV : LREAL := ([0-9.e+-]+);", text).group(1))
    assert kv == joint["position"]["kv_per_s"]
    st_to_python(text)


def test_replay_refuses_runs_the_code_does_not_describe(plant):
    r = run(plant, load=500.0, duration=0.01, controller=PID(0.085, 14.7), fidelity="rigid")
    with pytest.raises(ValueError, match="run is continuous"):
        replay_inputs(r, plant)
    r = run(plant, load=500.0, duration=0.01, controller=PID(0.085, 14.7), fidelity="rigid", discrete=True,
            measurement="kf")
    with pytest.raises(ValueError, match="run measured the speed with 'kf'"):
        replay_inputs(r, plant)
