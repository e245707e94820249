"""``prsa-fit``: calibrate a plant file from measured drive data, or design the experiment.

``prsa-fit [DATA.csv ...] [--frf FRF.csv ...] --out MY.toml [--json REPORT.json] [--plots DIR]
[--frequency-unit Hz|rad/s]
[--plant BASE] [--fit KEY,...] [--fidelity rigid|compliant] [--validate OTHER.csv ...]
[--columns name=header,...] [--torque-constant KT] [--load N] [--frf-speed RAD_S] [--frf-load N]
[--frf-sample-time S] [--frf-band FMIN_HZ,FMAX_HZ] [--coherence-min C] [--delay-samples N] [--command-logged applied|computed] [--verbose]``

The command delay: by default the fit of time-domain records searches the whole-sample delay
between the logged command and its action (:func:`prsa_ctrl.identification.delay.search_delay`)
and writes ``drive.command_delay_samples`` (the delay less the computation delay of a command
logged ``computed``); ``--delay-samples N`` fixes it instead.

``prsa-fit --design multisine|chirp|steps --out excitation.csv [--duration S] [--sample-time S]
[--f-min HZ] [--f-max HZ] [--amplitude RAD_S] [--offset RAD_S]``

Validation (:mod:`prsa_ctrl.identification.validation`): every record is replayed through the
plant as written (prediction-error form: these logs describe no reference or controller), the
residuals' whiteness is reported and, with several records, each is replayed by the plant fitted
on the others. A plant that does not explain the data ends with exit 3, a one-line diagnosis
naming the most likely missing physics and no plant file (``--force`` writes it, its header
saying so; ``--json`` is written either way).

Exit codes: 0 success, 2 bad input (one line naming the value), 3 the fit did not converge or
the fitted plant does not explain the data, 130 interrupted (Ctrl-C: one line, the files and folders this run made are taken back).
Output and figure paths are checked before the fit, the way they will be written (two outputs
on one path, a symlink loop, a name too long are refused); every file is written atomically.
The base plant (``--plant``) is parsed and its fitted file's text checked before the fit too. Python warnings (e.g. the base plant's geometry note) are shown after the
result as one ``prsa-fit: note:`` line each; the geometry note of a built-in plant only with
``--verbose``, as in ``prsa-tune``.

Keys the data cannot inform keep the base plant's value and source in the written file
(:func:`prsa_ctrl.identification.timedomain.fit_plant`); the output names them and the JSON marks them
``"kept_base": true`` with the reason. The base file's ``[uncertainty]`` entries are kept (an
entry narrower than the fit's 95 % interval, or one that does not hold the fitted value, is
replaced by the fit's); ``--uncertainty-from-fit`` writes the fit's own for every fitted key.

An excitation design is a nut-speed setpoint: its peak ``|offset| + amplitude`` must stay within
:data:`DESIGN_MAX_SPEED_RAD_S` (the tuner's speed limit, ``prsa_ctrl.studies.scene.SETPOINT_MAX_RPM``).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import warnings
from pathlib import Path
from typing import Sequence

from ..errors import GeometryWarning, PlantFileError
from ..options import DEFAULT_FREQUENCY_UNIT, FREQUENCY_UNITS, SPEED_MAX_RPM, rad_s_to_rpm, rpm_to_rad_s
from ..identification.calibrate import FRF_COHERENCE_MIN_DEFAULT, FRF_SPEED_DEFAULT_RAD_S, MOTOR_COORDINATES
from .common import KeepTyped, Run, Parser, UsageError, echo, invoke, long_options, number, progress, typed_text

__all__ = ["main", "build_parser", "plant_toml", "DESIGN_MAX_SPEED_RAD_S", "new_outputs", "take_back", "FIT_VALUE_FLAGS"]

#: Largest nut speed an excitation design may reach, rad/s: ``|offset| + amplitude`` within the
#: speed range the tuner accepts (:data:`prsa_ctrl.studies.scene.SETPOINT_MAX_RPM`, 6000 rpm).
DESIGN_MAX_SPEED_RAD_S = rpm_to_rad_s(SPEED_MAX_RPM)


def _positive(flag: str):
    """Converter of a number flag > 0 (messages quote the text: ``--duration '-1': ...``)."""
    return number(flag, 0.0, what="a finite number > 0", lo_open=True, quoted=True, not_a_number="a number")


def _finite(flag: str):
    """Converter of a finite number flag."""
    return number(flag, what="a finite number", quoted=True, not_a_number="a number")


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="prsa-fit", flag_first=True, description="Fit a plant file to measured drive data (grey-box, with 95 % CIs), "
                "or write an excitation signal for the experiment.")
    p.add_argument("data", nargs="*", metavar="DATA.csv", help="time-domain records to fit")
    p.add_argument("--out", required=True, metavar="PATH", help="output plant .toml (or excitation .csv with --design)")
    p.add_argument("--json", metavar="PATH", help="JSON report")
    p.add_argument("--frf", nargs="+", default=[], metavar="FRF.csv", help="frequency responses torque command -> "
                   "nut speed (frequency_hz, magnitude_db, phase_deg[, coherence] or real, imag): fitted alone "
                   "without DATA.csv, otherwise used to validate the fit")
    p.add_argument("--frf-from-logs", default=None, metavar="KP,KI[,TAU_S]",
                   help="estimate the plant's frequency response from the DATA.csv closed-loop logs (joint "
                   "input-output method: the speed reference, given back by the drive's PI speed loop described "
                   "here, kp in N m s/rad, ki in N m/rad, the speed filter's time constant in s, default 0) and fit it "
                   "as --frf does, instead of the time-domain fit; --command-logged says how the log holds the command")
    p.add_argument("--speed-loop", default=None, metavar="KP,KI[,TAU_S]",
                   help="the drive's PI speed loop while logging DATA.csv (kp in N m s/rad, ki in N m/rad, the speed "
                   "filter's time constant in s, default 0): a --fidelity compliant fit without --frf starts from the "
                   "logs' own frequency response (joint input-output) where it shows an axial mode")
    p.add_argument("--frf-speed", action=KeepTyped, type=_finite("--frf-speed"), default=FRF_SPEED_DEFAULT_RAD_S,
                   metavar="RAD_S", help=f"nut speed during the FRF measurement, rad/s (default {FRF_SPEED_DEFAULT_RAD_S:g}); also the "
                   "speed a compliant fit's axial mode is reported at")
    p.add_argument("--frf-load", action=KeepTyped, type=_finite("--frf-load"), default=None, metavar="N",
                   help="axial load during the FRF measurement, N (default --load, else 0); also the load a compliant "
                   "fit's axial mode is reported at (the mode moves with the nut force)")
    p.add_argument("--frf-sample-time", type=number("--frf-sample-time", 0.0, what="a finite time >= 0 s",
                                                    quoted=True, not_a_number="a time in s"), default=None,
                   metavar="S", help="sample time of the drive that measured the --frf responses, s (default the "
                   "plant's sensor.sample_time_s: command held over a sample, speed the backward difference of the "
                   "angle); 0: a continuous-time response (e.g. computed from a model)")
    p.add_argument("--frf-band", default=None, metavar="FMIN_HZ,FMAX_HZ",
                   help="fit the --frf responses (alone, without --fit) on the points in this band only: the reduced-order "
                   "model of the band the loop uses; resonances outside it are named in the report and the plant's "
                   "sources, the tail of those above it is fitted as an upper residual and the current loop held at "
                   "the base value; fit %% and intervals are the band's")
    p.add_argument("--coherence-min", type=_finite("--coherence-min"), default=FRF_COHERENCE_MIN_DEFAULT,
                   metavar="C", help=f"FRF points with a lower coherence are dropped (default {FRF_COHERENCE_MIN_DEFAULT:g})")
    p.add_argument("--plots", metavar="DIR", help="write residual, overlay and Bode figures (PNG) into DIR "
                   "(created if missing)")
    p.add_argument("--frequency-unit", choices=tuple(FREQUENCY_UNITS), default=DEFAULT_FREQUENCY_UNIT,
                   help="unit of the frequency axes of the --plots Bode figures (default Hz; the JSON report's "
                   "frequencies are in Hz either way)")
    p.add_argument("--plant", default=None, metavar="NAME|PATH", help="base plant (default paper-iprsm)")
    p.add_argument("--fit", default=None, metavar="KEY,...", help="plant keys to fit (default: inertia, efficiency, "
                   "no-load torque, viscous, current-loop bandwidth; FRF only: inertia, current-loop bandwidth, with "
                   "--fidelity compliant also contact.stiffness_n_per_mm_e); drive.command_delay_s fits a continuous "
                   "command delay from --frf data; friction.static, friction.stribeck_velocity_m_s and "
                   "friction.no_load_breakaway_torque_n_m come from the records' steady low-speed plateaus "
                   "(a low-speed staircase), given the time-domain fit of the other keys")
    p.add_argument("--validate", nargs="+", default=[], metavar="CSV", help="records not fitted; their fit %% is reported")
    p.add_argument("--columns", default=None, metavar="name=header,...", help="map other CSV headers to the standard names")
    p.add_argument("--torque-constant", type=_positive("--torque-constant"), metavar="N_M_PER_A",
                   help="torque constant for a current_a column, N m/A")
    p.add_argument("--load", type=_finite("--load"), metavar="N", help="constant axial load, N, "
                   "for files without a load column")
    p.add_argument("--fidelity", default=None, choices=("rigid", "compliant"), help="model fidelity (default rigid; "
                   "--frf without DATA.csv: not given, the structure the response needs, rigid or two-mass (compliant); "
                   "rigid is refused, with the reason, for a response that shows an axial mode)")
    p.add_argument("--segment", type=_positive("--segment"), default=None, metavar="S",
                   help="multiple-shooting segment length, s (default 0.1; 0.05 with --fidelity compliant)")
    p.add_argument("--delay-samples", type=int, default=None, metavar="N", help="samples between a logged command and "
                   "the sample the current loop receives it from (default: found by the fit from time-domain records; "
                   "FRF only with --fit KEYS: the base plant's drive.command_delay_samples, plus 1 with --command-logged computed; "
                   "refused with --frf alone, whose fit fits the delay)")
    p.add_argument("--log-format", metavar="FORMAT.toml", help="log description (prsa_ctrl.identification.logformat): "
                   "a log in motor (axis = \"rotary\") or load coordinates, the latter converted with the plant's lead")
    p.add_argument("--command-logged", choices=("applied", "computed"), default=None,
                   help="how the log holds the command: as the controller applied it over the sample (default; "
                   "prsa-tune's simulator logs it so) or as computed at the sample, acting one sample later "
                   "(many drives log it so); the fitted drive.command_delay_samples is the delay found less this "
                   "one sample")
    p.add_argument("--design", choices=("multisine", "chirp", "steps"), help="write an excitation signal instead of fitting")
    p.add_argument("--duration", type=_positive("--duration"), default=4.0, metavar="S", help="excitation length, s")
    p.add_argument("--sample-time", type=_positive("--sample-time"), default=2.5e-4, metavar="S", help="sample time, s")
    p.add_argument("--f-min", type=_positive("--f-min"), default=1.0, metavar="HZ", help="lowest frequency, Hz")
    p.add_argument("--f-max", type=_positive("--f-max"), default=200.0, metavar="HZ", help="highest frequency, Hz")
    p.add_argument("--amplitude", action=KeepTyped, type=_positive("--amplitude"), default=20.0, metavar="RAD_S",
                   help="peak excursion of the speed setpoint, rad/s (|offset| + amplitude at most "
                   f"{DESIGN_MAX_SPEED_RAD_S:.4g} rad/s = {SPEED_MAX_RPM:g} rpm)")
    p.add_argument("--offset", action=KeepTyped, type=_finite("--offset"), default=30.0, metavar="RAD_S",
                   help="mean of the speed setpoint, rad/s")
    p.add_argument("--uncertainty-from-fit", action="store_true", help="write the fit's own intervals as the fitted "
                   "keys' [uncertainty] entries (default: keep the base plant's entries, replaced only where one is "
                   "narrower than the fit's 95 %% interval)")
    p.add_argument("--force", action="store_true", help="write the plant file even when the validation says the "
                   "fitted plant does not explain the data (exit 3 all the same; the file's header says so)")
    p.add_argument("--no-cross-validation", action="store_true", help="skip the leave-one-out cross-validation of "
                   "several records (faster; the verdict then rests on the replay of the fitted records)")
    p.add_argument("--verbose", action="store_true", help="also show the geometry note of a built-in base plant, "
                   "and a progress line when the fit starts")
    return p


def plant_toml(base_text: str, plant, name: str, keys: Sequence[str], description: str | None = None,
               uncertainty_keys: Sequence[str] | None = None) -> str:
    """The base plant file's text with the fitted keys' values, sources and uncertainty replaced
    (:meth:`prsa_ctrl.plant.plantfile.Plant.to_toml`, the one plant-file writer: the base's
    layout and comments kept). Kept here for its callers; ``prsa-fit`` composes no file itself."""
    return plant.to_toml(base_text, name=name, keys=keys, description=description, uncertainty_keys=uncertainty_keys)


def _write_outputs(files: dict[str, tuple[str, str]], inputs: Sequence[str], created: list | None = None) -> None:
    """The one place that writes files: ``{path: (flag, text)}``, each atomically; the new ones
    are added to ``created`` (taken back when the run fails or is interrupted later)."""
    from ..io.output import write_text

    for path, (flag, text) in files.items():
        existed = Path(path).exists()
        write_text(path, text, inputs=inputs, flag=flag)
        if created is not None and not existed:
            created.append(Path(path))


def _check_outputs(paths: dict[str, str], inputs: Sequence[str]) -> None:
    from ..io.output import check_writable

    for flag, path in paths.items():
        check_writable(path, inputs=inputs, flag=flag)


def _base_text(plant_arg: str | None) -> tuple[str, str | None]:
    """Text of the base plant file and its path (None for a built-in)."""
    from ..plant.plantfile import plant_file_path

    src = plant_file_path(plant_arg)
    return src.read_bytes().decode("utf-8"), (str(src) if isinstance(src, Path) else None)


def _typed(args, flag: str, value: float) -> str:
    """A flag's value as the user typed it (a :class:`~prsa_ctrl.cli.common.KeepTyped` flag of
    the parsed arguments), else the default."""
    found = typed_text(args, flag[2:].replace("-", "_"))
    return found if found is not None else f"{value:g} (default)"


def _design(args) -> int:
    import numpy as np

    from ..identification.data import design_excitation

    if args.json:
        raise UsageError(f"--json {args.json!r} with --design; expected no JSON report (the design writes only the "
                          "excitation CSV named by --out)")
    peak = abs(args.offset) + args.amplitude
    if peak > DESIGN_MAX_SPEED_RAD_S:
        raise UsageError(f"--amplitude {_typed(args, '--amplitude', args.amplitude)} with --offset "
                          f"{_typed(args, '--offset', args.offset)}: the setpoint reaches "
                          f"{peak:.6g} rad/s ({rad_s_to_rpm(peak):.6g} rpm); expected |offset| + amplitude <= "
                          f"{DESIGN_MAX_SPEED_RAD_S:.6g} rad/s ({SPEED_MAX_RPM:g} rpm, the tuner's speed limit)")
    t, v = design_excitation(args.design, duration_s=args.duration, sample_time_s=args.sample_time,
                             f_min_hz=args.f_min, f_max_hz=args.f_max, amplitude=args.amplitude, offset=args.offset)
    _check_outputs({"--out": args.out}, [])
    lines = ["# prsa-fit --design " + args.design + ": speed setpoint (rad/s) for the drive's speed loop",
             "time_s,setpoint_rad_s"]
    lines += [f"{a:.9g},{b:.9g}" for a, b in zip(t, np.asarray(v))]
    _write_outputs({args.out: ("--out", "\n".join(lines) + "\n")}, [])
    echo(f"wrote {args.out}: {args.design}, {len(t)} samples, {args.duration:g} s")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``prsa-fit``; returns the exit code.

    Python warnings raised on the way are collected and shown after the result, one
    ``prsa-fit: note:`` line each (never Python's two-line format); the geometry note of a
    built-in plant only with ``--verbose``.
    """
    # (the parser accepts abbreviations: its long options let attach_values glue "--frf-b -1,300" too)
    return invoke("prsa-fit", argv, _body, FIT_VALUE_FLAGS, long_options(build_parser()))


