"""``prsa-pid``: the generic optimal PI/PID tuner (:func:`prsa_ctrl.tuning.tune_pid`) on any SISO
transfer function, from the command line.

The plant is given without ``eval``: either as polynomial coefficients in ``s`` (highest power
first), ``--num 1 --den 4 1``, or as an expression, ``--plant "1/(4s+1)"``, read by a small
parser (:func:`parse_plant`) that knows numbers, ``s``, ``+ - * /``, ``^`` (or ``**``) with a
non-negative integer exponent, parentheses and implicit products (``4s``, ``2(s+1)``,
``(s+1)(2s+1)``). A delay is ``--delay L`` (seconds, exact ``e^{-sL}``), not part of the
expression.

The load disturbance is a unit step at the plant input; the objective (``--objective``) is
that of the continuous closed loop integrated to infinity (with the exact delay for IE, IAE and
ITAE; ISE with a delay on the Pade model the tuner reports). The report gives the gains in
parallel form (kp, ki, kd) and standard form (K, Ti, Td), the filters, the 2-DOF weights, the
objective, the true peaks Ms, Mt, Mks, the gain and phase margins and the crossover, the
status ("optimal" only where the tuner's independent first-order check holds) and every
warning. ``--json`` writes the same as data, enough to rebuild the controller.

Every flag and the plant are checked before any heavy import (CasADi, python-control), and the
output path before the tuning: bad input is one line naming the value, exit 2. Exit codes as
every command (:mod:`prsa_ctrl.cli.common`): 0 ok, 2 bad input, 3 numerical failure or a result
not proven optimal (unless ``--accept-unconverged``), 130 interrupted.
"""

from __future__ import annotations

import argparse
import math
import re
import warnings
from typing import Sequence

import numpy as np

from ..errors import PlantTextError
from ..io.output import Transaction, check_writable, json_safe
from ..options import CONTROLLERS, MS_MAX_DEFAULT, OBJECTIVES, PEAK_BOUND_RANGE
from ..reporttext import format_pid_report
from ..tuning.plant_text import parse_plant_text, quote_plant_text
from .common import (EXIT_NUMERICAL, EXIT_OK, Parser, Run, UsageError, commit, echo, invoke, native_output, number,
                     path_text, progress, report_failure, show_notes, write_json_atomic)

__all__ = ["pid_main", "build_pid_parser", "parse_plant", "PLANT_ORDER_MAX"]

#: Largest plant order the command accepts (the tuner's own limit, ``tune_pid``'s ``MAX_ORDER``;
#: ``tests/cli/test_pid.py`` checks that the two agree without importing the tuner here).
PLANT_ORDER_MAX = 30

#: Flags whose value may start with ``-`` (a negative coefficient or exponent).
_LIST_FLAGS = ("--num", "--den")
#: Flags of one value that may start with ``-`` (reported by their converter, not as an option).
_VALUE_FLAGS = ("--plant", "--delay", "--ms-max", "--mt-max", "--mks-max", "--max-noise-gain", "--filter-tf", "--tf",
                "--json", "--objective", "--controller", "--filter-order")

_EXAMPLE = "'1/(4s+1)', '2(s+1)/(s^2+3s+1)' or '1/(s+1)^3'"
#: Longest plant expression read (characters).
_TEXT_MAX = 10_000


def _coefficients(flag: str, text: str) -> np.ndarray:
    """``--num``/``--den`` values (blank- or comma-separated numbers) as a float array."""
    parts = [p for p in re.split(r"[\s,]+", text.strip()) if p]
    if not parts:
        raise UsageError(f"{flag} {text!r}: expected coefficients, highest power of s first (e.g. {flag} 4 1)")
    conv = number(flag, what="a finite number", not_a_number="a number (coefficients, highest power of s first)",
                  quoted=True)  # the flags' converter: decided by options.check_number, the text as typed
    try:
        return np.array([conv(p) for p in parts])
    except argparse.ArgumentTypeError as exc:
        raise UsageError(str(exc)) from None


