"""``prsa-tune``: tune the speed loop for a load step, verify, compare with baselines.

Exit codes: 0 success, 2 bad input (one line naming the value), 3 numerical failure.
Heavy modules are imported only after the arguments, the plant and the scene are validated.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Sequence

from .errors import PlantFileError, SceneError, SimulationError
from .options import CONTROLLERS, ESTIMATORS

__all__ = ["main", "parse_load_step", "write_json_atomic"]

_T_START = time.perf_counter()


class _UsageError(Exception):
    pass


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2, no usage dump
        raise _UsageError(message)


def parse_load_step(text: str) -> tuple[float, tuple[float, ...]]:
    """Parse ``INITIAL:FINAL[,FINAL...]`` (N), e.g. ``500:1500`` or ``500:1000,1500,2000``."""
    expected = "expected INITIAL:FINAL[,FINAL...] in newtons >= 0, e.g. 500:1500"
    parts = text.split(":")
    if len(parts) != 2 or not parts[0].strip() or not parts[1].strip():
        raise argparse.ArgumentTypeError(f"{text!r}: {expected}")
    try:
        initial = float(parts[0])
        finals = tuple(float(p) for p in parts[1].split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: {expected}") from None
    for v in (initial, *finals):
        if not math.isfinite(v) or v < 0:
            raise argparse.ArgumentTypeError(f"{text!r}: load {v:g} N is not allowed; {expected}")
    for f in finals:
        if f == initial:
            raise argparse.ArgumentTypeError(f"{text!r}: final load equals the initial load; expected a step")
    return initial, finals


def _positive(name: str):
    def conv(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r}: expected a number") from None
        if not math.isfinite(v) or v <= 0:
            raise argparse.ArgumentTypeError(f"{text!r}: expected a finite number > 0")
        return v

    return conv


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="prsa-tune",
        description="Tune the nut-speed PI/PID of an inverted planetary roller screw actuator "
        "for a load step, verify on the nonlinear simulator, compare with baselines.",
    )
    p.add_argument("--load-step", type=parse_load_step, metavar="N0:N1[,N2...]",
                   help="initial and final axial load(s) in N (default: the scene's, 500:1500)")
    p.add_argument("--plant", default=None, metavar="NAME|PATH", help="built-in plant name or .toml (default paper-iprsm)")
    p.add_argument("--scene", default=None, metavar="NAME|PATH", help="built-in scene name or .toml (default paper-load-step)")
    p.add_argument("--setpoint-rpm", type=_positive("--setpoint-rpm"), help="nut-speed setpoint, rpm")
    p.add_argument("--step-time", type=_positive("--step-time"), help="time of the load step, s")
    p.add_argument("--duration", type=_positive("--duration"), help="end of the record, s")
    p.add_argument("--ms-max", type=_positive("--ms-max"), help="peak-sensitivity bound (default 1.4)")
    p.add_argument("--objective", choices=("ie", "iae", "itae", "ise"), help="tuning objective")
    p.add_argument("--controller", choices=CONTROLLERS, help="controller structure")
    p.add_argument("--estimator", choices=ESTIMATORS, help="speed measurement: drive difference or Kalman filter")
    p.add_argument("--feedforward", action="store_true", help="feed the estimated load torque forward (needs --estimator kf)")
    p.add_argument("--json", type=Path, metavar="PATH", help="write the report as JSON (atomically)")
    p.add_argument("--plots", type=Path, metavar="DIR", help="write the standard plots (PNG and SVG) into DIR")
    p.add_argument("--workers", type=int, default=None, help="processes for verification (default: cores)")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")
    return p


def write_json_atomic(path: Path, data: dict) -> None:
    """Write JSON to a temporary file beside ``path`` and rename it into place."""
    text = json.dumps(data, indent=2, allow_nan=False, default=float)
    directory = path.resolve().parent
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=directory)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text + "\n")
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


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


def _table(header: Sequence[str], rows: Sequence[Sequence]) -> str:
    cells = [list(header)] + [[_fmt(c) for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def format_report(rep) -> str:
    """Readable text report of an :class:`~prsa_ctrl.autotune.ActuatorTuning`."""
    sc, b = rep.scene, rep.best
    obj = sc.objective.upper()
    loads = ", ".join(f"{f:g}" for f in sc.final_loads)
    out = [
        f"prsa-tune: plant {rep.plant.name}, scene {sc.name}: {sc.setpoint_rpm:g} rpm, "
        f"{sc.initial_load:g} N -> {loads} N at {sc.step_time:g} s",
        f"verification: {rep.fidelity_reason}; {'sampled controller (ZOH, quantised encoder)' if sc.discrete else 'continuous controller'}",
        "",
        f"Tuned {sc.controller.upper()} ({b.name}): kp = {b.pid.kp:.5g} N m s/rad, ki = {b.pid.ki:.5g} N m/rad"
        + (f", kd = {b.pid.kd:.5g} N m s^2/rad (tf {b.pid.tf:g} s)" if b.pid.kd else "")
        + (f", load feed-forward gain kff = {b.pid.kff:.3g}" if sc.feedforward else ""),
        f"Margins: Ms {b.margins.ms:.3f}, Mt {b.margins.mt:.3f}, GM {_fmt(b.margins.gm_db)} dB, "
        f"PM {_fmt(b.margins.pm_deg)} deg, crossover {_fmt(b.margins.wc_rad_s)} rad/s",
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
    for k, f1 in enumerate(sc.final_loads):
        pm, vm = b.predicted[k], b.verified[k]
        rows = []
        for label, attr in fields:
            p, v = getattr(pm, attr), getattr(vm, attr)
            diff = (p / v - 1) * 100 if isinstance(v, float) and not isinstance(v, bool) and v and math.isfinite(v) and math.isfinite(p) else None
            rows.append([label, p, v, f"{diff:+.1f} %" if diff is not None else "-"])
        out.append(f"Load step {sc.initial_load:g} -> {f1:g} N")
        out.append(_table(["metric", "predicted (linear)", "verified (nonlinear)", "difference"], rows))
        out.append("")
    rows = []
    comp = {c["baseline"]: c for c in rep.comparisons}
    for d in rep.baselines:
        c = comp[d.name]
        rows.append([d.name, d.pid.kp, d.pid.ki, d.margins.ms, d.objective_verified,
                     c["tuned_objective_verified"], c["tuned_ms"], c["beaten"]])
    out.append(f"Baselines ({obj}, verified; tuned at equal or better Ms)")
    out.append(_table(["baseline", "kp", "ki", "Ms", obj, f"tuned {obj}", "tuned Ms", "beaten"], rows))
    out.append("")
    t = rep.timing_s
    out.append(
        f"Run time: linearise {t['linearize']:.2f} s, tune {t['tune']:.2f} s, verify {t['verify']:.2f} s, "
        f"total {t['total']:.2f} s (process {t.get('process', math.nan):.2f} s)"
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


def _attach_values(argv: Sequence[str]) -> list[str]:
    """``--load-step -5:10`` would read ``-5:10`` as an option; glue values to their flag so
    that such a value reaches the validator and is reported by name."""
    out: list[str] = []
    it = iter(argv)
    for a in it:
        if a in _VALUE_FLAGS:
            nxt = next(it, None)
            out.append(a if nxt is None else f"{a}={nxt}")
        else:
            out.append(a)
    return out


_VALUE_FLAGS = {"--load-step", "--setpoint-rpm", "--step-time", "--duration", "--ms-max"}


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"{Path(sys.argv[0]).name if sys.argv and sys.argv[0] else 'prsa'}: note: {message}", file=sys.stderr)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        args = parser.parse_args(_attach_values(argv))
        warnings.showwarning = _show_warning
        if args.quiet:
            warnings.simplefilter("ignore")
        from .plant import load_plant
        from .scene import load_scene

        plant = load_plant(args.plant)
        scene = load_scene(args.scene)
        changes = {}
        if args.load_step is not None:
            changes["initial_load"], changes["final_loads"] = args.load_step
        for arg, field in (("setpoint_rpm", None), ("step_time", "step_time"), ("duration", "duration"),
                           ("ms_max", "ms_max"), ("objective", "objective"), ("controller", "controller")):
            v = getattr(args, arg)
            if v is None:
                continue
            if arg == "setpoint_rpm":
                changes["setpoint_rad_s"] = v * math.pi / 30.0
            else:
                changes[field] = v
        if args.estimator is not None:
            changes["estimator"] = args.estimator
        if args.feedforward:
            changes["feedforward"] = True
        if changes:
            scene = scene.replace(origin="command line", **changes)
        if args.workers is not None and args.workers < 1:
            raise _UsageError(f"--workers {args.workers}: expected an integer >= 1")
        if args.json is not None and not args.json.resolve().parent.is_dir():
            raise _UsageError(f"--json {str(args.json)!r}: directory does not exist")
        if args.plots is not None and args.plots.exists() and not args.plots.is_dir():
            raise _UsageError(f"--plots {str(args.plots)!r}: exists and is not a directory")
        # Out-of-range loads are bad input too: check the motor can hold every level.
        from .equilibrium import operating_point

        for f in (scene.initial_load, *scene.final_loads):
            try:
                operating_point(plant, scene.setpoint_rad_s, f, "rigid")
            except SimulationError as exc:
                raise _UsageError(f"load {f:g} N out of range for {plant.name}: {exc}") from None
    except (_UsageError, argparse.ArgumentTypeError) as exc:
        print(f"prsa-tune: error: {exc}", file=sys.stderr)
        return 2
    except (PlantFileError, SceneError) as exc:
        print(f"prsa-tune: error: {exc}", file=sys.stderr)
        return 2

    try:
        from .autotune import tune_actuator

        rep = tune_actuator(plant, scene, workers=args.workers)
    except (SimulationError, ArithmeticError) as exc:
        print(f"prsa-tune: numerical failure: {exc}", file=sys.stderr)
        return 3
    except ValueError as exc:  # e.g. no gains meet the robustness bound
        print(f"prsa-tune: error: {exc}", file=sys.stderr)
        return 3
    rep.timing_s["process"] = time.perf_counter() - _T_START
    if args.plots is not None:
        from .plots import write_standard_plots

        args.plots.mkdir(parents=True, exist_ok=True)
        rep.plot_files = write_standard_plots(rep, args.plots)
    if args.json is not None:
        data = rep.as_dict()
        data["timing_s"] = dict(rep.timing_s)
        write_json_atomic(args.json, data)
    if not args.quiet:
        print(format_report(rep))
        if args.json is not None:
            print(f"JSON report: {args.json}")
        if args.plots is not None:
            print(f"plots: {', '.join(str(p) for p in rep.plot_files)}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())


def build_plot_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="prsa-plot", description="Bode and step-response plots for a plant and given gains (no tuning).")
    p.add_argument("--plant", default=None, metavar="NAME|PATH")
    p.add_argument("--scene", default=None, metavar="NAME|PATH")
    p.add_argument("--kp", type=_positive("--kp"), required=True, help="N m s/rad")
    p.add_argument("--ki", type=float, default=0.0, help="N m/rad")
    p.add_argument("--kd", type=float, default=0.0, help="N m s^2/rad")
    p.add_argument("--load-step", type=parse_load_step, metavar="N0:N1")
    p.add_argument("--setpoint-rpm", type=_positive("--setpoint-rpm"))
    p.add_argument("--out", type=Path, default=Path("prsa-plots"), metavar="DIR")
    return p


def plot_main(argv: Sequence[str] | None = None) -> int:
    """``prsa-plot``: plant and loop Bode plots, sensitivities, load-step and setpoint-step
    responses for given gains, written as PNG and SVG into ``--out``."""
    parser = build_plot_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        args = parser.parse_args(_attach_values(argv))
        warnings.showwarning = _show_warning
        from .controller import PID
        from .plant import load_plant
        from .scene import load_scene

        plant = load_plant(args.plant)
        scene = load_scene(args.scene)
        changes = {}
        if args.load_step is not None:
            changes["initial_load"], changes["final_loads"] = args.load_step[0], args.load_step[1][:1]
        if args.setpoint_rpm is not None:
            changes["setpoint_rad_s"] = args.setpoint_rpm * math.pi / 30.0
        if changes:
            scene = scene.replace(origin="command line", **changes)
        try:
            pid = PID(args.kp, args.ki, args.kd, tf=4 * plant.sample_time_s)
        except ValueError as exc:
            raise _UsageError(str(exc)) from None
        if args.out.exists() and not args.out.is_dir():
            raise _UsageError(f"--out {str(args.out)!r}: exists and is not a directory")
    except (_UsageError, argparse.ArgumentTypeError, PlantFileError, SceneError) as exc:
        print(f"prsa-plot: error: {exc}", file=sys.stderr)
        return 2
    try:
        from .plots import write_design_plots

        files = write_design_plots(plant, scene, pid, args.out)
    except (SimulationError, ArithmeticError) as exc:
        print(f"prsa-plot: numerical failure: {exc}", file=sys.stderr)
        return 3
    except ValueError as exc:  # e.g. destabilising gains
        print(f"prsa-plot: error: {exc}", file=sys.stderr)
        return 2
    print("\n".join(str(f) for f in files))
    return 0
