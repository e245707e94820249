"""The one status vocabulary of prsa-ctrl's result objects (light: no imports beyond the standard library).

Every result (:class:`~prsa_ctrl.studies.autotune.Design`,
:class:`~prsa_ctrl.studies.autotune.ActuatorTuning`,
:class:`~prsa_ctrl.tuning.filtered.FilteredDesign`, :class:`~prsa_ctrl.tuning.robust.RobustTuning`,
:class:`~prsa_ctrl.studies.montecarlo.MonteCarloReport`, and the tuner's ``TuningResult``) is a
frozen dataclass with a ``status`` string, a ``warnings`` tuple (one line each) and ``as_dict()``.
A status is one of the heads below, optionally followed by ``": <why>"`` (or, for
``"optimal"``, a parenthesised qualifier such as ``"optimal (acceptable level)"``).
``converged`` and ``ok`` are derived from the status (:func:`is_converged`, :func:`is_ok`),
never stored beside it.
"""

from __future__ import annotations

import copy
import math
import re
from typing import Any, Mapping

__all__ = ["STATUSES", "status_head", "is_converged", "is_ok", "check_status", "json_safe", "FrozenDict", "FrozenList",
           "freeze"]

#: Status heads and what each means. A result's ``status`` starts with exactly one of them.
STATUSES: dict[str, str] = {
    "optimal": "an optimiser's result whose first-order optimality conditions and every bound were verified "
               "independently of the solver's own exit status",
    "not proven optimal": "the solver stopped at a point that meets every bound but the independent first-order "
                          "check fails (the residual follows the colon)",
    "not converged": "the solver failed; the result is the best verified point found (why follows the colon)",
    "no <kind> helps": "filtered tuning: the best filter found does not earn its place (why follows the colon); "
                       "the gains alone are returned, converged when their own tuning was",
    "ok": "a verified result: every nonlinear run passed every health check (a report, a verified design, a "
          "complete Monte-Carlo run)",
    "flagged": "a verified result that failed a health check (the checks it failed follow the colon); never "
               "reported as good",
    "unverified": "a design not (yet) run on the nonlinear simulator: only its linear prediction is known",
    "interrupted": "a run stopped before all its work was done (partial results; how far follows the colon)",
}

_NO_HELPS = re.compile(r"no \S+ helps(:|$)")


def status_head(status: str) -> str:
    """The vocabulary entry a status string belongs to (a key of :data:`STATUSES`).

    Examples
    --------
    >>> status_head("optimal (acceptable level)"), status_head("flagged: the nut reverses")
    ('optimal', 'flagged')
    >>> status_head("no notch helps: too shallow")
    'no <kind> helps'
    """
    if not isinstance(status, str):
        raise TypeError(f"status = {status!r}; expected a str starting with one of {', '.join(STATUSES)}")
    if _NO_HELPS.match(status):
        return "no <kind> helps"
    for head in sorted(STATUSES, key=len, reverse=True):  # "not proven optimal" before "optimal"
        if status == head or status.startswith(head + ":") or status.startswith(head + " ("):
            return head
    raise ValueError(f"status = {status!r}; expected a str starting with one of {', '.join(STATUSES)}")


def check_status(status: str) -> str:
    """``status`` itself if it belongs to the vocabulary, else a ValueError naming it."""
    status_head(status)
    return status


def is_converged(status: str) -> bool:
    """Whether a solver's status is a verified optimum (head ``"optimal"``)."""
    return status_head(status) == "optimal"


def is_ok(status: str) -> bool:
    """Whether a result may be reported as good: a verified optimum or a healthy verified result."""
    return status_head(status) in ("optimal", "ok")


def json_safe(obj: Any) -> Any:
    """``obj`` with non-finite floats (unfinished runs, targets never reached, infinite
    margins) as ``None`` and numpy scalars as Python numbers, ready for strict JSON.

    Examples
    --------
    >>> json_safe({"a": float("inf"), "b": [1.0, float("nan")], "c": "x"})
    {'a': None, 'b': [1.0, None], 'c': 'x'}
    """
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if type(obj).__module__ == "numpy" and hasattr(obj, "item") and getattr(obj, "ndim", 1) == 0:
        return json_safe(obj.item())
    return obj



# --- read-only containers of frozen results ---------------------------------------------------------

def _read_only(self, *args: Any, **kwargs: Any) -> Any:
    raise TypeError(f"{type(self).__name__} is read-only (part of a frozen result); copy it first "
                    "(dict(x) / list(x)) to change it")


class FrozenDict(dict):
    """A ``dict`` that cannot be changed: the mappings of frozen results (``Plant.uncertainty``,
    ``TuningResult.stats``, ``SimRun.info``). It is a ``dict`` for everything that reads one
    (``json``, ``==``, ``isinstance``, ``dataclasses.asdict``); it pickles (plain
    :mod:`pickle` too, unlike :class:`types.MappingProxyType`) and copies as itself.

    Examples
    --------
    >>> d = freeze({"a": [1, 2], "b": {"c": 3}})
    >>> d == {"a": [1, 2], "b": {"c": 3}}, type(d["a"]).__name__, type(d["b"]).__name__
    (True, 'FrozenList', 'FrozenDict')
    >>> d["a"].append(3)
    Traceback (most recent call last):
    ...
    TypeError: FrozenList is read-only (part of a frozen result); copy it first (dict(x) / list(x)) to change it
    """

    __slots__ = ()
    __setitem__ = __delitem__ = clear = pop = popitem = setdefault = update = __ior__ = _read_only

    def __reduce__(self):
        return freeze, (dict(self),)

    def __copy__(self) -> "FrozenDict":
        return self

    def __deepcopy__(self, memo: dict) -> "FrozenDict":
        return freeze(copy.deepcopy(dict(self), memo))


class FrozenList(list):
    """A ``list`` that cannot be changed (``==`` a list of the same items; pickles and copies as
    itself); the lists of frozen results (``TuningResult.per_loop``, ``margins``)."""

    __slots__ = ()
    __setitem__ = __delitem__ = __iadd__ = __imul__ = append = extend = insert = pop = remove = clear = \
        sort = reverse = _read_only

    def __reduce__(self):
        return freeze, (list(self),)

    def __copy__(self) -> "FrozenList":
        return self

    def __deepcopy__(self, memo: dict) -> "FrozenList":
        return freeze(copy.deepcopy(list(self), memo))


def freeze(obj: Any) -> Any:
    """``obj`` made read-only, deeply: mappings become :class:`FrozenDict`, lists
    :class:`FrozenList`, tuples keep their type with frozen items, numpy arrays read-only
    views (``flags.writeable = False``; the caller's array is left writeable); anything else
    as it is (frozen dataclasses, numbers, strings).

    >>> import numpy as np
    >>> a = freeze(np.zeros(2))
    >>> a.flags.writeable
    False
    """
    if isinstance(obj, (FrozenDict, FrozenList)):
        return obj
    if isinstance(obj, Mapping):
        return FrozenDict({k: freeze(v) for k, v in obj.items()})
    if isinstance(obj, list):
        return FrozenList(freeze(v) for v in obj)
    if type(obj) is tuple:
        return tuple(freeze(v) for v in obj)
    if type(obj).__module__ == "numpy" and hasattr(obj, "flags") and getattr(obj, "ndim", 0) > 0:
        if not obj.flags.writeable:
            return obj
        view = obj.view()
        view.flags.writeable = False
        return view
    return obj
