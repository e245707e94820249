"""The one sampled-loop builder (``drive_loop``) with its pluggable measurement blocks, checked
against the drive's per-sample law written out by hand (``tests/tuning/hand_loop.py``, plain
NumPy, no builder code)."""

import numpy as np
import pytest

from hand_loop import A, ANGLE, B, C_SPEED, GAINS, SPEED_BQ, STEP, TF, TORQUE_BQ, TS, HandLoop  # tests/tuning on sys.path
from hand_loop import toy_kf as _kf
from prsa_ctrl.tuning.builders import drive_loop
from prsa_ctrl.tuning.loopmeasure import EncoderDifference, KalmanEstimate


def _kf_loop(n_delay: int, feedforward: bool = True, **kw):
    return drive_loop(A, B, C_SPEED, ANGLE, ts=TS, tf=TF, horizon=0.02, step=STEP,
                      filters=(("speed_measurement", SPEED_BQ), ("torque_command", TORQUE_BQ)),
                      command_delay_samples=n_delay, measurement=KalmanEstimate(_kf(), feedforward), **kw)


@pytest.mark.parametrize("n_delay", [0, 2])
def test_kf_loop_with_filters_and_delay_follows_the_hand_written_law_in_time(n_delay):
    lp = _kf_loop(n_delay)
    assert lp.stability(GAINS) == "stable"
    hand = HandLoop(_kf(), GAINS, n_delay)
    s = np.zeros(hand.size)
    speed = []
    for _ in range(lp.n_steps):
        speed.append(s[0])
        s = hand.step(s, STEP, 0.0)
    err = lp.error(GAINS)
    scale = np.max(np.abs(speed))
    assert scale > 1e-3  # the step moves the speed
    np.testing.assert_allclose(err, -np.asarray(speed), rtol=0, atol=1e-9 * scale)


@pytest.mark.parametrize("n_delay", [0, 2])
def test_kf_loop_poles_are_the_hand_written_loops_poles(n_delay):
    lp = _kf_loop(n_delay)
    a_hand = HandLoop(_kf(), GAINS, n_delay).matrices()[0]
    lam_h = np.linalg.eigvals(a_hand)
    drift = np.argmin(np.abs(lam_h - 1.0))  # the angle and its estimate drifting together
    assert abs(lam_h[drift] - 1.0) < 1e-9
    lam_h = np.delete(lam_h, drift)
    lam_m = lp.poles(GAINS)
    # (the hand loop also stores the previous measured speed, which the model reads from the
    # speed biquad's memory: one more pole at 0)
    assert np.sum(np.abs(lam_m) > 0.1) == np.sum(np.abs(lam_h) > 0.1) >= 8
    for x, y in ((lam_h, lam_m), (lam_m, lam_h)):  # the well-separated poles match both ways
        for lam in x[np.abs(x) > 0.1]:
            assert np.min(np.abs(y - lam)) < 1e-7, lam


@pytest.mark.parametrize("n_delay", [0, 2])
def test_kf_loop_sensitivity_is_the_hand_written_loops_at_the_plant_input(n_delay):
    """``S = 1/(1 + L)`` of the model against the hand loop's transfer from a disturbance added
    to the plant's input to that input, ``1 + c (zI - A)^-1 b_d``."""
    lp = _kf_loop(n_delay)
    hand = HandLoop(_kf(), GAINS, n_delay)
    w = np.array([5.0, 60.0, 700.0, 3000.0, 9000.0])  # rad/s, below Nyquist (12566)
    s_hand = hand.sensitivity(w)
    s_model = 1.0 / (1.0 + lp.loop_response(GAINS, w))
    np.testing.assert_allclose(s_model, s_hand, rtol=1e-8)


