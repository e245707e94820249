"""The ``linear-axis`` plant: a screw axis described by its load-side equivalents, its closed-loop
replay and its calibration from closed-loop logs (:mod:`prsa_ctrl.identification.logformat`).

Model (load coordinates: position ``x`` in m, force in N)::

    M x'' = F_drive + F_load - F_f(x')
    F_f(v) = Fc+ + Fv+ v          for v > 0
    F_f(v) = -Fc- + Fv- v         for v < 0
    at v = 0 the axis sticks while -Fc- <= F_drive + F_load <= Fc+

``Fc+`` and ``Fc-`` are magnitudes (N); Coulomb friction plus a constant offset (gravity, a
sensor offset) is the same model with ``Fc+ = Fc + offset`` and ``Fc- = Fc - offset``; ``Fv+``
and ``Fv-`` are the viscous coefficients per direction (N s/m). No Stribeck term: the fit would
need constant-speed phases near zero speed to inform it (see :func:`fit_linear_axis`).

A two-mass axis (``axis.load_mass_kg`` > 0, :attr:`LinearAxisPlant.second_mass`) is the motor
side ``M - m_l`` (the friction above, the logged position) carrying the load mass ``m_l`` through a
spring-damper, the external load on the load mass (:mod:`prsa_ctrl.identification.axistwomass`:
the same model as :mod:`prsa_ctrl.plant.linearaxis`); the fit holds its second mass and fits ``M``
and the friction on its replay.

Between two controller samples the drive force is constant (zero-order hold), so the motion is
a linear ODE per direction of motion: it is integrated exactly (exponential solution, the
zero-speed crossing time in closed form, then stick or reversal in the rest of the sample). No
step size, no tolerance, no chattering at zero speed.

Plant file (TOML, ``mechanism = "linear-axis"``), every value with its source::

    name = "emps-fitted"
    description = "..."
    mechanism = "linear-axis"
    coordinates = "load"                       # m, N

    [axis]
    mass_kg = { value = 95.1, source = "fit: DATA_EMPS.mat ..." }
    [friction]
    coulomb_positive_n = { value = ..., source = "..." }         # Fc+, N (>= 0)
    coulomb_negative_n = { value = ..., source = "..." }         # Fc-, N (>= 0, a magnitude)
    viscous_positive_n_s_per_m = { value = ..., source = "..." } # Fv+, N s/m (>= 0)
    viscous_negative_n_s_per_m = { value = ..., source = "..." } # Fv-, N s/m (>= 0)
    [drive]
    gain_n_per_unit = { value = 35.15, source = "..." }          # force per command unit
    command_unit = "V"
    force_limit_n = { value = 351.5, source = "..." }            # saturation x gain
    [sensor]
    sample_time_s = { value = 0.001, source = "..." }
    encoder_resolution_m = { value = 5e-8, source = "..." }
    [uncertainty]                                                 # as in prsa_ctrl.plant.uncertainty
    "axis.mass_kg" = { dist = "normal", sigma = ..., truncate = 1.959964, source = "fit: ..." }
    correlation = { keys = ["axis.mass_kg", ...], matrix = [[1.0, ...], ...], source = "fit: ..." }

It is a plant file of the package (``prsa-tune --show-plant FILE`` lists every value with its
source; simulation, linearisation and the tuners load it with :func:`prsa_ctrl.plant.load_plant`):
``axis.mass_kg``, ``drive.gain_n_per_unit``, ``drive.force_limit_n``, ``sensor.sample_time_s`` and
``sensor.encoder_resolution_m`` are required (:data:`prsa_ctrl.plant.schema.REQUIRED`), every
other key has the default of :data:`prsa_ctrl.plant.schema.DEFAULTS` with its source. Keys carry
their units in their names.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from ..errors import AxisFitError, AxisPlantError, PlantFileError, SimulationError
from ..plant.plantfile import Plant
from ..plant import schema as plant_schema
from ..tomlfile import read_toml
from ..plant.uncertainty import (CORRELATION_KEY, carry_correlation, correlation_entry,
                                 inner_truncation)
from .axisfriction import filtered_position, measured_velocity  # noqa: F401 - measured_velocity re-exported
from .covariance import COVARIANCE_BLOCKS, batch_covariance, score_covariance, t95  # noqa: F401 - re-exported
from .fituncertainty import outside_note
from .logformat import AxisLog

__all__ = ["AxisPlantError", "AxisFitError", "LinearAxisPlant", "load_axis_plant", "axis_plant_toml", "axis_fit_status", "DEFAULTS", "PARAMETERS", "simulate_axis",
           "COORDINATES",
           "AxisReplay", "replay_axis", "AxisFit", "fit_linear_axis", "measured_velocity", "relative_error",
           "idim_estimate", "start_estimate", "check_force_limit", "logged_force_peak", "MECHANISM", "SMALL_SPEED_M_S", "METRIC_SKIP_SAMPLES",
           "score_covariance", "batch_covariance", "t95", "normal_entry"]

MECHANISM = "linear-axis"
_Z95 = 1.959963984540054
#: Speed at which ``friction_positive_n``/``friction_negative_n`` are reported, m/s.
SMALL_SPEED_M_S = 1e-3
#: Samples left out at the start of every replay error (the zero-phase filter's edge; the
#: benchmark's own script keeps samples from n_border = 50, 1-based, on).
METRIC_SKIP_SAMPLES = 49
#: Fitted parameters, in this order (plant keys).
PARAMETERS = ("axis.mass_kg", "friction.viscous_positive_n_s_per_m", "friction.viscous_negative_n_s_per_m",
              "friction.coulomb_positive_n", "friction.coulomb_negative_n")
_UNITS = {"axis.mass_kg": "kg", "friction.viscous_positive_n_s_per_m": "N s/m",
          "friction.viscous_negative_n_s_per_m": "N s/m", "friction.coulomb_positive_n": "N",
          "friction.coulomb_negative_n": "N", "drive.gain_n_per_unit": "N per command unit",
          "drive.force_limit_n": "N", "sensor.sample_time_s": "s", "sensor.encoder_resolution_m": "m"}
#: Key -> (default value, source) of the linear-axis keys a plant file may leave out: the entries
#: of :data:`prsa_ctrl.plant.schema.DEFAULTS` (one table for every plant file; the drive gain,
#: force limit, sample time and encoder resolution are required keys there,
#: :data:`prsa_ctrl.plant.schema.REQUIRED`).
DEFAULTS: Mapping[str, tuple[float, str]] = {k: plant_schema.DEFAULTS[k] for k in PARAMETERS[1:]}
#: Coordinates of a linear axis, as reports and files state them.
from ..options import LOAD_COORDINATES as COORDINATES  # noqa: E402 - defined once, re-exported here
_SECTIONS = {"axis": ("mass_kg", "load_mass_kg", "load_stiffness_n_per_um", "axial_damping_ratio"), "friction": ("coulomb_positive_n", "coulomb_negative_n", "viscous_positive_n_s_per_m",
                                                 "viscous_negative_n_s_per_m"),
             "drive": ("gain_n_per_unit", "force_limit_n", "command_unit"),
             "sensor": ("sample_time_s", "encoder_resolution_m")}


#: The keys of a two-mass linear axis (:data:`prsa_ctrl.plant.schema.LINEAR_AXIS_SCHEMA`): written
#: only when ``axis.load_mass_kg`` > 0 (a rigid axis's file stays as it was).
_TWO_MASS_KEYS = ("axis.load_mass_kg", "axis.load_stiffness_n_per_um", "axis.axial_damping_ratio")


@dataclass(frozen=True)
class LinearAxisPlant:
    """A linear axis in load coordinates; ``values`` SI by key (``section.key``), ``sources`` alike."""

    name: str
    values: Mapping[str, float]
    sources: Mapping[str, str]
    description: str = ""
    command_unit: str = "V"
    uncertainty: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)

    @property
    def theta(self) -> NDArray[np.float64]:
        """The fitted parameters :data:`PARAMETERS` as a vector."""
        return np.array([self.values[k] for k in PARAMETERS])

    @property
    def second_mass(self) -> tuple[float, float, float] | None:
        """``(m_l kg, k N/m, zeta)`` of a two-mass axis (``axis.load_mass_kg`` > 0: the replay and
        the fit's model, :func:`simulate_axis`), None for a rigid one."""
        ml = float(self.values.get("axis.load_mass_kg", 0.0))
        if not ml > 0:
            return None
        k, z = (float(self.values.get(key, plant_schema.DEFAULTS[key][0])) for key in _TWO_MASS_KEYS[1:])
        return ml, k * 1e6, z

    def with_values(self, values: Mapping[str, float], sources: Mapping[str, str]) -> "LinearAxisPlant":
        v, s = dict(self.values), dict(self.sources)
        v.update(values)
        s.update(sources)
        return LinearAxisPlant(self.name, v, s, self.description, self.command_unit, dict(self.uncertainty))

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any], origin: str) -> "LinearAxisPlant":
        """Build and check a plant from a parsed TOML document (``origin`` names it in errors).

        The document is read by the package's plant-file reader
        (:meth:`prsa_ctrl.plant.plantfile.Plant.from_dict`: the schema's kinds, plausible ranges,
        required keys and defaults with their sources), so a file this accepts is a plant file
        every part of the toolkit loads. A missing ``name`` is the file's stem.
        """
        if doc.get("mechanism") != MECHANISM:
            raise AxisPlantError(f"{origin}: mechanism = {doc.get('mechanism')!r}; expected {MECHANISM!r}")
        unit = doc.get("drive", {}).get("command_unit", "V") if isinstance(doc.get("drive", {}), dict) else "V"
        if unit not in ("V", "A", "N"):
            raise AxisPlantError(f"{origin}: [drive] command_unit = {unit!r}; expected V, A or N")
        named = dict(doc) if doc.get("name") else {**doc, "name": Path(origin).stem or "axis"}
        try:
            plant = Plant.from_dict(named, origin=origin)
        except PlantFileError as exc:
            raise AxisPlantError(str(exc)) from None
        return cls.from_plant(plant, command_unit=unit)

    @classmethod
    def from_plant(cls, plant: Plant, command_unit: str = "V") -> "LinearAxisPlant":
        """The linear axis of a ``linear-axis`` :class:`~prsa_ctrl.plant.plantfile.Plant` (its own
        keys, :data:`prsa_ctrl.plant.schema.LINEAR_AXIS_SCHEMA`, and the sample time, with their
        sources)."""
        if plant.mechanism != MECHANISM:
            raise AxisPlantError(f"{plant.origin}: mechanism = {plant.mechanism!r}; expected {MECHANISM!r}")
        keys = [k for sec, ks in _SECTIONS.items() for k in (f"{sec}.{x}" for x in ks) if k in plant.values]
        return cls(name=plant.name, values={k: float(plant.values[k]) for k in keys},
                   sources={k: plant.sources[k] for k in keys}, description=plant.description,
                   command_unit=command_unit, uncertainty=dict(plant.uncertainty))

    def to_plant(self) -> Plant:
        """This axis as the package's :class:`~prsa_ctrl.plant.plantfile.Plant` (what
        :func:`prsa_ctrl.plant.load_plant` makes of :func:`axis_plant_toml`): simulation,
        linearisation and the tuners take it. Needs every required key of a linear axis
        (:data:`prsa_ctrl.plant.schema.REQUIRED`)."""
        try:
            return Plant.from_dict(tomllib.loads(axis_plant_toml(self)), origin=f"{self.name} (linear axis)")
        except PlantFileError as exc:
            raise AxisPlantError(str(exc)) from None


