"""A scene's study sections, typed and frozen: ``[spec]`` (:class:`Spec`), ``[robust]``
(:class:`Robust`) and ``[uncertainty]`` (:class:`~prsa_ctrl.plant.uncertainty.Uncertainty`),
parsed once from the scene file (:meth:`Sections.parse`, validated by
:func:`~prsa_ctrl.plant.uncertainty.parse_scene_sections`) and read by attribute.

The robust tuning, the Monte-Carlo and design-to-spec studies and the CLI read these objects
(``scene.sections.robust.setpoints_rpm``); the plant layer receives only the
:class:`~prsa_ctrl.plant.uncertainty.Uncertainty` part (:attr:`Sections.plant_overrides`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Mapping

from ..plant.uncertainty import Uncertainty, parse_scene_sections

__all__ = ["Spec", "Robust", "Sections", "Uncertainty"]


@dataclass(frozen=True)
class Spec:
    """A scene's ``[spec]``: the upper bounds a design must meet (units in
    :data:`prsa_ctrl.plant.uncertainty.SPEC_BOUNDS`), ``no_saturation`` and the target yield.

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
        object.__setattr__(self, "bounds", MappingProxyType(dict(self.bounds)))

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
        """From the validated dict of :func:`~prsa_ctrl.plant.uncertainty.parse_scene_sections`
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
        :func:`~prsa_ctrl.plant.uncertainty.parse_scene_sections` (what ``Scene.robust`` was)."""
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
