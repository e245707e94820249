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

import math
import re
from typing import Any

__all__ = ["STATUSES", "status_head", "is_converged", "is_ok", "check_status", "json_safe"]

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

