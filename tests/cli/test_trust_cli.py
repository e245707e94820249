"""Trust on foreign ground (issue 20), the command-line part: outputs never clobber an input or
the package's own files and are written all or nothing; a symlink loop, a name too long, a bad
--scheduler, an out-of-range scene value or a plant unit mistake stop before any work in one
line (exit 2); Ctrl-C at any moment ends with exit 130 and one true line; the report's
differences and verdicts say what the numbers say.

Subprocess tests run the real console entry (``python -m prsa_ctrl.cli.tune``); the in-process ones
replace the expensive work by a stand-in that counts its calls (a step budget of zero for
refused input)."""

import json
import math
import os
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from prsa_ctrl.cli.tune import main

REPO = Path(__file__).resolve().parents[2]
SCENES = REPO / "tuning"
PLANTS = REPO / "plants"


def _env():
    env = dict(os.environ, MPLBACKEND="Agg", PYTHONDONTWRITEBYTECODE="1")
    env.pop("PYTHONWARNINGS", None)
    return env


def _run(args, cwd, module="prsa_ctrl.cli.tune", timeout=300):
    return subprocess.run([sys.executable, "-m", module, *args], cwd=cwd, env=_env(), capture_output=True,
                          text=True, timeout=timeout)


def _script(code, cwd, timeout=300):
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=cwd, env=_env(), capture_output=True,
                          text=True, timeout=timeout)


def _one_error(proc, *needles):
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]



# --- hostile 1, 2: inputs and the package's own files are never outputs -------------------------

def test_a_scene_trace_csv_is_an_input_and_never_an_output(tmp_path):
    for f in ("duty-trace.toml", "duty-trace.csv"):
        shutil.copy(SCENES / f, tmp_path / f)
    before = (tmp_path / "duty-trace.csv").read_bytes()
    p = _run(["--scene", "duty-trace.toml", "--json", "duty-trace.csv"], tmp_path)
    _one_error(p, "--json 'duty-trace.csv'", "input file")
    assert (tmp_path / "duty-trace.csv").read_bytes() == before


def _installed_folder(package):
    """Where the installed package keeps its data (the repository's folder in an editable
    install, site-packages otherwise): the place a user's run must not write into."""
    from importlib.resources import files

    return Path(os.fspath(files(package)))


@pytest.mark.parametrize("flag, package, name", [("--json", "prsa_ctrl.plants", "zz-trust-test.json"),
                                                 ("--export", "prsa_ctrl.scenes", "zz-trust-test.toml")])
def test_outputs_inside_the_package_data_are_refused(tmp_path, flag, package, name):
    target = _installed_folder(package) / name
    assert not target.exists()
    try:
        p = _run([flag, str(target)], tmp_path)
        _one_error(p, flag, "package's own files")
        assert not target.exists()
    finally:
        if target.exists():
            target.unlink()


def test_the_built_in_plant_file_itself_is_refused_before_any_work(tmp_path, stand_in, capsys):
    from prsa_ctrl.plant.plantfile import plant_file_path

    path = Path(str(plant_file_path("paper-iprsm")))
    before = path.read_bytes()
    assert main(["--json", str(path)]) == 2 and not stand_in
    assert "package's own files" in capsys.readouterr().err
    assert path.read_bytes() == before


# --- hostile 4, 13: every output path checked up front, all or nothing --------------------------

