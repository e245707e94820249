"""A plant typed as text, e.g. ``"1/(4s+1)"`` or ``"2(s+1)/((s+2)^2 (0.1s+1))"``, read into
transfer-function coefficients: the one parser behind ``prsa-pid --plant`` and the app's generic
tuner.

numpy only (the command line's flag checks import it without the control libraries). Nothing is
evaluated as Python: a recursive-descent reader of numbers, ``s``, ``+ - * /``, ``^`` or ``**``
and parentheses, every loop bounded by the text's length, the nesting depth, the exponent and the
degree limits below. Errors are :class:`~prsa_ctrl.errors.PlantTextError` with a message that
does not name the text (each caller prefixes its own label, e.g. ``--plant '1/(s+1'``).
"""

from __future__ import annotations

import math
import re

import numpy as np

from ..errors import PlantTextError

__all__ = ["parse_plant_text", "quote_plant_text", "MAX_DEPTH", "MAX_POWER", "MAX_DEGREE", "EXPECTED"]

#: Deepest nesting of parentheses accepted.
MAX_DEPTH = 20
#: Largest exponent accepted after ``^`` or ``**`` (a whole number).
MAX_POWER = 30
#: Largest degree of any intermediate numerator or denominator polynomial (bounds the work of
#: nested powers such as ``((s+1)^30)^30``).
MAX_DEGREE = 1000
#: What every message ends with.
EXPECTED = "expected a rational function of s, e.g. 1/(4s+1) or 2(s+1)/((s+2)^2 (0.1s+1))"

_TOKEN = re.compile(r"\s*(?:(?P<num>(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)|(?P<op>\*\*|[-+*/^()])|(?P<s>s)|(?P<bad>\S))")
_ONE = np.array([1.0])


def quote_plant_text(text: str, limit: int = 80) -> str:
    """``repr(text)``, or the first 60 characters' ``repr`` and ``...`` when ``text`` is longer
    than ``limit`` characters: how a caller names the text in a one-line message.

    Examples
    --------
    >>> quote_plant_text("1/(s+1)")
    "'1/(s+1)'"
    """
    return repr(text) if len(text) <= limit else repr(text[:60]) + "..."


