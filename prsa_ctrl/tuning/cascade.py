"""The position loop over the speed loop: move scenes, metrics, cascade tuning and export.

A *move scene* (a ``tuning/*.toml`` file with a ``[move]`` section, e.g. ``paper-move``) says
which move the actuator makes (:mod:`prsa_ctrl.drive.motion`), which loads appear during it and
while holding, what the position loop measures, and the robustness bound of the tuning.

Simulation
    :func:`simulate_move` runs the move in the one sampled-loop simulator
    (:func:`prsa_ctrl.sim.simulate.run` with a :class:`~prsa_ctrl.drive.measurement.PositionLoop`),
    from rest, on the nonlinear model (Stribeck friction with Karnopp stiction, both
    directions; compliant threads). :func:`move_metrics` gives peak and RMS following error,
    settling time into the position window, overshoot, peak torque, the holding deviation
    after the load step while holding and the hunting check (:func:`hunting`).

Linear model of the sampled cascade (:class:`CascadeModel`)
    The plant linearised at the move's cruise speed and held load
    (:func:`prsa_ctrl.plant.linear.linear_core`), discretised with a zero-order hold, under exactly
    the per-sample law the simulator runs (encoder difference and speed filter, speed PI with
    Euler integral, one-sample computation delay; position P/PI with velocity and acceleration
    feed-forward, at the speed-loop rate). Its loop transfer functions at the four
    loop-breaking points, with ``G`` the torque-command-to-angle response (delay included),
    ``G_p`` the same to the measured position (rad), ``W`` the speed measurement,
    ``C_s = kp + ki Ts z^-1/(1 - z^-1)``, ``C_p = kv + kip Ts/(1 - z^-1)``::

        speed loop, position loop closed:  L_sc = W G C_s / (1 + G_p C_s C_p)
        speed loop, position loop opened:  L_so = W G C_s
        position loop, speed loop closed:  L_p  = G_p C_s C_p / (1 + W G C_s)
        torque command (both loops broken at the plant input):  L_t = G_p C_s C_p + W G C_s

    Ms = max |1/(1 + L)| at each (:data:`BREAKING_POINTS`). The linearisation ignores stiction (at rest the nut
    sticks, which the nonlinear verification includes).

Tuning (:func:`tune_cascade`)
    *joint*: speed PI, position gain (and integral), velocity and acceleration feed-forward in
    one CasADi/ipopt NLP, minimising ``w_f mean(e_move^2)/e_f0^2 + w_h mean(e_hold^2)/e_h0^2``
    (following error over the move with its load step, position deviation after the load
    step while holding; normalised by the baseline's values) subject to
    ``|S| <= Ms`` at all four points on a frequency grid, with an optional bandwidth ratio
    ``kp/J >= ratio kv``. The true Ms of the result is verified on a dense grid with local
    refinement; a violated bound adds its frequency and solves again.
    *sequential* (the baseline): the speed PI tuned alone by :func:`prsa_ctrl.tuning.tuner.tune_loops`
    (IAE of the load step) at the same Ms, then the position P gain at 1/5 .. 1/10 of the
    speed loop's crossover (the largest that keeps every Ms within the bound), full velocity
    and acceleration feed-forward (``kvff = kaff = 1``). Both are verified on the nonlinear
    compliant model.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

import numpy as np
from numpy.typing import NDArray

from ..errors import SceneError
from ..drive.motion import PROFILE_KINDS, MotionProfile, plan

if TYPE_CHECKING:  # CasADi, the controller and the loop blocks are imported where they are used,
    # so that prsa-tune can tell a move scene from a speed-loop scene without them.
    from ..drive.pid import PID
    from ..drive.measurement import PositionLoop
    from ..plant.plantfile import Plant
    from ..sim.simulate import SimRun

#: What the position loop may measure (:data:`prsa_ctrl.drive.measurement.POSITION_SENSORS`).
POSITION_SENSORS = ("nut_angle", "screw_position")

__all__ = ["MoveScene", "load_move_scene", "is_move_scene", "MoveMetrics", "move_metrics", "hunting",
           "simulate_move", "CascadeModel", "CascadeDesign", "tune_cascade", "sequential_design",
           "export_cascade", "main_move", "verify_design", "write_move_plots", "format_move_report",
           "check_move_against_plant", "MOVE_FLAGS", "CASCADE_GAINS", "MS_RTOL",
           "BREAKING_POINTS", "POSITION_LAW"]

#: The loop-breaking points whose Ms the tuning bounds (:meth:`CascadeModel.loops`): the speed
#: loop with the position loop closed and opened, the position loop, the torque command (both
#: loops broken at the plant input).
BREAKING_POINTS = ("speed_closed", "speed_open", "position", "torque")
#: Relative tolerance of the verified Ms against the bound (the reported Ms is the true one).
MS_RTOL = 1e-5
#: Gains of a cascade design, in this order: speed kp (N m s/rad), ki (N m/rad); position kv
#: (1/s), kip (1/s^2); velocity and acceleration feed-forward (dimensionless).
CASCADE_GAINS = ("kp", "ki", "kv", "kip", "kvff", "kaff")

_MOVE_KEYS: Mapping[str, tuple[type, str]] = {
    "profile": (str, "one of " + ", ".join(PROFILE_KINDS)),
    "distance_mm": (float, "a finite non-zero travel in mm"),
    "max_speed_mm_s": (float, "a speed > 0 in mm/s"),
    "acceleration_m_s2": (float, "an acceleration > 0 in m/s^2"),
    "jerk_m_s3": (float, "a jerk > 0 in m/s^3"),
    "start_s": (float, "a start time >= 0 s"),
    "measured": (str, "one of " + ", ".join(POSITION_SENSORS)),
    "position_rate": (int, "1 (the cascade tuner models the position loop at the speed-loop rate; "
                      "PositionLoop(rate=...) simulates slower rates)"),
    "initial_load_n": (float, "a finite load in N"),
    "load_n": (float, "a finite load in N (the load that appears during the move)"),
    "load_time_s": (float, "a time in s inside the move"),
    "hold_step_n": (float, "a finite non-zero load step in N"),
    "hold_delay_s": (float, "a delay > 0 s after the end of the move"),
    "hold_duration_s": (float, "a time > 0 s"),
    "window_um": (float, "a settling window > 0 in um"),
    "fidelity": (str, "'rigid' or 'compliant'"),
}
_CASCADE_KEYS: Mapping[str, tuple[type, str]] = {
    "ms_max": (float, "a peak-sensitivity bound in (1, 10)"),
    "position_controller": (str, "'p' or 'pi'"),
    "weight_following": (float, "a weight >= 0"),
    "weight_holding": (float, "a weight >= 0"),
    "bandwidth_ratio": (float, "a ratio >= 1 of speed-loop to position-loop bandwidth"),
}
_REQUIRED = ("profile", "distance_mm", "max_speed_mm_s", "acceleration_m_s2")


@dataclass(frozen=True)
class MoveScene:
    """A positioning scene (the ``[move]`` and ``[cascade]`` sections of a scene file).

    Attributes (SI)
    ---------------
    profile : {"trapezoidal", "s-curve"}
    distance_m, max_speed_m_s, acceleration_m_s2, jerk_m_s3 : float
        The move (jerk only for the S-curve).
    start_s : float, s
        When the move starts (the axis holds at rest before).
    measured : {"nut_angle", "screw_position"}
    position_rate : int
        Position-loop sample time in controller samples (a scene file accepts 1 only: the
        cascade tuner models the position loop at the speed-loop rate).
    initial_load_n, load_n : float, N
        Load at the start and the load that appears at ``load_time_s`` (default: the middle
        of the move), then held.
    hold_step_n : float, N
        Load step applied while holding, ``hold_delay_s`` after the end of the move; the run
        lasts ``hold_duration_s`` after it.
    window_m : float, m
        Settling window of the position.
    fidelity : {"rigid", "compliant"}
        Model of the verification runs.
    ms_max : float
        Bound on the peak sensitivity at every loop-breaking point.
    position_controller : {"p", "pi"}
    weight_following, weight_holding : float
        Weights of the two parts of the tuning objective.
    bandwidth_ratio : float or None
        Smallest ratio of the speed loop's to the position loop's bandwidth (``kp/J >= ratio kv``).
    typed : dict
        The ``[move]`` values as the file typed them (named in error messages).
    """

    name: str
    origin: str
    profile: str
    distance_m: float
    max_speed_m_s: float
    acceleration_m_s2: float
    jerk_m_s3: float | None = None
    start_s: float = 0.01
    measured: str = "nut_angle"
    position_rate: int = 1
    initial_load_n: float = 0.0
    load_n: float = 0.0
    load_time_s: float | None = None
    hold_step_n: float = 0.0
    hold_delay_s: float = 0.1
    hold_duration_s: float = 0.15
    window_m: float = 2e-6
    fidelity: str = "compliant"
    ms_max: float = 1.4
    position_controller: str = "p"
    weight_following: float = 1.0
    weight_holding: float = 1.0
    bandwidth_ratio: float | None = None
    description: str = ""
    #: The ``[move]`` values as the file typed them (for error messages).
    typed: Mapping[str, Any] = field(default_factory=dict, compare=False, repr=False)

    def motion(self) -> MotionProfile:
        """The move, m of screw travel (:mod:`prsa_ctrl.drive.motion`)."""
        return plan(self.profile, self.distance_m, self.max_speed_m_s, self.acceleration_m_s2,
                    self.jerk_m_s3).shifted(self.start_s)

    @property
    def move_end_s(self) -> float:
        return self.motion().end_time

    @property
    def load_at_s(self) -> float:
        """Time the move's load appears, s (the middle of the move by default)."""
        m = self.motion()
        return self.load_time_s if self.load_time_s is not None else 0.5 * (m.t0[0] + m.end_time)

    @property
    def hold_step_s(self) -> float:
        return self.move_end_s + self.hold_delay_s

    @property
    def duration_s(self) -> float:
        return self.hold_step_s + self.hold_duration_s if self.hold_step_n else self.move_end_s + self.hold_delay_s

    def loads(self) -> list[tuple[float, float]]:
        """Load steps ``(time s, N)`` of the run."""
        pts = [(0.0, self.initial_load_n)]
        if self.load_n != self.initial_load_n:
            pts.append((self.load_at_s, self.load_n))
        if self.hold_step_n:
            pts.append((self.hold_step_s, self.load_n + self.hold_step_n))
        return pts


