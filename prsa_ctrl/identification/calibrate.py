"""Calibration as a library call: drive logs -> fit -> the fitted plant file's text and report.

What ``prsa-fit DATA.csv --out PLANT.toml --json REPORT.json`` does between reading its flags
and writing its files, for the command and for the browser app alike:

* :func:`fitted_plant_text`: the fitted plant file (the base file's layout and comments kept,
  :meth:`prsa_ctrl.plant.plantfile.Plant.to_toml`): the fitted keys, a command delay that is not
  the base's, the ``[uncertainty]`` entries that changed, the description naming the logs, and
  with ``force`` the header saying the plant was not validated;
* :func:`fit_report`: the JSON report (:meth:`FitResult.as_dict` and the coordinates);
* :func:`result_lines`: the report's text lines (values with 95 % intervals, fit %, warnings,
  coordinates, validation);
* :func:`calibrate_logs`: all of it from log files and a base plant, with ``prsa-fit``'s
  defaults (the app's calibration: :meth:`prsa_ctrl.app.session.AppSession.calibrate`);
* :func:`calibrate_frf`: the same from measured frequency responses (``prsa-fit --frf``: the
  structure the data choose, rigid or two-mass).

Nothing here writes a file or prints: the caller writes the text atomically
(:func:`prsa_ctrl.io.output.write_text`) and shows the lines.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

from ..errors import DataError, FitError, GeometryWarning, PlantFileError
from ..textsafe import printable

__all__ = ["MOTOR_COORDINATES", "Calibrated", "calibrate_logs", "fitted_plant_text", "fit_report", "result_lines",
           "validation_lines", "not_explained_line",
           "mat_log_refusal", "linear_axis_refusal", "calibrate_frf", "frf_point_check", "written_keys", "fitted_description", "structure_lines",
           "written_mode", "mode_line"]

#: Coordinates of a screw-driven plant file and of the logs it is fitted to, as reports state them.
from ..options import MOTOR_COORDINATES  # noqa: E402 - defined once, re-exported here


def fitted_description(base, result, fitted_from: str) -> str:
    """The fitted plant's description: the base, the logs, the keys fitted and kept."""
    return (f"{base.name} calibrated by prsa-fit from {fitted_from}"
            + (f" (fitted: {', '.join(result.plant_keys)}" if result.plant_keys else " (no key identifiable")
            + (f"; kept at the base values: {', '.join(result.kept_base)})" if result.kept_base else ")")
            + (f"; base: {base.description}" if base.description else ""))


def written_keys(base, result) -> tuple[list[str], list[str]]:
    """``(keys, uncertainty_keys)`` the fitted plant file rewrites: the fitted keys and the
    command delay, current-loop bandwidth or breakaway level that the fit changed from the
    base's, and the axial-mode keys a compliant fit started from a measured response
    (:func:`~prsa_ctrl.identification.compliant.seed_keys`: the plant fitted and validated has
    them; the file kept the base's); the ``[uncertainty]`` entries (and
    correlation) that differ from the base's."""
    from .compliant import seed_keys

    from ..plant.uncertainty import CORRELATION_KEY

    base_unc = dict(base.uncertainty or {})
    fitted_unc = dict(result.plant.uncertainty or {})  # (an entry that no longer held a written value: replaced or gone)
    unc_keys = [k for k in dict.fromkeys([*result.plant_keys, *base_unc, *fitted_unc, CORRELATION_KEY])
                if fitted_unc.get(k) != base_unc.get(k)]
    # the command delay (found, given or written from a fitted FRF delay) is written when it is not the base's
    delay_keys = [k for k in ("drive.command_delay_samples", "drive.current_loop_bandwidth_hz",
                              "friction.no_load_breakaway_torque_n_m", *seed_keys(base))  # (a given one raised to a fitted drag)
                  if k not in result.plant_keys and k in base.values and result.plant.values[k] != base.values[k]
                  and not (k == "friction.no_load_breakaway_torque_n_m" and k in result.plant.defaulted)]
    return [*result.plant_keys, *delay_keys], unc_keys


