"""What the time-domain and the frequency-response fits share.

The fittable plant keys with their units, bounds and scales; :class:`FitResult`; the toolkit's
own CasADi model with the fitted values as symbols (:func:`symbolic_rhs`), so the fitted plant
is exactly what the tuner uses; the checks of a fit's inputs against the plant
(:func:`checked_inputs`: duplicate data, the sample time, a unit slip in the torque balance,
FRF points above the drive's Nyquist frequency, the FRF operating point); and what a finished
fit makes of values and covariance (:func:`finish_fit`): 95 % intervals, identifiability
(:func:`info_split`, :data:`RANK_RTOL`), the keys kept at the base value, the fitted plant and
its ``[uncertainty]`` entries.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import warnings as _warnings
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import casadi as ca
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linprog
from scipy.signal import lfilter

from ..options import SPEED_MAX_RPM, rad_s_to_rpm, rpm_to_rad_s
from ..plant import model as model_equations
from ..plant.model import stick_band_rad_s
from ..plant.plantfile import Plant
from ..plant.schema import BREAKAWAY_KEY, PLAUSIBLE, SCHEMA
from ..plant.uncertainty import carry_correlation, correlation_entry, plant_uncertainty
from .data import MIN_FRF_POINTS, FrfRecord, Record
from .fituncertainty import (UNCERTAINTY_MODES, Z95, hold_written_values, physical_range, uncertainty_choice,
                             uncertainty_entries)
from .inertia_total import reflected_interval

__all__ = ["FitResult", "FITTABLE", "DELAY_KEY", "PSEUDO_KEYS", "CONTACT_KEYS", "DEFAULT_KEYS", "FRF_KEYS",
           "FRF_KEYS_COMPLIANT", "RANK_RTOL", "NULL_LOADING", "UNCERTAINTY_MODES", "SAMPLE_TIME_RTOL",
           "UNIT_SLIP_FACTOR", "UNIT_PLANT_FACTOR", "FRF_SPEED_MAX_RAD_S", "FRF_LOAD_MAX_RATED", "TORQUE_OVER_LIMIT",
           "symbolic_rhs", "key_bounds", "motor_torque", "check_keys", "inertia_key", "default_keys", "default_min_speed", "frf_operating_point_error",
           "checked_inputs", "frf_sample_time", "finish_fit", "info_split", "unit_text", "uncertainty_entries", "check_units",
           "uncertainty_choice", "fit_percent"]

#: Plant keys the fit can estimate: unit and meaning (bounds and scales: :func:`key_bounds`).
FITTABLE: Mapping[str, tuple[str, str]] = {
    "nut.inertia_kg_m2": ("kg m^2", "nut plus rotor inertia"),
    "axis.motor_inertia_kg_m2": ("kg m^2", "rotor inertia of a screw-driven axis (ball or roller screw: motor and "
                                           "coupling; the screw's own inertia is axis.screw_inertia_kg_m2)"),
    "friction.efficiency": ("-", "forward efficiency"),
    "friction.no_load_torque_n_m": ("N m", "no-load (Coulomb) drag torque"),
    "friction.viscous_n_m_s_per_rad": ("N m s/rad", "viscous coefficient"),
    "friction.torque_offset_n_m": ("N m", "drag offset: Coulomb levels no-load + offset forward, no-load - offset "
                                          "backward (needs data at speed in both directions)"),
    "friction.static": ("-", "static (breakaway) thread friction coefficient of the Stribeck curve (from "
                             "steady-speed plateaus below a few Stribeck speeds: prsa_ctrl.identification.friction_map)"),
    "friction.stribeck_velocity_m_s": ("m/s", "Stribeck velocity: screw speed over which the breakaway excess decays "
                                              "(from low-speed plateaus)"),
    "friction.no_load_breakaway_torque_n_m": ("N m", "breakaway level of the no-load drag (from low-speed plateaus)"),
    "friction.viscous_offset_n_m_s_per_rad": ("N m s/rad", "direction-dependent viscous part: viscous + offset "
                                                           "forward, viscous - offset backward (needs several speed "
                                                           "levels in both directions)"),
    "drive.current_loop_bandwidth_hz": ("Hz", "current-loop bandwidth"),
    "drive.command_delay_s": ("s", "command delay (logged command to the moment it acts; not a plant-file key)"),
    "contact.stiffness_n_per_mm_e": ("N/mm^e", "IMPACT thread-contact stiffness (compliant fidelity: the axial mode)"),
    "contact.damping_n_s_per_mm": ("N s/mm", "IMPACT thread-contact damping (compliant fidelity: the axial mode)"),
    "axis.moving_mass_kg": ("kg", "moving mass of a screw-driven axis (carriage, table, workpiece): the load side of "
                                  "its axial mode (compliant fidelity, from a frequency response)"),
    "axis.nut_stiffness_n_per_um": ("N/um", "nut stiffness of a screw-driven axis, in series with the shaft and the "
                                            "bearings: sets its axial mode (compliant fidelity, from a frequency response)"),
    "axis.axial_damping_ratio": ("-", "modal damping ratio of a screw-driven axis's axial mode (compliant fidelity, "
                                      "from a frequency response)"),
    "screw.mass_kg": ("kg", "translating screw of the inverted roller screw: the load side of its axial mode "
                            "(compliant fidelity, from a frequency response)"),
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


_Z95 = Z95


#: Above this correlation the data cannot separate two fitted keys (warning; a key this
#: correlated with an unidentifiable one is not identified either).
_CORR_SEPARATE = 0.95


#: Identifiability tolerance: a direction of the column-scaled parameter Jacobian (each column
#: of unit norm, segment initial states projected out) whose singular value is below this
#: fraction of the largest carries no information from the data. Round-off puts an exactly
#: singular direction near 1e-15 and a perturbation of the Jacobian at 1e-10 near 1e-10; weakly
#: but truly excited directions of the built-in experiments lie above 1e-3. Along such a
#: direction the interval is the whole stretch the physical ranges allow (:func:`_null_extent`).
RANK_RTOL = 1e-6


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
        response ``{"frequency_hz", "measured", "model"}`` (complex, (rad/s)/(N m)) with the
        data's ``"coherence"`` (0..1, None when the data have none), for
        :func:`prsa_ctrl.plots.fit.fit_figures`.
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
    covariance : ndarray or None
        Covariance of the fitted values (order of ``keys``), in the file units of the keys:
        entry ``(i, j)`` in ``unit_i * unit_j`` (``parameters[k]["unit"]``; e.g. kg m^2 times
        Hz). It is the one the 95 % intervals come from (``value +/- 1.96 sqrt(C_ii)``), the
        time-domain fit's HAC sandwich or the FRF fit's classic one; along directions the data
        do not inform (:func:`info_split`) it has no part, and the intervals there are the
        physical ranges instead. For a joint statement about several keys use
        :meth:`joint_distance2` (the joint 95 % region is an ellipsoid, not the box of the
        marginal intervals: six marginal 95 % intervals hold a true point jointly only about
        74 % of the time). None for a result made without it.
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
    covariance: NDArray[np.float64] | None = None

    def joint_distance2(self, point: Mapping[str, float]) -> float:
        """Squared Mahalanobis distance of ``point`` from the fitted values, with :attr:`covariance`.

        Parameters
        ----------
        point : mapping
            ``{key: value}`` in the keys' file units, for some or all of :attr:`keys` (the
            marginal distribution of those keys is used).

        Returns
        -------
        float
            ``d^T C^-1 d`` with ``d`` the difference and ``C`` the covariance block of the
            keys: ``point`` lies in the joint 95 % confidence region of those keys when this is at
            most ``scipy.stats.chi2(len(point)).ppf(0.95)`` (12.59 for six keys).

        Raises
        ------
        ValueError
            ``point`` empty or naming a key not fitted, no covariance, or a covariance block the
            data do not make positive definite (a key on an uninformed direction).
        """
        if self.covariance is None:
            raise ValueError("joint_distance2: this FitResult has no covariance; expected a result of fit_plant or fit_frf")
        names = list(point)
        bad = [k for k in names if k not in self.keys]
        if not names or bad:
            raise ValueError(f"point keys {', '.join(bad) or '(none)'}; expected some of {', '.join(self.keys)}")
        idx = [self.keys.index(k) for k in names]
        c = np.asarray(self.covariance, float)[np.ix_(idx, idx)]
        d = np.array([float(point[k]) - self.parameters[k]["value"] for k in names])
        sd = np.sqrt(np.clip(np.diag(c), 0.0, None))
        if not np.all(sd > 0):
            raise ValueError(f"point keys {', '.join(names)}: the covariance has no spread for "
                             f"{', '.join(k for k, s in zip(names, sd) if not s > 0)}; expected identified keys")
        corr = c / np.outer(sd, sd)
        try:
            chol = np.linalg.cholesky(corr)
        except np.linalg.LinAlgError:
            raise ValueError(f"point keys {', '.join(names)}: their covariance is not positive definite (the data "
                             "inform only a combination of them); expected identified keys") from None
        y = np.linalg.solve(chol, d / sd)
        return float(y @ y)

    @property
    def plant_keys(self) -> tuple[str, ...]:
        """The fitted keys written into the plant file (not the delay, not the keys kept at the
        base value)."""
        return tuple(k for k in self.keys if k not in PSEUDO_KEYS and not self.parameters[k].get("kept_base"))

    @property
    def kept_base(self) -> tuple[str, ...]:
        """Keys the data could not inform: the plant file keeps their base value and source."""
        return tuple(k for k, v in self.parameters.items() if v.get("kept_base"))

    @property
    def status(self) -> str:
        """The result's status in the package's vocabulary (:data:`prsa_ctrl.results.STATUSES`):
        ``"ok"`` when the fitted plant, replayed on the nonlinear simulator, explains the data
        (its validation passed, :mod:`prsa_ctrl.identification.validation`), ``"flagged: <the
        most likely missing physics>"`` when it does not, ``"unverified: ..."`` when no
        validation ran (a frequency-response fit, or ``validation=False``). A fit that did not
        converge raises :class:`~prsa_ctrl.errors.FitError` and has no result; the solver's own
        status is ``solver["status"]``."""
        v = self.solver.get("validation") if isinstance(self.solver, Mapping) else None
        if v is None:
            return "unverified: no validation replay of the fitted plant on the nonlinear simulator"
        if v.get("passes"):
            return "ok"
        return f"flagged: the fitted plant does not explain the data ({v.get('diagnosis', 'no diagnosis')})"

    @property
    def ok(self) -> bool:
        """Whether the result may be reported as good (:func:`prsa_ctrl.results.is_ok` of its status)."""
        from ..results import is_ok

        return is_ok(self.status)

    def as_dict(self) -> dict:
        """JSON-ready report (stable keys: ``status``, ``parameters``, ``reflected_inertia_kg_m2``,
        ``fit_percent``, ``warnings``, ``solver``, plus ``correlation``, ``covariance`` (keys,
        units, matrix) when there is one and, when the delay was fitted, ``delay``).
        :meth:`report` is the same."""
        out = {
            "status": self.status,
            "parameters": self.parameters,
            "reflected_inertia_kg_m2": self.reflected_inertia_kg_m2,
            "fit_percent": self.fit_percent,
            "warnings": list(self.warnings),
            "solver": self.solver,
            "correlation": {"keys": list(self.keys), "matrix": np.round(self.correlation, 6).tolist()},
        }
        if self.covariance is not None:
            out["covariance"] = {"keys": list(self.keys), "units": [FITTABLE[k][0] for k in self.keys],
                                 "note": "entry (i, j) in units[i] * units[j]",
                                 "matrix": np.asarray(self.covariance, float).tolist()}
        if self.delay is not None:
            out["delay"] = self.delay
        return out

    report = as_dict  # its former name


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


def symbolic_rhs(plant: Plant, keys: Sequence[str], fidelity: str):
    """``(x, u, p) -> xdot`` of the toolkit's model with the values of ``keys`` as ``p``."""
    p = ca.SX.sym("p", len(keys))
    values = dict(plant.values)
    for i, k in enumerate(keys):
        values[k] = p[i]
    with _warnings.catch_warnings():
        _warnings.simplefilter("ignore")
        sym = _SymbolicPlant(name=plant.name, values=values, sources=plant.sources, origin=plant.origin,
                             mechanism=plant.mechanism, defaulted=plant.defaulted)
    names = model_equations.plant_model(plant, fidelity).state_names
    x = ca.SX.sym("x", len(names))
    u = ca.SX.sym("u", 2)
    if fidelity not in ("rigid", "compliant"):
        raise ValueError(f"fidelity = {fidelity!r}; expected 'rigid' or 'compliant' for a fit")
    try:
        xdot = model_equations.state_derivative(sym, fidelity, x, u)[0]
    except TypeError as exc:  # an equation that needs a numeric value of a fitted key
        raise ValueError(f"the {fidelity} model cannot take {', '.join(keys)} as fitted symbols ({exc}); "
                         "expected fewer --fit keys") from None
    return ca.Function("f", [x, u, p], [xdot]), names


