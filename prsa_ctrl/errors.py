"""Exceptions raised by prsa-ctrl.

Every message names the value that was received and what was expected.
"""

__all__ = ["PlantFileError", "SceneError", "SimulationError", "GeometryWarning", "DataError", "FitError",
           "LogFormatError", "AxisPlantError", "AxisFitError", "OutputError", "MonteCarloInterrupted", "UsageError",
           "PlantTextError", "SchedulerProbeError", "NoStabilisingGains"]


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


class LogFormatError(ValueError):
    """A log description or a log does not hold what it should; one line naming file and key."""


class AxisPlantError(ValueError):
    """A linear-axis plant file is malformed; one line naming the file and key."""


class AxisFitError(RuntimeError):
    """The fit did not converge or the data do not inform the parameters; says which and why."""


class PlantTextError(ValueError):
    """A plant typed as a rational function of ``s`` (``prsa-pid --plant``, the app's generic
    tuner) cannot be read; the message says where and what is expected, without the text itself
    (each caller names it as typed)."""


class OutputError(ValueError):
    """An output path cannot (or must not) be written; the message names it as typed."""


class MonteCarloInterrupted(KeyboardInterrupt):
    """Ctrl-C during :func:`prsa_ctrl.studies.montecarlo.run_monte_carlo`.

    ``report`` (a :class:`~prsa_ctrl.studies.montecarlo.MonteCarloReport`) holds the finished
    samples with ``complete = False`` (never to be written as a complete result).
    """

    def __init__(self, report) -> None:
        super().__init__("Monte Carlo interrupted")
        self.report = report


class UsageError(Exception):
    """A command-line flag or argument is malformed: the command exits 2 with this one line."""


class SchedulerProbeError(ValueError):
    """No Dask scheduler answered at an address (:func:`prsa_ctrl.studies.daskprobe.probe_scheduler`):
    "cannot connect (...)", "no answer (...)" or "not a Dask scheduler (...)", in one line, without
    the address (the caller names it as the user typed it)."""


class NoStabilisingGains(ValueError):
    """The tuner found no gains of the asked structure that stabilise the loop (or none that
    also meet the bounds); the message says which and what to relax. ``prsa-pid`` tries the
    reverse-acting plant on this type (was: on the message's first words)."""
