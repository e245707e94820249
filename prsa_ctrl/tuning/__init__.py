"""Loop models and the tuners: generic PI/PID, filtered designs, robust tuning, the position/speed cascade."""

from .._lazy import lazy_exports

#: Names of the move scene, its verification, export, figures and report are listed here as well
#: (they lived in ``tuning.cascade`` before the redesign) and resolve lazily to their modules in
#: the higher layers (``".studies.move"`` is ``prsa_ctrl.studies.move``); nothing in ``tuning``
#: imports them.
_EXPORTS = {
    "BREAKING_POINTS": "cascade",
    "CASCADE_GAINS": "cascade",
    "CONT_RTOL": "tuner",
    "CascadeDesign": "cascade",
    "CascadeModel": "cascade",
    "FilterBounds": "filtered",
    "FilteredDesign": "filtered",
    "KKT_TOL": "tuner",
    "LoopModel": "tuner",
    "MAX_ORDER": "tuner",
    "MOVE_FLAGS": ".cli.tune",
    "MS_EXCESS_RTOL": "cascade",
    "MoveMetrics": ".studies.move",
    "MoveScene": ".studies.movescene",
    "OBJECTIVES": "tuner",
    "POSITION_LAW": ".io.export",
    "RobustTuning": "robust",
    "STABILITY": "tuner",
    "Scenario": "robust",
    "TAIL_RTOL": "tuner",
    "TUNABLE": "filtered",
    "Tuner": "tuner",
    "TuningResult": "tuner",
    "check_move_against_plant": ".studies.move",
    "compare_designs": "robust",
    "continuous_loop": "tuner",
    "dominant_resonance_hz": "filtered",
    "drive_loop": "tuner",
    "export_cascade": ".io.export",
    "format_move_report": ".cli.report",
    "hunting": ".studies.move",
    "is_move_scene": ".studies.scenefile",
    "load_move_scene": ".studies.movescene",
    "loop_builder": "filtered",
    "move_metrics": ".studies.move",
    "operating_points": "robust",
    "scenario_loops": "robust",
    "scenarios": "robust",
    "sequential_design": "cascade",
    "simulate_move": ".studies.move",
    "tune_cascade": "cascade",
    "tune_filtered": "filtered",
    "tune_loops": "tuner",
    "tune_pid": "tuner",
    "tune_robust": "robust",
    "tune_robust_actuator": "robust",
    "verify_design": ".studies.move",
    "write_move_plots": ".plots.move",
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
