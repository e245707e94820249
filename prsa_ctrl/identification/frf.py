"""Frequency-response fits: the model linearised at a measurement's speed and load, sampled as
the drive measures it (command held over a sample, speed the backward difference of the
angle), fitted on the log response (:func:`fit_frf`); the model's response
(:func:`frf_response`), the compliant model's axial mode (:func:`axial_mode`) and the fit %
of a response (:func:`frf_fit_percent`).
"""

from __future__ import annotations

import math
from typing import Sequence

import casadi as ca
import numpy as np
from numpy.typing import NDArray
from scipy.linalg import eigvals
from scipy.optimize import least_squares

from ..drive.sampled import zoh
from ..errors import FitError
from ..plant.plantfile import Plant, load_plant
from .common import (DELAY_KEY, FRF_KEYS, FRF_KEYS_COMPLIANT, PSEUDO_KEYS, UNCERTAINTY_MODES, FitResult, check_keys,
                     default_keys,
                     checked_inputs, finish_fit, frf_sample_time, info_split, key_bounds, symbolic_rhs)
from .data import FrfRecord

__all__ = ["fit_frf", "frf_response", "axial_mode", "frf_fit_percent", "FRF_SPREAD_MIN", "linearised", "write_delay", "refuse_beyond_bracket"]

def _plant_value(plant: Plant, key: str, delay_s: float = 0.0) -> float:
    """Initial value of a fitted key (the delay is no plant key: ``delay_s``)."""
    return delay_s if key == DELAY_KEY else plant.values[key]


_LIN_CACHE: dict = {}


