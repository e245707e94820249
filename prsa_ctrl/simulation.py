"""Nonlinear closed-loop simulation with CasADi's implicit integrators.

Inputs are piecewise constant (load and setpoint steps); every discontinuity starts a new
integration segment, so a step is a step and never a ramp. Integrators are built once per
plant, fidelity and settings and reused across calls (only their parameters change).
"""

from __future__ import annotations

import math
import time
import weakref
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import TYPE_CHECKING, Sequence

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from .controller import PID, pid_law
from .equilibrium import operating_point
from .errors import SimulationError
from .model import PlantModel, plant_model
from .plant import Plant

if TYPE_CHECKING:  # annotations only: python-control is imported where it is used
    import control

__all__ = ["simulate", "run", "SimRun", "Profile", "SimSettings", "energy_balance", "INTEGRATORS"]

INTEGRATORS = ("cvodes", "idas")

_CTRL_STATES = ("speed_filtered", "pid_integral", "speed_derivative_state")
#: Longest stretch of simulated time per integrator call (s); the wall-time budget is checked
#: between calls, so no run can hang.
CHUNK_S = 0.1
_ENERGY_STATES = ("work_motor", "work_load", "work_dissipated")
# Parameter vector of the closed loop: setpoint, load, kp, ki, kd, tf, feed-forward, duration.
_NP = 8


Profile = float | Sequence[tuple[float, float]]


