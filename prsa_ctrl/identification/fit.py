"""Grey-box calibration of a plant from measured drive data (output error, confidence intervals).

The model is the toolkit's own CasADi model (:mod:`prsa_ctrl.plant.model`) with the fitted plant
values as symbols, so the fitted plant is exactly what the tuner uses. Each record is cut into
multiple-shooting segments (each with its own free initial state, so that an open-loop
integration of the recorded torque command cannot drift over a long record); every sample
interval is one 3-stage Radau IIA collocation step (order 5, L-stable for the stiff friction
and current loop) with the recorded command held (zero-order hold) and the recorded load.
The residual is the measured encoder angle minus the model angle at every sample (or, without
an angle column, the measured speed minus the model's one-sample angle difference), weighted
by the encoder quantisation noise ``q / sqrt(12)``. Data where the nut is near standstill or
reversing (``|speed|`` below about 1 rad/s, or a sign change between samples) are left out and
the record is cut there into separate segments: the friction law is not smooth there
(Karnopp stick band, Stribeck drop), one collocation step per sample does not resolve the
stick-slip transition, and that model error biased every parameter by many standard errors.
The problem -- scaled, bounded parameters, segment initial states and collocation states -- is
solved by a constrained Gauss-Newton method with exact CasADi derivatives (three state-only
warm-up steps, then bounded parameter steps).

Confidence: the sensitivity of the residuals to the parameters (segment initial states
projected out) follows from the collocation equations by the implicit-function theorem. The
covariance is a sandwich with a prewhitened Newey-West (HAC) estimate of the score covariance
(coloured residuals: quantisation, the speed loop, model error), which equals the classic
``s^2 (J^T J)^-1`` for white residuals; it gives 95 % intervals (normal approximation), the
correlation matrix and identifiability warnings. Identifiability is decided on the singular
values of the column-scaled parameter Jacobian (:data:`RANK_RTOL`, far above round-off): along
a direction the data do not inform, the intervals span what the physical ranges allow and the
keys on it keep the base plant's values. Measured coverage (tests/test_fit.py, ``PRSA_SLOW=1``):
see the README's calibration section.

Inputs are checked against the plant before the fit (:func:`_checked_inputs`): duplicate data,
the sample time, a unit slip in the torque balance, FRF points above the drive's Nyquist
frequency. The overlay figures show one continuous simulation of the fitted plant.

Frequency responses (:func:`fit_frf`): the rigid model linearised at the measurement's speed and
load, sampled as the drive measures it, fitted on the log response.
"""

from __future__ import annotations

import math
import warnings as _warnings
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from .data import FrfRecord, Record
from ..plant.plantfile import Plant

__all__ = ["fit_plant", "fit_frf", "frf_response", "frf_operating_point_error", "axial_mode", "fit_figures", "FitResult", "FitError", "FITTABLE",
           "DEFAULT_KEYS", "FRF_KEYS", "FRF_KEYS_COMPLIANT", "DELAY_KEY", "fit_percent"]

#: Plant keys the fit can estimate: unit and meaning (bounds and scales: :func:`_bounds`).
FITTABLE: Mapping[str, tuple[str, str]] = {
    "nut.inertia_kg_m2": ("kg m^2", "nut plus rotor inertia"),
    "friction.efficiency": ("-", "forward efficiency"),
    "friction.no_load_torque_n_m": ("N m", "no-load (Coulomb) drag torque"),
    "friction.viscous_n_m_s_per_rad": ("N m s/rad", "viscous coefficient"),
    "drive.current_loop_bandwidth_hz": ("Hz", "current-loop bandwidth"),
    "drive.command_delay_s": ("s", "command delay (logged command to the moment it acts; not a plant-file key)"),
    "contact.stiffness_n_per_mm_e": ("N/mm^e", "IMPACT thread-contact stiffness (compliant fidelity: the axial mode)"),
    "contact.damping_n_s_per_mm": ("N s/mm", "IMPACT thread-contact damping (compliant fidelity: the axial mode)"),
}
#: The fitted command delay: a dead time between the logged torque command and the moment it
#: acts, beyond the zero-order hold. The plant file has no such key (the toolkit models the
#: drive's one-sample computation delay in the sampled loop and the rest of the drive as the
#: first-order current loop), so the delay is reported, not written; its first-order
#: equivalent is ``FitResult.delay["equivalent_current_loop_bandwidth_hz"]``.
DELAY_KEY = "drive.command_delay_s"
#: Fittable keys that are not plant-file keys.
PSEUDO_KEYS = (DELAY_KEY,)
#: Keys that only the compliant fidelity depends on.
CONTACT_KEYS = ("contact.stiffness_n_per_mm_e", "contact.damping_n_s_per_mm")
#: Keys fitted when none are chosen.
DEFAULT_KEYS = ("nut.inertia_kg_m2", "friction.efficiency", "friction.no_load_torque_n_m",
                "friction.viscous_n_m_s_per_rad", "drive.current_loop_bandwidth_hz")
#: Keys an FRF-only fit estimates by default: the response at speed shows the inertia and the
#: current loop; efficiency and no-load torque do not enter the linearisation at speed, and the
#: viscous corner (b / J, well below 1 Hz) lies under the usual lowest measured frequency. With
#: the compliant fidelity the contact stiffness is added (:data:`FRF_KEYS_COMPLIANT`).
FRF_KEYS = ("nut.inertia_kg_m2", "drive.current_loop_bandwidth_hz")
FRF_KEYS_COMPLIANT = FRF_KEYS + ("contact.stiffness_n_per_mm_e",)

# 3-stage Radau IIA (order 5): stage times and coefficients; the last stage is the step end.
_S6 = math.sqrt(6.0)
_RADAU_C = ((4 - _S6) / 10, (4 + _S6) / 10, 1.0)
_RADAU_A = (
    ((88 - 7 * _S6) / 360, (296 - 169 * _S6) / 1800, (-2 + 3 * _S6) / 225),
    ((296 + 169 * _S6) / 1800, (88 + 7 * _S6) / 360, (-2 - 3 * _S6) / 225),
    ((16 - _S6) / 36, (16 + _S6) / 36, 1 / 9),
)
_Z95 = 1.959963984540054
#: Above this correlation the data cannot separate two fitted keys (warning; a key this
#: correlated with an unidentifiable one is not identified either).
_CORR_SEPARATE = 0.95
#: Budget of one fit: total sample intervals of all records.
MAX_INTERVALS = 200_000
#: A Gauss-Newton attempt whose constraint residual fell by less than 10 % over this many
#: iterations is given up (the next attempt starts differently).
STALL_ITERATIONS = 15
#: Converged when every parameter step is below this fraction of its standard error (or ``tol``).
STEP_SE_FRACTION = 1e-3
#: Shortest multiple-shooting segment (sample intervals); shorter stretches of usable data are left out.
MIN_SEGMENT = 20
#: Identifiability tolerance: a direction of the column-scaled parameter Jacobian (each column
#: of unit norm, segment initial states projected out) whose singular value is below this
#: fraction of the largest carries no information from the data. Round-off puts an exactly
#: singular direction near 1e-15 and a perturbation of the Jacobian at 1e-10 near 1e-10; weakly
#: but truly excited directions of the built-in experiments lie above 1e-3. Along such a
#: direction the interval is the whole stretch the physical ranges allow (:func:`_null_extent`).
RANK_RTOL = 1e-6


class FitError(RuntimeError):
    """The fit did not converge; the message names the solver status and a remedy."""


@dataclass(frozen=True, eq=False)
class FitResult:
    """Result of :func:`fit_plant`.

    Attributes
    ----------
    plant : Plant
        The base plant with the fitted values (``Plant.with_params``); sources say ``fit: ...``.
    parameters : dict
        ``{key: {"value": v, "ci95": [lo, hi], "unit": u, "kept_base": bool}}`` in file units
        (no ``kept_base`` for the delay, which is never written).
        A key with ``kept_base`` true was not identifiable from the data (:func:`fit_plant`):
        ``value`` and ``ci95`` are what the fit with it free gave, ``written`` the base value the
        plant keeps and ``reason`` why; the other keys are refitted with it held there.
    reflected_inertia_kg_m2 : dict
        The total inertia at the nut in the same form, kg m^2.
    correlation : ndarray
        Correlation matrix of the fitted parameters (order of ``keys``).
    keys : tuple of str
    fit_percent : dict
        ``{record name: fit %}``: ``100 (1 - |v - v_model| / |v - mean(v)|)`` on the nut speed
        (one-sample angle difference) over the shooting segments.
    warnings : list of str
    solver : dict
        Solver name, status, iterations (and over all attempts), final objective, residual
        standard deviation (in the unit of the residual), number of residuals, segments,
        left-out samples, covariance method with its HAC bandwidth, the residuals' lag-1
        autocorrelation and how much wider the intervals are than white-residual ones.
    traces : dict
        Per record ``{"time_s", "measured", "model"}`` (nut speed, rad/s) and per frequency
        response ``{"frequency_hz", "measured", "model"}`` (complex, (rad/s)/(N m)), for
        :func:`fit_figures`.
    not_identified : dict
        ``{key: reason}`` for the fitted keys that the data of this fit cannot inform (95 % CI
        wider than the key's physical range, more than +/- 50 % of the value, or at a bound of
        the range; :func:`_not_identified`).
    delay : dict or None
        When ``drive.command_delay_s`` was fitted: the delay (``value``, ``ci95``, s; ``samples``)
        and how it maps to the plant file, which has no delay key:
        ``equivalent_current_loop_bandwidth_hz`` (``value``, ``ci95``) is the first-order current
        loop with the same low-frequency phase lag, ``1 / (2 pi (1 / (2 pi f_c) + T_d))``,
        for a log whose command is the applied one (the toolkit's simulator logs it so); a drive
        that logs the computed command shows its one-sample computation delay, which the tuner
        already models, in ``T_d`` too (subtract ``sample_time_s``).
    """

    plant: Plant
    parameters: dict
    reflected_inertia_kg_m2: dict
    correlation: NDArray[np.float64]
    keys: tuple[str, ...]
    fit_percent: dict
    warnings: list
    solver: dict
    traces: dict = field(default_factory=dict, repr=False)
    delay: dict | None = None
    not_identified: dict = field(default_factory=dict)

    @property
    def plant_keys(self) -> tuple[str, ...]:
        """The fitted keys written into the plant file (not the delay, not the keys kept at the
        base value)."""
        return tuple(k for k in self.keys if k not in PSEUDO_KEYS and not self.parameters[k].get("kept_base"))

    @property
    def kept_base(self) -> tuple[str, ...]:
        """Keys the data could not inform: the plant file keeps their base value and source."""
        return tuple(k for k, v in self.parameters.items() if v.get("kept_base"))

    def report(self) -> dict:
        """JSON-ready report (stable keys: ``parameters``, ``reflected_inertia_kg_m2``,
        ``fit_percent``, ``warnings``, ``solver``, plus ``correlation`` and, when the delay was
        fitted, ``delay``)."""
        out = {
            "parameters": self.parameters,
            "reflected_inertia_kg_m2": self.reflected_inertia_kg_m2,
            "fit_percent": self.fit_percent,
            "warnings": list(self.warnings),
            "solver": self.solver,
            "correlation": {"keys": list(self.keys), "matrix": np.round(self.correlation, 6).tolist()},
        }
        if self.delay is not None:
            out["delay"] = self.delay
        return out


class _SymbolicPlant(Plant):
    """A plant whose fitted values are CasADi symbols (the model equations accept them)."""

    @property
    def slip_arm_m(self):  # same formula as Plant.slip_arm_m without the numeric branch
        eta = self.values["friction.efficiency"]
        mu = self.values["friction.dynamic"]
        if mu == 0.0:
            return 0.0
        f_n, f_s = self.normal_force_factor()
        return self.lead_per_rad * (1.0 / eta - 1.0) / (mu * (f_n + f_s))


def _symbolic_rhs(plant: Plant, keys: Sequence[str], fidelity: str):
    """``(x, u, p) -> xdot`` of the toolkit's model with the values of ``keys`` as ``p``."""
    import casadi as ca

    from ..plant import model as m

    p = ca.SX.sym("p", len(keys))
    values = dict(plant.values)
    for i, k in enumerate(keys):
        values[k] = p[i]
    with _warnings.catch_warnings():
        _warnings.simplefilter("ignore")
        sym = _SymbolicPlant(name=plant.name, values=values, sources=plant.sources, origin=plant.origin)
    names = m.plant_model(plant, fidelity).state_names
    x = ca.SX.sym("x", len(names))
    u = ca.SX.sym("u", 2)
    builders = {"rigid": getattr(m, "_rigid", None), "compliant": getattr(m, "_compliant", None)}
    build = builders.get(fidelity)
    if build is None:
        raise ValueError(f"fidelity = {fidelity!r}; expected 'rigid' or 'compliant' for a fit")
    try:
        xdot = build(sym, x, u)[0]
    except TypeError as exc:  # an equation that needs a numeric value of a fitted key
        raise ValueError(f"the {fidelity} model cannot take {', '.join(keys)} as fitted symbols ({exc}); "
                         "expected fewer --fit keys") from None
    return ca.Function("f", [x, u, p], [xdot]), names