#: Flags of ``prsa-fit`` (and its linear-axis mode) whose value may start with ``-``: a number, a
#: list of numbers or of keys, a choice (:func:`prsa_ctrl.cli.common.attach_values` glues the value to its
#: flag, so that ``--frf-band -1,300`` reaches the band's check and is refused naming '-1,300';
#: argparse took it for a flag and said only "expected one argument"). Paths are not listed: a
#: path flag followed by another flag keeps argparse's "expected one argument".
FIT_VALUE_FLAGS = frozenset({
    "--frf-band", "--frf-speed", "--frf-load", "--frf-sample-time", "--coherence-min", "--load", "--torque-constant",
    "--segment", "--delay-samples", "--speed-loop", "--frf-from-logs", "--fit", "--columns", "--command-logged",
    "--fidelity", "--duration", "--sample-time", "--f-min", "--f-max", "--amplitude", "--offset", "--holdout",
    "--frequency-unit", "--design"})


def _body(run: Run, argv: list[str]) -> int:
    """:func:`main` inside :func:`prsa_ctrl.cli.common.invoke` (Ctrl-C: the files this run wrote
    taken back, one line, exit 130)."""
    from .axis import motor_log_mode, run as _axis_run, wants_axis_mode  # described logs (issue 21)

    motor = motor_log_mode(argv)  # described logs fitted in motor coordinates (a screw-driven plant)
    if wants_axis_mode(argv) and not motor:
        made: list = []  # what the run is about to write, known once its arguments are parsed
        try:
            return _axis_run(argv, check=run.check, parsed=lambda args: made.append(new_outputs(args)))
        except KeyboardInterrupt:
            if made:
                take_back(made[0]())  # the linear-axis path writes its files one by one
            raise
    created: list = []  # files and directories this run made, taken back when it is interrupted
    parsed: list = []  # the parsed arguments (argv is read once, by the parser)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            code = _main(argv, created, run, parsed)
    except BaseException as exc:
        take_back(created)  # all or nothing
        if run.interrupted:  # also when a library turned the KeyboardInterrupt into an error
            raise KeyboardInterrupt from None  # invoke: one line, exit 130
        if parsed and parsed[0].verbose and isinstance(exc, Exception):  # the cause, before invoke's one line
            _print_chain(exc)
        raise
    seen = set()
    for w in caught:
        text = " ".join(str(w.message).split())
        if text in seen or (issubclass(w.category, GeometryWarning) and "(built-in)" in text
                            and not (parsed and parsed[0].verbose)):
            continue
        seen.add(text)
        echo(f"prsa-fit: note: {text}", file=sys.stderr)
    return code


