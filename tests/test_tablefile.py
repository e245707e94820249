"""prsa_ctrl.tablefile: the one CSV reader (records, drive logs, load and speed traces)."""

import ast
from pathlib import Path

import numpy as np
import pytest

import prsa_ctrl
from prsa_ctrl.errors import DataError
from prsa_ctrl.tablefile import ROW_BYTES_MAX, read_table

PKG = Path(prsa_ctrl.__file__).parent


def _write(tmp_path, text, name="t.csv", encoding="utf-8"):
    p = tmp_path / name
    p.write_bytes(text.encode(encoding))
    return p


def test_header_columns_lines_and_text_as_typed(tmp_path):
    p = _write(tmp_path, "\ufeff# logged 2026\n\n a , b ,c\n1,2.5,x\n# pause\n 3 ,-4e-3,y\n")
    t = read_table(p, max_rows=10, columns=("a", "b", "zz"), keep_text=True)
    assert t.header == ("a", "b", "c")
    assert t.header_line == 3
    assert set(t.columns) == {"a", "b"}  # the asked columns present; 'c' (text) is not converted
    np.testing.assert_array_equal(t.columns["b"], [2.5, -4e-3])
    assert list(t.lines) == [4, 6]
    assert t.n == 2
    assert t.typed["a"] == ("1", "3")


@pytest.mark.parametrize("text, message", [
    ("a,b\n1,2\n3,nan\n", "t.csv line 3: b = 'nan'; expected a finite number"),
    ("a,b\n1,2\n3,1e999\n", "t.csv line 3: b = '1e999'; expected a finite number"),
    ("a,b\n1,2\n3,\n", "t.csv line 3: b = ''; expected a finite number"),
    ("a,b\n1,2\n3,\x1b[2Jzap\n", "t.csv line 3: b = '\\x1b[2Jzap'; expected a finite number"),
    ("a,b\n1,2\n3\n", "t.csv line 3: 1 fields; expected 2 like the header"),
    ("a,a\n1,2\n", "t.csv line 1: column 'a' appears twice in the header (columns 1 and 2); expected each name once"),
    ("# nothing\n\n", "t.csv: no header row; expected a CSV header naming the columns"),
])
def test_refusals_are_one_line_naming_file_line_and_value_as_typed(tmp_path, text, message):
    p = _write(tmp_path, text)
    with pytest.raises(DataError) as err:
        read_table(p, max_rows=10, name="t.csv", error=DataError)
    assert str(err.value) == message


def test_not_utf8_and_missing_files_are_refused(tmp_path):
    p = _write(tmp_path, "a,b\n1,2\n\u00e9,3\n", encoding="latin-1")
    with pytest.raises(ValueError, match=r"^t\.csv: cannot be read \(UnicodeDecodeError: .*\); expected a UTF-8 CSV file$"):
        read_table(p, max_rows=10, name="t.csv")
    with pytest.raises(ValueError, match=r"no\.csv: file not found"):
        read_table(tmp_path / "no.csv", max_rows=10)
    with pytest.raises(ValueError, match=r"not a regular file"):
        read_table(tmp_path, max_rows=10)


def test_size_is_bounded_before_the_file_is_opened(tmp_path, monkeypatch):
    p = _write(tmp_path, "a\n" + "1\n" * 100)
    opened = []
    real_open = Path.open
    monkeypatch.setattr(Path, "open", lambda self, *a, **k: opened.append(self) or real_open(self, *a, **k))
    with pytest.raises(ValueError, match=rf"t\.csv has {p.stat().st_size} bytes; expected at most 100 bytes"):
        read_table(p, max_rows=1000, max_bytes=100, name="t.csv")
    assert opened == []
    assert ROW_BYTES_MAX * 11 >= p.stat().st_size  # default bound: ROW_BYTES_MAX per row
    read_table(p, max_rows=100)


def test_rows_are_bounded_while_reading_without_reading_the_rest(tmp_path):
    p = _write(tmp_path, "a\n" + "1\n" * 5 + "not a number\n" * 10)
    with pytest.raises(ValueError, match=r"^t\.csv: more than 5 data rows \(line 7\); expected at most 5"):
        read_table(p, max_rows=5, max_bytes=10_000, name="t.csv", columns=())


def test_the_header_check_speaks_before_the_rows(tmp_path):
    p = _write(tmp_path, "a,b\nx,y\n")
    seen = []

    def check(header, line):
        seen.append((header, line))
        raise DataError("header refused")

    with pytest.raises(DataError, match="header refused"):
        read_table(p, max_rows=5, on_header=check)
    assert seen == [(("a", "b"), 1)]


def test_one_csv_reader_in_the_package():
    """Only prsa_ctrl/tablefile.py parses CSV (``csv.reader``/``DictReader``, ``loadtxt``,
    ``genfromtxt``); on main at 1dddb38 four modules did, each with its own rule."""
    users = []
    for path in sorted(PKG.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Attribute) and node.attr in ("reader", "DictReader", "loadtxt", "genfromtxt") \
                    and isinstance(node.value, ast.Name) and node.value.id in ("csv", "np", "numpy"):
                users.append(path.relative_to(PKG).as_posix())
    assert users == ["tablefile.py"]
