"""The one reader of CSV tables (measured records, drive logs, load and speed traces).

Every CSV file the toolkit reads goes through :func:`read_table`, with one rule for all:

- UTF-8, with or without a byte-order mark (Excel's "CSV UTF-8" export);
- blank rows and rows whose first cell starts with ``#`` (comments) are skipped, anywhere;
- the first other row is the header (cells stripped); every data row has as many fields;
- the size is bounded before reading (``max_bytes``) and the data rows while reading
  (``max_rows``: the file is refused at row ``max_rows + 1``, without reading the rest);
- every kept cell is a finite number (``nan`` and ``inf`` are refused where they are typed);
- every message is one line naming the file, the line and the value as typed.

The callers check what their format means (column names, units, increasing times, ranges).
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

from .textsafe import quote

__all__ = ["Table", "read_table", "ROW_BYTES_MAX"]

#: Largest mean length of a row, in bytes, that the default size bound allows (a record of 8
#: columns of 25 digits each is 208 bytes): ``max_bytes = ROW_BYTES_MAX * (max_rows + 1)``.
ROW_BYTES_MAX = 256


@dataclass(frozen=True)
class Table:
    """A CSV table as read by :func:`read_table`.

    Attributes
    ----------
    name : str
        The file as the messages name it.
    header : tuple of str
        Every column's name (stripped), in file order.
    header_line : int
        Line number (1-based) of the header.
    columns : mapping
        ``{name: float64 array}`` of the columns kept (the asked ones present in the header).
    lines : array of int
        Line number (1-based) of each data row.
    typed : mapping
        ``{name: tuple of str}``: the kept cells as typed (stripped), when asked for.
    """

    name: str
    header: tuple[str, ...]
    header_line: int
    columns: Mapping[str, Any]
    lines: Any
    typed: Mapping[str, tuple[str, ...]]

    @property
    def n(self) -> int:
        """Number of data rows."""
        return len(self.lines)


def read_table(path: "str | Path", *, max_rows: int, name: str | None = None, columns: Iterable[str] | None = None,
               max_bytes: int | None = None, error: Callable[[str], Exception] = ValueError,
               keep_text: bool = False, on_header: Callable[[tuple[str, ...], int], None] | None = None) -> Table:
    """Read a CSV table by the rule of the module docstring.

    Parameters
    ----------
    path : str or Path
    max_rows : int
        Most data rows accepted.
    name : str, optional
        How the messages name the file (default: the path as given).
    columns : iterable of str, optional
        The columns to keep (the others are not converted); those absent from the header are
        left out (the caller says what is missing). Default: every column.
    max_bytes : int, optional
        Largest file size, bytes (default ``ROW_BYTES_MAX * (max_rows + 1)``).
    error : exception class
        Raised with the one-line message (:class:`ValueError` or a subclass).
    keep_text : bool
        Keep the cells as typed (:attr:`Table.typed`), for later messages.
    on_header : callable, optional
        Called with the header and its line number before any data row is read (a format's
        check of its column names, so that it speaks first).

    Returns
    -------
    Table

    Raises
    ------
    ValueError (or ``error``)
        File missing or unreadable, too large, no header, too many rows, a row with another
        number of fields than the header, a column named twice, a cell that is not a finite
        number: one line naming the file, the line and the cell as typed.
    """
    import numpy as np
    from array import array

    p = Path(path)
    name = str(path) if name is None else name
    max_bytes = ROW_BYTES_MAX * (max_rows + 1) if max_bytes is None else max_bytes
    try:
        if not p.is_file():
            raise error(f"{name}: file not found (or not a regular file); expected a readable CSV file")
        size = p.stat().st_size
    except OSError as exc:
        raise error(f"{name}: cannot be read ({exc.strerror or exc.__class__.__name__}); expected a UTF-8 CSV file") from None
    if size > max_bytes:
        raise error(f"{name} has {size} bytes; expected at most {max_bytes} bytes ({max_rows} rows: cut or resample it)")
    wanted = None if columns is None else list(columns)
    header: list[str] | None = None
    header_line = 0
    keep: dict[str, int] = {}
    values: dict[str, array] = {}
    texts: dict[str, list[str]] = {}
    lines = array("q")
    try:
        with p.open(newline="", encoding="utf-8-sig") as fh:
            for line, row in enumerate(csv.reader(fh), start=1):
                if not row or not any(c.strip() for c in row) or row[0].lstrip().startswith("#"):
                    continue
                if header is None:
                    header, header_line = [h.strip() for h in row], line
                    if on_header is not None:
                        on_header(tuple(header), line)
                    for c, h in enumerate(header):
                        if wanted is not None and h not in wanted:
                            continue
                        if h in keep:
                            raise error(f"{name} line {line}: column {quote(h)} appears twice in the header (columns "
                                        f"{keep[h] + 1} and {c + 1}); expected each name once")
                        keep[h] = c
                        values[h], texts[h] = array("d"), []
                    continue
                if len(lines) >= max_rows:
                    raise error(f"{name}: more than {max_rows} data rows (line {line}); expected at most {max_rows} "
                                "(cut or resample it)")
                if len(row) != len(header):
                    raise error(f"{name} line {line}: {len(row)} fields; expected {len(header)} like the header")
                for h, c in keep.items():
                    cell = row[c].strip()
                    try:
                        v = float(cell)
                    except ValueError:
                        v = math.nan
                    if not math.isfinite(v):
                        raise error(f"{name} line {line}: {h} = {quote(cell)}; expected a finite number")
                    values[h].append(v)
                    if keep_text:
                        texts[h].append(cell)
                lines.append(line)
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise error(f"{name}: cannot be read ({exc.__class__.__name__}: {exc}); expected a UTF-8 CSV file") from None
    if header is None:
        raise error(f"{name}: no header row; expected a CSV header naming the columns")
    return Table(name, tuple(header), header_line,
                 {h: np.frombuffer(v, dtype=float).copy() for h, v in values.items()},
                 np.frombuffer(lines, dtype=np.int64).copy(),
                 {h: tuple(t) for h, t in texts.items()} if keep_text else {})
