"""What runs in the drive: the PID law, filters, speed measurement, the Kalman estimator, motion profiles, drive parameter units, and the sampled-loop algebra (zero-order hold, per-sample PID rows)."""

from .._lazy import lazy_exports

_EXPORTS = {
    "DEFAULT_LOAD_CHANGE_TIME_S": "estimator",
    "DiscreteBiquad": "filters",
    "EncoderDifference": "measurement",
    "Filter": "filters",
    "FirstOrderLowPass": "filters",
    "GeneralBiquad": "filters",
    "KFDesign": "estimator",
    "KalmanSpeed": "measurement",
    "LoopFilter": "filters",
    "MAX_SEGMENTS": "motion",
    "METHODS": "filters",
    "MotionProfile": "motion",
    "Notch": "filters",
    "PID": "pid",
    "PLACES": "filters",
    "POSITION_SENSORS": "measurement",
    "PROFILE_KINDS": "motion",
    "PositionLoop": "measurement",
    "SecondOrderLowPass": "filters",
    "SpeedMeasurement": "measurement",
    "closed_loop": "linear_loop",
    "design_kf": "estimator",
    "filter_from_dict": "filters",
    "freq_grid": "sampled",
    "loop_filters": "filters",
    "measurement_for": "measurement",
    "out_and_back": "motion",
    "pid_controller": "linear_loop",
    "pid_frequency_parts": "sampled",
    "pid_law": "pid",
    "pid_rows": "sampled",
    "predict_load_step": "linear_loop",
    "s_curve": "motion",
    "ss_response": "sampled",
    "trapezoidal": "motion",
    "zoh": "sampled",
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