class _Linear:
    """``(speed, load, p) -> (A, B)`` of a fidelity's model linearised at steady speed and load,
    with the values of the plant keys ``keys`` as ``p``; ``i_th`` and ``i_w`` index the nut angle
    and speed states. Built once per plant, key set and fidelity (:func:`_linear`)."""

    def __init__(self, plant: Plant, keys: Sequence[str], fidelity: str):
        self.plant, self.keys, self.fidelity = plant, tuple(keys), fidelity
        f, names = symbolic_rhs(plant, keys, fidelity)
        self.names = names
        self.i_th, self.i_w = names.index("theta_nut"), names.index("omega_nut")
        i_w, i_tau = self.i_w, names.index("tau_motor")
        w0, f0 = ca.SX.sym("w0"), ca.SX.sym("f0")
        p = ca.SX.sym("p", len(keys))
        x = ca.SX.sym("x", len(names))
        u = ca.SX.sym("u", 2)
        xdot = f(x, u, p)
        # a rigid linear axis's compliant model is its rigid one (it carries no compliance)
        self.rigid = fidelity == "rigid" or "delta_screw" not in names
        self.screw_driven = "x_roller" in names and "omega_cage" not in names
        self.two_mass_axis = not self.rigid and "x_roller" not in names  # the two-mass linear axis
        if self.two_mass_axis:
            # steady state at speed w0 and load f0: both masses at w0; the spring's compression and
            # the drive force z make both accelerations zero (affine in z away from the stick band)
            i_d, i_v = names.index("delta_screw"), names.index("v_screw")
            z = ca.SX.sym("z", 2)
            xs = [0] * len(names)
            xs[i_w], xs[i_v], xs[i_d], xs[i_tau] = w0, w0, z[0], z[1]
            x_op = ca.vertcat(*xs)
            r = f(x_op, ca.vertcat(z[1], f0), p)[[i_w, i_v]]
            z0 = -ca.solve(ca.substitute(ca.jacobian(r, z), z, ca.DM.zeros(2)), ca.substitute(r, z, ca.DM.zeros(2)))
            sub = lambda e: ca.substitute(e, ca.vertcat(x, u), ca.vertcat(ca.substitute(x_op, z, z0), z0[1], f0))  # noqa: E731
            self._rigid = ca.Function("lin", [w0, f0, p], [sub(ca.jacobian(xdot, x)), sub(ca.jacobian(xdot, u[0]))])
            return
        if self.rigid:
            x_free = ca.vertcat(*[0 if i != i_w else w0 for i in range(len(names))])
            acc0 = ca.substitute(xdot[i_w], ca.vertcat(x, u), ca.vertcat(x_free, 0, f0))
            d_acc = ca.substitute(ca.jacobian(xdot[i_w], x[i_tau]), ca.vertcat(x, u), ca.vertcat(x_free, 0, f0))
            tau0 = -acc0 / d_acc  # the rigid nut's acceleration is affine in the motor torque
            x_op = ca.vertcat(*[tau0 if i == i_tau else x_free[i] for i in range(len(names))])
            sub = lambda e: ca.substitute(e, ca.vertcat(x, u), ca.vertcat(x_op, tau0, f0))  # noqa: E731
            self._rigid = ca.Function("lin", [w0, f0, p], [sub(ca.jacobian(xdot, x)), sub(ca.jacobian(xdot, u[0]))])
            return
        # Compliant: the steady state at speed w0 and load f0 has theta free, the roller assembly
        # and the screw at the screw speed a w0; unknowns z = (cage speed, x_roller, delta_screw,
        # motor torque = command) make the nut, cage, roller and screw accelerations zero.
        # Screw-driven (roller or ball screw): the shaft does not move axially at steady state
        # (v_roller = 0), the carriage moves at a w0; unknowns z = (shaft displacement, helix
        # compression, motor torque) make the rotor, shaft and carriage accelerations zero.
        a = plant.lead_per_rad
        idx = {n: i for i, n in enumerate(names)}

        xs = [0] * len(names)
        if self.screw_driven:
            z = ca.SX.sym("z", 3)
            xs[idx["omega_nut"]], xs[idx["v_screw"]] = w0, a * w0
            xs[idx["x_roller"]], xs[idx["delta_screw"]], xs[idx["tau_motor"]] = z[0], z[1], z[2]
            rows = [idx[n] for n in ("omega_nut", "v_roller", "v_screw")]
        else:
            z = ca.SX.sym("z", 4)
            xs[idx["omega_nut"]], xs[idx["v_roller"]], xs[idx["v_screw"]] = w0, a * w0, a * w0
            xs[idx["omega_cage"]], xs[idx["x_roller"]], xs[idx["delta_screw"]], xs[idx["tau_motor"]] = z[0], z[1], z[2], z[3]
            rows = [idx[n] for n in ("omega_nut", "omega_cage", "v_roller", "v_screw")]
        x_op = ca.vertcat(*xs)
        r = f(x_op, ca.vertcat(z[-1], f0), p)[rows]
        self._steady = ca.Function("steady", [z, w0, f0, p], [r, ca.jacobian(r, z)])
        self._state = ca.Function("state", [z, w0], [x_op])
        self._jac = ca.Function("lin_ab", [x, u, p], [ca.jacobian(xdot, x), ca.jacobian(xdot, u[0])])

    def _guess(self, speed: float, load: float, pv) -> np.ndarray:
        """Initial steady state of the compliant model: rigid cage ratio, Hertz deflections for
        the load on both interfaces, the rigid holding torque (screw-driven: the springs'
        deflections under the load, the rigid holding torque)."""
        pl = self.plant
        vals = dict(pl.values)
        vals.update({k: float(v) for k, v in zip(self.keys, pv)})
        tau = load * pl.lead_per_rad / vals["friction.efficiency"] + vals["friction.no_load_torque_n_m"] \
            + vals["friction.viscous_n_m_s_per_rad"] * speed + vals.get("friction.torque_offset_n_m", 0.0) \
            + vals.get("friction.viscous_offset_n_m_s_per_rad", 0.0) * abs(speed)
        if self.screw_driven:
            k_h = pl.axial_stiffness_n_per_m()  # a start only: the series stiffness bounds the helix one from below
            k_b = vals["axis.bearing_stiffness_n_per_um"] * 1e6
            return np.array([-load / k_b, load / k_h, tau])
        k_si = vals["contact.stiffness_n_per_mm_e"] * 1000.0 ** vals["contact.exponent"]
        e = vals["contact.exponent"]
        cb = math.cos(pl.flank_angle_rad)
        out = []
        for helix in (pl.helix_nut_rad, pl.helix_screw_rad):
            c = cb * math.cos(helix)
            d = (abs(load) / (pl.n_contacts * k_si * c ** (e + 1))) ** (1.0 / e) / c
            out.append(d if load >= 0 else -(d + vals["thread.backlash_mm"] * 1e-3))
        return np.array([speed * pl.cage_ratio, -out[0], out[1], tau])

    def __call__(self, speed: float, load: float, pv):
        pv = np.asarray(pv, float)
        if self.rigid or self.two_mass_axis:
            a, b = self._rigid(speed, load, pv)
            return np.asarray(a, float), np.asarray(b, float)
        if not self.screw_driven and abs(load) < 1e-9 * self.plant.rated_load_n:
            raise ValueError(f"load_n = {load!r} for a compliant frequency response; expected the measurement's "
                             "axial load (> 0 N): without load the thread contacts sit in the backlash and no "
                             "axial mode exists")
        z = self._guess(speed, load, pv)
        zs = np.abs(z) + (np.array([1e-9, 1e-9, 1e-3 * self.plant.torque_limit]) if self.screw_driven else
                          np.array([1.0, 1e-9, 1e-9, 1e-3 * self.plant.torque_limit]))
        r, jz = (np.asarray(m, float).ravel() if i == 0 else np.asarray(m, float) for i, m in
                 enumerate(self._steady(z, speed, load, pv)))
        for _ in range(60):  # damped Newton, bounded
            step = -np.linalg.lstsq(jz * zs, r, rcond=None)[0] * zs
            nr, alpha = np.linalg.norm(r), 1.0
            for _ in range(30):
                r1, j1 = self._steady(z + alpha * step, speed, load, pv)
                r1 = np.asarray(r1, float).ravel()
                if np.all(np.isfinite(r1)) and np.linalg.norm(r1) <= (1 - 1e-4 * alpha) * nr:
                    break
                alpha *= 0.5
            z = z + alpha * step
            r, jz = r1, np.asarray(j1, float)
            if np.all(np.abs(alpha * step) <= 1e-13 * zs):
                break
        if not np.all(np.isfinite(z)) or np.linalg.norm(r) > 1e-6 * max(nr, 1.0) and np.linalg.norm(r) > 1e-3:
            raise FitError(f"no steady state of the compliant model at {speed:g} rad/s and {load:g} N "
                           f"(residual {np.linalg.norm(r):.3g}); remedy: check the operating point (--frf-speed, "
                           "--frf-load) or start from a closer base plant (--plant)")
        x_op = np.asarray(self._state(z, speed), float).ravel()
        a, b = self._jac(x_op, [z[-1], load], pv)
        return np.asarray(a, float), np.asarray(b, float)