@dataclass(frozen=True)
class SimSettings:
    """Integrator settings. Tolerances apply to states scaled to order one.

    Parameters
    ----------
    integrator : {"cvodes", "idas"}
    rtol, atol : float
        Relative and absolute tolerances.
    max_steps : int
        Step budget per output interval; exceeding it raises :class:`SimulationError`.
    max_wall_s : float
        Wall-time budget of one run, s, checked between integration chunks (at most
        ``CHUNK_S`` of simulated time each); exceeding it raises :class:`SimulationError`.
    energy_tol : float
        With ``energy=True`` the run audits itself: an energy-balance residual above this
        (relative, see :func:`energy_balance`) means the integration is not trustworthy and
        raises :class:`SimulationError`.
    """

    integrator: str = "cvodes"
    rtol: float = 1e-8
    atol: float = 1e-8
    max_steps: int = 20000
    max_wall_s: float = 120.0
    energy_tol: float = 1e-4

    def __post_init__(self) -> None:
        if self.integrator not in INTEGRATORS:
            raise ValueError(f"integrator = {self.integrator!r}; expected one of {', '.join(INTEGRATORS)}")
        for name in ("rtol", "atol"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not (0 < v < 1):
                raise ValueError(f"{name} = {v!r}; expected a tolerance in (0, 1)")
        if int(self.max_steps) < 10:
            raise ValueError(f"max_steps = {self.max_steps!r}; expected an integer >= 10")
        if not (isinstance(self.max_wall_s, (int, float)) and self.max_wall_s > 0):
            raise ValueError(f"max_wall_s = {self.max_wall_s!r}; expected a positive time in s")


def _state_scale(model: PlantModel) -> NDArray[np.float64]:
    """Typical magnitude of each state, so that tolerances mean the same for all of them."""
    p = model.plant
    w = 100.0
    f_rated = p.rated_load_n
    per_contact = f_rated * max(p.normal_force_factor()) / p.n_contacts
    defl = (per_contact / p.contact_stiffness_si) ** (1.0 / p.values["contact.exponent"])
    scale = {
        "theta_nut": 10.0,
        "theta_cage": 10.0,
        "omega_nut": w,
        "omega_cage": w,
        "x_roller": defl,
        "v_roller": defl * 1e3,
        "delta_screw": defl,
        "v_screw": p.lead_per_rad * w,
        "tau_motor": p.torque_limit,
    }
    return np.array([scale[n] for n in model.state_names])


@dataclass(eq=False)
class _Built:
    """Closed-loop functions of one plant model (built once)."""

    model: PlantModel
    scale: NDArray[np.float64]
    energy: bool
    rhs: ca.Function  # (z, p) -> dz/dt in scaled, duration-normalised time
    continuous: dict = field(default_factory=dict)  # (settings, n_out) -> integrator
    sampled: dict = field(default_factory=dict)  # settings -> one-sample integrator


_BUILT: "weakref.WeakKeyDictionary[PlantModel, dict[bool, _Built]]" = weakref.WeakKeyDictionary()


def _plant_rates(model: PlantModel, x, u, load, energy: bool):
    """Plant state rates, followed by the motor, load and dissipated powers when ``energy``."""
    uu = ca.vertcat(u, load)
    if not energy:
        return model.f(x, uu)
    return ca.vertcat(model.f(x, uu), model.power(x, uu)[1:])


def _build(model: PlantModel, energy: bool) -> _Built:
    cache = _BUILT.setdefault(model, {})
    if energy in cache:
        return cache[energy]
    p = model.plant
    nx = model.nx
    ctrl_scale = [100.0, p.torque_limit, 100.0]  # rad/s, N m, rad/s
    scale = np.concatenate([_state_scale(model), ctrl_scale, np.ones(3 if energy else 0)])
    z = ca.SX.sym("z", len(scale))
    par = ca.SX.sym("p", _NP)
    ref, load, gains, tau_ff, duration = par[0], par[1], par[2:6], par[6], par[7]
    x_all = z * scale
    x = x_all[:nx]
    w_f, integral, w_d = x_all[nx], x_all[nx + 1], x_all[nx + 2]
    tf = gains[3]
    derivative = (w_f - w_d) / tf
    u, _, dintegral = pid_law(ref - w_f, integral, derivative, gains, tau_ff, p.torque_limit)
    w_n = x[model.index("omega_nut")]
    plant_rates = _plant_rates(model, x, u, load, energy)
    rates = ca.vertcat(
        plant_rates[:nx], (w_n - w_f) / p.speed_filter_s, dintegral, derivative, plant_rates[nx:]
    )
    rhs = duration * rates / scale
    built = _Built(model, scale, energy, ca.Function("rhs", [z, par], [rhs]))
    cache[energy] = built
    return built


def _opts(settings: SimSettings) -> dict:
    return {
        "abstol": settings.atol,
        "reltol": settings.rtol,
        "max_num_steps": int(settings.max_steps),
        "print_stats": False,
    }


def _continuous_integrator(built: _Built, settings: SimSettings, n_out: int) -> ca.Function:
    key = (settings, n_out)
    if key not in built.continuous:
        z = ca.SX.sym("z", len(built.scale))
        par = ca.SX.sym("p", _NP)
        dae = {"x": z, "p": par, "ode": built.rhs(z, par)}
        grid = list(np.linspace(0.0, 1.0, n_out + 1)[1:])
        built.continuous[key] = ca.integrator("segment", settings.integrator, dae, 0.0, grid, _opts(settings))
    return built.continuous[key]


def _normalise_profile(profile: Profile, duration: float, what: str, unit: str) -> list[tuple[float, float]]:
    if isinstance(profile, (int, float)) and not isinstance(profile, bool):
        pts = [(0.0, float(profile))]
    else:
        try:
            pts = [(float(t), float(v)) for t, v in profile]  # type: ignore[union-attr]
        except (TypeError, ValueError):
            raise ValueError(
                f"{what} = {profile!r}; expected a number ({unit}) or a list of (time_s, value) pairs"
            ) from None
    if not pts:
        raise ValueError(f"{what} = {profile!r}; expected at least one value")
    for t, v in pts:
        if not (math.isfinite(t) and math.isfinite(v)):
            raise ValueError(f"{what} point ({t}, {v}) is not finite; expected finite time (s) and value ({unit})")
    if pts[0][0] != 0.0:
        raise ValueError(f"{what} starts at t = {pts[0][0]} s; expected the first point at t = 0")
    times = [t for t, _ in pts]
    if any(b <= a for a, b in zip(times, times[1:])) or times[-1] >= duration:
        raise ValueError(f"{what} times {times} must increase strictly and stay below the duration {duration} s")
    return pts


def _value_at(pts: list[tuple[float, float]], t: float) -> float:
    val = pts[0][1]
    for tk, vk in pts:
        if tk <= t + 1e-12:
            val = vk
    return val


def _initial_speed(plant: Plant, fidelity: str, ref: float, load: float, pid: PID | None, tau_ff: float,
                   seed: int = 0):
    """Closed-loop steady speed (rad/s) and torque (N m) before the first input change."""
    if pid is None or pid.ki > 0:
        op = operating_point(plant, ref, load, fidelity, seed)
        return op, op.torque - tau_ff if pid is not None else 0.0
    if pid.kp == 0:
        raise ValueError("PID with kp = ki = 0 has no steady state; expected kp > 0 or ki > 0")

    def residual(w: float) -> float:
        return operating_point(plant, w, load, fidelity, seed).torque - tau_ff - pid.kp * (ref - w)

    from scipy.optimize import brentq  # only P-only controllers need it (and it costs 0.25 s to import)

    span = plant.torque_limit / pid.kp
    w0 = brentq(residual, ref - span, ref + span, xtol=1e-12, rtol=1e-14)
    return operating_point(plant, w0, load, fidelity, seed), 0.0


_REMEDY = (
    "loosen rtol/atol, raise max_steps or max_wall_s, or check that the load and gains are "
    "physical (torque limit, contact stiffness)"
)


def _fail(exc: Exception, t0: float, t1: float, model: PlantModel, x: NDArray[np.float64],
          what: str = "integration failed", remedy: str = _REMEDY) -> SimulationError:
    names = model.state_names + _CTRL_STATES
    state = ", ".join(f"{n}={v:.6g}" for n, v in zip(names, x))
    reason = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
    return SimulationError(
        f"{what} between t = {t0:.6g} s and t = {t1:.6g} s from state [{state}] ({reason}); remedy: {remedy}"
    )


def simulate(
    plant: Plant,
    *,
    setpoint: Profile = 31.4159,
    load: Profile = 500.0,
    duration: float = 0.6,
    controller: PID | None = None,
    feedforward_torque: float = 0.0,
    fidelity: str = "compliant",
    discrete: bool = False,
    dt: float = 1e-4,
    settings: SimSettings | None = None,
    energy: bool = False,
    seed: int = 0,
) -> "control.TimeResponseData":
    """Simulate the actuator's speed loop from steady state.

    Parameters
    ----------
    plant : Plant
    setpoint : float or list of (time_s, rad/s)
        Nut-speed setpoint, piecewise constant.
    load : float or list of (time_s, N)
        Axial load on the screw, piecewise constant (e.g. ``[(0, 500), (0.2, 1500)]``).
    duration : float, s
    controller : PID, optional
        Speed controller. Without one the torque command is held at the initial equilibrium
        torque (open loop) plus ``feedforward_torque``.
    feedforward_torque : float, N m
        Torque added to the controller's command.
    fidelity : {"rigid", "compliant", "multi-roller"}
    discrete : bool
        Run the controller at the plant's sample time with zero-order hold, a one-sample
        computation delay and the quantised encoder, instead of in continuous time.
    dt : float, s
        Output spacing in continuous mode (discrete mode outputs every sample).
    settings : SimSettings, optional
    energy : bool
        Also integrate motor, load and dissipated work (see :func:`energy_balance`).
    seed : int
        Seed of the per-roller errors (``fidelity="multi-roller"`` only).

    Returns
    -------
    control.TimeResponseData
        Outputs ``nut_speed``, ``cage_speed``, ``roller_speed`` (spin relative to the cage),
        ``roller_speed_abs``, ``screw_velocity`` (m/s), ``motor_torque`` (N m) and, when
        compliant, ``contact_force_nut`` / ``contact_force_screw`` (total normal force, N;
        multi-roller adds ``contact_force_nut_<i>`` / ``contact_force_screw_<i>`` per roller);
        inputs ``speed_setpoint`` (rad/s) and ``axial_load`` (N). ``result.info`` holds the
        fidelity, integrator and wall time; with ``energy=True``, ``result.energy`` holds the
        work terms.

    Raises
    ------
    SimulationError
        If the integrator fails (the message names the time, the state and a remedy).

    Examples
    --------
    >>> from prsa_ctrl import load_plant, simulate, PID
    >>> r = simulate(load_plant(), load=[(0, 500), (0.05, 1500)], duration=0.1,
    ...              controller=PID(0.5, 20.0), fidelity="rigid")
    >>> float(r.outputs[0].min()) < 31.4159
    True
    """
    import control

    r = run(plant, setpoint=setpoint, load=load, duration=duration, controller=controller,
            feedforward_torque=feedforward_torque, fidelity=fidelity, discrete=discrete, dt=dt,
            settings=settings, energy=energy, seed=seed)
    result = control.TimeResponseData(
        r.time,
        r.outputs,
        r.states,
        r.inputs,
        output_labels=list(r.output_labels),
        state_labels=list(r.state_labels),
        input_labels=["speed_setpoint", "axial_load"],
        sysname=f"{plant.name}[{fidelity}]",
        plot_inputs=False,
    )
    result.info = r.info
    if energy:
        result.energy = r.energy
    return result


@dataclass(frozen=True, eq=False)
class SimRun:
    """Plain arrays of one simulation (what :func:`simulate` wraps as TimeResponseData).

    ``outputs`` has one row per ``output_labels`` entry, ``states`` one per ``state_labels``,
    ``inputs`` the setpoint (rad/s) and load (N) rows.
    """

    time: NDArray[np.float64]
    outputs: NDArray[np.float64]
    states: NDArray[np.float64]
    inputs: NDArray[np.float64]
    output_labels: tuple[str, ...]
    state_labels: tuple[str, ...]
    info: dict
    energy: dict | None = None

    def output(self, name: str) -> NDArray[np.float64]:
        return self.outputs[self.output_labels.index(name)]


def run(
    plant: Plant,
    *,
    setpoint: Profile = 31.4159,
    load: Profile = 500.0,
    duration: float = 0.6,
    controller: PID | None = None,
    feedforward_torque: float = 0.0,
    fidelity: str = "compliant",
    discrete: bool = False,
    dt: float = 1e-4,
    settings: SimSettings | None = None,
    energy: bool = False,
    seed: int = 0,
) -> SimRun:
    """:func:`simulate` without python-control: the same run, returned as plain arrays."""
    settings = settings or SimSettings()
    if not (isinstance(duration, (int, float)) and math.isfinite(duration) and duration > 0):
        raise ValueError(f"duration = {duration!r}; expected a finite time > 0 s")
    if not (isinstance(dt, (int, float)) and math.isfinite(dt) and 0 < dt <= duration):
        raise ValueError(f"dt = {dt!r}; expected 0 < dt <= duration ({duration} s)")
    if not math.isfinite(feedforward_torque):
        raise ValueError(f"feedforward_torque = {feedforward_torque!r}; expected a finite torque in N m")
    sp = _normalise_profile(setpoint, duration, "setpoint", "rad/s")
    ld = _normalise_profile(load, duration, "load", "N")
    model = plant_model(plant, fidelity, seed)
    built = _build(model, energy)
    started = time.perf_counter()

    op, integral0 = _initial_speed(plant, fidelity, sp[0][1], ld[0][1], controller, feedforward_torque, seed)
    gains = controller.params if controller is not None else [0.0, 0.0, 0.0, 1e-3]
    ff = feedforward_torque + (0.0 if controller is not None else op.torque)
    x0 = np.concatenate([op.x, [op.omega_nut, integral0, op.omega_nut], np.zeros(3 if energy else 0)])

    if discrete:
        t, xs = _run_sampled(built, settings, sp, ld, duration, gains, ff, x0)
    else:
        t, xs = _run_continuous(built, settings, sp, ld, duration, dt, gains, ff, x0)
    if not np.all(np.isfinite(xs)):
        bad = int(np.argmax(~np.all(np.isfinite(xs), axis=0)))
        raise _fail(ValueError("non-finite state"), t[max(bad - 1, 0)], t[bad], model, xs[:, max(bad - 1, 0)])

    nx = model.nx
    u_cmd = np.array([_value_at(ld, tk) for tk in t])
    refs = np.array([_value_at(sp, tk) for tk in t])
    y = np.asarray(model.h.map(len(t))(xs[:nx], np.vstack([np.zeros_like(t), u_cmd])))
    info = {
        "fidelity": fidelity,
        "discrete": bool(discrete),
        "integrator": settings.integrator,
        "rtol": settings.rtol,
        "atol": settings.atol,
        "wall_time_s": time.perf_counter() - started,
    }
    energy_terms = None
    if energy:
        stored = np.asarray(model.power.map(len(t))(xs[:nx], np.vstack([np.zeros_like(t), u_cmd])))[0]
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
                0.0, float(t[-1]), model, xs[: nx + 3, -1], what="untrustworthy integration",
                remedy=f"tighten rtol/atol (now {settings.rtol:g}/{settings.atol:g})",
            )
    return SimRun(t, y, xs[: nx + 3], np.vstack([refs, u_cmd]), tuple(model.output_names),
                  tuple(model.state_names + _CTRL_STATES), info, energy_terms)