def _check(origin: str, section: str, key: str, val: Any, spec: tuple[type, str]) -> Any:
    typ, expected = spec
    if typ is float and isinstance(val, int) and not isinstance(val, bool):
        val = float(val)
    if not isinstance(val, typ) or isinstance(val, bool):
        raise SceneError(f"{origin}: {section}.{key} = {val!r}; expected {expected}")
    if typ is float and not math.isfinite(val):
        raise SceneError(f"{origin}: {section}.{key} = {val!r}; expected {expected}")
    return val


def _parse_move(doc: Mapping[str, Any], origin: str) -> MoveScene:
    allowed = {"name", "description", "move", "cascade"}
    unknown = sorted(set(doc) - allowed)
    if unknown:
        raise SceneError(f"{origin}: unknown section {unknown[0]!r} in a move scene; expected move, cascade")
    kw: dict[str, Any] = {"origin": origin, "name": doc.get("name", Path(origin.split(" ")[0]).stem)}
    if not isinstance(kw["name"], str):
        raise SceneError(f"{origin}: name = {kw['name']!r}; expected a string")
    if "description" in doc:
        if not isinstance(doc["description"], str):
            raise SceneError(f"{origin}: description = {doc['description']!r}; expected a string")
        kw["description"] = doc["description"]
    for section, keys in (("move", _MOVE_KEYS), ("cascade", _CASCADE_KEYS)):
        table = doc.get(section, {})
        if not isinstance(table, Mapping):
            raise SceneError(f"{origin}: [{section}] must be a table")
        extra = sorted(set(table) - set(keys))
        if extra:
            raise SceneError(f"{origin}: unknown key {section}.{extra[0]}; expected one of "
                             + ", ".join(f"{section}.{k}" for k in keys))
        for key, val in table.items():
            kw[key] = _check(origin, section, key, val, keys[key])
    for key in _REQUIRED:
        if key not in kw:
            raise SceneError(f"{origin}: move.{key} missing; expected {_MOVE_KEYS[key][1]}")

    def bad(section: str, key: str) -> SceneError:
        spec = (_MOVE_KEYS if section == "move" else _CASCADE_KEYS)[key]
        return SceneError(f"{origin}: {section}.{key} = {kw[key]!r}; expected {spec[1]}")

    if kw["profile"] not in PROFILE_KINDS:
        raise bad("move", "profile")
    if kw["distance_mm"] == 0:
        raise bad("move", "distance_mm")
    for key in ("max_speed_mm_s", "acceleration_m_s2", "jerk_m_s3", "hold_delay_s", "hold_duration_s", "window_um"):
        if key in kw and not kw[key] > 0:
            raise bad("move", key)
    if kw["profile"] == "s-curve" and "jerk_m_s3" not in kw:
        raise SceneError(f"{origin}: move.jerk_m_s3 missing; expected a jerk > 0 in m/s^3 for profile = 's-curve'")
    if kw["profile"] == "trapezoidal" and "jerk_m_s3" in kw:
        raise SceneError(f"{origin}: move.jerk_m_s3 = {kw['jerk_m_s3']!r} with profile = 'trapezoidal'; expected no "
                         "jerk (a trapezoidal move has infinite jerk) or profile = 's-curve'")
    if kw.get("start_s", 0.0) < 0:
        raise bad("move", "start_s")
    if kw.get("measured", "nut_angle") not in POSITION_SENSORS:
        raise bad("move", "measured")
    if kw.get("position_rate", 1) != 1:
        raise bad("move", "position_rate")
    if kw.get("fidelity", "compliant") not in ("rigid", "compliant"):
        raise bad("move", "fidelity")
    if "hold_step_n" in kw and kw["hold_step_n"] == 0:
        raise bad("move", "hold_step_n")
    if not 1 < kw.get("ms_max", 1.4) < 10:
        raise bad("cascade", "ms_max")
    if kw.get("position_controller", "p") not in ("p", "pi"):
        raise bad("cascade", "position_controller")
    for key in ("weight_following", "weight_holding"):
        if kw.get(key, 1.0) < 0:
            raise bad("cascade", key)
    if kw.get("weight_following", 1.0) + kw.get("weight_holding", 1.0) == 0:
        raise SceneError(f"{origin}: cascade.weight_following = cascade.weight_holding = 0; expected a positive weight")
    if kw.get("bandwidth_ratio", 1.0) < 1:
        raise bad("cascade", "bandwidth_ratio")
    kw["typed"] = dict(doc.get("move", {}))
    kw["distance_m"] = kw.pop("distance_mm") * 1e-3
    kw["max_speed_m_s"] = kw.pop("max_speed_mm_s") * 1e-3
    if "window_um" in kw:
        kw["window_m"] = kw.pop("window_um") * 1e-6
    sc = MoveScene(**kw)
    m = sc.motion()
    if sc.load_time_s is not None and not (m.t0[0] <= sc.load_time_s <= m.end_time):
        raise SceneError(f"{origin}: move.load_time_s = {sc.load_time_s!r}; expected a time in s inside the move "
                         f"[{m.t0[0]:.6g}, {m.end_time:.6g}]")
    return sc


def check_move_against_plant(scene: MoveScene, plant: "Plant") -> None:
    """Refuse a move the plant cannot run, before any tuning (``prsa-tune`` exit 2), as
    :func:`prsa_ctrl.studies.scene.check_against_plant` does for speed-loop scenes: a cruise speed
    outside the speed range of the speed-loop scenes (the cascade is linearised there), a load
    the motor cannot hold while moving (steady torque at cruise speed plus the inertia torque
    of the peak acceleration) or at rest after the hold step, a run longer than
    ``MAX_RECORD_SAMPLES`` controller samples.

    Parameters
    ----------
    scene : MoveScene
    plant : Plant

    Raises
    ------
    SceneError
        One line naming the file, the key and its value as typed, the limit and why.
    """
    from ..plant.equilibrium import steady_torque
    from ..studies.scene import MAX_RECORD_SAMPLES, SETPOINT_MAX_RPM, STICTION_MARGIN

    o, a, ts = scene.origin, plant.lead_per_rad, plant.sample_time_s

    def label(key: str, value: float) -> str:
        return f"{o}: move.{key} = {scene.typed.get(key, value)!r}"

    mm_s_per_rpm = a * math.pi / 30.0 * 1e3
    v_min = STICTION_MARGIN * plant.values["friction.stribeck_velocity_m_s"] * 1e3
    v_max = SETPOINT_MAX_RPM * mm_s_per_rpm
    v = scene.max_speed_m_s * 1e3
    if not v_min <= v <= v_max:
        raise SceneError(
            f"{label('max_speed_mm_s', v)}: expected a speed in [{v_min:.3g}, {v_max:.4g}] mm/s for {plant.name} "
            f"(the nut speeds [{v_min / mm_s_per_rpm:.3g}, {SETPOINT_MAX_RPM:g}] rpm of the speed-loop scenes: below, "
            "the friction is on the steep part of its Stribeck curve, where the cascade's linearisation at the "
            "cruise speed does not hold; above, beyond roller-screw speed ratings)")
    w = scene.max_speed_m_s / a
    inertia = plant.reflected_inertia_kg_m2 * scene.acceleration_m_s2 / a
    limit = plant.torque_limit
    for key, f in (("initial_load_n", scene.initial_load_n), ("load_n", scene.load_n)):
        need = max(abs(steady_torque(plant, w, f)), abs(steady_torque(plant, -w, f))) + inertia
        if not need < limit:
            raise SceneError(
                f"{label(key, f)}: moving at {v:g} mm/s ({w:.4g} rad/s) against {f:g} N needs {need:.3g} N m "
                f"(with {inertia:.3g} N m to accelerate at {scene.acceleration_m_s2:g} m/s^2), beyond the motor limit "
                f"of {limit:g} N m (drive.torque_limit_n_m); expected a smaller load")
    if scene.hold_step_n:
        f = scene.load_n + scene.hold_step_n
        need = abs(steady_torque(plant, 0.0, f))
        if not need < limit:
            raise SceneError(
                f"{label('hold_step_n', scene.hold_step_n)}: holding {f:g} N at rest needs {need:.3g} N m, beyond the "
                f"motor limit of {limit:g} N m (drive.torque_limit_n_m); expected a smaller step")
    n = scene.duration_s / ts
    if n > MAX_RECORD_SAMPLES:
        m = scene.motion()
        move_s = m.end_time - m.t0[0]
        parts = {"distance_mm": move_s, "start_s": scene.start_s,
                 "hold_duration_s": scene.hold_duration_s if scene.hold_step_n else 0.0,
                 "hold_delay_s": scene.hold_delay_s}
        key = max(parts, key=parts.get)
        value = scene.distance_m * 1e3 if key == "distance_mm" else getattr(scene, key)
        raise SceneError(
            f"{label(key, value)}: the run would last {scene.duration_s:.4g} s (a {move_s:.4g} s move), "
            f"{n:.3g} controller samples (sensor.sample_time_s = {ts:g} s); the limit is {MAX_RECORD_SAMPLES} samples, "
            f"a run of at most {MAX_RECORD_SAMPLES * ts:g} s; expected a shorter "
            + ("move (or a higher move.max_speed_mm_s)" if key == "distance_mm" else "time"))


