"""prsa-ctrl: speed-loop tuning for inverted planetary roller screw actuators.

Heavy modules (python-control, CasADi, matplotlib, filterpy) are imported only when a name that
needs them is first used, so ``import prsa_ctrl`` and plant loading stay cheap.
"""

from ._lazy import lazy_exports
from .errors import GeometryWarning, PlantFileError, SceneError, SimulationError
from .plant.plantfile import DEFAULT_PLANT, Kinematics, Plant, builtin_plants, load_plant

__version__ = "0.1.0"

_LAZY = {
    "PID": "drive.pid",
    "simulate": "sim.engine",
    "run": "sim.engine",
    "SimRun": "sim.engine",
    "SimSettings": "sim.integrators",
    "energy_balance": "sim.engine",
    "operating_point": "plant.equilibrium",
    "plant_model": "plant.model",
    "linearize": "plant.linear",
    "closed_loop": "drive.linear_loop",
    "predict_load_step": "drive.linear_loop",
    "nonlinear_iosys": "plant.iosys",
    "kinematics_table": "studies.paper",
    "load_step_study": "studies.paper",
    "tune_pid": "tuning.generic",
    "Tuner": "tuning.tuner",
    "tune_loops": "tuning.generic",
    "tune_actuator": "studies.autotune",
    "verify": "studies.autotune",
    "load_scene": "studies.scene",
    "Scene": "studies.scene",
    "load_step_metrics": "sim.metrics",
    "design_kf": "drive.estimator",
    "export_controller": "io.export",
    "fit_plant": "identification.timedomain",
    "FitResult": "identification.common",
    "FitError": "errors",
    "PiecewiseLinear": "sim.signals",
    "Design": "studies.autotune",
    "ActuatorTuning": "studies.autotune",
    "LoopModel": "tuning.loops",
    "TuningResult": "tuning.tuner",
    "tune_filtered": "tuning.filtered",
    "FilteredDesign": "tuning.filtered",
    "tune_robust": "tuning.robust",
    "tune_robust_actuator": "studies.scenerobust",
    "RobustTuning": "tuning.robust",
    "tune_cascade": "tuning.cascade",
    "CascadeDesign": "tuning.cascade",
    "load_move_scene": "studies.movescene",
    "MoveScene": "studies.movescene",
    "run_monte_carlo": "studies.montecarlo",
    "MonteCarloReport": "studies.montecarlo",
    "fit_frf": "identification.frf",
}

_EAGER = {
    "DEFAULT_PLANT": DEFAULT_PLANT,
    "GeometryWarning": GeometryWarning,
    "Kinematics": Kinematics,
    "Plant": Plant,
    "PlantFileError": PlantFileError,
    "SceneError": SceneError,
    "SimulationError": SimulationError,
    "builtin_plants": builtin_plants,
    "load_plant": load_plant,
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _LAZY, _EAGER)
