"""The simulator's CasADi functions, built once: integrator settings, the closed-loop right-hand
sides of a plant model, the adaptive SUNDIALS integrators, the fixed-step Radau IIA integrator
(tableau, sparse LU kernels, steps) and the compiled-code (JIT) cache.

Every function is built once per plant model, fidelity and settings and kept: in the model's
:class:`Built` (the ``_BUILT`` cache, weakly keyed by the model), in the LU kernel cache (by
matrix sparsity, shared by every plant of one structure) and in the compiled-code cache (by the
hash of the generated code, in this process and on disk, :func:`jit_cache_dir`). The per-sample
law of the sampled loop is written in :mod:`prsa_ctrl.sim.engine`; it is built from
:func:`sample_integrator` and chained by :func:`accumulated`.
"""

from __future__ import annotations

import hashlib
import math
import os
import shutil
import subprocess
import tempfile
import time
import warnings
import weakref
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from ..drive.pid import pid_law
from ..plant.model import PlantModel

__all__ = ["SimSettings", "INTEGRATORS", "RADAU_STAGES", "Built", "build", "continuous_integrator",
           "sample_integrator", "accumulated", "radau_tableau", "radau_step", "lu_kernels", "compiled", "jit_cache_dir",
           "state_scale", "plant_rates"]

INTEGRATORS = ("cvodes", "idas", "radau", "rodas")
#: Stages of the fixed-step ``"radau"`` integrator (Radau IIA: 1 = implicit Euler, order 1;
#: 2 = order 3; 3 = order 5; all L-stable and stiffly accurate).
RADAU_STAGES = (1, 2, 3)
# Parameter vector of the continuous closed loop: setpoint (rad/s) and load (N) at the segment
# start, kp, ki, kd, tf, feed-forward (N m), segment duration (s), setpoint and load slopes (per s).
_NP = 10