def _scene_path(name_or_path: "str | Path") -> tuple[Path | Any, str]:
    from ..plant.plantfile import _builtin_root

    text = str(name_or_path)
    if isinstance(name_or_path, Path) or text.endswith(".toml") or "/" in text:
        return Path(text).expanduser(), str(Path(text).expanduser())
    return _builtin_root("prsa_ctrl.scenes", "tuning") / f"{text}.toml", f"{text}.toml (built-in)"


def _read(name_or_path: "str | Path") -> tuple[dict | None, str]:
    path, origin = _scene_path(name_or_path)
    try:
        if not path.is_file():
            return None, origin
        return tomllib.loads(path.read_text(encoding="utf-8-sig")), origin  # -sig: a byte-order mark is dropped
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneError(f"{origin}: cannot be read ({exc.__class__.__name__}); expected a UTF-8 TOML file") from None
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"{origin}: invalid TOML ({exc})") from None


def is_move_scene(name_or_path: "str | Path | None") -> bool:
    """Whether the scene (built-in name or path) is a move scene (has a ``[move]`` section).
    Unreadable or missing files answer False (the ordinary scene loader reports them)."""
    if name_or_path is None:
        return False
    try:
        doc, _ = _read(name_or_path)
    except SceneError:
        return False
    return isinstance(doc, dict) and "move" in doc


def load_move_scene(name_or_path: "str | Path") -> MoveScene:
    """Load a move scene by built-in name (``"paper-move"``) or path.

    Parameters
    ----------
    name_or_path : str or Path

    Returns
    -------
    MoveScene

    Raises
    ------
    SceneError
        Missing or unreadable file, invalid TOML, unknown section or key, a value of the
        wrong type or range (one line naming the file and the key).

    Examples
    --------
    >>> sc = load_move_scene("paper-move")
    >>> sc.distance_m, sc.max_speed_m_s, sc.load_n
    (0.01, 0.03, 1500.0)
    """
    doc, origin = _read(name_or_path)
    if doc is None:
        raise SceneError(f"scene {str(name_or_path)!r} not found; expected a built-in name or a readable .toml file")
    if "move" not in doc:
        raise SceneError(f"{origin}: no [move] section; expected a move scene")
    return _parse_move(doc, origin)


# --- simulation and metrics ------------------------------------------------------------------

def simulate_move(plant: "Plant", scene: MoveScene, speed: PID, position: PositionLoop, *,
                  fidelity: str | None = None, settings=None, motion: MotionProfile | None = None,
                  loads: list | None = None, duration: float | None = None) -> "SimRun":
    """Run the scene's move (or ``motion``/``loads``/``duration`` instead) on the nonlinear
    model in the sampled loop, from rest.

    Parameters
    ----------
    plant : Plant
    scene : MoveScene
    speed : PID
        Speed PI.
    position : PositionLoop
    fidelity : {"rigid", "compliant"}, optional
        Default: the scene's.

    Returns
    -------
    SimRun
    """
    from ..sim.simulate import run

    return run(plant, load=loads if loads is not None else scene.loads(),
               duration=duration if duration is not None else scene.duration_s, controller=speed,
               fidelity=fidelity or scene.fidelity, discrete=True, position=position,
               motion=motion if motion is not None else scene.motion(), settings=settings)


@dataclass(frozen=True)
class MoveMetrics:
    """Metrics of one move (SI; positions in m of screw travel as the position loop measures).

    Attributes
    ----------
    peak_following_error_m : float
        Largest |reference - measured| from the start of the move to the hold step.
    rms_following_error_m : float
        RMS of the following error over the move (start to end of the profile).
    settling_time_s : float
        From the end of the profile until the error stays within ``window_m`` (up to the
        hold step); ``inf`` if it never does.
    overshoot_m : float
        Largest travel beyond the target in the direction of the move after the profile ends.
    peak_torque_n_m : float
        Largest |motor torque|.
    holding_deviation_m : float
        Largest |target - measured| after the load step while holding (``nan``-free: 0 without
        a hold step).
    final_error_m : float
        Error at the end of the run.
    hunting : dict
        :func:`hunting` over the last part of the hold.
    screw_holding_deviation_m, screw_final_error_m : float or None
        The same for the screw's true position ``x_S = a th_N + x_roller - delta_screw``
        against its reference (compliant model; None for the rigid one): with the nut angle
        measured, the loop does not see the thread-contact deflection under load.
    """

    peak_following_error_m: float
    rms_following_error_m: float
    settling_time_s: float
    overshoot_m: float
    peak_torque_n_m: float
    holding_deviation_m: float
    final_error_m: float
    hunting: dict = field(default_factory=dict)
    screw_holding_deviation_m: float | None = None
    screw_final_error_m: float | None = None

    def as_dict(self) -> dict:
        d = asdict(self)
        if not math.isfinite(d["settling_time_s"]):
            d["settling_time_s"] = None
        return d


def _error_m(r: "SimRun", plant: "Plant") -> NDArray[np.float64]:
    unit = plant.lead_per_rad if r.info["position_loop"]["measured"] == "nut_angle" else 1.0
    return (r.output("position_reference") - r.output("position_measured")) * unit


def hunting(t: NDArray[np.float64], error_m: NDArray[np.float64], speed: NDArray[np.float64], *,
            window_m: float, stick_band_rad_s: float) -> dict:
    """Sustained oscillation (hunting, a limit cycle against stiction) in a held record.

    The record oscillates when the nut reverses (speed crossing from above ``+2 w_b`` to below
    ``-2 w_b`` or back, ``w_b`` the stick band) at least 4 times and the position error's
    peak-to-peak exceeds ``window_m / 4``: a loop that settles (stuck within the window, or
    decaying) reverses a few times at most.

    Parameters
    ----------
    t : array, s
    error_m : array, m
    speed : array, rad/s
        Nut speed.
    window_m : float, m
    stick_band_rad_s : float, rad/s

    Returns
    -------
    dict
        ``oscillating`` (bool), ``reversals`` (int), ``peak_to_peak_m`` (float) and
        ``period_s`` (mean time between reversals of the same sense, s, or None).
    """
    thr = 2.0 * stick_band_rad_s
    state, flips, times = 0, 0, []
    for tk, w in zip(t, speed):
        s = 1 if w > thr else (-1 if w < -thr else 0)
        if s and s != state:
            if state:
                flips += 1
                times.append(tk)
            state = s
    p2p = float(np.ptp(error_m)) if error_m.size else 0.0
    period = float(2 * np.mean(np.diff(times))) if len(times) >= 2 else None
    return {"oscillating": bool(flips >= 4 and p2p > window_m / 4), "reversals": int(flips),
            "peak_to_peak_m": p2p, "period_s": period}