def key_bounds(plant: Plant, key: str, ts: float) -> tuple[float, float, float]:
    """Lower bound, upper bound and scale (file units) of a fitted key."""
    v = plant.values[key]
    t_max = plant.torque_limit
    if key in ("nut.inertia_kg_m2", "axis.motor_inertia_kg_m2"):
        return 0.05 * v, 20.0 * v, v
    if key == "friction.efficiency":
        return 0.3, 0.995, 1.0
    if key == "friction.no_load_torque_n_m":
        return 0.0, 0.5 * t_max, max(v, 0.01 * t_max)
    if key == "friction.viscous_n_m_s_per_rad":
        return 0.0, 0.01 * t_max, max(v, 1e-5 * t_max)
    if key == "friction.viscous_offset_n_m_s_per_rad":
        return -0.01 * t_max, 0.01 * t_max, max(abs(v), 1e-5 * t_max)
    if key == "friction.torque_offset_n_m":
        return -0.5 * t_max, 0.5 * t_max, max(abs(v), 0.01 * t_max)
    if key == "friction.static":  # static >= dynamic
        return plant.values["friction.dynamic"], 1.0, max(v, 0.05)
    if key == "friction.stribeck_velocity_m_s":
        return PLAUSIBLE[key][0], PLAUSIBLE[key][1], v
    if key == "friction.no_load_breakaway_torque_n_m":  # at least the sliding drag
        return plant.values["friction.no_load_torque_n_m"], 0.5 * t_max, max(v, 0.01 * t_max)
    if key == "drive.current_loop_bandwidth_hz":
        return 10.0, min(1e5, 10.0 / ts), v
    if key == "contact.stiffness_n_per_mm_e":  # the axial mode frequency goes with K^(1/(2e))
        return max(v / 30.0, 1e1), min(v * 30.0, 1e9), v
    if key in ("axis.moving_mass_kg", "screw.mass_kg"):
        return 0.05 * v, 20.0 * v, v
    if key == "axis.nut_stiffness_n_per_um":  # the mode's share of it is weak (series): a wide range
        return max(v / 100.0, PLAUSIBLE[key][0]), min(v * 100.0, PLAUSIBLE[key][1]), v
    if key == "axis.axial_damping_ratio":
        return 1e-4, 1.0, max(v, 0.01)
    if key == "contact.damping_n_s_per_mm":
        return 0.0, min(max(100.0 * v, 1e3), 1e5), max(v, 1.0)
    raise ValueError(f"--fit key {key!r}; expected one of {', '.join(FITTABLE)}")


