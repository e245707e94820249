"""What is uncertain about a plant, written down: the ``[uncertainty]`` section of plant files and
scenes, its validation, its vertices and its seeded samples.

A plant file (or a scene, for what is attached to the actuator in that scene) may give any
continuous plant parameter a distribution with its source::

    [uncertainty]
    "nut.inertia_kg_m2" = { dist = "uniform", relative = 0.5, source = "estimate: attached load masses" }
    "drive.current_loop_bandwidth_hz" = { dist = "loguniform", low = 500.0, high = 1500.0, source = "..." }
    "friction.efficiency" = { dist = "normal", sigma = 0.03, truncate = 2.0, source = "..." }

Distributions (values in the plant file's units, around the nominal value ``v`` of the file):

``uniform``
    ``relative = r`` (``v (1 - r)`` to ``v (1 + r)``, ``0 <= r < 1``) or ``low``/``high``.
``normal``
    mean ``v``, ``sigma`` (or ``relative_sigma``), truncated at ``truncate`` sigmas (0 < t <= 6).
``loguniform``
    ``low``/``high`` (both > 0).

The nominal value must lie inside the support, and every value of the support must be a valid
plant (the key's kind - positive, fraction ... - and the plant's cross-checks, e.g. static >=
dynamic friction, thread meshing), checked at the two ends of each key's support. Integer keys
(thread starts, roller count ...) cannot be uncertain.

The ``[tolerance]`` roller errors join the same mechanism: their standard deviations are plant
keys like any other (``"tolerance.roller_position_std_um"`` may carry a distribution), and each
Monte-Carlo sample draws its own per-roller errors from its own seed (multi-roller fidelity).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from ..errors import GeometryWarning, PlantFileError, SceneError
from .schema import KIND

__all__ = ["Uncertain", "UncertaintyModel", "DISTRIBUTIONS", "parse_entries", "uncertainty_model",
           "plant_uncertainty", "check_plant_uncertainty"]

#: Distribution name -> (required keys, optional keys) besides ``dist`` and ``source``.
DISTRIBUTIONS: Mapping[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "uniform": ((), ("relative", "low", "high")),
    "normal": (("truncate",), ("sigma", "relative_sigma")),
    "loguniform": (("low", "high"), ()),
}


@dataclass(frozen=True)
class Uncertain:
    """One uncertain plant parameter (file units, key ``section.key``).

    ``low``/``high`` are the support; for ``normal`` the mean is the nominal value and
    ``sigma`` its standard deviation.
    """

    key: str
    dist: str
    low: float
    high: float
    nominal: float
    sigma: float
    source: str

    def ppf(self, u: float | np.ndarray) -> float | np.ndarray:
        """Value at cumulative probability ``u`` in [0, 1] (inverse CDF)."""
        u = np.asarray(u, float)
        if self.dist == "uniform":
            return self.low + u * (self.high - self.low)
        if self.dist == "loguniform":
            return np.exp(math.log(self.low) + u * (math.log(self.high) - math.log(self.low)))
        from scipy.special import ndtr, ndtri

        a = ndtr((self.low - self.nominal) / self.sigma)
        b = ndtr((self.high - self.nominal) / self.sigma)
        return np.clip(self.nominal + self.sigma * ndtri(a + u * (b - a)), self.low, self.high)

    def as_dict(self) -> dict[str, Any]:
        return {"dist": self.dist, "low": self.low, "high": self.high, "nominal": self.nominal,
                "sigma": self.sigma if self.dist == "normal" else None, "source": self.source}


def _number(origin: str, where: str, value: Any, err: type[ValueError]) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise err(f"{origin}: {where} = {value!r}; expected a finite number")
    return float(value)


def _flatten(table: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"nut": {"inertia_kg_m2": {...}}}`` (unquoted dotted TOML keys) -> ``{"nut.inertia_kg_m2": {...}}``."""
    out: dict[str, Any] = {}
    for k, v in table.items():
        full = f"{prefix}{k}"
        if isinstance(v, Mapping) and "dist" not in v and all(isinstance(x, Mapping) for x in v.values()) and v:
            out.update(_flatten(v, full + "."))
        else:
            out[full] = v
    return out