def load_axis_plant(path: str | Path) -> LinearAxisPlant:
    """Read a ``linear-axis`` plant file; :class:`AxisPlantError` names the file and key.

    The file is a plant file of the package (:func:`prsa_ctrl.plant.load_plant` reads it the
    same way): required keys ``axis.mass_kg``, ``drive.gain_n_per_unit``, ``drive.force_limit_n``,
    ``sensor.sample_time_s``, ``sensor.encoder_resolution_m``; every other key has the default of
    :data:`prsa_ctrl.plant.schema.DEFAULTS` (``prsa-tune --show-plant FILE`` lists them).
    """
    p = Path(path)
    if not p.is_file():
        raise AxisPlantError(f"plant file {str(path)!r} not found; expected a readable .toml file")
    try:
        text = p.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise AxisPlantError(f"{path}: cannot be read as TOML ({exc})") from None
    doc = read_toml(text, str(path), AxisPlantError)
    return LinearAxisPlant.from_dict(doc, origin=str(path))


def axis_plant_toml(plant: LinearAxisPlant, header: Sequence[str] = ()) -> str:
    """The plant as a TOML file (every value with its source; ``[uncertainty]`` when there is
    one; ``header``: comment lines put first), written by the package's one plant-file writer
    (:func:`prsa_ctrl.plant.writer.document_toml`)."""
    from ..plant.writer import document_toml

    doc: dict[str, Any] = {"name": plant.name}
    if plant.description:
        doc["description"] = plant.description
    doc.update(mechanism=MECHANISM, coordinates="load")
    for sec, keys in _SECTIONS.items():
        table: dict[str, Any] = {}
        for k in keys:
            if k == "command_unit":
                table[k] = plant.command_unit
                continue
            full = f"{sec}.{k}"
            v = plant.values.get(full, math.inf)
            if math.isinf(v):
                continue  # the default (no limit) is what a missing key means
            if full in _TWO_MASS_KEYS and not plant.values.get("axis.load_mass_kg", 0.0) > 0:
                continue  # a rigid axis: no second mass, its spring and damping mean nothing
            if full in _TWO_MASS_KEYS[1:] and full not in plant.sources:
                continue
            table[k] = {"value": v, "source": plant.sources[full]}
        doc[sec] = table
    if plant.uncertainty:
        doc["uncertainty"] = {k: (e if k == CORRELATION_KEY else  # numbers of an entry as floats
                                  {a: b if isinstance(b, str) else float(b) for a, b in e.items()})
                              for k, e in plant.uncertainty.items()}
    return document_toml(doc, header=header, comments={"coordinates": "position m, force N"})


