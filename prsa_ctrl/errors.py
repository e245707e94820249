"""Exceptions raised by prsa-ctrl.

Every message names the value that was received and what was expected.
"""

__all__ = ["PlantFileError", "SceneError", "SimulationError", "GeometryWarning", "DataError", "FitError"]


class PlantFileError(ValueError):
    """A plant definition file (or plant override) is malformed or physically impossible."""


class SceneError(ValueError):
    """A tuning/simulation scene (file or arguments) is malformed."""


class SimulationError(RuntimeError):
    """The integrator failed; the message names the time, the state and a remedy."""


class GeometryWarning(UserWarning):
    """The roller-screw geometry does not close exactly (residuals are reported)."""


class DataError(ValueError):
    """A measured-data file or array is unusable; the message names file, column and row."""


class FitError(RuntimeError):
    """The fit did not converge; the message names the solver status and a remedy."""