@dataclass(frozen=True)
class SimSettings:
    """Integrator settings. Tolerances apply to states scaled to order one.

    Parameters
    ----------
    integrator : {"cvodes", "idas", "radau", "rodas"}
        ``"cvodes"`` (default, the reference) and ``"idas"`` are SUNDIALS' adaptive implicit
        integrators. ``"rodas"`` (continuous runs only, ``discrete=False``) is the adaptive
        RODAS4 Rosenbrock method of :mod:`prsa_ctrl.sim.rosenbrock`: L-stable, error controlled by
        ``rtol``/``atol`` like CVODES's, its steps chained in one CasADi function (compiled with
        ``jit``) instead of one callback per right-hand side. ``"radau"`` is a fixed-step,
        linearly implicit Radau IIA integrator written in CasADi SX (``substeps`` steps of ``stages`` stages per
        controller sample, each with ``newton`` simplified Newton iterations on the exact Jacobian at the step
        start): one sample is a plain expression, so a whole chunk of samples runs as one ``mapaccum``'d
        function without integrator restarts. Its error is not controlled by ``rtol``/``atol`` (they are
        unused); it is measured against a tight CVODES reference
        (:func:`~prsa_ctrl.sim.engine.fixed_step_error`) and the fast path is only chosen where that error is
        inside the scene's accuracy (see ``README``). In continuous mode it takes ``substeps`` steps per output
        interval.
    rtol, atol : float
        Relative and absolute tolerances (adaptive integrators).
    max_steps : int
        Step budget per output interval (``"rodas"``: step attempts per output point, summed over
        a segment); exceeding it raises :class:`~prsa_ctrl.errors.SimulationError`.
    max_wall_s : float
        Wall-time budget of one run, s, checked between integration chunks (at most
        :data:`~prsa_ctrl.sim.engine.CHUNK_S` of simulated time each; ``"rodas"`` also between its
        chained step attempts); exceeding it raises :class:`~prsa_ctrl.errors.SimulationError`.
    energy_tol : float
        With ``energy=True`` the run audits itself: an energy-balance residual above this
        (relative, see :func:`~prsa_ctrl.sim.engine.energy_balance`) means the integration is not trustworthy and
        raises :class:`~prsa_ctrl.errors.SimulationError`; ``inf`` switches the audit off.
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
        non-finite state, which the run reports as a :class:`~prsa_ctrl.errors.SimulationError`).
    jacobian_every : int
        ``"radau"`` only: the Jacobian (and the factorised iteration matrix) is evaluated at
        the start of every this many steps and reused by the steps between (1, the default:
        at every step; a divisor of ``substeps``). Reusing it makes the scheme a W-method-like
        linearly implicit one: fewer operations per step, an error the caller measures (the
        batched Monte Carlo refreshes it four times per controller sample, see
        :func:`prsa_ctrl.studies.mcbatch.batch_settings`).
    jit : bool
        ``"cvodes"``/``"idas"``: evaluate the model's right-hand side and its Jacobian as C code
        compiled once per model into a per-user cache (``$PRSA_CTRL_CACHE``, else
        ``$XDG_CACHE_HOME/prsa-ctrl`` or ``~/.cache/prsa-ctrl``; keyed by the hash of the
        generated code); ``"rodas"``: its chained steps, once per model structure. ``"radau"``:
        compile the whole per-sample law of the sampled loop (plant steps, measurement, PID) the same way, once
        per law (a few seconds of ``cc -O1`` the first time; all members of a parametric family share it, see
        :func:`prsa_ctrl.plant.model.register_member`). Same equations, same tolerances; without a C compiler
        the run falls back to CasADi's interpreter with a warning.
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
    jacobian_every: int = 1

    def __post_init__(self) -> None:
        if self.integrator not in INTEGRATORS:
            raise ValueError(f"integrator = {self.integrator!r}; expected one of {', '.join(INTEGRATORS)}")
        for name, lo, hi in (("substeps", 1, 64), ("newton", 1, 4)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
                raise ValueError(f"{name} = {v!r}; expected an integer in [{lo}, {hi}]")
        v = self.jacobian_every
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 1 <= v <= self.substeps \
                or self.substeps % v:
            raise ValueError(f"jacobian_every = {v!r}; expected a divisor of substeps = {self.substeps}")
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


def state_scale(model: PlantModel) -> NDArray[np.float64]:
    """Typical magnitude of each state (``model.state_names``, their SI units), so that
    tolerances mean the same for all of them."""
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


_state_scale = state_scale


@dataclass(eq=False)
class Built:
    """Closed-loop functions of one plant model, built once (:func:`build`) and kept.

    Attributes
    ----------
    model : PlantModel
    scale : ndarray
        Typical magnitude of each state of the continuous loop (plant states, then the
        controller's filtered speed rad/s, PID integral N m and derivative state rad/s, then
        the energy terms J): the integrators work on states divided by it.
    plant_scale : ndarray
        The same for the sampled loop's plant part (plant states, family parameters, energy).
    energy : bool
        Whether the motor, load and dissipated work are integrated too.
    rhs : casadi.Function
        Continuous loop ``(z, p, tau) -> dz/dtau`` in scaled states and segment time normalised
        to [0, 1] (``p``: see ``_NP``); None for a family member.
    continuous, sampled : dict
        The integrators and per-sample laws built from it, by settings and structure.
    theta0 : ndarray
        A family member's parameter values (constant states of the shared sampled loop).
    """

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


_BUILT: "weakref.WeakKeyDictionary[PlantModel, dict[bool, Built]]" = weakref.WeakKeyDictionary()


def plant_rates(model: PlantModel, x, u, load, energy: bool, theta=None):
    """Plant state rates, followed by the motor, load and dissipated powers when ``energy``
    (``theta``: the parameters of a :class:`~prsa_ctrl.plant.model.ParametricModel`)."""
    args = (x, ca.vertcat(u, load)) + (() if theta is None else (theta,))
    if not energy:
        return model.f(*args)
    return ca.vertcat(model.f(*args), model.power(*args)[1:])


_plant_rates = plant_rates


class _Bounded(dict):
    """A dict that forgets its oldest entries beyond ``cap`` (functions shared by a family)."""

    cap = 64

    def __setitem__(self, key, value) -> None:
        super().__setitem__(key, value)
        while len(self) > self.cap:
            del self[next(iter(self))]


def _member_built(model: PlantModel, energy: bool) -> Built:
    """A family member's functions: the family's (built once, shared) with the member's
    parameters as the initial values of the constant states (see ``Built.theta0``)."""
    fam = model.family
    key = ("built", energy)
    if key not in fam.cache:
        x_scale = _state_scale(fam)
        e_scale = np.ones(3 if energy else 0)
        plant_scale = np.concatenate([x_scale, np.ones(fam.n_theta), e_scale])
        fam.cache[key] = Built(fam, plant_scale, plant_scale, energy, None, _Bounded(), _Bounded())
    b = fam.cache[key]
    return Built(fam, b.scale, b.plant_scale, energy, None, b.continuous, b.sampled,
                 np.asarray(model.theta, dtype=float))


def build(model: PlantModel, energy: bool, shared: bool = False) -> Built:
    """The closed-loop functions of ``model``, built on the first call and cached with the model.

    Parameters
    ----------
    model : PlantModel
    energy : bool
        Also integrate the motor, load and dissipated work (J).
    shared : bool
        Sampled fixed-step runs: a member of a parametric family gets its family's functions
        (one law for every member, the member's parameters as constant states).

    Returns
    -------
    Built
    """
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
    built = Built(model, scale, np.concatenate([x_scale, e_scale]), energy,
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

def radau_tableau(stages: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Butcher matrix ``A`` and nodes ``c`` of the ``stages``-stage Radau IIA method (Hairer &
    Wanner, Solving ODEs II, Table IV.5.5); the last row of ``A`` is the weights (stiffly
    accurate), so the step's result is the last stage value. The one tableau of the package:
    the simulator's fixed-step integrator and the fit's collocation both read it.

    Parameters
    ----------
    stages : {1, 2, 3}
        1 = implicit Euler (order 1), 2 = order 3, 3 = order 5.

    Returns
    -------
    (A, c) : ndarray (stages x stages), ndarray (stages)
        Coefficients and nodes as fractions of the step (dimensionless).

    Examples
    --------
    >>> a, c = radau_tableau(3)
    >>> bool(np.allclose(a.sum(axis=1), c)), float(c[-1])  # row sums are the nodes; the last is the step end
    (True, 1.0)
    """
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


def lu_kernels(sp: ca.Sparsity) -> tuple[ca.Function, ca.Function]:
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


def radau_step(f: ca.Function, nz: int, npar: int, settings: SimSettings, span: float) -> ca.Function:
    """``(x0, p, tau0) -> x`` after ``span`` of normalised time from ``tau0``: ``settings.substeps``
    Radau IIA steps of ``f(z, p, tau) -> dz/dtau``, each solving its stage equations
    ``Z_i = x + h sum_j a_ij f(Z_j)`` with ``settings.newton`` simplified Newton iterations
    from ``Z_i = x`` on the iteration matrix ``I - h (A kron J(x))`` (exact Jacobian at the
    step start, factorised once per step). One Newton iteration makes it a linearly implicit
    (Rosenbrock-type) Radau method: still L-stable, the 25.8 kHz contact mode and the stiff
    traction creep are damped, not resolved. With ``settings.jacobian_every = m > 1`` the
    Jacobian and the factorised matrix are those of the start of every ``m``-th step, reused
    by the ``m - 1`` steps after it. A plain SX expression: no restarts, no convergence loop,
    a fixed cost per step.

    Parameters
    ----------
    f : casadi.Function
        ``(z, p, tau) -> dz/dtau``, scaled states and normalised time.
    nz, npar : int
        Sizes of ``z`` and ``p``.
    settings : SimSettings
        ``substeps``, ``stages`` and ``newton`` of the step.
    span : float
        Normalised time covered (dimensionless, 1 = the whole segment or sample).

    Returns
    -------
    casadi.Function
        ``radau_step(x0, p, tau0) -> xf``.
    """
    a_mat, c = radau_tableau(settings.stages)
    s = settings.stages
    z = ca.SX.sym("z", nz)
    p = ca.SX.sym("p", npar)
    tau = ca.SX.sym("tau")
    jac = ca.Function("radau_dfdz", [z, p, tau], [ca.jacobian(f(z, p, tau), z)])
    h = span / settings.substeps
    j_sym = ca.SX.sym("j", jac.sparsity_out(0))
    iter_mat = ca.Function("radau_iteration_matrix", [j_sym],
                           [ca.SX.eye(s * nz) - h * ca.kron(ca.SX(ca.DM(a_mat)), j_sym)])
    factor, solve = lu_kernels(iter_mat.sparsity_out(0))
    x0 = ca.SX.sym("x0", nz)
    tau0 = ca.SX.sym("tau0")
    x = x0
    every = getattr(settings, "jacobian_every", 1)
    for k in range(settings.substeps):
        t_k = tau0 + k * h
        if k % every == 0:
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
    root = os.environ.get("PRSA_CTRL_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "prsa-ctrl")
    return Path(root) / "jit"


def compiled(fun: ca.Function, jacobian: bool = True, flags: tuple[str, ...] = ("-O2",)) -> ca.Function | None:
    """``fun`` (and its Jacobian) as C code compiled once into :func:`jit_cache_dir` (keyed by the
    hash of the code, the CasADi version, the compiler and ``flags``) and loaded as an external function;
    ``None`` with a warning when no C compiler is found or compiling fails (the caller then
    uses CasADi's interpreter: same equations, slower).

    Parameters
    ----------
    fun : casadi.Function
    jacobian : bool
        Compile its Jacobian too (the SUNDIALS integrators need it).
    flags : tuple of str
        Compiler flags.

    Returns
    -------
    casadi.Function or None
    """
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
    ext = compiled(ca.Function("prsa_ode", [z, par, tau], [ode])) if settings.jit else None
    if ext is None:
        return {"x": z, "p": par, "t": tau, "ode": ode}
    zm, pm, tm = ca.MX.sym("z", z.numel()), ca.MX.sym("p", par.numel()), ca.MX.sym("tau")
    return {"x": zm, "p": pm, "t": tm, "ode": ext(zm, pm, tm)}


def continuous_integrator(built: Built, settings: SimSettings, n_out: int) -> ca.Function:
    """The continuous loop's integrator over one segment (normalised time 0..1) with ``n_out``
    equally spaced outputs: ``(x0 = scaled state, p = the segment's parameters) -> xf``
    (one column per output). SUNDIALS' ``settings.integrator``; for ``"radau"``,
    ``settings.substeps`` fixed steps per output interval chained by ``mapaccum``; for ``"rodas"``,
    a :class:`~prsa_ctrl.sim.rosenbrock.RodasSegment` (adaptive RODAS4 steps in chained chunks).
    Built once per ``(settings, n_out)`` and kept in ``built.continuous``.
    """
    key = (settings, n_out)
    if key not in built.continuous:
        z = ca.SX.sym("z", len(built.scale))
        par = ca.SX.sym("p", _NP)
        tau = ca.SX.sym("tau")
        if settings.integrator == "radau":
            # substeps fixed steps per output interval, all intervals chained (mapaccum)
            f = ca.Function("rhs_scaled", [z, par, tau], [built.rhs(z, par, tau)])
            step = radau_step(f, len(built.scale), _NP, settings, 1.0 / n_out)
            chain = step.mapaccum("radau_chain", n_out, [0], [0])
            x0 = ca.MX.sym("x0", len(built.scale))
            pm = ca.MX.sym("p", _NP)
            taus = ca.DM(np.arange(n_out) / n_out).T
            xf = chain(x0, ca.repmat(pm, 1, n_out), taus)
            built.continuous[key] = ca.Function("segment", [x0, pm], [xf], ["x0", "p"], ["xf"])
        elif settings.integrator == "rodas":
            from .rosenbrock import CHUNK_ATTEMPTS, RodasSegment, rodas_attempt

            ckey = ("rodas chunk", settings.jit)
            if ckey not in built.continuous:  # one function per model (n_out and tolerances are inputs)
                f = ca.Function("rhs_scaled", [z, par, tau], [built.rhs(z, par, tau)])
                chunk = rodas_attempt(f, len(built.scale), _NP, lu_kernels).mapaccum("rodas_chunk", CHUNK_ATTEMPTS,
                                                                                     [0], [0])
                built.continuous[ckey] = (compiled(chunk, jacobian=False) if settings.jit else None) or chunk
            built.continuous[key] = RodasSegment(built.continuous[ckey], len(built.scale), n_out, settings.rtol,
                                                 settings.atol, settings.max_steps * n_out)
        else:
            dae = _ode_dae(z, par, tau, built.rhs(z, par, tau), settings)
            grid = list(np.linspace(0.0, 1.0, n_out + 1)[1:])
            built.continuous[key] = ca.integrator("segment", settings.integrator, dae, 0.0, grid, _opts(settings))
    return built.continuous[key]


def sample_integrator(built: Built, settings: SimSettings) -> ca.Function:
    """Plant-only integrator with the command held: ``(x0 = scaled plant state (+ energy),
    p = [torque N m, load N at the start, load slope N/s, interval s]) -> xf``. Built once per
    settings and kept in ``built.sampled``."""
    if settings.integrator == "rodas":
        raise ValueError("integrator = 'rodas' in the sampled loop; expected 'cvodes', 'idas' or 'radau' "
                         "(RODAS4 integrates the continuous loop only: discrete=False)")
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
            step = radau_step(ca.Function("plant_scaled", [zp, pp, tau], [ode]), len(scale), 4, settings, 1.0)
            x0 = ca.SX.sym("x0", len(scale))
            built.sampled[key] = ca.Function("sample", [x0, pp], [step(x0, pp, 0.0)], ["x0", "p"], ["xf"])
        else:
            built.sampled[key] = ca.integrator("sample", settings.integrator, _ode_dae(zp, pp, tau, ode, settings),
                                               0.0, 1.0, _opts(settings))
    return built.sampled[key]


def accumulated(built: Built, law: ca.Function, n: int) -> ca.Function:
    """``n`` samples of ``law`` chained (mapaccum), built once per law and length; with
    ``SimSettings(integrator="radau", jit=True)`` the law is compiled C code (once per law).

    Parameters
    ----------
    built : Built
        Whose ``sampled`` cache holds ``law`` (keyed by its settings) and the result.
    law : casadi.Function
        One controller sample, ``(zm, p) -> zm`` at the next sample.
    n : int
        Samples chained.

    Returns
    -------
    casadi.Function
    """
    key = (law, "accum", n)
    if key not in built.sampled:
        settings = next((k[0] for k, v in list(built.sampled.items())
                         if v is law and isinstance(k, tuple) and isinstance(k[0], SimSettings)), None)
        fun = law
        if settings is not None and settings.jit and settings.integrator == "radau":
            ckey = (law, "compiled")
            if ckey not in built.sampled:
                built.sampled[ckey] = compiled(law, jacobian=False, flags=("-O1",)) or law
            fun = built.sampled[ckey]
        built.sampled[key] = fun.mapaccum(n)
    return built.sampled[key]
