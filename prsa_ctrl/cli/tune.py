"""``prsa-tune``: tune a scene's loop, verify it on the nonlinear simulator, report, export.

One path for every scene (:func:`main`): parse the flags, load the plant and the scene, build
the scene's problem from the registry of kinds (:mod:`prsa_ctrl.studies.scenekinds`: load step,
duty cycle, move), check it and the output paths, tune (``problem.tune``), write the report's
outputs (``--json``: ``report.as_dict()``, ``--export``: ``report.export_target()``,
``--plots``: the figures writer of the kind), all or none, and print ``report.format()``:

* a speed-loop scene (load steps, a Kalman filter or a duty cycle): the speed PI/PID
  (:func:`prsa_ctrl.studies.autotune.tune_actuator`), compared with baselines, with the robust
  study and the Monte-Carlo yield when asked;
* a move scene (``[move]`` section): the position loop over the speed loop, tuned sequentially
  and jointly and verified (:func:`prsa_ctrl.studies.move.tune_move`); flags that do not apply to
  it (:data:`~prsa_ctrl.studies.scenekinds.MOVE_FLAGS` lists those that do) are refused in one line
  by the kind (:meth:`~prsa_ctrl.studies.scenekinds.Move.refuse_flags`).

Exit codes and one-line errors as every command (:mod:`prsa_ctrl.cli.common`): 0 ok, 2 bad
input, 3 numerical failure (also when the best speed-loop design is flagged, unless
``--accept-unconverged``), 130 interrupted.

Every flag is checked in the user's unit before any heavy import; the scene is checked against
the plant (:func:`prsa_ctrl.studies.scene.check_against_plant`,
:func:`prsa_ctrl.studies.move.check_move_against_plant`), ``--scheduler`` is parsed and connected
to (bounded by ``SCHEDULER_CONNECT_TIMEOUT_S``); output paths are checked before the expensive
work and written by :mod:`prsa_ctrl.io.output` in one :class:`~prsa_ctrl.io.output.Transaction`
(atomic, all or nothing, never onto an input file -- plant, scene, CSV traces -- nor into the
package's own files).
"""

from __future__ import annotations

import time

_T_START = time.perf_counter()

import argparse  # noqa: E402
import os  # noqa: E402
import re  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Sequence  # noqa: E402

from .._lazy import module  # noqa: E402
from ..errors import GeometryWarning  # noqa: E402
from ..io.output import OutputError, Transaction, check_directory, check_distinct, check_writable  # noqa: E402
from ..options import (CONTROLLERS, DEFAULT_FREQUENCY_UNIT, ESTIMATORS, FREQUENCY_UNITS, MS_MAX_DEFAULT, OBJECTIVES,  # noqa: E402
                       PEAK_BOUND_RANGE)
from .common import (EXIT_BAD_INPUT, EXIT_INTERRUPTED, EXIT_NUMERICAL, EXIT_OK, Parser, Run, UsageError,  # noqa: E402
                     commit, describe_failure, echo, integer, invoke, native_output, number, path_text, progress,
                     report_failure, show_notes, staged, write_json_atomic)
from .inputs import VALUE_FLAGS, input_files, load_and_override, parse_load_step, scene_flags  # noqa: E402
from .plot import build_plot_parser, plot_main  # noqa: E402
from ..studies.scenekinds import MOVE_FLAGS, TuneOptions, file_kind, problem  # noqa: E402
from ..studies.scenereport import format_report  # noqa: E402

#: The figures modules (matplotlib) are imported when a figure is drawn.
loop_plots = module("prsa_ctrl.plots.loop")
move_plots = module("prsa_ctrl.plots.move")

__all__ = ["main", "plot_main", "parse_load_step", "write_json_atomic", "format_report", "build_parser",
           "build_plot_parser", "EXIT_OK", "EXIT_BAD_INPUT", "EXIT_NUMERICAL", "EXIT_INTERRUPTED", "MOVE_FLAGS",
           "WORKERS_MAX", "SCHEDULER_CONNECT_TIMEOUT_S"]

WORKERS_MAX = 64
#: Suffixes ``--export`` takes (drive file as JSON or TOML, code as C or Structured Text).
EXPORT_SUFFIXES = (".json", ".toml", ".c", ".st", ".xml")