def _bounds(plant: Plant, key: str, ts: float) -> tuple[float, float, float]:
    """Lower bound, upper bound and scale (file units) of a fitted key."""
    v = plant.values[key]
    t_max = plant.torque_limit
    if key == "nut.inertia_kg_m2":
        return 0.05 * v, 20.0 * v, v
    if key == "friction.efficiency":
        return 0.3, 0.995, 1.0
    if key == "friction.no_load_torque_n_m":
        return 0.0, 0.5 * t_max, max(v, 0.01 * t_max)
    if key == "friction.viscous_n_m_s_per_rad":
        return 0.0, 0.01 * t_max, max(v, 1e-5 * t_max)
    if key == "drive.current_loop_bandwidth_hz":
        return 10.0, min(1e5, 10.0 / ts), v
    if key == "contact.stiffness_n_per_mm_e":  # the axial mode frequency goes with K^(1/(2e))
        return max(v / 30.0, 1e1), min(v * 30.0, 1e9), v
    if key == "contact.damping_n_s_per_mm":
        return 0.0, min(max(100.0 * v, 1e3), 1e5), max(v, 1.0)
    raise ValueError(f"--fit key {key!r}; expected one of {', '.join(FITTABLE)}")


def _plant_value(plant: Plant, key: str, delay_s: float = 0.0) -> float:
    """Initial value of a fitted key (the delay is no plant key: ``delay_s``)."""
    return delay_s if key == DELAY_KEY else plant.values[key]


def _check_keys(keys: Sequence[str], fidelity: str) -> tuple[str, ...]:
    keys = tuple(keys)
    for k in keys:
        if k not in FITTABLE:
            raise ValueError(f"fit key {k!r}; expected one of {', '.join(FITTABLE)}")
    if not keys or len(set(keys)) != len(keys):
        raise ValueError(f"fit keys {', '.join(keys)}; expected one or more keys, each once")
    contact = [k for k in keys if k in CONTACT_KEYS]
    if contact and fidelity != "compliant":
        raise ValueError(f"fit key {contact[0]!r} with fidelity {fidelity!r}; expected fidelity 'compliant' "
                         "(only the compliant model has the thread contacts)")
    return keys


@dataclass
class _Seg:
    rec: int
    k0: int  # first sample of the segment
    n: int  # intervals


def _segments(records: Sequence[Record], segment_samples: int, refs=None, min_speed_rad_s: float = 0.0,
              margin: int = 2) -> tuple[list[_Seg], int]:
    """Multiple-shooting segments of about ``segment_samples`` intervals, and the samples left out.

    Intervals where the (smoothed) data speed is below ``min_speed_rad_s`` within ``margin``
    samples (speed reversals, standstill) are left out: there the friction law is not smooth
    (Karnopp stick band, Stribeck drop) and one collocation step per sample misses the
    stick-slip transition, a model error that would bias the fit and make its residuals
    coloured. Every stretch in between starts a segment of its own with a free initial state.
    Stretches shorter than ``MIN_SEGMENT`` intervals are left out too.
    """
    segs, left_out = [], 0
    for r, rec in enumerate(records):
        n_int = rec.n - 1
        ok = np.ones(n_int, bool)
        if refs is not None and min_speed_rad_s > 0:
            # mean speed over each interval (angle difference), lightly smoothed against noise
            v = np.diff(refs[r][0]) / np.diff(rec.time_s)
            v = np.convolve(v, np.ones(3) / 3, mode="same") if len(v) >= 3 else v
            slow = np.abs(v) < min_speed_rad_s
            flip = np.signbit(v[:-1]) != np.signbit(v[1:])  # a reversal faster than one sample
            slow[:-1] |= flip
            slow[1:] |= flip
            if margin:
                slow = np.convolve(slow.astype(float), np.ones(2 * margin + 1), mode="same") > 0
            ok = ~slow
        edges = np.flatnonzero(np.diff(np.concatenate([[0], ok.astype(int), [0]])))
        for a, b in zip(edges[::2], edges[1::2]):
            if b - a < MIN_SEGMENT:
                continue
            n_seg = max(1, int(round((b - a) / segment_samples)))
            cuts = np.linspace(a, b, n_seg + 1).round().astype(int)
            segs += [_Seg(r, int(c0), int(c1 - c0)) for c0, c1 in zip(cuts[:-1], cuts[1:])]
        left_out += n_int - int(ok.sum()) + sum(int(b - a) for a, b in zip(edges[::2], edges[1::2]) if b - a < MIN_SEGMENT)
    return segs, left_out


def _min_speed(plant: Plant) -> float:
    """Default speed (rad/s of the nut) below which data are left out of a fit: three Stribeck
    velocities plus the Karnopp blend band (``2 w_b``), where the friction law is not smooth."""
    from ..plant.model import stick_band_rad_s

    v_s = plant.values["friction.stribeck_velocity_m_s"] / plant.lead_per_rad
    return 3.0 * v_s + 2.0 * stick_band_rad_s(plant)


def _reference(rec: Record, plant: Plant) -> NDArray[np.float64]:
    """Data-based reference trajectory (nx=3 rigid-like rows: angle, speed, torque) per sample."""
    t = rec.time_s
    if rec.nut_angle_rad is not None:
        theta = rec.nut_angle_rad.astype(float)
    else:
        theta = np.concatenate([[0.0], np.cumsum(rec.nut_speed_rad_s[1:] * np.diff(t))])
    omega = np.gradient(theta, t)
    a = math.exp(-(t[1] - t[0]) / plant.current_loop_time_constant_s)
    cmd = np.clip(rec.torque_command_n_m, -plant.torque_limit, plant.torque_limit)
    tau = np.empty_like(cmd)
    tau[0] = cmd[0]
    for k in range(1, len(cmd)):
        tau[k] = a * tau[k - 1] + (1 - a) * cmd[k - 1]
    return np.vstack([theta, omega, tau])


def fit_plant(
    records: Sequence[Record],
    plant: Plant | None = None,
    *,
    frf: Sequence[FrfRecord] = (),
    keys: Sequence[str] | None = None,
    fidelity: str = "rigid",
    validate: Sequence[Record] = (),
    segment_s: float = 0.1,
    delay_samples: int = 0,
    substeps: int = 1,
    max_iter: int = 50,
    tol: float = 1e-8,
    min_speed_rad_s: float | None = None,
    keep_unidentified: bool = True,
    uncertainty: str = "keep",
) -> FitResult:
    """Fit plant parameters to measured time-domain records (output error through the model).

    Keys the data cannot inform (:func:`_not_identified`: a 95 % CI wider than the key's
    physical range or than +/- 50 % of the value, or a value at a bound of the range) keep the
    base plant's value and source in the fitted plant and get no ``[uncertainty]`` entry from
    the fit; their report entry says ``"kept_base": true`` with the reason. The other keys keep
    the values and intervals of the fit with every key free: those intervals allow for the
    unidentifiable keys being unknown (a refit with them held at base values would give
    narrower intervals conditional on values the data do not support, and fails outright
    when the data contradict them). The fit % of the plant as written (base values for the
    kept keys) is reported beside the free fit's (``solver["fit_percent_written"]``) and a
    warning names the records it fits worse.

    Parameters
    ----------
    records : sequence of Record
        Records to fit (see :func:`prsa_ctrl.identification.data.load_record`); they share the parameters.
        May be empty when ``frf`` is given: the fit then uses the frequency responses alone
        (:func:`fit_frf`).
    plant : Plant, optional
        Base plant (default: the built-in default plant); its values are the initial guess and
        its sensor's encoder resolution sets the residual weights.
    frf : sequence of FrfRecord
        Measured frequency responses (torque command -> nut speed). With time-domain records
        they validate the fitted plant (fit % and traces for the Bode overlay); alone they are
        fitted.
    keys : sequence of str, optional
        Plant keys to fit (default :data:`DEFAULT_KEYS`; :data:`FRF_KEYS` for an FRF-only fit).
    fidelity : {"rigid", "compliant"}
        Model fidelity.
    validate : sequence of Record
        Records not fitted; their fit % is reported (only the segments' initial states are fitted).
    segment_s : float, s
        Length of a multiple-shooting segment.
    substeps : int
        Radau IIA steps per sample interval (more resolve fast friction transitions at speed
        reversals better; cost grows in proportion).
    delay_samples : int
        Samples between a logged command and the sample it acts from (0: the logged command
        is held over the interval that follows it, as in the toolkit's simulator).
    max_iter : int
        Gauss-Newton iteration budget (plus three state-only warm-up steps).
    tol : float
        Convergence tolerance of the parameter step (scaled units).
    min_speed_rad_s : float, rad/s, optional
        Data where the nut speed is below this (speed reversals, standstill) are left out (the
        friction law is not smooth there; see :func:`_segments`). Default: three Stribeck
        velocities plus the Karnopp blend band of the base plant (about 1 rad/s for the paper
        plant); 0 keeps every sample.
    keep_unidentified : bool
        False writes every fitted value into the plant, identifiable or not.
    uncertainty : {"keep", "fit"}
        The fitted plant's ``[uncertainty]`` entries of the fitted keys: ``"keep"`` the base
        plant's (the user's assumptions) unless one is narrower than the fit's 95 % interval or
        does not hold the fitted value (then the fit's, with a warning), and none where the base
        has none; ``"fit"`` the fit's own for every fitted key (a normal with the fit's sigma,
        truncated at its 95 % interval).

    Returns
    -------
    FitResult

    Raises
    ------
    ValueError
        Bad arguments (unknown key, too long records, ...).
    FitError
        The solver did not converge (status and remedy in the message).
    """
    from ..plant.plantfile import load_plant

    plant = load_plant() if plant is None else plant
    records, frf, validate = list(records), list(frf), list(validate)
    records, validate, frf = _checked_inputs(records, validate, frf, plant)

    if uncertainty not in UNCERTAINTY_MODES:
        raise ValueError(f"uncertainty = {uncertainty!r}; expected one of {', '.join(map(repr, UNCERTAINTY_MODES))}")
    if not records and frf:
        return fit_frf(frf, plant, keys=keys, fidelity=fidelity, delay_samples=delay_samples,
                       keep_unidentified=keep_unidentified, uncertainty=uncertainty)
    return _fit_records(records, plant, frf=frf, keys=keys, fidelity=fidelity, validate=validate,
                        segment_s=segment_s, delay_samples=delay_samples, substeps=substeps, max_iter=max_iter,
                        tol=tol, min_speed_rad_s=min_speed_rad_s, keep_unidentified=keep_unidentified,
                        uncertainty=uncertainty)


#: Largest relative difference between a record's sample time and the plant's
#: ``sensor.sample_time_s``: the model holds each logged command over one logged sample, as the
#: drive does, so a log at another rate (or with time in another unit) is not this drive's loop.
SAMPLE_TIME_RTOL = 0.01
#: Unit slips the torque-balance check recognises: the factor by which the apparent inertia
#: (:func:`_apparent_inertia`) divides the plant's, and what it means for which column.
_UNIT_SLIPS = (
    (60.0 / (2 * math.pi), "speed in rpm"), (180.0 / math.pi, "speed in deg/s"), (1.0 / (2 * math.pi), "speed in rev/s"),
    (1e-3, "torque in mN m"),
)
#: The apparent inertia names a unit slip when it is within this factor of the plant's reflected
#: inertia divided by the slip's factor and more than :data:`UNIT_PLANT_FACTOR` away from the
#: plant's own; beyond ``1 / 20 .. 20`` times the plant's (the fit's inertia bounds) it cannot be
#: this plant in any case.
UNIT_SLIP_FACTOR = 2.0
#: Operating point of a measured frequency response: nut speed at most 6000 rpm (the tuner's
#: limit), axial load at most this many rated loads of the plant.
FRF_SPEED_MAX_RAD_S = 6000.0 * math.pi / 30.0
FRF_LOAD_MAX_RATED = 2.0
#: A logged torque command beyond this multiple of the plant's torque limit is not this drive's.
TORQUE_OVER_LIMIT = 10.0
UNIT_PLANT_FACTOR = 3.0


def _data_key(rec) -> bytes:
    """Bytes that are equal exactly when two records hold the same data: the same measured arrays
    at the same sample time (to 9 digits; a clock shifted by a constant is the same record)."""
    import hashlib

    h = hashlib.sha256()
    if isinstance(rec, Record):
        arrays = (np.array([float(f"{rec.sample_time_s:.9g}")]), rec.torque_command_n_m, rec.nut_angle_rad,
                  rec.nut_speed_rad_s, rec.axial_load_n)
    else:
        arrays = (rec.frequency_hz, rec.response, rec.coherence, np.array([rec.speed_rad_s, rec.load_n]))
    for a in arrays:
        h.update(b"-" if a is None else np.ascontiguousarray(a).tobytes())
    return h.digest()


def _dedupe(items: list, earlier: Sequence = ()):
    """``items`` without those whose data equal an earlier item's (or one of ``earlier``): the
    item kept gets a warning naming the dropped one (the same data twice would count its noise
    as new information and narrow the intervals by sqrt(2)). With ``earlier``: ``(items,
    notes)``, the notes naming the items dropped for being one of ``earlier``."""
    import dataclasses

    first = {_data_key(e): e.name for e in earlier}
    out, where, notes = [], {}, []
    for it in items:
        key = _data_key(it)
        if key in first or key in where:
            msg = (f"{it.name} holds the same data as {first.get(key) or out[where[key]].name}: used once (the same "
                   "data twice would narrow the intervals by sqrt(2) without new information)")
            if key in where:
                out[where[key]] = dataclasses.replace(out[where[key]], warnings=(*out[where[key]].warnings, msg))
            else:
                notes.append(msg.replace("used once", "not a validation (it is fitted)"))
            continue
        where[key] = len(out)
        out.append(it)
    return (out, notes) if earlier else out


