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

import math
import time
import weakref
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any, Callable, Sequence

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from ..drive.pid import PID, pid_law
from ..plant.equilibrium import operating_point
from ..errors import SimulationError
from ..drive.measurement import PositionLoop, SpeedMeasurement, measurement_for
from ..plant.model import PlantModel, plant_model
from ..options import SETPOINT_RAD_S
from ..plant.plantfile import Plant

if TYPE_CHECKING:  # annotations only: python-control is imported where it is used
    import control

    from ..drive.estimator import KFDesign
    from ..drive.filters import LoopFilter
    from ..drive.motion import MotionProfile

__all__ = ["simulate", "run", "SimRun", "Profile", "PiecewiseLinear", "SimSettings", "energy_balance",
           "INTEGRATORS", "MAX_OUTPUT_POINTS", "INPUT_LABELS", "fixed_step_error", "fast_settings", "jit_cache_dir",
           "RADAU_STAGES"]

INTEGRATORS = ("cvodes", "idas", "radau")
#: Stages of the fixed-step ``"radau"`` integrator (Radau IIA: 1 = implicit Euler, order 1;
#: 2 = order 3; 3 = order 5; all L-stable and stiffly accurate).
RADAU_STAGES = (1, 2, 3)

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
# Parameter vector of the continuous closed loop: setpoint (rad/s) and load (N) at the segment
# start, kp, ki, kd, tf, feed-forward (N m), segment duration (s), setpoint and load slopes (per s).
_NP = 10


@dataclass(frozen=True)
class PiecewiseLinear:
    """An input profile linear between its points, constant after the last one.

    Parameters
    ----------
    points : sequence of (time_s, value)
        The first at t = 0; times non-decreasing. Two points at the same time make a step
        there (from the first value to the second), so ramps and steps mix:
        ``[(0, 500), (0.1, 500), (0.1, 1500), (0.3, 1000)]`` holds 500 N, steps to 1500 N at
        0.1 s and ramps down to 1000 N at 0.3 s.

    Examples
    --------
    >>> ramp = PiecewiseLinear([(0.0, 500.0), (0.1, 1500.0)])
    >>> ramp.points[-1]
    (0.1, 1500.0)
    """

    points: tuple[tuple[float, float], ...]

    def __post_init__(self) -> None:
        try:
            pts = tuple((float(t), float(v)) for t, v in self.points)
        except (TypeError, ValueError):
            raise ValueError(f"points = {self.points!r}; expected a list of (time_s, value) pairs") from None
        object.__setattr__(self, "points", pts)

    @classmethod
    def from_csv(cls, path: "str | Path", column: str = "axial_load_n", *, max_rows: int = 1_000_000) -> "PiecewiseLinear":
        """A measured trace from a CSV file with a header: ``time_s`` and ``column``.

        Times must start at 0 and increase strictly; values must be finite. The trace is used
        as a piecewise-linear profile (at most one point per controller sample in a sampled
        run: resample faster traces).

        Parameters
        ----------
        path : str or Path
        column : str
            Header of the value column (default ``axial_load_n``, N).
        max_rows : int
            Largest number of rows read.

        Raises
        ------
        ValueError
            One line naming the file, the row (1 = first data row) and the column.
        """
        import csv

        p = Path(path)
        try:
            with p.open(newline="") as fh:
                reader = csv.reader(fh)
                header = [h.strip() for h in next(reader, [])]
                if "time_s" not in header or column not in header:
                    raise ValueError(f"{p}: header {header}; expected columns 'time_s' and {column!r}")
                it, iv = header.index("time_s"), header.index(column)
                pts: list[tuple[float, float]] = []
                for row_no, row in enumerate(reader, start=1):
                    if not row or all(not c.strip() for c in row):
                        continue
                    if row_no > max_rows:
                        raise ValueError(f"{p}: more than {max_rows} rows; expected a shorter trace")
                    try:
                        t, v = float(row[it]), float(row[iv])
                    except (IndexError, ValueError):
                        raise ValueError(f"{p}: row {row_no}: {row!r}; expected numbers in 'time_s' and {column!r}") \
                            from None
                    if not (math.isfinite(t) and math.isfinite(v)):
                        raise ValueError(f"{p}: row {row_no}: time_s = {t!r}, {column} = {v!r}; expected finite numbers")
                    if pts and t <= pts[-1][0]:
                        raise ValueError(f"{p}: row {row_no}: time_s = {t!r} after {pts[-1][0]!r}; expected increasing times")
                    pts.append((t, v))
        except OSError as exc:
            raise ValueError(f"{p}: cannot read ({exc.strerror}); expected a readable CSV file") from None
        except UnicodeDecodeError:
            raise ValueError(f"{p}: not a text file; expected a CSV file") from None
        if len(pts) < 2:
            raise ValueError(f"{p}: {len(pts)} data rows; expected at least 2")
        if pts[0][0] != 0.0:
            raise ValueError(f"{p}: row 1: time_s = {pts[0][0]!r}; expected the trace to start at 0")
        return cls(tuple(pts))