def fitted_plant_text(result, base, base_text: str, name: str, fitted_from: str, force: bool = False,
                      origin: str = "the fitted plant") -> str:
    """The fitted plant file's text (checked: it loads as a plant, with its ``[uncertainty]``).

    Parameters
    ----------
    result : FitResult
        The fit.
    base : Plant
        The base plant (``base_text`` parsed).
    base_text : str
        The base plant file: its layout and comments are kept.
    name : str
        The fitted plant's name (``prsa-fit``: the stem of ``--out``).
    fitted_from : str
        The logs, as the description names them.
    force : bool
        The fit's validation failed and the file is written all the same (``--force``): the
        header says so, with the diagnosis.
    origin : str
        How a failed check names the file.

    Raises
    ------
    FitError
        When the text would not load (a fault of the fit's composition, not of the user's input:
        ``prsa-fit`` exits 3 and writes nothing).
    """
    import tomllib

    from ..plant.plantfile import Plant

    keys, unc_keys = written_keys(base, result)
    validation = result.solver.get("validation")
    header: tuple[str, ...] = ()
    if force and validation is not None and not validation["passes"]:
        header = ("prsa-fit --force: NOT VALIDATED, this plant does not explain the data it was fitted to: "
                  f"{validation['diagnosis']}", str(validation["reasons"][0]))
    text = result.plant.to_toml(base_text, name=name, keys=keys, description=fitted_description(base, result, fitted_from),
                                uncertainty_keys=unc_keys, header=header)
    with warnings.catch_warnings():  # its geometry notes are the base plant's, given when it loaded
        warnings.simplefilter("ignore", GeometryWarning)
        try:  # what is written must load (with its [uncertainty])
            Plant.from_dict(tomllib.loads(text), origin=origin)
        except PlantFileError as exc:  # the tool's own fault, never the user's input (not exit 2)
            raise FitError(f"the fitted plant's file would not load, so none is written ({exc}); a fault of "
                           "prsa-fit, not of the input: please report it") from exc
    return text


def written_mode(result, plant_text: str | None, speed_rad_s: float, load_n: float) -> dict | None:
    """The first axial mode of the plant file a compliant fit writes, at an operating point: its
    compliant model linearised at ``speed_rad_s`` (rad/s) and ``load_n`` (N)
    (:func:`prsa_ctrl.identification.frf.axial_mode`), as the report states it: ``value`` (Hz),
    ``antiresonance_hz``, ``damping_ratio``, ``speed_rad_s``, ``load_n``.

    The point is part of the number: with the nut loss on the whole transmitted force the
    motor-side inertia of the mode depends on the nut force (the foreign feed axis's FRF-fitted
    plant: 106.68 Hz at 0 N, 107.94 Hz at 800 N, 105.40 Hz at -800 N; its anti-resonance 94.64 Hz
    at every load). ``None`` for a rigid fit (its plant's stiffness is the datasheet's, not
    fitted), a plant without the text, a mechanism without an axial mode, or no oscillatory mode
    at the point."""
    if plant_text is None or result.solver.get("fidelity") != "compliant":
        return None
    import tomllib

    from ..plant.plantfile import Plant
    from .frf import axial_mode

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the base plant's geometry notes were given when it loaded
        plant = Plant.from_dict(tomllib.loads(plant_text), origin="written")
        try:
            m = axial_mode(plant, speed_rad_s=float(speed_rad_s), load_n=float(load_n))
        except ValueError:
            return None
    anti = m["antiresonance_hz"]
    return {"value": m["resonance_hz"], "unit": "Hz", "antiresonance_hz": anti if math.isfinite(anti) else None,
            "damping_ratio": m["damping_ratio"], "speed_rad_s": float(speed_rad_s), "load_n": float(load_n),
            "of": "the written plant's compliant model linearised at this operating point"}


def mode_line(mode: Mapping[str, Any]) -> str:
    """The report's line of :func:`written_mode`: the mode with the point it is computed at."""
    anti = mode.get("antiresonance_hz")
    return (f"axial mode of the written plant {mode['value']:.5g} Hz"
            + (f", anti-resonance {anti:.5g} Hz" if anti is not None else "")
            + f" (its compliant model at {mode['speed_rad_s']:g} rad/s, {mode['load_n']:g} N; the mode moves with the "
            "nut force)")


