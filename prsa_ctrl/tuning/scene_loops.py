"""Deprecated alias of :mod:`prsa_ctrl.tuning.actuatorloops` (the actuator's loop models from
numbers; renamed so that it no longer differs from :mod:`prsa_ctrl.studies.sceneloops`, the scene
read once, by an underscore). Import from ``prsa_ctrl.tuning`` or ``prsa_ctrl.tuning.actuatorloops``;
every name read here warns (``DeprecationWarning``)."""

from __future__ import annotations

import warnings
from typing import Any

__all__ = ["step_loops", "profile_loops", "derivative_filter_s", "kf_drive_loop"]


def __getattr__(name: str) -> Any:
    if name not in __all__:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    warnings.warn(f"prsa_ctrl.tuning.scene_loops is deprecated; import {name} from prsa_ctrl.tuning.actuatorloops "
                  "(or prsa_ctrl.tuning)", DeprecationWarning, stacklevel=2)
    from . import actuatorloops

    return getattr(actuatorloops, name)
