"""The app's model: one plant and scene, the tuner, the designs the page shows, no GUI code.

Everything the browser page displays is computed here, with the toolkit's public functions
(:class:`prsa_ctrl.tuning.tuner.Tuner`, :func:`prsa_ctrl.studies.autotune.actuator_loops`,
:func:`prsa_ctrl.studies.autotune.baseline_designs`, :func:`prsa_ctrl.studies.autotune.verify`,
:func:`prsa_ctrl.io.export.export_controller`), so the numbers on the page are the toolkit's. The
session keeps one :class:`~prsa_ctrl.tuning.tuner.Tuner` per loop set (objective, controller, load
levels): a change of a bound (Ms, Mt, noise gain) re-solves on it without rebuilding the NLP.

Units are SI: gains ``kp`` N m s/rad, ``ki`` N m/rad, ``kd`` N m s^2/rad; speeds rad/s; loads N.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import math
import os
import shlex
import sys
import tempfile
import threading
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from ..studies.autotune import Design, actuator_loops, baseline_designs, checked, predict, verify
from ..studies.scenefile import parse_load_step
from ..drive.pid import PID
from ..errors import GeometryWarning, PlantFileError, SceneError
from ..options import FIDELITIES as _FIDELITIES, MS_MAX_DEFAULT, OBJECTIVES, PEAK_BOUND_RANGE, RAD_S_PER_RPM
from ..plant.plantfile import Plant, builtin_plants, load_plant
from ..results import check_status
from ..studies.scene import Scene, builtin_scenes, check_against_plant, load_scene
from ..studies.scenekinds import problem
from ..tuning.tuner import Tuner

__all__ = ["AppInputError", "Settings", "View", "AppSession", "Calibration", "FIDELITIES", "LANDSCAPE_POINTS",
           "upload_name", "TRACE_KEYS"]

#: Verification fidelities offered (``Scene.fidelity``).
FIDELITIES = ("auto", *_FIDELITIES)
#: Grid points per axis of the Kp-Ki landscape.
LANDSCAPE_POINTS = 41
#: Tuners kept per session (one per objective, controller and load levels), oldest dropped.
_MAX_TUNERS = 8


class AppInputError(ValueError):
    """Bad input from the page or the command line; ``str(exc)`` is the one line to show."""


def typed(value, limit: int = 200) -> str:
    """``repr(value)`` as a message quotes a value as typed, cut to ``limit`` characters (a
    client can send megabytes)."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def one_line(exc: BaseException) -> str:
    """The exception's message on one line (as the CLI prints it)."""
    return " ".join(str(exc).split())


@dataclass(frozen=True)
class Settings:
    """What the page's controls set.

    Attributes
    ----------
    objective : {"ie", "iae", "itae", "ise"}
    controller : {"pi", "pid"}
    ms_max : float
        Bound on the true peak sensitivity, in (1, 10).
    mt_max : float or None
        Bound on the true peak complementary sensitivity, in (1, 10), or none.
    max_noise_gain : float or None, N m s/rad
        Bound on the controller's high-frequency gain ``kp + kd/tf``, or none.
    mks_max : float or None, N m s/rad
        Bound on the true peak noise sensitivity ``max |C F S|`` (measured speed to torque
        command, every filter on the path), or none.
    load_step : str
        ``INITIAL:FINAL[,FINAL...]`` in N, as typed (the ``prsa-tune --load-step`` syntax).
    fidelity : str
        Verification fidelity (:data:`FIDELITIES`).
    """

    objective: str = "iae"
    controller: str = "pi"
    ms_max: float = MS_MAX_DEFAULT
    mt_max: float | None = None
    max_noise_gain: float | None = None
    load_step: str = "500:1500"
    fidelity: str = "auto"
    mks_max: float | None = None


#: Statuses of the views that are not the tuner's (:data:`prsa_ctrl.results.STATUSES`): a design
#: set by hand, a baseline rule's design (neither tuned nor yet simulated), and any design whose
#: linear loop is unstable on some load level (never simulated).
MANUAL_STATUS = "unverified: gains set by hand (not tuned)"
BASELINE_STATUS = "unverified: a baseline rule's gains (not tuned)"
UNSTABLE_STATUS = "flagged: the loop is unstable (linear model, some load level)"


@dataclass
class View:
    """One design as the page shows it.

    Attributes
    ----------
    design : Design
        Gains, true margins of the first load level's loop and the linear prediction.
    omega : array, rad/s
        Dense frequency grid of the loop (the one its true peaks were located on).
    loop : array of complex
        Loop transfer ``L(j omega)`` (first load level).
    t : list of arrays, s
        Time of the predicted response per load level.
    speed : list of arrays, rad/s
        Predicted nut speed per load level.
    status : str
        In the package's vocabulary (:data:`prsa_ctrl.results.STATUSES`): the tuner's status for
        the optimum, :data:`MANUAL_STATUS` for a design set by hand, :data:`BASELINE_STATUS` for
        a baseline, :data:`UNSTABLE_STATUS` for any of them whose loop is unstable.
    noise_gain : float, N m s/rad
        The controller's high-frequency gain ``kp + kd/tf``.
    mks : float or None, N m s/rad
        The true peak noise sensitivity ``max |C F S|`` of the first load level's loop.
    """

    design: Design
    omega: np.ndarray
    loop: np.ndarray
    t: list
    speed: list
    status: str
    noise_gain: float
    mks: float | None = None

    def __post_init__(self) -> None:
        check_status(self.status)

    @property
    def pid(self) -> PID:
        return self.design.pid

    def drive_terms(self, ts: float) -> dict[str, float | None]:
        """The gains as a drive takes them: SI gains, ``Ti = kp/ki`` (s), gains per rpm."""
        p = self.pid
        return {"kp_n_m_s_per_rad": p.kp, "ki_n_m_per_rad": p.ki, "kd_n_m_s2_per_rad": p.kd,
                "ti_s": p.kp / p.ki if p.ki > 0 else None, "kp_n_m_per_rpm": p.kp * RAD_S_PER_RPM,
                "ki_n_m_per_rev": p.ki * 2.0 * math.pi, "sample_time_s": ts}


