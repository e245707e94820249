"""What every command-line front end shares: the one-line argument parser, flag converters, exit
codes, the run wrapper (Ctrl-C and SIGTERM, solver output, one-line errors) and the output
helpers.

Exit codes, the same for every tool (``prsa-tune``, ``prsa-plot``, ``prsa-fit``, ``prsa-mc``):

* ``EXIT_OK`` 0 -- success (warnings, if any, are printed after the result);
* ``EXIT_BAD_INPUT`` 2 -- bad input: one line ``PROG: error: ...`` naming the value as typed and
  what was expected (flags, plant and scene files, output paths); nothing is written;
* ``EXIT_NUMERICAL`` 3 -- numerical failure: one line ``PROG: numerical failure: ...``; nothing
  is written;
* ``EXIT_INTERRUPTED`` 130 -- interrupted (Ctrl-C), at any moment up to the exit: the run stops
  within a second with one line; the outputs are all old or all new, and the line says which
  ("no output written", or "after the outputs were written complete: ..."); only in the
  interpreter's own shutdown, after the last check, is a Ctrl-C ignored (the run is complete);
* ``EXIT_TERMINATED`` 143 -- the same after SIGTERM;
* ``EXIT_BROKEN_PIPE`` 141 -- the reader of the standard output went away (``prsa-tune
  --show-plant X | head -1``): the command stops quietly, no line, no traceback, with the
  status a shell shows for a tool that SIGPIPE ended (128 + 13), so ``set -o pipefail`` treats
  it as such tools; temporaries are removed as after Ctrl-C, outputs already committed stay.
  (argparse's help printer ignores write errors: ``--help`` into a closed pipe may exit 0,
  equally quietly.)

A command is a ``body(run, argv) -> exit code`` handed to :func:`invoke`, which installs the
signal handlers (:func:`guard`), turns :class:`UsageError` and the input errors into exit 2 and
anything else into one line (:func:`describe_failure`).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import shutil
import signal
import sys
import tempfile
import threading
import warnings
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Sequence

from ..errors import GeometryWarning, PlantFileError, SceneError, SimulationError, UsageError
from ..options import check_number
from ..io.output import OutputError, Transaction, cleanup_temporaries, remove_created, write_text
from ..textsafe import MESSAGE_CHARS_MAX, printable

__all__ = ["report_failure", "EXIT_OK", "EXIT_BAD_INPUT", "EXIT_NUMERICAL", "EXIT_INTERRUPTED", "EXIT_TERMINATED",
           "EXIT_BROKEN_PIPE", "INTERRUPT_GRACE_S", "UsageError", "Parser", "number", "integer", "path_text", "attach_values", "long_options",
           "Run", "guard", "native_output", "invoke", "invoke_inner", "describe_failure", "raised_in", "one_line",
           "status_says_interrupted", "show_notes", "progress", "commit", "staged", "write_json_atomic",
           "KeepTyped", "typed_text", "echo"]

EXIT_OK, EXIT_BAD_INPUT, EXIT_NUMERICAL, EXIT_INTERRUPTED = 0, 2, 3, 130
#: Exit code after SIGTERM (128 + 15): handled like Ctrl-C (workers stopped, one line, nothing written).
EXIT_TERMINATED = 128 + signal.SIGTERM
#: Exit code when the standard output's reader has gone (128 + SIGPIPE, as a tool SIGPIPE ends): quiet.
EXIT_BROKEN_PIPE = 128 + signal.SIGPIPE

#: Seconds between Ctrl-C and a forced exit when a solver does not hand control back.
INTERRUPT_GRACE_S = 0.8


class Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line: :meth:`error` raises :class:`UsageError`
    (exit 2 at the command's boundary) instead of printing the usage and exiting.

    argparse says ``argument --x: MESSAGE``; when ``MESSAGE`` already starts with the flag (the
    converters of this module name it) the prefix is dropped. With ``flag_first`` (prsa-fit)
    every such message becomes ``--x MESSAGE``.
    """

    def __init__(self, *args: Any, flag_first: bool = False, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.flag_first = flag_first

    def error(self, message: str) -> None:  # one line, exit 2, no usage dump
        m = re.match(r"argument (\S+): (--\S+ .*)$", message, re.S)
        if m and m.group(2).split()[0] in m.group(1).split("/"):
            message = m.group(2)  # our converters already name the flag
        elif self.flag_first:
            message = re.sub(r"^argument (-[-\w]+)(?:/-[-\w]+)*: ", r"\1 ", message)
        raise UsageError(message)


# --- flag values ---------------------------------------------------------------------------------

def number(flag: str, lo: float = -math.inf, hi: float = math.inf, unit: str = "", what: str = "a number",
           lo_open: bool = False, hi_open: bool = False, *, quoted: bool = False,
           not_a_number: str | None = None) -> Callable[[str], float]:
    """Converter of a number flag: a finite number in ``[lo, hi]`` (``lo_open``/``hi_open``: the
    bound excluded). The messages name the flag and the text as typed: ``FLAG 'TEXT': expected
    WHAT in RANGE UNIT`` for text that is no number (``not_a_number`` instead of ``what`` if
    given), ``FLAG TEXT UNIT: expected ...`` for a number out of range (``quoted``: ``'TEXT'``).
    The range is left out when a bound is infinite (``what`` says it then).

    >>> number("--duration", 0.0, 1e4, "s", "a time", lo_open=True)("0")
    Traceback (most recent call last):
    ...
    argparse.ArgumentTypeError: --duration 0 s: expected a time in (0, 10000] s
    >>> number("--segment", 0.0, what="a finite number > 0", lo_open=True, quoted=True)("-1")
    Traceback (most recent call last):
    ...
    argparse.ArgumentTypeError: --segment '-1': expected a finite number > 0
    """
    lb = "(" if lo_open else "["
    rb = ")" if hi_open else "]"
    bounded = math.isfinite(lo) and math.isfinite(hi)
    rng = (f" in {lb}{lo:g}, {hi:g}{rb}" + (f" {unit}" if unit else "")) if bounded else ""

    def conv(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{flag} {text!r}: expected {not_a_number or what}{rng}") from None
        try:  # the range decided by the one number validator; the message in the flags' form
            return check_number(flag, v, lo, hi, lo_open=lo_open, hi_open=hi_open)
        except ValueError:
            shown = repr(text) if quoted else text
            raise argparse.ArgumentTypeError(f"{flag} {shown}" + (f" {unit}" if unit and math.isfinite(v) else "")
                                             + f": expected {what}{rng}") from None

    return conv


def integer(flag: str, lo: int, hi: int, what: str) -> Callable[[str], int]:
    """Converter of an integer flag in ``lo..hi``; the messages name the flag and the text as typed."""
    def conv(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{flag} {text!r}: expected {what} {lo}..{hi}") from None
        try:
            return check_number(flag, v, lo, hi, integer=True)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{flag} {text}: expected {what} {lo}..{hi}") from None

    return conv


def path_text(flag: str) -> Callable[[str], str]:
    """Converter of a path flag: not blank, no NUL character (the text is returned as typed)."""
    def conv(text: str) -> str:
        if not text.strip():
            raise argparse.ArgumentTypeError(f"{flag} {text!r}: expected a path")
        if "\x00" in text:
            raise argparse.ArgumentTypeError(f"{flag} {text!r}: a path may not contain NUL characters")
        return text

    return conv

def long_options(parser: argparse.ArgumentParser) -> list[str]:
    """Every long option (``--x``) of ``parser``: the ``flags`` :func:`attach_values` needs for a
    parser that accepts abbreviations."""
    return [o for a in parser._actions for o in a.option_strings if o.startswith("--")]


def attach_values(argv: Sequence[str], value_flags: Iterable[str] = (), flags: Iterable[str] = ()) -> list[str]:
    """``--load-step -5:10`` would read ``-5:10`` as an option; glue values to their flag so
    that such a value reaches the validator and is reported by name (``value_flags``: the flags
    that take a value which may start with ``-``). A flag followed by a long option (``--x``) is
    left alone: no value of theirs starts with ``--``, and argparse then says the value is missing.
    ``flags``: every long option of a parser that accepts abbreviations (prsa-fit); an
    abbreviation that argparse resolves to a value flag (a prefix of that flag alone) is glued as
    typed (``--frf-b=-1,300``, which argparse resolves the same). After a bare ``--`` every
    argument is positional and is passed on as typed.

    >>> attach_values(["--frf-band", "-1,300", "--out", "p.toml"], {"--frf-band"})
    ['--frf-band=-1,300', '--out', 'p.toml']
    >>> attach_values(["--frf-band", "--out", "p.toml"], {"--frf-band"})
    ['--frf-band', '--out', 'p.toml']
    >>> attach_values(["--frf-b", "-1,300", "--", "--frf-band", "-x.csv"], {"--frf-band"}, {"--frf", "--frf-band"})
    ['--frf-b=-1,300', '--', '--frf-band', '-x.csv']
    """
    value_flags = set(value_flags)
    flags = set(flags)
    abbreviated = bool(flags)  # (parsers without abbreviations pass none: their prefixes stay unknown options)
    flags |= value_flags
    argv = list(argv)
    out: list[str] = []
    i = 0
    while i < len(argv):
        a = argv[i]
        if a == "--":  # the separator: the rest are positionals, as typed
            out += argv[i:]
            break
        if a.startswith("--") and a.partition("=")[2] == "--":
            raise UsageError(f"{a.partition('=')[0]} '--': expected a value")
        nxt = argv[i + 1] if i + 1 < len(argv) else None
        # (an abbreviation: the one long option it is a prefix of, which argparse resolves it to)
        prefix_of = ([f for f in flags if f.startswith(a)]
                     if abbreviated and a.startswith("--") and a not in flags and "=" not in a else [])
        takes = a in value_flags or (len(prefix_of) == 1 and prefix_of[0] in value_flags)
        if takes and nxt == "--":  # argparse would drop it and hand the converter nothing
            raise UsageError(f"{a} '--': expected a value")
        if takes and nxt is not None and not nxt.startswith("--"):
            out.append(f"{a}={nxt}")
            i += 2
        else:
            out.append(a)
            i += 1
    return out


# --- run-time guards: Ctrl-C, solver chatter, warnings ------------------------------------------

class Run:
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
        #: that the outputs end all old or all new (:func:`commit`).
        self.defer = False
        #: Output files in place (the interrupt line names them).
        self.written: list[str] = []
        self.cause = "Ctrl-C"  # or "SIGTERM"
        self.exit_code = EXIT_INTERRUPTED  # EXIT_TERMINATED after SIGTERM
        #: True while a solver runs that would swallow a raised KeyboardInterrupt (CasADi turns it
        #: into a failed evaluation and prints its inputs): Ctrl-C is recorded and the watchdog
        #: armed, and the caller's :meth:`check` at the solver's iteration boundaries raises it.
        self.record = False
        self.late = False  # Ctrl-C after the command finished (:meth:`on_late`)
        #: ``--quiet``: the body sets it; no ``note:`` lines then (:func:`invoke_inner`).
        self.quiet = False

    def say(self, line: str) -> bool:
        """Print the final one-line message once (main thread or watchdog, whichever first);
        control characters escaped and the length bounded (:func:`prsa_ctrl.textsafe.printable`)."""
        with self.lock:
            if self.reported:
                return False
            self.reported = True
        self.write_err(line)
        return True

    def write_err(self, line: str) -> None:
        """Write one line to the terminal's stderr, control characters escaped and the length
        bounded (:func:`prsa_ctrl.textsafe.printable`): to :attr:`err_fd` directly even while the
        solvers' output is captured (:func:`native_output`), through ``sys.stderr`` where that is
        not a real file (pytest capture, StringIO)."""
        line = printable(line, limit=MESSAGE_CHARS_MAX)
        try:
            sys.stderr.flush()
            sys.stderr.fileno()
            real = True
        except Exception:  # noqa: BLE001 - not a real file (pytest capture, StringIO)
            real = False
        if real:
            with contextlib.suppress(OSError):
                os.write(self.err_fd, (line + "\n").encode("utf-8", "replace"))
        else:
            print(line, file=sys.stderr)

    def interrupt_line(self) -> str:
        if self.written:
            return (f"{self.prog}: interrupted ({self.cause}) after the outputs were written complete: "
                    f"{', '.join(self.written)}")
        return f"{self.prog}: interrupted ({self.cause}); no output written"

    def force_exit(self) -> None:  # watchdog thread: a solver kept control after Ctrl-C
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
        if self.defer:  # outputs being renamed into place: finish them, then stop (commit)
            return
        if self.timer is None:
            self.timer = threading.Timer(INTERRUPT_GRACE_S, self.force_exit)
            self.timer.daemon = True
            self.timer.start()
        if self.record:  # raised by the next check(), outside the solver
            return
        raise KeyboardInterrupt

    def on_late(self, signum, frame) -> None:
        """Ctrl-C after the command finished (:func:`guard` for the process): recorded only."""
        self.late = True

    def check(self) -> None:
        """Raise KeyboardInterrupt if Ctrl-C came while a solver swallowed it."""
        if self.interrupted:
            raise KeyboardInterrupt


@contextlib.contextmanager
def guard(run: Run, process: bool = False) -> Iterator[None]:
    """Install the Ctrl-C and SIGTERM handlers for the duration of a command (main thread only).
    For the process itself (``process``), SIGINT is blocked from the end of the command to the
    exit: :func:`invoke` turns a pending one into exit 130 with its line (never a death by
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
            # For the process, a late one is recorded (run.late): another thread (a BLAS worker)
            # may take a process signal that the main thread blocks, and the old handler would
            # then end the finished process by SIGINT.
            signal.signal(signal.SIGINT, signal.SIG_IGN if run.interrupted else run.on_late if process else old)
            signal.signal(signal.SIGTERM, old_term)  # never left ignored: children would inherit SIG_IGN


@contextlib.contextmanager
def native_output(run: Run, lines: list[str]) -> Iterator[None]:
    """Collect what the solvers print -- C code (IPOPT, SUNDIALS) on descriptors 1 and 2, and
    CasADi through Python's ``sys.stdout``/``sys.stderr`` -- in a temporary file; the lines
    are returned in ``lines`` (shown with ``--verbose``, otherwise counted in one note). The
    command's own final line goes to the saved terminal descriptor (:meth:`Run.say`)."""
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


def write_json_atomic(path: str | os.PathLike, data: dict, inputs: Sequence[str | os.PathLike] = (),
                      transaction=None) -> Path:
    """Write JSON through :func:`prsa_ctrl.io.output.write_text` (atomic, never onto ``inputs``);
    with a :class:`prsa_ctrl.io.output.Transaction`, staged in it (renamed at its commit)."""
    text = json.dumps(data, indent=2, allow_nan=False, default=float) + "\n"
    if transaction is not None:
        return transaction.stage(path, lambda tmp: tmp.write_text(text, encoding="utf-8"), "--json")
    return write_text(path, text, inputs, flag="--json")


def commit(run: Run, outputs) -> None:
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


def staged(run: Run, render: Callable[[Path], list[Path]], directory: str, inputs: Sequence[str],
            outputs=None) -> list[Path]:
    """``render`` writes files into a private staging folder; each is then staged in the
    :class:`prsa_ctrl.io.output.Transaction` ``outputs`` (one of its own, committed here, if
    ``None``) for ``directory`` (created only now)."""
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
            commit(run, tr)
        return out
    finally:
        if own:
            tr.abort()  # no-op after the commit
        shutil.rmtree(staging, ignore_errors=True)


# --- error translation ---------------------------------------------------------------------------

def raised_in(exc: BaseException) -> str:
    """The module in which ``exc`` was raised (its innermost traceback frame), ``""`` if it was
    never raised (built and passed on)."""
    tb = exc.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    return "" if tb is None else str(tb.tb_frame.f_globals.get("__name__", ""))


def report_failure(run: "Run", exc: BaseException, what: str, verbose: bool) -> int:
    """Say a failure of the step ``what`` in one line (the internal detail too with
    ``--verbose``, never a traceback) and return its exit code (:func:`describe_failure`)."""
    run.check()
    code, line = describe_failure(exc, what)
    if verbose:  # the internal detail, for a bug report
        echo(f"{run.prog}: detail: {type(exc).__name__}: {one_line(exc)[:500]}", file=sys.stderr)
    run.say(f"{run.prog}: {line}")
    return code


def describe_failure(exc: BaseException, what: str) -> tuple[int, str]:
    """Map an exception of the expensive phase to (exit code, one line without internal names).

    Classified by type and by where it was raised, never by its message: the toolkit's own
    errors (:mod:`prsa_ctrl.errors`, and a ``ValueError`` raised in ``prsa_ctrl``) are shown as
    they are; arithmetic and linear-algebra errors and anything raised inside NumPy, SciPy,
    CasADi or python-control are internal (their messages name internals): one line says which
    step failed and what to check."""
    import numpy as np

    where = raised_in(exc)
    ours = where == "" or where == "prsa_ctrl" or where.startswith("prsa_ctrl.")
    if isinstance(exc, MemoryError):
        return EXIT_BAD_INPUT, f"error: {what} needs more memory than this machine has; shorten --duration or use fewer load levels"
    if isinstance(exc, (PlantFileError, SceneError, OutputError)):
        return EXIT_BAD_INPUT, f"error: {one_line(exc)}"
    if isinstance(exc, SimulationError):
        return EXIT_NUMERICAL, f"numerical failure: {one_line(exc)}"
    if isinstance(exc, (ArithmeticError, np.linalg.LinAlgError)):
        return EXIT_NUMERICAL, (f"numerical failure: {what} produced non-finite numbers "
                                f"({type(exc).__name__}); check the plant values and the operating point")
    if isinstance(exc, ValueError) and ours:  # our own messages (e.g. no gains meet the robustness bound)
        return EXIT_NUMERICAL, f"numerical failure: {one_line(exc)}"
    if isinstance(exc, (ValueError, RuntimeError)) and not ours:
        return EXIT_NUMERICAL, (f"numerical failure: {what} failed in {where.split('.')[0]} ({type(exc).__name__}); "
                                "check the plant values and the operating point, or rerun with --verbose for details")
    return EXIT_NUMERICAL, f"numerical failure: {what} failed ({type(exc).__name__}); rerun with --verbose for details"


class KeepTyped(argparse.Action):
    """Store a flag's value and keep the text as the user typed it (for messages that quote it
    beside a converted value): ``p.add_argument("--offset", action=KeepTyped, type=conv)``;
    :func:`typed_text` gives the text back (argv is read once, by argparse). The converter runs
    here, and its errors read as argparse's own."""

    def __init__(self, option_strings, dest, type=None, **kwargs):  # noqa: A002 -- argparse's name
        self.convert = type
        super().__init__(option_strings, dest, **kwargs)  # no type: argparse hands over the text

    def __call__(self, parser, namespace, values, option_string=None):
        try:
            value = self.convert(values) if self.convert is not None else values
        except argparse.ArgumentTypeError as exc:
            raise argparse.ArgumentError(self, str(exc)) from None
        except (TypeError, ValueError):
            name = getattr(self.convert, "__name__", repr(self.convert))
            raise argparse.ArgumentError(self, f"invalid {name} value: {values!r}") from None
        setattr(namespace, self.dest, value)
        namespace.typed_text = {**(getattr(namespace, "typed_text", None) or {}), self.dest: values}


def typed_text(args: argparse.Namespace, dest: str) -> str | None:
    """The text as typed of a :class:`KeepTyped` flag (its ``dest``: ``"frf_speed"``), or None
    when the command line did not give it (the value is then the default)."""
    return (getattr(args, "typed_text", None) or {}).get(dest)


def one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


def status_says_interrupted(obj: Any) -> bool:
    """Deprecated (warns); always False. A Ctrl-C that a solver turned into a status (IPOPT's
    ``User_Requested_Stop``) is known by type, not read back from a result: the command's
    signal handler records it and :meth:`Run.check` raises ``KeyboardInterrupt`` after the
    solver returns (was: a walk of the result's dicts to depth 6 for the word)."""
    warnings.warn("status_says_interrupted is deprecated and always False: an interruption is known by type "
                  "(Run.check raises KeyboardInterrupt)", DeprecationWarning, stacklevel=2)
    return False


# --- notes and the command frame -----------------------------------------------------------------

def show_notes(run: Run, notes: list[warnings.WarningMessage], native: list[str], verbose: bool, quiet: bool) -> None:
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
        echo(f"{run.prog}: note: {text}", file=sys.stderr)
    if native:
        if verbose:
            for line in native:
                echo(f"{run.prog}: solver: {line}", file=sys.stderr)
        else:
            echo(f"{run.prog}: note: the numerical solvers printed {len(native)} diagnostic lines "
                 "(shown with --verbose)", file=sys.stderr)


def progress(run: Run, verbose: bool, text: str) -> None:
    """A progress line on stderr (``--verbose`` only); while the solvers' output is captured
    (:func:`native_output`) it goes to the terminal's stderr directly, not among the solver
    lines (was shown again as ``prog: solver: prog: ...``)."""
    if verbose:
        run.write_err(f"{run.prog}: {text}")


def echo(text: Any, file: Any = None, flush: bool = False) -> None:
    """Print what a command shows (its report, notes, error lines) with the user's text made
    harmless for a terminal (:func:`prsa_ctrl.textsafe.printable`): every control character
    (ESC, BEL, CR, ...) is written as an escape. On stdout (the report) line feeds and tabs stay;
    on stderr (notes and errors, one line each) they are escaped too and the line is bounded to
    :data:`prsa_ctrl.textsafe.MESSAGE_CHARS_MAX` characters."""
    stream = sys.stdout if file is None else file
    one = stream is sys.stderr
    print(printable(text, multiline=not one, limit=MESSAGE_CHARS_MAX if one else None), file=stream, flush=flush)


def invoke(prog: str, argv: Sequence[str] | None, body: Callable[[Run, list[str]], int],
           value_flags: Iterable[str] = (), flags: Iterable[str] = ()) -> int:
    """Common frame of the commands: Ctrl-C guard, one-line errors, exit codes.

    Parameters
    ----------
    prog : str
        The command's name (first word of its messages).
    argv : list of str or None
        The arguments (None: ``sys.argv[1:]``, the process itself: exit 130 ends it at once).
    body : callable
        ``body(run, argv) -> exit code``.
    value_flags : iterable of str
        Flags whose value may start with ``-`` (:func:`attach_values`).
    flags : iterable of str
        Every long option of a parser that accepts abbreviations (:func:`attach_values`).
    """
    run = Run(prog)
    try:
        code = invoke_inner(run, argv, body, value_flags, flags)
    except SystemExit:  # argparse's --help inside a body: its output may meet a closed pipe too
        if argv is None and _flush_stdout(run, EXIT_OK) == EXIT_BROKEN_PIPE:
            raise SystemExit(EXIT_BROKEN_PIPE) from None
        raise
    if argv is None and code != EXIT_BROKEN_PIPE:
        code = _flush_stdout(run, code)
    if argv is None and code not in (EXIT_INTERRUPTED, EXIT_TERMINATED) and (
            run.late or signal.SIGINT in _pending_signals()):
        # Ctrl-C after the command finished (blocked by guard): exit 130 with its line.
        run.reported = False
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        run.say(run.interrupt_line())
        code = EXIT_INTERRUPTED
    if argv is None and code not in (EXIT_INTERRUPTED, EXIT_TERMINATED):
        # A Ctrl-C from here to the exit is ignored (the outputs are complete): Python's
        # finalisation resets the handler to the default, and a thread that does not block
        # SIGINT (a BLAS worker) would take it -- a finished run dying by SIGINT, no line.
        with contextlib.suppress(ValueError):  # not the main thread
            signal.signal(signal.SIGINT, signal.SIG_IGN)
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


def invoke_inner(run: Run, argv: Sequence[str] | None, body: Callable[[Run, list[str]], int],
                 value_flags: Iterable[str] = (), flags: Iterable[str] = ()) -> int:
    """:func:`invoke` without the end of the process: the guarded body and its error lines.

    A Python warning the body does not collect itself (numpy's ``RuntimeWarning`` of a bad
    input, say) never reaches the terminal in Python's format (file, line, source text): after a
    successful command it is one ``PROG: note:`` line; when the command fails its one line is
    all it prints; with ``--quiet`` (``run.quiet``) nothing. The warning filters are left as they are (``-W``/``PYTHONWARNINGS`` still
    decide what is shown)."""
    with warnings.catch_warnings(record=True) as stray:
        code = _guarded(run, argv, body, value_flags, flags)
    if code == EXIT_OK and not run.quiet:
        for text in dict.fromkeys(f"{w.category.__name__}: {w.message}" for w in stray):
            echo(f"{run.prog}: note: {text}", file=sys.stderr)
    return code


def _stdout_gone() -> bool:
    """Whether the standard output is a pipe (or socket) whose reader has gone (poll: error or
    hang-up on the write end)."""
    import select

    try:
        fd = sys.stdout.fileno()
        poller = select.poll()
        poller.register(fd, select.POLLOUT)
        return any(ev & (select.POLLERR | select.POLLHUP) for _, ev in poller.poll(0))
    except (AttributeError, OSError, ValueError):  # not a real file (a test's capture), no poll
        return False


def _flush_stdout(run: Run, code: int) -> int:
    """Flush what is still buffered for the standard output, where a closed pipe can be told
    apart: ``code``, or :data:`EXIT_BROKEN_PIPE` when the reader has gone."""
    try:
        sys.stdout.flush()
    except BrokenPipeError:
        if not _stdout_gone():
            raise
        return _quiet_broken_pipe(run)
    return code


def _quiet_broken_pipe(run: Run) -> int:
    """End quietly after the standard output's reader went away: no line (the run counts as
    reported), the rest of the output to the null device (so the interpreter's last flush does
    not print an ignored exception), exit :data:`EXIT_BROKEN_PIPE`."""
    run.reported = True
    with contextlib.suppress(OSError, ValueError, AttributeError):
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, sys.stdout.fileno())
        os.close(null)
    return EXIT_BROKEN_PIPE


def _guarded(run: Run, argv: Sequence[str] | None, body: Callable[[Run, list[str]], int],
             value_flags: Iterable[str] = (), flags: Iterable[str] = ()) -> int:
    prog = run.prog
    with guard(run, process=argv is None):
        try:
            run.argv = attach_values(list(sys.argv[1:] if argv is None else argv), value_flags, flags)
            return body(run, run.argv)
        except KeyboardInterrupt:
            cleanup_temporaries()
            remove_created(run.created)
            run.say(run.interrupt_line())
            return run.exit_code
        except (UsageError, argparse.ArgumentTypeError, PlantFileError, SceneError, OutputError) as exc:
            remove_created(run.created)
            if run.interrupted:
                run.say(run.interrupt_line())
                return run.exit_code
            run.say(f"{prog}: error: {one_line(exc)}")
            return EXIT_BAD_INPUT
        except Exception as exc:  # noqa: BLE001 - a bug must not print a traceback either
            if isinstance(exc, BrokenPipeError) and _stdout_gone():  # not another pipe (a worker's, a socket)
                cleanup_temporaries()
                remove_created(run.created)
                return _quiet_broken_pipe(run)
            remove_created(run.created)
            if run.interrupted:
                run.say(run.interrupt_line())
                return run.exit_code
            code, line = describe_failure(exc, f"{prog} {' '.join(run.argv)}".strip())
            run.say(f"{prog}: {line}")
            return code
