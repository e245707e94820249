"""The nonlinear simulator (integrators, signals) and the metrics of its runs."""

from .._lazy import lazy_exports

_EXPORTS = {
    "DEFAULT_BAND": "metrics",
    "INPUT_LABELS": "simulate",
    "INTEGRATORS": "simulate",
    "LoadStepMetrics": "metrics",
    "MAX_OUTPUT_POINTS": "simulate",
    "Margins": "metrics",
    "PiecewiseLinear": "simulate",
    "Profile": "simulate",
    "ProfileMetrics": "metrics",
    "RADAU_STAGES": "simulate",
    "SimRun": "simulate",
    "SimSettings": "simulate",
    "energy_balance": "simulate",
    "fast_settings": "simulate",
    "fixed_step_error": "simulate",
    "jit_cache_dir": "simulate",
    "load_step_metrics": "metrics",
    "margins_from_response": "metrics",
    "metric_resolution": "metrics",
    "profile_metrics": "metrics",
    "relative_difference": "metrics",
    "run": "simulate",
    "simulate": "simulate",
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