def move_metrics(r: "SimRun", plant: "Plant", scene: MoveScene) -> MoveMetrics:
    """Metrics of a run of :func:`simulate_move` (see :class:`MoveMetrics`).

    Parameters
    ----------
    r : SimRun
    plant : Plant
    scene : MoveScene

    Returns
    -------
    MoveMetrics
    """
    from ..plant.model import stick_band_rad_s

    t = r.time
    e = _error_m(r, plant)
    m = scene.motion()
    t_start, t_end = m.t0[0], m.end_time
    t_hold = scene.hold_step_s if scene.hold_step_n else t[-1] + 1.0
    pre = t < t_hold
    move = (t >= t_start) & (t <= t_end)
    peak = float(np.max(np.abs(e[(t >= t_start) & pre]))) if np.any((t >= t_start) & pre) else 0.0
    rms = float(np.sqrt(np.mean(e[move] ** 2))) if np.any(move) else 0.0
    after = (t >= t_end) & pre
    settle = math.inf
    if np.any(after):
        ta, ea = t[after], e[after]
        outside = np.flatnonzero(np.abs(ea) > scene.window_m)
        if outside.size == 0:
            settle = 0.0
        elif outside[-1] < ea.size - 1:
            settle = float(ta[outside[-1] + 1] - t_end)
    direction = math.copysign(1.0, scene.distance_m)
    overshoot = float(max(0.0, np.max(-direction * e[after]))) if np.any(after) else 0.0
    hold = t >= t_hold
    holding = float(np.max(np.abs(e[hold]))) if np.any(hold) else 0.0
    tail = t >= (t_hold + 0.5 * (t[-1] - t_hold) if np.any(hold) else t_end + 0.5 * (t[-1] - t_end))
    hunt = hunting(t[tail], e[tail], r.output("nut_speed")[tail], window_m=scene.window_m,
                   stick_band_rad_s=stick_band_rad_s(plant))
    screw_hold = screw_final = None
    if "delta_screw" in r.state_labels:
        x = r.states
        x_s = plant.lead_per_rad * x[r.state_labels.index("theta_nut")] + x[r.state_labels.index("x_roller")] \
            - x[r.state_labels.index("delta_screw")]
        e_s = x_s[0] + m.at(t)[0] - x_s
        screw_hold = float(np.max(np.abs(e_s[hold]))) if np.any(hold) else 0.0
        screw_final = float(e_s[-1])
    return MoveMetrics(peak, rms, settle, overshoot, float(np.max(np.abs(r.output("motor_torque")))), holding,
                       float(e[-1]), hunt, screw_hold, screw_final)


# --- linear model of the sampled cascade ------------------------------------------------------

def _cplx_mul(a, b):
    return (a[0] * b[0] - a[1] * b[1], a[0] * b[1] + a[1] * b[0])


def _abs2(a):
    return a[0] ** 2 + a[1] ** 2


class CascadeModel:
    """Linear model of the sampled cascade around the move's cruise speed and held load.

    Parameters
    ----------
    plant : Plant
    scene : MoveScene
    fidelity : {"rigid", "compliant"}, optional
        Linearised model (default: the scene's).
    n_grid : int
        Frequencies of the Ms constraints (log-spaced to the Nyquist frequency, plus the
        plant's resonances).

    Notes
    -----
    Gains ``g = [kp, ki, kv, kip, kvff, kaff]`` (:data:`CASCADE_GAINS`). The position loop
    runs at the speed-loop rate in this model (``position_rate = 1``).
    """

    def __init__(self, plant: "Plant", scene: MoveScene, fidelity: str | None = None, n_grid: int = 300) -> None:
        from scipy.linalg import expm

        from ..plant.linear import linear_core
        from ..plant.model import plant_model

        if scene.position_rate != 1:
            raise ValueError(f"{scene.origin}: move.position_rate = {scene.position_rate}; the cascade tuner models the "
                             "position loop at the speed-loop rate: expected 1")
        self.plant, self.scene = plant, scene
        fid = fidelity or scene.fidelity
        model = plant_model(plant, fid)
        self.a_lead = a = plant.lead_per_rad
        self.inertia = plant.reflected_inertia_kg_m2
        self.ts = ts = plant.sample_time_s
        w_cruise = scene.max_speed_m_s / a * math.copysign(1.0, scene.distance_m)
        self.w_lin, self.load_lin = w_cruise, scene.load_n
        A, B, _, _, _ = linear_core(plant, w_cruise, scene.load_n, fid)
        n = A.shape[0]
        M = np.zeros((n + 2, n + 2))
        M[:n, :n], M[:n, n:] = A, B
        E = expm(M * ts)
        self.Ad, self.bu, self.bd = E[:n, :n], E[:n, n], E[:n, n + 1]
        self.n = n
        self.c_th = np.eye(n)[model.index("theta_nut")]
        if scene.measured == "nut_angle":
            self.c_pos = self.c_th.copy()
        else:
            self.c_pos = self.c_th.copy()
            if "delta_screw" in model.state_names:
                self.c_pos = self.c_pos + (np.eye(n)[model.index("x_roller")] - np.eye(n)[model.index("delta_screw")]) / a
        self.alpha = math.exp(-ts / plant.speed_filter_s)
        nyq = math.pi / ts
        lam = np.log(np.linalg.eigvals(self.Ad).astype(complex)) / ts
        from .tuner import _resonance_points

        self.omega = np.unique(np.concatenate([np.geomspace(1.0, nyq * 0.999, n_grid),
                                               _resonance_points(lam, 1.0, nyq * 0.999)]))
        self._resp_cache: dict = {}
        self._build_casadi()

    # frequency responses (numeric, gain-free parts)
    def parts(self, omega: NDArray[np.float64]) -> dict[str, NDArray[np.complex128]]:
        """Gain-free responses at ``omega`` (rad/s): ``G`` torque command -> nut angle (rad per
        N m, computation delay and ZOH included), ``Gp`` -> measured position (rad), ``W`` nut
        angle -> speed measurement (1/s), ``cs_i`` and ``cp_i`` the integral parts of the
        speed and position laws per unit gain."""
        w = np.asarray(omega, float)
        zi = np.exp(-1j * w * self.ts)
        z = 1 / zi
        n = self.n
        lhs = z[:, None, None] * np.eye(n)[None] - self.Ad[None]
        res = np.linalg.solve(lhs, np.broadcast_to(self.bu, (w.size, n))[..., None])[..., 0]
        G = zi * (res @ self.c_th)
        Gp = zi * (res @ self.c_pos)
        W = (1 - self.alpha) / (1 - self.alpha * zi) * (1 - zi) / self.ts
        return {"G": G, "Gp": Gp, "W": W, "cs_i": self.ts * zi / (1 - zi), "cp_i": self.ts / (1 - zi)}

    def loops(self, g, omega: NDArray[np.float64] | None = None) -> dict[str, NDArray[np.complex128]]:
        """Loop transfer functions at the three breaking points (module docstring) and at the
        torque command (``torque``: both loops broken at once), at ``omega`` (rad/s)."""
        w = self.omega if omega is None else np.asarray(omega, float)
        P = self.parts(w)
        kp, ki, kv, kip = (float(x) for x in g[:4])
        cs = kp + ki * P["cs_i"]
        cp = kv + kip * P["cp_i"]
        q, r = P["Gp"] * cs * cp, P["W"] * P["G"] * cs
        return {"speed_closed": r / (1 + q), "speed_open": r, "position": q / (1 + r), "torque": q + r}

    def ms(self, g, n_dense: int = 20000) -> dict[str, float]:
        """True peak sensitivities ``max |1/(1 + L)|`` at each breaking point: dense log grid
        (``n_dense`` points to the Nyquist frequency, plus the constraint grid) and a golden
        section search around each grid maximum; with their frequencies (rad/s)."""
        nyq = math.pi / self.ts
        w = np.unique(np.concatenate([np.geomspace(1e-2, nyq * 0.99999, n_dense), self.omega]))
        out = {}
        for name, L in self.loops(g, w).items():
            s = np.abs(1 / (1 + L))
            i = int(np.argmax(s))
            lo, hi = w[max(i - 1, 0)], w[min(i + 1, w.size - 1)]
            f = lambda x: float(np.abs(1 / (1 + self.loops(g, np.array([x]))[name][0])))  # noqa: E731
            gr = (math.sqrt(5) - 1) / 2
            a_, b_ = lo, hi
            for _ in range(60):
                c_, d_ = b_ - gr * (b_ - a_), a_ + gr * (b_ - a_)
                if f(c_) > f(d_):
                    b_ = d_
                else:
                    a_ = c_
            wm = 0.5 * (a_ + b_)
            best = max((s[i], w[i]), (f(wm), wm))
            out[name] = float(best[0])
            out[f"w_{name}"] = float(best[1])
        return out

    def crossover(self, g, loop: str = "speed_open") -> float:
        """First frequency (rad/s) where |L| falls through 1 at a breaking point."""
        nyq = math.pi / self.ts
        w = np.geomspace(1e-1, nyq * 0.999, 20000)
        mag = np.abs(self.loops(g, w)[loop])
        idx = np.flatnonzero((mag[:-1] >= 1) & (mag[1:] < 1))
        return float(w[idx[0]]) if idx.size else float("nan")

    # closed loop in the time domain
    def _build_casadi(self) -> None:
        import casadi as ca

        n, ts, a = self.n, self.ts, self.a_lead
        g = ca.SX.sym("g", 6)
        X = ca.SX.sym("X", n + 5)
        r = ca.SX.sym("r", 4)  # position ref (rad), speed ref (rad/s), accel ref (rad/s^2), load (N)
        kp, ki, kv, kip, kvff, kaff = (g[i] for i in range(6))
        x, th_prev, w_f, i_s, u_pend, i_p = X[:n], X[n], X[n + 1], X[n + 2], X[n + 3], X[n + 4]
        theta = ca.dot(ca.DM(self.c_th), x)
        pm = ca.dot(ca.DM(self.c_pos), x)
        w_f1 = self.alpha * w_f + (1 - self.alpha) * (theta - th_prev) / ts
        e_p = r[0] - pm
        i_p1 = i_p + ts * kip * e_p
        w_ref = kv * e_p + i_p1 + kvff * r[1]
        u = kp * (w_ref - w_f1) + i_s + kaff * self.inertia * r[2]
        i_s1 = i_s + ts * ki * (w_ref - w_f1)
        x1 = ca.mtimes(ca.DM(self.Ad), x) + ca.DM(self.bu) * u_pend + ca.DM(self.bd) * r[3]
        Xn = ca.vertcat(x1, theta, w_f1, i_s1, u, i_p1)
        self.step = ca.Function("cascade_step", [X, r, g], [Xn, e_p * a])
        self.jac = ca.Function("cascade_ab", [g], [ca.jacobian(Xn, X), ca.jacobian(Xn, r)])
        self.nX = n + 5

    def closed_loop_matrices(self, g) -> tuple[NDArray, NDArray]:
        A, B = self.jac(list(map(float, g)))
        return np.asarray(A), np.asarray(B)

    def spectral_radius(self, g) -> float:
        """Largest |closed-loop eigenvalue|; a P position loop (``kip = 0``) leaves its unused
        integral state constant (an undriven eigenvalue 1), which is left out."""
        A = self.closed_loop_matrices(g)[0]
        if float(g[3]) == 0.0:
            A = A[:-1, :-1]
        return float(np.max(np.abs(np.linalg.eigvals(A))))

    def inputs(self, kind: str) -> NDArray[np.float64]:
        """Input sequences (4 x N) of the two tuning experiments: ``"move"`` (the profile with
        the move's load step, from the scene's start to 0.05 s after its end) and ``"hold"``
        (the hold step at rest, 0.1 s). Loads are deviations from the linearisation load."""
        sc, a, ts = self.scene, self.a_lead, self.ts
        if kind == "move":
            m = sc.motion()
            t = np.arange(0.0, m.end_time + 0.05, ts)
            p, v, acc = m.at(t)
            load = np.where(t >= sc.load_at_s, sc.load_n - sc.initial_load_n, 0.0) if sc.load_n != sc.initial_load_n \
                else np.zeros_like(t)
            return np.vstack([p / a, v / a, acc / a, load])
        t = np.arange(0.0, 0.1, ts)
        step = sc.hold_step_n if sc.hold_step_n else max(abs(sc.load_n), 100.0)
        return np.vstack([np.zeros((3, t.size)), np.where(t >= 2 * ts, step, 0.0)])

    def error(self, g, kind: str) -> NDArray[np.float64]:
        """Linear following error / holding deviation (m) of the experiment ``kind``."""
        r = self.inputs(kind)
        f = self.step.mapaccum(r.shape[1])
        _, e = f(np.zeros(self.nX), r, np.tile(np.asarray(g, float)[:, None], (1, r.shape[1])))
        return np.asarray(e).ravel()