# --- simulation ----------------------------------------------------------------------------------


def _phi(z: float) -> float:
    """(1 - exp(-z)) / z, accurate for small z (z >= 0)."""
    return -math.expm1(-z) / z if z > 1e-8 else 1.0 - 0.5 * z


def _motion(x: float, v: float, f: float, m: float, fv: float, fc: float, s: int, T: float) -> tuple[float, float, float]:
    """Move in direction ``s`` (+1/-1) from speed ``v`` (s*v >= 0) for at most ``T`` s under the net
    force ``f`` (drive + load) against Coulomb ``fc`` and viscous ``fv``; returns position, speed and
    the time left when the axis stops on the way (0 if it does not)."""
    a0 = (f - s * fc - fv * v) / m  # acceleration at the start
    k = fv / m  # 1/s
    z = k * T
    # v(t) = v + a0 t phi(k t), x(t) = x + v t + a0 t^2 psi(k t); stop when v(t) = 0 in direction s
    vend = v + a0 * T * _phi(z)
    if s * vend > 0 or (s * a0 >= 0):
        return x + v * T + a0 * T * T * _psi(z), vend, 0.0
    # stops at tc: v + a0 tc phi(k tc) = 0
    if k > 0:
        y = k * v / a0  # exp(-k tc) = 1 + y in (0, 1]; log1p keeps tc exact for a tiny viscous term
        tc = -math.log1p(y) / k if y > -1.0 else T
    else:
        tc = -v / a0
    tc = min(max(tc, 0.0), T)
    return x + v * tc + a0 * tc * tc * _psi(k * tc), 0.0, T - tc


def _psi(z: float) -> float:
    """(z - 1 + exp(-z)) / z^2, accurate for small z (z >= 0)."""
    return (z + math.expm1(-z)) / (z * z) if z > 1e-4 else 0.5 - z / 6.0 + z * z / 24.0


def _step(x: float, v: float, f: float, m: float, fvp: float, fvn: float, fcp: float, fcn: float, h: float):
    """Exact motion over one sample of constant net force ``f`` (N); returns (x, v)."""
    T = h
    if v > 0:
        x, v, T = _motion(x, v, f, m, fvp, fcp, 1, T)
    elif v < 0:
        x, v, T = _motion(x, v, f, m, fvn, fcn, -1, T)
    if T > 0 and v == 0.0:  # at rest for the time left: stick or break away
        if f > fcp:
            x, v, _ = _motion(x, 0.0, f, m, fvp, fcp, 1, T)
        elif f < -fcn:
            x, v, _ = _motion(x, 0.0, f, m, fvn, fcn, -1, T)
    return x, v


@dataclass(frozen=True)
class _Trace:
    position_m: NDArray[np.float64]
    velocity_m_s: NDArray[np.float64]
    command: NDArray[np.float64]  # as logged: computed (or applied), incl. test signal, command unit


