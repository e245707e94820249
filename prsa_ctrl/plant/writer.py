"""The one writer of plant files (TOML): a fitted plant, a linear axis, any plant document.

:func:`plant_toml` is :meth:`prsa_ctrl.plant.plantfile.Plant.to_toml`: the plant's values,
sources and ``[uncertainty]`` written as a plant file. Given the base file's text, the base's
layout and comments are kept (the document is edited with :mod:`tomlkit`, which round-trips
TOML: only the entries that change are rewritten, in their own spelling -- inline tables,
dotted keys, sub-tables); without a base, or when the edited document would not read back as
exactly the plant's (checked with :mod:`tomllib`), the whole file is written afresh, a header
line saying so. :func:`document_toml` does the same for any plant document (a ``dict`` as
:mod:`tomllib` reads one), e.g. a linear axis of :mod:`prsa_ctrl.identification.axis`.

Text from a user's file is data: every string is written as a TOML basic string with quotes,
backslashes, control characters, the bidirectional marks and overrides and the line separators
escaped (``\\uXXXX``); a lone surrogate (an undecodable file name) cannot be written to TOML and
is refused (``ValueError`` naming the key), except in the sources and description of a fitted
plant (:func:`fitted_document`), where it names a log file and is written as its byte
(``\\xNN``, :func:`prsa_ctrl.textsafe.unicode_text`). Header comment lines go through
:func:`prsa_ctrl.textsafe.printable` (one line each). Numbers keep all their digits
(``repr``), so that the file reads back exactly.

The text is checked before it is returned: it parses and holds exactly the document asked for.
Writing it to disk is the caller's (atomically, never over an input:
:func:`prsa_ctrl.io.output.write_plant_toml`).
"""

from __future__ import annotations

import copy
import math
import re
import tomllib
from typing import Any, Mapping, Sequence

from ..errors import PlantFileError
from ..textsafe import printable, unicode_text

__all__ = ["plant_toml", "document_toml", "fitted_document", "toml_string", "inline_value", "data_value", "data_lines", "FRESH_NOTE", "NO_TOMLKIT_NOTE", "UNCERTAINTY_COMMENT"]

#: The header line of a file written afresh although a base file was given.
FRESH_NOTE = ("Written by prsa-fit: the base plant file's TOML spelling could not be kept line by line, so its "
              "comments are not repeated here.")
#: The header line of a file written afresh because :mod:`tomlkit` is not installed.
NO_TOMLKIT_NOTE = ("Written by prsa-fit: tomlkit (a dependency of prsa-ctrl: pip install tomlkit) is not installed, so "
                   "the base plant file's layout and comments are not repeated here.")
#: The comment above an ``[uncertainty]`` section the writer adds.
UNCERTAINTY_COMMENT = "What the fit leaves uncertain (95 % intervals as truncated normals; prsa_ctrl.plant.uncertainty)"

_TOP = ("name", "description")
_SHORT = {"\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f", "\r": "\\r", '"': '\\"', "\\": "\\\\"}
# C0/C1 controls, DEL, the bidirectional marks and overrides, the line/paragraph separators.
_ESCAPED = re.compile("[\x00-\x1f\x7f-\x9f\u061c\u200e\u200f\u2028-\u202e\u2066-\u2069]")
_BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")


def toml_string(s: str, where: str = "value", *, ascii_only: bool = False) -> str:
    r"""``s`` as a TOML basic string that :mod:`tomllib` reads back as exactly ``s``: quotes,
    backslashes, control characters (C0, DEL, C1), the bidirectional marks and overrides and the
    line separators escaped (``\uXXXX``); with ``ascii_only`` every non-ASCII character too
    (``\uXXXX``, or ``\UXXXXXXXX`` outside the Basic Multilingual Plane: no surrogate pairs,
    which TOML refuses). The package's one TOML string writer (also behind
    :func:`prsa_ctrl.io.export.toml_string`).

    Raises
    ------
    ValueError
        A lone surrogate (not representable in TOML), naming ``where``.

    Examples
    --------
    >>> print(toml_string('a"b\\c\x1b\u202e µ'))
    "a\"b\\c\u001B\u202E µ"
    >>> print(toml_string("µ\U0001F600", ascii_only=True))
    "\u00B5\U0001F600"
    """
    out = ['"']
    for ch in str(s):
        o = ord(ch)
        if ch in _SHORT:
            out.append(_SHORT[ch])
        elif 0xD800 <= o <= 0xDFFF:
            raise ValueError(f"{where} = {s!r}; expected text of Unicode characters (a lone surrogate U+{o:04X} "
                             "cannot be written to TOML)")
        elif _ESCAPED.match(ch) or (o > 0x7E and ascii_only):
            out.append("\\u%04X" % o if o <= 0xFFFF else "\\U%08X" % o)
        else:
            out.append(ch)
    return "".join(out) + '"'