def fit_report(result, coordinates: Mapping[str, str], choice=None, *, point: tuple[float, float] | None = None,
               mode: Mapping[str, Any] | None = None) -> dict:
    """The JSON report: :meth:`FitResult.as_dict` and ``coordinates`` (the plant's and each log's);
    with a frequency-response structure ``choice`` that chose the two-mass model, also
    ``frf_axial_mode_hz`` and ``frf_antiresonance_hz`` (value and 95 % interval, Hz; with
    ``point`` = (speed rad/s, load N) the response's operating point, as ``speed_rad_s`` and
    ``load_n``): the mode the response shows there; with ``mode`` (:func:`written_mode`) the
    written plant's mode at its stated point as ``axial_mode_hz`` (the written plant's
    ``--show-plant`` mode is the series formula's, without the load or the nut loss)."""
    report = {**result.as_dict(), "coordinates": {"plant": MOTOR_COORDINATES, "logs": dict(coordinates)}}
    if choice is not None and choice.structure == "two-mass" and choice.two_mass is not None:
        v = choice.two_mass.values
        at = {} if point is None else {"speed_rad_s": float(point[0]), "load_n": float(point[1])}
        report["frf_axial_mode_hz"] = {**v["resonance_hz"], **at}
        report["frf_antiresonance_hz"] = {**v["antiresonance_hz"], **at}
    if mode is not None:
        report["axial_mode_hz"] = dict(mode)
    return report


def _ci_text(v: Mapping[str, Any], fmt: str = ".4g") -> str:
    """A value with its 95 % interval; one held (at a bound of the fit, or given) with its note
    instead: no interval."""
    if v.get("ci95") is None:
        return f"{v['value']:{fmt}} ({v.get('note', 'held, not fitted')})"
    return f"{v['value']:{fmt}} (95 % CI {v['ci95'][0]:{fmt}}..{v['ci95'][1]:{fmt}})"


def structure_lines(choice, point: tuple[float, float] | None = None) -> list[str]:
    """The structure an FRF chose, why, and the two-mass model's mode with intervals, at the
    response's operating ``point`` (speed rad/s, load N) when given."""
    out = [f"structure: {choice.structure} ({choice.reason})"]
    two = choice.two_mass
    if two is not None and choice.structure == "two-mass":
        v = two.values
        at = "" if point is None else f" at the response's operating point {point[0]:g} rad/s, {point[1]:g} N"
        out.append(f"  axial mode {_ci_text(v['resonance_hz'])} Hz, anti-resonance {_ci_text(v['antiresonance_hz'])} Hz"
                   f"{at}, damping ratio {_ci_text(v['damping_ratio'], '.3g')}")
        out.append(f"  total inertia {_ci_text(v['total_inertia_kg_m2'])} kg m^2 = motor side "
                   f"{_ci_text(v['motor_inertia_kg_m2'])} + load side {_ci_text(v['load_inertia_kg_m2'])}; stiffness "
                   f"{_ci_text(v['stiffness_n_m_per_rad'])} N m/rad; current loop "
                   f"{_ci_text(v['current_loop_bandwidth_hz'])} Hz; delay {_ci_text(v['delay_s'], '.3g')} s")
    return out


def validation_lines(v: Mapping[str, Any]) -> list[str]:
    """The validation's per-log lines (:mod:`prsa_ctrl.identification.validation`), one line each
    (the logs' names made printable: :func:`prsa_ctrl.textsafe.printable`)."""
    out = [f"validation ({v['replay']}):"]
    for part, what in (("written_plant", "plant as written"), ("cross_validation", "left out, fitted on the others")):
        for name, e in (v.get(part) or {}).items():
            if "failed" in e:
                out.append(f"  {name} ({what}): the fit failed: {e['failed']}")
                continue
            w = e.get("whiteness")
            out.append(f"  {name} ({what}): replay fit {e['fit_percent']:.2f} %, error {e['error_rms_rad_s']:.4g} rad/s = "
                       f"{e['error_rms_rad_s'] / max(e['noise_floor_rad_s'], 1e-300):.3g} x the noise floor "
                       f"{e['noise_floor_rad_s']:.3g} rad/s, {'explained' if e['explained'] else 'NOT explained'}"
                       + (f"; residual autocorrelation lag 1 {w['acf'][1]:+.2f} (white band +/- {w['band']:.2g})"
                          if w else ""))
    out.append(f"  rule: {v['rule']}")
    out.append("  verdict: " + ("the plant explains the data" if v["passes"] else "NOT validated: " + "; ".join(v["reasons"])))
    return [printable(x) for x in out]  # one line each: a log named with a line feed cannot forge a line