def inertia_key(plant: Plant) -> str:
    """The fitted key of the rotating inertia: ``axis.motor_inertia_kg_m2`` for a screw-driven
    axis (its ``nut.inertia_kg_m2`` is derived, the motor plus the screw), else ``nut.inertia_kg_m2``."""
    return "axis.motor_inertia_kg_m2" if plant.screw_driven else "nut.inertia_kg_m2"


def default_keys(plant: Plant, keys: Sequence[str] = DEFAULT_KEYS) -> tuple[str, ...]:
    """``keys`` (default :data:`DEFAULT_KEYS`) for ``plant``'s mechanism: the inertia key is
    :func:`inertia_key`'s."""
    j = inertia_key(plant)
    return tuple(j if k == "nut.inertia_kg_m2" else k for k in keys)


def check_keys(keys: Sequence[str], fidelity: str, plant: Plant | None = None) -> tuple[str, ...]:
    keys = tuple(keys)
    for k in keys:
        if k not in FITTABLE:
            raise ValueError(f"fit key {k!r}; expected one of {', '.join(FITTABLE)}")
    if plant is not None:
        j = inertia_key(plant)
        wrong = [k for k in keys if k in ("nut.inertia_kg_m2", "axis.motor_inertia_kg_m2") and k != j]
        if wrong:
            raise ValueError(f"fit key {wrong[0]!r} for a {plant.mechanism} plant; expected {j!r} (the rotating "
                             "inertia this mechanism's model uses)")
        if plant.mechanism == "linear-axis":
            raise ValueError("a linear-axis plant; expected the linear-axis fit (prsa-axis, "
                             "prsa_ctrl.identification.axis.fit_linear_axis) for load-side equivalents")
    if not keys or len(set(keys)) != len(keys):
        raise ValueError(f"fit keys {', '.join(keys)}; expected one or more keys, each once")
    contact = [k for k in keys if k in CONTACT_KEYS]
    if contact and fidelity != "compliant":
        raise ValueError(f"fit key {contact[0]!r} with fidelity {fidelity!r}; expected fidelity 'compliant' "
                         "(only the compliant model has the thread contacts)")
    return keys