def _float_text(f: float) -> str:
    """A finite float with all its digits (``repr``), always read back as a float (``1.0``, not ``1``)."""
    r = repr(f)
    return r if any(c in r for c in ".en") else r + ".0"


def _key(k: str) -> str:
    return k if _BARE_KEY.match(k) else toml_string(k, "key")


def _value(v: Any, where: str) -> str:
    """One TOML value (inline: tables as ``{ a = 1, ... }``, arrays on one line)."""
    if isinstance(v, bool) or type(v).__name__ == "bool_":
        return "true" if v else "false"
    if isinstance(v, int) or (type(v).__module__ == "numpy" and hasattr(v, "dtype") and v.dtype.kind in "iu"):
        return str(int(v))
    if isinstance(v, float) or (type(v).__module__ == "numpy" and hasattr(v, "dtype") and v.dtype.kind == "f"):
        f = float(v)
        if math.isnan(f):
            return "nan"
        if math.isinf(f):
            return "inf" if f > 0 else "-inf"
        return _float_text(f)
    if isinstance(v, str):
        return toml_string(v, where)
    if isinstance(v, Mapping):
        if not v:
            return "{}"
        return "{ " + ", ".join(f"{_key(k)} = {_value(x, f'{where}.{k}')}" for k, x in v.items()) + " }"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x, f"{where}[{i}]") for i, x in enumerate(v)) + "]"
    raise ValueError(f"{where} = {v!r}; expected a number, string, bool, table or array (TOML has no null)")


def inline_value(v: Any, where: str = "value") -> str:
    """``v`` as one inline TOML value (tables ``{ a = 1, ... }``, arrays on one line), with this
    module's escaping and all the digits of every number.

    >>> inline_value({"keys": ["a", "b"], "matrix": [[1.0, 0.5], [0.5, 1.0]], "source": "fit"})
    '{ keys = ["a", "b"], matrix = [[1.0, 0.5], [0.5, 1.0]], source = "fit" }'
    """
    return _value(_plain(v), where)


def data_value(v: Any, where: str = "value", *, ascii_only: bool = True) -> str:
    """A TOML value of a data file (a drive export): bool, integer, finite float (all digits,
    ``repr``), string (:func:`toml_string`: ASCII with ``\\uXXXX``/``\\UXXXXXXXX`` escapes unless
    ``ascii_only`` is false), or a list of those (:func:`prsa_ctrl.io.export.toml_value`).

    Raises
    ------
    ValueError
        A non-finite number, None or another type, naming ``where``.

    >>> data_value([1, 2.5, "x"]), data_value(True), data_value("µ", ascii_only=False)
    ('[1, 2.5, "x"]', 'true', '"µ"')
    """
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int) or (type(v).__module__ == "numpy" and hasattr(v, "dtype") and v.dtype.kind in "iu"):
        return str(int(v))
    if isinstance(v, float) or (type(v).__module__ == "numpy" and hasattr(v, "dtype") and v.dtype.kind == "f"):
        f = float(v)
        if not math.isfinite(f):
            raise ValueError(f"{where} = {f!r}; expected a finite number (TOML export)")
        return _float_text(f)
    if isinstance(v, str):
        return toml_string(v, where, ascii_only=ascii_only)
    if isinstance(v, (list, tuple)) and not any(isinstance(x, dict) for x in v):
        return "[" + ", ".join(data_value(x, where, ascii_only=ascii_only) for x in v) + "]"
    raise ValueError(f"{where} = {v!r}; expected a number, string, bool or list of those (TOML has no null)")


