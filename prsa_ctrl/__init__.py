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
    "simulate": "sim.simulate",
    "run": "sim.simulate",
    "SimRun": "sim.simulate",
    "SimSettings": "sim.simulate",
    "energy_balance": "sim.simulate",
    "operating_point": "plant.equilibrium",
    "plant_model": "plant.model",
    "linearize": "plant.linear",
    "closed_loop": "plant.linear",
    "predict_load_step": "plant.linear",
    "nonlinear_iosys": "plant.iosys",
    "kinematics_table": "studies.paper",
    "load_step_study": "studies.paper",
    "tune_pid": "tuning.tuner",
    "Tuner": "tuning.tuner",
    "tune_loops": "tuning.tuner",
    "tune_actuator": "studies.autotune",
    "verify": "studies.autotune",
    "load_scene": "studies.scene",
    "Scene": "studies.scene",
    "load_step_metrics": "sim.metrics",
    "design_kf": "drive.estimator",
    "export_controller": "io.export",
    "fit_plant": "identification.fit",
    "FitResult": "identification.fit",
    "FitError": "identification.fit",
    "PiecewiseLinear": "sim.simulate",
    "Design": "studies.autotune",
    "ActuatorTuning": "studies.autotune",
    "LoopModel": "tuning.tuner",
    "TuningResult": "tuning.tuner",
    "tune_filtered": "tuning.filtered",
    "FilteredDesign": "tuning.filtered",
    "tune_robust": "tuning.robust",
    "tune_robust_actuator": "tuning.robust",
    "RobustTuning": "tuning.robust",
    "tune_cascade": "tuning.cascade",
    "CascadeDesign": "tuning.cascade",
    "load_move_scene": "tuning.cascade",
    "MoveScene": "tuning.cascade",
    "run_monte_carlo": "studies.montecarlo",
    "MonteCarloReport": "studies.montecarlo",
    "fit_frf": "identification.fit",
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
