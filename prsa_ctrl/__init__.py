"""prsa-ctrl: speed-loop tuning for inverted planetary roller screw actuators.

Heavy modules (python-control, CasADi, matplotlib, filterpy) are imported only when a name that
needs them is first used, so ``import prsa_ctrl`` and plant loading stay cheap.
"""

from importlib import import_module
from typing import Any

from .errors import GeometryWarning, PlantFileError, SceneError, SimulationError
from .plant import DEFAULT_PLANT, Kinematics, Plant, builtin_plants, load_plant

__version__ = "0.1.0"

_LAZY = {
    "PID": "controller",
    "simulate": "simulation",
    "run": "simulation",
    "SimRun": "simulation",
    "SimSettings": "simulation",
    "energy_balance": "simulation",
    "operating_point": "equilibrium",
    "plant_model": "model",
    "linearize": "linear",
    "closed_loop": "linear",
    "predict_load_step": "linear",
    "nonlinear_iosys": "iosys",
    "kinematics_table": "paper",
    "load_step_study": "paper",
    "tune_pid": "tuning",
    "Tuner": "tuning",
    "tune_loops": "tuning",
    "tune_actuator": "autotune",
    "verify": "autotune",
    "load_scene": "scene",
    "Scene": "scene",
    "load_step_metrics": "metrics",
    "design_kf": "estimator",
    "export_controller": "export",
    "fit_plant": "fit",
    "FitResult": "fit",
    "FitError": "fit",
    "PiecewiseLinear": "simulation",
}

__all__ = [
    "DEFAULT_PLANT",
    "GeometryWarning",
    "Kinematics",
    "Plant",
    "PlantFileError",
    "SceneError",
    "SimulationError",
    "builtin_plants",
    "load_plant",
    *_LAZY,
]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(import_module(f".{_LAZY[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'prsa_ctrl' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
