"""The one reader of a plant typed as text (``prsa_ctrl.tuning.plant_text``), behind both
``prsa-pid --plant`` and the app's generic tuner: known cases, a hypothesis check against a
direct complex evaluation, and every refusal as one line naming where and what is expected."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from prsa_ctrl.errors import PlantTextError
from prsa_ctrl.tuning.plant_text import EXPECTED, MAX_DEGREE, MAX_DEPTH, MAX_POWER, parse_plant_text, quote_plant_text


def _parse(text, **kw):
    return parse_plant_text(text, max_length=kw.pop("max_length", 400), **kw)


@pytest.mark.parametrize("text, num, den", [
    ("1/(4s+1)", [1], [4, 1]),
    ("1 / (4*s + 1)", [1], [4, 1]),
    ("2(s+1)/((s+2)^2 (0.1s+1))", [2, 2], np.polymul(np.polymul([1, 2], [1, 2]), [0.1, 1])),
    ("(1-0.5s)/(s**2+2s+1)", [-0.5, 1], [1, 2, 1]),
    ("-3/(s(s+1))", [-3], [1, 1, 0]),
    ("1e-3/(2.5E-2 s + .5)", [1e-3], [2.5e-2, 0.5]),
    ("s/(s+1)^0", [1, 0], [1]),
    ("3/(s+1) + 1/(s+2)", [4, 7], [1, 3, 2]),
    ("(1/(s+1)) * (1/(s+2)) - 0", [1], [1, 3, 2]),
    ("--+-s/(s+1)", [-1, 0], [1, 1]),
    ("2*-3/(s+1)", [-6], [1, 1]),
    ("  1/(s+1)  ", [1], [1, 1]),
])
def test_known_cases_monic(text, num, den):
    n, d = _parse(text)
    den = np.asarray(den, float)
    assert d[0] == 1.0
    assert n == pytest.approx(np.asarray(num, float) / den[0], rel=1e-12)
    assert d == pytest.approx(den / den[0], rel=1e-12)


_coef = st.floats(min_value=-9, max_value=9, allow_nan=False).filter(lambda x: abs(x) > 1e-3).map(lambda x: round(x, 3))


@settings(max_examples=60, deadline=None, derandomize=True)
@given(st.lists(st.lists(_coef, min_size=1, max_size=3), min_size=1, max_size=3),
       st.lists(st.lists(_coef, min_size=2, max_size=3), min_size=1, max_size=3),
       st.integers(0, 3))
def test_parser_agrees_with_a_direct_evaluation(nums, dens, power):
    """Products of typed polynomials over products of typed polynomials (one raised to a
    power), written with explicit and implicit products: the parsed rational function equals
    the direct complex evaluation at test points."""
    def poly_text(c):
        n = len(c) - 1
        return "(" + " + ".join(f"{a!r}" + ("" if k == n else (" s" if k == n - 1 else f" s^{n - k}"))
                                for k, a in enumerate(c)) + ")"

    def poly_val(c, s):
        return sum(a * s ** (len(c) - 1 - k) for k, a in enumerate(c))

    den_text = " * ".join(poly_text(c) for c in dens[:-1]) + (" * " if len(dens) > 1 else "") + \
        poly_text(dens[-1]) + f"^{power}"
    text = "".join(poly_text(c) for c in nums) + "/(" + den_text + ")"
    n, d = _parse(text)
    for s in (0.37 + 1.1j, -0.8 + 0.3j, 2.5j):
        want = np.prod([poly_val(c, s) for c in nums]) / (
            np.prod([poly_val(c, s) for c in dens[:-1]]) * poly_val(dens[-1], s) ** power)
        if not np.isfinite(want) or abs(want) > 1e12:
            continue
        assert complex(np.polyval(n, s) / np.polyval(d, s)) == pytest.approx(complex(want), rel=1e-8, abs=1e-10)


@pytest.mark.parametrize("text, message", [
    ("", r"^empty; "),
    ("   ", r"^empty; "),
    ("1/(s+1", r"^unbalanced parenthesis: missing '\)' at the end; "),
    ("(s^2^3)/(s+1)", r"^unbalanced parenthesis: missing '\)' at position 5; "),
    ("1/(s-s)", r"^division by zero; "),
    ("1/0", r"^division by zero; "),
    ("exp(-s)/(s+1)", r"^unexpected 'e' at position 1; a delay is given separately; "),
    ("1/(s+1) E", r"^unexpected 'E' at position 9; a delay is given separately; "),
    ("eps/(s+1)", r"^unexpected 'e' at position 1; expected a rational"),  # no delay hint for another word
    ("__import__('os')", r"^unexpected '_' at position 1; "),
    ("1/(s+1)^31", r"^exponent '31' at position 9: expected a whole number 0\.\.30; "),
    ("1/(s+1)^-1", r"^exponent '-' at position 9: expected a whole number 0\.\.30; "),
    ("1/(s+1)^1.5", r"^exponent '1\.5' at position 9: expected a whole number 0\.\.30; "),
    ("1/(s+1)^", r"^exponent at the end: expected a whole number 0\.\.30; "),
    ("0*s/(s+1)", r"^the plant is zero; "),
    ("(" * 21 + "s" + ")" * 21, r"^parentheses nested deeper than 20 at position 21; "),
    ("1/(s+1))", r"^unexpected '\)' at position 8; "),
    ("1/(s+1)*", r"^unexpected end; "),
    ("1e999/(s+1)", r"^number '1e999' is not finite at position 1; "),
    ("1e200^2/(s+1)", r"^coefficients beyond double precision; "),
    ("1e300/(1e-300s+1)", r"^coefficients beyond double precision once the denominator is made monic; "),
    ("1e-300/(1e300s+1)", r"^coefficients beyond double precision once the denominator is made monic; "),
    ("((s+1)^30)^30 ((s+1)^30)^30", rf"^a product of degree above {MAX_DEGREE}; "),
    # issue 31: numbers side by side were multiplied (1..2 read as 0.2, 1.2.3 as 0.36, 2 3 as 6)
    ("1/(1..2s+1)", r"^number '1\.\.2' at position 4: expected one number with at most one decimal point"),
    ("1/(1.2.3s+1)", r"^number '1\.2\.3' at position 4: expected one number with at most one decimal point"),
    ("1/(2.5e-3.5s+1)", r"^number '2\.5e-3\.5' at position 4: expected one number"),
    ("2 3/(s+1)", r"^number '3' at position 3 right after the number '2' at position 1: expected an operator"),
    ("1/(1.2 .3s+1)", r"^number '\.3' at position 8 right after the number '1\.2' at position 4: expected an op"),
    ("1/(s+1)^2 3", r"^number '3' at position 11 right after the number '2' at position 9: expected an operator"),
    ("1/(s2+1)", r"^number '2' at position 5 right after 's' at position 4: expected an operator between them"),
    ("1/(s 2+1)", r"^number '2' at position 6 right after 's' at position 4: "),
])
def test_refusals_are_one_line_with_where_and_what(text, message):
    with pytest.raises(PlantTextError, match=message) as info:
        _parse(text)
    msg = str(info.value)
    assert "\n" not in msg
    assert repr(text) not in msg  # the caller names the text
    assert msg.endswith(EXPECTED)
    assert isinstance(info.value, ValueError)


def test_implicit_products_that_stay_are_the_documented_ones():
    """Adjacent factors still multiply where one of them is not a bare number: 4s, 2(s+1),
    (s+1)(s+2), (s+2)^2 (0.1s+1), a number after a parenthesis."""
    for text, num, den in (("1/(4 s+1)", [0.25], [1, 0.25]), ("2 (s+1)/(s+2)", [2, 2], [1, 2]),
                           ("1/((s+1) (s+2))", [1], [1, 3, 2]), ("(s+1)2/(s+2)", [2, 2], [1, 2])):
        n, d = _parse(text)
        assert n == pytest.approx(num)
        assert d == pytest.approx(den)


def test_prsa_pid_names_the_text_and_the_position(capsys):
    from prsa_ctrl.cli.pid import pid_main

    assert pid_main(["--plant", "1/(1..2s+1)"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("prsa-pid: error: --plant '1/(1..2s+1)': number '1..2' at position 4")
    assert err.count("\n") == 1


def test_limits_are_the_documented_ones():
    assert (MAX_DEPTH, MAX_POWER) == (20, 30)
    assert _parse("(" * 20 + "s" + ")" * 20 + "/(s+1)")[0] == pytest.approx([1, 0])
    n, d = _parse("1/(s+1)^30")
    assert d == pytest.approx(np.poly(-np.ones(30)), rel=1e-12)
    assert n == pytest.approx([1.0])


def test_length_limit_is_the_callers():
    text = "1/(s+1)" + " " * 93  # 100 characters
    assert _parse(text, max_length=100)[1] == pytest.approx([1, 1])
    with pytest.raises(PlantTextError, match=r"^101 characters; expected at most 100$"):
        _parse(text + " ", max_length=100)


def test_delay_hint_is_the_callers():
    with pytest.raises(PlantTextError, match=r"^unexpected 'e' at position 9; use the delay box; "):
        _parse("1/(s+1)*exp(-s)", delay_hint="use the delay box")


def test_not_text():
    with pytest.raises(PlantTextError, match=r"^not text; "):
        _parse(12)


def test_quote_shortens_long_text():
    assert quote_plant_text("1/(s+1)") == "'1/(s+1)'"
    assert quote_plant_text("s" * 81) == repr("s" * 60) + "..."
    assert quote_plant_text("s" * 80) == repr("s" * 80)


def test_the_cli_and_the_app_prefix_their_labels():
    from prsa_ctrl.cli.common import UsageError
    from prsa_ctrl.cli.pid import parse_plant

    with pytest.raises(UsageError) as info:
        parse_plant("1/(s+1)^31")
    want = f"exponent '31' at position 9: expected a whole number 0..30; {EXPECTED}"
    assert str(info.value) == f"--plant '1/(s+1)^31': {want}"
    with pytest.raises(UsageError, match=r"^--plant '1/\(s\+1\)\*exp\(-s\)': unexpected 'e' at position 9; "
                                         r"give a delay with --delay; "):
        parse_plant("1/(s+1)*exp(-s)")
    pytest.importorskip("bokeh")
    from prsa_ctrl.app.generic import parse_transfer_function
    from prsa_ctrl.app.session import AppInputError

    with pytest.raises(AppInputError) as info:
        parse_transfer_function("1/(s+1)^31")
    assert str(info.value) == f"plant '1/(s+1)^31': {want}"


def test_the_reader_imports_numpy_only():
    code = ("import sys, prsa_ctrl.tuning.plant_text as m; m.parse_plant_text('1/(s+1)', max_length=9); "
            "print(sorted(k for k in ('control', 'casadi', 'scipy', 'matplotlib') if k in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
