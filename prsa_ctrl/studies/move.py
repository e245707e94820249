"""Move scenes run, measured and tuned: the check against the plant, the nonlinear run of a move
(:func:`simulate_move`), its metrics (:func:`move_metrics`, :func:`hunting`), the verification
of a cascade design (:func:`verify_design`) and the tuning of both cascades a move scene
compares (:func:`tune_move`: sequential rule and joint NLP, :mod:`prsa_ctrl.tuning.cascade`).

Simulation
    :func:`simulate_move` runs the move in the one sampled-loop simulator
    (:func:`prsa_ctrl.sim.engine.run` with a :class:`~prsa_ctrl.drive.measurement.PositionLoop`),
    from rest, on the nonlinear model (Stribeck friction with Karnopp stiction, both
    directions; compliant threads). :func:`move_metrics` gives peak and RMS following error,
    settling time into the position window, overshoot, peak torque, the holding deviation
    after the load step while holding and the hunting check (:func:`hunting`).

The scene itself (:class:`~prsa_ctrl.studies.movescene.MoveScene`) is parsed in
:mod:`prsa_ctrl.studies.movescene`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from typing import TYPE_CHECKING, Callable

import numpy as np
from numpy.typing import NDArray

from ..drive.measurement import PositionLoop
from ..drive.motion import MotionProfile
from ..drive.pid import PID
from ..options import rpm_to_rad_s
from ..errors import SceneError
from ..plant.equilibrium import steady_torque
from ..plant.model import stick_band_rad_s
from ..sim.engine import run
from ..tuning import cascade
from .movescene import MoveScene
from .scenefile import MAX_RECORD_SAMPLES, SETPOINT_MAX_RPM, STICTION_MARGIN

if TYPE_CHECKING:
    from ..plant.plantfile import Plant
    from ..sim.engine import SimRun
    from ..tuning.cascade import CascadeDesign

__all__ = ["check_move_against_plant", "simulate_move", "friction_feedforward_effect", "MoveMetrics", "following_error_m", "hunting",
           "move_metrics", "verify_design", "tune_move"]


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
    o, a, ts = scene.origin, plant.lead_per_rad, plant.sample_time_s

    def label(key: str, value: float) -> str:
        return f"{o}: move.{key} = {scene.typed.get(key, value)!r}"

    mm_s_per_rpm = rpm_to_rad_s(a) * 1e3
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
    if scene.filters:
        from .scenefilters import check_filters_against_plant

        check_filters_against_plant(scene.filters, scene.filter_labels, ts, plant.name)
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



def simulate_move(plant: "Plant", scene: MoveScene, speed: PID, position: PositionLoop, *,
                  fidelity: str | None = None, settings=None, motion: MotionProfile | None = None,
                  loads: list | None = None, duration: float | None = None, filters=None) -> "SimRun":
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
    filters : sequence of LoopFilter, optional
        The drive's loop filters (default: the scene's ``filters``).

    Returns
    -------
    SimRun
    """
    filters = scene.filters if filters is None else tuple(filters)
    return run(plant, load=loads if loads is not None else scene.loads(),
               duration=duration if duration is not None else scene.duration_s, controller=speed,
               fidelity=fidelity or scene.fidelity, discrete=True, position=position,
               motion=motion if motion is not None else scene.motion(), settings=settings,
               **({"filters": filters} if filters else {}))


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
        Largest travel beyond the target in the direction of the (last) move after the profile ends.
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


def following_error_m(r: "SimRun", plant: "Plant") -> NDArray[np.float64]:
    """Position reference minus the measured position of a run of :func:`simulate_move`, m of
    screw travel (the nut angle measured: rad times the lead)."""
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
    t = r.time
    e = following_error_m(r, plant)
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
    # the direction of the last move (back to the start for an out-and-back move)
    direction = math.copysign(1.0, scene.distance_m) * (-1.0 if scene.return_dwell_s is not None else 1.0)
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