def parse_entries(table: Any, origin: str, err: type[ValueError] = PlantFileError) -> dict[str, dict[str, Any]]:
    """Structural check of an ``[uncertainty]`` table (no plant needed): known distribution,
    the parameters it needs, positive widths, a source. Returns ``key -> entry`` (flattened).

    Raises
    ------
    PlantFileError or SceneError (``err``)
        Naming the file (``origin``), the key and what was expected.
    """
    if not isinstance(table, Mapping):
        raise err(f"{origin}: [uncertainty] = {table!r}; expected a table of 'section.key' = {{ dist = ... }}")
    out: dict[str, dict[str, Any]] = {}
    for key, entry in _flatten(table).items():
        where = f"uncertainty.{key!r}"
        if key not in KIND:
            raise err(f"{origin}: unknown key {where}; expected a plant parameter 'section.key' "
                      f"(e.g. 'nut.inertia_kg_m2')")
        if KIND[key] == "positive integer":
            raise err(f"{origin}: {where}: {key} is an integer parameter; expected a continuous one "
                      "(integer keys cannot be uncertain)")
        if not isinstance(entry, Mapping):
            raise err(f"{origin}: {where} = {entry!r}; expected {{ dist = \"uniform\"|\"normal\"|\"loguniform\", "
                      "..., source = \"...\" }")
        dist = entry.get("dist")
        if dist not in DISTRIBUTIONS:
            raise err(f"{origin}: {where}.dist = {dist!r}; expected one of {', '.join(DISTRIBUTIONS)}")
        required, optional = DISTRIBUTIONS[dist]
        extra = sorted(set(entry) - {"dist", "source", *required, *optional})
        if extra:
            raise err(f"{origin}: {where}: unknown field {extra[0]!r} for dist = {dist!r}; expected "
                      f"{', '.join(['source', *required, *optional])}")
        src = entry.get("source")
        if not isinstance(src, str) or not src.strip():
            raise err(f"{origin}: {where}.source = {src!r}; expected a non-empty string "
                      "(paper, \"assumption: why\", \"estimate: why\", \"fit: file\")")
        for r in required:
            if r not in entry:
                raise err(f"{origin}: {where}: missing {r!r}; dist = {dist!r} needs {', '.join(required)}")
        nums = {k: _number(origin, f"{where}.{k}", v, err) for k, v in entry.items() if k not in ("dist", "source")}
        if dist == "uniform":
            if ("relative" in nums) == ("low" in nums or "high" in nums):
                raise err(f"{origin}: {where}: expected either relative = r or low and high for dist = 'uniform'")
            if "relative" in nums and not 0 <= nums["relative"] < 1:
                raise err(f"{origin}: {where}.relative = {entry['relative']!r}; expected a relative half-width in [0, 1)")
            if "relative" not in nums and not ("low" in nums and "high" in nums):
                raise err(f"{origin}: {where}: expected both low and high for dist = 'uniform'")
        if dist == "normal":
            if ("sigma" in nums) == ("relative_sigma" in nums):
                raise err(f"{origin}: {where}: expected exactly one of sigma, relative_sigma for dist = 'normal'")
            s_key = "sigma" if "sigma" in nums else "relative_sigma"
            if nums[s_key] <= 0:
                raise err(f"{origin}: {where}.{s_key} = {entry[s_key]!r}; expected a positive standard deviation")
            if not 0 < nums["truncate"] <= 6:
                raise err(f"{origin}: {where}.truncate = {entry['truncate']!r}; expected a bound in sigmas in (0, 6]")
        if dist == "loguniform" and not nums["low"] > 0:
            raise err(f"{origin}: {where}.low = {entry['low']!r}; expected a positive value (loguniform)")
        if "low" in nums and "high" in nums and not nums["low"] < nums["high"]:
            raise err(f"{origin}: {where}: low = {entry['low']!r} >= high = {entry['high']!r}; expected low < high")
        out[key] = {"dist": dist, "source": src.strip(), **nums}
    return out