def result_lines(result, coordinates: Mapping[str, str], choice=None, *, point: tuple[float, float] | None = None,
                 mode: Mapping[str, Any] | None = None) -> list[str]:
    """The fit's report as text lines (what ``prsa-fit`` prints before ``wrote ...``): values with
    95 % intervals, the command delay and friction map when found, the reflected inertia, the
    FRF structure (``choice``, its mode at the response's operating ``point``), the written
    plant's axial mode at its point (``mode``, :func:`written_mode`), fit % per record, warnings,
    coordinates, validation. One line
    each: the logs' names and the warnings made printable (:func:`prsa_ctrl.textsafe.printable`:
    a line feed in a file name is ``\\n``, not a line of its own)."""
    from .common import unit_text

    out = []
    for k, v in result.parameters.items():
        u = unit_text(v["unit"])
        if v.get("ci95") is None:  # held at a bound of the fit: no interval
            out.append(f"{k} = {v['value']:.6g}{u} ({v.get('note', 'held, not fitted')})")
            continue
        lo, hi = v["ci95"]
        line = f"{k} = {v['value']:.6g}{u} (95 % CI {lo:.6g}..{hi:.6g})"
        if v.get("kept_base"):
            line += f"; not identifiable, the plant keeps the base value {v['written']:.6g}{u}"
        out.append(line)
    if result.delay is not None:
        out.append(f"  ({result.delay['plant_file']})")
    fmap = result.solver.get("friction_map")
    if fmap is not None:
        out.append(f"friction map: {len(fmap['plateaus'])} steady-speed plateau(s), {fmap.get('in_stribeck_region', 0)} "
                   f"below {fmap['criteria']['stribeck_region_speeds']:g} Stribeck speeds; Stribeck intervals "
                   f"{fmap.get('intervals', 'not computed (too few plateaus)')}")
    cd = result.solver.get("command_delay")
    if cd is not None:
        status = cd.get("status") or ("decided" if (cd.get("search") or {}).get("decided") else "undecided")
        undecided = ("search" in cd or "continuous" in cd) and status.startswith("undecided")
        out.append(f"command delay: {'undecided, fitted at ' if undecided else ''}{cd['shift_samples']} sample(s) from "
                   f"the logged command (logged as {cd['command_logged']}) to its action, drive.command_delay_samples = "
                   f"{cd['drive_command_delay_samples']} ({cd['how']}"
                   + ((f", {status}" if "continuous" in cd else "") if "search" not in cd else
                      f", {status}; objective per delay " + ", ".join(f"{k}: {v:.6g}" if v is not None else f"{k}: failed"
                                                                     for k, v in cd["search"]["objective"].items())
                      + ("; the refit at it on the asked segments failed: the values written are the search's"
                         if cd["search"].get("refit_failed") else "")) + ")")
    j = result.reflected_inertia_kg_m2
    out.append(f"reflected inertia = {j['value']:.6g} kg m^2 (95 % CI {j['ci95'][0]:.6g}..{j['ci95'][1]:.6g})")
    if choice is not None:
        out += structure_lines(choice, point)
    if mode is not None:
        out.append(mode_line(mode))
    for f, pct in result.fit_percent.items():
        out.append(f"fit {pct:.2f} % on {f}" if math.isfinite(pct) else
                   f"fit n/a on {f} (the measured response does not vary: a normalised fit is not defined)")
    out += [f"warning: {w}" for w in result.warnings]
    out.append(f"coordinates: {MOTOR_COORDINATES}")
    out += [f"  {f}: logged in {how}" for f, how in coordinates.items()]
    validation = result.solver.get("validation")
    if validation is not None:
        out += validation_lines(validation)
    return [printable(x) for x in out]  # one line each: a log (or warning) naming a line feed cannot forge a line


def not_explained_line(result, force: bool = False) -> str | None:
    """The one line of a fit whose validation failed (None when it passed or did not run)."""
    v = result.solver.get("validation")
    if v is None or v["passes"]:
        return None
    from .validation import refusal

    return (refusal(v["diagnosis"])
            + (" (--force: the plant file was written all the same)" if force else
               " (no plant file written; --force writes it)"))


