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

Correlation (a Gaussian copula). The fit of a plant leaves its keys correlated (e.g. the Coulomb
and viscous friction of one direction, about -0.87 on the EMPS record); the same table may say so::

    correlation = { keys = ["friction.coulomb_positive_n", "friction.viscous_positive_n_s_per_m"],
                    matrix = [[1.0, -0.87], [-0.87, 1.0]], source = "fit: DATA_EMPS.mat (covariance)" }

(or an array of such tables, blocks with no key in common). ``correlation`` is a reserved name,
never a plant key (plant keys are ``section.key``). Each key of a block has its own entry in the
same table and appears once; the matrix is square, symmetric (to ``1e-12``), finite, with a unit
diagonal (to ``1e-12``), ``|r| <= 1`` and positive semi-definite: smallest eigenvalue
``>= -PSD_TOLERANCE`` (``1e-9``); a singular matrix (``r = 1``) is fine. ``matrix`` is the
correlation of the keys' *normal scores* ``Phi^-1(F_i(x_i))``: a draw takes the block's uniforms
``u`` (the same ``len(model)`` uniforms an uncorrelated draw takes), ``z = L Phi^-1(u)`` with
``L L' = R`` (a semi-definite Cholesky factor, rows scaled to unit length), and each key's value
``F_i^-1(Phi(z_i))``: every marginal is its entry's distribution, whatever it is. For a fit's
normal entries this is the fit's joint normal (truncated like its marginals). A model without a
correlation draws exactly what it drew before (the same uniforms, the same values). The vertices
of the robust tuner stay the corners of the support box (a correlation does not move them).

Scenes: a scene's ``[uncertainty]`` entry for a key replaces the plant's; a plant correlation
block then keeps only the keys whose entry is still the plant's (the rest of its matrix: a
principal sub-matrix, still valid), and the dropped keys are named in the model's ``notes``
(and in the JSON of a Monte Carlo, per key). A scene (or ``extra``) may give its own block for
its own keys; ``[robust] plant_uncertainty = false`` drops the plant's blocks with its entries.

