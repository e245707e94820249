"""The one reader of the TOML files a user hands over (plants, scenes with their filters, log
descriptions, linear-axis plants, the uncertainty correlations inside a plant).

:func:`read_toml` parses with :mod:`tomllib` and refuses, in one line naming the file and the
key, what the parser accepts but no number of a plant can hold:

* an integer beyond the floating-point range (``1`` followed by 400 zeros; about 1.8e308 is
  the largest float) or beyond Python's digit limit for reading integers (4,300 digits);
* arrays or tables nested deeper than :data:`NESTING_MAX` levels (the deepest key of a valid
  file is four levels down), including nesting so deep that the parser itself would overflow
  Python's stack.

The messages quote values as bounded excerpts (:func:`prsa_ctrl.textsafe.quote`).
"""

from __future__ import annotations

import re
import sys
import tomllib
from typing import Any, Callable

from .textsafe import quote

__all__ = ["read_toml", "NESTING_MAX"]

#: Deepest nesting of arrays and tables accepted in a user's TOML file (levels).
NESTING_MAX = 32

#: Tokens of the nesting scan (strings and comments skipped, brackets and line ends counted).
_TOKEN = re.compile(r'"""(?:[^"\\]|\\[\s\S]|"(?!""))*"{3,5}|' r"'''[\s\S]*?'{3,5}|"
                    r'"(?:[^"\\\n]|\\.)*"|' r"'[^'\n]*'|#[^\n]*|[\[\]{}\n]")
_KEY = re.compile(r"^\s*([^=#\[\]{}\n]+?)\s*=")


def read_toml(text: str, origin: str, error: Callable[[str], Exception]) -> dict[str, Any]:
    """Parse a user's TOML text and check that every number fits a float and the nesting is shallow.

    Parameters
    ----------
    text : str
        The file's text (decoded; a byte-order mark already dropped by the caller).
    origin : str
        How messages name the file (its path as typed, or ``"name.toml (built-in)"``).
    error : callable
        The exception class of the caller (``PlantFileError``, ``SceneError``, ...), called
        with the one-line message.

    Returns
    -------
    dict
        The document, as :func:`tomllib.loads` returns it.

    Raises
    ------
    Exception
        ``error(message)``: invalid TOML, an integer beyond the float range, too deep a nesting;
        the message names ``origin`` and the key (dotted, ``[i]`` for array entries).

    Examples
    --------
    >>> read_toml("a = 1", "x.toml", ValueError)
    {'a': 1}
    >>> read_toml("[s]\\nk = [1, 1" + "0" * 400 + "]", "x.toml", ValueError)
    Traceback (most recent call last):
    ...
    ValueError: x.toml: s.k[1] = 1000000000000000000000...0000000000 (an integer of 401 digits): beyond the floating-point range; expected a number of magnitude at most 1.8e+308
    """
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{origin}: invalid TOML ({exc})") from None
    except RecursionError:
        line, key = _deepest(text)
        raise error(f"{origin}: {_where(line, key)}nests arrays or tables too deep for the parser; expected at "
                    f"most {NESTING_MAX} levels") from None
    except ValueError as exc:  # an integer beyond sys.get_int_max_str_digits() (tomllib raises it raw)
        line, key = _long_integer(text)
        raise error(f"{origin}: {_where(line, key)}an integer of more than {sys.get_int_max_str_digits()} digits "
                    f"({type(exc).__name__}); expected a number of magnitude at most {sys.float_info.max:.2g}") from None
    _check(doc, origin, error)
    return doc


def _where(line: int | None, key: str | None) -> str:
    if line is None:
        return ""
    return f"line {line}" + (f", key {key!r}" if key else "") + ": "


def _check(doc: dict, origin: str, error: Callable[[str], Exception]) -> None:
    """Walk the document without recursion: integers within float range, nesting bounded."""
    stack: list[tuple[str, Any, int]] = [(k, v, 1) for k, v in reversed(list(doc.items()))]
    while stack:
        key, value, depth = stack.pop()
        if isinstance(value, (dict, list)):
            if depth > NESTING_MAX:
                shown = re.sub(r"(\[\d+\]){3,}", "[...]", key)
                raise error(f"{origin}: {shown if len(shown) <= 80 else shown[:80] + '...'} nests arrays or tables "
                            f"more than {NESTING_MAX} levels deep; "
                            f"expected at most {NESTING_MAX} levels")
            items = value.items() if isinstance(value, dict) else ((f"[{i}]", v) for i, v in enumerate(value))
            sub = [(f"{key}.{k}" if isinstance(value, dict) else f"{key}{k}", v, depth + 1) for k, v in items]
            stack.extend(reversed(sub))
        elif isinstance(value, int) and not isinstance(value, bool):
            try:
                float(value)
            except OverflowError:
                raise error(f"{origin}: {key} = {quote(value)}: beyond the floating-point range; expected a "
                            f"number of magnitude at most {sys.float_info.max:.2g}") from None


def _deepest(text: str) -> tuple[int | None, str | None]:
    """(line, key) of the first value nested deeper than :data:`NESTING_MAX` (the message's
    pointer only; the refusal itself comes from the parser)."""
    depth, line, start, key = 0, 1, None, None
    lines = text.splitlines()
    for m in _TOKEN.finditer(text):
        tok = m.group(0)
        if tok == "\n":
            line += 1
        elif tok in "[{":
            if depth == 0:
                start = line
                k = _KEY.match(lines[line - 1]) if line - 1 < len(lines) else None
                key = k.group(1).strip() if k else None
            depth += 1
            if depth > NESTING_MAX:
                return start, key
        elif tok in "]}":
            depth = max(depth - 1, 0)
        else:
            line += tok.count("\n")
    return None, None


def _long_integer(text: str) -> tuple[int | None, str | None]:
    """(line, key) of the first line holding a run of more digits than Python reads."""
    limit = sys.get_int_max_str_digits()
    run = re.compile(r"\d[\d_]{%d,}" % limit)
    for i, ln in enumerate(text.splitlines(), 1):
        if run.search(ln):
            k = _KEY.match(ln)
            return i, (k.group(1).strip() if k else None)
    return None, None