def default_min_speed(plant: Plant) -> float:
    """Default speed (rad/s of the nut) below which data are left out of a fit: three Stribeck
    velocities plus the Karnopp blend band (``2 w_b``), where the friction law is not smooth."""
    v_s = plant.values["friction.stribeck_velocity_m_s"] / plant.lead_per_rad
    return 3.0 * v_s + 2.0 * stick_band_rad_s(plant)


#: Largest relative difference between a record's sample time and the plant's
#: ``sensor.sample_time_s``: the model holds each logged command over one logged sample, as the
#: drive does, so a log at another rate (or with time in another unit) is not this drive's loop.
SAMPLE_TIME_RTOL = 0.01
#: Unit slips the torque-balance check recognises: the factor by which the apparent inertia
#: (:func:`_apparent_inertia`) divides the plant's, and what it means for which column.
_UNIT_SLIPS = (
    (rad_s_to_rpm(1.0), "speed in rpm"), (180.0 / math.pi, "speed in deg/s"), (1.0 / (2 * math.pi), "speed in rev/s"),
    (1e-3, "torque in mN m"),
)
#: The apparent inertia names a unit slip when it is within this factor of the plant's reflected
#: inertia divided by the slip's factor and more than :data:`UNIT_PLANT_FACTOR` away from the
#: plant's own; beyond ``1 / 20 .. 20`` times the plant's (the fit's inertia bounds) it cannot be
#: this plant in any case.
UNIT_SLIP_FACTOR = 2.0
#: Operating point of a measured frequency response: nut speed at most 6000 rpm (the tuner's
#: limit), axial load at most this many rated loads of the plant.
FRF_SPEED_MAX_RAD_S = rpm_to_rad_s(SPEED_MAX_RPM)
FRF_LOAD_MAX_RATED = 2.0
#: A logged torque command beyond this multiple of the plant's torque limit is not this drive's.
TORQUE_OVER_LIMIT = 10.0
UNIT_PLANT_FACTOR = 3.0


