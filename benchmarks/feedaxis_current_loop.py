"""Is the foreign feed axis's current loop in its logs? (issue 32; not a test: an analysis with
its numbers, run ``python benchmarks/feedaxis_current_loop.py`` from a checkout, ~2 min.)

On the generator's own physics (``tests/identification/foreign/gen_feedaxis_load.py``: two
masses, 110 Hz axial mode, 800 Hz first-order current loop, 4 kHz, seed 0), each log is replayed
open loop from its applied command on 0.1 s segments (the fit's default), each segment's free
initial state (angle, speed, torque lag) projected out. Per log it prints the angle's
sensitivity to ln f_c, the noise's (torque noise through the plant, encoder noise and
quantisation) and the standard deviation of the least-squares estimate of ln f_c from the
noise alone over 20 draws, alone and with the inertia fitted too; then, on the multisine, the
rigid model's misfit of the mode against the current loop's signature.

Measured (01:40 UTC 2026-11-28): with the true structure, the inertia free and the delay
given, the multisine sets f_c to +-7.7 % (95 %), the staircase to +-17 %, the load steps to
+-48 %: the current loop *is* in the logs. The rigid model's misfit of the mode on the
multisine is 0.0205 rad RMS, 127 x the 1.6e-4 rad a +25 % current loop moves the angle, and its
projection on that direction is -2.2 in ln f_c: a rigid fit's bandwidth is set by the mode it
lacks, hence 'not identified' (prsa_ctrl.identification.validation's second-mass diagnosis
says so with the loop's lag at the resonance).
"""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "identification"))
from foreign import _axis  # noqa: E402
from foreign import gen_feedaxis_load as fa  # noqa: E402

SEG_S = 0.1
AX, DRV, SEN = fa.AXIS, fa.DRIVE, fa.SENSORS
TS = DRV.sample_time_s
NSEG = int(round(SEG_S / TS))


def replay(run, fc, y0, noise=None, ax=AX):
    """Open-loop angle (rad per sample) of ``ax`` from the applied command (acting n_t samples later)."""
    wc, h, nt = 2 * math.pi * fc, TS / DRV.n_sub, DRV.transport_delay_samples
    u, fe = run.command_applied, run.force_true
    out, y = np.empty(u.size), y0
    for k in range(u.size):
        out[k] = y[0]
        te_in = u[k - nt] if k >= nt else u[0]
        d = 0.0 if noise is None else noise[k]
        for _ in range(DRV.n_sub):
            y = _axis._rk4(lambda yy, *a: _axis._deriv_two_mass(ax, wc, yy, *a), y, h, te_in, d, fe[k])
    return out


def segments(x, fc):
    """``x`` per segment, less its least-squares fit of the free initial state's responses."""
    t = np.arange(NSEG) * TS
    a = np.column_stack([np.ones_like(t), t, 1 - np.exp(-2 * math.pi * fc * t)])
    out = []
    for k0 in range(0, x.size - NSEG + 1, NSEG):
        seg = x[k0:k0 + NSEG]
        out.append(seg - a @ np.linalg.lstsq(a, seg, rcond=None)[0])
    return np.concatenate(out)


def start(run, ax=AX):
    w0 = float(run.speed_true[0])
    t0 = _axis.steady_torque(ax, w0, run.force_true[0]) if w0 != 0 else 0.0
    fs0 = run.force_true[0] if w0 != 0 else 0.0
    return (0.0, w0, -fs0 / ax.stiffness_n_per_m, ax.a * w0, t0)


def main() -> None:
    runs = fa.simulate_all(0)
    rng = np.random.default_rng(123)
    q = 2 * math.pi / SEN.counts_per_rev
    fc0 = DRV.current_loop_hz
    heavier = dataclasses.replace(AX, motor_side_inertia_kg_m2=AX.motor_side_inertia_kg_m2 * 1.05,
                                  load_mass_kg=AX.load_mass_kg * 1.05)
    for name in ("multisine", "loadsteps", "staircase"):
        run = runs[name]
        y0 = start(run)
        base = replay(run, fc0, y0)
        s_fc = (segments(replay(run, 1.25 * fc0, y0), fc0) - segments(base, fc0)) / math.log(1.25)
        s_j = (segments(replay(run, fc0, y0, ax=heavier), fc0) - segments(base, fc0)) / math.log(1.05)
        reg = np.column_stack([s_fc, s_j])
        one, two = [], []
        for _ in range(20):
            noisy = replay(run, fc0, y0, noise=rng.standard_normal(run.time.size) * DRV.torque_noise_n_m)
            enc = rng.standard_normal(run.time.size) * SEN.angle_noise_rad + (rng.random(run.time.size) - 0.5) * q
            e = segments(noisy - base, fc0) + segments(enc, fc0)
            one.append(float(s_fc @ e) / float(s_fc @ s_fc))
            two.append(np.linalg.lstsq(reg, e, rcond=None)[0][0])
        sd1, sd2 = float(np.std(one, ddof=1)), float(np.std(two, ddof=1))
        print(f"{name:10s} d theta/d ln f_c RMS {math.sqrt(np.mean(s_fc ** 2)):.3g} rad, noise RMS "
              f"{math.sqrt(np.mean(e ** 2)):.3g} rad: f_c to +-{100 * (math.exp(1.96 * sd1) - 1):.1f} % (95 %) alone, "
              f"+-{100 * (math.exp(1.96 * sd2) - 1):.1f} % with the inertia fitted too")
    run = runs["multisine"]
    stiff = dataclasses.replace(AX, stiffness_n_per_m=AX.stiffness_n_per_m * 100, damping_n_s_per_m=AX.damping_n_s_per_m * 10)
    base = segments(replay(run, fc0, start(run)), fc0)
    mis = segments(replay(run, fc0, start(run, stiff), ax=stiff), fc0) - base
    d = segments(replay(run, 1.25 * fc0, start(run)), fc0) - base
    print(f"multisine: rigid-model misfit of the mode RMS {math.sqrt(np.mean(mis ** 2)):.3g} rad against "
          f"{math.sqrt(np.mean(d ** 2)):.3g} rad for +25 % f_c; its projection on that direction "
          f"{float(mis @ d) / float(d @ d) * math.log(1.25):+.3g} in ln f_c")


if __name__ == "__main__":
    main()
