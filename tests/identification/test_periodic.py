"""identification/periodic: a replay residual's peak told apart as a torque periodic in the motor
angle (cogging) or a mode, and the screw path's diagnosis naming the former with its cycles per
revolution (gen_third's ball logs named their 6-per-revolution cogging at 25 rad/s a 23.4 Hz
'second mass')."""

from __future__ import annotations

import math

import numpy as np
import pytest

from prsa_ctrl.identification.periodic import periodic_or_mode
from prsa_ctrl.identification.validation import diagnosis

TS = 2.5e-4


def _entry(speed, residual_of, seed=0, noise=0.05):
    """A replay entry (the fields the diagnosis reads) whose residual is ``residual_of(t, theta)``
    (rad/s) plus white noise, at the motor speed ``speed`` (rad/s per sample)."""
    rng = np.random.default_rng(seed)
    t = TS * np.arange(1, len(speed) + 1)
    theta = np.cumsum(speed) * TS
    res = residual_of(t, theta) + noise * rng.standard_normal(len(t))
    return {"finite": True, "time_s": t, "measured": speed, "model": speed - res, "skip_samples": 80,
            "fit_percent": 70.0, "error_rms_rad_s": float(np.std(res)), "noise_floor_rad_s": 0.01}


def _varying(n=6000):  # load steps: 25 rad/s, +-1 rad/s as the loop rides them
    t = TS * np.arange(1, n + 1)
    return 25.0 + 1.0 * np.sin(2 * math.pi * 0.5 * t)


def _cogging(t, theta):
    return 0.3 * np.sin(6.0 * theta + 0.7)


def _mode(t, theta):
    return 0.3 * np.sin(2 * math.pi * 121.0 * t)


def test_a_torque_periodic_in_the_angle_is_not_a_mode():
    e = _entry(_varying(), _cogging)
    pm = periodic_or_mode(e, 6 * 25.0 / (2 * math.pi))
    assert pm["verdict"] == "periodic"
    assert pm["cycles_per_rev"] == pytest.approx(6.0, abs=0.03)
    assert pm["angle_share"] > pm["time_share"]


def test_a_mode_is_not_periodic_in_the_angle():
    e = _entry(_varying(), _mode)
    assert periodic_or_mode(e, 121.0)["verdict"] == "mode"
    # a staircase (10, 20, 30 rad/s): the mode's frequency stays, its cycles per revolution do not
    stairs = np.repeat([10.0, 20.0, 30.0], 2500)
    assert periodic_or_mode(_entry(stairs, _mode), 121.0)["verdict"] == "mode"
    pm = periodic_or_mode(_entry(stairs, _cogging), 6 * 20.0 / (2 * math.pi))
    assert pm["verdict"] == "periodic"
    assert pm["cycles_per_rev"] == pytest.approx(6.0, abs=0.03)


def test_a_constant_speed_cannot_tell_and_says_so():
    e = _entry(np.full(6000, 25.0), _cogging)
    assert periodic_or_mode(e, 6 * 25.0 / (2 * math.pi))["verdict"] == "undecided"


def test_too_little_motion_is_no_verdict():
    assert periodic_or_mode(_entry(np.full(600, 25.0), _cogging), 23.9) is None
    assert periodic_or_mode(_entry(np.zeros(6000), _cogging), 23.9) is None


def test_diagnosis_names_the_cogging_and_the_mode_of_another_log():
    class _R:  # the parts of a FitResult the diagnosis reads
        keys = ("axis.motor_inertia_kg_m2",)
        not_identified = {}

    cog = _entry(_varying(), _cogging)
    written = {"loadsteps": cog, "multisine": _entry(_varying(), _mode, seed=1)}
    d = diagnosis({"loadsteps": cog}, {"decided": True}, _R())
    assert d.startswith("position-periodic torque")
    assert "6.00 cycles per revolution" in d
    # with a mode in another log's residual, both are named, the larger share first
    d = diagnosis(written, {"decided": True}, _R())
    assert d.startswith("second mass")
    assert "121" in d.split(";")[0]
    assert "besides, position-periodic torque" in d
    assert "loadsteps" in d.split("besides")[1]
    # the mode alone is still a second mass
    assert diagnosis({"multisine": written["multisine"]}, {"decided": True}, _R()).startswith("second mass")
