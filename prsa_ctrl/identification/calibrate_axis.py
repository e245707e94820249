"""Calibration from described logs as a library call (``prsa-fit LOG... --log-format FORMAT.toml``):
logs as drives and test benches write them (CSV or MATLAB ``.mat``, :mod:`prsa_ctrl.identification.logformat`).

* :func:`axis_base_plant`: the base plant of a linear-axis fit: a ``linear-axis`` plant file, or one
  built from what the logs say (drive gain, sample time, force limit, encoder resolution) with the
  schema's defaults for the rest (what ``prsa-fit LOG --log-format F [--plant BASE.toml]`` uses);
* :func:`calibrate_described`: the whole calibration, for the browser app: a description in load
  coordinates (``axis = "linear"``) fits a ``linear-axis`` plant
  (:func:`prsa_ctrl.identification.axis.fit_linear_axis`, closed-loop replay from the reference
  where the description gives the controller; the two-mass axis when the data choose it,
  :func:`choose_structure`), validated (no plant text when it does not explain the logs); one in motor coordinates (``axis = "rotary"``)
  fits the screw-driven base as ``prsa-fit LOG --log-format F --plant BASE`` does
  (:func:`prsa_ctrl.identification.calibrate.calibrate_logs` with the description).

Nothing here writes a file or prints (the caller writes the text and shows the lines).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Callable, Sequence

__all__ = ["axis_base_plant", "calibrate_described", "choose_structure", "axis_outputs", "LOG_FACTS", "BASE_KEPT"]

#: Keys the log states and a base plant also gives: a disagreement is refused (the log's value is
#: a fact of the record: the drive gain converts every logged command to force, the sample time is
#: the controller's) or warned about and the base's value kept (the drive's force limit can exceed
#: the controller's saturation, which the replay applies anyway; the encoder resolution is not fitted).
LOG_FACTS = ("drive.gain_n_per_unit", "sensor.sample_time_s")
BASE_KEPT = ("drive.force_limit_n", "sensor.encoder_resolution_m")
_UNITS = {"drive.gain_n_per_unit": "N per command unit", "sensor.sample_time_s": "s", "drive.force_limit_n": "N",
          "sensor.encoder_resolution_m": "m"}


def axis_base_plant(logs: Sequence, log_format: str, plant_path: str | None = None):
    """The base plant of a linear-axis fit: ``plant_path`` (a linear-axis plant file) or one built
    from what the logs say, with the schema's defaults (:data:`prsa_ctrl.plant.schema.DEFAULTS`) for
    every other key; the drive gain, sample time, force limit and encoder resolution of the logs fill
    the built plant and are checked against a base file (:data:`LOG_FACTS` refused when they
    disagree, :data:`BASE_KEPT` kept from the base with a warning).

    Parameters
    ----------
    logs : sequence of AxisLog
        The logs (:func:`prsa_ctrl.identification.logformat.load_axis_log`), of one axis.
    log_format : str
        The description's path (its name is the built plant's source).
    plant_path : str, optional
        ``--plant``: a linear-axis plant file.

    Returns
    -------
    (LinearAxisPlant, list of str)
        The base and its warnings.

    Raises
    ------
    ValueError
        One line naming the log or ``--plant`` and the value (``prsa-fit``'s exit 2).
    """
    import numpy as np

    from .axis import LinearAxisPlant, check_force_limit, load_axis_plant, logged_force_peak

    lg = logs[0]
    fmt_name = Path(log_format).name
    log_name = Path(lg.name).name
    for other in logs[1:]:
        if not math.isclose(other.gain_n_per_unit, lg.gain_n_per_unit, rel_tol=1e-9):
            raise ValueError(f"{other.name}: drive gain {other.gain_n_per_unit:g} differs from {lg.name}'s "
                             f"{lg.gain_n_per_unit:g}; expected logs of one axis")
    vals, srcs = {}, {}
    vals["drive.gain_n_per_unit"] = lg.gain_n_per_unit
    srcs["drive.gain_n_per_unit"] = f"log: {lg.sources.get('gain', fmt_name)}"
    vals["sensor.sample_time_s"], srcs["sensor.sample_time_s"] = lg.sample_time_s, f"log: {fmt_name}"
    if lg.controller is not None and math.isfinite(lg.controller.saturation):
        vals["drive.force_limit_n"] = lg.controller.saturation * lg.gain_n_per_unit
        srcs["drive.force_limit_n"] = f"log: {fmt_name} [controller] saturation x drive gain"
        peak, where = logged_force_peak(logs)
        if peak > vals["drive.force_limit_n"]:  # a test signal added after the controller's saturation
            vals["drive.force_limit_n"] = peak
            srcs["drive.force_limit_n"] = (f"log: the largest logged force, in {Path(where).name} (above {fmt_name}'s "
                                           "[controller] saturation x drive gain: the test signal is added after it)")
    if lg.resolution_m is not None:
        vals["sensor.encoder_resolution_m"] = lg.resolution_m
        srcs["sensor.encoder_resolution_m"] = f"log: {fmt_name} [position] resolution"
    if plant_path:
        base, notes = _merge_base(load_axis_plant(plant_path), plant_path, vals, srcs)
        check_force_limit(base.values.get("drive.force_limit_n", math.inf), logs, f"--plant {plant_path}")
        return base, notes
    if "drive.force_limit_n" not in vals:
        peak = max(float(np.max(np.abs(g.gain_n_per_unit * g.command))) for g in logs)
        vals["drive.force_limit_n"] = max(peak, 1e-3)
        srcs["drive.force_limit_n"] = (f"estimate: largest force in {log_name} (no controller saturation described; "
                                       "give the drive's limit with --plant)")
    if "sensor.encoder_resolution_m" not in vals:
        steps = np.abs(np.diff(lg.position_m))
        steps = steps[steps > 0]
        res = float(steps.min()) if steps.size else 0.0
        vals["sensor.encoder_resolution_m"] = min(max(res, 1e-10), 1e-2)
        srcs["sensor.encoder_resolution_m"] = (f"estimate: smallest position step in {log_name}" if 1e-10 <= res <= 1e-2
                                               else f"estimate: {log_name} holds no plausible position step; the "
                                                    "finest resolution the schema accepts (not used by the fit)")
    vals["axis.mass_kg"], srcs["axis.mass_kg"] = 1.0, "default: placeholder, replaced by the fit"
    doc: dict = {"name": "base", "mechanism": "linear-axis", "coordinates": "load"}
    for k, v in vals.items():
        sec, key = k.split(".")
        doc.setdefault(sec, {})[key] = {"value": float(v), "source": srcs[k]}
    doc["drive"]["command_unit"] = lg.command_unit
    return LinearAxisPlant.from_dict(doc, origin=f"base plant of {log_name}"), []


def _merge_base(base, plant_path: str, vals: dict, srcs: dict):
    """The base plant file with what the logs say: every base value, description and
    ``[uncertainty]`` entry is kept; a log value that disagrees with the base (relative tolerance
    1e-6) is refused for :data:`LOG_FACTS` and kept from the base, with a warning, for
    :data:`BASE_KEPT`. Returns ``(plant, warnings)``."""
    notes = []
    for k, v in vals.items():
        b = base.values.get(k)
        if b is None or math.isclose(b, v, rel_tol=1e-6):
            continue
        unit = _UNITS[k]
        if k in LOG_FACTS:
            raise ValueError(f"--plant {plant_path}: {k} = {b:.6g} {unit} disagrees with {v:.6g} {unit} from the log "
                             f"({srcs[k]}); expected the same value (correct the base or the log description)")
        notes.append(f"{k}: kept {b:.6g} {unit} of --plant {plant_path}, not {v:.6g} {unit} from the log ({srcs[k]}): "
                     "the base states the axis (the fit and the replays clip the drive force at it; the replayed "
                     "controller still clips its output at its own saturation)")
    return base, notes


def calibrate_described(paths: Sequence[str | Path], log_format: str | Path, base: str | None = None, *, name: str,
                        labels: Sequence[str] | None = None,
                        check_interrupt: Callable[[], None] | None = None, fidelity: str = "auto"):
    """Fit a plant to described logs (CSV or ``.mat``) and compose its outputs.

    A description in load coordinates (``axis = "linear"``, the default) fits a ``linear-axis``
    plant as ``prsa-fit LOG... --log-format FORMAT.toml --out NAME.toml`` does: the base built
    from the logs (:func:`axis_base_plant`; ``base`` is not read: a screw-driven base would convert
    the log with its lead instead, which a linear axis has not), the fit, each log replayed
    closed loop from its reference where the description gives the controller. A description in
    motor coordinates (``axis = "rotary"``) fits the screw-driven ``base`` as ``prsa-fit LOG...
    --log-format FORMAT.toml --plant BASE`` does
    (:func:`prsa_ctrl.identification.calibrate.calibrate_logs`).

    Parameters
    ----------
    paths : sequence of path-like
        The logs.
    log_format : path-like
        The log description (TOML).
    base : str, optional
        Motor coordinates: the base plant (built-in name or file; default the default plant).
    name : str
        The fitted plant's name.
    labels : sequence of str, optional
        How the results name each log (default: the path as given).
    check_interrupt : callable, optional
        Motor coordinates: called at the fit's iterations (the caller's cancellation).
    fidelity : str
        Load coordinates: ``"rigid"`` (``prsa-fit``'s default), ``"compliant"`` (``--fidelity
        compliant``: the two-mass axis) or ``"auto"`` (the app's: the data choose,
        :func:`choose_structure`).

    Returns
    -------
    Calibrated
        Load coordinates: ``result`` the :class:`~prsa_ctrl.identification.axis.AxisFit`,
        ``report`` ``prsa-fit --json``'s (with ``mechanism`` ``"linear-axis"`` and, per log,
        ``fit_percent`` the replay's velocity fit %), ``lines`` its text lines; ``failure``
        prsa-fit's exit-3 line and ``plant_text`` None when the validation says the plant does not
        explain the logs (:mod:`prsa_ctrl.identification.axisvalidation`).

    Raises
    ------
    LogFormatError, DataError, PlantFileError, ValueError
        Bad input (``prsa-fit``'s exit 2).
    AxisFitError, FitError
        The fit did not converge (``prsa-fit``'s exit 3).
    """
    from .calibrate import Calibrated, calibrate_logs
    from .logformat import load_axis_log, load_log_format

    paths = [str(p) for p in paths]
    labels = list(paths) if labels is None else [str(x) for x in labels]
    if len(labels) != len(paths) or not paths:
        raise ValueError(f"labels: {len(labels)} for {len(paths)} logs; expected one per log, at least one")
    fmt = load_log_format(log_format)
    if fmt.doc.get("axis", "linear") == "rotary":
        return calibrate_logs(paths, base, name=name, labels=labels, check_interrupt=check_interrupt,
                              log_format=str(log_format))
    from dataclasses import replace

    from .axis import axis_plant_toml

    logs = []
    for path, label in zip(paths, labels):
        lg = load_axis_log(path, fmt)
        logs.append(replace(lg, name=label))
    from .axisvalidation import refusal_line

    if fidelity not in ("rigid", "compliant", "auto"):
        raise ValueError(f"fidelity = {fidelity!r}; expected 'rigid', 'compliant' or 'auto'")
    base_plant, notes = axis_base_plant(logs, str(log_format))
    result, choice = choose_structure(logs, base_plant, name, fidelity)
    report, lines = axis_outputs(result, logs, notes)
    if choice is not None:
        report["structure_choice"] = choice
        lines = [choice, *lines]
    failure = refusal_line(result)  # prsa-fit's exit 3: no plant file
    return Calibrated(result, None if failure else axis_plant_toml(result.plant), report, tuple(lines),
                      None if failure is None else f"{failure} (no plant file written; --force writes it)", tuple(logs))


#: The diagnoses of a rigid fit whose residual is a response the rigid model lacks (a mode):
#: :func:`choose_structure` then fits the two-mass axis.
_MASS_MISSING = ("second mass", "unmodelled dynamics")


def choose_structure(logs: Sequence, base, name: str, fidelity: str = "auto"):
    """The linear-axis fit the data choose: ``(fit, line)``.

    ``"rigid"``: :func:`prsa_ctrl.identification.axis.fit_linear_axis`; ``"compliant"``:
    :func:`prsa_ctrl.identification.axiscompliant.fit_two_mass_axis` (``prsa-fit --fidelity
    compliant``); ``"auto"``: the rigid fit, and when its validation refuses it naming a response
    the rigid model lacks (a second mass: the residual the excitation predicts,
    :mod:`prsa_ctrl.identification.axisvalidation`), the two-mass fit too, taken when it explains the
    logs. ``line`` says what was chosen and why (None when the rigid fit was not refused, or a
    fidelity was asked for). Errors as the fits'.
    """
    from ..errors import AxisFitError
    from .axis import fit_linear_axis
    from .axiscompliant import fit_two_mass_axis

    if fidelity == "compliant":
        return fit_two_mass_axis(logs, base, name=name), None
    rigid = fit_linear_axis(logs, base, name=name)
    diag = rigid.validation.get("diagnosis") or ""
    if fidelity == "rigid" or rigid.passes or not diag.startswith(_MASS_MISSING):
        return rigid, None
    said = f"structure: the rigid fit does not explain the logs ({diag.split(':')[0]})"
    try:
        two = fit_two_mass_axis(logs, base, name=name)
    except (AxisFitError, ValueError) as exc:
        return rigid, f"{said}; the two-mass fit (prsa-fit --fidelity compliant) failed: {exc}"
    if not two.passes:
        return rigid, (f"{said}; the two-mass fit (prsa-fit --fidelity compliant) does not explain them either "
                       f"({two.validation.get('diagnosis')}): the rigid fit's verdict stands")
    mode = two.equivalent["mode_hz"]
    return two, (f"{said}; the two-mass fit (prsa-fit --fidelity compliant) does: chosen, its axial mode "
                 f"{mode['value']:.4g} Hz (95 % CI {mode['ci95'][0]:.4g}..{mode['ci95'][1]:.4g})")


def axis_outputs(result, logs: Sequence, notes: Sequence[str] = (), held: Sequence = (),
                 holdout: float | None = None) -> tuple[dict, list[str]]:
    """``prsa-fit --log-format``'s JSON report and text lines of a linear-axis fit: the fit's
    report (:meth:`~prsa_ctrl.identification.axis.AxisFit.as_dict`) with the base's ``notes``
    first among the warnings, each log's friction map (a report: the replay model stays Coulomb +
    viscous), the held-out parts' replays (``held``, the last ``holdout`` of each log), and per log
    ``fit_percent`` the replay's velocity fit % (the app's table; ``prsa-fit``'s JSON leaves it out).
    The lines: the equivalent values with 95 % intervals, each replay, the friction maps, the
    warnings and the coordinates, each made printable."""
    from ..reporttext import axis_fit_lines, axis_verdict_lines
    from ..textsafe import printable
    from .axis import replay_axis
    from .friction_map import axis_friction_map

    from .axis import DELAY_MARGIN
    from .delay import axis_delay_record

    report = result.as_dict()
    report["warnings"] = [*notes, *report["warnings"]]
    report["command_delay"] = axis_delay_record(
        logs, (report.get("delay_check") or {}).get("cost_by_command_delay_samples"), DELAY_MARGIN)
    axis_plant = result.plant.to_plant()
    report["friction_map"] = {Path(lg.name).name: axis_friction_map(lg.name, lg.time_s, lg.position_m,
                                                                    lg.gain_n_per_unit * lg.command, axis_plant)
                              for lg in logs}
    report["warnings"] += [w for fmap in report["friction_map"].values() for w in fmap.get("warnings", [])]
    if held:
        report["holdout"] = {"fraction": holdout, "note": "fitted on the first part of each log, replayed on the "
                             "rest (closed loop from the reference, starting from the logged position at rest)",
                             "replay": [replay_axis(result.plant, h).as_dict() for h in held]}
    lines = [printable(x) for x in axis_fit_lines(report)]  # before fit_percent: the JSON's report leaves it out
    if report.get("validation"):  # the verdict (identification.axisvalidation)
        lines += [printable(x) for x in axis_verdict_lines(report["validation"])]
    report["fit_percent"] = {r["log"]: r["fit_percent"]["velocity"] for r in report["replay"]}
    return report, lines