def _linear(plant: Plant, keys: Sequence[str], fidelity: str = "rigid") -> _Linear:
    ck = (id(plant), tuple(keys), fidelity)
    hit = _LIN_CACHE.get(ck)
    if hit is not None and hit[0] is plant:
        return hit[1]
    lin = _Linear(plant, keys, fidelity)
    if len(_LIN_CACHE) > 8:
        _LIN_CACHE.clear()
    _LIN_CACHE[ck] = (plant, lin)
    return lin


def linearised(plant: Plant, keys: Sequence[str] = (), fidelity: str = "compliant") -> _Linear:
    """``(speed_rad_s, load_n, values) -> (A, B)``: the fidelity's model linearised at steady speed
    and load with the plant keys ``keys`` set to ``values`` (file units); ``.rigid`` says whether
    it is the rigid model (a linear axis's compliant one is), ``.i_w`` indexes the motor speed.
    Built once per plant, key set and fidelity."""
    return _linear(plant, keys, fidelity)


def _frf_eval(lin: _Linear, p, frequency_hz, speed, load, ts, delay_s):
    """Model response torque command -> nut speed at ``frequency_hz`` (sampled when ``ts > 0``)
    with a command delay of ``delay_s`` seconds."""
    a, b = lin(speed, load, p)
    nx = a.shape[0]
    i_th, i_w = lin.i_th, lin.i_w
    s = 2j * np.pi * np.asarray(frequency_hz, float)
    eye = np.eye(nx)[None, :, :]
    if ts <= 0:  # continuous: C (sI - A)^-1 B on the speed
        rhs = np.broadcast_to(b[:, :1].astype(complex), (len(s), nx, 1))
        out = np.linalg.solve(s[:, None, None] * eye - a[None], rhs)[:, i_w, 0]
    else:  # the drive's sampled response: command held over a sample, speed = backward angle difference / ts
        phi, gam = zoh(a, b[:, :1], ts)
        gam = gam[:, 0]
        z = np.exp(s * ts)
        rhs = np.broadcast_to(gam[:, None].astype(complex), (len(z), nx, 1))
        th = np.linalg.solve(z[:, None, None] * eye - phi[None], rhs)[:, i_th, 0]
        out = (1 - 1 / z) / ts * th
    if delay_s:
        out = out * np.exp(-s * delay_s)
    if not np.all(np.isfinite(out)) or np.any(out == 0):
        raise FitError("model frequency response not finite; remedy: start from a closer base plant (--plant)")
    return out


def frf_response(
    plant: Plant,
    frequency_hz,
    *,
    speed_rad_s: float = 30.0,
    load_n: float = 0.0,
    sample_time_s: float | None = None,
    delay_samples: int = 0,
    delay_s: float = 0.0,
    fidelity: str = "rigid",
) -> NDArray[np.complex128]:
    """Frequency response torque command (N m) -> nut speed (rad/s) of the model at speed.

    Parameters
    ----------
    plant : Plant
    frequency_hz : array, Hz
    speed_rad_s : float, rad/s
        Steady nut speed of the linearisation.
    load_n : float, N
        Axial load (the compliant fidelity needs one: it closes the thread contacts).
    sample_time_s : float, s, optional
        The drive's sample time (default the plant's ``sensor.sample_time_s``): the response is
        the sampled one, command held over a sample and speed the backward difference of the
        angle; 0 gives the continuous response.
    delay_samples : int
        Extra command delay, samples.
    delay_s : float, s
        Extra command delay, seconds (added to ``delay_samples``).
    fidelity : {"rigid", "compliant"}
        Model linearised: rigid (inertia and current loop) or compliant (with the thread
        contacts' axial modes, :func:`axial_mode`).

    Returns
    -------
    ndarray of complex, (rad/s)/(N m)

    Examples
    --------
    >>> from prsa_ctrl import load_plant
    >>> import warnings; warnings.simplefilter("ignore")
    >>> p = load_plant()
    >>> g = frf_response(p, [10.0], sample_time_s=0.0)
    >>> round(float(abs(g[0]) * 2 * np.pi * 10 * p.reflected_inertia_kg_m2), 2)  # 1 / (J s) at 10 Hz
    1.0
    """
    if fidelity not in ("rigid", "compliant"):
        raise ValueError(f"fidelity = {fidelity!r}; expected 'rigid' or 'compliant' for a frequency response")
    lin = _linear(plant, (), fidelity)
    ts = plant.sample_time_s if sample_time_s is None else float(sample_time_s)
    delay = float(delay_s) + (int(delay_samples) * ts if ts > 0 else 0.0)
    return _frf_eval(lin, np.zeros(0), frequency_hz, speed_rad_s, load_n, ts, delay)


