"""User text on its way to a terminal or into a one-line message.

Text from a user's file or command line (plant and scene names, descriptions, file names, values
quoted in error messages) is data. Two helpers keep it so:

* :func:`printable` escapes the characters a terminal would act on (C0 and C1 control characters
  such as ESC, BEL, CR, DEL; the bidirectional overrides; line and paragraph separators; lone
  surrogates) as ``\\x1b``, ``\\u202e``, ... ; every print of the command-line tools goes
  through it;
* :func:`quote` is the ``repr`` of a value cut to a bounded excerpt (a 100,000-entry list is
  quoted by its first entries and its length, never in full).

Both are pure string functions (no imports beyond the standard library).
"""

from __future__ import annotations

import re
from typing import Any

__all__ = ["printable", "quote", "unicode_text", "MESSAGE_CHARS_MAX", "QUOTE_CHARS_MAX"]

#: Characters at most in one line a command prints (errors, notes); longer lines lose their middle.
MESSAGE_CHARS_MAX = 2000
#: Characters at most of one quoted value (:func:`quote`).
QUOTE_CHARS_MAX = 200

# C0 controls but TAB and LF, DEL and the C1 controls (Unicode category Cc), the bidirectional
# marks and overrides, the line/paragraph separators and lone surrogates (undecodable file names).
_UNSAFE_MULTI = re.compile("[\x00-\x08\x0b-\x1f\x7f-\x9f\u061c\u200e\u200f\u2028-\u202e\u2066-\u2069"
                           "\ud800-\udfff]")
_UNSAFE_LINE = re.compile("[\x00-\x1f\x7f-\x9f\u061c\u200e\u200f\u2028-\u202e\u2066-\u2069\ud800-\udfff]")
_NAMED = {"\t": "\\t", "\n": "\\n", "\r": "\\r"}


def _escape(m: re.Match) -> str:
    c = m.group(0)
    if c in _NAMED:
        return _NAMED[c]
    n = ord(c)
    return f"\\x{n:02x}" if n < 0x100 else f"\\u{n:04x}"


def printable(text: Any, multiline: bool = False, limit: int | None = None) -> str:
    """``text`` with every character a terminal would act on written as an escape.

    Parameters
    ----------
    text : object
        The text (``str()`` of anything else).
    multiline : bool
        Keep line feeds and tabs (a report of several lines); otherwise they are escaped too
        (``\\n``, ``\\t``) and the result is one line.
    limit : int, optional
        At most this many characters (after escaping): a longer text keeps its beginning and
        end around ``... (N characters left out) ...``.

    Returns
    -------
    str

    Examples
    --------
    >>> printable("evil\\x1b]0;title\\x07 name")
    'evil\\\\x1b]0;title\\\\x07 name'
    >>> printable("two\\nlines", multiline=True)
    'two\\nlines'
    >>> printable("two\\nlines")
    'two\\\\nlines'
    >>> len(printable("x" * 10_000, limit=100)) <= 100
    True
    """
    s = text if isinstance(text, str) else str(text)
    s = (_UNSAFE_MULTI if multiline else _UNSAFE_LINE).sub(_escape, s)
    if limit is not None and len(s) > limit:
        cut = f" ... ({len(s)} characters, the middle left out) ... "
        keep = max(limit - len(cut), 2)
        head = (2 * keep) // 3
        s = s[:head] + cut + s[len(s) - (keep - head):]
    return s


def quote(value: Any, limit: int = QUOTE_CHARS_MAX) -> str:
    """``repr(value)`` as an error message quotes it: at most about ``limit`` characters.

    A longer representation keeps its beginning and says how long the value is (entries of a
    list, table or string, digits of an integer); an integer too long for ``repr`` is described
    by its digit count.

    Examples
    --------
    >>> quote([1500.0] * 100_000).endswith("... (a list of 100000 entries, 800000 characters)")
    True
    >>> quote(10 ** 400)
    '1000000000000000000000...0000000000 (an integer of 401 digits)'
    >>> quote("ok")
    "'ok'"
    """
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 64:
        digits = _int_digits(value)
        if digits is not None and len(digits) > 40:
            return f"{digits[:22]}...{digits[-10:]} (an integer of {len(digits.lstrip('-'))} digits)"
        if digits is None:
            return f"an integer of about {int(value.bit_length() * 0.30103) + 1} digits"
    try:
        r = repr(value)
    except ValueError:  # an int beyond Python's digit limit, inside a container
        r = f"<{type(value).__name__} too large to show>"
    if len(r) <= limit:
        return r
    if isinstance(value, (list, tuple, dict, set, frozenset)):
        size = f"a {type(value).__name__} of {len(value)} entries, {len(r)} characters"
    elif isinstance(value, str):
        size = f"a text of {len(value)} characters"
    else:
        size = f"{len(r)} characters"
    return f"{r[:limit]}... ({size})"


def _int_digits(value: int) -> str | None:
    try:
        return str(value)
    except ValueError:  # beyond sys.get_int_max_str_digits()
        return None


_SURROGATE = re.compile("[\ud800-\udfff]")


def unicode_text(text: str) -> str:
    r"""``text`` with every lone surrogate written as an escape: ``\xNN`` for the byte an
    undecodable file name carried (Python's ``surrogateescape``, U+DC80..U+DCFF), ``\uXXXX``
    for any other; text that can be encoded (UTF-8, TOML, JSON) and names the file by the
    byte it had.

    >>> unicode_text("log\udcff.csv")
    'log\\xff.csv'
    """
    def esc(m: re.Match) -> str:
        n = ord(m.group(0))
        return f"\\x{n - 0xDC00:02x}" if 0xDC80 <= n <= 0xDCFF else f"\\u{n:04x}"

    return _SURROGATE.sub(esc, text)
