"""Nonlinear closed-loop simulation with CasADi's implicit integrators: one simulator.

:func:`run` is the one implementation (plain arrays, no python-control); :func:`simulate` is
the same run returned as python-control ``TimeResponseData`` (``run(...).to_response()``).

Two controller forms:

continuous (``discrete=False``)
    The PID runs inside the ODE on the low-pass-filtered nut speed. Every input discontinuity
    starts a new integration segment at its exact time, so a step is a step and never a ramp.
sampled (``discrete=True``)
    The drive's real loop, one function per controller sample (:func:`_sample_law`, the only
    place the per-sample law is written): quantise the encoder angle, measure the speed with a
    pluggable block (:mod:`prsa_ctrl.drive.measurement`: filtered backward difference or Kalman
    filter), run the PID, and hold the previous command over the sample (one-sample
    computation delay, zero-order hold) while the plant is integrated.

Input events in the sampled loop: a **load** change acts on the plant at its exact time, also
between samples (that sample's integration is split at the event); a **setpoint** change is
seen by the controller at the first sample at or after it (the drive reads its setpoint only
then), and the returned input row shows the setpoint the controller used at each sample.
``info["events"]`` lists each event with the time it acted.

Integrators are built once per plant, fidelity, measurement and settings and reused across
calls (only their parameters change). Every run is bounded before it starts (output size) and
while it runs (a wall-time budget checked between integration chunks, with an injectable
clock), and can audit its own energy balance.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any, Sequence

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from .._lazy import module
from ..drive.filters import LoopFilter, loop_filters
from ..drive.measurement import PositionLoop, SpeedMeasurement, measurement_for
from ..drive.motion import MotionProfile
from ..drive.pid import PID, pid_law
from ..errors import SimulationError
from ..options import SETPOINT_RAD_S, check_number
from ..results import freeze
from ..plant.equilibrium import operating_point
from ..plant.model import PlantModel, plant_model
from ..plant.plantfile import Plant
from .integrators import Built, SimSettings, accumulated, build, continuous_integrator, sample_integrator
from .rosenbrock import RodasSegment
from .signals import NormalisedProfile, Profile, is_number, normalise_profile

if TYPE_CHECKING:  # annotations only
    from ..drive.estimator import KFDesign

control = module("control")  # only SimRun.to_response needs python-control
optimize = module("scipy.optimize")  # only P-only controllers need it (and it costs 0.25 s to import)

__all__ = ["simulate", "run", "SimRun", "energy_balance", "initial_state", "MAX_OUTPUT_POINTS", "INPUT_LABELS",
           "fixed_step_error", "fast_settings"]


#: Input rows of every run: the speed setpoint the controller used (rad/s) and the axial load
#: on the screw (N).
INPUT_LABELS = ("speed_setpoint", "axial_load")
_CTRL_STATES = ("speed_filtered", "pid_integral", "speed_derivative_state")
_SAMPLED_STATES = ("pid_integral", "speed_derivative_state")
#: Extra output rows of a sampled run: the torque command applied to the current loop during
#: the sample that starts at each time (N m), the speed the PID used (rad/s), the raw backward
#: difference of the quantised angle (rad/s) and the load-torque estimate (N m, 0 without an
#: observer).
_SAMPLED_OUTPUTS = ("torque_command", "speed_measured", "speed_fd", "load_torque_estimate")
#: Longest stretch of simulated time per integrator call (s); the wall-time budget is checked
#: between calls, so no run can hang.
CHUNK_S = 0.1
#: Largest number of output points (time samples) one run may return: 2e6 points of ~16 rows
#: are ~256 MB. Checked before anything is allocated.
MAX_OUTPUT_POINTS = 2_000_000


def initial_state(plant: Plant, fidelity: str, ref: float, load: float, pid: PID | None, tau_ff: float,
                  seed: int, observer_ff: bool):
    """Closed-loop steady state before the first input change.

    With an integral action the speed sits on the setpoint and the integral holds the rest of
    the torque; a P-only controller settles where
    ``kp (ref - w) + tau_ff (+ kff * load torque estimate) = torque(w)``.

    Parameters
    ----------
    plant : Plant
    fidelity : {"rigid", "compliant", "multi-roller"}
    ref : float, rad/s
        Nut-speed setpoint at t = 0.
    load : float, N
        Axial load at t = 0.
    pid : PID or None
        The speed controller (None: open loop, the equilibrium torque is held).
    tau_ff : float, N m
        Feed-forward torque added to the command.
    seed : int
        Seed of the per-roller errors (``fidelity="multi-roller"``).
    observer_ff : bool
        The load-torque estimate (equal to the steady torque) is fed forward with ``pid.kff``.

    Returns
    -------
    (OperatingPoint, float)
        The operating point and the PID integral, N m.

    Raises
    ------
    SimulationError
        A P-only loop without a steady state within the torque limit.
    """
    kff = pid.kff if (pid is not None and observer_ff) else 0.0
    if pid is None or pid.ki > 0:
        op = operating_point(plant, ref, load, fidelity, seed)
        return op, (op.torque * (1.0 - kff) - tau_ff) if pid is not None else 0.0
    if pid.kp == 0:
        raise ValueError("PID with kp = ki = 0 has no steady state; expected kp > 0 or ki > 0")

    def residual(w: float) -> float:
        tau = operating_point(plant, w, load, fidelity, seed).torque
        return tau * (1.0 - kff) - tau_ff - pid.kp * (ref - w)

    span = plant.torque_limit / pid.kp
    try:
        w0 = optimize.brentq(residual, ref - span, ref + span, xtol=1e-12, rtol=1e-14, maxiter=200)
    except (ValueError, SimulationError, RuntimeError):
        raise SimulationError(
            f"no steady state of the P-only loop (kp = {pid.kp:g} N m s/rad) at {ref:g} rad/s and {load:g} N "
            "within the torque limit; remedy: raise kp, add an integral gain or lower the load"
        ) from None
    return operating_point(plant, w0, load, fidelity, seed), 0.0


_REMEDY = (
    "loosen rtol/atol, raise max_steps or max_wall_s, or check that the load and gains are "
    "physical (torque limit, contact stiffness)"
)


def _fail(exc: Exception, t0: float, t1: float, names: Sequence[str], x: NDArray[np.float64],
          what: str = "integration failed", remedy: str = _REMEDY) -> SimulationError:
    state = ", ".join(f"{n}={v:.6g}" for n, v in zip(names, x))
    reason = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
    return SimulationError(
        f"{what} between t = {t0:.6g} s and t = {t1:.6g} s from state [{state}] ({reason}); remedy: {remedy}"
    )


class _Budget:
    """The wall-time budget of one run, on the settings' clock."""

    def __init__(self, settings: SimSettings) -> None:
        self.settings = settings
        self.started = settings.clock()

    def check(self, t: float, names: Sequence[str], x) -> None:
        elapsed = self.settings.clock() - self.started
        if elapsed > self.settings.max_wall_s:
            state = ", ".join(f"{n}={v:.6g}" for n, v in zip(names, x))
            raise SimulationError(
                f"run stopped at t = {t:.6g} s: wall-time budget max_wall_s = {self.settings.max_wall_s:g} s used up "
                f"after {elapsed:.3g} s (state [{state}]); remedy: raise max_wall_s, loosen rtol/atol or shorten "
                "the run"
            )

    @property
    def elapsed(self) -> float:
        return self.settings.clock() - self.started