def build_parser() -> argparse.ArgumentParser:
    """Argument parser of ``prsa-tune``."""
    p = Parser(
        prog="prsa-tune", allow_abbrev=False,
        description="Tune the nut-speed PI/PID of an inverted planetary roller screw actuator "
        "for a load step, verify on the nonlinear simulator, compare with baselines. "
        "Exit codes: 0 ok, 2 bad input, 3 numerical failure, 130 interrupted.",
    )
    scene_flags(p)
    p.add_argument("--show-plant", type=path_text("--show-plant"), metavar="NAME|PATH",
                   help="print every value of the plant with its unit and source (given or default), then exit")
    p.add_argument("--step-time", metavar="S", type=number("--step-time", 0.0, 1e4, "s", "a time", lo_open=True),
                   help="time of the load step, s; at least 8 controller samples after t = 0 (default: the scene's)")
    p.add_argument("--duration", metavar="S", type=number("--duration", 0.0, 1e4, "s", "a time", lo_open=True),
                   help="end of the record, s; at least 80 controller samples after the step and at most "
                        "40000 samples in all (default: the scene's)")
    lo, hi = PEAK_BOUND_RANGE
    p.add_argument("--ms-max", metavar="MS", type=number("--ms-max", lo, hi, "", "a peak sensitivity",
                                                          lo_open=True, hi_open=True),
                   help=f"peak-sensitivity bound, in ({lo:g}, {hi:g}) (default: the scene's, {MS_MAX_DEFAULT:g})")
    p.add_argument("--mt-max", metavar="MT", type=number("--mt-max", lo, hi, "", "a peak complementary sensitivity",
                                                          lo_open=True, hi_open=True),
                   help=f"peak complementary-sensitivity bound, in ({lo:g}, {hi:g}); Mt >= 1 with integral action "
                        "(default: the scene's, none)")
    p.add_argument("--mks-max", metavar="MKS", type=number("--mks-max", 0.0, 1e12, "N m s/rad",
                                                            "a noise-sensitivity bound", lo_open=True),
                   help="bound on the true peak noise sensitivity max|C F S| from the measured speed to the torque "
                        "command, N m s/rad (default: the scene's, none)")
    p.add_argument("--objective", choices=OBJECTIVES, help="tuning objective (default: the scene's, iae)")
    p.add_argument("--controller", choices=CONTROLLERS, help="controller structure (default: the scene's, pi)")
    p.add_argument("--estimator", choices=ESTIMATORS, help="speed measurement: drive difference or Kalman filter")
    p.add_argument("--feedforward", action="store_true", help="feed the estimated load torque forward (needs --estimator kf)")
    p.add_argument("--json", type=path_text("--json"), metavar="PATH",
                   help="write the report as JSON (atomically; never onto an input file; symlinks are written through)")
    p.add_argument("--plots", type=path_text("--plots"), metavar="DIR",
                   help="write the standard plots (PNG and SVG) into DIR (created if missing)")
    p.add_argument("--frequency-unit", choices=tuple(FREQUENCY_UNITS), default=DEFAULT_FREQUENCY_UNIT,
                   help="unit of the frequency axes of the Bode and sensitivity plots (default Hz; the data and "
                        "the printed margins stay in rad/s)")
    p.add_argument("--workers", type=integer("--workers", 1, WORKERS_MAX, "an integer"), default=None,
                   help="processes for verification and Monte Carlo, or the workers of --scheduler local "
                        "(default: cores, at most 4)")
    p.add_argument("--export", type=path_text("--export"), metavar="PATH.json|PATH.toml|PATH.c|PATH.st|PATH.xml",
                   help="write the tuned gains in a drive's terms (continuous and discrete forms, Kp/Tn, "
                        "biquads) as JSON or TOML, or the complete discrete controller as C (PATH.c and PATH.h) "
                        "or IEC 61131-3 Structured Text (PATH.st; PATH.xml: the same function block as PLCopen XML "
                        "for TwinCAT/CODESYS import), chosen by the suffix")
    p.add_argument("--export-real", choices=("double", "float"), default="double",
                   help="floating-point type of a .c/.st/.xml export (default double)")
    p.add_argument("--export-template", metavar="NAME|PATH.toml",
                   help="with --export PATH.toml|.json: write the drive parameter set of this template (built-in: "
                        "generic, cia402, siemens-sinamics, beckhoff-ax8000; or a copy you edited)")
    p.add_argument("--motor", metavar="PATH.toml|KEY=VALUE,...",
                   help="motor data for current-based gains: a TOML file with [motor] or e.g. "
                        "torque_constant_n_m_per_a=0.9,rated_torque_n_m=3,rated_current_a=4,pole_pairs=5 (or "
                        "back_emf_v_per_krpm[_rms|_peak] / back_emf_v_s_per_rad_rms|_peak, line-to-line)")
    p.add_argument("--rated-torque", metavar="N_M", type=number("--rated-torque", 0.0, 1e6, "N m", "a torque",
                                                                lo_open=True),
                   help="rated motor torque, N m: adds the gains per unit of rated torque to --export (with or "
                        "without --motor)")
    p.add_argument("--friction-ff", action="store_true",
                   help="move scenes: feed the plant file's friction curve forward from the profile's speed (at the "
                        "scene's load at the start of the move), verify the joint design with and without it and "
                        "export it with the design (formula and table in .json/.toml, code in .c/.st)")
    p.add_argument("--robust", action="store_true",
                   help="also tune one design over the scenario models of the plant's and scene's [uncertainty] "
                        "(default: when the scene has a [robust] section) and compare it with the nominal design")
    p.add_argument("--design-to-spec", action="store_true",
                   help="search for the design that meets the scene's [spec] most often: nominal and robust tunings "
                        "at a sequence of Ms bounds plus the baselines, chosen on common Monte-Carlo samples; the "
                        "reported yield is the chosen design's on --monte-carlo N fresh samples (default the "
                        "scene's [robust] monte_carlo, else 200)")
    p.add_argument("--monte-carlo", metavar="N", type=integer("--monte-carlo", 0, 1_000_000, "a sample count"),
                   default=None, help="verify the designs on N seeded samples of the uncertainty and report the "
                                      "yield against the scene's [spec] (default: the scene's [robust] monte_carlo; 0: off)")
    p.add_argument("--seed", metavar="S", type=integer("--seed", 0, 2**31 - 1, "a seed"), default=None,
                   help="Monte-Carlo seed (default: the scene's, else 0); sample i depends only on (seed, i)")
    p.add_argument("--scheduler", metavar="local|tcp://HOST:PORT", type=path_text("--scheduler"), default=None,
                   help="run the Monte Carlo on Dask: 'local' starts a LocalCluster, an address connects to a "
                        "running scheduler (needs pip install 'prsa-ctrl[dask]', or '.[dask]' in a checkout)")
    p.add_argument("--tune-filter", choices=("notch", "lowpass", "lowpass2"), default=None,
                   help="also tune a filter with the gains (one NLP, prsa_ctrl.tuning.filtered): a notch on the "
                        "torque command, or a first-/second-order low-pass on the measured speed; kept (added to "
                        "the scene's filters, then the scene is tuned and verified with it) only if it lowers the "
                        "IAE by >= 1 %% against the gains alone under the same bounds and a notch is >= 3 dB deep "
                        "near the mode; otherwise reported as not kept")
    p.add_argument("--accept-unconverged", action="store_true",
                   help="exit 0 even when the best design is flagged (tuner not converged or a verified run "
                        "that reverses, never recovers, saturates or departs from the linear model); default: exit 3")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """``prsa-tune``; returns the exit code (0, 2, 3 or 130, see the module docstring)."""
    return invoke("prsa-tune", argv, _tune_body, VALUE_FLAGS)


