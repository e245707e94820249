"""Plant definitions: loading, validation, defaults, geometry matching and rigid kinematics.

A plant file (``plants/*.toml``) names its ``mechanism`` (default ``inverted-roller-screw``;
:data:`prsa_ctrl.plant.schema.MECHANISMS`) and holds one table per component; every parameter
is an inline table ``{ value = ..., source = "..." }`` so that its origin (paper table, paper
text, catalogue, or ``"assumption: <why>"``) travels with it. Only a few keys are required
per mechanism (:data:`~prsa_ctrl.plant.schema.REQUIRED`); every other key takes its documented
default with that default's source (:data:`~prsa_ctrl.plant.schema.DEFAULTS`), and
:func:`prsa_ctrl.plant.describe.describe_plant` (``prsa-tune --show-plant``) lists every value
the plant uses (:func:`~prsa_ctrl.plant.describe.used_keys`), given or defaulted. Key
names carry their units; inside the library everything is SI.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import GeometryWarning, PlantFileError
from ..results import FrozenDict, freeze
from ..options import check_number
from ..textsafe import quote
from ..tomlfile import read_toml
from .schema import (ALLOWED_KEYS, BREAKAWAY_KEY, FINITE, VISCOUS_OFFSET_KEY, DEFAULT_MECHANISM, DEFAULTS, FRACTION, KIND, MECHANISMS,  # noqa: F401
                     MOUNTINGS, DEFAULT_MOUNTING, NON_NEGATIVE, NON_NEGATIVE_INTEGER, PLAUSIBLE, POSITIVE, POSITIVE_INTEGER, REQUIRED, SCHEMA,
                     SCREW_DRIVEN, UNITS, keys_of)
from .uncertainty import check_plant_uncertainty

__all__ = [
    "Plant",
    "Kinematics",
    "GeometryReport",
    "load_plant",
    "builtin_plants",
    "plant_file_path",
    "DEFAULT_PLANT",
    "PLANT_FILE_BYTES_MAX",
    "SCHEMA",
    "PLAUSIBLE",
]

DEFAULT_PLANT = "paper-iprsm"
#: Bytes at most of a plant file (the shipped ones hold under 10 kB): a larger one is refused before
#: it is read (a fit parses its base twice with tomlkit, about 4 s per megabyte).
PLANT_FILE_BYTES_MAX = 1_000_000
_STEEL_KG_M3 = 7850.0  # density of steel, kg/m^3 (as the defaults of plant/schema.py)

def builtin_root(package: str, folder: str) -> Any:
    """Where the built-in TOML files live: the installed package data, or, when running from a
    source checkout that shadows the installed package, the repository folder itself."""
    try:
        return resources.files(package)
    except ModuleNotFoundError:
        return Path(__file__).resolve().parents[2] / folder  # prsa_ctrl/plant/plantfile.py -> the checkout


def builtin_plants() -> list[str]:
    """Names of the plant files shipped with the package (``plants/*.toml``)."""
    root = builtin_root("prsa_ctrl.plants", "plants")
    return sorted(p.name[:-5] for p in root.iterdir() if p.name.endswith(".toml"))


def _likely_mistake(key: str, v: float) -> str:
    """The unit mistake a value outside ``PLAUSIBLE`` most likely is (empty if none stands out)."""
    if key == "sensor.encoder_counts_per_rev" and v <= 32:
        return f"; a resolution in bits typed as counts? {v:g} bits = {2 ** int(v)} counts"
    return ""


#: Largest torque limit as a multiple of the torque that drives the screw's rated load
#: (``rated_load L / (2 pi eta)``): static load ratings are ~2-3x the dynamic one, and a
#: rotor's acceleration torque is of the same order; 20x is beyond any real pairing of motor
#: and screw (the built-in plants: 1.3x to 1.6x), while a torque in mN m typed as N m is 1000x.
TORQUE_LIMIT_MAX_RATIO = 20.0
#: Slowest speed-measurement filter, in controller samples (25 ms at 4 kHz): beyond it the
#: measurement lags every speed loop a sampled drive can close (crossover ~0.01..0.1 / Ts);
#: a time constant in ms typed as s is 1000x.
SPEED_FILTER_MAX_SAMPLES = 100.0
#: Largest torque-measurement noise as a fraction of the torque limit (current sensing is
#: ~0.1-1 % of the peak current).
TORQUE_NOISE_MAX_FRACTION = 0.1


_CONSISTENCY_KEYS = ("drive.torque_limit_n_m", "screw.rated_load_n", "screw.lead_mm", "friction.efficiency",
                     "friction.no_load_torque_n_m", "sensor.torque_noise_n_m", "sensor.sample_time_s",
                     "sensor.speed_filter_time_constant_s", "friction.traction_preload_n")


def _check_consistency(v: Mapping[str, float], o: str) -> None:
    """Cross-checks between keys of a plant file that catch unit mistakes a single range
    cannot (:data:`TORQUE_LIMIT_MAX_RATIO`, :data:`SPEED_FILTER_MAX_SAMPLES`,
    :data:`TORQUE_NOISE_MAX_FRACTION`, drag below the torque limit, traction preload at most
    the rated load)."""
    t_lim = v["drive.torque_limit_n_m"]
    t_rated = v["screw.rated_load_n"] * v["screw.lead_mm"] * 1e-3 / (2 * math.pi * v["friction.efficiency"])
    if t_lim > TORQUE_LIMIT_MAX_RATIO * t_rated:
        force = t_lim * 2 * math.pi * v["friction.efficiency"] / (v["screw.lead_mm"] * 1e-3)
        raise PlantFileError(
            f"{o}: drive.torque_limit_n_m = {t_lim:g} N m would push {force:.3g} N through the screw, "
            f"{t_lim / t_rated:.0f} x its screw.rated_load_n = {v['screw.rated_load_n']:g} N (which needs {t_rated:.3g} N m "
            f"at screw.lead_mm = {v['screw.lead_mm']:g}, friction.efficiency = {v['friction.efficiency']:g}); expected at "
            f"most {TORQUE_LIMIT_MAX_RATIO:g} x that ({TORQUE_LIMIT_MAX_RATIO * t_rated:.3g} N m); a torque in mN m typed as N m?")
    if v["friction.no_load_torque_n_m"] >= t_lim:
        raise PlantFileError(
            f"{o}: friction.no_load_torque_n_m = {v['friction.no_load_torque_n_m']:g} N m is not below "
            f"drive.torque_limit_n_m = {t_lim:g} N m (the motor could not even turn the unloaded screw); check both units")
    t_s0 = v.get(BREAKAWAY_KEY, v["friction.no_load_torque_n_m"])
    if isinstance(t_s0, (int, float)) and t_s0 < v["friction.no_load_torque_n_m"]:
        raise PlantFileError(
            f"{o}: {BREAKAWAY_KEY} = {t_s0:g} N m is below friction.no_load_torque_n_m = "
            f"{v['friction.no_load_torque_n_m']:g} N m; expected breakaway >= sliding drag (as friction.static >= "
            "friction.dynamic; leave the key out for no breakaway excess)")
    b, b_o = v.get("friction.viscous_n_m_s_per_rad", 0.0), v.get(VISCOUS_OFFSET_KEY, 0.0)
    if isinstance(b_o, (int, float)) and isinstance(b, (int, float)) and abs(b_o) > b:
        raise PlantFileError(
            f"{o}: {VISCOUS_OFFSET_KEY} = {b_o:g} N m s/rad exceeds friction.viscous_n_m_s_per_rad = {b:g} N m s/rad "
            "in magnitude; expected |offset| <= viscous (the coefficients b + offset forward and b - offset backward "
            "are not negative)")
    if isinstance(t_s0, (int, float)) and t_s0 >= t_lim:
        raise PlantFileError(
            f"{o}: {BREAKAWAY_KEY} = {t_s0:g} N m is not below drive.torque_limit_n_m = {t_lim:g} N m (the motor "
            "could not break the unloaded screw loose); check both units")
    if v["sensor.torque_noise_n_m"] > TORQUE_NOISE_MAX_FRACTION * t_lim:
        raise PlantFileError(
            f"{o}: sensor.torque_noise_n_m = {v['sensor.torque_noise_n_m']:g} N m is more than "
            f"{TORQUE_NOISE_MAX_FRACTION:.0%} of drive.torque_limit_n_m = {t_lim:g} N m (current sensing is ~0.1-1 % of "
            "the peak); check its unit (N m RMS per sample)")
    ts, tf = v["sensor.sample_time_s"], v["sensor.speed_filter_time_constant_s"]
    if tf > SPEED_FILTER_MAX_SAMPLES * ts:
        raise PlantFileError(
            f"{o}: sensor.speed_filter_time_constant_s = {tf:g} s is {tf / ts:.0f} controller samples "
            f"(sensor.sample_time_s = {ts:g} s); expected at most {SPEED_FILTER_MAX_SAMPLES:g} samples "
            f"({SPEED_FILTER_MAX_SAMPLES * ts:g} s): a time constant in ms typed as s?")
    if v["friction.traction_preload_n"] > v["screw.rated_load_n"]:
        raise PlantFileError(
            f"{o}: friction.traction_preload_n = {v['friction.traction_preload_n']:g} N exceeds screw.rated_load_n = "
            f"{v['screw.rated_load_n']:g} N; expected a preload of at most the rated load")


#: The range of each kind of plant-file number: (low bound, high bound, low bound excluded, whole).
_KIND_RANGE = {POSITIVE: (0.0, math.inf, True, False), NON_NEGATIVE: (0.0, math.inf, False, False),
               POSITIVE_INTEGER: (1.0, math.inf, False, True), NON_NEGATIVE_INTEGER: (0.0, math.inf, False, True),
               FRACTION: (0.0, 1.0, True, False), FINITE: (-math.inf, math.inf, False, False)}


def _check_value(kind: str, key: str, value: Any, origin: str, plausible: bool = True) -> float:
    where = f"{origin}: {key}"
    lo, hi, lo_open, whole = _KIND_RANGE[kind]
    expected = {POSITIVE: "a finite positive number", NON_NEGATIVE: "a finite non-negative number",
                FINITE: "a finite number"}.get(kind, f"a {kind}")
    v = check_number(where, value, lo, hi, lo_open=lo_open, error=PlantFileError, expected=expected)
    if whole and v != int(v):
        raise PlantFileError(f"{where} = {quote(value)}; expected {expected}")
    if plausible and key in PLAUSIBLE:
        lo, hi, why = PLAUSIBLE[key]
        if not lo <= v <= hi:
            raise PlantFileError(
                f"{where} = {quote(value)} is outside the plausible range [{lo:g}, {hi:g}] ({why}); "
                "check the value and its unit" + _likely_mistake(key, v)
            )
    return v


def _text_key(doc: Mapping[str, Any], key: str, choices, default: str, origin: str) -> tuple[str, str, bool]:
    """``(value, source, given)`` of a top-level text key (``mechanism``, ``mounting``): a plain
    string or ``{ value = "...", source = "..." }``."""
    if key not in doc:
        return default, f"default: {default}", False
    entry = doc[key]
    src = "plant file"
    if isinstance(entry, Mapping):
        if set(entry) != {"value", "source"} or not isinstance(entry["source"], str) or not entry["source"].strip():
            raise PlantFileError(f'{origin}: {key} = {quote(entry)}; expected "<name>" or {{ value = "<name>", source = "<why>" }}')
        entry, src = entry["value"], entry["source"].strip()
    if entry not in choices:
        raise PlantFileError(f"{origin}: {key} = {quote(entry)}; expected one of {', '.join(repr(c) for c in choices)}")
    return entry, src, True


#: Top-level entries besides the sections; ``coordinates`` and ``drive.command_unit`` are the
#: linear-axis file's (:mod:`prsa_ctrl.identification.axis`), accepted and not used here.
_TOP_LEVEL = ("name", "description", "mechanism", "mounting", "uncertainty")


def _sections(mechanism: str) -> dict[str, tuple[str, ...]]:
    out: dict[str, list[str]] = {}
    for full in keys_of(mechanism):
        section, key = full.split(".")
        out.setdefault(section, []).append(key)
    return {s: tuple(k) for s, k in out.items()}


def _given_values(doc: Mapping[str, Any], mechanism: str, origin: str) -> tuple[dict[str, float], dict[str, str]]:
    """The keys the file gives, checked (kind and plausible range), with their sources."""
    sections = _sections(mechanism)
    top = _TOP_LEVEL + (("coordinates",) if mechanism == "linear-axis" else ())
    unknown = sorted(set(doc) - set(sections) - set(top))
    if unknown:
        other = [m for m in MECHANISMS if unknown[0] in _sections(m)]
        hint = f" (a section of mechanism {', '.join(other)}; this file's mechanism is {quote(mechanism)})" if other else ""
        raise PlantFileError(f"{origin}: unknown section {quote(unknown[0])}; expected one of "
                             f"{', '.join([*top[:2], *sections, *top[2:]])}{hint}")
    if mechanism == "linear-axis" and doc.get("coordinates", "load") != "load":
        raise PlantFileError(f"{origin}: coordinates = {quote(doc['coordinates'])}; expected \"load\" (m, N)")
    values: dict[str, float] = {}
    sources: dict[str, str] = {}
    for section, keys in sections.items():
        table = doc.get(section, {})
        if not isinstance(table, Mapping):
            raise PlantFileError(f"{origin}: {section} = {quote(table)}; expected a table [{section}]")
        extra = sorted(set(table) - set(keys) - ({"command_unit"} if (mechanism, section) == ("linear-axis", "drive") else set()))
        if extra:
            full = f"{section}.{extra[0]}"
            other = [m for m in MECHANISMS if full in keys_of(m)]
            hint = f" ({full} belongs to mechanism {', '.join(other)}; this file's mechanism is {quote(mechanism)})" if other else ""
            raise PlantFileError(
                f"{origin}: unknown key {full}; expected one of {', '.join(f'{section}.{k}' for k in keys)}{hint}")
        for key in keys:
            full = f"{section}.{key}"
            if key not in table:
                continue
            entry = table[key]
            if not isinstance(entry, Mapping) or set(entry) != {"value", "source"}:
                raise PlantFileError(
                    f"{origin}: {full} = {quote(entry)}; expected {{ value = <number>, "
                    f'source = "<paper table/text or assumption: why>" }}'
                )
            src = entry["source"]
            if not isinstance(src, str) or not src.strip():
                raise PlantFileError(f"{origin}: {full}.source = {quote(src)}; expected a non-empty string")
            values[full] = _check_value(KIND[full], full, entry["value"], origin)
            sources[full] = src.strip()
    return values, sources


def _default_source(key: str, mechanism: str) -> str:
    src = DEFAULTS[key][1]
    return src if isinstance(src, str) else src.get(mechanism, src.get("*", ""))


def _fill_defaults(values: dict[str, float], sources: dict[str, str], mechanism: str, origin: str) -> set[str]:
    """Add every key of ``mechanism`` the file left out (:data:`~prsa_ctrl.plant.schema.DEFAULTS`);
    return the keys defaulted. Rules are evaluated once their inputs exist (bounded: one pass
    per key at most)."""
    todo = [k for k in keys_of(mechanism) if k not in values]
    missing = [k for k in REQUIRED[mechanism] if k not in values]
    if missing:
        raise PlantFileError(
            f"{origin}: missing key {missing[0]}; expected it for mechanism = {quote(mechanism)} "
            f"(required: {', '.join(REQUIRED[mechanism])}; every other key has a default, see prsa-tune --show-plant)")
    defaulted = set(todo)
    for _ in range(len(todo) + 1):
        if not todo:
            break
        left = []
        for key in todo:
            rule = DEFAULTS[key][0]
            try:
                v = rule(values, mechanism) if callable(rule) else rule
            except KeyError:
                left.append(key)
                continue
            values[key] = _check_value(KIND[key], key, v, f"{origin} (default)", plausible=False)
            sources[key] = _default_source(key, mechanism)
        todo = left
    if todo:  # a rule whose inputs never appear: a defect of the DEFAULTS table, not of the file
        raise RuntimeError(f"plant defaults: no value for {', '.join(todo)} (DEFAULTS rules depend on missing keys)")
    return defaulted


def _check_screw_axis(v: Mapping[str, float], o: str) -> None:
    """Cross-checks of a screw-driven axis: the nut within the bearing span (strictly inside for
    fixed-fixed), the root below the pitch diameter."""
    x, span = v["axis.stroke_position_mm"], v["axis.bearing_span_mm"]
    if x > span or (v["axis.fixed_ends"] == 2 and x >= span):
        raise PlantFileError(
            f"{o}: axis.stroke_position_mm = {x:g} mm is not inside axis.bearing_span_mm = {span:g} mm; expected "
            f"0 < stroke position {'<' if v['axis.fixed_ends'] == 2 else '<='} span (distance of the nut from the fixed bearing)")
    if v["screw.root_diameter_mm"] >= v["screw.pitch_diameter_mm"]:
        raise PlantFileError(
            f"{o}: screw.root_diameter_mm = {v['screw.root_diameter_mm']:g} is not below screw.pitch_diameter_mm = "
            f"{v['screw.pitch_diameter_mm']:g}; expected the thread root inside the pitch circle")


def _check_linear_axis(v: Mapping[str, float], o: str) -> None:
    """Cross-check of a linear axis: the mass beyond its spring is a part of the whole moving mass."""
    if v["axis.load_mass_kg"] >= v["axis.mass_kg"]:
        raise PlantFileError(
            f"{o}: axis.load_mass_kg = {v['axis.load_mass_kg']:g} kg is not below axis.mass_kg = {v['axis.mass_kg']:g} kg; "
            "expected the load side's part of the whole moving mass (0: a rigid axis)")


def _parse(doc: Mapping[str, Any], origin: str):
    """Validate a parsed plant document; return name, description, mechanism, values, sources
    and the keys defaulted."""
    name = doc.get("name")
    if not isinstance(name, str) or not name.strip():
        raise PlantFileError(f"{origin}: name = {quote(name)}; expected a non-empty string")
    description = doc.get("description", "")
    if not isinstance(description, str):
        raise PlantFileError(f"{origin}: description = {quote(description)}; expected a string")
    mechanism, mech_src, _ = _text_key(doc, "mechanism", MECHANISMS, DEFAULT_MECHANISM, origin)
    if "mounting" in doc and mechanism not in SCREW_DRIVEN:
        raise PlantFileError(f"{origin}: mounting = {quote(doc['mounting'])} for mechanism = {quote(mechanism)}; expected no "
                             f"mounting (it applies to {', '.join(SCREW_DRIVEN)})")
    values, sources = _given_values(doc, mechanism, origin)
    if mechanism in SCREW_DRIVEN and "mounting" in doc:
        if "axis.fixed_ends" in values:
            raise PlantFileError(f"{origin}: both mounting and axis.fixed_ends given; expected one of them")
        mounting, m_src, _ = _text_key(doc, "mounting", tuple(MOUNTINGS), DEFAULT_MOUNTING, origin)
        values["axis.fixed_ends"] = float(MOUNTINGS[mounting])
        sources["axis.fixed_ends"] = f"{m_src} (mounting = {quote(mounting)})"
    defaulted = _fill_defaults(values, sources, mechanism, origin)
    if mechanism in SCREW_DRIVEN:
        _check_screw_axis(values, origin)
    if mechanism == "linear-axis":
        _check_linear_axis(values, origin)
    ordered = {k: values[k] for k in keys_of(mechanism)}
    return name.strip(), description, mechanism, mech_src, ordered, {k: sources[k] for k in ordered}, defaulted


@dataclass(frozen=True)
class Kinematics:
    """Rigid-body speeds of the inverted roller screw for a given nut speed.

    Attributes
    ----------
    omega_nut : ndarray, rad/s
        Nut (input) angular speed.
    omega_cage : ndarray, rad/s
        Cage (retainer) speed = roller orbit speed, ``w_N d_N / (d_N + d_S)``.
    omega_roller_rel : ndarray, rad/s
        Roller spin relative to the cage (what the roller-cage revolute joint measures),
        ``w_P d_S / d_R``. This is what ``roller_speed`` means in every simulation output.
    omega_roller_abs : ndarray, rad/s
        Roller spin relative to ground, ``w_P (d_S + d_R) / d_R``.
    v_screw : ndarray, m/s
        Screw axial speed, ``lead w_N / (2 pi)``.
    """

    omega_nut: NDArray[np.float64]
    omega_cage: NDArray[np.float64]
    omega_roller_rel: NDArray[np.float64]
    omega_roller_abs: NDArray[np.float64]
    v_screw: NDArray[np.float64]


@dataclass(frozen=True)
class GeometryReport:
    """How well the thread geometry closes. Lengths in metres, angles in radians.

    ``closure_residual_m`` is ``d_N - (d_S + 2 d_R)``; ``screw_match_residual_m`` is
    ``d_S - n_S d_R`` and ``nut_match_residual_m`` is ``d_N - (n_S + 2) d_R`` (the matching rule of
    the inverted design with rollers of opposite hand); ``helix_mismatch_rad`` is the screw helix
    angle minus the roller helix angle, which the rule makes zero.
    """

    closure_residual_m: float
    screw_match_residual_m: float
    nut_match_residual_m: float
    helix_screw_rad: float
    helix_nut_rad: float
    helix_roller_rad: float
    helix_mismatch_rad: float
    pitch_m: float
    messages: tuple[str, ...]

    def lines(self) -> list[str]:
        """Human-readable report lines (mm and degrees)."""
        deg = math.degrees
        out = [
            f"d_N - (d_S + 2 d_R) = {self.closure_residual_m * 1e3:+.3f} mm",
            f"d_S - n_S d_R       = {self.screw_match_residual_m * 1e3:+.3f} mm",
            f"d_N - (n_S+2) d_R   = {self.nut_match_residual_m * 1e3:+.3f} mm",
            f"helix angles: screw {deg(self.helix_screw_rad):.3f} deg, nut "
            f"{deg(self.helix_nut_rad):.3f} deg, roller {deg(self.helix_roller_rad):.3f} deg "
            f"(screw - roller {deg(self.helix_mismatch_rad):+.3f} deg)",
            f"thread pitch {self.pitch_m * 1e3:.4f} mm",
        ]
        return out + list(self.messages)


@dataclass(frozen=True, eq=False)
class Plant:
    """A screw actuator (or a linear axis), validated.

    Use :func:`load_plant` to build one. ``values`` keeps the numbers (file units, keys
    ``section.key``); the ``*_m``, ``*_kg`` ... properties give SI values. ``sources`` says
    where each value came from: the file's own source string, or ``"default: ..."`` /
    ``"derived: ..."`` for a key the file left out (``defaulted`` lists those keys; see
    :data:`prsa_ctrl.plant.schema.DEFAULTS` and :func:`prsa_ctrl.plant.describe.describe_plant`).

    ``mechanism`` (:data:`~prsa_ctrl.plant.schema.MECHANISMS`) sets the kinematics, the
    reflected inertia and what the compliant fidelity is (:mod:`prsa_ctrl.plant.model`). A
    plant built without one takes it from its keys: ``axis.mass_kg`` makes a linear axis,
    ``axis.moving_mass_kg`` a screw-driven axis (``ball-screw``; a ``roller-screw`` has the
    same equations), otherwise the inverted roller screw.
    """

    name: str
    values: Mapping[str, float]
    sources: Mapping[str, str]
    origin: str = "<dict>"
    description: str = ""
    geometry: GeometryReport = field(init=False, repr=False)
    #: The file's ``[uncertainty]`` section (validated by :mod:`prsa_ctrl.plant.uncertainty`).
    uncertainty: Mapping[str, Any] = field(default_factory=dict, repr=False)
    mechanism: str | None = None
    #: Keys the file left out (their values and sources come from ``DEFAULTS``).
    defaulted: frozenset = field(default_factory=frozenset, repr=False)
    #: Source of the mechanism: the file's (``"plant file"`` or its own source) or ``"default: ..."``.
    mechanism_source: str = ""

    def __post_init__(self) -> None:
        values = dict(self.values)
        if BREAKAWAY_KEY in values and BREAKAWAY_KEY not in self.defaulted and str(
                self.sources.get(BREAKAWAY_KEY, "")) == _default_source(BREAKAWAY_KEY, ""):
            # a plant rebuilt from another's values and sources (without ``defaulted``): the
            # default breakaway level still follows the no-load torque
            object.__setattr__(self, "defaulted", frozenset(self.defaulted) | {BREAKAWAY_KEY})
            if isinstance(values["friction.no_load_torque_n_m"], (int, float)):
                values[BREAKAWAY_KEY] = values["friction.no_load_torque_n_m"]
        object.__setattr__(self, "values", FrozenDict(values))  # read-only, and pickles (process pools)
        object.__setattr__(self, "sources", FrozenDict(self.sources))
        object.__setattr__(self, "uncertainty", freeze(self.uncertainty))
        object.__setattr__(self, "defaulted", frozenset(self.defaulted))
        if self.mechanism is None:
            inferred = ("linear-axis" if "axis.mass_kg" in self.values
                        else "ball-screw" if "axis.moving_mass_kg" in self.values else DEFAULT_MECHANISM)
            object.__setattr__(self, "mechanism", inferred)
        elif self.mechanism not in MECHANISMS:
            raise PlantFileError(f"{self.origin}: mechanism = {quote(self.mechanism)}; expected one of "
                                 f"{', '.join(repr(m) for m in MECHANISMS)}")
        if not self.mechanism_source:
            object.__setattr__(self, "mechanism_source", "inferred from the keys")
        if all(isinstance(self.values.get(k), (int, float)) for k in _CONSISTENCY_KEYS):  # not symbolic (fit)
            _check_consistency(self.values, self.origin)
        object.__setattr__(self, "geometry", self._check_geometry())

    @property
    def screw_driven(self) -> bool:
        """True for a ``roller-screw`` or ``ball-screw``: the motor turns the screw, the nut translates."""
        return self.mechanism in SCREW_DRIVEN

    def given(self, key: str) -> bool:
        """Whether the plant file gave ``key`` (False: defaulted or derived, see ``sources``)."""
        if key not in self.values:
            raise KeyError(f"{quote(key)} is not a key of this {self.mechanism} plant")
        return key not in self.defaulted

    # --- construction -------------------------------------------------------------------------
    @classmethod
    def from_dict(cls, doc: Mapping[str, Any], origin: str = "<dict>") -> "Plant":
        """Validate a plant document (the parsed TOML) and build the plant."""
        name, description, mechanism, mech_src, values, sources, defaulted = _parse(doc, origin)
        plant = cls(name=name, values=values, sources=sources, origin=origin, description=description,
                    uncertainty=doc.get("uncertainty", {}), mechanism=mechanism, defaulted=frozenset(defaulted),
                    mechanism_source=mech_src)
        if "uncertainty" in doc:
            check_plant_uncertainty(plant)
        return plant

    def to_toml(self, base_text: str | None = None, *, name: str | None = None, keys=None,
                description: str | None = None, uncertainty_keys=None, header=()) -> str:
        """This plant as a plant file's text (:func:`prsa_ctrl.plant.writer.plant_toml`, the one
        plant-file writer): with ``base_text`` the base file's layout and comments kept and the
        ``keys`` (``section.key``) rewritten with this plant's values and sources; without it every
        given key written afresh. ``header``: comment lines put first. The text reads back as
        the plant written (checked)."""
        from .writer import plant_toml

        return plant_toml(self, base_text, name=name, keys=keys, description=description,
                          uncertainty_keys=uncertainty_keys, header=header)

    def with_params(self, overrides: Mapping[str, float], name: str | None = None) -> "Plant":
        """Copy of the plant with some values replaced (file units, keys ``section.key``).

        Raises
        ------
        PlantFileError
            For an unknown key (the message lists the allowed ones) or an invalid value.
        """
        values = dict(self.values)
        sources = dict(self.sources)
        for key, v in overrides.items():
            if key not in values:
                raise PlantFileError(
                    f"{self.name}: unknown parameter {quote(key)}; allowed: {', '.join(self.values)}"
                )
            if key in self.defaulted and sources[key].startswith("derived:"):
                raise PlantFileError(f"{self.name}: {key} = {quote(v)} cannot be set: it is {sources[key]}; expected a "
                                     "value for the key it is derived from")
            values[key] = _check_value(KIND[key], key, v, f"{self.name} override")
            sources[key] = "override"
        defaulted = self.defaulted - set(overrides)
        if defaulted:  # defaults follow the values they derive from (e.g. the screw inertia its span)
            kept = {k: v for k, v in values.items() if k not in defaulted}
            srcs = {k: v for k, v in sources.items() if k not in defaulted}
            _fill_defaults(kept, srcs, self.mechanism, f"{self.name} override")
            values = {k: kept[k] for k in values}
            sources = {k: srcs[k] for k in values}
        if self.screw_driven:
            _check_screw_axis(values, f"{self.name} override")
        if self.mechanism == "linear-axis":
            _check_linear_axis(values, f"{self.name} override")
        return Plant(
            name=name or f"{self.name}*",
            values=values,
            sources=sources,
            origin=self.origin,
            description=self.description,
            uncertainty=self.uncertainty,
            mechanism=self.mechanism,
            defaulted=defaulted,
            mechanism_source=self.mechanism_source,
        )

    # --- SI views -----------------------------------------------------------------------------
    def _v(self, key: str) -> float:
        return self.values[key]

    @property
    def d_screw_m(self) -> float:
        """Screw pitch diameter d_S, m."""
        return self._v("screw.pitch_diameter_mm") * 1e-3

    @property
    def d_nut_m(self) -> float:
        """Nut pitch diameter d_N, m."""
        return self._v("nut.pitch_diameter_mm") * 1e-3

    @property
    def d_roller_m(self) -> float:
        """Roller pitch diameter d_R, m."""
        return self._v("roller.pitch_diameter_mm") * 1e-3

    @property
    def lead_m(self) -> float:
        """Screw lead (screw advance per nut revolution), m."""
        return self._v("screw.lead_mm") * 1e-3

    @property
    def lead_per_rad(self) -> float:
        """Screw advance per radian of nut rotation, m/rad."""
        return self.lead_m / (2.0 * math.pi)

    @property
    def n_rollers(self) -> int:
        return int(self._v("roller.count"))

    @property
    def n_contacts(self) -> int:
        """Engaged thread contacts per interface (rollers x engaged threads)."""
        return self.n_rollers * int(self._v("thread.engaged_threads"))

    @property
    def cage_ratio(self) -> float:
        """Cage (roller carrier) speed per unit motor speed: ``d_N / (d_N + d_S)`` for the inverted
        roller screw (the nut turns), ``d_S / (d_S + d_N)`` for a screw-driven roller screw (the
        screw turns, the nut does not), 0 for a ball screw (the ball train is not modelled) and a
        linear axis."""
        if self.mechanism == "inverted-roller-screw":
            return self.d_nut_m / (self.d_nut_m + self.d_screw_m)
        if self.mechanism == "roller-screw":
            return self.d_screw_m / (self.d_screw_m + self.d_nut_m)
        return 0.0

    @property
    def roller_spin_ratios(self) -> tuple[float, float]:
        """Roller spin per unit cage speed: (relative to the cage, relative to ground).

        Rolling without slip at both pitch circles, one sign convention for both designs
        (relative spin = absolute spin - cage speed): inverted (nut turns, screw still)
        ``(d_S / d_R, (d_S + d_R) / d_R)``; screw-driven roller screw (screw turns, nut still)
        ``(-d_N / d_R, -(d_S + d_R) / d_R)`` (the rollers spin against the carrier's orbit);
        0 where there are no rollers.
        """
        d_s, d_n, d_r = self.d_screw_m, self.d_nut_m, self.d_roller_m
        if self.mechanism == "inverted-roller-screw":
            return d_s / d_r, (d_s + d_r) / d_r
        if self.mechanism == "roller-screw":
            return -d_n / d_r, -(d_s + d_r) / d_r
        return 0.0, 0.0

    @property
    def helix_nut_rad(self) -> float:
        return math.atan(self._v("nut.lead_mm") / (math.pi * self._v("nut.pitch_diameter_mm")))

    @property
    def helix_screw_rad(self) -> float:
        return math.atan(self._v("screw.lead_mm") / (math.pi * self._v("screw.pitch_diameter_mm")))

    @property
    def flank_angle_rad(self) -> float:
        return math.radians(self._v("thread.flank_angle_deg"))

    @property
    def contact_stiffness_si(self) -> float:
        """IMPACT stiffness K in N/m^e (file value is N/mm^e: K_SI = K_mm * 1000^e)."""
        return self._v("contact.stiffness_n_per_mm_e") * 1000.0 ** self._v("contact.exponent")

    @property
    def contact_damping_si(self) -> float:
        """IMPACT maximum damping C_max, N s/m."""
        return self._v("contact.damping_n_s_per_mm") * 1e3

    @property
    def penetration_m(self) -> float:
        """Penetration at which the IMPACT damping reaches C_max, m."""
        return self._v("contact.penetration_mm") * 1e-3

    @property
    def rated_load_n(self) -> float:
        return self._v("screw.rated_load_n")

    @property
    def torque_limit(self) -> float:
        """Motor torque limit, N m."""
        return self._v("drive.torque_limit_n_m")

    @property
    def current_loop_time_constant_s(self) -> float:
        """First-order current (torque) loop time constant 1 / (2 pi f_c), s."""
        return 1.0 / (2.0 * math.pi * self._v("drive.current_loop_bandwidth_hz"))

    @property
    def command_delay_samples(self) -> int:
        """The drive's command delay beyond the controller's one-sample computation delay,
        samples (``drive.command_delay_samples``; see
        :data:`prsa_ctrl.plant.schema.COMMAND_DELAY_KEY`)."""
        return int(self.values.get("drive.command_delay_samples", 0))

    @property
    def sample_time_s(self) -> float:
        return self._v("sensor.sample_time_s")

    @property
    def speed_filter_s(self) -> float:
        return self._v("sensor.speed_filter_time_constant_s")

    @property
    def encoder_counts(self) -> int:
        return int(self._v("sensor.encoder_counts_per_rev"))

    def normal_force_factor(self) -> tuple[float, float]:
        """Total normal thread force per newton of axial force, (nut side, screw side).

        Each engaged thread flank carries ``F_a / (N_R z cos(beta) cos(lambda))``; summed over
        all ``N_R z`` contacts this is ``F_a / (cos(beta) cos(lambda))``.
        """
        cb = math.cos(self.flank_angle_rad)
        return 1.0 / (cb * math.cos(self.helix_nut_rad)), 1.0 / (cb * math.cos(self.helix_screw_rad))

    @property
    def slip_arm_m(self) -> float:
        """Effective sliding arm of the thread contacts, m per rad of nut rotation.

        Chosen so that Coulomb friction with the dynamic coefficient on the thread normal forces
        gives the plant's forward efficiency at constant speed:
        ``eta = F L/(2 pi) / (F L/(2 pi) + k mu_d F (f_N + f_S))``.
        """
        eta = self._v("friction.efficiency")
        mu = self._v("friction.dynamic")
        try:
            lossless = bool(eta >= 1.0 or mu == 0.0)
        except RuntimeError:  # CasADi symbols (prsa_ctrl.plant.model.parametric_family): the formula, 0 at eta = 1
            lossless = False
        if lossless:
            return 0.0
        f_n, f_s = self.normal_force_factor()
        return self.lead_per_rad * (1.0 / eta - 1.0) / (mu * (f_n + f_s))

    @property
    def cage_inertia_kg_m2(self) -> float:
        """Rotational inertia about the screw axis seen by the cage, kg m^2.

        The cage itself, the rollers' orbit (point masses on the orbit radius
        ``(d_S + d_R)/2``) and the rollers' absolute spin ``w_P (d_S + d_R)/d_R`` (solid
        cylinders of diameter ``d_R``).
        """
        d_s, d_r = self.d_screw_m, self.d_roller_m
        m_r = self._v("roller.mass_kg")
        j_spin = 0.5 * m_r * (0.5 * d_r) ** 2
        r_orbit = 0.5 * (d_s + d_r)
        return self._v("cage.inertia_kg_m2") + self.n_rollers * (
            m_r * r_orbit**2 + j_spin * ((d_s + d_r) / d_r) ** 2
        )

    @property
    def roller_assembly_mass_kg(self) -> float:
        """Axially moving mass of the cage with its rollers, kg."""
        return self._v("cage.mass_kg") + self.n_rollers * self._v("roller.mass_kg")

    @property
    def reflected_inertia_kg_m2(self) -> float:
        """Total inertia seen at the motor through the rigid kinematics, kg m^2.

        Inverted roller screw: ``J_nut + J_cage (w_P/w_N)^2 + (m_screw + m_rollers) (L/2 pi)^2``
        (the roller assembly travels axially with the screw, see :mod:`prsa_ctrl.plant.model`).
        Screw-driven: ``J_motor + J_screw + m_moving (L/2 pi)^2`` (the rollers' or balls' own
        inertia is neglected: grams on a small radius). Linear axis: its mass (load
        coordinates, 1 m per rad).

        Examples
        --------
        >>> round(load_plant().reflected_inertia_kg_m2 * 1e4, 3)  # kg cm^2
        2.019
        """
        v = self.values
        if self.screw_driven:
            return (v["axis.motor_inertia_kg_m2"] + v["axis.screw_inertia_kg_m2"]
                    + v["axis.moving_mass_kg"] * self.lead_per_rad**2)
        if self.mechanism == "linear-axis":
            return v["axis.mass_kg"]
        return (self._v("nut.inertia_kg_m2") + self.cage_inertia_kg_m2 * self.cage_ratio**2
                + (self._v("screw.mass_kg") + self.roller_assembly_mass_kg) * self.lead_per_rad**2)

    # --- screw-driven axes: compliance along the stroke ------------------------------------------
    def shaft_stiffness_n_per_m(self, stroke_position_mm=None):
        """Axial stiffness of the screw shaft between the fixed bearing(s) and the nut, N/m.

        ``k = E A / x`` for a fixed-free mounting (only the length ``x`` from the fixed bearing to
        the nut carries the load), ``k = E A L / (x (L - x))`` for fixed-fixed (both lengths in
        parallel: ``E A / x + E A / (L - x)``), with ``A = pi d_r^2 / 4`` the root section, ``L``
        the bearing span and ``x`` the stroke position (default: the plant's
        ``axis.stroke_position_mm``). Works on numbers and on CasADi symbols.
        """
        v = self.values
        x = (v["axis.stroke_position_mm"] if stroke_position_mm is None else stroke_position_mm) * 1e-3
        span = v["axis.bearing_span_mm"] * 1e-3
        ea = v["screw.youngs_modulus_gpa"] * 1e9 * math.pi / 4.0 * (v["screw.root_diameter_mm"] * 1e-3) ** 2
        if v["axis.fixed_ends"] == 2:
            return ea * span / (x * (span - x))
        return ea / x

    @property
    def screw_axial_mass_kg(self) -> float:
        """Axially moving mass of the screw shaft, kg: a steel cylinder of the root diameter over
        the bearing span (the whole shaft moves when its support bearing deflects; lumped into
        one body, see :func:`prsa_ctrl.plant.model.plant_model`)."""
        v = self.values
        return _STEEL_KG_M3 * math.pi / 4.0 * (v["screw.root_diameter_mm"] * 1e-3) ** 2 * v["axis.bearing_span_mm"] * 1e-3

    def axial_stiffness_n_per_m(self, stroke_position_mm=None):
        """Axial stiffness between the motor-side helix and the carriage, N/m: the screw shaft
        (:meth:`shaft_stiffness_n_per_m`), the nut and the support bearing(s) in series
        (``1/k = 1/k_shaft + 1/k_nut + 1/k_bearing``; the catalogue formula of THK and HIWIN
        without the mounting-bracket term). For fixed-fixed the bearing value is that of the
        pair of supports together."""
        v = self.values
        k_nut = v["axis.nut_stiffness_n_per_um"] * 1e6
        k_brg = v["axis.bearing_stiffness_n_per_um"] * 1e6
        return 1.0 / (1.0 / self.shaft_stiffness_n_per_m(stroke_position_mm) + 1.0 / k_nut + 1.0 / k_brg)

    def axial_mode_hz(self, stroke_position_mm=None) -> float:
        """Undamped frequency of the axial mode of a screw-driven axis, Hz: the two-mass system
        of the rotating inertia ``J = J_motor + J_screw`` and the moving mass ``m`` coupled by
        the axial stiffness ``k`` through the lead ``a = L / 2 pi``:
        ``w^2 = k (1/m + a^2/J)``."""
        if not self.screw_driven:
            raise ValueError(f"axial_mode_hz: mechanism = {quote(self.mechanism)}; expected one of {', '.join(SCREW_DRIVEN)}")
        v = self.values
        j = v["axis.motor_inertia_kg_m2"] + v["axis.screw_inertia_kg_m2"]
        k = self.axial_stiffness_n_per_m(stroke_position_mm)
        return math.sqrt(k * (1.0 / v["axis.moving_mass_kg"] + self.lead_per_rad**2 / j)) / (2.0 * math.pi)

    @property
    def backdrive_efficiency(self) -> float:
        """Efficiency when the load drives the motor (back-driving), ``2 - 1/eta``.

        The model's thread loss torque does not depend on the direction of power flow (it is
        ``(1/eta - 1) a |F|`` at speed), so the power reaching the motor is
        ``F v - (1/eta - 1) F v``. For a ball screw this matches the catalogue pair
        ``eta = (1 - mu tan b)/(1 + mu/tan b)``, ``eta' = (1 - mu/tan b)/(1 + mu tan b)`` to
        first order in ``mu`` (checked in the tests); below ``eta = 0.5`` the screw self-locks
        (``eta' <= 0``).
        """
        return 2.0 - 1.0 / self._v("friction.efficiency")

    # --- kinematics ---------------------------------------------------------------------------
    def kinematics(self, omega_nut: ArrayLike) -> Kinematics:
        """Rigid-body kinematics for motor speed(s) ``omega_nut`` (rad/s): the nut of the
        inverted roller screw, the screw of a screw-driven axis (``v_screw`` is then the nut's
        and carriage's speed), for a linear axis the load speed in m/s (1 m per rad).

        Examples
        --------
        >>> k = load_plant().kinematics(31.4159)
        >>> round(float(k.omega_cage), 2), round(float(k.v_screw) * 1e3, 2)
        (19.06, 10.0)
        """
        w = np.asarray(omega_nut, dtype=float)
        w_p = w * self.cage_ratio
        rel, ab = self.roller_spin_ratios
        return Kinematics(
            omega_nut=w,
            omega_cage=w_p,
            omega_roller_rel=w_p * rel,
            omega_roller_abs=w_p * ab,
            v_screw=w * self.lead_m / (2.0 * math.pi),
        )

    # --- geometry -----------------------------------------------------------------------------
    def _check_geometry(self) -> GeometryReport:
        v, o = self.values, self.origin
        d_s, d_n, d_r = self.d_screw_m, self.d_nut_m, self.d_roller_m
        if self.mechanism != "inverted-roller-screw":
            return self._generic_geometry()
        if d_n <= d_s:
            raise PlantFileError(
                f"{o}: nut.pitch_diameter_mm = {v['nut.pitch_diameter_mm']} must exceed "
                f"screw.pitch_diameter_mm = {v['screw.pitch_diameter_mm']} (rollers sit between them)"
            )
        closure = d_n - (d_s + 2 * d_r)
        if abs(closure) > 0.25 * d_r:
            raise PlantFileError(
                f"{o}: roller.pitch_diameter_mm = {v['roller.pitch_diameter_mm']} cannot fit: "
                f"d_N - (d_S + 2 d_R) = {closure * 1e3:.3f} mm (expected within 25 % of d_R)"
            )
        if self.n_rollers * d_r >= math.pi * (d_s + d_r):
            raise PlantFileError(
                f"{o}: roller.count = {self.n_rollers} rollers of {d_r * 1e3:g} mm do not fit on "
                f"the orbit circle of {math.pi * (d_s + d_r) * 1e3:.1f} mm circumference"
            )
        if not 0 < v["thread.flank_angle_deg"] < 90:
            raise PlantFileError(f"{o}: thread.flank_angle_deg = {v['thread.flank_angle_deg']}; expected 0 < beta < 90")
        if v["contact.exponent"] < 1.0:
            raise PlantFileError(
                f"{o}: contact.exponent = {v['contact.exponent']}; expected >= 1 "
                "(below 1 the contact Jacobian is infinite at first touch)"
            )
        if v["friction.static"] < v["friction.dynamic"]:
            raise PlantFileError(
                f"{o}: friction.static = {v['friction.static']} is below friction.dynamic = "
                f"{v['friction.dynamic']}; expected static >= dynamic"
            )
        pitches = {
            part: v[f"{part}.lead_mm"] / v[f"{part}.starts"] for part in ("screw", "nut", "roller")
        }
        p_ref = pitches["roller"]
        for part, p in pitches.items():
            if abs(p - p_ref) > 1e-9 * p_ref:
                raise PlantFileError(
                    f"{o}: {part}.lead_mm / {part}.starts = {p:g} mm pitch does not mesh with the "
                    f"roller pitch {p_ref:g} mm; expected equal thread pitches"
                )
        if abs(v["screw.lead_mm"] - v["nut.lead_mm"]) > 1e-9 * v["screw.lead_mm"]:
            raise PlantFileError(
                f"{o}: nut.lead_mm = {v['nut.lead_mm']} differs from screw.lead_mm = "
                f"{v['screw.lead_mm']}; expected equal leads (same starts and pitch)"
            )
        n_s = v["screw.starts"]
        helix_r = math.atan(v["roller.lead_mm"] / (math.pi * v["roller.pitch_diameter_mm"]))
        report = GeometryReport(
            closure_residual_m=closure,
            screw_match_residual_m=d_s - n_s * d_r,
            nut_match_residual_m=d_n - (n_s + 2) * d_r,
            helix_screw_rad=self.helix_screw_rad,
            helix_nut_rad=self.helix_nut_rad,
            helix_roller_rad=helix_r,
            helix_mismatch_rad=self.helix_screw_rad - helix_r,
            pitch_m=p_ref * 1e-3,
            messages=(),
        )
        msgs = []
        tol = 1e-3 * d_r
        if abs(report.closure_residual_m) > tol:
            msgs.append(
                f"geometry does not close: d_N = {d_n * 1e3:g} mm but d_S + 2 d_R = "
                f"{(d_s + 2 * d_r) * 1e3:g} mm (residual {closure * 1e3:+.3f} mm)"
            )
        if abs(report.screw_match_residual_m) > tol:
            msgs.append(
                f"matching rule d_S = n_S d_R not met: d_S = {d_s * 1e3:g} mm, "
                f"n_S d_R = {n_s * d_r * 1e3:g} mm (residual {report.screw_match_residual_m * 1e3:+.3f} mm)"
            )
        if msgs:
            warnings.warn(f"{o}: " + "; ".join(msgs), GeometryWarning, stacklevel=4)
        object.__setattr__(report, "messages", tuple(msgs))
        return report


    def _generic_geometry(self) -> GeometryReport:
        """The checks every mechanism shares (friction and contact laws); the thread-matching
        report of the inverted design does not apply (zero residuals, no messages)."""
        v, o = self.values, self.origin
        if v["contact.exponent"] < 1.0:
            raise PlantFileError(f"{o}: contact.exponent = {v['contact.exponent']}; expected >= 1 "
                                 "(below 1 the contact Jacobian is infinite at first touch)")
        if v["friction.static"] < v["friction.dynamic"]:
            raise PlantFileError(f"{o}: friction.static = {v['friction.static']} is below friction.dynamic = "
                                 f"{v['friction.dynamic']}; expected static >= dynamic")
        helix = self.helix_screw_rad
        return GeometryReport(0.0, 0.0, 0.0, helix, helix, helix, 0.0,
                              v["screw.lead_mm"] / v["screw.starts"] * 1e-3, ())


def plant_file_path(name_or_path: str | Path | None = None) -> Path | Any:
    """The plant file a name or path refers to, as :func:`load_plant` resolves it.

    Parameters
    ----------
    name_or_path : str or Path, optional
        A built-in plant name (``plants/*.toml``, default ``paper-iprsm``) or a path to a .toml file.

    Returns
    -------
    Path or importlib.resources.abc.Traversable
        Readable with ``.read_text()``: the installed package data, or the repository's
        ``plants/`` folder when a source checkout shadows the installed package.

    Examples
    --------
    >>> plant_file_path("paper-iprsm").name
    'paper-iprsm.toml'
    """
    return _resolve(name_or_path)


def _resolve(name_or_path: str | Path | None) -> Path | Any:
    if name_or_path is None:
        name_or_path = DEFAULT_PLANT
    text = str(name_or_path)
    looks_like_path = isinstance(name_or_path, Path) or text.endswith(".toml") or "/" in text or "\\" in text
    if looks_like_path:
        path = Path(text).expanduser()
        if not path.is_file():
            raise PlantFileError(f"plant file {quote(text)} not found; expected a readable .toml file")
        return path
    res = builtin_root("prsa_ctrl.plants", "plants") / f"{text}.toml"
    if not res.is_file():
        raise PlantFileError(
            f"unknown plant {quote(text)}; expected a built-in name ({', '.join(builtin_plants())}) "
            "or a path to a .toml file"
        )
    return res


def load_plant(name_or_path: str | Path | None = None) -> Plant:
    """Load and validate a plant definition.

    Parameters
    ----------
    name_or_path : str or Path, optional
        A built-in plant name (see :func:`builtin_plants`; default ``"paper-iprsm"``) or a path
        to a plant ``.toml`` file.

    Raises
    ------
    PlantFileError
        If the file is missing, unreadable, larger than :data:`PLANT_FILE_BYTES_MAX` or invalid;
        the message names the file and key.
    """
    src = _resolve(name_or_path)
    builtin = name_or_path is None or not (isinstance(name_or_path, Path) or str(name_or_path).endswith(".toml")
                                           or "/" in str(name_or_path) or "\\" in str(name_or_path))
    origin = f"{src.name} (built-in)" if builtin else str(src)
    try:
        size = src.stat().st_size if isinstance(src, Path) else 0
        if size > PLANT_FILE_BYTES_MAX:
            raise PlantFileError(f"{origin}: {size} bytes; expected a plant file of at most {PLANT_FILE_BYTES_MAX} bytes")
        text = src.read_text(encoding="utf-8-sig")  # -sig: a byte-order mark is dropped
    except (OSError, UnicodeDecodeError) as exc:
        raise PlantFileError(f"{origin}: cannot be read ({exc}); expected a UTF-8 TOML file") from None
    doc = read_toml(text, origin, PlantFileError)
    return Plant.from_dict(doc, origin=origin)