@dataclass(frozen=True, eq=False)
class SimRun:
    """Plain arrays of one simulation; :meth:`to_response` wraps them as python-control data.

    Attributes
    ----------
    time : ndarray, s
    outputs : ndarray
        One row per ``output_labels`` entry: the model's outputs (``nut_speed`` rad/s,
        ``motor_torque`` the actual torque N m, ...) followed by ``torque_command`` (N m) and
        ``speed_measured`` (rad/s), and in sampled runs ``speed_fd`` (rad/s) and
        ``load_torque_estimate`` (N m).
    states : ndarray
        One row per ``state_labels`` entry: the plant's states, then the controller's.
    inputs : ndarray
        ``speed_setpoint`` (rad/s, as the controller used it) and ``axial_load`` (N) rows.
    output_labels, state_labels, input_labels : tuple of str
    info : dict
        Fidelity, controller form, measurement, integrator, tolerances, wall time (s) and the
        input events with the time each acted (``events``).
    energy : dict or None
        With ``energy=True``: cumulative ``work_motor``, ``work_load``, ``work_dissipated`` and
        the ``stored`` energy, J (see :func:`energy_balance`).
    sysname : str
    """

    time: NDArray[np.float64]
    outputs: NDArray[np.float64]
    states: NDArray[np.float64]
    inputs: NDArray[np.float64]
    output_labels: tuple[str, ...]
    state_labels: tuple[str, ...]
    info: dict
    energy: dict | None = None
    input_labels: tuple[str, ...] = INPUT_LABELS
    sysname: str = ""

    def __post_init__(self) -> None:
        # a frozen result: arrays read-only, info and energy read-only mappings
        for name in ("time", "outputs", "states", "inputs", "info", "energy"):
            object.__setattr__(self, name, freeze(getattr(self, name)))

    def __setstate__(self, state: dict) -> None:
        """Unpickled (process pools) read-only as built: pickle does not keep an array's flags."""
        for name, value in state.items():
            object.__setattr__(self, name, freeze(value))

    def output(self, name: str) -> NDArray[np.float64]:
        """The output row ``name``."""
        if name not in self.output_labels:
            raise KeyError(f"output {name!r}; expected one of {', '.join(self.output_labels)}")
        return self.outputs[self.output_labels.index(name)]

    def to_response(self) -> "control.TimeResponseData":
        """This run as python-control ``TimeResponseData`` (a :class:`SimResponse` that also
        carries ``info`` and ``energy``)."""
        return _response_class()(self)


_RESPONSE_CLASS: list = []


def _response_class():
    """``SimResponse``: python-control ``TimeResponseData`` with the run's ``info`` and
    ``energy`` declared (built on first use, so python-control is imported only here)."""
    if _RESPONSE_CLASS:
        return _RESPONSE_CLASS[0]
    class SimResponse(control.TimeResponseData):
        """Time response of :func:`simulate`: python-control's ``TimeResponseData`` plus

        Attributes
        ----------
        info : dict
            As :attr:`SimRun.info`.
        energy : dict or None
            As :attr:`SimRun.energy`.
        """

        info: dict
        energy: dict | None

        def __init__(self, r: SimRun) -> None:
            super().__init__(
                r.time, r.outputs, r.states, r.inputs,
                output_labels=list(r.output_labels), state_labels=list(r.state_labels),
                input_labels=list(r.input_labels), sysname=r.sysname, plot_inputs=False,
            )
            self.info = r.info
            self.energy = r.energy

    _RESPONSE_CLASS.append(SimResponse)
    return SimResponse


def simulate(plant: Plant, **kwargs: Any) -> "control.TimeResponseData":
    """Simulate the actuator's speed loop from steady state: :func:`run` returned as
    python-control ``TimeResponseData`` (``run(plant, **kwargs).to_response()``).

    Parameters
    ----------
    plant : Plant
    **kwargs
        Exactly :func:`run`'s keyword arguments.

    Returns
    -------
    control.TimeResponseData
        With ``info`` and ``energy`` attributes (see :class:`SimRun`).

    Examples
    --------
    >>> from prsa_ctrl import load_plant, simulate, PID
    >>> r = simulate(load_plant(), load=[(0, 500), (0.05, 1500)], duration=0.1,
    ...              controller=PID(0.5, 20.0), fidelity="rigid")
    >>> float(r.outputs[0].min()) < 31.4159
    True
    """
    return run(plant, **kwargs).to_response()


