"""Data loss (issue 13): the one output writer and the CLI's output rules. No tuning runs here:
a stand-in for the expensive work counts its calls (a step budget of zero for bad paths)."""

import os
import stat
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from prsa_ctrl.io import output
from prsa_ctrl.cli.tune import main, plot_main
from prsa_ctrl.io.output import OutputError, check_directory, check_writable, make_directory, write_file, write_text

PLANT_DIR = Path(__file__).resolve().parents[2] / "plants"


def _no_temporaries(d: Path) -> bool:
    return not [p for p in d.iterdir() if output.TEMP_MARK in p.name]


def test_symlink_is_written_through_and_stays_a_link(tmp_path):
    target = tmp_path / "real.json"
    target.write_text("old\n")
    link = tmp_path / "link.json"
    link.symlink_to(target)
    write_text(link, "new\n")
    assert link.is_symlink()
    assert target.read_text() == "new\n"
    assert _no_temporaries(tmp_path)


def test_existing_mode_is_kept_and_new_files_follow_the_umask(tmp_path):
    old = tmp_path / "shared.json"
    old.write_text("x")
    os.chmod(old, 0o640)
    write_text(old, "y")
    assert stat.S_IMODE(old.stat().st_mode) == 0o640
    mask = os.umask(0o027)
    try:
        new = write_text(tmp_path / "new.json", "z")
    finally:
        os.umask(mask)
    assert stat.S_IMODE(new.stat().st_mode) == 0o640  # 0o666 & ~0o027


@pytest.mark.parametrize("exc", [RuntimeError("producer failed"), KeyboardInterrupt()])
def test_failed_or_interrupted_write_keeps_old_file_and_leaves_no_temporary(tmp_path, exc):
    f = tmp_path / "out.json"
    f.write_text("previous\n")

    def producer(tmp):
        tmp.write_text("half")
        raise exc

    with pytest.raises(type(exc)):
        write_file(f, producer)
    assert f.read_text() == "previous\n"
    assert _no_temporaries(tmp_path)
    assert output.live_temporaries() == []


def test_temporary_has_a_recognisable_name_in_the_target_directory(tmp_path):
    seen = []
    write_file(tmp_path / "r.json", lambda tmp: (seen.append(tmp), tmp.write_text("{}")))
    assert seen[0].parent == tmp_path
    assert seen[0].name.startswith(".r.json" + output.TEMP_MARK)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda d: "", r"expected a file path"),
        (lambda d: str(d), r"is a directory"),
        (lambda d: "/dev/null", r"not a regular file"),
        (lambda d: str(d / "missing" / "x.json"), r"directory .*missing.* does not exist"),
        (lambda d: "/proc/nope.json", r"cannot create a file in directory '/proc'"),
        (lambda d: "-", r"standard output is not an output of these tools.*\./-"),
    ],
)
def test_bad_output_files_are_refused(tmp_path, make, match):
    with pytest.raises(OutputError, match=match):
        check_writable(make(tmp_path), flag="--json")


def test_input_files_are_never_outputs_even_through_links(tmp_path):
    plant = tmp_path / "myplant.toml"
    plant.write_text("data")
    hard = tmp_path / "hard.toml"
    os.link(plant, hard)
    soft = tmp_path / "soft.toml"
    soft.symlink_to(plant)
    for p in (plant, hard, soft, tmp_path / "sub" / ".." / "myplant.toml"):
        (tmp_path / "sub").mkdir(exist_ok=True)
        with pytest.raises(OutputError, match="input file of this run"):
            write_text(p, "report", inputs=[str(plant)])
    assert plant.read_text() == "data"