class AppSession:
    """Plant, scene, tuners and designs of one app page (thread-safe through one lock).

    Parameters
    ----------
    plant : str or Path, optional
        Built-in plant name or path to a plant ``.toml`` file (default ``paper-iprsm``).
    scene : str or Path, optional
        Built-in scene name or path to a load-step scene ``.toml`` file (default
        ``paper-load-step``).

    Raises
    ------
    AppInputError
        One line naming the file or value and what was expected (the CLI's message).
    """

    def __init__(self, plant: str | Path | None = None, scene: str | Path | None = None) -> None:
        self._lock = threading.RLock()
        self._tmp: tempfile.TemporaryDirectory | None = None
        self.notes: list[str] = []
        self.plant, self.plant_label, notes_p = _load_plant(plant)
        self.plant_source = None if plant is None else str(plant)  # as prsa-fit --plant takes it
        self.base_scene, self.scene_label, notes_s = _load_scene(scene)
        self.notes = notes_p + notes_s
        _check_scene_plant(self.base_scene, self.plant)
        self._tuners: dict = {}
        self._loops: dict = {}
        self._baselines: dict = {}
        self._landscapes: dict = {}

    # ---- inputs -------------------------------------------------------------------------

    def default_settings(self) -> Settings:
        """Settings from the scene file (its objective, controller, bounds and load step)."""
        sc = self.base_scene
        return Settings(objective=sc.objective, controller=sc.controller, ms_max=sc.ms_max, mt_max=sc.mt_max,
                        load_step=f"{sc.initial_load:g}:" + ",".join(f"{f:g}" for f in sc.final_loads),
                        fidelity=sc.fidelity)

    def set_plant(self, name_or_path: str | Path, label: str | None = None) -> list[str]:
        """Switch to another plant (checked against the scene first); returns its notes.

        ``name_or_path`` is a built-in plant name or a file in the session's own private folder
        (an upload, a calibration's fitted plant): any other path is refused before the disk is
        touched (the page's select sends client text here; see :meth:`_own`).
        """
        self._own("plant", name_or_path, builtin_names()[0])
        plant, plabel, notes = _load_plant(name_or_path, label)
        _check_scene_plant(self.base_scene, plant)
        with self._lock:
            self.plant, self.plant_label = plant, plabel
            self.plant_source = str(name_or_path)
            self._clear()
        return notes

    def set_scene(self, name_or_path: str | Path, label: str | None = None) -> list[str]:
        """Switch to another load-step scene (checked against the plant first); returns its notes.

        ``name_or_path`` is a built-in load-step scene name or a file in the session's own
        private folder (an upload, read without its CSV traces: :meth:`upload`); any other path
        is refused before the disk is touched.
        """
        own = self._own("scene", name_or_path, builtin_names()[1])
        scene, slabel, notes = _load_uploaded_scene(name_or_path, label) if own else _load_scene(name_or_path, label)
        _check_scene_plant(scene, self.plant)
        with self._lock:
            self.base_scene, self.scene_label = scene, slabel
            self._clear()
        return notes

    def upload(self, kind: str, filename: str, content: bytes) -> list[str]:
        """Load an uploaded plant or scene file (``kind`` ``"plant"`` or ``"scene"``).

        The file is stored under its own name (:func:`upload_name`: the last part of
        ``filename``, or ``uploaded-KIND.toml``) in a private temporary folder, and every message
        names it as uploaded, exactly as the CLI names a file given as ``--plant FILENAME`` in
        its folder. An uploaded scene never reads another file: one naming a CSV trace
        (``operating.load_trace_csv``, ``operating.setpoint_trace_csv``) is refused before any
        read (the app tunes load-step scenes, which have no trace).
        """
        if kind not in ("plant", "scene"):
            raise ValueError(f"kind = {kind!r}; expected 'plant' or 'scene'")
        name = upload_name(filename, f"uploaded-{kind}.toml")
        path = self._folder(kind) / name
        path.write_bytes(content)
        try:
            if kind == "plant":
                return self.set_plant(str(path), label=name)
            return self.set_scene(str(path), label=name)
        except AppInputError as exc:
            raise AppInputError(str(exc).replace(str(path), name)) from None

    def _own(self, kind: str, name_or_path, builtins) -> bool:
        """Whether ``name_or_path`` is a file in the session's private folder (True) or one of
        ``builtins`` (False); anything else raises :class:`AppInputError` without touching the
        disk (the same line whether or not such a file exists)."""
        text = str(name_or_path)
        if not isinstance(name_or_path, Path) and text in builtins:
            return False
        with self._lock:
            root = None if self._tmp is None else Path(self._tmp.name)
        if root is not None and isinstance(name_or_path, (str, Path)) and Path(text).is_absolute():
            p = Path(os.path.normpath(text))
            if p.parent.parent == root:  # ROOT/<kind>-<n>/<name>: written by upload() or calibrate()
                return True
        raise AppInputError(f"{kind} {typed(text)}: expected a built-in {kind} ({', '.join(builtins)}) "
                            f"or an uploaded {kind} file")

    def _folder(self, kind: str) -> Path:
        """A new folder in the session's private temporary folder."""
        with self._lock:
            if self._tmp is None:
                self._tmp = tempfile.TemporaryDirectory(prefix="prsa-app-")
            folder = Path(self._tmp.name) / f"{kind}-{len(list(Path(self._tmp.name).iterdir()))}"
            folder.mkdir()
            return folder

    # ---- calibration from a drive log ---------------------------------------------------

    def calibrate(self, filename: str, content: bytes, cancelled: Callable[[], bool] | None = None,
                  poll_s: float = 0.1, kind: str = "log", log_format: tuple[str, bytes] | None = None) -> "Calibration":
        """Fit the session's plant to an uploaded drive log: what ``prsa-fit LOG --plant BASE --out
        LOG-fitted.toml --json LOG-fit.json`` does, as a library call in this thread
        (:func:`prsa_ctrl.identification.calibrate.calibrate_logs`: the same checks, fit, warnings,
        messages and plant file), the log kept under its uploaded name in a private folder, BASE
        being the session's plant (built-in name or file). The fitted plant file is written there
        (atomically, :func:`prsa_ctrl.io.output.write_text`). The session's plant is not changed
        (:meth:`use_calibration` does that).

        Slow (a Gauss-Newton fit, seconds): call it off the page's event loop.
        ``cancelled()`` is polled at the fit's iterations and simulations, at most every ``poll_s``
        s; when it turns true the fit stops there (:class:`Cancelled`).

        A fit whose plant does not explain the log (prsa-fit's exit 3 with its report) returns
        a :class:`Calibration` with ``refused`` set (the diagnosis) and no plant file.

        ``kind="frf"``: the upload is a measured frequency response, fitted as ``prsa-fit --frf
        FRF.csv --plant BASE`` does (:func:`prsa_ctrl.identification.calibrate.calibrate_frf`: the
        rigid and the two-mass model, the structure the data choose, the report's
        ``frf_structure``); a refused fit (prsa-fit's exit 3: the rigid model refused, no model
        explains the response, an implausible inertia or delay) returns a :class:`Calibration`
        with ``refused`` set, an empty ``report`` and no plant file.

        ``log_format=(file name, bytes)``: a log description (``prsa-fit --log-format``) the log (CSV
        or MATLAB ``.mat``) is read through
        (:func:`prsa_ctrl.identification.calibrate_axis.calibrate_described`): in load coordinates
        a ``linear-axis`` plant fitted from the log alone, to download (``usable`` False: the app
        tunes screw-driven actuators), in motor coordinates the session's plant.

        Raises
        ------
        AppInputError
            prsa-fit's one-line error (bad log, bad base plant; the fit did not converge; the
            fitted plant does not explain the data), files named as uploaded.
        Cancelled
            ``cancelled()`` turned true.
        """
        import time

        from ..errors import AxisFitError, DataError, FitError
        from ..identification.calibrate import calibrate_frf, calibrate_logs
        from ..identification.calibrate_axis import calibrate_described
        from ..io.output import json_safe, write_text
        from ..textsafe import MESSAGE_CHARS_MAX, printable

        if kind not in ("log", "frf"):
            raise ValueError(f"kind = {kind!r}; expected 'log' or 'frf'")
        name = upload_name(filename, f"uploaded-{kind}.csv")
        folder = self._folder("log")
        path = folder / name
        path.write_bytes(content)
        fmt_path = None
        if log_format is not None:  # beside the log, under its uploaded name
            if kind != "log" or upload_name(log_format[0], "log-format.toml") == name:
                raise AppInputError(f"{name}: a log description with a {kind} named like it; expected a drive log "
                                    "and its description under another name")
            fmt_path = folder / upload_name(log_format[0], "log-format.toml")
            fmt_path.write_bytes(log_format[1])
        stem = Path(name).stem or "log"
        out = f"{stem}-fitted.toml"
        base, base_label = self.plant_source, self.plant_label
        state = {"cancelled": False, "last": -math.inf}

        def check() -> None:
            if cancelled is None:
                return
            now = time.monotonic()
            if now - state["last"] < poll_s:
                return
            state["last"] = now
            if cancelled():
                state["cancelled"] = True
                raise Cancelled("calibration cancelled")

        def named(text: str, one_line: bool = True) -> str:
            """A line as prsa-fit prints it (user text escaped, :func:`prsa_ctrl.textsafe.printable`),
            the files named as uploaded."""
            text = printable(text, limit=MESSAGE_CHARS_MAX) if one_line else text
            for p, shown in ((str(path), name), (str(folder / out), out),
                             *([(str(fmt_path), fmt_path.name)] if fmt_path is not None else []),
                             *([(base, base_label)] if base is not None else [])):
                text = text.replace(p, shown)
            return " ".join(text.split())

        with thread_warnings() as caught:  # this call's warnings only (another session may be calibrating)
            try:
                check()
                if kind == "frf":  # prsa-fit --frf (no iteration hook: a cancel discards the result)
                    got = calibrate_frf([str(path)], base, name=Path(out).stem, labels=[name])
                    state["last"] = -math.inf  # the cancel pressed meanwhile is seen now
                    check()
                elif fmt_path is not None:
                    got = calibrate_described([str(path)], str(fmt_path), base, name=Path(out).stem, labels=[name],
                                              check_interrupt=check)
                else:
                    got = calibrate_logs([str(path)], base, name=Path(out).stem, labels=[name], check_interrupt=check)
            except Cancelled:
                raise
            except (FitError, AxisFitError) as exc:
                if state["cancelled"]:
                    raise Cancelled("calibration cancelled") from None
                if kind != "frf":
                    raise AppInputError(named(str(exc))) from None
                return Calibration(log_name=name, base_label=base_label, plant_path="", file_name="", report={},
                                   lines=(named(str(exc)),), refused=named(str(exc)))
            except (DataError, PlantFileError, FitError, ValueError) as exc:
                if state["cancelled"]:  # a fit that failed because it was stopped
                    raise Cancelled("calibration cancelled") from None
                raise AppInputError(named(str(exc))) from None
            except OSError as exc:
                raise AppInputError(named(f"{getattr(exc, 'filename', None) or ''}: cannot be read "
                                          f"({exc.strerror or exc}); expected readable files")) from None
            except Exception:
                if state["cancelled"]:
                    raise Cancelled("calibration cancelled") from None
                raise
        notes, seen = [], set()
        for w in caught:  # prsa-fit's note lines (a built-in plant's geometry note only with --verbose)
            text = named(str(w.message))
            if text in seen or (issubclass(w.category, GeometryWarning) and "(built-in)" in text):
                continue
            seen.add(text)
            notes.append(text)
        from ..plots.fit import axis_views, fit_views

        # as prsa-fit --json writes it, with the fit's three views (replay, FRF in Hz, residuals)
        linear = got.report.get("mechanism") == "linear-axis"  # (its views: prsa-fit --plots's, as data)
        report = json.loads(json.dumps(json_safe({**got.report, "views": axis_views(got.result) if linear else
                                                  fit_views(got.result, got.records)})))
        lines = tuple(named(x, False) for line in got.lines
                      for x in printable(line, multiline=True).splitlines() if x.strip())
        if got.failure is not None:  # the fit ran and its plant does not explain the log: a verdict, no plant file
            refused = named(got.failure).removesuffix(" (no plant file written; --force writes it)")
            return Calibration(log_name=name, base_label=base_label, plant_path="", file_name="", report=report,
                               lines=lines, notes=tuple(notes), refused=refused)
        write_text(folder / out, got.plant_text, inputs=[path], flag="--out")
        return Calibration(log_name=name, base_label="a linear axis built from the log" if linear else base_label,
                           plant_path=str(folder / out), file_name=out, report=report, notes=tuple(notes), lines=lines,
                           usable=not linear)

    def use_calibration(self, cal: "Calibration") -> list[str]:
        """Make the fitted plant the session's plant (checked against the scene; its file name
        is the plant's label from now on); returns its notes. A refused calibration has no
        plant: AppInputError with its line."""
        if cal.refused is not None:
            raise AppInputError(f"{cal.log_name}: the fit is refused, no plant to use ({cal.refused})")
        if not cal.usable:
            raise AppInputError(f"{cal.file_name}: a linear-axis plant; expected a screw-driven plant to tune here "
                                "(download it: prsa-axis tunes a linear axis)")
        return self.set_plant(cal.plant_path, label=cal.file_name)

    def scene_for(self, s: Settings) -> Scene:
        """The scene with the page's settings, checked against the plant (one-line errors)."""
        if s.objective not in OBJECTIVES:
            raise AppInputError(f"objective {s.objective!r}: expected one of {', '.join(OBJECTIVES)}")
        if s.controller not in ("pi", "pid"):
            raise AppInputError(f"controller {s.controller!r}: expected pi or pid")
        if s.fidelity not in FIDELITIES:
            raise AppInputError(f"fidelity {s.fidelity!r}: expected one of {', '.join(FIDELITIES)}")
        for what, v in (("Ms bound", s.ms_max), ("Mt bound", s.mt_max)):
            if v is not None and not (isinstance(v, (int, float)) and PEAK_BOUND_RANGE[0] < v < PEAK_BOUND_RANGE[1]):
                raise AppInputError(f"{what} {v!r}: expected a number in ({PEAK_BOUND_RANGE[0]:g}, {PEAK_BOUND_RANGE[1]:g})")
        if s.max_noise_gain is not None and not (math.isfinite(s.max_noise_gain) and s.max_noise_gain > 0):
            raise AppInputError(f"noise-gain bound {s.max_noise_gain!r}: expected a positive number in N m s/rad")
        if s.mks_max is not None and not (isinstance(s.mks_max, (int, float)) and math.isfinite(s.mks_max)
                                          and s.mks_max > 0):
            raise AppInputError(f"Mks bound {s.mks_max!r}: expected a positive number in N m s/rad")
        try:
            initial, finals = parse_load_step(s.load_step.strip())
        except argparse.ArgumentTypeError as exc:
            raise AppInputError(f"load step {one_line(exc)}") from None
        typed = {"initial_load": f"load step {s.load_step!r}", "final_loads": f"load step {s.load_step!r}"}
        try:
            scene = self.base_scene.replace(origin="app", objective=s.objective, controller=s.controller,
                                            ms_max=s.ms_max, mt_max=s.mt_max, initial_load=initial,
                                            final_loads=finals, fidelity=s.fidelity)
            check_against_plant(scene, self.plant, typed)
        except SceneError as exc:
            raise AppInputError(one_line(exc)) from None
        return scene

    # ---- tuning -------------------------------------------------------------------------

    def _key(self, scene: Scene) -> tuple:
        return (scene.objective, scene.controller, scene.initial_load, scene.final_loads)

    def loops(self, scene: Scene) -> list:
        """Loop models of the scene's load levels (cached per load levels)."""
        key = (scene.initial_load, scene.final_loads)
        with self._lock:
            if key not in self._loops:
                self._loops[key] = actuator_loops(self.plant, scene)
            return self._loops[key]

    def tuner(self, scene: Scene) -> Tuner:
        """The session's Tuner of the scene's loop set (built once, reused for every bound)."""
        key = self._key(scene)
        with self._lock:
            if key not in self._tuners:
                if len(self._tuners) >= _MAX_TUNERS:
                    self._tuners.pop(next(iter(self._tuners)))
                self._tuners[key] = Tuner(self.loops(scene), objective=scene.objective, controller=scene.controller,
                                          worst_case=scene.aggregate == "worst")
            return self._tuners[key]

    def tuned(self, s: Settings) -> View:
        """The optimal design under the settings' bounds (``Tuner.tune`` on the session's tuner)."""
        scene = self.scene_for(s)
        with self._lock:
            res = self.tuner(scene).tune(ms_max=s.ms_max, mt_max=s.mt_max, max_noise_gain=s.max_noise_gain,
                                         mks_max=s.mks_max)
            d = Design(f"optimum (Ms <= {s.ms_max:.3g})", res.pid, res.margins[0], tuner_status=res.status)
            return self._view(d, scene, res.status)

    def manual(self, s: Settings, kp: float, ki: float, kd: float = 0.0) -> View:
        """A design set by hand: its true margins and linear prediction on the same loops."""
        for name, v in (("kp", kp), ("ki", ki), ("kd", kd)):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise AppInputError(f"manual {name} {v!r}: expected a finite number >= 0")
        if kp <= 0:
            raise AppInputError(f"manual kp {kp!r}: expected a positive gain in N m s/rad")
        scene = self.scene_for(s)
        with self._lock:
            lp = self.loops(scene)[0]
            pid = PID(float(kp), float(ki), float(kd), tf=lp.tf)
            d = Design("manual", pid, lp.margins(pid.gains))  # not tuned: no tuner status to flag
            return self._view(d, scene, MANUAL_STATUS)

    def baselines(self, s: Settings) -> list[View]:
        """The report's baseline designs (paper Kp sweep, SIMC, PM 60 deg, rule of thumb)."""
        scene = self.scene_for(s)
        key = (self._key(scene))
        with self._lock:
            if key not in self._baselines:
                loops = self.loops(scene)
                self._baselines[key] = [self._view(d, scene, BASELINE_STATUS)
                                        for d in baseline_designs(self.plant, scene, loops)]
            return self._baselines[key]

    def stability(self, s: Settings, pid: PID) -> str:
        """``"stable"``, ``"marginal"`` or ``"unstable"`` on every load level's loop (worst)."""
        scene = self.scene_for(s)
        order = ("stable", "marginal", "unstable")
        return max((lp.stability(pid.gains) for lp in self.loops(scene)), key=order.index)

    def _view(self, d: Design, scene: Scene, status: str) -> View:
        loops = self.loops(scene)
        lp = loops[0]
        pk = lp.peaks(d.pid.gains)
        stable = all(l.is_stable(d.pid.gains) for l in loops)
        ts, speeds = [], []
        if stable:
            d = predict(d, loops, self.plant, scene)
            for err, l in zip(d.predicted_error, loops):
                ts.append(scene.step_time + l.h * np.arange(-1, l.n_steps))
                speeds.append(d.predicted_start_speed + np.concatenate([[0.0], -np.asarray(err)]))
        return View(design=d, omega=np.asarray(pk["omega"]), loop=np.asarray(pk["L"]), t=ts, speed=speeds,
                    status=status if stable else UNSTABLE_STATUS, noise_gain=d.pid.kp + d.pid.kd / d.pid.tf,
                    mks=lp.noise_peak(d.pid.gains)["mks"] if lp.noise is not None else None)

    # ---- landscape ----------------------------------------------------------------------

    def landscape(self, s: Settings, centre: list[PID], kd: float = 0.0) -> dict:
        """The Kp-Ki plane around ``centre`` designs: objective and grid Ms (first load level).

        Returns
        -------
        dict
            ``kp`` (N m s/rad), ``ki`` (N m/rad) axes; ``objective`` (the scene's objective
            summed/worst over the load levels as the tuner sees it, nan where unstable) and
            ``ms`` (max |S| on the loop's grid, inf where unstable), shape ``(n_ki, n_kp)``.
        """
        scene = self.scene_for(s)
        kp_hi = 1.6 * max(p.kp for p in centre)
        ki_hi = 1.6 * max(p.ki for p in centre)
        key = (self._key(scene), round(kp_hi, 12), round(ki_hi, 12), kd)
        with self._lock:
            if key in self._landscapes:
                return self._landscapes[key]
            loops = self.loops(scene)
            n = LANDSCAPE_POINTS
            kp = np.linspace(kp_hi / n, kp_hi, n)
            ki = np.linspace(0.0, ki_hi, n)
            kk, ii = np.meshgrid(kp, ki)
            ng = loops[0].n_gains
            g = np.zeros((kk.size, ng))
            g[:, 0], g[:, 1] = kk.ravel(), ii.ravel()
            if ng > 2:
                g[:, 2] = kd
            stable = np.array([all(lp.is_stable(x) for lp in loops) for x in g])
            obj = np.full(kk.size, np.nan)
            vals = [lp.objectives(g[stable], scene.objective) for lp in loops]
            obj[stable] = np.max(vals, axis=0) if scene.aggregate == "worst" else np.sum(vals, axis=0)
            L = g @ loops[0].L
            ms = np.max(1.0 / np.abs(1.0 + L), axis=1)
            ms[~stable] = np.inf
            out = {"kp": kp, "ki": ki, "objective": obj.reshape(kk.shape), "ms": ms.reshape(kk.shape), "kd": kd}
            if len(self._landscapes) > 8:
                self._landscapes.clear()
            self._landscapes[key] = out
            return out

    # ---- verification -------------------------------------------------------------------

    def verify(self, s: Settings, views: list[View], progress: Callable[[int, int, str], None] | None = None,
               cancelled: Callable[[], bool] | None = None) -> list[View]:
        """Run each design on the nonlinear simulator (``prsa_ctrl.studies.autotune.verify``) and check
        its health; ``progress(done, total, name)`` is called before and after each design.
        Returns the views whose designs now carry ``verified``/``verified_runs``/``flags``;
        stops early (returning those done) when ``cancelled()`` turns true."""
        scene = self.scene_for(s)
        done = []
        for i, v in enumerate(views):
            if cancelled is not None and cancelled():
                break
            if progress is not None:
                progress(i, len(views), v.design.name)
            d = replace(v.design, verified=(), verified_runs=(), flags=())
            if v.status == UNSTABLE_STATUS:
                d = replace(d, flags=("the loop is unstable: not simulated",))
            else:
                d = checked(verify(d, self.plant, scene), self.plant, scene)
            done.append(replace(v, design=d))
        if progress is not None:
            progress(len(done), len(views), "")
        return done

    # ---- export and code ----------------------------------------------------------------

    def export_files(self, s: Settings, view: View, extra: dict | None = None) -> dict[str, str]:
        """The drive file (TOML, :func:`prsa_ctrl.io.export.export_controller`) and the JSON report
        of a design: ``{file name: text}``."""
        from ..io.export import dumps, export_controller

        scene = self.scene_for(s)
        drive = dumps(export_controller(view.pid, self.plant, fmt="toml"), "toml")
        report = {
            "plant": self.plant.name, "plant_file": self.plant_label, "scene": scene.as_dict(),
            "bounds": {"ms_max": s.ms_max, "mt_max": s.mt_max, "max_noise_gain_n_m_s_per_rad": s.max_noise_gain,
                       "mks_max_n_m_s_per_rad": s.mks_max},
            "design": view.design.as_dict(), "tuner_status": view.status,
            "drive_terms": view.drive_terms(self.plant.sample_time_s),
            "units": {"kp": "N m s/rad", "ki": "N m/rad", "kd": "N m s^2/rad", "tf": "s"},
            **(extra or {}),
        }
        return {"speed-controller.toml": drive, "prsa-app-report.json": json.dumps(_finite(report), indent=2)}

    def code(self, s: Settings) -> tuple[str, str]:
        """The equivalent ``prsa-tune`` command line and Python call of the settings."""
        args = ["prsa-tune", "--plant", self.plant_label, "--scene", self.scene_label,
                "--load-step", s.load_step.replace(" ", ""), "--objective", s.objective,
                "--controller", s.controller, "--ms-max", f"{s.ms_max:g}"]
        if s.mt_max is not None:
            args += ["--mt-max", f"{s.mt_max:g}"]
        if s.mks_max is not None:
            args += ["--mks-max", f"{s.mks_max:g}"]
        cli = " ".join(shlex.quote(a) for a in args)
        if s.max_noise_gain is not None:
            cli += "  # prsa-tune has no noise-gain flag: the bound applies to the Python call only"
        scene_args = (f"objective={s.objective!r}, controller={s.controller!r}, ms_max={s.ms_max!r}, "
                      f"mt_max={s.mt_max!r}, initial_load={_initial(s)!r}, final_loads={_finals(s)!r}, "
                      f"fidelity={s.fidelity!r}")
        py = "\n".join([
            "from prsa_ctrl import Tuner, load_plant, load_scene",
            "from prsa_ctrl.studies.autotune import actuator_loops",
            "",
            f"plant = load_plant({self.plant_label!r})",
            f"scene = load_scene({self.scene_label!r}).replace({scene_args})",
            "tuner = Tuner(actuator_loops(plant, scene), objective=scene.objective, controller=scene.controller)",
            f"result = tuner.tune(ms_max={s.ms_max!r}, mt_max={s.mt_max!r}, max_noise_gain={s.max_noise_gain!r}"
            + (f", mks_max={s.mks_max!r})" if s.mks_max is not None else ")"),
            "print(result.status, result.pid, result.ms)",
        ])
        return cli, py

    # ---- housekeeping -------------------------------------------------------------------

    def _clear(self) -> None:
        self._tuners.clear()
        self._loops.clear()
        self._baselines.clear()
        self._landscapes.clear()

    def close(self) -> None:
        """Remove the uploaded files and drop the tuners, loop models and cached designs (the
        session's memory; it is rebuilt on the next use)."""
        with self._lock:
            self._clear()
            if self._tmp is not None:
                self._tmp.cleanup()
                self._tmp = None


