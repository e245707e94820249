"""The position loop over the speed loop: the linear model of the sampled cascade and its tuners.

A cascade is tuned for a move's numbers (:class:`~prsa_ctrl.tuning.cascadespec.CascadeSpec`, built
by :meth:`prsa_ctrl.studies.movescene.MoveScene.cascade_spec`); the nonlinear runs, metrics,
verification and the comparison of both designs are in :mod:`prsa_ctrl.studies.move`, the drive
export in :func:`prsa_ctrl.io.export.export_cascade`, the figures in :mod:`prsa_ctrl.plots.move`.

Linear model of the sampled cascade (:class:`CascadeModel`)
    The plant linearised at the move's cruise speed and held load
    (:func:`prsa_ctrl.plant.linear.linear_core`), discretised with a zero-order hold, under exactly
    the per-sample law the simulator runs (encoder difference and speed filter, speed PI with
    Euler integral, one-sample computation delay; position P/PI with velocity and acceleration
    feed-forward, every ``position_rate`` speed-loop samples, the speed reference held in
    between; the multi-rate loop below). Its loop transfer functions at the four
    loop-breaking points, with ``G`` the torque-command-to-angle response (delay included),
    ``G_p`` the same to the measured position (rad), ``W`` the speed measurement,
    ``C_s = kp + ki Ts z^-1/(1 - z^-1)``, ``C_p = (kv + kip Ts/(1 - z^-1)) z^-d`` (``d`` the
    position loop's own computation delay, ``[move] position_delay_samples``: its output is
    applied d position-loop samples after it is computed)::

        speed loop, position loop closed:  L_sc = W G C_s / (1 + G_p C_s C_p)
        speed loop, position loop opened:  L_so = W G C_s
        position loop, speed loop closed:  L_p  = G_p C_s C_p / (1 + W G C_s)
        torque command (both loops broken at the plant input):  L_t = G_p C_s C_p + W G C_s

    Ms = max |1/(1 + L)| at each (:data:`BREAKING_POINTS`). With the position loop every N > 1
    speed samples (Tp = N Ts) the loop is N-periodic and is lifted to the position period
    (:meth:`CascadeModel.lift`: exact for the sampled loop): the position loop is scalar at its
    own rate (:meth:`CascadeModel.position_loop`), the speed loop alone unchanged, and at the
    torque command and the speed loop with the position loop closed the peak is that of
    ``sigma_max((I + L_lifted)^-1)`` (:meth:`CascadeModel.return_differences`), the L2 gain of
    the periodic sensitivity. The linearisation ignores stiction (at rest the nut
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

from ..drive.filters import loop_filters
from ..drive.sampled import zoh
from ..drive.measurement import PositionLoop
from ..drive.pid import PID
from ..options import DERIVATIVE_FILTER_SAMPLES, POSITION_DELAY_MAX, POSITION_RATE_MAX, parse_kv
from ..plant.linear import linear_core
from ..plant.model import plant_model
from .loops import resonance_points
from .builders import drive_loop
from .cascadems import abs2, cplx_mul, multirate_constraints
from .cascadespec import CascadeSpec
from .generic import tune_loops

if TYPE_CHECKING:
    from ..plant.plantfile import Plant

__all__ = ["CascadeModel", "CascadeSpec", "CascadeDesign", "tune_cascade", "sequential_design", "kv_ceiling", "CASCADE_GAINS",
           "cascade_design", "gains_from_solution",
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


class CascadeModel:
    """Linear model of the sampled cascade around the move's cruise speed and held load.

    Parameters
    ----------
    plant : Plant
    spec : CascadeSpec
        The move's numbers.
    fidelity : {"rigid", "compliant"}, optional
        Linearised model (default: the spec's).
    n_grid : int
        Frequencies of the Ms constraints (log-spaced to the Nyquist frequency, plus the
        plant's resonances).

    Notes
    -----
    Gains ``g = [kp, ki, kv, kip, kvff, kaff]`` (:data:`CASCADE_GAINS`). The position loop
    runs every ``spec.position_rate`` speed-loop samples (``tp`` = its sample time, s).
    """

    def __init__(self, plant: "Plant", spec: CascadeSpec, fidelity: str | None = None, n_grid: int = 300) -> None:
        rate = spec.position_rate
        if isinstance(rate, bool) or not isinstance(rate, int) or not 1 <= rate <= POSITION_RATE_MAX:
            raise ValueError(f"{spec.origin}: move.position_rate = {rate!r}; expected an integer number of speed-loop "
                             f"samples in [1, {POSITION_RATE_MAX}]")
        self.rate = rate
        delay = spec.position_delay_samples
        if isinstance(delay, bool) or not isinstance(delay, int) or not 0 <= delay <= POSITION_DELAY_MAX:
            raise ValueError(f"{spec.origin}: move.position_delay_samples = {delay!r}; expected an integer number of "
                             f"position-loop samples in [0, {POSITION_DELAY_MAX}]")
        #: The position loop's computation delay, in position-loop samples.
        self.delay = delay
        self.plant, self.spec = plant, spec
        #: The drive's fixed loop filters (the scene's ``[filters]``), as the simulator runs them:
        #: speed-measurement biquads on the filtered speed the PI reads, torque-command biquads on
        #: the PI's command (feed-forward included) before the delay.
        self.filters = tuple(loop_filters(tuple(spec.filters), plant.sample_time_s))
        self.biquads = tuple((lf.place, lf.biquad(plant.sample_time_s)) for lf in self.filters)
        fid = fidelity or spec.fidelity
        model = plant_model(plant, fid)
        self.a_lead = a = plant.lead_per_rad
        self.inertia = plant.reflected_inertia_kg_m2
        self.ts = ts = plant.sample_time_s
        #: Position-loop sample time, s.
        self.tp = rate * ts
        w_cruise = spec.cruise_speed_m_s / a
        self.w_lin, self.load_lin = w_cruise, spec.load_n
        A, B, _, _, _ = linear_core(plant, w_cruise, spec.load_n, fid)
        n = A.shape[0]
        Ad, Bd = zoh(A, B, ts)
        self.Ad, self.bu, self.bd = Ad, Bd[:, 0], Bd[:, 1]
        self.n = n
        self.c_th = np.eye(n)[model.index("theta_nut")]
        if spec.measured == "nut_angle":
            self.c_pos = self.c_th.copy()
        else:
            self.c_pos = self.c_th.copy()
            if "delta_screw" in model.state_names:
                self.c_pos = self.c_pos + (np.eye(n)[model.index("x_roller")] - np.eye(n)[model.index("delta_screw")]) / a
        self.alpha = math.exp(-ts / plant.speed_filter_s)
        nyq = math.pi / self.tp  # the position loop's Nyquist frequency (the speed loop's at rate 1)
        lam = np.log(np.linalg.eigvals(self.Ad).astype(complex)) / ts
        if rate > 1:  # resonances above the position loop's Nyquist frequency appear at their aliases
            lam = np.concatenate([lam + 2j * math.pi * k / self.tp for k in range(-rate, rate + 1)])
        self.omega = np.unique(np.concatenate([np.geomspace(1.0, nyq * 0.999, n_grid),
                                               resonance_points(lam, 1.0, nyq * 0.999)]))
        #: Gain-free responses of the recent frequency grids (:meth:`_cached`), read-only.
        self._resp_cache: dict = {}
        self._build_casadi()

    #: Grids of at least this many frequencies have their gain-free responses kept (the dense
    #: grids :meth:`ms` evaluates at every call), at most ``_CACHE_MAX`` of them.
    _CACHE_MIN, _CACHE_MAX = 64, 8

    def _cached(self, kind: str, w: NDArray[np.float64], compute) -> dict:
        """``compute(w)`` (a dict of arrays, functions of ``w`` and the model alone, never of the
        gains), kept for grids of ``_CACHE_MIN`` or more frequencies: :meth:`ms` evaluates the same
        dense grid at every gain, and the responses are the same numbers whichever the gains. The
        arrays are read-only; the dict is a copy. At most ``_CACHE_MAX`` grids (the oldest dropped)."""
        if w.size < self._CACHE_MIN:
            return compute(w)
        key = (kind, w.shape, w.tobytes())
        hit = self._resp_cache.get(key)
        if hit is None:
            hit = compute(w)
            for v in hit.values():
                if isinstance(v, np.ndarray):
                    v.setflags(write=False)
            while len(self._resp_cache) >= self._CACHE_MAX:
                self._resp_cache.pop(next(iter(self._resp_cache)))
            self._resp_cache[key] = hit
        return dict(hit)

    # frequency responses (numeric, gain-free parts)
    def parts(self, omega: NDArray[np.float64]) -> dict[str, NDArray[np.complex128]]:
        """Gain-free responses at ``omega`` (rad/s): ``G`` torque command -> nut angle (rad per
        N m, computation delay and ZOH included), ``Gp`` -> measured position (rad), ``W`` nut
        angle -> speed measurement (1/s), ``cs_i`` and ``cp_i`` the integral parts of the
        speed and position laws per unit gain, ``dp`` = ``z^-(N d)`` the position loop's own
        computation delay (``d = position_delay_samples`` position samples of ``N`` speed samples;
        it multiplies ``C_p`` wherever ``C_p`` appears)."""
        return self._cached("parts", np.asarray(omega, float), self._parts)

    def _parts(self, w: NDArray[np.float64]) -> dict[str, NDArray[np.complex128]]:
        zi = np.exp(-1j * w * self.ts)
        z = 1 / zi
        n = self.n
        lhs = z[:, None, None] * np.eye(n)[None] - self.Ad[None]
        res = np.linalg.solve(lhs, np.broadcast_to(self.bu, (w.size, n))[..., None])[..., 0]
        zd = zi ** (1 + self.plant.command_delay_samples)  # computation delay and the drive's command delay
        G = zd * (res @ self.c_th)
        Gp = zd * (res @ self.c_pos)
        W = (1 - self.alpha) / (1 - self.alpha * zi) * (1 - zi) / self.ts
        for place, bq in self.biquads:  # the loop filters (none: the responses unchanged)
            f = bq.frequency_response(w)
            if place == "speed_measurement":
                W = W * f
            else:
                G, Gp = G * f, Gp * f
        return {"G": G, "Gp": Gp, "W": W, "cs_i": self.ts * zi / (1 - zi), "cp_i": self.ts / (1 - zi),
                "dp": zi ** (self.rate * self.delay)}

    def loops(self, g, omega: NDArray[np.float64] | None = None) -> dict[str, NDArray[np.complex128]]:
        """Loop transfer functions at the three breaking points (module docstring) and at the
        torque command (``torque``: both loops broken at once), at ``omega`` (rad/s).

        With ``position_rate = N > 1`` only the two loops a scalar transfer function describes
        are returned: ``speed_open`` (the speed loop alone, at the speed-loop rate) and
        ``position`` (the position loop at its own sample time over the closed speed loop,
        :meth:`position_loop`); the other two points are N-periodic
        (:meth:`return_differences`)."""
        w = self.omega if omega is None else np.asarray(omega, float)
        if self.rate > 1:
            P = self.parts(w)
            r = P["W"] * P["G"] * (float(g[0]) + float(g[1]) * P["cs_i"])
            return {"speed_open": r, "position": self.position_loop(g, w)}
        P = self.parts(w)
        kp, ki, kv, kip = (float(x) for x in g[:4])
        cs = kp + ki * P["cs_i"]
        cp = (kv + kip * P["cp_i"]) * P["dp"]
        q, r = P["Gp"] * cs * cp, P["W"] * P["G"] * cs
        return {"speed_closed": r / (1 + q), "speed_open": r, "position": q / (1 + r), "torque": q + r}

    # --- the multi-rate loop (position_rate = N > 1) -------------------------------------
    def aliases(self, omega: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.complex128]]:
        """The N speed-loop frequencies ``w_k = w - 2 pi k/Tp`` (rad/s, k = 0..N-1; shape
        (N, len(omega))) that a position-loop frequency ``w`` (rad/s) lifts, and ``z_k =
        exp(j w_k Ts)``."""
        w = np.asarray(omega, float)
        wk = w[None, :] - 2.0 * math.pi * np.arange(self.rate)[:, None] / self.tp
        return wk, np.exp(1j * wk * self.ts)

    def lift(self, h: NDArray[np.complex128], z: NDArray[np.complex128]) -> NDArray[np.complex128]:
        """The lifted (N x N, at the position-loop rate) response of a speed-loop-rate LTI
        response ``h`` given at the aliases ``z`` (:meth:`aliases`, shape (N, n)): entry
        ``[m, l] = (1/N) sum_k z_k^(m-l) h(z_k)``, the response of the m-th speed sample of a
        position period to the l-th; shape (n, N, N)."""
        N = self.rate
        ml = (np.arange(N)[:, None] - np.arange(N)[None, :]).astype(float)
        return np.sum(h.T[:, :, None, None] * z.T[:, :, None, None] ** ml[None, None], axis=1) / N

    def lifted_parts(self, omega: NDArray[np.float64]) -> dict:
        """Gain-free lifted responses at the position-loop frequencies ``omega`` (rad/s, up to
        pi/Tp): ``A`` = lift(W G), ``Lc`` = lift of the speed integral per unit ``ki``, ``c``
        the first row of lift(G_p) (the position read at the position-loop sample), ``cp_i``
        ``Tp/(1 - z_p^-1)`` (the position integral per unit gain at its own rate), ``dp`` =
        ``z_p^-d`` (the position loop's own computation delay of d position samples) and, per
        alias (shape (N, n)), ``r`` = W G, ``cs_i``, ``Gp``, ``h`` = ``(1 - z_k^-N)/(N (1 - z_k^-1))``
        (the hold of the speed reference and the sampling of the position)."""
        return self._cached("lifted", np.asarray(omega, float), self._lifted_parts)

    def _lifted_parts(self, w: NDArray[np.float64]) -> dict:
        wk, z = self.aliases(w)
        P = self._parts(wk.ravel())
        sh = wk.shape
        WG, csi, Gp = (P["W"] * P["G"]).reshape(sh), P["cs_i"].reshape(sh), P["Gp"].reshape(sh)
        zp = np.exp(1j * w * self.tp)
        N = self.rate
        h = sum(z ** (-float(l)) for l in range(N)) / N  # (1 - z^-N)/(N (1 - z^-1)), finite at z = 1
        return {"A": self.lift(WG, z), "Lc": self.lift(csi, z), "c": self.lift(Gp, z)[:, 0, :],
                "cp_i": self.tp / (1 - 1 / zp), "dp": zp ** (-float(self.delay)),  # the position loop's delay
                "r": WG, "cs_i": csi, "Gp": Gp, "h": h, "G": P["G"].reshape(sh)}

    def position_loop(self, g, omega: NDArray[np.float64]) -> NDArray[np.complex128]:
        """The position loop broken at its sampled measurement, the speed loop closed, at its
        own sample time Tp (exact: the speed-loop-closed plant from the held speed reference
        to the position sampled every N speed samples), at ``omega`` (rad/s, up to pi/Tp)::

            L_p(z_p) = C_p(z_p) (1/N) sum_k T(z_k) (1 - z_k^-N)/(1 - z_k^-1),
            T = G_p C_s/(1 + W G C_s),  C_p = kv + kip Tp/(1 - z_p^-1)

        (the alias sum of the held and sampled response; at N = 1 ``q/(1 + r)``)."""
        w = np.asarray(omega, float)
        if self.rate == 1:
            return self.loops(g, w)["position"]
        L = self.lifted_parts(w)
        cs = float(g[0]) + float(g[1]) * L["cs_i"]
        T = L["Gp"] * cs / (1 + L["r"] * cs)
        return (float(g[2]) + float(g[3]) * L["cp_i"]) * L["dp"] * np.sum(L["h"] * T, axis=0)

    def return_differences(self, g, omega: NDArray[np.float64]) -> dict[str, NDArray[np.complex128]]:
        """Lifted return differences ``M = I + L`` (shape (n, N, N), at the position-loop
        frequencies ``omega``, rad/s) at the two N-periodic breaking points, with ``B`` =
        lift(C_s), ``A`` = lift(W G), ``a = B 1`` (the speed reference held over the period),
        ``b^T = C_p c^T`` (the position sampled at its first speed sample)::

            torque:        M_t  = I + B A + a b^T
            speed_closed:  M_sc = I + A (I + a b^T)^-1 B

        Their sensitivity ``S = M^-1`` has the peak ``max_w sigma_max(S) = 1/min_w sigma_min(M)``,
        the L2-induced gain of the periodic loop's sensitivity (at N = 1 ``|1/(1 + L)|``)."""
        w = np.asarray(omega, float)
        L = self.lifted_parts(w)
        N = self.rate
        eye = np.eye(N)[None]
        B = float(g[0]) * eye + float(g[1]) * L["Lc"]
        A = L["A"]
        a = B @ np.ones(N)
        b = ((float(g[2]) + float(g[3]) * L["cp_i"]) * L["dp"])[:, None] * L["c"]
        ab = a[:, :, None] * b[:, None, :]
        Mt = eye + B @ A + ab
        Msc = eye + A @ np.linalg.solve(eye + ab, B)
        return {"torque": Mt, "speed_closed": Msc}

    def sensitivity(self, g, omega: NDArray[np.float64], points=BREAKING_POINTS) -> dict[str, NDArray[np.float64]]:
        """Sensitivity magnitudes at every breaking point (:data:`BREAKING_POINTS`) at ``omega``
        (rad/s): ``|1/(1 + L)|``, and for the lifted points of a multi-rate loop
        ``sigma_max(M^-1)`` (:meth:`return_differences`). ``speed_open`` is read at the
        speed-loop rate (up to pi/Ts), the others at the position loop's (up to pi/Tp)."""
        if self.rate == 1:
            return {k: np.abs(1 / (1 + v)) for k, v in self.loops(g, omega).items()}
        w = np.asarray(omega, float)
        out = {}
        if "speed_open" in points:
            P = self.parts(w)
            out["speed_open"] = np.abs(1 / (1 + P["W"] * P["G"] * (float(g[0]) + float(g[1]) * P["cs_i"])))
        if "position" in points:
            out["position"] = np.abs(1 / (1 + self.position_loop(g, w)))
        if "torque" in points or "speed_closed" in points:
            for k, M in self.return_differences(g, w).items():
                out[k] = 1 / np.linalg.svd(M, compute_uv=False)[:, -1]
        return out

    def ms(self, g, n_dense: int = 20000) -> dict[str, float]:
        """True peak sensitivities (:meth:`sensitivity`) at each breaking point: dense log grid
        (``n_dense`` points to the Nyquist frequency of the point's rate, plus the constraint
        grid) and a golden section search around each grid maximum; with their frequencies
        (rad/s)."""
        grids: dict = {}
        brackets = {}
        for name in BREAKING_POINTS:
            nyq = math.pi / (self.ts if (name == "speed_open" or self.rate == 1) else self.tp)
            if nyq not in grids:
                w = np.unique(np.concatenate([np.geomspace(1e-2, nyq * 0.99999, n_dense),
                                              self.omega[self.omega < nyq]]))
                grids[nyq] = (w, self.sensitivity(g, w, [k for k in BREAKING_POINTS if self.rate == 1 or
                                                          (k == "speed_open") == (nyq == math.pi / self.ts)]))
            w, sens = grids[nyq]
            s = sens[name]
            i = int(np.argmax(s))
            brackets[name] = [w[max(i - 1, 0)], w[min(i + 1, w.size - 1)], s[i], w[i]]
        # The golden section searches of the four points in lockstep: one sensitivity call per
        # step evaluates every point's two trial frequencies (each value is the point's own at
        # its own frequency: the searches are those of one point at a time).
        names = list(brackets)

        def f(xs):
            sens = self.sensitivity(g, np.asarray(xs, float), names)
            return [float(sens[n][j]) for j, n in enumerate(n for n in names for _ in range(len(xs) // len(names)))]

        gr = (math.sqrt(5) - 1) / 2
        for _ in range(60):
            trial = []
            for n in names:
                a_, b_ = brackets[n][:2]
                trial += [b_ - gr * (b_ - a_), a_ + gr * (b_ - a_)]
            fx = f(trial)
            for k, n in enumerate(names):
                c_, d_ = trial[2 * k], trial[2 * k + 1]
                if fx[2 * k] > fx[2 * k + 1]:
                    brackets[n][1] = d_
                else:
                    brackets[n][0] = c_
        wms = [0.5 * (brackets[n][0] + brackets[n][1]) for n in names]
        out = {}
        for n, wm, fm in zip(names, wms, f(wms)):
            best = max((brackets[n][2], brackets[n][3]), (fm, wm))
            out[n] = float(best[0])
            out[f"w_{n}"] = float(best[1])
        return out

    def crossover(self, g, loop: str = "speed_open") -> float:
        """First frequency (rad/s) where |L| falls through 1 at a breaking point (at a
        multi-rate loop: ``speed_open`` or ``position``)."""
        nyq = math.pi / (self.ts if loop == "speed_open" else self.tp)
        w = np.geomspace(1e-1, nyq * 0.999, 20000)
        mag = np.abs(self.loops(g, w)[loop])
        idx = np.flatnonzero((mag[:-1] >= 1) & (mag[1:] < 1))
        return float(w[idx[0]]) if idx.size else float("nan")

    # closed loop in the time domain
    def _build_casadi(self) -> None:
        if self.rate > 1:
            return self._build_casadi_multirate()
        n, ts, a = self.n, self.ts, self.a_lead
        nd = self.plant.command_delay_samples  # the drive's command delay: a line of nd commands after the states
        nf = 4 * len(self.biquads)  # the filters' memory, last
        npd = 2 * self.delay  # the position loop's pending (speed reference, feed-forward) pairs, before the filters
        g = ca.SX.sym("g", 6)
        X = ca.SX.sym("X", n + 5 + nd + npd + nf)
        r = ca.SX.sym("r", 4)  # position ref (rad), speed ref (rad/s), accel ref (rad/s^2), load (N)
        kp, ki, kv, kip, kvff, kaff = (g[i] for i in range(6))
        x, th_prev, w_f, i_s, u_pend, i_p = X[:n], X[n], X[n + 1], X[n + 2], X[n + 3], X[n + 4]
        theta = ca.dot(ca.DM(self.c_th), x)
        pm = ca.dot(ca.DM(self.c_pos), x)
        w_f1 = self.alpha * w_f + (1 - self.alpha) * (theta - th_prev) / ts
        fmem = X[X.numel() - nf:]
        w_m, fnext = self._filter("speed_measurement", w_f1, fmem)
        e_p = r[0] - pm
        i_p1 = i_p + ts * kip * e_p
        w_ref = kv * e_p + i_p1 + kvff * r[1]
        tau = kaff * self.inertia * r[2]
        pl = X[n + 5 + nd:n + 5 + nd + npd]
        pnext = [w_ref, tau] + [pl[i] for i in range(npd - 2)] if npd else []
        if npd:  # the position loop's computation delay: its oldest pending output is applied
            w_ref, tau = pl[npd - 2], pl[npd - 1]
        u = kp * (w_ref - w_m) + i_s + tau
        i_s1 = i_s + ts * ki * (w_ref - w_m)
        u, fnext = self._filter("torque_command", u, fmem, fnext)
        line = X[n + 5:n + 5 + nd]
        act = line[nd - 1] if nd else u_pend
        x1 = ca.mtimes(ca.DM(self.Ad), x) + ca.DM(self.bu) * act + ca.DM(self.bd) * r[3]
        Xn = ca.vertcat(x1, theta, w_f1, i_s1, u, i_p1, *([u_pend] if nd else []), *[line[i] for i in range(nd - 1)],
                        *pnext, *fnext)
        self.step = ca.Function("cascade_step", [X, r, g], [Xn, e_p * a])
        self.jac = ca.Function("cascade_ab", [g], [ca.jacobian(Xn, X), ca.jacobian(Xn, r)])
        self.nX = n + 5 + nd + npd + nf

    def _filter(self, place: str, x, fmem, fnext=None):
        """The biquads at ``place`` run on ``x`` in order (direct form I, the simulator's
        recursion); returns the output and the filters' next memory (all filters)."""
        fnext = list(fnext) if fnext is not None else [fmem[i] for i in range(fmem.numel())]
        for i, (pl, bq) in enumerate(self.biquads):
            if pl != place:
                continue
            m = fmem[4 * i:4 * i + 4]
            y = bq.b0 * x + bq.b1 * m[0] + bq.b2 * m[1] - bq.a1 * m[2] - bq.a2 * m[3]
            fnext[4 * i:4 * i + 4] = [x, m[0], y, m[2]]
            x = y
        return x, fnext

    def _build_casadi_multirate(self) -> None:
        """The per-speed-sample law of a position loop every N samples (the simulator's
        :meth:`~prsa_ctrl.drive.measurement.PositionLoop.update`): at a position-loop sample
        (input ``active`` = 1) the position is read, the integral advanced by ``Tp kip e`` and
        the speed reference and torque feed-forward computed and used at once; in between
        both are held (zero-order hold over Tp)."""
        n, ts, a = self.n, self.ts, self.a_lead
        nd = self.plant.command_delay_samples
        nf = 4 * len(self.biquads)
        npd = 2 * self.delay  # the pending (speed reference, feed-forward) pairs, shifted at position-loop samples
        g = ca.SX.sym("g", 6)
        X = ca.SX.sym("X", n + 7 + nd + npd + nf)
        act = ca.SX.sym("active")
        # position ref (rad), speed ref (rad/s), accel ref (rad/s^2), load (N), active (0/1)
        r4 = ca.SX.sym("r", 4)
        r = ca.vertcat(r4, act)
        kp, ki, kv, kip, kvff, kaff = (g[i] for i in range(6))
        x, th_prev, w_f, i_s, u_pend, i_p = X[:n], X[n], X[n + 1], X[n + 2], X[n + 3], X[n + 4]
        w_hold, tau_hold = X[n + 5], X[n + 6]
        theta = ca.dot(ca.DM(self.c_th), x)
        pm = ca.dot(ca.DM(self.c_pos), x)
        w_f1 = self.alpha * w_f + (1 - self.alpha) * (theta - th_prev) / ts
        fmem = X[X.numel() - nf:]
        w_m, fnext = self._filter("speed_measurement", w_f1, fmem)
        e_p = r[0] - pm
        i_p1 = i_p + act * self.tp * kip * e_p
        w_new, tau_new = kv * e_p + i_p1 + kvff * r[1], kaff * self.inertia * r[2]
        pl = X[n + 7 + nd:n + 7 + nd + npd]
        pnext = []
        if npd:  # the position loop's computation delay: at its sample the oldest pending output is applied
            shifted = [w_new, tau_new] + [pl[i] for i in range(npd - 2)]
            pnext = [act * shifted[i] + (1 - act) * pl[i] for i in range(npd)]
            w_new, tau_new = pl[npd - 2], pl[npd - 1]
        w_ref = act * w_new + (1 - act) * w_hold
        tau = act * tau_new + (1 - act) * tau_hold
        u = kp * (w_ref - w_m) + i_s + tau
        i_s1 = i_s + ts * ki * (w_ref - w_m)
        u, fnext = self._filter("torque_command", u, fmem, fnext)
        line = X[n + 7:n + 7 + nd]
        cmd = line[nd - 1] if nd else u_pend
        x1 = ca.mtimes(ca.DM(self.Ad), x) + ca.DM(self.bu) * cmd + ca.DM(self.bd) * r[3]
        Xn = ca.vertcat(x1, theta, w_f1, i_s1, u, i_p1, w_ref, tau, *([u_pend] if nd else []),
                        *[line[i] for i in range(nd - 1)], *pnext, *fnext)
        self.step = ca.Function("cascade_step", [X, r, g], [Xn, e_p * a])
        self.jac = ca.Function("cascade_ab", [g, act], [ca.jacobian(Xn, X), ca.jacobian(Xn, r4)])
        self.nX = n + 7 + nd + npd + nf

    def closed_loop_matrices(self, g, active: float = 1.0) -> tuple[NDArray, NDArray]:
        """One speed-loop sample's closed-loop matrices ``(A, B)`` (``X+ = A X + B r``); of a
        multi-rate loop at a position-loop sample (``active = 1``) or in between (0)."""
        A, B = self.jac(list(map(float, g))) if self.rate == 1 else self.jac(list(map(float, g)), float(active))
        return np.asarray(A), np.asarray(B)

    def spectral_radius(self, g) -> float:
        """Largest |closed-loop eigenvalue|; a P position loop (``kip = 0``) leaves its unused
        integral state constant (an undriven eigenvalue 1), which is left out. Of a multi-rate
        loop: the N-th root of the spectral radius of the period's transition matrix (one
        position-loop sample, then N - 1 held)."""
        if self.rate == 1:
            A = self.closed_loop_matrices(g)[0]
            if float(g[3]) == 0.0:  # the position integral is state n + 4
                keep = np.r_[0:self.n + 4, self.n + 5:self.nX]
                A = A[np.ix_(keep, keep)]
            return float(np.max(np.abs(np.linalg.eigvals(A))))
        A1, A0 = self.closed_loop_matrices(g, 1.0)[0], self.closed_loop_matrices(g, 0.0)[0]
        phi = np.linalg.matrix_power(A0, self.rate - 1) @ A1
        if float(g[3]) == 0.0:
            keep = np.r_[0:self.n + 4, self.n + 5:self.nX]
            phi = phi[np.ix_(keep, keep)]
        return float(np.max(np.abs(np.linalg.eigvals(phi))) ** (1.0 / self.rate))

    def inputs(self, kind: str) -> NDArray[np.float64]:
        """Input sequences (4 x N) of the two tuning experiments: ``"move"`` (the profile with
        the move's load step, from the scene's start to 0.05 s after its end) and ``"hold"``
        (the hold step at rest, 0.1 s). Loads are deviations from the linearisation load. A
        multi-rate loop has a fifth row: 1 at the position-loop samples (0, N, 2N, ...)."""
        sc, a, ts = self.spec, self.a_lead, self.ts
        if kind == "move":
            m = sc.motion
            t = np.arange(0.0, m.end_time + 0.05, ts)
            p, v, acc = m.at(t)
            load = np.where(t >= sc.load_at_s, sc.load_n - sc.initial_load_n, 0.0) if sc.load_n != sc.initial_load_n \
                else np.zeros_like(t)
            out = np.vstack([p / a, v / a, acc / a, load])
        else:
            t = np.arange(0.0, 0.1, ts)
            step = sc.hold_step_n if sc.hold_step_n else max(abs(sc.load_n), 100.0)
            out = np.vstack([np.zeros((3, t.size)), np.where(t >= 2 * ts, step, 0.0)])
        if self.rate > 1:  # the position-loop samples, as the simulator runs them (k = 0, N, 2N, ...)
            out = np.vstack([out, (np.arange(t.size) % self.rate == 0).astype(float)])
        return out

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
    #: The drive's fixed loop filters the design was tuned with (LoopFilter; the scene's
    #: ``[filters]``): verified and exported with it.
    filters: tuple = ()
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
                             "rate": self.position.rate, "delay_samples": self.position.delay},
                "ms": self.ms_points, "crossover_rad_s": self.crossover_rad_s, "linear": self.linear,
                "objective": self.objective, "verified": self.verified.as_dict() if self.verified else None,
                "notes": list(self.notes), "solver": self.solver,
                **({"filters": [lf.as_dict() for lf in self.filters]} if self.filters else {})}


def _linear_summary(cm: CascadeModel, g) -> dict:
    em, eh = cm.error(g, "move"), cm.error(g, "hold")
    return {"peak_following_error_m": float(np.max(np.abs(em))), "rms_following_error_m": float(np.sqrt(np.mean(em**2))),
            "holding_deviation_m": float(np.max(np.abs(eh))), "ms_following": float(np.mean(em**2)),
            "ms_holding": float(np.mean(eh**2))}


def cascade_design(cm: CascadeModel, method: str, g, objective: float, notes=None, solver=None) -> CascadeDesign:
    """The design of the cascade ``cm`` at the gains ``g``: its controllers, true Ms at each
    breaking point, crossovers and linear metrics (what the tuners return).

    Parameters
    ----------
    cm : CascadeModel
    method : str
        How the gains were found (``"joint"``, ``"sequential"``, ...).
    g : sequence of float
        The six gains of :data:`CASCADE_GAINS` (N m s/rad, N m/rad, 1/s, 1/s^2, -, -).
    objective : float
        The tuner's objective at ``g``.
    notes : sequence of str, optional
    solver : dict, optional
        The solver's report.

    Returns
    -------
    CascadeDesign
    """
    sc = cm.spec
    speed = PID(float(g[0]), float(g[1]))
    pos = PositionLoop(kv=float(g[2]), ki=float(g[3]), kvff=float(g[4]), kaff=float(g[5]), measured=sc.measured,
                       rate=sc.position_rate, delay=sc.position_delay_samples)
    cross = {"speed_open": cm.crossover(g, "speed_open"), "position": cm.crossover(g, "position")}
    return CascadeDesign(method, speed, pos, cm.ms(g), cross, _linear_summary(cm, g), float(objective),
                         notes=tuple(notes or ()), solver=dict(solver or {}), filters=cm.filters)


def kv_ceiling(spec: CascadeSpec, kv_max: "float | str | None" = None) -> float:
    """The position-gain ceiling of a tuning, 1/s: ``kv_max`` (a float in 1/s or a string with
    its unit, ``"3 (m/min)/mm"``, :func:`prsa_ctrl.options.parse_kv`) or else the spec's
    ``kv_max_per_s``; ``inf`` without either.

    Raises
    ------
    ValueError
        One line naming the value as given and what was expected.
    """
    v = kv_max if kv_max is not None else spec.kv_max_per_s
    if v is None:
        return math.inf
    if isinstance(v, str):
        return parse_kv(v)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not v > 0:
        raise ValueError(f"kv_max = {v!r}; expected a position gain > 0 in 1/s, or a string with its unit, "
                         "e.g. \"3 (m/min)/mm\"")
    return float(v)


def sequential_design(plant: "Plant", spec: CascadeSpec, cm: CascadeModel | None = None,
                      ratios=(5.0, 6.0, 7.0, 8.0, 9.0, 10.0), *, kv_max: "float | str | None" = None) -> CascadeDesign:
    """The rule-of-thumb baseline (module docstring): speed PI tuned alone at ``spec.ms_max``
    (:func:`prsa_ctrl.tuning.generic.tune_loops`, IAE of the load step on the drive loop), position P
    at ``crossover / ratio`` for the smallest ``ratio`` in ``ratios`` that keeps every Ms within
    the bound, ``kvff = kaff = 1``; the position gain at most ``kv_max`` (:func:`kv_ceiling`:
    1/s or a string with its unit; default the spec's ``kv_max_per_s``).

    Returns
    -------
    CascadeDesign
    """
    kv_cap = kv_ceiling(spec, kv_max)
    cm = cm or CascadeModel(plant, spec)
    model = plant_model(plant, spec.fidelity)
    a_, b_, c_, _, _ = linear_core(plant, cm.w_lin, spec.load_n, spec.fidelity)
    step = spec.hold_step_n or max(abs(spec.load_n), 100.0)
    lp = drive_loop(a_, b_, c_[model.output_names.index("nut_speed")], model.index("theta_nut"), ts=plant.sample_time_s,
                    speed_filter=plant.speed_filter_s, tf=DERIVATIVE_FILTER_SAMPLES * plant.sample_time_s, horizon=0.1, step=step,
                    command_delay_samples=plant.command_delay_samples, **({"filters": cm.filters} if cm.filters else {}))
    ms_max = spec.ms_max

    def worst(g) -> float:
        pk = cm.ms(g)
        return max(pk[k] for k in BREAKING_POINTS) if cm.spectral_radius(g) < 1 else math.inf

    def attempt(ms_speed: float):
        """Speed PI at ``ms_speed``; the smallest ratio that keeps every Ms <= ms_max (None if
        even the largest does not) and the worst Ms at the largest ratio."""
        res = tune_loops([lp], objective="iae", controller="pi", ms_max=ms_speed)
        kp, ki = res.pid.kp, res.pid.ki
        wc = cm.crossover([kp, ki, 0.0, 0.0, 0.0, 0.0], "speed_open")
        slowest = [kp, ki, min(wc / max(ratios), kv_cap), 0.0, 1.0, 1.0]
        w_slow = worst(slowest)
        if w_slow > ms_max:
            return res, wc, None, slowest, w_slow
        for ratio in sorted(ratios)[:-1]:
            g = [kp, ki, min(wc / ratio, kv_cap), 0.0, 1.0, 1.0]
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
    if g[2] >= kv_cap:
        notes.append(f"position gain at its ceiling kv_max = {kv_cap:.6g} 1/s ({kv_cap * 0.06:.4g} (m/min)/mm), "
                     f"below crossover/{ratio:g}")
    if ms_speed < ms_max:
        notes.append(f"the speed loop tuned alone at Ms {ms_max:g} gives Ms > {ms_max:g} once the position loop is "
                     f"closed (any ratio in {min(ratios):g}..{max(ratios):g}): re-tuned at Ms {ms_speed:.4g} for equal Ms")
    return cascade_design(cm, "sequential", g, spec.weight_following + spec.weight_holding, notes,
                   {"speed_tuner_status": res.status, "ratio": ratio, "speed_ms_bound": ms_speed})


def gains_from_solution(x, lbx, ubx, free, scale) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The scaled NLP solution projected onto its bounds, and the six gains it gives
    (:data:`CASCADE_GAINS`). Ipopt may end a hair outside its bounds (``kaff = -9e-9`` for a
    1 um move), which :class:`~prsa_ctrl.drive.measurement.PositionLoop` rightly refuses.

    >>> x, g = gains_from_solution([1.0, 1.0, 1.0, 1.0, -9e-9], [1e-3] * 3 + [0.0] * 2, [1e3] * 3 + [1.5] * 2,
    ...                             [0, 1, 2, 4, 5], [0.08, 10.0, 40.0, 160.0, 1.0, 1.0])
    >>> float(g[5]), float(g[2])
    (0.0, 40.0)
    """
    x = np.clip(np.asarray(x, float).ravel(), np.asarray(lbx, float), np.asarray(ubx, float))
    gv = np.zeros(6)
    for k, i in enumerate(free):
        gv[i] = x[k] * scale[i]
    return x, gv


def tune_cascade(plant: "Plant", spec: CascadeSpec, *, baseline: CascadeDesign | None = None,
                 cm: CascadeModel | None = None, max_rounds: int = 8, max_iter: int = 300,
                 kv_max: "float | str | None" = None) -> CascadeDesign:
    """Joint tuning of the whole cascade in one NLP (module docstring), started from the
    sequential baseline.

    Parameters
    ----------
    plant : Plant
    spec : CascadeSpec
        The move's numbers (:meth:`prsa_ctrl.studies.movescene.MoveScene.cascade_spec`).
    baseline : CascadeDesign, optional
        The start and the normalisation (default :func:`sequential_design`).
    max_rounds : int
        Most re-solves with frequencies added where the verified Ms exceeds the bound.
    max_iter : int
        Ipopt iteration budget per solve.
    kv_max : float (1/s) or str, optional
        Ceiling on the position gain ``Kv``, a bound of the NLP (:func:`kv_ceiling`; a string
        with its unit, ``"3 (m/min)/mm"``; default the spec's ``kv_max_per_s``, else none).

    Returns
    -------
    CascadeDesign
        With the verified (dense-grid, refined) Ms at all breaking points.
    """
    kv_cap = kv_ceiling(spec, kv_max)
    cm = cm or CascadeModel(plant, spec)
    baseline = baseline or sequential_design(plant, spec, cm, kv_max=kv_max)
    g0 = np.asarray(baseline.gains, float)
    sc = spec
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
        m2 = sc.ms_max ** 2 * (1 - 1e-4)
        if cm.rate > 1:
            cons = multirate_constraints(cm, g, g0, np.array(omegas), m2)
        else:
            P = cm.parts(np.array(omegas))
            def c(v):
                return (ca.DM(v.real), ca.DM(v.imag))
            G, Gp, W, csi, cpi, dp = (c(P[k]) for k in ("G", "Gp", "W", "cs_i", "cp_i", "dp"))
            cs = (g[0] + g[1] * csi[0], g[1] * csi[1])
            cp = cplx_mul((g[2] + g[3] * cpi[0], g[3] * cpi[1]), dp)
            q = cplx_mul(cplx_mul(Gp, cs), cp)
            r = cplx_mul(cplx_mul(W, G), cs)
            one_q = (1 + q[0], q[1])
            one_r = (1 + r[0], r[1])
            d = (1 + q[0] + r[0], q[1] + r[1])
            cons = [m2 * abs2(d) - abs2(one_q), m2 * abs2(one_r) - 1, m2 * abs2(d) - abs2(one_r),
                    m2 * abs2(d) - 1]
        lbg = [0.0] * sum(int(ci.numel()) for ci in cons)
        if sc.bandwidth_ratio is not None:
            cons.append(g[0] / cm.inertia - sc.bandwidth_ratio * g[2])
            lbg.append(0.0)
        lbx = [1e-3] * len(free)
        ubx = [1e3] * len(free)
        for k, i in enumerate(free):
            if i in (4, 5):
                lbx[k], ubx[k] = 0.0, 1.5
            if i == 2 and math.isfinite(kv_cap):
                ubx[k] = min(ubx[k], kv_cap / scale[2])
                lbx[k] = min(lbx[k], 0.5 * ubx[k])  # a baseline far above the ceiling: the bounds stay ordered
        x = np.clip(x, lbx, ubx)
        nlp = {"x": y, "f": J, "g": ca.vertcat(*cons)}
        solver = ca.nlpsol("cascade", "ipopt", nlp, {"ipopt.print_level": 0, "print_time": False,
                                                    "ipopt.sb": "yes", "ipopt.max_iter": int(max_iter),
                                                    "ipopt.hessian_approximation": "limited-memory",
                                                    "ipopt.tol": 1e-8})
        sol = solver(x0=x, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ca.inf)
        st = solver.stats()
        x, gv = gains_from_solution(sol["x"], lbx, ubx, free, scale)
        solver_info = {"status": st["return_status"], "iterations": int(st["iter_count"]), "rounds": rnd + 1,
                       "grid_points": len(omegas)}
        pk = cm.ms(gv)
        worst = max(BREAKING_POINTS, key=lambda k: pk[k])
        stable = cm.spectral_radius(gv) < 1
        if stable and pk[worst] <= sc.ms_max * (1 + MS_EXCESS_RTOL):
            best = gv
            break
        # (a multi-rate loop's constraints are at the position-loop frequencies: the speed loop's
        # peak frequency is folded into 0..pi/Tp, where its alias is constrained)
        wp = 2 * math.pi / cm.tp
        omegas = sorted(set(omegas) | {abs((pk[f"w_{k}"] + wp / 2) % wp - wp / 2) if cm.rate > 1 else pk[f"w_{k}"]
                                       for k in BREAKING_POINTS})
        notes.append(f"round {rnd + 1}: verified Ms {pk[worst]:.5g} at {worst} (w = {pk['w_' + worst]:.5g} rad/s)"
                     f"{'' if stable else ', unstable'}; frequencies added")
    if best is None:
        notes.append("joint solve did not verify within the Ms bound; the baseline is returned")
        return cascade_design(cm, "joint (failed: baseline)", g0, sc.weight_following + sc.weight_holding, notes, solver_info)
    if best[2] >= kv_cap * (1 - 1e-6):
        notes.append(f"position gain at its ceiling kv_max = {kv_cap:.6g} 1/s ({kv_cap * 0.06:.4g} (m/min)/mm)")
    lin = _linear_summary(cm, best)
    obj = sc.weight_following * lin["ms_following"] / e_f0 + sc.weight_holding * lin["ms_holding"] / e_h0
    return cascade_design(cm, "joint", best, obj, notes, solver_info)