def _resolve(key: str, entry: Mapping[str, Any], nominal: float, origin: str, err) -> Uncertain:
    where = f"uncertainty.{key!r}"
    dist = entry["dist"]
    sigma = 0.0
    if dist == "uniform" and "relative" in entry:
        lo, hi = nominal * (1 - entry["relative"]), nominal * (1 + entry["relative"])
    elif dist == "normal":
        sigma = entry["sigma"] if "sigma" in entry else entry["relative_sigma"] * abs(nominal)
        if sigma <= 0:
            raise err(f"{origin}: {where}: relative_sigma of a zero nominal value; expected sigma in file units")
        lo, hi = nominal - entry["truncate"] * sigma, nominal + entry["truncate"] * sigma
    else:
        lo, hi = entry["low"], entry["high"]
    if not lo <= nominal <= hi:
        raise err(f"{origin}: {where}: support [{lo:g}, {hi:g}] does not contain the nominal value {nominal:g}; "
                  "expected a range around the plant file's value")
    kind = KIND[key]
    ok = {"positive": lo > 0, "non-negative": lo >= 0, "fraction in (0, 1]": lo > 0 and hi <= 1}.get(kind, True)
    if not ok:
        raise err(f"{origin}: {where}: {dist} reaches [{lo:g}, {hi:g}], outside the physical range of {key} "
                  f"({kind}); expected a narrower distribution")
    return Uncertain(key, dist, float(lo), float(hi), float(nominal), float(sigma), entry["source"])


@dataclass(frozen=True)
class UncertaintyModel:
    """The uncertain parameters of one plant (sorted by key, so samples do not depend on the
    order the file lists them in)."""

    entries: tuple[Uncertain, ...]

    @property
    def keys(self) -> tuple[str, ...]:
        return tuple(e.key for e in self.entries)

    def __len__(self) -> int:
        return len(self.entries)

    def sample(self, rng: np.random.Generator) -> dict[str, float]:
        """One draw (file units), consuming ``len(self)`` uniforms from ``rng``."""
        u = rng.random(len(self.entries))
        return {e.key: float(e.ppf(ui)) for e, ui in zip(self.entries, u)}

    def vertices(self) -> list[dict[str, float]]:
        """Corners of the support box (``2**len(self)`` points, first key varying slowest)."""
        out = []
        for bits in range(2 ** len(self.entries)):
            out.append({e.key: (e.high if (bits >> (len(self.entries) - 1 - j)) & 1 else e.low)
                        for j, e in enumerate(self.entries)})
        return out

    def as_dict(self) -> dict[str, Any]:
        return {e.key: e.as_dict() for e in self.entries}


def _build(entries: Mapping[str, Mapping[str, Any]], plant, origin: str, err) -> UncertaintyModel:
    unc = []
    for key in sorted(entries):
        if key not in plant.values:
            raise err(f"{origin}: unknown key uncertainty.{key!r}; the plant {plant.name!r} has no such parameter")
        unc.append(_resolve(key, entries[key], float(plant.values[key]), origin, err))
    model = UncertaintyModel(tuple(unc))
    # Every end of every key's support must be a valid plant (cross-checks such as static >=
    # dynamic friction and thread meshing live in the plant).
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeometryWarning)
        for e in unc:
            for v in (e.low, e.high):
                try:
                    plant.with_params({e.key: v})
                except PlantFileError as exc:
                    raise err(f"{origin}: uncertainty.{e.key!r} = {v:g} (end of its {e.dist} support) makes an "
                              f"invalid plant: {str(exc).split(': ', 1)[-1]}; expected a narrower distribution") from None
        _check_joint(unc, plant, origin, err)
    return model


#: Most uncertain keys whose supports are checked three at a time (the plant's cross-checks
#: tie at most three parameters: static >= dynamic friction, equal leads, diameter closure).
JOINT_CHECK_MAX_KEYS = 16


def _check_joint(unc: Sequence[Uncertain], plant, origin: str, err) -> None:
    """Every corner of the supports of every pair (and, up to ``JOINT_CHECK_MAX_KEYS`` keys,
    every triple) of uncertain keys, the others nominal, is a valid plant; the error names the
    smallest set of keys whose ends clash (e.g. ``friction.static`` 0.26..0.34 with
    ``friction.dynamic`` 0.2..0.3: static 0.26 < dynamic 0.3)."""
    import itertools

    n = len(unc)
    for size in (2, 3):
        if n < size or (size == 3 and n > JOINT_CHECK_MAX_KEYS):
            continue
        for idx in itertools.combinations(range(n), size):
            for ends in itertools.product((0, 1), repeat=size):
                vals = {unc[i].key: (unc[i].low, unc[i].high)[e] for i, e in zip(idx, ends)}
                try:
                    plant.with_params(vals)
                except PlantFileError as exc:
                    which = " with ".join(f"uncertainty.{unc[i].key!r} = {unc[i].low:g}..{unc[i].high:g}" for i in idx)
                    at = ", ".join(f"{k} = {v:g}" for k, v in vals.items())
                    raise err(f"{origin}: {which}: together they reach an invalid plant at {at}: "
                              f"{str(exc).split(': ', 1)[-1]}; expected supports that are valid together "
                              "(narrow one of them)") from None