@dataclass
class CascadeDesign:
    """A tuned cascade: gains, their true Ms (verified), linear and nonlinear metrics.

    Attributes
    ----------
    method : {"joint", "sequential"}
    speed : PID
    position : PositionLoop
    ms : dict
        True Ms at each breaking point (:meth:`CascadeModel.ms`) with the frequencies.
    crossover_rad_s : dict
        Speed-loop (position loop opened) and position-loop crossovers.
    linear : dict
        Linear peak/RMS following error and holding deviation, m.
    objective : float
        Value of the tuning objective (baseline = weight_following + weight_holding).
    verified : MoveMetrics or None
        Metrics on the nonlinear model.
    notes : list of str
    """

    method: str
    speed: PID
    position: PositionLoop
    ms: dict
    crossover_rad_s: dict
    linear: dict
    objective: float
    verified: MoveMetrics | None = None
    notes: list = field(default_factory=list)
    solver: dict = field(default_factory=dict)
    #: The nonlinear run of :func:`verify_design` (for the figures; not in :meth:`as_dict`).
    run: Any = field(default=None, repr=False, compare=False)

    @property
    def gains(self) -> list[float]:
        return [self.speed.kp, self.speed.ki, *self.position.gains[:2], *self.position.gains[2:]]

    def as_dict(self) -> dict:
        return {"method": self.method, "speed": self.speed.as_dict(),
                "position": {"kv_per_s": self.position.kv, "ki_per_s2": self.position.ki, "kvff": self.position.kvff,
                             "kaff": self.position.kaff, "measured": self.position.measured,
                             "rate": self.position.rate},
                "ms": self.ms, "crossover_rad_s": self.crossover_rad_s, "linear": self.linear,
                "objective": self.objective, "verified": self.verified.as_dict() if self.verified else None,
                "notes": list(self.notes), "solver": self.solver}


def _linear_summary(cm: CascadeModel, g) -> dict:
    em, eh = cm.error(g, "move"), cm.error(g, "hold")
    return {"peak_following_error_m": float(np.max(np.abs(em))), "rms_following_error_m": float(np.sqrt(np.mean(em**2))),
            "holding_deviation_m": float(np.max(np.abs(eh))), "ms_following": float(np.mean(em**2)),
            "ms_holding": float(np.mean(eh**2))}


def _design(cm: CascadeModel, method: str, g, objective: float, notes=None, solver=None) -> CascadeDesign:
    from ..drive.pid import PID
    from ..drive.measurement import PositionLoop

    sc = cm.scene
    speed = PID(float(g[0]), float(g[1]))
    pos = PositionLoop(kv=float(g[2]), ki=float(g[3]), kvff=float(g[4]), kaff=float(g[5]), measured=sc.measured,
                       rate=sc.position_rate)
    cross = {"speed_open": cm.crossover(g, "speed_open"), "position": cm.crossover(g, "position")}
    return CascadeDesign(method, speed, pos, cm.ms(g), cross, _linear_summary(cm, g), float(objective),
                         notes=list(notes or []), solver=dict(solver or {}))


def sequential_design(plant: "Plant", scene: MoveScene, cm: CascadeModel | None = None,
                      ratios=(5.0, 6.0, 7.0, 8.0, 9.0, 10.0)) -> CascadeDesign:
    """The rule-of-thumb baseline (module docstring): speed PI tuned alone at ``scene.ms_max``
    (:func:`prsa_ctrl.tuning.tuner.tune_loops`, IAE of the load step on the drive loop), position P
    at ``crossover / ratio`` for the smallest ``ratio`` in ``ratios`` that keeps every Ms within
    the bound, ``kvff = kaff = 1``.

    Returns
    -------
    CascadeDesign
    """
    from ..plant.linear import linear_core
    from ..plant.model import plant_model
    from .tuner import drive_loop, tune_loops

    cm = cm or CascadeModel(plant, scene)
    model = plant_model(plant, scene.fidelity)
    a_, b_, c_, _, _ = linear_core(plant, cm.w_lin, scene.load_n, scene.fidelity)
    step = scene.hold_step_n or max(abs(scene.load_n), 100.0)
    lp = drive_loop(a_, b_, c_[model.output_names.index("nut_speed")], model.index("theta_nut"), ts=plant.sample_time_s,
                    speed_filter=plant.speed_filter_s, tf=4 * plant.sample_time_s, horizon=0.1, step=step)
    ms_max = scene.ms_max

    def worst(g) -> float:
        pk = cm.ms(g)
        return max(pk[k] for k in BREAKING_POINTS) if cm.spectral_radius(g) < 1 else math.inf

    def attempt(ms_speed: float):
        """Speed PI at ``ms_speed``; the smallest ratio that keeps every Ms <= ms_max (None if
        even the largest does not) and the worst Ms at the largest ratio."""
        res = tune_loops([lp], objective="iae", controller="pi", ms_max=ms_speed)
        kp, ki = res.pid.kp, res.pid.ki
        wc = cm.crossover([kp, ki, 0.0, 0.0, 0.0, 0.0], "speed_open")
        slowest = [kp, ki, wc / max(ratios), 0.0, 1.0, 1.0]
        w_slow = worst(slowest)
        if w_slow > ms_max:
            return res, wc, None, slowest, w_slow
        for ratio in sorted(ratios)[:-1]:
            g = [kp, ki, wc / ratio, 0.0, 1.0, 1.0]
            if worst(g) <= ms_max:
                return res, wc, ratio, g, w_slow
        return res, wc, max(ratios), slowest, w_slow

    # The speed loop alone at Ms = ms_max; if closing the position loop (at the slowest ratio)
    # pushes an Ms above the bound, the speed loop is re-tuned at a lower Ms so that both designs
    # are compared at equal Ms: a secant search on the speed loop's bound for the worst cascade
    # Ms = ms_max (at most 8 speed-loop tunings), keeping the best feasible point.
    res, wc, ratio, g, w_slow = attempt(ms_max)
    ms_speed = ms_max
    if ratio is None:
        x0, f0 = ms_max, w_slow - ms_max
        x1 = max(1.02, ms_max - max(f0, 1e-3))
        found = None
        for _ in range(8):
            out = attempt(x1)
            f1 = out[4] - ms_max
            if out[2] is not None and (found is None or x1 > found[0]):
                found = (x1, out)
            if out[2] is not None and f1 > -1e-3:
                break
            x2 = x1 - f1 * (x1 - x0) / (f1 - f0) if math.isfinite(f1) and f1 != f0 else 0.5 * (x1 + 1.02)
            x2 = min(max(x2, 1.02), ms_max) - (1e-4 if f1 <= 0 else 0.0)
            x0, f0, x1 = x1, f1, x2
        if found is None:
            raise ValueError(f"no sequential cascade found within Ms <= {ms_max:g}; relax cascade.ms_max")
        ms_speed, (res, wc, ratio, g, _) = found
    notes = [f"speed PI tuned alone (tune_loops, IAE of the {step:g} N step, Ms <= {ms_speed:.4g}: {res.status}); "
             f"speed-loop crossover {wc:.4g} rad/s; position P gain kv = crossover/{ratio:g}; kvff = kaff = 1"]
    if ms_speed < ms_max:
        notes.append(f"the speed loop tuned alone at Ms {ms_max:g} gives Ms > {ms_max:g} once the position loop is "
                     f"closed (any ratio in {min(ratios):g}..{max(ratios):g}): re-tuned at Ms {ms_speed:.4g} for equal Ms")
    return _design(cm, "sequential", g, scene.weight_following + scene.weight_holding, notes,
                   {"speed_tuner_status": res.status, "ratio": ratio, "speed_ms_bound": ms_speed})