def run(
    plant: Plant,
    *,
    setpoint: Profile = SETPOINT_RAD_S,
    load: Profile = 500.0,
    duration: float = 0.6,
    controller: PID | None = None,
    feedforward_torque: float = 0.0,
    fidelity: str = "compliant",
    discrete: bool = False,
    dt: float = 1e-4,
    measurement: "str | SpeedMeasurement" = "encoder",
    kf: "KFDesign | None" = None,
    torque_noise: bool = False,
    settings: SimSettings | None = None,
    energy: bool = False,
    seed: int = 0,
    position: "PositionLoop | None" = None,
    motion: "MotionProfile | None" = None,
    filters: "Sequence[LoopFilter] | None" = None,
) -> SimRun:
    """Simulate the actuator's speed loop from steady state (the one simulator).

    Parameters
    ----------
    plant : Plant
    setpoint : float, list of (time_s, rad/s) or PiecewiseLinear
        Nut-speed setpoint: a list of pairs is piecewise constant (steps), a
        :class:`PiecewiseLinear` ramps between its points. A sampled controller reads it at
        each sample (a step at the first sample at or after its time).
    load : float, list of (time_s, N) or PiecewiseLinear
        Axial load on the screw, steps (e.g. ``[(0, 500), (0.2, 1500)]``) or ramps; it acts on
        the plant exactly, also between controller samples (the integration is split at every
        step or kink). The run starts in steady state at the t = 0 values.
    duration : float, s
        Length of the run. A sampled run ends at the last sample at or before it.
    controller : PID, optional
        Speed controller. Without one the torque command is held at the initial equilibrium
        torque (open loop) plus ``feedforward_torque``.
    feedforward_torque : float, N m
        Torque added to the controller's command.
    fidelity : {"rigid", "compliant", "multi-roller"}
    discrete : bool
        Run the drive's sampled loop (plant sample time, zero-order hold, one-sample
        computation delay, quantised encoder) instead of a continuous controller.
    dt : float, s
        Output spacing in continuous mode (a sampled run outputs every sample).
    measurement : {"encoder", "kf"} or SpeedMeasurement
        Sampled runs only: the speed the PID acts on, the filtered encoder difference
        (default) or the Kalman filter ``kf``, which also estimates the load torque that
        ``controller.kff`` feeds forward.
    kf : KFDesign, optional
        Filter for ``measurement="kf"`` (default :func:`prsa_ctrl.drive.estimator.design_kf`).
    torque_noise : bool
        Sampled runs only: add the plant's current-measurement noise
        (``sensor.torque_noise_n_m``, seeded by ``seed``) to the applied torque as ripple.
    settings : SimSettings, optional
    energy : bool
        Also integrate motor, load and dissipated work (see :func:`energy_balance`); the run
        then audits its energy balance against ``settings.energy_tol``.
    seed : int
        Seed of the per-roller errors (``fidelity="multi-roller"``) and of the torque noise.
    position : PositionLoop, optional
        Sampled runs only: a position loop over the speed PI (``controller``, which then needs
        an integral gain). The run starts at rest (``setpoint`` is not used: the position loop
        gives the speed reference, reported in the ``speed_setpoint`` input row) and the
        outputs gain ``position_measured``, ``position_reference`` (rad or m, see
        ``PositionLoop.measured``), ``speed_reference`` (rad/s) and ``torque_feedforward`` (N m).
    motion : MotionProfile, optional
        The move the position loop follows, m of screw travel from the position measured at
        t = 0 (default: hold that position).
    filters : sequence of LoopFilter, optional
        Sampled runs only: speed-measurement and torque-command filters
        (:class:`prsa_ctrl.drive.filters.LoopFilter`, or ``(place, Filter)`` pairs), each run as the
        discrete biquad the drive export writes. The outputs gain ``speed_unfiltered`` (the
        measurement block's speed before the speed-measurement filters, rad/s) and
        ``torque_command_unfiltered`` (the PID's limited command before the torque-command
        filters, N m); ``speed_measured`` is the filtered speed the PID acted on.

    Returns
    -------
    SimRun

    Raises
    ------
    ValueError
        For an invalid argument (the message names it and what was expected), or a run whose
        output would exceed ``MAX_OUTPUT_POINTS`` points.
    SimulationError
        If the integrator fails, the budget is used up or the energy audit fails (the message
        names the time, the state and a remedy).

    Examples
    --------
    >>> from prsa_ctrl import load_plant, PID
    >>> r = run(load_plant(), load=[(0, 500), (0.0101, 1500)], duration=0.02,
    ...         controller=PID(0.085, 14.7), fidelity="rigid", discrete=True)
    >>> r.info["events"][0]["acts_at_s"], r.output_labels[-4:]
    (0.0101, ('torque_command', 'speed_measured', 'speed_fd', 'load_torque_estimate'))
    """
    settings = SimSettings() if settings is None else settings
    if not isinstance(plant, Plant):
        raise ValueError(f"plant = {plant!r}; expected a Plant (see prsa_ctrl.load_plant)")
    if not isinstance(settings, SimSettings):
        raise ValueError(f"settings = {settings!r}; expected a SimSettings")
    if controller is not None and not isinstance(controller, PID):
        raise ValueError(f"controller = {controller!r}; expected a PID or None")
    if not isinstance(discrete, bool):
        raise ValueError(f"discrete = {discrete!r}; expected True or False")
    duration = check_number("duration", duration, 0.0, 1e6, unit="s", lo_open=True)
    feedforward_torque = check_number("feedforward_torque", feedforward_torque, -1e6, 1e6, unit="N m")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed = {seed!r}; expected an integer >= 0")
    if position is not None or motion is not None:
        if not isinstance(position, PositionLoop):
            raise ValueError(f"position = {position!r}; expected a PositionLoop (with motion = a MotionProfile)")
        if motion is None:
            motion = MotionProfile((), (), (), (), (), 0.0)
        if not isinstance(motion, MotionProfile):
            raise ValueError(f"motion = {motion!r}; expected a MotionProfile (prsa_ctrl.drive.motion)")
        if motion.t0 and motion.t0[0] < 0:
            raise ValueError(f"motion starts at {motion.t0[0]!r} s; expected a start at t >= 0")
        if not discrete:
            raise ValueError("position = PositionLoop(...) with discrete = False; expected discrete=True (the position "
                             "loop runs in the drive's sampled loop)")
        if controller is None or controller.ki <= 0:
            raise ValueError(f"controller = {controller!r} with a position loop; expected a speed PI (ki > 0) that "
                             "holds the load at rest")
        setpoint = 0.0
    if filters is not None:
        filters = loop_filters(filters, plant.sample_time_s if discrete else None)
        if filters and not discrete:
            raise ValueError(f"filters = {filters!r} with discrete = False; expected discrete=True (the filters run in "
                             "the drive's sampled loop)")
    else:
        filters = ()
    if discrete and settings.integrator == "rodas":
        raise ValueError("settings.integrator = 'rodas' with discrete = True; expected 'cvodes', 'idas' or 'radau' "
                         "(RODAS4 integrates the continuous loop only)")
    if discrete:
        ts = plant.sample_time_s
        n_points = math.floor(duration / ts + 1e-9) + 1
        if n_points < 2:
            raise ValueError(f"duration = {duration!r} s is shorter than the sample time {ts:g} s")
        size_msg = f"duration {duration:g} s at the sample time {ts:g} s"
    else:
        if not (is_number(dt) and math.isfinite(dt) and 0 < dt <= duration):
            raise ValueError(f"dt = {dt!r}; expected 0 < dt <= duration ({duration} s)")
        n_points = int(duration / dt) + 1
        size_msg = f"duration {duration:g} s at dt = {dt:g} s"
    if n_points > MAX_OUTPUT_POINTS:
        raise ValueError(f"{size_msg} gives {n_points:.3g} output points; expected at most "
                         f"{MAX_OUTPUT_POINTS:.0e} (shorten the run or coarsen dt)")
    sp = normalise_profile(setpoint, duration, "setpoint", "rad/s")
    ld = normalise_profile(load, duration, "load", "N")
    model = plant_model(plant, fidelity, seed)
    if discrete:
        meas = measurement_for(plant, measurement, kf)
    elif measurement != "encoder" or torque_noise:
        raise ValueError(f"measurement = {measurement!r}, torque_noise = {torque_noise!r}; expected the defaults "
                         "in continuous mode (estimators and noise belong to the sampled loop: discrete=True)")
    else:
        meas = None
    if controller is not None and controller.kff > 0 and not (meas is not None and meas.estimates_load):
        raise ValueError(f"PID kff = {controller.kff:g} needs a load-torque estimate; expected discrete=True "
                         "with measurement='kf'")
    built = build(model, energy, shared=discrete and position is None and settings.integrator == "radau")
    budget = _Budget(settings)

    op, integral0 = initial_state(plant, fidelity, float(sp.v[0]), float(ld.v[0]), controller, feedforward_torque, seed,
                                  observer_ff=meas is not None and meas.estimates_load)
    gains = controller.params if controller is not None else [0.0, 0.0, 0.0, 1e-3]
    kff = controller.kff if controller is not None else 0.0
    ff = feedforward_torque + (0.0 if controller is not None else op.torque)
    e0 = np.concatenate([built.theta0, np.zeros(3 if energy else 0)])  # (theta0: family parameters)
    if discrete:
        assert meas is not None
        t, xs, extra, refs, loads, state_labels, events = _run_sampled(
            built, settings, budget, meas, sp, ld, n_points - 1, gains, kff, ff, op, integral0, e0, torque_noise,
            seed, outer=position, motion=motion, filters=filters)
        if position is not None:  # the speed reference the position loop gave is the setpoint used
            refs = extra[len(_SAMPLED_OUTPUTS) + _POSITION_OUTPUTS.index("speed_reference")]
    else:
        x0 = np.concatenate([op.x, [op.omega_nut, integral0, op.omega_nut], e0])
        t, xs = _run_continuous(built, settings, budget, sp, ld, duration, dt, gains, ff, x0)
        refs, loads = sp.at(t), ld.at(t)
        extra = _continuous_extras(model, xs, refs, gains, ff, plant.torque_limit)
        state_labels = tuple(model.state_names) + _CTRL_STATES
        events = [{"input": name, "time_s": float(tk), "acts_at_s": float(tk)}
                  for name, prof in (("speed_setpoint", sp), ("axial_load", ld)) for tk in prof.t[prof.jump]]
    n_ctrl = len(state_labels) - model.nx
    if not np.all(np.isfinite(xs)):
        bad = int(np.argmax(~np.all(np.isfinite(xs), axis=0)))
        raise _fail(ValueError("non-finite state"), t[max(bad - 1, 0)], t[bad], state_labels, xs[:, max(bad - 1, 0)])

    nx = model.nx
    u_in = np.vstack([extra[0], loads])
    y = np.asarray(model.h.map(len(t))(xs[:nx], u_in))
    out_labels = tuple(model.output_names) + (_SAMPLED_OUTPUTS if discrete else _SAMPLED_OUTPUTS[:2]) \
        + (_POSITION_OUTPUTS if position is not None else ()) + (_FILTER_OUTPUTS if filters else ())
    info = {
        "fidelity": fidelity,
        "discrete": bool(discrete),
        "measurement": meas.name if meas is not None else "continuous filter",
        "integrator": settings.integrator,
        "rtol": settings.rtol,
        "atol": settings.atol,
        "events": events,
        "wall_time_s": budget.elapsed,
    }
    if filters:
        info["filters"] = [lf.to_dict(plant.sample_time_s) for lf in filters]
    if position is not None:
        info["position_loop"] = {"measured": position.measured, "rate": position.rate, "kv_per_s": position.kv,
                                 "ki_per_s2": position.ki, "kvff": position.kvff, "kaff": position.kaff,
                                 "position_unit": "rad" if position.measured == "nut_angle" else "m"}
    energy_terms = None
    if energy:
        stored = np.asarray(model.power.map(len(t))(xs[:nx], u_in))[0]
        energy_terms = {
            "stored": stored,
            "work_motor": xs[-3],
            "work_load": xs[-2],
            "work_dissipated": xs[-1],
        }
        audit = energy_balance(SimpleNamespace(energy=energy_terms))
        if audit["relative_residual"] > settings.energy_tol:
            raise _fail(
                ValueError(f"energy balance residual {audit['residual_j']:.3g} J, relative "
                           f"{audit['relative_residual']:.2g} > energy_tol {settings.energy_tol:g}"),
                0.0, float(t[-1]), state_labels, xs[: nx + n_ctrl, -1], what="untrustworthy integration",
                remedy=f"tighten rtol/atol (now {settings.rtol:g}/{settings.atol:g})",
            )
    return SimRun(t, np.vstack([y, extra]), xs[: nx + n_ctrl], np.vstack([refs, loads]), out_labels,
                  state_labels, info, energy_terms, INPUT_LABELS, f"{plant.name}[{fidelity}]")


