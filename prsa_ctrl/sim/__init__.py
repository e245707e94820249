"""The nonlinear simulator (integrators, signals) and the metrics of its runs."""

from .._lazy import lazy_exports

_EXPORTS = {
    "Built": "integrators",
    "DEFAULT_BAND": "metrics",
    "INPUT_LABELS": "engine",
    "INTEGRATORS": "integrators",
    "LoadStepMetrics": "metrics",
    "MAX_OUTPUT_POINTS": "engine",
    "Margins": "metrics",
    "NormalisedProfile": "signals",
    "PiecewiseLinear": "signals",
    "Profile": "signals",
    "ProfileMetrics": "metrics",
    "RADAU_STAGES": "integrators",
    "SimRun": "engine",
    "SimSettings": "integrators",
    "accumulated": "integrators",
    "build": "integrators",
    "compiled": "integrators",
    "continuous_integrator": "integrators",
    "energy_balance": "engine",
    "fast_settings": "engine",
    "fixed_step_error": "engine",
    "initial_state": "engine",
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
    "run": "engine",
    "sample_integrator": "integrators",
    "simulate": "engine",
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
