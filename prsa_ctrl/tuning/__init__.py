"""Loop models and the tuners: generic PI/PID, filtered designs, robust tuning, the position/speed cascade."""

from .._lazy import lazy_exports

_EXPORTS = {
    "BREAKING_POINTS": "cascade",
    "CASCADE_GAINS": "cascade",
    "CONT_RTOL": "settings",
    "CascadeDesign": "cascade",
    "CascadeModel": "cascade",
    "CascadeSpec": "cascadespec",
    "FilterBounds": "filtered",
    "FilteredDesign": "filtered",
    "KKT_TOL": "settings",
    "LoopModel": "loops",
    "MAX_ORDER": "generic",
    "MS_EXCESS_RTOL": "cascade",
    "MS_RTOL": "settings",
    "RobustTuning": "robust",
    "STABILITY": "settings",
    "Scenario": "robust",
    "TAIL_RTOL": "settings",
    "TUNABLE": "filtered",
    "Tuner": "tuner",
    "TuningResult": "tuner",
    "compare_designs": "robust",
    "continuous_loop": "builders",
    "derivative_filter_s": "actuatorloops",
    "dominant_resonance_hz": "filtered",
    "drive_loop": "builders",
    "kf_drive_loop": "actuatorloops",
    "loop_builder": "filtered",
    "profile_loops": "actuatorloops",
    "sequential_design": "cascade",
    "step_loops": "actuatorloops",
    "tune_cascade": "cascade",
    "tune_filtered": "filtered",
    "tune_loops": "generic",
    "tune_pid": "generic",
    "tune_robust": "robust",
    "tune_scenario_loops": "robust",
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