def simulate_axis(theta: Sequence[float], log: AxisLog, *, gain: float | None = None,
                  force_limit_n: float = math.inf, closed_loop: bool | None = None,
                  x0: tuple[float, float] | None = None,
                  second_mass: tuple[float, float, float] | None = None) -> _Trace:
    """Replay a log through the axis model.

    Parameters
    ----------
    theta : sequence of float
        ``M`` kg, ``Fv+``, ``Fv-`` N s/m, ``Fc+``, ``Fc-`` N (:data:`PARAMETERS`).
    log : AxisLog
        The log: reference, test signal and external load drive the replay.
    gain : float, optional
        Drive gain, N per command unit (default: the log's).
    force_limit_n : float
        Drive force limit, N (on top of the controller's saturation).
    closed_loop : bool, optional
        Closed loop from the reference with the log's controller (default when it has one), or
        open loop from the logged command (drifts for an integrating axis).
    x0 : (float, float), optional
        Initial position m and speed m/s (default: the first logged position, at rest). The
        controller's past positions are taken on that motion (``q(k-1) = x0 - v0 dt``).
    second_mass : (float, float, float), optional
        ``(m_l kg, k N/m, zeta)``: the two-mass axis (:class:`LinearAxisPlant.second_mass`,
        :mod:`prsa_ctrl.identification.axistwomass`) whose motor side (``M - m_l``, the friction,
        the logged position) carries the load mass through a spring-damper, starting relaxed at
        the motor side's speed; the external load acts on the load mass. Default: one rigid mass.

    Returns
    -------
    _Trace
        Position m, speed m/s (at the sample instants) and the command as the log holds it.
    """
    m, fvp, fvn, fcp, fcn = (float(a) for a in theta)
    if not (m > 0 and min(fvp, fvn, fcp, fcn) >= 0 and all(map(math.isfinite, (m, fvp, fvn, fcp, fcn)))):
        raise ValueError(f"theta = {list(theta)!r}; expected M > 0 and friction >= 0, all finite")
    g = log.gain_n_per_unit if gain is None else float(gain)
    c = log.controller
    closed = (c is not None and log.reference_m is not None) if closed_loop is None else closed_loop
    if closed and (c is None or log.reference_m is None):
        raise ValueError(f"log {log.name!r}: closed_loop=True needs a controller and a reference")
    n, h = log.n, float(log.sample_time_s)
    # plain Python floats in the loop: faster than numpy scalars, and overflow gives inf (caught below)
    ext = [0.0] * n if log.load_n is None else log.load_n.tolist()
    test = [0.0] * n if log.test_signal is None else log.test_signal.tolist()
    q = np.empty(n)
    vs = np.empty(n)
    cmd = np.empty(n)
    x, v = (float(log.position_m[0]), 0.0) if x0 is None else (float(x0[0]), float(x0[1]))
    flim = force_limit_n
    if second_mass is None:
        def step(x, v, fd, fe):
            return _step(x, v, fd + fe, m, fvp, fvn, fcp, fcn, h)
    else:
        from .axistwomass import TwoMassStepper

        two = TwoMassStepper((m, fvp, fvn, fcp, fcn), *second_mass, h)
        inner = [0.0, v]  # the spring's compression (m) and the load mass's speed (m/s)

        def step(x, v, fd, fe):
            x, v, inner[0], inner[1] = two.step((x, v, inner[0], inner[1]), fd, fe)
            return x, v
    if not closed:
        d = 0 if c is None else c.command_delay_samples
        shift = d if log.command_logged == "as-computed" else 0
        applied = (np.r_[np.zeros(shift), log.command[:n - shift]] if shift else log.command).tolist()
        for k in range(n):
            q[k], vs[k] = x, v
            x, v = step(x, v, min(max(g * applied[k], -flim), flim), ext[k])
        return _finite(_Trace(q, vs, log.command.copy()), log)
    kp, kv, ki, sat = c.kp, c.kv, c.ki, c.saturation
    avg = c.velocity_estimate == "average2-difference"
    d = c.command_delay_samples
    r = log.reference_m.tolist()
    buf = [0.0] * d
    q_prev, qf_prev = x - v * h, x - 1.5 * v * h
    integ = 0.0
    for k in range(n):
        q[k], vs[k] = x, v
        if avg:
            qf = 0.5 * (x + q_prev)
            dq = (qf - qf_prev) / h
            qf_prev = qf
        else:
            dq = (x - q_prev) / h
        q_prev = x
        ev = kp * (r[k] - x) - dq
        u = kv * ev
        if ki:
            integ += ki * h * ev
            u += kv * integ
        u = min(max(u, -sat), sat)
        if d:
            buf.append(u)
            ua = buf.pop(0)
        else:
            ua = u
        cmd[k] = u + test[k]
        x, v = step(x, v, min(max(g * (ua + test[k]), -flim), flim), ext[k])
    if d and log.command_logged == "as-applied":
        tst = np.asarray(test)
        cmd = np.r_[tst[:d], cmd[:n - d] - tst[:n - d] + tst[d:]]
    return _finite(_Trace(q, vs, cmd), log)


def _finite(tr: _Trace, log: AxisLog) -> _Trace:
    """The trace, or a SimulationError naming the first sample where the replay left the finite numbers."""
    bad = ~(np.isfinite(tr.position_m) & np.isfinite(tr.velocity_m_s) & np.isfinite(tr.command))
    if bad.any():
        k = int(np.argmax(bad))
        raise SimulationError(f"replay of {log.name} diverged at t = {log.time_s[k]:.6g} s (sample {k}: position "
                              f"{tr.position_m[k]!r} m, speed {tr.velocity_m_s[k]!r} m/s); check the controller gains "
                              "and the plant's mass and friction (an unstable closed loop)")
    return tr


# --- measured signals and errors -------------------------------------------------------------------


def relative_error(y: NDArray[np.float64], y_sim: NDArray[np.float64], skip: int = METRIC_SKIP_SAMPLES) -> float:
    """``100 * ||y - y_sim|| / ||y||`` over the samples from ``skip`` on, %.

    Examples
    --------
    >>> round(relative_error([1.0, 2.0, 2.0], [1.0, 2.0, 1.0], skip=0), 4)
    33.3333
    """
    y, y_sim = np.asarray(y)[skip:], np.asarray(y_sim)[skip:]
    den = float(np.linalg.norm(y))
    return math.inf if den == 0 else 100.0 * float(np.linalg.norm(y - y_sim)) / den


def _fit_percent(y, y_sim, skip: int = METRIC_SKIP_SAMPLES) -> float:
    y, y_sim = np.asarray(y)[skip:], np.asarray(y_sim)[skip:]
    den = float(np.linalg.norm(y - y.mean()))
    return -math.inf if den == 0 else 100.0 * (1.0 - float(np.linalg.norm(y - y_sim)) / den)


@dataclass(frozen=True)
class AxisReplay:
    """One log replayed through a plant: traces and errors (``errors_percent``: position,
    velocity, force as ``100 ||y - y_sim|| / ||y||``; ``fit_percent`` alike as NRMSE fit)."""

    name: str
    closed_loop: bool
    time_s: NDArray[np.float64]
    position_measured: NDArray[np.float64]
    position_simulated: NDArray[np.float64]
    velocity_measured: NDArray[np.float64]
    velocity_simulated: NDArray[np.float64]
    force_measured: NDArray[np.float64]
    force_simulated: NDArray[np.float64]
    errors_percent: Mapping[str, float]
    fit_percent: Mapping[str, float]
    reference_m: NDArray[np.float64] | None = None
    #: ``(m_l kg, k N/m, zeta)`` when the plant replayed is a two-mass axis (None: rigid).
    second_mass: tuple[float, float, float] | None = None

    def as_dict(self) -> dict:
        """JSON-ready replay: the log, how it was replayed, samples, errors and fit (%)."""
        how = "closed loop from the reference" if self.closed_loop else "open loop from the logged command"
        if self.second_mass is not None:
            how += (f", two-mass axis ({self.second_mass[0]:.6g} kg beyond {self.second_mass[1] * 1e-6:.6g} N/um, "
                    f"damping {self.second_mass[2]:.3g})")
        return {"log": self.name, "replay": how, "samples": int(self.time_s.size),
                "errors_percent": dict(self.errors_percent), "fit_percent": dict(self.fit_percent),
                "metric": f"100*||y - y_sim||/||y|| from sample {METRIC_SKIP_SAMPLES} on; position vs the logged "
                          "position, velocity vs the logged speed (or the position low-passed at fs/10, zero phase, "
                          "central differences), force = drive gain x command"}

    report = as_dict  # its former name

    def traces_csv(self) -> str:
        rows = ["time_s,position_measured,position_simulated,force_measured,force_simulated"]
        rows += [f"{a:.9g},{b:.12g},{c:.12g},{d:.9g},{e:.9g}" for a, b, c, d, e in
                 zip(self.time_s, self.position_measured, self.position_simulated, self.force_measured,
                     self.force_simulated)]
        return "\n".join(rows) + "\n"