def _initial(s: Settings) -> float:
    return parse_load_step(s.load_step.strip())[0]


def _finals(s: Settings) -> tuple[float, ...]:
    return parse_load_step(s.load_step.strip())[1]


def _finite(x):
    """JSON-safe copy: non-finite floats become None."""
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


_THREAD_WARNINGS = threading.local()
_THREAD_WARNINGS_LOCK = threading.Lock()


def _warn_routed(message, category=None, stacklevel=1, source=None, **kwargs):
    """:func:`warnings.warn` with a per-thread recorder: while this thread is inside
    :func:`thread_warnings`, the warning goes to its list (every one, as ``"always"`` would,
    but for the filters the code run since has added: ``ignore`` drops it, ``error`` raises it);
    otherwise to the warn it replaced."""
    caught = getattr(_THREAD_WARNINGS, "caught", None)
    if caught is None:
        if getattr(_THREAD_WARNINGS, "forwarding", False):  # a wrapper of ours that we wrapped: no loop
            import _warnings

            return _warnings.warn(message, category, stacklevel + 1, source, **kwargs)
        _THREAD_WARNINGS.forwarding = True
        try:
            return _warn_routed.previous(message, category, stacklevel + 1, source, **kwargs)
        finally:
            _THREAD_WARNINGS.forwarding = False
    if isinstance(message, Warning):
        category = message.__class__
    else:
        category = category or UserWarning
        message = category(message)
    try:
        module = sys._getframe(stacklevel).f_globals.get("__name__", "")
    except ValueError:
        module = ""
    action = _added_filter_action(message, category, module)
    if action == "ignore":
        return None
    if action == "error":
        raise message
    caught.append(warnings.WarningMessage(message, category, "", 0, source=source))