def _segments(sp, ld, duration: float) -> list[float]:
    return sorted({0.0, duration, *[t for t, _ in sp], *[t for t, _ in ld]})


def _over_budget(settings: SimSettings, started: float, t: float, model: PlantModel, x) -> None:
    elapsed = time.perf_counter() - started
    if elapsed > settings.max_wall_s:
        raise _fail(
            TimeoutError(f"wall-time budget max_wall_s = {settings.max_wall_s:g} s used up after {elapsed:.1f} s"),
            t, t, model, x,
        )


def _chunks(bounds: list[float]) -> list[tuple[float, float]]:
    """Integration pieces: every input discontinuity starts a piece (a restart), and long
    segments are cut into pieces of at most ``CHUNK_S``."""
    out = []
    for t0, t1 in zip(bounds[:-1], bounds[1:]):
        n = max(1, math.ceil((t1 - t0) / CHUNK_S - 1e-9))
        edges = np.linspace(t0, t1, n + 1)
        out += [(float(a), float(b)) for a, b in zip(edges[:-1], edges[1:])]
    return out


def _run_continuous(built, settings, sp, ld, duration, dt, gains, ff, x0):
    scale = built.scale
    z = x0 / scale
    times = [np.array([0.0])]
    states = [x0[:, None]]
    started = time.perf_counter()
    for t0, t1 in _chunks(_segments(sp, ld, duration)):
        _over_budget(settings, started, t0, built.model, z * scale)
        n_out = max(1, int(round((t1 - t0) / dt)))
        integ = _continuous_integrator(built, settings, n_out)
        par = [_value_at(sp, t0), _value_at(ld, t0), *gains, ff, t1 - t0]
        try:
            zf = np.asarray(integ(x0=z, p=par)["xf"])
        except RuntimeError as exc:
            raise _fail(exc, t0, t1, built.model, z * scale) from None
        times.append(t0 + (t1 - t0) * np.arange(1, n_out + 1) / n_out)
        states.append(zf * scale[:, None])
        z = zf[:, -1]
    return np.concatenate(times), np.hstack(states)