def _data_key(k: str) -> str:
    if not isinstance(k, str):
        raise ValueError(f"key {k!r}; expected a string")
    return k if _BARE_KEY.match(k) else toml_string(k, ascii_only=True)  # a data file's keys in ASCII


def data_lines(d: Mapping[str, Any], path: Sequence[str] = ()) -> list[str]:
    """A data file's tables as TOML lines: a table's values first (:func:`data_value`), then its
    sub-tables (``[a.b]``) and arrays of tables (``[[a.c]]``), each after a blank line; so that
    :mod:`tomllib` reads back exactly ``d`` (:func:`prsa_ctrl.io.export.dumps`)."""
    lines: list[str] = []
    tables = []
    for k, v in d.items():
        if isinstance(v, dict) or (isinstance(v, list) and v and all(isinstance(x, dict) for x in v)):
            tables.append((k, v))
        else:
            lines.append(f"{_data_key(k)} = {data_value(v, '.'.join([*path, k]))}")
    for k, v in tables:
        sub = [*path, _data_key(k)]
        if isinstance(v, dict):
            lines.extend(["", f"[{'.'.join(sub)}]"])
            lines.extend(data_lines(v, sub))
        else:
            for item in v:
                lines.extend(["", f"[[{'.'.join(sub)}]]"])
                lines.extend(data_lines(item, sub))
    return lines


def _equal(a: Any, b: Any) -> bool:
    """Documents compared as values (NaN equal to NaN; an int never equal to a float of the same value)."""
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        return a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    if isinstance(a, bool) or isinstance(b, bool):
        return type(a) is type(b) and a == b
    if isinstance(a, int) != isinstance(b, int):
        return False
    return a == b


def _plain(doc: Any) -> Any:
    """A document with numpy scalars as Python numbers and tuples as lists (what tomllib reads)."""
    if isinstance(doc, Mapping):
        return {str(k): _plain(v) for k, v in doc.items()}
    if isinstance(doc, (list, tuple)):
        return [_plain(v) for v in doc]
    if type(doc).__module__ == "numpy" and hasattr(doc, "item"):
        return doc.item()
    return doc


def document_toml(doc: Mapping[str, Any], base_text: str | None = None, header: Sequence[str] = (),
                  comments: Mapping[str, str] | None = None) -> str:
    """A plant document written as TOML text that :mod:`tomllib` reads back as exactly ``doc``.

    Parameters
    ----------
    doc : mapping
        The document (``name``, ``description``, top-level keys, ``[section]`` tables of
        ``key = { value = ..., source = "..." }`` entries, ``[uncertainty]``).
    base_text : str, optional
        A plant file whose layout and comments are kept: its document is edited into ``doc``
        (the entries equal in both are left as they are spelled). Without it, or when the edit
        does not read back as ``doc``, the file is written afresh (with a base given, the
        header line :data:`FRESH_NOTE` says so). A base whose every line ends in CR LF gives a
        text with CR LF line endings too (read the base with its newlines kept, e.g. from
        ``bytes.decode``).
    header : sequence of str
        Comment lines put first (each made one printable line).
    comments : mapping, optional
        ``{top-level key or section: comment}``: a trailing comment on that line of a file
        written afresh (``coordinates = "load"  # position m, force N``).

    Returns
    -------
    str

    Raises
    ------
    ValueError
        A value TOML cannot hold (None, a lone surrogate in a text), naming its key.
    """
    if base_text is not None and _crlf(base_text):  # a Windows-edited base keeps its line endings
        base_text = base_text.replace("\r\n", "\n")
        return document_toml(doc, base_text, header, comments).replace("\n", "\r\n")
    want = _plain(doc)
    head = "".join(f"# {printable(line)}\n" for line in header)
    if base_text is not None:
        try:
            import tomlkit  # noqa: F401 - a declared dependency; without it the file is written afresh, saying why
        except ImportError:
            head += f"# {NO_TOMLKIT_NOTE}\n"
        else:
            try:
                text = _edited(base_text.removeprefix("\ufeff"), want)
                if _equal(tomllib.loads(text), want):
                    return head + text
            except Exception:  # noqa: BLE001 - tomlkit refusing an edit (out-of-order tables raise IndexError)
                pass
            head += f"# {FRESH_NOTE}\n"
    text = head + _fresh(want, comments or {})
    if not _equal(tomllib.loads(text), want):  # a writer bug, never a user's input
        raise PlantFileError("plant file writer: the text written does not read back as the plant")
    return text