def _chunks(bounds: list[float]) -> list[tuple[float, float]]:
    """Integration pieces: every input discontinuity starts a piece (a restart), and long
    segments are cut into pieces of at most ``CHUNK_S``."""
    out = []
    for t0, t1 in zip(bounds[:-1], bounds[1:]):
        n = max(1, math.ceil((t1 - t0) / CHUNK_S - 1e-9))
        edges = np.linspace(t0, t1, n + 1)
        out += [(float(a), float(b)) for a, b in zip(edges[:-1], edges[1:])]
    return out


def _run_continuous(built, settings, budget, sp, ld, duration, dt, gains, ff, x0):
    scale = built.scale
    names = tuple(built.model.state_names) + _CTRL_STATES
    z = x0 / scale
    times = [np.array([0.0])]
    states = [x0[:, None]]
    bounds = sorted({0.0, duration, *sp.t.tolist(), *ld.t.tolist()})
    for t0, t1 in _chunks(bounds):
        budget.check(t0, names, z * scale)
        n_out = max(1, int(round((t1 - t0) / dt)))
        integ = continuous_integrator(built, settings, n_out)
        par = [float(sp.at(t0)), float(ld.at(t0)), *gains, ff, t1 - t0, float(sp.slope_at(t0)),
               float(ld.slope_at(t0))]
        try:
            if isinstance(integ, RodasSegment):  # its chunks check the wall-time budget inside the segment
                zf = integ(x0=z, p=par, check=lambda tau, zz, a=t0, b=t1: budget.check(a + (b - a) * tau, names,
                                                                                         zz * scale))["xf"]
            else:
                zf = np.asarray(integ(x0=z, p=par)["xf"])
        except SimulationError:  # the budget's own message (raised by a RODAS4 segment's check)
            raise
        except RuntimeError as exc:
            raise _fail(exc, t0, t1, names, z * scale) from None
        times.append(t0 + (t1 - t0) * np.arange(1, n_out + 1) / n_out)
        states.append(zf * scale[:, None])
        z = zf[:, -1]
    return np.concatenate(times), np.hstack(states)