def test_a_245_character_export_name_is_written_with_the_other_outputs(tmp_path):
    name = "x" * 245 + ".toml"
    p = _run(["--export", name, "--json", "j.json", "--plots", "pl"], tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    assert (tmp_path / name).is_file() and json.loads((tmp_path / "j.json").read_text())["status"] == "ok"
    assert len(list((tmp_path / "pl").iterdir())) >= 2
    assert not [f for f in tmp_path.rglob("*") if ".prsa-tmp-" in f.name]


def test_a_name_over_name_max_is_refused_before_anything_is_written(tmp_path):
    name = "x" * 260 + ".toml"
    p = _run(["--export", name, "--json", "j.json", "--plots", "pl"], tmp_path)
    _one_error(p, "--export", "265 bytes long", "at most 255")
    assert sorted(os.listdir(tmp_path)) == []


def test_symlink_loop_outputs_are_refused_in_one_line_before_any_work(tmp_path, stand_in, capsys):
    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    p = _run(["--json", "a"], tmp_path)
    _one_error(p, "--json 'a'", "symlink loop")
    for flag in ("--json", "--export", "--plots"):
        arg = str(tmp_path / "a") + (".toml" if flag == "--export" else "")
        if flag == "--export":
            (tmp_path / "a.toml").symlink_to(tmp_path / "a.toml")
        assert main([flag, arg]) == 2 and not stand_in
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "symlink loop" in err[0], err


def test_a_failing_output_leaves_every_other_output_as_it_was(tmp_path, monkeypatch):
    """Transaction: the second file's producer fails -> the first target keeps its old content."""
    from prsa_ctrl.io.output import Transaction

    (tmp_path / "a.json").write_text("old a")
    with pytest.raises(RuntimeError):
        with Transaction() as tr:
            tr.stage(tmp_path / "a.json", lambda tmp: tmp.write_text("new a"))
            tr.make_directory(tmp_path / "figs")
            tr.stage(tmp_path / "figs" / "b.png", lambda tmp: (_ for _ in ()).throw(RuntimeError("render failed")))
            tr.commit()
    assert (tmp_path / "a.json").read_text() == "old a" and sorted(os.listdir(tmp_path)) == ["a.json"]


# --- hostile 14: --scheduler checked and connected before the tuning ----------------------------

@pytest.mark.parametrize("address, needle", [("tcp://127.0.0.1:1", "cannot connect"),
                                             ("tcp://127.0.0.1:99999", "port 99999 out of range"),
                                             ("tcp://127.0.0.1", "no port"),
                                             ("tls://127.0.0.1:8786", "TLS"),
                                             ("127.0.0.1:8786", "expected 'local' or tcp://HOST:PORT")])
def test_bad_scheduler_addresses_stop_before_the_tuning(address, needle, stand_in, capsys):
    rc = main(["--scene", "robust-load-step", "--monte-carlo", "2", "--scheduler", address])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and not stand_in, (rc, err)
    assert len(err) == 1 and err[0].startswith(f"prsa-tune: error: --scheduler {address!r}") and needle in err[0], err


def test_unreachable_scheduler_is_exit_2_from_the_console_entry(tmp_path):
    p = _run(["--scene", "robust-load-step", "--monte-carlo", "2", "--scheduler", "tcp://127.0.0.1:1"], tmp_path)
    _one_error(p, "--scheduler 'tcp://127.0.0.1:1'", "cannot connect")


# --- hostile 15: scene values out of range name the file and the key ----------------------------

def _robust_scene(tmp_path, edit, extra=""):
    text = (SCENES / "robust-load-step.toml").read_text()
    text = edit(text) + extra
    path = tmp_path / "r.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("edit, needles", [
    (lambda t: re.sub(r"(?m)^setpoints_rpm = .*$", "setpoints_rpm = [1e9]", t), ["robust.setpoints_rpm", "1e+09 rpm", "expected nut speeds"]),
    (lambda t: re.sub(r"(?m)^setpoints_rpm = .*$", "setpoints_rpm = [0.001]", t), ["robust.setpoints_rpm", "0.001 rpm", "expected nut speeds"]),
    (lambda t: re.sub(r"(?m)^final_loads_n = \[1500.0\]$", "final_loads_n = [1e7]", t), ["robust.final_loads_n", "1e+07 N", "expected loads up to"]),
    (lambda t: re.sub(r'(?m)^"drive.current_loop_bandwidth_hz".*$',
                      '"drive.torque_limit_n_m" = { dist = "uniform", low = 0.3, high = 3.0, source = "assumption: t" }', t),
     ["drive.torque_limit_n_m = 0.3", "holds at most", "1500 N"]),
    (lambda t: t.replace("[outputs]", "[estimator]\nload_change_time_s = 1e300\n\n[outputs]"),
     ["estimator.load_change_time_s = 1e+300", "expected a positive time in [0.001, 1000] s"]),
])
def test_scene_values_out_of_range_name_file_and_key_before_the_tuning(tmp_path, edit, needles, stand_in, capsys):
    path = _robust_scene(tmp_path, edit)
    assert main(["--scene", str(path), "--monte-carlo", "0"]) == 2 and not stand_in
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0], err
    for n in needles:
        assert n in err[0], (n, err[0])


