"""``prsa-tune`` (tune the speed loop for a load step or a duty cycle, verify, compare with baselines) and
``prsa-plot`` (figures and margins for given gains).

Exit codes, the same for both tools:

* 0 -- success (warnings, if any, are printed after the result);
* 2 -- bad input: one line ``prsa-tune: error: ...`` naming the value as typed and what was
  expected (flags, plant and scene files, output paths); nothing is written;
* 3 -- numerical failure: one line ``prsa-tune: numerical failure: ...``; nothing is written;
* 130 -- interrupted (Ctrl-C), at any moment up to the exit: the run stops within a second with
  one line; the outputs are all old or all new, and the line says which ("no output written",
  or "after the outputs were written complete: ...").

Every flag is checked in the user's unit before any heavy import; the scene is checked against
the plant (:func:`prsa_ctrl.studies.scene.check_against_plant`), ``--scheduler`` is parsed and connected
to (bounded by ``SCHEDULER_CONNECT_TIMEOUT_S``); output paths are checked before the expensive
work and written by :mod:`prsa_ctrl.io.output` in one :class:`~prsa_ctrl.io.output.Transaction`
(atomic, all or nothing, never onto an input file -- plant, scene, CSV traces -- nor into the
package's own files).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import re
import os
import signal
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

from ..errors import GeometryWarning, PlantFileError, SceneError, SimulationError
from ..options import CONTROLLERS, ESTIMATORS, OBJECTIVES
from ..io.output import OutputError

__all__ = ["main", "plot_main", "parse_load_step", "write_json_atomic", "format_report", "build_parser",
           "build_plot_parser", "EXIT_OK", "EXIT_BAD_INPUT", "EXIT_NUMERICAL", "EXIT_INTERRUPTED"]

_T_START = time.perf_counter()

EXIT_OK, EXIT_BAD_INPUT, EXIT_NUMERICAL, EXIT_INTERRUPTED = 0, 2, 3, 130
#: Exit code after SIGTERM (128 + 15): handled like Ctrl-C (workers stopped, one line, nothing written).
EXIT_TERMINATED = 128 + signal.SIGTERM

#: Seconds between Ctrl-C and a forced exit when a solver does not hand control back.
INTERRUPT_GRACE_S = 0.8

#: Gain ranges accepted by ``prsa-plot`` (SI): far beyond any sensible speed loop of a roller
#: screw (tuned kp ~0.1 N m s/rad), but finite so that every matrix stays representable.
KP_RANGE = (1e-9, 1e4)
KI_RANGE = (0.0, 1e7)
KD_RANGE = (0.0, 1e2)
WORKERS_MAX = 64


class _UsageError(Exception):
    """Bad input: exit 2 with the message."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2, no usage dump
        m = re.match(r"argument (\S+): (--\S+ .*)$", message, re.S)
        if m and m.group(2).split()[0] in m.group(1).split("/"):
            message = m.group(2)  # our converters already name the flag
        raise _UsageError(message)


# --- flag values ---------------------------------------------------------------------------------