def _continuous_extras(model: PlantModel, xs, refs, gains, ff, torque_limit: float) -> NDArray[np.float64]:
    """Torque command and filtered speed of the continuous controller at each output time."""
    nx = model.nx
    w_f, integral, w_d = xs[nx], xs[nx + 1], xs[nx + 2]
    kp, _, kd, tf = gains
    u = kp * (refs - w_f) + integral - kd * (w_f - w_d) / tf + ff
    return np.vstack([np.clip(u, -torque_limit, torque_limit), w_f])


# --- the sampled loop --------------------------------------------------------------------------
# Memory carried from sample to sample: previous quantised angle (rad), PID integral (N m),
# derivative-filter state (rad/s^2), previous measured speed (rad/s), pending command (N m),
# then the measurement block's memory, then this sample's reported values (_SAMPLED_OUTPUTS).
_MEM_HEAD = ("encoder_angle_prev", "pid_integral", "speed_derivative_state", "speed_measured_prev",
             "torque_command_pending")
# Per-sample parameters: setpoint (rad/s); load (N) and its slope (N/s) at the sample start;
# load and slope after a breakpoint inside the sample; the breakpoint's position in the sample
# (0..1, 0 = none); torque ripple (N m); kp, ki, kd, tf, kff; feed-forward torque (N m).
_NPS = 13


#: Extra output rows of a sampled run with a position loop: the position it measured and its
#: reference (rad of the nut or m of the screw, ``PositionLoop.measured``), the speed reference
#: it gave the speed loop (rad/s) and its torque feed-forward (N m).
_POSITION_OUTPUTS = ("position_measured", "position_reference", "speed_reference", "torque_feedforward")
#: Extra output rows of a sampled run with filters (:class:`prsa_ctrl.drive.filters.LoopFilter`): the
#: measurement block's speed before the speed-measurement filters (rad/s) and the PID's limited
#: command before the torque-command filters (N m).
_FILTER_OUTPUTS = ("speed_unfiltered", "torque_command_unfiltered")
#: Memory of one filter biquad (direct form I: last two inputs and outputs) and its per-sample
#: parameters (b0, b1, b2, a1, a2).
_FILTER_MEMORY = ("x1", "x2", "y1", "y2")
_FILTER_NP = 5


def _biquad_step(x, mem, c):
    """``y = b0 x + b1 x1 + b2 x2 - a1 y1 - a2 y2`` and the shifted memory (direct form I, the
    recursion of :meth:`prsa_ctrl.drive.filters.DiscreteBiquad.step`)."""
    y = c[0] * x + c[1] * mem[0] + c[2] * mem[1] - c[3] * mem[2] - c[4] * mem[3]
    return y, [x, mem[0], y, mem[2]]


def _measured_position(model: PlantModel, x, theta_q, outer: "PositionLoop"):
    """The position the position loop reads: the quantised nut angle (rad), or the screw
    position ``x_S = a th_N + x_roller - delta_screw`` (m; ``a th_N`` in the rigid model)
    quantised at the linear scale's resolution."""
    if outer.measured == "nut_angle":
        return theta_q
    p = model.plant
    x_s = p.lead_per_rad * x[model.index("theta_nut")]
    if "delta_screw" in model.state_names:
        x_s = x_s + x[model.index("x_roller")] - x[model.index("delta_screw")]
    res = outer.scale_resolution_m
    return ca.floor(x_s / res) * res


