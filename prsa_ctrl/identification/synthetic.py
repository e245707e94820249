"""A simulated calibration record with a known truth: the paper plant perturbed to
:data:`FIT_TRUTH`, run in the sampled speed loop and measured as a drive logs it
(:func:`fit_record`); the fit's test case and benchmark (``python benchmarks/bench.py``)."""

from __future__ import annotations

import math

import numpy as np

from ..drive.pid import PID
from ..plant.plantfile import load_plant
from ..sim.engine import run
from .data import design_excitation, record_from_arrays

__all__ = ["FIT_TRUTH", "fit_record"]


#: Issue 11's perturbed plant (inertia -25 %, efficiency 0.88, no-load 0.03 N m, viscous
#: 1.5e-4 N m s/rad, current loop 1200 Hz), the truth of the fit benchmark.
FIT_TRUTH = {"nut.inertia_kg_m2": 1.5e-4, "friction.efficiency": 0.88, "friction.no_load_torque_n_m": 0.03,
             "friction.viscous_n_m_s_per_rad": 1.5e-4, "drive.current_loop_bandwidth_hz": 1200.0}


def fit_record(duration_s: float = 4.0, seed: int = 0):
    """The fit's test record: a closed-loop run of the toolkit's simulator on the plant
    :data:`FIT_TRUTH`, sampled at 4 kHz.

    Multisine speed setpoint 30 +- 20 rad/s (2..150 Hz, 2.5 ms steps), PI speed loop
    (Kp 0.05 N m s/rad, Ki 2 N m/rad), axial load steps every 0.5 s (200, 1500, 300, 2500 N in
    turn), nut angle through the 20-bit encoder with 1e-5 rad of Gaussian interpolation noise
    before quantisation.

    Parameters
    ----------
    duration_s : float, s
        Record length.
    seed : int
        Seed of the multisine phases and of the angle noise.

    Returns
    -------
    (Record, Plant)
        The record and the true plant.
    """
    truth = load_plant().with_params(FIT_TRUTH)
    t, v = design_excitation("multisine", duration_s=duration_s, sample_time_s=2.5e-3, f_min_hz=2, f_max_hz=150,
                             amplitude=20, offset=30, seed=seed)
    load = [(0.5 * k, (200.0, 1500.0, 300.0, 2500.0)[k % 4]) for k in range(int(math.ceil(duration_s / 0.5)))]
    r = run(truth, setpoint=list(zip(t.tolist(), v.tolist())), load=load, duration=duration_s,
            controller=PID(0.05, 2.0), fidelity="rigid", discrete=True)
    theta = r.states[r.state_labels.index("theta_nut")]
    q = 2 * math.pi / truth.encoder_counts
    noise = 1e-5 * np.random.default_rng(seed).standard_normal(theta.shape)
    angle = np.floor((theta + noise) / q) * q
    rec = record_from_arrays(f"sim-{duration_s:g}s", r.time, r.output("torque_command"), nut_angle_rad=angle,
                             axial_load_n=r.inputs[1])
    return rec, truth