def _gains_from_solution(x, lbx, ubx, free, scale) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The scaled NLP solution projected onto its bounds, and the six gains it gives
    (:data:`CASCADE_GAINS`). Ipopt may end a hair outside its bounds (``kaff = -9e-9`` for a
    1 um move), which :class:`~prsa_ctrl.drive.measurement.PositionLoop` rightly refuses.

    >>> x, g = _gains_from_solution([1.0, 1.0, 1.0, 1.0, -9e-9], [1e-3] * 3 + [0.0] * 2, [1e3] * 3 + [1.5] * 2,
    ...                             [0, 1, 2, 4, 5], [0.08, 10.0, 40.0, 160.0, 1.0, 1.0])
    >>> float(g[5]), float(g[2])
    (0.0, 40.0)
    """
    x = np.clip(np.asarray(x, float).ravel(), np.asarray(lbx, float), np.asarray(ubx, float))
    gv = np.zeros(6)
    for k, i in enumerate(free):
        gv[i] = x[k] * scale[i]
    return x, gv


def tune_cascade(plant: "Plant", scene: MoveScene, *, baseline: CascadeDesign | None = None,
                 cm: CascadeModel | None = None, max_rounds: int = 8, max_iter: int = 300) -> CascadeDesign:
    """Joint tuning of the whole cascade in one NLP (module docstring), started from the
    sequential baseline.

    Parameters
    ----------
    plant : Plant
    scene : MoveScene
    baseline : CascadeDesign, optional
        The start and the normalisation (default :func:`sequential_design`).
    max_rounds : int
        Most re-solves with frequencies added where the verified Ms exceeds the bound.
    max_iter : int
        Ipopt iteration budget per solve.

    Returns
    -------
    CascadeDesign
        With the verified (dense-grid, refined) Ms at all breaking points.
    """
    import casadi as ca

    cm = cm or CascadeModel(plant, scene)
    baseline = baseline or sequential_design(plant, scene, cm)
    g0 = np.asarray(baseline.gains, float)
    sc = scene
    rm, rh = cm.inputs("move"), cm.inputs("hold")
    e_f0, e_h0 = max(baseline.linear["ms_following"], 1e-300), max(baseline.linear["ms_holding"], 1e-300)
    # Scaled decision variables: gains relative to the baseline's (kip relative to kv^2/10).
    scale = np.array([g0[0], g0[1], g0[2], g0[2] ** 2 / 10, 1.0, 1.0])
    free = [0, 1, 2, 4, 5] + ([3] if sc.position_controller == "pi" else [])
    y = ca.SX.sym("y", len(free))
    gs = [ca.SX(0.0)] * 6
    for k, i in enumerate(free):
        gs[i] = y[k] * scale[i]
    g = ca.vertcat(*gs)
    X0 = ca.DM.zeros(cm.nX)
    fm = cm.step.mapaccum(rm.shape[1])
    fh = cm.step.mapaccum(rh.shape[1])
    em = fm(X0, ca.DM(rm), ca.repmat(g, 1, rm.shape[1]))[1]
    eh = fh(X0, ca.DM(rh), ca.repmat(g, 1, rh.shape[1]))[1]
    J = sc.weight_following * ca.sumsqr(em) / rm.shape[1] / e_f0 + sc.weight_holding * ca.sumsqr(eh) / rh.shape[1] / e_h0
    omegas = list(cm.omega)
    notes: list[str] = []
    x = np.ones(len(free))
    solver_info: dict = {}
    best = None
    for rnd in range(max_rounds):
        P = cm.parts(np.array(omegas))
        def c(v):
            return (ca.DM(v.real), ca.DM(v.imag))
        G, Gp, W, csi, cpi = (c(P[k]) for k in ("G", "Gp", "W", "cs_i", "cp_i"))
        cs = (g[0] + g[1] * csi[0], g[1] * csi[1])
        cp = (g[2] + g[3] * cpi[0], g[3] * cpi[1])
        q = _cplx_mul(_cplx_mul(Gp, cs), cp)
        r = _cplx_mul(_cplx_mul(W, G), cs)
        one_q = (1 + q[0], q[1])
        one_r = (1 + r[0], r[1])
        d = (1 + q[0] + r[0], q[1] + r[1])
        m2 = sc.ms_max ** 2 * (1 - 1e-4)
        cons = [m2 * _abs2(d) - _abs2(one_q), m2 * _abs2(one_r) - 1, m2 * _abs2(d) - _abs2(one_r),
                m2 * _abs2(d) - 1]
        lbg = [0.0] * (4 * len(omegas))
        if sc.bandwidth_ratio is not None:
            cons.append(g[0] / cm.inertia - sc.bandwidth_ratio * g[2])
            lbg.append(0.0)
        lbx = [1e-3] * len(free)
        ubx = [1e3] * len(free)
        for k, i in enumerate(free):
            if i in (4, 5):
                lbx[k], ubx[k] = 0.0, 1.5
        nlp = {"x": y, "f": J, "g": ca.vertcat(*cons)}
        solver = ca.nlpsol("cascade", "ipopt", nlp, {"ipopt.print_level": 0, "print_time": False,
                                                    "ipopt.sb": "yes", "ipopt.max_iter": int(max_iter),
                                                    "ipopt.hessian_approximation": "limited-memory",
                                                    "ipopt.tol": 1e-8})
        sol = solver(x0=x, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ca.inf)
        st = solver.stats()
        x, gv = _gains_from_solution(sol["x"], lbx, ubx, free, scale)
        solver_info = {"status": st["return_status"], "iterations": int(st["iter_count"]), "rounds": rnd + 1,
                       "grid_points": len(omegas)}
        pk = cm.ms(gv)
        worst = max(BREAKING_POINTS, key=lambda k: pk[k])
        stable = cm.spectral_radius(gv) < 1
        if stable and pk[worst] <= sc.ms_max * (1 + MS_RTOL):
            best = gv
            break
        omegas = sorted(set(omegas) | {pk[f"w_{k}"] for k in BREAKING_POINTS})
        notes.append(f"round {rnd + 1}: verified Ms {pk[worst]:.5g} at {worst} (w = {pk['w_' + worst]:.5g} rad/s)"
                     f"{'' if stable else ', unstable'}; frequencies added")
    if best is None:
        notes.append("joint solve did not verify within the Ms bound; the baseline is returned")
        return _design(cm, "joint (failed: baseline)", g0, sc.weight_following + sc.weight_holding, notes, solver_info)
    lin = _linear_summary(cm, best)
    obj = sc.weight_following * lin["ms_following"] / e_f0 + sc.weight_holding * lin["ms_holding"] / e_h0
    return _design(cm, "joint", best, obj, notes, solver_info)


def verify_design(plant: "Plant", scene: MoveScene, design: CascadeDesign, fidelity: str | None = None) -> MoveMetrics:
    """Run ``design`` on the nonlinear model and store its metrics in ``design.verified``.

    Returns
    -------
    MoveMetrics
    """
    r = simulate_move(plant, scene, design.speed, design.position, fidelity=fidelity)
    design.verified = move_metrics(r, plant, scene)
    design.run = r
    return design.verified


# --- export -----------------------------------------------------------------------------------

#: The position loop's per-sample law as the drive export states it (``position_controller.law``):
#: each right-hand side is an expression in the exported fields of ``position_controller`` and
#: the signals ``p_ref, p_meas, v_ref, acc_ref, I_prev`` (the same law as
#: :meth:`prsa_ctrl.drive.measurement.PositionLoop.update`).
POSITION_LAW = {
    "e": "(p_ref - p_meas) * error_to_rad",
    "I": "I_prev + sample_time_s * ki_per_s2 * e",
    "w_ref": "kv_per_s * e + I + velocity_feedforward * v_ref / lead_m_per_rad",
    "tau_ff": "torque_per_acceleration_n_m_s2_per_rad * acc_ref / lead_m_per_rad",
}

def export_cascade(design: CascadeDesign, plant: "Plant", *, fmt: str) -> dict:
    """Drive export of a cascade: the speed PI as :func:`prsa_ctrl.io.export.export_controller`
    gives it, plus the position loop (``Kv`` [1/s], integral gain, feed-forward gains, the
    acceleration feed-forward as a torque per acceleration, the position-loop sample time and
    the discrete law).

    Parameters
    ----------
    design : CascadeDesign
    plant : Plant
    fmt : {"json", "toml"}

    Returns
    -------
    dict
    """
    from ..io.export import export_controller

    out = export_controller(design.speed, plant, fmt=fmt)
    pos = design.position
    ts = plant.sample_time_s
    tp = ts * pos.rate
    a = plant.lead_per_rad
    inertia = float(plant.reflected_inertia_kg_m2)
    out["loop"] = "position over speed"
    ctrl = out["speed_controller"]
    if "vendor" in ctrl and isinstance(ctrl["vendor"], dict):
        ctrl["vendor"]["kv_per_s"] = float(pos.kv)
        ctrl["vendor"]["note"] = ("Tn = kp/ki (integral/reset time), Tv = kd/kp (derivative time), per-rpm gains use "
                                  "1 rpm = 2 pi/60 rad/s; Kv = kv_per_s is the gain of the position loop over this "
                                  "speed loop (see position_controller)")
    law = dict(POSITION_LAW)
    out["position_controller"] = {
        "measured": pos.measured,
        "sample_time_s": tp,
        "kv_per_s": float(pos.kv),
        "kv_m_min_per_mm": float(pos.kv) * 60.0 / 1000.0,  # (m/min of speed) per mm of error
        "ki_per_s2": float(pos.ki),
        "tn_s": float(pos.kv / pos.ki) if pos.ki > 0 else None,
        "velocity_feedforward": float(pos.kvff),
        "acceleration_feedforward": float(pos.kaff),
        "reflected_inertia_kg_m2": inertia,
        "torque_per_acceleration_n_m_s2_per_rad": float(pos.kaff) * inertia,
        "lead_m_per_rad": a,
        "error_to_rad": 1.0 if pos.measured == "nut_angle" else 1.0 / a,
        "law": law,
        "formula": "; ".join(f"{k}[k] = {v}" for k, v in law.items())
                   + " (p_ref, p_meas in the measured unit: rad of the nut for nut_angle, m for screw_position; "
                     "v_ref in m/s, acc_ref in m/s^2 of screw travel; I_prev = I[k-1], 0 at rest); w_ref (rad/s) "
                     "is the speed PI's reference and tau_ff (N m) is added to its command u[k]; both held for "
                     "sample_time_s. torque_per_acceleration_n_m_s2_per_rad already contains "
                     "acceleration_feedforward (= acceleration_feedforward reflected_inertia_kg_m2): do not "
                     "multiply by it again",
        "discretisation": "explicit sum for the integral (I updated with e[k] before use), zero-order hold of w_ref "
                          "and tau_ff over sample_time_s",
    }
    if fmt == "toml":
        out["position_controller"] = {k: v for k, v in out["position_controller"].items() if v is not None}
    return out


# --- prsa-tune --scene <move scene> -----------------------------------------------------------

def _finite_json(obj: Any) -> Any:
    """Plain JSON data: numpy scalars as Python numbers, non-finite numbers as null."""
    if isinstance(obj, dict):
        return {str(k): _finite_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite_json(v) for v in obj]
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj


#: ``prsa-tune`` options a move scene honours; every other option is refused (exit 2).
MOVE_FLAGS = ("plant", "scene", "json", "export", "plots", "quiet", "verbose", "export_real", "export_template", "motor")


def _refused_flag(args: Any, run: Any) -> str | None:
    """The first ``prsa-tune`` option given that a move scene does not honour, as typed."""
    from ..cli.tune import build_parser

    raw = {a.split("=", 1)[0]: a.split("=", 1)[1] for a in getattr(run, "argv", None) or []
           if a.startswith("--") and "=" in a}
    for action in build_parser()._actions:
        if not action.option_strings or action.dest in MOVE_FLAGS or action.dest == "help":
            continue
        value = getattr(args, action.dest, action.default)
        if value is None or value is False or value == action.default:
            continue
        flag = action.option_strings[-1]
        return flag if value is True else f"{flag} {raw.get(flag, value)}"
    return None


def write_move_plots(plant: "Plant", scene: MoveScene, designs: "list[CascadeDesign]", directory: "str | Path") -> list[Path]:
    """Figures of a move scene, PNG and SVG (matplotlib is imported here only): the move
    (position, following error, nut speed and motor torque of each design against time) and
    the hold (position deviation after the hold step, nut and screw side).

    Parameters
    ----------
    plant : Plant
    scene : MoveScene
    designs : list of CascadeDesign
        Verified designs (:func:`verify_design` keeps their runs).
    directory : str or Path
        Existing folder the files are written into.

    Returns
    -------
    list of Path
        ``move.png``, ``move.svg``, ``hold.png``, ``hold.svg``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..plots.loop import save_figure

    directory = Path(directory)
    m = scene.motion()
    runs = []
    for d in designs:
        r = d.run if d.run is not None else simulate_move(plant, scene, d.speed, d.position)
        runs.append((d, r))
    fig, ax = plt.subplots(4, 1, sharex=True, figsize=(7.5, 8.0), layout="constrained")
    t_end = scene.hold_step_s if scene.hold_step_n else scene.duration_s
    for n, (d, r) in enumerate(runs):
        t = np.asarray(r.time)
        unit = plant.lead_per_rad if d.position.measured == "nut_angle" else 1.0
        keep = t <= t_end
        label = f"{d.method} (Kv {d.position.kv:.3g} 1/s)"
        if n == 0:
            ax[0].plot(t[keep], r.output("position_reference")[keep] * unit * 1e3, "k--", lw=1.0, label="reference")
            ax[2].plot(t[keep], m.at(t[keep])[1] / plant.lead_per_rad, "k--", lw=1.0, label="profile")
        ax[0].plot(t[keep], r.output("position_measured")[keep] * unit * 1e3, lw=1.2, label=label)
        ax[1].plot(t[keep], _error_m(r, plant)[keep] * 1e6, lw=1.2, label=label)
        ax[2].plot(t[keep], r.output("nut_speed")[keep], lw=1.2, label=label)
        ax[3].plot(t[keep], r.output("motor_torque")[keep], lw=1.2, label=label)
    for a_ in ax:
        a_.axvline(scene.load_at_s, color="0.6", lw=0.8, ls=":")
        a_.grid(True, alpha=0.3)
    ax[1].axhspan(-scene.window_m * 1e6, scene.window_m * 1e6, color="0.9", zorder=0)
    ax[0].set_ylabel("position (mm)")
    ax[1].set_ylabel("following error (um)")
    ax[2].set_ylabel("nut speed (rad/s)")
    ax[3].set_ylabel("motor torque (N m)")
    ax[3].axhline(plant.torque_limit, color="r", lw=0.8, ls="--")
    ax[3].set_xlabel("time (s)")
    ax[0].legend(fontsize=8)
    ax[0].set_title(f"{scene.name}: {scene.distance_m * 1e3:g} mm move at {scene.max_speed_m_s * 1e3:g} mm/s, "
                    f"{scene.load_n:g} N at {scene.load_at_s:.3g} s (dotted)", fontsize=9)
    files = save_figure(fig, directory / "move")
    plt.close(fig)
    if scene.hold_step_n:
        fig, ax = plt.subplots(1, 1, figsize=(7.5, 4.0), layout="constrained")
        for d, r in runs:
            t = np.asarray(r.time)
            keep = t >= scene.hold_step_s - 0.005
            ax.plot(t[keep], _error_m(r, plant)[keep] * 1e6, lw=1.2,
                    label=f"{d.method}: max {d.verified.holding_deviation_m * 1e6:.3g} um" if d.verified else d.method)
        ax.axhspan(-scene.window_m * 1e6, scene.window_m * 1e6, color="0.9", zorder=0)
        ax.axvline(scene.hold_step_s, color="0.6", lw=0.8, ls=":")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("position deviation (um)")
        ax.set_title(f"holding: {scene.hold_step_n:g} N step at {scene.hold_step_s:.3g} s "
                     f"({'nut angle' if scene.measured == 'nut_angle' else 'screw position'} measured)", fontsize=9)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
        files += save_figure(fig, directory / "hold")
        plt.close(fig)
    return files