def _sample_law(built: Built, settings: SimSettings, meas: SpeedMeasurement, split: bool,
                outer: "PositionLoop | None" = None, places: tuple[str, ...] = ()) -> ca.Function:
    """One controller sample of the drive (the only place the per-sample law is written).

    At the sampling instant: quantise the encoder angle, let the measurement block update,
    filter the derivative, run the PID (with the block's load-torque estimate fed forward by
    ``kff``) and store the new command. Over the sample: apply the command stored at the
    previous sample (one-sample computation delay, zero-order hold, plus optional ripple; with
    the plant's ``drive.command_delay_samples`` = n, the current loop receives it n samples
    later, through a line of n commands after the rest of the memory; the reported
    ``torque_command`` is the controller's output, before that delay) and integrate the plant,
    split at a load event inside the sample when ``split``; then let the measurement block
    predict with the applied command.

    With an ``outer`` block (a :class:`~prsa_ctrl.drive.measurement.PositionLoop`), the speed
    reference is not the setpoint column but what the block computes at the same instant from
    the measured position (the quantised nut angle, or the screw position quantised at the
    linear scale's resolution), and its torque feed-forward adds to the command. Its memory
    follows the measurement block's; its reported values (``_POSITION_OUTPUTS``) follow
    ``_SAMPLED_OUTPUTS``; its per-sample inputs follow the ``_NPS`` parameters.

    ``places`` (one entry per :class:`~prsa_ctrl.drive.filters.LoopFilter`, in order) adds the
    filters' biquads: ``speed_measurement`` ones filter the measured speed before the PID (its
    error, integral and derivative all act on the filtered speed), ``torque_command`` ones
    filter the PID's limited command, which is limited again before it is stored for the next
    sample. Their memory (``_FILTER_MEMORY`` each) follows the position loop's; their
    coefficients (``_FILTER_NP`` each) follow the other per-sample parameters; their reported
    values (``_FILTER_OUTPUTS``) come last.

    ``(zm = [scaled plant state; memory], p = per-sample parameters) -> zm at the next sample``
    """
    model, scale = built.model, built.plant_scale
    p = model.plant
    n_dl = p.command_delay_samples
    key = (settings, meas.key(), split, outer.key() if outer is not None else None, tuple(places), n_dl)
    if key in built.sampled:
        return built.sampled[key]
    nz, nx = len(scale), model.nx
    n_meas = len(meas.memory_names)
    n_outer = len(outer.memory_names) if outer is not None else 0
    n_filt = len(_FILTER_MEMORY) * len(places)
    nm = len(_MEM_HEAD) + n_meas + n_outer + n_filt + len(_SAMPLED_OUTPUTS) + (len(_POSITION_OUTPUTS) if outer else 0) \
        + (len(_FILTER_OUTPUTS) if places else 0) + n_dl
    ts = p.sample_time_s
    q = 2.0 * math.pi / p.encoder_counts
    integ = sample_integrator(built, settings)
    zm = ca.SX.sym("zm", nz + nm)
    n_par_outer = _NPS + (outer.n_inputs if outer is not None else 0)
    par = ca.SX.sym("p", n_par_outer + _FILTER_NP * len(places))
    z, mem = zm[:nz], zm[nz:]
    ref, load_a, slope_a, load_b, slope_b, frac, ripple = (par[i] for i in range(7))
    gains, kff, tau_ff = par[7:11], par[11], par[12]
    th_prev, integral, deriv_old, w_prev, u_pend = mem[0], mem[1], mem[2], mem[3], mem[4]
    m_meas = mem[5 : 5 + n_meas]

    theta = (z * scale)[model.index("theta_nut")]
    theta_q = ca.floor(theta / q) * q
    w_fd = (theta_q - th_prev) / ts
    w_meas, tl_hat, m_meas = meas.update(m_meas, theta_q, th_prev)
    m_filt = mem[5 + n_meas + n_outer : 5 + n_meas + n_outer + n_filt]
    filt_next: list = [None] * len(places)

    def run_filters(x, place):
        for i, pl in enumerate(places):
            if pl == place:
                c = par[n_par_outer + _FILTER_NP * i : n_par_outer + _FILTER_NP * (i + 1)]
                x, filt_next[i] = _biquad_step(x, m_filt[4 * i : 4 * i + 4], c)
        return x

    w_raw = w_meas
    w_meas = run_filters(w_meas, "speed_measurement")
    beta = ca.exp(-ts / gains[3])
    deriv = beta * deriv_old + (1 - beta) * (w_meas - w_prev) / ts
    if outer is not None:
        m_outer = mem[5 + n_meas : 5 + n_meas + n_outer]
        p_meas = _measured_position(model, z * scale, theta_q, outer)
        p_ref = par[_NPS]
        ref, tau_pos, m_outer = outer.update(m_outer, p_meas, par[_NPS:], ts, p.lead_per_rad,
                                             p.reflected_inertia_kg_m2)
        tau_ff = tau_ff + tau_pos
    _, u_sat, dintegral = pid_law(ref - w_meas, integral, deriv, gains, tau_ff + kff * tl_hat, p.torque_limit)
    u_pid = u_sat
    if "torque_command" in places:
        u_sat = ca.fmin(ca.fmax(run_filters(u_sat, "torque_command"), -p.torque_limit), p.torque_limit)
    # The controller's output over this sample is the command stored at the previous one; the
    # drive's command delay (n_dl samples, a line of the last n_dl outputs, oldest first, after
    # the rest of the memory) passes it to the current loop n_dl samples later.
    if n_dl:
        line = mem[nm - n_dl:]
        applied, line_next = line[0] + ripple, ca.vertcat(*[line[i] for i in range(1, n_dl)], u_pend)
    else:
        applied, line_next = u_pend + ripple, ca.DM.zeros(0)
    if split:
        z = integ(x0=z, p=ca.vertcat(applied, load_a, slope_a, frac * ts))["xf"]
        z = integ(x0=z, p=ca.vertcat(applied, load_b, slope_b, (1 - frac) * ts))["xf"]
    else:
        z = integ(x0=z, p=ca.vertcat(applied, load_a, slope_a, ts))["xf"]
    m_meas = meas.predict(m_meas, u_pend)
    mem_next = ca.vertcat(theta_q, integral + ts * dintegral, deriv, w_meas, u_sat, m_meas,
                          *([m_outer] if outer is not None else []), *[v for f in filt_next for v in f],
                          u_pend, w_meas, w_fd, tl_hat,
                          *([p_meas, p_ref, ref, tau_pos] if outer is not None else []),
                          *([w_raw, u_pid] if places else []), line_next)
    law = ca.Function("sample_law", [zm, par], [ca.vertcat(z, mem_next)])
    built.sampled[key] = law
    return law