def test_jointly_invalid_uncertainty_names_the_scene_and_both_keys(tmp_path, stand_in, capsys):
    path = _robust_scene(tmp_path, lambda t: t.split("[uncertainty]")[0] + t.split("[uncertainty]")[1].split("\n\n", 1)[1],
                         textwrap.dedent('''
                         [uncertainty]
                         "friction.static" = { dist = "uniform", low = 0.26, high = 0.34, source = "assumption: t" }
                         "friction.dynamic" = { dist = "uniform", low = 0.2, high = 0.3, source = "assumption: t" }
                         '''))
    assert main(["--scene", str(path), "--monte-carlo", "0"]) == 2 and not stand_in
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"prsa-tune: error: {path}:"), err
    assert "friction.static" in err[0] and "friction.dynamic" in err[0] and "built-in" not in err[0], err


# --- hostile 17: Ctrl-C at any point: exit 130, one true line, outputs all old or all new ---------

_INTERRUPT_AT_FIRST_RENAME = """
import os, signal, sys
real, fired = os.replace, []
def replace(a, b):
    real(a, b)
    if not fired:
        fired.append(1)
        os.kill(os.getpid(), signal.SIGINT)
os.replace = replace
from prsa_ctrl.cli.tune import main
sys.argv = ["prsa-tune", "--json", "j.json", "--export", "e.json"]
raise SystemExit(main())
"""


def test_ctrl_c_while_the_outputs_are_renamed_leaves_all_old_or_all_new(tmp_path):
    (tmp_path / "j.json").write_text("old j")
    (tmp_path / "e.json").write_text("old e")
    p = _script(_INTERRUPT_AT_FIRST_RENAME, tmp_path)
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 130 and len(lines) == 1 and "Traceback" not in p.stderr, (p.returncode, p.stderr[-2000:])
    j, e = (tmp_path / "j.json").read_text(), (tmp_path / "e.json").read_text()
    if j == "old j" or e == "old e":
        assert (j, e) == ("old j", "old e") and "no output written" in lines[0], (j[:20], e[:20], lines)
    else:
        assert json.loads(j)["status"] == "ok" and "kp" in json.dumps(json.loads(e))
        assert "no output written" not in lines[0] and "j.json" in lines[0] and "e.json" in lines[0], lines


_INTERRUPT_AFTER_THE_COMMAND = """
import os, signal, sys
import prsa_ctrl.cli.common as cli
from prsa_ctrl.cli.tune import main
inner = cli.invoke_inner
def wrapped(*a, **k):
    code = inner(*a, **k)
    os.kill(os.getpid(), signal.SIGINT)
    return code
cli.invoke_inner = wrapped
sys.argv = ["prsa-tune", "--json", "j.json", "--quiet"]
raise SystemExit(main())
"""


def test_ctrl_c_after_the_command_finished_is_exit_130_with_one_line(tmp_path):
    p = _script(_INTERRUPT_AFTER_THE_COMMAND, tmp_path)
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 130 and len(lines) == 1 and "Traceback" not in p.stderr, (p.returncode, p.stderr[-2000:])
    assert "interrupted (Ctrl-C)" in lines[0] and "j.json" in lines[0], lines
    assert json.loads((tmp_path / "j.json").read_text())["status"] == "ok"


# --- hostile 19: prsa-bench --out and --repeats -------------------------------------------------

#: The benchmarks, outside the package (issue 22): ``python benchmarks/bench.py``.
BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "bench.py"


def _bench_module():
    import importlib.util

    spec = importlib.util.spec_from_file_location("bench", BENCH)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    return bench


@pytest.mark.parametrize("out", ["/etc/passwd", "/proc/x", "loop"])
def test_bench_out_is_checked_in_one_line(tmp_path, out):
    (tmp_path / "loop").symlink_to(tmp_path / "loop")
    p = subprocess.run([sys.executable, str(BENCH), "--out", out, "--fast"], cwd=tmp_path, env=_env(),
                       capture_output=True, text=True, timeout=300)
    _one_error(p, "bench: error: --out")