@dataclass(frozen=True)
class Calibrated:
    """What :func:`calibrate_logs` made of the logs.

    Attributes
    ----------
    result : FitResult
        The fit (``status``: ``"ok"``, or ``"flagged: ..."`` when the validation failed).
    plant_text : str or None
        The fitted plant file's text; None when the validation failed (``prsa-fit`` writes no
        plant file then).
    report : dict
        The JSON report (:func:`fit_report`).
    lines : tuple of str
        The report's text lines (:func:`result_lines`).
    failure : str or None
        :func:`not_explained_line` when the validation failed.
    records : tuple of Record
        The logs as read (named by their labels): the fit's views
        (:func:`prsa_ctrl.plots.fit.fit_views`) replay them.
    choice : StructureChoice or None
        :func:`calibrate_frf`: the structure the responses chose.
    """

    result: Any
    plant_text: str | None
    report: dict
    lines: tuple[str, ...]
    failure: str | None = None
    records: tuple = ()
    choice: Any = None


def mat_log_refusal(path: str) -> str:
    """The one line refusing a MATLAB ``.mat`` log given without a log description."""
    return (f"{path!r}: a MATLAB .mat log is read through a log description; expected --log-format FILE.toml "
            "(an example: examples/emps/log.toml)")


def linear_axis_refusal(base: str | None) -> str:
    """The one line refusing a ``linear-axis`` base plant for records in motor coordinates."""
    return (f"--plant {base}: mechanism = \"linear-axis\" (load coordinates: m, N); expected a screw-driven plant "
            "for records in motor coordinates (a linear axis is fitted from its log with --log-format FORMAT.toml, "
            "or from its measured frequency response in m/s per N with --frf alone)")


def calibrate_logs(paths: Sequence[str | Path], base: str | None = None, *, name: str,
                   labels: Sequence[str] | None = None,
                   check_interrupt: Callable[[], None] | None = None, log_format: str | None = None) -> Calibrated:
    """Fit a base plant to drive logs with ``prsa-fit``'s defaults and compose its outputs.

    The same steps, checks and messages as ``prsa-fit LOG... [--plant BASE] --out NAME.toml
    --json REPORT.json``: a MATLAB ``.mat`` log is refused (it needs a log description), a
    ``linear-axis`` base is refused, the fitted file's text is checked before the fit, the logs
    are read (:func:`prsa_ctrl.identification.data.load_record`), the command delay is searched,
    the fitted plant is validated (with several logs, cross-validated).

    Parameters
    ----------
    paths : sequence of path-like
        The logs (CSV, motor coordinates).
    base : str, optional
        Built-in plant name or plant file path (default: the default plant).
    name : str
        The fitted plant's name.
    labels : sequence of str, optional
        How the results name each log (default: the path as given): the records' names, the
        description, the report's ``fit_percent`` and ``coordinates``.
    check_interrupt : callable, optional
        Called at every iteration and after every simulation of the fit; an exception it raises
        ends the fit (the caller's cancellation).
    log_format : str, optional
        A log description (``--log-format``): the logs (CSV or ``.mat``) are read through it in
        the plant's motor coordinates (a log in load coordinates converted with the lead,
        :func:`prsa_ctrl.identification.logformat.load_motor_record`), the command convention is
        its ``[command] logged``.

    Returns
    -------
    Calibrated

    Raises
    ------
    DataError, PlantFileError, ValueError
        Bad input (one line naming the file and the value: ``prsa-fit``'s exit 2).
    FitError
        The fit did not converge (``prsa-fit``'s exit 3).
    """
    from dataclasses import replace

    from ..options import check_number
    from ..plant.plantfile import load_plant, plant_file_path
    from .common import FITTABLE
    from .data import load_record
    from .timedomain import fit_plant

    paths = [str(p) for p in paths]
    labels = list(paths) if labels is None else [str(x) for x in labels]
    if len(labels) != len(paths):
        raise ValueError(f"labels: {len(labels)} for {len(paths)} logs; expected one per log")
    mat = next((p for p in paths if p.lower().endswith(".mat")), None)
    if mat is not None and log_format is None:
        raise DataError(mat_log_refusal(mat))
    plant = load_plant(base)
    if plant.mechanism == "linear-axis":
        raise PlantFileError(linear_axis_refusal(base))
    base_text = plant_file_path(base).read_bytes().decode("utf-8")  # CR LF kept for the writer
    plant.to_toml(base_text, name=name, keys=[k for k in FITTABLE if k in plant.values], description="check")
    records, logged, coordinates = [], "applied", {label: MOTOR_COORDINATES for label in labels}
    if log_format is not None:
        from .logformat import MOTOR_CONVENTION, load_log_format, load_motor_record

        fmt = load_log_format(log_format)
        logged = MOTOR_CONVENTION[fmt.doc["command"].get("logged", "as-computed")]
        if fmt.doc.get("axis", "linear") == "linear":
            how = (f"load (position m, force N), converted with the lead {plant.lead_per_rad:.9g} m/rad: angle = "
                   "position / lead, torque = force x lead")
            coordinates = {label: how for label in labels}
    for path, label in zip(paths, labels):
        rec = load_record(path) if log_format is None else load_motor_record(path, fmt, plant)[0]
        records.append(replace(rec, name=label, warnings=tuple(w.replace(path, label) for w in rec.warnings)))
    result = fit_plant(records, plant, fidelity="rigid", validate=[], segment_s=0.1, delay_samples="find",
                       command_logged=logged, uncertainty="keep", check_interrupt=check_interrupt,
                       cross_validate=True, closed_loops={})
    if check_interrupt is not None:
        check_interrupt()
    failure = not_explained_line(result)
    text = None if failure else fitted_plant_text(result, plant, base_text, name, ", ".join(Path(x).name for x in labels),
                                                  origin=name)
    return Calibrated(result, text, fit_report(result, coordinates), tuple(result_lines(result, coordinates)), failure,
                      tuple(records))