def _added_filter_action(message: Warning, category: type, module: str) -> str | None:
    """The action of the first filter added since this thread's recording began (the code it
    runs silencing a warning: ``catch_warnings(); simplefilter("ignore", ...)``) that matches,
    else None (recorded). ``simplefilter``/``filterwarnings`` put a filter first and drop an
    equal one further down, so the added filters are the front of the list before the part that
    is, in order, the filters at the start."""
    current, base = list(warnings.filters), _THREAD_WARNINGS.filters
    i, j = len(current) - 1, len(base) - 1
    while i >= 0 and j >= 0:
        if current[i] == base[j]:
            i -= 1
        j -= 1
    for action, msg, cat, mod, lineno in current[:i + 1]:
        if ((msg is None or msg.match(str(message))) and issubclass(category, cat)
                and (mod is None or mod.match(module)) and lineno == 0):
            return action
    return None


def _show_routed(message, category, filename, lineno, file=None, line=None):
    """:func:`warnings.showwarning` with the same per-thread recorder (warnings issued by C code,
    which do not go through :func:`warnings.warn`'s Python name, once the filters let them through)."""
    caught = getattr(_THREAD_WARNINGS, "caught", None)
    if caught is None:
        if getattr(_THREAD_WARNINGS, "showing", False):  # a wrapper of ours that we wrapped: no loop
            return warnings._showwarning_orig(message, category, filename, lineno, file, line)
        _THREAD_WARNINGS.showing = True
        try:
            return _show_routed.previous(message, category, filename, lineno, file, line)
        finally:
            _THREAD_WARNINGS.showing = False
    caught.append(warnings.WarningMessage(message, category, filename, lineno, file, line))