def format_move_report(plant: "Plant", scene: MoveScene, designs: "list[CascadeDesign]", prog: str = "prsa-tune") -> str:
    """The text report of a move scene: each design's gains, its true Ms at the four
    loop-breaking points, the verified (nonlinear) metrics and the linear model's.

    Returns
    -------
    str
    """
    w_lin = scene.max_speed_m_s / plant.lead_per_rad
    lines = [f"{prog}: plant {plant.name}, move scene {scene.name}: {scene.distance_m * 1e3:g} mm at "
             f"{scene.max_speed_m_s * 1e3:g} mm/s ({scene.profile}), load {scene.load_n:g} N at {scene.load_at_s:.4g} s, "
             f"hold step {scene.hold_step_n:g} N; Ms <= {scene.ms_max:g} at each loop-breaking point: speed loop "
             "(position loop closed / opened), position loop, torque command (both loops broken at the plant input)"]
    for d in designs:
        v = d.verified
        ki = f", ki {d.position.ki:.4g} 1/s^2" if scene.position_controller == "pi" or d.position.ki > 0 else ""
        lines.append(
            f"  {d.method:10s} kp {d.speed.kp:.4g} N m s/rad, ki {d.speed.ki:.4g} N m/rad, Kv {d.position.kv:.4g} 1/s"
            f"{ki}, kvff {d.position.kvff:.3g}, kaff {d.position.kaff:.3g}; Ms speed(closed/open) "
            f"{d.ms['speed_closed']:.3f}/{d.ms['speed_open']:.3f}, position {d.ms['position']:.3f}, torque command "
            f"{d.ms['torque']:.3f}")
        if v is not None:
            lines.append(
                f"  {'':10s} verified ({scene.fidelity}): following error peak {v.peak_following_error_m * 1e6:.3f} um, "
                f"RMS {v.rms_following_error_m * 1e6:.3f} um; holding deviation {v.holding_deviation_m * 1e6:.3f} um; "
                f"settling {v.settling_time_s * 1e3:.2f} ms; overshoot {v.overshoot_m * 1e6:.3f} um; peak torque "
                f"{v.peak_torque_n_m:.3f} N m; hunting {'YES' if v.hunting['oscillating'] else 'no'}")
        lin = d.linear
        ratio = (f" ({lin['holding_deviation_m'] / v.holding_deviation_m:.2g} x the verified)"
                 if v is not None and v.holding_deviation_m > 0 else "")
        lines.append(
            f"  {'':10s} linear model the tuner optimises (linearised at the cruise speed {w_lin:.4g} rad/s, "
            f"{scene.load_n:g} N): following error peak {lin['peak_following_error_m'] * 1e6:.3f} um, RMS "
            f"{lin['rms_following_error_m'] * 1e6:.3f} um; holding deviation {lin['holding_deviation_m'] * 1e6:.3f} um"
            f"{ratio}: at rest the nut sticks, which the linearisation at speed does not see; the verified "
            "numbers are the truth")
        if v is not None and v.screw_final_error_m is not None and scene.measured == "nut_angle":
            lines.append(f"  {'':10s} screw (load side, not seen by the nut encoder): holding "
                         f"deviation {v.screw_holding_deviation_m * 1e6:.3f} um, final error "
                         f"{v.screw_final_error_m * 1e6:.3f} um")
    for d in designs:
        lines += [f"  note ({d.method}): {n}" for n in d.notes]
    return "\n".join(lines)