Profile = float | Sequence[tuple[float, float]] | PiecewiseLinear


@dataclass(frozen=True)
class SimSettings:
    """Integrator settings. Tolerances apply to states scaled to order one.

    Parameters
    ----------
    integrator : {"cvodes", "idas", "radau"}
        ``"cvodes"`` (default, the reference) and ``"idas"`` are SUNDIALS' adaptive implicit
        integrators. ``"radau"`` is a fixed-step, linearly implicit Radau IIA integrator written
        in CasADi SX (``substeps`` steps of ``stages`` stages per controller sample, each with
        ``newton`` simplified Newton iterations on the exact Jacobian at the step start): one
        sample is a plain expression, so a whole chunk of samples runs as one ``mapaccum``'d
        function without integrator restarts. Its error is not controlled by ``rtol``/``atol``
        (they are unused); it is measured against a tight CVODES reference
        (:func:`fixed_step_error`) and the fast path is only chosen where that error is inside
        the scene's accuracy (see ``README``). In continuous mode it takes ``substeps`` steps per
        output interval.
    rtol, atol : float
        Relative and absolute tolerances (adaptive integrators).
    max_steps : int
        Step budget per output interval; exceeding it raises :class:`SimulationError`.
    max_wall_s : float
        Wall-time budget of one run, s, checked between integration chunks (at most
        ``CHUNK_S`` of simulated time each); exceeding it raises :class:`SimulationError`.
    energy_tol : float
        With ``energy=True`` the run audits itself: an energy-balance residual above this
        (relative, see :func:`energy_balance`) means the integration is not trustworthy and
        raises :class:`SimulationError`; ``inf`` switches the audit off.
    clock : callable
        Returns the time in s that the budget is measured with (default
        ``time.perf_counter``; tests inject a fake clock). Not part of the settings' identity.
    substeps : int
        ``"radau"`` only: fixed steps per controller sample (1..64).
    stages : {1, 2, 3}
        ``"radau"`` only: Radau IIA stages.
    newton : int
        ``"radau"`` only: simplified Newton iterations per step (1..4), a fixed number (no
        convergence test: the error is measured instead, and a diverging step ends in a
        non-finite state, which the run reports as a :class:`SimulationError`).
    jit : bool
        ``"cvodes"``/``"idas"``: evaluate the model's right-hand side and its Jacobian as C code
        compiled once per model into a per-user cache (``$PRSA_CTRL_CACHE``, else
        ``$XDG_CACHE_HOME/prsa-ctrl`` or ``~/.cache/prsa-ctrl``; keyed by the hash of the
        generated code). ``"radau"``: compile the whole per-sample law of the sampled loop
        (plant steps, measurement, PID) the same way, once per law (a few seconds of ``cc -O1``
        the first time; all members of a parametric family share it, see
        :func:`prsa_ctrl.plant.model.register_member`). Same equations, same tolerances; without a C
        compiler the run falls back to CasADi's interpreter with a warning.
    """

    integrator: str = "cvodes"
    rtol: float = 1e-8
    atol: float = 1e-8
    max_steps: int = 20000
    max_wall_s: float = 120.0
    energy_tol: float = 1e-4
    clock: Callable[[], float] = field(default=time.perf_counter, compare=False, hash=False, repr=False)
    substeps: int = 4
    stages: int = 2
    newton: int = 1
    jit: bool = False

    def __post_init__(self) -> None:
        if self.integrator not in INTEGRATORS:
            raise ValueError(f"integrator = {self.integrator!r}; expected one of {', '.join(INTEGRATORS)}")
        for name, lo, hi in (("substeps", 1, 64), ("newton", 1, 4)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
                raise ValueError(f"{name} = {v!r}; expected an integer in [{lo}, {hi}]")
        if isinstance(self.stages, bool) or self.stages not in RADAU_STAGES:
            raise ValueError(f"stages = {self.stages!r}; expected one of {', '.join(map(str, RADAU_STAGES))}")
        if not isinstance(self.jit, bool):
            raise ValueError(f"jit = {self.jit!r}; expected True or False")
        for name in ("rtol", "atol"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (0 < v < 1):
                raise ValueError(f"{name} = {v!r}; expected a tolerance in (0, 1)")
        if isinstance(self.max_steps, bool) or not isinstance(self.max_steps, (int, float)) \
                or not math.isfinite(self.max_steps) or not 10 <= self.max_steps <= 1e9:
            raise ValueError(f"max_steps = {self.max_steps!r}; expected an integer in [10, 1e9]")
        if isinstance(self.max_wall_s, bool) or not isinstance(self.max_wall_s, (int, float)) \
                or not (self.max_wall_s > 0 and math.isfinite(self.max_wall_s)):
            raise ValueError(f"max_wall_s = {self.max_wall_s!r}; expected a positive time in s")
        if isinstance(self.energy_tol, bool) or not isinstance(self.energy_tol, (int, float)) \
                or not self.energy_tol > 0:
            raise ValueError(f"energy_tol = {self.energy_tol!r}; expected a relative tolerance > 0 (inf: no audit)")
        if not callable(self.clock):
            raise ValueError(f"clock = {self.clock!r}; expected a callable returning seconds")


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
        "v_roller": p.lead_per_rad * w,  # the rollers travel axially with the screw
        "delta_screw": defl,
        "v_screw": p.lead_per_rad * w,
        "tau_motor": p.torque_limit,
    }
    # A model may declare the typical magnitudes of states it adds (e.g. friction states).
    scale.update(getattr(model, "state_scales", None) or {})
    return np.array([scale[n] for n in model.state_names])


@dataclass(eq=False)
class _Built:
    """Closed-loop functions of one plant model (built once)."""

    model: PlantModel
    scale: NDArray[np.float64]  # plant states (+ continuous controller states) (+ energy)
    plant_scale: NDArray[np.float64]  # plant states (+ energy): the sampled loop's plant part
    energy: bool
    rhs: ca.Function  # continuous loop: (z, p, tau) -> dz/dtau in scaled, duration-normalised time
    continuous: dict = field(default_factory=dict)  # (settings, n_out) -> integrator
    sampled: dict = field(default_factory=dict)  # (settings, measurement key, ...) -> functions
    # Member of a parametric family (model.register_member): the family's parameter values,
    # carried through the sampled loop as constant plant states between the physical states and
    # the energy terms (scale 1, zero rate), so that one law serves every member.
    theta0: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))


