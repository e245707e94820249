"""The plant and scene flags that ``prsa-tune`` and ``prsa-plot`` share: their parser entries,
``--load-step`` parsing, and the plant and speed-loop scene with the overrides applied and checked
against each other (:func:`load_and_override`)."""

from __future__ import annotations

import argparse
import os
from typing import Any

from ..textsafe import quote
from ..options import rpm_to_rad_s
from ..errors import SceneError
from ..plant.plantfile import Plant, load_plant
from ..studies.scene import Scene, check_against_plant, load_scene, require_speed_scene
from ..studies.scenefilters import parse_filter_flag
from ..studies.scenekinds import problem
from ..studies.scenefile import SETPOINT_MAX_RPM, parse_load_step  # noqa: F401 (parse_load_step re-exported)
from .common import Run, UsageError, number, path_text

__all__ = ["parse_load_step", "scene_flags", "VALUE_FLAGS", "input_files", "load_and_override"]


def _load_step_flag(text: str) -> tuple[float, tuple[float, ...]]:
    try:
        return parse_load_step(text)
    except argparse.ArgumentTypeError as exc:
        raise argparse.ArgumentTypeError(f"--load-step {exc}") from None


def _filter_flag(text: str):
    try:
        return parse_filter_flag(text)
    except SceneError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def scene_flags(p: argparse.ArgumentParser) -> None:
    """The plant and scene flags of ``prsa-tune`` and ``prsa-plot``."""
    p.add_argument("--plant", default=None, type=path_text("--plant"), metavar="NAME|PATH",
                   help="built-in plant name or a plant .toml file (default: paper-iprsm)")
    p.add_argument("--scene", default=None, type=path_text("--scene"), metavar="NAME|PATH",
                   help="built-in scene name or a scene .toml file (default: paper-load-step); duty-cycle "
                        "scenes (load/setpoint profiles, CSV traces): duty-ramp, duty-trace")
    p.add_argument("--load-step", type=_load_step_flag, metavar="N0:N1[,N2...]",
                   help="initial and final axial load(s), N, compressive >= 0; at most what the motor can hold "
                        "at the setpoint (default: the scene's, 500:1500)")
    p.add_argument("--setpoint-rpm", metavar="RPM",
                   type=number("--setpoint-rpm", 0.0, SETPOINT_MAX_RPM, "rpm", "a nut speed", lo_open=True),
                   help=f"nut-speed setpoint, rpm, in (0, {SETPOINT_MAX_RPM:g}] (default: the scene's, 300)")
    p.add_argument("--filter", action="append", type=_filter_flag, default=None,
                   metavar="notch:path=torque|speed,centre_hz=F,width_hz=W[,depth_db=D] | "
                           "lowpass:path=torque|speed,corner_hz=F[,order=1|2][,damping=Z]",
                   help="a notch or low-pass filter on the torque command (path=torque) or the measured speed "
                        "(path=speed), Hz and dB, as in a scene's [filters] table; repeat for several (they "
                        "replace the scene's); in the loop models, the tuner, the verification and the export")
    p.add_argument("--verbose", action="store_true",
                   help="progress lines on stderr, solver diagnostics and notes about the plant (geometry)")


#: Flags of ``prsa-tune`` and ``prsa-plot`` whose value may start with ``-`` (:func:`prsa_ctrl.cli.common.attach_values`).
VALUE_FLAGS = {"--load-step", "--setpoint-rpm", "--step-time", "--duration", "--ms-max", "--mt-max", "--mks-max", "--kp",
                "--ki", "--kd", "--workers", "--rated-torque", "--seed", "--monte-carlo", "--motor",
                "--objective", "--controller", "--estimator", "--tune-filter", "--export-real", "--frequency-unit",
                "--filter"}  # (the choices too: '--objective -x' is refused naming '-x', not as a missing value)


def input_files(args, scene=None) -> list[str]:
    """Every file the run reads: the plant and scene files given as paths and the scene's CSV
    traces (the built-in files are protected by :func:`prsa_ctrl.io.output.package_roots`)."""
    files = []
    for v in (getattr(args, "plant", None), getattr(args, "scene", None)):
        if v is not None and os.path.exists(v):
            files.append(v)
    files.extend(getattr(scene, "input_files", ()))
    return files


def load_and_override(args, run: Run, plot: bool = False) -> tuple[Plant, Scene, list[str]]:
    """Plant and speed-loop scene with the command-line overrides, checked against each other;
    the flags that changed the scene, as typed."""
    plant = load_plant(args.plant)
    scene = require_speed_scene(load_scene(args.scene))
    changes: dict[str, Any] = {}
    typed: dict[str, str] = {}
    overrides: list[str] = []
    raw = {a.split("=", 1)[0]: a.split("=", 1)[1] for a in run.argv if a.startswith("--") and "=" in a}
    given = {flag: getattr(args, flag[2:].replace("-", "_"), None)
             for flag in ("--robust", "--monte-carlo", "--scheduler", "--estimator", "--load-step", "--step-time",
                          "--setpoint-rpm")}
    problem(scene).check_overrides(given, raw)  # what the scene's kind does not take, as typed
    if args.load_step is not None:
        initial, finals = args.load_step
        if plot:
            finals = finals[:1]
        changes["initial_load"], changes["final_loads"] = initial, finals
        typed["initial_load"] = typed["final_loads"] = f"--load-step {quote(raw.get('--load-step', ''))}"
        overrides.append(f"--load-step {raw.get('--load-step', '')}")
    if args.setpoint_rpm is not None:
        changes["setpoint_rad_s"] = rpm_to_rad_s(args.setpoint_rpm)
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
    if getattr(args, "filter", None):
        changes["filters"] = tuple(lf for lf, _, _ in args.filter)
        changes["filter_labels"] = tuple(label for _, _, label in args.filter)
        overrides.extend(flag for _, flag, _ in args.filter)
    if changes:
        try:
            scene = scene.replace(origin="command line", **changes)
        except SceneError as exc:
            raise UsageError(_cross_check_message(exc, typed, scene, changes)) from None
    check_against_plant(scene, plant, typed)
    return plant, scene, overrides


def _cross_check_message(exc: SceneError, typed: dict[str, str], scene, changes: dict) -> str:
    """A scene field rejected after overrides: say it with the flags as typed."""
    msg = str(exc)
    if msg.startswith("command line: duration") and ("duration" in typed or "step_time" in typed) and problem(scene).takes("step-time"):
        who = " and ".join(typed[k] for k in ("step_time", "duration") if k in typed)
        st = changes.get("step_time", scene.step_time)
        du = changes.get("duration", scene.duration)
        return f"{who}: the record ends at {du:g} s, before the load step at {st:g} s has any response; expected a duration beyond the step time"
    return msg.replace("command line: ", "command line (with " + ", ".join(typed.values()) + "): ") if typed else msg