def main_move(run: Any, args: Any) -> int:
    """``prsa-tune --scene <move scene>``: tune the cascade jointly and sequentially, verify
    both on the nonlinear model, print the comparison, write ``--json``/``--export``/``--plots``.

    Parameters
    ----------
    run : cli._Run
        The CLI's run context (``say``, ``prog``, ``argv``, ``created``).
    args : argparse.Namespace
        Parsed ``prsa-tune`` arguments. Honoured: :data:`MOVE_FLAGS` (``--plant``, ``--scene``,
        ``--json``, ``--export``, ``--plots``, ``--quiet``, ``--verbose``); any other option
        given is refused in one line (exit 2).

    Returns
    -------
    int
        Exit code (0 ok, 2 bad input, 3 numerical failure).
    """
    import json
    import os
    import sys
    import warnings

    from ..io.export import dumps
    from ..io.output import OutputError, Transaction, check_directory, check_distinct, check_writable
    from ..plant.plantfile import load_plant

    prog = getattr(run, "prog", "prsa-tune")
    quiet, verbose = bool(getattr(args, "quiet", False)), bool(getattr(args, "verbose", False))

    def progress(text: str) -> None:
        if verbose:
            print(f"{prog}: {text}", file=sys.stderr, flush=True)

    def fail(line: str) -> None:
        say = getattr(run, "say", None)
        if callable(say):
            say(f"{prog}: {line}")
        else:
            print(f"{prog}: {line}", file=sys.stderr)

    json_path, export_path, plots_dir = (getattr(args, f, None) for f in ("json", "export", "plots"))
    try:
        refused = _refused_flag(args, run)
        scene = load_move_scene(args.scene)
        if refused:
            raise ValueError(f"{refused} does not apply to a move scene ({scene.name}); expected only --plant, --json, "
                             "--export, --plots, --quiet and --verbose")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            plant = load_plant(getattr(args, "plant", None))
        check_move_against_plant(scene, plant)
        inputs = [v for v in (getattr(args, "plant", None), args.scene) if v is not None and os.path.exists(v)]
        if export_path is not None and os.path.splitext(export_path)[1].lower() not in (".json", ".toml", ".c", ".st"):
            raise ValueError(f"--export {export_path!r}: expected a path ending in .json, .toml, .c or .st")
        check_distinct({"--json": json_path, "--export": export_path, "--plots": plots_dir})
        for flag, path in (("--json", json_path), ("--export", export_path)):
            if path is not None:
                check_writable(path, inputs, flag)
        if export_path is not None and os.path.splitext(export_path)[1].lower() == ".c":  # issue 24: + the header
            from ..io.codegen import check_code_export

            check_code_export(export_path, inputs, "--export")
        if getattr(args, "motor", None) is not None or getattr(args, "export_template", None) is not None:
            from ..drive.params import check_cli_options

            check_cli_options(args)  # issue 24: bad --motor / --export-template exit 2 before tuning
        if plots_dir is not None:
            check_directory(plots_dir, "--plots")
    except (SceneError, ValueError, OutputError) as exc:  # PlantFileError is a ValueError
        fail(f"error: {' '.join(str(exc).split())}")
        return 2
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            progress(f"move scene {scene.name}: linearising the cascade at {scene.max_speed_m_s * 1e3:g} mm/s")
            cm = CascadeModel(plant, scene)
            progress("sequential design (speed PI alone, then the position gain) ...")
            seq = sequential_design(plant, scene, cm)
            progress("joint design (one NLP over all gains) ...")
            joint = tune_cascade(plant, scene, baseline=seq, cm=cm)
            for d in (seq, joint):
                progress(f"verifying the {d.method} design on the nonlinear {scene.fidelity} model ...")
                verify_design(plant, scene, d)
    except KeyboardInterrupt:
        raise
    except Exception as exc:  # noqa: BLE001 - one line at the CLI boundary, as for speed-loop scenes
        from ..cli.tune import _describe_failure

        code, line = _describe_failure(exc, f"tuning the cascade of {scene.name}")
        if verbose:
            print(f"{prog}: detail: {type(exc).__name__}: {' '.join(str(exc).split())[:500]}", file=sys.stderr)
        fail(line)
        return code
    data = _finite_json({"plant": plant.name, "scene": scene.name, "sequential": seq.as_dict(), "joint": joint.as_dict()})
    plot_files: list = []
    with Transaction(inputs) as outputs:  # all outputs or none, as for speed-loop scenes
        if plots_dir is not None:
            progress("writing the figures ...")
            if hasattr(run, "created"):
                from ..cli.tune import _staged

                plot_files = _staged(run, lambda staging: write_move_plots(plant, scene, [seq, joint], staging),
                                     plots_dir, inputs, outputs)
            else:
                os.makedirs(plots_dir, exist_ok=True)
                plot_files = write_move_plots(plant, scene, [seq, joint], plots_dir)
        if json_path is not None:
            text = json.dumps(data, indent=2, allow_nan=False) + "\n"
            outputs.stage(json_path, lambda tmp: tmp.write_text(text, encoding="utf-8"), "--json")
        if export_path is not None:
            fmt = os.path.splitext(export_path)[1].lower().lstrip(".")
            if fmt in ("c", "st"):  # the discrete cascade as code (prsa_ctrl.io.codegen)
                from ..io.codegen import stage_code_export

                stage_code_export(outputs, export_path, joint, plant, real=getattr(args, "export_real", "double"))
            else:
                exported = export_cascade(joint, plant, fmt=fmt)
                if getattr(args, "motor", None) is not None or getattr(args, "export_template", None) is not None:
                    from ..drive.params import cli_export_data

                    exported = cli_export_data(args, exported, joint, plant)
                text = dumps(exported, fmt)
                outputs.stage(export_path, lambda tmp: tmp.write_text(text, encoding="utf-8"), "--export")
        if hasattr(run, "created"):
            from ..cli.tune import _commit

            _commit(run, outputs)
        else:
            outputs.commit()
    if not quiet:
        print(format_move_report(plant, scene, [seq, joint], prog))
        if json_path is not None:
            print(f"JSON report: {json_path}")
        if export_path is not None:
            print(f"drive export: {export_path}")
        if plot_files:
            print(f"plots: {', '.join(str(p) for p in plot_files)}")
    return 0
