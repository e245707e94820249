"""The position loop over the speed loop: the linear model of the sampled cascade and its tuners.

The move scene a cascade is tuned for (:class:`~prsa_ctrl.studies.movescene.MoveScene`) is read
by :mod:`prsa_ctrl.studies.movescene`; the nonlinear runs, metrics, verification and the
comparison of both designs are in :mod:`prsa_ctrl.studies.move`, the drive export in
:func:`prsa_ctrl.io.export.export_cascade`, the figures in :mod:`prsa_ctrl.plots.move`.

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
    *sequential* (the baseline): the speed PI tuned alone by :func:`prsa_ctrl.tuning.generic.tune_loops`
    (IAE of the load step) at the same Ms, then the position P gain at 1/5 .. 1/10 of the
    speed loop's crossover (the largest that keeps every Ms within the bound), full velocity
    and acceleration feed-forward (``kvff = kaff = 1``). Both are verified on the nonlinear
    compliant model (:func:`prsa_ctrl.studies.move.tune_move`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from ..drive.sampled import zoh
from ..drive.measurement import PositionLoop
from ..drive.pid import PID
from ..options import DERIVATIVE_FILTER_SAMPLES
from ..plant.linear import linear_core
from ..plant.model import plant_model
from .loops import resonance_points
from .builders import drive_loop
from .generic import tune_loops

if TYPE_CHECKING:
    from ..plant.plantfile import Plant
# A move scene (prsa_ctrl.studies.movescene.MoveScene) and its verified metrics
# (prsa_ctrl.studies.move.MoveMetrics) live a layer up: named in annotations only, never imported.

__all__ = ["CascadeModel", "CascadeDesign", "tune_cascade", "sequential_design", "CASCADE_GAINS",
           "MS_EXCESS_RTOL", "BREAKING_POINTS"]

#: The loop-breaking points whose Ms the tuning bounds (:meth:`CascadeModel.loops`): the speed
#: loop with the position loop closed and opened, the position loop, the torque command (both
#: loops broken at the plant input).
BREAKING_POINTS = ("speed_closed", "speed_open", "position", "torque")
#: Largest relative excess of a joint design's verified (true, dense-grid) Ms over the bound
#: that is accepted; beyond it the frequency is added to the NLP's grid and it is solved again
#: (not the tuner's ``MS_RTOL``, which says how close to an active bound the tuner ends).
MS_EXCESS_RTOL = 1e-5
#: Gains of a cascade design, in this order: speed kp (N m s/rad), ki (N m/rad); position kv
#: (1/s), kip (1/s^2); velocity and acceleration feed-forward (dimensionless).
CASCADE_GAINS = ("kp", "ki", "kv", "kip", "kvff", "kaff")


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
        Ad, Bd = zoh(A, B, ts)
        self.Ad, self.bu, self.bd = Ad, Bd[:, 0], Bd[:, 1]
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
        self.omega = np.unique(np.concatenate([np.geomspace(1.0, nyq * 0.999, n_grid),
                                               resonance_points(lam, 1.0, nyq * 0.999)]))
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
        zd = zi ** (1 + self.plant.command_delay_samples)  # computation delay and the drive's command delay
        G = zd * (res @ self.c_th)
        Gp = zd * (res @ self.c_pos)
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
        n, ts, a = self.n, self.ts, self.a_lead
        nd = self.plant.command_delay_samples  # the drive's command delay: a line of nd commands after the states
        g = ca.SX.sym("g", 6)
        X = ca.SX.sym("X", n + 5 + nd)
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
        line = X[n + 5:]
        act = line[nd - 1] if nd else u_pend
        x1 = ca.mtimes(ca.DM(self.Ad), x) + ca.DM(self.bu) * act + ca.DM(self.bd) * r[3]
        Xn = ca.vertcat(x1, theta, w_f1, i_s1, u, i_p1, *([u_pend] if nd else []), *[line[i] for i in range(nd - 1)])
        self.step = ca.Function("cascade_step", [X, r, g], [Xn, e_p * a])
        self.jac = ca.Function("cascade_ab", [g], [ca.jacobian(Xn, X), ca.jacobian(Xn, r)])
        self.nX = n + 5 + nd

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


@dataclass(frozen=True)
class CascadeDesign:
    """A tuned cascade: gains, their true Ms (verified), linear and nonlinear metrics.

    Attributes
    ----------
    method : {"joint", "sequential"}
    speed : PID
    position : PositionLoop
    ms_points : dict
        True Ms at each breaking point (:meth:`CascadeModel.ms`) with the frequencies
        (``"ms"`` in :meth:`as_dict`).
    ms : float
        The largest of them (a property, as ``ms`` is on every other result).
    crossover_rad_s : dict
        Speed-loop (position loop opened) and position-loop crossovers.
    linear : dict
        Linear peak/RMS following error and holding deviation, m.
    objective : float
        Value of the tuning objective (baseline = weight_following + weight_holding).
    verified : MoveMetrics or None
        Metrics on the nonlinear model (:func:`prsa_ctrl.studies.move.verify_design` returns
        a verified copy).
    notes : tuple of str
        The design's caveats (also ``warnings``).
    status : str
        ``"unverified"``, ``"ok"`` (verified, settles in its window) or ``"flagged: ..."``
        (:data:`prsa_ctrl.results.STATUSES`).
    """

    method: str
    speed: PID
    position: PositionLoop
    ms_points: dict
    crossover_rad_s: dict
    linear: dict
    objective: float
    verified: MoveMetrics | None = None
    notes: tuple = ()
    solver: dict = field(default_factory=dict)
    #: The nonlinear run of :func:`verify_design` (for the figures; not in :meth:`as_dict`).
    run: Any = field(default=None, repr=False, compare=False)

    @property
    def ms(self) -> float:
        """The largest true Ms over the breaking points."""
        return float(max(self.ms_points[k] for k in BREAKING_POINTS if k in self.ms_points))

    @property
    def warnings(self) -> tuple[str, ...]:
        return tuple(self.notes)

    @property
    def status(self) -> str:
        if self.verified is None:
            return "unverified"
        if not math.isfinite(self.verified.settling_time_s):
            return "flagged: the nonlinear run never settles in the scene's window"
        return "ok"

    @property
    def gains(self) -> list[float]:
        return [self.speed.kp, self.speed.ki, *self.position.gains[:2], *self.position.gains[2:]]

    def as_dict(self) -> dict:
        return {"method": self.method, "speed": self.speed.as_dict(),
                "position": {"kv_per_s": self.position.kv, "ki_per_s2": self.position.ki, "kvff": self.position.kvff,
                             "kaff": self.position.kaff, "measured": self.position.measured,
                             "rate": self.position.rate},
                "ms": self.ms_points, "crossover_rad_s": self.crossover_rad_s, "linear": self.linear,
                "objective": self.objective, "verified": self.verified.as_dict() if self.verified else None,
                "notes": list(self.notes), "solver": self.solver}


def _linear_summary(cm: CascadeModel, g) -> dict:
    em, eh = cm.error(g, "move"), cm.error(g, "hold")
    return {"peak_following_error_m": float(np.max(np.abs(em))), "rms_following_error_m": float(np.sqrt(np.mean(em**2))),
            "holding_deviation_m": float(np.max(np.abs(eh))), "ms_following": float(np.mean(em**2)),
            "ms_holding": float(np.mean(eh**2))}


def _design(cm: CascadeModel, method: str, g, objective: float, notes=None, solver=None) -> CascadeDesign:
    sc = cm.scene
    speed = PID(float(g[0]), float(g[1]))
    pos = PositionLoop(kv=float(g[2]), ki=float(g[3]), kvff=float(g[4]), kaff=float(g[5]), measured=sc.measured,
                       rate=sc.position_rate)
    cross = {"speed_open": cm.crossover(g, "speed_open"), "position": cm.crossover(g, "position")}
    return CascadeDesign(method, speed, pos, cm.ms(g), cross, _linear_summary(cm, g), float(objective),
                         notes=tuple(notes or ()), solver=dict(solver or {}))


def sequential_design(plant: "Plant", scene: MoveScene, cm: CascadeModel | None = None,
                      ratios=(5.0, 6.0, 7.0, 8.0, 9.0, 10.0)) -> CascadeDesign:
    """The rule-of-thumb baseline (module docstring): speed PI tuned alone at ``scene.ms_max``
    (:func:`prsa_ctrl.tuning.generic.tune_loops`, IAE of the load step on the drive loop), position P
    at ``crossover / ratio`` for the smallest ``ratio`` in ``ratios`` that keeps every Ms within
    the bound, ``kvff = kaff = 1``.

    Returns
    -------
    CascadeDesign
    """
    cm = cm or CascadeModel(plant, scene)
    model = plant_model(plant, scene.fidelity)
    a_, b_, c_, _, _ = linear_core(plant, cm.w_lin, scene.load_n, scene.fidelity)
    step = scene.hold_step_n or max(abs(scene.load_n), 100.0)
    lp = drive_loop(a_, b_, c_[model.output_names.index("nut_speed")], model.index("theta_nut"), ts=plant.sample_time_s,
                    speed_filter=plant.speed_filter_s, tf=DERIVATIVE_FILTER_SAMPLES * plant.sample_time_s, horizon=0.1, step=step,
                    command_delay_samples=plant.command_delay_samples)
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
        if stable and pk[worst] <= sc.ms_max * (1 + MS_EXCESS_RTOL):
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