def _poly_text(c) -> str:
    """``[4, 0, 1]`` -> ``'4 s^2 + 1'``."""
    c = np.trim_zeros(np.asarray(c, float), "f")
    n = c.size - 1
    terms = []
    for i, a in enumerate(c):
        p = n - i
        if a == 0 and c.size > 1:
            continue
        mag = abs(a)
        coef = "" if (mag == 1 and p > 0) else f"{mag:g}"
        var = "" if p == 0 else ("s" if p == 1 else f"s^{p}")
        sign = ("-" if a < 0 else "") if not terms else (" - " if a < 0 else " + ")
        terms.append(sign + " ".join(x for x in (coef, var) if x))
    return "".join(terms) or "0"


def parse_plant(text: str | None = None, num: str | None = None, den: str | None = None) -> tuple[list, list, str]:
    """The plant of ``--plant TEXT`` or ``--num``/``--den`` as ``(num, den, shown)``: coefficient
    lists in ``s``, highest power first, leading zeros dropped (an expression's denominator made
    monic; ``--num``/``--den`` as typed), and ``shown``, the plant as text. Checked here, with numpy only: finite
    coefficients, a non-zero numerator, strictly proper, order 1..``PLANT_ORDER_MAX``, no undamped
    poles on the imaginary axis (other than at 0). A :class:`UsageError` names the value.

    Examples
    --------
    >>> parse_plant("2/(s+1)^2")[:2]
    ([2.0], [1.0, 2.0, 1.0])
    >>> parse_plant("1/(4s+1)")[:2]
    ([0.25], [1.0, 0.25])
    >>> parse_plant(num="1", den="4 1")[:2]
    ([1.0], [4.0, 1.0])
    """
    if text is not None:
        label, shown = f"--plant {quote_plant_text(text)}", text
        try:  # an expression's scale is arbitrary: its denominator comes back monic
            n, d = parse_plant_text(text, max_length=_TEXT_MAX, delay_hint="give a delay with --delay")
        except PlantTextError as exc:
            raise UsageError(f"{label}: {exc}") from None
    else:
        label = f"--num {' '.join(num.split())} --den {' '.join(den.split())}"
        n, d = _coefficients("--num", num), _coefficients("--den", den)
        shown = f"({_poly_text(n)})/({_poly_text(d)})"
    n, d = np.trim_zeros(np.asarray(n, float), "f"), np.trim_zeros(np.asarray(d, float), "f")
    if not (np.all(np.isfinite(n)) and np.all(np.isfinite(d))):
        raise UsageError(f"{label}: coefficients overflow double precision; expected finite numbers")
    if d.size == 0:
        raise UsageError(f"{label}: the denominator is zero; expected a non-zero polynomial in s")
    if n.size == 0:
        raise UsageError(f"{label}: the plant is zero; expected a non-zero numerator")
    if n.size >= d.size:
        raise UsageError(f"{label}: numerator degree {n.size - 1} >= denominator degree {d.size - 1} "
                         "(not strictly proper); expected a strictly proper plant (more poles than zeros)")
    if d.size - 1 > PLANT_ORDER_MAX:
        raise UsageError(f"{label}: order {d.size - 1}; expected at most {PLANT_ORDER_MAX} "
                         "(reduce the model first)")
    poles = np.roots(d)
    osc = poles[(np.abs(poles) > 0) & (np.abs(poles.real) <= 1e-12 * np.abs(poles))]
    if osc.size:
        raise UsageError(f"{label}: undamped poles at +-{np.abs(osc.imag).max():.6g}j rad/s; expected damped "
                         "poles (add a little damping)")
    return [float(x) for x in n], [float(x) for x in d], shown


def _relative_degree(num: Sequence[float], den: Sequence[float]) -> int:
    return len(den) - len(num)


