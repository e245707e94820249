"""The data files of described logs (:mod:`prsa_ctrl.identification.logformat`): the columns of
a CSV file or the variables of a MATLAB ``.mat`` file that a log description names, read within
a memory bound fixed before anything is read.

* Any file: at most :data:`prsa_ctrl.identification.data.MAX_FILE_BYTES`, checked before it is
  opened (the record path's limit).
* CSV: streamed; only the named columns are parsed and kept (one float array each); a name the
  description uses twice in the header is refused; more than
  :data:`prsa_ctrl.identification.data.MAX_SAMPLES` data rows are refused at the first row past
  them.
* ``.mat`` (v4, v5/v7; v7.3 HDF5 is refused): every variable's header is read first (class,
  complex flag, shape; a compressed variable is decompressed only as far as its header, at most
  :data:`MAT_HEADER_BYTES`), at most :data:`MAT_MAX_VARIABLES` variables; only the named ones
  are then decompressed (each bounded by its shape) and loaded, each refused before that when it
  holds more than ``MAX_SAMPLES`` values or is not real numbers (struct, cell array, text, sparse,
  complex: the message says which).

Every problem is a :class:`~prsa_ctrl.errors.LogFormatError` with one line naming the file and the
column or variable.
"""

from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import scipy.io

from ..errors import LogFormatError
from ..options import check_number
from ..tablefile import read_table
from .data import MAX_FILE_BYTES, MAX_SAMPLES

__all__ = ["LogFile", "MAT_HEADER_BYTES", "MAT_MAX_VARIABLES"]

#: MATLAB array classes (mxArray class numbers of the v5 format).
_MAT_CLASSES = {1: "cell", 2: "struct", 3: "object", 4: "char", 5: "sparse", 6: "double", 7: "single", 8: "int8",
                9: "uint8", 10: "int16", 11: "uint16", 12: "int32", 13: "uint32", 14: "int64", 15: "uint64",
                16: "function", 17: "opaque"}