def _number(flag: str, lo: float, hi: float, unit: str, what: str, lo_open: bool = False,
            hi_open: bool = False) -> Callable[[str], float]:
    """Converter for a finite number in a stated range; messages quote the text as typed."""
    lb = "(" if lo_open else "["
    rb = ")" if hi_open else "]"
    rng = f"{lb}{lo:g}, {hi:g}{rb}" + (f" {unit}" if unit else "")

    def conv(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{flag} {text!r}: expected {what} in {rng}") from None
        ok = math.isfinite(v) and (v > lo if lo_open else v >= lo) and (v < hi if hi_open else v <= hi)
        if not ok:
            raise argparse.ArgumentTypeError(f"{flag} {text}" + (f" {unit}" if unit and math.isfinite(v) else "")
                                             + f": expected {what} in {rng}")
        return v

    return conv


def _integer(flag: str, lo: int, hi: int, what: str) -> Callable[[str], int]:
    def conv(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{flag} {text!r}: expected {what} {lo}..{hi}") from None
        if not lo <= v <= hi:
            raise argparse.ArgumentTypeError(f"{flag} {text}: expected {what} {lo}..{hi}")
        return v

    return conv


def _path_text(flag: str) -> Callable[[str], str]:
    def conv(text: str) -> str:
        if not text.strip():
            raise argparse.ArgumentTypeError(f"{flag} {text!r}: expected a path")
        if "\x00" in text:
            raise argparse.ArgumentTypeError(f"{flag} {text!r}: a path may not contain NUL characters")
        return text

    return conv


def parse_load_step(text: str) -> tuple[float, tuple[float, ...]]:
    """Parse ``INITIAL:FINAL[,FINAL...]`` (N), e.g. ``500:1500`` or ``500:1000,1500,2000``.

    Raises
    ------
    argparse.ArgumentTypeError
        One line quoting ``text``: malformed, non-finite or negative loads, a final load equal
        to the initial one, more than ``MAX_LOAD_LEVELS`` levels. Whether the plant can hold
        the loads is checked against the plant (:func:`prsa_ctrl.studies.scene.check_against_plant`).

    Examples
    --------
    >>> parse_load_step("500:1000,1500")
    (500.0, (1000.0, 1500.0))
    """
    from ..studies.scene import MAX_LOAD_LEVELS

    expected = "expected INITIAL:FINAL[,FINAL...] in newtons >= 0, e.g. 500:1500"
    parts = text.split(":")
    if len(parts) != 2 or not parts[0].strip() or not parts[1].strip():
        raise argparse.ArgumentTypeError(f"{text!r}: {expected}")
    tokens = parts[1].split(",")
    if len(tokens) > MAX_LOAD_LEVELS:
        raise argparse.ArgumentTypeError(f"{text[:40]!r}...: {len(tokens)} load levels; expected at most {MAX_LOAD_LEVELS}")
    try:
        initial = float(parts[0])
        finals = tuple(float(p) for p in tokens)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: {expected}") from None
    for tok, v in zip((parts[0], *tokens), (initial, *finals)):
        if not math.isfinite(v) or v < 0:
            raise argparse.ArgumentTypeError(f"{text!r}: load {tok.strip()} N is not allowed; {expected}")
    for f in finals:
        if f == initial:
            raise argparse.ArgumentTypeError(f"{text!r}: final load equals the initial load; expected a step")
    return initial, finals


def _load_step_flag(text: str) -> tuple[float, tuple[float, ...]]:
    try:
        return parse_load_step(text)
    except argparse.ArgumentTypeError as exc:
        raise argparse.ArgumentTypeError(f"--load-step {exc}") from None


# --- parsers -------------------------------------------------------------------------------------

def _common_flags(p: argparse.ArgumentParser) -> None:
    from ..studies.scene import SETPOINT_MAX_RPM

    p.add_argument("--plant", default=None, type=_path_text("--plant"), metavar="NAME|PATH",
                   help="built-in plant name or a plant .toml file (default: paper-iprsm)")
    p.add_argument("--scene", default=None, type=_path_text("--scene"), metavar="NAME|PATH",
                   help="built-in scene name or a scene .toml file (default: paper-load-step); duty-cycle "
                        "scenes (load/setpoint profiles, CSV traces): duty-ramp, duty-trace")
    p.add_argument("--load-step", type=_load_step_flag, metavar="N0:N1[,N2...]",
                   help="initial and final axial load(s), N, compressive >= 0; at most what the motor can hold "
                        "at the setpoint (default: the scene's, 500:1500)")
    p.add_argument("--setpoint-rpm", metavar="RPM",
                   type=_number("--setpoint-rpm", 0.0, SETPOINT_MAX_RPM, "rpm", "a nut speed", lo_open=True),
                   help=f"nut-speed setpoint, rpm, in (0, {SETPOINT_MAX_RPM:g}] (default: the scene's, 300)")
    p.add_argument("--verbose", action="store_true",
                   help="progress lines on stderr, solver diagnostics and notes about the plant (geometry)")


def build_parser() -> argparse.ArgumentParser:
    """Argument parser of ``prsa-tune``."""
    p = _Parser(
        prog="prsa-tune", allow_abbrev=False,
        description="Tune the nut-speed PI/PID of an inverted planetary roller screw actuator "
        "for a load step, verify on the nonlinear simulator, compare with baselines. "
        "Exit codes: 0 ok, 2 bad input, 3 numerical failure, 130 interrupted.",
    )
    _common_flags(p)
    p.add_argument("--show-plant", type=_path_text("--show-plant"), metavar="NAME|PATH",
                   help="print every value of the plant with its unit and source (given or default), then exit")
    p.add_argument("--step-time", metavar="S", type=_number("--step-time", 0.0, 1e4, "s", "a time", lo_open=True),
                   help="time of the load step, s; at least 8 controller samples after t = 0 (default: the scene's)")
    p.add_argument("--duration", metavar="S", type=_number("--duration", 0.0, 1e4, "s", "a time", lo_open=True),
                   help="end of the record, s; at least 80 controller samples after the step and at most "
                        "40000 samples in all (default: the scene's)")
    p.add_argument("--ms-max", metavar="MS", type=_number("--ms-max", 1.0, 10.0, "", "a peak sensitivity",
                                                          lo_open=True, hi_open=True),
                   help="peak-sensitivity bound, in (1, 10) (default: the scene's, 1.4)")
    p.add_argument("--mt-max", metavar="MT", type=_number("--mt-max", 1.0, 10.0, "", "a peak complementary sensitivity",
                                                          lo_open=True, hi_open=True),
                   help="peak complementary-sensitivity bound, in (1, 10); Mt >= 1 with integral action "
                        "(default: the scene's, none)")
    p.add_argument("--mks-max", metavar="MKS", type=_number("--mks-max", 0.0, 1e12, "N m s/rad",
                                                            "a noise-sensitivity bound", lo_open=True),
                   help="bound on the true peak noise sensitivity max|C F S| from the measured speed to the torque "
                        "command, N m s/rad (default: the scene's, none)")
    p.add_argument("--objective", choices=OBJECTIVES, help="tuning objective (default: the scene's, iae)")
    p.add_argument("--controller", choices=CONTROLLERS, help="controller structure (default: the scene's, pi)")
    p.add_argument("--estimator", choices=ESTIMATORS, help="speed measurement: drive difference or Kalman filter")
    p.add_argument("--feedforward", action="store_true", help="feed the estimated load torque forward (needs --estimator kf)")
    p.add_argument("--json", type=_path_text("--json"), metavar="PATH",
                   help="write the report as JSON (atomically; never onto an input file; symlinks are written through)")
    p.add_argument("--plots", type=_path_text("--plots"), metavar="DIR",
                   help="write the standard plots (PNG and SVG) into DIR (created if missing)")
    p.add_argument("--workers", type=_integer("--workers", 1, WORKERS_MAX, "an integer"), default=None,
                   help="processes for verification and Monte Carlo, or the workers of --scheduler local "
                        "(default: cores, at most 4)")
    p.add_argument("--export", type=_path_text("--export"), metavar="PATH.json|PATH.toml|PATH.c|PATH.st",
                   help="write the tuned gains in a drive's terms (continuous and discrete forms, Kp/Tn, "
                        "biquads) as JSON or TOML, or the complete discrete controller as C (PATH.c and PATH.h) "
                        "or IEC 61131-3 Structured Text (PATH.st), chosen by the suffix")
    p.add_argument("--export-real", choices=("double", "float"), default="double",
                   help="floating-point type of a .c/.st export (default double)")
    p.add_argument("--export-template", metavar="NAME|PATH.toml",
                   help="with --export PATH.toml|.json: write the drive parameter set of this template (built-in: "
                        "generic, cia402, siemens-sinamics, beckhoff-ax8000; or a copy you edited)")
    p.add_argument("--motor", metavar="PATH.toml|KEY=VALUE,...",
                   help="motor data for current-based gains: a TOML file with [motor] or e.g. "
                        "torque_constant_n_m_per_a=0.9,rated_torque_n_m=3,rated_current_a=4 (or back_emf_v_per_krpm)")
    p.add_argument("--robust", action="store_true",
                   help="also tune one design over the scenario models of the plant's and scene's [uncertainty] "
                        "(default: when the scene has a [robust] section) and compare it with the nominal design")
    p.add_argument("--monte-carlo", metavar="N", type=_integer("--monte-carlo", 0, 1_000_000, "a sample count"),
                   default=None, help="verify the designs on N seeded samples of the uncertainty and report the "
                                      "yield against the scene's [spec] (default: the scene's [robust] monte_carlo; 0: off)")
    p.add_argument("--seed", metavar="S", type=_integer("--seed", 0, 2**31 - 1, "a seed"), default=None,
                   help="Monte-Carlo seed (default: the scene's, else 0); sample i depends only on (seed, i)")
    p.add_argument("--scheduler", metavar="local|tcp://HOST:PORT", type=_path_text("--scheduler"), default=None,
                   help="run the Monte Carlo on Dask: 'local' starts a LocalCluster, an address connects to a "
                        "running scheduler (needs pip install 'prsa-ctrl[dask]', or '.[dask]' in a checkout)")
    p.add_argument("--accept-unconverged", action="store_true",
                   help="exit 0 even when the best design is flagged (tuner not converged or a verified run "
                        "that reverses, never recovers, saturates or departs from the linear model); default: exit 3")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")
    return p


def build_plot_parser() -> argparse.ArgumentParser:
    """Argument parser of ``prsa-plot``."""
    p = _Parser(
        prog="prsa-plot", allow_abbrev=False,
        description="Bode, sensitivity, load-step and setpoint-step figures for a plant and given gains (no tuning), "
        "and the margins (Ms, Mt, GM, PM, crossover) they give. Unstable or marginal gains are plotted "
        "with a warning (time responses of an unstable loop are not drawn). "
        "Exit codes: 0 ok, 2 bad input, 3 numerical failure, 130 interrupted.",
    )
    p.add_argument("--kp", required=True, metavar="KP",
                   type=_number("--kp", KP_RANGE[0], KP_RANGE[1], "N m s/rad", "a proportional gain"),
                   help=f"proportional gain, N m s/rad, in [{KP_RANGE[0]:g}, {KP_RANGE[1]:g}] (required)")
    p.add_argument("--ki", default=0.0, metavar="KI", type=_number("--ki", *KI_RANGE, "N m/rad", "an integral gain"),
                   help=f"integral gain, N m/rad, in [0, {KI_RANGE[1]:g}] (default 0: P or PD only)")
    p.add_argument("--kd", default=0.0, metavar="KD", type=_number("--kd", *KD_RANGE, "N m s^2/rad", "a derivative gain"),
                   help=f"derivative gain, N m s^2/rad, in [0, {KD_RANGE[1]:g}] (default 0), filtered with "
                        "tf = 4 sample times")
    _common_flags(p)
    p.add_argument("--plots", "--out", dest="out", default="prsa-plots", type=_path_text("--plots"), metavar="DIR",
                   help="folder for the PNG and SVG files (default: ./prsa-plots, created if missing; "
                        "not created when the run fails)")
    return p


_VALUE_FLAGS = {"--load-step", "--setpoint-rpm", "--step-time", "--duration", "--ms-max", "--mt-max", "--kp",
                "--ki", "--kd", "--workers"}


def _attach_values(argv: Sequence[str]) -> list[str]:
    """``--load-step -5:10`` would read ``-5:10`` as an option; glue values to their flag so
    that such a value reaches the validator and is reported by name."""
    out: list[str] = []
    it = iter(argv)
    for a in it:
        if a.startswith("--") and a.partition("=")[2] == "--":
            raise _UsageError(f"{a.partition('=')[0]} '--': expected a value")
        if a in _VALUE_FLAGS:
            nxt = next(it, None)
            if nxt == "--":  # argparse would drop it and hand the converter nothing
                raise _UsageError(f"{a} '--': expected a value")
            out.append(a if nxt is None else f"{a}={nxt}")
        else:
            out.append(a)
    return out


# --- run-time guards: Ctrl-C, solver chatter, warnings ------------------------------------------

class _Run:
    """State of one command invocation: the program name, the interrupt flag, the watchdog,
    the original stderr descriptor and the directories created so far."""

    def __init__(self, prog: str) -> None:
        self.prog = prog
        self.interrupted = False
        self.reported = False
        self.lock = threading.Lock()
        self.timer: threading.Timer | None = None
        self.err_fd = 2
        self.created: list[Path] = []
        self.pid = os.getpid()
        self.argv: list[str] = []
        #: True while the outputs are renamed into place: Ctrl-C is remembered, not raised, so
        #: that the outputs end all old or all new (:func:`_commit`).
        self.defer = False
        #: Output files in place (the interrupt line names them).
        self.written: list[str] = []
        self.cause = "Ctrl-C"  # or "SIGTERM"
        self.exit_code = EXIT_INTERRUPTED  # EXIT_TERMINATED after SIGTERM

    def say(self, line: str) -> bool:
        """Print the final one-line message once (main thread or watchdog, whichever first)."""
        with self.lock:
            if self.reported:
                return False
            self.reported = True
        data = (line + "\n").encode("utf-8", "replace")
        try:
            sys.stderr.flush()
            sys.stderr.fileno()
            real = True
        except Exception:  # noqa: BLE001 - not a real file (pytest capture, StringIO)
            real = False
        if real:
            os.write(self.err_fd, data)  # the terminal's stderr even while solver output is captured
        else:
            print(line, file=sys.stderr)
        return True

    def interrupt_line(self) -> str:
        if self.written:
            return (f"{self.prog}: interrupted ({self.cause}) after the outputs were written complete: "
                    f"{', '.join(self.written)}")
        return f"{self.prog}: interrupted ({self.cause}); no output written"

    def force_exit(self) -> None:  # watchdog thread: a solver kept control after Ctrl-C
        from ..io.output import cleanup_temporaries, remove_created

        cleanup_temporaries()
        remove_created(self.created)
        try:
            import multiprocessing

            for child in multiprocessing.active_children():
                child.kill()
        except Exception:  # noqa: BLE001 - best effort
            pass
        self.say(self.interrupt_line())
        os._exit(self.exit_code)

    def on_sigterm(self, signum, frame) -> None:
        """SIGTERM ends the command like Ctrl-C (its workers stopped), with exit 143."""
        if os.getpid() != self.pid:  # a forked worker (stopped by the parent): end now
            os._exit(EXIT_TERMINATED)
        if not self.interrupted:
            self.cause, self.exit_code = "SIGTERM", EXIT_TERMINATED
        self.on_sigint(signum, frame)

    def on_sigint(self, signum, frame) -> None:
        if os.getpid() != self.pid:  # a forked worker: the parent reports
            os._exit(EXIT_INTERRUPTED)
        self.interrupted = True
        if self.defer:  # outputs being renamed into place: finish them, then stop (_commit)
            return
        if self.timer is None:
            self.timer = threading.Timer(INTERRUPT_GRACE_S, self.force_exit)
            self.timer.daemon = True
            self.timer.start()
        raise KeyboardInterrupt

    def check(self) -> None:
        """Raise KeyboardInterrupt if Ctrl-C came while a solver swallowed it."""
        if self.interrupted:
            raise KeyboardInterrupt


@contextlib.contextmanager
def _guard(run: _Run, process: bool = False) -> Iterator[None]:
    """Install the Ctrl-C and SIGTERM handlers for the duration of a command (main thread only).
    For the process itself (``process``), SIGINT is blocked from the end of the command to the
    exit: :func:`_invoke` turns a pending one into exit 130 with its line (never a death by
    SIGINT or a traceback after the command finished)."""
    old = old_term = None
    if threading.current_thread() is threading.main_thread():
        old = signal.signal(signal.SIGINT, run.on_sigint)
        old_term = signal.signal(signal.SIGTERM, run.on_sigterm)
    try:
        yield
    finally:
        if run.timer is not None:
            run.timer.cancel()
        if process and old is not None:
            signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        if old is not None:
            # After an interrupt a second delivery may still be pending (a solver that caught
            # the first re-raises it): ignore it, the command is ending with exit 130 anyway.
            signal.signal(signal.SIGINT, signal.SIG_IGN if run.interrupted else old)
            signal.signal(signal.SIGTERM, old_term)  # never left ignored: children would inherit SIG_IGN


@contextlib.contextmanager
def _native_output(run: _Run, lines: list[str]) -> Iterator[None]:
    """Collect what the solvers print -- C code (IPOPT, SUNDIALS) on descriptors 1 and 2, and
    CasADi through Python's ``sys.stdout``/``sys.stderr`` -- in a temporary file; the lines
    are returned in ``lines`` (shown with ``--verbose``, otherwise counted in one note). The
    command's own final line goes to the saved terminal descriptor (:meth:`_Run.say`)."""
    try:
        sys.stdout.flush()
        sys.stderr.flush()
        saved = {fd: os.dup(fd) for fd in (1, 2)}
    except (OSError, ValueError, AttributeError):
        yield
        return
    sink = tempfile.TemporaryFile()
    text_sink = open(os.dup(sink.fileno()), "w", buffering=1, encoding="utf-8", errors="replace")
    old_streams = sys.stdout, sys.stderr
    sys.stdout = sys.stderr = text_sink
    for fd in (1, 2):
        os.dup2(sink.fileno(), fd)
    run.err_fd = saved[2]
    try:
        yield
    finally:
        with contextlib.suppress(Exception):
            text_sink.flush()
        for fd in (1, 2):
            os.dup2(saved[fd], fd)
        run.err_fd = 2
        sys.stdout, sys.stderr = old_streams
        text_sink.close()
        for fd in saved.values():
            os.close(fd)
        sink.seek(0)
        text = sink.read().decode("utf-8", "replace")
        sink.close()
        lines.extend(l for l in text.splitlines() if l.strip())


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        if math.isinf(v):
            return "never"
        return f"{v:.4g}"
    return str(v)


def _fmt_margin(v: float) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "none"
    return "inf" if math.isinf(v) else f"{v:.4g}"


def _table(header: Sequence[str], rows: Sequence[Sequence]) -> str:
    cells = [list(header)] + [[_fmt(c) for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def _scene_header(sc, overrides: Sequence[str] = ()) -> str:
    loads = ", ".join(f"{f:g}" for f in sc.final_loads)
    bounds = f"Ms <= {sc.ms_max:g}" + (f", Mt <= {sc.mt_max:g}" if sc.mt_max is not None else "") + (
        f", Mks <= {sc.mks_max:g} N m s/rad" if sc.mks_max is not None else "")
    name = f"scene {sc.name}" + (f" with {' '.join(overrides)}" if overrides else "")
    if sc.is_profile:
        goal = {"load": "load rejection", "setpoint": "setpoint tracking",
                "mix": f"mix, setpoint share {sc.setpoint_share:g}"}[sc.goal]
        b = f", setpoint weight b = {sc.setpoint_weight:g}" if sc.setpoint_profile is not None else ""
        return (f"{name}: duty cycle ({sc.profile_source}) from {sc.setpoint_rpm:g} rpm, {sc.initial_load:g} N, "
                f"record to {sc.duration:g} s; {sc.objective.upper()} over the record ({goal}{b}), "
                f"{sc.controller.upper()}, {bounds}")
    return (f"{name}: {sc.setpoint_rpm:g} rpm, {sc.initial_load:g} N -> {loads} N at {sc.step_time:g} s, "
            f"record to {sc.duration:g} s; {sc.objective.upper()}, {sc.controller.upper()}, {bounds}")


def _pct_text(diff: float) -> str:
    """A signed percentage to 0.1 %; a difference that rounds to zero is "0.0 %", never "-0.0 %".

    >>> _pct_text(-0.04), _pct_text(0.04), _pct_text(-1.25)
    ('0.0 %', '0.0 %', '-1.2 %')
    """
    text = f"{diff:+.1f}"
    return ("0.0" if float(text) == 0.0 else text) + " %"


def _diff_text(p, v, res: float = 0.0) -> str:
    """Difference of the prediction ``p`` from the verified value ``v``: the percentage
    ``(p - v) / |v|`` (:func:`prsa_ctrl.sim.metrics.relative_difference`, the one definition the
    warnings use too) where both values reach the metric's resolution ``res``; below it the
    absolute difference ``p - v`` marked "abs." (a percentage of a value at numerical zero
    means nothing); "-" where undefined.

    >>> _diff_text(1.776e-15, 3.829e-06, res=0.0365), _diff_text(3.67, 3.651, res=0.0365)
    ('-3.83e-06 abs.', '+0.5 %')
    """
    from ..sim.metrics import relative_difference

    finite = all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in (p, v))
    if not finite:
        return "-"
    d = relative_difference(p, v)
    if d is not None and abs(p) >= res and abs(v) >= res:
        return _pct_text(100 * d)
    return f"{p - v:+.3g} abs."


def _resolutions(rep, drop: float, window: float) -> Callable[[str], float]:
    """Metric name -> its resolution in the report's verified runs (:func:`prsa_ctrl.sim.metrics.metric_resolution`)."""
    from ..sim.metrics import metric_resolution

    sc = rep.scene
    return lambda name: metric_resolution(name, accuracy=sc.accuracy, drop_rad_s=drop,
                                          sample_time_s=rep.plant.sample_time_s, window_s=window,
                                          torque_limit_n_m=rep.plant.torque_limit)


_DIFF_NOTE = ("difference = (predicted - verified) / |verified|; where either value is below the metric's resolution "
              "(the verification accuracy in its unit: {speed:.3g} rad/s for speeds, one sample for times) the absolute "
              "difference predicted - verified (abs.)")


def _beaten_text(c: dict, obj: str) -> str:
    """The verdict of a baseline comparison with its reason when the baseline is not beaten."""
    if c["beaten"]:
        return "yes"
    if c.get("tuned_flags"):
        return "no: tuned design flagged"
    if c["tuned_ms"] > c["baseline_ms"] * (1 + 1e-9):
        return "no: tuned Ms higher"
    if not c["tuned_objective_verified"] < c["baseline_objective_verified"]:
        return f"no: {obj} not lower"
    return "no"


def _profile_tables(rep) -> list[str]:
    """Predicted against verified metrics of each duty-cycle record, then its load steps."""
    sc, b = rep.scene, rep.best
    out = []
    fields = [("IAE over the record (rad)", "iae"), ("ITAE (rad s)", "itae"), ("ISE (rad^2/s)", "ise"),
              ("peak error (rad/s)", "peak_deviation_rad_s"), ("peak error time (s)", "peak_time_s"),
              ("RMS error (rad/s)", "rms_error_rad_s"), ("final error (rad/s)", "final_error_rad_s"),
              ("peak torque (N m)", "peak_torque_n_m"), ("time at torque limit", "saturated_fraction")]
    for k, case in enumerate(sc.cases):
        pm, vm = b.predicted[k], b.verified[k]
        res = _resolutions(rep, vm.peak_deviation_rad_s, sc.duration)
        rows = [[lab, getattr(pm, attr), getattr(vm, attr),
                 "-" if attr in ("final_error_rad_s", "saturated_fraction")
                 else _diff_text(getattr(pm, attr), getattr(vm, attr), res(attr))]
                for lab, attr in fields]
        out.append(f"Duty cycle, {case} (error = setpoint - speed over the whole record)")
        out.append(_table(["metric", "predicted (linear)", "verified (nonlinear)", "difference"], rows))
        out.append(_DIFF_NOTE.format(speed=res("peak_deviation_rad_s")))
        if vm.steps:
            rows = []
            for (t_s, ms_v), ms_p in zip(zip(vm.step_times_s, vm.steps), pm.steps):
                rows.append([f"{t_s:g} s", "up" if ms_v.direction > 0 else "down", ms_p.peak_drop_rad_s,
                             ms_v.peak_drop_rad_s, ms_v.recovery_time_s, ms_v.iae])
            out.append("Load steps in the profile (verified recovery within 5 % of the step's peak, until the next change)")
            out.append(_table(["step at", "load", "predicted peak (rad/s)", "verified peak (rad/s)",
                               "recovery (s)", "IAE to next change (rad)"], rows))
        out.append("")
    return out


def format_report(rep, overrides: Sequence[str] = ()) -> str:
    """Readable text report of an :class:`~prsa_ctrl.studies.autotune.ActuatorTuning`; ``overrides``
    are the command-line flags that changed the scene (named in the header)."""
    sc, b = rep.scene, rep.best
    obj = sc.objective.upper()
    label = b.name[len("tuned "):] if b.name.startswith("tuned ") else f"({b.name})"
    out = [
        f"prsa-tune: plant {rep.plant.name}, {_scene_header(sc, overrides)}",
        f"verification: {rep.fidelity_reason}; {'sampled controller (ZOH, quantised encoder)' if sc.discrete else 'continuous controller'}",
        "",
        f"Tuned {sc.controller.upper()} {label}: kp = {b.pid.kp:.5g} N m s/rad, ki = {b.pid.ki:.5g} N m/rad"
        + (f", kd = {b.pid.kd:.5g} N m s^2/rad (tf {b.pid.tf:g} s)" if b.pid.kd else "")
        + (f", load feed-forward gain kff = {b.pid.kff:.3g}" if sc.feedforward else ""),
        f"Margins: Ms {b.margins.ms:.3f}, Mt {b.margins.mt:.3f}, GM {_fmt(b.margins.gm_db)} dB, "
        f"PM {_fmt(b.margins.pm_deg)} deg, crossover {_fmt(b.margins.wc_rad_s)} rad/s",
        "Drive terms: "
        + (f"sample time {rep.plant.sample_time_s * 1e3:.4g} ms, " if sc.discrete else "continuous controller, ")
        + (f"integral time Ti = kp/ki = {b.pid.kp / b.pid.ki * 1e3:.4g} ms, " if b.pid.ki > 0 else "no integral action, ")
        + f"kp = {b.pid.kp * 2 * math.pi / 60:.4g} N m/rpm",
        f"Status: {rep.status}",
        "",
    ]
    fields = [
        ("peak drop (rad/s)", "peak_drop_rad_s"),
        ("peak time (s)", "peak_time_s"),
        ("recovery time (s)", "recovery_time_s"),
        ("IE (rad)", "ie"),
        ("IAE (rad)", "iae"),
        ("ITAE (rad s)", "itae"),
        ("ISE (rad^2/s)", "ise"),
        ("steady-state error (rad/s)", "steady_state_error_rad_s"),
        ("overshoot (rad/s)", "overshoot_rad_s"),
        ("peak torque (N m)", "peak_torque_n_m"),
        ("torque saturated", "saturated"),
    ]
    if sc.is_profile:
        out.extend(_profile_tables(rep))
    for k, f1 in enumerate(sc.final_loads):
        pm, vm = b.predicted[k], b.verified[k]
        res = _resolutions(rep, vm.peak_drop_rad_s, sc.duration - sc.step_time)
        rows = []
        for lab, attr in fields:
            p, v = getattr(pm, attr), getattr(vm, attr)
            rows.append([lab, p, v, _diff_text(p, v, res(attr))])
        out.append(f"Load step {sc.initial_load:g} -> {f1:g} N")
        out.append(_table(["metric", "predicted (linear)", "verified (nonlinear)", "difference"], rows))
        out.append(_DIFF_NOTE.format(speed=res("peak_drop_rad_s")))
        out.append("")
    rows = []
    comp = {c["baseline"]: c for c in rep.comparisons}
    for d in rep.baselines:
        c = comp[d.name]
        rows.append([d.name, d.pid.kp, d.pid.ki, d.margins.ms, d.objective_verified,
                     c["tuned_objective_verified"], c["tuned_ms"], _beaten_text(c, obj)])
    out.append(f"Baselines ({obj}, verified; tuned at equal or better Ms)")
    out.append(_table(["baseline", "kp", "ki", "Ms", obj, f"tuned {obj}", "tuned Ms", "beaten"], rows))
    out.append("")
    t = rep.timing_s
    out.append(
        f"Run time: linearise {t['linearize']:.2f} s, tune {t['tune']:.2f} s, verify {t['verify']:.2f} s, "
        f"total {t['total']:.2f} s" + (f" (process {t['process']:.2f} s)" if "process" in t else "")
    )
    if b.estimation:
        e = b.estimation[0]
        out.append(
            f"Speed estimation (verified run): Kalman filter RMS error {e['kf_speed_rms_rad_s']:.4g} rad/s, "
            f"finite difference {e['fd_speed_rms_rad_s']:.4g} rad/s"
        )
    for w in rep.warnings:
        out.append(f"warning: {w}")
    return "\n".join(out)


def write_json_atomic(path: str | os.PathLike, data: dict, inputs: Sequence[str | os.PathLike] = (),
                      transaction=None) -> Path:
    """Write JSON through :func:`prsa_ctrl.io.output.write_text` (atomic, never onto ``inputs``);
    with a :class:`prsa_ctrl.io.output.Transaction`, staged in it (renamed at its commit)."""
    from ..io.output import write_text

    text = json.dumps(data, indent=2, allow_nan=False, default=float) + "\n"
    if transaction is not None:
        return transaction.stage(path, lambda tmp: tmp.write_text(text, encoding="utf-8"), "--json")
    return write_text(path, text, inputs, flag="--json")


def _commit(run: _Run, outputs) -> None:
    """Rename every staged output into place with Ctrl-C deferred (all old or all new), then
    honour a Ctrl-C that came meanwhile (exit 130 naming the files written)."""
    run.check()
    run.defer = True
    try:
        outputs.commit()
        run.written = list(outputs.written)
    finally:
        run.defer = False
    run.check()


# --- error translation ---------------------------------------------------------------------------

#: Messages of numpy/scipy/CasADi that mean "the numbers left the representable range".
_INTERNAL = ("must not contain infs or nans", "failed to find a finite solution", "maximum allowed dimension",
             "array is too big", "unable to allocate", "singular matrix", "math domain error", "overflow",
             "division by zero", "invalid value encountered", "must be finite")


def _describe_failure(exc: BaseException, what: str) -> tuple[int, str]:
    """Map an exception of the expensive phase to (exit code, one line without internal names)."""
    if isinstance(exc, (MemoryError,)) or "maximum allowed dimension" in str(exc).lower() or \
            "unable to allocate" in str(exc).lower():
        return EXIT_BAD_INPUT, f"error: {what} needs more memory than this machine has; shorten --duration or use fewer load levels"
    if isinstance(exc, (PlantFileError, SceneError, OutputError)):
        return EXIT_BAD_INPUT, f"error: {_one_line(exc)}"
    if isinstance(exc, SimulationError):
        return EXIT_NUMERICAL, f"numerical failure: {_one_line(exc)}"
    msg = str(exc).lower()
    if isinstance(exc, (ArithmeticError, FloatingPointError)) or any(k in msg for k in _INTERNAL) \
            or re.search(r"\b(nan|inf)\b", msg):
        return EXIT_NUMERICAL, (f"numerical failure: {what} produced non-finite numbers "
                                f"({type(exc).__name__}); check the plant values and the operating point")
    if isinstance(exc, ValueError):  # our own messages (e.g. no gains meet the robustness bound)
        return EXIT_NUMERICAL, f"numerical failure: {_one_line(exc)}"
    return EXIT_NUMERICAL, f"numerical failure: {what} failed ({type(exc).__name__}); rerun with --verbose for details"


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


def _status_says_interrupted(obj: Any, depth: int = 0) -> bool:
    """True if a solver status anywhere in a result says the user stopped it (IPOPT's
    ``User_Requested_Stop``: CasADi turns Ctrl-C into that status instead of an exception)."""
    if depth > 6:
        return False
    if isinstance(obj, str):
        return "user_requested_stop" in obj.lower() or "interrupted" in obj.lower()
    if isinstance(obj, dict):
        return any(_status_says_interrupted(v, depth + 1) for k, v in obj.items()
                   if isinstance(v, (dict, list, tuple)) or "status" in str(k).lower())
    if isinstance(obj, (list, tuple)):
        return any(_status_says_interrupted(v, depth + 1) for v in obj)
    return False


# --- shared set-up -------------------------------------------------------------------------------

def _input_files(args, scene=None) -> list[str]:
    """Every file the run reads: the plant and scene files given as paths and the scene's CSV
    traces (the built-in files are protected by :func:`prsa_ctrl.io.output.package_roots`)."""
    files = []
    for v in (getattr(args, "plant", None), getattr(args, "scene", None)):
        if v is not None and os.path.exists(v):
            files.append(v)
    files.extend(getattr(scene, "input_files", ()))
    return files


def _load_and_override(args, run: _Run, plot: bool = False):
    """Plant and scene with the command-line overrides, checked against each other."""
    from ..plant.plantfile import load_plant
    from ..studies.scene import check_against_plant, load_scene

    plant = load_plant(args.plant)
    scene = load_scene(args.scene)
    changes: dict[str, Any] = {}
    typed: dict[str, str] = {}
    overrides: list[str] = []
    raw = {a.split("=", 1)[0]: a.split("=", 1)[1] for a in run.argv if a.startswith("--") and "=" in a}
    if scene.is_profile:
        for flag in ("--robust", "--monte-carlo", "--scheduler"):
            v = getattr(args, flag[2:].replace("-", "_"), None)
            if v:
                raise _UsageError(f"{flag}: scene {scene.name} is a duty cycle ({scene.profile_source}); expected a "
                                  "load-step scene (the robust and Monte-Carlo studies run load steps)")
        estimator = getattr(args, "estimator", None)
        if estimator not in (None, "none"):
            raise _UsageError(f"--estimator {raw.get('--estimator', estimator)}: scene {scene.name} is a duty cycle "
                              f"({scene.profile_source}); expected --estimator none (the Kalman-filter loop is tuned and "
                              "verified on load steps only, not on a duty-cycle record)")
        for flag, v in (("--load-step", args.load_step), ("--step-time", getattr(args, "step_time", None)),
                        ("--setpoint-rpm", args.setpoint_rpm if scene.setpoint_profile is not None else None)):
            if v is not None:
                raise _UsageError(f"{flag} {raw.get(flag, v)!r}: scene {scene.name} is a duty cycle ({scene.profile_source}); "
                                  f"expected its profile to set the {'load' if flag != '--setpoint-rpm' else 'setpoint'} "
                                  "and events (edit the scene file to change them)")
    if args.load_step is not None:
        initial, finals = args.load_step
        if plot:
            finals = finals[:1]
        changes["initial_load"], changes["final_loads"] = initial, finals
        typed["initial_load"] = typed["final_loads"] = f"--load-step {raw.get('--load-step', '')!r}"
        overrides.append(f"--load-step {raw.get('--load-step', '')}")
    if args.setpoint_rpm is not None:
        changes["setpoint_rad_s"] = args.setpoint_rpm * math.pi / 30.0
        typed["setpoint_rad_s"] = f"--setpoint-rpm {raw.get('--setpoint-rpm', args.setpoint_rpm)}"
        overrides.append(typed["setpoint_rad_s"])
    for arg, fieldname, flag in (("step_time", "step_time", "--step-time"), ("duration", "duration", "--duration"),
                                 ("ms_max", "ms_max", "--ms-max"), ("mt_max", "mt_max", "--mt-max"),
                                 ("mks_max", "mks_max", "--mks-max"),
                                 ("objective", "objective", "--objective"),
                                 ("controller", "controller", "--controller"), ("estimator", "estimator", "--estimator")):
        v = getattr(args, arg, None)
        if v is None:
            continue
        changes[fieldname] = v
        typed[fieldname] = f"{flag} {raw.get(flag, v)}"
        overrides.append(typed[fieldname])
    if getattr(args, "feedforward", False):
        changes["feedforward"] = True
        overrides.append("--feedforward")
    if changes:
        try:
            scene = scene.replace(origin="command line", **changes)
        except SceneError as exc:
            raise _UsageError(_cross_check_message(exc, typed, scene, changes)) from None
    check_against_plant(scene, plant, typed)
    return plant, scene, overrides


def _cross_check_message(exc: SceneError, typed: dict[str, str], scene, changes: dict) -> str:
    """A scene field rejected after overrides: say it with the flags as typed."""
    msg = str(exc)
    if msg.startswith("command line: duration") and ("duration" in typed or "step_time" in typed) and not scene.is_profile:
        who = " and ".join(typed[k] for k in ("step_time", "duration") if k in typed)
        st = changes.get("step_time", scene.step_time)
        du = changes.get("duration", scene.duration)
        return f"{who}: the record ends at {du:g} s, before the load step at {st:g} s has any response; expected a duration beyond the step time"
    return msg.replace("command line: ", "command line (with " + ", ".join(typed.values()) + "): ") if typed else msg


def _show_notes(run: _Run, notes: list[warnings.WarningMessage], native: list[str], verbose: bool, quiet: bool) -> None:
    """Notes after the result: Python warnings (deduplicated; geometry notes of built-in plants
    only with --verbose) and one line for solver diagnostics."""
    if quiet:
        return
    seen = set()
    for w in notes:
        text = str(w.message)
        if text in seen:
            continue
        seen.add(text)
        if issubclass(w.category, GeometryWarning) and "(built-in)" in text and not verbose:
            continue
        print(f"{run.prog}: note: {text}", file=sys.stderr)
    if native:
        if verbose:
            for line in native:
                print(f"{run.prog}: solver: {line}", file=sys.stderr)
        else:
            print(f"{run.prog}: note: the numerical solvers printed {len(native)} diagnostic lines "
                  "(shown with --verbose)", file=sys.stderr)


def _progress(run: _Run, verbose: bool, text: str) -> None:
    if verbose:
        print(f"{run.prog}: {text}", file=sys.stderr, flush=True)


def _invoke(prog: str, argv: Sequence[str] | None, body: Callable[[_Run, list[str]], int]) -> int:
    """Common frame of both commands: Ctrl-C guard, one-line errors, exit codes."""
    run = _Run(prog)
    code = _invoke_inner(run, argv, body)
    if argv is None and code not in (EXIT_INTERRUPTED, EXIT_TERMINATED) and signal.SIGINT in _pending_signals():
        # Ctrl-C after the command finished (blocked by _guard): exit 130 with its line.
        run.reported = False
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        run.say(run.interrupt_line())
        code = EXIT_INTERRUPTED
    if code in (EXIT_INTERRUPTED, EXIT_TERMINATED) and argv is None:
        # The process itself (console script, python -m): end now with 130. A second SIGINT
        # delivery left pending by a solver, or an atexit hook of a solver library, would
        # otherwise turn the exit into a death by SIGINT.
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        with contextlib.suppress(Exception):  # no worker may outlive us (they ignore SIGINT)
            import multiprocessing

            for child in multiprocessing.active_children():
                child.kill()
        os._exit(code)
    return code


def _pending_signals() -> set:
    try:
        return set(signal.sigpending())
    except (AttributeError, OSError):  # pragma: no cover - not POSIX
        return set()


def _invoke_inner(run: _Run, argv: Sequence[str] | None, body: Callable[[_Run, list[str]], int]) -> int:
    prog = run.prog
    with _guard(run, process=argv is None):
        try:
            run.argv = _attach_values(list(sys.argv[1:] if argv is None else argv))
            return body(run, run.argv)
        except KeyboardInterrupt:
            from ..io.output import cleanup_temporaries, remove_created

            cleanup_temporaries()
            remove_created(run.created)
            run.say(run.interrupt_line())
            return run.exit_code
        except (_UsageError, argparse.ArgumentTypeError, PlantFileError, SceneError, OutputError) as exc:
            from ..io.output import remove_created

            remove_created(run.created)
            if run.interrupted:
                run.say(run.interrupt_line())
                return run.exit_code
            run.say(f"{prog}: error: {_one_line(exc)}")
            return EXIT_BAD_INPUT
        except Exception as exc:  # noqa: BLE001 - a bug must not print a traceback either
            from ..io.output import remove_created

            remove_created(run.created)
            if run.interrupted:
                run.say(run.interrupt_line())
                return run.exit_code
            code, line = _describe_failure(exc, f"{prog} {' '.join(run.argv)}".strip())
            run.say(f"{prog}: {line}")
            return code


# --- prsa-tune -----------------------------------------------------------------------------------

def main(argv: Sequence[str] | None = None) -> int:
    """``prsa-tune``; returns the exit code (0, 2, 3 or 130, see the module docstring)."""
    return _invoke("prsa-tune", argv, _tune_body)


def _tune_body(run: _Run, argv: list[str]) -> int:
    from ..io.output import check_directory, check_distinct, check_writable

    if "-h" in argv or "--help" in argv:
        build_parser().print_help()
        return EXIT_OK
    args = build_parser().parse_args(argv)
    if args.show_plant is not None:  # issue 21: the plant's values with their sources
        from ..plant.plantfile import show_plant

        print(show_plant(args.show_plant))
        return EXIT_OK
    from ..tuning.cascade import is_move_scene  # issue 12: a scene with a [move] section tunes the cascade

    if is_move_scene(args.scene):
        from ..tuning.cascade import main_move

        return main_move(run, args)
    notes: list[warnings.WarningMessage] = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        plant, scene, overrides = _load_and_override(args, run)
        inputs = _input_files(args, scene)
        if args.json is not None:
            check_writable(args.json, inputs, "--json")
        if args.scheduler is not None:
            from importlib.util import find_spec

            from ..studies.montecarlo import scene_options

            n_mc = args.monte_carlo if args.monte_carlo is not None else scene_options(scene)["samples"]
            if not n_mc:
                raise _UsageError(f"--scheduler {args.scheduler!r}: expected --monte-carlo N (or a scene with "
                                  "[robust] monte_carlo) to run on it")
            address = _scheduler_address(args.scheduler)
            if find_spec("distributed") is None:
                raise _UsageError(f"--scheduler {args.scheduler!r} needs Dask: pip install 'prsa-ctrl[dask]', or '.[dask]' in a checkout")
            if address is not None:
                _probe_scheduler(args.scheduler, *address)
        if args.export is not None:
            if os.path.splitext(args.export)[1].lower() not in (".json", ".toml", ".c", ".st"):
                raise _UsageError(f"--export {args.export!r}: expected a path ending in .json, .toml, .c or .st")
            check_writable(args.export, inputs, "--export")
            if os.path.splitext(args.export)[1].lower() == ".c":  # issue 24: the header beside the source
                from ..io.codegen import check_code_export

                check_code_export(args.export, inputs, "--export")
            if scene.feedforward:
                raise _UsageError(f"--export {args.export!r} with --feedforward: the drive export does not describe the "
                                  "Kalman filter's load-torque feed-forward (kff > 0); expected --export without "
                                  "--feedforward (or no --export)")
        if args.motor is not None or args.export_template is not None:  # issue 24: drive units, parameter sets
            from ..drive.params import check_cli_options

            try:
                check_cli_options(args)
            except ValueError as exc:
                raise _UsageError(str(exc)) from None
        if args.plots is not None:
            check_directory(args.plots, "--plots")
        check_distinct({"--json": args.json, "--export": args.export, "--plots": args.plots})
        notes.extend(caught)
    run.check()
    native: list[str] = []
    what = (f"tuning {plant.name} on the {scene.name} duty cycle" if scene.is_profile else
            f"tuning {plant.name} at {scene.setpoint_rpm:g} rpm, {scene.initial_load:g} N -> "
            f"{', '.join(f'{f:g}' for f in scene.final_loads)} N")
    _progress(run, args.verbose, f"{what}: linearise, tune, verify ...")
    try:
        with warnings.catch_warnings(record=True) as caught, _native_output(run, native):
            warnings.simplefilter("always")
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", GeometryWarning)
                from ..studies.autotune import tune_actuator

                rep = tune_actuator(plant, scene, workers=args.workers)
                run.check()
                if _status_says_interrupted(rep.as_dict()):
                    raise KeyboardInterrupt
                robust_rep, mc = _robust_and_monte_carlo(run, args, plant, rep)
            notes.extend(caught)
        run.check()
    except KeyboardInterrupt:
        raise
    except Exception as exc:  # noqa: BLE001 - translated into one line at this boundary
        run.check()
        code, line = _describe_failure(exc, what)
        if args.verbose:  # the internal detail, for a bug report; never a traceback
            print(f"{run.prog}: detail: {type(exc).__name__}: {_one_line(exc)[:500]}", file=sys.stderr)
        run.say(f"{run.prog}: {line}")
        return code
    rep.timing_s["process"] = time.perf_counter() - _T_START
    _progress(run, args.verbose, "writing outputs")
    if args.export is not None:  # before any output is written: all or nothing
        export_pid, export_design = _export_choice(rep, robust_rep)
        if export_pid is None:
            run.say(f"{run.prog}: --export {args.export}: {export_design['why']}; nothing written")
            return EXIT_NUMERICAL if robust_rep is not None else EXIT_BAD_INPUT
    from ..io.output import Transaction

    outputs = Transaction(inputs)  # all outputs or none (issue 20, hostile 4 and 17)
    try:
        if args.plots is not None:
            rep.plot_files = _publish_report_plots(run, rep, args.plots, inputs, outputs)
        if args.json is not None:
            data = rep.as_dict()
            data["timing_s"] = dict(rep.timing_s)
            _add_setpoint_weight(data, rep.scene)
            if robust_rep is not None:
                data["robust"] = robust_rep.as_dict()
                data["recommended"] = data["robust"]["recommended"]
            if mc is not None:
                data["monte_carlo"] = mc.as_dict()
            run.check()
            write_json_atomic(args.json, data, inputs, transaction=outputs)
        if args.export is not None:
            from ..io.export import dumps, export_controller

            fmt = os.path.splitext(args.export)[1].lower().lstrip(".")
            if fmt in ("c", "st"):  # issue 24: the discrete controller as code (prsa_ctrl.io.codegen)
                from ..io.codegen import stage_code_export

                stage_code_export(outputs, args.export, export_pid, rep.plant, real=args.export_real,
                                  setpoint_weight=_setpoint_weight(rep.scene))
            else:
                exported = export_controller(export_pid, rep.plant, fmt=fmt, setpoint_weight=_setpoint_weight(rep.scene),
                                             design=export_design)
                if args.motor is not None or args.export_template is not None:
                    from ..drive.params import cli_export_data

                    exported = cli_export_data(args, exported, export_pid, rep.plant)
                text = dumps(exported, fmt)
                outputs.stage(args.export, lambda tmp: tmp.write_text(text, encoding="utf-8"), "--export")
        _commit(run, outputs)
    except OutputError:
        raise
    except KeyboardInterrupt:
        raise
    except Exception as exc:  # noqa: BLE001
        code, line = _describe_failure(exc, "writing the outputs")
        run.say(f"{run.prog}: {line}")
        return code
    finally:
        outputs.abort()  # takes back what was not committed (nothing after the commit)
    if not args.quiet:
        print(format_report(rep, overrides))
        if robust_rep is not None:
            print(_format_robust(robust_rep))
        if mc is not None:
            from ..studies.montecarlo import format_report as format_mc

            print(format_mc(mc))
        if args.json is not None:
            print(f"JSON report: {args.json}")
        if args.plots is not None:
            print(f"plots: {', '.join(str(p) for p in rep.plot_files)}")
        if args.export is not None:
            print(f"drive export: {args.export} holds the design {export_design['name']!r}, "
                  f"{export_design['chosen_by']}")
    _show_notes(run, notes, native, args.verbose, args.quiet)
    if rep.status != "ok" and not args.accept_unconverged:
        run.say(f"{run.prog}: the best design is flagged ({rep.status}); its numbers are reported above but "
                "are not a trustworthy design (use --accept-unconverged to exit 0)")
        return EXIT_NUMERICAL
    return EXIT_OK


#: Seconds the up-front connection to a ``--scheduler`` address may take.
SCHEDULER_CONNECT_TIMEOUT_S = 5.0
_SCHEDULER_RE = re.compile(r"tcp://(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9._-]+)(?::(\d+))?")


def _scheduler_address(text: str) -> tuple[str, int] | None:
    """``--scheduler`` checked before any work: ``None`` for ``local``, else ``(host, port)``
    of ``tcp://HOST:PORT`` (port 1..65535). TLS (``tls://``) needs a security configuration
    (certificates) the command does not take; any other form is refused.

    Raises
    ------
    _UsageError
        One line naming ``--scheduler`` and the text as typed.
    """
    if text == "local":
        return None
    expected = "expected 'local' or tcp://HOST:PORT, e.g. tcp://127.0.0.1:8786"
    if text.startswith("tls://"):
        raise _UsageError(f"--scheduler {text!r}: a TLS scheduler needs certificates (a Dask security "
                          f"configuration) that prsa-tune does not take; {expected}")
    m = _SCHEDULER_RE.fullmatch(text)
    if m is None:
        raise _UsageError(f"--scheduler {text!r}: {expected}")
    if m.group(2) is None:
        raise _UsageError(f"--scheduler {text!r}: no port; {expected}")
    port = int(m.group(2))
    if not 1 <= port <= 65535:
        raise _UsageError(f"--scheduler {text!r}: port {m.group(2)} out of range; expected a TCP port 1..65535")
    return m.group(1).strip("[]"), port


def _probe_scheduler(text: str, host: str, port: int) -> None:
    """Open (and close) a TCP connection to the scheduler, bounded by
    ``SCHEDULER_CONNECT_TIMEOUT_S``, so that an unreachable address stops the run before the
    tuning, not after it."""
    import socket

    try:
        with socket.create_connection((host, port), timeout=SCHEDULER_CONNECT_TIMEOUT_S):
            pass
    except OSError as exc:
        why = "no answer" if isinstance(exc, socket.timeout) else (exc.strerror or type(exc).__name__)
        raise _UsageError(f"--scheduler {text!r}: cannot connect to {host}:{port} within "
                          f"{SCHEDULER_CONNECT_TIMEOUT_S:g} s ({why}); expected the address of a running Dask "
                          "scheduler (dask scheduler --host HOST --port PORT), or 'local'") from None


def _setpoint_weight(scene) -> float:
    """The 2-DOF setpoint weight b the design runs with (1 unless a duty cycle's setpoint
    profile sets ``[tuning] setpoint_weight``)."""
    return float(getattr(scene, "setpoint_weight", 1.0)) if getattr(scene, "setpoint_profile", None) is not None else 1.0


def _add_setpoint_weight(data: dict, scene) -> None:
    """Put b into every ``gains`` block of the JSON report (the controller law is
    ``u = kp (b r - y) + I``; b = 1 for load-step scenes)."""
    b = _setpoint_weight(scene)

    def walk(obj, depth: int = 0) -> None:
        if depth > 6:
            return
        if isinstance(obj, dict):
            for k, v in obj.items():
                if k == "gains" and isinstance(v, dict) and "kp" in v:
                    v.setdefault("b", b)
                else:
                    walk(v, depth + 1)
        elif isinstance(obj, list):
            for v in obj:
                walk(v, depth + 1)

    walk(data)
    units = data.get("units")
    if isinstance(units, dict):
        units.setdefault("b", "dimensionless (2-DOF setpoint weight: u = kp (b r - y) + I)")


def _robust_and_monte_carlo(run: _Run, args, plant, rep):
    """The robust design (``--robust`` or a scene ``[robust]`` section) and the Monte-Carlo
    verification (``--monte-carlo N`` or the scene's setting) of the report's designs."""
    from ..studies.montecarlo import scene_options

    scene = rep.scene
    opts = scene_options(scene)
    has_robust = bool((getattr(scene, "robust", None) or {}).get("robust"))
    robust_rep = None
    if args.robust or has_robust:
        from ..tuning.robust import tune_robust_actuator

        _progress(run, args.verbose, "robust tuning over the scenario models ...")
        robust_rep = tune_robust_actuator(plant, scene)
        run.check()
    n = args.monte_carlo if args.monte_carlo is not None else opts["samples"]
    if not n:
        return robust_rep, None
    from ..studies.montecarlo import run_monte_carlo

    designs = {rep.best.name: rep.best.pid}
    if robust_rep is not None:
        designs = {"nominal design": robust_rep.nominal, "robust design": robust_rep.robust}
        _add_design(designs, rep.best.name, rep.best.pid)
    for b in rep.baselines:
        _add_design(designs, b.name, b.pid)
    seed = args.seed if args.seed is not None else opts["seed"]
    _progress(run, args.verbose, f"Monte Carlo: {n} samples of {len(designs)} designs ...")
    from ..studies.autotune import default_workers

    # Like the verification: in parallel on the machine's cores unless --workers says otherwise.
    mc = run_monte_carlo(plant, scene, designs, n, seed=seed, scheduler=args.scheduler,
                         workers=args.workers or default_workers(), quiet=args.quiet)
    if robust_rep is not None:
        robust_rep.recommend(mc)
    return robust_rep, mc


def _add_design(designs: dict, name: str, pid) -> None:
    """Add a design to verify unless one with the same gains is there already (one name per
    design: the robust study's nominal design is the tuned design when their gains agree)."""
    key = (pid.kp, pid.ki, pid.kd, pid.tf, pid.kff)
    if name in designs or any((p.kp, p.ki, p.kd, p.tf, p.kff) == key for p in designs.values()):
        return
    designs[name] = pid


def _export_choice(rep, robust_rep) -> tuple[Any, dict]:
    """The design ``--export`` writes and how it was chosen: the robust study's recommended
    design (:meth:`prsa_ctrl.tuning.robust.RobustTuning.recommend`) when there is one, else the
    tuned design; ``(None, {"why": ...})`` when there is none to export."""
    if robust_rep is not None:
        r = robust_rep.recommended or robust_rep.recommend()
        if r.get("design") is None:
            return None, {"why": f"no design recommended ({r['why']})"}
        d = {"name": f"{r['design']} design", "chosen_by": "recommended by the robust study", "why": r["why"],
             "basis": r["basis"]}
        if r.get("yield") is not None:
            d["yield"] = r["yield"]
        return robust_rep.design(r["design"]), d
    if rep.best.pid.kff != 0:
        return None, {"why": "the best design feeds the Kalman filter's load estimate forward (kff > 0), which the "
                             "drive export does not describe"}
    return rep.best.pid, {"name": rep.best.name, "chosen_by": "the tuned design (no robust study)"}


def _format_robust(rr) -> str:
    """Nominal against robust design on the same scenario models."""
    comp = rr.comparison
    obj = comp["objective"].upper()
    out = [f"Robust tuning over {len(rr.scenarios)} scenario models ({comp.get('aggregate', 'worst')} {obj}; "
           f"Ms bound {comp['ms_max']:g} on every model)"]
    rows = []
    for name, pid in (("nominal", rr.nominal), ("robust", rr.robust)):
        d = comp["designs"][name]
        bad = "unstable" if not d["all_stable"] else None
        rows.append([name, pid.kp, pid.ki, bad or d["max_ms"], d["ms_violations"], bad or d["worst_objective"],
                     bad or d["mean_objective"]])
    out.append(_table(["design", "kp", "ki", "max Ms", "models over the Ms bound", f"worst {obj}", f"mean {obj}"], rows))
    unstable = {name: sum(1 for p in comp["designs"][name]["per_scenario"] if not p["stable"])
                for name in ("nominal", "robust")}
    for name, k in unstable.items():
        if k:
            out.append(f"{name}: closed loop unstable on {k} of {len(rr.scenarios)} scenario models")
    r = rr.recommended or rr.recommend()
    out.append(f"recommended: {r['design'] + ' design' if r.get('design') else 'none'} ({r['why']})")
    return "\n".join(out) + "\n"


def _publish_report_plots(run: _Run, rep, directory: str, inputs: Sequence[str], outputs=None) -> list[Path]:
    """Render the standard plots into a private staging folder, then stage each in the run's
    output transaction for ``directory`` (created only now, and taken back if this fails)."""
    from ..plots.loop import write_standard_plots

    return _staged(run, lambda staging: write_standard_plots(rep, staging), directory, inputs, outputs)


def _staged(run: _Run, render: Callable[[Path], list[Path]], directory: str, inputs: Sequence[str],
            outputs=None) -> list[Path]:
    """``render`` writes files into a private staging folder; each is then staged in the
    :class:`prsa_ctrl.io.output.Transaction` ``outputs`` (one of its own, committed here, if
    ``None``) for ``directory`` (created only now)."""
    import shutil

    from ..io.output import Transaction

    own = outputs is None
    tr = Transaction(inputs) if own else outputs
    staging = tempfile.mkdtemp(prefix="prsa-plots.prsa-tmp-")
    try:
        files = render(Path(staging))
        run.check()
        tr.make_directory(directory, "--plots")
        out = []
        for f in files:
            src = str(f)
            out.append(Path(directory) / Path(f).name)
            tr.stage(out[-1], lambda tmp, src=src: shutil.copyfile(src, tmp), "--plots", listed=False)
        if own:
            _commit(run, tr)
        return out
    finally:
        if own:
            tr.abort()  # no-op after the commit
        shutil.rmtree(staging, ignore_errors=True)


# --- prsa-plot -----------------------------------------------------------------------------------

def _stability(lp, gains) -> str:
    """"stable", "marginal" or "unstable" (``LoopModel.stability`` when the tuner has it;
    else from the spectral radius of the sampled closed loop with a 1e-6 tolerance)."""
    if hasattr(lp, "stability"):
        return lp.stability(gains)
    rho = lp.spectral_radius(gains)
    if rho < 1.0 - 1e-6:
        return "stable"
    return "marginal" if rho <= 1.0 + 1e-6 else "unstable"


def plot_main(argv: Sequence[str] | None = None) -> int:
    """``prsa-plot``: plant and loop Bode plots, sensitivities, load-step and setpoint-step
    responses for given gains, written as PNG and SVG into ``--plots`` (alias ``--out``),
    and the margins printed; returns the exit code (0, 2, 3 or 130)."""
    return _invoke("prsa-plot", argv, _plot_body)


def _plot_figures(plant, scene, pid, state, loops):
    from ..plots.loop import design_figures

    return design_figures(plant, scene, pid, state, loops)


def _plot_body(run: _Run, argv: list[str]) -> int:
    from ..io.output import check_directory

    if "-h" in argv or "--help" in argv:
        build_plot_parser().print_help()
        return EXIT_OK
    args = build_plot_parser().parse_args(argv)
    notes: list[warnings.WarningMessage] = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        plant, scene, _ = _load_and_override(args, run, plot=True)
        from ..drive.pid import PID
        from ..options import DERIVATIVE_FILTER_SAMPLES

        try:
            pid = PID(args.kp, args.ki, args.kd, tf=DERIVATIVE_FILTER_SAMPLES * plant.sample_time_s)
        except ValueError as exc:
            raise _UsageError(str(exc)) from None
        check_directory(args.out, "--plots")
        inputs = _input_files(args, scene)
        notes.extend(caught)
    run.check()
    native: list[str] = []
    what = f"plotting kp = {args.kp:g}, ki = {args.ki:g}, kd = {args.kd:g} on {plant.name}"
    _progress(run, args.verbose, f"{what} ...")
    try:
        with warnings.catch_warnings(record=True) as caught, _native_output(run, native):
            warnings.simplefilter("always")
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", GeometryWarning)
                from ..studies.autotune import actuator_loops
                from ..studies.scene import choose_fidelity

                loops = actuator_loops(plant, choose_fidelity(scene)[0])
                state = _stability(loops[0], pid.gains)
                m = loops[0].margins(pid.gains)
                figs = None if state == "stable" else _plot_figures(plant, scene, pid, state, loops)
                files = None
                if state == "stable":
                    from ..plots.loop import write_design_plots

                    files = _staged(run, lambda staging: write_design_plots(plant, scene, pid, staging), args.out, inputs)
            notes.extend(caught)
        run.check()
    except KeyboardInterrupt:
        raise
    except Exception as exc:  # noqa: BLE001 - translated at this boundary
        run.check()
        code, line = _describe_failure(exc, what)
        if args.verbose:  # the internal detail, for a bug report; never a traceback
            print(f"{run.prog}: detail: {type(exc).__name__}: {_one_line(exc)[:500]}", file=sys.stderr)
        run.say(f"{run.prog}: {line}")
        return code
    if files is None:
        files = _write_figures(run, figs, args.out, inputs)
    print(f"prsa-plot: plant {plant.name}, {_scene_header(scene)}")
    print(f"gains: kp = {args.kp:g} N m s/rad, ki = {args.ki:g} N m/rad, kd = {args.kd:g} N m s^2/rad")
    print(f"Margins: Ms {m.ms:.3f}, Mt {m.mt:.3f}, GM {_fmt_margin(m.gm_db)} dB, PM {_fmt_margin(m.pm_deg)} deg, "
          f"crossover {_fmt_margin(m.wc_rad_s)} rad/s"
          + (" (frequency-response values; not margins of a stable loop)" if state == "unstable" else ""))
    if state == "unstable":
        print(f"warning: the closed loop is UNSTABLE with these gains on {plant.name}; only the frequency plots "
              "were drawn (time responses diverge)")
    elif state == "marginal":
        why = ("P-only (ki = 0) leaves a steady error after a load step" if args.ki == 0
               else "a closed-loop pole sits on the stability boundary")
        print(f"warning: marginally stable: {why}")
    elif m.ms > scene.ms_max * (1 + 1e-3):
        print(f"warning: Ms {m.ms:.3f} exceeds the scene's bound {scene.ms_max:g}")
    print("\n".join(str(f) for f in files))
    _show_notes(run, notes, native, args.verbose, False)
    return EXIT_OK


def _write_figures(run: _Run, figs: dict, directory: str, inputs: Sequence[str]) -> list[Path]:
    import matplotlib.pyplot as plt

    from ..io.output import Transaction

    run.check()
    files: list[Path] = []
    with Transaction(inputs) as tr:
        tr.make_directory(directory, "--plots")
        for name, fig in figs.items():
            for ext in ("png", "svg"):
                path = Path(directory) / f"{name}.{ext}"
                tr.stage(path, lambda tmp, fig=fig, ext=ext: fig.savefig(tmp, format=ext, dpi=150), "--plots",
                         listed=False)
                files.append(path)
            plt.close(fig)
        _commit(run, tr)
    return files


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
