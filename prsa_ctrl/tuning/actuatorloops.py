"""Loop models of the actuator's speed loop from numbers: the sampled (or continuous) loop
linearised at each load step's mid load (:func:`step_loops`), or over each record of a duty
cycle (:func:`profile_loops`). Every sampled loop is built by the one builder
:func:`~prsa_ctrl.tuning.builders.drive_loop`; the Kalman filter is its measurement block
(:class:`~prsa_ctrl.tuning.loopmeasure.KalmanEstimate`; :func:`kf_drive_loop` is that call).

The builders take numbers and arrays only; a scene is read in :mod:`prsa_ctrl.studies.sceneloops`
(:func:`~prsa_ctrl.studies.sceneloops.loop_spec`, :func:`~prsa_ctrl.studies.sceneloops.actuator_loops`).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from .._lazy import module
from ..drive.estimator import KFDesign, design_kf
from ..options import DERIVATIVE_FILTER_SAMPLES
from ..plant.linear import linear_core
from ..plant.model import plant_model
from ..plant.plantfile import Plant
from .loops import LoopModel
from .builders import continuous_loop, drive_loop
from .loopmeasure import KalmanEstimate

__all__ = ["step_loops", "profile_loops", "derivative_filter_s", "kf_drive_loop"]

control = module("control")


def derivative_filter_s(plant: Plant) -> float:
    """Derivative-filter time constant of the tuned PID, s (``DERIVATIVE_FILTER_SAMPLES``
    controller samples)."""
    return DERIVATIVE_FILTER_SAMPLES * plant.sample_time_s


def step_loops(plant: Plant, *, setpoint_rad_s: float, initial_load_n: float, final_loads_n: Sequence[float],
               fidelity: str, horizon_s: float, discrete: bool = True, kf_load_change_time_s: float | None = None,
               feedforward: bool = False, filters: Sequence = ()) -> list[LoopModel]:
    """One loop model per final load, linearised at the mid load of the step (the response
    to a step is the same from any linearisation point; the mid load keeps the Jacobians
    closest to both ends).

    Parameters
    ----------
    plant : Plant
    setpoint_rad_s : float, rad/s
        Nut-speed setpoint (the linearisation speed).
    initial_load_n : float, N
        Axial load before the step.
    final_loads_n : sequence of float, N
        Axial load after each step; one loop per value.
    fidelity : str
        Fidelity of the linearised plant model.
    horizon_s : float, s
        Horizon of the objective after the step.
    discrete : bool
        The sampled drive loop (default) or the continuous controller.
    kf_load_change_time_s : float, s, optional
        With a value: the speed is measured by the Kalman filter designed for this load-change
        time scale (:func:`prsa_ctrl.drive.estimator.design_kf`; sampled loops only).
    feedforward : bool
        With the Kalman filter: tune the load feed-forward gain as a fourth gain.
    filters : sequence of LoopFilter
        The drive's speed-measurement and torque-command filters (sampled loops, with the
        encoder's difference or the Kalman filter; :func:`prsa_ctrl.tuning.builders.drive_loop`).

    Returns
    -------
    list of LoopModel
    """
    kf = None
    if filters and not discrete:
        raise ValueError("filters: expected a sampled loop (the continuous loop has no loop filters)")
    if kf_load_change_time_s is not None:
        if not discrete:
            raise ValueError("kf_load_change_time_s with discrete = False; expected a sampled loop (the Kalman "
                             "filter runs at the sample time)")
        kf = design_kf(plant, kf_load_change_time_s)
    model = plant_model(plant, fidelity)
    i_speed = model.output_names.index("nut_speed")
    i_torque = model.output_names.index("motor_torque")
    horizon = horizon_s
    # The plant linearised at every step's mid load, then the loop models.
    cores = [linear_core(plant, setpoint_rad_s, 0.5 * (initial_load_n + f1), fidelity)[:3] for f1 in final_loads_n]
    loops = []
    for f1, (a, b, c) in zip(final_loads_n, cores):
        step = f1 - initial_load_n
        if discrete:  # the one sampled builder; the Kalman filter is its measurement block
            meas = {"speed_filter": plant.speed_filter_s} if kf is None else \
                {"measurement": KalmanEstimate(kf, feedforward)}
            loops.append(
                drive_loop(
                    a, b, c[i_speed], model.index("theta_nut"),
                    ts=plant.sample_time_s, tf=derivative_filter_s(plant),
                    horizon=horizon, step=step, name=f"step to {f1:g} N" + (" (KF)" if kf is not None else ""),
                    outputs={"nut_speed": c[i_speed], "motor_torque": c[i_torque]}, filters=filters,
                    command_delay_samples=plant.command_delay_samples, **meas,
                )
            )
        else:
            t_f = plant.speed_filter_s
            # The continuous controller measures speed, never the angle: the nut-angle state is
            # a pure integrator nothing depends on (its column is zero) and would leave a pole
            # at exactly 0 for every gain, so it is removed.
            i_th = model.index("theta_nut")
            if np.any(a[:, i_th] != 0) or np.any(c[:, i_th] != 0):
                raise ArithmeticError("the linearised plant depends on the absolute nut angle")
            keep = [i for i in range(a.shape[0]) if i != i_th]
            a, b, c = a[np.ix_(keep, keep)], b[keep], c[:, keep]
            n = a.shape[0]
            # Plant plus speed filter; the filtered speed is fed back.
            aa = np.block([[a, np.zeros((n, 1))], [c[i_speed][None, :] / t_f, -np.ones((1, 1)) / t_f]])
            bb = np.vstack([b, np.zeros((1, 2))])
            cc = np.concatenate([np.zeros(n), [1.0]])[None, :]
            sys = control.ss(aa, bb, cc, np.zeros((1, 2)))
            loops.append(continuous_loop(sys, tf=derivative_filter_s(plant), horizon=horizon, n_steps=int(round(horizon / 1e-4)), step=step))
    return loops


def profile_loops(plant: Plant, records: Sequence[tuple], *, fidelity: str, horizon_s: float,
                  setpoint_weight: float = 1.0, filters: Sequence = (), kf_load_change_time_s: float | None = None,
                  feedforward: bool = False) -> list[LoopModel]:
    """One sampled loop model per duty-cycle record, linearised at the middle of its range.

    Parameters
    ----------
    plant : Plant
    records : sequence of (name, w_lin, f_lin, load_sequence, setpoint_sequence)
        Per record: its name, the linearisation point (rad/s, N), the mean load deviation over
        each controller sample (N, or None) and the setpoint deviation the controller reads at
        each sample (rad/s, or None).
    fidelity : str
        Fidelity of the linearised plant model.
    horizon_s : float, s
        Length of each record.
    setpoint_weight : float
        2-DOF setpoint weight b.
    filters : sequence of LoopFilter
        The drive's speed-measurement and torque-command filters.
    kf_load_change_time_s : float, s, optional
        With a value: the speed is measured by the Kalman filter designed for this load-change
        time scale (:func:`prsa_ctrl.drive.estimator.design_kf`), the measurement block of the one
        sampled builder (:class:`~prsa_ctrl.tuning.loopmeasure.KalmanEstimate`); else the
        encoder's filtered difference.
    feedforward : bool
        With the Kalman filter: tune the load feed-forward gain as a fourth gain.

    Returns
    -------
    list of LoopModel
    """
    if kf_load_change_time_s is None:
        meas = {"speed_filter": plant.speed_filter_s}
    else:
        meas = {"measurement": KalmanEstimate(design_kf(plant, kf_load_change_time_s), feedforward)}
    model = plant_model(plant, fidelity)
    i_speed = model.output_names.index("nut_speed")
    i_torque = model.output_names.index("motor_torque")
    cores = [linear_core(plant, w_lin, f_lin, fidelity)[:3] for _, w_lin, f_lin, _, _ in records]
    loops = []
    for (name, _, _, load_sequence, setpoint_sequence), (a, b, c) in zip(records, cores):
        loops.append(drive_loop(
            a, b, c[i_speed], model.index("theta_nut"), ts=plant.sample_time_s,
            tf=derivative_filter_s(plant), horizon=horizon_s, name=name + (" (KF)" if "measurement" in meas else ""),
            outputs={"nut_speed": c[i_speed], "motor_torque": c[i_torque]},
            load_sequence=load_sequence, setpoint_sequence=setpoint_sequence,
            setpoint_weight=setpoint_weight, filters=filters, command_delay_samples=plant.command_delay_samples,
            **meas))
    return loops


def kf_drive_loop(a, b, c_speed, angle_index: int, kf: KFDesign, *, tf: float, horizon: float, step: float,
                  feedforward: bool, omega: NDArray | None = None, name: str = "drive+KF",
                  outputs: dict | None = None, filters: Sequence = (), command_delay_samples: int = 0):
    """Loop model of the sampled drive with the Kalman filter as its speed measurement: the one
    builder :func:`prsa_ctrl.tuning.builders.drive_loop` with the
    :class:`~prsa_ctrl.tuning.loopmeasure.KalmanEstimate` block (kept for its callers).

    Parameters
    ----------
    a, b : ndarray
        Continuous plant Jacobians with the nut angle kept (inputs torque command, load).
    c_speed : ndarray
        Output row of the nut speed.
    angle_index : int
        Index of the nut angle state.
    kf : KFDesign
    tf : float, s
        Derivative-filter time constant.
    horizon : float, s
    step : float, N
        Load step of the objective's disturbance.
    feedforward : bool
        Tune the load feed-forward gain ``kff`` as a fourth gain (``u += kff * load estimate``).
    omega : array, rad/s, optional
        Frequency grid (default 500 points up to the Nyquist frequency).
    name : str
    outputs : dict, optional
        Extra output rows to record along the trajectory.
    filters : sequence of LoopFilter
        Speed-measurement filters (on the estimated speed) and torque-command filters.
    command_delay_samples : int
        The drive's command delay beyond the one-sample computation delay, samples.
    """
    return drive_loop(a, b, c_speed, angle_index, ts=kf.ts, tf=tf, horizon=horizon, step=step, omega=omega,
                      name=name, outputs=outputs, filters=filters, command_delay_samples=command_delay_samples,
                      measurement=KalmanEstimate(kf, feedforward))