def axial_mode(plant: Plant, *, speed_rad_s: float = 30.0, load_n: float = 800.0) -> dict:
    """The compliant model's axial mode as torque command -> nut speed sees it.

    The screw (with its load mass) on the thread-contact stiffness, linearised at the speed and
    load: the lowest oscillatory pole pair (resonance) and zero pair (anti-resonance) of the
    response, and how much the mode changes the response against the rigid model (infinitely
    stiff contacts, the same inertia reflected through the lead).

    Parameters
    ----------
    plant : Plant
    speed_rad_s : float, rad/s
    load_n : float, N
        Axial load (> 0: it closes the contacts; the linearised stiffness grows with it).

    Returns
    -------
    dict
        ``resonance_hz``, ``damping_ratio``, ``antiresonance_hz``, ``reflected_axial_inertia_ratio``
        (screw mass through the lead over the nut inertia), ``max_effect_db`` and
        ``max_effect_deg`` (largest change of magnitude and phase against the rigid model up to
        the Nyquist frequency of ``sensor.sample_time_s``, continuous response) and ``at_hz``.

    Examples
    --------
    >>> from prsa_ctrl import load_plant
    >>> import warnings; warnings.simplefilter("ignore")
    >>> m = axial_mode(load_plant())
    >>> round(m["resonance_hz"], -2), m["max_effect_db"] < 0.5
    (2400.0, True)
    """
    lin = _linear(plant, (), "compliant")
    if lin.rigid:
        raise ValueError(f"{plant.name}: mechanism = {plant.mechanism!r} carries no axial compliance (its compliant "
                         "model is the rigid one); expected a screw mechanism (inverted-roller-screw, roller-screw, "
                         "ball-screw) or a linear axis with axis.load_mass_kg > 0, or fit a two-mass model to the "
                         "response (prsa_ctrl.identification.twomass)")
    a, b = lin(speed_rad_s, load_n, np.zeros(0))
    nx = a.shape[0]
    ev = np.linalg.eigvals(a)
    osc = sorted((e for e in ev if e.imag > 1e-3 * abs(e)), key=abs)
    if not osc:
        raise ValueError(f"{plant.name}: no oscillatory axial mode at {load_n:g} N; expected a loaded contact")
    res = osc[0]
    c = np.zeros(nx)
    c[lin.i_w] = 1.0
    mm = np.block([[a, b[:, :1]], [c[None, :], np.zeros((1, 1))]])
    nn = np.zeros_like(mm)
    nn[:nx, :nx] = np.eye(nx)
    with np.errstate(all="ignore"):
        zeros = eigvals(mm, nn)
    zeros = sorted((z for z in zeros if np.isfinite(z) and z.imag > 1e-3 * abs(z)), key=abs)
    f_nyq = 0.5 / plant.sample_time_s
    f = np.unique(np.concatenate([np.geomspace(1.0, f_nyq, 600), abs(res) / 2 / np.pi * np.linspace(0.9, 1.1, 401)]))
    f = f[f <= f_nyq]
    g = frf_response(plant, f, speed_rad_s=speed_rad_s, load_n=load_n, sample_time_s=0.0, fidelity="compliant")
    g0 = frf_response(plant, f, speed_rad_s=speed_rad_s, load_n=load_n, sample_time_s=0.0, fidelity="rigid")
    d = np.log(g / g0)
    i = int(np.argmax(np.abs(d)))
    return {
        "resonance_hz": float(abs(res) / (2 * np.pi)),
        "damping_ratio": float(-res.real / abs(res)),
        "antiresonance_hz": float(abs(zeros[0]) / (2 * np.pi)) if zeros else float("nan"),
        "reflected_axial_inertia_ratio": _axial_ratio(plant),
        "max_effect_db": float(20 / math.log(10) * np.max(np.abs(d.real))),
        "max_effect_deg": float(np.degrees(np.max(np.abs(d.imag)))),
        "at_hz": float(f[i]),
    }


def _axial_ratio(plant: Plant) -> float:
    """The translating mass through the lead over the rotating inertia at the motor: the screw
    over the nut (inverted roller screw), the carriage over the rotor with the screw
    (screw-driven), the load mass over the motor side (a two-mass linear axis)."""
    v, a2 = plant.values, plant.lead_per_rad**2
    if plant.mechanism == "linear-axis":  # the load mass over the motor side's
        return float(v["axis.load_mass_kg"] / (v["axis.mass_kg"] - v["axis.load_mass_kg"]))
    if plant.screw_driven:
        return float(v["axis.moving_mass_kg"] * a2 / (v["axis.motor_inertia_kg_m2"] + v["axis.screw_inertia_kg_m2"]))
    return float(v["screw.mass_kg"] * a2 / v["nut.inertia_kg_m2"])


#: A response whose log varies by less than this (RMS, nepers and radians) has no spread to
#: normalise a fit % by (a constant response: round-off gave "fit -6.4e17 %").
FRF_SPREAD_MIN = 1e-6


def frf_fit_percent(measured, model) -> float:
    """Fit % of a frequency response on its complex logarithm (magnitude and phase alike); NaN
    when the measured response does not vary (RMS spread of its log below :data:`FRF_SPREAD_MIN`)."""
    lm, lg = np.log(measured), np.log(model)
    d = np.angle(np.exp(1j * (lm.imag - lg.imag)))
    err = np.sqrt(np.sum((lm.real - lg.real) ** 2 + d**2))
    ref = np.sqrt(np.sum((lm.real - lm.real.mean()) ** 2 + (np.unwrap(lm.imag) - np.unwrap(lm.imag).mean()) ** 2))
    return float(100.0 * (1.0 - err / ref)) if ref > FRF_SPREAD_MIN * math.sqrt(len(lm)) else float("nan")