_BUILT: "weakref.WeakKeyDictionary[PlantModel, dict[bool, _Built]]" = weakref.WeakKeyDictionary()


def _plant_rates(model: PlantModel, x, u, load, energy: bool, theta=None):
    """Plant state rates, followed by the motor, load and dissipated powers when ``energy``
    (``theta``: the parameters of a :class:`~prsa_ctrl.plant.model.ParametricModel`)."""
    args = (x, ca.vertcat(u, load)) + (() if theta is None else (theta,))
    if not energy:
        return model.f(*args)
    return ca.vertcat(model.f(*args), model.power(*args)[1:])


class _Bounded(dict):
    """A dict that forgets its oldest entries beyond ``cap`` (functions shared by a family)."""

    cap = 64

    def __setitem__(self, key, value) -> None:
        super().__setitem__(key, value)
        while len(self) > self.cap:
            del self[next(iter(self))]


def _member_built(model: PlantModel, energy: bool) -> _Built:
    """A family member's functions: the family's (built once, shared) with the member's
    parameters as the initial values of the constant states (see ``_Built.theta0``)."""
    fam = model.family
    key = ("built", energy)
    if key not in fam.cache:
        x_scale = _state_scale(fam)
        e_scale = np.ones(3 if energy else 0)
        plant_scale = np.concatenate([x_scale, np.ones(fam.n_theta), e_scale])
        fam.cache[key] = _Built(fam, plant_scale, plant_scale, energy, None, _Bounded(), _Bounded())
    b = fam.cache[key]
    return _Built(fam, b.scale, b.plant_scale, energy, None, b.continuous, b.sampled,
                  np.asarray(model.theta, dtype=float))


def _build(model: PlantModel, energy: bool, shared: bool = False) -> _Built:
    """The closed-loop functions of ``model``; with ``shared`` (sampled fixed-step runs) a
    member of a parametric family gets its family's."""
    cache = _BUILT.setdefault(model, {})
    if shared and model.family is not None:
        key = ("member", energy)
        if key not in cache:
            cache[key] = _member_built(model, energy)
        return cache[key]
    if energy in cache:
        return cache[energy]
    p = model.plant
    nx = model.nx
    ctrl_scale = [100.0, p.torque_limit, 100.0]  # rad/s, N m, rad/s
    e_scale = np.ones(3 if energy else 0)
    x_scale = _state_scale(model)
    scale = np.concatenate([x_scale, ctrl_scale, e_scale])
    z = ca.SX.sym("z", len(scale))
    par = ca.SX.sym("p", _NP)
    tau = ca.SX.sym("tau")  # segment time normalised to [0, 1]
    gains, tau_ff, duration = par[2:6], par[6], par[7]
    ref = par[0] + par[8] * duration * tau
    load = par[1] + par[9] * duration * tau
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
    built = _Built(model, scale, np.concatenate([x_scale, e_scale]), energy,
                   ca.Function("rhs", [z, par, tau], [rhs]))
    cache[energy] = built
    return built


def _opts(settings: SimSettings) -> dict:
    return {
        "abstol": settings.atol,
        "reltol": settings.rtol,
        "max_num_steps": int(settings.max_steps),
        "print_stats": False,
    }


# --- fixed-step Radau IIA (SimSettings(integrator="radau")) ------------------------------------