# --- flags ----------------------------------------------------------------------------------------

def build_pid_parser() -> argparse.ArgumentParser:
    """Argument parser of ``prsa-pid``."""
    p = Parser(
        prog="prsa-pid", allow_abbrev=False,
        description="Optimal PI/PID for load-disturbance rejection on a SISO transfer function, under true "
        "Ms/Mt/Mks bounds (tune_pid). The load is a unit step at the plant input. "
        "Exit codes: 0 ok, 2 bad input, 3 numerical failure or not proven optimal, 130 interrupted.",
    )
    src = p.add_mutually_exclusive_group()
    src.add_argument("--plant", metavar="EXPR",
                     help=f"plant as a rational function of s, e.g. {_EXAMPLE} (numbers, s, + - * /, ^ with a whole "
                          "exponent, parentheses, implicit products; no delay: use --delay)")
    src.add_argument("--num", metavar="COEFS", help="numerator coefficients, highest power of s first (with --den)")
    p.add_argument("--den", metavar="COEFS", help="denominator coefficients, highest power of s first, e.g. --den 4 1")
    p.add_argument("--delay", metavar="L", type=number("--delay", 0.0, 1e6, "s", "a delay >= 0"), default=0.0,
                   help="exact plant delay e^(-sL), s (default 0)")
    p.add_argument("--objective", choices=OBJECTIVES, default="iae",
                   help="integral of the error after the unit load step, to infinity (default iae)")
    p.add_argument("--controller", choices=CONTROLLERS, default="pi", help="controller structure (default pi)")
    lo, hi = PEAK_BOUND_RANGE
    p.add_argument("--ms-max", metavar="MS", default=MS_MAX_DEFAULT,
                   type=number("--ms-max", lo, hi, "", "a peak sensitivity", lo_open=True, hi_open=True),
                   help=f"bound on the true peak sensitivity max|S|, in ({lo:g}, {hi:g}) (default {MS_MAX_DEFAULT:g})")
    p.add_argument("--mt-max", metavar="MT",
                   type=number("--mt-max", lo, hi, "", "a peak complementary sensitivity", lo_open=True, hi_open=True),
                   help=f"bound on the true peak complementary sensitivity max|T|, in ({lo:g}, {hi:g}) (default none)")
    p.add_argument("--mks-max", metavar="MKS", type=number("--mks-max", 0.0, math.inf, "", "a noise-sensitivity bound > 0",
                                                            lo_open=True),
                   help="bound on the true peak noise sensitivity max|C F S| (plant-input units per output unit; "
                        "default none)")
    p.add_argument("--max-noise-gain", metavar="G", type=number("--max-noise-gain", 0.0, math.inf, "",
                                                                 "a controller high-frequency gain bound > 0",
                                                                 lo_open=True),
                   help="bound on the controller's high-frequency gain kp + kd/tf (default: only where robustness "
                        "alone does not limit the gains)")
    p.add_argument("--filter-order", type=int, choices=(0, 1, 2), default=0,
                   help="measurement filter on the whole controller: 0 none, 1: 1/(Tf s+1), 2: 1/(Tf^2 s^2/2+Tf s+1)")
    p.add_argument("--filter-tf", metavar="S", type=number("--filter-tf", 0.0, 1e6, "s", "a time constant > 0",
                                                            lo_open=True),
                   help="the measurement filter's time constant Tf, s (default: optimised; slow, one tuning per Tf)")
    p.add_argument("--tf", metavar="S", type=number("--tf", 0.0, 1e6, "s", "a time constant > 0", lo_open=True),
                   help="a filtered-derivative PID's derivative filter time constant, s (default 0.1/w135)")
    p.add_argument("--ideal", action="store_true",
                   help="ideal PID kp + ki/s + kd s (no derivative filter; needs --controller pid, and a plant of "
                        "relative degree 2 or a measurement filter)")
    p.add_argument("--setpoint-weights", action="store_true",
                   help="also choose the 2-DOF setpoint weights b, c in [0, 1] (least IAE after a unit setpoint step, "
                        "gains fixed)")
    p.add_argument("--json", type=path_text("--json"), metavar="PATH",
                   help="write the result as JSON (atomically; enough to rebuild the controller)")
    p.add_argument("--accept-unconverged", action="store_true",
                   help="exit 0 even when the result is not proven optimal (default: exit 3)")
    p.add_argument("--verbose", action="store_true", help="progress lines and the solvers' output")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")
    return p