def _crlf(text: str) -> bool:
    """True for a text whose every line ends in CR LF (a file saved on Windows)."""
    n = text.count("\n")
    return n > 0 and text.count("\r\n") == n


def _edited(base_text: str, want: Mapping[str, Any]) -> str:
    """The base file's tomlkit document edited into ``want`` (comments and layout kept)."""
    import tomlkit

    doc = tomlkit.parse(base_text)
    _sync(doc, want, "", top=True)
    return tomlkit.dumps(doc)


def _item(v: Any, where: str):
    """A tomlkit item of ``v`` with this module's escaping (parsed from its one-line text)."""
    import tomlkit

    return tomlkit.parse(f"v = {_value(v, where)}\n")["v"]


def _sync(container, want: Mapping[str, Any], where: str, top: bool = False) -> None:
    """Edit a tomlkit table in place until it holds ``want``."""
    import tomlkit
    from tomlkit.items import InlineTable, Table

    for k in [k for k in container.keys() if k not in want]:
        del container[k]
    for k, v in want.items():
        path = f"{where}.{k}" if where else k
        if k in container:
            cur = container[k]
            old = cur.unwrap() if hasattr(cur, "unwrap") else cur
            if _equal(_plain(old), v):
                continue
            if isinstance(v, Mapping) and isinstance(cur, (Table, InlineTable)) or (
                    isinstance(v, Mapping) and type(cur).__name__ == "OutOfOrderTableProxy"):
                _sync(cur, v, path)
                continue
            container[k] = _item(v, path)
        elif top and isinstance(v, Mapping) and (_is_section(v) or k == "uncertainty"):
            table = tomlkit.table()
            for kk, e in v.items():
                table[kk] = _item(e, f"{k}.{kk}")
            if k == "uncertainty":  # above its header (the comment ends the section before it)
                container.add(tomlkit.nl())
                container.add(tomlkit.comment(UNCERTAINTY_COMMENT))
            container[k] = table
        else:
            container[k] = _item(v, path)


def _is_section(v: Any) -> bool:
    """A top-level table written as ``[section]``: one holding tables (``key = { value = ... }``)."""
    return isinstance(v, Mapping) and any(isinstance(e, Mapping) for e in v.values())


def _fresh(doc: Mapping[str, Any], comments: Mapping[str, str]) -> str:
    """The whole document written from scratch: name, description, top-level entries,
    ``[section]`` tables of one-line entries, ``[uncertainty]`` last."""
    def line(k: str, v: Any, where: str) -> str:
        note = comments.get(where)
        return f"{_key(k)} = {_value(v, where)}" + (f"  # {printable(note)}" if note else "")

    out = [line(k, doc[k], k) for k in _TOP if k in doc]
    sections = {k: v for k, v in doc.items() if k not in (*_TOP, "uncertainty") and _is_section(v)}
    out += [line(k, v, k) for k, v in doc.items() if k not in (*_TOP, "uncertainty") and k not in sections]
    for sec, table in sections.items():
        out += ["", f"[{_key(sec)}]"] + [line(k, e, f"{sec}.{k}") for k, e in table.items()]
    if "uncertainty" in doc:
        unc = doc["uncertainty"]
        out += ["", f"# {UNCERTAINTY_COMMENT}", "[uncertainty]"] if unc else ["", "[uncertainty]"]
        out += [line(k, e, f"uncertainty.{k}") for k, e in unc.items()]
    return "\n".join(out) + "\n"