@contextlib.contextmanager
def thread_warnings():
    """Record the warnings this thread issues, and only those (a list of
    :class:`warnings.WarningMessage`), without the process-wide state of
    :func:`warnings.catch_warnings` (its filters and ``showwarning`` are the process's, so two
    sessions calibrating at once in two threads saw each other's warnings, and the one that
    finished first reset the other's recording). Other threads' warnings go where they went.
    Nests (the inner block gets its own list)."""
    with _THREAD_WARNINGS_LOCK:  # installed once; again when someone (a test harness) put theirs back
        if warnings.warn is not _warn_routed:
            _warn_routed.previous = warnings.warn
            warnings.warn = _warn_routed
        if warnings.showwarning is not _show_routed:
            _show_routed.previous = warnings.showwarning
            warnings.showwarning = _show_routed
    outer = getattr(_THREAD_WARNINGS, "caught", None), getattr(_THREAD_WARNINGS, "filters", None)
    caught = []
    _THREAD_WARNINGS.caught, _THREAD_WARNINGS.filters = caught, list(warnings.filters)
    try:
        yield caught
    finally:
        _THREAD_WARNINGS.caught, _THREAD_WARNINGS.filters = outer


def _notes(caught: list) -> list[str]:
    out = []
    for w in caught:
        line = " ".join(str(w.message).split())
        if line not in out:
            out.append(line)
    return out