The ``[tolerance]`` roller errors join the same mechanism: their standard deviations are plant
keys like any other (``"tolerance.roller_position_std_um"`` may carry a distribution), and each
Monte-Carlo sample draws its own per-roller errors from its own seed (multi-roller fidelity).
"""

from __future__ import annotations

import functools
import math
import warnings
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from ..textsafe import quote
from ..errors import GeometryWarning, PlantFileError, SceneError
from ..options import check_number
from .schema import KIND

__all__ = ["Uncertain", "Uncertainty", "UncertaintyModel", "Correlation", "DISTRIBUTIONS", "parse_entries", "resolve_entry", "uncertainty_model",
           "plant_uncertainty", "check_plant_uncertainty", "CORRELATION_KEY", "PSD_TOLERANCE",
           "correlation_entry", "restrict_correlation", "correlation_toml", "carry_correlation", "inner_truncation"]

#: Reserved name of the correlation blocks in an ``[uncertainty]`` table (never a plant key).
CORRELATION_KEY = "correlation"
#: Smallest eigenvalue accepted in a correlation matrix (positive semi-definite within round-off).
PSD_TOLERANCE = 1e-9
#: Largest asymmetry ``|r_ij - r_ji|`` and diagonal error ``|r_ii - 1|`` accepted.
SYMMETRY_TOLERANCE = 1e-12

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
    the parameters it needs, positive widths, a source. Returns ``key -> entry`` (flattened),
    plus ``"correlation"`` -> its blocks (``[{"keys", "matrix", "source"}]``, checked: see the
    module docstring) when the table has one; the result parses again to itself.

    Raises
    ------
    PlantFileError or SceneError (``err``)
        Naming the file (``origin``), the key and what was expected.
    """
    if not isinstance(table, Mapping):
        raise err(f"{origin}: [uncertainty] = {quote(table)}; expected a table of 'section.key' = {{ dist = ... }}")
    out: dict[str, Any] = {}
    flat = _flatten(table)
    corr = flat.pop(CORRELATION_KEY, None)
    for key, entry in flat.items():
        where = f"uncertainty.{quote(key)}"
        if key not in KIND:
            raise err(f"{origin}: unknown key {where}; expected a plant parameter 'section.key' "
                      f"(e.g. 'nut.inertia_kg_m2')")
        if KIND[key] == "positive integer":
            raise err(f"{origin}: {where}: {key} is an integer parameter; expected a continuous one "
                      "(integer keys cannot be uncertain)")
        if not isinstance(entry, Mapping):
            raise err(f"{origin}: {where} = {quote(entry)}; expected {{ dist = \"uniform\"|\"normal\"|\"loguniform\", "
                      "..., source = \"...\" }")
        dist = entry.get("dist")
        if dist not in DISTRIBUTIONS:
            raise err(f"{origin}: {where}.dist = {quote(dist)}; expected one of {', '.join(DISTRIBUTIONS)}")
        required, optional = DISTRIBUTIONS[dist]
        extra = sorted(set(entry) - {"dist", "source", *required, *optional})
        if extra:
            raise err(f"{origin}: {where}: unknown field {quote(extra[0])} for dist = {quote(dist)}; expected "
                      f"{', '.join(['source', *required, *optional])}")
        src = entry.get("source")
        if not isinstance(src, str) or not src.strip():
            raise err(f"{origin}: {where}.source = {quote(src)}; expected a non-empty string "
                      "(paper, \"assumption: why\", \"estimate: why\", \"fit: file\")")
        for r in required:
            if r not in entry:
                raise err(f"{origin}: {where}: missing {quote(r)}; dist = {quote(dist)} needs {', '.join(required)}")
        nums = {k: check_number(f"{origin}: {where}.{k}", v, error=err) for k, v in entry.items() if k not in ("dist", "source")}
        if dist == "uniform":
            if ("relative" in nums) == ("low" in nums or "high" in nums):
                raise err(f"{origin}: {where}: expected either relative = r or low and high for dist = 'uniform'")
            if "relative" in nums and not 0 <= nums["relative"] < 1:
                raise err(f"{origin}: {where}.relative = {quote(entry['relative'])}; expected a relative half-width in [0, 1)")
            if "relative" not in nums and not ("low" in nums and "high" in nums):
                raise err(f"{origin}: {where}: expected both low and high for dist = 'uniform'")
        if dist == "normal":
            if ("sigma" in nums) == ("relative_sigma" in nums):
                raise err(f"{origin}: {where}: expected exactly one of sigma, relative_sigma for dist = 'normal'")
            s_key = "sigma" if "sigma" in nums else "relative_sigma"
            if nums[s_key] <= 0:
                raise err(f"{origin}: {where}.{s_key} = {quote(entry[s_key])}; expected a positive standard deviation")
            if not 0 < nums["truncate"] <= 6:
                raise err(f"{origin}: {where}.truncate = {quote(entry['truncate'])}; expected a bound in sigmas in (0, 6]")
        if dist == "loguniform" and not nums["low"] > 0:
            raise err(f"{origin}: {where}.low = {quote(entry['low'])}; expected a positive value (loguniform)")
        if "low" in nums and "high" in nums and not nums["low"] < nums["high"]:
            raise err(f"{origin}: {where}: low = {quote(entry['low'])} >= high = {quote(entry['high'])}; expected low < high")
        out[key] = {"dist": dist, "source": src.strip(), **nums}
    if corr is not None:
        out[CORRELATION_KEY] = _parse_correlation(corr, out, origin, err)
    return out


