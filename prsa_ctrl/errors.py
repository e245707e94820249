"""Exceptions raised by prsa-ctrl.

Every message names the value that was received and what was expected.
"""

__all__ = ["PlantFileError", "SceneError", "SimulationError", "GeometryWarning"]


class PlantFileError(ValueError):
    """A plant definition file (or plant override) is malformed or physically impossible."""


class SceneError(ValueError):
    """A tuning/simulation scene (file or arguments) is malformed."""


class SimulationError(RuntimeError):
    """The integrator failed; the message names the time, the state and a remedy."""


class GeometryWarning(UserWarning):
    """The roller-screw geometry does not close exactly (residuals are reported)."""