def test_kf_loop_without_feedforward_has_three_gains_and_ignores_kff():
    lp = _kf_loop(1, feedforward=False)
    assert lp.n_gains == 3
    hand = HandLoop(_kf(), GAINS[:3] + (0.0,), 1)
    s, speed = np.zeros(hand.size), []
    for _ in range(lp.n_steps):
        speed.append(s[0])
        s = hand.step(s, STEP, 0.0)
    np.testing.assert_allclose(lp.error(GAINS[:3]), -np.asarray(speed), rtol=0, atol=1e-9 * np.max(np.abs(speed)))


def test_kf_duty_cycle_loop_follows_the_hand_written_law():
    """A load profile (mean load per sample) and a setpoint profile with a 2-DOF weight: the
    loop's error ``r - speed`` against the hand-written law fed the same sequences."""
    n = int(round(0.02 / TS))
    k = np.arange(n)
    load = 150.0 * np.sin(2 * np.pi * k / 37.0) + 80.0 * (k > 20)  # N
    ref = np.concatenate([[0.0], 3.0 * (np.arange(1, n + 1) > 10) - 1.5 * (np.arange(1, n + 1) > 50)])  # rad/s
    lp = drive_loop(A, B, C_SPEED, ANGLE, ts=TS, tf=TF, horizon=0.02, load_sequence=load, setpoint_sequence=ref,
                    setpoint_weight=0.6, filters=(("speed_measurement", SPEED_BQ), ("torque_command", TORQUE_BQ)),
                    command_delay_samples=1, measurement=KalmanEstimate(_kf(), True))
    hand = HandLoop(_kf(), GAINS, 1, weight=0.6)
    s, err = np.zeros(hand.size), []
    for j in range(n):
        err.append(ref[j] - s[0])
        s = hand.step(s, load[j], 0.0, ref[j])
    np.testing.assert_allclose(lp.error(GAINS), err, rtol=0, atol=1e-9 * np.max(np.abs(err)))


def test_the_command_delay_changes_the_kf_loop():
    e0, e2 = _kf_loop(0).error(GAINS), _kf_loop(2).error(GAINS)
    assert np.max(np.abs(e0 - e2)) > 1e-3 * np.max(np.abs(e0))


def test_drive_loop_takes_one_measurement():
    with pytest.raises(ValueError, match="speed_filter = 0.001 with measurement KalmanEstimate"):
        _kf_loop(0, speed_filter=1e-3)
    with pytest.raises(ValueError, match="speed_filter = None; expected"):
        drive_loop(A, B, C_SPEED, ANGLE, ts=TS, tf=TF, horizon=0.02, step=STEP)
    with pytest.raises(ValueError, match="measurement = 'kf'; expected a LoopMeasurement"):
        drive_loop(A, B, C_SPEED, ANGLE, ts=TS, tf=TF, horizon=0.02, step=STEP, measurement="kf")


def test_kalman_block_refuses_a_filter_designed_at_another_sample_time():
    kf = _kf()
    with pytest.raises(ValueError, match="Kalman filter designed at ts = 0.00025 s; expected the loop's sample time"):
        drive_loop(A, B, C_SPEED, ANGLE, ts=2 * TS, tf=TF, horizon=0.02, step=STEP, measurement=KalmanEstimate(kf))


def test_blocks_refuse_what_they_cannot_use():
    with pytest.raises(ValueError, match="kf = 'kf'; expected a KFDesign"):
        KalmanEstimate("kf")
    with pytest.raises(ValueError, match="feedforward = 1; expected True or False"):
        KalmanEstimate(_kf(), 1)
    with pytest.raises(ValueError, match="speed_filter_s = -0.001; expected a positive finite time constant"):
        EncoderDifference(-1e-3)


def test_encoder_block_is_the_default_measurement():
    plain = drive_loop(A, B, C_SPEED, ANGLE, ts=TS, speed_filter=1e-3, tf=TF, horizon=0.02, step=STEP)
    block = drive_loop(A, B, C_SPEED, ANGLE, ts=TS, tf=TF, horizon=0.02, step=STEP,
                       measurement=EncoderDifference(1e-3))
    np.testing.assert_array_equal(plain.A0, block.A0)
    np.testing.assert_array_equal(plain.L, block.L)
