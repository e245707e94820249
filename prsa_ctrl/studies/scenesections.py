"""A scene's study sections, typed and frozen: ``[spec]`` (:class:`Spec`), ``[robust]``
(:class:`Robust`) and ``[uncertainty]`` (:class:`~prsa_ctrl.plant.uncertainty.Uncertainty`),
parsed once from the scene file (:meth:`Sections.parse`, validated by
:func:`parse_scene_sections`) and read by attribute.

The robust tuning, the Monte-Carlo and design-to-spec studies and the CLI read these objects
(``scene.sections.robust.setpoints_rpm``); the plant layer receives only the
:class:`~prsa_ctrl.plant.uncertainty.Uncertainty` part (:attr:`Sections.plant_overrides`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping

from ..errors import SceneError
from ..plant.uncertainty import Uncertainty, parse_entries
from ..results import FrozenDict
from ..textsafe import quote

__all__ = ["Spec", "Robust", "Sections", "Uncertainty", "parse_scene_sections", "SPEC_BOUNDS"]


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
    ``no_saturation = true``; ``yield = 0.95`` (optional) is the target probability of meeting
    them, returned apart as ``{"spec_yield": {"yield": 0.95}}``. ``[robust]``: ``aggregate`` ("worst"/"mean" over scenario models),
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
            raise SceneError(f"{origin}: [spec] = {quote(table)}; expected a table of bounds")
        spec: dict[str, Any] = {}
        for k, v in table.items():
            if k == "yield":  # the target probability of meeting the bounds (not a bound itself)
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < 1:
                    raise SceneError(f"{origin}: spec.yield = {quote(v)}; expected a target probability in (0, 1), "
                                     "e.g. 0.95")
                out["spec_yield"] = {"yield": float(v)}
                continue
            if k == "no_saturation":
                if not isinstance(v, bool):
                    raise SceneError(f"{origin}: spec.no_saturation = {quote(v)}; expected true or false")
                spec[k] = v
                continue
            if k not in SPEC_BOUNDS:
                raise SceneError(f"{origin}: unknown key spec.{k}; expected one of "
                                 f"{', '.join(f'spec.{b}' for b in (*SPEC_BOUNDS, 'no_saturation', 'yield'))}")
            if not _pos(v):
                raise SceneError(f"{origin}: spec.{k} = {quote(v)}; expected a positive upper bound ({SPEC_BOUNDS[k]})")
            if k in ("ms", "mt") and not v > 1.0 - (k == "mt") * 0.5:
                raise SceneError(f"{origin}: spec.{k} = {quote(v)}; expected a bound > {1.0 if k == 'ms' else 0.5:g}")
            spec[k] = float(v)
        if "spec_yield" in out and not spec:  # (was taken for a scene without [spec] by --design-to-spec)
            raise SceneError(f"{origin}: spec.yield = {quote(table['yield'])} and no bound in [spec]; expected the "
                             "bounds the yield counts (e.g. spec.peak_drop_rad_s = 12.0)")
        out["spec"] = spec
    if "robust" in doc:
        table = doc["robust"]
        if not isinstance(table, Mapping):
            raise SceneError(f"{origin}: [robust] = {quote(table)}; expected a table")
        rob: dict[str, Any] = {}
        for k, v in table.items():
            if k not in _ROBUST_KEYS:
                raise SceneError(f"{origin}: unknown key robust.{k}; expected one of "
                                 f"{', '.join(f'robust.{r}' for r in _ROBUST_KEYS)}")
            typ, check, expected = _ROBUST_KEYS[k]
            if not isinstance(v, typ) or (typ is int and isinstance(v, bool)) or not check(v):
                raise SceneError(f"{origin}: robust.{k} = {quote(v)}; expected {expected}")
            rob[k] = [float(x) for x in v] if typ is list else v
        out["robust"] = rob
    if "uncertainty" in doc:
        out["uncertainty"] = parse_entries(doc["uncertainty"], origin, SceneError)
    return out


@dataclass(frozen=True)
class Spec:
    """A scene's ``[spec]``: the upper bounds a design must meet (units in
    :data:`SPEC_BOUNDS`), ``no_saturation`` and the target yield.

    Attributes
    ----------
    bounds : Mapping
        ``name -> bound`` in the file's order, ``no_saturation`` (bool) included when given.
    yield_target : float or None
        ``spec.yield``: the probability of meeting the bounds to design to, in (0, 1).
    """

    bounds: Mapping[str, Any] = field(default_factory=dict, compare=False, hash=False)
    yield_target: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "bounds", FrozenDict(self.bounds))

    def as_dict(self) -> dict[str, Any]:
        """The bounds as a plain dict (the report's and the studies' ``spec``)."""
        return dict(self.bounds)


@dataclass(frozen=True)
class Robust:
    """A scene's ``[robust]`` table, typed (defaults: what the studies use when a key is absent).

    Attributes
    ----------
    given : tuple of str
        The keys the file wrote, in its order (the rest are the defaults below).
    aggregate : {"worst", "mean"}
        Over the scenarios.
    setpoints_rpm, final_loads_n : tuple of float
        Operating points of the robust study, rpm and N (empty: the scene's own).
    vertices : bool
    samples, seed, monte_carlo : int
    max_scenarios : int or None
        None: the study's default.
    plant_uncertainty : bool
        False: the plant file's ``[uncertainty]`` is left out.
    """

    given: tuple[str, ...] = ()
    aggregate: str = "worst"
    setpoints_rpm: tuple[float, ...] = ()
    final_loads_n: tuple[float, ...] = ()
    vertices: bool = True
    samples: int = 0
    seed: int = 0
    monte_carlo: int = 0
    max_scenarios: int | None = None
    plant_uncertainty: bool = True

    def as_dict(self) -> dict[str, Any]:
        """The keys the file gave, as a plain dict (lists for the sequences)."""
        return {k: (list(getattr(self, k)) if k in ("setpoints_rpm", "final_loads_n") else getattr(self, k))
                for k in self.given}


@dataclass(frozen=True)
class Sections:
    """The study sections of one scene (each None when the file has not got it).

    Attributes
    ----------
    spec : Spec or None
    robust : Robust or None
    uncertainty : Uncertainty or None
        The scene's ``[uncertainty]`` entries as written.
    origin : str
    """

    spec: Spec | None = None
    robust: Robust | None = None
    uncertainty: Uncertainty | None = None
    origin: str = "<scene>"

    @classmethod
    def parse(cls, doc: Mapping[str, Any], origin: str) -> "Sections":
        """Validate and type a scene document's ``[spec]``, ``[robust]`` and ``[uncertainty]``.

        Raises
        ------
        SceneError
            Naming the file, the key and what was expected.
        """
        return cls.from_dict(parse_scene_sections(doc, origin), origin)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | "Sections" | None, origin: str = "<scene>") -> "Sections":
        """From the validated dict of :func:`parse_scene_sections`
        (``{"spec", "spec_yield", "robust", "uncertainty"}``); a :class:`Sections` is returned as is."""
        if isinstance(d, Sections):
            return d
        d = d or {}
        spec = None
        if "spec" in d:
            spec = Spec(d["spec"], (d.get("spec_yield") or {}).get("yield"))
        robust = None
        if "robust" in d:
            rob = d["robust"]
            robust = Robust(given=tuple(rob), **{k: (tuple(v) if isinstance(v, list) else v) for k, v in rob.items()})
        unc = Uncertainty(d["uncertainty"], origin) if "uncertainty" in d else None
        return cls(spec, robust, unc, origin)

    def __bool__(self) -> bool:
        return self.spec is not None or self.robust is not None or self.uncertainty is not None

    @property
    def plant_overrides(self) -> Uncertainty:
        """What :func:`~prsa_ctrl.plant.uncertainty.uncertainty_model` takes: the scene's entries
        and its ``[robust] plant_uncertainty`` switch."""
        return Uncertainty(dict(self.uncertainty.entries) if self.uncertainty is not None else {}, self.origin,
                           self.robust.plant_uncertainty if self.robust is not None else True)

    @property
    def spec_bounds(self) -> dict[str, Any]:
        """``[spec]``'s bounds as a dict (empty without a ``[spec]``)."""
        return self.spec.as_dict() if self.spec is not None else {}

    @property
    def yield_target(self) -> float | None:
        """``spec.yield`` (None when not given)."""
        return self.spec.yield_target if self.spec is not None else None

    def as_dict(self) -> dict[str, Any]:
        """The validated dict shape of
        :func:`parse_scene_sections` (what ``Scene.robust`` was)."""
        out: dict[str, Any] = {}
        if self.spec is not None:
            if self.spec.yield_target is not None:
                out["spec_yield"] = {"yield": self.spec.yield_target}
            out["spec"] = self.spec.as_dict()
        if self.robust is not None:
            out["robust"] = self.robust.as_dict()
        if self.uncertainty is not None:
            out["uncertainty"] = dict(self.uncertainty.entries)
        return out