def _tune_body(run: Run, argv: list[str]) -> int:
    if "-h" in argv or "--help" in argv:
        build_parser().print_help()
        return EXIT_OK
    args = build_parser().parse_args(argv)
    run.quiet = args.quiet  # no stray-warning notes either (invoke_inner)
    if args.show_plant is not None:  # issue 21: the plant's values with their sources
        from ..plant.describe import show_plant  # traces the model: CasADi only here

        echo(show_plant(args.show_plant))
        return EXIT_OK
    notes: list[warnings.WarningMessage] = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        plant, scene, overrides = _load(args, run)
        inputs = input_files(args, scene)
        prob, options = problem(scene), _options(run, args)  # built once per run
        _check_outputs(args, prob, options, scene, inputs)
        notes.extend(caught)
    run.check()
    prob.check(options)
    native: list[str] = []
    what = prob.what(plant)
    if prob.announces:
        progress(run, args.verbose, f"{what}: linearise, tune, verify ...")
    try:
        with warnings.catch_warnings(record=True) as caught, native_output(run, native):
            warnings.simplefilter("always")
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", GeometryWarning)
                report = prob.tune(plant, options, _coordinates(plant))
            notes.extend(caught)
        run.check()
    except KeyboardInterrupt:
        raise
    except Exception as exc:  # noqa: BLE001 - translated into one line at this boundary
        return report_failure(run, exc, what, args.verbose)
    if report.timing_s is not None:
        report.timing_s["process"] = time.perf_counter() - _T_START
        progress(run, args.verbose, "writing outputs")
    target = None
    if args.export is not None:  # before any output is written: all or nothing
        target = report.export_target()
        if target.design is None:
            run.say(f"{run.prog}: --export {args.export}: {target.choice['why']}; nothing written")
            return EXIT_NUMERICAL if getattr(report, "robust", None) is not None else EXIT_BAD_INPUT
    outputs = Transaction(inputs)  # all outputs or none (issue 20, hostile 4 and 17)
    try:
        plot_files = _write_outputs(run, args, plant, report, target, inputs, outputs)
    except OutputError:
        raise
    except KeyboardInterrupt:
        raise
    except Exception as exc:  # noqa: BLE001
        code, line = describe_failure(exc, "writing the outputs")
        run.say(f"{run.prog}: {line}")
        return code
    finally:
        outputs.abort()  # takes back what was not committed (nothing after the commit)
    if not args.quiet:
        echo(report.format(overrides))
        for line in report.file_lines(json=args.json, export=args.export, target=target,
                                      plots=plot_files if args.plots is not None else None):
            echo(line)
    show_notes(run, notes, native, args.verbose, args.quiet)
    if report.status != "ok" and not args.accept_unconverged:
        run.say(f"{run.prog}: the best design is flagged ({report.status}); its numbers are reported above but "
                "are not a trustworthy design (use --accept-unconverged to exit 0)")
        return EXIT_NUMERICAL
    return EXIT_OK