def check_plant_uncertainty(plant) -> UncertaintyModel:
    """Validate a plant's own ``[uncertainty]`` section against its values (PlantFileError)."""
    entries = parse_entries(getattr(plant, "uncertainty", {}) or {}, plant.origin, PlantFileError)
    return _build(entries, plant, plant.origin, PlantFileError)


def plant_uncertainty(plant) -> UncertaintyModel:
    """The plant's own uncertainty model (empty when the file has no ``[uncertainty]``)."""
    return check_plant_uncertainty(plant)


def uncertainty_model(plant, scene=None, extra: Mapping[str, Any] | None = None) -> UncertaintyModel:
    """Plant uncertainty, overridden/extended by the scene's ``[uncertainty]`` (what the scene
    attaches to the actuator) and by ``extra`` (API callers), key by key. A scene with
    ``[robust] plant_uncertainty = false`` uses its own section alone.

    Raises
    ------
    PlantFileError, SceneError
        Naming the file and the key of the bad entry.
    """
    entries = parse_entries(getattr(plant, "uncertainty", {}) or {}, plant.origin, PlantFileError)
    model = _build(entries, plant, plant.origin, PlantFileError)
    if scene is not None and not (getattr(scene, "robust", None) or {}).get("robust", {}).get("plant_uncertainty", True):
        entries, model = {}, UncertaintyModel(())
    merged = dict(entries)
    origin = "<extra>"
    if scene is not None:
        raw = (getattr(scene, "robust", None) or {}).get("uncertainty", {})
        origin = scene.origin
        s_entries = parse_entries(raw, origin, SceneError)
        merged.update(s_entries)
        if s_entries:
            model = _build(merged, plant, origin, SceneError)
    if extra:
        merged.update(parse_entries(extra, "<extra>", ValueError))
        model = _build(merged, plant, "<extra>", ValueError)
    return model


