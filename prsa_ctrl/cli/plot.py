"""``prsa-plot``: Bode, sensitivity, load-step and setpoint-step figures for a plant and given
gains (no tuning), and the margins (Ms, Mt, GM, PM, crossover) they give.

Exit codes and errors as every command (:mod:`prsa_ctrl.cli.common`); the figures are written
into ``--plots`` (alias ``--out``) all or none.
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path
from typing import Sequence

from .._lazy import module
from ..errors import GeometryWarning
from ..io.output import Transaction, check_directory
from ..options import DEFAULT_FREQUENCY_UNIT, DERIVATIVE_FILTER_SAMPLES, FREQUENCY_UNITS
from ..studies.scene import choose_fidelity
from .common import (EXIT_OK, Parser, Run, UsageError, commit, echo, invoke, native_output, number, path_text, progress,
                     report_failure, show_notes, staged)
from .inputs import VALUE_FLAGS, input_files, load_and_override, scene_flags
from ..studies.scenereport import fmt_margin, scene_header

#: The figures module and pyplot (matplotlib) are imported when a figure is drawn.
loop_plots = module("prsa_ctrl.plots.loop")
pyplot = module("matplotlib.pyplot")

__all__ = ["plot_main", "build_plot_parser", "KP_RANGE", "KI_RANGE", "KD_RANGE"]

#: Gain ranges accepted by ``prsa-plot`` (SI): far beyond any sensible speed loop of a roller
#: screw (tuned kp ~0.1 N m s/rad), but finite so that every matrix stays representable.
KP_RANGE = (1e-9, 1e4)
KI_RANGE = (0.0, 1e7)
KD_RANGE = (0.0, 1e2)


def build_plot_parser() -> argparse.ArgumentParser:
    """Argument parser of ``prsa-plot``."""
    p = Parser(
        prog="prsa-plot", allow_abbrev=False,
        description="Bode, sensitivity, load-step and setpoint-step figures for a plant and given gains (no tuning), "
        "and the margins (Ms, Mt, GM, PM, crossover) they give. Unstable or marginal gains are plotted "
        "with a warning (time responses of an unstable loop are not drawn). "
        "Exit codes: 0 ok, 2 bad input, 3 numerical failure, 130 interrupted.",
    )
    p.add_argument("--kp", required=True, metavar="KP",
                   type=number("--kp", KP_RANGE[0], KP_RANGE[1], "N m s/rad", "a proportional gain"),
                   help=f"proportional gain, N m s/rad, in [{KP_RANGE[0]:g}, {KP_RANGE[1]:g}] (required)")
    p.add_argument("--ki", default=0.0, metavar="KI", type=number("--ki", *KI_RANGE, "N m/rad", "an integral gain"),
                   help=f"integral gain, N m/rad, in [0, {KI_RANGE[1]:g}] (default 0: P or PD only)")
    p.add_argument("--kd", default=0.0, metavar="KD", type=number("--kd", *KD_RANGE, "N m s^2/rad", "a derivative gain"),
                   help=f"derivative gain, N m s^2/rad, in [0, {KD_RANGE[1]:g}] (default 0), filtered with "
                        "tf = 4 sample times")
    scene_flags(p)
    p.add_argument("--plots", "--out", dest="out", default="prsa-plots", type=path_text("--plots"), metavar="DIR",
                   help="folder for the PNG and SVG files (default: ./prsa-plots, created if missing; "
                        "not created when the run fails)")
    p.add_argument("--frequency-unit", choices=tuple(FREQUENCY_UNITS), default=DEFAULT_FREQUENCY_UNIT,
                   help="unit of the frequency axes of the Bode and sensitivity plots (default Hz; the data and "
                        "the printed margins stay in rad/s)")
    return p


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
    return invoke("prsa-plot", argv, _plot_body, VALUE_FLAGS)


def _plot_figures(plant, scene, pid, state, loops, frequency_unit: str = DEFAULT_FREQUENCY_UNIT):
    return loop_plots.design_figures(plant, scene, pid, state, loops, frequency_unit)


def _plot_body(run: Run, argv: list[str]) -> int:
    if "-h" in argv or "--help" in argv:
        build_plot_parser().print_help()
        return EXIT_OK
    args = build_plot_parser().parse_args(argv)
    notes: list[warnings.WarningMessage] = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        plant, scene, _ = load_and_override(args, run, plot=True)
        from ..drive.pid import PID  # CasADi: after the flags are checked

        try:
            pid = PID(args.kp, args.ki, args.kd, tf=DERIVATIVE_FILTER_SAMPLES * plant.sample_time_s)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
        check_directory(args.out, "--plots")
        inputs = input_files(args, scene)
        notes.extend(caught)
    run.check()
    native: list[str] = []
    what = f"plotting kp = {args.kp:g}, ki = {args.ki:g}, kd = {args.kd:g} on {plant.name}"
    progress(run, args.verbose, f"{what} ...")
    try:
        with warnings.catch_warnings(record=True) as caught, native_output(run, native):
            warnings.simplefilter("always")
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", GeometryWarning)
                from ..studies.autotune import actuator_loops  # the tuner's loop models (CasADi)

                loops = actuator_loops(plant, choose_fidelity(scene)[0])
                state = _stability(loops[0], pid.gains)
                m = loops[0].margins(pid.gains)
                figs = None if state == "stable" else _plot_figures(plant, scene, pid, state, loops, args.frequency_unit)
                files = None
                if state == "stable":
                    files = staged(run, lambda staging: loop_plots.write_design_plots(plant, scene, pid, staging,
                                                                                  args.frequency_unit),
                                   args.out, inputs)
            notes.extend(caught)
        run.check()
    except KeyboardInterrupt:
        raise
    except Exception as exc:  # noqa: BLE001 - translated at this boundary
        return report_failure(run, exc, what, args.verbose)
    if files is None:
        files = _write_figures(run, figs, args.out, inputs)
    echo(f"prsa-plot: plant {plant.name}, {scene_header(scene)}")
    echo(f"gains: kp = {args.kp:g} N m s/rad, ki = {args.ki:g} N m/rad, kd = {args.kd:g} N m s^2/rad")
    echo(f"Margins: Ms {m.ms:.3f}, Mt {m.mt:.3f}, GM {fmt_margin(m.gm_db)} dB, PM {fmt_margin(m.pm_deg)} deg, "
         f"crossover {fmt_margin(m.wc_rad_s)} rad/s"
         + (" (frequency-response values; not margins of a stable loop)" if state == "unstable" else ""))
    if state == "unstable":
        echo(f"warning: the closed loop is UNSTABLE with these gains on {plant.name}; only the frequency plots "
             "were drawn (time responses diverge)")
    elif state == "marginal":
        why = ("P-only (ki = 0) leaves a steady error after a load step" if args.ki == 0
               else "a closed-loop pole sits on the stability boundary")
        echo(f"warning: marginally stable: {why}")
    elif m.ms > scene.ms_max * (1 + 1e-3):
        echo(f"warning: Ms {m.ms:.3f} exceeds the scene's bound {scene.ms_max:g}")
    echo("\n".join(str(f) for f in files))
    show_notes(run, notes, native, args.verbose, False)
    return EXIT_OK


def _write_figures(run: Run, figs: dict, directory: str, inputs: Sequence[str]) -> list[Path]:
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
            pyplot.close(fig)
        commit(run, tr)
    return files


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(plot_main())