def replay_axis(plant: LinearAxisPlant, log: AxisLog) -> AxisReplay:
    """Replay ``log`` through ``plant`` (closed loop from the reference when the log describes its
    controller, the test signal added at the drive input; open loop from the logged command
    otherwise) and measure the errors. The replay starts at the first logged position with the
    measured speed (:func:`~prsa_ctrl.identification.axisfriction.measured_velocity`: the log's speed signal, else the derived one)."""
    theta = plant.theta
    gain = log.gain_n_per_unit
    vm = measured_velocity(log)
    tr = simulate_axis(theta, log, gain=gain, force_limit_n=plant.values.get("drive.force_limit_n", math.inf),
                       x0=(float(log.position_m[0]), float(vm[0])), second_mass=plant.second_mass)
    fm, fs = gain * log.command, gain * tr.command
    pairs = {"position": (log.position_m, tr.position_m), "velocity": (vm, tr.velocity_m_s), "force": (fm, fs)}
    closed = log.controller is not None and log.reference_m is not None
    return AxisReplay(log.name, closed, log.time_s, log.position_m, tr.position_m, vm, tr.velocity_m_s, fm, fs,
                      {k: relative_error(*p) for k, p in pairs.items()}, {k: _fit_percent(*p) for k, p in pairs.items()},
                      log.reference_m, plant.second_mass)


# --- calibration ------------------------------------------------------------------------------------


def _idim_rows(log: AxisLog, min_speed_fraction: float):
    """Regressor rows ``[a, v+, v-, 1(v>0), -1(v<0)]`` and the force of one log (inverse dynamics
    on the zero-phase filtered position; samples slower than ``min_speed_fraction`` of the peak
    speed and the 50 samples at each end are left out)."""
    h = log.sample_time_s
    qf = filtered_position(log)
    v = np.gradient(qf, h)
    a = np.gradient(v, h)
    f = log.gain_n_per_unit * log.command + (0.0 if log.load_n is None else log.load_n)
    keep = np.abs(v) > min_speed_fraction * np.max(np.abs(v))
    keep[:50] = keep[-50:] = False
    pos, neg = (v > 0).astype(float), (v < 0).astype(float)
    A = np.column_stack([a, v * pos, v * neg, pos, -neg])
    return A[keep], f[keep]


def start_estimate(logs: Sequence[AxisLog], base: LinearAxisPlant) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """The fit's start: the inverse-dynamic estimate (:func:`idim_estimate`) where the logs inform
    it, the base plant's values (``base.theta``, SI) elsewhere; and which were informed.

    Raises
    ------
    AxisFitError
        A mass estimate <= 0 kg (the command does not explain the logged accelerations).
    """
    theta0, informed = idim_estimate(logs)
    theta0 = np.where(informed, theta0, base.theta)
    if theta0[0] <= 0:
        raise AxisFitError(f"inverse-dynamic mass estimate {theta0[0]:.6g} kg <= 0; expected a log with accelerations "
                           "that the command explains (check the drive gain and the command's sign)")
    return theta0, informed