def _options(run: Run, args) -> TuneOptions:
    """The study flags as the registry's options, with the run's progress and interrupt checks
    (``run.check``: a Ctrl-C a solver swallowed, IPOPT's User_Requested_Stop, raises there)."""
    return TuneOptions(workers=args.workers, tune_filter=args.tune_filter, robust=args.robust,
                       design_to_spec=bool(getattr(args, "design_to_spec", False)), monte_carlo=args.monte_carlo,
                       seed=args.seed, scheduler=args.scheduler, quiet=args.quiet, friction_ff=args.friction_ff,
                       progress=lambda text: progress(run, args.verbose, text), checkpoint=run.check)


# --- the steps, each for both kinds of scene -----------------------------------------------------

def _load(args, run: Run):
    """Plant and scene, loaded by the scene file's kind (:func:`~prsa_ctrl.studies.scenekinds.file_kind`:
    a speed-loop scene with the command-line overrides, :func:`~prsa_ctrl.cli.inputs.load_and_override`;
    a move refuses the options it does not honour), checked against each other, and the
    overriding flags as typed."""
    return file_kind(args.scene).load(args.scene, args.plant, _given_flags(args, run),
                                      lambda: load_and_override(args, run))


def _given_flags(args, run: Run) -> list[tuple[str, str]]:
    """Every ``prsa-tune`` option given (not at its default), in the parser's order:
    (argparse destination, the flag with its value as typed)."""
    raw = {a.split("=", 1)[0]: a.split("=", 1)[1] for a in run.argv if a.startswith("--") and "=" in a}
    given = []
    for action in build_parser()._actions:
        if not action.option_strings or action.dest == "help":
            continue
        value = getattr(args, action.dest, action.default)
        if value is None or value is False or value == action.default:
            continue
        flag = action.option_strings[-1]
        given.append((action.dest, flag if value is True else f"{flag} {raw.get(flag, value)}"))
    return given