def _radau_tableau(stages: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Butcher matrix ``A`` and nodes ``c`` of the ``stages``-stage Radau IIA method (Hairer &
    Wanner, Solving ODEs II, Table IV.5.5); the last row of ``A`` is the weights (stiffly
    accurate), so the step's result is the last stage value."""
    if stages == 1:
        return np.array([[1.0]]), np.array([1.0])
    if stages == 2:
        return np.array([[5.0 / 12.0, -1.0 / 12.0], [3.0 / 4.0, 1.0 / 4.0]]), np.array([1.0 / 3.0, 1.0])
    r6 = math.sqrt(6.0)
    a = np.array([[(88.0 - 7.0 * r6) / 360.0, (296.0 - 169.0 * r6) / 1800.0, (-2.0 + 3.0 * r6) / 225.0],
                  [(296.0 + 169.0 * r6) / 1800.0, (88.0 + 7.0 * r6) / 360.0, (-2.0 - 3.0 * r6) / 225.0],
                  [(16.0 - r6) / 36.0, (16.0 + r6) / 36.0, 1.0 / 9.0]])
    return a, np.array([(4.0 - r6) / 10.0, (4.0 + r6) / 10.0, 1.0])


#: Sparse LU kernels by matrix sparsity (shared by every plant of one structure, so a plant
#: with other parameter values does not rebuild them).
_LU_KERNELS: dict[str, tuple[ca.Function, ca.Function]] = {}


def _lu_kernels(sp: ca.Sparsity) -> tuple[ca.Function, ca.Function]:
    """``factor(M) -> lu`` and ``solve(lu, b) -> M^-1 b`` for square matrices of sparsity ``sp``:
    Gaussian elimination in the given order (no pivoting) on the structural nonzeros only.

    Used on ``I - h (A kron J)`` of a dissipative plant, whose diagonal dominates the elimination;
    a vanishing pivot gives a non-finite state, which the run reports as a SimulationError (it
    never passes silently)."""
    key = sp.serialize()
    if key in _LU_KERNELS:
        return _LU_KERNELS[key]
    n = sp.size1()
    m = ca.SX.sym("m", sp)
    a = [[m[i, j] if sp.has_nz(i, j) else None for j in range(n)] for i in range(n)]
    lower: list[list] = [[None] * n for _ in range(n)]
    for k in range(n):
        if a[k][k] is None:
            raise ValueError(f"structurally zero pivot {k} in the Radau iteration matrix")
        for i in range(k + 1, n):
            if a[i][k] is None:
                continue
            lik = a[i][k] / a[k][k]
            lower[i][k] = lik
            for j in range(k + 1, n):
                if a[k][j] is not None:
                    a[i][j] = -lik * a[k][j] if a[i][j] is None else a[i][j] - lik * a[k][j]
    entries = [lower[i][k] for i in range(n) for k in range(i) if lower[i][k] is not None] + \
              [a[i][j] for i in range(n) for j in range(i, n) if a[i][j] is not None]
    lu = ca.vertcat(*entries)
    factor = ca.Function("radau_lu_factor", [m], [lu])
    lus = ca.SX.sym("lu", lu.numel())
    b = ca.SX.sym("b", n)
    it = iter(range(lu.numel()))
    lo = [[next(it) if lower[i][k] is not None else None for k in range(i)] for i in range(n)]
    up = [[next(it) if a[i][j] is not None else None for j in range(i, n)] for i in range(n)]
    y: list = []
    for i in range(n):
        yi = b[i]
        for k in range(i):
            if lo[i][k] is not None:
                yi = yi - lus[lo[i][k]] * y[k]
        y.append(yi)
    x: list = [None] * n
    for i in reversed(range(n)):
        xi = y[i]
        for j in range(i + 1, n):
            if up[i][j - i] is not None:
                xi = xi - lus[up[i][j - i]] * x[j]
        x[i] = xi / lus[up[i][0]]
    solve = ca.Function("radau_lu_solve", [lus, b], [ca.vertcat(*x)])
    _LU_KERNELS[key] = (factor, solve)
    return factor, solve


def _radau_step(f: ca.Function, nz: int, npar: int, settings: SimSettings, span: float) -> ca.Function:
    """``(x0, p, tau0) -> x`` after ``span`` of normalised time from ``tau0``: ``settings.substeps``
    Radau IIA steps of ``f(z, p, tau) -> dz/dtau``, each solving its stage equations
    ``Z_i = x + h sum_j a_ij f(Z_j)`` with ``settings.newton`` simplified Newton iterations
    from ``Z_i = x`` on the iteration matrix ``I - h (A kron J(x))`` (exact Jacobian at the
    step start, factorised once per step). One Newton iteration makes it a linearly implicit
    (Rosenbrock-type) Radau method: still L-stable, the 25.8 kHz contact mode and the stiff
    traction creep are damped, not resolved. A plain SX expression: no restarts, no
    convergence loop, a fixed cost per step."""
    a_mat, c = _radau_tableau(settings.stages)
    s = settings.stages
    z = ca.SX.sym("z", nz)
    p = ca.SX.sym("p", npar)
    tau = ca.SX.sym("tau")
    jac = ca.Function("radau_dfdz", [z, p, tau], [ca.jacobian(f(z, p, tau), z)])
    h = span / settings.substeps
    j_sym = ca.SX.sym("j", jac.sparsity_out(0))
    iter_mat = ca.Function("radau_iteration_matrix", [j_sym],
                           [ca.SX.eye(s * nz) - h * ca.kron(ca.SX(ca.DM(a_mat)), j_sym)])
    factor, solve = _lu_kernels(iter_mat.sparsity_out(0))
    x0 = ca.SX.sym("x0", nz)
    tau0 = ca.SX.sym("tau0")
    x = x0
    for k in range(settings.substeps):
        t_k = tau0 + k * h
        lu = factor(iter_mat(jac(x, p, t_k)))
        stages = [x] * s
        for _ in range(settings.newton):
            rates = [f(stages[i], p, t_k + c[i] * h) for i in range(s)]
            g = ca.vertcat(*[stages[i] - x - h * sum(a_mat[i, j] * rates[j] for j in range(s)) for i in range(s)])
            dz = solve(lu, g)
            stages = [stages[i] - dz[i * nz:(i + 1) * nz] for i in range(s)]
        x = stages[-1]
    return ca.Function("radau_step", [x0, p, tau0], [x], ["x0", "p", "tau0"], ["xf"])


#: Compiled right-hand sides loaded in this process, by code hash (see ``SimSettings.jit``).
_COMPILED: dict[str, ca.Function] = {}


def jit_cache_dir() -> Path:
    """Directory of the compiled right-hand sides (``SimSettings(jit=True)``):
    ``$PRSA_CTRL_CACHE/jit``, else ``$XDG_CACHE_HOME/prsa-ctrl/jit`` or ``~/.cache/prsa-ctrl/jit``."""
    import os

    root = os.environ.get("PRSA_CTRL_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "prsa-ctrl")
    return Path(root) / "jit"


def _compiled(fun: ca.Function, jacobian: bool = True, flags: tuple[str, ...] = ("-O2",)) -> ca.Function | None:
    """``fun`` (and its Jacobian) as C code compiled once into :func:`jit_cache_dir` (keyed by the
    hash of the code, the CasADi version, the compiler and ``flags``) and loaded as an external function;
    ``None`` with a warning when no C compiler is found or compiling fails (the caller then
    uses CasADi's interpreter: same equations, slower)."""
    import hashlib
    import os
    import shutil
    import subprocess
    import tempfile
    import warnings

    cg = ca.CodeGenerator(f"{fun.name()}.c", {"with_header": False})
    cg.add(fun)
    if jacobian:
        cg.add(fun.jacobian())
    code = cg.dump()
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    key = hashlib.sha256("\n".join([code, ca.__version__, str(cc), *flags]).encode()).hexdigest()[:24]
    if key in _COMPILED:
        return _COMPILED[key]
    if cc is None:
        warnings.warn("SimSettings(jit=True): no C compiler found (set CC); using CasADi's interpreter", stacklevel=3)
        return None
    folder = jit_cache_dir()
    lib = folder / f"{fun.name()}_{key}.so"
    if not lib.exists():
        try:
            folder.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryDirectory(dir=folder) as tmp:
                src, out = Path(tmp) / "f.c", Path(tmp) / "f.so"
                src.write_text(code)
                res = subprocess.run([cc, *flags, "-shared", "-fPIC", str(src), "-o", str(out), "-lm"],
                                     capture_output=True, text=True, timeout=600)
                if res.returncode != 0:
                    raise OSError(res.stderr.strip().splitlines()[-1] if res.stderr.strip() else f"exit {res.returncode}")
                os.replace(out, lib)  # atomic: a concurrent worker never loads a half-written library
        except (OSError, subprocess.SubprocessError) as exc:
            warnings.warn(f"SimSettings(jit=True): compiling with {cc} into {folder} failed ({exc}); using CasADi's "
                          "interpreter", stacklevel=3)
            return None
    ext = ca.external(fun.name(), str(lib))
    _COMPILED[key] = ext
    return ext


def _ode_dae(z: ca.SX, par: ca.SX, tau: ca.SX, ode: ca.SX, settings: SimSettings) -> dict:
    """The integrator's ODE, as compiled code when ``settings.jit`` (and a compiler works)."""
    ext = _compiled(ca.Function("prsa_ode", [z, par, tau], [ode])) if settings.jit else None
    if ext is None:
        return {"x": z, "p": par, "t": tau, "ode": ode}
    zm, pm, tm = ca.MX.sym("z", z.numel()), ca.MX.sym("p", par.numel()), ca.MX.sym("tau")
    return {"x": zm, "p": pm, "t": tm, "ode": ext(zm, pm, tm)}


def _continuous_integrator(built: _Built, settings: SimSettings, n_out: int) -> ca.Function:
    key = (settings, n_out)
    if key not in built.continuous:
        z = ca.SX.sym("z", len(built.scale))
        par = ca.SX.sym("p", _NP)
        tau = ca.SX.sym("tau")
        if settings.integrator == "radau":
            # substeps fixed steps per output interval, all intervals chained (mapaccum)
            f = ca.Function("rhs_scaled", [z, par, tau], [built.rhs(z, par, tau)])
            step = _radau_step(f, len(built.scale), _NP, settings, 1.0 / n_out)
            chain = step.mapaccum("radau_chain", n_out, [0], [0])
            x0 = ca.MX.sym("x0", len(built.scale))
            pm = ca.MX.sym("p", _NP)
            taus = ca.DM(np.arange(n_out) / n_out).T
            xf = chain(x0, ca.repmat(pm, 1, n_out), taus)
            built.continuous[key] = ca.Function("segment", [x0, pm], [xf], ["x0", "p"], ["xf"])
        else:
            dae = _ode_dae(z, par, tau, built.rhs(z, par, tau), settings)
            grid = list(np.linspace(0.0, 1.0, n_out + 1)[1:])
            built.continuous[key] = ca.integrator("segment", settings.integrator, dae, 0.0, grid, _opts(settings))
    return built.continuous[key]


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


@dataclass(frozen=True)
class _Prof:
    """A normalised input profile: at each breakpoint ``t[i]`` the value becomes ``v[i]`` and
    then changes with slope ``s[i]`` (per s) until the next breakpoint. ``jump[i]`` says
    whether the value is discontinuous there (a step event)."""

    t: NDArray[np.float64]
    v: NDArray[np.float64]
    s: NDArray[np.float64]
    jump: NDArray[np.bool_]

    def at(self, t: NDArray[np.float64] | float) -> NDArray[np.float64]:
        """Value at time(s) ``t`` (after any step at exactly ``t``)."""
        tt = np.asarray(t, dtype=float)
        i = np.clip(np.searchsorted(self.t, tt + 1e-12, side="right") - 1, 0, len(self.t) - 1)
        return self.v[i] + self.s[i] * np.maximum(tt - self.t[i], 0.0)

    def slope_at(self, t: NDArray[np.float64] | float) -> NDArray[np.float64]:
        tt = np.asarray(t, dtype=float)
        i = np.clip(np.searchsorted(self.t, tt + 1e-12, side="right") - 1, 0, len(self.t) - 1)
        return self.s[i]

    @property
    def breaks(self) -> NDArray[np.float64]:
        """Breakpoints after t = 0 (steps and kinks)."""
        return self.t[1:]


def _normalise_profile(profile: Profile, duration: float, what: str, unit: str) -> _Prof:
    linear = isinstance(profile, PiecewiseLinear)
    if _is_number(profile):
        pts = [(0.0, float(profile))]  # type: ignore[arg-type]
    else:
        try:
            pts = list(profile.points) if linear else [(float(t), float(v)) for t, v in profile]  # type: ignore
        except (TypeError, ValueError):
            raise ValueError(
                f"{what} = {profile!r}; expected a number ({unit}), a list of (time_s, value) steps or a "
                "PiecewiseLinear profile"
            ) from None
    if not pts:
        raise ValueError(f"{what} = {profile!r}; expected at least one value")
    for t, v in pts:
        if not (math.isfinite(t) and math.isfinite(v)):
            raise ValueError(f"{what} point ({t}, {v}) is not finite; expected finite time (s) and value ({unit})")
    if pts[0][0] != 0.0:
        raise ValueError(f"{what} starts at t = {pts[0][0]} s; expected the first point at t = 0")
    times = [t for t, _ in pts]
    if linear:
        bad = any(b < a for a, b in zip(times, times[1:])) or any(
            a == b == c for a, b, c in zip(times, times[1:], times[2:]))
        if bad or times[-1] >= duration:
            raise ValueError(f"{what} times {times} must not decrease (two equal times make a step, three are "
                             f"ambiguous) and must stay below the duration {duration} s")
    elif any(b <= a for a, b in zip(times, times[1:])) or times[-1] >= duration:
        raise ValueError(f"{what} times {times} must increase strictly and stay below the duration {duration} s")
    # Breakpoints: the first and last value given at each distinct time.
    first: dict[float, float] = {}
    last: dict[float, float] = {}
    for t, v in pts:
        first.setdefault(t, v)
        last[t] = v
    bt = sorted(first)
    bv = [last[t] for t in bt]
    if linear:
        bs = [(first[t1] - bv[i]) / (t1 - bt[i]) for i, t1 in enumerate(bt[1:])] + [0.0]
        bj = [False] + [first[t] != last[t] for t in bt[1:]]
    else:
        bs = [0.0] * len(bt)
        bj = [False] + [True] * (len(bt) - 1)
    return _Prof(np.array(bt), np.array(bv), np.array(bs), np.array(bj, dtype=bool))


def _values_at(prof: _Prof, t: NDArray[np.float64] | float) -> NDArray[np.float64]:
    """Value of a profile at time(s) ``t``."""
    return prof.at(t)


def _value_at(prof: _Prof, t: float) -> float:
    return float(prof.at(t))


def _initial_state(plant: Plant, fidelity: str, ref: float, load: float, pid: PID | None, tau_ff: float,
                   seed: int, observer_ff: bool):
    """Closed-loop steady state before the first input change.

    Returns the operating point and the PID integral (N m). With an integral action the speed
    sits on the setpoint and the integral holds the rest of the torque; a P-only controller
    settles where ``kp (ref - w) + tau_ff (+ kff * load torque estimate) = torque(w)``.
    ``observer_ff``: the load-torque estimate (equal to the steady torque) is fed forward
    with ``pid.kff``.
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

    from scipy.optimize import brentq  # only P-only controllers need it (and it costs 0.25 s to import)

    span = plant.torque_limit / pid.kp
    try:
        w0 = brentq(residual, ref - span, ref + span, xtol=1e-12, rtol=1e-14, maxiter=200)
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
    import control

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


def _check_number(name: str, v: Any, lo: float, hi: float, unit: str, lo_open: bool = True) -> float:
    ok = _is_number(v) and math.isfinite(float(v)) and (v > lo if lo_open else v >= lo) and v <= hi
    if not ok:
        lo_s = f"> {lo:g}" if lo_open else f">= {lo:g}"
        raise ValueError(f"{name} = {v!r}; expected a finite number {lo_s} and <= {hi:g} {unit}".rstrip())
    return float(v)


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
    duration = _check_number("duration", duration, 0.0, 1e6, "s")
    feedforward_torque = _check_number("feedforward_torque", feedforward_torque, -1e6, 1e6, "N m", lo_open=False)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed = {seed!r}; expected an integer >= 0")
    if position is not None or motion is not None:
        from ..drive.motion import MotionProfile

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
        from ..drive.filters import loop_filters

        filters = loop_filters(filters, plant.sample_time_s if discrete else None)
        if filters and not discrete:
            raise ValueError(f"filters = {filters!r} with discrete = False; expected discrete=True (the filters run in "
                             "the drive's sampled loop)")
    else:
        filters = ()
    if discrete:
        ts = plant.sample_time_s
        n_points = math.floor(duration / ts + 1e-9) + 1
        if n_points < 2:
            raise ValueError(f"duration = {duration!r} s is shorter than the sample time {ts:g} s")
        size_msg = f"duration {duration:g} s at the sample time {ts:g} s"
    else:
        if not (_is_number(dt) and math.isfinite(dt) and 0 < dt <= duration):
            raise ValueError(f"dt = {dt!r}; expected 0 < dt <= duration ({duration} s)")
        n_points = int(duration / dt) + 1
        size_msg = f"duration {duration:g} s at dt = {dt:g} s"
    if n_points > MAX_OUTPUT_POINTS:
        raise ValueError(f"{size_msg} gives {n_points:.3g} output points; expected at most "
                         f"{MAX_OUTPUT_POINTS:.0e} (shorten the run or coarsen dt)")
    sp = _normalise_profile(setpoint, duration, "setpoint", "rad/s")
    ld = _normalise_profile(load, duration, "load", "N")
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
    built = _build(model, energy, shared=discrete and position is None and settings.integrator == "radau")
    budget = _Budget(settings)

    op, integral0 = _initial_state(plant, fidelity, float(sp.v[0]), float(ld.v[0]), controller, feedforward_torque, seed,
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
        refs, loads = _values_at(sp, t), _values_at(ld, t)
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
        integ = _continuous_integrator(built, settings, n_out)
        par = [_value_at(sp, t0), _value_at(ld, t0), *gains, ff, t1 - t0, float(sp.slope_at(t0)),
               float(ld.slope_at(t0))]
        try:
            zf = np.asarray(integ(x0=z, p=par)["xf"])
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


def _sample_integrator(built: _Built, settings: SimSettings) -> ca.Function:
    """Plant-only integrator with the command held: ``(x0 = scaled plant state (+ energy),
    p = [torque N m, load N at the start, load slope N/s, interval s]) -> xf``."""
    key = (settings, "plant")
    if key not in built.sampled:
        model, scale = built.model, built.plant_scale
        nx = model.nx
        n_theta = getattr(model, "n_theta", 0)  # parameters of a family: constant states after x
        zp = ca.SX.sym("z", len(scale))
        pp = ca.SX.sym("p", 4)
        tau = ca.SX.sym("tau")
        x_all = zp * scale
        rates = _plant_rates(model, x_all[:nx], pp[0], pp[1] + pp[2] * pp[3] * tau, built.energy,
                             x_all[nx:nx + n_theta] if n_theta else None)
        if n_theta:
            rates = ca.vertcat(rates[:nx], ca.SX.zeros(n_theta), rates[nx:])
        ode = pp[3] * rates / scale
        if settings.integrator == "radau":
            step = _radau_step(ca.Function("plant_scaled", [zp, pp, tau], [ode]), len(scale), 4, settings, 1.0)
            x0 = ca.SX.sym("x0", len(scale))
            built.sampled[key] = ca.Function("sample", [x0, pp], [step(x0, pp, 0.0)], ["x0", "p"], ["xf"])
        else:
            built.sampled[key] = ca.integrator("sample", settings.integrator, _ode_dae(zp, pp, tau, ode, settings),
                                               0.0, 1.0, _opts(settings))
    return built.sampled[key]


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


def _sample_law(built: _Built, settings: SimSettings, meas: SpeedMeasurement, split: bool,
                outer: "PositionLoop | None" = None, places: tuple[str, ...] = ()) -> ca.Function:
    """One controller sample of the drive (the only place the per-sample law is written).

    At the sampling instant: quantise the encoder angle, let the measurement block update,
    filter the derivative, run the PID (with the block's load-torque estimate fed forward by
    ``kff``) and store the new command. Over the sample: apply the command stored at the
    previous sample (one-sample computation delay, zero-order hold, plus optional ripple) and
    integrate the plant, split at a load event inside the sample when ``split``; then let the
    measurement block predict with the applied command.

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
    key = (settings, meas.key(), split, outer.key() if outer is not None else None, tuple(places))
    if key in built.sampled:
        return built.sampled[key]
    model, scale = built.model, built.plant_scale
    p = model.plant
    nz, nx = len(scale), model.nx
    n_meas = len(meas.memory_names)
    n_outer = len(outer.memory_names) if outer is not None else 0
    n_filt = len(_FILTER_MEMORY) * len(places)
    nm = len(_MEM_HEAD) + n_meas + n_outer + n_filt + len(_SAMPLED_OUTPUTS) + (len(_POSITION_OUTPUTS) if outer else 0) \
        + (len(_FILTER_OUTPUTS) if places else 0)
    ts = p.sample_time_s
    q = 2.0 * math.pi / p.encoder_counts
    integ = _sample_integrator(built, settings)
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
    applied = u_pend + ripple
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
                          *([w_raw, u_pid] if places else []))
    law = ca.Function("sample_law", [zm, par], [ca.vertcat(z, mem_next)])
    built.sampled[key] = law
    return law


def _accumulated(built: _Built, law: ca.Function, n: int) -> ca.Function:
    """``n`` samples of ``law`` chained (mapaccum), built once per law and length; with
    ``SimSettings(integrator="radau", jit=True)`` the law is compiled C code (once per law)."""
    key = (law, "accum", n)
    if key not in built.sampled:
        settings = next((k[0] for k, v in list(built.sampled.items())
                         if v is law and isinstance(k, tuple) and isinstance(k[0], SimSettings)), None)
        fun = law
        if settings is not None and settings.jit and settings.integrator == "radau":
            ckey = (law, "compiled")
            if ckey not in built.sampled:
                built.sampled[ckey] = _compiled(law, jacobian=False, flags=("-O1",)) or law
            fun = built.sampled[ckey]
        built.sampled[key] = fun.mapaccum(n)
    return built.sampled[key]


def _sample_events(ld: _Prof, sp: _Prof, ts: float, n: int):
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
    refs = _values_at(sp, t)
    sigma = p.values["sensor.torque_noise_n_m"]
    ripple = (np.random.default_rng(seed).normal(0.0, sigma, n + 1) if torque_noise and sigma > 0
              else np.zeros(n + 1))
    cols = np.vstack([refs, load_a, slope_a, load_b, slope_b, frac, ripple,
                      np.tile(np.r_[gains, kff, ff][:, None], (1, n + 1))])
    q = 2.0 * math.pi / p.encoder_counts
    if outer is not None:
        # A position run starts at rest: the encoder reads the middle of a count, so that no
        # rounding at a count edge flickers the reading (the plant does not depend on the angle).
        from dataclasses import replace as _replace

        x_mid = np.array(op.x, dtype=float)
        x_mid[model.index("theta_nut")] = 0.5 * q
        op = _replace(op, x=x_mid)
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
                      + (len(_FILTER_OUTPUTS) if filters else 0))]
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
            law = _accumulated(built, plain, k1 - k0) if k1 - k0 > 1 else plain
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
    extra = traj[nz + len(_MEM_HEAD) + n_meas + n_outer + n_filt :, :]
    xs = np.vstack([plant_x[:nx], ctrl, plant_x[nx:]])
    state_labels = tuple(model.state_names) + _SAMPLED_STATES + tuple(meas.memory_names) \
        + (tuple(outer.memory_names) if outer is not None else ()) + filt_names
    return t, xs, extra, refs, _values_at(ld, t), state_labels, events


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
    if not (_is_number(accuracy) and 0 < accuracy < 1):
        raise ValueError(f"accuracy = {accuracy!r}; expected a relative accuracy in (0, 1)")
    measured = fixed_step_error(plant, settings, reference, **run_kwargs)
    return (settings if measured["relative"] <= margin * accuracy else None), measured