def _parse_correlation(raw: Any, entries: Mapping[str, Any], origin: str, err) -> list[dict[str, Any]]:
    """Check ``correlation`` (one table or an array of tables, see the module docstring); returns
    the blocks as ``[{"keys": [...], "matrix": [[...]], "source": "..."}]`` (floats), a form this
    function accepts again."""
    blocks = raw if isinstance(raw, list) else [raw]
    if not blocks:
        raise err(f"{origin}: uncertainty.correlation = {quote(raw)}; expected a table {{ keys = [...], matrix = [[...]], "
                  "source = \"...\" } or an array of such tables")
    seen: dict[str, int] = {}
    out = []
    for b, block in enumerate(blocks):
        where = "uncertainty.correlation" + (f"[{b}]" if isinstance(raw, list) else "")
        if not isinstance(block, Mapping):
            raise err(f"{origin}: {where} = {quote(block)}; expected a table {{ keys = [...], matrix = [[...]], source = \"...\" }}")
        extra = sorted(set(block) - {"keys", "matrix", "source"})
        if extra:
            raise err(f"{origin}: {where}: unknown field {quote(extra[0])}; expected keys, matrix, source")
        missing = [f for f in ("keys", "matrix", "source") if f not in block]
        if missing:
            raise err(f"{origin}: {where}: missing {quote(missing[0])}; expected {{ keys = [...], matrix = [[...]], "
                      "source = \"...\" }")
        keys, matrix, src = block["keys"], block["matrix"], block["source"]
        if not isinstance(src, str) or not src.strip():
            raise err(f"{origin}: {where}.source = {quote(src)}; expected a non-empty string (\"fit: file\", \"estimate: why\")")
        if not isinstance(keys, list) or len(keys) < 2 or not all(isinstance(k, str) for k in keys):
            raise err(f"{origin}: {where}.keys = {quote(keys)}; expected a list of at least two 'section.key' names")
        for k in keys:
            if k not in entries:
                raise err(f"{origin}: {where}.keys: {quote(k)} has no entry of its own in [uncertainty]; expected every "
                          "correlated key to have its distribution in the same table")
            if k in seen:
                raise err(f"{origin}: {where}.keys: {quote(k)} appears twice" + ("" if seen[k] == b else " (in two blocks)")
                          + "; expected each key once")
            seen[k] = b
        n = len(keys)
        if (not isinstance(matrix, list) or len(matrix) != n
                or not all(isinstance(row, list) and len(row) == n for row in matrix)):
            raise err(f"{origin}: {where}.matrix = {quote(matrix)}; expected a square {n} x {n} array (one row per key)")
        m = np.array([[check_number(f"{origin}: {where}.matrix[{i}][{j}]", x, error=err) for j, x in enumerate(row)]
                      for i, row in enumerate(matrix)])
        for i in range(n):
            if abs(m[i, i] - 1.0) > SYMMETRY_TOLERANCE:
                raise err(f"{origin}: {where}.matrix[{i}][{i}] = {quote(matrix[i][i])}; expected 1 (a correlation's diagonal)")
            for j in range(n):
                if abs(m[i, j]) > 1.0:
                    raise err(f"{origin}: {where}.matrix[{i}][{j}] = {quote(matrix[i][j])}; expected a correlation in [-1, 1]")
                if abs(m[i, j] - m[j, i]) > SYMMETRY_TOLERANCE:
                    raise err(f"{origin}: {where}.matrix[{i}][{j}] = {quote(matrix[i][j])} but [{j}][{i}] = {quote(matrix[j][i])}; "
                              "expected a symmetric matrix")
        low = float(np.linalg.eigvalsh(0.5 * (m + m.T)).min())
        if low < -PSD_TOLERANCE:
            raise err(f"{origin}: {where}.matrix = {quote(matrix)} has the eigenvalue {low:.3g}; expected a positive "
                      f"semi-definite correlation (eigenvalues >= -{PSD_TOLERANCE:g})")
        out.append({"keys": list(keys), "matrix": [[float(x) for x in row] for row in m], "source": src.strip()})
    return out


def resolve_entry(key: str, entry: Mapping[str, Any], nominal: float, origin: str, err) -> Uncertain:
    """One parsed ``[uncertainty]`` entry of a plant key as a distribution about its nominal value.

    Parameters
    ----------
    key : str
        The plant key (SI units as the plant file states them).
    entry : mapping
        The entry as :func:`parse_entries` returns it (``dist`` and its spread).
    nominal : float
        The key's nominal value, in the key's units.
    origin : str
        Where the entry was read (for messages).
    err : type
        The exception raised on an entry that does not fit the key (one line naming it).

    Returns
    -------
    Uncertain
    """
    where = f"uncertainty.{quote(key)}"
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


#: A pivot of the semi-definite Cholesky factor at or below this is a zero (a singular direction).
_PIVOT_ZERO = 1e-12


