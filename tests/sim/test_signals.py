"""prsa_ctrl.sim.signals: a measured trace read through the one CSV reader."""

import pytest

from prsa_ctrl.sim.signals import PiecewiseLinear


@pytest.mark.parametrize("text, match", [
    ("time_s,force\n0,1\n", r"bad\.csv line 1: header 'time_s,force'; expected columns 'time_s' and 'axial_load_n'"),
    ("time_s,axial_load_n\n0,1\n0.1,x\n", r"bad\.csv line 3: axial_load_n = 'x'; expected a finite number"),
    ("time_s,axial_load_n\n0,1\n0.2,2\n0.1,3\n", r"bad\.csv line 4: time_s = 0\.1 after 0\.2; expected increasing"),
    ("time_s,axial_load_n\n0,1\n0.1,nan\n", r"bad\.csv line 3: axial_load_n = 'nan'; expected a finite number"),
    ("time_s,axial_load_n\n0,1\n0.1, -inf \n", r"bad\.csv line 3: axial_load_n = '-inf'; expected a finite number"),
    ("time_s,axial_load_n\n0.5,1\n0.6,1\n", r"bad\.csv line 2: time_s = 0\.5; expected the trace to start at 0"),
    ("time_s,axial_load_n\n0,1\n0.1,2,3\n", r"bad\.csv line 3: 3 fields; expected 2 like the header"),
    ("time_s,axial_load_n\n0,1\n", r"bad\.csv: 1 data rows; expected at least 2"),
    ("# only a comment\n\n", r"bad\.csv: no header row"),
])
def test_a_bad_trace_is_refused_in_one_line_naming_file_line_and_value(tmp_path, text, match):
    bad = tmp_path / "bad.csv"
    bad.write_text(text, encoding="utf-8")
    with pytest.raises(ValueError, match=match):
        PiecewiseLinear.from_csv(bad)


def test_a_missing_trace_is_refused(tmp_path):
    with pytest.raises(ValueError, match=r"missing\.csv: file not found"):
        PiecewiseLinear.from_csv(tmp_path / "missing.csv")


def test_bom_comments_and_blank_rows_follow_the_one_rule(tmp_path):
    """An Excel "CSV UTF-8" export (byte-order mark) with comments before and inside the data
    reads to the same points as the plain file (was: a BOM broke the header, a comment a row)."""
    plain = tmp_path / "plain.csv"
    plain.write_text("time_s,axial_load_n\n0,500\n0.1,1500\n0.2,1000\n", encoding="utf-8")
    excel = tmp_path / "excel.csv"
    excel.write_bytes("\ufeff# measured 2026-11-27\ntime_s , axial_load_n\n0,500\n\n# step\n0.1,1500\n0.2,1000\n"
                      .encode("utf-8"))
    assert PiecewiseLinear.from_csv(excel).points == PiecewiseLinear.from_csv(plain).points \
        == ((0.0, 500.0), (0.1, 1500.0), (0.2, 1000.0))


def test_rows_and_size_are_bounded_before_the_rest_is_read(tmp_path):
    f = tmp_path / "long.csv"
    f.write_text("time_s,axial_load_n\n" + "".join(f"{i},1\n" for i in range(10)), encoding="utf-8")
    with pytest.raises(ValueError, match=r"long\.csv: more than 5 data rows \(line 7\); expected at most 5"):
        PiecewiseLinear.from_csv(f, max_rows=5)
    f.write_text("time_s,axial_load_n\n0,1\n0.1," + "1" * 5000 + "\n", encoding="utf-8")
    with pytest.raises(ValueError, match=r"long\.csv has \d+ bytes; expected at most 1536 bytes"):
        PiecewiseLinear.from_csv(f, max_rows=5)
