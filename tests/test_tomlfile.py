"""The one reader of a user's TOML (issue 31): an integer beyond the float range and a nesting
deep enough to overflow the parser are bad input -- exit 2, one line naming the file and the key
-- in a plant, a scene, a scene's [filters], a plant's uncertainty correlation and a log
description (they were exit 3 "non-finite numbers (OverflowError)" / "failed (RecursionError)")."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from prsa_ctrl.cli.fit import main as fit_main
from prsa_ctrl.cli.tune import main as tune_main
from prsa_ctrl.tomlfile import NESTING_MAX, read_toml

ROOT = Path(__file__).resolve().parents[1]
PAPER = (ROOT / "plants" / "paper-iprsm.toml").read_text(encoding="utf-8")
SCENE = (ROOT / "tuning" / "paper-load-step.toml").read_text(encoding="utf-8")
HUGE = "1" + "0" * 400  # 1e400: an int for tomllib, beyond every float
CORRELATION = ('\n"correlation" = { keys = ["nut.inertia_kg_m2", "drive.current_loop_bandwidth_hz"], '
               'matrix = [[1.0, 0.5], [0.5, 1.0]], source = "estimate: test" }\n')
LOG_FORMAT = ('axis = "linear"\n[time]\nname = "t"\nunit = "s"\n[position]\nname = "x_mm"\nunit = "mm"\n'
              '[command]\nname = "f_n"\nunit = "N"\nlogged = "as-applied"\n[load]\nname = "fz"\nunit = "N"\n')


def _sub(text: str, old: str, new: str) -> str:
    assert text.count(old) == 1, old
    return text.replace(old, new)


def _plant_with_correlation(matrix: str) -> str:
    return PAPER + CORRELATION.replace("[[1.0, 0.5], [0.5, 1.0]]", matrix)


def _scene_with_filter(centre: str) -> str:
    return SCENE + f'\n[[filters.notch]]\npath = "torque"\ncentre_hz = {centre}\nwidth_hz = 40.0\n'


def _deep(n: int) -> str:
    return "[" * n + "1.0" + "]" * n


def test_the_bases_are_valid(tmp_path, capsys):
    """The files below differ from these only in the bad number: these load."""
    (tmp_path / "p.toml").write_text(_plant_with_correlation("[[1.0, 0.5], [0.5, 1.0]]"))
    assert tune_main(["--show-plant", str(tmp_path / "p.toml")]) == 0
    from prsa_ctrl.identification.logformat import load_log_format
    from prsa_ctrl.studies.scene import load_scene

    (tmp_path / "s.toml").write_text(_scene_with_filter("163.0"))
    assert load_scene(str(tmp_path / "s.toml")).filters
    (tmp_path / "f.toml").write_text(LOG_FORMAT)
    load_log_format(tmp_path / "f.toml")


CASES = {
    # name: (file kind, text, key the message names)
    "plant-int": ("plant", _sub(PAPER, "static = { value = 0.3,", f"static = {{ value = {HUGE},"),
                  "friction.static.value"),
    "correlation-int": ("plant", _plant_with_correlation(f"[[1.0, {HUGE}], [0.5, 1.0]]"),
                        "uncertainty.correlation.matrix[0][1]"),
    "plant-deep": ("plant", PAPER + f"\n[extra]\nx = {_deep(3000)}\n", "'x'"),
    "scene-int": ("scene", _sub(SCENE, "final_loads_n = [1500.0]", f"final_loads_n = [{HUGE}]"),
                  "operating.final_loads_n[0]"),
    "filter-int": ("scene", _scene_with_filter(HUGE), "filters.notch[0].centre_hz"),
    "scene-deep": ("scene", _sub(SCENE, "final_loads_n = [1500.0]", f"final_loads_n = {_deep(3000)}"),
                   "'final_loads_n'"),
    "filter-inline-deep": ("scene", SCENE + "\n[filters]\nnotch = " + "{a = " * 2000 + "1" + "}" * 2000 + "\n",
                           "'notch'"),
    "log-int": ("log", LOG_FORMAT + f"[controller]\nkp = {HUGE}\n", "controller.kp"),
    "log-deep": ("log", LOG_FORMAT + f"[controller]\nkp = {_deep(3000)}\n", "'kp'"),
    "plant-digits": ("plant", _sub(PAPER, "static = { value = 0.3,", "static = { value = 1" + "0" * 5000 + ","),
                     "'static'"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_toml_numbers_and_nesting_are_bad_input(case, tmp_path, capsys):
    kind, text, key = CASES[case]
    f = tmp_path / f"{case}.toml"
    f.write_text(text, encoding="utf-8")
    capsys.readouterr()
    if kind == "plant":
        rc = tune_main(["--show-plant", str(f)])
        prog = "prsa-tune"
    elif kind == "scene":
        rc = tune_main(["--scene", str(f), "--json", str(tmp_path / "out.json")])
        prog = "prsa-tune"
    else:
        (tmp_path / "log.csv").write_text("t,x_mm,f_n,fz\n0,0,0,0\n")
        rc = fit_main([str(tmp_path / "log.csv"), "--log-format", str(f), "--plant", "ballscrew-32x10",
                       "--out", str(tmp_path / "out.toml")])
        prog = "prsa-fit"
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert len(err.splitlines()) == 1, err
    assert err.startswith(f"{prog}: error: "), err
    assert str(f) in err, err
    assert key in err, err
    assert "Overflow" not in err, err
    assert "Recursion" not in err, err
    assert len(err) < 400, err
    assert not (tmp_path / "out.json").exists()
    assert not (tmp_path / "out.toml").exists()


def test_read_toml_bounds_nesting_below_the_parsers_limit():
    ok = read_toml(f"x = {_deep(NESTING_MAX - 1)}", "f.toml", ValueError)
    assert ok["x"] is not None
    with pytest.raises(ValueError, match=r"^f\.toml: x\[\.\.\.\] nests arrays or tables more than 32 levels"):
        read_toml(f"x = {_deep(NESTING_MAX + 5)}", "f.toml", ValueError)


def test_read_toml_keeps_large_finite_integers_and_the_float_edge():
    big = int(sys.float_info.max)  # the largest float, written as an integer: still a float
    doc = read_toml(f"a = {big}\nb = -{big}\nc = 9007199254740993", "f.toml", ValueError)
    assert doc == {"a": big, "b": -big, "c": 9007199254740993}
    with pytest.raises(ValueError, match=r"^f\.toml: a = .*an integer of 310 digits\): beyond the floating-point"):
        read_toml(f"a = {10 * big}", "f.toml", ValueError)


def test_brackets_in_strings_do_not_count_as_nesting():
    text = 's = "[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[["\nm = """\n' + "{" * 100 + '\n"""\n# ' + "[" * 100 + "\nk = 1\n"
    assert read_toml(text, "f.toml", ValueError)["k"] == 1