def _data_key(rec) -> bytes:
    """Bytes that are equal exactly when two records hold the same data: the same measured arrays
    at the same sample time (to 9 digits; a clock shifted by a constant is the same record)."""
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


def motor_torque(rec: Record, plant: Plant) -> NDArray[np.float64]:
    """The motor torque of a record (N m, per sample): its command through the plant's first-order
    current loop, clipped at the torque limit (the torque balance of the fit and of the plateaus)."""
    return _motor_torque(rec, plant)


def _motor_torque(rec: Record, plant: Plant, clip: bool = True) -> NDArray[np.float64]:
    """The torque command through the plant's first-order current loop (clipped at its limit
    unless ``clip`` is false), N m."""
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


def check_units(rec: Record, plant: Plant) -> None:
    """Refuse a record whose torque balance shows a unit slip (:func:`_apparent_inertia` against
    the plant's reflected inertia, :data:`_UNIT_SLIPS`) or an inertia no fit of this plant can reach.

    Parameters
    ----------
    rec : Record
        The record in SI units (N m, rad, rad/s).
    plant : Plant
        The base plant (its torque limit, N m, and reflected inertia, kg m^2).

    Raises
    ------
    ValueError
        One line naming the record and the column: a torque command beyond the torque limit, a
        unit slip (rpm, mN m, deg, ...), or an inertia beyond a factor 20 of the plant's.
    """
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
    v_min, v_max, f_max = default_min_speed(plant), FRF_SPEED_MAX_RAD_S, FRF_LOAD_MAX_RATED * plant.rated_load_n
    if not v_min <= abs(speed_rad_s) <= v_max:
        return "speed", (f"expected a nut speed with {v_min:.3g} <= |speed| <= {v_max:.6g} rad/s (the linearisation "
                         f"needs motion above the friction's stick band; {SPEED_MAX_RPM:g} rpm is the tuner's limit)")
    if abs(load_n) > f_max:
        return "load", (f"expected |load| <= {f_max:.6g} N ({FRF_LOAD_MAX_RATED:g} x the plant's rated load "
                        f"{plant.rated_load_n:.6g} N)")
    return None