def _sample_events(ld: NormalisedProfile, sp: NormalisedProfile, ts: float, n: int):
    """Per-sample load columns and the event log of a sampled run (see the module docstring).

    Samples ``0 .. n-1`` advance the plant. A load breakpoint (step or ramp kink) strictly
    inside a sample splits that sample's integration there; at most one per sample.
    """
    t_samples = ts * np.arange(n)
    load_a, slope_a = ld.at(t_samples), ld.slope_at(t_samples)
    load_b, slope_b = load_a.copy(), slope_a.copy()
    frac = np.zeros(n)
    events = []
    for t_e, value, slope, jump in zip(ld.t[1:], ld.v[1:], ld.s[1:], ld.jump[1:]):
        k = math.floor(t_e / ts + 1e-9)
        if k >= n:
            raise ValueError(f"load change at {t_e:g} s comes after the last sample ({(n - 1) * ts:g} s); "
                             "expected it earlier or a longer duration")
        if t_e - k * ts > 1e-9 * ts:
            if frac[k] > 0:
                raise ValueError(f"two load changes inside the sample starting at {k * ts:g} s; expected at most one "
                                 f"per sample time ({ts:g} s): resample the load profile")
            frac[k] = (t_e - k * ts) / ts
            load_b[k], slope_b[k] = value, slope
        if jump:
            events.append({"input": "axial_load", "time_s": float(t_e), "acts_at_s": float(t_e)})
    for t_e in sp.t[1:][sp.jump[1:]]:
        k = math.ceil(t_e / ts - 1e-9)
        if k >= n:
            raise ValueError(f"setpoint change at {t_e:g} s comes after the last sample ({(n - 1) * ts:g} s); "
                             "expected it earlier or a longer duration")
        events.append({"input": "speed_setpoint", "time_s": float(t_e), "acts_at_s": round(k * ts, 12)})
    return load_a, slope_a, load_b, slope_b, frac, sorted(events, key=lambda e: e["time_s"])


def _run_sampled(built, settings, budget, meas, sp, ld, n, gains, kff, ff, op, integral0, e0, torque_noise, seed,
                 outer=None, motion=None, filters=()):
    """Samples ``0 .. n``: the first ``n`` advance the plant to ``t_n``; the one at ``t_n`` is
    evaluated too, so that what the drive measured and commanded there is reported.

    With a position loop ``outer`` the reference is ``motion`` (a
    :class:`~prsa_ctrl.drive.motion.MotionProfile`, m) added to the position measured at t = 0, read
    at each position-loop sample (every ``outer.rate``-th controller sample)."""
    model = built.model
    p = model.plant
    ts = p.sample_time_s
    scale = built.plant_scale
    nz, nx = len(scale), model.nx
    n_meas = len(meas.memory_names)
    t = ts * np.arange(n + 1)
    load_a, slope_a, load_b, slope_b, frac, events = _sample_events(ld, sp, ts, n)
    load_a, slope_a, load_b, slope_b, frac = (np.append(v, v[-1]) for v in (load_a, slope_a, load_b, slope_b, frac))
    frac[-1] = 0.0
    refs = sp.at(t)
    sigma = p.values["sensor.torque_noise_n_m"]
    ripple = (np.random.default_rng(seed).normal(0.0, sigma, n + 1) if torque_noise and sigma > 0
              else np.zeros(n + 1))
    cols = np.vstack([refs, load_a, slope_a, load_b, slope_b, frac, ripple,
                      np.tile(np.r_[gains, kff, ff][:, None], (1, n + 1))])
    q = 2.0 * math.pi / p.encoder_counts
    if outer is not None:
        # A position run starts at rest: the encoder reads the middle of a count, so that no
        # rounding at a count edge flickers the reading (the plant does not depend on the angle).
        x_mid = np.array(op.x, dtype=float)
        x_mid[model.index("theta_nut")] = 0.5 * q
        op = dataclasses.replace(op, x=x_mid)
    theta0, w0 = op.x[model.index("theta_nut")], op.omega_nut
    n_outer = len(outer.memory_names) if outer is not None else 0
    if outer is not None:
        p_meas0 = float(_measured_position(model, op.x, math.floor(theta0 / q) * q, outer))
        p_ref, v_ref, a_ref = motion.at(t)
        active = (np.arange(n + 1) % outer.rate == 0).astype(float)
        cols = np.vstack([cols, p_meas0 + p_ref / outer.unit_m(p.lead_per_rad), v_ref, a_ref, active,
                          np.tile(np.asarray(outer.gains)[:, None], (1, n + 1))])
    places = tuple(lf.place for lf in filters)
    n_filt = len(_FILTER_MEMORY) * len(places)
    if filters:  # coefficients as per-sample parameters (one compiled law per filter structure)
        coef = np.concatenate([[bq.b0, bq.b1, bq.b2, bq.a1, bq.a2] for bq in (lf.biquad(ts) for lf in filters)])
        cols = np.vstack([cols, np.tile(coef[:, None], (1, n + 1))])
    # Filters start in steady state: past inputs and outputs at the steady speed or torque (unit DC gain).
    filt0 = [v for pl in places for v in [w0 if pl == "speed_measurement" else op.torque] * 4]
    mem0 = [math.floor((theta0 - w0 * ts) / q) * q, integral0, 0.0, w0, op.torque,
            *meas.initial(theta0, w0, op.torque), *(outer.initial() if outer is not None else []), *filt0,
            *np.zeros(len(_SAMPLED_OUTPUTS) + (len(_POSITION_OUTPUTS) if outer is not None else 0)
                      + (len(_FILTER_OUTPUTS) if filters else 0)),
            *[op.torque] * p.command_delay_samples]  # the command delay line, in steady state
    zm = np.concatenate([np.concatenate([op.x, e0]) / scale, mem0])
    filt_names = tuple(f"filter{i + 1}_{pl}_{m}" for i, pl in enumerate(places) for m in _FILTER_MEMORY)
    names = tuple(model.state_names) + ("energy",) * len(e0) + _MEM_HEAD + meas.memory_names \
        + (outer.memory_names if outer is not None else ()) + filt_names
    plain = _sample_law(built, settings, meas, split=False, outer=outer, places=places)
    splits = np.flatnonzero(frac > 0)
    per_chunk = max(1, int(round(CHUNK_S / ts)))
    out = []
    k0 = 0
    while k0 <= n:
        budget.check(k0 * ts, names, zm[:nz] * scale)
        if frac[k0] > 0:
            k1, law = k0 + 1, _sample_law(built, settings, meas, split=True, outer=outer, places=places)
        else:
            later = splits[splits > k0]
            k1 = min(k0 + per_chunk, n + 1, int(later[0]) if later.size else n + 1)
            law = accumulated(built, plain, k1 - k0) if k1 - k0 > 1 else plain
        try:
            traj = np.asarray(law(zm, cols[:, k0:k1]))
        except RuntimeError as exc:
            raise _fail(exc, k0 * ts, k1 * ts, names, np.concatenate([zm[:nz] * scale, zm[nz:]])) from None
        out.append(traj)
        zm = traj[:, -1]
        k0 = k1
    traj = np.hstack(out)
    plant_x = np.hstack([np.concatenate([op.x, e0])[:, None], traj[:nz, :n] * scale[:, None]])
    mem = np.hstack([np.asarray(mem0, float)[:, None], traj[nz:, :n]])
    ctrl = np.vstack([mem[1:3], mem[5 : 5 + n_meas + n_outer + n_filt]])
    extra = traj[nz + len(_MEM_HEAD) + n_meas + n_outer + n_filt : traj.shape[0] - p.command_delay_samples, :]
    xs = np.vstack([plant_x[:nx], ctrl, plant_x[nx:]])
    state_labels = tuple(model.state_names) + _SAMPLED_STATES + tuple(meas.memory_names) \
        + (tuple(outer.memory_names) if outer is not None else ()) + filt_names
    return t, xs, extra, refs, ld.at(t), state_labels, events


