"""Tuning the position loop of a linear axis with the controller structure of its log, by the
toolkit's tuner (:func:`prsa_ctrl.tuning.tune_loops`), and the comparison with the gains that ran.

The controller (:class:`prsa_ctrl.identification.logformat.ControllerSpec`, structure
``position-p/velocity-p``, the EMPS benchmark's)::

    v(k) = kv (kp (r(k) - q(k)) - dq(k)),  force = gain * v(k)

with ``dq`` the controller's velocity estimate (``average2-difference``: the position averaged
over two samples, then differenced, ``dq(k) = (q(k) - q(k-2)) / (2 Ts)``; ``difference``:
``(q(k) - q(k-1)) / Ts``) and the command applied in the sample it is computed in. Written in
the gains ``kv`` and ``kv kp`` it is a speed PI whose integral is the position error itself,
``v = kv (r' - dq) + kv kp (r - q)`` (an exact integral, no Euler sum): the loop is affine in
``(kv, kv kp)``, which is the tuner's ``(kp, ki)`` of a PI (its :class:`~prsa_ctrl.tuning.LoopModel`
is built here, :func:`axis_loop`). Position P over velocity P is therefore ``kp = ki / kp_tuner``,
``kv = kp_tuner``.

Loop model (:func:`axis_loop`): the plant linearised by the toolkit
(:func:`prsa_ctrl.plant.linear.linear_core`, rigid fidelity, or the compliant one, the two-mass
axis of :mod:`prsa_ctrl.plant.linearaxis`, when the plant has a load mass; at a speed of ``+speed`` or
``-speed`` so that a direction's viscous friction is the slope; the plant's current-loop lag is
part of it), held over each sample (zero-order hold), the velocity estimate and the position error
exactly as above. Robustness: ``Ms = max |1 / (1 + L)|`` with the loop broken at the drive input,
``L = (kv D(z) + kv kp) gain P(z)``. Performance: the tuner's ISE of the following error
``r - q`` over a reference trajectory (a profile loop; the Coulomb friction of the direction of
the reference's motion enters as a load sequence), summed over both directions' loops.

:func:`retune_axis` tunes at the sensitivity peak of the gains that ran (equal robustness: the
largest Ms of the two directions' loops), then replays the logged trajectory through the fitted
nonlinear plant in closed loop (:func:`prsa_ctrl.identification.axis.simulate_axis`) for both
designs: the verified following error, the peak controller output against its saturation, and
the margins.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
from numpy.typing import NDArray

from ..drive.sampled import freq_grid, ss_response, zoh
from ..identification.axis import LinearAxisPlant, simulate_axis
from ..identification.logformat import VELOCITY_ESTIMATES, AxisLog, ControllerSpec
from ..plant.linear import linear_core
from ..plant.linearaxis import is_two_mass_axis, two_mass_axis_parameters
from ..plant.model import plant_model
from ..plant.plantfile import Plant
from ..results import check_status
from ..tuning.generic import tune_loops
from ..tuning.loops import LoopModel
from ..tuning.tuner import TuningResult

__all__ = ["axis_loop", "axis_loops", "AxisGains", "AxisDesign", "AxisRetuning", "retune_axis",
           "LINEARISATION_SPEED_M_S"]

#: Speed of the linearisation, m/s: small against the axis' speeds, large enough that the
#: direction's viscous slope (not the kink at zero) is the linear model.
LINEARISATION_SPEED_M_S = 1e-3


def _estimate_row(velocity_estimate: str, i_th: int, i_q1: int, i_q2: int, n: int, ts: float) -> NDArray[np.float64]:
    """Row of the velocity estimate ``dq(k)`` over the loop state."""
    row = np.zeros(n)
    if velocity_estimate == "average2-difference":
        row[i_th], row[i_q2] = 1.0 / (2 * ts), -1.0 / (2 * ts)
    elif velocity_estimate == "difference":
        row[i_th], row[i_q1] = 1.0 / ts, -1.0 / ts
    else:
        raise ValueError(f"velocity_estimate = {velocity_estimate!r}; expected one of {', '.join(VELOCITY_ESTIMATES)}")
    return row


def _estimate_response(velocity_estimate: str, zi: NDArray[np.complex128], ts: float) -> NDArray[np.complex128]:
    """``D(z)`` of the velocity estimate at ``zi = z^-1``."""
    return (1 - zi ** 2) / (2 * ts) if velocity_estimate == "average2-difference" else (1 - zi) / ts


def axis_loop(plant: Plant, *, gain_n_per_unit: float, sample_time_s: float,
              velocity_estimate: str = "average2-difference", direction: int = 1,
              reference_m: Sequence[float] | None = None, coulomb: bool = True,
              horizon_s: float = 1.0, name: str | None = None) -> LoopModel:
    """Loop model of a linear axis under position P over velocity P (see the module docstring).

    Parameters
    ----------
    plant : Plant
        A ``linear-axis`` plant (load coordinates: m, N), e.g. a fitted one
        (:meth:`prsa_ctrl.identification.axis.LinearAxisPlant.to_plant`).
    gain_n_per_unit : float
        Drive gain, N per command unit (the controller's output is in command units, e.g. V).
    sample_time_s : float
        Controller sample time, s.
    velocity_estimate : str
        ``"average2-difference"`` or ``"difference"``
        (:data:`prsa_ctrl.identification.logformat.VELOCITY_ESTIMATES`).
    direction : int
        +1 or -1: the linearisation at ``direction * LINEARISATION_SPEED_M_S`` (that direction's
        viscous friction).
    reference_m : sequence of float, optional
        Position reference, m, one value per sample: the loop is then a profile loop whose error
        is the following error over it (from rest at the first value). Without it: a load step of
        1 N from rest (its error the position deviation, m).
    coulomb : bool
        With a reference: the Coulomb friction of the plant in the direction of the reference's
        motion enters as a load sequence (the linear model has none).
    horizon_s : float
        Without a reference: the step response's length, s.
    name : str, optional
        The loop's name.

    Returns
    -------
    LoopModel
        Gains ``(kv, kv kp, 0)`` in (command unit per m/s, command unit per m); sampled
        (``nyquist = pi / sample_time_s``), with its exact frequency response.
    """
    if getattr(plant, "mechanism", None) != "linear-axis":
        raise ValueError(f"plant mechanism = {getattr(plant, 'mechanism', None)!r}; expected a 'linear-axis' plant")
    if direction not in (1, -1):
        raise ValueError(f"direction = {direction!r}; expected +1 or -1")
    for arg, v in (("gain_n_per_unit", gain_n_per_unit), ("sample_time_s", sample_time_s), ("horizon_s", horizon_s)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0):
            raise ValueError(f"{arg} = {v!r}; expected a positive finite number")
    ts, g = float(sample_time_s), float(gain_n_per_unit)
    fidelity = "compliant" if is_two_mass_axis(plant) else "rigid"  # the two-mass axis where the plant has one
    a, b, _, _, _ = linear_core(plant, direction * LINEARISATION_SPEED_M_S, 0.0, fidelity)
    names = plant_model(plant, fidelity).state_names
    i_w = names.index("omega_nut")
    # friction acts on the motor side (the whole mass of a rigid axis): a force column there, N
    friction_col = np.zeros(a.shape[0])
    friction_col[i_w] = -1.0 / (two_mass_axis_parameters(plant)[0] if fidelity == "compliant"
                                else float(plant.values["axis.mass_kg"]))
    ad, bd = zoh(a, np.column_stack([b, friction_col]), ts)
    n = ad.shape[0]
    i_th = names.index("theta_nut")  # position of the motor side (the encoder's; a rigid axis's load), m
    i_q1, i_q2, i_r = n, n + 1, n + 2
    N = n + 3
    E = np.eye(N)
    est = _estimate_row(velocity_estimate, i_th, i_q1, i_q2, N, ts)
    bu, bl = bd[:, 0] * g, bd[:, 1]
    A0 = np.zeros((N, N))
    A0[:n, :n] = ad
    A0[i_q1] = E[i_th]
    A0[i_q2] = E[i_q1]
    a_kv = np.zeros((N, N))
    a_kv[:n] = np.outer(bu, -est)
    a_kpv = np.zeros((N, N))
    a_kpv[:n] = np.outer(bu, E[i_r] - E[i_th])
    ce = E[i_r] - E[i_th]
    bdv = np.zeros(N)
    profile = None
    if reference_m is None:
        n_steps = max(10, int(round(horizon_s / ts)))
        bdv[:n] = bl * 1.0
    else:
        r = np.asarray(reference_m, float).ravel()
        if r.size < 11 or not np.all(np.isfinite(r)):
            raise ValueError(f"reference_m of {r.size} values; expected at least 11 finite positions in m")
        r = r - r[0]
        n_steps = r.size - 1
        profile = np.zeros((n_steps, N))
        profile[:, i_r] = r[1:]
        if coulomb:
            v = plant.values
            vr = np.diff(r)
            # the plant's load input is an axial force against +x: friction opposing the motion
            load = np.where(vr > 0, v["friction.coulomb_positive_n"], 0.0) \
                - np.where(vr < 0, v["friction.coulomb_negative_n"], 0.0)
            load[-1] = 0.0  # held after the horizon: the axis at rest, where Coulomb friction is no load
            profile[:, :n] = load[:, None] * bd[:, 2][None, :]
        k = int(np.argmax(np.abs(r)))
        bdv[i_r] = r[k]
    nyq = math.pi / ts
    c_th = E[i_th][:n]

    def response(w):
        w = np.asarray(w, float)
        zi = np.exp(-1j * w * ts)
        p = ss_response(ad, bu[:, None], c_th[None, :], w, lambda x: np.exp(1j * x * ts))
        return None, np.vstack([p * _estimate_response(velocity_estimate, zi, ts), p, np.zeros_like(p)]), None, None

    omega = freq_grid(1e-1, nyq * 0.999, 500)
    L = response(omega)[1]
    label = name or f"{plant.name} {'+' if direction > 0 else '-'}x"
    return LoopModel(A0, (a_kv, a_kpv, np.zeros((N, N))), bdv, ce, ts, n_steps, omega, L, 4 * ts, name=label,
                     response=response, nyquist=nyq, profile=profile)


def axis_loops(plant: Plant, log: AxisLog, **kwargs: Any) -> tuple[LoopModel, LoopModel]:
    """The loop models of both directions (:func:`axis_loop`) with the log's drive gain, sample
    time, velocity estimate and reference (``kwargs`` go to :func:`axis_loop`)."""
    c = _controller(log)
    opts = dict(gain_n_per_unit=log.gain_n_per_unit, sample_time_s=log.sample_time_s,
                velocity_estimate=c.velocity_estimate, reference_m=log.reference_m)
    opts.update(kwargs)
    return tuple(axis_loop(plant, direction=d, **opts) for d in (1, -1))  # type: ignore[return-value]


def _controller(log: AxisLog) -> ControllerSpec:
    c = log.controller
    if c is None or log.reference_m is None:
        raise ValueError(f"log {log.name!r}: expected a described controller and a reference")
    if c.structure != "position-p/velocity-p" or c.command_delay_samples != 0:
        raise ValueError(f"log {log.name!r}: controller {c.structure!r} with a command delay of "
                         f"{c.command_delay_samples} samples; expected 'position-p/velocity-p' applied in the sample "
                         "it is computed in (the structure axis_loop models)")
    return c


@dataclass(frozen=True)
class AxisGains:
    """Position P over velocity P: ``kp`` 1/s, ``kv`` command unit per m/s."""

    kp: float
    kv: float

    @property
    def tuner_gains(self) -> tuple[float, float, float]:
        """The loop model's gains ``(kv, kv kp, 0)``."""
        return (self.kv, self.kv * self.kp, 0.0)

    @classmethod
    def from_tuner(cls, result: TuningResult) -> "AxisGains":
        """From a PI result on :func:`axis_loop` models (``kp = ki / kp_tuner``, ``kv = kp_tuner``)."""
        return cls(kp=result.pid.ki / result.pid.kp, kv=result.pid.kp)


@dataclass(frozen=True)
class AxisDesign:
    """One design on the fitted axis: linear robustness and the nonlinear replay of the log."""

    label: str
    gains: AxisGains
    ms: float  # largest Ms of the two directions' loops
    gain_margin_db: float  # smallest of the two loops'
    phase_margin_deg: float  # smallest of the two loops'
    following_rms_m: float
    following_peak_m: float
    command_peak: float  # controller output the design demands (replayed without saturation), command units
    ise_linear: float  # the tuner's objective: ISE of the following error, both loops, m^2 s

    def as_dict(self) -> dict:
        return {**dataclasses.asdict(self), "gains": {"kp_per_s": self.gains.kp, "kv_per_m_s": self.gains.kv}}


@dataclass(frozen=True)
class AxisRetuning:
    """Result of :func:`retune_axis`."""

    running: AxisDesign
    tuned: AxisDesign
    tuning: TuningResult
    saturation: float
    status: str
    warnings: tuple[str, ...] = field(default_factory=tuple)
    measured_following_rms_m: float = math.nan
    measured_following_peak_m: float = math.nan

    @property
    def ok(self) -> bool:
        """Whether the result may be reported as good (:func:`prsa_ctrl.results.is_ok` of its status)."""
        from ..results import is_ok

        return is_ok(self.status)

    def as_dict(self) -> dict:
        return {"running": self.running.as_dict(), "tuned": self.tuned.as_dict(), "saturation": self.saturation,
                "status": self.status, "warnings": list(self.warnings), "tuner_status": self.tuning.status,
                "measured_following_rms_m": self.measured_following_rms_m,
                "measured_following_peak_m": self.measured_following_peak_m,
                "coordinates": "load (position m, force N)"}


def _design(label: str, gains: AxisGains, loops: Sequence[LoopModel], axis: LinearAxisPlant, log: AxisLog,
            x0: tuple[float, float]) -> AxisDesign:
    g = gains.tuner_gains
    margins = [lp.margins(g) for lp in loops]
    worst = max(range(len(loops)), key=lambda i: margins[i].ms)
    m = margins[worst]
    # saturation lifted: the peak command is what the design demands (flagged beyond the limit)
    c = dataclasses.replace(log.controller, kp=gains.kp, kv=gains.kv, saturation=math.inf)
    tr = simulate_axis(axis.theta, dataclasses.replace(log, controller=c), force_limit_n=math.inf, x0=x0,
                       second_mass=axis.second_mass)
    e = log.reference_m - tr.position_m
    ise = float(sum(lp.true_objective(g, "ise")[0] for lp in loops))
    return AxisDesign(label, gains, float(m.ms), min(float(x.gm_db) for x in margins),
                      min(float(x.pm_deg) for x in margins), float(np.sqrt(np.mean(e ** 2))), float(np.max(np.abs(e))),
                      float(np.max(np.abs(tr.command))), ise)


def retune_axis(axis: LinearAxisPlant, log: AxisLog, *, ms_max: float | None = None,
                loops: Sequence[LoopModel] | None = None) -> AxisRetuning:
    """Tune ``kp``, ``kv`` of the log's controller on the fitted axis at the robustness of the gains
    that ran, and compare both designs on the logged trajectory.

    Parameters
    ----------
    axis : LinearAxisPlant
        The fitted axis (``prsa-fit --out`` file, :func:`prsa_ctrl.identification.axis.load_axis_plant`).
    log : AxisLog
        The log whose controller ran (``position-p/velocity-p``, no command delay) and whose
        reference is the trajectory to follow.
    ms_max : float, optional
        Bound on Ms (default: the largest Ms of the running gains over both directions' loops).
    loops : sequence of LoopModel, optional
        The loop models (default :func:`axis_loops` of the log's reference).

    Returns
    -------
    AxisRetuning
        ``status`` (:data:`prsa_ctrl.results.STATUSES`) is ``"ok"`` when the tuner's result is
        proven optimal and the tuned design stays within the controller's saturation on the
        replay; the tuner's status (``"not converged: ..."``, ``"not proven optimal: ..."``) when
        it is not; ``"flagged: the tuned design saturates ..."`` when the design would saturate.
    """
    c = _controller(log)
    plant = axis.to_plant()
    lps = tuple(loops) if loops is not None else axis_loops(plant, log)
    running = AxisGains(c.kp, c.kv)
    x0 = (float(log.position_m[0]), 0.0)
    ms0 = max(lp.margins(running.tuner_gains).ms for lp in lps)
    bound = ms0 if ms_max is None else float(ms_max)
    res = tune_loops(lps, objective="ise", controller="pi", ms_max=bound)
    tuned = AxisGains.from_tuner(res)
    d0 = _design("gains that ran", running, lps, axis, log, x0)
    d1 = _design("tuned", tuned, lps, axis, log, x0)
    warnings = list(res.warnings)
    status = "ok" if res.converged else res.status  # the tuner's own status when it failed (the vocabulary's)
    if d1.command_peak > c.saturation:
        warnings.append(f"the tuned design's controller output peaks at {d1.command_peak:.3g} on the logged trajectory, "
                        f"beyond the saturation {c.saturation:g} (its predicted following error assumes no saturation)")
        if status == "ok":
            status = "flagged: the tuned design saturates the controller output on the logged trajectory"
    check_status(status)
    em = log.reference_m - log.position_m
    return AxisRetuning(d0, d1, res, float(c.saturation), status, tuple(warnings),
                        float(np.sqrt(np.mean(em ** 2))), float(np.max(np.abs(em))))