def refuse_beyond_bracket(delay: dict | None, sample_time_s: float) -> None:
    """Raise :class:`~prsa_ctrl.errors.FitError` when an FRF fit's command delay (``value`` in s)
    ended at the top of its bracket (``at_bound == "upper"``): the response lags its command at
    least that much, and the whole samples written would be the bracket's, not the response's
    (a response 12 samples late fitted with the default bracket of 0 to 10 samples wrote 10 with
    exit 0 and fit 86 %). A delay at the bracket's bottom (none beyond the computation delay) is
    a finding, not a bound, and passes. (Only :func:`fit_frf`'s delay has a top: the two-mass
    structure fit bounds it below alone.)"""
    if not delay or delay.get("at_bound") != "upper":
        return
    raise FitError(f"no plant written: the command delay is held at the top of its bracket, {delay['value']:.4g} s "
                   f"({delay['value'] / sample_time_s:.4g} samples of {sample_time_s:.4g} s): the response lags its "
                   "command at least that much and the fit cannot say by how much more; expected a delay inside the "
                   "bracket: move it with --delay-samples N (the bracket is N to N + 10 samples)")


def fit_frf(
    frf: Sequence[FrfRecord],
    plant: Plant | None = None,
    *,
    keys: Sequence[str] | None = None,
    fidelity: str = "rigid",
    delay_samples: int = 0,
    max_nfev: int = 200,
    keep_unidentified: bool = True,
    uncertainty: str = "keep",
    scan_stiffness: bool = True,
    command_logged: str = "applied",
    scan_delay: bool = True,
) -> FitResult:
    """Fit plant parameters to measured frequency responses (torque command -> nut speed).

    The model response is the model linearised at each record's speed and load, sampled as the
    drive measures it (:func:`frf_response`). The residual of a point is the complex logarithm
    of model / measured (log magnitude and wrapped phase), weighted by the coherence
    ``gamma^2``: the log-response variance is proportional to ``(1 - gamma^2) / gamma^2``
    (Bendat & Piersol), so the weight is ``sqrt(gamma^2 / (1 - gamma^2))`` (capped at coherence
    0.999); without coherence all points weigh the same. Bounded least squares
    (``scipy.optimize.least_squares``, trust-region reflective) on scaled parameters; 95 % CIs
    from the Jacobian at the optimum with the residual variance. A fitted contact stiffness
    starts from the best point of a log-spaced scan of its range (a narrow resonance gives the
    least-squares problem local minima).

    Parameters
    ----------
    frf : sequence of FrfRecord
    plant : Plant, optional
        Base plant and initial guess.
    keys : sequence of str, optional
        Keys to fit (default :data:`FRF_KEYS`, with the compliant fidelity
        :data:`FRF_KEYS_COMPLIANT`). ``drive.command_delay_s`` fits a continuous command delay
        (s, the phase slope ``-w T_d``; it replaces ``delay_samples``, which then only sets its
        initial value); the contact keys need ``fidelity="compliant"``.
    fidelity : {"rigid", "compliant"}
        Model linearised. The compliant model shows the axial mode (:func:`axial_mode`); a
        warning names ``contact.stiffness_n_per_mm_e`` when the responses do not reach the mode
        or the mode changes them by less than their noise.
    delay_samples : int
        Extra command delay, samples.
    command_logged : {"applied", "computed"}
        How the command the responses start from was logged
        (:data:`prsa_ctrl.identification.delay.CONVENTIONS`). With ``drive.command_delay_s``
        fitted, the fitted plant carries the delay: ``drive.command_delay_samples`` the whole
        samples of ``T_d`` (less the computation delay of a computed command) and the rest of
        ``T_d`` added to the current loop's lag (``drive.current_loop_bandwidth_hz`` written
        as ``1 / (2 pi (1 / (2 pi f_c) + rest))``); ``FitResult.delay["plant_file"]`` says so.
    max_nfev : int
        Budget of model evaluations.
    keep_unidentified : bool
        Keys the responses cannot inform keep the base value (see :func:`fit_plant`).
    uncertainty : {"keep", "fit"}
        The fitted keys' ``[uncertainty]`` entries (see :func:`fit_plant`).
    scan_stiffness : bool
        Start a fitted contact stiffness from the best point of a scan of its range (default);
        False: from the plant's value (a start that already sits at the mode, e.g. the two-mass
        mapping of :func:`prsa_ctrl.identification.frfplant.fit_frf_structure`).
    scan_delay : bool
        With ``drive.command_delay_s`` fitted, start it from the best point of a scan of its
        bracket in quarter samples (default: the wrapped phase is periodic in the delay, and one
        start stopped in another period); False: from ``delay_samples`` + 0.25 (a start already in
        the delay's period). A delay that ends at the bracket's top has no interval (undecided).

    Returns
    -------
    FitResult
    """
    plant = load_plant() if plant is None else plant
    frf = list(frf)
    if not frf:
        raise ValueError("frf = []; expected at least one frequency response")
    frf = checked_inputs([], [], frf, plant)[2]
    if uncertainty not in UNCERTAINTY_MODES:
        raise ValueError(f"uncertainty = {uncertainty!r}; expected one of {', '.join(map(repr, UNCERTAINTY_MODES))}")
    if fidelity not in ("rigid", "compliant"):
        raise ValueError(f"fidelity = {fidelity!r}; expected 'rigid' or 'compliant' for a frequency-response fit")
    keys = check_keys(default_keys(plant, FRF_KEYS_COMPLIANT) if keys is None and fidelity == "compliant" else
                       default_keys(plant, FRF_KEYS) if keys is None else keys, fidelity, plant)
    if not (isinstance(delay_samples, int) and 0 <= delay_samples <= 10):
        raise ValueError(f"delay_samples = {delay_samples!r}; expected an integer 0..10")
    ts_fit = min(frf_sample_time(fr, plant) or plant.sample_time_s for fr in frf)
    bounds = []
    for k in keys:
        if k == DELAY_KEY:
            bounds.append((0.0, (delay_samples + 10) * ts_fit, ts_fit))
        else:
            bounds.append(key_bounds(plant, k, ts_fit))
    scales = np.array([b[2] for b in bounds])
    lo = np.array([b[0] for b in bounds]) / scales
    hi = np.array([b[1] for b in bounds]) / scales
    s0 = np.clip(np.array([_plant_value(plant, k, (delay_samples + 0.25) * ts_fit) for k in keys]) / scales, lo, hi)
    pkeys = [k for k in keys if k not in PSEUDO_KEYS]
    i_p = [keys.index(k) for k in pkeys]
    i_d = keys.index(DELAY_KEY) if DELAY_KEY in keys else None
    lin = _linear(plant, pkeys, fidelity)
    weights = []
    for fr in frf:
        if fr.coherence is None:
            weights.append(np.ones(fr.n))
        else:
            c = np.minimum(fr.coherence, 0.999)
            weights.append(np.sqrt(c / (1 - c)))
    wmax = max(float(np.max(w)) for w in weights)
    weights = [w / wmax for w in weights]

    def delay_of(sv, fr):
        ts = frf_sample_time(fr, plant)
        return sv[i_d] * scales[i_d] if i_d is not None else (delay_samples * ts if ts > 0 else 0.0)

    def resid(sv):
        out = []
        pv = (sv * scales)[i_p]
        for fr, w in zip(frf, weights):
            g = _frf_eval(lin, pv, fr.frequency_hz, fr.speed_rad_s, fr.load_n, frf_sample_time(fr, plant), delay_of(sv, fr))
            d = np.log(g) - np.log(fr.response)
            out += [w * d.real, w * np.angle(np.exp(1j * d.imag))]
        return np.concatenate(out)

    if scan_stiffness and "contact.stiffness_n_per_mm_e" in keys:  # bounded scan of the stiffness: the start of the fit
        i_k = keys.index("contact.stiffness_n_per_mm_e")
        best = None
        n_mag = sum(fr.n for fr in frf)
        for sk in np.geomspace(lo[i_k], hi[i_k], 31):
            sv = s0.copy()
            sv[i_k] = sk
            try:
                rv = resid(sv)
            except (FitError, np.linalg.LinAlgError, ValueError):
                continue
            # the log-magnitude offset (an inertia error of the start) profiled out
            mag = np.concatenate([rv[sum(fr.n for fr in frf[:j]) * 2:][:fr.n] for j, fr in enumerate(frf)])
            cost = float(np.sum(rv**2) - n_mag * np.mean(mag) ** 2)
            if best is None or cost < best[0]:
                best = (cost, sk)
        if best is not None:
            s0[i_k] = best[1]
    if i_d is not None and scan_delay:  # bounded scan of the delay (quarter samples over its bracket): the wrapped phase is
        # periodic in it, and from one start the fit stopped in another period (a 10-sample delay fitted 0.16)
        best = None
        for dv in np.arange(lo[i_d], hi[i_d] + 1e-9, 0.25 * ts_fit / scales[i_d]):
            sv = s0.copy()
            sv[i_d] = dv
            try:
                cost = float(np.sum(resid(sv) ** 2))
            except (FitError, np.linalg.LinAlgError, ValueError):
                continue
            if math.isfinite(cost) and (best is None or cost < best[0]):
                best = (cost, dv)
        if best is not None:
            s0[i_d] = best[1]
    sol = least_squares(resid, s0, bounds=(lo, hi), x_scale=1.0, max_nfev=max_nfev, method="trf")
    if not sol.success:
        raise FitError(f"FRF fit did not converge: least-squares status {sol.status} ({sol.message}) after "
                       f"{sol.nfev} evaluations; remedy: check the response's units ((rad/s)/(N m)) and operating "
                       "point, fit fewer parameters (--fit) or start from a closer base plant (--plant)")
    r, jac = sol.fun, sol.jac
    n_res, npar = len(r), len(keys)
    dof = max(n_res - npar, 1)
    s2 = float(r @ r) / dof
    cn = np.linalg.norm(jac, axis=0)
    cn[cn == 0] = 1.0
    a_inv, null, ratios = info_split(jac / cn)
    inv = a_inv / np.outer(cn, cn)
    cov = s2 * inv * np.outer(scales, scales)
    null = null / cn[:, None] * scales[:, None]
    values = sol.x * scales
    names_txt = ", ".join(fr.name for fr in frf)
    warns = [w for fr in frf for w in fr.warnings]
    params, corr, fitted, reflected, delay, reasons = finish_fit(plant, keys, values, cov, lo * scales, hi * scales, names_txt,
                                                              warns, ts_fit, keep_unidentified, null, ratios,
                                                              uncertainty)
    if i_d is not None and values[i_d] <= lo[i_d] * scales[i_d] + 1e-9 * ts_fit:
        _delay_at_zero(params, delay, warns)
    elif i_d is not None and values[i_d] >= hi[i_d] * scales[i_d] - 1e-6 * ts_fit:
        for e in (params[DELAY_KEY], delay):  # the response may lag more: no interval around the bracket's end
            if e is not None:
                e.update(ci95=None, at_bound="upper", note=f"at the top of its bracket ({delay_samples} + 10 samples): "
                         "the response may lag more; move the bracket with delay_samples (--delay-samples)")
    if "contact.stiffness_n_per_mm_e" in keys:
        warns += _mode_warnings(fitted, frf, math.sqrt(s2) / np.sqrt(np.mean(np.concatenate(weights) ** 2)))
    fit_pct, traces = {}, {}
    for fr in frf:
        g = frf_response(fitted, fr.frequency_hz, speed_rad_s=fr.speed_rad_s, load_n=fr.load_n,
                         sample_time_s=frf_sample_time(fr, plant), delay_s=delay_of(sol.x, fr), fidelity=fidelity)
        fit_pct[fr.name] = round(frf_fit_percent(fr.response, g), 3)
        traces[fr.name] = {"frequency_hz": fr.frequency_hz, "measured": fr.response, "model": g, "coherence": fr.coherence}
    if delay is not None:  # after the fit %: the traces use the fitted continuous delay itself
        fitted, delay = _write_delay(fitted, delay, ts_fit, command_logged, warns)
    solver = {
        "name": "bounded least squares on the log frequency response (scipy trust-region reflective)",
        "status": "converged",
        "iterations": int(sol.nfev),
        "objective": float(0.5 * r @ r),
        "residual_std": float(math.sqrt(s2)),
        "residual_unit": "log response (coherence weighted)",
        "residuals": int(n_res),
        "fidelity": fidelity,
        "covariance": "classic (residual variance x inverse Gauss-Newton matrix)",
    }
    if delay is not None:  # (held: the caller states it, timedomain.fit_plant)
        from .delay import frf_delay_record

        solver["command_delay"] = frf_delay_record(delay, fitted, ts_fit, command_logged,
                                                   loop_held="drive.current_loop_bandwidth_hz" not in keys)
    return FitResult(fitted, params, reflected, corr, keys, fit_pct, warns, solver, traces, delay, reasons, cov)