def _load_plant(name_or_path, label: str | None = None) -> tuple[Plant, str, list[str]]:
    with thread_warnings() as caught:
        try:
            plant = load_plant(name_or_path)
        except PlantFileError as exc:
            raise AppInputError(one_line(exc)) from None
    text = str(name_or_path) if name_or_path is not None else plant.name
    notes = _notes(caught)
    if label:  # notes name the file as the user knows it
        notes = [n.replace(text, label) for n in notes]
    return plant, label or text, notes


def _load_scene(name_or_path, label: str | None = None) -> tuple[Scene, str, list[str]]:
    text = label or (str(name_or_path) if name_or_path is not None else "paper-load-step")
    with thread_warnings() as caught:
        try:
            scene = load_scene(name_or_path)
        except SceneError as exc:
            raise AppInputError(one_line(exc)) from None
    prob = problem(scene)
    if not prob.takes("app"):  # a duty cycle or a move: tuned by prsa-tune
        raise AppInputError(f"scene {text!r} is {prob.described}; expected a load-step scene "
                            f"(tune it with prsa-tune --scene {text})")
    return scene, text, _notes(caught)


#: Scene keys naming a file to read (a CSV trace); an uploaded scene may not hold them.
TRACE_KEYS = ("load_trace_csv", "setpoint_trace_csv")