@pytest.mark.parametrize("args, needle", [(["--repeats", "0"], "--repeats 0"), (["--repeats", "21"], "--repeats 21"),
                                          (["--repeats", "x"], "--repeats"), (["--samples", "0"], "--samples 0")])
def test_bench_bad_counts_are_refused_before_any_benchmark(tmp_path, monkeypatch, capsys, args, needle):
    bench = _bench_module()

    def never(*a, **k):
        raise AssertionError("a benchmark ran")

    for name in ("work_precision", "fidelity_ladder", "tuning_benchmark", "monte_carlo_benchmark",
                 "robust_tuning_benchmark", "fit_benchmark", "cold_cli_benchmark"):
        monkeypatch.setattr(bench, name, never)
    assert bench.main([*args, "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0], err
    assert not (tmp_path / "b").exists()


# --- hostile 20: a byte-order mark is accepted ----------------------------------------------------

def test_plant_and_scene_files_with_a_byte_order_mark_load(tmp_path, stand_in, capsys):
    from prsa_ctrl import load_plant, load_scene

    plant = tmp_path / "bom-plant.toml"
    plant.write_bytes(b"\xef\xbb\xbf" + (PLANTS / "paper-iprsm.toml").read_bytes())
    scene = tmp_path / "bom-scene.toml"
    scene.write_bytes(b"\xef\xbb\xbf" + (SCENES / "paper-load-step.toml").read_bytes())
    assert load_plant(plant).values == load_plant("paper-iprsm").values
    assert load_scene(scene).final_loads == load_scene("paper-load-step").final_loads
    assert main(["--plant", str(plant), "--scene", str(scene)]) == 3 and len(stand_in) == 1  # reached the tuner
    assert "stand-in" in capsys.readouterr().err


# --- section 4: unit mistakes in the plant file --------------------------------------------------

def _plant_text(key, value):
    section, sub = key.split(".")
    text = (PLANTS / "paper-iprsm.toml").read_text()
    block = text.split(f"[{section}]")[1]
    line = next(l for l in block.splitlines() if l.startswith(f"{sub} = "))
    return text.replace(line, re.sub(r"value = [^,]+,", f"value = {value},", line), 1)


@pytest.mark.parametrize("key, value, needles", [
    ("sensor.encoder_counts_per_rev", "17", ["sensor.encoder_counts_per_rev = 17", "[64,", "bits", "131072 counts"]),
    ("drive.torque_limit_n_m", "20000.0", ["drive.torque_limit_n_m = 20000 N m", "rated_load_n = 5000 N", "mN m typed as N m"]),
    ("sensor.speed_filter_time_constant_s", "0.2", ["sensor.speed_filter_time_constant_s = 0.2 s", "800 controller samples", "ms typed as s"]),
    ("sensor.torque_noise_n_m", "0.5", ["sensor.torque_noise_n_m = 0.5 N m", "10%"]),
    ("friction.no_load_torque_n_m", "5.0", ["friction.no_load_torque_n_m = 5 N m", "drive.torque_limit_n_m = 3"]),
    ("friction.traction_preload_n", "20000.0", ["friction.traction_preload_n = 20000 N", "screw.rated_load_n"]),
])
def test_plant_unit_mistakes_stop_in_one_line_naming_the_key(tmp_path, key, value, needles, stand_in, capsys):
    path = tmp_path / "p.toml"
    path.write_text(_plant_text(key, value))
    assert main(["--plant", str(path)]) == 2 and not stand_in
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0], err
    for n in needles:
        assert n in err[0], (n, err[0])


def test_the_built_in_plants_pass_the_cross_checks():
    from prsa_ctrl import load_plant
    from prsa_ctrl.plant.plantfile import TORQUE_LIMIT_MAX_RATIO, builtin_plants

    for name in builtin_plants():
        v = load_plant(name).values
        t_rated = v["screw.rated_load_n"] * v["screw.lead_mm"] * 1e-3 / (2 * math.pi * v["friction.efficiency"])
        assert 1.0 < v["drive.torque_limit_n_m"] / t_rated < TORQUE_LIMIT_MAX_RATIO / 5


def test_an_encoder_too_coarse_for_the_setpoint_names_the_encoder(tmp_path, stand_in, capsys):
    path = tmp_path / "p.toml"
    path.write_text(_plant_text("sensor.encoder_counts_per_rev", "100"))  # plausible, but 2400 rpm per count and sample
    assert main(["--plant", str(path)]) == 2 and not stand_in
    err = capsys.readouterr().err.strip()
    assert "sensor.encoder_counts_per_rev = 100" in err and "at least 800 counts" in err, err


def test_encoder_in_bits_from_the_console_entry(tmp_path):
    (tmp_path / "p.toml").write_text(_plant_text("sensor.encoder_counts_per_rev", "17"))
    _one_error(_run(["--plant", "p.toml"], tmp_path), "sensor.encoder_counts_per_rev = 17", "bits")


# --- section 4: the report ------------------------------------------------------------------------

def test_differences_are_percentages_only_above_the_resolution():
    from prsa_ctrl.cli.report import diff_text as _diff_text

    assert _diff_text(1.4e-14, 1.4e-4, res=0.0365) == "-0.00014 abs."
    # issue 24: even with no resolution given, a value at numerical zero against a real one is no percentage
    assert _diff_text(1.4e-14, 1.4e-4) == "-0.00014 abs."
    assert _diff_text(3.67, 3.651, res=0.0365) == "+0.5 %"
    assert _diff_text(-2.833, -2.8, res=0.01) == "-1.2 %"  # relative to |verified|
    assert _diff_text(float("inf"), 0.1) == "-"


def test_table_and_flag_use_one_definition_of_the_difference():
    import dataclasses

    from prsa_ctrl import load_plant, load_scene
    from prsa_ctrl.studies.autotune import health_flags, tune_actuator
    from prsa_ctrl.cli.report import diff_text as _diff_text

    rep = tune_actuator(load_plant(), load_scene(), workers=1)
    v = rep.best.objective_verified
    d = dataclasses.replace(rep.best, objective_predicted=v * 1e-3)  # a prediction 1000x too small (Design is frozen)
    flag = next(f for f in health_flags(d, rep.plant, rep.scene) if "departs from the linear prediction" in f)
    assert "-99.9 %" in flag and _diff_text(d.objective_predicted, v) == "-99.9 %", flag


def test_a_baseline_not_beaten_says_why_in_the_table():
    from prsa_ctrl.cli.report import beaten_text as _beaten_text

    base = {"beaten": False, "tuned_flags": [], "tuned_ms": 1.4, "baseline_ms": 1.5,
            "tuned_objective_verified": 0.01, "baseline_objective_verified": 0.02}
    assert _beaten_text({**base, "tuned_flags": ["never recovers"]}, "IAE") == "no: tuned design flagged"
    assert _beaten_text({**base, "tuned_ms": 1.6}, "IAE") == "no: tuned Ms higher"
    assert _beaten_text({**base, "tuned_objective_verified": 0.03}, "IAE") == "no: IAE not lower"
    assert _beaten_text({**base, "beaten": True}, "IAE") == "yes"


def test_one_name_per_design_in_the_monte_carlo():
    from prsa_ctrl.cli.tune import _add_design
    from prsa_ctrl.drive.pid import PID

    designs = {"nominal design": PID(0.08, 14.0), "robust design": PID(0.04, 4.0)}
    _add_design(designs, "tuned (Ms <= 1.4)", PID(0.08, 14.0))
    _add_design(designs, "SIMC", PID(0.13, 23.0))
    assert list(designs) == ["nominal design", "robust design", "SIMC"]


def test_the_plain_report_has_no_percentage_of_a_value_at_numerical_zero(tmp_path):
    p = _run([], tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    row = next(l for l in p.stdout.splitlines() if l.startswith("steady-state error"))
    assert row.rstrip().endswith("abs.") and "%" not in row, row
    assert "difference = (predicted - verified) / |verified|" in p.stdout
