"""Retune the EMPS position/velocity cascade on the fitted plant and compare it with the gains that
ran (kp 160.18 1/s, kv 243.45 V/(m/s)) at equal robustness.

    python examples/emps/tune_compare.py [FITTED.toml] [PATH/DATA_EMPS.mat]

Robustness: the peak of the sensitivity ``|S| = |1/(1 + L)|`` with the loop broken at the drive
input, ``L(z) = kv (kp + D(z)) P(z)``: ``P`` the fitted axis linearised (mass and the mean of the
two viscous coefficients; Coulomb friction has no linear part) behind a zero-order hold,
``D(z) = (1 - z^-2) / (2 dt)`` the controller's velocity estimate (two-sample average, then a
difference). Performance: the RMS following error ``qg - q`` predicted by replaying the logged
reference through the fitted nonlinear plant in closed loop. A grid of (kp, kv) is searched for
the smallest predicted error with ``Ms`` no larger than the running gains' and the controller
output within its +-10 V.
"""

import sys
from pathlib import Path

import numpy as np

from prsa_ctrl.identification.axis import fit_linear_axis, load_axis_plant, simulate_axis
from prsa_ctrl.identification.logformat import load_axis_log, load_log_format

HERE = Path(__file__).resolve().parent


def loop_numbers(kp, kv, mass, viscous, gain, h, w):
    """Ms, gain margin (dB) and phase margin (deg) of the linear loop, and its stability."""
    import control

    P = control.c2d(control.tf([gain], [mass, viscous, 0.0]), h, "zoh")
    z = control.tf([1.0, 0.0], [1.0], h)
    D = (1 - z ** -2) / (2 * h)
    L = kv * (kp + D) * P
    resp = L(np.exp(1j * w * h))
    ms = float(np.max(np.abs(1.0 / (1.0 + resp))))
    poles = control.poles(control.feedback(L, 1))
    stable = bool(np.all(np.abs(poles) < 1.0))
    mag, ph = np.abs(resp), np.unwrap(np.angle(resp))
    # gain margin: smallest 1/|L| where the phase crosses -180 deg (mod 360); phase margin at |L| = 1
    k180 = np.flatnonzero(np.diff(np.floor((ph + np.pi) / (2 * np.pi))) != 0)
    gm_db = min((-20 * np.log10(mag[k]) for k in k180), default=np.inf)
    k1 = np.flatnonzero((mag[:-1] >= 1) & (mag[1:] < 1))
    pm = min((np.degrees(ph[k]) + 360.0) % 360.0 - 180.0 for k in k1) if k1.size else np.inf  # 180 + phase, wrapped
    return ms, gm_db, pm, stable


def following(theta, log, kp, kv):
    """RMS and peak following error (m) and peak controller output (V) of the closed-loop replay."""
    import dataclasses

    alt = dataclasses.replace(log, controller=dataclasses.replace(log.controller, kp=kp, kv=kv,
                                                                  saturation=1e9))
    tr = simulate_axis(theta, alt, x0=(float(log.position_m[0]), 0.0))
    e = log.reference_m - tr.position_m
    return float(np.sqrt(np.mean(e ** 2))), float(np.max(np.abs(e))), float(np.max(np.abs(tr.command)))


def main() -> None:
    data = sys.argv[2] if len(sys.argv) > 2 else str(HERE / "DATA_EMPS.mat")
    log = load_axis_log(data, load_log_format(HERE / "log.toml"))
    if len(sys.argv) > 1:
        plant = load_axis_plant(sys.argv[1])
    else:
        plant = fit_linear_axis([log], load_axis_plant(HERE / "plant.toml")).plant
    v = plant.values
    mass = v["axis.mass_kg"]
    viscous = 0.5 * (v["friction.viscous_positive_n_s_per_m"] + v["friction.viscous_negative_n_s_per_m"])
    gain, h = log.gain_n_per_unit, log.sample_time_s
    w = np.geomspace(0.1, np.pi / h * 0.999, 3000)
    kp0, kv0 = log.controller.kp, log.controller.kv
    ms0, gm0, pm0, st0 = loop_numbers(kp0, kv0, mass, viscous, gain, h, w)
    rms0, peak0, u0 = following(plant.theta, log, kp0, kv0)
    e_meas = log.reference_m - log.position_m
    print(f"running gains kp {kp0:g} 1/s, kv {kv0:g} V/(m/s): Ms {ms0:.3f}, GM {gm0:.2f} dB, PM {pm0:.1f} deg; "
          f"predicted following error RMS {1e6 * rms0:.1f} um (measured {1e6 * np.sqrt(np.mean(e_meas ** 2)):.1f} um), "
          f"peak {1e6 * peak0:.0f} um (measured {1e6 * np.max(np.abs(e_meas)):.0f} um), peak command {u0:.2f} V")
    best = None
    for kp in np.geomspace(kp0 / 2, kp0 * 4, 13):
        for kv in np.geomspace(kv0 / 2, kv0 * 4, 13):
            ms, gm, pm, st = loop_numbers(kp, kv, mass, viscous, gain, h, w)
            if not st or ms > ms0 * (1 + 1e-6):
                continue
            rms, peak, u = following(plant.theta, log, kp, kv)
            if u > log.controller.saturation:
                continue
            if best is None or rms < best[0]:
                best = (rms, peak, u, kp, kv, ms, gm, pm)
    rms, peak, u, kp, kv, ms, gm, pm = best
    print(f"retuned at Ms <= {ms0:.3f}: kp {kp:.4g} 1/s, kv {kv:.4g} V/(m/s): Ms {ms:.3f}, GM {gm:.2f} dB, "
          f"PM {pm:.1f} deg; predicted following error RMS {1e6 * rms:.1f} um ({100 * (rms / rms0 - 1):+.0f} %), "
          f"peak {1e6 * peak:.0f} um, peak command {u:.2f} V")


if __name__ == "__main__":
    main()