def _factor(matrix: Sequence[Sequence[float]]) -> tuple[tuple[float, ...], ...]:
    """Lower-triangular ``L`` with ``L L' = R`` for a positive semi-definite correlation ``R``
    (Cholesky; a pivot ``<= 1e-12`` gives a zero column, so a singular ``R`` factors too), each
    row scaled to unit length so that every ``z_i = (L n)_i`` is exactly standard normal.
    Plain floats and ``math.fsum``: the same factor on any machine and any BLAS."""
    n = len(matrix)
    L = [[0.0] * n for _ in range(n)]
    for j in range(n):
        d = matrix[j][j] - math.fsum(L[j][k] ** 2 for k in range(j))
        if d <= _PIVOT_ZERO:
            continue
        L[j][j] = math.sqrt(d)
        for i in range(j + 1, n):
            L[i][j] = (matrix[i][j] - math.fsum(L[i][k] * L[j][k] for k in range(j))) / L[j][j]
    rows = []
    for row in L:
        norm = math.sqrt(math.fsum(x * x for x in row))
        rows.append(tuple(x / norm for x in row))
    return tuple(rows)


@dataclass(frozen=True)
class Correlation:
    """One correlation block of an uncertainty model: the correlation ``matrix`` of the normal
    scores of ``keys`` (a Gaussian copula, see the module docstring) and its source."""

    keys: tuple[str, ...]
    matrix: tuple[tuple[float, ...], ...]
    source: str

    @functools.cached_property
    def factor(self) -> tuple[tuple[float, ...], ...]:
        """The unit-row semi-definite Cholesky factor (:func:`_factor`), computed once."""
        return _factor(self.matrix)

    def as_dict(self) -> dict[str, Any]:
        return {"keys": list(self.keys), "matrix": [list(r) for r in self.matrix], "source": self.source}


@dataclass(frozen=True)
class UncertaintyModel:
    """The uncertain parameters of one plant (sorted by key, so samples do not depend on the
    order the file lists them in), the correlation blocks among them and notes (e.g. a plant
    correlation that a scene's entries cut)."""

    entries: tuple[Uncertain, ...]
    correlations: tuple[Correlation, ...] = ()
    notes: tuple[str, ...] = ()

    @property
    def keys(self) -> tuple[str, ...]:
        return tuple(e.key for e in self.entries)

    def __len__(self) -> int:
        return len(self.entries)

    def sample(self, rng: np.random.Generator) -> dict[str, float]:
        """One draw (file units), consuming ``len(self)`` uniforms from ``rng``.

        Without correlation each key's uniform ``u`` gives its value ``F^-1(u)``. A correlation
        block turns its keys' uniforms into ``Phi(L Phi^-1(u))`` first (Gaussian copula, the same
        uniforms consumed); the other keys are drawn as without it.
        """
        u = rng.random(len(self.entries))
        if self.correlations:
            u = self._correlated(u)
        return {e.key: float(e.ppf(ui)) for e, ui in zip(self.entries, u)}

    def _correlated(self, u: np.ndarray) -> np.ndarray:
        from scipy.special import ndtr, ndtri

        u = u.copy()
        pos = {k: i for i, k in enumerate(self.keys)}
        for c in self.correlations:
            idx = [pos[k] for k in c.keys]
            n = ndtri(np.clip(u[idx], 2.0 ** -60, None)).tolist()  # rng.random() may return 0.0
            z = [math.fsum(a * b for a, b in zip(row, n)) for row in c.factor]
            u[idx] = ndtr(np.array(z))
        return u

    def vertices(self) -> list[dict[str, float]]:
        """Corners of the support box (``2**len(self)`` points, first key varying slowest); a
        correlation does not change them (every corner stays a possible worst case)."""
        out = []
        for bits in range(2 ** len(self.entries)):
            out.append({e.key: (e.high if (bits >> (len(self.entries) - 1 - j)) & 1 else e.low)
                        for j, e in enumerate(self.entries)})
        return out

    def as_dict(self) -> dict[str, Any]:
        """Key -> distribution; a correlated key also has ``correlation`` (``with``: the other
        keys of its block and their correlations, ``source``), a key whose plant correlation a
        scene cut a ``correlation_note``."""
        out = {e.key: e.as_dict() for e in self.entries}
        for c in self.correlations:
            for i, k in enumerate(c.keys):
                out[k]["correlation"] = {"with": {o: c.matrix[i][j] for j, o in enumerate(c.keys) if j != i},
                                         "source": c.source}
        for note in self.notes:
            for k in out:
                if f"{quote(k)}" in note.split(":", 1)[0]:
                    out[k]["correlation_note"] = note
        return out