#: ``prsa-fit --frf-speed``'s default: the nut speed of a measured response (rad/s).
FRF_SPEED_DEFAULT_RAD_S = 30.0
#: ``prsa-fit --coherence-min``'s default: response points below this coherence are dropped.
FRF_COHERENCE_MIN_DEFAULT = 0.8


def frf_point_check(plant, speed_rad_s: float, load_n: float, typed: Mapping[str, str] | None = None) -> None:
    """Refuse a measurement's operating point the plant cannot be linearised at: ValueError,
    one line naming the flag (``--frf-speed`` or ``--frf-load``) and its value as typed
    (``typed[flag]``; else the number's repr)
    (:func:`prsa_ctrl.identification.common.frf_operating_point_error`)."""
    from .common import frf_operating_point_error

    bad = frf_operating_point_error(plant, speed_rad_s, load_n)
    if bad:
        flag, value = ("--frf-speed", speed_rad_s) if bad[0] == "speed" else ("--frf-load", load_n)
        raise ValueError(f"{flag} {(typed or {}).get(flag, repr(value))}: {bad[1]}")


def calibrate_frf(paths: Sequence[str | Path], base: str | None = None, *, name: str,
                  labels: Sequence[str] | None = None, speed_rad_s: float = FRF_SPEED_DEFAULT_RAD_S,
                  load_n: float = 0.0, coherence_min: float = FRF_COHERENCE_MIN_DEFAULT,
                  sample_time_s: float | None = None,
                  fidelity: str | None = None, command_logged: str = "applied", uncertainty: str = "keep",
                  force: bool = False, origin: str | None = None, typed: Mapping[str, str] | None = None,
                  extra: Sequence = (), fitted_from: str | None = None,
                  coordinates: Mapping[str, str] | None = None, band: tuple[float, float] | None = None) -> Calibrated:
    """Fit a base plant to measured frequency responses with ``prsa-fit``'s defaults:
    ``prsa-fit --frf FRF.csv... [--plant BASE] --out NAME.toml --json REPORT.json``.

    The same checks and messages as the command: the operating point (``--frf-speed``,
    ``--frf-load``) checked against the plant, the fitted file's text checked before the fit, the
    responses read (:func:`prsa_ctrl.identification.data.load_frf`), the rigid and the two-mass
    model fitted and the structure the data choose
    (:func:`prsa_ctrl.identification.frfplant.fit_frf_structure`, ``--fidelity`` not given). A
    ``linear-axis`` base is fitted (its response in (m/s)/N), as the command does with ``--frf``
    alone.

    Parameters
    ----------
    paths : sequence of path-like
        The responses (CSV: ``frequency_hz`` and ``magnitude_db, phase_deg`` or ``real, imag``,
        optionally ``coherence``).
    base : str, optional
        Built-in plant name or plant file path (default: the default plant).
    name : str
        The fitted plant's name.
    labels : sequence of str, optional
        How the results name each response (default: the path as given).
    speed_rad_s : float, rad/s
        Nut speed during the measurement (``--frf-speed``).
    load_n : float, N
        Axial load during the measurement (``--frf-load``).
    coherence_min : float
        Points below this coherence are dropped (``--coherence-min``, 0 <= C < 1).
    sample_time_s : float, s, optional
        Sample time of the drive that measured the responses (``--frf-sample-time``; None: the
        plant's; 0: continuous-time responses).
    fidelity : {None, "rigid", "compliant"}
        ``--fidelity`` (None: the structure the data choose).
    command_logged : {"applied", "computed"}
        ``--command-logged``.
    uncertainty : {"keep", "fit"}
        The written keys' ``[uncertainty]`` entries (``fit``: ``--uncertainty-from-fit``).
    force : bool
        ``--force`` (the plant file's header says when it was not validated).
    origin : str, optional
        How a failed check of the fitted file names it (default ``name``; ``prsa-fit``: ``--out``).
    typed : mapping, optional
        ``{flag: value as typed}`` for the messages (``prsa-fit``'s ``--frf-speed``, ``--frf-load``).
    extra : sequence of FrfRecord
        Responses already made (``prsa-fit --frf-from-logs``), fitted after the files'.
    fitted_from : str, optional
        What the description names (default: the files' names).
    coordinates : mapping, optional
        ``{log: coordinates}`` the report and lines state (default none: responses only).
    band : (float, float), Hz, optional
        ``--frf-band``: fit the points in ``[fmin, fmax]`` only
        (:mod:`prsa_ctrl.identification.frfband`; ``typed["--frf-band"]`` the band as typed);
        the report's ``frf_band`` and lines name the band and the resonances the model omits.

    Returns
    -------
    Calibrated
        ``choice`` the structure the data chose; ``report`` also holds ``frf_structure``: ``{"structure", "reason", "lines"}`` (the
        structure the data chose, why, and the two-mass model's mode and anti-resonance with
        their 95 % intervals, :func:`structure_lines`).

    Raises
    ------
    DataError, PlantFileError, ValueError
        Bad input (``prsa-fit``'s exit 2).
    FitError
        The fit did not converge or its plant is refused (``prsa-fit``'s exit 3, no plant file).
    """
    from dataclasses import replace

    from ..options import check_number
    from ..plant.plantfile import load_plant, plant_file_path
    from .common import FITTABLE
    from .data import load_frf
    from .frfplant import fit_frf_structure

    paths = [str(p) for p in paths]
    labels = list(paths) if labels is None else [str(x) for x in labels]
    if len(labels) != len(paths) or not (paths or extra):
        raise ValueError(f"labels: {len(labels)} for {len(paths)} responses; expected one per response, at least one")
    coherence_min = check_number("coherence_min", coherence_min, 0.0, 1.0, hi_open=True)
    plant = load_plant(base)
    base_text = plant_file_path(base).read_bytes().decode("utf-8")
    plant.to_toml(base_text, name=name, keys=[k for k in FITTABLE if k in plant.values], description="check")
    if paths:
        frf_point_check(plant, speed_rad_s, load_n, typed)
    frfs = []
    for path, label in zip(paths, labels):
        fr = load_frf(path, speed_rad_s=speed_rad_s, load_n=load_n, coherence_min=coherence_min,
                      sample_time_s=sample_time_s)
        frfs.append(replace(fr, name=label, warnings=tuple(w.replace(path, label) for w in fr.warnings)))
    frfs += list(extra)
    result, choice = fit_frf_structure(frfs, plant, fidelity=fidelity, command_logged=command_logged,
                                       uncertainty=uncertainty, band=band, band_typed=(typed or {}).get("--frf-band"))
    failure = not_explained_line(result, force)
    coordinates = dict(coordinates or {})
    fitted_from = ", ".join(Path(x).name for x in labels) if fitted_from is None else fitted_from
    text = None if failure and not force else fitted_plant_text(result, plant, base_text, name, fitted_from, force=force,
                                                                origin=name if origin is None else origin)
    point = (frfs[0].speed_rad_s, frfs[0].load_n)  # the plant keys are mapped at the first response's point
    mode = written_mode(result, text, *point)
    from .frfband import band_lines

    band_info = result.solver.get("frf_band")
    report = {**fit_report(result, coordinates, choice, point=point, mode=mode),
              "frf_structure": {"structure": choice.structure, "reason": choice.reason,
                                "lines": structure_lines(choice, point)}}
    if band_info:
        report["frf_band"] = dict(band_info)
    lines = [*band_lines(band_info), *result_lines(result, coordinates, choice, point=point, mode=mode)]
    return Calibrated(result, text, report, tuple(printable(x) for x in lines), failure, (), choice)
