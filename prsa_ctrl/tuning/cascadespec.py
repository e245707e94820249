"""The numbers a cascade is tuned for (:class:`CascadeSpec`): what the linear cascade model and its
tuners (:mod:`prsa_ctrl.tuning.cascade`) use of a move, and nothing else.

A move scene is a studies-level object (:class:`~prsa_ctrl.studies.movescene.MoveScene`); it
builds its spec once (:meth:`~prsa_ctrl.studies.movescene.MoveScene.cascade_spec`) and the
tuning layer reads numbers, a motion profile and the drive's filters only.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..drive.filters import LoopFilter
from ..drive.motion import MotionProfile
from ..options import MS_MAX_DEFAULT

__all__ = ["CascadeSpec"]


@dataclass(frozen=True)
class CascadeSpec:
    """What the cascade model and its tuners use of a move (SI units).

    Attributes
    ----------
    origin : str
        Where the numbers come from (a scene file), as messages name it.
    motion : MotionProfile
        The move, m of screw travel, from its start (:mod:`prsa_ctrl.drive.motion`).
    cruise_speed_m_s : float, m/s
        The speed the cascade is linearised at, signed as the move (the distance's sign).
    initial_load_n, load_n : float, N
        Load at the start, and the load from ``load_at_s`` on (the linearisation load).
    load_at_s : float, s
        When ``load_n`` appears.
    hold_step_n : float, N
        The load step while holding (0: none; the tuning then steps ``max(|load_n|, 100 N)``).
    measured : {"nut_angle", "screw_position"}
        What the position loop measures.
    position_rate : int
        Position-loop sample time in speed-loop samples.
    position_delay_samples : int
        The position loop's computation delay, in position-loop samples.
    fidelity : {"rigid", "compliant"}
        The linearised model.
    ms_max : float
        Bound on the peak sensitivity at every loop-breaking point.
    position_controller : {"p", "pi"}
    weight_following, weight_holding : float
        Weights of the two parts of the joint tuning's objective.
    bandwidth_ratio : float or None
        Smallest ratio of the speed loop's to the position loop's bandwidth.
    kv_max_per_s : float or None, 1/s
        Ceiling on the position gain.
    filters : tuple of LoopFilter
        The drive's fixed speed-measurement and torque-command filters.
    """

    origin: str
    motion: MotionProfile
    cruise_speed_m_s: float
    load_at_s: float
    initial_load_n: float = 0.0
    load_n: float = 0.0
    hold_step_n: float = 0.0
    measured: str = "nut_angle"
    position_rate: int = 1
    position_delay_samples: int = 0
    fidelity: str = "compliant"
    ms_max: float = MS_MAX_DEFAULT
    position_controller: str = "p"
    weight_following: float = 1.0
    weight_holding: float = 1.0
    bandwidth_ratio: float | None = None
    kv_max_per_s: float | None = None
    filters: tuple[LoopFilter, ...] = ()
