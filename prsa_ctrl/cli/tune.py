"""``prsa-tune``: tune a scene's loop, verify it on the nonlinear simulator, report, export.

One path for every scene (:func:`main`): parse the flags, load the plant and the scene, check
them and the output paths, tune and verify, write the outputs (``--json``, ``--export``,
``--plots``, all or none), print the report. Each step dispatches on the scene's kind:

* a speed-loop scene (load steps or a duty cycle, :class:`~prsa_ctrl.studies.scene.Scene`):
  the speed PI/PID (:func:`prsa_ctrl.studies.autotune.tune_actuator`), compared with baselines,
  with the robust study and the Monte-Carlo yield when asked;
* a move scene (``[move]`` section, :class:`~prsa_ctrl.studies.movescene.MoveScene`): the
  position loop over the speed loop, tuned sequentially and jointly and verified
  (:func:`prsa_ctrl.studies.move.tune_move`); flags that do not apply to it
  (:data:`MOVE_FLAGS` lists those that do) are refused in one line.

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
from typing import Any, Sequence  # noqa: E402

from .._lazy import module  # noqa: E402
from ..errors import GeometryWarning  # noqa: E402
from ..io.output import OutputError, Transaction, check_directory, check_distinct, check_writable, json_safe  # noqa: E402
from ..options import (CONTROLLERS, DEFAULT_FREQUENCY_UNIT, ESTIMATORS, FREQUENCY_UNITS, MS_MAX_DEFAULT, OBJECTIVES,  # noqa: E402
                       PEAK_BOUND_RANGE)
from ..plant.plantfile import load_plant  # noqa: E402
from ..studies.movescene import MoveScene  # noqa: E402
from ..studies.scene import load_scene  # noqa: E402
from ..studies.scenefile import is_move_scene  # noqa: E402
from .common import (EXIT_BAD_INPUT, EXIT_INTERRUPTED, EXIT_NUMERICAL, EXIT_OK, Parser, Run, UsageError,  # noqa: E402
                     commit, describe_failure, echo, integer, invoke, native_output, number, path_text, progress,
                     report_failure, show_notes, staged, status_says_interrupted, write_json_atomic)
from .inputs import VALUE_FLAGS, input_files, load_and_override, parse_load_step, scene_flags  # noqa: E402
from .plot import build_plot_parser, plot_main  # noqa: E402
from .report import format_friction_ff, format_move_report, format_report, format_robust  # noqa: E402

#: The figures modules (matplotlib) are imported when a figure is drawn.
loop_plots = module("prsa_ctrl.plots.loop")
move_plots = module("prsa_ctrl.plots.move")

__all__ = ["main", "plot_main", "parse_load_step", "write_json_atomic", "format_report", "build_parser",
           "build_plot_parser", "EXIT_OK", "EXIT_BAD_INPUT", "EXIT_NUMERICAL", "EXIT_INTERRUPTED", "MOVE_FLAGS",
           "WORKERS_MAX", "SCHEDULER_CONNECT_TIMEOUT_S"]

WORKERS_MAX = 64
#: ``prsa-tune`` options a move scene honours; every other option given is refused (exit 2).
MOVE_FLAGS = ("plant", "scene", "json", "export", "plots", "quiet", "verbose", "export_real", "export_template", "motor",
              "rated_torque", "friction_ff")
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
        _check_outputs(args, scene, inputs)
        notes.extend(caught)
    run.check()
    move = isinstance(scene, MoveScene)
    if not move and args.tune_filter is not None:
        from ..studies.scenetunefilter import check_tune_filter

        check_tune_filter(scene, args.tune_filter)
    native: list[str] = []
    what = (f"tuning the cascade of {scene.name}" if move else
            f"tuning {plant.name} on the {scene.name} duty cycle" if scene.is_profile else
            f"tuning {plant.name} at {scene.setpoint_rpm:g} rpm, {scene.initial_load:g} N -> "
            f"{', '.join(f'{f:g}' for f in scene.final_loads)} N")
    if not move:
        progress(run, args.verbose, f"{what}: linearise, tune, verify ...")
    try:
        with warnings.catch_warnings(record=True) as caught, native_output(run, native):
            warnings.simplefilter("always")
            result = _tune(run, args, plant, scene)
            notes.extend(caught)
        run.check()
    except KeyboardInterrupt:
        raise
    except Exception as exc:  # noqa: BLE001 - translated into one line at this boundary
        return report_failure(run, exc, what, args.verbose)
    if not move:
        result["rep"].timing_s["process"] = time.perf_counter() - _T_START
        progress(run, args.verbose, "writing outputs")
    if args.export is not None and not move:  # before any output is written: all or nothing
        result["export"] = _export_choice(result["rep"], result["robust"])
        if result["export"][0] is None:
            run.say(f"{run.prog}: --export {args.export}: {result['export'][1]['why']}; nothing written")
            return EXIT_NUMERICAL if result["robust"] is not None else EXIT_BAD_INPUT
    outputs = Transaction(inputs)  # all outputs or none (issue 20, hostile 4 and 17)
    try:
        plot_files = _write_outputs(run, args, plant, scene, result, inputs, outputs)
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
        _print_report(args, plant, scene, overrides, result, plot_files)
    show_notes(run, notes, native, args.verbose, args.quiet)
    rep = result.get("rep")
    if rep is not None and rep.status != "ok" and not args.accept_unconverged:
        run.say(f"{run.prog}: the best design is flagged ({rep.status}); its numbers are reported above but "
                "are not a trustworthy design (use --accept-unconverged to exit 0)")
        return EXIT_NUMERICAL
    return EXIT_OK


# --- the steps, each for both kinds of scene -----------------------------------------------------

def _load(args, run: Run):
    """Plant and scene (with the command-line overrides of a speed-loop scene), checked against
    each other, and the overriding flags as typed."""
    if not is_move_scene(args.scene):
        return load_and_override(args, run)
    from ..studies.move import check_move_against_plant

    refused = _refused_flag(args, run)
    scene = load_scene(args.scene)
    if refused:
        raise UsageError(f"{refused} does not apply to a move scene ({scene.name}); expected only --plant, --json, "
                         "--export, --plots, --quiet and --verbose")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a move scene's run shows no plant notes
        plant = load_plant(args.plant)
    check_move_against_plant(scene, plant)
    return plant, scene, []


def _refused_flag(args, run: Run) -> str | None:
    """The first ``prsa-tune`` option given that a move scene does not honour, as typed."""
    raw = {a.split("=", 1)[0]: a.split("=", 1)[1] for a in run.argv if a.startswith("--") and "=" in a}
    for action in build_parser()._actions:
        if not action.option_strings or action.dest in MOVE_FLAGS or action.dest == "help":
            continue
        value = getattr(args, action.dest, action.default)
        if value is None or value is False or value == action.default:
            continue
        flag = action.option_strings[-1]
        return flag if value is True else f"{flag} {raw.get(flag, value)}"
    return None


def _check_outputs(args, scene, inputs: Sequence[str]) -> None:
    """Every output path and export option checked before the expensive work (the order of the
    checks, which decides the message when several fail, is each scene kind's own)."""
    move = isinstance(scene, MoveScene)

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
        if not move and scene.feedforward:
            raise UsageError(f"--export {args.export!r} with --feedforward: the drive export does not describe the "
                             "Kalman filter's load-torque feed-forward (kff > 0); expected --export without "
                             "--feedforward (or no --export)")

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

    def friction_ff() -> None:
        if args.friction_ff and not move:
            raise UsageError(f"--friction-ff does not apply to the speed-loop scene {scene.name}; expected a move "
                             "scene (the feed-forward acts from a motion profile's speed), e.g. --scene "
                             "paper-slow-reversal")

    def design_to_spec() -> None:
        if not getattr(args, "design_to_spec", False):
            return
        if move or getattr(scene, "is_profile", False):
            raise UsageError(f"--design-to-spec does not apply to the scene {scene.name}; expected a load-step scene "
                             "with a [spec] section")
        if not (getattr(scene, "robust", None) or {}).get("spec"):
            raise UsageError(f"--design-to-spec: the scene {scene.name} has no [spec] section; expected the bounds "
                             "to design to (e.g. [spec] peak_drop_rad_s = 12.0)")
        if args.monte_carlo == 0:
            raise UsageError("--design-to-spec with --monte-carlo 0; expected a sample count of the final check >= 1")
        from ..studies.designspec import SAMPLES_MAX
        from ..studies.montecarlo import scene_options

        # the final check's sample count, refused here rather than by the study after the robust tuning (was exit 3)
        if args.monte_carlo is not None and args.monte_carlo > SAMPLES_MAX:
            raise UsageError(f"--design-to-spec with --monte-carlo {args.monte_carlo}; expected a sample count of the "
                             f"final check in 1..{SAMPLES_MAX}")
        n_scene = scene_options(scene)["samples"]
        if args.monte_carlo is None and n_scene > SAMPLES_MAX:
            raise UsageError(f"--design-to-spec: the scene {scene.name} has [robust] monte_carlo = {n_scene}; expected "
                             f"a sample count of the final check in 1..{SAMPLES_MAX} (or --monte-carlo N)")

    if move:
        steps = (design_to_spec, suffix, distinct, json_path, export, drive_options, plots)
    else:
        steps = (friction_ff, design_to_spec, json_path, lambda: _check_scheduler(args, scene), suffix, export,
                 drive_options, plots, distinct)
    for step in steps:
        step()


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


def _tune(run: Run, args, plant, scene) -> dict:
    """Tune and verify: ``{"designs": [sequential, joint]}`` for a move scene, else ``{"rep":
    ActuatorTuning, "robust": RobustTuning or None, "mc": MonteCarloReport or None}``."""
    with warnings.catch_warnings():
        if isinstance(scene, MoveScene):
            warnings.simplefilter("ignore")  # as the cascade always ran: no notes
            from ..studies.move import tune_move

            designs = tune_move(plant, scene, lambda text: progress(run, args.verbose, text))
            if not args.friction_ff:
                return {"designs": designs}
            from ..studies.move import friction_feedforward_effect  # issue 24: friction feed-forward

            progress(run, args.verbose, "verifying the joint design with the friction feed-forward ...")
            return {"designs": designs, "friction_ff": friction_feedforward_effect(designs[1], plant, scene)}
        warnings.simplefilter("ignore", GeometryWarning)
        from ..studies.autotune import tune_actuator

        ft = None
        if args.tune_filter is not None:  # issue 24: a filter tuned with the gains joins the scene's
            from ..studies.scenetunefilter import tune_scene_filter

            progress(run, args.verbose, f"tuning a {args.tune_filter} with the gains ...")
            ft = tune_scene_filter(plant, scene, args.tune_filter)
            scene = ft.scene
            run.check()
        rep = tune_actuator(plant, scene, workers=args.workers)
        run.check()
        if status_says_interrupted(rep.as_dict()):
            raise KeyboardInterrupt
        if getattr(args, "design_to_spec", False):
            robust_rep, mc, dts = _design_to_spec(run, args, plant, rep)
            return {"rep": rep, "robust": robust_rep, "mc": mc, "filter_tuning": ft, "design_to_spec": dts}
        robust_rep, mc = _robust_and_monte_carlo(run, args, plant, rep)
    return {"rep": rep, "robust": robust_rep, "mc": mc, "filter_tuning": ft}


def _write_outputs(run: Run, args, plant, scene, result: dict, inputs: Sequence[str], outputs) -> list[Path]:
    """Stage ``--plots``, ``--json`` and ``--export`` in the run's transaction and commit them."""
    move = isinstance(scene, MoveScene)
    plot_files: list[Path] = []
    if args.plots is not None:
        if move:
            progress(run, args.verbose, "writing the figures ...")
            designs = result["designs"]
            plot_files = staged(run, lambda staging: move_plots.write_move_plots(plant, scene, designs, staging),
                                args.plots, inputs, outputs)
        else:
            plot_files = _publish_report_plots(run, result["rep"], args.plots, inputs, outputs, args.frequency_unit)
    if args.json is not None:
        run.check()
        write_json_atomic(args.json, _json_report(scene, plant, result), inputs, transaction=outputs)
    if args.export is not None:
        _stage_export(args, plant, scene, result, outputs)
    commit(run, outputs)
    return plot_files


def _coordinates(plant) -> str:
    """The coordinates a plant's numbers are in, as the JSON report states them."""
    from ..identification.axis import COORDINATES
    from .axis import MOTOR_COORDINATES

    if plant.mechanism == "linear-axis":
        return f"{COORDINATES}: read rad as m, rad/s as m/s, N m as N, N m s/rad as N s/m (1 m of travel per radian)"
    return MOTOR_COORDINATES


def _json_report(scene, plant, result: dict) -> dict:
    """The ``--json`` report of either kind of scene."""
    if isinstance(scene, MoveScene):
        seq, joint = result["designs"]
        out = {"plant": plant.name, "scene": scene.name, "sequential": seq.as_dict(), "joint": joint.as_dict()}
        if "friction_ff" in result:
            out["friction_feedforward"] = {k: v for k, v in result["friction_ff"].items() if k != "design"}
        return json_safe(out)
    rep, robust_rep, mc = result["rep"], result["robust"], result["mc"]
    data = rep.as_dict()
    data["coordinates"] = _coordinates(plant)
    data["timing_s"] = dict(rep.timing_s)
    _add_setpoint_weight(data, rep.scene)
    if robust_rep is not None:
        data["robust"] = robust_rep.as_dict()
        data["recommended"] = data["robust"]["recommended"]
    if mc is not None:
        data["monte_carlo"] = mc.as_dict()
    if result.get("design_to_spec") is not None:
        data["design_to_spec"] = result["design_to_spec"].as_dict()
    if result.get("filter_tuning") is not None:
        data["filter_tuning"] = json_safe(result["filter_tuning"].as_dict())
    return data


def _stage_export(args, plant, scene, result: dict, outputs) -> None:
    """Stage ``--export``: the speed loop's chosen design, or a move scene's joint cascade, as a
    drive file (JSON/TOML, with ``--motor``/``--export-template`` terms) or as code (C, ST)."""
    from ..io.export import dumps, export_cascade, export_controller

    fmt = os.path.splitext(args.export)[1].lower().lstrip(".")
    filters: tuple = ()  # issue 24: the scene's loop filters (and a tuned one) go with the gains
    if isinstance(scene, MoveScene):
        design, b = result["designs"][1], None
        if "friction_ff" in result:  # the joint design with the friction feed-forward in its position loop
            design = result["friction_ff"]["design"]
        filters = tuple(design.filters)  # issue 34: the move scene's fixed filters, tuned around
    else:
        design, b, plant = result["export"][0], _setpoint_weight(result["rep"].scene), result["rep"].plant
        filters = result["rep"].scene.filters
    if fmt in ("c", "st", "xml"):  # issue 24 (xml: issue 36): the discrete controller as code (prsa_ctrl.io.codegen)
        from ..io.codegen import stage_code_export

        kw = ({} if b is None else {"setpoint_weight": b}) | ({"filters": filters} if filters else {})
        stage_code_export(outputs, args.export, design, plant, real=args.export_real, **kw)
        return
    if b is None:
        exported = export_cascade(design, plant, fmt=fmt,
                                  friction_table_speed_rad_s=scene.max_speed_m_s / plant.lead_per_rad)
    else:
        exported = export_controller(design, plant, fmt=fmt, setpoint_weight=b, design=result["export"][1],
                                     **({"filters": filters} if filters else {}))
    if args.motor is not None or args.export_template is not None or args.rated_torque is not None:
        from ..io.driveparams import cli_export_data

        exported = cli_export_data(args, exported, design, plant, filters=filters)
    text = dumps(exported, fmt)
    outputs.stage(args.export, lambda tmp: tmp.write_text(text, encoding="utf-8"), "--export")


def _print_report(args, plant, scene, overrides: Sequence[str], result: dict, plot_files: list[Path]) -> None:
    """The text report and the lines naming the files written."""
    if isinstance(scene, MoveScene):
        echo(format_move_report(plant, scene, result["designs"], "prsa-tune"))
        if "friction_ff" in result:
            echo(format_friction_ff(result["friction_ff"], scene.fidelity))
        if args.json is not None:
            echo(f"JSON report: {args.json}")
        if args.export is not None:
            echo(f"drive export: {args.export}")
        if plot_files:
            echo(f"plots: {', '.join(str(p) for p in plot_files)}")
        return
    echo(format_report(result["rep"], overrides))
    if result.get("filter_tuning") is not None:
        echo("\n".join(result["filter_tuning"].lines()))
    if result["robust"] is not None:
        echo(format_robust(result["robust"]))
    if result["mc"] is not None:
        from ..studies.montecarlo import format_report as format_mc

        echo(format_mc(result["mc"]))
    if args.json is not None:
        echo(f"JSON report: {args.json}")
    if args.plots is not None:
        echo(f"plots: {', '.join(str(p) for p in plot_files)}")
    if args.export is not None:
        export_design = result["export"][1]
        echo(f"drive export: {args.export} holds the design {export_design['name']!r}, "
             f"{export_design['chosen_by']}")


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


def _robust_and_monte_carlo(run: Run, args, plant, rep):
    """The robust design (``--robust`` or a scene ``[robust]`` section) and the Monte-Carlo
    verification (``--monte-carlo N`` or the scene's setting) of the report's designs."""
    from ..studies.montecarlo import run_monte_carlo, scene_options
    from ..studies.autotune import default_workers

    scene = rep.scene
    opts = scene_options(scene)
    has_robust = bool((getattr(scene, "robust", None) or {}).get("robust"))
    robust_rep = None
    if args.robust or has_robust:
        from ..studies.scenerobust import tune_robust_actuator

        progress(run, args.verbose, "robust tuning over the scenario models ...")
        robust_rep = tune_robust_actuator(plant, scene)
        run.check()
    n = args.monte_carlo if args.monte_carlo is not None else opts["samples"]
    if not n:
        return robust_rep, None
    designs = {rep.best.name: rep.best.pid}
    if robust_rep is not None:
        designs = {"nominal design": robust_rep.nominal, "robust design": robust_rep.robust}
        _add_design(designs, rep.best.name, rep.best.pid)
        # every design the run tuned: the recommendation ranks them all on the same samples
        for c in getattr(rep, "candidates", ()) or ():
            if c.pid.kff == 0:
                _add_design(designs, c.name, c.pid)
    for b in rep.baselines:
        _add_design(designs, b.name, b.pid)
    seed = args.seed if args.seed is not None else opts["seed"]
    progress(run, args.verbose, f"Monte Carlo: {n} samples of {len(designs)} designs ...")
    # Like the verification: in parallel on the machine's cores unless --workers says otherwise.
    mc = run_monte_carlo(plant, scene, designs, n, seed=seed, scheduler=args.scheduler,
                         workers=args.workers or default_workers(), quiet=args.quiet)
    if robust_rep is not None:
        others = {k: v for k, v in designs.items() if k not in ("nominal design", "robust design")}
        target = ((getattr(scene, "robust", None) or {}).get("spec_yield") or {}).get("yield")
        robust_rep = robust_rep.with_recommendation(mc, others=others, target=target)
    return robust_rep, mc


def _design_to_spec(run: Run, args, plant, rep):
    """``--design-to-spec``: the robust study, then :func:`prsa_ctrl.studies.designspec.design_to_spec`
    over its family plus the run's designs; the chosen design is the study's recommendation and
    the Monte-Carlo report is the chosen design's on fresh samples."""
    from dataclasses import replace

    from ..errors import SceneError
    from ..studies.autotune import default_workers
    from ..studies.designspec import design_to_spec
    from ..studies.montecarlo import scene_options
    from ..studies.scenerobust import tune_robust_actuator

    scene = rep.scene
    if not (getattr(scene, "robust", None) or {}).get("spec"):
        raise SceneError(f"{scene.origin}: --design-to-spec needs a [spec] section; expected the bounds to design to")
    opts = scene_options(scene)
    n = args.monte_carlo or opts["samples"] or 200
    seed = args.seed if args.seed is not None else opts["seed"]
    progress(run, args.verbose, "robust tuning over the scenario models ...")
    rr = tune_robust_actuator(plant, scene)
    run.check()
    extra = {"nominal design": rr.nominal, "robust design": rr.robust}
    for d in (rep.best, *(getattr(rep, "candidates", ()) or ()), *rep.baselines):
        _add_design(extra, d.name, d.pid)
    n_search = min(64, n)
    progress(run, args.verbose, f"design to the spec: proposals on {n_search} common samples, the chosen one on "
                                f"{n} fresh samples ...")
    dts = design_to_spec(plant, scene, n_search=n_search, n_final=n, seed=seed, extra=extra,
                         workers=args.workers or default_workers(), quiet=args.quiet, robust=rr)
    s = dts.search
    d = dts.decide or s  # the decision among the (near-)maximal designs on more samples, where it ran
    nd = d["rows"][0]["samples"] if dts.decide and d.get("rows") else n_search
    basis = (f"design to the spec: {len(dts.designs)} designs screened on {n_search} common Monte-Carlo samples "
             f"(seed {dts.search_seed})" + (f", the {len(d['rows'])} of (near-)maximal yield decided on {nd} samples "
                                            "of the same seed" if dts.decide else "")
             + f"; yield on {n} fresh samples (seed {dts.final_seed})")
    rec = {"basis": basis, "table": s.get("rows", []), "rule": s.get("rule", ""),
           **{k: d[k] for k in ("target", "reached", "limit") if k in d}}
    if dts.decide:
        rec["decide_table"] = d.get("rows", [])
    fy = dts.final_yield
    if fy is None:
        rec.update(design=None, name=None, why=s.get("why", "no design chosen"))
    else:
        lo, hi = fy.ci95
        rec.update(design=dts.chosen, name=dts.chosen, gains=dts.pid.as_dict(), **{"yield": fy.yield_},
                   passed=fy.passed, samples=fy.n, yield_ci95=list(fy.ci95),
                   why=(f"on the {'decision' if dts.decide else 'search'} samples: {d['why']}; on {fy.n} fresh samples: "
                        f"yield {100 * fy.yield_:.1f} % "
                        f"({fy.passed}/{fy.n}), 95 % CI [{100 * lo:.1f}, {100 * hi:.1f}] %"))
    rr = replace(rr, others=dict(dts.designs), recommended=rec)
    return rr, dts.final, dts


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
        d = {"name": r.get("name") or f"{r['design']} design", "chosen_by": "recommended by the robust study",
             "why": r["why"],
             "basis": r["basis"]}
        if r.get("yield") is not None:
            d["yield"] = r["yield"]
        return robust_rep.design(r["design"]), d
    if rep.best.pid.kff != 0:
        return None, {"why": "the best design feeds the Kalman filter's load estimate forward (kff > 0), which the "
                             "drive export does not describe"}
    return rep.best.pid, {"name": rep.best.name, "chosen_by": "the tuned design (no robust study)"}


def _publish_report_plots(run: Run, rep, directory: str, inputs: Sequence[str], outputs=None,
                          frequency_unit: str = DEFAULT_FREQUENCY_UNIT) -> list[Path]:
    """Render the standard plots into a private staging folder, then stage each in the run's
    output transaction for ``directory`` (created only now, and taken back if this fails)."""
    return staged(run, lambda staging: loop_plots.write_standard_plots(rep, staging, frequency_unit), directory, inputs,
                  outputs)


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