def new_outputs(args):
    """What this run is about to write (the parsed ``--out``, ``--json``, ``--traces``, the
    ``--plots`` folder and its figures): a function returning, after the run, the files and
    folders that did not exist before it (for :func:`take_back`).

    Parameters
    ----------
    args : argparse.Namespace
        The parsed arguments (``out``, ``json``, ``traces``, ``plots``; any may be missing).

    Returns
    -------
    callable
        ``made() -> list of Path``: what the run created, files then new figures (and the
        ``--plots`` folder when the run made it).
    """
    import os

    files = [v for v in (getattr(args, k, None) for k in ("out", "json", "traces")) if v]
    plots = getattr(args, "plots", None)
    existed = {p for p in files if os.path.lexists(p)}
    plots_had = set(os.listdir(plots)) if plots and os.path.isdir(plots) else None

    def made() -> list:
        out = [Path(p) for p in files if p not in existed]
        if plots and os.path.isdir(plots) and not os.path.islink(plots):
            out += [Path(plots) / n for n in sorted(os.listdir(plots)) if plots_had is None or n not in plots_had]
            if plots_had is None:
                out.append(Path(plots))
        return out

    return made


def take_back(created: list) -> None:
    """Remove what a failed or interrupted run wrote: its files, then its (then empty)
    directories, and the atomic writes' temporaries; ``created`` is emptied.

    Parameters
    ----------
    created : list of Path
        What the run created (:func:`new_outputs`); nothing else is touched.
    """
    from ..io.output import cleanup_temporaries, remove_created

    cleanup_temporaries()
    for item in reversed(created):
        if isinstance(item, Path) and item.is_file():
            item.unlink(missing_ok=True)
    remove_created([d for d in created if isinstance(d, Path) and d.is_dir()])
    created.clear()