def fitted_document(base_doc: Mapping[str, Any], plant, name: str | None = None, keys: Sequence[str] = (),
                    description: str | None = None, uncertainty_keys: Sequence[str] | None = None) -> dict:
    """The document of a plant file: ``base_doc`` with the name, the description, the ``keys``'
    values and sources and the ``uncertainty_keys``' ``[uncertainty]`` entries of ``plant``.

    Parameters
    ----------
    base_doc : mapping
        The base file's document (:func:`tomllib.loads`).
    plant : Plant
        Values (SI, file units), sources and ``uncertainty`` of the keys written.
    name, description : str, optional
        The new name and top-level description (default: the base's).
    keys : sequence of str
        Plant keys (``section.key``) written from ``plant`` (a section the base left out is added).
        Their sources, ``[uncertainty]`` sources and the description name the logs a fit read: a
        log file name that is not UTF-8 (a lone surrogate) is written with the byte as ``\\xNN``
        (:func:`prsa_ctrl.textsafe.unicode_text`); a ``name`` holding one is refused.
    uncertainty_keys : sequence of str, optional
        Keys whose ``[uncertainty]`` entry is ``plant.uncertainty``'s (removed when it has
        none). Default: the ``keys`` with an entry in ``plant.uncertainty``.
    """
    unc = dict(getattr(plant, "uncertainty", None) or {})
    unc_keys = [k for k in keys if k in unc] if uncertainty_keys is None else list(uncertainty_keys)
    doc = copy.deepcopy(_plain(base_doc))
    if name is not None:
        doc["name"] = name
    if description is not None:
        doc["description"] = unicode_text(description)  # (an undecodable log file name: its byte as \xNN)
    for k in keys:
        section, sub = k.split(".")
        if not isinstance(doc.get(section, {}), dict):
            raise PlantFileError(f"base plant file: {section} = {doc[section]!r} is not a table; expected [{section}]")
        doc.setdefault(section, {})[sub] = {"value": _plain(plant.values[k]), "source": unicode_text(plant.sources[k])}
    old = doc.get("uncertainty", {})
    new = {k: v for k, v in old.items() if k not in unc_keys}
    new.update({k: _sourced(_plain(unc[k])) for k in unc_keys if k in unc})
    if new or "uncertainty" in doc:
        doc["uncertainty"] = new
    return doc


def _sourced(entry: Any) -> Any:
    """An ``[uncertainty]`` entry with its ``source`` text encodable (:func:`unicode_text`)."""
    if isinstance(entry, dict) and isinstance(entry.get("source"), str):
        return {**entry, "source": unicode_text(entry["source"])}
    return entry


def plant_toml(plant, base_text: str | None = None, *, name: str | None = None, keys: Sequence[str] | None = None,
               description: str | None = None, uncertainty_keys: Sequence[str] | None = None,
               header: Sequence[str] = ()) -> str:
    """The plant file of ``plant`` (:meth:`prsa_ctrl.plant.plantfile.Plant.to_toml`).

    Parameters
    ----------
    plant : Plant
        The plant (values in file units, sources, ``uncertainty``).
    base_text : str, optional
        The base plant file: its layout and comments are kept, the ``keys`` rewritten (see
        :func:`document_toml`). Without it, every given (not defaulted) key of the plant is
        written afresh.
    name, description : str, optional
        The new name and description (default: the base's, else the plant's).
    keys : sequence of str, optional
        The keys written from ``plant`` (default: with a base none, else every given key).
    uncertainty_keys : sequence of str, optional
        See :func:`fitted_document`.
    header : sequence of str
        Comment lines put first (``prsa-fit --force``'s warning).

    Returns
    -------
    str
        Text that :func:`prsa_ctrl.plant.plantfile.load_plant` reads as the plant written.
    """
    if base_text is not None:
        base_doc = tomllib.loads(base_text.removeprefix("\ufeff"))
        doc = fitted_document(base_doc, plant, name, list(keys or ()), description, uncertainty_keys)
        return document_toml(doc, base_text, header)
    defaulted = set(getattr(plant, "defaulted", ()) or ())
    chosen = list(keys) if keys is not None else [k for k in plant.values if k not in defaulted]
    base_doc: dict[str, Any] = {"name": plant.name}
    if plant.description:
        base_doc["description"] = plant.description
    src = str(getattr(plant, "mechanism_source", "") or "")
    if src and src not in ("plant file", "inferred from the keys") and not src.startswith("default:"):
        base_doc["mechanism"] = {"value": plant.mechanism, "source": src}
    else:
        base_doc["mechanism"] = plant.mechanism
    doc = fitted_document(base_doc, plant, name, chosen, description,
                          list(getattr(plant, "uncertainty", None) or {}) if uncertainty_keys is None else uncertainty_keys)
    return document_toml(doc, None, header)