def apply(plant, values: Mapping[str, float], name: str | None = None):
    """The plant at one point of its uncertainty (``values`` in file units)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeometryWarning)
        return plant.with_params(values, name=name or f"{plant.name}*")


def describe(model: UncertaintyModel) -> list[str]:
    """One line per uncertain parameter (for reports)."""
    return [f"{e.key}: {e.dist} [{e.low:.4g}, {e.high:.4g}] (nominal {e.nominal:.4g}; {e.source})"
            for e in model.entries]


def keys_of(models: Sequence[UncertaintyModel]) -> list[str]:
    return sorted({k for m in models for k in m.keys})


# --- scene sections: [spec], [robust], [uncertainty] ------------------------------------------

#: Spec bounds a scene may state: metric -> what it bounds (all upper bounds, worst over steps).
SPEC_BOUNDS: Mapping[str, str] = {
    "peak_drop_rad_s": "largest speed drop after the step, rad/s",
    "recovery_time_s": "time to re-enter the 5 % band, s",
    "ie": "integral of the error, rad",
    "iae": "integral of |error|, rad",
    "itae": "integral of t |error|, rad s",
    "ise": "integral of error^2, rad^2/s",
    "overshoot_rad_s": "rise above the setpoint after the low point, rad/s",
    "peak_torque_n_m": "largest |motor torque| after the step, N m",
    "steady_state_error_rad_s": "|mean error| over the last 10 % of the record, rad/s",
    "ms": "peak sensitivity of the sample's linearised sampled loop",
    "mt": "peak complementary sensitivity of the sample's linearised sampled loop",
}

#: ``[robust]`` keys -> (type, check, expected).
_ROBUST_KEYS: Mapping[str, tuple[type, Any, str]] = {
    "aggregate": (str, lambda v: v in ("worst", "mean"), "'worst' or 'mean'"),
    "setpoints_rpm": (list, lambda v: 1 <= len(v) <= 16 and all(_pos(x) for x in v), "1 to 16 positive speeds in rpm"),
    "final_loads_n": (list, lambda v: 1 <= len(v) <= 16 and all(_nonneg(x) for x in v), "1 to 16 loads >= 0 N"),
    "vertices": (bool, lambda v: True, "true or false"),
    "samples": (int, lambda v: 0 <= v <= 256, "an integer 0..256 (random scenario models)"),
    "seed": (int, lambda v: 0 <= v < 2**63, "an integer >= 0"),
    "monte_carlo": (int, lambda v: 0 <= v <= 1_000_000, "an integer 0..1000000 (samples)"),
    "max_scenarios": (int, lambda v: 1 <= v <= 256, "an integer 1..256"),
    "plant_uncertainty": (bool, lambda v: True, "true or false (include the plant file's [uncertainty])"),
}


def _pos(x: Any) -> bool:
    return not isinstance(x, bool) and isinstance(x, (int, float)) and math.isfinite(x) and x > 0


def _nonneg(x: Any) -> bool:
    return not isinstance(x, bool) and isinstance(x, (int, float)) and math.isfinite(x) and x >= 0


def parse_scene_sections(doc: Mapping[str, Any], origin: str) -> dict[str, dict[str, Any]]:
    """Validate a scene's ``[spec]``, ``[robust]`` and ``[uncertainty]`` sections.

    ``[spec]``: upper bounds (``SPEC_BOUNDS``), e.g. ``peak_drop_rad_s = 5.0``, and
    ``no_saturation = true``. ``[robust]``: ``aggregate`` ("worst"/"mean" over scenario models),
    the operating range ``setpoints_rpm`` and ``final_loads_n``, ``vertices``, ``samples``,
    ``seed``, ``monte_carlo`` (samples), ``max_scenarios``. ``[uncertainty]``: as in plant files.

    Returns
    -------
    dict
        ``{"spec": {...}, "robust": {...}, "uncertainty": {...}}`` (only the sections present).

    Raises
    ------
    SceneError
        Naming the file, the key and what was expected.

    Examples
    --------
    >>> parse_scene_sections({"spec": {"peak_drop_rad_s": 5}}, "s.toml")["spec"]
    {'peak_drop_rad_s': 5.0}
    """
    out: dict[str, dict[str, Any]] = {}
    if "spec" in doc:
        table = doc["spec"]
        if not isinstance(table, Mapping):
            raise SceneError(f"{origin}: [spec] = {table!r}; expected a table of bounds")
        spec: dict[str, Any] = {}
        for k, v in table.items():
            if k == "no_saturation":
                if not isinstance(v, bool):
                    raise SceneError(f"{origin}: spec.no_saturation = {v!r}; expected true or false")
                spec[k] = v
                continue
            if k not in SPEC_BOUNDS:
                raise SceneError(f"{origin}: unknown key spec.{k}; expected one of "
                                 f"{', '.join(f'spec.{b}' for b in (*SPEC_BOUNDS, 'no_saturation'))}")
            if not _pos(v):
                raise SceneError(f"{origin}: spec.{k} = {v!r}; expected a positive upper bound ({SPEC_BOUNDS[k]})")
            if k in ("ms", "mt") and not v > 1.0 - (k == "mt") * 0.5:
                raise SceneError(f"{origin}: spec.{k} = {v!r}; expected a bound > {1.0 if k == 'ms' else 0.5:g}")
            spec[k] = float(v)
        out["spec"] = spec
    if "robust" in doc:
        table = doc["robust"]
        if not isinstance(table, Mapping):
            raise SceneError(f"{origin}: [robust] = {table!r}; expected a table")
        rob: dict[str, Any] = {}
        for k, v in table.items():
            if k not in _ROBUST_KEYS:
                raise SceneError(f"{origin}: unknown key robust.{k}; expected one of "
                                 f"{', '.join(f'robust.{r}' for r in _ROBUST_KEYS)}")
            typ, check, expected = _ROBUST_KEYS[k]
            if not isinstance(v, typ) or (typ is int and isinstance(v, bool)) or not check(v):
                raise SceneError(f"{origin}: robust.{k} = {v!r}; expected {expected}")
            rob[k] = [float(x) for x in v] if typ is list else v
        out["robust"] = rob
    if "uncertainty" in doc:
        out["uncertainty"] = parse_entries(doc["uncertainty"], origin, SceneError)
    return out