def idim_estimate(logs: Sequence[AxisLog], min_speed_fraction: float = 0.05) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Inverse-dynamic least-squares estimate of :data:`PARAMETERS` (the starting point of the
    output-error fit) and which of them the data inform (a direction of motion the logs never
    run in leaves its two friction parameters uninformed)."""
    rows = [_idim_rows(lg, min_speed_fraction) for lg in logs]
    A = np.vstack([r[0] for r in rows])
    y = np.concatenate([r[1] for r in rows])
    informed = np.array([True, *(np.count_nonzero(A[:, j]) >= 20 for j in (1, 2, 3, 4))])
    if A.shape[0] < 50:
        raise AxisFitError(f"only {A.shape[0]} samples above {100 * min_speed_fraction:g} % of the peak speed; "
                           "expected a log that moves the axis")
    th = np.zeros(len(PARAMETERS))
    th[informed] = np.linalg.lstsq(A[:, informed], y, rcond=None)[0]
    return th, informed


@dataclass(frozen=True)
class AxisFit:
    """Result of :func:`fit_linear_axis`."""

    plant: LinearAxisPlant
    parameters: Mapping[str, Mapping[str, Any]]
    equivalent: Mapping[str, Mapping[str, Any]]
    start: Mapping[str, float]
    replays: Sequence[AxisReplay]
    covariance: NDArray[np.float64]
    blocks: int  # the batch means' blocks of the covariance (covariance.score_covariance)
    status: str
    iterations: int
    warnings: Sequence[str]
    cost: float = math.nan
    message: str = ""
    delay_costs: Mapping[int, float] = field(default_factory=dict)
    #: The least-squares solver's own verdict (``"converged"``: a fit that did not raises).
    solver_status: str = "converged"
    #: The validation (:func:`prsa_ctrl.identification.axisvalidation.validate_axis`; empty: not validated).
    validation: Mapping[str, Any] = field(default_factory=dict)

    @property
    def passes(self) -> bool:
        """Whether the fit was validated and its plant explains the logs."""
        return bool(self.validation.get("passes"))

    @property
    def ok(self) -> bool:
        """Whether the result may be reported as good (:func:`prsa_ctrl.results.is_ok` of its status)."""
        from ..results import is_ok

        return is_ok(self.status)

    def as_dict(self) -> dict:
        """JSON-ready report: ``status`` (:data:`prsa_ctrl.results.STATUSES`: ``"ok"``, or
        ``"flagged: ..."`` naming the failed checks, :func:`axis_fit_status`), the solver's
        status, iterations and cost, the parameters with 95 % intervals, their load-side
        equivalents, covariance and correlation, and every replay. :meth:`report` is the same."""
        return {"mechanism": MECHANISM, "coordinates": COORDINATES, "status": self.status,
                "solver_status": self.solver_status,
                "iterations": self.iterations, "cost": self.cost, "solver_message": self.message,
                "delay_check": {"cost_by_command_delay_samples": {str(k): v for k, v in sorted(self.delay_costs.items())},
                                "note": "each alternative delay refitted with the same weights for at most "
                                        f"{DELAY_CHECK_EVALUATIONS} replays (its cost bounds its optimum from above); "
                                        "lower is better"},
                "method": "output error of the closed-loop replay from the reference (position and force, each "
                          "weighted by its residual RMS at the inverse-dynamic start), started from inverse-dynamic "
                          "least squares; 95 % intervals from the sandwich covariance that holds both a batch-means "
                          f"({self.blocks} contiguous blocks) and a prewhitened Newey-West long-run variance of the "
                          f"scores (the residuals are correlated in time), Student's t with {self.blocks - 1} degrees "
                          "of freedom",
                "parameters": {k: dict(v) for k, v in self.parameters.items()},
                "equivalent": {k: dict(v) for k, v in self.equivalent.items()},
                "inverse_dynamic_start": dict(self.start),
                **self._covariance_report(),
                "replay": [r.as_dict() for r in self.replays],
                **({"validation": dict(self.validation)} if self.validation else {}), "warnings": list(self.warnings)}

    report = as_dict  # its former name


    def _covariance_report(self) -> dict:
        """``covariance`` (the matrix the 95 % intervals come from, SI units of :data:`PARAMETERS`)
        and ``correlation`` (over the parameters with a positive variance: the fitted ones)."""
        cov = np.asarray(self.covariance, float)
        sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        idx = [j for j in range(len(PARAMETERS)) if sd[j] > 0]
        corr = cov[np.ix_(idx, idx)] / np.outer(sd[idx], sd[idx])
        np.fill_diagonal(corr, 1.0)
        return {"covariance": {"keys": list(PARAMETERS), "units": [_UNITS[k] for k in PARAMETERS],
                               "matrix": cov.tolist(),
                               "note": "entry (i, j) in units[i] x units[j]; 95 % interval = value +- t x sqrt(diagonal) "
                                       f"(Student's t with {self.blocks - 1} degrees of freedom)"},
                "correlation": {"keys": [PARAMETERS[j] for j in idx], "matrix": corr.tolist()}}


def _equivalents(theta, cov, z: float) -> dict:
    """Load-side equivalents with 95 % intervals (linear combinations of the parameters)."""
    vs = SMALL_SPEED_M_S
    combos = {
        "mass_kg": ([1, 0, 0, 0, 0], "kg", "mass seen by the axis"),
        "viscous_n_s_per_m": ([0, 0.5, 0.5, 0, 0], "N s/m", "mean of the two directions' viscous coefficients"),
        "viscous_positive_n_s_per_m": ([0, 1, 0, 0, 0], "N s/m", "viscous coefficient moving in +x"),
        "viscous_negative_n_s_per_m": ([0, 0, 1, 0, 0], "N s/m", "viscous coefficient moving in -x"),
        "friction_positive_n": ([0, vs, 0, 1, 0], "N", f"friction force at +{vs:g} m/s (signed)"),
        "friction_negative_n": ([0, 0, -vs, 0, -1], "N", f"friction force at -{vs:g} m/s (signed)"),
        "coulomb_n": ([0, 0, 0, 0.5, 0.5], "N", "Coulomb level, mean of the two directions"),
        "offset_n": ([0, 0, 0, 0.5, -0.5], "N", "constant force offset: (Fc+ - Fc-)/2, as in force = ... + offset"),
    }
    out = {}
    for k, (g, unit, meaning) in combos.items():
        g = np.asarray(g, dtype=float)
        val = float(g @ theta)
        sd = float(math.sqrt(max(g @ cov @ g, 0.0)))
        out[k] = {"value": val, "ci95": [val - z * sd, val + z * sd], "std": sd, "unit": unit, "meaning": meaning}
    return out


#: An alternative command delay is reported when its fit's cost is lower by more than this fraction.
DELAY_MARGIN = 0.05
#: Replays spent on each alternative delay (its cost at the bound is an upper bound of its optimum,
#: so a warning it triggers holds; a missing warning means "not better within this budget").
DELAY_CHECK_EVALUATIONS = 4


def _starts(logs: Sequence[AxisLog]) -> list[tuple[float, float]]:
    """Each log's initial position (m) and measured speed (m/s), where its replay starts."""
    return [(float(lg.position_m[0]), float(measured_velocity(lg)[0])) for lg in logs]


def _channels(theta, logs: Sequence[AxisLog], flim: float, starts, skip: int = METRIC_SKIP_SAMPLES, second=None):
    """Position (m) and force (N) errors of each log's replay from sample ``skip`` on (``second``:
    the two-mass axis's second mass, :func:`simulate_axis`)."""
    out = []
    for lg, x0 in zip(logs, starts):
        tr = simulate_axis(theta, lg, force_limit_n=flim, x0=x0, second_mass=second)
        out.append((tr.position_m[skip:] - lg.position_m[skip:], lg.gain_n_per_unit * (tr.command[skip:] - lg.command[skip:])))
    return out


def _output_error(logs, theta0, free, x0, lb, sig, flim, max_evaluations, starts, strict: bool = True, second=None):
    """Least-squares output-error fit of the parameters ``free`` (the others stay at ``theta0``),
    position and force errors weighted by ``sig`` (m, N). Raises AxisFitError when it does not
    converge within ``max_evaluations`` residual evaluations (each Jacobian adds one replay per free
    parameter) (``strict=False``: returns the best point found,
    whose cost bounds the optimum from above)."""

    def resid(x):
        th = theta0.copy()
        th[free] = x
        ch = _channels(th, logs, flim, starts, second=second)
        return np.concatenate([np.concatenate([c[0] for c in ch]) / sig[0], np.concatenate([c[1] for c in ch]) / sig[1]])

    scale = np.maximum(np.abs(theta0[free]), 1e-3 * max(abs(theta0[0]), 1.0))
    sol = least_squares(resid, x0, bounds=(lb, np.inf), x_scale=scale, diff_step=1e-6, method="trf",
                        max_nfev=max_evaluations, xtol=1e-10, ftol=1e-10, gtol=1e-10)
    if strict and sol.status <= 0:
        raise AxisFitError(f"output-error fit did not converge within {max_evaluations} replays (cost {sol.cost:.6g}); "
                           "expected a log whose controller description reproduces the command")
    return sol


def logged_force_peak(logs: Sequence[AxisLog]) -> tuple[float, str]:
    """The largest logged drive force ``|gain x command|`` over ``logs``, N, and the log it is in."""
    peaks = [(float(np.max(np.abs(lg.force_n))) if lg.n else 0.0, lg.name) for lg in logs]
    return max(peaks, key=lambda p: p[0]) if peaks else (0.0, "")