BW_KEY = "drive.current_loop_bandwidth_hz"


def _delay_at_zero(params: dict, delay: dict | None, warns: list) -> None:
    """A fitted continuous delay that ended at its lower bound 0 reported as held there (in place):
    no interval (:data:`prsa_ctrl.identification.twomass.AT_BOUND_NOTE`), the bracket warning
    replaced by the reason (the bound is not a bracket to move: a command cannot act before it is
    given; the model holds every lag a drive's measurement has)."""
    from .twomass import AT_BOUND_NOTE

    for e in (params[DELAY_KEY], delay):
        if e is not None:
            e.update(value=0.0, ci95=None, at_bound="lower", note=AT_BOUND_NOTE)
    warns[:] = [w for w in warns if not (w.startswith(f"{DELAY_KEY} = ") and "is at its bound [0" in w)]
    warns.append(f"{DELAY_KEY} = 0 s, {AT_BOUND_NOTE}: the response lags its command no more than the model's "
                 "current loop and sampling do (a delay cannot be negative: a command does not act before it is "
                 "given); the other intervals hold it at 0")


def write_delay(fitted: Plant, delay: dict, ts: float, command_logged: str, warns: list) -> tuple[Plant, dict]:
    """The fitted plant with a fitted continuous command delay ``delay["value"]`` (s) written:
    the nearest whole samples as ``drive.command_delay_samples`` (less one for a command logged
    as computed), the remainder (within half a sample, either sign) lumped into the current-loop
    lag (a negative remainder shortens it, never below half: then the whole samples below and a
    positive remainder); ``delay`` gains ``plant_file`` and
    ``written``. Warnings are appended to ``warns``."""
    return _write_delay(fitted, delay, ts, command_logged, warns)