def checked_inputs(records, validate, frf, plant):
    """Inputs of a fit after the checks that need the plant: duplicate data used once (with a
    warning), each record's sample time equal to the plant's within :data:`SAMPLE_TIME_RTOL`,
    no unit slip in the torque balance (:func:`check_units`), FRF points at or above the
    drive's Nyquist frequency dropped (a warning each; too few left: ValueError), each response's
    operating point within :data:`FRF_SPEED_MAX_RAD_S` and :data:`FRF_LOAD_MAX_RATED`."""
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
        check_units(rec, plant)
    out = []
    for fr in frf:
        bad = frf_operating_point_error(plant, fr.speed_rad_s, fr.load_n)
        if bad:
            field_, expected = bad
            value = fr.speed_rad_s if field_ == "speed" else fr.load_n
            raise ValueError(f"{fr.name}: {field_} = {value!r}; {expected}")
        ts = frf_sample_time(fr, plant)
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


def finish_fit(plant, keys, values, cov, lo, hi, names, warns, ts=None, keep_unidentified=True, null=None,
            ratios=None, uncertainty="keep"):
    """Parameters with 95 % CIs, correlation, identifiability warnings, the fitted plant, the
    reflected inertia, the delay block (None unless the delay was fitted) and the reasons of the
    keys not identified, from fitted values and their covariance (file units; ``lo``/``hi``
    bounds; ``ts`` the sample time, s). ``null``: the directions the data do not inform
    (columns, file units; :func:`info_split`) and ``ratios`` the singular values over the
    largest: a key's interval spans how far those directions move it within the physical
    ranges (:func:`_null_extent`) plus the covariance's interval. With ``keep_unidentified``
    the keys not identified keep the base plant's value, source and ``[uncertainty]`` entry;
    ``uncertainty`` says what the fitted keys' entries become
    (:func:`~prsa_ctrl.identification.fituncertainty.uncertainty_choice`)."""
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(std, std)
    corr = np.nan_to_num(corr)
    ts = plant.sample_time_s if ts is None else ts
    null = np.zeros((len(keys), 0)) if null is None else np.asarray(null, float)
    ranges = [physical_range(plant, k, lo[i], hi[i]) if k not in PSEUDO_KEYS else (lo[i], hi[i])
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
        u = unit_text(unit)
        if not np.isfinite(width) or width > 0.5 * max(abs(values[i]), floor):
            warns.append(f"{k} is not identifiable from this data (95 % CI +/- {width:.3g}{u} around "
                         f"{values[i]:.4g}): {_REMEDY_KEY.get(k, 'excite it more')}")
        if values[i] <= lo[i] * (1 + 1e-6) + 1e-15 or values[i] >= hi[i] * (1 - 1e-6):
            warns.append(f"{k} = {values[i]:.4g}{u} is at its bound [{lo[i]:.4g}, {hi[i]:.4g}]: its interval "
                         "is not reliable" + ("; move the bracket with delay_samples (--delay-samples)"
                                              if k == DELAY_KEY else ""))
        reason = _not_identified(k, float(values[i]), float(width), physical_range(plant, k, lo[i], hi[i]), floor)
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
            warns.append(f"{k} kept at the base value {plant.values[k]:.6g}{unit_text(FITTABLE[k][0])} in the plant "
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
    t0_new = overrides.get("friction.no_load_torque_n_m")
    if (t0_new is not None and BREAKAWAY_KEY in plant.values and BREAKAWAY_KEY not in overrides
            and BREAKAWAY_KEY not in plant.defaulted and plant.values[BREAKAWAY_KEY] < t0_new):
        overrides[BREAKAWAY_KEY] = t0_new  # a breakaway level below the sliding drag is no plant
        warns.append(f"{BREAKAWAY_KEY} = {plant.values[BREAKAWAY_KEY]:.6g} N m of the base plant is below the fitted "
                     f"friction.no_load_torque_n_m = {t0_new:.6g} N m: raised to it (no breakaway excess on the drag); "
                     "fit it too (--fit ...,friction.no_load_breakaway_torque_n_m with a low-speed staircase)")
    with _warnings.catch_warnings():
        _warnings.simplefilter("ignore")  # the base plant's own geometry notes were given when it loaded
        fitted = plant.with_params(overrides, name=f"{plant.name}-fit")
        srcs = dict(fitted.sources)
        for k in plant_keys:
            lo_ci, hi_ci = params[k]["ci95"]
            srcs[k] = f"fit: {names} (95 % CI {lo_ci:.6g}..{hi_ci:.6g})"
        base_unc = dict(getattr(plant, "uncertainty", None) or {})
        unc = {k: v for k, v in base_unc.items() if k not in plant_keys}
        fit_unc = uncertainty_entries(fitted, {k: params[k] for k in plant_keys}, names,
                                       [std[keys.index(k)] for k in plant_keys],
                                       [physical_range(plant, k, lo[keys.index(k)], hi[keys.index(k)])
                                        for k in plant_keys])
        for k in plant_keys:
            choice, note = uncertainty_choice(fitted, k, base_unc.get(k), fit_unc.get(k), params[k]["ci95"],
                                               physical_range(plant, k, lo[keys.index(k)], hi[keys.index(k)]),
                                               uncertainty)
            if choice is not None:
                unc[k] = choice
            if note:
                warns.append(note)
        # the fit's correlation among the keys written with the fit's own entry (not along an uninformed direction)
        own = [k for k in plant_keys if k in unc and unc[k] is fit_unc.get(k) and k not in in_null]
        idx = [keys.index(k) for k in own]
        unc = carry_correlation(unc, base_unc, correlation_entry(
            own, np.asarray(cov, float)[np.ix_(idx, idx)], f"fit: {names} (correlation of the fitted keys from the fit's covariance)"), warns)
        fitted = Plant(name=fitted.name, values=fitted.values, sources=srcs, origin=fitted.origin,
                       description=f"{plant.name} fitted by prsa-fit to {names}", uncertainty=unc,
                       mechanism=fitted.mechanism, defaulted=fitted.defaulted, mechanism_source=fitted.mechanism_source)
        if BREAKAWAY_KEY in overrides and BREAKAWAY_KEY not in plant_keys:  # raised to the drag: its entry must hold it
            fitted, notes = hold_written_values(fitted, [BREAKAWAY_KEY], {}, {})
            warns.extend(notes)
    j_ref = fitted.reflected_inertia_kg_m2  # its interval from every fitted key it depends on (a mass too)
    ci = reflected_interval(fitted, inertia_key(plant), keys, params, corr)
    reflected = {"value": float(j_ref), "ci95": ci, "unit": "kg m^2"}
    delay = None
    if DELAY_KEY in keys:
        delay = _delay_block(fitted, keys, values, cov, ts)
    return params, corr, fitted, reflected, delay, reasons


def info_split(jn: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
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


def unit_text(unit: str) -> str:
    """`` N m`` for a unit, nothing for a dimensionless key (``-``)."""
    return "" if unit in ("-", "") else f" {unit}"


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


def frf_sample_time(fr: FrfRecord, plant: Plant) -> float:
    return plant.sample_time_s if fr.sample_time_s is None else fr.sample_time_s


_REMEDY_KEY = {
    "friction.efficiency": "record with load changes (load steps) so that load-dependent friction shows",
    "friction.no_load_torque_n_m": "record speed reversals (a staircase through both directions)",
    "friction.viscous_n_m_s_per_rad": "record several speed levels",
    "friction.viscous_offset_n_m_s_per_rad": "record several speed levels in both directions",
    "friction.static": "record a low-speed staircase (plateaus below ~3 Stribeck speeds, both directions, two loads)",
    "friction.stribeck_velocity_m_s": "record a low-speed staircase (plateaus from ~0.3 to ~5 Stribeck speeds)",
    "friction.no_load_breakaway_torque_n_m": "record a low-speed staircase at two loads or more (one load informs "
                                             "only the sum of the drag's and the thread's breakaway excess)",
    "drive.current_loop_bandwidth_hz": "excite higher frequencies (multisine up to a few hundred Hz) or fix it with --fit",
    "nut.inertia_kg_m2": "excite accelerations (multisine or speed steps)",
    "axis.motor_inertia_kg_m2": "excite accelerations (multisine or speed steps)",
    "drive.command_delay_s": "measure up to the current-loop bandwidth, or fix the delay (leave it out of --fit)",
    "contact.stiffness_n_per_mm_e": "measure a frequency response that covers the axial mode (under load), "
                                    "or leave the stiffness out of --fit",
    "contact.damping_n_s_per_mm": "measure the axial mode's peak with a fine frequency resolution",
    "axis.moving_mass_kg": "measure a frequency response through the axial mode (anti-resonance and resonance)",
    "screw.mass_kg": "measure a frequency response through the axial mode (anti-resonance and resonance)",
    "axis.nut_stiffness_n_per_um": "measure a frequency response through the axial mode",
    "axis.axial_damping_ratio": "measure the axial mode's peak with a fine frequency resolution",
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