def _check_outputs(args, prob, options: TuneOptions, scene, inputs: Sequence[str]) -> None:
    """The study flags the scene's kind (``prob``) refuses, then every output path and export
    option, checked before the expensive work (the order of the checks, which decides the message
    when several fail, is each scene kind's own: :data:`_OUTPUT_CHECKS`)."""

    def suffix() -> None:
        if args.export is not None and os.path.splitext(args.export)[1].lower() not in EXPORT_SUFFIXES:
            raise UsageError(f"--export {args.export!r}: expected a path ending in .json, .toml, .c, .st or .xml")

    def distinct() -> None:
        check_distinct({"--json": args.json, "--export": args.export, "--plots": args.plots})

    def json_path() -> None:
        if args.json is not None:
            check_writable(args.json, inputs, "--json")

    def export() -> None:
        if args.export is None:
            return
        check_writable(args.export, inputs, "--export")
        if os.path.splitext(args.export)[1].lower() == ".c":  # issue 24: the header beside the source
            from ..io.codegen import check_code_export

            check_code_export(args.export, inputs, "--export")
        prob.check_export(args.export)

    def drive_options() -> None:
        # issue 24: drive units, parameter sets
        if args.motor is not None or args.export_template is not None or args.rated_torque is not None:
            from ..io.driveparams import check_cli_options

            try:
                check_cli_options(args)
            except ValueError as exc:
                raise UsageError(str(exc)) from None

    def plots() -> None:
        if args.plots is not None:
            check_directory(args.plots, "--plots")

    steps = {"suffix": suffix, "distinct": distinct, "json": json_path, "export": export, "drive": drive_options,
             "plots": plots, "scheduler": lambda: _check_scheduler(args, scene)}
    prob.check_options(options)
    for step in _OUTPUT_CHECKS[prob.name]:
        steps[step]()


#: The order of the output checks of each scene kind (it decides the message when several fail).
_OUTPUT_CHECKS = {"load-step": ("json", "scheduler", "suffix", "export", "drive", "plots", "distinct"),
                  "duty-cycle": ("json", "scheduler", "suffix", "export", "drive", "plots", "distinct"),
                  "move": ("suffix", "distinct", "json", "export", "drive", "plots")}


def _check_scheduler(args, scene) -> None:
    """``--scheduler``: a Monte Carlo to run on it, Dask installed, the address reachable."""
    if args.scheduler is None:
        return
    from importlib.util import find_spec

    from ..studies.montecarlo import scene_options

    n_mc = args.monte_carlo if args.monte_carlo is not None else scene_options(scene)["samples"]
    if not n_mc:
        raise UsageError(f"--scheduler {args.scheduler!r}: expected --monte-carlo N (or a scene with "
                         "[robust] monte_carlo) to run on it")
    address = _scheduler_address(args.scheduler)
    if find_spec("distributed") is None:
        raise UsageError(f"--scheduler {args.scheduler!r} needs Dask: pip install 'prsa-ctrl[dask]', or '.[dask]' in a checkout")
    if address is not None:
        _probe_scheduler(args.scheduler, *address)


def _write_outputs(run: Run, args, plant, report, target, inputs: Sequence[str], outputs) -> list[Path]:
    """Stage ``--plots``, ``--json`` and ``--export`` in the run's transaction and commit them."""
    plot_files: list[Path] = []
    if args.plots is not None:
        plot_files = _FIGURES[report.kind](run, args, plant, report, inputs, outputs)
    if args.json is not None:
        run.check()
        write_json_atomic(args.json, report.as_dict(), inputs, transaction=outputs)
    if args.export is not None:
        _stage_export(args, target, outputs)
    commit(run, outputs)
    return plot_files


def _speed_figures(run: Run, args, plant, report, inputs, outputs) -> list[Path]:
    """The standard plots of a speed-loop report (:func:`prsa_ctrl.plots.loop.write_standard_plots`)."""
    return _publish_report_plots(run, report.rep, args.plots, inputs, outputs, args.frequency_unit)


def _move_figures(run: Run, args, plant, report, inputs, outputs) -> list[Path]:
    """The figures of a move report (:func:`prsa_ctrl.plots.move.write_move_plots`)."""
    progress(run, args.verbose, "writing the figures ...")
    return staged(run, lambda staging: move_plots.write_move_plots(plant, report.scene, list(report.designs), staging),
                  args.plots, inputs, outputs)


#: The figures writer of each scene kind (the plots layer is above the registry's).
_FIGURES = {"load-step": _speed_figures, "duty-cycle": _speed_figures, "move": _move_figures}


def _coordinates(plant) -> str:
    """The coordinates a plant's numbers are in, as the JSON report states them."""
    from ..options import LOAD_COORDINATES, MOTOR_COORDINATES  # (not identification: ~0.9 s of imports a run)

    if plant.mechanism == "linear-axis":
        return f"{LOAD_COORDINATES}: read rad as m, rad/s as m/s, N m as N, N m s/rad as N s/m (1 m of travel per radian)"
    return MOTOR_COORDINATES


