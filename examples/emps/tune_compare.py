"""Retune the EMPS position/velocity cascade on the fitted plant with the toolkit's tuner and compare
it with the gains that ran (kp 160.18 1/s, kv 243.45 V/(m/s)) at equal robustness.

    python examples/emps/tune_compare.py [FITTED.toml] [PATH/DATA_EMPS.mat]

The controller of the log (position P over velocity P, the two-sample averaged velocity estimate,
1 ms, no command delay) is a speed PI whose integral is the position error, affine in
``(kv, kv kp)``: :func:`prsa_ctrl.studies.axistune.retune_axis` builds its loop model on the
fitted axis (linearised by the toolkit in each direction of motion, zero-order hold), and
:func:`prsa_ctrl.tuning.tune_loops` minimises the ISE of the following error over the logged
reference (Coulomb friction of the direction of motion as a load) subject to ``Ms`` no larger than
that of the gains that ran (loop broken at the drive input, both directions). Both designs are then
replayed through the fitted nonlinear plant in closed loop on the logged trajectory.
"""

import sys
from pathlib import Path

from prsa_ctrl.identification.axis import fit_linear_axis, load_axis_plant
from prsa_ctrl.identification.logformat import load_axis_log, load_log_format
from prsa_ctrl.studies.axistune import retune_axis

HERE = Path(__file__).resolve().parent


def main() -> None:
    data = sys.argv[2] if len(sys.argv) > 2 else str(HERE / "DATA_EMPS.mat")
    log = load_axis_log(data, load_log_format(HERE / "log.toml"))
    if len(sys.argv) > 1:
        axis = load_axis_plant(sys.argv[1])
    else:
        axis = fit_linear_axis([log], load_axis_plant(HERE / "plant.toml")).plant
    res = retune_axis(axis, log)
    print(f"measured following error of the gains that ran: RMS {1e6 * res.measured_following_rms_m:.1f} um, "
          f"peak {1e6 * res.measured_following_peak_m:.0f} um")
    for d in (res.running, res.tuned):
        print(f"{d.label:>15}: kp {d.gains.kp:8.2f} 1/s, kv {d.gains.kv:8.2f} V/(m/s): Ms {d.ms:.4f}, "
              f"GM {d.gain_margin_db:.2f} dB, PM {d.phase_margin_deg:.1f} deg; predicted following error RMS "
              f"{1e6 * d.following_rms_m:.1f} um, peak {1e6 * d.following_peak_m:.0f} um; peak command "
              f"{d.command_peak:.2f} V (saturation {res.saturation:g} V)")
    print(f"change: following error RMS {100 * (res.tuned.following_rms_m / res.running.following_rms_m - 1):+.1f} %, "
          f"peak {100 * (res.tuned.following_peak_m / res.running.following_peak_m - 1):+.1f} %; "
          f"tuner: {res.tuning.status}; status: {res.status}")
    for w in res.warnings:
        print(f"warning: {w}")


if __name__ == "__main__":
    main()