def verify_design(design: "CascadeDesign", plant: "Plant", scene: MoveScene, fidelity: str | None = None
                  ) -> "CascadeDesign":
    """Run ``design`` on the nonlinear model: a copy of it with its metrics in ``verified``
    (and the run in ``run``, for the figures). The argument order is the speed loop's
    :func:`prsa_ctrl.studies.autotune.verify` (design, plant, scene); ``design`` is not changed.

    Returns
    -------
    CascadeDesign
    """
    r = simulate_move(plant, scene, design.speed, design.position, fidelity=fidelity, filters=design.filters)
    return replace(design, verified=move_metrics(r, plant, scene), run=r)


def tune_move(plant: "Plant", scene: MoveScene, progress: Callable[[str], None] | None = None
              ) -> "list[CascadeDesign]":
    """Tune the cascade of a move scene sequentially (:func:`prsa_ctrl.tuning.cascade.sequential_design`)
    and jointly (:func:`prsa_ctrl.tuning.cascade.tune_cascade`, started from the sequential
    design) on one linear model, and verify both on the nonlinear model (:func:`verify_design`).

    Parameters
    ----------
    plant : Plant
    scene : MoveScene
    progress : callable, optional
        Called with one line before each step.

    Returns
    -------
    list of CascadeDesign
        ``[sequential, joint]``, both verified.
    """
    say = progress or (lambda text: None)
    say(f"move scene {scene.name}: linearising the cascade at {scene.max_speed_m_s * 1e3:g} mm/s")
    spec = scene.cascade_spec()
    cm = cascade.CascadeModel(plant, spec)
    say("sequential design (speed PI alone, then the position gain) ...")
    seq = cascade.sequential_design(plant, spec, cm)
    say("joint design (one NLP over all gains) ...")
    joint = cascade.tune_cascade(plant, spec, baseline=seq, cm=cm)
    verified = []
    for d in (seq, joint):
        say(f"verifying the {d.method} design on the nonlinear {scene.fidelity} model ...")
        verified.append(verify_design(d, plant, scene))
    return verified


def friction_feedforward_effect(design: "CascadeDesign", plant: "Plant", scene: MoveScene, *,
                                load_n: float | None = None, gain: float = 1.0) -> dict:
    """The move run with and without the plant's friction feed-forward, on the nonlinear model.

    The feed-forward (:class:`~prsa_ctrl.drive.friction.FrictionFeedforward`) is the plant file's
    friction curve at the scene's load at the start of the move (``load_n`` to choose another),
    applied from the profile's speed in the drive's sampled law; everything else is ``design``.

    Parameters
    ----------
    design : CascadeDesign
    plant : Plant
    scene : MoveScene
    load_n : float, N, optional
        Axial load the friction curve is computed at (default: ``scene.initial_load_n``).
    gain : float
        Fraction of the friction model fed forward.

    Returns
    -------
    dict
        ``feedforward`` (the curve, plain data with a table up to the scene's speed),
        ``without`` and ``with`` (:class:`MoveMetrics` as dicts, m and s), the verified
        ``rms_ratio`` and ``peak_ratio`` (with / without) and ``design`` (the design with the
        feed-forward in its position loop, verified).
    """
    from ..drive.friction import FrictionFeedforward

    load = scene.initial_load_n if load_n is None else load_n
    ff = FrictionFeedforward.from_plant(plant, load, gain)
    base = design if design.verified is not None and design.position.friction is None else \
        verify_design(replace(design, position=replace(design.position, friction=None)), plant, scene)
    with_ff = verify_design(replace(design, position=replace(design.position, friction=ff)), plant, scene)
    a, b = base.verified, with_ff.verified
    return {"feedforward": ff.as_dict(scene.max_speed_m_s / plant.lead_per_rad),
            "without": a.as_dict(), "with": b.as_dict(),
            "rms_ratio": b.rms_following_error_m / a.rms_following_error_m if a.rms_following_error_m > 0 else None,
            "peak_ratio": b.peak_following_error_m / a.peak_following_error_m if a.peak_following_error_m > 0 else None,
            "design": with_ff}
