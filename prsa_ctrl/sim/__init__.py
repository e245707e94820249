"""The nonlinear simulator (integrators, signals) and the metrics of its runs."""

from .._lazy import lazy_exports

_EXPORTS = {
    "Built": "integrators",
    "DEFAULT_BAND": "metrics",
    "INPUT_LABELS": "simulate",
    "INTEGRATORS": "integrators",
    "LoadStepMetrics": "metrics",
    "MAX_OUTPUT_POINTS": "simulate",
    "Margins": "metrics",
    "NormalisedProfile": "signals",
    "PiecewiseLinear": "signals",
    "Profile": "signals",
    "ProfileMetrics": "metrics",
    "RADAU_STAGES": "integrators",
    "SimRun": "simulate",
    "SimSettings": "integrators",
    "accumulated": "integrators",
    "build": "integrators",
    "compiled": "integrators",
    "continuous_integrator": "integrators",
    "energy_balance": "simulate",
    "fast_settings": "simulate",
    "fixed_step_error": "simulate",
    "initial_state": "simulate",
    "is_number": "signals",
    "jit_cache_dir": "integrators",
    "load_step_metrics": "metrics",
    "margins_from_response": "metrics",
    "metric_resolution": "metrics",
    "normalise_profile": "signals",
    "profile_metrics": "metrics",
    "radau_step": "integrators",
    "radau_tableau": "integrators",
    "relative_difference": "metrics",
    "run": "simulate",
    "sample_integrator": "integrators",
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