def parse_plant_text(text: str, *, max_length: int, delay_hint: str = "a delay is given separately",
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Numerator and denominator coefficients (highest power of ``s`` first) of a plant typed as
    a rational function of ``s`` (``s`` in rad/s; the coefficients in the units the text implies).

    Parameters
    ----------
    text : str
        Numbers, ``s``, ``+ - * /``, ``^`` or ``**`` with a whole exponent 0..:data:`MAX_POWER`,
        parentheses nested up to :data:`MAX_DEPTH`; adjacent factors multiply (``4s``,
        ``2(s+1)``, ``(s+1)(s+2)``), except a number right after a number or ``s`` (``2 3``,
        ``1..2``, ``1.2.3``, ``s2``): refused with its position, never multiplied.
    max_length : int
        Longest text accepted (characters), the caller's limit.
    delay_hint : str, optional
        Appended when the text holds ``e`` or ``exp`` (a delay typed into the transfer function):
        where the caller takes a delay instead.

    Returns
    -------
    (ndarray, ndarray)
        Numerator and denominator, leading zeros dropped, the denominator's leading coefficient 1
        (common factors are not cancelled).

    Raises
    ------
    PlantTextError
        One line without the text itself: what is wrong, where (a 1-based position), and what is
        expected.

    Examples
    --------
    >>> num, den = parse_plant_text("1/(4s+1)", max_length=400)
    >>> num.tolist(), den.tolist()
    ([0.25], [1.0, 0.25])
    """
    if not isinstance(text, str):
        raise PlantTextError(f"not text; {EXPECTED}")
    if len(text) > max_length:
        raise PlantTextError(f"{len(text)} characters; expected at most {max_length}")
    num, den = _Reader(text, delay_hint).parse()
    num, den = np.trim_zeros(np.asarray(num, float), "f"), np.trim_zeros(np.asarray(den, float), "f")
    if not (np.all(np.isfinite(num)) and np.all(np.isfinite(den))) or den.size == 0:
        raise PlantTextError(f"coefficients beyond double precision; {EXPECTED}")
    if num.size == 0:
        raise PlantTextError(f"the plant is zero; {EXPECTED}")
    with np.errstate(over="ignore", under="ignore", invalid="ignore"):  # checked just below, no warning
        num, den = num / den[0], den / den[0]
    # 1e300/(1e-300s+1) is 1e600 after the scaling, 1e-300/(1e300s+1) 1e-600 (zero)
    if not (np.all(np.isfinite(num)) and np.all(np.isfinite(den)) and np.any(num)):
        raise PlantTextError(f"coefficients beyond double precision once the denominator is made monic; {EXPECTED}")
    return num, den


class _Reader:
    """Recursive descent over the tokens; values are ``(num, den)`` coefficient arrays, highest
    power first."""

    def __init__(self, text: str, delay_hint: str) -> None:
        self.text = text
        self.toks: list[tuple[str, str, int]] = []
        pos = 0
        while pos < len(text):
            m = _TOKEN.match(text, pos)
            if m is None:  # only trailing blanks left
                break
            kind = m.lastgroup
            if kind == "bad":
                j = m.start("bad")
                word = re.match(r"[A-Za-z_]+", text[j:])
                hint = f"; {delay_hint}" if word and word.group(0).lower() in ("e", "exp") else ""
                self.fail(f"unexpected {text[j]!r} at position {j + 1}{hint}")
            if kind == "num" and self.toks and self.toks[-1][0] in ("num", "s"):
                self._side_by_side(self.toks[-1], m.group(kind), m.start(kind))
            self.toks.append((kind, m.group(kind), m.start(kind)))
            pos = m.end()
        self.i = 0
        self.depth = 0

    def fail(self, what: str):
        raise PlantTextError(f"{what}; {EXPECTED}")

    def _side_by_side(self, before: tuple[str, str, int], number: str, start: int) -> None:
        """A number right after a number or ``s`` (blanks between or not) is refused, never
        multiplied: ``1..2`` and ``1.2.3`` are mistyped numbers (they read as 1 x 0.2 and
        1.2 x 0.3), ``2 3`` a missing operator, ``s2`` a missing ``^``."""
        if before[0] == "s":
            self.fail(f"number {number!r} at position {start + 1} right after 's' at position {before[2] + 1}: "
                      f"expected an operator between them (write {number}s, s^{number} or s*{number})")
        if self.text[before[2] + len(before[1]):start] == "":  # written together: one mistyped number
            self.fail(f"number {before[1] + number!r} at position {before[2] + 1}: expected one number with at "
                      "most one decimal point (e.g. 1.2)")
        self.fail(f"number {number!r} at position {start + 1} right after the number {before[1]!r} at position "
                  f"{before[2] + 1}: expected an operator between two numbers (e.g. 2*3)")

    def peek(self) -> tuple[str, str, int] | None:
        return self.toks[self.i] if self.i < len(self.toks) else None

    def take(self, *ops: str) -> str | None:
        """The next operator if it is one of ``ops`` (consumed), else None."""
        t = self.peek()
        if t is not None and t[0] == "op" and t[1] in ops:
            self.i += 1
            return t[1]
        return None

    def where(self) -> str:
        t = self.peek()
        return f"at position {t[2] + 1}" if t is not None else "at the end"

    def parse(self):
        if not self.toks:
            self.fail("empty")
        v = self.expr()
        if self.peek() is not None:
            self.fail(f"unexpected {self.peek()[1]!r} {self.where()}")
        return v

    def mul(self, a, b):
        if (a[0].size + b[0].size - 2 > MAX_DEGREE) or (a[1].size + b[1].size - 2 > MAX_DEGREE):
            self.fail(f"a product of degree above {MAX_DEGREE}")
        return np.polymul(a[0], b[0]), np.polymul(a[1], b[1])

    def expr(self):
        v = self.term()
        while (op := self.take("+", "-")) is not None:
            w = self.term()
            num, den = self.mul((v[0], v[1]), (w[1], w[1]))  # a/b + c/d = (a d + c b) / (b d)
            v = np.polyadd(num, (-1.0 if op == "-" else 1.0) * np.polymul(w[0], v[1])), den
        return v

    def term(self):
        v = self.unary()
        while True:
            op = self.take("*", "/")
            t = self.peek()
            if op is None and not (t is not None and (t[0] in ("num", "s") or t[1] == "(")):
                return v
            w = self.unary() if op else self.power()  # implicit product: 4s, 2(s+1), (s+1)(s+2)
            if op == "/":
                if not np.any(w[0]):
                    self.fail("division by zero")
                w = (w[1], w[0])
            v = self.mul(v, w)

    def unary(self):
        sign = 1.0
        while (op := self.take("+", "-")) is not None:  # a run of signs, read without recursion
            sign = -sign if op == "-" else sign
        v = self.power()
        return (sign * v[0], v[1])

    def power(self):
        v = self.atom()
        if self.take("^", "**") is None:
            return v
        t = self.peek()
        if t is None or t[0] != "num" or not re.fullmatch(r"\d+", t[1]) or int(t[1]) > MAX_POWER:
            shown = f"{t[1]!r} " if t is not None else ""
            self.fail(f"exponent {shown}{self.where()}: expected a whole number 0..{MAX_POWER}")
        self.i += 1
        out = (_ONE, _ONE)
        for _ in range(int(t[1])):
            out = self.mul(out, v)
        return out

    def atom(self):
        t = self.peek()
        if t is None:
            self.fail("unexpected end")
        if t[0] == "num":
            x = float(t[1])
            if not math.isfinite(x):
                self.fail(f"number {t[1]!r} is not finite at position {t[2] + 1}")
            self.i += 1
            return np.array([x]), _ONE
        if t[0] == "s":
            self.i += 1
            return np.array([1.0, 0.0]), _ONE
        if self.take("(") is None:
            self.fail(f"unexpected {t[1]!r} {self.where()}")
        self.depth += 1
        if self.depth > MAX_DEPTH:
            self.fail(f"parentheses nested deeper than {MAX_DEPTH} at position {t[2] + 1}")
        v = self.expr()
        if self.take(")") is None:
            self.fail(f"unbalanced parenthesis: missing ')' {self.where()}")
        self.depth -= 1
        return v