def check_force_limit(flim: float, logs: Sequence[AxisLog], what: str) -> None:
    """Refuse a drive force limit (N) below the force a log holds: the replay clips the drive force
    at the limit in every sample, while the log says the drive applied more (force = gain x
    command), so the fit would explain the log with a force the drive never saturated at."""
    peak, where = logged_force_peak(logs)
    if flim < peak * (1.0 - 1e-9):
        raise ValueError(f"{what}: drive.force_limit_n = {flim:.6g} N is below the largest logged force {peak:.6g} N "
                         f"(drive gain x command) in {where}; expected a force limit >= the logged forces")


def normal_entry(value: float, sigma: float, positive: bool, source: str) -> dict | None:
    """The ``[uncertainty]`` entry of a fitted key: a normal of standard deviation ``sigma`` (a
    normal whose +-1.96 sigma is the fit's 95 % interval) truncated at 1.96 sigma, or closer where
    the key's physical range ends (mass > 0, friction >= 0) without ever crossing it
    (:func:`prsa_ctrl.plant.uncertainty.inner_truncation`); None when ``sigma`` is 0 or the
    truncation is below 0.1 sigma."""
    if not (sigma > 0 and math.isfinite(sigma)):
        return None
    trunc = inner_truncation(value, sigma, 0.0, limit=_Z95, open_floor=positive)
    if trunc < 0.1:
        return None
    return {"dist": "normal", "sigma": sigma, "truncate": trunc, "source": source}