def upload_name(filename, default: str) -> str:
    """The name an uploaded file is stored (and named in messages) under: the last part of the
    name the browser sent (``/`` and ``\\`` both separate parts), or ``default`` when that is
    empty, ``.``/``..``, starts with a dot, holds a control character or is longer than 200
    bytes. Never a path: the file is written into the session's private folder under it."""
    text = filename if isinstance(filename, str) else ""
    name = text.replace("\\", "/").rsplit("/", 1)[-1].strip()
    if (not name or name.startswith(".") or any(ord(c) < 32 or 0x7F <= ord(c) < 0xA0 for c in name)
            or len(name.encode("utf-8", "replace")) > 200):
        return default
    return name


def _load_uploaded_scene(path, label: str | None = None) -> tuple[Scene, str, list[str]]:
    """An uploaded scene file, read without touching any other file: a CSV trace key (the only
    keys of a scene that name a file) is refused before anything else is read, with one line
    naming the key and the value as typed."""
    from ..studies.scenefile import read_scene_doc

    text = label or Path(str(path)).name
    try:
        doc = read_scene_doc(Path(str(path)), text)
    except SceneError as exc:
        raise AppInputError(one_line(exc)) from None
    op = doc.get("operating")
    if isinstance(op, dict):
        for key in TRACE_KEYS:
            if key in op:
                raise AppInputError(f"{text}: operating.{key} = {typed(op[key])}: an uploaded scene cannot read files on "
                                    "the server; expected a load-step scene without a CSV trace")
    return _load_scene(path, label)


