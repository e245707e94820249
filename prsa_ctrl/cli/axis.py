"""``prsa-fit`` for logs described by ``--log-format`` (linear axes in load coordinates).

``prsa-fit LOG... --log-format FORMAT.toml --out FITTED.toml [--json FIT.json] [--plant BASE.toml]
[--holdout FRACTION] [--plots DIR]``
    Fit a ``linear-axis`` plant (:mod:`prsa_ctrl.identification.axis`) on the logs; with ``--holdout F`` the
    last fraction ``F`` of each log is left out of the fit and replayed afterwards (reported under
    ``holdout`` in the JSON).

``prsa-fit --validate PLANT.toml LOG... [--log-format FORMAT.toml] [--json R.json] [--traces T.csv]
[--plots DIR]``
    Replay each log through the plant (closed loop from the reference when the log describes its
    controller, with the log's test signal added at the drive input; open loop from the logged
    command otherwise) and report, per log, ``100 ||y - y_sim|| / ||y||`` of position, velocity
    and force, and the fit %. Without ``--log-format`` a log must be a CSV file with the standard
    columns (:data:`prsa_ctrl.identification.logformat.DEFAULT_CSV_FORMAT`), replayed open loop.

Reached from :func:`prsa_ctrl.cli.fit.main` when ``--log-format`` is given or ``--validate`` names
a ``.toml`` plant, except for a fit in motor coordinates (:func:`motor_log_mode`: the log
description says ``axis = "rotary"`` or ``--plant`` names a screw-driven plant): that one is the
plant fit of :func:`prsa_ctrl.cli.fit.main` on the described logs (:func:`motor_records`), a log in
load coordinates converted with the plant's lead. Exit codes: 0 success, 2 bad input (one line naming the value, nothing
written), 3 the fit did not converge or its plant does not explain the logs (validation,
:mod:`prsa_ctrl.identification.axisvalidation`: no plant file unless ``--force``).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Sequence

from ..options import MOTOR_COORDINATES  # re-exported (coordinates of every plant but a linear axis)
from ..reporttext import axis_validation_lines
from .common import Parser, Run, UsageError, echo, progress

__all__ = ["wants_axis_mode", "run", "motor_log_mode", "motor_records", "MOTOR_COORDINATES"]


def _mode_flags(argv: Sequence[str]) -> argparse.Namespace:
    """The flags that choose ``prsa-fit``'s mode, read by argparse before the mode's own parser
    (``--log-format``, ``--plant``, ``--validate``; their exact names, every other argument left
    to that parser, which reports any error): ``None`` when not given, ``""`` for a flag given
    without its value."""
    p = Parser(add_help=False, allow_abbrev=False)
    p.add_argument("--log-format", nargs="?", const="")
    p.add_argument("--plant", nargs="?", const="")
    p.add_argument("--validate", nargs="*")
    try:
        return p.parse_known_args(list(argv))[0]
    except UsageError:  # the mode's own parser reports it
        return argparse.Namespace(log_format=None, plant=None, validate=None)


def wants_axis_mode(argv: Sequence[str]) -> bool:
    """True when the arguments ask for a described log (``--log-format``) or validate a plant file."""
    m = _mode_flags(argv)
    return m.log_format is not None or bool(m.validate and m.validate[0].lower().endswith(".toml"))


def motor_log_mode(argv: Sequence[str]) -> bool:
    """True when described logs (``--log-format``) are to be fitted in motor coordinates: the
    description says ``axis = "rotary"``, or ``--plant`` names a plant that is not a linear axis
    (a ball, roller or inverted roller screw: the plant works in rad and N m). A description or
    plant that cannot be read gives False (the linear-axis path then reports it, one line)."""
    import tomllib
    import warnings

    from ..plant.plantfile import load_plant

    m = _mode_flags(argv)
    fmt, plant = m.log_format, m.plant
    if not fmt or m.validate is not None:
        return False
    try:
        if tomllib.loads(Path(fmt).read_text(encoding="utf-8-sig")).get("axis", "linear") == "rotary":
            return True
        if not plant:
            return False
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return load_plant(plant).mechanism != "linear-axis"
    except Exception:  # noqa: BLE001 -- any unreadable input: the linear-axis path names it
        return False


def motor_records(args, plant) -> tuple[list, list, str, dict]:
    """The described logs of a motor-coordinate fit (``prsa-fit LOG... --log-format F --plant P``).

    Returns ``(records, validate, command_logged, coordinates)``: the records in the plant's
    motor coordinates (:func:`prsa_ctrl.identification.logformat.load_motor_record`), the command
    convention (the description's ``[command] logged``; a ``--command-logged`` that disagrees is
    refused) and, per log, the coordinates it was written in and how it was converted.
    """
    from ..identification.logformat import MOTOR_CONVENTION, load_log_format, load_motor_record

    for flag, given in (("--columns", args.columns), ("--torque-constant", args.torque_constant),
                        ("--load", args.load)):  # (an --frf file beside described logs is its own input)
        if given is not None:  # (a load of 0 N or an empty map is given too)
            raise UsageError(f"{flag} with --log-format {args.log_format}; expected the log description to say "
                             "which column holds what, in which unit")
    fmt = load_log_format(args.log_format)
    logged = MOTOR_CONVENTION[fmt.doc["command"].get("logged", "as-computed")]
    if args.command_logged is not None and args.command_logged != logged:
        raise UsageError(f"--command-logged {args.command_logged} with --log-format {args.log_format}, whose [command] "
                         f"logged is {fmt.doc['command'].get('logged', 'as-computed (default)')!r}; expected one of them")
    linear = fmt.doc.get("axis", "linear") == "linear"
    how = (f"load (position m, force N), converted with the lead {plant.lead_per_rad:.9g} m/rad: angle = position / "
           "lead, torque = force x lead" if linear else MOTOR_COORDINATES)
    records = [load_motor_record(p, fmt, plant)[0] for p in args.data]
    validate = [load_motor_record(p, fmt, plant)[0] for p in args.validate]
    return records, validate, logged, {r.name: how for r in (*records, *validate)}


def _fraction(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a number in (0, 0.9)") from None
    if not 0 < v < 0.9:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a number in (0, 0.9)")
    return v


def _parser() -> argparse.ArgumentParser:
    p = Parser(prog="prsa-fit", flag_first=True, description="Fit or validate a linear-axis plant on logs described by --log-format.",
                allow_abbrev=False)
    p.add_argument("data", nargs="*", metavar="LOG", help="logs (CSV or MATLAB .mat) to fit")
    p.add_argument("--log-format", metavar="FORMAT.toml", help="log description (prsa_ctrl.identification.logformat)")
    p.add_argument("--validate", nargs="+", metavar="PLANT.toml LOG", help="a linear-axis plant file, then the logs "
                   "to replay through it")
    p.add_argument("--out", metavar="PATH", help="fitted plant file (.toml)")
    p.add_argument("--json", metavar="PATH", help="JSON report")
    p.add_argument("--plant", metavar="BASE.toml", help="base linear-axis plant: values the fit does not estimate")
    p.add_argument("--holdout", type=_fraction, metavar="FRACTION", help="leave the last FRACTION of each log out "
                   "of the fit and replay it afterwards")
    p.add_argument("--traces", metavar="T.csv", help="with --validate: measured and simulated position and force "
                   "per sample")
    p.add_argument("--plots", metavar="DIR", help="overlay figures (PNG) of each replay and of its frequency "
                   "response beside the log's (Hz)")
    p.add_argument("--fidelity", choices=("rigid", "compliant"), default="rigid", help="rigid: one moving mass "
                   "(default); compliant: the two-mass axis (motor side, load mass, stiffness, damping) fitted on the "
                   "closed-loop replay; either is validated: exit 3 and no plant file when it does not explain the logs")
    p.add_argument("--frf", metavar="FRF.csv", help="with --fidelity compliant: a measured frequency response force -> "
                   "speed ((m/s)/N) whose two-mass fit starts the second mass (default: the logs' own, through their "
                   "test signal)")
    p.add_argument("--force", action="store_true", help="write the plant file even when it does not explain the logs "
                   "(its header says so; the exit code stays 3)")
    p.add_argument("--verbose", action="store_true", help="a progress line on stderr when the work starts")
    return p


def run(argv: Sequence[str], verbose: bool = False, check=None, parsed=None) -> int:
    """Entry point for the described-log modes; returns the exit code (Ctrl-C raises
    ``KeyboardInterrupt``: :func:`prsa_ctrl.cli.fit.main` runs in
    :func:`prsa_ctrl.cli.common.invoke`, which turns it into one line and exit 130).
    ``verbose``: a progress line on stderr when the work starts; ``check``: called before an
    error is reported (:meth:`prsa_ctrl.cli.common.Run.check`: an error that follows a Ctrl-C,
    e.g. a library that swallowed the ``KeyboardInterrupt``, is the interrupt); ``parsed``: called
    with the parsed arguments before any work (``prsa-fit`` notes the outputs it may take back)."""
    from ..identification.axis import AxisFitError, AxisPlantError
    from ..errors import SimulationError
    from ..identification.logformat import LogFormatError
    from ..io.output import OutputError

    try:
        args = _parser().parse_args(list(argv))
        if parsed is not None:
            parsed(args)
        progress(Run("prsa-fit"), verbose or args.verbose, "validating" if args.validate else "fitting")
        if args.validate:
            return _validate(args)
        return _fit(args)
    except (UsageError, argparse.ArgumentTypeError, LogFormatError, AxisPlantError, OutputError, ValueError) as exc:
        (check or _no_check)()
        echo(f"prsa-fit: error: {exc}", file=sys.stderr)
        return 2
    except (AxisFitError, SimulationError) as exc:
        (check or _no_check)()
        echo(f"prsa-fit: {exc}", file=sys.stderr)
        return 3


def _no_check() -> None:
    """No interrupt check (:func:`run` called without one)."""


def _load_logs(args, paths: Sequence[str]):
    from ..identification.logformat import DEFAULT_CSV_FORMAT, load_axis_log, load_log_format

    if not args.log_format:
        other = [p for p in paths if not p.lower().endswith(".csv")]
        if other:
            raise UsageError(f"{other[0]}: no --log-format; expected --log-format FORMAT.toml describing the log's "
                              "variables, units and controller (only a CSV log with the standard columns time_s, "
                              "position_m, force_n needs none)")
        fmt = DEFAULT_CSV_FORMAT
    else:
        fmt = load_log_format(args.log_format)
    return fmt, [load_axis_log(p, fmt) for p in paths]


def _check(outs: dict[str, str | None], inputs: Sequence[str], plots: str | None) -> None:
    from ..io.output import check_directory, check_distinct, check_writable

    outs = {k: v for k, v in outs.items() if v is not None}
    check_distinct({**outs, **({"--plots": plots} if plots else {})})
    for flag, path in outs.items():
        check_writable(path, inputs=inputs, flag=flag)
    if plots is not None:
        check_directory(plots, "--plots")


def _write(files: dict[str, tuple[str, str]], inputs: Sequence[str]) -> None:
    from ..io.output import write_text

    for path, (flag, text) in files.items():
        write_text(path, text, inputs=inputs, flag=flag)


def _json(obj) -> str:
    from ..io.output import json_safe

    return json.dumps(json_safe(obj), indent=2) + "\n"


def _base_plant(args, logs):
    """The base plant: ``--plant`` (a linear-axis plant file) or one built from what the logs say
    (:func:`prsa_ctrl.identification.calibrate_axis.axis_base_plant`, the app's too). Returns
    ``(plant, warnings)``."""
    from ..identification.calibrate_axis import axis_base_plant

    return axis_base_plant(logs, args.log_format, args.plant)


def _fit(args) -> int:
    from ..identification.axis import axis_plant_toml, fit_linear_axis

    if args.traces:
        raise UsageError(f"--traces {args.traces!r} without --validate; expected it with --validate PLANT.toml LOG")
    if args.frf and args.fidelity != "compliant":
        raise UsageError(f"--frf with --fidelity {args.fidelity}; expected it with --fidelity compliant (the "
                         "two-mass fit, started from the response)")
    if not args.data:
        raise UsageError("no log; expected prsa-fit LOG... --log-format FORMAT.toml --out FITTED.toml")
    if not args.out:
        raise UsageError("no --out; expected --out FITTED.toml for the fitted plant")
    if not args.log_format:
        raise UsageError(f"--log-format {args.log_format!r}: expected a log description FORMAT.toml to fit with")
    inputs = [*args.data, args.log_format or "", *([args.plant] if args.plant else []), *([args.frf] if args.frf else [])]
    _check({"--out": args.out, "--json": args.json}, inputs, args.plots)
    fmt, logs = _load_logs(args, args.data)
    base, base_notes = _base_plant(args, logs)
    fit_logs, held = logs, []
    if args.holdout:
        from ..identification.data import MIN_SAMPLES

        fit_logs, held = [], []
        for lg in logs:
            cut = int(round(lg.n * (1 - args.holdout)))
            if min(cut, lg.n - cut) < MIN_SAMPLES:
                raise UsageError(f"--holdout {args.holdout:g}: {lg.name} has "
                                 f"{lg.n} samples, which leaves {lg.n - cut} held out and {cut} to fit; expected a "
                                 f"fraction that leaves at least {MIN_SAMPLES} samples in each part")
            fit_logs.append(lg.window(0, cut))
            held.append(lg.window(cut, lg.n))
    from ..identification.axisvalidation import refusal_line

    if args.fidelity == "compliant":
        from ..identification.axiscompliant import fit_two_mass_axis

        result = fit_two_mass_axis(fit_logs, base, frf=_axis_frf(args.frf) if args.frf else None,
                                   name=Path(args.out).stem)
    else:
        result = fit_linear_axis(fit_logs, base, name=Path(args.out).stem)
    failure = refusal_line(result)
    from ..identification.calibrate_axis import axis_outputs  # the app's composer too

    header = (f"prsa-fit --force: NOT VALIDATED, this plant does not explain the data it was fitted to: "
              f"{result.validation['diagnosis']}", str(result.validation["reasons"][0])) if failure else ()
    text = axis_plant_toml(result.plant, header=header)
    report, lines = axis_outputs(result, fit_logs, base_notes, held, args.holdout)
    files = {args.out: ("--out", text)} if not failure or args.force else {}
    if args.json:
        files[args.json] = ("--json", _json({k: v for k, v in report.items() if k != "fit_percent"}))
    plots = _plots(args.plots, result.replays, inputs) if args.plots else []
    _write(files, inputs)
    for line in lines:
        echo(line)
    written = [*files, *plots]
    echo(("wrote " + ", ".join(written)) if written else "wrote no file")
    if failure:
        echo(f"prsa-fit: {failure} " + ("(--force: the plant file was written all the same)" if args.force else
                                        "(no plant file written; --force writes it)"), file=sys.stderr)
        return 3
    return 0


def _axis_frf(path: str):
    """``--frf`` of a linear axis: the response force -> speed ((m/s)/N: the file's (rad/s)/(N m)
    columns at 1 m per rad, :func:`prsa_ctrl.identification.data.load_frf`)."""
    from ..identification.data import load_frf

    return load_frf(path, speed_rad_s=0.0, load_n=0.0)


def _validate(args) -> int:
    from ..identification.axis import COORDINATES, load_axis_plant, replay_axis

    plant_path, *paths = args.validate
    paths = [*paths, *args.data]
    if args.out:
        raise UsageError(f"--out {args.out!r} with --validate; expected --json/--traces/--plots for a validation")
    if args.holdout or args.plant or args.frf or args.force or args.fidelity != "rigid":
        raise UsageError("--holdout/--plant/--frf/--force/--fidelity with --validate; expected them only when fitting "
                         "(the plant file says whether it is a two-mass axis)")
    if not paths:
        raise UsageError(f"--validate {plant_path}: no log; expected --validate PLANT.toml LOG...")
    if args.traces and len(paths) > 1:
        raise UsageError(f"--traces {args.traces!r} with {len(paths)} logs; expected one log (one row per sample)")
    inputs = [plant_path, *paths, args.log_format or ""]
    _check({"--json": args.json, "--traces": args.traces}, inputs, args.plots)
    plant = load_axis_plant(plant_path)
    fmt, logs = _load_logs(args, paths)
    replays = [replay_axis(plant, lg) for lg in logs]
    files = {}
    if args.json:
        files[args.json] = ("--json", _json({"plant": plant_path, "mechanism": "linear-axis", "coordinates": COORDINATES,
                                                 "replay": [r.as_dict() for r in replays]}))
    if args.traces:
        files[args.traces] = ("--traces", replays[0].traces_csv())
    plots = _plots(args.plots, replays, inputs) if args.plots else []
    _write(files, inputs)
    for line in axis_validation_lines([(r.as_dict(), r.closed_loop) for r in replays], COORDINATES):
        echo(line)
    if files or plots:
        echo("wrote " + ", ".join([*files, *plots]))
    return 0


def _plots(directory: str, replays, inputs) -> list[str]:
    """Overlay figures, per replay: ``replay-*.png`` (:func:`prsa_ctrl.plots.fit.axis_replay_figure`:
    tracking error, velocity, force, measured vs replayed, and the velocity residual) and
    ``response-*.png`` (:func:`prsa_ctrl.plots.fit.axis_response_figure`: the log's frequency
    response beside the replay's on a Hz axis, their residual and the coherence; not for a log
    under 256 samples)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from ..io.output import make_directory, write_file
    from ..plots.fit import axis_replay_figure, axis_response_figure

    make_directory(directory, "--plots")
    out = []
    for i, r in enumerate(replays):
        stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", Path(r.name).name)
        for kind, make in (("replay", axis_replay_figure), ("response", axis_response_figure)):
            fig = make(r)
            if fig is None:
                continue
            path = Path(directory) / f"{kind}-{i + 1}-{stem}.png"
            try:
                write_file(path, lambda tmp, fig=fig: fig.savefig(tmp, format="png", dpi=110), inputs, "--plots")
            finally:
                plt.close(fig)
            out.append(str(path))
    return out