def _sample_integrator(built: _Built, settings: SimSettings) -> ca.Function:
    """Plant-only integrator over one sample with the command held (controller states frozen):
    ``(x0 = scaled state, p = [torque command N m, load N, sample time s]) -> xf``."""
    key = (settings, "sample")
    if key not in built.sampled:
        model, scale = built.model, built.scale
        nx = model.nx
        zp = ca.SX.sym("z", len(scale))
        pp = ca.SX.sym("p", 3)
        rates = _plant_rates(model, (zp * scale)[:nx], pp[0], pp[1], built.energy)
        ode = pp[2] * ca.vertcat(rates[:nx], ca.DM.zeros(3), rates[nx:]) / scale
        built.sampled[key] = ca.integrator("sample", settings.integrator, {"x": zp, "p": pp, "ode": ode}, 0.0, 1.0,
                                           _opts(settings))
    return built.sampled[key]


def _sampled_step(built: _Built, settings: SimSettings) -> ca.Function:
    """One controller sample: update the PID from the quantised encoder, hold the previous
    command over the sample (one-sample computation delay) and integrate the plant."""
    if settings in built.sampled:
        return built.sampled[settings]
    model, scale = built.model, built.scale
    p = model.plant
    nx, nz = model.nx, len(scale)
    ts = p.sample_time_s
    q = 2.0 * math.pi / p.encoder_counts
    sample = _sample_integrator(built, settings)
    # Controller memory: previous quantised angle, filtered derivative, pending command.
    z = ca.SX.sym("z", nz)
    mem = ca.SX.sym("m", 3)
    par = ca.SX.sym("p", _NP)
    x = z * scale
    gains = par[2:6]
    theta_q = ca.floor(x[model.index("theta_nut")] / q) * q
    w_meas = (theta_q - mem[0]) / ts
    alpha = math.exp(-ts / p.speed_filter_s)
    w_f_old = x[nx]
    w_f = alpha * w_f_old + (1 - alpha) * w_meas
    beta = ca.exp(-ts / gains[3])
    deriv = beta * mem[1] + (1 - beta) * (w_f - w_f_old) / ts
    u, _, dintegral = pid_law(par[0] - w_f, x[nx + 1], deriv, gains, par[6], p.torque_limit)
    integral = x[nx + 1] + ts * dintegral
    zf = sample(x0=z, p=ca.vertcat(mem[2], par[1], ts))["xf"]
    xf = zf * scale
    xf = ca.vertcat(xf[:nx], w_f, integral, w_f, xf[nx + 3 :])
    step = ca.Function("step", [ca.vertcat(z, mem), par], [ca.vertcat(xf / scale, theta_q, deriv, u)])
    built.sampled[settings] = step
    return step