def fit_linear_axis(logs: Sequence[AxisLog], base: LinearAxisPlant, *, max_evaluations: int = 60,
                    name: str = "fitted", check_delay: bool = True, validate: bool = True) -> AxisFit:
    """Calibrate a linear axis on closed-loop logs.

    1. Inverse-dynamic least squares (:func:`idim_estimate`) gives the start.
    2. Output error: the closed loop is replayed from the reference with the logged controller
       (:func:`simulate_axis`) and ``M, Fv+, Fv-, Fc+, Fc-`` minimise the weighted sum of squared
       position and force errors (``scipy.optimize.least_squares``, trust region, at most
       ``max_evaluations`` residual evaluations, each Jacobian by forward differences: at most
       ``max_evaluations * 6`` replays of each log). Logs without a described controller are
       replayed open loop from the logged command. A two-mass base (``axis.load_mass_kg`` > 0, e.g.
       from ``prsa-fit --frf``) is replayed as the two-mass axis (:attr:`LinearAxisPlant.second_mass`),
       its load mass, stiffness and damping held at the base's values and ``M`` kept above the load mass.
    3. 95 % intervals from the sandwich covariance that holds both a batch-means and a prewhitened
       Newey-West long-run variance of the scores, Student's t (:func:`prsa_ctrl.identification.covariance.score_covariance`): the residuals
       of a real axis are correlated over many samples,
       and intervals that treat them as white would be far too narrow.

    Parameters
    ----------
    logs : sequence of AxisLog
        Logs to fit (closed-loop logs need their controller and reference).
    base : LinearAxisPlant
        Supplies every value the fit does not estimate (drive gain, force limit, sensor). Its
        ``drive.force_limit_n`` clips the drive force in every replay, so it must be at least the
        largest logged force (gain x command, N).
    max_evaluations : int
        Bound on the residual evaluations of the output-error fit (an integer >= 1).
    name : str
        Name of the fitted plant.
    check_delay : bool
        Also fit with the command delay one sample shorter and longer than described and warn
        when one of them lowers the cost by more than :data:`DELAY_MARGIN`.
    validate : bool
        Validate the fitted plant on the logs
        (:func:`prsa_ctrl.identification.axisvalidation.validate_axis`; with more than one log each
        left out is replayed by the plant fitted on the others): ``validation["passes"]`` False and
        the status flagged when it does not explain them.

    Returns
    -------
    AxisFit

    Raises
    ------
    AxisFitError
        The logs do not move the axis, or the fit does not converge within the bound.
    ValueError
        The base's ``drive.force_limit_n`` is below the largest logged force (the replay would clip
        the drive force the log says was applied), or ``max_evaluations`` is not an integer >= 1.
    """
    if not logs:
        raise ValueError("logs: expected at least one log")
    if isinstance(max_evaluations, bool) or not isinstance(max_evaluations, (int, np.integer)) or max_evaluations < 1:
        raise ValueError(f"max_evaluations = {max_evaluations!r}; expected an integer >= 1 (residual evaluations of "
                         "the output-error fit)")
    check_force_limit(base.values.get("drive.force_limit_n", math.inf), logs, f"base plant {base.name!r}")
    theta0, informed = start_estimate(logs, base)
    base_theta = base.theta
    warnings = []
    for j in range(1, 5):
        if informed[j] and theta0[j] < 0:
            warnings.append(f"inverse-dynamic start of {PARAMETERS[j]} = {theta0[j]:.6g} < 0; started from 0")
            theta0[j] = 0.0
    for j in np.flatnonzero(~informed):
        warnings.append(f"{PARAMETERS[j]}: the logs never move the axis in that direction; kept the base value "
                        f"{base_theta[j]:.6g}")
    skip = METRIC_SKIP_SAMPLES
    flim = base.values.get("drive.force_limit_n", math.inf)

    starts = _starts(logs)
    second = base.second_mass  # a two-mass axis: its second mass held, M and the friction fitted on its replay
    if second is not None and not theta0[0] > second[0] * (1 + 1e-3):
        warnings.append(f"inverse-dynamic mass start {theta0[0]:.6g} kg is not above the load mass {second[0]:.6g} kg; "
                        f"started from {2 * second[0]:.6g} kg")
        theta0[0] = 2 * second[0]
    ch0 = _channels(theta0, logs, flim, starts, second=second)
    sig = (math.sqrt(np.mean(np.concatenate([c[0] for c in ch0]) ** 2)) or 1e-12,
           math.sqrt(np.mean(np.concatenate([c[1] for c in ch0]) ** 2)) or 1e-12)
    free = np.flatnonzero(informed)
    lb = np.where(free == 0, 1e-6 * theta0[0] if second is None else second[0] * (1 + 1e-3), 0.0)
    x0 = np.clip(theta0[free], lb, None)
    sol = _output_error(logs, theta0, free, x0, lb, sig, flim, max_evaluations, starts, second=second)
    delays = {}
    d0 = logs[0].controller.command_delay_samples if logs[0].controller is not None else None
    if check_delay and d0 is not None and all(lg.controller is not None for lg in logs):
        delays[d0] = float(sol.cost)
        for d in (d0 - 1, d0 + 1):
            if 0 <= d <= 10:
                alt = [dataclasses.replace(lg, controller=dataclasses.replace(lg.controller, command_delay_samples=d))
                       for lg in logs]
                alt_sol = _output_error(alt, theta0, free, sol.x, lb, sig, flim, DELAY_CHECK_EVALUATIONS, starts,
                                        strict=False, second=second)
                delays[d] = float(alt_sol.cost)
        best = min(delays, key=delays.get)
        if best != d0 and delays[best] < (1.0 - DELAY_MARGIN) * delays[d0]:
            warnings.append(f"a command delay of {best} samples fits better than the described {d0} (cost "
                            f"{delays[best]:.6g} against {delays[d0]:.6g}, more than {100 * DELAY_MARGIN:g} % lower); "
                            "check [controller] command_delay_samples and [command] logged")
    theta = theta0.copy()
    theta[free] = sol.x
    n_time = sum(lg.n - skip for lg in logs)
    # residual rows: [positions of all logs; forces of all logs] -> channel-major with n_time rows each
    cov_free, L = score_covariance(sol.jac, sol.fun, n_time)
    z = t95(L - 1)
    cov = np.zeros((len(PARAMETERS), len(PARAMETERS)))
    cov[np.ix_(free, free)] = cov_free
    at_bound = [PARAMETERS[j] for j, x in zip(free, sol.x) if x <= lb[list(free).index(j)] * (1 + 1e-9) + 1e-12]
    for k in at_bound:
        warnings.append(f"{k} ended at its bound (the load mass {second[0]:.6g} kg of the two-mass axis): the motor "
                        "side has no mass left; check axis.load_mass_kg" if k == PARAMETERS[0] else
                        f"{k} ended at its bound (0): the data do not support that friction term")
    names = ", ".join(Path(lg.name).name for lg in logs)
    params, values, sources, unc = {}, {}, {}, {}
    for j, k in enumerate(PARAMETERS):
        sd = float(math.sqrt(max(cov[j, j], 0.0)))
        v = float(theta[j])
        entry = {"value": v, "ci95": [v - z * sd, v + z * sd], "std": sd, "unit": _UNITS[k],
                 "start": float(theta0[j])}
        if not informed[j]:  # kept, not fitted: no interval (was a zero-width one)
            entry.update(ci95=None, std=None, note="kept at the base value, not fitted: no interval")
            entry["kept_base"] = True
            sources[k] = base.sources[k]
        else:
            sources[k] = f"fit: {names} (95 % CI {v - z * sd:.6g}..{v + z * sd:.6g}; closed-loop output error)"
            entry_k = normal_entry(v, z * sd / _Z95, j == 0, f"fit: {names} (95 % CI {v - z * sd:.6g}..{v + z * sd:.6g})")
            typed = base.uncertainty.get(k)
            if isinstance(typed, dict) and "low" in typed and "high" in typed and not typed["low"] <= v <= typed["high"]:
                warnings.append(outside_note(k, v, (v - z * sd, v + z * sd), typed, "the fit's entry is written instead"
                                             if entry_k is not None else "no [uncertainty] entry written for it"))
            if entry_k is not None:
                unc[k] = entry_k
        params[k] = entry
        values[k] = v
    idx = [j for j, k in enumerate(PARAMETERS) if k in unc]
    corr = correlation_entry([PARAMETERS[j] for j in idx], cov[np.ix_(idx, idx)],
                             f"fit: {names} (correlation of the fitted keys from the fit's covariance)")
    # the base's entries on keys the fit leaves alone are kept, its correlation blocks restricted to them
    kept = {k: e for k, e in base.uncertainty.items() if k not in unc and k not in {PARAMETERS[j] for j in free}}
    unc = carry_correlation({**kept, **unc}, base.uncertainty, corr, warnings)
    what = f"linear axis calibrated by prsa-fit from {names} (closed-loop output error" + (
        f"; two-mass axis, its second mass held at the base's {second[0]:.6g} kg, {second[1] * 1e-6:.6g} N/um)"
        if second is not None else ")")
    fitted = LinearAxisPlant(name=name, values={**base.values, **values}, sources={**base.sources, **sources},
                             description=f"{base.description}; {what}" if base.description else what,
                             command_unit=base.command_unit, uncertainty=unc)
    replays = [replay_axis(fitted, lg) for lg in logs]
    validation = {}
    if validate:
        from .axisvalidation import validate_axis

        def refit(others):
            return fit_linear_axis(others, base, max_evaluations=max_evaluations, name=name, check_delay=False,
                                   validate=False).plant
        kept = [f"{PARAMETERS[j]} kept at the base value" for j in np.flatnonzero(~informed)]
        validation = validate_axis(fitted, logs, replays, replay_axis, METRIC_SKIP_SAMPLES, refit=refit,
                                   unidentified=kept + [f"{k} ended at its bound (0)" for k in at_bound])
        if not validation["passes"]:
            warnings.append(f"validation failed: {validation['reasons'][0]}" + (
                f" (and {len(validation['reasons']) - 1} more)" if len(validation["reasons"]) > 1 else "")
                + f"; most likely missing physics: {validation['diagnosis']}")
    status = axis_fit_status(replays, at_bound)
    if validation and not validation["passes"]:
        status = ("flagged: " if status == "ok" else status + "; ") + f"validation failed: {validation['reasons'][0]}"
    return AxisFit(fitted, params, _equivalents(theta, cov, z), dict(zip(PARAMETERS, map(float, theta0))), replays,
                   cov, L, status, int(sol.nfev), warnings, float(sol.cost), str(sol.message),
                   delays, validation=validation)


def axis_fit_status(replays: Sequence[AxisReplay], at_bound: Sequence[str]) -> str:
    """The fit's status (:data:`prsa_ctrl.results.STATUSES`): ``"ok"`` when every replay of the
    fitted plant on the nonlinear simulator is finite (every error and fit % a number) and no
    fitted friction term ended at its bound; ``"flagged: ..."`` naming what failed otherwise."""
    bad = [r.name for r in replays
           if not all(math.isfinite(float(x)) for x in (*r.errors_percent.values(), *r.fit_percent.values()))]
    why = ([f"the replay of {', '.join(bad)} is not finite"] if bad else []) + \
        ([f"{', '.join(at_bound)} ended at its bound (0)"] if at_bound else [])
    return "flagged: " + "; ".join(why) if why else "ok"
