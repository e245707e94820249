"""Deprecated alias of :mod:`prsa_ctrl.tuning.actuatorloops` (the actuator's loop models from
numbers; renamed so that it no longer differs from :mod:`prsa_ctrl.studies.sceneloops`, the scene
read once, by an underscore). Import from ``prsa_ctrl.tuning`` or ``prsa_ctrl.tuning.actuatorloops``."""

from .actuatorloops import derivative_filter_s, kf_drive_loop, profile_loops, step_loops

__all__ = ["step_loops", "profile_loops", "derivative_filter_s", "kf_drive_loop"]