def _glue_lists(argv: Sequence[str]) -> list[str]:
    """``--den 4 1`` -> ``--den=4 1``: the blank-separated values of ``--num``/``--den`` (which may
    start with ``-``, e.g. ``-1e-3``) handed to the parser as one text, up to the next flag."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        a = argv[i]
        if a in _LIST_FLAGS:
            vals = []
            i += 1
            while i < len(argv) and not re.match(r"--[a-zA-Z]", argv[i]):
                vals.append(argv[i])
                i += 1
            if not vals:
                raise UsageError(f"{a}: expected coefficients, highest power of s first (e.g. {a} 4 1)")
            out.append(f"{a}={' '.join(vals)}")
            continue
        out.append(a)
        i += 1
    return out


def _checked(args) -> tuple[list, list, str]:
    """The plant and the combination of options, checked (a :class:`UsageError` naming them)."""
    if args.plant is None and args.num is None:
        raise UsageError("no plant; expected --plant EXPR (e.g. --plant '1/(4s+1)') or --num COEFS --den COEFS")
    if args.plant is not None and args.den is not None:
        raise UsageError(f"--den {args.den} with --plant; expected either --plant EXPR or --num with --den")
    if args.num is not None and args.den is None:
        raise UsageError(f"--num {args.num} without --den; expected --den COEFS too (e.g. --num 1 --den 4 1)")
    num, den, shown = parse_plant(args.plant, args.num, args.den)
    if args.ideal and args.controller != "pid":
        raise UsageError(f"--ideal with --controller {args.controller}; expected --controller pid (the ideal "
                         "derivative)")
    if args.filter_tf is not None and not args.filter_order:
        raise UsageError(f"--filter-tf {args.filter_tf:g} without a filter; expected --filter-order 1 or 2")
    if args.tf is not None and (args.controller != "pid" or args.ideal):
        raise UsageError(f"--tf {args.tf:g} with " + ("--ideal" if args.ideal else f"--controller {args.controller}")
                         + "; expected a filtered-derivative PID (--controller pid without --ideal)")
    if args.ideal and not args.filter_order:
        if args.mks_max is not None:
            raise UsageError(f"--mks-max {args.mks_max:g} with --ideal and no measurement filter: |C S| grows "
                             "without bound with frequency; expected --filter-order 1 or 2")
        if _relative_degree(num, den) < 2:
            raise UsageError(f"--ideal on {shown} (relative degree 1): the ideal derivative feeds the control input "
                             "through; expected --filter-order 1 or 2, or a plant of relative degree 2 or more")
    return num, den, shown


# --- the command ----------------------------------------------------------------------------------

def pid_main(argv: Sequence[str] | None = None) -> int:
    """``prsa-pid``; returns the exit code (0, 2, 3 or 130, see the module docstring)."""
    return invoke("prsa-pid", argv, _body, _VALUE_FLAGS)


def _body(run: Run, argv: list[str]) -> int:
    if "-h" in argv or "--help" in argv:
        build_pid_parser().print_help()
        return EXIT_OK
    args = build_pid_parser().parse_args(_glue_lists(argv))
    run.quiet = args.quiet  # no stray-warning notes either (invoke_inner)
    num, den, shown = _checked(args)
    if args.json is not None:
        check_writable(args.json, (), "--json")
    run.check()
    what = f"tuning {shown}"
    progress(run, args.verbose, f"{what} ...")
    notes: list[warnings.WarningMessage] = []
    native: list[str] = []
    try:
        with warnings.catch_warnings(record=True) as caught, native_output(run, native):
            warnings.simplefilter("always")
            res, sign = _tune(args, num, den)
            notes.extend(caught)
        run.check()
    except KeyboardInterrupt:
        raise
    except Exception as exc:  # noqa: BLE001 - one line at this boundary
        return report_failure(run, exc, what, args.verbose)
    data = result_data(args, num, den, shown, res, sign)
    if args.json is not None:
        outputs = Transaction(())
        try:
            write_json_atomic(args.json, json_safe(data), (), transaction=outputs)
            commit(run, outputs)
        finally:
            outputs.abort()
    if not args.quiet:
        echo(format_pid_report(data))
        if args.json is not None:
            echo(f"JSON: {args.json}")
    show_notes(run, notes, native, args.verbose, args.quiet)
    if not data["converged"] and not args.accept_unconverged:
        run.say(f"{run.prog}: the result is not proven optimal ({data['status']}); its numbers are reported but are "
                "not a verified optimum (use --accept-unconverged to exit 0)")
        return EXIT_NUMERICAL
    return EXIT_OK


def _tune(args, num: list, den: list):
    """:func:`prsa_ctrl.tuning.tune_pid` with the command's options (the heavy imports here):
    ``(result, sign)``. The tuner's gains are non-negative; where no such gains stabilise the
    loop (a reverse-acting plant, e.g. ``-1/(s+1)``), ``-P`` is tuned instead and ``sign`` is -1:
    the gains of ``P`` are then the result's negated (the loop ``P C = (-P)(-C)``, its peaks and
    the load response's magnitude are the same). The sign is found by trying, not guessed from a
    gain (an unstable ``1/(s-1)`` has a negative static gain yet needs positive gains)."""
    from dataclasses import replace

    import control

    from ..errors import NoStabilisingGains
    from ..tuning.generic import tune_pid

    def tune(sign: float):
        return tune_pid(control.tf([sign * x for x in num], den), objective=args.objective,
                        controller=args.controller, ms_max=args.ms_max, mt_max=args.mt_max, mks_max=args.mks_max,
                        max_noise_gain=args.max_noise_gain, tf=args.tf, filter_order=args.filter_order,
                        filter_tf=args.filter_tf, ideal=args.ideal, delay=args.delay,
                        setpoint_weights=args.setpoint_weights)

    try:
        return tune(1.0), 1.0
    except NoStabilisingGains as exc:
        try:
            res = tune(-1.0)
        except ValueError:
            raise exc from None  # neither sign: the error of the plant as given
    return replace(res, warnings=(*res.warnings, "no non-negative gains stabilise this plant: tuned as -P (reverse "
                                                 "acting), the gains negated (same loop, peaks and load-response "
                                                 "magnitude)")), -1.0


def _objective_text(kind: str, delay: float, stats: dict | None = None) -> str:
    """What the reported objective is, in words (``stats``: the result's, for the delay model
    actually used: ``stats["delay_model"]``)."""
    from ..tuning.settings import CONT_RTOL

    model = (stats or {}).get("delay_model") or {}
    order = model.get("pade_order", 6)
    base = f"{kind.upper()} of the continuous closed loop after a unit load step at the plant input, to infinity"
    if kind == "ie":
        how = "closed form: 1/|ki|"
    elif kind == "ise":
        how = "closed form" + (f"; the delay as its Pade model of order {order}" if delay else "")
    else:
        how = f"integrated to a relative accuracy of {CONT_RTOL:g}"
    if delay and kind in ("iae", "itae") and model.get("objective") == "pade":
        return f"{base} ({how}; the delay as its Pade model of order {order}: too far below the loop's time scale " \
               "to simulate exactly)"
    return f"{base} ({how}" + ("; exact delay)" if delay and kind != "ise" else ")")


def result_data(args, num: list, den: list, shown: str, res, sign: float = 1.0) -> dict:
    """The result of ``prsa-pid`` as plain data (the ``--json`` file; the text report's source).

    ``controller`` holds the law ``u = kp (b r - y_f) + ki (r - y_f)/s + kd D(s) (c r - y_f)``,
    ``y_f = F(s) y`` (the filter on the measurement only; from the measurement the controller is
    ``C(s) F(s)``, ``C = kp + ki/s + kd D(s)``) with ``D = s/(tf s + 1)`` (``tf_s`` None: the ideal
    ``s``; a PI has ``kd = 0`` and no ``tf_s``), ``F`` the measurement filter (``filter_order`` 0:
    none; 1: ``1/(Tf s + 1)``; 2: ``1/(Tf^2 s^2/2 + Tf s + 1)``) and ``b``, ``c`` the setpoint
    weights (None: 1); ``standard`` the same gains as ``K (1 + 1/(Ti s) + Td s ...)``.
    """
    pid = res.pid
    kp, ki, kd = sign * pid.kp + 0.0, sign * pid.ki + 0.0, sign * pid.kd + 0.0  # sign -1: a reverse-acting plant tuned as -P
    derivative = args.controller == "pid"
    tf_s = pid.tf if derivative and not args.ideal else None
    filt = res.filter or {}
    order = int(filt.get("order", 0) or 0)
    m = res.margins[0]
    std = {"K": kp, "Ti_s": kp / ki if ki != 0 else math.inf, "Td_s": kd / kp if kp != 0 else math.inf}
    if tf_s is not None and kd > 0:
        std["N"] = std["Td_s"] / tf_s
    sp = res.setpoint
    return {
        "plant": {"text": shown, "num": num, "den": den, "delay_s": args.delay,
                  "load": "unit step at the plant input"},
        "options": {"objective": args.objective, "controller": args.controller, "ms_max": args.ms_max,
                    "mt_max": args.mt_max, "mks_max": args.mks_max, "max_noise_gain": args.max_noise_gain,
                    "filter_order": args.filter_order, "filter_tf_s": args.filter_tf, "tf_s": args.tf,
                    "ideal": args.ideal, "setpoint_weights": args.setpoint_weights},
        "controller": {"kp": kp, "ki": ki, "kd": kd, "tf_s": tf_s,
                       "derivative": "ideal" if args.ideal else ("filtered" if derivative else "none"),
                       "filter_order": order, "filter_tf_s": filt.get("tf_s") if order else None,
                       "b": sp["b"] if sp else None, "c": sp["c"] if sp else None,
                       "law": "u = kp (b r - y_f) + ki (r - y_f)/s + kd D(s) (c r - y_f), y_f = F(s) y: "
                              "D(s) = s/(tf s + 1) (s when ideal), F the measurement filter (1 without one) on the "
                              "measurement only, the setpoint r unfiltered; b = c = 1 without setpoint weights"},
        "standard": std,
        "objective": {"kind": res.kind, "value": res.objective,
                      "evaluation": _objective_text(res.kind, args.delay, res.stats)},
        "ms": res.ms, "mt": res.mt, "mks": res.mks,
        "margins": {"gm_db": m.gm_db, "pm_deg": m.pm_deg, "wc_rad_s": m.wc_rad_s,
                    "wc_hz": m.wc_rad_s / (2 * math.pi) if math.isfinite(m.wc_rad_s) else None,
                    "delay": "exact" if args.delay else "none"},
        "setpoint": sp,
        "status": res.status, "converged": res.converged, "warnings": list(res.warnings),
        "stats": {k: v for k, v in res.stats.items() if k in (
            "objective_sampled", "objective_pade", "delay_pade_change", "delay_model", "filter_search", "first_order", "polished",
            "wall_s", "horizon")},
    }


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(pid_main())