def _probe_output(path: str, inputs: Sequence[str], flag: str) -> None:
    """Check an output path up front the way it will be written: the rules of
    :func:`prsa_ctrl.io.output.check_writable`, then the atomic write's temporary file created and
    removed in the target's directory (a name too long, a symlink loop or a full directory
    fails here, before the fit)."""
    import os
    import tempfile

    from ..io.output import TEMP_MARK, OutputError, check_writable

    what = f"{flag} {path!r}"
    try:
        target = check_writable(path, inputs=inputs, flag=flag)
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}{TEMP_MARK}", dir=target.parent)
        try:
            os.close(fd)
        finally:  # removed after a Ctrl-C too
            os.unlink(tmp)
    except OSError as exc:
        if isinstance(exc, OutputError):
            raise
        raise UsageError(f"{what}: cannot be written ({exc.strerror or exc}); expected a writable file path "
                          "(a shorter name, no symlink loop)") from None


def _probe_plots(directory: str, names: Sequence[str], inputs: Sequence[str]) -> None:
    """Check every figure path of ``--plots`` up front (in the directory, or where it will be created)."""
    from ..io.output import check_directory

    check_directory(directory, "--plots")
    d = Path(directory)
    anc = d
    while not anc.exists():
        anc = anc.parent
    for name in names:
        _probe_output(str(d / name) if d.is_dir() else str(anc / name), inputs, "--plots")