def test_directories_under_a_file_or_unwritable_are_refused(tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(OutputError, match="not a directory"):
        check_directory(f / "figs", "--plots")
    with pytest.raises(OutputError, match="exists and is not a directory"):
        check_directory(f, "--plots")
    with pytest.raises(OutputError, match="cannot create a file"):
        check_directory("/proc/nope", "--plots")
    created = make_directory(tmp_path / "a" / "b", "--plots")
    assert [p.name for p in created] == ["a", "b"]
    output.remove_created(created)
    assert not (tmp_path / "a").exists()


@settings(max_examples=40)
@given(st.text(alphabet=st.sampled_from("ab./ \x01-_~"), max_size=12))
def test_any_path_text_is_written_or_refused_with_one_line(tmp_path_factory, name):
    d = tmp_path_factory.mktemp("any")
    keep = d / "keep"
    keep.write_text("k")
    cwd = os.getcwd()
    os.chdir(d)
    try:
        try:
            p = write_text(name, "v")
        except OutputError as exc:
            assert "\n" not in str(exc)
            assert repr(name) in str(exc)
        else:
            assert p.read_text() == "v"
    finally:
        os.chdir(cwd)
    assert keep.read_text() == "k"
    assert _no_temporaries(d)


# --- through the command line: refused before any expensive work ----------------------------------

@pytest.fixture
def no_tuning(monkeypatch):
    import prsa_ctrl.studies.autotune as autotune

    calls = []
    monkeypatch.setattr(autotune, "tune_actuator", lambda *a, **k: calls.append(a) or pytest.fail("tuner reached"))
    monkeypatch.setattr(autotune, "actuator_loops", lambda *a, **k: calls.append(a) or pytest.fail("loops built"))
    return calls


def _one_error_line(capsys, prog="prsa-tune"):
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"{prog}: error: "), err
    assert "Traceback" not in err, err
    return lines[0]


def test_json_onto_the_plant_file_is_refused_and_the_plant_kept(tmp_path, capsys, no_tuning):
    plant = tmp_path / "myplant.toml"
    plant.write_bytes((PLANT_DIR / "paper-iprsm.toml").read_bytes())
    before = plant.read_bytes()
    assert main(["--plant", str(plant), "--json", str(plant)]) == 2
    assert "input file of this run" in _one_error_line(capsys)
    assert plant.read_bytes() == before
    assert not no_tuning


@pytest.mark.parametrize("flag, make", [
    ("--json", lambda d: ""),
    ("--json", lambda d: str(d)),
    ("--json", lambda d: str(d / "no" / "r.json")),
    ("--json", lambda d: "/dev/null"),
    ("--plots", lambda d: str(d / "file" / "figs")),
    ("--plots", lambda d: "/proc/nope"),
])
def test_bad_output_paths_exit_2_before_the_work(tmp_path, capsys, no_tuning, flag, make):
    (tmp_path / "file").write_text("x")
    assert main([flag, make(tmp_path)]) == 2
    _one_error_line(capsys)
    assert not no_tuning
    assert (tmp_path / "file").read_text() == "x"


def test_prsa_plot_leaves_no_directory_behind_on_failure(tmp_path, capsys, monkeypatch):
    import prsa_ctrl.studies.autotune as autotune
    from prsa_ctrl import SimulationError

    def boom(*a, **k):
        raise SimulationError("integration failed at t = 0.2 s from state [...]; remedy: ...")

    monkeypatch.setattr(autotune, "actuator_loops", boom)
    out = tmp_path / "new" / "figs"
    assert plot_main(["--kp", "0.085", "--ki", "14.7", "--plots", str(out)]) == 3
    assert capsys.readouterr().err.startswith("prsa-plot: numerical failure: integration failed")
    assert not (tmp_path / "new").exists()
    assert plot_main(["--kp", "0.085", "--plots", "/proc/nope"]) == 2
    _one_error_line(capsys, "prsa-plot")


def test_dash_is_refused_before_any_file_is_made_and_dot_slash_dash_is_a_file(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(OutputError, match=r"^--out '-': standard output"):
        write_text("-", "plant", flag="--out")
    assert list(tmp_path.iterdir()) == []
    write_text("./-", "plant", flag="--out")
    assert (tmp_path / "-").read_text() == "plant"