def _write_delay(fitted: Plant, delay: dict, ts: float, command_logged: str, warns: list) -> tuple[Plant, dict]:
    """The fitted plant with the fitted continuous delay written (see :func:`fit_frf`)."""
    offset = {"applied": 0, "computed": 1}.get(command_logged)
    if offset is None:
        raise ValueError(f"command_logged = {command_logged!r}; expected 'applied' or 'computed'")
    t_d = float(delay["value"]) - offset * ts
    if t_d < -0.5 * ts:
        warns.append(f"the fitted command delay {delay['value']:.4g} s is shorter than the computation delay "
                     f"{ts:g} s of a command logged as computed: written as no delay; expected command_logged "
                     "'applied' for these responses")
        t_d = 0.0
    # The nearest whole sample, the remainder (at most half a sample, either sign) as current-loop
    # lag: a first-order lag tau approximates a delay tau below its bandwidth. The floor (was)
    # turned a fitted 1.9996 samples into 1 sample and 0.9996 sample of lag, halving the current
    # loop (322 against 650 Hz on a foreign roller screw). A negative remainder shortens the
    # lag, but never below half of it (then the floor, a positive remainder).
    f_c = fitted.values["drive.current_loop_bandwidth_hz"]
    n = int(math.floor(t_d / ts + 0.5))
    if 1.0 / f_c + 2 * math.pi * (t_d - n * ts) < 0.5 / f_c:
        n = int(math.floor(t_d / ts + 1e-9))
    n = max(n, 0)
    rest = t_d - n * ts
    if 1.0 / f_c + 2 * math.pi * rest < 0.5 / f_c:  # a delay shorter than the log's convention allows
        warns.append(f"the fitted command delay {delay['value']:.4g} s is {-1e6 * rest:.3g} us shorter than the "
                     f"{offset} sample(s) a command logged as {command_logged} implies, more than half the current "
                     f"loop's lag ({1e6 / (2 * math.pi * f_c):.3g} us) can absorb: written as no delay and twice the "
                     "fitted current-loop bandwidth; check --command-logged")
        rest = -0.25 / (math.pi * f_c)
    f_w = 1.0 / (1.0 / f_c + 2 * math.pi * rest)
    out = fitted.with_params({"drive.command_delay_samples": n, "drive.current_loop_bandwidth_hz": f_w},
                             name=fitted.name)
    srcs = dict(out.sources)
    srcs["drive.command_delay_samples"] = (f"fit: whole samples of the fitted command delay {delay['value']:.4g} s "
                                           f"(command logged as {command_logged})")
    srcs["drive.current_loop_bandwidth_hz"] = (f"fit: {f_c:.6g} Hz with the delay's remaining {rest:.4g} s "
                                               "as current-loop lag")
    unc = dict(out.uncertainty or {})
    if BW_KEY in unc and isinstance(unc[BW_KEY], dict):  # its absolute numbers follow the written value
        e = dict(unc[BW_KEY])
        for field_ in ("low", "high", "sigma"):
            if isinstance(e.get(field_), (int, float)) and not isinstance(e.get(field_), bool):
                e[field_] = e[field_] * f_w / f_c
        e["source"] = f"{e.get('source', '')}; scaled to the written bandwidth (delay remainder as lag)".lstrip("; ")
        unc[BW_KEY] = e
    out = Plant(name=out.name, values=out.values, sources=srcs, origin=out.origin, description=out.description,
                uncertainty=unc, mechanism=out.mechanism, defaulted=out.defaulted,
                mechanism_source=out.mechanism_source)
    delay = dict(delay)
    delay["plant_file"] = (f"written: drive.command_delay_samples = {n} and drive.current_loop_bandwidth_hz = "
                           f"{f_w:.6g} (the fitted {f_c:.6g} Hz with the remaining {rest:.4g} s of the delay as "
                           "current-loop lag)")
    delay["written"] = {"drive.command_delay_samples": n, "drive.current_loop_bandwidth_hz": f_w}
    return out, delay