def energy_balance(result) -> dict[str, float]:
    """Energy audit of a simulation run with ``energy=True``.

    Parameters
    ----------
    result : SimRun or TimeResponseData
        From :func:`run` or :func:`simulate` with ``energy=True``.

    Returns the motor work, load work, dissipated work and change of stored (kinetic plus
    contact) energy in J, the residual ``W_motor - W_load - W_diss - dE`` and the residual
    relative to the largest of those terms and of the stored energy.
    """
    if getattr(result, "energy", None) is None:
        raise ValueError("result has no energy terms; expected simulate(..., energy=True)")
    e = result.energy
    w_m, w_l, w_d = (float(e[k][-1] - e[k][0]) for k in ("work_motor", "work_load", "work_dissipated"))
    d_e = float(e["stored"][-1] - e["stored"][0])
    residual = w_m - w_l - w_d - d_e
    # Relative to the largest energy in play (a run can release stored energy with little motor work).
    scale = max(abs(w_m), abs(w_l), abs(w_d), abs(d_e), float(np.max(np.abs(e["stored"]))), 1e-300)
    return {
        "work_motor_j": w_m,
        "work_load_j": w_l,
        "work_dissipated_j": w_d,
        "stored_change_j": d_e,
        "residual_j": residual,
        "relative_residual": abs(residual) / scale,
    }


def fixed_step_error(plant: Plant, settings: SimSettings | None = None, reference: SimSettings | None = None,
                     **run_kwargs: Any) -> dict[str, float]:
    """Measured nut-speed error of a run with ``settings`` (default the fixed-step
    ``SimSettings(integrator="radau")``) against the same run with a tight CVODES reference
    (default rtol = atol = 1e-10).

    Parameters
    ----------
    plant : Plant
    settings, reference : SimSettings, optional
    **run_kwargs
        :func:`run`'s other keyword arguments (the scenario: setpoint, load, controller, ...).

    Returns
    -------
    dict
        ``max_error_rad_s`` (largest nut-speed difference, rad/s), ``max_deviation_rad_s``
        (largest deviation of the reference's nut speed from its start, rad/s, e.g. the
        peak drop of a load step) and ``relative`` (their ratio: compare it with a scene's
        ``accuracy``).
    """
    settings = SimSettings(integrator="radau") if settings is None else settings
    reference = SimSettings(rtol=1e-10, atol=1e-10) if reference is None else reference
    w_ref = run(plant, settings=reference, **run_kwargs).output("nut_speed")
    w = run(plant, settings=settings, **run_kwargs).output("nut_speed")
    err = float(np.max(np.abs(w - w_ref)))
    dev = float(np.max(np.abs(w_ref - w_ref[0])))
    return {"max_error_rad_s": err, "max_deviation_rad_s": dev, "relative": err / dev if dev > 0 else math.inf}


def fast_settings(plant: Plant, accuracy: float, settings: SimSettings | None = None, margin: float = 0.5,
                  reference: SimSettings | None = None, **run_kwargs: Any) -> tuple[SimSettings | None, dict[str, float]]:
    """The fixed-step settings when their measured error (:func:`fixed_step_error` against
    ``reference``, on the scenario ``run_kwargs``) is inside ``margin * accuracy`` of the
    reference's deviation, else ``None`` (keep the adaptive reference integrator). Returns the
    choice and the measurement, which a report should quote."""
    settings = SimSettings(integrator="radau") if settings is None else settings
    if not (is_number(accuracy) and 0 < accuracy < 1):
        raise ValueError(f"accuracy = {accuracy!r}; expected a relative accuracy in (0, 1)")
    measured = fixed_step_error(plant, settings, reference, **run_kwargs)
    return (settings if measured["relative"] <= margin * accuracy else None), measured