def _stage_export(args, target, outputs) -> None:
    """Stage ``--export``: the report's export target (a speed loop's chosen design or a move's
    joint cascade) as a drive file (JSON/TOML, with ``--motor``/``--export-template`` terms) or
    as code (C, ST, PLCopen XML)."""
    from ..io.export import dumps, export_cascade, export_controller

    fmt = os.path.splitext(args.export)[1].lower().lstrip(".")
    design, plant, filters = target.design, target.plant, tuple(target.filters)  # issue 24/34: the loop filters
    b = target.setpoint_weight
    if fmt in ("c", "st", "xml"):  # issue 24 (xml: issue 36): the discrete controller as code (prsa_ctrl.io.codegen)
        from ..io.codegen import stage_code_export

        kw = ({} if b is None else {"setpoint_weight": b}) | ({"filters": filters} if filters else {})
        stage_code_export(outputs, args.export, design, plant, real=args.export_real, **kw)
        return
    if target.is_cascade:
        exported = export_cascade(design, plant, fmt=fmt, friction_table_speed_rad_s=target.friction_table_speed_rad_s)
    else:
        exported = export_controller(design, plant, fmt=fmt, setpoint_weight=b, design=dict(target.choice),
                                     **({"filters": filters} if filters else {}))
    if args.motor is not None or args.export_template is not None or args.rated_torque is not None:
        from ..io.driveparams import cli_export_data

        exported = cli_export_data(args, exported, design, plant, filters=filters)
    text = dumps(exported, fmt)
    outputs.stage(args.export, lambda tmp: tmp.write_text(text, encoding="utf-8"), "--export")


#: Seconds the up-front check of a ``--scheduler`` address may take in all (connection, Dask
#: handshake and identity: :func:`prsa_ctrl.studies.daskprobe.probe_scheduler`).
SCHEDULER_CONNECT_TIMEOUT_S = 5.0
_SCHEDULER_RE = re.compile(r"tcp://(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9._-]+)(?::(\d+))?")


def _scheduler_address(text: str) -> tuple[str, int] | None:
    """``--scheduler`` checked before any work: ``None`` for ``local``, else ``(host, port)``
    of ``tcp://HOST:PORT`` (port 1..65535). TLS (``tls://``) needs a security configuration
    (certificates) the command does not take; any other form is refused.

    Raises
    ------
    UsageError
        One line naming ``--scheduler`` and the text as typed.
    """
    if text == "local":
        return None
    expected = "expected 'local' or tcp://HOST:PORT, e.g. tcp://127.0.0.1:8786"
    if text.startswith("tls://"):
        raise UsageError(f"--scheduler {text!r}: a TLS scheduler needs certificates (a Dask security "
                          f"configuration) that prsa-tune does not take; {expected}")
    m = _SCHEDULER_RE.fullmatch(text)
    if m is None:
        raise UsageError(f"--scheduler {text!r}: {expected}")
    if m.group(2) is None:
        raise UsageError(f"--scheduler {text!r}: no port; {expected}")
    port = int(m.group(2))
    if not 1 <= port <= 65535:
        raise UsageError(f"--scheduler {text!r}: port {m.group(2)} out of range; expected a TCP port 1..65535")
    return m.group(1).strip("[]"), port


def _probe_scheduler(text: str, host: str, port: int) -> None:
    """Check that a Dask scheduler answers at the address (connection, Dask handshake, identity:
    :func:`prsa_ctrl.studies.daskprobe.probe_scheduler`), all within
    ``SCHEDULER_CONNECT_TIMEOUT_S``, so that an unreachable address, or one where something else
    listens, stops the run before the tuning, not after it (or never)."""
    from ..studies.daskprobe import SchedulerProbeError, probe_scheduler

    timeout = SCHEDULER_CONNECT_TIMEOUT_S
    try:
        probe_scheduler(host, port, timeout)
    except SchedulerProbeError as exc:
        raise UsageError(f"--scheduler {text!r}: not a Dask scheduler / no answer at {host}:{port} within "
                          f"{timeout:g} s: {exc}; expected the address of a running Dask scheduler (dask "
                          "scheduler --host HOST --port PORT), or 'local'") from None


def _publish_report_plots(run: Run, rep, directory: str, inputs: Sequence[str], outputs=None,
                          frequency_unit: str = DEFAULT_FREQUENCY_UNIT) -> list[Path]:
    """Render the standard plots into a private staging folder, then stage each in the run's
    output transaction for ``directory`` (created only now, and taken back if this fails)."""
    return staged(run, lambda staging: loop_plots.write_standard_plots(rep, staging, frequency_unit), directory, inputs,
                  outputs)


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