def _mode_warnings(fitted: Plant, frf: Sequence[FrfRecord], noise_log: float) -> list[str]:
    """Warnings naming the contact stiffness when the responses cannot show the axial mode: they
    end below it, or the mode changes them (in their band) by less than three times their noise
    (``noise_log``: residual standard deviation of the log response, unweighted)."""
    out = []
    key = "contact.stiffness_n_per_mm_e"
    for fr in frf:
        try:
            m = axial_mode(fitted, speed_rad_s=fr.speed_rad_s, load_n=fr.load_n)
        except (ValueError, FitError):
            continue
        f_top = float(np.max(fr.frequency_hz))
        f_first = min(m["resonance_hz"], m["antiresonance_hz"]) if math.isfinite(m["antiresonance_hz"]) \
            else m["resonance_hz"]
        ts = frf_sample_time(fr, fitted)
        g = frf_response(fitted, fr.frequency_hz, speed_rad_s=fr.speed_rad_s, load_n=fr.load_n, sample_time_s=ts,
                         fidelity="compliant")
        g0 = frf_response(fitted, fr.frequency_hz, speed_rad_s=fr.speed_rad_s, load_n=fr.load_n, sample_time_s=ts,
                          fidelity="rigid")
        effect = float(np.max(np.abs(np.log(g / g0))))
        if f_top < 0.9 * f_first:
            out.append(f"{key}: {fr.name} ends at {f_top:.4g} Hz, below the axial mode (anti-resonance "
                       f"{m['antiresonance_hz']:.4g} Hz, resonance {m['resonance_hz']:.4g} Hz at the fitted stiffness): "
                       "the data see at most the mode's low-frequency tail, so the stiffness rests on the model's "
                       "inertia split and its interval is not reliable; measure up to the mode or leave the "
                       "stiffness out of --fit")
        elif effect < 3.0 * noise_log:
            out.append(f"{key}: the axial mode ({m['resonance_hz']:.4g} Hz) changes {fr.name} by at most "
                       f"{20 / math.log(10) * effect:.2g} dB at the measured frequencies, under three times the "
                       f"response's noise ({20 / math.log(10) * noise_log:.2g} dB): the reflected axial mass is "
                       f"{100 * m['reflected_axial_inertia_ratio']:.2g} % of the nut inertia, too small for "
                       "torque -> nut speed to show the mode; the stiffness is not identifiable from it")
    return out