def _motor_torque(rec: Record, plant: Plant, clip: bool = True) -> NDArray[np.float64]:
    """The torque command through the plant's first-order current loop (clipped at its limit
    unless ``clip`` is false), N m."""
    from scipy.signal import lfilter

    a = math.exp(-rec.sample_time_s / plant.current_loop_time_constant_s)
    cmd = np.clip(rec.torque_command_n_m, -plant.torque_limit, plant.torque_limit) if clip else rec.torque_command_n_m

    return np.concatenate([[cmd[0]], lfilter([1 - a], [1, -a], cmd[:-1], zi=[a * cmd[0]])[0]])


def _apparent_inertia(rec: Record, plant: Plant) -> float | None:
    """The inertia (kg m^2) the record's torque balance shows, from the data alone.

    Over windows of ``m`` samples the change of the measured speed is regressed on the integrals
    of the motor torque (the command through the current loop), of the speed sign, the speed,
    the load and the load times the speed sign (Coulomb, viscous and load friction): the first
    coefficient is ``1 / J``. Integrals of the clean command as regressors keep the speed noise
    out of them. None when the regression does not explain the data (R^2 < 0.5) or the speed
    does not respond to the torque.
    """
    v = rec.speed_rad_s  # interval means
    if len(v) < 40:
        return None
    tau = _motor_torque(rec, plant, clip=False)  # unclipped: a unit slip shows in full
    tau = 0.5 * (tau[:-1] + tau[1:])
    sg = np.sign(v)
    f = rec.axial_load_n[:-1]
    ts = rec.sample_time_s
    cols = np.column_stack([tau, sg, v, f, f * sg]) * ts
    c = np.vstack([np.zeros(cols.shape[1]), np.cumsum(cols, axis=0)])
    m = max(4, min(40, len(v) // 20))
    j = np.arange(len(v) - m)
    dv = v[j + m] - v[j]
    x = c[j + m] - c[j]  # integral over the intervals j..j+m-1 (mid-interval to mid-interval)
    scale = np.maximum(np.linalg.norm(x, axis=0), 1e-300)
    beta, *_ = np.linalg.lstsq(x / scale, dv, rcond=None)
    beta = beta / scale
    ss = float(np.sum((dv - dv.mean()) ** 2))
    if ss <= 0 or beta[0] <= 0:
        return None
    r2 = 1.0 - float(np.sum((dv - x @ beta) ** 2)) / ss
    return 1.0 / float(beta[0]) if r2 >= 0.5 else None


def _check_units(rec: Record, plant: Plant) -> None:
    """Refuse a record whose torque balance shows a unit slip (:func:`_apparent_inertia` against
    the plant's reflected inertia, :data:`_UNIT_SLIPS`) or an inertia no fit of this plant can reach."""
    peak = float(np.max(np.abs(rec.torque_command_n_m)))
    if peak > TORQUE_OVER_LIMIT * plant.torque_limit:
        raise ValueError(f"{rec.name}: column torque_command_n_m reaches {peak:.6g}, {peak / plant.torque_limit:.3g} x "
                         f"the plant's torque limit {plant.torque_limit:.6g} N m; expected N m (mN m? a current "
                         "without --torque-constant?) or the actuator's own plant (--plant)")
    j_app = _apparent_inertia(rec, plant)
    if j_app is None:
        return
    j_pl = plant.reflected_inertia_kg_m2
    ratio = j_pl / j_app
    col = "nut_angle_rad" if rec.nut_angle_rad is not None else "nut_speed_rad_s"
    what = (f"{rec.name}: the torque balance of torque_command_n_m and {col} shows an inertia of {j_app:.3g} kg m^2 "
            f"where the plant has {j_pl:.3g} kg m^2 (ratio {ratio:.3g})")
    if abs(math.log(ratio)) > math.log(UNIT_PLANT_FACTOR):
        for factor, slip in _UNIT_SLIPS:
            if abs(math.log(ratio / factor)) < math.log(UNIT_SLIP_FACTOR):
                column = "torque_command_n_m" if "torque" in slip else col
                angle = " (or the angle in deg / rev)" if column == "nut_angle_rad" else ""
                raise ValueError(f"{what}: column {column} looks like {slip}{angle}; expected SI units "
                                 "(N m, rad, rad/s): convert the column (or, if it is SI, give a plant with the "
                                 "actuator's inertia, --plant)")
    if not 1 / 20 <= ratio <= 20:
        raise ValueError(f"{what}; expected within a factor 20 of the plant (the fit's range): check the units of "
                         f"torque_command_n_m and {col}, or give the actuator's own plant (--plant)")


def frf_operating_point_error(plant: Plant, speed_rad_s: float, load_n: float) -> tuple[str, str] | None:
    """What is wrong with a frequency response's operating point for ``plant``, or None.

    Returns
    -------
    tuple or None
        ``("speed", expected)`` for a nut speed (rad/s) inside the friction's stick band (the
        linearisation needs motion) or above :data:`FRF_SPEED_MAX_RAD_S`; ``("load", expected)``
        for an axial load (N) above :data:`FRF_LOAD_MAX_RATED` rated loads.
    """
    v_min, v_max, f_max = _min_speed(plant), FRF_SPEED_MAX_RAD_S, FRF_LOAD_MAX_RATED * plant.rated_load_n
    if not v_min <= abs(speed_rad_s) <= v_max:
        return "speed", (f"expected a nut speed with {v_min:.3g} <= |speed| <= {v_max:.6g} rad/s (the linearisation "
                         "needs motion above the friction's stick band; 6000 rpm is the tuner's limit)")
    if abs(load_n) > f_max:
        return "load", (f"expected |load| <= {f_max:.6g} N ({FRF_LOAD_MAX_RATED:g} x the plant's rated load "
                        f"{plant.rated_load_n:.6g} N)")
    return None


def _checked_inputs(records, validate, frf, plant):
    """Inputs of a fit after the checks that need the plant: duplicate data used once (with a
    warning), each record's sample time equal to the plant's within :data:`SAMPLE_TIME_RTOL`,
    no unit slip in the torque balance (:func:`_check_units`), FRF points at or above the
    drive's Nyquist frequency dropped (a warning each; too few left: ValueError), each response's
    operating point within :data:`FRF_SPEED_MAX_RAD_S` and :data:`FRF_LOAD_MAX_RATED`."""
    from .data import MIN_FRF_POINTS

    import dataclasses

    records = _dedupe(records)
    frf = _dedupe(frf)
    if validate:
        validate, notes = _dedupe(validate, records)
        if notes:
            records[0] = dataclasses.replace(records[0], warnings=(*records[0].warnings, *notes))
    ts_pl = plant.sample_time_s
    for rec in (*records, *validate):
        if abs(rec.sample_time_s / ts_pl - 1.0) > SAMPLE_TIME_RTOL:
            raise ValueError(f"{rec.name}: column time_s gives a sample time of {rec.sample_time_s:.6g} s; expected the "
                             f"plant's sensor.sample_time_s {ts_pl:.6g} s within {100 * SAMPLE_TIME_RTOL:g} % (time in "
                             "another unit? a log at another rate than the drive's loop? or give the drive's plant)")
        _check_units(rec, plant)
    out = []
    for fr in frf:
        bad = frf_operating_point_error(plant, fr.speed_rad_s, fr.load_n)
        if bad:
            field_, expected = bad
            value = fr.speed_rad_s if field_ == "speed" else fr.load_n
            raise ValueError(f"{fr.name}: {field_} = {value!r}; {expected}")
        ts = _frf_ts(fr, plant)
        if ts > 0 and fr.frequency_hz[-1] >= 0.5 / ts:
            keep = fr.frequency_hz < 0.5 / ts
            n_drop = int(np.sum(~keep))
            if int(np.sum(keep)) < MIN_FRF_POINTS:
                raise ValueError(f"{fr.name}: {int(np.sum(keep))} frequency points below the drive's Nyquist frequency "
                                 f"{0.5 / ts:g} Hz (sample time {ts:g} s); expected at least {MIN_FRF_POINTS}")
            note = (f"{fr.name}: {n_drop} points at or above the drive's Nyquist frequency {0.5 / ts:g} Hz "
                    f"(sample time {ts:g} s) dropped: a sampled drive cannot measure them")
            fr = dataclasses.replace(fr, frequency_hz=fr.frequency_hz[keep], response=fr.response[keep],
                                     coherence=None if fr.coherence is None else fr.coherence[keep],
                                     warnings=(*fr.warnings, note))
        out.append(fr)
    return records, validate, out


def _fit_records(records, plant, *, frf, keys, fidelity, validate, segment_s, delay_samples, substeps, max_iter, tol,
                 min_speed_rad_s, keep_unidentified, uncertainty="keep") -> FitResult:
    """The output-error fit of :func:`fit_plant` on time-domain ``records``."""
    if not records:
        raise ValueError("records = []; expected at least one data record")
    keys = tuple(DEFAULT_KEYS if keys is None else keys)
    if not keys:
        raise ValueError("keys = (); expected at least one plant key to fit")
    keys = _check_keys(keys, fidelity)
    if DELAY_KEY in keys:
        raise ValueError(f"fit key {DELAY_KEY!r} with time-domain records; expected it in a frequency-response fit "
                         "(--frf without DATA.csv): in closed-loop records it is not separable from the current-loop "
                         "bandwidth, give the integer delay_samples (--delay-samples) instead")
    if not (isinstance(delay_samples, int) and 0 <= delay_samples <= 10):
        raise ValueError(f"delay_samples = {delay_samples!r}; expected an integer 0..10")
    if not (isinstance(substeps, int) and 1 <= substeps <= 8):
        raise ValueError(f"substeps = {substeps!r}; expected an integer 1..8")
    if not (math.isfinite(segment_s) and segment_s > 0):
        raise ValueError(f"segment_s = {segment_s!r}; expected a time > 0 s")
    if min_speed_rad_s is None:
        min_speed_rad_s = _min_speed(plant)
    if isinstance(min_speed_rad_s, bool) or not (math.isfinite(min_speed_rad_s) and min_speed_rad_s >= 0):
        raise ValueError(f"min_speed_rad_s = {min_speed_rad_s!r}; expected a speed >= 0 rad/s")
    ts = records[0].sample_time_s
    for rec in (*records, *validate):
        if abs(rec.sample_time_s / ts - 1) > 1e-3:
            raise ValueError(f"{rec.name}: sample time {rec.sample_time_s:g} s differs from {ts:g} s of "
                             f"{records[0].name}; expected one sample time for all records")
    total = sum(r.n - 1 for r in (*records, *validate))
    if total > MAX_INTERVALS:
        raise ValueError(f"records hold {total} sample intervals; expected at most {MAX_INTERVALS} (shorten them)")
    bounds = [_bounds(plant, k, ts) for k in keys]
    s0 = np.array([plant.values[k] / b[2] for k, b in zip(keys, bounds)])
    lo = np.array([b[0] / b[2] for b in bounds])
    hi = np.array([b[1] / b[2] for b in bounds])
    s0 = np.clip(s0, lo, hi)
    scales = np.array([b[2] for b in bounds])

    fit_run = _Problem(plant, keys, scales, fidelity, records, ts, segment_s, delay_samples, substeps,
                       min_speed_rad_s)
    # Bounded attempts, each given up early when it stalls: a cautious trust region for the
    # parameter steps after a state-only warm-up, the same without it, a bolder one. The
    # warm-up first: without it, parameter steps taken while the trajectories are still far
    # from the data can lead the iteration into a stall (a 4 s record took 33 wasted
    # iterations before the warm-up attempt converged in 9).
    attempts = ((0.3, 3), (0.3, 0), (1.0, 3))
    spent = 0
    for i, (box, warm) in enumerate(attempts):
        try:
            sol = fit_run.solve(s0, lo, hi, max_iter, tol, fixed=False, box=box, warm=warm)
            break
        except FitError:
            spent += fit_run.last_iterations
            if i == len(attempts) - 1:
                raise
    s_opt = sol["s"]
    cov_s, sigma, n_res, jac_cols, cov_info = fit_run.covariance(sol)
    values = s_opt * scales
    cov = cov_s * np.outer(scales, scales)
    names = ", ".join(r.name for r in records)
    warns = [w for rec in (*records, *validate, *frf) for w in rec.warnings]
    if fit_run.left_out:
        total_int = sum(r.n - 1 for r in records)
        warns.append(f"{fit_run.left_out} of {total_int} sample intervals at |speed| < {min_speed_rad_s:.3g} rad/s "
                     "(speed reversals, standstill) left out: the friction law is not smooth there")
    if cov_info["residual_autocorrelation_lag1"] > 0.5:
        warns.append(f"residuals strongly coloured (lag-1 autocorrelation {cov_info['residual_autocorrelation_lag1']:.2f}): "
                     "the intervals are widened for it (HAC) but stay optimistic (measured: 73 % coverage on AR(1) "
                     "noise of 0.95); look for unmodelled dynamics or a filtered encoder signal")
    params, corr, fitted, reflected, delay, reasons = _finish(plant, keys, values, cov, lo * scales, hi * scales,
                                                              names, warns, ts, keep_unidentified,
                                                              fit_run.null_scaled * scales[:, None],
                                                              np.array(cov_info["singular_value_ratios"]), uncertainty)
    fit_pct = dict(sol["fit_percent"])
    traces = dict(sol["traces"])
    _add_simulations(traces, fit_run.simulate(sol, fitted))
    kept = [k for k in keys if params[k].get("kept_base")]
    s_written = np.array([plant.values[k] / sc if k in kept else sv for k, sv, sc in zip(keys, s_opt, scales)])
    written_pct = None
    if kept:  # the plant as written (base values for the kept keys) on the fitted records
        wsol = fit_run.solve(s_written, s_written, s_written, max_iter, tol, fixed=True)
        written_pct = dict(wsol["fit_percent"])
        worse = [f"{n} {written_pct[n]:.2f} % (free fit {fit_pct[n]:.2f} %)" for n in written_pct
                 if written_pct[n] < fit_pct[n] - 1.0]
        if worse:
            warns.append(f"the plant as written, with {', '.join(kept)} at the base value{'s' if len(kept) > 1 else ''}, "
                         f"fits {'; '.join(worse)}: the data inform a combination of the kept keys but not each "
                         "one; record the excitation the warnings above name to identify them")
    for rec in validate:  # the plant as written
        vrun = _Problem(fitted, keys, scales, fidelity, [rec], ts, segment_s, delay_samples, substeps,
                        min_speed_rad_s)
        vsol = vrun.solve(s_written, s_written, s_written, max_iter, tol, fixed=True)
        fit_pct.update(vsol["fit_percent"])
        traces.update(vsol["traces"])
        _add_simulations(traces, vrun.simulate(vsol, fitted))
    for fr in frf:  # frequency responses given with time-domain data validate the fitted plant
        g = frf_response(fitted, fr.frequency_hz, speed_rad_s=fr.speed_rad_s, load_n=fr.load_n,
                         sample_time_s=_frf_ts(fr, fitted), delay_samples=delay_samples,
                         fidelity=fidelity if fr.load_n else "rigid")
        fit_pct[fr.name] = round(_frf_fit_percent(fr.response, g), 3)
        traces[fr.name] = {"frequency_hz": fr.frequency_hz, "measured": fr.response, "model": g}
    solver = {
        "name": "constrained Gauss-Newton (multiple shooting, Radau IIA collocation per sample, exact CasADi derivatives)",
        "status": sol["status"],
        "iterations": sol["iterations"],
        "attempts": i + 1,
        "iterations_all_attempts": spent + sol["iterations"],
        "objective": sol["objective"],
        "residual_std": float(sigma),
        "residual_unit": fit_run.residual_unit,
        "residuals": int(n_res),
        "segments": len(fit_run.segs),
        "left_out_samples": int(fit_run.left_out),
        "min_speed_rad_s": float(min_speed_rad_s),
        "fidelity": fidelity,
        **cov_info,
    }
    if written_pct is not None:
        solver["fit_percent_written"] = written_pct
    return FitResult(fitted, params, reflected, corr, keys, fit_pct, warns, solver, traces, None, reasons)


def _add_simulations(traces: dict, sims: dict) -> None:
    """Attach each record's continuous simulation (:meth:`_Problem.simulate`) to its trace as ``"simulated"``."""
    for name, sim in sims.items():
        if name in traces:
            traces[name]["simulated"] = sim


def _finish(plant, keys, values, cov, lo, hi, names, warns, ts=None, keep_unidentified=True, null=None,
            ratios=None, uncertainty="keep"):
    """Parameters with 95 % CIs, correlation, identifiability warnings, the fitted plant, the
    reflected inertia, the delay block (None unless the delay was fitted) and the reasons of the
    keys not identified, from fitted values and their covariance (file units; ``lo``/``hi``
    bounds; ``ts`` the sample time, s). ``null``: the directions the data do not inform
    (columns, file units; :func:`_info_split`) and ``ratios`` the singular values over the
    largest: a key's interval spans how far those directions move it within the physical
    ranges (:func:`_null_extent`) plus the covariance's interval. With ``keep_unidentified``
    the keys not identified keep the base plant's value, source and ``[uncertainty]`` entry;
    ``uncertainty`` says what the fitted keys' entries become (:func:`_uncertainty_choice`)."""
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(std, std)
    corr = np.nan_to_num(corr)
    ts = plant.sample_time_s if ts is None else ts
    null = np.zeros((len(keys), 0)) if null is None else np.asarray(null, float)
    ranges = [_physical_range(plant, k, lo[i], hi[i]) if k not in PSEUDO_KEYS else (lo[i], hi[i])
              for i, k in enumerate(keys)]
    ext_lo, ext_hi = _null_extent(values, null, [r[0] for r in ranges], [r[1] for r in ranges])
    params, overrides, reasons, in_null = {}, {}, {}, set()
    for i, k in enumerate(keys):
        unit = FITTABLE[k][0]
        ci = [float(ext_lo[i] - _Z95 * std[i]), float(ext_hi[i] + _Z95 * std[i])]
        params[k] = {"value": float(values[i]), "ci95": ci, "unit": unit}
        if k not in PSEUDO_KEYS:  # the delay is never written, so never kept either
            overrides[k] = float(values[i])
            params[k]["kept_base"] = False
        width = max(ci[1] - values[i], values[i] - ci[0])
        std[i] = width / _Z95  # the honest standard deviation (uninformed directions included)
        floor = 0.2 * ts if k == DELAY_KEY else 1e-3 * (hi[i] - lo[i])  # a delay of 0 is a value like any
        u = _unit_text(unit)
        if not np.isfinite(width) or width > 0.5 * max(abs(values[i]), floor):
            warns.append(f"{k} is not identifiable from this data (95 % CI +/- {width:.3g}{u} around "
                         f"{values[i]:.4g}): {_REMEDY_KEY.get(k, 'excite it more')}")
        if values[i] <= lo[i] * (1 + 1e-6) + 1e-15 or values[i] >= hi[i] * (1 - 1e-6):
            warns.append(f"{k} = {values[i]:.4g}{u} is at its bound [{lo[i]:.4g}, {hi[i]:.4g}]: its interval "
                         "is not reliable" + ("; move the bracket with delay_samples (--delay-samples)"
                                              if k == DELAY_KEY else ""))
        reason = _not_identified(k, float(values[i]), float(width), _physical_range(plant, k, lo[i], hi[i]), floor)
        mates = _null_mates(keys, null / np.array([max(r[1] - r[0], 1e-300) for r in ranges])[:, None], i)
        if mates is not None:  # moves along an uninformed direction: the data do not set it
            in_null.add(k)
            small = float(np.min(ratios)) if ratios is not None and len(ratios) else 0.0
            reason = (f"the data inform only its combination with {', '.join(mates) or 'nothing else'} (a direction of "
                      f"the scaled Jacobian with singular value {small:.1e} x the largest, below the tolerance "
                      f"{RANK_RTOL:g}): the physical ranges alone bound it to {ext_lo[i]:.6g}..{ext_hi[i]:.6g}; "
                      f"{_REMEDY_KEY.get(k, 'excite it more')}")
        if reason:
            reasons[k] = reason
    # A key the data cannot separate from an unidentifiable one is not identified either: its
    # narrow interval holds only with the other at its (unsupported) fitted value or bound.
    # (Not for a key left free by an uninformed direction: the covariance has no part along
    # it, so a correlation with it says nothing; the keys that share the direction are found
    # by :func:`_null_extent`.)
    for _ in range(len(keys)):
        more = {}
        for i, k in enumerate(keys):
            if k in reasons:
                continue
            j = next((j for j, kk in enumerate(keys) if kk in reasons and kk not in in_null
                      and abs(corr[i, j]) > _CORR_SEPARATE), None)
            if j is not None:
                more[k] = (f"strongly correlated ({corr[i, j]:+.3f}) with {keys[j]}, which the data cannot inform: "
                           "only their combination is identified")
        if not more:
            break
        reasons.update(more)
    for k, reason in reasons.items():
        if keep_unidentified and k not in PSEUDO_KEYS:
            del overrides[k]
            params[k].update(kept_base=True, written=plant.values[k], reason=reason)
            warns.append(f"{k} kept at the base value {plant.values[k]:.6g}{_unit_text(FITTABLE[k][0])} in the plant "
                         f"file (not identifiable: {reason})")
    for i in range(len(keys)):
        for j in range(i + 1, len(keys)):
            # (a key on an uninformed direction: its reason names the combination; the
            # covariance has no part along that direction, so its correlations say nothing)
            if abs(corr[i, j]) > _CORR_SEPARATE and keys[i] not in in_null and keys[j] not in in_null:
                pair = {keys[i], keys[j]}
                if pair == {DELAY_KEY, "drive.current_loop_bandwidth_hz"}:
                    warns.append(f"{DELAY_KEY} and drive.current_loop_bandwidth_hz are strongly correlated "
                                 f"({corr[i, j]:+.3f}): below the current-loop bandwidth both only add the phase "
                                 "lag w (1 / (2 pi f_c) + T_d), so the data inform their sum (the delay block's "
                                 "equivalent bandwidth) but cannot separate them; measure up to the current-loop "
                                 "bandwidth or fit one of them")
                else:
                    warns.append(f"{keys[i]} and {keys[j]} are strongly correlated ({corr[i, j]:+.3f}): "
                                 "the data cannot separate them, and their intervals hold only if the model is "
                                 "exact (record load changes, speed levels in both directions)")
    plant_keys = [k for k in keys if k not in PSEUDO_KEYS and not params[k]["kept_base"]]
    with _warnings.catch_warnings():
        _warnings.simplefilter("ignore")  # the base plant's own geometry notes were given when it loaded
        fitted = plant.with_params(overrides, name=f"{plant.name}-fit")
        srcs = dict(fitted.sources)
        for k in plant_keys:
            lo_ci, hi_ci = params[k]["ci95"]
            srcs[k] = f"fit: {names} (95 % CI {lo_ci:.6g}..{hi_ci:.6g})"
        base_unc = dict(getattr(plant, "uncertainty", None) or {})
        unc = {k: v for k, v in base_unc.items() if k not in plant_keys}
        fit_unc = _uncertainty_entries(fitted, {k: params[k] for k in plant_keys}, names,
                                       [std[keys.index(k)] for k in plant_keys],
                                       [_physical_range(plant, k, lo[keys.index(k)], hi[keys.index(k)])
                                        for k in plant_keys])
        for k in plant_keys:
            choice, note = _uncertainty_choice(fitted, k, base_unc.get(k), fit_unc.get(k), params[k]["ci95"],
                                               _physical_range(plant, k, lo[keys.index(k)], hi[keys.index(k)]),
                                               uncertainty)
            if choice is not None:
                unc[k] = choice
            if note:
                warns.append(note)
        fitted = Plant(name=fitted.name, values=fitted.values, sources=srcs, origin=fitted.origin,
                       description=f"{plant.name} fitted by prsa-fit to {names}", uncertainty=unc)
    extra = plant.reflected_inertia_kg_m2 - plant.values["nut.inertia_kg_m2"]
    j_ref = fitted.reflected_inertia_kg_m2
    if "nut.inertia_kg_m2" in plant_keys:
        ci = [c + extra for c in params["nut.inertia_kg_m2"]["ci95"]]
    else:
        ci = [j_ref, j_ref]
    reflected = {"value": float(j_ref), "ci95": ci, "unit": "kg m^2"}
    delay = None
    if DELAY_KEY in keys:
        delay = _delay_block(fitted, keys, values, cov, ts)
    return params, corr, fitted, reflected, delay, reasons


def _info_split(jn: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Rank-revealing split of a column-scaled Jacobian ``jn`` (columns of unit norm).

    Returns ``(a_inv, null, ratios)``: the pseudo-inverse of ``jn^T jn`` on the directions the
    data inform (singular value at least :data:`RANK_RTOL` times the largest), a basis of the
    directions they do not (columns, in ``jn``'s coordinates; may have no columns) and every
    singular value over the largest. The decision does not hinge on round-off: an exactly
    singular direction (1e-15) and one perturbed at 1e-10 fall on the same side of 1e-6.
    """
    _, sv, vt = np.linalg.svd(np.asarray(jn, float), full_matrices=False)
    n = jn.shape[1]
    if sv.size < n:  # fewer residuals than parameters: the missing directions are null too
        sv = np.concatenate([sv, np.zeros(n - sv.size)])
        vt = np.linalg.svd(np.vstack([jn, np.zeros((n - jn.shape[0], n))]), full_matrices=True)[2]
    top = float(sv[0]) if sv.size and sv[0] > 0 else 0.0
    ratios = sv / top if top > 0 else np.zeros_like(sv)
    keep = ratios >= RANK_RTOL
    a_inv = (vt[keep].T / sv[keep] ** 2) @ vt[keep]
    return a_inv, vt[~keep].T, ratios


def _null_extent(values, null, lo, hi) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """How far each parameter can move along the uninformed directions ``null`` (columns, file
    units) while every parameter stays in its range ``lo..hi``: per key the smallest and largest
    value of ``values + null @ t`` over that polytope (one small linear programme per key and
    end). Without uninformed directions both are ``values``."""
    values = np.asarray(values, float)
    if null.size == 0:
        return values.copy(), values.copy()
    from scipy.optimize import linprog

    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    span = np.where(hi > lo, hi - lo, 1.0)
    lo, hi = np.minimum(lo, values), np.maximum(hi, values)  # the fitted point is always inside
    ny = null / span[:, None]
    a_ub = np.vstack([ny, -ny])
    b_ub = np.concatenate([(hi - values) / span, (values - lo) / span])
    ext_lo, ext_hi = values.copy(), values.copy()
    for k in range(len(values)):
        if not np.any(np.abs(ny[k]) > 1e-12):
            continue
        for sign, out in ((1.0, ext_lo), (-1.0, ext_hi)):
            res = linprog(sign * ny[k], A_ub=a_ub, b_ub=b_ub, bounds=[(None, None)] * ny.shape[1], method="highs")
            out[k] = values[k] + span[k] * (float(ny[k] @ res.x) if res.status == 0 else -sign * math.inf)
    return np.clip(ext_lo, lo, None), np.clip(ext_hi, None, hi)


#: A key takes part in an uninformed direction when its component in a unit vector of that
#: direction (each key scaled by its physical range) exceeds this. Structural non-identifiability
#: gives components of order 0.1..1; round-off and a Jacobian perturbed at 1e-10 give 1e-8 or less.
NULL_LOADING = 1e-3


def _null_mates(keys, null, i) -> list[str] | None:
    """The other keys sharing an uninformed direction with key ``i`` (None when key ``i`` has no
    part in one, :data:`NULL_LOADING`): only their combination is identified. ``null``:
    the directions' columns with each key scaled by its physical range."""
    if null.size == 0:
        return None
    unit = null / np.maximum(np.linalg.norm(null, axis=0), 1e-300)
    cols = np.flatnonzero(np.abs(unit[i]) > NULL_LOADING)
    if cols.size == 0:
        return None
    return [keys[j] for j in range(len(keys)) if j != i and np.any(np.abs(unit[j, cols]) > NULL_LOADING)]


def _unit_text(unit: str) -> str:
    """`` N m`` for a unit, nothing for a dimensionless key (``-``)."""
    return "" if unit in ("-", "") else f" {unit}"


def _physical_range(plant: Plant, key: str, lo: float, hi: float) -> tuple[float, float]:
    """Where a fitted key can physically lie, file units: the fit's bounds ``lo..hi``
    (:func:`_bounds`, e.g. the no-load torque below half the motor's torque limit) within the
    plausible range of :data:`prsa_ctrl.plant.plantfile.PLAUSIBLE`."""
    from ..plant.plantfile import PLAUSIBLE

    p_lo, p_hi, _ = PLAUSIBLE.get(key, (-math.inf, math.inf, ""))
    return max(float(lo), float(p_lo)), min(float(hi), float(p_hi))


def _not_identified(key: str, value: float, half_width: float, rng: tuple[float, float], floor: float) -> str | None:
    """Why the data cannot inform ``key`` (None when they can): its 95 % interval (``value +/-
    half_width``) is wider than the physical range ``rng``, wider than +/- 50 % of the value
    (``floor`` for values near 0), or the value sits at an end of the range."""
    lo, hi = rng
    if not math.isfinite(half_width):
        return "its 95 % CI is not finite"
    if 2 * half_width > hi - lo:
        return (f"its 95 % CI {value - half_width:.6g}..{value + half_width:.6g} is wider than its physical range "
                f"{lo:.6g}..{hi:.6g}")
    if value <= lo * (1 + 1e-6) + 1e-15 or value >= hi * (1 - 1e-6):
        return f"the fit ends at a bound of its range {lo:.6g}..{hi:.6g}"
    if half_width > 0.5 * max(abs(value), floor):
        return f"its 95 % CI +/- {half_width:.3g} is more than half the value {value:.6g}"
    return None


def _delay_block(fitted: Plant, keys, values, cov, ts: float) -> dict:
    """The fitted delay and its first-order equivalent current loop (delta-method CI)."""
    i_d = keys.index(DELAY_KEY)
    t_d = float(values[i_d])
    f_c = fitted.values["drive.current_loop_bandwidth_hz"]
    tau = 1.0 / (2 * math.pi * f_c)
    f_eq = 1.0 / (2 * math.pi * (tau + t_d))
    # gradient of f_eq in (T_d, f_c); f_c only when fitted
    grad = np.zeros(len(keys))
    grad[i_d] = -2 * math.pi * f_eq**2
    if "drive.current_loop_bandwidth_hz" in keys:
        grad[keys.index("drive.current_loop_bandwidth_hz")] = f_eq**2 / f_c**2
    sd_eq = float(np.sqrt(max(grad @ cov @ grad, 0.0)))
    sd_d = float(np.sqrt(max(cov[i_d, i_d], 0.0)))
    return {
        "value": t_d, "ci95": [t_d - _Z95 * sd_d, t_d + _Z95 * sd_d], "unit": "s", "samples": t_d / ts,
        "equivalent_current_loop_bandwidth_hz": {"value": f_eq, "ci95": [f_eq - _Z95 * sd_eq, f_eq + _Z95 * sd_eq],
                                                 "unit": "Hz"},
        "plant_file": "not written: the plant file has no delay key (the tuner models the drive's one-sample "
                      "computation delay and the current loop only); the equivalent first-order current-loop "
                      "bandwidth carries the same low-frequency phase lag",
    }


#: What a fit writes into the fitted plant's ``[uncertainty]`` for a fitted key: ``"keep"`` the
#: base plant's own entry (the user's assumption) unless it is narrower than the fit's 95 %
#: interval or does not hold the fitted value (then the fit's entry), and no entry where the base
#: has none; ``"fit"`` the fit's entry (:func:`_uncertainty_entries`) for every fitted key.
UNCERTAINTY_MODES = ("keep", "fit")


def _entry_support(fitted: Plant, key: str, entry) -> tuple[float, float] | None:
    """Support ``(low, high)`` of a base ``[uncertainty]`` entry around the fitted plant's value
    (None when it is not valid there, e.g. absolute bounds that exclude the fitted value)."""
    from ..errors import PlantFileError
    from ..plant.uncertainty import plant_uncertainty

    try:
        p = Plant(name=fitted.name, values=fitted.values, sources=fitted.sources, uncertainty={key: entry})
        (u,) = plant_uncertainty(p).entries
    except (PlantFileError, ValueError):
        return None
    return float(u.low), float(u.high)


def _uncertainty_choice(fitted: Plant, key: str, base_entry, fit_entry, ci95, rng, mode: str):
    """The ``[uncertainty]`` entry written for a fitted key and a note (or None) saying why it
    is not the user's: see :data:`UNCERTAINTY_MODES`. Never narrower than the fit's 95 %
    interval (clipped to the key's physical range ``rng``)."""
    if base_entry is None and mode == "keep":
        return None, None  # the user assumed no spread there; the fit's own entry only when asked ("fit")
    if base_entry is None or mode == "fit":
        if fit_entry is None:
            return None, (f"{key}: no [uncertainty] entry written (its interval is degenerate or leaves the "
                          "physical range)")
        return fit_entry, None
    support = _entry_support(fitted, key, base_entry)
    lo_ci, hi_ci = max(ci95[0], rng[0]), min(ci95[1], rng[1])
    if support is not None and support[1] - support[0] >= (hi_ci - lo_ci) * (1 - 1e-9):
        return base_entry, None
    why = ("does not hold the fitted value" if support is None else
           f"({support[0]:.6g}..{support[1]:.6g}) is narrower than the fit's 95 % interval {lo_ci:.6g}..{hi_ci:.6g}")
    if fit_entry is None:
        return base_entry, f"{key}: the base plant's [uncertainty] entry {why}; kept (the fit's interval is degenerate)"
    return fit_entry, f"{key}: the base plant's [uncertainty] entry {why}: the fit's entry is written instead"


def _uncertainty_entries(fitted: Plant, params: Mapping, names: str, std, ranges=None) -> dict:
    """``[uncertainty]`` entries of the fitted keys: a normal distribution with the fit's standard
    deviation, truncated at the 95 % interval (1.96 sigma) or closer where the key's physical
    range or the plant's cross-checks end; a key at a bound of its range (e.g. no-load torque 0)
    gets a uniform distribution from that bound to its interval's far end. Keys whose interval
    is degenerate or invalid are left out (the fit's warnings say why). ``ranges``: each key's
    physical range (:func:`_physical_range`); no entry reaches beyond it."""
    from ..errors import PlantFileError
    from ..plant.plantfile import SCHEMA

    out = {}
    ranges = ranges if ranges is not None else [(-math.inf, math.inf)] * len(params)
    for (k, v), sd, (r_lo, r_hi) in zip(params.items(), std, ranges):
        value = v["value"]
        lo_ci, hi_ci = v["ci95"]
        if not (np.isfinite(sd) and sd > 0):
            continue
        section, sub = k.split(".")
        kind = SCHEMA[section][sub]
        floor = 0.0 if kind in ("positive", "non-negative", "fraction in (0, 1]") else -math.inf
        ceil = 1.0 if kind == "fraction in (0, 1]" else math.inf
        floor, ceil = max(floor, r_lo), min(ceil, r_hi)
        if not floor <= value <= ceil:
            continue
        src = f"fit: {names} (95 % CI {lo_ci:.6g}..{hi_ci:.6g}; sigma from the fit's covariance)"
        trunc = min(_Z95, (value - floor) / sd * (1 - 1e-9), (ceil - value) / sd * (1 - 1e-9))
        if trunc >= 0.1:
            entry = {"dist": "normal", "sigma": float(sd), "truncate": float(round(trunc, 6) if trunc < _Z95 else _Z95),
                     "source": src}
            ends = (value - entry["truncate"] * sd, value + entry["truncate"] * sd)
        elif kind == "non-negative" and value - floor < 0.1 * sd:
            entry = {"dist": "uniform", "low": float(floor), "high": float(min(max(hi_ci, value + sd), ceil)),
                     "source": src}
            ends = (entry["low"], entry["high"])
        else:
            continue
        try:
            for e in ends:
                fitted.with_params({k: e})
        except PlantFileError:
            continue
        out[k] = entry
    return out


# --- frequency-response fit -------------------------------------------------------------------


def _frf_ts(fr: FrfRecord, plant: Plant) -> float:
    return plant.sample_time_s if fr.sample_time_s is None else fr.sample_time_s


_LIN_CACHE: dict = {}


class _Linear:
    """``(speed, load, p) -> (A, B)`` of a fidelity's model linearised at steady speed and load,
    with the values of the plant keys ``keys`` as ``p``; ``i_th`` and ``i_w`` index the nut angle
    and speed states. Built once per plant, key set and fidelity (:func:`_linear`)."""

    def __init__(self, plant: Plant, keys: Sequence[str], fidelity: str):
        import casadi as ca

        self.plant, self.keys, self.fidelity = plant, tuple(keys), fidelity
        f, names = _symbolic_rhs(plant, keys, fidelity)
        self.names = names
        self.i_th, self.i_w = names.index("theta_nut"), names.index("omega_nut")
        i_w, i_tau = self.i_w, names.index("tau_motor")
        w0, f0 = ca.SX.sym("w0"), ca.SX.sym("f0")
        p = ca.SX.sym("p", len(keys))
        x = ca.SX.sym("x", len(names))
        u = ca.SX.sym("u", 2)
        xdot = f(x, u, p)
        if fidelity == "rigid":
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
        a = plant.lead_per_rad
        z = ca.SX.sym("z", 4)
        idx = {n: i for i, n in enumerate(names)}
        xs = [0] * len(names)
        xs[idx["omega_nut"]], xs[idx["v_roller"]], xs[idx["v_screw"]] = w0, a * w0, a * w0
        xs[idx["omega_cage"]], xs[idx["x_roller"]], xs[idx["delta_screw"]], xs[idx["tau_motor"]] = z[0], z[1], z[2], z[3]
        x_op = ca.vertcat(*xs)
        rows = [idx[n] for n in ("omega_nut", "omega_cage", "v_roller", "v_screw")]
        r = f(x_op, ca.vertcat(z[3], f0), p)[rows]
        self._steady = ca.Function("steady", [z, w0, f0, p], [r, ca.jacobian(r, z)])
        self._state = ca.Function("state", [z, w0], [x_op])
        self._jac = ca.Function("lin_ab", [x, u, p], [ca.jacobian(xdot, x), ca.jacobian(xdot, u[0])])

    def _guess(self, speed: float, load: float, pv) -> np.ndarray:
        """Initial steady state of the compliant model: rigid cage ratio, Hertz deflections for
        the load on both interfaces, the rigid holding torque."""
        pl = self.plant
        vals = dict(pl.values)
        vals.update({k: float(v) for k, v in zip(self.keys, pv)})
        k_si = vals["contact.stiffness_n_per_mm_e"] * 1000.0 ** vals["contact.exponent"]
        e = vals["contact.exponent"]
        cb = math.cos(pl.flank_angle_rad)
        out = []
        for helix in (pl.helix_nut_rad, pl.helix_screw_rad):
            c = cb * math.cos(helix)
            d = (abs(load) / (pl.n_contacts * k_si * c ** (e + 1))) ** (1.0 / e) / c
            out.append(d if load >= 0 else -(d + vals["thread.backlash_mm"] * 1e-3))
        tau = load * pl.lead_per_rad / vals["friction.efficiency"] + vals["friction.no_load_torque_n_m"] \
            + vals["friction.viscous_n_m_s_per_rad"] * speed
        return np.array([speed * pl.cage_ratio, -out[0], out[1], tau])

    def __call__(self, speed: float, load: float, pv):
        pv = np.asarray(pv, float)
        if self.fidelity == "rigid":
            a, b = self._rigid(speed, load, pv)
            return np.asarray(a, float), np.asarray(b, float)
        if abs(load) < 1e-9 * self.plant.rated_load_n:
            raise ValueError(f"load_n = {load!r} for a compliant frequency response; expected the measurement's "
                             "axial load (> 0 N): without load the thread contacts sit in the backlash and no "
                             "axial mode exists")
        z = self._guess(speed, load, pv)
        zs = np.abs(z) + np.array([1.0, 1e-9, 1e-9, 1e-3 * self.plant.torque_limit])
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
        a, b = self._jac(x_op, [z[3], load], pv)
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


def _frf_eval(lin: _Linear, p, frequency_hz, speed, load, ts, delay_s):
    """Model response torque command -> nut speed at ``frequency_hz`` (sampled when ``ts > 0``)
    with a command delay of ``delay_s`` seconds."""
    from scipy.linalg import expm

    a, b = lin(speed, load, p)
    nx = a.shape[0]
    i_th, i_w = lin.i_th, lin.i_w
    s = 2j * np.pi * np.asarray(frequency_hz, float)
    eye = np.eye(nx)[None, :, :]
    if ts <= 0:  # continuous: C (sI - A)^-1 B on the speed
        rhs = np.broadcast_to(b[:, :1].astype(complex), (len(s), nx, 1))
        out = np.linalg.solve(s[:, None, None] * eye - a[None], rhs)[:, i_w, 0]
    else:  # the drive's sampled response: command held over a sample, speed = backward angle difference / ts
        m = np.zeros((nx + 1, nx + 1))
        m[:nx, :nx], m[:nx, nx] = a * ts, b[:, 0] * ts
        e = expm(m)
        phi, gam = e[:nx, :nx], e[:nx, nx]
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
    from scipy.linalg import eigvals

    lin = _linear(plant, (), "compliant")
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
        "reflected_axial_inertia_ratio": float(plant.values["screw.mass_kg"] * plant.lead_per_rad**2
                                               / plant.values["nut.inertia_kg_m2"]),
        "max_effect_db": float(20 / math.log(10) * np.max(np.abs(d.real))),
        "max_effect_deg": float(np.degrees(np.max(np.abs(d.imag)))),
        "at_hz": float(f[i]),
    }


#: A response whose log varies by less than this (RMS, nepers and radians) has no spread to
#: normalise a fit % by (a constant response: round-off gave "fit -6.4e17 %").
FRF_SPREAD_MIN = 1e-6


def _frf_fit_percent(measured, model) -> float:
    """Fit % of a frequency response on its complex logarithm (magnitude and phase alike); NaN
    when the measured response does not vary (RMS spread of its log below :data:`FRF_SPREAD_MIN`)."""
    lm, lg = np.log(measured), np.log(model)
    d = np.angle(np.exp(1j * (lm.imag - lg.imag)))
    err = np.sqrt(np.sum((lm.real - lg.real) ** 2 + d**2))
    ref = np.sqrt(np.sum((lm.real - lm.real.mean()) ** 2 + (np.unwrap(lm.imag) - np.unwrap(lm.imag).mean()) ** 2))
    return float(100.0 * (1.0 - err / ref)) if ref > FRF_SPREAD_MIN * math.sqrt(len(lm)) else float("nan")


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
    max_nfev : int
        Budget of model evaluations.
    keep_unidentified : bool
        Keys the responses cannot inform keep the base value (see :func:`fit_plant`).
    uncertainty : {"keep", "fit"}
        The fitted keys' ``[uncertainty]`` entries (see :func:`fit_plant`).

    Returns
    -------
    FitResult
    """
    from scipy.optimize import least_squares

    from ..plant.plantfile import load_plant

    plant = load_plant() if plant is None else plant
    frf = list(frf)
    if not frf:
        raise ValueError("frf = []; expected at least one frequency response")
    frf = _checked_inputs([], [], frf, plant)[2]
    if uncertainty not in UNCERTAINTY_MODES:
        raise ValueError(f"uncertainty = {uncertainty!r}; expected one of {', '.join(map(repr, UNCERTAINTY_MODES))}")
    if fidelity not in ("rigid", "compliant"):
        raise ValueError(f"fidelity = {fidelity!r}; expected 'rigid' or 'compliant' for a frequency-response fit")
    keys = _check_keys(FRF_KEYS_COMPLIANT if keys is None and fidelity == "compliant" else
                       FRF_KEYS if keys is None else keys, fidelity)
    if not (isinstance(delay_samples, int) and 0 <= delay_samples <= 10):
        raise ValueError(f"delay_samples = {delay_samples!r}; expected an integer 0..10")
    ts_fit = min(_frf_ts(fr, plant) or plant.sample_time_s for fr in frf)
    bounds = []
    for k in keys:
        if k == DELAY_KEY:
            bounds.append((0.0, (delay_samples + 10) * ts_fit, ts_fit))
        else:
            bounds.append(_bounds(plant, k, ts_fit))
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
        ts = _frf_ts(fr, plant)
        return sv[i_d] * scales[i_d] if i_d is not None else (delay_samples * ts if ts > 0 else 0.0)

    def resid(sv):
        out = []
        pv = (sv * scales)[i_p]
        for fr, w in zip(frf, weights):
            g = _frf_eval(lin, pv, fr.frequency_hz, fr.speed_rad_s, fr.load_n, _frf_ts(fr, plant), delay_of(sv, fr))
            d = np.log(g) - np.log(fr.response)
            out += [w * d.real, w * np.angle(np.exp(1j * d.imag))]
        return np.concatenate(out)

    if "contact.stiffness_n_per_mm_e" in keys:  # bounded scan of the stiffness: the start of the fit
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
    a_inv, null, ratios = _info_split(jac / cn)
    inv = a_inv / np.outer(cn, cn)
    cov = s2 * inv * np.outer(scales, scales)
    null = null / cn[:, None] * scales[:, None]
    values = sol.x * scales
    names_txt = ", ".join(fr.name for fr in frf)
    warns = [w for fr in frf for w in fr.warnings]
    params, corr, fitted, reflected, delay, reasons = _finish(plant, keys, values, cov, lo * scales, hi * scales, names_txt,
                                                              warns, ts_fit, keep_unidentified, null, ratios,
                                                              uncertainty)
    if "contact.stiffness_n_per_mm_e" in keys:
        warns += _mode_warnings(fitted, frf, math.sqrt(s2) / np.sqrt(np.mean(np.concatenate(weights) ** 2)))
    fit_pct, traces = {}, {}
    for fr in frf:
        g = frf_response(fitted, fr.frequency_hz, speed_rad_s=fr.speed_rad_s, load_n=fr.load_n,
                         sample_time_s=_frf_ts(fr, plant), delay_s=delay_of(sol.x, fr), fidelity=fidelity)
        fit_pct[fr.name] = round(_frf_fit_percent(fr.response, g), 3)
        traces[fr.name] = {"frequency_hz": fr.frequency_hz, "measured": fr.response, "model": g}
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
    return FitResult(fitted, params, reflected, corr, keys, fit_pct, warns, solver, traces, delay, reasons)


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
        ts = _frf_ts(fr, fitted)
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


def _figure_stem(name: str, used: set) -> str:
    import re
    from pathlib import PurePath

    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", PurePath(name).stem) or "data"
    out, i = stem, 2
    while out in used:
        out, i = f"{stem}-{i}", i + 1
    used.add(out)
    return out


def fit_figures(result: FitResult) -> dict:
    """Figures of a fit: per time-domain record the measured and simulated nut speed with the
    residual below; per frequency response a Bode overlay (measured vs fitted model).

    Parameters
    ----------
    result : FitResult

    Returns
    -------
    dict
        ``{file stem: matplotlib Figure}`` (``<record>-fit`` and ``<response>-bode``); the
        caller saves and closes them.
    """
    import matplotlib.pyplot as plt

    figs, used = {}, set()
    for name, tr in result.traces.items():
        stem = _figure_stem(name, used)
        if "time_s" in tr:
            t, meas, mod, label, joins = _overlay_data(tr)
            fig, (ax1, ax2) = plt.subplots(2, 1, sharex=True, figsize=(8, 5.5), height_ratios=(2, 1))
            ax1.plot(t, meas, lw=0.8, color="0.5", label="measured (angle difference)")
            ax1.plot(t, mod, lw=1.0, color="C0", label=label)
            for tj in joins:  # only when the shooting segments themselves are shown
                ax1.axvline(tj, color="C1", lw=0.4, alpha=0.5)
            ax1.set_ylabel("nut speed (rad/s)")
            ax1.set_title(f"{name}: fit {result.fit_percent.get(name, float('nan')):.1f} %")
            ax1.legend(loc="best", fontsize=8)
            ax2.plot(t, meas - mod, lw=0.6, color="C3")
            ax2.axhline(0.0, color="0.3", lw=0.5)
            ax2.set_ylabel("residual (rad/s)")
            ax2.set_xlabel("time (s)")
            for ax in (ax1, ax2):
                ax.grid(True, alpha=0.3)
            fig.tight_layout()
            figs[f"{stem}-fit"] = fig
        else:
            f = np.asarray(tr["frequency_hz"], float)
            gm, gf = np.asarray(tr["measured"]), np.asarray(tr["model"])
            fig, (ax1, ax2) = plt.subplots(2, 1, sharex=True, figsize=(8, 5.5))
            ax1.semilogx(f, 20 * np.log10(np.abs(gm)), ".", ms=4, color="0.4", label="measured")
            ax1.semilogx(f, 20 * np.log10(np.abs(gf)), "-", color="C0", label="fitted model")
            ax1.set_ylabel("|G| (dB re 1 rad/s per N m)")
            ax1.set_title(f"{name}: fit {result.fit_percent.get(name, float('nan')):.1f} %")
            ax1.legend(loc="best", fontsize=8)
            pm = np.degrees(np.unwrap(np.angle(gm)))
            pf = np.degrees(np.unwrap(np.angle(gf)))
            ax2.semilogx(f, pm, ".", ms=4, color="0.4")
            ax2.semilogx(f, pf, "-", color="C0")
            ax2.set_ylabel("phase (deg)")
            ax2.set_xlabel("frequency (Hz)")
            for ax in (ax1, ax2):
                ax.grid(True, which="both", alpha=0.3)
            fig.tight_layout()
            figs[f"{stem}-bode"] = fig
    return figs


def _overlay_data(tr: dict):
    """What a record's overlay figure plots: ``(time_s, measured, model, model label, join
    times)``. The model is the continuous simulation of the fitted plant when there is one
    (:meth:`_Problem.simulate`: no segment joins, so no resets that look like model error);
    otherwise the shooting segments, each drawn apart (NaN between them) with its start marked.
    Gaps in the data (left-out stretches) are broken with NaN too."""
    sim = tr.get("simulated")
    if sim is not None:
        t, meas, mod = (np.asarray(sim[k], float) for k in ("time_s", "measured", "model"))
        breaks, joins, label = np.zeros(0, int), [], "fitted plant, one continuous simulation"
    else:
        t, meas, mod = (np.asarray(tr[k], float) for k in ("time_s", "measured", "model"))
        breaks = np.asarray(tr.get("joins", np.zeros(0, int)), int)
        joins = [float(t[j]) for j in breaks]
        label = "fitted model (shooting segments; each starts at a marked join)"
    gap = np.flatnonzero(np.diff(t) > 1.5 * float(np.median(np.diff(t))))
    cut = np.union1d(gap + 1, breaks)
    return (*(np.insert(a, cut, np.nan) for a in (t, meas, mod)), label, joins)


def figure_names(names: Sequence[str], frf_names: Sequence[str] = ()) -> list[str]:
    """File stems :func:`fit_figures` will use for these record and response names (in order:
    fitted and validation records, then responses), so output paths can be checked first."""
    used: set = set()
    return [f"{_figure_stem(n, used)}-fit" for n in names] + [f"{_figure_stem(n, used)}-bode" for n in frf_names]


_REMEDY_KEY = {
    "friction.efficiency": "record with load changes (load steps) so that load-dependent friction shows",
    "friction.no_load_torque_n_m": "record speed reversals (a staircase through both directions)",
    "friction.viscous_n_m_s_per_rad": "record several speed levels",
    "drive.current_loop_bandwidth_hz": "excite higher frequencies (multisine up to a few hundred Hz) or fix it with --fit",
    "nut.inertia_kg_m2": "excite accelerations (multisine or speed steps)",
    "drive.command_delay_s": "measure up to the current-loop bandwidth, or fix the delay (leave it out of --fit)",
    "contact.stiffness_n_per_mm_e": "measure a frequency response that covers the axial mode (under load), "
                                    "or leave the stiffness out of --fit",
    "contact.damping_n_s_per_mm": "measure the axial mode's peak with a fine frequency resolution",
}


def fit_percent(measured: NDArray[np.float64], model: NDArray[np.float64]) -> float:
    """Normalised-RMS fit, % : ``100 (1 - |y - y_model| / |y - mean(y)|)``.

    Examples
    --------
    >>> fit_percent(np.array([1.0, 2.0, 3.0]), np.array([1.0, 2.0, 3.0]))
    100.0
    """
    den = float(np.linalg.norm(measured - np.mean(measured)))
    if den == 0:
        return float("nan")
    return float(100.0 * (1.0 - np.linalg.norm(measured - model) / den))


class _Problem:
    """Collocation equations, residuals and the constrained Gauss-Newton solver of a fit.

    Unknowns (all scaled): ``V`` the stage states of every sample interval (deviations from a
    data-based reference, in units of ``state_scale``), ``X0`` each segment's initial state,
    ``s`` the parameters in units of their scale. The residuals are linear in ``V`` and ``X0``;
    each Gauss-Newton step linearises the collocation equations, eliminates ``V`` segment by
    segment (sparse LU of the block-bidiagonal equations) and solves a small bounded linear
    least-squares problem for ``(s, X0)``.
    """

    def __init__(self, plant, keys, scales, fidelity, records, ts, segment_s, delay, substeps=1,
                 min_speed_rad_s=0.0):
        import casadi as ca

        self.plant, self.records, self.ts = plant, records, ts
        self.fidelity, self.delay = fidelity, int(delay)
        self.scales = np.asarray(scales, float)
        f, names = _symbolic_rhs(plant, keys, fidelity)
        self.names = names
        nx = self.nx = len(names)
        npar = self.npar = len(keys)
        self.i_th = i_th = names.index("theta_nut")
        i_w, i_tau = names.index("omega_nut"), names.index("tau_motor")
        self.nsub = nsub = int(substeps)
        self.ns = ns = 3 * nsub  # collocation stages per sample interval
        seg_n = max(2, int(round(segment_s / ts)))
        refs = [_reference(r, plant) for r in records]
        self.segs, self.left_out = _segments(records, seg_n, refs, min_speed_rad_s)
        segs = self.segs
        if not segs:
            raise ValueError(f"{', '.join(r.name for r in records)}: no stretch of at least {MIN_SEGMENT} samples "
                             f"with |speed| >= {min_speed_rad_s:.3g} rad/s; expected data at speed (not only "
                             "standstill and reversals)")
        q = 2 * math.pi / plant.encoder_counts
        self.sigma0 = max(q / math.sqrt(12.0), 1e-9)
        w_scale = max(max(float(np.max(np.abs(r[1]))) for r in refs), 1.0)
        sc = np.ones(nx)
        sc[i_th] = max(w_scale * ts, 1e-6)
        sc[i_w] = 0.1 * w_scale
        sc[i_tau] = 0.1 * plant.torque_limit
        self.S = sc
        uu, hh, xr0, xrs = [], [], [], []
        for sg in segs:
            rec, ref = records[sg.rec], refs[sg.rec]
            ks = np.arange(sg.k0, sg.k0 + sg.n)
            kd = np.clip(ks - delay, 0, None)
            uu.append(np.vstack([rec.torque_command_n_m[kd], rec.axial_load_n[ks]]))
            hh.append(np.diff(rec.time_s)[ks])
            full = np.zeros((nx, rec.n))
            full[[i_th, i_w, i_tau]] = ref
            xr0.append(full[:, sg.k0])
            st = [full[:, ks] + (m + c) / nsub * (full[:, ks + 1] - full[:, ks]) for m in range(nsub) for c in _RADAU_C]
            xrs.append(np.stack(st, axis=1).reshape(nx, ns * sg.n, order="F"))
        self.U, self.H = np.hstack(uu), np.concatenate(hh)
        self.XR, self.XR0 = np.hstack(xrs), np.column_stack(xr0)
        self.M = M = self.U.shape[1]
        self.use_angle = all(r.nut_angle_rad is not None for r in records)
        self.residual_unit = "rad (encoder angle)" if self.use_angle else "rad/s (speed)"
        # One interval: scaled collocation residual and its Jacobians, mapped over all intervals.
        xs = ca.SX.sym("xs", nx)
        K = ca.SX.sym("K", nx, ns)
        u = ca.SX.sym("u", 2)
        h = ca.SX.sym("h")
        p = ca.SX.sym("p", npar)
        fk = [f(K[:, j], u, p) for j in range(ns)]
        rows = []
        for m in range(nsub):  # nsub Radau steps of h / nsub, each from the previous step's end
            x_start = xs if m == 0 else K[:, 3 * m - 1]
            for j in range(3):
                acc = sum(_RADAU_A[j][l] * fk[3 * m + l] for l in range(3))
                rows.append((K[:, 3 * m + j] - x_start - (h / nsub) * acc) / ca.DM(sc))
        res = ca.vertcat(*rows)
        kv = ca.vec(K)
        # Dense Jacobian blocks, evaluated into preallocated NumPy buffers (no DM conversion:
        # that cost twice the evaluation itself); the parameters are one column for all intervals.
        fun = ca.Function("coll", [xs, K, u, h, p],
                          [res, ca.densify(ca.jacobian(res, kv)), ca.densify(ca.jacobian(res, xs)),
                           ca.densify(ca.jacobian(res, p))])
        self.blocks = _Buffered(fun.map("coll_map", "serial", M, [4], []))
        # The collocation residual alone (line-search merits need no Jacobians).
        self.residual_blocks = _Buffered(ca.Function("coll_res", [xs, K, u, h, p], [res])
                                         .map("coll_res_map", "serial", M, [4], []))
        # Segment bookkeeping: first interval and sample offsets.
        self.first = np.cumsum([0] + [sg.n for sg in segs[:-1]])
        n3 = ns * nx
        # Sparse pattern of one segment's block-bidiagonal equations (same for all lengths n).
        self._patterns = {}
        self.n3 = n3

    # --- evaluation -----------------------------------------------------------------------
    def _physical(self, V, X0):
        nx, M = self.nx, self.M
        K = self.XR + V.reshape(M * self.ns, nx).T * self.S[:, None]
        x0 = self.XR0 + X0.reshape(len(self.segs), nx).T * self.S[:, None]
        return K, x0

    def _starts(self, K, x0):
        ends = K[:, self.ns - 1::self.ns]
        xs = np.empty((self.nx, self.M))
        for g, sg in enumerate(self.segs):
            m0 = self.first[g]
            xs[:, m0] = x0[:, g]
            xs[:, m0 + 1:m0 + sg.n] = ends[:, m0:m0 + sg.n - 1]
        return xs

    def thetas(self, V, X0):
        """Model angle (rad) at every sample of every segment, segment after segment."""
        K, x0 = self._physical(V, X0)
        ends = K[self.i_th, self.ns - 1::self.ns]
        out = []
        for g, sg in enumerate(self.segs):
            m0 = self.first[g]
            out.append(np.concatenate([[x0[self.i_th, g]], ends[m0:m0 + sg.n]]))
        return out

    def residuals(self, V, X0):
        """Weighted residual vectors per segment (dimensionless: in units of the quantisation noise)."""
        out = []
        for g, (sg, th) in enumerate(zip(self.segs, self.thetas(V, X0))):
            rec = self.records[sg.rec]
            if self.use_angle:
                out.append((th - rec.nut_angle_rad[sg.k0:sg.k0 + sg.n + 1]) / self.sigma0)
            else:
                h = np.diff(rec.time_s[sg.k0:sg.k0 + sg.n + 1])
                meas = rec.nut_speed_rad_s[sg.k0 + 1:sg.k0 + sg.n + 1]
                out.append((np.diff(th) / h - meas) / (self.sigma0 / self.ts))
        return out

    def _a_matrices(self, g):
        """d(residual)/d(V of the segment) (sparse) and d(residual)/d(X0 of the segment) (dense)."""
        from scipy.sparse import csr_matrix

        sg = self.segs[g]
        nx, n3, n = self.nx, self.n3, sg.n
        col_end = np.arange(n) * n3 + (self.ns - 1) * nx + self.i_th  # end-stage angle of each interval
        w = self.S[self.i_th] / self.sigma0
        if self.use_angle:
            a_v = csr_matrix((np.full(n, w), (np.arange(1, n + 1), col_end)), shape=(n + 1, n * n3))
            a_x = np.zeros((n + 1, nx))
            a_x[0, self.i_th] = w
        else:
            h = np.diff(self.records[sg.rec].time_s[sg.k0:sg.k0 + n + 1])
            wv = w * self.ts / h
            rows = np.concatenate([np.arange(n), np.arange(1, n)])
            cols = np.concatenate([col_end, col_end[:-1]])
            vals = np.concatenate([wv, -wv[1:]])
            a_v = csr_matrix((vals, (rows, cols)), shape=(n, n * n3))
            a_x = np.zeros((n, nx))
            a_x[0, self.i_th] = -wv[0]
        return a_v, a_x

    def linearise(self, V, X0, s):
        """Constraint residual, and per segment: the condensed residual and Jacobian columns."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.linalg import splu

        nx, n3, npar, M = self.nx, self.n3, self.npar, self.M
        K, x0 = self._physical(V, X0)
        xs = self._starts(K, x0)
        res, jk, jxs, jp = self.blocks(xs, K, self.U, self.H, s * self.scales)
        res = res.reshape(n3, M, order="F")
        # Column-major blocks side by side -> (rows, interval, cols of the block).
        jk = jk.reshape(n3, n3, M, order="F").transpose(0, 2, 1)
        jxs = jxs.reshape(n3, nx, M, order="F").transpose(0, 2, 1)
        jp = jp.reshape(n3, npar, M, order="F").transpose(0, 2, 1)
        if not (np.all(np.isfinite(res)) and np.all(np.isfinite(jk)) and np.all(np.isfinite(jp))):
            bad = int(np.argmax(~np.all(np.isfinite(res), axis=0)))
            raise FitError(f"model not finite at interval {bad} (t = {bad * self.ts:.6g} s); remedy: check the "
                           "data's units and sample time, or start from a closer base plant (--plant)")
        jk = jk * np.tile(self.S, self.ns)[None, None, :]
        jxs = jxs * self.S[None, None, :]
        jp = jp * self.scales[None, None, :]
        resid = self.residuals(V, X0)
        out = []
        for g, sg in enumerate(self.segs):
            m0, n = self.first[g], sg.n
            sl = slice(m0, m0 + n)
            # Block-bidiagonal equations of the segment.
            ii, jj = np.meshgrid(np.arange(n3), np.arange(n3), indexing="ij")
            rows = [(np.arange(n)[:, None, None] * n3 + ii[None]).ravel()]
            cols = [(np.arange(n)[:, None, None] * n3 + jj[None]).ravel()]
            vals = [np.moveaxis(jk[:, sl, :], 1, 0).ravel()]
            if n > 1:
                ia, ib = np.meshgrid(np.arange(n3), np.arange(nx), indexing="ij")
                rows.append((np.arange(1, n)[:, None, None] * n3 + ia[None]).ravel())
                cols.append((np.arange(n - 1)[:, None, None] * n3 + (self.ns - 1) * nx + ib[None]).ravel())
                vals.append(np.moveaxis(jxs[:, m0 + 1:m0 + n, :], 1, 0).ravel())
            gv = coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                            shape=(n * n3, n * n3)).tocsc()
            g_res = res[:, sl].T.ravel()
            g_s = np.moveaxis(jp[:, sl, :], 1, 0).reshape(n * n3, npar)
            g_x0 = np.zeros((n * n3, nx))
            g_x0[:n3] = jxs[:, m0, :]
            try:
                lu = splu(gv)
                z = lu.solve(np.column_stack([g_res, g_s, g_x0]))
            except RuntimeError as exc:
                raise FitError(f"collocation equations singular in segment {g} ({exc}); remedy: shorter "
                               "segments or a closer base plant (--plant)") from None
            if not np.all(np.isfinite(z)):
                raise FitError(f"collocation equations singular in segment {g}; remedy: shorter segments "
                               "or a closer base plant (--plant)")
            a_v, a_x = self._a_matrices(g)
            r_lin = resid[g] - a_v @ z[:, 0]
            j_s = -(a_v @ z[:, 1:1 + npar])
            j_x = a_x - a_v @ z[:, 1 + npar:]
            out.append((r_lin, j_s, j_x, z))
        return res, out

    def _merit_terms(self, V, X0, s):
        """Largest scaled collocation residual and the objective at a trial point."""
        try:
            K, x0 = self._physical(V, X0)
            (r,) = self.residual_blocks(self._starts(K, x0), K, self.U, self.H, s * self.scales)
            g = float(np.max(np.abs(r)))
            f = 0.5 * sum(float(e @ e) for e in self.residuals(V, X0))
        except RuntimeError:
            return float("inf"), float("inf")
        return (g, f) if np.isfinite(g) and np.isfinite(f) else (float("inf"), float("inf"))

    def solve(self, s0, lo, hi, max_iter, tol, fixed, box=0.3, warm=3):
        from scipy.optimize import lsq_linear

        nx, nseg, npar = self.nx, len(self.segs), self.npar
        V = np.zeros(self.n3 * self.M)
        X0 = np.zeros(nx * nseg)
        s = np.array(s0, float)
        status, it = "maximum iterations", 0
        free_steps = 3
        # Warm-up: ``warm`` steps on the states alone (parameters held) bring the trajectories
        # close to the data before the parameters move.
        warm = 0 if fixed else int(warm)
        g_norm = f_val = float("nan")
        g_hist: list[float] = []
        for it in range(1, int(max_iter) + warm + 1):
            res, lin = self.linearise(V, X0, s)
            g_norm = float(np.max(np.abs(res)))
            g_hist.append(g_norm)
            if (len(g_hist) > warm + STALL_ITERATIONS and g_norm > 1e-6
                    and g_norm > 0.9 * g_hist[-1 - STALL_ITERATIONS]):
                status = "stalled"  # the constraint residual no longer falls: give this attempt up early
                break
            f_val = 0.5 * sum(float(r @ r) for r in self.residuals(V, X0))
            js, rv, backs = _condense(lin)
            se = None
            if fixed or npar == 0 or it <= warm:
                d_s = np.zeros(npar)
            else:
                cn = np.linalg.norm(js, axis=0)
                cn[cn == 0] = 1.0
                # ``box``: trust region of one step, in units of the parameter scales
                lb_s, ub_s = np.maximum(lo - s, -box), np.minimum(hi - s, box)
                sol = lsq_linear(js / cn, -rv, bounds=(lb_s * cn, ub_s * cn), method="bvls", max_iter=100)
                d_s = sol.x / cn
                # Standard errors of the scaled parameters (white-residual estimate): a step far
                # below them changes nothing the intervals can resolve.
                dof = max(len(rv) - npar - nx * nseg, 1)
                s2 = float(rv @ rv) / dof
                inv = np.linalg.pinv((js / cn).T @ (js / cn), rcond=1e-12, hermitian=True)
                se = np.sqrt(np.clip(np.diag(inv), 0.0, None) * s2) / cn
            d_x0 = np.concatenate([back(d_s) for back in backs])
            step = {"s": d_s, "X0": d_x0}
            step["V"] = np.concatenate([
                -(z[:, 0] + z[:, 1:1 + npar] @ d_s + z[:, 1 + npar:] @ d_x0[g * nx:(g + 1) * nx])
                for g, (*_, z) in enumerate(lin)])
            alpha, accepted = 1.0, False
            for _ in range(12):
                V1, X1, s1 = V + alpha * step["V"], X0 + alpha * step["X0"], np.clip(s + alpha * d_s, lo, hi)
                g1, f1 = self._merit_terms(V1, X1, s1)
                if np.isfinite(g1) and (g1 < (1 - 1e-4 * alpha) * g_norm
                                        or (g1 <= max(g_norm, 1e-8) and f1 <= f_val * (1 + 1e-9) + 1e-12)):
                    accepted = True
                    break
                alpha *= 0.5
            if not accepted:  # a bounded number of full (non-monotone) steps, then give up
                free_steps -= 1
                if free_steps < 0:
                    status = "line search failed"
                    break
                alpha = 1.0
                V1, X1, s1 = V + step["V"], X0 + step["X0"], np.clip(s + d_s, lo, hi)
                g1, f1 = self._merit_terms(V1, X1, s1)
                if not np.isfinite(g1):
                    status = "diverged"
                    break
            V, X0, s = V1, X1, s1
            small = bool(np.all(np.abs(alpha * d_s) < np.maximum(tol, STEP_SE_FRACTION * se))) if npar and se is not None else True
            if it > warm and accepted and g1 < 1e-8 and small and float(np.max(np.abs(alpha * step["X0"]))) < 1e-3:
                status = "converged"
                g_norm, f_val = g1, f1
                break
        else:
            if not np.isfinite(g_norm):
                status = "diverged"
        self.last_iterations = it
        if status != "converged":
            raise FitError(
                f"fit did not converge: Gauss-Newton status {status!r} after {it} iterations (constraint residual "
                f"{g_norm:.3g}); remedy: check the data (units, that the command drives this actuator, sample time), "
                "fit fewer parameters (--fit), start from a closer base plant (--plant) or use shorter segments"
            )
        self._final = (V, X0, s)
        out = {"V": V, "X0": X0, "s": s, "status": status, "iterations": it, "objective": f_val}
        out["fit_percent"], out["traces"] = self._fit_percent(self.thetas(V, X0))
        return out

    def simulate(self, sol, plant: Plant) -> dict:
        """One continuous simulation of ``plant`` per record (the figures' model trace).

        From the fitted initial state of the record's first segment to the record's end, with
        the logged command (held over each sample, ``delay`` samples late) and load, through
        the left-out stretches too: no segment joins, so nothing in the trace is a reset of the
        multiple shooting. CVODES (BDF, stiff), one sample per step of a ``mapaccum``.

        Returns
        -------
        dict
            ``{record name: {"time_s", "measured", "model"}}`` (nut speed over each sample
            interval, rad/s, at the interval's end); a record whose simulation fails is left out.
        """
        import casadi as ca

        f, names = _symbolic_rhs(plant, (), self.fidelity)
        nx, sc = len(names), self.S
        x = ca.SX.sym("x", nx)
        u = ca.SX.sym("u", 2)
        h = ca.SX.sym("h")
        ode = h * f(x * ca.DM(sc), u, ca.DM.zeros(0)) / ca.DM(sc)
        step = ca.integrator("fit_sim", "cvodes", {"x": x, "p": ca.vertcat(u, h), "ode": ode}, 0.0, 1.0,
                             {"abstol": 1e-9, "reltol": 1e-8, "max_num_steps": 20000})
        _, x0 = self._physical(sol["V"], sol["X0"])
        out = {}
        for r, rec in enumerate(self.records):
            g = next((g for g, sg in enumerate(self.segs) if sg.rec == r), None)
            if g is None or rec.name in out:
                continue
            k0 = self.segs[g].k0
            ks = np.arange(k0, rec.n - 1)
            kd = np.clip(ks - self.delay, 0, None)
            pu = np.vstack([rec.torque_command_n_m[kd], rec.axial_load_n[ks], np.diff(rec.time_s)[ks]])
            try:
                xs = np.asarray(step.mapaccum("fit_sim_acc", len(ks), ["x0"], ["xf"])(
                    x0=x0[:, g] / sc, p=pu)["xf"], float) * sc[:, None]
            except RuntimeError:
                continue
            th = np.concatenate([[x0[self.i_th, g]], xs[self.i_th]])
            v = np.diff(th) / np.diff(rec.time_s[k0:])
            if np.all(np.isfinite(v)):
                out[rec.name] = {"time_s": rec.time_s[k0 + 1:], "measured": rec.speed_rad_s[k0:], "model": v}
        return out

    def _fit_percent(self, thetas):
        """Speed fit % per record from the model angles at the samples of each segment."""
        per: dict[str, tuple] = {}
        for sg, th in zip(self.segs, thetas):
            rec = self.records[sg.rec]
            v_model = np.diff(th) / np.diff(rec.time_s[sg.k0:sg.k0 + sg.n + 1])
            v_meas = rec.speed_rad_s[sg.k0:sg.k0 + sg.n]
            m, mm, tt, jj = per.setdefault(rec.name, ([], [], [], []))
            jj.append(sum(len(a) for a in m))
            m.append(v_meas)
            mm.append(v_model)
            tt.append(rec.time_s[sg.k0 + 1:sg.k0 + sg.n + 1])
        out, traces = {}, {}
        for name, (m, mm, tt, jj) in per.items():
            a, b = np.concatenate(m), np.concatenate(mm)
            out[name] = round(fit_percent(a, b), 3)
            # joins: index of each segment's first sample in these arrays (its own initial state)
            traces[name] = {"time_s": np.concatenate(tt), "measured": a, "model": b, "joins": np.array(jj[1:], int)}
        return out, traces

    def covariance(self, sol):
        """Covariance of the scaled parameters (HAC sandwich), residual std, residual count, columns, info.

        The residuals of a real fit are not white: quantisation and the speed loop colour the
        noise, and any model error is smooth in time. The covariance is therefore the sandwich
        ``A^-1 Omega A^-1`` (``A = J^T J`` of the condensed Jacobian, segment initial states
        projected out) with ``Omega`` the Newey-West (Bartlett-kernel) long-run covariance of the
        scores ``J_k r_k`` summed within each segment (segments have free initial states, so they
        are independent); the bandwidth is the Newey-West rule or the lag where the pooled
        residual autocorrelation falls below its ``2/sqrt(N)`` band, whichever is larger (bounded
        by a quarter segment). With white residuals it equals the classic ``s^2 A^-1``.
        """
        V, X0, s = sol["V"], sol["X0"], sol["s"]
        nx, nseg, npar = self.nx, len(self.segs), self.npar
        _, lin = self.linearise(V, X0, s)
        js, r, _ = _condense(lin)
        lens = [len(item[0]) for item in lin]
        n_rows = len(r)
        n_cols = npar + nx * nseg
        dof = max(n_rows - n_cols, 1)
        s2 = float(r @ r) / dof
        cn = np.linalg.norm(js, axis=0)
        cn[cn == 0] = 1.0
        jn = js / cn
        a_inv, null, ratios = _info_split(jn)
        bounds = np.cumsum([0] + lens)
        parts = [slice(int(bounds[i]), int(bounds[i + 1])) for i in range(len(lens))]
        # Pooled residual autocorrelation within segments, lags 1..max_lag.
        n_min = min(lens)
        max_lag = max(1, min(n_min // 4, 200))
        den = float(r @ r)
        acf = np.array([sum(float(r[p][l:] @ r[p][:-l]) for p in parts if len(r[p]) > l) / den
                        for l in range(1, max_lag + 1)]) if den > 0 else np.zeros(max_lag)
        band = 2.0 / math.sqrt(max(n_rows, 1))
        below = np.flatnonzero(np.abs(acf) < band)
        lag_acf = int(below[0]) if below.size else max_lag  # lags before the first one inside the band
        lag_nw = int(4 * (float(np.mean(lens)) / 100.0) ** (2.0 / 9.0))
        L = int(min(max(lag_nw, lag_acf), max_lag))
        # Prewhitened HAC (Andrews & Monahan, Econometrica 60(4) 1992): a VAR(1) on the scores
        # takes out the bulk of the colour, Bartlett-kernel Newey-West on what is left, recoloured.
        gs = [jn[p] * r[p][:, None] for p in parts]
        s_lag = sum(g[1:].T @ g[:-1] for g in gs if len(g) > 1)
        s_0 = sum(g[:-1].T @ g[:-1] for g in gs if len(g) > 1)
        a_var = s_lag @ np.linalg.pinv(s_0, rcond=1e-12)
        u_, sv, vt = np.linalg.svd(a_var)  # keep it away from a unit root (their adjustment)
        a_var = (u_ * np.minimum(sv, 0.97)) @ vt
        omega = np.zeros((npar, npar))
        for g in gs:
            e = g.copy()
            e[1:] -= g[:-1] @ a_var.T
            omega += e.T @ e
            for l in range(1, min(L, len(e) - 1) + 1):
                c = e[l:].T @ e[:-l]
                omega += (1.0 - l / (L + 1.0)) * (c + c.T)
        recolour = np.linalg.inv(np.eye(npar) - a_var)
        omega = recolour @ omega @ recolour.T
        omega *= n_rows / dof
        cov_hac = a_inv @ omega @ a_inv
        cov = cov_hac / np.outer(cn, cn)
        unit_sigma = self.sigma0 if self.use_angle else self.sigma0 / self.ts
        info = {"covariance": "prewhitened (VAR(1)) Newey-West HAC sandwich over segments",
                "hac_bandwidth_samples": L, "residual_acf_band_lag": lag_acf,
                "residual_autocorrelation_lag1": float(acf[0]) if len(acf) else 0.0,
                "ci_widening_vs_white": float(np.sqrt(np.max(np.diag(cov_hac) / np.maximum(s2 * np.diag(a_inv), 1e-300)))),
                "singular_value_ratios": [float(x) for x in ratios], "rank_tolerance": RANK_RTOL,
                "uninformed_directions": int(null.shape[1])}
        self.null_scaled = null / cn[:, None]  # uninformed directions in the scaled parameters
        return cov, math.sqrt(s2) * unit_sigma, n_rows, n_cols, info


class _Buffered:
    """A CasADi function evaluated straight from and into NumPy arrays (``Function.buffer``).

    Inputs are taken in column-major order and checked for size; outputs are new flat
    column-major arrays of the outputs' nonzeros (dense outputs: every entry).
    """

    def __init__(self, fun):
        self.fun = fun
        self.n_in = [int(fun.nnz_in(i)) for i in range(fun.n_in())]
        self.n_out = [int(fun.nnz_out(i)) for i in range(fun.n_out())]

    def __call__(self, *args):
        if len(args) != len(self.n_in):
            raise ValueError(f"{self.fun.name()}: {len(args)} inputs; expected {len(self.n_in)}")
        flat = [np.ascontiguousarray(np.asarray(a, dtype=float).ravel(order="F")) for a in args]
        for i, (a, n) in enumerate(zip(flat, self.n_in)):
            if a.size != n:  # the buffer interface reads exactly n values: never hand it fewer
                raise ValueError(f"{self.fun.name()}: input {i} has {a.size} values; expected {n}")
        outs = [np.empty(n) for n in self.n_out]
        buf, evaluate = self.fun.buffer()  # a fresh buffer per call: thread-safe, references held here
        for i, a in enumerate(flat):
            buf.set_arg(i, a)
        for i, o in enumerate(outs):
            buf.set_res(i, o)
        evaluate()
        return outs


def _condense(lin):
    """Eliminate each segment's initial state from the linearised least-squares problem.

    Returns the parameter Jacobian and residual with the initial-state directions projected
    out (their normal equations are the Schur complement for the parameters) and, per segment,
    a function giving the initial-state step for a parameter step.
    """
    js_parts, r_parts, backs = [], [], []
    for r_lin, j_s, j_x, _ in lin:
        q, rr = np.linalg.qr(j_x)
        keep = np.abs(np.diag(rr)) > 1e-12 * max(1.0, float(np.max(np.abs(rr))))
        q, rr = q[:, keep], rr[np.ix_(keep, keep)]
        js_parts.append(j_s - q @ (q.T @ j_s))
        r_parts.append(r_lin - q @ (q.T @ r_lin))

        def back(d_s, q=q, rr=rr, keep=keep, r_lin=r_lin, j_s=j_s):
            out = np.zeros(len(keep))
            out[keep] = -np.linalg.solve(rr, q.T @ (r_lin + j_s @ d_s))
            return out

        backs.append(back)
    return np.vstack(js_parts), np.concatenate(r_parts), backs