def _build(entries: Mapping[str, Any], plant, origin: str, err, notes: Sequence[str] = ()) -> UncertaintyModel:
    unc = []
    for key in sorted(k for k in entries if k != CORRELATION_KEY):
        if key not in plant.values:
            raise err(f"{origin}: unknown key uncertainty.{quote(key)}; the plant {quote(plant.name)} has no such parameter")
        unc.append(resolve_entry(key, entries[key], float(plant.values[key]), origin, err))
    corr = tuple(Correlation(tuple(b["keys"]), tuple(tuple(r) for r in b["matrix"]), b["source"])
                 for b in entries.get(CORRELATION_KEY, ()))
    model = UncertaintyModel(tuple(unc), corr, tuple(notes))
    # Every end of every key's support must be a valid plant (cross-checks such as static >=
    # dynamic friction and thread meshing live in the plant).
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeometryWarning)
        for e in unc:
            for v in (e.low, e.high):
                try:
                    plant.with_params({e.key: v})
                except PlantFileError as exc:
                    raise err(f"{origin}: uncertainty.{quote(e.key)} = {v:g} (end of its {e.dist} support) makes an "
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
                    which = " with ".join(f"uncertainty.{quote(unc[i].key)} = {unc[i].low:g}..{unc[i].high:g}" for i in idx)
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


@dataclass(frozen=True)
class Uncertainty:
    """What a study adds to the plant's uncertainty (a scene's ``[uncertainty]`` table and its
    ``[robust] plant_uncertainty`` switch), typed: the plant layer reads this, never a scene.

    Attributes
    ----------
    entries : Mapping
        Parsed entries (:func:`parse_entries`), ``key -> entry`` plus ``"correlation"`` blocks;
        empty when the study adds none.
    origin : str
        Where the entries came from (a file name), for messages.
    plant_uncertainty : bool
        False: the plant file's own ``[uncertainty]`` is dropped and ``entries`` used alone.
    """

    entries: Mapping[str, Any] = field(default_factory=dict, compare=False, hash=False)
    origin: str = "<scene>"
    plant_uncertainty: bool = True


def uncertainty_model(plant, section: Uncertainty | None = None,
                      extra: Mapping[str, Any] | None = None) -> UncertaintyModel:
    """Plant uncertainty, overridden/extended by a study's ``section`` (what a scene attaches to
    the actuator: ``scene.sections.plant_overrides``) and by ``extra`` (API callers), key by key.
    A section with ``plant_uncertainty = False`` (a scene's ``[robust] plant_uncertainty =
    false``) uses its own entries alone.

    Parameters
    ----------
    plant : Plant
    section : Uncertainty, optional
    extra : Mapping, optional
        ``[uncertainty]``-style entries.

    Raises
    ------
    PlantFileError, SceneError
        Naming the file and the key of the bad entry.
    TypeError
        ``section`` is not an :class:`Uncertainty` (a scene is no longer read here).
    """
    if section is not None and not isinstance(section, Uncertainty):
        raise TypeError(f"uncertainty_model: section is a {type(section).__name__}; expected an Uncertainty "
                        "(a scene's: scene.sections.plant_overrides)")
    entries = parse_entries(getattr(plant, "uncertainty", {}) or {}, plant.origin, PlantFileError)
    model = _build(entries, plant, plant.origin, PlantFileError)
    if section is not None and not section.plant_uncertainty:
        entries, model = {}, UncertaintyModel(())
    merged: dict[str, Any] = dict(entries)
    notes: list[str] = []
    if section is not None:
        s_entries = parse_entries(dict(section.entries), section.origin, SceneError)
        if s_entries:
            merged = _override(merged, s_entries, section.origin, notes)
            model = _build(merged, plant, section.origin, SceneError, notes)
    if extra:
        merged = _override(merged, parse_entries(extra, "<extra>", ValueError), "<extra>", notes)
        model = _build(merged, plant, "<extra>", ValueError, notes)
    return model


def restrict_correlation(block: Mapping[str, Any], keys: Sequence[str]) -> dict[str, Any] | None:
    """The block (``{"keys", "matrix", "source"}``) restricted to those of its keys in ``keys``
    (its principal sub-matrix, valid whenever the block is), or None when fewer than two remain."""
    idx = [i for i, k in enumerate(block["keys"]) if k in keys]
    if len(idx) < 2:
        return None
    return {"keys": [block["keys"][i] for i in idx], "matrix": [[block["matrix"][i][j] for j in idx] for i in idx],
            "source": block["source"]}


def _override(base: Mapping[str, Any], over: Mapping[str, Any], origin: str, notes: list[str]) -> dict[str, Any]:
    """``base`` entries overridden key by key by ``over``'s; each correlation block of ``base``
    keeps the keys ``over`` leaves alone (the dropped ones named in ``notes``), ``over``'s own
    blocks are added."""
    out = {k: v for k, v in base.items() if k != CORRELATION_KEY}
    out.update({k: v for k, v in over.items() if k != CORRELATION_KEY})
    blocks = []
    for b in base.get(CORRELATION_KEY, ()):
        cut = [k for k in b["keys"] if k in over]
        if cut:
            notes.append(f"{', '.join(repr(k) for k in cut)}: {origin} overrides the entr"
                         f"{'ies' if len(cut) > 1 else 'y'}, so the plant's correlation ({b['source']}) no longer "
                         "applies to " + ("them" if len(cut) > 1 else "it") + "; drawn independently of "
                         + ", ".join(k for k in b["keys"] if k not in over))
        kept = restrict_correlation(b, [k for k in b["keys"] if k not in over])
        if kept is not None:
            blocks.append(kept)
    blocks += list(over.get(CORRELATION_KEY, ()))
    if blocks:
        out[CORRELATION_KEY] = blocks
    return out


def correlation_entry(keys: Sequence[str], covariance: Any, source: str) -> dict[str, Any] | None:
    """A correlation block (``{"keys", "matrix", "source"}``) from a covariance of ``keys``
    (any units: ``R_ij = C_ij / sqrt(C_ii C_jj)``, made exactly symmetric with a unit diagonal),
    or None with fewer than two keys, a variance that is not positive and finite, or a matrix
    that is not positive semi-definite within :data:`PSD_TOLERANCE`."""
    c = np.asarray(covariance, float)
    if len(keys) < 2 or c.shape != (len(keys), len(keys)) or not np.all(np.isfinite(c)):
        return None
    sd = np.sqrt(np.diag(c))
    if not np.all(sd > 0):
        return None
    r = c / np.outer(sd, sd)
    r = np.clip(0.5 * (r + r.T), -1.0, 1.0)
    np.fill_diagonal(r, 1.0)
    if float(np.linalg.eigvalsh(r).min()) < -PSD_TOLERANCE:
        return None
    return {"keys": list(keys), "matrix": [[float(x) for x in row] for row in r], "source": source}


def carry_correlation(entries: Mapping[str, Any], base: Mapping[str, Any],
                      block: Mapping[str, Any] | None = None, notes: list[str] | None = None) -> dict[str, Any]:
    """An ``[uncertainty]`` table written from ``base``'s (e.g. a fitted plant from its base
    plant): ``entries`` with ``base``'s correlation blocks restricted to the keys whose entry is
    still ``base``'s own (:func:`restrict_correlation`), plus ``block`` (e.g. the fit's).

    Parameters
    ----------
    entries : mapping
        The new table's per-key entries (a ``correlation`` in it is replaced).
    base : mapping
        The table it was made from (raw TOML form; its ``correlation`` a table or an array).
    block : mapping, optional
        A new block (``{"keys", "matrix", "source"}``) over keys whose entries are new; it replaces
        the base's blocks over its keys (a refit whose entries equal the base's still takes them
        out of the base's blocks, so that no key is in two blocks).
    notes : list of str, optional
        Gets one line per base block that loses keys (naming them).

    Returns
    -------
    dict
        The table; its ``correlation`` one table (one block) or an array (several), absent when
        there is none.
    """
    out = {k: v for k, v in entries.items() if k != CORRELATION_KEY}
    old = base.get(CORRELATION_KEY) or []
    new_keys = set(block["keys"]) if block is not None else set()  # the new block replaces the base's over them
    blocks = []
    for b in old if isinstance(old, list) else [old]:
        same = [k for k in b["keys"] if k in out and out[k] == base.get(k) and k not in new_keys]
        kept = restrict_correlation(b, same)
        if kept is not None:
            blocks.append(kept)
        gone = [k for k in b["keys"] if k not in same]
        if notes is not None and gone:
            why = ("the new correlation block holds them" if all(k in new_keys for k in gone) else
                   f"{'their entries are' if len(gone) > 1 else 'its entry is'} no longer the base's")
            notes.append(f"[uncertainty] correlation ({b['source']}): dropped for {', '.join(gone)} ({why})"
                         + ("" if kept else "; nothing is left of the block"))
    if block is not None:
        blocks.append(dict(block))
    if blocks:
        out[CORRELATION_KEY] = blocks[0] if len(blocks) == 1 else blocks
    return out


def inner_truncation(value: float, sigma: float, floor: float = -math.inf, ceil: float = math.inf, *,
                     limit: float = 1.959963984540054, open_floor: bool = False, decimals: int = 6) -> float:
    """The truncation (in standard deviations) of a normal ``[uncertainty]`` entry that keeps its
    support inside ``[floor, ceil]``: ``limit`` when that fits, else the largest multiple of
    ``10**-decimals`` below it that does, checked in the arithmetic the plant-file reader uses
    (``value -/+ truncate * sigma``). Rounding a truncation to the nearest multiple instead can
    cross the bound (a Coulomb interval reaching 0 written as a support from -3.3e-09 N: the file
    is refused).

    Parameters
    ----------
    value, sigma : float
        Nominal value and standard deviation (file units; ``sigma > 0``).
    floor, ceil : float
        The physical range of the key (file units).
    limit : float
        The largest truncation wanted (default 1.96: the 95 % interval).
    open_floor : bool
        The support must stay strictly above ``floor`` (a ``positive`` key).
    decimals : int
        Decimals of a truncation below ``limit``.

    Returns
    -------
    float
        The truncation, >= 0 (0 when not even ``10**-decimals`` fits).

    Examples
    --------
    >>> round(1.2345679 * (1 - 1e-9), 6)  # nearest: past the bound 1.2345679
    1.234568
    >>> inner_truncation(1.2345679, 1.0, floor=0.0)
    1.234567
    """
    def inside(t: float) -> bool:
        lo, hi = value - t * sigma, value + t * sigma
        return (lo > floor if open_floor else lo >= floor) and hi <= ceil

    if not (sigma > 0 and math.isfinite(value) and math.isfinite(sigma)):
        raise ValueError(f"value = {value!r}, sigma = {sigma!r}; expected finite numbers, sigma > 0")
    if inside(limit):
        return float(limit)
    q = 10 ** decimals
    k = math.floor(min(limit, (value - floor) / sigma, (ceil - value) / sigma) * q) + 1  # the quotient is rounded
    for _ in range(8):  # within a few ulps of the bound: a step or two at most
        if k <= 0:
            return 0.0
        if k / q < limit and inside(k / q):
            return k / q
        k -= 1
    return 0.0


def correlation_toml(blocks: Sequence[Mapping[str, Any]]) -> str:
    """The TOML value of ``correlation`` (after ``correlation = ``): one inline table, or an array
    of them; every number with all its digits (``repr``), so that the file reads back exactly
    (written by the one plant-file writer, :mod:`prsa_ctrl.plant.writer`)."""
    from .writer import inline_value

    one = [{"keys": list(b["keys"]), "matrix": [[float(x) for x in row] for row in b["matrix"]], "source": b["source"]}
           for b in blocks]
    return inline_value(one[0] if len(one) == 1 else one, CORRELATION_KEY)


def apply(plant, values: Mapping[str, float], name: str | None = None):
    """The plant at one point of its uncertainty (``values`` in file units)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeometryWarning)
        return plant.with_params(values, name=name or f"{plant.name}*")


def describe(model: UncertaintyModel) -> list[str]:
    """One line per uncertain parameter, per correlation block and per note (for reports)."""
    return ([f"{e.key}: {e.dist} [{e.low:.4g}, {e.high:.4g}] (nominal {e.nominal:.4g}; {e.source})"
             for e in model.entries]
            + [f"correlation of {', '.join(c.keys)} (normal scores, Gaussian copula; {c.source})" for c in model.correlations]
            + [f"note: {n}" for n in model.notes])


def keys_of(models: Sequence[UncertaintyModel]) -> list[str]:
    return sorted({k for m in models for k in m.keys})