def _accumulated(built: _Built, settings: SimSettings, step: ca.Function, n: int) -> ca.Function:
    """``n`` samples of ``step`` chained (mapaccum), built once per length."""
    key = (settings, "accum", n)
    if key not in built.sampled:
        built.sampled[key] = step.mapaccum(n)
    return built.sampled[key]


def _run_sampled(built, settings, sp, ld, duration, gains, ff, x0):
    model = built.model
    p = model.plant
    ts = p.sample_time_s
    n_total = int(round(duration / ts))
    if n_total < 1:
        raise ValueError(f"duration {duration} s is shorter than the sample time {ts} s")
    step = _sampled_step(built, settings)
    scale = built.scale
    q = 2.0 * math.pi / p.encoder_counts
    theta0 = x0[model.index("theta_nut")]
    # Steady start: the previous sample saw the same speed; the held command is the current one.
    w0 = x0[model.index("omega_nut")]
    mem0 = [math.floor((theta0 - w0 * ts) / q) * q, 0.0, x0[model.index("tau_motor")]]
    # Discontinuities are applied at the nearest sample boundary.
    ks = sorted({0, n_total, *[min(n_total, int(round(t / ts))) for t, _ in sp + ld]})
    zm = np.concatenate([x0 / scale, mem0])
    out = [x0[:, None]]
    per_chunk = max(1, int(round(CHUNK_S / ts)))
    ks = sorted(set(ks) | set(range(0, n_total, per_chunk)))
    started = time.perf_counter()
    for k0, k1 in zip(ks[:-1], ks[1:]):
        if k1 == k0:
            continue
        _over_budget(settings, started, k0 * ts, model, zm[: len(scale)] * scale)
        t0 = k0 * ts
        par = [_value_at(sp, t0), _value_at(ld, t0), *gains, ff, ts]
        try:
            traj = np.asarray(_accumulated(built, settings, step, k1 - k0)(zm, ca.repmat(ca.DM(par), 1, k1 - k0)))
        except RuntimeError as exc:
            raise _fail(exc, t0, k1 * ts, model, zm[: len(scale)] * scale) from None
        out.append(traj[: len(scale)] * scale[:, None])
        zm = traj[:, -1]
    return ts * np.arange(n_total + 1), np.hstack(out)


def energy_balance(result) -> dict[str, float]:
    """Energy audit of a simulation run with ``energy=True``.

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