_MAT_NUMERIC = {"double", "single", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64", "logical"}
#: Largest variable header (flags, dimensions, name) of a .mat file read, bytes.
MAT_HEADER_BYTES = 4096
_MI_MATRIX, _MI_COMPRESSED = 14, 15
#: Most variables a .mat log may hold (each header is read); names listed in a message.
MAT_MAX_VARIABLES, _NAMES_SHOWN = 100_000, 50


@dataclass(frozen=True)
class _MatVar:
    """One variable of a v5 .mat file, from its header: class, complex flag, shape and where its
    element is (``start``: its tag, ``end``: past its data; ``compressed``: a zlib element)."""

    name: str
    kind: str
    complex: bool
    shape: tuple[int, ...]
    start: int
    end: int
    compressed: bool
    header_bytes: int

    @property
    def size(self) -> int:
        return math.prod(self.shape)



class LogFile:
    """The columns (CSV) or variables (.mat) of one data file that its description names.

    Memory is bounded before anything is read: the file at most
    :data:`prsa_ctrl.identification.data.MAX_FILE_BYTES`; a CSV file is streamed, only the named
    columns kept, refused at its row ``MAX_SAMPLES + 1``; a .mat file's variable headers are read
    first (class, complex flag, shape: a compressed one decompressed only as far as its header)
    and only the named variables are decompressed and loaded, each refused before that when it
    is not real numbers or holds more than :data:`prsa_ctrl.identification.data.MAX_SAMPLES`
    values. ``names`` lists every column or variable of the file (for messages).
    """

    def __init__(self, path: str, fmt: str, wanted: Mapping[str, str] | None = None):
        self.path, self.fmt = path, fmt
        self.wanted = dict(wanted or {})
        p = Path(path)
        if not p.is_file():
            raise LogFormatError(f"{path}: log file not found; expected a readable {fmt} file")
        try:
            size = p.stat().st_size
        except OSError as exc:
            raise LogFormatError(f"{path}: cannot be read ({exc.strerror or exc}); expected a readable {fmt} file") from None
        if size > MAX_FILE_BYTES:
            raise LogFormatError(f"{path}: {size} bytes; expected at most {MAX_FILE_BYTES} bytes (cut the log)")
        self.all_names: list[str] = []  # (the first _NAMES_SHOWN of a .mat file's)
        self.names_total = 0
        self.kinds: dict[str, str] = {}  # variables that are not real numbers: what they are
        self.data: dict[str, np.ndarray] = self._read_mat(p, size) if fmt == "mat" else self._read_csv(p)

    # --- .mat ------------------------------------------------------------------------------------

    def _bad_mat(self, text: str) -> LogFormatError:
        return LogFormatError(f"{self.path}: cannot be read as a MATLAB .mat file ({text}); expected a MATLAB v4 or "
                              "v5/v7 .mat file")

    def _read_mat(self, p: Path, size: int) -> dict[str, np.ndarray]:
        from scipy.io.matlab import MatReadError, matfile_version

        if size == 0:
            raise self._bad_mat("an empty file")
        try:
            with p.open("rb") as fh:
                major, _ = matfile_version(fh)
        except (MatReadError, OSError, ValueError, TypeError, IndexError, struct.error) as exc:
            raise self._bad_mat(str(exc) or type(exc).__name__) from None
        if major == 2:
            raise LogFormatError(f"{self.path}: MATLAB v7.3 (HDF5) file; expected a v5/v7 .mat file (save with "
                                 "-v7)")
        try:
            raw = self._read_mat4(p, size) if major == 0 else self._read_mat5(p, size)
        except LogFormatError:
            raise
        except (MatReadError, OSError, ValueError, TypeError, KeyError, IndexError, struct.error, zlib.error,
                NotImplementedError, AttributeError) as exc:
            raise self._bad_mat(str(exc) or type(exc).__name__) from None
        out = {}
        for k, v in raw.items():
            if k.startswith("__") or k not in self.wanted:
                continue
            if not isinstance(v, np.ndarray) or v.dtype.kind not in "fiub":
                what = "complex numbers" if isinstance(v, np.ndarray) and v.dtype.kind == "c" else \
                    f"a MATLAB {type(v).__name__ if not isinstance(v, np.ndarray) else v.dtype.name} array"
                raise self._not_numbers(k, what)
            out[k] = np.asarray(v, dtype=float)
        return out

    def _not_numbers(self, var: str, what: str) -> LogFormatError:
        return LogFormatError(f"{self.path}: variable {var!r} ({self.wanted.get(var, 'named')}) holds {what}; expected "
                              "a real numeric vector or scalar (double, single, integer or logical)")

    def _check_var(self, name: str, kind: str, complex_: bool, shape: tuple[int, ...]) -> None:
        """A named variable checked from its header, before its data are read."""
        if kind not in _MAT_NUMERIC:
            what = {"char": "text (a MATLAB char array)", "cell": "a MATLAB cell array", "sparse": "a MATLAB sparse matrix",
                    "struct": "a MATLAB struct"}.get(kind, f"a MATLAB {kind}")
            raise self._not_numbers(name, what)
        if complex_:
            raise self._not_numbers(name, f"complex numbers (class {kind})")
        n = math.prod(shape)
        if n > MAX_SAMPLES:
            raise LogFormatError(f"{self.path}: variable {name!r} ({self.wanted[name]}) has shape "
                                 f"{'x'.join(map(str, shape))} ({n} values); expected at most {MAX_SAMPLES} values (one "
                                 "per sample; cut the log)")

    def _read_mat4(self, p: Path, size: int) -> dict:
        """A v4 file (never compressed): every variable's 20-byte header read, the named ones
        checked, then only those loaded (from memory)."""
        import io

        chunks, seen, count, pos = [], set(), 0, 0
        with p.open("rb") as fh:
            while pos + 20 <= size:
                count += 1
                if count > MAT_MAX_VARIABLES:
                    raise self._bad_mat(f"more than {MAT_MAX_VARIABLES} variables")
                fh.seek(pos)
                raw = fh.read(20)
                for endian in "<>":
                    mopt, rows, cols, imagf, namlen = struct.unpack(endian + "5i", raw)
                    if 0 <= mopt < 5000 and mopt // 100 % 10 == 0:
                        break
                else:
                    raise self._bad_mat(f"no MATLAB v4 variable header at byte {pos}")
                itemsize = {0: 8, 1: 4, 2: 4, 3: 2, 4: 2, 5: 1}.get(mopt // 10 % 10)
                if itemsize is None or min(rows, cols, namlen) < 0 or namlen > 4096:
                    raise self._bad_mat(f"a bad MATLAB v4 variable header at byte {pos}")
                name = fh.read(namlen).rstrip(b"\0").decode("latin1")
                end = pos + 20 + namlen + rows * cols * itemsize * (2 if imagf else 1)
                if end > size:
                    raise self._bad_mat(f"the variable at byte {pos} runs past the end of the file")
                if len(self.all_names) < _NAMES_SHOWN:
                    self.all_names.append(name)
                if name in self.wanted:
                    if name in seen:
                        raise LogFormatError(f"{self.path}: variable {name!r} ({self.wanted[name]}) appears twice in "
                                             "the file; expected each name once")
                    seen.add(name)
                    kind = {0: "double", 1: "char", 2: "sparse"}.get(mopt % 10, f"type {mopt % 10}")
                    self._check_var(name, kind, bool(imagf), (rows, cols))
                    fh.seek(pos)
                    chunks.append(fh.read(end - pos))
                pos = end
        self.names_total = count
        return scipy.io.loadmat(io.BytesIO(b"".join(chunks))) if chunks else {}

    def _read_mat5(self, p: Path, size: int) -> dict:
        """A v5/v7 file: every variable's header read (a compressed one decompressed only to
        :data:`MAT_HEADER_BYTES`), the named ones checked, then only those decompressed (each
        bounded by its shape) and loaded from memory."""
        import io

        with p.open("rb") as fh:
            head = fh.read(128)
            endian = {b"IM": "<", b"MI": ">"}.get(head[126:128])
            if endian is None:
                raise self._bad_mat("no endian indicator in its header")
            variables, count = [], 0
            pos = 128
            while pos + 8 <= size:
                count += 1
                if count > MAT_MAX_VARIABLES:
                    raise self._bad_mat(f"more than {MAT_MAX_VARIABLES} variables")
                fh.seek(pos)
                mdtype, nbytes = struct.unpack(endian + "II", fh.read(8))
                end = pos + 8 + nbytes
                if mdtype not in (_MI_MATRIX, _MI_COMPRESSED):
                    raise self._bad_mat(f"data element of type {mdtype} at byte {pos}, expected a matrix")
                if end > size:
                    raise self._bad_mat(f"the element at byte {pos} runs past the end of the file")
                v = self._mat5_header(fh, endian, pos, end, mdtype == _MI_COMPRESSED)
                if len(self.all_names) < _NAMES_SHOWN:
                    self.all_names.append(v.name)
                if v.name in self.wanted:  # only these are kept
                    variables.append(v)
                pos = end
            self.names_total = count
            chunks, seen = [head], set()
            for v in variables:
                if v.name not in self.wanted:
                    continue
                if v.name in seen:
                    raise LogFormatError(f"{self.path}: variable {v.name!r} ({self.wanted[v.name]}) appears twice in the "
                                         "file; expected each name once")
                seen.add(v.name)
                self._check_var(v.name, v.kind, v.complex, v.shape)
                chunks.append(self._mat5_element(fh, endian, v))
        if len(chunks) == 1:
            return {}
        return scipy.io.loadmat(io.BytesIO(b"".join(chunks)))

    @staticmethod
    def _inflate(fh, start: int, end: int, limit: int) -> bytes:
        """The decompressed bytes of the zlib stream in ``[start, end)`` of the file, at most
        ``limit + 1`` of them (so that more than ``limit`` is seen)."""
        d = zlib.decompressobj()
        out = []
        got = 0
        fh.seek(start)
        left = end - start
        pending = b""
        while got <= limit:
            if not pending:
                if left <= 0:
                    break
                pending = fh.read(min(65536, left))
                left -= len(pending)
                if not pending:
                    break
            chunk = d.decompress(pending, limit + 1 - got)
            pending = d.unconsumed_tail
            out.append(chunk)
            got += len(chunk)
            if d.eof:
                break
        return b"".join(out)

    def _mat5_header(self, fh, endian: str, pos: int, end: int, compressed: bool) -> _MatVar:
        if compressed:
            raw = self._inflate(fh, pos + 8, end, MAT_HEADER_BYTES)
            mdtype, _ = struct.unpack(endian + "II", raw[:8])
            if mdtype != _MI_MATRIX:
                raise self._bad_mat(f"compressed element at byte {pos} holds type {mdtype}, expected a matrix")
            body = raw[8:]
        else:
            fh.seek(pos + 8)
            body = fh.read(min(end - pos - 8, MAT_HEADER_BYTES))
        if not body:  # an empty matrix element (MATLAB writes these for empty arrays)
            return _MatVar("", "double", False, (0, 0), pos, end, compressed, 0)
        off = 0
        fields = []
        for _ in range(3):  # array flags, dimensions, name
            if off + 8 > len(body):
                raise self._bad_mat(f"the variable header at byte {pos} is longer than {MAT_HEADER_BYTES} bytes or cut")
            first = struct.unpack(endian + "I", body[off:off + 4])[0]
            if first >> 16:  # a small data element: type and length in one word, data in the next
                n = first >> 16
                fields.append(body[off + 4:off + 4 + n])
                off += 8
            else:
                n = struct.unpack(endian + "I", body[off + 4:off + 8])[0]
                if off + 8 + n > len(body):
                    raise self._bad_mat(f"the variable header at byte {pos} is longer than {MAT_HEADER_BYTES} bytes "
                                        "or cut")
                fields.append(body[off + 8:off + 8 + n])
                off += 8 + (n + 7) // 8 * 8
        flags = struct.unpack(endian + "I", fields[0][:4])[0]
        kind = "logical" if flags >> 9 & 1 else _MAT_CLASSES.get(flags & 0xFF, f"class {flags & 0xFF}")
        dims = tuple(struct.unpack(endian + f"{len(fields[1]) // 4}i", fields[1][:len(fields[1]) // 4 * 4]))
        if any(d < 0 for d in dims):
            raise self._bad_mat(f"negative dimensions {dims} at byte {pos}")
        return _MatVar(fields[2].decode("latin1"), kind, bool(flags >> 11 & 1), dims, pos, end, compressed, off)

    def _mat5_element(self, fh, endian: str, v: _MatVar) -> bytes:
        """A named variable's element, uncompressed, its size bounded by its shape (8 bytes a value
        at most, plus its header and padding)."""
        bound = v.header_bytes + 16 + 8 * v.size + 8
        if v.compressed:
            raw = self._inflate(fh, v.start + 8, v.end, bound + 8)
            if len(raw) > bound + 8:
                raise self._bad_mat(f"variable {v.name!r} decompresses to more than its shape "
                                    f"{'x'.join(map(str, v.shape))} holds")
            return raw
        if v.end - v.start > bound + 8:
            raise self._bad_mat(f"variable {v.name!r} takes {v.end - v.start} bytes, more than its shape "
                                f"{'x'.join(map(str, v.shape))} holds")
        fh.seek(v.start)
        return fh.read(v.end - v.start)

    # --- CSV -------------------------------------------------------------------------------------

    def _read_csv(self, p: Path) -> dict[str, np.ndarray]:
        """The named columns, read by the one CSV reader (:func:`prsa_ctrl.tablefile.read_table`:
        streamed, a file with more than ``MAX_SAMPLES`` data rows is refused at its row
        ``MAX_SAMPLES + 1``; a column the description names twice in the header is refused)."""
        def check_header(header: tuple[str, ...], line: int) -> None:
            seen: dict[str, int] = {}
            for c, h in enumerate(header):
                if h in self.wanted and h in seen:
                    raise LogFormatError(f"{self.path}: column {h!r} ({self.wanted[h]}) appears twice in the header "
                                         f"(columns {seen[h] + 1} and {c + 1}, line {line}); expected each name once")
                seen.setdefault(h, c)

        table = read_table(p, max_rows=MAX_SAMPLES, max_bytes=MAX_FILE_BYTES, name=self.path, error=LogFormatError,
                           columns=self.wanted, on_header=check_header)
        self.all_names = list(table.header)
        return dict(table.columns)

    def names(self) -> str:
        """The file's columns or variables for a message (the first :data:`_NAMES_SHOWN`)."""
        total = max(self.names_total, len(self.all_names))
        shown = ", ".join(self.all_names[:_NAMES_SHOWN]) or "nothing"
        return shown + (f", ... ({total} in all)" if total > _NAMES_SHOWN else "")

    def signal(self, key: str, var: str, n: int | None) -> np.ndarray:
        what = "column" if self.fmt == "csv" else "variable"
        if var not in self.data:
            raise LogFormatError(f"{self.path}: {key} names {what} {var!r}, not in the file; it has {self.names()}")
        v = self.data[var]
        if v.ndim == 2 and 1 in v.shape:
            v = v.ravel()
        if v.ndim != 1 or v.size < 2:
            raise LogFormatError(f"{self.path}: {what} {var!r} ({key}) has shape {self.data[var].shape}; expected a "
                                 "vector (one value per sample)")
        if n is not None and v.size != n:
            raise LogFormatError(f"{self.path}: {what} {var!r} ({key}) has {v.size} samples; expected {n} like the time")
        bad = np.flatnonzero(~np.isfinite(v))
        if bad.size:
            raise LogFormatError(f"{self.path}: {what} {var!r} ({key}) sample {bad[0]}: {v[bad[0]]}; expected finite values")
        return v.astype(float)

    def scalar(self, key: str, value: Any, fmt_path: str) -> tuple[float, str]:
        """A number given in the description (> 0), or the name of a scalar variable of a .mat file
        (:func:`prsa_ctrl.options.check_number` checks either)."""
        if isinstance(value, str) and self.fmt == "mat":
            if value not in self.data:
                raise LogFormatError(f"{self.path}: {key} names variable {value!r}, not in the file; it has {self.names()}")
            v = self.data[value]
            if v.size != 1:
                raise LogFormatError(f"{self.path}: variable {value!r} ({key}) has shape {v.shape}; expected a scalar")
            x = float(v.ravel()[0])
            return (check_number(f"{self.path}: {key}", x, 0.0, lo_open=True, error=LogFormatError,
                                 typed=f"{x!r} (variable {value!r})"), f"{Path(self.path).name}: {value}")
        expected = ("a finite number > 0 or a variable name" if self.fmt == "mat" else
                    "a finite number > 0" + (" (variable names work for .mat files only)" if isinstance(value, str) else ""))
        return (check_number(f"{fmt_path}: {key}", value, 0.0, lo_open=True, error=LogFormatError, expected=expected),
                Path(fmt_path).name)