def _check_frf_point(plant, speed: float, load: float, args) -> None:
    """The FRF operating point (``--frf-speed``, ``--frf-load``) checked before the fit, the
    flag named (:func:`prsa_ctrl.identification.common.frf_operating_point_error`)."""
    from ..identification.calibrate import frf_point_check

    frf_point_check(plant, speed, load, _typed_point(args, speed, load))


def _typed_point(args, speed: float, load: float) -> dict:
    """``--frf-speed`` and ``--frf-load`` as typed (for the operating point's messages)."""
    return {"--frf-speed": _typed(args, "--frf-speed", speed), "--frf-load": _typed(args, "--frf-load", load)}


def _main(argv: Sequence[str], created: list | None = None, run: Run | None = None, parsed: list | None = None) -> int:
    from ..identification.data import DataError, load_frf, load_record, parse_columns
    from ..io.output import OutputError

    created = [] if created is None else created

    try:
        args = build_parser().parse_args(argv)
        if parsed is not None:
            parsed.append(args)
        mat = next((p for p in (*args.data, *args.validate) if p.lower().endswith(".mat")), None)
        if mat is not None and args.log_format is None:  # a MATLAB log has no fixed columns: a description says
            from ..identification.calibrate import mat_log_refusal

            raise UsageError(mat_log_refusal(mat))
        if args.design:
            if args.data:
                raise UsageError(f"--design with data files {' '.join(args.data)}; expected one or the other")
            return _design(args)
        if not args.data and not args.frf:
            raise UsageError("no data file; expected prsa-fit DATA.csv [...] [--frf FRF.csv] --out PLANT.toml "
                              "(or --design)")
        if not 0 <= args.coherence_min < 1:
            raise UsageError(f"--coherence-min {args.coherence_min!r}: expected 0 <= C < 1")
        band = None
        if args.frf_band is not None:
            from ..identification.frfband import parse_band

            band = parse_band(args.frf_band)
            if not args.frf or args.data or args.fit is not None:
                raise UsageError(f"--frf-band {args.frf_band!r}: expected it with --frf FRF.csv alone (no DATA.csv, no "
                                 "--fit): it cuts the measured responses the structure is fitted to")
        from ..identification.calibrate import linear_axis_refusal
        from ..identification.common import FITTABLE
        from ..plant.plantfile import load_plant

        keys = None
        if args.fit is not None:
            keys = [k.strip() for k in args.fit.split(",")]
            if keys == [""]:
                raise UsageError(f"--fit {args.fit!r}: expected at least one key")
            for i, k in enumerate(keys):
                if not k:
                    raise UsageError(f"--fit {args.fit!r}: empty item {i + 1}; expected keys separated by single commas")
                if k not in FITTABLE:
                    raise UsageError(f"--fit {args.fit!r}: unknown key {k!r}; expected some of {', '.join(FITTABLE)}")
                if k in keys[:i]:
                    raise UsageError(f"--fit {args.fit!r}: key {k!r} given twice; expected each key once")
        if args.delay_samples is not None and not 0 <= args.delay_samples <= 10:
            raise UsageError(f"--delay-samples {args.delay_samples}: expected 0..10")
        plant = load_plant(args.plant)
        if plant.mechanism == "linear-axis" and (args.data or args.log_format or args.frf_from_logs is not None):
            # load coordinates: fitted from a described log, not these records (its measured FRF, --frf alone, is)
            raise UsageError(linear_axis_refusal(args.plant))
        base_text, base_path = _base_text(args.plant)
        # the fitted plant file can be written for any spelling of the base (checked before the fit)
        plant.to_toml(base_text, name=Path(args.out).stem, keys=[k for k in (keys or FITTABLE) if k in plant.values],
                      description="check")
        frf_load = args.frf_load if args.frf_load is not None else (args.load or 0.0)
        if args.frf:
            _check_frf_point(plant, args.frf_speed, frf_load, args)
        inputs = [*args.data, *args.validate, *args.frf] + ([base_path] if base_path else []) + \
            ([args.log_format] if args.log_format else [])
        outs = {"--out": args.out}
        if args.json:
            outs["--json"] = args.json
        from ..io.output import check_distinct

        check_distinct(outs)
        for flag, path in outs.items():
            _probe_output(path, inputs, flag)
        plot_paths = []
        if args.plots is not None:
            from ..plots.fit import figure_names

            check_distinct({"--plots": args.plots, **outs})
            stems = (figure_names([], [*args.frf, *args.data]) if args.frf_from_logs is not None else
                     figure_names([*(args.data or []), *(args.validate if args.data else [])], args.frf,
                                  log_responses=True))
            plot_paths = [str(Path(args.plots) / f"{stem}.png") for stem in stems]
            _probe_plots(args.plots, [f"{stem}.png" for stem in stems], inputs)
        columns = parse_columns(args.columns) if args.columns is not None else None  # (an empty map is refused)
        opts = {"columns": columns, "torque_constant_n_m_per_a": args.torque_constant, "load_n": args.load}
        coordinates = {}
        closed_loops = {}
        if args.log_format:
            from .axis import motor_records

            records, validate, args.command_logged, coordinates = motor_records(args, plant)
            closed_loops = _closed_loops(args)
        else:
            records = [load_record(f, **opts) for f in args.data]
            validate = [load_record(f, **opts) for f in args.validate]
            coordinates = {f: MOTOR_COORDINATES for f in (*args.data, *args.validate)}
        if args.validate and not args.data:
            raise UsageError("--validate without DATA.csv; expected time-domain records to fit first")
        # the FRF-only fit (--frf alone, or --frf-from-logs) without --fit: identification.calibrate.calibrate_frf
        # reads the --frf files, fits and composes the outputs (the app's calibration calls it too)
        frf_only = keys is None and (not args.data or args.frf_from_logs is not None)
        if frf_only and args.delay_samples is not None:  # (was silently ignored: the report said "fitted")
            mode = "--frf-from-logs" if args.frf_from_logs is not None else "--frf alone"
            held = ("the fit of DATA.csv without --frf-from-logs" if args.frf_from_logs is not None else "DATA.csv")
            raise UsageError(f"--delay-samples {args.delay_samples} with {mode}: the frequency-response fit fits the "
                             f"command delay as a continuous time (reported with its interval); expected it with "
                             f"{held}, or --fit KEYS without drive.command_delay_s to hold the delay at N")
        frfs = [] if frf_only else [load_frf(f, speed_rad_s=args.frf_speed, load_n=frf_load,
                                             coherence_min=args.coherence_min, sample_time_s=args.frf_sample_time)
                                    for f in args.frf]
        speed_loop = _speed_loop(args, records)
        if args.frf_from_logs is not None:
            records, frfs = [], frfs + _frfs_from_logs(args, records)
    except (UsageError, argparse.ArgumentTypeError, DataError, PlantFileError, OutputError, ValueError) as exc:
        echo(f"prsa-fit: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # e.g. an input path that is a symlink loop
        _echo_unreadable(exc)
        return 2
    from ..errors import FitError
    from ..identification.timedomain import fit_plant

    run = Run("prsa-fit") if run is None else run
    progress(run, args.verbose, f"fitting {len(records)} record(s)")
    choice = result = cal = None
    fitted_from = ", ".join(Path(f).name for f in [*args.data, *([] if args.data else args.frf)])
    try:
        run.record = True  # Ctrl-C recorded while CasADi runs, raised at the fit's iterations (run.check)
        if frf_only:  # FRF only: the structure the data choose (issue 32), the library's one path
            from ..identification.calibrate import calibrate_frf

            cal = calibrate_frf(args.frf, args.plant, name=Path(args.out).stem, speed_rad_s=args.frf_speed,
                                load_n=frf_load, coherence_min=args.coherence_min, fidelity=args.fidelity,
                                sample_time_s=args.frf_sample_time,
                                command_logged=args.command_logged or "applied",
                                uncertainty="fit" if args.uncertainty_from_fit else "keep", force=args.force,
                                origin=args.out, typed={**_typed_point(args, args.frf_speed, frf_load),
                                                        "--frf-band": repr(args.frf_band)}, extra=frfs,
                                fitted_from=fitted_from, coordinates=coordinates, band=band)
            result, choice = cal.result, cal.choice
        elif not records and frfs:  # --fit KEY,...: the structure checked, then the keys' own fit
            result, choice = _fit_frf_only(args, plant, frfs, keys)
        if result is None:
            result = fit_plant(records, plant, frf=frfs, keys=keys, fidelity=args.fidelity or "rigid", validate=validate,
                               segment_s=args.segment,
                               delay_samples=args.delay_samples if args.delay_samples is not None or not records else "find",
                               command_logged=args.command_logged or "applied", uncertainty="fit" if args.uncertainty_from_fit else "keep",
                               check_interrupt=run.check, cross_validate=not args.no_cross_validation,
                               closed_loops=closed_loops, speed_loop=speed_loop)
    except FitError as exc:
        run.check()  # a fit that failed after Ctrl-C was interrupted
        if args.verbose:  # where it was raised, and what caused it
            _print_chain(exc, skip_message=True)
        echo(f"prsa-fit: {exc}", file=sys.stderr)
        return 3
    except ValueError as exc:
        run.check()
        echo(f"prsa-fit: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a --frf file read by calibrate_frf (e.g. a symlink loop)
        _echo_unreadable(exc)
        return 2
    finally:
        run.record = False
    run.check()  # a Ctrl-C in a step of the fit without an iteration check: nothing written
    from ..identification.calibrate import fit_report, fitted_plant_text, not_explained_line, result_lines, written_mode

    validation = result.solver.get("validation")
    failed = validation is not None and not validation["passes"]
    try:
        text = cal.plant_text if cal is not None else fitted_plant_text(result, plant, base_text, Path(args.out).stem,
                                                                        fitted_from, force=args.force, origin=args.out)
    except FitError as exc:  # the fitted file would not load: the tool's fault, not the user's input
        echo(f"prsa-fit: {exc}", file=sys.stderr)
        return 3
    files = {args.out: ("--out", text)} if not failed or args.force else {}
    # a compliant plant's mode is stated at the FRF's operating point (--frf-speed, --frf-load): it moves with the nut force
    point = (frfs[0].speed_rad_s, frfs[0].load_n) if frfs else (args.frf_speed, frf_load)
    mode = None if cal is not None or args.out not in files else written_mode(result, text, *point)
    if args.json:
        from ..io.output import json_safe
        from ..plots.fit import fit_views

        report = {**(cal.report if cal is not None else fit_report(result, coordinates, choice, point=point, mode=mode)),
                  "views": fit_views(result, [*records, *validate])}
        files[args.json] = ("--json", json.dumps(json_safe(report), indent=2) + "\n")
    try:
        if args.plots is not None:
            plot_paths = _write_plots(result, args.plots, inputs, created, args.frequency_unit, [*records, *validate])
        _write_outputs(files, inputs, created)
    except (OutputError, OSError) as exc:  # all or nothing: the figures of this run are taken back
        take_back(created)
        echo(f"prsa-fit: error: {exc if isinstance(exc, OutputError) else f'writing the outputs failed ({exc})'}",
             file=sys.stderr)
        return 2
    for line in (cal.lines if cal is not None else result_lines(result, coordinates, choice, point=point, mode=mode)):
        echo(line)
    written = [p for p, _ in ((args.out, 0),) if p in files] + ([args.json] if args.json else [])
    echo(("wrote " + " and ".join(written)) if written else "wrote no file")
    if args.plots is not None:
        echo("plots: " + ", ".join(plot_paths))
    if failed:
        echo(f"prsa-fit: {not_explained_line(result, args.force)}", file=sys.stderr)
        return 3
    return 0


def _echo_unreadable(exc: OSError) -> None:
    echo(f"prsa-fit: error: {getattr(exc, 'filename', None) or ''}: cannot be read ({exc.strerror or exc}); "
         "expected readable files", file=sys.stderr)


def _closed_loops(args) -> dict:
    """``{record name: ClosedLoop}`` of the described logs (load coordinates) whose description
    gives the controller and the reference: their validation replays the closed loop."""
    from ..identification.logformat import load_axis_log, load_log_format
    from ..identification.validation import closed_loop_of

    fmt = load_log_format(args.log_format)
    if fmt.doc.get("axis", "linear") != "linear" or "controller" not in fmt.doc:
        return {}
    out = {}
    for path in (*args.data, *args.validate):
        log = load_axis_log(path, fmt)
        cl = closed_loop_of(log)
        if cl is not None:
            out[log.name] = cl
    return out


def _loop_numbers(flag: str, text: str) -> list[float]:
    """``KP,KI[,TAU_S]`` of a speed-loop flag as typed, or one line naming it (UsageError)."""
    parts = [x.strip() for x in text.split(",")]
    try:
        nums = [float(x) for x in parts]
    except ValueError:
        nums = []
    if len(nums) not in (2, 3) or not all(math.isfinite(x) for x in nums):
        raise UsageError(f"{flag} {text!r}: expected KP,KI[,TAU_S] (the speed PI's gains in N m s/rad and "
                         "N m/rad, the speed filter's time constant in s), e.g. 1.0,100,2e-4")
    return nums


def _speed_loop(args, records):
    """``--speed-loop KP,KI[,TAU_S]``: the described loop a compliant fit of the logs starts from
    (:func:`prsa_ctrl.identification.compliant.compliant_start`); None without the flag."""
    import numpy as np

    from ..identification.closedloop import SpeedLoop

    if args.speed_loop is None:
        return None
    typed = repr(args.speed_loop)
    if args.fidelity != "compliant" or not records or args.frf_from_logs is not None:
        raise UsageError(f"--speed-loop {typed}: expected it with DATA.csv and --fidelity compliant (without "
                         "--frf-from-logs): it starts the compliant time-domain fit from the logs' response")
    nums = _loop_numbers("--speed-loop", args.speed_loop)
    try:
        return SpeedLoop(nums[0], nums[1], float(np.median(np.diff(records[0].time_s))), nums[2] if len(nums) == 3 else 0.0,
                         args.command_logged or "applied")
    except ValueError as exc:
        raise UsageError(f"--speed-loop {typed}: {exc}") from None


def _frfs_from_logs(args, records) -> list:
    """``--frf-from-logs KP,KI[,TAU_S]``: the frequency response of each DATA.csv log
    (:func:`prsa_ctrl.identification.closedloop.frf_from_logs`)."""
    import numpy as np

    from ..identification.closedloop import SpeedLoop, frf_from_logs
    from ..identification.data import DataError

    text = args.frf_from_logs
    typed = repr(text)  # a text flag: the value is the text as typed
    nums = _loop_numbers("--frf-from-logs", text)
    if not records:
        raise UsageError(f"--frf-from-logs {typed} without DATA.csv; expected closed-loop logs to estimate it from")
    out, why = [], []
    for rec in records:
        ts = float(np.median(np.diff(rec.time_s)))
        try:
            loop = SpeedLoop(nums[0], nums[1], ts, nums[2] if len(nums) == 3 else 0.0,
                             args.command_logged or "applied")
        except ValueError as exc:
            raise UsageError(f"--frf-from-logs {typed}: {exc}") from None
        load = float(np.mean(rec.axial_load_n)) if rec.axial_load_n is not None else (args.load or 0.0)
        try:
            out.append(frf_from_logs(rec, loop, load_n=load, coherence_min=args.coherence_min))
        except DataError as exc:
            why.append(str(exc))
    if not out:
        raise DataError(f"--frf-from-logs {typed}: no log gives a frequency response ({'; '.join(why)})")
    return out


def _fit_frf_only(args, plant, frfs, keys):
    """``--frf`` with ``--fit KEY,...`` (no DATA.csv): the structure the data choose checked first,
    refused with the reason when ``--fidelity rigid`` (the default here) meets a response with an
    axial mode; the keys' own fit (:func:`prsa_ctrl.identification.frf.fit_frf`) runs after it.
    Without ``--fit`` the FRF-only path is :func:`prsa_ctrl.identification.calibrate.calibrate_frf`.
    Returns ``(None, choice)``."""
    from ..errors import FitError
    from ..identification.frfcheck import choose_structure_checked
    from ..identification.common import frf_sample_time

    choice = choose_structure_checked(frfs, plant.reflected_inertia_kg_m2, sample_time_s=frf_sample_time(frfs[0], plant))
    if choice.structure == "two-mass" and (args.fidelity or "rigid") == "rigid":
        raise FitError(f"rigid model refused: {choice.reason}; fit it with --fidelity compliant (the two-mass axis)")
    return None, choice


def _print_chain(exc: BaseException, skip_message: bool = False) -> None:
    """``--verbose`` on a failure: the exception chain, one line each (type, message, where);
    ``skip_message``: the first one's message is printed after it anyway (only where it was raised)."""
    seen = set()
    e, depth = exc, 0
    while e is not None and id(e) not in seen and depth < 10:
        seen.add(id(e))
        tb = e.__traceback__
        where = ""
        while tb is not None and tb.tb_next is not None:
            tb = tb.tb_next
        if tb is not None:
            co = tb.tb_frame.f_code
            where = f" (at {Path(co.co_filename).name}:{tb.tb_lineno} in {co.co_name})"
        msg = "(message below)" if skip_message and depth == 0 else " ".join(str(e).split())
        echo(f"prsa-fit: cause{' ' * (depth > 0)}{'' if depth == 0 else f'[{depth}]'}: "
              f"{type(e).__name__}: {msg}{where}", file=sys.stderr)
        e = e.__cause__ if e.__cause__ is not None else (None if e.__suppress_context__ else e.__context__)
        depth += 1


def _write_plots(result, directory: str, inputs: Sequence[str], created: list,
                 frequency_unit: str = DEFAULT_FREQUENCY_UNIT, records: Sequence = ()) -> list[str]:
    """Write :func:`prsa_ctrl.plots.fit.fit_figures` as PNG files into ``directory`` (created if
    missing; Bode axes in ``frequency_unit``; each of ``records`` with its own response
    figure); the directories made and the files written are added to ``created``."""
    import matplotlib.pyplot as plt

    from ..plots.fit import fit_figures
    from ..io.output import make_directory, write_file

    created += make_directory(directory, "--plots")
    out = []
    figs = fit_figures(result, frequency_unit, records)
    try:
        for stem, fig in figs.items():
            path = Path(directory) / f"{stem}.png"
            existed = path.exists()
            write_file(path, lambda tmp, fig=fig: fig.savefig(tmp, format="png", dpi=120), inputs, "--plots")
            if not existed:
                created.append(path)
            out.append(str(path))
    finally:
        for fig in figs.values():
            plt.close(fig)
    return out


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