def _check_scene_plant(scene: Scene, plant: Plant) -> None:
    try:
        check_against_plant(scene, plant)
    except SceneError as exc:
        raise AppInputError(one_line(exc)) from None


def builtin_names() -> tuple[list[str], list[str]]:
    """Built-in plant names and load-step scene names (the choices of the page; the only names
    :meth:`AppSession.set_plant`/:meth:`AppSession.set_scene` take besides uploads)."""
    plants, scenes = _builtin_names()
    return list(plants), list(scenes)


@functools.lru_cache(maxsize=1)
def _builtin_names() -> tuple[tuple[str, ...], tuple[str, ...]]:
    scenes = []
    for name in builtin_scenes():
        try:
            _load_scene(name)
        except AppInputError:
            continue
        scenes.append(name)
    return tuple(builtin_plants()), tuple(scenes)


@dataclass(frozen=True)
class Calibration:
    """What ``prsa-fit`` made of an uploaded log (:meth:`AppSession.calibrate`).

    Attributes
    ----------
    log_name : str
        The log's file name as uploaded.
    base_label : str
        The base plant (the session's plant when the fit ran).
    plant_path : str
        The fitted plant file prsa-fit wrote (in the session's temporary folder).
    file_name : str
        Its name (``<log stem>-fitted.toml``).
    report : dict
        prsa-fit's JSON report: ``parameters`` (``value``, ``ci95``, ``unit``, ``kept_base``,
        ``written``), ``reflected_inertia_kg_m2``, ``fit_percent``, ``warnings``, ``solver``.
    lines : tuple of str
        prsa-fit's output lines (values with 95 % intervals, fit %, ``warning:`` lines).
    notes : tuple of str
        prsa-fit's ``note:`` lines.
    refused : str or None
        When prsa-fit refused the fitted plant (exit 3: it does not explain the log), its one
        line with the diagnosis; ``plant_path`` and ``file_name`` are then empty (no plant
        file is written) and ``report`` says why (``solver.validation``, ``views``).
    usable : bool
        Whether the app can tune the fitted plant (False for a linear axis: download only).
    """

    log_name: str
    base_label: str
    plant_path: str
    file_name: str
    report: dict
    lines: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()
    refused: str | None = None
    usable: bool = True

    @property
    def plant_text(self) -> str:
        """The fitted plant file's text (what ``prsa-fit --out`` writes); ValueError for a
        refused fit (none was written)."""
        if self.refused is not None:
            raise ValueError(f"{self.log_name}: no fitted plant file ({self.refused})")
        return Path(self.plant_path).read_text(encoding="utf-8")


class Cancelled(Exception):
    """Raised inside a long study when the page's cancel was pressed."""


def robust_study(session: AppSession, s: Settings, designs: dict, n: int,
                 progress: Callable[[str, int, int], None] | None = None,
                 cancelled: Callable[[], bool] | None = None, seed: int = 0) -> dict:
    """Robust tuning over the plant's documented uncertainty, then Monte-Carlo yield.

    Runs :func:`prsa_ctrl.studies.scenerobust.tune_robust_actuator` on the page's scene (its Ms/Mt bounds;
    the noise-gain bound is not part of the robust problem) and
    :func:`prsa_ctrl.studies.montecarlo.run_monte_carlo` (serial, seeded) of ``designs`` plus the
    robust design on ``n`` samples. ``progress(stage, done, total)`` reports; ``cancelled()``
    is polled between the stages and after every chunk of samples (the robust NLP itself is
    not interruptible).

    Returns
    -------
    dict
        ``robust`` (gains dict), ``comparison`` (per design: ``max_ms``, ``worst_objective``
        over the scenario models), ``monte_carlo`` (the report's ``as_dict()``: ``complete``
        false when cancelled, yields over the samples done).

    Raises
    ------
    Cancelled
        When cancelled before any sample finished.
    """
    from ..studies.montecarlo import MonteCarloInterrupted, run_monte_carlo
    from ..studies.scenerobust import tune_robust_actuator

    if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= 10_000:
        raise AppInputError(f"samples {n!r}: expected an integer in 1..10000")
    scene = session.scene_for(s)
    if progress is not None:
        progress("robust tuning", 0, n)
    rr = tune_robust_actuator(session.plant, scene)
    if cancelled is not None and cancelled():
        raise Cancelled("cancelled after the robust tuning")
    every = {**designs, "robust": rr.robust}
    comparison = {}
    if rr.loops:
        from ..tuning.robust import compare_designs

        comp = compare_designs(every, rr.loops, rr.scenarios, scene.objective, scene.ms_max)
        comparison = {k: {"max_ms": v["max_ms"], "worst_objective": v["worst_objective"]}
                      for k, v in comp["designs"].items()}

    def step(done: int, total: int) -> None:
        if progress is not None:
            progress("Monte Carlo", done, total)
        if cancelled is not None and cancelled():
            raise KeyboardInterrupt  # run_monte_carlo turns it into its partial report

    try:
        rep = run_monte_carlo(session.plant, scene, every, n=n, seed=seed, backend="serial", progress=step,
                              quiet=True)
    except MonteCarloInterrupted as exc:
        rep = exc.report
    return {"robust": rr.robust.as_dict(), "comparison": comparison, "monte_carlo": rep.as_dict()}
